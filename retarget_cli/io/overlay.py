"""Overlay video for checking a track by eye: landmarks coloured by confidence, head frame drawn."""

from __future__ import annotations

import os

import numpy as np

from .video import atomic_video_writer


def confidence_colour(c: float) -> tuple[int, int, int]:
    """BGR colour from red (confidence 0) through yellow to green (1)."""
    c = float(np.clip(c, 0, 1))
    return (0, int(255 * min(1.0, 2 * c)), int(255 * min(1.0, 2 * (1 - c))))


def draw_overlay(frame, points, confidence, head, *, axis: float = 40.0, origin=None) -> np.ndarray:
    """One overlay frame.

    Parameters
    ----------
    frame : ndarray, shape (H, W, 3), uint8
    points : ndarray, shape (L, 2)
    confidence : ndarray, shape (L,)
    head : ndarray, shape (2, 3)
        Similarity from stabilized coordinates to image pixels.
    axis : float
        Length of the head axes in stabilized pixels.
    origin : ndarray, shape (2,), optional
        Head-frame origin in stabilized coordinates (default the image of the
        mean of *points* under the inverse head).

    Returns
    -------
    ndarray, shape (H, W, 3), uint8
    """
    import cv2

    img = frame.copy()
    A, t = np.asarray(head[:, :2], float), np.asarray(head[:, 2], float)
    if origin is None:
        origin = np.linalg.solve(A, np.asarray(points, float).mean(0) - t)
    o = A @ origin + t
    for end, col in ((origin + [axis, 0], (0, 0, 255)), (origin + [0, axis], (255, 0, 0))):
        e = A @ end + t
        cv2.arrowedLine(img, tuple(int(round(v * 16)) for v in o), tuple(int(round(v * 16)) for v in e), col, 1,
                        cv2.LINE_AA, 4, 0.15)
    for (x, y), c in zip(points, confidence):
        if np.isfinite(x) and np.isfinite(y):
            cv2.circle(img, (int(round(x * 16)), int(round(y * 16))), 2 * 16, confidence_colour(c), -1, cv2.LINE_AA, 4)
    return img


def write_overlay(path: str | os.PathLike, frames, points, confidence, head, *, fps: float, frame_size,
                  progress=None) -> None:
    """Atomically write an overlay video (mp4v) of *frames* with the track drawn.

    Parameters
    ----------
    frames : iterable of ndarray (H, W, 3) uint8
        The tracked frames, in order (at least ``len(points)``; extra ones are ignored).
    points : ndarray, shape (T, L, 2)
    confidence : ndarray, shape (T, L)
    head : ndarray, shape (T, 2, 3)
    fps : float
    frame_size : (int, int)
    progress : callable, optional
        Called after each frame.
    """
    points = np.asarray(points, float)
    head = np.asarray(head, float)
    origin = points[0].mean(0)
    with atomic_video_writer(path, fps, frame_size) as writer:
        for t, frame in enumerate(frames):
            if t >= len(points):
                break
            writer.write(draw_overlay(frame, points[t], confidence[t], head[t], origin=origin))
            if progress is not None:
                progress(t)
