"""Vertex tracks from optical flow: a dense 2D correspondence term for VCDGS (our addition to
the paper's eq. 2; ``VCDGSConfig.track_weight = 0`` gives the paper's loss).

Why: the splat image loss moves a Gaussian only through the pixels its footprint covers, and a
Gaussian hidden behind another one gets no gradient at all (the depth order carries none). On
CPU budgets (hundreds of steps, not the paper's 60k) that leaves large motions under-fitted:
a wide-open mouth stays nearly closed while the chin stretches down. Optical flow from the
first frame (the rest pose: paper §3.1.2) to frame t of the same view gives, for every vertex
visible at rest, where its pixel went: a long-range signal that needs no appearance model.

Per view v and frame t, two estimates of where a vertex's rest pixel went, both from DIS optical
flow (OpenCV) run both ways on lightly blurred grey images (the blur damps per-texel noise of
generated side views), each valid only where the forward-backward round trip returns within
``fb_px`` pixels (occlusions, disocclusions and flow failures break it):
- direct: flow from frame 0 to frame t. Precise for small motion, but it fails on large motion
  of untextured skin: a wide-open jaw moves the lower lip ~10 px at 128 px, where the direct flow
  is valid for 5-30 % of those vertices and recovers 0.3 of their motion;
- chained: the vertex's pixel advanced frame by frame (t-1 -> t, ~1 px steps), dropped for good at
  the first failed round trip. Valid for 90-97 % of those vertices, recovering 0.7-0.9 of the
  motion, but each step adds ~0.1 px of drift.
With ``chain`` (the default), a track is the direct one where it is valid and the chained one is
lost, agrees within ``agree_px``, or lands on a pixel less like the rest pixel (absolute grey
difference, 3x3 box-filtered); else the chained one where it is valid. (Chained wherever the two
disagree made the turtle's blink 8 % worse: a chained track next to a closing eyelid can slide
along with the lid; direct wherever valid kept the wrong direct tracks of a few lower-lip vertices.)
Both flows may run on the images upsampled (``flow_size``; VCDGSConfig.track_flow_size = 256): DIS
matches 8 px patches, and at 128 px a patch on the lower lip also holds the upper lip, which stays,
so the flow under-reports a dropping jaw (facecap, true motion >= 6 px: gain 0.76 at 128 px, 0.90
at 256 px). Thresholds and the returned displacements stay in the given images' pixels.
A track counts only where the vertex is visible in the rest render of that view (depth test).
The loss (vcdgs.train) compares the model's projected displacement x(v, t) - x(v, 0) with the
tracked one, so a per-view shape disagreement at rest (a 4D generator's side view) is not
mistaken for motion; going further than a track along its expression motion is free up to a slack
(``track_loss``), because the flow falls short of small expressions. vcdgs.step_terms scales the term to pixels of
a 128 px image (``TRACK_UNIT_SIDE``), so that ``track_weight`` means the same at every training resolution.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from t2bs.geometry.camera import Camera
from t2bs.geometry.mesh import Mesh


@dataclass
class VertexTracks:
    displacement: torch.Tensor  # [V, T, N, 2] float32 pixel motion of each vertex's rest pixel, frame 0 -> t
    weights: torch.Tensor  # [V, T, N] float32 1 where the track is valid (visible at rest, round trip ok), else 0
    textured: torch.Tensor | None = None  # [V, N] bool: the track starts on a textured pixel (None = all do)

    def to(self, device) -> "VertexTracks":
        return VertexTracks(
            self.displacement.to(device),
            self.weights.to(device),
            None if self.textured is None else self.textured.to(device),
        )

    def coverage(self) -> float:
        """Share of (view, frame, vertex) entries with a valid track."""
        return float(self.weights.mean())


# The track term's errors count in pixels of an image of this longer side, at every training resolution: in the training
# images' own pixels the term grew with the resolution (twice the weight at 256 px, four times at the paper preset's 512,
# which cost facecap's wide mouth 0.253 -> 0.333 of the rigid oracle at 256 px; docs/VCDGS_NOTES.md)
TRACK_UNIT_SIDE = 128


def project_points(x: torch.Tensor, viewmats: torch.Tensor, ks: torch.Tensor) -> torch.Tensor:
    """x [B, N, 3] world points, viewmats [B, 4, 4] world->camera (OpenCV), ks [B, 3, 3] -> pixels [B, N, 2]."""
    xc = x @ viewmats[:, :3, :3].transpose(1, 2) + viewmats[:, None, :3, 3]
    xy = xc[..., :2] / xc[..., 2:3].clamp_min(1e-6)
    return xy @ ks[:, :2, :2].transpose(1, 2) + ks[:, None, :2, 2]


def _sample(field: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of ``field`` [H, W, C] at continuous pixel positions ``uv`` [N, 2] (pixel i
    covers [i, i + 1), so its centre is i + 0.5) -> [N, C]; positions outside are clamped to the border."""
    from scipy.ndimage import map_coordinates

    coords = [uv[:, 1] - 0.5, uv[:, 0] - 0.5]
    return np.stack(
        [map_coordinates(field[..., c], coords, order=1, mode="nearest") for c in range(field.shape[-1])], -1
    )


def _grey(img: np.ndarray, blur_px: float) -> np.ndarray:
    import cv2

    g = cv2.cvtColor(np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
    return cv2.GaussianBlur(g, (0, 0), blur_px) if blur_px > 0 else g


def _box3(grey: np.ndarray) -> np.ndarray:
    """[H, W, 1] float32 3x3 box filter of a grey image: the photometric check of a track's end pixel."""
    import cv2

    return cv2.blur(grey, (3, 3)).astype(np.float32)[..., None]


def _flow_engine():
    """DIS optical flow (Kroeger et al. 2016), medium preset refined down to the finest scale with
    small overlapping patches: ~0.6 px mean error on 128 px face renders (3 px mean motion)."""
    import cv2

    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    dis.setFinestScale(0)
    dis.setPatchSize(8)
    dis.setPatchStride(2)
    return dis


def _flow_frame(h: int, w: int, flow_size: int) -> tuple[float, tuple[int, int]]:
    """(scale, (width, height)) of the images the flow runs on: upsampled so that their longer side is at least
    ``flow_size`` (0 = as given)."""
    scale = max(1.0, flow_size / max(h, w)) if flow_size else 1.0
    return scale, (round(w * scale), round(h * scale))


def _flow_grey(img: np.ndarray, size: tuple[int, int], scale: float, blur_px: float) -> np.ndarray:
    """An RGB image 0..1 as the flow sees it: upsampled (bicubic) to ``size`` when ``scale`` > 1, grey, blurred by
    ``blur_px`` given pixels."""
    import cv2

    if scale > 1.0:
        img = cv2.resize(img, size, interpolation=cv2.INTER_CUBIC)
    return _grey(img, blur_px * scale)


def _round_trip(dis, a: np.ndarray, b: np.ndarray, uv: np.ndarray, tol_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Flow a -> b sampled at ``uv`` [N, 2], and whether the b -> a flow brings it back within ``tol_px`` (all in the
    flow's pixels)."""
    d = _sample(dis.calc(a, b, None), uv)
    back = _sample(dis.calc(b, a, None), uv + d)
    return d, np.linalg.norm(d + back, axis=-1) < tol_px


VISIBILITY_SIZE = 1024  # px (longer side) of the rest-pose depth test, whatever the training resolution


def rest_visibility(mesh: Mesh, cameras: list[Camera], views: list[int]) -> np.ndarray:
    """[V, N] bool: vertex visible at rest from camera v (False for views not listed)."""
    from t2bs.render.mesh_renderer import MeshRenderer

    out = np.zeros((len(cameras), mesh.num_vertices), bool)
    with MeshRenderer() as renderer:
        for v in views:
            out[v] = renderer.vertex_visibility(mesh, cameras[v], min_size=VISIBILITY_SIZE)
    return out


def texture_strength(grey: np.ndarray) -> np.ndarray:
    """[H, W] smaller eigenvalue of the 5x5 structure tensor of a grey image (uint8), in units of
    a 128 px image with intensities 0..1 (gradients per pixel shrink with resolution). Flow is only
    determined where it is large (Shi and Tomasi's "good features to track"): on flat skin and
    along straight edges the flow is filled in by its smoothness prior, which under-estimates
    motion (the aperture problem)."""
    import cv2

    lam = cv2.cornerMinEigenVal(grey.astype(np.float32) / 255.0, 5, 3)
    return lam * (max(grey.shape) / 128.0) ** 2


def compute_tracks(
    mesh: Mesh,
    images: torch.Tensor,
    cameras: list[Camera],
    views: list[int],
    fb_px: float = 1.0,
    blur_px: float = 0.7,
    progress: bool = False,
    min_texture: float = 0.0,
    workers: int = 0,
    chain: bool = True,
    agree_px: float = 1.5,
    flow_size: int = 0,
) -> VertexTracks:
    """Tracks of every vertex in ``views`` of ``images`` [V, T, H, W, 3] float 0..1 (rest pose at
    t = 0), seen by ``cameras`` [V] at the images' resolution. Views not listed get weight 0.
    ``min_texture``: ``textured`` marks the tracks starting where ``texture_strength`` of the rest
    image reaches it (the others start on flat skin or straight edges; track_loss weighs them).
    ``chain``: combine direct and frame-to-frame (chained) flow (module docstring); False = direct only.
    ``flow_size``: the flow runs on the images upsampled (bicubic) so that their longer side is at least
    this many px (0 = as given); ``fb_px``, ``blur_px``, ``agree_px`` and the returned displacements
    stay in the given images' pixels. Why: DIS matches 8 px patches, wider than a lip at 128 px, so a
    patch on the lower lip also holds the still upper lip and the flow under-estimates a dropping jaw.
    ``workers``: views computed at once in threads (OpenCV's flow releases the GIL; each view has
    its own flow engine, so the result does not depend on it); 0 = torch's thread count."""
    from concurrent.futures import ThreadPoolExecutor

    import cv2
    from tqdm import tqdm

    cv2.setNumThreads(1)  # parallel over views instead: one flow per thread, none fighting torch's
    nv, nt, h, w = images.shape[:4]
    scale, size = _flow_frame(h, w, flow_size)
    # per axis, as the resized camera scales them: rounding the size can make x and y differ slightly
    to_given_px = np.array([w / size[0], h / size[1]], np.float32)
    n = mesh.num_vertices
    disp = np.zeros((nv, nt, n, 2), np.float32)
    weights = np.zeros((nv, nt, n), np.float32)
    textured = np.zeros((nv, n), bool)
    verts = mesh.vertices.astype(np.float64)
    visible = rest_visibility(mesh, cameras, views)

    def view_tracks(v: int) -> None:
        dis = _flow_engine()
        cam = cameras[v].resized(*size) if scale > 1.0 else cameras[v]
        u0 = cam.project(verts)[0].astype(np.float32)  # [N, 2], in the flow's pixels
        grey = [_flow_grey(f, size, scale, blur_px) for f in images[v].numpy()]
        textured[v] = _sample(texture_strength(grey[0])[..., None], u0)[:, 0] >= min_texture
        start = visible[v]
        weights[v, 0] = start
        u, alive = u0.copy(), start.copy()  # the chained track: current pixel, not yet lost
        rest_grey = _sample(_box3(grey[0]), u0)[:, 0]
        for t in range(1, nt):
            d, ok = _round_trip(dis, grey[0], grey[t], u0, fb_px * scale)
            ok &= start
            if chain:
                # At t = 1 the chained step is the direct flow itself (same images, same pixels).
                step, step_ok = (d, ok) if t == 1 else _round_trip(dis, grey[t - 1], grey[t], u, fb_px * scale)
                alive &= step_ok
                u = u + step
                box = _box3(grey[t])
                closer = np.abs(_sample(box, u0 + d)[:, 0] - rest_grey) <= np.abs(_sample(box, u)[:, 0] - rest_grey)
                direct = ok & (~alive | (np.linalg.norm(d - (u - u0), axis=-1) < agree_px * scale) | closer)
                d = np.where(direct[:, None], d, u - u0)
                ok = direct | alive
            disp[v, t] = d * to_given_px
            weights[v, t] = ok

    with ThreadPoolExecutor(max(1, min(len(views), workers or torch.get_num_threads()))) as pool:
        for _ in tqdm(
            pool.map(view_tracks, views), total=len(views), desc="vertex tracks", leave=False, disable=not progress
        ):
            pass
    return VertexTracks(torch.from_numpy(disp), torch.from_numpy(weights), torch.from_numpy(textured))


def residual_tracks(
    tracks: VertexTracks,
    renders: np.ndarray,
    images: np.ndarray,
    projected: np.ndarray,
    views: list[int],
    fb_px: float = 1.0,
    blur_px: float = 0.7,
    flow_size: int = 0,
    workers: int = 0,
    head: np.ndarray | None = None,
    below_px: float = 0.0,
) -> VertexTracks:
    """``tracks`` measured again against a model: renders [V, T, H, W, 3] of the model and the input ``images`` (the
    same shape, 0..1), ``projected`` [V, T, N, 2] the model's vertices in each render's pixels. Per (view, time), the
    flow from the render to the input at a vertex's pixel is what the model still misses there; the new track is the
    model's own motion from frame 0 plus that residual, less the residual at frame 0 (where render and input differ in
    appearance, not motion). Why: DIS under-reports small motion (a lip corner's 1-2 px: a gain of 0.3-0.8,
    benchmarks/track_accuracy.py), and a short flow against a render that has already moved most of the way loses
    little. Only tracks the first flow found are measured again (a vertex occluded at frame t would take its
    occluder's residual); a track keeps its old value where either new round trip fails. Weights do not change.
    ``head`` [V, T, N, 2] (optional): the image motion the model's head motion alone gives; with ``below_px`` > 0 only
    tracks whose motion beyond it is shorter than ``below_px`` are measured again (the first flow follows large motion
    well: a wide mouth's lower lip at a gain of ~0.9, where a smile's corners get 0.3-0.8)."""
    from concurrent.futures import ThreadPoolExecutor

    import cv2

    cv2.setNumThreads(1)
    nv, nt, h, w = images.shape[:4]
    scale, size = _flow_frame(h, w, flow_size)
    to_flow = np.array([size[0] / w, size[1] / h], np.float32)
    disp = tracks.displacement.cpu().numpy().copy()
    weights = tracks.weights.cpu().numpy().copy()

    def view_residuals(v: int) -> None:
        dis = _flow_engine()
        res, ok = [], []
        for t in range(nt):
            a, b = _flow_grey(renders[v, t], size, scale, blur_px), _flow_grey(images[v, t], size, scale, blur_px)
            d, passed = _round_trip(dis, a, b, projected[v, t] * to_flow, fb_px * scale)
            res.append(d / to_flow)
            ok.append(passed)
        for t in range(1, nt):
            # only where the first flow found the vertex (an occluded one would take its occluder's residual)
            valid = ok[t] & ok[0] & (weights[v, t] > 0)
            if head is not None and below_px > 0:  # only small non-rigid motion: the flow tracks large motion
                valid &= np.linalg.norm(disp[v, t] - head[v, t], axis=-1) < below_px
            new = projected[v, t] - projected[v, 0] + res[t] - res[0]
            disp[v, t] = np.where(valid[:, None], new, disp[v, t])

    with ThreadPoolExecutor(max(1, min(len(views), workers or torch.get_num_threads()))) as pool:
        list(pool.map(view_residuals, views))
    dev = tracks.displacement.device
    return VertexTracks(torch.from_numpy(disp).to(dev), torch.from_numpy(weights).to(dev), tracks.textured)


def track_loss(
    x_t: torch.Tensor,
    x_0: torch.Tensor,
    viewmats: torch.Tensor,
    ks: torch.Tensor,
    tracks: VertexTracks,
    v_idx: torch.Tensor,
    t_idx: torch.Tensor,
    delta_px: float = 1.0,
    flat_weight: float = 1.0,
    slack: float = 0.0,
    head: torch.Tensor | None = None,
) -> torch.Tensor:
    """Huber (in pixels, / delta so that large errors count as L1) between the projected model
    motion x_t - x_0 ([B, N, 3] each, at (v, t) and (v, 0)) and the tracked motion, averaged over
    valid tracks. viewmats/ks [B, ...] are the batch's cameras. Tracks that start on untextured
    pixels count ``flat_weight`` times as much as textured ones. ``slack``: going further along a track,
    up to ``slack`` times its length, costs nothing (falling short, overshooting beyond that and moving
    across it cost as without): the flow under-reports a small expression (benchmarks/track_accuracy.py).
    ``head`` [B, N, 2]: the projected motion the model's head motion alone gives; the slack then counts along
    the track's motion beyond it (the expression's), so that the head cannot overshoot its tracks."""
    vi, ti = v_idx.to(tracks.weights.device), t_idx.to(tracks.weights.device)
    w = tracks.weights[vi, ti]  # [B, N]
    if tracks.textured is not None and flat_weight != 1.0:
        w = w * torch.where(tracks.textured[vi], 1.0, flat_weight)
    w = w.to(x_t.device)
    target = tracks.displacement[vi, ti].to(x_t.device)  # [B, N, 2]
    moved = project_points(x_t, viewmats, ks) - project_points(x_0, viewmats, ks)
    diff = moved - target
    if slack > 0:
        own = target if head is None else target - head.detach()
        n = own.norm(dim=-1, keepdim=True)
        u = own / n.clamp_min(1e-6)
        over = (diff * u).sum(-1, keepdim=True)  # how far the model goes beyond the track along it
        diff = diff - u * (over.clamp(0.0, None) - (over - slack * n).clamp(0.0, None))
    err = (
        torch.nn.functional.huber_loss(diff, torch.zeros_like(diff), delta=delta_px, reduction="none").sum(-1)
        / delta_px
    )
    return (w * err).sum() / w.sum().clamp_min(1.0)
