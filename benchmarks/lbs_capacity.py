"""How much of an expression the control points could carry at best (issue 37): the motion basis alone, no images.

    python3 benchmarks/lbs_capacity.py ASSET PROMPT [--control-points 400] [--knn 10] [--defects clean]

Builds the benchmark's grid of ASSET animated by PROMPT and the control points and LBS weights as a reconstruction
builds them, then solves, frame by frame, for the translation of every control point that brings the skinned
vertices closest to the true ones (linear least squares; rotations would add a little). The result is the best any
training could do with that basis: if it misses the expression, more steps or a better loss cannot bring it back.
Prints one JSON object with the expression metric of that best fit (expr_ratio: its error over the rigid oracle's;
recovered, cosine). Measurements: docs/VCDGS_NOTES.md ("The quick preset's motion basis caps a blink at about half").
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import numpy as np  # noqa: E402
import typer  # noqa: E402

from t2bs.cli.exits import run_command  # noqa: E402


def main(
    asset: str = typer.Argument(..., help="turtle, facecap, vipe_hero_head or procedural:NAME."),
    prompt: str = typer.Argument(..., help="Expression prompt, e.g. blinking."),
    control_points: int = typer.Option(400, help="Control points (the quick preset: 400; the paper: 2000)."),
    knn: int = typer.Option(10, help="Control points each vertex is skinned to."),
    defects: str = typer.Option("clean", help="Simulated 4D-model defects: clean, mild, paper."),
) -> None:
    """Fit the control points' translations to the true vertices and print the expression metric of the fit."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.linalg import lsqr

    from t2bs.eval.bench_vcdgs import load_asset
    from t2bs.geometry.metrics import expression_metrics
    from t2bs.recon.config import preset
    from t2bs.recon.control_points import build_control_points
    from t2bs.render.mesh_renderer import MeshRenderer
    from t2bs.video.defects import preset as defect_preset
    from t2bs.video.synth import GridConfig, make_grid

    cfg = preset("quick")
    _, mesh = load_asset(asset)
    with MeshRenderer() as renderer:  # the motion does not depend on the frame size: small renders suffice
        grid = make_grid(mesh, prompt, config=GridConfig(size=64), defects=defect_preset(defects), renderer=renderer)
    cps = build_control_points(
        mesh.vertices, mesh.faces, control_points, knn, cfg.control_points.control_neighbours, seed=cfg.runtime.seed
    )
    n, k = mesh.num_vertices, len(cps.positions)
    rows = np.repeat(np.arange(n), cps.neighbours.shape[1])
    blend = csr_matrix((cps.weights.ravel(), (rows, cps.neighbours.ravel())), shape=(n, k))  # [N, K]
    truth = grid.gt_vertices.astype(np.float64)
    best = np.empty_like(truth)
    for t, frame in enumerate(truth):
        d = frame - mesh.vertices
        moves = np.stack([lsqr(blend, d[:, c], atol=1e-10, btol=1e-10, iter_lim=5000)[0] for c in range(3)], 1)
        best[t] = mesh.vertices + blend @ moves
    m = expression_metrics(best, truth, mesh.vertices)
    print(
        json.dumps(
            {
                "asset": asset,
                "prompt": prompt,
                "defects": defects,
                "control_points": k,
                "knn": knn,
                **{name: round(float(m[name]), 3) for name in ("expr_ratio", "recovered", "cosine")},
            }
        )
    )


if __name__ == "__main__":
    run_command(main)
