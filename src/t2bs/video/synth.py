"""Offline multi-view grid: animate the character, render I[v, t] from the orbit, add defects.

The canonical view (azimuth 0, the orbit's middle camera = ``frontal_camera``) is the fixed-view
video a video model would make from the frontal render; it is rendered from the true animated
geometry without defects. Every other view is what a 4D video model would add: the same
animation seen from the orbit camera, with ``defects`` applied. The true vertices [T, N, 3] are
stored with the grid.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from t2bs.errors import UserError
from t2bs.geometry.camera import ORBIT_VIEWS, canonical_view_index, orbit_azimuths, orbit_cameras
from t2bs.geometry.mesh import Mesh
from t2bs.video.animator import Animation, AnimationConfig, animate, apply_head_motion
from t2bs.video.defects import DefectConfig, apply_appearance, noisy_colors, view_appearance, view_distortion
from t2bs.video.grid import VideoGrid


@dataclass
class GridConfig:
    frames: int = 16  # T (paper's video models: 16-49)
    size: int = 512  # square frame side, pixels (paper: 512; 128 for quick runs)
    views: int = ORBIT_VIEWS  # V orbit views over azimuth -60..60 (paper: 15); odd, so azimuth 0 is a view
    fps: float = 8.0  # time stamps (CogVideoX: 8 fps)
    shading: str = "unlit"  # "unlit" (ambient = 1, the appendix protocol) or "lambert"
    intensity: float = 1.0  # scale of expression weights
    head_motion: float = 1.0  # scale of the rigid head motion (0 = none)


def check_config(cfg: GridConfig) -> None:
    if not 2 <= cfg.frames <= 256:
        raise UserError(f"--frames must be between 2 and 256, got {cfg.frames}")
    if not 16 <= cfg.size <= 2048:
        raise UserError(f"--size must be between 16 and 2048 pixels, got {cfg.size}")
    if cfg.views < 1 or cfg.views % 2 == 0:
        raise UserError(f"--views must be odd (azimuth 0 must be one of the views), got {cfg.views}")
    if cfg.shading not in ("unlit", "lambert"):
        raise UserError(f"shading must be unlit or lambert, got {cfg.shading!r}")


def make_grid(
    mesh: Mesh,
    expression: str,
    sample: int = 0,
    seed: int = 0,
    config: GridConfig = GridConfig(),
    defects: DefectConfig = DefectConfig(),
    renderer=None,
    prompt: str | None = None,
    progress=None,
) -> VideoGrid:
    """Animate ``mesh`` (canonical frame) with ``expression`` and render the V x T grid."""
    check_config(config)
    anim = animate(
        mesh,
        expression,
        seed=seed,
        sample=sample,
        config=AnimationConfig(config.frames, config.fps, config.intensity, config.head_motion),
    )
    return render_grid(
        mesh,
        anim,
        config,
        defects,
        renderer,
        meta={"prompt": prompt or expression, "expression": expression, "sample": sample, "seed": seed},
        progress=progress,
    )


def render_grid(
    mesh: Mesh,
    anim: Animation,
    config: GridConfig = GridConfig(),
    defects: DefectConfig = DefectConfig(),
    renderer=None,
    meta: dict | None = None,
    progress=None,
) -> VideoGrid:
    """Render ``anim`` from the orbit cameras; defects on every view but the canonical one."""
    check_config(config)
    own = renderer is None
    if own:
        from t2bs.render.mesh_renderer import MeshRenderer

        renderer = MeshRenderer()
    try:
        return _render(mesh, anim, config, defects, renderer, meta or {}, progress)
    finally:
        if own:
            renderer.release()


def _render(mesh, anim, config, defects, renderer, meta, progress) -> VideoGrid:
    V, T, S = config.views, config.frames, config.size
    if anim.vertices.shape[0] != T:
        raise UserError(f"the animation has {anim.vertices.shape[0]} frames but the grid asks for {T}")
    cams = orbit_cameras(V, S)
    azimuths = orbit_azimuths(V)
    canon = canonical_view_index(V)
    frames = np.empty((V, T, S, S, 3), np.uint8)  # [V, T, H, W, 3]
    masks = np.empty((V, T, S, S), bool)  # [V, T, H, W]
    textured = mesh.texture is not None and mesh.uv is not None
    base_colors = mesh.texture if textured else mesh.vertex_rgb()
    view_stats = []

    def draw(v: int, t: int, verts: np.ndarray, colors, app=None) -> None:
        kw = {"texture": colors} if textured else {"vertex_colors": colors}
        res = renderer.render(mesh, cams[v], vertices=verts, shading=config.shading, **kw)
        rgb = res.rgb if app is None else apply_appearance(res.rgb, res.normal, res.mask, app, t)
        frames[v, t] = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
        masks[v, t] = res.mask
        if progress is not None:
            progress.update(1)

    # Canonical view first: clean colours, true geometry (the fixed-view video).
    for t in range(T):
        draw(canon, t, anim.vertices[t], base_colors)
    others = [v for v in range(V) if v != canon]
    # Per-view geometry: distort the morphed shape, then apply the same rigid head motion.
    view_verts, apps = {}, {}
    diag = mesh.bbox_diagonal()
    for v in others:
        off = view_distortion(mesh.vertices, v, float(azimuths[v]), defects)  # [N, 3]
        view_verts[v] = (
            anim.vertices
            if not off.any()
            else apply_head_motion(anim.morphed + off[None], anim.head_angles, anim.pivot)
        )
        apps[v] = None if defects.is_clean else view_appearance(v, float(azimuths[v]), T, S, cams[v].position, defects)
        view_stats.append(
            {
                "view": v,
                "azimuth": float(azimuths[v]),
                "geometry_offset_max": float(np.linalg.norm(off, axis=1).max() / diag),
                "blur_sigma_px": apps[v].blur_sigma if apps[v] is not None else 0.0,
            }
        )
    # Time outer, views inner: one noisy texture per frame, shared by the views (appendix).
    for t in range(T):
        colors = noisy_colors(base_colors, t, defects)
        for v in others:
            draw(v, t, view_verts[v][t], colors, apps[v])
    info = {
        **meta,
        "fps": config.fps,
        "grid_config": asdict(config),
        "defects": asdict(defects),
        "defect_views": view_stats,
        "animation": {
            "morph_names": anim.names,
            "morph_weights": np.round(anim.weights, 5).tolist(),  # [T, M]
            "head_angles_deg": np.round(anim.head_angles, 4).tolist(),  # [T, 3] yaw, pitch, roll
            "head_pivot": anim.pivot.tolist(),
            **anim.info,
        },
    }
    return VideoGrid(
        frames, cams, anim.times.astype(np.float32), canon, masks, anim.vertices.astype(np.float32), "procedural", info
    ).validate("procedural grid")
