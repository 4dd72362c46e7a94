"""The T2Bs blendshape model (paper §3.3): PCA of per-frame meshes as offsets from the neutral mesh.

Why an *uncentred* PCA (SVD of the offsets ``x_t - neutral``, no mean subtracted): a glTF morph
target rig evaluates ``position = base + sum_i w_i * target_i`` and every tool (Blender, three.js,
Unity) opens a file at its default weights, which we write as 0. With the neutral mesh as the
base and an uncentred basis, weights 0 are exactly the neutral character and every captured
frame is ``neutral + basis^T w``. A centred PCA would put the *mean expression* at weights 0 (or
need non-zero default weights that many importers ignore), so the exported rig would open
half-smiling. The price is small: the first component absorbs the mean offset, and the remaining
ones are orthogonal to it, so the span (what the model can express) is the same as a centred PCA
with one more component.

The basis is orthonormal over flattened vertices (``basis.reshape(K, -1)`` has orthonormal
rows), so the geometric fit of a target is a projection (closed form, see ``fit.py``).

Expressions, not head motion: a capture moves the whole head and deforms the face. Before the PCA each frame's
dominant rigid motion (geometry.rigid.robust_rigid_motion from the neutral) is taken out and kept as the capture's
head track (``head_tracks``), so no component is a head turn. Each component is oriented so that its observed
extreme is positive (exported at weight 1, see export.py), and flagged ``visible`` when it moves some vertex by at
least ``VISIBLE_FRACTION`` of the bounding-box diagonal there; the glTF and the viewer list only those.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from t2bs.errors import UserError
from t2bs.geometry.mesh import bbox_diagonal

MODEL_VERSION = 2
# A component is visible when, at its observed extreme, some vertex moves by this fraction of the bounding-box
# diagonal: 0.2 % is about one pixel of the 512 px frontal render (the paper's renders). Chosen from that pixel
# size, not from any asset.
VISIBLE_FRACTION = 0.002


@dataclass
class BlendshapeModel:
    neutral: np.ndarray  # [N, 3] float32, the rest mesh (weights 0)
    basis: np.ndarray  # [K, N, 3] float32, orthonormal rows once flattened to [K, 3N]
    singular_values: np.ndarray  # [K] float64, of the offset matrix [frames, 3N], descending
    names: list[str]  # [K] morph target name of each component ("pc000", ...)
    explained_variance: np.ndarray | None = None  # [K] fraction of the total offset energy per component
    capture_weights: dict[str, np.ndarray] = field(default_factory=dict)  # video_id -> [T, K] weights of each frame
    semantic_names: list[str] = field(default_factory=list)  # [S] named shapes (jaw_open, smile, ...)
    semantic_weights: np.ndarray | None = None  # [S, K] each named shape expressed in the basis
    semantic_sources: list[str] = field(default_factory=list)  # [S] "video_id:frame" each named shape came from
    meta: dict = field(default_factory=dict)  # source, components asked, rank, frames, tolerance
    visible: np.ndarray | None = None  # [K] bool: the component moves some vertex by >= VISIBLE_FRACTION x diagonal
    head_tracks: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # video_id -> (rotations
    #   [T, 3, 3], translations [T, 3]): the head motion taken out of each capture (frame = R (neutral + offsets) + t)

    @property
    def num_components(self) -> int:
        return int(self.basis.shape[0])

    @property
    def num_vertices(self) -> int:
        return int(self.neutral.shape[0])

    def flat_basis(self) -> np.ndarray:
        """[K, 3N] float64 view used for projections."""
        return self.basis.reshape(self.num_components, -1).astype(np.float64)

    def offsets(self, weights: np.ndarray) -> np.ndarray:
        """Offsets from the neutral mesh for weights [..., K] -> [..., N, 3]."""
        w = np.asarray(weights, dtype=np.float64)
        if w.shape[-1] != self.num_components:
            raise ValueError(f"expected weights [..., {self.num_components}], got {w.shape}")
        return (w @ self.flat_basis()).reshape(*w.shape[:-1], self.num_vertices, 3)

    def vertices(self, weights: np.ndarray) -> np.ndarray:
        """Vertex positions [..., N, 3] (float32) for weights [..., K]; weights 0 = neutral."""
        return (self.neutral.astype(np.float64) + self.offsets(weights)).astype(np.float32)

    def project(self, vertices: np.ndarray) -> np.ndarray:
        """Least-squares weights [..., K] of vertex positions [..., N, 3] (orthonormal basis: B d)."""
        v = np.asarray(vertices, dtype=np.float64)
        d = (v - self.neutral.astype(np.float64)).reshape(*v.shape[:-2], -1)
        return d @ self.flat_basis().T

    def capture_frames(self, video_id: str) -> np.ndarray:
        """[T, N, 3] a capture's frames as the model holds them: its weights posed, then its head track applied."""
        verts = self.vertices(self.capture_weights[video_id])
        if video_id not in self.head_tracks:
            return verts
        from t2bs.geometry.rigid import apply_rigid_frames

        return apply_rigid_frames(*self.head_tracks[video_id], verts).astype(np.float32)

    def visible_components(self) -> np.ndarray:
        """[K'] indices of the components that move something visible: at the largest weight the captures gave it,
        some vertex moves by >= VISIBLE_FRACTION of the diagonal (``visible``, set by build_model). A model made
        without the flags (a file older than them, one assembled by hand) shows every component."""
        if self.visible is None:
            return np.arange(self.num_components)
        return np.flatnonzero(self.visible)

    def semantic_offsets(self) -> np.ndarray:
        """[S, N, 3] offsets of the named shapes (their projection onto the basis)."""
        if self.semantic_weights is None or not self.semantic_names:
            return np.zeros((0, self.num_vertices, 3), np.float32)
        return self.offsets(self.semantic_weights).astype(np.float32)


def build_model(
    neutral: np.ndarray,
    captures: dict[str, np.ndarray],
    components: int = 100,
    rank_tol: float | None = None,
    source: str = "",
    remove_head_motion: bool = True,
) -> BlendshapeModel:
    """PCA over every frame of every capture (``video_id -> [T, N, 3]``) as offsets from ``neutral``.

    ``remove_head_motion``: each frame's dominant rigid motion is taken out first (kept in ``head_tracks``), so the
    components are expressions; False keeps the frames as they are (head motion becomes components).

    The number of components is min(components, numerical rank of the offsets). The rank counts
    singular values above the rounding noise of float32 vertex positions: noise of size
    ``eps_float32 * max|x|`` per coordinate has a largest singular value of about that times
    ``sqrt(frames) + sqrt(3N)`` (random-matrix bound). numpy's ``matrix_rank`` rule
    (``s_max * max(frames, 3N) * eps``) would be ~1000x stricter here and drop real, small
    motions (e.g. the non-linear residue of a head turn) on large meshes. ``rank_tol`` (relative
    to ``s_max``) overrides it.
    """
    neutral = np.asarray(neutral, dtype=np.float32)
    if neutral.ndim != 2 or neutral.shape[1] != 3:
        raise UserError(f"neutral mesh must be [N, 3], got {neutral.shape}")
    if components < 1:
        raise UserError(f"--components must be at least 1, got {components}")
    if not captures:
        raise UserError("no captures to build a blendshape model from")
    n = neutral.shape[0]
    ids = sorted(captures)
    for vid in ids:
        c = np.asarray(captures[vid])
        if c.ndim != 3 or c.shape[1:] != (n, 3):
            raise UserError(f"capture {vid}: vertices {c.shape} do not match the neutral mesh [T, {n}, 3]")
        if c.shape[0] == 0:
            raise UserError(f"capture {vid}: has no frames")
        if not np.isfinite(c).all():
            raise UserError(f"capture {vid}: vertices contain NaN or infinite values")
    head_tracks = {}
    if remove_head_motion:
        from t2bs.geometry.rigid import nonrigid_displacements

        base = neutral.astype(np.float64)
        moved = {}
        for v in ids:
            disp, rot, trans = nonrigid_displacements(base, captures[v])
            moved[v], head_tracks[v] = (base + disp).astype(np.float32), (rot, trans)
        captures = moved
    lengths = [int(np.asarray(captures[v]).shape[0]) for v in ids]
    # [M, 3N] float32 storage (a character x 60 videos x 49 frames fits); products in float64.
    data = np.concatenate(
        [
            (np.asarray(captures[v], np.float64) - neutral.astype(np.float64)).reshape(length, -1)
            for v, length in zip(ids, lengths)
        ]
    ).astype(np.float32)
    s, vt = _svd_rows(data)  # [R], [R, 3N]
    total = float(np.einsum("ij,ij->", data, data, dtype=np.float64))
    if total <= 0 or s.size == 0 or s[0] <= 0:
        raise UserError(
            "captures do not move: every frame equals the neutral mesh, nothing to model"
            + (" (after taking each frame's head motion out)" if remove_head_motion else "")
        )
    if rank_tol is None:
        scale = max(float(np.abs(neutral).max()), max(float(np.abs(np.asarray(captures[v])).max()) for v in ids))
        noise = np.finfo(np.float32).eps * scale * (np.sqrt(data.shape[0]) + np.sqrt(data.shape[1]))
        tol = max(noise / s[0], 1e-6)  # 1e-6: below it the Gram-matrix SVD itself is not accurate
    else:
        tol = rank_tol
    rank = int((s > s[0] * tol).sum())
    k = min(components, rank)
    s, vt = s[:k], vt[:k]
    # Orientation (SVD signs are arbitrary): the observed weight of largest magnitude is positive, so that
    # 0 -> 1 on an exported slider moves into the range the captures saw (not away from it).
    weights = data.astype(np.float64) @ vt.T  # [M, K]
    extreme = weights[np.abs(weights).argmax(0), np.arange(k)]  # [K]
    flip = np.where(extreme < 0, -1.0, 1.0)
    vt, weights = vt * flip[:, None], weights * flip[None]
    # Visible: at its observed extreme, the component's largest vertex offset.
    peak = np.linalg.norm(vt.reshape(k, n, 3), axis=-1).max(1) * np.abs(weights).max(0)  # [K]
    visible = peak >= VISIBLE_FRACTION * bbox_diagonal(neutral)
    split = np.split(weights, np.cumsum(lengths)[:-1])
    return BlendshapeModel(
        neutral=neutral,
        basis=vt.reshape(k, n, 3).astype(np.float32),
        singular_values=s.astype(np.float64),
        names=[f"pc{i:03d}" for i in range(k)],
        explained_variance=(s**2 / total).astype(np.float64),
        capture_weights={v: w.astype(np.float32) for v, w in zip(ids, split)},
        meta={
            "source": source,
            "components_requested": int(components),
            "rank": rank,
            "frames": int(sum(lengths)),
            "captures": len(ids),
            "rank_tol": float(tol),
            "centred": False,
            "head_motion_removed": remove_head_motion,
            "visible_fraction": VISIBLE_FRACTION,
            "visible": int(visible.sum()),
        },
        visible=visible,
        head_tracks=head_tracks,
    )


def _svd_rows(data: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Singular values [R] (descending) and right singular vectors [R, D] of ``data`` [M, D].

    Through the eigendecomposition of the smaller Gram matrix (M x M or D x D) in float64: one
    pass over the data, memory O(min(M, D)^2), a few seconds for thousands of frames. The Gram
    matrix squares the condition number, which is harmless because components below the
    float32 rank tolerance (~1e-3 of s_max) are dropped anyway; rows are re-orthonormalised.
    """
    m, d = data.shape
    chunk = 4096
    if m <= d:
        d64 = data.astype(np.float64)
        gram = d64 @ d64.T
        del d64
        evals, u = np.linalg.eigh(gram)
        order = np.argsort(evals)[::-1]
        evals, u = np.clip(evals[order], 0, None), u[:, order]
        s = np.sqrt(evals)
        keep = s > s[0] * 1e-7 if s.size and s[0] > 0 else np.zeros(0, bool)
        s, u = s[keep], u[:, keep]
        vt = np.zeros((s.size, d))
        for j in range(0, d, chunk):
            vt[:, j : j + chunk] = (u.T @ data[:, j : j + chunk].astype(np.float64)) / s[:, None]
    else:
        cov = np.zeros((d, d))
        for i in range(0, m, chunk):
            block = data[i : i + chunk].astype(np.float64)
            cov += block.T @ block
        evals, v = np.linalg.eigh(cov)
        order = np.argsort(evals)[::-1]
        evals, v = np.clip(evals[order], 0, None), v[:, order]
        s = np.sqrt(evals)
        keep = s > s[0] * 1e-7 if s.size and s[0] > 0 else np.zeros(0, bool)
        s, vt = s[keep], v[:, keep].T
    # One QR pass removes the small loss of orthogonality from the squared condition number.
    q, r = np.linalg.qr(vt.T)
    vt = (q * np.sign(np.diag(r))[None, :]).T
    return s, vt


# --------------------------------------------------------------------------------- npz I/O


def save_model(model: BlendshapeModel, path: str | os.PathLike) -> Path:
    """Write ``model`` to an .npz (atomic). Capture weights are stored per capture."""
    from t2bs.project import to_jsonable, write_npz
    import json

    ids = sorted(model.capture_weights)
    arrays = {
        "version": np.array(MODEL_VERSION),
        "neutral": model.neutral.astype(np.float32),
        "basis": model.basis.astype(np.float32),
        "singular_values": np.asarray(model.singular_values, np.float64),
        "names": np.array(model.names, dtype=str),
        "explained_variance": np.asarray(
            model.explained_variance if model.explained_variance is not None else np.full(model.num_components, np.nan)
        ),
        "capture_ids": np.array(ids, dtype=str),
        "semantic_names": np.array(model.semantic_names, dtype=str),
        "semantic_weights": (
            np.asarray(model.semantic_weights, np.float32)
            if model.semantic_weights is not None
            else np.zeros((0, model.num_components), np.float32)
        ),
        "semantic_offsets": model.semantic_offsets(),
        "semantic_sources": np.array(model.semantic_sources, dtype=str),
        "meta": np.array(json.dumps(to_jsonable(model.meta))),
    }
    if model.visible is not None:
        arrays["visible"] = np.asarray(model.visible, bool)
    for i, vid in enumerate(ids):
        arrays[f"capture_weights_{i:04d}"] = np.asarray(model.capture_weights[vid], np.float32)
        if vid in model.head_tracks:
            rot, trans = model.head_tracks[vid]
            arrays[f"head_rotations_{i:04d}"] = np.asarray(rot, np.float32)
            arrays[f"head_translations_{i:04d}"] = np.asarray(trans, np.float32)
    return write_npz(path, **arrays)


def load_model(path: str | os.PathLike) -> BlendshapeModel:
    """Read a model written by ``save_model`` (UserError on a missing or malformed file)."""
    import json

    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no blendshape model (run `t2bs blendshapes DIR` first)")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:
        raise UserError(f"{path}: not a readable blendshape model ({type(exc).__name__})") from None
    for key in ("neutral", "basis", "singular_values", "names"):
        if key not in data:
            raise UserError(f"{path}: blendshape model lacks {key!r}")
    basis, neutral = data["basis"], data["neutral"]
    if basis.ndim != 3 or basis.shape[1:] != neutral.shape:
        raise UserError(f"{path}: basis {basis.shape} does not match neutral {neutral.shape}")
    # Read back from a project folder: refuse what would poison every output made from it.
    if (
        neutral.ndim != 2
        or neutral.shape[1] != 3
        or len(data["names"]) != len(basis)
        or len(data["singular_values"]) != len(basis)
    ):
        raise UserError(
            f"{path}: blendshape model arrays disagree (neutral {neutral.shape}, basis {basis.shape}, "
            f"{len(data['names'])} names, {len(data['singular_values'])} singular values)"
        )
    for key in ("neutral", "basis", "singular_values"):
        if data[key].dtype.kind not in "fiu" or not np.isfinite(data[key]).all():
            raise UserError(
                f"{path}: blendshape model {key!r} holds NaN, infinite or non-numeric values; "
                f"rebuild it with `t2bs blendshapes DIR`"
            )
    ids = [str(s) for s in data.get("capture_ids", np.array([], dtype=str))]
    ev = data.get("explained_variance")
    sem_w = data.get("semantic_weights")
    return BlendshapeModel(
        neutral=neutral.astype(np.float32),
        basis=basis.astype(np.float32),
        singular_values=data["singular_values"].astype(np.float64),
        names=[str(s) for s in data["names"]],
        explained_variance=None if ev is None or np.isnan(ev).all() else ev.astype(np.float64),
        capture_weights={vid: data[f"capture_weights_{i:04d}"] for i, vid in enumerate(ids)},
        semantic_names=[str(s) for s in data.get("semantic_names", np.array([], dtype=str))],
        semantic_weights=None if sem_w is None or sem_w.shape[0] == 0 else sem_w.astype(np.float32),
        semantic_sources=[str(s) for s in data.get("semantic_sources", np.array([], dtype=str))],
        meta=json.loads(str(data["meta"])) if "meta" in data else {},
        visible=data["visible"].astype(bool)
        if "visible" in data and data["visible"].shape == (basis.shape[0],)
        else None,
        head_tracks={
            vid: (data[f"head_rotations_{i:04d}"], data[f"head_translations_{i:04d}"])
            for i, vid in enumerate(ids)
            if f"head_rotations_{i:04d}" in data
        },
    )
