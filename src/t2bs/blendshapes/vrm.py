"""VRM 1.0 export (``VRMC_vrm``): the rig as an avatar that VTubing apps and three-vrm load.

A .vrm is a .glb with the ``VRMC_vrm`` extension (https://github.com/vrm-c/vrm-specification,
specification/VRMC_vrm-1.0): meta (name, authors, licence), a humanoid skeleton and expressions
that bind morph targets. What is written:

- The mesh and morph targets of ``model.glb`` (ARKit-named shapes, prompt-named shapes, visible
  PCA components; ``export.rig_targets``), without the capture animation.
- A humanoid: VRM 1.0 requires 15 bones (hips, spine, head, arms, hands, legs, feet) even for a
  head. The head bone sits at the neck (under the head's centre) and carries the mesh, so a
  consumer turning the head turns the character; the other bones are empty nodes in a rest
  T-pose below it (the character has no body to skin).
- Preset expressions (happy, angry, sad, relaxed, surprised, aa, ih, ou, ee, oh, blink,
  blinkLeft, blinkRight, lookUp/Down/Left/Right) bound to the rig's shapes by ``PRESET_RECIPES``:
  for each preset the first recipe whose shapes all exist (prompt-named shapes first for the
  emotions, ARKit combinations otherwise). A preset no recipe fits is left out and reported.
- Every ARKit shape as a custom expression of the same name ("perfect sync": apps that drive
  the 52 ARKit weights find them by name).

Left/right: VRM 1.0 avatars face +Z with their left at +X, the canonical frame's convention.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

# preset -> recipes, each [(shape, weight), ...]; the first recipe whose shapes all exist is used.
PRESET_RECIPES: dict[str, list[list[tuple[str, float]]]] = {
    "happy": [
        [("happy", 1.0)],
        [("smile", 1.0)],
        [("mouthSmileLeft", 1.0), ("mouthSmileRight", 1.0), ("cheekSquintLeft", 0.5), ("cheekSquintRight", 0.5)],
        [("mouthSmileLeft", 1.0), ("mouthSmileRight", 1.0)],
    ],
    "angry": [
        [("angry", 1.0)],
        [("frown", 1.0)],
        [("browDownLeft", 1.0), ("browDownRight", 1.0), ("mouthFrownLeft", 0.6), ("mouthFrownRight", 0.6)],
        [("mouthFrownLeft", 1.0), ("mouthFrownRight", 1.0), ("mouthPressLeft", 0.5), ("mouthPressRight", 0.5)],
    ],
    "sad": [
        [("sad", 1.0)],
        [("disappointed", 1.0)],
        [("mouthFrownLeft", 1.0), ("mouthFrownRight", 1.0), ("browInnerUp", 1.0)],
        [("mouthFrownLeft", 1.0), ("mouthFrownRight", 1.0), ("mouthShrugLower", 0.5)],
        [("mouthShrugLower", 1.0), ("mouthRollLower", 0.5)],
    ],
    "relaxed": [
        [("chill", 1.0)],
        [("mouthSmileLeft", 0.4), ("mouthSmileRight", 0.4), ("eyeBlinkLeft", 0.3), ("eyeBlinkRight", 0.3)],
        [("smile", 0.4), ("blink", 0.3)],
    ],
    "surprised": [
        [("surprised", 1.0)],
        [("eyeWideLeft", 1.0), ("eyeWideRight", 1.0), ("jawOpen", 0.5)],
        [("brow_up", 1.0), ("jaw_open", 0.5)],
        [("jawOpen", 0.6), ("mouthFunnel", 0.4)],
    ],
    "aa": [[("jawOpen", 1.0)], [("jaw_open", 1.0)]],
    "ih": [
        [("jawOpen", 0.25), ("mouthSmileLeft", 0.5), ("mouthSmileRight", 0.5)],
        [("jaw_open", 0.25), ("smile", 0.5)],
    ],
    "ou": [[("mouthPucker", 1.0), ("jawOpen", 0.15)], [("mouthFunnel", 0.8), ("jawOpen", 0.2)], [("jaw_open", 0.3)]],
    "ee": [
        [("mouthStretchLeft", 0.8), ("mouthStretchRight", 0.8), ("jawOpen", 0.2)],
        [("mouthSmileLeft", 0.6), ("mouthSmileRight", 0.6), ("jawOpen", 0.2)],
        [("smile", 0.6), ("jaw_open", 0.2)],
    ],
    "oh": [[("mouthFunnel", 1.0), ("jawOpen", 0.4)], [("jawOpen", 0.6), ("mouthPucker", 0.5)], [("jaw_open", 0.6)]],
    "blink": [
        [("eyeBlinkLeft", 1.0), ("eyeBlinkRight", 1.0)],
        [("blink", 1.0)],
        [("blink_left", 1.0), ("blink_right", 1.0)],
    ],
    "blinkLeft": [[("eyeBlinkLeft", 1.0)], [("blink_left", 1.0)]],
    "blinkRight": [[("eyeBlinkRight", 1.0)], [("blink_right", 1.0)]],
    "lookUp": [[("eyeLookUpLeft", 1.0), ("eyeLookUpRight", 1.0)], [("look_up", 1.0)]],
    "lookDown": [[("eyeLookDownLeft", 1.0), ("eyeLookDownRight", 1.0)], [("look_down", 1.0)]],
    # Looking to the character's left: the left eye turns out, the right eye turns in.
    "lookLeft": [[("eyeLookOutLeft", 1.0), ("eyeLookInRight", 1.0)], [("look_left", 1.0)]],
    "lookRight": [[("eyeLookInLeft", 1.0), ("eyeLookOutRight", 1.0)], [("look_right", 1.0)]],
}
PRESETS = list(PRESET_RECIPES)

# --license values -> licence document URLs (anything starting with http is taken as given). VRM 1.0's
# meta.licenseUrl is always the VRM Public License (its usage fields say what is allowed, and
# three-vrm rejects any other URL there); another licence goes in meta.otherLicenseUrl.
VPL_URL = "https://vrm.dev/licenses/1.0/"
LICENSES = {
    "VPL-1.0": VPL_URL,
    "CC0-1.0": "https://creativecommons.org/publicdomain/zero/1.0/",
    "CC-BY-4.0": "https://creativecommons.org/licenses/by/4.0/",
    "CC-BY-SA-4.0": "https://creativecommons.org/licenses/by-sa/4.0/",
    "CC-BY-NC-4.0": "https://creativecommons.org/licenses/by-nc/4.0/",
    "CC-BY-NC-SA-4.0": "https://creativecommons.org/licenses/by-nc-sa/4.0/",
    "CC-BY-ND-4.0": "https://creativecommons.org/licenses/by-nd/4.0/",
}
# What each licence allows, in VRM meta terms (open licences allow everyone everything they grant).
_OPEN = {
    "avatarPermission": "everyone",
    "commercialUsage": "corporation",
    "allowRedistribution": True,
    "modification": "allowModificationRedistribution",
    "creditNotation": "required",
}
LICENSE_META = {
    "CC0-1.0": {**_OPEN, "creditNotation": "unnecessary"},
    "CC-BY-4.0": _OPEN,
    "CC-BY-SA-4.0": _OPEN,
    "CC-BY-NC-4.0": {**_OPEN, "commercialUsage": "personalNonProfit"},
    "CC-BY-NC-SA-4.0": {**_OPEN, "commercialUsage": "personalNonProfit"},
    "CC-BY-ND-4.0": {**_OPEN, "modification": "prohibited"},
}
# Conservative VRM defaults for a licence we cannot read (VRM 1.0's own defaults).
_CLOSED = {
    "avatarPermission": "onlyAuthor",
    "commercialUsage": "personalNonProfit",
    "allowRedistribution": False,
    "modification": "prohibited",
    "creditNotation": "required",
}


def license_url(license: str) -> str:
    """URL of a licence given as an id of LICENSES or a URL (UserError otherwise)."""
    from t2bs.errors import UserError

    if license in LICENSES:
        return LICENSES[license]
    if license.startswith(("http://", "https://")):
        return license
    raise UserError(f"--license {license!r}: use one of {', '.join(LICENSES)} or a URL of the licence text")


def bind_presets(names: list[str]) -> tuple[dict[str, list[tuple[str, float]]], list[str]]:
    """(preset -> [(shape, weight)] bound, presets left unbound) for a rig with morph targets ``names``."""
    have = set(names)
    bound, missing = {}, []
    for preset, recipes in PRESET_RECIPES.items():
        recipe = next((r for r in recipes if all(s in have for s, _ in r)), None)
        if recipe is None:
            missing.append(preset)
        else:
            bound[preset] = recipe
    return bound, missing


# Humanoid bones VRM 1.0 requires: name -> (parent, offset from the parent in units of the head height).
_BONES = {
    "hips": (None, (0.0, -2.4, 0.0)),
    "spine": ("hips", (0.0, 0.8, 0.0)),
    "head": ("spine", (0.0, 1.6, 0.0)),
    "leftUpperArm": ("spine", (0.7, 1.2, 0.0)),
    "leftLowerArm": ("leftUpperArm", (1.0, 0.0, 0.0)),
    "leftHand": ("leftLowerArm", (1.0, 0.0, 0.0)),
    "rightUpperArm": ("spine", (-0.7, 1.2, 0.0)),
    "rightLowerArm": ("rightUpperArm", (-1.0, 0.0, 0.0)),
    "rightHand": ("rightLowerArm", (-1.0, 0.0, 0.0)),
    "leftUpperLeg": ("hips", (0.4, -0.2, 0.0)),
    "leftLowerLeg": ("leftUpperLeg", (0.0, -1.6, 0.0)),
    "leftFoot": ("leftLowerLeg", (0.0, -1.6, 0.0)),
    "rightUpperLeg": ("hips", (-0.4, -0.2, 0.0)),
    "rightLowerLeg": ("rightUpperLeg", (0.0, -1.6, 0.0)),
    "rightFoot": ("rightLowerLeg", (0.0, -1.6, 0.0)),
}


def export_vrm(
    model,
    character,
    path: str | os.PathLike,
    name: str,
    authors: list[str],
    license: str,
    arkit=None,
    version: str = "1",
) -> tuple[Path, dict]:
    """Write the rig as a VRM 1.0 file; returns (path, {"presets": bound, "unbound": [...], "custom": [...]})."""
    import pygltflib

    from t2bs.blendshapes.export import rig_mesh
    from t2bs.errors import UserError
    from t2bs.geometry.io import _to_gltf
    from t2bs.project import atomic_path

    if not name.strip():
        raise UserError("VRM meta needs a name")
    if not authors or not all(a.strip() for a in authors):
        raise UserError("VRM meta needs at least one author (--author)")
    url = license_url(license)
    mesh = rig_mesh(model, character, arkit)
    names = mesh.morph_names
    gltf = _to_gltf(mesh, None)
    # Skeleton: the head bone at the neck carries the mesh node (offset back so vertices stay put).
    v = mesh.vertices.astype(np.float64)
    pivot = np.array([v[:, 0].mean(), v[:, 1].min(), v[:, 2].mean()])
    unit = float(v[:, 1].max() - v[:, 1].min())  # head height: scale of the stand-in body
    mesh_node = gltf.nodes[0]
    index = {}
    for bone, (parent, offset) in _BONES.items():  # parents come before children in _BONES
        index[bone] = len(gltf.nodes)
        # hips + spine + head offsets sum to 0: the head bone lands exactly on the pivot.
        base = pivot if parent is None else np.zeros(3)
        gltf.nodes.append(pygltflib.Node(name=bone, translation=[float(x) for x in base + unit * np.asarray(offset)]))
        if parent is not None:
            gltf.nodes[index[parent]].children = (gltf.nodes[index[parent]].children or []) + [index[bone]]
    mesh_node.translation = [float(-x) for x in pivot]
    gltf.nodes[index["head"]].children = (gltf.nodes[index["head"]].children or []) + [0]
    gltf.scenes = [pygltflib.Scene(nodes=[index["hips"]])]
    bound, unbound = bind_presets(names)

    def binds(recipe):
        return [{"node": 0, "index": names.index(s), "weight": float(w)} for s, w in recipe]

    preset = {
        p: {
            "morphTargetBinds": binds(r),
            "isBinary": False,
            "overrideBlink": "none",
            "overrideLookAt": "none",
            "overrideMouth": "none",
        }
        for p, r in bound.items()
    }
    # An emotion whose recipe closes the eyes itself blends with the blink presets instead of adding to them.
    for p in ("happy", "angry", "sad", "relaxed", "surprised"):
        if p in preset and any("Blink" in s or "blink" in s for s, _ in bound[p]):
            preset[p]["overrideBlink"] = "blend"
    custom_names = list(arkit.names) if arkit is not None else []
    custom = {n: {"morphTargetBinds": binds([(n, 1.0)]), "isBinary": False} for n in custom_names}
    meta = {
        "name": name,
        "version": version,
        "authors": authors,
        "licenseUrl": VPL_URL,
        **({"otherLicenseUrl": url} if url != VPL_URL else {}),
        **LICENSE_META.get(license, _CLOSED),
        "allowExcessivelyViolentUsage": False,
        "allowExcessivelySexualUsage": False,
        "allowPoliticalOrReligiousUsage": False,
        "allowAntisocialOrHateUsage": False,
    }
    if license not in LICENSES or license == "VPL-1.0":
        meta.update(_CLOSED)
    gltf.extensionsUsed = ["VRMC_vrm"]
    gltf.extensions = {
        "VRMC_vrm": {
            "specVersion": "1.0",
            "meta": meta,
            "humanoid": {"humanBones": {bone: {"node": index[bone]} for bone in _BONES}},
            "expressions": {"preset": preset, "custom": custom},
            "lookAt": {"type": "expression", "offsetFromHeadBone": [0.0, 0.6 * unit, 0.0]},
        }
    }
    path = Path(path)
    with atomic_path(path) as tmp:
        gltf.save_binary(str(tmp))
    return path, {"presets": {p: r for p, r in bound.items()}, "unbound": unbound, "custom": custom_names}
