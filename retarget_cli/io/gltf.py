"""Binary glTF 2.0 (``.glb``) with morph targets and their weight animation.

A small writer following the glTF 2.0 specification (Khronos, 2021): one
mesh (polygons fan-triangulated, vertices in OBJ order, never merged), one
morph target per key shape or rig shape (their names in
``mesh.extras.targetNames``, the convention Blender, three.js and Babylon.js
read), a ``weights`` animation sampled at every frame, and optionally the
head motion as the node's animated translation, rotation and scale. Any glTF
viewer plays it.

Given the OBJ's surface (:func:`~retarget_cli.io.objsurface.obj_surface`),
the mesh also carries ``TEXCOORD_0`` (where every face corner has a ``vt``),
``NORMAL`` (the OBJ's ``vn``, else smooth area-weighted normals of the base
mesh) and one primitive per ``usemtl`` material with the ``.mtl``'s ``Kd`` as
``baseColorFactor``. glTF has one UV and normal per vertex, so a vertex whose
corners carry different UVs or normals (a UV seam) is split: the first N
glTF vertices are the OBJ's in order, the copies follow.

Layout of the file: 12-byte header (``glTF``, version 2, total length), a JSON
chunk padded with spaces and a BIN chunk padded with zeros, both to 4 bytes;
every buffer view starts on a 4-byte boundary. POSITION accessors (of the mesh
and of each target) and the animation's time accessor carry ``min``/``max``
as the specification requires.
"""

from __future__ import annotations

import json
import os
import struct

import numpy as np
from scipy.spatial.transform import Rotation

from .. import __version__
from ..errors import ShapeError
from .atomic import write_bytes
from .objsurface import vertex_normals

_FLOAT, _UINT = 5126, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_TRIANGLES = 4


def triangulate(faces) -> np.ndarray:
    """Fan-triangulate polygons in file order: ``(v0, vi, vi+1)`` for each face.

    Parameters
    ----------
    faces : sequence of sequence of int
        0-based vertex ids; faces with fewer than 3 corners are skipped.
        Fans are exact for convex polygons (the usual quads and n-gons).

    Returns
    -------
    ndarray, shape (F', 3), uint32
    """
    rows = [(f[0], f[i], f[i + 1]) for f in faces for i in range(1, len(f) - 1)]
    return np.asarray(rows, dtype=np.uint32).reshape(-1, 3)


def split_vertices(surface, n_vertices: int):
    """glTF vertices for an OBJ surface: one per distinct (vertex, UV, normal) of the face corners.

    Parameters
    ----------
    surface : ObjSurface
    n_vertices : int
        N, the OBJ's vertex count.

    Returns
    -------
    src : ndarray, shape (N',), int64
        OBJ vertex of each glTF vertex; ``src[:N] == arange(N)``, the seam
        copies after, in order of first use.
    corners : ndarray, shape (C,), int64
        glTF vertex of each face corner.
    vt, vn : ndarray, shape (N',), int64, or None
        The ``vt`` / ``vn`` id of each glTF vertex (-1 for vertices no face
        uses); None when not every corner has one.
    """
    v = surface.v
    cols = [v]
    use_vt, use_vn = surface.has_uv, surface.has_normals
    if use_vt:
        cols.append(surface.vt)
    if use_vn:
        cols.append(surface.vn)
    K = np.stack(cols, 1)
    primary = np.full((n_vertices, K.shape[1]), -1, np.int64)
    primary[:, 0] = np.arange(n_vertices)
    first_v, first_at = np.unique(v, return_index=True)
    primary[first_v] = K[first_at]
    same = np.all(K == primary[v], axis=1)
    corners = v.copy()
    extra = np.zeros((0, K.shape[1]), np.int64)
    if not same.all():
        rows, first, inverse = np.unique(K[~same], axis=0, return_index=True, return_inverse=True)
        order = np.argsort(first, kind="stable")
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        corners[~same] = n_vertices + rank[inverse.ravel()]
        extra = rows[order]
    table = np.concatenate([primary, extra])
    k = 1
    vt = vn = None
    if use_vt:
        vt, k = table[:, k], k + 1
    if use_vn:
        vn = table[:, k]
    return table[:, 0], corners, vt, vn


def _fan(counts, corners) -> np.ndarray:
    """Fan triangles ``(c0, cj, cj+1)`` of every face, in file order; (F', 3) and the face of each."""
    counts = np.asarray(counts, dtype=np.int64)
    n_tri = np.maximum(counts - 2, 0)
    face = np.repeat(np.arange(len(counts)), n_tri)
    start = np.cumsum(counts) - counts
    j = np.arange(len(face)) - np.repeat(np.cumsum(n_tri) - n_tri, n_tri) + 1
    s0 = start[face]
    tris = np.stack([corners[s0], corners[s0 + j], corners[s0 + j + 1]], 1)
    return tris.astype(np.uint32), face


class _Bin:
    """The BIN chunk under construction: buffer views and accessors."""

    def __init__(self):
        self.parts: list[bytes] = []
        self.size = 0
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(self, arr: np.ndarray, *, kind: str, target: int | None = None, bounds: bool = False) -> int:
        """Append *arr* (float32 or uint32, C order) as a view and an accessor; return the accessor index."""
        comp = _UINT if arr.dtype == np.uint32 else _FLOAT
        data = np.ascontiguousarray(arr).tobytes()
        view = {"buffer": 0, "byteOffset": self.size, "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        self.views.append(view)
        pad = (-len(data)) % 4
        self.parts += [data, b"\0" * pad]
        self.size += len(data) + pad
        n_comp = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[kind]
        acc = {"bufferView": len(self.views) - 1, "componentType": comp, "count": arr.size // n_comp, "type": kind}
        if bounds:
            flat = arr.reshape(acc["count"], n_comp)
            acc["min"] = [float(v) for v in flat.min(0)]
            acc["max"] = [float(v) for v in flat.max(0)]
        self.accessors.append(acc)
        return len(self.accessors) - 1


def _check_glb_inputs(base: np.ndarray, D: np.ndarray, W: np.ndarray, target_names, fps: float) -> None:
    """Shapes of :func:`glb_bytes`'s arrays: base (N, 3), targets (M, N, 3), weights (T >= 1, M); fps > 0."""
    if base.ndim != 2 or base.shape[1] != 3:
        raise ShapeError(f"base: expected shape (N, 3), got {base.shape}")
    if D.ndim != 3 or D.shape[1:] != base.shape:
        raise ShapeError(f"targets: expected shape (M, {base.shape[0]}, 3), got {D.shape}")
    if W.ndim != 2 or W.shape[1] != D.shape[0] or W.shape[0] < 1:
        raise ShapeError(f"weights: expected shape (T, {D.shape[0]}), got {W.shape}")
    if len(target_names) != D.shape[0]:
        raise ShapeError(f"target_names: expected {D.shape[0]} names, got {len(target_names)}")
    if not fps > 0:
        raise ShapeError(f"fps: expected > 0, got {fps}")


def _surface_normals(surface, base: np.ndarray, src: np.ndarray, vn, N: int) -> np.ndarray:
    """Unit normals (V, 3) of the split vertices: the OBJ's ``vn`` where given, else computed from the faces."""

    if vn is not None:
        nrm = surface.normals[np.maximum(vn, 0)]
        nrm[vn < 0] = 0
    else:
        nrm = vertex_normals(base[:N], surface.counts, surface.v)[src]
    length = np.linalg.norm(nrm, axis=1, keepdims=True)
    return np.where(length > 0, nrm / np.where(length > 0, length, 1), [0.0, 0.0, 1.0])  # unit, as glTF requires


def _material_groups(surface, tris: np.ndarray, face: np.ndarray) -> tuple[list, list]:
    """Triangles grouped per OBJ material as ``[(material index or None, (F, 3))]``, and the glTF materials."""
    tri_mat = surface.material[face]
    groups, materials = [], []
    for m, mat in enumerate(surface.materials):
        color = surface.base_colors.get(mat)
        if color is None and not mat:
            groups.append((None, tris[tri_mat == m]))
            continue
        pbr = {"metallicFactor": 0.0}
        if color is not None:
            pbr["baseColorFactor"] = [float(c) for c in color] + [1.0]
        groups.append((len(materials), tris[tri_mat == m]))
        materials.append({"name": mat, "pbrMetallicRoughness": pbr})
    return groups or [(None, tris)], materials


def _plain_mesh(b: _Bin, base: np.ndarray, faces, N: int) -> tuple[dict, list]:
    """Attributes and one triangle group of a mesh given as polygons only."""
    tris = triangulate(faces)
    if tris.size and int(tris.max()) >= N:
        raise ShapeError(f"faces: vertex id {int(tris.max())} is out of range for {N} vertices")
    attributes = {"POSITION": b.add(base, kind="VEC3", target=_ARRAY_BUFFER, bounds=True)}
    return attributes, [(None, tris)]


def _surface_mesh(b: _Bin, surface, base: np.ndarray, D: np.ndarray, N: int):
    """Attributes, triangle groups and materials of an OBJ surface; base and targets split per corner."""
    if surface.v.size and int(surface.v.max()) >= N:
        raise ShapeError(f"surface: vertex id {int(surface.v.max())} is out of range for {N} vertices")
    src, corners, vt, vn = split_vertices(surface, N)
    base, D = base[src], D[:, src]
    attributes = {"POSITION": b.add(base, kind="VEC3", target=_ARRAY_BUFFER, bounds=True)}
    nrm = _surface_normals(surface, base, src, vn, N)
    attributes["NORMAL"] = b.add(nrm.astype(np.float32), kind="VEC3", target=_ARRAY_BUFFER)
    if vt is not None:
        uv = surface.uv[np.maximum(vt, 0)] * [1.0, -1.0] + [0.0, 1.0]  # glTF's v runs downwards
        uv[vt < 0] = 0
        attributes["TEXCOORD_0"] = b.add(uv.astype(np.float32), kind="VEC2", target=_ARRAY_BUFFER)
    tris, face = _fan(surface.counts, corners)
    groups, materials = _material_groups(surface, tris, face)
    return attributes, groups, materials, D


def _primitives(b: _Bin, groups: list, attributes: dict, targets: list) -> list:
    """One glTF primitive per triangle group, sharing the attributes and morph targets."""
    prims = []
    for mat, tri in groups:
        prim = {"attributes": attributes, "mode": _TRIANGLES, "targets": targets}
        if len(tri):
            prim["indices"] = b.add(tri.reshape(-1), kind="SCALAR", target=_ELEMENT_ARRAY_BUFFER)
        if mat is not None:
            prim["material"] = mat
        prims.append(prim)
    return prims


def _quaternions(R) -> np.ndarray:
    """glTF ``[x, y, z, w]`` unit quaternions (T, 4) of rotation matrices (T, 3, 3), each in the hemisphere of the
    previous one (a linear interpolation between keys then turns the short way)."""
    q = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()
    if len(q):
        q[0] *= -1.0 if q[0, 3] < 0 else 1.0
    for t in range(1, len(q)):
        if q[t] @ q[t - 1] < 0:
            q[t] = -q[t]
    return q


def _node_animation(b: _Bin, node_transforms, T: int, t_acc: int, samplers: list, channels: list) -> None:
    """Append the node's TRS samplers and channels for per-frame similarities (T, 3, 4): a rotation in 3D (the
    head's 3D pose) or about z (the 2D head motion's roll), a uniform scale and a translation."""
    A = np.asarray(node_transforms, dtype=np.float64)
    if A.shape != (T, 3, 4):
        raise ShapeError(f"node_transforms: expected shape ({T}, 3, 4), got {A.shape}")
    s = np.linalg.norm(A[:, :, 0], axis=1)
    quat = _quaternions(A[:, :, :3] / s[:, None, None])
    for path, val in (("translation", A[:, :, 3]), ("rotation", quat), ("scale", np.repeat(s[:, None], 3, 1))):
        kind = "VEC4" if path == "rotation" else "VEC3"
        samplers.append({"input": t_acc, "output": b.add(val.astype(np.float32), kind=kind),
                         "interpolation": "LINEAR"})
        channels.append({"sampler": len(samplers) - 1, "target": {"node": 0, "path": path}})


def _container(doc: dict, b: _Bin) -> bytes:
    """The GLB container: header, JSON chunk (space-padded), BIN chunk."""
    js = json.dumps(doc, sort_keys=True, separators=(",", ":"), allow_nan=False).encode("utf-8")
    js += b" " * ((-len(js)) % 4)
    binary = b"".join(b.parts)
    total = 12 + 8 + len(js) + 8 + len(binary)
    return b"".join([
        struct.pack("<4sII", b"glTF", 2, total),
        struct.pack("<I4s", len(js), b"JSON"), js,
        struct.pack("<I4s", len(binary), b"BIN\0"), binary,
    ])


def glb_bytes(*, base, faces, targets, target_names, weights, fps: float, node_transforms=None,
              name: str = "character", surface=None, times=None) -> bytes:
    """A complete ``.glb`` file.

    The mesh at frame ``t`` is ``base + Σ_m weights[t, m] targets[m]`` (glTF
    morph targets), placed by the node transform of frame ``t`` when given.

    Parameters
    ----------
    base : ndarray, shape (N, 3)
        Base mesh positions (the neutral, or the first key).
    faces : sequence of sequence of int
        0-based polygons; fan-triangulated.
    targets : ndarray, shape (M, N, 3)
        Morph target displacements.
    target_names : sequence of str, length M
        Stored in ``mesh.extras.targetNames``.
    weights : ndarray, shape (T, M)
        Morph weights per frame; keyed at ``t / fps`` seconds, or at *times*.
    fps : float
    node_transforms : ndarray, shape (T, 3, 4), optional
        Per-frame similarity ``X' = s R X + t`` (rotation, uniform scale,
        translation), animated as the node's TRS.
    surface : ObjSurface, optional
        The OBJ's faces, UVs, normals and materials
        (:func:`~retarget_cli.io.objsurface.obj_surface`); replaces *faces*
        and adds ``TEXCOORD_0``, ``NORMAL`` and materials (see the module
        docstring).
    times : ndarray, shape (T,), optional
        Each frame's time in seconds (the source's timestamps: a take tracked from frame 100 starts at 100 / fps).
    """
    base = np.asarray(base, dtype=np.float32)
    D = np.asarray(targets, dtype=np.float32)
    W = np.asarray(weights, dtype=np.float32)
    _check_glb_inputs(base, D, W, target_names, fps)
    T = W.shape[0]
    N = base.shape[0]
    b = _Bin()
    if surface is None:
        attributes, groups = _plain_mesh(b, base, faces, N)
        materials = []
    else:
        attributes, groups, materials, D = _surface_mesh(b, surface, base, D, N)
    targets = [{"POSITION": b.add(d, kind="VEC3", target=_ARRAY_BUFFER, bounds=True)} for d in D]
    prims = _primitives(b, groups, attributes, targets)
    times = (np.arange(T) / fps if times is None else np.asarray(times, dtype=np.float64)).astype(np.float32)
    if times.shape != (T,) or np.any(np.diff(times) <= 0):
        raise ShapeError(f"times: expected {T} increasing seconds, got shape {times.shape}")
    t_acc = b.add(times, kind="SCALAR", bounds=True)
    samplers = [{"input": t_acc, "output": b.add(W.reshape(-1), kind="SCALAR"), "interpolation": "LINEAR"}]
    channels = [{"sampler": 0, "target": {"node": 0, "path": "weights"}}]
    if node_transforms is not None:
        _node_animation(b, node_transforms, T, t_acc, samplers, channels)
    doc = {
        "asset": {"version": "2.0", "generator": f"retarget {__version__}"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": name}],
        "meshes": [{"name": name, "primitives": prims, "weights": [0.0] * D.shape[0],
                    "extras": {"targetNames": list(map(str, target_names))}}],
        "animations": [{"name": "retarget", "samplers": samplers, "channels": channels}],
        "buffers": [{"byteLength": b.size}],
        "bufferViews": b.views,
        "accessors": b.accessors,
    }
    if materials:
        doc["materials"] = materials
    return _container(doc, b)


def write_glb(path: str | os.PathLike, **kwargs) -> None:
    """Atomically write :func:`glb_bytes` to *path*."""
    write_bytes(path, glb_bytes(**kwargs))
