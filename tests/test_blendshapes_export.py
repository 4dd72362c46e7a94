"""model.glb opens in other tools: Khronos glTF validator (node) and three.js in headless Chromium."""

from __future__ import annotations

import functools
import http.server
import json
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

import numpy as np
import pytest

from t2bs.blendshapes.export import export_glb, export_weights, rig_targets
from t2bs.blendshapes.model import build_model
from t2bs.blendshapes.semantic import semantic_shapes

REPO = Path(__file__).resolve().parents[1]
JS = REPO / "tools" / "js"
TURTLE = REPO.parent / "shared" / "assets" / "turtle.glb"
CHROMEDRIVER = "/usr/bin/chromedriver"


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """(model, character, path of model.glb) built from turtle captures of the video animator."""
    from t2bs.blendshapes.commands import animator_captures
    from t2bs.geometry.io import load_mesh
    from t2bs.geometry.mesh import normalize

    if not TURTLE.exists():
        pytest.skip(f"shared asset {TURTLE} not present")
    mesh, _ = normalize(load_mesh(TURTLE))
    caps, expr = animator_captures(mesh, frames=10, expressions=["blinking", "smiling", "opening the mouth extremely wide",
                                                                 "shaking the head", "talking"])
    model = build_model(mesh.vertices, caps, components=100)
    model.semantic_names, model.semantic_weights, model.semantic_sources = semantic_shapes(model, caps, expr)
    path = tmp_path_factory.mktemp("rig") / "model.glb"
    export_glb(model, mesh, path, capture="blinking-s0")
    return model, mesh, path


def test_glb_round_trip_targets_animation(rig):
    from t2bs.geometry.io import load_mesh

    model, mesh, path = rig
    back = load_mesh(path)
    names, offsets, scale = rig_targets(model)
    visible = model.visible_components()
    assert list(back.morph_targets) == names == [model.names[k] for k in visible] + model.semantic_names
    assert "jaw_open" in names and "blink" in names
    np.testing.assert_allclose(back.vertices, model.neutral, atol=1e-6)
    # Exported weights (scaled targets) pose the same mesh as the basis weights, within -1..1.
    w = model.capture_weights["smiling-s0"]
    ew = export_weights(model, w)
    assert np.abs(ew).max() <= 1 + 1e-6
    posed = back.vertices + np.einsum("tm,mnc->tnc", ew, np.stack(list(back.morph_targets.values())))
    np.testing.assert_allclose(posed, model.vertices(np.where(model.visible, w, 0.0)), atol=1e-4)
    # The components left out move no vertex by VISIBLE_FRACTION of the diagonal over the captures.
    from t2bs.blendshapes.model import VISIBLE_FRACTION

    hidden = ~model.visible
    if hidden.any():
        allw = np.concatenate(list(model.capture_weights.values()))
        off = model.offsets(np.where(hidden, allw, 0.0)[:, None, :] * np.eye(model.num_components)[None][:, hidden])
        assert np.linalg.norm(off, axis=-1).max() < VISIBLE_FRACTION * mesh.bbox_diagonal() * hidden.sum()
    import pygltflib

    gltf = pygltflib.GLTF2().load(str(path))
    assert gltf.meshes[0].weights == [0.0] * len(names)  # opens at the neutral pose
    assert len(gltf.animations) == 1 and gltf.animations[0].channels[0].target.path == "weights"


def _node_modules() -> Path:
    if shutil.which("node") is None:
        pytest.skip("node is not installed (scripts/setup.sh installs it with the system packages)")
    if not (JS / "node_modules" / "gltf-validator").exists() or not (JS / "node_modules" / "three").exists():
        if shutil.which("npm") is None:
            pytest.skip("npm is not installed")
        subprocess.run(["npm", "install", "--no-audit", "--no-fund", "--silent"], cwd=JS, check=True, timeout=300)
    return JS / "node_modules"


def test_khronos_gltf_validator_reports_no_errors(rig):
    _node_modules()
    _, _, path = rig
    proc = subprocess.run(["node", str(JS / "validate_glb.mjs"), str(path)], capture_output=True, text=True, timeout=120)
    report = json.loads(proc.stdout)
    assert proc.returncode == 0 and report["errors"] == 0, report["messages"]
    assert report["info"]["animationCount"] == 1


def test_validator_script_catches_a_broken_file(tmp_path, rig):
    _node_modules()
    _, _, path = rig
    broken = tmp_path / "broken.glb"
    data = bytearray(path.read_bytes())
    broken.write_bytes(bytes(data[: len(data) // 2]))  # truncated binary chunk
    proc = subprocess.run(["node", str(JS / "validate_glb.mjs"), str(broken)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1 and json.loads(proc.stdout)["errors"] > 0


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    extensions_map = {**http.server.SimpleHTTPRequestHandler.extensions_map, ".js": "text/javascript",
                      ".mjs": "text/javascript", ".glb": "model/gltf-binary"}

    def log_message(self, *args):  # keep pytest output clean
        pass


def test_three_js_loads_the_rig_in_headless_chromium(rig, tmp_path):
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None or not Path(CHROMEDRIVER).exists():
        pytest.skip("Debian's chromium + chromium-driver are not installed (scripts/setup.sh installs them)")
    _node_modules()
    webdriver = pytest.importorskip("selenium.webdriver", reason="pip install selenium (the test extra)")
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.support.ui import WebDriverWait

    model, _, path = rig
    shutil.copy(path, JS / f".test-{tmp_path.name}.glb")  # served next to the page (dot file: not committed)
    handler = functools.partial(_QuietHandler, directory=str(JS))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-dev-shm-usage",
                 f"--user-data-dir={tempfile.mkdtemp(prefix='t2bs-chrome-', dir=tmp_path)}"):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    try:
        port = server.server_address[1]
        driver.get(f"http://127.0.0.1:{port}/three_check.html?glb=.test-{tmp_path.name}.glb")
        result = WebDriverWait(driver, 60).until(lambda d: d.execute_script("return window.t2bsResult || null"))
    finally:
        driver.quit()
        server.shutdown()
        (JS / f".test-{tmp_path.name}.glb").unlink(missing_ok=True)
    assert result["ok"], result
    names = [model.names[k] for k in model.visible_components()] + model.semantic_names
    (mesh,) = result["meshes"]
    assert mesh["morphTargetInfluences"] == len(names) == mesh["morphPositions"]
    assert mesh["targetNames"] == names and mesh["influencesAllZero"] and mesh["textured"]
    assert mesh["vertices"] == model.num_vertices
    assert result["clips"][0]["name"] == "blinking-s0" and result["mixerOk"] is True


def test_usd_export(rig, tmp_path):
    pxr = pytest.importorskip("pxr", reason="usd-core is optional (pip install usd-core)")
    from pxr import Usd, UsdSkel

    from t2bs.blendshapes.export import export_usd

    model, mesh, _ = rig
    path = export_usd(model, mesh, tmp_path / "model.usda", capture="blinking-s0")
    stage = Usd.Stage.Open(str(path))
    binding = UsdSkel.BindingAPI(stage.GetPrimAtPath("/Character/Mesh"))
    names = binding.GetBlendShapesAttr().Get()
    assert len(names) == len(model.visible_components()) + len(model.semantic_names)
    shape = UsdSkel.BlendShape(stage.GetPrimAtPath(f"/Character/Mesh/{names[0]}"))
    assert len(shape.GetOffsetsAttr().Get()) == model.num_vertices
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/Character/Skel/Anim"))
    assert len(anim.GetBlendShapeWeightsAttr().GetTimeSamples()) == len(model.capture_weights["blinking-s0"])
    assert pxr is not None
