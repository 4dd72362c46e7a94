"""Where a reconstruction loses an expression: the eyes or the mouth (issue 37).

    python3 benchmarks/expression_regions.py ASSET PROMPT [--set KEY=VALUE ...] [--defects clean] [--json PATH]

Reconstructs the benchmark's grid of ASSET (turtle, facecap, procedural:fox, ...) animated by PROMPT, as
``benchmarks/vcdgs.py`` does for the method ``full`` (quick preset, ``--time-budget 0``, held-out views 4 and 10),
then splits the expression metric (geometry.metrics.expression_metrics: each frame's head motion taken out) by region:
``eyes``, the vertices the auto rig's blinks move; ``mouth``, those its jaw and smiles move (a vertex both move counts
where it moves more; each shape's support: displacement above 2 % of its largest); ``elsewhere``, the rest. Per
region: the share of the whole expression error, the ratio to the rigid oracle's, recovered / true and the cosine.
Also the learned weights of the expression basis at the frame of largest true motion. A smiling capture that also
narrows the eyes shows here which of the two the fit misses. Needs the expression basis (a face the auto rig finds).
Prints one JSON object. Measurements: docs/VCDGS_NOTES.md ("The fox's smile is lost at the mouth").
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import numpy as np  # noqa: E402
import typer  # noqa: E402

from t2bs.cli.exits import run_command  # noqa: E402

EYES = ("eyeBlinkLeft", "eyeBlinkRight")
MOUTH = ("jawOpen", "mouthSmileLeft", "mouthSmileRight")


def main(
    asset: str = typer.Argument(..., help="turtle, facecap, vipe_hero_head or procedural:NAME."),
    prompt: str = typer.Argument(..., help="Expression prompt, e.g. smiling."),
    set_options: list[str] = typer.Option(None, "--set", help="Any VCDGS option as KEY=VALUE (repeat)."),
    defects: str = typer.Option("clean", help="Simulated 4D-model defects: clean, mild, paper."),
    json_path: Path = typer.Option(None, "--json", help="Also write the JSON object here."),
) -> None:
    """Reconstruct one case and split its expression error between the eyes and the mouth."""
    from t2bs.eval.bench_vcdgs import load_asset
    from t2bs.errors import UserError
    from t2bs.geometry.metrics import expression_metrics
    from t2bs.geometry.rigid import nonrigid_displacements
    from t2bs.project import write_json
    from t2bs.recon.config import parse_options, preset
    from t2bs.recon.expression_basis import expression_basis, face_regions
    from t2bs.recon.vcdgs import reconstruct_grid
    from t2bs.render.mesh_renderer import MeshRenderer
    from t2bs.video.defects import preset as defect_preset
    from t2bs.video.synth import GridConfig, make_grid

    t0 = time.time()
    options = parse_options(set_options or [])
    cfg = preset("quick", **{"time_budget_s": 0.0, "holdout_views": (4, 10), **options})
    _, mesh = load_asset(asset)
    basis, info = expression_basis(mesh, EYES + MOUTH)
    if basis is None or info.get("missing"):
        why = info.get("error") or f"no {', '.join(info.get('missing') or EYES + MOUTH)} shape"
        raise UserError(f"{asset}: no expression basis to split the face by: {why}")
    regions = face_regions(basis, info["shapes"])
    with MeshRenderer() as renderer:
        grid = make_grid(mesh, prompt, config=GridConfig(size=128), defects=defect_preset(defects), renderer=renderer)
    res = reconstruct_grid(mesh, grid, cfg, progress=False)
    gt, pred, rest = grid.gt_vertices, res.vertices, mesh.vertices
    whole = expression_metrics(pred, gt, rest)
    whole_error = whole["expr_p2p"] * whole["expr_fraction"]  # summed error over all (frame, vertex) pairs, scaled
    out = {"asset": asset, "prompt": prompt, "defects": defects, "options": set_options or [], "whole": whole}
    for name, sel in regions.items():
        m = expression_metrics(pred, gt, rest, select=sel)
        share = m["expr_p2p"] * m["expr_fraction"] / whole_error if m["expr_fraction"] else 0.0
        out[name] = {
            "vertices": int(sel.sum()),
            "error_share": round(float(share), 3),
            **{k: m[k] for k in ("expr_ratio", "recovered", "cosine", "expr_fraction")},
        }
    e_gt = nonrigid_displacements(rest, gt)[0]
    peak = int(np.argmax(np.linalg.norm(e_gt, axis=-1).sum(1)))
    weights = res.expression.get("weights")
    out["peak_frame"] = peak
    out["shapes"] = res.expression.get("shapes", [])
    out["peak_weights"] = np.round(np.asarray(weights)[peak], 3).tolist() if weights is not None else None
    out["seconds"] = round(time.time() - t0, 1)
    if json_path is not None:
        write_json(json_path, out)
    print(json.dumps(out))


if __name__ == "__main__":
    run_command(main)
