"""The character stage: text -> DIR/character/mesh.glb (parts, rig morph targets) and its renders."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from t2bs.errors import UserError
from t2bs.project import Project, project_lock


@dataclass
class CharacterConfig:
    prompt: str  # text describing the character, e.g. "a cartoon fox with big ears"
    backend: str = "procedural"  # procedural (offline), diffusers (Shap-E), command (a template), file (a mesh)
    seed: int = 0  # random seed: same prompt + seed -> same character
    checkpoint: Path | None = None  # diffusers: local Shap-E folder (None: ~/.cache/t2bs/checkpoints/shap-e)
    command: str | None = None  # command: template with {prompt} {out} {seed}, run without a shell; writes a mesh
    command_timeout: float = 3600.0  # command: seconds before the command is killed (0 = no limit)
    mesh: Path | None = None  # file: a mesh (.glb .gltf .vrm .obj .ply)
    steps: int = 64  # diffusers: denoising steps
    size: int = 512  # render size, pixels (>= 16)


@dataclass
class CharacterResult:
    mesh_path: Path  # DIR/character/mesh.glb
    renders: Path  # DIR/renders (front.png, orbit/view00..14.png, cameras.json)
    backend: str  # the backend that made the mesh
    archetype: str | None  # procedural: the archetype the prompt picked (None for other backends)
    vertices: int  # vertex count of the character
    parts: tuple[str, ...]  # part labels (eyelid_left, ...), sorted
    morph_targets: tuple[str, ...]  # the character's own rig (morph target names)
    notices: tuple[str, ...]  # what the backend could not honour (printed as "notice: ...")


def run(project: Project | str | os.PathLike, config: CharacterConfig) -> CharacterResult:
    """Text -> character: the mesh, its part labels and rig, and the frontal and orbit renders.

    Makes the character with ``config.backend``: ``procedural`` (offline archetypes: the prompt picks one, the
    seed varies it), ``diffusers`` (Shap-E weights in ``checkpoint``), ``command`` (an external generator run
    from a template without a shell) or ``file`` (``mesh``), and moves it to the canonical frame.

    Writes, in the project folder:
      - character/mesh.glb: the canonical character (part labels, morph targets of its rig);
      - renders/front.png [size, size, 3], renders/orbit/view00..14.png, renders/cameras.json, renders/done.json;
      - manifest.json: the ``character`` stage (backend, archetype, notices, params) and the ``render`` stage.

    Prints one ``notice:`` line per thing the backend could not honour, then a summary (mesh, parts, rig,
    renders). Raises UserError for a bad setting (size < 16, unknown backend, empty prompt, a template without
    {out}, missing weights, ...), before the project folder is written (a folder made by this run is removed
    again), and when another t2bs run holds the project. A re-run that makes the same mesh skips the rendering.
    """
    from t2bs.character.backends import generate
    from t2bs.character.render_stage import RenderConfig, render_project

    project = project if isinstance(project, Project) else Project(project)
    with project_lock(project.root, "character"):
        if config.size < 16:
            raise UserError("--size must be >= 16")
        result = generate(
            config.prompt,
            backend=config.backend,
            seed=config.seed,
            checkpoint=config.checkpoint,
            command=config.command,
            mesh_path=config.mesh,
            steps=config.steps,
            command_timeout=config.command_timeout,
        )
        for line in result.notices:
            print(f"notice: {line}")
        info = {k: v for k, v in result.info.items() if k != "params"}
        renders = render_project(
            result.mesh, project.root, {"backend": result.info["backend"]}, RenderConfig(size=config.size)
        )
        project.record_stage(
            "character",
            **info,
            notices=result.notices,
            params=result.info.get("params"),
            outputs={"mesh": "character/mesh.glb"},
        )
        parts = sorted(set(result.mesh.part_names))
        print(
            f"character: {project.mesh_path} ({result.mesh.num_vertices} vertices, backend {result.info['backend']}"
            + (f", archetype {result.info['archetype']}" if "archetype" in result.info else "")
            + ")"
        )
        if parts:
            print(f"parts:     {', '.join(parts)}")
        if result.mesh.morph_names:
            print(f"rig:       {', '.join(result.mesh.morph_names)}")
        print(f"renders:   {renders}")
    return CharacterResult(
        mesh_path=project.mesh_path,
        renders=renders,
        backend=result.info["backend"],
        archetype=result.info.get("archetype"),
        vertices=result.mesh.num_vertices,
        parts=tuple(parts),
        morph_targets=tuple(result.mesh.morph_names),
        notices=tuple(result.notices),
    )
