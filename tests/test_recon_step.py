"""The VCDGS training step (issue 36): one batched step equals the per-pair steps it replaces, the compiled step
equals the eager one, the fused algebra equals roma's, and a run that trains nothing says so."""

from __future__ import annotations

import pytest
import roma
import torch

from t2bs.eval.scenes import lid_scene
from t2bs.recon.config import preset
from t2bs.recon.gaussians import camera_tensors, frame_quat
from t2bs.recon.lbs import matvec, quat_left_matrix, quat_right_matrix
from t2bs.recon.losses import PerceptualLoss
from t2bs.recon.tracks import VertexTracks, project_points
from t2bs.recon.vcdgs import _rest_as_seen, build_model, prepare_data, step_terms


def test_frame_quat_is_the_rotation_of_its_axes_including_half_turns():
    torch.manual_seed(0)
    rot = roma.random_rotmat(5000).double()
    # Each of Shepperd's four branches, and the half turns where the trace formula alone breaks down.
    rot[0] = torch.eye(3, dtype=rot.dtype)
    for i, d in enumerate(([1.0, -1, -1], [-1.0, 1, -1], [-1.0, -1, 1])):
        rot[1 + i] = torch.diag(torch.tensor(d, dtype=rot.dtype))
    q = frame_quat(rot[..., 0], rot[..., 1], rot[..., 2])
    assert torch.allclose(q.norm(dim=-1), torch.ones(len(q), dtype=q.dtype), atol=1e-9)
    assert (roma.unitquat_to_rotmat(q) - rot).abs().max() < 1e-6
    # Gradients stay finite through the branches not taken (their square roots are clamped).
    r = rot.float()[:, :, :].clone().requires_grad_(True)
    frame_quat(r[..., 0], r[..., 1], r[..., 2]).sum().backward()
    assert torch.isfinite(r.grad).all()


def test_quaternion_product_matrices_equal_roma():
    torch.manual_seed(1)
    p, q = roma.random_unitquat(200), roma.random_unitquat(200)
    ref = roma.quat_product(p, q)
    assert torch.allclose(matvec(quat_right_matrix(q), p), ref, atol=1e-6)
    assert torch.allclose(matvec(quat_left_matrix(p), q), ref, atol=1e-6)


def _scene(**overrides):
    """A small trained-from-scratch setup on the lid scene: model, data, config, cameras, loss, rest pose."""
    mesh, grid = lid_scene(frames=4, size=32, views=3)
    cfg = preset(
        "quick",
        resolution=32,
        static_iters=5,
        num_control_points=40,
        hidden=32,
        depth=2,
        refine_hidden=16,
        time_budget_s=0.0,
        **overrides,
    )
    data = prepare_data(grid, cfg)
    v, t, n = data.views, data.frames, mesh.num_vertices
    # Synthetic tracks with every weight 1: the track term's normaliser is then the same for every pair.
    g = torch.Generator().manual_seed(3)
    data.tracks = VertexTracks(
        torch.randn(v, t, n, 2, generator=g), torch.ones(v, t, n), torch.ones(v, n, dtype=torch.bool)
    )
    torch.manual_seed(0)
    model, _ = build_model(mesh, data, cfg)
    # Non-zero deformation networks (their last layers start at zero): every term and gradient is then non-trivial.
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=g))
    vm, ks = camera_tensors(data.cameras)
    return (
        model,
        data,
        cfg,
        vm,
        ks,
        PerceptualLoss(cfg.loss.perceptual, cfg.loss.lpips_weights),
        _rest_as_seen(model, data.views),
    )


def _loss_and_grads(model, fn):
    model.zero_grad(set_to_none=True)
    loss = fn()
    loss.backward()
    return loss.detach(), {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}


def test_batched_step_equals_the_mean_of_per_pair_steps():
    """One deformation + one rasterization call over B (view, time) pairs gives the loss and gradients of B separate
    single-pair steps averaged: every term is a mean over the batch (the track term too, its weights being equal)."""
    model, data, cfg, vm, ks, perc, rest = _scene()
    v_idx, t_idx = torch.tensor([1, 0, 2, 1]), torch.tensor([0, 3, 1, 2])
    for joint in (False, True):
        batched, g_b = _loss_and_grads(
            model, lambda: sum(step_terms(model, data, cfg, v_idx, t_idx, vm, ks, perc, joint, rest_seen=rest).values())
        )
        per_pair, g_p = _loss_and_grads(
            model,
            lambda: sum(
                sum(
                    step_terms(
                        model, data, cfg, v_idx[i : i + 1], t_idx[i : i + 1], vm, ks, perc, joint, rest_seen=rest
                    ).values()
                )
                for i in range(len(v_idx))
            )
            / len(v_idx),
        )
        assert float(batched) > 0
        assert torch.allclose(batched, per_pair, rtol=1e-5), (joint, float(batched), float(per_pair))
        assert g_b.keys() == g_p.keys() and len(g_b) >= (2 if not joint else 6)
        top = max(float(g.abs().max()) for g in g_p.values())
        for name in g_b:  # relative to the tensor's largest gradient (or 1e-3 of the largest of all: some are ~0)
            scale = max(float(g_p[name].abs().max()), 1e-3 * top)
            assert float((g_b[name] - g_p[name]).abs().max()) / scale < 1e-4, name


@pytest.mark.slow
def test_compiled_step_equals_the_eager_step():
    """config.runtime.compile: the same loss terms and gradients as the eager step (torch.compile, the rasterizer
    excluded)."""
    model, data, cfg, vm, ks, perc, rest = _scene()
    v_idx, t_idx = torch.tensor([1, 0, 2, 1]), torch.tensor([0, 3, 1, 2])
    compiled = torch.compile(step_terms, dynamic=False)
    for fn in (step_terms, compiled):
        terms = fn(model, data, cfg, v_idx, t_idx, vm, ks, perc, True, rest_seen=rest)
        model.zero_grad(set_to_none=True)
        sum(terms.values()).backward()
        grads = {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}
        if fn is step_terms:
            ref_terms, ref_grads = {k: float(v.detach()) for k, v in terms.items()}, grads
    assert set(terms) == set(ref_terms) and "track" in terms and "rigidity" in terms
    assert grads.keys() == ref_grads.keys()  # every parameter the eager step reaches, the compiled one reaches too
    for k, v in terms.items():
        assert float(v.detach()) == pytest.approx(ref_terms[k], rel=1e-4, abs=1e-7), k
    top = max(float(g.abs().max()) for g in ref_grads.values())
    for name, g in grads.items():
        scale = max(float(ref_grads[name].abs().max()), 1e-3 * top)
        assert float((g - ref_grads[name]).abs().max()) / scale < 1e-3, name


def test_the_compiled_step_is_two_graphs_around_the_rasterizer():
    """torch.compile traces the step as one graph before the rasterizer and one after (the LBS blend as a gather
    while tracing: the sparse matmul cut it into 16), so nothing but the rasterizer runs eagerly between them."""
    model, data, cfg, vm, ks, perc, rest = _scene()
    v_idx, t_idx = torch.tensor([1, 0, 2, 1]), torch.tensor([0, 3, 1, 2])
    for joint in (False, True):
        torch._dynamo.reset()
        seen = torch._dynamo.explain(step_terms)(model, data, cfg, v_idx, t_idx, vm, ks, perc, joint, rest_seen=rest)
        assert (seen.graph_count, seen.graph_break_count) == (2, 1), (joint, seen.break_reasons)
        assert "_render_uncompiled" in str(seen.break_reasons[0].reason)


def test_the_warm_up_step_gives_the_deformation_network_no_gradient_by_its_call():
    """The global warm-up trains T_global alone, and says so in the call (``deform_grad``): with every parameter
    requiring a gradient, the warm-up step's loss reaches T_global and not the DeformMLP, the joint step's both.
    A requires_grad flip alone is not enough under torch.compile: torch 2.11's guards missed it behind the step's
    graph breaks, and a compiled run on an H100 (and on this CPU with torch 2.11) trained nothing (issue 36)."""
    model, data, cfg, vm, ks, perc, rest = _scene()
    v_idx, t_idx = torch.tensor([1, 0, 2, 1]), torch.tensor([0, 3, 1, 2])
    assert all(p.requires_grad for p in model.parameters())
    for joint in (False, True):
        _, grads = _loss_and_grads(
            model, lambda: sum(step_terms(model, data, cfg, v_idx, t_idx, vm, ks, perc, joint, rest_seen=rest).values())
        )
        deform = [g for n, g in grads.items() if n.startswith("deform.") and g.abs().max() > 0]
        moved = [g for n, g in grads.items() if n.startswith("global_se3.") and g.abs().max() > 0]
        assert bool(deform) == joint and moved, (joint, len(deform), len(moved))


def test_a_training_run_that_leaves_the_network_unchanged_is_an_error(monkeypatch):
    """train(): joint steps that never change the deformation network (a broken step: CUDA graphs on an H100 did
    that silently) end in one UserError, not in a model that looks trained; a working run passes the check."""
    from t2bs.errors import UserError
    from t2bs.recon.vcdgs import train

    model, data, cfg, *_ = _scene(iterations=6, global_iters=2)
    before = [p.detach().clone() for p in model.deform.parameters()]
    train(model, data, cfg, progress=False)
    assert not all(torch.equal(p, b) for p, b in zip(model.deform.parameters(), before))
    model, data, cfg, *_ = _scene(iterations=6, global_iters=2)
    monkeypatch.setattr(torch.optim.Adam, "step", lambda self, closure=None: None)
    with pytest.raises(UserError, match="VCDGS trained nothing: 4 joint steps"):
        train(model, data, cfg, progress=False)


def test_the_track_term_means_the_same_at_every_training_resolution():
    """The track term counts its errors in pixels of a 128 px image: training the same model at 32 or at 64 px gives the
    same track term for the same motion, in fractions of the image (in the training images' own pixels it doubled)."""
    model, data32, cfg, _, _, perc, _ = _scene()
    _, grid = lid_scene(frames=4, size=64, views=3)
    data64 = prepare_data(grid, cfg.replace(resolution=64))
    v_idx, t_idx = torch.tensor([1, 0, 2, 1]), torch.tensor([0, 3, 1, 2])
    terms = {}
    for data in (data32, data64):
        side = max(data.size)
        vm, ks = camera_tensors(data.cameras)
        rest = _rest_as_seen(model, data.views)
        every_v = torch.arange(data.views).repeat_interleave(data.frames)
        with torch.no_grad():
            x = model(every_v, torch.arange(data.frames).repeat(data.views))["means"]
            moved = project_points(x, vm[every_v], ks[every_v]) - project_points(
                rest[every_v], vm[every_v], ks[every_v]
            )
            # the model's own motion off by 0.03 of the image side: the same error at both resolutions
            disp = (moved + 0.03 * side).reshape(data.views, data.frames, -1, 2)
            data.tracks = VertexTracks(
                disp, torch.ones(disp.shape[:3]), torch.ones(data.views, disp.shape[2], dtype=bool)
            )
            terms[side] = float(
                step_terms(model, data, cfg, v_idx, t_idx, vm, ks, perc, False, rest_seen=rest)["track"]
            )
    assert terms[32] > 0 and terms[64] == pytest.approx(terms[32], rel=1e-3)
