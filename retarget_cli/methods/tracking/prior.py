"""Shape prior built from annotated frames: recovers unreliable landmarks from the rest.

The annotated shapes are aligned by similarity Procrustes to the first one;
their mean and, when there are several, principal modes (a point distribution
model, as in active shape models) describe the plausible shapes. Fitting the
model to the reliable points of a frame (weighted by confidence) predicts
every landmark, so lost points are put back where the rest of the face says
they are instead of drifting.
"""

from __future__ import annotations

import numpy as np

from ...errors import ShapeError
from .head import apply_similarity, fit_similarity, invert_similarity


class ShapePrior:
    """Similarity-aligned mean shape plus PCA modes of the annotated shapes.

    Parameters
    ----------
    shapes : ndarray, shape (K, L, 2)
        Annotated landmark sets (K >= 1).
    variance : float
        Fraction of the shape variance the kept modes explain.
    limit : float
        Mode coefficients are clamped to ``±limit`` standard deviations.
    """

    def __init__(self, shapes, *, variance: float = 0.98, limit: float = 3.0):
        S = np.asarray(shapes, dtype=np.float64)
        if S.ndim == 2:
            S = S[None]
        if S.ndim != 3 or S.shape[2] != 2 or S.shape[1] < 2:
            raise ShapeError(f"shapes: expected shape (K, L, 2) with L >= 2, got {S.shape}")
        K, L, _ = S.shape
        M = fit_similarity(S[0], S, iterations=0)
        aligned = apply_similarity(invert_similarity(M), S)
        self.mean = aligned.mean(0)
        self.limit = limit
        X = (aligned - self.mean).reshape(K, -1)
        if K >= 2:
            _, sv, Vt = np.linalg.svd(X, full_matrices=False)
            var = sv**2 / (K - 1)
            keep = var > 1e-9 * max(var.max(), 1e-12)
            cum = np.cumsum(var[keep]) / max(var[keep].sum(), 1e-12)
            n = int(np.searchsorted(cum, variance) + 1) if keep.any() else 0
            self.modes = Vt[:n].reshape(n, L, 2)
            self.sd = np.sqrt(var[:n])
        else:
            self.modes = np.zeros((0, L, 2))
            self.sd = np.zeros(0)

    @property
    def n_points(self) -> int:
        return int(self.mean.shape[0])

    def fit(self, points, weights, *, iterations: int = 3) -> np.ndarray:
        """Model shape closest to *points* where *weights* are high.

        Parameters
        ----------
        points : ndarray, shape (L, 2)
            Current landmark estimates (any values where the weight is 0).
        weights : ndarray, shape (L,)
            Non-negative reliability of each estimate.

        Returns
        -------
        ndarray, shape (L, 2)
            The fitted model shape in image pixels.
        """
        P = np.asarray(points, dtype=np.float64)
        w = np.asarray(weights, dtype=np.float64)
        if P.shape != self.mean.shape or w.shape != (self.n_points,):
            raise ShapeError(f"points/weights: expected shapes {self.mean.shape} and {(self.n_points,)}, "
                             f"got {P.shape} and {w.shape}")
        P = np.where(np.isfinite(P), P, 0.0)
        w = np.where(np.isfinite(np.asarray(points)).all(1), np.clip(w, 0, None), 0.0)
        shape = self.mean.copy()
        n = len(self.sd)
        for _ in range(iterations):
            M = fit_similarity(shape, P[None], w[None], iterations=1)[0]
            if n == 0:
                return shape @ M[:, :2].T + M[:, 2]
            y = apply_similarity(invert_similarity(M[None]), P[None])[0]
            B = self.modes.reshape(n, -1).T  # (2L, n)
            ww = np.repeat(w, 2)
            r = (y - self.mean).ravel()
            A = B.T @ (ww[:, None] * B) + np.diag(1.0 / np.maximum(self.sd, 1e-6) ** 2) * 1e-2 * max(w.sum(), 1e-9)
            c = np.linalg.solve(A, B.T @ (ww * r))
            c = np.clip(c, -self.limit * self.sd, self.limit * self.sd)
            shape = self.mean + (B @ c).reshape(-1, 2)
        M = fit_similarity(shape, P[None], w[None], iterations=1)[0]
        return shape @ M[:, :2].T + M[:, 2]
