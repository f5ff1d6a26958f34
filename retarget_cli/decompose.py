"""Decomposition: each frame as non-negative weights over the key shapes.

Chuang & Bregler (2002, §4.1) model a frame's landmark vector ``S_t`` as a
linear combination of key shapes ``S_i`` (eq. 3) and recover the weights by
non-negative least squares (eq. 4), which avoids the large cancelling weights
of unconstrained least squares that distort the retargeted result.
"""

from __future__ import annotations

import logging

import numpy as np

from ._validate import check_array
from .errors import ShapeError

log = logging.getLogger(__name__)

#: Solvers available to :func:`decompose`.
SOLVERS = ("nnls", "ls")


def decompose(frames, keys, *, solver: str = "nnls"):
    """Weights ``w_t`` with ``S_t ≈ Σ_i w_{t,i} S_i`` for every frame.

    .. math::

        \\min_{w_t} \\| S_t - \\sum_{i=1}^{k} w_{t,i} S_i \\|^2
        \\quad \\text{s.t. } w_{t,i} \\ge 0

    (Chuang & Bregler 2002, eq. 3 and 4; ``solver="ls"`` drops the
    constraint, as in their Fig. 4, to show why it is needed).

    Parameters
    ----------
    frames : ndarray, shape (T, D)
        Feature vectors per frame (flattened stabilized landmarks).
    keys : ndarray, shape (K, D)
        Key-shape feature vectors.
    solver : {"nnls", "ls"}

    Returns
    -------
    weights : ndarray, shape (T, K)
    residual : ndarray, shape (T,)
        Euclidean norm of each frame's reconstruction error.
    """
    S = check_array(frames, "frames", ndim=2)
    B = check_array(keys, "keys", ndim=2)
    if B.shape[1] != S.shape[1]:
        raise ShapeError(f"keys: expected shape (K, {S.shape[1]}) to match frames, got {B.shape}")
    if solver not in SOLVERS:
        raise ValueError(f"solver: expected one of {SOLVERS}, got {solver!r}")
    if solver == "ls":
        W = np.linalg.lstsq(B.T, S.T, rcond=None)[0].T
    else:
        from scipy.optimize import nnls

        A = B.T
        W = np.empty((S.shape[0], B.shape[0]))
        for t in range(S.shape[0]):
            W[t] = nnls(A, S[t])[0]
    residual = np.linalg.norm(S - W @ B, axis=1)
    return W, residual


def reconstruction_error(frames, keys) -> float:
    """Chuang & Bregler's key-set score ``E = Σ_t ||Q_t - F(w, S)||²`` (eq. 5).

    The weights come from NNLS (eq. 4), as in the paper's Figure 6.

    Parameters
    ----------
    frames : ndarray, shape (T, D)
    keys : ndarray, shape (K, D)

    Returns
    -------
    float
    """
    _, res = decompose(frames, keys, solver="nnls")
    return float(np.sum(res**2))
