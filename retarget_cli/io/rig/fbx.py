"""Read a character rig (meshes and their blend shapes) from an FBX file, through Assimp.

:func:`read_fbx_rig` reads ``.fbx`` (binary and ASCII) with the Open Asset Import Library (Assimp, BSD-3-Clause)
through its Python bindings ``impasse`` (BSD) and the library itself from the ``cmeel-assimp`` wheel
(BSD-3-Clause): the optional extra ``fbx`` (``pip install 'retarget[fbx]'``). It writes nothing and returns the
glTF reader's :class:`~retarget_cli.io.rig.gltf.GltfRig` (``kind == "fbx"``; :class:`FbxRig` adds the file's
units) in world space, in the file's units.

What Assimp's FBX importer gives, and so what is read:

- every mesh of the node tree, placed by the nodes' transforms composed from the root (Assimp's pivot
  helper nodes included); a mesh with several materials arrives as one mesh per material;
- vertices **per face corner** (Assimp unrolls FBX control points): corners that are equal in position and
  in every blend shape of their mesh are welded back into one vertex here, so a smooth mesh has about its
  control-point count again (more at hard edges only where a shape splits them, never fewer than needed);
  the vertex order is that of first use by the faces, not the FBX control-point order;
- faces triangulated by Assimp (``aiProcess_Triangulate``); the data structure validated
  (``aiProcess_ValidateDataStructure``);
- blend shapes: one Assimp anim mesh per FBX shape, named after its blend-shape channel
  (``Deformer.Channel``); the delta is the anim mesh minus the mesh. A channel with in-between shapes arrives
  as several anim meshes of one name and Assimp does not give their ``FullWeights``: the last one (the
  largest full weight, which FBX keeps in ascending order, normally 100 %) is read and the in-betweens are
  dropped (logged);
- axes and units: Assimp's root node turns the file's axis system (``UpAxis``, ``FrontAxis``, ``CoordAxis``
  of its global settings) into Y up, +Z front, right-handed, and that node transform is applied like the
  others, so a Z-up file reads Y-up; units are not converted: the file's ``UnitScaleFactor`` (centimetres per
  unit) is reported as :attr:`FbxRig.meters_per_unit`, and its original up axis as :attr:`FbxRig.up_axis`.

Lost: control-point ids (see above), in-betweens, normals of shapes, skinning (a skinned mesh is read in its
bind pose as stored), the channels' default weights (``DeformPercent``; the neutral has every weight 0).
Sliders: the blend shapes grouped by name across meshes, the common ``Deformer.`` prefix dropped (:mod:`._scene`).
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import InputError, MissingExtraError
from ._isolated import read_isolated
from ._scene import SceneMesh, assemble
from .gltf import GltfRig

log = logging.getLogger(__name__)

#: The suffixes read as FBX.
FBX_EXTS = (".fbx",)
#: Largest FBX file read (Assimp reads it whole into memory, several times its size).
MAX_FBX_BYTES = 1 << 30
_MISSING = "reading an FBX rig needs the optional extra 'fbx': pip install 'retarget[fbx]' (impasse, cmeel-assimp)"
_TRIANGULATE, _VALIDATE = 0x8, 0x400


@dataclass(frozen=True, eq=False)
class FbxRig(GltfRig):
    """:class:`GltfRig` of an FBX file, with its units.

    Attributes
    ----------
    meters_per_unit : float or None
        ``UnitScaleFactor / 100`` (FBX units are centimetres times the factor); None when the file does not say.
    up_axis : str or None
        The file's own up axis, ``"+Y"``, ``"+Z"`` ... from ``UpAxis``/``UpAxisSign`` (the coordinates returned
        are Y-up, see the module docstring); None when the file does not say.
    """

    meters_per_unit: float | None = None
    up_axis: str | None = None


def _impasse(path: Path):
    """``impasse`` with Assimp from the ``cmeel-assimp`` wheel; a one-line MissingExtraError without them."""
    try:
        lib = importlib.metadata.distribution("cmeel-assimp").locate_file("cmeel.prefix/lib")
    except importlib.metadata.PackageNotFoundError:
        lib = None
    old = os.environ.get("LD_LIBRARY_PATH")
    if lib is not None:  # impasse looks for libassimp at import in a few system folders and LD_LIBRARY_PATH
        os.environ["LD_LIBRARY_PATH"] = os.pathsep.join([str(lib), *([old] if old else [])])
    try:
        import impasse
    except ImportError:
        raise MissingExtraError(f"{path.name}: {_MISSING}") from None
    except BaseException as exc:  # impasse's AssimpError derives from BaseException
        if type(exc).__name__ != "AssimpError":
            raise
        raise MissingExtraError(f"{path.name}: the Assimp library was not found; {_MISSING}") from None
    finally:
        if lib is not None:
            if old is None:
                os.environ.pop("LD_LIBRARY_PATH", None)
            else:
                os.environ["LD_LIBRARY_PATH"] = old
    return impasse


def _load(impasse, path: Path):
    size = path.stat().st_size
    if size > MAX_FBX_BYTES:
        raise InputError(f"{path.name}: {size >> 20} MiB, more than the {MAX_FBX_BYTES >> 20} MiB an FBX rig may be")
    with open(path, "rb") as fh:
        head = fh.read(64)
    if not (head.startswith(b"Kaydara FBX Binary") or b"FBX" in head or head.lstrip().startswith(b";")):
        raise InputError(f"{path.name}: not an FBX file (no 'Kaydara FBX Binary' header or FBX ASCII comment)")
    try:
        return impasse.load(str(path), processing=_TRIANGULATE | _VALIDATE)
    except BaseException as exc:
        if type(exc).__name__ != "AssimpError":
            raise
        raise InputError(f"{path.name}: Assimp cannot import it as FBX (corrupt, truncated or not FBX)") from None


def _vectors(ffi, ptr, n: int) -> np.ndarray:
    """``n`` aiVector3D at *ptr* as (n, 3) float32, a view of Assimp's memory (copy it before the scene goes)."""
    if n == 0 or ptr == ffi.NULL:
        return np.zeros((n, 3), dtype=np.float32)
    return np.frombuffer(ffi.buffer(ptr, 12 * n), dtype=np.float32).reshape(n, 3)


def _name(ffi, s) -> str:
    return ffi.string(s.data, min(int(s.length), 1023)).decode("utf-8", "replace")


def _faces(ffi, m, n: int, where: str) -> np.ndarray:
    """Triangles (F, 3) of an aiMesh (points and lines, left by Triangulate, add none)."""
    tris = []
    for i in range(int(m.mNumFaces)):
        face = m.mFaces[i]
        if int(face.mNumIndices) == 3:
            tris.append(tuple(face.mIndices[c] for c in range(3)))
    faces = np.array(tris, dtype=np.int64).reshape(-1, 3)
    if faces.size and int(faces.max()) >= n:
        raise InputError(f"{where}: a face uses vertex {int(faces.max())}, the mesh has {n}")
    return faces


def _shapes(ffi, m, n: int, where: str, file: str):
    """(labels, anim meshes): the last anim mesh of each run of one name (in-betweens dropped)."""
    runs: list = []
    for i in range(int(m.mNumAnimMeshes)):
        a = m.mAnimMeshes[i]
        label = _name(ffi, a.mName) or f"#{i}"
        if int(a.mNumVertices) != n or a.mVertices == ffi.NULL:
            raise InputError(f"{file}: {where}: blend shape '{label}' has {int(a.mNumVertices)} vertices, the mesh "
                             f"{n}")
        if runs and runs[-1][0] == label:
            runs[-1][1] += 1
            runs[-1][2] = a
        else:
            runs.append([label, 1, a])
    dropped = [f"{label} ({k - 1})" for label, k, _ in runs if k > 1]
    if dropped:
        log.info("%s: %s: in-between shapes dropped, the last (full-weight) shape of each channel read: %s",
                 file, where, ", ".join(dropped))
    return [label for label, _, _ in runs], [a for _, _, a in runs]


def _weld(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows (n, m) float32 equal bit for bit merged: (kept rows (u,) in first-use order, index into them (n,)).

    Grouped by the first 3 columns (the position) first, then the rows that differ from their position's first
    row elsewhere (a shape splits them) by whole rows: no sort of the long rows in the usual case.
    """
    n = len(rows)
    if n == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    void = lambda a: np.ascontiguousarray(a).view(np.dtype((np.void, a.dtype.itemsize * a.shape[1]))).ravel()
    _, first, inv = np.unique(void(rows[:, :3]), return_index=True, return_inverse=True)
    rep = first[inv.ravel()]
    differs = np.flatnonzero(np.any(rows.view(np.uint32) != rows.view(np.uint32)[rep], axis=1))
    if differs.size:
        _, sub_first, sub_inv = np.unique(void(rows[differs]), return_index=True, return_inverse=True)
        rep[differs] = differs[sub_first[sub_inv.ravel()]]
    keep, index = np.unique(rep, return_inverse=True)
    return keep, index.ravel()


def _meshes(impasse, scene, file: str) -> list[SceneMesh]:
    ffi = impasse.structs.ffi
    s = scene.struct
    out, seen = [], {}
    stack = [(s.mRootNode, np.eye(4), 0)]
    while stack:
        node, above, depth = stack.pop()
        if node == ffi.NULL or depth > 1000:
            raise InputError(f"{file}: the node tree is deeper than 1000 levels or has an empty node")
        t = node.mTransformation
        local = np.array([[t.a1, t.a2, t.a3, t.a4], [t.b1, t.b2, t.b3, t.b4], [t.c1, t.c2, t.c3, t.c4],
                          [t.d1, t.d2, t.d3, t.d4]], dtype=np.float64)
        with np.errstate(over="ignore", invalid="ignore"):
            world = above @ local
        if not np.isfinite(world).all():
            raise InputError(f"{file}: node '{_name(ffi, node.mName)}': its world transform is not finite")
        for j in range(int(node.mNumMeshes)):
            idx = int(node.mMeshes[j])
            if idx >= int(s.mNumMeshes):
                raise InputError(f"{file}: node '{_name(ffi, node.mName)}' uses mesh {idx}, the file has "
                                 f"{int(s.mNumMeshes)}")
            out.append(_mesh(ffi, s.mMeshes[idx], world, _name(ffi, node.mName), file, seen))
        for c in reversed(range(int(node.mNumChildren))):
            stack.append((node.mChildren[c], world, depth + 1))
    return out


def _mesh(ffi, m, world: np.ndarray, node: str, file: str, seen: dict) -> SceneMesh:
    name = _name(ffi, m.mName) or node or "mesh"
    seen[name] = seen.get(name, 0) + 1
    unique = name if seen[name] == 1 else f"{name}~{seen[name]}"
    where = f"mesh '{unique}'"
    n = int(m.mNumVertices)
    faces = _faces(ffi, m, n, f"{file}: {where}")
    labels, anims = _shapes(ffi, m, n, where, file)
    rows = np.empty((n, 3 + 3 * len(anims)), dtype=np.float32)  # the corner, then where each shape puts it
    rows[:, :3] = _vectors(ffi, m.mVertices, n)
    for k, a in enumerate(anims):
        rows[:, 3 + 3 * k:6 + 3 * k] = _vectors(ffi, a.mVertices, n)
    keep, index = _weld(rows)  # corners of one control point: equal position, equal in every shape
    faces = index[faces] if faces.size else faces
    base = rows[keep, :3].astype(np.float64)
    lin, shift = world[:3, :3], world[:3, 3]
    with np.errstate(over="ignore", invalid="ignore"):
        points = base @ lin.T + shift
        deltas = [(rows[keep, 3 + 3 * k:6 + 3 * k].astype(np.float64) - base) @ lin.T for k in range(len(anims))]
    return SceneMesh(name=unique, points=points, faces=faces, labels=labels,
                     deltas=[(lambda d=d: d) for d in deltas], aliases=(node, name))


def _units(scene) -> tuple[float | None, str | None]:
    meta = scene.metadata
    keys = set(meta.keys()) if meta is not None else set()
    mpu = float(meta["UnitScaleFactor"]) / 100.0 if "UnitScaleFactor" in keys else None
    up = None
    if "UpAxis" in keys:
        sign = "-" if "UpAxisSign" in keys and int(meta["UpAxisSign"]) < 0 else "+"
        up = sign + "XYZ"[int(meta["UpAxis"]) % 3]
    return mpu, up


def read_fbx_here(path, *, meshes=None, targets=None) -> FbxRig:
    """:func:`read_fbx_rig` in this process (the child of :mod:`._isolated`; a crash in the library is this process's)."""
    return _read(path, meshes=meshes, targets=targets)


def read_fbx_rig(path, *, meshes=None, targets=None) -> FbxRig:
    """Read a rig from an FBX file: every mesh's vertices, triangles and blend shapes, in world space.

    Parameters
    ----------
    path : str or Path
    meshes : str or list of str, optional
        Glob patterns on mesh or node names. Default: every mesh with blend shapes.
    targets : str or list of str, optional
        Glob patterns on blend shape names (``Deformer.Channel``, or ``mesh/name``).

    Returns
    -------
    FbxRig
        ``neutral`` (V, 3), ``faces`` (F, 3), ``deltas`` (K, V, 3) float64 in the file's units (Y up), and its
        ``meters_per_unit`` and original ``up_axis``.

    Raises
    ------
    InputError
        One line: a file Assimp cannot import, a malformed mesh, no blend shapes, a pattern matching nothing.
    MissingExtraError
        The extra ``fbx`` is not installed.

    Notes
    -----
    Assimp runs in a child process (:mod:`._isolated`), its memory and time limited: a crash or a runaway
    allocation on a hostile file costs one InputError line, not the process. Starting it costs about 0.5 s.
    """
    path = Path(path)
    if importlib.util.find_spec("impasse") is None:
        raise MissingExtraError(f"{path.name}: {_MISSING}")
    if not path.is_file():
        raise InputError(f"{path}: rig file not found")
    return read_isolated("fbx", path, "Assimp", FbxRig, meshes=meshes, targets=targets)


def _read(path, *, meshes=None, targets=None) -> FbxRig:
    path = Path(path)
    impasse = _impasse(path)
    if not path.is_file():
        raise InputError(f"{path}: rig file not found")
    scene = _load(impasse, path)
    found = _meshes(impasse, scene, path.name)
    mpu, up = _units(scene)
    log.info("%s: UnitScaleFactor gives %s m per unit (not converted); the file's up axis %s, read Y-up",
             path.name, "?" if mpu is None else f"{mpu:g}", up or "?")
    return assemble(path.name, found, mesh_patterns=meshes, targets=targets, kind="fbx", rig_class=FbxRig,
                    meters_per_unit=mpu, up_axis=up)


__all__ = ["FBX_EXTS", "FbxRig", "MAX_FBX_BYTES", "read_fbx_here", "read_fbx_rig"]
