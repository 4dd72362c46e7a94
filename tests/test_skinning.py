"""The C++ linear blend skinning (render/splat/skinning.cpp) against its PyTorch reference (recon.lbs)."""

from __future__ import annotations

import numpy as np
import pytest
import roma
import torch

from t2bs.recon.control_points import build_control_points
from t2bs.recon.lbs import blend_matrix, lbs, lbs_reference, packed_transforms
from t2bs.render.splat.cpu import kernel_error, skin_cpu


@pytest.fixture(scope="module")
def kernel():
    err = kernel_error()
    assert err is None, f"C++ kernel failed to build: {err}"


def _scene(n=300, k=25, knn=6, batch=3, dtype=torch.float32, seed=0):
    rng = np.random.default_rng(seed)
    x = torch.tensor(rng.normal(size=(n, 3)), dtype=dtype)
    cps = build_control_points(x.numpy().astype(np.float64), None, k=k, knn=knn)
    p = torch.as_tensor(cps.positions).to(dtype)
    nb = torch.as_tensor(cps.neighbours)
    w = torch.as_tensor(cps.weights).to(dtype)
    g = torch.Generator().manual_seed(seed)
    q_rest = torch.randn(n, 4, generator=g, dtype=torch.float64)
    q_rest = (q_rest / q_rest.norm(dim=-1, keepdim=True)).to(dtype)
    rv = 0.4 * torch.randn(batch, k, 3, generator=g, dtype=dtype)
    tr = 0.1 * torch.randn(batch, k, 3, generator=g, dtype=dtype)
    rest = x[None] + 0.05 * torch.randn(batch, n, 3, generator=g, dtype=dtype)  # an expression per item
    return x, rest, q_rest, p, nb, w, rv, tr


@pytest.mark.parametrize("batched_rest", [False, True])
def test_cpp_equals_reference(kernel, batched_rest):
    """Positions, rotations and the gradients to the transforms and to a rest pose that wants one agree with the
    reference (the sparse-matmul blend) to float rounding."""
    x, rest, q_rest, p, nb, w, rv0, tr0 = _scene()
    matrix = blend_matrix(nb, w, len(p))
    results = []
    for fn in ("reference", "cpp"):
        rv, tr = rv0.clone().requires_grad_(), tr0.clone().requires_grad_()
        xr = (rest if batched_rest else x).clone().requires_grad_()
        if fn == "reference":
            xt, qt = lbs_reference(xr, q_rest, p, rv, tr, nb, w, matrix)
        else:
            xt, qt = lbs(xr, q_rest, p, rv, tr, nb, w, matrix)
            assert "Skin" in type(xt.grad_fn).__name__
        (xt.square().sum() + (qt * torch.linspace(-1, 1, 4)).sum()).backward()
        results.append((xt.detach(), qt.detach(), rv.grad, tr.grad, xr.grad))
    for ref, fast in zip(*results):
        assert fast.shape == ref.shape
        assert float((fast - ref).abs().max()) <= 1e-5 * max(1.0, float(ref.abs().max()))
    assert results[0][0].sub(x).abs().max() > 0.05  # the transforms really move the points


def test_cpp_gradcheck_double(kernel):
    """The hand-written backward is the forward's derivative (finite differences, double precision): to the packed
    transforms and to a per-item rest pose."""
    x, rest, q_rest, p, nb, w, rv, tr = _scene(n=40, k=8, knn=4, batch=2, dtype=torch.float64, seed=1)
    packed = packed_transforms(rv, tr, p).detach().requires_grad_()
    rest = rest.detach().requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: skin_cpu(a, b, q_rest, nb, w), (packed, rest))


def test_cpp_is_deterministic_and_dispatch(kernel):
    """Two backward passes give the same gradient to the last bit; a weight tensor that wants a gradient is left to
    the reference (the C++ backward gives it none); a bad neighbour index is refused, not read out of bounds."""
    x, rest, q_rest, p, nb, w, rv, tr = _scene(n=500, k=30, knn=8, batch=5, seed=2)
    packed = packed_transforms(rv, tr, p)
    grads = []
    for _ in range(2):
        pk = packed.detach().clone().requires_grad_()
        xt, qt = skin_cpu(pk, rest, q_rest, nb, w)
        (xt.sin().sum() + qt.cos().sum()).backward()
        grads.append(pk.grad)
    assert torch.equal(grads[0], grads[1])
    assert skin_cpu(packed, rest, q_rest, nb, w.clone().requires_grad_()) is None
    with pytest.raises(RuntimeError, match="outside"):
        skin_cpu(packed, rest, q_rest, nb + len(p), w)


def test_identity_transforms_keep_the_rest_pose(kernel):
    """Zero motion: every vertex at its rest position with its rest orientation (a rotation, as the reference)."""
    x, rest, q_rest, p, nb, w, rv, tr = _scene(n=200, k=20, knn=5, batch=2, seed=3)
    zeros = torch.zeros(2, len(p), 3)
    xt, qt = lbs(x, q_rest, p, zeros, zeros, nb, w, blend_matrix(nb, w, len(p)))
    torch.testing.assert_close(xt, x.expand(2, -1, -1), atol=1e-5, rtol=0)
    torch.testing.assert_close(roma.unitquat_to_rotmat(qt), roma.unitquat_to_rotmat(q_rest).expand(2, -1, -1, -1))
