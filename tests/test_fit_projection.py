"""The fit's differentiable vertex splatter (blendshapes.fit.splat_vertices) on cases small enough to compute by hand.

Its projection is the shared one (recon.tracks.project_points, the camera model of geometry.camera); before its own
copy was removed the two agreed on 20 random cameras/meshes to 2.9e-6 (float32) / 5.3e-15 (float64) in the image
and 9e-6 / 1.2e-14 relative in the vertex gradients.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from t2bs.blendshapes.fit import splat_vertices  # noqa: E402
from t2bs.geometry.camera import Camera, orbit_camera  # noqa: E402


def _camera() -> Camera:
    """8x8 pixels, focal 4, principal point at the centre; the camera sits at z = -2 looking along +z."""
    w2c = np.eye(4)
    w2c[2, 3] = 2.0
    return Camera(np.array([[4.0, 0.0, 4.0], [0.0, 4.0, 4.0], [0.0, 0.0, 1.0]]), w2c, 8, 8)


def test_one_vertex_by_hand():
    # World (0.5, -0.25, 0) -> camera (0.5, -0.25, 2) -> pixel (4 * 0.5 / 2 + 4, 4 * -0.25 / 2 + 4) = (5, 3.5): with
    # pixel centres at integer coordinates that is u = 4.5 (halfway between columns 4 and 5), v = 3 (row 3).
    # One vertex: sigma = clip(0.6 * sqrt((8 * 0.55)^2 / 1), 0.6, 1.5) = 1.5, taps at columns 4 - 2 .. 4 + 3.
    x = torch.tensor([[[0.5, -0.25, 0.0]]], dtype=torch.float64)
    colour = torch.tensor([[0.2, 0.4, 0.8]], dtype=torch.float64)
    img = splat_vertices(x, colour, _camera(), torch.ones(1, 1)).numpy()[0]  # [H, W, 3]

    def expected(row: int, col: int) -> np.ndarray:
        g = math.exp(-((col - 4.5) ** 2 + (row - 3.0) ** 2) / (2 * 1.5**2))
        alpha = 1 - math.exp(-g)
        return alpha * (g * colour[0].numpy() / (g + 1e-6)) + (1 - alpha) * 1.0

    for row, col in [(3, 4), (3, 5), (3, 7), (1, 4), (5, 2), (4, 6)]:
        np.testing.assert_allclose(img[row, col], expected(row, col), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(img[3, 4], img[3, 5], atol=1e-15)  # symmetric about u = 4.5
    assert (img[:, 1] == 1.0).all() and (img[0] == 1.0).all()  # outside the tap window: background


def test_hidden_vertex_leaves_the_background_and_gradient_matches_finite_differences():
    x = torch.tensor([[[0.5, -0.25, 0.0], [0.1, 0.1, 0.0]]], dtype=torch.float64, requires_grad=True)
    colour = torch.tensor([[0.2, 0.4, 0.8], [0.9, 0.1, 0.1]], dtype=torch.float64)
    vis = torch.tensor([[1.0, 0.0]])
    cam = _camera()
    img = splat_vertices(x, colour, cam, vis)
    only = splat_vertices(x[:, :1].detach(), colour[:1], cam, vis[:, :1])
    np.testing.assert_allclose(img.detach().numpy(), only.numpy(), atol=1e-12)
    # d image[3, 5] / d x of the visible vertex, against central differences.
    img[0, 3, 5].sum().backward()
    eps = 1e-6
    for axis in range(3):
        d = torch.zeros_like(x)
        d[0, 0, axis] = eps
        fd = (
            splat_vertices(x.detach() + d, colour, cam, vis)[0, 3, 5].sum()
            - splat_vertices(x.detach() - d, colour, cam, vis)[0, 3, 5].sum()
        ) / (2 * eps)
        assert float(x.grad[0, 0, axis]) == pytest.approx(float(fd), rel=1e-5, abs=1e-9)
    assert float(x.grad[0, 1].abs().sum()) == 0.0  # the hidden vertex gets no gradient


def test_footprint_centre_is_the_cameras_projection():
    """The brightest pixel of a lone dark vertex is the one nearest to Camera.project (pixel (i, j) centre at
    (j + 0.5, i + 0.5)), for random orbit cameras."""
    rng = np.random.default_rng(0)
    for _ in range(10):
        cam = orbit_camera(rng.uniform(-60, 60), rng.uniform(-15, 25), 2.25, size=int(rng.integers(32, 97)))
        p = rng.normal(0, 0.15, (1, 3))
        ((u, v),), _ = cam.project(p)
        img = splat_vertices(torch.tensor(p[None]), torch.zeros(1, 3, dtype=torch.float64), cam, torch.ones(1, 1))
        row, col = np.unravel_index(int(img[0, ..., 0].argmin()), img.shape[1:3])
        assert (row, col) == (int(np.floor(v)), int(np.floor(u)))
