"""Per-frame blendshape weights (paper §4.3): landmark distance 1.0 + ARAP 0.1 + eye terms.

The model is linear, ``v(w) = neutral + sum_k w_k B_k``, so every term is solved in closed form:

- Landmarks (weight 1.0): mean over the 20 landmarks of the squared distance between their X, Y
  (frontal image plane) and the transferred targets; linear in w. Z is not constrained (a frontal
  video does not observe it; ARAP and the basis decide it).
- ARAP (weight 0.1): mean over mesh edges (welded across UV seams) of ``|(v_i - v_j) - R_ij (n_i - n_j)|^2`` with
  ``R_ij = (R_i + R_j) / 2`` the local rotations. Solved the standard local/global way: the local
  step fits each vertex's rotation to the current pose (batched 3x3 SVD), the global step is then a
  K x K linear system because v is linear in w. The quadratic part ``(DB)^T (DB)`` is precomputed once.
- Eye terms: (a) lid gap: per eye, the mean vertical gap between upper- and lower-lid landmarks
  equals the neutral gap times the transferred openness (0 when the human's eye is shut, so the
  lids close fully); (b) depth (the paper's L_Depth): eyeball vertices may not move towards the
  camera more than their lids do (hinge, handled as an active set: solve, add the violated
  vertices as quadratic penalties, solve again).
- The PCA's own Gaussian prior, ``ridge * sum_k (s_0 / s_k)^2 w_k^2`` (``pca_prior``; ``with_pca_prior``): 40
  landmark numbers cannot pin 50-100 components, and without it the solve drove components the captures barely used
  (captured weights within +-0.01) to +-1.6, moving the turtle a median 4.7 % of its diagonal beyond anything its
  captures did (session 43, `t2bs bench retarget`); among the weight vectors that move the landmarks alike it picks
  the one the captures make most often. Without it (``prior=None``) a tiny plain ridge keeps components that
  neither landmarks nor ARAP see at zero.
- Bounds (``with_pca_prior``): every weight within the range the captures saw, so that a target no capture made
  (lips pressed tighter than at rest) is not reached by running a component backwards.

Warm start: each frame starts its ARAP rotations and eye active set from the previous frame's
solution, so one or two local/global rounds suffice.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from t2bs.geometry.mesh import weld_index, welded_edges
from t2bs.face.face_tracking import EYE_LID_PAIRS, LEFT_EYE, RIGHT_EYE


# The PCA prior's weight, relative to the solve's largest diagonal entry (SolveConfig.ridge with ``pca_prior``): chosen
# on facecap's ARKit shapes (face/arkit.py: median cosine 0.56 -> 0.72); on `t2bs bench retarget` (session 43; Pearson
# jaw / left eye / right eye / smile) the turtle 0.929 / 0.870 / 0.922 / 0.851 -> 0.961 / 0.942 / 0.942 / 0.860, the
# procedural fox 0.944 / 0.952 / 0.961 / 0.923 -> 0.957 / 0.952 / 0.960 / 0.912 (1e-5: 0.960 / 0.868 / 0.856 / 0.858
# and 0.952 / 0.952 / 0.960 / 0.933).
PRIOR_RIDGE = 1e-4


def observed_range(capture_weights: dict) -> np.ndarray | None:
    """[2, K] each component's lowest and highest weight over every captured frame (``BlendshapeModel
    .capture_weights``: video -> [T, K]); None without captures."""
    if not capture_weights:
        return None
    allw = np.concatenate([np.asarray(w, np.float64) for w in capture_weights.values()])
    return np.stack([allw.min(0), allw.max(0)])


def pca_prior(singular_values: np.ndarray) -> np.ndarray:
    """[K] relative ridge per component, (s_0 / s_k)^2 for the captures' singular values [K]: a component the
    captures use 10x less than the first costs 100x as much."""
    sv = np.maximum(np.asarray(singular_values, np.float64), 1e-12)
    return (sv[0] / sv) ** 2


@dataclass
class SolveConfig:
    landmark_weight: float = 1.0  # paper: 1.0 (mean squared landmark distance, world units)
    arap_weight: float = 0.1  # paper: 0.1 (mean squared ARAP edge residual)
    eye_gap_weight: float = 1.0  # lid-gap term per eye (squared gap error)
    eye_depth_weight: float = 1.0  # eyeball-behind-lids hinge
    ridge: float = 1e-7  # Tikhonov on the weights, relative to the largest diagonal entry
    iterations: int = 2  # ARAP local/global rounds per frame (warm-started)


class RetargetSolver:
    """Precomputed linear pieces of the objective for one model + landmark set (state: caches)."""

    def __init__(
        self,
        neutral: np.ndarray,
        basis: np.ndarray,
        faces: np.ndarray,
        landmark_ids: np.ndarray,
        eyeballs: dict | None = None,
        config: SolveConfig = SolveConfig(),
        prior: np.ndarray | None = None,
        bounds: np.ndarray | None = None,
    ):
        self.config = config
        # [2, K] lowest and highest weight per component (None: unbounded); see ``with_pca_prior``
        self.bounds = None if bounds is None else np.asarray(bounds, np.float64)
        # [K] relative ridge per weight (default 1 = plain Tikhonov); e.g. (s_0 / s_k)^2 makes
        # components the captures rarely use expensive (a Gaussian prior from the PCA).
        self.prior = np.ones(np.asarray(basis).shape[0]) if prior is None else np.asarray(prior, np.float64)
        self.neutral = np.asarray(neutral, np.float64)  # [N, 3]
        self.basis = np.asarray(basis, np.float64)  # [K, N, 3]
        self.k = self.basis.shape[0]
        self.ids = np.asarray(landmark_ids, int)  # [20]
        # ARAP edges between welded vertices: an exporter splits a vertex at every UV seam, and
        # without welding each copy would fit its rotation to half of its neighbourhood. Each weld
        # node is represented by one of its vertices (the copies share the basis' motion).
        node, first = weld_index(self.neutral)
        self.edges = first[welded_edges(node, np.asarray(faces, int))]  # [E, 2] vertex ids
        i, j = self.edges[:, 0], self.edges[:, 1]
        self.e0 = self.neutral[i] - self.neutral[j]  # [E, 3] rest edges
        # [K, 3E] edge vectors of each basis shape; ARAP quadratic form (mean over edges).
        self.db = (self.basis[:, i] - self.basis[:, j]).reshape(self.k, -1)
        n_e = len(self.edges)
        self.h_arap = self.db @ self.db.T / n_e
        # Local step precomputation: the rotations only need solving at vertices touching an edge
        # some basis shape changes (elsewhere the pose equals the rest pose and R = I), and the
        # per-vertex covariance sums are a sparse incidence product (much faster than np.add.at).
        from scipy import sparse

        moving = np.abs(self.db.reshape(self.k, n_e, 3)).max(axis=(0, 2)) > 0  # [E]
        self._active_v = np.unique(self.edges[moving])  # [A] vertex ids
        self._moving_e = np.nonzero(moving)[0]  # [Em]
        ea = self.edges[self._moving_e]
        slot = np.full(len(self.neutral), -1)
        slot[self._active_v] = np.arange(len(self._active_v))
        rows = np.concatenate([slot[ea[:, 0]], slot[ea[:, 1]]])
        cols = np.concatenate([np.arange(len(ea))] * 2)
        self._inc = sparse.csr_matrix(
            (np.ones(len(rows)), (rows, cols)), shape=(len(self._active_v), len(ea))
        )  # [A, Em]
        # Static edges next to an active vertex still add their rest covariance to its sum.
        static = ~moving
        ei = self.edges[static]
        cov0 = np.einsum("ea,eb->eab", self.e0[static], self.e0[static]).reshape(-1, 9)
        s0 = np.zeros((len(self._active_v), 9))
        for col in (0, 1):
            sl = slot[ei[:, col]]
            ok = sl >= 0
            for c in range(9):
                s0[:, c] += np.bincount(sl[ok], weights=cov0[ok, c], minlength=len(self._active_v))
        self._s_static = s0  # [A, 9]
        # Landmark rows: X, Y of the 20 landmark vertices, [40, K].
        self.a_lm = self.basis[:, self.ids, :2].reshape(self.k, -1).T
        self.h_lm = self.a_lm.T @ self.a_lm / len(self.ids)
        # Lid gaps: per eye the mean (upper Y - lower Y) over its two lid pairs, [2, K] (right, left).
        self.a_gap = np.zeros((2, self.k))
        self.gap0 = np.zeros(2)
        for r, (eye, base) in enumerate((("right", RIGHT_EYE[0]), ("left", LEFT_EYE[0]))):
            for up, lo in EYE_LID_PAIRS[eye]:
                vu, vl = self.ids[up], self.ids[lo]
                self.a_gap[r] += (self.basis[:, vu, 1] - self.basis[:, vl, 1]) / 2
                self.gap0[r] += (self.neutral[vu, 1] - self.neutral[vl, 1]) / 2
        # Eyeball depth hinge rows: dz(eyeball vertex) - mean dz(lid landmarks of that eye), [M, K].
        rows = []
        for eye, idx in (("right", RIGHT_EYE), ("left", LEFT_EYE)):
            ball = np.asarray((eyeballs or {}).get(eye, []), int)
            ball = ball[~np.isin(ball, self.ids)]
            if len(ball):
                lid = self.basis[:, self.ids[idx], 2].mean(1)  # [K]
                rows.append(self.basis[:, ball, 2].T - lid[None, :])
        self.a_depth = np.concatenate(rows) if rows else np.zeros((0, self.k))
        self._active = np.zeros(len(self.a_depth), bool)
        self._w = np.zeros(self.k)

    @classmethod
    def with_pca_prior(
        cls,
        model,
        faces: np.ndarray,
        landmark_ids: np.ndarray,
        eyeballs: dict | None = None,
        ridge: float = PRIOR_RIDGE,
        bounded: bool = True,
    ) -> "RetargetSolver":
        """The solver retargeting uses for a blendshape model (``neutral``, ``basis``, ``singular_values``,
        ``capture_weights``): the PCA's prior at ``ridge`` (module docstring) and, with ``bounded``, every weight kept
        within the range the captures saw (``observed_range``, widened to hold 0, the neutral). Why the bounds: a
        landmark target the captures never made (lips pressed tighter than at rest) is otherwise reached by running
        a component backwards (the jaw up into the head); measured on `t2bs bench retarget` (session 43)."""
        observed = observed_range(model.capture_weights) if bounded else None
        if observed is not None:
            observed = np.stack([np.minimum(observed[0], 0.0), np.maximum(observed[1], 0.0)])
        return cls(
            model.neutral,
            model.basis,
            faces,
            landmark_ids,
            eyeballs,
            SolveConfig(ridge=ridge),
            pca_prior(model.singular_values),
            observed,
        )

    def _solve_linear(self, h: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """argmin_w 1/2 w^T h w - rhs^T w (h symmetric positive definite), within ``bounds`` when set: the
        unconstrained solution where it lies inside them, else bounded-variable least squares on h's Cholesky factor
        (1/2 |L^T w - L^-1 rhs|^2 is the same objective up to a constant)."""
        w = np.linalg.solve(h, rhs)
        if self.bounds is None or ((w >= self.bounds[0]) & (w <= self.bounds[1])).all():
            return w
        from scipy.linalg import solve_triangular
        from scipy.optimize import lsq_linear

        chol = np.linalg.cholesky(h)  # h = L L^T
        b = solve_triangular(chol, rhs, lower=True)
        return lsq_linear(chol.T, b, bounds=(self.bounds[0], self.bounds[1]), method="bvls").x

    def reset(self) -> None:
        self._active[:] = False
        self._w = np.zeros(self.k)

    def _rotations(self, w: np.ndarray) -> np.ndarray:
        """Local step: per-vertex best rotation [N, 3, 3] from rest edges to the edges of pose w."""
        rot = np.broadcast_to(np.eye(3), (len(self.neutral), 3, 3)).copy()
        if len(self._active_v) == 0:
            return rot
        ea = self.edges[self._moving_e]
        v = self.neutral + np.tensordot(w, self.basis, axes=1)
        e = v[ea[:, 0]] - v[ea[:, 1]]
        cov = np.einsum("ea,eb->eab", self.e0[self._moving_e], e).reshape(-1, 9)  # [Em, 9]
        s = (self._inc @ cov + self._s_static).reshape(-1, 3, 3)  # [A, 3, 3]
        u, _, vt = np.linalg.svd(s)
        r = np.einsum("nba,ncb->nac", vt, u)  # V U^T
        det = np.linalg.det(r)
        fix = det < 0
        if fix.any():
            u2 = u[fix].copy()
            u2[:, :, 2] *= -1
            r[fix] = np.einsum("nba,ncb->nac", vt[fix], u2)
        rot[self._active_v] = r
        return rot

    def solve_frame(self, targets_xy: np.ndarray, eye_openness: np.ndarray | None = None) -> np.ndarray:
        """Weights [K] for landmark targets [20, 2] (world X, Y) and eye openness [2] (right, left)."""
        c = self.config
        b_lm = (np.asarray(targets_xy, np.float64) - self.neutral[self.ids, :2]).reshape(-1)
        h = c.landmark_weight * self.h_lm + c.arap_weight * self.h_arap
        g = c.landmark_weight * self.a_lm.T @ b_lm / len(self.ids)
        if eye_openness is not None and c.eye_gap_weight > 0:
            target_gap = self.gap0 * np.asarray(eye_openness, np.float64)
            h = h + c.eye_gap_weight * self.a_gap.T @ self.a_gap
            g = g + c.eye_gap_weight * self.a_gap.T @ (target_gap - self.gap0)
        ridge = c.ridge * max(float(np.abs(np.diag(h)).max()), 1e-12) * np.diag(self.prior)
        w = self._w
        i, j = self.edges[:, 0], self.edges[:, 1]
        n_e = len(self.edges)
        for _ in range(max(1, c.iterations)):
            g_arap = 0.0
            if c.arap_weight > 0:
                rot = self._rotations(w)
                rij = 0.5 * (rot[i] + rot[j])  # [E, 3, 3]
                resid = np.einsum("eab,eb->ea", rij, self.e0) - self.e0  # target edge change [E, 3]
                g_arap = c.arap_weight * self.db @ resid.reshape(-1) / n_e
            for _round in range(3):  # eye-depth active set
                hd = h + ridge
                if self._active.any() and c.eye_depth_weight > 0:
                    a = self.a_depth[self._active]
                    hd = hd + c.eye_depth_weight * a.T @ a / max(len(self.a_depth), 1)
                w = self._solve_linear(hd, g + g_arap)
                if len(self.a_depth) == 0 or c.eye_depth_weight <= 0:
                    break
                viol = self.a_depth @ w > 0
                if not (viol & ~self._active).any():
                    break
                self._active |= viol
        if len(self.a_depth):
            self._active = self.a_depth @ w > -1e-9  # keep what binds for the next frame (warm start)
        self._w = w
        return w

    def solve(self, targets: np.ndarray, eye_openness: np.ndarray | None = None, progress=None) -> np.ndarray:
        """Weights [T, K] for targets [T, 20, 2] (each frame warm-started from the previous)."""
        self.reset()
        out = np.zeros((len(targets), self.k))
        for t in range(len(targets)):
            out[t] = self.solve_frame(targets[t], None if eye_openness is None else eye_openness[t])
            if progress is not None:
                progress(t + 1, len(targets))
        return out
