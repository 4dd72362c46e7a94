"""`t2bs blendshapes DIR` and `t2bs export DIR`: the command lines of t2bs.blendshapes.stage and
t2bs.blendshapes.export_stage."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from t2bs.blendshapes import export_stage, stage


def blendshapes_command(
    project_dir: Path = typer.Argument(..., help="Project folder (character/mesh.glb + recon/ or videos/)."),
    components: int = typer.Option(
        100, "--components", "-k", help="Most shapes to keep (also capped by the data's rank)."
    ),
    source: str = typer.Option(
        "auto", "--source", help="vcdgs: recon/*/vertices.npy; gt: videos/*/gt_vertices.npy; auto: vcdgs if present."
    ),
    semantic: bool = typer.Option(True, "--semantic/--no-semantic", help="Add one named shape per expression prompt."),
    animation: Optional[str] = typer.Option(
        None, "--animation", help="Video id replayed by model.glb (default: the capture that moves most)."
    ),
    usd: bool = typer.Option(
        False, "--usd", help="Also write model.usdc (binary USD, UsdSkel blend shapes; needs usd-core)."
    ),
    fps: float = typer.Option(8.0, "--fps", help="Frame rate of the exported animation."),
    force: bool = typer.Option(False, "--force", help="Rebuild even if the inputs did not change."),
    arkit: bool = typer.Option(
        True, "--arkit/--no-arkit", help="Derive the ARKit-52 named shapes (needs the 20 landmarks; docs/ARKIT.md)."
    ),
) -> None:
    """PCA blendshape model of every captured frame -> DIR/blendshapes/model.npz + model.glb (paper §3.3)."""
    stage.run(
        project_dir,
        stage.BlendshapesConfig(
            components=components,
            source=source,
            semantic=semantic,
            animation=animation,
            usd=usd,
            fps=fps,
            force=force,
            arkit=arkit,
        ),
    )


def export_command(
    project_dir: Path = typer.Argument(..., help="Project folder with blendshapes/model.npz."),
    format: str = typer.Option(
        "vrm", "--format", "-f", help="glb (model.glb), usd (model.usdc; -o x.usda for text) or vrm (VRM 1.0 avatar)."
    ),
    out: Optional[Path] = typer.Option(None, "-o", "--out", help="Output file (default DIR/blendshapes/model.<ext>)."),
    license: Optional[str] = typer.Option(
        None, "--license", help="VRM: licence id (VPL-1.0, CC0-1.0, CC-BY-4.0, ...) or URL; required."
    ),
    author: list[str] = typer.Option([], "--author", help="VRM: author name (repeatable; default: the t2bs user)."),
    name: Optional[str] = typer.Option(
        None, "--name", help="VRM: avatar name (default: the character prompt or folder name)."
    ),
) -> None:
    """Export the blendshape rig (ARKit shapes first) as .glb, .usdc/.usda or .vrm (docs/ARKIT.md)."""
    export_stage.run(
        project_dir, export_stage.ExportConfig(format=format, out=out, license=license, author=tuple(author), name=name)
    )
