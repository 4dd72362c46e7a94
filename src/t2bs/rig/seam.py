"""The lip seam seen from the front: where two surface points that touch in space are far apart on the mesh.

A face detector trained on human photos places a cartoon's mouth where a human's would be (on the
turtle: between the nostrils and its real mouth line). The mesh itself knows better where it can
open: across a lip seam, two pixels one row apart show points a hair apart in space whose geodesic
distances to a point above the mouth (and to one below it) differ by the way around the mouth
corner or through the mouth bag. An occlusion edge (the nose tip over the lip) is not mistaken for
it, because there the two points are far apart in space too; a dimple or a nostril is not, because
the detour is no longer than the gap.

``find_lip_seam`` scans the pixel columns of the frontal render around the detected mouth for that
jump, keeps the widest run of columns where it is found, and returns the 8 inner-lip landmark
vertices (68-point order 60-67) on its rim. A sealed mouth (no seam) returns None: then the
detector's points stay.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from t2bs.rig.surface import Surface

# A jump counts when the surface distance between the two points (bounded from below by the jump)
# exceeds RATIO x their straight gap plus MIN_DETOUR x the eye distance. On a smooth surface the jump
# stays under the gap (times ~1.4 for shortest paths along a mesh's edges); a dimple or a crease
# detours by about its gap, a lip by the way round its corner.
RATIO = 2.0
MIN_DETOUR = 0.06
# A groove goes on while its row lies this fraction of the eye distance deeper than the mean of the
# rows 2 % of the eye distance above and below it.
CREASE_DEPTH = 0.004
# A mouth is at least this fraction of the eye distance wide (cartoon mouths run past the eyes).
MIN_WIDTH = 0.25


@dataclass
class LipSeam:
    ids: np.ndarray  # [8] vertex ids of the inner lip, 68-point order 60-67
    line: np.ndarray  # [K, 2] pixel (x, y) of the mouth line, one per column from corner to corner
    seam_columns: int  # how many of those columns the mesh is open at (the rest: a groove)


def _pixel_samples(render, mesh_faces: np.ndarray, uv: np.ndarray, rows: np.ndarray, cols: np.ndarray):
    """Barycentric weights [R, C, 3] of each pixel in its triangle (from the projected vertices) and
    the triangle's vertex ids [R, C, 3] (-1 on background)."""
    fid = render.face_id[np.ix_(rows, cols)]
    tri = np.where(fid[..., None] >= 0, mesh_faces[np.maximum(fid, 0)], -1)
    a, b, c = (uv[np.maximum(tri[..., k], 0)] for k in range(3))
    p = np.stack(np.meshgrid(cols + 0.5, rows + 0.5), -1)
    v0, v1, v2 = b - a, c - a, p - a
    den = v0[..., 0] * v1[..., 1] - v1[..., 0] * v0[..., 1]
    den = np.where(np.abs(den) < 1e-12, 1e-12, den)
    wb = (v2[..., 0] * v1[..., 1] - v1[..., 0] * v2[..., 1]) / den
    wc = (v0[..., 0] * v2[..., 1] - v2[..., 0] * v0[..., 1]) / den
    w = np.clip(np.stack([1 - wb - wc, wb, wc], -1), 0.0, 1.0)
    w /= np.maximum(w.sum(-1, keepdims=True), 1e-12)
    return w, tri


def find_lip_seam(
    vertices: np.ndarray,
    faces: np.ndarray,
    uv: np.ndarray,
    render,
    skin: np.ndarray,
    eyes_px: np.ndarray,
    mouth_px: np.ndarray,
) -> LipSeam | None:
    """The inner-lip landmarks on the mesh's lip seam near the detected mouth, or None (sealed mouth).

    vertices [N, 3], faces [F, 3]; uv [N, 2] the vertices projected into the frontal ``render`` (its
    ``face_id`` [H, W] is read); skin [N] bool: visible face-skin vertices (where landmarks may go);
    eyes_px [12, 2] the detected eye points (36-47), mouth_px [8, 2] the detected inner lip (60-67).
    """
    v = np.asarray(vertices, np.float64)
    eye_r, eye_l = eyes_px[:6].mean(0), eyes_px[6:].mean(0)
    m = mouth_px.mean(0)
    iod_px = float(np.linalg.norm(eye_l - eye_r))
    em_px = float(m[1] - 0.5 * (eye_r[1] + eye_l[1]))  # image y grows downwards
    if iod_px <= 0 or em_px <= 0:
        return None
    h, w = render.face_id.shape
    seen = np.nonzero(skin)[0]
    if len(seen) == 0:
        return None

    def nearest_skin(x: float, y: float) -> int:
        return int(seen[np.argmin(np.hypot(uv[seen, 0] - x, uv[seen, 1] - y))])

    surf = Surface(v, faces)
    d_top, _ = surf.distance([nearest_skin(m[0], m[1] - 0.45 * em_px)])
    d_bot, _ = surf.distance([nearest_skin(m[0], m[1] + 0.9 * em_px)])
    # The eye distance in world units (the thresholds below are fractions of it).
    er3, el3 = v[nearest_skin(*eye_r)], v[nearest_skin(*eye_l)]
    iod = float(np.linalg.norm(el3 - er3))
    rows = np.arange(max(int(m[1] - 0.35 * em_px), 0), min(int(m[1] + 0.85 * em_px) + 1, h))
    cols = np.arange(max(int(m[0] - 0.7 * iod_px), 0), min(int(m[0] + 0.7 * iod_px) + 1, w))
    if len(rows) < 3 or len(cols) < 3:
        return None
    wts, tri = _pixel_samples(render, np.asarray(faces), uv, rows, cols)
    valid = (tri >= 0).all(-1) & skin[np.maximum(tri, 0)].any(-1)
    safe = np.maximum(tri, 0)

    def interp(field: np.ndarray) -> np.ndarray:
        f = field[safe]
        with np.errstate(invalid="ignore"):  # unreached vertices (inf) give nan, never a seam
            return np.where(np.isfinite(f).all(-1), (f * wts).sum(-1), np.nan)

    dt, db = interp(d_top), interp(d_bot)
    p3 = (v[safe] * wts[..., None]).sum(-2)  # [R, C, 3]
    # Row pairs (r, r + g): neighbours, or the two lips across a visible gap (the mouth's inside,
    # teeth: no skin) up to a tenth of the eye distance tall.
    score = np.full(valid.shape, -np.inf)
    below = np.arange(len(rows))[:, None] + np.ones(len(cols), np.int64)[None]  # the lower lip's row
    n_valid = np.concatenate([np.zeros((1, len(cols)), np.int64), np.cumsum(valid, 0)])
    max_gap = max(1, round(0.1 * iod_px))
    for g in range(1, max_gap + 1):
        if g >= len(rows):
            break
        gap = np.linalg.norm(p3[g:] - p3[:-g], axis=-1)
        jump_t = dt[g:] - dt[:-g]  # going down, away from the seed above
        jump_b = db[:-g] - db[g:]  # going up, away from the seed below
        with np.errstate(invalid="ignore"):
            # |d(a) - d(b)| <= the surface distance from a to b (triangle inequality), so the larger
            # jump bounds the way around from below; both must grow away from their seed.
            detour = np.where(np.minimum(jump_t, jump_b) > 0, np.maximum(jump_t, jump_b), np.nan) - RATIO * gap
        between = n_valid[g:-1] - n_valid[1 : len(rows) - g + 1] if g > 1 else 0
        ok = valid[g:] & valid[:-g] & (between == 0) & np.isfinite(detour) & (detour > MIN_DETOUR * iod)
        better = ok & (detour > score[:-g])
        score[:-g] = np.where(better, detour, score[:-g])
        below[:-g] = np.where(better, np.arange(g, len(rows))[:, None], below[:-g])
    # Each column's seam: the row pair with the largest detour (the mouth, not a fold beside it).
    best = score.argmax(0)
    has = np.isfinite(score[best, np.arange(len(cols))])
    if not has.any():
        return None
    # Runs of neighbouring columns whose seam rows join up (the mouth line bends, it does not leap).
    step = max(2, int(0.03 * iod_px))
    hit = np.nonzero(has)[0]
    runs, cur = [], [hit[0]]
    for a, b in zip(hit[:-1], hit[1:]):
        if b - a <= step and abs(int(best[b]) - int(best[a])) <= max(2, 0.06 * em_px) * (b - a):
            cur.append(b)
        else:
            runs.append(cur)
            cur = [b]
    runs.append(cur)
    run = max(runs, key=lambda r: (cols[r[-1]] - cols[r[0]], -abs(0.5 * (cols[r[-1]] + cols[r[0]]) - m[0])))
    # Past the opening the mouth line often goes on as a sculpted groove to the corners: follow the
    # crease (a row deeper than the rows around it) outwards from both ends while it stays a crease.
    k = max(2, round(0.02 * iod_px))
    depth = np.asarray(render.depth, np.float64)[np.ix_(rows, cols)]
    crease = np.full(depth.shape, -np.inf)
    with np.errstate(invalid="ignore"):
        c = depth[k:-k] - 0.5 * (depth[: -2 * k] + depth[2 * k :])
    skin3 = valid[k:-k] & valid[: -2 * k] & valid[2 * k :]  # all three rows on the skin (no gap, no teeth)
    crease[k:-k] = np.where(np.isfinite(c) & skin3, c, -np.inf)
    line = {int(j): int(best[j]) for j in range(run[0], run[-1] + 1) if has[j]}
    lower_row = {j: int(below[r, j]) for j, r in line.items()}
    seam_cols = set(line)
    for j in range(run[0], run[-1] + 1):  # short gaps inside the run take the neighbours' row
        if j not in line:
            line[j] = line[max(i for i in line if i < j)]

    def opening(j: int, upper: int, lower: int) -> tuple[int, int] | None:
        """(upper row, lower row) of a visible gap between two skin rows in column j that overlaps
        the gap (upper, lower) of the column before (the lips still apart: an open slit)."""
        col = valid[:, j]
        rr = next((q for q in range(upper + 1, lower) if not col[q]), None)
        if rr is None:
            return None
        top = rr
        while top > 0 and not col[top - 1]:
            top -= 1
        bottom = rr
        while bottom + 1 < len(rows) and not col[bottom + 1]:
            bottom += 1
        if top == 0 or bottom + 1 >= len(rows) or bottom - top + 1 > max_gap:
            return None
        return top - 1, bottom + 1

    for end, direction in ((run[0], -1), (run[-1], 1)):
        r, j = line[end], end + direction
        while 0 <= j < len(cols):
            lo, hi = max(r - 2, 0), min(r + 3, len(rows))
            rr = lo + int(np.argmax(crease[lo:hi, j]))
            if crease[rr, j] >= CREASE_DEPTH * iod:
                line[j], lower_row[j] = rr, rr + 1
            elif (gap_rows := opening(j, r, lower_row[j - direction])) is not None:
                line[j], lower_row[j] = gap_rows
            else:
                break
            r, j = line[j], j + direction
    js = np.asarray(sorted(line))
    sx, sy = cols[js], rows[[line[j] for j in js]]
    if sx[-1] - sx[0] < MIN_WIDTH * iod_px:
        return None
    # Which lip a vertex belongs to: across the seam the surface distance to the seed above jumps
    # and the one to the seed below drops, so d_top - d_bot splits the lips even where the upper lip
    # hangs over the lower one (as seen from the front, its rim may lie below the lower rim).
    with np.errstate(invalid="ignore"):
        split = d_top - d_bot
    split_px = interp(split)

    def lip(frac: float, upper: bool) -> int:
        """The lip vertex nearest the mouth line at this fraction of it from the right corner, among
        the vertices of the triangles seen in the rows just above (below) the line there."""
        q = int(np.argmin(np.abs(sx - (sx[0] + frac * (sx[-1] - sx[0])))))
        j, y = int(js[q]), int(line[int(js[q])])
        y2 = lower_row.get(j, y + 1)
        band = slice(max(y - 3, 0), y + 1) if upper else slice(y2, min(y2 + 4, len(rows)))
        cols_near = slice(max(j - 2, 0), j + 3)
        cand = np.unique(tri[band, cols_near][valid[band, cols_near]].reshape(-1))
        if j in seam_cols and 0 <= y2 < len(rows):
            mid = 0.5 * (split_px[y, j] + split_px[y2, j])
            cand = cand[(split[cand] < mid) == upper]
        else:
            cand = cand[(uv[cand, 1] <= sy[q] + 1.0) if upper else (uv[cand, 1] > sy[q] + 1.0)]
        if len(cand) == 0:  # no triangle there: the nearest seen skin vertex on that side
            side = (uv[seen, 1] <= sy[q] + 1.0) if upper else (uv[seen, 1] > sy[q] + 1.0)
            cand = seen[side] if side.any() else seen
        ty = sy[q] + 1.0 if upper else float(rows[min(y2, len(rows) - 1)])  # the line's edge on that side
        return int(cand[np.argmin(np.hypot(uv[cand, 0] - sx[q] - 0.5, uv[cand, 1] - ty))])

    # 60 (the character's right corner: image left), 61-63 upper lip right -> left, 64, 65-67 lower left -> right.
    ids = [nearest_skin(sx[0], sy[0] + 0.5), lip(0.25, True), lip(0.5, True), lip(0.75, True)]
    ids += [nearest_skin(sx[-1], sy[-1] + 0.5)]
    ids += [lip(0.75, False), lip(0.5, False), lip(0.25, False)]
    return LipSeam(np.asarray(ids, np.int64), np.stack([sx, sy], 1).astype(np.float64), len(seam_cols))
