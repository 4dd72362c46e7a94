"""Motion of the mesh parts that no training view sees at rest (our addition, docs/VCDGS_NOTES.md).

Teeth behind closed lips, a mouth bag, the inside of an eyelid: separate parts of the asset that
every training view hides at rest. Their Gaussians are bound to control points whose motion the
images set elsewhere (the lips, the skin in front), so after training they follow a blend of the
motions around them: on facecap's "mouth wide" the lower teeth stay with the head while the jaw
drops. Images do see them once the mouth opens, but at 2 px a tooth the splat loss barely pulls.

After training, each such part may take one of a few rigid motions instead of its own: those of
clusters of the seen vertices (k-means over their reconstructed trajectories, so the jaw, the
skull and the cheeks come out as separate clusters), each fitted per frame (Kabsch). The pick
compares mesh renders of the output with the training images at a few views near the canonical
one, part by part (largest first), and keeps a part's own motion unless another one lowers the
L1 image difference; a part that changes no rendered pixel under any candidate keeps its own.
Opt-in (``config.hidden_pick``): it helps where a mouth opens wide and is noise elsewhere.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from t2bs.geometry.camera import Camera
from t2bs.geometry.mesh import Mesh, weld_index, welded_edges


@dataclass
class HiddenPick:
    """What ``pick_hidden_motions`` did: which parts, which motion each got, and what it cost."""
    parts: list[np.ndarray] = field(default_factory=list)  # vertex indices of each hidden part
    picks: list[int] = field(default_factory=list)  # per part: -1 own motion, else the cluster index
    observable: list[bool] = field(default_factory=list)  # per part: some candidate changes a rendered pixel
    views: list[int] = field(default_factory=list)  # views the renders were compared at
    loss_before: float = 0.0  # mean L1 image difference with every part's own motion
    loss_after: float = 0.0  # same after the picks
    sweeps: int = 0  # passes over the parts that ran
    seconds: float = 0.0

    def summary(self) -> dict:
        return {"hidden_parts": len(self.parts), "observable": int(sum(self.observable)),
                "moved": int(sum(p >= 0 for p in self.picks)), "views": self.views,
                "loss_before": round(self.loss_before, 6), "loss_after": round(self.loss_after, 6),
                "seconds": round(self.seconds, 1)}


def mesh_components(mesh: Mesh) -> np.ndarray:
    """[N] int64 connected-part label of each vertex, over the welded mesh (UV-seam copies are one point)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    node, first = weld_index(mesh.vertices)
    e = welded_edges(node, mesh.faces) if len(mesh.faces) else np.zeros((0, 2), np.int64)
    m = len(first)
    adj = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(m, m))
    _, label = connected_components(adj, directed=False)
    return label[node].astype(np.int64)


def hidden_parts(mesh: Mesh, seen: np.ndarray, min_vertices: int = 20) -> list[np.ndarray]:
    """Vertex indices of each connected part with no vertex in ``seen`` [N] bool and at least
    ``min_vertices`` vertices (smaller ones are specks, not worth a render), largest first."""
    label = mesh_components(mesh)
    out = [np.flatnonzero(label == p) for p in np.unique(label)]
    out = [ix for ix in out if len(ix) >= min_vertices and not seen[ix].any()]
    return sorted(out, key=len, reverse=True)


def cluster_motions(rest: np.ndarray, vertices: np.ndarray, seen: np.ndarray, clusters: int = 8, seed: int = 0,
                    min_size: int = 10) -> tuple[np.ndarray, np.ndarray]:
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


def apply_motion(rotations: np.ndarray, translations: np.ndarray, points: np.ndarray) -> np.ndarray:
    """rotations [T, 3, 3], translations [T, 3], rest points [n, 3] -> [T, n, 3]."""
    return np.einsum("tij,nj->tni", rotations, points) + translations[:, None]


def compare_views(cameras: list[Camera], canonical: int, candidates: list[int], count: int = 5,
                  min_separation_deg: float = 15.0, max_angle_deg: float = 40.0) -> list[int]:
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


def render_losses(renderer, mesh: Mesh, vertices: np.ndarray, images: np.ndarray, cameras: list[Camera],
                  views: list[int], frames: list[int], shading: str = "lambert") -> np.ndarray:
    """[len(views) * len(frames)] mean L1 difference between mesh renders of ``vertices`` [T, N, 3] and
    ``images`` [V, T, H, W, 3] (float 0..1, at ``cameras``' size), view-major."""
    return np.array([np.abs(renderer.render(mesh, cameras[v], vertices=vertices[t], shading=shading).rgb
                            - images[v, t]).mean() for v in views for t in frames])


def pick_hidden_motions(mesh: Mesh, vertices: np.ndarray, seen: np.ndarray, images: np.ndarray,
                        cameras: list[Camera], views: list[int], frames: list[int], shading: str = "lambert",
                        clusters: int = 8, min_vertices: int = 20, seed: int = 0,
                        renderer=None, sweeps: int = 1) -> tuple[np.ndarray, HiddenPick]:
    """``vertices`` [T, N, 3] with each hidden part's motion replaced by the candidate rigid motion
    whose mesh renders best match ``images`` [V, T, H, W, 3] (float 0..1, at ``cameras``' size) at
    ``views`` x ``frames`` (module docstring). ``seen`` [N] bool: vertices some training view sees
    at rest. ``sweeps``: passes over the parts (coordinate descent on the render loss, stopping early
    when a pass moves nothing); 1 is the default and what ``config.hidden_pick`` runs: more sweeps lower
    the loss but not the vertex error on facecap (benchmarks/hidden_pick.py). Returns (vertices, HiddenPick)."""
    import time

    from t2bs.render.mesh_renderer import MeshRenderer

    t0 = time.time()
    out = np.array(vertices, np.float32, copy=True)
    report = HiddenPick(parts=hidden_parts(mesh, seen, min_vertices), views=list(views))
    if not report.parts:
        report.seconds = time.time() - t0
        return out, report
    rots, trans = cluster_motions(mesh.vertices, out, seen, clusters, seed)
    own = renderer is None
    r = MeshRenderer() if own else renderer
    try:
        def losses(verts: np.ndarray) -> np.ndarray:
            return render_losses(r, mesh, verts, images, cameras, views, frames, shading)

        base = losses(out)
        report.loss_before = float(base.mean())
        own_motion = [out[:, ix].copy() for ix in report.parts]
        report.picks = [-1] * len(report.parts)
        for sweep in range(sweeps):
            moved = False
            for p, ix in enumerate(report.parts):
                pick, pick_losses, pick_motion, changed = report.picks[p], base, out[:, ix], False
                for c in range(-1, len(rots)):  # -1: the part's own motion (an option from the second sweep on)
                    if c == report.picks[p]:
                        continue
                    trial = out.copy()
                    trial[:, ix] = motion = own_motion[p] if c < 0 else apply_motion(rots[c], trans[c], mesh.vertices[ix])
                    trial_losses = losses(trial)
                    changed = changed or bool(np.any(trial_losses != base))
                    if trial_losses.mean() < pick_losses.mean():
                        pick, pick_losses, pick_motion = c, trial_losses, motion
                if sweep == 0:
                    report.observable.append(changed)
                moved = moved or pick != report.picks[p]
                report.picks[p] = pick
                out[:, ix] = pick_motion
                base = pick_losses
            report.sweeps = sweep + 1
            if not moved:
                break
        report.loss_after = float(base.mean())
    finally:
        if own:
            r.release()
    report.seconds = time.time() - t0
    return out, report
