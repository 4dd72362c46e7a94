"""`t2bs render MESH -o DIR`: bring a character mesh into a project and render the paper's views.

Writes DIR/character/mesh.glb (canonical frame, morph targets and part labels kept), the
frontal image DIR/renders/front.png, the fixed-time orbit DIR/renders/orbit/view00..14.png, the
cameras (renders/cameras.json) and manifest.json. A re-run with the same mesh and settings
skips the work (content key in renders/done.json).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import typer
from tqdm import tqdm

from t2bs.errors import UserError
from t2bs.geometry.camera import ORBIT_VIEWS, frontal_camera, orbit_cameras
from t2bs.geometry.io import load_mesh, save_mesh
from t2bs.geometry.mesh import Mesh, detect_facing, normalize
from t2bs.project import Project, content_key, is_done, mark_done, write_image, write_json
from t2bs.project import locked


@dataclass
class RenderConfig:
    size: int = 512  # square image side, pixels (paper: 512, cropped as the video model needs)
    views: int = ORBIT_VIEWS  # orbit views over azimuth -60..60 deg (paper: 15)
    shading: str = "lambert"  # "lambert" (headlight) or "unlit" (ambient = 1, evaluation protocol)


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
        outputs={"mesh": "character/mesh.glb", "front": "renders/front.png", "orbit": f"renders/orbit/view00..{config.views - 1:02d}.png"},
        vertices=mesh.num_vertices,
        faces=int(mesh.faces.shape[0]),
        morph_targets=mesh.morph_names,
        seconds=round(seconds, 3),
    )
    return renders


@locked("out", "render")  # one run at a time per project (issue 39)
def render_command(
    mesh: Path = typer.Argument(..., help="Character mesh: .glb .gltf .vrm .obj .ply (morph targets are kept)."),
    out: Path = typer.Option(..., "-o", "--out", help="Project folder to create or update."),
    facing: str = typer.Option("auto", help="Axis the character faces: auto, +z, -z, +x, -x."),
    size: int = typer.Option(512, help="Image side in pixels."),
    views: int = typer.Option(ORBIT_VIEWS, help="Orbit views over azimuth -60..60 deg."),
    shading: str = typer.Option("lambert", help="lambert or unlit."),
) -> None:
    """Import a character mesh into a project folder and render the frontal and orbit views."""
    if size < 16 or views < 1:
        raise UserError("--size must be >= 16 and --views >= 1")
    if shading not in ("lambert", "unlit"):
        raise UserError(f"--shading must be lambert or unlit, got {shading!r}")
    character, info = canonical_character(mesh, facing)  # validates before anything is written
    renders = render_project(character, out, {"backend": "file", **info}, RenderConfig(size, views, shading))
    print(f"character: {Project(out).mesh_path}\nrenders:   {renders}")
