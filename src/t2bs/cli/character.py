"""CLI: `t2bs character PROMPT -o DIR` and `t2bs gallery -o DIR` (the code: t2bs.character.stage, .gallery)."""

from __future__ import annotations

from pathlib import Path

import typer

from t2bs.character import stage
from t2bs.character.gallery import render_gallery


def character_command(
    prompt: str = typer.Argument(..., help='Text describing the character, e.g. "a cartoon fox with big ears".'),
    out: Path = typer.Option(..., "-o", "--out", help="Project folder to create or update."),
    backend: str = typer.Option(
        "procedural",
        help="procedural (offline), diffusers (Shap-E: openai/shap-e weights, MIT licence), command, file.",
    ),
    seed: int = typer.Option(0, help="Random seed: same prompt + seed -> same character."),
    checkpoint: Path = typer.Option(
        None, help="diffusers: local Shap-E folder (default ~/.cache/t2bs/checkpoints/shap-e)."
    ),
    command: str = typer.Option(
        None,
        help="command: template with {prompt} {out} {seed}; it writes a mesh into "
        "{out}. Run without a shell (docs/HOSTILE_INPUTS.md).",
    ),
    command_timeout: float = typer.Option(3600.0, help="command: seconds before the command is killed (0 = no limit)."),
    mesh: Path = typer.Option(None, help="file: a mesh (.glb .gltf .vrm .obj .ply)."),
    steps: int = typer.Option(64, help="diffusers: denoising steps."),
    size: int = typer.Option(512, help="Render size in pixels."),
) -> None:
    """Text -> character: DIR/character/mesh.glb (parts, rig morph targets) and the renders."""
    stage.run(
        out,
        stage.CharacterConfig(
            prompt=prompt,
            backend=backend,
            seed=seed,
            checkpoint=checkpoint,
            command=command,
            command_timeout=command_timeout,
            mesh=mesh,
            steps=steps,
            size=size,
        ),
    )


def gallery_command(
    out: Path = typer.Option(..., "-o", "--out", help="Folder for gallery.png and gallery.json."),
    seed: int = typer.Option(0, help="Random seed for every character."),
    size: int = typer.Option(320, help="Pixels per view."),
) -> None:
    """Render 16 procedural characters (the paper's 10 and 6 more), front and three-quarter view."""
    path, stats = render_gallery(out, seed, size)
    total = sum(s["seconds"] for s in stats.values())
    print(f"gallery: {path} ({len(stats)} characters, generation {total:.1f} s in all)")
