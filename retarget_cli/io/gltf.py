"""Binary glTF 2.0 (``.glb``) with morph targets and their weight animation.

A small writer following the glTF 2.0 specification (Khronos, 2021): one
mesh (polygons fan-triangulated, vertices in OBJ order, never merged), one
morph target per key shape, a ``weights`` animation sampled at every frame,
and optionally the head motion as the node's animated translation, rotation
and scale. Any glTF viewer plays it.

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

from .. import __version__
from ..errors import ShapeError
from .atomic import write_bytes

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
        n_comp = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[kind]
        acc = {"bufferView": len(self.views) - 1, "componentType": comp, "count": arr.size // n_comp, "type": kind}
        if bounds:
            flat = arr.reshape(acc["count"], n_comp)
            acc["min"] = [float(v) for v in flat.min(0)]
            acc["max"] = [float(v) for v in flat.max(0)]
        self.accessors.append(acc)
        return len(self.accessors) - 1


def glb_bytes(*, base, faces, targets, target_names, weights, fps: float, node_transforms=None,
              name: str = "character") -> bytes:
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
        Morph weights per frame; keyed at ``t / fps`` seconds.
    fps : float
    node_transforms : ndarray, shape (T, 3, 4), optional
        Per-frame similarity ``X' = s R X + t`` (rotation, uniform scale,
        translation), animated as the node's TRS.
    """
    base = np.asarray(base, dtype=np.float32)
    D = np.asarray(targets, dtype=np.float32)
    W = np.asarray(weights, dtype=np.float32)
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
    T = W.shape[0]
    tris = triangulate(faces)
    if tris.size and int(tris.max()) >= base.shape[0]:
        raise ShapeError(f"faces: vertex id {int(tris.max())} is out of range for {base.shape[0]} vertices")
    b = _Bin()
    prim = {"attributes": {"POSITION": b.add(base, kind="VEC3", target=_ARRAY_BUFFER, bounds=True)},
            "mode": _TRIANGLES}
    if len(tris):
        prim["indices"] = b.add(tris.reshape(-1), kind="SCALAR", target=_ELEMENT_ARRAY_BUFFER)
    prim["targets"] = [{"POSITION": b.add(d, kind="VEC3", target=_ARRAY_BUFFER, bounds=True)} for d in D]
    times = (np.arange(T) / fps).astype(np.float32)
    t_acc = b.add(times, kind="SCALAR", bounds=True)
    samplers = [{"input": t_acc, "output": b.add(W.reshape(-1), kind="SCALAR"), "interpolation": "LINEAR"}]
    channels = [{"sampler": 0, "target": {"node": 0, "path": "weights"}}]
    if node_transforms is not None:
        A = np.asarray(node_transforms, dtype=np.float64)
        if A.shape != (T, 3, 4):
            raise ShapeError(f"node_transforms: expected shape ({T}, 3, 4), got {A.shape}")
        s = np.linalg.norm(A[:, :, 0], axis=1)
        phi = np.arctan2(A[:, 1, 0], A[:, 0, 0])  # roll about z
        quat = np.stack([np.zeros(T), np.zeros(T), np.sin(phi / 2), np.cos(phi / 2)], 1)
        for path, val in (("translation", A[:, :, 3]), ("rotation", quat), ("scale", np.repeat(s[:, None], 3, 1))):
            kind = "VEC4" if path == "rotation" else "VEC3"
            samplers.append({"input": t_acc, "output": b.add(val.astype(np.float32), kind=kind),
                             "interpolation": "LINEAR"})
            channels.append({"sampler": len(samplers) - 1, "target": {"node": 0, "path": path}})
    doc = {
        "asset": {"version": "2.0", "generator": f"retarget {__version__}"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": name}],
        "meshes": [{"name": name, "primitives": [prim], "weights": [0.0] * D.shape[0],
                    "extras": {"targetNames": list(map(str, target_names))}}],
        "animations": [{"name": "retarget", "samplers": samplers, "channels": channels}],
        "buffers": [{"byteLength": b.size}],
        "bufferViews": b.views,
        "accessors": b.accessors,
    }
    js = json.dumps(doc, sort_keys=True, separators=(",", ":"), allow_nan=False).encode("utf-8")
    js += b" " * ((-len(js)) % 4)
    binary = b"".join(b.parts)
    total = 12 + 8 + len(js) + 8 + len(binary)
    return b"".join([
        struct.pack("<4sII", b"glTF", 2, total),
        struct.pack("<I4s", len(js), b"JSON"), js,
        struct.pack("<I4s", len(binary), b"BIN\0"), binary,
    ])


def write_glb(path: str | os.PathLike, **kwargs) -> None:
    """Atomically write :func:`glb_bytes` to *path*."""
    write_bytes(path, glb_bytes(**kwargs))
