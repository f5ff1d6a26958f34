"""``apply``'s exports for rig users: Live Link Face CSV and USD (their file handling).

:func:`~retarget_cli.stages.apply.run_apply` computes the curves or the
meshes; the functions here turn them into files (writers in
:mod:`retarget_cli.io.livelink` and :mod:`retarget_cli.io.usd`).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.atomic import write_text

log = logging.getLogger(__name__)


def head_rotation(landmarks, T: int):
    """(T, 3) head yaw, pitch, roll (radians) from ``landmarks.npz``, or None without a landmarks file.

    Roll comes from the tracked 2D head motion; yaw and pitch are 0 (the 2D
    track has no estimate of them).
    """
    from ..io.landmarks import load_landmarks
    from ..io.livelink import head_rotation_from_similarity

    if landmarks is None:
        return None
    lm = load_landmarks(landmarks)
    if lm.n_frames != T:
        raise InputError(f"{landmarks}: has {lm.n_frames} frames but the weights have {T}")
    return head_rotation_from_similarity(lm.head)


def write_livelink(path: Path, rig, curves: np.ndarray, fps: float, *, landmarks=None) -> Path:
    """Write the rig's curves as a Live Link Face CSV (:func:`retarget_cli.io.livelink.livelink_csv`).

    Parameters
    ----------
    rig : BlendshapeRig
        Its slider names, and ``rig.yaml``'s ``names:`` mapping (``rig.spec.names``).
    curves : ndarray, shape (T, n)
    landmarks : path-like, optional
        ``landmarks.npz``: HeadRoll from its head motion; without it the head columns are 0.
    """
    from ..io.livelink import livelink_csv

    rot = head_rotation(landmarks, len(curves))
    if rot is None:
        log.info("Live Link Face CSV: no landmarks file, so the head rotation columns are 0")
    names = rig.spec.names if rig.spec is not None else {}
    write_text(path, livelink_csv(curves, rig.names, fps, names=names, head_rotation=rot))
    return path


__all__ = ["head_rotation", "write_livelink"]
