"""Evaluation metrics on inputs with known answers."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from t2bs.eval.bench_vcdgs import full_vs_markdown, markdown, seen_vertices, summarise
from t2bs.geometry.mesh import vertex_normals
from t2bs.errors import UserError
from t2bs.geometry.metrics import (
    expression_metrics,
    geometry_metrics,
    moving_mask,
    normal_consistency,
    p2p,
    part_errors,
    psnr,
    ssim,
)


def cube():
    b = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    return np.asarray(b.vertices, np.float32), np.asarray(b.faces, np.int32)


def test_p2p_is_mean_distance_over_diagonal():
    v, _ = cube()
    diag = np.sqrt(3.0)
    moved = v + np.array([0.1, 0.0, 0.0], np.float32)
    assert p2p(moved[None], v[None]) == pytest.approx(0.1 / diag, rel=1e-6)
    mask = np.zeros((1, len(v)), bool)
    mask[0, :2] = True
    half = v.copy()
    half[:2] += [0.0, 0.3, 0.4]  # distance 0.5 on two vertices only
    assert p2p(half[None], v[None], mask=mask) == pytest.approx(0.5 / diag, rel=1e-6)
    assert p2p(half[None], v[None]) == pytest.approx(0.5 * 2 / len(v) / diag, rel=1e-6)


def test_moving_mask_threshold():
    v, _ = cube()
    gt = np.stack([v, v + [0.004, 0, 0], v + [0.02, 0, 0]])  # 0.23 % and 1.2 % of the diagonal
    m = moving_mask(gt, v)
    assert not m[0].any() and not m[1].any() and m[2].all()


def test_normal_consistency_known_rotation():
    v, f = cube()
    assert normal_consistency(v, v, f) == pytest.approx(0.0, abs=1e-6)
    # Rotating the shape rotates every normal: NC = mean(1 - n . R n).
    a = np.radians(60)
    rot = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    n = vertex_normals(v, f)
    assert normal_consistency(v @ rot.T, v, f) == pytest.approx(np.mean(1 - (n * (n @ rot.T)).sum(1)), abs=1e-5)
    # Inside-out faces flip every normal: 1 - cos = 2.
    assert normal_consistency(v, v, f[:, ::-1].copy()) == pytest.approx(0.0, abs=1e-6)
    assert np.mean(1 - (vertex_normals(v, f[:, ::-1].copy()) * n).sum(1)) == pytest.approx(2.0, abs=1e-5)
    # Translation and scale leave normals alone.
    assert normal_consistency(v * 2 + 1, v, f) == pytest.approx(0.0, abs=1e-6)


def test_psnr_and_ssim_known_values():
    rng = np.random.default_rng(0)
    a = rng.random((2, 48, 48, 3)).astype(np.float32)
    assert psnr(a, a) == float("inf")
    b = np.clip(a + 0.1, 0, 1)
    mse = np.mean((a - b) ** 2)
    assert psnr(b, a) == pytest.approx(10 * np.log10(1 / mse), rel=1e-6)
    assert psnr(np.full((4, 4), 0.5), np.full((4, 4), 0.6)) == pytest.approx(20.0, rel=1e-6)
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-5)
    assert ssim(rng.random((2, 48, 48, 3)), a) < 0.2


def test_geometry_metrics_and_summary_table():
    v, f = cube()
    gt = np.stack([v, v + [0.1, 0, 0]])
    geo = geometry_metrics(gt, gt, v, f)
    assert geo["p2p_all"] == 0 and geo["p2p_moving"] == 0 and geo["moving_fraction"] == pytest.approx(0.5)
    static = geometry_metrics(np.stack([v, v]), gt, v, f)
    assert static["p2p_moving"] == pytest.approx(0.1 / np.sqrt(3), rel=1e-5)
    # p2p_seen counts only the seen vertices: a prediction right on the seen half and static on the other
    seen = np.arange(len(v)) < 4
    half = np.stack([v, np.where(seen[:, None], gt[1], v)])
    geo = geometry_metrics(half, gt, v, f, seen=seen)
    assert geo["p2p_seen"] == 0 and geo["seen_fraction"] == pytest.approx(0.5)
    assert geo["p2p_moving"] == pytest.approx(0.5 * static["p2p_moving"], rel=1e-5)
    rows = [
        {
            "asset": "cube",
            "prompt": "p",
            "defects": "clean",
            "method": m,
            "p2p_all": x,
            "p2p_moving": x,
            "p2p_seen": x / 2,
            "nc": x,
            "psnr": 30.0,
            "ssim": 0.9,
            "seconds": 1.0,
        }
        for m, x in (("full", 0.01), ("static", 0.04))
    ]
    s = summarise(rows)
    assert s["ratio_full_over_static"]["cube/p/clean"]["p2p_moving"] == pytest.approx(0.25)
    assert s["ratio_full_over_static"]["cube/p/clean"]["p2p_seen"] == pytest.approx(0.25)
    assert s["ratio_full_over_static"]["cube/p/clean"]["nc_better"]
    assert s["mean"]["clean/full"]["p2p_seen"] == pytest.approx(0.005)
    assert markdown(rows).count("\n") == 3 and "| 0.00500 |" in markdown(rows)
    # a row kept from a file older than p2p_seen: shown as "-", left out of the mean and the ratio
    del rows[0]["p2p_seen"]
    s = summarise(rows)
    assert "p2p_seen" not in s["mean"]["clean/full"] and "p2p_seen" not in s["ratio_full_over_static"]["cube/p/clean"]
    assert markdown(rows).splitlines()[2].split(" | ")[6] == "-"


def test_full_vs_ablations_counts_only_cases_both_ran():
    def row(asset, method, moving, seen=None):
        r = {
            "asset": asset,
            "prompt": "p",
            "defects": "paper",
            "method": method,
            "p2p_all": moving,
            "p2p_moving": moving,
            "nc": 0.01,
            "psnr": 30.0,
            "ssim": 0.9,
            "seconds": 1.0,
        }
        return r if seen is None else {**r, "p2p_seen": seen}

    rows = [
        row("a", "full", 0.010, 0.020),
        row("a", "no_lbs", 0.012, 0.018),
        row("a", "static", 0.05, 0.05),
        row("b", "full", 0.004, 0.006),
        row("b", "no_lbs", 0.003, 0.007),
        row("b", "no_view", 0.005, 0.008),
        row("c", "no_view", 0.001, 0.001),
    ]  # c has no full row: left out of the comparison
    vs = summarise(rows)["full_vs"]
    assert set(vs) == {"paper/no_lbs", "paper/no_view"}
    assert vs["paper/no_lbs"]["cases"] == 2 and vs["paper/no_view"]["cases"] == 1
    assert vs["paper/no_lbs"]["p2p_moving"] == pytest.approx({"full": 0.007, "ablation": 0.0075, "full_lower": 1})
    assert vs["paper/no_lbs"]["p2p_seen"] == pytest.approx({"full": 0.013, "ablation": 0.0125, "full_lower": 1})
    assert vs["paper/no_view"]["p2p_moving"] == pytest.approx({"full": 0.004, "ablation": 0.005, "full_lower": 1})
    table = full_vs_markdown(vs).splitlines()
    assert vs["paper/no_lbs"]["nc"] == pytest.approx({"full": 0.01, "ablation": 0.01, "full_lower": 0})
    assert len(table) == 2 + 6
    assert table[5] == "| paper | no_lbs | p2p_moving | 2 | 0.00700 | 0.00750 | 6.7 % | 1 of 2 |"
    # a row without p2p_seen (an older file) drops that metric, not the comparison
    del rows[4]["p2p_seen"]
    vs = summarise(rows)["full_vs"]
    assert "p2p_seen" not in vs["paper/no_lbs"] and vs["paper/no_lbs"]["p2p_moving"]["full_lower"] == 1


def test_seen_vertices_union_over_frames_and_cameras(mesh_renderer):
    """A small cube inside a larger one is hidden until a frame moves it out; the back faces stay hidden."""
    from t2bs.geometry.camera import frontal_camera
    from t2bs.geometry.mesh import Mesh

    outer, f = cube()
    mesh = Mesh(np.concatenate([0.4 * outer, 0.1 * outer]), np.concatenate([f, f + len(outer)]).astype(np.int32))
    out = mesh.vertices.copy()
    out[8:] += [0.35, 0.0, 0.0]  # the inner cube moved beside the outer one
    cam = frontal_camera(256, elevation_deg=0.0)
    front = mesh.vertices[:, 2] > 0
    np.testing.assert_array_equal(
        seen_vertices(mesh, mesh.vertices[None], [cam], mesh_renderer), front & (np.arange(16) < 8)
    )
    # (the inner cube's side facing the camera is too oblique for the depth test's tolerance)
    np.testing.assert_array_equal(seen_vertices(mesh, np.stack([mesh.vertices, out]), [cam], mesh_renderer), front)


def test_benchmark_resumes_only_missing_rows(tmp_path, monkeypatch, capsys):
    """A re-run with the same --json file and settings keeps finished rows; other settings or --fresh recompute."""
    from t2bs.eval import bench_vcdgs

    calls = []

    def fake_case(name, mesh, prompt, defects, methods, *args, **kwargs):
        calls.append((name, prompt, tuple(methods)))
        return [
            {
                "asset": name,
                "prompt": prompt,
                "defects": defects,
                "method": m,
                "p2p_all": 0.1,
                "p2p_moving": 0.2,
                "nc": 0.01,
                "psnr": 30.0,
                "ssim": 0.9,
                "seconds": float(len(calls)),
            }
            for m in methods
        ]

    monkeypatch.setattr(bench_vcdgs, "run_case", fake_case)
    monkeypatch.setattr(bench_vcdgs, "load_asset", lambda spec: (spec, None))
    out = tmp_path / "bench.json"

    def run(methods, **kw):
        return bench_vcdgs.run_bench(["a", "b"], ["smiling"], ["clean"], methods, json_path=out, **kw)

    first = run(["full", "static"])
    assert calls == [("a", "smiling", ("full", "static")), ("b", "smiling", ("full", "static"))]
    assert {r["commit"] for r in first["rows"]} == {bench_vcdgs.code_commit()}  # each row says which code made it
    assert run(["full", "static"])["rows"] == first["rows"] and len(calls) == 2  # nothing recomputed
    both = run(["full", "no_lbs", "static"])  # only the new method runs, rows keep the requested order
    assert calls[2:] == [("a", "smiling", ("no_lbs",)), ("b", "smiling", ("no_lbs",))]
    assert [r["method"] for r in both["rows"]] == ["full", "no_lbs", "static"] * 2
    assert both["rows"][0] == first["rows"][0]
    run(["full"], options={"track_weight": 0.0})  # another configuration: old rows are not reused
    assert calls[4:] == [("a", "smiling", ("full",)), ("b", "smiling", ("full",))]
    assert "other settings" in capsys.readouterr().out
    run(["full"], options={"track_weight": 0.0}, resume=False)
    assert len(calls) == 8


def _fake_case_in_a_process(name, mesh, prompt, defects, methods, *args):
    """A benchmark case for the --workers test: module-level so that a spawned worker can import it."""
    import os
    import time

    time.sleep(1.5 if name == "a" else 0.0)  # "a" finishes last
    return [
        {
            "asset": name,
            "prompt": prompt,
            "defects": defects,
            "method": m,
            "p2p_all": 0.1,
            "p2p_moving": 0.2,
            "nc": 0.01,
            "psnr": 30.0,
            "ssim": 0.9,
            "seconds": float(os.getpid()),
        }
        for m in methods
    ]


def test_benchmark_workers_run_cases_in_processes_and_keep_the_order(tmp_path, monkeypatch):
    import json
    import os

    from t2bs.eval import bench_vcdgs

    monkeypatch.setattr(bench_vcdgs, "run_case", _fake_case_in_a_process)
    monkeypatch.setattr(bench_vcdgs, "load_asset", lambda spec: (spec, None))
    out = tmp_path / "bench.json"
    res = bench_vcdgs.run_bench(["a", "b"], ["smiling"], ["clean"], ["full", "static"], json_path=out, workers=2)
    assert [(r["asset"], r["method"]) for r in res["rows"]] == [
        ("a", "full"),
        ("a", "static"),
        ("b", "full"),
        ("b", "static"),
    ]
    pids = {r["asset"]: r["seconds"] for r in res["rows"]}
    assert pids["a"] != pids["b"] and os.getpid() not in pids.values()
    assert json.loads(out.read_text())["rows"] == res["rows"]
    with pytest.raises(UserError, match="--workers"):
        bench_vcdgs.run_bench(["a"], ["smiling"], ["clean"], ["full"], workers=0)


def test_benchmark_cli_passes_time_budget_track_weight_seed_and_perfect_tracks(monkeypatch):
    """--time-budget / --track-weight / --seed reach the VCDGS configuration (and so the resume settings); unset, the
    preset's. --perfect-tracks reaches run_bench, and rows made with it are not resumed as the flow's (or the reverse)."""
    import typer
    from typer.testing import CliRunner

    from t2bs.cli.bench import bench_vcdgs_command
    from t2bs.eval import bench_vcdgs

    seen = []
    monkeypatch.setattr(
        bench_vcdgs,
        "run_bench",
        lambda *a, options=None, perfect_tracks=False, **kw: seen.append((options, perfect_tracks))
        or {"rows": [], "summary": summarise([])},
    )
    app = typer.Typer()
    app.command()(bench_vcdgs_command)
    assert CliRunner().invoke(app, ["--asset", "facecap", "--time-budget", "0"]).exit_code == 0
    assert CliRunner().invoke(app, ["--asset", "facecap", "--track-weight", "0.5"]).exit_code == 0
    assert CliRunner().invoke(app, ["--asset", "facecap"]).exit_code == 0
    assert CliRunner().invoke(app, ["--asset", "facecap", "--seed", "1"]).exit_code == 0
    assert CliRunner().invoke(app, ["--asset", "facecap", "--perfect-tracks"]).exit_code == 0
    options, perfect = zip(*seen)
    assert list(options) == [{"time_budget_s": 0.0}, {"track_weight": 0.5}, None, {"seed": 1}, None]
    assert list(perfect) == [False, False, False, False, True]
    assert bench_vcdgs.bench_settings("quick", 128, 16, (4, 10), 0, options[3])["config"]["seed"] == 1
    assert bench_vcdgs.bench_settings("quick", 128, 16, (4, 10), 0, options[0])["config"]["time_budget_s"] == 0.0
    flow_settings, perfect_settings = (
        bench_vcdgs.bench_settings("quick", 128, 16, (4, 10), 0, None, p) for p in (False, True)
    )
    assert perfect_settings == {**flow_settings, "tracks": "true"}


def _turn_plus_bump(frames: int = 6, bump_scale: float = 1.0):
    """A sphere (diagonal ~2) turning about y and drifting, with a bump on a small patch of known size:
    (rest [N, 3], vertices [T, N, 3], bump [T, N, 3] in the head's frame, rotations [T, 3, 3], translations [T, 3])."""
    import roma
    import torch

    rest = np.asarray(trimesh.creation.icosphere(subdivisions=3).vertices, np.float64)
    patch = rest[:, 2] > 0.9  # a cap of ~5 % of the vertices ("the eyelid")
    s = np.linspace(0.0, 1.0, frames)
    bump = np.zeros((frames, len(rest), 3))
    bump[:, patch, 1] = -0.08 * bump_scale * s[:, None]  # the lid slides down, 4 % of the diagonal at the peak
    rot = roma.rotvec_to_rotmat(torch.as_tensor(np.stack([np.zeros(frames), 0.3 * s, 0.1 * s], 1))).numpy()
    trans = np.stack([0.05 * s, 0.02 * s, np.zeros(frames)], 1)
    verts = np.einsum("tij,tnj->tni", rot, rest[None] + bump) + trans[:, None]
    return rest, verts, bump, rot, trans


def test_expression_metrics_take_the_head_motion_out():
    rest, gt, bump, rot, trans = _turn_plus_bump()
    diag = bbox = float(np.linalg.norm(rest.max(0) - rest.min(0)))
    moving = np.linalg.norm(bump, axis=-1) > 0.005 * bbox
    true_mean = float(np.linalg.norm(bump, axis=-1)[moving].mean() / diag)
    # A perfect reconstruction: exact.
    m = expression_metrics(gt, gt, rest)
    assert m["expr_p2p"] == pytest.approx(0.0, abs=1e-9)
    assert m["recovered"] == pytest.approx(1.0, abs=1e-9) and m["cosine"] == pytest.approx(1.0, abs=1e-9)
    assert m["expr_rigid"] == pytest.approx(true_mean, rel=1e-9)
    assert m["expr_fraction"] == pytest.approx(moving.mean())
    # The rigid oracle (true head motion, neutral face): error = the bump itself, nothing recovered.
    oracle = np.einsum("tij,nj->tni", rot, rest) + trans[:, None]
    m = expression_metrics(oracle, gt, rest)
    assert m["expr_p2p"] == pytest.approx(true_mean, rel=1e-9) and m["expr_ratio"] == pytest.approx(1.0, rel=1e-9)
    assert m["recovered"] == pytest.approx(0.0, abs=1e-9)
    # Half the bump, under a different (wrong) head motion: the head error does not count, the expression does.
    _, half, _, _, _ = _turn_plus_bump(bump_scale=0.5)
    off = half + np.array([0.03, 0.0, 0.0])  # a head-tracking error of 1.5 % of the diagonal
    m = expression_metrics(off, gt, rest)
    assert m["recovered"] == pytest.approx(0.5, abs=1e-6) and m["cosine"] == pytest.approx(1.0, abs=1e-6)
    assert m["expr_p2p"] == pytest.approx(0.5 * true_mean, rel=1e-6)
    assert m["expr_ratio"] == pytest.approx(0.5, rel=1e-6)
    # p2p over the moving vertices, by contrast, is dominated by the head motion.
    assert (
        p2p(oracle, gt, mask=moving_mask(gt, rest))
        < p2p(np.repeat(rest[None], len(gt), 0), gt, mask=moving_mask(gt, rest)) / 3
    )
    # A bump the other way: cosine -1.
    m = expression_metrics(np.einsum("tij,tnj->tni", rot, rest[None] - bump) + trans[:, None], gt, rest)
    assert m["cosine"] == pytest.approx(-1.0, abs=1e-6) and m["expr_ratio"] == pytest.approx(2.0, rel=1e-6)


def test_expression_metrics_see_motion_where_the_truth_is_still():
    """A lid closed at the wrong frame: the masked ratio cannot see it, ``spurious`` does, in the true motion's units."""
    rest, gt, bump, rot, trans = _turn_plus_bump()
    diag = float(np.linalg.norm(rest.max(0) - rest.min(0)))
    assert expression_metrics(gt, gt, rest)["spurious"] == pytest.approx(0.0, abs=1e-9)
    # The truth still at frames 0-1 (frame 0 is the rest, frame 1's bump made 0): the prediction moves at frame 1 by
    # the peak bump.
    gt2, pred = gt.copy(), gt.copy()
    gt2[1] = np.einsum("ij,nj->ni", rot[1], rest) + trans[1]
    pred[1] = np.einsum("ij,nj->ni", rot[1], rest + bump[-1]) + trans[1]
    m = expression_metrics(pred, gt2, rest)
    moving = np.linalg.norm(bump[2:], axis=-1) > 0.005 * diag
    true_mean = float(np.linalg.norm(bump[2:], axis=-1)[moving].mean() / diag)
    assert m["expr_ratio"] == pytest.approx(0.0, abs=1e-9)  # blind to it
    patch = moving.any(0)
    false_mean = float(np.linalg.norm(bump[-1][patch], axis=-1).mean() / diag)  # frame 1's false motion on the patch
    # the still pairs: frames 0 and 1 of the patch, frame 1 carrying the false motion
    assert m["spurious"] == pytest.approx(false_mean / 2 / true_mean, rel=1e-6)


def test_expression_metrics_of_a_rigid_capture_are_undefined():
    rest, _, _, rot, trans = _turn_plus_bump()
    rigid = np.einsum("tij,nj->tni", rot, rest) + trans[:, None]
    m = expression_metrics(rigid, rigid, rest)
    assert m["expr_fraction"] == 0.0 and np.isnan(m["expr_ratio"])
    with pytest.raises(ValueError):
        expression_metrics(rigid[:, :5], rigid, rest)


def test_expression_metrics_of_a_region_count_its_vertices_only():
    """Half the bump on one half of the patch, all of it on the other: each region's numbers are its own, and the
    regions' errors add up to the whole's (the rigid fits use every vertex either way)."""
    rest, gt, bump, rot, trans = _turn_plus_bump()
    left = rest[:, 0] < 0
    scale = np.where(left, 0.5, 1.0)[None, :, None]
    pred = np.einsum("tij,tnj->tni", rot, rest[None] + scale * bump) + trans[:, None]
    whole = expression_metrics(pred, gt, rest)
    half = expression_metrics(pred, gt, rest, select=left)
    full = expression_metrics(pred, gt, rest, select=~left)
    assert half["recovered"] == pytest.approx(0.5, abs=1e-6) and half["expr_ratio"] == pytest.approx(0.5, rel=1e-6)
    assert full["expr_ratio"] == pytest.approx(0.0, abs=1e-6) and full["cosine"] == pytest.approx(1.0, abs=1e-6)
    pairs = whole["expr_fraction"] * len(gt) * len(rest)
    split = (half["expr_p2p"] * half["expr_fraction"] + full["expr_p2p"] * full["expr_fraction"]) * len(gt) * len(rest)
    assert split == pytest.approx(whole["expr_p2p"] * pairs, rel=1e-9)
    assert np.isnan(expression_metrics(pred, gt, rest, select=rest[:, 2] < 0)["expr_ratio"])  # the patch is not there


def test_benchmark_rows_name_the_commit_of_their_code():
    """``code_commit`` is this checkout's HEAD (``+dirty`` with uncommitted changes to tracked files), and None where
    the code is not a git checkout of t2bs."""
    import shutil
    import subprocess
    from pathlib import Path

    from t2bs.eval import bench_vcdgs

    here = Path(bench_vcdgs.__file__).resolve().parents[3]
    if shutil.which("git") is None or not (here / ".git").exists():
        pytest.skip("the code under test is not a git checkout")
    head = subprocess.run(["git", "-C", str(here), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    got = bench_vcdgs.code_commit()
    assert got is not None and got.split("+")[0] == head and len(head) == 40
    dirty = subprocess.run(
        ["git", "-C", str(here), "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True
    ).stdout.strip()
    assert got.endswith("+dirty") == bool(dirty)


def test_part_errors_split_p2p_moving_by_part():
    # two separate cubes; the truth moves both by 0.2, the reconstruction gets the first exactly and leaves the second
    # at rest (error 0.2 on each of its vertices): the second holds the whole error, the oracle (rest) errs on both
    v, f = cube()
    rest = np.concatenate([v, v + [3.0, 0.0, 0.0]]).astype(np.float32)
    faces = np.concatenate([f, f + len(v)])
    gt = (rest + [0.0, 0.2, 0.0])[None].astype(np.float32)
    pred = gt.copy()
    pred[0, len(v) :] = rest[len(v) :]
    seen = np.zeros(len(rest), bool)
    seen[:4] = True  # half of the first cube
    diag = float(np.linalg.norm(rest.max(0) - rest.min(0)))
    parts = part_errors(pred, gt, rest, faces, seen=seen, oracle=rest[None])
    assert [p["vertices"] for p in parts] == [8, 8]
    second, first = parts
    assert second["share"] == pytest.approx(1.0) and first["share"] == pytest.approx(0.0)
    assert second["p2p"] == pytest.approx(0.2 / diag, rel=1e-5) and first["p2p"] == pytest.approx(0.0, abs=1e-9)
    assert second["pairs"] == first["pairs"] == pytest.approx(0.5)
    assert first["seen"] == pytest.approx(0.5) and second["seen"] == 0.0
    assert first["oracle_p2p"] == second["oracle_p2p"] == pytest.approx(0.2 / diag, rel=1e-5)
    # the shares of all parts add up to 1, and p2p moving is their pairs-weighted mean
    pred[0, :8] += [0.0, 0.0, 0.1]
    parts = part_errors(pred, gt, rest, faces)
    assert sum(p["share"] for p in parts) == pytest.approx(1.0)
    mask = moving_mask(gt, rest)
    assert sum(p["p2p"] * p["pairs"] for p in parts) == pytest.approx(p2p(pred, gt, diag, mask), rel=1e-6)
    assert part_errors(rest[None], rest[None], rest, faces) == []  # nothing moves
    assert len(part_errors(pred, gt, rest, faces, top=1)) == 1
