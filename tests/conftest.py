"""Shared fixtures. Real assets live in ../shared/assets beside the clone (never in the repo)."""

from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads (see t2bs/__init__.py)

import pytest

REPO = Path(__file__).resolve().parents[1]
ASSETS = REPO.parent / "shared" / "assets"


def asset(name: str) -> Path:
    """Path of a shared test asset (turtle.glb, facecap.glb, vipe_hero_head.glb); skip if absent."""
    path = ASSETS / name
    if not path.exists():
        pytest.skip(f"shared asset {path} not present")
    return path


@pytest.fixture(scope="session")
def mesh_renderer():
    """One headless GL context for the whole session (creating one costs ~50 ms)."""
    from t2bs.render.mesh_renderer import MeshRenderer

    renderer = MeshRenderer()
    yield renderer
    renderer.release()
