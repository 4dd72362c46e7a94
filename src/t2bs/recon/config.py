"""VCDGS configuration (paper §3.2, §4.1 and the appendix) with two presets.

``quick``: CPU, minutes per video (128 px, a few hundred control points, ~1k iterations).
``paper``: GPU, the paper's values (2000 control points, 60k iterations, 512 px).
"""

from __future__ import annotations

import math
import typing
from dataclasses import asdict, dataclass, field, replace

from t2bs.errors import UserError

METHODS = ("full", "no_view", "no_refine", "no_lbs", "no_global")


@dataclass
class VCDGSConfig:
    # --- data ---
    resolution: int = 128  # training image size (longer side, px); the rasterizer cost grows with it
    holdout_views: tuple[int, ...] = ()  # views never trained on (the benchmark renders them for PSNR/SSIM)
    # --- static Gaussians (one per mesh vertex) ---
    static_iters: int = 100  # Adam steps fitting scale/orientation/colour to renders of the static mesh
    static_lr: float = 0.01  # learning rate of that fit (log-scales, quaternions, colours)
    static_views_per_iter: int = 3  # views rendered per static-fit step
    face_gaussians: bool = True  # also one Gaussian per triangle, rebuilt from its deformed corners (covers faces
    #   that open up, e.g. a mouth; sharper silhouettes); outputs stay per vertex
    max_face_gaussians: int = 10000  # face Gaussians only on this many of the largest triangles (0 = all). A training
    #   step's cost grows with the Gaussian count; on a dense mesh at 128 px most triangles are under a pixel and
    #   their corners' Gaussians already cover them (gaussians.largest_faces). Turtle (2.6k) and facecap (8k
    #   triangles) keep all; the 47k-triangle demo fox goes from 70.5k to 33.5k Gaussians per render
    flatness: float = 0.25  # initial normal-axis scale / tangent scale: Gaussians start as flat disks
    static_fit_colors: bool = False  # also fit colours (else the texture's; hidden Gaussians would get painted)
    debias_static: bool = False  # add the rest-pose residual (splats - mesh render, per view) to the targets (vcdgs.debias_targets)
    static_shading: str = "auto"  # mesh shading for the static fit: auto (the grid's, from its meta) | unlit | lambert
    # --- control points (appendix) ---
    num_control_points: int = 400  # k; the paper uses 2000
    knn: int = 10  # control points per Gaussian (paper: 10)
    min_part_control_points: int = 0  # each connected part gets at least this many control points of its own (0 =
    #   farthest-point sampling alone, the paper's): FPS spreads them by space and leaves a small part (a lip tube,
    #   the inside of a mouth, a tooth) one or none, so its vertices are skinned to another part's
    control_neighbours: int = 6  # control-point neighbours used by the rigidity regulariser
    anchor_first_frame: bool = True  # frame 0 is the static mesh (paper §3.1.2: the grid's first column is the
    #   fixed-time render of the static asset), so the shared deformation of t = 0 is held at the identity
    # --- networks ---
    hidden: int = 128  # MLP width (Deform, Refine, per-Gaussian)
    depth: int = 4  # hidden layers
    refine_hidden: int = 32  # RefineMLP width (it runs on every Gaussian of every (v, t) pair)
    refine_depth: int = 2  # RefineMLP hidden layers
    refine_pos_freqs: int = 2  # RefineMLP position frequencies: low, so colour offsets stay smooth over the surface
    #   (lighting / colour drift) and cannot paint a geometric change (an open mouth) onto the closed one
    pos_freqs: int = 6  # Fourier frequencies of control-point / Gaussian positions
    time_freqs: int = 5  # Fourier frequencies of normalised time
    view_freqs: int = 3  # Fourier frequencies of the normalised view index
    # --- optimisation ---
    iterations: int = 800  # total steps (global warm-up included)
    time_budget_s: float = 260.0  # wall-clock cap of one reconstruction (static fit included; 0 = none): when the
    #   steps would overrun it, the schedule follows elapsed time instead (vcdgs._Schedule): warm-up, joint stage and
    #   learning-rate decay keep their shares of the run, in fewer steps (large meshes, a loaded CPU); the history
    #   records the steps actually run. Results then depend on the machine's speed; 0 makes them exact per seed
    global_iters: int = 200  # warm-up steps that fit only the global SE(3) per (v, t) (paper: "first fit the global transformation")
    global_coarse: int = 0  # coarse-to-fine warm-up: its loss starts on 2^k-downsampled images (k = global_coarse),
    #   k decreasing linearly to 0 by the end of the warm-up (a wide basin for the head's rigid motion first)
    batch_size: int = 4  # (v, t) pairs rendered per step
    canonical_fraction: float = 0.25  # share of sampled pairs at the canonical view (it defines the output geometry)
    lr_deform: float = 2e-3  # Adam lr of DeformMLP / per-Gaussian MLP (decays x lr_final_ratio)
    lr_global: float = 5e-3  # Adam lr of the global SE(3) tables
    lr_refine: float = 1e-3  # Adam lr of RefineMLP
    lr_final_ratio: float = 0.1  # exponential learning-rate decay to this fraction by the last step
    # --- loss (eq. 2: Huber + perceptual) ---
    huber_delta: float = 0.1  # Huber transition on RGB differences in 0..1
    pyramid_levels: int = 3  # Huber also on 2x, 4x, ... average-pooled images: widens the basin of large motions
    mask_weight: float = 1.0  # Huber between rendered alpha and the grid's foreground masks (when the grid has masks)
    silhouette_band: int = 1  # px: silhouettes matched against the mask dilated this much (splat tails), see losses.py
    track_weight: float = 0.05  # vertex tracks from optical flow (recon/tracks.py; our addition, 0 = the paper's loss):
    #   projected vertex motion x(v, t) - x(v, 0) matches the flow-tracked motion of its rest pixel, all stages
    track_refresh: int = 20  # steps between refreshes of the per-view rest pose the track term measures motion from
    track_views: str = "all"  # views with tracks: "all" training views or only the "canonical" one
    track_delta: float = 0.008  # Huber transition of the track term, fraction of the image's longer side (1 px at 128)
    track_fb: float = 0.008  # forward-backward flow round-trip tolerance for a valid track, same unit
    track_min_texture: float = 0.001  # a track is "textured" from this min eigenvalue of the 5x5 structure tensor
    #   (tracks.texture_strength, 128 px / 0..1 units); flat skin and straight edges leave flow to its smoothness prior
    track_flat_weight: float = 1.0  # weight of tracks starting on untextured pixels, in the joint stage only (the warm-up
    #   uses textured ones alone): flow there is filled in from edges and silhouettes, which follows a dropping jaw
    #   but under-estimates a rigid turn of a plain surface. 0 = textured tracks only (the previous default)
    track_chain: bool = True  # tracks also chained frame to frame, used where the direct frame 0 -> t flow fails, or
    #   disagrees and ends on a pixel less like the rest pixel (tracks.py): a wide-open jaw's lower lip moves ~10 px at
    #   128 px, beyond the direct flow on plain skin. Facecap clean mouth wide: the lower lip's recovered motion 0.43 ->
    #   0.75 (least-squares gain), ratio to static 0.440 -> 0.427. False = direct only
    track_agree: float = 0.012  # the direct track is kept where it is within this of the chained one, same unit (1.5 px)
    track_flow_size: int = 256  # px: the flow runs on the training images upsampled (bicubic) to at least this longer
    #   side (0 = at the training resolution; the paper preset's 512 px is not upsampled). DIS matches 8 px patches,
    #   wider than a lip at 128 px, so the lower lip's patch also holds the still upper lip. Facecap clean mouth wide,
    #   tracks of true motion >= 6 px over the training views: gain 0.76 -> 0.90, error 2.41 -> 1.85 px; see the notes
    track_blur: float = 0.0055  # Gaussian blur sigma of the flow's input images, same unit (0.7 px at 128)
    perceptual_weight: float = 0.2  # weight of LPIPS (weights present) or D-SSIM (otherwise)
    perceptual: str = "auto"  # "auto" (LPIPS if weights are configured, else D-SSIM), "lpips", "dssim", "none"
    lpips_weights: str = ""  # path to an lpips-style state dict (AlexNet features + lin layers), see losses.py
    # --- regularisers (documented in vcdgs.py) ---
    rigidity_weight: float = 0.2  # neighbouring control-point transforms agree (ARAP-like), on |delta|^2 / diag^2
    local_weight: float = 0.02  # L1-like prior on the local (DeformMLP) motion: facial motion is sparse, the rest follows T_global
    temporal_weight: float = 0.02  # adjacent frames' control-point motion is smooth
    global_smooth_weight: float = 0.0  # second differences over frames of the shared global motion stay small
    #   (head motion is smooth; each frame is only seen in a few steps, so the per-frame fit is noisy); all stages
    view_residual_static: bool = True  # view residuals depend on the view only: a per-view shape disagreement fixed over
    #   the video (a 4D generator's side view is consistently a little off: no common 3D geometry), so they cannot
    #   absorb time-varying motion; appearance drift over time goes to RefineMLP. False = the paper's residual on (v, t).
    #   Paper-like defects, mouth wide, p2p moving: facecap 0.0175 -> 0.0151 (no_view 0.0154); clean grids: see README
    view_residual_weight: float = 1.0  # view-dependent part of the deformation stays small
    refine_weight: float = 0.01  # RefineMLP offsets stay small (appearance only, not geometry)
    output_smoothing: int = 4  # Laplacian smoothing steps on each output frame's non-rigid displacement (extract.
    #   smooth_displacements): removes per-vertex fitting noise that tilts normals; 0 = the raw Gaussian centres
    hidden_pick: bool = True  # parts no training view sees at rest (teeth, mouth bag) may take the rigid motion of a
    #   cluster of seen vertices, picked by mesh renders against the training images, in groups by where they lie
    #   across the opening that reveals them (recon/hidden_parts.py); where nothing opens, nothing moves. Clean facecap
    #   mouth wide 0.409 -> 0.219 of static, tongue 0.326 -> 0.222 (docs/VCDGS_NOTES.md). Runs after training,
    #   outside time_budget_s (7-13 s a video where something opens, 0.1 s where nothing does)
    hidden_pick_clusters: int = 8  # k-means clusters of the seen vertices' trajectories: the candidate motions
    hidden_pick_views: int = 5  # training views the renders are compared at (the canonical one and up to 4 around it)
    hidden_pick_min_vertices: int = 20  # smaller hidden parts keep their own motion
    hidden_pick_closed_rigid: bool = False  # where nothing opens (no render can choose), the hidden parts take the seen
    #   surface's robust rigid motion (the head's) instead of their own, a blend of the control points around them,
    #   which a smile drags along (geometry.rigid.robust_rigid_motion; opt-in until the benchmark tables are re-run)
    # --- ablations ---
    method: str = "full"  # full | no_view | no_refine | no_lbs | no_global
    # --- misc ---
    seed: int = 0  # every random choice (sampling, init) derives from it
    device: str = "auto"  # "auto" (cuda if available), "cpu", "cuda"
    compile: bool = False  # torch.compile the training step's deformation and losses (the rasterizer stays as it is):
    #   fused kernels, ~1/5 of the operator calls per step, a CPU step ~1.3x faster than eager; but each new mesh size
    #   first compiles for ~70 s on 2 cores (cached on disk after), so it is off by default; not measured on a GPU yet.
    #   docs/BENCHMARKS.md (benchmarks/step_cost.py, speed_compare.py)
    threads: int = 2  # torch CPU threads (2: ~1.35x faster than 1 on the 2-core reference machine). A fixed count,
    #   not "all cores", because CPU reductions split work per thread: the same config then gives the same
    #   numbers on every machine and executor. 0 = torch's default
    checkpoint_every: int = 200  # steps between resumable checkpoints (0 = never)
    preview_side_view: int = 0  # view index shown next to the canonical one in preview.mp4

    def validate(self) -> "VCDGSConfig":
        if self.method not in METHODS:
            raise UserError(f"unknown method {self.method!r}; use one of {', '.join(METHODS)}")
        if self.resolution < 16:
            raise UserError(f"resolution {self.resolution} is too small (>= 16 px)")
        if self.num_control_points < 1 or self.knn < 1 or self.min_part_control_points < 0:
            raise UserError("num_control_points and knn must be >= 1, min_part_control_points >= 0")
        if self.perceptual not in ("auto", "lpips", "dssim", "none"):
            raise UserError(f"perceptual must be auto|lpips|dssim|none, got {self.perceptual!r}")
        if self.track_views not in ("all", "canonical"):
            raise UserError(f"track_views must be all|canonical, got {self.track_views!r}")
        if self.max_face_gaussians < 0:
            raise UserError(f"max_face_gaussians must be >= 0 (0 = every triangle), got {self.max_face_gaussians}")
        if self.iterations < 1 or self.global_iters < 0 or self.batch_size < 1:
            raise UserError("iterations and batch_size must be >= 1, global_iters >= 0")
        if self.hidden_pick_clusters < 1 or self.hidden_pick_views < 1:
            raise UserError("hidden_pick_clusters and hidden_pick_views must be >= 1")
        self._check_ranges()
        return self

    # Floats that must be > 0 (a zero learning rate or Huber width trains nothing / divides by 0).
    _POSITIVE = ("static_lr", "lr_deform", "lr_global", "lr_refine", "lr_final_ratio", "huber_delta", "flatness",
                 "track_delta")
    _FRACTIONS = ("canonical_fraction", "lr_final_ratio")  # also <= 1

    def _check_ranges(self) -> None:
        """Every number finite and in range: NaN or a negative count from --set would otherwise train
        NaN or crash deep inside (issue 39). Counts and weights are >= 0; the seed may be any int."""
        for name, f in self.__dataclass_fields__.items():
            value = getattr(self, name)
            if isinstance(value, bool) or name == "seed":
                continue
            if isinstance(value, float) and not math.isfinite(value):
                raise UserError(f"VCDGS option {name}={value}: must be a finite number")
            if isinstance(value, (int, float)) and value < 0:
                raise UserError(f"VCDGS option {name}={value}: must be >= 0")
            if name in self._POSITIVE and value <= 0:
                raise UserError(f"VCDGS option {name}={value}: must be > 0")
            if name in self._FRACTIONS and value > 1:
                raise UserError(f"VCDGS option {name}={value}: must be at most 1")
        if any(v < 0 for v in self.holdout_views):
            raise UserError(f"holdout_views {list(self.holdout_views)}: view indices are >= 0")
        if self.device not in ("auto", "cpu", "cuda") and not self.device.startswith("cuda:"):
            raise UserError(f"device must be auto, cpu or cuda, got {self.device!r}")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["holdout_views"] = list(self.holdout_views)
        return d

    @property
    def use_view(self) -> bool:
        return self.method != "no_view"

    @property
    def use_refine(self) -> bool:
        return self.method != "no_refine"

    @property
    def use_lbs(self) -> bool:
        return self.method != "no_lbs"

    @property
    def use_global(self) -> bool:
        return self.method != "no_global"


PRESETS = {
    "quick": VCDGSConfig(),
    # §4.1 and the appendix: 2000 control points, 60k iterations, 512 px renders, wider MLPs.
    "paper": VCDGSConfig(resolution=512, static_iters=2000, num_control_points=2000, hidden=256, depth=6,
                         refine_hidden=64, refine_depth=3, pos_freqs=8, time_freqs=6, iterations=60000, global_iters=3000, batch_size=4,
                         pyramid_levels=4, max_face_gaussians=0, checkpoint_every=2000, device="auto", threads=0, time_budget_s=0.0),
}


def preset(name: str, **overrides) -> VCDGSConfig:
    """A copy of the named preset with ``overrides`` applied (UserError for unknown names)."""
    if name not in PRESETS:
        raise UserError(f"unknown preset {name!r}; use one of {', '.join(PRESETS)}")
    bad = [k for k in overrides if k not in VCDGSConfig.__dataclass_fields__]
    if bad:
        raise UserError(f"unknown VCDGS option(s): {', '.join(bad)}")
    return replace(PRESETS[name], **overrides).validate()


_TRUE, _FALSE = ("1", "true", "yes", "on"), ("0", "false", "no", "off")


def _parse_value(name: str, kind, text: str):
    """``text`` as a value of the field type ``kind`` (int, float, bool, str or tuple[int, ...])."""
    try:
        if kind is bool and text.lower() in _TRUE + _FALSE:
            return text.lower() in _TRUE
        if kind in (int, float, str):
            return kind(text)
        if typing.get_origin(kind) is tuple:
            return tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        pass
    shown = text if len(text) <= 40 else text[:40] + f"... ({len(text)} characters)"
    raise UserError(f"VCDGS option {name}={shown!r}: not a valid {getattr(kind, '__name__', str(kind))}")


def parse_options(items: typing.Iterable[str]) -> dict:
    """``["knn=4", "hidden_pick=true", "holdout_views=4,10"]`` -> {field: typed value} overrides of VCDGSConfig
    (the CLI's ``--set``): any field by name, the value read by its type (bool: true/false, 1/0, yes/no, on/off;
    tuples: comma-separated). UserError on a malformed item, an unknown field or a value of the wrong type."""
    kinds = typing.get_type_hints(VCDGSConfig)
    out = {}
    for item in items:
        name, sep, text = item.partition("=")
        name = name.strip()
        if not sep or not name:
            raise UserError(f"--set {item!r}: expected KEY=VALUE, e.g. knn=4")
        if name not in kinds:
            raise UserError(f"--set {item!r}: no VCDGS option {name!r} (the fields of t2bs.recon.config.VCDGSConfig)")
        out[name] = _parse_value(name, kinds[name], text.strip())
    return out


__all__ = ["VCDGSConfig", "PRESETS", "METHODS", "preset", "parse_options", "field"]
