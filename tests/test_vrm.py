"""VRM 1.0 export of the fox rig (issue 38): VRMC_vrm meta, humanoid, presets + ARKit custom expressions."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pygltflib
import pytest
from test_livelink import fox_project  # noqa: F401  (the shared module fixture)
from typer.testing import CliRunner

from t2bs.blendshapes.vrm import PRESETS, VPL_URL, bind_presets
from t2bs.cli import app
from t2bs.errors import UserError


@pytest.fixture(scope="module")
def vrm(fox_project, tmp_path_factory):  # noqa: F811
    root, model, shapes = fox_project
    path = tmp_path_factory.mktemp("vrm") / "fox.vrm"
    res = CliRunner().invoke(app, ["export", str(root), "--format", "vrm", "--license", "CC-BY-4.0",
                                   "--author", "Ada", "--name", "Foxy", "-o", str(path)])
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
    assert meta["otherLicenseUrl"] == "https://creativecommons.org/licenses/by/4.0/" and meta["commercialUsage"] == "corporation"
    bones = ext["humanoid"]["humanBones"]
    assert len(bones) == 15 and {"hips", "spine", "head", "leftHand", "rightFoot"} <= set(bones)
    names = gltf.meshes[0].extras["targetNames"]
    assert names[:len(shapes.names)] == shapes.names  # ARKit shapes first
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


def test_vrm_needs_a_license(fox_project, tmp_path):  # noqa: F811
    root, _, _ = fox_project
    res = CliRunner().invoke(app, ["export", str(root), "--format", "vrm", "-o", str(tmp_path / "x.vrm")])
    assert res.exit_code != 0 and isinstance(res.exception, UserError) and "--license" in str(res.exception)
    res = CliRunner().invoke(app, ["export", str(root), "--format", "vrm", "--license", "whatever", "-o", str(tmp_path / "x.vrm")])
    assert isinstance(res.exception, UserError) and "use one of" in str(res.exception)
    assert not (tmp_path / "x.vrm").exists()


def test_gltf_validator_and_three_vrm(vrm, tmp_path):
    from browser_page import JS, node_modules, run_page

    path, _, shapes, _ = vrm
    node_modules()
    proc = subprocess.run(["node", str(JS / "validate_glb.mjs"), str(path)], capture_output=True, text=True, timeout=120)
    report = json.loads(proc.stdout)
    assert proc.returncode == 0 and report["errors"] == 0, report["messages"]
    result = run_page("vrm_check.html", {f".test-{tmp_path.name}.vrm": path}, f"vrm=.test-{tmp_path.name}.vrm", tmp_path)
    assert result["ok"], result
    assert result["metaVersion"] == "1" and result["name"] == "Foxy" and len(result["humanBones"]) == 15
    assert {"aa", "blink", "blinkLeft", "blinkRight", "oh"} <= set(result["presets"])
    assert set(shapes.names) == set(result["custom"]) and set(result["expressions"]) >= set(result["presets"])
    assert result["driven"]["aa"] == {"jawOpen": 1} and result["driven"]["blinkLeft"] == {"eyeBlinkLeft": 1}
