"""Head motion: per-frame 2D similarity between stabilized and image landmarks.

Chuang & Bregler (2002, §3 and §5) remove the head's rigid motion before
decomposing expressions and put it back on the character afterwards. We model
it as a 2D similarity (uniform scale, roll, translation) fitted by weighted,
iteratively reweighted least squares on a set of points that expressions do not
move (eye corners and nose for the 68-point Multi-PIE layout).
"""

from __future__ import annotations

import numpy as np

from ...errors import ShapeError

#: Rigid points of the 68-point Multi-PIE layout (0-based): eye corners
#: (36, 39, 42, 45) and the nose bridge and base (27-31, 33, 35).
RIGID_68 = (27, 28, 29, 30, 31, 33, 35, 36, 39, 42, 45)


def default_rigid_points(n_points: int) -> np.ndarray:
    """Indices used to fit head motion when the user names none.

    Parameters
    ----------
    n_points : int
        Landmark count L.

    Returns
    -------
    ndarray of int
        :data:`RIGID_68` for L = 68, otherwise all points (the robust fit then
        down-weights those that move with expressions).
    """
    if n_points == 68:
        return np.array(RIGID_68)
    return np.arange(n_points)


def fit_similarity(src, dst, weights=None, *, iterations: int = 3) -> np.ndarray:
    """Least-squares 2D similarity ``dst ≈ s R src + t`` for many frames at once.

    Treating points as complex numbers ``z``, the model is
    ``z_dst = a z_src + b`` with complex ``a = s e^{iθ}``; the weighted LS
    solution is closed form. A few IRLS passes with Huber weights (scale set
    from the median residual) make it robust to a minority of bad points.

    Parameters
    ----------
    src : ndarray, shape (L, 2) or (T, L, 2)
        Source points (e.g. the stabilized reference shape).
    dst : ndarray, shape (T, L, 2)
        Destination points per frame.
    weights : ndarray, shape (T, L), optional
        Non-negative per-point weights (e.g. tracking confidence).
    iterations : int
        IRLS passes after the first weighted fit (0 = plain weighted LS).

    Returns
    -------
    ndarray, shape (T, 2, 3), float64
        Affine matrices ``[[s cos θ, -s sin θ, tx], [s sin θ, s cos θ, ty]]``.
    """
    dst = np.asarray(dst, dtype=np.float64)
    if dst.ndim != 3 or dst.shape[2] != 2:
        raise ShapeError(f"dst: expected shape (T, L, 2), got {dst.shape}")
    T, L, _ = dst.shape
    src = np.asarray(src, dtype=np.float64)
    if src.shape not in ((L, 2), (T, L, 2)):  # (L, 2) broadcasts over the frames
        src = np.broadcast_to(src, (T, L, 2))
    w0 = np.ones((T, L)) if weights is None else np.asarray(weights, dtype=np.float64).copy()
    if w0.shape != (T, L):
        raise ShapeError(f"weights: expected shape {(T, L)}, got {w0.shape}")
    finite = np.isfinite(dst).all(-1)
    w0 = np.where(finite, np.clip(w0, 0, None), 0.0)
    if not finite.all():
        dst = np.nan_to_num(dst)
    from ._kernels import similarity_irls  # numba: imported on first use

    zs = np.ascontiguousarray(np.broadcast_to(src[..., 0] + 1j * src[..., 1], (T, L)))
    zd = np.ascontiguousarray(dst[..., 0] + 1j * dst[..., 1])
    out = np.empty((T, 2, 3))
    similarity_irls(zs, zd, np.ascontiguousarray(w0), int(iterations), out)
    return out


def apply_similarity(head, points) -> np.ndarray:
    """Map points through per-frame 2x3 matrices.

    Parameters
    ----------
    head : ndarray, shape (T, 2, 3)
    points : ndarray, shape (T, L, 2)

    Returns
    -------
    ndarray, shape (T, L, 2)
    """
    head = np.asarray(head, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    out = np.einsum("tij,tlj->tli", head[:, :, :2], points)
    out += head[:, None, :, 2]  # in place: one (T, L, 2) array, not two
    return out


def invert_similarity(head) -> np.ndarray:
    """Inverse of per-frame 2x3 affine matrices, shape (T, 2, 3) -> (T, 2, 3)."""
    head = np.asarray(head, dtype=np.float64)
    inv = np.linalg.inv(head[:, :, :2])
    t = -np.einsum("tij,tj->ti", inv, head[:, :, 2])
    return np.concatenate([inv, t[:, :, None]], axis=2)


#: Frames mapped at once by :func:`estimate_head` when it writes the stabilized landmarks in another dtype.
CHUNK = 4096


def fit_head(points, confidence=None, *, rigid_points=None, reference_frame: int = 0) -> np.ndarray:
    """The head motion of :func:`estimate_head` alone (its ``head``; the stabilized landmarks not made).

    Parameters and errors as :func:`estimate_head`.

    Returns
    -------
    head : ndarray, shape (T, 2, 3), float64
        Similarity mapping stabilized coordinates to image pixels (``head[reference_frame]`` the identity).
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 3 or points.shape[2] != 2 or points.shape[0] == 0:
        raise ShapeError(f"points: expected shape (T, L, 2) with T >= 1, got {points.shape}")
    T, L, _ = points.shape
    idx = default_rigid_points(L) if rigid_points is None else np.asarray(rigid_points, dtype=int)
    if idx.size < 2 or idx.min() < 0 or idx.max() >= L:
        raise ShapeError(f"rigid_points: need at least 2 indices in [0, {L}), got {idx.tolist()}")
    if not 0 <= reference_frame < T:
        raise ShapeError(f"reference_frame: expected 0 <= frame < {T}, got {reference_frame}")
    conf = None if confidence is None else np.asarray(confidence, dtype=np.float64)[:, idx]
    ref = points[reference_frame, idx]
    if not np.all(np.isfinite(ref)):
        raise ShapeError(f"points: reference frame {reference_frame} has non-finite rigid points")
    return fit_similarity(ref, points[:, idx], conf)


def stabilized_rows(inverse, points, a: int, b: int) -> np.ndarray:
    """Rows ``a:b`` of the stabilized landmarks (float64): *points* (T, L, 2) mapped through *inverse* (T, 2, 3),
    the inverse of :func:`fit_head`'s head (:func:`invert_similarity`). Each row is mapped on its own, so the
    rows are those of mapping the whole take at once."""
    return apply_similarity(inverse[a:b], np.asarray(points[a:b], dtype=np.float64))


def estimate_head(points, confidence=None, *, rigid_points=None, reference_frame: int = 0, dtype=np.float64):
    """Separate head motion from expression (the routine every consumer uses).

    The reference is the rigid points of *reference_frame*, so stabilized
    coordinates are that frame's image pixels and ``head[reference_frame]`` is
    the identity.

    Parameters
    ----------
    points : ndarray, shape (T, L, 2)
        Image landmarks in pixels.
    confidence : ndarray, shape (T, L), optional
        Per-point weights in [0, 1].
    rigid_points : sequence of int, optional
        Indices that expressions do not move; default
        :func:`default_rigid_points`.
    reference_frame : int
        Frame whose pose defines the stabilized coordinate frame.
    dtype : dtype
        Of *stabilized*: another than float64 (float32, as ``landmarks.npz`` stores it) is written
        :data:`CHUNK` frames at a time, each mapped at float64 and rounded once, so no float64 copy of the
        whole take is made.

    Returns
    -------
    head : ndarray, shape (T, 2, 3), float64
        Similarity mapping stabilized coordinates to image pixels.
    stabilized : ndarray, shape (T, L, 2), *dtype*
        Landmarks with the head motion removed.
    """
    points = np.asarray(points, dtype=np.float64)
    head = fit_head(points, confidence, rigid_points=rigid_points, reference_frame=reference_frame)
    inverse = invert_similarity(head)
    if np.dtype(dtype) == np.float64:
        return head, apply_similarity(inverse, points)
    T = len(points)
    stabilized = np.empty(points.shape, dtype)
    for a in range(0, T, CHUNK):
        stabilized[a:a + CHUNK] = stabilized_rows(inverse, points, a, a + CHUNK)
    return head, stabilized


def smooth_head(head, window: int) -> np.ndarray:
    """Temporal smoothing of a head track, keeping frame 0 the identity.

    The similarity parameters ``(s cos θ, s sin θ, tx, ty)`` are filtered
    with a Savitzky–Golay filter (quadratic, *window* frames), then the track
    is re-expressed relative to its smoothed frame 0.

    Parameters
    ----------
    head : ndarray, shape (T, 2, 3)
    window : int
        Filter length in frames (odd >= 3; even values are rounded up). Tracks
        shorter than the window are returned unchanged.

    Returns
    -------
    ndarray, shape (T, 2, 3)
    """
    from scipy.signal import savgol_filter

    head = np.asarray(head, dtype=np.float64)
    if head.ndim != 3 or head.shape[1:] != (2, 3):
        raise ShapeError(f"head: expected shape (T, 2, 3), got {head.shape}")
    window = int(window) | 1
    if window < 3 or len(head) < window:
        return head.copy()
    p = np.stack([head[:, 0, 0], head[:, 1, 0], head[:, 0, 2], head[:, 1, 2]], 1)
    p = savgol_filter(p, window, 2, axis=0, mode="interp")
    out = np.empty_like(head)
    out[:, 0, 0], out[:, 0, 1], out[:, 0, 2] = p[:, 0], -p[:, 1], p[:, 2]
    out[:, 1, 0], out[:, 1, 1], out[:, 1, 2] = p[:, 1], p[:, 0], p[:, 3]
    inv0 = invert_similarity(out[:1])[0]
    A = out[:, :, :2] @ inv0[:, :2]
    t = np.einsum("tij,j->ti", out[:, :, :2], inv0[:, 2]) + out[:, :, 2]
    res = np.concatenate([A, t[:, :, None]], axis=2)
    res[0] = np.eye(2, 3)
    return res
