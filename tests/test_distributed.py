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
        Job(key=f"k{i}", name=f"job{i}", out_dir=root / f"job{i}", fn="jobs_for_tests:write_square",
            kwargs={"value": i, "log": str(log), "sleep": sleep})
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
def test_ray_cluster_survives_a_killed_worker(tmp_path):
    """Two-node Ray cluster on loopback; one worker process is SIGKILLed mid-job; every job is
    still committed exactly once (the killed attempt is retried in a fresh staging folder)."""
    pytest.importorskip("ray", reason="Ray is an optional extra (pip install 't2bs[ray]')")
    import signal
    import threading
    import time

    import ray

    port = _free_port()
    env = {**os.environ, "PYTHONPATH": TESTS + os.pathsep + os.environ.get("PYTHONPATH", ""), "RAY_USAGE_STATS_ENABLED": "0"}
    temp = f"/tmp/rt{os.getpid()}"
    ray_bin = [sys.executable, "-m", "ray.scripts.scripts"]
    common = ["--node-ip-address", "127.0.0.1", "--disable-usage-stats"]
    subprocess.run([*ray_bin, "start", "--head", "--port", str(port), "--num-cpus", "2", "--include-dashboard", "false",
                    "--temp-dir", temp, *common], env=env, check=True, capture_output=True)
    try:
        subprocess.run([*ray_bin, "start", "--address", f"127.0.0.1:{port}", "--num-cpus", "1", *common],
                       env=env, check=True, capture_output=True)
        log = tmp_path / "log.txt"
        jobs = _jobs(tmp_path / "out", log, n=6, sleep=2.0)
        killed = []

        def kill_one_running_worker():
            # Wait until a job has started, then kill the worker process running it.
            for _ in range(600):
                if log.exists() and log.read_text().strip():
                    pid = int(log.read_text().splitlines()[0].split()[1])
                    os.kill(pid, signal.SIGKILL)
                    killed.append(pid)
                    return
                time.sleep(0.05)

        killer = threading.Thread(target=kill_one_running_worker)
        killer.start()
        done = run_jobs(jobs, executor="ray", ray_address=f"127.0.0.1:{port}", retries=3)
        killer.join()
        assert killed, "no worker was killed"
        assert sorted(done) == [f"job{i}" for i in range(6)]
        assert _squares(tmp_path / "out", 6) == [i * i for i in range(6)]
        attempts = log.read_text().splitlines()
        assert len(attempts) >= 7  # the killed attempt ran again
        assert all(is_done(tmp_path / "out" / f"job{i}", f"k{i}") for i in range(6))
        assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [f"job{i}" for i in range(6)]
        # Ran on both nodes' workers: more than one worker pid committed results.
        assert len({info["worker_pid"] for info in done.values()}) >= 2
    finally:
        ray.shutdown()
        subprocess.run([*ray_bin, "stop", "--force"], env=env, capture_output=True)
