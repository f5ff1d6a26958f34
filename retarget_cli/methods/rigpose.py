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
from dataclasses import dataclass

import numpy as np

from .._validate import check_array
from ..errors import InputError, ParameterError, ShapeError
from .blas import small_blas
from .decomposition import box_qp
from .decomposition.boxqp import box_qp_masked
from .decomposition.temporal import _second_difference, event_terms, sparse_box_qp, take_windows
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
#: Default weight of the other regions' landmarks in a region's fit (:func:`delta_pose`'s *spill*): each region's
#: sliders are fitted on its own landmarks, and what they move elsewhere is error there that no other region's fit
#: sees (a VRM ``angry`` owned by the eyes parts the lips); those landmarks are rows with target 0 at this weight.
DEFAULT_SPILL = 1.0
#: A region's sliders that change the gap of another region's lips (closed at the rig's rest) by more than this share of
#: the mouth's width over their range meet the lips' gap as a row of its own, target 0, weighted as the region's own
#: gaps times *spill* (:func:`delta_pose`): the landmarks' spill rows weigh the parting as a few pixels, while a viewer
#: sees the lips part. The Godette VRM's ``angry`` (owned by the eyes, which it narrows) parts its lips by 0.32 of the
#: mouth's width; no ICT FaceKit or VALID slider passes. Lids are open at rest and left out: on the ICT FaceKit,
#: ``noseSneer`` (the mouth's) narrows an eye by 0.05 of its width, and holding that as a row cost d3's mouth width
#: 0.09-0.11 r and eye contact 1 % on ``bench/peer.py``.
SPILL_GAP_CHANGE = 0.03


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
                ridge: float = DEFAULT_RIDGE, exclusive=None, free=None, scale_rows=None) -> np.ndarray:
    """Bounded, sparse least-squares sliders with mutually exclusive pairs.

    .. math::

        \\min_{l \\le w \\le u}\\; \\tfrac12 \\lVert B w - m \\rVert_C^2 + \\lambda' \\mathbf 1^T w
        + \\tfrac{\\mu'}{2} \\lVert w \\rVert^2

    with ``λ' = sparsity · h̄`` and ``μ' = ridge · h̄``, ``h̄`` the mean
    diagonal of ``BᵀCB`` (its first *scale_rows* rows) over the free sliders, so both are independent of the
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
    scale_rows : int, optional
        ``h̄`` over the first *scale_rows* rows only (the landmarks), so that rows appended with weights of
        their own (the contact gaps, boosted up to ``CONTACT_BOOST ** CONTACT_PASSES``) do not raise the
        sparsity and ridge price of every slider with them. Default: every row.

    Returns
    -------
    ndarray, shape (n,)
    """

    return _slider_qp(B, m, lower, upper, weights=weights, sparsity=sparsity, ridge=ridge, exclusive=exclusive,
                      free=free, scale_rows=scale_rows)[0]


def _slider_qp(B, m, lower, upper, *, weights=None, sparsity: float = DEFAULT_SPARSITY, ridge: float = DEFAULT_RIDGE,
               exclusive=None, free=None, scale_rows=None):
    """:func:`fit_sliders`, also returning its QP: ``(w, H, q, free)``, ``½ wᵀHw − qᵀw`` over the final *free*
    sliders (the exclusive pairs' losers removed); ``H`` is None when nothing is free."""
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
        return w, None, None, free
    BtC = B.T * c
    H = BtC @ B
    q = BtC @ m
    k = r if scale_rows is None else scale_rows
    hbar = float(np.mean(((c[:k, None] * B[:k] ** 2).sum(axis=0))[free]))
    if hbar <= 0:
        return w, None, None, np.zeros(n, dtype=bool)
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
    return w, H, q, free


@dataclass(frozen=True)
class Contact:
    """Landmark pairs that meet when a feature closes: the lips, or one eye's lids.

    Attributes
    ----------
    kind : {"lips", "lids"}
        ``lips``: the rig's lips are closed at rest, and the actor's inner-lip gap is a target in itself
        (:func:`contact_targets`); ``lids``: the eye's openness relative to the neutral frame.
    pairs : tuple of (int, int)
        (upper, lower) landmark rows.
    corners : (int, int)
        The feature's corners, image-left first; their line's normal is the direction of the gap.
    """

    kind: str
    pairs: tuple
    corners: tuple


#: The contact pairs of the 68-point Multi-PIE layout: inner lips 61/67, 62/66, 63/65 between the outer mouth
#: corners 48/54; the image-left eye's lids 37/41, 38/40 (corners 36/39), the image-right eye's 43/47, 44/46
#: (corners 42/45).
CONTACT_68 = (Contact("lips", ((61, 67), (62, 66), (63, 65)), (48, 54)),
              Contact("lids", ((37, 41), (38, 40)), (36, 39)),
              Contact("lids", ((43, 47), (44, 46)), (42, 45)))
#: Default λ of :func:`smooth_sliders` in ``auto-pose --frames all``, and its event threshold (measured with
#: bench/peer.py on the shared clips: λ 1 / threshold 1 left the character's jitter above the peer's on 3 of 12
#: runs, λ 3 / threshold 3 on 2, both neutral-dependent; λ 10 released more events and jittered more).
DEFAULT_SMOOTH = 3.0
DEFAULT_SMOOTH_ROBUST = 3.0
#: Openness within this of the open eye counts as open (:func:`contact_targets`): the lid gap is held at rest
#: there instead of following the tracker's lid noise, which the openness map amplifies (by 1.8x on the
#: 68-point detector); a squint deeper than this is followed.
LID_DEADBAND = 0.15
#: Default weight of a contact gap, in landmarks (a gap row counts as this many landmarks of the region).
DEFAULT_CONTACT_WEIGHT = 4.0
#: Default inner-lip gap / mouth width, above the neutral frame's, below which the actor's lips count as closed.
DEFAULT_LIP_CLOSED = 0.02
#: Default lid gap / eye width at which the actor's tracked eye counts as closed: None, the take's
#: (:func:`take_lid_closed`: :data:`LID_CLOSED_FRACTION` of its open eyes' reading); a number is that reading.
DEFAULT_LID_CLOSED = None
#: The tracked eye counts as closed at this fraction of its open reading (lid gap / eye width). A 68-point shape
#: model never closes its lids: it reads closed lids at about a third of the open eye, as a fraction of the
#: actor's own aperture (on the shared clips: d3 0.125-0.13 of 0.35-0.37, d9 with glasses 0.09-0.10 of
#: 0.29-0.31, per the frames MediaPipe sees closed), so one absolute reading (0.15, the earlier default) closed
#: d9's narrowed eyes in a smile, which MediaPipe and the picture see open (docs/auto-pose.md).
LID_CLOSED_FRACTION = 0.42
CONTACT_KINDS = ("lips", "lids")
#: Percentiles of :func:`contact_references`: the take's closed lips and open eyes; the closed lips' readings
#: are those within CLOSED_BAND (of the mouth width) of that percentile.
CLOSED_PERCENTILE = 5.0
CLOSED_BAND = 0.03
#: The neutral frame's eye is the open reference unless it is closed by more than three quarters, from the take's
#: open reading towards its closed reading (:func:`take_lid_closed`; a squint, a wink, a blink).
NEUTRAL_OPEN = 0.25
OPEN_PERCENTILE = 75.0
#: Default tolerance of a contact gap, as a fraction of its feature's width on the rig (mouth or eye corners).
DEFAULT_CONTACT_TOL = 0.0075
#: A slider whose full range changes an eye's lid gap by more than this fraction of its width opens or closes it
#: (:func:`lid_antagonists`).
ANTAGONIST_CHANGE = 0.03
#: Passes of :func:`_fit_region` that weigh a gap outside its tolerance CONTACT_BOOST times more.
CONTACT_PASSES = 4
CONTACT_BOOST = 8.0


#: The 68-point landmarks of :func:`frontal_rotation`: the outer eye corners (image-left, image-right) and the chin.
FRONT_68 = (36, 45, 8)


def frontal_rotation(X0, left: int, right: int, down: int) -> np.ndarray:
    """The rotation that shows the rig from the front, from three of its landmarks at rest.

    Image x runs from landmark *left* to *right* (the outer eye corners), image y (down) towards *down* (the
    chin) and z away from the viewer, snapped to the nearest of the rig file's axes (a face rig is modelled
    facing one of them, glTF's +Z, and the chin sits in front of the eyes, which would tilt the view by
    10°): lips that meet are then measured as a viewer facing the character sees them, not through the head
    pose of some frame. Without a clear nearest axis the unsnapped rotation is returned.

    Parameters
    ----------
    X0 : ndarray, shape (L, 3)
        The rig's landmark vertices at rest.
    left, right, down : int

    Returns
    -------
    ndarray, shape (3, 3)
        Rows x, y, z: ``R @ X`` is in image-like axes.
    """
    ex = X0[right] - X0[left]
    ex = ex / max(float(np.linalg.norm(ex)), 1e-300)
    ey = X0[down] - 0.5 * (X0[left] + X0[right])
    ey = ey - (ey @ ex) * ex
    ey = ey / max(float(np.linalg.norm(ey)), 1e-300)
    R = np.stack([ex, ey, np.cross(ex, ey)])
    axes = np.argmax(np.abs(R), axis=1)
    if len(set(axes.tolist())) < 3:
        return R
    snapped = np.zeros((3, 3))
    snapped[np.arange(3), axes] = np.sign(R[np.arange(3), axes])
    return snapped if np.linalg.det(snapped) > 0 else R


def _normal(P, a: int, b: int) -> np.ndarray:
    """Unit normal of the line from point *a* to *b* of ``P`` (L, 2), rotated +90° (down the image)."""
    d = P[b] - P[a]
    n = np.array([-d[1], d[0]])
    return n / max(float(np.linalg.norm(n)), 1e-300)


def _gaps(P, c: Contact) -> np.ndarray:
    """Signed gaps of *c*'s pairs in the points ``P`` (L, 2) along its corner line's normal, shape (pairs,)."""
    n = _normal(P, *c.corners)
    return np.array([float(n @ (P[lo] - P[up])) for up, lo in c.pairs])


def contact_ratios(points, c: Contact) -> np.ndarray:
    """Each pair's gap over the feature's width (the corners' distance) in every frame.

    Parameters
    ----------
    points : array_like, shape (T, L, 2) or (L, 2)
    c : Contact

    Returns
    -------
    ndarray, shape (T, pairs) (or (pairs,) for one frame)
    """
    P = np.asarray(points, dtype=np.float64)
    one = P.ndim == 2
    P = P[None] if one else P
    a, b = c.corners
    d = P[:, b] - P[:, a]
    width = np.maximum(np.linalg.norm(d, axis=1), 1e-300)
    n = np.stack([-d[:, 1], d[:, 0]], axis=1) / width[:, None]
    out = np.stack([np.einsum("tc,tc->t", P[:, lo] - P[:, up], n) for up, lo in c.pairs], axis=1) / width[:, None]
    return out[0] if one else out


def lid_closed_reading(lid_closed: float | None, r_open: float) -> float:
    """The lid gap / eye width at which an eye whose open reading is *r_open* counts as closed: *lid_closed*
    when given, else :data:`LID_CLOSED_FRACTION` of *r_open*."""
    return LID_CLOSED_FRACTION * float(r_open) if lid_closed is None else float(lid_closed)


def _tracked_ratios(P, C, c: Contact) -> np.ndarray:
    """:func:`contact_ratios` of *c* in the frames of *P* (T, L, 2) where its points are tracked (finite, and
    confidence above 0 in *C* (T, L) when given), shape (T', pairs); one row of zeros when there is none."""
    r = contact_ratios(P, c)
    ok = np.isfinite(r).all(axis=1)
    if C is not None:
        ok &= (C[:, [p for pair in c.pairs for p in pair] + list(c.corners)] > 0).all(axis=1)
    return r[ok] if ok.any() else np.zeros((1, len(c.pairs)))


def take_lid_closed(points, contact, confidence=None, *, fraction: float = LID_CLOSED_FRACTION,
                    open_percentile: float = OPEN_PERCENTILE) -> float | None:
    """The lid gap / eye width at which the take's tracked eyes count as closed: *fraction* of their open reading.

    A 68-point shape model never shuts its lids: it reads closed lids at about a third of the open eye, as a
    fraction of the actor's own aperture, so the closed reading is the take's, not a constant
    (:data:`LID_CLOSED_FRACTION`).

    Parameters
    ----------
    points : array_like, shape (T, L, 2)
    contact : sequence of Contact
    confidence : array_like, shape (T, L), optional
        Frames where a group's point has confidence 0 are left out.
    fraction : float
    open_percentile : float
        The open eye's reading: this percentile of each eye's mean lid gap / eye width over the take (as
        :func:`contact_references`), averaged over the eyes.

    Returns
    -------
    float or None
        None without a ``lids`` group.
    """
    lids = [c for c in contact or () if c.kind == "lids"]
    if not lids:
        return None
    P = check_array(points, "points", ndim=3)
    C = None if confidence is None else np.asarray(confidence, dtype=np.float64)
    return fraction * float(np.mean([np.percentile(_tracked_ratios(P, C, c).mean(axis=1), open_percentile)
                                     for c in lids]))


def contact_references(points, contact, confidence=None, *, neutral=None, lid_closed: float | None = DEFAULT_LID_CLOSED,
                       closed_percentile: float = CLOSED_PERCENTILE,
                       open_percentile: float = OPEN_PERCENTILE) -> list[np.ndarray]:
    """What closed lips and open eyes read as in a take: the references of :func:`contact_targets`.

    Contact is a state of the face, not a change from the neutral frame, and the tracker reads it with a
    bias of its own (lips that meet keep a gap of 0–0.03 of the mouth width, lids that meet one of 0.1 of
    the eye width). So per group, over the take's frames where its points are tracked: ``lips``, each pair's
    median gap / mouth width over the frames within :data:`CLOSED_BAND` of its *closed_percentile*
    percentile (the cluster of closed lips: they meet in most takes, on more than that fraction of the
    frames); ``lids``, the *open_percentile* percentile of the mean lid gap / eye width
    (the eye at rest: open on most frames, blinks and squints below it, wide eyes above), or the *neutral*
    frame's unless that is closed by more than three quarters of the way to *lid_closed*
    (:data:`NEUTRAL_OPEN`), so that the neutral frame's eyes are the rig's at rest unless they squint, wink or
    blink.

    Parameters
    ----------
    points : array_like, shape (T, L, 2)
    contact : sequence of Contact
    confidence : array_like, shape (T, L), optional
        Frames where a group's point has confidence 0 are left out of its statistic.
    neutral : array_like, shape (L, 2), optional
        The neutral frame's landmarks.
    lid_closed : float, optional
        As :func:`contact_targets` (None: the take's, :func:`take_lid_closed`).

    Returns
    -------
    list of ndarray, one per group, each shape (pairs,)
    """
    P = check_array(points, "points", ndim=3)
    C = None if confidence is None else np.asarray(confidence, dtype=np.float64)
    if lid_closed is None:
        lid_closed = take_lid_closed(P, contact, C, open_percentile=open_percentile)
    out = []
    for c in contact or ():
        r = _tracked_ratios(P, C, c)
        if c.kind == "lips":
            low = np.percentile(r, closed_percentile, axis=0)
            out.append(np.array([np.median(r[r[:, j] <= low[j] + CLOSED_BAND, j]) for j in range(r.shape[1])]))
        else:
            r_open = float(np.percentile(r.mean(axis=1), open_percentile))
            if neutral is not None:
                r_n = float(np.mean(contact_ratios(neutral, c)))
                if r_n >= lid_closed + NEUTRAL_OPEN * (r_open - lid_closed):  # the neutral frame's eye is the rest
                    r_open = r_n
            out.append(np.full(len(c.pairs), r_open))
    return out


def contact_targets(c: Contact, Yk, ref, P0, B, free, lower, upper, *, lid_closed: float | None = DEFAULT_LID_CLOSED,
                    lip_closed: float = DEFAULT_LIP_CLOSED):
    """The gap rows of one contact group: what the rig's gaps must change by, from its rest pose.

    The delta fit asks the rig's landmarks to move as the actor's moved from the neutral frame, which
    does not keep contact: lips that are parted in the neutral frame cross on the character when the actor
    closes them, and a tracker whose closed lids keep a gap leaves the character's eyes half open. So the
    gap of each pair becomes a target of its own, as a fraction of the feature's width (the corners'
    distance) on the actor, against the take's references (:func:`contact_references`), carried over to the
    rig's width:

    - ``lips``: the rig's lips are closed at rest. The actor's opening is the pair's gap / mouth width above
      the take's closed reading, less *lip_closed* (the tracker's noise on closed lips), never below 0: the
      character's lips part by as much of their width, and never cross;
    - ``lids``: the actor's openness ``o = (r_k − r_c) / (r_o − r_c)``, ``r_k`` the mean lid gap / eye width,
      ``r_o`` the take's open reading and ``r_c`` where the tracker's lids read closed (*lid_closed*: the
      take's, :func:`take_lid_closed`; without it :data:`LID_CLOSED_FRACTION` of ``r_o``),
      clipped at 0 and stretched by :data:`LID_DEADBAND` (an eye within it of open is open), poses the
      rig's gap between its rest gap (``o = 1``) and its most closed one (the
      slider among *free* that closes it most, at its bound, ``o = 0``); an eye wider than ``r_o`` widens
      the rig's by ``r_k − r_o`` of its width.

    Parameters
    ----------
    c : Contact
    Yk : ndarray, shape (L, 2)
        The actor's landmarks in the frame (pixels).
    ref : ndarray, shape (pairs,)
        The group's references (:func:`contact_references`).
    P0 : ndarray, shape (L, 2)
        The rig's rest landmarks seen through a camera rotation (rig units).
    B : ndarray, shape (L, 2, n)
        The rig's landmark displacements seen through the same rotation.
    free : ndarray of bool, shape (n,)
        The sliders that may move.
    lower, upper : array_like, shape (n,)
        Slider ranges.
    lid_closed : float, optional
        The closed lids' reading (:func:`take_lid_closed`; None: :data:`LID_CLOSED_FRACTION` of *ref*).
    lip_closed : float

    Returns
    -------
    G : ndarray, shape (pairs, n)
        Gap change per slider in that view, ``n · (B_lower − B_upper)``.
    target : ndarray, shape (pairs,)
        The gap change the rig must make (rig units).
    closed : ndarray, shape (pairs,)
        The gap change of the rig's closed feature (lips: 0, their rest).
    """
    if c.kind not in CONTACT_KINDS:
        raise ParameterError(f"contact: kind {c.kind!r} is not one of {', '.join(CONTACT_KINDS)}")
    return _contact_target(c, _contact_rig(c, P0, B, free, lower, upper), contact_ratios(Yk, c), ref,
                           lid_closed=lid_closed, lip_closed=lip_closed)


def _contact_rig(c: Contact, P0, B, free, lower, upper):
    """The rig's side of :func:`contact_targets` (the same for every frame seen in one view):
    ``(G (pairs, n), the feature's width in the rig, closed (pairs,))``."""
    n = _normal(P0, *c.corners)
    G = np.stack([n @ (B[lo] - B[up]) for up, lo in c.pairs])
    width_rig = float(np.linalg.norm(P0[c.corners[1]] - P0[c.corners[0]]))
    if c.kind == "lips":
        return G, width_rig, np.zeros(len(c.pairs))
    reach = np.minimum(G * np.asarray(upper, dtype=np.float64), G * np.asarray(lower, dtype=np.float64))
    closed = np.min(np.where(free, reach, 0.0), axis=1, initial=0.0)  # (pairs,): the most closing slider's
    return G, width_rig, closed


def _contact_target(c: Contact, rig, ratio, ref, *, lid_closed: float, lip_closed: float):
    """:func:`contact_targets` from the rig's side *rig* (:func:`_contact_rig`) and the actor's gap ratios
    *ratio* (:func:`contact_ratios` of the frame)."""
    G, width_rig, closed = rig
    if c.kind == "lips":
        return G, np.maximum(ratio - np.asarray(ref) - lip_closed, 0.0) * width_rig, closed
    r_k, r_o = float(np.mean(ratio)), float(np.mean(ref))
    r_c = lid_closed_reading(lid_closed, r_o)
    if r_o - r_c <= 1e-6:
        return G, np.zeros(len(c.pairs)), closed  # the open eye reads no more open than closed: no target
    if r_k >= r_o:
        return G, np.full(len(c.pairs), (r_k - r_o) * width_rig), closed
    o = min(max((r_k - r_c) / (r_o - r_c), 0.0) / (1.0 - LID_DEADBAND), 1.0)
    return G, (1.0 - o) * closed, closed


#: Default of :func:`depth_sliders`: a slider whose fitted landmark vertices move, at the farthest, more than this
#: many times as far in 3D as in the rig's front view. On the ICT FaceKit only ``jawForward`` passes (6.6: its chin
#: juts 0.12 inter-ocular distances and shows as 0.02 down in the picture); next come ``cheekPuff_*`` (4.3) and
#: ``mouthPucker`` (2.2); on the VALID avatar ``LlipCorner_h`` and ``RlipCorner_h`` (52, 35), then ``JawFront_h``
#: (4.3) and ``Lblow_h``/``Rblow_h`` (3.5-3.7); on the Godette VRM none (1.5 at most).
DEPTH_RATIO = 5.0


def depth_sliders(X0, DL, rows, front, *, ratio: float = DEPTH_RATIO) -> np.ndarray:
    """The sliders that move the landmarks mostly along the line of sight: 2D landmarks do not see them.

    Such a slider (a jaw thrust) shows in the picture only by a side effect a few pixels large, so the 2D fit
    takes it, at full weight, for any small residual that side effect matches (the ICT FaceKit's ``jawForward``
    at 0.5 or more on 57-61 % of the d12 clip's frames: a jutting jaw the actor does not make; docs/auto-pose.md).
    Like the gaze sliders without pupils, they are left out of the fit.

    Parameters
    ----------
    X0 : ndarray, shape (L, 3)
        The rig's landmark vertices at rest (:func:`rig_landmarks`).
    DL : ndarray, shape (L, 3, n)
        Their displacement per slider at full weight.
    rows : array_like of int
        The landmarks the fit uses.
    front : (int, int, int)
        The landmarks of :func:`frontal_rotation` (for 68 points :data:`FRONT_68`).
    ratio : float
        A slider whose largest 3D displacement over *rows* exceeds *ratio* times its largest displacement in the
        front view is a depth slider.

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    R = frontal_rotation(np.asarray(X0, dtype=np.float64), *front)
    D = np.asarray(DL, dtype=np.float64)[np.asarray(rows, dtype=np.int64)]
    full = np.linalg.norm(D, axis=1).max(axis=0, initial=0.0)
    seen = np.linalg.norm(np.einsum("ij,rjn->rin", R[:2], D), axis=1).max(axis=0, initial=0.0)
    return (full > 0) & (full > ratio * seen)


def lid_antagonists(P0, B, contact, lower, upper, *, change: float = ANTAGONIST_CHANGE) -> np.ndarray:
    """Pairs of sliders that one opens and the other closes the same eye: kept mutually exclusive.

    Stacked, an opener (eyeWide) and a closer (eyeSquint, cheekSquint, cheekRaiser, eyeBlink, …) of the same
    lids cancel on the lid gap and move both lids together: no face does that, but a least-squares fit
    reaches for it to explain an eye that the head's motion or the tracker shifted (issue 27 counted
    300–500 such frames in 12 runs on the shared clips). Lids only: on the lips, jawOpen with mouthClose
    is a real pose (closed lips, open jaw).

    Parameters
    ----------
    P0 : ndarray, shape (L, 2)
        The rig's rest landmarks (front view).
    B : ndarray, shape (L, 2, n)
        Its landmark displacements, same view.
    contact : sequence of Contact
        The ``lids`` groups are used.
    lower, upper : array_like, shape (n,)
    change : float
        A slider opens (closes) the eye when its full range widens (narrows) the mean lid gap by more than
        this fraction of the eye's width.

    Returns
    -------
    ndarray of int, shape (P, 2)
    """
    lo, hi = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    out = []
    for c in contact or ():
        if c.kind != "lids":
            continue
        n = _normal(P0, *c.corners)
        g = np.mean([n @ (B[d] - B[u]) for u, d in c.pairs], axis=0)  # (n,) mean gap change per unit
        width = max(float(np.linalg.norm(P0[c.corners[1]] - P0[c.corners[0]])), 1e-300)
        opens = np.flatnonzero(np.maximum(g * hi, g * lo) > change * width)
        closes = np.flatnonzero(np.minimum(g * hi, g * lo) < -change * width)
        out += [(int(a), int(b)) for a in opens for b in closes if a != b]
    return np.array(sorted(set(out)), dtype=np.int64).reshape(-1, 2)


def _exclusive_pairs(exclusive, rig, P0, B, contact):
    """*exclusive* (names or indices) as indices (P, 2), with the :func:`lid_antagonists` of *contact*; or None."""
    pairs = exclusive_indices(exclusive, rig.index) if exclusive is not None and len(exclusive) and isinstance(
        exclusive[0][0], str) else exclusive
    lid_pairs = lid_antagonists(P0, B, contact, rig.lower, rig.upper)
    if not len(lid_pairs):
        return pairs
    if pairs is None:
        return lid_pairs
    return np.unique(np.vstack([np.asarray(pairs, np.int64).reshape(-1, 2), lid_pairs]), axis=0)


#: Frames of :func:`delta_pose` whose per-frame QPs are solved together (bounds the memory of a long take).
_BATCH = 256

#: Frames of a long take whose sliders :func:`delta_pose` smooths together (:func:`smoothing_windows`): its
#: per-frame fits (~50 KB a frame and region) and the smoothing's sparse system and LU (~350 KB a frame for the
#: ICT rig's two regions) are held for one window at a time, so the memory of a take does not grow with its
#: length (measured: ``bench/long_take.py``, docs/benchmarks.md).
SMOOTH_WINDOW = 2 * _BATCH
#: Frames each side of a window fitted and smoothed with it but taken from its neighbours: the smoothing's
#: coupling (a second difference) is below rounding after a few tens of frames.
SMOOTH_MARGIN = 64


def delta_pose(rig, vertices, neutral, targets, *, weights=None, neutral_weights=None, regions=None,
               sparsity: float = DEFAULT_SPARSITY, ridge: float = DEFAULT_RIDGE, exclusive=None,
               region_scale: bool = True, rigid=None, fixed=None, robust_iterations: int = 2,
               contact=None, contact_weight: float = DEFAULT_CONTACT_WEIGHT,
               lid_closed: float | None = DEFAULT_LID_CLOSED, lip_closed: float = DEFAULT_LIP_CLOSED,
               smooth: float = 0.0, smooth_robust: float = DEFAULT_SMOOTH_ROBUST, smooth_noise: bool = True,
               contact_tol: float = DEFAULT_CONTACT_TOL,
               contact_refs=None, front=None, spill: float = DEFAULT_SPILL, preset=None,
               smooth_window: int | None = SMOOTH_WINDOW, smooth_margin: int = SMOOTH_MARGIN, out=None) -> dict:
    """Rig sliders that reproduce each target frame's landmark displacement from the neutral frame.

    The delta transfer of the module docstring: one scaled orthographic
    camera (:func:`retarget_cli.methods.editing.fit_orthographic`) between the rig's rest
    landmark vertices and the actor's *neutral* landmarks, then per region the
    sliders it owns (:func:`slider_owners`) fitted by :func:`fit_sliders` to
    the region's landmark displacements divided by its scale
    (:func:`region_scales`), with the gaps of *contact* pairs as targets of
    their own (:func:`contact_targets`).

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
    contact : sequence of Contact, optional
        Pairs whose gap is a target (:func:`contact_targets`; for 68 points
        :data:`CONTACT_68`); a group is fitted with the region that holds all
        its pairs. The pair's two landmarks keep their mean displacement from
        the delta fit; their gap is replaced by the target.
    contact_weight : float
        Weight of each gap row, in landmarks (0: the gaps as the delta fit has them, no extra row). A gap
        that crosses, or is not closed where the actor's is, by more than *contact_tol* of its feature's
        width weighs :data:`CONTACT_BOOST` times more, up to :data:`CONTACT_PASSES` times. With the lids'
        groups, their :func:`lid_antagonists` join the *exclusive* pairs.
    lid_closed : float, optional
        See :func:`contact_targets` (None: the take's, :func:`take_lid_closed` of the neutral and target frames).
    lip_closed : float
        See :func:`contact_targets`.
    smooth : float
        λ of :func:`smooth_sliders` (the targets are then consecutive frames; 0: each frame alone).
    smooth_robust : float
        Its event threshold.
    smooth_noise : bool
        The event test takes no residual excess within the take's own tracking noise (a landmark's,
        :func:`tracking_noise`) or within about 1.7 *contact_tol* (a contact gap's) for an event
        (:func:`noise_floor`).
    smooth_window, smooth_margin : int
        A take longer than ``smooth_window + smooth_margin`` frames is fitted and smoothed in windows of
        *smooth_window* frames reaching *smooth_margin* frames into their neighbours (:func:`smoothing_windows`),
        so that its memory does not grow with its length; None: the whole take at once.
    contact_tol : float
    contact_refs : list of ndarray, optional
        :func:`contact_references` of the take (default: of the neutral and target frames).
    front : (int, int, int), optional
        Landmarks that give the rig's front view (:func:`frontal_rotation`; for 68 points :data:`FRONT_68`), in
        which the contact gaps are measured; default the neutral frame's view.
    preset : array_like, shape (K, n), optional
        Slider values set before the fit (the gaze sliders of :mod:`retarget_cli.methods.gaze_rig`), for
        sliders that are *fixed*: their landmark displacement is a fixed offset, taken off each frame's
        displacement and off its contact gaps' targets before the other sliders are fitted, so what they
        already move (a rig's eyeLookDown lowering the lids) is not fitted twice; they are added to ``w``.
    out : ndarray, shape (K, n), float64, optional
        Where ``w`` is written (e.g. a long take's rows of the caller's array: no second copy of them).

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
    # the targets and weights as given (a long take's float32 landmarks are not copied): each frame is read at
    # float64 when it is fitted
    Y = check_array(targets, "targets", ndim=3, dtype=_float_dtype(targets))
    if Y.shape[1:] != (L, 2):
        raise ShapeError(f"targets: expected shape (K, {L}, 2), got {Y.shape}")
    K = len(Y)
    c0 = np.ones(L) if neutral_weights is None else check_array(neutral_weights, "neutral_weights", ndim=1)
    C = np.ones((K, L)) if weights is None else check_array(weights, "weights", ndim=2, dtype=_float_dtype(weights))
    if c0.shape != (L,) or C.shape != (K, L):
        raise ShapeError(f"weights: expected shapes ({K}, {L}) and ({L},), got {C.shape} and {c0.shape}")
    regions = regions or {"face": list(range(L))}
    names = list(regions)
    ids = [np.asarray(regions[r], dtype=np.int64) for r in names]
    for r, i in zip(names, ids):
        if i.size == 0 or i.min() < 0 or i.max() >= L:
            raise ShapeError(f"regions: {r!r} must list landmark ids in [0, {L})")
    P = _check_preset(preset, K, rig.n_sliders)
    if contact_weight > 0 and contact:
        lid_closed, contact_refs = _take_contact(Y0, Y, c0, C, contact, lid_closed, contact_refs)
    groups = _region_contacts(contact if contact_weight > 0 else None, contact_refs, ids, L)
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
    Rc = R if front is None else frontal_rotation(X0, *front)
    P0n, Bn = X0 @ Rc[:2].T, project(DL, Rc)  # the rig seen from the front: where its contact gaps are measured
    pairs = _exclusive_pairs(exclusive, rig, P0n, Bn, [c for g in groups for c, _ in g])
    fitted = np.unique(np.concatenate(ids))
    others = [np.setdiff1d(fitted, i) if spill > 0 else fitted[:0] for i in ids]
    foreign = _foreign_contacts(groups, owner, P0n, Bn, rig, spill)
    opts = dict(sparsity=sparsity, ridge=ridge, exclusive=pairs, robust_iterations=robust_iterations, spill=spill,
                contact_weight=contact_weight, contact_tol=contact_tol, lid_closed=lid_closed, lip_closed=lip_closed)
    W = _zeroed_out(out, K, rig.n_sliders)
    sq = np.zeros(K)
    cnt = np.zeros(K)
    B0 = project(DL, R)
    noise = tracking_noise(Y) if smooth > 0 and smooth_noise else None  # the whole take's: windows agree
    for a, b, lo, hi in smoothing_windows(K, smooth_window, smooth_margin if smooth > 0 else 0):
        # frames [lo, hi) fitted and smoothed together; rows [a, b) of W kept (the whole take unless it is long)
        fits = [[] for _ in ids]
        with small_blas():  # many small solves: BLAS threads only add overhead (methods/blas.py)
            for k0 in range(lo, hi, _BATCH):  # frames in batches: their QPs are solved together
                frames = [_frame(Y[k].astype(np.float64), C[k].astype(np.float64), c0, X0, DL, e0, (s, R, t), rig_ids,
                                 P0n, Bn, None if P is None else P[k])
                          for k in range(k0, min(hi, k0 + _BATCH))]
                for ri, (i, sr) in enumerate(zip(ids, scales)):
                    free = owner == ri
                    if not free.any():
                        continue
                    fits[ri] += _fit_region_frames(rig, frames, i, sr, free, groups[ri], others=others[ri],
                                                   foreign=foreign[ri], **opts)
        for ri, i in enumerate(ids):
            if not fits[ri]:
                continue
            Bi = B0[i].reshape(-1, rig.n_sliders)
            Wr = smooth_sliders(fits[ri], Bi.T @ Bi, rig.lower, rig.upper, lam=smooth, robust=smooth_robust,
                                noise=None if noise is None else noise[np.concatenate([i, others[ri]])])
            for k in range(a, b):
                f, w = fits[ri][k - lo], Wr[k - lo]
                W[k] += w
                e2, n2 = f.residual(w)
                sq[k] += e2
                cnt[k] += n2
        del fits
    W += 0.0 if P is None else np.where(owner < 0, P, 0.0)  # the preset sliders, as they were set
    rms = np.sqrt(sq / np.maximum(cnt, 1e-300))
    return {"w": W, "owner": owner, "regions": names, "scale": float(s), "region_scales": scales * s,
            "rotation": R, "translation": t, "rms": rms}


def _take_contact(Y0, Y, c0, C, contact, lid_closed, contact_refs):
    """:func:`delta_pose`'s *lid_closed* and *contact_refs*, each as given or (None) of the neutral and target
    frames (:func:`take_lid_closed`, :func:`contact_references`)."""
    if lid_closed is None or contact_refs is None:
        P, W = np.concatenate([Y0[None], Y]), np.concatenate([c0[None], C])
        if lid_closed is None:
            lid_closed = take_lid_closed(P, contact, W)
        if contact_refs is None:
            contact_refs = contact_references(P, contact, W, neutral=Y0, lid_closed=lid_closed)
    return lid_closed, contact_refs


def _zeroed_out(out, K: int, n: int) -> np.ndarray:
    """:func:`delta_pose`'s result array: *out* (float64 (K, n)) set to 0, or a new one."""
    if out is None:
        return np.zeros((K, n))
    if out.shape != (K, n) or out.dtype != np.float64:
        raise ShapeError(f"out: expected a float64 array of shape ({K}, {n}), got {out.dtype} {out.shape}")
    out[...] = 0.0
    return out


def _float_dtype(x):
    """float32 for a float32 array (kept as it is), else float64."""
    return np.float32 if getattr(x, "dtype", None) == np.float32 else np.float64


def _check_preset(preset, K: int, n: int):
    """:func:`delta_pose`'s *preset* as float (K, n), or None."""
    if preset is None:
        return None
    P = check_array(preset, "preset", ndim=2)
    if P.shape != (K, n):
        raise ShapeError(f"preset: expected shape ({K}, {n}), got {P.shape}")
    return P


@dataclass(frozen=True)
class _Frame:
    """One target frame as :func:`_fit_region` needs it: the actor's points and the neutral face in the frame's
    pose (pixels), the rig's rest points and displacements through the frame's rotation (rig
    units), the landmark weights (L,), the frame's camera scale, and the rig's rest points and displacements
    through the neutral frame's rotation."""

    Y: np.ndarray
    rest: np.ndarray
    P0: np.ndarray
    B: np.ndarray
    c: np.ndarray
    s: float
    P0n: np.ndarray
    Bn: np.ndarray
    preset: np.ndarray | None = None


def _frame(Yk, Ck, c0, X0, DL, e0, camera, rig_ids, P0n, Bn, preset=None) -> _Frame:
    """Target frame *Yk* (L, 2) with confidences *Ck* (L,) as :func:`_fit_region_frames` needs it: seen through
    its own camera fitted on the *rig_ids* landmarks (the neutral frame's *camera* ``(s, R, t)`` without them)."""
    s, R, t = camera
    if rig_ids is None:
        sk, Rk, tk = s, R, t
    else:
        ck = np.minimum(Ck[rig_ids], c0[rig_ids])
        sk, Rk, tk = fit_orthographic(X0[rig_ids], Yk[rig_ids] - e0[rig_ids], ck if np.count_nonzero(ck) >= 3
                                      else None)
    rest_k = sk * X0 @ Rk[:2].T + tk + (sk / s) * e0  # the neutral face in frame k's pose
    return _Frame(Yk, rest_k, X0 @ Rk[:2].T, project(DL, Rk), np.minimum(Ck, c0), sk, P0n, Bn, preset)


def _region_contacts(contact, refs, ids, L: int) -> list:
    """Per region, ``(group, references)`` of the contact groups all of whose pairs' landmarks lie in it."""
    out = [[] for _ in ids]
    for c, ref in zip(contact or (), refs or ()):
        pts = [p for pair in c.pairs for p in pair]
        if c.kind not in CONTACT_KINDS or not c.pairs or any(not 0 <= p < L for p in (*pts, *c.corners)):
            raise ShapeError(f"contact: expected kind lips or lids and pairs/corners of landmark ids in [0, {L}), "
                             f"got {c!r}")
        for ri, i in enumerate(ids):
            if set(pts) <= set(i.tolist()):
                out[ri].append((c, np.asarray(ref, dtype=np.float64)))
                break
    return out




def _foreign_contacts(groups, owner, P0n, Bn, rig, spill: float) -> list:
    """Per region, the other regions' lips groups whose gap its sliders change by more than
    :data:`SPILL_GAP_CHANGE` of the mouth's width over their range (none when *spill* is 0)."""
    out = [[] for _ in groups]
    if spill <= 0:
        return out
    for ri in range(len(groups)):
        free = owner == ri
        if not free.any():
            continue
        for rj, g in enumerate(groups):
            for c, _ in (g if rj != ri else ()):
                if c.kind != "lips":
                    continue
                G, width, _ = _contact_rig(c, P0n, Bn, free, rig.lower, rig.upper)
                reach = np.maximum(np.abs(G * rig.upper), np.abs(G * rig.lower))[:, free]
                if reach.size and float(reach.max()) > SPILL_GAP_CHANGE * width:
                    out[ri].append(c)
    return out


def smoothing_windows(K: int, window: int | None = SMOOTH_WINDOW, margin: int = SMOOTH_MARGIN) -> list:
    """The windows :func:`delta_pose` fits and smooths a take of *K* frames in, as ``(a, b, lo, hi)``
    (:func:`~retarget_cli.methods.decomposition.temporal.take_windows`): rows ``[a, b)`` of the result come
    from the frames ``[lo, hi)`` fitted and smoothed together (:func:`smooth_sliders`). A take of at most
    ``window + margin`` frames is one window: the whole take smoothed at once. Each frame's own fit is the
    whole take's to rounding (bit for bit when the windows and margins are multiples of ``_BATCH``, whose
    batches they then keep), and so is the smoothing, whose coupling dies out across the margin; the event
    test's normalisation (:func:`smooth_sliders`) is the window's own (``tests/unit/methods/test_rigpose_window.py``).

    Returns
    -------
    list of (int, int, int, int)
    """
    return take_windows(K, window, margin)


def _region_rows(rig, fr: _Frame, i, sr, groups, free, *, contact_tol, lid_closed, lip_closed, others=(),
                 neutral_view=None, foreign=(), foreign_view=None):
    """The rows of one region of one frame: ``A`` (r, n), ``b`` (r,) (the landmark coordinates' displacements,
    then the *others* landmarks' coordinates with target 0, then a row per contact pair, then a row per pair of
    the *foreign* groups (other regions' contacts) with target 0), and per pair its landmark weight, tolerance
    and closed gap, and the frame's pixels per rig unit. *neutral_view*, *foreign_view*: the groups'
    :func:`_contact_rig` in the neutral frame's view (``fr.P0n``, ``fr.Bn``), when already known."""
    n = rig.n_sliders
    scale = fr.s * sr
    m = ((fr.Y[i] - fr.rest[i]) / scale)  # (|i|, 2) the delta fit's displacements, rig units
    Br = fr.B[i]
    if fr.preset is not None:  # the preset sliders' displacement is a fixed offset
        m = m - np.einsum("lbn,n->lb", Br, fr.preset)
    pos = {int(p): j for j, p in enumerate(i)}
    G_rows, g_t, g_c, g_tol, g_closed = [], [], [], [], []
    for gi, (c, ref) in enumerate(groups):
        # contact_targets in two views, the frame's gap ratios read once
        if c.kind not in CONTACT_KINDS:
            raise ParameterError(f"contact: kind {c.kind!r} is not one of {', '.join(CONTACT_KINDS)}")
        ratio = contact_ratios(fr.Y, c)
        # the pair's gap in the frame's view replaces the delta's (their mean displacement is kept) ...
        G_k, target_k, _ = _contact_target(c, _contact_rig(c, fr.P0, fr.B, free, rig.lower, rig.upper), ratio, ref,
                                           lid_closed=lid_closed, lip_closed=lip_closed)
        # ... and the gap seen in the neutral frame's view is a row of its own (contact is the face's, not the view's)
        rig_n = neutral_view[gi] if neutral_view is not None else \
            _contact_rig(c, fr.P0n, fr.Bn, free, rig.lower, rig.upper)
        G, target, closed = _contact_target(c, rig_n, ratio, ref, lid_closed=lid_closed, lip_closed=lip_closed)
        if fr.preset is not None:  # the gap the preset sliders already make is taken off the targets
            target_k, target = target_k - G_k @ fr.preset, target - G @ fr.preset
        nrm = _normal(fr.P0, *c.corners)
        for (up, lo), tg in zip(c.pairs, target_k):
            # keep the pair's mean displacement, replace its gap change by the target
            fix = 0.5 * (tg - float(nrm @ (m[pos[lo]] - m[pos[up]]))) * nrm
            m[pos[lo]] += fix
            m[pos[up]] -= fix
            g_c.append(min(fr.c[up], fr.c[lo]))
        G_rows.append(G)
        g_t.append(target)
        g_closed.append(closed)
        g_tol += [contact_tol * float(np.linalg.norm(fr.P0n[c.corners[1]] - fr.P0n[c.corners[0]]))] * len(c.pairs)
    for fi, c in enumerate(foreign):
        # another region's gap: this region's sliders should leave it as it is (that region poses it)
        G = (foreign_view[fi] if foreign_view is not None else
             _contact_rig(c, fr.P0n, fr.Bn, free, rig.lower, rig.upper))[0]
        G_rows.append(G)
        g_t.append(np.zeros(len(c.pairs)))
        g_closed.append(np.zeros(len(c.pairs)))
        g_c += [min(fr.c[up], fr.c[lo]) for up, lo in c.pairs]
        g_tol += [contact_tol * float(np.linalg.norm(fr.P0n[c.corners[1]] - fr.P0n[c.corners[0]]))] * len(c.pairs)
    others = np.asarray(others, dtype=np.int64)
    A = np.vstack([Br.reshape(-1, n), fr.B[others].reshape(-1, n)])
    b = np.concatenate([m.ravel(), np.zeros(2 * len(others))])
    if G_rows:
        A = np.vstack([A, *G_rows])
        b = np.concatenate([b, *g_t])
    closed = np.concatenate(g_closed) if g_closed else np.zeros(0)
    return A, b, np.asarray(g_c, dtype=np.float64), np.asarray(g_tol, dtype=np.float64), closed, scale


def _fit_region_frames(rig, frames, i, sr, free, groups, *, sparsity, ridge, exclusive, robust_iterations,
                       contact_weight, contact_tol, lid_closed, lip_closed, others=(), spill=DEFAULT_SPILL,
                       foreign=()) -> list:
    """One region of each of *frames*: a :class:`_RegionFit` per frame.

    Per frame, the sliders of :func:`fit_sliders` on the region's rows (:func:`_region_rows`: the region's
    landmarks, and the *others* (the other regions' landmarks) with target 0 at weight *spill*, since what the
    region's sliders move there is error that the other regions' fits do not see, and the *foreign* contact groups'
    gaps (other regions' lips, :func:`_foreign_contacts`) with target 0 at the contact weight times *spill*), then
    ``robust_iterations`` Huber reweightings per landmark (a point the tracker lost, tens of pixels off, must not
    pose the face: the threshold is ROBUST_PX pixels, or twice the median residual when that is larger), then up to
    CONTACT_PASSES passes where a gap that crosses (below the closed one by more than *contact_tol* of its feature's
    width), or that is not closed where the actor's is, weighs CONTACT_BOOST times more, until none is. Each step's
    QPs are solved for every frame at once (:func:`_slider_qps`).
    """
    others = np.asarray(others, dtype=np.int64)
    # the neutral frame's view is every frame's: its side of the contact rows is computed once
    neutral_view = [_contact_rig(c, frames[0].P0n, frames[0].Bn, free, rig.lower, rig.upper) for c, _ in groups] \
        if frames else None
    foreign_view = [_contact_rig(c, frames[0].P0n, frames[0].Bn, free, rig.lower, rig.upper) for c in foreign] \
        if frames else None
    rows = [_region_rows(rig, fr, i, sr, groups, free, contact_tol=contact_tol, lid_closed=lid_closed,
                         lip_closed=lip_closed, others=others, neutral_view=neutral_view, foreign=foreign,
                         foreign_view=foreign_view) for fr in frames]
    A = np.stack([r[0] for r in rows])
    b = np.stack([r[1] for r in rows])
    g_c = np.stack([r[2] for r in rows])
    tol = np.stack([r[3] for r in rows])
    closed = np.stack([r[4] for r in rows])
    scale = np.array([r[5] for r in rows])
    cl = np.stack([np.concatenate([fr.c[i], spill * fr.c[others]]) for fr in frames])
    T, n_own, n_lm = len(frames), 2 * len(i), 2 * (len(i) + len(others))
    pos = {int(p): j for j, p in enumerate(np.concatenate([i, others]))}
    every_pair = [pr for c, _ in groups for pr in c.pairs] + [pr for c in foreign for pr in c.pairs]
    ups = np.array([pos[up] for up, _ in every_pair], dtype=np.int64)
    los = np.array([pos[lo] for _, lo in every_pair], dtype=np.int64)
    gw = np.concatenate([np.ones(sum(len(c.pairs) for c, _ in groups)),
                         np.full(sum(len(c.pairs) for c in foreign), spill)])  # a foreign gap weighs as a spill row
    boost = np.ones(g_c.shape)

    def row_weights(h, k):
        cw = np.repeat(cl[k] * h[k], 2, axis=1)
        if len(ups):
            hp = np.minimum(h[k][:, ups], h[k][:, los])
            cw = np.concatenate([cw, contact_weight * gw * boost[k] * g_c[k] * hp], axis=1)
        return cw

    every = np.arange(T)
    h = np.ones((T, len(i) + len(others)))
    cw = row_weights(h, every)
    qp = dict(sparsity=sparsity, ridge=ridge, exclusive=exclusive, free=free, scale_rows=n_own)
    w, H, q, used = _slider_qps(A, b, rig.lower, rig.upper, cw, **qp)
    for _ in range(robust_iterations):
        e = np.linalg.norm((np.einsum("trn,tn->tr", A[:, :n_lm], w) - b[:, :n_lm]).reshape(T, -1, 2), axis=2)
        e *= scale[:, None]
        thr = np.maximum(ROBUST_PX, 2.0 * np.median(e, axis=1))
        h = np.minimum(1.0, thr[:, None] / np.maximum(e, 1e-12))
        cw = row_weights(h, every)
        w, H, q, used = _slider_qps(A, b, rig.lower, rig.upper, cw, **qp)
    shut = b[:, n_lm:] <= closed + tol  # the actor's feature is closed: contact
    todo = every if len(ups) else every[:0]
    for _ in range(CONTACT_PASSES):
        if not todo.size:
            break
        g = np.einsum("trn,tn->tr", A[todo, n_lm:], w[todo])
        off = (g < closed[todo] - tol[todo]) | (shut[todo] & (np.abs(g - b[todo, n_lm:]) > tol[todo]))
        more = off.any(axis=1)
        todo, off = todo[more], off[more]
        if not todo.size:
            break
        bt = boost[todo]
        bt[off] *= CONTACT_BOOST
        boost[todo] = bt
        cw[todo] = row_weights(h, todo)
        w[todo], Ht, q[todo], used[todo] = _slider_qps(A[todo], b[todo], rig.lower, rig.upper, cw[todo], **qp)
        for j, k in enumerate(todo):
            H[k] = Ht[j]
    return [_RegionFit(w[k], H[k], q[k] if H[k] is not None else None, used[k], A[k], b[k], cw[k], n_lm,
                       float(scale[k]), n_own, tol[k]) for k in range(T)]


def _slider_qps(A, b, lower, upper, CW, *, sparsity, ridge, exclusive, free, scale_rows=None):
    """:func:`_slider_qp` of many frames at once: ``A`` (T, r, n), ``b`` (T, r), ``CW`` (T, r) row weights
    (*scale_rows* as :func:`fit_sliders`'s).

    Every frame's QP (its own Hessian ``Aᵀ diag(c) A`` with the ridge and sparsity of :func:`fit_sliders`) is
    solved over its own free sliders by :func:`~retarget_cli.methods.decomposition.boxqp.box_qp_masked` (every
    frame in one call of the compiled kernel, whatever its free set); a frame where both sliders of an exclusive pair are active loses the weaker one and is
    solved again, as :func:`_slider_qp` does.

    Returns
    -------
    w : ndarray, shape (T, n)
    H : list of (ndarray (n, n) or None)
        None where nothing is free (or the frame's rows weigh nothing).
    q : ndarray, shape (T, n)
    free : ndarray of bool, shape (T, n)
    """
    T, _, n = A.shape
    lo = np.broadcast_to(np.asarray(lower, dtype=np.float64), (n,)).copy()
    hi = np.broadcast_to(np.asarray(upper, dtype=np.float64), (n,)).copy()
    if np.any(lo > 0) or np.any(hi < 0):
        raise ParameterError("fit_sliders: every slider range must contain 0 (the rest pose)")
    pairs = np.zeros((0, 2), np.int64) if exclusive is None else np.asarray(exclusive, dtype=np.int64).reshape(-1, 2)
    F = np.tile(np.asarray(free, dtype=bool), (T, 1))
    w = np.zeros((T, n))
    BtC = A.transpose(0, 2, 1) * CW[:, None, :]
    Hs = BtC @ A
    q = (BtC @ b[..., None])[..., 0]
    kr = A.shape[1] if scale_rows is None else scale_rows
    hbar = np.array([float(np.mean(((CW[k, :kr, None] * A[k, :kr] ** 2).sum(axis=0))[F[k]])) if F[k].any() else 0.0
                     for k in range(T)])
    ok = hbar > 0
    F[~ok] = False
    Hs = Hs + (ridge * hbar)[:, None, None] * np.eye(n)
    q = q - (sparsity * hbar)[:, None] * (lo >= 0)
    todo = np.flatnonzero(ok)
    for _ in range(len(pairs) + 1):
        if not todo.size:
            break
        w[todo] = box_qp_masked(Hs[todo], q[todo], F[todo], lower=lo, upper=hi)
        if not len(pairs):
            break
        act = np.abs(w[todo]) > ACTIVE
        both = act[:, pairs[:, 0]] & act[:, pairs[:, 1]]
        again = both.any(axis=1)
        for k, hit in zip(todo[again], both[again]):
            for a, c in pairs[hit]:
                F[k, c if abs(w[k, c]) <= abs(w[k, a]) else a] = False
        todo = todo[again]
    H = [Hs[k] if ok[k] else None for k in range(T)]
    return w, H, q, F


@dataclass
class _RegionFit:
    """One region of one frame, fitted (:func:`_fit_region`): the sliders ``w`` (n,), the QP they solve (``H``
    (n, n) or None, ``q`` (n,), the sliders ``free`` in it), its rows ``A`` (r, n), ``b`` (r,) and weights ``cw``
    (r,), of which the first ``n_lm`` are landmark coordinates (the first ``n_own`` the region's own, the others'
    after them), the pixels per rig unit ``scale``, and each gap row's contact tolerance ``gap_tol``
    (r − n_lm,)."""

    w: np.ndarray
    H: np.ndarray | None
    q: np.ndarray | None
    free: np.ndarray
    A: np.ndarray
    b: np.ndarray
    cw: np.ndarray
    n_lm: int
    scale: float
    n_own: int | None = None
    gap_tol: np.ndarray | None = None

    def point_residuals(self, w) -> np.ndarray:
        """Weighted squared residual of *w* per landmark (its two rows together) and per gap row, (P,)."""
        return self.point_residuals_of(self.A @ w - self.b)

    def point_residuals_of(self, r) -> np.ndarray:
        """:meth:`point_residuals` of the row residuals *r* (r,)."""
        e = self.cw * np.asarray(r, dtype=np.float64) ** 2
        return np.concatenate([e[:self.n_lm].reshape(-1, 2).sum(axis=1), e[self.n_lm:]])

    def residual(self, w) -> tuple[float, float]:
        """The region's own landmark rows' weighted squared residual of *w* in pixels² and their total weight / 2."""
        k = self.n_lm if self.n_own is None else self.n_own
        res = (self.A[:k] @ w - self.b[:k]) * self.scale
        return float(np.sum(self.cw[:k] * res**2)), float(self.cw[:k].sum()) / 2


#: A landmark's floor in :func:`smooth_sliders`'s event test, as a fraction of the residual that the take's
#: tracking noise alone leaves there (:func:`tracking_noise`): where a per-frame fit cannot follow the noise its
#: residual is about that, so an event it passed still passes (a three-frame blink seen by its landmarks alone);
#: where a fit follows the noise (its residual far below it) the noise is not taken for events.
NOISE_FLOOR = 0.5
#: A contact gap's floor in :func:`smooth_sliders`'s event test, in squares of its contact tolerance
#: (``contact_tol``): an excess within about 1.7 tolerances is not an event. On the 12 runs of ``bench/peer.py``
#: the character's jitter 2.83 (×1000) and closed-eye contact 96.0 % (3.65 and 96.1 % without floors); with the
#: landmarks' floor at the whole noise residual, 2, 3 and 4 gave 2.50, 2.41 and 2.24, and 96.2, 96.0 and 95.6 %.
GAP_FLOOR = 3.0


def tracking_noise(points) -> np.ndarray:
    """The take's tracking noise per landmark coordinate: the robust standard deviation of its second difference
    over frames (1.4826 × its median absolute value), / √6, what white noise gives. A blink or a fast word
    moves few frames and leaves the median; the head's motion is smooth at this scale.

    Parameters
    ----------
    points : array_like, shape (K, L, 2)
        Pixels (non-finite frames are skipped).

    Returns
    -------
    ndarray, shape (L, 2)
        Pixels (0 with fewer than 3 frames).
    """
    P = np.asarray(points)
    out = np.zeros(P.shape[1:])
    if len(P) < 3:
        return out
    for k in range(P.shape[1]):  # a landmark at a time: a long take's (K, L, 2) is not copied
        x = P[:, k].astype(np.float64)
        d2 = np.abs(x[2:] - 2.0 * x[1:-1] + x[:-2])
        d2 = d2[np.isfinite(d2).all(axis=1)]
        if len(d2):
            out[k] = 1.4826 * np.median(d2, axis=0) / np.sqrt(6.0)
    return out


def noise_floor(fits, noise_px) -> np.ndarray:
    """Per frame and point of a region's rows (its landmarks, then its contact gaps), the floor of the event test.

    A landmark's is :data:`NOISE_FLOOR` times the weighted squared residual that the tracking noise alone leaves
    (*noise_px*, over each frame's pixels per rig unit). A contact gap's is :data:`GAP_FLOOR` times its weighted
    squared tolerance: the gap rows, boosted where contact is off, leave no residual in the per-frame fits, and
    the landmarks' noise (filtered) would leave them as sensitive as without a floor.

    Parameters
    ----------
    fits : list of _RegionFit
        One per frame.
    noise_px : ndarray, shape (M, 2)
        The tracking noise of the rows' landmarks, in their order, pixels (:func:`tracking_noise`).

    Returns
    -------
    ndarray, shape (T, P)
    """
    sigma = np.sqrt(NOISE_FLOOR) * np.asarray(noise_px, dtype=np.float64).ravel()
    return np.stack([f.point_residuals_of(np.r_[sigma / f.scale, np.sqrt(GAP_FLOOR) * (
        f.gap_tol if f.gap_tol is not None else np.zeros(len(f.b) - f.n_lm))]) for f in fits])


def smooth_sliders(fits, M, lower, upper, *, lam: float, robust: float = DEFAULT_SMOOTH_ROBUST, passes: int = 3,
                   point_factor: float = 5.0, noise=None) -> np.ndarray:
    """One region's sliders over consecutive frames, smoothed where the face does not move fast.

    The per-frame fits of :func:`delta_pose` (their QPs, with the Huber weights and the exclusive pairs'
    choices of each frame) joined by the acceleration of the rig's landmarks, as the ``temporal`` solver
    of the decomposition does for key weights in shape space (docs/temporal.md):

    .. math::

        \\min_{l \\le w_t \\le u} \\sum_t \\tfrac12 w_t^T H_t w_t - q_t^T w_t
        + \\tfrac{\\lambda}{2} \\sum_t \\rho_t \\lVert w_{t-1} - 2 w_t + w_{t+1} \\rVert_M^2

    with ``M = Σ_i P D_iᵀ P D_i`` over the region's landmarks (rig units, so ``λ`` is unitless). Sliders a
    frame's fit held at 0 stay at 0 there. ``ρ_t`` is released (0) around fast events, by the test of
    :func:`retarget_cli.methods.decomposition.temporal.event_terms` on each landmark's (and gap's) excess
    residual over its per-frame fit, so blinks keep their amplitude; with *noise*, an excess within the take's
    tracking noise is not an event (on a rig that can follow the noise the per-frame fits leave a residual far
    below it: d9's brows behind glasses were released on 39 % of the frames). Solved exactly by
    :func:`retarget_cli.methods.decomposition.temporal.sparse_box_qp`.

    Parameters
    ----------
    fits : list of _RegionFit
        One per frame, in order.
    M : ndarray, shape (n, n)
    lower, upper : ndarray, shape (n,)
    lam : float
        ``λ`` (0: the per-frame fits).
    robust, point_factor : float
        The event test's thresholds (``robust`` 0: no release).
    passes : int
    noise : ndarray, shape (M, 2), optional
        The tracking noise (pixels, :func:`tracking_noise`) of the rows' landmarks, in their order: each point's
        unit in the event test is at least :func:`noise_floor`, so that the noise a per-frame fit followed (on a
        rig whose sliders can) is smoothed, not taken for an event.

    Returns
    -------
    ndarray, shape (T, n)
    """
    from scipy import sparse

    T = len(fits)
    W0 = np.stack([f.w for f in fits]) if fits else np.zeros((0, len(lower)))
    if T < 3 or not lam > 0:
        return W0
    n = W0.shape[1]
    live = np.stack([f.free if f.H is not None else np.zeros(n, dtype=bool) for f in fits])
    cols = np.flatnonzero(live.any(axis=0))  # sliders free in some frame
    if not cols.size:
        return W0
    k = len(cols)
    Hb = np.stack([f.H[np.ix_(cols, cols)] if f.H is not None else np.eye(k) for f in fits])
    q = np.concatenate([f.q[cols] if f.q is not None else np.zeros(k) for f in fits])
    var = live[:, cols].ravel()  # the unknowns: (frame, slider) pairs a frame's fit left free
    lo = np.tile(np.asarray(lower, dtype=np.float64)[cols], T)[var]
    hi = np.tile(np.asarray(upper, dtype=np.float64)[cols], T)[var]
    blocks = sparse.bsr_matrix((Hb, np.arange(T), np.arange(T + 1)), shape=(T * k, T * k)).tocsr()
    D2 = _second_difference(T)
    Mk = sparse.csr_matrix(np.asarray(M, dtype=np.float64)[np.ix_(cols, cols)])
    p0 = np.stack([f.point_residuals(f.w) for f in fits])
    floor = None if noise is None else noise_floor(fits, noise)
    rho = np.ones(T - 2)
    W = W0
    for it in range(max(int(passes), 1)):
        pen = sparse.kron(D2.T @ sparse.diags(rho) @ D2, Mk, format="csr")
        Hv = (blocks + lam * pen)[var][:, var]
        x, settled = sparse_box_qp(Hv, q[var], lo, hi, W0[:, cols].ravel()[var])
        if not settled:
            log.warning("auto-pose: the smoothing of %d frames did not settle; its last iterate is kept", T)
        full = np.zeros(T * k)
        full[var] = x
        W = W0.copy()
        W[:, cols] = full.reshape(T, k)
        if not robust > 0 or it == passes - 1:
            break
        p = np.stack([f.point_residuals(w) for f, w in zip(fits, W)])
        touch = event_terms(p, p0, robust=robust, point_factor=point_factor, point_floor=floor)
        if not np.any(touch & (rho > 0)):
            break
        rho[touch] = 0.0
    return W


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
    "DEFAULT_RIDGE", "DEFAULT_SPARSITY", "DEPTH_RATIO", "delta_pose", "depth_sliders", "exclusive_indices",
    "fit_sliders", "infer_exclusive", "project", "region_scales", "rig_curves", "rig_landmarks", "rig_region_masks",
    "slider_owners",
]
