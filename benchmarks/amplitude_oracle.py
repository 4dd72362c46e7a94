"""Where an expression is lost: in the images' optimum, or in the motion model (issue 37).

    python3 benchmarks/amplitude_oracle.py ASSET PROMPT [--set KEY=VALUE ...] [--defects clean] [--steps 300]

Builds the benchmark's grid of ASSET (turtle, facecap, procedural:fox, ...) animated by PROMPT, fits the static
Gaussians as a reconstruction does, then replaces the whole motion model by the truth with one unknown per frame:
the splats are placed at the true head motion plus ``s_t`` times the true non-rigid motion (each frame's robust
rigid fit taken out, as in the expression metric), and only ``s_t`` is fitted, with the training loss, by Adam.
If the fitted ``s_t`` comes out near 1, the images hold the expression and a reconstruction that misses it loses
it in the motion model; if not, the splats' appearance biases the photometric optimum itself.

Prints one JSON object: ``amplitude_gain`` (the fitted s_t averaged with weights |non-rigid motion|^2, so the peak
frames count most), ``peak_gain`` (s_t at the frame of largest motion), the per-frame ``s`` and the seconds.

``--direction auto-rig``: instead, the splats follow the true head motion applied to the rest pose plus per-frame
weights of the expression basis's auto-rig shapes (recon/expression_basis.py), the weights alone fitted; prints the
expression error / rigid oracle of those weights (``expr_ratio_images``) beside that of the weights least squares
gives against the true motion (``expr_ratio_least_squares``), and both at the peak frame: whether a reconstruction
with the basis stops at what the images ask for, and how far that is from what the shapes could reach.
Measurements: docs/VCDGS_NOTES.md ("The images hold the blink once the splats end where the lids end", "With the
basis the fit reaches what the images ask for").
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


def main(
    asset: str = typer.Argument(..., help="turtle, facecap, vipe_hero_head or procedural:NAME."),
    prompt: str = typer.Argument(..., help="Expression prompt, e.g. blinking."),
    set_options: list[str] = typer.Option(None, "--set", help="Any VCDGS option as KEY=VALUE (repeat)."),
    defects: str = typer.Option("clean", help="Simulated 4D-model defects: clean, mild, paper."),
    steps: int = typer.Option(300, help="Adam steps on the per-frame amplitudes."),
    seed: int = typer.Option(0, help="Seed of the static fit and the batches."),
    direction: str = typer.Option(
        "truth",
        help="truth: one amplitude per frame of the true non-rigid motion. auto-rig: per-frame weights of the "
        "expression basis's shapes (model.expression_shapes), posed by the true head motion, beside the weights "
        "least squares gives them.",
    ),
) -> None:
    """Fit one amplitude per frame of the true expression and print how much of it the images ask for."""
    import torch

    from t2bs.eval.bench_vcdgs import load_asset
    from t2bs.errors import UserError
    from t2bs.geometry.metrics import expression_metrics
    from t2bs.geometry.rigid import apply_motion, remove_motion, robust_rigid_motion
    from t2bs.recon.expression_basis import expression_basis
    from t2bs.recon.config import parse_options, preset
    from t2bs.recon.gaussians import camera_tensors
    from t2bs.recon.losses import PerceptualLoss, image_loss
    from t2bs.recon.vcdgs import _sample, batch_targets, build_model, prepare_data, render_model, static_splats
    from t2bs.render.mesh_renderer import MeshRenderer
    from t2bs.video.defects import preset as defect_preset
    from t2bs.video.synth import GridConfig, make_grid

    if direction not in ("truth", "auto-rig"):
        raise UserError(f"--direction {direction!r}: use truth or auto-rig")
    t0 = time.time()
    cfg = preset("quick", **{"time_budget_s": 0.0, **parse_options(set_options or [])})
    _, mesh = load_asset(asset)
    with MeshRenderer() as renderer:
        grid = make_grid(mesh, prompt, config=GridConfig(size=128), defects=defect_preset(defects), renderer=renderer)
    torch.manual_seed(seed)
    data = prepare_data(grid, cfg)
    # the expression basis as a reconstruction builds it: it can decide which triangles get face Gaussians
    basis, info = expression_basis(mesh, cfg.model.expression_shapes)
    model, _ = build_model(mesh, data, cfg, expression_basis=basis)
    truth = grid.gt_vertices.astype(np.float64)
    rot, trans = robust_rigid_motion(mesh.vertices, truth)  # each frame's head motion
    head = apply_motion(rot, trans, mesh.vertices)  # [T, N, 3]
    nonrigid = torch.as_tensor(truth - head, dtype=torch.float32)
    head = torch.as_tensor(head, dtype=torch.float32)
    if direction == "auto-rig":
        if basis is None:
            raise UserError(f"no expression basis for {asset}: {info.get('error', info)}")
        rot_t, trans_t = torch.as_tensor(rot, dtype=torch.float32), torch.as_tensor(trans, dtype=torch.float32)
        rest, shapes = torch.as_tensor(mesh.vertices, dtype=torch.float32), torch.as_tensor(basis)
        amp = torch.zeros(data.frames, len(basis), requires_grad=True)

        def pose(t_idx, weights):  # the true head motion of frames t_idx applied to rest + weights . shapes
            local = rest + torch.einsum("bj,jnk->bnk", weights, shapes)
            return torch.einsum("bij,bnj->bni", rot_t[t_idx], local) + trans_t[t_idx, None]
    else:
        amp = torch.zeros(data.frames, requires_grad=True)

        def pose(t_idx, weights):
            return head[t_idx] + weights[:, None, None] * nonrigid[t_idx]

    opt = torch.optim.Adam([amp], lr=0.02)
    vm, ks = camera_tensors(data.cameras)
    w, h = data.size
    perceptual = PerceptualLoss(cfg.loss.perceptual, cfg.loss.lpips_weights)
    gen = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        v_idx, t_idx = _sample(gen, data, cfg.optim.batch_size, 0.0)
        x = pose(t_idx, amp[t_idx])
        out = render_model(model, static_splats(model, len(t_idx), x)["splats"], vm[v_idx], ks[v_idx], w, h)
        target, mask = batch_targets(data, v_idx, t_idx)
        loss = sum(image_loss(out, target, mask, perceptual, cfg).values())
        opt.zero_grad()
        loss.backward()
        opt.step()
    fitted = amp.detach().numpy()
    weight = np.linalg.norm(nonrigid.numpy(), axis=-1).mean(1) ** 2
    if direction == "auto-rig":  # the weights the images ask for, against those least squares gives (no images)
        local = remove_motion(rot, trans, truth) - mesh.vertices  # [T, N, 3] the true motion seen from the head
        flat = basis.reshape(len(basis), -1).T.astype(np.float64)  # [3N, J]
        lsq = np.linalg.lstsq(flat, local.reshape(len(local), -1).T, rcond=None)[0].T  # [T, J]
        all_frames = torch.arange(data.frames)
        with torch.no_grad():
            images = pose(all_frames, torch.as_tensor(fitted)).numpy()
            squares = pose(all_frames, torch.as_tensor(lsq, dtype=torch.float32)).numpy()
        peak = int(weight.argmax())
        result = {
            "shapes": info["shapes"],
            "expr_ratio_images": round(expression_metrics(images, truth, mesh.vertices)["expr_ratio"], 3),
            "expr_ratio_least_squares": round(expression_metrics(squares, truth, mesh.vertices)["expr_ratio"], 3),
            "peak_weights_images": [round(float(x), 3) for x in fitted[peak]],
            "peak_weights_least_squares": [round(float(x), 3) for x in lsq[peak]],
        }
        result["seconds"] = round(time.time() - t0, 1)
        print(
            json.dumps({"asset": asset, "prompt": prompt, "defects": defects, "options": set_options or [], **result})
        )
        return
    print(
        json.dumps(
            {
                "asset": asset,
                "prompt": prompt,
                "defects": defects,
                "options": set_options or [],
                "amplitude_gain": round(float((fitted * weight).sum() / max(weight.sum(), 1e-30)), 3),
                "peak_gain": round(float(fitted[int(weight.argmax())]), 3),
                "s": [round(float(x), 3) for x in fitted],
                "seconds": round(time.time() - t0, 1),
            }
        )
    )


if __name__ == "__main__":
    run_command(main)
