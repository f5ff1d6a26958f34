"""read_gltf_rig on small GLB / glTF / VRM files written by the test, and on the two real rigs of ../shared.

The synthetic scene: a root node (translated) with a head (float positions, three named targets: dense, sparse
without a bufferView, sparse over a bufferView) and teeth (KHR_mesh_quantization int16 positions and int8 target,
an EXT_meshopt_compression vertex stream, triangle stream and EXPONENTIAL-filtered target, names in the primitive's
extras), plus an eye without targets. Expected values are computed here from the same numbers, independently of
the reader.
"""

from __future__ import annotations

import base64
import json
import os
import struct
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from retarget_cli.errors import InputError, MissingExtraError, RetargetError
from retarget_cli.io.rig import _gltfdata
from retarget_cli.io.rig.gltf import read_gltf_rig

try:
    import meshoptimizer as mo
except ImportError:  # the optional extra 'rigs'
    mo = None
needs_meshopt = pytest.mark.skipif(mo is None, reason="meshoptimizer (the 'rigs' extra) is not installed")

REAL = Path(__file__).resolve().parents[4].parent / "shared" / "realdata" / "rigs"
VALID = REAL / "valid-glb" / "White_F_2_Busi.glb"
GODETTE = REAL / "godette-vrm" / "Godette_vrm_v4.vrm"
FUZZ = settings(max_examples=int(os.environ.get("RETARGET_FUZZ_EXAMPLES", "150")), deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


# ---------------------------------------------------------------------- a small glTF writer
class Builder:
    """Buffer 0 (the GLB BIN chunk or rig.bin), an optional meshopt fallback buffer 1, views and accessors."""

    def __init__(self):
        self.bin = bytearray()
        self.views, self.accessors, self.fallback = [], [], 0

    def _put(self, data: bytes) -> int:
        self.bin += b"\0" * (-len(self.bin) % 4)
        off = len(self.bin)
        self.bin += data
        return off

    def view(self, data: bytes, stride=None) -> int:
        v = {"buffer": 0, "byteOffset": self._put(data), "byteLength": len(data)}
        if stride:
            v["byteStride"] = stride
        self.views.append(v)
        return len(self.views) - 1

    def meshopt_view(self, encoded: bytes, count: int, stride: int, mode="ATTRIBUTES", filt=None) -> int:
        ext = {"buffer": 0, "byteOffset": self._put(encoded), "byteLength": len(encoded), "byteStride": stride,
               "count": count, "mode": mode}
        if filt:
            ext["filter"] = filt
        v = {"buffer": 1, "byteOffset": self.fallback, "byteLength": count * stride,
             "extensions": {"EXT_meshopt_compression": ext}}
        if mode == "ATTRIBUTES":
            v["byteStride"] = stride
        self.fallback += count * stride + (-(count * stride) % 4)
        self.views.append(v)
        return len(self.views) - 1

    def accessor(self, count, ctype, atype, view=None, normalized=False, sparse=None) -> int:
        a = {"count": count, "componentType": ctype, "type": atype}
        if view is not None:
            a["bufferView"] = view
        if normalized:
            a["normalized"] = True
        if sparse:
            a["sparse"] = sparse
        self.accessors.append(a)
        return len(self.accessors) - 1

    def floats(self, arr, atype="VEC3") -> int:
        arr = np.asarray(arr, dtype="<f4")
        return self.accessor(len(arr), 5126, atype, self.view(arr.tobytes()))

    def doc(self, meshes, nodes, scene_nodes, **extra) -> dict:
        buffers = [{"byteLength": len(self.bin)}]
        if self.fallback:
            buffers.append({"byteLength": self.fallback, "extensions": {"EXT_meshopt_compression": {"fallback": True}}})
        d = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": scene_nodes}], "nodes": nodes,
             "meshes": meshes, "accessors": self.accessors, "bufferViews": self.views, "buffers": buffers}
        d.update(extra)
        return d


def glb_bytes(doc: dict, binary: bytes) -> bytes:
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    binary = bytes(binary) + b"\0" * (-len(binary) % 4)
    body = struct.pack("<II", len(js), 0x4E4F534A) + js + struct.pack("<II", len(binary), 0x004E4942) + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


HEAD_P = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float32)
JAW = np.array([[0, -0.25, 0], [0, -0.25, 0], [0, 0, 0], [0, 0, 0]], dtype=np.float32)
SMILE_BASE = np.full((4, 3), [0.125, 0, 0], dtype=np.float32)
TEETH_Q = np.array([[32767, 0, 0], [0, 32767, 0], [-32767, -32767, 0]], dtype=np.int16)
T_JAW_Q = np.array([[0, -127, 0], [0, -127, 0], [0, 64, 0]], dtype=np.int8)
T_BLINK = np.array([[0.5, 0, 0], [0, 0.25, -1.5], [0.0009765625, 0, 0]], dtype=np.float32)  # k * 2**-10
ROOT_T = np.array([1.0, 0, 0])
HEAD_T, HEAD_S = np.array([0, 1.0, 0]), 2.0
TEETH_T, TEETH_S = np.array([0, 0, 1.0]), 0.5
Q90 = [0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)]  # 90 degrees about +z: (x, y, z) -> (-y, x, z)


def _exp_words(values: np.ndarray, e: int = -10) -> np.ndarray:
    """meshopt EXPONENTIAL filter words (exponent << 24 | 24-bit mantissa) of values that are k * 2**e."""
    m = np.round(values.astype(np.float64) * 2.0 ** -e).astype(np.int64)
    return ((e & 0xFF) << 24 | (m & 0xFFFFFF)).astype(np.uint32)


def build_scene(vertex_version: int = 0, meshopt: bool | None = None):
    """The synthetic scene: (Builder, meshes, nodes, scene roots); the teeth meshopt-compressed when *meshopt*."""
    meshopt = mo is not None if meshopt is None else meshopt
    b = Builder()
    head_idx = b.accessor(6, 5123, "SCALAR", b.view(np.array([0, 1, 2, 0, 2, 3], "<u2").tobytes()))
    pos = b.floats(HEAD_P)
    jaw = b.floats(JAW)
    blink = b.accessor(4, 5126, "VEC3", sparse={
        "count": 1, "indices": {"bufferView": b.view(np.array([2], "<u1").tobytes()), "componentType": 5121},
        "values": {"bufferView": b.view(np.array([[0, 0, 0.5]], "<f4").tobytes())}})
    smile = b.accessor(4, 5126, "VEC3", b.view(SMILE_BASE.tobytes()), sparse={
        "count": 2, "indices": {"bufferView": b.view(np.array([0, 3], "<u2").tobytes()), "componentType": 5123},
        "values": {"bufferView": b.view(np.array([[0, 0.2, 0], [0, 0, 0.3]], "<f4").tobytes())}})
    head = {"name": "Head", "extras": {"targetNames": ["jawOpen", "blink", "smile"]},
            "primitives": [{"attributes": {"POSITION": pos}, "indices": head_idx,
                            "targets": [{"POSITION": jaw}, {"POSITION": blink}, {"POSITION": smile}]}]}
    # teeth: int16 positions padded to 8 bytes, meshopt ATTRIBUTES; triangles meshopt TRIANGLES
    padded = np.zeros((3, 4), "<i2")
    padded[:, :3] = TEETH_Q
    if meshopt:
        mo.encode_vertex_version(vertex_version)
        tpos_view = b.meshopt_view(mo.encode_vertex_buffer(padded.view(np.float32), 3, 8), 3, 8)
        tri = b.meshopt_view(mo.encode_index_buffer(np.array([0, 1, 2], np.uint32), 3, 3), 3, 2, mode="TRIANGLES")
    else:
        tpos_view = b.view(padded.tobytes(), stride=8)
        tri = b.view(np.array([0, 1, 2], "<u2").tobytes())
    tpos = b.accessor(3, 5122, "VEC3", tpos_view, normalized=True)
    tidx = b.accessor(3, 5123, "SCALAR", tri)
    padded8 = np.zeros((3, 4), "<i1")
    padded8[:, :3] = T_JAW_Q
    tjaw = b.accessor(3, 5120, "VEC3", b.view(padded8.tobytes(), stride=4), normalized=True)
    words = _exp_words(T_BLINK)
    if meshopt:
        tblink = b.accessor(3, 5126, "VEC3", b.meshopt_view(mo.encode_vertex_buffer(words.view(np.float32), 3, 12),
                                                            3, 12, filt="EXPONENTIAL"))
    else:
        tblink = b.floats(T_BLINK)
    teeth = {"name": "Teeth", "primitives": [{"attributes": {"POSITION": tpos}, "indices": tidx,
                                              "targets": [{"POSITION": tjaw}, {"POSITION": tblink}],
                                              "extras": {"targetNames": ["t_jawOpen", "blink"]}}]}
    eye = {"name": "Eye", "primitives": [{"attributes": {"POSITION": b.floats(HEAD_P[:3] * 0.1)}}]}
    nodes = [{"name": "Root", "translation": list(ROOT_T), "children": [1, 2]},
             {"name": "HeadNode", "mesh": 0, "translation": list(HEAD_T), "scale": [HEAD_S] * 3},
             {"name": "TeethNode", "mesh": 1, "translation": list(TEETH_T), "rotation": Q90, "scale": [TEETH_S] * 3},
             {"name": "EyeNode", "mesh": 2}]
    return b, [head, teeth, eye], nodes, [0, 3]


def _rot(v):
    v = np.asarray(v, dtype=np.float64)
    return np.stack([-v[..., 1], v[..., 0], v[..., 2]], axis=-1)


def expected():
    head = ROOT_T + HEAD_T + HEAD_S * HEAD_P.astype(np.float64)
    teeth = ROOT_T + TEETH_T + TEETH_S * _rot(TEETH_Q / 32767.0)
    neutral = np.vstack([head, teeth])
    d = np.zeros((5, 7, 3))
    d[0, :4] = HEAD_S * JAW
    d[1, 2] = HEAD_S * np.array([0, 0, 0.5])
    smile = SMILE_BASE.astype(np.float64).copy()
    smile[0], smile[3] = [0, 0.2, 0], [0, 0, 0.3]
    d[2, :4] = HEAD_S * smile.astype(np.float32)
    d[3, 4:] = TEETH_S * _rot(np.maximum(T_JAW_Q / 127.0, -1))
    d[4, 4:] = TEETH_S * _rot(T_BLINK)
    return neutral, d


EXTS = ["KHR_mesh_quantization", "EXT_meshopt_compression", "EXT_texture_webp", "KHR_texture_transform",
        "KHR_materials_emissive_strength"]


def write_glb(tmp_path: Path, name="rig.glb", mutate=None, **kw) -> Path:
    b, meshes, nodes, roots = build_scene(**kw)
    doc = b.doc(meshes, nodes, roots, extensionsUsed=EXTS, extensionsRequired=EXTS)
    if mutate:
        mutate(doc, b)
    p = tmp_path / name
    p.write_bytes(glb_bytes(doc, b.bin))
    return p


# ---------------------------------------------------------------------- decoding
@pytest.mark.parametrize("vertex_version", [0, 1])
@pytest.mark.parametrize("meshopt", [False, pytest.param(True, marks=needs_meshopt)])
def test_glb_scene_decodes_exactly(tmp_path, vertex_version, meshopt):
    if vertex_version and not meshopt:
        pytest.skip("the vertex codec version only matters with meshopt")
    rig = read_gltf_rig(write_glb(tmp_path, vertex_version=vertex_version, meshopt=meshopt))
    neutral, deltas = expected()
    assert rig.kind == "gltf"
    assert rig.mesh_ranges == [("Head", 0, 4), ("Teeth", 4, 7)]
    np.testing.assert_allclose(rig.neutral, neutral, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(rig.faces, [[0, 1, 2], [0, 2, 3], [4, 5, 6]])
    assert rig.faces.dtype == np.int64 and rig.neutral.dtype == np.float64 and rig.deltas.dtype == np.float64
    assert rig.target_names == ["jawOpen", "Head/blink", "smile", "t_jawOpen", "Teeth/blink"]
    assert rig.target_meshes == ["Head", "Head", "Head", "Teeth", "Teeth"]
    np.testing.assert_allclose(rig.deltas, deltas, rtol=0, atol=1e-12)
    # same name on two meshes -> one slider; t_jawOpen joins jawOpen (the t_X rule)
    assert rig.groups == {"jawOpen": [(0, 1.0), (3, 1.0)], "blink": [(1, 1.0), (4, 1.0)], "smile": [(2, 1.0)]}
    assert rig.raw_groups == {n: [(k, 1.0)] for k, n in enumerate(rig.target_names)}


def test_gltf_with_external_buffer_and_data_uri(tmp_path):
    b, meshes, nodes, roots = build_scene()
    neutral, deltas = expected()
    for uri in ("rig%20data.bin", "data:application/octet-stream;base64," + base64.b64encode(b.bin).decode()):
        doc = b.doc(meshes, nodes, roots, extensionsRequired=EXTS)
        doc["buffers"][0]["uri"] = uri
        (tmp_path / "rig data.bin").write_bytes(bytes(b.bin))
        p = tmp_path / "rig.gltf"
        p.write_text(json.dumps(doc))
        rig = read_gltf_rig(p)
        np.testing.assert_allclose(rig.neutral, neutral, rtol=0, atol=1e-12)
        np.testing.assert_allclose(rig.deltas, deltas, rtol=0, atol=1e-12)


def test_mesh_and_target_filters(tmp_path):
    p = write_glb(tmp_path)
    rig = read_gltf_rig(p, meshes=["Eye*", "Head"])
    assert [r[0] for r in rig.mesh_ranges] == ["Head", "Eye"]
    assert rig.deltas.shape == (3, 7, 3) and not rig.deltas[:, 4:].any()
    rig = read_gltf_rig(p, targets=["*blink"])
    assert rig.target_names == ["Head/blink", "Teeth/blink"] and rig.groups == {"blink": [(0, 1.0), (1, 1.0)]}
    rig = read_gltf_rig(p, meshes="Teeth*", targets=["Teeth/blink"])
    assert rig.target_names == ["blink"] and rig.neutral.shape == (3, 3)


def test_quantized_uint8_unnormalized_and_strip(tmp_path):
    b = Builder()
    q = np.array([[0, 0, 0, 0], [200, 0, 0, 0], [0, 255, 7, 0], [3, 4, 5, 0]], "<u1")  # not normalized: plain values
    pos = b.accessor(4, 5121, "VEC3", b.view(q.tobytes(), stride=4))
    tgt = b.accessor(4, 5122, "VEC3", b.view(np.array([[-32767, 0, 32767, 0]] * 4, "<i2").tobytes(), stride=8),
                     normalized=True)
    mesh = {"name": "M", "extras": {"targetNames": ["x"]},
            "primitives": [{"attributes": {"POSITION": pos}, "mode": 5, "targets": [{"POSITION": tgt}]}]}
    p = tmp_path / "q.glb"
    p.write_bytes(glb_bytes(b.doc([mesh], [{"mesh": 0, "matrix": [2, 0, 0, 0, 0, 2, 0, 0, 0, 0, 2, 0, 1, 2, 3, 1]}],
                                  [0], extensionsRequired=["KHR_mesh_quantization"]), b.bin))
    rig = read_gltf_rig(p)
    np.testing.assert_array_equal(rig.neutral, 2.0 * q[:, :3] + [1, 2, 3])
    np.testing.assert_array_equal(rig.deltas[0], np.tile([-2.0, 0, 2.0], (4, 1)))
    np.testing.assert_array_equal(rig.faces, [[0, 1, 2], [1, 3, 2]])  # strip winding alternates (§3.7.2.1)


def test_shared_vertex_primitives_are_read_once(tmp_path):
    b = Builder()
    pos, tgt = b.floats(HEAD_P), b.floats(JAW)
    i1 = b.accessor(3, 5125, "SCALAR", b.view(np.array([0, 1, 2], "<u4").tobytes()))
    i2 = b.accessor(3, 5125, "SCALAR", b.view(np.array([0, 2, 3], "<u4").tobytes()))
    prims = [{"attributes": {"POSITION": pos}, "indices": i, "targets": [{"POSITION": tgt}]} for i in (i1, i2)]
    p = tmp_path / "s.glb"
    p.write_bytes(glb_bytes(b.doc([{"name": "M", "primitives": prims}], [{"mesh": 0}], [0]), b.bin))
    rig = read_gltf_rig(p)
    assert rig.neutral.shape == (4, 3) and rig.target_names == ["M/#0"]
    np.testing.assert_array_equal(rig.faces, [[0, 1, 2], [0, 2, 3]])


def _skinned(tmp_path, joints_world, ibm, weights=None):
    """A 3-vertex mesh skinned to two joints; the mesh node has a scale that glTF says to ignore."""
    b = Builder()
    pos, tgt = b.floats(HEAD_P[:3]), b.floats(JAW[:3])
    attrs = {"POSITION": pos}
    if weights is not None:
        attrs["JOINTS_0"] = b.accessor(3, 5121, "VEC4", b.view(np.array([[0, 1, 0, 0]] * 3, "<u1").tobytes()))
        attrs["WEIGHTS_0"] = b.floats(weights, "VEC4")
    ibm_acc = b.accessor(2, 5126, "MAT4", b.view(np.stack([m.T for m in ibm]).astype("<f4").tobytes()))
    nodes = [{"name": "Skinned", "mesh": 0, "skin": 0, "scale": [0.01] * 3},
             {"name": "J0", "matrix": list(joints_world[0].T.ravel()), "children": [2]},
             {"name": "J1", "matrix": list((np.linalg.inv(joints_world[0]) @ joints_world[1]).T.ravel())}]
    mesh = {"name": "M", "primitives": [{"attributes": attrs, "targets": [{"POSITION": tgt}]}]}
    doc = b.doc([mesh], nodes, [0, 1], skins=[{"joints": [1, 2], "inverseBindMatrices": ibm_acc}])
    p = tmp_path / "skin.glb"
    p.write_bytes(glb_bytes(doc, b.bin))
    return read_gltf_rig(p)


def _trs(t=(0, 0, 0), s=1.0):
    m = np.eye(4)
    m[:3, :3] *= s
    m[:3, 3] = t
    return m


def test_skin_rest_equals_bind_uses_the_common_matrix(tmp_path):
    q = _trs((0, 2, 0), 0.5)  # what gltfpack puts in the inverse bind matrices (dequantization)
    g = [_trs((0, 1, 0)), _trs((1, 1, 0), 2.0)]
    rig = _skinned(tmp_path, g, [np.linalg.inv(m) @ q for m in g])
    np.testing.assert_allclose(rig.neutral, HEAD_P[:3] * 0.5 + [0, 2, 0], atol=1e-6)  # node scale 0.01 ignored
    np.testing.assert_allclose(rig.deltas[0], JAW[:3] * 0.5, atol=1e-6)


def test_skin_rest_pose_not_bind_pose_blends(tmp_path):
    g = [_trs(), _trs((0, 0, 0), 2.0)]
    w = np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0.5, 0.5, 0, 0]])
    rig = _skinned(tmp_path, g, [np.eye(4), np.eye(4)], weights=w)
    scale = np.array([1.0, 2.0, 1.5])[:, None]
    np.testing.assert_allclose(rig.neutral, HEAD_P[:3] * scale, atol=1e-6)
    np.testing.assert_allclose(rig.deltas[0], JAW[:3] * scale, atol=1e-6)


def test_vrm0_blend_shape_groups(tmp_path, caplog):
    groups = [{"name": "A", "presetName": "a", "binds": [{"mesh": 0, "index": 0, "weight": 100},
                                                         {"mesh": 1, "index": 0, "weight": 50}]},
              {"name": "Neutral", "presetName": "neutral", "binds": []},
              {"name": "Wink", "presetName": "unknown", "binds": [{"mesh": 0, "index": 1, "weight": 30},
                                                                  {"mesh": 0, "index": 1, "weight": 20}]},
              {"name": "EyeOnly", "presetName": "unknown", "binds": [{"mesh": 1, "index": 1, "weight": 100}]}]

    def mutate(doc, b):
        doc["extensions"] = {"VRM": {"blendShapeMaster": {"blendShapeGroups": groups}}}
    rig = read_gltf_rig(write_glb(tmp_path, mutate=mutate))
    assert rig.kind == "vrm0"
    assert rig.groups == {"a": [(0, 1.0), (3, 0.5)], "Wink": [(1, 0.5)], "EyeOnly": [(4, 1.0)]}
    assert list(rig.raw_groups) == rig.target_names
    caplog.set_level("INFO", logger="retarget_cli.io.rig.gltf")
    rig = read_gltf_rig(write_glb(tmp_path, mutate=mutate), meshes=["Head"])
    assert rig.groups == {"a": [(0, 1.0)], "Wink": [(1, 0.5)]}  # binds on the teeth are not chosen
    assert "expression 'a' keeps 1 binds, 1 are on meshes or targets not chosen" in caplog.text
    assert "expression 'EyeOnly' moves no chosen target" in caplog.text
    rig = read_gltf_rig(write_glb(tmp_path, mutate=mutate), targets=["smile"])  # no expression left: by name
    assert rig.kind == "gltf" and rig.groups == {"smile": [(0, 1.0)]}


def test_vrm1_expressions(tmp_path):
    def mutate(doc, b):
        doc["extensions"] = {"VRMC_vrm": {"specVersion": "1.0", "expressions": {
            "preset": {"aa": {"morphTargetBinds": [{"node": 1, "index": 0, "weight": 1.0},
                                                   {"node": 2, "index": 0, "weight": 0.5}]},
                       "blink": {"morphTargetBinds": [{"node": 1, "index": 1, "weight": 1.0},
                                                      {"node": 2, "index": 1, "weight": 0.25}]},
                       "neutral": {}},
            "custom": {"smirk": {"morphTargetBinds": [{"node": 1, "index": 2, "weight": 0.75}]}}}}}
    rig = read_gltf_rig(write_glb(tmp_path, mutate=mutate))
    assert rig.kind == "vrm1"
    assert rig.groups == {"aa": [(0, 1.0), (3, 0.5)], "blink": [(1, 1.0), (4, 0.25)], "smirk": [(2, 0.75)]}


def test_draco_primitive(tmp_path):
    draco = pytest.importorskip("DracoPy", reason="DracoPy is not installed")
    pts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.5]], dtype=np.float32)
    tris = np.array([[0, 1, 2], [0, 2, 3]])
    data = draco.encode(pts, tris, quantization_bits=16, preserve_order=True)
    b = Builder()
    bv = b.view(data)
    pos = b.accessor(4, 5126, "VEC3")
    idx = b.accessor(6, 5123, "SCALAR")
    tgt = b.floats(JAW)
    mesh = {"name": "D", "extras": {"targetNames": ["jawOpen"]}, "primitives": [
        {"attributes": {"POSITION": pos}, "indices": idx, "targets": [{"POSITION": tgt}],
         "extensions": {"KHR_draco_mesh_compression": {"bufferView": bv, "attributes": {"POSITION": 0}}}}]}
    p = tmp_path / "d.glb"
    p.write_bytes(glb_bytes(b.doc([mesh], [{"mesh": 0}], [0], extensionsRequired=["KHR_draco_mesh_compression"]),
                            b.bin))
    rig = read_gltf_rig(p)
    np.testing.assert_allclose(rig.neutral, pts, atol=1e-4)  # 16-bit quantization
    np.testing.assert_array_equal(rig.faces, tris)
    np.testing.assert_array_equal(rig.deltas[0], JAW)


# ---------------------------------------------------------------------- errors: one line, the tool's class
def _one_line_error(path, match, **kw):
    with pytest.raises(InputError, match=match) as info:
        read_gltf_rig(path, **kw)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(Path(path).name), msg
    return msg


def test_error_no_morph_targets(tmp_path):
    b = Builder()
    p = tmp_path / "plain.glb"
    mesh = {"name": "Body", "primitives": [{"attributes": {"POSITION": b.floats(HEAD_P)}}]}
    p.write_bytes(glb_bytes(b.doc([mesh], [{"mesh": 0}], [0]), b.bin))
    _one_line_error(p, r"no morph targets in any mesh \(meshes: Body\)")


def test_error_unsupported_required_extension(tmp_path):
    def mutate(doc, b):
        doc["extensionsRequired"] = EXTS + ["EXT_mesh_gpu_instancing"]
    _one_line_error(write_glb(tmp_path, mutate=mutate), "requires the glTF extension EXT_mesh_gpu_instancing")


def test_error_meshes_pattern_matches_nothing(tmp_path):
    msg = _one_line_error(write_glb(tmp_path), "'Hed' matches no mesh", meshes=["Hed"])
    assert msg.endswith("the file's meshes: Head, Teeth, Eye")
    _one_line_error(write_glb(tmp_path), "'jaw' matches no morph target", targets=["jaw"])


@pytest.mark.parametrize("uri", ["../rig.bin", "sub/../../rig.bin", "/etc/passwd", "http://example.com/rig.bin",
                                 "file:///etc/passwd", "C:/rig.bin", "..%2Frig.bin"])
def test_error_buffer_uri_outside_the_folder(tmp_path, uri):
    b, meshes, nodes, roots = build_scene()
    doc = b.doc(meshes, nodes, roots)
    doc["buffers"][0]["uri"] = uri
    (tmp_path / "rig.bin").write_bytes(bytes(b.bin))
    d = tmp_path / "sub"
    d.mkdir()
    p = d / "rig.gltf"
    p.write_text(json.dumps(doc))
    _one_line_error(p, "not a relative path inside the rig's folder")


def test_error_symlink_out_of_the_folder(tmp_path):
    b, meshes, nodes, roots = build_scene()
    (tmp_path / "outside.bin").write_bytes(bytes(b.bin))
    d = tmp_path / "rig"
    d.mkdir()
    (d / "link.bin").symlink_to(tmp_path / "outside.bin")
    doc = b.doc(meshes, nodes, roots)
    doc["buffers"][0]["uri"] = "link.bin"
    (d / "rig.gltf").write_text(json.dumps(doc))
    _one_line_error(d / "rig.gltf", "resolves outside the rig's folder")


def test_error_external_buffer_not_a_regular_file(tmp_path):
    b, meshes, nodes, roots = build_scene()
    doc = b.doc(meshes, nodes, roots)
    doc["buffers"][0]["uri"] = "pipe.bin"
    os.mkfifo(tmp_path / "pipe.bin")
    (tmp_path / "rig.gltf").write_text(json.dumps(doc))
    _one_line_error(tmp_path / "rig.gltf", "external buffer pipe.bin is not a regular file")


def test_error_truncated_files(tmp_path):
    data = write_glb(tmp_path).read_bytes()
    cut = tmp_path / "cut.glb"
    cut.write_bytes(data[:-40])
    _one_line_error(cut, "truncated: the GLB header declares")
    b, meshes, nodes, roots = build_scene()
    doc = b.doc(meshes, nodes, roots)
    doc["buffers"][0]["uri"] = "short.bin"
    (tmp_path / "short.bin").write_bytes(bytes(b.bin[:-8]))
    (tmp_path / "short.gltf").write_text(json.dumps(doc))
    _one_line_error(tmp_path / "short.gltf", f"truncated: buffer 0 declares {len(b.bin)} bytes, its data has")


def test_error_malformed_json(tmp_path):
    p = tmp_path / "bad.glb"
    js = b'{"asset": {"version": "2.0"}, "meshes": [ '
    p.write_bytes(struct.pack("<4sII", b"glTF", 2, 20 + len(js)) + struct.pack("<II", len(js), 0x4E4F534A) + js)
    _one_line_error(p, "malformed JSON")


def test_error_accessor_out_of_range(tmp_path):
    def mutate(doc, b):
        doc["accessors"][1]["count"] = 4000  # the head's POSITION: 4 elements of 12 bytes in its view
    _one_line_error(write_glb(tmp_path, mutate=mutate),
                    r"accessor 1 \(POSITION of mesh 'Head' primitive 0\): 4000 elements of 12 bytes from byte 0 "
                    r"run past the end of bufferView 1 \(48 bytes\)")

    def mutate_view(doc, b):
        doc["bufferViews"][1]["byteOffset"] = len(b.bin) - 8
    _one_line_error(write_glb(tmp_path, mutate=mutate_view), "bufferView 1 .* runs past the end of buffer 0")

    def mutate_sparse(doc, b):
        doc["accessors"][3]["sparse"]["count"] = 3  # 3 sparse indices in a 1-byte view
    _one_line_error(write_glb(tmp_path, mutate=mutate_sparse), "sparse indices: 3 elements of 1 bytes")


def _meshopt_ext(doc, mode):
    return next(v["extensions"]["EXT_meshopt_compression"] for v in doc["bufferViews"]
                if v.get("extensions", {}).get("EXT_meshopt_compression", {}).get("mode") == mode)


def test_missing_meshoptimizer_is_a_one_line_error(tmp_path, monkeypatch):
    if mo is None:
        pytest.skip("needs meshoptimizer to write the compressed file")
    p = write_glb(tmp_path, meshopt=True)
    monkeypatch.setattr(_gltfdata, "_meshopt", lambda: None)
    with pytest.raises(MissingExtraError, match=r"^rig.glb: EXT_meshopt_compression needs the meshoptimizer package"):
        read_gltf_rig(p)


@needs_meshopt
def test_error_meshopt_stream_that_lies_about_its_size(tmp_path):
    def lie(doc, b):  # 2 billion bytes claimed by a 40-byte stream (view length made consistent)
        v = next(v for v in doc["bufferViews"] if "extensions" in v)
        ext = v["extensions"]["EXT_meshopt_compression"]
        ext["count"] = 1 << 24
        v["byteLength"] = ext["count"] * ext["byteStride"]
    _one_line_error(write_glb(tmp_path, mutate=lie), "compressed bytes cannot hold 16777216 elements of 8 bytes")

    def inconsistent(doc, b):
        _meshopt_ext(doc, "TRIANGLES")["count"] = 6
    _one_line_error(write_glb(tmp_path, mutate=inconsistent), "6 elements of 2 bytes do not make the bufferView")

    def corrupt(doc, b):  # a plausible size, but the stream is cut short: the decoder refuses it
        ext = _meshopt_ext(doc, "ATTRIBUTES")
        ext["byteLength"] -= 20
    _one_line_error(write_glb(tmp_path, mutate=corrupt), "stream of .* bytes does not decode to 3 elements")


def test_error_node_cycle_and_bad_types(tmp_path):
    def cycle(doc, b):
        doc["nodes"][1]["children"] = [0]
    _one_line_error(write_glb(tmp_path, mutate=cycle), "node 0: its parents form a cycle")

    def bad(doc, b):
        doc["accessors"][1]["count"] = "4"
    _one_line_error(write_glb(tmp_path, mutate=bad), "'count' must be an integer")

    def huge(doc, b):
        doc["nodes"][0]["scale"] = [1e308] * 3
        doc["nodes"][1]["scale"] = [1e308] * 3
    _one_line_error(write_glb(tmp_path, mutate=huge), "node 1: its world transform is not finite")


@FUZZ
@given(st.data())
def test_fuzzed_files_raise_only_the_tools_errors(data):
    """Flipped bytes, truncations and JSON edits: a RetargetError of one line or a rig, never a crash or a hang."""
    with tempfile.TemporaryDirectory() as d:
        base = write_glb(Path(d)).read_bytes()
        kind = data.draw(st.sampled_from(["flip", "cut", "json"]))
        if kind == "flip":
            buf = bytearray(base)
            for _ in range(data.draw(st.integers(1, 8))):
                buf[data.draw(st.integers(0, len(buf) - 1))] = data.draw(st.integers(0, 255))
            blob = bytes(buf)
        elif kind == "cut":
            blob = base[:data.draw(st.integers(0, len(base)))]
        else:
            jlen = struct.unpack_from("<I", base, 12)[0]
            doc = json.loads(base[20:20 + jlen])
            binary = base[20 + jlen + 8:]
            section = data.draw(st.sampled_from(["accessors", "bufferViews", "nodes", "meshes", "buffers"]))
            entry = doc[section][data.draw(st.integers(0, len(doc[section]) - 1))]
            key = data.draw(st.sampled_from(sorted(entry) + ["count", "byteOffset", "byteLength", "children"]))
            entry[key] = data.draw(st.sampled_from([-1, 0, 1, 3, 7, 2**31, 2**63, 1.5, "x", None, [], {}, [0, 0],
                                                    True, float("nan")]))
            blob = glb_bytes(doc, binary)
        p = Path(d) / "f.glb"
        p.write_bytes(blob)
        try:
            read_gltf_rig(p)
        except RetargetError as exc:
            assert "\n" not in str(exc).strip(), str(exc)


# ---------------------------------------------------------------------- the real rigs (../shared/realdata)
needs_valid = pytest.mark.skipif(not VALID.is_file(), reason=f"real rig not found: {VALID} (needs ../shared/realdata)")
needs_godette = pytest.mark.skipif(not GODETTE.is_file(),
                                   reason=f"real rig not found: {GODETTE} (needs ../shared/realdata)")


@needs_valid
@needs_meshopt
def test_real_valid_glb():
    rig = read_gltf_rig(VALID)
    assert [(n, b - a) for n, a, b in rig.mesh_ranges] == [("H_DDS_HighRes", 22249), ("h_TeethDown", 4737)]
    assert rig.target_meshes.count("H_DDS_HighRes") == 65 and rig.target_meshes.count("h_TeethDown") == 31
    assert rig.faces.min() == 0 and rig.faces.max() == len(rig.neutral) - 1
    head = rig.neutral[:22249]
    assert 1.6 < head[:, 1].max() - head[:, 1].min() < 1.9  # a whole body, metres
    top = head[head[:, 1] > head[:, 1].max() - 0.27]
    assert 0.15 < np.ptp(top[:, 2]) < 0.3
    # MouthOpen moves the chin (front-most midline vertex just under the lips) down, and the lower teeth with it
    cand = np.nonzero((np.abs(head[:, 0]) < 0.004) & (head[:, 1] > 1.48) & (head[:, 1] < 1.51))[0]
    chin = cand[np.argmax(head[cand, 2])]
    group = rig.groups["MouthOpen_h"]
    assert [rig.target_names[k] for k, _ in group] == ["h_expressions.MouthOpen_h", "h_teeth.t_MouthOpen_h"]
    assert rig.deltas[group[0][0], chin, 1] < -0.01
    assert rig.deltas[group[1][0], 22249:, 1].mean() < -0.005


@needs_valid
@needs_meshopt
def test_real_valid_meshopt_streams_match_a_decoder_written_from_the_spec():
    """The wrapper's decode of every unfiltered stream of the real file against meshopt_spec_decoder (first 4096)."""
    from meshopt_spec_decoder import decode_attributes, decode_triangles

    f = _gltfdata.GltfFile(VALID)
    checked = []
    for i, bv in enumerate(f.json["bufferViews"]):
        ext = bv.get("extensions", {}).get("EXT_meshopt_compression")
        if not ext or ext.get("filter", "NONE") != "NONE":
            continue
        src = bytes(f.bin[ext["byteOffset"]:ext["byteOffset"] + ext["byteLength"]])
        ours = bytes(f.view(i, "test"))
        if ext["mode"] == "TRIANGLES":
            dtype = "<u2" if ext["byteStride"] == 2 else "<u4"
            np.testing.assert_array_equal(np.frombuffer(ours, dtype), decode_triangles(src, ext["count"]))
        else:
            n = min(ext["count"], 4096)
            assert ours[:n * ext["byteStride"]] == decode_attributes(src, ext["count"], ext["byteStride"], n)
        checked.append(ext["mode"])
    assert checked.count("TRIANGLES") == 1 and checked.count("ATTRIBUTES") == 3


@needs_godette
def test_real_godette_vrm_matches_pygltflib():
    pygltflib = pytest.importorskip("pygltflib")
    rig = read_gltf_rig(GODETTE)
    g = pygltflib.GLTF2().load_binary(str(GODETTE))
    blob = g.binary_blob()

    def raw(i):
        a = g.accessors[i]
        bv = g.bufferViews[a.bufferView]
        n = {"SCALAR": 1, "VEC3": 3}[a.type]
        dt = {5126: "<f4", 5123: "<u2", 5125: "<u4"}[a.componentType]
        return np.frombuffer(blob, dt, a.count * n, (bv.byteOffset or 0) + (a.byteOffset or 0)).reshape(a.count, n)

    prim = g.meshes[0].primitives[0]
    assert rig.kind == "vrm0" and rig.mesh_ranges == [("FaceMesh", 0, 630)] and len(rig.target_names) == 15
    np.testing.assert_allclose(rig.neutral, raw(prim.attributes.POSITION), rtol=0, atol=1e-7)
    np.testing.assert_array_equal(rig.faces, raw(prim.indices).reshape(-1, 3))
    for k, t in enumerate(prim.targets):
        np.testing.assert_allclose(rig.deltas[k], raw(t["POSITION"] if isinstance(t, dict) else t.POSITION),
                                   rtol=0, atol=1e-7)
    assert len(rig.groups) == 16 and "neutral" not in rig.groups  # 17 groups, 'neutral' binds nothing
    assert rig.groups["blink"] == [(3, 1.0), (4, 1.0)] and rig.groups["joy"] == [(9, 0.5), (10, 0.25)]
