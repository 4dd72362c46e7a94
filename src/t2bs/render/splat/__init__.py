"""Differentiable 3D Gaussian splatting rasterizer with one API and several backends.

``rasterize_gaussians`` renders RGB, alpha and expected depth for a batch of cameras and is
differentiable w.r.t. means, quats, scales, opacities and colors (and, through autograd, the
camera matrices). Backends:

- "reference": plain PyTorch autograd (tile loop in Python); defines the rules (see reference.py).
- "cpu": fused C++ kernels (JIT-built on first use into ~/.cache) for the projection and the
  compositing, with hand-written backwards. Same rules as the reference, so they agree to float
  rounding. Falls back to the reference with a warning when the kernel cannot be built.
- "gsplat": ``gsplat.rasterization`` on CUDA tensors (same conventions; tiny differences in the
  footprint cut-off rules, agreement ~1e-3).
- "dense": every Gaussian against every pixel, pure PyTorch; a benchmark baseline only.
- "auto": gsplat for CUDA tensors when it is importable, else "cpu".

Speed (2-core CPU, see benchmarks/raster.py): the kernel runs on torch.get_num_threads() threads, torch's own
OpenMP team (parallel.h). How those threads wait between operators is chosen when t2bs is imported, before torch
loads (t2bs/openmp.py: a short spin when the process has the cores to itself, passive when they are shared).
"""

from __future__ import annotations

import torch

from t2bs.errors import UserError

from .reference import LOWPASS, finish, project_gaussians, rasterize_reference_projected

BACKENDS = ("auto", "reference", "cpu", "gsplat", "dense")

__all__ = ["rasterize_gaussians", "BACKENDS"]


def _per_camera(name: str, x: torch.Tensor, C: int, tail: tuple[int, ...]) -> torch.Tensor:
    """Accept [N, *tail] (shared by all cameras) or [C, N, *tail]; return [C, N, *tail] (a view)."""
    if x.dim() == 1 + len(tail) and tuple(x.shape[1:]) == tail:
        return x.unsqueeze(0).expand(C, *x.shape)
    if x.dim() == 2 + len(tail) and x.shape[0] == C and tuple(x.shape[2:]) == tail:
        return x
    want = "x".join(str(t) for t in tail)
    raise UserError(
        f"rasterize_gaussians: {name} has shape {tuple(x.shape)}, expected [N{',' + want if tail else ''}] "
        f"or [C={C}, N{',' + want if tail else ''}]"
    )


def rasterize_gaussians(
    means,
    quats,
    scales,
    opacities,
    colors,
    viewmats,
    Ks,
    width,
    height,
    background=None,
    backend="auto",
    near=0.01,
    lowpass=LOWPASS,
):
    """Render Gaussians into C cameras.

    Args (N Gaussians, C cameras; each Gaussian tensor is either shared [N, ...] or per camera
    [C, N, ...], e.g. one deformed set per (view, time)):
        means:     [N, 3] | [C, N, 3] world positions.
        quats:     [N, 4] | [C, N, 4] rotations, wxyz, any norm (normalised inside).
        scales:    [N, 3] | [C, N, 3] standard deviations along the rotated axes (linear, not log).
        opacities: [N] | [C, N] in [0, 1].
        colors:    [N, 3] | [C, N, 3] RGB.
        viewmats:  [C, 4, 4] OpenCV world->camera (x right, y down, z forward).
        Ks:        [C, 3, 3] pinhole intrinsics in pixels (pixel (i, j) centre = (j + .5, i + .5)).
        width, height: image size in pixels.
        background: None (black, i.e. premultiplied), [3] or [C, 3] RGB composited behind.
        backend:   "auto" | "reference" | "cpu" | "gsplat" | "dense".
        near:      Gaussians with camera depth <= near are culled.
        lowpass:   px^2 added to every 2D covariance's diagonal (3DGS's and gsplat's eps2d, 0.3 by default): the
                   least footprint a Gaussian has on screen, and a blur of ~sqrt(lowpass) px on every edge.
    Returns dict:
        rgb   [C, H, W, 3]: sum_i w_i c_i + (1 - alpha) * background,
        alpha [C, H, W, 1]: 1 - final transmittance,
        depth [C, H, W, 1]: alpha-weighted expected camera depth sum_i w_i z_i / alpha (0 if empty).
    All outputs share the dtype/device of ``means``.
    """
    if backend not in BACKENDS:
        raise UserError(f"rasterize_gaussians: unknown backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    width, height = int(width), int(height)
    if width <= 0 or height <= 0:
        raise UserError(f"rasterize_gaussians: image size must be positive, got {width}x{height}")
    if not lowpass >= 0:  # NaN too
        raise UserError(f"rasterize_gaussians: lowpass must be >= 0 px^2, got {lowpass}")
    if viewmats.dim() != 3 or tuple(viewmats.shape[1:]) != (4, 4):
        raise UserError(f"rasterize_gaussians: viewmats has shape {tuple(viewmats.shape)}, expected [C, 4, 4]")
    C = viewmats.shape[0]
    if tuple(Ks.shape) != (C, 3, 3):
        raise UserError(f"rasterize_gaussians: Ks has shape {tuple(Ks.shape)}, expected [{C}, 3, 3]")
    means = _per_camera("means", means, C, (3,))
    quats = _per_camera("quats", quats, C, (4,))
    scales = _per_camera("scales", scales, C, (3,))
    opacities = _per_camera("opacities", opacities, C, ())
    colors = _per_camera("colors", colors, C, (3,))
    N = means.shape[1]
    for name, x in (("quats", quats), ("scales", scales), ("opacities", opacities), ("colors", colors)):
        if x.shape[1] != N:
            raise UserError(f"rasterize_gaussians: {name} has {x.shape[1]} Gaussians but means has {N}")
    dt, dev = means.dtype, means.device
    viewmats, Ks = viewmats.to(dev, dt), Ks.to(dev, dt)
    if background is not None:
        background = torch.as_tensor(background, dtype=dt, device=dev)
        if background.shape == (3,):
            background = background.expand(C, 3)
        elif tuple(background.shape) != (C, 3):
            raise UserError(
                f"rasterize_gaussians: background has shape {tuple(background.shape)}, expected [3] or [{C}, 3]"
            )

    if backend == "auto":
        backend = "gsplat" if (dev.type == "cuda" and _gsplat_available()) else "cpu"
    if backend == "gsplat":
        from .gsplat_backend import rasterize_gsplat

        return rasterize_gsplat(
            means, quats, scales, opacities, colors, viewmats, Ks, width, height, background, near, lowpass
        )

    project, composite = project_gaussians, rasterize_reference_projected
    if backend == "cpu":
        from .cpu import project_cpu, rasterize_cpu_projected

        project, composite = project_cpu, rasterize_cpu_projected
    elif backend == "dense":
        from .dense import rasterize_dense_projected

        composite = rasterize_dense_projected
    proj = project(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near, lowpass)
    acc_rgb, alpha, acc_depth = composite(proj, width, height)
    return finish(acc_rgb, alpha, acc_depth, background)


def _gsplat_available() -> bool:
    try:
        import gsplat  # noqa: F401
    except Exception:  # ImportError, or a broken CUDA build raising at import
        return False
    return True
