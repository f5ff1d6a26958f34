"""Marker tracking: painted dots found as blobs, identities kept by assignment.

Each frame, dark dots are detected (morphological black-hat, threshold,
connected components, intensity-weighted centroids), every landmark's
position is predicted by pyramidal Lucas–Kanade flow from the previous frame,
and landmarks are matched to dots by minimum total distance (Hungarian
algorithm, :func:`scipy.optimize.linear_sum_assignment`) within a gate. A
landmark with no dot in its gate (occluded, merged with a neighbour, blinked
away) is flagged with confidence 0 and carried by its flow prediction, or by
the shape prior when the flow fails too; it is re-found as soon as a dot
reappears within the gate.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable

import numpy as np

from ...errors import FaceLostError, ShapeError
from .base import check_inside, flow_forward_backward, normalize_annotations
from .base import to_gray as _gray
from .prior import ShapePrior

log = logging.getLogger(__name__)


def detect_dots(gray, *, radius: float = 2.0, min_contrast: float = 25.0) -> np.ndarray:
    """Centres of small dark dots in a grey image.

    Parameters
    ----------
    gray : ndarray, shape (H, W), uint8
    radius : float
        Expected dot radius in pixels.
    min_contrast : float
        Minimum darkness below the surroundings, grey levels.

    Returns
    -------
    ndarray, shape (N, 2)
        Sub-pixel peaks of the black-hat response (darkness relative to a
        disc of twice the radius), smoothed at the dot's scale, pixels.
    """
    import cv2

    k = 2 * int(np.ceil(2 * radius)) + 1
    bh = cv2.morphologyEx(gray, cv2.MORPH_BLACKHAT, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    resp = cv2.GaussianBlur(bh.astype(np.float32), (0, 0), max(0.5, 0.6 * radius))
    # local maxima of the darkness response (touching dots stay separate)
    peak = (resp >= cv2.dilate(resp, np.ones((3, 3), np.uint8))) & (resp > min_contrast)
    ys, xs = np.nonzero(peak[1:-1, 1:-1])
    ys, xs = ys + 1, xs + 1
    if ys.size == 0:
        return np.zeros((0, 2))
    # sub-pixel centre: darkness-weighted centroid of the unsmoothed black-hat
    # over a disc of the dot's radius around the peak
    rr = int(np.ceil(radius))
    oy, ox = np.mgrid[-rr:rr + 1, -rr:rr + 1]
    disc = (ox**2 + oy**2) <= (radius + 0.5) ** 2
    oy, ox = oy[disc], ox[disc]
    H, W = gray.shape
    py = np.clip(ys[:, None] + oy[None], 0, H - 1)
    px = np.clip(xs[:, None] + ox[None], 0, W - 1)
    v = bh[py, px].astype(np.float64)
    v = np.clip(v - 0.25 * v.max(1, keepdims=True), 0, None)
    s = np.maximum(v.sum(1), 1e-9)
    return np.stack([(v * px).sum(1) / s, (v * py).sum(1) / s], 1)


def track_markers(frames: Iterable[np.ndarray], annotations, *, radius: float = 2.0, gate: float = 2.0,
                  contrast: float = 25.0, ambiguity: float = 1.5,
                  window: int = 11, levels: int = 3, lost_frames: int = 10, progress=None):
    """Track painted dots, one per landmark, from annotated frames.

    Parameters
    ----------
    frames : iterable of ndarray (H, W, 3) or (H, W), uint8
    annotations : ndarray (L, 2) or dict of int to ndarray (L, 2)
        Dot centres on annotated frames (0 must be annotated); annotated frames
        are taken as given.
    radius : float
        Dot radius in pixels.
    contrast : float
        Minimum darkness of a dot below its surroundings (smoothed black-hat), grey levels.
    gate : float
        Largest distance in pixels between a landmark's prediction and the dot it is assigned.
    ambiguity : float
        A match is skipped (the landmark flagged and carried by its flow) when
        another dot, or another landmark's prediction, lies within
        ``ambiguity * gate``: crowded dots would otherwise swap identities.
    window, levels : int
        Lucas–Kanade window and pyramid levels of the prediction.
    lost_frames : int
        Raise :class:`~retarget_cli.methods.tracking.lk.FaceLostError` when fewer than a
        quarter of the dots are found for this many frames in a row.
    progress : callable, optional

    Returns
    -------
    points : ndarray, shape (T, L, 2)
    confidence : ndarray, shape (T, L)
        1 for a dot found, 0 for a flagged (vanished) one.
    """
    import cv2
    from scipy.optimize import linear_sum_assignment

    ann = normalize_annotations(annotations)
    if 0 not in ann:
        raise ShapeError(f"annotations: the first frame must be annotated; annotated frames are {list(ann)[:5]}")
    if radius <= 0 or gate <= 0:
        raise ShapeError(f"radius and gate must be > 0, got {radius} and {gate}")
    lk = dict(winSize=(window, window), maxLevel=levels,
              criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    prior = ShapePrior(np.stack(list(ann.values())))
    it = iter(frames)
    try:
        prev = _gray(next(it))
    except StopIteration:
        raise ShapeError("frames: the sequence is empty") from None
    h, w = prev.shape
    check_inside(ann[0], (w, h), "annotations: frame 0")
    P = ann[0].copy()
    L = len(P)
    pts, conf = [P.copy()], [np.ones(L)]
    lost_run = 0
    for t, frame in enumerate(it, start=1):
        cur = _gray(frame)
        if t in ann:
            check_inside(ann[t], (w, h), f"annotations: frame {t}")
            P = ann[t].copy()
            pts.append(P.copy())
            conf.append(np.ones(L))
            prev = cur
            lost_run = 0
            if progress is not None:
                progress(t)
            continue
        p0 = P.astype(np.float32).reshape(-1, 1, 2)
        fwd, fb = flow_forward_backward(prev, cur, p0, lk)
        flow_ok = fb < 1.0
        pred = np.where(flow_ok[:, None], fwd.reshape(-1, 2), P)
        dots = detect_dots(cur, radius=radius, min_contrast=contrast)
        found = np.zeros(L, bool)
        new = pred.copy()
        if len(dots):
            D = np.linalg.norm(pred[:, None] - dots[None], axis=2)
            cost = np.where(D <= gate, D, 1e6)
            rows, cols = linear_sum_assignment(cost)
            ok = cost[rows, cols] < 1e6
            # ambiguous matches (another dot, or another landmark's prediction,
            # nearly as close) would swap identities of crowded dots: skip them
            Ds = np.sort(D, axis=1)
            second_dot = Ds[rows, 1] if D.shape[1] > 1 else np.full(len(rows), np.inf)
            Dc = np.sort(D[:, cols], axis=0)
            second_lm = Dc[1] if D.shape[0] > 1 else np.full(len(rows), np.inf)
            ok &= (second_dot > ambiguity * gate) & (second_lm > ambiguity * gate)
            new[rows[ok]] = dots[cols[ok]]
            found[rows[ok]] = True
        if found.sum() >= 3:
            # flagged dots whose flow failed too: put back by the shape prior
            fix = ~found & ~flow_ok
            if fix.any():
                new[fix] = prior.fit(new, found.astype(float))[fix]
        if found.sum() < max(3, L // 4):
            lost_run += 1
            if lost_run >= lost_frames:
                f0 = t - lost_run + 1
                raise FaceLostError(f"the face was lost from frame {f0}: fewer than {max(3, L // 4)} of {L} dots "
                                    f"found for {lost_run} frames", f0, np.stack(pts[:f0]), np.stack(conf[:f0]))
        else:
            lost_run = 0
        P = new
        pts.append(P.copy())
        conf.append(found.astype(float))
        prev = cur
        if progress is not None:
            progress(t)
    return np.stack(pts), np.stack(conf)
