"""Geometry and image metrics of the paper's evaluation (§4, appendix).

p2p: mean vertex distance / bounding-box diagonal; NC: mean (1 - cos) between vertex normals;
PSNR and SSIM of images in 0..1. Moving vertices: (frame, vertex) pairs whose true
displacement from the rest pose exceeds a fraction (0.5 %) of the diagonal. Seen vertices (our
addition): those some training view sees in some frame; the others (a mouth's back teeth) change
no pixel of any input image, so where a method puts them is its prior, not what it recovered.

Expression (``expression_metrics``): a character's frames move the whole head and deform the face. p2p over the
moving vertices is dominated by the head's motion, so a perfect head tracker with a neutral face scores well. Here
each frame's dominant rigid motion (geometry.rigid.robust_rigid_motion) is taken out of the truth and, separately,
out of the reconstruction; what is left is the expression as seen from the head, compared over the vertices whose
true non-rigid motion exceeds 0.5 % of the diagonal. The ``rigid`` baseline (the neutral moved by the true head
motion: perfect head tracking, no expression) scores expr_p2p = the mean true non-rigid motion there.
"""

from __future__ import annotations

import numpy as np

from t2bs.geometry.mesh import bbox_diagonal, vertex_normals, welded_components
from t2bs.geometry.rigid import nonrigid_displacements


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


def geometry_metrics(
    pred: np.ndarray,
    gt: np.ndarray,
    rest: np.ndarray,
    faces: np.ndarray,
    fraction: float = 0.005,
    seen: np.ndarray | None = None,
) -> dict:
    """p2p_all, p2p_moving, nc for pred/gt [T, N, 3] against the rest pose [N, 3]; with ``seen``
    [N] bool also p2p_seen (moving pairs of seen vertices) and seen_fraction (their share of the
    moving pairs)."""
    diag = bbox_diagonal(rest)
    mask = moving_mask(gt, rest, fraction, diag)
    out = {
        "p2p_all": p2p(pred, gt, diag),
        "p2p_moving": p2p(pred, gt, diag, mask),
        "nc": normal_consistency(pred, gt, faces),
        "moving_fraction": float(mask.mean()),
    }
    if seen is not None:
        seen_moving = mask & np.asarray(seen, bool)[None]
        out["p2p_seen"] = p2p(pred, gt, diag, seen_moving)
        out["seen_fraction"] = float(seen_moving.sum() / max(mask.sum(), 1))
    return out


def part_errors(
    pred: np.ndarray,
    gt: np.ndarray,
    rest: np.ndarray,
    faces: np.ndarray,
    seen: np.ndarray | None = None,
    oracle: np.ndarray | None = None,
    top: int = 6,
    fraction: float = 0.005,
) -> list[dict]:
    """Where p2p over the moving pairs comes from, part by part: a mesh's separate parts (teeth, eyeballs, a mouth
    bag) can hold most of it, and no single number says so.

    pred, gt [T, N, 3] (reconstruction, truth), rest [N, 3], faces [F, 3]: parts are the welded mesh's connected
    components (geometry.mesh.welded_components); moving pairs as in ``geometry_metrics``. Per part with moving
    pairs, the ``top`` of them by error share, largest first: ``part`` (its label), ``vertices``, ``share`` (its
    part of the summed error over every moving pair; the shares of all parts add up to 1), ``p2p`` (mean error /
    diagonal over its moving pairs), ``pairs`` (its share of the moving pairs); with ``seen`` [N] bool ``seen``
    (the share of its moving pairs that are seen), with ``oracle`` [T, N, 3] (e.g. the rigid oracle's vertices)
    ``oracle_p2p`` there. [] when nothing moves."""
    pred, gt, rest = np.asarray(pred, np.float64), np.asarray(gt, np.float64), np.asarray(rest, np.float64)
    if pred.shape != gt.shape or gt.ndim != 3 or gt.shape[1:] != rest.shape:
        raise ValueError(f"part_errors: shapes {pred.shape}, {gt.shape}, rest {rest.shape}")
    d = bbox_diagonal(rest)
    mask = moving_mask(gt, rest, fraction, d)
    if not mask.any():
        return []
    label = welded_components(rest, np.asarray(faces))
    at = np.broadcast_to(label, mask.shape)[mask]  # the part of each moving pair

    def per_part(values: np.ndarray | None = None) -> np.ndarray:  # sums over each part's moving pairs
        return np.bincount(at, weights=None if values is None else values[mask], minlength=label.max() + 1)

    pairs = per_part()
    err = per_part(np.linalg.norm(pred - gt, axis=-1))
    seen_pairs = per_part(np.broadcast_to(np.asarray(seen, float), mask.shape)) if seen is not None else None
    oracle_err = per_part(np.linalg.norm(np.asarray(oracle, np.float64) - gt, axis=-1)) if oracle is not None else None
    sizes = np.bincount(label)
    out = []
    for part in np.flatnonzero(pairs):
        row = {
            "part": int(part),
            "vertices": int(sizes[part]),
            "share": float(err[part] / max(err.sum(), 1e-300)),
            "p2p": float(err[part] / pairs[part] / d),
            "pairs": float(pairs[part] / mask.sum()),
        }
        if seen_pairs is not None:
            row["seen"] = float(seen_pairs[part] / pairs[part])
        if oracle_err is not None:
            row["oracle_p2p"] = float(oracle_err[part] / pairs[part] / d)
        out.append(row)
    return sorted(out, key=lambda r: -r["share"])[:top]


def expression_metrics(
    pred: np.ndarray,
    gt: np.ndarray,
    rest: np.ndarray,
    fraction: float = 0.005,
    diagonal: float | None = None,
    select: np.ndarray | None = None,
) -> dict:
    """The expression recovered, with each frame's head motion taken out of both sides.

    pred, gt [T, N, 3]: reconstruction and truth; rest [N, 3] the neutral. Per frame, the dominant rigid motion of
    each (robust Kabsch fit from ``rest``) is removed, leaving non-rigid displacements e_pred, e_gt [T, N, 3] in the
    head's frame. Over the (frame, vertex) pairs where |e_gt| > ``fraction`` x diagonal (the eyelids of a blink, the
    lips of a smile):

    - ``expr_p2p``: mean |e_pred - e_gt| / diagonal;
    - ``expr_rigid``: the same for the rigid oracle (e_pred = 0): mean |e_gt| / diagonal;
    - ``expr_ratio``: expr_p2p / expr_rigid (1 = no better than a perfect head tracker with a neutral face, 0 = exact);
    - ``recovered``: |e_pred| / |e_gt| (Frobenius norms over those pairs): how much of the motion's size came back;
    - ``cosine``: <e_pred, e_gt> / (|e_pred| |e_gt|) over those pairs: whether it went the right way (0 when
      nothing moved, i.e. |e_pred| < 1e-4 |e_gt|);
    - ``expr_fraction``: the share of (frame, vertex) pairs in the mask;
    - ``spurious``: what the mask cannot see, motion where the truth is still: mean |e_pred - e_gt| over the frames
      where the expression's vertices (those in the mask in some frame) stay under the threshold, divided by
      ``expr_rigid`` (0 = still where the truth is still; 1 = as much false motion there as the true motion's mean
      size; a lid closed at the wrong frames shows here and not in ``expr_ratio``). nan when those vertices move in
      every frame.

    ``select`` [N] bool: only these vertices count (a region: the eyes, the mouth); each frame's rigid fit still
    uses every vertex, so the regions' numbers add up to the whole's.

    With no pair above the threshold (a capture without expression) the ratios are nan."""
    pred, gt, rest = np.asarray(pred, np.float64), np.asarray(gt, np.float64), np.asarray(rest, np.float64)
    if pred.shape != gt.shape or gt.ndim != 3 or gt.shape[1:] != rest.shape:
        raise ValueError(f"expression_metrics: shapes {pred.shape}, {gt.shape}, rest {rest.shape}")
    d = diagonal if diagonal is not None else bbox_diagonal(rest)
    e_gt = nonrigid_displacements(rest, gt)[0]
    e_pred = nonrigid_displacements(rest, pred)[0]
    mask = np.linalg.norm(e_gt, axis=-1) > fraction * d  # [T, N]
    if select is not None:
        mask &= np.asarray(select, bool)[None]
    if not mask.any():
        nan = float("nan")
        return {
            "expr_p2p": nan,
            "expr_rigid": nan,
            "expr_ratio": nan,
            "recovered": nan,
            "cosine": nan,
            "expr_fraction": 0.0,
            "spurious": nan,
        }
    a, b = e_pred[mask], e_gt[mask]  # [M, 3]
    err = float(np.linalg.norm(a - b, axis=-1).mean() / d)
    rigid = float(np.linalg.norm(b, axis=-1).mean() / d)
    na, nb = float(np.linalg.norm(a)), float(np.linalg.norm(b))
    still = mask.any(0)[None] & ~mask  # [T, N]: the expression's vertices where the truth leaves them be
    spurious = float(np.linalg.norm((e_pred - e_gt)[still], axis=-1).mean() / d / rigid) if still.any() else np.nan
    return {
        "expr_p2p": err,
        "expr_rigid": rigid,
        "expr_ratio": err / rigid,
        "recovered": na / nb,
        # below 1e-4 of the true motion, what is left is float32 rounding of a rigid motion: no direction
        "cosine": float((a * b).sum() / (na * nb)) if na > 1e-4 * nb else 0.0,
        "expr_fraction": float(mask.mean()),
        "spurious": spurious,
    }
