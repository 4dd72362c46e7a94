"""Rasterizer benchmark: ms per forward+backward for the fast CPU path, the autograd reference and
the dense all-pairs baseline on the same scenes, plus their max abs image difference; with CUDA
and gsplat present, also gsplat on the GPU (``gsplat_ms``, synchronised) and its image difference
to the CPU path (mean and max abs: the footprint cut-offs differ, see gsplat_backend.py).

Scenes imitate what VCDGS renders: N Gaussians on a head-sized ellipsoid surface (flattened
along the normal like a fitted surface, sizes matched to the sample spacing so the surface is
covered), random colours and opacities in [0.5, 1], seen by C orbit cameras.
The last line printed is one JSON object (the output contract in issue 3).
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import time

import numpy as np
import torch

from . import _gsplat_available, rasterize_gaussians

CASES = {  # name -> (height = width, gaussians, cameras)
    "a": (128, 5000, 4),
    "b": (256, 20000, 4),
    "c": (512, 50000, 4),
}
MEMORY_BUDGET = 6 * 2**30  # bytes an autograd baseline may use on this shared machine


def make_scene(n: int, cameras: int, size: int, seed: int = 0):
    """(params [means, quats, scales, opacities, colors], viewmats [C,4,4], Ks [C,3,3])."""
    from t2bs.geometry.camera import orbit_cameras

    g = torch.Generator().manual_seed(seed)
    radii = torch.tensor([0.42, 0.5, 0.4])
    d = torch.randn(n, 3, generator=g)
    d = d / d.norm(dim=1, keepdim=True)
    means = d * radii * (1 + 0.02 * torch.randn(n, 1, generator=g))
    normal = d / radii
    normal = normal / normal.norm(dim=1, keepdim=True)
    # Rotation taking +z onto the normal, then a random twist about it.
    w = 1.0 + normal[:, 2]
    q = torch.cat([w[:, None], torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0]).expand(n, 3), normal)], 1)
    q = q / q.norm(dim=1, keepdim=True)
    area = 4 * np.pi * float(radii.prod() ** (2 / 3))
    spacing = (area / n) ** 0.5
    scales = spacing * torch.cat([0.6 + 0.8 * torch.rand(n, 2, generator=g), torch.full((n, 1), 0.1)], 1)
    opac = 0.5 + 0.5 * torch.rand(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    views = [c for i, c in enumerate(orbit_cameras(views=15, size=size)) if i in (0, 4, 7, 11, 14, 2, 9, 12)][:cameras]
    vm = torch.tensor(np.stack([c.world_to_camera for c in views]), dtype=torch.float32)
    K = torch.tensor(np.stack([c.K for c in views]), dtype=torch.float32)
    return [means, q, scales, opac, colors], vm, K


def fwd_bwd(params, vm, K, size, backend, weights):
    """One forward + backward; returns (seconds, outputs)."""
    ps = [p.clone().requires_grad_() for p in params]
    t0 = time.perf_counter()
    out = rasterize_gaussians(*ps, vm, K, size, size, background=torch.ones(3), backend=backend)
    loss = (out["rgb"] * weights[..., :3]).sum() + (out["alpha"] * weights[..., 3:4]).sum()
    loss = loss + (out["depth"] * weights[..., 4:5]).sum()
    loss.backward()
    if vm.is_cuda:
        torch.cuda.synchronize()
    dt = time.perf_counter() - t0
    return dt, {k: v.detach() for k, v in out.items()}


def _timed(params, vm, K, size, backend, weights, repeats, per_camera=False):
    """Median seconds over repeats; per_camera runs cameras one at a time (same total work,
    1/C of the memory) for the all-pairs baselines."""
    times, out = [], None
    for _ in range(repeats):
        if per_camera:
            total, outs = 0.0, []
            for c in range(vm.shape[0]):
                dt, o = fwd_bwd(params, vm[c : c + 1], K[c : c + 1], size, backend, weights[c : c + 1])
                total += dt
                outs.append(o)
            out = {k: torch.cat([o[k] for o in outs]) for k in outs[0]}
            times.append(total)
        else:
            dt, out = fwd_bwd(params, vm, K, size, backend, weights)
            times.append(dt)
    return statistics.median(times), out


def _pairs(params, vm, K, size) -> int:
    """Exact number of (tile, Gaussian) overlaps, from the kernel's own binning."""
    from .cpu import load_kernel
    from .reference import TILE, project_gaussians

    C = vm.shape[0]
    with torch.no_grad():
        ps = [p.unsqueeze(0).expand(C, *p.shape) for p in params]
        pr = project_gaussians(*ps, vm, K, size, size)
        res = load_kernel().forward(
            pr.means2d.contiguous(),
            pr.conics.contiguous(),
            pr.opacities.contiguous(),
            pr.colors.contiguous(),
            pr.depths.contiguous(),
            pr.d2max.contiguous(),
            pr.radii.contiguous(),
            pr.valid.contiguous(),
            size,
            size,
            TILE,
        )
    return int(res[6].numel())


def _diff(a, b) -> float:
    return max(float((a[k] - b[k]).abs().max()) for k in ("rgb", "alpha"))


def run_case(name: str, repeats: int = 5, with_reference: bool = True, with_dense: bool = True) -> dict:
    size, n, cams = CASES[name]
    params, vm, K = make_scene(n, cams, size)
    weights = torch.rand(cams, size, size, 5, generator=torch.Generator().manual_seed(1))
    fwd_bwd(params, vm, K, size, "cpu", weights)  # warm-up (kernel build/load, allocator)
    fast_s, fast = _timed(params, vm, K, size, "cpu", weights, repeats)
    result = {
        "name": name,
        "height": size,
        "width": size,
        "gaussians": n,
        "cameras": cams,
        "fast_ms": round(fast_s * 1e3, 2),
        "reference_ms": None,
        "dense_ms": None,
        "max_abs_diff": None,
    }
    diffs, depth_diffs = [], []
    fast_pc = None  # fast path run one camera at a time, to diff against per-camera baselines

    def fast_like(per_camera: bool):
        # Compare like with like: a 1-camera projection rounds differently from a 4-camera batched
        # one, and the hard footprint cut-offs (d2 <= d2max) turn 1-ulp input differences into
        # whole-contribution jumps at a few boundary pixels.
        nonlocal fast_pc
        if not per_camera:
            return fast
        if fast_pc is None:
            fast_pc = _timed(params, vm, K, size, "cpu", weights, 1, per_camera=True)[1]
        return fast_pc

    # Memory of the autograd baselines: ~16 float32 [pixels, Gaussians] tensors live per pair.
    ref_bytes = _pairs(params, vm, K, size) * 16 * 16 * 4 * 16
    if with_reference and ref_bytes <= cams * MEMORY_BUDGET:
        # All cameras in one graph when it fits, else one camera at a time (same work).
        split = ref_bytes > MEMORY_BUDGET
        ref_s, ref = _timed(params, vm, K, size, "reference", weights, max(1, repeats // 3), per_camera=split)
        result["reference_ms"] = round(ref_s * 1e3, 1)
        diffs.append(_diff(fast_like(split), ref))
        depth_diffs.append(float(((fast_like(split)["depth"] - ref["depth"]) * ref["alpha"]).abs().max()))
    dense_bytes = size * size * n * 4 * 16  # per camera (run one camera at a time)
    if with_dense and dense_bytes <= MEMORY_BUDGET:
        dense_s, dense = _timed(params, vm, K, size, "dense", weights, max(1, repeats // 5), per_camera=True)
        result["dense_ms"] = round(dense_s * 1e3, 1)
        diffs.append(_diff(fast_like(True), dense))
    if torch.cuda.is_available() and _gsplat_available():
        cuda = [p.cuda() for p in params]
        vm_c, K_c, w_c = vm.cuda(), K.cuda(), weights.cuda()
        fwd_bwd(cuda, vm_c, K_c, size, "gsplat", w_c)  # warm-up (JIT load, allocator)
        gs_s, gs = _timed(cuda, vm_c, K_c, size, "gsplat", w_c, repeats)
        result["gsplat_ms"] = round(gs_s * 1e3, 2)
        result["gsplat_device"] = torch.cuda.get_device_name()
        d = (gs["rgb"].cpu() - fast["rgb"]).abs()
        result["gsplat_vs_cpu_rgb_abs_diff"] = {"mean": float(d.mean()), "max": float(d.max())}
    if diffs:
        result["max_abs_diff"] = max(diffs)
    if depth_diffs:
        result["max_abs_diff_alpha_weighted_depth"] = max(depth_diffs)
    if result["reference_ms"]:
        result["speedup_vs_reference"] = round(result["reference_ms"] / result["fast_ms"], 1)
    if result["dense_ms"]:
        result["speedup_vs_dense"] = round(result["dense_ms"] / result["fast_ms"], 1)
    return result


def main(cases: str = "a,b,c", repeats: int = 5, threads: int = 2) -> dict:
    torch.set_num_threads(threads)
    load_before = os.getloadavg()
    out = []
    for name in cases.split(","):
        r = run_case(name.strip(), repeats)
        print(json.dumps(r), flush=True)
        out.append(r)
    cpu_name = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu_name = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    report = {
        "cases": out,
        "device": f"cpu: {cpu_name}, torch threads={threads}, os.cpu_count={os.cpu_count()}",
        "load_average_1m": [round(load_before[0], 2), round(os.getloadavg()[0], 2)],
        "repeats": repeats,
        "statistic": "median",
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "default (spinning)"),
    }
    print(json.dumps(report), flush=True)
    return report
