"""Where the face is on a static head mesh: 20 landmark vertices, optional named points, eyeballs.

Landmarks are vertex ids in the 68-point order used across t2bs (face_tracking.LANDMARKS_68):
36-41 the character's right eye (-X), 42-47 its left eye (+X), 60-67 the inner lip contour.
Sources, first that works:

1. ``--landmarks FILE``: ``{"vertex_ids": [20 ints]}`` (what ``t2bs landmarks`` writes and reads
   with ``--override``), optionally with named vertex ids (NAMED_POINTS) at the top level or
   under ``"named"``. A user's file beats any guess, so it is tried first.
2. Part labels (procedural characters): ``t2bs.face.landmarks`` with the ``parts`` backend.
3. MediaPipe face mesh on the frontal render (humanoid faces, also most cartoon faces with two
   eyes and a mouth): the 20 points and the brows / chin, lifted to the nearest visible vertex.
   Where the mesh has separate eyeball parts, the eye points come from them instead (the skin
   just outside what the front camera sees of each ball): geometry beats a detector trained on
   human photos when the eyes are a cartoon's. A flat eye part (an anime iris disc or lash card
   seen at the detected eye) gives the opening with the eye white painted on the skin around it
   (``painted_eye``), and the points go on the skin at its edge, under a lash card if one hides it.

Eyeballs come from part labels (eye_left / eye_right) or, on unlabelled meshes, from separate
sphere-shaped parts (a mirrored pair): they give the centre the lids turn about and the vertices
the eyeLook* shapes turn.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from t2bs.errors import UserError
from t2bs.geometry.mesh import Mesh, welded_components
from t2bs.rig.seam import find_lip_seam

# Optional named vertices a landmarks file may add (the 20 are enough; these refine the rig).
NAMED_POINTS = (
    "brow_left",
    "brow_right",
    "brow_inner_left",
    "brow_inner_right",
    "brow_outer_left",
    "brow_outer_right",
    "chin",
    "jaw_hinge",
)
# MediaPipe face-mesh indices of the named points (subject's left = character's left = +X).
MEDIAPIPE_NAMED = {
    "brow_right": 105,
    "brow_left": 334,
    "brow_inner_right": 107,
    "brow_inner_left": 336,
    "brow_outer_right": 70,
    "brow_outer_left": 300,
    "chin": 152,
}
# Positions in the 20 whose point lies on an upper edge (upper lid, upper inner lip) or a lower edge.
UPPER_POINTS = (1, 2, 7, 8, 13, 14, 15)
LOWER_POINTS = (4, 5, 10, 11, 17, 18, 19)
HOW_TO = (
    'give them with --landmarks FILE: {"vertex_ids": [20 vertex ids in the 68-point order 36-47, 60-67]} '
    "(the JSON `t2bs landmarks --show` writes; optional named ids: " + ", ".join(NAMED_POINTS) + "), "
    "or click them on the character in `t2bs view DIR` (folder Landmarks)"
)


@dataclass
class FaceLandmarks:
    vertex_ids: np.ndarray  # [20] int vertex ids, 68-point order 36-47, 60-67
    source: str  # "file", "parts", "mediapipe" or "mediapipe + eye parts"
    named: dict[str, int] = field(default_factory=dict)  # NAMED_POINTS -> vertex id (those known)
    eyeballs: dict[str, np.ndarray] = field(default_factory=dict)  # "left"/"right" -> [M] vertex ids

    def to_dict(self) -> dict:
        return {
            "vertex_ids": self.vertex_ids.tolist(),
            "source": self.source,
            "named": dict(self.named),
            "eyeballs": {k: int(len(v)) for k, v in self.eyeballs.items()},
        }


def read_landmarks_file(path: Path, num_vertices: int) -> tuple[np.ndarray, dict[str, int]]:
    """The user's JSON -> ([20] vertex ids, named ids); one UserError line on anything malformed."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"landmarks file {path} does not exist")
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise UserError(f"landmarks file {path} is not JSON: {e}") from None
    if not isinstance(data, dict) or "vertex_ids" not in data:
        raise UserError(f'landmarks file {path} needs "vertex_ids": {HOW_TO}')
    try:
        ids = np.asarray(data["vertex_ids"], dtype=np.int64)
    except (TypeError, ValueError):
        raise UserError(f"landmarks file {path}: vertex_ids must be 20 integers") from None
    if ids.shape != (20,):
        raise UserError(
            f"landmarks file {path}: vertex_ids must be 20 integers (68-point order 36-47, 60-67), got {ids.size}"
        )
    named_src = {**{k: v for k, v in data.items() if k in NAMED_POINTS}, **(data.get("named") or {})}
    named = {}
    for k, v in named_src.items():
        if k not in NAMED_POINTS:
            raise UserError(f"landmarks file {path}: unknown named point {k!r}; known: {', '.join(NAMED_POINTS)}")
        if not isinstance(v, int) or isinstance(v, bool):
            raise UserError(f"landmarks file {path}: named point {k!r} must be one vertex id")
        named[k] = v
    allv = np.concatenate([ids, np.asarray(list(named.values()), np.int64)])
    if allv.min() < 0 or allv.max() >= num_vertices:
        raise UserError(f"landmarks file {path}: vertex ids must be in 0..{num_vertices - 1}")
    return ids, named


def fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Least-squares sphere through points [P, 3] -> (centre [3], radius, rms residual / radius)."""
    p = np.asarray(points, np.float64)
    a = np.concatenate([2 * p, np.ones((len(p), 1))], axis=1)
    sol, *_ = np.linalg.lstsq(a, (p**2).sum(1), rcond=None)
    c = sol[:3]
    r = float(np.sqrt(max(sol[3] + c @ c, 1e-18)))
    res = float(np.sqrt(np.mean((np.linalg.norm(p - c, axis=1) - r) ** 2)) / r)
    return c, r, res


def find_eyeballs(mesh: Mesh) -> dict[str, np.ndarray]:
    """ "left"/"right" -> eyeball vertex ids: labelled eye parts, else a mirrored pair of sphere-shaped parts."""
    names = set(mesh.part_names)
    if {"eye_left", "eye_right"} <= names:
        return {s: np.nonzero(mesh.part_mask(f"eye_{s}"))[0] for s in ("left", "right")}
    comp = welded_components(mesh.vertices, mesh.faces)
    counts = np.bincount(comp)
    v = mesh.vertices.astype(np.float64)
    diag = mesh.bbox_diagonal()
    spheres = []
    for c in np.nonzero(counts >= 12)[0]:
        if counts[c] == counts.max():
            continue  # the head itself
        idx = np.nonzero(comp == c)[0]
        centre, r, res = fit_sphere(v[idx])
        # An eyeball: closed and round (small residual), a few percent of the head, in the front half.
        if res < 0.08 and 0.01 * diag < r < 0.15 * diag and centre[2] > 0.0:
            spheres.append((idx, centre, r))
    best, score = None, np.inf
    for i, (ia, ca, ra) in enumerate(spheres):
        for ib, cb, rb in spheres[i + 1 :]:
            if ca[0] * cb[0] >= 0:
                continue  # a pair sits on both sides of the face
            s = (abs(ca[0] + cb[0]) + abs(ca[1] - cb[1]) + abs(ca[2] - cb[2])) / (ra + rb) + abs(ra - rb) / (ra + rb)
            if s < 0.5 and s < score:
                best, score = ((ia, ca), (ib, cb)), s
    if best is None:
        return {}
    (ia, ca), (ib, cb) = best
    return {"left": ia, "right": ib} if ca[0] > 0 else {"left": ib, "right": ia}


def _lift(points2d: np.ndarray, uv: np.ndarray, candidates: np.ndarray, side: np.ndarray) -> np.ndarray:
    """Nearest candidate vertex in the image to each point; ``side`` +1: only vertices at or above the
    point (image y smaller), -1: at or below, 0: any (keeps upper and lower lip apart on a closed mouth)."""
    out = np.zeros(len(points2d), np.int64)
    cand = np.nonzero(candidates)[0]
    for k, p in enumerate(points2d):
        c = cand
        if side[k] != 0:
            ok = (p[1] - uv[cand, 1]) * side[k] >= -0.5
            c = cand[ok] if ok.any() else cand
        out[k] = c[np.argmin(np.linalg.norm(uv[c] - p[None], axis=1))]
    return out


def landmarks_mediapipe(mesh: Mesh, renderer, eyeballs: dict[str, np.ndarray], size: int = 512) -> tuple | str:
    """MediaPipe face mesh on the frontal render -> (ids [20], named ids, the 20 points [20, 2] in pixels,
    whether the mouth points came from the mesh's lip seam); a reason string when it finds nothing."""
    from t2bs.geometry.camera import frontal_camera
    from t2bs.face.face_tracking import MEDIAPIPE_20, mediapipe_available, run_face_mesh

    if not mediapipe_available():
        return "MediaPipe is not installed (scripts/setup.sh)"
    cam = frontal_camera(size)
    rendered = renderer.render(mesh, cam, shading="lambert")
    img = (np.clip(rendered.rgb, 0, 1) * 255).astype(np.uint8)
    lm, found = run_face_mesh(img[None], static=True)
    if not found[0]:
        return "MediaPipe found no face on the frontal render"
    vis = renderer.vertex_visibility(mesh, cam)
    for ids in eyeballs.values():
        vis[ids] = False  # lid points belong on the lid, not on the eyeball behind it
    uv, _ = cam.project(mesh.vertices.astype(np.float64))
    # The face's skin is the part with the most visible vertices inside the detected face: points are
    # lifted onto it, not onto lashes, brows or hair cards floating in front of it.
    lo, hi = lm[0, :, :2].min(0), lm[0, :, :2].max(0)
    comp = welded_components(mesh.vertices, mesh.faces)
    inside = vis & np.all((uv >= lo) & (uv <= hi), axis=1)
    if inside.any():
        vis &= comp == np.bincount(comp[inside]).argmax()
    side = np.zeros(20, int)
    side[list(UPPER_POINTS)] = 1
    side[list(LOWER_POINTS)] = -1
    pts = lm[0, MEDIAPIPE_20, :2]
    ids = _lift(pts, uv, vis, side)
    # A closed mouth (or eye) puts an upper and a lower point on one pixel; the lower one must then
    # land strictly below the vertex its upper partner took, on the other lip.
    for up, lo in ((13, 19), (14, 18), (15, 17), (1, 5), (2, 4), (7, 11), (8, 10)):
        below = vis & (uv[:, 1] > uv[ids[up], 1] + 0.25)
        if below.any():
            ids[lo] = _lift(pts[[lo]], uv, below, np.array([-1]))[0]
    names = list(MEDIAPIPE_NAMED)
    named_ids = _lift(lm[0, [MEDIAPIPE_NAMED[n] for n in names], :2], uv, vis, np.zeros(len(names), int))
    named = {n: int(i) for n, i in zip(names, named_ids)}
    # The mesh's own lip seam beats the detector's guess of the mouth (a cartoon's mouth line is not
    # where a human's would be); a sealed mouth keeps the detector's points.
    seam = find_lip_seam(mesh.vertices, mesh.faces, uv, rendered, vis, pts[:12], pts[12:])
    if seam is not None:
        ids[12:] = seam.ids
        pts = np.concatenate([pts[:12], uv[seam.ids]])
        # The detector's chin came with its mouth: it must lie well below the seam to be a chin.
        eye_y = 0.5 * (pts[:6, 1].mean() + pts[6:12, 1].mean())
        if uv[named["chin"], 1] < uv[seam.ids[[5, 6, 7]], 1].max() + 0.25 * (pts[12:, 1].mean() - eye_y):
            del named["chin"]
    return ids, named, pts, seam is not None


def eye_parts_at(mesh: Mesh, renderer, points2d: np.ndarray, size: int = 512) -> dict[str, np.ndarray]:
    """Separate eye parts (a flat or painted eye disc, not a ball) seen at the detected eye centres:
    "left"/"right" -> vertex ids of the small part the front camera sees there ({} if the skin is seen)."""
    from t2bs.geometry.camera import frontal_camera

    fid = renderer.render(mesh, frontal_camera(size), shading="unlit").face_id
    comp = welded_components(mesh.vertices, mesh.faces)
    counts = np.bincount(comp)
    out = {}
    for side, sl in (("right", slice(0, 6)), ("left", slice(6, 12))):
        x, y = np.round(points2d[sl].mean(0)).astype(int)
        if not (0 <= y < fid.shape[0] and 0 <= x < fid.shape[1]) or fid[y, x] < 0:
            return {}
        c = comp[mesh.faces[fid[y, x], 0]]
        if counts[c] == counts.max() or counts[c] > 0.1 * mesh.num_vertices:
            return {}  # the eye is painted on the skin
        out[side] = np.nonzero(comp == c)[0]
    return (
        out
        if out.get("left") is not None
        and out.get("right") is not None
        and not np.array_equal(out["left"], out["right"])
        else {}
    )


# A skin pixel belongs to a painted eye (the white around a flat iris) when its colour is this far from the
# skin's median colour (RGB in [0, 1], unlit render: no shading): a painted eye white or lash line is a
# different colour (vipe's pink skin to its eye white: 0.83), a texture's own variation is not (blush, pores,
# baked shading: under 0.1).
PAINT_STEP = 0.25


def painted_eye(part: np.ndarray, seen_comp: np.ndarray, skin_comp: int, rgb: np.ndarray) -> np.ndarray:
    """[H, W] bool: the eye opening around a flat eye part (``part`` [H, W] bool, its pixels): the eye white
    painted on the skin around it and the parts inside that (an iris disc), not the lash card over it.

    Painted: skin pixels (``seen_comp`` [H, W] the component seen at each pixel, -1 background) of another
    colour than the skin's median (PAINT_STEP), connected to the part, no farther from it than its own width
    and height (a painted eye is a few iris sizes across; a brow or a cheek mark beside it is not taken).
    Parts whose pixels lie mostly within the painted region's convex hull are in the eye (an iris, a pupil,
    the part itself when it is the iris); a lash card lies along the region's edge, mostly outside its hull,
    and stays out, so the region ends at the lash line, where the lid margin is. Nothing painted: the part."""
    from scipy import ndimage
    from scipy.spatial import ConvexHull, QhullError

    ys, xs = np.nonzero(part)
    skin = seen_comp == skin_comp
    if len(xs) == 0 or not skin.any():
        return part
    w, h = xs.max() - xs.min() + 1, ys.max() - ys.min() + 1
    window = np.zeros_like(part)
    window[max(ys.min() - 2 * h, 0) : ys.max() + 2 * h + 1, max(xs.min() - 2 * w, 0) : xs.max() + 2 * w + 1] = True
    paint = skin & window & (np.linalg.norm(rgb - np.median(rgb[skin], axis=0), axis=-1) > PAINT_STEP)
    lab, _ = ndimage.label(paint | part, structure=np.ones((3, 3)))
    touching = np.unique(lab[part])
    paint &= np.isin(lab, touching[touching > 0])
    py, px = np.nonzero(paint)
    if len(px) < 16:
        return part
    try:
        hull = ConvexHull(np.stack([px, py], axis=1)).equations  # inside: a x + b y + c <= 0 for every edge
    except QhullError:  # a painted line, no area
        return part
    region = paint.copy()
    for c in np.unique(seen_comp[window & ~skin & (seen_comp >= 0)]):
        cy, cx = np.nonzero((seen_comp == c) & window)
        inside = np.all(np.stack([cx, cy], axis=1) @ hull[:, :2].T + hull[:, 2] <= 0.5, axis=1)
        if inside.mean() > 0.5:
            region[cy, cx] = True
    return ndimage.binary_fill_holes(region)


def eyes_from_parts(
    mesh: Mesh, renderer, eyeballs: dict[str, np.ndarray], size: int = 512, flat: bool = False
) -> np.ndarray | None:
    """[12] eye landmark ids (36-47) from separate eye parts (balls or discs): the lid margin is the
    surface just outside what the frontal camera sees of each part (as the parts backend does with
    labelled eyes). None when a part is not seen from the front.

    ``flat``: the parts are flat eyes (an iris disc, ``eye_parts_at``): the opening is the part and the
    eye white painted on the skin around it (``painted_eye``), and the points go on the skin there even
    where a lash card hides it (the lid margin is the skin under the lashes)."""
    from scipy import ndimage

    from t2bs.geometry.camera import frontal_camera
    from t2bs.face.landmarks import EYE_ANGLES, contour_points, largest_component, lift_points

    cam = frontal_camera(size)
    rendered = renderer.render(mesh, cam, shading="unlit")
    fid = rendered.face_id
    seen_vertex = np.where(fid >= 0, mesh.faces[np.maximum(fid, 0), 0], -1)
    balls = np.concatenate(list(eyeballs.values()))
    vis = renderer.vertex_visibility(mesh, cam)
    vis[balls] = False
    if flat:
        comp = welded_components(mesh.vertices, mesh.faces)
        seen_comp = np.where(seen_vertex >= 0, comp[np.maximum(seen_vertex, 0)], -1)
        skin_visible: dict[int, np.ndarray] = {}  # per skin part: both eyes usually lie on one, rendered once
    out = []
    for side in ("right", "left"):  # 36-41 then 42-47
        mask = largest_component(np.isin(seen_vertex, eyeballs[side]))
        if mask.sum() < 16:
            return None
        visible = vis
        if flat:
            # The skin: the part seen most around the eye part (not the eye part itself).
            ring = ndimage.binary_dilation(mask, np.ones((3, 3)), iterations=3) & ~mask & (seen_comp >= 0)
            if not ring.any():
                return None
            skin_c = int(np.bincount(seen_comp[ring]).argmax())
            mask = painted_eye(mask, seen_comp, skin_c, rendered.rgb)
            if skin_c not in skin_visible:
                skin_faces = comp[mesh.faces[:, 0]] == skin_c
                skin_mesh = replace(mesh, faces=mesh.faces[skin_faces])
                skin_visible[skin_c] = renderer.vertex_visibility(skin_mesh, cam) & (comp == skin_c)
            visible = skin_visible[skin_c]
        p2, _ = contour_points(mask, EYE_ANGLES)
        out.append(lift_points(p2, cam, mesh.vertices, visible, mask, "outside"))
    return np.concatenate(out).astype(np.int64)


def find_face(
    mesh: Mesh, landmarks_file: Path | None = None, renderer=None, use_mediapipe: bool = True, source_name: str = "mesh"
) -> FaceLandmarks:
    """Landmarks of ``mesh`` (canonical frame: +Z forward, Y up) from the first source that works."""
    eyeballs = find_eyeballs(mesh)
    if landmarks_file is not None:
        ids, named = read_landmarks_file(landmarks_file, mesh.num_vertices)
        return FaceLandmarks(ids, "file", named, eyeballs)
    from t2bs.render.mesh_renderer import MeshRenderer
    from t2bs.face.landmarks import detect_landmarks, has_part_labels

    own = renderer is None
    renderer = renderer or MeshRenderer()
    try:
        reasons = []
        if has_part_labels(mesh):
            try:
                lm, _ = detect_landmarks(mesh, backend="parts", renderer=renderer)
                return FaceLandmarks(np.asarray(lm.vertex_ids, np.int64), "parts", {}, eyeballs)
            except UserError as e:
                reasons.append(f"part labels: {e}")
        else:
            reasons.append("no eye/mouth part labels")
        if use_mediapipe:
            got = landmarks_mediapipe(mesh, renderer, eyeballs)
            if isinstance(got, str):
                reasons.append(got)
            else:
                ids, source = got[0], "mediapipe + lip seam" if got[3] else "mediapipe"
                # Separate eye parts pin the eyes down geometrically; a detector trained on human
                # photos only guesses them on a cartoon (it keeps the mouth and brows).
                parts = eyeballs or eye_parts_at(mesh, renderer, got[2])
                eyes = eyes_from_parts(mesh, renderer, parts, flat=not eyeballs) if parts else None
                if eyes is not None:
                    ids, source = np.concatenate([eyes, ids[12:]]), source + " + eye parts"
                return FaceLandmarks(ids, source, got[1], eyeballs)
        else:
            reasons.append("MediaPipe not tried")
    finally:
        if own:
            renderer.release()
    raise UserError(
        f"no face found on {source_name}: missing the 20 face landmarks (eyes 36-47, inner lips 60-67; "
        f"{'; '.join(reasons)}); {HOW_TO}"
    )
