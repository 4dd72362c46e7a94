"""CLI: `t2bs autorig MESH -o OUT.glb` (the code: t2bs.rig.stage)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from t2bs.rig import stage


def autorig_command(
    mesh_path: Path = typer.Argument(..., help="Head mesh (glb, gltf, vrm, obj, ply) without a face rig."),
    out: Path = typer.Option(..., "-o", "--out", help="Output .glb: the mesh with ARKit-named morph targets."),
    landmarks: Optional[Path] = typer.Option(
        None, "--landmarks", help="JSON with 20 vertex_ids (68-point order 36-47, 60-67), optional named ids."
    ),
    facing: str = typer.Option("auto", help="Axis the face looks along in the file: auto, +z, -z, +x, -x."),
    keep: bool = typer.Option(False, "--keep", help="Keep the mesh's own morph targets next to the new ones."),
    lid_meet: Optional[float] = typer.Option(
        None,
        "--lid-meet",
        help="Where closed lids meet: 0 = at the lower lid, 1 = at the upper lid. Default by the eye: 0.2 over an "
        "eyeball (a human blink), 0.4 over a flat or painted eye (both lids stretched alike).",
    ),
) -> None:
    """Build a face rig on a static head mesh in seconds: jawOpen, eyeBlinkLeft, mouthSmileLeft, ... (ARKit names)."""
    stage.run(
        out, stage.AutorigConfig(mesh_path=mesh_path, landmarks=landmarks, facing=facing, keep=keep, lid_meet=lid_meet)
    )
