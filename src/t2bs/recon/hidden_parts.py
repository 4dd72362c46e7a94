"""Motion of the mesh parts that no training view sees at rest (our addition, docs/VCDGS_NOTES.md).

Teeth behind closed lips, a mouth bag, the inside of an eyelid: separate parts of the asset that
every training view hides at rest. Their Gaussians are bound to control points whose motion the
images set elsewhere (the lips, the skin in front), so after training they follow a blend of the
motions around them: on facecap's "mouth wide" the lower teeth stay with the head while the jaw
drops. Images do see them once the mouth opens, but at 2 px a tooth the splat loss barely pulls.

After training, such parts may take one of a few rigid motions instead of their own: those of
clusters of the seen vertices (k-means over their reconstructed trajectories, so the jaw, the
skull and the cheeks come out as separate clusters), each fitted per frame (Kabsch). The pick
compares mesh renders of the output with the training images at a few views near the canonical
one and keeps the own motion unless another one lowers the L1 image difference.

Parts are decided in groups, not one by one: decided alone, an upper tooth moved down with the jaw
fills the opening where the images show the lower teeth (the reconstructed upper lip sits a pixel
low and covers the upper teeth the images show), so a part-by-part pick lowers the image loss while
moving the teeth wrongly. The groups come from the opening that reveals the parts: pairs of seen
vertices that touch at rest and move apart (the lips) give a plane through the slit, with the
normal along their separation, and each hidden part goes by where it lies. Two rules group them
(``GROUPINGS``): by share, wholly on one side, wholly on the other, across evenly (a mouth bag, whose
floor and roof move apart) or across but mostly on one side (upper teeth reaching below the lips'
line); by centroid, across evenly, else the side its centroid lies on. Neither is right on every
mouth: teeth overlap the slit, so the share rule can leave upper and lower teeth in one leftover
group that no single motion fits (facecap's wide mouth), while the centroid rule extrapolates a
tilted slit plane deep into the mouth and puts back upper teeth with the lower row (facecap's tongue,
whose protruding tongue tilts the lips' separation forward). A group takes one motion for all its
parts, by coordinate descent over the groups, once per rule; the rule whose pick renders closer to
the images is kept (a grouping that mixes the rows cannot reach as low a loss). The group across
the slit evenly keeps its own motion (``SPANNING``): its sides part with the opening, which no one
rigid motion does; given a cluster's motion for a lower render loss, facecap's mouth bag (wide mouth)
went from p2p 0.011 to 0.034, worse than the rigid oracle's 0.024 (session 44). An opening reveals only
what lies within its own length of it (``revealing_openings``): a blink's lids part too, and
teeth grouped by an eye's slit took a closing lid's turn, unseen inside the head. Where nothing
opens near a part, no render can tell its motions apart: with ``closed_rigid``
(``config.hidden_parts.hidden_pick_closed_rigid``, on by default) such a part takes the seen
surface's dominant rigid motion (``robust_rigid_motion``: the head's), since a smile or a blink
deforms the lips around the teeth, whose blend of control points then drags them along while they
should follow the skull; without it nothing moves.
On by default (``config.hidden_parts.hidden_pick``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from t2bs.geometry.camera import Camera
from t2bs.geometry.mesh import Mesh, welded_components
from t2bs.geometry.rigid import apply_motion, robust_rigid_motion


@dataclass
class Opening:
    """Where the seen surface opens (``find_openings``): a plane through the slit, in rest coordinates."""

    point: np.ndarray  # [3] mean of the opening pairs' rest midpoints
    normal: np.ndarray  # [3] unit: the pairs' main direction of separation, towards where the side that moves more goes
    pairs: int  # pairs of seen vertices that open
    frame: int  # frame where they are open widest
    midpoints: np.ndarray | None = None  # [P, 3] the pairs' rest midpoints
    extent: float = 0.0  # the slit's length: twice the largest distance of a midpoint from ``point``

    def distance(self, points: np.ndarray) -> float:
        """Smallest distance from ``points`` [M, 3] (rest coordinates) to the slit's midpoints."""
        from scipy.spatial import cKDTree

        return float(cKDTree(self.midpoints).query(np.asarray(points, np.float64))[0].min())


@dataclass
class HiddenPick:
    """What ``pick_hidden_motions`` did: which parts, how they were grouped, which motion each group got."""

    parts: list[np.ndarray] = field(default_factory=list)  # vertex indices of each hidden part
    groups: list[list[int]] = field(default_factory=list)  # part indices of each group of the kept rule, in order
    spanning: list[bool] = field(default_factory=list)  # per group: across the opening evenly, kept on its own motion
    grouping: str = ""  # the kept rule (GROUPINGS): its pick's render loss was the lowest
    grouping_losses: dict = field(default_factory=dict)  # rule -> mean L1 after its pick (rules grouping alike: one)
    picks: list[int] = field(default_factory=list)  # per part: -1 own motion, else the cluster index
    observable: list[bool] = field(default_factory=list)  # per group: some candidate changes a rendered pixel
    openings: list[Opening] = field(default_factory=list)  # the slits that reveal some part (``revealing_openings``)
    revealed_by: list[int] = field(default_factory=list)  # per part: its index in find_openings' list, -1 for none
    closed_rigid: bool = False  # the parts no opening reveals took the seen surface's robust rigid motion
    views: list[int] = field(default_factory=list)  # views the renders were compared at
    loss_before: float = 0.0  # mean L1 image difference with every part's own motion
    loss_after: float = 0.0  # same after the picks
    sweeps: int = 0  # passes over the groups that ran (the kept rule's)
    seconds: float = 0.0

    @property
    def opening(self) -> Opening | None:
        """The first of ``openings`` (the most pairs); None: no opening reveals a part."""
        return self.openings[0] if self.openings else None

    def summary(self) -> dict:
        return {
            "hidden_parts": len(self.parts),
            "groups": [len(g) for g in self.groups],
            "spanning": int(sum(self.spanning)),
            "grouping": self.grouping,
            "grouping_losses": {k: round(v, 6) for k, v in self.grouping_losses.items()},
            "opening_pairs": sum(o.pairs for o in self.openings),
            "openings": len(self.openings),
            "unrevealed": int(sum(k < 0 for k in self.revealed_by)),
            "observable": int(sum(self.observable)),
            "closed_rigid": self.closed_rigid,
            "moved": int(sum(p >= 0 for p in self.picks))
            + (int(sum(k < 0 for k in self.revealed_by)) if self.closed_rigid else 0),
            "views": self.views,
            "loss_before": round(self.loss_before, 6),
            "loss_after": round(self.loss_after, 6),
            "sweeps": self.sweeps,
            "seconds": round(self.seconds, 1),
        }


def hidden_parts(mesh: Mesh, seen: np.ndarray, min_vertices: int = 20) -> list[np.ndarray]:
    """Vertex indices of each connected part with no vertex in ``seen`` [N] bool and at least
    ``min_vertices`` vertices (smaller ones are specks, not worth a render), largest first."""
    label = welded_components(mesh.vertices, mesh.faces)
    out = [np.flatnonzero(label == p) for p in np.unique(label)]
    out = [ix for ix in out if len(ix) >= min_vertices and not seen[ix].any()]
    return sorted(out, key=len, reverse=True)


def cluster_motions(
    rest: np.ndarray, vertices: np.ndarray, seen: np.ndarray, clusters: int = 8, seed: int = 0, min_size: int = 10
) -> tuple[np.ndarray, np.ndarray]:
    """Rigid motions of clusters of the seen vertices: rest [N, 3], vertices [T, N, 3], seen [N] bool
    -> (rotations [C, T, 3, 3], translations [C, T, 3]), C <= ``clusters`` (clusters under
    ``min_size`` vertices are dropped). Features: each seen vertex's displacement over time plus
    half its rest position (both standardised), so a cluster moves together and is in one piece."""
    import roma
    import torch
    from scipy.cluster.vq import kmeans2

    none = np.zeros((0, len(vertices), 3, 3)), np.zeros((0, len(vertices), 3))
    idx = np.flatnonzero(seen)
    if len(idx) < max(min_size, clusters):
        return none
    disp = (vertices[:, idx] - rest[idx][None]).transpose(1, 0, 2).reshape(len(idx), -1)
    feat = np.concatenate([disp / max(disp.std(), 1e-12), 0.5 * rest[idx] / max(rest[idx].std(), 1e-12)], 1)
    _, label = kmeans2(feat.astype(np.float64), clusters, minit="++", seed=seed)
    rots, trans = [], []
    for c in range(clusters):
        members = idx[label == c]
        if len(members) < min_size:
            continue
        x = torch.as_tensor(rest[members], dtype=torch.float64).expand(len(vertices), -1, -1)
        r, t = roma.rigid_points_registration(x, torch.as_tensor(vertices[:, members], dtype=torch.float64))
        rots.append(r.numpy())
        trans.append(t.numpy())
    return (np.stack(rots), np.stack(trans)) if rots else none


def compare_views(
    cameras: list[Camera],
    canonical: int,
    candidates: list[int],
    count: int = 5,
    min_separation_deg: float = 15.0,
    max_angle_deg: float = 40.0,
) -> list[int]:
    """Up to ``count`` of ``candidates`` (the canonical view first), each within ``max_angle_deg`` of
    the canonical view's direction and ``min_separation_deg`` from every view already chosen: views
    that see into the mouth from different sides, without near-duplicates."""

    def angle(a: int, b: int) -> float:  # between the viewing directions (OpenCV camera z axes in the world)
        za, zb = cameras[a].world_to_camera[2, :3], cameras[b].world_to_camera[2, :3]
        return float(np.degrees(np.arccos(np.clip(za @ zb / np.linalg.norm(za) / np.linalg.norm(zb), -1.0, 1.0))))

    chosen = [canonical]
    for v in sorted(candidates, key=lambda v: angle(v, canonical)):
        if len(chosen) >= count or angle(v, canonical) > max_angle_deg:
            break
        if v not in chosen and all(angle(v, u) >= min_separation_deg for u in chosen):
            chosen.append(v)
    return chosen


def render_losses(
    renderer,
    mesh: Mesh,
    vertices: np.ndarray,
    images: np.ndarray,
    cameras: list[Camera],
    views: list[int],
    frames: list[int],
    shading: str = "lambert",
) -> np.ndarray:
    """[len(views) * len(frames)] mean L1 difference between mesh renders of ``vertices`` [T, N, 3] and
    ``images`` [V, T, H, W, 3] (float 0..1, at ``cameras``' size), view-major."""
    losses = np.empty((len(views), len(frames)))
    view_cameras = [cameras[v] for v in views]
    for j, t in enumerate(frames):  # each pose uploaded once, drawn from every view
        for i, rgb in enumerate(renderer.render_rgb(mesh, view_cameras, vertices[t], shading)):
            losses[i, j] = np.abs(rgb - images[views[i], t]).mean()
    return losses.ravel()


def find_openings(
    rest: np.ndarray,
    vertices: np.ndarray,
    seen: np.ndarray,
    radius: float = 0.01,
    min_gap: float = 0.01,
    link: float = 0.02,
) -> list[Opening]:
    """Every slit where the seen surface opens, the one with the most pairs first (none: an empty list): rest
    [N, 3], vertices [T, N, 3], seen [N] bool. Opening pairs: seen vertices within ``radius`` of each other at rest
    that move more than ``min_gap`` further apart in some frame (all three fractions of the rest bounding-box
    diagonal); skin that merely stretches does not double its edges, lips that part do. Pairs whose rest midpoints
    lie within ``link`` (or twice the pairs' median spacing, if more) of each other form one slit: a mouth, each
    closing eye's lids."""
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    idx = np.flatnonzero(seen)
    diag = float(np.linalg.norm(rest.max(0) - rest.min(0)))
    if len(idx) < 2 or diag <= 0:
        return []
    x = rest[idx].astype(np.float64)
    pairs = cKDTree(x).query_pairs(radius * diag, output_type="ndarray")
    if not len(pairs):
        return []
    i_all, j_all = idx[pairs[:, 0]], idx[pairs[:, 1]]
    grow = np.linalg.norm(vertices[:, i_all] - vertices[:, j_all], axis=-1) - np.linalg.norm(
        x[pairs[:, 0]] - x[pairs[:, 1]], axis=-1
    )
    opens = grow.max(0) > min_gap * diag
    if not opens.any():
        return []
    mid = cKDTree(0.5 * (rest[i_all[opens]] + rest[j_all[opens]]))
    if mid.n > 1:  # on a coarse mesh the pairs along one slit lie further apart: link at twice their usual spacing
        link = max(link, 2.0 * float(np.median(mid.query(mid.data, k=2)[0][:, 1])) / diag)
    _, slit = connected_components(mid.sparse_distance_matrix(mid, link * diag), directed=False)
    out = []
    for s in np.argsort(-np.bincount(slit), kind="stable"):
        members = np.flatnonzero(opens)[slit == s]
        i, j = i_all[members], j_all[members]
        frame = int(np.argmax(grow[:, members].sum(1)))
        sep = (vertices[frame, i] - vertices[frame, j]) - (rest[i] - rest[j])  # [P, 3], each pair's sign arbitrary
        normal = np.linalg.eigh(sep.T.astype(np.float64) @ sep)[1][:, -1]  # main axis of the separations
        # Its sign: towards where the side that moves more goes (down, for a jaw): GROUPINGS' "moving side".
        move_i, move_j = vertices[frame, i] - rest[i], vertices[frame, j] - rest[j]
        mover = np.where((np.linalg.norm(move_i, axis=-1) >= np.linalg.norm(move_j, axis=-1))[:, None], move_i, move_j)
        normal = normal if float((mover @ normal).sum()) >= 0 else -normal
        mids = 0.5 * (rest[i] + rest[j])
        point = mids.mean(0)
        extent = 2.0 * float(np.linalg.norm(mids.astype(np.float64) - point, axis=-1).max())
        out.append(Opening(point, normal, len(members), frame, mids, extent))
    return out


def revealing_openings(rest: np.ndarray, parts: list[np.ndarray], openings: list[Opening]) -> list[int]:
    """Per part, the index of the opening that reveals it, or -1: the nearest slit among those that lie within
    their own length (``Opening.extent``) of the part. Why: an opening shows what lies behind it to about its own
    width; a blink's parting lids (a cartoon shark's eye, 0.3 of the head away from its teeth) cannot show teeth,
    and a render-picked motion for them from there moves them unseen inside the head (session 43: the shark's teeth
    took a closing lid's 58-degree turn, at 5e-7 of the render loss)."""
    out = []
    for ix in parts:
        dist = [o.distance(rest[ix]) for o in openings]
        near = [k for k, d in enumerate(dist) if d <= openings[k].extent]
        out.append(min(near, key=lambda k: dist[k]) if near else -1)
    return out


# The grouping rules (``group_parts``) and, for each, where a hidden part may lie relative to the opening's plane,
# in this order; the moving side is the one the normal points to.
GROUPINGS = {
    "share": ("moving side", "other side", "across, evenly", "across, mostly one side"),
    "centroid": ("moving side", "other side", "across, evenly"),
}
SPANNING = "across, evenly"  # the group that keeps its own motion (``pick_hidden_motions``)


def part_sides(
    rest: np.ndarray,
    parts: list[np.ndarray],
    opening: Opening,
    side_fraction: float = 0.9,
    even: float = 0.7,
    rule: str = "share",
) -> list[int]:
    """Per part, where it lies relative to ``opening``'s plane: an index into ``GROUPINGS[rule]``. ``rule="share"``:
    a part with at least ``side_fraction`` of its vertices on one side lies on that side; one across the plane lies
    across evenly when the shorter of its two reaches past the plane is at least ``even`` of the longer, else across
    mostly on one side. ``rule="centroid"``: across evenly as before, else on the side of its mean signed distance
    (``side_fraction`` unused)."""
    if rule not in GROUPINGS:
        raise ValueError(f"part_sides: unknown rule {rule!r}; use one of {', '.join(GROUPINGS)}")
    label = []
    for ix in parts:
        s = (rest[ix] - opening.point) @ opening.normal
        above = float((s > 0).mean())
        reach = sorted([max(float(s.max()), 0.0), max(float(-s.min()), 0.0)])
        evenly = reach[0] >= even * reach[1]
        if rule == "centroid":
            label.append(2 if evenly else 0 if float(s.mean()) > 0 else 1)
        else:
            label.append(0 if above >= side_fraction else 1 if above <= 1 - side_fraction else 2 if evenly else 3)
    return label


def group_parts(sides: list[int], rule: str = "share") -> list[list[int]]:
    """Part indices of each group in ``GROUPINGS[rule]`` (empty groups dropped) from the parts' ``part_sides``."""
    groups = ([p for p, side in enumerate(sides) if side == k] for k in range(len(GROUPINGS[rule])))
    return [g for g in groups if g]


def pick_hidden_motions(
    mesh: Mesh,
    vertices: np.ndarray,
    seen: np.ndarray,
    images: np.ndarray,
    cameras: list[Camera],
    views: list[int],
    frames: list[int],
    shading: str = "lambert",
    clusters: int = 8,
    min_vertices: int = 20,
    seed: int = 0,
    renderer=None,
    sweeps: int = 4,
    closed_rigid: bool = True,
    side_fraction: float = 0.9,
    even: float = 0.7,
) -> tuple[np.ndarray, HiddenPick]:
    """``vertices`` [T, N, 3] with each group of hidden parts moved by the candidate rigid motion whose
    mesh renders best match ``images`` [V, T, H, W, 3] (float 0..1, at ``cameras``' size) at
    ``views`` x ``frames`` (module docstring). ``seen`` [N] bool: vertices some training view sees
    at rest. ``sweeps``: at most this many passes of coordinate descent over the groups (each group
    takes the option that lowers the render loss most, the others fixed); it stops early when a pass
    moves nothing. ``closed_rigid``: a hidden part no opening reveals (``revealing_openings``; all of them where
    nothing opens) takes ``robust_rigid_motion`` of the seen vertices instead of keeping its own (False: it keeps its
    own). Each revealing opening groups the parts it reveals by its own plane. ``side_fraction``, ``even``: the grouping
    rules' thresholds (``part_sides``); the descent runs once per rule in ``GROUPINGS`` (from the parts' own
    motion each time; the ``SPANNING`` group is not searched) and the rule whose pick has the lower render loss is
    kept. Returns (vertices, HiddenPick)."""
    import time

    from t2bs.render.mesh_renderer import MeshRenderer

    t0 = time.time()
    out = np.array(vertices, np.float32, copy=True)
    report = HiddenPick(parts=hidden_parts(mesh, seen, min_vertices), views=list(views))
    report.picks = [-1] * len(report.parts)
    openings = find_openings(mesh.vertices, out, seen) if report.parts else []
    report.revealed_by = revealing_openings(mesh.vertices, report.parts, openings)
    used = sorted({k for k in report.revealed_by if k >= 0})
    report.openings = [openings[k] for k in used]
    closed = [p for p, k in enumerate(report.revealed_by) if k < 0]
    if closed and closed_rigid and seen.sum() >= 3:
        head_rots, head_trans = robust_rigid_motion(mesh.vertices[seen], out[:, seen])
        for p in closed:
            out[:, report.parts[p]] = apply_motion(head_rots, head_trans, mesh.vertices[report.parts[p]])
        report.closed_rigid = True
    rots, trans = cluster_motions(mesh.vertices, out, seen, clusters, seed) if report.opening else ([], [])
    if not len(rots):
        report.seconds = time.time() - t0
        return out, report
    own = renderer is None
    r = MeshRenderer() if own else renderer
    try:

        def moved(current: np.ndarray, group: list[int], c: int) -> np.ndarray:
            """A copy of ``current`` with the group's parts on option c (-1: each part's own motion)."""
            trial = current.copy()
            for p in group:
                ix = report.parts[p]
                trial[:, ix] = vertices[:, ix] if c < 0 else apply_motion(rots[c], trans[c], mesh.vertices[ix])
            return trial

        def descend(groups: list[list[int]], fixed: list[bool], start: np.ndarray, base: np.ndarray) -> tuple:
            """Coordinate descent over ``groups`` (those ``fixed`` keep their own motion) from ``start`` (render
            losses ``base``) -> (vertices, losses, choice per group, observable per group, sweeps run)."""
            choice, observable, done = [-1] * len(groups), [False] * len(groups), 0
            for sweep in range(sweeps):
                changed = False
                for g, group in enumerate(groups):
                    if fixed[g]:
                        continue
                    for c in range(-1, len(rots)):
                        if c == choice[g]:
                            continue
                        trial = moved(start, group, c)
                        trial_losses = render_losses(r, mesh, trial, images, cameras, views, frames, shading)
                        observable[g] = observable[g] or bool(np.any(trial_losses != base))
                        if trial_losses.mean() < base.mean():  # strictly lower: ties keep the current option
                            choice[g], base, start, changed = c, trial_losses, trial, True
                done = sweep + 1
                if not changed:
                    break
            return start, base, choice, observable, done

        base = render_losses(r, mesh, out, images, cameras, views, frames, shading)
        report.loss_before = float(base.mean())
        best = None
        for rule in GROUPINGS:
            groups, spanning = [], []  # each revealing opening's groups, in the parts' own indices
            for k in used:
                mine = [p for p, by in enumerate(report.revealed_by) if by == k]
                sides = part_sides(
                    mesh.vertices, [report.parts[p] for p in mine], openings[k], side_fraction, even, rule
                )
                local = group_parts(sides, rule)
                groups += [[mine[q] for q in g] for g in local]
                # A group across the slit evenly (a mouth bag: its floor follows the jaw, its roof the skull) keeps
                # its own motion, which can stretch with the opening: one rigid motion for all of it cannot.
                spanning += [GROUPINGS[rule][sides[g[0]]] == SPANNING for g in local]
            if best is not None and groups == best[0]:
                continue  # grouped alike: the same descent
            picked, losses, choice, observable, done = descend(groups, spanning, out, base)
            report.grouping_losses[rule] = float(losses.mean())
            if best is None or losses.mean() < best[3].mean():  # strictly lower: ties keep the earlier rule
                best = (groups, spanning, picked, losses, choice, observable, done, rule)
        report.groups, report.spanning, out, base, choice, report.observable, report.sweeps, report.grouping = best
        for g, group in enumerate(report.groups):
            for p in group:
                report.picks[p] = choice[g]
        report.loss_after = float(base.mean())
    finally:
        if own:
            r.release()
    report.seconds = time.time() - t0
    return out, report
