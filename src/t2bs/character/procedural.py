"""Procedural character heads: prompt -> parameters -> labelled parts -> one Mesh with a rig.

Layout in head units (cranium radius ~1, centre at the origin, Y up, facing +Z, the
character's LEFT is +X). The face is split the way a puppet is: the head (cranium, upper face,
muzzle) ends in a flat palate at the mouth line; a separate jaw hangs below it. Closed, the jaw's
top is hidden inside the head and the lips cover the crease; opened (rotated about a hinge), a
dark mouth interior, teeth and a tongue show in the gap. Eyes are spheres inside a thick eyelid
shell with an opening; blinking rotates the shell around the opening until it is closed.

Every part is one or more closed manifold surfaces with a part label; the rig is a set of
named morph targets (offsets per vertex, same topology), see ``RIG_REGIONS``.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np

from t2bs.character.archetypes import CharacterParams
from t2bs.character.primitives import (
    icosphere,
    orient_outward,
    rotate_about,
    surface_along,
    tube,
    uv_sphere,
)
from t2bs.character.prompt import parse_prompt, prompt_seed
from t2bs.geometry.curves import smoothstep
from t2bs.geometry.mesh import Mesh, merge_meshes, normalize

# Rig amplitudes (radians / head units): large enough to read in a 512 px render.
JAW_ANGLE = np.radians(26.0)
LOOK_ANGLE = np.radians(24.0)
EAR_ANGLE = np.radians(28.0)

# Which part labels each control may move (the tests hold the generator to this).
RIG_REGIONS: dict[str, set[str]] = {
    "jaw_open": {"jaw", "lip_lower", "teeth", "tongue", "mouth_interior"},
    "blink_left": {"eyelid_left"},
    "blink_right": {"eyelid_right"},
    "smile": {"lip_upper", "lip_lower", "head", "jaw"},
    "frown": {"lip_upper", "lip_lower", "head", "jaw", "brow"},
    "brow_up": {"brow"},
    "ear_wave": {"ear_left", "ear_right"},
    "tongue_out": {"tongue"},
    "cheek_puff": {"head", "jaw"},
    "look_left": {"eye_left", "eye_right"},
    "look_right": {"eye_left", "eye_right"},
    "look_up": {"eye_left", "eye_right"},
    "look_down": {"eye_left", "eye_right"},
}
RIG_CONTROLS = list(RIG_REGIONS)


@dataclass
class _Part:
    label: str
    vertices: np.ndarray  # [N, 3]
    faces: np.ndarray  # [F, 3]
    colors: np.ndarray  # [N, 3]
    morphs: dict[str, np.ndarray] = field(default_factory=dict)  # control -> [N, 3] offsets


@dataclass
class _Face:
    """Landmarks of the built head that later parts attach to."""

    y_mouth: float  # mouth line (palate) height
    z_mouth: float  # front of the upper lip
    z_hinge: float  # jaw hinge z (the jaw spans z_hinge .. z_mouth)
    jaw_half_width: float
    hinge: np.ndarray  # [3] jaw rotation pivot
    snouted: bool
    nose_tip: np.ndarray  # [3] front of the face above the mouth
    corners: np.ndarray = None  # [2, 3] mouth corners (left, right)
    eyes: list = field(default_factory=list)  # (centre [3], radius, forward [3]) left then right


def _colors(n: int, rgb) -> np.ndarray:
    return np.tile(np.asarray(rgb, np.float64), (n, 1))


def _shade(rgb, k: float) -> np.ndarray:
    return np.clip(np.asarray(rgb, np.float64) * k, 0, 1)


def _mix(a: np.ndarray, b, w: np.ndarray) -> np.ndarray:
    return a * (1 - w[:, None]) + np.asarray(b, np.float64)[None] * w[:, None]


def _ellipsoid(center, radii, subdiv: int = 3, exponent: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    v, f = icosphere(subdiv)
    if exponent != 2.0:
        v = v / (np.abs(v) ** exponent).sum(1, keepdims=True) ** (1 / exponent)
    return v * np.asarray(radii) + np.asarray(center), f


def _rotate_jaw(points: np.ndarray, face: _Face, weight=1.0) -> np.ndarray:
    """Offsets [N, 3] of the jaw opening (positive angle about +X moves the chin down)."""
    angle = JAW_ANGLE * np.broadcast_to(np.asarray(weight, np.float64), (len(points),))
    return rotate_about(points, face.hinge, np.array([1.0, 0, 0]), angle) - points


def _dir(az_deg: float, el_deg: float, side: float = 1.0) -> np.ndarray:
    az, el = np.radians(az_deg), np.radians(el_deg)
    return np.array([side * np.sin(az) * np.cos(el), np.sin(el), np.cos(az) * np.cos(el)])


# --------------------------------------------------------------------------------------------
# head and jaw


def _build_head(p: CharacterParams, rng: np.random.Generator) -> tuple[_Part, _Face]:
    v, f = icosphere(5)
    n = p.squareness
    q = v / (np.abs(v) ** n).sum(1, keepdims=True) ** (1 / n) * np.asarray(p.head_radii)
    if p.cranium_lift:
        q[:, 1] += p.cranium_lift * np.clip(q[:, 1], 0, None) ** 2
    snouted = p.snout_length > 0.12
    if p.snout_length > 0:
        a = np.array([0.0, -p.snout_drop, 1.0])
        a /= np.linalg.norm(a)
        c = (v / np.linalg.norm(v, axis=1, keepdims=True)) @ a
        w = smoothstep(np.cos(np.radians(p.snout_angle)), 1.0, c)
        along = q @ a
        lateral = q - along[:, None] * a
        q = (along + p.snout_length * w**0.8)[:, None] * a + lateral * (1 - p.snout_taper * w)[:, None]
    rx, ry, rz = p.head_radii
    if snouted:
        front = q[:, 2].max()
        sel = (np.abs(q[:, 0]) < 0.08) & (q[:, 2] > front - 0.3 * p.snout_length)
        y_bot, y_top = q[sel, 1].min(), q[sel, 1].max()
        y_mouth = y_bot + 0.28 * (y_top - y_bot)
        z_hinge = rz * 0.45
    else:
        y_mouth = p.mouth_height * ry
        z_hinge = rz * 0.2
    jaw_w = max(p.mouth_width * 1.2, 0.22)
    # Carve a flat palate under the front of the face: the jaw part supplies the surface below.
    wz = smoothstep(z_hinge - 0.05, z_hinge + 0.25, q[:, 2])
    wx = 1 - smoothstep(jaw_w * 0.85, jaw_w * 1.15, np.abs(q[:, 0]))
    below = q[:, 1] < y_mouth
    depth = 0.06
    carved = y_mouth - depth * np.tanh((y_mouth - q[:, 1]) / depth)
    q[:, 1] = np.where(below, q[:, 1] + wz * wx * (carved - q[:, 1]), q[:, 1])
    near = (np.abs(q[:, 0]) < 0.06) & (np.abs(q[:, 1] - (y_mouth + 0.03)) < 0.05)
    z_mouth = float(q[near, 2].max()) if near.any() else float(q[:, 2].max())
    hinge = np.array([0.0, y_mouth + 0.02, z_hinge - 0.1])
    if snouted:
        tip_sel = q[:, 2] > q[:, 2].max() - 0.08
        nose_tip = q[tip_sel].mean(0)
        nose_tip[1] = q[tip_sel, 1].max() - 0.04
        nose_tip[2] = q[:, 2].max()
    else:
        nose_tip = surface_along(q, np.array([0.0, 0.0, 0.0]), np.array([0.0, (y_mouth * 0.45) / max(rz, 1e-3), 1.0]))
    face = _Face(float(y_mouth), z_mouth, float(z_hinge), float(jaw_w), hinge, snouted, nose_tip)
    return _Part("head", q, f, _colors(len(q), p.base_color)), face


def _build_jaw(p: CharacterParams, face: _Face) -> _Part:
    z_front = face.z_mouth - (0.1 if face.snouted else 0.03)
    z_back = face.z_hinge - 0.12
    jh = p.jaw_size * (0.15 if face.snouted else 0.26)
    top = face.y_mouth + 0.05
    centre = np.array([0.0, top - jh, (z_front + z_back) / 2])
    v, f = _ellipsoid(centre, (face.jaw_half_width * 1.08, jh, (z_front - z_back) / 2), 4, exponent=2.6)
    if face.snouted:  # a V-shaped lower jaw: narrower toward the front
        t = np.clip((v[:, 2] - z_back) / (z_front - z_back), 0, 1)
        v[:, 0] *= 1 - 0.35 * t
    part = _Part("jaw", v, f, _colors(len(v), p.base_color))
    part.morphs["jaw_open"] = _rotate_jaw(v, face)
    return part


def _mouth_curve(surface: np.ndarray, face: _Face, y: float, half_width: float, count: int = 25) -> np.ndarray:
    """Points [count, 3] on the face surface at height ``y`` spanning the mouth width."""
    origin = np.array([0.0, y, face.z_mouth - 0.6])
    xs = np.linspace(-half_width, half_width, count)
    return np.stack([surface_along(surface, origin, np.array([x, 0.0, 0.6]), 0.03) for x in xs])


def _build_mouth(p: CharacterParams, face: _Face, head: _Part, jaw: _Part) -> list[_Part]:
    parts = []
    y_m, mw = face.y_mouth, p.mouth_width
    both = np.concatenate([head.vertices, jaw.vertices])
    lip_r = 0.04 + 0.035 * min(mw, 0.6)
    upper = _mouth_curve(head.vertices, face, y_m + 0.015, mw)
    lower = _mouth_curve(both, face, y_m - 0.025, mw * 0.97)
    face.corners = np.stack([upper[-1], upper[0]])  # left (+X) first
    lip_rgb = p.lip_color if p.lip_color is not None else _shade(p.base_color, 0.72)
    u = np.linspace(0, 1, len(upper))
    profile = lip_r * (0.35 + 0.65 * np.sin(np.pi * u) ** 0.6)
    for label, curve, sign in (("lip_upper", upper, 1.0), ("lip_lower", lower, -1.0)):
        inward = curve - np.array([0.0, curve[0, 1], face.z_mouth - 0.6])
        inward[:, 1] = 0
        inward /= np.linalg.norm(inward, axis=1, keepdims=True)
        path = curve - inward * lip_r * 0.45
        v, f = tube(path, profile, sides=10)
        part = _Part(label, v, f, _colors(len(v), lip_rgb))
        _lip_morphs(part, face, mw, sign)
        if label == "lip_lower":
            part.morphs["jaw_open"] = _rotate_jaw(v, face)
        parts.append(part)

    # Mouth interior: a dark sack behind the lips; its lower half follows the jaw.
    depth = face.z_mouth - face.z_hinge
    ci = np.array([0.0, y_m - 0.035, face.z_mouth - 0.07 - depth * 0.42])
    ri = (face.jaw_half_width * 0.82, min(0.13, 0.6 * p.jaw_size * (0.15 if face.snouted else 0.26)), depth * 0.42)
    v, f = _ellipsoid(ci, ri, 3)
    dark = np.array([0.32, 0.06, 0.08])
    shade = 0.55 + 0.45 * smoothstep(ci[2] - ri[2], ci[2] + ri[2], v[:, 2])  # darker deep inside
    part = _Part("mouth_interior", v, f, dark[None] * shade[:, None])
    wj = smoothstep(ci[1] + 0.3 * ri[1], ci[1] - 0.5 * ri[1], v[:, 1])
    part.morphs["jaw_open"] = _rotate_jaw(v, face, wj)
    parts.append(part)

    # Tongue: rests on the jaw floor; sticking out stretches it forward and down.
    tl = min(0.32, depth * 0.4)
    ct = np.array([0.0, y_m - 0.075, face.z_mouth - 0.08 - tl])
    v, f = _ellipsoid(ct, (face.jaw_half_width * 0.58, 0.05, tl), 3)
    v[:, 1] += 0.03 * (v[:, 0] / (face.jaw_half_width * 0.58)) ** 2  # a groove down the middle
    part = _Part("tongue", v, f, _colors(len(v), (0.9, 0.38, 0.45)))
    part.morphs["jaw_open"] = _rotate_jaw(v, face)
    t = smoothstep(ct[2] - tl, ct[2] + tl, v[:, 2])
    part.morphs["tongue_out"] = np.stack([np.zeros_like(t), -0.1 * t, (0.25 + 0.25 * tl) * t], 1)
    parts.append(part)
    parts += _build_teeth(p, face, upper, lower, lip_r)
    return parts


def _lip_morphs(part: _Part, face: _Face, mw: float, sign: float) -> None:
    v = part.vertices
    corner = smoothstep(0.25 * mw, 1.0 * mw, np.abs(v[:, 0]))  # 0 at the middle, 1 at the corners
    side = np.sign(v[:, 0])
    smile = np.stack([side * 0.05 * corner, 0.1 * corner**1.5, -0.04 * corner], 1)
    # The middle of the lower lip drops a little in a smile (an open, happy curve).
    if sign < 0:
        smile[:, 1] += -0.02 * (1 - corner)
    part.morphs["smile"] = smile
    part.morphs["frown"] = np.stack([-side * 0.015 * corner, -0.09 * corner**1.5, 0.0 * corner], 1)


def _cheek_field(points: np.ndarray, face: _Face, radius: float) -> np.ndarray:
    """[N] smooth weight around the mouth corners (0 far away)."""
    d = np.min(np.linalg.norm(points[:, None, :] - face.corners[None], axis=2), axis=1)
    return np.exp(-((d / radius) ** 2)) * (d < 2.5 * radius)


def _face_morphs(p: CharacterParams, face: _Face, head: _Part, jaw: _Part) -> None:
    """Smile/frown pull the skin near the mouth corners; cheek puff inflates the cheeks."""
    r = 0.12 + 0.15 * p.mouth_width
    for part in (head, jaw):
        v = part.vertices
        w = _cheek_field(v, face, r)
        side = np.sign(v[:, 0])
        part.morphs["smile"] = np.stack([side * 0.03 * w, 0.06 * w, -0.02 * w], 1)
        part.morphs["frown"] = np.stack([0 * w, -0.05 * w, 0 * w], 1)
        # Cheeks sit behind and a little above the mouth corners, pushed out along the normal.
        cheek_c = face.corners + np.array([[0.12, 0.06, -0.12], [-0.12, 0.06, -0.12]])
        d = np.min(np.linalg.norm(v[:, None, :] - cheek_c[None], axis=2), axis=1)
        cr = 0.2 + 0.2 * p.mouth_width
        wc = np.exp(-((d / cr) ** 2)) * (d < 2.5 * cr)
        normals = Mesh(v.astype(np.float32), part.faces).vertex_normals().astype(np.float64)
        part.morphs["cheek_puff"] = normals * (0.09 * wc)[:, None]


def _build_teeth(p: CharacterParams, face: _Face, upper: np.ndarray, lower: np.ndarray, lip_r: float) -> list[_Part]:
    white = (0.97, 0.96, 0.9)
    inset = 0.02 + lip_r * 0.5  # just behind the lips, so an open mouth shows them
    comps = []  # (vertices, faces, moves_with_jaw)

    def inner(curve, lo, hi, count, y):
        idx = np.linspace(lo * (len(curve) - 1), hi * (len(curve) - 1), count)
        pts = np.stack([np.interp(idx, np.arange(len(curve)), curve[:, k]) for k in range(3)], 1)
        d = pts - np.array([0.0, pts[0, 1], face.z_mouth - 0.6])
        d[:, 1] = 0
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        pts = pts - d * inset
        pts[:, 1] = y
        return pts

    y_m = face.y_mouth
    if p.teeth in ("flat", "fangs", "buck"):
        for y, jawed, lo, hi in ((y_m - 0.035, False, 0.22, 0.78), (y_m - 0.035, True, 0.25, 0.75)):
            path = inner(upper if not jawed else lower, lo, hi, 15, y)
            rad = 0.032 * np.ones(len(path))
            rad[0] = rad[-1] = 0.012
            comps.append((*tube(path, rad, 10), jawed))
    if p.teeth == "fangs":
        for pt in inner(upper, 0.3, 0.7, 2, y_m - 0.02):
            path = np.stack([pt, pt + [0, -0.06, 0.0], pt + [0, -0.11, 0.01]])
            comps.append((*tube(path, np.array([0.03, 0.02, 0.003]), 8), False))
    if p.teeth == "buck":
        for x in (-0.038, 0.038):
            pt = inner(upper, 0.5, 0.5, 1, y_m)[0] + [x, 0.0, 0.015]
            path = np.stack([pt + [0, 0.02, 0], pt + [0, -0.06, 0], pt + [0, -0.12, 0]])
            comps.append((*tube(path, np.array([0.034, 0.034, 0.02]), 8), False))
    if p.teeth == "sharp":
        n_teeth = int(np.clip(round(p.mouth_width * 22), 5, 14))
        size = 0.06 + 0.05 * p.jaw_size
        for curve, jawed, y, direction in ((upper, False, y_m + 0.015, -1.0), (lower, True, y_m - 0.05, 1.0)):
            for pt in inner(curve, 0.08, 0.92, n_teeth, y):
                path = np.stack([pt, pt + [0, direction * size * 0.5, 0], pt + [0, direction * size, 0]])
                comps.append((*tube(path, np.array([0.026, 0.016, 0.002]), 8), jawed))
    verts, faces, jawed, off = [], [], [], 0
    for v, f, j in comps:
        verts.append(v)
        faces.append(f + off)
        jawed.append(np.full(len(v), float(j)))
        off += len(v)
    v, f, j = np.concatenate(verts), np.concatenate(faces), np.concatenate(jawed)
    part = _Part("teeth", v, f, _colors(len(v), white))
    part.morphs["jaw_open"] = _rotate_jaw(v, face, j)
    return [part]


# --------------------------------------------------------------------------------------------
# eyes, eyelids, brows


def _eye_frame(forward: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    f = forward / np.linalg.norm(forward)
    side = np.cross([0.0, 1.0, 0.0], f)
    side /= np.linalg.norm(side)
    up = np.cross(f, side)
    return f, up, side


def _build_eyes(p: CharacterParams, face: _Face, head: _Part) -> list[_Part]:
    parts = []
    r = p.eye_size
    lid_rgb = _shade(p.base_color, 0.9)
    for side_sign, suffix in ((1.0, "left"), (-1.0, "right")):
        d = _dir(p.eye_azimuth, p.eye_elevation, side_sign)
        surf = surface_along(head.vertices, np.zeros(3), d)
        normal = surf / np.linalg.norm(surf)
        centre = surf - normal * r * 0.42
        fwd = p.eye_forward * np.array([0.0, 0.0, 1.0]) + (1 - p.eye_forward) * normal
        f, up, side = _eye_frame(fwd)
        face.eyes.append((centre, r, f))

        # Eyeball: sclera, iris, pupil and a highlight painted by angle from the gaze.
        v, faces = icosphere(4)
        colors = _eyeball_colors(p, v @ f, v @ up, v @ side)
        v = centre + v * r
        eye = _Part(f"eye_{suffix}", v, faces, colors)
        for name, axis, angle in (
            ("look_left", up, LOOK_ANGLE),
            ("look_right", up, -LOOK_ANGLE),
            ("look_up", side, -LOOK_ANGLE),
            ("look_down", side, LOOK_ANGLE),
        ):
            eye.morphs[name] = rotate_about(v, centre, axis, angle) - v
        parts.append(eye)
        parts.append(_eyelid(p, centre, r, f, up, side, suffix, lid_rgb))
        if p.brow_size > 0:
            parts.append(_brow(p, centre, r, f, up, side_sign, head, suffix))
    return parts


def _eyeball_colors(p: CharacterParams, cf: np.ndarray, cu: np.ndarray, cs: np.ndarray) -> np.ndarray:
    ang = np.degrees(np.arccos(np.clip(cf, -1, 1)))  # angle from the gaze
    iris = np.asarray(p.iris_color, np.float64)
    out = _colors(len(cf), (0.97, 0.97, 0.95))
    if p.pupil == "compound":  # bug/alien: one glossy dark eye with a faint facet shimmer
        facet = 0.85 + 0.15 * np.sin(cu * 40) * np.sin(cs * 40)
        out = iris[None] * facet[:, None]
        spot = np.degrees(np.arccos(np.clip(cf * 0.966 + cu * 0.259 * 0.8 - cs * 0.259 * 0.6, -1, 1)))
        return _mix(out, (0.95, 0.95, 1.0), smoothstep(9, 6, spot))
    iris_r = 30.0 if p.pupil != "glow" else 40.0
    w_iris = smoothstep(iris_r + 2, iris_r - 2, ang)
    ring = smoothstep(iris_r - 8, iris_r, ang) * w_iris
    out = _mix(out, iris, w_iris)
    out = _mix(out, _shade(iris, 0.55), ring * 0.8)
    if p.pupil == "slit":
        w_pupil = smoothstep(0.09, 0.06, np.abs(cs)) * smoothstep(iris_r - 4, iris_r - 8, ang)
    elif p.pupil == "glow":
        w_pupil = np.zeros(len(cf))  # glowing eyes: a bright centre instead of a pupil
        out = _mix(out, (0.92, 1.0, 1.0), smoothstep(16, 8, ang))
    else:
        w_pupil = smoothstep(15, 12, ang)
    out = _mix(out, (0.03, 0.03, 0.04), w_pupil)
    # Highlight up and toward the character's right (the viewer's left).
    hl = np.degrees(
        np.arccos(np.clip(cf * np.cos(np.radians(17)) + (cu * 0.8 - cs * 0.6) * np.sin(np.radians(17)), -1, 1))
    )
    return _mix(out, (1.0, 1.0, 1.0), smoothstep(7, 4.5, hl))


def _eyelid(p, centre, r, f, up, side, suffix, rgb) -> _Part:
    """A thick spherical shell with a round opening in front of the eyeball; blink closes it."""
    aperture = np.radians(50.0 if p.pupil != "compound" else 62.0)
    v, faces, s = uv_sphere(20, 36)
    lon = np.arctan2(v[:, 1], v[:, 0])
    theta = aperture + (np.pi - aperture) * (1 - 2 * s) ** 2  # angle from the gaze: back -> rim -> back
    r_out, r_in = 1.17 * r, 1.05 * r
    rho = (r_out + r_in) / 2 + (r_out - r_in) / 2 * np.cos(np.pi * s)
    local = np.stack([np.sin(theta) * np.cos(lon), np.sin(theta) * np.sin(lon), np.cos(theta)], 1) * rho[:, None]
    a, b, c = local[:, 0], local[:, 1], local[:, 2]  # side, up, forward coordinates
    verts = centre + a[:, None] * side + b[:, None] * up + c[:, None] * f
    faces = orient_outward(verts, faces)
    colors = _colors(len(verts), rgb)
    lash = smoothstep(0.09, 0.02, np.abs(s - 0.5))  # dark lash line along the rim
    colors = _mix(colors, (0.1, 0.07, 0.07), lash * (p.archetype != "robot"))

    # Blink: rotate each point about the eye's side axis so the opening's upper and lower rims
    # meet slightly below the middle; the skin behind them stretches smoothly.
    alpha = np.clip(a / rho, -1, 1)
    e = np.arctan2(b, c)  # angle in the up-forward plane
    e_top = np.arctan2(np.sqrt(np.clip(np.sin(aperture) ** 2 - alpha**2, 0, None)), np.cos(aperture))
    e_meet = -0.15 * e_top
    span = 1.8
    upper = e >= e_meet
    g_up = 1 - smoothstep(e_top, e_top + span, e)
    g_lo = 1 - smoothstep(e_top, e_top + span, -e)
    shift = np.where(upper, -(e_top - e_meet) * g_up, (e_top + e_meet) * g_lo)
    ang = e + shift
    rr = np.sqrt(b**2 + c**2)
    # Slight bulge of the closed lid keeps it outside the eyeball halfway through a blink.
    bulge = 1 + 0.12 * np.where(upper, g_up, g_lo) * (e_top / np.sin(aperture))
    nb, nc = rr * np.sin(ang) * bulge, rr * np.cos(ang) * bulge
    na = a * bulge
    closed = centre + na[:, None] * side + nb[:, None] * up + nc[:, None] * f
    part = _Part(f"eyelid_{suffix}", verts, faces, colors)
    part.morphs[f"blink_{suffix}"] = closed - verts
    return part


def _brow(p, centre, r, f, up, side_sign, head: _Part, suffix) -> _Part:
    angles = np.radians(np.linspace(-55, 55, 11))
    lateral = np.array([side_sign, 0.0, 0.0])
    pts = []
    for ang in angles:
        target = centre + r * 1.5 * (up * np.cos(ang) + lateral * np.sin(ang)) + f * r * 0.2
        pts.append(surface_along(head.vertices, np.zeros(3), target) + (target / np.linalg.norm(target)) * 0.012)
    pts = np.stack(pts)
    u = np.linspace(0, 1, len(pts))
    rad = (0.028 + 0.012 * p.brow_size) * (0.4 + 0.6 * np.sin(np.pi * u) ** 0.5) * p.brow_size
    v, faces = tube(pts, np.maximum(rad, 0.006), 8)
    rgb = p.brow_color if p.brow_color is not None else _shade(p.base_color, 0.5)
    part = _Part("brow", v, faces, _colors(len(v), rgb))
    inner = smoothstep(0.6, -0.6, (np.abs(v[:, 0]) - abs(centre[0])) / (r * 1.3))  # 1 at the nose side
    part.morphs["brow_up"] = np.tile(up * 0.09 + f * 0.01, (len(v), 1))
    part.morphs["frown"] = np.stack([-side_sign * 0.03 * inner, -0.07 * inner, 0.02 * inner], 1)
    return part


# --------------------------------------------------------------------------------------------
# nose, ears, horns, extras


def _build_nose(p: CharacterParams, face: _Face) -> list[_Part]:
    if p.nose == "none":
        return []
    s = p.nose_size
    if p.nose == "beak":
        base = face.nose_tip + np.array([0, 0.02, -0.08])
        path = np.stack([base, base + [0, -0.07, 0.12], base + [0, -0.17, 0.2]])
        v, f = tube(path, np.array([s * 0.55, s * 0.38, 0.01]), 16)
        v[:, 0] *= 1.3
        return [_Part("nose", v, f, _colors(len(v), p.nose_color))]
    if p.nose == "human":
        c = face.nose_tip + np.array([0, 0.0, -s * 0.5])
        v, f = _ellipsoid(c, (s * 0.8, s * 1.1, s * 0.9), 3)
        return [_Part("nose", v, f, _colors(len(v), _shade(p.base_color, 0.96)))]
    c = face.nose_tip + np.array([0, 0.0, -s * 0.45])
    v, f = _ellipsoid(c, (s * 1.2, s * 0.8, s * 0.8), 3)
    shine = smoothstep(0.5, 0.9, (v - c)[:, 1] / (s * 0.8) * 0.6 + (v - c)[:, 2] / (s * 0.8) * 0.5)
    colors = _mix(_colors(len(v), p.nose_color), (0.6, 0.6, 0.65), shine * 0.5)
    return [_Part("nose", v, f, colors)]


def _ear_shape(kind: str, width: float, height: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ear in its local frame (x across, y along, z facing forward): vertices, faces, inner-face weight."""
    v, f = icosphere(3)
    t = (v[:, 1] + 1) / 2  # 0 at the base, 1 at the tip
    ring = np.sqrt(np.clip(1 - v[:, 1] ** 2, 1e-9, 1))  # cross-section radius of the sphere
    if kind in ("pointy", "tuft"):
        wf = (1 - t) ** 0.85 * (0.55 + 0.45 * np.sqrt(np.clip(1 - (2 * t - 1) ** 2, 0, 1))) + 0.02
    elif kind in ("long", "floppy", "side", "leaf"):
        wf = np.sin(np.pi * t) ** 0.7 * (1 - 0.5 * t) + 0.03
        wf = np.where(t < 0.15, np.maximum(wf, 0.45 * np.sqrt(t / 0.15)), wf) * (1.3 if kind == "leaf" else 1.0)
    else:  # round, human: a flattened disc
        wf = ring
    thick = 0.22 if kind != "leaf" else 0.12
    x = v[:, 0] / ring * wf * width / 2
    z = v[:, 2] / ring * wf * width / 2 * thick
    cup = -0.22 * width * (1 - np.clip((2 * x / width) ** 2, 0, 1)) * np.sin(np.pi * np.clip(t, 0, 1))
    y = t * height
    verts = np.stack([x, y, z + cup], 1)
    inner = (
        (v[:, 2] > 0.1) * smoothstep(0.9, 0.5, np.abs(v[:, 0])) * smoothstep(0.95, 0.7, t) * smoothstep(0.02, 0.12, t)
    )
    return verts, f, inner


def _build_ears(p: CharacterParams, face: _Face, head: _Part) -> list[_Part]:
    if p.ear == "none":
        return []
    parts = []
    for side_sign, suffix in ((1.0, "left"), (-1.0, "right")):
        d = _dir(p.ear_azimuth, p.ear_elevation, side_sign)
        base = surface_along(head.vertices, np.zeros(3), d)
        normal = base / np.linalg.norm(base)
        out = np.array([side_sign, 0.0, 0.0])
        tilt = np.radians(p.ear_tilt if p.ear != "floppy" else 115.0)
        axis = np.cos(tilt) * np.array([0.0, 1.0, 0.0]) + np.sin(tilt) * out + np.array([0, 0, -0.15])
        axis /= np.linalg.norm(axis)
        fwd = np.array([0.0, 0.0, 1.0]) - axis * axis[2]
        fwd /= np.linalg.norm(fwd)
        across = np.cross(axis, fwd)
        if p.ear == "antenna":
            parts.append(_antenna(p, base - normal * 0.05, axis, f"ear_{suffix}", side_sign))
            continue
        if p.ear == "bolt":
            path = np.stack([base - out * 0.1, base + out * 0.05, base + out * 0.12])
            v, f = tube(path, np.array([0.16, 0.16, 0.12]) * p.ear_size / 0.3, 20)
            part = _Part(f"ear_{suffix}", v, f, _colors(len(v), _shade(p.base_color, 0.8)))
            pivot, swing = base, out
        else:
            h = p.ear_size
            w = p.ear_size * p.ear_width
            if p.ear == "human":
                fwd, across = out, np.array([0.0, 0.0, side_sign * -1.0])
                axis = np.array([0.0, 1.0, 0.0])
                local, f, inner = _ear_shape("human", w, h)
                local[:, 1] -= h * 0.5
                sink = 0.05
            else:
                local, f, inner = _ear_shape(p.ear, w, h)
                sink = 0.16 * h + 0.04
            v = base + local[:, :1] * across + (local[:, 1:2] - sink) * axis + local[:, 2:3] * fwd
            f = orient_outward(v, f)
            rgb = p.base_color if p.ear != "leaf" else p.ear_inner_color
            colors = _colors(len(v), rgb)
            if p.ear in ("pointy", "round", "long", "side", "floppy", "tuft"):
                colors = _mix(colors, p.ear_inner_color, inner)
            if p.ear == "leaf":  # a vein down the middle
                colors = _mix(colors, _shade(rgb, 0.7), smoothstep(0.03, 0.0, np.abs(local[:, 0])) * 0.8)
            if p.ear_tip_color is not None:
                colors = _mix(colors, p.ear_tip_color, smoothstep(0.7, 0.85, local[:, 1] / h))
            part = _Part(f"ear_{suffix}", v, f, colors)
            pivot, swing = base, fwd
        # Ear wave: swing outward about the ear's forward axis through its base.
        part.morphs["ear_wave"] = rotate_about(part.vertices, pivot, swing, -side_sign * EAR_ANGLE) - part.vertices
        parts.append(part)
    return parts


def _antenna(p, base, axis, label, side_sign) -> _Part:
    h = p.ear_size
    t = np.linspace(0, 1, 9)[:, None]
    bend = np.array([side_sign * 0.25, 0.0, 0.15]) * h
    path = base + axis * (t * h) + bend * t**2
    v1, f1 = tube(path, np.linspace(0.035, 0.022, len(path)), 10)
    v2, f2 = _ellipsoid(path[-1], (0.08, 0.08, 0.08), 2)
    v = np.concatenate([v1, v2])
    f = np.concatenate([f1, f2 + len(v1)])
    colors = np.concatenate([_colors(len(v1), _shade(p.base_color, 0.8)), _colors(len(v2), p.extra_color)])
    part = _Part(label, v, f, colors)
    part.morphs["ear_wave"] = rotate_about(v, base, np.array([0.0, 0.0, 1.0]), -side_sign * EAR_ANGLE) - v
    return part


def _build_horns(p: CharacterParams, face: _Face, head: _Part) -> list[_Part]:
    if p.horn == "none":
        return []
    comps = []
    s = p.horn_size
    label = "horn"
    rgb = p.horn_color
    if p.horn in ("antlers", "horns"):
        for side_sign in (1.0, -1.0):
            base = surface_along(head.vertices, np.zeros(3), _dir(28, 62, side_sign))
            out = np.array([side_sign, 0.0, 0.0])
            t = np.linspace(0, 1, 12)[:, None]
            if p.horn == "antlers":
                path = base + s * (
                    out * (0.45 * t + 0.2 * t**2)
                    + np.array([0, 1.0, 0]) * (0.9 * t - 0.15 * t**2)
                    + np.array([0, 0, -1.0]) * (0.25 * t - 0.35 * t**2)
                )
                comps.append(tube(path, np.linspace(0.075, 0.025, len(path)) * (0.6 + 0.4 * s), 10))
                for k, (at, direction) in enumerate(
                    ((0.35, (0.1, 0.6, 0.8)), (0.65, (0.35, 0.8, 0.35)), (0.9, (0.6, 0.6, -0.3)))
                ):
                    start = path[int(at * (len(path) - 1))]
                    dvec = np.array([direction[0] * side_sign, direction[1], direction[2]])
                    tt = np.linspace(0, 1, 6)[:, None]
                    tine = start + s * 0.38 * (tt * dvec + tt**2 * np.array([0, 0.3, 0]))
                    comps.append(tube(tine, np.linspace(0.045, 0.012, 6) * (0.6 + 0.4 * s), 8))
            else:
                path = base + s * (
                    out * (0.35 * t + 0.15 * t**2)
                    + np.array([0, 1.0, 0]) * (0.55 * t)
                    + np.array([0, 0, -1.0]) * (0.15 * t + 0.3 * t**3)
                )
                comps.append(tube(path, np.linspace(0.13, 0.005, len(path)) * (0.6 + 0.4 * s), 14))
    elif p.horn == "spikes":
        for el in np.linspace(62, 150, 6):  # along the midline, from the forehead over the top to the back
            d = np.array([0.0, np.sin(np.radians(el)), np.cos(np.radians(el))])
            base = surface_along(head.vertices, np.zeros(3), d)
            n = base / np.linalg.norm(base)
            path = np.stack(
                [
                    base - n * 0.06,
                    base + n * s * 0.2 - np.array([0, 0, 0.05]),
                    base + n * s * 0.42 - np.array([0, 0, 0.12]),
                ]
            )
            comps.append(tube(path, np.array([0.1, 0.06, 0.004]) * (0.7 + 0.3 * s), 10))
    elif p.horn == "antenna":
        base = surface_along(head.vertices, np.zeros(3), np.array([0.0, 1.0, 0.0]))
        path = np.stack([base - [0, 0.05, 0], base + [0, s * 0.5, 0], base + [0, s, 0]])
        comps.append(tube(path, np.array([0.05, 0.035, 0.03]), 10))
        comps.append(_ellipsoid(base + [0, s + 0.05, 0], (0.1, 0.1, 0.1), 2))
        label = "antenna"
    part = _merge_comps(label, comps, rgb if label == "horn" else _shade(p.base_color, 0.8))
    if label == "antenna":
        part.colors[-len(comps[-1][0]) :] = p.extra_color  # the knob on top
    return [part]


def _build_extras(p: CharacterParams, face: _Face, head: _Part, rng: np.random.Generator) -> list[_Part]:
    parts = []
    if "fin" in p.extras:
        v, f = icosphere(3)
        t = (v[:, 1] + 1) / 2
        base = surface_along(head.vertices, np.zeros(3), np.array([0.0, 1.0, -0.25]))
        wf = (1 - t) ** 1.1 + 0.02
        verts = np.stack([v[:, 0] * 0.07 * wf, t * 0.65, v[:, 2] * 0.45 * wf - 0.45 * t**1.5], 1) + base - [0, 0.1, 0]
        parts.append(_Part("fin", verts, orient_outward(verts, f), _colors(len(verts), p.extra_color)))
    if "tears" in p.extras and face.eyes:
        comps = []
        for centre, r, f_eye in face.eyes:
            side = np.sign(centre[0])
            c = centre + np.array([side * r * 0.3, -r * 1.45, r * 0.55])
            v, f = icosphere(2)
            up = np.clip(v[:, 1], 0, None)
            v = v * np.array([0.06, 0.08, 0.05])
            v[:, 1] += up * 0.05  # drop: pointed at the top
            v[:, 0] *= 1 - 0.7 * up
            comps.append((v + c, f))
        parts.append(_merge_comps("tear", comps, (0.55, 0.8, 1.0)))
    if "petals" in p.extras:
        comps = []
        count = 11
        radius = max(p.head_radii[0], p.head_radii[1]) * 0.98
        for k in range(count):
            ang = 2 * np.pi * k / count + np.pi / 2 + float(rng.uniform(-0.05, 0.05))
            radial = np.array([np.cos(ang), np.sin(ang), 0.0])
            v, f = icosphere(2)
            tang = np.array([-np.sin(ang), np.cos(ang), 0.0])
            length = 0.42
            local = v * np.array([length, 0.2, 0.06])
            local[:, 1] *= 1 - 0.5 * np.clip(v[:, 0], 0, 1) ** 2
            pos = radial * (radius + length * 0.55) + np.array([0, 0, -0.25 + 0.1 * np.cos(ang)])
            verts = pos + local[:, :1] * radial + local[:, 1:2] * tang + local[:, 2:3] * np.array([0, 0, 1.0])
            verts[:, 2] += 0.12 * (local[:, 0] / length) ** 2
            comps.append((verts, orient_outward(verts, f)))
        parts.append(_merge_comps("petal", comps, p.extra_color))
    if "hair" in p.extras:
        v, f = icosphere(4)
        q = v * np.asarray(p.head_radii) * 1.07
        zf = v[:, 2]
        hairline = 0.25 + 0.35 * smoothstep(-0.3, 0.7, zf)  # lower at the back, higher at the forehead
        inside = smoothstep(hairline + 0.05, hairline - 0.12, v[:, 1])
        q = q * (1 - 0.22 * inside)[:, None]
        q[:, 1] += 0.08 * np.clip(v[:, 1], 0, None) * (1 + 0.3 * np.sin(v[:, 0] * 9) * (v[:, 2] > 0.3))
        parts.append(_Part("hair", q, f, _colors(len(q), p.hair_color)))
    return parts


def _merge_comps(label: str, comps, rgb) -> _Part:
    verts, faces, off = [], [], 0
    for v, f in comps:
        verts.append(v)
        faces.append(f + off)
        off += len(v)
    v = np.concatenate(verts)
    return _Part(label, v, np.concatenate(faces), _colors(len(v), rgb))


# --------------------------------------------------------------------------------------------
# skin colours


def _paint_skin(p: CharacterParams, face: _Face, head: _Part, jaw: _Part, rng: np.random.Generator) -> None:
    y_m = face.y_mouth
    for part in (head, jaw):
        v = part.vertices
        c = _colors(len(v), p.base_color)
        if p.secondary == "muzzle":
            if face.snouted:
                w = smoothstep(face.z_hinge + 0.05, face.z_hinge + 0.35, v[:, 2]) * smoothstep(
                    y_m + 0.35, y_m + 0.12, v[:, 1]
                )
            else:
                d = np.linalg.norm((v - [0, y_m, face.z_mouth]) * [1.0, 1.3, 0.6], axis=1)
                w = smoothstep(0.5, 0.35, d)
            if part.label == "jaw":
                w = np.ones(len(v))
            c = _mix(c, p.secondary_color, w)
        elif p.secondary == "belly":
            w = smoothstep(y_m + 0.12, y_m - 0.05, v[:, 1]) if part.label == "head" else np.ones(len(v))
            c = _mix(c, p.secondary_color, w)
        elif p.secondary == "blaze":
            w_m = smoothstep(face.z_hinge + 0.05, face.z_hinge + 0.3, v[:, 2]) * smoothstep(
                y_m + 0.35, y_m + 0.15, v[:, 1]
            )
            w_b = smoothstep(0.16, 0.1, np.abs(v[:, 0])) * (v[:, 2] > 0) * smoothstep(0.0, 0.3, v[:, 2])
            w = np.maximum(w_m, w_b) if part.label == "head" else np.ones(len(v))
            c = _mix(c, p.secondary_color, w)
        elif p.secondary == "face":
            dirs = v / np.linalg.norm(v, axis=1, keepdims=True)
            w = smoothstep(0.55, 0.75, dirs[:, 2]) * smoothstep(0.7, 0.5, dirs[:, 1])
            c = _mix(c, p.secondary_color, w if part.label == "head" else np.ones(len(v)))
        if part.label == "head":
            away = _away_from_face(v, face)
            if p.pattern == "stripes":
                az = np.arctan2(v[:, 0], -v[:, 2])
                w = (
                    smoothstep(0.55, 0.75, np.sin(az * 9 + v[:, 1] * 2))
                    * smoothstep(0.0, 0.3, v[:, 1] - y_m - 0.3)
                    * away
                )
                c = _mix(c, p.pattern_color, w)
            elif p.pattern == "spots":
                dirs = rng.normal(size=(22, 3))
                dirs[:, 1] = np.abs(dirs[:, 1]) + 0.2
                dirs[:, 2] -= 0.6
                centres = np.stack([surface_along(v, np.zeros(3), d) for d in dirs])
                sizes = rng.uniform(0.06, 0.12, len(centres))
                dist = np.min(np.linalg.norm(v[:, None] - centres[None], axis=2) / sizes[None], axis=1)
                c = _mix(c, p.pattern_color, smoothstep(1.0, 0.8, dist) * away)
            elif p.pattern == "panels":
                band = smoothstep(0.02, 0.008, np.abs(np.abs(v[:, 0]) - 0.62 * p.head_radii[0]))
                c = _mix(c, p.pattern_color, band * away)
                rivet = np.zeros(len(v))
                for x in (-0.75, 0.75):
                    for y in (0.55, -0.1):
                        rivet = np.maximum(
                            rivet, smoothstep(0.05, 0.03, np.linalg.norm(v[:, :2] - [x * p.head_radii[0], y], axis=1))
                        )
                c = _mix(c, _shade(p.base_color, 0.6), rivet * (v[:, 2] > 0))
            elif p.pattern == "top":
                c = _mix(c, p.pattern_color, smoothstep(0.2, 0.6, v[:, 1]) * away)
            if "gills" in p.extras:
                for k in range(3):
                    zc = face.z_hinge - 0.2 - 0.14 * k
                    w = smoothstep(0.025, 0.01, np.abs(v[:, 2] - zc)) * smoothstep(
                        0.25, 0.1, np.abs(v[:, 1] - y_m - 0.05)
                    )
                    c = _mix(c, _shade(p.base_color, 0.55), w)
            if "blush" in p.extras and face.eyes:
                for centre, r, _ in face.eyes:
                    bc = centre + np.array([np.sign(centre[0]) * r * 0.6, -r * 1.6, 0.0])
                    w = smoothstep(0.16, 0.08, np.linalg.norm(v - bc, axis=1))
                    c = _mix(c, (1.0, 0.55, 0.6), 0.55 * w)
        part.colors = c


def _away_from_face(v: np.ndarray, face: _Face) -> np.ndarray:
    """[N] 0 near the eyes and the mouth (keep patterns off the features), 1 elsewhere."""
    w = np.ones(len(v))
    for centre, r, _ in face.eyes:
        w *= smoothstep(r * 1.3, r * 1.8, np.linalg.norm(v - centre, axis=1))
    if face.corners is not None:
        mid = face.corners.mean(0)
        w *= smoothstep(0.25, 0.4, np.linalg.norm((v - mid) * [0.7, 1.0, 1.0], axis=1))
    return w


# --------------------------------------------------------------------------------------------
# assembly


def build_character(p: CharacterParams, rng: np.random.Generator) -> Mesh:
    """Parameters -> canonical Mesh (part labels, vertex colours, rig morph targets)."""
    head, face = _build_head(p, rng)
    jaw = _build_jaw(p, face)
    parts = [head, jaw]
    parts += _build_mouth(p, face, head, jaw)
    parts += _build_eyes(p, face, head)
    _face_morphs(p, face, head, jaw)
    parts += _build_nose(p, face)
    parts += _build_ears(p, face, head)
    parts += _build_horns(p, face, head)
    parts += _build_extras(p, face, head, rng)
    _paint_skin(p, face, head, jaw, rng)

    controls = [c for c in RIG_CONTROLS if any(c in part.morphs for part in parts)]
    named = []
    for part in parts:
        m = Mesh(
            part.vertices.astype(np.float32),
            part.faces.astype(np.int32),
            np.clip(part.colors, 0, 1).astype(np.float32),
            morph_targets={c: part.morphs.get(c, np.zeros_like(part.vertices)).astype(np.float32) for c in controls},
        )
        named.append((part.label, m))
    mesh = merge_meshes(named)
    mesh, _ = normalize(mesh, facing="+z")
    return mesh.validate("procedural character")


@dataclass
class GenerationResult:
    mesh: Mesh  # canonical character
    info: dict  # backend, archetype, notices, timing (recorded in the manifest)
    notices: list[str]  # lines for the user


def generate_procedural(prompt: str, seed: int = 0) -> GenerationResult:
    """The offline default backend: a parametric cartoon head read from the prompt."""
    start = time.perf_counter()
    parsed = parse_prompt(prompt, seed)
    rng = np.random.default_rng(prompt_seed(prompt, seed) ^ 0x5EED)
    mesh = build_character(parsed.params, rng)
    info = {
        "backend": "procedural",
        "prompt": prompt,
        "seed": int(seed),
        "archetype": parsed.archetype,
        "matched_words": parsed.matched,
        "ignored_words": parsed.ignored,
        "params": asdict(parsed.params),
        "vertices": mesh.num_vertices,
        "faces": int(len(mesh.faces)),
        "rig_controls": mesh.morph_names,
        "seconds": round(time.perf_counter() - start, 3),
    }
    return GenerationResult(mesh, info, parsed.notices)
