"""The auto rig: a face rig (ARKit-named morph targets) for a static head.

`run(out, AutorigConfig(mesh_path=...))` is `t2bs autorig MESH -o OUT.glb` (a mesh file in, a rigged
file out, no project); `project_autorig` rigs a project's character for the video stage (cached in the
project); `rig_canonical` is what both share.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from t2bs.errors import UserError

AUTORIG_VERSION = "t2bs-autorig-4"  # bump when the deformers change what a rig holds


@dataclass
class AutorigConfig:
    """`t2bs autorig`'s settings (the deformers' own settings are t2bs.rig.autorig.AutoRigConfig)."""

    mesh_path: Path  # head mesh (glb, gltf, vrm, obj, ply) without a face rig
    landmarks: Path | None = None  # JSON with 20 vertex_ids (68-point order 36-47, 60-67), optional named ids
    facing: str = "auto"  # axis the face looks along in the file: auto, +z, -z, +x, -x
    keep: bool = False  # keep the mesh's own morph targets next to the new ones
    lid_meet: float | None = None  # where closed lids meet, 0 = lower lid .. 1 = upper lid (None: by the eye)


@dataclass
class AutorigResult:
    out: Path  # the rigged mesh (.glb, the input's frame and vertex order)
    summary_path: Path  # the .json beside it: source, facing, seconds, shapes, missing shapes and why, landmarks
    shapes: tuple[str, ...]  # the ARKit shapes made
    missing: dict  # ARKit name -> why it is missing
    landmark_source: str  # where the face's 20 points came from: file, parts, mediapipe, mediapipe + eye parts
    facing: str  # the axis the face looked along in the file (auto resolved)
    seconds: float  # time to find the face and build the rig


def rig_canonical(mesh, landmarks_file: Path | None = None, renderer=None, source_name: str = "mesh", config=None):
    """Canonical-frame mesh -> (AutoRig, seconds): find the face, build the rig."""
    from t2bs.rig.autorig import AutoRigConfig, autorig
    from t2bs.rig.face import find_face

    t0 = time.perf_counter()
    face = find_face(mesh, landmarks_file, renderer=renderer, source_name=source_name)
    rig = autorig(mesh, face, config or AutoRigConfig())
    return rig, time.perf_counter() - t0


def run(out: str | os.PathLike, config: AutorigConfig) -> AutorigResult:
    """Build a face rig on a static head mesh file: jawOpen, eyeBlinkLeft, mouthSmileLeft, ... (ARKit names).

    Reads ``config.mesh_path`` (any mesh format; vertex order and count are kept) and, when given, the
    ``landmarks`` JSON (20 vertex ids); without it the face is found from part labels or MediaPipe on a render.
    The rig is built in the canonical frame and its offsets turned back into the file's frame.

    Writes ``out`` (a .glb: the mesh with ARKit-named morph targets, each offsets [N, 3] float32; the mesh's own
    targets too with ``keep``) and ``out`` with suffix .json (source, facing, seconds, shapes, missing shapes
    and why, landmarks). Prints one summary line.

    Raises UserError when ``out`` is not a .glb, the mesh file is missing or broken, the landmarks file is
    bad, or no face is found (nothing is written then). Nothing is cached: every run rebuilds the rig (seconds).
    """
    from t2bs.geometry.io import load_mesh, save_mesh
    from t2bs.geometry.mesh import detect_facing, normalize
    from t2bs.project import write_json
    from t2bs.rig.autorig import AutoRigConfig

    out, mesh_path = Path(out), Path(config.mesh_path)
    landmarks = None if config.landmarks is None else Path(config.landmarks)
    if out.suffix.lower() != ".glb":
        raise UserError(f"-o must name a .glb file, got {out}")
    if not mesh_path.is_file():
        raise UserError(f"{mesh_path}: no such mesh file")
    if config.lid_meet is not None and not 0.0 <= config.lid_meet <= 1.0:
        raise UserError(
            f"--lid-meet must lie in [0, 1] (0 = at the lower lid, 1 = at the upper), got {config.lid_meet}"
        )
    original = load_mesh(mesh_path)
    facing = config.facing
    if facing == "auto":
        facing = "-z" if mesh_path.suffix.lower() == ".vrm" else detect_facing(original)
    canon, transform = normalize(replace(original, morph_targets={}), facing)
    rig, seconds = rig_canonical(
        canon, landmarks, source_name=str(mesh_path), config=AutoRigConfig(lid_meet=config.lid_meet)
    )
    # Offsets back to the file's frame: canonical = scale * R @ x + t, so an offset d_c is R^T d_c / scale.
    rot, scale = np.asarray(transform["rotation"]), float(transform["scale"])
    morphs = dict(original.morph_targets) if config.keep else {}
    morphs.update({n: (d.astype(np.float64) @ rot / scale).astype(np.float32) for n, d in rig.morph_targets.items()})
    out.parent.mkdir(parents=True, exist_ok=True)
    save_mesh(replace(original, morph_targets=morphs), out)
    summary = {"source": str(mesh_path), "facing": facing, "seconds": round(seconds, 3), **rig.summary()}
    summary_path = out.with_suffix(".json")
    write_json(summary_path, summary)
    print(
        f"autorig: {len(rig.morph_targets)} ARKit shapes from {rig.landmarks.source} landmarks in {seconds:.1f} s "
        f"-> {out} (missing {len(rig.missing)}: see {summary_path}); mouth: {rig.info['mouth']}"
    )
    return AutorigResult(
        out=out,
        summary_path=summary_path,
        shapes=tuple(rig.morph_targets),
        missing=dict(rig.missing),
        landmark_source=rig.landmarks.source,
        facing=facing,
        seconds=seconds,
    )


def project_autorig(project, mesh, renderer=None):
    """The character with an auto rig, for a project whose mesh has none the animator can play.

    Cached in DIR/character/autorig.glb (+ autorig.json); the user's points in DIR/landmarks/picked.json
    (the viewer's picker, or any --landmarks JSON copied there) are used when present. Returns (rigged
    mesh, summary for the manifest).
    """
    from t2bs.geometry.io import load_mesh, save_mesh
    from t2bs.project import content_key, is_done, mark_done, read_json, write_json
    from t2bs.rig.pick import picked_landmarks

    # The user's points (the viewer's picker writes them there); landmarks/landmarks.json is the
    # landmarks stage's output, which rewrites it from the auto rig after the reconstruction.
    lm_file = picked_landmarks(project)
    folder = project.path("character")
    rig_path, info_path = folder / "autorig.glb", folder / "autorig.json"
    key = content_key(project.mesh_path, *([lm_file] if lm_file else []), AUTORIG_VERSION)
    done_dir = project.path("character", "autorig")
    if is_done(done_dir, key) and rig_path.exists() and info_path.exists():
        rigged = load_mesh(rig_path)
        if rigged.num_vertices == mesh.num_vertices:
            return rigged, read_json(info_path)
    rig, seconds = rig_canonical(
        replace(mesh, morph_targets={}), lm_file, renderer=renderer, source_name=str(project.mesh_path)
    )
    rigged = replace(mesh, morph_targets=dict(rig.morph_targets))
    save_mesh(rigged, rig_path)
    summary = {"motion_source": "autorig", "seconds": round(seconds, 3), **rig.summary()}
    write_json(info_path, summary)
    mark_done(done_dir, key, seconds=round(seconds, 3))
    return rigged, summary
