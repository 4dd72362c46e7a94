"""Export a blendshape model as glTF morph targets (and optionally USD blend shapes).

glTF (``model.glb``): the neutral textured character (``t2bs.geometry.io.save_mesh``), morph
targets in the order a user looks for them: the ARKit-named shapes (``t2bs.face.arkit``, Apple's
names), then the prompt-named shapes, then the PCA components that move something visible (the
exported target's largest vertex offset is at least ``model.VISIBLE_FRACTION`` of the bounding-box diagonal,
about one pixel of the 512-px frontal render; ``model.npz`` keeps the full basis). build_model took each
frame's head motion out first (the animation replays the expression; the head track stays in model.npz)
and made each component's observed extreme positive, so weight 1 is the most the captures showed. Names in
``mesh.extras.targetNames`` (what three.js and Blender read), default weights 0 (= the neutral
pose, see model.py), and an animation that replays one capture. The PCA targets are stored
*scaled*: target_k = basis_k * range_k with range_k = the largest |weight| of component k over the captures, so every captured
frame lies within weights -1..1 of the sliders (an orthonormal basis vector has unit norm over all
3N coordinates, which would put useful weights in the tens or hundreds). Named shapes are stored
at full strength (weight 1 = the peak of the expression).

USD (``model.usdc``, binary; ``.usda`` for text; needs ``usd-core``): a UsdSkel skeleton-less
blend shape rig — a Mesh bound to a SkelRoot/Skeleton with one UsdSkel.BlendShape per target and a SkelAnimation of the weights.
The stage states metersPerUnit = 1 (glTF's unit; without it tools assume centimetres and show a
character 100x too small), the mesh carries its extent (the rest pose's box grown by every
target's reach, so culling never clips a pose), displayColor is linear like glTF's COLOR_0, and a
blend shape lists pointIndices only when it moves fewer than all points (UsdSkel applies offsets
to every point when the list is absent; a full 0..N-1 list in every shape made 66 MB of text). The
stage writes the binary crate format: the demo fox's 63 dense shapes x 23,550 points are 70 MB as
text and 18.5 MB as .usdc.
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from t2bs.blendshapes.model import BlendshapeModel
from t2bs.geometry.mesh import Mesh


def target_ranges(model: BlendshapeModel) -> np.ndarray:
    """[K] scale of each exported PCA target: max |weight| over the captures (fallback: s / sqrt(frames))."""
    if model.capture_weights:
        w = np.concatenate([np.abs(np.asarray(v)) for v in model.capture_weights.values()])
        rng = w.max(0)
    else:
        frames = max(int(model.meta.get("frames", 1)), 1)
        rng = np.asarray(model.singular_values) / np.sqrt(frames)
    return np.maximum(rng, 1e-9).astype(np.float64)


def _named(arkit) -> tuple[list[str], np.ndarray | None]:
    """(names, weights [S, K]) of ARKit shapes given as an ``ArkitShapes`` or None."""
    if arkit is None or not len(arkit.names):
        return [], None
    return list(arkit.names), np.asarray(arkit.weights, np.float64)


def rig_targets(model: BlendshapeModel, arkit=None) -> tuple[list[str], np.ndarray, np.ndarray]:
    """(names [M], offsets [M, N, 3], per-target scale [K'] of the kept PCA part) as exported:
    ARKit shapes (``arkit``: ``t2bs.face.arkit.ArkitShapes`` or None), named shapes, visible PCs."""
    keep = model.visible_components()
    rng = target_ranges(model)[keep]
    pcs = model.basis[keep].astype(np.float64) * rng[:, None, None]
    sem = model.semantic_offsets().astype(np.float64)
    ark_names, ark_w = _named(arkit)
    ark = model.offsets(ark_w) if ark_w is not None else np.zeros((0, *model.neutral.shape))
    names = ark_names + list(model.semantic_names) + [model.names[k] for k in keep]
    return names, np.concatenate([ark, sem, pcs]).astype(np.float32), rng


def export_weights(model: BlendshapeModel, weights: np.ndarray, arkit=None) -> np.ndarray:
    """Basis weights [T, K] -> exported target weights [T, M] (named shapes at 0, invisible PCs dropped)."""
    keep = model.visible_components()
    w = np.asarray(weights, np.float64)[:, keep] / target_ranges(model)[keep]
    named = len(_named(arkit)[0]) + len(model.semantic_names)
    return np.concatenate([np.zeros((len(w), named)), w], 1).astype(np.float32)


def rig_mesh(model: BlendshapeModel, character: Mesh, arkit=None) -> Mesh:
    """The character at the model's neutral with the model's targets replacing its own."""
    if character.vertices.shape != model.neutral.shape:
        raise ValueError(f"character has {character.num_vertices} vertices, model {model.num_vertices}")
    names, offsets, _ = rig_targets(model, arkit)
    return replace(character, vertices=model.neutral.astype(np.float32), morph_targets=dict(zip(names, offsets)))


def export_glb(
    model: BlendshapeModel,
    character: Mesh,
    path: str | os.PathLike,
    capture: str | None = None,
    fps: float = 8.0,
    arkit=None,
) -> Path:
    """Write ``model`` as a .glb; ``capture`` (a video id of the model) becomes its animation;
    ``arkit`` (``ArkitShapes``) adds the ARKit-named shapes first."""
    from t2bs.geometry.io import save_mesh

    mesh = rig_mesh(model, character, arkit)
    animation = None
    if capture is not None and capture in model.capture_weights:
        w = export_weights(model, model.capture_weights[capture], arkit)
        animation = {"times": np.arange(len(w), dtype=np.float32) / fps, "weights": w, "name": capture}
    return save_mesh(mesh, path, animation=animation)


def export_usd(
    model: BlendshapeModel,
    character: Mesh,
    path: str | os.PathLike,
    capture: str | None = None,
    fps: float = 8.0,
    arkit=None,
) -> Path:
    """Write ``model`` as USD (UsdSkel blend shapes); ImportError if usd-core is not installed."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt  # noqa: F401

    from t2bs.geometry.io import srgb_to_linear
    from t2bs.project import atomic_path

    path = Path(path)
    names, offsets, _ = rig_targets(model, arkit)
    tokens = [_usd_token(n) for n in names]
    with atomic_path(path) as tmp:
        tmp_usda = tmp.with_suffix(path.suffix)
        stage = Usd.Stage.CreateNew(str(tmp_usda))
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        stage.SetTimeCodesPerSecond(fps)
        root = UsdSkel.Root.Define(stage, "/Character")
        stage.SetDefaultPrim(root.GetPrim())
        mesh = UsdGeom.Mesh.Define(stage, "/Character/Mesh")
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(model.neutral.astype(np.float32)))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(character.faces), 3, np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(character.faces.reshape(-1).astype(np.int32)))
        mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        mesh.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(rig_extent(model.neutral, offsets)))
        rgb = srgb_to_linear(character.vertex_rgb())
        UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
            "displayColor", Sdf.ValueTypeNames.Color3fArray, UsdGeom.Tokens.vertex
        ).Set(Vt.Vec3fArray.FromNumpy(rgb))
        skel = UsdSkel.Skeleton.Define(stage, "/Character/Skel")
        skel.CreateJointsAttr([])
        binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
        binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
        binding.CreateBlendShapesAttr(tokens)
        targets = []
        for token, off in zip(tokens, offsets):
            shape = UsdSkel.BlendShape.Define(stage, f"/Character/Mesh/{token}")
            moving = np.nonzero(np.abs(off).max(1) > 0)[0].astype(np.int32)
            if len(moving) < len(off):  # sparse shape: only the points it moves
                shape.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(off[moving].astype(np.float32)))
                shape.CreatePointIndicesAttr(Vt.IntArray.FromNumpy(moving))
            else:  # dense shape: no index list, UsdSkel then applies the offsets to every point in order
                shape.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(off.astype(np.float32)))
            targets.append(shape.GetPath())
        binding.CreateBlendShapeTargetsRel().SetTargets(targets)
        anim = UsdSkel.Animation.Define(stage, "/Character/Skel/Anim")
        anim.CreateBlendShapesAttr(tokens)
        weights_attr = anim.CreateBlendShapeWeightsAttr()
        weights_attr.Set(Vt.FloatArray.FromNumpy(np.zeros(len(tokens), np.float32)))
        if capture is not None and capture in model.capture_weights:
            w = export_weights(model, model.capture_weights[capture], arkit)
            for t, row in enumerate(w):
                weights_attr.Set(Vt.FloatArray.FromNumpy(row), Usd.TimeCode(t))
            stage.SetStartTimeCode(0)
            stage.SetEndTimeCode(len(w) - 1)
        UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])
        stage.GetRootLayer().Save()
        os.replace(tmp_usda, tmp)
    return path


def rig_extent(neutral: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """[2, 3] box holding the rest pose and each target applied alone at weights -1..1."""
    v = np.asarray(neutral, np.float64)
    reach_lo = np.minimum(offsets, 0).min(0) if len(offsets) else 0.0  # [N, 3] along each axis
    reach_hi = np.maximum(offsets, 0).max(0) if len(offsets) else 0.0
    span = np.maximum(np.abs(reach_lo), reach_hi)  # weights may be negative too
    return np.stack([(v - span).min(0), (v + span).max(0)]).astype(np.float32)


def _usd_token(name: str) -> str:
    import re

    token = re.sub(r"[^A-Za-z0-9_]", "_", name)
    return token if token and not token[0].isdigit() else f"_{token}"
