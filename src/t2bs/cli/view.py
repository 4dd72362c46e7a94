"""CLI: `t2bs view DIR` (the server: t2bs.viewer.serve)."""

from __future__ import annotations

from pathlib import Path

import typer

from t2bs.viewer.serve import ViewConfig, serve


def view_command(
    project_dir: Path = typer.Argument(..., help="Project folder (made by `t2bs create` or the stage commands)."),
    port: int = typer.Option(
        8080, "--port", help="Port to serve on (0 = any free port; a busy port moves to the next free one)."
    ),
    host: str = typer.Option(
        "127.0.0.1",
        "--host",
        help="Address to bind. The default serves this machine only; "
        "0.0.0.0 exposes the viewer (no authentication) to the network.",
    ),
    splats: bool = typer.Option(
        False, "--splats", help="Start with the character drawn as Gaussian splats instead of the mesh."
    ),
) -> None:
    """Web page with the character, one slider per blendshape, captures and retargeting playback."""
    serve(project_dir, ViewConfig(port=port, host=host, splats=splats))
