"""`t2bs export DIR --format glb|usd|vrm`: write a built rig in the format a consumer wants."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from t2bs.errors import UserError

FORMATS = ("glb", "usd", "vrm")


def _project_name(project) -> str:
    """The character's prompt when the character stage recorded one, else the folder name."""
    stage = project.manifest().get("stages", {}).get("character", {})
    for key in ("prompt", "text"):
        value = stage.get(key) or (stage.get("config") or {}).get(key)
        if isinstance(value, str) and value.strip():
            return value.strip()
    return project.root.resolve().name


def export_command(
    project_dir: Path = typer.Argument(..., help="Project folder with blendshapes/model.npz."),
    format: str = typer.Option("vrm", "--format", "-f", help="glb (model.glb), usd (model.usdc; -o x.usda for text) or vrm (VRM 1.0 avatar)."),
    out: Optional[Path] = typer.Option(None, "-o", "--out", help="Output file (default DIR/blendshapes/model.<ext>)."),
    license: Optional[str] = typer.Option(None, "--license", help="VRM: licence id (VPL-1.0, CC0-1.0, CC-BY-4.0, ...) or URL; required."),
    author: list[str] = typer.Option([], "--author", help="VRM: author name (repeatable; default: the t2bs user)."),
    name: Optional[str] = typer.Option(None, "--name", help="VRM: avatar name (default: the character prompt or folder name)."),
) -> None:
    """Export the blendshape rig (ARKit shapes first) as .glb, .usdc/.usda or .vrm (docs/ARKIT.md)."""
    import getpass

    from t2bs.blendshapes.export import export_glb, export_usd
    from t2bs.blendshapes.model import load_model
    from t2bs.project import Project, read_json
    from t2bs.face.arkit import load_arkit_shapes

    if format not in FORMATS:
        raise UserError(f"unknown --format {format!r}; use one of {', '.join(FORMATS)}")
    project = Project(project_dir)
    if not project.root.is_dir():
        raise UserError(f"{project_dir}: no such project folder")
    model = load_model(project.path("blendshapes", "model.npz"))
    character = project.load_character()
    if character.num_vertices != model.num_vertices:
        raise UserError(f"blendshape model has {model.num_vertices} vertices but the character has {character.num_vertices}")
    arkit = load_arkit_shapes(project.path("blendshapes", "arkit.json"), model.num_components)
    ext = {"glb": ".glb", "usd": ".usdc", "vrm": ".vrm"}[format]
    path = Path(out) if out is not None else project.path("blendshapes", f"model{ext}")
    stats = project.path("blendshapes", "stats.json")
    replay = read_json(stats).get("animation") if stats.exists() else None  # the capture model.glb replays
    if format == "glb":
        export_glb(model, character, path, capture=replay, arkit=arkit)
    elif format == "usd":
        try:
            export_usd(model, character, path, capture=replay, arkit=arkit)
        except ImportError:
            raise UserError("--format usd needs usd-core: pip install usd-core") from None
    else:
        from t2bs.blendshapes.vrm import export_vrm

        if license is None:
            raise UserError("--format vrm needs --license (VPL-1.0, CC0-1.0, CC-BY-4.0, ... or a URL): "
                            "VRM meta must say how the avatar may be used")
        authors = author or [getpass.getuser() or "t2bs user"]
        _, info = export_vrm(model, character, path, name or _project_name(project), authors, license, arkit=arkit)
        if info["unbound"]:
            print(f"VRM presets without a matching shape on this rig (left out): {', '.join(info['unbound'])}")
        print(f"VRM presets: {', '.join(info['presets'])}; ARKit custom expressions: {len(info['custom'])}")
    if arkit is None:
        print("note: no blendshapes/arkit.json, so no ARKit shapes (rebuild with `t2bs blendshapes DIR --arkit`)")
    print(f"wrote {path}")
