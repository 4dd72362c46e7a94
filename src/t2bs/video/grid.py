"""A synchronized multi-view video I[v, t] (paper §3.1.2) and its folder format.

Every expression video, whether made by the offline animator, imported from a 4D video model
(SV4D, 4Real-Video, ...) or written by hand, is one folder with this layout::

    <grid>/grid.json                  {"format": "t2bs-grid", "version": 1,
                                        "views": V, "frames": T, "height": H, "width": W,
                                        "times": [T] seconds (strictly increasing),
                                        "canonical_view": v0 (the fixed-view video, paper's v = 0),
                                        "backend": "procedural" | "sv4d-import" | "cogvideox" | ...,
                                        "frame_format": "png" | "mp4",
                                        "meta": {prompt, expression, sample, defects, fps, ...}}
    <grid>/cameras.json               [V] camera dicts (Camera.to_dict: K, world_to_camera
                                        OpenCV 4x4, width, height, name), one per view, same
                                        order as the frames; width/height equal W/H
    <grid>/frames/view00/0000.png     frame_format "png" (default): one RGB PNG per (view, time),
    <grid>/frames/view00/0001.png       views view00..view{V-1}, times 0000..{T-1}, all [H, W]
    ...
    <grid>/frames/view00.mp4          frame_format "mp4": one video per view instead (lossy;
                                        accepted for imports, never used for ground truth)
    <grid>/masks.npz                  optional: "masks" [V, T, H, W] bool (foreground)
    <grid>/gt_vertices.npy            optional: [T, N, 3] float32 true vertex positions in the
                                        canonical view's frame (character topology)

PNG is the default because it is lossless: the ground-truth tests compare the canonical view
against re-renders of the true vertices at > 35 dB, which a video codec would not keep.
``load_grid`` checks every count and shape against grid.json and raises a one-line UserError
naming the first problem, so a broken import never reaches the reconstruction.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from t2bs.errors import UserError
from t2bs.geometry.camera import Camera, canonical_view_index, orbit_cameras
from t2bs.project import atomic_path, read_json, write_json, write_npz

GRID_FORMAT = "t2bs-grid"
GRID_VERSION = 1
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".webp", ".bmp")
VIDEO_SUFFIXES = (".mp4", ".webm", ".mov", ".avi", ".gif")


@dataclass
class VideoGrid:
    frames: np.ndarray  # [V, T, H, W, 3] uint8
    cameras: list[Camera]  # [V] one camera per view, same order as frames
    times: np.ndarray  # [T] float32 seconds, strictly increasing
    canonical_view: int  # index of the fixed-view video (the paper's v = 0)
    masks: np.ndarray | None = None  # [V, T, H, W] bool foreground, if known
    gt_vertices: np.ndarray | None = None  # [T, N, 3] float32 true vertices (canonical frame), if known
    backend: str = "unknown"  # what produced the frames (procedural, cogvideox, sv4d-import, ...)
    meta: dict = field(default_factory=dict)  # prompt, expression, sample, defects, fps, ...

    @property
    def num_views(self) -> int:
        return int(self.frames.shape[0])

    @property
    def num_frames(self) -> int:
        return int(self.frames.shape[1])

    @property
    def height(self) -> int:
        return int(self.frames.shape[2])

    @property
    def width(self) -> int:
        return int(self.frames.shape[3])

    def canonical_frames(self) -> np.ndarray:
        """[T, H, W, 3] uint8: the fixed-view video."""
        return self.frames[self.canonical_view]

    def validate(self, source: str = "grid") -> "VideoGrid":
        """Raise UserError naming the first inconsistent count, shape or value."""
        f = self.frames
        if not isinstance(f, np.ndarray) or f.ndim != 5 or f.shape[-1] != 3:
            raise UserError(f"{source}: frames must be [V, T, H, W, 3], got shape {getattr(f, 'shape', None)}")
        if f.dtype != np.uint8:
            raise UserError(f"{source}: frames must be uint8, got {f.dtype}")
        v, t, h, w, _ = f.shape
        if min(v, t, h, w) == 0:
            raise UserError(f"{source}: empty grid (V={v}, T={t}, H={h}, W={w})")
        if len(self.cameras) != v:
            raise UserError(f"{source}: {len(self.cameras)} cameras for {v} views")
        for i, cam in enumerate(self.cameras):
            if (cam.width, cam.height) != (w, h):
                raise UserError(f"{source}: camera {i} is {cam.width}x{cam.height} but frames are {w}x{h}")
            if np.asarray(cam.K).shape != (3, 3) or np.asarray(cam.world_to_camera).shape != (4, 4):
                raise UserError(f"{source}: camera {i} needs K [3, 3] and world_to_camera [4, 4]")
        times = np.asarray(self.times)
        if times.shape != (t,):
            raise UserError(f"{source}: {times.size} time stamps for {t} frames")
        if not np.isfinite(times).all() or (t > 1 and np.any(np.diff(times) <= 0)):
            raise UserError(f"{source}: time stamps must be finite and strictly increasing")
        if not (0 <= int(self.canonical_view) < v):
            raise UserError(f"{source}: canonical_view {self.canonical_view} is outside 0..{v - 1}")
        if self.masks is not None and (self.masks.shape != (v, t, h, w) or self.masks.dtype != bool):
            raise UserError(
                f"{source}: masks must be bool [{v}, {t}, {h}, {w}], got {self.masks.dtype} {self.masks.shape}"
            )
        if self.gt_vertices is not None:
            g = self.gt_vertices
            if g.ndim != 3 or g.shape[0] != t or g.shape[2] != 3:
                raise UserError(f"{source}: gt_vertices must be [{t}, N, 3], got {g.shape}")
            if not np.isfinite(g).all():
                raise UserError(f"{source}: gt_vertices contain NaN or infinite values")
        return self


def save_grid(grid: VideoGrid, folder: str | os.PathLike, frame_format: str = "png", fps: float | None = None) -> Path:
    """Write ``grid`` to ``folder`` in the format above (grid.json last, so a partial folder fails to load)."""
    folder = Path(folder)
    grid.validate(str(folder))
    if frame_format not in ("png", "mp4"):
        raise UserError(f"frame_format must be png or mp4, got {frame_format!r}")
    folder.mkdir(parents=True, exist_ok=True)
    # A stale grid.json from an earlier run must not describe half-written new frames.
    (folder / "grid.json").unlink(missing_ok=True)
    frames_dir = folder / "frames"
    if frame_format == "png":
        from PIL import Image

        for v in range(grid.num_views):
            vdir = frames_dir / f"view{v:02d}"
            vdir.mkdir(parents=True, exist_ok=True)
            for stale in vdir.glob("*.png"):  # frames of an earlier, longer grid
                if not stale.stem.isdigit() or int(stale.stem) >= grid.num_frames:
                    stale.unlink()
            for t in range(grid.num_frames):
                with atomic_path(vdir / f"{t:04d}.png") as tmp:
                    # compress_level 1: lossless either way, ~5x faster to write than the default.
                    Image.fromarray(grid.frames[v, t]).save(tmp, format="PNG", compress_level=1)
    else:
        import imageio.v2 as iio

        frames_dir.mkdir(parents=True, exist_ok=True)
        rate = fps or float(grid.meta.get("fps", 8.0))
        for v in range(grid.num_views):
            with atomic_path(frames_dir / f"view{v:02d}.mp4") as tmp:
                with iio.get_writer(
                    tmp,
                    format="FFMPEG",
                    fps=rate,
                    codec="libx264",
                    quality=9,
                    macro_block_size=1,
                    ffmpeg_log_level="error",
                ) as writer:
                    for t in range(grid.num_frames):
                        writer.append_data(grid.frames[v, t])
    write_json(folder / "cameras.json", [c.to_dict() for c in grid.cameras])
    if grid.masks is not None:
        write_npz(folder / "masks.npz", masks=grid.masks)
    else:
        (folder / "masks.npz").unlink(missing_ok=True)
    if grid.gt_vertices is not None:
        with atomic_path(folder / "gt_vertices.npy") as tmp:
            with open(tmp, "wb") as fh:
                np.save(fh, np.asarray(grid.gt_vertices, dtype=np.float32))
    else:
        (folder / "gt_vertices.npy").unlink(missing_ok=True)
    write_json(
        folder / "grid.json",
        {
            "format": GRID_FORMAT,
            "version": GRID_VERSION,
            "views": grid.num_views,
            "frames": grid.num_frames,
            "height": grid.height,
            "width": grid.width,
            "times": np.asarray(grid.times, dtype=np.float64).tolist(),
            "canonical_view": int(grid.canonical_view),
            "backend": grid.backend,
            "frame_format": frame_format,
            "meta": grid.meta,
        },
    )
    return folder


def load_grid(folder: str | os.PathLike, load_frames: bool = True) -> VideoGrid:
    """Read a grid folder; UserError (one line) for anything missing or inconsistent.

    ``load_frames=False`` returns the grid with ``frames`` of shape [V, T, H, W, 3] as a zero
    array view (np.broadcast_to) after checking the frame files exist, for callers that need
    only cameras/GT.
    """
    folder = Path(folder)
    src = str(folder)
    if not folder.is_dir():
        raise UserError(f"{src}: no such grid folder")
    info_path = folder / "grid.json"
    if not info_path.exists():
        raise UserError(f"{src}: not a video grid (grid.json missing)")
    try:
        info = read_json(info_path)
    except ValueError as exc:
        raise UserError(f"{src}/grid.json: not valid JSON ({exc})") from None
    if not isinstance(info, dict) or info.get("format") != GRID_FORMAT:
        raise UserError(f"{src}/grid.json: format is not {GRID_FORMAT!r}")
    try:
        nv, nt, h, w = (int(info[k]) for k in ("views", "frames", "height", "width"))
        times = np.asarray(info["times"], dtype=np.float32)
        canonical = int(info["canonical_view"])
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(f"{src}/grid.json: missing or bad field {exc}") from None
    cams_path = folder / "cameras.json"
    if not cams_path.exists():
        raise UserError(f"{src}: cameras.json missing (one camera per view is required)")
    try:
        cams_raw = read_json(cams_path)
        cams_raw = cams_raw["cameras"] if isinstance(cams_raw, dict) else cams_raw
        cameras = [Camera.from_dict(c) for c in cams_raw]
    except (ValueError, KeyError, TypeError) as exc:
        raise UserError(f"{src}/cameras.json: unreadable camera list ({exc})") from None
    if len(cameras) != nv:
        raise UserError(f"{src}: cameras.json has {len(cameras)} cameras but grid.json says {nv} views")
    fmt = info.get("frame_format", "png")
    if load_frames:
        frames = _read_frames(folder / "frames", fmt, nv, nt, h, w, src)
    else:
        _check_frame_files(folder / "frames", fmt, nv, nt, src)
        frames = np.broadcast_to(np.zeros((1, 1, 1, 1, 3), np.uint8), (nv, nt, h, w, 3))
    masks = None
    if (folder / "masks.npz").exists():
        try:
            import zipfile

            with np.load(folder / "masks.npz", allow_pickle=False) as z:
                masks = z["masks"].astype(bool)
        except (KeyError, ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
            raise UserError(f"{src}/masks.npz: unreadable ({exc})") from None
    gt = None
    if (folder / "gt_vertices.npy").exists():
        from t2bs.project import read_array

        gt = read_array(folder / "gt_vertices.npy", "ground-truth vertices", ndim=3, trailing=(3,)).astype(np.float32)
    grid = VideoGrid(
        frames, cameras, times, canonical, masks, gt, str(info.get("backend", "unknown")), dict(info.get("meta") or {})
    )
    return grid.validate(src)


def _check_frame_files(frames_dir: Path, fmt: str, nv: int, nt: int, src: str) -> None:
    for v in range(nv):
        if fmt == "mp4":
            if not (frames_dir / f"view{v:02d}.mp4").exists():
                raise UserError(f"{src}: frames/view{v:02d}.mp4 missing ({nv} views expected)")
            continue
        vdir = frames_dir / f"view{v:02d}"
        if not vdir.is_dir():
            raise UserError(f"{src}: frames/view{v:02d}/ missing ({nv} views expected)")
        n = len([p for p in vdir.glob("*.png") if p.stem.isdigit()])
        if n != nt:
            raise UserError(f"{src}: frames/view{v:02d}/ has {n} frames but grid.json says {nt}")
    if fmt == "png":
        extra = sorted(
            p.name for p in frames_dir.glob("view*") if p.is_dir() and p.name[4:].isdigit() and int(p.name[4:]) >= nv
        )
        if extra:
            raise UserError(f"{src}: frames/{extra[0]}/ is an extra view ({nv} views expected)")
    elif fmt != "mp4":
        raise UserError(f"{src}/grid.json: frame_format must be png or mp4, got {fmt!r}")


def _read_frames(frames_dir: Path, fmt: str, nv: int, nt: int, h: int, w: int, src: str) -> np.ndarray:
    _check_frame_files(frames_dir, fmt, nv, nt, src)
    out = np.empty((nv, nt, h, w, 3), np.uint8)  # [V, T, H, W, 3]
    for v in range(nv):
        if fmt == "mp4":
            video = read_video(frames_dir / f"view{v:02d}.mp4")
            if video.shape[0] != nt:
                raise UserError(f"{src}: frames/view{v:02d}.mp4 has {video.shape[0]} frames but grid.json says {nt}")
            imgs = list(video)
        else:
            imgs = [read_rgb(frames_dir / f"view{v:02d}" / f"{t:04d}.png", src) for t in range(nt)]
        for t, img in enumerate(imgs):
            if img.shape != (h, w, 3):
                raise UserError(
                    f"{src}: view {v} frame {t} is {img.shape[1]}x{img.shape[0]} but grid.json says {w}x{h}"
                )
            out[v, t] = img
    return out


def read_rgb(path: Path, src: str | None = None, alphas: list | None = None) -> np.ndarray:
    """[H, W, 3] uint8 from an image file (alpha composited over white, grey expanded).

    ``alphas``: if given, the image's alpha channel [H, W] uint8 (or None) is appended to it."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            alpha = None
            if im.mode in ("RGBA", "LA") or (im.mode == "P" and "transparency" in im.info):
                im = im.convert("RGBA")
                alpha = np.asarray(im, dtype=np.uint8)[..., 3].copy()
                bg = Image.new("RGBA", im.size, (255, 255, 255, 255))
                im = Image.alpha_composite(bg, im)
            if alphas is not None:
                alphas.append(alpha)
            return np.asarray(im.convert("RGB"), dtype=np.uint8)
    except FileNotFoundError:
        raise UserError(f"{src or path}: {path.name} missing") from None
    except (UnidentifiedImageError, OSError) as exc:
        raise UserError(f"{path}: not a readable image ({exc})") from None


def read_video(path: Path) -> np.ndarray:
    """[T, H, W, 3] uint8 frames of a video file."""
    import imageio.v3 as iio

    try:
        frames = iio.imread(path, index=None, plugin="pyav" if _has_pyav() else None)
    except Exception as exc:  # imageio raises many types for a broken or unsupported file
        first = str(exc).strip().splitlines()[0][:160] if str(exc).strip() else ""  # not ffmpeg's whole banner
        raise UserError(f"{path}: not a readable video ({type(exc).__name__}{': ' + first if first else ''})") from None
    frames = np.asarray(frames)
    if frames.ndim == 3:
        frames = frames[None]
    return np.ascontiguousarray(frames[..., :3]).astype(np.uint8)


def _has_pyav() -> bool:
    try:
        import av  # noqa: F401
    except ImportError:
        return False
    return True


def masks_from_frames(frames: np.ndarray, tolerance: int = 12) -> np.ndarray:
    """[..., H, W, 3] uint8 frames on a plain background -> [..., H, W] bool foreground.

    The background colour of each frame is keyed from its border (median of the outermost pixels:
    4D video models and our renders put the character on a uniform, usually white, ground); a
    pixel is foreground where any channel differs from it by more than ``tolerance``.
    """
    f = np.asarray(frames)
    border = np.concatenate([f[..., 0, :, :], f[..., -1, :, :], f[..., :, 0, :], f[..., :, -1, :]], axis=-2)
    key = np.median(border, axis=-2).astype(np.int16)  # [..., 3]
    diff = np.abs(f.astype(np.int16) - key[..., None, None, :]).max(axis=-1)
    return diff > tolerance


# ---------------------------------------------------------------------------------------------
# Importer for grids written by SV4D-style 4D video models.


def import_image_grid(
    source: str | os.PathLike,
    views: int | None = None,
    frames: int | None = None,
    cameras: list[Camera] | str | os.PathLike | None = None,
    canonical_view: int | None = None,
    fps: float = 8.0,
    backend: str = "sv4d-import",
    meta: dict | None = None,
    shading: str | None = None,
) -> VideoGrid:
    """A V x T image grid written by a 4D video model -> VideoGrid.

    ``source`` is one of
      - one big image holding V rows (views) x T columns (times) of equal tiles: ``views`` and
        ``frames`` are required;
      - a folder with one sub-folder per view (sorted by name), each holding T images sorted by
        name (numbers sort numerically);
      - a folder with one video file per view (sorted by name);
      - a flat folder of V*T images sorted view-major (view 0's T frames first): ``views`` is required.
    ``cameras`` is a list of Camera, a cameras.json path, or None for the paper's orbit
    (``orbit_cameras(V)``: azimuth -60..60, the middle view canonical). Every count and size is
    checked; a mismatch is a one-line UserError.

    Masks are kept: from the images' alpha where every image has one, else keyed from the plain
    background (``masks_from_frames``). ``shading`` (unlit or lambert: how the mesh render the 4D
    model started from was lit) goes into meta["grid_config"], where VCDGS reads it for its
    static fit; None records nothing (VCDGS then assumes lambert).
    """
    source = Path(source)
    if not source.exists():
        raise UserError(f"{source}: no such image grid (a file or a folder)")
    if shading not in (None, "unlit", "lambert"):
        raise UserError(f"shading must be unlit or lambert, got {shading!r}")
    alphas: list = []  # alpha channels of the images read (None where an image has none)
    if source.is_file():
        if views is None or frames is None:
            raise UserError(f"{source}: a single grid image needs --views and --frames (rows x columns)")
        big = read_rgb(source, alphas=alphas)
        gh, gw = big.shape[:2]
        if gh % views or gw % frames:
            raise UserError(
                f"{source}: a {gw}x{gh} image does not split into {views} rows x {frames} columns of equal tiles"
            )
        th, tw = gh // views, gw // frames
        data = big.reshape(views, th, frames, tw, 3).transpose(0, 2, 1, 3, 4)  # [V, T, th, tw, 3]
        if alphas[0] is not None:
            alphas = [alphas[0].reshape(views, th, frames, tw).transpose(0, 2, 1, 3)]
    else:
        data = _import_folder(source, views, frames, alphas)
    if alphas and all(a is not None for a in alphas):
        masks = np.asarray(alphas).reshape(data.shape[:4]) > 127  # [V, T, H, W]
        mask_source = "alpha"
    else:
        masks = masks_from_frames(data)
        mask_source = "background key"
    nv, nt = data.shape[:2]
    if views is not None and nv != views:
        raise UserError(f"{source}: found {nv} views but {views} were expected")
    if frames is not None and nt != frames:
        raise UserError(f"{source}: found {nt} frames per view but {frames} were expected")
    h, w = data.shape[2:4]
    if cameras is None:
        if h != w:
            raise UserError(f"{source}: tiles are {w}x{h}; the default orbit cameras are square, pass cameras")
        cams = orbit_cameras(nv, size=w)
        canon = canonical_view_index(nv) if canonical_view is None else canonical_view
    else:
        if isinstance(cameras, (str, os.PathLike)):
            try:
                raw = read_json(cameras)
                raw = raw["cameras"] if isinstance(raw, dict) else raw
                cams = [Camera.from_dict(c) for c in raw]
            except (OSError, ValueError, KeyError, TypeError) as exc:
                raise UserError(f"{cameras}: unreadable camera list ({exc})") from None
        else:
            cams = list(cameras)
        if len(cams) != nv:
            raise UserError(f"{source}: {len(cams)} cameras for {nv} views")
        # A camera list at another resolution (e.g. the 512 px orbit for a 576 px SV4D output)
        # describes the same views: rescale the intrinsics to the tiles.
        cams = [c if (c.width, c.height) == (w, h) else c.resized(w, h) for c in cams]
        canon = canonical_view_index(nv) if canonical_view is None else canonical_view
    times = (np.arange(nt, dtype=np.float32) / np.float32(fps)).astype(np.float32)
    info = {"fps": fps, "source": str(source), "masks_from": mask_source, **(meta or {})}
    if shading is not None:
        info["grid_config"] = {**(info.get("grid_config") or {}), "shading": shading}
    grid = VideoGrid(np.ascontiguousarray(data), cams, times, int(canon), masks, None, backend, info)
    return grid.validate(str(source))


def _natural_key(p: Path):
    return [int(s) if s.isdigit() else s for s in re.split(r"(\d+)", p.name)]


def _stack(images: list[np.ndarray], src: str, what: str) -> np.ndarray:
    shapes = {im.shape for im in images}
    if len(shapes) != 1:
        raise UserError(f"{src}: {what} have different sizes {sorted(shapes)}")
    return np.stack(images)


def _import_folder(source: Path, views: int | None, frames: int | None, alphas: list | None = None) -> np.ndarray:
    entries = sorted((p for p in source.iterdir() if not p.name.startswith(".")), key=_natural_key)
    subdirs = [p for p in entries if p.is_dir()]
    images = [p for p in entries if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    videos = [p for p in entries if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES]
    src = str(source)
    if subdirs:
        per_view = []
        for d in subdirs:
            imgs = sorted((p for p in d.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES), key=_natural_key)
            if not imgs:
                raise UserError(f"{d}: no images in this view folder")
            per_view.append(_stack([read_rgb(p, alphas=alphas) for p in imgs], str(d), "frames"))
        counts = {len(x) for x in per_view}
        if len(counts) != 1:
            raise UserError(f"{src}: view folders hold different frame counts {sorted(counts)}")
        return _stack(per_view, src, "views")
    if videos:
        per_view = [read_video(p) for p in videos]
        counts = {len(x) for x in per_view}
        if len(counts) != 1:
            raise UserError(f"{src}: view videos hold different frame counts {sorted(counts)}")
        return _stack(per_view, src, "view videos")
    if images:
        if views is None:
            raise UserError(f"{src}: a flat folder of images needs --views (images are read view-major)")
        if len(images) % views:
            raise UserError(f"{src}: {len(images)} images do not split into {views} views")
        nt = len(images) // views
        data = _stack([read_rgb(p, alphas=alphas) for p in images], src, "images")
        return data.reshape(views, nt, *data.shape[1:])
    raise UserError(f"{src}: no images, view folders or videos found")
