"""Compiled per-frame geometry of the trackers (numba).

The ``lk`` tracker fits a few robust similarities, evaluates a
moving-least-squares warp and solves one small regularisation system per
frame. Each is a handful of arithmetic on at most a few thousand numbers, so
as numpy it costs its call overhead many times over (about two thirds of a
frame's time at 320x320 before these kernels). The functions here are the same
arithmetic as loops; :mod:`retarget_cli.methods.tracking.head` and
:mod:`retarget_cli.methods.tracking.lk` keep the documented interfaces and call them.

``cache=True`` keeps the compiled code next to this file (or in numba's user
cache directory when that is read-only), so only the first run on a machine
compiles.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def similarity_irls(zs, zd, w0, iterations, out):  # pragma: no cover - compiled
    """Weighted IRLS fit of ``zd ≈ a zs + b`` per frame (see :func:`~retarget_cli.methods.tracking.head.fit_similarity`).

    Parameters
    ----------
    zs, zd : ndarray, shape (T, L), complex128
        Source and destination points as complex numbers (finite).
    w0 : ndarray, shape (T, L), float64
        Non-negative weights (zero where a destination was not finite).
    iterations : int
        Huber reweighting passes after the first weighted fit.
    out : ndarray, shape (T, 2, 3), float64
        Output: the similarities as affine matrices.
    """
    T, L = zd.shape
    w = np.empty(L)
    r = np.empty(L)
    for t in range(T):
        unweighted = False
        for i in range(L):
            w[i] = w0[t, i]
            if w0[t, i] <= 0:
                unweighted = True
        a = 1.0 + 0.0j
        b = 0.0j
        for it in range(iterations + 1):
            wsum = 0.0
            ms = 0.0j
            md = 0.0j
            for i in range(L):
                wsum += w[i]
                ms += w[i] * zs[t, i]
                md += w[i] * zd[t, i]
            if not wsum > 0:
                wsum = 1.0
            ms /= wsum
            md /= wsum
            den = 0.0
            num = 0.0j
            for i in range(L):
                cs = zs[t, i] - ms
                cd = zd[t, i] - md
                den += w[i] * (cs.real * cs.real + cs.imag * cs.imag)
                num += w[i] * cs.conjugate() * cd
            a = num / den if den > 0 else 1.0 + 0.0j
            b = md - a * ms
            if it == iterations:
                break
            bad = False
            for i in range(L):
                r[i] = abs(zd[t, i] - (a * zs[t, i] + b))
                if math.isnan(r[i]):
                    bad = True
            # a frame with a zero weight has scale 1 (its median would be meaningless)
            scale = 1.0 if unweighted or bad else max(1.4826 * np.median(r), 1e-3)
            k = 1.345 * scale
            for i in range(L):
                w[i] = w0[t, i] * (1.0 if r[i] <= k else k / max(r[i], 1e-12))
        out[t, 0, 0] = a.real
        out[t, 0, 1] = -a.imag
        out[t, 0, 2] = b.real
        out[t, 1, 0] = a.imag
        out[t, 1, 1] = a.real
        out[t, 1, 2] = b.imag


@njit(cache=True, nogil=True)
def mls_similarity(p, q, v, soft2, f, a):  # pragma: no cover - compiled
    """Moving-least-squares similarity deformation (Schaefer et al. 2006, eq. 6) at query points *v*.

    Parameters
    ----------
    p, q : ndarray, shape (L,), complex128
        Control points and where they go.
    v : ndarray, shape (G,), complex128
    soft2 : float
        Squared softening radius of the weights ``1 / (|p_i - v|^2 + soft2)``.
    f, a : ndarray, shape (G,), complex128
        Output: deformed points and the local similarity factor.
    """
    L = p.shape[0]
    wv = np.empty(L)
    for g in range(v.shape[0]):
        ws = 0.0
        ps = 0.0j
        qs = 0.0j
        for i in range(L):
            d = p[i] - v[g]
            wi = 1.0 / (d.real * d.real + d.imag * d.imag + soft2)
            wv[i] = wi
            ws += wi
            ps += wi * p[i]
            qs += wi * q[i]
        ps /= ws
        qs /= ws
        num = 0.0j
        den = 0.0
        for i in range(L):
            ph = p[i] - ps
            num += wv[i] * ph.conjugate() * (q[i] - qs)
            den += wv[i] * (ph.real * ph.real + ph.imag * ph.imag)
        ag = num / max(den, 1e-12)
        f[g] = ag * (v[g] - ps) + qs
        a[g] = ag


@njit(cache=True, nogil=True)
def regularize_solve(G, m, rigid_weight, neighbours, smooth_weight, huber, iterations):  # pragma: no cover
    """IRLS solve of the aperture-aware displacement smoothing of :func:`~retarget_cli.methods.tracking.lk._regularize`.

    Minimises ``sum_i (d_i - m_i)^T G_i (d_i - m_i) + rho_i |d_i|^2 +
    lambda sum_ij w_ij h_ij |d_i - d_j|^2`` with Huber weights ``h_ij``
    of the previous iterate's differences.

    Parameters
    ----------
    G : ndarray, shape (L, 2, 2)
        Per-point information matrices (confidence already applied).
    m : ndarray, shape (L, 2)
        Measured displacements.
    rigid_weight : ndarray, shape (L,)
        ``rho_i``.
    neighbours : ndarray, shape (L, L)
        ``w_ij`` (zero diagonal).
    smooth_weight, huber : float
        ``lambda`` and the Huber threshold.
    iterations : int

    Returns
    -------
    ndarray, shape (L, 2)
    """
    L = m.shape[0]
    n = 2 * L
    rhs = np.empty(n)
    for i in range(L):
        rhs[2 * i] = G[i, 0, 0] * m[i, 0] + G[i, 0, 1] * m[i, 1]
        rhs[2 * i + 1] = G[i, 1, 0] * m[i, 0] + G[i, 1, 1] * m[i, 1]
    d = m.copy()
    A = np.empty((n, n))
    for _ in range(iterations):
        A[:] = 0.0
        for i in range(L):
            for a in range(2):
                for b in range(2):
                    A[2 * i + a, 2 * i + b] = G[i, a, b]
            A[2 * i, 2 * i] += rigid_weight[i]
            A[2 * i + 1, 2 * i + 1] += rigid_weight[i]
        for i in range(L):
            for j in range(L):
                if i == j:
                    continue
                dx = d[i, 0] - d[j, 0]
                dy = d[i, 1] - d[j, 1]
                r = math.sqrt(dx * dx + dy * dy)
                wij = smooth_weight * neighbours[i, j] * min(1.0, huber / max(r, 1e-12))
                for c in range(2):
                    A[2 * i + c, 2 * i + c] += wij
                    A[2 * i + c, 2 * j + c] -= wij
        d = _cholesky_solve(A, rhs).reshape(L, 2)
    return d


@njit(cache=True, nogil=True)
def _cholesky_solve(A, b):  # pragma: no cover - compiled
    """Solve ``A x = b`` for symmetric positive definite *A* (LAPACK Cholesky, then two triangular sweeps)."""
    C = np.linalg.cholesky(A)
    n = b.shape[0]
    y = np.empty(n)
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= C[i, k] * y[k]
        y[i] = s / C[i, i]
    x = np.empty(n)
    for i in range(n - 1, -1, -1):
        s = y[i]
        for k in range(i + 1, n):
            s -= C[k, i] * x[k]
        x[i] = s / C[i, i]
    return x


@njit(cache=True, nogil=True)
def light_fit(T, image, u, v, iterations):  # pragma: no cover - compiled
    """Robust least-squares fit of ``image ≈ T (a + b u + c v)`` over the pixels where ``T > 0``.

    The relighting model of :func:`~retarget_cli.methods.tracking.lk._match_lighting`
    (Hager & Belhumeur 1998, first order): weighted normal equations, then
    Huber reweighting at twice the median absolute residual (at least 0.5
    grey levels) for *iterations* - 1 further solves.

    Parameters
    ----------
    T, image : ndarray, shape (h, w), uint8
        Template and image samples.
    u, v : ndarray, shape (w,) and (h,), float64
        Normalised coordinates of the sample columns and rows.
    iterations : int
        Number of solves (>= 1).

    Returns
    -------
    coef : ndarray, shape (3,)
        ``(a, b, c)``; ``(1, 0, 0)`` when fewer than 16 samples are usable.
    """
    h, w = T.shape
    n = 0
    for y in range(h):
        for x in range(w):
            if T[y, x] > 0:
                n += 1
    coef = np.array([1.0, 0.0, 0.0])
    if n < 16:
        return coef
    A = np.empty((n, 3))
    b = np.empty(n)
    k = 0
    for y in range(h):
        for x in range(w):
            if T[y, x] > 0:
                t = float(T[y, x])
                A[k, 0] = t
                A[k, 1] = t * u[x]
                A[k, 2] = t * v[y]
                b[k] = float(image[y, x])
                k += 1
    wt = np.ones(n)
    r = np.empty(n)
    for _ in range(iterations):
        N = np.zeros((3, 3))
        rhs = np.zeros(3)
        for i in range(n):
            for p in range(3):
                wa = wt[i] * A[i, p]
                rhs[p] += wa * b[i]
                for q in range(3):
                    N[p, q] += wa * A[i, q]
        for p in range(3):
            N[p, p] += 1e-6
        coef = np.linalg.solve(N, rhs)
        for i in range(n):
            r[i] = abs(A[i, 0] * coef[0] + A[i, 1] * coef[1] + A[i, 2] * coef[2] - b[i])
        kk = 2.0 * max(np.median(r), 0.5)
        for i in range(n):
            wt[i] = min(1.0, kk / max(r[i], 1e-6))
    return coef
