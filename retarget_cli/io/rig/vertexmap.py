"""Landmark-to-vertex maps: which rig vertex each tracked landmark sits on.

A map is a text file (``--landmark-vertices``, or ``landmarks: file`` in
``rig.yaml``) or the ``landmarks:`` list of ``rig.yaml``. Errors name the
file and line (or the list index) and what was expected.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from ...errors import InputError

log = logging.getLogger(__name__)


def _map_rows(path: Path) -> tuple[list, list]:
    """The map's rows of integers (all of one width) and the 1-based line number of each."""
    if not path.is_file():
        raise InputError(f"{path}: landmark-vertex map not found")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not a UTF-8 text file ({exc.reason} at byte {exc.start})") from None
    rows, linenos = [], []
    for i, line in enumerate(text.splitlines(), 1):
        tok = line.split("#", 1)[0].replace(",", " ").split()
        if not tok:
            continue
        if len(tok) > 2 or not all(t.lstrip("-").isdigit() for t in tok):
            raise InputError(f"{path}:{i}: expected 'vertex' or 'landmark vertex' (integers), got {line.strip()!r}")
        if rows and len(tok) != len(rows[0]):
            raise InputError(f"{path}:{i}: has {len(tok)} numbers but line {linenos[0]} has {len(rows[0])}; "
                             "use one vertex id per landmark, or 'landmark vertex' pairs on every line")
        rows.append([int(t) for t in tok])
        linenos.append(i)
    if not rows:
        raise InputError(f"{path}: no vertex ids; expected one vertex id per landmark, or 'landmark vertex' pairs")
    return rows, linenos


def _check_ids(path: Path, lm: np.ndarray, vx: np.ndarray, linenos: list, pairs: bool, n_landmarks: int | None,
               n_vertices: int) -> None:
    """Each row's landmark id (pairs only) and vertex id must exist."""
    for k, (a, v) in enumerate(zip(lm.tolist(), vx.tolist())):
        if pairs and (a < 0 or (n_landmarks is not None and a >= n_landmarks)):
            top = f"0-{n_landmarks - 1}" if n_landmarks is not None else ">= 0"
            raise InputError(f"{path}:{linenos[k]}: landmark {a} does not exist (landmark ids {top})")
        if not 0 <= v < n_vertices:
            raise InputError(f"{path}:{linenos[k]}: vertex {v} is outside the mesh "
                             f"({n_vertices} vertices, ids 0-{n_vertices - 1})")


def _check_mapped_once(path: Path, lm: np.ndarray, linenos: list) -> None:
    first: dict[int, int] = {}
    for k, a in enumerate(lm.tolist()):
        if a in first:
            raise InputError(f"{path}:{linenos[k]}: landmark {a} is mapped twice (also on line {first[a]})")
        first[a] = linenos[k]


def _warn_shared_vertices(path: Path, vx: np.ndarray, linenos: list) -> None:
    seen: dict[int, int] = {}
    for k, v in enumerate(vx.tolist()):
        if v in seen:
            log.warning("%s:%d: vertex %d is also the vertex of line %d", path, linenos[k], v, seen[v])
        seen.setdefault(v, linenos[k])


def read_vertex_map(path: str | os.PathLike, n_landmarks: int | None, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Read a landmark-to-vertex map.

    One vertex id per line (line i = landmark i), or ``landmark vertex`` pairs
    (a subset); ``#`` starts a comment, commas count as spaces, blank lines
    are skipped.

    Parameters
    ----------
    path : path-like
    n_landmarks : int or None
        Landmarks per frame of the landmarks file; None skips the count and
        landmark-id checks (a map checked against the rig alone).
    n_vertices : int
        Vertices of the rig's neutral.

    Returns
    -------
    landmarks : ndarray of int64, shape (L,)
    vertices : ndarray of int64, shape (L,)

    Raises
    ------
    InputError
        ``file:line`` for a line that is not integers, a vertex id outside
        ``[0, n_vertices)``, a landmark id outside ``[0, n_landmarks)``, or a
        landmark mapped twice; the file and both counts when a one-column map
        lists another number of vertices than there are landmarks. A vertex
        given to two landmarks is only logged (a warning).
    """
    path = Path(path)
    rows, linenos = _map_rows(path)
    arr = np.array(rows, dtype=np.int64)
    pairs = arr.shape[1] == 2
    lm, vx = (arr[:, 0], arr[:, 1]) if pairs else (np.arange(len(arr)), arr[:, 0])
    if not pairs and n_landmarks is not None and len(arr) != n_landmarks:
        raise InputError(f"{path}: lists {len(arr)} vertices but the landmarks file has {n_landmarks} landmarks "
                         "(one line per landmark)")
    _check_ids(path, lm, vx, linenos, pairs, n_landmarks, n_vertices)
    if pairs:
        _check_mapped_once(path, lm, linenos)
    _warn_shared_vertices(path, vx, linenos)
    return lm, vx


def check_landmark_list(where: str, landmarks, n_vertices: int, neutral_name: str) -> np.ndarray:
    """Check ``rig.yaml``'s ``landmarks:`` list of vertex ids against the neutral.

    Returns
    -------
    ndarray of int64, shape (L,)

    Raises
    ------
    InputError
        ``rig.yaml: landmarks[12] = 30000 is not a vertex of the neutral n.obj
        (26719 vertices, ids 0-26718)``.
    """
    ids = np.asarray(landmarks, dtype=np.int64)
    bad = np.flatnonzero((ids < 0) | (ids >= n_vertices))
    if bad.size:
        i = int(bad[0])
        raise InputError(f"{where}: landmarks[{i}] = {int(ids[i])} is not a vertex of the neutral {neutral_name} "
                         f"({n_vertices} vertices, ids 0-{n_vertices - 1})")
    return ids


__all__ = ["check_landmark_list", "read_vertex_map"]
