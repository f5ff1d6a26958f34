"""Synthetic facial performances: the project's deterministic test data.

A take is generated from a small, fully known model, after the setting of
Chuang & Bregler (2002): a source face whose 68 landmarks (Multi-PIE / iBUG
layout) are a linear blend of expression displacements, moved by a 2D head
similarity, rendered to video, plus a 3D target character whose blendshapes
carry the *same* activation curves. Every stage of the pipeline can therefore
be checked against ground truth: tracking against the true landmarks, head
estimation against the true similarity, decomposition and retargeting against
the true target animation.

Model
-----
With activation curves :math:`c_e(t) \\in [0, 1]` (:func:`expression_curves`),
normalized source landmarks :math:`n` (:func:`source_neutral`), expression
displacements :math:`d_e` (:func:`source_deltas`), the fixed placement
:math:`P` (:func:`place_neutral`) and per-frame head similarities :math:`H_t`
(:func:`head_motion`):

.. math::

    s_t = P\\Big(n + \\sum_e c_e(t)\\, d_e\\Big), \\qquad x_t = H_t(s_t)

:math:`s_t` are the stabilized landmarks (frame-0 pixels), :math:`x_t` the
image landmarks. The target character is
:math:`V_t = V_0 + \\sum_e c_e(t)\\, D_e` (:func:`target_rig`,
:func:`target_animation`).

Determinism
-----------
All randomness flows from the integer ``seed`` through
``np.random.default_rng([seed, stream, ...])`` with one fixed stream id per
purpose, so changing, say, the frame size never changes the expression
curves, and the same seed gives byte-identical files.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..config import Command, Flag, Param
from ..errors import ParameterError, ShapeError
from ..io.annotations import write_pts
from ..io.atomic import savez, write_bytes, write_text
from ..io.landmarks import Landmarks, save_landmarks
from ..io.obj import format_obj
from ..io.video import atomic_video_writer
from ..methods.tracking.head import RIGID_68, apply_similarity, fit_similarity

logger = logging.getLogger(__name__)

__all__ = [
    "EXPRESSIONS",
    "expression_curves",
    "source_neutral",
    "source_deltas",
    "head_motion",
    "place_neutral",
    "render_frames",
    "target_rig",
    "target_animation",
    "write_take",
    "overlapping_rig",
    "landmark_rig",
]

#: Expression names, in column order of every curve and delta array.
EXPRESSIONS: tuple[str, ...] = (
    "blink_l", "blink_r", "brow_raise", "brow_l", "smile", "jaw_open", "pucker", "smirk_l",
)

#: Face width in pixels as a fraction of ``min(W, H)`` (see :func:`place_neutral`).
FACE_WIDTH_FRACTION = 0.45

# Random sub-stream ids: np.random.default_rng([seed, stream, ...]).
_STREAM_CURVES = 1
_STREAM_HEAD = 2
_STREAM_TEXTURE = 3
_STREAM_LIGHT = 4
_STREAM_NOISE = 5

#: Seconds at the start of a take with every expression at rest.
_LEAD_S = 0.3
#: Lowest peak of a non-blink expression event.
_PEAK_MIN = 0.62
#: Std of the Gaussian sensor noise, grey levels.
_NOISE_SIGMA = 2.0

_E = {name: i for i, name in enumerate(EXPRESSIONS)}

# Left/right mirror of the 68-point layout (subject's right <-> subject's left).
_MIRROR_68 = np.array(
    list(range(16, -1, -1))  # jaw
    + list(range(26, 16, -1))  # brows
    + [27, 28, 29, 30]  # nose bridge
    + [35, 34, 33, 32, 31]  # nose base
    + [45, 44, 43, 42, 47, 46]  # right eye -> left eye
    + [39, 38, 37, 36, 41, 40]  # left eye -> right eye
    + [54, 53, 52, 51, 50, 49, 48, 59, 58, 57, 56, 55]  # outer lip
    + [64, 63, 62, 61, 60, 67, 66, 65]  # inner lip
)


# --------------------------------------------------------------------------
# argument checks
# --------------------------------------------------------------------------


def _check_int(name: str, value, minimum: int) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ParameterError(f"{name}: expected an int >= {minimum}, got {value!r}")
    if value < minimum:
        raise ParameterError(f"{name}: expected an int >= {minimum}, got {value}")
    return int(value)


def _check_seed(seed) -> int:
    return _check_int("seed", seed, 0)


def _check_fps(fps) -> float:
    try:
        fps = float(fps)
    except (TypeError, ValueError):
        raise ParameterError(f"fps: expected a positive number, got {fps!r}") from None
    if not np.isfinite(fps) or fps <= 0:
        raise ParameterError(f"fps: expected a positive finite number, got {fps}")
    return fps


def _check_size(size) -> tuple[int, int]:
    try:
        w, h = size
    except (TypeError, ValueError):
        raise ParameterError(f"size: expected (width, height), got {size!r}") from None
    w = _check_int("size[0] (width)", w, 64)
    h = _check_int("size[1] (height)", h, 64)
    return w, h


# --------------------------------------------------------------------------
# expression curves
# --------------------------------------------------------------------------


def _envelope(u: np.ndarray, attack: float, hold: float, release: float) -> np.ndarray:
    """Raised-cosine attack, flat hold, raised-cosine release (C1, support [0, a+h+r])."""
    out = np.zeros_like(u)
    up = (u > 0) & (u < attack)
    out[up] = 0.5 * (1 - np.cos(np.pi * u[up] / attack))
    flat = (u >= attack) & (u <= attack + hold)
    out[flat] = 1.0
    v = u - attack - hold
    down = (v > 0) & (v < release)
    out[down] = 0.5 * (1 + np.cos(np.pi * v[down] / release))
    return out


def _draw_event(rng: np.random.Generator, e: int) -> tuple[float, float, float, float, float]:
    """Natural (uncompressed) timing of one event: attack, hold, release, peak, step to next start."""
    if e in (_E["blink_l"], _E["blink_r"]):
        attack = rng.uniform(0.06, 0.09)
        hold = rng.uniform(0.0, 0.04)
        release = rng.uniform(0.08, 0.14)
        peak = 1.0
        step = attack + hold + release + rng.uniform(0.1, 0.5)
    else:
        dur = rng.uniform(0.6, 1.8)
        attack = dur * rng.uniform(0.3, 0.45)
        hold = dur * rng.uniform(0.0, 0.25)
        release = dur - attack - hold
        peak = rng.uniform(_PEAK_MIN, 1.0)
        if rng.random() < 0.45:  # overlap the next expression (combinations)
            step = attack + hold * rng.random() + release * rng.uniform(0.0, 0.6)
        else:  # rest before the next one
            step = dur + rng.uniform(0.1, 0.8)
    return attack, hold, release, peak, step


def _place_cycle(cycle, k: float, t0: float, fps: float):
    """Lay out one cycle of events from *t0* with durations scaled by *k*.

    Returns the events ``(e, start, attack, hold, release, peak)`` and the
    start time of the next cycle. Each peak starts on a frame time.
    """
    evs, t = [], t0
    for e, (a, h, r, peak, step) in cycle:
        a2, r2, h2 = max(a * k, 1.0 / fps), max(r * k, 1.0 / fps), h * k
        t_peak = np.ceil((t + a2) * fps - 1e-9) / fps
        evs.append((e, t_peak - a2, a2, h2, r2, peak))
        t = t_peak - a2 + max(step * k, a2 + 1.0 / fps)
    return evs, t


def _schedule(n_frames: int, fps: float, rng: np.random.Generator) -> list:
    """Events ``(expression, start, attack, hold, release, peak)`` in seconds.

    Expressions are visited in cycles, each a fresh seeded permutation. The
    first cycle is time-compressed if needed so that it fits in the take, so
    every expression peaks at least once when the take is long enough (for
    >= 120 frames always). Peaks are snapped onto frame times, so the sampled
    curve reaches the drawn peak exactly.
    """
    t_last = (n_frames - 1) / fps
    n_expr = len(EXPRESSIONS)

    def fits(cycle, k, t0):
        e, s, a, h, r, _ = _place_cycle(cycle, k, t0, fps)[0][-1]
        return s + a + h + r <= t_last + 1e-9

    events: list = []
    last_end = np.full(n_expr, -np.inf)
    t = _LEAD_S
    first = True
    last_e = -1
    while t < t_last:
        order = [int(e) for e in rng.permutation(n_expr)]
        if order[0] == last_e:  # never the same expression twice in a row
            order[0], order[-1] = order[-1], order[0]
        cycle = [(e, _draw_event(rng, e)) for e in order]
        k = 1.0
        if first and not fits(cycle, 1.0, t):
            # largest time compression k < 1 that fits the whole first cycle
            lo, hi = 0.0, 1.0
            for _ in range(40):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if fits(cycle, mid, t) else (lo, mid)
            k = lo
        first = False
        evs, t_next = _place_cycle(cycle, k, t, fps)
        for e, s, a, h, r, p in evs:
            if s < last_end[e] + 0.05:  # never overlap the same expression; keep the peak on a frame
                s = np.ceil((last_end[e] + 0.05 + a) * fps) / fps - a
            if s >= t_last:
                continue
            events.append((e, s, a, h, r, p))
            last_end[e] = s + a + h + r
        t = t_next
        last_e = order[-1]

    # bilateral blinks every few seconds (winks above give each eye its own events)
    bl, br = _E["blink_l"], _E["blink_r"]
    tb = _LEAD_S + rng.uniform(1.0, 3.0)
    while tb < t_last:
        a, h, r = rng.uniform(0.06, 0.09), rng.uniform(0.0, 0.04), rng.uniform(0.08, 0.14)
        s = np.ceil((tb + a) * fps - 1e-9) / fps - a
        end = s + a + h + r
        clash = any(
            ev[0] in (bl, br) and s < ev[1] + ev[2] + ev[3] + ev[4] + 0.05 and ev[1] < end + 0.05
            for ev in events
        )
        if not clash and s + a <= t_last:
            events.append((bl, s, a, h, r, 1.0))
            events.append((br, s, a, h, r, 1.0))
        tb += rng.uniform(2.0, 4.5)
    return events


def expression_curves(n_frames: int, *, fps: float = 30.0, seed: int = 0) -> np.ndarray:
    """Smooth, seeded expression activation curves.

    Blinks are short events (0.15–0.3 s); the other expressions are smooth
    bumps (raised-cosine attack, hold, raised-cosine release; 0.5–2 s) with
    peaks in [0.62, 1], sometimes overlapping one another, with rests in
    between. Expressions are visited in cycles of seeded random order; the
    first cycle is compressed in time when the take is short, so that for
    ``n_frames >= 120`` every expression reaches at least 0.6.

    Parameters
    ----------
    n_frames : int
        Number of frames T, at least 2.
    fps : float
        Frame rate; durations are in seconds.
    seed : int
        Non-negative random seed.

    Returns
    -------
    ndarray, shape (T, E), float64
        Activations in [0, 1], columns in :data:`EXPRESSIONS` order. Frame 0
        is exactly zero and the first 0.3 s stay at rest. Each curve is C1 in
        time (sampled at the frame times).
    """
    n_frames = _check_int("n_frames", n_frames, 2)
    fps = _check_fps(fps)
    seed = _check_seed(seed)
    rng = np.random.default_rng([seed, _STREAM_CURVES])
    t = np.arange(n_frames) / fps
    curves = np.zeros((n_frames, len(EXPRESSIONS)))
    for e, s, a, h, r, peak in _schedule(n_frames, fps, rng):
        curves[:, e] += peak * _envelope(t - s, a, h, r)
    curves[0] = 0.0
    np.clip(curves, 0.0, 1.0, out=curves)
    return curves


# --------------------------------------------------------------------------
# source face
# --------------------------------------------------------------------------

# Subject's right half (image left, x < 0) and midline of a frontal face, in
# face-width units, y down; the left half is mirrored. Proportions follow the
# mean 68-point iBUG shape, with the lips closed.
_HALF_FACE = {
    0: (-0.500, 0.010), 1: (-0.494, 0.140), 2: (-0.478, 0.275), 3: (-0.450, 0.405),
    4: (-0.400, 0.525), 5: (-0.322, 0.634), 6: (-0.224, 0.728), 7: (-0.116, 0.798), 8: (0.0, 0.820),
    17: (-0.412, -0.092), 18: (-0.350, -0.142), 19: (-0.268, -0.157), 20: (-0.184, -0.145), 21: (-0.102, -0.110),
    27: (0.0, -0.010), 28: (0.0, 0.078), 29: (0.0, 0.166), 30: (0.0, 0.252),
    31: (-0.100, 0.305), 32: (-0.054, 0.325), 33: (0.0, 0.338),
    36: (-0.305, 0.002), 37: (-0.254, -0.030), 38: (-0.190, -0.030),
    39: (-0.137, 0.008), 40: (-0.193, 0.022), 41: (-0.256, 0.023),
    48: (-0.192, 0.468), 49: (-0.124, 0.438), 50: (-0.054, 0.424), 51: (0.0, 0.433),
    59: (-0.126, 0.536), 58: (-0.056, 0.566), 57: (0.0, 0.574),
    60: (-0.160, 0.470), 61: (-0.054, 0.470), 62: (0.0, 0.472),
    67: (-0.054, 0.475), 66: (0.0, 0.477),
}


def _mirror(half: dict) -> np.ndarray:
    """(68, 2) array from a dict of right-half/midline entries; the other half mirrored (x negated)."""
    out = np.zeros((68, 2))
    for i, (x, y) in half.items():
        out[i] = (x, y)
        out[_MIRROR_68[i]] = (-x, y)
    return out


def source_neutral() -> np.ndarray:
    """Neutral frontal face in the 68-point Multi-PIE / iBUG layout.

    Image-style coordinates (x right, y down; the subject's right is image
    left) in normalized units: the jaw from point 0 to point 16 is 1.0 wide
    and the landmarks' bounding box is centred at the origin. The inner lips
    are closed (upper and lower inner lip points 0.005 apart).

    Returns
    -------
    ndarray, shape (68, 2), float64
    """
    pts = _mirror(_HALF_FACE)
    lo, hi = pts.min(0), pts.max(0)
    pts -= (lo + hi) / 2
    return pts


def _blink_delta(pts: np.ndarray) -> np.ndarray:
    """Subject's right eye closing: lids meet 3/4 of the way down, 0.002 apart."""
    d = np.zeros((68, 2))
    for up, low in ((37, 41), (38, 40)):
        gap = pts[low, 1] - pts[up, 1]
        d[up, 1] = 0.75 * gap - 0.001
        d[low, 1] = -(0.25 * gap - 0.001)
    return d


def _field(pts: np.ndarray, centre: int, vec, ids, sigma: float = 0.09) -> np.ndarray:
    """Displacement *vec* at landmark *centre*, spread over landmarks *ids* with a Gaussian falloff.

    A smooth field keeps neighbouring landmarks moving together, so thin
    triangles around the lips do not fold.
    """
    d = np.zeros((68, 2))
    r2 = ((pts[ids] - pts[centre]) ** 2).sum(1)
    d[ids] = np.exp(-0.5 * r2 / sigma**2)[:, None] * np.asarray(vec, float)
    return d


def _mirror_delta(d: np.ndarray) -> np.ndarray:
    """The same displacement on the other side of the face."""
    out = np.zeros_like(d)
    out[_MIRROR_68] = d * (-1.0, 1.0)
    return out


def source_deltas() -> np.ndarray:
    """Landmark displacement of each expression at full activation.

    Same units and axes as :func:`source_neutral`. The rigid points
    :data:`~retarget_cli.methods.tracking.head.RIGID_68` never move. Deformations are
    mild enough that a Delaunay triangulation of the neutral landmarks (plus
    the renderer's extra points) does not fold for any activations in
    [0, 1] (checked in the tests).

    Returns
    -------
    ndarray, shape (E, 68, 2), float64
        Rows in :data:`EXPRESSIONS` order.
    """
    pts = source_neutral()
    D = np.zeros((len(EXPRESSIONS), 68, 2))

    blink_r = _blink_delta(pts)
    D[_E["blink_r"]] = blink_r
    D[_E["blink_l"]] = _mirror_delta(blink_r)

    brows = {17: (0, -0.040), 18: (0, -0.050), 19: (0, -0.055), 20: (0, -0.052), 21: (0.003, -0.045)}
    D[_E["brow_raise"]] = _mirror(brows)

    brow_l = np.zeros((68, 2))
    for i, dy in zip(range(22, 27), (-0.030, -0.042, -0.055, -0.060, -0.050)):
        brow_l[i, 1] = dy
    D[_E["brow_l"]] = brow_l

    mouth = np.arange(48, 68)
    D[_E["smile"]] = _field(pts, 48, (-0.035, -0.040), mouth) + _field(pts, 54, (0.035, -0.040), mouth)

    jaw = {3: (0, 0.020), 4: (0, 0.050), 5: (0.002, 0.090), 6: (0.003, 0.130), 7: (0.002, 0.165),
           8: (0, 0.180),
           48: (0.004, 0.030), 60: (0.004, 0.030),
           59: (0.002, 0.085), 58: (0, 0.115), 57: (0, 0.120),
           67: (0.002, 0.105), 66: (0, 0.110)}
    D[_E["jaw_open"]] = _mirror(jaw)

    pucker = _field(pts, 48, (0.045, 0.0), mouth) + _field(pts, 54, (-0.045, 0.0), mouth)
    pucker += _mirror({51: (0, -0.008), 50: (0, -0.006), 57: (0, 0.008), 58: (0, 0.006),
                       62: (0, -0.004), 61: (0, -0.003), 66: (0, 0.008), 67: (0, 0.006)})
    D[_E["pucker"]] = pucker

    left_mouth = mouth[pts[mouth, 0] >= 0]  # strictly one-sided: the right corner never moves
    D[_E["smirk_l"]] = _field(pts, 54, (0.015, -0.050), left_mouth)

    D[:, list(RIGID_68)] = 0.0
    return D


# --------------------------------------------------------------------------
# placement and head motion
# --------------------------------------------------------------------------


def place_neutral(size) -> np.ndarray:
    """Fixed map from normalized face units to frame-0 pixels.

    The face (jaw width) spans :data:`FACE_WIDTH_FRACTION` of
    ``min(W, H)``, centred horizontally and 4% of the height above centre
    (OpenCV pixel-centre convention).

    Parameters
    ----------
    size : (int, int)
        Frame ``(W, H)`` in pixels, each >= 64.

    Returns
    -------
    ndarray, shape (2, 3), float64
        ``[[k, 0, cx], [0, k, cy]]``.
    """
    w, h = _check_size(size)
    k = FACE_WIDTH_FRACTION * min(w, h)
    return np.array([[k, 0.0, (w - 1) / 2.0], [0.0, k, (h - 1) / 2.0 - 0.04 * h]])


def _smooth_signal(rng: np.random.Generator, t: np.ndarray, fmin: float, fmax: float, n: int = 3) -> np.ndarray:
    """Smooth random signal in [-1, 1], exactly 0 at t = 0."""
    amp = rng.uniform(0.5, 1.0, n)
    amp /= amp.sum()
    freq = rng.uniform(fmin, fmax, n)
    phase = rng.uniform(0, 2 * np.pi, n)
    r = (amp[:, None] * (np.sin(2 * np.pi * freq[:, None] * t + phase[:, None]) - np.sin(phase)[:, None])).sum(0)
    return np.sin(np.pi / 4 * r)  # |r| <= 2 -> [-1, 1], boosts mid-range values


def head_motion(n_frames: int, *, size=(320, 320), seed: int = 0, fps: float = 30.0, speed: float = 1.0) -> np.ndarray:
    """Smooth random head motion as per-frame 2D similarities.

    Roll stays within ±15°, scale within ±10% and translation within ±6% of
    the image size; rotation and scale are about the face centre
    (``place_neutral(size)[:, 2]``), so the face stays in view.

    Parameters
    ----------
    n_frames : int
        Number of frames T, at least 2.
    size : (int, int)
        Frame ``(W, H)`` in pixels.
    seed : int
    fps : float
    speed : float
        Time-scale factor of the motion (> 0); 3 makes the same path three
        times faster (fast head motion). 1 is the default take.

    Returns
    -------
    ndarray, shape (T, 2, 3), float64
        Similarity mapping stabilized coordinates (frame-0 pixels) to image
        pixels; frame 0 is exactly the identity.
    """
    n_frames = _check_int("n_frames", n_frames, 2)
    w, h = _check_size(size)
    seed = _check_seed(seed)
    fps = _check_fps(fps)
    if not (isinstance(speed, (int, float)) and speed > 0):
        raise ParameterError(f"speed: expected a number > 0, got {speed!r}")
    rng = np.random.default_rng([seed, _STREAM_HEAD])
    t = np.arange(n_frames) / fps * speed
    roll = np.deg2rad(15.0) * _smooth_signal(rng, t, 0.05, 0.35)
    scale = 1.0 + 0.10 * _smooth_signal(rng, t, 0.04, 0.25)
    dx = 0.06 * w * _smooth_signal(rng, t, 0.04, 0.30)
    dy = 0.06 * h * _smooth_signal(rng, t, 0.04, 0.30)
    c = place_neutral((w, h))[:, 2]
    a, b = scale * np.cos(roll), scale * np.sin(roll)
    head = np.empty((n_frames, 2, 3))
    head[:, 0, 0], head[:, 0, 1] = a, -b
    head[:, 1, 0], head[:, 1, 1] = b, a
    head[:, 0, 2] = c[0] + dx - (a * c[0] - b * c[1])
    head[:, 1, 2] = c[1] + dy - (b * c[0] + a * c[1])
    head[0] = np.eye(2, 3)
    return head


def _truth_landmarks(n_frames: int, size, seed: int, fps: float, speed: float = 1.0):
    """curves (T, E), stabilized (T, 68, 2), head (T, 2, 3), image points (T, 68, 2)."""
    curves = expression_curves(n_frames, fps=fps, seed=seed)
    norm = source_neutral()[None] + np.einsum("te,eld->tld", curves, source_deltas())
    P = place_neutral(size)
    stab = norm @ P[:, :2].T + P[:, 2]
    head = head_motion(n_frames, size=size, seed=seed, fps=fps, speed=speed)
    return curves, stab, head, apply_similarity(head, stab)


# --------------------------------------------------------------------------
# renderer
# --------------------------------------------------------------------------

def _extra_points() -> np.ndarray:
    """Extra warp-mesh points (X, 2), normalized units: rigid skin anchors and a ring.

    Anchors on the hairline and cheekbones keep brow and mouth deformations
    local; the ring lies outside the head (and outside the open jaw). All
    follow the head similarity only.
    """
    anchors = np.array([[0.0, -0.70], [-0.30, -0.62], [0.30, -0.62], [-0.30, -0.12], [0.30, -0.12]])
    phi = np.linspace(0, 2 * np.pi, 24, endpoint=False) + np.pi / 24
    ring = np.stack([0.72 * np.cos(phi), -0.12 + 1.02 * np.sin(phi)], 1)
    return np.concatenate([anchors, ring])


def _warp_mesh():
    """Canonical (normalized) points of the warp mesh and their Delaunay triangles.

    Returns
    -------
    points : ndarray, shape (68 + X, 2)
        Neutral landmarks, then :func:`_extra_points`.
    triangles : ndarray, shape (K, 3), int
        Counter-clockwise in image axes (positive signed area with y down).
    """
    from scipy.spatial import Delaunay

    pts = np.concatenate([source_neutral(), _extra_points()])
    tri = Delaunay(pts).simplices.astype(np.int64)
    a, b, c = pts[tri[:, 0]], pts[tri[:, 1]], pts[tri[:, 2]]
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    flip = area < 0
    tri[flip] = tri[flip][:, [0, 2, 1]]
    return pts, tri


def _band_noise(rng: np.random.Generator, shape, sigma: float) -> np.ndarray:
    """Gaussian-filtered white noise with unit std, float32."""
    import cv2

    n = rng.standard_normal(shape).astype(np.float32)
    n = cv2.GaussianBlur(n, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    return n / max(float(n.std()), 1e-6)


def _spots(rng: np.random.Generator, shape, density: float, sigma: float, weight=None) -> np.ndarray:
    """Soft random spots (peak ~1) as blurred sparse impulses, float32; *weight* modulates density."""
    import cv2

    h, w = shape
    n = int(density * h * w)
    ys, xs = rng.integers(0, h, n), rng.integers(0, w, n)
    amp = rng.uniform(0.5, 1.0, n).astype(np.float32)
    if weight is not None:
        amp *= weight[ys, xs] > rng.random(n)
    imp = np.zeros(shape, np.float32)
    np.add.at(imp, (ys, xs), amp)
    imp = cv2.GaussianBlur(imp, (0, 0), sigma)
    return imp * (2 * np.pi * sigma**2)


def _fill(shape, polys, *, closed=True, thickness=-1) -> np.ndarray:
    """Anti-aliased coverage in [0, 1] (float32) of polygons (filled) or polylines."""
    import cv2

    m = np.zeros(shape, np.uint8)
    ip = [np.round(np.asarray(p) * 16).astype(np.int32) for p in polys]
    if thickness < 0:
        cv2.fillPoly(m, ip, 255, lineType=cv2.LINE_AA, shift=4)
    else:
        cv2.polylines(m, ip, closed, 255, thickness=thickness, lineType=cv2.LINE_AA, shift=4)
    return m.astype(np.float32) / 255.0


def _blend(img: np.ndarray, alpha: np.ndarray, color) -> None:
    """In place: img = img (1 - alpha) + color alpha; alpha (H, W), color (3,) or (H, W, 3)."""
    a = alpha[..., None]
    img *= 1 - a
    img += a * np.asarray(color, np.float32)


def _gauss(x, y, cx, cy, sx, sy):
    return np.exp(-0.5 * (((x - cx) / sx) ** 2 + ((y - cy) / sy) ** 2)).astype(np.float32)


class _Renderer:
    """Canonical face image, static background and the per-frame warp."""

    def __init__(self, size, seed: int, fps: float, noise: float = _NOISE_SIGMA, blur: float = 0.0,
                 jpeg: int | None = None, light: float = 1.0, dots: float = 0.0):
        import cv2

        self.noise, self.blur, self.jpeg, self.light, self.dots = noise, blur, jpeg, light, dots
        self.w, self.h = size
        self.fps = fps
        self.seed = seed
        w, h = size
        P = place_neutral(size)
        self.k = P[0, 0]
        mesh, self.tri = _warp_mesh()
        self.canon = mesh @ P[:, :2].T + P[:, 2]  # (M, 2) frame-0 pixels
        self.canon_rigid = self.canon[list(RIGID_68)]
        s = self.canon[self.tri]
        e1, e2 = s[:, 1] - s[:, 0], s[:, 2] - s[:, 0]
        self.canon_area = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
        rng = np.random.default_rng([seed, _STREAM_TEXTURE])
        self.background = self._paint_background(rng)
        face, alpha = self._paint_face(rng, P)
        self.face = np.dstack([np.clip(face + 0.5, 0, 255), alpha * 255 + 0.5]).astype(np.uint8)
        iris_hue = rng.uniform(0, 1)
        self.iris = np.array([40 + 60 * iris_hue, 70 + 30 * (1 - iris_hue), 95 - 45 * iris_hue], np.float32)
        light = np.random.default_rng([seed, _STREAM_LIGHT])
        self.light_params = [(light.uniform(0.5, 1.0, 3), light.uniform(0.03, 0.15, 3), light.uniform(0, 2 * np.pi, 3))
                             for _ in range(3)]
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        self.xx, self.yy = xx, yy
        self.xn = (xx - (w - 1) / 2) / (w / 2)
        self.yn = (yy - (h - 1) / 2) / (h / 2)
        self.idmap = np.zeros((h, w), np.uint16)
        self.cv2 = cv2

    # ---- painting (once) -------------------------------------------------

    def _paint_background(self, rng) -> np.ndarray:
        import cv2

        h, w = self.h, self.w
        base = np.array([rng.uniform(90, 140), rng.uniform(100, 150), rng.uniform(110, 160)], np.float32)
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        bg = np.empty((h, w, 3), np.float32)
        bg[:] = base
        bg *= (0.85 + 0.3 * xx / w)[..., None]
        # soft panels and stripes (a room), then texture at two scales
        for _ in range(10):
            x0, y0 = rng.uniform(-0.2, 1.0) * w, rng.uniform(-0.2, 1.0) * h
            pw, ph = rng.uniform(0.1, 0.5) * w, rng.uniform(0.1, 0.5) * h
            m = np.zeros((h, w), np.float32)
            cv2.rectangle(m, (int(x0), int(y0)), (int(x0 + pw), int(y0 + ph)), 1.0, -1)
            m = cv2.GaussianBlur(m, (0, 0), 1.5)
            _blend(bg, 0.6 * m, base * rng.uniform(0.6, 1.3, 3))
        bg += 14 * _band_noise(rng, (h, w), 0.02 * min(w, h))[..., None]
        bg += 6 * _band_noise(rng, (h, w), 1.0)[..., None] * np.float32([1.0, 0.95, 0.9])
        return np.clip(bg, 0, 255)

    def _paint_face(self, rng, P):
        """Colour (H, W, 3) float32 and soft alpha (H, W) of the neutral head at frame 0."""
        import cv2

        h, w, k = self.h, self.w, self.k
        L = self.canon[:68]
        to_px = lambda q: np.asarray(q) @ P[:, :2].T + P[:, 2]  # noqa: E731
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        x = (xx - P[0, 2]) / k  # normalized coordinates
        y = (yy - P[1, 2]) / k
        n = source_neutral()

        tone = rng.uniform(0, 1)
        skin = np.array([95 + 60 * tone, 125 + 50 * tone, 175 + 45 * tone], np.float32)  # BGR
        img = np.empty((h, w, 3), np.float32)
        img[:] = skin
        # shading: darker towards the outline, eye sockets, nose sides, under nose and lip
        r2 = (x / 0.56) ** 2 + ((y + 0.05) / 0.72) ** 2
        shade = 1.0 - 0.28 * np.clip(r2, 0, 1.4) ** 2
        for sx in (-1, 1):
            shade -= 0.10 * _gauss(x, y, sx * 0.22, -0.36, 0.10, 0.05)  # eye socket, above the eye
            shade -= 0.08 * _gauss(x, y, sx * 0.075, -0.18, 0.025, 0.12)  # nose side
            shade += 0.05 * _gauss(x, y, sx * 0.26, -0.10, 0.08, 0.06)  # cheekbone highlight
        shade += 0.06 * _gauss(x, y, 0.0, -0.15, 0.02, 0.12)  # nose bridge highlight
        shade -= 0.10 * _gauss(x, y, 0.0, 0.035, 0.07, 0.018)  # under the nose
        shade -= 0.10 * _gauss(x, y, 0.0, 0.30, 0.10, 0.03)  # under the lower lip
        img *= shade[..., None]
        blush = sum(_gauss(x, y, sx * 0.27, 0.02, 0.09, 0.07) for sx in (-1, 1))
        img += (blush * 18)[..., None] * np.float32([-0.6, -0.4, 1.0])
        # texture: band-limited noise at three scales, pores, freckles
        img += (9 * _band_noise(rng, (h, w), 0.04 * k) + 6 * _band_noise(rng, (h, w), 1.6)
                + 5 * _band_noise(rng, (h, w), 0.7))[..., None] * np.float32([0.9, 0.95, 1.0])
        pores = _spots(rng, (h, w), 0.015, 0.6)
        img -= (28 * pores)[..., None] * np.float32([1.0, 1.0, 0.8])
        freckle_w = sum(_gauss(x, y, sx * 0.2, -0.05, 0.14, 0.1) for sx in (-1, 1)) + _gauss(x, y, 0, -0.12, 0.06, 0.1)
        freckles = _spots(rng, (h, w), 0.004, max(0.9, 0.006 * k), weight=np.clip(freckle_w, 0, 1))
        img -= (45 * np.clip(freckles, 0, 1.5))[..., None] * np.float32([0.9, 0.8, 0.55])

        # head silhouette: jaw line + skull; hair above a hairline
        phi = np.linspace(0, np.pi, 40)
        skull = np.stack([0.505 * np.cos(phi), n[0, 1] - 0.56 * np.sin(phi)], 1)
        head_poly = np.concatenate([n[0:17], skull[1:-1]])
        hair_top = np.stack([0.56 * np.cos(phi), -0.34 - 0.60 * np.sin(phi)], 1)
        hx = np.linspace(-0.56, 0.56, 30)
        hairline = np.stack([hx, -0.72 + 0.30 * (hx / 0.5) ** 2 + 0.05 * np.sin(9 * hx)], 1)
        hair_poly = np.concatenate([hair_top, hairline])
        head_m = _fill((h, w), [to_px(head_poly)])
        # hair may stick out of the skull outline above the temples, never below them
        hair_m = _fill((h, w), [to_px(hair_poly)]) * np.clip(head_m + (y < n[0, 1]), 0, 1)
        palette = np.array([[25, 35, 55], [18, 20, 26], [30, 50, 110], [70, 120, 165]], np.float32)  # BGR
        hair_col = palette[rng.integers(len(palette))] * rng.uniform(0.85, 1.15)
        strands = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), 0.6, sigmaY=3.0)
        strands /= max(float(strands.std()), 1e-6)
        hair_tex = hair_col * (1 + 0.25 * strands[..., None]) + 10 * _band_noise(rng, (h, w), 3.0)[..., None]
        _blend(img, hair_m, hair_tex)

        # eyebrows: tapered strokes with hair texture
        brow_col = np.minimum(hair_col * 0.8, [40, 50, 70])
        for ids in (range(17, 22), range(22, 27)):
            c = L[list(ids)]
            thick = np.linspace(0.010, 0.020, 5) * k
            if ids[0] == 22:
                thick = thick[::-1]
            top, bot = c - [0, 1] * thick[:, None], c + [0, 0.6] * thick[:, None]
            m = _fill((h, w), [np.concatenate([top, bot[::-1]])])
            m = cv2.GaussianBlur(m, (0, 0), 0.5)
            _blend(img, 0.9 * m * np.clip(0.75 + 0.35 * strands, 0, 1), brow_col)

        # eyes: sclera, lid lines, crease (the iris is drawn per frame)
        for ids in (range(36, 42), range(42, 48)):
            c = L[list(ids)]
            # sclera 1 px inside the lid polygon, so that its anti-aliased edge
            # never spills into the skin triangles (white specks on closed lids)
            out = c - c.mean(0)
            m = _fill((h, w), [c - out / np.linalg.norm(out, axis=1, keepdims=True)])
            cx = c[[0, 3]].mean(0)
            ey = np.exp(-(((xx - cx[0]) / (0.09 * k)) ** 2)).astype(np.float32)
            _blend(img, m, np.float32([205, 210, 220]) * (0.8 + 0.2 * ey)[..., None])
            up = c[[0, 1, 2, 3]]
            _blend(img, _fill((h, w), [up], closed=False, thickness=max(1, int(round(0.012 * k)))), [25, 25, 35])
            _blend(img, 0.6 * _fill((h, w), [c[[3, 4, 5, 0]]], closed=False, thickness=1), [60, 70, 100])
            crease = up - [0, 0.035 * k] + np.array([[0.0, 0], [0, -0.005 * k], [0, -0.005 * k], [0, 0]])
            _blend(img, 0.35 * _fill((h, w), [crease], closed=False, thickness=1), skin * 0.55)

        # nose: nostrils and tip highlight
        for a, b in ((31, 32), (35, 34)):
            cx = (L[a] + L[b]) / 2 - [0, 0.012 * k]
            m = np.zeros((h, w), np.uint8)
            ax = (int(round(0.026 * k * 16)), int(round(0.011 * k * 16)))
            ang = 15 if a == 31 else -15
            cv2.ellipse(m, tuple(int(round(v * 16)) for v in cx), ax, ang, 0, 360, 255, -1, cv2.LINE_AA, 4)
            _blend(img, 0.85 * m.astype(np.float32) / 255, [35, 40, 70])
        img += (25 * _gauss(x, y, 0.0, n[30, 1] + 0.01, 0.03, 0.02))[..., None]  # tip highlight
        for sx in (-1, 1):  # alar creases
            img *= (1 - 0.12 * _gauss(x, y, sx * 0.095, n[31, 1] - 0.03, 0.018, 0.03))[..., None]

        # lips: colour, vertical lip lines, dark seam between the inner contours
        lip_m = _fill((h, w), [L[48:60]])
        lip_col = np.array([skin[0] * 0.55, skin[1] * 0.5, skin[2] * 0.85], np.float32)
        lines = cv2.GaussianBlur(
            rng.standard_normal((h, w)).astype(np.float32), (0, 0), 0.5, sigmaY=2.0)
        lip_tex = lip_col * (1 + 0.15 * lines[..., None]) * (1 - 0.12 * (y < n[62, 1]))[..., None]
        _blend(img, lip_m, lip_tex)
        seam = np.clip(_fill((h, w), [L[60:68]]) + _fill((h, w), [L[60:68]], thickness=1), 0, 1)
        _blend(img, 0.8 * seam, [40, 35, 80])

        alpha = np.clip(head_m + hair_m, 0, 1)
        alpha = cv2.GaussianBlur(alpha, (0, 0), 0.7)
        return img, alpha

    # ---- per frame ---------------------------------------------------------

    def _warp(self, dst: np.ndarray) -> np.ndarray:
        """Piecewise-affine warp of the canonical BGRA image onto mesh points *dst* (M, 2)."""
        cv2 = self.cv2
        src = self.canon
        tri = self.tri
        d = dst[tri]  # (K, 3, 2)
        s = src[tri]
        e1, e2 = d[:, 1] - d[:, 0], d[:, 2] - d[:, 0]
        det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
        ok = np.abs(det) > 1e-9
        # affine dst -> src per triangle: [x y 1] @ A = src
        Dm = np.concatenate([d, np.ones((len(tri), 3, 1))], axis=2)
        Dm[~ok] = np.eye(3)
        A = np.linalg.solve(Dm, s)  # (K, 3, 2)
        coef = np.zeros((len(tri) + 1, 6), np.float32)
        coef[0] = (0, 0, -1e4, 0, 0, -1e4)  # outside the mesh -> transparent
        coef[1:, 0], coef[1:, 1], coef[1:, 2] = A[:, 0, 0], A[:, 1, 0], A[:, 2, 0]
        coef[1:, 3], coef[1:, 4], coef[1:, 5] = A[:, 0, 1], A[:, 1, 1], A[:, 2, 1]
        idmap = self.idmap
        idmap[:] = 0
        ip = np.round(d * 16).astype(np.int32)
        # Squashed triangles (closed eyelids) first: their edge pixels would
        # sample stretched content, so their neighbours overwrite them.
        order = np.argsort(np.abs(det) / self.canon_area, kind="stable")
        for i in order[ok[order]]:
            cv2.fillConvexPoly(idmap, ip[i], int(i + 1), cv2.LINE_8, 4)
        c = coef[idmap]  # (H, W, 6)
        mapx = c[..., 0] * self.xx + c[..., 1] * self.yy + c[..., 2]
        mapy = c[..., 3] * self.xx + c[..., 4] * self.yy + c[..., 5]
        return cv2.remap(self.face, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def _draw_eye(self, img: np.ndarray, eye: np.ndarray, scale: float) -> None:
        """Iris and pupil, clipped by the lid polygon *eye* (6, 2)."""
        cv2 = self.cv2
        c = (eye[0] + eye[3]) / 2 + [0, 0.004 * self.k * scale]
        r = 0.26 * np.linalg.norm(eye[3] - eye[0])
        x0, y0 = np.floor(c - r - 2).astype(int)
        x1, y1 = np.ceil(c + r + 3).astype(int)
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, self.w), min(y1, self.h)
        if x1 <= x0 or y1 <= y0:
            return
        shp = (y1 - y0, x1 - x0)
        off = np.array([x0, y0], float)
        # lid aperture in pixels: fades the iris out as the lids meet
        aperture = float(np.mean(eye[[5, 4], 1] - eye[[1, 2], 1]))
        lid = _fill(shp, [eye - off]) * np.float32(np.clip((aperture - 0.5) / 2.0, 0.0, 1.0))
        if lid.max() == 0:
            return
        cc = tuple(int(round(v * 16)) for v in c - off)
        iris = np.zeros(shp, np.uint8)
        cv2.circle(iris, cc, int(round(r * 16)), 255, -1, cv2.LINE_AA, 4)
        pupil = np.zeros(shp, np.uint8)
        cv2.circle(pupil, cc, int(round(0.42 * r * 16)), 255, -1, cv2.LINE_AA, 4)
        yy, xx = np.mgrid[0:shp[0], 0:shp[1]].astype(np.float32)
        rr = np.hypot(xx - (c[0] - x0), yy - (c[1] - y0)) / max(r, 1e-3)
        ang = np.arctan2(yy - (c[1] - y0), xx - (c[0] - x0))
        iris_col = self.iris * (1.15 - 0.45 * rr ** 3 + 0.12 * np.sin(11 * ang))[..., None]
        roi = img[y0:y1, x0:x1]
        _blend(roi, lid * iris.astype(np.float32) / 255, iris_col)
        _blend(roi, lid * pupil.astype(np.float32) / 255, [12, 10, 10])
        hl = np.zeros(shp, np.uint8)
        hc = tuple(int(round(v * 16)) for v in c - off + [0.3 * r, -0.3 * r])
        cv2.circle(hl, hc, int(round(max(0.7, 0.18 * r) * 16)), 255, -1, cv2.LINE_AA, 4)
        _blend(roi, 0.8 * lid * hl.astype(np.float32) / 255, [235, 240, 245])

    def _draw_mouth(self, img: np.ndarray, inner: np.ndarray, scale: float) -> None:
        """Dark mouth interior and upper teeth inside the inner lip contour *inner* (8, 2)."""
        x0, y0 = np.floor(inner.min(0) - 2).astype(int)
        x1, y1 = np.ceil(inner.max(0) + 3).astype(int)
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, self.w), min(y1, self.h)
        if x1 <= x0 or y1 <= y0:
            return
        shp = (y1 - y0, x1 - x0)
        off = np.array([x0, y0], float)
        m = _fill(shp, [inner - off])
        if m.max() == 0:
            return
        roi = img[y0:y1, x0:x1]
        yy = np.arange(shp[0], dtype=np.float32)[:, None] + y0
        depth = np.clip((yy - inner[:, 1].min()) / max(float(np.ptp(inner[:, 1])), 1.0), 0, 1)
        _blend(roi, m, np.float32([25, 20, 55]) * (1.2 - 0.6 * depth)[..., None] * np.ones(3, np.float32))
        # teeth show once the lips part by a couple of pixels
        opening = float(np.mean(inner[[7, 6, 5], 1] - inner[[1, 2, 3], 1]))
        show = np.clip((opening - 2.0) / 4.0, 0.0, 1.0)
        if show > 0:
            upper = inner[[0, 1, 2, 3, 4]]
            teeth = np.concatenate([upper, (upper + [0, 0.032 * self.k * scale])[::-1]])
            _blend(roi, show * m * _fill(shp, [teeth - off]), [200, 215, 222])

    def _draw_dots(self, img: np.ndarray, pts: np.ndarray, scale: float) -> None:
        """Painted make-up dots (dark blue, anti-aliased discs) centred on the landmarks."""
        m = np.zeros((self.h, self.w), np.uint8)
        r = int(round(self.dots * scale * 16))
        for x, y in pts:
            self.cv2.circle(m, (int(round(x * 16)), int(round(y * 16))), r, 255, -1, self.cv2.LINE_AA, 4)
        _blend(img, m.astype(np.float32) / 255, [90, 40, 30])

    def _lighting(self, t: int) -> np.ndarray:
        """Multiplicative light field (H, W) for frame *t*: gain ±10% and a drifting linear gradient."""
        ts = t / self.fps
        vals = []
        for amp, freq, phase in self.light_params:
            amp = amp / amp.sum()
            r = (amp * (np.sin(2 * np.pi * freq * ts + phase) - np.sin(phase))).sum()
            vals.append(np.sin(np.pi / 4 * r))
        gain = 1.0 + 0.10 * vals[0] * self.light
        theta = np.pi * vals[1] + 0.3
        slope = (0.05 + 0.03 * vals[2]) * self.light
        return (gain * (1 + slope * (np.cos(theta) * self.xn + np.sin(theta) * self.yn))).astype(np.float32)

    def frame(self, pts: np.ndarray, head: np.ndarray, t: int) -> np.ndarray:
        """Render one frame from image landmarks (68, 2) and the head similarity (2, 3)."""
        extra = self.canon[68:] @ head[:, :2].T + head[:, 2]
        warped = self._warp(np.concatenate([pts, extra]))
        alpha = warped[..., 3:4].astype(np.float32) * np.float32(1 / 255)
        img = self.background + (warped[..., :3].astype(np.float32) - self.background) * alpha
        scale = float(np.hypot(head[0, 0], head[1, 0]))
        self._draw_eye(img, pts[36:42], scale)
        self._draw_eye(img, pts[42:48], scale)
        self._draw_mouth(img, pts[60:68], scale)
        if self.dots > 0:
            self._draw_dots(img, pts, scale)
        img *= self._lighting(t)[..., None]
        if self.blur > 0:
            img = self.cv2.GaussianBlur(img, (0, 0), self.blur)
        noise = np.random.default_rng([self.seed, _STREAM_NOISE, t]).standard_normal(img.shape, dtype=np.float32)
        img += noise * np.float32(self.noise) + np.float32(0.5)
        np.clip(img, 0, 255, out=img)
        out = img.astype(np.uint8)
        if self.jpeg is not None:
            ok, buf = self.cv2.imencode(".jpg", out, [self.cv2.IMWRITE_JPEG_QUALITY, int(self.jpeg)])
            out = self.cv2.imdecode(buf, self.cv2.IMREAD_COLOR)
        return out


def render_frames(points, *, size, seed: int = 0, fps: float = 30.0, noise: float = _NOISE_SIGMA,
                  blur: float = 0.0, jpeg: int | None = None, light: float = 1.0,
                  dots: float = 0.0) -> Iterator[np.ndarray]:
    """Render a textured synthetic face following the given landmarks.

    One canonical head (textured skin with band-limited noise, pores and
    freckles; hair, eyebrows, eye whites and lids, nostrils, lips) is
    painted at the neutral frame-0 landmarks (:func:`place_neutral` of
    :func:`source_neutral`) and warped to each frame with a piecewise-affine
    warp over a Delaunay triangulation of the landmarks plus rigid anchor
    points and a ring around the head, which follow the head similarity
    fitted on :data:`~retarget_cli.methods.tracking.head.RIGID_68`. (No image-border
    points: only the head is warped, so large head motion cannot fold
    triangles between the ring and the frame edge.) The warped head is
    composited over a static textured background with its soft mask; iris,
    pupils (clipped by the lids) and the mouth interior (dark, with upper
    teeth) are drawn after the warp. Finally a slow lighting drift (gain
    ±10%, moving linear gradient) and Gaussian sensor noise (sigma 2 grey
    levels, seeded per frame) are applied.

    Parameters
    ----------
    points : ndarray, shape (T, 68, 2)
        Image landmarks in pixels, e.g. from the model in the module
        docstring. Rigid points should move rigidly.
    size : (int, int)
        Frame ``(W, H)``, each >= 64.
    seed : int
        Texture, lighting and noise seed.
    fps : float
        Only sets the speed of the lighting drift.
    noise : float
        Std of the Gaussian sensor noise in grey levels (default 2).
    blur : float
        Gaussian blur sigma in pixels applied before the noise (0: none).
    jpeg : int, optional
        JPEG quality (1-100): each frame is JPEG-compressed and decoded.
    light : float
        Multiplier of the lighting drift's gain and gradient amplitudes.
    dots : float
        Radius in pixels (at the frame-0 scale) of painted dots centred on
        every landmark, for marker tracking (0: none).

    The defaults give the committed sample's exact bytes; the other values are
    the perturbations ``bench/track.py`` turns up.

    Yields
    ------
    ndarray, shape (H, W, 3), uint8
        BGR frames, one per row of *points*.
    """
    w, h = _check_size(size)
    seed = _check_seed(seed)
    fps = _check_fps(fps)
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 3 or points.shape[1:] != (68, 2) or len(points) == 0:
        raise ShapeError(f"points: expected shape (T, 68, 2) with T >= 1, got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise ShapeError("points: every coordinate must be finite")
    if not noise >= 0 or not blur >= 0 or not light >= 0:
        raise ParameterError(f"noise, blur and light must be >= 0, got {noise}, {blur}, {light}")
    if jpeg is not None and not 1 <= int(jpeg) <= 100:
        raise ParameterError(f"jpeg: expected a quality in [1, 100], got {jpeg}")
    if not dots >= 0:
        raise ParameterError(f"dots: expected a radius >= 0, got {dots}")
    return _render_iter(points, (w, h), seed, fps, dict(noise=noise, blur=blur, jpeg=jpeg, light=light, dots=dots))


def _render_iter(points, size, seed, fps, opts):
    r = _Renderer(size, seed, fps, **opts)
    heads = fit_similarity(r.canon_rigid, points[:, list(RIGID_68)], iterations=0)
    for t in range(len(points)):
        yield r.frame(points[t], heads[t], t)


# --------------------------------------------------------------------------
# target character
# --------------------------------------------------------------------------


def _bump(x, y, cx, cy, rx, ry):
    """Compactly supported smooth bump (1 - d^2)^3, d the elliptical distance."""
    d2 = ((x - cx) / rx) ** 2 + ((y - cy) / ry) ** 2
    return np.where(d2 < 1, (1 - np.minimum(d2, 1)) ** 3, 0.0)


def _g(x, y, cx, cy, sx, sy):
    return np.exp(-0.5 * (((x - cx) / sx) ** 2 + ((y - cy) / sy) ** 2))


def target_rig(*, seed: int = 0) -> dict:
    """A synthetic 3D blendshape character, shaped unlike the source face.

    A 48 x 56 grid mask is mapped onto an oval (cartoonish: round cheeks,
    big nose bulb, long chin), in centimetres (about 10.4 wide, 13.6 tall; x
    to the subject's left, y up, z toward the viewer), with a relief for
    forehead, brow ridge, eye sockets, nose, cheeks, lips and chin. Each
    expression is a smooth, compactly supported displacement of its region
    (peak 0.5–1.5 cm, i.e. 5–15% of the face width).

    Parameters
    ----------
    seed : int
        Varies the relief and expression shapes by a few percent.

    Returns
    -------
    dict
        ``vertices`` (N, 3) float64 neutral; ``faces`` (F, 4) int64 quads,
        counter-clockwise seen from +z; ``uvs`` (N, 2) float64 in [0, 1], one
        per vertex; ``deltas`` (E, N, 3) float64 in :data:`EXPRESSIONS`
        order; ``names`` tuple of E str.
    """
    seed = _check_seed(seed)
    rng = np.random.default_rng([seed, 6])
    jit = lambda: 1.0 + 0.05 * rng.uniform(-1, 1)  # noqa: E731
    nx, ny = 48, 56
    u, v = np.meshgrid(np.linspace(0, 1, nx), np.linspace(0, 1, ny))
    s, r = 2 * u - 1, 2 * v - 1
    # square -> disc (elliptical grid mapping), then an oval face
    x = 5.2 * s * np.sqrt(1 - r**2 / 2)
    y = 6.8 * r * np.sqrt(1 - s**2 / 2) - 0.4 * (r < 0) * r**2  # longer chin
    z = 3.4 * np.sqrt(np.clip(1 - (x / 6.2) ** 2 - (y / 7.8) ** 2, 0, 1))
    z += 1.5 * jit() * _g(x, y, 0, -0.5, 0.5, 1.2) + 0.8 * jit() * _g(x, y, 0, -1.6, 0.55, 0.45)  # nose + bulb
    z += 0.5 * _g(x, y, 0, 2.5, 2.8, 0.5)  # brow ridge
    z += 0.5 * _g(x, y, 0, 4.5, 3.5, 1.5)  # forehead
    for sx in (-1, 1):
        z += -0.6 * _g(x, y, sx * 2.0, 1.3, 0.8, 0.7) + 0.35 * _g(x, y, sx * 2.0, 1.3, 0.5, 0.4)  # socket, eyeball
        z += 0.7 * jit() * _g(x, y, sx * 2.6, -1.4, 1.2, 1.1)  # round cheeks
    z += 0.35 * _g(x, y, 0, -3.2, 1.6, 0.5) - 0.15 * _g(x, y, 0, -3.2, 1.4, 0.12)  # lips, mouth line
    z += 0.5 * _g(x, y, 0, -5.6, 1.2, 0.8)  # chin
    vertices = np.stack([x, y, z], -1).reshape(-1, 3)
    idx = np.arange(nx * ny).reshape(ny, nx)
    faces = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], -1).reshape(-1, 4)
    uvs = np.stack([u.ravel(), v.ravel()], 1)

    X, Y = vertices[:, 0], vertices[:, 1]
    D = np.zeros((len(EXPRESSIONS), len(vertices), 3))

    def vec(w, dx, dy, dz):
        return np.stack([w * dx, w * dy, w * dz], -1)

    for name, sx in (("blink_l", 1), ("blink_r", -1)):
        lid = _bump(X, Y, sx * 2.0, 1.6, 1.1, 0.55)
        low = _bump(X, Y, sx * 2.0, 0.95, 0.9, 0.3)
        D[_E[name]] = vec(lid, 0, -0.75 * jit(), 0.12) + vec(low, 0, 0.15, 0)
    brow = lambda sx: _bump(X, Y, sx * 2.0, 2.6, 1.7, 1.1)  # noqa: E731
    D[_E["brow_raise"]] = vec(brow(1) + brow(-1), 0, 0.9 * jit(), 0.05) + vec(_bump(X, Y, 0, 3.6, 3.5, 1.2), 0, 0.3, 0)
    outer = np.clip(0.6 + 0.4 * (X - 0.3) / 3.4, 0.3, 1.2)
    D[_E["brow_l"]] = vec(brow(1) * outer, 0.05, 0.85 * jit(), 0.05)
    for sx in (-1, 1):
        D[_E["smile"]] += vec(_bump(X, Y, sx * 1.9, -3.0, 1.5, 1.2), sx * 0.55, 0.6 * jit(), -0.35)
        D[_E["smile"]] += vec(_bump(X, Y, sx * 2.4, -1.6, 1.3, 1.0), 0, 0.25, 0.2)
    t = np.clip((-2.9 - Y) / 1.4, 0, 1)
    jaw_w = t**3 * (10 - 15 * t + 6 * t**2) * np.clip(1 - (X / 5.5) ** 2, 0, 1)
    D[_E["jaw_open"]] = vec(jaw_w, 0, -1.4 * jit(), -0.35)
    lips = _bump(X, Y, 0, -3.2, 2.3, 1.1)
    D[_E["pucker"]] = vec(lips, -0.45 * np.tanh(X / 1.2), 0, 0) + vec(_bump(X, Y, 0, -3.2, 1.6, 0.8), 0, 0, 0.8 * jit())
    D[_E["smirk_l"]] = vec(_bump(X, Y, 1.9, -3.0, 1.4, 1.1), 0.3, 0.65 * jit(), -0.3)
    return {"vertices": vertices, "faces": faces, "uvs": uvs, "deltas": D, "names": EXPRESSIONS}


def target_animation(rig: dict, curves) -> np.ndarray:
    """Ground-truth animation of the target: the blendshape model.

    .. math:: V_t = V_0 + \\sum_e c_e(t) D_e

    Parameters
    ----------
    rig : dict
        From :func:`target_rig` (``vertices`` (N, 3), ``deltas`` (E, N, 3)).
    curves : ndarray, shape (T, E)

    Returns
    -------
    ndarray, shape (T, N, 3), float64
    """
    V0 = np.asarray(rig["vertices"], dtype=np.float64)
    D = np.asarray(rig["deltas"], dtype=np.float64)
    curves = np.asarray(curves, dtype=np.float64)
    if curves.ndim != 2 or curves.shape[1] != D.shape[0]:
        raise ShapeError(f"curves: expected shape (T, {D.shape[0]}), got {curves.shape}")
    return V0[None] + np.einsum("te,enk->tnk", curves, D)


# --------------------------------------------------------------------------
# writing a take
# --------------------------------------------------------------------------

#: Landmark regions of the 68-point layout modelled separately, as Chuang &
#: Bregler (2002, §5) model the eye and mouth regions: brows and eyes; mouth
#: with the lower jaw line (which moves with the jaw).
SOURCE_REGIONS = {
    "brows-eyes": list(range(17, 27)) + list(range(36, 48)),
    "mouth": list(range(3, 14)) + list(range(48, 68)),
}
#: Expressions each region carries (used to build the target's region masks).
REGION_EXPRESSIONS = {
    "brows-eyes": ("blink_l", "blink_r", "brow_raise", "brow_l"),
    "mouth": ("smile", "jaw_open", "pucker", "smirk_l"),
}


def target_region_masks(rig: dict) -> dict:
    """Per-vertex region weights for the target, from where each region's expressions move it.

    A vertex's weight for region r is its share of the displacement caused by
    r's expressions (:data:`REGION_EXPRESSIONS`), so the masks sum to 1 where
    any expression moves the face, blend smoothly where regions meet, and are 0
    on vertices no expression moves (those keep the neutral).

    Parameters
    ----------
    rig : dict
        From :func:`target_rig`.

    Returns
    -------
    dict of str to ndarray, each shape (N,), float64 in [0, 1]
    """
    mags = {
        r: sum(np.linalg.norm(rig["deltas"][EXPRESSIONS.index(e)], axis=1) for e in exprs)
        for r, exprs in REGION_EXPRESSIONS.items()
    }
    total = sum(mags.values())
    moving = total > 1e-4 * total.max()
    return {r: np.where(moving, m / np.where(moving, total, 1.0), 0.0) for r, m in mags.items()}


_OBJ_HEADER = "# retarget synth target character\nmtllib character.mtl\no character\nusemtl skin\n"
_MTL = """# retarget synth target character
newmtl skin
Ka 0.000000 0.000000 0.000000
Kd 0.850000 0.660000 0.560000
Ks 0.050000 0.050000 0.050000
Ns 10.000000
d 1.000000
illum 2
"""


def _write_video(path: Path, frames, size, fps: float, n_frames: int) -> None:
    """Atomically write *frames* as an mp4v video, logging progress."""

    step = max(1, n_frames // 10)
    with atomic_video_writer(path, fps, tuple(size)) as writer:
        for t, img in enumerate(frames):
            writer.write(img)
            if (t + 1) % step == 0 or t + 1 == n_frames:
                logger.info("synth: rendered %d/%d frames", t + 1, n_frames)


def write_take(outdir, *, n_frames: int = 240, size=(320, 320), seed: int = 0, fps: float = 30.0,
               speed: float = 1.0, **render) -> dict:
    """Generate a synthetic take with its ground truth and target character.

    Files written into *outdir* (each atomically; same arguments give
    byte-identical files):

    - ``face.mp4``: the rendered performance (mp4v);
    - ``face_00000.pts``: frame-0 landmarks (iBUG, 1-based);
    - ``truth_landmarks.npz``: true landmarks in the ``landmarks.npz``
      contract (points, confidence, head, stabilized, fps, frame_size, meta);
    - ``truth.npz``: ``curves`` (T, E) float64, ``names`` (E,) str, ``target``
      (T, N, 3) float32 (the target's true animation);
    - ``target/neutral.obj``, ``target/shapes/<expression>.obj`` (full mesh at
      activation 1, same topology), ``target/character.mtl``;
    - ``rig.yaml``: neutral, shapes and range, paths relative to it;
    - ``config.yaml``: :data:`SAMPLE_CONFIG`, the whole pipeline on this take.

    Parameters
    ----------
    outdir : path-like
        Created if missing.
    n_frames : int
        T >= 2.
    size : (int, int)
        Frame ``(W, H)``, each >= 64.
    seed : int
    fps : float
    speed : float
        Head-motion speed factor (see :func:`head_motion`).
    **render
        Perturbations passed to :func:`render_frames` (``noise``, ``blur``,
        ``jpeg``, ``light``, ``dots``). The defaults reproduce ``sample_data/``.

    Returns
    -------
    dict of str to Path
        Every file written, keyed ``video``, ``pts``, ``landmarks``,
        ``truth``, ``neutral``, ``shape:<expression>``, ``mtl``, ``rig``, ``config``.
    """
    import yaml


    n_frames = _check_int("n_frames", n_frames, 2)
    w, h = _check_size(size)
    seed = _check_seed(seed)
    fps = _check_fps(fps)
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    logger.info("synth: %d frames at %dx%d, seed %d -> %s", n_frames, w, h, seed, out)

    curves, stab, head, points = _truth_landmarks(n_frames, (w, h), seed, fps, speed)
    inside = (points[..., 0] >= 0) & (points[..., 0] <= w - 1) & (points[..., 1] >= 0) & (points[..., 1] <= h - 1)
    if not inside.all():
        logger.warning("synth: %d landmark positions fall outside the frame", int((~inside).sum()))

    paths: dict[str, Path] = {}
    paths["video"] = out / "face.mp4"
    _write_video(paths["video"], render_frames(points, size=(w, h), seed=seed, fps=fps, **render), (w, h), fps,
                 n_frames)

    paths["pts"] = out / "face_00000.pts"
    write_pts(paths["pts"], points[0])

    paths["landmarks"] = out / "truth_landmarks.npz"
    meta = {"source": "retarget synth", "seed": seed, "frames": n_frames, "size": [w, h],
            "expressions": list(EXPRESSIONS), "generator": "retarget_cli.synth"}
    save_landmarks(paths["landmarks"], Landmarks(
        points=points, confidence=np.ones(points.shape[:2]), head=head, stabilized=stab, fps=fps,
        frame_size=np.array([w, h]), meta=meta))

    rig = target_rig(seed=seed)
    paths["truth"] = out / "truth.npz"
    savez(paths["truth"], {
        "curves": curves,
        "names": np.array(EXPRESSIONS),
        "target": target_animation(rig, curves).astype(np.float32),
    })

    tdir = out / "target"
    obj = lambda verts: format_obj(verts, rig["faces"], uvs=rig["uvs"], face_uvs=rig["faces"],  # noqa: E731
                                   header=_OBJ_HEADER)
    paths["neutral"] = tdir / "neutral.obj"
    write_bytes(paths["neutral"], obj(rig["vertices"]))
    shapes = {}
    for e, name in enumerate(EXPRESSIONS):
        p = tdir / "shapes" / f"{name}.obj"
        write_bytes(p, obj(rig["vertices"] + rig["deltas"][e]))
        paths[f"shape:{name}"] = p
        shapes[name] = p.relative_to(out).as_posix()
    paths["mtl"] = tdir / "character.mtl"
    write_text(paths["mtl"], _MTL)

    paths["rig"] = out / "rig.yaml"
    doc = {"neutral": paths["neutral"].relative_to(out).as_posix(), "shapes": shapes, "range": [0, 1]}
    write_text(paths["rig"], yaml.safe_dump(doc, sort_keys=False))

    for region, mask in target_region_masks(rig).items():
        paths[f"mask:{region}"] = tdir / "regions" / f"{region}.txt"
        write_text(paths[f"mask:{region}"], "".join(f"{v:.6f}\n" for v in mask))

    paths["config"] = out / "config.yaml"
    write_text(paths["config"], SAMPLE_CONFIG)
    return paths


#: The ``config.yaml`` written beside every synthetic take: the whole pipeline,
#: with the rig posed at the true slider values of each key frame standing in
#: for the artist (``pose`` stage).
SAMPLE_CONFIG = """\
# Written by `retarget synth`. Run: retarget run config.yaml
# Input paths are relative to this file; outputs go under output_dir.
output_dir: out
seed: 0
track:
  video: face.mp4
  init: face_00000.pts
  method: lk         # the flow tracker from the annotation: on these rendered faces it beats the detector
select:
  method: greedy
  k: 12
  regions:           # modelled separately and blended on the target (Chuang & Bregler §5)
    brows-eyes: [17, 18, 19, 20, 21, 22, 23, 24, 25, 26, 36, 37, 38, 39, 40, 41, 42, 43, 44, 45, 46, 47]
    mouth: [3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 48, 49, 50, 51, 52, 53, 54, 55, 56, 57, 58, 59, 60, 61, 62, 63, 64, 65, 66, 67]
decompose:          # measured best on synthetic takes (README, "Decomposition")
  solver: sparse
  formulation: delta
  alpha: 0.05
  csv: weights.csv
pose:                # the synthetic artist: the rig posed at each key frame's true sliders
  rig: rig.yaml
  poses: truth.npz
  masks:
    brows-eyes: target/regions/brows-eyes.txt
    mouth: target/regions/mouth.txt
apply:
  head_motion: none
"""


# --------------------------------------------------------------------------
# rigs for the editing tools (retarget edit, retarget auto-pose)
# --------------------------------------------------------------------------


def overlapping_rig(*, n_shapes: int = 12, grid=(24, 20), seed: int = 0) -> dict:
    """A delta blendshape rig whose shapes overlap, as real rigs' do (Lewis et al. 2005, §1).

    A ``nx x ny`` grid over a dome (x, y in [-1, 1], z up to 0.3), quads, and
    *n_shapes* smooth, compactly supported bumps: each moves the vertices
    within radius 0.35-0.8 of a random centre along a random 3D direction
    (peak 0.1-0.3), so several shapes move most vertices ("blendshape
    interference").

    Parameters
    ----------
    n_shapes : int
    grid : (int, int)
        Vertices per row and column; ``(125, 200)`` gives 25,000 vertices.
    seed : int

    Returns
    -------
    dict
        ``vertices`` (N, 3), ``faces`` (F, 4), ``deltas`` (n_shapes, N, 3),
        ``names`` (``s00``, ``s01``, ...).
    """
    seed = _check_seed(seed)
    n_shapes = _check_int("n_shapes", n_shapes, 1)
    nx, ny = (_check_int("grid", g, 2) for g in grid)
    rng = np.random.default_rng([seed, 7])
    u, v = np.meshgrid(np.linspace(-1, 1, nx), np.linspace(-1, 1, ny))
    vertices = np.stack([u.ravel(), v.ravel(), 0.3 * (1 - 0.5 * (u**2 + v**2)).ravel()], 1)
    idx = np.arange(nx * ny).reshape(ny, nx)
    faces = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], -1).reshape(-1, 4)
    D = np.zeros((n_shapes, len(vertices), 3))
    for k in range(n_shapes):
        c = rng.uniform(-0.7, 0.7, 2)
        r = rng.uniform(0.35, 0.8)
        d = rng.normal(size=3)
        d *= rng.uniform(0.1, 0.3) / np.linalg.norm(d)
        fall = np.clip(1 - np.sum((vertices[:, :2] - c) ** 2, 1) / r**2, 0, None) ** 2
        D[k] = fall[:, None] * d
    names = tuple(f"s{k:02d}" for k in range(n_shapes))
    return {"vertices": vertices, "faces": faces, "deltas": D, "names": names}


def landmark_rig(*, n_extra: int = 60, seed: int = 0) -> dict:
    """A 3D rig whose landmark vertices reproduce the source face's 2D landmarks.

    The 68 source landmarks (:func:`source_neutral`, flipped to y up) are
    lifted onto a dome (z up to 0.3) and each expression's source
    displacement (:func:`source_deltas`) gets a small depth component, so an
    orthographic view of the rig posed at ``c(t)`` is the source face's
    landmarks for the same curves. *n_extra* further vertices (a ring
    around the face, no expression moves them) are added and all vertices
    shuffled, so the landmark-to-vertex map is not the identity.

    Returns
    -------
    dict
        ``vertices`` (N, 3), ``faces`` (F, 3) triangles, ``deltas`` (E, N, 3)
        in :data:`EXPRESSIONS` order, ``names``, ``landmark_vertices`` (68,)
        the vertex of each landmark.
    """
    from scipy.spatial import Delaunay

    seed = _check_seed(seed)
    rng = np.random.default_rng([seed, 8])
    n = source_neutral() * np.array([1.0, -1.0])
    d = source_deltas() * np.array([1.0, -1.0])
    ang = np.linspace(0, 2 * np.pi, n_extra, endpoint=False)
    ring = 0.75 * np.column_stack([np.cos(ang), np.sin(ang)])
    xy = np.vstack([n, ring])
    z = 0.3 * np.clip(1 - np.sum(xy**2, 1) / 0.75**2, 0, None)
    V = np.column_stack([xy, z])
    dz = 0.5 * np.linalg.norm(d, axis=2) * rng.uniform(-1, 1, (len(d), 1))
    D = np.zeros((len(d), len(V), 3))
    D[:, :68, :2] = d
    D[:, :68, 2] = dz
    perm = rng.permutation(len(V))  # new vertex i is old vertex perm[i]
    inv = np.argsort(perm)
    faces = inv[Delaunay(xy).simplices]
    return {"vertices": V[perm], "faces": faces, "deltas": D[:, perm], "names": EXPRESSIONS,
            "landmark_vertices": inv[:68]}


#: ``synth`` (:func:`retarget_cli.synth.take.write_take`).
SYNTH_PARAMS = [
    Param("outdir", "output", str, help="Folder for the take."),
    Param("frames", "setting", int, 240, "Number of frames.", min=2, max=100000),
    Param("size", "setting", list, [320, 320], "Frame size WxH in pixels."),
    Param("seed", "setting", int, 0, "Random seed.", min=0),
]


def _cli_synth(values, out):
    return list(write_take(values["outdir"], n_frames=values["frames"], size=tuple(values["size"]),
                           seed=values["seed"]).values())


#: ``synth`` (the CLI builds it: :mod:`retarget_cli.cli.commands`).
COMMAND = Command(
    "synth",
    """Write a synthetic performance (video, truth, target rig, config) into OUTDIR.""",
    lambda: SYNTH_PARAMS,
    (Flag("outdir", argument=True, path="folder"), "frames",
     Flag("size", value="size", value_args=(("lo", 64), ("hi", 4096)), default="320x320", metavar="WxH"), "seed"),
    _cli_synth,
    folder_output=True,
)
