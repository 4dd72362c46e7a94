"""`t2bs reconstruct` end to end on a tiny project: outputs, resume, bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from t2bs.errors import UserError
from t2bs.geometry.io import load_mesh, save_mesh
from t2bs.project import Project
from t2bs.recon.stage import list_videos, reconstruct_video
from t2bs.recon.config import parse_options, preset
from t2bs.video.grid import save_grid

from test_recon import sphere_mesh, splat_grid


def test_reconstruct_writes_outputs_and_resumes(tmp_path):
    mesh = sphere_mesh(1)
    v = mesh.vertices
    frames = np.stack([v, v + [0.02, 0.0, 0.0], v + [0.04, 0.01, 0.0]]).astype(np.float32)
    grid, _ = splat_grid(mesh, frames, size=32, views=3)
    project = Project(tmp_path / "proj")
    save_mesh(mesh, project.mesh_path)
    save_grid(grid, project.path("videos", "smile-s0"))
    cfg = preset(
        "quick",
        face_gaussians=False,
        silhouette_band=0,
        mask_weight=0.5,
        resolution=32,
        static_iters=5,
        iterations=12,
        global_iters=4,
        num_control_points=8,
        checkpoint_every=5,
        perceptual="none",
    )
    out, ran = reconstruct_video(project, project.path("videos", "smile-s0"), cfg, progress=False)
    assert ran
    for name in ("vertices.npy", "animation.glb", "state.pt", "preview.mp4", "metrics.json", "done.json"):
        assert (out / name).exists(), name
    assert not (out / "checkpoint.pt").exists()
    verts = np.load(out / "vertices.npy")
    assert verts.shape == (3, mesh.num_vertices, 3) and np.isfinite(verts).all()
    assert np.allclose(verts[0], mesh.vertices, atol=1e-5)  # frame 0 anchored to the rest pose
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["perceptual_loss"] == "none" and "p2p_moving" in metrics["geometry"]
    assert metrics["face_gaussians"] == 0  # face_gaussians=False: vertex Gaussians only
    anim = load_mesh(out / "animation.glb")
    assert len(anim.morph_targets) == 3
    assert np.allclose(anim.vertices + anim.morph_targets["frame0002"], verts[2], atol=1e-4)
    # Unchanged inputs: skipped. A missing done.json (a killed run): redone.
    assert reconstruct_video(project, project.path("videos", "smile-s0"), cfg, progress=False)[1] is False
    (out / "done.json").unlink()
    assert reconstruct_video(project, project.path("videos", "smile-s0"), cfg, progress=False, preview=False)[1] is True
    with pytest.raises(UserError, match="unknown video id"):
        list_videos(project, ["nope"])
    with pytest.raises(UserError, match="unknown method"):
        preset("quick", method="bogus")


def test_set_options_are_typed_by_field_and_bad_ones_are_user_errors():
    over = parse_options(["knn=4", "hidden_pick=off", "track_weight=0", "holdout_views=4,10", "perceptual=dssim"])
    assert over == {
        "knn": 4,
        "hidden_pick": False,
        "track_weight": 0.0,
        "holdout_views": (4, 10),
        "perceptual": "dssim",
    }
    assert type(over["track_weight"]) is float and type(over["knn"]) is int
    cfg = preset("quick", **over)
    assert (cfg.control_points.knn, cfg.hidden_parts.hidden_pick, cfg.data.holdout_views) == (
        4,
        False,
        (4, 10),
    )  # --set turns off what is on by default
    assert parse_options(["hidden_pick=True"]) == {"hidden_pick": True}
    for bad, says in (
        (["knn"], "KEY=VALUE"),
        (["no_such=1"], "no VCDGS option 'no_such'"),
        (["knn=four"], "not a valid int"),
        (["hidden_pick=maybe"], "not a valid bool"),
    ):
        with pytest.raises(UserError, match=says):
            parse_options(bad)
    with pytest.raises(UserError, match="knn"):  # parsed, then rejected by the config's own check
        preset("quick", **parse_options(["knn=0"]))
    with pytest.raises(UserError, match="track_refit"):  # joint-stage fractions
        preset("quick", **parse_options(["track_refit=0.6,1.5"]))
    assert preset("quick", **parse_options(["track_refit=0.9,0.3"])).tracks.track_refit == (0.3, 0.9)
    assert preset("quick", **parse_options(["track_refit="])).tracks.track_refit == ()  # --set turns it off
    # CUDA graphs replay the compiled step (back since a lent H200 trained with them: issue 36), so they need it;
    # the paper preset (the GPU's) turns both on
    with pytest.raises(UserError, match="cuda_graphs replays the compiled step: set compile=true with it"):
        preset("quick", **parse_options(["cuda_graphs=true"]))
    assert preset("quick", **parse_options(["cuda_graphs=true", "compile=true"])).runtime.cuda_graphs
    assert preset("paper").runtime.compile and preset("paper").runtime.cuda_graphs
    r = subprocess.run(
        [sys.executable, "-m", "t2bs.cli", "reconstruct", "nowhere", "--set", "knn=four"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and r.stderr.strip() == "error: VCDGS option knn='four': not a valid int", r.stderr


def test_a_preset_copy_shares_no_section_with_the_preset():
    """The config is a tree of mutable dataclasses: changing a copy's field must not change the preset."""
    from t2bs.recon.config import PRESETS, SECTIONS, VCDGSConfig

    cfg = preset("quick", knn=4)
    cfg.optim.iterations = 5
    assert PRESETS["quick"].optim.iterations == 800 and preset("quick").optim.iterations == 800
    assert all(getattr(cfg, s) is not getattr(PRESETS["quick"], s) for s in SECTIONS)
    back = VCDGSConfig.from_dict(cfg.to_dict())
    assert back == cfg and back.data.holdout_views == () and back.control_points.knn == 4


def test_a_video_the_time_budget_cut_is_named_in_one_line(tmp_path):
    """A budget that ends training early makes the result depend on the machine's speed: the run says so."""
    from t2bs.recon.stage import budget_cut

    cfg = preset("quick")
    line = budget_cut("smiling-s0", {"stopped_at_budget": True, "steps_run": 407}, cfg, tmp_path)
    assert line.startswith("smiling-s0: the time budget (260 s a video)") and "step 407 of 800" in line
    assert f"t2bs reconstruct {tmp_path} --set time_budget_s=0" in line
    assert budget_cut("smiling-s0", {"stopped_at_budget": False, "steps_run": 800}, cfg, tmp_path) is None
    assert budget_cut("smiling-s0", {}, cfg, tmp_path) is None  # not run now (up to date)
