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


# The configuration is a small tree: one dataclass per concern, each field one line. Field names are unique
# across the tree, so `--set knn=4` names a field without its section (`--set control_points.knn=4` also works).
# Measurements behind the defaults are in docs/VCDGS_NOTES.md, not here.


@dataclass
class DataConfig:
    resolution: int = 128  # training image size, longer side in px (the rasterizer's cost grows with it)
    holdout_views: tuple[int, ...] = ()  # views never trained on (the benchmark renders them for PSNR / SSIM)


@dataclass
class StaticFitConfig:
    static_iters: int = 100  # Adam steps fitting Gaussian scales / orientations to renders of the static mesh
    static_lr: float = 0.01  # learning rate of that fit (log-scales, quaternions)
    static_views_per_iter: int = 3  # views rendered per static-fit step
    static_shading: str = "auto"  # shading of those mesh renders: auto (the grid's, from its meta) | unlit | lambert
    face_gaussians: bool = True  # also one Gaussian per triangle, rebuilt from its deformed corners (mouths opening)
    max_face_gaussians: int = 10000  # face Gaussians only on this many of the largest triangles (0 = every triangle)
    # ... and on every triangle an expression-basis shape stretches by more than this area ratio (0 = none)
    stretch_face_gaussians: float = 1.25
    flatness: float = 0.25  # initial normal-axis scale / tangent scale: Gaussians start as flat disks
    splat_offsets: bool = True  # the fit may slide each vertex Gaussian along the surface, off its vertex (part edges)


@dataclass
class ControlPointsConfig:
    num_control_points: int = 400  # k control points, farthest-point sampled on the mesh (paper: 2000)
    knn: int = 10  # control points skinning each Gaussian (LBS, paper: 10)
    control_neighbours: int = 6  # control-point neighbours in the rigidity regulariser


@dataclass
class ModelConfig:
    hidden: int = 128  # width of the DeformMLP and the per-Gaussian MLP (no_lbs)
    depth: int = 4  # their hidden layers
    refine_hidden: int = 32  # RefineMLP width (it runs on every Gaussian of every (view, time) pair)
    refine_depth: int = 2  # RefineMLP hidden layers
    refine_pos_freqs: int = 2  # RefineMLP position frequencies (low: colour offsets stay smooth, cannot paint shape)
    pos_freqs: int = 6  # Fourier frequencies of control-point / Gaussian positions
    time_freqs: int = 5  # Fourier frequencies of normalised time
    view_freqs: int = 3  # Fourier frequencies of the normalised view index
    view_residual_static: bool = True  # view residuals depend on the view only (False: on (view, time), the paper's)
    # px^2 the rasterizer adds to each splat's 2D covariance in the static fit, the training and every render of the
    # model. 3DGS's 0.3 (the paper preset's) blurs every edge by ~0.55 px: at 128 px it drew facecap's ~3 px eye
    # openings half shut. 0.18: clean table mean 0.432 -> 0.407 of the rigid oracle, p2p moving -4.6 %; 0.1 and 0.03
    # drew the eyes sharper still but moved the whole head (facecap blinking p2p +31 % / +64 %)
    splat_lowpass: float = 0.18
    # Auto-rig shapes (ARKit names) whose per-frame weights the fit also learns, under the networks' motion (ours,
    # recon/expression_basis.py; () = the paper's model)
    expression_shapes: tuple[str, ...] = (
        "eyeBlinkLeft",
        "eyeBlinkRight",
        "jawOpen",
        "mouthSmileLeft",
        "mouthSmileRight",
    )


@dataclass
class OptimConfig:
    iterations: int = 800  # training steps, the global warm-up included
    time_budget_s: float = 260.0  # wall-clock cap of a reconstruction, static fit in, compiling out (0 = none, exact)
    global_iters: int = 200  # warm-up steps fitting only the global SE(3) per (view, time)
    batch_size: int = 4  # (view, time) pairs rendered per step
    canonical_fraction: float = 0.25  # share of sampled pairs at the canonical view (it defines the output geometry)
    lr_deform: float = 2e-3  # Adam learning rate of the DeformMLP / per-Gaussian MLP
    lr_global: float = 5e-3  # Adam learning rate of the global SE(3) tables
    # The global SE(3)'s rate decays over the warm-up to this fraction and on from there (1 = no extra decay): at the
    # full rate Adam's steps keep the head motion noisier than a blink moves a lid (docs/VCDGS_NOTES.md, "The head
    # motion's rate, again")
    lr_global_joint: float = 0.1
    lr_refine: float = 1e-3  # Adam learning rate of the RefineMLP
    lr_expression: float = 0.05  # Adam learning rate of the expression weights (DCT coefficients over the frames)
    lr_final_ratio: float = 0.1  # exponential learning-rate decay to this fraction by the last step
    # Points of the joint stage (fractions, 0 = its start) where each frame's expression weights are picked by render
    # (recon/expression_pick.py): a search out of the plateau a lid's weight gets stuck on; the last, near the end,
    # catches weights that drift back onto it (the demo fox's smile kept one eye open without it). () = never
    expression_pick: tuple[float, ...] = (0.0, 0.5, 0.9)
    expression_pick_views: int = 3  # views whose image losses a pick compares: the canonical one and its nearest


@dataclass
class LossConfig:
    huber_delta: float = 0.1  # Huber transition on RGB differences in 0..1 (eq. 2)
    pyramid_levels: int = 3  # Huber also on 2x, 4x, ... average-pooled images (a wider basin for large motions)
    mask_weight: float = 1.0  # Huber between rendered alpha and the grid's foreground masks (grids with masks)
    silhouette_band: int = 1  # px the masks are dilated by before silhouettes are matched (splat tails)
    perceptual_weight: float = 0.2  # weight of LPIPS (weights given) or D-SSIM (otherwise)
    perceptual: str = "auto"  # auto (LPIPS if lpips_weights, else D-SSIM) | lpips | dssim | none
    lpips_weights: str = ""  # local LPIPS state dict or folder (AlexNet features + lin layers), see losses.py
    rigidity_weight: float = 0.2  # neighbouring control-point transforms agree (ARAP-like, on |delta|^2 / diag^2)
    local_weight: float = 0.02  # L1-like prior on the local (DeformMLP) motion: facial motion is sparse
    temporal_weight: float = 0.02  # adjacent frames' control-point motion is smooth
    view_residual_weight: float = 1.0  # the view-dependent part of the deformation stays small
    refine_weight: float = 0.01  # RefineMLP offsets stay small (appearance, not geometry)


@dataclass
class TrackConfig:
    # weight of the optical-flow vertex-track term, whose errors count in pixels of a 128 px image at every training
    # resolution (0 = the paper's loss alone)
    track_weight: float = 0.05
    track_refresh: int = 20  # steps between refreshes of the per-view rest pose the term measures motion from
    track_delta: float = 0.008  # Huber transition of the term, fraction of the image's longer side (1 px at 128)
    track_fb: float = 0.008  # forward-backward flow round-trip tolerance of a valid track, same unit
    track_min_texture: float = 0.001  # structure-tensor min eigenvalue from which a track start is "textured"
    track_flat_weight: float = 1.0  # weight of untextured tracks in the joint stage (the warm-up uses textured ones)
    # joint stage: the model may go up to this many times a track's non-rigid motion further along it at no cost
    # (flow carries 0.2-0.8 of a blink's or smile's motion: benchmarks/track_accuracy.py); 0 = plain Huber
    track_slack: float = 1.0
    track_chain: bool = True  # also chain the flow frame to frame, used where the direct 0 -> t flow fails
    track_agree: float = 0.012  # the direct track is kept within this of the chained one, same unit (1.5 px)
    track_flow_size: int = 256  # px: the flow runs on the training images upsampled to this longer side (0 = as is)
    track_blur: float = 0.0055  # Gaussian blur sigma of the flow's input images, same unit (0.7 px at 128)
    # Vertices an expression-basis blink shape moves downwards by more than this fraction of its largest motion (the
    # upper lids) get no track term: the flow holds a closing lid back (0 = tracks everywhere)
    track_release_lids: float = 0.1
    # joint-stage fractions at which the tracks are measured again as the model's motion plus the flow from its render
    # to the input frame: smiles gain on every character, blinks lose a little (docs/VCDGS_NOTES.md); () = never
    track_refit: tuple[float, ...] = (0.6,)
    # only tracks whose non-rigid motion (less the model's head motion) is below this are measured again, fraction of
    # the image's longer side (2 px at 128): the first flow follows large motion (clean mean 0.423 -> 0.411 with it)
    track_refit_below: float = 0.016


@dataclass
class HiddenPartsConfig:
    hidden_pick: bool = True  # parts no view sees at rest (teeth) may take a seen cluster's motion, picked by render
    hidden_pick_clusters: int = 8  # k-means clusters of the seen vertices' trajectories: the candidate motions
    hidden_pick_views: int = 5  # training views the renders are compared at (the canonical one and 4 around it)
    hidden_pick_min_vertices: int = 20  # smaller hidden parts keep their own motion
    hidden_pick_side_fraction: float = 0.9  # a part lies on one side of the opening when this share of it does
    hidden_pick_even: float = 0.7  # parts spread evenly across the opening (neither side above this) form one group
    hidden_pick_closed_rigid: bool = True  # where nothing opens, hidden parts take the head's robust rigid motion


@dataclass
class OutputConfig:
    output_smoothing: int = 4  # Laplacian smoothing steps on each output frame's non-rigid displacement (0 = raw)


@dataclass
class RuntimeConfig:
    seed: int = 0  # every random choice (sampling, initialisation) derives from it
    device: str = "auto"  # auto (cuda if available) | cpu | cuda | cuda:N
    compile: bool = False  # torch.compile the step's deformation and losses (the rasterizer stays eager)
    cuda_graphs: bool = False  # with compile, on CUDA: replay the compiled graphs as CUDA graphs (H200: 15 -> 8 ms)
    threads: int = 2  # torch CPU threads; fixed, so that one config gives the same numbers everywhere (0 = torch's)
    checkpoint_every: int = 200  # steps between resumable checkpoints (0 = never)


SECTIONS = {
    "data": DataConfig,
    "static_fit": StaticFitConfig,
    "control_points": ControlPointsConfig,
    "model": ModelConfig,
    "optim": OptimConfig,
    "loss": LossConfig,
    "tracks": TrackConfig,
    "hidden_parts": HiddenPartsConfig,
    "output": OutputConfig,
    "runtime": RuntimeConfig,
}
# field name -> its section (field names are unique across the tree)
FIELD_SECTION = {name: section for section, cls in SECTIONS.items() for name in cls.__dataclass_fields__}


@dataclass
class VCDGSConfig:
    method: str = "full"  # full | no_view | no_refine | no_lbs | no_global (the paper's ablations)
    data: DataConfig = field(default_factory=DataConfig)  # training images
    static_fit: StaticFitConfig = field(default_factory=StaticFitConfig)  # the Gaussians of the static mesh
    control_points: ControlPointsConfig = field(default_factory=ControlPointsConfig)  # LBS control points
    model: ModelConfig = field(default_factory=ModelConfig)  # the networks
    optim: OptimConfig = field(default_factory=OptimConfig)  # steps, schedule, learning rates
    loss: LossConfig = field(default_factory=LossConfig)  # image loss terms and regularisers
    tracks: TrackConfig = field(default_factory=TrackConfig)  # the optical-flow vertex-track term (ours)
    hidden_parts: HiddenPartsConfig = field(default_factory=HiddenPartsConfig)  # motion of parts no view sees
    output: OutputConfig = field(default_factory=OutputConfig)  # the per-frame meshes
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)  # seed, device, threads, checkpoints

    def __post_init__(self):
        self.data.holdout_views = tuple(self.data.holdout_views)
        self.model.expression_shapes = tuple(self.model.expression_shapes)
        self.optim.expression_pick = tuple(self.optim.expression_pick)
        self.tracks.track_refit = tuple(sorted(self.tracks.track_refit))

    def replace(self, **fields) -> "VCDGSConfig":
        """A copy with ``fields`` changed: any field of the tree by its name (``knn=4``) or ``method``.
        UserError names an unknown field."""
        bad = [k for k in fields if k != "method" and k not in FIELD_SECTION]
        if bad:
            raise UserError(f"unknown VCDGS option(s): {', '.join(bad)}")
        by_section: dict[str, dict] = {}
        for name, value in fields.items():
            if name != "method":
                by_section.setdefault(FIELD_SECTION[name], {})[name] = value
        # every section copied, changed or not: a copy never shares a mutable section with its source (a preset)
        sections = {sec: replace(getattr(self, sec), **by_section.get(sec, {})) for sec in SECTIONS}
        return replace(self, **sections, **({"method": fields["method"]} if "method" in fields else {}))

    def flat(self) -> dict:
        """Every field by name, ``method`` included: {name: value} (the tree's leaves)."""
        out = {"method": self.method}
        for section in SECTIONS:
            out.update(asdict(getattr(self, section)))
        return out

    def to_dict(self) -> dict:
        """The tree as plain JSON types: {"method": ..., section: {field: value}}."""
        d = asdict(self)
        d["data"]["holdout_views"] = list(self.data.holdout_views)
        d["model"]["expression_shapes"] = list(self.model.expression_shapes)
        d["optim"]["expression_pick"] = list(self.optim.expression_pick)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "VCDGSConfig":
        """Inverse of ``to_dict`` (a checkpoint's or a job's config); UserError for unknown sections or fields."""
        unknown = [k for k in d if k != "method" and k not in SECTIONS]
        if unknown:
            raise UserError(f"unknown VCDGS config section(s): {', '.join(unknown)}")
        flat = {k: v for sec in SECTIONS for k, v in (d.get(sec) or {}).items()}
        return cls().replace(method=d.get("method", "full"), **flat)

    def validate(self) -> "VCDGSConfig":
        if self.method not in METHODS:
            raise UserError(f"unknown method {self.method!r}; use one of {', '.join(METHODS)}")
        if self.data.resolution < 16:
            raise UserError(f"resolution {self.data.resolution} is too small (>= 16 px)")
        cp = self.control_points
        if cp.num_control_points < 1 or cp.knn < 1:
            raise UserError("num_control_points and knn must be >= 1")
        if self.loss.perceptual not in ("auto", "lpips", "dssim", "none"):
            raise UserError(f"perceptual must be auto|lpips|dssim|none, got {self.loss.perceptual!r}")
        if self.static_fit.static_shading not in ("auto", "unlit", "lambert"):
            raise UserError(f"static_shading must be auto|unlit|lambert, got {self.static_fit.static_shading!r}")
        if self.static_fit.max_face_gaussians < 0:
            raise UserError(
                f"max_face_gaussians must be >= 0 (0 = every triangle), got {self.static_fit.max_face_gaussians}"
            )
        o = self.optim
        if o.iterations < 1 or o.global_iters < 0 or o.batch_size < 1:
            raise UserError("iterations and batch_size must be >= 1, global_iters >= 0")
        if any(not 0.0 <= f < 1.0 for f in o.expression_pick) or o.expression_pick_views < 1:
            raise UserError(
                f"expression_pick must be fractions in [0, 1) of the joint stage, got {o.expression_pick}; "
                "expression_pick_views >= 1"
            )
        if not self.model.splat_lowpass >= 0:  # NaN too
            raise UserError(f"splat_lowpass must be >= 0 px^2, got {self.model.splat_lowpass}")
        from t2bs.face.arkit import ARKIT_NAMES

        unknown = [n for n in self.model.expression_shapes if n not in ARKIT_NAMES]
        if unknown:
            raise UserError(
                f"expression_shapes: {', '.join(unknown)} not ARKit shape names (e.g. eyeBlinkLeft, jawOpen)"
            )
        if self.runtime.cuda_graphs and not self.runtime.compile:
            raise UserError("cuda_graphs replays the compiled step: set compile=true with it")
        h = self.hidden_parts
        if h.hidden_pick_clusters < 1 or h.hidden_pick_views < 1:
            raise UserError("hidden_pick_clusters and hidden_pick_views must be >= 1")
        self._check_ranges()
        return self

    # Floats that must be > 0 (a zero learning rate or Huber width trains nothing / divides by 0).
    _POSITIVE = (
        "static_lr",
        "lr_deform",
        "lr_global",
        "lr_refine",
        "lr_expression",
        "lr_final_ratio",
        "lr_global_joint",
        "huber_delta",
        "flatness",
        "track_delta",
    )
    _FRACTIONS = (
        "canonical_fraction",
        "lr_final_ratio",
        "lr_global_joint",
        "hidden_pick_side_fraction",
        "hidden_pick_even",
        "track_release_lids",
        "track_refit_below",
    )  # <= 1

    def _check_ranges(self) -> None:
        """Every number finite and in range: NaN or a negative count from --set would otherwise train
        NaN or crash deep inside (issue 39). Counts and weights are >= 0; the seed may be any int."""
        for name, value in self.flat().items():
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
        if any(not 0.0 <= f <= 1.0 for f in self.tracks.track_refit):
            raise UserError(f"track_refit {list(self.tracks.track_refit)}: joint-stage fractions between 0 and 1")
        if any(v < 0 for v in self.data.holdout_views):
            raise UserError(f"holdout_views {list(self.data.holdout_views)}: view indices are >= 0")
        device = self.runtime.device
        if device not in ("auto", "cpu", "cuda") and not device.startswith("cuda:"):
            raise UserError(f"device must be auto, cpu or cuda, got {device!r}")

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
    "paper": VCDGSConfig().replace(
        resolution=512,
        static_iters=2000,
        num_control_points=2000,
        hidden=256,
        depth=6,
        refine_hidden=64,
        refine_depth=3,
        pos_freqs=8,
        time_freqs=6,
        iterations=60000,
        global_iters=3000,
        batch_size=4,
        pyramid_levels=4,
        max_face_gaussians=0,
        splat_lowpass=0.3,  # 3DGS's; at 512 px its blur is a quarter as wide against the face (not measured otherwise)
        checkpoint_every=2000,
        device="auto",
        # a step of ~2300 small kernels is launch-bound on a GPU: compiled and replayed as CUDA graphs its joint step
        # takes 7.9 ms instead of 15.3 (compiled) on an H200 and 47.5 (eager) on an H100 (docs/BENCHMARKS.md)
        compile=True,
        cuda_graphs=True,
        threads=0,
        time_budget_s=0.0,
        track_refit=(),  # not measured at 512 px or on a GPU yet (its flows run on the CPU: 416 at 512 px a refit)
    ),
}


def preset(name: str, **overrides) -> VCDGSConfig:
    """A copy of the named preset with ``overrides`` (fields by name) applied and validated (UserError for
    unknown names or bad values)."""
    if name not in PRESETS:
        raise UserError(f"unknown preset {name!r}; use one of {', '.join(PRESETS)}")
    return PRESETS[name].replace(**overrides).validate()


def iteration_overrides(preset_name: str, iterations: int) -> dict:
    """The fields a step count other than the preset's sets (the CLIs' ``--iterations``; 0 = the preset's): the
    steps, and the warm-up shortened to min(the preset's, a fifth of them). UserError for an unknown preset."""
    if not iterations:
        return {}
    return {"iterations": iterations, "global_iters": min(preset(preset_name).optim.global_iters, iterations // 5)}


_TRUE, _FALSE = ("1", "true", "yes", "on"), ("0", "false", "no", "off")


def _parse_value(name: str, kind, text: str):
    """``text`` as a value of the field type ``kind`` (int, float, bool, str, tuple[int, ...] or tuple[str, ...])."""
    try:
        if kind is bool and text.lower() in _TRUE + _FALSE:
            return text.lower() in _TRUE
        if kind in (int, float, str):
            return kind(text)
        if typing.get_origin(kind) is tuple:
            item = typing.get_args(kind)[0]
            return tuple(item(x.strip()) for x in text.split(",") if x.strip())
    except ValueError:
        pass
    shown = text if len(text) <= 40 else text[:40] + f"... ({len(text)} characters)"
    raise UserError(f"VCDGS option {name}={shown!r}: not a valid {getattr(kind, '__name__', str(kind))}")


def parse_options(items: typing.Iterable[str]) -> dict:
    """``["knn=4", "hidden_pick=true", "holdout_views=4,10"]`` -> {field: typed value} overrides of VCDGSConfig
    (the CLI's ``--set``): any field by name or as ``section.field``, the value read by its type (bool: true/false, 1/0, yes/no, on/off;
    tuples: comma-separated). UserError on a malformed item, an unknown field or a value of the wrong type."""
    kinds = {"method": str}
    for cls in SECTIONS.values():
        kinds.update(typing.get_type_hints(cls))
    out = {}
    for item in items:
        name, sep, text = item.partition("=")
        name = name.strip()
        section, dot, leaf = name.rpartition(".")
        if dot and (section not in SECTIONS or FIELD_SECTION.get(leaf) != section):
            raise UserError(f"--set {item!r}: no VCDGS option {name!r} (see t2bs.recon.config: section.field or field)")
        name = leaf if dot else name
        if not sep or not name:
            raise UserError(f"--set {item!r}: expected KEY=VALUE, e.g. knn=4")
        if name not in kinds:
            raise UserError(
                f"--set {item!r}: no VCDGS option {name!r} (the fields of the sections in t2bs.recon.config)"
            )
        out[name] = _parse_value(name, kinds[name], text.strip())
    return out


__all__ = ["VCDGSConfig", "PRESETS", "METHODS", "SECTIONS", "preset", "parse_options", "iteration_overrides"]
