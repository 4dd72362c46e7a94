"""`t2bs autorig MESH -o OUT.glb`, and the auto rig of a project's character for the video stage."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from t2bs.errors import UserError

AUTORIG_VERSION = "t2bs-autorig-3"  # bump when the deformers change what a rig holds


def rig_canonical(mesh, landmarks_file: Path | None = None, renderer=None, source_name: str = "mesh", config=None):
    """Canonical-frame mesh -> (AutoRig, seconds): find the face, build the rig."""
    from t2bs.rig.autorig import AutoRigConfig, autorig
    from t2bs.rig.face import find_face

    t0 = time.perf_counter()
    face = find_face(mesh, landmarks_file, renderer=renderer, source_name=source_name)
    rig = autorig(mesh, face, config or AutoRigConfig())
    return rig, time.perf_counter() - t0


def autorig_command(
    mesh_path: Path = typer.Argument(..., help="Head mesh (glb, gltf, vrm, obj, ply) without a face rig."),
    out: Path = typer.Option(..., "-o", "--out", help="Output .glb: the mesh with ARKit-named morph targets."),
    landmarks: Optional[Path] = typer.Option(None, "--landmarks", help="JSON with 20 vertex_ids (68-point order 36-47, 60-67), optional named ids."),
    facing: str = typer.Option("auto", help="Axis the face looks along in the file: auto, +z, -z, +x, -x."),
    keep: bool = typer.Option(False, "--keep", help="Keep the mesh's own morph targets next to the new ones."),
) -> None:
    """Build a face rig on a static head mesh in seconds: jawOpen, eyeBlinkLeft, mouthSmileLeft, ... (ARKit names)."""
    from t2bs.geometry.io import load_mesh, save_mesh
    from t2bs.geometry.mesh import detect_facing, normalize
    from t2bs.project import write_json

    if out.suffix.lower() != ".glb":
        raise UserError(f"-o must name a .glb file, got {out}")
    if not mesh_path.is_file():
        raise UserError(f"{mesh_path}: no such mesh file")
    original = load_mesh(mesh_path)
    if facing == "auto":
        facing = "-z" if mesh_path.suffix.lower() == ".vrm" else detect_facing(original)
    canon, transform = normalize(replace(original, morph_targets={}), facing)
    rig, seconds = rig_canonical(canon, landmarks, source_name=str(mesh_path))
    # Offsets back to the file's frame: canonical = scale * R @ x + t, so an offset d_c is R^T d_c / scale.
    rot, scale = np.asarray(transform["rotation"]), float(transform["scale"])
    morphs = dict(original.morph_targets) if keep else {}
    morphs.update({n: (d.astype(np.float64) @ rot / scale).astype(np.float32) for n, d in rig.morph_targets.items()})
    out.parent.mkdir(parents=True, exist_ok=True)
    save_mesh(replace(original, morph_targets=morphs), out)
    summary = {"source": str(mesh_path), "facing": facing, "seconds": round(seconds, 3), **rig.summary()}
    write_json(out.with_suffix(".json"), summary)
    print(f"autorig: {len(rig.morph_targets)} ARKit shapes from {rig.landmarks.source} landmarks in {seconds:.1f} s -> {out} "
          f"(missing {len(rig.missing)}: see {out.with_suffix('.json')}); mouth: {rig.info['mouth']}")


def project_autorig(project, mesh, renderer=None):
    """The character with an auto rig, for a project whose mesh has none the animator can play.

    Cached in DIR/character/autorig.glb (+ autorig.json); the user's points in DIR/landmarks/picked.json
    (the viewer's picker, or any --landmarks JSON copied there) are used when present. Returns (rigged
    mesh, summary for the manifest).
    """
    from t2bs.geometry.io import load_mesh, save_mesh
    from t2bs.project import content_key, is_done, mark_done, read_json, write_json
    from t2bs.rig.pick import PICKED

    # The user's points (the viewer's picker writes them there); landmarks/landmarks.json is the
    # landmarks stage's output, which rewrites it from the auto rig after the reconstruction.
    lm_file = project.path("landmarks", PICKED)
    lm_file = lm_file if lm_file.exists() else None
    folder = project.path("character")
    rig_path, info_path = folder / "autorig.glb", folder / "autorig.json"
    key = content_key(project.mesh_path, *( [lm_file] if lm_file else []), AUTORIG_VERSION)
    done_dir = project.path("character", "autorig")
    if is_done(done_dir, key) and rig_path.exists() and info_path.exists():
        rigged = load_mesh(rig_path)
        if rigged.num_vertices == mesh.num_vertices:
            return rigged, read_json(info_path)
    rig, seconds = rig_canonical(replace(mesh, morph_targets={}), lm_file, renderer=renderer, source_name=str(project.mesh_path))
    rigged = replace(mesh, morph_targets=dict(rig.morph_targets))
    save_mesh(rigged, rig_path)
    summary = {"motion_source": "autorig", "seconds": round(seconds, 3), **rig.summary()}
    write_json(info_path, summary)
    mark_done(done_dir, key, seconds=round(seconds, 3))
    return rigged, summary

