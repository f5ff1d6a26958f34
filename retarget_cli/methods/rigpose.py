"""Posing a blendshape rig from tracked 2D landmarks: the rig as the artist.

Chuang & Bregler (2002, §5) assume an artist sculpts one target shape per
chosen source key frame. A user who owns a rig instead poses it: each key
frame's landmarks give the rig's slider values, and every frame's sliders then
follow from the decomposition weights (:func:`rig_curves`), so the output is
the rig's own animation curves.

The actor and the character have different faces, so the sliders must explain
how the actor's face *moved*, not what it looks like. :func:`delta_pose` works
in the delta form of the rig, ``f = f0 + D w`` (Lewis et al. 2005, §3; the
blendshape slides' "delta blendshape" formulation): the rig's neutral ``f0``
corresponds to the actor's neutral frame, a scaled orthographic camera is fitted
once between the rig's landmark vertices at rest and the actor's neutral
landmarks, and each key frame's landmark *displacement* from the neutral frame,
brought into rig units by that camera (per region, by the region's own scale),
is what ``D w`` must reproduce:

.. math::

    \\min_{l \\le w \\le u} \\tfrac12 \\sum_i c_i \\lVert P_r D_i w - (y_i - y^0_i) / s_r \\rVert^2
    + \\lambda\\, \\mathbf 1^T w + \\tfrac{\\mu}{2} \\lVert w \\rVert^2

(``P_r`` the camera's rotation rows, ``s_r`` the region's scale, ``c_i`` the
landmark confidences), a box-constrained QP solved exactly by
:func:`retarget_cli.methods.decomposition.box_qp`. The L1 term (``λ``, linear for sliders
that cannot go below 0) keeps sliders that do not help at 0, and pairs of
mutually exclusive sliders (jawLeft/jawRight, eyeBlink/eyeWide, …) keep at most
one member active. The neutral frame's displacement is 0, so it poses every
slider at 0. The absolute fit of the actor's landmark positions
(:func:`retarget_cli.methods.editing.auto_pose`) stays available; it turns the difference
between the two faces into expression.
"""

from __future__ import annotations

import logging

import numpy as np

from .._validate import check_array
from ..errors import InputError, ParameterError, ShapeError
from .decomposition import box_qp
from .editing import fit_orthographic

log = logging.getLogger(__name__)

#: Default L1 weight λ and ridge μ of :func:`fit_sliders`, relative to the mean diagonal of ``BᵀCB``.
#: Measured on the ICT FaceKit with the shared real clips (README, "Your video, your rig").
DEFAULT_SPARSITY = 0.01
DEFAULT_RIDGE = 0.001
#: A slider counts as active above this value when enforcing exclusive pairs.
ACTIVE = 1e-3
#: Two sliders whose landmark displacements have a cosine below this oppose each other (inferred exclusive pairs).
OPPOSING_COSINE = -0.7
#: Huber threshold of :func:`delta_pose`'s reweighting, in image pixels.
ROBUST_PX = 2.0


def rig_landmarks(rig, vertices) -> tuple[np.ndarray, np.ndarray]:
    """The rig's landmark vertices at rest and their displacement per slider.

    Parameters
    ----------
    rig : BlendshapeRig
    vertices : array_like of int, shape (L,)

    Returns
    -------
    X0 : ndarray, shape (L, 3)
        ``f0`` at the landmark vertices.
    DL : ndarray, shape (L, 3, n)
        ``D`` rows of those vertices.
    """
    v = rig.check_vertices(vertices, "landmark vertices")
    rows = rig.rows(v)
    return rig.f0[rows].reshape(len(v), 3), rig.block(rows).reshape(len(v), 3, -1)


def project(DL, R) -> np.ndarray:
    """Landmark displacements seen through the camera rotation: ``R[:2] D_i`` for each landmark.

    Parameters
    ----------
    DL : ndarray, shape (L, 3, n)
    R : ndarray, shape (3, 3)

    Returns
    -------
    ndarray, shape (L, 2, n)
    """
    return np.einsum("ba,lan->lbn", np.asarray(R)[:2], DL)


def region_scales(X0, Y0, R, s, regions, weights=None) -> np.ndarray:
    """Per-region camera scale: the actor's region size over the rig's, in the camera's view.

    For each region, the least-squares uniform scale between the rig's
    projected rest landmarks and the actor's neutral landmarks of that region,
    both centred (rotation shared with the global camera). A mouth that is
    wider on the actor than on the character, relative to the whole face, then
    opens by as much *relative to its size*.

    Parameters
    ----------
    X0 : ndarray, shape (L, 3)
    Y0 : ndarray, shape (L, 2)
        The actor's neutral landmarks (pixels).
    R : ndarray, shape (3, 3)
    s : float
        The global camera scale (pixels per rig unit), used for regions of fewer than 3 points.
    regions : list of array_like of int
        Landmark ids of each region.
    weights : array_like, shape (L,), optional

    Returns
    -------
    ndarray, shape (len(regions),)
        Pixels per rig unit, per region.
    """
    P = X0 @ np.asarray(R)[:2].T
    c = np.ones(len(X0)) if weights is None else np.asarray(weights, dtype=np.float64)
    out = np.full(len(regions), float(s))
    for i, ids in enumerate(regions):
        ids = np.asarray(ids)
        w = c[ids]
        if np.count_nonzero(w > 0) < 3:
            continue
        p = P[ids] - w @ P[ids] / w.sum()
        y = Y0[ids] - w @ Y0[ids] / w.sum()
        den = float(np.sum(w[:, None] * p * p))
        if den > 0:
            out[i] = max(float(np.sum(w[:, None] * p * y)) / den, 1e-12)
    return out


def slider_owners(B, regions, *, tiny: float = 1e-6) -> np.ndarray:
    """The region that owns each slider: the one whose landmarks it moves most.

    Parameters
    ----------
    B : ndarray, shape (L, 2, n)
        Projected landmark displacements per slider (:func:`project`).
    regions : list of array_like of int
        Landmark ids of each region.
    tiny : float
        A slider whose largest region energy is below ``tiny`` times the
        largest of any slider moves no landmark and is owned by none.

    Returns
    -------
    ndarray of int, shape (n,)
        Region index per slider, -1 for none.
    """
    E = np.stack([np.sum(B[np.asarray(ids)] ** 2, axis=(0, 1)) for ids in regions])  # (R, n)
    owner = np.argmax(E, axis=0)
    best = E[owner, np.arange(E.shape[1])]
    owner[best <= tiny * max(float(best.max(initial=0.0)), 1e-300)] = -1
    return owner


def infer_exclusive(B, names, *, cosine: float = OPPOSING_COSINE) -> list[tuple[str, str]]:
    """Pairs of sliders whose landmark displacements oppose each other (cosine below *cosine*).

    Parameters
    ----------
    B : ndarray, shape (L, 2, n)
    names : sequence of str, length n

    Returns
    -------
    list of (str, str)
    """
    M = B.reshape(-1, B.shape[-1])
    norm = np.linalg.norm(M, axis=0)
    live = norm > 1e-12 * max(float(norm.max(initial=0.0)), 1e-300)
    U = np.where(live, M / np.where(live, norm, 1.0), 0.0)
    C = U.T @ U
    i, j = np.nonzero(np.triu(C < cosine, 1))
    return [(names[a], names[b]) for a, b in zip(i.tolist(), j.tolist())]


def exclusive_indices(pairs, index: dict) -> np.ndarray:
    """Slider-name pairs to an int array of shape (P, 2)."""
    out = []
    for a, b in pairs or ():
        if a not in index or b not in index:
            raise InputError(f"exclusive: pair [{a}, {b}] names a slider the rig does not have")
        out.append((index[a], index[b]))
    return np.array(out, dtype=np.int64).reshape(-1, 2)


def fit_sliders(B, m, lower, upper, *, weights=None, sparsity: float = DEFAULT_SPARSITY,
                ridge: float = DEFAULT_RIDGE, exclusive=None, free=None) -> np.ndarray:
    """Bounded, sparse least-squares sliders with mutually exclusive pairs.

    .. math::

        \\min_{l \\le w \\le u}\\; \\tfrac12 \\lVert B w - m \\rVert_C^2 + \\lambda' \\mathbf 1^T w
        + \\tfrac{\\mu'}{2} \\lVert w \\rVert^2

    with ``λ' = sparsity · h̄`` and ``μ' = ridge · h̄``, ``h̄`` the mean
    diagonal of ``BᵀCB`` over the free sliders, so both are independent of the
    rig's units. The L1 term applies to sliders whose lower bound is 0 or more
    (for them ``|w| = w``). Exclusive pairs: after a solve, the smaller member
    of every pair with both members above :data:`ACTIVE` is fixed at 0 and the
    QP is solved again, until no pair is violated.

    Parameters
    ----------
    B : array_like, shape (r, n)
    m : array_like, shape (r,)
    lower, upper : array_like, shape (n,)
        Slider ranges; 0 must lie in each (sliders fixed at rest are set to 0).
    weights : array_like, shape (r,), optional
        Row weights ``C`` (confidences), default 1.
    sparsity, ridge : float
        ``λ`` and ``μ`` relative to ``h̄``.
    exclusive : ndarray of int, shape (P, 2), optional
    free : array_like of bool, shape (n,), optional
        Sliders that may move (others stay 0).

    Returns
    -------
    ndarray, shape (n,)
    """

    B = check_array(B, "B", ndim=2)
    r, n = B.shape
    m = check_array(m, "m", ndim=1)
    if m.shape != (r,):
        raise ShapeError(f"m: expected shape ({r},) to match B's rows, got {m.shape}")
    lo = np.broadcast_to(np.asarray(lower, dtype=np.float64), (n,)).copy()
    hi = np.broadcast_to(np.asarray(upper, dtype=np.float64), (n,)).copy()
    if np.any(lo > 0) or np.any(hi < 0):
        raise ParameterError("fit_sliders: every slider range must contain 0 (the rest pose)")
    c = np.ones(r) if weights is None else check_array(weights, "weights", ndim=1)
    if c.shape != (r,) or np.any(c < 0):
        raise ShapeError(f"weights: expected shape ({r},) of values >= 0, got {c.shape}")
    free = np.ones(n, dtype=bool) if free is None else np.asarray(free, dtype=bool).copy()
    pairs = np.zeros((0, 2), np.int64) if exclusive is None else np.asarray(exclusive, dtype=np.int64).reshape(-1, 2)
    w = np.zeros(n)
    if not free.any():
        return w
    BtC = B.T * c
    H = BtC @ B
    q = BtC @ m
    hbar = float(np.mean(np.diag(H)[free]))
    if hbar <= 0:
        return w
    H = H + ridge * hbar * np.eye(n)
    q = q - sparsity * hbar * (lo >= 0)
    for _ in range(len(pairs) + 1):
        idx = np.flatnonzero(free)
        w = np.zeros(n)
        w[idx] = box_qp(H[np.ix_(idx, idx)], q[idx][None], lower=lo[idx], upper=hi[idx])[0]
        both = pairs[(np.abs(w[pairs[:, 0]]) > ACTIVE) & (np.abs(w[pairs[:, 1]]) > ACTIVE)]
        if not len(both):
            break
        for a, b in both:
            free[b if abs(w[b]) <= abs(w[a]) else a] = False
    return w


def delta_pose(rig, vertices, neutral, targets, *, weights=None, neutral_weights=None, regions=None,
               sparsity: float = DEFAULT_SPARSITY, ridge: float = DEFAULT_RIDGE, exclusive=None,
               region_scale: bool = True, rigid=None, fixed=None, robust_iterations: int = 2) -> dict:
    """Rig sliders that reproduce each target frame's landmark displacement from the neutral frame.

    The delta transfer of the module docstring: one scaled orthographic
    camera (:func:`retarget_cli.methods.editing.fit_orthographic`) between the rig's rest
    landmark vertices and the actor's *neutral* landmarks, then per region the
    sliders it owns (:func:`slider_owners`) fitted by :func:`fit_sliders` to
    the region's landmark displacements divided by its scale
    (:func:`region_scales`).

    Parameters
    ----------
    rig : BlendshapeRig
    vertices : array_like of int, shape (L,)
        Rig vertex of each landmark.
    neutral : array_like, shape (L, 2)
        The actor's neutral-frame landmarks (stabilized pixels).
    targets : array_like, shape (K, L, 2)
        Landmarks of the frames to pose (stabilized pixels).
    weights : array_like, shape (K, L), optional
        Landmark confidences of the target frames.
    neutral_weights : array_like, shape (L,), optional
        Landmark confidences of the neutral frame.
    regions : dict, optional
        Region name to landmark ids; default one region of every landmark.
        Each region's sliders are fitted to its own landmarks only.
    sparsity, ridge : float
        See :func:`fit_sliders`.
    exclusive : ndarray of int, shape (P, 2), optional
        Mutually exclusive slider pairs.
    region_scale : bool
        Scale each region's displacements by its own camera scale (default)
        rather than the global one.
    robust_iterations : int
        Huber reweighting passes per region and frame (0: plain least squares),
        so that a landmark the tracker lost does not pose the face.
    fixed : array_like of bool, shape (n,), optional
        Sliders that stay at 0 (for example gaze sliders, which 2D landmarks
        without pupils cannot observe).
    rigid : array_like of int, optional
        Landmarks that do not move with expression (eye corners, nose). When
        given, every target frame gets its own camera, fitted on these points
        (with the actor's identity offset from the neutral frame carried
        over), so a head that turns or nods away from its neutral-frame pose
        does not read as expression: the frame's displacement is measured
        from the neutral face seen in *that frame's* pose. Without it one
        camera (the neutral frame's) serves every frame.

    Returns
    -------
    dict
        ``w`` (K, n) sliders; ``owner`` (n,) region index of each slider (-1:
        moves no landmark); ``regions`` (list of names); ``scale`` (global,
        pixels per rig unit), ``region_scales`` (R,), ``rotation`` (3, 3),
        ``translation`` (2,); ``rms`` (K,) landmark reprojection error of the
        fitted displacement in pixels.
    """

    v = rig.check_vertices(vertices, "landmark vertices")
    L = len(v)
    Y0 = check_array(neutral, "neutral", ndim=2)
    if Y0.shape != (L, 2):
        raise ShapeError(f"neutral: expected shape ({L}, 2) for {L} landmark vertices, got {Y0.shape}")
    Y = check_array(targets, "targets", ndim=3)
    if Y.shape[1:] != (L, 2):
        raise ShapeError(f"targets: expected shape (K, {L}, 2), got {Y.shape}")
    K = len(Y)
    c0 = np.ones(L) if neutral_weights is None else check_array(neutral_weights, "neutral_weights", ndim=1)
    C = np.ones((K, L)) if weights is None else check_array(weights, "weights", ndim=2)
    if c0.shape != (L,) or C.shape != (K, L):
        raise ShapeError(f"weights: expected shapes ({K}, {L}) and ({L},), got {C.shape} and {c0.shape}")
    regions = regions or {"face": list(range(L))}
    names = list(regions)
    ids = [np.asarray(regions[r], dtype=np.int64) for r in names]
    for r, i in zip(names, ids):
        if i.size == 0 or i.min() < 0 or i.max() >= L:
            raise ShapeError(f"regions: {r!r} must list landmark ids in [0, {L})")
    X0, DL = rig_landmarks(rig, v)
    rig_ids = None if rigid is None else np.asarray(rigid, dtype=np.int64)
    cam = slice(None) if rig_ids is None else rig_ids
    s, R, t = fit_orthographic(X0[cam], Y0[cam], c0[cam])
    # The actor's identity offset: where the neutral face differs from the rig at rest, in the neutral view.
    e0 = Y0 - (s * X0 @ R[:2].T + t)
    scales = region_scales(X0, Y0, R, s, ids, c0) / s if region_scale else np.ones(len(ids))
    owner = slider_owners(project(DL, R), ids)
    if fixed is not None:
        owner[np.asarray(fixed, dtype=bool)] = -1
    pairs = exclusive_indices(exclusive, rig.index) if exclusive is not None and len(exclusive) and isinstance(
        exclusive[0][0], str) else exclusive
    W = np.zeros((K, rig.n_sliders))
    sq = np.zeros(K)
    cnt = np.zeros(K)
    for k in range(K):
        if rig_ids is None:
            sk, Rk, tk = s, R, t
        else:
            ck = np.minimum(C[k, rig_ids], c0[rig_ids])
            sk, Rk, tk = fit_orthographic(X0[rig_ids], Y[k, rig_ids] - e0[rig_ids], ck if np.count_nonzero(ck) >= 3
                                          else None)
        rest_k = sk * X0 @ Rk[:2].T + tk + (sk / s) * e0  # the neutral face in frame k's pose
        Bk = project(DL, Rk)
        for ri, (i, sr) in enumerate(zip(ids, scales)):
            free = owner == ri
            if not free.any():
                continue
            Br = Bk[i].reshape(-1, rig.n_sliders)
            cw = np.repeat(np.minimum(C[k, i], c0[i]), 2)
            m = ((Y[k, i] - rest_k[i]) / (sk * sr)).ravel()
            w = fit_sliders(Br, m, rig.lower, rig.upper, weights=cw, sparsity=sparsity, ridge=ridge,
                            exclusive=pairs, free=free)
            for _ in range(robust_iterations):
                # Huber reweighting per landmark: a point the tracker lost (tens of pixels off) must not pose the
                # face. The threshold is ROBUST_PX pixels, or twice the median residual when that is larger.
                e = np.linalg.norm((Br @ w - m).reshape(-1, 2), axis=1) * sk * sr
                h = max(ROBUST_PX, 2.0 * float(np.median(e)))
                cw = np.repeat(np.minimum(C[k, i], c0[i]) * np.minimum(1.0, h / np.maximum(e, 1e-12)), 2)
                w = fit_sliders(Br, m, rig.lower, rig.upper, weights=cw, sparsity=sparsity, ridge=ridge,
                                exclusive=pairs, free=free)
            W[k] += w
            res = (Br @ w - m) * sk * sr
            sq[k] += float(np.sum(cw * res**2))
            cnt[k] += float(cw.sum()) / 2
    rms = np.sqrt(sq / np.maximum(cnt, 1e-300))
    return {"w": W, "owner": owner, "regions": names, "scale": float(s), "region_scales": scales * s,
            "rotation": R, "translation": t, "rms": rms}


def rig_curves(region_weights, region_sliders, lower=None, upper=None) -> np.ndarray:
    """Every frame's rig sliders from the decomposition weights and the key frames' sliders.

    With keys posed on a linear rig, frame ``t`` of region ``r`` is
    ``Σ_k w_{t,k} K_k = f0 Σ_k w_{t,k} + D Σ_k w_{t,k} s_k``; in the delta
    formulation (weights in whole-face form that sum to 1, the neutral key's
    sliders 0) that is exactly the rig at ``Σ_k w_{t,k} s_k``. Each region's
    keys carry only the sliders the region owns, so the regions' sums add up
    without overlap.

    Parameters
    ----------
    region_weights : list of ndarray, each shape (T, K_r)
    region_sliders : list of ndarray, each shape (K_r, n)
        The sliders of each region's keys, in the weights' column order.
    lower, upper : array_like, shape (n,), optional
        Slider ranges to clip to.

    Returns
    -------
    ndarray, shape (T, n)
    """
    if not region_weights or len(region_weights) != len(region_sliders):
        raise ShapeError("rig_curves: expected one slider table per region's weights")
    T = region_weights[0].shape[0]
    n = region_sliders[0].shape[1]
    out = np.zeros((T, n))
    for W, S in zip(region_weights, region_sliders):
        W, S = np.asarray(W, dtype=np.float64), np.asarray(S, dtype=np.float64)
        if W.shape[0] != T or S.shape != (W.shape[1], n):
            raise ShapeError(f"rig_curves: weights {W.shape} and key sliders {S.shape} do not match (T={T}, n={n})")
        out += W @ S
    if lower is not None or upper is not None:
        out = np.clip(out, -np.inf if lower is None else lower, np.inf if upper is None else upper)
    return out


def rig_region_masks(rig, owner, n_regions: int, *, threshold: float = 1e-4) -> np.ndarray:
    """Region masks derived from the rig: each vertex shared by the regions whose sliders move it.

    A vertex's weight for region ``r`` is ``m_r / Σ_r' m_r'``, where ``m_r``
    is the largest displacement any slider owned by ``r`` gives it. Vertices
    that no owned slider moves by more than *threshold* times the rig's
    largest displacement get 0 everywhere (they keep the neutral, which is
    where the rig leaves them). Separate shells need no special case: the
    teeth move with jawOpen, so they belong to the region that owns jawOpen.

    Parameters
    ----------
    rig : BlendshapeRig
    owner : ndarray of int, shape (n,)
        Region index of each slider, -1 for none (:func:`slider_owners`).
    n_regions : int
    threshold : float

    Returns
    -------
    ndarray, shape (n_regions, N), values in [0, 1]
    """
    owner = np.asarray(owner)
    N = rig.n_vertices
    M = np.zeros((n_regions, N))
    for j in range(rig.n_sliders):
        if owner[j] < 0:
            continue
        col = rig.D[:, [j]]
        col = (col.toarray() if hasattr(col, "toarray") else np.asarray(col)).reshape(N, 3)
        np.maximum(M[owner[j]], np.linalg.norm(col, axis=1), out=M[owner[j]])
    total = M.sum(axis=0)
    moving = total > threshold * max(float(total.max(initial=0.0)), 1e-300)
    out = np.zeros_like(M)
    out[:, moving] = M[:, moving] / total[moving]
    return out


__all__ = [
    "DEFAULT_RIDGE", "DEFAULT_SPARSITY", "delta_pose", "exclusive_indices", "fit_sliders", "infer_exclusive",
    "project", "region_scales", "rig_curves", "rig_landmarks", "rig_region_masks", "slider_owners",
]
