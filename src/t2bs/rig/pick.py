"""Landmarks picked by clicking on the character (``t2bs view``): the 20 points of the auto rig and
its optional named points, saved as the JSON ``t2bs autorig --landmarks`` and the video stage read.

The viewer turns a click into a ray (origin, direction in the project's world frame); ``ray_vertex``
finds the triangle it hits first and returns that triangle's vertex nearest the hit point.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from t2bs.errors import UserError
from t2bs.rig.face import NAMED_POINTS

PICKED = "picked.json"  # DIR/landmarks/<this>: the user's points for the project's auto rig


def picked_landmarks(project) -> Path | None:
    """DIR/landmarks/picked.json of ``project`` (a t2bs.project.Project) when the user has picked points there (the
    viewer's picker, or any --landmarks JSON copied there), else None: what every auto rig of the project uses."""
    path = project.path("landmarks", PICKED)
    return path if path.exists() else None


# The 20 points in the 68-point order (36-47, 60-67): (slot, what to click). Right / left are the
# character's own (right eye on -X, image left in the frontal view).
SLOTS: list[tuple[str, str]] = [
    ("36", "right eye, outer corner"),
    ("37", "right eye, upper lid (outer third)"),
    ("38", "right eye, upper lid (inner third)"),
    ("39", "right eye, inner corner"),
    ("40", "right eye, lower lid (inner third)"),
    ("41", "right eye, lower lid (outer third)"),
    ("42", "left eye, inner corner"),
    ("43", "left eye, upper lid (inner third)"),
    ("44", "left eye, upper lid (outer third)"),
    ("45", "left eye, outer corner"),
    ("46", "left eye, lower lid (outer third)"),
    ("47", "left eye, lower lid (inner third)"),
    ("60", "mouth, right corner"),
    ("61", "upper inner lip, right"),
    ("62", "upper inner lip, middle"),
    ("63", "upper inner lip, left"),
    ("64", "mouth, left corner"),
    ("65", "lower inner lip, left"),
    ("66", "lower inner lip, middle"),
    ("67", "lower inner lip, right"),
] + [(n, f"optional: {n.replace('_', ' ')}") for n in NAMED_POINTS]


def ray_vertex(vertices: np.ndarray, faces: np.ndarray, origin, direction) -> int | None:
    """Vertex of the first triangle the ray hits nearest the hit point (Moller-Trumbore over all
    triangles); None when the ray misses the mesh."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    o = np.asarray(origin, np.float64)
    d = np.asarray(direction, np.float64)
    d = d / max(np.linalg.norm(d), 1e-12)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    e1, e2 = b - a, c - a
    p = np.cross(d, e2)
    det = (e1 * p).sum(1)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = o - a
    u = (s * p).sum(1) * inv
    q = np.cross(s, e1)
    w = (q @ d) * inv
    t = (e2 * q).sum(1) * inv
    hit = ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 0)
    if not hit.any():
        return None
    k = np.nonzero(hit)[0][np.argmin(t[hit])]
    point = o + t[k] * d
    tri = f[k]
    return int(tri[np.argmin(np.linalg.norm(v[tri] - point, axis=1))])


class LandmarkPicks:
    """The points picked so far: slot -> vertex id (the 20 are required, the named ones optional)."""

    def __init__(self, num_vertices: int):
        self.num_vertices = int(num_vertices)
        self.ids: dict[str, int] = {}

    @classmethod
    def from_file(cls, path: Path, num_vertices: int) -> "LandmarkPicks":
        """Start from an existing landmarks file (to fix a few points), else empty."""
        from t2bs.rig.face import read_landmarks_file

        picks = cls(num_vertices)
        if Path(path).is_file():
            try:
                ids, named = read_landmarks_file(path, num_vertices)
            except UserError:
                return picks
            picks.ids = {SLOTS[i][0]: int(x) for i, x in enumerate(ids)} | dict(named)
        return picks

    @classmethod
    def for_project(cls, root: Path, num_vertices: int) -> "LandmarkPicks":
        """The project's picks (landmarks/picked.json), else the points its auto rig found
        (character/autorig.json), to correct rather than click all 20."""
        import json

        picked = Path(root) / "landmarks" / PICKED
        if picked.is_file():
            return cls.from_file(picked, num_vertices)
        picks = cls(num_vertices)
        found = Path(root) / "character" / "autorig.json"
        if found.is_file():
            try:
                lm = json.loads(found.read_text())["landmarks"]
                for (slot, _), vid in zip(SLOTS, lm["vertex_ids"]):
                    picks.set(slot, int(vid))
                for slot, vid in (lm.get("named") or {}).items():
                    picks.set(slot, int(vid))
            except (ValueError, KeyError, TypeError, UserError):
                return cls(num_vertices)
        return picks

    def set(self, slot: str, vertex: int) -> None:
        if slot not in dict(SLOTS):
            raise UserError(f"unknown landmark {slot!r}")
        if not 0 <= int(vertex) < self.num_vertices:
            raise UserError(f"vertex {vertex} is not in 0..{self.num_vertices - 1}")
        self.ids[slot] = int(vertex)

    def missing(self) -> list[str]:
        return [s for s, _ in SLOTS[:20] if s not in self.ids]

    def next_slot(self, after: str | None = None) -> str:
        """The first unset required slot after ``after`` (wrapping), else the slot after it."""
        names = [s for s, _ in SLOTS]
        start = names.index(after) + 1 if after in names else 0
        order = names[start:] + names[:start]
        for s in order:
            if s in [m for m in self.missing()]:
                return s
        return order[0]

    def to_dict(self) -> dict:
        if self.missing():
            raise UserError(f"landmarks not picked yet: {', '.join(self.missing())} (68-point numbers)")
        return {
            "vertex_ids": [self.ids[s] for s, _ in SLOTS[:20]],
            "backend": "picked",
            "named": {s: self.ids[s] for s, _ in SLOTS[20:] if s in self.ids},
        }

    def save(self, path: Path) -> Path:
        from t2bs.project import write_json

        write_json(Path(path), self.to_dict())
        return Path(path)
