"""retarget_cli.io.rig.usd: UsdSkel blend shapes read as a rig (synthetic stages written in the tests).

Round trips through the project's own UsdSkel writer (io/usd.py, ``apply --format usd``), stages built with pxr
(several meshes, transforms, sparse offsets, in-betweens, units), filters, errors, and untrusted files.
"""

import logging
import os
import tempfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from retarget_cli.errors import InputError, MissingExtraError, RetargetError
from retarget_cli.io.exports import SameExport
from retarget_cli.io.rig import load_rig, read_rig
from retarget_cli.io.rig.usd import read_usd_rig
from retarget_cli.io.usd import write_usd_skel
from retarget_cli.methods.rig import BlendshapeRig

pxr = pytest.importorskip("pxr", reason="usd-core (the 'usd' extra) is not installed")
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt  # noqa: E402

FUZZ = settings(max_examples=int(os.environ.get("RETARGET_FUZZ_EXAMPLES", "30")), deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


# ---------------------------------------------------------------------- round trip through the project's writer
def _synthetic(seed=0, n=40, k=5):
    """A small rig: a strip of quads, k shapes (one dense, the others on a few vertices)."""
    rng = np.random.default_rng(seed)
    cols = n // 2
    P = np.array([[x, y, 0.1 * x * y] for y in (0.0, 1.0) for x in np.linspace(0, 3, cols)])
    quads = [[i, i + 1, cols + i + 1, cols + i] for i in range(cols - 1)]
    D = np.zeros((k, n, 3))
    D[0] = rng.normal(0, 0.1, (n, 3))
    for j in range(1, k):
        ids = rng.choice(n, 6, replace=False)
        D[j, ids] = rng.normal(0, 0.2, (6, 3))
    return P, quads, D, [f"shape{j}" for j in range(k)]


def _write(path, P, quads, D, names):
    """Through the writer (a crate ``.usd``), exported as *path*'s format when that is another."""
    counts = [len(q) for q in quads]
    corners = [i for q in quads for i in q]
    path = Path(path)
    first = path if path.suffix == ".usd" else path.with_name(path.stem + "-w.usd")
    write_usd_skel(first, points=P, counts=counts, corners=corners, shapes=D, names=names,
                   weights=np.zeros((2, len(D))), fps=30.0)
    if first != path:
        Sdf.Layer.FindOrOpen(str(first)).Export(str(path))
    return path


@pytest.mark.parametrize("suffix", [".usd", ".usda", ".usdc"])
def test_round_trip_through_the_usdskel_writer(tmp_path, suffix):
    P, quads, D, names = _synthetic()
    path = _write(tmp_path / f"char{suffix}", P, quads, D, names)
    rig = load_rig(path)
    assert list(rig.names) == names and rig.n_vertices == len(P)
    ref = BlendshapeRig(P, D, names)
    for w in np.random.default_rng(1).uniform(-0.5, 1.5, (4, len(names))):
        np.testing.assert_allclose(rig.evaluate(w), ref.evaluate(w), rtol=0, atol=1e-5)  # float32 in the file
    g = read_usd_rig(path)
    assert g.kind == "usd" and g.mesh_ranges == [("face", 0, len(P))] and g.meters_per_unit == 0.01
    assert len(g.faces) == 2 * len(quads)  # quads fan-triangulated
    assert set(map(tuple, np.sort(g.faces[:2], axis=1))) == {(0, 1, 21), (0, 20, 21)}


def test_usdz_package(tmp_path):
    P, quads, D, names = _synthetic(2)
    src = _write(tmp_path / "char.usdc", P, quads, D, names)
    from pxr import UsdUtils
    assert UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(src)), str(tmp_path / "char.usdz"))
    rig = load_rig(tmp_path / "char.usdz")
    np.testing.assert_allclose(rig.neutral, P, atol=1e-6)
    w = np.linspace(0, 1, len(names))
    np.testing.assert_allclose(rig.evaluate(w), P + np.tensordot(w, D, 1), atol=1e-5)


# ---------------------------------------------------------------------- stages built here: meshes, transforms, units
def _mesh(stage, path, points, faces, shapes, *, translate=None, scale=None, left=False):
    """A Mesh prim (under an Xform with translate/scale) with BlendShape children: name -> (offsets, ids or None)."""
    parent = path.rsplit("/", 1)[0]
    xf = UsdGeom.Xform.Define(stage, parent)
    if translate is not None:
        xf.AddTranslateOp().Set(Gf.Vec3d(*translate))
    if scale is not None:
        xf.AddScaleOp().Set(Gf.Vec3f(*scale))
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(points, np.float32)))
    mesh.CreateFaceVertexCountsAttr([len(f) for f in faces])
    mesh.CreateFaceVertexIndicesAttr([i for f in faces for i in f])
    if left:
        mesh.CreateOrientationAttr(UsdGeom.Tokens.leftHanded)
    if shapes:
        binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
        binding.CreateBlendShapesAttr(list(shapes))
        targets = []
        for k, (offsets, ids) in enumerate(shapes.values()):
            shape = UsdSkel.BlendShape.Define(stage, f"{path}/bs{k}")
            shape.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(offsets, np.float32)))
            if ids is not None:
                shape.CreatePointIndicesAttr(list(ids))
            targets.append(shape.GetPath())
        binding.CreateBlendShapeTargetsRel().SetTargets(targets)
    return mesh


TRI = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)


def _two_meshes(path, **stage_meta):
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, stage_meta.get("mpu", 1.0))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    _mesh(stage, "/Char/Head/Head", TRI, [[0, 1, 3, 2]],
          {"jawOpen": ([[0, -1, 0], [0, -2, 0]], [0, 1]), "blink": ([[0, 0, 1]] * 4, None)},
          translate=(10, 0, 0), scale=(2, 2, 2))
    teeth = _mesh(stage, "/Char/Teeth/Teeth", TRI[:3], [[0, 1, 2]], {"jawOpen": ([[0, -0.5, 0]], [2])},
                  translate=(0, 5, 0), left=True)
    shape = UsdSkel.BlendShape(stage.GetPrimAtPath("/Char/Teeth/Teeth/bs0"))
    half = shape.CreateInbetween("half")
    half.SetWeight(0.5)
    half.SetOffsets(Vt.Vec3fArray([Gf.Vec3f(0, -9, 0)]))
    _mesh(stage, "/Char/Eye/Eye", TRI, [[0, 1, 2], [1, 3, 2]], {})
    stage.GetRootLayer().Save()
    return teeth


def test_meshes_transforms_units_and_one_slider_across_meshes(tmp_path, caplog):
    _two_meshes(tmp_path / "two.usda")
    with caplog.at_level(logging.INFO, logger="retarget_cli.io.rig.usd"):
        g = read_usd_rig(tmp_path / "two.usda")
    assert g.mesh_ranges == [("Head", 0, 4), ("Teeth", 4, 7)]  # the eye has no blend shapes
    np.testing.assert_allclose(g.neutral[:4], TRI * 2 + [10, 0, 0])
    np.testing.assert_allclose(g.neutral[4:], TRI[:3] + [0, 5, 0])
    assert g.target_names == ["Head/jawOpen", "blink", "Teeth/jawOpen"]
    assert g.groups == {"jawOpen": [(0, 1.0), (2, 1.0)], "blink": [(1, 1.0)]}
    np.testing.assert_allclose(g.deltas[0, :2], [[0, -2, 0], [0, -4, 0]])  # sparse, scaled by 2, not translated
    assert not g.deltas[0, 2:].any() and not g.deltas[2, :6].any()
    np.testing.assert_allclose(g.deltas[2, 6], [0, -0.5, 0])  # the full-weight shape, the in-between dropped
    assert "1 in-between shapes not read" in caplog.text
    assert g.faces.tolist()[:2] == [[0, 1, 3], [0, 3, 2]] and g.faces.tolist()[2] == [4, 6, 5]  # leftHanded flipped
    assert (g.meters_per_unit, g.up_axis) == (1.0, "Z") and "metersPerUnit 1 (authored)" in caplog.text
    rig = load_rig(tmp_path / "two.usda")
    assert list(rig.names) == ["jawOpen", "blink"]
    moved = rig.evaluate(np.array([1.0, 0.0])) - rig.neutral
    np.testing.assert_allclose(moved[[0, 1, 6]], [[0, -2, 0], [0, -4, 0], [0, -0.5, 0]])  # head and teeth together


def test_rig_yaml_source_with_filters_and_sliders(tmp_path):
    _two_meshes(tmp_path / "two.usda")
    (tmp_path / "rig.yaml").write_text("source: two.usda\nmeshes: [Head, /Char/Eye/*]\ntargets: ['*jaw*']\n"
                                       "sliders: [targets, {both: {jawOpen: 1, blink: 0.5}}]\nlandmarks: [0, 7]\n")
    with pytest.raises(InputError, match="unknown target 'blink'"):
        read_rig(tmp_path / "rig.yaml")
    (tmp_path / "rig.yaml").write_text("source: two.usda\nmeshes: [Head, /Char/Eye/*]\n"
                                       "sliders: [targets, {both: {jawOpen: 1, blink: 0.5}}]\nlandmarks: [0, 7]\n")
    spec = read_rig(tmp_path / "rig.yaml")
    assert spec.outline.mesh_ranges == [("Head", 0, 4), ("Eye", 4, 8)] and spec.outline.n_vertices == 8
    cache = tmp_path / "cache"
    for _ in range(2):  # cold, then from the cache
        rig = load_rig(tmp_path / "rig.yaml", cache_dir=cache)
        assert list(rig.names) == ["jawOpen", "blink", "both"] and rig.n_vertices == 8
        np.testing.assert_allclose(rig.evaluate(np.array([0, 0, 1.0]))[0] - rig.neutral[0],
                                   [0, -2, 1])
        assert rig.landmarks[1].tolist() == [0, 7]
    assert len(list(cache.glob("rig-*.npz"))) == 1


def test_apply_format_same_takes_a_usd_rig(tmp_path):
    P, quads, D, names = _synthetic()
    rig = load_rig(_write(tmp_path / "char.usd", P, quads, D, names))
    ctx = SimpleNamespace(rig=rig, rig_file=tmp_path / "char.usd", out=tmp_path / "out", weights=None, targets=None,
                          landmarks=None)
    SameExport.check_context(ctx)  # the copy itself: tests/unit/io/test_usd_animation.py
    assert SameExport.outputs(ctx, tmp_path / "char.usd") == (tmp_path / "out" / "char_animated.usd",)
    ctx.out = tmp_path
    with pytest.raises(InputError, match="char_animated.usd"):  # not over an input of the run
        ctx.rig_file = tmp_path / "char_animated.usd"
        SameExport.check_context(ctx)


# ---------------------------------------------------------------------- errors: one line naming the file
def _one_line(path, match, **kw):
    with pytest.raises(InputError, match=match) as info:
        load_rig(path, **kw)
    assert "\n" not in str(info.value), str(info.value)
    return str(info.value)


def test_errors_no_blend_shapes_and_filters(tmp_path):
    stage = Usd.Stage.CreateNew(str(tmp_path / "plain.usda"))
    _mesh(stage, "/A/Body", TRI, [[0, 1, 2]], {})
    stage.GetRootLayer().Save()
    _one_line(tmp_path / "plain.usda", r"plain.usda: no blend shapes in any mesh \(meshes: Body\)")
    _two_meshes(tmp_path / "two.usda")
    (tmp_path / "a.yaml").write_text("source: two.usda\nmeshes: Nose\n")
    _one_line(tmp_path / "a.yaml", "meshes: 'Nose' matches no mesh; the file's meshes: Head, Teeth, Eye")
    (tmp_path / "b.yaml").write_text("source: two.usda\nmeshes: Eye\n")
    _one_line(tmp_path / "b.yaml", r"no blend shapes in the chosen meshes \(meshes: Eye\)")
    (tmp_path / "c.yaml").write_text("source: two.usda\ntargets: smile\n")
    _one_line(tmp_path / "c.yaml", "targets: 'smile' matches no blend shape; the blend shapes: Head/jawOpen, blink")


@pytest.mark.parametrize("edit, match", [
    (lambda st: UsdSkel.BlendShape(st.GetPrimAtPath("/Char/Head/Head/bs0")).GetPointIndicesAttr().Set([0, 9]),
     r"blend shape 'jawOpen' \(/Char/Head/Head/bs0\): pointIndices holds 9, the mesh has 4 points"),
    (lambda st: UsdSkel.BlendShape(st.GetPrimAtPath("/Char/Head/Head/bs1")).GetOffsetsAttr().Set(
        Vt.Vec3fArray([Gf.Vec3f(0, 0, 1)])), r"blend shape 'blink' .*: 1 offsets for the mesh's 4 points"),
    (lambda st: UsdSkel.BindingAPI(st.GetPrimAtPath("/Char/Head/Head")).GetBlendShapesAttr().Set(["a"]),
     "skel:blendShapes names 1 shapes, skel:blendShapeTargets 2"),
    (lambda st: UsdGeom.Mesh(st.GetPrimAtPath("/Char/Head/Head")).GetFaceVertexIndicesAttr().Set([0, 1, 3, 7]),
     "faceVertexIndices holds 7, the mesh has 4 points"),
    (lambda st: UsdGeom.Mesh(st.GetPrimAtPath("/Char/Head/Head")).GetPointsAttr().Set(
        Vt.Vec3fArray([Gf.Vec3f(float("nan"), 0, 0)] * 4)), "positions or blend shape offsets are not finite"),
])
def test_errors_malformed_meshes_and_shapes(tmp_path, edit, match):
    _two_meshes(tmp_path / "two.usda")
    stage = Usd.Stage.Open(str(tmp_path / "two.usda"))
    edit(stage)
    stage.GetRootLayer().Save()
    msg = _one_line(tmp_path / "two.usda", match)
    assert msg.startswith("two.usda: "), msg


def test_error_layers_outside_the_rig_folder(tmp_path):
    (tmp_path / "rig").mkdir()
    P, quads, D, names = _synthetic()
    _write(tmp_path / "outside.usd", P, quads, D, names)
    _write(tmp_path / "rig" / "inside.usd", P, quads, D, names)
    for i, (ref, ok) in enumerate([("../outside.usd", False), (str(tmp_path / "outside.usd"), False),
                                   ("./inside.usd", True), ("missing.usd", False),
                                   ("http://example.invalid/x.usd", False)]):
        top = tmp_path / "rig" / f"top{i}.usda"
        stage = Usd.Stage.CreateNew(str(top))
        stage.DefinePrim("/Top").GetReferences().AddReference(ref)
        stage.GetRootLayer().Save()
        del stage
        if ok:
            assert list(load_rig(top).names) == names
            assert read_rig(top).files()[1:] == [(tmp_path / "rig" / "inside.usd").resolve()]
        else:
            _one_line(top, "which is not a file inside the rig's folder")


def test_missing_usd_core_is_one_line(tmp_path, monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "pxr" else real(name, *a))
    with pytest.raises(MissingExtraError, match=r"^char.usd: reading a USD rig needs usd-core, the optional extra "
                                                r"'usd': pip install 'retarget\[usd\]'$"):
        read_usd_rig(tmp_path / "char.usd")


# ---------------------------------------------------------------------- untrusted files: truncated, flipped bytes
def test_a_file_that_crashes_usd_core_is_one_line(tmp_path, caplog):
    """usd-core 26.11 aborts on this mutated crate file: the reader's child process dies, not the caller."""
    crash = Path(__file__).resolve().parents[3] / "data" / "usd" / "crash_sdf_primspec.usd"
    msg = _one_line(crash, "crash_sdf_primspec.usd: ")
    assert "usd-core stopped reading it" in msg or "not a USD file usd-core can read" in msg, msg


def test_child_log_records_come_back(tmp_path, caplog):
    _two_meshes(tmp_path / "two.usda")
    with caplog.at_level(logging.INFO, logger="retarget_cli.io.rig.usd"):
        read_usd_rig(tmp_path / "two.usda")
    assert [r.name for r in caplog.records if "in-between" in r.getMessage()] == ["retarget_cli.io.rig.usd"]



@pytest.fixture(scope="module")
def usd_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("usd")
    P, quads, D, names = _synthetic(3, n=12, k=3)
    _write(d / "c.usdc", P, quads, D, names)
    Sdf.Layer.FindOrOpen(str(d / "c.usdc")).Export(str(d / "a.usda"))
    return {"usdc": (d / "c.usdc").read_bytes(), "usda": (d / "a.usda").read_bytes()}


def test_truncated_files_are_one_line(usd_files, tmp_path):
    for kind, blob in usd_files.items():
        for cut in (0, 8, 100, len(blob) // 2) + ((len(blob) - 1,) if kind == "usdc" else ()):
            p = tmp_path / f"t{cut}.{kind}"
            p.write_bytes(blob[:cut])
            with pytest.raises(InputError) as info:
                load_rig(p)
            assert "\n" not in str(info.value) and p.name in str(info.value), str(info.value)


@FUZZ
@given(data=st.data())
def test_fuzzed_usd_files_raise_only_the_tools_errors(usd_files, data):
    """Flipped bytes and truncations of a .usdc and a .usda through load_rig: a rig or one RetargetError line."""
    kind = data.draw(st.sampled_from(sorted(usd_files)))
    buf = bytearray(usd_files[kind])
    if data.draw(st.booleans()):
        buf = buf[:data.draw(st.integers(0, len(buf)))]
    else:
        for _ in range(data.draw(st.integers(1, 8))):
            buf[data.draw(st.integers(0, len(buf) - 1))] = data.draw(st.integers(0, 255))
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / f"f.{kind}"
        p.write_bytes(bytes(buf))
        try:
            load_rig(p)
        except RetargetError as exc:
            assert "\n" not in str(exc).strip(), str(exc)
