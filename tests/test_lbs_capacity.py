"""benchmarks/lbs_capacity.py: its linear motion model is the skinning's first-order motion, column by column."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _module():
    spec = importlib.util.spec_from_file_location("lbs_capacity", ROOT / "benchmarks" / "lbs_capacity.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_motion_design_is_the_skinned_translations_rotations_and_shapes():
    rng = np.random.default_rng(0)
    n, k, knn, j = 40, 5, 3, 2
    x = rng.normal(size=(n, 3))
    p = x[rng.choice(n, k, replace=False)]
    nb = np.stack([rng.choice(k, knn, replace=False) for _ in range(n)])  # [N, knn]
    w = rng.random((n, knn))
    w /= w.sum(1, keepdims=True)
    shapes = rng.normal(size=(j, n, 3))
    t, omega, c = rng.normal(size=(k, 3)), rng.normal(size=(k, 3)), rng.normal(size=j)
    expected = np.einsum("nq,nqc->nc", w, t[nb] + np.cross(omega[nb], x[:, None] - p[nb])) + np.einsum(
        "j,jnc->nc", c, shapes
    )
    motion_design = _module().motion_design
    design = motion_design(x, p, nb, w, True, shapes)
    params = np.concatenate([np.concatenate([t, omega], 1).ravel(), c])
    np.testing.assert_allclose((design @ params).reshape(n, 3), expected, atol=1e-12)
    # translations only, no shapes: the blend of the control points' translations
    plain = motion_design(x, p, nb, w, False, None)
    np.testing.assert_allclose((plain @ t.ravel()).reshape(n, 3), np.einsum("nq,nqc->nc", w, t[nb]), atol=1e-12)
