"""Automatic face rig: landmarks -> deformers that behave like a face -> ARKit-named morph targets.

Works in the canonical frame (+Z forward, Y up, the character's left = +X). Every shape is a
deformer evaluated once at full strength and stored as per-vertex offsets [N, 3]:

- jaw (jawOpen, jawForward, jawLeft/Right): a rotation about a hinge axis (along X, behind the
  mouth at about the nose's height, or the user's ``jaw_hinge`` vertex). The weight of a vertex
  is d_static / (d_static + d_jaw) over geodesic distances (along the surface, never through
  the air) to the parts that stay (upper lip, everything above the nose, behind the hinge, the
  neck) and to the parts the jaw carries (lower lip, chin). Where the mesh has a lip seam the two
  anchors lie on opposite sides of the opening and the lips part; a sealed mouth is reported.
  Parts the surface does not reach (teeth, tongue, a separate jaw) follow the jaw if they sit
  below the mouth line (rigid when small, like a tooth).
- lids (eyeBlink*, eyeWide*, eyeSquint*): over a round eye (a fitted eyeball part, else a surface
  in the opening that bulges like a ball: a sphere behind the lid opening) lid vertices turn about
  the eyeball centre around the eye's corner-to-corner axis; a turn about the centre keeps each
  vertex's distance to it, so a lid never enters the ball. Over a flat eye (a painted eye, a flat
  eye disc, a socket, an empty opening) there is no ball: lid vertices slide across that axis in
  the face's plane and the opening squashes. The upper lid moves down and the lower lid up until
  both reach the meeting line, and no vertex passes it. Weights fall off geodesically from the lid
  margin (the surface path through the lid landmarks, 0 at the corners) and the upper lid's weight
  is cut where the lower lid is nearer, so weights never leak from one lid to the other.
- eyeballs (eyeLook*): a separate eyeball part turns rigidly about its centre.
- mouth, cheeks, brows, nose (mouthSmile*, mouthFrown*, browInnerUp, ...): surface-tangent
  displacements of a seed point with a smooth geodesic falloff (Wendland-like (1 - t^2)^2); a smile's weight also
  fades out along the lips before the mouth's centre line, so the lips' middle stays still.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from t2bs.errors import UserError
from t2bs.face.arkit import ARKIT_NAMES as ARKIT_52
from t2bs.geometry.curves import smoothstep
from t2bs.geometry.mesh import Mesh, vertex_normals, welded_components
from t2bs.rig.face import FaceLandmarks, fit_sphere
from t2bs.rig.surface import Surface

# Apple's 52 ARKit blend shape locations, alphabetical: the order the rig's morph targets are written in.
ARKIT_NAMES = sorted(ARKIT_52)
NOT_MODELLED = "lip roll / press / close need the lips' volume, which the auto rig does not model"
# Positions in the 20 landmarks (68-point order 36-47, 60-67).
EYES = {"right": slice(0, 6), "left": slice(6, 12)}  # each: corner, upper, upper, corner, lower, lower
MOUTH_CORNER = {"right": 12, "left": 16}
UPPER_LIP = {"right": 13, "mid": 14, "left": 15}
LOWER_LIP = {"left": 17, "mid": 18, "right": 19}


@dataclass
class AutoRigConfig:
    jaw_open: float = 0.8  # lower-lip travel of a full jawOpen along its arc, in mouth widths (ARKit 1 = fully open)
    # Where closed lids meet (0 = at the lower lid, 1 = at the upper lid). None: by the eye, LID_MEET_ROUND over
    # a round eye, the equal-strain line over a flat one (see ``lid_meet_line``).
    lid_meet: float | None = None
    smile: float = 0.22  # mouth-corner travel of a full smile, in mouth widths
    frown: float = 0.12  # mouth-corner travel of a full frown, in mouth widths
    brow: float = 0.10  # brow travel, in inter-ocular distances
    eye_look_deg: float = 20.0  # eyeball turn of a full eyeLook*, degrees
    falloff: float = 1.0  # scale of every falloff radius (larger: softer, wider shapes)


@dataclass
class AutoRig:
    morph_targets: dict[str, np.ndarray]  # ARKit name -> [N, 3] float32 offsets (the mesh's frame)
    missing: dict[str, str]  # ARKit name -> why this mesh does not get it
    landmarks: FaceLandmarks  # where the face was found
    info: dict = field(default_factory=dict)  # hinge, eye centres, mouth seam or sealed, jaw angle

    def summary(self) -> dict:
        return {
            "shapes": list(self.morph_targets),
            "missing": dict(self.missing),
            "landmarks": self.landmarks.to_dict(),
            **self.info,
        }


def _falloff(t: np.ndarray) -> np.ndarray:
    """1 at t = 0, 0 from t = 1 on, flat at both ends (no crease where the weight starts or stops)."""
    t = np.clip(np.nan_to_num(t, nan=1.0, posinf=1.0), 0.0, 1.0)
    return (1.0 - t * t) ** 2


def _unit(v) -> np.ndarray:
    v = np.asarray(v, np.float64)
    return v / max(float(np.linalg.norm(v)), 1e-12)


def rotate_about(points: np.ndarray, centre: np.ndarray, axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rodrigues: points [P, 3] turned by ``angle`` (radians, scalar or [P]) about the line centre + t axis."""
    k = _unit(axis)
    p = np.asarray(points, np.float64) - centre
    a = np.broadcast_to(np.asarray(angle, np.float64), (len(p),))[:, None]
    c, s = np.cos(a), np.sin(a)
    return centre + p * c + np.cross(k, p) * s + np.outer(p @ k, k) * (1 - c)


@dataclass
class _Face:
    """Measurements of the face the deformers are scaled by (canonical frame)."""

    v: np.ndarray  # [N, 3] float64 vertices
    normals: np.ndarray  # [N, 3] unit vertex normals
    P: np.ndarray  # [20, 3] landmark positions
    ids: np.ndarray  # [20] landmark vertex ids
    skin: np.ndarray  # [N] bool: the surface(s) the landmarks lie on
    io: float  # inter-ocular distance (eye centre to eye centre)
    mw: float  # mouth width (corner to corner)
    em: float  # height of the eyes over the mouth
    mc: np.ndarray  # [3] mouth centre

    def seam_y(self, x: np.ndarray) -> np.ndarray:
        """Height of the mouth line at x: through the corners and the middles of the inner-lip pairs."""
        pts = [self.P[12], self.P[16]] + [(self.P[u] + self.P[lo]) / 2 for u, lo in ((13, 19), (14, 18), (15, 17))]
        pts = np.asarray(sorted(pts, key=lambda p: p[0]))
        return np.interp(x, pts[:, 0], pts[:, 1])

    def front_vertex(self, x: float, y: float, radius: float) -> int:
        """The foremost skin vertex within ``radius`` of (x, y) seen from the front (nearest if none)."""
        dxy = np.hypot(self.v[:, 0] - x, self.v[:, 1] - y)
        cand = np.nonzero(self.skin & (dxy < radius))[0]
        if len(cand):
            return int(cand[np.argmax(self.v[cand, 2])])
        sk = np.nonzero(self.skin)[0]
        return int(sk[np.argmin(dxy[sk])])

    def tangent(self, direction) -> np.ndarray:
        """[N, 3] ``direction`` with the normal component removed at each vertex (slides on the surface)."""
        d = np.asarray(direction, np.float64)
        return d[None] - (self.normals @ d)[:, None] * self.normals


def _check_landmarks(P: np.ndarray) -> None:
    eye_r, eye_l, mouth = P[0:6].mean(0), P[6:12].mean(0), P[12:20]
    if eye_l[0] <= eye_r[0]:
        raise UserError(
            "landmarks: the left eye (42-47) must be on the character's left (+X) of the right eye (36-41); "
            "check the 68-point order or the mesh's facing"
        )
    if min(eye_l[1], eye_r[1]) <= mouth[:, 1].mean():
        raise UserError("landmarks: the eyes must be above the mouth (Y up); check the order or the mesh's up axis")
    if P[16, 0] <= P[12, 0]:
        raise UserError("landmarks: mouth corner 64 (character's left) must be at +X of corner 60")


def autorig(mesh: Mesh, landmarks: FaceLandmarks, config: AutoRigConfig = AutoRigConfig()) -> AutoRig:
    """ARKit morph targets for ``mesh`` (canonical frame) from its face ``landmarks``."""
    v = mesh.vertices.astype(np.float64)
    ids = np.asarray(landmarks.vertex_ids, np.int64)
    P = v[ids]
    _check_landmarks(P)
    comp = welded_components(mesh.vertices, mesh.faces)
    skin = np.isin(comp, comp[ids])
    eyeballs = {s: np.asarray(e, np.int64) for s, e in landmarks.eyeballs.items()}
    for e in eyeballs.values():
        skin[e] = False
    f = _Face(
        v,
        vertex_normals(v, mesh.faces).astype(np.float64),
        P,
        ids,
        skin,
        float(np.linalg.norm(P[6:12].mean(0) - P[0:6].mean(0))),
        float(np.linalg.norm(P[16] - P[12])),
        float(0.5 * (P[0:6, 1].mean() + P[6:12, 1].mean()) - P[12:20, 1].mean()),
        P[12:20].mean(0),
    )
    surf = Surface(v, mesh.faces)
    fo = config.falloff
    shapes: dict[str, np.ndarray] = {}
    missing: dict[str, str] = {}
    info: dict = {}

    # ---- jaw
    w_jaw, hinge, jaw_info = _jaw_weights(mesh, f, surf, landmarks, eyeballs, comp)
    info.update(jaw_info)
    lower_mid = P[LOWER_LIP["mid"]]
    radius = float(np.hypot(*(lower_mid - hinge)[1:]))
    angle = float(
        np.clip(config.jaw_open * f.mw / max(radius, 1e-9), np.radians(8), np.radians(30))
    )  # a human jaw opens ~25-30 degrees
    info["jaw_angle_deg"] = round(float(np.degrees(angle)), 2)
    turned = rotate_about(v, hinge, np.array([1.0, 0, 0]), angle)
    shapes["jawOpen"] = w_jaw[:, None] * (turned - v)
    shapes["jawForward"] = w_jaw[:, None] * np.array([0, 0, 0.12 * f.mw])
    shapes["jawLeft"] = w_jaw[:, None] * np.array([0.12 * f.mw, 0, 0])
    shapes["jawRight"] = w_jaw[:, None] * np.array([-0.12 * f.mw, 0, 0])

    # Small parts sitting on the skin (lashes, brow cards, decals) follow the skin under them: the
    # lids turn them with the weight of their skin vertex, the other shapes copy its displacement;
    # teeth, tongue and eyeballs keep their own bones (jaw, eyeLook*).
    attached = _attachments(f, comp, eyeballs) if len(mesh.part_names) < 3 else (np.zeros(0, np.int64),) * 2
    info["attached_vertices"] = int(len(attached[0]))

    # ---- lids and eyeballs
    upper_lid = np.zeros(len(v))  # largest upper-lid weight of either eye (brows leave the lid margin still)
    for side in ("left", "right"):
        lid = _lids(f, surf, side, eyeballs.get(side), config, attached, comp)
        info[f"eye_{side}"] = lid["info"]
        cap = side.capitalize()
        shapes[f"eyeBlink{cap}"] = lid["move"](1.0, 1.0, clamp=True)
        shapes[f"eyeWide{cap}"] = lid["move"](-0.3, 0.0, clamp=False)
        shapes[f"eyeSquint{cap}"] = lid["move"](0.15, 0.45, clamp=True)
        upper_lid = np.maximum(upper_lid, lid["w_upper"])
        ball = eyeballs.get(side)
        if ball is None or len(ball) < 4:
            for d in ("Up", "Down", "In", "Out"):
                missing[f"eyeLook{d}{cap}"] = "no separate eyeball part (painted or sculpted-in eyes cannot turn)"
            continue
        c, _, _ = fit_sphere(v[ball])
        out_sign = 1.0 if side == "left" else -1.0
        a = np.radians(config.eye_look_deg)
        for d, axis, ang in (
            ("Up", [1, 0, 0], -a),
            ("Down", [1, 0, 0], a),
            ("Out", [0, 1, 0], out_sign * a),
            ("In", [0, 1, 0], -out_sign * a),
        ):
            off = np.zeros_like(v)
            off[ball] = rotate_about(v[ball], c, np.asarray(axis, float), ang) - v[ball]
            shapes[f"eyeLook{d}{cap}"] = off

    # ---- mouth, cheeks, nose, brows: falloffs flow across touching parts (lips laid on a head)
    balls = np.zeros(len(v), bool)
    for e in eyeballs.values():
        balls[e] = True
    surf = Surface(v, mesh.faces, glue=0.02 * f.io, exclude=balls)
    reach, _ = surf.distance(ids)
    f = replace(f, skin=f.skin | (np.isfinite(reach) & ~balls))
    d_up, _ = surf.distance(ids[[13, 14, 15]])
    d_lo, _ = surf.distance(ids[[17, 18, 19]])
    with np.errstate(invalid="ignore"):  # parts neither lip reaches: nan, no mouth weight there
        upper_side = np.nan_to_num(
            np.clip((d_lo - d_up) / (0.1 * f.mw) + 0.5, 0.0, 1.0), nan=0.5
        )  # 1: upper lip's side
    up, fwd = np.array([0, 1.0, 0]), np.array([0, 0, 1.0])
    mouth_d, _ = surf.distance(ids[12:20], limit=0.7 * f.mw * fo)
    for side in ("left", "right"):
        cap = side.capitalize()
        out = np.array([1.0 if side == "left" else -1.0, 0, 0])
        corner = ids[MOUTH_CORNER[side]]
        d_c, _ = surf.distance([corner], limit=0.9 * f.mw * fo)
        # A smile pulls the corner up and back and leaves the middle of the lips still (every smile measured, the
        # artists' and the generator's: docs/AUTORIG.md), so its weight along the lips fades out before the centre line.
        lateral = out[0] * (f.v[:, 0] - f.mc[0]) / (0.5 * f.mw)  # 0 at the mouth's centre line, 1 at this corner
        shapes[f"mouthSmile{cap}"] = (
            _push(f, d_c, 0.8 * f.mw * fo, _unit(0.5 * out + 0.75 * up - 0.3 * fwd), config.smile * f.mw)
            * smoothstep(0.25, 0.85, lateral)[:, None]
        )
        shapes[f"mouthFrown{cap}"] = _push(f, d_c, 0.6 * f.mw * fo, _unit(0.3 * out - 0.9 * up), config.frown * f.mw)
        shapes[f"mouthDimple{cap}"] = _push(f, d_c, 0.5 * f.mw * fo, _unit(0.4 * out - 0.9 * fwd), 0.08 * f.mw)
        shapes[f"mouthStretch{cap}"] = _push(f, d_c, 0.7 * f.mw * fo, _unit(0.8 * out - 0.5 * up), 0.15 * f.mw)
        d_u, _ = surf.distance([ids[UPPER_LIP[side]]], limit=0.5 * f.mw * fo)
        d_l, _ = surf.distance([ids[LOWER_LIP[side]]], limit=0.5 * f.mw * fo)
        shapes[f"mouthUpperUp{cap}"] = _push(f, d_u, 0.5 * f.mw * fo, up, 0.1 * f.mw) * upper_side[:, None]
        shapes[f"mouthLowerDown{cap}"] = _push(f, d_l, 0.5 * f.mw * fo, -up, 0.1 * f.mw) * (1 - upper_side)[:, None]
    w_m = _falloff(mouth_d / (0.7 * f.mw * fo)) * f.skin
    shapes["mouthLeft"] = w_m[:, None] * np.array([0.15 * f.mw, 0, 0])
    shapes["mouthRight"] = w_m[:, None] * np.array([-0.15 * f.mw, 0, 0])
    squeeze = np.zeros_like(v)
    squeeze[:, 0] = f.mc[0] - v[:, 0]
    shapes["mouthPucker"] = w_m[:, None] * (0.3 * squeeze + np.array([0, 0, 0.12 * f.mw]))
    flare = (2 * upper_side - 1)[:, None] * np.array([0, 0.08 * f.mw, 0])
    shapes["mouthFunnel"] = w_m[:, None] * (0.2 * squeeze + np.array([0, 0, 0.1 * f.mw]) + flare)
    shapes["mouthShrugUpper"] = _push(f, d_up, 0.5 * f.mw * fo, up, 0.06 * f.mw) * upper_side[:, None]
    shapes["mouthShrugLower"] = _push(f, d_lo, 0.6 * f.mw * fo, up, 0.06 * f.mw) * (1 - upper_side)[:, None]
    for n in ("mouthClose", "mouthPressLeft", "mouthPressRight", "mouthRollLower", "mouthRollUpper"):
        missing[n] = NOT_MODELLED
    info["mouth"] = jaw_info["mouth"]

    # ---- cheeks, nose
    cheeks = []
    for side in ("left", "right"):
        cap = side.capitalize()
        sgn = 1.0 if side == "left" else -1.0
        c = P[MOUTH_CORNER[side]]
        cheeks.append(f.front_vertex(c[0] + sgn * 0.45 * f.mw, f.mc[1] + 0.25 * f.em, 0.15 * f.io))
        eye = P[EYES[side]].mean(0)
        we = float(np.linalg.norm(P[EYES[side]][0] - P[EYES[side]][3]))
        below_eye = f.front_vertex(eye[0], eye[1] - 0.6 * we, 0.15 * f.io)
        d_s, _ = surf.distance([below_eye], limit=0.5 * we * fo)
        shapes[f"cheekSquint{cap}"] = _push(f, d_s, 0.5 * we * fo, up, 0.05 * f.io)
        nose = f.front_vertex(f.mc[0] + sgn * 0.2 * f.io, f.mc[1] + 0.55 * f.em, 0.1 * f.io)
        d_n, _ = surf.distance([nose], limit=0.35 * f.em * fo)
        shapes[f"noseSneer{cap}"] = _push(f, d_n, 0.35 * f.em * fo, up, 0.05 * f.io)
    d_ch, _ = surf.distance(cheeks, limit=0.45 * f.em * fo)
    shapes["cheekPuff"] = (_falloff(d_ch / (0.45 * f.em * fo)) * f.skin)[:, None] * f.normals * 0.1 * f.mw

    # ---- brows
    brow = _brows(f, surf, landmarks, mesh, config, upper_lid)
    shapes.update(brow)

    # ---- tongue
    if "tongue" in mesh.part_names and mesh.part_mask("tongue").any():
        t = mesh.part_mask("tongue")
        off = np.zeros_like(v)
        off[t] = shapes["jawOpen"][t] + np.array([0, -0.15 * f.mw, 0.6 * f.mw])
        shapes["tongueOut"] = off
    else:
        missing["tongueOut"] = "no tongue part (a part labelled 'tongue')"

    # (part-labelled characters: every part already has its role -- brows, lids, lashes move as such)
    idx, nn = attached
    for name, d in shapes.items():
        if len(idx) and not name.startswith(("jaw", "eyeLook", "tongue", "eyeBlink", "eyeWide", "eyeSquint")):
            d[idx] = d[nn]
    out: dict[str, np.ndarray] = {}
    for name in ARKIT_NAMES:
        if name in shapes:
            d = np.nan_to_num(shapes[name]).astype(np.float32)
            if np.abs(d).max() > 1e-7 * mesh.bbox_diagonal():
                out[name] = d
            else:
                missing[name] = "its deformer moves nothing on this mesh (no surface around its landmark)"
    missing = {n: missing[n] for n in ARKIT_NAMES if n in missing}
    info["hinge"] = [round(float(x), 5) for x in hinge]
    return AutoRig(out, missing, landmarks, info)


def _attachments(f: _Face, comp: np.ndarray, eyeballs: dict) -> tuple[np.ndarray, np.ndarray]:
    """(vertex ids of parts lying on the skin, nearest skin vertex of each): every vertex of the part
    within 0.15 inter-ocular distances of the skin, and the part not in the mouth (teeth, tongue)."""
    from scipy.spatial import cKDTree

    skin_ids = np.nonzero(f.skin)[0]
    tree = cKDTree(f.v[skin_ids])
    balls = np.concatenate([np.asarray(e, np.int64) for e in eyeballs.values()]) if eyeballs else np.zeros(0, np.int64)
    idx, nn = [], []
    for c in np.unique(comp[~f.skin]):
        part = np.setdiff1d(np.nonzero(comp == c)[0], balls)
        if len(part) == 0:
            continue
        cen = f.v[part].mean(0)
        if abs(cen[0] - f.mc[0]) < 0.6 * f.mw and abs(cen[1] - f.mc[1]) < 0.35 * f.em:
            continue  # in the mouth
        dist, j = tree.query(f.v[part])
        if dist.max() < 0.15 * f.io:
            idx.append(part)
            nn.append(skin_ids[j])
    if not idx:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(idx), np.concatenate(nn)


def _push(f: _Face, dist: np.ndarray, radius: float, direction, amount: float) -> np.ndarray:
    """[N, 3] a displacement of ``amount`` along ``direction`` (tangent to the surface) falling off over ``radius``."""
    w = _falloff(dist / max(radius, 1e-12)) * f.skin
    return w[:, None] * f.tangent(direction) * amount


def _jaw_weights(mesh: Mesh, f: _Face, surf: Surface, landmarks: FaceLandmarks, eyeballs: dict, comp: np.ndarray):
    """([N] jaw weight in [0, 1], hinge point [3], info) -- see the module docstring."""
    v, ids = f.v, f.ids
    lo, hi = v[f.skin].min(0), v[f.skin].max(0)
    named = landmarks.named
    if "jaw_hinge" in named:
        hinge = np.array([f.mc[0], v[named["jaw_hinge"], 1], v[named["jaw_hinge"], 2]])
    elif "jaw" in mesh.part_names and mesh.part_mask("jaw").any():
        # A labelled jaw turns about its back end (where a mandible's condyle is), at the mouth line.
        jz = v[mesh.part_mask("jaw"), 2]
        hinge = np.array([f.mc[0], float(f.seam_y(np.array([f.mc[0]]))[0]), jz.min() + 0.1 * np.ptp(jz)])
    else:
        # Human skulls: the jaw joint sits in front of the ear, about halfway between the mouth and
        # the eyes in height and a little more than an eye distance behind the lips.
        hinge = np.array([f.mc[0], f.mc[1] + 0.5 * f.em, f.mc[2] - 1.2 * f.io])
        hinge[2] = max(hinge[2], lo[2] + 0.15 * (hi[2] - lo[2]))
    chin_y = v[named["chin"], 1] if "chin" in named else max(f.mc[1] - 0.75 * f.em, lo[1])
    seam = f.seam_y(v[:, 0])
    x_mouth = np.abs(v[:, 0] - f.mc[0]) < 0.6 * f.mw
    lower = (
        f.skin
        & x_mouth
        & (v[:, 1] < seam - 0.15 * f.em)
        & (v[:, 1] > chin_y - 0.1 * f.em)
        & (v[:, 2] > f.mc[2] - 0.5 * f.em)
    )
    lower[ids[[17, 18, 19]]] = True
    if "chin" in named:
        lower[named["chin"]] = True
    static = f.skin & ((v[:, 1] > f.mc[1] + 0.45 * f.em) | (v[:, 2] < hinge[2]) | (v[:, 1] < chin_y - 0.3 * f.em))
    static[ids[[13, 14, 15]]] = True
    if (
        "jaw" in mesh.part_names
    ):  # a labelled jaw (procedural characters): it and the lower lip are the jaw, the head stays
        lower |= mesh.part_mask(*[n for n in ("jaw", "lip_lower") if n in mesh.part_names])
        if "head" in mesh.part_names:
            static |= mesh.part_mask("head")
    static &= ~lower
    d_s, _ = surf.distance(np.nonzero(static)[0])
    d_l, _ = surf.distance(np.nonzero(lower)[0])
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.where(np.isfinite(d_s) & np.isfinite(d_l), d_s / (d_s + d_l), np.nan)
    w = np.where(np.isfinite(d_l) & ~np.isfinite(d_s), 1.0, w)
    w = np.where(np.isfinite(d_s) & ~np.isfinite(d_l), 0.0, w)
    # Parts the surface reaches from neither anchor: teeth, tongue, a separate jaw or mouth bag.
    free = np.isnan(w)
    rigid_parts = 0
    for c in np.unique(comp[free]):
        idx = np.nonzero((comp == c) & free)[0]
        below = seam[idx] - v[idx, 1]
        cen = v[idx].mean(0)
        if not (abs(cen[0] - f.mc[0]) < f.mw and f.mc[1] - 0.6 * f.em < cen[1] < f.mc[1] + 0.3 * f.em):
            w[idx] = 0.0  # not in the mouth (a collar, a necklace): the jaw does not carry it
            continue
        if np.ptp(v[idx, 1]) < 0.35 * f.em:  # small (a tooth): all of it goes one way
            w[idx] = float(below.mean() > 0)
            rigid_parts += 1
        else:
            w[idx] = np.clip(below / (0.2 * f.em) + 0.5, 0.0, 1.0)
    for e in eyeballs.values():
        w[e] = 0.0  # eyeballs stay in the skull
    w = np.clip(w, 0.0, 1.0)
    w[lower] = 1.0
    # Sealed mouth: along the surface the upper and lower inner lip are (almost) as near as in space.
    d_ul, _ = surf.distance([ids[14]])
    gap = float(np.linalg.norm(v[ids[14]] - v[ids[18]]))
    sealed = bool(d_ul[ids[18]] < 2.5 * gap + 1e-6 * mesh.bbox_diagonal())
    info = {
        "mouth": "sealed: the lips stretch apart, no cavity opens" if sealed else "lip seam: the lips part",
        "mouth_sealed": sealed,
        "jaw_rigid_parts": rigid_parts,
    }
    return w, hinge, info


def _smooth_on(surf: Surface, idx: np.ndarray, w: np.ndarray, iterations: int = 8) -> np.ndarray:
    """``w`` [N] with its values on vertices ``idx`` averaged over their mesh neighbours within ``idx``."""
    nodes = np.unique(surf.node[idx])
    sub = surf.graph[nodes][:, nodes]
    sub = ((sub + sub.T) > 0).astype(np.float64)
    deg = np.asarray(sub.sum(1)).ravel()
    vals = np.zeros(len(nodes))
    pos = np.searchsorted(nodes, surf.node[idx])
    np.maximum.at(vals, pos, w[idx])
    for _ in range(iterations):
        vals = np.where(deg > 0, 0.5 * vals + 0.5 * (sub @ vals) / np.maximum(deg, 1), vals)
    out = w.copy()
    out[idx] = vals[pos]
    return out


# A surface seen in a lid opening is an eyeball the lids turn about when it fits a ball of at most this
# radius, in eye widths (corner to corner): a human eyeball is about 0.4 eye widths in radius, the face it
# sits in about 2 (a head is some four eye widths across). In between, on a log scale.
ROUND_EYE_MAX_RADIUS = 1.0


def _inside_polygon(p: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """[P] bool: points p [P, 2] inside the closed polygon [K, 2] (even-odd rule)."""
    inside = np.zeros(len(p), bool)
    for (x0, y0), (x1, y1) in zip(poly, np.roll(poly, -1, axis=0)):
        crosses = (y0 > p[:, 1]) != (y1 > p[:, 1])
        with np.errstate(divide="ignore", invalid="ignore"):
            x = x0 + (p[:, 1] - y0) * (x1 - x0) / (y1 - y0)
        inside ^= crosses & (p[:, 0] < x)
    return inside


def _eye_is_round(
    v: np.ndarray, skin: np.ndarray, pts: np.ndarray, we: float, ball: np.ndarray | None
) -> tuple[bool, dict]:
    """Whether the lids close over a ball (and turn about it) or over a flat eye (and slide), from geometry.

    A sphere-shaped eyeball part (``find_eyeballs``: a sphere fit within 8 % of its radius, or a part
    labelled as an eye) is round. Without one, the skin (``skin`` [N] bool) seen in the lid opening decides:
    a sphere is fitted to the six lid points and every skin vertex inside their outline (seen across the
    plane of the lid points, within half an eye width of it). An eye sculpted into the skin bulges towards
    the viewer like a ball: the fitted centre lies behind that plane and the radius is eye-sized
    (ROUND_EYE_MAX_RADIUS). An eye painted on the skin gives the face's own curvature (a radius of several
    eye widths), a plane, or a hollow (a socket: the centre in front of the lids); a hole in the skin has
    nothing in it. Then there is no ball to turn about (turning about an invented one swings the lid skin
    out of the face) and the lids slide. Other parts in the opening do not count: a flat iris disc or a
    lash card floating in front of a painted eye would make a dome of it; they lie on the skin and move
    with it (``_attachments``).
    """
    if ball is not None and len(ball) >= 4:
        return True, {"eye_surface": "eyeball part"}
    c = pts.mean(0)
    _, _, vt = np.linalg.svd(pts - c)
    normal = vt[2] if vt[2, 2] >= 0 else -vt[2]  # the lid points' plane, facing the viewer (+Z)
    q = v - c
    depth = q @ normal
    in_plane = np.stack([q @ vt[0], q @ vt[1]], axis=1)
    outline = np.stack([(pts - c) @ vt[0], (pts - c) @ vt[1]], axis=1)  # 36-41 go round the eye in order
    seen = skin & _inside_polygon(in_plane, outline) & (np.abs(depth) < 0.5 * we)
    if not seen.any():
        return False, {"eye_surface": "empty opening"}
    centre, radius, _ = fit_sphere(np.concatenate([pts, v[seen]]))
    behind = float((centre - c) @ normal) < 0
    round_eye = bool(behind and radius <= ROUND_EYE_MAX_RADIUS * we)
    info = {
        "eye_surface": "round" if round_eye else "flat",
        "eye_surface_radius_eye_widths": round(float(radius / we), 3),
        "eye_surface_centre": "behind the lids" if behind else "in front of the lids",
    }
    return round_eye, info


# Over a round eye closed lids meet at 0.2 of the opening's height (angle about the ball) from the lower lid:
# a human lower lid moves little (facecap's artist blink; 0.35 before it was measured there).
LID_MEET_ROUND = 0.2


def lid_meet_line(round_eye: bool, r_upper: float, r_lower: float) -> float:
    """Where the closed lids meet, 0 = at the lower lid, 1 = at the upper lid.

    Round eye: LID_MEET_ROUND, the human lid over its eyeball. A flat eye (painted, a disc, a socket) has no
    ball and no anatomy to follow: each lid gives way in proportion to the skin that moves with it, so the
    two are stretched alike: travel_upper / r_upper = travel_lower / r_lower, i.e. r_lower / (r_upper + r_lower)
    of the height (0.4 with the lids' falloff radii). ``r_upper`` / ``r_lower``: those radii, any unit.
    """
    if round_eye:
        return LID_MEET_ROUND
    return r_lower / (r_upper + r_lower)


def _lids(
    f: _Face,
    surf: Surface,
    side: str,
    ball: np.ndarray | None,
    config: AutoRigConfig,
    attached: tuple[np.ndarray, np.ndarray] | None = None,
    comp: np.ndarray | None = None,
) -> dict:
    """Lid deformer of one eye: ``move(upper, lower, clamp)`` -> [N, 3] offsets (upper 1 = to the meeting line).

    Round eyes (see ``_eye_is_round``): lid vertices turn about the eyeball's centre around the corner-to-corner
    axis, by angle. Flat eyes: they slide along the eye's up direction (in the face's plane, across that
    axis), by height: the opening squashes onto the meeting line. The weights are the same for both.

    A lid shell (``comp`` [N] welded component ids given, and the eye's six points on a component of their own,
    not the mouth's, within two eye widths of the eye: a cartoon lid modelled as a separate part around the eyeball)
    turns as one piece: its weights fall off from the margin over the whole shell, to 0 only at its far side,
    instead of over the skin's anatomical lid height (which bends a shell a third of the way back and leaves the
    rest behind), and its lids meet where a flat eye's do.
    """
    v, pts, pid = f.v, f.P[EYES[side]], f.ids[EYES[side]]
    we = float(np.linalg.norm(pts[0] - pts[3]))
    axis = _unit(pts[3] - pts[0]) if pts[3, 0] > pts[0, 0] else _unit(pts[0] - pts[3])
    upv = _unit(np.array([0, 1.0, 0]) - axis[1] * axis)
    fwd = np.cross(axis, upv)
    round_eye, shape = _eye_is_round(v, f.skin, pts, we, ball)
    if ball is not None and len(ball) >= 4:
        centre, r_ball, _ = fit_sphere(v[ball])
    else:
        # No eyeball part: a ball behind the lid opening, as wide as the opening (round eyes only).
        r_ball = 0.5 * we
        centre = pts.mean(0) - np.array([0, 0, 0.6 * r_ball])
    origin = pts.mean(0)

    def elevation(p):
        """Where a point is between the lids: its angle about the ball (round) or its height (flat)."""
        if round_eye:
            q = np.asarray(p) - centre
            return np.arctan2(q @ upv, q @ fwd)
        return (np.asarray(p) - origin) @ upv

    th_u, th_l = float(elevation(pts[[1, 2]]).mean()), float(elevation(pts[[4, 5]]).mean())
    if th_u <= th_l:
        raise UserError(
            f"landmarks: the {side} eye's upper lid points (37-38 / 43-44) are not above its lower lid points"
        )
    # Anatomy: the moving upper lid spans lash line to crease (about a third of the eye's width), the lower less.
    r_u, r_l = 0.45 * we * config.falloff, 0.3 * we * config.falloff
    meet = lid_meet_line(round_eye, r_u, r_l) if config.lid_meet is None else config.lid_meet
    eye_h = float(np.mean(np.linalg.norm(pts[[1, 2]] - pts[[5, 4]], axis=1)))

    def margin(order):
        nodes = np.concatenate(
            [surf.path(pid[a], pid[b])[:-1] for a, b in zip(order[:-1], order[1:])] + [[surf.node[pid[order[-1]]]]]
        )
        return surf.first[nodes]

    up_seeds, lo_seeds = margin([0, 1, 2, 3]), margin([0, 5, 4, 3])
    shell = comp is not None and len(np.unique(comp[pid])) == 1 and comp[pid[0]] not in comp[f.ids[12:20]]
    if shell:  # and it stays around the eye (a head whose lips are a part of their own is no shell)
        own = comp == comp[pid[0]]  # [N] the shell's vertices
        shell = bool(np.linalg.norm(v[own] - pts.mean(0), axis=1).max() < 2.0 * we)
    limit = np.inf if shell else 2 * r_u  # a shell is its own component: no distance leaves it
    d_u, src_u = surf.distance(up_seeds, limit=limit)
    d_l, src_l = surf.distance(lo_seeds, limit=limit)
    if shell:
        # A shell is no human lid over its ball (whose lower lid hardly moves): its lids meet where a flat eye's
        # do, each giving way in proportion to its lid height (lid_meet_line: 0.4). Its weights fall off over the
        # whole shell, margin to far side.
        meet = lid_meet_line(False, r_u, r_l) if config.lid_meet is None else config.lid_meet
        reach = np.minimum(d_u, d_l)[own]  # the same welded component: finite but kept safe
        r_u = r_l = float(np.max(reach[np.isfinite(reach)]))
    with np.errstate(invalid="ignore"):  # inf - inf where neither margin is in reach: no weight anyway
        # Which lid a vertex follows: a band of 0.3 eye heights about the line halfway between the margins, narrowed
        # near the corners, where the margins come closer than that, so that a margin vertex always follows its own
        # lid all the way (a fixed band left both lids' vertices half-weighted near the corners: open triangles
        # there in a closed eye, seen on the demo fox).
        band = np.minimum(0.3 * eye_h, d_l + d_u)
        gate_u = np.clip((d_l - d_u) / band, 0.0, 1.0)
        gate_l = np.clip((d_u - d_l) / band, 0.0, 1.0)
    w_u = (src_u >= 0) * _falloff(d_u / r_u) * np.nan_to_num(gate_u, nan=1.0)
    w_l = (src_l >= 0) * _falloff(d_l / r_l) * np.nan_to_num(gate_l, nan=1.0)
    w_u = np.where(np.isfinite(d_u), w_u, 0.0) * f.skin
    w_l = np.where(np.isfinite(d_l), w_l, 0.0) * f.skin
    if attached is not None and len(attached[0]):  # parts on the lid (lashes) turn with it
        idx, nn = attached
        w_u[idx], w_l[idx], src_u[idx], src_l[idx] = w_u[nn], w_l[nn], src_u[nn], src_l[nn]
        # Smoothed along the part itself, so a lash line spanning both lids bends at the corners
        # instead of splitting where its nearest skin vertex changes lid.
        w_u, w_l = _smooth_on(surf, idx, w_u), _smooth_on(surf, idx, w_l)
    th = elevation(v)
    # Each vertex turns (slides) as far as the margin point nearest to it must to reach the meeting
    # line, so the whole margin (not only its mean) closes on a lid of any shape. The line runs from corner to
    # corner at ``meet`` of the way between the two margins at each place along the eye: one height for the whole
    # eye left the margins short of each other near the corners of a slanted or almond eye, and the corners,
    # where the margins already touch, would have moved onto it; on this line they stay put, so no taper is needed.
    th_node = elevation(v[surf.first])
    a_node = (v[surf.first] - origin) @ axis
    n_u, n_l = surf.node[up_seeds], surf.node[lo_seeds]
    # The line is drawn through the margins, which follow a modelled opening. On an eye painted on the skin they
    # are shortest paths of mesh edges that can wander off the painted edge (a third of the eye's height on a
    # synthetic head with a polar grid); a line through the six points alone is steadier there but loses where the
    # eye is modelled (autorig bench, blink cosine: facecap .74 -> .64, vipe .81 -> .77, fox .94 -> .87; turtle
    # .935 -> .939).
    lids = (a_node[n_u], th_node[n_u], a_node[n_l], th_node[n_l])
    meet_node = _meeting_line(a_node, *lids, meet)
    s_u, s_l = np.maximum(src_u, 0), np.maximum(src_l, 0)
    span_u = np.where(src_u >= 0, np.maximum(th_node[s_u] - meet_node[s_u], 0.0), 0.0)
    span_l = np.where(src_l >= 0, np.maximum(meet_node[s_l] - th_node[s_l], 0.0), 0.0)
    # A closing vertex stops at the line where it is (the margin point it follows may be elsewhere along the eye).
    m_v = meet_node[surf.node]
    r_min = r_ball * 1.01

    def move(upper: float, lower: float, clamp: bool) -> np.ndarray:
        sel = (w_u > 0) | (w_l > 0)
        new = th - w_u * upper * span_u + w_l * lower * span_l
        if clamp:  # a closing lid stops at the meeting line
            new = np.where((w_u >= w_l) & (th >= m_v), np.maximum(new, np.minimum(th, m_v)), new)
            new = np.where((w_l > w_u) & (th <= m_v), np.minimum(new, np.maximum(th, m_v)), new)
        off = np.zeros_like(v)
        idx = np.nonzero(sel)[0]
        if not round_eye:  # flat: a slide across the corner-to-corner axis, in the face's plane
            off[idx] = (new[idx] - th[idx])[:, None] * upv[None]
            return off
        moved = rotate_about(v[idx], centre, axis, th[idx] - new[idx])
        # A turn about the ball's centre keeps every distance to it; lid vertices that already touch
        # the ball (numerically inside it) are put on its surface so none end up within it.
        rad = np.linalg.norm(moved - centre, axis=1)
        inside = rad < r_min
        moved[inside] = centre + (moved[inside] - centre) * (r_min / np.maximum(rad[inside], 1e-12))[:, None]
        off[idx] = moved - v[idx]
        return off

    info = {"lids": "turn about the eyeball" if round_eye else "slide (flat eye)", **shape, "lid_meet": round(meet, 3)}
    info["lid_shell"] = bool(shell)
    if round_eye:
        info.update(
            centre=[round(float(x), 5) for x in centre],
            radius=round(float(r_ball), 5),
            closing_deg=round(float(np.degrees(th_u - th_l)), 2),
        )
    else:
        info["closing_eye_widths"] = round(float((th_u - th_l) / we), 3)
    info["eyeball_part"] = ball is not None and len(ball) >= 4
    return {"move": move, "w_upper": w_u, "info": info}


def _meeting_line(
    a: np.ndarray, a_upper: np.ndarray, th_upper: np.ndarray, a_lower: np.ndarray, th_lower: np.ndarray, meet: float
) -> np.ndarray:
    """Where closed lids meet, at places a [K] along the eye's corner-to-corner axis: [K] elevations.

    a_upper, th_upper [U] / a_lower, th_lower [L]: the upper / lower margin's points, their places along the axis
    and their elevations. The line is L(a) + meet * (U(a) - L(a)), U and L the margins interpolated along the
    axis, so an upper and a lower margin point at the same place close onto the same height, the corners (where
    the margins already meet) staying where they are. Each margin counts by its convex hull (an opening is
    convex): a stretch that dips into the opening (a path of edges over a painted eye, a margin going round a
    round opening's side) does not pull the line with it (autorig bench, blink cosine with / without the hull:
    facecap .737 / .726, vipe .805 / .798, the others within .001).
    """
    a_u, th_u = _hull(a_upper, th_upper, upper=True)
    a_l, th_l = _hull(a_lower, th_lower, upper=False)
    lower = np.interp(a, a_l, th_l)
    return lower + meet * (np.interp(a, a_u, th_u) - lower)


def _hull(x: np.ndarray, y: np.ndarray, upper: bool) -> tuple[np.ndarray, np.ndarray]:
    """The upper (or lower) convex hull of points (x, y) [K]: its vertices, x ascending."""
    sign = 1.0 if upper else -1.0
    out: list[tuple[float, float]] = []
    for px, py in sorted(zip(x.tolist(), (sign * y).tolist())):
        # monotone chain: the last vertex goes while it lies on or below the chord from the one before to this point
        while (
            len(out) >= 2
            and (out[-1][0] - out[-2][0]) * (py - out[-2][1]) - (out[-1][1] - out[-2][1]) * (px - out[-2][0]) >= 0
        ):
            out.pop()
        out.append((px, py))
    hx, hy = np.array(out).T
    return hx, sign * hy


def _brows(
    f: _Face, surf: Surface, landmarks: FaceLandmarks, mesh: Mesh, config: AutoRigConfig, upper_lid: np.ndarray
) -> dict:
    """browInnerUp, browOuterUp*, browDown*: labelled brow parts move whole; else skin above each eye."""
    v, named = f.v, landmarks.named
    up = np.array([0, 1.0, 0])
    amount = config.brow * f.io
    lid_still = 1.0 - np.clip(upper_lid, 0, 1)
    out: dict[str, np.ndarray] = {}
    inner_seeds = []
    for side in ("left", "right"):
        cap = side.capitalize()
        sgn = 1.0 if side == "left" else -1.0
        pts = f.P[EYES[side]]
        we = float(np.linalg.norm(pts[0] - pts[3]))
        eye = pts.mean(0)
        top = pts[[1, 2], 1].max()
        if "brow" in mesh.part_names:  # procedural characters: the brow is its own part
            mask = mesh.part_mask("brow") & (np.sign(v[:, 0] - f.mc[0]) == sgn)
            if mask.any():
                bx = v[mask, 0]
                inner_w = (
                    np.clip((bx.max() - bx) / max(np.ptp(bx), 1e-9), 0, 1)
                    if sgn > 0
                    else np.clip((bx - bx.min()) / max(np.ptp(bx), 1e-9), 0, 1)
                )
                ow = np.zeros(len(v))
                ow[mask] = 1 - inner_w
                iw = np.zeros(len(v))
                iw[mask] = inner_w
                inner_seeds.append(iw)
                out[f"browOuterUp{cap}"] = ow[:, None] * up * amount
                dw = np.zeros(len(v))
                dw[mask] = 1.0
                out[f"browDown{cap}"] = dw[:, None] * _unit(-0.9 * up + np.array([-0.4 * sgn, 0, 0])) * amount
                continue
        get = lambda key, x, y: named[key] if key in named else f.front_vertex(x, y, 0.2 * we)  # noqa: E731
        mid = get(f"brow_{side}", eye[0], top + 0.45 * we)
        inner = get(f"brow_inner_{side}", eye[0] - sgn * 0.4 * we, top + 0.4 * we)
        outer = get(f"brow_outer_{side}", eye[0] + sgn * 0.45 * we, top + 0.35 * we)
        r = 0.7 * we * config.falloff
        d_o, _ = surf.distance([outer], limit=r)
        out[f"browOuterUp{cap}"] = _push(f, d_o, r, up, amount) * lid_still[:, None]
        d_d, _ = surf.distance([mid, inner], limit=1.1 * r)
        out[f"browDown{cap}"] = (
            _push(f, d_d, 1.1 * r, _unit(-0.9 * up + np.array([-0.4 * sgn, 0, 0])), amount) * lid_still[:, None]
        )
        d_i, _ = surf.distance([inner], limit=r)
        inner_seeds.append(_falloff(d_i / r) * f.skin * lid_still)
    if inner_seeds:
        w = np.maximum(inner_seeds[0], inner_seeds[1]) if len(inner_seeds) == 2 else inner_seeds[0]
        out["browInnerUp"] = w[:, None] * (f.tangent(up) if "brow" not in mesh.part_names else up[None]) * amount
    return out
