"""Decomposition: each frame as weights over the key shapes.

Chuang & Bregler (2002, §4.1) model a frame's landmark vector ``S_t`` as a
linear combination of key shapes ``S_i`` (eq. 3) and recover the weights by
non-negative least squares (eq. 4), which avoids the large cancelling weights
of unconstrained least squares that distort the retargeted result (their
Figs. 4–5).

This module provides that solver and its variants, all solved for every frame
at once:

* formulations ``whole`` (eq. 3), ``convex`` (also ``Σ w = 1``, the
  barycentric form of Lewis et al. 2005, §3) and ``delta`` (relative to a
  neutral shape ``S_0``: ``S_t − S_0 ≈ Σ w_i (S_i − S_0)``);
* solvers ``ls``, ``nnls``, ``bounded``, ``ridge`` / ``ridge-clipped``
  (Racković et al. 2023, eqs. 5–6), ``temporal-causal`` (Lewis & Anjyo 2010,
  eq. 2 with the previous frame as ``w_0``), ``temporal`` (a second-difference
  roughness penalty over the whole take, one banded problem), ``sparse`` (an
  L1 term, which with ``w ≥ 0`` is ``α 1ᵀw``) and ``sequential`` (Seol et al.
  2011, Racković et al. 2023 eq. 7).

Every constrained problem here is a box-constrained quadratic programme with
a Hessian shared by all frames, solved exactly for all frames at once by
:mod:`.boxqp` (with per-frame confidence weights, one Hessian per frame); the
solvers across frames are in :mod:`.temporal`, the measures of a result
(residual, cardinality, jitter) in :mod:`.measures`. :func:`decompose` is the
one entry point; the package re-exports the solvers and measures other modules use.
"""

from __future__ import annotations

import numpy as np

from ..._validate import check_array
from ...errors import ParameterError, ShapeError

# The package's public face: the solvers and measures its modules define.
from .boxqp import (  # noqa: E402, F401, I001
    DEFAULT_UPPER,
    _equality_ls,
    _solve_weighted,
    _spread,
    box_qp,
    box_qp_weighted,
    nnls_batched,
    prefetch_kernel,
    weighted_hessians,
)
from .measures import (  # noqa: E402, F401
    CARDINALITY_THRESHOLD,
    cardinality,
    interpolate_lost,
    jitter,
    mean_acceleration,
    row_residuals,
)
from .temporal import (
    _sequential,
    _temporal_causal,
    temporal_events,  # noqa: F401
    temporal_whole,  # noqa: E402, F401
    temporal_windows,
)

#: Solvers available to :func:`decompose`.
SOLVERS = ("nnls", "ls", "bounded", "ridge", "ridge-clipped", "temporal", "temporal-causal", "sparse", "sequential")


#: Formulations available to :func:`decompose`.
FORMULATIONS = ("whole", "convex", "delta")


#: Solvers that do not support ``formulation="convex"``.
NO_CONVEX = ("ridge-clipped", "sequential", "temporal")


#: Default regularisation strength (relative to the keys' spread) per solver.
DEFAULT_ALPHA = {"ridge": 0.01, "ridge-clipped": 0.01, "temporal": 0.1, "temporal-causal": 0.1, "sparse": 0.05}


#: What ``temporal`` and ``temporal-causal`` smooth: the reconstructed shape ``Σ w_i S_i`` or the raw weights.
SMOOTH_SPACES = ("shape", "weights")


#: Default alpha of the temporal solvers in shape space (the penalty is in landmark units, alpha is not scaled).
DEFAULT_SHAPE_ALPHA = {"temporal": 1.0, "temporal-causal": 1.0}


def decompose(frames, keys, *, solver: str = "nnls", formulation: str = "whole", alpha: float | None = None,
              upper: float | None = None, neutral=None, confidence=None, smooth_space: str = "shape",
              robust: float = 0.0):
    """Weights ``w_t`` with ``S_t ≈ Σ_i w_{t,i} S_i`` for every frame.

    The default is Chuang & Bregler's eq. 4:

    .. math::

        \\min_{w_t} \\| S_t - \\sum_{i=1}^{k} w_{t,i} S_i \\|_{C_t}^2
        \\quad \\text{s.t. } w_{t,i} \\ge 0

    where ``‖r‖²_C = Σ_d c_{t,d} r_d²`` weights each coordinate by its
    landmark's confidence (all ones by default). Other solvers add to or
    replace the constraint (``λ = alpha · mean_i ‖S_i − S̄‖²``, so *alpha* is
    relative to the spread of the key shapes and has no units; the temporal
    solvers in shape space use ``λ = alpha``, their penalty being in the
    landmarks' units already):

    ``ls``
        no constraint (their Fig. 4, to show the distortion);
    ``nnls``
        ``w ≥ 0`` (eq. 4; ``w ≤ upper`` too when *upper* is given);
    ``bounded``
        ``0 ≤ w ≤ upper`` (*upper* defaults to 1);
    ``ridge``
        ``+ λ‖w‖²`` unconstrained, the closed form ``(BᵀB + λI)⁻¹Bᵀb`` of
        Racković et al. 2023, eqs. 5–6;
    ``ridge-clipped``
        ``ridge`` clipped to ``[0, upper]`` (*upper* defaults to 1), their
        initialisation;
    ``temporal-causal``
        ``+ λ‖Bᵀ(w_t − w_{t−1})‖²``, ``w ≥ 0``, frame by frame (Lewis & Anjyo
        2010, eq. 2 with the previous frame's weights as ``w_0``, the distance
        measured on the reconstructed shape); ``+ λ‖w_t − w_{t−1}‖²`` with
        ``smooth_space="weights"``;
    ``temporal``
        ``+ λ Σ_t ‖Bᵀ(w_{t−1} − 2w_t + w_{t+1})‖²`` over the whole take
        (``‖D₂ W S‖²``, the acceleration of the reconstructed landmarks),
        ``w ≥ 0``, solved jointly (:func:`temporal_whole`); ``+ λ Σ_t
        ‖w_{t−1} − 2w_t + w_{t+1}‖²`` with ``smooth_space="weights"``;
    ``sparse``
        ``+ λ 1ᵀw``, ``w ≥ 0`` (the L1 norm on the non-negative orthant);
    ``sequential``
        Seol et al. 2011 (Racković et al. 2023, eq. 7): keys visited in order
        of decreasing mean offset, each fitted alone to the remaining residual
        and clipped to ``[0, upper]``.

    Formulations: ``whole`` (eq. 3), ``convex`` (also ``Σ_i w_{t,i} = 1``,
    Lewis et al. 2005 §3) and ``delta`` (``S_t − S_0 ≈ Σ_i w_{t,i} (S_i − S_0)``
    with *neutral* ``S_0``; a key equal to the neutral gets weight 0).

    Parameters
    ----------
    frames : ndarray, shape (T, D)
        Feature vectors per frame (flattened stabilized landmarks).
    keys : ndarray, shape (K, D)
        Key-shape feature vectors.
    solver : str
        One of :data:`SOLVERS`.
    formulation : {"whole", "convex", "delta"}
    alpha : float, optional
        Regularisation strength of ``ridge``, ``ridge-clipped``, ``temporal``,
        ``temporal-causal`` and ``sparse`` (default :data:`DEFAULT_ALPHA`).
    upper : float, optional
        Upper bound on every weight for the constrained solvers.
    neutral : ndarray, shape (D,), optional
        ``S_0``; required by ``formulation="delta"``.
    confidence : ndarray, shape (T, D), optional
        Non-negative weight of each coordinate in each frame (row weights).
    smooth_space : {"shape", "weights"}
        What ``temporal`` and ``temporal-causal`` penalise (see above).
    robust : float
        ``temporal`` only: release the penalty at fast events whose windowed
        excess residual exceeds this (:func:`temporal_events`; 0: off).

    Returns
    -------
    weights : ndarray, shape (T, K)
    residual : ndarray, shape (T,)
        Euclidean norm of each frame's (unweighted) reconstruction error.

    Raises
    ------
    ShapeError, ValueError
        For mismatched shapes, NaN, or unknown or incompatible options.
    """
    S = check_array(frames, "frames", ndim=2)
    B = check_array(keys, "keys", ndim=2)
    T, D = S.shape
    if B.shape[1] != D:
        raise ShapeError(f"keys: expected shape (K, {D}) to match frames, got {B.shape}")
    shape_space, alpha = _check_options(solver, formulation, smooth_space, alpha, upper)
    if formulation == "delta":
        if neutral is None:
            raise ParameterError("neutral: formulation 'delta' needs the neutral shape S_0 (D,)")
        n0 = check_array(neutral, "neutral", ndim=1)
        if n0.shape != (D,):
            raise ShapeError(f"neutral: expected shape ({D},), got {n0.shape}")
        S, B = S - n0, B - n0
    C = _check_confidence(confidence, T, D)

    K = B.shape[0]
    used = np.arange(K)
    if formulation == "delta":
        # A key equal to the neutral has no delta: it gets weight 0.
        norms = np.einsum("kd,kd->k", B, B)
        used = np.flatnonzero(norms > 1e-20 * max(norms.max(initial=0.0), 1.0))
    W = np.zeros((T, K))
    if used.size:
        W[:, used] = _solve(S, B[used], C, solver=solver, convex=formulation == "convex",
                            lam=alpha if shape_space else alpha * _spread(B[used]), upper=upper,
                            shape_space=shape_space, robust=robust)
    return W, row_residuals(S, W, B)


def _check_options(solver, formulation, smooth_space, alpha, upper) -> tuple[bool, float]:
    """Check :func:`decompose`'s options; whether the smoothing is in shape space, and alpha (its default filled)."""
    if solver not in SOLVERS:
        raise ParameterError(f"solver: expected one of {SOLVERS}, got {solver!r}")
    if formulation not in FORMULATIONS:
        raise ParameterError(f"formulation: expected one of {FORMULATIONS}, got {formulation!r}")
    if formulation == "convex" and solver in NO_CONVEX:
        raise ParameterError(f"solver {solver!r} does not support formulation 'convex' "
                             f"(use one of {tuple(s for s in SOLVERS if s not in NO_CONVEX)})")
    if smooth_space not in SMOOTH_SPACES:
        raise ParameterError(f"smooth_space: expected one of {SMOOTH_SPACES}, got {smooth_space!r}")
    shape_space = smooth_space == "shape" and solver in ("temporal", "temporal-causal")
    if alpha is None:
        alpha = (DEFAULT_SHAPE_ALPHA if shape_space else DEFAULT_ALPHA).get(solver, 0.0)
    if not np.isfinite(alpha) or alpha < 0:
        raise ParameterError(f"alpha: expected a finite number >= 0, got {alpha!r}")
    if upper is not None and not upper > 0:
        raise ParameterError(f"upper: expected a number > 0, got {upper!r}")
    return shape_space, alpha


def _check_confidence(confidence, T: int, D: int) -> np.ndarray | None:
    """Per-coordinate weights (T, D) >= 0, or None when absent or all 1."""
    if confidence is None:
        return None
    C = check_array(confidence, "confidence", ndim=2)
    if C.shape != (T, D):
        raise ShapeError(f"confidence: expected shape ({T}, {D}) like frames, got {C.shape}")
    if np.any(C < 0):
        raise ParameterError("confidence: weights must be >= 0")
    return None if np.all(C == 1) else C


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


def _groups(C, T):
    """Frames sharing a confidence row: yields (frame indices, row or None)."""
    if C is None:
        yield np.arange(T), None
        return
    uniq, inv = np.unique(C, axis=0, return_inverse=True)
    inv = inv.ravel()
    for g in range(len(uniq)):
        yield np.flatnonzero(inv == g), uniq[g]


def _solve(S, B, C, *, solver, convex, lam, upper, shape_space=False, robust=0.0):
    """Weights (T, K) for one formulation's frames S (T, D) and keys B (K, D)."""
    T, K = len(S), len(B)
    eq = 1.0 if convex else None
    if solver == "temporal":
        return temporal_windows(S, B, lam=lam, upper=upper, confidence=C, shape_space=shape_space, robust=robust)
    if solver == "temporal-causal":
        return _temporal_causal(S, B, C, lam=lam, upper=upper, eq=eq, shape_space=shape_space)
    if solver == "sequential":
        return _sequential(S, B, C, upper=upper)
    if C is not None:
        return _solve_weighted(S, B, C, solver=solver, eq=eq, lam=lam, upper=upper)
    W = np.empty((T, K))
    for rows, c in _groups(C, T):
        Bc = B if c is None else B * c
        H = Bc @ B.T
        Q = S[rows] @ Bc.T
        if solver in ("ridge", "ridge-clipped"):
            H = H + lam * np.eye(K)
        if solver in ("ls", "ridge", "ridge-clipped"):
            X = _equality_ls(H, Q, eq)
            if solver == "ridge-clipped":
                X = np.clip(X, 0.0, DEFAULT_UPPER if upper is None else upper)
        else:
            hi = DEFAULT_UPPER if (solver == "bounded" and upper is None) else (np.inf if upper is None else upper)
            if solver == "sparse":
                Q = Q - lam / 2
            X = box_qp(H, Q, lower=0.0, upper=hi, sum_to=eq)
        W[rows] = X
    return W
