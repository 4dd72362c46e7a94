"""The landmarks and retarget stages called from Python (t2bs.retarget.landmarks_stage / stage): files written,
values, and the UserError lines of bad settings."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from t2bs.errors import UserError
from t2bs.project import Project, read_json, write_json
from t2bs.retarget import landmarks_stage, stage
from t2bs.retarget.landmarks_stage import LandmarksConfig
from t2bs.retarget.stage import RetargetConfig


@pytest.fixture(scope="module")
def fox():
    """The procedural fox: eye / mouth part labels, rig controls as morph targets."""
    from t2bs.character.procedural import generate_procedural

    return generate_procedural("a cartoon fox", 0).mesh


def _project(tmp_path, mesh) -> Project:
    from t2bs.geometry.io import save_mesh

    project = Project(tmp_path / "proj")
    save_mesh(mesh, project.mesh_path)
    return project


def _model(mesh, shift: float = 0.0):
    """A two-shape rig of the mesh (the fox's jaw_open and blink_left), its neutral moved by ``shift`` along Z."""
    from t2bs.blendshapes.model import BlendshapeModel

    basis = np.stack([mesh.morph_targets["jaw_open"], mesh.morph_targets["blink_left"]]).astype(np.float32)
    return BlendshapeModel(
        neutral=(mesh.vertices + [0.0, 0.0, shift]).astype(np.float32),
        basis=basis,
        singular_values=np.array([2.0, 1.0]),
        names=["pc000", "pc001"],
    )


def test_landmarks_from_the_characters_parts(tmp_path, fox, capsys):
    project = _project(tmp_path, fox)
    res = landmarks_stage.run(project.root, LandmarksConfig(show=True))
    assert res.backend == "parts" and res.path == project.path("landmarks", "landmarks.json")
    saved = read_json(res.path)
    assert saved["vertex_ids"] == res.landmarks.vertex_ids.tolist() and len(saved["vertex_ids"]) == 20
    x = fox.vertices[res.landmarks.vertex_ids, 0]  # [20]: 6 on the character's right eye (-X), 6 on its left, 8 mouth
    assert (x[:6] < 0).all() and (x[6:12] > 0).all() and abs(x[12:].mean()) < 0.5 * x[6:12].mean()
    from PIL import Image

    assert res.overlay == project.path("landmarks", "overlay.png")
    assert Image.open(res.overlay).size == (512, 512)
    assert project.manifest()["stages"]["landmarks"]["backend"] == "parts"
    assert f"landmarks (parts) -> {res.path}" in capsys.readouterr().out


def test_landmarks_from_an_override_on_the_rigs_neutral(tmp_path, fox):
    from t2bs.blendshapes.model import save_model

    project = _project(tmp_path, fox)
    save_model(_model(fox, shift=0.01), project.path("blendshapes", "model.npz"))
    ids = list(range(0, 2000, 100))
    override = tmp_path / "mine.json"
    override.write_text(json.dumps({"vertex_ids": ids}))
    res = landmarks_stage.run(project, LandmarksConfig(override=override))
    assert res.backend == "override" and res.overlay is None and not project.path("landmarks", "overlay.png").exists()
    saved = read_json(res.path)
    assert saved["vertex_ids"] == ids
    # Found on the rig's neutral (the character moved 0.01 along Z), not on the character mesh.
    np.testing.assert_allclose(res.landmarks.positions, fox.vertices[ids] + [0.0, 0.0, 0.01], atol=1e-6)
    assert project.manifest()["stages"]["landmarks"]["config"] == {"backend": "auto", "override": str(override)}


def test_landmarks_bad_settings(tmp_path, fox):
    with pytest.raises(UserError, match=r"no character/mesh.glb \(run `t2bs render MESH -o"):
        landmarks_stage.run(tmp_path / "empty")
    project = _project(tmp_path, fox)
    with pytest.raises(UserError, match="^override file .*nope.json does not exist$"):
        landmarks_stage.run(project, LandmarksConfig(override=tmp_path / "nope.json"))
    (tmp_path / "torn.json").write_text("{torn")
    with pytest.raises(UserError, match=r"is not valid JSON \(.*line 1\)"):
        landmarks_stage.run(project, LandmarksConfig(override=tmp_path / "torn.json"))
    assert not project.path("landmarks").exists()


@pytest.fixture
def csv_project(tmp_path, fox):
    """The fox, its two-shape rig, ARKit eyeBlinkLeft / jawOpen on it, and a 12-frame Live Link take."""
    from t2bs.blendshapes.model import save_model
    from t2bs.face.arkit import ArkitShapes
    from t2bs.face.livelink import write_livelink_csv

    project = _project(tmp_path, fox)
    save_model(_model(fox), project.path("blendshapes", "model.npz"))
    shapes = ArkitShapes(["eyeBlinkLeft", "jawOpen"], np.array([[0.0, 1.0], [1.0, 0.0]]))
    write_json(project.path("blendshapes", "arkit.json"), shapes.to_dict())
    t = np.arange(12) / 60.0
    weights = {
        "EyeBlinkLeft": np.linspace(0, 1, 12),
        "JawOpen": 0.5 * np.sin(np.pi * t / t[-1]),
        "BrowInnerUp": np.full(12, 0.3),
    }
    head = np.stack([0.2 * np.sin(10 * t), np.zeros(12), np.zeros(12)], 1)  # yaw, pitch, roll in radians
    take = write_livelink_csv(tmp_path / "take.csv", weights, t, head)
    return project, take, weights, head


def test_retarget_from_a_live_link_csv(csv_project, capsys):
    project, take, weights, head = csv_project
    res = stage.run(project.root, RetargetConfig(driver=take, size=32))
    out = project.path("retarget", "take")
    assert res.out == out and res.frames == 12 and res.backend == "livelink-csv"
    assert res.shapes == ["eyeBlinkLeft", "jawOpen"] and res.rate_hz == pytest.approx(60.0)
    with open(out / "weights.csv") as f:
        rows = list(csv.reader(f))
    assert rows[0] == ["frame", "time", "eyeBlinkLeft", "jawOpen", "headYaw", "headPitch", "headRoll"]
    data = np.asarray(rows[1:], float)  # [12, 7]
    np.testing.assert_allclose(data[:, 2], weights["EyeBlinkLeft"], atol=1e-6)
    np.testing.assert_allclose(data[:, 3], weights["JawOpen"], atol=1e-6)
    np.testing.assert_allclose(data[:, 4:], head, atol=1e-6)
    report = read_json(out / "report.json")
    assert report["frames"] == 12 and report["shapes_absent_on_rig"] == ["browInnerUp"]
    assert (out / "animation.glb").stat().st_size > 0 and (out / "preview.mp4").stat().st_size > 0
    assert project.manifest()["stages"]["retarget"]["backend"] == "livelink-csv"
    printed = capsys.readouterr().out
    assert "note: 1 CSV shapes are absent on this rig" in printed and "retargeted 12 frames at 60 Hz" in printed
    res = stage.run(project, RetargetConfig(driver=take, out=project.root / "short", max_frames=5, size=32))
    assert res.frames == 5 and len((project.root / "short" / "weights.csv").read_text().splitlines()) == 6


def test_retarget_bad_settings(csv_project, tmp_path):
    project, take, _, _ = csv_project
    with pytest.raises(UserError, match="^retarget needs a driver"):
        stage.run(project)
    with pytest.raises(UserError, match=r"^--size must be 16\.\.4096 pixels, got 8$"):
        stage.run(project, RetargetConfig(driver=take, size=8))
    with pytest.raises(UserError, match=r"^--smooth must be a finite sigma >= 0 frames, got -1\.0$"):
        stage.run(project, RetargetConfig(driver=take, smooth=-1.0))
    with pytest.raises(UserError, match=r"^--max-frames must be >= 1, got 0$"):
        stage.run(project, RetargetConfig(driver=take, max_frames=0))
    project.path("blendshapes", "model.npz").unlink()
    with pytest.raises(UserError, match=r"no blendshapes/model.npz \(build the blendshape model first\)$"):
        stage.run(project, RetargetConfig(driver=take))
    assert not project.path("retarget").exists()
