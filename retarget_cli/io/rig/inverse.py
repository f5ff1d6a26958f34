"""Files of the inverse rig: a ``rig.yaml`` with corrective shapes, mesh
sequences to fit, and the solved slider curves.

``rig.yaml`` (read by :func:`retarget_cli.io.stagefiles.read_rig`) may list
corrective shapes for pairs of sliders::

    neutral: target/neutral.obj
    shapes: {smile: target/shapes/smile.obj, jaw_open: target/shapes/jaw_open.obj}
    correctives:
      - {shapes: [smile, jaw_open], obj: target/correctives/smile_jaw_open.obj}

Like a shape, a corrective OBJ is a full mesh: the neutral with the
corrective's displacement added, so :math:`\\mathbf b^{\\{i,j\\}}` = corrective
OBJ − neutral, and the rig is eq. 4 of Racković et al. (2023):
``neutral + Σ w_e (shape_e − neutral) + Σ w_i w_j (corrective_ij − neutral)``.
With ``shapes_are: delta`` the shape and corrective OBJs hold the offsets
themselves (``neutral + Σ w_e shape_e + Σ w_i w_j corrective_ij``), as for
:class:`~retarget_cli.methods.rig.BlendshapeRig`.
"""

from __future__ import annotations

import glob
import json
import os
import re
from pathlib import Path

import numpy as np

from ... import __version__
from ...errors import InputError
from ...methods.inverse_rig import QuadraticRig
from ..atomic import load_npz, savez, write_text
from ..obj import read_obj
from .cache import check_vertex_counts, load_rig_meshes
from .spec import Rig, read_rig

_FRAME_NUM = re.compile(r"(\d+)")


def parse_correctives(rig: Rig) -> list[tuple[int, int, Path]]:
    """Check the raw ``correctives`` of a rig and resolve names and paths.

    Returns
    -------
    list of (i, j, path)
        Shape indices in ``rig.shapes`` order and the absolute OBJ path.

    Raises
    ------
    InputError
        Naming the rig file and the entry: not a list of ``{shapes: [a, b], obj: file}``,
        unknown shape, the same shape twice, or a pair listed twice.
    """
    raw = rig.correctives
    if raw is None:
        return []
    where = f"{rig.path}: correctives"
    if not isinstance(raw, list):
        raise InputError(f"{where}: expected a list of {{shapes: [a, b], obj: file.obj}}, got {type(raw).__name__}")
    index = {name: k for k, name in enumerate(rig.shapes)}
    seen: dict[tuple[int, int], int] = {}
    out = []
    for k, entry in enumerate(raw):
        if not isinstance(entry, dict) or set(entry) != {"shapes", "obj"}:
            got = sorted(entry) if isinstance(entry, dict) else type(entry).__name__
            raise InputError(f"{where}[{k}]: expected keys 'shapes' and 'obj', got {got}")
        pair, obj = entry["shapes"], entry["obj"]
        if not isinstance(pair, list) or len(pair) != 2 or not all(isinstance(s, str) for s in pair):
            raise InputError(f"{where}[{k}]: 'shapes' must name two shapes, e.g. [smile, jaw_open], got {pair!r}")
        if not isinstance(obj, str):
            raise InputError(f"{where}[{k}]: 'obj' must be an OBJ path, got {obj!r}")
        for s in pair:
            if s not in index:
                raise InputError(f"{where}[{k}]: unknown shape {s!r}; the rig's shapes are {', '.join(index)}")
        i, j = index[pair[0]], index[pair[1]]
        if i == j:
            raise InputError(f"{where}[{k}]: a corrective pairs two different shapes, got {pair[0]!r} twice")
        key = (min(i, j), max(i, j))
        if key in seen:
            raise InputError(f"{where}[{k}]: duplicate pair [{pair[0]}, {pair[1]}] (already correctives[{seen[key]}])")
        seen[key] = k
        out.append((i, j, rig.path.parent / obj))
    return out


def _quadratic_spec(path):
    """``rig.yaml`` checked for solve-rig: (spec, correctives, mesh entries, every file)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: rig file not found")
    spec = read_rig(path)
    if spec.source is not None:
        raise InputError(f"{path}: solve-rig reads a rig of OBJs (neutral:, shapes:, correctives:); a rig read from "
                         f"{spec.source.name} has no corrective shapes")
    if tuple(float(x) for x in spec.range) != (0.0, 1.0):
        raise InputError(f"{path}: solve-rig supports range [0, 1] (Racković et al. eq. 8), got {list(spec.range)}")
    if not spec.shapes:
        raise InputError(f"{path}: 'shapes' is empty")
    corr = parse_correctives(spec)
    entries = [("neutral", spec.neutral), *((f"shapes.{k}", p) for k, p in spec.shapes.items()),
               *((f"correctives[{k}]", p) for k, (_, _, p) in enumerate(corr))]
    for label, p in entries:
        if not Path(p).is_file():
            raise InputError(f"{p}: OBJ file not found (the {label} of {path})")
    return spec, corr, entries, [path, *(p for _, p in entries)]


def check_quadratic_rig(path: str | os.PathLike) -> tuple[list[Path], int]:
    """Check a solve-rig ``rig.yaml`` and its OBJs' vertex counts without parsing the OBJs.

    Returns
    -------
    files : list of Path
        Every file of the rig (as :func:`read_quadratic_rig` returns them).
    n_vertices : int

    Raises
    ------
    InputError
        As :func:`read_quadratic_rig`, for everything but the OBJs' contents;
        a mesh whose vertex count differs from the neutral's is named by its
        ``rig.yaml`` entry (``shapes.smile``, ``correctives[0]``).
    """

    _, _, entries, files = _quadratic_spec(path)
    return files, check_vertex_counts(path, entries)


def read_quadratic_rig(path: str | os.PathLike, *, cache_dir=None):
    """Read ``rig.yaml`` with its OBJs into a :class:`~retarget_cli.methods.inverse_rig.QuadraticRig`.

    Parameters
    ----------
    path : path-like
    cache_dir : path-like, optional
        Keep the parsed OBJs there (see :mod:`retarget_cli.io.rig.cache`).

    Returns
    -------
    rig : QuadraticRig
    files : list of Path
        Every file read (``rig.yaml``, neutral, shapes, correctives).

    Raises
    ------
    InputError
        Bad YAML, missing files, meshes of another vertex count or topology,
        a ``range`` other than [0, 1], or bad corrective entries
        (:func:`parse_correctives`).
    """

    spec, corr, entries, files = _quadratic_spec(path)
    _, V = load_rig_meshes(path, entries, cache_dir=cache_dir)
    V0, n = V[0], len(spec.shapes)
    # ``shapes_are: delta``: the shape and corrective OBJs hold the offsets themselves
    base = V0 if spec.shapes_are == "absolute" else 0.0
    rig = QuadraticRig(V0, V[1:n + 1] - base, [(i, j) for i, j, _ in corr],
                       V[n + 1:] - base if corr else None, names=list(spec.shapes))
    return rig, files


def _natural_key(p: Path):
    return [int(t) if t.isdigit() else t for t in _FRAME_NUM.split(p.name)]


def read_meshes(spec: str | os.PathLike, n_vertices: int) -> tuple[np.ndarray, list[str]]:
    """Read the meshes to fit.

    Parameters
    ----------
    spec : path-like or str
        An ``.npz`` with ``positions`` (T, N, 3); a directory holding
        ``frame_*.obj``; a glob pattern such as ``scans/*.obj``; or one OBJ.
        OBJ files are taken in natural order (``frame_2`` before ``frame_10``).
    n_vertices : int
        The rig's vertex count N; every mesh must have it.

    Returns
    -------
    positions : ndarray, shape (T, N, 3), float64
    sources : list of str
        File name of each frame (or ``name.npz[t]``).

    Raises
    ------
    InputError
        Nothing found, an unreadable file, or a vertex count other than N
        (naming the frame and file).
    """
    text = str(spec)
    p = Path(text)
    if p.is_file() and p.suffix.lower() == ".npz":
        data = load_npz(p)
        if "positions" not in data:
            raise InputError(f"{p}: expected an array 'positions' (T, N, 3); found {', '.join(sorted(data)) or 'none'}")
        X = np.asarray(data["positions"])
        if X.ndim != 3 or X.shape[2] != 3 or X.shape[0] < 1:
            raise InputError(f"{p}: 'positions' must have shape (T, N, 3), got {X.shape}")
        if X.shape[1] != n_vertices:
            raise InputError(f"{p}: 'positions' has {X.shape[1]} vertices per frame, the rig has {n_vertices}")
        X = X.astype(np.float64)
        if not np.all(np.isfinite(X)):
            t = int(np.argwhere(~np.isfinite(X))[0, 0])
            raise InputError(f"{p}: frame {t} of 'positions' is not finite")
        return X, [f"{p.name}[{t}]" for t in range(len(X))]
    if p.is_dir():
        files = sorted((f for f in p.glob("frame_*.obj") if f.is_file()), key=_natural_key)
        if not files:
            raise InputError(f"{p}: no frame_*.obj files in this directory")
    elif p.is_file():
        files = [p]
    else:
        files = sorted((Path(f) for f in glob.glob(text) if Path(f).is_file()), key=_natural_key)
        if not files:
            raise InputError(f"{text}: no such file, directory or matching OBJ files")
    X = np.empty((len(files), n_vertices, 3))
    for t, f in enumerate(files):
        mesh = read_obj(f)
        if mesh.n_vertices != n_vertices:
            raise InputError(f"{f}: frame {t} has {mesh.n_vertices} vertices, the rig has {n_vertices}")
        X[t] = mesh.vertices
    return X, [f.name for f in files]


def save_inverse_weights(path, result, names, sources, meta: dict) -> None:
    """Write the solved curves (deterministic NPZ).

    Members: ``curves`` (T, m) weights in [0, 1] and ``names`` (m,) (the
    layout ``pose-keys --poses`` reads), per-frame ``rmse``, ``cardinality``,
    ``objective``, ``iterations`` (T,), ``sources`` (T,) and ``meta`` (JSON).
    Wall times are not stored here (they would change the bytes on every run);
    see :func:`metrics_csv`.
    """
    savez(path, {
        "curves": np.asarray(result.weights, dtype=np.float64),
        "names": np.asarray(list(names), dtype=str),
        "rmse": np.asarray(result.rmse, dtype=np.float64),
        "cardinality": np.asarray(result.cardinality, dtype=np.int64),
        "objective": np.asarray(result.objective, dtype=np.float64),
        "iterations": np.asarray(result.iterations, dtype=np.int64),
        "sources": np.asarray(list(sources), dtype=str),
        "meta": np.array(json.dumps({"version": __version__, **meta}, sort_keys=True)),
    })


def metrics_csv(result, sources) -> str:
    """CSV text: ``frame,source,rmse,cardinality,objective,iterations,seconds``, one line per frame."""
    lines = ["frame,source,rmse,cardinality,objective,iterations,seconds"]
    for t, src in enumerate(sources):
        lines.append(f"{t},{src},{result.rmse[t]:.9g},{int(result.cardinality[t])},{result.objective[t]:.9g},"
                     f"{int(result.iterations[t])},{result.seconds[t]:.6f}")
    return "\n".join(lines) + "\n"


def write_metrics_csv(path, result, sources) -> None:
    """Atomically write :func:`metrics_csv`."""
    write_text(path, metrics_csv(result, sources))


__all__ = ["check_quadratic_rig", "metrics_csv", "parse_correctives", "read_meshes", "read_quadratic_rig", "save_inverse_weights",
           "write_metrics_csv"]
