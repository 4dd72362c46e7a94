"""`t2bs reconstruct DIR`: the reconstruct stage (t2bs.recon.stage) from the command line."""

from __future__ import annotations

from pathlib import Path

import typer

from t2bs.recon.config import METHODS, PRESETS, parse_options
from t2bs.recon.stage import ReconstructConfig, run


def reconstruct_command(
    project_dir: Path = typer.Argument(..., help="Project folder with character/mesh.glb and videos/<id>/ grids."),
    videos: list[str] = typer.Option(
        None, "--videos", help="Video ids to reconstruct (repeat or comma-separate); default all."
    ),
    preset_name: str = typer.Option(
        "quick",
        "--preset",
        help=f"Settings: {' | '.join(PRESETS)} (quick = CPU minutes, paper = GPU, §4.1: ~11 min a video on an H200, and"
        " less accurate than quick on a wide mouth).",
    ),
    method: str = typer.Option("full", help=f"Method or ablation: {' | '.join(METHODS)}."),
    iterations: int = typer.Option(0, help="Override the preset's training steps (0 = preset)."),
    control_points: int = typer.Option(0, help="Override the number of control points (0 = preset)."),
    track_weight: float = typer.Option(
        None, help="Weight of the optical-flow vertex-track term (0 = the paper's loss alone; default: the preset's)."
    ),
    face_gaussians: int = typer.Option(
        -1,
        help="Face Gaussians on at most this many of the largest triangles (0 = every triangle; -1 = the preset's: quick 10000, paper all).",
    ),
    hidden_pick: bool = typer.Option(
        None,
        "--hidden-pick/--no-hidden-pick",
        help="After training, parts no training view sees at rest (teeth, a mouth bag) may take a seen cluster's rigid motion, picked by render in groups by where they lie across the opening that reveals them (two groupings tried, the one whose renders match the images better kept; recon/hidden_parts.py); where nothing opens they take the head's motion. Default: the preset's, on.",
    ),
    device: str = typer.Option("auto", help="auto | cpu | cuda."),
    lpips_weights: str = typer.Option(
        "",
        help="Local LPIPS weights (file or folder; LPIPS lin layers BSD-2-Clause, AlexNet features BSD-3-Clause); default D-SSIM.",
    ),
    no_preview: bool = typer.Option(False, "--no-preview", help="Skip preview.mp4."),
    seed: int = typer.Option(0, help="Seed of sampling and initialisation."),
    workers: int = typer.Option(1, help="Videos reconstructed in parallel on this machine (process pool)."),
    ray: str = typer.Option(None, "--ray", help="Run the jobs on Ray: 'auto', 'local' or host:port."),
    set_options: list[str] = typer.Option(
        None,
        "--set",
        help="Any VCDGS option as KEY=VALUE (repeat; a field of the config tree in t2bs.recon.config, by name or as section.name, e.g. --set knn=4); applied after the options above.",
    ),
) -> None:
    """Recover per-frame meshes from each multi-view grid with VCDGS (resumable)."""
    options = parse_options(set_options or [])
    run(
        project_dir,
        ReconstructConfig(
            videos=tuple(videos or ()),
            preset_name=preset_name,
            method=method,
            iterations=iterations,
            control_points=control_points,
            track_weight=track_weight,
            face_gaussians=face_gaussians,
            hidden_pick=hidden_pick,
            device=device,
            lpips_weights=lpips_weights,
            preview=not no_preview,
            seed=seed,
            workers=workers,
            ray=ray,
            options=options,
        ),
    )
