"""A tiny project folder for the viewer tests, built from scratch (no assets in the repo).

The character is a coloured sphere with the canonical size (bounding-box diagonal 1.2) and two
blendshapes with disjoint support, so a test can tell *where* a slider moved the surface:

- ``pc000``: the character's upper right (-X, +Y, front) slides up ("brow raise"), i.e. the image's
  upper left in the frontal view, clear of viser's overlays (notification top-left corner, panel on
  the right);
- ``pc001``: the lower front ("jaw") pushed down and forward.

Plus a named shape ``jaw_open`` (= 1.0 x pc001 in the basis), a 4-frame reconstructed capture of
the bump with its 3-view input grid, and a retargeting result whose CSV has a time column, a PCA
column, a semantic column and a column that names nothing.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

BUMP_DIR = np.array([-0.55, 0.45, 0.70])  # direction of the bump centre (character's right, up, front)
JAW_DIR = np.array([0.0, -0.65, 0.76])  # direction of the jaw centre
PEAK = 0.10  # world units a unit-weight shape moves its peak vertex: ~8 % of the bbox diagonal
CAPTURE_ID = "bump-s0"
RETARGET_NAME = "face"


def sphere(subdivisions: int = 4):
    import trimesh

    radius = 1.2 / (2 * np.sqrt(3.0))  # bounding-box diagonal 1.2 (the canonical frame)
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.int32)


def _bump(vertices: np.ndarray, direction: np.ndarray, width: float, along: np.ndarray | None = None) -> np.ndarray:
    """[N, 3] offsets: a Gaussian bump around ``direction`` (angular width in radians), along the
    normal or along ``along``; zero (exactly) far from it so the support is compact."""
    n = vertices / np.linalg.norm(vertices, axis=1, keepdims=True)
    d = direction / np.linalg.norm(direction)
    ang = np.arccos(np.clip(n @ d, -1, 1))
    w = np.exp(-((ang / width) ** 2))
    w[ang > 2.5 * width] = 0.0
    dirs = n if along is None else np.broadcast_to(along / np.linalg.norm(along), n.shape)
    return (w[:, None] * dirs).astype(np.float64)


def colours(vertices: np.ndarray) -> np.ndarray:
    """[N, 3] a warm skin colour with darker latitude bands, so shading changes are visible."""
    n = vertices / np.linalg.norm(vertices, axis=1, keepdims=True)
    band = 0.5 + 0.5 * np.cos(n[:, 1] * 9.0)
    base = np.array([0.93, 0.66, 0.45])
    dark = np.array([0.55, 0.30, 0.20])
    return (base[None] * band[:, None] + dark[None] * (1 - band[:, None])).astype(np.float32)


def build_fixture_project(root: Path, with_model: bool = True) -> dict:
    """Write the project under ``root``; returns the arrays a test compares against."""
    from t2bs.geometry.camera import orbit_cameras
    from t2bs.geometry.io import save_mesh
    from t2bs.geometry.mesh import Mesh

    root = Path(root)
    v, f = sphere()
    n = len(v)
    bump = _bump(v, BUMP_DIR, 0.30, along=np.array([0.0, 1.0, 0.2]))  # a "brow raise": slides the colour bands up
    jaw = _bump(v, JAW_DIR, 0.35, along=np.array([0.0, -1.0, 0.6]))
    # Orthonormal rows over the flattened vertices (the model's contract): the supports are
    # disjoint, so Gram-Schmidt only normalises.
    b0 = bump.reshape(-1) / np.linalg.norm(bump)
    b1 = jaw.reshape(-1) - (jaw.reshape(-1) @ b0) * b0
    b1 /= np.linalg.norm(b1)
    basis = np.stack([b0, b1]).reshape(2, n, 3).astype(np.float32)  # [K=2, N, 3]
    # Weight at which the peak vertex moves by PEAK.
    scale = np.array([PEAK / np.linalg.norm(basis[k], axis=1).max() for k in range(2)])

    mesh = Mesh(
        vertices=v,
        faces=f,
        vertex_colors=colours(v),
        morph_targets={"smile": (bump * PEAK).astype(np.float32), "jaw_open": (jaw * PEAK).astype(np.float32)},
    )
    save_mesh(mesh, root / "character" / "mesh.glb")
    info = {
        "neutral": v,
        "faces": f,
        "basis": basis,
        "scale": scale,
        "colors": mesh.vertex_colors,
        "morph_targets": mesh.morph_targets,
    }
    if not with_model:
        return info

    from t2bs.blendshapes.model import BlendshapeModel, save_model

    t = 4
    cap_w = np.zeros((t, 2), np.float32)
    cap_w[:, 0] = np.linspace(0, 1, t) * scale[0]  # the bump grows over the capture
    recon = (v[None].astype(np.float64) + np.einsum("tk,knc->tnc", cap_w, basis)).astype(np.float32)  # [T, N, 3]
    model = BlendshapeModel(
        neutral=v,
        basis=basis,
        singular_values=np.array([2.0, 1.0]),
        names=["pc000", "pc001"],
        explained_variance=np.array([0.8, 0.2]),
        capture_weights={CAPTURE_ID: cap_w},
        semantic_names=["jaw_open"],
        semantic_weights=np.array([[0.0, scale[1]]], np.float32),
        semantic_sources=[f"{CAPTURE_ID}:3"],
        meta={"source": "viewer test fixture"},
    )
    save_model(model, root / "blendshapes" / "model.npz")

    (root / "recon" / CAPTURE_ID).mkdir(parents=True)
    np.save(root / "recon" / CAPTURE_ID / "vertices.npy", recon)
    frames = input_frames(views=3, t=t, size=64)
    _save_grid(root / "videos" / CAPTURE_ID, frames, orbit_cameras(3, size=64))

    rows = np.array([[i / 10, 0.5 * scale[0] * i / 4, 0.8 * i / 4, 7.0] for i in range(5)])
    csv = "time,pc000,jaw_open,not_a_shape\n" + "\n".join(",".join(f"{x:.6f}" for x in r) for r in rows) + "\n"
    (root / "retarget" / RETARGET_NAME).mkdir(parents=True)
    (root / "retarget" / RETARGET_NAME / "weights.csv").write_text(csv)
    info.update(model=model, recon=recon, frames=frames, capture_weights=cap_w, retarget_rows=rows)
    return info


def input_frames(views: int, t: int, size: int) -> np.ndarray:
    """[V, T, H, W, 3] uint8: a disc whose radius grows with t and whose colour encodes the view."""
    yy, xx = np.mgrid[:size, :size]
    out = np.full((views, t, size, size, 3), 255, np.uint8)
    for vi in range(views):
        for ti in range(t):
            r = size * (0.2 + 0.05 * ti)
            disc = (xx - size / 2) ** 2 + (yy - size / 2) ** 2 < r * r
            out[vi, ti][disc] = (60 + 80 * vi, 120, 200 - 60 * vi)
    return out


def _save_grid(folder: Path, frames: np.ndarray, cameras) -> None:
    from t2bs.video.grid import VideoGrid, save_grid

    nv, nt = frames.shape[:2]
    grid = VideoGrid(
        frames=frames,
        cameras=cameras,
        times=(np.arange(nt) / 8.0).astype(np.float32),
        canonical_view=nv // 2,
        masks=None,
        gt_vertices=None,
        backend="test-fixture",
        meta={"fps": 8.0, "expression": "bump"},
    )
    save_grid(grid, folder)
