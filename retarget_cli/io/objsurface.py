"""The surface attributes of an OBJ that exporters need: face corners with their UV and normal ids, materials.

:class:`~retarget_cli.io.obj.ObjMesh` keeps everything but the ``v`` lines
as bytes; :func:`obj_surface` parses the ``vt``, ``vn``, ``f``, ``usemtl`` and
``mtllib`` lines from them (indices already checked by
:func:`~retarget_cli.io.obj.read_obj`) and reads the diffuse colour (``Kd``)
of each material from the ``.mtl`` files beside the OBJ.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


@dataclass
class ObjSurface:
    """Face corners and their attributes, in file order.

    Attributes
    ----------
    counts : ndarray, shape (F,), int64
        Corners per face.
    v, vt, vn : ndarray, shape (C,), int64
        Per corner: 0-based vertex, texture coordinate and normal ids (-1 where the corner has none).
    uv : ndarray, shape (M, 2) or None
        ``vt`` lines (u, v), None when there are none.
    normals : ndarray, shape (K, 3) or None
        ``vn`` lines, None when there are none.
    material : ndarray, shape (F,), int64
        Index of each face's material in :attr:`materials` (``usemtl``; 0 before any).
    materials : list of str
        Material names in order of first use (``""`` for faces before any ``usemtl``).
    base_colors : dict
        Material name to its ``Kd`` (r, g, b), for those found in the ``mtllib`` files.
    """

    counts: np.ndarray
    v: np.ndarray
    vt: np.ndarray
    vn: np.ndarray
    uv: np.ndarray | None
    normals: np.ndarray | None
    material: np.ndarray
    materials: list = field(default_factory=list)
    base_colors: dict = field(default_factory=dict)

    @property
    def has_uv(self) -> bool:
        return self.uv is not None and bool(np.all(self.vt >= 0))

    @property
    def has_normals(self) -> bool:
        return self.normals is not None and bool(np.all(self.vn >= 0))


def read_mtl_colors(path: Path) -> dict:
    """``Kd`` of every ``newmtl`` in a ``.mtl`` file (missing or unreadable file: empty)."""
    colors, current = {}, None
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError:
        log.warning("%s: material library not found; no base colours", path)
        return colors
    for line in text.splitlines():
        tok = line.split("#", 1)[0].split()
        if not tok:
            continue
        if tok[0] == "newmtl" and len(tok) > 1:
            current = " ".join(tok[1:])
        elif tok[0] == "Kd" and current is not None and len(tok) >= 4:
            try:
                colors[current] = tuple(min(max(float(x), 0.0), 1.0) for x in tok[1:4])
            except ValueError:
                pass
    return colors


def obj_surface(mesh) -> ObjSurface:
    """Parse the face corners, UVs, normals and materials of an :class:`~retarget_cli.io.obj.ObjMesh`.

    Negative (relative) indices are resolved against the lines read so far,
    as the OBJ specification says.
    """
    counts, cv, ct, cn, fmat = [], [], [], [], []
    uv, vn = [], []
    materials: dict[str, int] = {}
    current = None
    libs = []
    n_v = 0
    for i, seg in enumerate(mesh.segments):
        for line in seg.splitlines():
            tok = line.split(b"#", 1)[0].split()
            if not tok:
                continue
            head = tok[0]
            if head == b"vt":
                uv.append((float(tok[1]), float(tok[2]) if len(tok) > 2 else 0.0))
            elif head == b"vn":
                vn.append((float(tok[1]), float(tok[2]), float(tok[3])))
            elif head == b"usemtl":
                current = b" ".join(tok[1:]).decode("utf-8", "replace")
            elif head == b"mtllib":
                libs += [t.decode("utf-8", "replace") for t in tok[1:]]
            elif head == b"f":
                for t in tok[1:]:
                    parts = t.split(b"/")
                    ids = []
                    for slot, total in enumerate((n_v, len(uv), len(vn))):
                        p = parts[slot] if slot < len(parts) else b""
                        if not p:
                            ids.append(-1)
                            continue
                        k = int(p)
                        ids.append(k - 1 if k > 0 else total + k)
                    cv.append(ids[0])
                    ct.append(ids[1])
                    cn.append(ids[2])
                counts.append(len(tok) - 1)
                name = current or ""
                fmat.append(materials.setdefault(name, len(materials)))
        if i < len(mesh.runs):
            n_v = mesh.runs[i][1]
    colors = {}
    for lib in libs:
        colors.update(read_mtl_colors(Path(mesh.path).parent / lib))
    as_int = lambda x: np.asarray(x, dtype=np.int64)
    return ObjSurface(as_int(counts), as_int(cv), as_int(ct), as_int(cn),
                      np.asarray(uv, dtype=np.float64).reshape(-1, 2) if uv else None,
                      np.asarray(vn, dtype=np.float64).reshape(-1, 3) if vn else None,
                      as_int(fmat), list(materials), {m: colors[m] for m in materials if m in colors})


def vertex_normals(vertices, counts, corners) -> np.ndarray:
    """Area-weighted smooth vertex normals (unit length; 0 for vertices on no face).

    Each polygon adds the cross products of its fan triangles (Newell-like:
    the sum is twice the polygon's vector area) to its corners' vertices.

    Parameters
    ----------
    vertices : ndarray, shape (N, 3)
    counts : ndarray, shape (F,)
    corners : ndarray, shape (sum(counts),)

    Returns
    -------
    ndarray, shape (N, 3)
    """
    V = np.asarray(vertices, dtype=np.float64)
    counts = np.asarray(counts, dtype=np.int64)
    corners = np.asarray(corners, dtype=np.int64)
    start = np.cumsum(counts) - counts
    face_n = np.zeros((len(counts), 3))
    for j in range(1, int(counts.max(initial=0)) - 1):
        sel = counts > j + 1
        a, b, c = corners[start[sel]], corners[start[sel] + j], corners[start[sel] + j + 1]
        face_n[sel] += np.cross(V[b] - V[a], V[c] - V[a])
    out = np.zeros_like(V)
    np.add.at(out, corners, np.repeat(face_n, counts, axis=0))
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return np.divide(out, norm, out=np.zeros_like(out), where=norm > 0)


__all__ = ["ObjSurface", "obj_surface", "read_mtl_colors", "vertex_normals"]
