"""CLI: `t2bs landmarks DIR`, `t2bs retarget DIR --driver VIDEO -o OUT`, `t2bs bench retarget`."""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path
from typing import Optional

import numpy as np
import typer
from tqdm import tqdm

from t2bs.errors import UserError
from t2bs.project import OutputSet, Project, read_json, write_image, write_json
from t2bs.project import locked


def _load_character(project_dir: Path):
    project = Project(project_dir)
    if not project.mesh_path.exists():
        raise UserError(f"{project_dir}: no character/mesh.glb (run `t2bs render MESH -o {project_dir}` first)")
    from t2bs.geometry.io import load_mesh

    return project, load_mesh(project.mesh_path)


def _load_model(project: Project, required: bool):
    path = project.path("blendshapes", "model.npz")
    if not path.exists():
        if required:
            raise UserError(f"{project.path()}: no blendshapes/model.npz (build the blendshape model first)")
        return None
    from t2bs.blendshapes.model import load_model

    return load_model(path)


def compute_landmarks(project_dir: Path, backend: str = "auto", override: Optional[Path] = None, show: bool = False):
    """Detect (or read from the user's JSON) the 20 landmarks; writes DIR/landmarks/landmarks.json."""
    from t2bs.face.landmarks import detect_landmarks, landmarks_from_override, overlay_image

    project, mesh = _load_character(project_dir)
    model = _load_model(project, required=False)
    if model is not None and model.num_vertices == mesh.num_vertices:
        mesh = mesh.with_vertices(model.neutral)
    regions = None
    if override is not None:
        if not Path(override).exists():
            raise UserError(f"override file {override} does not exist")
        try:
            data = json.loads(Path(override).read_text())
        except json.JSONDecodeError as exc:
            raise UserError(f"override file {override} is not valid JSON ({exc.msg}, line {exc.lineno})") from None
        lm = landmarks_from_override(data, mesh)
    elif backend == "auto" and project.path("character", "autorig.json").exists():
        # The motion came from the auto rig (issue 34): its 20 landmarks are this character's, in the
        # same 68-point order, found before any shape existed.
        lm = landmarks_from_override({"vertex_ids": read_json(project.path("character", "autorig.json"))["landmarks"]["vertex_ids"]}, mesh)
        lm.backend = "autorig"
    else:
        lm, regions = detect_landmarks(mesh, backend, model=model)
    out = project.path("landmarks")
    write_json(out / "landmarks.json", lm.to_dict())
    if show:
        write_image(out / "overlay.png", overlay_image(mesh, lm, regions))
    project.record_stage("landmarks", backend=lm.backend, config={"backend": backend, "override": str(override) if override else None})
    return lm


@locked("project_dir", "landmarks")  # one run at a time per project (issue 39)
def landmarks_command(
    project_dir: Path = typer.Argument(..., help="project folder (with character/mesh.glb)"),
    show: bool = typer.Option(False, "--show", help="also write landmarks/overlay.png"),
    backend: str = typer.Option("auto", "--backend", help="auto | parts | motion | grounding-sam (local Grounding-DINO + SAM checkpoints through transformers; both Apache-2.0)"),
    override: Optional[Path] = typer.Option(None, "--override", help="JSON with 20 vertex_ids or points2d"),
) -> None:
    """Find the character's 20 retargeting landmarks (6 per eye, 8 mouth) on its frontal render."""
    lm = compute_landmarks(project_dir, backend, override, show)
    print(f"landmarks ({lm.backend}) -> {Path(project_dir) / 'landmarks' / 'landmarks.json'}")
    if show:
        print(f"overlay -> {Path(project_dir) / 'landmarks' / 'overlay.png'}")


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
        print(f"warning: {path} is unreadable or does not fit this character ({str(exc).splitlines()[0][:120] if str(exc) else type(exc).__name__}); "
              "detecting the landmarks again")
        return None


def _side_by_side(driver: np.ndarray, char: np.ndarray) -> np.ndarray:
    """Driver frame scaled to the character frame's height, then both side by side (even sizes)."""
    from PIL import Image

    h = char.shape[0]
    w = int(round(driver.shape[1] * h / driver.shape[0])) // 2 * 2
    d = np.asarray(Image.fromarray(driver).resize((w, h), Image.BILINEAR))
    return np.concatenate([d, char], axis=1)


@locked("project_dir", "retarget")  # one run at a time per project (issue 39)
def retarget_command(
    project_dir: Path = typer.Argument(..., help="project folder (character/mesh.glb, blendshapes/model.npz)"),
    driver: Path = typer.Option(..., "--driver", help="human face video file, folder of images, or Live Link Face .csv"),
    out: Optional[Path] = typer.Option(None, "-o", "--out", help="output folder (default DIR/retarget/<driver name>)"),
    neutral_frame: Optional[int] = typer.Option(None, "--neutral-frame", help="index of the neutral frame (default: detected)"),
    smooth: float = typer.Option(1.0, "--smooth", help="temporal smoothing of the landmarks, sigma in frames (0 = off)"),
    max_frames: Optional[int] = typer.Option(None, "--max-frames", help="use at most this many frames"),
    size: int = typer.Option(256, "--size", help="preview video height in pixels"),
) -> None:
    """Drive the character's blendshape model with a human face video (MediaPipe + landmark solve)
    or a Live Link Face CSV (its ARKit weights drive the rig's ARKit shapes directly)."""
    if driver.suffix.lower() == ".csv":
        retarget_from_csv(project_dir, driver, out, max_frames, size)
        return
    from t2bs.geometry.camera import frontal_camera
    from t2bs.geometry.io import save_mesh
    from t2bs.render.mesh_renderer import MeshRenderer
    from t2bs.face.face_tracking import TrackConfig, read_driver, track_face
    from t2bs.face.solve import RetargetSolver
    from t2bs.face.transfer import transfer_motion

    t0 = time.perf_counter()
    if size < 16 or size > 4096:
        raise UserError(f"--size must be 16..4096 pixels, got {size}")
    if not (np.isfinite(smooth) and smooth >= 0):
        raise UserError(f"--smooth must be a finite sigma >= 0 frames, got {smooth}")
    if max_frames is not None and max_frames < 1:
        raise UserError(f"--max-frames must be >= 1, got {max_frames}")
    if neutral_frame is not None and neutral_frame < 0:
        raise UserError(f"--neutral-frame must be >= 0, got {neutral_frame}")
    project, mesh = _load_character(project_dir)
    model = _load_model(project, required=True)
    if model.num_vertices != mesh.num_vertices:
        raise UserError(f"blendshape model has {model.num_vertices} vertices but the character has {mesh.num_vertices}")
    frames, fps = read_driver(driver, max_frames)  # a bad driver fails before landmarks are written
    lm_path = project.path("landmarks", "landmarks.json")
    lm = _read_landmarks(lm_path, mesh.num_vertices)
    if lm is None:
        lm = compute_landmarks(project_dir)
    out = Path(out) if out is not None else project.path("retarget", driver.stem)
    bar = tqdm(total=len(frames), desc="tracking face", unit="frame")
    try:  # closed before an error prints, so the error line is not glued onto the bar
        track = track_face(frames, fps, TrackConfig(smooth_sigma=smooth, neutral_frame=neutral_frame,
                                                     static=driver.is_dir()), progress=lambda d, n: bar.update(d - bar.n))
    finally:
        bar.close()
    if track.report["missing"]:
        print(f"warning: no face in {track.report['missing']} of {len(frames)} frames "
              f"(runs {track.report['missing_runs']}); interpolated between tracked frames")
    positions = model.neutral[lm.vertex_ids].astype(np.float64)
    tr = transfer_motion(track, positions, mouth_width=lm.regions.get("mouth", {}).get("width_world"))
    solver = RetargetSolver(model.neutral, model.basis, mesh.faces, lm.vertex_ids, lm.eyeballs)
    bar = tqdm(total=len(frames), desc="solving weights", unit="frame")
    weights = solver.solve(tr.targets, tr.eye_openness, progress=lambda d, n: bar.update(d - bar.n))
    bar.close()
    if not np.isfinite(weights).all():  # never write a NaN rig over a good one
        raise UserError(f"the solve produced NaN weights for {int((~np.isfinite(weights)).any(1).sum())} frames; "
                        f"nothing was written to {out}")
    staged = OutputSet(out, marker="report.json")  # the files below land in `out` together at commit()
    out = staged.folder
    times = np.arange(len(frames)) / fps
    with open(out / "weights.csv", "w", newline="") as f:
        wr = csv.writer(f)
        wr.writerow(["frame", "time"] + list(model.names))
        for t in range(len(frames)):
            wr.writerow([t, f"{times[t]:.4f}"] + [f"{x:.6f}" for x in weights[t]])
    rig = mesh.with_vertices(model.neutral)
    rig.morph_targets = {n: model.basis[k].astype(np.float32) for k, n in enumerate(model.names)}
    save_mesh(rig, out / "animation.glb", animation={"times": times.astype(np.float32), "weights": weights.astype(np.float32),
                                                       "name": f"retarget:{driver.name}"})
    import imageio.v2 as imageio

    cam = frontal_camera(size)
    verts = model.vertices(weights)
    with MeshRenderer() as renderer, imageio.get_writer(out / "preview.mp4", fps=fps, macro_block_size=1) as writer:
        for t in tqdm(range(len(frames)), desc="preview", unit="frame"):
            char = (renderer.render(rig, cam, vertices=verts[t]).rgb * 255 + 0.5).astype(np.uint8)
            writer.append_data(_side_by_side(frames[t], char))
    write_json(out / "report.json", {"driver": str(driver), "frames": len(frames), "fps": fps, "tracking": track.report,
                                     "landmarks_backend": lm.backend, "scales": tr.scales,
                                     "seconds": round(time.perf_counter() - t0, 2)})
    out = staged.commit()
    project.record_stage("retarget", backend="mediapipe-0.10.21", config={"driver": str(driver), "smooth": smooth,
                                                                          "neutral_frame": track.neutral})
    print(f"retargeted {len(frames)} frames -> {out}/weights.csv, animation.glb, preview.mp4")


def _head_pivot(vertices: np.ndarray) -> np.ndarray:
    """[3] point the head turns about: under the head's centre, at the bottom of the mesh (the neck)."""
    return np.array([vertices[:, 0].mean(), vertices[:, 1].min(), vertices[:, 2].mean()])


def retarget_from_csv(project_dir: Path, driver: Path, out: Optional[Path] = None, max_frames: Optional[int] = None,
                      size: int = 256) -> Path:
    """Live Link Face CSV -> DIR/retarget/<name>/weights.csv (the ARKit weights the rig has), animation.glb
    (ARKit morph targets + the head rotation as node motion), preview.mp4, report.json."""
    from scipy.spatial.transform import Rotation

    from t2bs.geometry.camera import frontal_camera
    from t2bs.geometry.io import save_mesh
    from t2bs.project import atomic_path
    from t2bs.render.mesh_renderer import MeshRenderer
    from t2bs.face.arkit import load_arkit_shapes
    from t2bs.face.livelink import head_rotations, read_livelink_csv

    t0 = time.perf_counter()
    project, mesh = _load_character(project_dir)
    model = _load_model(project, required=True)
    if model.num_vertices != mesh.num_vertices:
        raise UserError(f"blendshape model has {model.num_vertices} vertices but the character has {mesh.num_vertices}")
    capture = read_livelink_csv(driver)
    shapes = load_arkit_shapes(project.path("blendshapes", "arkit.json"), model.num_components)
    if shapes is None or not shapes.names:
        raise UserError(f"{project.path()}: the rig has no ARKit shapes (blendshapes/arkit.json); "
                        f"rebuild with `t2bs blendshapes {project_dir} --arkit`")
    used = [n for n in shapes.names if n in capture.weights]
    if not used:
        raise UserError(f"{driver}: none of its shapes is on this rig (rig has {', '.join(shapes.names[:6])}, ...)")
    unused = [n for n in capture.weights if n not in shapes.names and np.abs(capture.weights[n]).max() > 0]
    if unused:
        print(f"note: {len(unused)} CSV shapes are absent on this rig and do not move it: {', '.join(unused)} "
              f"(why: blendshapes/arkit.json)")
    n = len(capture.times) if max_frames is None else min(max_frames, len(capture.times))
    times, head = capture.times[:n], capture.head[:n]
    w = np.stack([capture.weights[name][:n] for name in used], 1)  # [T, S] the CSV's own weights
    sel = [shapes.names.index(name) for name in used]
    basis_w = w @ shapes.weights[sel]  # [T, K] the same pose in the model's basis
    offsets = model.offsets(shapes.weights[sel]).astype(np.float32)  # [S, N, 3]
    out = Path(out) if out is not None else project.path("retarget", driver.stem)
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
    save_mesh(rig, out / "animation.glb", animation={
        "times": times.astype(np.float32), "weights": w.astype(np.float32), "name": f"livelink:{driver.name}",
        "rotation": Rotation.from_matrix(rot).as_quat().astype(np.float32), "translation": trans.astype(np.float32)})
    import imageio.v2 as imageio

    cam = frontal_camera(size)
    verts = model.vertices(basis_w).astype(np.float64)  # [T, N, 3]
    verts = np.einsum("tij,tnj->tni", rot, verts) + trans[:, None, :]
    rate = float(1.0 / np.median(np.diff(times))) if n > 1 else capture.fps  # samples per second (60 for the app)
    with MeshRenderer() as renderer, imageio.get_writer(out / "preview.mp4", fps=rate, macro_block_size=1) as writer:
        for t in tqdm(range(n), desc="preview", unit="frame"):
            writer.append_data((renderer.render(rig, cam, vertices=verts[t].astype(np.float32)).rgb * 255 + 0.5).astype(np.uint8))
    write_json(out / "report.json", {"driver": str(driver), "kind": "livelink-csv", "frames": n, "rate_hz": round(rate, 3), "timecode_fps": capture.fps,
                                     "shapes_used": used, "shapes_absent_on_rig": unused,
                                     "seconds": round(time.perf_counter() - t0, 2)})
    project.record_stage("retarget", backend="livelink-csv", config={"driver": str(driver), "max_frames": max_frames})
    print(f"retargeted {n} frames at {rate:.0f} Hz ({len(used)} ARKit shapes) -> "
          f"{out}/weights.csv, animation.glb, preview.mp4")
    return out
