"""The videos stage: one multi-view grid per (expression prompt, sample) in DIR/videos/<video_id>/.

Backends:
- ``procedural`` (default, offline): the character's own rig animated by the prompt, rendered
  from the orbit cameras with simulated 4D-generator defects; ground-truth vertices kept.
- ``cogvideox``: the fixed-view video from a local CogVideoX-5b-I2V checkpoint (one view).
- ``sv4d2``: the paper's 4D stage: the fixed-view video (a one-view cogvideox grid, a procedural
  grid's canonical view, or ``video``) plus the static mesh's orbit renders -> the V x T
  grid from a local SV4D 2.0 checkpoint, by chained passes (docs/SV4D2.md).
- ``import_grid``: bring one grid written by SV4D / any 4D model into the project.

Finished videos are skipped on re-run (content key of the character, prompt and settings in
each video's done.json); an interrupted video is redone. The command line is t2bs.cli.videos.
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from t2bs.errors import UserError
from t2bs.geometry.camera import ORBIT_VIEWS, frontal_camera
from t2bs.project import Project, content_key, is_done, mark_done, output_set, project_lock, read_json
from t2bs.video.defects import preset
from t2bs.video.grid import VIDEO_SUFFIXES, import_image_grid, load_grid, save_grid
from t2bs.video.prompts import (
    SAMPLES_PER_PROMPT,
    VideoJob,
    load_prompt_list,
    make_jobs,
    resolve_expressions,
    slug,
    video_prompt,
)
from t2bs.video.sheets import save_contact_sheet
from t2bs.video.synth import GridConfig, check_config, make_grid

GRID_VERSION_KEY = "t2bs-videos-1"  # bump when the animator or defects change what a grid holds
BACKENDS = ("procedural", "cogvideox", "sv4d2")


@dataclass
class VideosConfig:
    prompts: str = "all"  # "all", a comma list of expressions, or a prompt-list file (.txt one per line, .json)
    samples: int = SAMPLES_PER_PROMPT  # videos per prompt (paper: 3)
    defects: str = "mild"  # simulated 4D-generator defects on the side views: clean, mild or paper
    frames: int = 16  # frames per video T (paper's models: 16-49)
    size: int = 512  # frame side in pixels (128 for quick runs)
    views: int = ORBIT_VIEWS  # orbit views over azimuth -60..60 degrees (odd; paper: 15)
    seed: int = 0  # seed of animation, defects and the video models
    shading: str | None = None  # unlit or lambert; None: unlit (import_grid: required, how its source render was lit)
    backend: str = "procedural"  # procedural (offline, with ground truth), cogvideox (fixed view only) or sv4d2
    checkpoint: Path | None = None  # cogvideox: CogVideoX-5b-I2V folder; sv4d2: folder holding sv4d2.safetensors
    steps: int = 50  # denoising steps (cogvideox; sv4d2 per pass)
    video: Path | None = None  # sv4d2: a fixed-view video file to use instead of the project's (needs expression)
    dtype: str = "auto"  # sv4d2 UNet precision: auto (bf16 on CUDA), float32, bfloat16 or float16
    offload: bool = False  # sv4d2: keep weights on the CPU between parts (GPUs under ~24 GB)
    import_grid: Path | None = None  # a V x T grid to import (one image, view folders or videos) instead of making one
    expression: str | None = None  # expression of the imported grid or of `video` (names its folder)
    sample: int = 0  # sample index of the imported grid or of `video`


@dataclass
class VideosResult:
    backend: str  # procedural, cogvideox, sv4d2, or the imported grid's backend
    videos: list[str] = field(default_factory=list)  # video ids this run covered (folders under DIR/videos/)
    made: list[str] = field(default_factory=list)  # of those, written by this run
    skipped: list[str] = field(default_factory=list)  # of those, already up to date
    folder: Path | None = None  # DIR/videos


def character_prompt(project: Project) -> str:
    """The text the character was made from (manifest), else a neutral description."""
    stages = project.manifest().get("stages", {})
    for stage in ("character", "render"):
        info = stages.get(stage, {})
        for src in (info, info.get("config") or {}):
            if isinstance(src, dict) and isinstance(src.get("prompt"), str) and src["prompt"].strip():
                return src["prompt"].strip()
    return "a 3D character head"


def parse_expressions(prompts: str, backend: str) -> list[str]:
    """'all', a comma list, or a prompt-list file (text or JSON)."""
    path = Path(prompts)
    try:
        is_file = path.is_file()
    except OSError:  # a long prompt list is not a file name (ENAMETOOLONG)
        is_file = False
    if prompts.strip().lower() != "all" and (path.suffix.lower() in (".txt", ".json") or is_file):
        items = load_prompt_list(path)
        # A video model takes any text; the offline animator checks words when it animates.
        return resolve_expressions(items, allow_custom=True)
    return resolve_expressions(prompts, allow_custom=backend == "cogvideox")


def run(project: Project | str | os.PathLike, config: VideosConfig = VideosConfig()) -> VideosResult:
    """Make the expression videos: one multi-view grid per (prompt, sample) in DIR/videos/.

    Reads DIR/character/mesh.glb and the character prompt in DIR/manifest.json (procedural,
    cogvideox); cogvideox also reads DIR/renders/front.png, sv4d2 DIR/renders/cameras.json and
    DIR/renders/orbit/viewVV.png (`t2bs render`) plus each video's fixed-view grid (or
    ``config.video``). A character without a usable face rig is auto-rigged first
    (t2bs.rig.stage.project_autorig: DIR/character/autorig.glb).

    Writes, per video id ``<expression-slug>-s<sample>``, one set in DIR/videos/<id>/ (see
    t2bs.video.grid): frames/viewVV/TTTT.png (V views x T frames, size x size RGB), cameras.json
    (V cameras), masks.npz (``masks`` [V, T, S, S]), gt_vertices.npy [T, N, 3] float32 (procedural
    only: the animated mesh), grid.json (times, canonical view, meta), contact_sheet.png and
    done.json last (the content key). Records the stage in DIR/manifest.json. Prints a progress
    bar and one summary line (``videos: M made, K up to date, in DIR/videos (S s)``).

    ``config.import_grid`` imports one grid instead (``expression`` and ``shading`` required).
    sv4d2 lifts the existing fixed-view grids in place (the 4D grid keeps the key of its source,
    so the fixed-view stage does not redo it).

    Raises UserError on a bad setting (backend, expression, defects, views, frames), a missing
    input (no character, no renders, no checkpoint) or another t2bs command holding the project.
    Re-runs skip videos whose done.json matches the content key (character, rig, prompt, settings,
    seed); a video interrupted while written is redone, its previous version kept until then.
    """
    project = project if isinstance(project, Project) else Project(project)
    with project_lock(project.root, "videos"):  # one run at a time per project (issue 39)
        return _run(project, config)


def _run(project: Project, config: VideosConfig) -> VideosResult:
    c = config
    # Python callers may pass strings for the paths.
    checkpoint, video = (Path(p) if p is not None else None for p in (c.checkpoint, c.video))
    if c.import_grid is not None:
        return _import(project, Path(c.import_grid), c.expression, c.sample, c.views, c.frames, c.shading)
    if c.backend not in BACKENDS:
        raise UserError(f"--backend must be procedural, cogvideox or sv4d2, got {c.backend!r}")
    shading = c.shading or "unlit"
    if c.backend == "sv4d2":
        return _sv4d2(
            project,
            c.prompts,
            c.samples,
            checkpoint,
            c.steps,
            c.seed,
            video,
            c.expression,
            c.sample,
            c.dtype,
            c.offload,
        )
    cfg = GridConfig(frames=c.frames, size=c.size, views=c.views, shading=shading)
    check_config(cfg)
    defect_cfg = preset(c.defects, seed=c.seed)
    expressions = parse_expressions(c.prompts, c.backend)
    mesh = project.load_character()
    character = character_prompt(project)
    jobs = make_jobs(character, expressions, c.samples)
    if c.backend == "cogvideox":
        return _cogvideox(project, jobs, checkpoint, cfg, c.steps, c.seed)
    from t2bs.video.animator import resolve_expression, usable_rig

    for e in expressions:
        resolve_expression(e)  # unknown words fail before any rendering
    motion, rig_key, autorig_info = "rig", [], None
    if not usable_rig(mesh):
        # A static mesh (scan, sculpt, text-to-3D output) has nothing to play but head turns: build a
        # face rig on it (issue 34) and animate that, so the videos show the expressions.
        from t2bs.rig.stage import project_autorig

        mesh, autorig_info = project_autorig(project, mesh)
        motion, rig_key = "autorig", [project.path("character", "autorig.glb")]
        print(
            f"videos: the character has no face rig; auto rig: {len(autorig_info['shapes'])} ARKit shapes "
            f"({autorig_info['landmarks']['source']} landmarks) -> {project.path('character', 'autorig.glb')}"
        )
    from t2bs.render.mesh_renderer import MeshRenderer

    t0 = time.perf_counter()
    made, skipped = [], []
    renders = len(jobs) * cfg.views * cfg.frames
    with MeshRenderer() as renderer, tqdm(total=renders, desc="videos", unit="frame") as bar:
        for job in jobs:
            vdir = project.path("videos", job.video_id)
            key = content_key(
                project.mesh_path,
                *rig_key,
                GRID_VERSION_KEY,
                job.prompt,
                job.sample,
                asdict(cfg),
                asdict(defect_cfg),
                c.seed,
            )
            if _done(vdir, key):
                skipped.append(job.video_id)
                bar.update(cfg.views * cfg.frames)
                continue
            bar.set_postfix_str(job.video_id)
            t1 = time.perf_counter()
            grid = make_grid(
                mesh, job.expression, job.sample, c.seed, cfg, defect_cfg, renderer, prompt=job.prompt, progress=bar
            )
            grid.meta.update(
                {
                    "video_id": job.video_id,
                    "character_prompt": character,
                    "defect_preset": c.defects,
                    "motion_source": motion,
                }
            )
            write_grid_folder(grid, vdir, key, seconds=round(time.perf_counter() - t1, 3), backend="procedural")
            made.append(job.video_id)
    seconds = time.perf_counter() - t0
    autorig = (
        {
            "autorig": {
                "shapes": autorig_info["shapes"],
                "landmarks": autorig_info["landmarks"]["source"],
                "missing": autorig_info["missing"],
                "mouth": autorig_info.get("mouth"),
            }
        }
        if autorig_info
        else {}
    )
    project.record_stage(
        "videos",
        backend="procedural",
        config={**asdict(cfg), "defects": c.defects, "seed": c.seed, "samples": c.samples},
        defects=asdict(defect_cfg),
        expressions=expressions,
        videos=[j.video_id for j in jobs],
        made=len(made),
        skipped=len(skipped),
        seconds=round(seconds, 3),
        motion_source=motion,
        **autorig,
    )
    print(f"videos: {len(made)} made, {len(skipped)} up to date, in {project.path('videos')} ({seconds:.1f} s)")
    return VideosResult("procedural", [j.video_id for j in jobs], made, skipped, project.path("videos"))


def write_grid_folder(grid, vdir: Path, key: str, **info) -> None:
    """The grid, its contact sheet and done.json as one set (project.output_set): a run killed while
    regenerating a grid leaves the previous grid and its done.json as they were, never the old
    done.json beside new, half-written frames."""
    with output_set(vdir, marker="done.json", exclusive=True) as stage:
        save_grid(grid, stage)
        save_contact_sheet(grid, stage / "contact_sheet.png")
        mark_done(stage, key, **info)


def _cogvideox(
    project: Project, jobs: list[VideoJob], checkpoint: Path | None, cfg: GridConfig, steps: int, seed: int
) -> VideosResult:
    from t2bs.video.cogvideox import (
        CogVideoXConfig,
        check_checkpoint,
        fixed_view_grid,
        generate_fixed_view,
        load_pipeline,
    )
    from t2bs.video.grid import read_rgb

    if checkpoint is None:
        raise UserError("--backend cogvideox needs --checkpoint DIR (a local THUDM/CogVideoX-5b-I2V folder)")
    check_checkpoint(checkpoint)
    front_path = project.path("renders", "front.png")
    if not front_path.exists():
        raise UserError(
            f"{front_path} missing: run `t2bs render` first (the video model starts from the frontal render)"
        )
    front = read_rgb(front_path)
    vcfg = CogVideoXConfig(frames=max(cfg.frames, 9), steps=steps, fps=cfg.fps)
    pipe = None
    made, skipped = [], []
    for job in tqdm(jobs, desc="videos (cogvideox)", unit="video"):
        vdir = project.path("videos", job.video_id)
        key = content_key(front_path, checkpoint.resolve().as_posix(), job.prompt, job.sample, asdict(vcfg), seed)
        if _done(vdir, key):
            skipped.append(job.video_id)
            continue
        pipe = pipe or load_pipeline(checkpoint)
        t1 = time.perf_counter()
        video = generate_fixed_view(pipe, front, job.prompt, vcfg, seed=seed * 1000 + job.sample)
        grid = fixed_view_grid(
            video,
            frontal_camera(front.shape[0]),
            vcfg.fps,
            {
                "prompt": job.prompt,
                "expression": job.expression,
                "sample": job.sample,
                "seed": seed,
                "video_id": job.video_id,
                "checkpoint": str(checkpoint),
                "cogvideox": asdict(vcfg),
            },
        )
        write_grid_folder(grid, vdir, key, seconds=round(time.perf_counter() - t1, 3), backend="cogvideox")
        made.append(job.video_id)
    project.record_stage(
        "videos",
        backend="cogvideox",
        checkpoint=str(checkpoint),
        config=asdict(vcfg),
        videos=[j.video_id for j in jobs],
    )
    return VideosResult("cogvideox", [j.video_id for j in jobs], made, skipped, project.path("videos"))


def _sv4d2(
    project: Project,
    prompts: str,
    samples: int,
    checkpoint: Path | None,
    steps: int,
    seed: int,
    video: Path | None,
    expression: str | None,
    sample: int,
    dtype: str,
    offload: bool,
) -> VideosResult:
    from t2bs.geometry.camera import Camera, canonical_view_index, orbit_azimuths
    from t2bs.video.grid import VideoGrid, masks_from_frames, read_rgb, read_video
    from t2bs.video.sv4d2 import SV4D2GridConfig, check_checkpoint, load_model, make_grid_frames

    if checkpoint is None:
        raise UserError(
            "--backend sv4d2 needs --checkpoint DIR (a folder holding sv4d2.safetensors from stabilityai/sv4d2.0)"
        )
    ckpt_file = check_checkpoint(checkpoint)
    # The static mesh's fixed-time orbit (frame 0 of every view) and its cameras, from `t2bs render`.
    cams_path = project.path("renders", "cameras.json")
    if not cams_path.exists():
        raise UserError(
            f"{cams_path} missing: run `t2bs render` first "
            f"(SV4D 2.0 starts every view from the mesh's orbit renders)"
        )
    try:
        cameras = [Camera.from_dict(c) for c in read_json(cams_path)["orbit"]]
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(f"{cams_path}: unreadable orbit cameras ({exc})") from None
    nv = len(cameras)
    orbit = np.stack(
        [read_rgb(project.path("renders", "orbit", f"view{v:02d}.png")) for v in range(nv)]
    )  # [V, S, S, 3]
    size = orbit.shape[1]
    canonical = canonical_view_index(nv)
    azimuths = orbit_azimuths(nv)
    render_cfg = (project.manifest().get("stages", {}).get("render") or {}).get("config") or {}
    shading = render_cfg.get("shading", "lambert") if isinstance(render_cfg, dict) else "lambert"
    gcfg = SV4D2GridConfig(steps=steps, seed=seed, dtype=dtype, offload=offload)
    sources = []  # (video_id, expression, sample, prompt, frames [T, S, S, 3], times [T], source meta, gt)
    character = character_prompt(project)
    if video is not None:
        if not expression:
            raise UserError("--video needs --expression NAME (the expression the video shows; names its folder)")
        expr = resolve_expressions([expression], allow_custom=True)[0]
        frames = _square(read_video(video), size)
        fps = _video_fps(video)
        sources.append(
            (
                f"{slug(expr)}-s{sample}",
                expr,
                sample,
                video_prompt(character, expr),
                frames,
                (np.arange(len(frames)) / fps).astype(np.float32),
                {"source": str(video), "backend": "file"},
                None,
            )
        )
    else:
        for job in make_jobs(character, parse_expressions(prompts, "cogvideox"), samples):
            vdir = project.path("videos", job.video_id)
            if not (vdir / "grid.json").exists():
                raise UserError(
                    f"{vdir}: no fixed-view video for {job.video_id}: make it first "
                    f"(`t2bs videos DIR --backend cogvideox ...`, or the procedural backend) "
                    f"or pass --video FILE --expression NAME"
                )
            src = load_grid(vdir)
            frames = _square(src.canonical_frames(), size)
            info = {"backend": src.meta.get("source_backend", src.backend), "video_id": job.video_id}
            sources.append(
                (job.video_id, job.expression, job.sample, job.prompt, frames, src.times, info, src.gt_vertices)
            )
    model = None
    made, skipped = [], []
    t0 = time.perf_counter()
    for video_id, expr, smp, prompt, frames, times, src_info, gt in sources:
        vdir = project.path("videos", video_id)
        key = content_key(
            ckpt_file.resolve().as_posix(), os.path.getsize(ckpt_file), frames, orbit, asdict(gcfg), "t2bs-sv4d2-1"
        )
        if is_done(vdir, key):
            skipped.append(video_id)
            continue
        if model is None:
            model = load_model(checkpoint, dtype=dtype, offload=offload)
        t1 = time.perf_counter()
        with tqdm(desc=f"sv4d2 {video_id}", unit="pass") as bar:

            def step(k, n):
                bar.total = n
                bar.update(1)

            grid_frames, passes = make_grid_frames(model, frames, orbit, azimuths, canonical, gcfg, progress=step)
        meta = {
            "prompt": prompt,
            "expression": expr,
            "sample": smp,
            "video_id": video_id,
            "seed": seed,
            "checkpoint": str(ckpt_file),
            "source_backend": src_info.get("backend"),
            "input": src_info,
            "sv4d2": asdict(gcfg),
            "passes": [{"frames": [p.frames[0], p.frames[-1]], "views": p.views} for p in passes],
            "grid_config": {"shading": shading, "size": size, "views": nv, "frames": len(frames)},
            "masks_from": "background key",
            "licence": "Stability AI Community License (SV4D 2.0 outputs)",
        }
        grid = VideoGrid(
            grid_frames,
            cameras,
            np.asarray(times, np.float32),
            canonical,
            masks_from_frames(grid_frames),
            gt,
            "sv4d2",
            meta,
        ).validate("sv4d2 grid")
        prior = read_json(vdir / "done.json") if (vdir / "done.json").exists() else {}
        source_key = prior.get("source_key") if prior.get("backend") == "sv4d2" else prior.get("key")
        write_grid_folder(
            grid, vdir, key, seconds=round(time.perf_counter() - t1, 3), backend="sv4d2", source_key=source_key
        )
        made.append(video_id)
    seconds = time.perf_counter() - t0
    # Keep what made the fixed-view videos (backend, checkpoint) in the record: the report names both.
    prev = project.manifest().get("stages", {}).get("videos") or {}
    fixed_view = prev.get("fixed_view_stage") if prev.get("backend") == "sv4d2" else prev
    fixed_view = (
        {k: fixed_view[k] for k in ("backend", "checkpoint", "config") if k in fixed_view} if fixed_view else None
    )
    if video is not None:
        fixed_view = {"backend": "file", "checkpoint": None, "config": {"video": str(video)}}
    project.record_stage(
        "videos",
        backend="sv4d2",
        checkpoint=str(ckpt_file),
        config=asdict(gcfg),
        fixed_view_stage=fixed_view,
        videos=[s[0] for s in sources],
        made=len(made),
        skipped=len(skipped),
        inputs={s[0]: s[6].get("backend") for s in sources},
        seconds=round(seconds, 3),
    )
    print(
        f"videos (sv4d2): {len(made)} made, {len(skipped)} up to date, {nv} views each, in {project.path('videos')} "
        f"({seconds:.1f} s)"
    )
    return VideosResult("sv4d2", [s[0] for s in sources], made, skipped, project.path("videos"))


def _video_fps(path: Path) -> float:
    """Frame rate of a video file (its time stamps), from its metadata; 8 fps said aloud when absent."""
    import imageio.v3 as iio

    try:
        fps = float(iio.immeta(path).get("fps") or 0)
    except Exception:  # imageio raises many types for containers without metadata
        fps = 0.0
    if not np.isfinite(fps) or fps <= 0:
        print(f"{path}: no frame rate in the file; time stamps at 8 fps")
        return 8.0
    return fps


def _done(vdir: Path, key: str) -> bool:
    """Finished for ``key``, or since lifted to a 4D grid from exactly that fixed-view video (kept:
    the 4D grid's canonical view is that video, and redoing it would undo the 4D stage)."""
    if is_done(vdir, key):
        return True
    marker = vdir / "done.json"
    try:
        return marker.exists() and read_json(marker).get("source_key") == key
    except (ValueError, OSError):
        return False


def _square(frames: np.ndarray, size: int) -> np.ndarray:
    """[T, H, W, 3] -> [T, size, size, 3]: centre square crop, resized (the render's framing)."""
    from PIL import Image

    frames = np.asarray(frames, np.uint8)
    h, w = frames.shape[1:3]
    side = min(h, w)
    y0, x0 = (h - side) // 2, (w - side) // 2
    crop = frames[:, y0 : y0 + side, x0 : x0 + side]
    if side == size:
        return np.ascontiguousarray(crop)
    return np.stack([np.asarray(Image.fromarray(f).resize((size, size), Image.BICUBIC)) for f in crop])


def _import(
    project: Project, source: Path, expression: str | None, sample: int, views: int, frames: int, shading: str | None
) -> VideosResult:
    if not expression:
        raise UserError("--import-grid needs --expression NAME (the prompt the 4D model animated)")
    if shading not in ("unlit", "lambert"):
        raise UserError(
            "--import-grid needs --shading unlit or lambert: how the mesh render the 4D model started from "
            "was lit (VCDGS fits its static Gaussians to mesh renders lit the same way)"
        )
    expr = resolve_expressions([expression], allow_custom=True)[0]
    video_id = f"{slug(expr)}-s{sample}"
    single = source.is_file()
    # A flat folder of images needs a view count, so --views counts even at its default (15);
    # view sub-folders and view videos carry their own count, checked only when --views is changed.
    flat = source.is_dir() and not any(p.is_dir() or p.suffix.lower() in VIDEO_SUFFIXES for p in source.iterdir())
    grid = import_image_grid(
        source,
        views=views if single or flat or views != ORBIT_VIEWS else None,
        frames=frames if single else None,
        meta={
            "expression": expr,
            "sample": sample,
            "video_id": video_id,
            "prompt": video_prompt(character_prompt(project), expr),
        },
        shading=shading,
    )
    vdir = project.path("videos", video_id)
    write_grid_folder(grid, vdir, content_key(source, views, frames, shading), backend=grid.backend)
    load_grid(vdir)  # what the next stage will read: check it now
    print(
        f"imported {grid.num_views} views x {grid.num_frames} frames into {vdir} "
        f"(masks from {grid.meta['masks_from']}, shading {shading})"
    )
    return VideosResult(grid.backend, [video_id], [video_id], [], project.path("videos"))
