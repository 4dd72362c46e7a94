"""Rigid motion of point sets over frames: the dominant (head) motion and what is left without it.

Used by the expression metric (geometry.metrics), by PCA over captures (blendshapes: no component may be a head turn)
and by the pick of hidden parts (recon.hidden_parts). numpy in, numpy out.
"""

from __future__ import annotations

import numpy as np


def robust_rigid_motion(rest: np.ndarray, vertices: np.ndarray, iterations: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """The dominant rigid motion of points ``rest`` [n, 3] moving to ``vertices`` [T, n, 3].

    Returns (rotations [T, 3, 3], translations [T, 3]) with ``vertices ~ rest @ R^T + t``: a least-squares fit
    (Kabsch) refitted ``iterations`` - 1 times with Cauchy weights on its residuals (scale: their median per frame),
    so points that deform (smiling lips, a closing lid) drop out and the motion most of them share (the head's)
    remains. One plain fit would be pulled towards the deforming points."""
    import roma
    import torch

    x = torch.as_tensor(np.asarray(rest), dtype=torch.float64).expand(len(vertices), -1, -1)
    y = torch.as_tensor(np.asarray(vertices), dtype=torch.float64)
    w = torch.ones(y.shape[:2], dtype=torch.float64)
    for _ in range(max(int(iterations), 1)):
        r, t = roma.rigid_points_registration(x, y, weights=w)
        residual = (x @ r.transpose(-1, -2) + t[:, None] - y).norm(dim=-1)  # [T, n]
        scale = residual.median(dim=1, keepdim=True).values.clamp_min(1e-12)
        w = 1.0 / (1.0 + (residual / scale) ** 2)
    return r.numpy(), t.numpy()


def apply_motion(rotations: np.ndarray, translations: np.ndarray, points: np.ndarray) -> np.ndarray:
    """rotations [T, 3, 3], translations [T, 3], rest points [n, 3] -> [T, n, 3]."""
    return apply_rigid_frames(rotations, translations, np.broadcast_to(points, (len(rotations), *np.shape(points))))


def apply_rigid_frames(rotations: np.ndarray, translations: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Each frame of ``vertices`` [T, n, 3] moved by its own rigid motion (R x + t) -> [T, n, 3]."""
    return np.einsum("tij,tnj->tni", rotations, np.asarray(vertices, np.float64)) + translations[:, None]


def remove_motion(rotations: np.ndarray, translations: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """The inverse of ``apply_motion``: vertices [T, n, 3] moved back by each frame's rigid motion -> [T, n, 3]
    (R^T (x - t)), i.e. the frames as seen from the head."""
    return np.einsum("tji,tnj->tni", rotations, np.asarray(vertices, np.float64) - translations[:, None])


def nonrigid_displacements(
    rest: np.ndarray, vertices: np.ndarray, iterations: int = 10
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split ``vertices`` [T, n, 3] into the dominant rigid motion and the rest:
    -> (displacements [T, n, 3] from ``rest`` [n, 3] in the head's frame, rotations [T, 3, 3], translations [T, 3]),
    so that vertices = apply_motion(R, t, rest + displacements) exactly."""
    rest = np.asarray(rest, np.float64)
    rot, trans = robust_rigid_motion(rest, vertices, iterations)
    return remove_motion(rot, trans, vertices) - rest[None], rot, trans
