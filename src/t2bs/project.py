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
import sys
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from t2bs.errors import UserError
from t2bs.fileio import (  # noqa: F401  (re-exported: the project API writes and reads through them)
    InvalidJsonError,
    atomic_path,
    read_array,
    read_json,
    to_jsonable,
    write_image,
    write_json,
    write_npz,
)


def content_key(*parts: Any) -> str:
    """Stable hash of inputs: files are hashed by content, everything else by its JSON form."""
    h = hashlib.sha256()
    for part in parts:
        if isinstance(part, Path):
            if part.is_dir():
                # Hidden files and folders (temp files, a killed run's .t2bs-staging-*) are not content.
                for f in sorted(
                    p
                    for p in part.rglob("*")
                    if p.is_file() and not any(x.startswith(".") for x in p.relative_to(part).parts)
                ):
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
        info = read_json(marker)
    except (ValueError, OSError):  # a torn or garbage done.json: not done
        return False
    return isinstance(info, dict) and info.get("key") == key


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
            try:
                data = read_json(self.manifest_path)
            except ValueError as exc:
                data = None
                print(f"warning: {exc}; it is rewritten from this run on", file=sys.stderr)
            if isinstance(data, dict) and isinstance(data.get("stages", {}), dict):
                return data
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
            raise UserError(
                f"{self.root}: no character/mesh.glb (run `t2bs render MESH -o {self.root}` or `t2bs character`)"
            )
        return load_mesh(self.mesh_path)


# ------------------------------------------------------------------ safety of a shared project folder


def invalidate(job_dir: str | os.PathLike) -> None:
    """Remove ``job_dir/done.json`` before a job rewrites the folder: a run killed half-way must
    not leave the old marker beside new, half-written files (the next run would call it done)."""
    (Path(job_dir) / "done.json").unlink(missing_ok=True)


STAGING_PREFIX = ".t2bs-staging-"


class OutputSet:
    """A command's outputs written as one set: files go into ``folder`` (an empty staging folder
    inside ``final``) and ``commit()`` moves them into ``final`` together.

    Nothing in ``final`` changes before the commit, so a refusal or crash half-way (a NaN input, a
    full disk, Ctrl-C, kill -9) leaves the previous outputs whole. The commit removes ``marker``
    (the file that says the set is complete: done.json, report.json) from ``final`` first, renames
    every staged entry into place and the marker last, so a reader never takes a mixed set for a
    finished one. ``exclusive``: ``final`` holds only this set (a grid folder), so entries the new
    set does not write (masks of an earlier grid) are removed at the commit; otherwise (a user's
    -o folder) they are left alone. A set that never commits is removed when the object goes (an
    exception on the way), and staging folders of killed runs when the next set opens there (the
    project lock keeps runs apart)."""

    def __init__(self, final: str | os.PathLike, marker: str, exclusive: bool = False):
        import shutil
        import uuid
        import weakref

        self.final, self.marker, self.exclusive = Path(final), marker, exclusive
        self.final.mkdir(parents=True, exist_ok=True)
        for stale in self.final.glob(STAGING_PREFIX + "*"):
            shutil.rmtree(stale, ignore_errors=True)
        self.folder = self.final / f"{STAGING_PREFIX}{uuid.uuid4().hex[:8]}"
        self.folder.mkdir()
        self._cleanup = weakref.finalize(self, shutil.rmtree, str(self.folder), True)

    def commit(self) -> Path:
        import shutil

        (self.final / self.marker).unlink(missing_ok=True)
        if self.exclusive:
            new = {p.name for p in self.folder.iterdir()}
            for old in self.final.iterdir():
                if old != self.folder and old.name not in new:
                    shutil.rmtree(old) if old.is_dir() and not old.is_symlink() else old.unlink()
        for entry in sorted(self.folder.iterdir(), key=lambda p: p.name == self.marker):  # marker last
            target = self.final / entry.name
            if entry.is_dir() and target.is_dir():
                shutil.rmtree(target)
            os.replace(entry, target)
        self.folder.rmdir()
        return self.final

    def discard(self) -> None:
        self._cleanup()  # rmtree once (a no-op after commit removed the folder)


@contextlib.contextmanager
def output_set(final: str | os.PathLike, marker: str, exclusive: bool = False) -> Iterator[Path]:
    """``OutputSet`` as a block: yields the staging folder, commits on success, discards on failure."""
    staged = OutputSet(final, marker, exclusive)
    try:
        yield staged.folder
        staged.commit()
    finally:
        staged.discard()


LOCK_NAME = ".t2bs.lock"
_held_locks: dict[Path, list] = {}  # folder -> [open lock file, depth]: a command calling another re-enters


@contextlib.contextmanager
def project_lock(root: str | os.PathLike, command: str) -> Iterator[None]:
    """Hold an exclusive lock on the project folder while a command writes it.

    A second t2bs run on the same project (in another terminal, a script) gets one UserError line
    naming the first instead of deleting its staging folders or mixing outputs. The lock is an
    flock on DIR/.t2bs.lock, released by the kernel when the holder dies (kill -9 included), so a
    crash never leaves the project locked. Re-entrant within a process (``t2bs create`` runs the
    stage commands). A folder created here and left empty by a failed command is removed again."""
    import fcntl

    root = Path(root).absolute()
    if root in _held_locks:
        _held_locks[root][1] += 1
        try:
            yield
        finally:
            _held_locks[root][1] -= 1
        return
    if root.exists() and not root.is_dir():
        raise UserError(f"{root}: is a file, expected a project folder")
    created = not root.exists()
    try:
        root.mkdir(parents=True, exist_ok=True)
        fh = open(root / LOCK_NAME, "a+")
    except OSError as exc:
        raise UserError(
            f"{root}: cannot write to the project folder ({exc.strerror or exc}); "
            f"check its permissions, or copy it somewhere writable"
        ) from None
    try:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.seek(0)
        holder = fh.read().strip() or "another t2bs process"
        fh.close()
        raise UserError(
            f"{root}: another t2bs command is working on this project ({holder}); wait for it to "
            f"finish, or stop it, then re-run"
        ) from None
    _held_locks[root] = [fh, 1]
    ok = False
    try:
        fh.seek(0)
        fh.truncate()
        fh.write(f"pid {os.getpid()}, `t2bs {command}`, since {_now()}\n")
        fh.flush()
        yield
        ok = True
    finally:
        del _held_locks[root]
        fcntl.flock(fh, fcntl.LOCK_UN)
        fh.close()
        if created and not ok and [p.name for p in root.iterdir()] == [LOCK_NAME]:
            (root / LOCK_NAME).unlink(missing_ok=True)
            root.rmdir()
