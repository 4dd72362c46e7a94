"""Pure-PyTorch (autograd) Gaussian splatting: the projection (used by the reference and dense
backends; projection.cpp is its C++ twin for the cpu backend, equal to float rounding) and the
reference compositor that defines the rules the fast kernel must reproduce bit for bit.

Rules (identical in every backend, so they agree to float rounding):
- Projection (EWA): camera-space covariance W R S S^T R^T W^T, pushed through the Jacobian of the
  perspective map at the mean (x/z, y/z clamped to 1.3x the half field of view like 3DGS/gsplat),
  plus a low-pass dilation on the diagonal (``lowpass`` px^2; 3DGS's and gsplat's 0.3 by default). Pixel
  (row i, col j) has its centre at (j + 0.5, i + 0.5) in the K convention (OpenCV, principal point W/2 = image
  centre).
- A Gaussian is culled when its camera depth z <= near, its 2D covariance is not positive
  definite, or its opacity is below 1/255.
- Extent: Gaussian g touches pixel p iff d2 = (p - mu)^T Sigma2d^-1 (p - mu) <= d2max(g) with
  d2max = min(9, 2 ln(255 o)): the 3-sigma ellipse intersected with the region where
  alpha = o exp(-d2 / 2) >= 1/255. Writing the 1/255 rule as a threshold on d2 (computed with the
  same float ops in torch and C++) makes the touch decision bit-identical across backends.
- alpha = min(0.99, o exp(-d2/2)); front-to-back by camera depth of the mean (stable on ties);
  compositing stops before the Gaussian that would bring the transmittance below 1e-4.
- Outputs: rgb = sum w_i c_i + T_final * background, alpha = 1 - T_final and depth = (sum w_i z_i)
  / max(alpha, 1e-10) (expected depth of the visible surface, gsplat's "ED"; 0 where empty), with
  w_i = alpha_i T_i.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

TILE = 16  # tile edge in pixels (binning granularity; results do not depend on it)
LOWPASS = 0.3  # default px^2 added to the 2D covariance diagonal (3DGS/gsplat eps2d)
EXTENT_SIGMA2 = 9.0  # squared Mahalanobis cut-off: the 3-sigma ellipse
ALPHA_MIN = 1.0 / 255.0  # contributions below this alpha are skipped
ALPHA_MAX = 0.99  # alpha clamp (keeps 1 - alpha invertible for the backward pass)
T_STOP = 1e-4  # stop compositing before transmittance would fall below this
DEPTH_EPS = 1e-10  # alpha floor when normalising the expected depth


@dataclass
class Projected:
    """Per-(camera, Gaussian) 2D quantities; tensors [C, N, ...] differentiable where noted."""

    means2d: torch.Tensor  # [C, N, 2] pixel coordinates of the mean (differentiable)
    conics: torch.Tensor  # [C, N, 3] (a, b, c) of the inverse 2D covariance [[a, b], [b, c]] (differentiable)
    depths: torch.Tensor  # [C, N] camera z of the mean (differentiable)
    opacities: torch.Tensor  # [C, N] (differentiable)
    colors: torch.Tensor  # [C, N, 3] (differentiable)
    d2max: torch.Tensor  # [C, N] squared Mahalanobis extent (no grad)
    radii: torch.Tensor  # [C, N, 2] conservative half extents in x and y, pixels (no grad)
    valid: torch.Tensor  # [C, N] bool: survives culling and overlaps the image


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """[..., 4] wxyz (any norm) -> [..., 3, 3] rotation matrices."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, dim=-1).reshape(*q.shape[:-1], 3, 3)


def is_shared_set(x: torch.Tensor) -> bool:
    """True for a [C, N, k] tensor that is one set broadcast to every camera (C = 1 or a stride-0
    expand): the projection then computes its camera-independent parts once, not C times."""
    return x.dim() == 3 and (x.shape[0] == 1 or x.stride(0) == 0)


def project_gaussians(
    means, quats, scales, opacities, colors, viewmats, Ks, width, height, near=0.01, lowpass=LOWPASS
) -> Projected:
    """EWA projection of N Gaussians into C cameras.

    means/quats/scales may be shared ([N, ...], or a stride-0 expand of it) or per camera
    ([C, N, ...]); opacities/colors are [C, N(, 3)]. Written with element-wise ops on small
    tensors (no batched 3x3 matmuls) because this runs thousands of times per fit.
    """
    means, quats, scales = (x[0] if is_shared_set(x) else x for x in (means, quats, scales))
    R = viewmats[:, :3, :3]  # [C, 3, 3]
    t = viewmats[:, None, :3, 3]  # [C, 1, 3]
    p_cam = torch.matmul(means, R.transpose(-1, -2)) + t  # [C, N, 3]
    x, y, z = p_cam.unbind(-1)
    in_front = z > near
    # Safe depth for culled Gaussians so no inf/NaN leaks into the backward pass.
    zs = torch.where(in_front, z, torch.ones_like(z))

    M = quat_to_rotmat(quats) * scales[..., None, :]  # R S: [(C,) N, 3, 3]

    fx, fy = Ks[:, 0, 0][:, None], Ks[:, 1, 1][:, None]  # [C, 1]
    cx, cy = Ks[:, 0, 2][:, None], Ks[:, 1, 2][:, None]
    # Clamp the Jacobian's evaluation point to 1.3x the half FOV (3DGS/gsplat) so Gaussians far
    # outside the frustum do not get huge, numerically wild footprints.
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lim_xp, lim_xn = (width - cx) / fx + 0.3 * tan_x, cx / fx + 0.3 * tan_x
    lim_yp, lim_yn = (height - cy) / fy + 0.3 * tan_y, cy / fy + 0.3 * tan_y
    inv_z = 1.0 / zs
    u = torch.minimum(lim_xp, torch.maximum(-lim_xn, x * inv_z))  # clamped x / z
    v = torch.minimum(lim_yp, torch.maximum(-lim_yn, y * inv_z))
    # Rows of J W (Jacobian of the perspective map times the camera rotation), [C, N, 3]:
    # J = [[fx/z, 0, -fx u/z], [0, fy/z, -fy v/z]].
    a0, a2 = (fx * inv_z)[..., None], (-fx * u * inv_z)[..., None]
    b1, b2 = (fy * inv_z)[..., None], (-fy * v * inv_z)[..., None]
    T0 = a0 * R[:, None, 0, :] + a2 * R[:, None, 2, :]
    T1 = b1 * R[:, None, 1, :] + b2 * R[:, None, 2, :]
    # (J W R S) rows: [C, N, 3]; cov2d = (J W M)(J W M)^T.
    P0 = (T0[..., :, None] * M).sum(-2)
    P1 = (T1[..., :, None] * M).sum(-2)
    sa = (P0 * P0).sum(-1) + lowpass
    sb = (P0 * P1).sum(-1)
    sc = (P1 * P1).sum(-1) + lowpass
    det = sa * sc - sb * sb
    ok_det = det > 0
    inv_det = 1.0 / torch.where(ok_det, det, torch.ones_like(det))
    conics = torch.stack([sc * inv_det, -sb * inv_det, sa * inv_det], -1)  # [C, N, 3]
    means2d = torch.stack([fx * x * inv_z + cx, fy * y * inv_z + cy], -1)  # [C, N, 2]

    with torch.no_grad():
        o = opacities.detach()
        d2max = torch.clamp(2.0 * torch.log(torch.clamp(o * 255.0, min=1e-30)), max=EXTENT_SIGMA2)
        d2max = torch.where(o >= ALPHA_MIN, d2max, torch.zeros_like(d2max))
        # Axis half extents of the ellipse d2 <= d2max (+1 px margin: binning must be
        # conservative, the per-pixel d2 test is what decides).
        dm = d2max.clamp_min(0)
        rx = torch.sqrt(dm * sa.detach().clamp_min(0)) + 1.0
        ry = torch.sqrt(dm * sc.detach().clamp_min(0)) + 1.0
        m2 = means2d.detach()
        finite = (
            torch.isfinite(m2).all(-1)
            & torch.isfinite(rx)
            & torch.isfinite(ry)
            & torch.isfinite(conics.detach()).all(-1)
        )
        overlaps = (
            (m2[..., 0] + rx > 0) & (m2[..., 0] - rx < width) & (m2[..., 1] + ry > 0) & (m2[..., 1] - ry < height)
        )
        valid = in_front & ok_det & (o >= ALPHA_MIN) & finite & overlaps
        radii = torch.stack([rx, ry], -1)
        radii = torch.where(valid[..., None], radii, torch.zeros_like(radii))
    return Projected(means2d, conics, z, opacities, colors, d2max, radii, valid)


def pixel_d2(px, py, means2d, conics):
    """Squared Mahalanobis distance; the op order is mirrored exactly in kernel.cpp (no FMA)."""
    dx = px - means2d[..., 0]
    dy = py - means2d[..., 1]
    a, b, c = conics.unbind(-1)
    return (a * dx * dx + c * dy * dy) + 2.0 * b * dx * dy


def composite(px, py, means2d, conics, depths, opacities, colors, d2max):
    """Front-to-back compositing of K depth-sorted Gaussians at P pixels (autograd).

    px, py [P, 1]; Gaussian tensors [K, ...] sorted front to back.
    Returns (acc_rgb [P, 3], alpha [P], acc_depth [P]) without the background.
    """
    d2 = pixel_d2(px, py, means2d[None], conics[None])  # [P, K]
    touch = d2 <= d2max[None]
    a = torch.clamp(opacities[None] * torch.exp(-0.5 * d2), max=ALPHA_MAX)
    a = torch.where(touch, a, torch.zeros_like(a))
    with torch.no_grad():
        # Gaussian i is composited iff the transmittance after it stays >= T_STOP; the product
        # is monotone, so this is exactly "stop before the first one that would cross".
        keep = torch.cumprod(1.0 - a.detach(), dim=1) >= T_STOP
    a = torch.where(keep, a, torch.zeros_like(a))
    one_minus = 1.0 - a
    T_incl = torch.cumprod(one_minus, dim=1)  # [P, K]
    T_excl = torch.cat([torch.ones_like(T_incl[:, :1]), T_incl[:, :-1]], dim=1)
    w = a * T_excl
    acc_rgb = w @ colors  # [P, 3]
    acc_depth = w @ depths  # [P]
    alpha = 1.0 - (T_incl[:, -1] if T_incl.shape[1] else torch.ones_like(px[:, 0]))
    return acc_rgb, alpha, acc_depth


def finish(acc_rgb, alpha, acc_depth, background):
    """Background and depth normalisation shared by every backend.

    acc_rgb [C, H, W, 3], alpha [C, H, W], acc_depth [C, H, W], background [C, 3] | None.
    """
    rgb = acc_rgb
    if background is not None:
        rgb = rgb + (1.0 - alpha)[..., None] * background[:, None, None, :]
    depth = acc_depth / alpha.clamp_min(DEPTH_EPS)
    return {"rgb": rgb, "alpha": alpha[..., None], "depth": depth[..., None]}


def rasterize_reference_projected(proj: Projected, width: int, height: int):
    """Tile loop in Python: per tile, every overlapping Gaussian (depth-sorted) vs its pixels.

    Returns (acc_rgb [C, H, W, 3], alpha [C, H, W], acc_depth [C, H, W]).
    """
    C, N = proj.depths.shape
    dev, dt = proj.means2d.device, proj.means2d.dtype
    order = torch.sort(proj.depths.detach(), dim=1, stable=True).indices  # [C, N]
    out_rgb, out_a, out_d = [], [], []
    for ci in range(C):
        o = order[ci][proj.valid[ci][order[ci]]]  # valid Gaussians front to back
        m2, r = proj.means2d[ci].detach()[o], proj.radii[ci][o]
        lo_x, hi_x = m2[:, 0] - r[:, 0], m2[:, 0] + r[:, 0]
        lo_y, hi_y = m2[:, 1] - r[:, 1], m2[:, 1] + r[:, 1]
        rows = []
        for y0 in range(0, height, TILE):
            y1 = min(y0 + TILE, height)
            in_rows = (hi_y >= y0) & (lo_y <= y1)
            cols = []
            for x0 in range(0, width, TILE):
                x1 = min(x0 + TILE, width)
                ids = o[in_rows & (hi_x >= x0) & (lo_x <= x1)]
                ys, xs = torch.meshgrid(
                    torch.arange(y0, y1, device=dev, dtype=dt) + 0.5,
                    torch.arange(x0, x1, device=dev, dtype=dt) + 0.5,
                    indexing="ij",
                )
                acc_rgb, alpha, acc_depth = composite(
                    xs.reshape(-1, 1),
                    ys.reshape(-1, 1),
                    proj.means2d[ci][ids],
                    proj.conics[ci][ids],
                    proj.depths[ci][ids],
                    proj.opacities[ci][ids],
                    proj.colors[ci][ids],
                    proj.d2max[ci][ids],
                )
                h, w = y1 - y0, x1 - x0
                cols.append((acc_rgb.reshape(h, w, 3), alpha.reshape(h, w), acc_depth.reshape(h, w)))
            rows.append(tuple(torch.cat([c[k] for c in cols], dim=1) for k in range(3)))
        img = tuple(torch.cat([r[k] for r in rows], dim=0) for k in range(3))
        out_rgb.append(img[0]), out_a.append(img[1]), out_d.append(img[2])
    return torch.stack(out_rgb), torch.stack(out_a), torch.stack(out_d)
