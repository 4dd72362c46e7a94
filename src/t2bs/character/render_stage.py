"""The render stage: bring a character mesh into a project and render the paper's views.

`run(project, RenderStageConfig(mesh=...))` is `t2bs render MESH -o DIR`; `render_project` is the part the
character stage shares (save the canonical mesh, render the frontal and orbit images, resumable);
`canonical_character` loads any mesh file into the canonical frame (also used by the benchmarks).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from t2bs.errors import UserError
from t2bs.geometry.camera import ORBIT_VIEWS, frontal_camera, orbit_cameras
from t2bs.geometry.io import load_mesh, save_mesh
from t2bs.geometry.mesh import Mesh, detect_facing, normalize
from t2bs.project import Project, content_key, is_done, mark_done, project_lock, write_image, write_json


@dataclass
class RenderConfig:
    size: int = 512  # square image side, pixels (paper: 512, cropped as the video model needs)
    views: int = ORBIT_VIEWS  # orbit views over azimuth -60..60 deg (paper: 15)
    shading: str = "lambert"  # "lambert" (headlight) or "unlit" (ambient = 1, evaluation protocol)


@dataclass(kw_only=True)
class RenderStageConfig(RenderConfig):
    """`t2bs render`'s settings: the render settings (size, views, shading) plus the mesh to bring in."""

    mesh: Path  # the character mesh file: .glb .gltf .vrm .obj .ply (morph targets and part labels are kept)
    facing: str = "auto"  # axis the character faces in the file: auto, +z, -z, +x, -x

    def render_config(self) -> RenderConfig:
        """The render settings alone: what the renders' content key and the manifest hold (not the mesh's path)."""
        return RenderConfig(self.size, self.views, self.shading)


@dataclass
class RenderStageResult:
    mesh_path: Path  # DIR/character/mesh.glb (canonical frame)
    renders: Path  # DIR/renders (front.png, orbit/view00..NN.png, cameras.json)
    facing: str  # the axis the character faced in the file (auto resolved)
    vertices: int  # vertex count of the character
    views: int  # orbit views rendered


def canonical_character(path: Path, facing: str = "auto") -> tuple[Mesh, dict]:
    """Load any mesh file and move it to the canonical frame; returns (mesh, info for the manifest)."""
    mesh = load_mesh(path)
    if facing == "auto":
        facing = "-z" if path.suffix.lower() == ".vrm" else detect_facing(mesh)  # VRM 0.x faces -Z
    mesh, transform = normalize(mesh, facing)
    return mesh, {"source": str(path), "facing": facing, "transform": transform}


def render_project(mesh: Mesh, out_dir: Path, backend_info: dict, config: RenderConfig = RenderConfig()) -> Path:
    """Save ``mesh`` as DIR/character/mesh.glb and render the frontal + orbit images (resumable)."""
    project = Project(out_dir)
    t0 = time.perf_counter()
    # glb bytes are deterministic for a given mesh, so an unchanged character keeps its key.
    mesh_path = save_mesh(mesh, project.mesh_path)
    renders = project.path("renders")
    key = content_key(mesh_path, config)
    if is_done(renders, key):
        print(f"renders up to date in {renders}")
        return renders
    from t2bs.render.mesh_renderer import MeshRenderer

    cameras = orbit_cameras(config.views, config.size)
    front = frontal_camera(config.size)
    with MeshRenderer() as renderer:
        write_image(renders / "front.png", renderer.render(mesh, front, shading=config.shading).rgb)
        for i, cam in enumerate(tqdm(cameras, desc="orbit views", unit="view")):
            write_image(renders / "orbit" / f"view{i:02d}.png", renderer.render(mesh, cam, shading=config.shading).rgb)
    write_json(renders / "cameras.json", {"front": front.to_dict(), "orbit": [c.to_dict() for c in cameras]})
    seconds = time.perf_counter() - t0
    mark_done(renders, key, seconds=round(seconds, 3))
    project.record_stage(
        "render",
        **backend_info,
        config=config,
        outputs={
            "mesh": "character/mesh.glb",
            "front": "renders/front.png",
            "orbit": f"renders/orbit/view00..{config.views - 1:02d}.png",
        },
        vertices=mesh.num_vertices,
        faces=int(mesh.faces.shape[0]),
        morph_targets=mesh.morph_names,
        seconds=round(seconds, 3),
    )
    return renders


def run(project: Project | str | os.PathLike, config: RenderStageConfig) -> RenderStageResult:
    """Import a character mesh into a project folder and render the frontal and orbit views.

    Reads ``config.mesh`` (glTF/GLB, VRM, OBJ or PLY; morph targets and part labels are kept), turns it to face
    ``config.facing`` (auto: detected; VRM 0.x files face -Z) and moves it to the canonical frame (Y up, facing
    +Z, centred, bounding-box diagonal 1.2).

    Writes, in the project folder:
      - character/mesh.glb: the canonical character;
      - renders/front.png [size, size, 3] and renders/orbit/view00..NN.png (``views`` images over azimuth
        -60..60 deg), shaded ``lambert`` (headlight) or ``unlit``;
      - renders/cameras.json (the cameras), renders/done.json (content key of the mesh and render settings);
      - manifest.json: the ``render`` stage (source file, facing, transform, settings, counts).

    Raises UserError for a bad setting (size < 16, views < 1, unknown shading or facing) or an unreadable,
    empty or broken mesh, before anything is written (a project folder made by this run is removed again), and
    when another t2bs run holds the project. A re-run with the same mesh and settings skips the rendering
    ("renders up to date").
    """
    project = project if isinstance(project, Project) else Project(project)
    with project_lock(project.root, "render"):
        if config.size < 16 or config.views < 1:
            raise UserError("--size must be >= 16 and --views >= 1")
        if config.shading not in ("lambert", "unlit"):
            raise UserError(f"--shading must be lambert or unlit, got {config.shading!r}")
        # Validates the mesh before anything is written.
        character, info = canonical_character(Path(config.mesh), config.facing)
        renders = render_project(character, project.root, {"backend": "file", **info}, config.render_config())
        print(f"character: {project.mesh_path}\nrenders:   {renders}")
    return RenderStageResult(
        mesh_path=project.mesh_path,
        renders=renders,
        facing=info["facing"],
        vertices=character.num_vertices,
        views=config.views,
    )
