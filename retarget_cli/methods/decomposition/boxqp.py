"""Box-constrained quadratic programmes for every frame at once: the solvers behind :func:`~retarget_cli.methods.decomposition.decompose`.

Chuang & Bregler (2002, eq. 4) solve a non-negative least-squares problem per frame; with bounds
(Racković et al. 2023, eqs. 5–6) and the convex constraint (Lewis et al. 2005, §3) every frame is
``min ½ wᵀHw − q_tᵀw, lo ≤ w ≤ hi`` (optionally ``1ᵀw = 1``) with a Hessian shared by all frames.
:func:`box_qp` solves all frames together by a primal–dual active-set iteration (Hintermüller, Ito &
Kunisch 2002) with reduced systems solved by Cholesky factorisations vectorised across frames (or
per frame in the compiled kernel ``_qp_kernel``); unsettled frames are finished by an exact primal
active-set method (Nocedal & Wright, Algorithm 16.3). :func:`weighted_hessians` and
:func:`box_qp_weighted` do the same with per-frame confidence weights.
"""

from __future__ import annotations

import logging
import os
import threading

import numpy as np

from ..._validate import check_array
from ...errors import ParameterError, ShapeError
from ..blas import one_blas_thread, small_blas

log = logging.getLogger(__name__)


#: Upper bound of ``bounded`` and ``ridge-clipped`` when none is given.
DEFAULT_UPPER = 1.0


_EPS = np.finfo(np.float64).eps


def _bounds(lower, upper, K: int, sum_to=None) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds broadcast to (K,) float64 copies; checked against each other and *sum_to*."""
    lo = np.broadcast_to(np.asarray(lower, dtype=np.float64), (K,)).copy()
    hi = np.broadcast_to(np.asarray(upper, dtype=np.float64), (K,)).copy()
    if np.any(lo > hi):
        raise ParameterError("bounds: lower must not exceed upper")
    if sum_to is not None and not (lo.sum() <= sum_to <= hi.sum()):
        raise ParameterError(f"sum_to: {sum_to} cannot be reached within the bounds")
    return lo, hi


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
        with one_blas_thread(len(S)):
            Htri, Q = weighted_hessians(B, C), (S * C) @ B.T
        return box_qp_weighted(Htri, Q, lower=0.0, upper=hi, compiled=compiled)
    with one_blas_thread(len(S)):
        return box_qp(B @ B.T, S @ B.T, lower=0.0, upper=hi, compiled=compiled)


def _spread(B: np.ndarray) -> float:
    """Scale for *alpha*: ``mean_i ‖S_i − S̄‖²`` (or ``mean ‖S_i‖²`` for one key)."""
    spread = float(np.mean(np.sum((B - B.mean(0)) ** 2, axis=1))) if len(B) > 1 else 0.0
    if spread <= 1e-12 * max(float(np.mean(np.sum(B**2, axis=1))), 1e-300):
        spread = float(np.mean(np.sum(B**2, axis=1)))
    return spread if spread > 0 else 1.0


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
    with one_blas_thread(T):
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
    with one_blas_thread(T):
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


def box_qp_masked(H, Q, free, *, lower=0.0, upper=np.inf, max_iter: int = 30) -> np.ndarray:
    """:func:`box_qp_weighted` with each frame's problem over its own variables: ``min ½ x_tᵀH_t x_t − q_tᵀx_t``
    over ``x_t[F_t]``, ``l ≤ x_t ≤ u``, ``x_t = 0`` off the free set ``F_t``.

    Every frame is solved by the compiled per-frame kernel
    (:func:`retarget_cli.methods.decomposition._qp_kernel.pdas_frames_masked`: the primal–dual active-set
    iteration of :func:`box_qp_weighted` on the reduced Hessian ``H_t[F_t, F_t]``, certified by its KKT
    conditions), whatever the free sets, so frames of many different sets cost one call; a frame it leaves
    unsettled is finished by :func:`box_qp_weighted`'s numpy iteration with the frames of its free set.

    Parameters
    ----------
    H : ndarray, shape (T, K, K)
        Symmetric positive semi-definite Hessians.
    Q : ndarray, shape (T, K)
    free : ndarray of bool, shape (T, K)
    lower, upper : float or ndarray, shape (K,)
        Bounds, ``lower ≤ 0 ≤ upper``.
    max_iter : int

    Returns
    -------
    ndarray, shape (T, K)
        Zero off each frame's free set.
    """
    Q = np.atleast_2d(np.asarray(Q, dtype=np.float64))
    T, K = Q.shape
    H = np.ascontiguousarray(H, dtype=np.float64)
    F = np.ascontiguousarray(free, dtype=bool)
    if H.shape != (T, K, K) or F.shape != (T, K):
        raise ShapeError(f"H, free: expected shapes ({T}, {K}, {K}) and ({T}, {K}), got {H.shape} and {F.shape}")
    lo, hi = _bounds(lower, upper, K, None)
    if np.any(lo > 0) or np.any(hi < 0):
        raise ParameterError("box_qp_masked: every range must contain 0")
    X = np.zeros((T, K))
    if T == 0 or K == 0:
        return X
    _await_kernel(True)
    from ._qp_kernel import pdas_frames_masked

    done = np.empty(T, dtype=bool)
    pdas_frames_masked(H, np.ascontiguousarray(Q), F, lo, hi, int(max_iter), X, done)
    left = np.flatnonzero(~done)
    if left.size:
        log.debug("box_qp_masked: %d of %d frames left by the compiled kernel", left.size, T)
        pats, inv = np.unique(F[left], axis=0, return_inverse=True)
        for g, pat in enumerate(pats):
            ks = left[inv.ravel() == g]
            idx = np.flatnonzero(pat)
            iu, ju = np.triu_indices(len(idx))
            Hsub = H[ks][:, idx][:, :, idx]
            X[np.ix_(ks, idx)] = box_qp_weighted(Hsub[:, iu, ju], Q[ks][:, idx], lower=lo[idx], upper=hi[idx],
                                                 max_iter=max_iter, compiled=False)
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
        with one_blas_thread(T):
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
