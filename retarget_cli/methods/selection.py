"""Key-shape selection (Chuang & Bregler 2002, §4.2).

Key shapes are frames of the take. The artist sculpts one target shape per
key, so keys are chosen to cover the take's shape variation with as few frames
as possible, and each choice is scored by the reconstruction error E (eq. 5).

Methods (all honour ``include``, frames that must be keys and count towards k):

- ``pca-extremes``: maximum spread along principal components (the paper's best);
- ``kmeans``: k-means in the first 2 or 3 principal components, key = the
  actual frame nearest each centroid (the paper's "clustering");
- ``convex-hull``: frames on the convex hull in the first 2 principal
  components; the number of keys is set by the data, not by k;
- ``greedy``: forward selection of the frame that most reduces E (eq. 5);
- ``greedy-swap``: greedy, then exchange passes that replace a key whenever a
  swap lowers E.

Invariance: the PCA-based methods use PCA scores with a sign convention fixed on
the scores themselves, so they are invariant to any translation and rotation of
the landmarks. ``greedy`` and ``greedy-swap`` measure E after subtracting the
take's mean landmark position (one point for the whole take): eq. 3 has no
offset term, so E on raw pixel coordinates depends on where the image origin
is; centred, E is invariant to translating and rotating the landmarks.
"""

from __future__ import annotations

import logging

import numpy as np

from .._validate import check_array
from ..errors import ParameterError, ShapeError
from .blas import small_blas
from .decomposition import reconstruction_error

log = logging.getLogger(__name__)

#: Selection methods available to :func:`select_keys`.
METHODS = ("pca-extremes", "kmeans", "convex-hull", "greedy", "greedy-swap")

#: Candidates evaluated exactly per greedy step (ranked by an exact lower bound on their gain).
GREEDY_SCREEN = 16
#: Frames of a take whose ranking products greedy's screen forms at once, 512 candidates by this many frames
#: (float32, 16 MB): a longer take's are summed block by block, so that its memory does not grow as T².
RANK_COLUMNS = 8192
#: Screened candidates whose trial solves are formed and solved at once (:meth:`_Greedy.try_many`): each holds
#: its frames' rows and weights, (k + 1) values a frame several times over, so a long take's step holds this
#: many candidates' copies, not the whole screen's. The keys do not depend on it.
TRIALS_AT_ONCE = 4


# --------------------------------------------------------------------------- shared checks


def _check(features, k, include, *, need_k=True):
    """Validated features, the include list and the per-frame distinct-shape id."""
    X = check_array(features, "features", ndim=2)
    T = X.shape[0]
    if need_k and (isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1):
        raise ShapeError(f"k: expected an integer k >= 1, got {k!r}")
    if not np.any(np.abs(X - X.mean(0)) > 1e-9):
        raise ShapeError("features: every frame has the same shape (no variation to choose keys from)")
    _, first, uid = np.unique(X.round(6), axis=0, return_index=True, return_inverse=True)
    uid = uid.ravel()
    n_distinct = len(first)
    if need_k and k > n_distinct:
        raise ShapeError(f"k: {k} keys requested but the take has only {n_distinct} distinct frames")
    inc: list[int] = []
    for f in include:
        if isinstance(f, bool) or not isinstance(f, (int, np.integer)) or not 0 <= int(f) < T:
            raise ShapeError(f"include: frame {f!r} is outside the take (0..{T - 1})")
        if all(uid[int(f)] != uid[g] for g in inc):
            inc.append(int(f))
    return X, inc, uid


def _pca_scores(X, n: int) -> np.ndarray:
    """PCA scores (T, n) with each component's sign fixed by its scores.

    The frame with the largest absolute score gets a positive score (ties to
    the lower frame index), so the result does not depend on the arbitrary
    sign of the SVD and is unchanged when the landmarks are rotated.
    """
    from sklearn.decomposition import PCA

    n = int(min(n, X.shape[0], X.shape[1]))
    S = PCA(n_components=n, svd_solver="full").fit_transform(X)
    idx = np.argmax(np.abs(S).round(9), axis=0)
    sign = np.sign(S[idx, np.arange(n)])
    sign[sign == 0] = 1
    return S * sign


def _ties(v, scale) -> np.ndarray:
    """*v* rounded to 1e-9 of *scale*, so exact ties stay ties under floating-point noise
    (they are then broken by the lower frame index)."""
    return np.round(np.asarray(v) / max(float(scale), 1e-300), 9)


def _centre(X, point_dim: int) -> np.ndarray:
    """Subtract the take's mean point (one ``point_dim`` vector for every frame and landmark)."""
    if point_dim < 1 or X.shape[1] % point_dim:
        raise ShapeError(f"features: expected (T, L*{point_dim}) flattened points, got shape {X.shape}")
    return X - X.reshape(len(X), -1, point_dim).mean((0, 1)).tolist() * (X.shape[1] // point_dim)


# --------------------------------------------------------------------------- PCA extremes


def pca_extremes(features, k: int, *, include=()) -> np.ndarray:
    """Frames of maximum and minimum projection on the principal axes.

    "Maximum spread along principal components" (Chuang & Bregler 2002,
    §4.2): starting from the axis of largest variance, the frames with the
    largest and smallest projection become keys, so k keys use about k/2 axes.
    A frame already chosen (or with the same shape as one) is skipped and the
    next axis supplies the remaining keys, so the result always holds k
    distinct frames; for odd k the last axis contributes only its maximum.

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
    X, chosen, uid = _check(features, k, include)
    T = X.shape[0]
    chosen = chosen[:k]
    if len(chosen) == k:
        return np.array(chosen)
    proj = _pca_scores(X, min(T, X.shape[1]))
    used = {int(uid[f]) for f in chosen}
    for axis in range(proj.shape[1]):
        # Stable order: ties broken by the lower frame index.
        p = _ties(proj[:, axis], np.abs(proj).max())
        order_max = np.lexsort((np.arange(T), -p))
        order_min = np.lexsort((np.arange(T), p))
        for order in (order_max, order_min):
            for f in order:
                if int(uid[f]) not in used:
                    chosen.append(int(f))
                    used.add(int(uid[f]))
                    break
            if len(chosen) == k:
                return np.array(chosen)
    # Fewer useful axes than k/2: fill with frames farthest from the chosen set.
    return np.array(_farthest_fill(X, chosen, uid, k))


def _farthest_fill(X, chosen, uid, k) -> list[int]:
    chosen = list(chosen)
    d = np.min(np.linalg.norm(X[:, None, :] - X[None, chosen, :], axis=2), axis=1)
    while len(chosen) < k:
        used = np.isin(uid, uid[chosen])
        f = int(np.argmax(np.where(used, -1.0, d)))
        chosen.append(f)
        d = np.minimum(d, np.linalg.norm(X - X[f], axis=1))
    return chosen


# --------------------------------------------------------------------------- clustering


def kmeans_keys(features, k: int, *, components: int = 2, include=(), seed: int = 0) -> np.ndarray:
    """k-means in the first principal components; a key is the frame nearest a centroid.

    "Clustering" of Chuang & Bregler (2002, §4.2) with 2 or 3 principal
    components. The paper takes each cluster's centre of mass; here the key
    is the actual frame nearest each centroid (in PCA space), because the
    artist needs a real frame to sculpt. Frames in *include* stand for the
    cluster they fall in; the other clusters, largest first, each supply the
    unused frame nearest their centroid until there are k keys.

    Parameters
    ----------
    features : ndarray, shape (T, D)
    k : int
    components : int
        Principal components clustered (the paper reports 2 and 3).
    include : sequence of int
    seed : int
        ``random_state`` of :class:`sklearn.cluster.KMeans`.

    Returns
    -------
    ndarray of int, shape (k,)
        Frame indices: *include* first, then one per cluster.
    """
    X, chosen, uid = _check(features, k, include)
    if components < 1:
        raise ShapeError(f"components: expected >= 1, got {components}")
    chosen = chosen[:k]
    if len(chosen) == k:
        return np.array(chosen)
    import warnings

    from sklearn.cluster import KMeans
    from sklearn.exceptions import ConvergenceWarning

    Z = _pca_scores(X, components)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)  # fewer distinct points than k: filled below
        km = KMeans(n_clusters=k, n_init=10, random_state=seed).fit(Z)
    covered = {int(km.labels_[f]) for f in chosen}
    sizes = np.bincount(km.labels_, minlength=k)
    used = {int(uid[f]) for f in chosen}
    for c in np.lexsort((np.arange(k), -sizes)):
        if len(chosen) == k:
            break
        if int(c) in covered:
            continue
        d = _ties(np.linalg.norm(Z - km.cluster_centers_[c], axis=1), np.abs(Z).max())
        for f in np.lexsort((np.arange(len(d)), d)):
            if int(uid[f]) not in used:
                chosen.append(int(f))
                used.add(int(uid[f]))
                break
    if len(chosen) < k:
        chosen = _farthest_fill(X, chosen, uid, k)
    return np.array(chosen)


# --------------------------------------------------------------------------- convex hull


def convex_hull_keys(features, *, include=()) -> np.ndarray:
    """Frames on the convex hull of the take in its first two principal components.

    "Convex hull" of Chuang & Bregler (2002, §4.2): every other frame lies
    inside the hull, so it should be an interpolation of the hull frames. The
    number of keys is the number of hull vertices (plus *include*); the user
    does not choose it. The paper uses 2 components because in 3 or more
    nearly every frame lies on the hull.

    Parameters
    ----------
    features : ndarray, shape (T, D)
    include : sequence of int

    Returns
    -------
    ndarray of int, shape (n,)
        *include* first, then the hull vertices counter-clockwise.
    """
    X, chosen, uid = _check(features, None, include, need_k=False)
    from scipy.spatial import ConvexHull, QhullError

    Z = _pca_scores(X, 2)
    try:
        if Z.shape[1] < 2:
            raise QhullError("one component")
        hull = list(ConvexHull(Z).vertices)
    except QhullError:  # all frames on a line: its two ends
        hull = [int(np.argmax(Z[:, 0])), int(np.argmin(Z[:, 0]))]
    used = {int(uid[f]) for f in chosen}
    for f in hull:
        if int(uid[f]) not in used:
            chosen.append(int(f))
            used.add(int(uid[f]))
    return np.array(chosen)


# --------------------------------------------------------------------------- greedy (eq. 5)


def _masked_solve(G, b, P):
    """Solve ``G_PP z_P = b_P`` per row of *b* (z = 0 outside the passive set P)."""
    A = G[None] * (P[:, :, None] & P[:, None, :])
    idx = np.arange(G.shape[0])
    A[:, idx, idx] += ~P
    rhs = np.where(P, b, 0.0)
    try:
        return np.linalg.solve(A, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return np.stack([np.linalg.lstsq(a, r, rcond=None)[0] for a, r in zip(A, rhs)]) * P


def _nnls_gram(G, b, w0, max_iter=None, *, warm_optimal=False):
    """Exact batched NNLS in Gram form, warm-started (Lawson & Hanson 1974).

    Minimises ``w' G w - 2 b' w`` subject to ``w >= 0`` for every row of *b*,
    i.e. ``||q - B' w||^2`` with ``G = B B'`` and ``b = B q`` (eq. 4). The
    passive set starts at the support of the feasible *w0*, so adding one
    column to a solved problem usually costs one or two iterations.

    Parameters
    ----------
    G : ndarray, shape (k, k)
    b : ndarray, shape (n, k)
    w0 : ndarray, shape (n, k), non-negative
    warm_optimal : bool
        *w0* is already the least-squares solution on its support (a solved
        problem plus new zero columns): skip the first inner solve.

    Returns
    -------
    w : ndarray, shape (n, k)
    ok : ndarray of bool, shape (n,)
        False where the iteration cap was reached.
    """
    n, k = b.shape
    w = w0.copy()
    P = w > 0
    scale = max(float(np.max(np.diag(G))), 1e-300)
    tol = 1e-11 * scale
    max_iter = max_iter or 3 * k + 10
    rows = np.arange(n)
    ok = np.ones(n, bool)

    def feasible(rows):
        # Inner loop: least squares on P, stepping back to the boundary while infeasible.
        for _ in range(k + 1):
            z = _masked_solve(G, b[rows], P[rows])
            bad = P[rows] & (z <= 0)
            nb = bad.any(1)
            good = rows[~nb]
            w[good] = np.where(P[good], z[~nb], 0.0)
            if not nb.any():
                return
            r, zb, wb = rows[nb], z[nb], w[rows[nb]]
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.where(bad[nb], wb / (wb - zb), np.inf)
            alpha = np.clip(ratio.min(1), 0.0, 1.0)[:, None]
            w[r] = np.where(P[r], wb + alpha * (zb - wb), 0.0)
            P[r] &= w[r] > 1e-14 * np.maximum(1.0, np.abs(w[r]).max(1, keepdims=True))
            w[r] = np.where(P[r], w[r], 0.0)
            rows = r

    if not warm_optimal:
        feasible(rows)
    for _ in range(max_iter):
        grad = b[rows] - w[rows] @ G
        cand = ~P[rows] & (grad > tol)
        go = cand.any(1)
        rows = rows[go]
        if not len(rows):
            return w, ok
        j = np.argmax(np.where(cand[go], grad[go], -np.inf), axis=1)
        P[rows, j] = True
        feasible(rows)
    ok[rows] = False
    return w, ok


class _Greedy:
    """State of forward selection: keys, NNLS weights and errors of every frame, in Gram form."""

    def __init__(self, X, uid):
        self.X, self.uid = X, uid
        self.norm2 = np.einsum("td,td->t", X, X)
        _, first = np.unique(uid, return_index=True)
        self.reps = np.sort(first)  # one frame per distinct shape
        self.set_keys([])

    def _solve(self, G, b, W0, rows, *, warm_optimal=False):
        """Exact NNLS weights and errors of *rows* given Gram *G* and ``b = X[rows] B'``."""
        W, ok = _nnls_gram(G, b, W0, warm_optimal=warm_optimal)
        if not ok.all():  # iteration cap: scipy for those frames
            from scipy.optimize import nnls

            B = self.X[self.keys_for_G]
            for i in np.flatnonzero(~ok):
                W[i] = nnls(B.T, self.X[rows[i]], maxiter=100 * len(B))[0]
        err = self.norm2[rows] - 2 * np.einsum("tk,tk->t", W, b) + np.einsum("tk,tk->t", W @ G, W)
        return W, np.maximum(err, 0.0)

    def set_keys(self, keys):
        self.keys = [int(f) for f in keys]
        T = len(self.X)
        self.XB = self.X @ self.X[self.keys].T if self.keys else np.zeros((T, 0))
        self.G = self.XB[self.keys]
        self.keys_for_G = self.keys
        if self.keys:
            self.W, self.err = self._solve(self.G, self.XB, np.zeros((T, len(self.keys))), np.arange(T))
        else:
            self.W, self.err = np.zeros((T, 0)), self.norm2.copy()

    def try_add(self, c, xc):
        """E after adding frame *c* (``xc = X @ X[c]``); only frames whose optimality
        condition the new key violates can change (KKT), the others keep their error."""
        corr = xc - self.W @ self.XB[c]
        rows = np.flatnonzero(corr > 1e-11 * self.norm2.max())
        if not len(rows):
            return float(self.err.sum()), None
        G = np.block([[self.G, self.XB[c][:, None]], [self.XB[c][None, :], self.norm2[c]]])
        b = np.hstack([self.XB[rows], xc[rows, None]])
        W0 = np.hstack([self.W[rows], np.zeros((len(rows), 1))])
        self.keys_for_G = self.keys + [c]
        W, e = self._solve(G, b, W0, rows, warm_optimal=True)
        return float(self.err.sum() - self.err[rows].sum() + e.sum()), (rows, W, e, G, xc)

    def add(self, c, update, xc):
        T = len(self.X)
        W = np.hstack([self.W, np.zeros((T, 1))])
        err = self.err.copy()
        if update is not None:
            rows, Wr, e, _, _ = update
            W[rows], err[rows] = Wr, e
        self.G = np.block([[self.G, self.XB[c][:, None]], [self.XB[c][None, :], self.norm2[c]]])
        self.XB = np.hstack([self.XB, xc[:, None]])
        self.keys.append(int(c))
        self.W, self.err = W, err

    def best_addition(self, screen):
        """The candidate whose addition gives the lowest E: (frame, E, update, X @ X[frame])."""
        X = self.X
        used = set(int(self.uid[f]) for f in self.keys)
        cands = np.array([f for f in self.reps if int(self.uid[f]) not in used])
        R = X - self.W @ X[self.keys] if self.keys else X
        # Ranking score: the gain of the candidate's direction orthogonal to the current keys,
        # ``c_perp = x_c - B' G^-1 B x_c``, with a non-negative weight while the other weights
        # follow by least squares. Cheap (one (T x T x D) product) and, unlike holding the other
        # weights fixed, it sees that a new key mostly replaces part of the neutral's weight.
        lower = np.empty(len(cands))
        X32, R32 = X[cands].astype(np.float32), R.T.astype(np.float32)  # ranking only: float32 is enough
        if self.keys:
            Gi = np.linalg.pinv(self.G)
            A = self.XB[cands] @ Gi  # (C, k)
            H = (self.XB - self.W @ self.G).astype(np.float32)  # (T, k): r_t . x_key
            den = self.norm2[cands] - np.einsum("ck,ck->c", A, self.XB[cands])
        else:
            A, H, den = np.zeros((len(cands), 0)), np.zeros((len(X), 0), np.float32), self.norm2[cands]
        den = np.maximum(den, 1e-12 * self.norm2.max())
        # blocks of 512 candidates by RANK_COLUMNS frames: a long take's (candidates, T) product is never held
        # (a take of at most RANK_COLUMNS frames is one block of columns, as before)
        for s in range(0, len(cands), 512):
            A32 = A[s:s + 512].astype(np.float32)
            acc = np.zeros(len(X32[s:s + 512]), np.float32)
            for t in range(0, len(X), RANK_COLUMNS):
                C = np.maximum(X32[s:s + 512] @ R32[:, t:t + RANK_COLUMNS] - A32 @ H[t:t + RANK_COLUMNS].T, 0)
                acc += np.einsum("ct,ct->c", C, C)
            lower[s:s + 512] = acc / den[s:s + 512]
        order = np.lexsort((cands, -lower))
        if screen is not None:
            order = order[:screen]
        best = None
        for s in range(0, len(order), TRIALS_AT_ONCE):
            sel = cands[order[s:s + TRIALS_AT_ONCE]]
            XC = X @ X[sel].T
            trials = self.try_many(sel, XC) if self.BATCHED else (self.try_add(int(c), XC[:, j])
                                                                 for j, c in enumerate(sel))
            for j, (E, upd) in enumerate(trials):
                if best is None or E < best[1] - 1e-12 * max(best[1], 1.0):
                    best = (int(sel[j]), E, upd, XC[:, j].copy())
        return best

    #: Score candidates by :meth:`try_many` (all at once) rather than one :meth:`try_add` each (the reference).
    BATCHED = True

    def try_many(self, sel, XC):
        """:meth:`try_add` for every candidate in *sel* at once (``XC = X @ X[sel].T``, shape (T, n)).

        The same problems and the same Lawson-Hanson iteration, warm-started from the current
        weights, on the same frames (those whose optimality condition the candidate violates),
        all candidates' frames solved by one call of a compiled kernel
        (:func:`retarget_cli.methods.decomposition._qp_kernel.nnls_gram_pairs`; a frame it cannot
        settle goes to :meth:`try_add`'s numpy iteration). Returns a list of (E, update), one per candidate.
        """
        from .decomposition._qp_kernel import nnls_gram_pairs

        k = len(self.keys)
        thr = 1e-11 * self.norm2.max()
        tried, Gs, which, Bs, Ws = [], [], [], [], []
        for j, c in enumerate(sel):
            c = int(c)
            xc = XC[:, j]
            corr = xc - self.W @ self.XB[c]
            rows = np.flatnonzero(corr > thr)
            if not len(rows):
                tried.append(None)
                continue
            which.append(np.full(len(rows), len(Gs)))
            Gs.append(np.block([[self.G, self.XB[c][:, None]], [self.XB[c][None, :], self.norm2[c]]]))
            Bs.append(np.hstack([self.XB[rows], xc[rows, None]]))
            Ws.append(np.hstack([self.W[rows], np.zeros((len(rows), 1))]))
            tried.append((c, rows, xc))
        if Gs:
            G3 = np.ascontiguousarray(Gs)
            tol = 1e-11 * np.maximum(np.einsum("nkk->nk", G3).max(1), 1e-300)
            W_all = np.concatenate(Ws)
            ok = np.empty(len(W_all), bool)
            nnls_gram_pairs(G3, np.concatenate(which), np.concatenate(Bs), W_all, tol, 3 * (k + 1) + 10, ok)
            splits = np.cumsum([len(w) for w in Ws])[:-1]
            W_parts, ok_parts = np.split(W_all, splits), np.split(ok, splits)
        out, g = [], 0
        for t in tried:
            if t is None:
                out.append((float(self.err.sum()), None))
                continue
            c, rows, xc = t
            G, b, W, done = Gs[g], Bs[g], W_parts[g], ok_parts[g]
            g += 1
            e = self.norm2[rows] - 2 * np.einsum("tk,tk->t", W, b) + np.einsum("tk,tk->t", W @ G, W)
            e = np.maximum(e, 0.0)
            if not done.all():  # not settled by the kernel: the numpy iteration, from the same start
                left = ~done
                self.keys_for_G = self.keys + [c]
                W0 = np.hstack([self.W[rows[left]], np.zeros((int(left.sum()), 1))])
                W[left], e[left] = self._solve(G, b[left], W0, rows[left], warm_optimal=True)
            out.append((float(self.err.sum() - self.err[rows].sum() + e.sum()), (rows, W, e, G, xc)))
        return out


def greedy(features, k: int, *, include=(), screen: int | None = GREEDY_SCREEN, swap: bool = False,
           point_dim: int = 2, max_passes: int = 3) -> np.ndarray:
    """Forward selection of the frames that most reduce the reconstruction error E.

    Starting from *include*, each step adds the frame ``c`` minimising

    .. math::

        E(S \\cup \\{c\\}) = \\sum_t \\min_{w \\ge 0} \\| Q_t - \\sum_{i} w_i S_i \\|^2

    (Chuang & Bregler 2002, eq. 5 with NNLS weights, eq. 4), the criterion
    the paper evaluates its heuristics by, optimised directly. E is exact:
    each candidate is scored by a warm-started Lawson-Hanson NNLS on the
    frames whose optimality conditions the new key violates (the others
    cannot change). To stay fast only the *screen* candidates with the
    largest exact lower bound on their gain (the gain of the new key's weight
    alone, the others held) are scored; ``screen=None`` scores every frame.
    The screened candidates' solves run together, one compiled call per
    :data:`TRIALS_AT_ONCE` candidates (:meth:`_Greedy.try_many`), with BLAS
    single-threaded.

    With ``swap=True`` (``greedy-swap``), exchange passes follow: each key
    (except *include*) is removed and the best frame put in its place, which
    is kept when E drops; passes repeat until none helps (at most
    *max_passes*).

    Parameters
    ----------
    features : ndarray, shape (T, L * point_dim)
        Flattened landmarks per frame. E is measured after subtracting the
        take's mean point, which makes the choice invariant to translating and
        rotating the landmarks.
    k : int
    include : sequence of int
    screen : int or None
    swap : bool
    point_dim : int
    max_passes : int

    Returns
    -------
    ndarray of int, shape (k,)
        Frame indices in the order added (after swaps, swapped keys keep their slot).
    """
    X, inc, uid = _check(features, k, include)
    if screen is not None and screen < 1:
        raise ShapeError(f"screen: expected >= 1 or None, got {screen}")
    X = _centre(X, point_dim)
    with small_blas():  # many small products and solves: BLAS threads only add overhead (and CPU)
        return _greedy(X, uid, k, inc, screen, swap, max_passes)


def _greedy(X, uid, k, inc, screen, swap, max_passes) -> np.ndarray:
    """The steps of :func:`greedy` on the centred features *X*."""
    g = _Greedy(X, uid)
    g.set_keys(inc[:k])
    while len(g.keys) < k:
        c, E, upd, xc = g.best_addition(screen)
        g.add(c, upd, xc)
        log.debug("greedy: key %d -> frame %d, E = %.6g", len(g.keys), c, E)
    if swap:
        n_inc = len(inc[:k])
        for _ in range(max_passes):
            improved = False
            for slot in range(n_inc, k):
                E_now = float(g.err.sum())
                keys = list(g.keys)
                rest = keys[:slot] + keys[slot + 1:]
                g.set_keys(rest)
                c, E, upd, xc = g.best_addition(screen)
                if E < E_now * (1 - 1e-9) and c != keys[slot]:
                    g.add(c, upd, xc)
                    keys[slot] = c
                    improved = True
                    log.debug("greedy-swap: frame %d -> %d, E %.6g -> %.6g", g.keys[-1], c, E_now, E)
                g.set_keys(keys)
            if not improved:
                break
    return np.array(g.keys)


# --------------------------------------------------------------------------- dispatch


def select_keys(features, k: int | None, *, method: str = "pca-extremes", include=(), seed: int = 0,
                components: int = 2, point_dim: int = 2) -> np.ndarray:
    """Choose *k* key frames with the named *method*.

    Parameters
    ----------
    features : ndarray, shape (T, L * point_dim)
    k : int or None
        Number of keys. ``convex-hull`` chooses its own number: *k* = None
        accepts it, another k logs a warning and is ignored.
    method : {"pca-extremes", "kmeans", "convex-hull", "greedy", "greedy-swap"}
    include : sequence of int
        Frames that must be keys (counted in k), e.g. the neutral frame: with
        the whole-shape model of eq. 3 and non-negative weights, a frame can
        only be reproduced inside the cone of the keys, so a take whose keys
        are all expressive cannot return to rest.
    seed : int
        For ``kmeans``.
    components : int
        Principal components for ``kmeans`` (2 or 3 in the paper).
    point_dim : int
        Coordinates per landmark (greedy centres the landmarks).

    Returns
    -------
    ndarray of int, shape (k,)
        Key frame indices, sorted ascending.
    """
    if method not in METHODS:
        raise ParameterError(f"method: expected one of {METHODS}, got {method!r}")
    if method == "convex-hull":
        frames = convex_hull_keys(features, include=include)
        if k is not None and k != len(frames):
            log.warning("convex-hull: the hull has %d frames; k = %d is ignored (the hull's size is not chosen)",
                        len(frames), k)
    elif k is None:
        raise ShapeError(f"k: method {method!r} needs a number of keys")
    elif method == "pca-extremes":
        frames = pca_extremes(features, k, include=include)
    elif method == "kmeans":
        frames = kmeans_keys(features, k, components=components, include=include, seed=seed)
    else:
        frames = greedy(features, k, include=include, swap=method == "greedy-swap", point_dim=point_dim)
    return np.sort(frames)


# --------------------------------------------------------------------------- evaluation (Fig. 6)

#: Curves of :func:`evaluation_curve`: label -> (method, k-means components).
CURVES = {
    "pca-extremes": ("pca-extremes", None),
    "kmeans-2pc": ("kmeans", 2),
    "kmeans-3pc": ("kmeans", 3),
    "convex-hull": ("convex-hull", None),
    "greedy": ("greedy", None),
    "greedy-swap": ("greedy-swap", None),
}


def key_error(features, frames) -> float:
    """E (eq. 5) of the key set *frames*, by :func:`retarget_cli.methods.decomposition.reconstruction_error`.

    When scipy's NNLS stops at its iteration cap (it does on some exactly
    degenerate key sets, e.g. noise-free synthetic landmarks), E comes from this
    module's exact active-set solver instead.
    """

    X = check_array(features, "features", ndim=2)
    try:
        return float(reconstruction_error(X, X[np.asarray(frames)]))
    except RuntimeError as exc:
        log.debug("reconstruction_error: %s; using the active-set solver", exc)
        g = _Greedy(X, np.arange(len(X)))
        g.set_keys(list(frames))
        return float(g.err.sum())


def evaluation_curve(features, k_max: int, *, k: int | None = None, include=(), seed: int = 0,
                     point_dim: int = 2, progress=None) -> list[dict]:
    """Reconstruction error E (eq. 5) against the number of keys for every method.

    The evaluation of Chuang & Bregler (2002, §4.2, Fig. 6): for k = 2 ... *k_max*
    each method chooses k keys and E is the sum over frames of the squared
    landmark error with NNLS weights (eq. 4), computed by
    :func:`retarget_cli.methods.decomposition.reconstruction_error` on *features* as given.
    ``convex-hull`` gives one point (its size is fixed by the data);
    ``greedy-swap`` is evaluated only at the chosen *k* (its exchange passes are
    too costly to repeat for every k). ``pca-extremes`` and ``greedy`` are
    nested (the k-key set is a prefix of the (k+1)-key one), so each is run once.

    Parameters
    ----------
    features : ndarray, shape (T, D)
    k_max : int
        Largest k, capped at the number of distinct frames.
    k : int, optional
        The chosen k (for ``greedy-swap``).
    include : sequence of int
    seed : int
    point_dim : int
    progress : callable, optional
        Called with 1 after each curve.

    Returns
    -------
    list of dict
        ``{"curve", "method", "k", "error", "frames"}`` rows.
    """
    X, _, uid = _check(features, 2, include)
    k_hi = int(min(k_max, len(np.unique(uid))))
    rows = []

    def add(label, method, frames):
        frames = np.sort(np.asarray(frames))
        rows.append({"curve": label, "method": method, "k": int(len(frames)),
                     "error": key_error(X, frames), "frames": [int(f) for f in frames]})

    for label, (method, comp) in CURVES.items():
        if method == "pca-extremes" or method == "greedy":
            order = (pca_extremes(X, k_hi, include=include) if method == "pca-extremes"
                     else greedy(X, k_hi, include=include, point_dim=point_dim))
            for kk in range(2, k_hi + 1):
                add(label, method, order[:kk])
        elif method == "kmeans":
            for kk in range(2, k_hi + 1):
                add(label, method, kmeans_keys(X, kk, components=comp, include=include, seed=seed))
        elif method == "convex-hull":
            add(label, method, convex_hull_keys(X, include=include))
        elif k is not None and 2 <= k <= k_hi:
            add(label, method, greedy(X, k, include=include, swap=True, point_dim=point_dim))
        if progress is not None:
            progress(1)
    return rows


def curve_winner(rows: list[dict], k: int) -> dict:
    """The curve with the lowest E at *k* (``convex-hull`` counts at its own size only)."""
    at = {r["curve"]: r["error"] for r in rows if r["k"] == k}
    if not at:
        raise ShapeError(f"k: no method was evaluated at k = {k}")
    best = min(sorted(at), key=lambda c: at[c])
    return {"k": k, "winner": best, "error": at[best], "errors": dict(sorted(at.items()))}
