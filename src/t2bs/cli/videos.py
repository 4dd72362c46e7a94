"""`t2bs videos DIR`: the command line of the videos stage (t2bs.video.stage)."""

from __future__ import annotations

from pathlib import Path

import typer

from t2bs.geometry.camera import ORBIT_VIEWS
from t2bs.video.defects import STRENGTHS
from t2bs.video.prompts import SAMPLES_PER_PROMPT
from t2bs.video.stage import VideosConfig, run


def videos_command(
    project_dir: Path = typer.Argument(..., help="Project folder (with character/mesh.glb)."),
    prompts: str = typer.Option(
        "all", help="all, a comma list of expressions, or a prompt-list file (.txt one per line, .json)."
    ),
    samples: int = typer.Option(SAMPLES_PER_PROMPT, help="Videos per prompt (paper: 3)."),
    defects: str = typer.Option(
        "mild",
        help="Simulated 4D-generator defects on the side views: clean, mild, paper; only_<defect> or "
        f"paper_without_<defect> for one defect ({', '.join(STRENGTHS)}).",
    ),
    frames: int = typer.Option(16, help="Frames per video T (paper's models: 16-49)."),
    size: int = typer.Option(512, help="Frame side in pixels (128 for quick runs)."),
    views: int = typer.Option(ORBIT_VIEWS, help="Orbit views over azimuth -60..60 (odd; paper: 15)."),
    seed: int = typer.Option(0, help="Seed of animation and defects."),
    shading: str = typer.Option(
        None,
        help="unlit (ambient = 1, the paper's protocol; procedural default) or lambert. "
        "--import-grid: how the render the 4D model started from was lit (required).",
    ),
    backend: str = typer.Option(
        "procedural",
        help="procedural (offline, with ground truth), cogvideox (fixed view "
        "only; THUDM/CogVideoX-5b-I2V weights under the CogVideoX LICENSE, commercial use "
        "needs registration) or sv4d2 (the V x T grid from the fixed-view video; see below).",
    ),
    checkpoint: Path = typer.Option(
        None,
        help="cogvideox: CogVideoX-5b-I2V folder (diffusers layout). sv4d2: folder "
        "holding sv4d2.safetensors from stabilityai/sv4d2.0 (one file with UNet, CLIP "
        "image encoder and VAE; Stability AI Community License: accept it on the model "
        "page, then `huggingface-cli download stabilityai/sv4d2.0 sv4d2.safetensors "
        "--local-dir DIR`).",
    ),
    steps: int = typer.Option(50, help="Denoising steps (cogvideox; sv4d2 per pass, authors' default 50)."),
    video: Path = typer.Option(
        None,
        "--video",
        help="sv4d2: a fixed-view video file (front view over time) to use "
        "instead of the project's; needs --expression.",
    ),
    dtype: str = typer.Option("auto", help="sv4d2 UNet precision: auto (bf16 on CUDA), float32, bfloat16, float16."),
    offload: bool = typer.Option(False, help="sv4d2: keep weights on the CPU between parts (GPUs under ~24 GB)."),
    import_grid: Path = typer.Option(
        None, "--import-grid", help="Import a V x T grid (one image, view folders or videos) from a 4D model."
    ),
    expression: str = typer.Option(None, help="Expression of the imported grid or of --video (names its folder)."),
    sample: int = typer.Option(0, help="Sample index of the imported grid or of --video."),
) -> None:
    """Make the expression videos: one multi-view grid per (prompt, sample) in DIR/videos/.

    --backend sv4d2 is the paper's 4D stage with SV4D 2.0 (Stability AI; weights under the Stability
    AI Community License, which you accept on the model page of stabilityai/sv4d2.0 before
    downloading: free for research and for organisations under USD 1M annual revenue). It reads
    each video's fixed-view video (made first with --backend cogvideox, or a procedural grid's
    canonical view, or --video FILE) and the static mesh's orbit renders (`t2bs render`), and
    writes the 15-view grid, 4 views x 12 frames per pass, chained (docs/SV4D2.md).
    """
    run(
        project_dir,
        VideosConfig(
            prompts=prompts,
            samples=samples,
            defects=defects,
            frames=frames,
            size=size,
            views=views,
            seed=seed,
            shading=shading,
            backend=backend,
            checkpoint=checkpoint,
            steps=steps,
            video=video,
            dtype=dtype,
            offload=offload,
            import_grid=import_grid,
            expression=expression,
            sample=sample,
        ),
    )
