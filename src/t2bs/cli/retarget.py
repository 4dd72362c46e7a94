"""CLI: `t2bs landmarks DIR` and `t2bs retarget DIR --driver VIDEO|IMAGES|CSV` (the stages: t2bs.retarget)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from t2bs.retarget import landmarks_stage, stage


def landmarks_command(
    project_dir: Path = typer.Argument(..., help="project folder (with character/mesh.glb)"),
    show: bool = typer.Option(False, "--show", help="also write landmarks/overlay.png"),
    backend: str = typer.Option(
        "auto",
        "--backend",
        help="auto | parts | motion | grounding-sam (local Grounding-DINO"
        " + SAM checkpoints through transformers; both Apache-2.0)",
    ),
    override: Optional[Path] = typer.Option(None, "--override", help="JSON with 20 vertex_ids or points2d"),
) -> None:
    """Find the character's 20 retargeting landmarks (6 per eye, 8 mouth) on its frontal render."""
    landmarks_stage.run(project_dir, landmarks_stage.LandmarksConfig(show=show, backend=backend, override=override))


def retarget_command(
    project_dir: Path = typer.Argument(..., help="project folder (character/mesh.glb, blendshapes/model.npz)"),
    driver: Path = typer.Option(
        ..., "--driver", help="human face video file, folder of images, or Live Link Face .csv"
    ),
    out: Optional[Path] = typer.Option(None, "-o", "--out", help="output folder (default DIR/retarget/<driver name>)"),
    neutral_frame: Optional[int] = typer.Option(
        None, "--neutral-frame", help="index of the neutral frame (default: detected)"
    ),
    smooth: float = typer.Option(
        1.0, "--smooth", help="temporal smoothing of the landmarks, sigma in frames (0 = off)"
    ),
    max_frames: Optional[int] = typer.Option(None, "--max-frames", help="use at most this many frames"),
    size: int = typer.Option(256, "--size", help="preview video height in pixels"),
) -> None:
    """Drive the character's blendshape model with a human face video (MediaPipe + landmark solve)
    or a Live Link Face CSV (its ARKit weights drive the rig's ARKit shapes directly)."""
    stage.run(
        project_dir,
        stage.RetargetConfig(
            driver=driver, out=out, neutral_frame=neutral_frame, smooth=smooth, max_frames=max_frames, size=size
        ),
    )
