"""The one mesh type every stage passes around: numpy in, numpy out (trimesh style).

A character is a triangle mesh with either per-vertex colours or UV + texture, optional named
glTF morph targets (per-vertex offsets, the ground truth of real assets) and an optional part
label per vertex (eyes, eyelids, mouth interior... from procedural characters or from the
primitives of a multi-part asset).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from t2bs.errors import UserError

# Canonical frame (DESIGN.md, Conventions): centred on the bounding-box centre, facing +Z, Y up,
# bounding-box diagonal equal to this. The orbit camera distance (2.25) is chosen for it.
CANONICAL_DIAGONAL = 1.2


@dataclass
class Mesh:
    vertices: np.ndarray  # [N, 3] float32, world units
    faces: np.ndarray  # [F, 3] int32, counter-clockwise seen from outside
    vertex_colors: np.ndarray | None = None  # [N, 3] float32 in [0, 1]; used when no texture
    uv: np.ndarray | None = None  # [N, 2] float32, glTF convention (v = 0 at the image top)
    texture: np.ndarray | None = None  # [H, W, 3] uint8, sampled with clamp-to-edge
    morph_targets: dict[str, np.ndarray] = field(default_factory=dict)  # name -> [N, 3] offsets
    part_ids: np.ndarray | None = None  # [N] int32, index into part_names
    part_names: list[str] = field(default_factory=list)  # label of each part id

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def morph_names(self) -> list[str]:
        return list(self.morph_targets)

    def bbox_diagonal(self) -> float:
        return float(np.linalg.norm(self.vertices.max(0) - self.vertices.min(0)))

    def with_vertices(self, vertices: np.ndarray) -> "Mesh":
        """Same topology, colours, labels and morph targets; new positions [N, 3]."""
        vertices = np.asarray(vertices, dtype=np.float32)
        if vertices.shape != self.vertices.shape:
            raise ValueError(f"expected vertices {self.vertices.shape}, got {vertices.shape}")
        return replace(self, vertices=vertices)

    def posed(self, weights: dict[str, float]) -> np.ndarray:
        """Vertex positions [N, 3] with morph target weights applied (unknown names raise)."""
        out = self.vertices.astype(np.float64).copy()
        for name, w in weights.items():
            if name not in self.morph_targets:
                raise KeyError(f"no morph target named {name!r}; have {self.morph_names}")
            out += float(w) * self.morph_targets[name]
        return out.astype(np.float32)

    def part_mask(self, *names: str) -> np.ndarray:
        """[N] bool: vertices whose part label is one of ``names`` (missing labels: all False)."""
        if self.part_ids is None:
            return np.zeros(self.num_vertices, dtype=bool)
        ids = [i for i, n in enumerate(self.part_names) if n in names]
        return np.isin(self.part_ids, ids)

    def vertex_rgb(self) -> np.ndarray:
        """[N, 3] float32 colour per vertex: the vertex colours, else the texture at each UV."""
        if self.texture is not None and self.uv is not None:
            return sample_texture(self.texture, self.uv)
        if self.vertex_colors is not None:
            return self.vertex_colors.astype(np.float32)
        return np.full((self.num_vertices, 3), 0.7, dtype=np.float32)

    def vertex_normals(self, vertices: np.ndarray | None = None) -> np.ndarray:
        """[N, 3] area-weighted unit vertex normals (of ``vertices`` if given, same topology)."""
        return vertex_normals(self.vertices if vertices is None else vertices, self.faces)

    def validate(self, source: str = "mesh") -> "Mesh":
        """Raise UserError naming the problem for empty, NaN, face-less or out-of-range meshes."""
        v, f = self.vertices, self.faces
        if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
            raise UserError(f"{source}: mesh has no vertices")
        if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
            raise UserError(f"{source}: mesh has no faces (a point cloud is not a character mesh)")
        if not np.isfinite(v).all():
            bad = int((~np.isfinite(v)).any(1).sum())
            raise UserError(f"{source}: {bad} vertices have NaN or infinite coordinates")
        if f.min() < 0 or f.max() >= v.shape[0]:
            raise UserError(f"{source}: faces index vertices outside 0..{v.shape[0] - 1}")
        if self.bbox_diagonal() <= 0:
            raise UserError(f"{source}: all vertices are at one point")
        if not (np.linalg.norm(face_area_normals(v, f), axis=1) > 0).any():
            raise UserError(f"{source}: every face has zero area (nothing to render)")
        for name, d in self.morph_targets.items():
            if d.shape != v.shape or not np.isfinite(d).all():
                raise UserError(f"{source}: morph target {name!r} has a bad shape or NaN offsets")
        return self


def face_area_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[F, 3] float64 unnormalised face normals (right-hand rule); each one's length is twice its triangle's area."""
    tri = np.asarray(vertices, dtype=np.float64)[faces]  # [F, 3, 3]
    return np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[N, 3] unit normals: sum of adjacent face normals weighted by face area."""
    v = np.asarray(vertices, dtype=np.float64)
    fn = face_area_normals(v, faces)
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return n.astype(np.float32)


def incident_edge_lengths(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-vertex edge statistics, float64: (mean length of the face edges at each vertex [N] (0 where none),
    their count [N], the length of every face edge [3F], a shared edge once per face). One splat per vertex is
    sized from the mean (the VCDGS static Gaussians, the viewer's splats)."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])  # [3F, 2]
    length = np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1)
    ends = np.concatenate([e[:, 0], e[:, 1]])
    total = np.bincount(ends, np.concatenate([length, length]), minlength=len(v))
    count = np.bincount(ends, minlength=len(v)).astype(np.float64)
    return total / np.maximum(count, 1), count, length


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges [E, 2] of a triangle mesh."""
    faces = np.asarray(faces, dtype=np.int64)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.sort(e, axis=1)
    return np.unique(e, axis=0)


def weld_index(vertices: np.ndarray, tolerance: float = 1e-7) -> tuple[np.ndarray, np.ndarray]:
    """Weld coincident vertices: -> (node [N] int64 welded id of each vertex in 0..M-1, first [M] int64
    a vertex of each node). Exporters split a vertex wherever its UV or normal jumps (texture seams,
    hard edges, part borders), so ``faces`` alone cut one surface into islands; vertices whose
    positions agree to ``tolerance`` x the bounding-box diagonal are one surface point."""
    v = np.asarray(vertices, dtype=np.float64)
    scale = float(np.linalg.norm(v.max(0) - v.min(0))) if len(v) else 1.0
    key = np.round(v / ((scale or 1.0) * tolerance)).astype(np.int64)
    _, first, node = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return node.ravel().astype(np.int64), first.astype(np.int64)


def welded_edges(node: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges [E, 2] between welded nodes (``weld_index``), self-loops dropped."""
    e = np.sort(np.asarray(node)[mesh_edges(faces)], axis=1)
    return np.unique(e[e[:, 0] != e[:, 1]], axis=0)


def welded_components(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[N] int64 connected-part label of each vertex over the welded mesh (``weld_index``: UV-seam copies of a
    vertex are one point, so a part is what the surface connects, not what the exporter's islands say)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    node, first = weld_index(vertices)
    e = welded_edges(node, faces) if len(faces) else np.zeros((0, 2), np.int64)
    m = len(first)
    adj = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(m, m))
    _, label = connected_components(adj, directed=False)
    return label[node].astype(np.int64)


def sample_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of ``texture`` [H, W, 3] uint8 at ``uv`` [N, 2] -> [N, 3] float in [0, 1]."""
    h, w = texture.shape[:2]
    tex = texture.astype(np.float32) / 255.0
    x = np.clip(uv[:, 0], 0.0, 1.0) * (w - 1)
    y = np.clip(uv[:, 1], 0.0, 1.0) * (h - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    top = tex[y0, x0] * (1 - fx) + tex[y0, x1] * fx
    bottom = tex[y1, x0] * (1 - fx) + tex[y1, x1] * fx
    return (top * (1 - fy) + bottom * fy).astype(np.float32)


FACING_ROTATIONS = {
    # Rotation taking the asset's facing direction to +Z (Y stays up).
    "+z": np.eye(3),
    "-z": np.diag([-1.0, 1.0, -1.0]),
    "+x": np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]]),
    "-x": np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]]),
}


def bbox_diagonal(vertices: np.ndarray) -> float:
    """Length of the axis-aligned bounding box's diagonal of points [..., 3] (float64)."""
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    return float(np.linalg.norm(v.max(0) - v.min(0)))


def normalize(mesh: Mesh, facing: str = "+z", diagonal: float = CANONICAL_DIAGONAL) -> tuple[Mesh, dict]:
    """Move ``mesh`` to the canonical frame: rotate ``facing`` to +Z, centre, fix the diagonal.

    Returns the new mesh and the transform applied (``x_canonical = scale * R @ (x) + t``) so
    that ground truth in asset units can be mapped the same way. Morph offsets are rotated and
    scaled (not translated).
    """
    if facing not in FACING_ROTATIONS:
        raise UserError(f"unknown facing {facing!r}; use one of {sorted(FACING_ROTATIONS)}")
    rot = FACING_ROTATIONS[facing]
    v = mesh.vertices.astype(np.float64) @ rot.T
    lo, hi = v.min(0), v.max(0)
    scale = diagonal / float(np.linalg.norm(hi - lo))
    centre = (lo + hi) / 2
    v = (v - centre) * scale
    morphs = {k: (d.astype(np.float64) @ rot.T * scale).astype(np.float32) for k, d in mesh.morph_targets.items()}
    transform = {"rotation": rot.tolist(), "scale": scale, "translation": (-centre * scale).tolist()}
    return replace(mesh, vertices=v.astype(np.float32), morph_targets=morphs), transform


def detect_facing(mesh: Mesh) -> str:
    """Guess which horizontal axis the character faces, for assets without a convention.

    Expressions happen on the face, so the displacement-weighted centroid of the morph targets
    lies in front of the bounding-box centre. Without morph targets, glTF's +Z is assumed.
    """
    if not mesh.morph_targets:
        return "+z"
    motion = np.zeros(mesh.num_vertices)
    for d in mesh.morph_targets.values():
        motion = np.maximum(motion, np.linalg.norm(d, axis=1))
    if motion.sum() <= 0:
        return "+z"
    centre = (mesh.vertices.min(0) + mesh.vertices.max(0)) / 2
    lean = (motion[:, None] * (mesh.vertices - centre)).sum(0) / motion.sum()
    axis = 0 if abs(lean[0]) > abs(lean[2]) else 2
    return ("+" if lean[axis] > 0 else "-") + "xz"[axis // 2]


def merge_meshes(parts: list[tuple[str, Mesh]]) -> Mesh:
    """Concatenate named parts into one mesh with a part label per vertex.

    Colours: if any part has a texture, all textures (and solid tiles for untextured parts) are
    packed side by side into one atlas and UVs remapped; otherwise vertex colours are kept.
    Morph targets are the union of names; parts without a target get zero offsets.
    """
    if not parts:
        raise ValueError("merge_meshes needs at least one part")
    names = list(dict.fromkeys(n for n, _ in parts))
    offsets = np.cumsum([0] + [m.num_vertices for _, m in parts])
    vertices = np.concatenate([m.vertices for _, m in parts]).astype(np.float32)
    faces = np.concatenate([m.faces + o for (_, m), o in zip(parts, offsets)]).astype(np.int32)
    part_ids = np.concatenate([np.full(m.num_vertices, names.index(n), np.int32) for n, m in parts])
    morph_names = list(dict.fromkeys(k for _, m in parts for k in m.morph_targets))
    morphs = {
        k: np.concatenate([m.morph_targets.get(k, np.zeros_like(m.vertices)) for _, m in parts]).astype(np.float32)
        for k in morph_names
    }
    uv, texture, colors = None, None, None
    if any(m.texture is not None for _, m in parts):
        uv, texture = _pack_atlas([m for _, m in parts])
    else:
        colors = np.concatenate([m.vertex_rgb() for _, m in parts]).astype(np.float32)
    return Mesh(vertices, faces, colors, uv, texture, morphs, part_ids, names)


def _pack_atlas(meshes: list[Mesh]) -> tuple[np.ndarray, np.ndarray]:
    """Pack each mesh's texture (or a solid tile of its colour) left to right in one image."""
    tiles, uvs = [], []
    for m in meshes:
        if m.texture is not None and m.uv is not None:
            tiles.append(m.texture)
            uvs.append(np.clip(m.uv, 0.0, 1.0))
        else:
            rgb = m.vertex_rgb().mean(0)
            tiles.append(np.broadcast_to((rgb * 255).astype(np.uint8), (8, 8, 3)))
            uvs.append(np.full((m.num_vertices, 2), 0.5, np.float32))
    if all(t is tiles[0] or np.array_equal(t, tiles[0]) for t in tiles):
        return np.concatenate(uvs).astype(np.float32), np.ascontiguousarray(tiles[0])
    height = max(t.shape[0] for t in tiles)
    resized = [_resize_nearest(t, height) for t in tiles]
    widths = [t.shape[1] for t in resized]
    total = sum(widths)
    out_uv, x0 = [], 0
    for uv, w in zip(uvs, widths):
        # Half-texel inset keeps bilinear lookups inside the tile.
        u = (x0 + 0.5 + uv[:, 0] * (w - 1)) / total
        out_uv.append(np.stack([u, uv[:, 1]], 1))
        x0 += w
    return np.concatenate(out_uv).astype(np.float32), np.concatenate(resized, axis=1)


def _resize_nearest(img: np.ndarray, height: int) -> np.ndarray:
    if img.shape[0] == height:
        return np.ascontiguousarray(img)
    width = max(1, round(img.shape[1] * height / img.shape[0]))
    ys = (np.arange(height) * img.shape[0] / height).astype(int)
    xs = (np.arange(width) * img.shape[1] / width).astype(int)
    return np.ascontiguousarray(img[ys][:, xs])
