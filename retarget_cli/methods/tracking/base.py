"""What every tracker shares: its registry entry (:class:`TrackerSpec`) and the helpers trackers use.

A tracker is a function ``track(frames, annotations, *, progress, **settings)
-> (points, confidence)``: *frames* an iterable of images (gray ``uint8`` when
the spec says ``gray``), *annotations* ``{frame index: (L, 2) array}``,
*points* ``(T, L, 2)`` and *confidence* ``(T, L)`` in [0, 1]. It raises
:class:`~retarget_cli.errors.FaceLostError` when the face is lost. The track
stage (:mod:`retarget_cli.stages.track`) finds it in
:data:`retarget_cli.methods.tracking.TRACKERS` and passes it the settings its spec names.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ...errors import ShapeError


def to_gray(frame: np.ndarray) -> np.ndarray:
    """A BGR frame (H, W, 3) as grayscale (H, W); a 2-D frame is returned as it is."""
    import cv2

    return cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if frame.ndim == 3 else frame


@dataclass(frozen=True)
class TrackerSpec:
    """One tracking method of ``track --method``.

    Attributes
    ----------
    help : str
        What the method is, one phrase for ``--method``'s help and docs/config.md.
    function : str or callable
        ``"module:function"`` of the tracker (imported only when it runs, so
        ``retarget --help`` stays fast), or the function itself.
    settings : tuple of str
        The ``track`` settings it takes as keyword arguments (``window``,
        ``downscale``, ``rigid_points``, ...). A setting it does not take is
        ignored with a warning when it is not at its default.
    gray : bool
        It tracks gray ``uint8`` frames (converted while decoding).
    needs : tuple of str
        Objects the stage prepares for it: ``"detector"`` (the pretrained
        landmark detector) or ``"model"`` (the loaded Facemark model of
        ``track.model``).
    params : tuple of Param
        Settings of its own, added to the ``track`` stage's declarations
        (YAML, CLI options, docs) when no other declares them.
    gaps : bool
        It keeps tracking through frames without a face: called with ``gaps=True`` it returns a third
        value, a :class:`~retarget_cli.methods.gaps.Coverage` (which frames had a face, why not, scene cuts),
        and raises :class:`~retarget_cli.errors.FaceLostError` only when no frame has one.
    on_frame : bool
        It takes ``on_frame``, called after each frame with the frame in gray at full resolution and its
        landmarks as tracked so far (see :func:`~retarget_cli.methods.tracking.detect.track_detect`): the stage
        keeps the eyes' pixels for the gaze instead of decoding the video again.
    """

    help: str
    function: str | Callable
    settings: tuple[str, ...] = ()
    gray: bool = False
    needs: tuple[str, ...] = ()
    params: tuple = ()
    gaps: bool = False
    on_frame: bool = False

    def load(self) -> Callable:
        """The tracker function."""
        if callable(self.function):
            return self.function
        module, _, name = self.function.partition(":")
        return getattr(importlib.import_module(module), name)


def check_inside(P, size, what: str) -> None:
    """Raise if any point of *P* (L, 2) lies outside an image of *size* ``(W, H)``."""
    w, h = size
    out = (P < -0.5).any(1) | (P[:, 0] > w - 0.5) | (P[:, 1] > h - 0.5)
    if out.any():
        i = int(np.flatnonzero(out)[0])
        raise ShapeError(f"{what}: point {i} at {P[i].round(1).tolist()} lies outside the {w}x{h} image "
                         f"({int(out.sum())} of {len(P)} points outside)")


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


def flow_forward_backward(src, dst, points, lk: dict, guess=None, lk_init: dict | None = None, back_guess=None,
                          lk_back: dict | None = None):
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
    back_guess : ndarray, shape (L, 1, 2), float32, optional
        Offsets from the forward result at which the backward pass starts,
        used with *lk_back* (with ``cv2.OPTFLOW_USE_INITIAL_FLOW``). By
        default the backward pass starts at the forward result with *lk*.

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
    if back_guess is None:
        bwd, st2, _ = cv2.calcOpticalFlowPyrLK(dst, src, fwd, None, **lk)
    else:
        bwd, st2, _ = cv2.calcOpticalFlowPyrLK(dst, src, fwd, fwd + back_guess, **lk_back)
    fb = np.linalg.norm((bwd - points).reshape(-1, 2), axis=1)
    ok = (st1.ravel() == 1) & (st2.ravel() == 1) & np.isfinite(fb)
    return fwd, np.where(ok, fb, np.inf)
