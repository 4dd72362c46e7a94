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

    def losses(t: int, rows: torch.Tensor) -> torch.Tensor:
        """rows [C, J] candidate weights of frame t -> [C] image loss summed over the views."""
        c = len(rows)
        v_idx = view_idx.repeat_interleave(c)  # view-major: item i = (view i // C, candidate i % C)
        t_idx = torch.full_like(v_idx, t)
        expr = rows.repeat(len(views), 1)
        out = []
        for s in range(0, len(v_idx), chunk):
            sl = slice(s, s + chunk)
            deformed = model(v_idx[sl], t_idx[sl], refine=refine, expression=expr[sl])
            r = render_model(model, deformed["splats"], vm[v_idx[sl]], ks[v_idx[sl]], w, h)
            tgt, msk = batch_targets(data, v_idx[sl], t_idx[sl])
            out.append(image_loss_per_item(r, tgt, msk, perceptual, cfg))
        return torch.cat(out).view(len(views), c).sum(0)

    for t in range(1, frames):
        known = None  # the loss of the frame's current weights, once measured: not rendered again for the next shape
        for j in range(shapes):
            current = float(weights[t, j])
            cands = [current] + [v for v in values if abs(v - current) > 1e-6]
            rows = weights[t].repeat(len(cands), 1)
            rows[:, j] = torch.tensor(cands, device=dev)
            if known is None:
                scores = losses(t, rows)
            else:
                scores = torch.cat([known.view(1), losses(t, rows[1:])])
            best = int(torch.argmin(scores))  # ties keep the current weight (index 0)
            known = scores[best]
            if best:
                weights[t, j] = cands[best]
                changed += 1
    # The weights are DCT coefficients (deform.frames_from_dct: W = B c - (B c)[0], B orthonormal); with W[0] = 0
    # the coefficients c = B^T W give back exactly W.
    model.expression_coef.copy_(model.expression_dct.T @ weights)
    return {"changed": changed, "frames": frames, "shapes": shapes, "seconds": round(time.time() - t0, 2)}
