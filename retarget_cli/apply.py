"""Retargeting: drive the artist's target key shapes with the source weights.

Chuang & Bregler (2002, eq. 2 and §5): the weights found in the source domain
are reused unchanged; only the key shapes are replaced, ``B_t = Σ_i w_i B_i``.
Regions (eyes, mouth, ...) are modelled separately and blended linearly.
"""

from __future__ import annotations

import numpy as np

from ._validate import check_array
from .errors import ShapeError


def blend_keys(weights, key_vertices) -> np.ndarray:
    """Retargeted vertex positions ``B_t = Σ_i w_{t,i} B_i`` (eq. 2 with eq. 3).

    Parameters
    ----------
    weights : ndarray, shape (T, K)
    key_vertices : ndarray, shape (K, N, 3)

    Returns
    -------
    ndarray, shape (T, N, 3)
    """
    W = check_array(weights, "weights", ndim=2)
    B = check_array(key_vertices, "key_vertices", ndim=3)
    if B.shape[0] != W.shape[1]:
        raise ShapeError(f"key_vertices: expected {W.shape[1]} key shapes (one per weight column), got {B.shape[0]}")
    return np.einsum("tk,knd->tnd", W, B, optimize=True)


def blend_regions(region_positions, masks, neutral) -> np.ndarray:
    """Blend per-region results with per-vertex masks normalised to sum to 1.

    ``V_t = Σ_r m_r ⊙ R_{r,t} + (1 - Σ_r m_r) ⊙ V_0`` where the masks are
    first scaled so that no vertex's total exceeds 1; vertices covered by no
    region keep the neutral pose (Chuang & Bregler 2002, §5).

    Parameters
    ----------
    region_positions : sequence of ndarray, each shape (T, N, 3)
    masks : sequence of ndarray, each shape (N,), values in [0, 1]
    neutral : ndarray, shape (N, 3)

    Returns
    -------
    ndarray, shape (T, N, 3)
    """
    V0 = check_array(neutral, "neutral", ndim=2)
    M = np.stack([check_array(m, "mask", ndim=1) for m in masks])
    if M.shape[1] != V0.shape[0]:
        raise ShapeError(f"mask: expected {V0.shape[0]} per-vertex values, got {M.shape[1]}")
    if np.any(M < 0):
        raise ShapeError("mask: weights must be >= 0")
    total = M.sum(0)
    M = M / np.maximum(total, 1.0)
    rest = 1.0 - M.sum(0)
    out = rest[None, :, None] * V0[None]
    for m, R in zip(M, region_positions):
        out = out + m[None, :, None] * R
    return out
