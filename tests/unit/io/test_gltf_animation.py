"""The animated copy of a character's GLB/glTF/VRM (apply --format same) and its VRM Animation, read back.

Small synthetic files written here: a head and teeth that share the slider ``jawOpen`` (two meshes, one slider),
quantized teeth (meshopt-compressed or not), an eye without targets, a skin, a material with an embedded
texture, an animation already in the file, unknown extensions and extras; VRM 0.x and 1.0 variants with
expressions and a humanoid. Each copy is read back with ``read_gltf_rig`` and with ``pygltflib`` (an independent
reader): nodes, meshes and every original JSON entry unchanged, the source's BIN bytes unchanged, the new
animation's morph weights equal to the curves at every frame.
"""

from __future__ import annotations

import json
import logging
import os
import struct
import tempfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from retarget_cli.errors import InputError, RetargetError
from retarget_cli.io.exports import EXPORTS, SameExport
from retarget_cli.io.gltf_animation import (
    ANIMATION_NAME,
    animated_copy_bytes,
    copy_groups,
    vrma_bytes,
    write_animated_copy,
    write_vrma,
)
from retarget_cli.io.rig.gltf import read_gltf_rig

pygltflib = pytest.importorskip("pygltflib")
try:
    import meshoptimizer as mo
except ImportError:  # the optional extra 'rigs'
    mo = None
needs_meshopt = pytest.mark.skipif(mo is None, reason="meshoptimizer (the 'rigs' extra) is not installed")

REAL = Path(__file__).resolve().parents[3].parent / "shared" / "realdata" / "rigs"
VALID = REAL / "valid-glb" / "White_F_2_Busi.glb"
GODETTE = REAL / "godette-vrm" / "Godette_vrm_v4.vrm"
T, FPS = 9, 24.0
FUZZ = settings(max_examples=int(os.environ.get("RETARGET_FUZZ_EXAMPLES", "150")), deadline=None,
                suppress_health_check=[HealthCheck.too_slow])
HEAD_P = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
JAW = np.array([[0, -0.25, 0], [0, -0.25, 0], [0, 0, 0], [0, 0, 0]], np.float32)
BLINK = np.array([[0, 0, 0], [0, 0, 0], [0, -0.1, 0], [0, -0.1, 0]], np.float32)
TEETH_Q = np.array([[32767, 0, 0, 0], [0, 32767, 0, 0], [-32767, -32767, 0, 0]], "<i2")
T_JAW = np.array([[0, -0.2, 0], [0, -0.2, 0], [0, 0.1, 0]], np.float32)
PNG = b"\x89PNG\r\n\x1a\n" + bytes(range(40))  # not a decodable picture: only its bytes are compared


# ---------------------------------------------------------------------- a small glTF writer
class Builder:
    """Buffer 0 (the BIN chunk), an optional meshopt fallback buffer 1, views and accessors."""

    def __init__(self):
        self.bin, self.views, self.accessors, self.fallback = bytearray(), [], [], 0

    def view(self, data: bytes, stride=None) -> int:
        self.bin += b"\0" * (-len(self.bin) % 4)
        v = {"buffer": 0, "byteOffset": len(self.bin), "byteLength": len(data)}
        if stride:
            v["byteStride"] = stride
        self.bin += data
        self.views.append(v)
        return len(self.views) - 1

    def meshopt_view(self, data: bytes, count: int, stride: int) -> int:
        encoded = mo.encode_vertex_buffer(np.frombuffer(data, np.float32), count, stride)
        self.bin += b"\0" * (-len(self.bin) % 4)
        ext = {"buffer": 0, "byteOffset": len(self.bin), "byteLength": len(encoded), "byteStride": stride,
               "count": count, "mode": "ATTRIBUTES"}
        self.bin += encoded
        self.views.append({"buffer": 1, "byteOffset": self.fallback, "byteLength": count * stride,
                           "byteStride": stride, "extensions": {"EXT_meshopt_compression": ext}})
        self.fallback += count * stride
        return len(self.views) - 1

    def accessor(self, view, count, ctype, atype, **kw) -> int:
        self.accessors.append({"bufferView": view, "count": count, "componentType": ctype, "type": atype, **kw})
        return len(self.accessors) - 1

    def floats(self, arr, atype="VEC3", **kw) -> int:
        arr = np.asarray(arr, "<f4")
        return self.accessor(self.view(arr.tobytes()), len(arr), 5126, atype, **kw)


def scene(meshopt=False, vrm=None) -> tuple[dict, bytes]:
    """(JSON, BIN) of the synthetic character; *vrm* in (None, 0, 1)."""
    b = Builder()
    idx = b.accessor(b.view(np.array([0, 1, 2, 0, 2, 3], "<u2").tobytes()), 6, 5123, "SCALAR")
    uv = b.floats(HEAD_P[:, :2], "VEC2")
    head = {"name": "Head", "weights": [0.0, 0.25], "extras": {"targetNames": ["jawOpen", "blink"]},
            "primitives": [{"attributes": {"POSITION": b.floats(HEAD_P, min=[0, 0, 0], max=[1, 1, 0]),
                                           "TEXCOORD_0": uv}, "indices": idx, "material": 0,
                            "targets": [{"POSITION": b.floats(JAW)}, {"POSITION": b.floats(BLINK)}]}]}
    tview = b.meshopt_view(TEETH_Q.tobytes(), 3, 8) if meshopt else b.view(TEETH_Q.tobytes(), stride=8)
    joints = b.accessor(b.view(np.zeros((3, 4), "<u1").tobytes()), 3, 5121, "VEC4")
    wts = b.floats(np.tile([1.0, 0, 0, 0], (3, 1)), "VEC4")
    teeth = {"name": "Teeth", "extras": {"targetNames": ["jawOpen"]},
             "primitives": [{"attributes": {"POSITION": b.accessor(tview, 3, 5122, "VEC3", normalized=True),
                                            "JOINTS_0": joints, "WEIGHTS_0": wts},
                             "targets": [{"POSITION": b.floats(T_JAW)}]}]}
    eye = {"name": "Eye", "primitives": [{"attributes": {"POSITION": b.floats(HEAD_P[:3] * 0.1)}}]}
    ibm = b.floats(np.eye(4)[None].repeat(1, 0).reshape(1, 16), "MAT4")
    image = b.view(PNG)
    old_t = b.floats([[0.0], [1.0]], "SCALAR", min=[0.0], max=[1.0])
    old_r = b.floats([[0, 0, 0, 1], [0, 0.7071068, 0, 0.7071068]], "VEC4")
    nodes = [{"name": "Hips", "translation": [0, 1.0, 0.5], "children": [1, 4]},
             {"name": "Spine", "translation": [0, 0.25, 0], "children": [2]},
             {"name": "HeadBone", "translation": [0, 0.5, 0], "children": [3], "extras": {"keep": "me"}},
             {"name": "HeadNode", "mesh": 0, "translation": [0, 0.1, 0]},
             {"name": "TeethNode", "mesh": 1, "skin": 0},
             {"name": "EyeNode", "mesh": 2, "extensions": {"EXT_made_up": {"answer": 42}}}]
    doc = {"asset": {"version": "2.0", "generator": "the test", "copyright": "CC0 \u00e9t\u00e9"},
           "extensionsUsed": ["KHR_mesh_quantization", "EXT_made_up"] + (["EXT_meshopt_compression"] * meshopt),
           "extensionsRequired": ["KHR_mesh_quantization"] + (["EXT_meshopt_compression"] * meshopt),
           "scene": 0, "scenes": [{"nodes": [0, 5]}], "nodes": nodes, "meshes": [head, teeth, eye],
           "skins": [{"joints": [0], "inverseBindMatrices": ibm}],
           "materials": [{"name": "Skin", "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}},
                          "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 2.5}}}],
           "textures": [{"source": 0, "sampler": 0}], "samplers": [{"magFilter": 9729}],
           "images": [{"bufferView": image, "mimeType": "image/png"}],
           "animations": [{"name": "wave", "channels": [{"sampler": 0, "target": {"node": 0, "path": "rotation"}}],
                           "samplers": [{"input": old_t, "output": old_r}]}],
           "extensions": {"EXT_made_up": {"list": [1, 2.5, 1e-07, "x"]}}, "extras": {"author": "nobody"},
           "accessors": b.accessors, "bufferViews": b.views, "buffers": [{"byteLength": len(b.bin)}]}
    if meshopt:
        doc["buffers"].append({"byteLength": b.fallback, "extensions": {"EXT_meshopt_compression": {"fallback": True}}})
    if vrm == 0:
        doc["extensions"]["VRM"] = {"specVersion": "0.0", "humanoid": {"humanBones": [
            {"bone": "hips", "node": 0}, {"bone": "spine", "node": 1}, {"bone": "head", "node": 2},
            {"bone": "leftThumbProximal", "node": 5}]},
            "blendShapeMaster": {"blendShapeGroups": [
                {"name": "A", "presetName": "a", "binds": [{"mesh": 0, "index": 0, "weight": 100},
                                                           {"mesh": 1, "index": 0, "weight": 50}]},
                {"name": "Blink", "presetName": "blink", "binds": [{"mesh": 0, "index": 1, "weight": 100}]},
                {"name": "Smirk", "presetName": "unknown", "binds": [{"mesh": 0, "index": 1, "weight": 30}]},
                {"name": "LookUp", "presetName": "lookup", "binds": [{"mesh": 0, "index": 1, "weight": 10}]}]}}
        doc["extensionsUsed"].append("VRM")
    elif vrm == 1:
        doc["extensions"]["VRMC_vrm"] = {"specVersion": "1.0", "humanoid": {"humanBones": {
            "hips": {"node": 0}, "spine": {"node": 1}, "head": {"node": 2}, "leftEye": {"node": 5}}},
            "expressions": {"preset": {"aa": {"morphTargetBinds": [{"node": 3, "index": 0, "weight": 1.0},
                                                                   {"node": 4, "index": 0, "weight": 0.5}]},
                                       "blink": {"morphTargetBinds": [{"node": 3, "index": 1, "weight": 1.0}]},
                                       "lookUp": {"morphTargetBinds": [{"node": 3, "index": 1, "weight": 0.1}]}},
                            "custom": {"Smirk": {"morphTargetBinds": [{"node": 3, "index": 1, "weight": 0.3}]}}}}
        doc["extensionsUsed"].append("VRMC_vrm")
    return doc, bytes(b.bin)


def glb_bytes(doc: dict, binary: bytes) -> bytes:
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    binary = bytes(binary) + b"\0" * (-len(binary) % 4)
    body = struct.pack("<II", len(js), 0x4E4F534A) + js + struct.pack("<II", len(binary), 0x004E4942) + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def write_source(tmp_path: Path, name="char.glb", **kw) -> tuple[Path, dict, bytes]:
    doc, binary = scene(**kw)
    p = tmp_path / name
    p.write_bytes(glb_bytes(doc, binary))
    return p, doc, binary


def chunks(data: bytes) -> tuple[dict, bytes]:
    """(JSON, BIN) of a GLB, with its layout checked (glTF 2.0 §4.4)."""
    magic, version, length = struct.unpack_from("<4sII", data)
    assert (magic, version, length) == (b"glTF", 2, len(data))
    n, kind = struct.unpack_from("<II", data, 12)
    assert kind == 0x4E4F534A and n % 4 == 0
    doc = json.loads(data[20:20 + n])
    m, kind = struct.unpack_from("<II", data, 20 + n)
    assert kind == 0x004E4942 and m % 4 == 0 and 28 + n + m == len(data)
    return doc, data[28 + n:]


def curves_for(names, seed=0):
    """Ramps and a blink over [0, 1], one column past the range (clipped by the writer)."""
    rng = np.random.default_rng(seed)
    C = rng.uniform(0, 1, (T, len(names)))
    C[:, 0] = np.linspace(-0.2, 1.3, T)
    return C


def pyg_floats(g, index: int) -> np.ndarray:
    """Accessor *index* of a pygltflib document as float32 (count, components)."""
    a = g.accessors[index]
    bv = g.bufferViews[a.bufferView]
    n = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[a.type]
    assert a.componentType == 5126 and (bv.byteOffset or 0) % 4 == 0
    return np.frombuffer(g.binary_blob(), "<f4", a.count * n, (bv.byteOffset or 0) + (a.byteOffset or 0)).reshape(
        a.count, n)


def animation_weights(path: Path) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """(times, {node: (T, n) weights}) of the copy's last animation, read by pygltflib."""
    g = pygltflib.GLTF2().load_binary(str(path))
    anim = g.animations[-1]
    assert anim.name == ANIMATION_NAME
    out, times = {}, None
    for ch in anim.channels:
        s = anim.samplers[ch.sampler]
        assert ch.target.path == "weights" and s.interpolation == "LINEAR"
        t = pyg_floats(g, s.input)[:, 0]
        times = t if times is None else times
        np.testing.assert_array_equal(t, times)
        out[ch.target.node] = pyg_floats(g, s.output).reshape(len(t), -1)
    return times, out


def assert_original_kept(src_doc: dict, src_bin: bytes, copy: bytes, *, buffer0=("byteLength",)):
    """Every original JSON entry unchanged (buffer 0 aside from *buffer0*), the source's BIN bytes unchanged."""
    doc, binary = chunks(copy)
    assert set(doc) == set(src_doc) | {"animations"}
    for key, value in src_doc.items():
        if key == "buffers":
            assert {k: v for k, v in doc[key][0].items() if k not in buffer0} == \
                   {k: v for k, v in value[0].items() if k not in buffer0}
            assert doc[key][1:] == value[1:]
        elif isinstance(value, list) and key not in ("extensionsUsed", "extensionsRequired"):
            assert doc[key][:len(value)] == value, key
        else:
            assert doc[key] == value, key
    assert binary[:len(src_bin)] == src_bin
    assert doc["buffers"][0]["byteLength"] <= len(binary) < doc["buffers"][0]["byteLength"] + 4
    for v in doc["bufferViews"][len(src_doc["bufferViews"]):]:
        assert v["buffer"] == 0 and v["byteOffset"] % 4 == 0 and v["byteOffset"] >= len(src_bin)
        assert "byteStride" not in v and "target" not in v
    return doc


def expected_weights(C, names, binds, defaults):
    """{node: (T, n)}: *binds* maps (node, k) to [(slider, weight)]; targets not bound keep *defaults*."""
    out = {node: np.tile(np.asarray(d, float), (len(C), 1)) for node, d in defaults.items()}
    Cc = np.clip(C, 0, 1)
    for (node, k), terms in binds.items():
        out[node][:, k] = sum(Cc[:, names.index(s)] * w for s, w in terms)
    return out


# ---------------------------------------------------------------------- the copy
@pytest.mark.parametrize("meshopt", [False, pytest.param(True, marks=needs_meshopt)])
def test_two_meshes_one_slider_copy_reads_back(tmp_path, meshopt):
    src, src_doc, src_bin = write_source(tmp_path, meshopt=meshopt)
    rig = read_gltf_rig(src)
    assert rig.groups["jawOpen"] == [(0, 1.0), (2, 1.0)]  # head and teeth: one slider
    names = list(rig.groups)  # jawOpen, blink
    C = curves_for(names)
    groups, missing = copy_groups(rig, ["jawOpen"])
    assert groups == {"jawOpen": [(3, 0, 1.0), (4, 0, 1.0)]} and not missing
    out = write_animated_copy(tmp_path / "out" / "char_animated.glb", src, C[:, :1], ["jawOpen"], FPS, groups,
                              lower=[0.0], upper=[1.0])
    data = out.read_bytes()
    doc = assert_original_kept(src_doc, src_bin, data)
    assert len(doc["animations"]) == 2 and doc["animations"][0] == src_doc["animations"][0]
    # the rig read back from the copy is the source's rig
    back = read_gltf_rig(out)
    np.testing.assert_array_equal(back.neutral, rig.neutral)
    np.testing.assert_array_equal(back.deltas, rig.deltas)
    assert back.groups == rig.groups and back.target_names == rig.target_names
    # pygltflib: same nodes and meshes; the morph weights are the curve (clipped to [0, 1]) at every frame
    g = pygltflib.GLTF2().load_binary(str(out))
    assert len(g.nodes) == len(src_doc["nodes"]) and len(g.meshes) == len(src_doc["meshes"])
    times, W = animation_weights(out)
    np.testing.assert_allclose(times, np.arange(T) / FPS, rtol=0, atol=1e-6)
    assert sorted(W) == [3, 4]  # the head and teeth nodes; the eye has no targets
    want = expected_weights(C, names, {(3, 0): [("jawOpen", 1.0)], (4, 0): [("jawOpen", 1.0)]},
                            {3: [0.0, 0.25], 4: [0.0]})
    for node in W:
        np.testing.assert_allclose(W[node], want[node], rtol=0, atol=1e-6)
    assert W[3][0, 0] == 0 and W[3][-1, 0] == 1  # clipped to the slider's range
    np.testing.assert_array_equal(W[3][:, 1], 0.25)  # blink has no curve: the mesh's default weight
    acc = g.accessors[g.animations[-1].samplers[0].input]
    assert acc.min == [0.0] and acc.max == [pytest.approx((T - 1) / FPS)]
    # deterministic
    assert animated_copy_bytes(src, C[:, :1], ["jawOpen"], FPS, groups, lower=[0.0], upper=[1.0]) == data


def test_gltf_source_with_external_buffer_and_image_becomes_one_glb(tmp_path):
    doc, binary = scene()
    folder = tmp_path / "char"
    folder.mkdir()
    (folder / "char data.bin").write_bytes(binary)
    (folder / "skin.png").write_bytes(PNG)
    doc["buffers"][0]["uri"] = "char%20data.bin"
    doc["images"].append({"uri": "skin.png"})
    (folder / "char.gltf").write_text(json.dumps(doc))
    rig = read_gltf_rig(folder / "char.gltf")
    groups, _ = copy_groups(rig, ["jawOpen", "blink"])
    C = curves_for(["jawOpen", "blink"], seed=1)
    out = write_animated_copy(tmp_path / "out.glb", folder / "char.gltf", C, ["jawOpen", "blink"], FPS, groups,
                              lower=[0, 0], upper=[1, 1])
    copy, _ = chunks(out.read_bytes())
    assert "uri" not in copy["buffers"][0]  # buffer 0 is the BIN chunk now
    uri = copy["images"][1]["uri"]
    assert uri.startswith("data:image/png;base64,")
    import base64

    assert base64.b64decode(uri.split(",", 1)[1]) == PNG
    doc["images"][1] = copy["images"][1]
    assert_original_kept(doc, binary, out.read_bytes(), buffer0=("byteLength", "uri"))
    back = read_gltf_rig(out)
    np.testing.assert_array_equal(back.deltas, rig.deltas)
    _, W = animation_weights(out)
    want = expected_weights(C, ["jawOpen", "blink"], {(3, 0): [("jawOpen", 1)], (4, 0): [("jawOpen", 1)],
                                                      (3, 1): [("blink", 1)]}, {3: [0, 0.25], 4: [0]})
    for node in W:
        np.testing.assert_allclose(W[node], want[node], rtol=0, atol=1e-6)


@pytest.mark.parametrize("uri", ["../secret.png", "/etc/hostname", "http://example.com/a.png", "sub/../../x.png"])
def test_image_uri_outside_the_folder_is_refused(tmp_path, uri):
    (tmp_path / "a").mkdir()
    src, doc, binary = write_source(tmp_path / "a")
    doc["images"].append({"uri": uri})
    (tmp_path / "secret.png").write_bytes(PNG)
    src.write_bytes(glb_bytes(doc, binary))
    with pytest.raises(InputError, match=r"char.glb: image 1: uri .* (not a relative path inside|outside)") as info:
        write_animated_copy(tmp_path / "out.glb", src, np.zeros((T, 1)), ["jawOpen"], FPS,
                            {"jawOpen": [(3, 0, 1.0)]})
    assert "\n" not in str(info.value) and not (tmp_path / "out.glb").exists()


def test_bad_binds_and_a_file_without_targets_are_one_line_errors(tmp_path):
    src, doc, binary = write_source(tmp_path)
    with pytest.raises(InputError, match="slider 'jawOpen': node 5 morph target 0 is not a morph target"):
        animated_copy_bytes(src, np.zeros((T, 1)), ["jawOpen"], FPS, {"jawOpen": [(5, 0, 1.0)]})
    for mesh in doc["meshes"]:
        for prim in mesh["primitives"]:
            prim.pop("targets", None)
    src.write_bytes(glb_bytes(doc, binary))
    with pytest.raises(InputError, match="char.glb: no node has a mesh with morph targets"):
        animated_copy_bytes(src, np.zeros((T, 1)), ["jawOpen"], FPS, {})


@FUZZ
@given(st.data())
def test_fuzzed_sources_raise_only_the_tools_errors(data):
    """JSON edits, flipped bytes and cuts of a VRM source: a copy and a .vrma, or a one-line RetargetError."""
    with tempfile.TemporaryDirectory() as d:
        doc, binary = scene(vrm=data.draw(st.sampled_from([0, 1])))
        kind = data.draw(st.sampled_from(["json", "json", "flip", "cut"]))
        if kind == "json":
            where = data.draw(st.sampled_from(["accessors", "bufferViews", "nodes", "meshes", "buffers", "images",
                                               "skins", "animations", "extensions", "top"]))
            entry = doc if where == "top" else doc[where]
            if isinstance(entry, list):
                entry = entry[data.draw(st.integers(0, len(entry) - 1))]
            if where == "extensions":
                entry = entry.get("VRM") or entry["VRMC_vrm"]
                entry = entry[data.draw(st.sampled_from(sorted(k for k in entry if k != "specVersion")))]
            key = data.draw(st.sampled_from(sorted(entry) + ["uri", "weights", "children", "humanBones"]))
            entry[key] = data.draw(st.sampled_from([-1, 0, 1, 7, 2**31, 1.5, "x", "../x.bin", None, [], {}, [0, 0],
                                                    True, [{"node": 99}], {"hips": {"node": -1}}]))
            blob = glb_bytes(doc, binary)
        else:
            blob = glb_bytes(doc, binary)
            if kind == "flip":
                buf = bytearray(blob)
                for _ in range(data.draw(st.integers(1, 8))):
                    buf[data.draw(st.integers(0, len(buf) - 1))] = data.draw(st.integers(0, 255))
                blob = bytes(buf)
            else:
                blob = blob[:data.draw(st.integers(0, len(blob)))]
        src = Path(d) / "f.vrm"
        src.write_bytes(blob)
        C = np.linspace(0, 1, 2 * T).reshape(T, 2)
        for call in (lambda: animated_copy_bytes(src, C, ["a", "b"], FPS, {"a": [(3, 0, 1.0)], "b": [(4, 0, 0.5)]}),
                     lambda: vrma_bytes(src, C, ["a", "blink"], FPS)):
            try:
                call()
            except RetargetError as exc:
                assert "\n" not in str(exc).strip(), str(exc)


# ---------------------------------------------------------------------- VRM: the copy and the .vrma
def vrma_tracks(path: Path) -> tuple[dict, dict[tuple[str, str], np.ndarray]]:
    """(the VRMC_vrm_animation extension, {(section, expression): (T,) weights}) of a .vrma, read by pygltflib."""
    g = pygltflib.GLTF2().load_binary(str(path))
    ext = g.extensions["VRMC_vrm_animation"]
    assert "VRMC_vrm_animation" in g.extensionsUsed and ext["specVersion"] == "1.0"
    by_node = {e["node"]: (section, name) for section, table in ext["expressions"].items()
               for name, e in table.items()}
    tracks = {}
    for ch in g.animations[0].channels:
        s = g.animations[0].samplers[ch.sampler]
        assert ch.target.path == "translation" and s.interpolation == "LINEAR"
        np.testing.assert_allclose(pyg_floats(g, s.input)[:, 0], np.arange(T) / FPS, rtol=0, atol=1e-6)
        xyz = pyg_floats(g, s.output)
        assert not xyz[:, 1:].any()
        tracks[by_node[ch.target.node]] = xyz[:, 0]
    assert g.nodes[g.scenes[0].nodes[0]].name == "hips"
    return ext, tracks


@pytest.mark.parametrize("version", [0, 1])
def test_vrm_copy_and_vrma(tmp_path, version):
    src, src_doc, src_bin = write_source(tmp_path, name="avatar.vrm", vrm=version)
    rig = read_gltf_rig(src)
    names = ["a", "blink", "Smirk", "lookup"] if version == 0 else ["aa", "blink", "Smirk", "lookUp"]
    assert sorted(rig.groups) == sorted(names)
    C = curves_for(names, seed=2)
    groups, missing = copy_groups(rig, names)
    assert not missing
    out = write_animated_copy(tmp_path / "avatar_animated.glb", src, C, names, FPS, groups, lower=np.zeros(4),
                              upper=np.ones(4))
    doc = assert_original_kept(src_doc, src_bin, out.read_bytes())
    assert doc["extensionsUsed"] == src_doc["extensionsUsed"]  # VRM metadata kept, no extension added
    _, W = animation_weights(out)
    a, blink, smirk, look = names
    want = expected_weights(C, names, {(3, 0): [(a, 1.0)], (4, 0): [(a, 0.5)],
                                       (3, 1): [(blink, 1.0), (smirk, 0.3), (look, 0.1)]}, {3: [0, 0.25], 4: [0]})
    for node in W:
        np.testing.assert_allclose(W[node], want[node], rtol=0, atol=1e-6)
    # the VRM Animation: expression tracks of the expressions, VRM 1.0 names, gaze left out
    vrma = write_vrma(tmp_path / "avatar_animated.vrma", src, C, names, FPS, lower=np.zeros(4), upper=np.ones(4))
    ext, tracks = vrma_tracks(vrma)
    assert sorted(tracks) == [("custom", "Smirk"), ("preset", "aa"), ("preset", "blink")]
    for (section, expr), name in zip([("preset", "aa"), ("preset", "blink"), ("custom", "Smirk")], names):
        np.testing.assert_allclose(tracks[(section, expr)], np.clip(C[:, names.index(name)], 0, 1), rtol=0,
                                   atol=1e-6)
    # the humanoid at rest: world positions (VRM 0.x turned to face +z), the source's hierarchy
    g = pygltflib.GLTF2().load_binary(str(vrma))
    bones = {b: e["node"] for b, e in ext["humanoid"]["humanBones"].items()}
    assert set(bones) == ({"hips", "spine", "head", "leftThumbMetacarpal"} if version == 0 else
                          {"hips", "spine", "head"})  # VRM 0.x thumbs renamed; no eyes in a .vrma
    flip = [-1, 1, -1] if version == 0 else [1, 1, 1]
    np.testing.assert_allclose(g.nodes[bones["hips"]].translation, np.multiply([0, 1.0, 0.5], flip))
    np.testing.assert_allclose(g.nodes[bones["head"]].translation, [0, 0.5, 0])
    assert g.nodes[bones["spine"]].children == [bones["head"]]
    assert vrma.read_bytes() == vrma_bytes(src, C, names, FPS, lower=np.zeros(4), upper=np.ones(4))


def test_plain_glb_has_no_vrma(tmp_path, caplog):
    src, _, _ = write_source(tmp_path)
    with caplog.at_level(logging.INFO, logger="retarget_cli.io.gltf_animation"):
        assert write_vrma(tmp_path / "x.vrma", src, np.zeros((T, 1)), ["jawOpen"], FPS) is None
    assert not (tmp_path / "x.vrma").exists() and "no .vrma written" in caplog.text


# ---------------------------------------------------------------------- the exporter (apply --format same)
def _ctx(tmp_path, source, names, curves, rig_file=None):
    spec = SimpleNamespace(source=source)
    rig = SimpleNamespace(spec=spec, names=names, lower=np.zeros(len(names)), upper=np.ones(len(names)))
    out = tmp_path / "out"
    out.mkdir(exist_ok=True)
    return SimpleNamespace(out=out, fps=FPS, rig=rig, curves=curves, rig_file=rig_file, weights=tmp_path / "w.npz",
                           targets=tmp_path / "t.yaml", landmarks=None)


def test_same_export_writes_the_copy_and_vrma(tmp_path, caplog):
    assert EXPORTS["same"] is SameExport and SameExport.needs_rig
    src, _, _ = write_source(tmp_path, name="avatar.vrm", vrm=1)
    names = ["aa", "blink", "notInTheFile"]
    C = curves_for(names, seed=3)
    ctx = _ctx(tmp_path, src, names, C)
    SameExport.check_context(ctx)
    with caplog.at_level(logging.WARNING):
        written = SameExport(ctx).finish()
    assert written == [ctx.out / "avatar_animated.glb", ctx.out / "avatar_animated.vrma"]
    assert "1 slider(s) are not sliders or morph targets of the file" in caplog.text and "notInTheFile" in caplog.text
    _, W = animation_weights(written[0])
    np.testing.assert_allclose(W[4][:, 0], 0.5 * np.clip(C[:, 0], 0, 1), rtol=0, atol=1e-6)
    _, tracks = vrma_tracks(written[1])
    assert sorted(tracks) == [("preset", "aa"), ("preset", "blink")]


def test_same_export_needs_a_rig_from_a_gltf_file(tmp_path):
    for source in (None, tmp_path / "rig" / "neutral.obj"):
        ctx = _ctx(tmp_path, source, ["jawOpen"], np.zeros((T, 1)), rig_file=tmp_path / "rig" / "rig.yaml")
        with pytest.raises(InputError) as info:
            SameExport.check_context(ctx)
        assert str(info.value) == (f"{tmp_path / 'rig' / 'rig.yaml'}: apply.formats: same needs a rig read from a "
                                   ".glb/.gltf/.vrm or .usd/.usda/.usdc/.usdz file (rig.yaml source:)")
    assert not any((tmp_path / "out").iterdir())


def test_apply_format_same_with_a_rig_of_objs_is_an_error_before_any_frame(tmp_path):
    from retarget_cli.io.editfiles import write_animation
    from retarget_cli.io.obj import format_obj
    from retarget_cli.io.stagefiles import save_weights, write_targets
    from retarget_cli.stages import run_apply

    r = tmp_path / "rig"
    r.mkdir()
    faces = np.array([[0, 1, 2, 3]])
    (r / "neutral.obj").write_bytes(format_obj(HEAD_P.astype(float), faces))
    (r / "jaw.obj").write_bytes(format_obj((HEAD_P + JAW).astype(float), faces))
    (r / "rig.yaml").write_text("neutral: neutral.obj\nshapes:\n  jawOpen: jaw.obj\n")
    t = tmp_path / "t"
    t.mkdir()
    (t / "k0.obj").write_bytes(format_obj(HEAD_P.astype(float), faces))
    (t / "k1.obj").write_bytes(format_obj((HEAD_P + JAW).astype(float), faces))
    write_animation(t / "sliders.npz", ["jawOpen"], np.array([[0.0], [1.0]]), np.array([0, 3]))
    write_targets(t / "targets.yaml", {"face": {"keys": {0: "k0.obj", 3: "k1.obj"}}}, rig="../rig/rig.yaml",
                  sliders="sliders.npz")
    W = np.array([[1.0, 0.0], [0.5, 0.5], [0.0, 1.0]])
    save_weights(tmp_path / "weights.npz", {"face": (W, np.array([0, 3]), np.zeros(3))}, {"fps": FPS})
    out = tmp_path / "out"
    with pytest.raises(InputError, match=r"rig.yaml: apply.formats: same needs a rig read from a "
                                         r"\.glb/\.gltf/\.vrm or \.usd/\.usda/\.usdc/\.usdz file \(rig.yaml source:\)"):
        run_apply(weights=tmp_path / "weights.npz", targets=t / "targets.yaml", output=out, formats=["obj", "same"])
    assert not list(out.glob("*.obj")) and not list(out.glob("*.glb"))


# ---------------------------------------------------------------------- the two real rigs (skipped without them)
@pytest.mark.skipif(not VALID.is_file() or mo is None, reason="needs ../shared/realdata and meshoptimizer")
def test_real_valid_glb_copy(tmp_path):
    rig = read_gltf_rig(VALID)
    names = ["MouthOpen_h", "LeyeClose_h", "ReyeClose_h"]
    C = np.zeros((T, 3))
    C[:, 0] = np.linspace(0, 1, T)
    C[T // 2, 1:] = 1.0  # a blink
    groups, _ = copy_groups(rig, names)
    out = write_animated_copy(tmp_path / "v.glb", VALID, C, names, FPS, groups)
    src_doc, src_bin = chunks(VALID.read_bytes())
    assert_original_kept(src_doc, src_bin, out.read_bytes())
    g = pygltflib.GLTF2().load_binary(str(out))
    assert (len(g.nodes), len(g.meshes)) == (len(src_doc["nodes"]), len(src_doc["meshes"]))
    _, W = animation_weights(out)
    for name, e in zip(names, range(3)):
        for j, w in rig.groups[name]:
            node, k = rig.target_refs[j]
            np.testing.assert_allclose(W[node][:, k], C[:, e] * w, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(read_gltf_rig(out).deltas, rig.deltas)
