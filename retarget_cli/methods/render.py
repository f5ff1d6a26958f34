"""A small vectorised software rasteriser (numpy + OpenCV): no GPU, no display.

Meshes are drawn with a z-buffer and Lambert shading, either flat (one
normal per face) or Gouraud (vertex normals interpolated as intensities).
Quads and n-gons are split into triangles by a fan from their first vertex.

How it stays fast in numpy: triangles are grouped by the size of their pixel
bounding box (powers of two in x and in y). Each group is tested against its
boxes' pixel grids in one broadcast (edge functions, with the top-left fill
rule so that triangles sharing an edge never both cover a pixel). Every
covered pixel becomes a fragment whose key packs its quantised depth above
its triangle id; ``np.minimum.at`` over the pixel index then resolves the
z-buffer in a single pass, and shading is computed only for the surviving
pixel of each covered pixel.

Conventions: model coordinates are the mesh's own (for ``retarget synth``
characters x to the subject's left, y up, z toward the viewer). The camera
orbits the mesh centre (``yaw`` about the model's y axis, then ``pitch``
about the camera's x axis) and by default looks along -z. Images are BGR
``uint8`` with pixel centres at integer coordinates (OpenCV's convention).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._validate import check_array
from ..errors import ParameterError, ShapeError

#: Largest number of pixel tests broadcast at once (bounds the temporary memory).
_CHUNK = 1 << 18
#: Depth is quantised to this many levels inside the scene's depth range.
_DEPTH_LEVELS = (1 << 31) - 1
_EMPTY = np.iinfo(np.int64).max


@dataclass(frozen=True)
class Camera:
    """An orbit camera around a mesh's centre.

    Parameters
    ----------
    yaw : float
        Degrees about the model's vertical (y) axis; positive turns the
        model's +x side toward the viewer.
    pitch : float
        Degrees about the camera's horizontal axis; positive looks down on
        the model.
    fov : float
        Vertical field of view in degrees for the perspective projection;
        ``0`` selects an orthographic projection.
    distance : float or None
        Camera distance from the mesh centre in units of the mesh's bounding
        radius (perspective only). ``None`` places the camera so that the
        bounding sphere fills *fill* of the image at this *fov*.
    fill : float
        Fraction of the image's smaller side covered by the bounding sphere
        (the zoom), in (0, 2].
    """

    yaw: float = 0.0
    pitch: float = 0.0
    fov: float = 30.0
    distance: float | None = None
    fill: float = 0.9

    def __post_init__(self):
        if not 0 <= self.fov < 170:
            raise ParameterError(f"camera fov: expected 0 (orthographic) or a value in (0, 170) degrees, got {self.fov}")
        if self.distance is not None and not self.distance > 1.0:
            raise ParameterError(f"camera distance: expected > 1 bounding radius (or None), got {self.distance}")
        if not 0 < self.fill <= 2:
            raise ParameterError(f"camera fill: expected a value in (0, 2], got {self.fill}")


def _rotation(yaw: float, pitch: float) -> np.ndarray:
    a, b = np.radians(yaw), np.radians(pitch)
    ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    return rx @ ry


def triangulate(faces) -> np.ndarray:
    """Split polygons into triangles by a fan from each polygon's first vertex.

    Parameters
    ----------
    faces : ndarray (F, n) of int, or list of lists of int
        0-based vertex ids; lists may mix triangles, quads and n-gons.
        Polygons with fewer than 3 vertices are dropped.

    Returns
    -------
    ndarray, shape (M, 3), int64
        Triangles grouped by polygon size (triangles first), then in face
        order; polygon ``[a, b, c, d]`` gives
        ``[a, b, c]`` and ``[a, c, d]``.
    """
    if isinstance(faces, np.ndarray):
        if faces.ndim != 2:
            raise ShapeError(f"faces: expected shape (F, n), got {faces.shape}")
        groups = {faces.shape[1]: faces.astype(np.int64)}
    else:
        by_len: dict[int, list] = {}
        for f in faces:
            by_len.setdefault(len(f), []).append(f)
        groups = {n: np.asarray(fs, dtype=np.int64) for n, fs in by_len.items()}
    tris = []
    for n, arr in sorted(groups.items()):
        if n < 3 or arr.size == 0:
            continue
        for j in range(1, n - 1):
            tris.append(np.stack([arr[:, 0], arr[:, j], arr[:, j + 1]], 1))
    if not tris:
        return np.zeros((0, 3), np.int64)
    return np.concatenate(tris, 0)


def face_normals(vertices: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Unit normals of triangles (right-handed: counter-clockwise faces point at you).

    Parameters
    ----------
    vertices : ndarray, shape (N, 3)
    tris : ndarray, shape (M, 3), int

    Returns
    -------
    ndarray, shape (M, 3)
        Zero for degenerate triangles.
    """
    v = vertices[tris]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def vertex_normals(vertices: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals.

    Parameters
    ----------
    vertices : ndarray, shape (N, 3)
    tris : ndarray, shape (M, 3), int

    Returns
    -------
    ndarray, shape (N, 3)
        Zero for vertices used by no (non-degenerate) triangle.
    """
    v = vertices[tris]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])  # length = 2 * area
    out = np.zeros((len(vertices), 3))
    for k in range(3):
        out[:, k] = np.bincount(tris.ravel(), weights=np.repeat(n[:, k], 3), minlength=len(vertices))
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return np.divide(out, norm, out=np.zeros_like(out), where=norm > 0)


def rasterize(xy: np.ndarray, depth: np.ndarray, tris: np.ndarray, size: tuple[int, int]):
    """Z-buffered coverage of screen-space triangles.

    A pixel (centre at integer coordinates) belongs to a triangle when it is
    inside it or on a top or left edge (the top-left fill rule of Direct3D
    and OpenGL), so a mesh covers each pixel once. Of the triangles covering
    a pixel the one with the smallest interpolated *depth* wins; ties go to
    the lower triangle id.

    Parameters
    ----------
    xy : ndarray, shape (N, 2)
        Vertex positions in pixels (x right, y down).
    depth : ndarray, shape (N,)
        A per-vertex depth that is linear in screen space (smaller is
        nearer). Triangles with a non-finite depth or position are dropped
        (e.g. vertices behind a perspective camera).
    tris : ndarray, shape (M, 3), int
    size : (width, height)

    Returns
    -------
    tri_id : ndarray, shape (H, W), int32
        Winning triangle per pixel, ``-1`` where nothing is drawn.
    bary : ndarray, shape (H, W, 3), float32
        Barycentric coordinates of the pixel centre in its triangle (zeros on
        the background).
    """
    xy = check_array(xy, "xy", ndim=2, finite=False)
    if xy.shape[1] != 2:
        raise ShapeError(f"xy: expected shape (N, 2), got {xy.shape}")
    depth = np.asarray(depth, dtype=np.float64)
    if depth.shape != (len(xy),):
        raise ShapeError(f"depth: expected shape ({len(xy)},), got {depth.shape}")
    tris = np.asarray(tris, dtype=np.int64)
    if tris.size == 0:
        tris = tris.reshape(0, 3)
    if tris.ndim != 2 or tris.shape[1] != 3:
        raise ShapeError(f"tris: expected shape (M, 3) (see triangulate for polygons), got {tris.shape}")
    if tris.size and (tris.min() < 0 or tris.max() >= len(xy)):
        raise ShapeError(f"tris: vertex ids must lie in [0, {len(xy)}), got [{tris.min()}, {tris.max()}]")
    W, H = (int(s) for s in size)
    pix, tid, bc = _raster(xy, depth, tris, W, H)
    tri_id = np.full(W * H, -1, dtype=np.int32)
    bary = np.zeros((W * H, 3), dtype=np.float32)
    tri_id[pix] = tid
    bary[pix] = bc
    return tri_id.reshape(H, W), bary.reshape(H, W, 3)


def _raster(xy, depth, tris, W, H, first=None):
    """Covered pixels only: flat pixel indices (n,), winning triangle ids (n,), barycentrics (n, 3).

    *first* (bool (M,), optional) names triangles likely to be visible (those
    that won a pixel in the previous frame of a sequence): they are drawn
    first, and of the others only those not provably behind the drawn
    surface at every pixel of their box (:func:`_hidden`) are drawn after
    them. The z-buffer keeps the minimum over all fragments, and a skipped
    triangle has no fragment that could be that minimum, so the result is
    the same as drawing every triangle (only faster when most of a mesh is
    hidden: the back of a head, eyeballs, teeth and mouth shells).
    """
    coef = _setup(xy, depth, tris, W, H)
    if coef is None:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3))
    keys = np.full(W * H, _EMPTY, dtype=np.int64)
    if first is None:
        _scan(coef, keys, W)
    else:
        pri = first[coef["ids"]]
        _scan(coef, keys, W, np.flatnonzero(pri))
        rest = np.flatnonzero(~pri)
        if len(rest):
            _scan(coef, keys, W, rest[~_hidden(coef, keys, W, rest)])
    pix = np.flatnonzero(keys != _EMPTY)
    local = keys[pix] & 0xFFFFFFFF
    px, py = (pix % W).astype(np.float64), (pix // W).astype(np.float64)
    e = np.empty((len(pix), 3))
    for k in range(3):
        e[:, k] = (coef["A"][k][local] * px + coef["C"][k][local]) + coef["B"][k][local] * py
    e /= e.sum(1, keepdims=True)
    return pix, coef["ids"][local], e


def _setup(xy, depth, tris, W, H):
    """Per-triangle edge functions, depth planes and clipped pixel boxes (culled triangles removed).

    Per-edge arrays are edge-major, shape (3, M): edge ``i`` is opposite
    vertex ``i`` (from vertex ``i+1`` to vertex ``i+2``), and its edge function
    divided by their sum is the barycentric weight of vertex ``i``.
    """
    x, y = np.ascontiguousarray(xy[:, 0]), np.ascontiguousarray(xy[:, 1])
    t0, t1, t2 = (np.ascontiguousarray(tris[:, k]) for k in range(3))
    X = [x[t0], x[t1], x[t2]]
    Y = [y[t0], y[t1], y[t2]]
    Z = [depth[t0], depth[t1], depth[t2]]
    xmin, xmax = np.minimum(np.minimum(X[0], X[1]), X[2]), np.maximum(np.maximum(X[0], X[1]), X[2])
    ymin, ymax = np.minimum(np.minimum(Y[0], Y[1]), Y[2]), np.maximum(np.maximum(Y[0], Y[1]), Y[2])
    # E_i(x, y) = A_i x + B_i y + C_i = cross(b - a, p - a) for the edge a -> b opposite vertex i
    A = np.stack([Y[1] - Y[2], Y[2] - Y[0], Y[0] - Y[1]])
    B = np.stack([X[2] - X[1], X[0] - X[2], X[1] - X[0]])
    C = np.stack([X[1] * Y[2] - Y[1] * X[2], X[2] * Y[0] - Y[2] * X[0], X[0] * Y[1] - Y[0] * X[1]])
    area2 = C[0] + C[1] + C[2]  # twice the signed area: sum of the E_i at any point (A, B sum to 0)
    with np.errstate(invalid="ignore"):
        x0 = np.ceil(np.maximum(xmin, 0))
        x1 = np.floor(np.minimum(xmax, W - 1))
        y0 = np.ceil(np.maximum(ymin, 0))
        y1 = np.floor(np.minimum(ymax, H - 1))
        keep = (x1 >= x0) & (y1 >= y0) & (area2 != 0) & np.isfinite(Z[0] + Z[1] + Z[2])
    idx = np.flatnonzero(keep)
    if not len(idx):
        return None
    sign = np.sign(area2[idx])
    A, B, C = A[:, idx] * sign, B[:, idx] * sign, C[:, idx] * sign
    tot = area2[idx] * sign
    # Top-left rule: a pixel exactly on an edge counts only for a top edge
    # (horizontal, interior below: E grows with y) or a left edge (interior
    # to its right: E grows with x). Two triangles sharing an edge get exactly
    # negated edge functions, so the rule gives every pixel to exactly one.
    topleft = (A > 0) | ((A == 0) & (B > 0))
    # "E > 0, or E == 0 on a top-left edge" as one comparison: for floats,
    # E >= 0 exactly when E > -(smallest subnormal).
    thr = np.where(topleft, -np.nextafter(0.0, 1.0), 0.0)
    z = np.stack([Z[0][idx], Z[1][idx], Z[2][idx]])
    # depth plane z(x, y) = za x + zb y + zc (barycentric interpolation of the vertex depths)
    za, zb, zc = ((M * z).sum(0) / tot for M in (A, B, C))
    clipped = (xmin[idx] < 0) | (ymin[idx] < 0) | (xmax[idx] > W - 1) | (ymax[idx] > H - 1)
    return {"ids": idx, "A": A, "B": B, "C": C, "thr": thr, "clipped": clipped,
            "x0": x0[idx].astype(np.int64), "y0": y0[idx].astype(np.int64),
            "x1": x1[idx].astype(np.int64), "y1": y1[idx].astype(np.int64),
            "za": za, "zb": zb, "zc": zc, "zmin": float(z.min()), "zmax": float(z.max())}


#: Box sides triangles are padded to: exact for small boxes (most triangles of
#: a dense mesh), then steps of at most 1.5x, so padding wastes little work.
_SIDES = np.unique([1, 2, 3, 4, 5, 6, 8, 10, 12, 16, 20, 24, 32]
                   + [48 * 2 ** i for i in range(12)] + [64 * 2 ** i for i in range(12)])


def _bucket(n: np.ndarray) -> np.ndarray:
    """Smallest padded side (see ``_SIDES``) >= n (n >= 1)."""
    return _SIDES[np.searchsorted(_SIDES, np.maximum(n, 1))]


def _depth_scale(c: dict) -> tuple[float, float]:
    """(zlo, scale) of the depth quantisation ``q = (z − zlo)·scale`` shared by every fragment of a frame."""
    zlo, zspan = c["zmin"], c["zmax"] - c["zmin"]
    return zlo, ((_DEPTH_LEVELS - 1) / zspan if zspan > 0 else 0.0)


def _hidden(c: dict, keys: np.ndarray, W: int, rows: np.ndarray) -> np.ndarray:
    """For the triangles *rows* (local ids): True where no fragment can beat *keys* anywhere in the box.

    A conservative test: the largest quantised depth already in the box
    (from a max pyramid of the z-buffer, over at most 2×2 tiles covering the
    box) against a lower bound of the triangle's fragment depths (the depth
    plane's minimum over the box corners, less a bound on the rounding of
    its evaluation at a pixel). Strictly nearer everywhere means every
    fragment's key is larger than the one in place, whatever the ids.
    Empty pixels hold the largest key, so a box that reaches one is never hidden.
    """
    H = len(keys) // W
    zlo, scale = _depth_scale(c)
    q = (keys >> 32).astype(np.int32).reshape(H, W)  # (quantised depths fit: _DEPTH_LEVELS = 2**31 - 1)
    levels = [q]
    while levels[-1].shape != (1, 1):
        a = levels[-1]
        h, w = a.shape
        if h % 2 or w % 2:
            a = np.pad(a, ((0, h % 2), (0, w % 2)), constant_values=_DEPTH_LEVELS)
        levels.append(np.maximum(np.maximum(a[0::2, 0::2], a[0::2, 1::2]), np.maximum(a[1::2, 0::2], a[1::2, 1::2])))
    x0, x1, y0, y1 = (c[k][rows] for k in ("x0", "x1", "y0", "y1"))
    # the level whose tiles are at least half the box's side: the box spans at most 3 x 3 of them
    side = np.maximum(x1 - x0, y1 - y0) + 1
    lev = np.clip(np.ceil(np.log2(np.maximum(side, 2) / 2)).astype(np.int64), 0, len(levels) - 1)
    top = np.empty(len(rows), dtype=np.int64)
    for k in np.unique(lev).tolist():
        i = np.flatnonzero(lev == k)
        a = levels[k]
        tx0, tx1 = x0[i] >> k, x1[i] >> k
        ty0, ty1 = y0[i] >> k, y1[i] >> k
        m = a[ty0, tx0]
        for dy in range(3):
            ty = np.minimum(ty0 + dy, ty1)
            for dx in range(3):
                m = np.maximum(m, a[ty, np.minimum(tx0 + dx, tx1)])
        top[i] = m
    za, zb, zc = c["za"][rows], c["zb"][rows], c["zc"][rows]
    fx0, fx1, fy0, fy1 = (v.astype(np.float64) for v in (x0, x1, y0, y1))
    with np.errstate(invalid="ignore", over="ignore"):
        low = np.minimum(za * fx0, za * fx1) + np.minimum(zb * fy0, zb * fy1) + zc
        # |error| of za·x + zb·y + zc at a pixel, and of this bound, is below 3u(|za x| + |zb y| + |zc|)
        low -= 8 * np.finfo(np.float64).eps * (np.abs(za) * np.maximum(fx0, fx1) + np.abs(zb) * np.maximum(fy0, fy1)
                                                + np.abs(zc))
        ok = np.isfinite(low)
        qlo = np.clip((np.where(ok, low, zlo) - zlo) * scale, 0, _DEPTH_LEVELS - 1).astype(np.int64)
    return ok & (top < qlo)


def _scan(c: dict, keys: np.ndarray, W: int, rows: np.ndarray | None = None) -> None:
    """Test the box pixels of the triangles *rows* (local ids; default all); fold fragments into *keys*.

    A key is ``quantised depth << 32 | local id``: the smallest wins.
    """
    rows = np.arange(len(c["ids"])) if rows is None else np.asarray(rows, dtype=np.int64)
    if not len(rows):
        return
    bw = _bucket(c["x1"][rows] - c["x0"][rows] + 1)
    bh = _bucket(c["y1"][rows] - c["y0"][rows] + 1)
    group = bw * (1 << 20) + bh
    o = np.argsort(group, kind="stable")
    order, bw, bh = rows[o], bw[o], bh[o]
    starts = np.flatnonzero(np.r_[True, np.diff(group[o]) != 0])
    ends = np.r_[starts[1:], len(order)]
    zlo, scale = _depth_scale(c)
    H = len(keys) // W
    for s, e in zip(starts, ends):
        sel_all = order[s:e]
        gw, gh = int(bw[s]), int(bh[s])
        step = max(1, _CHUNK // (gw * gh))
        ox = np.arange(gw, dtype=np.float64)
        oy = np.arange(gh, dtype=np.float64)
        for i in range(0, len(sel_all), step):
            sel = sel_all[i:i + step]
            x0, y0 = c["x0"][sel], c["y0"][sel]
            px = x0[:, None, None] + ox[None, None, :]  # (n, 1, gw)
            py = y0[:, None, None] + oy[None, :, None]  # (n, gh, 1)
            # Pixels of the padded box beyond the triangle's own box fail an edge test anyway;
            # only pixels past the image border (boxes were clipped to it) are dropped below.
            inside = None
            for k in range(3):
                # (A x + C) + B y: evaluated identically (up to sign) for both triangles of a
                # shared edge, so the fill rule below is exact
                ev = (c["A"][k, sel][:, None, None] * px + c["C"][k, sel][:, None, None]) \
                    + c["B"][k, sel][:, None, None] * py
                test = ev > c["thr"][k, sel][:, None, None]
                if inside is None:
                    inside = test
                else:
                    inside &= test
            t, yy, xx = np.nonzero(inside)
            if not len(t):
                continue
            fx = x0[t] + xx
            fy = y0[t] + yy
            if c["clipped"][sel].any():
                ok = (fx < W) & (fy < H)
                t, fx, fy = t[ok], fx[ok], fy[ok]
            tri = sel[t]
            z = c["za"][tri] * fx + c["zb"][tri] * fy + c["zc"][tri]
            q = np.clip((z - zlo) * scale, 0, _DEPTH_LEVELS - 1).astype(np.int64)
            np.minimum.at(keys, fy * W + fx, (q << 32) | tri)


# --------------------------------------------------------------------------- projection and shading


@dataclass
class View:
    """A camera fixed to a reference mesh (so a sequence keeps one framing).

    Attributes
    ----------
    rotation : ndarray (3, 3)
        Model to camera rotation (camera looks along -z, y up).
    centre : ndarray (3,)
        Orbit centre in model units.
    radius : float
        Bounding radius of the reference mesh (largest distance of a vertex
        from the centre of its bounding box).
    size : (width, height)
    camera : Camera
    """

    rotation: np.ndarray
    centre: np.ndarray
    radius: float
    size: tuple
    camera: Camera

    @classmethod
    def fit(cls, vertices: np.ndarray, camera: Camera = Camera(), size=(512, 512)) -> View:
        """Frame *vertices* (N, 3) with *camera* in an image of *size* (width, height)."""
        vertices = check_array(vertices, "vertices", ndim=2)
        if vertices.shape[1] != 3 or not len(vertices):
            raise ShapeError(f"vertices: expected shape (N, 3) with N > 0, got {vertices.shape}")
        W, H = (int(s) for s in size)
        if W < 1 or H < 1:
            raise ParameterError(f"size: expected positive width and height, got {size}")
        lo, hi = vertices.min(0), vertices.max(0)
        centre = (lo + hi) / 2
        radius = float(np.sqrt(((vertices - centre) ** 2).sum(1).max())) or 1.0
        return cls(_rotation(camera.yaw, camera.pitch), centre, radius, (W, H), camera)

    def project(self, vertices: np.ndarray):
        """Camera-space positions, pixel positions and a screen-linear depth.

        Parameters
        ----------
        vertices : ndarray, shape (N, 3)

        Returns
        -------
        cam : ndarray (N, 3)
            Camera-space positions (camera at the origin looking along -z) in
            model units.
        xy : ndarray (N, 2)
            Pixels, x right and y down.
        depth : ndarray (N,)
            Orthographic: distance along the view axis. Perspective:
            ``-1 / distance``, which is linear in screen space. Points behind
            the near plane are ``nan``.
        """
        W, H = self.size
        cam = (np.asarray(vertices, dtype=np.float64) - self.centre) @ self.rotation.T
        half = self.camera.fill * min(W, H) / 2
        if self.camera.fov == 0:
            dist = 3.0 * self.radius
            cam[:, 2] -= dist
            s = half / self.radius
            xy = np.stack([W / 2 - 0.5 + s * cam[:, 0], H / 2 - 0.5 - s * cam[:, 1]], 1)
            depth = -cam[:, 2]
        else:
            t = np.tan(np.radians(self.camera.fov) / 2)
            dist = (self.camera.distance * self.radius if self.camera.distance
                    else self.radius / np.sin(np.radians(self.camera.fov) / 2) / self.camera.fill)
            cam[:, 2] -= dist
            f = (H / 2) / t
            zc = -cam[:, 2]
            near = 1e-3 * self.radius
            with np.errstate(divide="ignore", invalid="ignore"):
                inv = np.where(zc > near, 1.0 / zc, np.nan)
            xy = np.stack([W / 2 - 0.5 + f * cam[:, 0] * inv, H / 2 - 0.5 - f * cam[:, 1] * inv], 1)
            depth = -inv
        return cam, xy, depth


@dataclass(frozen=True)
class Light:
    """A directional light fixed to the camera plus ambient light (Lambert).

    Parameters
    ----------
    direction : (3,)
        Direction toward the light in camera space (x right, y up, z toward
        the viewer).
    ambient, diffuse : float
        Intensity = ambient + diffuse * max(0, n . l) (two-sided: normals are
        turned toward the viewer first).
    """

    direction: tuple = (-0.35, 0.45, 1.0)
    ambient: float = 0.22
    diffuse: float = 0.78


def shade_intensity(normals: np.ndarray, view_dirs: np.ndarray, light: Light) -> np.ndarray:
    """Lambert intensity for camera-space *normals* (n, 3), turned toward *view_dirs* (n, 3) or (3,)."""
    ldir = np.asarray(light.direction, dtype=np.float64)
    ldir = ldir / np.linalg.norm(ldir)
    facing = np.sign(np.einsum("ij,ij->i", normals, np.broadcast_to(view_dirs, normals.shape)))
    facing[facing == 0] = 1
    n = normals * facing[:, None]
    return light.ambient + light.diffuse * np.clip(n @ ldir, 0, None)


class MeshRenderer:
    """Renders poses of one mesh topology with a fixed camera.

    Parameters
    ----------
    faces : ndarray (F, n) or list of lists of int
        Polygons (0-based vertex ids); split into triangles once.
    reference : ndarray, shape (N, 3)
        The pose the camera is framed on (e.g. the neutral or first frame).
    camera : Camera
    size : (width, height)
    shading : {"gouraud", "flat"}
    color : (3,) BGR in [0, 255]
        Surface colour at full intensity.
    background : (3,) BGR
    light : Light
    frame : ndarray (K, 3), optional
        Points the camera is framed on instead of *reference* (a face inside
        a whole-body mesh: its centre and bounding radius place the camera).
    """

    def __init__(self, faces, reference, *, camera: Camera = Camera(), size=(512, 512), shading: str = "gouraud",
                 color=(150, 170, 215), background=(40, 36, 32), light: Light = Light(), frame=None):
        if shading not in ("gouraud", "flat"):
            raise ParameterError(f"shading: expected 'gouraud' or 'flat', got {shading!r}")
        self.tris = triangulate(faces)
        reference = check_array(reference, "reference", ndim=2)
        if self.tris.size and self.tris.max() >= len(reference):
            raise ShapeError(f"faces use vertex {int(self.tris.max())} but the mesh has {len(reference)} vertices")
        self.n_vertices = len(reference)
        self.view = View.fit(reference if frame is None else frame, camera, size)
        self.shading = shading
        self.color = np.asarray(color, dtype=np.float64)
        self.background = np.asarray(background, dtype=np.uint8)
        self.light = light
        self._visible = None  # triangles that won a pixel in the last frame rendered

    @property
    def size(self) -> tuple:
        return self.view.size

    def render(self, vertices: np.ndarray, vertex_colors: np.ndarray | None = None) -> np.ndarray:
        """Render one pose.

        Parameters
        ----------
        vertices : ndarray, shape (N, 3)
            Positions in the reference's vertex order.
        vertex_colors : ndarray (N, 3) BGR, optional
            Per-vertex surface colours (interpolated) instead of *color*.

        Returns
        -------
        ndarray, shape (H, W, 3), uint8 (BGR)
        """
        vertices = check_array(vertices, "vertices", ndim=2)
        if vertices.shape != (self.n_vertices, 3):
            raise ShapeError(f"vertices: expected shape ({self.n_vertices}, 3), got {vertices.shape}")
        W, H = self.size
        cam, xy, depth = self.view.project(vertices)
        # the last frame's visible triangles first: the rest is mostly provably hidden (same picture)
        pix, tid, bc = _raster(xy, depth, self.tris, W, H, first=self._visible)
        self._visible = np.zeros(len(self.tris), dtype=bool)
        self._visible[tid] = True
        img = np.empty((H * W, 3), dtype=np.uint8)
        img[:] = self.background
        if not len(pix):
            return img.reshape(H, W, 3)
        vt = self.tris[tid]
        ortho = self.view.camera.fov == 0
        if self.shading == "flat":
            fn = face_normals(cam, self.tris)
            view = np.array([0.0, 0.0, 1.0]) if ortho else -cam[self.tris].mean(1)
            inten = shade_intensity(fn, view, self.light)[tid]
        else:
            vn = vertex_normals(cam, self.tris)
            view = np.array([0.0, 0.0, 1.0]) if ortho else -cam
            vi = shade_intensity(vn, view, self.light)[vt]
            inten = vi[:, 0] * bc[:, 0] + vi[:, 1] * bc[:, 1] + vi[:, 2] * bc[:, 2]
        if vertex_colors is not None:
            vc = np.asarray(vertex_colors, dtype=np.float64)
            if vc.shape != (self.n_vertices, 3):
                raise ShapeError(f"vertex_colors: expected shape ({self.n_vertices}, 3), got {vc.shape}")
            col = np.einsum("ij,ijk->ik", bc, vc[vt]) * inten[:, None]
        else:
            col = inten[:, None] * self.color[None]
        img[pix] = np.clip(col, 0, 255).astype(np.uint8)
        return img.reshape(H, W, 3)


def render_mesh(vertices, faces, *, camera: Camera = Camera(), size=(512, 512), shading: str = "gouraud",
                **kw) -> np.ndarray:
    """Render one mesh (framed on itself); see :class:`MeshRenderer`.

    Returns
    -------
    ndarray, shape (H, W, 3), uint8 (BGR)
    """
    return MeshRenderer(faces, vertices, camera=camera, size=size, shading=shading, **kw).render(vertices)
