"""Expressions through VCDGS: the lid scene (a still head whose lid slides over a dark eye, eval/scenes.py) must be
recovered by the photometric loss alone, and the diagnostic sheet (benchmarks/expression_view.py) must show it."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from t2bs.geometry.metrics import expression_metrics
from t2bs.eval.scenes import lid_scene
from t2bs.recon.config import preset

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def lid_reconstruction():
    from t2bs.recon.vcdgs import reconstruct_grid

    mesh, grid = lid_scene(frames=6, size=64)
    cfg = preset("quick", **LID_SETTINGS)
    return mesh, grid, cfg, reconstruct_grid(mesh, grid, cfg, progress=False)


# The photometric loss alone (no optical-flow tracks), at the scene's 64 px, exact per seed (no time cap).
LID_SETTINGS = dict(
    resolution=64, track_weight=0.0, iterations=400, global_iters=80, time_budget_s=0.0, hidden_pick=False
)


def test_lid_scene_moves_only_the_lid():
    mesh, grid = lid_scene(frames=6, size=64)
    lid = mesh.part_mask("eyelid_left")
    motion = np.linalg.norm(grid.gt_vertices - mesh.vertices[None], axis=-1)  # [T, N]
    assert motion[:, ~lid].max() == 0.0 and motion[0].max() == 0.0
    assert motion[:, lid].max() > 0.05 * mesh.bbox_diagonal()  # the peak: the lid has slid over the eye
    canon = grid.frames[grid.canonical_view].astype(np.float32)  # [T, H, W, 3]
    dark = (canon.mean(-1) < 60).sum((1, 2))  # the eye's dark pixels: covered at the peak, back at the end
    assert dark[2] < 0.6 * dark[0] and dark[-1] == dark[0]


@pytest.mark.slow
def test_photometric_loss_alone_moves_the_lid_the_right_way(lid_reconstruction):
    """What the method does today (issue 37, measured): the lid moves the right way but stops at 0.74 of its
    motion (0.51 of the non-rigid motion with the head's drift taken out; before the splat offsets 0.59 / 0.43)."""
    mesh, grid, _, res = lid_reconstruction
    m = expression_metrics(res.vertices, grid.gt_vertices, mesh.vertices)
    assert m["cosine"] >= 0.9 and m["recovered"] >= 0.45 and m["expr_ratio"] <= 0.6, m
    lid = mesh.part_mask("eyelid_left")
    true = grid.gt_vertices[:, lid] - mesh.vertices[lid]
    moved = res.vertices[:, lid] - mesh.vertices[lid]
    assert float((true * moved).sum() / (true**2).sum()) >= 0.65  # least-squares gain of the lid's motion


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True, reason="issue 37: the photometric loss alone recovers ~0.51 of the lid's motion, not 0.9"
)
def test_photometric_loss_alone_recovers_the_lid(lid_reconstruction):
    mesh, grid, _, res = lid_reconstruction
    m = expression_metrics(res.vertices, grid.gt_vertices, mesh.vertices)
    assert m["recovered"] >= 0.9 and m["cosine"] >= 0.9 and m["expr_ratio"] <= 0.3, m


@pytest.mark.slow
def test_expression_view_shows_input_gaussians_mesh_and_truth(lid_reconstruction, tmp_path):
    from PIL import Image

    from t2bs.geometry.io import save_mesh
    from t2bs.project import Project, mark_done
    from t2bs.recon.stage import job_metrics
    from t2bs.recon.extract import write_outputs
    from t2bs.video.grid import save_grid

    mesh, grid, cfg, res = lid_reconstruction
    project = Project(tmp_path / "lid")
    save_mesh(mesh, project.mesh_path)
    save_grid(grid, project.path("videos", "lid-s0"))
    out = project.path("recon", "lid-s0")
    write_outputs(out, mesh, grid, res, cfg, job_metrics(res, mesh, grid, cfg), preview=False)
    mark_done(out, "test")
    spec = importlib.util.spec_from_file_location("expression_view", ROOT / "benchmarks" / "expression_view.py")
    view = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(view)
    info = view.view_video(project.root, "lid-s0", size=96, peaks=2, crop=False)
    sheet = np.asarray(Image.open(info["file"]))
    assert sheet.shape == (2 * 96, 4 * 96, 3) and info["columns"][-1] == "ground truth"
    assert info["frames"] == [2, 3]  # the two frames where the lid is lowest
    m = expression_metrics(res.vertices, grid.gt_vertices, mesh.vertices)
    assert info["expression"]["recovered"] == pytest.approx(m["recovered"], abs=1e-4)
    # Tiles: the input and the truth show the lid over the eye (fewer of the eye's dark pixels than at rest); the
    # trained Gaussians' and the mesh's tiles show the eye, somewhere between rest and the input.
    dark = [(sheet[:96, 96 * k : 96 * (k + 1)].mean(-1) < 60).sum() for k in range(4)]
    rest = (np.asarray(Image.fromarray(grid.frames[grid.canonical_view, 0]).resize((96, 96))).mean(-1) < 60).sum()
    assert dark[0] < 0.7 * rest and dark[3] < 0.7 * rest, (dark, rest)
    assert 0 < dark[1] <= rest * 1.1 and 0 < dark[2] <= rest * 1.1, (dark, rest)
