"""The VCDGS deformation model (paper §3.2): DeformMLP, global SE(3), RefineMLP.

T~_k(v, t) = T_global(v, t) . DeformMLP(p_k, v, t), positions and rotations blended by LBS.

View conditioning that cannot corrupt the canonical view: both the global transform and the
DeformMLP are a *shared* part (depends on t only) plus a *view residual* (depends on v and t)
that is multiplied by 0 at the canonical view. Training on view v > 0 can bend the geometry to
match that view's distortions through the residual, while T(v = canonical, t) is exactly the
shared part: the output the paper extracts ("we use T_{0,t} to construct the final
blendshape"). The residual is also L2-regularised (vcdgs.py) so that it explains only what the
shared deformation cannot.

Ablations (config.method): ``no_view`` drops every view residual (global per t, DeformMLP(p, t));
``no_lbs`` replaces the control points by a per-Gaussian deformation MLP(x, v, t) as in 4D-GS;
``no_global`` drops T_global and its warm-up; ``no_refine`` drops RefineMLP.
"""

from __future__ import annotations

import math

import roma
import torch
from torch import nn

from t2bs.recon.gaussians import (
    corner_matrix_t,
    corner_mean,
    ring_shift,
    ring_shift_matrix,
    ring_shift_sparse,
    with_faces,
)
from t2bs.recon.lbs import apply_rigid, blend_matrix, lbs


def fourier(x: torch.Tensor, freqs: int) -> torch.Tensor:
    """[..., D] -> [..., D * (1 + 2 * freqs)]: x, sin(2^l pi x), cos(2^l pi x)."""
    if freqs <= 0:
        return x
    scales = (2.0 ** torch.arange(freqs, dtype=x.dtype, device=x.device)) * math.pi  # [L]
    xs = x[..., None] * scales  # [..., D, L]
    return torch.cat([x, torch.sin(xs).flatten(-2), torch.cos(xs).flatten(-2)], dim=-1)


def mlp(d_in: int, d_out: int, hidden: int, depth: int) -> nn.Sequential:
    """ReLU MLP whose last layer starts at zero: the model starts at the rest pose / no offset."""
    layers: list[nn.Module] = []
    d = d_in
    for _ in range(depth):
        # Not in place: a Linear on [B, P, H] returns a view of its [B * P, H] matmul, and an in-place ReLU on a view
        # makes autograd copy the whole gradient through CopySlices (~10 ms of the fox's joint step; session 50).
        layers += [nn.Linear(d, hidden), nn.ReLU()]
        d = hidden
    last = nn.Linear(d, d_out)
    nn.init.zeros_(last.weight)
    nn.init.zeros_(last.bias)
    layers.append(last)
    return nn.Sequential(*layers)


class CondMLP(nn.Module):
    """MLP over (point features [P, Dp], condition features [B, Dc]) -> [B, P, out].

    The first layer is split, W [f_p; f_c] = W_p f_p + W_c f_c, so the point part is computed
    once per step rather than once per (view, time) pair: the same network as an MLP on the
    concatenated input, at a fraction of the cost on CPU. Last layer zero-initialised.
    """

    def __init__(self, d_point: int, d_cond: int, d_out: int, hidden: int, depth: int):
        super().__init__()
        self.point_in = nn.Linear(d_point, hidden)
        self.cond_in = nn.Linear(d_cond, hidden, bias=False)
        self.body = mlp(hidden, d_out, hidden, max(depth - 1, 0))

    def forward(self, point_feat: torch.Tensor, cond_feat: torch.Tensor) -> torch.Tensor:
        h = torch.relu(self.point_in(point_feat)[None] + self.cond_in(cond_feat)[:, None])  # [B, P, H]
        return self.body(h)


class DeformMLP(nn.Module):
    """(p_k, v, t) -> rotation vector [3] + translation [3] per point.

    Used on control points (LBS) or, for the ``no_lbs`` ablation, on every Gaussian.
    ``forward`` returns the shared part and the view residual separately (residual = 0 at the
    canonical view or when view conditioning is off).
    """

    def __init__(
        self,
        hidden: int,
        depth: int,
        pos_freqs: int,
        time_freqs: int,
        view_freqs: int,
        view_conditioned: bool,
        translation_scale: float = 0.1,
    ):
        super().__init__()
        self.pos_freqs, self.time_freqs, self.view_freqs = pos_freqs, time_freqs, view_freqs
        self.view_conditioned = view_conditioned
        self.residual_static = False  # set by VCDGSModel from config.model.view_residual_static
        self.translation_scale = translation_scale  # outputs are O(1); scene motion is O(0.1)
        d_p, d_t, d_v = 3 * (1 + 2 * pos_freqs), 1 + 2 * time_freqs, 1 + 2 * view_freqs
        self.shared = CondMLP(d_p, d_t, 6, hidden, depth)
        self.residual = CondMLP(d_p, d_t + d_v, 6, hidden // 2, max(depth - 1, 1)) if view_conditioned else None
        self.register_buffer("scale", torch.tensor([1.0, 1.0, 1.0] + [translation_scale] * 3))

    def forward(self, pe: torch.Tensor, v: torch.Tensor, t: torch.Tensor, view_on: torch.Tensor | None):
        """pe [P, Dp] = fourier(points, pos_freqs); v, t [B] normalised to [-1, 1] and [0, 1];
        view_on [B] 0/1, or None for no view residual -> (shared [B, P, 6], residual [B, P, 6]) as
        (rotvec, translation). No branch on tensor values (a batch of canonical views still runs the
        residual network, times 0): nothing waits for the device, and a compiled step is one graph."""
        te = fourier(t[:, None], self.time_freqs)  # [B, Dt]
        # shared(p, t) - shared(p, 0): frame 0 is the static mesh (the grid's first column), exactly the rest pose
        both = self.shared(pe, torch.cat([te, fourier(t.new_zeros(1, 1), self.time_freqs)]))
        shared = (both[:-1] - both[-1:]) * self.scale
        if self.residual is None or view_on is None:
            return shared, torch.zeros_like(shared)
        ve = fourier(v[:, None], self.view_freqs)
        if self.residual_static:  # a per-view distortion, the same at every frame
            te = fourier(torch.zeros_like(t)[:, None], self.time_freqs)
        res = self.residual(pe, torch.cat([te, ve], -1)) * self.scale * view_on[:, None, None]
        return shared, res


def dct_basis(frames: int) -> torch.Tensor:
    """[T, T] orthonormal DCT-II basis over frames (row t: the basis functions' values at frame t)."""
    k = torch.arange(frames, dtype=torch.float32)
    basis = torch.cos(math.pi * (k[:, None] + 0.5) * k[None, :] / max(frames, 1))
    return basis * torch.where(k == 0, 1.0, math.sqrt(2.0)) / math.sqrt(max(frames, 1))


def frames_from_dct(basis: torch.Tensor, coef: torch.Tensor) -> torch.Tensor:
    """basis [T, T] (``dct_basis``), coef [T, C] -> [T, C] per-frame values, frame 0 subtracted: the first column of a
    grid is the static mesh, so whatever the coefficients say, frame 0 is the rest pose."""
    values = basis @ coef
    return values - values[:1]


class GlobalSE3(nn.Module):
    """Global rigid motion per (v, t): a shared part per t plus a view residual per (v, t).

    Both are coefficients on a cosine (DCT-II) basis over the frames rather than one free row
    per frame: with T basis functions this represents any per-frame motion, but every step
    updates every frame coherently (a table row only moves when its frame is sampled, and
    Adam's momentum keeps pushing unsampled rows, which makes the warm-up noisy).
    """

    def __init__(self, views: int, frames: int, view_conditioned: bool):
        super().__init__()
        self.register_buffer("basis", dct_basis(frames))  # [T, T] DCT-II, orthonormal
        self.shared = nn.Parameter(torch.zeros(frames, 6))  # [T coefficients, rotvec 3 + translation 3]
        self.residual = nn.Parameter(torch.zeros(views, frames, 6)) if view_conditioned else None
        self.residual_static = False  # set by VCDGSModel from config.model.view_residual_static

    def shared_table(self) -> torch.Tensor:
        """[T, 6] shared motion of every frame."""
        return frames_from_dct(self.basis, self.shared)  # frame 0's shared motion is the identity

    def forward(self, v_idx: torch.Tensor, t_idx: torch.Tensor, view_on: torch.Tensor):
        """-> (shared [B, 6], residual [B, 6])."""
        shared = self.shared_table()[t_idx]
        if self.residual is None:
            return shared, torch.zeros_like(shared)
        if self.residual_static:  # only the constant (DCT 0) coefficient: a per-view offset fixed over time
            res = self.basis[t_idx][:, :1] * self.residual[v_idx][:, 0]
        else:
            res = torch.einsum("bk,bkc->bc", self.basis[t_idx], self.residual[v_idx])
        return shared, res * view_on[:, None]


class RefineMLP(nn.Module):
    """(x, v, t) -> colour offset [3], log-scale offset [3], rotation-vector offset [3] (training only).

    x is the Gaussian's rest position (its identity); the offsets are per (view, time).
    """

    def __init__(self, hidden: int, depth: int, pos_freqs: int, time_freqs: int, view_freqs: int):
        super().__init__()
        self.pos_freqs, self.time_freqs, self.view_freqs = pos_freqs, time_freqs, view_freqs
        d_p, d_c = 3 * (1 + 2 * pos_freqs), 1 + 2 * time_freqs + 1 + 2 * view_freqs
        self.net = CondMLP(d_p, d_c, 9, hidden, depth)

    def forward(self, pe: torch.Tensor, v: torch.Tensor, t: torch.Tensor):
        """pe [N, Dp] = fourier(rest positions, pos_freqs); v, t [B] -> (dc, dlogs, drot), each [B, N, 3]."""
        cond = torch.cat([fourier(t[:, None], self.time_freqs), fourier(v[:, None], self.view_freqs)], -1)
        out = self.net(pe, cond)
        # Colour offsets may be large (lighting); scale/rotation offsets stay small. One tanh over all nine channels:
        # on a strided slice torch's CPU tanh takes the scalar path, ~2x slower (the values are the same bits).
        squashed = torch.tanh(out)
        return out[..., :3], 0.3 * squashed[..., 3:6], 0.2 * squashed[..., 6:9]


class VCDGSModel(nn.Module):
    """Static Gaussians + control points + the deformation networks; ``forward`` gives the
    Gaussians of a batch of (view, time) pairs."""

    def __init__(
        self,
        means,
        quats,
        log_scales,
        colors,
        cp_positions,
        neighbours,
        weights,
        views: int,
        frames: int,
        canonical_view: int,
        cfg,
        faces=None,
        face_colors=None,
        face_log_scale=None,
        ring=None,
        ring_weights=None,
        expression_basis=None,
    ):
        super().__init__()
        f32 = torch.float32
        # Face Gaussians (gaussians.face_gaussians): rebuilt from the deformed vertices, rendered only.
        self.register_buffer("faces", None if faces is None else torch.as_tensor(faces, dtype=torch.int64))  # [F, 3]
        self.register_buffer(
            "face_colors", None if face_colors is None else torch.as_tensor(face_colors, dtype=f32)
        )  # [F, 3]
        self.register_buffer(
            "face_log_scale", None if face_log_scale is None else torch.as_tensor(face_log_scale, dtype=f32)
        )  # [F]
        # Which vertices are which faces' corners, as a sparse matrix (gaussians.corner_mean's backward, the CPU path):
        # a face's colour offset is its corners' mean. Rebuilt, not saved.
        corners = () if faces is None else corner_matrix_t(self.faces, len(means))
        for i, part in enumerate(corners):
            self.register_buffer(f"corners_t_{i}", part, persistent=False)
        self.flatness = cfg.static_fit.flatness
        self.splat_lowpass = cfg.model.splat_lowpass  # px^2 every render of this model adds to a splat's footprint
        self.register_buffer("means", torch.as_tensor(means, dtype=f32))  # [N, 3]
        self.register_buffer("quats", torch.as_tensor(quats, dtype=f32))  # [N, 4] XYZW
        # Each vertex Gaussian's shift off its vertex (gaussians.fit_static_gaussians) as a fixed combination of its
        # edges: it follows the surface and nothing but the vertices moves it; ``means`` (the mesh) stays put.
        self.register_buffer("splat_ring", None if ring is None else torch.as_tensor(ring, dtype=torch.int64))  # [N, K]
        self.register_buffer(
            "splat_ring_weights", None if ring_weights is None else torch.as_tensor(ring_weights, dtype=f32)
        )  # [N, K]
        # The same shifts as a sparse matrix each way (gaussians.ring_shift_sparse, the CPU path); rebuilt, not saved.
        span = () if ring is None else ring_shift_matrix(self.splat_ring, self.splat_ring_weights)
        for i, part in enumerate(span):
            self.register_buffer(f"splat_span_{i}", part, persistent=False)
        self.register_buffer("log_scales", torch.as_tensor(log_scales, dtype=f32))  # [N, 3]
        self.register_buffer("colors", torch.as_tensor(colors, dtype=f32))  # [N, 3]
        self.register_buffer("cp", torch.as_tensor(cp_positions, dtype=f32))  # [K, 3]
        self.register_buffer("neighbours", torch.as_tensor(neighbours, dtype=torch.int64))  # [N, knn]
        self.register_buffer("weights", torch.as_tensor(weights, dtype=f32))  # [N, knn]
        # The same weights as a sparse [N, K] matrix: LBS as one sparse matmul (lbs.blend_matrix); rebuilt, not saved.
        self.register_buffer("blend", blend_matrix(self.neighbours, self.weights, len(self.cp)), persistent=False)
        self.views, self.frames, self.canonical_view = views, frames, canonical_view
        self.use_view, self.use_refine, self.use_lbs, self.use_global = (
            cfg.use_view,
            cfg.use_refine,
            cfg.use_lbs,
            cfg.use_global,
        )
        self.deform = DeformMLP(
            cfg.model.hidden,
            cfg.model.depth,
            cfg.model.pos_freqs,
            cfg.model.time_freqs,
            cfg.model.view_freqs,
            cfg.use_view,
        )
        self.global_se3 = GlobalSE3(views, frames, cfg.use_view) if cfg.use_global else None
        self.deform.residual_static = cfg.model.view_residual_static
        if self.global_se3 is not None:
            self.global_se3.residual_static = self.deform.residual_static
        self.refine = (
            RefineMLP(
                cfg.model.refine_hidden,
                cfg.model.refine_depth,
                cfg.model.refine_pos_freqs,
                cfg.model.time_freqs,
                cfg.model.view_freqs,
            )
            if cfg.use_refine
            else None
        )
        # Fourier features of the fixed points, computed once (positions never change).
        self.register_buffer(
            "pe_points", fourier(self.cp if self.use_lbs else self.means, cfg.model.pos_freqs), persistent=False
        )
        self.register_buffer("pe_means", fourier(self.means, cfg.model.refine_pos_freqs), persistent=False)
        # Expression basis (recon/expression_basis.py): J shapes [J, N, 3] added to the rest pose before the skinning,
        # with per-frame weights as coefficients on the DCT basis over the frames (as GlobalSE3: every step moves
        # every frame coherently); frame 0 is the rest pose.
        self.register_buffer(
            "expression_basis", None if expression_basis is None else torch.as_tensor(expression_basis, dtype=f32)
        )
        self.expression_coef = None
        if expression_basis is not None:
            self.register_buffer("expression_dct", dct_basis(frames), persistent=False)
            self.expression_coef = nn.Parameter(torch.zeros(frames, len(expression_basis)))
        self.radius = float(self.means.norm(dim=-1).mean())  # mean distance from the origin: rotation -> motion

    def expression_weights(self) -> torch.Tensor:
        """[T, J] weight of each expression shape per frame (0 at frame 0); [T, 0] without a basis."""
        if self.expression_coef is None:
            return self.means.new_zeros(self.frames, 0)
        return frames_from_dct(self.expression_dct, self.expression_coef)

    def rest_at(self, t_idx: torch.Tensor, expression: torch.Tensor | None = None) -> torch.Tensor:
        """The rest positions the deformation starts from: [N, 3] means, or [B, N, 3] with the expression basis at
        each frame's weights (or at ``expression`` [B, J], one row of weights per item, when given)."""
        if self.expression_coef is None:
            return self.means
        weights = self.expression_weights()[t_idx] if expression is None else expression
        return self.means + torch.einsum("bj,jnc->bnc", weights, self.expression_basis)

    def splats_at(self, x, q, scales, colors, face_colors=None) -> tuple:
        """The splats of vertices ``x`` [B, N, 3] with quats ``q`` [B, N, 4], ``scales``, ``colors`` [B, N, 3]: the
        vertex Gaussians moved by their offsets (spanned by the deformed edges), then the face Gaussians spanning
        those centres (``face_colors`` [B, F, 3], default the static ones)."""
        centres = x
        if self.splat_ring is not None:
            # The sparse matmul on the CPU, where it was measured; the gather where dynamo traces (a sparse tensor
            # breaks its graph) and on CUDA (its GPU measurements were made with the gather).
            if x.device.type == "cpu" and not torch.compiler.is_compiling():
                parts = tuple(getattr(self, f"splat_span_{i}") for i in range(6))
                centres = x + ring_shift_sparse(x, parts)
            else:
                centres = x + ring_shift(x, self.splat_ring, self.splat_ring_weights)
        fcol = self.face_colors if face_colors is None else face_colors
        return with_faces(centres, q, scales, colors, self.faces, fcol, self.face_log_scale, self.flatness)

    def corner_mean(self, x: torch.Tensor) -> torch.Tensor:
        """x [B, N, C] per vertex -> [B, F, C] the mean over each face's corners: on the CPU with its backward as a
        sparse matmul (gaussians.corner_mean, the same bits); the plain gather where dynamo traces (a sparse tensor
        breaks its graph) and on CUDA."""
        if x.device.type == "cpu" and not torch.compiler.is_compiling():
            return corner_mean(x, self.faces, tuple(getattr(self, f"corners_t_{i}") for i in range(3)))
        return x[:, self.faces].mean(2)

    # -- encodings of the discrete view / time indices --
    def norm_v(self, v_idx: torch.Tensor) -> torch.Tensor:
        return (v_idx.float() - self.canonical_view) / max(self.views - 1, 1) * 2.0

    def norm_t(self, t_idx: torch.Tensor) -> torch.Tensor:
        return t_idx.float() / max(self.frames - 1, 1)

    def view_on(self, v_idx: torch.Tensor) -> torch.Tensor:
        return (v_idx != self.canonical_view).float()

    def control_transforms(self, v_idx: torch.Tensor, t_idx: torch.Tensor, use_view: bool = True):
        """Per control point (or per Gaussian for no_lbs): (shared [B, P, 6], residual [B, P, 6])."""
        return self.deform(
            self.pe_points, self.norm_v(v_idx), self.norm_t(t_idx), self.view_on(v_idx) if use_view else None
        )

    def forward(
        self,
        v_idx: torch.Tensor,
        t_idx: torch.Tensor,
        refine: bool = True,
        use_view: bool = True,
        expression: torch.Tensor | None = None,
        deform_grad: bool = True,
    ) -> dict:
        """v_idx, t_idx [B] long -> dict of means [B, N, 3], quats [B, N, 4] XYZW, scales [B, N, 3]
        (linear), colors [B, N, 3], face_colors [B, F, 3] (None without faces), the splats drawn (``splats_at``),
        plus the raw parts the regularisers need. ``expression`` [B, J]: expression
        weights per item instead of the frames' own (the weights' pick tries several on one (view, time): the
        per-Gaussian RefineMLP then runs once per distinct (view, time)). ``deform_grad`` False: no gradient reaches
        the DeformMLP (the global warm-up trains T_global alone)."""
        shared, res = self.control_transforms(v_idx, t_idx, use_view)
        if not deform_grad:
            # Said in the call, not by the parameters' requires_grad: torch 2.11's guards missed a requires_grad flip
            # behind a graph break, so a compiled warm-up's gradient-free graph of the DeformMLP ran on through the
            # joint stage and nothing trained (issue 36, on an H100).
            shared, res = shared.detach(), res.detach()
        local = shared + res  # [B, P, 6]
        rest = self.rest_at(t_idx, expression)
        if self.use_lbs:
            x, q = lbs(
                rest,
                self.quats,
                self.cp,
                local[..., :3],
                local[..., 3:],
                self.neighbours,
                self.weights,
                # Traced by torch.compile: the gather, which dynamo follows (the sparse matmul cuts the step into 16
                # graphs, 2 with the gather: one before the rasterizer, one after; CPU ms per step the same). Chosen
                # here, not in lbs: dynamo breaks the trace wherever the sparse tensor is touched, even as an argument.
                None if torch.compiler.is_compiling() else self.blend,
            )
        else:
            rot = roma.rotvec_to_rotmat(local[..., :3])  # [B, N, 3, 3]: each Gaussian about itself
            x = rest + local[..., 3:]
            q = roma.quat_product(roma.rotmat_to_unitquat(rot), self.quats[None].expand(len(t_idx), -1, -1))
        g_shared = g_res = None
        if self.global_se3 is not None:
            on = self.view_on(v_idx) if use_view else torch.zeros(len(v_idx), device=v_idx.device)
            g_shared, g_res = self.global_se3(v_idx, t_idx, on)
            g = g_shared + g_res
            x, q = apply_rigid(x, q, g[:, :3], g[:, 3:])
        log_s = self.log_scales[None].expand(len(t_idx), -1, -1)
        col = self.colors[None].expand(len(t_idx), -1, -1)
        offsets = None
        if refine and self.refine is not None:
            if expression is None:
                dc, ds, dr = self.refine(self.pe_means, self.norm_v(v_idx), self.norm_t(t_idx))
            else:  # the offsets depend on (view, time) alone: once per distinct pair
                pairs, item = torch.unique(v_idx * self.frames + t_idx, return_inverse=True)
                u_v, u_t = pairs // self.frames, pairs % self.frames
                dc, ds, dr = (o[item] for o in self.refine(self.pe_means, self.norm_v(u_v), self.norm_t(u_t)))
            col = col + dc
            log_s = log_s + ds
            q = roma.quat_product(q, roma.rotvec_to_unitquat(dr))
            offsets = (dc, ds, dr)
        scales, col = log_s.exp(), col.clamp(0.0, 1.0)
        fcol = None
        if self.faces is not None:
            fcol = self.face_colors[None].expand(len(t_idx), -1, -1)
            if offsets is not None:  # faces take the mean colour offset of their corners
                fcol = fcol + self.corner_mean(offsets[0])
            fcol = fcol.clamp(0.0, 1.0)
        splats = self.splats_at(x, q, scales, col, fcol)
        return {
            "means": x,
            "quats": q,
            "scales": scales,
            "colors": col,
            "face_colors": fcol,
            "splats": splats,
            "shared": shared,
            "residual": res,
            "g_shared": g_shared,
            "g_residual": g_res,
            "offsets": offsets,
        }
