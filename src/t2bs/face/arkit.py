"""ARKit-52 named shapes on any rig, derived through the paper's retargeting (§3.3, §4.3).

Face-capture apps (Live Link Face, ARKit), MediaPipe's blendshape scores, VRM "perfect sync"
avatars and most engines speak Apple's 52 blendshape names. The PCA model is right for fitting,
but nobody can drive ``pc017``. Each ARKit shape is made here the way the paper retargets a human
video, with one frame of "video" per shape:

1. the shape's motion on a human face's 20 landmarks (68-scheme eyes 36-47, inner lips 60-67),
   read from ICT-FaceKit's ARKit expressions (MIT; ``data/arkit_landmarks.json``, derived by
   ``tools/derive_arkit_landmarks.py``: displacements only, no mesh);
2. transferred to the character's landmarks (``transfer.transfer_motion``: eyes scaled by the eye
   size ratios, the mouth by the mouth width ratio, the lid gap as an openness ratio);
3. solved in the character's blendshape space (``solve.RetargetSolver``: landmark 1.0 + ARAP 0.1 +
   eye terms). The result is a weight vector in the basis, so the shape stays inside what the
   captures support (like the prompt-named shapes of ``blendshapes/semantic.py``).

20 landmarks (40 numbers) cannot pin a model of 50-100 components: many weight vectors move the
landmarks alike (a blink, or a blink plus the eyeballs rolling). The solve therefore adds the PCA's
own Gaussian prior, ``ridge * sum_k (s_0 / s_k)^2 w_k^2``: among the shapes that move the landmarks
right it picks the one the captures make most often. Measured on facecap (whose own ARKit shapes are
the truth, ``benchmarks/arkit_facecap.py``): median displacement cosine 0.56 with the solve's plain
ridge, 0.72 with the prior at 1e-4 (jawOpen 0.62 -> 0.99, eyeBlinkLeft 0.34 -> 0.77).

Left/right are the character's own: the reference's ``...Left`` moves the subject's left (+X), the
character's landmarks 42-47 sit on its left (+X), nothing is mirrored.

A shape is *present* when (a) the reference moves the 20 landmarks visibly (the brows and the
tongue move none of them: the paper's landmarks cannot see those shapes) and (b) the solve reaches
the transferred landmark motion: in the regions (each eye; the mouth's right third, middle and left
third) the target moves, the
achieved landmark displacement has cosine >= ``min_cosine`` with the target and covers >=
``min_reach`` of it, and at most ``max_crosstalk`` of the achieved motion lies in the other regions.
A character whose captures only blink both eyes at once cannot express eyeBlinkLeft alone: the
solve closes both eyes half-way (crosstalk 0.7) and the shape is reported absent, not exported
wrong; the same holds for a one-sided smile on a rig that only smiles with both corners. The cosine is per region and lenient because a cartoon lid that closes from both sides is
still a blink, though its landmark pattern differs from the human's.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from t2bs.errors import UserError
from t2bs.face.solve import PRIOR_RIDGE, observed_range

# Apple's names, grouped as a viewer lists them (ARFaceAnchor.BlendShapeLocation).
ARKIT_GROUPS: dict[str, list[str]] = {
    "eyes": [
        "eyeBlinkLeft",
        "eyeBlinkRight",
        "eyeLookDownLeft",
        "eyeLookDownRight",
        "eyeLookInLeft",
        "eyeLookInRight",
        "eyeLookOutLeft",
        "eyeLookOutRight",
        "eyeLookUpLeft",
        "eyeLookUpRight",
        "eyeSquintLeft",
        "eyeSquintRight",
        "eyeWideLeft",
        "eyeWideRight",
    ],
    "brows": ["browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight"],
    "jaw": ["jawForward", "jawLeft", "jawRight", "jawOpen"],
    "mouth": [
        "mouthClose",
        "mouthFunnel",
        "mouthPucker",
        "mouthLeft",
        "mouthRight",
        "mouthSmileLeft",
        "mouthSmileRight",
        "mouthFrownLeft",
        "mouthFrownRight",
        "mouthDimpleLeft",
        "mouthDimpleRight",
        "mouthStretchLeft",
        "mouthStretchRight",
        "mouthRollLower",
        "mouthRollUpper",
        "mouthShrugLower",
        "mouthShrugUpper",
        "mouthPressLeft",
        "mouthPressRight",
        "mouthLowerDownLeft",
        "mouthLowerDownRight",
        "mouthUpperUpLeft",
        "mouthUpperUpRight",
    ],
    "cheeks": ["cheekPuff", "cheekSquintLeft", "cheekSquintRight"],
    "nose": ["noseSneerLeft", "noseSneerRight"],
    "tongue": ["tongueOut"],
}
ARKIT_NAMES: list[str] = [n for names in ARKIT_GROUPS.values() for n in names]  # [52]
ARKIT_GROUP_OF: dict[str, str] = {n: g for g, names in ARKIT_GROUPS.items() for n in names}
_BY_KEY = {n.lower(): n for n in ARKIT_NAMES}
REFERENCE = Path(__file__).resolve().parent / "data" / "arkit_landmarks.json"


def arkit_name(name: str) -> str | None:
    """Apple's spelling of an ARKit shape name, or None: "eyeBlink_L", "EyeBlinkLeft" (Live Link
    Face's CSV header), "eyeBlinkLeft" -> "eyeBlinkLeft"."""
    key = re.sub(r"_l$", "left", re.sub(r"_r$", "right", name.strip().lower()))
    return _BY_KEY.get(key.replace("_", ""))


@dataclass
class ArkitConfig:
    min_reference_motion: float = 0.035  # least landmark motion in the image plane, fraction of the eye / mouth width (jawForward: 3.1 %, a depth motion)
    min_cosine: float = 0.6  # achieved vs transferred landmark motion, over the regions the target moves
    min_reach: float = 0.3  # achieved landmark motion projected on the target, as a fraction of the target
    max_crosstalk: float = (
        0.4  # largest fraction of the achieved motion (norm) outside the target's regions (both eyes for one: ~0.7)
    )
    prior: float = PRIOR_RIDGE  # the PCA prior's weight (face/solve.py), relative to the largest diagonal entry
    # largest fraction of the shape's largest vertex motion that needs weights outside the captured range
    # (``outside_fraction``; session 43: <= 0.3 on the shapes that look right or match facecap's own, 0.63-0.99 on
    # those that push the jaw up into the head or the lids wider than rest; docs/ARKIT.md)
    max_outside: float = 0.5


@dataclass
class ArkitShapes:
    names: list[str]  # [S] present shapes, in ARKIT_NAMES order
    weights: np.ndarray  # [S, K] each present shape in the model's basis (weight 1 = the reference's full shape)
    report: dict = field(default_factory=dict)  # every one of the 52 -> {"present", "why", "cosine", "reach", ...}

    def to_dict(self) -> dict:
        return {
            "names": self.names,
            "weights": np.round(self.weights, 7).tolist(),
            "report": self.report,
            "reference": "ICT-FaceKit (MIT), see t2bs/face/data/arkit_landmarks.json",
        }

    @staticmethod
    def from_dict(d: dict, num_components: int) -> "ArkitShapes":
        w = (
            np.asarray(d.get("weights", []), np.float64).reshape(-1, num_components)
            if d.get("names")
            else np.zeros((0, num_components))
        )
        if len(w) != len(d.get("names", [])):
            raise UserError("arkit.json: names and weights disagree (rebuild with `t2bs blendshapes DIR --force`)")
        return ArkitShapes(list(d.get("names", [])), w, dict(d.get("report", {})))


def load_reference(path: Path = REFERENCE) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(neutral [20, 3], name -> displacement [20, 3]) of the human reference (cm, Y up, +X = subject's left)."""
    data = json.loads(Path(path).read_text())
    return np.asarray(data["neutral"], np.float64), {n: np.asarray(d, np.float64) for n, d in data["shapes"].items()}


def _reference_track(neutral: np.ndarray, disp: np.ndarray):
    """A two-frame FaceTrack (neutral, shape) in the tracker's convention: x right, y down."""
    from t2bs.face.face_tracking import FaceTrack

    pts = np.stack([neutral, neutral + disp]) * np.array([1.0, -1.0, 1.0])  # [2, 20, 3], Y up -> image y down
    return FaceTrack(points=pts, image_points=pts[..., :2], found=np.ones(2, bool), neutral=0, fps=1.0)


def reference_motion(neutral: np.ndarray, disp: np.ndarray) -> float:
    """Largest frontal-plane landmark motion of a reference shape, as a fraction of its region's width."""
    from t2bs.face.face_tracking import LEFT_EYE, MOUTH, RIGHT_EYE
    from t2bs.face.transfer import region_sizes

    sizes = region_sizes(neutral, y_up=True)
    out = 0.0
    for idx, width in ((RIGHT_EYE, sizes["right"][0]), (LEFT_EYE, sizes["left"][0]), (MOUTH, sizes["mouth"])):
        out = max(out, float(np.linalg.norm(disp[idx, :2], axis=1).max() / max(width, 1e-9)))
    return out


# Landmark regions (positions in the 20) for judging where a shape moves: each eye, and the mouth's
# right third (60, 61, 67), middle (62, 66) and left third (63, 64, 65), so a one-sided smile is told
# from a symmetric one.
REGIONS_20 = [list(range(0, 6)), list(range(6, 12)), [12, 13, 19], [14, 18], [15, 16, 17]]


def _agreement(target: np.ndarray, achieved: np.ndarray) -> tuple[float, float, float]:
    """(cosine, reach over the target's regions, fraction of the achieved motion elsewhere) of landmark
    motions [20, 2]; a region is the target's when it moves >= 25 % of the most moving region (ICT's
    mouthSmileLeft drags the right third 16 % as far as the left: not enough to count)."""
    size = np.array([np.linalg.norm(target[r]) for r in REGIONS_20])
    mine = np.zeros(20, bool)
    for r, sz in zip(REGIONS_20, size):
        mine[r] = sz >= 0.25 * size.max()
    t, a = target[mine].reshape(-1), achieved[mine].reshape(-1)
    tn, an = float(np.linalg.norm(t)), float(np.linalg.norm(achieved))
    cos = float(a @ t / max(np.linalg.norm(a) * tn, 1e-30))
    reach = float(a @ t / max(tn * tn, 1e-30))
    crosstalk = float(np.linalg.norm(achieved[~mine]) / max(an, 1e-30))
    return cos, reach, crosstalk


def outside_fraction(basis: np.ndarray, weights: np.ndarray, observed: np.ndarray) -> float:
    """How much of a shape lies beyond what the captures saw: ``basis`` [K, N, 3], the shape's ``weights`` [K],
    ``observed`` [2, K] each component's lowest and highest captured weight. -> the largest vertex motion of the
    weights' part outside that range, as a fraction of the shape's own largest vertex motion (0: inside; 1: all
    of it). A landmark solve may reach its target by running a component backwards (the jaw closing past rest,
    the lids opening wider than the neutral) where no capture went: such a shape is an extrapolation."""
    basis = np.asarray(basis, np.float64).reshape(len(basis), -1, 3)
    w = np.asarray(weights, np.float64)
    beyond = w - np.clip(w, observed[0], observed[1])
    peak = float(np.linalg.norm(np.einsum("k,kni->ni", w, basis), axis=-1).max())
    return float(np.linalg.norm(np.einsum("k,kni->ni", beyond, basis), axis=-1).max()) / max(peak, 1e-30)


def derive_arkit_shapes(
    neutral: np.ndarray,
    basis: np.ndarray,
    singular_values: np.ndarray,
    faces: np.ndarray,
    landmark_ids: np.ndarray,
    eyeballs: dict | None = None,
    mouth_width: float | None = None,
    config: ArkitConfig = ArkitConfig(),
    reference: Path = REFERENCE,
    observed: np.ndarray | None = None,
) -> ArkitShapes:
    """The 52 ARKit shapes in a blendshape model's space (``neutral`` [N, 3], ``basis`` [K, N, 3],
    ``singular_values`` [K] of the captures, for the prior).

    ``landmark_ids`` [20]: the character's retargeting landmarks (``t2bs landmarks``); ``eyeballs``
    and ``mouth_width`` as the landmark stage found them (see ``transfer_motion``). ``observed`` [2, K]: each
    component's captured weight range (``observed_range``); a shape that needs more than ``config.max_outside`` of
    its motion beyond it is absent (``outside_fraction``). None: not checked.
    """
    from t2bs.face.solve import RetargetSolver, SolveConfig, pca_prior
    from t2bs.face.transfer import TransferConfig, transfer_motion

    neutral = np.asarray(neutral, np.float64)
    basis = np.asarray(basis, np.float64)
    ids = np.asarray(landmark_ids, int)
    ref_neutral, ref_shapes = load_reference(reference)
    char_lm = neutral[ids]  # [20, 3]
    # The reference is exact geometry, not a MediaPipe reading: a shut reference eye is a shut eye.
    tcfg = TransferConfig(closed_ratio=0.0)
    solver = RetargetSolver(
        neutral, basis, faces, ids, eyeballs, SolveConfig(ridge=config.prior), pca_prior(singular_values)
    )
    a_lm = basis[:, ids, :2].reshape(len(basis), -1)  # [K, 40] landmark X, Y motion of each component
    names, weights, report = [], [], {}
    for name in ARKIT_NAMES:
        if name not in ref_shapes:
            report[name] = {"present": False, "why": "not in the human reference (ICT-FaceKit has no such shape)"}
            continue
        motion = reference_motion(ref_neutral, ref_shapes[name])
        if motion < config.min_reference_motion:
            report[name] = {
                "present": False,
                "reference_motion": round(motion, 4),
                "why": f"moves no eye or mouth landmark in the image plane (largest {motion:.1%} of the region's "
                f"width): the 20 retargeting landmarks cannot see it",
            }
            continue
        tr = transfer_motion(_reference_track(ref_neutral, ref_shapes[name]), char_lm, tcfg, mouth_width=mouth_width)
        solver.reset()
        w = solver.solve_frame(tr.targets[1], tr.eye_openness[1])  # [K]
        target = tr.targets[1] - char_lm[:, :2]  # [20, 2]
        achieved = (w @ a_lm).reshape(20, 2)
        cos, reach, crosstalk = _agreement(target, achieved)
        entry = {
            "reference_motion": round(motion, 4),
            "cosine": round(cos, 4),
            "reach": round(reach, 4),
            "crosstalk": round(crosstalk, 4),
        }
        outside = outside_fraction(basis, w, observed) if observed is not None else 0.0
        if observed is not None:
            entry["outside"] = round(outside, 4)
        agrees = cos >= config.min_cosine and reach >= config.min_reach and crosstalk <= config.max_crosstalk
        if agrees and outside <= config.max_outside:
            names.append(name)
            weights.append(w)
            report[name] = {"present": True, **entry, "why": "derived"}
        elif agrees:
            report[name] = {
                "present": False,
                **entry,
                "why": f"beyond the captures: {outside:.0%} of its motion needs weights outside the range the "
                f"captures saw (at most {config.max_outside:.0%}; e.g. a jaw closing past rest)",
            }
        else:
            report[name] = {
                "present": False,
                **entry,
                "why": f"the captures cannot express it: landmark cosine {cos:.2f} (need {config.min_cosine}), "
                f"reach {reach:.2f} (need {config.min_reach}), motion elsewhere {crosstalk:.2f} "
                f"(at most {config.max_crosstalk})",
            }
    w = np.asarray(weights, np.float64).reshape(len(names), basis.shape[0])
    return ArkitShapes(names, w, report)


def summary(shapes: ArkitShapes) -> str:
    """One line: how many of the 52 are present and why the others are not, by reason."""
    absent: dict[str, list[str]] = {}
    for name, r in shapes.report.items():
        if not r["present"]:
            key = r["why"].split(":")[0].split(" (")[0]
            absent.setdefault(key, []).append(name)
    parts = [f"{len(names)} {why}" for why, names in absent.items()]
    return f"ARKit shapes: {len(shapes.names)}/52 present" + (f"; absent: {'; '.join(parts)}" if parts else "")


def project_arkit_shapes(project_root: Path, model, character, config: ArkitConfig = ArkitConfig()) -> ArkitShapes:
    """ARKit shapes of a project's model: its landmarks (landmarks/landmarks.json, found on ``character``
    and the model's neutral and written when absent; UserError when the character has none) ->
    ``derive_arkit_shapes``."""
    from t2bs.project import Project, read_json
    from t2bs.face.landmarks import Landmarks, find_project_landmarks

    path = Path(project_root) / "landmarks" / "landmarks.json"
    if path.exists():
        lm = Landmarks.from_dict(read_json(path), model.num_vertices)
    else:
        lm = find_project_landmarks(Project(project_root), character, model)
    return derive_arkit_shapes(
        model.neutral,
        model.basis,
        model.singular_values,
        character.faces,
        lm.vertex_ids,
        lm.eyeballs,
        lm.regions.get("mouth", {}).get("width_world"),
        config,
        observed=observed_range(model.capture_weights),
    )


def load_arkit_shapes(path: Path, num_components: int) -> ArkitShapes | None:
    """blendshapes/arkit.json of a project (None when the stage derived none)."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise UserError(f"{path}: not valid JSON ({exc.msg}); rebuild with `t2bs blendshapes DIR --force`") from None
    return ArkitShapes.from_dict(data, num_components)


# A dozen shapes that show a rig's range at a glance (first the present ones of this list).
SHEET_SHAPES = [
    "eyeBlinkLeft",
    "eyeBlinkRight",
    "eyeWideLeft",
    "eyeLookDownLeft",
    "jawOpen",
    "mouthClose",
    "mouthFunnel",
    "mouthPucker",
    "mouthSmileLeft",
    "mouthSmileRight",
    "mouthFrownLeft",
    "mouthLeft",
    "mouthRollLower",
    "mouthShrugLower",
    "mouthPressLeft",
    "mouthLowerDownLeft",
    "mouthUpperUpLeft",
    "cheekSquintLeft",
    "jawLeft",
    "mouthStretchLeft",
    "noseSneerLeft",
    "cheekPuff",
]


def contact_sheet(
    model, character, shapes: ArkitShapes, count: int = 12, size: int = 192, columns: int = 4, renderer=None
) -> np.ndarray:
    """[H, W, 3] uint8 frontal renders of the neutral and up to ``count`` present ARKit shapes at weight 1,
    each labelled with its name (the neutral first, so each shape compares against it)."""
    from PIL import Image, ImageDraw

    from t2bs.geometry.camera import frontal_camera

    chosen = [n for n in SHEET_SHAPES if n in shapes.names][:count]
    chosen += [n for n in shapes.names if n not in chosen][: count - len(chosen)]
    poses = [("neutral", model.neutral)] + [(n, model.vertices(shapes.weights[shapes.names.index(n)])) for n in chosen]
    cam = frontal_camera(2 * size)  # rendered at twice the tile size, cropped to the character, then shrunk
    own = renderer is None
    if own:
        from t2bs.render.mesh_renderer import MeshRenderer

        renderer = MeshRenderer()
    try:
        renders = [renderer.render(character, cam, vertices=np.asarray(v, np.float32)) for _, v in poses]
    finally:
        if own:
            renderer.release()
    ys, xs = np.nonzero(np.any([r.mask for r in renders], axis=0))
    half = max(ys.max() - ys.min(), xs.max() - xs.min()) // 2 + 8  # one square box around every pose
    cy, cx = (ys.max() + ys.min()) // 2, (xs.max() + xs.min()) // 2
    box = (cx - half, cy - half, cx + half, cy + half)
    tiles = []
    for (label, _), r in zip(poses, renders):
        img = Image.fromarray((r.rgb * 255 + 0.5).astype(np.uint8)).crop(box).resize((size, size), Image.LANCZOS)
        ImageDraw.Draw(img).text((4, 4), label, fill=(0, 0, 0))
        tiles.append(np.asarray(img))
    rows = -(-len(tiles) // columns)
    sheet = np.full((rows * size, columns * size, 3), 255, np.uint8)
    for i, tile in enumerate(tiles):
        r, c = divmod(i, columns)
        sheet[r * size : (r + 1) * size, c * size : (c + 1) * size] = tile
    return sheet
