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
a Hessian shared by all frames, ``min ½ wᵀHw − q_tᵀw, lo ≤ w ≤ hi``
(optionally ``1ᵀw = 1``). :func:`box_qp` solves all frames together by a
primal–dual active-set iteration (Hintermüller, Ito & Kunisch 2002) whose
per-frame reduced systems are solved by Cholesky factorisations vectorised
across frames, bucketed by free-set size (or, for long takes, per frame in a
compiled kernel); each frame's answer is certified by its KKT conditions, and the
few frames that do not settle are finished by an exact per-frame primal
active-set method (Nocedal & Wright, Algorithm 16.3). The result is the exact
optimum, not an approximation. With per-frame confidence weights the Hessian
differs per frame: :func:`weighted_hessians` forms all of them in one matrix
product and :func:`box_qp_weighted` solves them by the same method.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading

import numpy as np

from ..._validate import check_array
from ...errors import ParameterError, ShapeError

log = logging.getLogger(__name__)

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
#: Upper bound of ``bounded`` and ``ridge-clipped`` when none is given.
DEFAULT_UPPER = 1.0
#: A weight above this counts towards the frame's cardinality.
CARDINALITY_THRESHOLD = 0.01

_EPS = np.finfo(np.float64).eps


# --------------------------------------------------------------------------- public API


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


def _bounds(lower, upper, K: int, sum_to=None) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds broadcast to (K,) float64 copies; checked against each other and *sum_to*."""
    lo = np.broadcast_to(np.asarray(lower, dtype=np.float64), (K,)).copy()
    hi = np.broadcast_to(np.asarray(upper, dtype=np.float64), (K,)).copy()
    if np.any(lo > hi):
        raise ParameterError("bounds: lower must not exceed upper")
    if sum_to is not None and not (lo.sum() <= sum_to <= hi.sum()):
        raise ParameterError(f"sum_to: {sum_to} cannot be reached within the bounds")
    return lo, hi


def row_residuals(S, W, B, step: int = 8192) -> np.ndarray:
    """``‖S_t − W_t B‖`` per frame, a block of frames at a time (no (T, D) temporaries)."""
    out = np.empty(len(S))
    for c0 in range(0, len(S), step):
        out[c0:c0 + step] = np.linalg.norm(S[c0:c0 + step] - W[c0:c0 + step] @ B, axis=1)
    return out


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


def nnls_batched(frames, keys, *, upper: float | None = None, confidence=None,
                 compiled: bool | None = None) -> np.ndarray:
    """Exact non-negative least squares for every frame at once (eq. 4).

    Solves ``min ‖S_t − Σ w_i S_i‖²_{C_t}, w ≥ 0`` (and ``w ≤ upper``) for
    all frames: with one shared Gram matrix ``H = B Bᵀ`` through
    :func:`box_qp`, or, with *confidence*, with every frame's
    ``H_t = B C_t Bᵀ`` formed in one product (:func:`weighted_hessians`)
    through :func:`box_qp_weighted`. Agrees with ``scipy.optimize.nnls``
    frame by frame (on the rows scaled by ``√c_t``).

    Parameters
    ----------
    frames : ndarray, shape (T, D)
    keys : ndarray, shape (K, D)
    upper : float, optional
    confidence : ndarray, shape (T, D), optional
        Non-negative weight of each coordinate in each frame.
    compiled : bool, optional
        Force (True) or avoid (False) the compiled kernel; by default the
        solver decides from the problem size.

    Returns
    -------
    ndarray, shape (T, K)
    """
    S = check_array(frames, "frames", ndim=2)
    B = check_array(keys, "keys", ndim=2)
    if B.shape[1] != S.shape[1]:
        raise ShapeError(f"keys: expected shape (K, {S.shape[1]}) to match frames, got {B.shape}")
    hi = np.inf if upper is None else upper
    if confidence is not None:
        C = check_array(confidence, "confidence", ndim=2)
        if C.shape != S.shape:
            raise ShapeError(f"confidence: expected shape {S.shape} like frames, got {C.shape}")
        with _one_blas_thread(len(S)):
            Htri, Q = weighted_hessians(B, C), (S * C) @ B.T
        return box_qp_weighted(Htri, Q, lower=0.0, upper=hi, compiled=compiled)
    with _one_blas_thread(len(S)):
        return box_qp(B @ B.T, S @ B.T, lower=0.0, upper=hi, compiled=compiled)


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


# --------------------------------------------------------------------------- solvers


def _spread(B: np.ndarray) -> float:
    """Scale for *alpha*: ``mean_i ‖S_i − S̄‖²`` (or ``mean ‖S_i‖²`` for one key)."""
    spread = float(np.mean(np.sum((B - B.mean(0)) ** 2, axis=1))) if len(B) > 1 else 0.0
    if spread <= 1e-12 * max(float(np.mean(np.sum(B**2, axis=1))), 1e-300):
        spread = float(np.mean(np.sum(B**2, axis=1)))
    return spread if spread > 0 else 1.0


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
        return temporal_events(S, B, lam=lam, upper=upper, confidence=C, shape_space=shape_space, robust=robust)
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


def _pinv_sym(M: np.ndarray) -> np.ndarray:
    """Pseudo-inverse of a symmetric matrix (eigenvalues below ``n·eps·max|λ|`` dropped)."""
    if M.size == 0:
        return M.copy()
    lam, V = np.linalg.eigh(M)
    cut = max(np.abs(lam).max(), 1e-300) * M.shape[0] * _EPS * 4
    inv = np.where(np.abs(lam) > cut, 1.0 / np.where(lam == 0, 1.0, lam), 0.0)
    return (V * inv) @ V.T


def _equality_ls(H, Q, eq):
    """Unconstrained minimiser of ``½wᵀHw − qᵀw`` (with ``1ᵀw = eq`` if given); minimum norm when singular."""
    if eq is None:
        return Q @ _pinv_sym(H)
    K = len(H)
    M = np.zeros((K + 1, K + 1))
    M[:K, :K], M[:K, K], M[K, :K] = H, 1.0, 1.0
    R = np.hstack([Q, np.full((len(Q), 1), eq)])
    return (R @ _pinv_sym(M))[:, :K]


def box_qp(H, Q, *, lower=0.0, upper=np.inf, sum_to=None, max_iter: int = 30, chunk: int = 8192,
           compiled: bool | None = None) -> np.ndarray:
    """Exact minimiser of a box-constrained QP for many right-hand sides at once.

    .. math::

        \\min_{x_t} \\tfrac12 x_t^T H x_t - q_t^T x_t
        \\quad \\text{s.t. } l \\le x_t \\le u \\;(\\text{and } 1^T x_t = s)

    for every row ``q_t`` of *Q*, with *H* shared (``H = BBᵀ`` and
    ``q_t = B S_t`` give the NNLS of Chuang & Bregler's eq. 4).

    Method: a primal–dual active-set iteration (Hintermüller, Ito & Kunisch
    2002) started from each frame's unconstrained minimiser. Each iteration
    solves the frame's reduced system ``H_FF x_F = q_F − H_FB x_B`` on its
    current free set F; a frame is finished when its KKT conditions hold
    (free variables within their bounds, multipliers of the bound ones
    correctly signed), so the solution on its free set is the exact optimum.
    Active sets differ from frame to frame, so frames cannot share
    factorisations. The iteration runs in numpy on all frames at once, the
    reduced systems bucketed by size into vectorised Cholesky solves; for
    large problems without an equality (see *compiled*) it runs per frame in
    compiled code instead (:mod:`retarget_cli.methods.decomposition._qp_kernel`), and the rare
    frames the kernel leaves go back to numpy. Frames still unsettled after
    *max_iter* iterations are finished one by one by an exact primal
    active-set method (Nocedal & Wright 2006, Algorithm 16.3).

    A singular *H* (duplicated or dependent keys) is handled by adding
    ``1e-14·max(diag H)`` to the reduced diagonals, which changes the
    objective by a relative amount of that order (minimum-norm limit).

    Parameters
    ----------
    H : ndarray, shape (K, K)
        Symmetric positive semi-definite.
    Q : ndarray, shape (T, K)
    lower, upper : float or ndarray of shape (K,)
        Bounds; ``upper`` may be ``inf``.
    sum_to : float, optional
        Also require ``Σ_i x_{t,i} = sum_to``.
    max_iter : int
        Batched iterations before the per-frame finish.
    chunk : int
        Frames solved together (bounds the memory of the stacked systems).
    compiled : bool, optional
        Use the compiled kernel (True) or the numpy iteration (False). By
        default the kernel runs when ``T·K ≥ 2·10⁶`` (about 90,000 frames at
        K = 22): below that the numpy iteration finishes before numba would
        have loaded (about a second per process). Both give the exact optimum;
        their results differ by round-off only, and the choice depends on
        the problem's size alone, so outputs stay reproducible.

    Returns
    -------
    ndarray, shape (T, K)
    """
    H = np.asarray(H, dtype=np.float64)
    Q = np.atleast_2d(np.asarray(Q, dtype=np.float64))
    T, K = Q.shape
    if H.shape != (K, K):
        raise ShapeError(f"H: expected shape ({K}, {K}), got {H.shape}")
    lo, hi = _bounds(lower, upper, K, sum_to)
    X = np.empty((T, K))
    if T == 0 or K == 0:
        return X
    with _one_blas_thread(T):
        use = (T * K >= _KERNEL_MIN_WORK) if compiled is None else bool(compiled)
        X, finish = _box_qp(H, Q, lo, hi, sum_to, max_iter, chunk, use and sum_to is None)
    if finish:
        log.debug("box_qp: %d of %d frames finished by the per-frame active-set method", len(finish), T)
    for t in finish:
        X[t] = _active_set_one(H, Q[t], lo, hi, sum_to)
    return np.clip(X, lo, hi)


_PREFETCH: dict[bool, threading.Thread] = {}


def prefetch_kernel(work: int, *, weighted: bool) -> bool:
    """Start loading the compiled kernel in a background thread if a solve of size *work* will use it.

    Loading numba and the kernel's cached code takes about half a second of
    mostly Python work; started before a long take is read (decompression
    releases the GIL) the two overlap. The kernel is chosen by the solve's
    size alone (``T·K`` against :data:`_KERNEL_MIN_WORK_WEIGHTED` with
    confidences, :data:`_KERNEL_MIN_WORK` without), so this only moves the
    load earlier and never changes a result; a prefetch the solve turns out
    not to need is wasted work in the background.

    Parameters
    ----------
    work : int
        ``T·K`` of the coming solve (frames times keys).
    weighted : bool
        Whether the frames will carry confidences (:func:`box_qp_weighted`).

    Returns
    -------
    bool
        Whether a load was started (or already had been).
    """
    if work < (_KERNEL_MIN_WORK_WEIGHTED if weighted else _KERNEL_MIN_WORK):
        return False
    if weighted not in _PREFETCH:
        def load():
            try:
                from ._qp_kernel import warm_up

                warm_up(weighted)
            except Exception as exc:  # pragma: no cover - the solve itself reports a broken kernel
                log.debug("kernel prefetch failed: %s", exc)

        _PREFETCH[weighted] = thread = threading.Thread(target=load, name="retarget-kernel-load", daemon=True)
        thread.start()
    return True


def _await_kernel(weighted: bool) -> None:
    """Wait for a background load of the kernel (:func:`prefetch_kernel`), if one was started."""
    thread = _PREFETCH.get(weighted)
    if thread is not None:
        thread.join()


def _box_qp(H, Q, lo, hi, sum_to, max_iter, chunk, compiled):
    """The iterations of :func:`box_qp`; returns (X, frames left for the per-frame method)."""
    T, K = Q.shape
    X = np.empty((T, K))
    hscale = max(float(np.abs(np.diag(H)).max()), 1e-300)
    Hd = H + 1e-14 * hscale * np.eye(K)
    X0 = _equality_ls(Hd, Q, sum_to)
    Hinv = None
    # (for a handful of frames the Schur start does not repay the inverse)
    if sum_to is None and T >= 64 and np.linalg.cond(Hd) < _SCHUR_MAX_COND:
        Hinv = np.linalg.inv(Hd)
        Hinv = (Hinv + Hinv.T) / 2
    rows = np.arange(T)
    if compiled:
        _await_kernel(False)
        from ._qp_kernel import pdas_frames

        done = np.empty(T, dtype=bool)
        pdas_frames(Hd, Q, lo, hi, X0, hscale, max_iter, X, done, Hinv)
        rows = np.flatnonzero(~done)  # not settled, or a singular reduced system
        if rows.size:
            log.debug("box_qp: %d of %d frames left by the compiled kernel", rows.size, T)
    finish = []
    for c0 in range(0, rows.size, chunk):
        sl = rows[c0:c0 + chunk]
        X[sl], left = _pdas(Hd, Q[sl], lo, hi, sum_to, X0[sl], max_iter, hscale, Hinv)
        finish += list(sl[left])
    return X, finish


def weighted_hessians(keys, confidence) -> np.ndarray:
    """Upper triangles of every frame's Hessian ``H_t = B diag(c_t) Bᵀ`` in one matrix product.

    With ``P[d, (i, j)] = B[i, d]·B[j, d]`` for ``i ≤ j``, the triangles of
    all frames are ``C P``, a (T × D) by (D × K(K+1)/2) product; when the
    coordinates come in pairs of equal weight (x and y of a landmark), the
    pairs' rows of ``P`` are summed first, a (T × D/2) by (D/2 × K(K+1)/2) product.

    Parameters
    ----------
    keys : ndarray, shape (K, D)
    confidence : ndarray, shape (T, D)

    Returns
    -------
    ndarray, shape (T, K(K+1)/2)
        Row ``t``: ``H_t[i, j]`` for ``i ≤ j`` in the order of ``numpy.triu_indices(K)``.
    """
    B = np.asarray(keys, dtype=np.float64)
    C = np.asarray(confidence, dtype=np.float64)
    iu, ju = np.triu_indices(len(B))
    P = (B[iu] * B[ju]).T
    if C.shape[1] % 2 == 0 and np.array_equal(C[:, 0::2], C[:, 1::2]):
        # landmark rows: x and y share their point's confidence, which halves the product
        return C[:, 0::2] @ np.ascontiguousarray(P[0::2] + P[1::2])
    return C @ np.ascontiguousarray(P)


def _pairs(K: int) -> np.ndarray:
    """(K, K) column of ``H[i, j]`` in the upper-triangle rows of :func:`weighted_hessians`."""
    iu, ju = np.triu_indices(K)
    pairs = np.empty((K, K), dtype=np.int64)
    pairs[iu, ju] = pairs[ju, iu] = np.arange(len(iu))
    return pairs


def box_qp_weighted(Htri, Q, *, lower=0.0, upper=np.inf, sum_to=None, max_iter: int = 30,
                    compiled: bool | None = None) -> np.ndarray:
    """:func:`box_qp` with a Hessian per frame: ``min ½ x_tᵀH_t x_t − q_tᵀx_t, l ≤ x_t ≤ u``.

    The per-frame problems of weighted NNLS (Chuang & Bregler's eq. 4 with a
    confidence per coordinate, ``H_t = B C_t Bᵀ``, ``q_t = B C_t S_t``) are
    solved together by the same exact primal–dual active-set iteration and
    certified by their KKT conditions: in numpy on all frames at once (the
    reduced systems gathered from the stack of Hessians), or, for large
    problems without an equality, per frame in the compiled kernel
    (:func:`retarget_cli.methods.decomposition._qp_kernel.pdas_frames_weighted`). Frames left
    unsettled are finished by the per-frame primal active-set method.

    Parameters
    ----------
    Htri : ndarray, shape (T, K(K+1)/2)
        Upper triangles of the Hessians (:func:`weighted_hessians`).
    Q : ndarray, shape (T, K)
    lower, upper, sum_to, max_iter
        As for :func:`box_qp`.
    compiled : bool, optional
        Use the compiled kernel (True) or the numpy iteration (False). By
        default the kernel runs when ``T·K ≥ 5·10⁵`` (about 23,000 frames at
        K = 22): the numpy iteration costs about 25 µs a frame more, the
        kernel about half a second to load once per process. The choice depends
        on the size alone, so outputs stay reproducible.

    Returns
    -------
    ndarray, shape (T, K)
    """
    Q = np.atleast_2d(np.asarray(Q, dtype=np.float64))
    T, K = Q.shape
    Htri = np.asarray(Htri, dtype=np.float64)
    if Htri.shape != (T, K * (K + 1) // 2):
        raise ShapeError(f"Htri: expected shape ({T}, {K * (K + 1) // 2}), got {Htri.shape}")
    lo, hi = _bounds(lower, upper, K, sum_to)
    X = np.empty((T, K))
    if T == 0 or K == 0:
        return X
    pairs = _pairs(K)
    use = (T * K >= _KERNEL_MIN_WORK_WEIGHTED) if compiled is None else bool(compiled)
    rows = np.arange(T)
    with _one_blas_thread(T):
        if use and sum_to is None:
            _await_kernel(True)
            from ._qp_kernel import pdas_frames_weighted

            done = np.empty(T, dtype=bool)
            pdas_frames_weighted(Htri, Q, lo, hi, max_iter, X, done)
            rows = np.flatnonzero(~done)
            if rows.size:
                log.debug("box_qp_weighted: %d of %d frames left by the compiled kernel", rows.size, T)
        # the stacked reduced systems of a chunk take about 2**25 bytes
        chunk = max(16, 2**22 // (4 * K * K))
        finish = []
        for c0 in range(0, rows.size, chunk):
            sl = rows[c0:c0 + chunk]
            H = Htri[sl][:, pairs]
            hscale = np.maximum(np.abs(np.diagonal(H, axis1=1, axis2=2)).max(1), 1e-300)
            Hd = H + (1e-14 * hscale)[:, None, None] * np.eye(K)
            X0 = _equality_ls_stacked(Hd, Q[sl], sum_to)
            X[sl], left = _pdas(Hd, Q[sl], lo, hi, sum_to, X0, max_iter, hscale)
            finish += [(t, H[i]) for t, i in zip(sl[left], left)]
    if finish:
        log.debug("box_qp_weighted: %d of %d frames finished by the per-frame active-set method", len(finish), T)
    for t, H in finish:
        X[t] = _active_set_one(H, Q[t], lo, hi, sum_to)
    return np.clip(X, lo, hi)


def _equality_ls_stacked(H, Q, eq):
    """:func:`_equality_ls` for a Hessian per frame, H (n, K, K) and Q (n, K): a batched solve.

    Falls back to the per-frame pseudo-inverse when a system is singular.
    """
    n, K = Q.shape
    if eq is None:
        M, R = H, Q
    else:
        M = np.zeros((n, K + 1, K + 1))
        M[:, :K, :K], M[:, :K, K], M[:, K, :K] = H, 1.0, 1.0
        R = np.hstack([Q, np.full((n, 1), eq)])
    try:
        X = np.linalg.solve(M, R[..., None])[..., 0]
    except np.linalg.LinAlgError:
        X = np.stack([_pinv_sym(M[t]) @ R[t] for t in range(n)])
    if not np.isfinite(X).all():
        bad = ~np.isfinite(X).all(1)
        X[bad] = np.stack([_pinv_sym(M[t]) @ R[t] for t in np.flatnonzero(bad)])
    return X[:, :K]


def _solve_weighted(S, B, C, *, solver, eq, lam, upper):
    """:func:`_solve` with a confidence row per frame: every frame's Hessian at once (no per-frame calls)."""
    T, K = len(S), len(B)
    if solver in ("ls", "ridge", "ridge-clipped"):
        Q = (S * C) @ B.T
        X = np.empty((T, K))
        step = max(1, 2**22 // (K * K))
        for c0 in range(0, T, step):
            sl = slice(c0, c0 + step)
            H = weighted_hessians(B, C[sl])[:, _pairs(K)]
            if solver != "ls":
                H = H + lam * np.eye(K)
            X[sl] = _equality_ls_pinv_stacked(H, Q[sl], eq)
        if solver == "ridge-clipped":
            X = np.clip(X, 0.0, DEFAULT_UPPER if upper is None else upper)
        return X
    hi = DEFAULT_UPPER if (solver == "bounded" and upper is None) else (np.inf if upper is None else upper)
    # the choice of kernel is made on the whole take; the Hessians are formed a chunk at a time
    compiled = T * K >= _KERNEL_MIN_WORK_WEIGHTED
    step = max(256, 2**24 // (K * (K + 1) * 4))
    X = np.empty((T, K))
    chunks = [slice(c0, c0 + step) for c0 in range(0, T, step)]

    def solve(sl):
        with _one_blas_thread(T):
            Htri = weighted_hessians(B, C[sl])
            Q = (S[sl] * C[sl]) @ B.T
        if solver == "sparse":
            Q -= lam / 2
        X[sl] = box_qp_weighted(Htri, Q, lower=0.0, upper=hi, sum_to=eq, compiled=compiled)

    # The chunks are fixed by size and solved independently, so solving them side by side (the
    # kernel and BLAS release the GIL) gives the same result as one after the other.
    workers = min(_SOLVE_THREADS, len(chunks)) if compiled and eq is None else 1
    if workers > 1:
        from concurrent.futures import ThreadPoolExecutor

        # BLAS limited once here: nested limits entered and left by the workers would race
        with small_blas(), ThreadPoolExecutor(max_workers=workers, thread_name_prefix="retarget-qp") as pool:
            list(pool.map(solve, chunks))
    else:
        for sl in chunks:
            solve(sl)
    return X


#: Threads :func:`_solve_weighted` solves chunks of a long take on (with the compiled kernel).
_SOLVE_THREADS = min(2, os.cpu_count() or 1)


def _equality_ls_pinv_stacked(H, Q, eq):
    """:func:`_equality_ls` frame by frame for H (n, K, K): the minimum-norm solution, batched eigendecompositions."""
    n, K = Q.shape
    if eq is None:
        M, R = H, Q
    else:
        M = np.zeros((n, K + 1, K + 1))
        M[:, :K, :K], M[:, :K, K], M[:, K, :K] = H, 1.0, 1.0
        R = np.hstack([Q, np.full((n, 1), eq)])
    lam, V = np.linalg.eigh(M)
    cut = np.maximum(np.abs(lam).max(1, keepdims=True), 1e-300) * M.shape[1] * _EPS * 4
    inv = np.where(np.abs(lam) > cut, 1.0 / np.where(lam == 0, 1.0, lam), 0.0)
    Y = np.einsum("nkj,nk->nj", V, R) * inv
    return np.einsum("nij,nj->ni", V, Y)[:, :K]


def _one_blas_thread(n_rows: int):
    """Limit BLAS to one thread for large batches: the many small products run faster unthreaded."""
    return contextlib.nullcontext() if n_rows < 512 else small_blas()


_CONTROLLER = None


@contextlib.contextmanager
def small_blas():
    """Run BLAS single-threaded: for many small products and solves threads only add overhead.

    Measured (``bench/edit.py``, 2 busy cores): bounded solves on a
    100-slider rig took 2-3x longer with OpenBLAS's default threads. The
    controller is created once: inspecting the loaded libraries costs about
    half a millisecond.
    """
    global _CONTROLLER
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:  # pragma: no cover - threadpoolctl ships with scikit-learn
        yield
        return
    if _CONTROLLER is None:
        _CONTROLLER = ThreadpoolController()
    with _CONTROLLER.limit(limits=1, user_api="blas"):
        yield


def _pdas(H, Q, lo, hi, eq, X0, max_iter, hscale, Hinv=None):
    """Primal–dual active-set iterations for the frames *Q* (n, K); returns (X, unsettled rows).

    With *Hinv* (``H⁻¹``, given when *H* is well conditioned and there is no
    equality), a frame whose bound set ``Z`` is smaller than its free set is
    solved from the unconstrained solution *X0* through the Schur complement
    of ``Z``: ``x = x0 + H⁻¹_{:,Z} (H⁻¹_{ZZ})⁻¹ (x_B − x0)_Z``, a system of
    size ``|Z|`` rather than ``|F|`` (the same point: the minimiser with
    ``x_Z = x_B``), during the first ``_SCHUR_ITERATIONS`` iterations. Those
    points only propose active sets; they are less accurate, so a frame is
    certified only from a direct solve.
    """
    n, K = Q.shape
    stacked = H.ndim == 3  # a Hessian per frame (H[t] for Q[t]), hscale per frame
    hs = np.broadcast_to(np.asarray(hscale, dtype=np.float64), (n,))[:, None]
    X = np.empty((n, K))
    status = np.zeros((n, K), dtype=np.int8)  # -1 at lower bound, +1 at upper, 0 free
    status[X0 < lo] = -1
    status[X0 > hi] = 1
    nu = np.zeros(n)
    pending = np.arange(n)
    bound_val = np.where(np.isfinite(hi), hi, 0.0)
    zero_lo = not np.any(lo)
    upper = bool(np.isfinite(hi).any())
    qscale = np.abs(Q).max(1, keepdims=True)
    best = np.full(n, K + 2)  # fewest infeasible variables seen, per frame
    tries = np.full(n, 3)  # full exchanges left without improvement
    for it in range(max_iter):
        st = status[pending]
        free = st == 0
        if upper:
            xB = np.where(st == -1, lo, np.where(st == 1, bound_val, 0.0))
        else:
            xB = np.zeros(st.shape) if zero_lo else np.where(st == -1, lo, 0.0)
        m = free.sum(1)
        Xp = np.empty((len(pending), K))
        nup = np.zeros(len(pending))
        # each frame takes the smaller system: its bound set through H⁻¹, or its free set
        small_z = (K - m < m) if Hinv is not None and it < _SCHUR_ITERATIONS else np.zeros(len(pending), dtype=bool)
        if small_z.any():
            i = np.flatnonzero(small_z)
            bound, x0 = ~free[i], X0[pending[i]]
            Y, _ = _solve_free(Hinv, np.where(bound, xB[i] - x0, 0.0), bound, K - m[i], np.zeros((len(i), K)), None)
            Xz = x0 + Y @ Hinv
            Xz[bound] = xB[i][bound]
            Xp[i] = Xz
        if not small_z.all():
            i = np.flatnonzero(~small_z) if small_z.any() else slice(None)
            R = Q[pending[i]]
            Hi = H[pending[i]] if stacked else H
            if upper or not zero_lo:
                R = R - (np.einsum("tk,tkl->tl", xB[i], Hi) if stacked else xB[i] @ H)  # for every coordinate
            Xp[i], nup[i] = _solve_free(Hi, R, free[i], m[i], xB[i], eq)
        X[pending] = Xp
        nu[pending] = nup
        HX = np.einsum("tk,tkl->tl", Xp, H[pending]) if stacked else Xp @ H
        G = HX - Q[pending] + nup[:, None]
        xs = 1.0 + np.abs(Xp).max(1, keepdims=True)
        tolx = 1e-10 * xs
        tolg = 1e-11 * (qscale[pending] + hs[pending] * xs)
        # a Schur point is accurate to about cond(H)·eps only: there, values
        # within 1e-8 of a bound are taken to be at it (a wrong guess is undone
        # by the multiplier check of the next, direct, iteration)
        tolf = np.where(small_z[:, None], -1e-8 * xs, tolx) if small_z.any() else tolx
        below = free & (Xp < lo - tolf)
        wrong = (st == -1) & (G < -tolg)
        new = st.copy()
        new[below] = -1
        if upper:
            above = free & (Xp > hi + tolf)
            wrong |= (st == 1) & (G > tolg)
            new[above] = 1
            bad = below | above | wrong
        else:
            bad = below | wrong
        new[wrong] = 0
        if eq is not None:
            nofree = np.flatnonzero(m == 0)
            if nofree.size:
                # The sum cannot move: free the variable whose multiplier is most negative.
                off = np.abs(xB[nofree].sum(1) - eq) > 1e-10
                bad[nofree[off]] = True
                j = np.argmin(np.where(st[nofree] == -1, G[nofree], -G[nofree]), axis=1)
                new[nofree[off], j[off]] = 0
        # Safeguard against cycling (the backup rule of Júdice & Pires 1994, as in
        # Kim & Park's block principal pivoting): when a frame's number of
        # infeasible variables has not improved for 3 iterations, exchange
        # only its last infeasible variable until it improves.
        ninf = bad.sum(1)
        if small_z.any():  # a Schur point is less accurate: it never certifies a frame
            ninf = np.where(small_z, np.maximum(ninf, 1), ninf)
        improved = ninf < best[pending]
        best[pending[improved]] = ninf[improved]
        tries[pending[improved]] = 3
        spend = ~improved & (tries[pending] > 0)
        tries[pending[spend]] -= 1
        backup = np.flatnonzero(~improved & ~spend & (ninf > 0))
        if backup.size:
            j = K - 1 - np.argmax(bad[backup, ::-1], axis=1)
            keep = new[backup, j]
            new[backup] = st[backup]
            new[backup, j] = keep
        ok = ninf == 0
        status[pending] = new
        pending = pending[~ok]
        if pending.size == 0:
            break
    return X, pending


#: Without ``compiled``, :func:`box_qp` uses the compiled per-frame kernel
#: (:mod:`retarget_cli.methods.decomposition._qp_kernel`) from this ``T·K`` on (measured: numba's
#: import and cache load take about a second, the numpy iteration about 10 µs
#: per frame at K = 22); the numpy iteration handles the rest, equalities and
#: any frame the kernel leaves.
_KERNEL_MIN_WORK = 2_000_000
#: ... and :func:`box_qp_weighted` from this ``T·K`` on (its numpy iteration
#: is slower: no shared Hessian to invert, every reduced system gathered from its own).
_KERNEL_MIN_WORK_WEIGHTED = 500_000

#: :func:`_pdas` starts from the Schur complement of the bound set when the
#: Hessian's condition number is below this (the inverse is then accurate).
_SCHUR_MAX_COND = 1e9
#: ... during its first iterations only: the Schur form's gradient is less
#: accurate, so frames with nearly degenerate multipliers are settled by direct solves.
_SCHUR_ITERATIONS = 2

#: Buckets with at least this many frames are solved by the vectorised Cholesky
#: of :func:`_cholesky_solve_stacked`; smaller ones by LAPACK one matrix at a time.
_VECTOR_MIN = 48


def _solve_free(H, R, free, m, xB, eq):
    """Solve every frame's reduced system on its free set.

    For each row ``t``: ``H_FF x_F = r_F`` (with ``1ᵀx = eq`` through a
    multiplier ``ν``: ``H_FF x_F + ν1 = r_F``) where ``F`` is the free set
    ``free[t]``; bound variables keep their value from *xB*.

    Frames are bucketed by the size of their free set. Sizes with few frames
    are merged into the next larger bucket and padded with identity rows, so
    that each bucket is one vectorised solve (:func:`_cholesky_solve_stacked`).

    Parameters
    ----------
    H : ndarray, shape (K, K), or (n, K, K) for a Hessian per frame
    R : ndarray, shape (n, K)
        Right-hand sides (already corrected for the bound variables).
    free : ndarray of bool, shape (n, K)
    m : ndarray of int, shape (n,)
        ``free.sum(1)``.
    xB : ndarray, shape (n, K)
        Values of the bound variables (0 at free ones).
    eq : float or None

    Returns
    -------
    X : ndarray, shape (n, K)
    nu : ndarray, shape (n,)
    """
    n, K = R.shape
    nu = np.zeros(n)
    counts = np.bincount(m, minlength=K + 1)
    perm = np.argsort(m, kind="stable")
    top = int(m.max(initial=0))
    groups, start, acc = [], 0, 0
    for size in range(top + 1):
        acc += int(counts[size])
        if acc and (acc >= _VECTOR_MIN or size == top):
            groups.append((start, start + acc, size))
            start, acc = start + acc, 0
    W = K + top  # variables plus the dummy identity variables that pad a bucket
    if H.ndim == 3:  # a Hessian per frame: frame t's entries start at base[t]
        Hp = np.zeros((n, W, W))
        Hp[:, :K, :K] = H
        Hp[:, K:, K:] = np.eye(top)
        base = np.arange(n, dtype=np.intp) * (W * W)
    else:
        Hp = np.zeros((W, W))
        Hp[:K, :K] = H
        Hp[K:, K:] = np.eye(top)
        base = None
    Hflat = Hp.ravel()
    Rp = np.zeros((n, W))
    Rp[:, :K] = R
    Rflat = Rp.ravel()
    Xp = np.zeros((n, W))
    Xp[:, :K] = xB
    Xflat = Xp.ravel()
    # free variables of the frames in bucket order, and each one's position in its reduced system
    mp = m[perm]
    ri_all, ci_all = np.nonzero(free[perm])
    first = np.cumsum(mp) - mp
    pos_all = (np.arange(len(ci_all)) - np.repeat(first, mp)).astype(np.intp)
    ci_all = ci_all.astype(np.int32)
    for r0, r1, size in groups:
        if size == 0:
            continue
        rows = perm[r0:r1]
        count = r1 - r0
        mr = mp[r0:r1]
        seg = slice(first[r0], first[r1 - 1] + mr[-1])
        ri, pos = ri_all[seg] - r0, pos_all[seg]
        # Ft[a, t]: the variable at position a of frame t's system; positions
        # a >= m_t hold the dummies K + a - m_t
        Ft = (K + np.arange(size, dtype=np.int32)[:, None] - mr[None, :].astype(np.int32))
        Ft[pos, ri] = ci_all[seg]
        flat_rows = (rows * W)[None, :]
        ok = np.zeros(count, dtype=bool)
        e = None if eq is None else eq - xB[rows].sum(1)
        if count >= _VECTOR_MIN:
            tri_i, tri_j = _tril(size)
            A = np.empty((size + (1 if eq is None else 2), size, count))
            # lower triangles only (all the factorisation reads); mode="clip" avoids
            # numpy's slow bounds-checked path, the indices are valid by construction
            idx = Ft[tri_i] if base is None else Ft[tri_i] + base[rows][None, :] // W
            idx *= W
            idx += Ft[tri_j]
            A[tri_i, tri_j] = np.take(Hflat, idx, mode="clip")
            A[size] = np.take(Rflat, flat_rows + Ft, mode="clip")
            if eq is not None:
                A[size + 1] = np.arange(size)[:, None] < mr[None, :]  # dummies do not count towards the sum
            x, v, ok = _cholesky_solve_stacked(A, e)
            np.put(Xflat, flat_rows + Ft, x, mode="clip")  # dummies land in the padding columns
            if eq is not None:
                nu[rows] = v
        if not ok.all():
            # small buckets, or systems the Cholesky found numerically singular: LAPACK's LU
            sub = np.flatnonzero(~ok)
            Fs = Ft[:, sub].T
            idx = Fs[:, :, None].astype(np.intp) * W + Fs[:, None, :]
            if base is not None:
                idx += base[rows[sub]][:, None, None]
            A = np.take(Hflat, idx, mode="clip")
            bs = np.take(Rflat, flat_rows[:, sub].T + Fs, mode="clip")
            if eq is not None:
                ones = (np.arange(size)[None, :] < mr[sub, None]).astype(float)
                A = np.concatenate([np.concatenate([A, ones[:, :, None]], 2),
                                    np.concatenate([ones[:, None, :], np.zeros((len(sub), 1, 1))], 2)], 1)
                bs = np.concatenate([bs, e[sub, None]], 1)
            out = np.linalg.solve(A, bs[..., None])[..., 0]
            np.put(Xflat, flat_rows[:, sub].T + Fs, out[:, :size], mode="clip")
            if eq is not None:
                nu[rows[sub]] = out[:, size]
    return Xp[:, :K], nu


_TRIL = {}


def _tril(size: int):
    """Cached ``numpy.tril_indices(size)``."""
    if size not in _TRIL:
        _TRIL[size] = np.tril_indices(size)
    return _TRIL[size]


def _cholesky_solve_stacked(A, eq=None):
    """Solve many small symmetric positive-definite systems, vectorised over the stack.

    The stack is the last axis so that every step of the Cholesky
    factorisation ``H = LLᵀ`` and of the triangular solves is one numpy
    operation over all systems; for the small systems of the active-set
    iteration this is several times faster than one LAPACK call per matrix.
    The right-hand side is an extra row of *A*, so the factorisation also
    performs the forward substitution ``y_b = L⁻¹b``. With *eq*, a second
    extra row ``e`` adds the constraint ``eᵀx = eq`` through a multiplier
    ``ν``: ``x = H⁻¹(b − νe)`` with ``ν = (eᵀH⁻¹b − eq) / eᵀH⁻¹e
    = (y_e·y_b − eq) / (y_e·y_e)``, so one back substitution suffices.

    Parameters
    ----------
    A : ndarray, shape (m + 1, m, n), or (m + 2, m, n) with *eq*
        Rows ``:m`` hold the matrices ``H`` (only the lower triangles are
        read), row ``m`` the right-hand sides ``b`` and row ``m + 1`` the
        constraint vectors ``e``. Overwritten.
    eq : ndarray, shape (n,), optional

    Returns
    -------
    x : ndarray, shape (m, n)
    nu : ndarray, shape (n,), or None without *eq*
    ok : ndarray of bool, shape (n,)
        False where a pivot was not positive (a numerically singular
        system); ``x`` is meaningless there.
    """
    m, n = A.shape[1], A.shape[2]
    diag = np.empty((m, n))
    ok = np.ones(n, dtype=bool)
    for j in range(m):
        if j:
            A[j:, j] -= np.einsum("ikn,kn->in", A[j:, :j], A[j, :j])
        d2 = A[j, j]
        bad = ~(d2 > 0)
        if bad.any():
            ok &= ~bad
            d2 = np.where(bad, 1.0, d2)
        diag[j] = np.sqrt(d2)
        A[j + 1:, j] /= diag[j]

    def back(y):
        x = np.empty((m, n))
        for i in range(m - 1, -1, -1):
            x[i] = (y[i] - np.einsum("kn,kn->n", A[i + 1:m, i], x[i + 1:])) / diag[i]
        return x

    if eq is None:
        return back(A[m]), None, ok
    # with y_b = L⁻¹b and y_e = L⁻¹e: eᵀH⁻¹b = y_e·y_b and eᵀH⁻¹e = y_e·y_e
    yb, ye = A[m], A[m + 1]
    nu = (np.einsum("kn,kn->n", ye, yb) - eq) / np.einsum("kn,kn->n", ye, ye)
    return back(yb - nu * ye), nu, ok


def _active_set_one(H, q, lo, hi, eq=None, x0=None, max_iter=None) -> np.ndarray:
    """Exact primal active-set method for one box-constrained QP (Nocedal & Wright, Alg. 16.3).

    ``min ½xᵀHx − qᵀx, lo ≤ x ≤ hi`` (and ``1ᵀx = eq``), starting from the
    feasible *x0* (default: the lower bounds, or a uniform split of *eq*).
    Zero-curvature descent directions of a singular *H* are followed to the
    bound that blocks them.
    """
    K = len(q)
    if x0 is None:
        if eq is None:
            x = np.clip(np.zeros(K), lo, hi)
        else:
            x = lo.copy()
            need = eq - x.sum()
            for i in range(K):  # fill greedily up to each upper bound
                add = min(need, hi[i] - x[i])
                x[i] += add
                need -= add
    else:
        x = np.clip(np.asarray(x0, dtype=np.float64), lo, hi)
    W = np.zeros(K, dtype=np.int8)  # -1 at lower, +1 at upper, 0 free
    W[x <= lo] = -1
    W[(x >= hi) & (W == 0)] = 1
    hscale = max(float(np.abs(np.diag(H)).max()), 1e-300)
    at_min = False  # x minimises the objective on the current face (after a full step)
    for _ in range(max_iter or 50 * K + 50):
        g = H @ x - q
        F = np.flatnonzero(W == 0)
        n = len(F)
        gtol = 1e-10 * (np.abs(q).max() + hscale * (1 + np.abs(x).max()))
        if eq is None:
            M, rhs = H[np.ix_(F, F)], -g[F]
        else:
            M = np.zeros((n + 1, n + 1))
            M[:n, :n], M[:n, n], M[n, :n] = H[np.ix_(F, F)], 1.0, 1.0
            rhs = np.concatenate([-g[F], [0.0]])
        if n == 0 and eq is None:
            sol, r = np.zeros(0), np.zeros(0)
        else:
            sol = _pinv_sym(M) @ rhs
            r = rhs - M @ sol
        unbounded_dir = r.size and np.linalg.norm(r) > gtol
        p = np.zeros(K)
        if unbounded_dir:
            p[F] = r[:n]  # zero curvature, strictly descending
        else:
            p[F] = sol[:n]
        if not unbounded_dir and (at_min or np.abs(p).max(initial=0.0) <= 1e-12 * (1 + np.abs(x).max())):
            at_min = False
            nu = sol[n] if eq is not None and n > 0 else 0.0
            if eq is not None and n == 0:
                nu = 0.0
            mu = g + nu
            viol = np.where(W == -1, -mu, np.where(W == 1, mu, -np.inf))
            j = int(np.argmax(viol))
            if viol[j] <= gtol:
                return x
            W[j] = 0
            continue
        step, block = (np.inf if unbounded_dir else 1.0), -1
        with np.errstate(divide="ignore", invalid="ignore"):
            lim = np.where(p < 0, (lo - x) / p, np.where(p > 0, (hi - x) / p, np.inf))
        lim[W != 0] = np.inf
        j = int(np.argmin(lim))
        if lim[j] < step:
            step, block = max(lim[j], 0.0), j
        if not np.isfinite(step):
            raise ParameterError("the quadratic programme is unbounded below (keys without curvature and no bound)")
        x = x + step * p
        at_min = block < 0
        if block >= 0:
            W[block] = -1 if p[block] < 0 else 1
            x[block] = lo[block] if p[block] < 0 else hi[block]
    log.warning("active-set QP stopped after %d iterations; the weights of this frame may be inexact", max_iter or 50 * K + 50)
    return x


def _temporal_causal(S, B, C, *, lam, upper, eq, shape_space=False):
    """Frame-by-frame ``min ‖Bᵀw − S_t‖²_C + λ‖w − w_{t−1}‖²_M`` with ``0 ≤ w ≤ upper`` (Lewis & Anjyo eq. 2).

    ``M = BBᵀ`` in shape space (the change of the reconstructed shape),
    ``M = I`` in weight space. The first frame has no predecessor and is
    solved without the penalty. Each frame's active set warm-starts the next.
    """
    T, K = len(S), len(B)
    M = B @ B.T if shape_space else np.eye(K)
    lo = np.zeros(K)
    hi = np.full(K, np.inf if upper is None else upper)
    W = np.empty((T, K))
    H0 = B @ B.T
    prev = None
    for t in range(T):
        if C is None:
            H, q = H0, B @ S[t]
        else:
            Bc = B * C[t]
            H, q = Bc @ B.T, Bc @ S[t]
        if prev is None:
            W[t] = box_qp(H, q[None], lower=lo, upper=hi, sum_to=eq)[0]
        else:
            W[t] = _active_set_one(H + lam * M, q + lam * (M @ prev), lo, hi, eq, x0=prev)
        prev = W[t]
    return W


def _sequential(S, B, C, *, upper):
    """Seol et al. 2011 (Racković et al. 2023, eq. 7) for every frame at once.

    Keys are visited in order of decreasing mean offset (mean per-coordinate
    magnitude of the key vector); each weight minimises ``‖w_i b_i − r‖²``
    over the current residual ``r``, clipped to ``[0, upper]``, and its
    contribution is then removed from ``r``.
    """
    T, K = len(S), len(B)
    hi = np.inf if upper is None else upper
    order = np.argsort(-np.abs(B).mean(1), kind="stable")
    R = S.copy()
    W = np.zeros((T, K))
    for i in order:
        b = B[i]
        if C is None:
            num, den = R @ b, np.full(T, b @ b)
        else:
            num, den = (R * C) @ b, C @ (b * b)
        w = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
        w = np.clip(w, 0.0, hi)
        W[:, i] = w
        R -= w[:, None] * b
    return W


def temporal_events(frames, keys, *, lam: float, upper: float | None = None, confidence=None,
                    shape_space: bool = True, robust: float = 0.0, passes: int = 3, point_dim: int = 2,
                    point_factor: float = 5.0) -> np.ndarray:
    """:func:`temporal_whole` that lets go of the smoothness penalty at fast events (blinks).

    After a smooth solve ``W``, each frame's excess residual over the
    unsmoothed (per-frame) solution ``W⁰``,

    .. math::

        e_t = \\frac{\\|S_t - B^T w_t\\|^2_{C_t} - \\|S_t - B^T w^0_t\\|^2_{C_t}}
                   {\\operatorname{median}_t \\|S_t - B^T w^0_t\\|^2_{C_t}},

    is averaged over frames ``t−1, t, t+1``; where the average exceeds
    *robust* the penalty cannot be the right model (the face moved faster
    than the smoothness allows: a blink, a plosive), so the weights ``ρ`` of
    the second-difference terms touching those frames (dilated by one frame)
    are set to 0 and the problem is solved again, at most *passes* times.
    Elsewhere the solution is smoothed as before. ``robust = 0`` is plain
    :func:`temporal_whole`.

    A blink moves a few points of a region: its excess, spread over all of
    the region's coordinates, can stay under *robust* while the character's
    eyes stay 10 % open. So the same test also runs per point (*point_dim*
    coordinates each, normalised by that point's own median residual, with
    a floor of a tenth of the region's median per point), and a frame whose
    largest windowed point excess exceeds ``point_factor · robust`` is an
    event too.

    Parameters
    ----------
    frames : ndarray, shape (T, D)
    keys : ndarray, shape (K, D)
    lam, upper, confidence, shape_space
        As :func:`temporal_whole`.
    robust : float
        Threshold on the windowed excess residual (0: off).
    passes : int
    point_dim : int
        Coordinates per point (2: image landmarks); a *D* it does not divide is tested per coordinate.
    point_factor : float
        The per-point threshold, in units of *robust* (``inf``: the region test only).

    Returns
    -------
    ndarray, shape (T, K)
    """
    S = check_array(frames, "frames", ndim=2)
    B = check_array(keys, "keys", ndim=2)
    W = temporal_whole(S, B, lam=lam, upper=upper, confidence=confidence, shape_space=shape_space)
    T = len(S)
    if not robust > 0 or T < 3 or lam == 0:
        return W
    C = np.ones_like(S) if confidence is None else np.asarray(confidence, dtype=np.float64)
    hi = np.inf if upper is None else upper
    W0 = np.concatenate([box_qp((B * C[t]) @ B.T, ((S[t] * C[t]) @ B.T)[None], lower=0.0, upper=hi)
                         for t in range(T)]) if confidence is not None else box_qp(B @ B.T, S @ B.T, upper=hi)
    pd = int(point_dim) if point_dim >= 1 and S.shape[1] % int(point_dim) == 0 else 1

    def per_point(W):
        return (C * (S - W @ B) ** 2).reshape(T, -1, pd).sum(axis=2)

    p0 = per_point(W0)
    r0 = p0.sum(axis=1)
    scale = max(float(np.median(r0)), 1e-12 * float(np.mean(np.sum(C * S**2, axis=1))), 1e-300)
    p_scale = np.maximum(np.median(p0, axis=0), 0.1 * scale / p0.shape[1])
    rho = np.ones(T - 2)
    for it in range(max(int(passes), 1)):
        p = per_point(W)
        win = _window3(np.column_stack([(p.sum(axis=1) - r0) / scale, (p - p0) / p_scale]))
        event = (win[:, 0] > robust) | (win[:, 1:].max(axis=1) > point_factor * robust)
        if not event.any():
            break
        event[1:] |= event[:-1].copy()
        event[:-1] |= event[1:].copy()
        # term t (frames t, t+1, t+2) touches an event frame
        touch = event[:-2] | event[1:-1] | event[2:]
        if not np.any(touch & (rho > 0)):
            break
        rho[touch] = 0.0
        log.debug("temporal: pass %d, %d event frames, %d terms released", it + 1, int(event.sum()), int(touch.sum()))
        W = temporal_whole(S, B, lam=lam, upper=upper, confidence=confidence, shape_space=shape_space,
                           row_weights=rho)
    return W


def _window3(e: np.ndarray) -> np.ndarray:
    """Mean of each row of *e* (T, n) with its neighbours ``t−1, t+1`` (two rows at the ends)."""
    win = e.copy()
    win[1:] += e[:-1]
    win[:-1] += e[1:]
    return win / np.convolve(np.ones(len(e)), np.ones(3), mode="same")[:, None]


def _second_difference(T: int):
    """Sparse (T−2, T) second-difference operator."""
    from scipy import sparse

    if T < 3:
        return sparse.csr_matrix((0, T))
    return sparse.diags([np.ones(T - 2), -2 * np.ones(T - 2), np.ones(T - 2)], [0, 1, 2], shape=(T - 2, T), format="csr")


def temporal_whole(frames, keys, *, lam: float, upper: float | None = None, confidence=None,
                   max_iter: int = 60, shape_space: bool = False, row_weights=None) -> np.ndarray:
    """Whole-take smooth weights: one sparse banded bound-constrained problem.

    .. math::

        \\min_{W} \\sum_t \\| S_t - B^T w_t \\|_{C_t}^2
        + \\lambda \\sum_{t=1}^{T-2} \\| w_{t-1} - 2 w_t + w_{t+1} \\|_M^2
        \\quad \\text{s.t. } 0 \\le w_{t,i} \\le u

    with ``M = I`` (weight space) or, with *shape_space*, ``M = BBᵀ``: the
    penalty is then ``‖D₂ W B‖²``, the squared acceleration of the
    reconstructed landmarks, so many small weight changes that move the face
    cost as much as the motion they cause, and keys that barely move it cost
    little. The Hessian ``blockdiag(B C_t Bᵀ) + λ (D₂ᵀD₂ ⊗ M)`` of all ``T·K``
    unknowns is banded (bandwidth ``3K``). It is solved exactly by a
    primal–dual active-set iteration (Hintermüller, Ito & Kunisch 2002) started
    from the per-frame NNLS solution; each iteration is one sparse LU solve
    (SuperLU, :func:`scipy.sparse.linalg.splu`) of the Hessian reduced to the
    free variables, and the result satisfies the KKT conditions. If the
    iteration does not settle, :func:`scipy.optimize.lsq_linear` (trust-region
    reflective on the equivalent sparse least-squares problem) finishes it.

    Parameters
    ----------
    frames : ndarray, shape (T, D)
    keys : ndarray, shape (K, D)
    lam : float
        Absolute penalty weight λ >= 0.
    upper : float, optional
    confidence : ndarray, shape (T, D), optional
    max_iter : int
    shape_space : bool
        ``M = BBᵀ`` instead of ``I``.
    row_weights : ndarray, shape (T−2,), optional
        Weight ``ρ_t ≥ 0`` of each second-difference term (default 1): the
        penalty becomes ``λ Σ_t ρ_t ‖…‖²_M`` (0 lets frames ``t−1 … t+1``
        bend freely; see :func:`temporal_events`).

    Returns
    -------
    ndarray, shape (T, K)
    """
    from scipy import sparse
    from scipy.sparse.linalg import splu

    S = check_array(frames, "frames", ndim=2)
    B = check_array(keys, "keys", ndim=2)
    T, K = len(S), len(B)
    hi_v = np.inf if upper is None else upper
    C_is_none = confidence is None
    if C_is_none:
        Hb = np.broadcast_to(B @ B.T, (T, K, K))
        Q = S @ B.T
    else:
        C = np.asarray(confidence, dtype=np.float64)
        Hb = np.einsum("kd,td,ld->tkl", B, C, B)
        Q = (S * C) @ B.T
    blocks = sparse.bsr_matrix((np.ascontiguousarray(Hb), np.arange(T), np.arange(T + 1)), shape=(T * K, T * K))
    D2 = _second_difference(T)
    if row_weights is not None and D2.shape[0]:
        D2 = sparse.diags(np.sqrt(np.asarray(row_weights, dtype=np.float64))) @ D2
    M = sparse.csr_matrix(B @ B.T) if shape_space else sparse.identity(K, format="csr")
    Hbig = (blocks + lam * sparse.kron(D2.T @ D2, M, format="csr")).tocsc()
    q = Q.ravel()
    # Start: per-frame NNLS, whose active set is usually close.
    if C_is_none:
        x = box_qp(B @ B.T, Q, lower=0.0, upper=hi_v).ravel()
    else:
        x = box_qp_weighted(weighted_hessians(B, C), Q, lower=0.0, upper=hi_v).ravel()
    if lam == 0 or T < 3:
        return x.reshape(T, K)
    n = T * K
    status = np.zeros(n, dtype=np.int8)
    status[x <= 0] = -1
    status[x >= hi_v] = 1
    hscale = max(float(np.abs(Hbig.diagonal()).max()), 1e-300)
    seen = set()
    limit = None  # after a cycle: change at most this many of the worst violators per iteration
    for it in range(4 * max_iter):
        F = np.flatnonzero(status == 0)
        xB = np.where(status == -1, 0.0, np.where(status == 1, hi_v, 0.0))
        x = xB.copy()
        if F.size:
            rhs = q[F] - Hbig[F] @ xB
            HF = Hbig[F][:, F].tocsc()
            try:
                x[F] = splu(HF).solve(rhs)
            except RuntimeError:  # singular reduced Hessian: least-squares solve
                from scipy.sparse.linalg import lsqr

                x[F] = lsqr(HF, rhs, atol=1e-14, btol=1e-14)[0]
        g = Hbig @ x - q
        xs = 1.0 + np.abs(x).max()
        tolx, tolg = 1e-10 * xs, 1e-9 * (np.abs(q).max() + hscale * xs)
        free = status == 0
        below = free & (x < -tolx)
        above = free & (x > hi_v + tolx)
        wrong = ((status == -1) & (g < -tolg)) | ((status == 1) & (g > tolg))
        nbad = int(below.sum() + above.sum() + wrong.sum())
        log.debug("temporal: iteration %d, %d free of %d, %d KKT violations", it + 1, F.size, n, nbad)
        if nbad == 0:
            return np.clip(x, 0.0, hi_v).reshape(T, K)
        if limit is not None and nbad > limit:
            score = np.where(below, -x / xs, 0.0) + np.where(above, (x - hi_v) / xs, 0.0) \
                + np.where(wrong, np.abs(g) / (hscale * xs), 0.0)
            keep = np.zeros(n, dtype=bool)
            keep[np.argsort(-score, kind="stable")[:limit]] = True
            below, above, wrong = below & keep, above & keep, wrong & keep
        status[below] = -1
        status[above] = 1
        status[wrong] = 0
        key = hash(status.tobytes())
        if key in seen:  # cycling: change fewer variables at a time (the KKT check still certifies the end)
            if limit == 1 or it >= max_iter and limit is None:
                break
            limit = max(1, (nbad if limit is None else limit) // 4)
            seen.clear()
        seen.add(key)
    log.warning("temporal: the active-set iteration did not settle after %d iterations; finishing with "
                "scipy.optimize.lsq_linear (weights may be slightly inexact; try a larger decompose.alpha)", it + 1)
    from scipy.optimize import lsq_linear

    if C_is_none:
        rows = sparse.kron(sparse.identity(T), sparse.csr_matrix(B.T))
        b = S.ravel()
    else:
        rw = np.sqrt(C)
        rows = sparse.block_diag([sparse.csr_matrix(B.T * rw[t][:, None]) for t in range(T)])
        b = (S * rw).ravel()
    pen = sparse.kron(D2, sparse.csr_matrix(B.T)) if shape_space else sparse.kron(D2, sparse.identity(K))
    A = sparse.vstack([rows, np.sqrt(lam) * pen]).tocsr()
    b = np.concatenate([b, np.zeros(pen.shape[0])])
    res = lsq_linear(A, b, bounds=(0.0, hi_v), method="trf", lsmr_tol="auto", tol=1e-12, max_iter=200)
    return np.clip(res.x, 0.0, hi_v).reshape(T, K)
