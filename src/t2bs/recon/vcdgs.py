"""VCDGS training (paper §3.2): register the static character to a multi-view video grid.

Schedule: (1) fit the static Gaussians' scale/orientation (one per vertex plus one per face,
texture colours) to renders of the static mesh (gaussians.py); (2) global-only warm-up: only
T_global(v, t) is optimised (the paper: "we first fit the global transformation"), with the per-frame weights of
the expression basis (ours, recon/expression_basis.py: auto-rig shapes added to the rest pose); (3) joint
training of T_global, DeformMLP and RefineMLP. Each step renders a batch of random (view, time)
pairs (a share of them at the canonical view, which defines the output) and minimises Huber
(+ pyramid) + perceptual (+ silhouette) losses; (4) the output: the vertex Gaussians' centres at
the canonical view, each frame's non-rigid displacement lightly smoothed over the mesh
(extract.smooth_displacements, config.output.output_smoothing). Frame 0 is anchored to the rest pose.
config.model.view_residual_static (on by default) keeps the view residuals fixed over time: a per-view
shape disagreement, as 4D generators make. config.optim.time_budget_s caps one reconstruction's wall
time (quick: 260 s; 0 = none): the schedule then runs on max(step, elapsed-time) progress, so
warm-up, joint stage and learning-rate decay all shrink in proportion when the steps do not fit
(``_Schedule``).

Regularisers (joint stage; all measured in units of the control-point spacing so the weights
do not depend on the character's size or on k):
- rigidity (ARAP-like): each control point's transform, applied to its neighbouring control
  points, should land where their own transforms put them; keeps the LBS field locally rigid
  where the images do not constrain it (occluded or textureless regions);
- temporal smoothness: control-point positions at t and t+1 (shared deformation) stay close;
- view residual: the view-dependent parts (DeformMLP residual and global residual) stay small,
  so they explain per-view distortions only, never the shared motion;
- refine: RefineMLP offsets stay small, so appearance changes do not replace geometry;
- local (sparsity): an L1-like penalty on the DeformMLP's shared motion, so that regions the
  images cannot see moving (textureless skin is only observable at silhouettes, and unlit
  renders carry no shading) follow the global head motion instead of drifting;
- track (our addition, recon/tracks.py; track_weight = 0 gives the paper's loss): projected vertex
  motion from frame 0 matches optical-flow tracks of the vertex's rest pixel (flow from frame 0, or
  chained frame to frame where that fails on large motion): textured pixels from the warm-up on,
  the others from the joint stage on. The splat loss moves a Gaussian only through
  the pixels it covers; the tracks give every visible vertex a long-range target.

Why each default is what it is, the measurements behind it, what limits accuracy on hidden mouth
parts, and what was tried and not kept: docs/VCDGS_NOTES.md.

Resume: a checkpoint (model + optimiser + step + RNG) is written every ``checkpoint_every``
steps next to the outputs, tagged with the job key; a re-run with the same key continues
from it.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import roma
import torch
import torch.nn.functional as F

from t2bs.geometry.camera import Camera
from t2bs.geometry.mesh import Mesh
from t2bs.recon.config import VCDGSConfig
from t2bs.recon.control_points import build_control_points
from t2bs.recon.deform import VCDGSModel
from t2bs.recon.images import resize_stack
from t2bs.recon.lbs import matvec
from t2bs.recon.gaussians import (
    StaticGaussians,
    camera_tensors,
    fit_static_gaussians,
    init_static_gaussians,
    render,
)
from t2bs.recon.losses import IMAGE_TERMS, PerceptualLoss, image_loss
from t2bs.recon.tracks import TRACK_UNIT_SIDE, VertexTracks, compute_tracks, project_points, track_loss


@dataclass
class TrainData:
    images: torch.Tensor  # [V, T, H, W, 3] float 0..1 at the training resolution
    masks: torch.Tensor | None  # [V, T, H, W] float 0..1 or None
    cameras: list[Camera]  # [V] resized to the training resolution
    canonical_view: int  # the paper's v = 0
    train_views: list[int]  # views used for training (holdout removed)
    shading: str = "lambert"  # the grid renderer's shading (from its meta), for the static fit's mesh renders
    tracks: VertexTracks | None = None  # optical-flow vertex tracks (config.tracks.track_weight > 0)

    def to(self, device) -> "TrainData":
        """A copy whose per-step tensors (targets, masks, residuals, tracks) live on ``device``:
        on a GPU a batch is then gathered there instead of copied over every step."""
        from dataclasses import replace

        def move(x):
            return None if x is None else x.to(device)

        return replace(self, images=move(self.images), masks=move(self.masks), tracks=move(self.tracks))

    @property
    def views(self) -> int:
        return int(self.images.shape[0])

    @property
    def frames(self) -> int:
        return int(self.images.shape[1])

    @property
    def size(self) -> tuple[int, int]:
        return int(self.images.shape[3]), int(self.images.shape[2])  # (W, H)


@dataclass
class ReconResult:
    vertices: np.ndarray  # [T, N, 3] at the canonical view
    model: VCDGSModel
    data: TrainData
    history: dict = field(default_factory=dict)  # losses over training
    seconds: float = 0.0  # wall time of the reconstruction
    loss_kind: str = "dssim"  # which perceptual term ran (lpips | dssim | none)
    hidden_pick: dict | None = None  # hidden_parts.HiddenPick.summary() when config.hidden_parts.hidden_pick ran
    expression: dict = field(default_factory=dict)  # the expression basis: shapes, landmarks, weights per frame
    # wall seconds per part: data, tracks, basis, model, train, extract, pick
    phases: dict = field(default_factory=dict)


def prepare_data(grid, cfg: VCDGSConfig) -> TrainData:
    """Downsample the grid to the training resolution (longer side = cfg.data.resolution)."""
    h, w = grid.height, grid.width
    s = min(1.0, cfg.data.resolution / max(h, w))
    size = (max(8, round(w * s)), max(8, round(h * s)))
    images = torch.stack([resize_stack(grid.frames[v], size) for v in range(grid.num_views)])  # [V, T, h, w, 3]
    masks = None
    if grid.masks is not None:
        masks = torch.stack(
            [resize_stack(grid.masks[v][..., None].astype(np.float32), size)[..., 0] for v in range(grid.num_views)]
        )
    cams = [c.resized(*size) for c in grid.cameras]
    hold = {int(v) for v in cfg.data.holdout_views}
    from t2bs.errors import UserError

    if grid.canonical_view in hold:
        raise UserError(f"the canonical view {grid.canonical_view} cannot be held out")
    if any(not 0 <= v < grid.num_views for v in hold):
        raise UserError(f"holdout_views {sorted(hold)}: the grid has views 0..{grid.num_views - 1}")
    if grid.num_frames < 2:
        raise UserError(f"the grid has {grid.num_frames} frame; VCDGS needs at least 2 (a rest frame and a moving one)")
    train_views = [v for v in range(grid.num_views) if v not in hold]
    shading = str((grid.meta.get("grid_config") or {}).get("shading", "lambert"))
    if "shading" not in (grid.meta.get("grid_config") or {}) and cfg.static_fit.static_shading == "auto":
        # Say it: an unlit grid fitted to lit mesh renders skews the static colours.
        print(
            f"warning: the grid ({grid.backend}) does not say how it was lit; the static fit assumes lambert "
            "mesh renders (`--set static_shading=unlit` if it is unlit, or re-import it with --shading)",
            flush=True,
        )
    return TrainData(
        images,
        masks,
        cams,
        int(grid.canonical_view),
        train_views,
        shading if shading in ("unlit", "lambert") else "lambert",
    )


def static_mesh_targets(mesh: Mesh, cameras: list[Camera], shading: str = "lambert") -> tuple[np.ndarray, np.ndarray]:
    """Renders of the static mesh: rgb [C, H, W, 3] float, mask [C, H, W] float."""
    from t2bs.render.mesh_renderer import MeshRenderer

    with MeshRenderer() as r:
        outs = [r.render(mesh, c, shading=shading) for c in cameras]
    return np.stack([o.rgb for o in outs]).astype(np.float32), np.stack([o.mask for o in outs]).astype(np.float32)


def build_model(
    mesh: Mesh, data: TrainData, cfg: VCDGSConfig, static_targets=None, progress: bool = False, expression_basis=None
) -> tuple[VCDGSModel, StaticGaussians]:
    """Static Gaussians (fitted) + control points -> an untrained VCDGS model.

    ``static_targets``: (rgb [V, H, W, 3], mask [V, H, W]) renders of the static mesh from every
    view of ``data`` (made with the mesh renderer when None); ``expression_basis``: [J, N, 3] shapes whose
    per-frame weights are learned too (recon/expression_basis.py), or None."""
    keep = None
    capped = 0 < cfg.static_fit.max_face_gaussians < len(mesh.faces)  # under the cap every triangle has one already
    if expression_basis is not None and cfg.static_fit.stretch_face_gaussians > 0 and capped:
        from t2bs.recon.expression_basis import stretched_faces

        keep = stretched_faces(mesh.vertices, mesh.faces, expression_basis, cfg.static_fit.stretch_face_gaussians)
    gs = init_static_gaussians(
        mesh, cfg.static_fit.flatness, cfg.static_fit.face_gaussians, cfg.static_fit.max_face_gaussians, keep
    )
    if cfg.static_fit.static_iters > 0:
        if static_targets is None:
            shading = data.shading if cfg.static_fit.static_shading == "auto" else cfg.static_fit.static_shading
            static_targets = static_mesh_targets(mesh, data.cameras, shading)
        rgb, mask = static_targets
        tv = data.train_views
        gs = fit_static_gaussians(
            gs,
            rgb[tv],
            mask[tv],
            [data.cameras[v] for v in tv],
            cfg.static_fit.static_iters,
            cfg.static_fit.static_lr,
            cfg.static_fit.static_views_per_iter,
            cfg.runtime.seed,
            device=_device(cfg).type,
            progress=progress,
            offset_faces=mesh.faces if cfg.static_fit.splat_offsets else None,
            lowpass=cfg.model.splat_lowpass,
        )
    cps = build_control_points(
        mesh.vertices,
        mesh.faces,
        cfg.control_points.num_control_points,
        cfg.control_points.knn,
        cfg.control_points.control_neighbours,
        seed=cfg.runtime.seed,
    )
    model = VCDGSModel(
        gs.means,
        gs.quats,
        gs.log_scales,
        gs.colors,
        cps.positions,
        cps.neighbours,
        cps.weights,
        data.views,
        data.frames,
        data.canonical_view,
        cfg,
        gs.faces,
        gs.face_colors,
        gs.face_log_scale,
        gs.ring,
        gs.ring_weights,
        expression_basis,
    )
    model.register_buffer("cp_neighbours", torch.as_tensor(cps.cp_neighbours))
    p = cps.positions
    spacing = (
        float(
            np.median(
                np.linalg.norm(p[:, None] - p[None], axis=-1)[np.arange(len(p))[:, None], cps.cp_neighbours][:, 0]
            )
        )
        if cps.cp_neighbours.shape[1]
        else 0.05
    )
    model.spacing = max(spacing, 1e-4)
    return model, gs


def batch_targets(data: TrainData, v_idx: torch.Tensor, t_idx: torch.Tensor):
    """The grid's images and masks of a batch of (view, time) pairs: (rgb [B, H, W, 3], mask [B, H, W] | None)."""
    vi, ti = v_idx.to(data.images.device), t_idx.to(data.images.device)
    return data.images[vi, ti], None if data.masks is None else data.masks[vi, ti]


def _device(cfg: VCDGSConfig) -> torch.device:
    if cfg.runtime.device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    check_device(cfg.runtime.device)
    return torch.device(cfg.runtime.device)


def check_device(device: str) -> None:
    """UserError for a CUDA device this machine does not have (instead of torch's deep traceback)."""
    from t2bs.errors import UserError

    if device.startswith("cuda"):
        if not torch.cuda.is_available():
            raise UserError(f"--device {device}: no CUDA GPU is available to torch here (use --device cpu or auto)")
        index = int(device.partition(":")[2] or 0) if device.partition(":")[2].isdigit() or device == "cuda" else -1
        if not 0 <= index < torch.cuda.device_count():
            raise UserError(f"--device {device}: this machine has CUDA devices 0..{torch.cuda.device_count() - 1}")


def _regularisers(model: VCDGSModel, out: dict, v_idx, t_idx, cfg: VCDGSConfig) -> dict:
    terms = {}
    s2 = model.spacing**2
    local = out["shared"] + out["residual"]  # [B, P, 6]
    if model.use_lbs and cfg.loss.rigidity_weight > 0 and model.cp_neighbours.shape[1]:
        import roma

        p, nb = model.cp, model.cp_neighbours  # [K, 3], [K, m]
        rot = roma.rotvec_to_rotmat(local[..., :3])  # [B, K, 3, 3]
        tr = local[..., 3:]
        pred = matvec(rot[:, :, None], p[nb] - p[:, None]) + p[:, None] + tr[:, :, None]  # [B, K, m, 3]
        actual = p[nb] + tr[:, nb]  # [B, K, m, 3]
        terms["rigidity"] = cfg.loss.rigidity_weight * ((pred - actual) ** 2).sum(-1).mean() / s2
    if cfg.loss.local_weight > 0:
        # Sparse local motion: without it, textureless skin (unobservable except at silhouettes)
        # drifts freely; with it, whatever the images do not demand follows the global motion.
        sh = out["shared"]
        mag = (sh[..., 3:] ** 2).sum(-1) / s2 + (sh[..., :3] ** 2).sum(-1)
        terms["local"] = cfg.loss.local_weight * (mag + 1e-4).sqrt().mean()
    if cfg.loss.temporal_weight > 0 and model.frames > 1:
        step = torch.where(t_idx < model.frames - 1, 1, -1)
        t2 = t_idx + step
        shared2, _ = model.control_transforms(v_idx, t2, use_view=False)
        d = out["shared"] - shared2
        terms["temporal"] = cfg.loss.temporal_weight * (
            (d[..., 3:] ** 2).sum(-1).mean() / s2 + (d[..., :3] ** 2).sum(-1).mean()
        )
    if model.use_view and cfg.loss.view_residual_weight > 0:
        r = out["residual"]
        reg = (r[..., 3:] ** 2).sum(-1).mean() / s2 + (r[..., :3] ** 2).sum(-1).mean()
        if out["g_residual"] is not None:
            # A global rotation by theta moves points ~radius * theta: measure both parts as motion.
            g = out["g_residual"]
            radius = model.radius
            reg = reg + ((g[:, 3:] ** 2).sum(-1).mean() + radius**2 * (g[:, :3] ** 2).sum(-1).mean()) / s2
        terms["view_residual"] = cfg.loss.view_residual_weight * reg
    if out["offsets"] is not None and cfg.loss.refine_weight > 0:
        dc, ds, dr = out["offsets"]
        terms["refine"] = cfg.loss.refine_weight * ((dc**2).mean() + (ds**2).mean() + (dr**2).mean())
    return terms


def _sample(gen: torch.Generator, data: TrainData, batch: int, canonical_fraction: float):
    t_idx = torch.randint(0, data.frames, (batch,), generator=gen)
    views = torch.tensor(data.train_views)
    v_idx = views[torch.randint(0, len(views), (batch,), generator=gen)]
    canon = torch.rand(batch, generator=gen) < canonical_fraction
    v_idx = torch.where(canon, torch.full_like(v_idx, data.canonical_view), v_idx)
    return v_idx, t_idx


class _Schedule:
    """Where training stands, as a fraction 0..1 of the run: steps done / iterations or, under a
    deadline, the elapsed share of the time left at the start, whichever is further.

    The warm-up owns the first ``warm / iterations`` of the run and the joint stage the rest
    (its learning rate decays over its share). Without a deadline this is the plain step
    schedule; with one, a character too large for the budget gets proportionally fewer
    warm-up *and* joint steps instead of a full warm-up and almost no joint training."""

    def __init__(self, iterations: int, warm: int, deadline: float | None):
        self.iterations, self.deadline = iterations, deadline
        self.t0 = time.time()
        self.warm_share = warm / max(iterations, 1)

    def progress(self, step: int) -> float:
        p = step / max(self.iterations, 1)
        if self.deadline is not None:
            elapsed = (time.time() - self.t0) / max(self.deadline - self.t0, 1e-6)
            # The clock takes over only once it is a whole step ahead of the steps: a run inside its budget follows
            # the steps alone, so it (and a resumed run) does not depend on how fast its first steps happened to be
            # (at step 0 the clock is always a little ahead, which moved the head motion's warm-up rate).
            if elapsed >= (step + 1) / max(self.iterations, 1):
                p = elapsed
        return p

    def leave_out(self, seconds: float) -> None:
        """``seconds`` that were not training (a compiled graph's first call compiles it, minutes cold): the clock's
        origin and the deadline move on by them, as the C++ kernel's build happens before the clock starts. Without
        this a cold compile under a time budget ate the warm-up: 80 s of a 600 s budget are 13 % of the run, past
        the paper preset's 5 % warm-up share, so the joint stage began after one step."""
        self.t0 += seconds
        if self.deadline is not None:
            self.deadline += seconds

    def joint(self, p: float) -> bool:
        """Past the warm-up's share (without a deadline: step >= warm, exactly)."""
        return p >= self.warm_share

    def warm_fraction(self, p: float) -> float:
        """How far through the warm-up (1 once it is over)."""
        return min(max(p / max(self.warm_share, 1e-9), 0.0), 1.0)

    def joint_fraction(self, p: float) -> float:
        return min(max((p - self.warm_share) / max(1.0 - self.warm_share, 1e-9), 0.0), 1.0)


def _lr_factor(group: str, joint: bool, warm_fraction: float, joint_fraction: float, optim) -> float:
    """The learning rate of parameter ``group`` as a fraction of its base rate at this point of the schedule.

    Every group decays exponentially to ``lr_final_ratio`` over the joint stage. With ``lr_global_joint`` < 1 the
    global SE(3) also decays over the warm-up, to that fraction, and continues from there. Why (0.1, the default since
    session 23; docs/VCDGS_NOTES.md, "The head motion's rate, again"): Adam moves each of the head motion's coefficients
    by about its rate a step, so at the full rate the per-frame head motion stays noisier than a blink moves a lid and
    keeps taking part of a small expression's image change (clean table 0.449 -> 0.434 of the rigid oracle, paper-like
    defects 0.526 -> 0.516). Before the expression basis carried the jaw it cost a wide mouth (0.227 -> 0.351); with it,
    no longer (0.215 -> 0.202)."""
    decay = optim.lr_final_ratio**joint_fraction if joint else 1.0
    if group != "global":
        return decay
    return optim.lr_global_joint * decay if joint else optim.lr_global_joint**warm_fraction


def param_groups(model: VCDGSModel, optim) -> dict[str, tuple[list, float]]:
    """The parameters ``train`` optimises, by group (deform, global, refine, expression: the names ``_lr_factor``
    knows), each with its base learning rate from ``optim`` (config.optim)."""
    groups = {"deform": (list(model.deform.parameters()), optim.lr_deform)}
    if model.global_se3 is not None:
        groups["global"] = (list(model.global_se3.parameters()), optim.lr_global)
    if model.refine is not None:
        groups["refine"] = (list(model.refine.parameters()), optim.lr_refine)
    if model.expression_coef is not None:
        groups["expression"] = ([model.expression_coef], optim.lr_expression)
    return groups


# What the warm-up trains: the head motion, and the expression weights with it, so that the head motion does not
# take a blink's or a smile's image change as a small turn before anything else can explain it.
WARM_UP_GROUPS = ("global", "expression")


def warm_up_steps(model: VCDGSModel, optim) -> int:
    """Steps of the global-only warm-up: ``optim.global_iters``, none without a global SE(3), and at least one joint
    step always left."""
    warm = optim.global_iters if model.global_se3 is not None else 0
    return min(warm, optim.iterations - 1) if optim.iterations > 1 else 0


@torch.compiler.disable
def _render_uncompiled(*args, **kwargs):
    """``render``, kept out of a compiled step (config.runtime.compile): the rasterizers are C++/CUDA kernels already,
    and tracing into gsplat's Python recompiles at every new number of tile intersections."""
    return render(*args, **kwargs)


def render_model(model: VCDGSModel, splats, viewmats: torch.Tensor, ks: torch.Tensor, width: int, height: int) -> dict:
    """Draw ``splats`` of ``model`` (``model(...)["splats"]`` or ``static_splats(...)["splats"]``) into the cameras
    ``viewmats`` [B, 4, 4], ``ks`` [B, 3, 3] with the low-pass the model was fitted and trained with
    (``model.splat_lowpass``): every render of a model goes through here, so none draws it with another one."""
    return _render_uncompiled(*splats, viewmats, ks, width, height, lowpass=model.splat_lowpass)


def step_terms(
    model: VCDGSModel,
    data: TrainData,
    cfg: VCDGSConfig,
    v_idx: torch.Tensor,
    t_idx: torch.Tensor,
    vm: torch.Tensor,
    ks: torch.Tensor,
    perceptual: PerceptualLoss,
    joint: bool,
    rest_seen: torch.Tensor | None = None,
) -> dict:
    """The loss terms of one training step on the (view, time) pairs ``v_idx``, ``t_idx`` [B] (on the model's device).

    vm [V, 4, 4], ks [V, 3, 3]: every view's camera (``camera_tensors``); ``joint``: the joint stage (RefineMLP and
    the regularisers on); ``rest_seen`` [V, N, 3]:
    the rest pose as each view sees it (``_rest_as_seen``), needed when the track term is on. One deformation and one
    rasterization call cover the whole batch. -> {name: scalar tensor}; the loss is their sum."""
    w, h = data.size
    out = model(v_idx, t_idx, refine=joint, deform_grad=joint)
    r = render_model(model, out["splats"], vm[v_idx], ks[v_idx], w, h)
    tgt, msk = batch_targets(data, v_idx, t_idx)
    terms = image_loss(r, tgt, msk, perceptual, cfg)
    if data.tracks is not None and cfg.tracks.track_weight > 0:
        # Untextured tracks join in the joint stage only: their flow is filled in from edges and
        # silhouettes, right for a jaw that drops but biased for a rigid turn (see the notes above).
        side = max(w, h)
        unit = TRACK_UNIT_SIDE / side  # the term in pixels of a 128 px image (its Huber is 1-homogeneous)
        terms["track"] = (
            cfg.tracks.track_weight
            * unit
            * track_loss(
                out["means"],
                rest_seen[v_idx],
                vm[v_idx],
                ks[v_idx],
                data.tracks,
                v_idx,
                t_idx,
                cfg.tracks.track_delta * side,
                flat_weight=cfg.tracks.track_flat_weight if joint else 0.0,
                slack=cfg.tracks.track_slack if joint else 0.0,
                head=_head_motion_px(model, out, rest_seen[v_idx], vm[v_idx], ks[v_idx], v_idx, t_idx)
                if joint and cfg.tracks.track_slack > 0
                else None,
            )
        )
    if joint:
        terms.update(_regularisers(model, out, v_idx, t_idx, cfg))
    return terms


@torch.no_grad()
def _head_motion_px(model: VCDGSModel, out: dict, x0: torch.Tensor, vm, ks, v_idx, t_idx) -> torch.Tensor | None:
    """[B, N, 2] the image motion of the rest pose as each view sees it (``x0`` [B, N, 3]) under the model's head
    motion alone, frame 0 -> t (its global SE(3) at t after undoing the one at frame 0); None without a global SE(3)."""
    if out["g_shared"] is None:
        return None
    g = out["g_shared"] + out["g_residual"]  # [B, 6]
    g0 = sum(model.global_se3(v_idx, torch.zeros_like(t_idx), model.view_on(v_idx)))
    r, r0 = roma.rotvec_to_rotmat(g[:, :3]), roma.rotvec_to_rotmat(g0[:, :3])
    x = torch.einsum("bij,bnj->bni", r @ r0.transpose(1, 2), x0 - g0[:, None, 3:]) + g[:, None, 3:]
    return project_points(x, vm, ks) - project_points(x0, vm, ks)


class _NetworkCheck:
    """A training run whose joint steps leave the deformation network exactly as it was has trained nothing (a
    compiled step replayed as CUDA graphs did that on an H100, silently, and ``compile=true`` with torch 2.11: issue
    36): ``check`` says so instead of returning an untrained model. Snapshots the network's weights when the joint
    stage starts."""

    def __init__(self, model: VCDGSModel, joint: bool):
        self.params = list(model.deform.parameters()) if joint and model.deform is not None else []
        self.before = [p.detach().clone() for p in self.params]

    def check(self, joint_steps: int, cfg: VCDGSConfig) -> None:
        if joint_steps < 1 or not self.params:
            return
        if all(torch.equal(p.detach(), b) for p, b in zip(self.params, self.before)):
            from t2bs.errors import UserError

            raise UserError(
                f"VCDGS trained nothing: {joint_steps} joint steps left the deformation network unchanged "
                f"(device {cfg.runtime.device}, compile={str(cfg.runtime.compile).lower()}, "
                f"cuda_graphs={str(cfg.runtime.cuda_graphs).lower()}); this is a bug, please "
                "report it with this line"
            )


def train(
    model: VCDGSModel,
    data: TrainData,
    cfg: VCDGSConfig,
    progress: bool = True,
    checkpoint: Path | None = None,
    key: str = "",
    deadline: float | None = None,
) -> dict:
    """Optimise ``model`` on ``data``; returns the loss history. Resumes from ``checkpoint``.

    ``deadline`` (time.time() value, optional): the schedule follows max(step fraction, elapsed-time
    fraction) (see ``_Schedule``), so a run that cannot finish its steps in time still gets the
    warm-up / joint split and the full learning-rate decay, compressed into the steps it can afford."""
    from tqdm import tqdm

    dev = _device(cfg)
    model.to(dev)
    data = data.to(dev)
    vm, ks = camera_tensors(data.cameras, dev)
    w, h = data.size
    perceptual = PerceptualLoss(cfg.loss.perceptual, cfg.loss.lpips_weights).to(dev)
    gen = torch.Generator().manual_seed(cfg.runtime.seed)
    groups = param_groups(model, cfg.optim)
    # fused: one kernel per optimiser step instead of ~10 operators per parameter tensor (CPU and CUDA).
    opts = {k: torch.optim.Adam(p, lr=lr, fused=True) for k, (p, lr) in groups.items()}
    warm = warm_up_steps(model, cfg.optim)
    # clock: training seconds at each logged step, the expression picks' left out (read after a device sync: the
    # loss's float)
    history = {"step": [], "loss": [], "image": [], "clock": [], "kind": perceptual.kind, "first_image_loss": None}
    started = time.perf_counter()
    start = 0
    if checkpoint is not None and checkpoint.exists():
        resumed = resume_checkpoint(checkpoint, key, model, opts, gen, cfg.optim.iterations, dev)
        if resumed is not None:
            history, start = resumed
    bar = tqdm(
        range(start, cfg.optim.iterations),
        desc="VCDGS",
        leave=False,
        disable=not progress,
        initial=start,
        total=cfg.optim.iterations,
    )
    history["clock_from"] = start  # a resumed run's earlier clock readings are another process's
    model.train()
    clock = _Schedule(cfg.optim.iterations, warm, deadline)
    joint = bool(history.get("joint_from") is not None and start >= history["joint_from"])
    history["steps_run"] = start
    terms_fn = step_terms
    graphs = cfg.runtime.compile and cfg.runtime.cuda_graphs and dev.type == "cuda"
    history["step_kind"] = "compiled, CUDA graphs" if graphs else "compiled" if cfg.runtime.compile else "eager"
    if cfg.runtime.compile:
        # Static shapes: a batch is always batch_size pairs; the warm-up and the joint stage are one graph each.
        # Inductor's reduce-overhead mode is its CUDA-graph replay (the one option it sets); none on the CPU.
        terms_fn = torch.compile(step_terms, dynamic=False, mode="reduce-overhead" if graphs else None)
    networks = _NetworkCheck(model, joint)
    rest_seen = None  # [V, N, 3] the rest pose as each view sees it, for the track term (refreshed)
    for step in bar:
        p = clock.progress(step)
        if p >= 1.0:  # only reachable through the deadline: steps alone end with the loop
            history["stopped_at_budget"] = step
            break
        if not joint and clock.joint(p):
            joint = True
            history["joint_from"] = step
            networks = _NetworkCheck(model, joint)
        frac = clock.joint_fraction(p)
        if joint and model.expression_coef is not None:
            # the clock counts steps only: a pick's seconds move its origin
            started += _pick_due_expression_weights(model, data, cfg, perceptual, opts, history, step, frac)
        refits = history.get("track_refits", 0)
        if joint and data.tracks is not None and cfg.tracks.track_refit:
            # a resumed run measures its tracks again from the resumed model (a checkpoint does not hold them)
            due = refits < len(cfg.tracks.track_refit) and frac >= cfg.tracks.track_refit[refits]
            if due or (step == start and refits > 0):
                began = time.perf_counter()
                data.tracks = _refit_tracks(model, data, cfg, vm, ks)
                history["track_refits"] = refits + int(due)
                spent = time.perf_counter() - began
                history["track_refit_s"] = round(history.get("track_refit_s", 0.0) + spent, 2)
                started += spent
        history["steps_run"] = step + 1
        for k, o in opts.items():
            base = groups[k][1]
            for g in o.param_groups:
                g["lr"] = base * _lr_factor(k, joint, clock.warm_fraction(p), frac, cfg.optim)
        v_idx, t_idx = _sample(gen, data, cfg.optim.batch_size, cfg.optim.canonical_fraction)
        v_idx, t_idx = v_idx.to(dev), t_idx.to(dev)
        if (
            data.tracks is not None
            and cfg.tracks.track_weight > 0
            and (rest_seen is None or step % cfg.tracks.track_refresh == 0)
        ):
            rest_seen = _rest_as_seen(model, data.views)
        # the first step of each compiled graph (the warm-up's, the joint stage's; a resumed run's first) compiles it
        compiling = cfg.runtime.compile and (step == start or history.get("joint_from") == step)
        compile_from = time.time()
        if cfg.runtime.compile:
            # A step's compiled graphs replayed as CUDA graphs (cuda_graphs) reuse their output buffers: say where a
            # step begins instead of leaving inductor to guess it; a no-op otherwise.
            torch.compiler.cudagraph_mark_step_begin()
        terms = terms_fn(model, data, cfg, v_idx, t_idx, vm, ks, perceptual, joint, rest_seen=rest_seen)
        img = sum(v for n, v in terms.items() if n in IMAGE_TERMS).detach()
        loss = sum(terms.values())
        for o in opts.values():
            o.zero_grad(set_to_none=True)
        loss.backward()
        for k, o in opts.items():
            if joint or k in WARM_UP_GROUPS:
                o.step()
        if compiling:  # its forward and backward graphs compiled: not in the time budget's schedule
            spent = time.time() - compile_from
            clock.leave_out(spent)
            history["compile_s"] = round(history.get("compile_s", 0.0) + spent, 2)
        if history["first_image_loss"] is None:
            history["first_image_loss"] = float(img)
        if step % 10 == 0 or step == cfg.optim.iterations - 1:
            history["terms"] = {k: round(float(v.detach()), 6) for k, v in terms.items()}
            history["step"].append(step)
            history["loss"].append(float(loss.detach()))
            history["image"].append(float(img))
            history.setdefault("clock", []).append(round(time.perf_counter() - started, 3))
            bar.set_postfix(stage="joint" if joint else "global", loss=f"{float(loss.detach()):.4f}")
        if (
            checkpoint is not None
            and cfg.runtime.checkpoint_every
            and (step + 1) % cfg.runtime.checkpoint_every == 0
            and step + 1 < cfg.optim.iterations
        ):
            from t2bs.project import atomic_path

            with atomic_path(checkpoint) as tmp:
                torch.save(
                    {
                        "key": key,
                        "step": step + 1,
                        "model": model.state_dict(),
                        "opts": {k: o.state_dict() for k, o in opts.items()},
                        "gen": gen.get_state(),
                        "history": history,
                    },
                    tmp,
                )
    model.eval()
    networks.check(history["steps_run"] - max(start, history.get("joint_from") or 0), cfg)
    history["final_image_loss"] = float(np.mean(history["image"][-5:])) if history["image"] else float("nan")
    history["joint_ms_per_step"] = joint_ms_per_step(history)
    return history


def joint_ms_per_step(history: dict, settle: int = 50) -> float | None:
    """Milliseconds per joint-stage step of a training run, from its logged clock, leaving out the stage's first
    ``settle`` steps (a compiled step compiles there) and any step before a resumed run's start. None when fewer
    than 20 steps follow."""
    first = max((history.get("joint_from") or 0) + settle, history.get("clock_from", 0))
    pairs = [(s, c) for s, c in zip(history["step"], history.get("clock", [])) if s >= first]
    if len(pairs) < 3 or pairs[-1][0] - pairs[0][0] < 20:
        return None
    return round(1000 * (pairs[-1][1] - pairs[0][1]) / (pairs[-1][0] - pairs[0][0]), 2)


def _pick_due_expression_weights(model, data, cfg, perceptual, opts, history, step: int, frac: float) -> float:
    """The picks of config.optim.expression_pick whose joint-stage fraction ``frac`` has reached and that have not
    run yet (a resumed run keeps its record in ``history["expression_picks"]``): recon/expression_pick.py. The
    weights' Adam state starts afresh after a pick: its momentum points back to the weights the pick left. Returns
    the seconds spent (0.0 when none was due)."""
    done = history.setdefault("expression_picks", [])
    due = [f for f in cfg.optim.expression_pick if f <= frac and all(d["at"] != f for d in done)]
    if not due:  # every joint step asks: nothing more than this list
        return 0.0
    from t2bs.recon.expression_pick import pick_expression_weights
    from t2bs.recon.hidden_parts import compare_views

    views = compare_views(data.cameras, data.canonical_view, list(data.train_views), cfg.optim.expression_pick_views)
    report = pick_expression_weights(model, data, cfg, views, refine=True, perceptual=perceptual)
    opts["expression"].state.clear()
    done.extend({"at": f, "step": step, **report} for f in due)
    return float(report["seconds"])


def resume_checkpoint(
    path: Path, key: str, model: VCDGSModel, opts: dict, gen: torch.Generator, iterations: int, dev
) -> tuple[dict, int] | None:
    """Load a training checkpoint into ``model``/``opts``/``gen``; (history, step), or None to start fresh.

    A project folder may come from someone else, so nothing in it is executed: the file is read
    with ``weights_only=True`` (tensors and plain containers only; a pickled callable is refused
    by torch's restricted unpickler), and its key is checked before any state is used. A file that
    does not load, belongs to other inputs or does not fit this model is removed with a warning,
    and training starts fresh with the model untouched."""
    import copy
    import sys

    def discard(why: str) -> None:
        print(f"warning: {path}: {why}; discarded, training starts fresh", file=sys.stderr, flush=True)
        path.unlink(missing_ok=True)

    try:
        ck = torch.load(path, map_location=dev, weights_only=True)
    except Exception as exc:  # truncated zip, a pickle with code in it, not a torch file: all untrusted input
        import pickle

        why = (
            "it holds objects other than tensors and plain values (possibly code), refused unexecuted"
            if isinstance(exc, pickle.UnpicklingError)
            else f"it is not a readable checkpoint ({type(exc).__name__})"
        )
        discard(f"checkpoint does not load: {why}")
        return None
    if not isinstance(ck, dict) or ck.get("key") != key:
        discard("checkpoint belongs to other inputs or settings (its key differs)")
        return None
    step, history = ck.get("step"), ck.get("history")
    if (
        not isinstance(step, int)
        or not 0 <= step <= iterations
        or not isinstance(history, dict)
        or not isinstance(ck.get("opts"), dict)
        or set(ck["opts"]) != set(opts)
    ):
        discard("checkpoint is malformed (step, history or optimiser state)")
        return None
    saved = (
        copy.deepcopy(model.state_dict()),
        {k: copy.deepcopy(o.state_dict()) for k, o in opts.items()},
        gen.get_state(),
    )
    try:
        model.load_state_dict(ck["model"])
        for k, o in opts.items():
            o.load_state_dict(ck["opts"][k])
        gen.set_state(ck["gen"])
        if any(not torch.isfinite(p).all() for p in model.parameters()):
            raise ValueError("non-finite parameters")
    except Exception as exc:  # shapes of another model, a wrong generator state: restore what was there
        model.load_state_dict(saved[0])
        for k, o in opts.items():
            o.load_state_dict(saved[1][k])
        gen.set_state(saved[2])
        discard(f"checkpoint does not fit this model ({type(exc).__name__})")
        return None
    return history, step


@torch.no_grad()
def _refit_tracks(model: VCDGSModel, data: TrainData, cfg: VCDGSConfig, vm, ks, batch: int = 8) -> VertexTracks:
    """config.tracks.track_refit: every training view and frame rendered as training renders it, and the tracks
    measured again as the model's motion plus the flow from its render to the input (tracks.residual_tracks)."""
    from t2bs.recon.tracks import residual_tracks

    w, h = data.size
    pairs = [(v, t) for v in data.train_views for t in range(data.frames)]
    renders = np.zeros((data.views, data.frames, h, w, 3), np.float32)
    projected = np.zeros((data.views, data.frames, len(model.means), 2), np.float32)
    head = np.zeros_like(projected)
    rest = _rest_as_seen(model, data.views)
    was = model.training
    model.eval()
    for i in range(0, len(pairs), batch):
        v_idx = torch.tensor([p[0] for p in pairs[i : i + batch]], device=model.means.device)
        t_idx = torch.tensor([p[1] for p in pairs[i : i + batch]], device=model.means.device)
        out = model(v_idx, t_idx, refine=True)
        r = render_model(model, out["splats"], vm[v_idx], ks[v_idx], w, h)
        vi, ti = v_idx.cpu().numpy(), t_idx.cpu().numpy()
        renders[vi, ti] = r["rgb"].clamp(0, 1).cpu().numpy()
        projected[vi, ti] = project_points(out["means"], vm[v_idx], ks[v_idx]).cpu().numpy()
        hp = _head_motion_px(model, out, rest[v_idx], vm[v_idx], ks[v_idx], v_idx, t_idx)
        if hp is not None:
            head[vi, ti] = hp.cpu().numpy()
    model.train(was)
    side = max(data.size)
    tc = cfg.tracks
    return residual_tracks(
        data.tracks,
        renders,
        data.images.cpu().numpy(),
        projected,
        data.train_views,
        tc.track_fb * side,
        tc.track_blur * side,
        tc.track_flow_size,
        head=head,
        below_px=tc.track_refit_below * side,
    )


@torch.no_grad()
def _rest_as_seen(model: VCDGSModel, views: int) -> torch.Tensor:
    """[V, N, 3] vertex positions at frame 0 per view: the rest pose plus that view's residual
    (a 4D generator's side view disagrees with the front one already at rest). The track term
    measures motion from here; it changes slowly, so train() refreshes it every few steps."""
    v_idx = torch.arange(views, device=model.means.device)
    return model(v_idx, torch.zeros_like(v_idx), refine=False)["means"]


def static_splats(model: VCDGSModel, batch: int, vertices: torch.Tensor | None = None) -> dict:
    """The static Gaussians (vertex + face; rest shapes, orientations and colours), repeated ``batch`` times, as
    ``model.forward`` returns them: at the rest pose, or centred on ``vertices`` [batch, N, 3] (diagnostics that
    place the static splats at given positions: benchmarks/lid_scene.py, truth_loss.py, amplitude_oracle.py)."""

    x = model.means[None].expand(batch, -1, -1) if vertices is None else vertices
    q = model.quats[None].expand(batch, -1, -1)
    s, c = model.log_scales.exp()[None].expand(batch, -1, -1), model.colors[None].expand(batch, -1, -1)
    return {"splats": model.splats_at(x, q, s, c)}


@torch.no_grad()
def evaluate_image_loss(model: VCDGSModel, data: TrainData, cfg: VCDGSConfig, deformed: bool = True) -> float:
    """Mean Huber image loss over every training (view, time) pair (no RefineMLP)."""
    dev = next(iter(model.buffers())).device
    vm, ks = camera_tensors(data.cameras, dev)
    w, h = data.size
    total, count = 0.0, 0
    for v in data.train_views:
        for t0 in range(0, data.frames, 8):
            t_idx = torch.arange(t0, min(t0 + 8, data.frames), device=dev)
            v_idx = torch.full_like(t_idx, v)
            if deformed:
                out = model(v_idx, t_idx, refine=False)
            else:
                out = static_splats(model, len(t_idx))
            r = render_model(model, out["splats"], vm[v_idx], ks[v_idx], w, h)
            tgt = batch_targets(data, v_idx, t_idx)[0].to(dev)
            total += float(F.huber_loss(r["rgb"], tgt, delta=cfg.loss.huber_delta)) * len(t_idx)
            count += len(t_idx)
    return total / max(count, 1)


@contextlib.contextmanager
def deterministic_on_cpu(cfg: VCDGSConfig):
    """torch's deterministic algorithms while ``cfg`` runs on the CPU, the caller's setting restored after. Why: the
    backward of a gather (``x[faces]``, ``x[ring]``) adds into ``x``'s gradient with atomic adds from torch's threads,
    so on a busy machine the float sums change order with the threads' timing, and a seeded reconstruction with them
    (facecap's clean rows moved by up to 0.04 of the rigid oracle between identical runs, the same case run alone and
    beside another). Deterministic mode adds in order (~8 % slower on that op alone). Not on CUDA, where it would
    refuse the ops that have no deterministic kernel."""
    before = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(before or _device(cfg).type == "cpu")
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(before)


def reconstruct_grid(
    mesh: Mesh,
    grid,
    cfg: VCDGSConfig,
    progress: bool = True,
    static_targets=None,
    checkpoint: Path | None = None,
    key: str = "",
    landmarks_file: Path | None = None,
    tracks_fn=None,
) -> ReconResult:
    """The whole VCDGS job for one grid: data, static fit, expression basis, control points, training, extraction.

    ``landmarks_file``: the user's 20 face points for the expression basis's auto rig (else the face is found on a
    render of ``mesh``, which must be in the canonical frame). ``tracks_fn(mesh, data, cfg, progress) ->
    VertexTracks``: what makes the vertex tracks (None = ``vertex_tracks``, the optical flow; the benchmark's
    ``--perfect-tracks`` passes the truth's image motion, to measure what better tracks could buy)."""
    from t2bs.errors import UserError

    cfg.validate()
    if grid.gt_vertices is not None and grid.gt_vertices.shape[1] != mesh.num_vertices:
        raise UserError(
            f"grid ground truth has {grid.gt_vertices.shape[1]} vertices but the character has {mesh.num_vertices}"
        )
    if _device(cfg).type == "cpu":
        # The C++ kernel's first build (a minute or more on 2 cores, once per torch installation) happens here, before
        # the video's clock starts: inside it, a fresh install's first demo video lost 225 of its 800 steps to the
        # 260 s budget (session 26).
        from t2bs.render.splat.cpu import load_kernel

        load_kernel()
    torch.manual_seed(cfg.runtime.seed)
    threads = torch.get_num_threads()
    if cfg.runtime.threads > 0:
        torch.set_num_threads(cfg.runtime.threads)
    try:
        with deterministic_on_cpu(cfg):
            return _reconstruct(mesh, grid, cfg, progress, static_targets, checkpoint, key, landmarks_file, tracks_fn)
    finally:
        torch.set_num_threads(threads)


def vertex_tracks(mesh: Mesh, data: TrainData, cfg: VCDGSConfig, progress: bool = False) -> VertexTracks:
    """The optical-flow tracks of ``data``'s training views as ``cfg.tracks`` asks for them (its pixel thresholds are
    fractions of the training images' longer side): what a reconstruction trains on, before the lids' release."""
    side = max(data.size)
    tc = cfg.tracks
    return compute_tracks(
        mesh,
        data.images,
        data.cameras,
        data.train_views,
        tc.track_fb * side,
        tc.track_blur * side,
        progress,
        min_texture=tc.track_min_texture,
        chain=tc.track_chain,
        agree_px=tc.track_agree * side,
        flow_size=tc.track_flow_size,
    )


def seconds_inside_train(history: dict) -> dict:
    """``train``'s history -> {"expression_picks": s, "track_refits": s}: seconds of the training phase (not laps of
    their own) that its expression picks and track refits took. One pick runs for every fraction due at its step, and
    each fraction gets a record with that pick's seconds, so picks count once per step; a resumed run's earlier picks
    (before ``clock_from``) are another process's. The refits' seconds are a running total in the history, so a
    resumed run's include the earlier process's."""
    start = history.get("clock_from", 0)
    picks = {p["step"]: p["seconds"] for p in history.get("expression_picks", []) if p["step"] >= start}
    return {"expression_picks": round(sum(picks.values()), 2), "track_refits": history.get("track_refit_s", 0.0)}


def _reconstruct(
    mesh: Mesh, grid, cfg: VCDGSConfig, progress, static_targets, checkpoint, key, landmarks_file, tracks_fn=None
) -> ReconResult:
    from t2bs.recon.expression_basis import expression_basis, release_lid_tracks
    from t2bs.recon.extract import canonical_vertices, smooth_displacements

    t0 = time.time()
    phases: dict[str, float] = {}
    mark = [t0]

    def lap(name: str) -> None:  # the seconds since the last lap, as phase `name`
        now = time.time()
        phases[name] = round(now - mark[0], 2)
        mark[0] = now

    data = prepare_data(grid, cfg)
    lap("data")
    if cfg.tracks.track_weight > 0:
        data.tracks = (tracks_fn or vertex_tracks)(mesh, data, cfg, progress)
    lap("tracks")
    basis, expression = expression_basis(mesh, cfg.model.expression_shapes, landmarks_file)
    if basis is not None and data.tracks is not None and cfg.tracks.track_release_lids > 0:
        expression["tracks_released"] = release_lid_tracks(
            data.tracks, basis, expression["shapes"], cfg.tracks.track_release_lids
        )
    lap("basis")
    model, _ = build_model(mesh, data, cfg, static_targets, progress, basis)
    lap("model")  # the static fit and the control points
    # Budget for training: what is left of time_budget_s, less a small margin for extraction.
    deadline = t0 + cfg.optim.time_budget_s - 5.0 if cfg.optim.time_budget_s > 0 else None
    history = train(model, data, cfg, progress, checkpoint, key, deadline=deadline)
    lap("train")
    phases.update(seconds_inside_train(history))
    if basis is not None:
        expression["weights"] = np.round(model.expression_weights().detach().cpu().numpy(), 4).tolist()  # [T, J]
    verts = smooth_displacements(canonical_vertices(model), mesh.vertices, mesh.faces, cfg.output.output_smoothing)
    lap("extract")
    pick = None
    if cfg.hidden_parts.hidden_pick:
        verts, pick = _pick_hidden(mesh, verts, data, cfg)
        lap("pick")
    seconds = time.time() - t0
    return ReconResult(verts, model, data, history, seconds, history.get("kind", "dssim"), pick, expression, phases)


def _pick_hidden(mesh: Mesh, verts: np.ndarray, data: TrainData, cfg: VCDGSConfig) -> tuple[np.ndarray, dict]:
    """config.hidden_parts.hidden_pick: the hidden parts' motion picked by render (recon/hidden_parts.py)."""
    from t2bs.recon.hidden_parts import compare_views, pick_hidden_motions
    from t2bs.recon.tracks import rest_visibility

    seen = rest_visibility(mesh, data.cameras, data.train_views).any(0)
    views = compare_views(data.cameras, data.canonical_view, data.train_views, cfg.hidden_parts.hidden_pick_views)
    frames = list(range(1, data.frames, 2))  # every other frame after the rest pose
    verts, report = pick_hidden_motions(
        mesh,
        verts,
        seen,
        data.images.cpu().numpy(),
        data.cameras,
        views,
        frames,
        data.shading,
        cfg.hidden_parts.hidden_pick_clusters,
        cfg.hidden_parts.hidden_pick_min_vertices,
        seed=cfg.runtime.seed,
        closed_rigid=cfg.hidden_parts.hidden_pick_closed_rigid,
        side_fraction=cfg.hidden_parts.hidden_pick_side_fraction,
        even=cfg.hidden_parts.hidden_pick_even,
    )
    return verts, report.summary()


def load_trained_model(state_path: Path) -> tuple[VCDGSModel, VCDGSConfig]:
    """The trained model of a finished reconstruction (``recon/<video>/state.pt``) -> (model on the CPU, config).

    Loaded with ``weights_only=True``: a state file holds tensors and plain values, so nothing in a project folder
    is executed. UserError when the file is missing or not such a state."""
    from t2bs.errors import UserError

    state_path = Path(state_path)
    if not state_path.exists():
        raise UserError(f"{state_path}: no trained model (run `t2bs reconstruct` first)")
    try:
        state = torch.load(state_path, map_location="cpu", weights_only=True)
        sd, raw = state["model"], dict(state["config"])
        # a model saved before the field existed was fitted, trained and drawn with 3DGS's low-pass
        raw["model"] = {"splat_lowpass": 0.3, **(raw.get("model") or {})}
        # options removed since (session 47) that change nothing a trained model draws: one only steered training,
        # the other placed control points, which the state holds
        for section, name in (("model", "global_from_still"), ("control_points", "min_part_control_points")):
            (raw.get(section) or {}).pop(name, None)
        cfg = VCDGSConfig.from_dict(raw)
        faces = sd.get("faces")
        model = VCDGSModel(
            sd["means"],
            sd["quats"],
            sd["log_scales"],
            sd["colors"],
            sd["cp"],
            sd["neighbours"],
            sd["weights"],
            int(state["views"]),
            int(state["frames"]),
            int(state["canonical_view"]),
            cfg,
            faces,
            sd.get("face_colors"),
            sd.get("face_log_scale"),
            sd.get("splat_ring"),
            sd.get("splat_ring_weights"),
            sd.get("expression_basis"),
        )
        model.register_buffer("cp_neighbours", sd["cp_neighbours"])
        model.load_state_dict(sd)
    except UserError:
        raise
    except Exception as exc:  # a truncated file, another format, missing keys
        raise UserError(f"{state_path}: not a t2bs reconstruction state ({type(exc).__name__}: {exc})") from None
    return model.eval(), cfg
