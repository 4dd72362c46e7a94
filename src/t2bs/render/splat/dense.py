"""Dense all-pairs baseline: every (valid) Gaussian against every pixel, no tiles, pure PyTorch.

Same rules as the reference (it reuses ``composite``), so the images agree; memory grows as
C x H x W x N, which is why it is only a benchmark baseline.
"""

from __future__ import annotations

import torch

from .reference import Projected, composite


def rasterize_dense_projected(proj: Projected, width: int, height: int):
    """Returns (acc_rgb [C, H, W, 3], alpha [C, H, W], acc_depth [C, H, W])."""
    C = proj.depths.shape[0]
    dev, dt = proj.means2d.device, proj.means2d.dtype
    ys, xs = torch.meshgrid(
        torch.arange(height, device=dev, dtype=dt) + 0.5, torch.arange(width, device=dev, dtype=dt) + 0.5, indexing="ij"
    )
    px, py = xs.reshape(-1, 1), ys.reshape(-1, 1)  # [P, 1]
    order = torch.sort(proj.depths.detach(), dim=1, stable=True).indices  # [C, N]
    out = []
    for ci in range(C):
        ids = order[ci][proj.valid[ci][order[ci]]]
        acc_rgb, alpha, acc_depth = composite(
            px,
            py,
            proj.means2d[ci][ids],
            proj.conics[ci][ids],
            proj.depths[ci][ids],
            proj.opacities[ci][ids],
            proj.colors[ci][ids],
            proj.d2max[ci][ids],
        )
        out.append((acc_rgb.reshape(height, width, 3), alpha.reshape(height, width), acc_depth.reshape(height, width)))
    return tuple(torch.stack([o[k] for o in out]) for k in range(3))


def dense_bytes_estimate(cameras: int, height: int, width: int, gaussians: int, dtype_bytes: int = 4) -> int:
    """Rough peak memory of one dense forward+backward per camera (about 12 [P, N] tensors live)."""
    return 12 * height * width * gaussians * dtype_bytes
