"""The reconstruct stage: VCDGS on every expression grid of a project (paper §3.2); `t2bs reconstruct DIR`.

from t2bs.recon.stage import ReconstructConfig, run
run("runs/fox", ReconstructConfig(preset_name="quick", iterations=300))
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from dataclasses import dataclass, field

import numpy as np

from t2bs.distributed import Job, run_jobs
from t2bs.errors import UserError
from t2bs.project import Project, content_key, project_lock
from t2bs.recon.config import VCDGSConfig, iteration_overrides, preset


@dataclass
class ReconstructConfig:
    videos: tuple[str, ...] = ()  # video ids to reconstruct (each may be a comma list); empty = every grid
    preset_name: str = "quick"  # VCDGS settings: quick (CPU minutes) | paper (GPU, §4.1)
    method: str = "full"  # method or ablation: full | no_view | no_refine | no_lbs | no_global
    iterations: int = 0  # training steps (0 = the preset's; the warm-up then becomes min(preset's, iterations // 5))
    control_points: int = 0  # number of control points (0 = the preset's)
    track_weight: float | None = None  # weight of the optical-flow vertex-track term (None = the preset's)
    face_gaussians: int = -1  # face Gaussians on at most this many of the largest triangles (0 = all, -1 = preset's)
    hidden_pick: bool | None = None  # hidden parts' motion picked by render after training (None = the preset's)
    device: str = "auto"  # auto | cpu | cuda
    lpips_weights: str = ""  # local LPIPS weights, file or folder (empty: D-SSIM)
    preview: bool = True  # write recon/<video>/preview.mp4
    seed: int = 0  # seed of sampling and initialisation
    workers: int = 1  # videos reconstructed in parallel on this machine (process pool)
    ray: str | None = None  # run the jobs on Ray: auto | local | host:port (None: on this machine)
    options: dict = field(default_factory=dict)  # any VCDGS field by name (t2bs.recon.config), applied last


@dataclass
class ReconstructResult:
    videos: list[str]  # the video ids of this run
    ran: int  # how many were reconstructed now (the others were up to date)
    config: VCDGSConfig  # the resolved VCDGS settings
    out_dir: Path  # DIR/recon


def vcdgs_config(config: ReconstructConfig) -> VCDGSConfig:
    """The VCDGS settings a ReconstructConfig asks for: the preset, the named fields, then ``options``."""
    overrides: dict = {"method": config.method, "device": config.device, "seed": config.seed}
    overrides.update(iteration_overrides(config.preset_name, config.iterations))
    if config.control_points:
        overrides["num_control_points"] = config.control_points
    if config.lpips_weights:
        overrides["lpips_weights"] = config.lpips_weights
    if config.track_weight is not None:
        overrides["track_weight"] = config.track_weight
    if config.hidden_pick is not None:
        overrides["hidden_pick"] = config.hidden_pick
    if config.face_gaussians >= 0:
        overrides["max_face_gaussians"] = config.face_gaussians
    if config.workers < 1:
        raise UserError(f"--workers must be >= 1, got {config.workers}")
    if config.workers > 1:  # parallel jobs share the cores instead of oversubscribing them
        overrides["threads"] = max(1, (os.cpu_count() or 1) // config.workers)
    overrides.update(config.options)
    return preset(config.preset_name, **overrides)


def list_videos(project: Project, videos: tuple[str, ...] | list[str] | None) -> list[Path]:
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

    m = {
        "method": cfg.method,
        "seconds": round(result.seconds, 2),
        # seconds of data, tracks, basis, model (static fit), train, extract, pick; expression_picks and
        # track_refits: seconds inside train
        "phases": result.phases,
        "perceptual_loss": result.loss_kind,
        "iterations": cfg.optim.iterations,
        "steps_run": result.history.get("steps_run"),
        "joint_ms_per_step": result.history.get("joint_ms_per_step"),  # after the joint stage's first 50 steps
        "step_kind": result.history.get("step_kind"),  # eager | compiled | compiled, CUDA graphs
        "compile_s": result.history.get("compile_s"),  # the compiled graphs' first steps (not in the time budget)
        "stopped_at_budget": result.history.get("stopped_at_budget") is not None,
        "control_points": cfg.control_points.num_control_points,
        "resolution": cfg.data.resolution,
        "face_gaussians": 0
        if result.model.faces is None
        else int(result.model.faces.shape[0]),  # after max_face_gaussians
        "track_weight": cfg.tracks.track_weight,  # 0 = the paper's loss alone
        "track_chain": cfg.tracks.track_chain,  # tracks chained frame to frame where the direct flow fails
        "track_flow_size": cfg.tracks.track_flow_size,  # px the flow ran at (upsampled from the training images)
        "hidden_pick": result.hidden_pick,  # hidden parts' motion picked by render (HiddenPick.summary(); None: off)
        # the expression basis (recon/expression_basis.py): auto-rig shapes used, where the face came from, weights
        "expression_basis": result.expression,
        # share of (view, frame, vertex) entries with a valid optical-flow track
        "track_coverage": None if result.data.tracks is None else round(result.data.tracks.coverage(), 4),
        "first_train_loss": result.history.get("first_image_loss"),
        "final_train_loss": result.history.get("final_image_loss"),
        "huber_static": evaluate_image_loss(result.model, result.data, cfg, deformed=False),
        "huber_recon": evaluate_image_loss(result.model, result.data, cfg, deformed=True),
    }
    if grid.gt_vertices is not None:
        from t2bs.geometry.metrics import expression_metrics, geometry_metrics

        static = np.repeat(mesh.vertices[None], grid.num_frames, axis=0)
        # The expression with each frame's head motion taken out (expr_rigid: the rigid oracle's error, a perfect
        # head tracker with a neutral face); then p2p over everything that moves, head motion included.
        m["expression"] = expression_metrics(result.vertices, grid.gt_vertices, mesh.vertices)
        m["geometry"] = geometry_metrics(result.vertices, grid.gt_vertices, mesh.vertices, mesh.faces)
        m["geometry_static"] = geometry_metrics(static, grid.gt_vertices, mesh.vertices, mesh.faces)
    return m


def budget_cut(video: str, info: dict, cfg: VCDGSConfig, project_root: Path) -> str | None:
    """One line naming a video whose time budget ended its training before the last step, else None. ``info``: what
    its job returned (``run_recon_job``; empty for a video not run now).

    The schedule then shrinks to the steps the machine managed, so the result depends on the machine's speed: on one
    2.1x slower than session 45's the demo fox's smile ran 407 of 800 steps and read 0.506 of the rigid oracle's error
    instead of 0.434 (docs/BENCHMARKS.md, "The demo, from a fresh clone")."""
    if not info.get("stopped_at_budget"):
        return None
    return (
        f"{video}: the time budget ({cfg.optim.time_budget_s:g} s a video) ended training at step "
        f"{info.get('steps_run')} of {cfg.optim.iterations}; `t2bs reconstruct {project_root} --set time_budget_s=0` "
        "runs every step (slower; the result then does not depend on the machine's speed)"
    )


def recon_job(project: Project, grid_dir: Path, cfg: VCDGSConfig, preview: bool = True) -> Job:
    """The job of one video: keyed by the grid, the character and the settings (and, with an expression basis,
    the auto rig's version and the user's face points)."""
    basis = ()
    if cfg.model.expression_shapes:
        from t2bs.rig.pick import picked_landmarks
        from t2bs.rig.stage import AUTORIG_VERSION

        picked = picked_landmarks(project)
        basis = (AUTORIG_VERSION, *([picked] if picked else []))
    key = content_key(grid_dir, project.mesh_path, cfg.to_dict(), *basis)
    return Job(
        key=key,
        name=f"recon/{grid_dir.name}",
        out_dir=project.path("recon", grid_dir.name),
        fn="t2bs.recon.stage:run_recon_job",
        kwargs={
            "project_dir": str(project.root),
            "grid_dir": str(grid_dir),
            "cfg": cfg.to_dict(),
            "preview": preview,
            "key": key,
        },
        num_gpus=1.0 if cfg.runtime.device == "cuda" else 0.0,
    )


def run_recon_job(
    staging: Path, project_dir: str, grid_dir: str, cfg: dict, preview: bool, key: str, progress: bool = True
) -> dict:
    """Executor entry point: VCDGS on one grid, outputs written into ``staging``.

    The training checkpoint lives outside the per-attempt staging folder (recon/.checkpoints/,
    named by the job key), so an attempt killed mid-training resumes where it stopped.
    """
    from t2bs.recon.extract import write_outputs
    from t2bs.recon.vcdgs import reconstruct_grid
    from t2bs.video.grid import load_grid

    cfg = VCDGSConfig.from_dict(cfg)
    project = Project(project_dir)
    mesh = project.load_character()
    grid = load_grid(grid_dir)
    if grid.gt_vertices is not None and grid.gt_vertices.shape[1] != mesh.num_vertices:
        raise UserError(
            f"{grid_dir}: ground truth has {grid.gt_vertices.shape[1]} vertices, the character {mesh.num_vertices}"
        )
    ckpt = project.path("recon", ".checkpoints", f"{Path(grid_dir).name}-{key}.pt")
    ckpt.parent.mkdir(parents=True, exist_ok=True)
    from t2bs.rig.pick import picked_landmarks

    result = reconstruct_grid(
        mesh, grid, cfg, progress=progress, checkpoint=ckpt, key=key, landmarks_file=picked_landmarks(project)
    )
    metrics = job_metrics(result, mesh, grid, cfg)
    write_outputs(staging, mesh, grid, result, cfg, metrics, preview=preview)
    ckpt.unlink(missing_ok=True)
    return {
        "method": cfg.method,
        "train_seconds": round(result.seconds, 2),
        "steps_run": metrics["steps_run"],
        "stopped_at_budget": metrics["stopped_at_budget"],
    }


def reconstruct_video(
    project: Project, grid_dir: Path, cfg: VCDGSConfig, progress: bool = True, preview: bool = True
) -> tuple[Path, bool]:
    """One VCDGS job in this process (resumable). Returns (output folder, whether it ran)."""
    job = recon_job(project, grid_dir, cfg, preview)
    job.kwargs["progress"] = progress
    return job.out_dir, bool(run_jobs([job], desc="reconstruct"))


def run(project: Project | str | os.PathLike, config: ReconstructConfig = ReconstructConfig()) -> ReconstructResult:
    """Recover per-frame meshes from each multi-view expression grid of a project with VCDGS.

    Reads DIR/character/mesh.glb (the character, N vertices) and every DIR/videos/<id>/ grid (``config.videos``
    picks some). For each video writes DIR/recon/<id>/: vertices.npy [T, N, 3] float32 (the per-frame meshes in
    the character's topology and canonical frame), animation.glb (the mesh with one morph target per frame),
    state.pt (the trained model and its config), preview.mp4 (unless ``config.preview`` is off), metrics.json
    (losses, seconds; expression and geometry errors when the grid carries ground truth) and, last, done.json.

    A video whose grid, character and resolved settings are unchanged is skipped; one interrupted mid-training
    continues from its checkpoint (DIR/recon/.checkpoints/). Jobs run here, in ``config.workers`` processes or on
    Ray. Holds the project lock. Raises UserError for a project without a character or grids, an unknown video
    id or preset, a bad VCDGS option, or a CUDA device this machine lacks. Returns the resolved settings and how
    many videos ran."""
    project = project if isinstance(project, Project) else Project(project)
    with project_lock(project.root, "reconstruct"):
        if not project.mesh_path.exists():
            raise UserError(f"{project.root}: no character/mesh.glb (run `t2bs render MESH -o {project.root}` first)")
        cfg = vcdgs_config(config)
        if cfg.runtime.device != "auto":
            from t2bs.recon.vcdgs import check_device

            check_device(cfg.runtime.device)  # before any job starts (a worker would fail each video in turn)
        grids = list_videos(project, config.videos)
        t0 = time.time()
        jobs = [recon_job(project, g, cfg, preview=config.preview) for g in grids]
        executor = "ray" if config.ray else ("process" if config.workers > 1 else "local")
        ran = run_jobs(jobs, executor=executor, workers=config.workers, ray_address=config.ray, desc="reconstruct")
        done = [g.name for g in grids]
        print(
            f"reconstruct: {len(ran)} reconstructed, {len(jobs) - len(ran)} up to date, in {project.path('recon')}",
            flush=True,
        )
        for job in jobs:
            cut = budget_cut(job.out_dir.name, ran.get(job.name, {}), cfg, project.root)
            if cut:
                print(f"reconstruct: {cut}", flush=True)
        project.record_stage(
            "recon",
            backend="vcdgs",
            config=cfg.to_dict(),
            preset=config.preset_name,
            videos=done,
            ran=len(ran),
            executor=executor,
            seconds=round(time.time() - t0, 2),
        )
    return ReconstructResult(done, len(ran), cfg, project.path("recon"))
