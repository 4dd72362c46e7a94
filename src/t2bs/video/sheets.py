"""Contact sheets: one PNG per grid, rows = views, columns = times, to look at a grid at a glance."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from t2bs.project import write_image
from t2bs.video.grid import VideoGrid


def contact_sheet(grid: VideoGrid, max_columns: int = 16, tile: int = 128, gap: int = 2) -> np.ndarray:
    """[H, W, 3] uint8 sheet: view v in row v, frame t in a column (at most ``max_columns``,
    evenly spaced, always including the first and last frame); the canonical row is framed red."""
    from PIL import Image

    V, T = grid.num_views, grid.num_frames
    cols = np.unique(np.round(np.linspace(0, T - 1, min(T, max_columns))).astype(int))
    th = tile
    tw = max(1, round(tile * grid.width / grid.height))
    sheet = np.full((V * (th + gap) + gap, len(cols) * (tw + gap) + gap, 3), 40, np.uint8)
    for v in range(V):
        for j, t in enumerate(cols):
            img = grid.frames[v, t]
            if img.shape[:2] != (th, tw):
                img = np.asarray(Image.fromarray(img).resize((tw, th), Image.BILINEAR))
            y, x = gap + v * (th + gap), gap + j * (tw + gap)
            sheet[y : y + th, x : x + tw] = img
    # Red frame around the canonical row (the fixed-view video, never defective).
    c = grid.canonical_view
    y0, y1 = c * (th + gap), (c + 1) * (th + gap) + gap
    sheet[y0 : y0 + gap, :] = sheet[y1 - gap : y1, :] = (220, 30, 30)
    sheet[y0:y1, :gap] = sheet[y0:y1, -gap:] = (220, 30, 30)
    return sheet


def save_contact_sheet(grid: VideoGrid, path: str | os.PathLike, **kw) -> Path:
    return write_image(path, contact_sheet(grid, **kw))
