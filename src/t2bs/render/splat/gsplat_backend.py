"""CUDA backend: ``gsplat.rasterization`` with this package's conventions.

gsplat already uses ours: quats wxyz (normalised inside), linear scales, OpenCV world->camera
viewmats, pinhole Ks, eps2d = our low-pass (px^2), alpha clamp 0.99, 1/255 skip and early stop at
T < 1e-4. Its "RGB+ED" mode returns the expected depth sum(w z) / alpha as a 4th channel, which is
our depth. Differences to the CPU backends are confined to the footprint cut-off (gsplat bins a
3-sigma circle of the largest eigenvalue per tile; we cut the 3-sigma ellipse per pixel), which
moves low-alpha fringe pixels slightly (images agree to ~1e-3 mean abs).

The background is composited here (rgb + (1 - alpha) * bg) rather than via gsplat's
``backgrounds`` so the depth channel is never blended with it.
"""

from __future__ import annotations

import functools

import torch

from t2bs.errors import UserError

from .reference import LOWPASS


def _shared(x: torch.Tensor) -> bool:
    """True when a [C, N, ...] tensor is a broadcast view of one [N, ...] set (stride 0 on C)."""
    return x.shape[0] == 1 or x.stride(0) == 0


@functools.cache
def _batch_dims_supported() -> bool:
    """gsplat >= 1.5 accepts leading batch dimensions (means [..., N, 3], viewmats [..., C, 4, 4])."""
    import gsplat

    major, minor = (int(x) for x in gsplat.__version__.split(".")[:2])
    return (major, minor) >= (1, 5)


def rasterize_gsplat(
    means, quats, scales, opacities, colors, viewmats, Ks, width, height, background, near, lowpass=LOWPASS
):
    """Inputs already broadcast to [C, N, ...] (see rasterize_gaussians); returns the same dict."""
    try:
        from gsplat import rasterization
    except Exception as exc:
        raise UserError(f"backend 'gsplat' needs the gsplat package with CUDA ({type(exc).__name__}: {exc})") from exc
    if means.device.type != "cuda":
        raise UserError("backend 'gsplat' needs CUDA tensors; move the inputs to a GPU or use backend='cpu'")
    C = viewmats.shape[0]
    kw = dict(
        width=width,
        height=height,
        near_plane=near,
        eps2d=lowpass,
        render_mode="RGB+ED",
        rasterize_mode="classic",
        packed=False,
    )
    dt = means.dtype
    f = lambda x: x.float()  # noqa: E731  (gsplat kernels are float32)
    if all(_shared(x) for x in (means, quats, scales, opacities)):
        # One Gaussian set for every camera: one batched call; colours may still be per camera.
        cols = colors[0] if _shared(colors) else colors
        render, alphas, _ = rasterization(
            f(means[0]), f(quats[0]), f(scales[0]), f(opacities[0]), f(cols), f(viewmats), f(Ks), **kw
        )
    elif _batch_dims_supported():
        # Per-camera sets (VCDGS deforms per (view, time)): each camera is a batch entry with its
        # own Gaussians, one call for all of them.
        render, alphas, _ = rasterization(
            f(means), f(quats), f(scales), f(opacities), f(colors), f(viewmats[:, None]), f(Ks[:, None]), **kw
        )
        render, alphas = render[:, 0], alphas[:, 0]
    else:
        # gsplat < 1.5 takes one Gaussian set per call.
        outs = [
            rasterization(
                f(means[c]),
                f(quats[c]),
                f(scales[c]),
                f(opacities[c]),
                f(colors[c]),
                f(viewmats[c : c + 1]),
                f(Ks[c : c + 1]),
                **kw,
            )
            for c in range(C)
        ]
        render = torch.cat([o[0] for o in outs], 0)
        alphas = torch.cat([o[1] for o in outs], 0)
    render, alphas = render.to(dt), alphas.to(dt)  # [C, H, W, 4], [C, H, W, 1]
    rgb = render[..., :3]
    if background is not None:
        rgb = rgb + (1.0 - alphas) * background[:, None, None, :]
    return {"rgb": rgb, "alpha": alphas, "depth": render[..., 3:4]}
