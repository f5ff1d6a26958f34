"""The animated copy of a USD character (apply --format same): UsdSkel blend-shape weights, read back with pxr.

Small stages written here: a head and teeth under transformed Xforms sharing the slider ``jawOpen``, bound to no
skeleton, an eye without blend shapes, a texture asset; a rig the project's UsdSkel writer made (already a
SkelRoot with a skeleton and an animation). Each copy is checked with pxr's own UsdSkel evaluation
(``UsdSkel.Cache`` weights per mesh, and ``UsdSkel.BakeSkinning`` points against the rig posed at the curves),
and read back through the project's USD reader.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from retarget_cli.errors import InputError, ParameterError
from retarget_cli.io.exports import EXPORTS, SameExport
from retarget_cli.io.rig import load_rig
from retarget_cli.io.rig.usd import read_usd_rig
from retarget_cli.io.usd import write_usd_skel
from retarget_cli.io.usd_animation import copy_name, target_weights, write_animated_usd

pytest.importorskip("pxr", reason="usd-core (the 'usd' extra) is not installed")
from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, UsdSkel, UsdUtils  # noqa: E402

from tests.unit.io.rig.test_usd_reader import TRI, _mesh  # noqa: E402

FPS, T = 24.0, 7


def _character(path: Path, *, teeth_parent="Teeth"):
    """Head (2 shapes) and teeth (jawOpen) bound to no skeleton, an eye, a material with a texture beside the file."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.Xform.Define(stage, "/Char").AddTranslateOp().Set(Gf.Vec3d(1, 2, 3))
    head = _mesh(stage, "/Char/Head/Head", TRI, [[0, 1, 3, 2]],
                 {"jawOpen": ([[0, -1, 0], [0, -2, 0]], [0, 1]), "blink": ([[0, 0, 1]] * 4, None)},
                 translate=(10, 0, 0), scale=(2, 2, 2))
    _mesh(stage, f"/Char/{teeth_parent}/Teeth", TRI[:3], [[0, 1, 2]], {"jawOpen": ([[0, -0.5, 0]], [2])},
          translate=(0, 5, 0) if teeth_parent != "Head" else None)
    _mesh(stage, "/Char/Eye/Eye", TRI, [[0, 1, 2], [1, 3, 2]], {})
    material = UsdShade.Material.Define(stage, "/Char/Looks/Skin")
    shader = UsdShade.Shader.Define(stage, "/Char/Looks/Skin/Tex")
    shader.CreateIdAttr("UsdUVTexture")
    shader.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath("tex/skin.png"))
    material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "rgb")
    UsdShade.MaterialBindingAPI.Apply(head.GetPrim()).Bind(material)
    stage.SetDefaultPrim(stage.GetPrimAtPath("/Char"))
    stage.GetRootLayer().Save()
    (path.parent / "tex").mkdir(exist_ok=True)
    (path.parent / "tex" / "skin.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 16)
    return path


def _ctx(tmp_path, rig_file, curves=None, seed=0):
    rig = load_rig(rig_file)
    C = np.random.default_rng(seed).uniform(-0.2, 1.2, (T, rig.n_sliders)) if curves is None else curves
    out = tmp_path / "out"
    out.mkdir(exist_ok=True)
    return SimpleNamespace(out=out, fps=FPS, rig=rig, curves=C, rig_file=rig_file, weights=tmp_path / "w.npz",
                           targets=tmp_path / "t.yaml", landmarks=None)


def _mesh_weights(stage) -> dict:
    """UsdSkel's own evaluation: mesh path -> (blend shape order, (T, n) weights the mesh receives)."""
    cache, out = UsdSkel.Cache(), {}
    for prim in stage.Traverse():
        if not prim.IsA(UsdSkel.Root):
            continue
        root = UsdSkel.Root(prim)
        cache.Populate(root, Usd.PrimDefaultPredicate)
        for binding in cache.ComputeSkelBindings(root, Usd.PrimDefaultPredicate):
            anim = cache.GetSkelQuery(binding.GetSkeleton()).GetAnimQuery()
            for target in binding.GetSkinningTargets():
                mapper = target.GetBlendShapeMapper()
                W = [list(mapper.Remap(anim.ComputeBlendShapeWeights(Usd.TimeCode(t)))) for t in range(T)]
                out[str(target.GetPrim().GetPath())] = ([str(s) for s in target.GetBlendShapeOrder()], np.array(W))
    return out


def _baked_points(stage, paths, t) -> np.ndarray:
    """World-space points of *paths* at time *t* after ``UsdSkel.BakeSkinning`` (blend shapes and skinning)."""
    pts = []
    for path in paths:
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(path))
        p = np.asarray(mesh.GetPointsAttr().Get(Usd.TimeCode(t)), dtype=np.float64)
        M = np.array(mesh.ComputeLocalToWorldTransform(Usd.TimeCode(t)))
        pts.append(p @ M[:3, :3] + M[3, :3])
    return np.concatenate(pts)


def _prims(stage) -> set:
    return {str(p.GetPath()) for p in stage.Traverse()}


def test_copy_of_meshes_bound_to_no_skeleton(tmp_path):
    src = _character(tmp_path / "char.usda")
    ctx = _ctx(tmp_path, src)
    assert EXPORTS["same"] is SameExport
    SameExport.check_context(ctx)
    written = SameExport(ctx).finish()
    assert written == [ctx.out / "char_animated.usda"] and copy_name(src) == "char_animated.usda"
    copy, source = Usd.Stage.Open(str(written[0])), Usd.Stage.Open(str(src))
    # the same prims, and only the skeletons and animations UsdSkel needs besides
    added = _prims(copy) - _prims(source)
    assert _prims(source) <= _prims(copy)
    assert added == {"/Char/Head/RetargetSkeleton", "/Char/Head/RetargetSkeleton/RetargetAnimation",
                     "/Char/Teeth/RetargetSkeleton", "/Char/Teeth/RetargetSkeleton/RetargetAnimation"}
    meshes = lambda s: sorted(str(p.GetPath()) for p in s.Traverse() if p.IsA(UsdGeom.Mesh))  # noqa: E731
    assert meshes(copy) == meshes(source) == ["/Char/Eye/Eye", "/Char/Head/Head", "/Char/Teeth/Teeth"]
    assert copy.GetPrimAtPath("/Char/Head").GetTypeName() == "SkelRoot"
    assert copy.GetTimeCodesPerSecond() == FPS and (copy.GetStartTimeCode(), copy.GetEndTimeCode()) == (0, T - 1)
    # UsdSkel's evaluation: each mesh's weights are the curves (clipped to [0, 1]) at every frame
    C = np.clip(ctx.curves, 0, 1)
    names = list(ctx.rig.names)
    got = _mesh_weights(copy)
    assert got["/Char/Head/Head"][0] == ["jawOpen", "blink"] and got["/Char/Teeth/Teeth"][0] == ["jawOpen"]
    np.testing.assert_allclose(got["/Char/Head/Head"][1], C[:, [names.index("jawOpen"), names.index("blink")]],
                               rtol=0, atol=1e-6)
    np.testing.assert_allclose(got["/Char/Teeth/Teeth"][1][:, 0], C[:, names.index("jawOpen")], rtol=0, atol=1e-6)
    anim = UsdSkel.Animation(copy.GetPrimAtPath("/Char/Head/RetargetSkeleton/RetargetAnimation"))
    assert anim.GetBlendShapeWeightsAttr().GetTimeSamples() == list(range(T))
    # the skinned meshes stay where they were: baked, they are the rig posed at the curves
    assert UsdSkel.BakeSkinning(copy.Traverse())
    for t in range(T):
        np.testing.assert_allclose(_baked_points(copy, ["/Char/Head/Head", "/Char/Teeth/Teeth"], t),
                                   ctx.rig.evaluate(C[t]), rtol=0, atol=1e-5)
    # the texture is still found from the copy's folder
    tex = copy.GetPrimAtPath("/Char/Looks/Skin/Tex").GetAttribute("inputs:file").Get()
    assert Path(tex.path) == (tmp_path / "tex" / "skin.png").resolve() and tex.resolvedPath
    # and the copy is a rig: the reader gives the source's geometry and blend shapes
    a, b = read_usd_rig(src), read_usd_rig(written[0])
    assert a.target_names == b.target_names and a.mesh_ranges == b.mesh_ranges and a.groups == b.groups
    np.testing.assert_array_equal(a.neutral, b.neutral)
    np.testing.assert_array_equal(a.deltas, b.deltas)


@pytest.mark.parametrize("suffix", [".usd", ".usdc"])
def test_copy_of_a_usdskel_character_keeps_its_skeleton_and_animation(tmp_path, suffix):
    rng = np.random.default_rng(4)
    P = rng.normal(0, 1, (12, 3))
    D = np.zeros((3, 12, 3))
    D[:, :4] = rng.normal(0, 0.2, (3, 4, 3))
    src = tmp_path / f"skel{suffix}"
    write_usd_skel(src if suffix == ".usd" else tmp_path / "w.usd", points=P, counts=[3, 3, 3, 3],
                   corners=np.arange(12), shapes=D, names=["jawOpen", "blink", "smile"],
                   weights=np.full((3, 3), 0.25), fps=30.0)
    if suffix != ".usd":
        Sdf.Layer.FindOrOpen(str(tmp_path / "w.usd")).Export(str(src))
    (tmp_path / "rig.yaml").write_text(f"source: {src.name}\ntargets: [jawOpen, blink]\n")
    ctx = _ctx(tmp_path, tmp_path / "rig.yaml", seed=2)
    assert list(ctx.rig.names) == ["jawOpen", "blink"]
    [path] = SameExport(ctx).finish()
    assert path == ctx.out / f"skel_animated{suffix}"
    first = path.read_bytes()
    assert SameExport(ctx).finish() == [path] and path.read_bytes() == first  # deterministic
    copy, source = Usd.Stage.Open(str(path)), Usd.Stage.Open(str(src))
    assert _prims(copy) == _prims(source)  # bound already: nothing added
    anim = UsdSkel.Animation(copy.GetPrimAtPath("/Character/Skel/Anim"))
    assert list(anim.GetJointsAttr().Get()) == ["root"]  # its joint animation kept
    assert list(anim.GetBlendShapesAttr().Get()) == ["jawOpen", "blink", "smile"]
    W = np.array([list(anim.GetBlendShapeWeightsAttr().Get(Usd.TimeCode(t))) for t in range(T)])
    np.testing.assert_allclose(W[:, :2], np.clip(ctx.curves, 0, 1), rtol=0, atol=1e-6)
    np.testing.assert_allclose(W[:, 2], 0.25, rtol=0, atol=1e-7)  # a shape no slider drives keeps its weight
    got = _mesh_weights(copy)["/Character/face"]
    np.testing.assert_allclose(got[1][:, :2], np.clip(ctx.curves, 0, 1), rtol=0, atol=1e-6)
    b = read_usd_rig(path)
    np.testing.assert_allclose(b.neutral, P, atol=1e-6)
    np.testing.assert_allclose(b.deltas, D, atol=1e-6)


def test_usdz_copy_carries_the_package_files(tmp_path):
    (tmp_path / "pkg").mkdir()
    src = _character(tmp_path / "pkg" / "char.usda")
    assert UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(src)), str(tmp_path / "char.usdz"))
    members = list(Sdf.ZipFile.Open(str(tmp_path / "char.usdz")).GetFileNames())
    assert len(members) == 2 and members[1].endswith("skin.png")  # usd-core names it 0/skin.png
    ctx = _ctx(tmp_path, tmp_path / "char.usdz", seed=5)
    [path] = SameExport(ctx).finish()
    assert path.name == "char_animated.usdz"
    zf = Sdf.ZipFile.Open(str(path))
    assert list(zf.GetFileNames()) == ["char_animated.usdc", members[1]]
    assert bytes(zf.GetFile(members[1])) == (tmp_path / "pkg" / "tex" / "skin.png").read_bytes()
    copy = Usd.Stage.Open(str(path))
    tex = copy.GetPrimAtPath("/Char/Looks/Skin/Tex").GetAttribute("inputs:file").Get()
    assert tex.path == members[1] and tex.resolvedPath.endswith(f"char_animated.usdz[{members[1]}]")
    got = _mesh_weights(copy)
    np.testing.assert_allclose(got["/Char/Teeth/Teeth"][1][:, 0],
                               np.clip(ctx.curves, 0, 1)[:, list(ctx.rig.names).index("jawOpen")], atol=1e-6)
    np.testing.assert_array_equal(read_usd_rig(path).deltas, read_usd_rig(tmp_path / "char.usdz").deltas)


def test_two_meshes_of_one_animation_driven_differently_is_one_line(tmp_path):
    _character(tmp_path / "char.usda", teeth_parent="Head")  # teeth beside the head: one SkelRoot, one animation
    (tmp_path / "rig.yaml").write_text("source: char.usda\nsliders: targets\n")  # Head/jawOpen, Teeth/jawOpen apart
    ctx = _ctx(tmp_path, tmp_path / "rig.yaml")
    with pytest.raises(InputError) as info:
        SameExport(ctx).finish()
    assert str(info.value).startswith("char.usda: blend shape 'jawOpen' of /Char/Head/Teeth and of /Char/Head/Head")
    assert "\n" not in str(info.value) and not any(ctx.out.iterdir())
    # one slider for both: one weight, written once
    (tmp_path / "rig.yaml").write_text("source: char.usda\n")
    ctx = _ctx(tmp_path, tmp_path / "rig.yaml")
    [path] = SameExport(ctx).finish()
    got = _mesh_weights(Usd.Stage.Open(str(path)))
    j = list(ctx.rig.names).index("jawOpen")
    for mesh in ("/Char/Head/Head", "/Char/Head/Teeth"):
        np.testing.assert_allclose(got[mesh][1][:, 0], np.clip(ctx.curves[:, j], 0, 1), atol=1e-6)


def test_a_mesh_at_the_root_of_the_stage_is_one_line(tmp_path):
    stage = Usd.Stage.CreateNew(str(tmp_path / "root.usda"))
    mesh = UsdGeom.Mesh.Define(stage, "/Face")
    mesh.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (0, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([3]), mesh.CreateFaceVertexIndicesAttr([0, 1, 2])
    shape = UsdSkel.BlendShape.Define(stage, "/Face/jaw")
    shape.CreateOffsetsAttr([(0, -1, 0)]), shape.CreatePointIndicesAttr([0])
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateBlendShapesAttr(["jawOpen"]), binding.CreateBlendShapeTargetsRel().SetTargets([shape.GetPath()])
    stage.GetRootLayer().Save()
    ctx = _ctx(tmp_path, tmp_path / "root.usda")
    with pytest.raises(InputError, match=r"^root.usda: mesh /Face is at the root of the stage; UsdSkel animates"):
        SameExport(ctx).finish()
    assert not any(ctx.out.iterdir())


def test_target_weights_and_argument_checks(tmp_path):
    W = target_weights(np.array([[0.5, 2.0], [-1.0, 0.2]]), ["a", "b"], {"a": [("x", 1.0), ("y", 0.5)],
                                                                        "b": [("y", 1.0)]},
                       ["x", "y", "z"], lower=[0, 0], upper=[1, 1])
    np.testing.assert_allclose(W, [[0.5, 1.25, 0], [0, 0.2, 0]])
    with pytest.raises(ParameterError, match="curves: expected"):
        target_weights(np.zeros((3, 1)), ["a", "b"], {}, ["x"])
    with pytest.raises(ParameterError, match="'a' binds 'w', not a blend shape of the file"):
        target_weights(np.zeros((3, 1)), ["a"], {"a": [("w", 1.0)]}, ["x"])
    src = _character(tmp_path / "char.usda")
    with pytest.raises(ParameterError, match="keeps its suffix"):
        write_animated_usd(tmp_path / "o.usdc", src, np.zeros((2, 3)), ["a", "b", "c"], 30.0)
    with pytest.raises(ParameterError, match="fps"):
        write_animated_usd(tmp_path / "o.usda", src, np.zeros((2, 3)), ["a", "b", "c"], 0.0)
    with pytest.raises(InputError, match="changed since it was read"):
        write_animated_usd(tmp_path / "o.usda", src, np.zeros((2, 3)), ["a", "b", "c"], 30.0)
    assert not (tmp_path / "o.usda").exists()


def test_time_codes_are_the_source_frame_numbers(tmp_path):
    src = _character(tmp_path / "char.usda")
    ctx = _ctx(tmp_path, src, seed=7)
    ctx.frames, ctx.source_fps = np.array([3, 4, 5, 8, 9, 10, 12]), 25.0  # a sequence with gaps, as apply passes
    [path] = SameExport(ctx).finish()
    copy = Usd.Stage.Open(str(path))
    assert copy.GetTimeCodesPerSecond() == 25.0 and (copy.GetStartTimeCode(), copy.GetEndTimeCode()) == (3, 12)
    anim = UsdSkel.Animation(copy.GetPrimAtPath("/Char/Teeth/RetargetSkeleton/RetargetAnimation"))
    assert anim.GetBlendShapeWeightsAttr().GetTimeSamples() == [3, 4, 5, 8, 9, 10, 12]
    W = [anim.GetBlendShapeWeightsAttr().Get(Usd.TimeCode(int(f)))[0] for f in ctx.frames]
    np.testing.assert_allclose(W, np.clip(ctx.curves[:, list(ctx.rig.names).index("jawOpen")], 0, 1), atol=1e-6)
    with pytest.raises(ParameterError, match="frames: expected 7 increasing frame numbers"):
        write_animated_usd(tmp_path / "o.usda", src, np.zeros((7, 3)), ["a", "b", "c"], 30.0, frames=[1] * 7)
