"""ARKit-52 named shapes derived through retargeting (issue 38), against facecap's own ARKit shapes."""

from __future__ import annotations


import numpy as np
import pytest
from conftest import asset
from t2bs.face.arkit import (
    ARKIT_GROUPS,
    ARKIT_NAMES,
    arkit_name,
    derive_arkit_shapes,
    load_reference,
    outside_fraction,
)
from t2bs.face.solve import observed_range
from t2bs.shared_assets import shared_asset

FACECAP = shared_asset("facecap.glb")


def test_names_and_reference_table():
    assert len(ARKIT_NAMES) == 52 == len(set(ARKIT_NAMES))
    assert list(ARKIT_GROUPS) == ["eyes", "brows", "jaw", "mouth", "cheeks", "nose", "tongue"]
    assert arkit_name("eyeBlink_L") == arkit_name("EyeBlinkLeft") == "eyeBlinkLeft"  # ICT/facecap, Live Link Face
    assert arkit_name("mouthSmile_R") == "mouthSmileRight" and arkit_name("TongueOut") == "tongueOut"
    assert arkit_name("HeadYaw") is None and arkit_name("blink") is None
    neutral, shapes = load_reference()
    assert neutral.shape == (20, 3) and len(shapes) == 51 and "tongueOut" not in shapes
    # The subject's left eye is at +X (68-scheme 42-47 = positions 6-11), and eyeBlinkLeft closes it alone.
    assert neutral[6:12, 0].min() > 0 > neutral[0:6, 0].max()
    blink = shapes["eyeBlinkLeft"]
    assert np.abs(blink[6:12]).max() > 0.5 and np.abs(blink[:6]).max() < 1e-3
    assert blink[7, 1] < -0.3 and blink[8, 1] < -0.3  # upper lid (43, 44) comes down
    assert shapes["jawOpen"][18, 1] < -1.0  # lower inner lip (66) drops


@pytest.fixture(scope="module")
def facecap():
    from t2bs.geometry.io import load_mesh
    from t2bs.geometry.mesh import normalize
    from t2bs.eval.bench_retarget import morph_model
    from t2bs.face.landmarks import detect_landmarks

    asset("facecap.glb")  # skipped here when absent, a failure in CI
    mesh, _ = normalize(load_mesh(FACECAP))
    model = morph_model(mesh)
    lm, _ = detect_landmarks(mesh, "motion", model=model)
    return mesh, model, lm


def _derive(model, mesh, lm, observed=None):
    return derive_arkit_shapes(
        model.neutral,
        model.basis,
        model.singular_values,
        mesh.faces,
        lm.vertex_ids,
        lm.eyeballs,
        lm.regions.get("mouth", {}).get("width_world"),
        observed=observed,
    )


def _blink_and_jaw_model(mesh):
    """A model of two captures of facecap: both eyes blinking together, and the jaw opening (12 frames each)."""
    from t2bs.blendshapes.model import build_model

    v0 = mesh.vertices.astype(np.float64)
    ramp = np.sin(np.linspace(0, np.pi, 12))[:, None, None]
    both = mesh.morph_targets["eyeBlink_L"] + mesh.morph_targets["eyeBlink_R"]
    caps = {"blink": v0 + ramp * both, "jaw": v0 + ramp * mesh.morph_targets["jawOpen"]}
    return build_model(mesh.vertices, {k: v.astype(np.float32) for k, v in caps.items()})


def test_derived_shapes_match_facecaps_own(facecap):
    mesh, model, lm = facecap
    shapes = _derive(model, mesh, lm)
    assert set(shapes.report) == set(ARKIT_NAMES)
    assert {"eyeBlinkLeft", "eyeBlinkRight", "jawOpen", "mouthSmileLeft", "mouthSmileRight", "mouthPucker"} <= set(
        shapes.names
    )
    assert not shapes.report["browInnerUp"]["present"] and "cannot see" in shapes.report["browInnerUp"]["why"]
    assert not shapes.report["tongueOut"]["present"] and "reference" in shapes.report["tongueOut"]["why"]
    truth = {arkit_name(n): d.reshape(-1).astype(np.float64) for n, d in mesh.morph_targets.items()}
    cos = {}
    for name, w in zip(shapes.names, shapes.weights):
        d = model.offsets(w).reshape(-1)
        cos[name] = float(d @ truth[name] / (np.linalg.norm(d) * np.linalg.norm(truth[name])))
    assert np.median(list(cos.values())) > 0.68  # measured 0.724 (benchmarks/arkit_facecap.py)
    assert cos["jawOpen"] > 0.95 and cos["eyeBlinkLeft"] > 0.7 and cos["mouthSmileLeft"] > 0.75
    # Left is the character's own left (+X): eyeBlinkLeft moves the +X eye far more than the -X one.
    d = np.linalg.norm(model.offsets(shapes.weights[shapes.names.index("eyeBlinkLeft")]), axis=1)
    x = model.neutral[:, 0]
    assert d[x > 0].max() > 5 * d[x < 0].max()


def test_a_rig_that_only_blinks_both_eyes_has_no_one_eyed_blink(facecap):
    mesh, _, lm = facecap
    shapes = _derive(_blink_and_jaw_model(mesh), mesh, lm)
    assert "jawOpen" in shapes.names
    for side in ("eyeBlinkLeft", "eyeBlinkRight"):
        r = shapes.report[side]
        assert not r["present"] and "captures cannot express" in r["why"] and r["crosstalk"] > 0.6  # both eyes move


def test_shapes_that_run_a_capture_backwards_are_absent(facecap):
    """Captures that only blink and open the jaw: the landmark solve reaches mouthClose, mouthRollLower and
    mouthShrugLower by closing the jaw past rest, where no capture went; with the captured range given they are
    reported absent ("beyond the captures"), jawOpen (inside it) stays."""
    mesh, _, lm = facecap
    model = _blink_and_jaw_model(mesh)
    unchecked = _derive(model, mesh, lm)
    checked = _derive(model, mesh, lm, observed_range(model.capture_weights))
    backwards = {"mouthClose", "mouthRollLower", "mouthShrugLower"}
    assert backwards <= set(unchecked.names) and not backwards & set(checked.names)
    assert set(checked.names) == set(unchecked.names) - backwards and "jawOpen" in checked.names
    for name in backwards:
        r = checked.report[name]
        assert not r["present"] and r["why"].startswith("beyond the captures") and r["outside"] > 0.99
    assert checked.report["jawOpen"]["outside"] < 0.01


def test_outside_fraction_is_the_share_of_motion_beyond_the_captured_range():
    basis = np.zeros((2, 3, 3))
    basis[0, 0, 1] = 1.0  # component 0 moves vertex 0 up
    basis[1, 1, 0] = 1.0  # component 1 moves vertex 1 sideways
    observed = np.array([[0.0, -1.0], [2.0, 1.0]])  # component 0 seen in [0, 2], component 1 in [-1, 1]
    assert outside_fraction(basis, np.array([1.5, 0.5]), observed) == 0.0
    assert outside_fraction(basis, np.array([-1.0, 0.0]), observed) == 1.0  # all of it backwards
    assert np.isclose(outside_fraction(basis, np.array([3.0, 0.0]), observed), 1.0 / 3.0)  # 1 of its 3 beyond
    assert np.isclose(outside_fraction(basis, np.array([1.0, -2.0]), observed), 0.5)  # vertex 1: 1 of 2
    caps = {"a": np.array([[0.0, 1.0], [2.0, -1.0]]), "b": np.array([[1.0, 0.5]])}
    assert np.array_equal(observed_range(caps), observed) and observed_range({}) is None


def test_report_lists_arkit_shapes_and_how_to_open_the_rig(tmp_path):
    from t2bs.pipeline import write_report
    from t2bs.project import Project, write_json
    from t2bs.face.arkit import ArkitShapes

    report = {"jawOpen": {"present": True, "why": "derived"}, "browInnerUp": {"present": False, "why": "cannot see it"}}
    write_json(tmp_path / "blendshapes" / "arkit.json", ArkitShapes(["jawOpen"], np.ones((1, 2)), report).to_dict())
    out = write_report(Project(tmp_path), "a fox", "quick", {"blendshapes": 1.0})
    assert out["blendshapes"]["arkit"] == ["jawOpen"] and out["blendshapes"]["arkit_absent"] == {
        "browInnerUp": "cannot see it"
    }
    md = (tmp_path / "report.md").read_text()
    assert "1 of the 52 present: jawOpen." in md and "![ARKit shapes](blendshapes/arkit_sheet.png)" in md
    assert "Blender: File > Import > glTF 2.0" in md and "--format vrm" in md and "t2bs view" in md
