"""The parsed-rig cache (io/rigcache.py), the vertex-count check before parsing and landmark maps."""

import logging

import numpy as np
import pytest

from retarget_cli.errors import InputError
from retarget_cli.io import obj as objmod
from retarget_cli.io.rig import cache as rigcache
from retarget_cli.io.rig import load_rig
from retarget_cli.io.rig.vertexmap import read_vertex_map


def _same_rig(a, b):
    assert a.names == b.names
    assert a.f0.tobytes() == b.f0.tobytes() and a.neutral.tobytes() == b.neutral.tobytes()
    Da = a.D.toarray() if a.sparse else a.D
    Db = b.D.toarray() if b.sparse else b.D
    assert a.sparse == b.sparse and Da.dtype == Db.dtype == np.float64 and Da.tobytes() == Db.tobytes()
    assert a.lower.tobytes() == b.lower.tobytes() and a.upper.tobytes() == b.upper.tobytes()
    assert a.template.path == b.template.path
    pose = a.evaluate(np.linspace(0.1, 0.9, a.n_sliders))
    assert a.template.to_bytes(pose) == b.template.to_bytes(pose)
    ta, tb = a.template, b.template
    assert (ta.segments, ta.runs, ta.tails, ta.topology, ta.n_faces) == (
        tb.segments, tb.runs, tb.tails, tb.topology, tb.n_faces)


def _cache_files(d):
    return sorted(p.name for p in d.iterdir()) if d.exists() else []


def test_cache_hit_is_bit_identical_to_a_cold_load(small_take, tmp_path, monkeypatch):
    rig_yaml = small_take / "rig.yaml"
    cache = tmp_path / "cache"
    cold = load_rig(rig_yaml)
    first = load_rig(rig_yaml, cache_dir=cache)
    files = _cache_files(cache)
    assert len(files) == 1 and files[0].startswith("rig-") and files[0].endswith(".npz")

    def no_parse(path):
        raise AssertionError(f"read_obj({path}) called on a cache hit")

    monkeypatch.setattr(rigcache, "read_obj", no_parse)
    hit = load_rig(rig_yaml, cache_dir=cache)
    for r in (first, hit):
        _same_rig(cold, r)
    out_cold, out_hit = tmp_path / "cold.obj", tmp_path / "hit.obj"
    w = np.full(cold.n_sliders, 0.5)
    objmod.write_obj(out_cold, cold.template, cold.evaluate(w))
    objmod.write_obj(out_hit, hit.template, hit.evaluate(w))
    assert out_cold.read_bytes() == out_hit.read_bytes()
    # the template keeps every non-coordinate byte: writing the neutral at its own positions reproduces the file
    assert hit.template.to_bytes(hit.neutral) == cold.template.to_bytes(cold.neutral)


def test_changing_one_shape_invalidates_the_cache(small_take, tmp_path):
    rig_yaml = small_take / "rig.yaml"
    cache = tmp_path / "cache"
    before = load_rig(rig_yaml, cache_dir=cache)
    shape = small_take / "target" / "shapes" / "smile.obj"
    text = shape.read_bytes()
    first_v = text.index(b"\nv ") + 1
    end = text.index(b"\n", first_v)
    shape.write_bytes(text[:first_v] + b"v 9 9 9" + text[end:])
    after = load_rig(rig_yaml, cache_dir=cache)
    assert len(_cache_files(cache)) == 2
    i = after.index["smile"]
    assert not np.array_equal(before.D[:, i] if not before.sparse else before.D[:, [i]].toarray(),
                              after.D[:, i] if not after.sparse else after.D[:, [i]].toarray())
    _same_rig(after, load_rig(rig_yaml))


def test_changing_rig_yaml_invalidates_the_cache(small_take, tmp_path):
    rig_yaml = small_take / "rig.yaml"
    cache = tmp_path / "cache"
    load_rig(rig_yaml, cache_dir=cache)
    rig_yaml.write_text(rig_yaml.read_text().replace("- 1\n", "- 2\n", 1))
    r = load_rig(rig_yaml, cache_dir=cache)
    assert len(_cache_files(cache)) == 2 and np.all(r.upper == 2)


@pytest.mark.parametrize("damage", ["truncate", "garbage", "wrong key"])
def test_a_corrupt_cache_is_rebuilt_with_a_warning(small_take, tmp_path, caplog, damage):
    rig_yaml = small_take / "rig.yaml"
    cache = tmp_path / "cache"
    cold = load_rig(rig_yaml, cache_dir=cache)
    (file,) = cache.iterdir()
    data = file.read_bytes()
    if damage == "truncate":
        file.write_bytes(data[: len(data) // 2])
    elif damage == "garbage":
        file.write_bytes(b"PK\x03\x04" + b"\0" * 100)
    else:  # a valid archive of another key under this name
        arrays = dict(np.load(file))
        arrays["key"] = np.array("0" * 64)
        rigcache.savez(file, arrays, compress=False)
    with caplog.at_level(logging.WARNING, logger="retarget_cli.io.rig.cache"):
        again = load_rig(rig_yaml, cache_dir=cache)
    assert any("unusable" in r.getMessage() for r in caplog.records)
    _same_rig(cold, again)
    assert file.read_bytes() == data  # rebuilt
    _same_rig(cold, load_rig(rig_yaml, cache_dir=cache))


def test_vertex_count_error_names_the_shape_entry_before_any_parse(small_take, monkeypatch):
    rig_yaml = small_take / "rig.yaml"
    shape = small_take / "target" / "shapes" / "jaw_open.obj"
    text = shape.read_bytes()
    first_v = text.index(b"\nv ") + 1
    shape.write_bytes(text[:first_v] + text[text.index(b"\n", first_v) + 1:])  # drop one v line
    n = objmod.read_obj(small_take / "target" / "neutral.obj").n_vertices

    def no_parse(path):
        raise AssertionError(f"read_obj({path}) called before the vertex counts were checked")

    monkeypatch.setattr(rigcache, "read_obj", no_parse)
    with pytest.raises(InputError) as exc:
        load_rig(rig_yaml)
    msg = str(exc.value)
    assert "shapes.jaw_open (jaw_open.obj)" in msg and f"{n - 1} vertices" in msg
    assert f"the neutral neutral.obj has {n}" in msg and msg.startswith(str(rig_yaml))


def test_rig_yaml_landmarks_are_checked_against_the_neutral(small_take, monkeypatch):
    rig_yaml = small_take / "rig.yaml"
    n = objmod.read_obj(small_take / "target" / "neutral.obj").n_vertices
    rig_yaml.write_text(rig_yaml.read_text() + f"landmarks: [0, 3, {n + 5}, 2]\n")
    monkeypatch.setattr(rigcache, "read_obj", lambda p: pytest.fail("parsed before the landmark check"))
    with pytest.raises(InputError, match=rf"landmarks\[2\] = {n + 5} is not a vertex of the neutral neutral.obj "
                                         rf"\({n} vertices"):
        load_rig(rig_yaml)


def test_rig_yaml_landmark_map_file_is_read_and_in_the_key(small_take, tmp_path):
    rig_yaml = small_take / "rig.yaml"
    (small_take / "map.txt").write_text("0\n5\n7\n")
    rig_yaml.write_text(rig_yaml.read_text() + "landmarks: map.txt\n")
    cache = tmp_path / "cache"
    r = load_rig(rig_yaml, cache_dir=cache)
    np.testing.assert_array_equal(r.landmarks[1], [0, 5, 7])
    (small_take / "map.txt").write_text("0\n5\n8\n")
    r = load_rig(rig_yaml, cache_dir=cache)
    np.testing.assert_array_equal(r.landmarks[1], [0, 5, 8])
    assert len(_cache_files(cache)) == 2


def test_fast_counts_agree_with_the_parser_on_the_rig(small_take):
    for p in [small_take / "target" / "neutral.obj", *(small_take / "target" / "shapes").glob("*.obj")]:
        assert objmod.count_vertices(p) == objmod.read_obj(p).n_vertices


@pytest.mark.parametrize("text, lines, match", [
    ("0\n1\n# c\n99\n3\n", 4, r"map.txt:4: vertex 99 is outside the mesh \(50 vertices"),
    ("0\n1\nx2\n3\n", 4, r"map.txt:3: expected 'vertex' or 'landmark vertex'"),
    ("0\n1\n2\n", 4, r"map.txt: lists 3 vertices but the landmarks file has 4 landmarks"),
    ("0 1\n1 2\n\n0 3\n", 4, r"map.txt:4: landmark 0 is mapped twice \(also on line 1\)"),
    ("0 1\n7 2\n", 4, r"map.txt:2: landmark 7 does not exist"),
    ("0 1\n1\n", 4, r"map.txt:2: has 1 numbers but line 1 has 2"),
    ("0\n-1\n2\n3\n", 4, r"map.txt:2: vertex -1 is outside the mesh"),
])
def test_vertex_map_errors_name_file_and_line(tmp_path, text, lines, match):
    p = tmp_path / "map.txt"
    p.write_text(text)
    with pytest.raises(InputError, match=match):
        read_vertex_map(p, lines, 50)


def test_vertex_map_reads_both_forms(tmp_path):
    p = tmp_path / "map.txt"
    p.write_text("# landmark vertex\n3 10\n1, 20\n")
    lm, vx = read_vertex_map(p, 4, 50)
    assert lm.tolist() == [3, 1] and vx.tolist() == [10, 20]
    p.write_text("10\n20  # nose\n30\n")
    lm, vx = read_vertex_map(p, 3, 50)
    assert lm.tolist() == [0, 1, 2] and vx.tolist() == [10, 20, 30]


def test_ict_rig_cached_load_matches_cold(ict_rig_dir, tmp_path):
    rig_yaml = ict_rig_dir / "rig.yaml"
    cold = load_rig(rig_yaml, cache_dir=tmp_path / "cache")
    assert cold.n_vertices == 26719 and cold.n_sliders == 57 and cold.landmarks[1].shape == (68,)
    assert cold.landmarks[0].tolist() == list(range(68))
    hit = load_rig(rig_yaml, cache_dir=tmp_path / "cache")
    _same_rig(cold, hit)
    ref = objmod._parse_lines(rig_yaml.parent / "jawOpen.obj", (rig_yaml.parent / "jawOpen.obj").read_bytes())
    i = hit.index["jawOpen"]
    D = hit.D.toarray() if hit.sparse else hit.D
    assert (ref.vertices - hit.neutral).ravel().tobytes() == np.ascontiguousarray(D[:, i]).tobytes()
    neutral = rig_yaml.parent / "generic_neutral_mesh.obj"
    ref = objmod._parse_lines(neutral, neutral.read_bytes())
    pose = hit.evaluate(np.full(hit.n_sliders, 0.3))
    assert hit.template.to_bytes(pose) == ref.to_bytes(pose)


def test_solve_rig_reader_uses_the_cache_with_correctives(tmp_path, monkeypatch):
    from retarget_cli.io.obj import format_obj
    from retarget_cli.io.rig.inverse import read_quadratic_rig
    from retarget_cli.synth.take import overlapping_rig

    r = overlapping_rig(n_shapes=3, grid=(5, 5))
    d = tmp_path / "rig"
    d.mkdir()
    (d / "neutral.obj").write_bytes(format_obj(r["vertices"], r["faces"]))
    for name, delta in zip(r["names"], r["deltas"]):
        (d / f"{name}.obj").write_bytes(format_obj(r["vertices"] + delta, r["faces"]))
    (d / "c.obj").write_bytes(format_obj(r["vertices"] + 0.1 * r["deltas"][0] * r["deltas"][1], r["faces"]))
    a, b = r["names"][:2]
    rig_yaml = d / "rig.yaml"
    rig_yaml.write_text("neutral: neutral.obj\nshapes:\n" + "".join(f"  {n}: {n}.obj\n" for n in r["names"])
                        + f"correctives:\n  - {{shapes: [{a}, {b}], obj: c.obj}}\n")
    cold, files = read_quadratic_rig(rig_yaml)
    first, _ = read_quadratic_rig(rig_yaml, cache_dir=tmp_path / "cache")
    monkeypatch.setattr(rigcache, "read_obj", lambda p: pytest.fail(f"{p} parsed although cached"))
    hit, files2 = read_quadratic_rig(rig_yaml, cache_dir=tmp_path / "cache")
    assert files == files2 and len(_cache_files(tmp_path / "cache")) == 1
    for r in (first, hit):
        assert r.names == cold.names and r.pairs.tolist() == cold.pairs.tolist() and len(cold.pairs) > 0
        assert r.b0.tobytes() == cold.b0.tobytes() and r.B.tobytes() == cold.B.tobytes()
        w = np.linspace(0.2, 0.8, len(cold.names))
        assert r.evaluate(w).tobytes() == cold.evaluate(w).tobytes()
