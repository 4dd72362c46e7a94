"""The export stage: a built rig (DIR/blendshapes/model.npz) in the format a consumer wants: glb, usd or vrm.

Its command line is `t2bs export` (t2bs.cli.blendshapes).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from t2bs.errors import UserError
from t2bs.project import Project, project_lock

FORMATS = ("glb", "usd", "vrm")


@dataclass
class ExportConfig:
    format: str = "vrm"  # glb (model.glb), usd (model.usdc; an out path ending .usda for text) or vrm (VRM 1.0)
    out: Path | None = None  # output file; None: DIR/blendshapes/model.<glb|usdc|vrm>
    license: str | None = None  # VRM: licence id (VPL-1.0, CC0-1.0, CC-BY-4.0, ...) or URL; required for vrm
    author: tuple[str, ...] = ()  # VRM: author names; empty: the t2bs user
    name: str | None = None  # VRM: avatar name; None: the character prompt or the folder name


@dataclass
class ExportResult:
    path: Path  # the file written
    format: str  # glb, usd or vrm
    arkit: bool  # True when the export carries the ARKit shapes (DIR/blendshapes/arkit.json present)


def _project_name(project) -> str:
    """The character's prompt when the character stage recorded one, else the folder name."""
    stage = project.manifest().get("stages", {}).get("character", {})
    for key in ("prompt", "text"):
        value = stage.get(key) or (stage.get("config") or {}).get(key)
        if isinstance(value, str) and value.strip():
            return value.strip()
    return project.root.resolve().name


def run(project: Project | str | os.PathLike, config: ExportConfig = ExportConfig()) -> ExportResult:
    """Export the blendshape rig (ARKit shapes first) as .glb, .usdc/.usda or .vrm (docs/ARKIT.md).

    Reads DIR/blendshapes/model.npz (the basis [K, N, 3]), DIR/character/mesh.glb (N vertices),
    DIR/blendshapes/arkit.json when present (the ARKit shapes, else a note is printed) and
    DIR/blendshapes/stats.json (the capture model.glb replays). Writes ``config.out``, by default
    DIR/blendshapes/model.glb, model.usdc or model.vrm (atomically), and prints ``wrote PATH`` (vrm: the
    presets bound and the ARKit custom expressions first).

    Raises UserError for an unknown format, a missing project folder or model, a model whose vertex count
    differs from the character's, vrm without ``license``, usd without usd-core, or another t2bs command
    holding the project. Nothing is skipped: every run writes the file again.
    """
    if config.format not in FORMATS:
        raise UserError(f"unknown --format {config.format!r}; use one of {', '.join(FORMATS)}")
    project = project if isinstance(project, Project) else Project(project)
    if not project.root.is_dir():
        raise UserError(f"{project.root}: no such project folder")
    with project_lock(project.root, "export"):  # one run at a time per project (issue 39)
        return _run(project, config)


def _run(project: Project, config: ExportConfig) -> ExportResult:
    from t2bs.blendshapes.export import export_glb, export_usd
    from t2bs.blendshapes.model import load_model
    from t2bs.face.arkit import load_arkit_shapes
    from t2bs.project import read_json

    fmt = config.format
    model = load_model(project.path("blendshapes", "model.npz"))
    character = project.load_character()
    if character.num_vertices != model.num_vertices:
        raise UserError(
            f"blendshape model has {model.num_vertices} vertices but the character has {character.num_vertices}"
        )
    arkit = load_arkit_shapes(project.path("blendshapes", "arkit.json"), model.num_components)
    ext = {"glb": ".glb", "usd": ".usdc", "vrm": ".vrm"}[fmt]
    path = Path(config.out) if config.out is not None else project.path("blendshapes", f"model{ext}")
    stats = project.path("blendshapes", "stats.json")
    replay = read_json(stats).get("animation") if stats.exists() else None  # the capture model.glb replays
    if fmt == "glb":
        export_glb(model, character, path, capture=replay, arkit=arkit)
    elif fmt == "usd":
        try:
            export_usd(model, character, path, capture=replay, arkit=arkit)
        except ImportError:
            raise UserError("--format usd needs usd-core: pip install usd-core") from None
    else:
        import getpass

        from t2bs.blendshapes.vrm import export_vrm

        if config.license is None:
            raise UserError(
                "--format vrm needs --license (VPL-1.0, CC0-1.0, CC-BY-4.0, ... or a URL): "
                "VRM meta must say how the avatar may be used"
            )
        authors = list(config.author) or [getpass.getuser() or "t2bs user"]
        _, info = export_vrm(
            model, character, path, config.name or _project_name(project), authors, config.license, arkit=arkit
        )
        if info["unbound"]:
            print(f"VRM presets without a matching shape on this rig (left out): {', '.join(info['unbound'])}")
        print(f"VRM presets: {', '.join(info['presets'])}; ARKit custom expressions: {len(info['custom'])}")
    if arkit is None:
        print("note: no blendshapes/arkit.json, so no ARKit shapes (rebuild with `t2bs blendshapes DIR --arkit`)")
    print(f"wrote {path}")
    return ExportResult(path, fmt, arkit is not None)
