"""Fast CPU backend: the C++ kernel (kernel.cpp) JIT-built with torch.utils.cpp_extension.

Both stages run in C++ with hand-written backwards on torch.get_num_threads() threads: the EWA
projection (projection.cpp: the rules of reference.project_gaussians in one pass per Gaussian,
~10x faster than its ~60 element-wise torch ops) and the per-pixel compositing (kernel.cpp, parallel
over (camera, tile) work items), where most of the time goes.
The build lands in $XDG_CACHE_HOME/t2bs/torch_extensions (default ~/.cache), one folder per torch
installation (``build_directory``), so a fresh clone or environment builds it on first use (1-3 min on
2 cores, once, announced by one line on stderr); if that fails the reference is used with a warning.
"""

from __future__ import annotations

import hashlib
import os
import sys
import threading
import warnings
from pathlib import Path

import torch

from .reference import LOWPASS, TILE, Projected, is_shared_set, project_gaussians, rasterize_reference_projected

_HERE = Path(__file__).parent
_SOURCES = [_HERE / "kernel.cpp", _HERE / "projection.cpp", _HERE / "faces.cpp", _HERE / "skinning.cpp"]
_HEADERS = [_HERE / "parallel.h"]
_CFLAGS = ["-O3", "-ffp-contract=off", "-std=c++17", "-pthread"]
# The kernels share torch's OpenMP threads (parallel.h says why); a compiler without OpenMP builds them on std::threads.
_OPENMP = ["-fopenmp"]

_lock = threading.Lock()
_module = None
_error: str | None = None


BUILD_MESSAGE = "t2bs: compiling the C++ splat kernel (first use with this torch installation, ~1-3 min)..."


def torch_installation() -> str:
    """What a build of the kernel is only valid for: torch's folder and version, and the Python running it."""
    py = f"{sys.implementation.cache_tag}-{sys.version_info[0]}.{sys.version_info[1]}"
    return f"{Path(torch.__file__).resolve().parent}|{torch.__version__}|{py}"


def build_directory(openmp: bool = True) -> Path:
    """$XDG_CACHE_HOME/t2bs/torch_extensions/<one folder per (sources, flags, torch installation)>.

    torch rebuilds when a listed source changes, not when a header does: the folder names them all. It also names the
    flags and where the sources and torch live: ninja rebuilds when a source's path or torch's changes, so two checkouts
    or two environments (venvs, conda) on one machine would otherwise rebuild the one folder in turn.
    """
    base = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
    where = f"{_HERE.resolve()}|{torch_installation()}|{' '.join(_flags(openmp))}".encode()
    digest = hashlib.sha1(b"".join(p.read_bytes() for p in _SOURCES + _HEADERS) + where).hexdigest()[:10]
    return base / "t2bs" / "torch_extensions" / f"splat_cpu_torch{torch.__version__.replace('+', '_')}_{digest}"


def is_built(path: Path) -> bool:
    """Whether ``path`` holds a finished build (the linked module; an interrupted build leaves none)."""
    return any(path.glob("t2bs_splat_cpu*.so"))


def _flags(openmp: bool) -> list[str]:
    return _CFLAGS + (_OPENMP if openmp else [])


def _compile(path: Path, openmp: bool = True):
    """torch.utils.cpp_extension.load: builds into ``path`` with ninja when needed, then imports the module."""
    from torch.utils.cpp_extension import load

    return load(
        name="t2bs_splat_cpu",
        sources=[str(p) for p in _SOURCES],
        extra_cflags=_flags(openmp),
        extra_ldflags=["-pthread"] + (_OPENMP if openmp else []),
        build_directory=str(path),
        verbose=False,
    )


def load_kernel():
    """The compiled extension module, or None (with the reason in ``kernel_error()``)."""
    global _module, _error
    if _module is not None or _error is not None:
        return _module
    with _lock:
        if _module is None and _error is None:
            announced = False
            for openmp in (True, False):  # a compiler without OpenMP (clang on macOS) still builds it, on std::threads
                try:
                    path = build_directory(openmp)
                    path.mkdir(parents=True, exist_ok=True)
                    if not is_built(path) and not announced:  # one line: a silent minute in a progress bar has a reason
                        print(BUILD_MESSAGE, file=sys.stderr, flush=True)
                        announced = True
                    _module, _error = _compile(path, openmp), None
                    break
                except Exception as exc:  # compiler missing, headers missing, link error, ...
                    _error = f"{type(exc).__name__}: {str(exc).strip().splitlines()[-1] if str(exc).strip() else exc}"
    return _module


def kernel_error() -> str | None:
    load_kernel()
    return _error


def _grad_in(g, shape, dtype=torch.float32):
    """An output's incoming gradient as the kernels take it: contiguous ``dtype`` on the CPU, zeros if None."""
    return torch.zeros(shape, dtype=dtype) if g is None else g.detach().cpu().to(dtype).contiguous()


class _Project(torch.autograd.Function):
    """(means, quats, scales) [1 | C, N, k] -> (means2d, conics, depths), C++ both ways (projection.cpp)."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmats, Ks, width, height, near, lowpass):
        ext = load_kernel()
        args = [t.detach().contiguous() for t in (means, quats, scales, viewmats, Ks)]
        means2d, conics, depths, d2max, radii, valid = ext.project_forward(
            *args[:3], opacities.detach().contiguous(), *args[3:], width, height, near, lowpass
        )
        ctx.save_for_backward(*args)
        ctx.size = (width, height, near, lowpass)
        ctx.mark_non_differentiable(d2max, radii, valid)
        return means2d, conics, depths, d2max, radii, valid

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, *_):
        ext = load_kernel()
        means, quats, scales, viewmats, Ks = ctx.saved_tensors
        C, N = viewmats.shape[0], means.shape[1]

        grads = ext.project_backward(
            means,
            quats,
            scales,
            viewmats,
            Ks,
            *ctx.size,
            _grad_in(g_means2d, (C, N, 2)),
            _grad_in(g_conics, (C, N, 3)),
            _grad_in(g_depths, (C, N)),
        )
        # Per-camera gradients; a set shared by every camera ([1, N, k]) sums them (fixed order).
        g_means, g_quats, g_scales = (
            g if x.shape[0] == C else g.sum(0, keepdim=True) for g, x in zip(grads, (means, quats, scales))
        )
        return g_means, g_quats, g_scales, None, None, None, None, None, None, None


def project_cpu(
    means, quats, scales, opacities, colors, viewmats, Ks, width, height, near=0.01, lowpass=LOWPASS
) -> Projected:
    """``reference.project_gaussians`` in C++ (same arguments and result). Falls back to it when
    the kernel is missing, a tensor is not float32 on the CPU, or the cameras need a gradient
    (the C++ backward gives none to them)."""
    tensors = (means, quats, scales, opacities, colors, viewmats, Ks)
    if (
        load_kernel() is None
        or any(t.dtype != torch.float32 or t.device.type != "cpu" for t in tensors)
        or viewmats.requires_grad
        or Ks.requires_grad
    ):
        return project_gaussians(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near, lowpass)

    # A set shared by every camera goes in as [1, N, k] (not copied C times).
    means, quats, scales = (x[:1] if is_shared_set(x) else x for x in (means, quats, scales))
    means2d, conics, depths, d2max, radii, valid = _Project.apply(
        means, quats, scales, opacities, viewmats, Ks, int(width), int(height), float(near), float(lowpass)
    )
    return Projected(means2d, conics, depths, opacities, colors, d2max, radii, valid)


class _FaceGaussians(torch.autograd.Function):
    """x [B, N, 3] -> the face Gaussians' (means [B, F, 3], quats [B, F, 4], scales [B, F, 3]), C++ both ways
    (faces.cpp); the gradient reaches ``x`` only."""

    @staticmethod
    def forward(ctx, x, faces, log_scale, flatness):
        args = (x.detach().contiguous(), faces.contiguous(), log_scale.detach().contiguous())
        ctx.save_for_backward(*args)
        ctx.flatness = flatness
        return tuple(load_kernel().faces_forward(*args, flatness))

    @staticmethod
    def backward(ctx, g_mean, g_quat, g_scale):
        x, faces, log_scale = ctx.saved_tensors
        b, f = x.shape[0], faces.shape[0]
        grads = [_grad_in(g, (b, f, k), x.dtype) for g, k in ((g_mean, 3), (g_quat, 4), (g_scale, 3))]
        return load_kernel().faces_backward(x, faces, log_scale, ctx.flatness, *grads), None, None, None


def face_gaussians_cpu(x, faces, face_log_scale, flatness: float):
    """``recon.gaussians.face_gaussians_reference`` in C++ (same arguments and result, to float rounding), or None
    where it does not apply: no kernel, tensors not float32 / float64 on the CPU, a ``face_log_scale`` that wants a
    gradient (the C++ backward gives only ``x`` one), or inside a torch.compile trace (the compiler fuses the
    reference itself)."""
    if (
        torch.compiler.is_compiling()
        or x.device.type != "cpu"
        or x.dtype not in (torch.float32, torch.float64)
        or face_log_scale.dtype != x.dtype
        or face_log_scale.requires_grad
        or load_kernel() is None
    ):
        return None
    return _FaceGaussians.apply(x, faces.to(device="cpu", dtype=torch.int64), face_log_scale, float(flatness))


class _Skin(torch.autograd.Function):
    """(packed [B, K, 16], x [1 | B, N, 3]) -> skinned (positions [B, N, 3], rotations [B, N, 4]), C++ both ways
    (skinning.cpp); q_rest, neighbours and weights get no gradient."""

    @staticmethod
    def forward(ctx, packed, x, q_rest, neighbours, weights):
        args = [t.detach().contiguous() for t in (packed, x, q_rest, neighbours, weights)]
        ctx.save_for_backward(*args)
        return tuple(load_kernel().skin_forward(*args))

    @staticmethod
    def backward(ctx, g_x, g_q):
        packed, x, q_rest, neighbours, weights = ctx.saved_tensors
        b, n = packed.shape[0], x.shape[1]
        g_x, g_q = _grad_in(g_x, (b, n, 3), packed.dtype), _grad_in(g_q, (b, n, 4), packed.dtype)
        g_packed, g_rest = load_kernel().skin_backward(packed, x, q_rest, neighbours, weights, g_x, g_q)
        if not ctx.needs_input_grad[1]:
            g_rest = None
        elif x.shape[0] != b:  # one rest pose shared by the batch: its gradient sums the items' (fixed order)
            g_rest = g_rest.sum(0, keepdim=True)
        return g_packed, g_rest, None, None, None


def skin_cpu(packed, x, q_rest, neighbours, weights):
    """``recon.lbs.lbs_reference`` from the packed transforms in C++: packed [B, K, 16] (``recon.lbs.packed_transforms``),
    x [N, 3] or [B, N, 3] -> (positions [B, N, 3], rotations [B, N, 4] XYZW); None where it does not apply (no kernel,
    not float32 / float64 on the CPU, a gradient wanted by q_rest or the weights, a torch.compile trace)."""
    tensors = (packed, x, q_rest, weights)
    if (
        torch.compiler.is_compiling()
        or any(t.device.type != "cpu" or t.dtype != packed.dtype for t in tensors)
        or packed.dtype not in (torch.float32, torch.float64)
        or q_rest.requires_grad
        or weights.requires_grad
        or load_kernel() is None
    ):
        return None
    rest = x if x.dim() == 3 else x[None]
    return _Skin.apply(packed, rest, q_rest, neighbours.to(torch.int64), weights)


class _SplatComposite(torch.autograd.Function):
    """(means2d, conics, opacities, colors, depths) -> (acc_rgb, alpha, acc_depth), C++ both ways."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, d2max, radii, valid, width, height):
        ext = load_kernel()
        args = [
            t.detach().cpu().float().contiguous() for t in (means2d, conics, opacities, colors, depths, d2max, radii)
        ]
        valid = valid.cpu().contiguous()
        ctx.device = means2d.device
        acc_rgb, alpha, acc_depth, T_final, last, offsets, ids = ext.forward(*args, valid, width, height, TILE)
        ctx.save_for_backward(*args, valid, offsets, ids, T_final, last)
        ctx.size = (width, height)
        ctx.dtypes = [t.dtype for t in (means2d, conics, opacities, colors, depths)]
        dev = means2d.device
        return acc_rgb.to(dev), alpha.to(dev), acc_depth.to(dev)

    @staticmethod
    def backward(ctx, g_rgb, g_alpha, g_depth):
        ext = load_kernel()
        *args, valid, offsets, ids, T_final, last = ctx.saved_tensors
        width, height = ctx.size
        C = args[4].shape[0]

        g = ext.backward(
            *args,
            valid,
            width,
            height,
            TILE,
            offsets,
            ids,
            T_final,
            last,
            _grad_in(g_rgb, (C, height, width, 3)),
            _grad_in(g_alpha, (C, height, width)),
            _grad_in(g_depth, (C, height, width)),
        )  # [C, N, 10]
        dt, dev = ctx.dtypes, ctx.device
        return (
            g[..., 0:2].to(dev, dt[0]),
            g[..., 2:5].to(dev, dt[1]),
            g[..., 5].to(dev, dt[2]),
            g[..., 6:9].to(dev, dt[3]),
            g[..., 9].to(dev, dt[4]),
            None,
            None,
            None,
            None,
            None,
        )


def rasterize_cpu_projected(proj: Projected, width: int, height: int):
    """Returns (acc_rgb [C, H, W, 3], alpha [C, H, W], acc_depth [C, H, W]); reference if no kernel."""
    if load_kernel() is None:
        warnings.warn(
            f"t2bs splat: the C++ CPU kernel could not be built ({_error}); "
            "using the slow PyTorch reference rasterizer",
            RuntimeWarning,
            stacklevel=3,
        )
        return rasterize_reference_projected(proj, width, height)
    out = _SplatComposite.apply(
        proj.means2d,
        proj.conics,
        proj.opacities,
        proj.colors,
        proj.depths,
        proj.d2max,
        proj.radii,
        proj.valid,
        width,
        height,
    )
    dt = proj.means2d.dtype
    return tuple(o.to(dt) for o in out)
