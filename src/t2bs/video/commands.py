"""`t2bs videos DIR`: one multi-view grid per (expression prompt, sample) in DIR/videos/<video_id>/.

Backends:
- ``procedural`` (default, offline): the character's own rig animated by the prompt, rendered
  from the orbit cameras with simulated 4D-generator defects; ground-truth vertices kept.
- ``cogvideox``: the fixed-view video from a local CogVideoX-5b-I2V checkpoint (one view; the
  multi-view grid then comes from a 4D video model, see ``--import-grid``).
- ``--import-grid PATH``: bring one grid written by SV4D / any 4D model into the project.

Finished videos are skipped on re-run (content key of the character, prompt and settings in
each video's done.json); an interrupted video is redone.
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path

import typer
from tqdm import tqdm

from t2bs.errors import UserError
from t2bs.geometry.camera import ORBIT_VIEWS, frontal_camera
from t2bs.project import Project, content_key, is_done, mark_done
from t2bs.video.defects import preset
from t2bs.video.grid import import_image_grid, load_grid, save_grid
from t2bs.video.prompts import (EXPRESSIONS, SAMPLES_PER_PROMPT, VideoJob, load_prompt_list, make_jobs,
                                resolve_expressions, slug, video_prompt)
from t2bs.video.sheets import save_contact_sheet
from t2bs.video.synth import GridConfig, check_config, make_grid

GRID_VERSION_KEY = "t2bs-videos-1"  # bump when the animator or defects change what a grid holds


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
    if prompts.strip().lower() != "all" and (path.suffix.lower() in (".txt", ".json") or path.is_file()):
        items = load_prompt_list(path)
        # A video model takes any text; the offline animator checks words when it animates.
        return resolve_expressions(items, allow_custom=True)
    return resolve_expressions(prompts, allow_custom=backend == "cogvideox")


def videos_command(
    project_dir: Path = typer.Argument(..., help="Project folder (with character/mesh.glb)."),
    prompts: str = typer.Option("all", help="all, a comma list of expressions, or a prompt-list file (.txt one per line, .json)."),
    samples: int = typer.Option(SAMPLES_PER_PROMPT, help="Videos per prompt (paper: 3)."),
    defects: str = typer.Option("mild", help="Simulated 4D-generator defects on the side views: clean, mild, paper."),
    frames: int = typer.Option(16, help="Frames per video T (paper's models: 16-49)."),
    size: int = typer.Option(512, help="Frame side in pixels (128 for quick runs)."),
    views: int = typer.Option(ORBIT_VIEWS, help="Orbit views over azimuth -60..60 (odd; paper: 15)."),
    seed: int = typer.Option(0, help="Seed of animation and defects."),
    shading: str = typer.Option("unlit", help="unlit (ambient = 1, the paper's protocol) or lambert."),
    backend: str = typer.Option("procedural", help="procedural (offline, with ground truth) or cogvideox (fixed view only)."),
    checkpoint: Path = typer.Option(None, help="CogVideoX-5b-I2V folder (diffusers layout) for --backend cogvideox."),
    steps: int = typer.Option(50, help="Denoising steps (cogvideox)."),
    import_grid: Path = typer.Option(None, "--import-grid", help="Import a V x T grid (one image, view folders or videos) from a 4D model."),
    expression: str = typer.Option(None, help="Expression of the imported grid (names its folder)."),
    sample: int = typer.Option(0, help="Sample index of the imported grid."),
) -> None:
    """Make the expression videos: one multi-view grid per (prompt, sample) in DIR/videos/."""
    project = Project(project_dir)
    if import_grid is not None:
        _import(project, import_grid, expression, sample, views, frames)
        return
    if backend not in ("procedural", "cogvideox"):
        raise UserError(f"--backend must be procedural or cogvideox, got {backend!r}")
    cfg = GridConfig(frames=frames, size=size, views=views, shading=shading)
    check_config(cfg)
    defect_cfg = preset(defects, seed=seed)
    expressions = parse_expressions(prompts, backend)
    mesh = project.load_character()
    character = character_prompt(project)
    jobs = make_jobs(character, expressions, samples)
    if backend == "cogvideox":
        _cogvideox(project, jobs, checkpoint, cfg, steps, seed)
        return
    from t2bs.video.animator import resolve_expression, usable_rig

    for e in expressions:
        resolve_expression(e)  # unknown words fail before any rendering
    motion, rig_key, autorig_info = "rig", [], None
    if not usable_rig(mesh):
        # A static mesh (scan, sculpt, text-to-3D output) has nothing to play but head turns: build a
        # face rig on it (issue 34) and animate that, so the videos show the expressions.
        from t2bs.rig.commands import project_autorig

        mesh, autorig_info = project_autorig(project, mesh)
        motion, rig_key = "autorig", [project.path("character", "autorig.glb")]
        print(f"videos: the character has no face rig; auto rig: {len(autorig_info['shapes'])} ARKit shapes "
              f"({autorig_info['landmarks']['source']} landmarks) -> {project.path('character', 'autorig.glb')}")
    from t2bs.render.mesh_renderer import MeshRenderer

    t0 = time.perf_counter()
    made, skipped = [], []
    renders = len(jobs) * cfg.views * cfg.frames
    with MeshRenderer() as renderer, tqdm(total=renders, desc="videos", unit="frame") as bar:
        for job in jobs:
            vdir = project.path("videos", job.video_id)
            key = content_key(project.mesh_path, *rig_key, GRID_VERSION_KEY, job.prompt, job.sample, asdict(cfg), asdict(defect_cfg), seed)
            if is_done(vdir, key):
                skipped.append(job.video_id)
                bar.update(cfg.views * cfg.frames)
                continue
            bar.set_postfix_str(job.video_id)
            t1 = time.perf_counter()
            grid = make_grid(mesh, job.expression, job.sample, seed, cfg, defect_cfg, renderer, prompt=job.prompt, progress=bar)
            grid.meta.update({"video_id": job.video_id, "character_prompt": character, "defect_preset": defects,
                              "motion_source": motion})
            save_grid(grid, vdir)
            save_contact_sheet(grid, vdir / "contact_sheet.png")
            mark_done(vdir, key, seconds=round(time.perf_counter() - t1, 3), backend="procedural")
            made.append(job.video_id)
    seconds = time.perf_counter() - t0
    project.record_stage("videos", backend="procedural", config={**asdict(cfg), "defects": defects, "seed": seed, "samples": samples},
                         defects=asdict(defect_cfg), expressions=expressions,
                         videos=[j.video_id for j in jobs], made=len(made), skipped=len(skipped), seconds=round(seconds, 3),
                         motion_source=motion, **({"autorig": {"shapes": autorig_info["shapes"], "landmarks": autorig_info["landmarks"]["source"],
                                                               "missing": autorig_info["missing"], "mouth": autorig_info.get("mouth")}}
                                                  if autorig_info else {}))
    print(f"videos: {len(made)} made, {len(skipped)} up to date, in {project.path('videos')} ({seconds:.1f} s)")


def _cogvideox(project: Project, jobs: list[VideoJob], checkpoint: Path | None, cfg: GridConfig, steps: int, seed: int) -> None:
    from t2bs.video.cogvideox import CogVideoXConfig, check_checkpoint, fixed_view_grid, generate_fixed_view, load_pipeline
    from t2bs.video.grid import read_rgb

    if checkpoint is None:
        raise UserError("--backend cogvideox needs --checkpoint DIR (a local THUDM/CogVideoX-5b-I2V folder)")
    check_checkpoint(checkpoint)
    front_path = project.path("renders", "front.png")
    if not front_path.exists():
        raise UserError(f"{front_path} missing: run `t2bs render` first (the video model starts from the frontal render)")
    front = read_rgb(front_path)
    vcfg = CogVideoXConfig(frames=max(cfg.frames, 9), steps=steps, fps=cfg.fps)
    pipe = None
    for job in tqdm(jobs, desc="videos (cogvideox)", unit="video"):
        vdir = project.path("videos", job.video_id)
        key = content_key(front_path, checkpoint.resolve().as_posix(), job.prompt, job.sample, asdict(vcfg), seed)
        if is_done(vdir, key):
            continue
        pipe = pipe or load_pipeline(checkpoint)
        t1 = time.perf_counter()
        video = generate_fixed_view(pipe, front, job.prompt, vcfg, seed=seed * 1000 + job.sample)
        grid = fixed_view_grid(video, frontal_camera(front.shape[0]), vcfg.fps, {
            "prompt": job.prompt, "expression": job.expression, "sample": job.sample, "seed": seed,
            "video_id": job.video_id, "checkpoint": str(checkpoint), "cogvideox": asdict(vcfg)})
        save_grid(grid, vdir)
        save_contact_sheet(grid, vdir / "contact_sheet.png")
        mark_done(vdir, key, seconds=round(time.perf_counter() - t1, 3), backend="cogvideox")
    project.record_stage("videos", backend="cogvideox", checkpoint=str(checkpoint), config=asdict(vcfg),
                         videos=[j.video_id for j in jobs])


def _import(project: Project, source: Path, expression: str | None, sample: int, views: int, frames: int) -> None:
    if not expression:
        raise UserError("--import-grid needs --expression NAME (the prompt the 4D model animated)")
    expr = resolve_expressions([expression], allow_custom=True)[0]
    video_id = f"{slug(expr)}-s{sample}"
    single = source.is_file()
    grid = import_image_grid(source, views=views if single or views != ORBIT_VIEWS else None,
                             frames=frames if single else None,
                             meta={"expression": expr, "sample": sample, "video_id": video_id,
                                   "prompt": video_prompt(character_prompt(project), expr)})
    vdir = project.path("videos", video_id)
    save_grid(grid, vdir)
    save_contact_sheet(grid, vdir / "contact_sheet.png")
    key = content_key(source, views, frames)
    mark_done(vdir, key, backend=grid.backend)
    load_grid(vdir)  # what the next stage will read: check it now
    print(f"imported {grid.num_views} views x {grid.num_frames} frames into {vdir}")


__all__ = ["videos_command", "EXPRESSIONS"]
