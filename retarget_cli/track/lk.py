"""Pyramidal Lucas–Kanade landmark tracking with drift correction.

Chuang & Bregler (2002, §3) track facial features after removing the head's
affine motion. This tracker follows each landmark with OpenCV's pyramidal
Lucas–Kanade flow from frame to frame, checks it with a forward–backward pass,
and corrects drift by re-registering against the annotated frame warped by
the current head similarity (a template-update strategy with drift
correction). Points that fail both checks are recovered from the shape prior:
the annotated shape mapped through the head similarity.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable

import numpy as np

from ..errors import ShapeError
from .head import default_rigid_points, fit_similarity

log = logging.getLogger(__name__)


def _gray(frame: np.ndarray) -> np.ndarray:
    import cv2

    if frame.ndim == 3:
        return cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    return frame


def _contour_points(n_points: int) -> np.ndarray:
    """Default silhouette points: the jaw line of the 68-point layout."""
    return np.arange(17) if n_points == 68 else np.zeros(0, dtype=int)


def track_lk(
    frames: Iterable[np.ndarray],
    init_points,
    *,
    window: int = 21,
    levels: int = 3,
    fb_threshold: float = 1.0,
    anchor: bool = True,
    rigid_points=None,
    contour_points=None,
    progress=None,
):
    """Track landmarks through a sequence of frames.

    Parameters
    ----------
    frames : iterable of ndarray, each shape (H, W, 3) or (H, W), uint8
        The video, first frame being the annotated one.
    init_points : ndarray, shape (L, 2)
        Landmarks on the first frame, image pixels.
    window : int
        LK search window side in pixels (odd, >= 5).
    levels : int
        Pyramid levels above the base image.
    fb_threshold : float
        Forward–backward error in pixels at which confidence falls to
        ``exp(-1)``; errors above 3x this mark a point as lost.
    anchor : bool
        Correct drift against the annotated frame (recommended).
    rigid_points : sequence of int, optional
        Points used for the similarity that warps the anchor; default
        :func:`~retarget_cli.track.head.default_rigid_points`.
    contour_points : sequence of int, optional
        Silhouette points tracked through an inward proxy; default the jaw
        line (0-16) for the 68-point layout, none otherwise.
    progress : callable, optional
        Called with the number of frames processed after each frame.

    Returns
    -------
    points : ndarray, shape (T, L, 2), float64
    confidence : ndarray, shape (T, L), float64 in [0, 1]
    """
    import cv2

    P0 = np.asarray(init_points, dtype=np.float64)
    if P0.ndim != 2 or P0.shape[1] != 2 or len(P0) == 0:
        raise ShapeError(f"init_points: expected shape (L, 2), got {P0.shape}")
    if window < 5 or window % 2 == 0:
        raise ShapeError(f"window: expected an odd number >= 5, got {window}")
    L = len(P0)
    rigid = default_rigid_points(L) if rigid_points is None else np.asarray(rigid_points, dtype=int)
    lk = dict(
        winSize=(window, window),
        maxLevel=levels,
        criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 0.001),
    )
    contour = _contour_points(L) if contour_points is None else np.asarray(contour_points, dtype=int)
    # Silhouette points (the jaw line) have background under half their window,
    # which drags them when the head moves. Track a proxy moved inward by about
    # half a window instead and map it back with the current head similarity.
    offset = np.zeros((L, 2))
    if contour.size:
        inward = P0.mean(0) - P0[contour]
        inward /= np.maximum(np.linalg.norm(inward, axis=1, keepdims=True), 1e-9)
        offset[contour] = inward * (window // 2 + 2)
    it = iter(frames)
    try:
        first = _gray(next(it))
    except StopIteration:
        raise ShapeError("frames: the sequence is empty") from None
    h, w = first.shape[:2]
    if np.any(P0 < -0.5) or np.any(P0[:, 0] > w - 0.5) or np.any(P0[:, 1] > h - 0.5):
        bad = int(np.argwhere((P0 < -0.5).any(1) | (P0[:, 0] > w - 0.5) | (P0[:, 1] > h - 0.5))[0, 0])
        raise ShapeError(f"init_points: point {bad} at {P0[bad].round(1).tolist()} lies outside the {w}x{h} image")
    Q0 = P0 + offset
    pts = [P0.copy()]
    conf = [np.ones(L)]
    prev = first
    q_prev = Q0
    for t, frame in enumerate(it, start=1):
        cur = _gray(frame)
        p_prev = q_prev.astype(np.float32).reshape(-1, 1, 2)
        fwd, st1, _ = cv2.calcOpticalFlowPyrLK(prev, cur, p_prev, None, **lk)
        bwd, st2, _ = cv2.calcOpticalFlowPyrLK(cur, prev, fwd, None, **lk)
        fb = np.linalg.norm((bwd - p_prev).reshape(-1, 2), axis=1)
        ok = (st1.ravel() == 1) & (st2.ravel() == 1) & np.isfinite(fb)
        est = fwd.reshape(-1, 2).astype(np.float64)
        err = np.where(ok, fb, np.inf)
        # Head similarity from the annotated frame to the current estimate.
        c_fit = np.where(err < 3 * fb_threshold, 1.0, 0.0)
        if c_fit[rigid].sum() < 2:
            c_fit = np.ones(L)
        M = fit_similarity(Q0[rigid], est[None, rigid], c_fit[None, rigid])[0]
        prior = Q0 @ M[:, :2].T + M[:, 2]
        if anchor:
            # Re-register against the annotated frame warped by the head motion:
            # removes the drift that frame-to-frame flow accumulates.
            warped = cv2.warpAffine(first, M.astype(np.float64), (w, h), flags=cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_REPLICATE)
            ref_now = prior.astype(np.float32).reshape(-1, 1, 2)
            guess = est.astype(np.float32).reshape(-1, 1, 2).copy()
            afw, sa1, _ = cv2.calcOpticalFlowPyrLK(warped, cur, ref_now, guess,
                                                   flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
            abw, sa2, _ = cv2.calcOpticalFlowPyrLK(cur, warped, afw, ref_now.copy(),
                                                   flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
            afb = np.linalg.norm((abw - ref_now).reshape(-1, 2), axis=1)
            aok = (sa1.ravel() == 1) & (sa2.ravel() == 1) & np.isfinite(afb)
            aerr = np.where(aok, afb, np.inf)
            use = aerr <= np.minimum(err, 3 * fb_threshold)
            est = np.where(use[:, None], afw.reshape(-1, 2), est)
            err = np.where(use, aerr, err)
        lost = ~(err < 3 * fb_threshold)
        est[lost] = prior[lost]
        c = np.exp(-np.where(lost, np.inf, err) / fb_threshold)
        q_prev = est
        pts.append(est - offset @ M[:, :2].T)
        conf.append(np.where(lost, 0.0, c))
        prev = cur
        if progress is not None:
            progress(t)
    return np.stack(pts), np.clip(np.stack(conf), 0.0, 1.0)
