"""Compiled per-frame kernel of :func:`retarget_cli.methods.decomposition.box_qp` (numba).

The batched primal–dual active-set iteration (Hintermüller, Ito & Kunisch
2002) needs a different reduced system for nearly every frame, since active
sets differ from frame to frame. Run as numpy over all frames, it spends its
time gathering those systems and in per-call overhead. Compiled, each frame
runs the whole iteration in registers and cache instead: a Cholesky
factorisation of ``H_FF`` per iteration, and the KKT check on the full
gradient.

:func:`nnls_gram_pairs` is the same idea for greedy key selection
(:mod:`retarget_cli.methods.selection`): many small warm-started NNLS problems
in Gram form, each frame's trial with each candidate key, in one call.

The module is imported on first use only: importing numba takes a few tenths
of a second, and the first call loads, or on a new machine compiles, the
kernel (``cache=True`` keeps the compiled code next to this file, or in
numba's user cache directory when that is read-only).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def pdas_frames(H, Q, lo, hi, X0, hscale, max_iter, X, done, Hinv=None):  # pragma: no cover - compiled
    """Primal–dual active-set solve of ``min ½xᵀHx − q_tᵀx, lo ≤ x ≤ hi`` for every row of *Q*.

    Parameters
    ----------
    H : ndarray, shape (K, K)
        Symmetric positive definite (regularised by the caller).
    Q : ndarray, shape (T, K)
    lo, hi : ndarray, shape (K,)
        Bounds (``hi`` may be ``inf``).
    X0 : ndarray, shape (T, K)
        Unconstrained minimisers, which give the initial active sets.
    hscale : float
        ``max(diag H)``, the scale of the KKT tolerances.
    max_iter : int
    X : ndarray, shape (T, K)
        Output: the solution of every frame marked done.
    done : ndarray of bool, shape (T,)
        Output: False where the iteration did not settle within *max_iter*
        or a reduced system was numerically singular; the caller finishes
        those frames by other means.
    Hinv : ndarray, shape (K, K), optional
        ``H⁻¹``, given when *H* is well conditioned. The first iteration's
        free sets (the positive part of *X0*) are the largest; where the bound
        set ``Z`` is the smaller one, that iteration's point is computed as
        ``x = x0 + H⁻¹_{:,Z} (H⁻¹_{ZZ})⁻¹ (x_B − x0)_Z`` (the minimiser with
        ``x_Z = x_B``, through the Schur complement), a system of size ``|Z|``.
        That point only proposes the next active set: it is less accurate
        (its error grows with the condition number of *H*), so no frame is
        certified from it; a frame that is already optimal takes one direct
        solve on the same free set.

    Notes
    -----
    A frame is done when its KKT conditions hold with the tolerances of
    :func:`retarget_cli.methods.decomposition._pdas` (free variables within their
    bounds to ``1e-10·(1 + max|x|)``, multipliers of the bound ones of the
    right sign to ``1e-11·(max|q| + max(diag H)·(1 + max|x|))``). Cycling is
    prevented by the backup rule of Júdice & Pires (1994): after three
    iterations without fewer infeasible variables, only the last infeasible
    one is exchanged until the count improves.
    """
    T, K = Q.shape
    ws = _workspace(K)
    for t in range(T):
        done[t] = _frame(H, Q[t], lo, hi, X0[t], False, False, Hinv, hscale, max_iter, X[t], *ws)


@njit(cache=True, nogil=True)
def pdas_frames_weighted(Htri, Q, lo, hi, max_iter, X, done):  # pragma: no cover - compiled
    """:func:`pdas_frames` with a Hessian per frame, each given by its upper triangle.

    Parameters
    ----------
    Htri : ndarray, shape (T, K(K+1)/2)
        Row ``t`` holds ``H_t[i, j]`` for ``i ≤ j``, in the order of
        ``numpy.triu_indices(K)``.
    Q, lo, hi, max_iter, X, done
        As for :func:`pdas_frames`.

    Notes
    -----
    Each frame's Hessian is unpacked, regularised as the shared one is
    (``1e-14·max(diag H_t)`` added to its diagonal) and solved by the same
    iteration. The first frame starts from the unconstrained minimiser (in
    its first iteration every variable is free); each later frame from the
    active set of the frame before it (frames of a take change little from
    one to the next), which only changes how many iterations it takes.
    """
    T, K = Q.shape
    ws = _workspace(K)
    H = np.empty((K, K))
    for t in range(T):
        hscale = 1e-300
        k = 0
        for i in range(K):  # the rows of Htri are in numpy.triu_indices order
            hscale = max(hscale, abs(Htri[t, k]))
            for j in range(i, K):
                H[i, j] = H[j, i] = Htri[t, k]
                k += 1
        for i in range(K):
            H[i, i] += 1e-14 * hscale
        if t and done[t - 1]:  # consecutive frames of a take: the last active set is a close guess
            done[t] = _frame(H, Q[t], lo, hi, X[t - 1], False, True, None, hscale, max_iter, X[t], *ws)
        else:
            done[t] = _frame(H, Q[t], lo, hi, Q[t], True, False, None, hscale, max_iter, X[t], *ws)


@njit(cache=True, nogil=True)
def pdas_frames_masked(H, Q, free, lo, hi, max_iter, X, done):  # pragma: no cover - compiled
    """:func:`pdas_frames` with a full Hessian per frame and each frame's QP over its own *free* variables.

    Parameters
    ----------
    H : ndarray, shape (T, K, K)
        Symmetric positive semi-definite Hessians (only the entries of free variables are read).
    Q : ndarray, shape (T, K)
    free : ndarray of bool, shape (T, K)
        The variables of frame ``t``'s problem; the others are held at 0 (``X[t]`` is 0 there).
    lo, hi, max_iter, X, done
        As for :func:`pdas_frames` (``lo ≤ 0 ≤ hi``).

    Notes
    -----
    Each frame's reduced Hessian ``H_t[F_t, F_t]`` is regularised as :func:`pdas_frames_weighted` does
    (``1e-14·max(diag)`` on its diagonal) and solved by the same iteration from the unconstrained
    minimiser. A frame without free variables is done, at 0.
    """
    T, K = Q.shape
    idx = np.empty(K, np.int64)
    hbuf = np.empty(K * K)
    qs = np.empty(K)
    ls = np.empty(K)
    us = np.empty(K)
    xs = np.empty(K)
    status, F, prevF, N, L, dinv, b, x, bad, grad, Z = _workspace(K)
    for t in range(T):
        m = 0
        for i in range(K):
            X[t, i] = 0.0
            if free[t, i]:
                idx[m] = i
                m += 1
        if m == 0:
            done[t] = True
            continue
        Hs = hbuf[:m * m].reshape((m, m))
        hscale = 1e-300
        for a in range(m):
            hscale = max(hscale, abs(H[t, idx[a], idx[a]]))
        for a in range(m):
            for c in range(m):
                Hs[a, c] = H[t, idx[a], idx[c]]
            Hs[a, a] += 1e-14 * hscale
            qs[a] = Q[t, idx[a]]
            ls[a] = lo[idx[a]]
            us[a] = hi[idx[a]]
        done[t] = _frame(Hs, qs[:m], ls[:m], us[:m], qs[:m], True, False, None, hscale, max_iter, xs[:m],
                         status[:m], F[:m], prevF[:m], N[:m], L, dinv[:m], b[:m], x[:m], bad[:m], grad[:m], Z[:m])
        if done[t]:
            for a in range(m):
                X[t, idx[a]] = xs[a]


@njit(cache=True, nogil=True)
def nnls_gram_pairs(G, which, B, W, tol, max_iter, ok):  # pragma: no cover - compiled
    """Warm-started Lawson–Hanson NNLS in Gram form for many small problems, each with one of several Grams.

    Problem ``p`` is ``min wᵀG_s w − 2 b_pᵀw`` subject to ``w ≥ 0`` with ``s = which[p]``, i.e.
    ``‖q − Bᵀw‖²`` with ``G = B Bᵀ``, ``b = B q`` (Chuang & Bregler's eq. 4). It is the iteration of
    :func:`retarget_cli.methods.selection._nnls_gram` with ``warm_optimal``: the passive set starts at
    the support of ``W[p]`` (least squares on it already), the most violated zero weight enters, and
    an infeasible least-squares point steps back to the boundary, dropping the weights it zeroes;
    the same tolerances. Each least-squares solve is a Cholesky factorisation of ``G_PP``.

    Parameters
    ----------
    G : ndarray, shape (n, K, K)
        Symmetric positive semi-definite Grams.
    which : ndarray of int, shape (P,)
        The Gram of each problem.
    B : ndarray, shape (P, K)
    W : ndarray, shape (P, K)
        In: non-negative starts, optimal on their support. Out: the solutions of the problems marked ok.
    tol : ndarray, shape (n,)
        Gradient tolerance of each Gram (``1e-11·max(diag G_s)``).
    max_iter : int
        Weights entering the passive set, at most.
    ok : ndarray of bool, shape (P,)
        Out: False where *max_iter* was reached or a ``G_PP`` was numerically singular (the caller
        solves those problems another way).
    """
    n_p, K = B.shape
    passive = np.empty(K, np.bool_)
    idx = np.empty(K, np.int64)
    L = np.empty((K, K))
    dinv = np.empty(K)
    z = np.empty(K)
    w = np.empty(K)
    for p in range(n_p):
        H = G[which[p]]
        b = B[p]
        for i in range(K):
            w[i] = W[p, i]
            passive[i] = w[i] > 0.0
        ok[p] = False
        for _ in range(max_iter):
            j = _entering(H, b, w, passive, tol[which[p]])
            if j < 0:
                ok[p] = True
                break
            passive[j] = True
            singular = False
            for _inner in range(K + 1):  # least squares on the passive set, stepping back while infeasible
                status = _ls_step(H, b, w, passive, idx, L, dinv, z)
                singular = status < 0
                if status != 1:
                    break
            if singular:
                break
        if ok[p]:
            for i in range(K):
                W[p, i] = w[i]


@njit(cache=True, nogil=True, inline="always")  # (a step of nnls_gram_pairs, inlined into it)
def _entering(H, b, w, passive, tol):  # pragma: no cover - compiled
    """The zero weight whose gradient ``b − Hw`` is largest and above *tol* (the first on ties), or -1."""
    K = len(b)
    j = -1
    gbest = tol
    for i in range(K):
        if passive[i]:
            continue
        g = b[i]
        for a in range(K):
            g -= w[a] * H[a, i]
        if g > gbest:
            gbest = g
            j = i
    return j


@njit(cache=True, nogil=True, inline="always")  # (a step of nnls_gram_pairs, inlined into it)
def _ls_step(H, b, w, passive, idx, L, dinv, z):  # pragma: no cover - compiled
    """Least squares on the passive set: 0 when feasible (*w* is the point), 1 after stepping *w* back to
    the boundary and dropping the weights it zeroes from *passive*, -1 when ``H_PP`` is singular."""
    K = len(b)
    m = 0
    for i in range(K):
        if passive[i]:
            idx[m] = i
            m += 1
    if not _factor(H, idx, 0, m, L, dinv):
        return -1
    for a in range(m):
        z[a] = b[idx[a]]
    _solve(L, dinv, m, z)
    alpha = np.inf
    for a in range(m):
        if z[a] <= 0.0:
            wi = w[idx[a]]
            alpha = min(alpha, wi / (wi - z[a]) if wi != z[a] else np.inf)
    if alpha == np.inf:
        for i in range(K):
            w[i] = 0.0
        for a in range(m):
            w[idx[a]] = z[a]
        return 0
    alpha = min(max(alpha, 0.0), 1.0)
    wmax = 0.0
    for a in range(m):
        i = idx[a]
        w[i] = w[i] + alpha * (z[a] - w[i])
        wmax = max(wmax, abs(w[i]))
    cut = 1e-14 * max(1.0, wmax)
    for a in range(m):
        i = idx[a]
        if not w[i] > cut:
            passive[i] = False
            w[i] = 0.0
    return 1


@njit(cache=True, nogil=True)
def _workspace(K):  # pragma: no cover - compiled
    """Scratch arrays of :func:`_frame`, allocated once per call."""
    return (np.empty(K, np.int8), np.empty(K, np.int64), np.empty(K, np.int64), np.empty(K, np.int64),
            np.empty((K, K)), np.empty(K), np.empty(K), np.empty(K), np.empty(K, np.bool_), np.empty(K),
            np.empty(K, np.int64))


@njit(cache=True, nogil=True)
def _frame(H, q, lo, hi, x0, start_free, warm, Hinv, hscale, max_iter, out,
           status, F, prevF, N, L, dinv, b, x, bad, grad, Z):  # pragma: no cover - compiled
    """One frame of :func:`pdas_frames`; True (and the solution in *out*) once its KKT conditions hold.

    The first active set is that of *x0* (the unconstrained minimiser), or
    every variable free when *start_free*, or with *warm* that of the
    previous solution *x0* (its variables at a bound start bound). *status* (-1 at the lower bound,
    +1 at the upper, 0 free), *F* (free variables, ascending), *prevF* (the
    free set whose factor *L* holds), *N* (bound variables with a nonzero
    value), *dinv* (reciprocals of L's diagonal) and the rest are scratch.
    """
    K = len(q)
    qs = _initial_status(q, lo, hi, x0, start_free, warm, status)
    best = K + 2
    tries = 3
    pm = 0  # rows of L valid for prevF[:pm]
    for it in range(max_iter):
        m, nn = _split(status, lo, hi, F, N, x)
        schur = False
        if it == 0 and Hinv is not None and K - m < m:
            schur = _schur_point(Hinv, x0, status, x, Z, L, dinv, b)
            pm = 0
        if not schur:
            pm = _reduced_solve(H, q, F, N, m, nn, x, prevF, pm, L, dinv, b)
            if pm < 0:
                break  # numerically singular: the caller finishes this frame
        xm = 0.0
        for i in range(K):
            xm = max(xm, abs(x[i]))
        tolx = 1e-10 * (1.0 + xm)
        tolg = 1e-11 * (qs + hscale * (1.0 + xm))
        # a Schur point is accurate to about cond(H)·eps only: there, values
        # within 1e-8 of a bound are taken to be at it (a wrong guess is
        # undone by the multiplier check of the next, direct, iteration)
        tolf = -1e-8 * (1.0 + xm) if schur else tolx
        ninf, last = _violations(H, q, lo, hi, status, x, F, N, m, nn, grad, bad, tolf, tolg)
        if ninf == 0 and not schur:
            for i in range(K):
                out[i] = x[i]
            return True
        full = True
        if ninf < best:
            best = ninf
            tries = 3
        elif tries > 0:
            tries -= 1
        else:
            full = False
        _flip(status, bad, x, lo, full, last, tolf)
    return False


@njit(cache=True, nogil=True, inline="always")  # (a step of _frame, inlined into it)
def _initial_status(q, lo, hi, x0, start_free, warm, status):  # pragma: no cover - compiled
    """The first active set of :func:`_frame` into *status*; returns max |q|."""
    qs = 0.0
    for i in range(len(q)):
        qs = max(qs, abs(q[i]))
        if start_free:
            status[i] = 0
        elif warm:  # x0 is a previous solution: variables at a bound start bound
            status[i] = -1 if x0[i] <= lo[i] else (1 if x0[i] >= hi[i] else 0)
        elif x0[i] < lo[i]:
            status[i] = -1
        elif x0[i] > hi[i]:
            status[i] = 1
        else:
            status[i] = 0
    return qs


@njit(cache=True, nogil=True, inline="always")  # (a step of _frame, inlined into it)
def _split(status, lo, hi, F, N, x):  # pragma: no cover - compiled
    """Free variables into *F*, bound ones with a nonzero bound into *N*; bound values into *x*. Returns (m, nn)."""
    m = 0
    nn = 0
    for i in range(len(status)):
        if status[i] == 0:
            F[m] = i
            m += 1
            x[i] = 0.0
        else:
            x[i] = lo[i] if status[i] == -1 else hi[i]
            if x[i] != 0.0:
                N[nn] = i
                nn += 1
    return m, nn


@njit(cache=True, nogil=True, inline="always")  # (a step of _frame, inlined into it)
def _reduced_solve(H, q, F, N, m, nn, x, prevF, pm, L, dinv, b):  # pragma: no cover - compiled
    """Solve ``H_FF x_F = q_F − H_FB x_B`` by Cholesky into *x*; the new *pm*, or -1 when singular.

    The rows of the factor for a prefix of F unchanged since the last
    iteration (``prevF[:pm]``) are kept.
    """
    for a in range(m):
        s = q[F[a]]
        for c in range(nn):
            s -= H[F[a], N[c]] * x[N[c]]
        b[a] = s
    r = 0
    while r < min(m, pm) and F[r] == prevF[r]:
        r += 1
    if not _factor(H, F, r, m, L, dinv):
        return -1
    for a in range(m):
        prevF[a] = F[a]
    _solve(L, dinv, m, b)
    for a in range(m):
        x[F[a]] = b[a]
    return m


@njit(cache=True, nogil=True, inline="always")  # (a step of _frame, inlined into it)
def _violations(H, q, lo, hi, status, x, F, N, m, nn, grad, bad, tolf, tolg):  # pragma: no cover - compiled
    """KKT check: mark the infeasible variables in *bad*; returns their count and the last one (-1: none)."""
    K = len(q)
    # gradient Hx − q, as a sum of rows of H (H is symmetric) over the
    # nonzero entries of x: contiguous loops the compiler vectorises
    for i in range(K):
        grad[i] = -q[i]
    for a in range(m):
        _axpy(x[F[a]], H, F[a], grad, K)
    for c in range(nn):
        _axpy(x[N[c]], H, N[c], grad, K)
    ninf = 0
    last = -1
    for i in range(K):
        if status[i] == 0:
            bad[i] = x[i] < lo[i] - tolf or x[i] > hi[i] + tolf
        else:
            g = grad[i]
            bad[i] = (status[i] == -1 and g < -tolg) or (status[i] == 1 and g > tolg)
        if bad[i]:
            ninf += 1
            last = i
    return ninf, last


@njit(cache=True, nogil=True, inline="always")  # (a step of _frame, inlined into it)
def _flip(status, bad, x, lo, full, last, tolf):  # pragma: no cover - compiled
    """Move the infeasible variables (all, or only the last when *full* is false) to the other set."""
    for i in range(len(status)):
        if not bad[i] or not (full or i == last):
            continue
        if status[i] != 0:
            status[i] = 0
        elif x[i] < lo[i] - tolf:
            status[i] = -1
        else:
            status[i] = 1


@njit(cache=True, nogil=True)
def _schur_point(Hinv, x0, status, x, Z, L, dinv, b):  # pragma: no cover - compiled
    """Minimiser with the bound variables at their values *x* (in place), from *x0* through ``H⁻¹``.

    Returns False (and leaves the free entries of *x* undefined) when
    ``H⁻¹_{ZZ}`` is numerically singular.
    """
    K = len(x0)
    z = 0
    for i in range(K):
        if status[i] != 0:
            Z[z] = i
            b[z] = x[i] - x0[i]
            z += 1
    if not _factor(Hinv, Z, 0, z, L, dinv):
        return False
    _solve(L, dinv, z, b)
    for i in range(K):
        if status[i] == 0:
            s = x0[i]
            for c in range(z):
                s += Hinv[i, Z[c]] * b[c]
            x[i] = s
    return True


@njit(cache=True, nogil=True)
def _factor(H, idx, start, m, L, dinv):  # pragma: no cover - compiled
    """Rows ``start..m-1`` of the Cholesky factor *L* of ``H[idx[:m]][:, idx[:m]]`` (rows above kept).

    *dinv* receives the reciprocals of the diagonal (multiplying by them is
    several times cheaper than dividing). Returns False if the matrix is not
    numerically positive definite.
    """
    for a in range(start, m):
        for c in range(a):
            L[a, c] = (H[idx[a], idx[c]] - _rowdot(L, a, c, c)) * dinv[c]
        s = H[idx[a], idx[a]] - _rowdot(L, a, a, a)
        if not s > 0.0:
            return False
        L[a, a] = math.sqrt(s)
        dinv[a] = 1.0 / L[a, a]
    return True


@njit(cache=True, nogil=True)
def _solve(L, dinv, m, b):  # pragma: no cover - compiled
    """``b[:m] ← (LLᵀ)⁻¹ b[:m]`` by forward and back substitution."""
    for a in range(m):
        s = b[a]
        for k in range(a):
            s -= L[a, k] * b[k]
        b[a] = s * dinv[a]
    for a in range(m - 1, -1, -1):
        s = b[a]
        for k in range(a + 1, m):
            s -= L[k, a] * b[k]
        b[a] = s * dinv[a]


# The factorisation's dot products carry much of the kernel's work. Summed
# with one accumulator, each step waits for the previous addition (no
# reassociation without fastmath); four independent accumulators keep the FPU
# busy. The order of summation is fixed, so results are reproducible.


@njit(cache=True, nogil=True, inline="always")
def _rowdot(L, a, c, n):  # pragma: no cover - compiled
    """``Σ_{k<n} L[a, k]·L[c, k]``."""
    s0 = s1 = s2 = s3 = 0.0
    k = 0
    while k + 4 <= n:
        s0 += L[a, k] * L[c, k]
        s1 += L[a, k + 1] * L[c, k + 1]
        s2 += L[a, k + 2] * L[c, k + 2]
        s3 += L[a, k + 3] * L[c, k + 3]
        k += 4
    while k < n:
        s0 += L[a, k] * L[c, k]
        k += 1
    return (s0 + s1) + (s2 + s3)


@njit(cache=True, nogil=True, inline="always")
def _axpy(alpha, H, j, y, n):  # pragma: no cover - compiled
    """``y[:n] += alpha·H[j, :n]``."""
    for i in range(n):
        y[i] += alpha * H[j, i]


@njit(cache=True, nogil=True)
def principal_csc(indptr, indices, data, keep, n):  # pragma: no cover - compiled
    """The principal submatrix ``H[keep][:, keep]`` of a CSC matrix with sorted row indices, in CSC.

    Parameters
    ----------
    indptr, indices, data : ndarray
        The CSC arrays of ``H`` (n, n), row indices sorted within each column.
    keep : ndarray of int, shape (m,)
        Ascending indices.
    n : int

    Returns
    -------
    indptr, indices, data : ndarray
        Of the (m, m) submatrix, row indices sorted (what scipy's slicing gives, without its two passes).
    """
    m = len(keep)
    new = np.full(n, -1, np.int64)
    for a in range(m):
        new[keep[a]] = a
    ptr = np.zeros(m + 1, indptr.dtype)
    count = 0
    for a in range(m):
        j = keep[a]
        for p in range(indptr[j], indptr[j + 1]):
            if new[indices[p]] >= 0:
                count += 1
        ptr[a + 1] = count
    rows = np.empty(count, indices.dtype)
    vals = np.empty(count, data.dtype)
    k = 0
    for a in range(m):
        j = keep[a]
        for p in range(indptr[j], indptr[j + 1]):
            r = new[indices[p]]
            if r >= 0:
                rows[k] = r
                vals[k] = data[p]
                k += 1
    return ptr, rows, vals


def warm_up(weighted: bool) -> None:
    """Load (on a new machine, compile) the kernel for the argument types the solvers pass.

    Solves a two-variable problem: :func:`pdas_frames_weighted` when
    *weighted*, else :func:`pdas_frames` with a ``Hinv``. Used by
    :func:`retarget_cli.methods.decomposition.prefetch_kernel` to load the code in the
    background while a take is read.
    """
    K = 2
    X, done = np.empty((1, K)), np.empty(1, dtype=np.bool_)
    lo, hi = np.zeros(K), np.full(K, np.inf)
    if weighted:
        pdas_frames_weighted(np.array([[2.0, 0.0, 2.0]]), np.ones((1, K)), lo, hi, 30, X, done)
    else:
        H = np.eye(K)
        pdas_frames(H, np.ones((1, K)), lo, hi, np.ones((1, K)), 1.0, 30, X, done, H)
