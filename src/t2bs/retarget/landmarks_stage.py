"""The landmarks stage (`t2bs landmarks DIR`): the character's 20 retargeting landmarks, as a library call."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from t2bs.errors import UserError
from t2bs.face.landmarks import Landmarks, find_project_landmarks
from t2bs.project import Project, project_lock


@dataclass
class LandmarksConfig:
    show: bool = False  # also write landmarks/overlay.png (the frontal render with the regions and the 20 points)
    backend: str = "auto"  # auto | parts | motion | grounding-sam (local Grounding-DINO + SAM checkpoints)
    override: Path | None = None  # the user's JSON with 20 "vertex_ids" or 20 "points2d" (pixels); None: find them


@dataclass
class LandmarksResult:
    path: Path  # landmarks/landmarks.json
    overlay: Path | None  # landmarks/overlay.png (None without show)
    backend: str  # what found them: parts | motion | grounding-sam | autorig | override
    landmarks: Landmarks  # the 20 (vertex_ids [20], points2d [20, 2], positions [20, 3], eyeballs, regions)


def load_model(project: Project, required: bool):
    """blendshapes/model.npz, or None when absent (UserError when ``required``)."""
    path = project.path("blendshapes", "model.npz")
    if not path.exists():
        if required:
            raise UserError(f"{project.path()}: no blendshapes/model.npz (build the blendshape model first)")
        return None
    from t2bs.blendshapes.model import load_model as load_blendshape_model

    return load_blendshape_model(path)


def run(project: "Project | str | os.PathLike", config: LandmarksConfig = LandmarksConfig()) -> LandmarksResult:
    """Find the character's 20 retargeting landmarks (6 per eye, 8 on the mouth) on its frontal render.

    Reads ``character/mesh.glb`` and, when present, ``blendshapes/model.npz`` (its neutral is the pose the
    landmarks are found on, and its named blink / mouth-open shapes serve the ``motion`` backend),
    ``character/autorig.json`` (backend "auto": the auto rig's own 20 landmarks are taken as they are) or the
    ``override`` JSON. Backend "auto" picks "parts" for a character with eye / mouth part labels (procedural
    ones), else "motion" (the character's blink and mouth-open shapes).

    Writes ``landmarks/landmarks.json`` (``vertex_ids`` [20] int in the 68-point order 36-47, 60-67,
    ``points2d`` [20, 2] pixels of the frontal camera, ``positions`` [20, 3], the camera, the backend, the
    eyeball vertices and the region sizes), ``landmarks/overlay.png`` [512, 512, 3] uint8 with ``show``, and
    the "landmarks" entry of ``manifest.json``. Each run finds them again and replaces the files (seconds).

    Raises UserError: no character, an override file that is missing or not valid JSON or holds no 20
    landmarks, an unknown backend, a character without eye / mouth labels or shapes (use "grounding-sam"
    or an override), another t2bs command holding the project.
    """
    project = project if isinstance(project, Project) else Project(project)
    with project_lock(project.root, "landmarks"):
        mesh = project.load_character()
        model = load_model(project, required=False)
        lm = find_project_landmarks(project, mesh, model, config.backend, config.override, config.show)
        path = project.path("landmarks", "landmarks.json")
        overlay = project.path("landmarks", "overlay.png") if config.show else None
        print(f"landmarks ({lm.backend}) -> {path}")
        if overlay is not None:
            print(f"overlay -> {overlay}")
        return LandmarksResult(path, overlay, lm.backend, lm)
