"""A tiny blendshape rig through the Python API alone (no command line): text -> character -> one expression
video -> VCDGS -> blendshape model. Runs on a CPU in a few minutes; the numbers are far from the quick
preset's (64 px, 5 views, 4 frames, 160 VCDGS steps), the calls are the same.

    python3 docs/examples/library_api.py OUT_DIR     # writes OUT_DIR/blendshapes/model.glb
"""

from __future__ import annotations

import sys
from pathlib import Path

from t2bs.blendshapes.stage import BlendshapesConfig
from t2bs.blendshapes.stage import run as build_blendshapes
from t2bs.character.stage import CharacterConfig
from t2bs.character.stage import run as make_character
from t2bs.project import Project
from t2bs.recon.stage import ReconstructConfig
from t2bs.recon.stage import run as reconstruct
from t2bs.video.stage import VideosConfig
from t2bs.video.stage import run as make_videos


def tiny_rig(out_dir: str | Path) -> Path:
    project = Project(out_dir)  # every stage reads and writes this one folder; a re-run skips finished work
    make_character(project, CharacterConfig(prompt="a round-headed cartoon frog", size=64, seed=0))
    make_videos(
        project,
        VideosConfig(
            prompts="opening the mouth extremely wide", samples=1, frames=4, size=64, views=5, defects="clean"
        ),
    )
    # Any VCDGS field (t2bs.recon.config) by name in `options`; time_budget_s=0 runs every step (exact per seed).
    reconstruct(
        project,
        ReconstructConfig(
            iterations=160, control_points=32, preview=False, options={"static_iters": 10, "time_budget_s": 0.0}
        ),
    )
    rig = build_blendshapes(project, BlendshapesConfig(arkit=False))  # ARKit names need the 20 landmarks
    return rig.folder / "model.glb"


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python3 docs/examples/library_api.py OUT_DIR")
    tiny_rig(sys.argv[1])
