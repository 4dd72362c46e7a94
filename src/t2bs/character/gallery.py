"""A contact sheet of procedural characters (`t2bs gallery -o DIR`): not a project stage, a folder of two files."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from t2bs.errors import UserError

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


def render_gallery(out: Path, seed: int = 0, size: int = 320, prompts=GALLERY_PROMPTS) -> tuple[Path, dict]:
    """Front and three-quarter views of every prompt in one labelled PNG grid (4 characters a row).

    Writes DIR/gallery.png ([rows * (size + 26), 4 * 2 * size, 3]) and DIR/gallery.json (seed; per character
    its prompt, archetype, vertex count and generation seconds). Returns (gallery.png's path, that per-character
    dict). UserError when ``size`` < 32.
    """
    from PIL import Image, ImageDraw

    from t2bs.character.procedural import generate_procedural
    from t2bs.geometry.camera import orbit_camera
    from t2bs.project import write_image, write_json
    from t2bs.render.mesh_renderer import MeshRenderer

    if size < 32:
        raise UserError("--size must be >= 32")
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
                sheet[r * cell_h + label_h : (r + 1) * cell_h, c * cell_w + k * size : c * cell_w + (k + 1) * size] = (
                    img
                )
            stats[name] = {
                "prompt": prompt,
                "archetype": result.info["archetype"],
                "vertices": result.mesh.num_vertices,
                "seconds": round(seconds, 3),
            }
    image = Image.fromarray((np.clip(sheet, 0, 1) * 255).astype(np.uint8))
    draw = ImageDraw.Draw(image)
    for i, (name, prompt) in enumerate(prompts):
        r, c = divmod(i, cols)
        draw.text((c * cell_w + 8, r * cell_h + 6), f'{name}: "{prompt}"', fill=(20, 20, 20))
        if c:
            draw.line([(c * cell_w, r * cell_h), (c * cell_w, (r + 1) * cell_h)], fill=(200, 200, 200))
    path = Path(out) / "gallery.png"
    write_image(path, np.asarray(image))
    write_json(Path(out) / "gallery.json", {"seed": seed, "characters": stats})
    return path, stats
