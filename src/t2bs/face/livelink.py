"""Live Link Face CSV captures (Epic's iPhone app, ARKit face tracking) driving a rig's ARKit shapes.

A recording's CSV has one row per frame (usually 60 Hz) and the header ``Timecode,
BlendShapeCount, EyeBlinkLeft, ..., TongueOut, HeadYaw, HeadPitch, HeadRoll, LeftEyeYaw,
LeftEyePitch, LeftEyeRoll, RightEyeYaw, RightEyePitch, RightEyeRoll``: 52 ARKit weights in 0..1
(names capitalised), then the head and eye rotations in radians. The timecode is SMPTE with a
fractional frame, ``HH:MM:SS:FF.fff``.

The rig is driven directly through its ARKit-named shapes (no landmarks, no solve): the CSV weight
of a shape is that shape's weight, so what comes out equals what went in on the shapes the rig has.
The head rotation becomes the rig's global motion, a rotation about a pivot under the head
(yaw about +Y, pitch about +X, roll about +Z, applied roll, then pitch, then yaw).
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from t2bs.errors import UserError
from t2bs.face.arkit import ARKIT_NAMES, arkit_name

HEAD_COLUMNS = ("HeadYaw", "HeadPitch", "HeadRoll")
EYE_COLUMNS = ("LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll", "RightEyeYaw", "RightEyePitch", "RightEyeRoll")
# Live Link Face's own column order (the 61 values it streams).
LIVE_LINK_ORDER = [
    "EyeBlinkLeft",
    "EyeLookDownLeft",
    "EyeLookInLeft",
    "EyeLookOutLeft",
    "EyeLookUpLeft",
    "EyeSquintLeft",
    "EyeWideLeft",
    "EyeBlinkRight",
    "EyeLookDownRight",
    "EyeLookInRight",
    "EyeLookOutRight",
    "EyeLookUpRight",
    "EyeSquintRight",
    "EyeWideRight",
    "JawForward",
    "JawRight",
    "JawLeft",
    "JawOpen",
    "MouthClose",
    "MouthFunnel",
    "MouthPucker",
    "MouthRight",
    "MouthLeft",
    "MouthSmileLeft",
    "MouthSmileRight",
    "MouthFrownLeft",
    "MouthFrownRight",
    "MouthDimpleLeft",
    "MouthDimpleRight",
    "MouthStretchLeft",
    "MouthStretchRight",
    "MouthRollLower",
    "MouthRollUpper",
    "MouthShrugLower",
    "MouthShrugUpper",
    "MouthPressLeft",
    "MouthPressRight",
    "MouthLowerDownLeft",
    "MouthLowerDownRight",
    "MouthUpperUpLeft",
    "MouthUpperUpRight",
    "BrowDownLeft",
    "BrowDownRight",
    "BrowInnerUp",
    "BrowOuterUpLeft",
    "BrowOuterUpRight",
    "CheekPuff",
    "CheekSquintLeft",
    "CheekSquintRight",
    "NoseSneerLeft",
    "NoseSneerRight",
    "TongueOut",
    *HEAD_COLUMNS,
    *EYE_COLUMNS,
]
_TIMECODE = re.compile(r"^(\d+):(\d{2}):(\d{2})[:;](\d+)(?:\.(\d+))?$")
STANDARD_RATES = (24, 25, 30, 48, 50, 60, 120)


@dataclass
class LiveLinkCapture:
    times: np.ndarray  # [T] seconds from the first frame
    fps: float  # frame rate of the timecode (from its frame field)
    weights: dict  # Apple name -> [T] weight, for every ARKit column present
    head: np.ndarray  # [T, 3] yaw, pitch, roll in radians (zeros when the CSV has no head columns)


def parse_timecode(text: str) -> tuple[float, int, float]:
    """ "HH:MM:SS:FF.fff" -> (seconds of the whole-second part, frame number, fraction of a frame)."""
    m = _TIMECODE.match(text.strip())
    if m is None:
        raise ValueError(text)
    h, mi, s, ff, frac = m.groups()
    return int(h) * 3600 + int(mi) * 60 + int(s), int(ff), float(f"0.{frac}") if frac else 0.0


def read_livelink_csv(path: str | Path) -> LiveLinkCapture:
    """Read a Live Link Face CSV (UserError with one line for anything malformed)."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"driver {path} does not exist")
    try:
        rows = list(csv.reader(path.read_text(encoding="utf-8-sig").splitlines()))
    except UnicodeDecodeError:
        raise UserError(f"{path}: not a text CSV file") from None
    rows = [r for r in rows if any(c.strip() for c in r)]
    if not rows:
        raise UserError(f"{path}: empty CSV")
    header = [c.strip() for c in rows[0]]
    if not header or header[0] != "Timecode":
        raise UserError(f"{path}: not a Live Link Face CSV (first column {header[0]!r}, expected 'Timecode')")
    shape_cols = {i: arkit_name(c) for i, c in enumerate(header) if arkit_name(c)}
    if not shape_cols:
        raise UserError(f"{path}: no ARKit blendshape columns (EyeBlinkLeft, JawOpen, ...) in the header")
    if len(rows) < 2:
        raise UserError(f"{path}: header only, no frames")
    head_idx = [header.index(c) if c in header else None for c in HEAD_COLUMNS]
    seconds, frames, fracs = [], [], []
    values = np.zeros((len(rows) - 1, len(header)))
    for r, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise UserError(f"{path}: line {r} has {len(row)} values, the header {len(header)}")
        try:
            s, f, fr = parse_timecode(row[0])
        except ValueError:
            raise UserError(f"{path}: line {r}: timecode {row[0]!r} is not HH:MM:SS:FF.fff") from None
        seconds.append(s)
        frames.append(f)
        fracs.append(fr)
        for i in list(shape_cols) + [i for i in head_idx if i is not None]:
            try:
                values[r - 2, i] = float(row[i])
            except ValueError:
                raise UserError(f"{path}: line {r}: {header[i]} = {row[i]!r} is not a number") from None
    if not np.isfinite(values).all():
        raise UserError(f"{path}: NaN or infinite values")
    frames_a = np.asarray(frames)
    # The timecode's frame rate: the smallest standard rate above its largest frame number, once the
    # take spans a whole second (every frame number occurs); a shorter take is read at the app's 60.
    if max(seconds) > min(seconds):
        fps = float(next((rate for rate in STANDARD_RATES if frames_a.max() < rate), frames_a.max() + 1))
    else:
        fps = 60.0
    t = np.asarray(seconds, np.float64) + (frames_a + np.asarray(fracs)) / fps
    t = t - t[0]
    if len(t) > 1 and np.any(np.diff(t) <= 0):
        bad = int(np.nonzero(np.diff(t) <= 0)[0][0]) + 3
        raise UserError(f"{path}: line {bad}: timecode does not increase")
    weights = {name: values[:, i].copy() for i, name in shape_cols.items()}
    head = np.stack([values[:, i] if i is not None else np.zeros(len(t)) for i in head_idx], 1)
    return LiveLinkCapture(t, fps, weights, head)


def head_rotations(head: np.ndarray) -> np.ndarray:
    """[T, 3] yaw, pitch, roll (radians) -> [T, 3, 3] rotations R = R_y(yaw) R_x(pitch) R_z(roll)."""
    from scipy.spatial.transform import Rotation

    h = np.asarray(head, np.float64)
    return Rotation.from_euler("YXZ", h, degrees=False).as_matrix()


def write_livelink_csv(
    path: str | Path, weights: dict, times: np.ndarray, head: np.ndarray | None = None, start: str = "16:20:00"
) -> Path:
    """A Live Link Face style CSV (the app's header and column order) from weights name -> [T]."""
    from t2bs.project import atomic_path

    times = np.asarray(times, np.float64)
    fps = 60.0
    h0, m0, s0 = (int(x) for x in start.split(":"))
    unknown = [n for n in weights if arkit_name(n) is None]
    if unknown:
        raise ValueError(f"not ARKit names: {unknown}")
    by_apple = {arkit_name(n): np.asarray(w, np.float64) for n, w in weights.items()}
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        wr = csv.writer(f)
        wr.writerow(["Timecode", "BlendShapeCount", *LIVE_LINK_ORDER])
        for t in range(len(times)):
            milli = int(round(times[t] * fps * 1000))  # thousandths of a frame since the start
            whole, rest = divmod(milli, int(fps) * 1000)
            total = s0 + m0 * 60 + h0 * 3600 + whole
            tc = f"{total // 3600:02d}:{total % 3600 // 60:02d}:{total % 60:02d}:{rest // 1000:02d}.{rest % 1000:03d}"
            row = [tc, 61]
            for c in LIVE_LINK_ORDER:
                if c in HEAD_COLUMNS and head is not None:
                    row.append(f"{head[t, HEAD_COLUMNS.index(c)]:.6f}")
                elif arkit_name(c) in by_apple:
                    row.append(f"{by_apple[arkit_name(c)][t]:.6f}")
                else:
                    row.append("0.0")
            wr.writerow(row)
    return Path(path)


def arkit_order(names) -> list[str]:
    """``names`` sorted in ARKIT_NAMES order."""
    return [n for n in ARKIT_NAMES if n in set(names)]
