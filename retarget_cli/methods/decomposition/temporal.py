"""Solvers across frames: the temporal, causal and sequential variants of the decomposition.

``temporal-causal`` is Lewis & Anjyo (2010, eq. 2) with the previous frame as ``w_0``; ``temporal``
adds a second-difference roughness penalty over the whole take (one banded problem,
:func:`temporal_whole`), released at fast events (:func:`temporal_events`); ``sequential`` is Seol et
al. (2011) as in Racković et al. (2023, eq. 7).
"""

from __future__ import annotations

import logging

import numpy as np

from ..._validate import check_array
from ...errors import ShapeError
from .boxqp import _active_set_one, box_qp, box_qp_weighted, weighted_hessians

log = logging.getLogger(__name__)


#: Frames of a long take solved together by :func:`temporal_windows` (and the other solvers across frames that
#: cut a take with :func:`take_windows`): a take's memory is then that of one window, whatever its length.
WINDOW = 1024
#: Frames each side of a window solved with it but taken from its neighbours.
MARGIN = 256


def take_windows(T: int, window: int | None = WINDOW, margin: int = MARGIN) -> list:
    """The windows a solver across frames cuts a take of *T* frames into, as ``(a, b, lo, hi)``.

    Rows ``[a, b)`` of the result come from the frames ``[lo, hi)`` solved together; the ``[a, b)`` tile
    ``[0, T)``. A take of at most ``window + margin`` frames (or *window* None) is one window, the whole take.
    A longer one is cut every *window* frames, each window reaching *margin* frames into its neighbours (a
    short tail joins the last window), so that no more than ``window + 2 * margin`` frames are held at once.
    Where the coupling between frames (a second difference, a Kalman smoother's gain) dies out within
    *margin* frames, the result is that of the whole take to rounding.

    Returns
    -------
    list of (int, int, int, int)
    """
    if window is None or T <= window + margin:
        return [(0, T, 0, T)]
    if window < 1 or margin < 0:
        raise ShapeError(f"take windows: expected window >= 1 and margin >= 0, got {window} and {margin}")
    out = []
    for a in range(0, T, window):
        b = min(T, a + window)
        if T - b <= margin:
            b = T
        out.append((a, b, max(0, a - margin), min(T, b + margin)))
        if b == T:
            break
    return out


def temporal_windows(frames, keys, *, confidence=None, window: int | None = WINDOW, margin: int = MARGIN,
                     **kw) -> np.ndarray:
    """:func:`temporal_events` of a long take, window by window (:func:`take_windows`).

    A take of at most ``window + margin`` frames is solved at once, as :func:`temporal_events` does. A longer
    one is solved in windows of *window* frames reaching *margin* frames into their neighbours: its memory stays
    that of one window (the banded Hessian and its LU grow with the frames solved together), the second
    difference's coupling has died out across the margin, and the event test's normalisation (the median
    residual) is the window's own rather than the whole take's.

    Parameters
    ----------
    frames : ndarray, shape (T, D)
    keys : ndarray, shape (K, D)
    confidence : ndarray, shape (T, D), optional
    window, margin : int
    **kw
        The other arguments of :func:`temporal_events`.

    Returns
    -------
    ndarray, shape (T, K)
    """
    S = check_array(frames, "frames", ndim=2)
    B = check_array(keys, "keys", ndim=2)
    wins = take_windows(len(S), window, margin)
    if len(wins) == 1:
        return temporal_events(S, B, confidence=confidence, **kw)
    C = None if confidence is None else np.asarray(confidence, dtype=np.float64)
    W = np.empty((len(S), len(B)))
    for a, b, lo, hi in wins:
        W[a:b] = temporal_events(S[lo:hi], B, confidence=None if C is None else C[lo:hi], **kw)[a - lo:b - lo]
    return W


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


def _per_frame(S, B, C, hi, chunk: int = 1024) -> np.ndarray:
    """Every frame's own weighted box QP (``H_t = B diag(c_t) Bᵀ``, ``q_t = B diag(c_t) s_t``, ``0 ≤ w ≤ hi``),
    solved together by :func:`box_qp_weighted` a chunk of frames at a time, (T, K)."""
    T, K = len(S), len(B)
    iu, ju = np.triu_indices(K)
    W0 = np.empty((T, K))
    for c0 in range(0, T, chunk):
        sl = slice(c0, c0 + chunk)
        H = np.matmul(B[None] * C[sl][:, None, :], B.T)  # (n, K, K), each as (B * c_t) @ Bᵀ
        Q = np.matmul((S[sl] * C[sl])[:, None, :], B.T)[:, 0]
        W0[sl] = box_qp_weighted(H[:, iu, ju], Q, lower=0.0, upper=hi)
    return W0


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
    W0 = _per_frame(S, B, C, hi) if confidence is not None else box_qp(B @ B.T, S @ B.T, upper=hi)
    pd = int(point_dim) if point_dim >= 1 and S.shape[1] % int(point_dim) == 0 else 1

    def per_point(W):
        return (C * (S - W @ B) ** 2).reshape(T, -1, pd).sum(axis=2)

    p0 = per_point(W0)
    floor = 1e-12 * float(np.mean(np.sum(C * S**2, axis=1)))
    rho = np.ones(T - 2)
    for it in range(max(int(passes), 1)):
        touch = event_terms(per_point(W), p0, robust=robust, point_factor=point_factor, floor=floor)
        if not np.any(touch & (rho > 0)):
            break
        rho[touch] = 0.0
        log.debug("temporal: pass %d, %d terms released", it + 1, int(touch.sum()))
        W = temporal_whole(S, B, lam=lam, upper=upper, confidence=confidence, shape_space=shape_space,
                           row_weights=rho)
    return W


def event_terms(p, p0, *, robust: float, point_factor: float = 5.0, floor: float = 0.0, point_floor=None) -> np.ndarray:
    """The second-difference terms a fast event touches (the test of :func:`temporal_events`).

    Parameters
    ----------
    p, p0 : ndarray, shape (T, P)
        Each frame's squared residual per point, of the smooth solution and of the per-frame one.
    robust, point_factor : float
        As :func:`temporal_events`.
    floor : float
        Lower bound of the median per-frame residual used as the unit.
    point_floor : ndarray, shape (P,) or (T, P), optional
        Lower bound of each point's unit (e.g. what the tracker's noise alone leaves), per frame or for all: an
        excess that small is not an event, however closely the per-frame fit followed the noise.

    Returns
    -------
    ndarray of bool, shape (T − 2,)
        Term ``t`` (frames ``t, t+1, t+2``) touches a frame flagged (dilated by one frame).
    """
    r0 = p0.sum(axis=1)
    scale = max(float(np.median(r0)), floor, 1e-300)
    p_scale = np.maximum(np.median(p0, axis=0), 0.1 * scale / p0.shape[1])
    if point_floor is not None:
        p_scale = np.maximum(p_scale, point_floor)
    win = _window3(np.column_stack([(p.sum(axis=1) - r0) / scale, (p - p0) / p_scale]))
    event = (win[:, 0] > robust) | (win[:, 1:].max(axis=1) > point_factor * robust)
    event[1:] |= event[:-1].copy()
    event[:-1] |= event[1:].copy()
    return event[:-2] | event[1:-1] | event[2:]


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


#: :func:`sparse_box_qp` slices its reduced matrices with the compiled kernel from this many nonzeros of H on
#: (smaller systems spare a process numba's start-up; the matrices are the same either way).
_SLICE_KERNEL_MIN_NNZ = 200_000


def sparse_box_qp(H, q, lower, upper, x0, *, max_iter: int = 60):
    """``min ½ xᵀHx − qᵀx`` subject to ``lower ≤ x ≤ upper``, for a large sparse positive definite *H*.

    The primal–dual active-set iteration of Hintermüller, Ito & Kunisch (2002) started from *x0* (whose
    bounds that it touches are the first active set); each iteration is one sparse LU solve
    (:func:`scipy.sparse.linalg.splu`) of *H* reduced to the free variables, and a returned solution
    satisfies the KKT conditions. After a cycle it changes fewer variables at a time.

    Parameters
    ----------
    H : scipy.sparse matrix, shape (n, n)
    q : ndarray, shape (n,)
    lower, upper : ndarray, shape (n,)
        Finite lower bounds below the (possibly infinite) upper ones.
    x0 : ndarray, shape (n,)
    max_iter : int

    Returns
    -------
    x : ndarray, shape (n,)
        Clipped to the bounds.
    settled : bool
        False when the iteration stopped without certifying the KKT conditions (*x* is then the last iterate).
    """
    from scipy.sparse.linalg import splu

    lo, hi_v = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    x = np.clip(np.asarray(x0, dtype=np.float64), lo, hi_v)
    Hbig = H.tocsc()
    n = len(q)
    # a large system's reduced matrices are sliced by the compiled kernel (the same matrix as scipy's slicing,
    # in a tenth of the time); the right-hand side's products then come from the rows of H in CSR
    compiled = Hbig.nnz >= _SLICE_KERNEL_MIN_NNZ
    if compiled:
        from scipy import sparse

        from ._qp_kernel import principal_csc

        Hbig = Hbig.copy() if not Hbig.has_sorted_indices else Hbig
        Hbig.sort_indices()
        Hrows = H.tocsr()
        Hrows = Hrows.copy() if not Hrows.has_sorted_indices else Hrows
        Hrows.sort_indices()
    status = np.zeros(n, dtype=np.int8)
    status[x <= lo] = -1
    status[x >= hi_v] = 1
    hscale = max(float(np.abs(Hbig.diagonal()).max()), 1e-300)
    seen = set()
    limit = None  # after a cycle: change at most this many of the worst violators per iteration
    for it in range(4 * max_iter):
        F = np.flatnonzero(status == 0)
        xB = np.where(status == -1, lo, np.where(status == 1, hi_v, 0.0))
        x = xB.copy()
        if F.size and compiled:
            # bound variables are often all at a zero bound: then the right-hand side is q_F itself
            rhs = q[F] - (Hrows @ xB)[F] if xB.any() else q[F]
            ptr, rows, vals = principal_csc(Hbig.indptr, Hbig.indices, Hbig.data, F, n)
            HF = sparse.csc_matrix((vals, rows, ptr), shape=(F.size, F.size))
        elif F.size:
            HrF = Hbig[F]  # the free rows, taken once (the slicing costs as much as a factorisation)
            rhs = q[F] - HrF @ xB if xB.any() else q[F]
            HF = HrF[:, F].tocsc()
        if F.size:
            try:
                x[F] = splu(HF).solve(rhs)
            except RuntimeError:  # singular reduced Hessian: least-squares solve
                from scipy.sparse.linalg import lsqr

                x[F] = lsqr(HF, rhs, atol=1e-14, btol=1e-14)[0]
        g = Hbig @ x - q
        xs = 1.0 + np.abs(x).max()
        tolx, tolg = 1e-10 * xs, 1e-9 * (np.abs(q).max(initial=0.0) + hscale * xs)
        free = status == 0
        below = free & (x < lo - tolx)
        above = free & (x > hi_v + tolx)
        wrong = ((status == -1) & (g < -tolg)) | ((status == 1) & (g > tolg))
        nbad = int(below.sum() + above.sum() + wrong.sum())
        log.debug("temporal: iteration %d, %d free of %d, %d KKT violations", it + 1, F.size, n, nbad)
        if nbad == 0:
            return np.clip(x, lo, hi_v), True
        if limit is not None and nbad > limit:
            score = np.where(below, (lo - x) / xs, 0.0) + np.where(above, (x - hi_v) / xs, 0.0) \
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
    return np.clip(x, lo, hi_v), False


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
    x, settled = sparse_box_qp(Hbig, q, np.zeros(T * K), np.full(T * K, hi_v), x, max_iter=max_iter)
    if settled:
        return x.reshape(T, K)
    log.warning("temporal: the active-set iteration did not settle after %d iterations; finishing with "
                "scipy.optimize.lsq_linear (weights may be slightly inexact; try a larger decompose.alpha)", 4 * max_iter)
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
