"""Does the training loss prefer the truth? The image loss of a trained reconstruction against that of the truth (issue 37).

    python3 benchmarks/truth_loss.py ASSET PROMPT [--set KEY=VALUE ...] [--defects clean] [--sheet PNG]

Reconstructs the benchmark's grid of ASSET animated by PROMPT (quick preset, no time budget), then scores vertex
positions with the training loss's image terms (every training view, frames 1..T-2), the trained model's static
splats placed at them (no RefineMLP, the static splat shapes, so that only the geometry differs):

- ``loss_fitted``: the trained model's vertices as each view sees them (its view residuals included);
  ``loss_fitted_canonical``: the canonical view's vertices in every view;
- ``loss_truth``: the true vertices;
- ``loss_fitted_head_true_expression`` / ``loss_true_head_fitted_expression``: each frame's head motion (the robust
  rigid fit of the canonical vertices, as the expression metric takes it out) of one with the non-rigid motion of
  the other.

If the truth scores higher than the fit, no optimiser can find the truth on that loss: the loss or the splats'
appearance has to change, not the schedule. At the frame of largest true non-rigid motion, canonical view, the
per-pixel difference (truth minus fit: colour L1 after the silhouette band, and alpha against the dilated mask) is
split into the pixels the true expression changes (``region``: the truth's render differs from the true head motion
applied to the rest pose by over 0.05 in some channel) and the rest; ``--sheet`` writes target | truth | fit | where
the fit wins (red) or the truth wins (green), colour and alpha. Prints one JSON object.
Measurements: docs/VCDGS_NOTES.md ("The fit beats the truth on its own loss").
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

REGION_CHANGE = 0.05  # a pixel belongs to the expression's region when the expression changes it by this much


def main(
    asset: str = typer.Argument(..., help="turtle, facecap, vipe_hero_head or procedural:NAME."),
    prompt: str = typer.Argument(..., help="Expression prompt, e.g. blinking."),
    set_options: list[str] = typer.Option(None, "--set", help="Any VCDGS option as KEY=VALUE (repeat)."),
    defects: str = typer.Option("clean", help="Simulated 4D-model defects: clean, mild, paper."),
    sheet: Path = typer.Option(None, help="Also write the peak frame's comparison here (PNG)."),
) -> None:
    """Reconstruct, then print the image loss of the fit, of the truth and of their mixes (one JSON object)."""
    import torch

    from lid_scene import fitted_vertices, image_loss_at
    from t2bs.eval.bench_vcdgs import load_asset
    from t2bs.geometry.metrics import expression_metrics
    from t2bs.geometry.rigid import apply_rigid_frames, remove_motion, robust_rigid_motion
    from t2bs.recon.config import parse_options, preset
    from t2bs.recon.gaussians import camera_tensors
    from t2bs.recon.losses import silhouette_band
    from t2bs.recon.vcdgs import batch_targets, reconstruct_grid, render_model, static_splats
    from t2bs.render.mesh_renderer import MeshRenderer
    from t2bs.video.defects import preset as defect_preset
    from t2bs.video.synth import GridConfig, make_grid

    t0 = time.time()
    cfg = preset("quick", **{"time_budget_s": 0.0, **parse_options(set_options or [])})
    _, mesh = load_asset(asset)
    with MeshRenderer() as renderer:
        grid = make_grid(mesh, prompt, config=GridConfig(size=128), defects=defect_preset(defects), renderer=renderer)
    res = reconstruct_grid(mesh, grid, cfg, progress=False)
    model, data = res.model, res.data
    views, cv = data.views, data.canonical_view
    metric = expression_metrics(res.vertices, grid.gt_vertices, mesh.vertices)
    fitted = fitted_vertices(model, data)
    truth = grid.gt_vertices.astype(np.float64)
    rot, trans = robust_rigid_motion(mesh.vertices, truth)
    true_local = remove_motion(rot, trans, truth)  # [T, N, 3]
    fit = fitted[:, cv].numpy().astype(np.float64)
    frot, ftrans = robust_rigid_motion(mesh.vertices, fit)
    fit_local = remove_motion(frot, ftrans, fit)

    def every_view(x: np.ndarray) -> torch.Tensor:  # [T, N, 3] -> [T, V, N, 3]
        return torch.as_tensor(np.asarray(x), dtype=torch.float32)[:, None].expand(-1, views, -1, -1)

    poses = {
        "fitted": fitted,
        "fitted_canonical": fitted[:, cv : cv + 1].expand(-1, views, -1, -1),
        "truth": every_view(truth),
        "fitted_head_true_expression": every_view(apply_rigid_frames(frot, ftrans, true_local)),
        "true_head_fitted_expression": every_view(apply_rigid_frames(rot, trans, fit_local)),
    }
    out = {f"loss_{k}": image_loss_at(model, data, cfg, x) for k, x in poses.items()}

    # The peak frame, canonical view: where each wins, per pixel.
    peak = int(np.linalg.norm(true_local - mesh.vertices, axis=-1).mean(1).argmax())
    vm, ks = camera_tensors(data.cameras)
    w, h = data.size

    def draw(x: torch.Tensor) -> dict:
        return render_model(model, static_splats(model, 1, x[None])["splats"], vm[[cv]], ks[[cv]], w, h)

    with torch.no_grad():
        target, mask = batch_targets(data, torch.tensor([cv]), torch.tensor([peak]))
        if mask is None:
            mask = torch.ones(target.shape[:3])

        def errors(r: dict) -> tuple[torch.Tensor, torch.Tensor]:
            rgb, dil = silhouette_band(r["rgb"], target, mask, cfg.loss.silhouette_band)
            return (rgb - target).abs().sum(-1)[0], (r["alpha"][..., 0] - dil).abs()[0]

        r_truth, r_fit = draw(poses["truth"][peak, cv]), draw(fitted[peak, cv])
        head_only = torch.as_tensor(
            apply_rigid_frames(rot[peak : peak + 1], trans[peak : peak + 1], mesh.vertices[None])
        )
        region = (r_truth["rgb"] - draw(head_only[0].float())["rgb"]).abs().amax(-1)[0] > REGION_CHANGE
        (c_truth, a_truth), (c_fit, a_fit) = errors(r_truth), errors(r_fit)
        gain_c, gain_a = c_truth - c_fit, a_truth - a_fit  # > 0: the fit matches the image better there
    out["peak_frame"] = peak
    out["region_pixels"] = int(region.sum())
    for name, g in (("colour", gain_c), ("alpha", gain_a)):
        out[f"peak_{name}_truth_minus_fit_region"] = round(float(g[region].sum()), 3)
        out[f"peak_{name}_truth_minus_fit_elsewhere"] = round(float(g[~region].sum()), 3)
    if sheet is not None:
        from PIL import Image

        def wins(g: torch.Tensor) -> torch.Tensor:
            return torch.stack([(3 * g).clamp(0, 1), (-3 * g).clamp(0, 1), torch.zeros_like(g)], -1)

        tiles = [target[0], r_truth["rgb"][0], r_fit["rgb"][0], wins(gain_c), wins(gain_a)]
        img = (torch.cat(tiles, 1).clamp(0, 1).numpy() * 255).astype(np.uint8)
        sheet.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(img).resize((img.shape[1] * 3, img.shape[0] * 3), Image.NEAREST).save(sheet)
    result = {
        "asset": asset,
        "prompt": prompt,
        "defects": defects,
        "options": set_options or [],
        **{k: round(float(metric[k]), 4) for k in ("expr_ratio", "recovered", "cosine")},
        **out,
        "seconds": round(time.time() - t0, 1),
    }
    print(json.dumps(result))


if __name__ == "__main__":
    run_command(main)
