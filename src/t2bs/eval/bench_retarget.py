"""`t2bs bench retarget`: retargeting end to end against ground truth (issue 8, "Must show").

Driver: facecap.glb (a realistic human head) animated with its own ARKit morphs jawOpen,
eyeBlink_L, eyeBlink_R and mouthSmile_L/R (together), rendered with the mesh renderer from a
frontal camera at 256 px. MediaPipe tracks the rendered head; the motion is retargeted onto the
target's blendshape model; the retargeted offsets of every frame are projected (jointly, least
squares) onto the target's own expression directions, and each coefficient is correlated
(Pearson) with the driver weight that should cause it. Mirror: the driver's eyeBlink_L (its
left eye, +X, image right) must close the target's left eye (+X).

Targets:
- turtle.glb: its model is the PCA of captures driven by its own 11 morph targets (the stand-in
  for VCDGS captures); directions mouthOpen, eyeLeftClose, eyeRightClose, smile (smileLeft + smileRight).
- a procedural character (``procedural:<prompt>``, t2bs.character): its rig morphs jaw_open,
  blink_left, blink_right, smile, modelled the same way.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from t2bs.errors import UserError
from t2bs.geometry.camera import Camera, intrinsics, look_at
from t2bs.geometry.mesh import Mesh, normalize
from t2bs.project import write_json
from t2bs.shared_assets import ENV, shared_asset, shared_assets_dir

ASSETS = shared_assets_dir()
DRIVER_PAIRS = {
    # driver shape -> (target morph direction for a turtle-style rig, for a procedural rig)
    "jawOpen": ("mouthOpen", "jaw_open"),
    "eyeBlink_L": ("eyeLeftClose", "blink_left"),
    "eyeBlink_R": ("eyeRightClose", "blink_right"),
    "mouthSmile_L+mouthSmile_R": ("smile", "smile"),
}


def driver_weights(frames: int = 96, seed: int = 0) -> dict[str, np.ndarray]:
    """Per-frame ARKit weights [T] with separate and overlapping events (so crosstalk would show)."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames)

    def bumps(centres, width, heights):
        out = np.zeros(frames)
        for c, hgt in zip(centres, heights):
            out = np.maximum(out, hgt * np.exp(-0.5 * ((t - c) / width) ** 2))
        return out

    f = frames / 96.0
    jaw = bumps(np.array([12, 45, 80]) * f, 5 * f, [0.9, 0.5, 0.75])
    blink_l = bumps(np.array([28, 62, 88]) * f, 2.2 * f, [1.0, 1.0, 0.7])
    blink_r = bumps(np.array([28, 50, 72]) * f, 2.2 * f, [1.0, 0.9, 1.0])
    smile = bumps(np.array([38, 70]) * f, 6 * f, [0.8, 1.0])
    jitter = rng.uniform(0.97, 1.0, frames)  # tiny, keeps runs with different seeds distinct
    return {
        "jawOpen": jaw * jitter,
        "eyeBlink_L": blink_l,
        "eyeBlink_R": blink_r,
        "mouthSmile_L": smile,
        "mouthSmile_R": smile,
    }


def driver_camera(size: int = 256) -> Camera:
    """Frontal camera framing the canonical facecap head (face ~ 60 % of the image width)."""
    return Camera(
        intrinsics(size, size, 30.0),
        look_at(np.array([0.0, 0.03, 1.55]), np.array([0.0, 0.03, 0.0])),
        size,
        size,
        "driver",
    )


def render_driver(
    weights: dict[str, np.ndarray], size: int = 256, asset: Path | None = None, renderer=None
) -> np.ndarray:
    """Frames [T, size, size, 3] uint8 of facecap.glb posed with ``weights``."""
    from t2bs.geometry.io import load_mesh
    from t2bs.render.mesh_renderer import MeshRenderer

    path = asset or ASSETS / "facecap.glb"
    if not path.exists():
        raise UserError(
            f"driver asset {path} not found (the shared assets: ${ENV} or ../shared/assets beside the checkout)"
        )
    mesh, _ = normalize(load_mesh(path))
    cam = driver_camera(size)
    frames = []
    own = renderer is None
    renderer = renderer or MeshRenderer()
    try:
        for t in range(len(next(iter(weights.values())))):
            v = mesh.posed({k: float(w[t]) for k, w in weights.items()})
            frames.append((renderer.render(mesh, cam, vertices=v).rgb * 255 + 0.5).astype(np.uint8))
    finally:
        if own:
            renderer.release()
    return np.stack(frames)


def morph_model(mesh: Mesh, components: int = 100, seed: int = 0):
    """Blendshape model of a mesh from captures driven by its own morph targets (rank = #morphs)."""
    from t2bs.blendshapes.model import build_model

    names = list(mesh.morph_targets)
    if not names:
        raise UserError("target has no morph targets to build a model from")
    rng = np.random.default_rng(seed)
    ramp = np.sin(np.linspace(0, np.pi, 16))  # one expression video: neutral -> peak -> neutral
    captures = {}
    v0 = mesh.vertices.astype(np.float64)
    for name in names:
        captures[name] = (v0[None] + ramp[:, None, None] * mesh.morph_targets[name][None]).astype(np.float32)
    for i in range(4):  # mixtures, as real captures mix shapes
        w = rng.uniform(0, 1, (16, len(names))) * (rng.uniform(size=len(names)) < 0.3)
        captures[f"mix{i}"] = (
            v0[None] + np.einsum("tm,mnc->tnc", w, np.stack([mesh.morph_targets[n] for n in names]))
        ).astype(np.float32)
    return build_model(mesh.vertices, captures, components=components, source="morph targets")


def project_directions(offsets: np.ndarray, mesh: Mesh) -> dict[str, np.ndarray]:
    """Least-squares coefficients [T] of offsets [T, N, 3] on all the mesh's morph directions jointly."""
    names = list(mesh.morph_targets)
    a = np.stack([mesh.morph_targets[n].reshape(-1) for n in names], axis=1).astype(np.float64)  # [3N, M]
    coef, *_ = np.linalg.lstsq(a, offsets.reshape(len(offsets), -1).T.astype(np.float64), rcond=None)
    return {n: coef[i] for i, n in enumerate(names)}


def load_target(spec: str, seed: int = 0) -> tuple[str, Mesh, bool]:
    """(label, canonical mesh, is_procedural) for a path or ``procedural:<prompt>``."""
    if spec.startswith("procedural"):
        prompt = spec.split(":", 1)[1].strip() if ":" in spec else ""
        prompt = prompt or "a cartoon fox"
        return f"procedural:{prompt}", procedural_mesh(prompt, seed), True
    from t2bs.character.render_stage import canonical_character

    path = Path(spec)
    if not path.exists():
        raise UserError(f"target {path} does not exist (a mesh file, or procedural:<prompt>)")
    mesh, _ = canonical_character(path)
    return path.stem, mesh, False


def procedural_mesh(prompt: str, seed: int = 0) -> Mesh:
    """The procedural generator's canonical character (rig controls as morph targets, part labels)."""
    try:
        from t2bs.character.procedural import generate_procedural
    except ImportError:
        raise UserError("procedural characters (t2bs.character) are not available in this build") from None
    return generate_procedural(prompt, seed).mesh


def pearson(a: np.ndarray, b: np.ndarray) -> float:
    a, b = np.asarray(a, float) - np.mean(a), np.asarray(b, float) - np.mean(b)
    den = float(np.linalg.norm(a) * np.linalg.norm(b))
    return float(a @ b / den) if den > 0 else 0.0


def retarget_target(spec: str, track, weights: dict[str, np.ndarray], renderer=None) -> list[dict]:
    """Retarget ``track`` onto one target and correlate with the driver weights; rows of the contract."""
    from t2bs.face.landmarks import detect_landmarks
    from t2bs.face.solve import RetargetSolver
    from t2bs.face.transfer import transfer_motion

    label, mesh, procedural = load_target(spec)
    model = morph_model(mesh)
    lm, _ = detect_landmarks(mesh, "parts" if procedural else "motion", model=model, renderer=renderer)
    tr = transfer_motion(track, lm.positions, mouth_width=lm.regions.get("mouth", {}).get("width_world"))
    solver = RetargetSolver.with_pca_prior(model, mesh.faces, lm.vertex_ids, lm.eyeballs)
    w = solver.solve(tr.targets, tr.eye_openness)
    offsets = model.offsets(w)  # [T, N, 3]
    coef = project_directions(offsets, mesh)
    rows = []
    for drv, (turtle_dir, proc_dir) in DRIVER_PAIRS.items():
        target_dir = proc_dir if procedural else turtle_dir
        parts = [
            d
            for d in (target_dir, target_dir.replace("smile", "smileLeft"), target_dir.replace("smile", "smileRight"))
            if d in coef
        ]
        if target_dir == "smile" and "smileLeft" in coef:
            series = (coef["smileLeft"] + coef["smileRight"]) / 2
        elif target_dir in coef:
            series = coef[target_dir]
        else:
            continue
        del parts
        driver = sum(weights[d] for d in drv.split("+")) / len(drv.split("+"))
        rows.append(
            {
                "target": label,
                "driver_shape": drv,
                "target_direction": target_dir,
                "pearson": round(pearson(driver, series), 4),
            }
        )
    return rows


def run_bench(
    targets: list[str], frames: int = 96, size: int = 256, seed: int = 0, save_dir: Path | None = None
) -> dict:
    from t2bs.render.mesh_renderer import MeshRenderer
    from t2bs.face.face_tracking import TrackConfig, track_face

    t0 = time.perf_counter()
    weights = driver_weights(frames, seed)
    with MeshRenderer() as renderer:
        video = render_driver(weights, size, renderer=renderer)
        t_render = time.perf_counter() - t0
        track = track_face(video, 30.0, TrackConfig(smooth_sigma=0.0))
        t_track = time.perf_counter() - t0 - t_render
        rows = []
        for spec in targets:
            rows += retarget_target(spec, track, weights, renderer=renderer)
    if save_dir is not None:
        import imageio.v2 as imageio

        save_dir.mkdir(parents=True, exist_ok=True)
        imageio.mimwrite(save_dir / "driver.mp4", list(video), fps=30, macro_block_size=1)
    return {
        "rows": rows,
        "driver": {
            "asset": "facecap.glb",
            "frames": frames,
            "size": size,
            "found": int(track.found.sum()),
            "neutral_frame": track.neutral,
        },
        "seconds": {
            "render_driver": round(t_render, 2),
            "track": round(t_track, 2),
            "total": round(time.perf_counter() - t0, 2),
        },
    }


@dataclass
class BenchRetargetConfig:
    target: tuple[str, ...] = ()  # target meshes with morph targets, or procedural:<prompt>; () = the shared turtle.glb
    json_path: Path | None = None  # also write the result to this JSON file
    frames: int = 96  # driver frames
    seed: int = 0  # seed of the driver weights' jitter


def bench_retarget(config: BenchRetargetConfig = BenchRetargetConfig()) -> dict:
    """Facecap ARKit morphs -> MediaPipe -> target model; Pearson of the target's own directions.

    Reads the shared facecap.glb (the driver) and each target (default: the shared turtle.glb, $T2BS_SHARED_ASSETS or
    ../shared/assets). Writes ``json_path`` if given. Returns ``run_bench``'s ``{"rows": [{target, driver_shape,
    target_direction, pearson}], "driver": {...}, "seconds": {...}}``. Raises UserError for a missing driver or
    target, or a target without morph targets.
    """
    result = run_bench(list(config.target or [str(shared_asset("turtle.glb"))]), frames=config.frames, seed=config.seed)
    if config.json_path is not None:
        write_json(config.json_path, result)
    return result
