"""The C++ face Gaussians (render/splat/faces.cpp) against their PyTorch reference (recon.gaussians)."""

from __future__ import annotations

import pytest
import torch

from t2bs.recon.gaussians import face_gaussians, face_gaussians_reference
from t2bs.render.splat.cpu import face_gaussians_cpu, kernel_error


@pytest.fixture(scope="module")
def kernel():
    err = kernel_error()
    assert err is None, f"C++ kernel failed to build: {err}"


def _sheet(n: int = 12, batch: int = 3, seed: int = 0, dtype=torch.float32):
    """A wavy n x n vertex sheet, each batch item turned by its own random rotation and jittered: triangles facing
    every way, so all four of Shepperd's formulas are used. -> x [B, n*n, 3], faces [F, 3]."""
    g = torch.Generator().manual_seed(seed)
    i, j = torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij")
    base = torch.stack([i.flatten() / n, j.flatten() / n, 0.1 * torch.sin(3.0 * i.flatten() / n)], -1).double()
    q = torch.randn(batch, 4, generator=g, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    w, a, b, c = q.unbind(-1)
    rot = torch.stack(
        [
            torch.stack([1 - 2 * (b * b + c * c), 2 * (a * b - w * c), 2 * (a * c + w * b)], -1),
            torch.stack([2 * (a * b + w * c), 1 - 2 * (a * a + c * c), 2 * (b * c - w * a)], -1),
            torch.stack([2 * (a * c - w * b), 2 * (b * c + w * a), 1 - 2 * (a * a + b * b)], -1),
        ],
        -2,
    )
    x = torch.einsum("bij,nj->bni", rot, base) + 0.01 * torch.randn(batch, n * n, 3, generator=g, dtype=torch.float64)
    quads = [
        (r * n + s, r * n + s + 1, (r + 1) * n + s, (r + 1) * n + s + 1) for r in range(n - 1) for s in range(n - 1)
    ]
    faces = torch.tensor([f for a0, a1, b0, b1 in quads for f in ((a0, b0, a1), (a1, b0, b1))], dtype=torch.int64)
    return x.to(dtype), faces


def _formulas(quats_xyzw: torch.Tensor) -> set[int]:
    """Which of Shepperd's formulas gives each quaternion: its largest |component| (w first, as the trace's test)."""
    big = quats_xyzw.abs().argmax(-1)
    return {0 if int(k) == 3 else int(k) + 1 for k in big.flatten()}


def _run(fn, x, faces, log_scale, grads):
    x = x.detach().clone().requires_grad_(True)
    out = fn(x, faces, log_scale, 0.25)
    sum((o * g).sum() for o, g in zip(out, grads)).backward()
    return [o.detach() for o in out], x.grad


def test_cpp_equals_reference_float32(kernel):
    """Every output and the gradient to the vertices agree to float rounding; the quaternion up to its sign (the same
    rotation: a tie between two formulas can be broken the other way)."""
    x, faces = _sheet()
    log_scale = 0.2 * torch.randn(len(faces), generator=torch.Generator().manual_seed(1))
    out_ref = face_gaussians_reference(x, faces, log_scale, 0.25)
    assert len(_formulas(out_ref[1])) == 4  # the scene reaches every branch
    grads = [torch.randn(o.shape, generator=torch.Generator().manual_seed(2 + k)) for k, o in enumerate(out_ref)]
    (rm, rq, rs), rg = _run(face_gaussians_reference, x, faces, log_scale, grads)
    (cm, cq, cs), cg = _run(face_gaussians_cpu, x, faces, log_scale, grads)
    sign = torch.sign((rq * cq).sum(-1, keepdim=True))
    torch.testing.assert_close(cm, rm, rtol=0, atol=1e-7)
    torch.testing.assert_close(sign * cq, rq, rtol=0, atol=2e-6)
    torch.testing.assert_close(cs, rs, rtol=1e-5, atol=1e-9)
    assert (sign > 0).float().mean() > 0.99
    # the gradient: sums over a vertex's triangles in another order, so relative to the largest
    assert float((cg - rg).abs().max() / rg.abs().max()) < 1e-5


def test_cpp_gradcheck_double(kernel):
    """The hand-written backward is the forward's derivative (finite differences, double precision), log scales
    non-zero so that every scale's path is used."""
    x, faces = _sheet(n=6, batch=2, seed=3, dtype=torch.float64)
    log_scale = 0.3 * torch.randn(len(faces), generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    x.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a: face_gaussians_cpu(a, faces, log_scale, 0.25), (x,))


def test_cpp_degenerate_triangle_as_reference(kernel):
    """A triangle with two corners at one point (zero area, the norms' clamps hold) and one collapsed to a point: the
    same finite values and gradients as the reference, in double precision."""
    x, faces = _sheet(n=4, batch=1, seed=5, dtype=torch.float64)
    x[0, 1] = x[0, 0]  # faces using vertices 0 and 1 lose an edge
    faces = torch.cat([faces, torch.tensor([[2, 2, 2]])])  # a point
    log_scale = torch.zeros(len(faces), dtype=torch.float64)
    grads = [torch.ones(1, len(faces), k, dtype=torch.float64) for k in (3, 4, 3)]
    (rm, rq, rs), rg = _run(face_gaussians_reference, x, faces, log_scale, grads)
    (cm, cq, cs), cg = _run(face_gaussians_cpu, x, faces, log_scale, grads)
    assert torch.isfinite(cg).all() and torch.isfinite(cq).all()
    sign = torch.sign((rq * cq).sum(-1, keepdim=True))
    torch.testing.assert_close(cm, rm)
    torch.testing.assert_close(sign * cq, rq)
    torch.testing.assert_close(cs, rs)
    torch.testing.assert_close(cg, rg)


def test_dispatch(kernel):
    """face_gaussians runs the C++ op on CPU float tensors, the reference where the C++ backward would drop a gradient
    (a log scale that wants one); bad indices are refused by the kernel, not read out of bounds."""
    x, faces = _sheet(n=4, batch=1)
    x.requires_grad_(True)
    log_scale = torch.zeros(len(faces))
    assert "FaceGaussians" in type(face_gaussians(x, faces, log_scale)[0].grad_fn).__name__
    log_scale.requires_grad_(True)
    assert face_gaussians_cpu(x, faces, log_scale, 0.25) is None
    out = face_gaussians(x, faces, log_scale)
    out[2].sum().backward()
    assert log_scale.grad is not None and float(log_scale.grad.abs().sum()) > 0
    with pytest.raises(RuntimeError, match="outside"):
        face_gaussians_cpu(x.detach(), faces + x.shape[1], torch.zeros(len(faces)), 0.25)


def test_cpp_is_deterministic(kernel):
    """Two runs give the same gradient to the last bit (the batch's items split across threads in a fixed order)."""
    x, faces = _sheet(n=16, batch=5, seed=6)
    log_scale = torch.zeros(len(faces))
    grads = [torch.randn(5, len(faces), k, generator=torch.Generator().manual_seed(k)) for k in (3, 4, 3)]
    _, g1 = _run(face_gaussians_cpu, x, faces, log_scale, grads)
    _, g2 = _run(face_gaussians_cpu, x, faces, log_scale, grads)
    assert torch.equal(g1, g2)
