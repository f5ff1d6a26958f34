"""Landmark annotations: iBUG ``.pts`` files.

iBUG ``.pts`` coordinates are 1-based (the 300-W convention: the centre of the
top-left pixel is (1, 1)); the pipeline uses OpenCV's 0-based pixel centres, so
reading subtracts :data:`PTS_ORIGIN` and writing adds it.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from ..errors import InputError
from .atomic import write_text

#: Pixel-centre coordinate of the top-left pixel in ``.pts`` files.
PTS_ORIGIN = 1.0


def read_pts(path: str | os.PathLike) -> np.ndarray:
    """Read an iBUG ``.pts`` file.

    Returns
    -------
    ndarray, shape (L, 2), float64
        0-based pixel coordinates.

    Raises
    ------
    InputError
        If the file is missing, the header is malformed, or the number of
        points differs from ``n_points``.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError:
        raise InputError(f"{path}: annotation file not found") from None
    m = re.search(r"n_points\s*:\s*(\d+)", text)
    body = re.search(r"\{(.*)\}", text, re.S)
    if not m or not body:
        raise InputError(f"{path}: not an iBUG .pts file (expected 'n_points: N' and a '{{ ... }}' block)")
    n = int(m.group(1))
    try:
        vals = np.array(body.group(1).split(), dtype=np.float64)
    except ValueError as exc:
        raise InputError(f"{path}: non-numeric coordinate ({exc})") from exc
    if vals.size != 2 * n:
        raise InputError(f"{path}: header says {n} points but the block holds {vals.size / 2:g}")
    pts = vals.reshape(n, 2) - PTS_ORIGIN
    if not np.all(np.isfinite(pts)):
        raise InputError(f"{path}: coordinates must be finite")
    return pts


def write_pts(path: str | os.PathLike, points: np.ndarray) -> None:
    """Atomically write 0-based pixel *points* (shape (L, 2)) as an iBUG ``.pts`` file."""
    points = np.asarray(points, dtype=np.float64) + PTS_ORIGIN
    lines = ["version: 1", f"n_points: {len(points)}", "{"]
    lines += [f"{x:.3f} {y:.3f}" for x, y in points]
    lines += ["}", ""]
    write_text(path, "\n".join(lines))
