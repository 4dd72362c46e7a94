"""The lid scene (issue 37): how much of a lid sliding over a dark eye VCDGS recovers, with any settings.

    python3 benchmarks/lid_scene.py [--set KEY=VALUE ...] [--self-targets] [--size 64]

A still sphere whose lid (a separate thin cap) turns 14 deg down over a dark eye (`t2bs.eval.scenes.lid_scene`, 64 px,
6 frames, 5 views); VCDGS with the photometric loss alone (`track_weight=0`, 400 steps, 80 of them warm-up, no time
budget, no hidden-part pick), then any `--set` on top. ``--self-targets`` replaces the grid's frames by renders of
the model's own fitted Gaussians at the true vertex positions: targets the splat model can reproduce exactly, so
the difference to a normal run is what the splat / mesh-render appearance gap costs. ``--scan`` adds where the
training loss's image terms (every view, the frames between the first and the last) put the lid: ``scan_truth``,
the static Gaussians at the rest pose plus s times the true motion, for a few s (its minimum: the amount of the true
motion the images ask for), and ``loss_trained`` / ``loss_truth``, the same loss with the splats at the trained
model's vertices / at the true ones (static splat shapes, no RefineMLP). Prints one JSON object: recovered, cosine
and expr_ratio (the expression metric, t2bs.geometry.metrics), lid_gain (least-squares gain of the lid vertices'
motion against the truth) and seconds. Measurements: docs/VCDGS_NOTES.md, "The lid scene".
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import typer  # noqa: E402

from t2bs.cli.exits import run_command  # noqa: E402

LID_SETTINGS = dict(
    resolution=64, track_weight=0.0, iterations=400, global_iters=80, time_budget_s=0.0, hidden_pick=False
)


def self_targets(model, data, gt_vertices) -> None:
    """Overwrite ``data``'s images (and masks) with the model's static Gaussians rendered at ``gt_vertices`` [T, N, 3]."""
    import torch

    from t2bs.recon.gaussians import camera_tensors
    from t2bs.recon.vcdgs import render_model, static_splats

    vm, ks = camera_tensors(data.cameras)
    w, h = data.size
    v = data.views
    with torch.no_grad():
        for t in range(data.frames):
            x = torch.as_tensor(gt_vertices[t])[None].expand(v, -1, -1)
            out = render_model(model, static_splats(model, v, x)["splats"], vm, ks, w, h)
            data.images[:, t] = out["rgb"]
            if data.masks is not None:
                data.masks[:, t] = out["alpha"][..., 0]


SCAN_AMOUNTS = (0.0, 0.5, 0.7, 0.8, 0.9, 1.0, 1.1, 1.2)


def image_loss_at(model, data, cfg, vertices) -> float:
    """The training loss's image terms, summed over every view and the frames 1..T-2, with the static splats placed at
    ``vertices`` [T, V, N, 3] (per frame and view)."""
    import torch

    from t2bs.recon.gaussians import camera_tensors
    from t2bs.recon.losses import PerceptualLoss, image_loss_per_item
    from t2bs.recon.vcdgs import batch_targets, render_model, static_splats

    vm, ks = camera_tensors(data.cameras)
    w, h = data.size
    v = data.views
    perceptual = PerceptualLoss(cfg.loss.perceptual, cfg.loss.lpips_weights)
    total = 0.0
    v_idx = torch.arange(v)
    with torch.no_grad():
        for t in range(1, data.frames - 1):
            out = render_model(model, static_splats(model, v, vertices[t])["splats"], vm, ks, w, h)
            target, mask = batch_targets(data, v_idx, torch.full_like(v_idx, t))
            total += float(image_loss_per_item(out, target, mask, perceptual, cfg).sum())
    return round(total, 5)


def fitted_vertices(model, data):
    """[T, V, N, 3] the trained model's vertices at every frame as each view sees them (no RefineMLP)."""
    import torch

    with torch.no_grad():
        views = torch.arange(data.views)
        return torch.stack([model(views, torch.full_like(views, t), refine=False)["means"] for t in range(data.frames)])


def main(
    set_options: list[str] = typer.Option(
        None, "--set", help="Any VCDGS option as KEY=VALUE (repeat), over the scene's settings."
    ),
    self_targets_on: bool = typer.Option(
        False, "--self-targets", help="Train on the model's own renders of the truth."
    ),
    size: int = typer.Option(64, help="Grid and training resolution, px."),
    scan: bool = typer.Option(False, "--scan", help="Also print the image loss along the true motion and at the fit."),
) -> None:
    """Reconstruct the lid scene and print how much of the lid's motion came back (one JSON object)."""
    from t2bs.eval.scenes import lid_scene
    from t2bs.geometry.metrics import expression_metrics
    from t2bs.recon.config import parse_options, preset
    from t2bs.recon.extract import canonical_vertices, smooth_displacements
    from t2bs.recon.vcdgs import build_model, deterministic_on_cpu, prepare_data, train

    options = parse_options(set_options or [])
    cfg = preset("quick", **{**LID_SETTINGS, "resolution": size, **options})
    mesh, grid = lid_scene(frames=6, size=size)
    import torch

    t0 = time.time()
    torch.manual_seed(cfg.runtime.seed)  # as reconstruct_grid does: the same rows as a normal reconstruction
    if cfg.runtime.threads > 0:
        torch.set_num_threads(cfg.runtime.threads)
    data = prepare_data(grid, cfg)
    with deterministic_on_cpu(cfg):
        model, _ = build_model(mesh, data, cfg)
        if self_targets_on:
            self_targets(model, data, grid.gt_vertices)
        extra = {}
        if scan:
            rest = torch.as_tensor(mesh.vertices)
            truth = torch.as_tensor(grid.gt_vertices)[:, None].expand(-1, data.views, -1, -1)  # [T, V, N, 3]
            extra["scan_truth"] = {
                str(a): image_loss_at(model, data, cfg, rest + a * (truth - rest)) for a in SCAN_AMOUNTS
            }
        train(model, data, cfg, progress=False)
        if scan:
            extra["loss_trained"] = image_loss_at(model, data, cfg, fitted_vertices(model, data))
            extra["loss_truth"] = image_loss_at(model, data, cfg, truth)
    verts = smooth_displacements(canonical_vertices(model), mesh.vertices, mesh.faces, cfg.output.output_smoothing)
    m = expression_metrics(verts, grid.gt_vertices, mesh.vertices)
    lid = mesh.part_mask("eyelid_left")
    true, moved = grid.gt_vertices[:, lid] - mesh.vertices[lid], verts[:, lid] - mesh.vertices[lid]
    gain = float((true * moved).sum() / (true**2).sum())
    print(
        json.dumps(
            {
                "options": set_options or [],
                "self_targets": self_targets_on,
                "size": size,
                **{k: round(float(m[k]), 4) for k in ("recovered", "cosine", "expr_ratio")},
                "lid_gain": round(gain, 4),
                **extra,
                "seconds": round(time.time() - t0, 1),
            }
        )
    )


if __name__ == "__main__":
    run_command(main)
