"""Motion transfer (paper §3.3, §4.3): human landmark motion relative to the neutral frame, scaled
by eye and mouth size, applied to the character's 20 landmarks.

Per region the human displacement (head pose removed, pixels, y down) becomes a character
displacement in the frontal image plane (world X right, Y up): eyes are scaled anisotropically
(x by the eye-width ratio, y by the eye-height ratio: a human eye is ~3x wider than tall, a cartoon
eye is often round, and the lids must still meet when the human's do), the mouth isotropically by
the mouth-width ratio (a closed character mouth has no height to compare with). Depth (Z) is left
to the solve: a frontal video says little about it and the blendshape model knows how the
character's surface moves in depth.

Eye openness is also transferred as a ratio for the solve's eye term: the human's lid gap over
its neutral gap, remapped so that MediaPipe's reading for a shut eye (the lids of a closed eye
still read ~20 % of the open gap) becomes 0, so the character's lids close fully.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from t2bs.face.face_tracking import EYE_CORNERS, EYE_LID_PAIRS, LEFT_EYE, MOUTH, MOUTH_CORNERS, RIGHT_EYE, FaceTrack


@dataclass
class TransferConfig:
    closed_ratio: float = 0.25  # human eye openness (fraction of neutral) read as fully shut
    max_openness: float = 1.5  # cap on the eye openness ratio (wide-eyed)
    eye_aspect_clamp: tuple[float, float] = (0.25, 6.0)  # eye y-scale / x-scale kept in this range


@dataclass
class Transfer:
    targets: np.ndarray  # [T, 20, 2] character landmark targets, world X, Y
    eye_openness: np.ndarray  # [T, 2] target lid gap / neutral lid gap, (right eye, left eye) of the 20's order
    scales: dict  # region -> (sx, sy) world units per human pixel


def region_sizes(points: np.ndarray, y_up: bool) -> dict:
    """Width and lid gap of each eye and the mouth width for landmarks [20, >=2]."""
    sign = 1.0 if y_up else -1.0
    out = {}
    for eye in ("right", "left"):
        c0, c1 = EYE_CORNERS[eye]
        width = abs(points[c1, 0] - points[c0, 0])
        gap = np.mean([sign * (points[up, 1] - points[lo, 1]) for up, lo in EYE_LID_PAIRS[eye]])
        out[eye] = (float(width), float(gap))
    c0, c1 = MOUTH_CORNERS
    out["mouth"] = float(abs(points[c1, 0] - points[c0, 0]))
    return out


def transfer_motion(
    track: FaceTrack,
    char_neutral: np.ndarray,
    config: TransferConfig = TransferConfig(),
    mouth_width: float | None = None,
) -> Transfer:
    """Human track + character neutral landmark positions [20, 3] (world) -> Transfer.

    ``mouth_width``: the character mouth width the motion is scaled to (world units); default the
    distance between the corner landmarks. The landmark detector passes the width of the mouth's
    segmented region when it moved the corners out to the smile's pull points.
    """
    human = track.points.astype(np.float64)  # [T, 20, 3] pixels, y down
    h0 = human[track.neutral]
    hs, cs = region_sizes(h0, y_up=False), region_sizes(char_neutral, y_up=True)
    disp = human[..., :2] - h0[None, :, :2]  # [T, 20, 2]
    disp[..., 1] *= -1.0  # image y down -> world Y up
    targets = np.repeat(char_neutral[None, :, :2], len(human), axis=0).astype(np.float64)
    scales = {}
    lo, hi = config.eye_aspect_clamp
    for eye, idx in (("right", RIGHT_EYE), ("left", LEFT_EYE)):
        sx = cs[eye][0] / max(hs[eye][0], 1e-9)
        sy = np.clip(cs[eye][1] / max(hs[eye][1], 1e-9), lo * sx, hi * sx)
        scales[eye] = (float(sx), float(sy))
        targets[:, idx, 0] += disp[:, idx, 0] * sx
        targets[:, idx, 1] += disp[:, idx, 1] * sy
    s = (mouth_width or cs["mouth"]) / max(hs["mouth"], 1e-9)
    scales["mouth"] = (float(s), float(s))
    targets[:, MOUTH] += disp[:, MOUTH] * s
    open_ratio = np.zeros((len(human), 2))
    for k, eye in enumerate(("right", "left")):
        gaps = np.mean([human[:, lo_, 1] - human[:, up, 1] for up, lo_ in EYE_LID_PAIRS[eye]], axis=0)  # [T] pixels
        r = gaps / max(hs[eye][1], 1e-9)
        open_ratio[:, k] = np.clip((r - config.closed_ratio) / (1.0 - config.closed_ratio), 0.0, config.max_openness)
    return Transfer(targets=targets, eye_openness=open_ratio, scales=scales)
