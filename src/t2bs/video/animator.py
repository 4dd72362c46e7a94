"""Offline stand-in for the image-to-video model: expression prompt -> morph-target time curves.

No video model weights can be used offline, so the character animates itself with its own
rig, which also gives the ground truth the benchmark needs. An expression is written in terms
of abstract *controls* (jaw_open, blink_left, smile_right, brow_up_left, look_up, happy, ...),
each a curve over normalised time u in [0, 1]. ``morph_drivers`` then maps the controls onto
whatever morph targets the mesh has:

- procedural characters (their rig, character/procedural.py): jaw_open, blink_left/right, smile, frown, brow_up,
  ear_wave, tongue_out, cheek_puff, look_left/right/up/down;
- ARKit blendshapes (facecap.glb): jawOpen, eyeBlink_L/R, mouthSmile_L/R, browInnerUp, ...; also
  Apple's spelling eyeBlinkLeft / mouthSmileRight (what ``t2bs autorig`` writes, issue 34);
- VRM 0.x / 1.0 presets (vipe_hero_head.glb): a e i o u, blink_l/r, joy, angry, sorrow, fun,
  look*; aa ih ou ee oh, blinkLeft/Right, happy, sad, relaxed, surprised;
- the turtle's names (turtle.glb): mouthOpen, eyeLeftClose/eyeRightClose, smileLeft/Right,
  mouthRound, eyeBrowLeftUp/Down, ...

Left/right: controls name the character's own side, which is +X in the canonical frame. Asset
names are not always right (the turtle's eyeBrowLeft* moves its -X brow), so each left/right
pair is checked against the geometry and swapped when its "left" moves the -X side.

Like a video model, the animator mixes expressions (a blink while talking), varies timing and
strength with the seed, and adds a small rigid head motion (turn / nod / tilt) applied to all
vertices. Frame 0 is always the neutral asset: in the paper the video starts from the frontal
render of the static mesh (I[0, 0]).
"""

from __future__ import annotations

import re
import zlib
from dataclasses import dataclass, field

import numpy as np

from t2bs.errors import UserError
from t2bs.geometry.curves import smoothstep
from t2bs.geometry.mesh import Mesh
from t2bs.video.prompts import EXPRESSIONS

# Morph name (lower case) -> [(control, gain)]: how much each control drives that morph.
MORPH_DRIVERS: dict[str, list[tuple[str, float]]] = {
    # Procedural rig (character/procedural.py, issue 4). Symmetric morphs take half of each side.
    "jaw_open": [("jaw_open", 1.0)],
    "blink_left": [("blink_left", 1.0)],
    "blink_right": [("blink_right", 1.0)],
    "smile": [("smile_left", 0.5), ("smile_right", 0.5)],
    "frown": [("frown", 1.0), ("lip_press", 0.4)],
    "brow_up": [("brow_up_left", 0.5), ("brow_up_right", 0.5), ("worry", 0.5)],
    "ear_wave": [("ear_wave", 1.0)],
    "tongue_out": [("tongue_out", 1.0)],
    "cheek_puff": [("cheek_puff", 1.0)],
    "look_left": [("look_left", 1.0)],
    "look_right": [("look_right", 1.0)],
    "look_up": [("look_up", 1.0)],
    "look_down": [("look_down", 1.0)],
    # ARKit (Apple face tracking names; facecap.glb). _L is the character's left.
    "jawopen": [("jaw_open", 1.0)],
    "jawforward": [("jaw_forward", 1.0)],
    "eyeblink_l": [("blink_left", 1.0)],
    "eyeblink_r": [("blink_right", 1.0)],
    "eyesquint_l": [("squint", 0.8)],
    "eyesquint_r": [("squint", 0.8)],
    "eyewide_l": [("eye_wide", 1.0)],
    "eyewide_r": [("eye_wide", 1.0)],
    "eyelookout_l": [("look_left", 1.0)],
    "eyelookin_r": [("look_left", 1.0)],
    "eyelookin_l": [("look_right", 1.0)],
    "eyelookout_r": [("look_right", 1.0)],
    "eyelookup_l": [("look_up", 1.0)],
    "eyelookup_r": [("look_up", 1.0)],
    "eyelookdown_l": [("look_down", 1.0)],
    "eyelookdown_r": [("look_down", 1.0)],
    "browinnerup": [("worry", 1.0), ("brow_up_left", 0.5), ("brow_up_right", 0.5)],
    "browouterup_l": [("brow_up_left", 1.0)],
    "browouterup_r": [("brow_up_right", 1.0)],
    "browdown_l": [("brow_down_left", 1.0)],
    "browdown_r": [("brow_down_right", 1.0)],
    "cheekpuff": [("cheek_puff", 1.0)],
    "cheeksquint_l": [("squint", 0.5), ("smile_left", 0.3)],
    "cheeksquint_r": [("squint", 0.5), ("smile_right", 0.3)],
    "nosesneer_l": [("sneer", 1.0)],
    "nosesneer_r": [("sneer", 1.0)],
    "mouthsmile_l": [("smile_left", 1.0)],
    "mouthsmile_r": [("smile_right", 1.0)],
    "mouthdimple_l": [("smile_left", 0.3)],
    "mouthdimple_r": [("smile_right", 0.3)],
    "mouthfrown_l": [("frown", 1.0)],
    "mouthfrown_r": [("frown", 1.0)],
    "mouthfunnel": [("mouth_round", 0.8)],
    "mouthpucker": [("mouth_round", 0.4), ("pucker", 1.0)],
    "mouthstretch_l": [("mouth_wide", 0.7)],
    "mouthstretch_r": [("mouth_wide", 0.7)],
    "mouthpress_l": [("lip_press", 1.0)],
    "mouthpress_r": [("lip_press", 1.0)],
    "mouthrollupper": [("lip_press", 0.4)],
    "mouthrolllower": [("lip_press", 0.4)],
    "mouthshruglower": [("frown", 0.4), ("lip_press", 0.3)],
    "mouthupperup_l": [("sneer", 0.5), ("mouth_wide", 0.2)],
    "mouthupperup_r": [("sneer", 0.5), ("mouth_wide", 0.2)],
    "mouthlowerdown_l": [("mouth_wide", 0.4)],
    "mouthlowerdown_r": [("mouth_wide", 0.4)],
    "mouthleft": [("mouth_side_left", 1.0)],
    "mouthright": [("mouth_side_right", 1.0)],
    "tongueout": [("tongue_out", 1.0)],
    # The turtle's names (turtle.glb).
    "mouthopen": [("jaw_open", 1.0)],
    "mouthround": [("mouth_round", 1.0), ("pucker", 0.5)],
    "mouthnasty": [("sneer", 1.0), ("frown", 0.5)],
    "eyeleftclose": [("blink_left", 1.0)],
    "eyerightclose": [("blink_right", 1.0)],
    "smileleft": [("smile_left", 1.0)],
    "smileright": [("smile_right", 1.0)],
    "eyebrowleftup": [("brow_up_left", 1.0)],
    "eyebrowrightup": [("brow_up_right", 1.0)],
    "eyebrowleftdown": [("brow_down_left", 1.0)],
    "eyebrowrightdown": [("brow_down_right", 1.0)],
    # VRM 0.x blend shape presets (vipe_hero_head.glb).
    "a": [("jaw_open", 1.0)],
    "i": [("mouth_wide", 0.6)],
    "u": [("pucker", 1.0), ("mouth_round", 0.4)],
    "e": [("mouth_wide", 0.8)],
    "o": [("mouth_round", 1.0)],
    "blink_l": [("blink_left", 1.0)],
    "blink_r": [("blink_right", 1.0)],
    "joy": [("happy", 1.0)],
    "fun": [("smile_left", 0.5), ("smile_right", 0.5)],
    "sorrow": [("sad", 1.0)],
    "angry": [("angry", 1.0)],
    "lookleft": [("look_left", 1.0)],
    "lookright": [("look_right", 1.0)],
    "lookup": [("look_up", 1.0)],
    "lookdown": [("look_down", 1.0)],
    # VRM 1.0 expression presets.
    "aa": [("jaw_open", 1.0)],
    "ih": [("mouth_wide", 0.6)],
    "ou": [("pucker", 1.0), ("mouth_round", 0.4)],
    "ee": [("mouth_wide", 0.8)],
    "oh": [("mouth_round", 1.0)],
    "blinkleft": [("blink_left", 1.0)],
    "blinkright": [("blink_right", 1.0)],
    "happy": [("happy", 1.0)],
    "sad": [("sad", 1.0)],
    "relaxed": [("calm", 1.0)],
    "surprised": [("surprise", 1.0)],
}

# Morph pairs whose first member should move the character's left (+X) side.
SIDE_PAIRS = [
    ("blink_left", "blink_right"),
    ("eyeblink_l", "eyeblink_r"),
    ("eyeleftclose", "eyerightclose"),
    ("blink_l", "blink_r"),
    ("blinkleft", "blinkright"),
    ("mouthsmile_l", "mouthsmile_r"),
    ("smileleft", "smileright"),
    ("browouterup_l", "browouterup_r"),
    ("browdown_l", "browdown_r"),
    ("eyebrowleftup", "eyebrowrightup"),
    ("eyebrowleftdown", "eyebrowrightdown"),
    ("cheeksquint_l", "cheeksquint_r"),
    ("mouthdimple_l", "mouthdimple_r"),
]

# Words of a user-written expression -> built-in expressions it is animated as (offline only).
KEYWORDS: list[tuple[tuple[str, ...], str]] = [
    (("talk", "speak", "chat", "sing", "say"), "talking"),
    (("scream", "shout", "yell", "roar"), "screaming"),
    (("laugh", "giggl", "chuckl"), "laughing"),
    (("smirk",), "smirking"),
    (("smil", "grin"), "smiling"),
    (("close", "shut"), "closing the mouth"),
    (("yawn", "wide", "gape", "open"), "opening the mouth extremely wide"),
    (("blink",), "blinking"),
    (("wink", "tease", "teasing", "flirt"), "teasing the eyes"),
    (("look", "glanc", "gaz", "around"), "looking around"),
    (("ear",), "waving the ears"),
    (("tongue", "lick"), "tongue sticking out the mouth"),
    (("shak", "nod", "head"), "shaking the head"),
    (("sad", "cry", "sorrow", "unhappy"), "sad"),
    (("angr", "mad", "furious", "rage"), "angry"),
    (("chill", "relax", "calm", "sleep"), "chilling"),
    (("happy", "joy", "glad", "cheer"), "happy"),
    (("pensive", "think", "ponder"), "pensive"),
    (("confus", "puzzl", "wonder"), "confused"),
    (("disappoint", "sigh", "bored"), "disappointed"),
]


@dataclass
class AnimationConfig:
    frames: int = 16  # T, frames of the video (the paper's video models make 16-49)
    fps: float = 8.0  # frames per second of the time stamps (CogVideoX: 8)
    intensity: float = 1.0  # scale of every expression weight
    head_motion: float = 1.0  # scale of the rigid head motion (0 = none)


@dataclass
class Animation:
    expression: str  # what was animated
    times: np.ndarray  # [T] float32 seconds
    controls: dict[str, np.ndarray]  # abstract control -> [T] curve in [0, 1]
    names: list[str]  # [M] morph target names driven
    weights: np.ndarray  # [T, M] float32 morph weights
    head_angles: np.ndarray  # [T, 3] float32 yaw (turn to own left +), pitch (nod down +), roll, degrees
    pivot: np.ndarray  # [3] float32 centre of the head rotation (the neck)
    morphed: np.ndarray  # [T, N, 3] float32 vertices with morphs only (before the head motion)
    vertices: np.ndarray  # [T, N, 3] float32 ground truth: morphs + rigid head motion
    info: dict = field(default_factory=dict)  # fallbacks used, controls the mesh cannot show

    def weights_dict(self, t: int) -> dict[str, float]:
        return {n: float(w) for n, w in zip(self.names, self.weights[t])}


# ---------------------------------------------------------------------------------------------
# Curves over normalised time u in [0, 1]; all are 0 at u = 0 (frame 0 is the neutral asset).


def hold(u: np.ndarray, on: float, full: float, release: float, off: float) -> np.ndarray:
    """Trapezoid: rises on..full, holds, falls release..off (smooth edges)."""
    rise = smoothstep(0.0, 1.0, (u - on) / max(full - on, 1e-6))
    fall = 1.0 - smoothstep(0.0, 1.0, (u - release) / max(off - release, 1e-6)) if release < 1.0 else np.ones_like(u)
    return rise * fall


def bumps(u: np.ndarray, centres, width: float, amps=None) -> np.ndarray:
    """Sum of raised-cosine bumps of half-width ``width`` (peak 1 at each centre), clipped to 1."""
    out = np.zeros_like(u)
    amps = np.ones(len(centres)) if amps is None else amps
    for c, a in zip(centres, amps):
        d = np.abs(u - c) / width
        out = np.maximum(out, a * np.where(d < 1, 0.5 * (1 + np.cos(np.pi * np.minimum(d, 1))), 0.0))
    return out


def envelope(u: np.ndarray, ramp: float = 0.15) -> np.ndarray:
    """0 at u = 0 rising to 1 at ``ramp``: keeps frame 0 neutral under continuous motions."""
    return smoothstep(0.0, 1.0, u / ramp)


def wobble(u: np.ndarray, rng: np.random.Generator, cycles: float = 1.5, terms: int = 3) -> np.ndarray:
    """Smooth random signal in about [-1, 1], 0 at u = 0."""
    out = np.zeros_like(u)
    for _ in range(terms):
        f = rng.uniform(0.5, cycles)
        ph = rng.uniform(0, 2 * np.pi)
        out += np.sin(2 * np.pi * f * u + ph) - np.sin(ph)
    return envelope(u) * out / terms


class _Curves:
    """Accumulates control curves and head angles for one expression."""

    def __init__(self, frames: int, rng: np.random.Generator):
        self.T = frames
        self.u = np.linspace(0.0, 1.0, frames)  # [T]
        self.rng = rng
        self.c: dict[str, np.ndarray] = {}
        self.head = np.zeros((frames, 3))  # [T, 3] yaw, pitch, roll degrees

    def add(self, name: str, curve: np.ndarray, amp: float = 1.0) -> None:
        jitter = self.rng.uniform(0.85, 1.1)
        self.c[name] = np.maximum(self.c.get(name, 0.0), np.clip(amp * jitter * curve, 0.0, 1.0))

    def frame_u(self, lo: float, hi: float, n: int, min_gap: float) -> list[float]:
        """``n`` random times in [lo, hi], snapped to frames and at least ``min_gap`` apart, so a
        short event (a blink) reaches its peak exactly on a frame."""
        frames = np.arange(self.T)
        cand = frames[(self.u >= lo) & (self.u <= hi)]
        picks: list[int] = []
        for f in self.rng.permutation(cand):
            if all(abs(self.u[f] - self.u[p]) >= min_gap for p in picks):
                picks.append(int(f))
            if len(picks) == n:
                break
        return sorted(float(self.u[p]) for p in picks)

    def blink_width(self) -> float:
        # About 0.3 s at 8 fps for T = 49, never under 1.5 frames so a 16-frame video shows it.
        return max(1.5 / max(self.T - 1, 1), 0.04)

    def blinks(self, n: int, lo: float = 0.15, hi: float = 0.95, amount: float = 1.0, lag: bool = True) -> None:
        w = self.blink_width()
        centres = self.frame_u(lo, hi, n, 2.5 * w)
        if not centres:
            return
        both = bumps(self.u, centres, w)
        self.add("blink_left", both, amount)
        # Eyes close together; an occasional tiny lag of one eye reads as natural.
        self.add(
            "blink_right",
            both if not lag or self.rng.random() < 0.7 else bumps(self.u, [c + 0.3 * w for c in centres], w),
            amount,
        )

    def head_noise(self, yaw: float = 2.5, pitch: float = 2.0, roll: float = 1.0) -> None:
        for k, a in enumerate((yaw, pitch, roll)):
            self.head[:, k] += a * wobble(self.u, self.rng)


def _r(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def _program(expression: str, c: _Curves) -> None:
    """The expression's control curves (a hand-written stand-in for what a video model makes)."""
    u, rng = c.u, c.rng
    side = ("left", "right")[int(rng.integers(2))]
    other = "right" if side == "left" else "left"
    if expression == "talking":
        n = int(rng.integers(5, 9))
        centres = np.sort(rng.uniform(0.12, 0.95, n))
        c.add("jaw_open", bumps(u, centres, _r(rng, 0.06, 0.1), rng.uniform(0.35, 0.8, n)))
        c.add("mouth_round", bumps(u, centres[::2] + 0.02, 0.07, rng.uniform(0.2, 0.7, len(centres[::2]))))
        c.add("mouth_wide", bumps(u, centres[1::2] + 0.02, 0.07, rng.uniform(0.2, 0.6, len(centres[1::2]))))
        c.add("brow_up_left", bumps(u, [_r(rng, 0.3, 0.7)], 0.15), 0.4)
        c.add("brow_up_right", c.c["brow_up_left"])
        c.blinks(int(rng.integers(1, 3)))
        c.head_noise(4.0, 3.0, 1.5)
    elif expression == "screaming":
        on = _r(rng, 0.1, 0.25)
        h = hold(u, on, on + 0.15, 0.85, 1.0 + 0.2)
        c.add("jaw_open", h)
        c.add("mouth_wide", h, 0.8)
        c.add("brow_up_left", h, 0.8)
        c.add("brow_up_right", h, 0.8)
        c.add("eye_wide", h, 0.8)
        c.add("surprise", h, 0.6)
        c.head[:, 1] -= 8.0 * h  # head thrown back
        c.head_noise(3.0, 1.5, 1.0)
    elif expression == "laughing":
        on = _r(rng, 0.1, 0.2)
        h = hold(u, on, on + 0.15, 0.9, 1.2)
        cycles = _r(rng, 3.0, 5.0) if c.T >= 24 else _r(rng, 2.0, 3.0)
        ha = 0.5 + 0.5 * np.sin(2 * np.pi * cycles * u)
        c.add("jaw_open", h * (0.3 + 0.5 * ha))
        for s in ("left", "right"):
            c.add(f"smile_{s}", h)
        c.add("squint", h, 0.6)
        c.add("happy", h)
        c.head[:, 1] += h * (-4.0 + 3.0 * np.sin(2 * np.pi * cycles * u))  # bobbing, tilted back
        c.blinks(1, lo=0.5)
        c.head_noise(2.0, 1.0, 1.5)
    elif expression == "smiling":
        on = _r(rng, 0.1, 0.35)
        h = hold(u, on, on + _r(rng, 0.15, 0.3), 1.0, 1.0)
        for s in ("left", "right"):
            c.add(f"smile_{s}", h, 0.9)
        c.add("squint", h, 0.3)
        c.add("happy", h, 0.6)
        c.head[:, 2] += _r(rng, -4.0, 4.0) * h
        c.blinks(1)
        c.head_noise()
    elif expression == "smirking":
        on = _r(rng, 0.1, 0.3)
        h = hold(u, on, on + 0.2, 1.0, 1.0)
        c.add(f"smile_{side}", h, 0.95)
        c.add(f"smile_{other}", h, 0.1)
        c.add(f"brow_up_{side}", h, 0.5)
        c.add(f"brow_down_{other}", h, 0.3)
        c.add(f"mouth_side_{side}", h, 0.3)
        c.add("squint", h, 0.2)
        c.head[:, 2] += (4.0 if side == "left" else -4.0) * h
        c.blinks(1)
        c.head_noise()
    elif expression == "closing the mouth":
        a = _r(rng, 0.15, 0.3)
        c.add("jaw_open", hold(u, a - 0.1, a, a + 0.1, a + 0.3), _r(rng, 0.35, 0.6))
        h = hold(u, a + 0.25, a + 0.4, 1.0, 1.0)
        c.add("lip_press", h, 0.9)
        c.add("pucker", h, 0.3)
        c.add("frown", h, 0.35)
        c.head[:, 1] -= 3.0 * h  # chin raised
        c.blinks(1)
        c.head_noise()
    elif expression == "opening the mouth extremely wide":
        on = _r(rng, 0.1, 0.2)
        h = hold(u, on, on + _r(rng, 0.2, 0.3), 0.85, 1.1)
        c.add("jaw_open", h, 1.0)
        c.add("mouth_wide", h, 0.5)
        c.add("mouth_round", h, 0.3)
        c.add("brow_up_left", h, 0.6)
        c.add("brow_up_right", h, 0.6)
        c.add("eye_wide", h, 0.5)
        c.add("surprise", h, 0.8)
        c.head[:, 1] -= 5.0 * h
        c.head_noise(2.0, 1.0, 1.0)
    elif expression == "blinking":
        c.blinks(int(rng.integers(2, 4)) if c.T >= 16 else 2, lo=0.12)
        c.head_noise()
    elif expression == "teasing the eyes":
        a = _r(rng, 0.15, 0.3)
        wink = hold(u, a, a + 0.1, a + 0.3, a + 0.4)
        c.add(f"blink_{side}", wink)
        c.add(f"smile_{side}", wink, 0.6)
        c.add(f"brow_down_{side}", wink, 0.4)
        c.add(f"brow_up_{other}", wink, 0.5)
        b = a + 0.45
        if b + 0.15 < 1.0:  # a second, quicker wink with the other eye
            c.add(f"blink_{other}", bumps(u, [b + 0.08], 0.1))
        c.add("squint", hold(u, a, a + 0.1, 0.9, 1.0), 0.3)
        look = ("look_left", "look_right")[int(rng.integers(2))]
        c.add(look, hold(u, 0.1, 0.2, 0.9, 1.0), 0.6)
        c.head[:, 2] += (5.0 if side == "left" else -5.0) * wink
        c.head_noise()
    elif expression == "looking around":
        dirs = ["look_left", "look_right", "look_up", "look_down"]
        n = int(rng.integers(3, 5))
        starts = np.linspace(0.1, 0.85, n + 1)
        yaw = np.zeros_like(u)
        pitch = np.zeros_like(u)
        for k in range(n):
            d = dirs[int(rng.integers(4))] if k else dirs[int(rng.integers(2))]
            s, e = starts[k], starts[k + 1]
            h = hold(u, s, s + 0.06, e - 0.02, e + 0.04)
            c.add(d, h, _r(rng, 0.7, 1.0))
            sign = {"look_left": (1, 0), "look_right": (-1, 0), "look_up": (0, -1), "look_down": (0, 1)}[d]
            yaw += sign[0] * _r(rng, 8.0, 15.0) * h
            pitch += sign[1] * _r(rng, 4.0, 7.0) * h
        c.head[:, 0] += yaw  # the head follows the eyes
        c.head[:, 1] += pitch
        c.blinks(1)
        c.head_noise(1.0, 1.0, 1.0)
    elif expression == "waving the ears":
        cycles = _r(rng, 1.5, 3.0)
        wave = envelope(u, 0.2) * (0.5 - 0.5 * np.cos(2 * np.pi * cycles * u))
        c.add("ear_wave", wave)
        # What a video model does with a character whose ears cannot move: the brows wiggle.
        c.add("brow_up_left", wave, 0.35)
        c.add("brow_up_right", wave, 0.35)
        c.add("smile_left", hold(u, 0.2, 0.4, 1.0, 1.0), 0.25)
        c.add("smile_right", c.c["smile_left"])
        c.blinks(1)
        c.head_noise(2.0, 1.5, 2.0)
    elif expression == "tongue sticking out the mouth":
        on = _r(rng, 0.1, 0.25)
        h = hold(u, on, on + 0.15, 0.85, 1.1)
        t = hold(u, on + 0.08, on + 0.25, 0.8, 1.05)
        c.add("jaw_open", h, 0.55)
        c.add("tongue_out", t, 1.0)
        c.add("mouth_round", h, 0.3)
        c.add("squint", h, 0.4)
        c.add("smile_left", h, 0.2)
        c.add("smile_right", h, 0.2)
        c.head[:, 1] += 3.0 * h
        c.blinks(1)
        c.head_noise()
    elif expression == "shaking the head":
        cycles = _r(rng, 1.5, 2.5)
        amp = _r(rng, 14.0, 22.0)
        c.head[:, 0] += amp * envelope(u, 0.15) * np.sin(2 * np.pi * cycles * u)
        h = hold(u, 0.15, 0.3, 1.0, 1.0)
        c.add("frown", h, 0.5)
        c.add("lip_press", h, 0.5)
        c.add("brow_down_left", h, 0.4)
        c.add("brow_down_right", h, 0.4)
        c.blinks(1)
        c.head_noise(0.5, 1.5, 1.0)
    elif expression == "sad":
        h = hold(u, _r(rng, 0.1, 0.2), _r(rng, 0.4, 0.55), 1.0, 1.0)
        c.add("frown", h, 0.85)
        c.add("worry", h, 0.8)
        c.add("sad", h)
        c.add("look_down", h, 0.5)
        c.add("squint", h, 0.2)
        c.add("blink_left", h, 0.25)
        c.add("blink_right", h, 0.25)
        c.head[:, 1] += 7.0 * h
        c.blinks(1, lo=0.5)
        c.head_noise(1.5, 1.0, 1.0)
    elif expression == "angry":
        h = hold(u, _r(rng, 0.1, 0.2), _r(rng, 0.3, 0.45), 1.0, 1.0)
        c.add("brow_down_left", h)
        c.add("brow_down_right", h)
        c.add("frown", h, 0.5)
        c.add("sneer", h, 0.7)
        c.add("angry", h)
        c.add("squint", h, 0.5)
        c.add("lip_press", h, 0.4)
        c.add("jaw_open", bumps(u, [_r(rng, 0.55, 0.8)], 0.12), 0.35)  # a growl
        c.add("mouth_wide", c.c["jaw_open"], 0.5)
        c.head[:, 1] += 4.0 * h
        c.blinks(1, lo=0.4)
        c.head_noise(2.0, 1.0, 1.0)
    elif expression == "chilling":
        h = hold(u, 0.1, _r(rng, 0.4, 0.6), 1.0, 1.0)
        c.add("smile_left", h, 0.35)
        c.add("smile_right", h, 0.35)
        c.add("blink_left", h, 0.4)  # heavy, half-closed eyelids
        c.add("blink_right", h, 0.4)
        c.add("calm", h)
        c.head[:, 2] += _r(rng, 4.0, 7.0) * envelope(u, 0.2) * np.sin(2 * np.pi * _r(rng, 0.6, 1.0) * u)
        c.head[:, 1] -= 3.0 * h
        c.blinks(1, lo=0.4)
        c.head_noise(1.5, 1.0, 0.5)
    elif expression == "happy":
        h = hold(u, _r(rng, 0.1, 0.2), _r(rng, 0.3, 0.45), 1.0, 1.0)
        c.add("smile_left", h, 0.85)
        c.add("smile_right", h, 0.85)
        c.add("happy", h)
        c.add("brow_up_left", h, 0.4)
        c.add("brow_up_right", h, 0.4)
        c.add("squint", h, 0.4)
        c.add("jaw_open", bumps(u, [_r(rng, 0.45, 0.75)], 0.15), 0.3)
        c.head[:, 1] += 2.0 * envelope(u) * np.sin(2 * np.pi * _r(rng, 1.5, 2.5) * u)
        c.blinks(1)
        c.head_noise(2.0, 1.0, 2.0)
    elif expression == "pensive":
        h = hold(u, _r(rng, 0.1, 0.2), _r(rng, 0.35, 0.5), 1.0, 1.0)
        look = ("look_left", "look_right")[int(rng.integers(2))]
        c.add("look_up", h, 0.6)
        c.add(look, h, 0.6)
        c.add(f"brow_up_{side}", h, 0.5)
        c.add(f"brow_down_{other}", h, 0.3)
        c.add("lip_press", h, 0.5)
        c.add(f"mouth_side_{side}", h, 0.4)
        c.add("pucker", h, 0.3)
        c.head[:, 2] += (5.0 if side == "left" else -5.0) * h
        c.head[:, 1] -= 4.0 * h
        c.head[:, 0] += (6.0 if look == "look_left" else -6.0) * h
        c.blinks(1, lo=0.5)
        c.head_noise(1.0, 1.0, 1.0)
    elif expression == "confused":
        h = hold(u, _r(rng, 0.1, 0.2), _r(rng, 0.3, 0.45), 1.0, 1.0)
        c.add(f"brow_up_{side}", h, 1.0)
        c.add(f"brow_down_{other}", h, 0.6)
        c.add(f"mouth_side_{other}", h, 0.4)
        c.add(f"smile_{other}", h, 0.2)
        c.add("frown", h, 0.3)
        c.add("squint", h, 0.3)
        c.add(("look_left", "look_right")[int(rng.integers(2))], h, 0.4)
        c.head[:, 2] += (8.0 if side == "left" else -8.0) * h
        c.blinks(int(rng.integers(1, 3)))
        c.head_noise(1.5, 1.0, 1.0)
    elif expression == "disappointed":
        h = hold(u, _r(rng, 0.1, 0.2), _r(rng, 0.35, 0.5), 1.0, 1.0)
        c.add("frown", h, 0.7)
        c.add("worry", h, 0.4)
        c.add("sad", h, 0.6)
        c.add("look_down", h, 0.6)
        c.add("lip_press", h, 0.4)
        c.add("blink_left", h, 0.2)
        c.add("blink_right", h, 0.2)
        c.add("jaw_open", bumps(u, [_r(rng, 0.4, 0.6)], 0.12), 0.25)  # a sigh
        c.head[:, 1] += 8.0 * h
        c.head[:, 0] += 3.0 * envelope(u, 0.3) * np.sin(2 * np.pi * _r(rng, 1.0, 1.5) * u)
        c.blinks(1, lo=0.55)
        c.head_noise(1.0, 1.0, 1.0)
    else:  # pragma: no cover - resolve_expression guards this
        raise UserError(f"no animation for expression {expression!r}")


def resolve_expression(expression: str) -> list[str]:
    """Built-in expressions that animate ``expression``: itself if it is one of the paper's 20,
    else those whose keywords appear in it ("winking and smiling" -> teasing the eyes + smiling)."""
    key = expression.strip().lower()
    for e in EXPRESSIONS:
        if key == e or key.replace("-", " ") == e:
            return [e]
    hits = [target for words, target in KEYWORDS if any(w in key for w in words)]
    hits = list(dict.fromkeys(hits))
    if not hits:
        raise UserError(
            f"the offline animator cannot animate {expression!r}; valid: {', '.join(EXPRESSIONS)} "
            "(or words such as blink, smile, talk, tongue, look, angry)"
        )
    return hits


def driver_key(name: str) -> str:
    """A morph name's key in MORPH_DRIVERS: lower case, and Apple's ARKit spelling (eyeBlinkLeft,
    mouthSmileRight: what ``t2bs autorig`` writes) read as the _L / _R one (eyeBlink_L)."""
    key = name.lower()
    if key in MORPH_DRIVERS:
        return key
    m = re.fullmatch(r"(.+?)(left|right)", key)
    if m and f"{m.group(1)}_{m.group(2)[0]}" in MORPH_DRIVERS:
        return f"{m.group(1)}_{m.group(2)[0]}"
    return key


def usable_rig(mesh: Mesh) -> bool:
    """Whether the animator can play a face on ``mesh``: a morph target drives the jaw, a blink or a smile
    (a mesh without one only gets the rigid head motion, so the video stage auto-rigs it)."""
    controls = {c for drv in morph_drivers(mesh).values() for c, _ in drv}
    return bool(controls & {"jaw_open", "blink_left", "blink_right", "smile_left", "smile_right"})


def morph_drivers(mesh: Mesh) -> dict[str, list[tuple[str, float]]]:
    """The mesh's morph names -> [(control, gain)], with left/right pairs checked on the geometry."""
    # Morphs with all-zero offsets (facecap's tongueOut, VRM "unbound" slots) cannot show anything.
    lower = {driver_key(n): n for n, d in mesh.morph_targets.items() if np.abs(d).max() > 0}
    drivers = {lower[k]: list(v) for k, v in MORPH_DRIVERS.items() if k in lower}
    for left, right in SIDE_PAIRS:
        if left in lower and right in lower:
            xl, xr = _side_x(mesh, lower[left]), _side_x(mesh, lower[right])
            if xl < 0 < xr:  # the asset's "left" is on -X: the character's right
                drivers[lower[left]], drivers[lower[right]] = drivers[lower[right]], drivers[lower[left]]
    return drivers


def _side_x(mesh: Mesh, name: str) -> float:
    """Displacement-weighted x of a morph target, relative to the bbox centre."""
    mag = np.linalg.norm(mesh.morph_targets[name], axis=1)
    if mag.sum() <= 0:
        return 0.0
    cx = 0.5 * (mesh.vertices[:, 0].min() + mesh.vertices[:, 0].max())
    return float((mag * (mesh.vertices[:, 0] - cx)).sum() / mag.sum())


def head_pivot(vertices: np.ndarray) -> np.ndarray:
    """[3] the neck: bottom-centre of the bounding box, a little behind the middle."""
    lo, hi = vertices.min(0), vertices.max(0)
    return np.array(
        [(lo[0] + hi[0]) / 2, lo[1] + 0.1 * (hi[1] - lo[1]), (lo[2] + hi[2]) / 2 - 0.1 * (hi[2] - lo[2])], np.float32
    )


def head_rotations(angles_deg: np.ndarray) -> np.ndarray:
    """[T, 3] yaw, pitch, roll (degrees) -> [T, 3, 3] rotations R = R_yaw @ R_pitch @ R_roll.

    yaw about +Y (positive turns the face towards the character's left, +X), pitch about +X
    (positive nods the face down), roll about +Z (positive tilts the top of the head to -X, the
    character's right)."""
    a = np.radians(np.asarray(angles_deg, np.float64))
    cy, sy = np.cos(a[:, 0]), np.sin(a[:, 0])
    cp, sp = np.cos(a[:, 1]), np.sin(a[:, 1])
    cr, sr = np.cos(a[:, 2]), np.sin(a[:, 2])
    T = len(a)
    ry = np.zeros((T, 3, 3))
    ry[:, 0, 0] = cy
    ry[:, 0, 2] = sy
    ry[:, 1, 1] = 1
    ry[:, 2, 0] = -sy
    ry[:, 2, 2] = cy  # noqa: E702
    rx = np.zeros((T, 3, 3))
    rx[:, 0, 0] = 1
    rx[:, 1, 1] = cp
    rx[:, 1, 2] = -sp
    rx[:, 2, 1] = sp
    rx[:, 2, 2] = cp  # noqa: E702
    rz = np.zeros((T, 3, 3))
    rz[:, 0, 0] = cr
    rz[:, 0, 1] = -sr
    rz[:, 1, 0] = sr
    rz[:, 1, 1] = cr
    rz[:, 2, 2] = 1  # noqa: E702
    return ry @ rx @ rz


def apply_head_motion(morphed: np.ndarray, angles_deg: np.ndarray, pivot: np.ndarray) -> np.ndarray:
    """[T, N, 3] vertices rotated rigidly about ``pivot`` by the per-frame head angles [T, 3]."""
    rot = head_rotations(angles_deg)  # [T, 3, 3]
    p = np.asarray(pivot, np.float64)
    out = np.einsum("tij,tnj->tni", rot, morphed.astype(np.float64) - p) + p
    return out.astype(np.float32)


def expression_seed(seed: int, expression: str, sample: int) -> int:
    """One seed per (global seed, expression, sample): samples differ, re-runs repeat."""
    return int(zlib.crc32(f"{seed}|{expression}|{sample}".encode()))


def expression_curves(expression: str, frames: int, seed: int) -> tuple[dict[str, np.ndarray], np.ndarray, list[str]]:
    """(control -> [T] curve, head angles [T, 3] degrees, built-in expressions used)."""
    if frames < 2:
        raise UserError(f"--frames must be at least 2, got {frames}")
    parts = resolve_expression(expression)
    c = _Curves(frames, np.random.default_rng(seed))
    for p in parts:
        _program(p, c)
    return c.c, c.head, parts


def animate(
    mesh: Mesh, expression: str, seed: int = 0, sample: int = 0, config: AnimationConfig = AnimationConfig()
) -> Animation:
    """Animate ``mesh`` (canonical frame) with ``expression``: weights, head motion and GT vertices."""
    rng_seed = expression_seed(seed, expression, sample)
    controls, head, parts = expression_curves(expression, config.frames, rng_seed)
    drivers = morph_drivers(mesh)
    info: dict = {"expressions": parts, "seed": rng_seed}
    diag = mesh.bbox_diagonal()
    names, weights = _weights(drivers, controls, config)
    morphed = _pose(mesh, names, weights)
    moved = np.linalg.norm(morphed - mesh.vertices[None], axis=-1).max() if len(names) else 0.0
    if moved < 0.01 * diag and mesh.morph_targets:
        # The character lacks every control this expression uses (e.g. ears on a turtle with
        # no ear morph). A video model would still move something: blink and move the mouth.
        fb = _Curves(config.frames, np.random.default_rng(rng_seed + 1))
        fb.blinks(2)
        fb.add("jaw_open", bumps(fb.u, [fb.frame_u(0.3, 0.8, 1, 0.1)[0]], 0.2), 0.5)
        for k, v in fb.c.items():
            controls[k] = np.maximum(controls.get(k, 0.0), v)
        names, weights = _weights(drivers, controls, config)
        morphed = _pose(mesh, names, weights)
        if np.linalg.norm(morphed - mesh.vertices[None], axis=-1).max() < 0.01 * diag:
            # Last resort: drive the strongest morph target of the asset with a smooth bump.
            strongest = max(
                mesh.morph_targets, key=lambda n: float(np.linalg.norm(mesh.morph_targets[n], axis=1).max())
            )
            extra = bumps(fb.u, [0.55], 0.3)
            if strongest in names:
                weights[:, names.index(strongest)] = np.maximum(weights[:, names.index(strongest)], extra)
            else:
                names.append(strongest)
                weights = np.concatenate([weights, extra[:, None].astype(np.float32)], axis=1)
            morphed = _pose(mesh, names, weights)
            info["fallback_morph"] = strongest
        info["fallback"] = "blink + mouth (the mesh has none of this expression's controls)"
    if not mesh.morph_targets:
        info["fallback"] = "rigid head motion only (the mesh has no morph targets)"
    used = {c for n in names for c, _ in drivers.get(n, [])}
    info["controls_missing"] = sorted(k for k, v in controls.items() if k not in used and float(np.max(v)) > 0)
    angles = (head * config.head_motion).astype(np.float32)
    pivot = head_pivot(mesh.vertices)
    vertices = apply_head_motion(morphed, angles, pivot)
    times = (np.arange(config.frames) / config.fps).astype(np.float32)
    return Animation(
        expression,
        times,
        {k: np.asarray(v, np.float32) for k, v in controls.items()},
        names,
        weights,
        angles,
        pivot,
        morphed,
        vertices,
        info,
    )


def _weights(
    drivers: dict[str, list[tuple[str, float]]], controls: dict[str, np.ndarray], config: AnimationConfig
) -> tuple[list[str], np.ndarray]:
    names, cols = [], []
    for name, drv in drivers.items():
        w = sum(g * controls[c] for c, g in drv if c in controls)
        if isinstance(w, np.ndarray) and w.max() > 1e-4:
            names.append(name)
            cols.append(np.clip(w * config.intensity, 0.0, 1.0))
    if not names:
        return [], np.zeros((config.frames, 0), np.float32)
    return names, np.stack(cols, axis=1).astype(np.float32)  # [T, M]


def _pose(mesh: Mesh, names: list[str], weights: np.ndarray) -> np.ndarray:
    """[T, N, 3] rest vertices + sum_m w[t, m] * offsets[m]."""
    base = mesh.vertices.astype(np.float32)
    if not names:
        return np.repeat(base[None], weights.shape[0], axis=0)
    offsets = np.stack([mesh.morph_targets[n] for n in names]).astype(np.float32)  # [M, N, 3]
    return base[None] + np.einsum("tm,mnc->tnc", weights, offsets)
