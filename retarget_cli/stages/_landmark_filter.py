"""Landmark filtering of ``track`` and ``import``: settings in, filtered points and their record out."""

from __future__ import annotations

import logging

import numpy as np

from ..config import Param
from ..errors import InputError
from ..methods.tracking.filter import filter_points

log = logging.getLogger(__name__)

#: Landmark filter settings of ``track`` and ``import`` (retarget_cli.methods.tracking.filter.filter_points).
FILTER_PARAMS = (
    Param("filter", "setting", str, "rts",
          "Landmark filter after tracking: rts (whole-take Rauch-Tung-Striebel smoother), one-euro (causal) or none; "
          "the unfiltered points are kept as points_raw.", choices=("rts", "one-euro", "none")),
    Param("filter_model", "setting", str, "ca", "Motion model of rts: ca (constant acceleration) or cv (velocity).",
          choices=("ca", "cv")),
    Param("filter_process_noise", "setting", float, 0.3,
          "rts process noise q, pixels per frame^3 (ca) or frame^2 (cv): larger follows faster motion.",
          min=1e-6, max=1e6),
    Param("filter_measurement_noise", "setting", float, 0.5,
          "rts measurement noise of a point with confidence 1, pixels (divided by the confidence).",
          min=1e-6, max=1e6),
    Param("filter_robust", "setting", float, 2.0,
          "rts event threshold (normalised residual over 3 frames): above it the smoother follows the points, "
          "so blinks keep their amplitude; 0: off.", min=0, max=1e6),
    Param("filter_min_cutoff", "setting", float, 1.0, "one-euro minimum cut-off frequency, Hz.", min=1e-6),
    Param("filter_beta", "setting", float, 0.05, "one-euro speed coefficient (cut-off Hz per pixel/s).", min=0),
    Param("filter_d_cutoff", "setting", float, 1.0, "one-euro cut-off of the speed estimate, Hz.", min=1e-6),
)


#: Keyword names of the filter settings, with their defaults.
FILTER_DEFAULTS = {p.name: p.default for p in FILTER_PARAMS}


#: Filter confidence of an annotated frame's points (measurement noise ÷ 10⁴: the track passes through them).
ANCHOR_CONFIDENCE = 1e8


def apply_filter(points, confidence, *, fps: float, settings: dict, where: str, anchors=()):
    """Filter a track with :func:`retarget_cli.methods.tracking.filter.filter_points` per *settings*.

    Parameters
    ----------
    points : ndarray, shape (T, L, 2)
    confidence : ndarray, shape (T, L)
    fps : float
    settings : dict
        :data:`FILTER_DEFAULTS` keys.
    where : str
        Names the input in errors.
    anchors : iterable of int
        Rows of annotated frames: the filter treats them as near-exact
        measurements and they keep their given positions.

    Returns
    -------
    points : ndarray, shape (T, L, 2)
        Filtered (the input itself when the filter is ``none``).
    raw : ndarray, shape (T, L, 2) or None
        The unfiltered points (None when the filter is ``none``).
    meta : dict
        The filter and its parameters, for ``landmarks.npz`` meta.
    """

    method = settings["filter"]
    meta = {"method": method}
    if method == "none":
        return points, None, meta
    if method == "rts":
        params = {"model": settings["filter_model"], "process_noise": settings["filter_process_noise"],
                  "measurement_noise": settings["filter_measurement_noise"], "robust": settings["filter_robust"]}
    else:
        params = {"fps": fps, "min_cutoff": settings["filter_min_cutoff"], "beta": settings["filter_beta"],
                  "d_cutoff": settings["filter_d_cutoff"]}
    anchors = [int(a) for a in anchors if 0 <= a < len(points)]
    conf = np.array(confidence, dtype=np.float64)
    if anchors and method == "rts":
        conf[anchors] = ANCHOR_CONFIDENCE
    try:
        out = filter_points(points, conf, method=method, **params)
    except ValueError as exc:
        raise InputError(f"{where}: filter {method}: {exc}") from exc
    out[anchors] = np.asarray(points, dtype=np.float64)[anchors]
    meta.update({k: v for k, v in params.items() if k != "fps"})
    moved = np.sqrt(np.mean(np.sum((out - points) ** 2, -1)))
    log.info("filter %s: landmarks moved by %.3g px RMS", method, moved)
    return out, np.asarray(points, dtype=np.float64), meta
