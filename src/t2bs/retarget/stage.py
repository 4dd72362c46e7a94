"""The retarget stage (`t2bs retarget DIR --driver VIDEO|IMAGES|CSV`): a human performance drives the
character's blendshape rig, as a library call."""

from __future__ import annotations

import csv
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from t2bs.errors import UserError
from t2bs.project import OutputSet, Project, project_lock, read_json, write_json
from t2bs.retarget.landmarks_stage import load_model


@dataclass
class RetargetConfig:
    driver: Path | None = None  # human face video file, folder of images, or Live Link Face .csv (required)
    out: Path | None = None  # output folder; None: DIR/retarget/<driver name>
    neutral_frame: int | None = None  # index of the driver's neutral frame; None: detected (video drivers)
    smooth: float = 1.0  # temporal smoothing of the tracked landmarks, Gaussian sigma in frames (0 = off)
    max_frames: int | None = None  # use at most this many frames of the driver; None: all
    size: int = 256  # preview video height in pixels (16..4096)


@dataclass
class RetargetResult:
    out: Path  # the output folder: weights.csv, animation.glb, preview.mp4, report.json
    frames: int  # frames retargeted
    rate_hz: float  # frames per second of weights.csv and preview.mp4
    backend: str  # "mediapipe-0.10.21" (a video or images) or "livelink-csv"
    shapes: list[str] = field(default_factory=list)  # the weight columns of weights.csv (rig shapes or ARKit names)


def _read_landmarks(path: Path, num_vertices: int):
    """landmarks.json validated; None (with a notice, so they are detected again) when missing or broken."""
    from t2bs.face.landmarks import Landmarks

    if not path.exists():
        print("no landmarks/landmarks.json yet: detecting them (t2bs landmarks DIR --show to check)")
        return None
    try:
        lm = Landmarks.from_dict(read_json(path), num_vertices)
        if not (np.isfinite(lm.points2d).all() and np.isfinite(lm.positions).all()):
            raise ValueError("NaN coordinates")
        return lm
    except (UserError, ValueError, KeyError, TypeError, AttributeError, OSError) as exc:
        why = str(exc).splitlines()[0][:120] if str(exc) else type(exc).__name__
        print(f"warning: {path} is unreadable or does not fit this character ({why}); detecting the landmarks again")
        return None


def _side_by_side(driver: np.ndarray, char: np.ndarray) -> np.ndarray:
    """Driver frame scaled to the character frame's height, then both side by side (even sizes)."""
    from PIL import Image

    h = char.shape[0]
    w = int(round(driver.shape[1] * h / driver.shape[0])) // 2 * 2
    d = np.asarray(Image.fromarray(driver).resize((w, h), Image.BILINEAR))
    return np.concatenate([d, char], axis=1)


def _head_pivot(vertices: np.ndarray) -> np.ndarray:
    """[3] point the head turns about: under the head's centre, at the bottom of the mesh (the neck)."""
    return np.array([vertices[:, 0].mean(), vertices[:, 1].min(), vertices[:, 2].mean()])


def _check(config: RetargetConfig) -> None:
    if config.driver is None:
        raise UserError("retarget needs a driver: a face video file, a folder of images or a Live Link Face .csv")
    if config.size < 16 or config.size > 4096:
        raise UserError(f"--size must be 16..4096 pixels, got {config.size}")
    if not (np.isfinite(config.smooth) and config.smooth >= 0):
        raise UserError(f"--smooth must be a finite sigma >= 0 frames, got {config.smooth}")
    if config.max_frames is not None and config.max_frames < 1:
        raise UserError(f"--max-frames must be >= 1, got {config.max_frames}")
    if config.neutral_frame is not None and config.neutral_frame < 0:
        raise UserError(f"--neutral-frame must be >= 0, got {config.neutral_frame}")


def run(project: "Project | str | os.PathLike", config: RetargetConfig = RetargetConfig()) -> RetargetResult:
    """Drive the character's blendshape model with a human performance.

    Reads ``character/mesh.glb`` and ``blendshapes/model.npz`` (neutral [N, 3], basis [K, N, 3]), and the
    driver ``config.driver``:

    - a face video or a folder of images: MediaPipe tracks the 20 landmarks of the face in every frame, their
      motion is transferred to the character's landmarks (``landmarks/landmarks.json``; found and written
      first when missing or unreadable, as ``t2bs landmarks`` would) and solved for the rig's weights;
    - a Live Link Face ``.csv``: its ARKit weights drive the rig's ARKit shapes (``blendshapes/arkit.json``)
      as they are, its head yaw / pitch / roll turn the head about the neck.

    Writes into ``config.out`` (default ``retarget/<driver name>/``): ``weights.csv`` (one row per frame:
    frame, time in seconds, one weight per shape; a video's columns are the rig's K shapes, a CSV's the ARKit
    shapes the rig has plus headYaw, headPitch, headRoll in radians), ``animation.glb`` (the neutral with the
    shapes as morph targets and the weights as an animation; a CSV's head rotation as node motion),
    ``preview.mp4`` (``size`` pixels high; a video's driver frames beside the character), ``report.json``
    (tracking report, backend, timings), and the "retarget" entry of ``manifest.json``. A video's files land
    together (staged, ``report.json`` last): a refused or failed run leaves the previous ones whole. Every run
    retargets the whole driver again (no skipping: the driver file is the input).

    Raises UserError: no driver, bad ``size`` / ``smooth`` / ``max_frames`` / ``neutral_frame``, no character
    or no blendshape model or one of another vertex count, an unreadable driver, a CSV on a rig without ARKit
    shapes or sharing none of them, a solve that gives NaN weights (nothing is written then), another t2bs
    command holding the project.
    """
    project = project if isinstance(project, Project) else Project(project)
    with project_lock(project.root, "retarget"):
        _check(config)
        if Path(config.driver).suffix.lower() == ".csv":
            return _from_csv(project, config)
        return _from_video(project, config)


def _rig(project: Project):
    """(character mesh, blendshape model) of one vertex count."""
    mesh = project.load_character()
    model = load_model(project, required=True)
    if model.num_vertices != mesh.num_vertices:
        raise UserError(f"blendshape model has {model.num_vertices} vertices but the character has {mesh.num_vertices}")
    return mesh, model


def _from_video(project: Project, config: RetargetConfig) -> RetargetResult:
    """A face video or image folder -> tracked landmarks -> solved rig weights."""
    import imageio.v2 as imageio

    from t2bs.face.face_tracking import TrackConfig, read_driver, track_face
    from t2bs.face.landmarks import find_project_landmarks
    from t2bs.face.solve import RetargetSolver
    from t2bs.face.transfer import transfer_motion
    from t2bs.geometry.camera import frontal_camera
    from t2bs.geometry.io import save_mesh
    from t2bs.render.mesh_renderer import MeshRenderer

    t0 = time.perf_counter()
    driver = Path(config.driver)
    mesh, model = _rig(project)
    frames, fps = read_driver(driver, config.max_frames)  # a bad driver fails before landmarks are written
    lm = _read_landmarks(project.path("landmarks", "landmarks.json"), mesh.num_vertices)
    if lm is None:
        lm = find_project_landmarks(project, mesh, model)
    out = Path(config.out) if config.out is not None else project.path("retarget", driver.stem)
    bar = tqdm(total=len(frames), desc="tracking face", unit="frame")
    try:  # closed before an error prints, so the error line is not glued onto the bar
        track_config = TrackConfig(
            smooth_sigma=config.smooth, neutral_frame=config.neutral_frame, static=driver.is_dir()
        )
        track = track_face(frames, fps, track_config, progress=lambda d, n: bar.update(d - bar.n))
    finally:
        bar.close()
    if track.report["missing"]:
        print(
            f"warning: no face in {track.report['missing']} of {len(frames)} frames "
            f"(runs {track.report['missing_runs']}); interpolated between tracked frames"
        )
    positions = model.neutral[lm.vertex_ids].astype(np.float64)
    tr = transfer_motion(track, positions, mouth_width=lm.regions.get("mouth", {}).get("width_world"))
    solver = RetargetSolver.with_pca_prior(model, mesh.faces, lm.vertex_ids, lm.eyeballs)
    bar = tqdm(total=len(frames), desc="solving weights", unit="frame")
    weights = solver.solve(tr.targets, tr.eye_openness, progress=lambda d, n: bar.update(d - bar.n))
    bar.close()
    if not np.isfinite(weights).all():  # never write a NaN rig over a good one
        raise UserError(
            f"the solve produced NaN weights for {int((~np.isfinite(weights)).any(1).sum())} frames; "
            f"nothing was written to {out}"
        )
    staged = OutputSet(out, marker="report.json")  # the files below land in `out` together at commit()
    folder = staged.folder
    times = np.arange(len(frames)) / fps
    with open(folder / "weights.csv", "w", newline="") as f:
        wr = csv.writer(f)
        wr.writerow(["frame", "time"] + list(model.names))
        for t in range(len(frames)):
            wr.writerow([t, f"{times[t]:.4f}"] + [f"{x:.6f}" for x in weights[t]])
    rig = mesh.with_vertices(model.neutral)
    rig.morph_targets = {n: model.basis[k].astype(np.float32) for k, n in enumerate(model.names)}
    save_mesh(
        rig,
        folder / "animation.glb",
        animation={
            "times": times.astype(np.float32),
            "weights": weights.astype(np.float32),
            "name": f"retarget:{driver.name}",
        },
    )
    cam = frontal_camera(config.size)
    verts = model.vertices(weights)
    with MeshRenderer() as renderer, imageio.get_writer(folder / "preview.mp4", fps=fps, macro_block_size=1) as writer:
        for t in tqdm(range(len(frames)), desc="preview", unit="frame"):
            char = (renderer.render(rig, cam, vertices=verts[t]).rgb * 255 + 0.5).astype(np.uint8)
            writer.append_data(_side_by_side(frames[t], char))
    write_json(
        folder / "report.json",
        {
            "driver": str(driver),
            "frames": len(frames),
            "fps": fps,
            "tracking": track.report,
            "landmarks_backend": lm.backend,
            "scales": tr.scales,
            "seconds": round(time.perf_counter() - t0, 2),
        },
    )
    out = staged.commit()
    backend = "mediapipe-0.10.21"
    project.record_stage(
        "retarget",
        backend=backend,
        config={"driver": str(driver), "smooth": config.smooth, "neutral_frame": track.neutral},
    )
    print(f"retargeted {len(frames)} frames -> {out}/weights.csv, animation.glb, preview.mp4")
    return RetargetResult(out, len(frames), float(fps), backend, list(model.names))


def _from_csv(project: Project, config: RetargetConfig) -> RetargetResult:
    """Live Link Face CSV -> weights.csv (the ARKit weights the rig has), animation.glb (ARKit morph targets +
    the head rotation as node motion), preview.mp4, report.json."""
    import imageio.v2 as imageio
    from scipy.spatial.transform import Rotation

    from t2bs.face.arkit import load_arkit_shapes
    from t2bs.face.livelink import head_rotations, read_livelink_csv
    from t2bs.geometry.camera import frontal_camera
    from t2bs.geometry.io import save_mesh
    from t2bs.project import atomic_path
    from t2bs.render.mesh_renderer import MeshRenderer

    t0 = time.perf_counter()
    driver, max_frames = Path(config.driver), config.max_frames
    mesh, model = _rig(project)
    capture = read_livelink_csv(driver)
    shapes = load_arkit_shapes(project.path("blendshapes", "arkit.json"), model.num_components)
    if shapes is None or not shapes.names:
        raise UserError(
            f"{project.path()}: the rig has no ARKit shapes (blendshapes/arkit.json); "
            f"rebuild with `t2bs blendshapes {project.root} --arkit`"
        )
    used = [n for n in shapes.names if n in capture.weights]
    if not used:
        raise UserError(f"{driver}: none of its shapes is on this rig (rig has {', '.join(shapes.names[:6])}, ...)")
    unused = [n for n in capture.weights if n not in shapes.names and np.abs(capture.weights[n]).max() > 0]
    if unused:
        print(
            f"note: {len(unused)} CSV shapes are absent on this rig and do not move it: {', '.join(unused)} "
            f"(why: blendshapes/arkit.json)"
        )
    n = len(capture.times) if max_frames is None else min(max_frames, len(capture.times))
    times, head = capture.times[:n], capture.head[:n]
    w = np.stack([capture.weights[name][:n] for name in used], 1)  # [T, S] the CSV's own weights
    sel = [shapes.names.index(name) for name in used]
    basis_w = w @ shapes.weights[sel]  # [T, K] the same pose in the model's basis
    offsets = model.offsets(shapes.weights[sel]).astype(np.float32)  # [S, N, 3]
    out = Path(config.out) if config.out is not None else project.path("retarget", driver.stem)
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "weights.csv") as tmp, open(tmp, "w", newline="") as f:
        wr = csv.writer(f)
        wr.writerow(["frame", "time"] + used + ["headYaw", "headPitch", "headRoll"])
        for t in range(n):
            wr.writerow([t, f"{times[t]:.4f}"] + [f"{x:.6f}" for x in w[t]] + [f"{x:.6f}" for x in head[t]])
    rig = mesh.with_vertices(model.neutral)
    rig.morph_targets = dict(zip(used, offsets))
    rot = head_rotations(head)  # [T, 3, 3]
    pivot = _head_pivot(model.neutral)
    trans = pivot[None] - np.einsum("tij,j->ti", rot, pivot)  # v' = R v + (p - R p): turn about the pivot
    save_mesh(
        rig,
        out / "animation.glb",
        animation={
            "times": times.astype(np.float32),
            "weights": w.astype(np.float32),
            "name": f"livelink:{driver.name}",
            "rotation": Rotation.from_matrix(rot).as_quat().astype(np.float32),
            "translation": trans.astype(np.float32),
        },
    )
    cam = frontal_camera(config.size)
    verts = model.vertices(basis_w).astype(np.float64)  # [T, N, 3]
    verts = np.einsum("tij,tnj->tni", rot, verts) + trans[:, None, :]
    rate = float(1.0 / np.median(np.diff(times))) if n > 1 else capture.fps  # samples per second (60 for the app)
    with MeshRenderer() as renderer, imageio.get_writer(out / "preview.mp4", fps=rate, macro_block_size=1) as writer:
        for t in tqdm(range(n), desc="preview", unit="frame"):
            rgb = renderer.render(rig, cam, vertices=verts[t].astype(np.float32)).rgb
            writer.append_data((rgb * 255 + 0.5).astype(np.uint8))
    write_json(
        out / "report.json",
        {
            "driver": str(driver),
            "kind": "livelink-csv",
            "frames": n,
            "rate_hz": round(rate, 3),
            "timecode_fps": capture.fps,
            "shapes_used": used,
            "shapes_absent_on_rig": unused,
            "seconds": round(time.perf_counter() - t0, 2),
        },
    )
    backend = "livelink-csv"
    project.record_stage("retarget", backend=backend, config={"driver": str(driver), "max_frames": max_frames})
    print(
        f"retargeted {n} frames at {rate:.0f} Hz ({len(used)} ARKit shapes) -> "
        f"{out}/weights.csv, animation.glb, preview.mp4"
    )
    return RetargetResult(out, n, float(rate), backend, list(used))
