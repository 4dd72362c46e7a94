"""`t2bs bench ...`: the benchmarks' command lines. Each maps its flags to the config of a function in t2bs.eval and
prints what it returns (the functions print their progress themselves)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from t2bs.eval.bench_blendshapes import BenchBlendshapesConfig, bench_blendshapes
from t2bs.eval.bench_raster import BenchRasterConfig, bench_raster
from t2bs.eval.bench_retarget import BenchRetargetConfig, bench_retarget
from t2bs.eval.bench_vcdgs import (
    ALL_METHODS,
    DEFAULT_PROMPTS,
    BenchVcdgsConfig,
    bench_vcdgs,
    full_vs_markdown,
    markdown,
)


def bench_raster_command(cases: str = "a,b,c", repeats: int = 5, threads: int = 2) -> None:
    """Splat rasterizer: fast C++ vs autograd reference vs dense, ms per forward+backward (JSON)."""
    bench_raster(BenchRasterConfig(cases=cases, repeats=repeats, threads=threads))


def bench_vcdgs_command(
    asset: list[str] = typer.Option(
        None,
        "--asset",
        help="Asset: turtle, facecap, a glb/vrm path with morph targets, "
        "or procedural:PROMPT (repeat). Default: turtle, facecap, procedural fox.",
    ),
    prompts: str = typer.Option(",".join(DEFAULT_PROMPTS), help="Comma-separated expression prompts."),
    defects: str = typer.Option("clean", help="Comma-separated defect presets: clean, mild, paper."),
    methods: str = typer.Option("full,static,rigid", help=f"Comma-separated: {', '.join(ALL_METHODS)} (or 'all')."),
    preset_name: str = typer.Option("quick", "--preset", help="VCDGS preset: quick | paper."),
    size: int = typer.Option(128, help="Grid frame size in pixels."),
    frames: int = typer.Option(16, help="Frames per grid."),
    iterations: int = typer.Option(0, help="Override the preset's training steps (0 = preset)."),
    track_weight: float = typer.Option(
        None,
        help="Weight of the optical-flow vertex-track term (0 = the paper's loss alone; default: the preset's).",
    ),
    time_budget: float = typer.Option(
        None,
        "--time-budget",
        help="Wall seconds per reconstruction (0 = no cap: every "
        "method runs all its steps, so a row depends on the seed only, not on the "
        "machine's speed or load; default: the preset's).",
    ),
    seed: int = typer.Option(
        None,
        help="VCDGS seed (sampling and initialisation; default: the preset's, 0). The grids do not change with it.",
    ),
    hidden_pick: bool = typer.Option(
        None,
        "--hidden-pick/--no-hidden-pick",
        help="Hidden parts' motion picked by render (recon/hidden_parts.py; default: the preset's, on).",
    ),
    json_file: Path = typer.Option(
        None,
        "--json",
        help="Also write the JSON here (after every case); a re-run with the same file and settings resumes.",
    ),
    fresh: bool = typer.Option(
        False, "--fresh", help="Recompute every row even if --json holds them from the same settings."
    ),
    set_options: list[str] = typer.Option(
        None,
        "--set",
        help="Any other VCDGS option as KEY=VALUE (repeat; a field of "
        "t2bs.recon.config.VCDGSConfig, e.g. --set knn=4), for every method; "
        "recorded in the JSON's settings.",
    ),
    workers: int = typer.Option(
        1,
        help="Cases run in this many parallel processes (each reconstruction keeps its "
        "configured torch threads, so the rows do not change with --workers; its wall seconds "
        "do, and under a time budget its step count: add --time-budget 0 for rows that do not "
        "depend on the machine's load).",
    ),
    progress: bool = typer.Option(
        False, "--progress", help="Show each reconstruction's progress bars on stderr (where a cut-off run stopped)."
    ),
    perfect_tracks: bool = typer.Option(
        False,
        "--perfect-tracks",
        help="Train on the truth's projected vertex motion instead of the optical flow's tracks (same validity): "
        "what perfect flow would buy.",
    ),
    landmarks: list[str] = typer.Option(
        None,
        "--landmarks",
        help="ASSET=FILE (repeat): that asset's 20 face points for the expression basis (the JSON of `t2bs autorig "
        "--landmarks`, or a project's landmarks/landmarks.json) instead of finding the face on a render.",
    ),
) -> None:
    """VCDGS vs ablations vs static on characters with ground truth (JSON + Markdown)."""
    result = bench_vcdgs(
        BenchVcdgsConfig(
            asset=tuple(asset or ()),
            prompts=prompts,
            defects=defects,
            methods=methods,
            preset_name=preset_name,
            size=size,
            frames=frames,
            iterations=iterations,
            track_weight=track_weight,
            time_budget=time_budget,
            seed=seed,
            hidden_pick=hidden_pick,
            json_file=json_file,
            fresh=fresh,
            set_options=tuple(set_options or ()),
            workers=workers,
            progress=progress,
            perfect_tracks=perfect_tracks,
            landmarks=tuple(landmarks or ()),
        )
    )
    print(markdown(result["rows"]))
    if result["summary"]["full_vs"]:
        print("\n" + full_vs_markdown(result["summary"]["full_vs"]))
    print(json.dumps(result, indent=1))


def bench_blendshapes_command(
    asset: str = typer.Option(
        ..., "--asset", help="Mesh with morph targets (.glb), a project folder, or procedural:PROMPT."
    ),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Also write the JSON here."),
    source: str = typer.Option("gt", "--source", help="gt: ground-truth captures; vcdgs: recon/ of a project folder."),
    components: int = typer.Option(100, "--components", "-k", help="Shapes in the model (paper: 100)."),
    held_out: int = typer.Option(5, "--held-out", help="Prompts held out of the model (paper: 5)."),
    prompts: int = typer.Option(20, "--prompts", help="Prompts animated for a mesh asset (paper: 20)."),
    frames: int = typer.Option(24, "--frames", help="Frames per capture for a mesh asset."),
    rgb_steps: int = typer.Option(
        10, "--rgb-steps", help="L-BFGS iterations of the 0.1 L_rgb refinement (0 = geometry only)."
    ),
    image_size: int = typer.Option(256, "--image-size", help="Side of the frontal renders for pixel L2."),
    facing: str = typer.Option("+z", "--facing", help="Direction a mesh asset faces (+z, -z, +x, -x)."),
    seed: int = typer.Option(0, "--seed", help="Random seed (captures and held-out choice)."),
) -> None:
    """Held-out expressiveness (paper appendix): mean p2p / bbox diagonal and pixel L2 of fitted held-out captures."""
    out = bench_blendshapes(
        BenchBlendshapesConfig(
            asset=asset,
            json_out=json_out,
            source=source,
            components=components,
            held_out=held_out,
            prompts=prompts,
            frames=frames,
            rgb_steps=rgb_steps,
            image_size=image_size,
            facing=facing,
            seed=seed,
        )
    )
    print(json.dumps(out, indent=2, default=float))


def bench_retarget_command(
    target: list[str] = typer.Option(
        None,
        "--target",
        help="target mesh with morph targets, or procedural:<prompt>; repeatable "
        "(default: the shared turtle.glb, $T2BS_SHARED_ASSETS or ../shared/assets)",
    ),
    json_path: Optional[Path] = typer.Option(None, "--json", help="also write the result to this JSON file"),
    frames: int = typer.Option(96, "--frames", help="driver frames"),
    seed: int = typer.Option(0, "--seed"),
) -> None:
    """Facecap ARKit morphs -> MediaPipe -> target model; Pearson of the target's own directions."""
    result = bench_retarget(
        BenchRetargetConfig(target=tuple(target or ()), json_path=json_path, frames=frames, seed=seed)
    )
    print(json.dumps(result, indent=2))
