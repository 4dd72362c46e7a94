"""Linear blend skinning of Gaussian positions and rotations (paper eq. 1).

Each control point k carries a rigid transform given as a rotation vector r_k and a
translation t_k *about the control point*: T_k x = R_k (x - p_k) + p_k + t_k. This is an
ordinary SE(3) (rotation R_k, translation p_k + t_k - R_k p_k); expressing it about p_k keeps the
translation and rotation decoupled, which makes the zero-initialised MLP outputs well
conditioned. Positions blend linearly (x_t = sum_k w_k T_k x); orientations blend as
normalised weighted unit quaternions (hemisphere-aligned), then compose with the Gaussian's
rest orientation. Quaternions here are roma's XYZW; the rasterizer wants WXYZ (``to_wxyz``).
"""

from __future__ import annotations

import roma
import torch


def matvec(m: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """m [..., 3, 3] times x [..., 3] (broadcast) -> [..., 3]. Written as multiply + sum because
    einsum lowers to a CPU bmm over millions of 3x3 blocks, which loops per block (~10x slower)."""
    return (m * x[..., None, :]).sum(-1)


def quat_right_matrix(q: torch.Tensor) -> torch.Tensor:
    """q [..., 4] XYZW -> M [..., 4, 4] with p (x) q = M p for every quaternion p (roma.quat_product order).

    With q fixed (a Gaussian's rest orientation) the product is one matrix-vector product: the
    broadcast cross product of ``roma.quat_product`` costs ~10 operators per call."""
    x, y, z, w = q.unbind(-1)
    return torch.stack(
        [
            torch.stack([w, z, -y, x], -1),
            torch.stack([-z, w, x, y], -1),
            torch.stack([y, -x, w, z], -1),
            torch.stack([-x, -y, -z, w], -1),
        ],
        -2,
    )


def quat_left_matrix(p: torch.Tensor) -> torch.Tensor:
    """p [..., 4] XYZW -> M [..., 4, 4] with p (x) q = M q for every quaternion q."""
    x, y, z, w = p.unbind(-1)
    return torch.stack(
        [
            torch.stack([w, -z, y, x], -1),
            torch.stack([z, w, -x, y], -1),
            torch.stack([-y, x, w, z], -1),
            torch.stack([-x, -y, -z, w], -1),
        ],
        -2,
    )


def blend_matrix(neighbours: torch.Tensor, weights: torch.Tensor, num_points: int) -> torch.Tensor:
    """neighbours/weights [N, knn] -> the same LBS weights as a sparse [N, K] matrix (COO, coalesced).

    Blending with it is one sparse matmul whose backward is another (W^T grad); the gather path
    materialises [B, N, knn, 16] and scatters it back in the backward, ~5x slower on a 23.5k-vertex
    mesh on CPU. Both give the same blend (``_blend`` with and without ``matrix``, tested)."""
    n, knn = neighbours.shape
    rows = torch.arange(n, device=neighbours.device).repeat_interleave(knn)
    idx = torch.stack([rows, neighbours.reshape(-1)])
    return torch.sparse_coo_tensor(idx, weights.reshape(-1), (n, num_points), check_invariants=True).coalesce()


def packed_transforms(rotvec: torch.Tensor, trans: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Per control point, what the blend averages: rotvec / trans [B, K, 3] about p [K, 3] -> [B, K, 16] = the
    rotation matrix (9, row-major), the offset (3; T_k x = R_k x + offset) and the unit quaternion (4, XYZW, w >= 0)."""
    rot = roma.rotvec_to_rotmat(rotvec)  # [B, K, 3, 3]
    off = p + trans - matvec(rot, p)  # [B, K, 3]
    q = roma.rotvec_to_unitquat(rotvec)  # [B, K, 4] XYZW
    q = torch.where(q[..., 3:4] < 0, -q, q)  # one hemisphere, so that the average is meaningful
    return torch.cat([rot.flatten(-2), off, q], -1)


def _blend(
    packed: torch.Tensor,
    neighbours: torch.Tensor,
    weights: torch.Tensor,
    matrix: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Blend per-control-point transforms per Gaussian: a sparse matmul with ``matrix`` (``blend_matrix``),
    else the reference gather over ``neighbours`` / ``weights``.

    -> (M [B, N, 3, 3] blended rotation matrices, b [B, N, 3] blended offsets, q [B, N, 4] XYZW
    blended unit quaternions), where T_k x = R_k x + (p_k + t_k - R_k p_k); ``packed`` [B, K, 16] from
    ``packed_transforms``."""
    if matrix is None:
        blended = (weights[None, :, :, None] * packed[:, neighbours]).sum(2)  # [B, N, 16]
    else:
        b, k, c = packed.shape
        blended = torch.sparse.mm(matrix, packed.transpose(0, 1).reshape(k, b * c)).reshape(-1, b, c).transpose(0, 1)
    bq = blended[..., 12:]
    return (
        blended[..., :9].unflatten(-1, (3, 3)),
        blended[..., 9:12],
        bq / bq.norm(dim=-1, keepdim=True).clamp_min(1e-12),
    )


def lbs(
    x: torch.Tensor,
    q_rest: torch.Tensor,
    p: torch.Tensor,
    rotvec: torch.Tensor,
    trans: torch.Tensor,
    neighbours: torch.Tensor,
    weights: torch.Tensor,
    matrix: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """x [N, 3] (or [B, N, 3], a rest pose per batch item), q_rest [N, 4] XYZW, p [K, 3], rotvec/trans [B, K, 3]
    (about p_k), neighbours/weights [N, knn], optional ``matrix`` = blend_matrix(neighbours, weights, K) (faster,
    same result) -> (positions [B, N, 3] = sum_k w_k T_k x, rotations [B, N, 4] XYZW).

    On the CPU (with ``matrix``: not inside a torch.compile trace) the blend and its application run in C++
    (render/splat/skinning.cpp: one pass per vertex each way, equal to ``lbs_reference`` to float rounding)."""
    packed = packed_transforms(rotvec, trans, p)
    if matrix is not None:
        from t2bs.render.splat.cpu import skin_cpu

        out = skin_cpu(packed, x, q_rest, neighbours, weights)
        if out is not None:
            return out
    return _skin_packed(packed, x, q_rest, neighbours, weights, matrix)


def lbs_reference(
    x: torch.Tensor,
    q_rest: torch.Tensor,
    p: torch.Tensor,
    rotvec: torch.Tensor,
    trans: torch.Tensor,
    neighbours: torch.Tensor,
    weights: torch.Tensor,
    matrix: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``lbs`` in torch operators (the CUDA path, a compiled step, and the C++ op's reference)."""
    return _skin_packed(packed_transforms(rotvec, trans, p), x, q_rest, neighbours, weights, matrix)


def _skin_packed(packed, x, q_rest, neighbours, weights, matrix) -> tuple[torch.Tensor, torch.Tensor]:
    """The torch blend of ``packed`` [B, K, 16] applied to x and q_rest (``lbs_reference``'s body)."""
    m, b, q = _blend(packed, neighbours, weights, matrix)
    xt = matvec(m, x) + b
    return xt, matvec(quat_right_matrix(q_rest), q)


def lbs_positions(
    x: torch.Tensor,
    p: torch.Tensor,
    rotvec: torch.Tensor,
    trans: torch.Tensor,
    neighbours: torch.Tensor,
    weights: torch.Tensor,
) -> torch.Tensor:
    """x [N, 3] rest positions, p [K, 3] control points, rotvec/trans [B, K, 3],
    neighbours/weights [N, knn] -> [B, N, 3] skinned positions."""
    m, b, _ = _blend(packed_transforms(rotvec, trans, p), neighbours, weights)
    return matvec(m, x) + b


def apply_rigid(
    x: torch.Tensor, q: torch.Tensor, rotvec: torch.Tensor, trans: torch.Tensor, centre: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """One rigid transform per batch item: x [B, N, 3], q [B, N, 4] XYZW, rotvec/trans [B, 3]
    -> rotated about ``centre`` [3] (origin by default) and translated."""
    rot = roma.rotvec_to_rotmat(rotvec)  # [B, 3, 3]
    c = torch.zeros(3, dtype=x.dtype, device=x.device) if centre is None else centre
    x2 = torch.einsum("bij,bnj->bni", rot, x - c) + c + trans[:, None, :]
    qg = quat_left_matrix(roma.rotvec_to_unitquat(rotvec))  # [B, 4, 4]
    return x2, torch.bmm(q, qg.transpose(1, 2))


def to_wxyz(q: torch.Tensor) -> torch.Tensor:
    """XYZW (roma) -> WXYZ (rasterizer contract)."""
    return torch.cat([q[..., 3:4], q[..., :3]], dim=-1)


def quat_from_normals(normals: torch.Tensor) -> torch.Tensor:
    """[N, 3] unit normals -> [N, 4] XYZW rotations taking the local z axis to each normal."""
    z = torch.zeros_like(normals)
    z[:, 2] = 1.0
    axis = torch.cross(z, normals, dim=-1)
    s = axis.norm(dim=-1, keepdim=True)
    c = (normals * z).sum(-1, keepdim=True)
    angle = torch.atan2(s, c)
    # Normal opposite to z: any perpendicular axis works.
    axis = torch.where(s > 1e-8, axis / s.clamp_min(1e-12), torch.tensor([1.0, 0.0, 0.0], dtype=normals.dtype))
    return roma.rotvec_to_unitquat(axis * angle)
