"""The expression weights picked by render: a search over each frame's weights that gradient steps cannot make.

Why (docs/VCDGS_NOTES.md, "The blink stuck on a plateau"): the image loss as a function of a blink's weight is flat
once the lid covers the eye, and rippled at the pixel scale below that. Gradient steps that an early misfit pushes
onto the plateau (the head not yet aligned, the networks' first Adam steps) stay there: on the demo fox the learned
weights were ~0.9 in open-eyed frames and ~0.2 in closed ones, while the same model rendered with the true weights
had the lower loss in every frame. A few renders per weight find the better value directly.

``pick_expression_weights`` does coordinate descent, one sweep: for every frame after the first and every shape, the
frame's weights with that shape at each of ``values`` (and at its current weight) are rendered at a few views and
the one with the lowest image loss (the training loss's image terms) is kept. The current weight is a candidate, so
the pick never raises the loss at those views.

A candidate's vertices need no forward of its own: the basis adds to the rest pose, and the skinning and the global
motion are affine in the rest pose (x = M rest + b per vertex), so at one (view, time) the deformed vertices are affine
in the weights, x(w) = x(w0) + sum_j (w_j - w0_j) D_j. One forward per view at the frame's weights and at each shape
one unit further gives x(w0) and the D_j; the candidates only rebuild their splats (the splat shifts and the face
Gaussians, which are not affine) from x. Everything else a forward gives (rotations, scales, colours: the RefineMLP)
does not depend on the weights. On the demo fox this took the model's forward out of a pick (issue 36, session 50).
"""

from __future__ import annotations

import time

import torch

# The weights tried for each shape: an ARKit shape's range, 0 (rest) to 1 (the full expression), in quarters.
PICK_VALUES = (0.0, 0.25, 0.5, 0.75, 1.0)


@torch.no_grad()
def pick_expression_weights(
    model,
    data,
    cfg,
    views: list[int],
    refine: bool,
    perceptual,
    values: tuple[float, ...] = PICK_VALUES,
    chunk: int = 32,
) -> dict:
    """Set ``model``'s expression weights (a VCDGSModel with a basis) to the best of ``values`` per frame and shape.

    data: TrainData (images and masks of every (view, time)); cfg: VCDGSConfig (the image loss's settings); views:
    the views whose image losses are summed (the canonical one first); refine: whether the RefineMLP's offsets are
    applied (as in the training stage the pick belongs to); perceptual: the training's PerceptualLoss; chunk: most
    items rendered at once. Returns {"changed": weights moved, "frames": T, "shapes": J, "seconds": ...}."""
    from t2bs.recon.gaussians import camera_tensors
    from t2bs.recon.losses import image_loss_per_item
    from t2bs.recon.vcdgs import batch_targets, render_model

    t0 = time.time()
    dev = model.means.device
    vm, ks = camera_tensors(data.cameras, dev)
    w, h = data.size
    weights = model.expression_weights().detach().clone()  # [T, J]
    frames, shapes = weights.shape
    view_idx = torch.tensor(views, device=dev)
    changed = 0

    def frame_state(t: int) -> tuple:
        """Every view at frame t's weights and at each shape one unit further -> (x [V, N, 3] the vertices at the
        weights, D [V, J, N, 3] each shape's motion per unit of weight, [quats, scales, colours, face colours] of
        each view's splats, which no weight changes)."""
        at = model(view_idx, torch.full_like(view_idx, t), refine=refine, expression=weights[t].repeat(len(views), 1))
        v_idx = view_idx.repeat_interleave(shapes)  # view-major: item i = (view i // J, shape i % J)
        t_idx = torch.full_like(v_idx, t)
        expr = (weights[t] + torch.eye(shapes, device=dev)).repeat(len(views), 1)
        # The RefineMLP moves no vertex: the unit rows leave it out.
        moved = [
            model(v_idx[s : s + chunk], t_idx[s : s + chunk], refine=False, expression=expr[s : s + chunk])["means"]
            for s in range(0, len(v_idx), chunk)
        ]
        x = at["means"]
        directions = torch.cat(moved).view(len(views), shapes, *x.shape[1:]) - x[:, None]
        return x, directions, [at[k] for k in ("quats", "scales", "colors", "face_colors")]

    def losses(t: int, x: torch.Tensor, keep: list) -> torch.Tensor:
        """x [V, C, N, 3] candidates' vertices at frame t -> [C] image loss summed over the views."""
        c = x.shape[1]
        v_idx = view_idx.repeat_interleave(c)  # view-major: item i = (view i // C, candidate i % C)
        t_idx = torch.full_like(v_idx, t)
        flat = x.reshape(-1, *x.shape[2:])
        rep = [None if k is None else k.repeat_interleave(c, 0) for k in keep]
        out = []
        for s in range(0, len(v_idx), chunk):
            sl = slice(s, s + chunk)
            splats = model.splats_at(flat[sl], *(None if k is None else k[sl] for k in rep))
            r = render_model(model, splats, vm[v_idx[sl]], ks[v_idx[sl]], w, h)
            tgt, msk = batch_targets(data, v_idx[sl], t_idx[sl])
            out.append(image_loss_per_item(r, tgt, msk, perceptual, cfg))
        return torch.cat(out).view(len(views), c).sum(0)

    for t in range(1, frames):
        x, directions, keep = frame_state(t)
        known = None  # the loss of the frame's current weights, once measured: not rendered again for the next shape
        for j in range(shapes):
            current = float(weights[t, j])
            cands = [current] + [v for v in values if abs(v - current) > 1e-6]
            steps = torch.tensor(cands, device=dev) - current  # [C]; the current weight's step is exactly 0
            xs = x[:, None] + steps[None, :, None, None] * directions[:, j, None]  # [V, C, N, 3]
            if known is None:
                scores = losses(t, xs, keep)
            else:
                scores = torch.cat([known.view(1), losses(t, xs[:, 1:], keep)])
            best = int(torch.argmin(scores))  # ties keep the current weight (index 0)
            known = scores[best]
            if best:
                weights[t, j] = cands[best]
                x = xs[:, best]  # the vertices just scored, so ``known`` stays their loss
                changed += 1
    # The weights are DCT coefficients (deform.frames_from_dct: W = B c - (B c)[0], B orthonormal); with W[0] = 0
    # the coefficients c = B^T W give back exactly W.
    model.expression_coef.copy_(model.expression_dct.T @ weights)
    return {"changed": changed, "frames": frames, "shapes": shapes, "seconds": round(time.time() - t0, 2)}
