"""How much of an expression the motion model could carry at best (issue 37): its basis alone, no images.

    python3 benchmarks/lbs_capacity.py ASSET PROMPT [--control-points 400] [--knn 10] [--defects clean]
        [--rotations/--no-rotations] [--basis/--no-basis]

Builds the benchmark's grid of ASSET animated by PROMPT and the control points, LBS weights and expression basis as a
reconstruction builds them, takes each frame's head motion out of the truth (the model's global SE(3) carries it),
then solves, frame by frame, for the motion that brings the rest pose closest to the true non-rigid one (linear least
squares): a translation per control point, with ``--rotations`` a small rotation per control point as well (the
DeformMLP outputs both; linearised, exact to first order in the angle), and with ``--basis`` a weight per expression
shape (the auto rig's, as ``model.expression_shapes`` picks them; added to the rest pose before the skinning, as the
model adds them). The result is the best any training could do with that motion model: if it misses the expression,
more steps or a better loss cannot bring it back. Prints one JSON object with the expression metric of that best fit
(expr_ratio: its error over the rigid oracle's; recovered, cosine). Measurements: docs/VCDGS_NOTES.md ("What the
quick preset's motion model can carry").
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import numpy as np  # noqa: E402
import typer  # noqa: E402

from t2bs.cli.exits import run_command  # noqa: E402


def motion_design(
    vertices: np.ndarray,
    positions: np.ndarray,
    neighbours: np.ndarray,
    weights: np.ndarray,
    rotations: bool,
    basis: np.ndarray | None,
):
    """The linear map from motion parameters to vertex displacements, as a sparse [3N, P] matrix.

    vertices [N, 3] rest pose; positions [K, 3] control points; neighbours, weights [N, knn] the LBS binding; columns:
    per control point its translation (3) and, with ``rotations``, its rotation vector (3; the displacement
    w x (x - p_k), first order in the angle); then one column per shape of ``basis`` [J, N, 3]."""
    from scipy.sparse import csr_matrix, hstack

    n, k = len(vertices), len(positions)
    per = 6 if rotations else 3
    rows = np.repeat(np.arange(n), neighbours.shape[1])
    nb, wt = neighbours.ravel(), weights.ravel().astype(np.float64)
    arm = np.asarray(vertices, np.float64)[rows] - positions[nb]  # [N * knn, 3] x_i - p_k
    r, c, val = [], [], []
    for axis in range(3):
        r.append(3 * rows + axis), c.append(per * nb + axis), val.append(wt)
        if rotations:  # (w x arm)_axis = w_a arm_b - w_b arm_a
            a, b = (axis + 1) % 3, (axis + 2) % 3
            r += [3 * rows + axis, 3 * rows + axis]
            c += [per * nb + 3 + a, per * nb + 3 + b]
            val += [wt * arm[:, b], -wt * arm[:, a]]
    lbs = csr_matrix((np.concatenate(val), (np.concatenate(r), np.concatenate(c))), shape=(3 * n, per * k))
    if basis is None or not len(basis):
        return lbs
    return hstack([lbs, csr_matrix(basis.reshape(len(basis), -1).T.astype(np.float64))]).tocsr()


def main(
    asset: str = typer.Argument(..., help="turtle, facecap, vipe_hero_head or procedural:NAME."),
    prompt: str = typer.Argument(..., help="Expression prompt, e.g. blinking."),
    control_points: int = typer.Option(400, help="Control points (the quick preset: 400; the paper: 2000)."),
    knn: int = typer.Option(10, help="Control points each vertex is skinned to."),
    defects: str = typer.Option("clean", help="Simulated 4D-model defects: clean, mild, paper."),
    rotations: bool = typer.Option(True, help="A rotation per control point as well as a translation."),
    basis: bool = typer.Option(True, help="The expression basis (the auto rig's shapes) as well."),
) -> None:
    """Fit the motion model to the true non-rigid motion and print the expression metric of the fit."""
    from scipy.linalg import pinvh

    from t2bs.eval.bench_vcdgs import load_asset
    from t2bs.geometry.metrics import expression_metrics
    from t2bs.geometry.rigid import nonrigid_displacements
    from t2bs.recon.config import preset
    from t2bs.recon.control_points import build_control_points
    from t2bs.recon.expression_basis import expression_basis
    from t2bs.render.mesh_renderer import MeshRenderer
    from t2bs.video.defects import preset as defect_preset
    from t2bs.video.synth import GridConfig, make_grid

    cfg = preset("quick")
    _, mesh = load_asset(asset)
    with MeshRenderer() as renderer:  # the motion does not depend on the frame size: small renders suffice
        grid = make_grid(mesh, prompt, config=GridConfig(size=64), defects=defect_preset(defects), renderer=renderer)
        shapes, info = expression_basis(mesh, cfg.model.expression_shapes, renderer=renderer) if basis else (None, {})
    cps = build_control_points(
        mesh.vertices, mesh.faces, control_points, knn, cfg.control_points.control_neighbours, seed=cfg.runtime.seed
    )
    design = motion_design(mesh.vertices, cps.positions, cps.neighbours, cps.weights, rotations, shapes)
    rest = mesh.vertices.astype(np.float64)
    motion, _, _ = nonrigid_displacements(rest, grid.gt_vertices)  # [T, N, 3] the truth as seen from the head
    # Least squares through the normal equations' pseudo-inverse, formed once: a control point whose vertices all lie
    # on a line leaves its rotation about that line free (a null direction, which the pseudo-inverse leaves at 0).
    solve = pinvh((design.T @ design).toarray())  # [P, P]
    best = rest + np.stack([(design @ (solve @ (design.T @ d.ravel()))).reshape(-1, 3) for d in motion])
    m = expression_metrics(best, rest + motion, mesh.vertices)
    print(
        json.dumps(
            {
                "asset": asset,
                "prompt": prompt,
                "defects": defects,
                "control_points": len(cps.positions),
                "knn": knn,
                "rotations": rotations,
                "basis": info.get("shapes", []),
                **{name: round(float(m[name]), 3) for name in ("expr_ratio", "recovered", "cosine")},
            }
        )
    )


if __name__ == "__main__":
    run_command(main)
