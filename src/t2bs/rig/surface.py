"""Geodesic distances on a mesh: shortest paths along its edges, never through the air.

The auto rig's falloffs and the lip-seam finder measure along the surface, so that a weight or a
distance never crosses an opening (the lips, an eyelid slit) the way a straight line would.
"""

from __future__ import annotations

import numpy as np

from t2bs.geometry.mesh import weld_index, welded_edges


class Surface:
    """Geodesic distances along a mesh's edges (UV-seam copies of a vertex welded into one node)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, glue: float = 0.0, exclude: np.ndarray | None = None):
        """``glue`` > 0: parts whose surfaces come within ``glue`` of each other (lips laid on a head,
        a separate jaw under the cheeks) are joined there, so a falloff flows from one to the other;
        ``exclude`` [N] bool vertices are never joined (eyeballs)."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        self.node, first = weld_index(vertices)  # [N] node of each vertex, [M] a vertex of each node
        e = welded_edges(self.node, faces)
        vn = np.asarray(vertices, np.float64)[first]
        m = len(first)
        if glue > 0:
            from scipy.spatial import cKDTree

            _, part = connected_components(
                coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(m, m)), directed=False
            )
            pairs = cKDTree(vn).query_pairs(glue, output_type="ndarray")
            ok = part[pairs[:, 0]] != part[pairs[:, 1]]
            if exclude is not None:
                bad = np.zeros(m, bool)
                bad[self.node[np.asarray(exclude, bool)]] = True
                ok &= ~bad[pairs[:, 0]] & ~bad[pairs[:, 1]]
            e = np.concatenate([e, pairs[ok]])
        length = np.maximum(np.linalg.norm(vn[e[:, 0]] - vn[e[:, 1]], axis=1), 1e-12)
        self.graph = coo_matrix((length, (e[:, 0], e[:, 1])), shape=(m, m)).tocsr()
        self.first = first

    def distance(self, seeds, limit: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """(distance [N] to the nearest seed vertex (inf where unreached), that seed's node [N] (-1))."""
        from scipy.sparse.csgraph import dijkstra

        nodes = np.unique(self.node[np.asarray(seeds, np.int64)])
        if len(nodes) == 0:
            n = len(self.node)
            return np.full(n, np.inf), np.full(n, -1)
        d, _, src = dijkstra(
            self.graph, directed=False, indices=nodes, min_only=True, limit=limit, return_predecessors=True
        )
        return d[self.node], src[self.node]

    def path(self, a: int, b: int) -> np.ndarray:
        """Nodes of the shortest surface path from vertex a to vertex b (a alone if unreachable)."""
        from scipy.sparse.csgraph import dijkstra

        na, nb = int(self.node[a]), int(self.node[b])
        _, pred = dijkstra(self.graph, directed=False, indices=na, return_predecessors=True)
        out = [nb]
        while out[-1] != na and pred[out[-1]] >= 0:
            out.append(int(pred[out[-1]]))
        return np.asarray(out[::-1] if out[-1] == na else [na], np.int64)
