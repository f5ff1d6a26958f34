"""Comparison of a run with the ground truth of a synthetic take (``retarget synth``).

A synthetic take's ``truth.npz`` holds the target character's true animation
(``target``, (T, N, 3)) and ``truth_landmarks.npz`` the true landmarks. The
functions here measure a run's output against them the way
``bench/temporal.py`` does (issue #16): mesh error in % of the mean true
expression displacement, mesh jitter (mean vertex acceleration) as a ratio to
the truth's, and the same for the landmarks. They are pure (arrays in, numbers
out); :mod:`retarget_cli.see.report` shows them.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import InputError, ShapeError
from ..io.atomic import load_npz
from ..methods.decomposition import mean_acceleration


def load_truth_animation(path: str | os.PathLike) -> np.ndarray:
    """The true target animation ``target`` (T, N, 3) of a ``truth.npz``.

    Raises
    ------
    InputError
        When the file is not an npz with a ``target`` array of shape (T, N, 3).
    """

    path = Path(path)
    data = load_npz(path)
    if "target" not in data:
        raise InputError(f"{path}: no 'target' array (the true animation retarget synth writes in truth.npz)")
    target = np.asarray(data["target"])
    if target.ndim != 3 or target.shape[2] != 3 or len(target) < 1:
        raise InputError(f"{path}: 'target' has shape {target.shape}; expected (frames, vertices, 3)")
    target = target.astype(np.float64)
    bad = ~np.isfinite(target).all(axis=(1, 2))
    if bad.any():
        raise InputError(f"{path}: 'target' frame {int(np.flatnonzero(bad)[0])} is not finite (NaN or inf)")
    return target


def mesh_against_truth(got, truth) -> dict:
    """Mesh error and jitter of an animation against the true one.

    Parameters
    ----------
    got : ndarray, shape (T, N, 3)
        The run's meshes (``apply``'s frames, in the character's own frame).
    truth : ndarray, shape (T, N, 3)
        The true animation; its frame 0 is the neutral the displacement is measured from.

    Returns
    -------
    dict
        ``error_mean`` (mean vertex distance), ``error_pct`` (that, in % of the
        mean true displacement from frame 0; NaN when the truth does not move),
        ``error_per_frame`` (T,), ``jitter`` and ``jitter_truth`` (mean vertex
        acceleration, :func:`~retarget_cli.methods.decomposition.mean_acceleration`),
        ``jitter_ratio`` (NaN when the truth has none).
    """
    G = np.asarray(got, dtype=np.float64)
    X = np.asarray(truth, dtype=np.float64)
    if G.ndim != 3 or G.shape != X.shape:
        raise ShapeError(f"got: expected the truth's shape {X.shape}, got {G.shape}")
    per_frame = np.linalg.norm(G - X, axis=2).mean(axis=1)
    disp = float(np.linalg.norm(X - X[:1], axis=2).mean())
    jit, jit_truth = mean_acceleration(G), mean_acceleration(X)
    return {"error_mean": float(per_frame.mean()), "error_pct": 100 * float(per_frame.mean()) / disp if disp > 0
            else float("nan"), "error_per_frame": per_frame, "jitter": jit, "jitter_truth": jit_truth,
            "jitter_ratio": jit / jit_truth if jit_truth > 0 else float("nan")}


def points_against_truth(got, truth) -> dict:
    """Landmark error (px) and jitter ratio of a point track against the true one.

    Parameters
    ----------
    got, truth : ndarray, shape (T, L, 2)

    Returns
    -------
    dict
        ``error_px`` (mean point distance), ``jitter`` and ``jitter_truth`` (px/frame²), ``jitter_ratio``.
    """
    G = np.asarray(got, dtype=np.float64)
    X = np.asarray(truth, dtype=np.float64)
    if G.ndim != 3 or G.shape != X.shape:
        raise ShapeError(f"got: expected the truth's shape {X.shape}, got {G.shape}")
    ok = np.isfinite(G).all(axis=2)
    jit, jit_truth = mean_acceleration(np.where(ok[..., None], G, X)), mean_acceleration(X)
    return {"error_px": float(np.linalg.norm(G - X, axis=2)[ok].mean()) if ok.any() else float("nan"),
            "jitter": jit, "jitter_truth": jit_truth,
            "jitter_ratio": jit / jit_truth if jit_truth > 0 else float("nan")}
