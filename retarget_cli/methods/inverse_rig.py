"""Inverse rig for blendshape models with quadratic corrective shapes.

Racković, Soares, Jakovetić & Desnica (2023), *A Majorization–Minimization-based
method for nonconvex inverse rig problems in facial animation*. The rig is

.. math::

    f_Q(\\mathbf w) = \\mathbf b_0 + \\mathbf B \\mathbf w
        + \\sum_{(i,j) \\in \\mathcal P} w_i w_j \\mathbf b^{\\{i,j\\}}        \\qquad (4)

and the inverse problem, for a target mesh :math:`\\hat{\\mathbf b}`, is

.. math::

    \\min_{0 \\le \\mathbf w \\le 1} \\|f_Q(\\mathbf w) - \\hat{\\mathbf b}\\|^2
        + \\alpha \\mathbf 1^T \\mathbf w                                      \\qquad (8)

Solvers (:data:`SOLVERS`):

``ridge``
    closed form of eq. 6, :math:`(B^TB + \\alpha I)^{-1} B^T \\hat b`, clipped to
    [0, 1] (linear rig; also the paper's initialisation of ``mm``);
``bounded``
    eq. 8 for the *linear* rig (correctives ignored), solved exactly by bounded
    least squares (:func:`scipy.optimize.lsq_linear`, BVLS);
``sequential``
    Seol et al. (2011), eq. 7: one pass over the shapes, largest mean offset
    first, each fitted alone to the residual and clipped (linear rig);
``mm``
    Algorithms 1 and 2: majorise eq. 9 by the separable surrogate ψ of
    eq. 15–16 and minimise each coordinate's quartic (eq. 17–18) on
    :math:`[-w_j, 1 - w_j]`;
``lbfgsb``
    our faster solver for the same objective (eq. 8): L-BFGS-B with the
    analytic gradient, evaluated in the reduced space of the precomputed Gram
    matrices (cost per evaluation independent of the vertex count) and
    warm-started from the previous frame.

Coordinates are flattened vertex-major: coordinate ``i = 3 * vertex + axis``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .._validate import check_array
from ..errors import ParameterError, ShapeError

log = logging.getLogger(__name__)

#: Solvers accepted by :func:`solve`, the default first.
SOLVERS = ("lbfgsb", "mm", "bounded", "ridge", "sequential")
DEFAULT_SOLVER = "lbfgsb"
#: Weight of the sparsity term α·1ᵀw of eq. 8 (objective units: squared mesh units).
DEFAULT_ALPHA = 0.1
#: Relative tolerance: stop when an iteration lowers the objective by less than tol × objective.
DEFAULT_TOL = 1e-7
#: Iteration cap T (mm: outer iterations of Algorithm 2; lbfgsb: L-BFGS-B iterations).
DEFAULT_MAX_ITER = 5000
#: A weight above this counts towards the cardinality.
CARDINALITY_THRESHOLD = 0.01


# --------------------------------------------------------------------------- the rig


class QuadraticRig:
    """A blendshape rig with pairwise corrective shapes (eq. 4).

    Parameters
    ----------
    neutral : array_like, shape (N, 3)
        :math:`\\mathbf b_0`.
    deltas : array_like, shape (m, N, 3)
        :math:`\\Delta \\mathbf b_i = \\mathbf b_i - \\mathbf b_0`, the columns of ``B``.
    pairs : array_like of int, shape (P, 2)
        The set :math:`\\mathcal P`: indices of two different shapes per
        corrective; no pair may appear twice (in either order).
    correctives : array_like, shape (P, N, 3)
        :math:`\\mathbf b^{\\{i,j\\}}` (deltas, added with weight :math:`w_i w_j`).
    names : sequence of str, optional
        Shape names (used in error messages and outputs).

    Attributes
    ----------
    b0 : ndarray, shape (3N,)
    B : ndarray, shape (3N, m)
    pairs : ndarray of int64, shape (P, 2)
    C : scipy.sparse.csr_matrix, shape (3N, P)
        Corrective deltas as columns. Row ``i`` holds the nonzero entries of
        :math:`\\mathbf D^{(i)}` (Algorithm 2: :math:`D^{(i)}_{jk} = D^{(i)}_{kj}
        = \\tfrac12 b^{\\{j,k\\}}_i`), so this one sparse matrix stores every
        :math:`\\mathbf D^{(i)}`; :meth:`D` materialises one.
    lam_min, lam_max, sigma : ndarray, shape (3N,)
        Smallest and largest eigenvalue and largest singular value of each
        :math:`\\mathbf D^{(i)}`, computed once, on first use
        (Algorithm 2, first loop): only the ``mm`` solver reads them.
    """

    def __init__(self, neutral, deltas, pairs=(), correctives=None, *, names=None):
        neutral = check_array(neutral, "neutral", ndim=2)
        if neutral.shape[1] != 3:
            raise ShapeError(f"neutral: expected shape (N, 3), got {neutral.shape}")
        n = neutral.shape[0]
        deltas = check_array(deltas, "deltas", ndim=3)
        if deltas.shape[1:] != (n, 3):
            raise ShapeError(f"deltas: expected shape (m, {n}, 3), got {deltas.shape}")
        m = deltas.shape[0]
        self.names = tuple(str(s) for s in names) if names is not None else tuple(f"shape{i}" for i in range(m))
        if len(self.names) != m:
            raise ShapeError(f"names: expected {m} names, got {len(self.names)}")
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        if correctives is None:
            correctives = np.zeros((0, n, 3))
        correctives = np.asarray(correctives, dtype=np.float64)
        if correctives.ndim != 3 or correctives.shape != (len(pairs), n, 3):
            raise ShapeError(f"correctives: expected shape ({len(pairs)}, {n}, 3), got {correctives.shape}")
        if not np.all(np.isfinite(correctives)):
            raise ShapeError("correctives: contains NaN or infinity")
        seen: dict = {}
        for k, (i, j) in enumerate(pairs.tolist()):
            if not (0 <= i < m and 0 <= j < m):
                raise ShapeError(f"pairs[{k}]: shape index out of range [0, {m}): ({i}, {j})")
            if i == j:
                raise ShapeError(f"pairs[{k}]: a corrective pairs two different shapes, got {self.names[i]!r} twice")
            key = (min(i, j), max(i, j))
            if key in seen:
                raise ShapeError(f"pairs[{k}]: duplicate corrective pair ({self.names[i]!r}, {self.names[j]!r}), "
                                 f"already pairs[{seen[key]}]")
            seen[key] = k
        from scipy import sparse

        self.b0 = neutral.reshape(-1).copy()
        self.B = np.ascontiguousarray(deltas.reshape(m, -1).T)
        self.pairs = pairs
        C = sparse.csr_matrix(correctives.reshape(len(pairs), 3 * n).T)
        C.eliminate_zeros()
        C.sort_indices()
        self.C = C
        self._spectra = None

    # ------------------------------------------------------------------ spectra (mm only)
    def _spectrum(self):
        """(lam_min, lam_max, sigma), computed on first use: only the ``mm`` solver needs them."""
        if self._spectra is None:
            self._spectra = _corrective_spectra(self.C, self.pairs, self.n_shapes)
        return self._spectra

    @property
    def lam_min(self) -> np.ndarray:
        return self._spectrum()[0]

    @property
    def lam_max(self) -> np.ndarray:
        return self._spectrum()[1]

    @property
    def sigma(self) -> np.ndarray:
        return self._spectrum()[2]

    # ------------------------------------------------------------------ sizes
    @property
    def n_vertices(self) -> int:
        return self.b0.size // 3

    @property
    def n_shapes(self) -> int:
        return self.B.shape[1]

    @property
    def n_pairs(self) -> int:
        return self.pairs.shape[0]

    # ------------------------------------------------------------------ model
    def D(self, i: int):
        """:math:`\\mathbf D^{(i)}` of coordinate *i* as a sparse (m, m) matrix (Algorithm 2)."""
        from scipy import sparse

        row = self.C.getrow(int(i))
        p = row.indices
        half = 0.5 * row.data
        rows = np.concatenate([self.pairs[p, 0], self.pairs[p, 1]])
        cols = np.concatenate([self.pairs[p, 1], self.pairs[p, 0]])
        return sparse.csr_matrix((np.concatenate([half, half]), (rows, cols)), shape=(self.n_shapes,) * 2)

    def products(self, w: np.ndarray) -> np.ndarray:
        """:math:`w_i w_j` for every pair: shape (..., P)."""
        return w[..., self.pairs[:, 0]] * w[..., self.pairs[:, 1]]

    def evaluate_flat(self, w) -> np.ndarray:
        """:math:`f_Q(\\mathbf w)` (eq. 4) flattened: (m,) -> (3N,), or (T, m) -> (T, 3N)."""
        w = np.asarray(w, dtype=np.float64)
        if w.shape[-1] != self.n_shapes or w.ndim not in (1, 2):
            raise ShapeError(f"w: expected shape (m,) or (T, m) with m={self.n_shapes}, got {w.shape}")
        p = self.products(w)
        out = w @ self.B.T + (self.C @ p.T).T
        return out + self.b0

    def evaluate(self, w) -> np.ndarray:
        """Mesh positions :math:`f_Q(\\mathbf w)` (eq. 4).

        Parameters
        ----------
        w : array_like, shape (m,) or (T, m)

        Returns
        -------
        ndarray, shape (N, 3) or (T, N, 3)
        """
        flat = self.evaluate_flat(w)
        return flat.reshape(*flat.shape[:-1], self.n_vertices, 3)

    def _S(self, w: np.ndarray):
        """Sparse (P, m) matrix with ``C @ S(w)`` the corrective part of the Jacobian."""
        from scipy import sparse

        P = self.n_pairs
        rows = np.concatenate([np.arange(P), np.arange(P)])
        cols = np.concatenate([self.pairs[:, 0], self.pairs[:, 1]])
        vals = np.concatenate([w[self.pairs[:, 1]], w[self.pairs[:, 0]]])
        return sparse.csr_matrix((vals, (rows, cols)), shape=(P, self.n_shapes))

    def _St(self, y: np.ndarray, w: np.ndarray) -> np.ndarray:
        """``S(w)^T y`` for y of shape (P,)."""
        m = self.n_shapes
        return (np.bincount(self.pairs[:, 0], y * w[self.pairs[:, 1]], minlength=m)
                + np.bincount(self.pairs[:, 1], y * w[self.pairs[:, 0]], minlength=m))

    def jacobian(self, w) -> np.ndarray:
        """:math:`\\partial f_Q / \\partial \\mathbf w`, shape (3N, m); row i is
        :math:`\\mathbf h_i = \\mathbf B_i + 2\\mathbf w^T \\mathbf D^{(i)}` (eq. 16)."""
        w = np.asarray(w, dtype=np.float64)
        return self.B + (self.C @ self._S(w)).toarray()

    def objective(self, w, target, alpha: float) -> float:
        """Eq. 8: :math:`\\|f_Q(\\mathbf w) - \\hat{\\mathbf b}\\|^2 + \\alpha \\mathbf 1^T \\mathbf w`.

        Parameters
        ----------
        w : array_like, shape (m,)
        target : array_like, shape (N, 3) or (3N,)
        alpha : float
        """
        r = self.evaluate_flat(w) - np.asarray(target, dtype=np.float64).reshape(-1)
        return float(r @ r + alpha * np.sum(w))

    # ------------------------------------------------------------------ precomputed
    @cached_property
    def gram(self) -> dict:
        """Gram matrices ``BB = BᵀB`` (m, m), ``BC = BᵀC`` (m, P), ``CC = CᵀC`` (P, P), and ``BF2 = ‖B‖_F²``."""
        BC = np.asarray((self.C.T @ self.B).T)
        CC = np.asarray((self.C.T @ self.C).toarray())
        return {"BB": self.B.T @ self.B, "BC": BC, "CC": CC, "BF2": float(np.sum(self.B**2))}

    @cached_property
    def _jf2_terms(self) -> dict:
        """Index arrays for :math:`\\|J(\\mathbf w)\\|_F^2` in O(P + Σ_j deg_j²) (see :func:`mm_coefficients`).

        :math:`J = B + CS(\\mathbf w)`, so :math:`\\|J\\|_F^2 = \\|B\\|_F^2 + 2\\,\\mathrm{tr}(G_{BC}S)
        + \\sum_j \\mathbf s_j^T G_{CC} \\mathbf s_j` where column :math:`\\mathbf s_j` of S is
        nonzero only on the pairs p containing shape j, with value :math:`w_{\\text{other}(p, j)}`.
        """
        P, pairs = self.n_pairs, self.pairs
        by_shape: dict[int, list[tuple[int, int]]] = {}
        for p, (i, j) in enumerate(pairs.tolist()):
            by_shape.setdefault(i, []).append((p, j))
            by_shape.setdefault(j, []).append((p, i))
        tp, tq, op, oq = [], [], [], []
        for lst in by_shape.values():
            for p, a in lst:
                for q, b in lst:
                    tp.append(p)
                    tq.append(q)
                    op.append(a)
                    oq.append(b)
        G = self.gram
        ar = np.arange(P)
        return {"g0": G["BC"][pairs[:, 0], ar], "g1": G["BC"][pairs[:, 1], ar],
                "gcc": G["CC"][np.asarray(tp, dtype=np.int64), np.asarray(tq, dtype=np.int64)],
                "op": np.asarray(op, dtype=np.int64), "oq": np.asarray(oq, dtype=np.int64)}

    @cached_property
    def _corrective_rows(self) -> dict:
        """Coordinates whose :math:`\\mathbf D^{(i)}` is nonzero, with their rows of B and C and spectra."""
        rows = np.flatnonzero(np.diff(self.C.indptr))
        return {"rows": rows, "B": np.ascontiguousarray(self.B[rows]), "C": self.C[rows],
                "lam_min": self.lam_min[rows], "lam_max": self.lam_max[rows]}

    def jacobian_fro2(self, w: np.ndarray) -> float:
        """:math:`\\sum_i \\|\\mathbf h_i\\|^2 = \\|J(\\mathbf w)\\|_F^2` without forming J."""
        G = self.gram
        if not self.n_pairs:
            return G["BF2"]
        t = self._jf2_terms
        cross = t["g0"] @ w[self.pairs[:, 1]] + t["g1"] @ w[self.pairs[:, 0]]
        return float(G["BF2"] + 2 * cross + t["gcc"] @ (w[t["op"]] * w[t["oq"]]))

    @cached_property
    def s_coefficient(self) -> float:
        """``s`` of eq. 18: :math:`2m\\sum_i \\sigma^2(\\mathbf D^{(i)})` (the same every iteration)."""
        return float(2 * self.n_shapes * np.sum(self.sigma**2))


def _corrective_spectra(C, pairs, m: int):
    """Eigen- and singular values of every :math:`\\mathbf D^{(i)}` (Algorithm 2, first loop).

    Coordinates with the same set of nonzero correctives share one small dense
    matrix layout (restricted to the shapes involved) and are diagonalised in
    one batched :func:`numpy.linalg.eigvalsh` call. :math:`\\mathbf D^{(i)}`
    restricted to its involved shapes has the same nonzero spectrum; the
    remaining eigenvalues are 0, which is folded into the min and max.

    Returns
    -------
    lam_min, lam_max, sigma : ndarray, shape (3N,)
    """
    n3 = C.shape[0]
    lam_min = np.zeros(n3)
    lam_max = np.zeros(n3)
    counts = np.diff(C.indptr)
    groups: dict[bytes, list[int]] = {}
    for i in np.flatnonzero(counts):
        groups.setdefault(C.indices[C.indptr[i]:C.indptr[i + 1]].tobytes(), []).append(int(i))
    for key, rows in groups.items():
        cols = np.frombuffer(key, dtype=C.indices.dtype)
        shapes, local = np.unique(pairs[cols].ravel(), return_inverse=True)
        local = local.reshape(-1, 2)
        pad = len(shapes) < m  # D^(i) has further zero eigenvalues
        # a block of rows at a time: with dense correctives one layout covers every coordinate,
        # and (3N, s, s) at once would not fit in memory (about 2**25 bytes per block)
        step = max(1, 2**22 // (len(shapes) ** 2))
        all_rows = np.asarray(rows)
        for r0 in range(0, len(all_rows), step):
            rows = all_rows[r0:r0 + step]
            vals = np.stack([C.data[C.indptr[i]:C.indptr[i + 1]] for i in rows])  # (R, len(cols))
            M = np.zeros((len(rows), len(shapes), len(shapes)))
            M[:, local[:, 0], local[:, 1]] = 0.5 * vals
            M[:, local[:, 1], local[:, 0]] = 0.5 * vals
            ev = np.linalg.eigvalsh(M)
            lam_min[rows] = np.minimum(ev[:, 0], 0.0) if pad else ev[:, 0]
            lam_max[rows] = np.maximum(ev[:, -1], 0.0) if pad else ev[:, -1]
    sigma = np.maximum(np.abs(lam_min), np.abs(lam_max))  # D^(i) is symmetric
    return lam_min, lam_max, sigma


# --------------------------------------------------------------------------- MM (Algorithms 1 and 2)


def quartic_argmin(q, r, s, lo, hi) -> np.ndarray:
    """Minimiser of :math:`\\varphi(v) = qv + rv^2 + sv^4` on [lo, hi] (eq. 17), elementwise.

    The real roots of the cubic :math:`\\varphi'(v) = q + 2rv + 4sv^3` that lie
    in the interval are compared with the interval ends (Racković et al.,
    below eq. 18). Cardano's formula in a cancellation-free form gives the
    single real root when the discriminant is non-negative (always the case
    for ``r >= 0``, as in the MM surrogate); the trigonometric form gives the
    three real roots otherwise. Every root gets one Newton polish.

    Parameters
    ----------
    q, r, s : array_like
        Coefficients, broadcast together; ``s >= 0``.
    lo, hi : array_like
        Interval ends, ``lo <= hi``.

    Returns
    -------
    ndarray
        The minimiser, broadcast shape of the inputs.
    """
    q, r, s, lo, hi = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (q, r, s, lo, hi)))
    if np.any(s < 0):
        raise ParameterError("s: the quartic coefficient must be >= 0")
    cands = [lo, hi]
    quartic = s > 0
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        ss = np.where(quartic, s, 1.0)
        P = r / (2 * ss)
        Q = q / (4 * ss)
        disc = (Q / 2) ** 2 + (P / 3) ** 3
        one = quartic & (disc >= 0)
        sgn = np.where(Q >= 0, 1.0, -1.0)
        u = -sgn * np.cbrt(np.abs(Q) / 2 + np.sqrt(np.where(one, disc, 0.0)))
        root1 = np.where(u != 0, u - P / (3 * np.where(u != 0, u, 1.0)), 0.0)
        cands.append(np.where(one, root1, np.nan))
        three = quartic & (disc < 0)
        if np.any(three):
            Pn = np.where(three, P, -1.0)  # P < 0 there
            amp = 2 * np.sqrt(-Pn / 3)
            arg = np.clip((3 * Q / (2 * Pn)) * np.sqrt(-3 / Pn), -1.0, 1.0)
            phi = np.arccos(arg) / 3
            for k in range(3):
                cands.append(np.where(three, amp * np.cos(phi - 2 * np.pi * k / 3), np.nan))
        if not np.all(quartic):
            # s == 0: a quadratic (r > 0) has its vertex; otherwise only the ends matter
            cands.append(np.where(~quartic & (r > 0), -q / (2 * np.where(r > 0, r, 1.0)), np.nan))
        X = np.stack(cands)
        # one Newton step on the cubic for the roots (not the ends)
        d1 = q + 2 * r * X[2:] + 4 * s * X[2:] ** 3
        d2 = 2 * r + 12 * s * X[2:] ** 2
        X[2:] = np.where(np.isfinite(X[2:]) & (d2 != 0), X[2:] - d1 / np.where(d2 != 0, d2, 1.0), X[2:])
        X = np.clip(X, lo, hi)
        vals = q * X + r * X**2 + s * X**4
        vals = np.where(np.isnan(X), np.inf, vals)
    best = np.argmin(vals, axis=0)
    return np.take_along_axis(X, best[None], axis=0)[0]


def mm_coefficients(rig: QuadraticRig, w, b, alpha: float, *, bt=None):
    """Coefficients q, r, s of the separable quartic surrogate (eq. 18) at ``w``.

    With :math:`g_i = \\mathbf B_i\\mathbf w + \\mathbf w^T\\mathbf D^{(i)}\\mathbf w - \\hat b_i`
    (the residual) and :math:`\\mathbf h_i` the Jacobian's row i:

    .. math::

        q_j = 2\\sum_i g_i h_{ij} + \\alpha,\\quad
        r = 2\\sum_i \\big(g_i\\lambda_M(\\mathbf D^{(i)}, g_i) + \\|\\mathbf h_i\\|^2\\big),\\quad
        s = 2m\\sum_i \\sigma^2(\\mathbf D^{(i)})

    :math:`\\sum_i g_i h_{ij}` and :math:`\\sum_i\\|\\mathbf h_i\\|^2 = \\|J\\|_F^2`
    are computed from the rig's Gram matrices (same values, fewer flops); the
    :math:`\\lambda_M` term needs the sign of every residual coordinate.

    Parameters
    ----------
    rig : QuadraticRig
    w : ndarray, shape (m,), in [0, 1]
    b : ndarray, shape (3N,)
        Target minus the neutral, :math:`\\hat{\\mathbf b} - \\mathbf b_0`.
    alpha : float
    bt : tuple of ndarray, optional
        ``(Bᵀb, Cᵀb)``, precomputed per frame.

    Returns
    -------
    q : ndarray, shape (m,)
    r, s : float
    objective : float
        Eq. 8 at ``w`` (= ψ(0), Condition 2).
    """
    G = rig.gram
    b = np.asarray(b, dtype=np.float64)
    yB, yC = bt if bt is not None else (rig.B.T @ b, rig.C.T @ b)
    p = rig.products(w)
    Btg = G["BB"] @ w + G["BC"] @ p - yB
    Ctg = G["BC"].T @ w + G["CC"] @ p - yC
    q = 2 * (Btg + rig._St(Ctg, w)) + alpha
    gl = 0.0
    if rig.n_pairs:  # g_i is needed only where D^(i) != 0 (elsewhere lambda_M = 0)
        cr = rig._corrective_rows
        g = cr["B"] @ w + cr["C"] @ p - b[cr["rows"]]
        gl = float(g @ np.where(g < 0, cr["lam_min"], cr["lam_max"]))
    r = 2 * (gl + rig.jacobian_fro2(w))
    g2 = w @ Btg + p @ Ctg - (yB @ w + yC @ p - b @ b)  # ||g||^2 = (Bw + Cp - b)^T g
    return q, r, rig.s_coefficient, float(g2 + alpha * np.sum(w))


def mm_surrogate(rig: QuadraticRig, w, v, target, alpha: float) -> float:
    """ψ(v; w) of eq. 15–16, evaluated literally coordinate by coordinate (for checking).

    .. math::

        \\psi(\\mathbf v) = \\sum_{i=1}^{3n}\\Big[g_i^2 + 2g_i\\mathbf h_i\\mathbf v
          + 2\\big(g_i\\lambda_M(\\mathbf D^{(i)}, g_i) + \\|\\mathbf h_i\\|^2\\big)\\|\\mathbf v\\|^2
          + 2m\\sigma^2(\\mathbf D^{(i)})\\sum_j v_j^4\\Big] + \\alpha\\mathbf 1^T(\\mathbf w + \\mathbf v)

    Parameters
    ----------
    w, v : array_like, shape (m,)
    target : array_like, shape (N, 3) or (3N,)
    """
    w = np.asarray(w, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    g = rig.evaluate_flat(w) - np.asarray(target, dtype=np.float64).reshape(-1)
    H = rig.jacobian(w)
    lam = np.where(g < 0, rig.lam_min, rig.lam_max)
    m = rig.n_shapes
    psi_i = (g**2 + 2 * g * (H @ v) + 2 * (g * lam + np.sum(H**2, axis=1)) * (v @ v)
             + 2 * m * rig.sigma**2 * np.sum(v**4))
    return float(psi_i.sum() + alpha * np.sum(w + v))


def mm_frame(rig: QuadraticRig, b, w0, *, alpha: float, tol: float, max_iter: int, bt=None, history=None):
    """Algorithm 2 for one frame: repeat Algorithm 1 (inner iteration) until convergence.

    Each iteration computes q, r, s (eq. 18), the increment
    :math:`\\hat v_j = \\arg\\min qv + rv^2 + sv^4` on :math:`[-w_j, 1-w_j]`
    for every j independently (eq. 17, :func:`quartic_argmin`), and
    :math:`\\mathbf w \\leftarrow \\mathbf w + \\hat{\\mathbf v}`. It stops when
    :math:`|\\psi(\\hat{\\mathbf v}) - \\psi(\\mathbf 0)| < \\epsilon` or after
    ``max_iter`` iterations. Here :math:`\\epsilon = \\text{tol} \\cdot \\psi(\\mathbf 0)`
    (relative, so that one setting fits any mesh unit).

    Parameters
    ----------
    b : ndarray, shape (3N,)
        Target minus neutral.
    w0 : ndarray, shape (m,), in [0, 1]
    history : list, optional
        Receives the objective (eq. 8) before the first and after every iteration.

    Returns
    -------
    w : ndarray, shape (m,)
    iterations : int
    """
    w = np.clip(np.asarray(w0, dtype=np.float64), 0.0, 1.0)
    it = 0
    while it < max_iter:
        it += 1
        q, r, s, obj = mm_coefficients(rig, w, b, alpha, bt=bt)  # obj = ψ(0) = eq. 8 at w_(t)
        if history is not None:
            history.append(obj)
        v = quartic_argmin(q, r, s, -w, 1.0 - w)
        dpsi = float(np.sum(q * v + r * v**2 + s * v**4))  # ψ(v̂) − ψ(0) <= 0
        w = np.clip(w + v, 0.0, 1.0)
        if abs(dpsi) < tol * obj:
            break
    if history is not None:
        history.append(rig.objective(w, b + rig.b0, alpha))
    return w, it


# --------------------------------------------------------------------------- linear baselines


def _ridge(rig: QuadraticRig, Y: np.ndarray, alpha: float) -> np.ndarray:
    """Eq. 6 for every frame: rows of Y are ``Bᵀb``; returns unclipped (T, m)."""
    from scipy import linalg

    A = rig.gram["BB"] + alpha * np.eye(rig.n_shapes)
    try:
        return linalg.solve(A, Y.T, assume_a="pos").T
    except (linalg.LinAlgError, ValueError):
        return linalg.lstsq(A, Y.T)[0].T


def _sequential(rig: QuadraticRig, Y: np.ndarray, alpha: float) -> np.ndarray:
    """Seol et al. eq. 7 for every frame (rows of Y are ``Bᵀb``).

    Shapes are visited once, in decreasing mean per-vertex offset; shape k gets
    :math:`\\arg\\min_{0\\le w\\le1}\\|w\\Delta b_k - \\hat b^{(k)}\\|^2 + \\alpha w` where
    :math:`\\hat b^{(k)}` is the target minus the shapes already fitted (step 2).
    In Gram form: :math:`\\langle\\Delta b_k, \\hat b^{(k)}\\rangle = (B^T\\hat b)_k - G_{k\\cdot}\\mathbf w`.
    """
    G = rig.gram["BB"]
    mean_offset = np.linalg.norm(rig.B.reshape(rig.n_vertices, 3, -1), axis=1).mean(axis=0)
    W = np.zeros_like(Y)
    for k in np.argsort(-mean_offset, kind="stable"):
        if G[k, k] <= 0:
            continue
        W[:, k] = np.clip((Y[:, k] - W @ G[k] - alpha / 2) / G[k, k], 0.0, 1.0)
    return W


def _bounded_factory(rig: QuadraticRig, alpha: float):
    """Per-frame exact solver of eq. 8 for the linear rig, via BVLS on the (m, m) reduced system.

    With :math:`G = B^TB = U\\Lambda U^T`, :math:`A = \\Lambda^{1/2}U^T` and
    :math:`y = \\Lambda^{-1/2}U^T(B^T\\hat b - \\tfrac\\alpha2\\mathbf 1)`,
    :math:`\\|A\\mathbf w - y\\|^2 = \\|B\\mathbf w - \\hat b\\|^2 + \\alpha\\mathbf 1^T\\mathbf w + \\text{const}`.
    """
    from scipy.optimize import lsq_linear

    lam, U = np.linalg.eigh(rig.gram["BB"])
    keep = lam > 1e-12 * max(lam.max(initial=0.0), 1e-300)
    if not np.all(keep):
        log.warning("bounded: B has rank %d < %d shapes; the alpha term is projected on its range",
                    int(keep.sum()), rig.n_shapes)
    sq = np.sqrt(lam[keep])
    A = sq[:, None] * U[:, keep].T
    Pm = U[:, keep].T / sq[:, None]

    def one(yB: np.ndarray):
        res = lsq_linear(A, Pm @ (yB - alpha / 2), bounds=(0.0, 1.0), method="bvls")
        return np.clip(res.x, 0.0, 1.0), int(res.nit)

    return one


# --------------------------------------------------------------------------- our faster solver


def _lbfgsb_frame(rig: QuadraticRig, bt, bb: float, w0, *, alpha: float, tol: float, max_iter: int):
    """Eq. 8 by L-BFGS-B with the analytic gradient, in Gram (reduced) form.

    With :math:`\\mathbf p = (w_iw_j)_{(i,j)\\in\\mathcal P}` and the residual
    :math:`\\mathbf r = B\\mathbf w + C\\mathbf p - \\hat b`:
    :math:`B^T\\mathbf r = G_{BB}\\mathbf w + G_{BC}\\mathbf p - B^T\\hat b`,
    :math:`C^T\\mathbf r = G_{BC}^T\\mathbf w + G_{CC}\\mathbf p - C^T\\hat b`,
    :math:`\\|\\mathbf r\\|^2 = \\mathbf w^TB^T\\mathbf r + \\mathbf p^TC^T\\mathbf r - \\hat b^T\\mathbf r` and
    :math:`\\nabla = 2(B^T\\mathbf r + S(\\mathbf w)^TC^T\\mathbf r) + \\alpha`.
    Each evaluation costs :math:`O(m^2 + mP + P^2)`, independent of the
    vertex count. It stops when an iteration lowers the objective by less
    than ``tol`` times the objective (or the projected gradient falls below
    ``1e-12·f(w0)``).
    """
    from scipy.optimize import minimize

    G = rig.gram
    yB, yC = bt
    pairs = rig.pairs

    def fg(w):
        p = w[pairs[:, 0]] * w[pairs[:, 1]]
        Btr = G["BB"] @ w + G["BC"] @ p - yB
        Ctr = G["BC"].T @ w + G["CC"] @ p - yC
        btr = yB @ w + yC @ p - bb
        f = w @ Btr + p @ Ctr - btr + alpha * w.sum()
        grad = 2 * (Btr + rig._St(Ctr, w)) + alpha
        return f, grad

    w0 = np.clip(np.asarray(w0, dtype=np.float64), 0.0, 1.0)
    f0 = fg(w0)[0]
    # L-BFGS-B's own test, (f_k − f_{k+1}) ≤ ftol·max(|f_k|, |f_{k+1}|, 1), is absolute once f < 1: on
    # f / f(w0) it stops at a decrease below tol·f(w0). The documented test, a decrease below
    # tol × objective, is made in the callback instead (ftol off); the objective is still scaled by
    # 1/f(w0) so that the gradient test (projected gradient ≤ 1e-12·f(w0)) has no mesh units.
    scale = 1.0 / f0 if f0 > 0 else 1.0
    last = [f0 * scale]

    def stop(intermediate_result):
        f = float(intermediate_result.fun)
        if last[0] - f <= tol * abs(f):
            raise StopIteration
        last[0] = f

    res = minimize(lambda w: tuple(x * scale for x in fg(w)), w0, jac=True, method="L-BFGS-B",
                   bounds=[(0.0, 1.0)] * rig.n_shapes, callback=stop,
                   options={"maxiter": max_iter, "ftol": 0.0, "gtol": 1e-12, "maxcor": 20})
    return np.clip(res.x, 0.0, 1.0), int(res.nit)


# --------------------------------------------------------------------------- driver


@dataclass
class InverseRigResult:
    """Weights and per-frame metrics of :func:`solve`.

    Attributes
    ----------
    weights : ndarray, shape (T, m), in [0, 1]
    rmse : ndarray, shape (T,)
        :math:`\\sqrt{\\tfrac1N\\sum_v\\|f_Q(\\mathbf w)_v - \\hat{\\mathbf b}_v\\|^2}`, mesh units
        (the quadratic rig is evaluated whatever the solver).
    cardinality : ndarray of int, shape (T,)
        Number of weights above :data:`CARDINALITY_THRESHOLD`.
    objective : ndarray, shape (T,)
        Eq. 8 at the returned weights.
    iterations : ndarray of int, shape (T,)
    seconds : ndarray, shape (T,)
        Wall time per frame (vectorised solvers: total / T).
    """

    weights: np.ndarray
    rmse: np.ndarray
    cardinality: np.ndarray
    objective: np.ndarray
    iterations: np.ndarray
    seconds: np.ndarray


def metrics(rig: QuadraticRig, weights, targets, alpha: float):
    """Per-frame RMSE, cardinality and objective (eq. 8) of weights against targets.

    Parameters
    ----------
    weights : ndarray, shape (T, m)
    targets : ndarray, shape (T, N, 3)

    Returns
    -------
    rmse, cardinality, objective : ndarray, shape (T,)
    """
    W = np.asarray(weights, dtype=np.float64)
    R = rig.evaluate_flat(W) - np.asarray(targets, dtype=np.float64).reshape(len(W), -1)
    sq = np.einsum("ti,ti->t", R, R)
    return (np.sqrt(sq / rig.n_vertices), (W > CARDINALITY_THRESHOLD).sum(axis=1),
            sq + alpha * W.sum(axis=1))


def _check_solve_args(rig: QuadraticRig, X: np.ndarray, solver: str, alpha: float, tol: float,
                      max_iter: int) -> None:
    """Refuse targets *X* (T, N, 3) that do not match *rig*, and out-of-range settings of :func:`solve`."""
    if X.shape[1:] != (rig.n_vertices, 3):
        raise ShapeError(f"targets: expected shape (T, {rig.n_vertices}, 3) to match the rig, got {X.shape}")
    if solver not in SOLVERS:
        raise ParameterError(f"solver: expected one of {', '.join(SOLVERS)}, got {solver!r}")
    if not (np.isfinite(alpha) and alpha >= 0):
        raise ParameterError(f"alpha: expected a number >= 0, got {alpha!r}")
    if not (np.isfinite(tol) and tol > 0):
        raise ParameterError(f"tol: expected a number > 0, got {tol!r}")
    if int(max_iter) < 1:
        raise ParameterError(f"max_iter: expected an integer >= 1, got {max_iter!r}")


def _check_init(rig: QuadraticRig, init) -> np.ndarray | None:
    """*init* as a float array of shape (m,), finite; None stays None."""
    if init is None:
        return None
    init = np.asarray(init, dtype=np.float64)
    if init.shape != (rig.n_shapes,) or not np.all(np.isfinite(init)):
        raise ShapeError(f"init: expected shape ({rig.n_shapes},) finite, got {init.shape}")
    return init


def solve(rig: QuadraticRig, targets, *, solver: str = DEFAULT_SOLVER, alpha: float = DEFAULT_ALPHA,
          tol: float = DEFAULT_TOL, max_iter: int = DEFAULT_MAX_ITER, init=None,
          callback: Callable[[int], None] | None = None, history: list | None = None) -> InverseRigResult:
    """Slider weights in [0, 1] that reproduce each target mesh (the inverse rig, eq. 8).

    Parameters
    ----------
    rig : QuadraticRig
    targets : array_like, shape (T, N, 3)
        Target meshes in the rig's vertex order and units.
    solver : {"lbfgsb", "mm", "bounded", "ridge", "sequential"}
        See the module docstring.
    alpha : float >= 0
        α of eq. 8 (``ridge``: α of eq. 5–6).
    tol : float > 0
        ``mm`` and ``lbfgsb`` stop when an iteration lowers the objective by
        less than ``tol`` times its value.
    max_iter : int >= 1
        ``mm``: T of Algorithm 2; ``lbfgsb``: iteration cap per frame.
    init : array_like, shape (m,), optional
        Start of the first frame (``lbfgsb``) or of every frame (``mm``);
        default the clipped ridge solution (eq. 6), as in the paper.
        ``lbfgsb`` starts every later frame from the previous frame's answer.
    callback : callable, optional
        Called with 1 after each frame (progress).
    history : list, optional
        ``mm`` only: receives, per frame, the list of objective values (eq. 8)
        before every iteration and at the end.

    Returns
    -------
    InverseRigResult
    """
    X = check_array(targets, "targets", ndim=3)
    _check_solve_args(rig, X, solver, alpha, tol, max_iter)
    max_iter = int(max_iter)
    init = _check_init(rig, init)
    tick = callback or (lambda n: None)
    T, m = X.shape[0], rig.n_shapes
    Bmat = X.reshape(T, -1) - rig.b0  # targets minus neutral
    t_start = time.perf_counter()
    _ = rig.gram  # precompute once per rig (not timed per frame below)
    Y = Bmat @ rig.B  # (T, m): Bᵀb per frame
    W = np.zeros((T, m))
    iters = np.zeros(T, dtype=np.int64)
    secs = np.zeros(T)
    if solver in ("ridge", "sequential"):
        W = np.clip(_ridge(rig, Y, alpha), 0, 1) if solver == "ridge" else _sequential(rig, Y, alpha)
        iters[:] = 1
        secs[:] = (time.perf_counter() - t_start) / T
        for _t in range(T):
            tick(1)
    else:
        YC = np.asarray((rig.C.T @ Bmat.T).T) if rig.n_pairs else np.zeros((T, 0))
        one = _bounded_factory(rig, alpha) if solver == "bounded" else None
        if solver == "lbfgsb":
            import scipy.optimize  # noqa: F401  (imported once, outside the per-frame timing)
        prev = init
        for t in range(T):
            t0 = time.perf_counter()
            if solver == "bounded":
                W[t], iters[t] = one(Y[t])
            else:
                w0 = prev if prev is not None else np.clip(_ridge(rig, Y[t:t + 1], alpha)[0], 0, 1)
                if solver == "mm":
                    h = [] if history is not None else None
                    W[t], iters[t] = mm_frame(rig, Bmat[t], w0, alpha=alpha, tol=tol, max_iter=max_iter,
                                              bt=(Y[t], YC[t]), history=h)
                    if h is not None:
                        history.append(h)
                else:
                    W[t], iters[t] = _lbfgsb_frame(rig, (Y[t], YC[t]), float(Bmat[t] @ Bmat[t]), w0,
                                                   alpha=alpha, tol=tol, max_iter=max_iter)
                    prev = W[t]
            secs[t] = time.perf_counter() - t0
            tick(1)
        if solver == "mm" and np.any(iters >= max_iter):
            log.warning("mm: %d of %d frames stopped at max_iter=%d before reaching tol=%g; raise --max-iter",
                        int(np.sum(iters >= max_iter)), T, max_iter, tol)
    rmse, card, obj = metrics(rig, W, X, alpha)
    return InverseRigResult(W, rmse, card, obj, iters, secs)


__all__ = [
    "CARDINALITY_THRESHOLD", "DEFAULT_ALPHA", "DEFAULT_MAX_ITER", "DEFAULT_SOLVER", "DEFAULT_TOL", "SOLVERS",
    "InverseRigResult", "QuadraticRig", "metrics", "mm_coefficients", "mm_frame", "mm_surrogate",
    "quartic_argmin", "solve",
]
