"""Control points of the LBS deformation (paper §3.2 and appendix "number of control points").

k control points are spread uniformly over the static asset by farthest-point sampling of its
vertices. Each Gaussian (= mesh vertex) is bound to its ``knn`` nearest control points; the
blending weights are normalised inverse Mahalanobis distances, where each control point's
covariance is the spread of the vertices closest to it (its Voronoi cell on the surface), so a
control point reaches further along the surface it covers than across it. Associations and
weights are computed once on the rest pose and stay fixed (the paper's modular design).

"Nearest" is measured along the mesh (shortest path over edges, with the copies of a vertex that
an exporter split at a UV or normal seam welded into one point) where the mesh connects the
two points, and as the straight-line distance plus half the bounding-box diagonal where it does
not (another part: eyeball vs eyelid, teeth vs lips): with a purely Euclidean
KNN the upper lip would be skinned to lower-lip control points across a closed mouth, and the
eyelids to the eyeball, so opening the mouth would drag both lips. Set ``geodesic=False`` for
the paper's plain Euclidean KNN.

Farthest-point sampling spreads points by space, so a small part (a lip, the inside of a mouth, a
tooth) may get one control point or none, and its vertices are then skinned mostly to another
part's. Topping each part up to a minimum of its own was measured and not kept (docs/VCDGS_NOTES.md,
"A minimum of control points per part").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from t2bs.geometry.mesh import weld_index, welded_edges


@dataclass
class ControlPoints:
    positions: np.ndarray  # [K, 3] float32 control points p_k (rest pose)
    vertex_index: np.ndarray  # [K] int64 the mesh vertex each control point sits on
    neighbours: np.ndarray  # [N, knn] int64 control points bound to each Gaussian
    weights: np.ndarray  # [N, knn] float32 LBS weights, rows sum to 1
    cp_neighbours: np.ndarray  # [K, m] int64 nearest other control points (rigidity regulariser)


def farthest_point_sampling(points: np.ndarray, k: int, seed: int = 0) -> np.ndarray:
    """[k] indices of points spread uniformly: each new point is the farthest from those chosen; the first is drawn
    with ``seed``."""
    pts = np.asarray(points, dtype=np.float64)
    n = pts.shape[0]
    k = min(int(k), n)
    chosen = [int(np.random.default_rng(seed).integers(n))]
    dist = np.linalg.norm(pts - pts[chosen[0]], axis=1)
    while len(chosen) < k:
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(pts - pts[chosen[-1]], axis=1))
    return np.asarray(chosen, dtype=np.int64)


def _surface_distances(vertices: np.ndarray, faces: np.ndarray | None, sources: np.ndarray) -> np.ndarray:
    """[K, N] distance from each source vertex to every vertex: along edges, else Euclidean + diag / 2."""
    v = np.asarray(vertices, dtype=np.float64)
    eucl = np.linalg.norm(v[sources][:, None, :] - v[None, :, :], axis=-1)  # [K, N]
    if faces is None or len(faces) == 0:
        return eucl
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    # Paths run over the welded mesh: copies of a vertex split at a UV seam are one point.
    node, first = weld_index(v)
    e = welded_edges(node, faces)
    length = np.linalg.norm(v[first[e[:, 0]]] - v[first[e[:, 1]]], axis=1)
    m = len(first)
    graph = coo_matrix((length, (e[:, 0], e[:, 1])), shape=(m, m)).tocsr()
    geo = dijkstra(graph, directed=False, indices=node[sources])[:, node]  # [K, N], inf where not connected
    # Not connected: behind every control point of the vertex's own part, still ordered by distance.
    far = 0.5 * float(np.linalg.norm(v.max(0) - v.min(0)))
    return np.where(np.isfinite(geo), np.maximum(geo, eucl), eucl + far)


def build_control_points(
    vertices: np.ndarray,
    faces: np.ndarray | None = None,
    k: int = 400,
    knn: int = 10,
    cp_neighbours: int = 6,
    geodesic: bool = True,
    seed: int = 0,
) -> ControlPoints:
    """Farthest-point control points on ``vertices`` [N, 3] and fixed Mahalanobis LBS weights."""
    v = np.asarray(vertices, dtype=np.float64)
    n = v.shape[0]
    idx = farthest_point_sampling(v, k, seed)
    p = v[idx]  # [K, 3]
    kk = len(idx)
    knn = min(knn, kk)
    dist = _surface_distances(v, faces if geodesic else None, idx)  # [K, N]
    nearest = np.argsort(dist, axis=0)[:knn].T  # [N, knn]
    # Covariance of each control point's cell (vertices whose nearest control point it is),
    # regularised by the mean spacing so that tiny or flat cells stay invertible.
    owner = nearest[:, 0]
    spacing = float(np.median(np.sort(np.linalg.norm(p[:, None] - p[None], axis=-1), axis=1)[:, 1])) if kk > 1 else 1.0
    eps = (0.5 * spacing) ** 2
    cov = np.repeat(np.eye(3)[None] * eps, kk, axis=0)
    for c in range(kk):
        d = v[owner == c] - p[c]
        if len(d) >= 3:
            cov[c] += d.T @ d / len(d)
    inv = np.linalg.inv(cov)  # [K, 3, 3]
    diff = v[:, None, :] - p[nearest]  # [N, knn, 3]
    maha = np.sqrt(np.einsum("nki,nkij,nkj->nk", diff, inv[nearest], diff))  # [N, knn]
    # The straight-line Mahalanobis distance knows nothing of the mesh; scale it by how much
    # longer the path along the surface is, so control points across a gap weigh less.
    ratio = dist[nearest, np.arange(n)[:, None]] / np.maximum(np.linalg.norm(diff, axis=-1), 1e-12)
    w = 1.0 / (maha * np.maximum(ratio, 1.0) + 1e-6)
    w /= w.sum(1, keepdims=True)
    m = min(cp_neighbours, kk - 1)
    cp_nb = np.argsort(dist[:, idx], axis=1)[:, 1 : m + 1] if m > 0 else np.zeros((kk, 0), np.int64)
    return ControlPoints(
        p.astype(np.float32), idx, nearest.astype(np.int64), w.astype(np.float32), cp_nb.astype(np.int64)
    )
