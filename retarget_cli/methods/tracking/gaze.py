"""Gaze: where each iris sits between its eye corners, found in the image inside the tracked eye.

The 68 landmarks bound each eye (corners and lids) but say nothing of the
iris. Inside each eye, mapped to a small upright patch whose width is the
eye's and masked to the lids' outline, the iris centre is the centroid of the
pixels darker than the eye's 40th gray-level percentile, weighted by the
square of how much darker they are (the iris and pupil are the darkest part of
an open eye). Its offset from the corners' midpoint, along and across the
corner line and in eye widths, is the gaze. Measured against MediaPipe Face
Mesh's iris on the shared clips whose gaze moves (``bench/gaze_head.py``), this
beat the gradient locator of Timm & Barth (2011, eq. 3 with its darkness
weight) and a dark-disk template of the iris's size horizontally. A closed or nearly closed eye shows no iris: the gaze holds its last
open value there, so a blink never moves it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import ShapeError

#: The two eyes of the 68-point layout, each as (left corner in the image, right corner, upper lid, lower lid):
#: the actor's right eye (36-41) is on the image's left.
EYES_68 = (
    (36, 39, (37, 38), (41, 40)),
    (42, 45, (43, 44), (47, 46)),
)

#: Patch geometry: the eye's corner-to-corner width in patch pixels, and the patch size (width, height).
_WIDTH = 40.0
_PATCH = (60, 36)


@dataclass(frozen=True)
class Gaze:
    """Per-frame gaze of both eyes.

    Attributes
    ----------
    offset : ndarray (T, 2, 2), float64
        For eye 0 (the actor's right, image left) and eye 1, the iris centre's offset from the corners'
        midpoint in eye widths: ``[..., 0]`` along the corner line (> 0 toward the image's right: the
        actor looks to their left), ``[..., 1]`` across it (> 0 downward in the image).
    opening : ndarray (T, 2), float64
        Lid gap over eye width; below the *closed* threshold the offset is held.
    held : ndarray (T, 2), bool
        Frames whose offset was held (eye closed, or its points lost).
    """

    offset: np.ndarray
    opening: np.ndarray
    held: np.ndarray


def eye_frame(points: np.ndarray, eye) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The corners' midpoint (2,), the unit axis along the corners (2,), across them (2,), and the eye width."""
    left, right = points[eye[0]], points[eye[1]]
    d = right - left
    w = float(np.hypot(*d))
    x = d / max(w, 1e-9)
    y = np.array([-x[1], x[0]])
    return (left + right) / 2.0, x, y, w


def _patch(gray: np.ndarray, mid, x, y, w) -> tuple[np.ndarray, np.ndarray]:
    """The eye region warped upright to :data:`_PATCH`, and the affine map from image to patch (2, 3)."""
    import cv2

    s = _WIDTH / max(w, 1e-9)
    A = np.array([[x[0] * s, x[1] * s, 0.0], [y[0] * s, y[1] * s, 0.0]])
    A[:, 2] = np.array(_PATCH, dtype=np.float64) / 2.0 - A[:, :2] @ mid
    patch = cv2.warpAffine(gray, A, _PATCH, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return patch.astype(np.float64), A


def _eye_mask(points: np.ndarray, eye, A: np.ndarray) -> np.ndarray:
    """Inside the eye's outline (corners and lids) in the patch, bool (H, W)."""
    import cv2

    outline = [eye[0], eye[2][0], eye[2][1], eye[1], eye[3][1], eye[3][0]]
    poly = points[outline] @ A[:, :2].T + A[:, 2]
    mask = np.zeros(_PATCH[::-1], np.uint8)
    cv2.fillPoly(mask, [np.round(poly * 4).astype(np.int32)], 1, shift=2)
    return mask.astype(bool)


def iris_centre(patch: np.ndarray, mask: np.ndarray, *, percentile: float = 40.0) -> np.ndarray | None:
    """The iris centre in an upright eye patch: the darkness-weighted centroid inside the lids.

    Parameters
    ----------
    patch : ndarray (H, W), float
        Gray levels.
    mask : ndarray (H, W), bool
        Inside the lids.
    percentile : float
        Pixels darker than this percentile of the masked gray levels count, weighted by the square of
        their difference to it.

    Returns
    -------
    ndarray (2,) or None
        ``(x, y)`` in patch pixels, None when the mask is (nearly) empty or uniform.
    """
    import cv2

    if mask.sum() < 8:
        return None
    gray = cv2.GaussianBlur(patch, (0, 0), 1.0)[mask]
    w = np.maximum(np.percentile(gray, percentile) - gray, 0.0) ** 2
    if w.sum() <= 0:
        return None
    yx = np.argwhere(mask).astype(np.float64)
    return (yx * w[:, None]).sum(axis=0)[::-1] / w.sum()


def gaze(frames, points, *, confidence=None, closed: float = 0.12, progress=None) -> Gaze:
    """The gaze of both eyes in every frame (see the module docstring).

    Parameters
    ----------
    frames : iterable of ndarray (H, W) or (H, W, 3), uint8
        The frames the points were tracked on (gray or BGR).
    points : ndarray (T, 68, 2)
        The tracked landmarks, image pixels.
    confidence : ndarray (T, 68), optional
        An eye with a corner or lid point below 0.1 is treated as closed.
    closed : float
        Lid gap over eye width below which an eye counts as closed.
    progress : callable, optional
        Called once per frame.

    Returns
    -------
    Gaze
    """
    import cv2

    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (68, 2):
        raise ShapeError(f"points: expected shape (T, 68, 2), got {P.shape}")
    T = len(P)
    offset = np.full((T, 2, 2), np.nan)
    opening = np.zeros((T, 2))
    held = np.ones((T, 2), dtype=bool)
    t = -1
    for t, frame in enumerate(frames):
        if t >= T:
            break
        gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if frame.ndim == 3 else frame
        for e, eye in enumerate(EYES_68):
            ids = [eye[0], eye[1], *eye[2], *eye[3]]
            if not np.all(np.isfinite(P[t, ids])) or (confidence is not None and np.min(confidence[t, ids]) < 0.1):
                continue
            mid, x, y, w = eye_frame(P[t], eye)
            gap = np.mean([np.hypot(*(P[t, a] - P[t, b])) for a, b in zip(eye[2], eye[3])])
            opening[t, e] = gap / max(w, 1e-9)
            if opening[t, e] < closed or w < 4:
                continue
            patch, A = _patch(gray, mid, x, y, w)
            c = iris_centre(patch, _eye_mask(P[t], eye, A))
            if c is not None:
                offset[t, e] = (c - np.array(_PATCH, dtype=np.float64) / 2.0) / _WIDTH
                held[t, e] = False
        if progress is not None:
            progress(1)
    if t + 1 < T:
        raise ShapeError(f"frames: {t + 1} frames for {T} frames of points")
    return Gaze(_hold(offset), opening, held)


def _hold(offset: np.ndarray) -> np.ndarray:
    """NaN frames take the last found value (the first found before it); none found: 0."""
    out = offset.copy()
    for e in range(out.shape[1]):
        found = np.flatnonzero(np.isfinite(out[:, e, 0]))
        if not len(found):
            out[:, e] = 0.0
            continue
        idx = np.maximum.accumulate(np.where(np.isfinite(out[:, e, 0]), np.arange(len(out)), -1))
        idx[idx < 0] = found[0]
        out[:, e] = out[idx, e]
    return out
