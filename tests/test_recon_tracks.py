"""Optical-flow vertex tracks (recon/tracks.py) against known motion."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from t2bs.geometry.mesh import Mesh
from t2bs.recon.gaussians import camera_tensors
from t2bs.recon.tracks import VertexTracks, compute_tracks, project_points, rest_visibility, track_loss
from t2bs.recon.images import resize_stack
from test_recon import sphere_mesh, splat_grid


def _true_motion(grid, frames: np.ndarray) -> np.ndarray:
    """[V, T, N, 2] projected pixel motion of the true vertices from frame 0."""
    out = []
    for cam in grid.cameras:
        uv = np.stack([cam.project(f.astype(np.float64))[0] for f in frames])  # [T, N, 2]
        out.append(uv - uv[:1])
    return np.stack(out).astype(np.float32)


def test_project_points_matches_camera():
    mesh = sphere_mesh(1)
    grid, _ = splat_grid(mesh, mesh.vertices[None], size=48, views=3)
    vm, ks = camera_tensors(grid.cameras)
    x = torch.as_tensor(mesh.vertices)[None].expand(3, -1, -1)
    uv = project_points(x, vm, ks).numpy()
    for v, cam in enumerate(grid.cameras):
        assert np.allclose(uv[v], cam.project(mesh.vertices.astype(np.float64))[0], atol=1e-3)


def test_tracks_follow_a_known_motion_and_skip_hidden_vertices():
    mesh = sphere_mesh(3)
    shift = np.array([0.04, -0.03, 0.0], np.float32)  # ~2 px at 64 px
    frames = np.stack([mesh.vertices, mesh.vertices + shift, mesh.vertices + 2 * shift]).astype(np.float32)
    grid, _ = splat_grid(mesh, frames, size=64, views=3)
    images = torch.stack([resize_stack(grid.frames[v], (64, 64)) for v in range(3)])
    tracks = compute_tracks(mesh, images, grid.cameras, [0, 1], fb_px=1.0, blur_px=0.5)  # every visible vertex
    assert tracks.displacement.shape == (3, 3, mesh.num_vertices, 2) and tracks.weights.shape == (
        3,
        3,
        mesh.num_vertices,
    )
    assert float(tracks.weights[2].abs().max()) == 0.0  # view 2 was not asked for
    assert float(tracks.displacement[:, 0].abs().max()) == 0.0  # frame 0 is the rest pose
    true = _true_motion(grid, frames)
    for v in (0, 1):
        cam = grid.cameras[v]
        facing = (mesh.vertex_normals() * (cam.position - mesh.vertices)).sum(-1) < 0  # back of the sphere
        assert float(tracks.weights[v, :, facing].max()) == 0.0  # never visible: never tracked
        for t in (1, 2):
            ok = tracks.weights[v, t].numpy() > 0
            assert ok.mean() > 0.3  # most of the visible half is tracked
            err = np.linalg.norm(tracks.displacement[v, t].numpy()[ok] - true[v, t][ok], axis=-1)
            moved = np.linalg.norm(true[v, t][ok], axis=-1)
            assert err.mean() < 0.3 * moved.mean(), (err.mean(), moved.mean())


def _dropping_jaw_scene(size: int):
    """A plainly coloured sphere whose lower half drops 0.3 over 8 frames, splatted at ``size`` px
    from 3 views: (mesh, frames [9, N, 3], grid, images [3, 9, size, size, 3])."""
    base = sphere_mesh(3)
    v = base.vertices
    col = 0.5 + 0.3 * np.sin(np.stack([2 * v[:, 0] + 2, 2 * v[:, 1] + 1, 2 * v[:, 2]], 1))
    mesh = Mesh(v, base.faces, vertex_colors=col.astype(np.float32))
    drop = (v[:, 1] < 0)[:, None] * np.array([0.0, -0.3, 0.0], np.float32)
    frames = np.stack([v + t / 8 * drop for t in range(9)]).astype(np.float32)
    grid, _ = splat_grid(mesh, frames, size=size, views=3)
    images = torch.stack([resize_stack(grid.frames[k], (size, size)) for k in range(3)])
    return mesh, frames, grid, images


def test_chained_tracks_follow_a_large_opening_that_direct_flow_loses():
    """A jaw-like opening: the lower half of a plainly coloured sphere drops ~17 px over 8 frames at
    64 px. Flow straight from frame 0 fails its round trip there (or is wrong); chained frame-to-frame
    flow keeps most of those vertices and recovers their motion."""
    mesh, frames, grid, images = _dropping_jaw_scene(64)
    true = _true_motion(grid, frames)[0, -1]
    moving = rest_visibility(mesh, grid.cameras, [0])[0] & (np.linalg.norm(true, axis=-1) > 3)
    assert moving.sum() > 50 and np.linalg.norm(true[moving], axis=-1).mean() > 12

    def valid_and_error(chain: bool):
        tr = compute_tracks(mesh, images, grid.cameras, [0], fb_px=1.0, blur_px=0.5, chain=chain, agree_px=1.0)
        ok = moving & (tr.weights[0, -1].numpy() > 0)
        err = np.linalg.norm(tr.displacement[0, -1].numpy()[ok] - true[ok], axis=-1)
        return ok.sum() / moving.sum(), (err.mean() if ok.any() else np.inf)

    direct_valid, _ = valid_and_error(False)
    chained_valid, chained_err = valid_and_error(True)
    assert direct_valid < 0.1
    assert chained_valid > 0.5 and chained_err < 0.15 * np.linalg.norm(true[moving], axis=-1).mean()


def test_upsampled_flow_tracks_a_small_image_closer_and_in_its_own_pixels():
    """The same dropping lower half at 32 px, where DIS's 8 px patches span much of the moving part:
    flow on images upsampled to 64 px (flow_size) recovers more of the motion, and its tracks come
    back in the 32 px images' pixels (the gain on the true motion is near 1, not near 2)."""
    mesh, frames, grid, images = _dropping_jaw_scene(32)
    true = _true_motion(grid, frames)[0]
    moving = rest_visibility(mesh, grid.cameras, [0])[0][None] & (np.linalg.norm(true, axis=-1) > 1.6)

    def gain_and_error(flow_size: int):
        tr = compute_tracks(mesh, images, grid.cameras, [0], fb_px=0.5, blur_px=0.25, agree_px=0.5, flow_size=flow_size)
        ok = moving & (tr.weights[0].numpy() > 0)
        d, g = tr.displacement[0].numpy()[ok], true[ok]
        assert ok.sum() > 0.5 * moving.sum()
        return (d * g).sum() / (g * g).sum(), np.linalg.norm(d - g, axis=-1).mean()

    gain0, err0 = gain_and_error(0)
    gain2, err2 = gain_and_error(64)
    assert err2 < 0.75 * err0, (err0, err2)
    assert abs(gain2 - 1.0) < 0.15 and abs(gain2 - 1.0) < abs(gain0 - 1.0), (gain0, gain2)


def test_track_loss_is_zero_at_the_true_motion_and_grows_away_from_it():
    mesh = sphere_mesh(1)
    frames = np.stack([mesh.vertices, mesh.vertices + [0.05, 0.0, 0.0]]).astype(np.float32)
    grid, _ = splat_grid(mesh, frames, size=48, views=3)
    true = torch.as_tensor(_true_motion(grid, frames))
    w = torch.ones(true.shape[:3])
    w[:, :, ::2] = 0.0  # invalid tracks must not count
    tracks = VertexTracks(true, w)
    vm, ks = camera_tensors(grid.cameras)
    v_idx, t_idx = torch.tensor([0, 1, 2]), torch.tensor([1, 1, 1])
    x0 = torch.as_tensor(frames[0])[None].expand(3, -1, -1)
    xt = torch.as_tensor(frames[1])[None].expand(3, -1, -1)
    at_truth = track_loss(xt, x0, vm, ks, tracks, v_idx, t_idx)
    assert float(at_truth) < 1e-6
    off = [float(track_loss(xt + d, x0, vm, ks, tracks, v_idx, t_idx)) for d in (0.01, 0.03, 0.1)]
    assert 0 < off[0] < off[1] < off[2]
    # The rest pose as the view sees it (a static per-view offset) is not motion.
    bias = torch.tensor([0.0, 0.02, 0.0])
    assert float(track_loss(xt + bias, x0 + bias, vm, ks, tracks, v_idx, t_idx)) < 0.05 * off[1]
    # Tracks starting on untextured pixels count flat_weight times as much: with 0, a wrong motion
    # of those vertices costs nothing; with 1 they count like the others.
    textured = torch.ones(true.shape[0], true.shape[2], dtype=torch.bool)
    textured[:, 1::4] = False
    wrong = xt.clone()
    wrong[:, 1::4] += 0.05
    flat = VertexTracks(true, w, textured)
    assert float(track_loss(wrong, x0, vm, ks, flat, v_idx, t_idx, flat_weight=0.0)) < 1e-6
    full = float(track_loss(wrong, x0, vm, ks, tracks, v_idx, t_idx))
    assert full > 0.1 and float(track_loss(wrong, x0, vm, ks, flat, v_idx, t_idx, flat_weight=1.0)) == pytest.approx(
        full
    )


def test_track_slack_frees_motion_beyond_the_track_along_it_only():
    """``slack``: flow under-reports a small motion, so going further along the track (up to slack x its length)
    costs nothing; falling short, going past the slack, or moving across the track costs as without it; a track
    that does not move (the still head), or whose motion is all the model's head motion, gives no slack."""
    mesh = sphere_mesh(1)
    frames = np.stack([mesh.vertices, mesh.vertices + [0.05, 0.0, 0.0]]).astype(np.float32)
    grid, _ = splat_grid(mesh, frames, size=48, views=3)
    true = torch.as_tensor(_true_motion(grid, frames))
    tracks = VertexTracks(true, torch.ones(true.shape[:3]))
    vm, ks = camera_tensors(grid.cameras)
    v_idx, t_idx = torch.tensor([0, 1, 2]), torch.tensor([1, 1, 1])
    x0 = torch.as_tensor(frames[0])[None].expand(3, -1, -1)

    def loss(motion, slack: float, trk=tracks) -> float:
        return float(
            track_loss(x0 + torch.as_tensor(motion, dtype=torch.float32), x0, vm, ks, trk, v_idx, t_idx, slack=slack)
        )

    assert loss([0.05, 0, 0], 1.0) < 1e-6
    assert loss([0.09, 0, 0], 1.0) < 1e-3 < loss([0.09, 0, 0], 0.0)  # further along the track: free within the slack
    assert loss([0.02, 0, 0], 1.0) == pytest.approx(loss([0.02, 0, 0], 0.0), rel=1e-4)  # short of it: the same cost
    assert loss([0.13, 0, 0], 1.0) == pytest.approx(loss([0.08, 0, 0], 0.0), rel=0.05)  # past the slack: from its end
    across = loss([0.05, 0.03, 0], 1.0)
    assert across > 0.1 and across == pytest.approx(loss([0.05, 0.03, 0], 0.0), rel=0.05)
    still = VertexTracks(torch.zeros_like(true), torch.ones(true.shape[:3]))
    assert loss([0.02, 0, 0], 1.0, still) == pytest.approx(loss([0.02, 0, 0], 0.0, still))
    # Motion the model's head motion already explains gets no slack: here all of the track is the head's.
    head = true[v_idx, t_idx]
    moved = x0 + torch.tensor([0.09, 0.0, 0.0])
    with_head = float(track_loss(moved, x0, vm, ks, tracks, v_idx, t_idx, slack=1.0, head=head))
    assert with_head == pytest.approx(loss([0.09, 0, 0], 0.0), rel=1e-4)


def test_head_motion_px_is_the_global_motion_from_frame_0_projected():
    """What the slack leaves out: the image motion the model's global SE(3) alone gives, frame 0 -> t, with a view's
    frame-0 pose undone first (here a per-view offset at frame 0 and a turn plus a shift at t)."""
    import roma

    from t2bs.eval.scenes import lid_scene
    from t2bs.recon.config import preset
    from t2bs.recon.vcdgs import _head_motion_px, build_model, prepare_data

    mesh, grid = lid_scene(frames=4, size=32, views=3)
    cfg = preset("quick", resolution=32, static_iters=0, num_control_points=40, hidden=32, depth=2)
    data = prepare_data(grid, cfg)
    torch.manual_seed(0)
    model, _ = build_model(mesh, data, cfg)
    v_idx, t_idx = torch.tensor([1, 2]), torch.tensor([2, 3])
    g0 = torch.tensor([[0.0, 0.02, 0.0, 0.01, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, -0.02, 0.0]])  # frame 0, per view
    g = torch.tensor([[0.0, 0.1, 0.0, 0.03, 0.0, 0.0], [0.05, 0.0, 0.0, 0.0, 0.0, 0.02]])  # frame t

    class FrameZero(torch.nn.Module):  # the global motion at frame 0, which is all _head_motion_px asks of it
        def forward(self, v, t, on):
            return torch.zeros(len(v), 6), g0.clone()

    model.global_se3 = FrameZero()
    out = {"g_shared": g, "g_residual": torch.zeros_like(g)}
    x0 = torch.as_tensor(mesh.vertices, dtype=torch.float32)[None] + torch.tensor(
        [[[0.0, 0.0, 0.01]], [[0.0, 0.0, 0.0]]]
    )
    vm, ks = camera_tensors(data.cameras)
    got = _head_motion_px(model, out, x0, vm[v_idx], ks[v_idx], v_idx, t_idx)
    # frame 0's pose undone (inverse of x -> R0 x + t0), then frame t's applied
    rest = (x0 - g0[:, None, 3:]) @ roma.rotvec_to_rotmat(g0[:, :3])
    moved = rest @ roma.rotvec_to_rotmat(g[:, :3]).transpose(1, 2) + g[:, None, 3:]
    want = project_points(moved, vm[v_idx], ks[v_idx]) - project_points(x0, vm[v_idx], ks[v_idx])
    assert got.shape == (2, mesh.num_vertices, 2) and float(got.abs().max()) > 0.5  # pixels: a visible motion
    torch.testing.assert_close(got, want, atol=1e-4, rtol=1e-4)
    assert _head_motion_px(model, {"g_shared": None}, x0, vm[v_idx], ks[v_idx], v_idx, t_idx) is None


def test_perfect_tracks_are_the_truth_projected_with_the_flows_validity():
    """The benchmark's --perfect-tracks: every trained view's tracks are the true vertices' image motion from frame 0,
    valid where the flow's are; reconstruct_grid trains on what its tracks_fn makes."""
    from t2bs.eval.bench_vcdgs import perfect_tracks_fn
    from t2bs.eval.scenes import lid_scene
    from t2bs.recon.config import preset
    from t2bs.recon.vcdgs import prepare_data, vertex_tracks

    mesh, grid = lid_scene(frames=4, size=32, views=3)
    cfg = preset("quick", resolution=32, static_iters=0, num_control_points=40, hidden=32, depth=2, holdout_views=(2,))
    data = prepare_data(grid, cfg)
    flow = vertex_tracks(mesh, data, cfg)
    perfect = perfect_tracks_fn(grid.gt_vertices)(mesh, data, cfg)
    assert data.train_views == [0, 1]
    torch.testing.assert_close(perfect.weights, flow.weights)
    true = _true_motion(grid, grid.gt_vertices)
    torch.testing.assert_close(perfect.displacement[:2], torch.from_numpy(true[:2]), atol=1e-4, rtol=0)
    assert float(true[:2].max()) > 1.0 and float(perfect.displacement[2].abs().max()) == 0.0  # held out: none
    _deterministic_when_tracks_are_made(mesh, grid, cfg)  # reconstruct_grid asks its tracks_fn for the tracks


def _deterministic_when_tracks_are_made(mesh, grid, cfg) -> bool:
    """Run ``reconstruct_grid`` up to its ``tracks_fn``, which must be called once: whether torch's deterministic
    algorithms were on at that point."""
    from t2bs.recon.vcdgs import reconstruct_grid

    seen = []

    class Stop(Exception):
        pass

    def spy(*args):
        seen.append(torch.are_deterministic_algorithms_enabled())
        raise Stop

    with pytest.raises(Stop):
        reconstruct_grid(mesh, grid, cfg, progress=False, tracks_fn=spy)
    assert len(seen) == 1
    return seen[0]


def test_reconstruction_runs_in_deterministic_mode_on_the_cpu_and_restores_it():
    """A CPU reconstruction runs with torch's deterministic algorithms (a gather's backward otherwise adds with
    atomics, so a busy machine changed a seeded run's result), and leaves the caller's setting as it was."""
    from t2bs.eval.scenes import lid_scene
    from t2bs.recon.config import preset

    mesh, grid = lid_scene(frames=2, size=32, views=3)
    cfg = preset("quick", resolution=32, static_iters=0, num_control_points=40, hidden=32, holdout_views=(2,))
    assert not torch.are_deterministic_algorithms_enabled()
    assert _deterministic_when_tracks_are_made(mesh, grid, cfg.replace(device="cpu"))
    assert not torch.are_deterministic_algorithms_enabled()


def test_residual_tracks_add_what_the_render_misses_and_cancel_a_still_offset():
    from scipy.ndimage import gaussian_filter, shift

    from t2bs.recon.tracks import residual_tracks

    rng = np.random.default_rng(0)
    texture = gaussian_filter(rng.random((64, 64)), 2.0)
    texture = (texture - texture.min()) / (texture.max() - texture.min())

    def image(offset):  # the texture moved by ``offset`` (x, y) px, as RGB
        return np.repeat(shift(texture, (offset[1], offset[0]), order=3, mode="nearest")[..., None], 3, -1)

    model = [np.zeros(2), np.array([1.0, 0.0]), np.array([1.5, -0.5])]  # the model's motion (render)
    truth = [np.zeros(2), np.array([2.5, -1.0]), np.array([3.0, 1.0])]  # the input's
    still = np.array([0.6, 0.4])  # render and input disagree at rest too: not motion
    renders = np.stack([[image(m) for m in model]]).astype(np.float32)  # [1, 3, 64, 64, 3]
    images = np.stack([[image(g + still) for g in truth]]).astype(np.float32)
    ys, xs = np.mgrid[20:44:4, 20:44:4]
    rest = np.stack([xs.ravel(), ys.ravel()], -1).astype(np.float32) + 0.5  # [N, 2] pixel centres
    projected = np.stack([[rest + m for m in model]]).astype(np.float32)  # [1, 3, N, 2]
    n = len(rest)
    old = VertexTracks(torch.zeros(1, 3, n, 2), torch.ones(1, 3, n))
    old.weights[0, :, 0] = 0.0  # not seen at rest: keeps its (zero) track and weight
    new = residual_tracks(old, renders, images, projected, [0], fb_px=1.0, blur_px=0.0)
    assert float(new.weights[0, :, 0].max()) == 0.0 and float(new.displacement[0, :, 0].abs().max()) == 0.0
    assert float(new.displacement[0, 0].abs().max()) == 0.0  # frame 0 stays the rest pose
    for t in (1, 2):
        ok = new.weights[0, t, 1:].numpy() > 0
        assert ok.mean() > 0.9
        err = np.linalg.norm(new.displacement[0, t, 1:].numpy()[ok] - truth[t], axis=-1)
        assert err.mean() < 0.2, (t, err.mean())  # the truth, not the model's motion nor the still offset
    # a track whose motion beyond the head's is already long keeps the first flow's value
    old.displacement[0, 1:, 1] = torch.tensor([6.0, 0.0])
    head = np.zeros((1, 3, n, 2), np.float32)
    head[0, :, 2] = (6.0, 0.0)  # the head moved vertex 2 as far: its own motion is short
    old.displacement[0, 1:, 2] = torch.tensor([6.0, 0.0])
    gated = residual_tracks(old, renders, images, projected, [0], fb_px=1.0, blur_px=0.0, head=head, below_px=3.0)
    assert torch.equal(gated.displacement[0, :, 1], old.displacement[0, :, 1])
    assert float(np.linalg.norm(gated.displacement[0, 2, 2].numpy() - truth[2])) < 0.3
