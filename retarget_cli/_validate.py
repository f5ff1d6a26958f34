"""Input checks shared by every layer: arrays (scikit-learn's ``check_array`` habit), names used in paths,
the closest valid name for an error message."""

from __future__ import annotations

import difflib
import re

import numpy as np

from .errors import InputError, ShapeError


def check_array(x, name: str, *, ndim: int, finite: bool = True, dtype=np.float64, min_rows: int = 1) -> np.ndarray:
    """Convert *x* to an array and check its rank and values.

    Parameters
    ----------
    x : array_like
    name : str
        Parameter name used in the error message.
    ndim : int
        Required number of dimensions.
    finite : bool
        Reject NaN and infinity.
    min_rows : int
        Minimum size of the first axis.

    Returns
    -------
    ndarray
        *x* as *dtype*.

    Raises
    ------
    ShapeError
        Naming the parameter, the shape expected and the shape received.
    """
    arr = np.asarray(x, dtype=dtype)
    if arr.ndim != ndim:
        raise ShapeError(f"{name}: expected a {ndim}-D array, got shape {arr.shape}")
    if arr.shape[0] < min_rows:
        raise ShapeError(f"{name}: expected at least {min_rows} rows, got shape {arr.shape}")
    if finite and not np.all(np.isfinite(arr)):
        where = np.argwhere(~np.isfinite(arr))[0]
        raise ShapeError(f"{name}: contains NaN or infinity (first at index {tuple(int(i) for i in where)})")
    return arr


#: Region and key names used in paths: letters, digits, ``_``, ``.``, ``-`` (no ``..``).
NAME_RE = re.compile(r"^[A-Za-z0-9_.-]+$")


def check_name(name, where: str) -> str:
    """*name* if it is safe as one path component (``[A-Za-z0-9_.-]+``, no ``..``), else an InputError."""
    if not isinstance(name, str) or not NAME_RE.match(name) or ".." in name:
        raise InputError(f"{where}: {name!r} is not a valid name; expected letters, digits, '_', '.' and '-' "
                         "(no '..', no '/')")
    return name


def closest(name: str, candidates) -> str | None:
    """The candidate most similar to *name*, or None when nothing is close."""
    hits = difflib.get_close_matches(name, list(candidates), n=1, cutoff=0.5)
    return hits[0] if hits else None
