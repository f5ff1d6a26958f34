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
#: Most landmarks an annotation may have, and largest frame number (memory-bomb guards).
MAX_POINTS = 100_000
MAX_FRAME = 100_000_000


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
        if path.stat().st_size > 64 * MAX_POINTS:
            raise InputError(f"{path}: too large for an annotation of at most {MAX_POINTS} points")
        text = path.read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError:
        raise InputError(f"{path}: annotation file not found") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a folder; expected a .pts file") from None
    m = re.search(r"n_points\s*:\s*(\d+)", text)
    body = re.search(r"\{(.*)\}", text, re.S)
    if not m or not body:
        raise InputError(f"{path}: not an iBUG .pts file (expected 'n_points: N' and a '{{ ... }}' block)")
    n = int(m.group(1)[:12])
    if not 1 <= n <= MAX_POINTS:
        raise InputError(f"{path}: n_points must be in [1, {MAX_POINTS}], got {m.group(1)[:12]}")
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


def pts_text(points: np.ndarray) -> str:
    """The iBUG ``.pts`` text of 0-based pixel *points* (shape (L, 2))."""
    points = np.asarray(points, dtype=np.float64) + PTS_ORIGIN
    lines = ["version: 1", f"n_points: {len(points)}", "{"]
    lines += [f"{x:.3f} {y:.3f}" for x, y in points]
    lines += ["}", ""]
    return "\n".join(lines)


def write_pts(path: str | os.PathLike, points: np.ndarray) -> None:
    """Atomically write 0-based pixel *points* (shape (L, 2)) as an iBUG ``.pts`` file."""
    write_text(path, pts_text(points))


_FRAME_IN_NAME = re.compile(r"(\d+)$")


def pts_frame(path) -> int | None:
    """Frame number at the end of a ``.pts`` file's stem (``face_00120.pts`` -> 120), else None."""
    m = _FRAME_IN_NAME.search(Path(path).stem)
    return int(m.group(1)) if m else None


def read_csv_landmarks(path: str | os.PathLike) -> dict[int, np.ndarray]:
    """Read a ``frame,point,x,y`` CSV (header line required; 0-based pixel coordinates).

    Returns
    -------
    dict of int to ndarray, shape (L, 2)
        Landmarks per frame; every frame must list points ``0..L-1`` once.

    Raises
    ------
    InputError
        Naming the file and line (bad header or value), or the frame (missing,
        repeated points, or a point count that differs from another frame's).
    """
    import csv

    path = Path(path)
    try:
        fh = path.open(newline="", encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{path}: landmarks CSV not found") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a folder; expected a frame,point,x,y CSV") from None
    rows: dict[int, dict[int, tuple[float, float]]] = {}
    try:
        with fh:
            _read_csv_rows(path, csv.reader(fh), rows)
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not UTF-8 text (byte {exc.start}); expected a frame,point,x,y CSV") from None
    except csv.Error as exc:
        raise InputError(f"{path}: not a readable CSV ({exc})") from None
    if not rows:
        raise InputError(f"{path}: no landmark rows")
    out, first = {}, None
    for f in sorted(rows):
        n = len(rows[f])
        if sorted(rows[f]) != list(range(n)):
            missing = next(i for i in range(n + 1) if i not in rows[f])
            raise InputError(f"{path}: frame {f} lacks point {missing} (points must be numbered 0..L-1)")
        if first is None:
            first = (f, n)
        elif n != first[1]:
            raise InputError(f"{path}: frame {f} has {n} points but frame {first[0]} has {first[1]}")
        out[f] = np.array([rows[f][p] for p in range(n)], dtype=np.float64)
    return out


def _read_csv_rows(path, reader, rows) -> None:
    """Fill *rows* (frame -> point -> (x, y)) from a ``frame,point,x,y`` CSV reader."""
    header = [h.strip().lower() for h in next(reader, [])]
    if header[:4] != ["frame", "point", "x", "y"]:
        raise InputError(f"{path}: expected the header 'frame,point,x,y', got {','.join(header)[:80]!r}")
    for line, row in enumerate(reader, start=2):
        if not row or all(not c.strip() for c in row):
            continue
        try:
            f, p, x, y = int(row[0]), int(row[1]), float(row[2]), float(row[3])
        except (ValueError, IndexError):
            raise InputError(f"{path}: line {line}: expected integers frame,point and numbers x,y, "
                             f"got {','.join(row)[:80]!r}") from None
        if f < 0 or p < 0 or not (np.isfinite(x) and np.isfinite(y)):
            raise InputError(f"{path}: line {line}: frame and point must be >= 0 and x, y finite")
        if p >= MAX_POINTS or f > MAX_FRAME:
            raise InputError(f"{path}: line {line}: point {p} / frame {f} is too large (points < {MAX_POINTS}, "
                             f"frames <= {MAX_FRAME})")
        if p in rows.setdefault(f, {}):
            raise InputError(f"{path}: line {line}: frame {f} lists point {p} twice")
        rows[f][p] = (x, y)


def write_csv_landmarks(path: str | os.PathLike, points, frames=None) -> None:
    """Atomically write landmarks (T, L, 2) as a ``frame,point,x,y`` CSV (0-based pixels)."""
    points = np.asarray(points, dtype=np.float64)
    frames = range(len(points)) if frames is None else frames
    lines = ["frame,point,x,y"]
    for f, P in zip(frames, points):
        lines += [f"{int(f)},{i},{x:.4f},{y:.4f}" for i, (x, y) in enumerate(P)]
    write_text(path, "\n".join(lines) + "\n")


def read_annotations(paths, *, frame: int | None = None) -> tuple[dict[int, np.ndarray], dict[int, Path]]:
    """Annotations of one or several frames from ``.pts`` and ``frame,point,x,y`` CSV files.

    The frame of a ``.pts`` file is the number ending its name
    (``face_00120.pts``), else *frame* (default 0) when it is the only file.

    Returns
    -------
    points : dict of int to ndarray (L, 2)
    sources : dict of int to Path
        The file each frame came from (for error messages).

    Raises
    ------
    InputError
        Two files for one frame, a ``.pts`` without a frame number among
        several files, or point counts that differ (naming both files and counts).
    """
    paths = [Path(p) for p in ([paths] if isinstance(paths, (str, os.PathLike)) else paths)]
    pts: dict[int, np.ndarray] = {}
    src: dict[int, Path] = {}
    for p in paths:
        if p.suffix.lower() == ".csv":
            got = read_csv_landmarks(p)
        elif p.suffix.lower() == ".pts":
            f = pts_frame(p) if frame is None else frame
            if f is None:
                if len(paths) > 1:
                    raise InputError(f"{p}: no frame number in the file name (expected e.g. face_00120.pts)")
                f = 0
            if f > MAX_FRAME:
                raise InputError(f"{p}: frame {f} (from the file name) is larger than {MAX_FRAME}")
            got = {f: read_pts(p)}
        else:
            raise InputError(f"{p}: unsupported annotation type {p.suffix!r}; expected .pts or .csv")
        for f, P in got.items():
            if f in pts:
                raise InputError(f"{p}: frame {f} is also annotated in {src[f]}")
            pts[f], src[f] = P, p
    first = min(pts)
    for f, P in pts.items():
        if len(P) != len(pts[first]):
            raise InputError(f"{src[f]}: frame {f} has {len(P)} points but {src[first]} (frame {first}) has "
                             f"{len(pts[first])}")
    return dict(sorted(pts.items())), src
