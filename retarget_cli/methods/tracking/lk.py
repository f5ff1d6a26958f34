"""Pyramidal Lucas–Kanade landmark tracking with drift correction and a shape prior.

Chuang & Bregler (2002, §3) track facial features after removing the head's
affine motion. This tracker follows each landmark with OpenCV's pyramidal
Lucas–Kanade flow (Bouguet's implementation) from frame to frame, starting
from a constant-velocity prediction, and checks it with a forward–backward
pass (on the base image, from the prediction; points that fail it are
tracked again with plain forward–backward flow on the full pyramid).
Frame-to-frame flow drifts, so every frame is also re-registered against an
annotated frame warped onto the current estimate (a template update with
drift correction, Matthews et al. 2004) and relit to match it (gain times a
linear ramp, Hager & Belhumeur 1998). The warp is a moving-least-squares
similarity deformation (Schaefer et al. 2006) through the landmarks, so the
template follows expressions as well as the head; the annotated frame used
is the one closest in shape (the first one favoured). A point whose anchor match passes the forward–backward check is
pulled halfway to it. Edges (lips, brows, the jaw line) fix a landmark
across the edge only; along it LK drifts (the aperture problem). A
regularisation step therefore smooths the landmarks' displacements from the
reference shape across neighbours, weighted per point and direction by the
reference image's LK structure tensor (robust Huber weights let the mouth
open). Points that both passes fail are recovered from
a shape prior built from the annotated frames
(:class:`~retarget_cli.methods.tracking.prior.ShapePrior`) and get confidence 0. Every
annotated frame it is given re-anchors the track and becomes a reference.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable

import numpy as np

from ...errors import FaceLostError, InputError, ShapeError  # noqa: F401  (FaceLostError re-exported)
from ..blas import small_blas
from .base import check_inside, flow_forward_backward, normalize_annotations  # noqa: F401  (public here too)
from .base import to_gray as _gray
from .head import default_rigid_points, fit_similarity
from .prior import ShapePrior

log = logging.getLogger(__name__)

# Algorithm constants (dimensionless unless stated; "rms" is the RMS distance
# of the annotated landmarks from their centroid, i.e. the face size).
_ANCHOR_LEVELS = 1      # pyramid levels of the anchor pass (it starts from the flow estimate)
_BACK_LEVELS = 0        # pyramid levels of the backward flow check (it starts from the motion prediction)
_ANCHOR_GAIN = 0.5      # fraction of the way a point moves to its accepted anchor match
_MLS_SOFTNESS = 0.4     # softening radius of the MLS template warp, in rms
_SMOOTH_WEIGHT = 0.03   # weight of the displacement smoothness against the (normalised) LK information
_SMOOTH_RADIUS = 0.3    # Gaussian radius of the neighbourhood, in rms
_SMOOTH_HUBER = 1.0     # displacement difference (pixels at full resolution) beyond which smoothing is robust
_LIGHT_SAMPLES = 4096   # pixels sampled for the relighting fit (a strided grid over the face box)
_RIGID_WEIGHT = 3.0     # pull of rigid points to the head similarity in the regularisation
# Weight of the first annotation's shape distance when choosing the anchor
# reference. The proxies are defined on the first annotation (other references
# place them by the head similarity only), and the choice feeds on itself (the
# anchor pulls the estimate toward the reference in use): with plain distances
# the track locked onto an expression reference and the mouth stayed 0.6-1.5 px
# off for the last 10 % of 5-annotation takes. 0.7 and 0.5 were tried on the
# seed-0 takes (320, stressed, 720p, 1080p); 0.7 is better on all four and on
# seeds 1-2 (not used to choose it) it is no worse anywhere.
_FIRST_REFERENCE = 0.7





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

    def flow(self, src, dst, points, lk: dict, guess=None, lk_init: dict | None = None, back_guess=None,
             lk_back: dict | None = None):
        """:func:`flow_forward_backward` between crops *src* and *dst* of this box, points in full-image pixels."""
        o = self.offset
        local = lambda p: None if p is None else (p.reshape(-1, 2) - o).astype(np.float32).reshape(-1, 1, 2)  # noqa: E731
        moved, err = flow_forward_backward(src, dst, local(points), lk, guess=local(guess), lk_init=lk_init,
                                           back_guess=back_guess, lk_back=lk_back)
        return (moved.reshape(-1, 2) + o).astype(np.float32).reshape(-1, 1, 2), err


def _contour_points(n_points: int) -> np.ndarray:
    """Default silhouette points: the jaw line of the 68-point layout."""
    return np.arange(17) if n_points == 68 else np.zeros(0, dtype=int)


def _mouth_up(P0: np.ndarray) -> np.ndarray | None:
    """Unit normal of the mouth axis (60 -> 64) of the 68-point layout, pointing up in the image; None otherwise."""
    if len(P0) != 68:
        return None
    axis = P0[64] - P0[60]
    n = np.linalg.norm(axis)
    if n < 1e-9:
        return None
    up = np.array([axis[1], -axis[0]]) / n
    return -up if up[1] > 0 else up  # image y points down


def _inner_lip_offsets(P0: np.ndarray, length: float) -> dict[int, np.ndarray]:
    """Proxy offsets of the inner-lip points of the 68-point layout, into the lips.

    The inner lips border the mouth opening, whose appearance (dark interior,
    teeth) a closed-mouth annotation does not show; the upper points (61-63)
    are tracked through a proxy moved up into the upper lip, the lower ones
    (65-67) through one moved down into the lower lip, perpendicular to the
    mouth axis (60 -> 64). Empty for other layouts.
    """
    up = _mouth_up(P0)
    if up is None:
        return {}
    return {**{i: up * length for i in (61, 62, 63)}, **{i: -up * length for i in (65, 66, 67)}}


def _outer_lip_offsets(P0: np.ndarray, half: float) -> dict[int, np.ndarray]:
    """Proxy offsets of the outer-lip points of the 68-point layout, away from the mouth line.

    When the lips are thinner than the LK window, the window of an outer-lip
    point reaches across the lip seam into the other lip, which moves on its
    own when the jaw opens: the lower lip drags the upper-lip points down
    and the static upper lip holds the lower-lip points back. Each upper
    outer-lip point (49-53) is tracked through a proxy moved up, each lower
    one (55-59) through one moved down, perpendicular to the mouth axis
    (60 -> 64), by just enough that the window (*half* its side plus a
    margin) stays on its own side of the seam (the line 60 -> 64): ``max(0,
    half - distance to the seam)``. Zero when the lips are thick enough
    (high resolution); empty for other layouts.
    """
    up = _mouth_up(P0)
    if up is None:
        return {}
    out = {}
    for ids, sign in (((49, 50, 51, 52, 53), 1.0), ((55, 56, 57, 58, 59), -1.0)):
        for i in ids:
            dist = sign * float((P0[i] - P0[60]) @ up)
            out[i] = sign * up * max(0.0, half - dist)
    return out






class _Reference:
    """An annotated frame used as an anchor template.

    Parameters
    ----------
    image : ndarray, shape (H, W), uint8
    points, offsets : ndarray, shape (L, 2)
        Landmarks and the offsets of their tracked carriers (proxies).
    window : int
        LK window, for the structure tensors.
    """

    def __init__(self, image, points, offsets, window: int):
        self.image = image
        self.points = points
        self.carriers = points + offsets
        rms = float(np.sqrt(((points - points.mean(0)) ** 2).sum(1).mean()))
        self.soft = max(_MLS_SOFTNESS * rms, 1.0)
        self.info = _structure_tensors(image, self.carriers, window)
        d = np.linalg.norm(points[:, None] - points[None], axis=2)
        self.neighbours = np.exp(-0.5 * (d / max(_SMOOTH_RADIUS * rms, 1e-9)) ** 2)
        np.fill_diagonal(self.neighbours, 0.0)

    def template(self, est, c_est, margin: float):
        """Reference image warped onto the current estimate, and where its carriers land in it.

        The warp is the moving-least-squares similarity deformation (Schaefer
        et al. 2006, eqs. 5-6, with the softened weights
        ``1 / (|p - v|^2 + soft^2)``) taking the landmarks *est* to the
        reference landmarks, evaluated on a coarse grid over the face and
        interpolated bilinearly; outside the face's box plus *margin* the
        template is black.

        Parameters
        ----------
        est, c_est : ndarray, shape (L, 2)
            Current landmark and carrier estimates.
        margin : float
            Pixels around the carriers' bounding box to fill.

        Returns
        -------
        template : ndarray, shape (H, W), uint8
        carriers : ndarray, shape (L, 2)
            The reference carriers' positions in the template.
        """
        import cv2

        h, w = self.image.shape[:2]
        lo = np.floor(np.clip(c_est.min(0) - margin, 0, None)).astype(int)
        hi = np.ceil(np.minimum(c_est.max(0) + margin, (w - 1, h - 1))).astype(int)
        hi = np.maximum(hi, lo)
        # The map is evaluated on a coarse grid of nodes over the box padded
        # by a node on each side and upsampled bilinearly by cv2.resize,
        # which puts node k of n over N pixels at pixel (k + 1/2) N / n - 1/2.
        target = max(4.0, self.soft / 2)
        pad = int(np.ceil(target))
        o = lo - pad
        size = hi - lo + 1 + 2 * pad
        n = np.ceil(size / target).astype(int) + 1
        step = size / n
        gx = o[0] + (np.arange(n[0]) + 0.5) * step[0] - 0.5
        gy = o[1] + (np.arange(n[1]) + 0.5) * step[1] - 0.5
        X, Y = np.meshgrid(gx, gy)
        p = est[:, 0] + 1j * est[:, 1]
        q = self.points[:, 0] + 1j * self.points[:, 1]
        f, _ = _mls_similarity(p, q, (X + 1j * Y).ravel(), self.soft**2)
        fx = f.real.reshape(X.shape).astype(np.float32)
        fy = f.imag.reshape(X.shape).astype(np.float32)
        inner = np.s_[pad:pad + hi[1] - lo[1] + 1, pad:pad + hi[0] - lo[0] + 1]
        mx = cv2.resize(fx, (int(size[0]), int(size[1])), interpolation=cv2.INTER_LINEAR)[inner]
        my = cv2.resize(fy, (int(size[0]), int(size[1])), interpolation=cv2.INTER_LINEAR)[inner]
        img = np.zeros((h, w), np.uint8)
        img[lo[1]:hi[1] + 1, lo[0]:hi[0] + 1] = cv2.remap(self.image, mx, my, cv2.INTER_LINEAR,
                                                           borderMode=cv2.BORDER_REPLICATE)
        # The sampled map at the current carriers, then one Newton step (local
        # similarity factor a) to where the reference carriers land in the template.
        cu = ((c_est[:, 0] - o[0] + 0.5) / step[0] - 0.5).astype(np.float32)[None]
        cv_ = ((c_est[:, 1] - o[1] + 0.5) / step[1] - 0.5).astype(np.float32)[None]
        r = (cv2.remap(fx, cu, cv_, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0]
             + 1j * cv2.remap(fy, cu, cv_, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0])
        cz = c_est[:, 0] + 1j * c_est[:, 1]
        _, a = _mls_similarity(p, q, cz, self.soft**2)
        tz = cz + ((self.carriers[:, 0] + 1j * self.carriers[:, 1]) - r) / a
        return img, np.stack([tz.real, tz.imag], 1)


def _mls_similarity(p, q, v, soft2: float):
    """Moving-least-squares similarity deformation (Schaefer et al. 2006, eq. 6) in complex form.

    Parameters
    ----------
    p, q : ndarray, shape (L,), complex
        Control points and where they go.
    v : ndarray, shape (G,), complex
        Query points.
    soft2 : float
        Squared softening radius of the weights ``1 / (|p_i - v|^2 + soft2)``.

    Returns
    -------
    f : ndarray, shape (G,), complex
        Deformed query points.
    a : ndarray, shape (G,), complex
        Local similarity factor (scale and rotation) at each query point.
    """
    from ._kernels import mls_similarity

    v = np.ascontiguousarray(v, dtype=np.complex128)
    f, a = np.empty_like(v), np.empty_like(v)
    mls_similarity(np.ascontiguousarray(p, dtype=np.complex128), np.ascontiguousarray(q, dtype=np.complex128),
                   v, float(soft2), f, a)
    return f, a


def _match_lighting(template, image, points) -> np.ndarray:
    """The warped reference *template* relit to match *image*: gain times a linear ramp.

    The anchor pass compares the current frame with an annotated frame that
    may be hundreds of frames old; LK assumes brightness constancy, so a
    change of exposure or of the light's direction in between biases every
    anchor match (frame-to-frame flow does not see it: the light changes
    little between neighbouring frames). A low-order multiplicative light
    field ``I(x, y) ~ T(x, y) (a + b x + c y)`` (the illumination model of
    Hager & Belhumeur 1998, first order) is fitted by least squares over the
    landmarks' bounding box where the template is filled, with one
    reweighting step (Huber weights at twice the median absolute residual)
    against what the reference cannot show (the mouth opening, background),
    and applied to the whole template.

    Parameters
    ----------
    template, image : ndarray, shape (H, W), uint8
        Warped reference (0 where not filled) and current frame, same crop.
    points : ndarray, shape (L, 2)
        Landmark estimates in the crop's pixels.

    Returns
    -------
    ndarray, shape (H, W), uint8
        The relit template (unchanged where the fit is not possible).
    """
    import cv2

    from ._kernels import light_fit

    h, w = template.shape[:2]
    lo = np.clip(np.floor(points.min(0)).astype(int), 0, (w - 1, h - 1))
    hi = np.clip(np.ceil(points.max(0)).astype(int) + 1, lo + 1, (w, h))
    # a strided sample of the box is plenty for three coefficients of a smooth field
    step = max(1, int(np.sqrt((hi[0] - lo[0]) * (hi[1] - lo[1]) / _LIGHT_SAMPLES)))
    cx, cy = (lo + hi - 1) / 2
    sx, sy = max((hi[0] - lo[0]) / 2, 1.0), max((hi[1] - lo[1]) / 2, 1.0)
    T = template[lo[1]:hi[1]:step, lo[0]:hi[0]:step]
    u = (np.arange(lo[0], hi[0], step) - cx) / sx
    v = (np.arange(lo[1], hi[1], step) - cy) / sy
    coef = light_fit(np.ascontiguousarray(T), np.ascontiguousarray(image[lo[1]:hi[1]:step, lo[0]:hi[0]:step]),
                     u, v, 2)
    if (coef == (1.0, 0.0, 0.0)).all():  # the identity, also what too few samples give
        return template
    gx = (coef[0] + coef[1] * (np.arange(w) - cx) / sx).astype(np.float32)
    gy = (coef[2] * (np.arange(h) - cy) / sy).astype(np.float32)
    field = np.add.outer(gy, gx)
    if gx.min() + gy.min() < 0.5 or gx.max() + gy.max() > 2.0:  # the field is linear: its extremes are corners
        np.clip(field, 0.5, 2.0, out=field)
    return cv2.convertScaleAbs(cv2.multiply(template, field, dtype=cv2.CV_32F))


def _structure_tensors(image, points, window: int) -> np.ndarray:
    """LK structure tensors of *image* over a *window* square at *points*.

    ``sum [Ix^2, IxIy; IxIy, Iy^2]`` (Lucas & Kanade; the inverse covariance
    of an LK match up to the noise level), normalised by the median trace
    over the points so that it is independent of contrast.

    Returns
    -------
    ndarray, shape (L, 2, 2)
    """
    import cv2

    g = cv2.GaussianBlur(image.astype(np.float32), (0, 0), 1.0)
    ix = cv2.Scharr(g, cv2.CV_32F, 1, 0) / 32
    iy = cv2.Scharr(g, cv2.CV_32F, 0, 1) / 32
    k = (window, window)
    sxx, sxy, syy = (cv2.boxFilter(a, -1, k) for a in (ix * ix, ix * iy, iy * iy))
    h, w = image.shape[:2]
    xi = np.clip(np.round(points[:, 0]).astype(int), 0, w - 1)
    yi = np.clip(np.round(points[:, 1]).astype(int), 0, h - 1)
    G = np.empty((len(points), 2, 2))
    G[:, 0, 0], G[:, 0, 1], G[:, 1, 1] = sxx[yi, xi], sxy[yi, xi], syy[yi, xi]
    G[:, 1, 0] = G[:, 0, 1]
    return G / max(float(np.median(np.trace(G, axis1=1, axis2=2))), 1e-9)


def _regularize(est, ref: _Reference, M, confidence, rigid_mask, huber: float, iterations: int = 3):
    """Aperture-aware smoothing of the landmarks' displacements from the reference shape.

    With ``d_i = x_i - M(r_i)`` (landmark minus reference landmark under the
    head similarity *M*) and the measured ``m_i``, minimises

    ``sum_i c_i (d_i - m_i)^T G_i (d_i - m_i) + rho_i |d_i|^2
    + lambda sum_ij w_ij h_ij |d_i - d_j|^2``

    where ``G_i`` is the reference's LK structure tensor rotated by *M*,
    ``c_i`` the tracking confidence, ``rho_i`` pulls rigid points to the head
    similarity, ``w_ij`` Gaussian neighbourhood weights and ``h_ij`` Huber
    weights of the current differences (IRLS), so large true deformations
    (mouth opening) are not smoothed away. Where the image constrains a
    point in one direction only (an edge), the neighbours decide the other.

    Parameters
    ----------
    est : ndarray, shape (L, 2)
    ref : _Reference
    M : ndarray, shape (2, 3)
        Head similarity from the reference to the current frame.
    confidence : ndarray, shape (L,)
    rigid_mask : ndarray, shape (L,), bool
    huber : float
        Huber threshold in (tracking-resolution) pixels.

    Returns
    -------
    ndarray, shape (L, 2)
    """
    R = M[:, :2] / np.sqrt(max(abs(np.linalg.det(M[:, :2])), 1e-12))
    G = np.einsum("ij,ljk,mk->lim", R, ref.info, R) * confidence[:, None, None] + 0.01 * np.eye(2)
    base = ref.points @ M[:, :2].T + M[:, 2]
    m = est - base
    from ._kernels import regularize_solve

    # a multithreaded BLAS is ~10x slower on this small system on a busy machine
    with small_blas():
        d = regularize_solve(np.ascontiguousarray(G), np.ascontiguousarray(m), _RIGID_WEIGHT * rigid_mask.astype(float),
                             ref.neighbours, _SMOOTH_WEIGHT, float(huber), iterations)
    return base + d


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
        :func:`~retarget_cli.methods.tracking.head.default_rigid_points`.
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
    ann, s = _scaled_annotations(annotations, window, downscale)
    P0 = ann[0]
    L = len(P0)
    rigid = default_rigid_points(L) if rigid_points is None else np.asarray(rigid_points, dtype=int)
    if rigid.size < 2 or rigid.min() < 0 or rigid.max() >= L:
        raise ShapeError(f"rigid_points: need at least 2 indices in [0, {L}), got {rigid.tolist()}")
    contour = _contour_points(L) if contour_points is None else np.asarray(contour_points, dtype=int)
    offset0, boundary = _carrier_offsets(P0, contour, window)
    it = iter(frames)
    try:
        first = _prepare(next(it), s)
    except StopIteration:
        raise ShapeError("frames: the sequence is empty") from None
    h, w = first.shape[:2]
    check_inside(P0, (w, h), "annotations: frame 0")
    track = _LKTrack(first, ann, s, rigid, offset0, boundary, window=window, levels=levels, fb_threshold=fb_threshold,
                     anchor=anchor, shape_prior=shape_prior, contour_refine=contour_refine,
                     rigid_tolerance=rigid_tolerance, lost_frames=lost_frames, roi=roi)
    for t, frame in enumerate(it, start=1):
        cur = _prepare(frame, s)
        if cur.shape != first.shape:
            raise ShapeError(f"frames: frame {t} is {cur.shape[1]}x{cur.shape[0]}, the first was {w}x{h}")
        if t in ann:
            track.annotated(t, cur)
        else:
            track.step(t, cur)
        if progress is not None:
            progress(t)
    return track.finish()


def _scaled_annotations(annotations, window: int, downscale: float) -> tuple[dict[int, np.ndarray], float]:
    """The annotations checked and moved to the tracking resolution, and the scale factor (see :func:`track_lk`)."""
    ann = normalize_annotations(annotations)
    if 0 not in ann:
        raise ShapeError(f"annotations: the first frame must be annotated; annotated frames are {list(ann)[:5]}")
    if window < 5 or window % 2 == 0:
        raise ShapeError(f"window: expected an odd number >= 5, got {window}")
    if not 0 < downscale <= 1:
        raise ShapeError(f"downscale: expected a factor in (0, 1], got {downscale}")
    s = float(downscale)
    return {f: (P + 0.5) * s - 0.5 for f, P in ann.items()}, s  # OpenCV resize keeps pixel-centre alignment


def _carrier_offsets(P0: np.ndarray, contour: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """Offsets of the tracked carriers (proxies) from the landmarks of *P0*, and the boundary points.

    Returns
    -------
    offsets : ndarray, shape (L, 2)
    boundary : ndarray of int
        The silhouette and inner-lip points (their proxies border appearance
        the annotated frames do not show).
    """
    # Silhouette points (the jaw line) have background under half their window,
    # which drags them when the head moves. Track a proxy moved inward by about
    # half a window instead and move the landmark by the proxy's displacement.
    offset0 = np.zeros((len(P0), 2))
    if contour.size:
        inward = P0.mean(0) - P0[contour]
        inward /= np.maximum(np.linalg.norm(inward, axis=1, keepdims=True), 1e-9)
        offset0[contour] = inward * (window // 2 + 2)
    # Likewise the inner lips, whose other side is the mouth opening.
    lips = _inner_lip_offsets(P0, window // 2 + 2)
    for i, o in lips.items():
        offset0[i] = o
    # and the outer lips, whose windows may reach across the seam into the other lip
    for i, o in _outer_lip_offsets(P0, window // 2 + 2).items():
        offset0[i] = o
    return offset0, np.concatenate([contour, list(lips)]).astype(int)


def _prepare(frame, s: float) -> np.ndarray:
    """A frame as grayscale at the tracking resolution (scaled by *s*)."""
    g = _gray(frame)
    if s != 1:
        import cv2

        g = cv2.resize(g, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    return g


class _HeadFit:
    """Head similarity on the rigid points (:func:`fit_similarity`), reusing the last fit when the inputs repeat."""

    def __init__(self, rigid: np.ndarray):
        self.rigid = rigid
        self._key: bytes | None = None
        self._M = None

    def __call__(self, src, dst, wts) -> np.ndarray:
        # the head fit of the anchor pass often repeats the previous one
        # exactly (same rigid points and weights): reuse it
        rigid = self.rigid
        args = (src[rigid], dst[rigid], wts[rigid])
        key = b"".join(np.ascontiguousarray(a).tobytes() for a in args)
        if key != self._key:
            self._key, self._M = key, fit_similarity(args[0], args[1][None], args[2][None])[0]
        return self._M.copy()


class _LKTrack:
    """State of :func:`track_lk` between frames, and its per-frame steps.

    Coordinates are at the tracking resolution (frames scaled by *s*) until
    :meth:`finish`. Parameters as in :func:`track_lk`; *first* is the
    prepared first frame, *ann* the scaled annotations, *offset0* and
    *boundary* from :func:`_carrier_offsets`.
    """

    def __init__(self, first, ann, s, rigid, offset0, boundary, *, window, levels, fb_threshold, anchor,
                 shape_prior, contour_refine, rigid_tolerance, lost_frames, roi):
        import cv2

        P0 = ann[0]
        L = len(P0)
        self.s, self.window, self.levels, self.fb_threshold = s, window, levels, fb_threshold
        self.anchor, self.rigid_tolerance, self.lost_frames, self.roi = anchor, rigid_tolerance, lost_frames, roi
        self.size = first.shape[1], first.shape[0]
        self.lk = dict(winSize=(window, window), maxLevel=levels,
                       criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
        self.lk_predicted = dict(self.lk, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        self.lk_back = dict(self.lk_predicted, maxLevel=min(levels, _BACK_LEVELS))
        self.lk_anchor = dict(self.lk, maxLevel=min(levels, _ANCHOR_LEVELS))
        self.lk_anchor_init = dict(self.lk_anchor, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        self.ann, self.P0, self.L = ann, P0, L
        self.rigid, self.is_rigid = rigid, np.isin(np.arange(L), rigid)
        self.offset0, self.boundary, self.is_boundary = offset0, boundary, np.isin(np.arange(L), boundary)
        self.similarity = _HeadFit(rigid)
        self.prior = ShapePrior(np.stack(list(ann.values()))) if shape_prior else ShapePrior(P0[None])
        self.refs = [_Reference(first, P0, offset0, window)]
        # Silhouette and inner-lip points are then refined along their normal by
        # matching the annotated frame's intensity profile across the edge (ASM-style).
        self.profile = _Profiles(first, P0[boundary], offset0[boundary]) if boundary.size and contour_refine else None
        self.pts, self.conf = [self._scale_back(P0)], [np.ones(L)]
        self.Q0 = P0 + offset0
        self.prev, self.c_prev = first, self.Q0.copy()
        self.velocity = np.zeros((L, 2))  # carriers' last displacement, the motion prediction
        self.lost_run = 0
        self.retried = 0

    def _scale_back(self, P):
        return (P + 0.5) / self.s - 0.5

    def annotated(self, t: int, cur) -> None:
        """Frame *t* is annotated: re-anchor the track there and make it a reference."""
        check_inside(self.ann[t], self.size, f"annotations: frame {t}")
        p = self.ann[t]
        off = self.offset0 @ self.similarity(self.P0, p, np.ones(self.L))[:, :2].T
        self.refs.append(_Reference(cur, p, off, self.window))
        self.pts.append(self._scale_back(p))
        self.conf.append(np.ones(self.L))
        self.prev, self.c_prev, self.lost_run = cur, p + off, 0
        self.velocity[:] = 0

    def step(self, t: int, cur) -> None:
        """Track the landmarks into frame *t* (not annotated); raise :class:`FaceLostError` when lost too long."""
        c_est, fwd, err, wts = self._flow(cur)
        off = self.offset0 @ self.similarity(self.Q0, c_est, wts)[:, :2].T
        est = c_est - off
        ref = self._closest_reference(est, wts)
        # 2. drift correction against the reference closest in shape, warped
        # onto the current estimate
        if self.anchor:
            c_est, err = self._anchor(cur, ref, est, c_est, fwd, err)
            est = c_est - off
        if self.profile is not None:
            est[self.boundary] = self.profile.refine(cur, est[self.boundary], off[self.boundary])
        # 3. aperture-aware smoothing of the displacements from the reference
        est = self._smooth(est, ref, err, wts)
        # 4. rigid points that left the head's similarity are unreliable, then
        # unreliable points are recovered from the shape prior
        good, c = self._reliable(est, err)
        est = self._recover(est, good, c)
        c_est = est + off
        self._count_lost(t, good)
        self.pts.append(self._scale_back(est))
        self.conf.append(c)
        self.velocity = c_est - self.c_prev
        self.prev, self.c_prev = cur, c_est

    def _flow(self, cur):
        """Step 1: frame-to-frame flow of the carriers, checked forward-backward.

        Forward on the full pyramid from the constant-velocity prediction,
        backward from the forward result less the prediction on the base
        image only; points that fail the check are tracked again by plain
        forward-backward flow on the full pyramid. Returns the carriers
        ``c_est`` (L, 2), the flow ``fwd`` (L, 1, 2) float32, the errors
        (L,) and the fit weights (L,).
        """
        c_prev, velocity, fb = self.c_prev, self.velocity, self.fb_threshold
        c0 = c_prev.astype(np.float32).reshape(-1, 1, 2)
        v = velocity.astype(np.float32).reshape(-1, 1, 2)
        box = _Box(np.concatenate([c_prev, c_prev + velocity]) if self.roi else [], self.size, self.window, self.levels)
        fwd, err = box.flow(box.crop(self.prev), box.crop(cur), c0, self.lk, guess=c0 + v, lk_init=self.lk_predicted,
                            back_guess=-v, lk_back=self.lk_back)
        retry = ~(err < 3 * fb)
        if _BACK_LEVELS < self.levels and retry.any():
            self._retry(cur, c0, retry, fwd, err)
        c_est = fwd.reshape(-1, 2).astype(np.float64)
        good = err < 3 * fb
        wts = good.astype(float) if good[self.rigid].sum() >= 2 else np.ones(self.L)
        # points whose flow fails the check start from where the motion of
        # the others (a similarity) takes them, not from the failed flow
        jump = err > fb
        if jump.any() and (~jump).sum() >= 3:
            Mf = fit_similarity(c_prev[~jump], c_est[None, ~jump])[0]
            c_est[jump] = c_prev[jump] @ Mf[:, :2].T + Mf[:, 2]
            fwd = c_est.astype(np.float32).reshape(-1, 1, 2)
        return c_est, fwd, err, wts

    def _retry(self, cur, c0, retry, fwd, err) -> None:
        """Track the *retry* points again by plain flow on the full pyramid; keep the better result in *fwd*, *err*."""
        self.retried += int(retry.sum())
        box = _Box(c0[retry] if self.roi else [], self.size, self.window, self.levels)
        fwd2, err2 = box.flow(box.crop(self.prev), box.crop(cur), c0[retry], self.lk)
        better = err2 < err[retry]
        idx = np.flatnonzero(retry)[better]
        fwd[idx], err[idx] = fwd2[better], err2[better]

    def _closest_reference(self, est, wts) -> _Reference:
        refs = self.refs
        return refs[0] if len(refs) == 1 else min(
            refs, key=lambda r: _shape_distance(r.points, est, wts) * (_FIRST_REFERENCE if r is refs[0] else 1.0))

    def _anchor(self, cur, ref, est, c_est, fwd, err):
        """Step 2: match the carriers against *ref* warped onto the estimate; the new carriers and errors."""
        fb = self.fb_threshold
        tmpl, c_tmpl = ref.template(est, c_est, self.window * 2**_ANCHOR_LEVELS // 2 + 8)
        c_t = c_tmpl.astype(np.float32).reshape(-1, 1, 2)
        box = _Box(np.concatenate([c_tmpl, fwd.reshape(-1, 2)]) if self.roi else [], self.size, self.window,
                   _ANCHOR_LEVELS)
        crop = box.crop(cur)
        tmpl = _match_lighting(box.crop(tmpl), crop, est - box.offset)
        afw, aerr = box.flow(tmpl, crop, c_t, self.lk_anchor, guess=fwd, lk_init=self.lk_anchor_init)
        # A match that passes the forward-backward check is drift-free;
        # frame-to-frame flow always has the smaller error, so comparing
        # the two would keep the drift. Proxies next to appearance the
        # reference does not show (background, mouth opening) keep that
        # comparison: their anchor matches are less reliable.
        use = np.where(self.is_boundary, aerr <= np.minimum(err, 3 * fb), aerr <= fb)
        c_est = np.where(use[:, None], c_est + _ANCHOR_GAIN * (afw.reshape(-1, 2) - c_est), c_est)
        return c_est, np.where(use, aerr, err)

    def _smooth(self, est, ref, err, wts):
        """Step 3: aperture-aware smoothing of the displacements from *ref* (:func:`_regularize`)."""
        fb_conf = np.exp(-np.where(np.isfinite(err), err, 1e3) / self.fb_threshold)
        Mh = self.similarity(ref.points, est, fb_conf if fb_conf[self.rigid].sum() > 0.5 else wts)
        return _regularize(est, ref, Mh, fb_conf, self.is_rigid, _SMOOTH_HUBER * self.s)

    def _reliable(self, est, err):
        """Step 4a: which points are reliable (flow check passed, rigid points on the head), and the confidences."""
        rigid, fb = self.rigid, self.fb_threshold
        good = err < 3 * fb
        Mr = self.similarity(self.P0, est, good.astype(float) if good[rigid].sum() >= 2 else np.ones(self.L))
        dev = np.linalg.norm(est[rigid] - (self.P0[rigid] @ Mr[:, :2].T + Mr[:, 2]), axis=1)
        good[rigid[dev > self.rigid_tolerance * self.s]] = False
        return good, np.where(good, np.exp(-np.where(good, err, 0) / fb), 0.0)

    def _recover(self, est, good, c):
        """Step 4b: the unreliable points of *est* recovered from the shape prior (*est* itself when all are good)."""
        if (~good).any():
            fitw = np.where(good, c, 0.0)
            if fitw.sum() > 0:
                prior, is_rigid = self.prior, self.is_rigid
                rec = prior.fit(est, fitw)
                if len(prior.sd) == 0 and fitw[self.rigid].sum() > 0 and (~good & is_rigid).any():
                    # the mean shape cannot follow expressions: place lost rigid
                    # points by the reliable rigid points only
                    rec[is_rigid] = prior.fit(est, np.where(is_rigid, fitw, 0.0))[is_rigid]
                return np.where(good[:, None], est, rec)
        return est

    def _count_lost(self, t: int, good) -> None:
        """Lost-face bookkeeping for frame *t*: raise :class:`FaceLostError` after ``lost_frames`` lost frames in a row."""
        L = self.L
        if good.sum() < max(3, L // 4) or good[self.rigid].sum() < 2:
            self.lost_run += 1
            if self.lost_run >= self.lost_frames:
                f0 = t - self.lost_run + 1
                raise FaceLostError(
                    f"the face was lost from frame {f0}: fewer than {max(3, L // 4)} of {L} landmarks "
                    f"tracked for {self.lost_run} frames", f0, np.stack(self.pts[:f0]), np.stack(self.conf[:f0]))
        else:
            self.lost_run = 0

    def finish(self):
        """The tracked points at full resolution (T, L, 2) and their confidences (T, L)."""
        L = self.L
        log.debug("%d of %d point-frames tracked again on the full pyramid", self.retried,
                  L * max(len(self.pts) - 1, 1))
        if 0 < self.lost_run:
            log.warning("the last %d frames have fewer than %d reliable landmarks", self.lost_run, max(3, L // 4))
        return np.stack(self.pts), np.clip(np.stack(self.conf), 0.0, 1.0)


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
