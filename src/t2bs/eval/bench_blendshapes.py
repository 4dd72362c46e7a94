"""`t2bs bench blendshapes`: held-out expressiveness of the blendshape model, on captures made from an asset's own
morph targets (or the video animator), against the paper's numbers."""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from t2bs.blendshapes.stage import _grid_gt, load_captures
from t2bs.errors import UserError


# ---------------------------------------------------------------- benchmark captures


def morph_captures(
    mesh, prompts: int = 20, frames: int = 24, seed: int = 0, head_motion: bool = True, max_targets: int = 3
) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Ground-truth captures from an asset's own morph targets: random sparse weight curves.

    Each "prompt" drives 1..max_targets randomly chosen morph targets with smooth bumps (random
    peak 0.5..1, onset and duration), and half of them add a small rigid head turn/nod (up to
    8 / 5 degrees about a pivot at the bottom of the head), like the video animator's head
    motion. Returns (video_id -> [T, N, 3], video_id -> description). Used by the benchmark
    when the video stage's animator is not installed.
    """
    names = mesh.morph_names
    if not names:
        raise UserError("the asset has no morph targets to animate (benchmark needs real blendshapes)")
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, frames)
    base = mesh.vertices.astype(np.float64)
    offsets = np.stack([mesh.morph_targets[n] for n in names]).astype(np.float64)  # [M, N, 3]
    pivot = np.array([0.0, base[:, 1].min(), 0.0]) + np.array([base[:, 0].mean(), 0.0, base[:, 2].mean()])
    captures, descriptions = {}, {}
    for p in range(prompts):
        count = int(rng.integers(1, min(max_targets, len(names)) + 1))
        chosen = rng.choice(len(names), size=count, replace=False)
        w = np.zeros((frames, len(names)))
        for c in chosen:
            start, length = rng.uniform(0.0, 0.4), rng.uniform(0.4, 0.6)
            phase = np.clip((t - start) / length, 0.0, 1.0)
            w[:, c] = rng.uniform(0.5, 1.0) * np.sin(np.pi * phase) ** 2
        verts = base[None] + np.einsum("tm,mnc->tnc", w, offsets)  # [T, N, 3]
        desc = "+".join(names[c] for c in chosen)
        if head_motion and p % 2 == 1:
            yaw = np.deg2rad(rng.uniform(-8, 8)) * np.sin(2 * np.pi * t)
            pitch = np.deg2rad(rng.uniform(-5, 5)) * np.sin(np.pi * t)
            verts = np.stack([(v - pivot) @ _rot(a, b).T + pivot for v, a, b in zip(verts, yaw, pitch)])
            desc += "+head"
        vid = f"morph{p:02d}-s0"
        captures[vid] = verts.astype(np.float32)
        descriptions[vid] = desc
    return captures, descriptions


def _rot(yaw: float, pitch: float) -> np.ndarray:
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    return ry @ rx


def animator_captures(
    mesh, frames: int = 24, seed: int = 0, expressions=None
) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Ground-truth captures from the video stage's animator: one per expression prompt (sample 0).

    ``mesh`` must be in the canonical frame. Returns (video_id -> [T, N, 3], video_id -> prompt),
    video ids "<expression-slug>-s0" as the video stage names its folders.
    """
    from t2bs.video.animator import AnimationConfig, animate
    from t2bs.video.prompts import EXPRESSIONS, slug

    config = AnimationConfig(frames=frames)
    captures, names = {}, {}
    for expr in expressions or EXPRESSIONS:
        vid = f"{slug(expr)}-s0"
        captures[vid] = animate(mesh, expr, seed=seed, sample=0, config=config).vertices.astype(np.float32)
        names[vid] = expr
    return captures, names


def _asset_captures(asset: str, source: str, frames: int, prompts: int, seed: int, facing: str):
    """(character Mesh in the canonical frame, captures, expressions, how the captures were made, GT or None).

    ``asset``: a project folder (its videos/ or recon/), a mesh file with morph targets, or
    ``procedural:PROMPT`` (a procedural character from the character stage).
    """
    from t2bs.geometry.io import load_mesh
    from t2bs.geometry.mesh import normalize
    from t2bs.project import Project

    path = Path(asset)
    if path.is_dir():
        project = Project(path)
        character = project.load_character()
        captures, expressions, _, used = load_captures(path, source)
        gt = None
        if used == "vcdgs" and (path / "videos").is_dir():
            gt = {v: g for v in captures for g in [_grid_gt(path / "videos" / v)[0]] if g is not None}
        return character, captures, expressions, f"project:{used}", gt
    if source == "vcdgs":
        raise UserError(
            f"{asset}: --source vcdgs needs a project folder with recon/ (run the pipeline on the asset first)"
        )
    if asset.startswith("procedural:"):
        from t2bs.character.backends import generate

        mesh = generate(asset.split(":", 1)[1], backend="procedural", seed=seed).mesh
    else:
        if not path.exists():
            raise UserError(f"{asset}: no such mesh file or project folder")
        mesh, _ = normalize(load_mesh(path), facing=facing)
    try:
        from t2bs.video.prompts import EXPRESSIONS

        captures, expressions = animator_captures(
            mesh, frames=frames, seed=seed, expressions=list(EXPRESSIONS)[:prompts]
        )
        return mesh, captures, expressions, "video-animator", None
    except ImportError:  # the video stage is not installed: the asset's own morph targets, random curves
        captures, expressions = morph_captures(mesh, prompts=prompts, frames=frames, seed=seed)
        return mesh, captures, expressions, "morph-random", None


def _held_out_split(captures: dict[str, np.ndarray], expressions: dict[str, str], held_out: int, seed: int):
    """Hold out every capture of ``held_out`` randomly chosen prompts (paper: 5 held-out videos)."""
    from t2bs.blendshapes.semantic import prompt_of

    by_prompt: dict[str, list[str]] = {}
    for vid in sorted(captures):
        by_prompt.setdefault(prompt_of(vid), []).append(vid)
    keys = sorted(by_prompt)
    if len(keys) < 2:
        raise UserError("need captures of at least 2 prompts to hold some out")
    count = min(held_out, len(keys) - 1)
    rng = np.random.default_rng(seed + 1)
    test_prompts = set(rng.choice(keys, size=count, replace=False).tolist())
    train = [v for k in keys if k not in test_prompts for v in by_prompt[k]]
    test = [v for k in keys if k in test_prompts for v in by_prompt[k]]
    return train, test


def evaluate_held_out(
    character,
    captures: dict[str, np.ndarray],
    expressions: dict[str, str],
    components: int = 100,
    held_out: int = 5,
    seed: int = 0,
    rgb_steps: int = 10,
    image_size: int = 256,
    renderer=None,
    ground_truth: dict[str, np.ndarray] | None = None,
) -> dict:
    """Build the model without the held-out prompts, fit their every frame, measure p2p and pixel L2.

    p2p: mean over frames of the mean vertex distance divided by the neutral's bounding-box
    diagonal. pixel_l2: mean over frames, pixels and RGB channels of the squared difference
    (colours in 0..1) between renders of the capture and of the fit from the frontal camera
    (whole image, white background; the mesh renderer with its default shading, vertex splats if
    it is unavailable). The fit minimises L_geo + 0.1 L_rgb + prior (fit.py).
    Errors are measured against the held-out captures themselves (the paper's protocol); with
    ``ground_truth`` (video_id -> true [T, N, 3], e.g. for VCDGS captures) ``p2p_vs_gt`` also
    measures the fit against the true geometry. The model holds expressions (build_model takes each frame's head
    motion out), so the held-out frames are fitted and measured as seen from the head too: each frame's robust
    rigid motion is taken out of the capture (and of the truth) first.
    """
    from t2bs.blendshapes.fit import FitConfig, fit_frames, splat_vertices, visible_vertices
    from t2bs.blendshapes.model import build_model
    from t2bs.geometry.camera import frontal_camera
    from t2bs.geometry.rigid import nonrigid_displacements

    def expression(frames: np.ndarray) -> np.ndarray:  # [T, N, 3] without each frame's head motion
        return character.vertices.astype(np.float64) + nonrigid_displacements(character.vertices, frames)[0]

    train, test = _held_out_split(captures, expressions, held_out, seed)
    t0 = time.time()
    model = build_model(character.vertices, {v: captures[v] for v in train}, components=components)
    build_s = time.time() - t0
    target = np.concatenate([expression(captures[v]) for v in test])  # [T, N, 3]
    camera = frontal_camera(image_size)
    colors = character.vertex_rgb()
    t0 = time.time()
    cfg = FitConfig(rgb_steps=rgb_steps)
    weights = fit_frames(
        model, colors=colors, faces=character.faces, target_vertices=target, cameras=[camera], config=cfg
    )
    fit_s = time.time() - t0
    fitted = model.vertices(weights)  # [T, N, 3]
    diag = character.bbox_diagonal()
    dist = np.linalg.norm(fitted.astype(np.float64) - target, axis=-1)  # [T, N]
    p2p = dist.mean(1) / diag  # [T]
    geo_only = model.vertices(fit_frames(model, target_vertices=target, config=cfg))
    p2p_geo = np.linalg.norm(geo_only.astype(np.float64) - target, axis=-1).mean(1) / diag
    pix, renderer_name = [], "mesh"
    if renderer is None:
        try:
            from t2bs.render.mesh_renderer import MeshRenderer

            renderer = MeshRenderer()
        except Exception as exc:  # no EGL / renderer not installed: fall back to the splat images
            print(f"bench blendshapes: mesh renderer unavailable ({exc}); pixel L2 from vertex splats", file=sys.stderr)
            renderer = None
    if renderer is not None:
        for a, b in zip(target, fitted):
            ra = renderer.render(character, camera, vertices=a).rgb
            rb = renderer.render(character, camera, vertices=b).rgb
            pix.append(float(((ra - rb) ** 2).mean()))
    else:
        import torch

        renderer_name = "vertex-splat"
        vis = visible_vertices(target, character.faces, camera)
        with torch.no_grad():
            ia = splat_vertices(torch.as_tensor(target), torch.as_tensor(colors), camera, torch.as_tensor(vis))
            ib = splat_vertices(torch.as_tensor(fitted), torch.as_tensor(colors), camera, torch.as_tensor(vis))
        pix = ((ia - ib) ** 2).mean((1, 2, 3)).numpy().tolist()
    extra = {}
    if ground_truth is not None and all(v in ground_truth for v in test):
        gt = np.concatenate([expression(ground_truth[v]) for v in test])
        extra["p2p_vs_gt"] = float((np.linalg.norm(fitted.astype(np.float64) - gt, axis=-1).mean(1) / diag).mean())
        extra["p2p_capture_vs_gt"] = float((np.linalg.norm(target - gt, axis=-1).mean(1) / diag).mean())
    return {
        **extra,
        "components": model.num_components,
        "p2p": float(p2p.mean()),
        "pixel_l2": float(np.mean(pix)),
        "p2p_geometry_only": float(p2p_geo.mean()),
        "p2p_max_frame": float(p2p.max()),
        "rank": model.meta["rank"],
        "explained_variance": float(model.explained_variance.sum()),
        "train_captures": len(train),
        "held_out_captures": len(test),
        "held_out": sorted(test),
        "held_out_frames": int(len(target)),
        "renderer": renderer_name,
        "image_size": image_size,
        "rgb_steps": rgb_steps,
        "build_s": round(build_s, 3),
        "fit_s": round(fit_s, 3),
    }


@dataclass
class BenchBlendshapesConfig:
    asset: str  # mesh with morph targets (.glb), a project folder, or procedural:PROMPT
    json_out: Path | None = None  # also write the JSON here
    source: str = "gt"  # gt: ground-truth captures; vcdgs: recon/ of a project folder
    components: int = 100  # shapes in the model (paper: 100)
    held_out: int = 5  # prompts held out of the model (paper: 5)
    prompts: int = 20  # prompts animated for a mesh asset (paper: 20)
    frames: int = 24  # frames per capture for a mesh asset
    rgb_steps: int = 10  # L-BFGS iterations of the 0.1 L_rgb refinement (0 = geometry only)
    image_size: int = 256  # side of the frontal renders for pixel L2, pixels
    facing: str = "+z"  # direction a mesh asset faces: +z, -z, +x, -x
    seed: int = 0  # random seed of the captures and of the held-out choice


def bench_blendshapes(config: BenchBlendshapesConfig) -> dict:
    """Held-out expressiveness (paper appendix): mean p2p / bbox diagonal and pixel L2 of fitted held-out captures.

    Reads ``asset``: a project folder (its videos/ captures, or its recon/ with ``source="vcdgs"``), a mesh file
    whose morph targets make the captures, or a procedural character. Builds the model without the held-out prompts
    and fits them (``evaluate_held_out``). Writes ``json_out`` if given. Returns
    ``{"benchmark": "blendshapes", "paper": {...}, "rows": [row]}``. Raises UserError for an unknown source, a
    missing asset, or ``source="vcdgs"`` without a project folder.
    """
    from t2bs.project import write_json

    asset, source, seed = config.asset, config.source, config.seed
    if source not in ("gt", "vcdgs"):
        raise UserError(f"unknown --source {source!r}; use gt or vcdgs")
    t0 = time.time()
    character, captures, expressions, made_by, gt = _asset_captures(
        asset, source, config.frames, config.prompts, seed, config.facing
    )
    result = evaluate_held_out(
        character,
        captures,
        expressions,
        components=config.components,
        held_out=config.held_out,
        seed=seed,
        rgb_steps=config.rgb_steps,
        image_size=config.image_size,
        ground_truth=gt,
    )
    name = (
        asset.split(":", 1)[1]
        if asset.startswith("procedural:")
        else (Path(asset).name if Path(asset).is_dir() else Path(asset).stem)
    )
    row = {"asset": name, "source": source, **result, "captures_from": made_by, "seconds": round(time.time() - t0, 2)}
    out = {"benchmark": "blendshapes", "paper": {"p2p": 0.0017, "pixel_l2": 0.0009}, "rows": [row]}
    if config.json_out is not None:
        write_json(config.json_out, out)
    return out
