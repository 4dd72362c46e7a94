"""The blendshapes stage: the PCA blendshape model of every captured frame, exported (paper §3.3).

Its benchmark is t2bs.eval.bench_blendshapes; its command line t2bs.cli.blendshapes.
"""

from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from t2bs.errors import UserError
from t2bs.project import Project, project_lock, read_array, read_json

SOURCES = ("auto", "vcdgs", "gt")


@dataclass
class BlendshapesConfig:
    components: int = 100  # most shapes to keep (also capped by the data's rank)
    source: str = "auto"  # vcdgs: recon/*/vertices.npy; gt: videos/*/gt_vertices.npy; auto: vcdgs if any finished
    semantic: bool = True  # add one named shape per expression prompt
    animation: str | None = None  # video id replayed by model.glb; None: the capture that moves most
    usd: bool = False  # also write model.usdc (binary USD, UsdSkel blend shapes; needs usd-core)
    fps: float = 8.0  # frame rate of the exported animation, frames per second
    force: bool = False  # rebuild even if the inputs did not change
    arkit: bool = True  # derive the ARKit-52 named shapes (needs the character's 20 landmarks; docs/ARKIT.md)


@dataclass
class BlendshapesResult:
    folder: Path  # DIR/blendshapes (model.npz, model.glb, stats.json, done.json, ...)
    components: int  # shapes in the model
    source: str  # captures used: vcdgs or gt
    animation: str | None  # video id model.glb replays
    arkit: list[str] | None  # ARKit shapes derived (None: not asked for, or no landmarks)
    up_to_date: bool = False  # True when nothing was rebuilt (the result is read from stats.json)


# ------------------------------------------------------------------------------ captures


def _grid_gt(folder: Path) -> tuple[np.ndarray | None, dict]:
    """Ground-truth vertices [T, N, 3] and meta of a video grid folder (grid loader when present)."""
    try:
        from t2bs.video.grid import load_grid
    except ImportError:
        load_grid = None
    if load_grid is not None and (folder / "grid.json").exists():
        grid = load_grid(folder, load_frames=False)
        return grid.gt_vertices, dict(grid.meta)
    path = folder / "gt_vertices.npy"
    if not path.exists():
        return None, {}
    return read_array(path, "ground-truth vertices", ndim=3, trailing=(3,)).astype(np.float32), {}


def load_captures(root: Path, source: str) -> tuple[dict[str, np.ndarray], dict[str, str], list[Path], str]:
    """Captures of a project: (video_id -> [T, N, 3], video_id -> expression, files read, source used).

    vcdgs: DIR/recon/<id>/vertices.npy of finished jobs (done.json present); gt: the grids'
    ground truth DIR/videos/<id>/gt_vertices.npy; auto: vcdgs when any finished recon exists.
    """
    if source not in SOURCES:
        raise UserError(f"unknown --source {source!r}; use one of {', '.join(SOURCES)}")
    recon_dir = root / "recon"
    recon = (
        sorted(p for p in recon_dir.glob("*/vertices.npy") if (p.parent / "done.json").exists())
        if recon_dir.is_dir()
        else []
    )
    if source == "auto":
        source = "vcdgs" if recon else "gt"
    captures, expressions, files = {}, {}, []
    if source == "vcdgs":
        skipped = (
            sorted(p.parent.name for p in recon_dir.glob("*/vertices.npy") if not (p.parent / "done.json").exists())
            if recon_dir.is_dir()
            else []
        )
        if skipped:
            print(
                f"blendshapes: skipping unfinished reconstructions (no done.json): {', '.join(skipped)}",
                file=sys.stderr,
            )
        if not recon:
            raise UserError(
                f"{root}: no finished reconstructions in recon/ (run `t2bs reconstruct {root}` or use --source gt)"
            )
        for p in recon:
            captures[p.parent.name] = read_array(p, "reconstructed vertices", ndim=3, trailing=(3,)).astype(np.float32)
            files.append(p)
            meta = root / "videos" / p.parent.name / "grid.json"
            if meta.exists():
                expressions[p.parent.name] = (
                    str(json.loads(meta.read_text()).get("meta", {}).get("expression", "")) or None
                )
    else:
        videos = sorted(p for p in (root / "videos").iterdir() if p.is_dir()) if (root / "videos").is_dir() else []
        for folder in videos:
            gt, meta = _grid_gt(folder)
            if gt is None:
                continue
            captures[folder.name] = gt
            if meta.get("expression"):
                expressions[folder.name] = str(meta["expression"])
            files.append(folder / "gt_vertices.npy")
        if not captures:
            raise UserError(f"{root}: no ground-truth captures in videos/*/gt_vertices.npy (run `t2bs videos {root}`)")
    return captures, {k: v for k, v in expressions.items() if v}, files, source


# ------------------------------------------------------------------------------ the stage


def run(project: Project | str | os.PathLike, config: BlendshapesConfig = BlendshapesConfig()) -> BlendshapesResult:
    """PCA blendshape model of every captured frame -> DIR/blendshapes/model.npz + model.glb (paper §3.3).

    Reads DIR/character/mesh.glb (N vertices) and the captures (``load_captures``): with source vcdgs the
    finished reconstructions DIR/recon/<id>/vertices.npy [T, N, 3] (their expressions from
    DIR/videos/<id>/grid.json), with gt the grids' DIR/videos/<id>/gt_vertices.npy [T, N, 3]; auto takes vcdgs
    when any reconstruction is finished. Each frame's head motion is taken out before the PCA.

    Writes one set in DIR/blendshapes/ (done.json last): model.npz (neutral [N, 3], basis [K, N, 3], weights per
    capture, head tracks, named shapes; t2bs.blendshapes.model), model.glb (the character with the visible
    shapes as morph targets, ARKit and named shapes first, and the replayed capture as an animation), model.usdc
    with ``usd``, arkit.json and arkit_sheet.png with ``arkit`` (when the character has landmarks; else one line
    on stderr), stats.json (explained variance, counts, animation). Records the stage in DIR/manifest.json and
    prints a summary line (shapes, frames, explained variance, named shapes) and the files written.

    Raises UserError on a bad setting (components < 1, fps, source, an animation that is no capture), missing
    captures or character, captures that hold no expression, ``usd`` without usd-core, or another t2bs command
    holding the project. A re-run with the same inputs and settings prints ``blendshapes: up to date`` and
    rebuilds nothing (``force`` rebuilds).
    """
    project = project if isinstance(project, Project) else Project(project)
    with project_lock(project.root, "blendshapes"):  # one run at a time per project (issue 39)
        return _run(project, config)


def _run(project: Project, config: BlendshapesConfig) -> BlendshapesResult:
    from t2bs.blendshapes.export import export_glb, export_usd
    from t2bs.blendshapes.model import VISIBLE_FRACTION, build_model, save_model
    from t2bs.blendshapes.semantic import semantic_shapes
    from t2bs.geometry.rigid import remove_motion
    from t2bs.project import OutputSet, content_key, is_done, mark_done, write_json

    components, fps, animation = config.components, config.fps, config.animation
    if components < 1 or not (np.isfinite(fps) and fps > 0):
        raise UserError(f"--components must be >= 1 and --fps a positive number (got {components}, {fps})")
    character = project.load_character()
    captures, expressions, files, used = load_captures(project.root, config.source)
    settings = {
        "components": components,
        "source": used,
        "semantic": config.semantic,
        "animation": animation,
        "usd": config.usd,
        "fps": fps,
        "arkit": config.arkit,
    }
    out = project.path("blendshapes")
    key = content_key(settings, project.mesh_path, *files)
    if not config.force and is_done(out, key) and (out / "model.npz").exists() and (out / "model.glb").exists():
        print(f"blendshapes: up to date ({out})")
        stats = read_json(out / "stats.json") if (out / "stats.json").exists() else {}
        done = read_json(out / "done.json")
        return BlendshapesResult(
            out,
            int(done.get("components", stats.get("components", 0))),
            used,
            stats.get("animation"),
            stats.get("arkit"),
            up_to_date=True,
        )
    t0 = time.time()
    model = build_model(character.vertices, captures, components=components, source=used)
    if not len(model.visible_components()):
        raise UserError(
            f"{project.root}: the captures hold no expression: with each frame's head motion taken out, "
            f"no component moves a vertex by {100 * VISIBLE_FRACTION:.2f} % of the diagonal"
        )
    if config.semantic:  # named shapes from each prompt's non-rigid peak: the captures as seen from the head
        expression_frames = {
            v: remove_motion(*model.head_tracks[v], c).astype(np.float32) if v in model.head_tracks else c
            for v, c in captures.items()
        }
        model.semantic_names, model.semantic_weights, model.semantic_sources = semantic_shapes(
            model, expression_frames, expressions
        )
    if animation is not None and animation not in captures:
        raise UserError(f"--animation {animation!r}: no such capture; have {', '.join(sorted(captures))}")
    replay = animation or max(captures, key=lambda v: float(np.abs(captures[v] - character.vertices).max()))
    staged = OutputSet(out, marker="done.json")  # the files below land in `out` together at commit()
    out = staged.folder
    save_model(model, out / "model.npz")
    shapes = _arkit_shapes(project, model, character, out) if config.arkit else None
    export_glb(model, character, out / "model.glb", capture=replay, fps=fps, arkit=shapes)
    if config.usd:
        try:
            export_usd(model, character, out / "model.usdc", capture=replay, fps=fps, arkit=shapes)
        except ImportError:
            raise UserError("--usd needs usd-core: pip install usd-core") from None
    ev = model.explained_variance
    cum = np.cumsum(ev)
    stats = {
        "source": used,
        "captures": len(captures),
        "frames": model.meta["frames"],
        "rank": model.meta["rank"],
        "components": model.num_components,
        "visible_components": int(len(model.visible_components())),
        "explained_variance": ev,
        "cumulative": cum,
        "semantic": dict(zip(model.semantic_names, model.semantic_sources)),
        "animation": replay,
        "arkit": shapes.names if shapes is not None else None,
        "seconds": round(time.time() - t0, 2),
    }
    write_json(out / "stats.json", stats)
    mark_done(out, key, components=model.num_components, source=used)
    out = staged.commit()
    project.record_stage(
        "blendshapes",
        backend="pca-uncentred",
        config=settings,
        outputs=["blendshapes/model.npz", "blendshapes/model.glb"],
        components=model.num_components,
    )
    at = {k: float(cum[k - 1]) for k in (1, 5, 10, 20, 50, 100) if k < len(cum)}
    at[len(cum)] = float(cum[-1])
    print(
        f"blendshapes: {model.num_components} shapes ({len(model.visible_components())} visible, exported) from "
        f"{model.meta['frames']} frames of {len(captures)} {used} captures "
        f"(rank {model.meta['rank']}); explained variance "
        + ", ".join(f"{k}: {v:.4f}" for k, v in at.items())
        + (f"; named: {', '.join(model.semantic_names)}" if model.semantic_names else "")
    )
    print(f"wrote {out / 'model.npz'} and {out / 'model.glb'} (animation: {replay})")
    arkit_names = list(shapes.names) if shapes is not None else None
    return BlendshapesResult(out, model.num_components, used, replay, arkit_names)


def _arkit_shapes(project, model, character, folder: Path):
    """ARKit shapes of the freshly saved model -> ``folder``/arkit.json (+ arkit_sheet.png): the blendshapes
    stage's staging folder, so they land with the model; None (said in one line) when the character has no
    landmarks to derive them from (a previous arkit.json is then removed)."""
    from t2bs.face.arkit import project_arkit_shapes, summary
    from t2bs.project import write_json

    path = folder / "arkit.json"
    try:
        shapes = project_arkit_shapes(project.root, model, character)
    except UserError as exc:
        project.path("blendshapes", "arkit.json").unlink(missing_ok=True)
        print(f"blendshapes: no ARKit shapes ({exc})", file=sys.stderr)
        return None
    write_json(path, shapes.to_dict())
    print(f"blendshapes: {summary(shapes)} (why each: {project.path('blendshapes', 'arkit.json')})")
    if shapes.names:
        from t2bs.face.arkit import contact_sheet
        from t2bs.project import write_image

        write_image(folder / "arkit_sheet.png", contact_sheet(model, character, shapes))
    return shapes
