"""Character landmarks (paper §3.3): 6 per eye + 8 on the mouth, as vertices of the character.

The paper segments the left eye, right eye and mouth on a frontal render (Grounding-DINO + SAM),
picks points on the region contours at predefined angles, and lifts them to 3D with shadow
mapping (the visible surface point whose projection is nearest). Here:

1. Regions, by one of three backends:
   - ``parts``: the character's own part labels (procedural characters): the visible eyeball
     (eye_left / eye_right) and the mouth (mouth_interior, teeth, tongue, else the lips).
   - ``motion``: what moves under the character's own blink / mouth-open shapes (morph targets of
     the mesh, or the blendshape model's named shapes): an eye is where the frontal image changes
     when that eye closes (the part of the eyeball the lids cover); the mouth is the opening that
     appears when the mouth opens, segmented in the open pose.
   - ``grounding-sam``: text-prompted boxes (Grounding-DINO) refined to masks (SAM) from local
     checkpoints (grounding_sam.py).
2. Contour points at fixed angles: for a region with centroid c and half extents (a, b), the
   point at angle theta is the last region pixel on the ray c + t (a cos theta, -b sin theta).
   Angles are measured in this ellipse-normalised frame (image x right, y up), so 60 degrees lands
   a third of the way in from the corner on any eye shape, as in the 68-point scheme:
   eyes [180, 120, 60, 0, -60, -120] (corner, two upper-lid points, corner, two lower-lid points,
   image left to right along the top), mouth every 45 degrees from the left corner.
3. Lifting: the depth test of the mesh renderer gives the vertices visible from the frontal
   camera (the paper's shadow map); each contour point takes the nearest visible vertex whose
   projection lies *outside* the region (eyes: the lid margin, not the eyeball; the open mouth: the
   lip edge) or *inside* it (a closed mouth segmented as lips: the lip itself).

Order of the 20 (face_tracking.LANDMARKS_68): 36-41 on the image-left eye (the character's right,
-X), 42-47 on the image-right eye (the character's left, +X), 60-67 on the mouth.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from t2bs.errors import UserError
from t2bs.geometry.camera import Camera, frontal_camera
from t2bs.geometry.mesh import Mesh
from t2bs.face.face_tracking import LANDMARKS_68
from t2bs.project import Project, read_json, write_image, write_json

EYE_ANGLES = [180.0, 120.0, 60.0, 0.0, -60.0, -120.0]  # degrees, ellipse-normalised, y up
MOUTH_ANGLES = [180.0, 135.0, 90.0, 45.0, 0.0, -45.0, -90.0, -135.0]
REGIONS = ["right_eye", "left_eye", "mouth"]  # in landmark order: image-left eye, image-right eye, mouth
BACKENDS = ["auto", "parts", "motion", "grounding-sam"]
LANDMARK_VERSION = 1

# Shape-name patterns for the motion backend (mesh morph targets or the model's named shapes).
SHAPE_PATTERNS = {
    "blink_left": r"^(blink_?l(eft)?|eye_?blink_?l(eft)?|eye_?left_?clos\w*|eye_?clos\w*_?l(eft)?|wink_?l(eft)?)$",
    "blink_right": r"^(blink_?r(ight)?|eye_?blink_?r(ight)?|eye_?right_?clos\w*|eye_?clos\w*_?r(ight)?|wink_?r(ight)?)$",
    "blink": r"^(blink|eyes?_?clos\w*|eye_?blink)$",
    "mouth_open": r"^(jaw_?open|mouth_?open|open_?mouth|a|aa|scream)$",
    "smile": r"^(smile|mouth_?smile|joy|happy)$",
    "smile_left": r"^(smile_?l(eft)?|mouth_?smile_?l(eft)?)$",
    "smile_right": r"^(smile_?r(ight)?|mouth_?smile_?r(ight)?)$",
}


@dataclass
class Region:
    mask: np.ndarray  # [H, W] bool in the image it was segmented in
    vertices: np.ndarray  # [N, 3] mesh pose the image shows (neutral, or the open-mouth pose)
    lift: str = "outside"  # "outside": nearest visible vertex projecting outside the mask; "inside": inside it
    eyeball: np.ndarray | None = None  # [N] bool vertices of the eyeball behind this eye (eye regions only)
    # Part-label refinements (parts backend): vertices each contour point may be lifted to, and for
    # the mouth the image masks of the upper / lower lip, whose meeting line is the inner contour.
    lift_vertices: list | None = None  # per contour point: [N] bool eligible vertices (None: any)
    lips: tuple[np.ndarray, np.ndarray] | None = None  # ([H, W] upper-lip pixels, [H, W] lower-lip pixels)


@dataclass
class Landmarks:
    vertex_ids: np.ndarray  # [20] int vertex index of each landmark (order of face_tracking.LANDMARKS_68)
    points2d: np.ndarray  # [20, 2] contour points in the frontal image (pixels)
    positions: np.ndarray  # [20, 3] neutral positions of the vertices
    camera: Camera  # the frontal camera the points live in
    backend: str  # which backend produced them ("override" for a user file)
    eyeballs: dict = field(default_factory=dict)  # "left"/"right" -> [M] int eyeball vertex ids (eye terms)
    regions: dict = field(default_factory=dict)  # region -> {"centre", "half_width", "half_height"} pixels

    def to_dict(self) -> dict:
        return {
            "version": LANDMARK_VERSION,
            "backend": self.backend,
            "landmarks_68": LANDMARKS_68,
            "vertex_ids": self.vertex_ids.tolist(),
            "points2d": np.round(self.points2d, 2).tolist(),
            "positions": np.round(self.positions, 6).tolist(),
            "camera": self.camera.to_dict(),
            "eyeballs": {k: np.asarray(v).tolist() for k, v in self.eyeballs.items()},
            "regions": self.regions,
        }

    @staticmethod
    def from_dict(d: dict, num_vertices: int | None = None) -> "Landmarks":
        ids = np.asarray(d.get("vertex_ids", []), int)
        if ids.shape != (20,):
            raise UserError(f"landmarks need 20 vertex ids (68-scheme 36-47, 60-67), got {ids.size}")
        if num_vertices is not None and (ids.min() < 0 or ids.max() >= num_vertices):
            raise UserError(f"landmark vertex ids must be in 0..{num_vertices - 1}")
        return Landmarks(
            ids,
            np.asarray(d.get("points2d", np.zeros((20, 2))), float),
            np.asarray(d.get("positions", np.zeros((20, 3))), float),
            Camera.from_dict(d["camera"]) if "camera" in d else frontal_camera(512),
            d.get("backend", "override"),
            {k: np.asarray(v, int) for k, v in d.get("eyeballs", {}).items()},
            d.get("regions", {}),
        )


# ----------------------------------------------------------------------------------------------
# Contours and lifting
# ----------------------------------------------------------------------------------------------


def largest_component(mask: np.ndarray) -> np.ndarray:
    """The largest 8-connected component of ``mask`` with its holes filled."""
    from scipy import ndimage

    lab, n = ndimage.label(mask, structure=np.ones((3, 3)))
    if n == 0:
        return mask
    sizes = ndimage.sum(mask, lab, index=np.arange(1, n + 1))
    return ndimage.binary_fill_holes(lab == (1 + int(np.argmax(sizes))))


def contour_points(mask: np.ndarray, angles_deg) -> tuple[np.ndarray, dict]:
    """Points [P, 2] (pixels, x right y down) on the boundary of ``mask`` at ellipse-normalised angles."""
    ys, xs = np.nonzero(mask)
    if len(xs) < 4:
        raise UserError("a landmark region is empty")
    cx, cy = xs.mean(), ys.mean()
    a = max((xs.max() - xs.min() + 1) / 2.0, 1.0)
    b = max((ys.max() - ys.min() + 1) / 2.0, 1.0)
    h, w = mask.shape
    steps = np.linspace(0.0, 3.0, 601)  # along the ray in units of the half extents
    out = []
    for ang in np.radians(angles_deg):
        px = cx + steps * a * np.cos(ang)
        py = cy - steps * b * np.sin(ang)
        ix, iy = np.round(px).astype(int), np.round(py).astype(int)
        ok = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
        inside = np.zeros_like(ok)
        inside[ok] = mask[iy[ok], ix[ok]]
        k = int(np.nonzero(inside)[0].max()) if inside.any() else 0
        out.append([px[k], py[k]])
    return np.asarray(out), {"centre": [float(cx), float(cy)], "half_width": float(a), "half_height": float(b)}


def lift_points(
    points2d: np.ndarray,
    camera: Camera,
    vertices: np.ndarray,
    visible: np.ndarray,
    mask: np.ndarray,
    lift: str = "outside",
    allowed: list | None = None,
) -> np.ndarray:
    """Vertex ids [P]: nearest visible vertex (in the image) to each point, outside/inside ``mask``.

    ``allowed``: per point an [N] bool of the vertices it may land on (e.g. the upper lip for the
    upper inner-lip points); the outside/inside rule is then not applied to that point.
    """
    uv, _ = camera.project(vertices.astype(np.float64))
    h, w = mask.shape
    ix = np.clip(np.round(uv[:, 0]).astype(int), 0, w - 1)
    iy = np.clip(np.round(uv[:, 1]).astype(int), 0, h - 1)
    in_mask = mask[iy, ix]
    eligible = visible & (~in_mask if lift == "outside" else in_mask)
    if not eligible.any():
        eligible = visible
    if not eligible.any():
        raise UserError("no vertex of the character is visible from the frontal camera")
    out = np.zeros(len(points2d), int)
    for k, p in enumerate(points2d):
        el = eligible
        if allowed is not None and allowed[k] is not None and (visible & allowed[k]).any():
            el = visible & allowed[k]
        cand = np.nonzero(el)[0]
        out[k] = cand[np.argmin(np.linalg.norm(uv[cand] - p[None], axis=-1))]
    return out


def inner_lip_points(points2d: np.ndarray, upper: np.ndarray, lower: np.ndarray) -> np.ndarray:
    """Mouth contour points [8, 2] (MOUTH_ANGLES) moved onto the inner lip contour.

    The 68-scheme's 61-63 / 65-67 lie on the inner edges of the lips; with the lips labelled, the
    inner edge in a pixel column is the lowest upper-lip pixel (61-63) or the highest lower-lip pixel
    (65-67). Corners (60, 64) go to the lips' extreme columns, where they meet (on a curved lip
    line that is not at the height of the region's centre). Columns with no lip pixel keep the
    contour point.
    """
    out = points2d.copy()
    w = upper.shape[1]
    lips = upper | lower
    ys, xs = np.nonzero(lips)
    for k, ang in enumerate(MOUTH_ANGLES):
        if ang in (0.0, 180.0):
            if len(xs):
                x = xs.min() if ang == 180.0 else xs.max()
                out[k] = [x, ys[xs == x].mean()]
            continue
        x = int(np.clip(np.round(points2d[k, 0]), 0, w - 1))
        col = upper[:, x] if ang > 0 else lower[:, x]
        rows = np.nonzero(col)[0]
        if len(rows):
            out[k, 1] = rows.max() if ang > 0 else rows.min()
    return out


# ----------------------------------------------------------------------------------------------
# Backends
# ----------------------------------------------------------------------------------------------


def face_parts(mesh: Mesh, face_id: np.ndarray) -> np.ndarray:
    """[H, W] part id of the surface seen in each pixel (-1 background / unlabelled)."""
    out = np.full(face_id.shape, -1, np.int32)
    if mesh.part_ids is None:
        return out
    fg = face_id >= 0
    out[fg] = mesh.part_ids[mesh.faces[face_id[fg], 0]]
    return out


def has_part_labels(mesh: Mesh) -> bool:
    names = set(mesh.part_names)
    return {"eye_left", "eye_right"} <= names and bool(names & {"lip_upper", "lip_lower", "mouth_interior", "teeth"})


def regions_from_parts(mesh: Mesh, camera: Camera, renderer) -> dict[str, Region]:
    """Eyes: the visible eyeball of each eye part; mouth: interior/teeth/tongue when visible, else the lips."""
    if not has_part_labels(mesh):
        raise UserError(
            "character has no eye/mouth part labels (eye_left, eye_right, lip_*/mouth_interior); "
            "use --backend motion or grounding-sam, or --override JSON"
        )
    res = renderer.render(mesh, camera, shading="unlit")
    parts = face_parts(mesh, res.face_id)
    ids = {n: i for i, n in enumerate(mesh.part_names)}

    def pix(*names):
        sel = [ids[n] for n in names if n in ids]
        return np.isin(parts, sel) if sel else np.zeros(parts.shape, bool)

    def verts(*names):
        present = [n for n in names if n in ids]
        return mesh.part_mask(*present) if present else None

    regions: dict[str, Region] = {}
    for region, part, side in (("right_eye", "eye_right", "right"), ("left_eye", "eye_left", "left")):
        m = pix(part)
        if m.sum() < 4:
            raise UserError(f"the character's {part} is not visible from the front; use --override JSON")
        # The six eye points belong on the lid margin around the visible eyeball (what a blink moves),
        # not on the eyeball's rim or the skin behind the lid: lift them to the eyelid part when labelled.
        lid = verts(f"eyelid_{side}")
        regions[region] = Region(
            largest_component(m),
            mesh.vertices,
            "outside",
            mesh.part_mask(part),
            lift_vertices=None if lid is None else [lid] * len(EYE_ANGLES),
        )
    upper, lower = pix("lip_upper"), pix("lip_lower")
    inner = pix("mouth_interior", "teeth", "tongue")
    if upper.sum() >= 4 and lower.sum() >= 4:
        # Lips labelled and seen: the mouth is lips + whatever shows between them; the points go on
        # the inner lip contour (upper points on the upper lip, lower on the lower lip, corners on
        # either), so mouth-open moves exactly the lower three and a smile the corners. A tiny
        # patch of interior or teeth (fangs over a closed mouth) is not the mouth opening.
        both_lips = verts("lip_upper", "lip_lower")
        allowed = [
            both_lips if a in (0.0, 180.0) else verts("lip_upper" if a > 0 else "lip_lower") for a in MOUTH_ANGLES
        ]
        regions["mouth"] = Region(
            largest_component(upper | lower | inner),
            mesh.vertices,
            "inside",
            lift_vertices=allowed,
            lips=(upper, lower),
        )
    elif inner.sum() >= 12:
        regions["mouth"] = Region(largest_component(inner), mesh.vertices, "outside")
    else:
        lips = upper | lower
        if lips.sum() < 4:
            raise UserError(
                "the character's mouth (lips or interior) is not visible from the front; use --override JSON"
            )
        regions["mouth"] = Region(largest_component(lips), mesh.vertices, "inside")
    return regions


def find_shapes(names: list[str]) -> dict[str, str]:
    """Role (blink_left, blink_right, blink, mouth_open) -> the first shape name matching it."""
    out: dict[str, str] = {}
    for role, pat in SHAPE_PATTERNS.items():
        for n in names:
            if re.match(pat, n, flags=re.IGNORECASE):
                out.setdefault(role, n)
    return out


def motion_shapes(mesh: Mesh, model=None) -> dict[str, np.ndarray]:
    """Role -> offsets [N, 3] from the mesh's morph targets, else the blendshape model's named shapes."""
    shapes: dict[str, np.ndarray] = {}
    for role, name in find_shapes(list(mesh.morph_targets)).items():
        shapes[role] = mesh.morph_targets[name].astype(np.float64)
    if model is not None and getattr(model, "semantic_names", None):
        offs = model.semantic_offsets()
        for role, name in find_shapes(list(model.semantic_names)).items():
            shapes.setdefault(role, offs[model.semantic_names.index(name)].astype(np.float64))
    if "smile" not in shapes and {"smile_left", "smile_right"} <= set(shapes):
        shapes["smile"] = shapes["smile_left"] + shapes["smile_right"]
    return shapes


def _hidden_faces(a, b, ratio: float = 0.25) -> np.ndarray:
    """[H, W] pixels of render ``a`` showing a triangle that render ``b`` (mostly) hides.

    Counted in pixels per triangle rather than seen / not seen, so that a closed eye's slit or a
    closed mouth's crease, which still shows slivers of the eyeball or the mouth interior, does
    not keep those triangles out of the region.
    """
    n = max(int(a.face_id.max()), int(b.face_id.max())) + 1
    ca = np.bincount(a.face_id[a.face_id >= 0], minlength=n)
    cb = np.bincount(b.face_id[b.face_id >= 0], minlength=n)
    hidden = cb < ratio * ca  # [F]
    return (a.face_id >= 0) & hidden[np.maximum(a.face_id, 0)]


def regions_from_motion(mesh: Mesh, camera: Camera, renderer, shapes: dict[str, np.ndarray]) -> dict[str, Region]:
    """Eyes: pixels that change when that eye blinks; mouth: the opening that appears when it opens."""
    from scipy import ndimage

    if "mouth_open" not in shapes or not ({"blink_left", "blink_right"} <= set(shapes) or "blink" in shapes):
        raise UserError(
            "character has no landmarks: no part labels and no blink / mouth-open shapes "
            "(morph targets or named blendshapes); use --backend grounding-sam or --override JSON"
        )
    v0 = mesh.vertices.astype(np.float64)
    neutral = renderer.render(mesh, camera, shading="lambert")
    h, w = neutral.mask.shape
    regions: dict[str, Region] = {}

    def scaled(offsets):
        return (v0 + offsets).astype(np.float32)

    def eye_region(offsets, side: str | None):
        # The eye opening: surface seen at rest that the closing lids hide (the visible eyeball).
        ch = _hidden_faces(neutral, renderer.render(mesh, camera, vertices=scaled(offsets)))
        ch = ndimage.binary_opening(ch, iterations=1)
        if side is not None:  # one shape closes both eyes: keep the image half of this eye
            half = np.zeros_like(ch)
            if side == "left":
                half[:, w // 2 :] = True
            else:
                half[:, : w // 2] = True
            ch &= half
        return largest_component(ch)

    for region, role, side in (("right_eye", "blink_right", "right"), ("left_eye", "blink_left", "left")):
        if role in shapes:
            m = eye_region(shapes[role], None)
        else:
            m = eye_region(shapes["blink"], side)
        if m.sum() < 4:
            raise UserError(f"the {role} shape changes nothing visible from the front; use --override JSON")
        regions[region] = Region(
            m, mesh.vertices, "outside", _eyeball(mesh, camera, renderer, m, shapes.get(role, shapes.get("blink")))
        )
    opened = scaled(shapes["mouth_open"])
    res_open = renderer.render(mesh, camera, vertices=opened)
    # The opening: pixels of the open pose showing surface hidden at rest (the mouth interior,
    # teeth, tongue revealed between the lips).
    hole = _hidden_faces(res_open, neutral)
    hole = ndimage.binary_opening(hole, iterations=1)
    moving = _projected_motion(camera, v0, shapes["mouth_open"], (h, w))
    hole &= moving  # only where the mouth-open shape actually moves the surface
    m = largest_component(hole)
    if m.sum() < 4:
        raise UserError("the mouth-open shape reveals no opening from the front; use --override JSON")
    regions["mouth"] = Region(m, opened, "outside")
    return regions


def _projected_motion(camera: Camera, v0: np.ndarray, offsets: np.ndarray, shape) -> np.ndarray:
    """[H, W] bool: dilated image footprint of the vertices the shape moves noticeably."""
    from scipy import ndimage

    mag = np.linalg.norm(offsets, axis=1)
    sel = mag > 0.05 * mag.max()
    uv, _ = camera.project(v0[sel])
    h, w = shape
    out = np.zeros(shape, bool)
    ix, iy = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
    ok = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
    out[iy[ok], ix[ok]] = True
    return ndimage.binary_dilation(out, iterations=max(2, h // 64))


def _smile_corners(mesh: Mesh, camera: Camera, renderer, mouth_ids: np.ndarray, smile: np.ndarray) -> np.ndarray:
    """Mouth corners (60, 64) moved to the visible vertex the smile shape moves most on each side.

    The opening a mouth-open shape reveals often stops short of where the lips meet (a cartoon
    mouth line runs on past the part that opens); the smile shape pulls hardest exactly there.
    Searched in a band around the mouth's height, left and right of its centre.
    """
    vis = renderer.vertex_visibility(mesh, camera)
    v = mesh.vertices
    mag = np.linalg.norm(smile, axis=1) * vis
    mouth = v[mouth_ids]
    cx, cy = mouth[:, 0].mean(), mouth[:, 1].mean()
    half_w = max(abs(mouth[4, 0] - mouth[0, 0]) / 2, 1e-6)
    band = np.abs(v[:, 1] - cy) < 0.6 * half_w
    out = mouth_ids.copy()
    for pos, side in ((0, -1.0), (4, 1.0)):
        cand = band & (side * (v[:, 0] - cx) > 0.5 * half_w)
        if cand.any() and mag[cand].max() > 0:
            out[pos] = int(np.argmax(np.where(cand, mag, -1.0)))
    return out


def _eyeball(mesh: Mesh, camera: Camera, renderer, mask: np.ndarray, blink: np.ndarray | None) -> np.ndarray:
    """[N] bool: visible vertices inside the eye region that the blink shape leaves (nearly) still."""
    vis = renderer.vertex_visibility(mesh, camera)
    uv, _ = camera.project(mesh.vertices.astype(np.float64))
    h, w = mask.shape
    ix, iy = np.clip(np.round(uv[:, 0]).astype(int), 0, w - 1), np.clip(np.round(uv[:, 1]).astype(int), 0, h - 1)
    inside = vis & mask[iy, ix]
    if blink is not None:
        mag = np.linalg.norm(blink, axis=1)
        inside &= mag < 0.2 * max(mag.max(), 1e-12)
    return inside


def regions_from_image(mesh: Mesh, camera: Camera, renderer, segmenter) -> dict[str, Region]:
    """Grounding-DINO + SAM on the frontal render (see grounding_sam.py)."""
    rgb = (renderer.render(mesh, camera, shading="lambert").rgb * 255).astype(np.uint8)
    masks = segmenter(rgb)  # {"left_eye", "right_eye", "mouth"} -> [H, W] bool (image-left eye = right_eye)
    regions = {}
    for name in REGIONS:
        m = largest_component(np.asarray(masks[name], bool))
        if m.sum() < 4:
            raise UserError(
                f"Grounding-DINO + SAM found no {name.replace('_', ' ')} on the frontal render; use --override JSON"
            )
        eyeball = None
        if name != "mouth":
            eyeball = _eyeball(mesh, camera, renderer, m, None)
        regions[name] = Region(m, mesh.vertices, "outside" if name != "mouth" else "inside", eyeball)
    return regions


# ----------------------------------------------------------------------------------------------
# Driver
# ----------------------------------------------------------------------------------------------


def choose_backend(mesh: Mesh, model=None) -> str:
    if has_part_labels(mesh):
        return "parts"
    shapes = motion_shapes(mesh, model)
    if "mouth_open" in shapes and ({"blink_left", "blink_right"} <= set(shapes) or "blink" in shapes):
        return "motion"
    raise UserError(
        "character has no landmarks: no eye/mouth part labels and no blink / mouth-open shapes; "
        "run `t2bs landmarks DIR --backend grounding-sam` (needs local checkpoints) or pass --override JSON"
    )


def detect_landmarks(
    mesh: Mesh, backend: str = "auto", model=None, size: int = 512, renderer=None, segmenter=None
) -> tuple[Landmarks, dict[str, Region]]:
    """Character mesh (canonical frame) -> 20 landmarks and the regions they came from."""
    from t2bs.render.mesh_renderer import MeshRenderer

    if backend not in BACKENDS:
        raise UserError(f"unknown landmark backend {backend!r}; use one of {BACKENDS}")
    if backend == "auto":
        backend = choose_backend(mesh, model)
    own = renderer is None
    renderer = renderer or MeshRenderer()
    try:
        camera = frontal_camera(size)
        if backend == "parts":
            regions = regions_from_parts(mesh, camera, renderer)
        elif backend == "motion":
            regions = regions_from_motion(mesh, camera, renderer, motion_shapes(mesh, model))
        else:
            if segmenter is None:
                from t2bs.face.grounding_sam import GroundingSamSegmenter

                segmenter = GroundingSamSegmenter.from_pretrained()
            regions = regions_from_image(mesh, camera, renderer, segmenter)
        ids, pts, info = [], [], {}
        for name in REGIONS:
            reg = regions[name]
            angles = MOUTH_ANGLES if name == "mouth" else EYE_ANGLES
            p2, info[name] = contour_points(reg.mask, angles)
            if reg.lips is not None:
                p2 = inner_lip_points(p2, reg.lips[0] & reg.mask, reg.lips[1] & reg.mask)
            vis = renderer.vertex_visibility(mesh, camera, vertices=reg.vertices)
            ids.append(lift_points(p2, camera, reg.vertices, vis, reg.mask, reg.lift, reg.lift_vertices))
            pts.append(p2)
        eyeballs = {
            side: np.nonzero(regions[f"{side}_eye"].eyeball)[0]
            for side in ("left", "right")
            if regions[f"{side}_eye"].eyeball is not None
        }
        info["mouth"]["width_world"] = float(abs(mesh.vertices[ids[2][4], 0] - mesh.vertices[ids[2][0], 0]))
        if backend == "motion":
            smile = motion_shapes(mesh, model).get("smile")
            if smile is not None:
                ids[2] = _smile_corners(mesh, camera, renderer, ids[2], smile)
    finally:
        if own:
            renderer.release()
    vid = np.concatenate(ids)
    return Landmarks(
        vid, np.concatenate(pts), mesh.vertices[vid].astype(np.float64), camera, backend, eyeballs, info
    ), regions


def landmarks_from_override(data: dict, mesh: Mesh, size: int = 512) -> Landmarks:
    """A user's JSON: {"vertex_ids": [20]} or {"points2d": [[x, y] x 20]} (pixels of the frontal render at ``size``)."""
    if "vertex_ids" in data:
        lm = Landmarks.from_dict({**data, "backend": "override"}, mesh.num_vertices)
        lm.positions = mesh.vertices[lm.vertex_ids].astype(np.float64)
        if "camera" not in data:
            lm.camera = frontal_camera(size)
            lm.points2d = lm.camera.project(lm.positions)[0]
        return lm
    if "points2d" in data:
        from t2bs.render.mesh_renderer import MeshRenderer

        p2 = np.asarray(data["points2d"], float)
        if p2.shape != (20, 2):
            raise UserError(f"override points2d must be 20 [x, y] pairs, got shape {p2.shape}")
        camera = frontal_camera(int(data.get("size", size)))
        with MeshRenderer() as r:
            vis = r.vertex_visibility(mesh, camera)
        ids = lift_points(p2, camera, mesh.vertices, vis, np.zeros((camera.height, camera.width), bool), "outside")
        return Landmarks(ids, p2, mesh.vertices[ids].astype(np.float64), camera, "override")
    raise UserError('override JSON needs "vertex_ids" (20 ints) or "points2d" (20 [x, y] pixel pairs)')


def overlay_image(mesh: Mesh, lm: Landmarks, regions: dict[str, Region] | None = None, renderer=None) -> np.ndarray:
    """[H, W, 3] uint8: frontal render, region tints, contour points (x) and lifted vertices (dots)."""
    from t2bs.render.mesh_renderer import MeshRenderer
    from t2bs.face.face_tracking import draw_points

    own = renderer is None
    renderer = renderer or MeshRenderer()
    try:
        img = (renderer.render(mesh, lm.camera).rgb * 255).astype(np.uint8)
    finally:
        if own:
            renderer.release()
    colours = {"right_eye": (230, 40, 40), "left_eye": (40, 90, 240), "mouth": (30, 190, 60)}
    out = img.astype(np.float32)
    for name, reg in (regions or {}).items():
        if reg.mask.shape == out.shape[:2]:
            out[reg.mask] = 0.55 * out[reg.mask] + 0.45 * np.asarray(colours[name], np.float32)
    out = out.astype(np.uint8)
    slices = {"right_eye": slice(0, 6), "left_eye": slice(6, 12), "mouth": slice(12, 20)}
    proj = lm.camera.project(lm.positions)[0]
    for name, sl in slices.items():
        out = draw_points(out, lm.points2d[sl], color=(255, 255, 0), radius=1)
        out = draw_points(out, proj[sl], color=colours[name], radius=2)
    return out


def find_project_landmarks(
    project: Project, mesh: Mesh, model=None, backend: str = "auto", override: Path | None = None, show: bool = False
) -> Landmarks:
    """A project's 20 landmarks -> ``landmarks/landmarks.json`` (+ ``landmarks/overlay.png`` with ``show``),
    recorded in the manifest as the "landmarks" stage.

    ``mesh``: the project's character (canonical frame). ``model``: the character's blendshape rig, or None;
    anything with ``neutral`` [N, 3], ``num_vertices`` and the named shapes ``semantic_names`` /
    ``semantic_offsets()`` (a ``t2bs.blendshapes`` model; passed in by the caller so that this layer never
    loads one). When it fits the mesh, the landmarks are found on its neutral, and the ``motion`` backend may
    use its named blink / mouth-open shapes. The landmarks come from, in this order: the user's ``override``
    JSON ({"vertex_ids": [20]} or {"points2d": [[x, y] x 20]}); the auto rig's own 20
    (``character/autorig.json``, when ``backend`` is "auto"); else ``detect_landmarks``.
    UserError: a missing or broken override file, a character without eyes / mouth to find."""
    if model is not None and model.num_vertices == mesh.num_vertices:
        mesh = mesh.with_vertices(model.neutral)
    regions = None
    if override is not None:
        if not Path(override).exists():
            raise UserError(f"override file {override} does not exist")
        try:
            data = json.loads(Path(override).read_text())
        except json.JSONDecodeError as exc:
            raise UserError(f"override file {override} is not valid JSON ({exc.msg}, line {exc.lineno})") from None
        lm = landmarks_from_override(data, mesh)
    elif backend == "auto" and project.path("character", "autorig.json").exists():
        # The motion came from the auto rig (issue 34): its 20 landmarks are this character's, in the
        # same 68-point order, found before any shape existed.
        ids = read_json(project.path("character", "autorig.json"))["landmarks"]["vertex_ids"]
        lm = landmarks_from_override({"vertex_ids": ids}, mesh)
        lm.backend = "autorig"
    else:
        lm, regions = detect_landmarks(mesh, backend, model=model)
    out = project.path("landmarks")
    write_json(out / "landmarks.json", lm.to_dict())
    if show:
        write_image(out / "overlay.png", overlay_image(mesh, lm, regions))
    project.record_stage(
        "landmarks", backend=lm.backend, config={"backend": backend, "override": str(override) if override else None}
    )
    return lm
