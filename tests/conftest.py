"""Shared fixtures. Real assets live in ../shared/assets beside the clone or in $T2BS_SHARED_ASSETS (never in the
repo; t2bs.shared_assets)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from t2bs.shared_assets import shared_asset, shared_assets_dir  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
ASSETS = shared_assets_dir()


def asset(name: str) -> Path:
    """Path of a shared test asset (turtle.glb, facecap.glb, vipe_hero_head.glb). Absent: the test is skipped on a
    developer's machine, and fails in CI (``CI=true``), where the assets are always beside the clone."""
    path = shared_asset(name)
    if not path.exists():
        why = f"shared asset {path} not present (set T2BS_SHARED_ASSETS or put shared/assets beside the checkout)"
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(why)
        pytest.skip(why)
    return path


@pytest.fixture(scope="session")
def mesh_renderer():
    """One headless GL context for the whole session (creating one costs ~50 ms)."""
    from t2bs.render.mesh_renderer import MeshRenderer

    renderer = MeshRenderer()
    yield renderer
    renderer.release()
