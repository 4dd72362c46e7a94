"""Static Gaussians of the character (paper §3.2): one per mesh vertex, so the deformed
Gaussians ARE the deformed vertices.

Positions = vertices, colours = the texture at each vertex, opacity 1. Each Gaussian starts as
a flat disk in the vertex's tangent plane whose radius follows the local edge length; scale,
orientation and colour are then fitted (Adam) so that the splat render matches renders of the
static mesh from the grid's cameras (the colour fit bakes the renderer's shading in; the
RefineMLP absorbs what differs per view/time). Positions stay fixed: they are the mesh.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch

from t2bs.geometry.camera import Camera
from t2bs.geometry.mesh import (
    Mesh,
    face_area_normals,
    incident_edge_lengths,
    mesh_edges,
    vertex_normals,
    weld_index,
)
from t2bs.recon.lbs import quat_from_normals, to_wxyz
from t2bs.render.splat.reference import LOWPASS

_warned_backend = False


@dataclass
class StaticGaussians:
    means: np.ndarray  # [N, 3] float32 = mesh vertices
    quats: np.ndarray  # [N, 4] float32 XYZW (roma convention)
    log_scales: np.ndarray  # [N, 3] float32 log standard deviations (tangent, tangent, normal)
    colors: np.ndarray  # [N, 3] float32 in [0, 1]
    faces: np.ndarray | None = None  # [F, 3] int64 triangles carrying one face Gaussian each (None = vertices only)
    face_colors: np.ndarray | None = None  # [F, 3] float32 colour of each face Gaussian
    face_log_scale: np.ndarray | None = None  # [F] float32 log multiplier of each face Gaussian's size
    fit_loss: float = float("nan")  # final L1 of the static fit (0..1 image units)
    offsets: np.ndarray | None = None  # [N, 3] float32 rest-pose shift of each vertex Gaussian off its vertex (tangent)
    ring: np.ndarray | None = None  # [N, K] int64 neighbours of each vertex (itself where it has fewer than K)
    ring_weights: np.ndarray | None = (
        None  # [N, K] float32 offsets = sum_k w_k (v[ring_k] - v): they follow the surface
    )

    def tensors(self, device="cpu") -> dict:
        f = None if self.faces is None else torch.as_tensor(self.faces, dtype=torch.int64, device=device)

        def opt(a):
            return None if a is None else torch.as_tensor(a, dtype=torch.float32, device=device)

        return {"faces": f, "face_colors": opt(self.face_colors), "face_log_scale": opt(self.face_log_scale)}


def frame_quat(u: torch.Tensor, w: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """Orthonormal right-handed axes u, w, n [..., 3] -> the XYZW unit quaternion of the rotation whose columns
    they are (local x, y, z -> u, w, n). The same rotation as ``roma.rotmat_to_unitquat`` (possibly -q: the
    same rotation), without stacking the matrix or gathering by argmax over a strided tensor, which made the
    face Gaussians the costliest part of the deformation on CPU. Shepperd's method: of the four formulas
    the one with the largest square root is used (chosen elementwise with ``where``); every square root's
    argument is clamped, so the formulas not chosen give no NaN to the backward pass."""
    m00, m10, m20 = u.unbind(-1)
    m01, m11, m21 = w.unbind(-1)
    m02, m12, m22 = n.unbind(-1)
    trace = m00 + m11 + m22
    # Per formula: the square root's argument (16 x the big component squared / 4) and the X, Y, Z, W numerators
    # (None: the big component itself, s / 4).
    formulas = (
        (1.0 + trace, (m21 - m12, m02 - m20, m10 - m01, None)),
        (1.0 + 2.0 * m00 - trace, (None, m01 + m10, m02 + m20, m21 - m12)),
        (1.0 + 2.0 * m11 - trace, (m01 + m10, None, m12 + m21, m02 - m20)),
        (1.0 + 2.0 * m22 - trace, (m02 + m20, m12 + m21, None, m10 - m01)),
    )
    cands = []
    for arg, numerators in formulas:
        s = 2.0 * arg.clamp_min(1e-8).sqrt()  # 4 x the big component
        cands.append(torch.stack([0.25 * s if x is None else x / s for x in numerators], -1))
    best = torch.stack([trace, m00, m11, m22], -1).argmax(-1, keepdim=True)  # contiguous: cheap
    q = torch.where(best == 0, cands[0], torch.where(best == 1, cands[1], torch.where(best == 2, cands[2], cands[3])))
    return q / q.norm(dim=-1, keepdim=True)


def face_gaussians(
    x: torch.Tensor, faces: torch.Tensor, face_log_scale: torch.Tensor, flatness: float = 0.25
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One Gaussian per triangle (``face_gaussians_reference`` says how), in C++ on the CPU (render/splat/faces.cpp:
    one pass per triangle each way instead of ~45 tensor operators; equal to float rounding, the quaternion possibly
    negated at a tie of Shepperd's formulas: the same rotation), the reference elsewhere (CUDA, a compiled step)."""
    from t2bs.render.splat.cpu import face_gaussians_cpu

    out = face_gaussians_cpu(x, faces, face_log_scale, flatness)
    return face_gaussians_reference(x, faces, face_log_scale, flatness) if out is None else out


def face_gaussians_reference(
    x: torch.Tensor, faces: torch.Tensor, face_log_scale: torch.Tensor, flatness: float = 0.25
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One Gaussian per triangle, built from the (deformed) vertex positions each time.

    x [B, N, 3], faces [F, 3], face_log_scale [F] -> means [B, F, 3] (centroids), quats [B, F, 4]
    XYZW (axes: first edge, in-plane normal to it, face normal) and scales [B, F, 3] (the spread of
    the triangle's corners along the two in-plane axes, x exp(face_log_scale); normal axis =
    flatness x the smaller). They stretch and turn with their triangle, so a face that opens
    up (a mouth, an eyelid) stays covered: one Gaussian per vertex alone leaves it empty.
    """
    tri = x[:, faces]  # [B, F, 3, 3]
    c = tri.mean(2)
    e1 = tri[:, :, 1] - tri[:, :, 0]
    e2 = tri[:, :, 2] - tri[:, :, 0]
    n = torch.cross(e1, e2, dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    u = e1 / e1.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w = torch.cross(n, u, dim=-1)
    d = tri - c[:, :, None]  # [B, F, 3, 3]
    su = ((d * u[:, :, None]).sum(-1) ** 2).mean(-1).clamp_min(1e-12).sqrt()  # [B, F]
    sw = ((d * w[:, :, None]).sum(-1) ** 2).mean(-1).clamp_min(1e-12).sqrt()
    k = face_log_scale.exp()[None]
    scales = torch.stack([su * k, sw * k, flatness * torch.minimum(su, sw) * k], -1).clamp_min(1e-6)
    return c, frame_quat(u, w, n), scales


def camera_tensors(cameras: list[Camera], device="cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """-> viewmats [C, 4, 4], Ks [C, 3, 3] float32."""
    vm = torch.tensor(np.stack([c.world_to_camera for c in cameras]), dtype=torch.float32, device=device)
    ks = torch.tensor(np.stack([c.K for c in cameras]), dtype=torch.float32, device=device)
    return vm, ks


def render(
    means,
    quats_xyzw,
    scales,
    colors,
    viewmats,
    ks,
    width: int,
    height: int,
    background=(1.0, 1.0, 1.0),
    backend: str = "auto",
    lowpass: float = LOWPASS,
) -> dict:
    """Splat render with the Gaussians in this package's convention (XYZW quats, opacity 1).

    Shapes: [C, N, ...] or [N, ...] per tensor; returns rgb [C, H, W, 3], alpha [C, H, W, 1]. ``lowpass``: px^2
    added to each splat's 2D covariance (``ModelConfig.splat_lowpass``; the rasterizer's default is 3DGS's 0.3).
    Falls back to the reference rasterizer (once warned) when the fast CPU kernel is missing.
    """
    from t2bs.render.splat import rasterize_gaussians

    global _warned_backend
    n = means.shape[-2]
    opac = torch.ones(n, dtype=means.dtype, device=means.device)
    bg = torch.tensor(background, dtype=means.dtype, device=means.device)
    args = (means, to_wxyz(quats_xyzw), scales, opac, colors, viewmats, ks, width, height)
    try:
        return rasterize_gaussians(*args, background=bg, backend=backend, lowpass=lowpass)
    except ImportError as exc:  # the fast kernel's module is not there (yet): same rules, slower
        if not _warned_backend:
            warnings.warn(
                f"splat backend {backend!r} unavailable ({exc}); using the reference rasterizer", stacklevel=2
            )
            _warned_backend = True
        return rasterize_gaussians(*args, background=bg, backend="reference", lowpass=lowpass)


def with_faces(means, quats, scales, colors, faces, face_colors, face_log_scale, flatness: float = 0.25):
    """Append the face Gaussians (if any) to per-vertex ones; every tensor [B, N, ...] -> [B, N + F, ...].

    ``face_colors`` is [F, 3] or [B, F, 3]."""
    if faces is None:
        return means, quats, scales, colors
    fm, fq, fs = face_gaussians(means, faces, face_log_scale, flatness)
    fc = face_colors if face_colors.dim() == 3 else face_colors[None].expand(means.shape[0], -1, -1)
    return (
        torch.cat([means, fm], 1),
        torch.cat([quats, fq], 1),
        torch.cat([scales, fs], 1),
        torch.cat([colors, fc], 1),
    )


def largest_faces(vertices: np.ndarray, faces: np.ndarray, limit: int, also: np.ndarray | None = None) -> np.ndarray:
    """The ``limit`` largest-area triangles of ``faces`` [F, 3] (all of them when F <= limit or
    limit <= 0) and those ``also`` [F] bool marks, in their original order -> [K, 3].

    Why the largest: a small triangle's corners sit within each other's vertex Gaussians (tangent
    std = half the mean edge), so its face Gaussian adds little coverage; a large one leaves a gap
    between its corners that only its face Gaussian fills. ``also``: small triangles that an expression
    stretches (a lid over the eye), where the corners' rest-sized Gaussians part and the eye shows through."""
    if limit <= 0 or len(faces) <= limit:
        return faces
    area = np.linalg.norm(face_area_normals(vertices, faces), axis=1)  # twice the area: the order is the same
    keep = np.zeros(len(faces), dtype=bool)
    keep[np.argsort(-area, kind="stable")[:limit]] = True
    if also is not None:
        keep |= also
    return faces[keep]


def init_static_gaussians(
    mesh: Mesh,
    flatness: float = 0.25,
    with_face_gaussians: bool = True,
    max_face_gaussians: int = 0,
    keep_faces: np.ndarray | None = None,
) -> StaticGaussians:
    """One flat Gaussian per vertex: tangent std = 0.5 x mean incident edge length; optionally one
    per triangle, on at most ``max_face_gaussians`` of the largest ones (0 = every triangle) and on
    the triangles ``keep_faces`` [F] bool marks."""
    v = mesh.vertices.astype(np.float64)
    f = mesh.faces.astype(np.int64)
    mean_edge, count, length = incident_edge_lengths(v, f)
    fallback = float(np.median(length)) if len(length) else 0.01
    mean_edge = np.where(count > 0, mean_edge, fallback)
    mean_edge = np.clip(mean_edge, 0.2 * fallback, 5.0 * fallback)
    s = 0.5 * mean_edge
    log_scales = np.log(np.stack([s, s, flatness * s], 1))
    normals = torch.as_tensor(mesh.vertex_normals(), dtype=torch.float32)
    quats = quat_from_normals(normals).numpy()
    colors = mesh.vertex_rgb().astype(np.float32)
    faces = face_colors = face_log_scale = None
    if with_face_gaussians:
        faces = largest_faces(v, f, max_face_gaussians, keep_faces)
        if mesh.texture is not None and mesh.uv is not None:
            from t2bs.geometry.mesh import sample_texture

            face_colors = sample_texture(mesh.texture, mesh.uv[faces].mean(1))
        else:
            face_colors = colors[faces].mean(1)
        face_log_scale = np.zeros(len(faces), np.float32)
    return StaticGaussians(
        mesh.vertices.astype(np.float32),
        quats.astype(np.float32),
        log_scales.astype(np.float32),
        colors,
        faces,
        face_colors.astype(np.float32) if face_colors is not None else None,
        face_log_scale,
    )


# The static fit's offsets (``splat_offsets``): learning rate (world units of the canonical frame, diagonal 1.2) and
# the weight of their squared length in the loss, which keeps the Gaussians that no view sees from drifting
# (Adam moves a parameter by ~lr per step whatever the size of its gradient). Lid scene, a perfect one-angle lid
# model fitted to the mesh renders: without offsets the angle's optimum is 0.73 of the truth, with them 0.84; with
# every Gaussian free (not only those at open edges) weight 1 gives 0.91, 0 gives 0.95 with the unseen Gaussians a
# full edge off their vertices, 10 gives 0.82. docs/VCDGS_NOTES.md.
OFFSET_LR = 0.002
OFFSET_WEIGHT = 1.0


RING = 8  # neighbours an offset is spanned by


def vertex_rings(faces: np.ndarray, num_vertices: int, k: int = RING) -> np.ndarray:
    """[N, k] int64: up to k edge neighbours of each vertex, padded with the vertex itself."""
    e = mesh_edges(faces)
    e = np.unique(np.concatenate([e, e[:, ::-1]]), axis=0)  # both directions, sorted by the first vertex
    ring = np.repeat(np.arange(num_vertices, dtype=np.int64)[:, None], k, 1)
    start = np.searchsorted(e[:, 0], np.arange(num_vertices))
    rank = np.arange(len(e)) - start[e[:, 0]]
    keep = rank < k
    ring[e[keep, 0], rank[keep]] = e[keep, 1]
    return ring


def near_open_edges(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[N] float32: 1 on the vertices of an edge that only one triangle uses (a hole's rim, a part's border) and on
    their neighbours (the second row spreads past a jagged border too; lid scene: lid gain 0.70 with the rim alone,
    0.74 with the neighbours, the same with two rows), else 0. Counted on welded vertices (``weld_index``): where an
    exporter split the surface at a UV seam, the seam is not a border."""
    node, first = weld_index(vertices)
    f = node[np.asarray(faces, np.int64)]
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), 1)
    # the welded edges (as ``welded_edges``) with how many triangles use each
    e, count = np.unique(e[e[:, 0] != e[:, 1]], axis=0, return_counts=True)
    rim = np.zeros(len(first), bool)
    rim[e[count == 1].ravel()] = True
    out = rim.copy()
    out[e[:, 0][rim[e[:, 1]]]] = True
    out[e[:, 1][rim[e[:, 0]]]] = True
    return out[node].astype(np.float32)


def ring_weights(vertices: np.ndarray, ring: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """[N, K] minimum-norm weights w with sum_k w_k (v[ring_k] - v) = offsets [N, 3] (least squares where the ring
    does not span the offset). Moving the splat as that combination of edges keeps it on the surface as it deforms
    (turns, stretches) and lets nothing move it but the vertices themselves."""
    v = np.asarray(vertices, np.float64)
    edges = np.transpose(v[ring] - v[:, None], (0, 2, 1))  # [N, 3, K]
    return (np.linalg.pinv(edges, rcond=1e-6) @ np.asarray(offsets, np.float64)[..., None])[..., 0].astype(np.float32)


def ring_shift(x: torch.Tensor, ring: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """x [B, N, 3] vertex positions, ring / weights [N, K] (``vertex_rings``, ``ring_weights``) -> [B, N, 3] each
    vertex Gaussian's shift off its vertex, sum_k w_k (x[ring_k] - x): the gather (the reference of
    ``ring_shift_sparse``; the compiled and the CUDA step use it)."""
    return ((x[:, ring] - x[:, :, None]) * weights[None, :, :, None]).sum(2)


def ring_shift_matrix(ring: torch.Tensor, weights: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """ring / weights [N, K] -> (crow, col, values) of the sparse [N, N] matrix S with S x = ``ring_shift``(x), then
    the same three of S^T (its backward): CSR parts as plain tensors, so that a model holding them as buffers moves
    between devices and deep-copies (a CSR tensor does not). Rows of vertices that do not shift hold nothing."""
    n, k = ring.shape
    ids = torch.arange(n, device=ring.device)
    w = torch.where(ring == ids[:, None], 0.0, weights)  # a ring's padding (the vertex itself): no edge
    idx = torch.cat([torch.stack([ids.repeat_interleave(k), ring.reshape(-1)]), ids.repeat(2, 1)], 1)
    val = torch.cat([w.reshape(-1), -w.sum(1)])
    keep = val != 0
    return sparse_parts(idx[:, keep], val[keep], (n, n))


def corner_matrix_t(faces: torch.Tensor, n: int) -> tuple[torch.Tensor, ...]:
    """faces [F, 3] of n vertices -> the CSR parts (crow, col, values) of the [n, F] matrix with a 1 where a vertex is
    a face's corner: ``corner_mean``'s backward."""
    f = len(faces)
    idx = torch.stack([torch.arange(f, device=faces.device).repeat_interleave(3), faces.reshape(-1)])
    return sparse_parts(idx, torch.ones(3 * f, device=faces.device), (f, n))[3:]


class _CornerMean(torch.autograd.Function):
    """x [B, N, C] -> [B, F, C] each face's corners' mean: the gather forward, one sparse matmul backward."""

    @staticmethod
    def forward(ctx, x, faces, parts):
        ctx.parts, ctx.n, ctx.f = parts, x.shape[1], len(faces)
        return x[:, faces].mean(2)

    @staticmethod
    def backward(ctx, grad):
        b, c = grad.shape[0], grad.shape[2]
        m_t = torch.sparse_csr_tensor(*ctx.parts, (ctx.n, ctx.f), check_invariants=False)
        flat = (grad / 3).transpose(0, 1).reshape(ctx.f, b * c)
        return (m_t @ flat).reshape(ctx.n, b, c).transpose(0, 1), None, None


def corner_mean(x: torch.Tensor, faces: torch.Tensor, parts: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """``x[:, faces].mean(2)`` (x [B, N, C], faces [F, 3]) with its backward as one sparse matmul by the corner matrix
    (``parts`` from ``corner_matrix_t``): the same bits both ways (the CSR rows sum a vertex's faces in the order
    deterministic mode's sorted scatter does), without that sort (the demo fox: ~2 ms of a step)."""
    return _CornerMean.apply(x, faces, parts)


def sparse_parts(idx: torch.Tensor, val: torch.Tensor, shape: tuple[int, int]) -> tuple[torch.Tensor, ...]:
    """COO entries (idx [2, E], val [E]) of a [R, C] matrix A -> (crow, col, values) of A, then of A^T, in CSR: plain
    tensors a module can keep as buffers (a CSR tensor neither deep-copies nor moves with the module)."""
    s = torch.sparse_coo_tensor(idx, val, shape, check_invariants=True).coalesce()
    parts = []
    with warnings.catch_warnings():  # torch's once-a-process note that CSR support is in beta, not the user's concern
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        for m in (s, s.t().coalesce()):
            csr = m.to_sparse_csr()
            parts += [csr.crow_indices(), csr.col_indices(), csr.values()]
    return tuple(parts)


class _ConstantSparseMM(torch.autograd.Function):
    """S @ x for a constant CSR S [N, N] and x [N, C], its backward S^T @ grad (the transpose given, built once)."""

    @staticmethod
    def forward(ctx, x, s, s_t):
        ctx.s_t = s_t
        return s @ x

    @staticmethod
    def backward(ctx, grad):
        return ctx.s_t @ grad, None, None


def ring_shift_sparse(x: torch.Tensor, parts: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """``ring_shift`` as one sparse matmul each way (``parts`` from ``ring_shift_matrix``), equal to it to float
    rounding. Why: the gather materialises [B, N, K, 3] and its backward scatters it back, which torch's deterministic
    mode (on for every CPU reconstruction) sorts: on the demo fox (23.5k vertices, K = 8) 48 ms of a training step
    forward and backward against 7 ms, and 117 ms against 7 for 15 items of an expression pick (2-core CPU)."""
    b, n = x.shape[:2]
    s, s_t = (torch.sparse_csr_tensor(*parts[i : i + 3], (n, n), check_invariants=False) for i in (0, 3))
    flat = x.transpose(0, 1).reshape(n, b * 3)  # [N, B * 3]: every item's coordinates as columns
    return _ConstantSparseMM.apply(flat, s, s_t).reshape(n, b, 3).transpose(0, 1)


def tangent_bases(normals: torch.Tensor) -> torch.Tensor:
    """[N, 3] unit normals -> [N, 3, 2] two unit tangents per vertex (columns), orthogonal to the normal."""
    x_axis = torch.tensor([1.0, 0.0, 0.0], dtype=normals.dtype, device=normals.device).expand_as(normals)
    y_axis = torch.tensor([0.0, 1.0, 0.0], dtype=normals.dtype, device=normals.device).expand_as(normals)
    ref = torch.where(normals[:, :1].abs() < 0.9, x_axis, y_axis)
    t1 = torch.nn.functional.normalize(torch.cross(normals, ref, dim=-1), dim=-1)
    return torch.stack([t1, torch.cross(normals, t1, dim=-1)], -1)


def fit_static_gaussians(
    gs: StaticGaussians,
    targets: np.ndarray,
    masks: np.ndarray | None,
    cameras: list[Camera],
    iters: int = 150,
    lr: float = 0.01,
    views_per_iter: int = 3,
    seed: int = 0,
    device: str = "cpu",
    progress: bool = False,
    offset_faces: np.ndarray | None = None,
    lowpass: float = LOWPASS,
) -> StaticGaussians:
    """Fit scales and orientations to ``targets`` [C, H, W, 3] float 0..1 (renders of the
    static mesh from ``cameras``), ``masks`` [C, H, W] float or None. The vertices stay fixed.

    ``offset_faces`` [F, 3] (the mesh's triangles): also fit ``offsets``, a shift of each vertex Gaussian along the
    surface. A Gaussian centred on a part's edge (a lid's margin, a lip's) spreads past it by about its own size
    plus the rasterizer's low-pass, so the splat part looks larger than the mesh part; at rest the excess
    often lies over skin of the same colour and costs nothing, but once the lid slides over the eye it covers too
    much, and the photometric optimum of its motion falls short (to 0.73 of a lid's turn). Shifted inwards, the
    edge Gaussians end where the part ends. ``lowpass``: the rasterizer's px^2 (``render``), as the model will be
    drawn."""
    if iters <= 0:
        return gs
    from tqdm import tqdm

    gen = torch.Generator().manual_seed(seed)
    dev = torch.device(device)
    means = torch.as_tensor(gs.means, device=dev)
    log_s = torch.nn.Parameter(torch.as_tensor(gs.log_scales, device=dev).clone())
    quats = torch.nn.Parameter(torch.as_tensor(gs.quats, device=dev).clone())
    # Colours stay the texture's (the paper fits scale and orientation only): fitting them would paint
    # hidden Gaussians (the mouth interior) with the colour of what covers them.
    col_logit = torch.logit(torch.as_tensor(gs.colors, device=dev).clamp(0.02, 0.98))
    params = [{"params": [log_s, quats], "lr": lr}]
    bases = off = None
    if offset_faces is not None:
        normals = vertex_normals(gs.means, offset_faces)
        bases = tangent_bases(torch.as_tensor(normals, dtype=torch.float32, device=dev))  # [N, 3, 2]
        # Only the Gaussians at an open edge (a lid's margin, a lip's, the rim of a part) move: elsewhere the
        # neighbours' Gaussians overlap on every side, and a free shift only trades places with them (every
        # Gaussian free: lid gain 0.40, the lid's Gaussians painting the head's places as it moves).
        bases = bases * torch.as_tensor(near_open_edges(gs.means, offset_faces), device=dev)[:, None, None]
        off = torch.nn.Parameter(torch.zeros(len(means), 2, device=dev))
        params += [{"params": [off], "lr": OFFSET_LR}]
    faces = None
    if gs.faces is not None:
        faces = torch.as_tensor(gs.faces, dtype=torch.int64, device=dev)
        fcol_logit = torch.logit(torch.as_tensor(gs.face_colors, device=dev).clamp(0.02, 0.98))
        flog = torch.nn.Parameter(torch.as_tensor(gs.face_log_scale, device=dev).clone())
        params += [{"params": [flog], "lr": lr}]
    opt = torch.optim.Adam(params)
    tgt = torch.as_tensor(targets, dtype=torch.float32, device=dev)
    msk = None if masks is None else torch.as_tensor(masks, dtype=torch.float32, device=dev)
    vm, ks = camera_tensors(cameras, dev)
    h, w = tgt.shape[1:3]
    c = len(cameras)
    last = float("nan")
    bar = tqdm(range(iters), desc="static Gaussians", leave=False, disable=not progress)
    for _ in bar:
        idx = torch.randperm(c, generator=gen)[: min(views_per_iter, c)].to(dev)
        q = quats / quats.norm(dim=-1, keepdim=True)
        centres = means if off is None else means + (bases @ off[..., None])[..., 0]
        g = (centres[None], q[None], log_s.exp()[None], torch.sigmoid(col_logit)[None])
        if faces is not None:  # the face Gaussians span the shifted centres: an edge triangle shrinks inwards too
            g = with_faces(*g, faces, torch.sigmoid(fcol_logit), flog)
        out = render(g[0][0], g[1][0], g[2][0], g[3][0], vm[idx], ks[idx], w, h, lowpass=lowpass)
        loss = (out["rgb"] - tgt[idx]).abs().mean()
        if msk is not None:
            loss = loss + 0.5 * (out["alpha"][..., 0] - msk[idx]).abs().mean()
        if off is not None:
            loss = loss + OFFSET_WEIGHT * (off**2).sum(-1).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        with torch.no_grad():  # keep splats from growing into blobs or vanishing
            log_s.clamp_(min=float(np.log(1e-4)), max=float(np.log(0.05)))
            if faces is not None:
                flog.clamp_(-2.0, 1.0)
        last = float(loss.detach())
        bar.set_postfix(loss=f"{last:.4f}")
    with torch.no_grad():
        q = quats / quats.norm(dim=-1, keepdim=True)
        offsets = ring = None
        if off is not None:
            offsets = (bases @ off[..., None])[..., 0].cpu().numpy().astype(np.float32)
            ring = vertex_rings(offset_faces, len(gs.means))
        fc = fl = None
        if faces is not None:
            fc = torch.sigmoid(fcol_logit).cpu().numpy().astype(np.float32)
            fl = flog.detach().clamp(-2.0, 1.0).cpu().numpy().astype(np.float32)
        return StaticGaussians(
            gs.means,
            q.cpu().numpy().astype(np.float32),
            log_s.cpu().numpy().astype(np.float32),
            torch.sigmoid(col_logit).cpu().numpy().astype(np.float32),
            gs.faces,
            fc,
            fl,
            last,
            offsets,
            ring,
            None if offsets is None else ring_weights(gs.means, ring, offsets),
        )
