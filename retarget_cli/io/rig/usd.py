"""Read a character rig (meshes and their UsdSkel blend shapes) from a USD file (``.usd``, ``.usda``, ``.usdc``, ``.usdz``).

:func:`read_usd_rig` is a pure reader through Pixar's ``usd-core`` (the optional extra ``usd``, TOST-1.0): it
opens the stage, writes nothing and returns the glTF reader's :class:`~retarget_cli.io.rig.gltf.GltfRig`
(``kind == "usd"``; :class:`UsdRig` adds the stage's units) in world space, in the stage's units.

What is read (UsdSkel schema, Pixar 2019-2025: "Blend Shapes"):

- every ``Mesh`` prim of the composed stage (instance proxies included): ``points`` at the default time (the
  earliest time sample when only samples are authored), ``faceVertexCounts``/``faceVertexIndices``
  fan-triangulated (faces of fewer than 3 corners add no triangle; ``holeIndices`` ignored), winding flipped
  for ``orientation = leftHanded``;
- placed by the prim's local-to-world transform (``UsdGeom.XformCache`` at the default time);
  skinning is not evaluated: a skinned mesh is read as authored (its bind pose);
- a mesh's blend shapes: the ``skel:blendShapes`` tokens (the names a ``SkelAnimation`` drives) paired in
  order with the ``skel:blendShapeTargets`` ``BlendShape`` prims; each shape's ``offsets`` (dense, or sparse
  with ``pointIndices``) at full weight, in the mesh's space, placed by the linear part of its transform.
  In-betweens (``inbetweens:*``) and ``normalOffsets`` are not read (logged): a shape with in-betweens
  contributes its full-weight offsets linearly;
- the stage's ``metersPerUnit`` and ``upAxis`` are reported (:class:`UsdRig`, and logged at INFO); the
  coordinates are returned as stored, not converted.

Sliders: the blend shapes grouped by name across meshes (:mod:`._scene`).

Untrusted files: before the stage is composed, every sublayer, reference and payload the file names (and
theirs) must resolve to a file inside the rig's folder (no ``..`` out, no absolute path elsewhere, no URL,
no search path); value clips are refused. usd-core's own errors (a corrupt or truncated file) become one
:class:`~retarget_cli.errors.InputError` line, and since usd-core can abort or allocate without bound on a
mutated crate file, it runs in a child process with its memory and time limited (:mod:`._isolated`).
"""

from __future__ import annotations

import importlib.util
import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import InputError, MissingExtraError
from ._isolated import read_isolated
from ._scene import SceneMesh, assemble
from .gltf import GltfRig

log = logging.getLogger(__name__)

#: The suffixes read as USD.
USD_EXTS = (".usd", ".usda", ".usdc", ".usdz")
#: Most layers one rig may compose (sublayers, references, payloads).
_MAX_LAYERS = 256
_MISSING = "reading a USD rig needs usd-core, the optional extra 'usd': pip install 'retarget[usd]'"


@dataclass(frozen=True, eq=False)
class UsdRig(GltfRig):
    """:class:`GltfRig` of a USD stage, with its units.

    Attributes
    ----------
    meters_per_unit : float
        ``metersPerUnit`` of the stage (USD's fallback 0.01 when not authored).
    up_axis : str
        ``"Y"`` or ``"Z"``.
    layers : list of Path
        Every layer file the stage composed besides the root (sublayers, references, payloads).
    """

    meters_per_unit: float = 0.01
    up_axis: str = "Y"
    layers: list = None


def _pxr(path: Path):
    try:
        from pxr import Sdf, Tf, Usd, UsdGeom, UsdSkel  # noqa: F401
    except ImportError:
        raise MissingExtraError(f"{path.name}: {_MISSING}") from None
    import pxr

    return pxr


def _usd_error(path: Path, exc: Exception) -> InputError:
    """usd-core's error (several lines, internal names) as one line."""
    try:
        text = str(exc)
    except UnicodeError:  # the message quotes the file's bytes
        text = "an error message that is not UTF-8"
    text = re.sub(r"pxrInternal_v\w+?__pxrReserved__::", "", text)
    text = re.sub(r"\s+", " ", text).strip()
    m = re.search(r"\.h : '(.*)'$|\.cpp : '(.*)'$", text)
    text = next((g for g in m.groups() if g), text) if m else text
    return InputError(f"{path.name}: not a USD file usd-core can read ({text[:200]})")


def _inside(folder: Path, target: str) -> Path | None:
    """*target* (an absolute path, possibly ``pkg.usdz[inner]``) as a file inside *folder*, or None."""
    outer = target.split("[", 1)[0]
    if not outer or re.match(r"^[A-Za-z][A-Za-z0-9+.-]+:", outer) and not re.match(r"^[A-Za-z]:[\\/]", outer):
        return None
    p = Path(outer)
    try:
        real = p.resolve(strict=True)
    except (OSError, RuntimeError):
        return None
    if not real.is_file() or not real.is_relative_to(folder):
        return None
    return real


def _layer(pxr, path: Path, where: str):
    Sdf, Tf = pxr.Sdf, pxr.Tf
    try:
        found = Sdf.Layer.Find(str(path))
        if found is not None:
            found.Reload(True)
        layer = found or Sdf.Layer.FindOrOpen(str(path))
    except Tf.ErrorException as exc:
        raise _usd_error(path, exc) from None
    if layer is None:
        raise InputError(f"{where}: not a USD file usd-core can read (truncated or corrupt)")
    return layer


def _check_dependencies(pxr, root: Path) -> list[Path]:
    """Every layer the file composes, checked to lie inside its folder before the stage is opened."""
    folder = root.resolve().parent
    seen, todo, files = {root.resolve()}, [(root, _layer(pxr, root, root.name))], []
    while todo:
        path, layer = todo.pop()
        for dep in layer.GetCompositionAssetDependencies():
            where = f"{root.name}: {path.name} names {dep!r}"
            resolved = _inside(folder, layer.ComputeAbsolutePath(dep)) if dep else None
            if resolved is None:
                raise InputError(f"{where}, which is not a file inside the rig's folder {folder} (layers outside "
                                 "it, URLs and search paths are not read)")
            if resolved in seen:
                continue
            seen.add(resolved)
            if len(seen) > _MAX_LAYERS:
                raise InputError(f"{root.name}: composes more than {_MAX_LAYERS} layers")
            files.append(resolved)
            if "[" not in layer.ComputeAbsolutePath(dep):
                todo.append((resolved, _layer(pxr, resolved, where)))
    return files


def _open(pxr, path: Path):
    Usd, Tf = pxr.Usd, pxr.Tf
    files = _check_dependencies(pxr, path)
    try:
        stage = Usd.Stage.Open(str(path), Usd.Stage.LoadAll)
    except Tf.ErrorException as exc:
        raise _usd_error(path, exc) from None
    if stage is None:
        raise InputError(f"{path.name}: not a USD file usd-core can read")
    return stage, files


def _value(attr, Usd):
    """An attribute's value at the default time, else its earliest time sample; None when unauthored."""
    value = attr.Get()
    if value is None and attr.GetNumTimeSamples():
        value = attr.Get(Usd.TimeCode.EarliestTime())
    return value


def _triangles(name: str, counts: np.ndarray, corners: np.ndarray, n: int) -> np.ndarray:
    """Fan triangulation of polygons (F, 3), int64, checked against *n* points."""
    if counts.ndim != 1 or corners.ndim != 1 or (counts.size and counts.min() < 0) or counts.sum() != corners.size:
        raise InputError(f"{name}: faceVertexCounts sum to {int(counts.sum()) if counts.ndim == 1 else '?'}, "
                         f"faceVertexIndices has {corners.size}")
    if corners.size and (corners.min() < 0 or corners.max() >= n):
        raise InputError(f"{name}: faceVertexIndices holds {int(corners.max())}, the mesh has {n} points")
    tri = np.maximum(counts - 2, 0)
    poly = np.repeat(np.arange(len(counts)), tri)
    first = (np.cumsum(counts) - counts)[poly]
    step = np.arange(len(poly)) - np.repeat(np.cumsum(tri) - tri, tri) + 1
    return np.stack([corners[first], corners[first + step], corners[first + step + 1]], axis=1).astype(np.int64)


def _shape_delta(pxr, where: str, shape, n: int, lin: np.ndarray):
    """The callable reading one BlendShape's full-weight offsets (n, 3), placed by *lin* (3, 3)."""
    Usd = pxr.Usd

    def read():
        offsets = _value(shape.GetOffsetsAttr(), Usd)
        offsets = np.zeros((0, 3)) if offsets is None else np.asarray(offsets, dtype=np.float64).reshape(-1, 3)
        ids = _value(shape.GetPointIndicesAttr(), Usd)
        d = np.zeros((n, 3))
        if ids is None:
            if len(offsets) != n:
                raise InputError(f"{where}: {len(offsets)} offsets for the mesh's {n} points (no pointIndices)")
            d[:] = offsets
        else:
            ids = np.asarray(ids, dtype=np.int64).ravel()
            if len(ids) != len(offsets):
                raise InputError(f"{where}: {len(ids)} pointIndices for {len(offsets)} offsets")
            if ids.size and (ids.min() < 0 or ids.max() >= n):
                raise InputError(f"{where}: pointIndices holds {int(ids.max() if ids.max() >= n else ids.min())}, "
                                 f"the mesh has {n} points")
            np.add.at(d, ids, offsets)
        return d @ lin

    return read


def _blend_shapes(pxr, name: str, prim, n: int, lin: np.ndarray):
    """A mesh's (names, delta callables) from ``skel:blendShapes`` and ``skel:blendShapeTargets``."""
    UsdSkel = pxr.UsdSkel
    binding = UsdSkel.BindingAPI(prim)
    tokens = binding.GetBlendShapesAttr().Get()
    targets = binding.GetBlendShapeTargetsRel().GetTargets()
    if not tokens and not targets:
        return [], []
    tokens = [str(t) for t in (tokens or [])]
    if len(tokens) != len(targets):
        raise InputError(f"{name}: skel:blendShapes names {len(tokens)} shapes, skel:blendShapeTargets {len(targets)}")
    labels, deltas, inbetweens = [], [], 0
    stage = prim.GetStage()
    for k, (token, target) in enumerate(zip(tokens, targets)):
        shape = UsdSkel.BlendShape(stage.GetPrimAtPath(target))
        if not shape or not shape.GetPrim().IsA(UsdSkel.BlendShape):
            raise InputError(f"{name}: skel:blendShapeTargets[{k}] {target} is not a BlendShape prim")
        inbetweens += len(shape.GetInbetweens())
        labels.append(token or f"#{k}")
        deltas.append(_shape_delta(pxr, f"{name} blend shape '{token}' ({target})", shape, n, lin))
    if inbetweens:
        log.info("%s: %d in-between shapes not read (each blend shape's full-weight offsets are)", name, inbetweens)
    return labels, deltas


def _mesh(pxr, file: str, prim, xf_cache, Usd) -> SceneMesh | None:
    UsdGeom = pxr.UsdGeom
    mesh = UsdGeom.Mesh(prim)
    where = f"{file}: mesh {prim.GetPath()}"
    points = _value(mesh.GetPointsAttr(), Usd)
    if points is None:
        log.warning("%s has no points; skipped", where)
        return None
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    counts = _value(mesh.GetFaceVertexCountsAttr(), Usd)
    corners = _value(mesh.GetFaceVertexIndicesAttr(), Usd)
    counts = np.zeros(0, np.int64) if counts is None else np.asarray(counts, dtype=np.int64).ravel()
    corners = np.zeros(0, np.int64) if corners is None else np.asarray(corners, dtype=np.int64).ravel()
    faces = _triangles(where, counts, corners, len(points))
    if mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
        faces = faces[:, [0, 2, 1]]
    m = np.array(xf_cache.GetLocalToWorldTransform(prim), dtype=np.float64).reshape(4, 4)
    if not np.isfinite(m).all():
        raise InputError(f"{where}: its world transform is not finite")
    with np.errstate(over="ignore", invalid="ignore"):
        world = points @ m[:3, :3] + m[3, :3]
    labels, deltas = _blend_shapes(pxr, where, prim, len(points), m[:3, :3])
    return SceneMesh(name=prim.GetName(), points=world, faces=faces, labels=labels, deltas=deltas,
                     aliases=(str(prim.GetPath()),))


def _scene_meshes(pxr, path: Path, stage) -> list[SceneMesh]:
    Usd, UsdGeom = pxr.Usd, pxr.UsdGeom
    xf_cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    out = []
    for prim in stage.Traverse(Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)):
        if prim.HasAuthoredMetadata("clips") or prim.HasAuthoredMetadata("clipSets"):
            raise InputError(f"{path.name}: {prim.GetPath()} has value clips (other files read at playback); "
                             "not read")
        if prim.IsA(UsdGeom.Mesh):
            mesh = _mesh(pxr, path.name, prim, xf_cache, Usd)
            if mesh is not None:
                out.append(mesh)
    counts: dict[str, int] = {}
    for m in out:
        counts[m.name] = counts.get(m.name, 0) + 1
    for m in out:
        if counts[m.name] > 1:
            m.name = m.aliases[0]
    return out


def read_usd_here(path, *, meshes=None, targets=None) -> UsdRig:
    """:func:`read_usd_rig` in this process (the child of :mod:`._isolated`; a crash in the library is this process's)."""
    return _read(path, meshes=meshes, targets=targets)


def read_usd_rig(path, *, meshes=None, targets=None) -> UsdRig:
    """Read a rig from a USD stage: every mesh's points, triangles and UsdSkel blend shapes, in world space.

    Parameters
    ----------
    path : str or Path
        A ``.usd``, ``.usda``, ``.usdc`` or ``.usdz`` file.
    meshes : str or list of str, optional
        Glob patterns on mesh prim names or paths (``Face*``, ``/Character/*``). Default: every mesh that
        has blend shapes. Each pattern must match a mesh.
    targets : str or list of str, optional
        Glob patterns on blend shape names (the ``skel:blendShapes`` tokens, or ``mesh/name``).

    Returns
    -------
    UsdRig
        ``neutral`` (V, 3), ``faces`` (F, 3), ``deltas`` (K, V, 3) float64 in the stage's units; the stage's
        ``meters_per_unit`` and ``up_axis``.

    Raises
    ------
    InputError
        One line: a corrupt or truncated file, a layer outside the rig's folder, a malformed mesh or blend
        shape, no blend shapes, a pattern that matches nothing.
    MissingExtraError
        usd-core is not installed (``pip install 'retarget[usd]'``).

    Notes
    -----
    usd-core runs in a child process (:mod:`._isolated`): it can abort or allocate without bound on a hostile
    file, which then costs one InputError line, not the process. Starting it costs about 0.5 s.
    """
    path = Path(path)
    if importlib.util.find_spec("pxr") is None:
        raise MissingExtraError(f"{path.name}: {_MISSING}")
    if not path.is_file():
        raise InputError(f"{path}: rig file not found")
    return read_isolated("usd", path, "usd-core", UsdRig, meshes=meshes, targets=targets)


def _read(path, *, meshes=None, targets=None) -> UsdRig:
    path = Path(path)
    pxr = _pxr(path)
    if not path.is_file():
        raise InputError(f"{path}: rig file not found")
    try:  # a crate file's values are read when asked for: its errors come at any Get
        stage, files = _open(pxr, path)
        scene = _scene_meshes(pxr, path, stage)
        mpu = float(pxr.UsdGeom.GetStageMetersPerUnit(stage))
        up = str(pxr.UsdGeom.GetStageUpAxis(stage))
        authored = pxr.UsdGeom.StageHasAuthoredMetersPerUnit(stage)
        log.info("%s: metersPerUnit %g (%s), upAxis %s; coordinates as stored", path.name, mpu,
                 "authored" if authored else "not authored: USD's fallback", up)
        return assemble(path.name, scene, mesh_patterns=meshes, targets=targets, kind="usd", rig_class=UsdRig,
                        meters_per_unit=mpu, up_axis=up, layers=files)
    except pxr.Tf.ErrorException as exc:
        raise _usd_error(path, exc) from None


__all__ = ["USD_EXTS", "UsdRig", "read_usd_here", "read_usd_rig"]
