"""File I/O every layer uses: atomic writes, JSON / npz / image files, validated array reads.

The lowest layer (beside t2bs.errors): a file is written to a temporary name in its folder and
renamed, so a reader never sees half a file; a corrupt or missing input is one UserError line.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from t2bs.errors import UserError


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` only if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if tmp_path.exists():  # mkstemp made it 0600: give it the mode a plain open() would (user's umask)
            os.chmod(tmp_path, 0o666 & ~_umask())
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def _umask() -> int:
    """The process umask (read by setting it and putting it back: there is no getter before 3.13)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_json(path: str | os.PathLike, data: Any) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(to_jsonable(data), indent=2) + "\n")
    return Path(path)


def read_json(path: str | os.PathLike) -> Any:
    """Parse a JSON file; a corrupt one is an InvalidJsonError (a UserError and a ValueError) naming it."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        where = f", line {exc.lineno}" if isinstance(exc, json.JSONDecodeError) else ""
        raise InvalidJsonError(f"{path}: not valid JSON ({getattr(exc, 'msg', 'not UTF-8 text')}{where})") from None


class InvalidJsonError(UserError, ValueError):
    """A project or input JSON file that does not parse: one error line for the CLI, and still the
    ValueError that callers which recover from bad JSON (is_done, camera lists) catch."""


def write_npz(path: str | os.PathLike, **arrays: np.ndarray) -> Path:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
    return Path(path)


def write_image(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Save an [H, W, 3|4] float in [0, 1] or uint8 image as PNG/JPEG, atomically."""
    from PIL import Image

    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    path = Path(path)
    with atomic_path(path) as tmp:
        Image.fromarray(img).save(tmp, format="PNG" if path.suffix.lower() == ".png" else "JPEG")
    return path


def to_jsonable(obj: Any) -> Any:
    """Dataclasses, numpy scalars/arrays and paths -> plain JSON types."""
    if is_dataclass(obj) and not isinstance(obj, type):
        return to_jsonable(asdict(obj))
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    return obj


def read_array(
    path: str | os.PathLike, what: str, ndim: int | None = None, trailing: tuple = (), finite: bool = True
) -> np.ndarray:
    """np.load of a project file, validated before use: UserError (one line, with the path) for a
    missing, empty, truncated or pickled file, a wrong number of axes / trailing shape, or NaN."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: {what} missing")
    try:
        arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise UserError(
            f"{path}: {what} is not a readable .npy file ({type(exc).__name__}); "
            f"delete it and re-run the stage that makes it"
        ) from None
    if not isinstance(arr, np.ndarray) or arr.dtype.kind not in "fiub":
        raise UserError(f"{path}: {what} is not a numeric array")
    if (
        (ndim is not None and arr.ndim != ndim)
        or (trailing and tuple(arr.shape[arr.ndim - len(trailing) :]) != tuple(trailing))
        or arr.size == 0
    ):
        want = f"{ndim} axes" + (f" ending in {tuple(trailing)}" if trailing else "") if ndim else "a non-empty array"
        raise UserError(f"{path}: {what} has shape {arr.shape}, expected {want}")
    if finite and not np.isfinite(arr).all():
        raise UserError(
            f"{path}: {what} holds NaN or infinite values ({int((~np.isfinite(arr)).sum())} entries); "
            f"re-run the stage that makes it"
        )
    return arr
