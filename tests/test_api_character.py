"""The character, render and auto rig stages (and the gallery, the viewer's settings) called from Python."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from t2bs.errors import UserError


def _image_shape(path) -> tuple[int, ...]:
    return np.asarray(Image.open(path)).shape


def test_character_run_writes_mesh_renders_and_manifest(tmp_path, capsys):
    from t2bs.character.stage import CharacterConfig, run
    from t2bs.project import Project

    result = run(tmp_path / "p", CharacterConfig(prompt="a cartoon fox with big ears", seed=3, size=32))
    project = Project(tmp_path / "p")
    assert result.mesh_path == project.mesh_path and result.mesh_path.is_file()
    assert result.backend == "procedural" and result.archetype == "fox" and result.notices == ()
    mesh = project.load_character()
    assert result.vertices == mesh.num_vertices > 100
    assert set(result.parts) == set(mesh.part_names) and "jaw_open" in result.morph_targets
    assert _image_shape(result.renders / "front.png") == (32, 32, 3)
    assert len(list((result.renders / "orbit").glob("view*.png"))) == 15
    stages = project.manifest()["stages"]
    assert stages["character"]["archetype"] == "fox" and stages["render"]["config"] == {
        "size": 32,
        "views": 15,
        "shading": "lambert",
    }
    out = capsys.readouterr().out
    assert f"character: {project.mesh_path} ({mesh.num_vertices} vertices, backend procedural, archetype fox)" in out
    # The same prompt and seed again: the same mesh, nothing re-rendered.
    run(tmp_path / "p", CharacterConfig(prompt="a cartoon fox with big ears", seed=3, size=32))
    assert "renders up to date" in capsys.readouterr().out


def test_render_run_imports_a_mesh_and_resumes(tmp_path, capsys):
    from t2bs.character.procedural import generate_procedural
    from t2bs.character.render_stage import RenderStageConfig, run
    from t2bs.geometry.io import save_mesh
    from t2bs.project import Project

    src = save_mesh(generate_procedural("a green frog", 0).mesh, tmp_path / "frog.glb")
    config = RenderStageConfig(mesh=src, size=24, views=3, shading="unlit")
    result = run(str(tmp_path / "p"), config)
    project = Project(tmp_path / "p")
    assert result.mesh_path == project.mesh_path and result.mesh_path.is_file()
    assert result.facing == "+z" and result.views == 3 and result.vertices == project.load_character().num_vertices
    assert _image_shape(result.renders / "front.png") == (24, 24, 3)
    assert sorted(p.name for p in (result.renders / "orbit").iterdir()) == ["view00.png", "view01.png", "view02.png"]
    assert len(json.loads((result.renders / "cameras.json").read_text())["orbit"]) == 3
    stage = project.manifest()["stages"]["render"]
    # The manifest and the content key hold the render settings, not the input file's path.
    assert stage["backend"] == "file" and stage["config"] == {"size": 24, "views": 3, "shading": "unlit"}
    assert stage["source"] == str(src) and stage["facing"] == "+z"
    assert "renders:   " in capsys.readouterr().out
    done = (result.renders / "done.json").read_text()
    run(tmp_path / "p", config)
    assert "renders up to date" in capsys.readouterr().out and (result.renders / "done.json").read_text() == done


def test_autorig_run_rigs_a_mesh_file(tmp_path):
    from test_autorig import synthetic_head

    from t2bs.geometry.io import load_mesh, save_mesh
    from t2bs.rig.stage import AutorigConfig, run

    mesh, lm, *_ = synthetic_head()
    src, lmf = tmp_path / "head.glb", tmp_path / "lm.json"
    save_mesh(mesh, src)
    lmf.write_text(json.dumps({"vertex_ids": lm.tolist()}))
    result = run(tmp_path / "out" / "rig.glb", AutorigConfig(mesh_path=src, landmarks=lmf))
    assert result.out == tmp_path / "out" / "rig.glb" and result.landmark_source == "file" and result.facing == "+z"
    rigged = load_mesh(result.out)
    assert set(rigged.morph_targets) == set(result.shapes) >= {"jawOpen", "eyeBlinkLeft", "mouthSmileRight"}
    assert rigged.morph_targets["jawOpen"].shape == (mesh.num_vertices, 3)
    summary = json.loads(result.summary_path.read_text())
    assert result.summary_path == result.out.with_suffix(".json") and summary["missing"] == result.missing
    assert "tongueOut" in result.missing


def test_character_bad_config_is_a_user_error_and_writes_nothing(tmp_path):
    from t2bs.character.stage import CharacterConfig, run

    with pytest.raises(UserError, match="--size must be >= 16"):
        run(tmp_path / "p", CharacterConfig("a fox", size=8))
    with pytest.raises(UserError, match="unknown --backend 'nope'"):
        run(tmp_path / "p", CharacterConfig("a fox", backend="nope"))
    assert not (tmp_path / "p").exists()  # the folder the lock made is removed again


def test_bad_configs_are_user_errors(tmp_path):
    from t2bs.character.gallery import render_gallery
    from t2bs.character.render_stage import RenderStageConfig
    from t2bs.character.render_stage import run as render
    from t2bs.rig.stage import AutorigConfig
    from t2bs.rig.stage import run as autorig
    from t2bs.viewer.serve import ViewConfig, serve

    (tmp_path / "ok.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(UserError, match="--shading must be lambert or unlit, got 'nope'"):
        render(tmp_path / "p", RenderStageConfig(mesh=tmp_path / "ok.obj", shading="nope"))
    with pytest.raises(UserError, match="--size must be >= 16 and --views >= 1"):
        render(tmp_path / "p", RenderStageConfig(mesh=tmp_path / "ok.obj", views=0))
    with pytest.raises(UserError, match="no such file"):
        render(tmp_path / "p", RenderStageConfig(mesh=tmp_path / "none.glb"))
    assert not (tmp_path / "p").exists()  # refused before the project folder was made
    with pytest.raises(UserError, match="-o must name a .glb file"):
        autorig(tmp_path / "rig.obj", AutorigConfig(mesh_path=tmp_path / "ok.obj"))
    with pytest.raises(UserError, match="no such mesh file"):
        autorig(tmp_path / "rig.glb", AutorigConfig(mesh_path=tmp_path / "none.glb"))
    with pytest.raises(UserError, match="--size must be >= 32"):
        render_gallery(tmp_path / "g", size=16)
    with pytest.raises(UserError, match="--host must not be empty"):
        serve(tmp_path / "p", ViewConfig(host=" "))
    assert not any((tmp_path / name).exists() for name in ("p", "g", "rig.glb"))
