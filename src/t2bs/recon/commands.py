"""`t2bs reconstruct DIR`: VCDGS on every expression grid of a project (paper §3.2).

For each DIR/videos/<video_id>/ (a VideoGrid folder) writes DIR/recon/<video_id>/:
vertices.npy [T, N, 3] (canonical view, the character's topology), animation.glb, state.pt,
preview.mp4, metrics.json and, last, done.json. Finished videos whose inputs and settings are
unchanged are skipped; a video interrupted mid-training continues from its checkpoint.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import typer

from t2bs.errors import UserError
from t2bs.distributed import Job, run_jobs
from t2bs.project import Project, content_key
from t2bs.recon.config import METHODS, PRESETS, VCDGSConfig, parse_options, preset
from t2bs.project import locked


def list_videos(project: Project, videos: list[str] | None) -> list[Path]:
    """Grid folders of the project, optionally filtered by id (UserError for unknown ids)."""
    root = project.path("videos")
    found = sorted(p for p in root.glob("*") if (p / "grid.json").exists()) if root.is_dir() else []
    if not found:
        raise UserError(f"{project.root}: no video grids in videos/ (run `t2bs videos {project.root}` first)")
    if videos:
        wanted = [v for item in videos for v in item.split(",") if v]
        by_id = {p.name: p for p in found}
        missing = [v for v in wanted if v not in by_id]
        if missing:
            raise UserError(f"unknown video id {missing[0]!r}; have {', '.join(sorted(by_id))}")
        found = [by_id[v] for v in wanted]
    return found


def job_metrics(result, mesh, grid, cfg: VCDGSConfig) -> dict:
    """metrics.json: losses, time, which perceptual loss ran; expression and geometry errors when the grid has GT."""
    from t2bs.recon.vcdgs import evaluate_image_loss

    m = {"method": cfg.method, "seconds": round(result.seconds, 2), "perceptual_loss": result.loss_kind,
         "iterations": cfg.iterations, "steps_run": result.history.get("steps_run"),
         "stopped_at_budget": result.history.get("stopped_at_budget") is not None,
         "control_points": cfg.num_control_points, "resolution": cfg.resolution,
         "face_gaussians": 0 if result.model.faces is None else int(result.model.faces.shape[0]),  # after max_face_gaussians
         "track_weight": cfg.track_weight,  # 0 = the paper's loss alone
         "track_chain": cfg.track_chain,  # tracks chained frame to frame where the direct flow fails
         "track_flow_size": cfg.track_flow_size,  # px the flow ran at (upsampled from the training images)
         "hidden_pick": result.hidden_pick,  # hidden parts' motion picked by render (HiddenPick.summary(); None: off)
         # share of (view, frame, vertex) entries with a valid optical-flow track
         "track_coverage": None if result.data.tracks is None else round(result.data.tracks.coverage(), 4),
         "first_train_loss": result.history.get("first_image_loss"), "final_train_loss": result.history.get("final_image_loss"),
         "huber_static": evaluate_image_loss(result.model, result.data, cfg, deformed=False),
         "huber_recon": evaluate_image_loss(result.model, result.data, cfg, deformed=True)}
    if grid.gt_vertices is not None:
        from t2bs.geometry.metrics import expression_metrics, geometry_metrics

        static = np.repeat(mesh.vertices[None], grid.num_frames, axis=0)
        # The expression with each frame's head motion taken out (expr_rigid: the rigid oracle's error, a perfect
        # head tracker with a neutral face); then p2p over everything that moves, head motion included.
        m["expression"] = expression_metrics(result.vertices, grid.gt_vertices, mesh.vertices)
        m["geometry"] = geometry_metrics(result.vertices, grid.gt_vertices, mesh.vertices, mesh.faces)
        m["geometry_static"] = geometry_metrics(static, grid.gt_vertices, mesh.vertices, mesh.faces)
    return m


def recon_job(project: Project, grid_dir: Path, cfg: VCDGSConfig, preview: bool = True) -> Job:
    """The job of one video: keyed by the grid, the character and the settings."""
    key = content_key(grid_dir, project.mesh_path, cfg.to_dict())
    return Job(key=key, name=f"recon/{grid_dir.name}", out_dir=project.path("recon", grid_dir.name),
               fn="t2bs.recon.commands:run_recon_job",
               kwargs={"project_dir": str(project.root), "grid_dir": str(grid_dir), "cfg": cfg.to_dict(),
                       "preview": preview, "key": key},
               num_gpus=1.0 if cfg.device == "cuda" else 0.0)


def run_recon_job(staging: Path, project_dir: str, grid_dir: str, cfg: dict, preview: bool, key: str,
                  progress: bool = True) -> dict:
    """Executor entry point: VCDGS on one grid, outputs written into ``staging``.

    The training checkpoint lives outside the per-attempt staging folder (recon/.checkpoints/,
    named by the job key), so an attempt killed mid-training resumes where it stopped.
    """
    from t2bs.recon.extract import write_outputs
    from t2bs.recon.vcdgs import reconstruct_grid
    from t2bs.video.grid import load_grid

    cfg = VCDGSConfig(**{**cfg, "holdout_views": tuple(cfg.get("holdout_views", ()))})
    project = Project(project_dir)
    mesh = project.load_character()
    grid = load_grid(grid_dir)
    if grid.gt_vertices is not None and grid.gt_vertices.shape[1] != mesh.num_vertices:
        raise UserError(f"{grid_dir}: ground truth has {grid.gt_vertices.shape[1]} vertices, the character {mesh.num_vertices}")
    ckpt = project.path("recon", ".checkpoints", f"{Path(grid_dir).name}-{key}.pt")
    ckpt.parent.mkdir(parents=True, exist_ok=True)
    result = reconstruct_grid(mesh, grid, cfg, progress=progress, checkpoint=ckpt, key=key)
    metrics = job_metrics(result, mesh, grid, cfg)
    write_outputs(staging, mesh, grid, result, cfg, metrics, preview=preview)
    ckpt.unlink(missing_ok=True)
    return {"method": cfg.method, "train_seconds": round(result.seconds, 2)}


def reconstruct_video(project: Project, grid_dir: Path, cfg: VCDGSConfig, progress: bool = True,
                      preview: bool = True) -> tuple[Path, bool]:
    """One VCDGS job in this process (resumable). Returns (output folder, whether it ran)."""
    job = recon_job(project, grid_dir, cfg, preview)
    job.kwargs["progress"] = progress
    return job.out_dir, bool(run_jobs([job], desc="reconstruct"))


@locked("project_dir", "reconstruct")  # one run at a time per project (issue 39)
def reconstruct_command(
    project_dir: Path = typer.Argument(..., help="Project folder with character/mesh.glb and videos/<id>/ grids."),
    videos: list[str] = typer.Option(None, "--videos", help="Video ids to reconstruct (repeat or comma-separate); default all."),
    preset_name: str = typer.Option("quick", "--preset", help=f"Settings: {' | '.join(PRESETS)} (quick = CPU minutes, paper = GPU, §4.1)."),
    method: str = typer.Option("full", help=f"Method or ablation: {' | '.join(METHODS)}."),
    iterations: int = typer.Option(0, help="Override the preset's training steps (0 = preset)."),
    control_points: int = typer.Option(0, help="Override the number of control points (0 = preset)."),
    track_weight: float = typer.Option(None, help="Weight of the optical-flow vertex-track term (0 = the paper's loss alone; default: the preset's)."),
    face_gaussians: int = typer.Option(-1, help="Face Gaussians on at most this many of the largest triangles (0 = every triangle; -1 = the preset's: quick 10000, paper all)."),
    hidden_pick: bool = typer.Option(None, "--hidden-pick/--no-hidden-pick", help="After training, parts no training view sees at rest (teeth, a mouth bag) may take a seen cluster's rigid motion, picked by render in groups by where they lie across the opening that reveals them (recon/hidden_parts.py; where nothing opens, nothing moves; default: the preset's, on)."),
    device: str = typer.Option("auto", help="auto | cpu | cuda."),
    lpips_weights: str = typer.Option("", help="Local LPIPS weights (file or folder; LPIPS lin layers BSD-2-Clause, AlexNet features BSD-3-Clause); default D-SSIM."),
    no_preview: bool = typer.Option(False, "--no-preview", help="Skip preview.mp4."),
    seed: int = typer.Option(0, help="Seed of sampling and initialisation."),
    workers: int = typer.Option(1, help="Videos reconstructed in parallel on this machine (process pool)."),
    ray: str = typer.Option(None, "--ray", help="Run the jobs on Ray: 'auto', 'local' or host:port."),
    set_options: list[str] = typer.Option(None, "--set", help="Any VCDGS option as KEY=VALUE (repeat; a field of t2bs.recon.config.VCDGSConfig, e.g. --set knn=4); applied after the options above."),
) -> None:
    """Recover per-frame meshes from each multi-view grid with VCDGS (resumable)."""
    extra = parse_options(set_options or [])
    project = Project(project_dir)
    if not project.mesh_path.exists():
        raise UserError(f"{project_dir}: no character/mesh.glb (run `t2bs render MESH -o {project_dir}` first)")
    overrides: dict = {"method": method, "device": device, "seed": seed}
    if iterations:
        overrides["iterations"] = iterations
        overrides["global_iters"] = min(PRESETS[preset_name].global_iters if preset_name in PRESETS else 0, iterations // 5)
    if control_points:
        overrides["num_control_points"] = control_points
    if lpips_weights:
        overrides["lpips_weights"] = lpips_weights
    if track_weight is not None:
        overrides["track_weight"] = track_weight
    if hidden_pick is not None:
        overrides["hidden_pick"] = hidden_pick
    if face_gaussians >= 0:
        overrides["max_face_gaussians"] = face_gaussians
    if workers < 1:
        raise UserError(f"--workers must be >= 1, got {workers}")
    if workers > 1:  # parallel jobs share the cores instead of oversubscribing them
        overrides["threads"] = max(1, (os.cpu_count() or 1) // workers)
    overrides.update(extra)
    cfg = preset(preset_name, **overrides)
    if cfg.device != "auto":
        from t2bs.recon.vcdgs import check_device

        check_device(cfg.device)  # before any job starts (a worker would fail each video in turn)
    grids = list_videos(project, videos)
    t0 = time.time()
    jobs = [recon_job(project, g, cfg, preview=not no_preview) for g in grids]
    executor = "ray" if ray else ("process" if workers > 1 else "local")
    ran = run_jobs(jobs, executor=executor, workers=workers, ray_address=ray, desc="reconstruct")
    done = [g.name for g in grids]
    print(f"reconstruct: {len(ran)} reconstructed, {len(jobs) - len(ran)} up to date, in {project.path('recon')}", flush=True)
    project.record_stage("recon", backend="vcdgs", config=cfg.to_dict(), preset=preset_name, videos=done,
                         ran=len(ran), executor=executor, seconds=round(time.time() - t0, 2))
