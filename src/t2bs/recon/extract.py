"""Per-frame meshes out of a trained VCDGS model (paper §3.2: "we designate v = 0 as the
canonical frame and use T_{0,t}"; §3.3: the splats are the mesh vertices).

Outputs of one reconstruction job (``write_outputs``): vertices.npy [T, N, 3], animation.glb
(the static asset with one morph target per frame, keyed over time), state.pt, preview.mp4
(input | reconstruction at the canonical view and at a side view), metrics.json.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from t2bs.geometry.mesh import Mesh
from t2bs.project import atomic_path, write_json


@torch.no_grad()
def canonical_vertices(model, chunk: int = 8) -> np.ndarray:
    """[T, N, 3] float32 vertex positions at the canonical view, without RefineMLP."""
    dev = model.means.device
    out = []
    for t0 in range(0, model.frames, chunk):
        t_idx = torch.arange(t0, min(t0 + chunk, model.frames), device=dev)
        v_idx = torch.full_like(t_idx, model.canonical_view)
        out.append(model(v_idx, t_idx, refine=False)["means"].cpu())
    return torch.cat(out).numpy().astype(np.float32)


def animated_mesh(mesh: Mesh, vertices: np.ndarray, times: np.ndarray) -> tuple[Mesh, dict]:
    """The static asset with one morph target per frame and a one-hot weight track over time."""
    t = vertices.shape[0]
    rest = mesh.vertices.astype(np.float32)
    targets = {f"frame{i:04d}": (vertices[i] - rest).astype(np.float32) for i in range(t)}
    anim_mesh = Mesh(mesh.vertices, mesh.faces, mesh.vertex_colors, mesh.uv, mesh.texture, targets, mesh.part_ids,
                     list(mesh.part_names))
    anim = {"times": np.asarray(times, np.float32), "weights": np.eye(t, dtype=np.float32), "name": "vcdgs"}
    return anim_mesh, anim


def preview_frames(mesh: Mesh, vertices: np.ndarray, grid, side_view: int, size: int = 256) -> np.ndarray:
    """[T, size, 4 * size, 3] uint8: input canonical | recon canonical | input side | recon side."""
    from t2bs.recon.vcdgs import resize_stack
    from t2bs.render.mesh_renderer import MeshRenderer

    cams = [grid.cameras[grid.canonical_view], grid.cameras[side_view]]
    h, w = grid.height, grid.width
    s = size / max(h, w)
    sz = (max(8, round(w * s)), max(8, round(h * s)))
    cams = [c.resized(*sz) for c in cams]
    rows = []
    inputs = [resize_stack(grid.frames[v], sz).numpy() for v in (grid.canonical_view, side_view)]  # [T, h, w, 3]
    shading = str((grid.meta.get("grid_config") or {}).get("shading", "lambert"))  # the grid renderer's, if known
    shading = shading if shading in ("unlit", "lambert") else "lambert"
    with MeshRenderer() as r:
        for t in range(vertices.shape[0]):
            tiles = []
            for j, cam in enumerate(cams):
                tiles.append(inputs[j][t])
                tiles.append(r.render(mesh, cam, vertices=vertices[t], shading=shading).rgb)
            rows.append(np.concatenate(tiles, axis=1))
    return (np.clip(np.stack(rows), 0, 1) * 255 + 0.5).astype(np.uint8)


def write_video(path: Path, frames: np.ndarray, fps: float) -> None:
    import imageio.v2 as iio

    with atomic_path(path) as tmp:
        with iio.get_writer(tmp, format="FFMPEG", fps=fps, codec="libx264", quality=8, macro_block_size=1,
                            ffmpeg_log_level="error") as wr:
            for f in frames:
                wr.append_data(f)


def write_outputs(out_dir: Path, mesh: Mesh, grid, result, cfg, metrics: dict, preview: bool = True) -> None:
    """Everything but done.json (the caller marks the job done last)."""
    from t2bs.geometry.io import save_mesh

    out_dir.mkdir(parents=True, exist_ok=True)
    with atomic_path(out_dir / "vertices.npy") as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, result.vertices)
    anim_mesh, anim = animated_mesh(mesh, result.vertices, grid.times)
    save_mesh(anim_mesh, out_dir / "animation.glb", animation=anim)
    with atomic_path(out_dir / "state.pt") as tmp:
        torch.save({"model": result.model.state_dict(), "config": cfg.to_dict(), "history": result.history,
                    "canonical_view": result.model.canonical_view, "views": result.model.views,
                    "frames": result.model.frames}, tmp)
    if preview:
        side = cfg.preview_side_view if 0 <= cfg.preview_side_view < grid.num_views else 0
        frames = preview_frames(mesh, result.vertices, grid, side)
        write_video(out_dir / "preview.mp4", frames, float(grid.meta.get("fps", 8.0)))
    write_json(out_dir / "metrics.json", metrics)
