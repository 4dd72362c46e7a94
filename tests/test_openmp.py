"""The OpenMP wait policy t2bs chooses before torch loads (t2bs/openmp.py): the user's wins, workers share."""

from __future__ import annotations

import os

import pytest

from t2bs import openmp


@pytest.fixture
def env(monkeypatch):
    for k in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", openmp.CHOSEN):
        monkeypatch.delenv(k, raising=False)
    return monkeypatch


def test_alone_spins_briefly_busy_waits_passively(env):
    env.setattr(openmp, "cores_busy", lambda: False)
    assert openmp.choose_wait_policy() == "spin"
    assert os.environ["GOMP_SPINCOUNT"] == openmp.SPIN_COUNT and "OMP_WAIT_POLICY" not in os.environ
    for k in ("GOMP_SPINCOUNT", openmp.CHOSEN):
        env.delenv(k)
    env.setattr(openmp, "cores_busy", lambda: True)
    assert openmp.choose_wait_policy() == "passive"
    assert os.environ["OMP_WAIT_POLICY"] == "PASSIVE" and "GOMP_SPINCOUNT" not in os.environ


def test_the_users_own_setting_wins(env):
    env.setenv("OMP_WAIT_POLICY", "ACTIVE")
    assert openmp.choose_wait_policy() is None and openmp.choose_wait_policy(shared=True) is None
    assert os.environ["OMP_WAIT_POLICY"] == "ACTIVE" and openmp.CHOSEN not in os.environ


def test_a_worker_keeps_its_pools_choice_and_the_pool_restores(env):
    env.setattr(openmp, "cores_busy", lambda: False)
    assert openmp.choose_wait_policy() == "spin"
    with openmp.shared_cores():  # what a spawned worker inherits
        assert os.environ["OMP_WAIT_POLICY"] == "PASSIVE" and "GOMP_SPINCOUNT" not in os.environ
        assert openmp.choose_wait_policy() == "passive"  # the worker's own import: kept, not re-decided
    assert os.environ["GOMP_SPINCOUNT"] == openmp.SPIN_COUNT and "OMP_WAIT_POLICY" not in os.environ
    assert os.environ[openmp.CHOSEN] == "spin"


def test_cores_busy_reads_other_processes_cpu_time(monkeypatch):
    monkeypatch.setattr(openmp.os, "cpu_count", lambda: 2)
    for ticks, busy in (([(1000, 500), (1030, 529)], False), ([(1000, 500), (1030, 515)], True)):
        samples = iter(ticks)  # 30 ticks on 2 cores; 1 (1/15 of a core) or 15 (one core) not idle
        monkeypatch.setattr(openmp, "cpu_ticks", lambda: next(samples))
        assert openmp.cores_busy(seconds=0) is busy

    def missing():
        raise FileNotFoundError("/proc/stat")

    monkeypatch.setattr(openmp, "cpu_ticks", missing)
    assert openmp.cores_busy(seconds=0) is False
