"""retarget_cli.io.rig.fbx: FBX blend shapes read as a rig through Assimp (the 'fbx' extra).

Two kinds of files: FBX ASCII written here (several meshes, node transforms, a Z-up axis system, an in-between,
units; every expected value known), and three files Maya wrote (tests/data/fbx, from ufbx's test data, MIT or
public domain), checked against ufbx's reference offsets and against the shapes stored in the ASCII twin.
"""

import logging
import os
import re
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from retarget_cli.errors import InputError, MissingExtraError, RetargetError
from retarget_cli.io.rig import fbx as fbxmod
from retarget_cli.io.rig import load_rig, read_rig

DATA = Path(__file__).resolve().parents[3] / "data" / "fbx"
CUBE = DATA / "maya_blend_shape_cube_7700_binary.fbx"
INB_BIN, INB_ASCII = DATA / "maya_blend_inbetween_7500_binary.fbx", DATA / "maya_blend_inbetween_7500_ascii.fbx"

try:
    fbxmod._impasse(Path("x.fbx"))
    HAVE = True
except MissingExtraError:
    HAVE = False
needs_fbx = pytest.mark.skipif(not HAVE, reason="the 'fbx' extra (impasse, cmeel-assimp) is not installed")
FUZZ = settings(max_examples=int(os.environ.get("RETARGET_FUZZ_EXAMPLES", "30")), deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


# ---------------------------------------------------------------------- FBX ASCII written here
def _arr(name, values, fmt="{:g}"):
    return f"\t\t{name}: *{len(values)} {{\n\t\t\ta: {','.join(fmt.format(v) for v in values)}\n\t\t}}\n"


def fbx_ascii(models, *, unit=1.0, up=1, front=2, front_sign=1):
    """An FBX 7.4 ASCII scene: each model a dict(name, points, polys, translate, scale, channels), each channel
    ``(name, [(full weight, control point ids, offsets), ...])`` in ascending full weight."""
    objs, conns, ids = [], [], iter(range(1001, 10**6))
    for m in models:
        g, mo = next(ids), next(ids)
        pvi = [i for poly in m["polys"] for i in (*poly[:-1], -poly[-1] - 1)]
        objs.append(f'\tGeometry: {g}, "Geometry::{m["name"]}", "Mesh" {{\n'
                    + _arr("Vertices", [c for p in m["points"] for c in p]) + _arr("PolygonVertexIndex", pvi, "{:d}")
                    + "\t\tGeometryVersion: 124\n\t}\n")
        t, s = m.get("translate", (0, 0, 0)), m.get("scale", (1, 1, 1))
        objs.append(f'\tModel: {mo}, "Model::{m["name"]}", "Mesh" {{\n\t\tVersion: 232\n\t\tProperties70:  {{\n'
                    f'\t\t\tP: "Lcl Translation", "Lcl Translation", "", "A",{t[0]:g},{t[1]:g},{t[2]:g}\n'
                    f'\t\t\tP: "Lcl Scaling", "Lcl Scaling", "", "A",{s[0]:g},{s[1]:g},{s[2]:g}\n\t\t}}\n\t}}\n')
        conns += [(mo, 0), (g, mo)]
        if m.get("channels"):
            bs = next(ids)
            objs.append(f'\tDeformer: {bs}, "Deformer::{m["name"]}Blend", "BlendShape" {{\n\t\tVersion: 100\n\t}}\n')
            conns.append((bs, g))
            for cname, shapes in m["channels"]:
                ch = next(ids)
                objs.append(f'\tDeformer: {ch}, "SubDeformer::{cname}", "BlendShapeChannel" {{\n\t\tVersion: 100\n'
                            "\t\tDeformPercent: 0\n" + _arr("FullWeights", [f for f, _, _ in shapes]) + "\t}\n")
                conns.append((ch, bs))
                for k, (_, cps, offs) in enumerate(shapes):
                    sh = next(ids)
                    objs.append(f'\tGeometry: {sh}, "Geometry::{cname}{k}", "Shape" {{\n\t\tVersion: 100\n'
                                + _arr("Indexes", cps, "{:d}") + _arr("Vertices", [c for o in offs for c in o])
                                + _arr("Normals", [0] * (3 * len(cps))) + "\t}\n")
                    conns.append((sh, ch))
    axes = "".join(f'\t\tP: "{k}", "int", "Integer", "",{v}\n' for k, v in
                   [("UpAxis", up), ("UpAxisSign", 1), ("FrontAxis", front), ("FrontAxisSign", front_sign),
                    ("CoordAxis", 0), ("CoordAxisSign", 1)])
    return ("; FBX 7.4.0 project file\nFBXHeaderExtension:  {\n\tFBXHeaderVersion: 1003\n\tFBXVersion: 7400\n}\n"
            "GlobalSettings:  {\n\tVersion: 1000\n\tProperties70:  {\n" + axes
            + f'\t\tP: "UnitScaleFactor", "double", "Number", "",{unit:g}\n\t}}\n}}\n'
            + "Objects:  {\n" + "".join(objs) + "}\nConnections:  {\n"
            + "".join(f'\tC: "OO",{a},{b}\n' for a, b in conns) + "}\n")


QUAD = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]
SCENE = [
    dict(name="Head", points=QUAD, polys=[(0, 1, 2, 3)], translate=(10, 0, 0), scale=(2, 2, 2),
         channels=[("Face.jawOpen", [(50, [0], [(0, -9, 0)]), (100, [0, 1], [(0, -1, 0), (0, -2, 0)])]),
                   ("Face.blink", [(100, [0, 1, 2, 3], [(0, 0, 1)] * 4)])]),
    dict(name="Teeth", points=QUAD[:3], polys=[(0, 1, 2)], translate=(0, 5, 0),
         channels=[("Teeth.jawOpen", [(100, [2], [(0, -0.5, 0)])])]),
    dict(name="Eye", points=QUAD, polys=[(0, 1, 2), (0, 2, 3)]),
]


@pytest.fixture
def scene(tmp_path):
    p = tmp_path / "char.fbx"
    p.write_text(fbx_ascii(SCENE))
    return p


@needs_fbx
def test_meshes_transforms_inbetween_and_one_slider_across_meshes(scene, caplog):
    with caplog.at_level(logging.INFO, logger="retarget_cli.io.rig.fbx"):
        g = fbxmod.read_fbx_rig(scene)
    assert g.kind == "fbx" and g.mesh_ranges == [("Head", 0, 4), ("Teeth", 4, 7)]  # the eye has no blend shapes
    np.testing.assert_allclose(g.neutral[:4], np.array(QUAD) * 2 + [10, 0, 0])
    np.testing.assert_allclose(g.neutral[4:], np.array(QUAD[:3]) + [0, 5, 0])
    assert g.target_names == ["Face.jawOpen", "Face.blink", "Teeth.jawOpen"]
    assert g.groups == {"jawOpen": [(0, 1.0), (2, 1.0)], "blink": [(1, 1.0)]}  # 'Face.' / 'Teeth.' dropped
    np.testing.assert_allclose(g.deltas[0, :2], [[0, -2, 0], [0, -4, 0]])  # the 100 % shape, scaled by 2
    assert not g.deltas[0, 2:].any()
    np.testing.assert_allclose(g.deltas[2, 6], [0, -0.5, 0])
    assert "in-between shapes dropped, the last (full-weight) shape of each channel read: Face.jawOpen (1)" \
        in caplog.text
    assert g.faces.shape == (3, 3) and g.meters_per_unit == 0.01 and g.up_axis == "+Y"
    rig = load_rig(scene)
    assert list(rig.names) == ["jawOpen", "blink"]
    moved = rig.evaluate(np.array([1.0, 0.0])) - rig.neutral
    np.testing.assert_allclose(moved[[0, 1, 6]], [[0, -2, 0], [0, -4, 0], [0, -0.5, 0]])  # head and teeth together


@needs_fbx
def test_z_up_file_reads_y_up_and_units_are_reported(tmp_path):
    p = tmp_path / "zup.fbx"
    p.write_text(fbx_ascii(SCENE[:1], unit=100, up=2, front=1, front_sign=-1))  # Blender's axes, metres
    g = fbxmod.read_fbx_rig(p)
    assert g.up_axis == "+Z" and g.meters_per_unit == 1.0
    np.testing.assert_allclose(g.neutral, [[10, 0, 0], [12, 0, 0], [12, 0, -2], [10, 0, -2]])  # (x, z, -y)
    np.testing.assert_allclose(g.deltas[1], [[0, 2, 0]] * 4)  # +z in the file is up


@needs_fbx
def test_corners_are_welded_back_to_vertices(tmp_path):
    """Assimp gives one vertex per face corner; corners equal in position and in every shape become one."""
    grid = [(x, y, 0) for y in range(3) for x in range(3)]
    polys = [(r * 3 + c, r * 3 + c + 1, r * 3 + c + 4, r * 3 + c + 3) for r in range(2) for c in range(2)]
    p = tmp_path / "grid.fbx"
    p.write_text(fbx_ascii([dict(name="Grid", points=grid, polys=polys,
                                 channels=[("up.up", [(100, [4], [(0, 0, 1)])])])]))
    g = fbxmod.read_fbx_rig(p)
    assert g.groups == {"up": [(0, 1.0)]}  # a deformer with one channel of its name (Blender's way): 'up.up' is 'up'
    assert len(g.neutral) == 9 and len(g.faces) == 8  # 16 corners in the file, 9 control points
    assert sorted(map(tuple, g.neutral.tolist())) == sorted(map(tuple, np.array(grid, float).tolist()))
    centre = int(np.flatnonzero((g.neutral == [1, 1, 0]).all(axis=1))[0])
    assert np.flatnonzero(g.deltas[0].any(axis=1)).tolist() == [centre]
    assert np.bincount(g.faces.ravel(), minlength=9)[centre] == 6  # one vertex in the 6 triangles at the centre


@needs_fbx
def test_rig_yaml_source_filters_and_errors(scene, tmp_path):
    (tmp_path / "rig.yaml").write_text("source: char.fbx\nmeshes: [Head, Eye]\ntargets: 'Face.j*'\nlandmarks: [0, 7]\n")
    spec = read_rig(tmp_path / "rig.yaml")
    assert spec.outline.mesh_ranges == [("Head", 0, 4), ("Eye", 4, 8)] and list(spec.sliders) == ["jawOpen"]
    rig = load_rig(tmp_path / "rig.yaml", cache_dir=tmp_path / "cache")
    again = load_rig(tmp_path / "rig.yaml", cache_dir=tmp_path / "cache")
    assert rig.n_vertices == again.n_vertices == 8 and again.landmarks[1].tolist() == [0, 7]
    for text, match in [("meshes: Nose", "meshes: 'Nose' matches no mesh; the file's meshes: Head, Teeth, Eye"),
                        ("meshes: Eye", r"no blend shapes in the chosen meshes \(meshes: Eye\)"),
                        ("targets: smile", "targets: 'smile' matches no blend shape")]:
        (tmp_path / "bad.yaml").write_text(f"source: char.fbx\n{text}\n")
        _one_line(tmp_path / "bad.yaml", match)
    p = tmp_path / "plain.fbx"
    p.write_text(fbx_ascii(SCENE[2:]))
    _one_line(p, r"plain.fbx: no blend shapes in any mesh \(meshes: Eye\)")


def _one_line(path, match):
    with pytest.raises(InputError, match=match) as info:
        load_rig(path)
    assert "\n" not in str(info.value), str(info.value)
    return str(info.value)


@needs_fbx
def test_corrupt_and_truncated_files_are_one_line(scene, tmp_path):
    blob = CUBE.read_bytes()
    for cut in (0, 20, 300, len(blob) // 2):
        (tmp_path / f"t{cut}.fbx").write_bytes(blob[:cut])
        msg = _one_line(tmp_path / f"t{cut}.fbx", f"t{cut}.fbx: ")
        assert msg.startswith(f"t{cut}.fbx: "), msg
    (tmp_path / "text.fbx").write_text("hello, I am not a character\n")
    _one_line(tmp_path / "text.fbx", "text.fbx: not an FBX file")


def test_missing_extra_is_one_line(tmp_path, monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "impasse" else real(name, *a))
    (tmp_path / "char.fbx").write_bytes(b"Kaydara FBX Binary  \x00")
    with pytest.raises(MissingExtraError, match=r"^char.fbx: reading an FBX rig needs the optional extra 'fbx': "
                                                r"pip install 'retarget\[fbx\]' \(impasse, cmeel-assimp\)$"):
        load_rig(tmp_path / "char.fbx")


# ---------------------------------------------------------------------- files Maya wrote (tests/data/fbx)
@needs_fbx
def test_maya_cube_matches_ufbx_reference_offsets():
    g = fbxmod.read_fbx_rig(CUBE)
    assert g.target_names == ["Squish.TopH", "Squish.TopV"] and list(g.groups) == ["TopH", "TopV"]
    assert len(g.neutral) == 8 and len(g.faces) == 12 and g.meters_per_unit == 0.01  # Maya: centimetres
    for k, (axis, size) in enumerate([(0, 0.317), (2, 0.284)]):  # ufbx's test_skin.h reference values
        moved = np.flatnonzero(g.deltas[k].any(axis=1))
        assert len(moved) == 4 and np.allclose(g.neutral[moved, 1], 0.5)  # the four top vertices
        np.testing.assert_allclose(np.abs(g.deltas[k][moved, axis]), size, atol=5e-4)
        assert not np.delete(g.deltas[k], axis, axis=1).any()


def _ascii_shapes(path):
    """Full-weight shapes of the ASCII twin: channel -> (control point ids, offsets (n, 3)) of its last shape."""
    text = path.read_text()
    geo = {m.group(1): m.group(2) for m in re.finditer(r'Geometry: (\d+), "Geometry::[^"]*", "Shape" \{(.*?)\n\t\}',
                                                     text, re.S)}
    chans = {m.group(1): m.group(2) for m in re.finditer(r'Deformer: (\d+), "SubDeformer::([^"]*)"', text)}
    links = re.findall(r'C: "OO",(\d+),(\d+)', text)
    out = {}
    for ch, name in ((c, n) for c, n in chans.items()):
        last = [a for a, b in links if b == ch and a in geo][-1]
        body = geo[last]
        nums = [np.array([float(x) for x in re.search(rf"{key}: \*\d+ \{{\s*a: ([^}}]*)\}}", body).group(1).split(",")])
                for key in ("Indexes", "Vertices")]
        out[name] = (nums[0].astype(int), nums[1].reshape(-1, 3))
    return out


@needs_fbx
@pytest.mark.parametrize("path", [INB_BIN, INB_ASCII], ids=["binary", "ascii"])
def test_maya_inbetweens_read_the_full_weight_shape(path):
    g = fbxmod.read_fbx_rig(path)
    assert g.target_names == ["KeyBlend.LiftTop", "KeyBlend.MoveToSide"] and len(g.neutral) == 26
    ref = _ascii_shapes(INB_ASCII)
    for k, name in enumerate(g.target_names):
        ids, offsets = ref[name]
        moved = np.flatnonzero(g.deltas[k].any(axis=1))
        assert len(moved) == len(ids)
        # the same displacements, as a set (vertex order is Assimp's, welded, not the control points')
        got = sorted(map(tuple, np.round(g.deltas[k][moved], 4).tolist()))
        assert got == sorted(map(tuple, np.round(offsets, 4).tolist())), name


# ---------------------------------------------------------------------- untrusted files
@needs_fbx
@FUZZ
@given(data=st.data())
def test_fuzzed_fbx_files_raise_only_the_tools_errors(data):
    """Flipped bytes and truncations of the binary and ASCII Maya files through load_rig."""
    src = data.draw(st.sampled_from([CUBE, INB_ASCII]))
    buf = bytearray(src.read_bytes())
    if data.draw(st.booleans()):
        buf = buf[:data.draw(st.integers(0, len(buf)))]
    else:
        for _ in range(data.draw(st.integers(1, 8))):
            buf[data.draw(st.integers(0, len(buf) - 1))] = data.draw(st.integers(0, 255))
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "f.fbx"
        p.write_bytes(bytes(buf))
        try:
            load_rig(p)
        except RetargetError as exc:
            assert "\n" not in str(exc).strip(), str(exc)
