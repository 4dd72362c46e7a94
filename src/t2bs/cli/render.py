"""CLI: `t2bs render MESH -o DIR` (the stage: t2bs.character.render_stage)."""

from __future__ import annotations

from pathlib import Path

import typer

from t2bs.character import render_stage
from t2bs.geometry.camera import ORBIT_VIEWS


def render_command(
    mesh: Path = typer.Argument(..., help="Character mesh: .glb .gltf .vrm .obj .ply (morph targets are kept)."),
    out: Path = typer.Option(..., "-o", "--out", help="Project folder to create or update."),
    facing: str = typer.Option("auto", help="Axis the character faces: auto, +z, -z, +x, -x."),
    size: int = typer.Option(512, help="Image side in pixels."),
    views: int = typer.Option(ORBIT_VIEWS, help="Orbit views over azimuth -60..60 deg."),
    shading: str = typer.Option("lambert", help="lambert or unlit."),
) -> None:
    """Import a character mesh into a project folder and render the frontal and orbit views."""
    render_stage.run(
        out, render_stage.RenderStageConfig(mesh=mesh, facing=facing, size=size, views=views, shading=shading)
    )
