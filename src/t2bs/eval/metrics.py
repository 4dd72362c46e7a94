"""Geometry and image metrics of the paper's evaluation (§4, appendix).

p2p: mean vertex distance / bounding-box diagonal; NC: mean (1 - cos) between vertex normals;
PSNR and SSIM of images in 0..1. Moving vertices: (frame, vertex) pairs whose true
displacement from the rest pose exceeds a fraction (0.5 %) of the diagonal. Seen vertices (our
addition): those some training view sees in some frame; the others (a mouth's back teeth) change
no pixel of any input image, so where a method puts them is its prior, not what it recovered.
"""

from __future__ import annotations

import numpy as np

from t2bs.geometry.mesh import vertex_normals


def bbox_diagonal(vertices: np.ndarray) -> float:
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    return float(np.linalg.norm(v.max(0) - v.min(0)))


def p2p(pred: np.ndarray, gt: np.ndarray, diagonal: float | None = None, mask: np.ndarray | None = None) -> float:
    """pred/gt [T, N, 3] (or [N, 3]); mean Euclidean error / diagonal (of gt's first frame by
    default) over all entries, or over ``mask`` [T, N] bool."""
    pred, gt = np.asarray(pred, np.float64), np.asarray(gt, np.float64)
    if pred.shape != gt.shape:
        raise ValueError(f"p2p: shapes differ {pred.shape} vs {gt.shape}")
    d = diagonal if diagonal is not None else bbox_diagonal(gt[0] if gt.ndim == 3 else gt)
    err = np.linalg.norm(pred - gt, axis=-1)
    if mask is not None:
        if not mask.any():
            return float("nan")
        err = err[mask]
    return float(err.mean() / d)


def moving_mask(gt: np.ndarray, rest: np.ndarray, fraction: float = 0.005, diagonal: float | None = None) -> np.ndarray:
    """[T, N] bool: true displacement from ``rest`` [N, 3] above ``fraction`` x diagonal."""
    d = diagonal if diagonal is not None else bbox_diagonal(rest)
    return np.linalg.norm(np.asarray(gt, np.float64) - np.asarray(rest, np.float64)[None], axis=-1) > fraction * d


def normal_consistency(pred: np.ndarray, gt: np.ndarray, faces: np.ndarray) -> float:
    """pred/gt [T, N, 3] (or [N, 3]) with shared ``faces``: mean (1 - cos) of vertex normals."""
    pred, gt = np.asarray(pred), np.asarray(gt)
    if pred.ndim == 2:
        pred, gt = pred[None], gt[None]
    used = np.zeros(pred.shape[1], bool)
    used[np.asarray(faces).ravel()] = True  # vertices outside any face have no normal
    vals = []
    for a, b in zip(pred, gt):
        na, nb = vertex_normals(a, faces), vertex_normals(b, faces)
        vals.append(1.0 - (na * nb).sum(-1)[used])
    return float(np.mean(np.concatenate(vals)))


def psnr(pred: np.ndarray, gt: np.ndarray) -> float:
    """Images in 0..1 (any shape, same for both) -> PSNR in dB (inf when identical)."""
    mse = float(np.mean((np.asarray(pred, np.float64) - np.asarray(gt, np.float64)) ** 2))
    return float("inf") if mse == 0 else float(10.0 * np.log10(1.0 / mse))


def ssim(pred: np.ndarray, gt: np.ndarray) -> float:
    """Images [..., H, W, 3] in 0..1 -> mean SSIM (Gaussian window 11, sigma 1.5; 7 for small images)."""
    import torch
    from pytorch_msssim import ssim as _ssim

    a = torch.as_tensor(np.asarray(pred, np.float32)).reshape(-1, *np.asarray(pred).shape[-3:]).permute(0, 3, 1, 2)
    b = torch.as_tensor(np.asarray(gt, np.float32)).reshape(-1, *np.asarray(gt).shape[-3:]).permute(0, 3, 1, 2)
    win = 11 if min(a.shape[-2:]) >= 11 * 4 else (7 if min(a.shape[-2:]) >= 28 else 3)
    return float(_ssim(a, b, data_range=1.0, size_average=True, win_size=win))


def geometry_metrics(pred: np.ndarray, gt: np.ndarray, rest: np.ndarray, faces: np.ndarray,
                     fraction: float = 0.005, seen: np.ndarray | None = None) -> dict:
    """p2p_all, p2p_moving, nc for pred/gt [T, N, 3] against the rest pose [N, 3]; with ``seen``
    [N] bool also p2p_seen (moving pairs of seen vertices) and seen_fraction (their share of the
    moving pairs)."""
    diag = bbox_diagonal(rest)
    mask = moving_mask(gt, rest, fraction, diag)
    out = {"p2p_all": p2p(pred, gt, diag), "p2p_moving": p2p(pred, gt, diag, mask),
           "nc": normal_consistency(pred, gt, faces), "moving_fraction": float(mask.mean())}
    if seen is not None:
        seen_moving = mask & np.asarray(seen, bool)[None]
        out["p2p_seen"] = p2p(pred, gt, diag, seen_moving)
        out["seen_fraction"] = float(seen_moving.sum() / max(mask.sum(), 1))
    return out
