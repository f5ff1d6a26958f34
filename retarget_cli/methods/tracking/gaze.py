"""Gaze: where each iris sits between its eye corners, found in the image inside the tracked eye.

The 68 landmarks bound each eye (corners and lids) but say nothing of the
iris. Inside each eye, mapped to a small upright patch whose width is the
eye's and masked to the lids' outline grown by 0.05 eye widths (the tracked
lids often sit inside the visible eye, the upper one below the iris's top), the
iris centre is first the centroid of the pixels darker than the eye's 40th
gray-level percentile, weighted by the square of how much darker they are (the
iris and pupil are the darkest part of an open eye). Its horizontal position is
then averaged with the limbus's: the centre, within 0.15 eye widths of the
centroid on its row, whose circle of radius 0.24 eye widths has the strongest
bright-to-dark horizontal gradient on its left arc and dark-to-bright on its
right (the lids cut the circle's top and bottom; the sides are the iris's
sharpest edges, and dark lashes or lid shadows off the iris do not pull them as
they pull a centroid). Its offset from the corners' midpoint, along and across
the corner line and in eye widths, is the gaze. Measured against MediaPipe Face
Mesh's iris on the shared clips whose gaze moves (``bench/gaze_head.py``), this
beat the gradient locator of Timm & Barth (2011, eq. 3 with its darkness
weight), a dark-disk template of the iris's size, and the centroid or the limbus
alone horizontally.

A nearly shut eye shows little iris and its horizontal reading is mostly lashes:
between lid gaps of 0.25 and 0.10 eye widths it is drawn linearly toward the
take's median horizontal gaze (fully at 0.10). A closed eye shows no iris: the
gaze holds its last open value there, so a blink never moves it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

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
#: The lid mask grown by this many patch pixels (0.05 eye widths) on every side.
_GROW = 2
#: The limbus circle's radius, and how far from the centroid its centre is looked for, in eye widths.
_LIMBUS_RADIUS = 0.24
_LIMBUS_SPAN = 0.15


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


def patch_reads(points: np.ndarray) -> np.ndarray:
    """The image pixels each eye patch of :func:`gaze` reads, as boxes ``[x0, y0, x1, y1)`` (before they are clamped
    to the image, as ``BORDER_REPLICATE`` clamps what lies outside it), for every frame.

    The patch maps its corners back to the image through the eye's frame (:func:`eye_frame`); bilinear sampling
    reads the pixel below and the one above each position, and two more pixels are added on every side for the
    fixed-point rounding of OpenCV's warp.

    Parameters
    ----------
    points : ndarray (T, 68, 2)
        Landmarks, image pixels.

    Returns
    -------
    ndarray (T, 2, 4), int64
        Per frame, for each eye of :data:`EYES_68`; a frame whose eye corners are not finite has ``[0, 0, 0, 0]``.
    """
    P = np.asarray(points, np.float64)
    out = np.zeros((len(P), len(EYES_68), 4), np.int64)
    c = np.array(_PATCH, np.float64) / 2.0  # the patch pixel the eye's middle maps to (as in _patch)
    lo_q, hi_q = -c, np.array(_PATCH, np.float64) - 1.0 - c
    corners = np.array([[lo_q[0], lo_q[1]], [hi_q[0], lo_q[1]], [lo_q[0], hi_q[1]], [hi_q[0], hi_q[1]]])
    for e, eye in enumerate(EYES_68):
        left, right = P[:, eye[0]], P[:, eye[1]]
        d = right - left
        w = np.hypot(d[:, 0], d[:, 1])
        ok = np.isfinite(w)
        x = d / np.maximum(w, 1e-9)[:, None]
        y = np.stack([-x[:, 1], x[:, 0]], axis=1)
        mid = (left + right) / 2.0
        r = np.maximum(w, 1e-9) / _WIDTH  # image pixels per patch pixel
        img = mid[:, None] + r[:, None, None] * (corners[None, :, :1] * x[:, None] + corners[None, :, 1:] * y[:, None])
        img = np.where(ok[:, None, None], img, 0.0)
        box = np.concatenate([np.floor(img.min(axis=1)) - 2, np.ceil(img.max(axis=1)) + 4], axis=1)
        out[:, e] = np.clip(box, -2**40, 2**40).astype(np.int64)
    return out


#: The eyes' pixels kept while tracking (:func:`eye_crop`, so the gaze needs no second decoding of the video) reach
#: this many eye widths beyond what the patches read at the landmarks tracked up to the frame: the smoothed and
#: filtered landmarks the gaze reads lie a little elsewhere.
CROP_MARGIN = 0.25


def eye_crop(points: np.ndarray) -> tuple[int, int, int, int]:
    """The rectangle ``[x0, y0, x1, y1)`` (pixels, not clamped to the image) of a frame to keep for the gaze of
    landmarks near *points* (68, 2): around each eye, the box of its patch (:func:`patch_reads`: 1.5 by 0.9 eye
    widths along and across the corner line) grown by :data:`CROP_MARGIN` eye widths and 6 pixels on every side.
    Scalar arithmetic (it runs once a frame while tracking); :func:`crops_cover` checks what was kept."""
    a = 0.5 * _PATCH[0] / _WIDTH + CROP_MARGIN
    b = 0.5 * _PATCH[1] / _WIDTH + CROP_MARGIN
    lo_x = lo_y = float("inf")
    hi_x = hi_y = float("-inf")
    for eye in EYES_68:
        (ax, ay), (bx, by) = points[eye[0]].tolist(), points[eye[1]].tolist()
        dx, dy = abs(bx - ax), abs(by - ay)  # the eye width times the corner line's direction
        rx, ry = a * dx + b * dy + 6.0, a * dy + b * dx + 6.0
        mx, my = (ax + bx) / 2.0, (ay + by) / 2.0
        lo_x, lo_y, hi_x, hi_y = min(lo_x, mx - rx), min(lo_y, my - ry), max(hi_x, mx + rx), max(hi_y, my + ry)
    if not all(map(math.isfinite, (lo_x, lo_y, hi_x, hi_y))):
        return 0, 0, 0, 0
    return math.floor(lo_x), math.floor(lo_y), math.ceil(hi_x) + 1, math.ceil(hi_y) + 1


def crops_cover(boxes: np.ndarray, points: np.ndarray, confidence, size) -> np.ndarray:
    """Frames whose kept rectangle holds every pixel :func:`gaze` reads there (the eye patches it makes).

    Parameters
    ----------
    boxes : ndarray (T, 4), int
        The rectangle kept of each frame, ``[x0, y0, x1, y1)`` clamped to the image.
    points : ndarray (T, 68, 2)
        The landmarks the gaze reads.
    confidence : ndarray (T, 68) or None
        As :func:`gaze` takes it: an eye it skips (a point below 0.1 or not finite) needs no pixels.
    size : (int, int)
        The image's ``(W, H)``: what a patch reads outside it is the border's pixels (``BORDER_REPLICATE``).

    Returns
    -------
    ndarray (T,), bool
    """
    P = np.asarray(points, np.float64)
    W, H = (int(v) for v in size)
    need = patch_reads(P)
    need[..., 0::2] = np.clip(need[..., 0::2], 0, W)
    need[..., 1::2] = np.clip(need[..., 1::2], 0, H)
    need[..., 0] = np.minimum(need[..., 0], W - 1)  # a patch left or right of the image reads its edge column
    need[..., 1] = np.minimum(need[..., 1], H - 1)
    need[..., 2] = np.maximum(need[..., 2], 1)
    need[..., 3] = np.maximum(need[..., 3], 1)
    b = np.asarray(boxes, np.int64)[:, None, :]
    inside = (b[..., 0] <= need[..., 0]) & (b[..., 1] <= need[..., 1]) & (b[..., 2] >= need[..., 2]) & \
        (b[..., 3] >= need[..., 3])
    used = np.zeros(inside.shape, bool)
    for e, eye in enumerate(EYES_68):
        ids = [eye[0], eye[1], *eye[2], *eye[3]]
        used[:, e] = np.isfinite(P[:, ids]).all(axis=(1, 2))
        if confidence is not None:
            used[:, e] &= ~(np.min(np.asarray(confidence)[:, ids], axis=1) < 0.1)  # (NaN: used, as gaze does)
    return (inside | ~used).all(axis=1)


def _eye_mask(points: np.ndarray, eye, A: np.ndarray, grow: int = _GROW) -> np.ndarray:
    """Inside the eye's outline (corners and lids) in the patch, grown by *grow* pixels, bool (H, W)."""
    import cv2

    outline = [eye[0], eye[2][0], eye[2][1], eye[1], eye[3][1], eye[3][0]]
    poly = points[outline] @ A[:, :2].T + A[:, 2]
    mask = np.zeros(_PATCH[::-1], np.uint8)
    cv2.fillPoly(mask, [np.round(poly * 4).astype(np.int32)], 1, shift=2)
    if grow:
        mask = cv2.dilate(mask, np.ones((2 * grow + 1, 2 * grow + 1), np.uint8))
    return mask.astype(bool)


@lru_cache(maxsize=4)
def _limbus_kernel(radius: float) -> np.ndarray:
    """Correlation kernel (2n+1, 2n+1) of a circle's side arcs: -1 on the left arc, +1 on the right.

    Rows within 0.8 *radius* of the centre only (the lids cut the top and bottom); each arc point is split
    linearly between its two neighbouring columns.
    """
    n = int(np.ceil(radius)) + 2
    K = np.zeros((2 * n + 1, 2 * n + 1))
    for dy in range(-n, n + 1):
        if abs(dy) > 0.8 * radius:
            continue
        dx = np.sqrt(radius * radius - dy * dy)
        for sign in (-1.0, 1.0):
            x = n + sign * dx
            x0 = int(np.floor(x))
            f = x - x0
            K[n + dy, x0] += sign * (1.0 - f)
            K[n + dy, x0 + 1] += sign * f
    K.setflags(write=False)
    return K


def limbus_x(gray: np.ndarray, mask: np.ndarray, centre, *, radius: float, span: float) -> float | None:
    """The iris's horizontal centre from its limbus, near a first guess.

    Parameters
    ----------
    gray : ndarray (H, W), float
        The (blurred) eye patch.
    mask : ndarray (H, W), bool
        Where the eye is; gradients outside it are ignored.
    centre : ndarray (2,)
        The first guess ``(x, y)``, patch pixels; the rows ``y - 1 .. y + 1`` are searched.
    radius, span : float
        The limbus circle's radius, and the search's half-width around ``x``, patch pixels.

    Returns
    -------
    float or None
        The ``x`` whose circle's left arc has the strongest bright-to-dark horizontal gradient and its right
        arc dark-to-bright (Sobel ``d/dx`` correlated with :func:`_limbus_kernel`), as the mean of the
        positions scoring above half the best, weighted by how much; None when no position scores above 0.
    """
    import cv2

    gx = cv2.Sobel(gray, cv2.CV_64F, 1, 0, ksize=3) * mask
    score = cv2.filter2D(gx, -1, _limbus_kernel(radius), borderType=cv2.BORDER_CONSTANT)
    H, W = gray.shape
    yi = min(max(int(round(centre[1])), 0), H - 1)
    x0, x1 = max(int(round(centre[0] - span)), 0), min(int(round(centre[0] + span)), W - 1)
    if x1 < x0:
        return None
    row = score[max(yi - 1, 0):yi + 2, x0:x1 + 1].mean(axis=0)
    top = row.max()
    if top <= 0:
        return None
    w = np.maximum(row - 0.5 * top, 0.0)
    return float(x0 + (np.arange(len(row)) * w).sum() / w.sum())


def iris_centre(patch: np.ndarray, mask: np.ndarray, *, percentile: float = 40.0,
                limbus: bool = True) -> np.ndarray | None:
    """The iris centre in an upright eye patch: the darkness-weighted centroid inside the lids, its ``x``
    averaged with the limbus's (:func:`limbus_x`).

    Parameters
    ----------
    patch : ndarray (H, W), float
        Gray levels.
    mask : ndarray (H, W), bool
        Inside the lids.
    percentile : float
        Pixels darker than this percentile of the masked gray levels count, weighted by the square of
        their difference to it.
    limbus : bool
        Average the centroid's ``x`` with :func:`limbus_x` (radius :data:`_LIMBUS_RADIUS`, within
        :data:`_LIMBUS_SPAN` of it, in eye widths of :data:`_WIDTH` pixels); False: the centroid alone.

    Returns
    -------
    ndarray (2,) or None
        ``(x, y)`` in patch pixels, None when the mask is (nearly) empty or uniform.
    """
    import cv2

    if mask.sum() < 8:
        return None
    blurred = cv2.GaussianBlur(patch, (0, 0), 1.0)
    gray = blurred[mask]
    w = np.maximum(np.percentile(gray, percentile) - gray, 0.0) ** 2
    if w.sum() <= 0:
        return None
    yx = np.argwhere(mask).astype(np.float64)
    c = (yx * w[:, None]).sum(axis=0)[::-1] / w.sum()
    if limbus:
        x = limbus_x(blurred, mask, c, radius=_LIMBUS_RADIUS * _WIDTH, span=_LIMBUS_SPAN * _WIDTH)
        if x is not None:
            c[0] = 0.5 * (c[0] + x)
    return c


def gaze(frames, points, *, confidence=None, closed: float = 0.12, unsure: tuple[float, float] = (0.10, 0.25),
         progress=None) -> Gaze:
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
    unsure : (float, float)
        Lid gaps over eye width between which an eye's horizontal reading is drawn linearly toward the take's
        median horizontal gaze of that eye: fully at the first, not at all from the second on
        (:func:`draw_unsure`).
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
    return Gaze(_hold(draw_unsure(offset, opening, unsure)), opening, held)


def draw_unsure(offset: np.ndarray, opening: np.ndarray, unsure: tuple[float, float] = (0.10, 0.25)) -> np.ndarray:
    """Nearly shut eyes' horizontal readings drawn toward each eye's median over the seen frames.

    Parameters
    ----------
    offset : ndarray (T, E, 2)
        Gaze offsets, NaN where unseen (:class:`Gaze`'s ``offset`` before holding).
    opening : ndarray (T, E)
        Lid gap over eye width.
    unsure : (float, float)
        The reading is kept in full from a gap of ``unsure[1]`` on, replaced by the median at ``unsure[0]``
        and below, linearly in between; ``unsure[1] <= unsure[0]``: unchanged.

    Returns
    -------
    ndarray (T, E, 2)
        A copy; the vertical readings and the NaNs unchanged.
    """
    out = np.array(offset, dtype=np.float64, copy=True)
    lo, hi = unsure
    if hi <= lo:
        return out
    for e in range(out.shape[1]):
        seen = np.isfinite(out[:, e, 0])
        if seen.any():
            med = np.median(out[seen, e, 0])
            keep = np.clip((opening[:, e] - lo) / (hi - lo), 0.0, 1.0)
            out[:, e, 0] = med + (out[:, e, 0] - med) * keep
    return out


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
