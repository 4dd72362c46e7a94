"""Where the shared test assets live (turtle.glb, facecap.glb, vipe_hero_head.glb: characters with real blendshapes).

They are never in the repository (their licences differ from the code's); a checkout finds them in
``$T2BS_SHARED_ASSETS``, else in ``../shared/assets`` beside the checkout. Benchmarks, the retarget command's default
target and the tests all resolve them here, by the same rule."""

from __future__ import annotations

import os
from pathlib import Path

ENV = "T2BS_SHARED_ASSETS"


def shared_assets_dir() -> Path:
    """``$T2BS_SHARED_ASSETS`` if set, else ``shared/assets`` beside the checkout this package runs from."""
    if os.environ.get(ENV):
        return Path(os.environ[ENV]).expanduser()
    return Path(__file__).resolve().parents[3] / "shared" / "assets"  # src/t2bs/ -> the checkout -> beside it


def shared_asset(name: str) -> Path:
    """The path of one shared asset, e.g. ``shared_asset("turtle.glb")`` (it may not exist: callers say so)."""
    return shared_assets_dir() / name
