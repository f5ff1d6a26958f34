"""Face measures on 2D point sets: mouth opening, eye opening, brow height.

Every measure is a ratio of distances between points of one frame, so it does not change with the
head's image position, in-plane rotation or scale, and the actor's values (from MediaPipe Face Mesh)
can be correlated over frames with the character's (from the rig's landmark vertices, projected
frontally) and with our tracker's (68-point Multi-PIE layout).

Points are image-like: x right, y down (for the character, ``x = X``, ``y = -Y`` of the y-up rig).
The gaps are signed: the lower point's offset from the upper one along the unit normal of the
corner-to-corner line (the normal pointing down the image when the corners run left to right), so
lips that cross give a negative opening instead of a positive distance.

Layouts name the point indices of each measure for one detector; "eye_l" is always the eye on the
image's left (the actor's right eye; for a character facing the camera, its right eye).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _as_frames(points) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim == 2:
        p = p[None]
    if p.ndim != 3 or p.shape[2] != 2:
        raise ValueError(f"points: expected shape (L, 2) or (T, L, 2), got {np.shape(points)}")
    return p


def signed_gap(points, upper, lower, corner_a: int, corner_b: int) -> np.ndarray:
    """Mean signed gap between paired upper and lower points, normal to the corner line.

    Parameters
    ----------
    points : array_like, shape (T, L, 2) or (L, 2)
    upper, lower : sequence of int, same length
        Paired point indices (upper lip/lid, lower lip/lid).
    corner_a, corner_b : int
        The corners, image-left first.

    Returns
    -------
    ndarray, shape (T,)
        Mean over pairs of ``(p[lower] - p[upper]) · n`` with ``n`` the unit normal of
        ``p[corner_b] - p[corner_a]`` rotated +90° (down the image for a left-to-right line).
    """
    p = _as_frames(points)
    if len(upper) != len(lower) or not len(upper):
        raise ValueError("upper, lower: expected the same non-zero number of indices")
    d = p[:, corner_b] - p[:, corner_a]
    n = np.stack([-d[:, 1], d[:, 0]], axis=1) / np.linalg.norm(d, axis=1, keepdims=True)
    diff = p[:, list(lower)] - p[:, list(upper)]
    return np.einsum("tkc,tc->tk", diff, n).mean(axis=1)


def distance(points, a: int, b: int) -> np.ndarray:
    """Distance between points *a* and *b* in every frame, shape (T,)."""
    p = _as_frames(points)
    return np.linalg.norm(p[:, a] - p[:, b], axis=1)


def opening(points, upper, lower, corner_a: int, corner_b: int) -> np.ndarray:
    """Opening of a mouth or an eye: signed gap / corner-to-corner width, shape (T,).

    See :func:`signed_gap`; the width is the distance between the two corners.
    """
    return signed_gap(points, upper, lower, corner_a, corner_b) / distance(points, corner_a, corner_b)


def brow_height(points, brow, corner_a: int, corner_b: int, iod_a: int, iod_b: int) -> np.ndarray:
    """Brow height: distance from the brow points' centroid to the eye-corner midpoint / inter-ocular distance.

    Parameters
    ----------
    points : array_like, shape (T, L, 2) or (L, 2)
    brow : sequence of int
        Points along one brow.
    corner_a, corner_b : int
        The two corners of the eye under that brow.
    iod_a, iod_b : int
        The outer corners of the two eyes.

    Returns
    -------
    ndarray, shape (T,)
    """
    p = _as_frames(points)
    c = p[:, list(brow)].mean(axis=1)
    mid = 0.5 * (p[:, corner_a] + p[:, corner_b])
    return np.linalg.norm(c - mid, axis=1) / distance(p, iod_a, iod_b)


@dataclass(frozen=True)
class Layout:
    """Point indices of each measure for one landmark scheme (see the module docstring)."""

    name: str
    n_points: int
    lip_upper: tuple
    lip_lower: tuple
    mouth_corners: tuple          # (image-left, image-right) outer corners
    eye_l: tuple                  # (upper tuple, lower tuple, corner image-left, corner image-right)
    eye_r: tuple
    brow_l: tuple
    brow_r: tuple


#: The 68-point Multi-PIE/iBUG layout (0-based): our tracker and the rig's landmark vertices.
#: Inner lips 61/67, 62/66, 63/65; outer mouth corners 48/54; eyes 37/41, 38/40 with corners
#: 36/39 (image-left) and 43/47, 44/46 with corners 42/45; brows 17-21 and 22-26.
MULTIPIE68 = Layout("multipie68", 68, (61, 62, 63), (67, 66, 65), (48, 54),
                    ((37, 38), (41, 40), 36, 39), ((43, 44), (47, 46), 42, 45),
                    (17, 18, 19, 20, 21), (22, 23, 24, 25, 26))

#: MediaPipe Face Mesh (478 points with refine_landmarks). Inner lips 81/178, 13/14, 311/402 (the
#: pairs of lipsUpperInner/lipsLowerInner nearest the 68-point inner-lip points); mouth corners
#: 61/291, the outer commissures (on d12 frame 0 within 2-3 px of the 68-point 48/54, while the inner
#: corners 78/308 sit a few pixels inside and are ill-defined on a closed mouth); image-left eye
#: upper 160/159/158, lower 144/145/153, corners 33 (outer) and 133, image-right eye 385/386/387,
#: 380/374/373, corners 362 and 263 (outer); brows 70, 63, 105, 66, 107 and 336, 296, 334, 293, 300.
MEDIAPIPE = Layout("mediapipe", 478, (81, 13, 311), (178, 14, 402), (61, 291),
                   ((160, 159, 158), (144, 145, 153), 33, 133), ((385, 386, 387), (380, 374, 373), 362, 263),
                   (70, 63, 105, 66, 107), (336, 296, 334, 293, 300))

MEASURES = ("mouth", "eye_l", "eye_r", "brow")


def face_measures(points, layout: Layout) -> dict:
    """Every measure of :data:`MEASURES` for points in *layout*.

    Parameters
    ----------
    points : array_like, shape (T, layout.n_points, 2) or (layout.n_points, 2)

    Returns
    -------
    dict
        ``mouth`` (inner-lip gap / outer mouth width), ``eye_l``, ``eye_r`` (lid gap / eye width),
        ``brow`` (the two brows' heights averaged); each shape (T,).
    """
    p = _as_frames(points)
    if p.shape[1] != layout.n_points:
        raise ValueError(f"points: expected {layout.n_points} points for layout {layout.name}, got {p.shape[1]}")
    L = layout
    iod = (L.eye_l[2], L.eye_r[3])
    return {
        "mouth": opening(p, L.lip_upper, L.lip_lower, *L.mouth_corners),
        "eye_l": opening(p, *L.eye_l),
        "eye_r": opening(p, *L.eye_r),
        "brow": 0.5 * (brow_height(p, L.brow_l, L.eye_l[2], L.eye_l[3], *iod)
                       + brow_height(p, L.brow_r, L.eye_r[2], L.eye_r[3], *iod)),
    }


def frontal(vertices) -> np.ndarray:
    """Frontal orthographic projection of y-up 3D points facing +z to image-like 2D (x right, y down).

    Parameters
    ----------
    vertices : array_like, shape (..., 3)

    Returns
    -------
    ndarray, shape (..., 2): ``(X, -Y)``.
    """
    v = np.asarray(vertices, dtype=np.float64)
    return np.stack([v[..., 0], -v[..., 1]], axis=-1)


def pearson(a, b, mask=None) -> float:
    """Pearson correlation of two series over the frames where both are finite (and *mask* holds).

    Returns NaN when fewer than 3 frames remain or either series is constant there.
    """
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    m = np.isfinite(a) & np.isfinite(b)
    if mask is not None:
        m &= np.asarray(mask, dtype=bool)
    if m.sum() < 3:
        return float("nan")
    x, y = a[m] - a[m].mean(), b[m] - b[m].mean()
    den = np.sqrt((x * x).sum() * (y * y).sum())
    return float((x * y).sum() / den) if den > 0 else float("nan")


__all__ = ["Layout", "MEASURES", "MEDIAPIPE", "MULTIPIE68", "brow_height", "distance", "face_measures", "frontal",
           "opening", "pearson", "signed_gap"]
