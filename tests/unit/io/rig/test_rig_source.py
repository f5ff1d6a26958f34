"""A character file as a rig: load_rig on a .glb/.gltf/.vrm directly and through rig.yaml's `source:`.

The synthetic scene is test_gltf_reader's (a head with jawOpen, blink, smile; teeth with t_jawOpen and blink;
an eye without targets). Expected deltas come from its `expected()`, computed independently of the reader.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from test_gltf_reader import EXTS, Builder, build_scene, expected, glb_bytes, write_glb

from retarget_cli.errors import InputError
from retarget_cli.io import obj as objmod
from retarget_cli.io.exports import rig_shapes
from retarget_cli.io.gltf import write_glb as export_glb
from retarget_cli.io.objsurface import obj_surface
from retarget_cli.io.rig import cache as rigcache
from retarget_cli.io.rig import load as rigload
from retarget_cli.io.rig import load_rig, read_rig
from retarget_cli.io.rig.gltf import read_gltf_outline, read_gltf_rig

HEAD, TEETH = slice(0, 4), slice(4, 7)
JAW, HEAD_BLINK, SMILE, T_JAW, TEETH_BLINK = range(5)  # rows of expected()'s deltas


def _dense(rig) -> np.ndarray:
    """The rig's deltas as (n, N, 3)."""
    D = rig.D.toarray() if rig.sparse else np.asarray(rig.D)
    return D.T.reshape(rig.n_sliders, -1, 3)


def _yaml(tmp_path: Path, text: str, name="rig.yaml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.fixture
def glb(tmp_path):
    return write_glb(tmp_path, meshopt=False)


# ---------------------------------------------------------------------- loading
@pytest.mark.parametrize("kw", [{}, {"meshes": ["Eye", "Teeth"]}, {"targets": ["*blink", "smile"]}])
def test_outline_is_what_the_reader_returns(glb, kw):
    outline, rig = read_gltf_outline(glb, **kw), read_gltf_rig(glb, **kw)
    assert outline.n_vertices == len(rig.neutral) and outline.mesh_ranges == rig.mesh_ranges
    assert (outline.target_names, outline.target_meshes, outline.kind) == (rig.target_names, rig.target_meshes,
                                                                           rig.kind)
    assert outline.groups == rig.groups and outline.raw_groups == rig.raw_groups and outline.files == []


def test_glb_is_a_rig_directly_and_through_source(tmp_path, glb):
    neutral, d = expected()
    for path in (glb, _yaml(tmp_path, "source: rig.glb\n")):
        rig = load_rig(path)
        assert rig.names == ("jawOpen", "blink", "smile")
        np.testing.assert_allclose(rig.neutral, neutral, rtol=0, atol=1e-12)
        D = _dense(rig)
        # one slider, two meshes: the teeth follow the jaw (the t_X rule), both blinks move together
        np.testing.assert_allclose(D[0], d[JAW] + d[T_JAW], rtol=0, atol=1e-12)
        np.testing.assert_allclose(D[1], d[HEAD_BLINK] + d[TEETH_BLINK], rtol=0, atol=1e-12)
        np.testing.assert_allclose(D[2], d[SMILE], rtol=0, atol=1e-12)
        moved = rig.evaluate([1.0, 0, 0]) - rig.neutral
        assert np.abs(moved[HEAD]).max() > 0.1 and np.abs(moved[TEETH]).max() > 0.1
        assert rig.spec.source == glb and rig.spec.neutral is None and glb in rig.spec.files()
        assert rig.spec.vertex_count() == 7 and list(rig.lower) == [0, 0, 0] and list(rig.upper) == [1, 1, 1]


def test_rig_yaml_keys_with_a_source(tmp_path, glb):
    p = _yaml(tmp_path, "source: rig.glb\nmeshes: [Head, Teeth]\ntargets: ['*jaw*', smile]\nrange: 2\n"
                        "ranges: {smile: [-1, 1]}\nlandmarks: [0, 6, 3]\nexclusive: [[jawOpen, smile]]\n"
                        "library: {grin: {smile: 0.5}}\nnames: {JawOpen: jawOpen}\n")
    rig = load_rig(p)
    assert rig.names == ("jawOpen", "smile")
    assert list(rig.lower) == [0, -1] and list(rig.upper) == [2, 1]
    np.testing.assert_array_equal(rig.landmarks[1], [0, 6, 3])
    assert rig.spec.exclusive == [("jawOpen", "smile")] and rig.library == {"grin": {"smile": 0.5}}
    assert rig.spec.names == {"JawOpen": ["jawOpen"]}


def test_sliders_targets_and_explicit_groups(tmp_path, glb):
    _, d = expected()
    rig = load_rig(_yaml(tmp_path, "source: rig.glb\nsliders: targets\n"))
    assert rig.names == ("jawOpen", "Head/blink", "smile", "t_jawOpen", "Teeth/blink")
    np.testing.assert_allclose(_dense(rig), d, rtol=0, atol=1e-12)
    rig = load_rig(_yaml(tmp_path, "source: rig.glb\nsliders:\n  - groups\n"
                                   "  - {jawOpen: {jawOpen: 1, t_jawOpen: 0.5}, wink: {Head/blink: 0.25}}\n"))
    assert rig.names == ("jawOpen", "blink", "smile", "wink")  # the explicit jawOpen replaces the group's
    D = _dense(rig)
    np.testing.assert_allclose(D[0], d[JAW] + 0.5 * d[T_JAW], rtol=0, atol=1e-12)
    np.testing.assert_allclose(D[3], 0.25 * d[HEAD_BLINK], rtol=0, atol=1e-12)


def test_vrm_expression_drives_two_targets_on_two_meshes(tmp_path):
    _, d = expected()
    groups = [{"name": "A", "presetName": "a", "binds": [{"mesh": 0, "index": 0, "weight": 100},
                                                         {"mesh": 1, "index": 0, "weight": 50}]},
              {"name": "Blink", "presetName": "blink", "binds": [{"mesh": 0, "index": 1, "weight": 100},
                                                                 {"mesh": 1, "index": 1, "weight": 100}]},
              {"name": "Neutral", "presetName": "neutral", "binds": []}]

    def mutate(doc, b):
        doc["extensions"] = {"VRM": {"blendShapeMaster": {"blendShapeGroups": groups}}}
    vrm = write_glb(tmp_path, name="avatar.vrm", mutate=mutate, meshopt=False)
    rig = load_rig(vrm)
    assert rig.names == ("a", "blink")
    D = _dense(rig)
    np.testing.assert_allclose(D[0], d[JAW] + 0.5 * d[T_JAW], rtol=0, atol=1e-12)
    np.testing.assert_allclose(D[1], d[HEAD_BLINK] + d[TEETH_BLINK], rtol=0, atol=1e-12)
    raw = load_rig(_yaml(tmp_path, "source: avatar.vrm\nsliders: targets\n"))
    assert raw.n_sliders == 5  # the raw targets stay available


def test_template_writes_obj_frames_with_one_object_per_mesh(tmp_path, glb):
    rig = load_rig(glb)
    pose = rig.evaluate([0.5, 1.0, 0.25])
    out = tmp_path / "frame_00000.obj"
    objmod.write_obj(out, rig.template, pose)
    back = objmod.read_obj(out)
    np.testing.assert_allclose(back.vertices, pose, rtol=0, atol=5e-7)
    assert back.topology == rig.template.topology and back.n_faces == 3
    text = out.read_text()
    assert text.startswith("o Head\n") and "\no Teeth\n" in text
    assert back.faces() == [[0, 1, 2], [0, 2, 3], [4, 5, 6]]
    assert rig.template.path.stem == "rig"  # the glb export names its node after it


def test_gltf_with_external_buffer_lists_it_as_a_file(tmp_path):
    b, meshes, nodes, roots = build_scene(meshopt=False)
    doc = b.doc(meshes, nodes, roots, extensionsRequired=EXTS)
    doc["buffers"][0]["uri"] = "rig.bin"
    (tmp_path / "rig.bin").write_bytes(bytes(b.bin))
    (tmp_path / "rig.gltf").write_text(json.dumps(doc))
    spec = read_rig(_yaml(tmp_path, "source: rig.gltf\n"))
    assert spec.files() == [tmp_path / "rig.gltf", (tmp_path / "rig.bin").resolve()]
    np.testing.assert_allclose(load_rig(spec.path).neutral, expected()[0], rtol=0, atol=1e-12)


def test_same_rig_through_objs_and_through_a_glb(small_take, tmp_path):
    """The synthetic take's OBJ rig, written as a GLB by the glb export's writer, read back as a rig."""
    objs = load_rig(small_take / "rig.yaml")
    shapes, names, W = rig_shapes(objs, np.zeros((1, objs.n_sliders)))
    export_glb(small_take / "character.glb", base=objs.neutral, faces=None, targets=shapes, target_names=names,
               weights=W, fps=30.0, surface=obj_surface(objs.template))
    rig = load_rig(_yaml(small_take, "source: character.glb\nrange: [0, 1]\n", "rig_glb.yaml"))
    assert rig.names == objs.names and rig.n_vertices >= objs.n_vertices
    N = objs.n_vertices  # glb vertices split at UV seams come after the OBJ's, in order
    rng = np.random.default_rng(0)
    for w in [np.zeros(objs.n_sliders), np.ones(objs.n_sliders), *rng.random((4, objs.n_sliders))]:
        np.testing.assert_allclose(rig.evaluate(w)[:N], objs.evaluate(w), rtol=0, atol=1e-6)


def test_cache_hit_reads_no_glb(tmp_path, glb, monkeypatch):
    p = _yaml(tmp_path, "source: rig.glb\nlandmarks: [0, 5]\n")
    cache = tmp_path / "cache"
    cold = load_rig(p)
    first = load_rig(p, cache_dir=cache)
    assert len(list(cache.glob("rig-*.npz"))) == 1
    monkeypatch.setattr(rigload, "read_character", lambda *a, **k: pytest.fail("the glb was decoded on a cache hit"))
    hit = load_rig(p, cache_dir=cache)
    for r in (first, hit):
        assert r.names == cold.names and r.neutral.tobytes() == cold.neutral.tobytes()
        assert _dense(r).tobytes() == _dense(cold).tobytes() and r.sparse == cold.sparse
        assert r.template.to_bytes(r.neutral) == cold.template.to_bytes(cold.neutral)
        assert r.template.topology == cold.template.topology
        np.testing.assert_array_equal(r.landmarks[1], [0, 5])
    monkeypatch.undo()
    write_glb(tmp_path, meshopt=False, mutate=_scale_root)  # the same name, other bytes
    changed = load_rig(p, cache_dir=cache)  # a changed glb is a new key
    assert len(list(cache.glob("rig-*.npz"))) == 2 and not np.allclose(changed.neutral, cold.neutral)


def _scale_root(doc, b):
    doc["nodes"][0]["scale"] = [2.0, 2.0, 2.0]


def test_unusable_cache_is_rebuilt(tmp_path, glb, caplog):
    cache = tmp_path / "cache"
    load_rig(glb, cache_dir=cache)
    (f,) = cache.glob("rig-*.npz")
    f.write_bytes(b"not a zip")
    caplog.set_level("WARNING", logger="retarget_cli.io.rig.cache")
    rig = load_rig(glb, cache_dir=cache)
    assert rig.names == ("jawOpen", "blink", "smile") and "is unusable" in caplog.text
    assert rigcache.CACHE_VERSION == 1


# ---------------------------------------------------------------------- errors: one line, before any decoding
@pytest.fixture
def no_decode(monkeypatch):
    monkeypatch.setattr(rigload, "read_character", lambda *a, **k: pytest.fail("decoded before the error"))


def _error(path, match):
    with pytest.raises(InputError, match=match) as info:
        load_rig(path)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith((str(path), path.name)), msg  # the reader names the file it reads
    return msg


@pytest.mark.parametrize("name", ["char.blend", "char.dae", "neutral.obj"])
def test_error_unsupported_extension_given_directly(tmp_path, no_decode, name):
    (tmp_path / name).write_bytes(b"\0" * 16)
    _error(tmp_path / name, f"a {Path(name).suffix} file is not a rig this version reads")


def test_error_unsupported_source_extension(tmp_path, no_decode):
    (tmp_path / "char.blend").write_bytes(b"\0" * 16)
    _error(_yaml(tmp_path, "source: char.blend\n"), r"source: char.blend: unsupported rig file extension '.blend'")
    _error(_yaml(tmp_path, "source: missing.glb\n"), "source: missing.glb not found")


def test_error_no_morph_targets(tmp_path, no_decode):
    b = Builder()
    mesh = {"name": "Body", "primitives": [{"attributes": {"POSITION": b.floats(np.eye(3))}}]}
    (tmp_path / "plain.glb").write_bytes(glb_bytes(b.doc([mesh], [{"mesh": 0}], [0]), b.bin))
    msg = _error(_yaml(tmp_path, "source: plain.glb\n"), r"plain.glb: no morph targets in any mesh")
    assert msg.startswith(f"{tmp_path / 'rig.yaml'}: source plain.glb:")
    _error(tmp_path / "plain.glb", "no morph targets")


def test_error_filters_that_match_nothing(tmp_path, glb, no_decode):
    _error(_yaml(tmp_path, "source: rig.glb\nmeshes: [Hed]\n"), r"meshes: 'Hed' matches no mesh; the file's meshes: "
                                                               "Head, Teeth, Eye")
    _error(_yaml(tmp_path, "source: rig.glb\ntargets: jaw\n"), "targets: 'jaw' matches no morph target")
    _error(_yaml(tmp_path, "source: rig.glb\nmeshes: [3]\n"), "meshes: expected a glob pattern or a list of them")


def test_error_slider_group_names_an_unknown_target(tmp_path, glb, no_decode):
    _error(_yaml(tmp_path, "source: rig.glb\nsliders: {open: {jawOpne: 1}}\n"),
           r"sliders.open: unknown target 'jawOpne'; did you mean 'jawOpen'\?")
    _error(_yaml(tmp_path, "source: rig.glb\nsliders: {open: {jawOpen: high}}\n"),
           r"sliders.open.jawOpen: expected a number")
    _error(_yaml(tmp_path, "source: rig.glb\nsliders: [groups, targets]\n"),
           "slider 'jawOpen' comes from both groups and targets")
    _error(_yaml(tmp_path, "source: rig.glb\nsliders: presets\n"), "sliders: expected 'groups', 'targets'")
    _error(_yaml(tmp_path, "source: rig.glb\nranges: {jaw: 2}\n"), r"ranges: unknown slider 'jaw'")


def test_error_landmarks_outside_the_combined_meshes(tmp_path, glb, no_decode):
    _error(_yaml(tmp_path, "source: rig.glb\nlandmarks: [0, 6, 7]\n"),
           r"landmarks\[2\] = 7 is not a vertex of the neutral rig.glb \(meshes Head, Teeth\) \(7 vertices, ids 0-6\)")
    (tmp_path / "map.txt").write_text("0\n9\n")
    with pytest.raises(InputError, match=r"map.txt.*9"):
        load_rig(_yaml(tmp_path, "source: rig.glb\nlandmarks: map.txt\n"))


def test_error_obj_keys_beside_a_source(tmp_path, glb, no_decode):
    _error(_yaml(tmp_path, "source: rig.glb\nneutral: n.obj\n"), "neutral: not used with 'source:'")
    _error(_yaml(tmp_path, "source: rig.glb\nmesh: Head\n"), r"unknown key 'mesh'; did you mean 'meshes'\?")
