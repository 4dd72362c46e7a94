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
