"""Per-frame meshes out of a trained VCDGS model (paper §3.2: "we designate v = 0 as the
canonical frame and use T_{0,t}"; §3.3: the splats are the mesh vertices), with the per-vertex
fitting noise smoothed out of their displacement (``smooth_displacements``).

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


def smooth_displacements(
    vertices: np.ndarray, rest: np.ndarray, faces: np.ndarray, iterations: int = 4, step: float = 0.5
) -> np.ndarray:
    """``vertices`` [T, N, 3] with the high frequencies of their deformation removed; ``rest`` [N, 3].

    Why: each vertex is one Gaussian fitted through images, so neighbouring vertices carry small
    independent errors (a fraction of a pixel) that barely move p2p but tilt the normals (clean
    grids, quick preset: facecap smiling NC .00389 -> .00270 with 4 iterations, p2p moving
    0.209 -> 0.210 of static; turtle mouth wide NC .00952 -> .00891). Per frame, the rigid
    motion that best maps ``rest`` onto the frame (Kabsch) is taken out, the remaining
    displacement gets ``iterations`` steps of uniform Laplacian smoothing over the mesh edges
    (x += step * (neighbour mean - x)), and the rigid motion is put back, so a rigidly moving
    character is returned unchanged. Coincident vertices (split at UV seams) are welded for the
    smoothing, so seams stay closed; vertices outside any face keep their positions."""
    import roma
    from scipy.sparse import coo_matrix, diags

    from t2bs.geometry.mesh import weld_index, welded_edges

    x = np.asarray(vertices, np.float64)
    if iterations <= 0 or len(faces) == 0:
        return np.asarray(vertices, np.float32).copy()
    rest = np.asarray(rest, np.float64)
    n = rest.shape[0]
    node, first = weld_index(rest)
    m = len(first)
    e = welded_edges(node, faces)
    adj = coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(m, m)).tocsr()
    deg = np.asarray(adj.sum(1)).ravel()
    mean_of_neighbours = diags(1.0 / np.maximum(deg, 1.0)) @ adj
    has = (deg > 0)[:, None]
    # per node, averaging its (welded) vertices
    pool = coo_matrix((np.ones(n), (node, np.arange(n))), shape=(m, n)).tocsr()
    pool = diags(1.0 / np.asarray(pool.sum(1)).ravel()) @ pool
    rot, trans = roma.rigid_points_registration(torch.as_tensor(rest)[None].expand(len(x), -1, -1), torch.as_tensor(x))
    rot, trans = rot.numpy(), trans.numpy()  # [T, 3, 3], [T, 3]: x ~ rest @ R^T + t
    out = np.empty_like(x)
    for i in range(len(x)):
        local = pool @ ((x[i] - trans[i]) @ rot[i] - rest)  # [m, 3] displacement without the rigid motion
        for _ in range(iterations):
            local = np.where(has, local + step * (mean_of_neighbours @ local - local), local)
        out[i] = (rest + local[node]) @ rot[i].T + trans[i]
    return out.astype(np.float32)


def animated_mesh(mesh: Mesh, vertices: np.ndarray, times: np.ndarray) -> tuple[Mesh, dict]:
    """The static asset with one morph target per frame and a one-hot weight track over time."""
    t = vertices.shape[0]
    rest = mesh.vertices.astype(np.float32)
    targets = {f"frame{i:04d}": (vertices[i] - rest).astype(np.float32) for i in range(t)}
    anim_mesh = Mesh(
        mesh.vertices,
        mesh.faces,
        mesh.vertex_colors,
        mesh.uv,
        mesh.texture,
        targets,
        mesh.part_ids,
        list(mesh.part_names),
    )
    anim = {"times": np.asarray(times, np.float32), "weights": np.eye(t, dtype=np.float32), "name": "vcdgs"}
    return anim_mesh, anim


def preview_frames(mesh: Mesh, vertices: np.ndarray, grid, side_view: int, size: int = 256) -> np.ndarray:
    """[T, size, 4 * size, 3] uint8: input canonical | recon canonical | input side | recon side."""
    from t2bs.recon.images import resize_stack
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
        with iio.get_writer(
            tmp, format="FFMPEG", fps=fps, codec="libx264", quality=8, macro_block_size=1, ffmpeg_log_level="error"
        ) as wr:
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
        torch.save(
            {
                "model": result.model.state_dict(),
                "config": cfg.to_dict(),
                "history": result.history,
                "canonical_view": result.model.canonical_view,
                "views": result.model.views,
                "frames": result.model.frames,
            },
            tmp,
        )
    if preview:
        frames = preview_frames(mesh, result.vertices, grid, side_view=0)
        write_video(out_dir / "preview.mp4", frames, float(grid.meta.get("fps", 8.0)))
    write_json(out_dir / "metrics.json", metrics)
