"""Input checks shared by the stage functions (scikit-learn's ``check_array`` habit)."""

from __future__ import annotations

import numpy as np

from .errors import ShapeError


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
