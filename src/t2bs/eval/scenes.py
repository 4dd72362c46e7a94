"""Small synthetic scenes with a known local motion, for tests and diagnostics of VCDGS.

``lid_scene``: a still head (a sphere) with a dark eye (a disk painted on it) and a lid (a thin spherical cap just
outside the head, skin-coloured like the head) that slides down over the eye and back. Only the lid moves, so
whatever the reconstruction moves elsewhere is error, and the lid's motion is visible only where its edge crosses
the eye: the situation of a blink at a small scale (issue 37).
"""

from __future__ import annotations

import numpy as np

from t2bs.geometry.mesh import Mesh, merge_meshes, normalize

SKIN = (0.85, 0.62, 0.5)
EYE = (0.08, 0.07, 0.1)


def _sphere(subdivisions: int, radius: float):
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(s.vertices, np.float32), np.asarray(s.faces, np.int32)


def _rot_x(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def lid_scene(frames: int = 6, size: int = 64, lid_angle_deg: float = 14.0, views: int = 5):
    """(mesh, grid) of the lid scene in the canonical frame (faces +Z, diagonal 1.2).

    The eye is a disk of 12 deg angular radius on the head, 18 deg above the equator; the lid a cap 1.5 % outside
    the head covering 14 deg above the eye's top at rest. Over the frames the lid turns down about the head's x
    axis by lid_angle_deg x sin(pi u), u in [0, 1] (closing, then opening): at the peak it covers most of the eye.
    ``views`` orbit cameras (odd; the middle one canonical), unlit renders, no defects, no head motion."""
    from t2bs.video.animator import Animation
    from t2bs.video.synth import GridConfig, render_grid

    r = 0.5
    hv, hf = _sphere(3, r)
    eye_dir = np.array([0.0, np.sin(np.radians(18.0)), np.cos(np.radians(18.0))])
    ang = np.degrees(np.arccos(np.clip(hv @ eye_dir / r, -1.0, 1.0)))
    head_rgb = np.where((ang < 12.0)[:, None], EYE, SKIN).astype(np.float32)
    # The lid: the part of a slightly larger sphere between 12 and 28 deg above the eye's centre (pitch), +-20 deg
    # sideways; faces kept whole.
    lv, lf = _sphere(4, r * 1.015)
    pitch = np.degrees(np.arctan2(lv[:, 1], lv[:, 2])) - 18.0
    yaw = np.degrees(np.arctan2(lv[:, 0], np.hypot(lv[:, 1], lv[:, 2])))
    inside = (pitch > 9.0) & (pitch < 26.0) & (np.abs(yaw) < 16.0) & (lv[:, 2] > 0)
    keep_f = inside[lf].all(1)
    used = np.unique(lf[keep_f])
    remap = -np.ones(len(lv), np.int64)
    remap[used] = np.arange(len(used))
    lid_v, lid_f = lv[used], remap[lf[keep_f]].astype(np.int32)
    head = Mesh(hv, hf, vertex_colors=head_rgb)
    lid = Mesh(lid_v, lid_f, vertex_colors=np.tile(np.asarray(SKIN, np.float32) * 0.97, (len(lid_v), 1)))
    mesh, _ = normalize(merge_meshes([("head", head), ("eyelid_left", lid)]))
    # Motion: the lid's vertices turn about the x axis through the head's centre (its centre after normalize).
    centre = mesh.vertices[mesh.part_mask("head")].mean(0)
    lid_mask = mesh.part_mask("eyelid_left")
    u = np.linspace(0.0, 1.0, frames)
    amount = np.sin(np.pi * u)
    verts = np.repeat(mesh.vertices[None].astype(np.float64), frames, 0)
    for t in range(frames):
        rot = _rot_x(np.radians(lid_angle_deg) * amount[t])  # +x rotation tips +z points towards -y: down
        verts[t, lid_mask] = (mesh.vertices[lid_mask] - centre) @ rot.T + centre
    verts = verts.astype(np.float32)
    times = (np.arange(frames) / 8.0).astype(np.float32)
    anim = Animation(
        "lid sliding down",
        times,
        {"blink": amount.astype(np.float32)},
        [],
        np.zeros((frames, 0), np.float32),
        np.zeros((frames, 3), np.float32),
        centre.astype(np.float32),
        verts,
        verts,
    )
    grid = render_grid(
        mesh,
        anim,
        GridConfig(frames=frames, size=size, views=views, shading="unlit", head_motion=0.0),
        meta={"prompt": "lid scene", "expression": "lid sliding down"},
    )
    return mesh, grid
