"""Retargeting: drive the artist's target key shapes with the source weights.

Chuang & Bregler (2002, eq. 2 and §5): the weights found in the source domain
are reused unchanged; only the key shapes are replaced, ``B_t = Σ_i w_i B_i``.
Regions (eyes, mouth, ...) are modelled separately and blended linearly.
"""

from __future__ import annotations

import numpy as np

from .._validate import check_array
from ..errors import ShapeError
from .tracking.headpose import angles_rotation


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


def mesh_edges(faces, n_vertices: int) -> np.ndarray:
    """Unique undirected edges joining every pair of corners of each face.

    Quads and n-gons contribute their diagonals too, so that graph distances
    approximate surface distances better than along face boundaries alone.

    Parameters
    ----------
    faces : sequence of sequence of int
        0-based vertex ids per face (any polygon size); ``l`` elements may be
        included (their consecutive pairs join).
    n_vertices : int

    Returns
    -------
    ndarray, shape (E, 2), int64, each row sorted, rows sorted
    """
    pairs = []
    by_size: dict[int, list] = {}
    for f in faces:
        by_size.setdefault(len(f), []).append(f)
    for n, group in by_size.items():
        if n < 2:
            continue
        F = np.asarray(group, dtype=np.int64)
        i, j = np.triu_indices(n, 1)
        pairs.append(np.stack([F[:, i].ravel(), F[:, j].ravel()], 1))
    if not pairs:
        return np.zeros((0, 2), np.int64)
    E = np.sort(np.concatenate(pairs), axis=1)
    E = E[E[:, 0] != E[:, 1]]
    if E.size and (E.min() < 0 or E.max() >= n_vertices):
        raise ShapeError(f"faces: vertex ids must lie in [0, {n_vertices}), got {E.min()}..{E.max()}")
    return np.unique(E, axis=0)


def falloff_mask(mask, *, vertices, edges, width: float) -> np.ndarray:
    """Widen a region mask by a linear falloff of *width* model units along the mesh.

    .. math:: m'(v) = \\operatorname{clip}\\big(\\max_u\\, m(u) - d(u, v) / w,\\; 0,\\; 1\\big)

    where ``d`` is the geodesic distance along mesh edges (Dijkstra over
    :func:`mesh_edges`, lengths measured on *vertices*, the neutral mesh). For
    a 0/1 mask this is ``1 - d(v, mask) / w`` outside the mask, falling
    linearly to 0 at distance ``w``: the linear blend of the intermediate
    region in Chuang & Bregler (2002, §5). The result is Lipschitz:
    ``|m'(a) - m'(b)| <= d(a, b) / w``, so no vertex jumps at the mask
    boundary. Parts of the mesh not connected to the region (separate eyeball
    or teeth shells) receive nothing.

    Parameters
    ----------
    mask : ndarray, shape (N,), values in [0, 1]
    vertices : ndarray, shape (N, 3)
        Neutral mesh.
    edges : ndarray, shape (E, 2)
        From :func:`mesh_edges`.
    width : float
        Falloff width in model units; 0 returns *mask* unchanged.

    Returns
    -------
    ndarray, shape (N,), float64 in [0, 1], ``>= mask``
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    m = check_array(mask, "mask", ndim=1)
    V = check_array(vertices, "vertices", ndim=2)
    if V.shape != (m.shape[0], 3):
        raise ShapeError(f"vertices: expected shape ({m.shape[0]}, 3), got {V.shape}")
    if not width > 0:
        if width < 0:
            raise ShapeError(f"width: expected a falloff >= 0 in model units, got {width}")
        return m.copy()
    if np.any((m < 0) | (m > 1)):
        raise ShapeError("mask: weights must lie in [0, 1]")
    E = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    N = m.shape[0]
    src = np.flatnonzero(m > 0)
    if src.size == 0:
        return m.copy()
    length = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)
    # A virtual source joined to every masked vertex u at cost (1 - m(u)) w:
    # its distance D(v) = min_u (1 - m(u)) w + d(u, v), and m'(v) = 1 - D(v) / w.
    # A tiny offset keeps zero-cost edges (explicit zeros are not edges).
    eps = 1e-9 * width
    rows = np.concatenate([E[:, 0], E[:, 1], np.full(src.size, N)])
    cols = np.concatenate([E[:, 1], E[:, 0], src])
    vals = np.concatenate([length, length, (1.0 - m[src]) * width + eps])
    G = coo_matrix((np.maximum(vals, eps), (rows, cols)), shape=(N + 1, N + 1)).tocsr()
    D = dijkstra(G, directed=True, indices=N, limit=width * (1 + 1e-9) + eps)[:N] - eps
    return np.maximum(m, np.clip(1.0 - D / width, 0.0, 1.0))


def region_weights(masks, *, vertices=None, faces=None, falloff=None) -> np.ndarray:
    """Per-vertex blending weights of the regions plus the neutral ("rest").

    Each mask is first widened by its falloff (:func:`falloff_mask`); the
    masks are then scaled so that no vertex's total exceeds 1, and the rest
    ``1 - Σ_r m_r`` goes to the neutral, so every vertex's weights (regions
    and rest) sum to 1 (Chuang & Bregler 2002, §5).

    Parameters
    ----------
    masks : sequence of ndarray, each shape (N,), values in [0, 1]
    vertices : ndarray, shape (N, 3), optional
        Neutral mesh; needed when any falloff is > 0.
    faces : sequence of sequence of int, optional
        Needed when any falloff is > 0.
    falloff : sequence of float, optional
        Falloff width per region, model units (0 or None: none).

    Returns
    -------
    ndarray, shape (R + 1, N)
        Rows 0..R-1 the regions, row R the neutral; columns sum to 1.
    """
    M = np.stack([check_array(m, "mask", ndim=1) for m in masks])
    if np.any((M < 0) | (M > 1)):
        raise ShapeError("mask: weights must lie in [0, 1]")
    widths = [0.0 if w is None else float(w) for w in (falloff or [None] * len(M))]
    if len(widths) != len(M):
        raise ShapeError(f"falloff: expected {len(M)} widths (one per mask), got {len(widths)}")
    if any(w > 0 for w in widths):
        if vertices is None or faces is None:
            raise ShapeError("falloff needs the neutral mesh's vertices and faces")
        edges = mesh_edges(faces, M.shape[1])
        M = np.stack([falloff_mask(m, vertices=vertices, edges=edges, width=w) for m, w in zip(M, widths)])
    M = M / np.maximum(M.sum(0), 1.0)
    return np.concatenate([M, (1.0 - M.sum(0))[None]])


def head_rotation_transforms(angles, *, pivot, transforms=None, keep_roll: bool = True) -> np.ndarray:
    """3D transforms that turn the character's head as the actor's: the 3D head pose (issue 28) about *pivot*.

    The rotation ``R_t`` of ``angles[t]`` (:func:`~retarget_cli.methods.tracking.headpose.angles_rotation`, in
    camera axes: x right, y down, z away) is carried into the model's axes (y up, the face looking along
    +z towards the viewer: ``F R_t F``, ``F = diag(1, -1, -1)``) and applied about *pivot*,
    ``X' = P + F R_t F (X - P)``; 0 degrees is the character as modelled, facing the viewer. With
    *transforms* (the 2D head motion of :func:`head_motion_transforms`, whose roll is the image's), the
    rotation is applied first and *keep_roll* false leaves the 3D roll out (the 2D motion has it):
    ``X'' = A_t X' + b_t``.

    Parameters
    ----------
    angles : ndarray, shape (T, 3)
        ``yaw, pitch, roll`` in degrees (``landmarks.npz`` ``head_angles``).
    pivot : array_like, shape (3,)
        Model-space centre of the rotation.
    transforms : ndarray, shape (T, 3, 4), optional
    keep_roll : bool

    Returns
    -------
    ndarray, shape (T, 3, 4)
    """
    a = check_array(angles, "angles", ndim=2)
    if a.shape[1] != 3:
        raise ShapeError(f"angles: expected shape (T, 3), got {a.shape}")
    a = a.copy()
    if not keep_roll:
        a[:, 2] = 0.0
    F = np.diag([1.0, -1.0, -1.0])
    R = F @ angles_rotation(a) @ F
    P = np.asarray(pivot, dtype=np.float64).reshape(3)
    out = np.concatenate([R, (P - R @ P)[:, :, None]], axis=2)
    if transforms is None:
        return out
    A = check_array(transforms, "transforms", ndim=3)
    if A.shape != (len(a), 3, 4):
        raise ShapeError(f"transforms: expected shape ({len(a)}, 3, 4), got {A.shape}")
    M = A[:, :, :3] @ out[:, :, :3]
    t = np.einsum("tij,tj->ti", A[:, :, :3], out[:, :, 3]) + A[:, :, 3]
    return np.concatenate([M, t[:, :, None]], axis=2)


def head_motion_transforms(head, *, units_per_pixel: float, pivot, image_pivot, reference: int = 0) -> np.ndarray:
    """3D transforms that put the tracked 2D head motion on the character.

    The per-frame similarity ``head[t]`` (stabilized coordinates to image
    pixels) is taken relative to the reference frame,
    ``H_t = head[t] ∘ head[ref]^{-1}``, i.e. ``p ↦ s_t R(θ_t) p + b_t``.
    Chuang & Bregler (2002, §5) apply only "scaled 2D translation and
    rotation" to the output; here: roll about the view axis (model ``z``,
    the model is assumed y-up facing +z, the image is y-down, so the roll
    angle changes sign), uniform scale about *pivot*, and the image motion of
    *image_pivot* converted to model units:

    .. math:: X' = P + s_t R_z(-θ_t) (X - P) + k\\,F (H_t(c) - c),\\quad F = \\mathrm{diag}(1, -1, 0)

    With the projection ``π(X) = c + F (X - P)_{xy} / k`` this satisfies
    ``π(X') = H_t(π(X))``: the character moves on screen as the actor's head did.

    Parameters
    ----------
    head : ndarray, shape (T, 2, 3)
        ``landmarks.npz`` ``head``.
    units_per_pixel : float
        ``k``, model units per image pixel.
    pivot : array_like, shape (3,)
        ``P``, model-space centre of roll and scale.
    image_pivot : array_like, shape (2,)
        ``c``, the image point (reference-frame pixels) that *pivot* corresponds to.
    reference : int
        Frame whose head pose is the character's rest pose.

    Returns
    -------
    ndarray, shape (T, 3, 4)
        Affine ``[A | t]`` per frame: ``X' = A X + t``.
    """
    H = check_array(head, "head", ndim=3)
    if H.shape[1:] != (2, 3):
        raise ShapeError(f"head: expected shape (T, 2, 3), got {H.shape}")
    if not 0 <= reference < H.shape[0]:
        raise ShapeError(f"reference: frame {reference} is outside the take ({H.shape[0]} frames)")
    if not units_per_pixel > 0:
        raise ShapeError(f"units_per_pixel: expected > 0, got {units_per_pixel}")
    P = np.asarray(pivot, dtype=np.float64).reshape(3)
    c = np.asarray(image_pivot, dtype=np.float64).reshape(2)
    ref = H[reference]
    Rinv = np.linalg.inv(ref[:, :2])
    tinv = -Rinv @ ref[:, 2]
    L = np.einsum("tij,jk->tik", H[:, :, :2], Rinv)  # (T, 2, 2)
    b = np.einsum("tij,j->ti", H[:, :, :2], tinv) + H[:, :, 2]
    a = L[:, 0, 0] + 1j * L[:, 1, 0]  # s e^{iθ} of the relative similarity
    s, theta = np.abs(a), np.angle(a)
    moved = np.einsum("tij,j->ti", L, c) + b - c  # H_t(c) - c
    delta = units_per_pixel * np.stack([moved[:, 0], -moved[:, 1], np.zeros(len(H))], 1)
    cos, sin = np.cos(-theta), np.sin(-theta)
    A = np.zeros((len(H), 3, 3))
    A[:, 0, 0], A[:, 0, 1], A[:, 1, 0], A[:, 1, 1], A[:, 2, 2] = cos, -sin, sin, cos, 1.0
    A *= s[:, None, None]
    t = P[None] + delta - np.einsum("tij,j->ti", A, P)
    return np.concatenate([A, t[:, :, None]], axis=2)


def apply_transforms(transforms, positions) -> np.ndarray:
    """``X' = A_t X + t_t`` for every frame.

    Parameters
    ----------
    transforms : ndarray, shape (T, 3, 4)
    positions : ndarray, shape (T, N, 3)

    Returns
    -------
    ndarray, shape (T, N, 3)
    """
    A = check_array(transforms, "transforms", ndim=3)
    X = check_array(positions, "positions", ndim=3)
    if A.shape[0] != X.shape[0]:
        raise ShapeError(f"transforms: expected {X.shape[0]} frames, got {A.shape[0]}")
    return np.einsum("tij,tnj->tni", A[:, :, :3], X) + A[:, None, :, 3]


def morph_targets(key_sets, region_masks, base) -> np.ndarray:
    """Express the region blend as morph targets on *base* (for glTF).

    With region masks ``m_r`` (rows of :func:`region_weights` without the
    rest) the blended frame is

    .. math:: V = (1 - Σ_r m_r) V_0 + Σ_r m_r Σ_k w_{rk} B_{rk}
              = V_0 + Σ_r Σ_k w_{rk}\\, m_r (B_{rk} - V_0) + Σ_r (Σ_k w_{rk} - 1)\\, m_r V_0

    so each region contributes one target per key, ``m_r (B_rk − V_0)``, and
    one "rest" target ``m_r V_0`` weighted by ``Σ_k w_rk − 1`` (non-negative
    weights need not sum to 1). The result equals :func:`blend_regions` exactly.

    Parameters
    ----------
    key_sets : sequence of ndarray, each shape (K_r, N, 3)
    region_masks : ndarray, shape (R, N), or None for one region covering every vertex
    base : ndarray, shape (N, 3)
        ``V_0``: the neutral (or, with one region and no neutral, its first key).

    Returns
    -------
    ndarray, shape (Σ_r K_r + R, N, 3)
        Per region: its K_r key targets, then its rest target.
    """
    V0 = check_array(base, "base", ndim=2)
    sets = [check_array(B, "key_vertices", ndim=3) for B in key_sets]
    M = np.ones((1, V0.shape[0])) if region_masks is None else check_array(region_masks, "region_masks", ndim=2)
    if M.shape != (len(sets), V0.shape[0]):
        raise ShapeError(f"region_masks: expected shape ({len(sets)}, {V0.shape[0]}), got {M.shape}")
    out = []
    for B, m in zip(sets, M):
        if B.shape[1:] != V0.shape:
            raise ShapeError(f"key_vertices: expected shape (K, {V0.shape[0]}, 3), got {B.shape}")
        out.append(m[None, :, None] * (B - V0[None]))
        out.append((m[:, None] * V0)[None])
    return np.concatenate(out)


def morph_weights(weights) -> np.ndarray:
    """Morph weights matching :func:`morph_targets`: per region ``[w_r1..w_rK, Σ_k w_rk − 1]``.

    Parameters
    ----------
    weights : sequence of ndarray, each shape (T, K_r)

    Returns
    -------
    ndarray, shape (T, Σ_r K_r + R)
    """
    Ws = [check_array(W, "weights", ndim=2) for W in weights]
    return np.concatenate([np.concatenate([W, W.sum(1, keepdims=True) - 1.0], 1) for W in Ws], 1)
