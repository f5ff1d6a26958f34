"""In the child process (:mod:`._child`): the animated copy of a USD character, written into its temporary folder.

What is written and why: :mod:`retarget_cli.io.usd_animation` (the parent's side). The stage is opened as the
reader opens it (:mod:`.usd`: layers outside the rig's folder and value clips refused), its meshes and blend shapes
chosen with the same ``meshes=``/``targets=`` rules (:mod:`._scene`), so target ``j`` of the weights is the
reader's target ``j``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ...errors import InputError
from . import usd
from ._scene import _plan

log = logging.getLogger(__name__)

SKELETON_NAME, ANIMATION_NAME, JOINT_NAME = "RetargetSkeleton", "RetargetAnimation", "root"
SHARED_TOKEN_TOL = 1e-9
_ROOT_TYPES = ("", "Xform", "Scope")


def _fresh_child(stage, parent, name: str):
    """A child path of *parent* named *name* (``name_2`` ... when taken)."""
    path, n = parent.AppendChild(name), 2
    while stage.GetPrimAtPath(path):
        path, n = parent.AppendChild(f"{name}_{n}"), n + 1
    return path


class _Binder:
    """Binds meshes to skeletons with animations on the flattened stage; collects each animation's tokens."""

    def __init__(self, pxr, name: str, stage):
        self.pxr, self.name, self.stage = pxr, name, stage
        self.cache = pxr.UsdGeom.XformCache(pxr.Usd.TimeCode.Default())
        self.rigid: dict = {}  # SkelRoot path -> (skeleton, animation) added here
        self.tracks: dict = {}  # animation path -> list of (token, target j, mesh path)

    def _skel_root(self, prim):
        UsdSkel = self.pxr.UsdSkel
        up = prim.GetParent()
        while up and not up.IsPseudoRoot():
            if up.IsA(UsdSkel.Root):
                return up
            up = up.GetParent()
        parent = prim.GetParent()
        if parent.IsPseudoRoot():
            raise InputError(f"{self.name}: mesh {prim.GetPath()} is at the root of the stage; UsdSkel animates "
                             "blend shapes under a SkelRoot, put it under an Xform")
        if parent.GetTypeName() not in _ROOT_TYPES:
            raise InputError(f"{self.name}: mesh {prim.GetPath()} is bound to no skeleton and its parent is a "
                             f"{parent.GetTypeName()}, not an Xform, Scope or SkelRoot to bind it under")
        if any(p.IsA(UsdSkel.Root) for p in self.pxr.Usd.PrimRange(parent) if p != parent):
            raise InputError(f"{self.name}: mesh {prim.GetPath()} is bound to no skeleton and {parent.GetPath()} "
                             "holds a SkelRoot already; SkelRoots are not nested")
        log.info("%s: %s retyped SkelRoot (was %s) for the blend-shape animation of %s", self.name,
                 parent.GetPath(), parent.GetTypeName() or "typeless", prim.GetName())
        parent.SetTypeName("SkelRoot")
        return parent

    def _rigid_skeleton(self, root):
        pxr = self.pxr
        Gf, UsdSkel, Vt = pxr.Gf, pxr.UsdSkel, pxr.Vt
        key = str(root.GetPath())
        if key not in self.rigid:
            skel = UsdSkel.Skeleton.Define(self.stage, _fresh_child(self.stage, root.GetPath(), SKELETON_NAME))
            skel.CreateJointsAttr([JOINT_NAME])
            skel.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1)]))
            skel.CreateRestTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1)]))
            anim = self._new_animation(skel)
            self.rigid[key] = (skel, anim)
        return self.rigid[key]

    def _new_animation(self, skel):
        UsdSkel = self.pxr.UsdSkel
        anim = UsdSkel.Animation.Define(self.stage, _fresh_child(self.stage, skel.GetPath(), ANIMATION_NAME))
        UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])
        return anim.GetPrim()

    def bind(self, prim, labels: list, rows: list):
        """Bind mesh *prim* so its blend shapes ``labels[k]`` (``(k, j)`` in *rows*) are animated as target ``j``."""
        pxr = self.pxr
        Gf, UsdSkel, Vt = pxr.Gf, pxr.UsdSkel, pxr.Vt
        where = f"{self.name}: mesh {prim.GetPath()}"
        if prim.IsInstanceProxy() or prim.IsInPrototype():
            raise InputError(f"{where} is inside an instance (shared by its instances); its blend shapes cannot be "
                             "animated one instance at a time")
        binding = UsdSkel.BindingAPI(prim)
        skel = binding.GetInheritedSkeleton()
        if skel:
            self._skel_root(prim)
            anim = UsdSkel.BindingAPI(skel.GetPrim()).GetInheritedAnimationSource()
            anim = anim if anim and anim.IsA(UsdSkel.Animation) else self._new_animation(skel)
        else:
            root = self._skel_root(prim)
            skel, anim = self._rigid_skeleton(root)
            binding = UsdSkel.BindingAPI.Apply(prim)
            binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
            binding.CreateJointIndicesPrimvar(True, 1).Set(Vt.IntArray([0]))
            binding.CreateJointWeightsPrimvar(True, 1).Set(Vt.FloatArray([1.0]))
            bind = self.cache.GetLocalToWorldTransform(prim) * self.cache.GetLocalToWorldTransform(
                skel.GetPrim()).GetInverse()
            binding.CreateGeomBindTransformAttr(Gf.Matrix4d(bind))
        tokens = [str(t) for t in (binding.GetBlendShapesAttr().Get() or [])]
        track = self.tracks.setdefault(anim.GetPath(), [])
        for k, j in rows:
            if not tokens[k]:
                raise InputError(f"{where}: blend shape {k} has an empty name in skel:blendShapes; an animation "
                                 "drives shapes by name")
            track.append((tokens[k], j, prim.GetPath()))


def _weights_of(name: str, track: list, W: np.ndarray) -> tuple[list[str], np.ndarray]:
    """One animation's tokens and their (T, n) weights; two meshes' targets of one token must agree."""
    tokens, cols, first = [], [], {}
    for token, j, mesh in track:
        if token in first:
            j0, mesh0 = first[token]
            if np.max(np.abs(W[:, j] - W[:, j0]), initial=0.0) > SHARED_TOKEN_TOL:
                raise InputError(f"{name}: blend shape {token!r} of {mesh} and of {mesh0} follow one animation, "
                                 "and the sliders drive them differently; choose one with targets: or give them "
                                 "one slider")
            continue
        first[token] = (j, mesh)
        tokens.append(token)
        cols.append(j)
    return tokens, W[:, cols]


def _animate(pxr, name: str, anim_prim, tokens: list[str], weights: np.ndarray, codes: list):
    """Author ``blendShapes`` and time-sampled ``blendShapeWeights`` (row t at time code ``codes[t]``) on the animation."""
    Usd, UsdSkel, Vt = pxr.Usd, pxr.UsdSkel, pxr.Vt
    anim = UsdSkel.Animation(anim_prim)
    T = len(weights)
    old_tokens = [str(t) for t in (anim.GetBlendShapesAttr().Get() or [])]
    kept = [t for t in old_tokens if t not in tokens]
    if kept:
        attr = anim.GetBlendShapeWeightsAttr()
        old = np.zeros((T, len(kept)))
        for t in range(T):
            value = attr.Get(Usd.TimeCode(codes[t]))
            if value is not None and len(value) == len(old_tokens):
                row = np.asarray(value, dtype=np.float64)
                old[t] = [row[old_tokens.index(tok)] for tok in kept]
        log.info("%s: %s keeps its own weights of %d blend shapes no slider drives", name, anim_prim.GetPath(),
                 len(kept))
        tokens, weights = tokens + kept, np.concatenate([weights, old], axis=1)
    anim.CreateBlendShapesAttr().Set(tokens)
    attr = anim.CreateBlendShapeWeightsAttr()
    attr.Clear()
    for t in range(T):
        attr.Set(Vt.FloatArray.FromNumpy(weights[t].astype(np.float32)), Usd.TimeCode(codes[t]))


def _absolute_assets(pxr, source: Path, stage, copy, package: str | None) -> set:
    """Asset paths of the copy as the source resolved them (absolute; inside a ``.usdz`` source, package-relative).

    Returns the package-relative names used (the files a ``.usdz`` copy carries).
    """
    Sdf, Usd = pxr.Sdf, pxr.Usd
    inner, n = set(), 0

    def fix(value):
        nonlocal n
        if not isinstance(value, Sdf.AssetPath) or not value.resolvedPath:
            return value
        resolved = value.resolvedPath
        if package and resolved.startswith(package + "["):
            resolved = resolved[len(package) + 1:-1]
            inner.add(resolved)
        n += resolved != value.path
        return Sdf.AssetPath(resolved)

    for prim in stage.Traverse():
        target = copy.GetPrimAtPath(prim.GetPath())
        if not target:
            continue
        for attr in prim.GetAttributes():
            if attr.GetTypeName() not in (Sdf.ValueTypeNames.Asset, Sdf.ValueTypeNames.AssetArray):
                continue
            out = target.GetAttribute(attr.GetName())
            for time in [Usd.TimeCode.Default(), *map(Usd.TimeCode, attr.GetTimeSamples())]:
                value = attr.Get(time)
                if value is None:
                    continue
                fixed = [fix(v) for v in value] if attr.GetTypeName() == Sdf.ValueTypeNames.AssetArray else fix(value)
                out.Set(Sdf.AssetPathArray(fixed) if isinstance(fixed, list) else fixed, time)
    if n:
        log.info("%s: %d asset paths (textures) written as the paths they resolve to", source.name, n)
    return inner


def _stage_time(pxr, name: str, layer, fps: float, codes: list):
    old = layer.timeCodesPerSecond if layer.HasTimeCodesPerSecond() else None
    if old is not None and abs(old - fps) > 1e-9:
        log.info("%s: timeCodesPerSecond %g replaced by the take's %g (other time samples of the file play at that "
                 "rate)", name, old, fps)
    layer.timeCodesPerSecond = fps
    layer.framesPerSecond = fps
    layer.startTimeCode = codes[0]
    layer.endTimeCode = codes[-1]


def _save(pxr, source: Path, copy_stage, inner: set, out: Path, suffix: str):
    Sdf = pxr.Sdf
    layer = copy_stage.GetRootLayer()
    if suffix != ".usdz":
        if not layer.Export(str(out / f"copy{suffix}")):
            raise InputError(f"{source.name}: usd-core could not write the animated copy")
        return
    root = out / "root.usdc"
    layer.Export(str(root))
    src = Sdf.ZipFile.Open(str(source))
    names = list(src.GetFileNames()) if src else []
    writer = Sdf.ZipFileWriter.CreateNew(str(out / "copy.usdz"))
    writer.AddFile(str(root), f"{source.stem}_animated.usdc")
    for n, member in enumerate(names[1:]):  # the first is the source's root layer, flattened into the copy's
        if member in inner:
            data = out / f"member{n}"
            data.write_bytes(bytes(src.GetFile(member)))
            writer.AddFile(str(data), member)
    writer.Save()


def animate_here(path, request: dict, out: Path) -> None:
    """Write ``out/copy.<suffix>``: the animated copy of the USD character *path* (in the child process).

    *request*: ``meshes``, ``targets`` (the reader's filters), ``target_names`` (the K names the parent's weights
    follow), ``fps``, ``codes`` (the T time codes), ``suffix``; ``out/weights.npy`` holds the (T, K) weights.
    """
    path, out = Path(path), Path(out)
    pxr = usd._pxr(path)
    W = np.load(out / "weights.npy")
    try:
        stage, _ = usd._open(pxr, path)
        chosen, table, unique = _plan(path.name, usd._scene_meshes(pxr, path, stage), request["meshes"],
                                     request["targets"])
        if list(unique) != list(request["target_names"]) or W.shape[1] != len(unique):
            raise InputError(f"{path.name}: changed since it was read as the rig (its blend shapes differ)")
        copy = pxr.Usd.Stage.Open(stage.Flatten())
        layer = copy.GetRootLayer()
        layer.documentation = stage.GetRootLayer().documentation
        package = str(path.resolve()) if request["suffix"] == ".usdz" else None
        inner = _absolute_assets(pxr, path, stage, copy, package)
        binder = _Binder(pxr, path.name, copy)
        rows: dict = {}
        for j, (i, k) in enumerate(table):
            rows.setdefault(i, []).append((k, j))
        for i, mesh_rows in rows.items():
            binder.bind(copy.GetPrimAtPath(chosen[i].aliases[0]), chosen[i].labels, mesh_rows)
        for anim_path, track in binder.tracks.items():
            tokens, weights = _weights_of(path.name, track, W)
            _animate(pxr, path.name, copy.GetPrimAtPath(anim_path), tokens, weights, request["codes"])
        _stage_time(pxr, path.name, layer, float(request["fps"]), request["codes"])
        _save(pxr, path, copy, inner, out, request["suffix"])
    except pxr.Tf.ErrorException as exc:
        raise usd._usd_error(path, exc) from None
    log.info("%s: animated copy: %d frames of %d blend shapes on %d meshes, %d animations", path.name, len(W),
             W.shape[1], len(rows), len(binder.tracks))
