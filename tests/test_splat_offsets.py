"""Splat offsets (issue 37): edge Gaussians shifted along the surface so that a splat part ends where the mesh part
ends, carried by the deformed edges."""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np
import roma
import torch
import trimesh

from t2bs.recon.gaussians import near_open_edges, ring_weights, vertex_rings


def _cap():
    """A sphere with a hole cut in it: open edges around the hole."""
    s = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    keep = s.triangles_center[:, 2] < 0.35
    s.update_faces(keep)
    s.remove_unreferenced_vertices()
    return np.asarray(s.vertices, np.float64), np.asarray(s.faces, np.int64)


def test_open_edges_and_their_neighbours_are_marked():
    v, f = _cap()
    near = near_open_edges(v, f).astype(bool)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), 1)
    u, c = np.unique(e, axis=0, return_counts=True)
    rim = np.unique(u[c == 1])
    assert near[rim].all() and 0 < near.sum() < len(v)
    closed = trimesh.creation.icosphere(subdivisions=1)
    cv, cf = np.asarray(closed.vertices), np.asarray(closed.faces)
    assert not near_open_edges(cv, cf).any()
    # A UV seam: the faces of one half get their own copies of the vertices (as exporters split them); each side
    # of the cut uses its edges once, but welded it is one closed surface, with no border.
    half = closed.triangles_center[:, 0] > 0
    split = cf.copy()
    split[half] += len(cv)
    assert not near_open_edges(np.concatenate([cv, cv]), split).any()


def test_ring_weights_rebuild_the_offsets_and_follow_a_rigid_motion_and_a_stretch():
    """sum_k w_k (v[ring_k] - v) gives the offsets back at rest, turns with a rotation, scales with a stretch."""
    from t2bs.recon.config import preset
    from t2bs.recon.deform import VCDGSModel

    v, f = _cap()
    n = len(v)
    rng = np.random.default_rng(0)
    normals = trimesh.Trimesh(v, f, process=False).vertex_normals
    tangent = rng.normal(size=(n, 3))
    tangent -= (tangent * normals).sum(1, keepdims=True) * normals
    offsets = 0.02 * tangent * near_open_edges(v, f)[:, None]
    ring = vertex_rings(f, n)
    w = ring_weights(v, ring, offsets)
    np.testing.assert_allclose((w[..., None] * (v[ring] - v[:, None])).sum(1), offsets, atol=1e-6)

    cfg = preset("quick", face_gaussians=False)
    q = np.tile(np.array([0, 0, 0, 1.0], np.float32), (n, 1))
    model = VCDGSModel(
        v, q, np.zeros((n, 3)), np.ones((n, 3)), v[:4], np.zeros((n, 1), np.int64), np.ones((n, 1)), 1, 1, 0, cfg,
        ring=ring, ring_weights=w,
    )  # fmt: skip
    rot = roma.rotvec_to_rotmat(torch.tensor([0.3, -0.5, 0.2])).double()
    t = torch.tensor([0.1, 0.2, -0.3], dtype=torch.float64)
    x, o = torch.as_tensor(v), torch.as_tensor(offsets)
    qs = torch.as_tensor(q)[None]
    for moved, expect in ((x @ rot.T + t, (x + o) @ rot.T + t), (1.7 * x, 1.7 * (x + o))):
        centres = model.splats_at(moved[None].float(), qs, qs[..., :3], qs[..., :3])[0][0]
        np.testing.assert_allclose(centres.numpy(), expect.numpy(), atol=1e-5)
    copied = copy.deepcopy(model)  # the sparse matrix's parts are plain buffers
    torch.testing.assert_close(
        copied.splats_at(x[None].float(), qs, qs[..., :3], qs[..., :3])[0],
        model.splats_at(x[None].float(), qs, qs[..., :3], qs[..., :3])[0],
    )
    # The vertices themselves (what the mesh is read from) are not moved: only the rendered centres.
    assert torch.equal(model.means, torch.as_tensor(v, dtype=torch.float32))


def test_ring_shift_as_a_sparse_matmul_equals_the_gather_values_and_gradients():
    """The CPU path (one CSR matmul each way) against the gather it replaces, on a mesh whose rings are padded (the
    cap's rim has fewer than 8 neighbours) and whose closed part does not shift: the same shifts and the same
    gradient to float rounding."""
    from t2bs.recon.gaussians import ring_shift, ring_shift_matrix, ring_shift_sparse

    v, f = _cap()
    n = len(v)
    ring = torch.as_tensor(vertex_rings(f, n))
    rng = np.random.default_rng(1)
    offsets = 0.02 * rng.normal(size=(n, 3)) * near_open_edges(v, f)[:, None]
    w = torch.as_tensor(ring_weights(v, ring.numpy(), offsets))
    assert (ring == torch.arange(n)[:, None]).any() and (w.abs().sum(1) == 0).any()
    parts = ring_shift_matrix(ring, w)
    x = (torch.as_tensor(v, dtype=torch.float32)[None] + 0.05 * torch.randn(3, n, 3)).requires_grad_(True)
    grad = torch.randn(3, n, 3)
    ref = ring_shift(x, ring, w)
    fast = ring_shift_sparse(x, parts)
    torch.testing.assert_close(fast, ref, atol=1e-6, rtol=0)
    g_ref, g_fast = (torch.autograd.grad(y, x, grad)[0] for y in (ref, fast))
    torch.testing.assert_close(g_fast, g_ref, atol=1e-5, rtol=0)
    # S has no row for a vertex that does not shift, and S^T is its transpose
    s = torch.sparse_csr_tensor(*parts[:3], (n, n), check_invariants=True).to_dense()
    s_t = torch.sparse_csr_tensor(*parts[3:], (n, n), check_invariants=True).to_dense()
    assert torch.equal(s_t, s.T) and not s[w.abs().sum(1) == 0].any()


def test_corner_mean_backward_as_a_sparse_matmul_gives_the_gathers_bits():
    """A face's colour offset, the mean of its corners', with its backward as one CSR matmul (the CPU path): the same
    bits as the gather's, forward and backward under deterministic mode (the demo's results stay what they were),
    with vertices no face uses getting no gradient."""
    from t2bs.recon.gaussians import corner_matrix_t, corner_mean

    v, f = _cap()
    n = len(v) + 2  # two vertices on no face: their rows are empty
    faces = torch.as_tensor(f, dtype=torch.int64)
    parts = corner_matrix_t(faces, n)
    x = torch.randn(4, n, 3, requires_grad=True)
    grad = torch.randn(4, len(faces), 3)
    ref = x[:, faces].mean(2)
    fast = corner_mean(x, faces, parts)
    assert torch.equal(fast, ref)
    deterministic = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(True)
    try:
        g_ref, g_fast = (torch.autograd.grad(y, x, grad)[0] for y in (ref, fast))
    finally:
        torch.use_deterministic_algorithms(deterministic)
    assert torch.equal(g_fast, g_ref) and not g_fast[:, -2:].any()
    m_t = torch.sparse_csr_tensor(*parts, (n, len(faces)), check_invariants=True).to_dense()
    assert torch.equal(m_t.sum(0), torch.full((len(faces),), 3.0))


def _lid_alone_area(model, mesh, cam_t, size):
    """Pixels (alpha > 0.5) the splat lid covers when rendered alone in the canonical view, at rest."""
    from t2bs.recon.gaussians import render

    lid = mesh.part_mask("eyelid_left")
    x = torch.as_tensor(mesh.vertices)[None]
    q, s, c = model.quats[None], model.log_scales.exp()[None], model.colors[None]
    centres = model.splats_at(x, q, s, c)[0][:, : mesh.num_vertices]  # the vertex Gaussians, moved by the offsets
    keep = torch.as_tensor(lid)
    out = render(centres[0, keep], q[0, keep], s[0, keep], c[0, keep], cam_t[0], cam_t[1], size, size)
    return int((out["alpha"][0, ..., 0] > 0.5).sum())


def test_static_fit_shrinks_a_thin_parts_splats_to_its_mesh_edge():
    """The lid scene's lid (a thin cap over a head of the same colour): its edge Gaussians spread past the mesh edge
    unseen at rest; with the offsets the splat lid alone covers fewer pixels, closer to the mesh lid's, and only
    Gaussians near open edges move (the closed head's stay on their vertices)."""
    from t2bs.eval.scenes import lid_scene
    from t2bs.recon.config import preset
    from t2bs.recon.gaussians import camera_tensors
    from t2bs.recon.vcdgs import build_model, prepare_data
    from t2bs.render.mesh_renderer import MeshRenderer

    mesh, grid = lid_scene(frames=2, size=64)
    cv = grid.canonical_view
    lid = mesh.part_mask("eyelid_left")
    lid_faces = lid[mesh.faces].all(1)
    with MeshRenderer() as r:
        mesh_area = int(
            r.render(replace(mesh, faces=mesh.faces[lid_faces]), grid.cameras[cv], shading="unlit").mask.sum()
        )
    vm, ks = camera_tensors([grid.cameras[cv]])
    areas = {}
    for on in (False, True):
        cfg = preset("quick", resolution=64, splat_offsets=on, face_gaussians=False)
        torch.manual_seed(0)
        model, gs = build_model(mesh, prepare_data(grid, cfg), cfg)
        areas[on] = _lid_alone_area(model, mesh, (vm, ks), 64)
        if on:
            moved = np.linalg.norm(gs.offsets, axis=1) > 0
            assert moved[lid].any() and not moved[~lid].any()
    # Measured: mesh lid 38 px, splat lid 70 px without the offsets, 41 with them.
    assert areas[True] < 0.75 * areas[False]
    assert abs(areas[True] - mesh_area) <= 0.25 * mesh_area
