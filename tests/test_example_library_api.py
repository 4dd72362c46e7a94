"""docs/examples/library_api.py: a tiny rig through the Python API alone, run as a user would."""

import ast
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

EXAMPLE = Path(__file__).resolve().parents[1] / "docs" / "examples" / "library_api.py"


def test_the_example_uses_the_library_only():
    tree = ast.parse(EXAMPLE.read_text())
    modules = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    modules |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    assert not any(m.startswith(("t2bs.cli", "typer", "subprocess")) for m in modules), modules


@pytest.mark.slow
def test_the_example_makes_a_rig_whose_mouth_opens(tmp_path):
    from t2bs.geometry.io import load_mesh

    out = tmp_path / "rig"
    r = subprocess.run([sys.executable, str(EXAMPLE), str(out)], capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    rig = load_mesh(out / "blendshapes" / "model.glb")
    assert rig.morph_targets, "the rig has no shapes"
    # The one prompt opens the mouth (the frog's jaw moves ~7 % of the diagonal in truth): the rig has a shape
    # that moves it by more than 3 %, and the reconstruction beats the rigid oracle (a neutral face) by a margin.
    diag = float(np.linalg.norm(rig.vertices.max(0) - rig.vertices.min(0)))
    largest = max(float(np.linalg.norm(d, axis=1).max()) for d in rig.morph_targets.values())
    assert largest > 0.03 * diag, largest / diag
    (metrics,) = [json.loads(p.read_text()) for p in (out / "recon").glob("*/metrics.json")]
    assert metrics["expression"]["expr_ratio"] < 0.75 and metrics["expression"]["cosine"] > 0.7, metrics["expression"]
    again = subprocess.run([sys.executable, str(EXAMPLE), str(out)], capture_output=True, text=True, timeout=900)
    assert again.returncode == 0 and "0 reconstructed, 1 up to date" in again.stdout  # a re-run skips finished work
