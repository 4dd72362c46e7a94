"""model.glb opens in other tools: Khronos glTF validator (node) and three.js in headless Chromium."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from conftest import asset
from t2bs.blendshapes.export import export_glb, export_weights, rig_targets
from t2bs.blendshapes.model import build_model
from t2bs.blendshapes.semantic import semantic_shapes
from t2bs.shared_assets import shared_asset

REPO = Path(__file__).resolve().parents[1]
JS = REPO / "tools" / "js"
TURTLE = shared_asset("turtle.glb")


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """(model, character, path of model.glb) built from turtle captures of the video animator."""
    from t2bs.eval.bench_blendshapes import animator_captures
    from t2bs.geometry.io import load_mesh
    from t2bs.geometry.mesh import normalize

    asset("turtle.glb")  # skipped here when absent, a failure in CI
    mesh, _ = normalize(load_mesh(TURTLE))
    caps, expr = animator_captures(
        mesh,
        frames=10,
        expressions=["blinking", "smiling", "opening the mouth extremely wide", "shaking the head", "talking"],
    )
    model = build_model(mesh.vertices, caps, components=100)
    model.semantic_names, model.semantic_weights, model.semantic_sources = semantic_shapes(model, caps, expr)
    path = tmp_path_factory.mktemp("rig") / "model.glb"
    export_glb(model, mesh, path, capture="blinking-s0", arkit=_arkit(model, mesh))
    return model, mesh, path


def _arkit(model, mesh):
    from t2bs.face.arkit import derive_arkit_shapes
    from t2bs.face.landmarks import detect_landmarks

    lm, _ = detect_landmarks(mesh, "auto", model=model)
    return derive_arkit_shapes(
        model.neutral,
        model.basis,
        model.singular_values,
        mesh.faces,
        lm.vertex_ids,
        lm.eyeballs,
        lm.regions.get("mouth", {}).get("width_world"),
    )


def _exported(path):
    """Morph target names of an exported .glb, in file order."""
    from t2bs.geometry.io import load_mesh

    return load_mesh(path).morph_names


def test_glb_round_trip_targets_animation(rig):
    from t2bs.geometry.io import load_mesh

    from t2bs.blendshapes.model import VISIBLE_FRACTION
    from t2bs.face.arkit import ARKIT_NAMES

    model, mesh, path = rig
    back = load_mesh(path)
    arkit = _arkit(model, mesh)
    names, offsets, scale = rig_targets(model, arkit)
    keep = model.visible_components()
    # ARKit names first (Apple's spelling, in ARKit order), then the prompt-named shapes, then visible PCs.
    assert list(back.morph_targets) == names == arkit.names + model.semantic_names + [model.names[k] for k in keep]
    assert {"eyeBlinkLeft", "eyeBlinkRight", "jawOpen"} <= set(arkit.names) and set(arkit.names) <= set(ARKIT_NAMES)
    assert "jaw_open" in names and "blink" in names
    assert 0 < len(keep) < model.num_components  # the turtle's captures leave invisible components
    np.testing.assert_allclose(back.vertices, model.neutral, atol=1e-6)
    np.testing.assert_allclose(
        offsets[names.index("jawOpen")], model.offsets(arkit.weights[arkit.names.index("jawOpen")]), atol=1e-6
    )
    # Exported weights (scaled targets) pose the same mesh as the basis weights, within -1..1, up to
    # the dropped components, each below VISIBLE_FRACTION of the diagonal.
    w = model.capture_weights["smiling-s0"]
    ew = export_weights(model, w, arkit)
    assert np.abs(ew).max() <= 1 + 1e-6 and ew.shape[1] == len(names)
    posed = back.vertices + np.einsum("tm,mnc->tnc", ew, np.stack(list(back.morph_targets.values())))
    drop = np.setdiff1d(np.arange(model.num_components), keep)
    bound = VISIBLE_FRACTION * mesh.bbox_diagonal() * len(drop) + 1e-4
    assert np.abs(posed - model.vertices(w)).max() < bound
    np.testing.assert_allclose(posed, model.vertices(w * np.isin(np.arange(model.num_components), keep)), atol=1e-4)
    import pygltflib

    gltf = pygltflib.GLTF2().load(str(path))
    assert gltf.meshes[0].weights == [0.0] * len(names)  # opens at the neutral pose
    assert len(gltf.animations) == 1 and gltf.animations[0].channels[0].target.path == "weights"


def _node_modules() -> Path:
    from browser_page import node_modules

    return node_modules()


def test_khronos_gltf_validator_reports_no_errors(rig):
    _node_modules()
    _, _, path = rig
    proc = subprocess.run(
        ["node", str(JS / "validate_glb.mjs"), str(path)], capture_output=True, text=True, timeout=120
    )
    report = json.loads(proc.stdout)
    assert proc.returncode == 0 and report["errors"] == 0, report["messages"]
    assert report["info"]["animationCount"] == 1


def test_validator_script_catches_a_broken_file(tmp_path, rig):
    _node_modules()
    _, _, path = rig
    broken = tmp_path / "broken.glb"
    data = bytearray(path.read_bytes())
    broken.write_bytes(bytes(data[: len(data) // 2]))  # truncated binary chunk
    proc = subprocess.run(
        ["node", str(JS / "validate_glb.mjs"), str(broken)], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 1 and json.loads(proc.stdout)["errors"] > 0


def test_three_js_loads_the_rig_in_headless_chromium(rig, tmp_path):
    import base64

    from browser_page import run_page

    model, _, path = rig
    result = run_page(
        "three_check.html",
        {f".test-{tmp_path.name}.glb": path},
        f"glb=.test-{tmp_path.name}.glb&shot=jawOpen",
        tmp_path,
    )
    assert result["ok"], result
    names = _exported(path)
    (mesh,) = result["meshes"]
    assert mesh["morphTargetInfluences"] == len(names) == mesh["morphPositions"]
    assert mesh["targetNames"] == names and mesh["influencesAllZero"] and mesh["textured"]
    assert names[0] == "eyeBlinkLeft" and "jawOpen" in result["dictionaries"][0]  # morphTargetDictionary: ARKit names
    assert mesh["vertices"] == model.num_vertices
    assert result["clips"][0]["name"] == "blinking-s0" and result["mixerOk"] is True
    # WebGL screenshots: jawOpen at 1 visibly changes the face (the mouth opens) and nothing else is lost.
    shot = result["screenshots"]
    assert (
        shot["characterPixels"] > 3000
        and 0.01 * shot["characterPixels"] < shot["changedPixels"] < 0.5 * shot["characterPixels"]
    )
    for key in ("neutral", "posed"):
        (tmp_path / f"three_jawOpen_{key}.png").write_bytes(base64.b64decode(shot[key].split(",", 1)[1]))


def test_usd_export(rig, tmp_path):
    pxr = pytest.importorskip("pxr", reason="usd-core is optional (pip install usd-core)")
    from pxr import Usd, UsdSkel

    from t2bs.blendshapes.export import export_usd

    model, mesh, _ = rig
    path = export_usd(model, mesh, tmp_path / "model.usda", capture="blinking-s0")
    stage = Usd.Stage.Open(str(path))
    binding = UsdSkel.BindingAPI(stage.GetPrimAtPath("/Character/Mesh"))
    names = binding.GetBlendShapesAttr().Get()
    assert list(names) == rig_targets(model)[0]
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/Character/Skel/Anim"))
    assert len(anim.GetBlendShapeWeightsAttr().GetTimeSamples()) == len(model.capture_weights["blinking-s0"])
    assert pxr is not None


# ------------------------------------------------------------------- what consumers showed (issue 38)


def _raw_accessor(path, index):
    import pygltflib

    from t2bs.geometry.io import _read_accessor

    gltf = pygltflib.GLTF2().load(str(path))
    return gltf, _read_accessor(gltf, [gltf.binary_blob()], index)


def test_color_0_is_linear_and_reads_back_as_display_colours(tmp_path):
    from t2bs.geometry.io import load_mesh, save_mesh
    from t2bs.geometry.mesh import Mesh

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32)
    f = np.array([[0, 1, 2], [1, 3, 2]], np.int32)
    srgb = np.array([[0.5, 0.5, 0.5], [1.0, 0.0, 0.02], [0.8, 0.6, 0.2], [0.04045, 0.2, 0.9]], np.float32)
    path = save_mesh(Mesh(v, f, vertex_colors=srgb), tmp_path / "c.glb")
    gltf, _ = _raw_accessor(path, 0)
    raw = _raw_accessor(path, gltf.meshes[0].primitives[0].attributes.COLOR_0)[1]
    # sRGB 0.5 is linear 0.2140 (IEC 61966-2-1); 0.04045 is the curve's knee, 0.04045 / 12.92.
    np.testing.assert_allclose(raw[0, :3], 0.21404, atol=1e-4)
    np.testing.assert_allclose(raw[3, 0], 0.04045 / 12.92, atol=1e-6)
    np.testing.assert_allclose(raw[1, :3], [1.0, 0.0, 0.02 / 12.92], atol=1e-6)
    np.testing.assert_allclose(load_mesh(path).vertex_colors, srgb, atol=1e-5)


def test_morph_targets_carry_normal_deltas(rig):
    from t2bs.geometry.mesh import vertex_normals

    model, mesh, path = rig
    gltf, _ = _raw_accessor(path, 0)
    from t2bs.geometry.io import load_mesh

    prim = gltf.meshes[0].primitives[0]
    back = load_mesh(path)
    names, offsets = back.morph_names, np.stack(list(back.morph_targets.values()))
    n0 = _raw_accessor(path, prim.attributes.NORMAL)[1]
    moved = 0
    for k in (names.index("jawOpen"), names.index("jaw_open"), names.index("pc000")):
        target = prim.targets[k]
        assert set(target) == {"POSITION", "NORMAL"}
        delta = _raw_accessor(path, target["NORMAL"])[1]
        # What a consumer does: base normal + weight * delta, renormalised = the posed mesh's normal.
        blended = n0 + delta
        blended /= np.linalg.norm(blended, axis=1, keepdims=True)
        true = vertex_normals(model.neutral + offsets[k], mesh.faces)
        ok = np.linalg.norm(true, axis=1) > 0.5
        np.testing.assert_allclose(blended[ok], true[ok], atol=1e-4)
        moved += int((np.abs(delta).max(1) > 1e-3).sum())
    assert moved > 0  # the shapes really turn some normals


def test_usd_units_extent_and_sparse_point_indices(rig, tmp_path):
    pytest.importorskip("pxr", reason="usd-core is optional (pip install usd-core)")
    from pxr import Usd, UsdGeom, UsdSkel

    from t2bs.blendshapes.export import export_usd

    model, mesh, _ = rig
    path = export_usd(model, mesh, tmp_path / "model.usda", capture="blinking-s0")
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0 and "metersPerUnit = 1" in path.read_text()
    geom = UsdGeom.Mesh(stage.GetPrimAtPath("/Character/Mesh"))
    extent = np.asarray(geom.GetExtentAttr().Get())
    names, offsets, _ = rig_targets(model)
    reach = np.abs(offsets).max(0)  # [N, 3]
    assert (extent[0] <= (model.neutral - reach).min(0) + 1e-6).all() and (
        extent[1] >= (model.neutral + reach).max(0) - 1e-6
    ).all()
    binding = UsdSkel.BindingAPI(geom.GetPrim())
    for token, off in zip(binding.GetBlendShapesAttr().Get(), offsets):
        shape = UsdSkel.BlendShape(stage.GetPrimAtPath(f"/Character/Mesh/{token}"))
        idx = shape.GetPointIndicesAttr().Get()
        got = np.zeros_like(off)
        if idx is None:  # dense: no repeated 0..N-1 list
            got[:] = np.asarray(shape.GetOffsetsAttr().Get())
        else:
            assert len(idx) < len(off)
            got[np.asarray(idx)] = np.asarray(shape.GetOffsetsAttr().Get())
        np.testing.assert_allclose(got, off, atol=1e-6)
    text = path.read_text()
    assert text.count("pointIndices") < len(names)


def test_usd_sparse_shape_lists_only_moving_points(tmp_path):
    pytest.importorskip("pxr", reason="usd-core is optional (pip install usd-core)")
    from pxr import Usd, UsdGeom, UsdSkel

    from t2bs.blendshapes.export import export_usd
    from t2bs.blendshapes.model import BlendshapeModel
    from t2bs.geometry.mesh import Mesh

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32)
    basis = np.zeros((1, 4, 3), np.float32)
    basis[0, 3, 2] = 1.0  # moves vertex 3 only
    model = BlendshapeModel(v, basis, np.ones(1), ["pc000"], capture_weights={"a": np.array([[0.5]], np.float32)})
    srgb = np.full((4, 3), 0.5, np.float32)
    path = export_usd(
        model, Mesh(v, np.array([[0, 1, 2], [1, 3, 2]], np.int32), vertex_colors=srgb), tmp_path / "m.usda"
    )
    stage = Usd.Stage.Open(str(path))
    shape = UsdSkel.BlendShape(stage.GetPrimAtPath("/Character/Mesh/pc000"))
    assert list(shape.GetPointIndicesAttr().Get()) == [3]
    np.testing.assert_allclose(np.asarray(shape.GetOffsetsAttr().Get()), [[0, 0, 0.5]], atol=1e-6)
    color = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Character/Mesh")).GetPrimvar("displayColor").Get()
    np.testing.assert_allclose(np.asarray(color), 0.21404, atol=1e-4)  # linear, like glTF


def test_usd_binary_is_the_default_and_reads_back(rig, tmp_path):
    pytest.importorskip("pxr", reason="usd-core is optional (pip install usd-core)")
    from pxr import Usd, UsdSkel

    from t2bs.blendshapes.export import export_usd

    model, mesh, _ = rig
    text = export_usd(model, mesh, tmp_path / "m.usda")
    binary = export_usd(model, mesh, tmp_path / "m.usdc")
    assert binary.read_bytes()[:8] == b"PXR-USDC" and binary.stat().st_size < 0.5 * text.stat().st_size
    a, b = Usd.Stage.Open(str(text)), Usd.Stage.Open(str(binary))
    names = rig_targets(model)[0]
    token = UsdSkel.BindingAPI(b.GetPrimAtPath("/Character/Mesh")).GetBlendShapesAttr().Get()[0]
    for stage in (a, b):
        shape = UsdSkel.BlendShape(stage.GetPrimAtPath(f"/Character/Mesh/{token}"))
        assert len(shape.GetOffsetsAttr().Get()) in (model.num_vertices, len(shape.GetPointIndicesAttr().Get() or []))
    assert len(UsdSkel.BindingAPI(b.GetPrimAtPath("/Character/Mesh")).GetBlendShapesAttr().Get()) == len(names)
