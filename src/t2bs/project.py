"""The project folder: layout, atomic writes, a manifest, and job keys for resume.

Every stage reads and writes one folder (DESIGN.md). A finished job leaves a ``done.json``
holding the content key of its inputs + config; a re-run whose key matches skips the job, and
a folder without ``done.json`` (a crash mid-job) is redone. Files are written to a temporary
name in the same folder and renamed, so a reader never sees half a file.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import os
import platform
import tempfile
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np


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
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def write_json(path: str | os.PathLike, data: Any) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(to_jsonable(data), indent=2) + "\n")
    return Path(path)


def read_json(path: str | os.PathLike) -> Any:
    return json.loads(Path(path).read_text())


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


def content_key(*parts: Any) -> str:
    """Stable hash of inputs: files are hashed by content, everything else by its JSON form."""
    h = hashlib.sha256()
    for part in parts:
        if isinstance(part, Path):
            if part.is_dir():
                for f in sorted(p for p in part.rglob("*") if p.is_file() and not p.name.startswith(".")):
                    h.update(str(f.relative_to(part)).encode())
                    h.update(_file_digest(f))
            else:
                h.update(_file_digest(part))
        elif isinstance(part, np.ndarray):
            h.update(np.ascontiguousarray(part).tobytes())
        else:
            h.update(json.dumps(to_jsonable(part), sort_keys=True, default=str).encode())
        h.update(b"|")
    return h.hexdigest()[:16]


def _file_digest(path: Path) -> bytes:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.digest()


def is_done(job_dir: str | os.PathLike, key: str) -> bool:
    """True when ``job_dir`` holds a finished job made from the same inputs (same key)."""
    marker = Path(job_dir) / "done.json"
    if not marker.exists():
        return False
    try:
        return read_json(marker).get("key") == key
    except (json.JSONDecodeError, OSError):
        return False


def mark_done(job_dir: str | os.PathLike, key: str, **info: Any) -> None:
    """Record a finished job; written last, so its presence means every output is complete."""
    write_json(Path(job_dir) / "done.json", {"key": key, "finished": _now(), **info})


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def versions() -> dict[str, str]:
    """Versions of t2bs and the libraries whose behaviour shapes the outputs."""
    import importlib.metadata as md

    import t2bs

    out = {"t2bs": t2bs.__version__, "python": platform.python_version()}
    for name in ("numpy", "torch", "moderngl", "pygltflib", "gsplat", "diffusers"):
        try:
            out[name] = md.version(name)
        except md.PackageNotFoundError:
            pass
    return out


class Project:
    """A project folder. Sub-folders: character/, renders/, videos/, recon/, blendshapes/, retarget/."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)

    def path(self, *parts: str) -> Path:
        return self.root.joinpath(*parts)

    @property
    def manifest_path(self) -> Path:
        return self.root / "manifest.json"

    def manifest(self) -> dict:
        if self.manifest_path.exists():
            return read_json(self.manifest_path)
        return {"stages": {}}

    def record_stage(self, stage: str, **info: Any) -> None:
        """Add what a stage made (backend, config, outputs) to manifest.json, with versions."""
        manifest = self.manifest()
        manifest.setdefault("stages", {})[stage] = {**to_jsonable(info), "finished": _now()}
        manifest["versions"] = versions()
        write_json(self.manifest_path, manifest)

    @property
    def mesh_path(self) -> Path:
        return self.path("character", "mesh.glb")

    def load_character(self):
        """The project's canonical character mesh (UserError if the character stage has not run)."""
        from t2bs.errors import UserError
        from t2bs.geometry.io import load_mesh

        if not self.mesh_path.exists():
            raise UserError(f"{self.root}: no character yet (run `t2bs character` or `t2bs render MESH -o {self.root}`)")
        return load_mesh(self.mesh_path)
