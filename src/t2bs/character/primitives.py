"""Closed, well-tessellated primitives the procedural characters are built from.

Every builder returns ``(vertices [N, 3] float64, faces [F, 3] int32)`` describing ONE closed,
manifold surface with outward (counter-clockwise) faces, so every part of a character is
watertight on its own and later stages (Gaussians from vertices, visibility tests) see a proper
surface. Shapes are made by deforming spheres with smooth functions rather than by CSG, which
keeps the topology fixed and the triangles well shaped.
"""

from __future__ import annotations

import functools

import numpy as np


@functools.lru_cache(maxsize=8)
def _icosphere_cached(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    return np.asarray(sphere.vertices, np.float64), np.asarray(sphere.faces, np.int32)


def icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere: 10 * 4**s + 2 vertices (s=3: 642, s=4: 2562, s=5: 10242)."""
    v, f = _icosphere_cached(int(subdivisions))
    return v.copy(), f.copy()


def uv_sphere(n_lat: int, n_lon: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit sphere with single pole vertices (poles on +Z / -Z) and a wrapped seam.

    Returns (vertices, faces, s) where ``s`` [N] in [0, 1] is the latitude parameter
    (0 at the +Z pole, 1 at the -Z pole); shells are made by remapping it.
    """
    lat = np.arange(1, n_lat) / n_lat  # interior rings, [n_lat - 1]
    lon = np.arange(n_lon) / n_lon * 2 * np.pi
    phi = lat[:, None] * np.pi
    ring = np.stack([np.sin(phi) * np.cos(lon), np.sin(phi) * np.sin(lon), np.cos(phi) * np.ones_like(lon)], -1)
    verts = np.concatenate([[[0.0, 0.0, 1.0]], ring.reshape(-1, 3), [[0.0, 0.0, -1.0]]])
    s = np.concatenate([[0.0], np.repeat(lat, n_lon), [1.0]])
    faces = []
    top, bottom = 0, len(verts) - 1
    idx = lambda i, j: 1 + i * n_lon + (j % n_lon)  # noqa: E731
    for j in range(n_lon):
        faces.append([top, idx(0, j), idx(0, j + 1)])
        faces.append([bottom, idx(n_lat - 2, j + 1), idx(n_lat - 2, j)])
    for i in range(n_lat - 2):
        for j in range(n_lon):
            a, b, c, d = idx(i, j), idx(i, j + 1), idx(i + 1, j), idx(i + 1, j + 1)
            faces += [[a, c, b], [b, c, d]]
    return verts, orient_outward(verts, np.asarray(faces, np.int32)), s


def tube(path: np.ndarray, radii: np.ndarray, sides: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Closed tube swept along ``path`` [M, 3] with radius ``radii`` [M]; ends capped by a fan.

    A radius near 0 at an end makes a point (horns, teeth, antennae tips).
    """
    path = np.asarray(path, np.float64)
    radii = np.asarray(radii, np.float64)
    m = len(path)
    tangents = np.gradient(path, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True) + 1e-12
    # Parallel-transport frames: no twisting along curved horns.
    ref = np.array([0.0, 0.0, 1.0]) if abs(tangents[0, 2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    normal = np.cross(tangents[0], ref)
    normal /= np.linalg.norm(normal)
    rings = []
    angles = np.arange(sides) / sides * 2 * np.pi
    for i in range(m):
        t = tangents[i]
        normal = normal - t * (normal @ t)
        normal /= np.linalg.norm(normal) + 1e-12
        binormal = np.cross(t, normal)
        r = max(radii[i], 1e-4)
        rings.append(path[i] + r * (np.cos(angles)[:, None] * normal + np.sin(angles)[:, None] * binormal))
    verts = np.concatenate([np.concatenate(rings), path[:1], path[-1:]])
    start, end = m * sides, m * sides + 1
    faces = []
    for i in range(m - 1):
        for j in range(sides):
            a, b = i * sides + j, i * sides + (j + 1) % sides
            c, d = a + sides, b + sides
            faces += [[a, b, c], [b, d, c]]
    for j in range(sides):
        faces.append([start, (j + 1) % sides, j])
        faces.append([end, (m - 1) * sides + j, (m - 1) * sides + (j + 1) % sides])
    return verts, orient_outward(verts, np.asarray(faces, np.int32))


def orient_outward(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Flip all faces if the enclosed signed volume is negative (faces must be consistent)."""
    tri = verts[faces]
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum()
    return faces[:, ::-1].copy() if volume < 0 else faces


def rotation(axis: np.ndarray, angle) -> np.ndarray:
    """Rodrigues rotation matrices: one axis [3], angles scalar or [N] -> [3, 3] or [N, 3, 3]."""
    axis = np.asarray(axis, np.float64)
    axis = axis / np.linalg.norm(axis)
    angle = np.asarray(angle, np.float64)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    s, c = np.sin(angle)[..., None, None], np.cos(angle)[..., None, None]
    return np.eye(3) + s * k + (1 - c) * (k @ k)


def rotate_about(points: np.ndarray, pivot: np.ndarray, axis: np.ndarray, angle) -> np.ndarray:
    """Rotate points [N, 3] about the line through ``pivot`` along ``axis`` by ``angle`` ([N] or scalar)."""
    rel = points - pivot
    rot = rotation(axis, angle)
    if rot.ndim == 2:
        return rel @ rot.T + pivot
    return np.einsum("nij,nj->ni", rot, rel) + pivot


def surface_along(verts: np.ndarray, origin: np.ndarray, direction: np.ndarray, radius: float = 0.04) -> np.ndarray:
    """Outermost point of a dense surface (its vertices [N, 3]) along a ray from an interior point.

    Vertices within ``radius`` of the ray line are projected on it; the farthest wins. Good
    enough for placing eyes, lips and ears on a densely tessellated, star-shaped head.
    """
    d = direction / np.linalg.norm(direction)
    rel = verts - origin
    t = rel @ d
    dist = np.linalg.norm(rel - t[:, None] * d, axis=1)
    for r in (radius, radius * 2, radius * 4, radius * 8):
        near = (dist < r) & (t > 0)
        if near.any():
            return origin + d * float(t[near].max())
    return origin + d * float(max(t.max(), 0.0))
