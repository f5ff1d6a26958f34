"""Pyramidal Lucas–Kanade landmark tracking with drift correction and a shape prior.

Chuang & Bregler (2002, §3) track facial features after removing the head's
affine motion. This tracker follows each landmark with OpenCV's pyramidal
Lucas–Kanade flow (Bouguet's implementation) from frame to frame and checks it
with a forward–backward pass. Frame-to-frame flow drifts, so every frame is
also re-registered against an annotated frame warped onto the current
estimate by the head similarity (a template update with drift correction;
for each point the pass with the smaller forward-backward error wins). Points that both passes fail are recovered from
a shape prior built from the annotated frames
(:class:`~retarget_cli.track.prior.ShapePrior`) and get confidence 0. Every
annotated frame it is given re-anchors the track and becomes a reference.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable

import numpy as np

from ..errors import InputError, ShapeError
from .head import default_rigid_points, fit_similarity
from .prior import ShapePrior

log = logging.getLogger(__name__)

class FaceLostError(InputError):
    """The face was lost: too few landmarks tracked for several frames.

    Attributes
    ----------
    frame : int
        Index (in the frames given) of the first frame of the lost run.
    points, confidence : ndarray
        What was tracked before the face was lost, shapes (frame, L, 2) and (frame, L).
    """

    def __init__(self, message, frame, points, confidence):
        super().__init__(message)
        self.frame, self.points, self.confidence = frame, points, confidence


def _gray(frame: np.ndarray) -> np.ndarray:
    import cv2

    if frame.ndim == 3:
        return cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    return frame


def flow_forward_backward(src, dst, points, lk: dict, guess=None, lk_init: dict | None = None):
    """Pyramidal LK from *src* to *dst* and back, with the forward–backward error.

    Parameters
    ----------
    src, dst : ndarray, shape (H, W), uint8
    points : ndarray, shape (L, 1, 2), float32
        Positions in *src*.
    lk : dict
        ``cv2.calcOpticalFlowPyrLK`` keyword arguments.
    guess : ndarray, shape (L, 1, 2), float32, optional
        Initial positions in *dst*, used with *lk_init* (which must carry
        ``flags=cv2.OPTFLOW_USE_INITIAL_FLOW``).

    Returns
    -------
    moved : ndarray, shape (L, 1, 2), float32
        Positions in *dst*.
    error : ndarray, shape (L,)
        Forward–backward distance in pixels; ``inf`` where either pass failed.
    """
    import cv2

    if guess is None:
        fwd, st1, _ = cv2.calcOpticalFlowPyrLK(src, dst, points, None, **lk)
    else:
        fwd, st1, _ = cv2.calcOpticalFlowPyrLK(src, dst, points, guess, **(lk_init or lk))
    bwd, st2, _ = cv2.calcOpticalFlowPyrLK(dst, src, fwd, None, **lk)
    fb = np.linalg.norm((bwd - points).reshape(-1, 2), axis=1)
    ok = (st1.ravel() == 1) & (st2.ravel() == 1) & np.isfinite(fb)
    return fwd, np.where(ok, fb, np.inf)


class _Box:
    """The region of interest of the LK calls: ``[x0, x1) x [y0, y1)`` of the tracking image.

    Pyramidal LK at level ``k`` reads a ``window``-wide patch of the level-``k``
    image, i.e. ``window / 2 * 2**k`` pixels of the base image around each
    point, and builds (and differentiates) the pyramids of both whole images
    it is given. Cropping both images to the points' bounding box plus
    ``(window // 2 + 8) * 2**levels`` pixels keeps every patch (and the
    pyramid's filter support) inside the crop, so the flow is the same as on
    the full frame while the cost no longer grows with the video resolution.
    The corner is aligned to ``2**levels`` so every pyramid level samples the
    same pixels as the full frame's pyramid, and the crop keeps as many
    pyramid levels as the full frame (OpenCV drops levels narrower than the window).
    """

    def __init__(self, points, size, window: int, levels: int):
        w, h = size
        step = 2**levels
        margin = (window // 2 + 8) * step
        need = (window + 2) * step  # smallest crop keeping every pyramid level
        P = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if not np.isfinite(P).all():
            P = P[np.isfinite(P).all(1)]
        if len(P) == 0:
            self.x0, self.y0, self.x1, self.y1 = 0, 0, w, h
            return
        (x_lo, y_lo), (x_hi, y_hi) = P.min(0).tolist(), P.max(0).tolist()
        self.x0, self.x1 = self._span(x_lo - margin, x_hi + margin + 1, w, need, step)
        self.y0, self.y1 = self._span(y_lo - margin, y_hi + margin + 1, h, need, step)

    @staticmethod
    def _span(lo, hi, n, need, step):
        a = min(max(math.floor(lo), 0), n - 1) // step * step
        b = min(max(math.ceil(hi), a + 1), n)
        if b - a < need:
            b = min(n, a + need)
            a = max(0, b - need) // step * step
        return a, b

    @property
    def offset(self) -> np.ndarray:
        return np.array([self.x0, self.y0], dtype=np.float64)

    def crop(self, image: np.ndarray) -> np.ndarray:
        return image[self.y0:self.y1, self.x0:self.x1]

    def flow(self, src, dst, points, lk: dict, guess=None, lk_init: dict | None = None):
        """:func:`flow_forward_backward` between crops *src* and *dst* of this box, points in full-image pixels."""
        o = self.offset
        local = lambda p: None if p is None else (p.reshape(-1, 2) - o).astype(np.float32).reshape(-1, 1, 2)  # noqa: E731
        moved, err = flow_forward_backward(src, dst, local(points), lk, guess=local(guess), lk_init=lk_init)
        return (moved.reshape(-1, 2) + o).astype(np.float32).reshape(-1, 1, 2), err


def _contour_points(n_points: int) -> np.ndarray:
    """Default silhouette points: the jaw line of the 68-point layout."""
    return np.arange(17) if n_points == 68 else np.zeros(0, dtype=int)


def normalize_annotations(annotations) -> dict[int, np.ndarray]:
    """``(L, 2)`` array (frame 0) or ``{frame: (L, 2)}`` to a sorted dict of float64 arrays.

    Raises
    ------
    ShapeError
        If the shapes differ between frames (naming both counts) or a frame is negative.
    """
    if isinstance(annotations, dict):
        items = sorted((int(k), np.asarray(v, dtype=np.float64)) for k, v in annotations.items())
    else:
        items = [(0, np.asarray(annotations, dtype=np.float64))]
    if not items:
        raise ShapeError("annotations: at least one annotated frame is needed")
    L = None
    for f, P in items:
        if f < 0:
            raise ShapeError(f"annotations: frame numbers must be >= 0, got {f}")
        if P.ndim != 2 or P.shape[1] != 2 or len(P) == 0:
            raise ShapeError(f"annotations: frame {f}: expected shape (L, 2), got {P.shape}")
        if not np.all(np.isfinite(P)):
            raise ShapeError(f"annotations: frame {f}: coordinates must be finite")
        if L is None:
            L, first = len(P), f
        elif len(P) != L:
            raise ShapeError(f"annotations: frame {f} has {len(P)} points but frame {first} has {L}")
    return dict(items)


def check_inside(P, size, what: str) -> None:
    """Raise if any point of *P* (L, 2) lies outside an image of *size* ``(W, H)``."""
    w, h = size
    out = (P < -0.5).any(1) | (P[:, 0] > w - 0.5) | (P[:, 1] > h - 0.5)
    if out.any():
        i = int(np.flatnonzero(out)[0])
        raise ShapeError(f"{what}: point {i} at {P[i].round(1).tolist()} lies outside the {w}x{h} image "
                         f"({int(out.sum())} of {len(P)} points outside)")


class _Reference:
    """An annotated frame used as an anchor template."""

    def __init__(self, image, points, offsets):
        self.image = image
        self.points = points
        self.carriers = points + offsets

    def template(self, M, size, box: _Box | None = None):
        """Reference image warped by the similarity *M* (2, 3) and its carriers' positions in it.

        With *box*, only that crop of the warped image is rendered (the
        positions stay in full-image pixels).
        """
        import cv2

        if box is not None:
            M_box = M.copy()
            M_box[:, 2] -= box.offset
            img = cv2.warpAffine(self.image, M_box, (box.x1 - box.x0, box.y1 - box.y0), flags=cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_REPLICATE)
        else:
            img = cv2.warpAffine(self.image, M, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return img, self.carriers @ M[:, :2].T + M[:, 2]


def track_lk(
    frames: Iterable[np.ndarray],
    annotations,
    *,
    window: int = 21,
    levels: int = 3,
    fb_threshold: float = 1.0,
    anchor: bool = True,
    rigid_points=None,
    contour_points=None,
    shape_prior: bool = True,
    contour_refine: bool = True,
    downscale: float = 1.0,
    rigid_tolerance: float = 3.0,
    lost_frames: int = 10,
    roi: bool = True,
    progress=None,
):
    """Track landmarks through a sequence of frames.

    Parameters
    ----------
    frames : iterable of ndarray, each shape (H, W, 3) or (H, W), uint8
        The frames, in order; the first one must be annotated.
    annotations : ndarray, shape (L, 2), or dict of int to ndarray (L, 2)
        Landmarks of the first frame, or of several frames keyed by their
        index in *frames* (0 must be among them). Every annotated frame
        re-anchors the track and becomes a reference template.
    window : int
        LK search window side in pixels (odd, >= 5), at the tracking resolution.
    levels : int
        Pyramid levels above the base image.
    fb_threshold : float
        Forward–backward error in pixels at which confidence falls to
        ``exp(-1)``; errors above 3x this mark a point as unreliable.
    anchor : bool
        Correct drift against the annotated frames (recommended).
    rigid_points : sequence of int, optional
        Points used for the similarity; default
        :func:`~retarget_cli.track.head.default_rigid_points`.
    contour_points : sequence of int, optional
        Silhouette points tracked through an inward proxy; default the jaw
        line (0-16) for the 68-point layout, none otherwise.
    shape_prior : bool
        Recover unreliable points from the shape model of the annotated
        frames (otherwise from the first annotation under the head similarity).
    contour_refine : bool
        Refine silhouette points along their normal by matching the annotated
        frame's intensity profile across the edge.
    downscale : float
        Factor in (0, 1] applied to the frames before tracking; coordinates
        are returned at full resolution.
    rigid_tolerance : float
        A rigid point further than this (full-resolution pixels) from where
        the head similarity puts it is unreliable (e.g. dragged by the
        teeth appearing in its window) and is recovered from the prior.
    lost_frames : int
        Raise :class:`FaceLostError` when fewer than a quarter of the points
        (or fewer than 2 rigid points) are reliable for this many frames in a row.
    roi : bool
        Run each LK call on a crop around the landmarks (see :class:`_Box`)
        instead of the whole frame: same flow up to float32 rounding, at a
        cost that does not grow with the video resolution.
    progress : callable, optional
        Called with the number of frames processed after each frame.

    Returns
    -------
    points : ndarray, shape (T, L, 2), float64
    confidence : ndarray, shape (T, L), float64 in [0, 1]

    Raises
    ------
    ShapeError
        Bad arguments, or annotations outside the image.
    FaceLostError
        The face was lost (carries what was tracked before).
    """
    import cv2

    ann = normalize_annotations(annotations)
    if 0 not in ann:
        raise ShapeError(f"annotations: the first frame must be annotated; annotated frames are {list(ann)[:5]}")
    if window < 5 or window % 2 == 0:
        raise ShapeError(f"window: expected an odd number >= 5, got {window}")
    if not 0 < downscale <= 1:
        raise ShapeError(f"downscale: expected a factor in (0, 1], got {downscale}")
    s = float(downscale)
    ann = {f: (P + 0.5) * s - 0.5 for f, P in ann.items()}  # OpenCV resize keeps pixel-centre alignment
    P0 = ann[0]
    L = len(P0)
    rigid = default_rigid_points(L) if rigid_points is None else np.asarray(rigid_points, dtype=int)
    if rigid.size < 2 or rigid.min() < 0 or rigid.max() >= L:
        raise ShapeError(f"rigid_points: need at least 2 indices in [0, {L}), got {rigid.tolist()}")
    contour = _contour_points(L) if contour_points is None else np.asarray(contour_points, dtype=int)
    lk = dict(winSize=(window, window), maxLevel=levels,
              criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 0.001))
    lk_init = dict(lk, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    # Silhouette points (the jaw line) have background under half their window,
    # which drags them when the head moves. Track a proxy moved inward by about
    # half a window instead and move the landmark by the proxy's displacement.
    offset0 = np.zeros((L, 2))
    if contour.size:
        inward = P0.mean(0) - P0[contour]
        inward /= np.maximum(np.linalg.norm(inward, axis=1, keepdims=True), 1e-9)
        offset0[contour] = inward * (window // 2 + 2)

    def prep(frame):
        g = _gray(frame)
        if s != 1:
            g = cv2.resize(g, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
        return g

    last_fit: list = [None, None]

    def similarity(src, dst, wts):
        # the head fit of the anchor pass often repeats the previous one
        # exactly (same rigid points and weights): reuse it
        args = (src[rigid], dst[rigid], wts[rigid])
        key = b"".join(np.ascontiguousarray(a).tobytes() for a in args)
        if key != last_fit[0]:
            last_fit[:] = key, fit_similarity(args[0], args[1][None], args[2][None])[0]
        return last_fit[1].copy()

    it = iter(frames)
    try:
        first = prep(next(it))
    except StopIteration:
        raise ShapeError("frames: the sequence is empty") from None
    h, w = first.shape[:2]
    scale_back = lambda P: (P + 0.5) / s - 0.5  # noqa: E731
    check_inside(P0, (w, h), "annotations: frame 0")
    prior = ShapePrior(np.stack(list(ann.values()))) if shape_prior else ShapePrior(P0[None])
    refs = [_Reference(first, P0, offset0)]
    # Silhouette points are then refined along their normal by matching the
    # annotated frame's intensity profile across the edge (ASM-style).
    profile = _Profiles(first, P0[contour], offset0[contour]) if contour.size and contour_refine else None
    pts, conf = [scale_back(P0)], [np.ones(L)]
    Q0 = P0 + offset0
    prev, c_prev = first, Q0.copy()
    is_rigid = np.isin(np.arange(L), rigid)
    lost_run = 0
    for t, frame in enumerate(it, start=1):
        cur = prep(frame)
        if cur.shape != first.shape:
            raise ShapeError(f"frames: frame {t} is {cur.shape[1]}x{cur.shape[0]}, the first was {w}x{h}")
        if t in ann:
            check_inside(ann[t], (w, h), f"annotations: frame {t}")
            p = ann[t]
            off = offset0 @ similarity(P0, p, np.ones(L))[:, :2].T
            refs.append(_Reference(cur, p, off))
            pts.append(scale_back(p))
            conf.append(np.ones(L))
            prev, c_prev, lost_run = cur, p + off, 0
            if progress is not None:
                progress(t)
            continue
        # 1. frame-to-frame flow of the carriers, checked forward-backward
        c0 = c_prev.astype(np.float32).reshape(-1, 1, 2)
        box = _Box(c0 if roi else [], (w, h), window, levels)
        fwd, err = box.flow(box.crop(prev), box.crop(cur), c0, lk)
        c_est = fwd.reshape(-1, 2).astype(np.float64)
        good = err < 3 * fb_threshold
        wts = good.astype(float) if good[rigid].sum() >= 2 else np.ones(L)
        off = offset0 @ similarity(Q0, c_est, wts)[:, :2].T
        est = c_est - off
        # 2. drift correction against the reference closest in shape
        if anchor:
            ref = refs[0] if len(refs) == 1 else min(refs, key=lambda r: _shape_distance(r.points, est, wts))
            M = similarity(ref.points, est, wts)
            c_tmpl = ref.carriers @ M[:, :2].T + M[:, 2]
            box = _Box(np.concatenate([c_tmpl, fwd.reshape(-1, 2)]) if roi else [], (w, h), window, levels)
            tmpl, c_tmpl = ref.template(M, (w, h), box)
            c_t = c_tmpl.astype(np.float32).reshape(-1, 1, 2)
            afw, aerr = box.flow(tmpl, box.crop(cur), c_t, lk, guess=fwd, lk_init=lk_init)
            use = aerr <= np.minimum(err, 3 * fb_threshold)
            c_est = np.where(use[:, None], afw.reshape(-1, 2), c_est)
            err = np.where(use, aerr, err)
            est = c_est - off
        if contour.size and profile is not None:
            est[contour] = profile.refine(cur, est[contour], off[contour])
        # 3. rigid points that left the head's similarity are unreliable, then
        # unreliable points are recovered from the shape prior
        good = err < 3 * fb_threshold
        Mr = similarity(P0, est, good.astype(float) if good[rigid].sum() >= 2 else np.ones(L))
        dev = np.linalg.norm(est[rigid] - (P0[rigid] @ Mr[:, :2].T + Mr[:, 2]), axis=1)
        good[rigid[dev > rigid_tolerance * s]] = False
        c = np.where(good, np.exp(-np.where(good, err, 0) / fb_threshold), 0.0)
        if (~good).any():
            fitw = np.where(good, c, 0.0)
            if fitw.sum() > 0:
                rec = prior.fit(est, fitw)
                if len(prior.sd) == 0 and fitw[rigid].sum() > 0 and (~good & is_rigid).any():
                    # the mean shape cannot follow expressions: place lost rigid
                    # points by the reliable rigid points only
                    rec[is_rigid] = prior.fit(est, np.where(is_rigid, fitw, 0.0))[is_rigid]
                est = np.where(good[:, None], est, rec)
                c_est = est + off
        if good.sum() < max(3, L // 4) or good[rigid].sum() < 2:
            lost_run += 1
            if lost_run >= lost_frames:
                f0 = t - lost_run + 1
                raise FaceLostError(
                    f"the face was lost from frame {f0}: fewer than {max(3, L // 4)} of {L} landmarks "
                    f"tracked for {lost_run} frames", f0, np.stack(pts[:f0]), np.stack(conf[:f0]))
        else:
            lost_run = 0
        pts.append(scale_back(est))
        conf.append(c)
        prev, c_prev = cur, c_est
        if progress is not None:
            progress(t)
    if 0 < lost_run:
        log.warning("the last %d frames have fewer than %d reliable landmarks", lost_run, max(3, L // 4))
    return np.stack(pts), np.clip(np.stack(conf), 0.0, 1.0)


class _Profiles:
    """Intensity profiles across the silhouette, for refining contour points along their normal.

    Active-shape-model style: at each contour point of the reference frame an
    intensity profile is sampled along the inward normal (mostly skin, plus
    the edge); in a new frame the profile is searched along the current
    normal around the proxy-based estimate by normalised cross-correlation.
    """

    def __init__(self, image, points, offsets, *, inside: float = 8.0, outside: float = 2.0,
                 search: float = 4.0, step: float = 0.5, min_ncc: float = 0.7):
        self.u = np.arange(-outside, inside + step / 2, step)
        self.shifts = np.arange(-search, search + step / 2, step)
        self.step, self.min_ncc = step, min_ncc
        n = offsets / np.maximum(np.linalg.norm(offsets, axis=1, keepdims=True), 1e-9)
        self.ref = self._norm(self._sample(image, points, n, self.u))

    @staticmethod
    def _norm(p):
        d = np.diff(p, axis=-1)
        d = d - d.mean(-1, keepdims=True)
        return d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-9)

    @staticmethod
    def _sample(image, points, normals, u):
        import cv2

        xy = points[:, None, :] + u[None, :, None] * normals[:, None, :]
        m = xy.astype(np.float32)
        return cv2.remap(image, m[..., 0], m[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
                         ).astype(np.float64)

    def refine(self, image, points, offsets) -> np.ndarray:
        n = offsets / np.maximum(np.linalg.norm(offsets, axis=1, keepdims=True), 1e-9)
        uu = (self.shifts[:, None] + self.u[None, :]).ravel()
        prof = self._sample(image, points, n, uu).reshape(len(points), len(self.shifts), len(self.u))
        ncc = (self._norm(prof) * self.ref[:, None, :]).sum(-1)
        k = ncc.argmax(1)
        best = ncc[np.arange(len(k)), k]
        # sub-sample parabola through the peak
        km, kp = np.clip(k - 1, 0, len(self.shifts) - 1), np.clip(k + 1, 0, len(self.shifts) - 1)
        a, b, c = ncc[np.arange(len(k)), km], best, ncc[np.arange(len(k)), kp]
        den = a - 2 * b + c
        frac = np.where((k > 0) & (k < len(self.shifts) - 1) & (den < 0), 0.5 * (a - c) / np.where(den < 0, den, -1), 0)
        shift = self.shifts[k] + frac * self.step
        ok = best > self.min_ncc
        return np.where(ok[:, None], points + shift[:, None] * n, points)


def _shape_distance(a, b, w) -> float:
    """Weighted RMS distance between shapes *a* and *b* (L, 2) after similarity alignment."""
    M = fit_similarity(a, b[None], w[None], iterations=0)[0]
    r = np.linalg.norm(a @ M[:, :2].T + M[:, 2] - b, axis=1)
    return float(np.sqrt((w * r**2).sum() / max(w.sum(), 1e-9)))
