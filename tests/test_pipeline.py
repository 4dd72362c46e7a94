"""`t2bs create` end to end on a tiny setting: resume after kill -9 equals an uninterrupted run."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from conftest import asset

# Small enough for CI: the turtle (1922 vertices), 2 prompts, 3 views, 6 frames at 48 px.
TINY = [
    "--prompts",
    "blinking,opening the mouth extremely wide",
    "--frames",
    "6",
    "--size",
    "48",
    "--views",
    "3",
    "--defects",
    "clean",
    "--iterations",
    "40",
    "--control-points",
    "48",
    "--seed",
    "3",
]


def create_args(out):
    return [
        sys.executable,
        "-m",
        "t2bs.cli",
        "create",
        "a turtle",
        "-o",
        str(out),
        "--character-backend",
        "file",
        "--mesh",
        str(asset("turtle.glb")),
        *TINY,
    ]


def run_create(out):
    r = subprocess.run(create_args(out), capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    return r


@pytest.mark.slow
def test_create_end_to_end_then_kill_and_resume(tmp_path):
    full = tmp_path / "full"
    run_create(full)
    # The rig and the report exist and say what made them.
    model = np.load(full / "blendshapes" / "model.npz")
    assert model["basis"].shape[0] >= 2
    assert (full / "blendshapes" / "model.glb").exists()
    report = json.loads((full / "report.json").read_text())
    assert report["backends"]["character"] == "file" and report["backends"]["recon"] == "vcdgs"
    assert {v["video"] for v in report["videos"]} == {"blinking-s0", "opening-the-mouth-extremely-wide-s0"}
    assert all(v["p2p_moving"] is not None for v in report["videos"])
    assert abs(report["blendshapes"]["explained_variance_total"] - 1.0) < 1e-3  # all components kept
    assert (full / "landmarks" / "landmarks.json").exists() and (full / "report.md").exists()

    # Kill -9 while the first video is being reconstructed (its staging folder exists).
    killed = tmp_path / "killed"
    proc = subprocess.Popen(
        create_args(killed), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
    )
    deadline = time.time() + 600
    while time.time() < deadline and not list((killed / "recon").glob(".staging-*")):
        assert proc.poll() is None, "create finished before it could be killed"
        time.sleep(0.05)
    time.sleep(0.5)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (killed / "blendshapes" / "model.npz").exists()
    finished_before = {p.parent.name: p.read_text() for p in (killed / "recon").glob("*/done.json")}

    r = run_create(killed)
    # Finished work is not redone: grids and finished reconstructions keep their done.json.
    for name, text in finished_before.items():
        assert (killed / "recon" / name / "done.json").read_text() == text
    assert "videos: 0 made, 2 up to date" in r.stdout  # both grids survived the kill
    assert not list((killed / "recon").glob(".staging-*"))
    # Same seed: the resumed project equals the uninterrupted one.
    for video in ("blinking-s0", "opening-the-mouth-extremely-wide-s0"):
        a = np.load(full / "recon" / video / "vertices.npy")
        b = np.load(killed / "recon" / video / "vertices.npy")
        np.testing.assert_allclose(a, b, atol=1e-6)
    np.testing.assert_allclose(np.load(killed / "blendshapes" / "model.npz")["basis"], model["basis"], atol=1e-5)

    # Nothing to do on a third run.
    r = run_create(killed)
    assert "reconstruct: 0 reconstructed, 2 up to date" in r.stdout
