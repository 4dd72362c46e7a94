"""How much of an expression the optical-flow vertex tracks carry, by face region (issue 37).

    python3 benchmarks/track_accuracy.py ASSET PROMPT [--set KEY=VALUE ...] [--defects clean] [--json PATH]

Renders the benchmark's grid of ASSET (turtle, facecap, procedural:NAME, ...) animated by PROMPT (128 px, as
``benchmarks/vcdgs.py``), computes the vertex tracks as a reconstruction does (``recon.vcdgs.vertex_tracks`` with
the quick preset's track settings and any ``--set``; before the lids' tracks are released), and compares them with
the truth's non-rigid image motion: per training view and frame, the true projected motion less that of the rest pose
moved by the true head motion (``geometry.rigid``), counted where it exceeds 0.5 px at a vertex visible at rest. Per
region (``recon.expression_basis.face_regions``: eyes, mouth, elsewhere): how many such (view, frame, vertex) there
are, the share with a valid track, the tracks' least-squares gain on the truth (1 = the whole motion; the head's
motion taken out of both), the same over tracks that start on textured pixels, the mean error and the truth's RMS in
training pixels. A gain well under 1 says the track term pulls that region's motion short. Prints one JSON object.
Measurements: docs/VCDGS_NOTES.md ("What the tracks carry of a smile").
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

SHAPES = ("eyeBlinkLeft", "eyeBlinkRight", "jawOpen", "mouthSmileLeft", "mouthSmileRight")
MIN_PX = 0.5  # true non-rigid motion counted from here (training pixels)


def main(
    asset: str = typer.Argument(..., help="turtle, facecap, vipe_hero_head or procedural:NAME."),
    prompt: str = typer.Argument(..., help="Expression prompt, e.g. smiling."),
    set_options: list[str] = typer.Option(None, "--set", help="Any VCDGS option as KEY=VALUE (repeat)."),
    defects: str = typer.Option("clean", help="Simulated 4D-model defects: clean, mild, paper."),
    size: int = typer.Option(128, help="Grid frame size in pixels (the tracks run at the training resolution)."),
    json_path: Path = typer.Option(None, "--json", help="Also write the JSON object here."),
) -> None:
    """Compare one case's vertex tracks with its true non-rigid image motion, region by region."""
    from t2bs.eval.bench_vcdgs import load_asset
    from t2bs.errors import UserError
    from t2bs.geometry.rigid import apply_motion, robust_rigid_motion
    from t2bs.project import write_json
    from t2bs.recon.config import parse_options, preset
    from t2bs.recon.expression_basis import expression_basis, face_regions
    from t2bs.recon.vcdgs import prepare_data, vertex_tracks
    from t2bs.render.mesh_renderer import MeshRenderer
    from t2bs.video.defects import preset as defect_preset
    from t2bs.video.synth import GridConfig, make_grid

    options = parse_options(set_options or [])
    cfg = preset("quick", **{"time_budget_s": 0.0, "holdout_views": (4, 10), **options})
    _, mesh = load_asset(asset)
    basis, info = expression_basis(mesh, SHAPES)
    if basis is None:
        raise UserError(f"{asset}: no expression basis to split the face by: {info.get('error')}")
    regions = face_regions(basis, info["shapes"])
    with MeshRenderer() as renderer:
        grid = make_grid(mesh, prompt, config=GridConfig(size=size), defects=defect_preset(defects), renderer=renderer)
    data = prepare_data(grid, cfg)
    t0 = time.time()
    tracks = vertex_tracks(mesh, data, cfg)
    seconds = time.time() - t0
    rest, truth = mesh.vertices, grid.gt_vertices
    head = apply_motion(*robust_rigid_motion(rest, truth), rest)  # [T, N, 3]: the rest pose moved by the head
    sums = {name: np.zeros(7) for name in regions}  # moving, valid, d.e, e.e, textured d.e, textured e.e, error
    for v in data.train_views:
        cam = data.cameras[v]
        at_rest = cam.project(rest)[0]
        textured = tracks.textured[v].numpy()
        seen = tracks.weights[v, 0].numpy() > 0  # visible at rest (frame 0's weight is that test alone)
        for t in range(1, truth.shape[0]):
            by_head = cam.project(head[t])[0]
            e = cam.project(truth[t])[0] - by_head  # the truth's non-rigid image motion [N, 2]
            d = tracks.displacement[v, t].numpy() - (by_head - at_rest)  # the tracks' non-rigid part
            valid = tracks.weights[v, t].numpy() > 0
            moving = seen & (np.linalg.norm(e, axis=-1) > MIN_PX)
            for name, sel in regions.items():
                m, ok = sel & moving, sel & moving & valid
                tx = ok & textured
                sums[name] += [
                    m.sum(),
                    ok.sum(),
                    (d[ok] * e[ok]).sum(),
                    (e[ok] ** 2).sum(),
                    (d[tx] * e[tx]).sum(),
                    (e[tx] ** 2).sum(),
                    np.linalg.norm(d[ok] - e[ok], axis=-1).sum(),
                ]
    out = {"asset": asset, "prompt": prompt, "defects": defects, "size": size, "options": set_options or []}
    for name, (moving, valid, de, ee, tde, tee, err) in sums.items():
        out[name] = {
            "moving": int(moving),
            "valid": round(valid / max(moving, 1), 3),
            "gain": round(de / max(ee, 1e-12), 3),
            "gain_textured": round(tde / max(tee, 1e-12), 3),
            "error_px": round(err / max(valid, 1), 3),
            "true_rms_px": round(float(np.sqrt(ee / max(valid, 1))), 3),
        }
    out["track_seconds"] = round(seconds, 1)
    if json_path is not None:
        write_json(json_path, out)
    print(json.dumps(out))


if __name__ == "__main__":
    run_command(main)
