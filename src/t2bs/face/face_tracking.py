"""Human face tracking (paper §3.3): MediaPipe face mesh -> the 20 retargeting landmarks per frame.

The 20 points are the 68-point scheme's eyes (36-41 the subject's right eye, 42-47 the subject's
left eye) and inner lips (60-67), in that order. ``MEDIAPIPE_TO_68`` below is the correspondence
with MediaPipe's 468-point face mesh, written here from the mesh's topology (see
mediapipe/python/solutions/face_mesh_connections.py: FACEMESH_RIGHT_EYE, FACEMESH_LEFT_EYE and
the inner ring of FACEMESH_LIPS):

| 68 | MediaPipe | where |                       | 68 | MediaPipe | where |
|----|-----------|-------|-----------------------|----|-----------|-------|
| 36 | 33  | right eye, outer corner                | 60 | 78  | inner lips, right corner |
| 37 | 160 | right eye, upper lid (outer third)     | 61 | 81  | upper inner lip, right   |
| 38 | 158 | right eye, upper lid (inner third)     | 62 | 13  | upper inner lip, middle  |
| 39 | 133 | right eye, inner corner                | 63 | 311 | upper inner lip, left    |
| 40 | 153 | right eye, lower lid (inner third)     | 64 | 308 | inner lips, left corner  |
| 41 | 144 | right eye, lower lid (outer third)     | 65 | 402 | lower inner lip, left    |
| 42 | 362 | left eye, inner corner                 | 66 | 14  | lower inner lip, middle  |
| 43 | 385 | left eye, upper lid (inner third)      | 67 | 178 | lower inner lip, right   |
| 44 | 387 | left eye, upper lid (outer third)      |    |     |                          |
| 45 | 263 | left eye, outer corner                 |    |     |                          |
| 46 | 373 | left eye, lower lid (outer third)      |    |     |                          |
| 47 | 380 | left eye, lower lid (inner third)      |    |     |                          |

"Right"/"left" are the subject's: in a frontal image the subject's right eye is on the image's
left. On the character the same convention holds (the character's left is +X, the image's right),
so the human's left eye drives the character's left eye and nothing is mirrored.

Which MediaPipe: mediapipe 0.10.21 is the last wheel with the legacy face-mesh graph and its
model inside the wheel (newer wheels only have the Tasks API, which needs a ``face_landmarker.task``
file from a download site). That wheel requires numpy < 2, so scripts/setup.sh installs it into its
own virtual environment (``~/.cache/t2bs/mediapipe-venv``, or ``$T2BS_MEDIAPIPE_PYTHON``) and
``_mediapipe_worker.py`` runs there in a subprocess; frames and landmarks travel as .npy files.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from t2bs.errors import UserError

# 68-scheme index -> MediaPipe face-mesh index (the table in the module docstring).
MEDIAPIPE_TO_68: dict[int, int] = {
    36: 33,
    37: 160,
    38: 158,
    39: 133,
    40: 153,
    41: 144,
    42: 362,
    43: 385,
    44: 387,
    45: 263,
    46: 373,
    47: 380,
    60: 78,
    61: 81,
    62: 13,
    63: 311,
    64: 308,
    65: 402,
    66: 14,
    67: 178,
}
LANDMARKS_68: list[int] = list(MEDIAPIPE_TO_68)  # [20] the retargeting landmarks, in order
MEDIAPIPE_20: list[int] = [MEDIAPIPE_TO_68[i] for i in LANDMARKS_68]  # [20] their MediaPipe indices

# Index ranges of the 20 points (positions in LANDMARKS_68).
RIGHT_EYE = list(range(0, 6))  # 36-41: the subject's right eye (image left, character -X)
LEFT_EYE = list(range(6, 12))  # 42-47: the subject's left eye (image right, character +X)
MOUTH = list(range(12, 20))  # 60-67: inner lip contour
# Upper / lower lid pairs (same column of the eye), as positions in the 20: (37, 41), (38, 40), ...
EYE_LID_PAIRS = {"right": [(1, 5), (2, 4)], "left": [(7, 11), (8, 10)]}
EYE_CORNERS = {"right": (0, 3), "left": (6, 9)}
MOUTH_CORNERS = (12, 16)
MOUTH_LIP_PAIRS = [(13, 19), (14, 18), (15, 17)]  # (61, 67), (62, 66), (63, 65)

# MediaPipe points that move little with expressions (forehead, nose bridge and tip, eye corners,
# cheekbones, temples): a similarity fit on them removes the head's rigid motion.
STABLE_MEDIAPIPE = [10, 151, 9, 8, 168, 6, 197, 195, 5, 4, 1, 33, 133, 362, 263, 234, 454, 127, 356, 93, 323, 116, 345]

DEFAULT_VENV = Path.home() / ".cache" / "t2bs" / "mediapipe-venv"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".webp")


@dataclass
class TrackConfig:
    smooth_sigma: float = 1.0  # temporal Gaussian smoothing of the landmarks, in frames (0 = off)
    neutral_frame: int | None = None  # index of the neutral (rest) frame; None = detect it
    static: bool = False  # detect the face on every frame instead of tracking it (image folders)
    max_frames: int | None = None  # read at most this many frames (None = all)


@dataclass
class FaceTrack:
    points: (
        np.ndarray
    )  # [T, 20, 3] head-pose-free landmarks, pixels of the neutral frame (x right, y down, z ~ x scale)
    image_points: np.ndarray  # [T, 20, 2] landmarks in the image (pixels), for overlays
    found: np.ndarray  # [T] bool: a face was detected in the frame (others are interpolated or held)
    neutral: int  # index of the neutral frame
    fps: float  # frames per second of the driver
    report: dict = field(default_factory=dict)  # frames, missing frames, how they were filled, neutral choice


# ----------------------------------------------------------------------------------------------
# Reading the driver
# ----------------------------------------------------------------------------------------------


def read_driver(path: str | os.PathLike, max_frames: int | None = None) -> tuple[np.ndarray, float]:
    """Frames [T, H, W, 3] uint8 and fps of a video file or a folder of images (sorted by name)."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"driver {path} does not exist")
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise UserError(f"driver folder {path} has no images ({', '.join(IMAGE_SUFFIXES)})")
        from PIL import Image

        frames = []
        for f in files[:max_frames]:
            try:
                frames.append(np.asarray(Image.open(f).convert("RGB")))
            except Exception as exc:  # PIL raises several types for broken files
                raise UserError(f"driver image {f} cannot be read ({type(exc).__name__})") from None
        if len({fr.shape for fr in frames}) > 1:
            raise UserError(f"driver folder {path}: images have different sizes")
        return np.stack(frames), 30.0
    import imageio.v2 as imageio

    frames = []
    try:
        reader = imageio.get_reader(str(path), format="ffmpeg")
        fps = float(reader.get_meta_data().get("fps", 30.0) or 30.0)
        for i, fr in enumerate(reader):
            if max_frames is not None and i >= max_frames:
                break
            frames.append(np.asarray(fr)[..., :3])
        reader.close()
    except Exception as exc:  # ffmpeg reports corrupt/unknown files as OSError/RuntimeError/IndexError
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise UserError(f"driver video {path} cannot be decoded: {first[:160]}") from None
    if not frames:
        raise UserError(f"driver video {path} has no frames")
    return np.stack(frames).astype(np.uint8), fps


# ----------------------------------------------------------------------------------------------
# MediaPipe
# ----------------------------------------------------------------------------------------------


def mediapipe_python() -> str:
    """The interpreter that has mediapipe 0.10.21 (its own venv, see the module docstring)."""
    env = os.environ.get("T2BS_MEDIAPIPE_PYTHON")
    if env:
        if not Path(env).exists():
            raise UserError(f"T2BS_MEDIAPIPE_PYTHON={env} does not exist")
        return env
    candidate = DEFAULT_VENV / "bin" / "python"
    if candidate.exists():
        return str(candidate)
    raise UserError(
        f"MediaPipe face tracker not installed: run scripts/setup.sh (it creates {DEFAULT_VENV}) "
        "or set T2BS_MEDIAPIPE_PYTHON to a python with mediapipe==0.10.21"
    )


def mediapipe_available() -> bool:
    try:
        mediapipe_python()
    except UserError:
        return False
    return True


def run_face_mesh(frames: np.ndarray, static: bool = False, progress=None) -> tuple[np.ndarray, np.ndarray]:
    """MediaPipe face mesh on frames [T, H, W, 3] uint8 -> (landmarks [T, 468, 3] pixels, found [T]).

    x, y in pixels; z in MediaPipe's relative depth scaled like x (smaller = nearer the camera).
    ``progress(done, total)`` is called as frames are processed.
    """
    frames = np.ascontiguousarray(frames, dtype=np.uint8)
    if frames.ndim != 4 or frames.shape[-1] != 3:
        raise ValueError(f"frames must be [T, H, W, 3] uint8, got {frames.shape}")
    python = mediapipe_python()
    worker = Path(__file__).with_name("_mediapipe_worker.py")
    with tempfile.TemporaryDirectory(prefix="t2bs-mp-") as tmp:
        fpath, opath = Path(tmp) / "frames.npy", Path(tmp) / "out.npz"
        np.save(fpath, frames)
        cmd = [python, str(worker), str(fpath), str(opath)] + (["--static"] if static else [])
        env = dict(os.environ, GLOG_minloglevel="2", TF_CPP_MIN_LOG_LEVEL="2")
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        for line in proc.stdout:
            parts = line.split()
            if progress is not None and len(parts) == 3 and parts[0] == "progress":
                progress(int(parts[1]), int(parts[2]))
        err = proc.stderr.read()
        if proc.wait() != 0 or not opath.exists():
            last = [ln for ln in err.strip().splitlines() if ln.strip()][-1:] or ["no output"]
            raise UserError(f"MediaPipe face tracker failed ({python}): {last[0][:200]}")
        with np.load(opath) as data:
            lm, found = data["landmarks"].astype(np.float64), data["found"].astype(bool)
    h, w = frames.shape[1:3]
    lm = lm * np.array([w, h, w], np.float64)
    return lm, found


# ----------------------------------------------------------------------------------------------
# From 468 points to the 20, head pose removed
# ----------------------------------------------------------------------------------------------


def eye_openness(p: np.ndarray, eye: str) -> np.ndarray:
    """Lid gap / eye width for points [..., 20, >=2] (image y down) -> [...]."""
    c0, c1 = EYE_CORNERS[eye]
    width = np.linalg.norm(p[..., c1, :2] - p[..., c0, :2], axis=-1)
    gap = np.mean([p[..., lo, 1] - p[..., up, 1] for up, lo in EYE_LID_PAIRS[eye]], axis=0)
    return gap / np.maximum(width, 1e-9)


def mouth_openness(p: np.ndarray) -> np.ndarray:
    """Inner-lip gap / mouth width -> [...]."""
    c0, c1 = MOUTH_CORNERS
    width = np.linalg.norm(p[..., c1, :2] - p[..., c0, :2], axis=-1)
    gap = np.mean([p[..., lo, 1] - p[..., up, 1] for up, lo in MOUTH_LIP_PAIRS], axis=0)
    return gap / np.maximum(width, 1e-9)


def detect_neutral(points: np.ndarray, found: np.ndarray) -> int:
    """Index of the most neutral frame: mouth closed, eyes at their usual openness, lips unstretched.

    Uses scale-free ratios, so head motion does not matter: mouth gap / width, eye gap / width
    against the median over the video (most frames have open, resting eyes), and mouth width over
    the inter-ocular distance against its lower quantile (a smile widens the mouth).
    """
    idx = np.nonzero(found)[0]
    p = points[idx]
    mouth = mouth_openness(p)
    eyes = (eye_openness(p, "left") + eye_openness(p, "right")) / 2
    iod = np.linalg.norm(p[:, 3, :2] - p[:, 6, :2], axis=-1)  # inner eye corners 39 and 42
    mw = np.linalg.norm(p[:, 16, :2] - p[:, 12, :2], axis=-1) / np.maximum(iod, 1e-9)
    med_eye = max(float(np.median(eyes)), 1e-6)
    score = np.maximum(mouth, 0) + np.abs(eyes - med_eye) / med_eye + np.maximum(mw - np.quantile(mw, 0.2), 0)
    return int(idx[int(np.argmin(score))])


def fill_missing(x: np.ndarray, found: np.ndarray) -> np.ndarray:
    """Linear interpolation over time of frames without a face; held at the ends. x [T, ...]."""
    t = np.arange(len(x))
    idx = np.nonzero(found)[0]
    flat = x.reshape(len(x), -1)
    out = np.stack([np.interp(t, idx, flat[idx, j]) for j in range(flat.shape[1])], axis=1)
    return out.reshape(x.shape)


def smooth(x: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing over time (axis 0), edges reflected."""
    if sigma <= 0 or len(x) < 3:
        return x
    from scipy.ndimage import gaussian_filter1d

    return gaussian_filter1d(x, sigma, axis=0, mode="nearest")


def track_landmarks(lm468: np.ndarray, found: np.ndarray, fps: float, config: TrackConfig = TrackConfig()) -> FaceTrack:
    """MediaPipe points [T, 468, 3] (pixels) + found [T] -> FaceTrack (pose removed, filled, smoothed)."""
    t = len(lm468)
    n_found = int(found.sum())
    if n_found == 0:
        raise UserError(f"no face found in any of the {t} driver frames")
    image20 = lm468[:, MEDIAPIPE_20, :]  # [T, 20, 3]
    if config.neutral_frame is not None:
        if not 0 <= config.neutral_frame < t:
            raise UserError(f"--neutral-frame {config.neutral_frame} is outside 0..{t - 1}")
        if not found[config.neutral_frame]:
            raise UserError(f"--neutral-frame {config.neutral_frame} has no face")
        neutral = int(config.neutral_frame)
    else:
        neutral = detect_neutral(image20, found)
    # Remove head motion: similarity fit of the stable points of each frame onto the neutral frame's.
    ref = lm468[neutral, STABLE_MEDIAPIPE]
    aligned = np.zeros((t, 20, 3))
    idx = np.nonzero(found)[0]
    if len(idx):  # Umeyama (roma): s R x + t ~ ref for each frame's stable points, all frames in one call
        import roma
        import torch

        src = torch.as_tensor(lm468[idx][:, STABLE_MEDIAPIPE], dtype=torch.float64)
        rot, tr, s = roma.rigid_points_registration(
            src, torch.as_tensor(ref, dtype=torch.float64).expand_as(src), compute_scaling=True
        )
        aligned[idx] = (
            s[:, None, None] * torch.as_tensor(image20[idx], dtype=torch.float64) @ rot.transpose(1, 2) + tr[:, None]
        ).numpy()
    missing = np.nonzero(~found)[0]
    if len(missing):
        aligned = fill_missing(aligned, found)
        image20 = fill_missing(image20, found)
    aligned = smooth(aligned, config.smooth_sigma)
    runs = _runs(missing)
    report = {
        "frames": t,
        "found": n_found,
        "missing": int(len(missing)),
        "missing_runs": runs,
        "filled": "linear interpolation between tracked frames, held before the first / after the last",
        "neutral_frame": neutral,
        "neutral_detected": config.neutral_frame is None,
        "smooth_sigma_frames": config.smooth_sigma,
    }
    return FaceTrack(
        points=aligned.astype(np.float32),
        image_points=image20[..., :2].astype(np.float32),
        found=found.copy(),
        neutral=neutral,
        fps=float(fps),
        report=report,
    )


def _runs(idx: np.ndarray) -> list[list[int]]:
    """Consecutive runs [[first, last], ...] of sorted indices."""
    runs: list[list[int]] = []
    for i in idx.tolist():
        if runs and runs[-1][1] == i - 1:
            runs[-1][1] = i
        else:
            runs.append([i, i])
    return runs


def track_face(frames: np.ndarray, fps: float = 30.0, config: TrackConfig = TrackConfig(), progress=None) -> FaceTrack:
    """Frames [T, H, W, 3] uint8 -> FaceTrack of the 20 landmarks."""
    lm, found = run_face_mesh(frames, static=config.static, progress=progress)
    return track_landmarks(lm, found, fps, config)


def draw_points(image: np.ndarray, points: np.ndarray, color=(255, 0, 0), radius: int = 2) -> np.ndarray:
    """Copy of ``image`` [H, W, 3] uint8 with dots at ``points`` [P, 2] (pixels)."""
    out = image.copy()
    h, w = out.shape[:2]
    yy, xx = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    disk = (xx**2 + yy**2) <= radius**2
    for x, y in np.round(points).astype(int):
        ys, xs = y + yy[disk], x + xx[disk]
        ok = (ys >= 0) & (ys < h) & (xs >= 0) & (xs < w)
        out[ys[ok], xs[ok]] = color
    return out


if __name__ == "__main__":  # pragma: no cover - manual check: python -m t2bs.face.face_tracking IMAGE
    from PIL import Image

    img = np.asarray(Image.open(sys.argv[1]).convert("RGB"))
    lm, ok = run_face_mesh(img[None], static=True)
    print(ok, lm[0, MEDIAPIPE_20, :2].round(1).tolist())
