"""The videos, blendshapes and export stages called from Python on a small procedural character."""

from __future__ import annotations

import numpy as np
import pytest

from t2bs.errors import UserError

FRAMES, SIZE, VIEWS = 4, 32, 3


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    """A project holding only a procedural fox (it has a face rig, so the videos need no auto rig)."""
    from t2bs.character.procedural import generate_procedural
    from t2bs.geometry.io import save_mesh
    from t2bs.geometry.mesh import normalize
    from t2bs.project import Project

    project = Project(tmp_path_factory.mktemp("api_video") / "fox")
    mesh, _ = normalize(generate_procedural("a cartoon fox", 0).mesh)
    save_mesh(mesh, project.mesh_path)
    return project


@pytest.fixture(scope="module")
def videos(project):
    from t2bs.video.stage import VideosConfig, run

    config = VideosConfig(
        prompts="blinking,smiling", samples=1, defects="clean", frames=FRAMES, size=SIZE, views=VIEWS, seed=0
    )
    return run(project.root, config), config


def test_videos_run_writes_one_grid_per_prompt_and_resumes(project, videos, capsys):
    from t2bs.video.grid import load_grid
    from t2bs.video.stage import run

    result, config = videos
    assert result.backend == "procedural" and result.folder == project.path("videos")
    assert result.videos == result.made == ["blinking-s0", "smiling-s0"] and result.skipped == []
    n = project.load_character().num_vertices
    for video_id in result.videos:
        folder = project.path("videos", video_id)
        grid = load_grid(folder)
        assert grid.frames.shape == (VIEWS, FRAMES, SIZE, SIZE, 3) and grid.frames.dtype == np.uint8
        assert grid.gt_vertices.shape == (FRAMES, n, 3) and grid.gt_vertices.dtype == np.float32
        assert grid.masks.shape == (VIEWS, FRAMES, SIZE, SIZE) and grid.canonical_view == 1
        assert grid.meta["motion_source"] == "rig" and grid.meta["video_id"] == video_id
        assert (folder / "contact_sheet.png").is_file() and (folder / "done.json").is_file()
        assert len(list((folder / "frames" / "view00").glob("*.png"))) == FRAMES
    # The blink moves the mesh: its ground truth is not the neutral character in every frame.
    gt = load_grid(project.path("videos", "blinking-s0"), load_frames=False).gt_vertices
    assert np.abs(gt - project.load_character().vertices).max() > 1e-4
    stage = project.manifest()["stages"]["videos"]
    assert stage["backend"] == "procedural" and stage["made"] == 2 and stage["expressions"] == ["blinking", "smiling"]
    capsys.readouterr()
    again = run(project, config)  # a Project works as well as a path; nothing changed: nothing redone
    assert again.made == [] and again.skipped == ["blinking-s0", "smiling-s0"]
    assert "videos: 0 made, 2 up to date" in capsys.readouterr().out


def test_blendshapes_run_builds_the_model_and_skips_a_rerun(project, videos, capsys):
    from t2bs.blendshapes.model import load_model
    from t2bs.blendshapes.stage import BlendshapesConfig, run
    from t2bs.geometry.io import load_mesh

    config = BlendshapesConfig(components=8, source="auto", arkit=False)
    result = run(project.root, config)
    out = project.path("blendshapes")
    assert result.folder == out and result.source == "gt" and not result.up_to_date
    assert result.animation in ("blinking-s0", "smiling-s0") and result.arkit is None
    model = load_model(out / "model.npz")
    n = project.load_character().num_vertices
    assert result.components == model.num_components and 1 <= model.num_components <= 8
    assert model.basis.shape == (model.num_components, n, 3) and model.neutral.shape == (n, 3)
    assert sorted(model.capture_weights) == ["blinking-s0", "smiling-s0"]
    assert model.capture_weights["blinking-s0"].shape == (FRAMES, model.num_components)
    assert model.semantic_names == ["blink", "smile"]
    rig = load_mesh(out / "model.glb")
    assert rig.num_vertices == n and list(rig.morph_targets)[:2] == ["blink", "smile"]
    assert not (out / "arkit.json").exists() and (out / "stats.json").is_file() and (out / "done.json").is_file()
    assert f"{model.num_components} shapes" in capsys.readouterr().out
    again = run(project.root, config)
    assert again.up_to_date and again.components == result.components and again.animation == result.animation
    assert "blendshapes: up to date" in capsys.readouterr().out


def test_export_run_writes_the_rig_in_the_asked_format(project, videos, tmp_path, capsys):
    from t2bs.blendshapes.export_stage import ExportConfig, run
    from t2bs.blendshapes.model import load_model
    from t2bs.blendshapes.stage import BlendshapesConfig
    from t2bs.blendshapes.stage import run as build
    from t2bs.geometry.io import load_mesh

    build(project.root, BlendshapesConfig(components=8, arkit=False))
    capsys.readouterr()
    result = run(project.root, ExportConfig(format="glb", out=tmp_path / "fox.glb"))
    assert result.path == tmp_path / "fox.glb" and result.format == "glb" and not result.arkit
    model = load_model(project.path("blendshapes", "model.npz"))
    rig = load_mesh(result.path)
    visible = [model.names[k] for k in model.visible_components()]
    assert list(rig.morph_targets) == model.semantic_names + visible
    out = capsys.readouterr().out
    assert "note: no blendshapes/arkit.json" in out and f"wrote {tmp_path / 'fox.glb'}" in out
    with pytest.raises(UserError, match=r"^--format vrm needs --license \(VPL-1.0"):
        run(project.root, ExportConfig(format="vrm", out=tmp_path / "fox.vrm"))
    assert not (tmp_path / "fox.vrm").exists()


def test_bad_settings_raise_one_line_user_errors(project, tmp_path):
    from t2bs.blendshapes import export_stage, stage
    from t2bs.video.stage import VideosConfig, run

    with pytest.raises(UserError, match="^--backend must be procedural, cogvideox or sv4d2, got 'veo'$"):
        run(project.root, VideosConfig(backend="veo"))
    with pytest.raises(UserError, match="^unknown expression 'dancing'"):
        run(project.root, VideosConfig(prompts="dancing", frames=FRAMES, size=SIZE, views=VIEWS))
    with pytest.raises(UserError, match="^--import-grid needs --expression NAME"):
        run(project.root, VideosConfig(import_grid=tmp_path))
    with pytest.raises(UserError, match=r"^--components must be >= 1 and --fps a positive number \(got 0, 8.0\)$"):
        stage.run(project.root, stage.BlendshapesConfig(components=0))
    with pytest.raises(UserError, match="^unknown --source 'both'; use one of auto, vcdgs, gt$"):
        stage.run(project.root, stage.BlendshapesConfig(source="both"))
    with pytest.raises(UserError, match="^unknown --format 'obj'; use one of glb, usd, vrm$"):
        export_stage.run(project.root, export_stage.ExportConfig(format="obj"))
    with pytest.raises(UserError, match="no such project folder$"):
        export_stage.run(tmp_path / "nowhere", export_stage.ExportConfig(format="glb"))
    assert not (tmp_path / "nowhere").exists()
