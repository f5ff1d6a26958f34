"""Temporal filtering of tracked landmarks: a whole-take smoother and a causal filter.

Two pure functions over a landmark track ``points (T, L, 2)`` with its
per-point confidence ``(T, L)``:

* :func:`rts_smooth` -- a Kalman filter followed by the Rauch–Tung–Striebel
  backward pass (Rauch, Tung & Striebel 1965; Särkkä, *Bayesian Filtering and
  Smoothing*, 2013, §4.3 and §8.2) with a constant-velocity or
  constant-acceleration motion model per coordinate. The measurement noise of
  each point in each frame comes from its confidence, so an occluded or lost
  point (confidence 0) has no measurement and is filled in by the model from
  its neighbours in time. An optional robust (edge-preserving) mode
  re-weights the process noise where the smoothed motion is improbable
  (iteratively reweighted, Huber), so that fast events -- blinks, plosive lip
  closures -- keep their amplitude while slow motion is smoothed.
* :func:`one_euro` -- the One-Euro filter (Casiez, Roussel & Vogel 2012), an
  adaptive first-order low-pass for streaming use: each frame depends only on
  the frames before it.

Both work in image pixels at 1 frame per time step; ``fps`` only enters the
One-Euro cut-off frequencies.
"""

from __future__ import annotations

import logging

import numpy as np

from ...errors import ParameterError, ShapeError

log = logging.getLogger(__name__)

#: Filters accepted by :func:`filter_points` (``track.filter``).
FILTERS = ("rts", "one-euro", "none")
#: Motion models of :func:`rts_smooth`.
MODELS = ("cv", "ca")
#: A confidence at or below this is no measurement at all.
MIN_CONFIDENCE = 1e-3
#: Largest process-noise inflation of the robust smoother.
_MAX_SCALE = 1e8
#: Parts of the 68-point Multi-PIE layout that move together (``rts_smooth`` *groups*): brows, each eye, the
#: outer and the inner lip. A blink or a lip closure moves a whole part, so its event test pools the part's points.
GROUPS_68 = (tuple(range(17, 22)), tuple(range(22, 27)), tuple(range(36, 42)), tuple(range(42, 48)),
             tuple(range(48, 60)), tuple(range(60, 68)))


def _check(points, confidence):
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 3 or P.shape[2] != 2:
        raise ShapeError(f"points: expected shape (T, L, 2), got {P.shape}")
    T, L, _ = P.shape
    if confidence is None:
        C = np.where(np.isfinite(P).all(-1), 1.0, 0.0)
    else:
        C = np.asarray(confidence, dtype=np.float64)
        if C.shape != (T, L):
            raise ShapeError(f"confidence: expected shape ({T}, {L}) like points, got {C.shape}")
        if np.any(~np.isfinite(C)) or np.any(C < 0):
            raise ParameterError("confidence: expected finite values >= 0")
    C = np.where(np.isfinite(P).all(-1), C, 0.0)
    return P, C


def motion_model(model: str, q: float):
    """Transition matrix ``F`` and process-noise covariance ``Q`` of one coordinate, one frame step.

    The continuous white-noise models of Bar-Shalom, Li & Kirubarajan (2001,
    §6.2), sampled at ``Δt = 1`` frame, with spectral density ``q²``:

    constant velocity (``cv``, state ``[x, ẋ]``, white acceleration)

    .. math::

        F = \\begin{pmatrix} 1 & 1 \\\\ 0 & 1 \\end{pmatrix}, \\quad
        Q = q^2 \\begin{pmatrix} 1/3 & 1/2 \\\\ 1/2 & 1 \\end{pmatrix}

    constant acceleration (``ca``, state ``[x, ẋ, ẍ]``, white jerk)

    .. math::

        F = \\begin{pmatrix} 1 & 1 & 1/2 \\\\ 0 & 1 & 1 \\\\ 0 & 0 & 1 \\end{pmatrix}, \\quad
        Q = q^2 \\begin{pmatrix} 1/20 & 1/8 & 1/6 \\\\ 1/8 & 1/3 & 1/2 \\\\ 1/6 & 1/2 & 1 \\end{pmatrix}

    Parameters
    ----------
    model : {"cv", "ca"}
    q : float
        Process noise, pixels per frame² (``cv``) or per frame³ (``ca``).

    Returns
    -------
    F, Q : ndarray, shape (n, n)
        ``n`` = 2 (``cv``) or 3 (``ca``).
    """
    if model == "cv":
        F = np.array([[1.0, 1.0], [0.0, 1.0]])
        Q = np.array([[1 / 3, 1 / 2], [1 / 2, 1.0]])
    elif model == "ca":
        F = np.array([[1.0, 1.0, 0.5], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]])
        Q = np.array([[1 / 20, 1 / 8, 1 / 6], [1 / 8, 1 / 3, 1 / 2], [1 / 6, 1 / 2, 1.0]])
    else:
        raise ParameterError(f"model: expected one of {MODELS}, got {model!r}")
    return F, q * q * Q


def _prior(P, C, n, prior_var):
    """Prior mean (L, 2, n) at frame 0: each point's first measured position, zero derivatives."""
    T, L, _ = P.shape
    measured = C > MIN_CONFIDENCE
    first = np.where(measured.any(0), measured.argmax(0), 0)
    m0 = np.zeros((L, 2, n))
    y0 = P[first, np.arange(L)]
    m0[:, :, 0] = np.where(np.isfinite(y0), y0, 0.0)
    P0 = np.broadcast_to(np.eye(n) * prior_var, (L, n, n)).copy()
    return m0, P0


def _kalman_rts(P, C, F, Q, r, scale, m0, P0):
    """Forward Kalman filter and RTS backward pass for every point; returns smoothed means (T, L, 2, n).

    ``Q`` is scaled per step and point by ``scale`` (T−1, L); measurement
    variance is ``r² / c`` (no update where ``c ≤`` :data:`MIN_CONFIDENCE`).
    The covariance is shared by a point's x and y (same model, same noise).
    """
    T, L, _ = P.shape
    n = F.shape[0]
    mp = np.empty((T, L, 2, n))   # predicted means
    Pp = np.empty((T, L, n, n))   # predicted covariances
    mf = np.empty((T, L, 2, n))   # filtered
    Pf = np.empty((T, L, n, n))
    measured = C > MIN_CONFIDENCE
    R = np.where(measured, r * r / np.where(measured, C, 1.0), np.inf)
    Y = np.where(np.isfinite(P), P, 0.0)
    m, Pc = m0, P0
    for t in range(T):
        if t:
            m = m @ F.T
            Pc = F @ Pc @ F.T + scale[t - 1][:, None, None] * Q
        mp[t], Pp[t] = m, Pc
        ok = measured[t]
        if ok.any():
            S = Pc[:, 0, 0] + np.where(ok, R[t], 1.0)          # (L,)
            K = Pc[:, :, 0] / S[:, None]                          # (L, n)
            K[~ok] = 0.0
            innov = Y[t] - m[:, :, 0]                             # (L, 2)
            m = m + innov[:, :, None] * K[:, None, :]
            Pc = Pc - K[:, :, None] * K[:, None, :] * S[:, None, None]
            Pc = 0.5 * (Pc + np.swapaxes(Pc, 1, 2))
        mf[t], Pf[t] = m, Pc
    ms = mf.copy()
    Ps = Pf[-1]
    for t in range(T - 2, -1, -1):
        # G = Pf[t] Fᵀ Pp[t+1]⁻¹ (Pp symmetric positive definite)
        G = np.swapaxes(np.linalg.solve(Pp[t + 1], F @ Pf[t]), 1, 2)
        ms[t] = mf[t] + (ms[t + 1] - mp[t + 1]) @ np.swapaxes(G, 1, 2)
        Ps = Pf[t] + G @ (Ps - Pp[t + 1]) @ np.swapaxes(G, 1, 2)
    return ms


def _window_residual(P, C, X, sigma, groups=()):
    """RMS normalised residual ``√(c‖y − x̂‖² / 2σ²)`` over frames t−1, t, t+1 of each point (T, L).

    With *groups*, a point's value is the larger of its own and its group's (the RMS over the group's points
    and the same frames).
    """
    measured = C > MIN_CONFIDENCE
    r2 = np.where(measured, C * np.sum((np.where(np.isfinite(P), P, 0.0) - X) ** 2, -1) / (2 * sigma**2), 0.0)
    n = measured.astype(np.float64)
    num, den = r2.copy(), n.copy()
    num[1:] += r2[:-1]
    num[:-1] += r2[1:]
    den[1:] += n[:-1]
    den[:-1] += n[1:]
    out = np.sqrt(num / np.maximum(den, 1.0))
    for g in groups:
        g = list(g)
        pooled = np.sqrt(num[:, g].sum(1) / np.maximum(den[:, g].sum(1), 1.0))
        out[:, g] = np.maximum(out[:, g], pooled[:, None])
    return out


def rts_smooth(points, confidence=None, *, model: str = "ca", process_noise: float = 0.1,
               measurement_noise: float = 0.5, robust: float = 0.0, iterations: int = 5,
               prior_var: float = 1e6, groups=(), return_state: bool = False):
    """Rauch–Tung–Striebel smoother of a landmark track (whole take).

    Each coordinate of each landmark is a linear-Gaussian state-space model
    (:func:`motion_model`)

    .. math::

        x_{t+1} = F x_t + v_t,\\ v_t \\sim N(0, s_{t} Q), \\qquad
        y_t = H x_t + e_t,\\ e_t \\sim N(0, \\sigma^2 / c_t), \\qquad H = (1, 0, \\dots)

    with ``σ`` = *measurement_noise* and ``c_t`` the point's confidence (no
    measurement where ``c_t ≤`` :data:`MIN_CONFIDENCE`), and the prior
    ``x_0 ~ N(m_0, prior_var·I)``, ``m_0`` = the point's first measured
    position with zero derivatives. The Kalman filter (forward)

    .. math::

        m^-_t = F m_{t-1},\\ P^-_t = F P_{t-1} F^T + s_{t-1} Q,\\
        K_t = P^-_t H^T / (H P^-_t H^T + \\sigma^2/c_t),\\
        m_t = m^-_t + K_t (y_t - H m^-_t),\\ P_t = P^-_t - K_t H P^-_t

    and the RTS backward pass

    .. math::

        G_t = P_t F^T (P^-_{t+1})^{-1},\\
        m^s_t = m_t + G_t (m^s_{t+1} - m^-_{t+1}),\\
        P^s_t = P_t + G_t (P^s_{t+1} - P^-_{t+1}) G_t^T

    give the posterior mean ``m^s_t``, which is also the minimiser of the
    dense least-squares problem

    .. math::

        \\|x_0 - m_0\\|^2_{P_0^{-1}} + \\sum_t \\frac{c_t}{\\sigma^2} (y_t - H x_t)^2
        + \\sum_t \\frac{1}{s_t} \\|x_{t+1} - F x_t\\|^2_{Q^{-1}}

    (``tests/unit/methods/tracking/test_filter.py`` checks the two agree to 1e-8).

    Edge preservation (*robust* ``k > 0``): the linear-Gaussian model
    smooths a blink's few frames of fast motion away. After each pass, the
    normalised residual of every point, ``r_t = √(c_t ‖y_t − m^s_t‖² / 2σ²)``,
    is averaged (RMS) over frames ``t−1, t, t+1``; where it exceeds ``k`` the
    smoothed track cannot explain the measurements (an event the motion model
    does not describe), and the process-noise scale ``s`` of the steps into,
    through and out of those frames (dilated by one frame) is set to
    :data:`_MAX_SCALE`, so the model lets go there and the track follows the
    measurements. Passes repeat until no window exceeds ``k`` (at most
    *iterations*). Under the model, ``r̄_t² · 6`` is χ² with 6 degrees of
    freedom, so a quiet window is flagged with probability about 5e-4 at
    ``k = 2`` (``track``'s default) and 1e-9 at ``k = 3``; a flagged window
    only means less smoothing there. Everything outside the events is
    smoothed exactly as without *robust*.

    *groups* (e.g. :data:`GROUPS_68`: the brows, each eye, each lip
    contour) shares the test among points that move together: a window
    flagged for one point of a group is flagged for all of them, and a
    point's ``r̄_t`` is the larger of its own and the RMS over its group's
    points and the same three frames. So a blink releases every point of the
    eye, including the lower lid, whose own motion is too small to be
    flagged alone.

    Parameters
    ----------
    points : ndarray, shape (T, L, 2)
        Image pixels; NaN is treated as no measurement.
    confidence : ndarray, shape (T, L), optional
        In [0, 1] (values above 1 mean more trust); default 1 where finite.
    model : {"ca", "cv"}
        Constant acceleration or constant velocity.
    process_noise : float
        ``q`` of :func:`motion_model`, pixels per frame² (``cv``) or frame³ (``ca``), > 0.
    measurement_noise : float
        ``σ``, pixels, of a point with confidence 1, > 0.
    robust : float
        Event threshold ``k`` on the windowed normalised residual (0: plain linear-Gaussian smoother).
    iterations : int
        Reweighting passes when *robust* > 0.
    prior_var : float
        Prior variance of the initial state (large: uninformative).
    groups : sequence of sequences of int
        Point indices that share the event test (see above); default none.
    return_state : bool
        Also return the smoothed state (T, L, 2, n) and the scales ``s`` (T−1, L).

    Returns
    -------
    ndarray, shape (T, L, 2)
        Smoothed positions (a point never measured keeps its input values).
    """
    P, C = _check(points, confidence)
    if not process_noise > 0 or not measurement_noise > 0 or not prior_var > 0:
        raise ParameterError(f"process_noise, measurement_noise and prior_var must be > 0, got "
                         f"{process_noise}, {measurement_noise}, {prior_var}")
    if not robust >= 0:
        raise ParameterError(f"robust: expected a number >= 0, got {robust}")
    T, L, _ = P.shape
    groups = [list(g) for g in groups]
    bad = [i for g in groups for i in g if not 0 <= int(i) < L]
    if bad:
        raise ValueError(f"groups: point index {bad[0]} is outside the {L} points")
    F, Q = motion_model(model, process_noise)
    n = F.shape[0]
    m0, P0 = _prior(P, C, n, prior_var)
    scale = np.ones((max(T - 1, 0), L))
    ms = _kalman_rts(P, C, F, Q, measurement_noise, scale, m0, P0)
    for it in range(max(int(iterations), 0) if robust > 0 and T >= 3 else 0):
        rbar = _window_residual(P, C, ms[..., 0], measurement_noise, groups)
        if rbar.max() <= robust:
            break
        event = rbar > robust                                           # (T, L)
        for g in groups:                                                 # an event of one point is its part's
            event[:, g] |= event[:, g].any(1, keepdims=True)
        event[1:] |= event[:-1].copy()
        event[:-1] |= event[1:].copy()                                   # frames t-1 .. t+1 of each window
        step = event[1:] | event[:-1]                                    # steps into and out of them
        if np.all(scale[step] >= _MAX_SCALE):
            break
        scale[step] = _MAX_SCALE
        log.debug("rts: pass %d, %d steps reweighted, max scale %.3g", it + 1, int((scale > 1).sum()), scale.max())
        ms = _kalman_rts(P, C, F, Q, measurement_noise, scale, m0, P0)
    out = ms[..., 0].copy()
    never = ~(C > MIN_CONFIDENCE).any(0)
    if never.any():
        out[:, never] = P[:, never]
    if return_state:
        return out, ms, scale
    return out


def one_euro(points, confidence=None, *, fps: float = 30.0, min_cutoff: float = 1.0, beta: float = 0.05,
             d_cutoff: float = 1.0) -> np.ndarray:
    """Causal One-Euro filter of a landmark track (Casiez, Roussel & Vogel 2012).

    With ``T_e = 1/fps`` and the smoothing factor of a first-order low-pass
    of cut-off ``f_c``, ``a(f_c) = 1 / (1 + τ/T_e)``, ``τ = 1/(2π f_c)``, each
    point is filtered frame by frame:

    .. math::

        \\dot{x}_t = (y_t - \\hat{x}_{t-1}) / T_e, \\quad
        \\hat{\\dot{x}}_t = \\hat{\\dot{x}}_{t-1} + a(f_d) (\\dot{x}_t - \\hat{\\dot{x}}_{t-1}),

        f_c = f_{min} + \\beta \\|\\hat{\\dot{x}}_t\\|, \\quad
        \\hat{x}_t = \\hat{x}_{t-1} + a(f_c)\\, c_t\\, (y_t - \\hat{x}_{t-1})

    (``‖·‖`` over the point's x and y, so both share one cut-off). The
    confidence ``c_t ∈ [0, 1]`` scales the update (confidence 1 is the
    original filter); a point with no measurement (confidence ≤
    :data:`MIN_CONFIDENCE` or NaN) moves on with the speed of its output,
    ``x̂_t = x̂_{t−1} + T_e v_{t−1}``, ``v`` the output's frame-to-frame
    speed low-passed at ``f_d``.
    Fast motion raises the cut-off (little lag); slow motion lowers it
    (little jitter).

    Parameters
    ----------
    points : ndarray, shape (T, L, 2)
    confidence : ndarray, shape (T, L), optional
    fps : float
    min_cutoff : float
        ``f_min``, Hz, > 0.
    beta : float
        Speed coefficient, per pixel (``f_c`` in Hz per pixel/s), >= 0.
    d_cutoff : float
        ``f_d``, Hz, cut-off of the speed estimate, > 0.

    Returns
    -------
    ndarray, shape (T, L, 2)
    """
    P, C = _check(points, confidence)
    if not fps > 0 or not min_cutoff > 0 or not d_cutoff > 0 or not beta >= 0:
        raise ParameterError(f"fps, min_cutoff and d_cutoff must be > 0 and beta >= 0, got {fps}, {min_cutoff}, "
                         f"{d_cutoff}, {beta}")
    T, L, _ = P.shape
    te = 1.0 / fps

    def a(fc):
        return 1.0 / (1.0 + 1.0 / (2 * np.pi * fc * te))

    c = np.clip(C, 0.0, 1.0)
    c[c <= MIN_CONFIDENCE] = 0.0
    out = np.empty_like(P)
    measured = c > 0
    first = np.where(measured.any(0), measured.argmax(0), 0)
    x = np.where(np.isfinite(P[first, np.arange(L)]), P[first, np.arange(L)], 0.0)
    dx = np.zeros((L, 2))
    v = np.zeros((L, 2))   # low-passed speed of the output, for the frames without a measurement
    ad = a(d_cutoff)
    for t in range(T):
        ok = measured[t][:, None]
        y = np.where(ok, P[t], x)
        raw = (y - x) / te
        dx = np.where(ok, dx + ad * (raw - dx), dx)
        fc = min_cutoff + beta * np.linalg.norm(dx, axis=1)
        new = np.where(ok, x + (a(fc) * c[t])[:, None] * (y - x), x + v * te)
        v = np.where(ok, v + ad * ((new - x) / te - v), v) if t else v
        x = new
        out[t] = x
    never = ~measured.any(0)
    if never.any():
        out[:, never] = P[:, never]
    return out


def filter_points(points, confidence=None, *, method: str = "rts", fps: float = 30.0, model: str = "ca",
                  process_noise: float = 0.1, measurement_noise: float = 0.5, robust: float = 0.0, groups=(),
                  min_cutoff: float = 1.0, beta: float = 0.05, d_cutoff: float = 1.0) -> np.ndarray:
    """Apply the landmark filter chosen by *method* (``track.filter``).

    ``rts`` calls :func:`rts_smooth` (*model*, *process_noise*,
    *measurement_noise*, *robust*, *groups*), ``one-euro`` :func:`one_euro` (*fps*,
    *min_cutoff*, *beta*, *d_cutoff*), ``none`` returns a copy.

    Parameters
    ----------
    points : ndarray, shape (T, L, 2)
    confidence : ndarray, shape (T, L), optional

    Returns
    -------
    ndarray, shape (T, L, 2), float64
    """
    if method == "rts":
        return rts_smooth(points, confidence, model=model, process_noise=process_noise,
                          measurement_noise=measurement_noise, robust=robust, groups=groups)
    if method == "one-euro":
        return one_euro(points, confidence, fps=fps, min_cutoff=min_cutoff, beta=beta, d_cutoff=d_cutoff)
    if method == "none":
        return np.array(points, dtype=np.float64)
    raise ParameterError(f"filter: expected one of {FILTERS}, got {method!r}")
