"""USD export through Pixar's ``usd-core`` (the optional extra ``usd``): UsdSkel blendshapes or a point cache.

Two layouts, both with the stage's ``timeCodesPerSecond`` (and
``framesPerSecond``) set to the take's frame rate and one time code per
frame (0 to T-1):

- **UsdSkel character** (a rig): ``/Character`` is a ``SkelRoot`` holding the
  neutral ``Mesh`` with one ``BlendShape`` child per shape (``offsets`` and,
  for shapes that move only some vertices, ``pointIndices``), a ``Skeleton``
  with one root joint the mesh is rigidly bound to, and a ``SkelAnimation``
  whose ``blendShapeWeights`` are time-sampled at every frame (UsdSkel
  schema, Pixar 2019-2025).
- **point cache** (no rig): ``/Character`` is an ``Xform`` holding a ``Mesh``
  whose ``points`` (and ``extent``) are time-sampled at every frame.

Texture coordinates are written as the face-varying primvar ``st`` (indexed).
The head motion, when given, is the time-sampled ``xformOp:transform`` of
``/Character``.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

import numpy as np

from ..errors import InputError, ShapeError

#: One-line error when ``pxr`` is missing.
MISSING = "format usd needs usd-core, the optional extra 'usd': pip install 'retarget[usd]' (or pip install usd-core)"


def require_pxr():
    """Import ``pxr``; an :class:`~retarget_cli.errors.InputError` naming the extra when usd-core is missing."""
    try:
        from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt  # noqa: F401
    except ImportError:
        raise InputError(MISSING) from None
    import pxr

    return pxr


def _valid_names(names) -> list[str]:
    """Prim names for *names*: valid USD identifiers, unique (``_2``, ``_3`` ... appended)."""
    from pxr import Tf

    out, seen = [], set()
    for n in names:
        base = Tf.MakeValidIdentifier(str(n))
        name, k = base, 2
        while name in seen:
            name, k = f"{base}_{k}", k + 1
        seen.add(name)
        out.append(name)
    return out


def _matrices(transforms):
    """(T, 3, 4) similarities ``X' = A[:, :3] X + A[:, 3]`` as USD row-vector 4x4 matrices."""
    from pxr import Gf

    A = np.asarray(transforms, dtype=np.float64)
    out = []
    for a in A:
        M = np.eye(4)
        M[:3, :3] = a[:, :3].T
        M[3, :3] = a[:, 3]
        out.append(Gf.Matrix4d(*M.ravel().tolist()))
    return out


@contextlib.contextmanager
def _new_stage(path: Path, fps: float, codes):
    """A new stage written to a temporary ``.usd`` beside *path*, renamed onto *path* when complete.

    *codes*: the time codes sampled (the source frame numbers), first and last the stage's start and end."""
    from pxr import Usd, UsdGeom

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".part.usd", dir=path.parent)
    os.close(fd)
    os.unlink(tmp)  # Usd creates it
    try:
        stage = Usd.Stage.CreateNew(tmp)
        stage.SetTimeCodesPerSecond(fps)
        stage.SetFramesPerSecond(fps)
        stage.SetStartTimeCode(float(codes[0]))
        stage.SetEndTimeCode(float(codes[-1]))
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        yield stage
        stage.GetRootLayer().Save()
        del stage
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _mesh(stage, prim_path: str, points, counts, corners, uv=None):
    from pxr import Sdf, UsdGeom, Vt

    mesh = UsdGeom.Mesh.Define(stage, prim_path)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(points, dtype=np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.asarray(counts, dtype=np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.asarray(corners, dtype=np.int32)))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateExtentAttr(UsdGeom.PointBased.ComputeExtent(mesh.GetPointsAttr().Get()))
    if uv is not None:
        values, indices = uv
        st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                     UsdGeom.Tokens.faceVarying)
        st.Set(Vt.Vec2fArray.FromNumpy(np.asarray(values, dtype=np.float32)))
        st.SetIndices(Vt.IntArray.FromNumpy(np.asarray(indices, dtype=np.int32)))
    return mesh


def _check(points, counts, corners, T_weights=None):
    P = np.asarray(points)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ShapeError(f"points: expected shape (N, 3), got {P.shape}")
    counts, corners = np.asarray(counts), np.asarray(corners)
    if counts.sum() != corners.size or (corners.size and (corners.min() < 0 or corners.max() >= len(P))):
        raise ShapeError("faces: corner counts and vertex ids do not match the points")
    return P


def _codes(frames, T: int) -> list:
    """Time codes of the *T* samples: the source frame numbers *frames* (default 0 … T−1), checked."""
    codes = np.arange(T) if frames is None else np.asarray(frames)
    if codes.shape != (T,) or np.any(np.diff(codes) <= 0):
        raise ShapeError(f"frames: expected {T} increasing frame numbers, got shape {codes.shape}")
    return [float(c) for c in codes]


def write_usd_skel(path, *, points, counts, corners, shapes, names, weights, fps: float, uv=None,
                   transforms=None, name: str = "face", frames=None) -> None:
    """Write a UsdSkel character: neutral mesh, one BlendShape per shape, time-sampled weights.

    At time code ``t`` the mesh is ``points + Σ_m weights[t, m] shape_m``
    (``UsdSkelBlendShapeQuery`` evaluation), then placed by
    ``transforms[t]`` when given.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        The neutral.
    counts : ndarray, shape (F,)
        Corners per face.
    corners : ndarray, shape (sum(counts),)
        0-based vertex ids of the face corners.
    shapes : ndarray, shape (M, N, 3)
        Displacements; each is stored sparsely (``pointIndices``) when it
        moves fewer than all vertices.
    names : sequence of str, length M
        The ``blendShapes`` tokens (BlendShape prims get valid identifiers of them).
    weights : ndarray, shape (T, M)
    fps : float
    uv : (ndarray (U, 2), ndarray (C,)), optional
        Face-varying texture coordinates: values and per-corner indices.
    transforms : ndarray, shape (T, 3, 4), optional
        Per-frame similarity of the character (head motion).
    frames : ndarray, shape (T,), optional
        The source frame number of each row, its time code (so time code / *fps* is the source's time);
        default 0 … T−1.
    """
    require_pxr()
    from pxr import Gf, Usd, UsdGeom, UsdSkel, Vt

    P = _check(points, counts, corners)
    D = np.asarray(shapes, dtype=np.float64)
    W = np.asarray(weights, dtype=np.float64)
    if D.ndim != 3 or D.shape[1:] != P.shape:
        raise ShapeError(f"shapes: expected shape (M, {len(P)}, 3), got {D.shape}")
    if W.ndim != 2 or W.shape[1] != len(D) or len(W) < 1 or len(names) != len(D):
        raise ShapeError(f"weights: expected shape (T, {len(D)}) and {len(D)} names, got {W.shape}, {len(names)}")
    if not fps > 0:
        raise ShapeError(f"fps: expected > 0, got {fps}")
    T = len(W)
    codes = _codes(frames, T)
    tokens = [str(n) for n in names]
    with _new_stage(path, fps, codes) as stage:
        root = UsdSkel.Root.Define(stage, "/Character")
        stage.SetDefaultPrim(root.GetPrim())
        if transforms is not None:
            op = UsdGeom.Xformable(root).AddTransformOp()
            for t, M in enumerate(_matrices(transforms)):
                op.Set(M, Usd.TimeCode(codes[t]))
        skel = UsdSkel.Skeleton.Define(stage, "/Character/Skel")
        skel.CreateJointsAttr(["root"])
        skel.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1)]))
        skel.CreateRestTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1)]))
        anim = UsdSkel.Animation.Define(stage, "/Character/Skel/Anim")
        anim.CreateJointsAttr(["root"])
        anim.CreateTranslationsAttr(Vt.Vec3fArray([Gf.Vec3f(0, 0, 0)]))
        anim.CreateRotationsAttr(Vt.QuatfArray([Gf.Quatf(1, 0, 0, 0)]))
        anim.CreateScalesAttr(Vt.Vec3hArray([Gf.Vec3h(1, 1, 1)]))
        anim.CreateBlendShapesAttr(tokens)
        attr = anim.CreateBlendShapeWeightsAttr()
        for t in range(T):
            attr.Set(Vt.FloatArray.FromNumpy(W[t].astype(np.float32)), Usd.TimeCode(codes[t]))
        UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])
        mesh_path = f"/Character/{_valid_names([name])[0]}"
        mesh = _mesh(stage, mesh_path, P, counts, corners, uv)
        binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
        binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
        binding.CreateJointIndicesPrimvar(True, 1).Set(Vt.IntArray([0]))
        binding.CreateJointWeightsPrimvar(True, 1).Set(Vt.FloatArray([1.0]))
        binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1))
        binding.CreateBlendShapesAttr(tokens)
        targets = []
        for prim_name, d in zip(_valid_names(tokens), D):
            shape = UsdSkel.BlendShape.Define(stage, f"{mesh_path}/{prim_name}")
            moved = np.flatnonzero(np.any(d != 0, axis=1))
            if len(moved) == len(P):
                shape.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(d.astype(np.float32)))
            else:
                shape.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(d[moved].astype(np.float32)))
                shape.CreatePointIndicesAttr(Vt.IntArray.FromNumpy(moved.astype(np.int32)))
            targets.append(shape.GetPath())
        binding.CreateBlendShapeTargetsRel().SetTargets(targets)


def write_usd_points(path, *, positions, counts, corners, fps: float, uv=None, transforms=None,
                     name: str = "face", frames=None) -> None:
    """Write a point cache: a mesh whose ``points`` are time-sampled at every frame.

    Parameters
    ----------
    positions : ndarray, shape (T, N, 3)
        The mesh at every frame (``points`` at time code ``t``).
    counts, corners, fps, uv, transforms, frames
        As :func:`write_usd_skel`.
    """
    require_pxr()
    from pxr import Usd, UsdGeom, Vt

    X = np.asarray(positions, dtype=np.float64)
    if X.ndim != 3 or X.shape[2] != 3 or len(X) < 1:
        raise ShapeError(f"positions: expected shape (T, N, 3), got {X.shape}")
    _check(X[0], counts, corners)
    if not fps > 0:
        raise ShapeError(f"fps: expected > 0, got {fps}")
    codes = _codes(frames, len(X))
    with _new_stage(path, fps, codes) as stage:
        root = UsdGeom.Xform.Define(stage, "/Character")
        stage.SetDefaultPrim(root.GetPrim())
        if transforms is not None:
            op = root.AddTransformOp()
            for t, M in enumerate(_matrices(transforms)):
                op.Set(M, Usd.TimeCode(codes[t]))
        mesh = _mesh(stage, f"/Character/{_valid_names([name])[0]}", X[0], counts, corners, uv)
        pts, ext = mesh.GetPointsAttr(), mesh.GetExtentAttr()
        for t, x in enumerate(X):
            arr = Vt.Vec3fArray.FromNumpy(x.astype(np.float32))
            pts.Set(arr, Usd.TimeCode(codes[t]))
            ext.Set(UsdGeom.PointBased.ComputeExtent(arr), Usd.TimeCode(codes[t]))


__all__ = ["MISSING", "require_pxr", "write_usd_points", "write_usd_skel"]
