"""The fox rig in the industry's formats (issue 38): a Live Link Face CSV drives it through its ARKit
shapes; VRM 1.0 export (VRMC_vrm meta, humanoid, presets + ARKit custom expressions); glb re-export."""

from __future__ import annotations

import csv
import json
import subprocess

import numpy as np
import pygltflib
import pytest
from typer.testing import CliRunner

from t2bs.blendshapes.vrm import PRESETS, VPL_URL, bind_presets
from t2bs.cli import app
from t2bs.errors import UserError
from t2bs.face.livelink import HEAD_COLUMNS, LIVE_LINK_ORDER, read_livelink_csv, write_livelink_csv


@pytest.fixture(scope="module")
def fox_project(tmp_path_factory):
    """A fox project: procedural character, a model of captures of its own rig controls, ARKit shapes."""
    from t2bs.blendshapes.model import save_model
    from t2bs.geometry.io import save_mesh
    from t2bs.project import Project, write_json
    from t2bs.face.arkit import project_arkit_shapes
    from t2bs.eval.bench_retarget import load_target, morph_model

    _, mesh, _ = load_target("procedural:a cartoon fox")
    root = tmp_path_factory.mktemp("fox")
    save_mesh(mesh, root / "character" / "mesh.glb")
    model = morph_model(mesh)
    save_model(model, root / "blendshapes" / "model.npz")
    shapes = project_arkit_shapes(root, model, Project(root).load_character())
    write_json(root / "blendshapes" / "arkit.json", shapes.to_dict())
    return root, model, shapes


def _capture(frames: int = 90, seed: int = 0):
    """60 Hz ARKit weights as the app records them: blinks, a jaw open, a smile, head turns."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / 60.0
    bump = lambda c, w: np.exp(-0.5 * ((t - c) / w) ** 2)  # noqa: E731
    weights = {
        name: np.clip(rng.normal(0.02, 0.01, frames), 0, 1)
        for name in [c for c in LIVE_LINK_ORDER if c not in HEAD_COLUMNS and not c.endswith(("Yaw", "Pitch", "Roll"))]
    }
    weights["EyeBlinkLeft"] = np.maximum(weights["EyeBlinkLeft"], bump(0.3, 0.05))
    weights["EyeBlinkRight"] = np.maximum(weights["EyeBlinkRight"], bump(0.3, 0.05))
    weights["JawOpen"] = 0.8 * bump(0.8, 0.2)
    weights["MouthSmileLeft"] = weights["MouthSmileRight"] = 0.6 * bump(1.1, 0.15)
    head = np.stack([0.3 * np.sin(2 * np.pi * t / 1.5), 0.1 * np.sin(2 * np.pi * t), 0.05 * t], 1)  # radians
    return t, weights, head


def test_reader_parses_the_apps_format(tmp_path):
    t, weights, head = _capture(30)
    path = write_livelink_csv(tmp_path / "take.csv", weights, t, head)
    header = path.read_text().splitlines()[0].split(",")
    assert header[:3] == ["Timecode", "BlendShapeCount", "EyeBlinkLeft"] and header[-1] == "RightEyeRoll"
    assert len(header) == 2 + 61
    cap = read_livelink_csv(path)
    assert cap.fps == 60 and len(cap.weights) == 52 and "eyeBlinkLeft" in cap.weights
    np.testing.assert_allclose(cap.times, t, atol=1e-3)
    np.testing.assert_allclose(cap.weights["jawOpen"], weights["JawOpen"], atol=1e-6)
    np.testing.assert_allclose(cap.head, head, atol=1e-6)


def _write_rows(path, rows):
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows(rows)
    return path


def test_bad_csvs_get_one_line(tmp_path):
    good = ["Timecode", "BlendShapeCount", "EyeBlinkLeft", "JawOpen"]
    cases = {
        "empty": ([], "empty CSV"),
        "header": ([["frame", "time", "jawOpen"], ["0", "0", "0.1"]], "not a Live Link Face CSV"),
        "noshape": ([["Timecode", "BlendShapeCount", "Foo"], ["00:00:00:01.000", "61", "0"]], "no ARKit blendshape"),
        "short": ([good, ["00:00:00:01.000", "61", "0.1"]], "line 2 has 3 values"),
        "nan": ([good, ["00:00:00:01.000", "61", "abc", "0.1"]], "EyeBlinkLeft = 'abc' is not a number"),
        "tc": ([good, ["1.5", "61", "0.1", "0.1"]], "timecode '1.5'"),
        "order": (
            [good, ["00:00:00:02.000", "61", "0", "0"], ["00:00:00:01.000", "61", "0", "0"]],
            "does not increase",
        ),
        "only": ([good], "header only"),
    }
    for name, (rows, message) in cases.items():
        with pytest.raises(UserError, match=message) as err:
            read_livelink_csv(_write_rows(tmp_path / f"{name}.csv", rows))
        assert "\n" not in str(err.value)


def test_csv_drives_the_fox(fox_project, tmp_path):
    from t2bs.geometry.io import _read_accessor

    root, model, shapes = fox_project
    assert {"eyeBlinkLeft", "eyeBlinkRight", "jawOpen"} <= set(shapes.names)
    t, weights, head = _capture(90)
    take = write_livelink_csv(tmp_path / "take.csv", weights, t, head)
    res = CliRunner().invoke(
        app, ["retarget", str(root), "--driver", str(take), "-o", str(tmp_path / "out"), "--size", "64"]
    )
    assert res.exit_code == 0, res.output
    assert "absent on this rig" in res.output  # brows etc. are said, not dropped silently
    with open(tmp_path / "out" / "weights.csv") as f:
        rows = list(csv.reader(f))
    header, data = rows[0], np.asarray(rows[1:], float)
    assert len(data) == 90 and header[2 : 2 + len(shapes.names)] == [n for n in shapes.names if n in header]
    for col, name in enumerate(header[2:-3], start=2):
        source = next(c for c in weights if c[0].lower() + c[1:] == name)
        np.testing.assert_allclose(data[:, col], weights[source], atol=1e-6)  # out = in on present shapes
    np.testing.assert_allclose(data[:, -3:], head, atol=1e-6)
    np.testing.assert_allclose(data[:, 1], t, atol=1e-3)
    # animation.glb: ARKit targets, the CSV weights, and the head rotation as node motion.
    gltf = pygltflib.GLTF2().load(str(tmp_path / "out" / "animation.glb"))
    blob = [gltf.binary_blob()]
    assert gltf.meshes[0].extras["targetNames"] == header[2:-3]
    (anim,) = gltf.animations
    paths = {c.target.path: c.sampler for c in anim.channels}
    assert set(paths) == {"weights", "rotation", "translation"}
    w = _read_accessor(gltf, blob, anim.samplers[paths["weights"]].output).reshape(90, -1)
    np.testing.assert_allclose(w, data[:, 2:-3], atol=1e-6)
    from scipy.spatial.transform import Rotation

    q = _read_accessor(gltf, blob, anim.samplers[paths["rotation"]].output)
    yaw, pitch, roll = Rotation.from_quat(q).as_euler("YXZ").T
    np.testing.assert_allclose(np.stack([yaw, pitch, roll], 1), head, atol=1e-5)
    assert (tmp_path / "out" / "preview.mp4").stat().st_size > 0


def test_csv_driver_needs_arkit_shapes(fox_project, tmp_path):
    import shutil

    root, _, _ = fox_project
    bare = tmp_path / "bare"
    shutil.copytree(root, bare)
    (bare / "blendshapes" / "arkit.json").unlink()
    t, weights, head = _capture(5)
    take = write_livelink_csv(tmp_path / "take.csv", weights, t, head)
    res = CliRunner().invoke(app, ["retarget", str(bare), "--driver", str(take)])
    assert res.exit_code != 0 and isinstance(res.exception, UserError) and "no ARKit shapes" in str(res.exception)


# --------------------------------------------------------------------------------------- VRM 1.0


@pytest.fixture(scope="module")
def vrm(fox_project, tmp_path_factory):
    root, model, shapes = fox_project
    path = tmp_path_factory.mktemp("vrm") / "fox.vrm"
    res = CliRunner().invoke(
        app,
        [
            "export",
            str(root),
            "--format",
            "vrm",
            "--license",
            "CC-BY-4.0",
            "--author",
            "Ada",
            "--name",
            "Foxy",
            "-o",
            str(path),
        ],
    )
    assert res.exit_code == 0, res.output
    return path, model, shapes, res.output


def test_vrm_extension_meta_humanoid_and_expressions(vrm):
    from t2bs.geometry.io import load_mesh

    path, model, shapes, output = vrm
    gltf = pygltflib.GLTF2().load_binary(str(path))
    assert gltf.extensionsUsed == ["VRMC_vrm"]
    ext = gltf.extensions["VRMC_vrm"]
    assert ext["specVersion"] == "1.0"
    meta = ext["meta"]
    assert meta["name"] == "Foxy" and meta["authors"] == ["Ada"] and meta["licenseUrl"] == VPL_URL
    assert (
        meta["otherLicenseUrl"] == "https://creativecommons.org/licenses/by/4.0/"
        and meta["commercialUsage"] == "corporation"
    )
    bones = ext["humanoid"]["humanBones"]
    assert len(bones) == 15 and {"hips", "spine", "head", "leftHand", "rightFoot"} <= set(bones)
    names = gltf.meshes[0].extras["targetNames"]
    assert names[: len(shapes.names)] == shapes.names  # ARKit shapes first
    preset, custom = ext["expressions"]["preset"], ext["expressions"]["custom"]
    assert set(preset) <= set(PRESETS) and list(custom) == shapes.names  # perfect sync: every ARKit shape by name

    def bound(expr):
        return {names[b["index"]]: b["weight"] for b in expr["morphTargetBinds"]}

    assert bound(preset["blink"]) == {"eyeBlinkLeft": 1.0, "eyeBlinkRight": 1.0}
    assert bound(preset["blinkLeft"]) == {"eyeBlinkLeft": 1.0} and bound(preset["aa"]) == {"jawOpen": 1.0}
    assert bound(custom["mouthFunnel"]) == {"mouthFunnel": 1.0}
    unbound = [p for p in PRESETS if p not in preset]
    assert unbound and f"left out): {', '.join(unbound)}" in output  # said, not hidden
    # The mesh lands where the rig is: head bone at the neck carries the mesh node back.
    np.testing.assert_allclose(load_mesh(path).vertices, model.neutral, atol=1e-5)


def test_bind_presets_prefers_prompt_named_emotions():
    bound, missing = bind_presets(["smile", "jawOpen", "eyeBlinkLeft", "eyeBlinkRight", "sad"])
    assert bound["happy"] == [("smile", 1.0)] and bound["sad"] == [("sad", 1.0)] and bound["aa"] == [("jawOpen", 1.0)]
    assert "lookUp" in missing and "blinkLeft" in bound


def test_vrm_needs_a_license(fox_project, tmp_path):
    root, _, _ = fox_project
    res = CliRunner().invoke(app, ["export", str(root), "--format", "vrm", "-o", str(tmp_path / "x.vrm")])
    assert res.exit_code != 0 and isinstance(res.exception, UserError) and "--license" in str(res.exception)
    res = CliRunner().invoke(
        app, ["export", str(root), "--format", "vrm", "--license", "whatever", "-o", str(tmp_path / "x.vrm")]
    )
    assert isinstance(res.exception, UserError) and "use one of" in str(res.exception)
    assert not (tmp_path / "x.vrm").exists()


def test_gltf_validator_and_three_vrm(vrm, tmp_path):
    from browser_page import JS, node_modules, run_page

    path, _, shapes, _ = vrm
    node_modules()
    proc = subprocess.run(
        ["node", str(JS / "validate_glb.mjs"), str(path)], capture_output=True, text=True, timeout=120
    )
    report = json.loads(proc.stdout)
    assert proc.returncode == 0 and report["errors"] == 0, report["messages"]
    result = run_page(
        "vrm_check.html", {f".test-{tmp_path.name}.vrm": path}, f"vrm=.test-{tmp_path.name}.vrm", tmp_path
    )
    assert result["ok"], result
    assert result["metaVersion"] == "1" and result["name"] == "Foxy" and len(result["humanBones"]) == 15
    assert {"aa", "blink", "blinkLeft", "blinkRight", "oh"} <= set(result["presets"])
    assert set(shapes.names) == set(result["custom"]) and set(result["expressions"]) >= set(result["presets"])
    assert result["driven"]["aa"] == {"jawOpen": 1} and result["driven"]["blinkLeft"] == {"eyeBlinkLeft": 1}


def test_export_glb_and_bad_format(fox_project, tmp_path):
    from t2bs.blendshapes.export import rig_targets
    from t2bs.geometry.io import load_mesh

    root, model, shapes = fox_project
    res = CliRunner().invoke(app, ["export", str(root), "--format", "glb", "-o", str(tmp_path / "rig.glb")])
    assert res.exit_code == 0, res.output
    back = load_mesh(tmp_path / "rig.glb")
    names, offsets, _ = rig_targets(model, shapes)
    assert back.morph_names == names and back.morph_names[: len(shapes.names)] == shapes.names
    np.testing.assert_allclose(back.morph_targets[names[0]], offsets[0], atol=1e-6)
    res = CliRunner().invoke(app, ["export", str(root), "--format", "fbx"])
    assert isinstance(res.exception, UserError) and "unknown --format" in str(res.exception)
