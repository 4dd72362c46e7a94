"""`t2bs character PROMPT -o DIR` and `t2bs gallery -o DIR`."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import typer

from t2bs.errors import UserError
from t2bs.project import locked

# The paper's 10 characters (Tables in the appendix) and 6 more archetypes.
GALLERY_PROMPTS = [
    ("plant", "a cute plant creature with a flower head"),
    ("bug", "a cartoon bug with antennae"),
    ("shark", "a cartoon shark"),
    ("alien", "a green alien"),
    ("indoraptor", "an indoraptor dinosaur"),
    ("deer", "a deer with antlers"),
    ("cryinghead", "a crying cartoon head"),
    ("corgi", "a corgi"),
    ("robot", "a robot"),
    ("fox", "a cartoon fox with big ears"),
    ("cat", "a grey striped cat"),
    ("bear", "a brown bear"),
    ("rabbit", "a white rabbit with long ears"),
    ("owl", "an owl"),
    ("frog", "a green frog"),
    ("monster", "a blue monster with horns"),
]


@locked("out", "character")  # one run at a time per project (issue 39)
def character_command(
    prompt: str = typer.Argument(..., help="Text describing the character, e.g. \"a cartoon fox with big ears\"."),
    out: Path = typer.Option(..., "-o", "--out", help="Project folder to create or update."),
    backend: str = typer.Option("procedural", help="procedural (offline), diffusers (Shap-E: openai/shap-e weights, MIT licence), command, file."),
    seed: int = typer.Option(0, help="Random seed: same prompt + seed -> same character."),
    checkpoint: Path = typer.Option(None, help="diffusers: local Shap-E folder (default ~/.cache/t2bs/checkpoints/shap-e)."),
    command: str = typer.Option(None, help="command: template with {prompt} {out} {seed}; it writes a mesh into {out}. Run without a shell (docs/HOSTILE_INPUTS.md)."),
    command_timeout: float = typer.Option(3600.0, help="command: seconds before the command is killed (0 = no limit)."),
    mesh: Path = typer.Option(None, help="file: a mesh (.glb .gltf .vrm .obj .ply)."),
    steps: int = typer.Option(64, help="diffusers: denoising steps."),
    size: int = typer.Option(512, help="Render size in pixels."),
) -> None:
    """Text -> character: DIR/character/mesh.glb (parts, rig morph targets) and the renders."""
    from t2bs.character.backends import generate
    from t2bs.commands_render import RenderConfig, render_project
    from t2bs.project import Project

    if size < 16:
        raise UserError("--size must be >= 16")
    result = generate(prompt, backend=backend, seed=seed, checkpoint=checkpoint, command=command, mesh_path=mesh,
                      steps=steps, command_timeout=command_timeout)
    for line in result.notices:
        print(f"notice: {line}")
    project = Project(out)
    info = {k: v for k, v in result.info.items() if k != "params"}
    renders = render_project(result.mesh, out, {"backend": result.info["backend"]}, RenderConfig(size=size))
    project.record_stage("character", **info, notices=result.notices,
                         params=result.info.get("params"), outputs={"mesh": "character/mesh.glb"})
    parts = sorted(set(result.mesh.part_names))
    print(f"character: {project.mesh_path} ({result.mesh.num_vertices} vertices, backend {result.info['backend']}"
          + (f", archetype {result.info['archetype']}" if "archetype" in result.info else "") + ")")
    if parts:
        print(f"parts:     {', '.join(parts)}")
    if result.mesh.morph_names:
        print(f"rig:       {', '.join(result.mesh.morph_names)}")
    print(f"renders:   {renders}")


def render_gallery(out: Path, seed: int = 0, size: int = 320, prompts=GALLERY_PROMPTS) -> tuple[Path, dict]:
    """Front and three-quarter views of every prompt in one labelled PNG grid (4 characters a row)."""
    from PIL import Image, ImageDraw

    from t2bs.character.procedural import generate_procedural
    from t2bs.geometry.camera import orbit_camera
    from t2bs.project import write_image, write_json
    from t2bs.render.mesh_renderer import MeshRenderer

    cols, label_h = 4, 26
    cell_w, cell_h = 2 * size, size + label_h
    rows = (len(prompts) + cols - 1) // cols
    sheet = np.ones((rows * cell_h, cols * cell_w, 3), np.float32)
    stats = {}
    cams = [orbit_camera(0.0, 10.0, size=size), orbit_camera(40.0, 10.0, size=size)]
    with MeshRenderer() as renderer:
        for i, (name, prompt) in enumerate(prompts):
            t0 = time.perf_counter()
            result = generate_procedural(prompt, seed)
            seconds = time.perf_counter() - t0
            r, c = divmod(i, cols)
            for k, cam in enumerate(cams):
                img = renderer.render(result.mesh, cam).rgb
                sheet[r * cell_h + label_h:(r + 1) * cell_h, c * cell_w + k * size:c * cell_w + (k + 1) * size] = img
            stats[name] = {"prompt": prompt, "archetype": result.info["archetype"],
                           "vertices": result.mesh.num_vertices, "seconds": round(seconds, 3)}
    image = Image.fromarray((np.clip(sheet, 0, 1) * 255).astype(np.uint8))
    draw = ImageDraw.Draw(image)
    for i, (name, prompt) in enumerate(prompts):
        r, c = divmod(i, cols)
        draw.text((c * cell_w + 8, r * cell_h + 6), f"{name}: \"{prompt}\"", fill=(20, 20, 20))
        if c:
            draw.line([(c * cell_w, r * cell_h), (c * cell_w, (r + 1) * cell_h)], fill=(200, 200, 200))
    path = Path(out) / "gallery.png"
    write_image(path, np.asarray(image))
    write_json(Path(out) / "gallery.json", {"seed": seed, "characters": stats})
    return path, stats


def gallery_command(
    out: Path = typer.Option(..., "-o", "--out", help="Folder for gallery.png and gallery.json."),
    seed: int = typer.Option(0, help="Random seed for every character."),
    size: int = typer.Option(320, help="Pixels per view."),
) -> None:
    """Render 16 procedural characters (the paper's 10 and 6 more), front and three-quarter view."""
    if size < 32:
        raise UserError("--size must be >= 32")
    path, stats = render_gallery(out, seed, size)
    total = sum(s["seconds"] for s in stats.values())
    print(f"gallery: {path} ({len(stats)} characters, generation {total:.1f} s in all)")
