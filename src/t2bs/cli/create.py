"""`t2bs create "PROMPT" -o DIR`: every stage (t2bs.pipeline.create) from the command line."""

from __future__ import annotations

from pathlib import Path

import typer

from t2bs.pipeline import CreateConfig, create


def create_command(
    prompt: str = typer.Argument(..., help='Text describing the character, e.g. "a cartoon fox with big ears".'),
    out: Path = typer.Option(..., "-o", "--out", help="Project folder (created, or resumed if it exists)."),
    preset: str = typer.Option(
        "quick",
        help="quick (CPU minutes) or paper (§4.1 settings, GPU; ~11 min a video on an H200, and less accurate than quick"
        " on a wide mouth: docs/BENCHMARKS.md).",
    ),
    prompts: str = typer.Option(
        None, help="Expression prompts: all, a comma list, or a prompt-list file (default: the preset's)."
    ),
    samples: int = typer.Option(0, help="Videos per prompt (0 = the preset's)."),
    seed: int = typer.Option(0, help="Seed for the character, animation, defects and training."),
    character_backend: str = typer.Option(
        "procedural",
        "--character-backend",
        help="procedural, diffusers (Shap-E weights, MIT licence), command or file.",
    ),
    mesh: Path = typer.Option(None, help="Bring your own mesh (character backend 'file')."),
    workers: int = typer.Option(1, help="Reconstruction jobs in parallel on this machine (process pool)."),
    ray: str = typer.Option(None, "--ray", help="Run reconstruction jobs on Ray: 'auto', 'local' or host:port."),
    frames: int = typer.Option(0, help="Frames per video (0 = the preset's)."),
    size: int = typer.Option(0, help="Grid frame side in pixels (0 = the preset's)."),
    views: int = typer.Option(0, help="Orbit views (0 = the paper's 15)."),
    defects: str = typer.Option(None, help="Simulated 4D-model defects: clean, mild, paper (default: the preset's)."),
    iterations: int = typer.Option(0, help="VCDGS steps per video (0 = the preset's)."),
    control_points: int = typer.Option(0, help="VCDGS control points (0 = the preset's)."),
    video_backend: str = typer.Option(
        "procedural",
        "--video-backend",
        help="procedural (offline animator), "
        "cogvideox+sv4d2 (the paper's chain: CogVideoX image-to-video, then SV4D 2.0 "
        "for the 15-view grid) or procedural+sv4d2 (the animator's front view into SV4D 2.0).",
    ),
    checkpoints: Path = typer.Option(
        None,
        "--checkpoints",
        help="Folder of the video models' weights: cogvideox/ "
        "(THUDM/CogVideoX-5b-I2V, diffusers layout) and sv4d2/ (sv4d2.safetensors from "
        "stabilityai/sv4d2.0, Stability AI Community License). See docs/SV4D2.md.",
    ),
    video_steps: int = typer.Option(0, help="Denoising steps of the video models (0 = their defaults, 50)."),
) -> None:
    """Text -> animatable blendshape rig: runs every stage and writes DIR/report.md."""
    create(
        out,
        CreateConfig(
            prompt=prompt,
            preset=preset,
            prompts=prompts,
            samples=samples,
            seed=seed,
            character_backend=character_backend,
            mesh=mesh,
            workers=workers,
            ray=ray,
            frames=frames,
            size=size,
            views=views,
            defects=defects,
            iterations=iterations,
            control_points=control_points,
            video_backend=video_backend,
            checkpoints=checkpoints,
            video_steps=video_steps,
        ),
    )
