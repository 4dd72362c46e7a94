"""Can the motion model learn an expression at all in the preset's steps (issue 37)? The true 3D vertices, no images.

    python3 benchmarks/motion_fit.py ASSET PROMPT [--set KEY=VALUE ...] [--head-motion/--no-head-motion] [--seen-only]
        [--basis] [--projected [--absolute [--all-views]] [--canonical-model]]

Builds the benchmark's grid of ASSET animated by PROMPT and an untrained VCDGS model as a reconstruction builds it
(control points, LBS weights, DeformMLP, global SE(3)), then trains it with the reconstruction's schedule (the global
warm-up, the joint stage, the learning rates and their decay: ``vcdgs._lr_factor``) on the squared distance of the
canonical view's deformed vertices to the true ones, instead of on images. Prints one JSON object with the
expression metric of the result (expr_ratio: its error over the rigid oracle's; recovered, cosine) and the loss
after the warm-up against the rigid oracle's (the true head motion with a neutral face): a warm-up loss far above
it means the head motion is not settled when the expression has to be learnt.

If this misses the expression, no image loss or track term can bring it back with these settings; if it finds it,
what is lost in a reconstruction is lost in the supervision. ``--no-head-motion`` takes each frame's rigid motion
out of the truth (and trains without the global SE(3)): the motion model alone. ``--seen-only`` supervises only the
vertices some training view sees at rest, those tracks can reach: perfect 3D tracks. No pick of hidden parts here,
and no expression basis unless ``--basis`` (its weights learnt with the rest as a reconstruction learns them, without
its picks by render), so a reconstruction can beat it where those help (a wide mouth). ``--projected`` supervises
perfect 2D tracks instead: per sampled (view, time), as training samples them, the squared pixel distance of the
projected deformed vertices to the truth's, over the vertices that view sees at rest; the model evaluated at that view
(``--canonical-model``: at the canonical view, one geometry for all views); the motion from frame 0 as the track term
measures it, or with ``--absolute`` the positions (the motion alone leaves the rest pose free, which images pin);
``--all-views`` (with ``--absolute``) holds each sample's geometry to every training view's projections at its frame.
``by_views_seeing`` splits the expression error by how many training views see a vertex at rest; ``depth_share`` is the
share of its square along the canonical camera's axis (over all vertices; over those four or more views see).
Measurements: docs/VCDGS_NOTES.md ("The head motion's noise swamps a blink", "What perfect tracks would buy",
"From 3D to 2D").
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
    set_options: list[str] = typer.Option([], "--set", help="VCDGS option KEY=VALUE of the quick preset (repeat)."),
    head_motion: bool = typer.Option(True, help="Keep the animator's head motion in the truth (else: taken out)."),
    defects: str = typer.Option("clean", help="Simulated 4D-model defects: clean, mild, paper."),
    seen_only: bool = typer.Option(
        False, "--seen-only", help="Supervise only the vertices some training view sees at rest (where tracks are)."
    ),
    basis: bool = typer.Option(
        False, "--basis", help="Learn the expression basis' weights too, as a reconstruction does (no image picks)."
    ),
    projected: bool = typer.Option(
        False,
        "--projected",
        help="Supervise with perfect 2D tracks: each sampled (view, time)'s projected motion from frame 0 of the "
        "vertices that view sees at rest, the model evaluated at that view (as the track term does).",
    ),
    absolute: bool = typer.Option(
        False, "--absolute", help="With --projected: supervise the projected positions, not the motion from frame 0."
    ),
    all_views: bool = typer.Option(
        False, "--all-views", help="With --projected --absolute: each sample's geometry against every view's tracks."
    ),
    canonical_model: bool = typer.Option(
        False, "--canonical-model", help="With --projected: evaluate the model at the canonical view for every view."
    ),
) -> None:
    """Train the motion model on the true vertices and print the expression metric of the fit."""
    import torch

    from t2bs.errors import UserError
    from t2bs.eval.bench_vcdgs import load_asset
    from t2bs.geometry.metrics import expression_metrics
    from t2bs.geometry.rigid import nonrigid_displacements
    from t2bs.recon.config import parse_options, preset
    from t2bs.recon.extract import canonical_vertices
    from t2bs.recon.tracks import rest_visibility
    from t2bs.recon.expression_basis import expression_basis
    from t2bs.recon.vcdgs import (
        WARM_UP_GROUPS,
        _lr_factor,
        _Schedule,
        build_model,
        param_groups,
        prepare_data,
        warm_up_steps,
    )
    from t2bs.render.mesh_renderer import MeshRenderer
    from t2bs.video.defects import preset as defect_preset
    from t2bs.video.synth import GridConfig, make_grid

    if (absolute or all_views or canonical_model) and not projected:
        raise UserError("--absolute, --all-views and --canonical-model go with --projected")
    if all_views and not absolute:
        raise UserError("--all-views needs --absolute (the motion from frame 0 is measured at each sample's own view)")
    over = {**parse_options(set_options), "static_iters": 0}
    if not head_motion:
        over["method"] = "no_global"
    cfg = preset("quick", **over)
    torch.set_num_threads(cfg.runtime.threads or torch.get_num_threads())
    _, mesh = load_asset(asset)
    with MeshRenderer() as renderer:  # the motion does not depend on the frame size: small renders suffice
        grid = make_grid(mesh, prompt, config=GridConfig(size=64), defects=defect_preset(defects), renderer=renderer)
    rest = mesh.vertices.astype(np.float64)
    truth = grid.gt_vertices.astype(np.float64)  # [T, N, 3]
    expression = nonrigid_displacements(rest, truth)[0]  # [T, N, 3] in the head's frame
    if not head_motion:
        truth = rest[None] + expression
    diag = float(np.linalg.norm(rest.max(0) - rest.min(0)))
    oracle = float((expression**2).sum(-1).mean()) / diag**2  # the rigid oracle's loss
    data = prepare_data(grid, cfg)
    torch.manual_seed(cfg.runtime.seed)
    shapes, info = None, {"shapes": []}
    if basis:
        shapes, info = expression_basis(mesh, cfg.model.expression_shapes)
        if shapes is None:
            raise UserError(f"{asset}: no expression basis: {info.get('error')}")
    model, _ = build_model(mesh, data, cfg, expression_basis=shapes)
    target = torch.as_tensor(truth, dtype=torch.float32)
    visible = rest_visibility(mesh, data.cameras, data.train_views)  # [V, N] seen by view v at rest
    weight = torch.ones(target.shape[1])  # [N]: which vertices the loss sees
    if seen_only:
        weight = torch.as_tensor(visible.any(0), dtype=torch.float32)
    frames, cv, o = target.shape[0], data.canonical_view, cfg.optim
    groups = param_groups(model, o)  # the refine group gets no gradient here (refine=False): Adam skips it
    opts = {k: torch.optim.Adam(p, lr=lr) for k, (p, lr) in groups.items()}
    warm = warm_up_steps(model, o)
    clock = _Schedule(o.iterations, warm, None)
    gen = torch.Generator().manual_seed(cfg.runtime.seed)

    def loss_of(t: torch.Tensor) -> torch.Tensor:
        x = model(torch.full_like(t, cv), t, refine=False)["means"]
        return (((x - target[t]) ** 2).sum(-1) * weight).sum() / (weight.sum() * len(t)) / diag**2

    if projected:
        from t2bs.recon.gaussians import camera_tensors
        from t2bs.recon.tracks import project_points
        from t2bs.recon.vcdgs import _sample

        vm, ks = camera_tensors(data.cameras)
        seen = torch.as_tensor(visible, dtype=torch.float32)  # [V, N]
        # [V, T, N, 2] the truth's image motion from frame 0 in each view: the perfect tracks
        truth_px = torch.stack(
            [project_points(target, vm[v].expand(frames, 4, 4), ks[v].expand(frames, 3, 3)) for v in range(len(vm))]
        )
        truth_motion = truth_px - truth_px[:, :1]
        px = float(ks[cv, 0, 0])  # pixels per unit depth-normalised length, to keep the loss near the 3D one's scale

        def track_loss_of(v: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
            mv = torch.full_like(v, cv) if canonical_model else v
            x = model(mv, t, refine=False)["means"]
            if all_views:  # each sample's geometry seen by every training view: [B * V] items
                nviews = len(data.train_views)
                views = torch.tensor(data.train_views).repeat(len(v))
                x, t, v = x.repeat_interleave(nviews, 0), t.repeat_interleave(nviews), views
            if absolute:  # 2D positions: the motion and the rest pose both, as images pin the rest pose
                err = ((project_points(x, vm[v], ks[v]) - truth_px[v, t]) ** 2).sum(-1) / px**2
            else:
                with torch.no_grad():  # the start of the motion, a constant of the step (no graph to build)
                    x0 = model(mv, torch.zeros_like(t), refine=False)["means"]
                moved = project_points(x, vm[v], ks[v]) - project_points(x0, vm[v], ks[v])
                err = ((moved - truth_motion[v, t]) ** 2).sum(-1) / px**2
            w = seen[v]  # [B, N]
            return (err * w).sum() / w.sum().clamp_min(1.0) / diag**2

    warm_loss = None
    for step in range(o.iterations):
        p = clock.progress(step)
        joint = clock.joint(p)
        if joint and warm_loss is None:
            with torch.no_grad():
                warm_loss = float(loss_of(torch.arange(frames)))
        for k, opt in opts.items():
            for g in opt.param_groups:
                g["lr"] = groups[k][1] * _lr_factor(k, joint, clock.warm_fraction(p), clock.joint_fraction(p), o)
        if projected:
            v, t = _sample(gen, data, o.batch_size, o.canonical_fraction)
            loss = track_loss_of(v, t)
        else:
            t = torch.randint(0, frames, (o.batch_size,), generator=gen)
            loss = loss_of(t)
        for opt in opts.values():
            opt.zero_grad(set_to_none=True)
        loss.backward()
        for k, opt in opts.items():
            if joint or k in WARM_UP_GROUPS:
                opt.step()
    with torch.no_grad():
        final_loss = float(loss_of(torch.arange(frames)))
        pred = canonical_vertices(model)
    m = expression_metrics(pred, truth, rest)
    count = visible.sum(0)  # [N] how many training views see a vertex at rest (depth needs two)
    # the share of the expression error along the canonical camera's axis (depth), over the metric's mask
    e_fit, e_true = nonrigid_displacements(rest, pred)[0], expression
    mask = np.linalg.norm(e_true, axis=-1) > 0.005 * diag
    axis = data.cameras[cv].world_to_camera[2, :3]

    def depth_share(select: np.ndarray) -> float:
        err = (e_fit - e_true)[mask & select[None]]
        return round(float(((err @ axis) ** 2).sum() / max((err**2).sum(), 1e-30)), 3)

    by_views = {}
    for name, lo, hi in (("0", 0, 0), ("1", 1, 1), ("2-3", 2, 3), ("4+", 4, 10**6)):
        r = expression_metrics(pred, truth, rest, select=(count >= lo) & (count <= hi))
        if r["expr_fraction"] > 0:
            by_views[name] = {
                "share": round(r["expr_fraction"] / m["expr_fraction"], 3),
                "expr_ratio": round(float(r["expr_ratio"]), 3),
            }
    print(
        json.dumps(
            {
                "asset": asset,
                "prompt": prompt,
                "head_motion": head_motion,
                "seen_only": seen_only,
                "projected": projected,
                "canonical_model": canonical_model,
                "absolute": absolute,
                "all_views": all_views,
                "basis": info["shapes"],  # the shapes the auto rig made, not the ones asked for
                "options": set_options,
                "steps": o.iterations,
                "warm_up": warm,
                "loss_after_warm_up / rigid oracle": None if warm_loss is None else round(warm_loss / oracle, 2),
                "final_loss / rigid oracle": round(final_loss / oracle, 3),
                **{name: round(float(m[name]), 3) for name in ("expr_ratio", "recovered", "cosine")},
                "by_views_seeing": by_views,
                # the share of the squared expression error along the canonical camera's axis: all, 4+ views
                "depth_share": [depth_share(count >= 0), depth_share(count >= 4)],
            }
        )
    )


if __name__ == "__main__":
    run_command(main)
