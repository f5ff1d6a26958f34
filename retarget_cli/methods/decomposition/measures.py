"""Measures of a decomposition and of any trajectory: residuals, cardinality, jitter, acceleration,
and the interpolation of lost frames. Used by the decomposition, the report and the truth metrics.
"""

from __future__ import annotations

import numpy as np

from ..._validate import check_array
from ...errors import ParameterError, ShapeError

#: A weight above this counts towards the frame's cardinality.
CARDINALITY_THRESHOLD = 0.01


def row_residuals(S, W, B, step: int = 8192) -> np.ndarray:
    """``‖S_t − W_t B‖`` per frame, a block of frames at a time (no (T, D) temporaries)."""
    out = np.empty(len(S))
    for c0 in range(0, len(S), step):
        out[c0:c0 + step] = np.linalg.norm(S[c0:c0 + step] - W[c0:c0 + step] @ B, axis=1)
    return out


def cardinality(weights, threshold: float = CARDINALITY_THRESHOLD) -> np.ndarray:
    """Number of weights above *threshold* in each frame.

    Parameters
    ----------
    weights : ndarray, shape (T, K)

    Returns
    -------
    ndarray of int64, shape (T,)
    """
    W = check_array(weights, "weights", ndim=2)
    return np.count_nonzero(W > threshold, axis=1).astype(np.int64)


def jitter(weights) -> float:
    """Mean squared second difference of the weight curves, ``mean (w_{t−1} − 2w_t + w_{t+1})²``.

    Parameters
    ----------
    weights : ndarray, shape (T, K)

    Returns
    -------
    float
        0 for fewer than three frames.
    """
    W = check_array(weights, "weights", ndim=2)
    if len(W) < 3:
        return 0.0
    return float(np.mean(np.diff(W, n=2, axis=0) ** 2))


def mean_acceleration(x) -> float:
    """Mean point acceleration of a point sequence, ``mean_{t,v} ‖x_{t−1,v} − 2x_{t,v} + x_{t+1,v}‖``.

    The mesh-space jitter measure: for landmarks (pixels per frame²) or mesh
    vertices (model units per frame²).

    Parameters
    ----------
    x : ndarray, shape (T, N, d) or (T, N·d) with ``d`` given by the last axis
        A (T, D) array is read as (T, D/2, 2): 2-D landmarks, flattened.

    Returns
    -------
    float
        0 for fewer than three frames.
    """
    X = np.asarray(x, dtype=np.float64)
    if X.ndim == 2:
        X = X.reshape(len(X), -1, 2)
    if X.ndim != 3:
        raise ShapeError(f"x: expected shape (T, N, d) or (T, D), got {X.shape}")
    if len(X) < 3:
        return 0.0
    # a block of frames at a time (no (T, N, d) temporaries); per point the root of the summed
    # squares over the last axis, as numpy.linalg.norm computes it
    T, N, d = X.shape
    step = max(1, 2**20 // max(N * d, 1))
    total = 0.0
    for c0 in range(0, T - 2, step):
        blk = X[c0:min(c0 + step, T - 2) + 2]
        acc = (blk[2:] - blk[1:-1]) - (blk[1:-1] - blk[:-2])
        acc *= acc
        total += float(np.sqrt(acc.sum(-1) if d != 2 else acc[..., 0] + acc[..., 1]).sum())
    return total / ((T - 2) * N)


def interpolate_lost(weights, lost) -> np.ndarray:
    """Replace the weights of *lost* frames by linear interpolation between kept frames.

    Frames before the first (after the last) kept frame take its weights.

    Parameters
    ----------
    weights : ndarray, shape (T, K)
    lost : ndarray of bool, shape (T,)

    Returns
    -------
    ndarray, shape (T, K)

    Raises
    ------
    ValueError
        When every frame is lost.
    """
    W = check_array(weights, "weights", ndim=2)
    lost = np.asarray(lost, dtype=bool)
    if lost.shape != (len(W),):
        raise ShapeError(f"lost: expected shape ({len(W)},), got {lost.shape}")
    if lost.all():
        raise ParameterError("every frame is lost; nothing to interpolate from")
    if not lost.any():
        return W.copy()
    t = np.arange(len(W))
    keep = ~lost
    out = W.copy()
    for k in range(W.shape[1]):
        out[lost, k] = np.interp(t[lost], t[keep], W[keep, k])
    return out
