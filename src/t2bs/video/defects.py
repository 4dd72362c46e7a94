"""Simulated defects of 4D video generators (paper §3.1.2, §4.4 and the appendix protocol).

A 4D video model (SV4D, 4Real-Video) gets the canonical fixed-view video right, because it is
its input, and the other views approximately: the shape seen from the side does not quite
agree with the front view (no common 3D geometry, so no epipolar consistency), colours and
shading drift between views and over time, side views are blurrier the further they turn, and
frames flicker. Each defect here has a strength knob (0 = clean, 1 = "paper-like"); all draw
from a generator seeded per (seed, defect, view, frame), so a grid is reproducible. The
canonical view is never touched.

- geometry: a smooth, low-frequency displacement field (random Fourier features over the rest
  shape), different per view, fixed over time, growing with |azimuth|; its largest vertex
  offset is ``geometry_fraction`` (3 %) of the bbox diagonal at strength 1 and |azimuth| 60.
- color: per-view brightness gain, a small per-channel tint and bias, plus a slow drift over time.
- lighting: a per-(view, time) light direction that reshades the render through its normals.
- texture_noise: the appendix protocol: the texture (or vertex colours) multiplied by
  U(1 - s/2, 1 + s/2) per texel (s = 1: U(0.5, 1.5)), clamped to [0, 1], redrawn every frame,
  the same across the non-canonical views of a frame.
- blur: Gaussian blur whose sigma grows linearly with |azimuth| (SV4D-like soft side views).
- flicker: an independent brightness jump per (view, time).
"""

from __future__ import annotations

import zlib
from dataclasses import asdict, dataclass, fields, replace

import numpy as np

from t2bs.errors import UserError


@dataclass
class DefectConfig:
    geometry: float = 0.0  # strength of the view-dependent shape distortion (0 = views agree)
    color: float = 0.0  # strength of per-(view, time) colour gain/bias
    lighting: float = 0.0  # strength of per-(view, time) lighting change
    texture_noise: float = 0.0  # texture x U(1 - s/2, 1 + s/2) per texel per frame (1 = appendix's U(0.5, 1.5))
    blur: float = 0.0  # strength of blur growing with |azimuth|
    flicker: float = 0.0  # strength of frame-to-frame brightness jumps
    geometry_fraction: float = 0.03  # largest offset / bbox diagonal at strength 1, |azimuth| = max
    geometry_cycles: float = 1.0  # spatial frequency of the distortion, cycles per bbox diagonal
    color_gain: float = 0.08  # std of the brightness gain (all channels) at strength 1
    color_tint: float = 0.03  # std of the per-channel gain (hue shift) at strength 1
    color_bias: float = 0.02  # std of the per-channel bias at strength 1
    light_mix: float = 0.5  # share of the colour that the moving light reshades at strength 1
    blur_sigma: float = 0.006  # blur sigma / image size at strength 1 and |azimuth| = 60 deg
    flicker_std: float = 0.06  # std of the brightness factor per frame at strength 1
    seed: int = 0  # every draw is derived from this

    @property
    def is_clean(self) -> bool:
        return all(getattr(self, k) == 0 for k in STRENGTHS)


STRENGTHS = ("geometry", "color", "lighting", "texture_noise", "blur", "flicker")

PRESETS: dict[str, dict[str, float]] = {
    "clean": {k: 0.0 for k in STRENGTHS},
    "mild": {"geometry": 0.35, "color": 0.35, "lighting": 0.3, "texture_noise": 0.2, "blur": 0.4, "flicker": 0.3},
    "paper": {k: 1.0 for k in STRENGTHS},
}
PRESET_ALIASES = {"paper-like": "paper", "none": "clean"}


def _strengths(key: str) -> dict[str, float] | None:
    """The strengths a preset name sets, or None for an unknown name. One defect at a time, to find which one costs a
    reconstruction what (docs/VCDGS_NOTES.md, "Which defect"): ``only_<defect>`` is that defect at its paper strength
    alone, ``paper_without_<defect>`` the paper preset less it."""
    if key in PRESETS:
        return PRESETS[key]
    paper = PRESETS["paper"]
    alone, without = key.removeprefix("only_"), key.removeprefix("paper_without_")
    if alone != key and alone in STRENGTHS:
        return {k: paper[k] if k == alone else 0.0 for k in STRENGTHS}
    if without != key and without in STRENGTHS:
        return {k: 0.0 if k == without else paper[k] for k in STRENGTHS}
    return None


def preset(name: str, seed: int = 0, **overrides: float) -> DefectConfig:
    """DefectConfig for ``clean``, ``mild`` or ``paper`` (alias ``paper-like``), ``only_<defect>`` or
    ``paper_without_<defect>`` (<defect>: a name in STRENGTHS), with overrides."""
    key = PRESET_ALIASES.get(name.lower(), name.lower())
    strengths = _strengths(key)
    if strengths is None:
        raise UserError(
            f"unknown defect preset {name!r}; valid: {', '.join(PRESETS)}, only_<defect>, paper_without_<defect> "
            f"(<defect>: {', '.join(STRENGTHS)})"
        )
    names = {f.name for f in fields(DefectConfig)}
    bad = [k for k in overrides if k not in names]
    if bad:
        raise UserError(f"unknown defect setting {bad[0]!r}; valid: {', '.join(sorted(names))}")
    cfg = replace(DefectConfig(seed=seed), **{**strengths, **overrides})
    for k in STRENGTHS:
        if getattr(cfg, k) < 0:
            raise UserError(f"defect strength {k} must be >= 0, got {getattr(cfg, k)}")
    return cfg


def config_dict(cfg: DefectConfig) -> dict:
    return asdict(cfg)


def _rng(cfg: DefectConfig, *key) -> np.random.Generator:
    return np.random.default_rng([cfg.seed & 0xFFFFFFFF, zlib.crc32("|".join(map(str, key)).encode())])


def _az_factor(azimuth_deg: float, max_azimuth: float = 60.0) -> float:
    return min(abs(azimuth_deg) / max_azimuth, 1.5)


# --------------------------------------------------------------------------------------------
# Geometry


def view_distortion(rest: np.ndarray, view: int, azimuth_deg: float, cfg: DefectConfig, terms: int = 6) -> np.ndarray:
    """[N, 3] offsets for one view: smooth in space (low-frequency Fourier features), fixed in time.

    Evaluated on the rest vertices so every vertex keeps its offset while the face moves; the
    field differs per view so no single 3D shape explains all views.
    """
    if cfg.geometry == 0:
        return np.zeros_like(rest, dtype=np.float32)
    rng = _rng(cfg, "geometry", view)
    lo, hi = rest.min(0), rest.max(0)
    diag = float(np.linalg.norm(hi - lo))
    x = (rest - (lo + hi) / 2) / diag  # [N, 3] about unit size
    freq = rng.normal(0.0, cfg.geometry_cycles, (terms, 3)) * 2 * np.pi  # [K, 3]
    phase = rng.uniform(0, 2 * np.pi, terms)  # [K]
    amp = rng.normal(0.0, 1.0, (terms, 3))  # [K, 3] displacement direction per term
    field = np.sin(x @ freq.T + phase) @ amp  # [N, 3]
    field -= field.mean(0)  # no net translation: that would be a camera error, not a shape error
    peak = float(np.linalg.norm(field, axis=1).max())
    if peak <= 0:
        return np.zeros_like(rest, dtype=np.float32)
    # Views near the input view stay closer to it (a generator is anchored there).
    scale = cfg.geometry * cfg.geometry_fraction * diag * (0.25 + 0.75 * _az_factor(azimuth_deg))
    return (field * (scale / peak)).astype(np.float32)


# --------------------------------------------------------------------------------------------
# Texture noise (appendix protocol)


def noisy_colors(base: np.ndarray, frame: int, cfg: DefectConfig) -> np.ndarray:
    """``base`` texture [H, W, 3] uint8 or vertex colours [N, 3] float, times U(1 - s/2, 1 + s/2)
    per texel/vertex, clamped; one draw per frame, shared by the views of that frame."""
    if cfg.texture_noise == 0:
        return base
    rng = _rng(cfg, "texture", frame)
    s = cfg.texture_noise
    noise = rng.uniform(1 - s / 2, 1 + s / 2, base.shape[:-1] + (1,)).astype(np.float32)
    if base.dtype == np.uint8:
        return np.clip(base.astype(np.float32) * noise + 0.5, 0, 255).astype(np.uint8)
    return np.clip(base * noise, 0.0, 1.0).astype(np.float32)


# --------------------------------------------------------------------------------------------
# Image-space defects


def _smooth_series(rng: np.random.Generator, frames: int, cycles: float = 1.0) -> np.ndarray:
    """[T] smooth random series with std about 1."""
    u = np.linspace(0, 1, frames)
    out = np.zeros(frames)
    for _ in range(3):
        out += np.sin(2 * np.pi * rng.uniform(0.3, cycles) * u + rng.uniform(0, 2 * np.pi))
    return out / np.sqrt(1.5)


@dataclass
class ViewAppearance:
    gain: np.ndarray  # [T, 3] colour gain per frame
    bias: np.ndarray  # [T, 3] colour bias per frame
    light_dir: np.ndarray  # [T, 3] unit world light direction per frame
    light_mix: float  # share of the colour reshaded by that light
    flicker: np.ndarray  # [T] brightness factor per frame
    blur_sigma: float  # pixels


def view_appearance(
    view: int, azimuth_deg: float, frames: int, size: int, camera_position: np.ndarray, cfg: DefectConfig
) -> ViewAppearance:
    """The image-space defect parameters of one view over time (deterministic per seed and view)."""
    rng = _rng(cfg, "appearance", view)
    # A view-level offset plus a slow drift over time; brightness dominates, hue shifts are small.
    luma = cfg.color_gain * (rng.normal(0, 1) + 0.5 * _smooth_series(rng, frames))[:, None]  # [T, 1]
    tint = cfg.color_tint * (
        rng.normal(0, 1, (1, 3)) + 0.5 * np.stack([_smooth_series(rng, frames) for _ in range(3)], 1)
    )
    gain = 1.0 + cfg.color * (luma + tint)  # [T, 3]
    bias = (
        cfg.color
        * cfg.color_bias
        * (rng.normal(0, 1, (1, 3)) + 0.5 * np.stack([_smooth_series(rng, frames) for _ in range(3)], 1))
    )
    # A light roughly from the camera side, wandering over time: shading differs per view and frame.
    to_cam = np.asarray(camera_position, float) / max(np.linalg.norm(camera_position), 1e-9)
    base = to_cam + rng.normal(0, 0.6, 3)
    drift = np.stack([_smooth_series(rng, frames, 1.5) for _ in range(3)], 1) * 0.35  # [T, 3]
    light = base[None] + drift
    light /= np.linalg.norm(light, axis=1, keepdims=True)
    flicker = 1.0 + cfg.flicker * cfg.flicker_std * rng.normal(0, 1, frames)
    sigma = cfg.blur * cfg.blur_sigma * size * _az_factor(azimuth_deg)
    return ViewAppearance(
        gain.astype(np.float32),
        bias.astype(np.float32),
        light.astype(np.float32),
        float(np.clip(cfg.lighting * cfg.light_mix, 0, 0.9)),
        flicker.astype(np.float32),
        float(sigma),
    )


def apply_appearance(rgb: np.ndarray, normal: np.ndarray, mask: np.ndarray, app: ViewAppearance, t: int) -> np.ndarray:
    """One rendered frame [H, W, 3] float -> defective frame (foreground recoloured, then blurred)."""
    out = rgb.astype(np.float32).copy()
    fg = mask
    if app.light_mix > 0:
        lam = np.clip(normal @ app.light_dir[t], 0.0, 1.0)  # [H, W]
        # Mean-preserving about half-lit: brighter where the light hits, darker elsewhere.
        shade = (1 - app.light_mix) + app.light_mix * (0.45 + 1.1 * lam)
        out[fg] *= shade[fg, None]
    out[fg] = out[fg] * (app.gain[t] * app.flicker[t]) + app.bias[t]
    out = np.clip(out, 0.0, 1.0)
    if app.blur_sigma > 0.05:
        from scipy.ndimage import gaussian_filter

        out = gaussian_filter(out, sigma=(app.blur_sigma, app.blur_sigma, 0), mode="nearest")
    return out
