"""Offline grids: ground truth reproduces the canonical view, defects only off it, determinism, CLI resume."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import asset
from t2bs.errors import UserError
from t2bs.geometry.camera import frontal_camera
from t2bs.video.defects import DefectConfig, preset
from t2bs.video.synth import GridConfig, make_grid

CFG = GridConfig(frames=8, size=64, views=5)


@pytest.fixture(scope="module")
def turtle():
    from t2bs.character.render_stage import canonical_character

    return canonical_character(asset("turtle.glb"))[0]


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float("inf") if mse == 0 else 10 * np.log10(255.0**2 / mse)


@pytest.fixture(scope="module")
def grids(turtle, mesh_renderer):
    clean = make_grid(turtle, "blinking", seed=0, config=CFG, defects=preset("clean"), renderer=mesh_renderer)
    paper = make_grid(turtle, "blinking", seed=0, config=CFG, defects=preset("paper"), renderer=mesh_renderer)
    return clean, paper


def test_gt_vertices_reproduce_the_canonical_view(turtle, grids, mesh_renderer):
    clean, paper = grids
    cam = frontal_camera(CFG.size)
    assert np.allclose(cam.world_to_camera, clean.cameras[clean.canonical_view].world_to_camera)
    for grid in (clean, paper):
        for t in range(CFG.frames):
            rgb = mesh_renderer.render(turtle, cam, vertices=grid.gt_vertices[t], shading="unlit").rgb
            assert _psnr((rgb * 255 + 0.5).astype(np.uint8), grid.frames[grid.canonical_view, t]) > 35
    # and the frames really change over time (the blink, the head motion)
    assert _psnr(clean.frames[2, 0], clean.frames[2, -1]) < 40 or _psnr(clean.frames[2, 0], clean.frames[2, 4]) < 40


def test_zero_strength_is_a_clean_render(turtle, grids, mesh_renderer):
    clean, _ = grids
    zero = make_grid(
        turtle,
        "blinking",
        seed=0,
        config=CFG,
        renderer=mesh_renderer,
        defects=DefectConfig(geometry=0, color=0, lighting=0, texture_noise=0, blur=0, flicker=0, seed=7),
    )
    assert np.array_equal(zero.frames, clean.frames)
    for v in (0, 4):  # every view is the plain render of the true vertices
        rgb = mesh_renderer.render(turtle, clean.cameras[v], vertices=clean.gt_vertices[3], shading="unlit").rgb
        assert np.array_equal((np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8), clean.frames[v, 3])


def test_defects_only_off_the_canonical_view(grids):
    clean, paper = grids
    c = clean.canonical_view
    assert np.array_equal(paper.frames[c], clean.frames[c])
    assert np.array_equal(paper.masks[c], clean.masks[c])
    for v in range(clean.num_views):
        if v == c:
            continue
        diff = np.abs(paper.frames[v].astype(int) - clean.frames[v]).mean()
        assert diff > 2.0, (v, diff)
        # the shape seen from this view differs (silhouette changes), not just the colours
        assert (paper.masks[v] != clean.masks[v]).mean() > 0.002
    offsets = {d["view"]: d["geometry_offset_max"] for d in paper.meta["defect_views"]}
    assert 0.005 < offsets[0] <= 0.031 and offsets[0] > offsets[1]  # grows with |azimuth|
    blur = {d["view"]: d["blur_sigma_px"] for d in paper.meta["defect_views"]}
    assert blur[0] > blur[1] > 0


def test_each_defect_alone_changes_side_views(turtle, grids, mesh_renderer):
    clean, _ = grids
    small = GridConfig(frames=3, size=48, views=3)
    base = make_grid(turtle, "smiling", seed=1, config=small, renderer=mesh_renderer)
    for name in ("geometry", "color", "lighting", "texture_noise", "blur", "flicker"):
        g = make_grid(
            turtle, "smiling", seed=1, config=small, renderer=mesh_renderer, defects=DefectConfig(**{name: 1.0})
        )
        assert np.array_equal(g.frames[1], base.frames[1]), name
        assert not np.array_equal(g.frames[0], base.frames[0]), name


def test_determinism(turtle, grids, mesh_renderer):
    _, paper = grids
    again = make_grid(turtle, "blinking", seed=0, config=CFG, defects=preset("paper"), renderer=mesh_renderer)
    assert np.array_equal(again.frames, paper.frames) and np.array_equal(again.gt_vertices, paper.gt_vertices)
    other = make_grid(turtle, "blinking", seed=1, config=CFG, defects=preset("paper", seed=1), renderer=mesh_renderer)
    assert not np.array_equal(other.frames, paper.frames)


def test_one_defect_presets_set_one_strength():
    from t2bs.video.defects import STRENGTHS

    for name in STRENGTHS:
        alone, without = preset(f"only_{name}"), preset(f"paper_without_{name}", seed=3)
        assert {k: getattr(alone, k) for k in STRENGTHS} == {k: float(k == name) for k in STRENGTHS}
        assert {k: getattr(without, k) for k in STRENGTHS} == {k: float(k != name) for k in STRENGTHS}
        assert without.seed == 3
    assert preset("Only_Blur", blur=0.5).blur == 0.5  # names are case-blind, overrides still apply
    assert preset("paper", flicker=0.0).flicker == 0.0  # an override of a preset's own strength


def test_bad_settings():
    with pytest.raises(UserError, match="--views must be odd"):
        make_grid(None, "blinking", config=GridConfig(views=4))
    with pytest.raises(UserError, match="unknown defect preset 'extreme'; valid: clean, mild, paper, only_<defect>"):
        preset("extreme")
    with pytest.raises(UserError, match="unknown defect preset 'only_noise'"):
        preset("only_noise")


def test_videos_command_resumes(tmp_path, turtle, capsys):
    from t2bs.geometry.io import load_mesh, save_mesh
    from t2bs.project import Project
    from t2bs.video.stage import VideosConfig, run
    from t2bs.video.grid import load_grid

    project = Project(tmp_path / "p")
    save_mesh(turtle, project.mesh_path)
    kw = dict(
        prompts="blinking,waving the ears",
        samples=1,
        defects="mild",
        frames=4,
        size=32,
        views=3,
        seed=0,
        shading="unlit",
        backend="procedural",
        checkpoint=None,
        steps=1,
        import_grid=None,
        expression=None,
        sample=0,
    )
    run(project.root, VideosConfig(**kw))
    assert "2 made" in capsys.readouterr().out
    g = load_grid(project.path("videos", "waving-the-ears-s0"))
    assert g.frames.shape == (3, 4, 32, 32, 3) and g.gt_vertices.shape == (
        4,
        load_mesh(project.mesh_path).num_vertices,
        3,
    )
    assert g.meta["prompt"] == "a 3D character head, waving the ears, static camera, the camera is holding still"
    assert project.path("videos", "blinking-s0", "contact_sheet.png").exists()
    run(project.root, VideosConfig(**kw))
    assert "0 made, 2 up to date" in capsys.readouterr().out
    run(project.root, VideosConfig(**{**kw, "defects": "paper"}))  # new settings: redone
    assert "2 made" in capsys.readouterr().out
    with pytest.raises(UserError, match="unknown expression 'dancing'"):
        run(project.root, VideosConfig(**{**kw, "prompts": "dancing"}))
