import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from t2bs.distributed import Job, run_jobs
from t2bs.project import is_done

TESTS = str(Path(__file__).parent)


def _jobs(root: Path, log: Path, n=4, sleep=0.0):
    return [
        Job(
            key=f"k{i}",
            name=f"job{i}",
            out_dir=root / f"job{i}",
            fn="jobs_for_tests:write_square",
            kwargs={"value": i, "log": str(log), "sleep": sleep},
        )
        for i in range(n)
    ]


def _squares(root: Path, n=4):
    return [json.loads((root / f"job{i}" / "result.json").read_text())["square"] for i in range(n)]


def test_local_runs_each_job_once_and_skips_on_rerun(tmp_path):
    log = tmp_path / "log.txt"
    done = run_jobs(_jobs(tmp_path / "out", log), executor="local")
    assert sorted(done) == [f"job{i}" for i in range(4)]
    assert _squares(tmp_path / "out") == [0, 1, 4, 9]
    assert len(log.read_text().splitlines()) == 4
    assert run_jobs(_jobs(tmp_path / "out", log), executor="local") == {}
    assert len(log.read_text().splitlines()) == 4
    # A changed key (changed input or config) reruns only that job.
    jobs = _jobs(tmp_path / "out", log)
    jobs[2].key = "changed"
    assert list(run_jobs(jobs, executor="local")) == ["job2"]


def test_unfinished_results_are_never_taken_as_done(tmp_path):
    out = tmp_path / "out"
    # A crash left a final folder without done.json and a stale staging folder.
    (out / "job1").mkdir(parents=True)
    (out / "job1" / "result.json").write_text("half")
    (out / ".staging-job2-dead").mkdir()
    jobs = _jobs(out, tmp_path / "log.txt")
    assert not is_done(out / "job1", "k1")
    run_jobs(jobs, executor="local")
    assert _squares(out) == [0, 1, 4, 9]
    assert not list(out.glob(".staging-*"))


def test_process_pool_and_retry(tmp_path, monkeypatch):
    monkeypatch.setenv("PYTHONPATH", TESTS + os.pathsep + os.environ.get("PYTHONPATH", ""))
    log = tmp_path / "log.txt"
    run_jobs(_jobs(tmp_path / "out", log), executor="process", workers=2)
    assert _squares(tmp_path / "out") == [0, 1, 4, 9]
    assert len(log.read_text().splitlines()) == 4
    flag = tmp_path / "flag"
    job = Job("k", "flaky", tmp_path / "flaky", "jobs_for_tests:fail_first_attempt", {"flag": str(flag)})
    run_jobs([job], executor="process", workers=2, retries=1)
    assert is_done(tmp_path / "flaky", "k") and (tmp_path / "flaky" / "ok").exists()
    assert not list(tmp_path.glob(".staging-*"))  # the failed attempt's folder is cleaned on the next run


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_ray_cluster_reconstructs_a_project_despite_a_killed_worker(tmp_path):
    """Two-node Ray cluster on loopback runs a small project's VCDGS jobs; one worker process is
    SIGKILLed mid-job; every video is still committed exactly once (the killed attempt is retried
    in a fresh staging folder) and equals an in-process run."""
    pytest.importorskip("ray", reason="Ray is an optional extra (pip install 't2bs[ray]')")
    import threading
    import time

    import numpy as np
    import psutil
    import ray

    from conftest import asset
    from t2bs.recon.stage import list_videos, recon_job
    from t2bs.recon.config import preset
    from t2bs.project import Project

    project = Project(tmp_path / "proj")
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "t2bs.cli",
            "render",
            str(asset("turtle.glb")),
            "-o",
            str(project.root),
            "--size",
            "64",
            "--views",
            "3",
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    from t2bs.video.stage import VideosConfig, run

    run(
        project,
        VideosConfig(
            prompts="blinking,smiling,opening the mouth extremely wide",
            samples=1,
            defects="clean",
            frames=5,
            size=48,
            views=3,
        ),
    )
    # No wall-time cap: under load the budget would compress the schedule and the two runs would differ.
    cfg = preset(
        "quick", iterations=40, global_iters=8, static_iters=20, num_control_points=48, seed=1, time_budget_s=0.0
    )
    jobs = [recon_job(project, g, cfg, preview=False) for g in list_videos(project, None)]
    assert len(jobs) == 3

    port = _free_port()
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}
    ray_bin = [sys.executable, "-m", "ray.scripts.scripts"]
    common = ["--node-ip-address", "127.0.0.1", "--disable-usage-stats"]
    subprocess.run(
        [
            *ray_bin,
            "start",
            "--head",
            "--port",
            str(port),
            "--num-cpus",
            "2",
            "--include-dashboard",
            "false",
            "--temp-dir",
            f"/tmp/rt{os.getpid()}",
            *common,
        ],
        env=env,
        check=True,
        capture_output=True,
    )
    try:
        subprocess.run(
            [*ray_bin, "start", "--address", f"127.0.0.1:{port}", "--num-cpus", "1", *common],
            env=env,
            check=True,
            capture_output=True,
        )
        killed = []

        def kill_one_running_worker():
            # A Ray worker names itself after the task it runs.
            for _ in range(3000):
                for proc in psutil.process_iter(["cmdline"]):
                    if any("ray::execute_attempt" in part for part in (proc.info["cmdline"] or [])):
                        time.sleep(1.0)  # let it get into training
                        proc.kill()
                        killed.append(proc.pid)
                        return
                time.sleep(0.1)

        killer = threading.Thread(target=kill_one_running_worker)
        killer.start()
        done = run_jobs(jobs, executor="ray", ray_address=f"127.0.0.1:{port}", retries=3)
        killer.join()
        assert killed, "no worker was killed"
        assert sorted(done) == sorted(j.name for j in jobs)
        assert all(is_done(j.out_dir, j.key) for j in jobs)
        recon = project.path("recon")
        assert sorted(p.name for p in recon.iterdir() if not p.name.startswith(".checkpoints")) == sorted(
            j.out_dir.name for j in jobs
        )
        assert len({info["worker_pid"] for info in done.values()}) >= 2  # both nodes' workers took jobs
    finally:
        ray.shutdown()
        subprocess.run([*ray_bin, "stop", "--force"], env=env, capture_output=True)
    # The cluster's results equal an in-process run of the same jobs (same seed).
    local = [
        recon_job(Project(project.root), j.out_dir.parents[1] / "videos" / j.out_dir.name, cfg, preview=False)
        for j in jobs[:1]
    ]
    local[0].out_dir = tmp_path / "local" / local[0].out_dir.name
    run_jobs(local)
    np.testing.assert_allclose(
        np.load(local[0].out_dir / "vertices.npy"), np.load(jobs[0].out_dir / "vertices.npy"), atol=1e-6
    )
