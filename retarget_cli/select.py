"""Key-shape selection (Chuang & Bregler 2002, §4.2).

Key shapes are frames of the take. The artist sculpts one target shape per
key, so keys are chosen to cover the take's shape variation with as few frames
as possible, and each choice is scored by the reconstruction error E (eq. 5).
"""

from __future__ import annotations

import logging

import numpy as np

from ._validate import check_array
from .errors import ShapeError

log = logging.getLogger(__name__)

#: Selection methods available to :func:`select_keys`.
METHODS = ("pca-extremes",)


def pca_extremes(features, k: int, *, include=()) -> np.ndarray:
    """Frames of maximum and minimum projection on the principal axes.

    "Maximum spread along principal components" (Chuang & Bregler 2002,
    §4.2): starting from the axis of largest variance, the frames with the
    largest and smallest projection become keys, so k keys use about k/2 axes.
    A frame already chosen is skipped and the next axis supplies the
    remaining keys, so the result always holds k distinct frames; for odd k the
    last axis contributes only its maximum.

    Parameters
    ----------
    features : ndarray, shape (T, D)
        One flattened stabilized shape per frame.
    k : int
        Number of keys, 1 <= k <= number of distinct frames.
    include : sequence of int
        Frames that must be keys (e.g. the neutral); they count towards k and
        are chosen first.

    Returns
    -------
    ndarray of int, shape (k,)
        Frame indices, in the order chosen.
    """
    X = check_array(features, "features", ndim=2)
    T = X.shape[0]
    if k < 1:
        raise ShapeError(f"k: expected k >= 1, got {k}")
    Xc = X - X.mean(0)
    if not np.any(np.abs(Xc) > 1e-9):
        raise ShapeError("features: every frame has the same shape (no variation to choose keys from)")
    n_distinct = len(np.unique(X.round(6), axis=0))
    if k > n_distinct:
        raise ShapeError(f"k: {k} keys requested but the take has only {n_distinct} distinct frames")
    from sklearn.decomposition import PCA

    n_comp = min(T, X.shape[1])
    proj = PCA(n_components=n_comp, svd_solver="full").fit_transform(X)
    chosen: list[int] = []
    for f in include:
        if not 0 <= int(f) < T:
            raise ShapeError(f"include: frame {f} is outside the take (0..{T - 1})")
        if int(f) not in chosen and len(chosen) < k:
            chosen.append(int(f))
    if len(chosen) == k:
        return np.array(chosen)
    for axis in range(n_comp):
        # Stable order: ties broken by the lower frame index.
        order_max = np.lexsort((np.arange(T), -proj[:, axis]))
        order_min = np.lexsort((np.arange(T), proj[:, axis]))
        for order in (order_max, order_min):
            for f in order:
                if f not in chosen:
                    chosen.append(int(f))
                    break
            if len(chosen) == k:
                return np.array(chosen)
    # Fewer useful axes than k/2: fill with frames farthest from the chosen set.
    while len(chosen) < k:
        d = np.min(np.linalg.norm(X[:, None, :] - X[None, chosen, :], axis=2), axis=1)
        chosen.append(int(np.argmax(d)))
    return np.array(chosen)


def select_keys(features, k: int, *, method: str = "pca-extremes", include=()) -> np.ndarray:
    """Choose *k* key frames with the named *method*.

    Parameters
    ----------
    features : ndarray, shape (T, D)
    k : int
    method : {"pca-extremes"}
    include : sequence of int
        Frames that must be keys (counted in k), e.g. the neutral frame: with
        the whole-shape model of eq. 3 and non-negative weights, a frame can
        only be reproduced inside the cone of the keys, so a take whose keys
        are all expressive cannot return to rest.

    Returns
    -------
    ndarray of int, shape (k,)
        Key frame indices, sorted ascending.
    """
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    frames = pca_extremes(features, k, include=include)
    return np.sort(frames)
