import numpy as np
import pytest

from retarget_cli.errors import InputError
from retarget_cli.io.obj import check_same_topology, format_obj, read_obj, write_obj

# Every OBJ feature the design names: comments, mtllib/usemtl, o/g/s, v with
# colours and w, vt and vn indexed apart from v, all face index forms,
# negative indices, n-gons, CRLF line endings, vertices in several runs.
FULL = (
    b"# exported by hand\r\n"
    b"mtllib face.mtl\r\n"
    b"o head\r\n"
    b"v 0 0 0\r\n"
    b"v 1.5 0 0 0.9 0.1 0.1\r\n"
    b"v 1 1 0\r\n"
    b"v 0 1 0 1.0\r\n"
    b"vt 0 0\r\nvt 1 0\r\nvt 1 1\r\n"
    b"vn 0 0 1\r\n"
    b"g front\r\n"
    b"usemtl skin\r\n"
    b"s 1\r\n"
    b"f 1/1/1 2/2/1 3/3/1 4/1/1\r\n"
    b"f 1//1 3//1 4//1\r\n"
    b"f 1 2 3\r\n"
    b"v 2 0 0\r\n"
    b"v 2 1 0\r\n"
    b"f -4/1 -2/2 -1/3 -3/1\r\n"
    b"l 1 2\r\n"
)


@pytest.fixture
def full_obj(tmp_path):
    p = tmp_path / "full.obj"
    p.write_bytes(FULL)
    return p


def test_reads_positions_in_file_order(full_obj):
    m = read_obj(full_obj)
    assert m.n_vertices == 6
    np.testing.assert_array_equal(m.vertices[1], [1.5, 0, 0])
    np.testing.assert_array_equal(m.vertices[5], [2, 1, 0])
    assert m.n_faces == 4


def test_faces_resolve_negative_indices_and_ngons(full_obj):
    faces = read_obj(full_obj).faces()
    assert faces[0] == [0, 1, 2, 3]
    assert faces[2] == [0, 1, 2]
    # -4 with 6 vertices defined so far is vertex 3 (1-based) -> id 2.
    assert faces[3] == [2, 4, 5, 3]


def test_rewrite_keeps_every_non_vertex_byte(full_obj, tmp_path):
    m = read_obj(full_obj)
    moved = m.vertices + np.array([0.25, -1.0, 3.0])
    out = tmp_path / "out.obj"
    write_obj(out, m, moved)
    data = out.read_bytes()
    src_lines = FULL.splitlines(keepends=True)
    out_lines = data.splitlines(keepends=True)
    assert len(src_lines) == len(out_lines)
    for a, b in zip(src_lines, out_lines):
        if a.startswith(b"v "):
            assert b.startswith(b"v ") and b.endswith(b"\r\n")
            assert a.split()[4:] == b.split()[4:]  # colours and w kept
        else:
            assert a == b
    np.testing.assert_allclose(read_obj(out).vertices, moved, atol=1e-6)


def test_identity_rewrite_of_generated_obj_is_byte_identical(tmp_path):
    v = np.random.default_rng(0).normal(size=(10, 3))
    f = np.array([[0, 1, 2, 3], [4, 5, 6, 7]])
    data = format_obj(v, f, uvs=np.zeros((10, 2)), face_uvs=f, header="mtllib a.mtl\n")
    p = tmp_path / "g.obj"
    p.write_bytes(data)
    m = read_obj(p)
    assert m.to_bytes(m.vertices) == data


def test_topology_mismatch_names_both_files(tmp_path):
    a, b = tmp_path / "a.obj", tmp_path / "b.obj"
    a.write_bytes(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    b.write_bytes(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 3 2\n")
    with pytest.raises(InputError, match="b.obj.*a.obj"):
        check_same_topology([read_obj(a), read_obj(b)])
    b.write_bytes(b"v 0 0 0\nv 1 0 0\nf 1 2 2\n")
    with pytest.raises(InputError, match="2 vertices.*3"):
        check_same_topology([read_obj(a), read_obj(b)])


def test_bad_input_is_a_clear_error(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_obj(tmp_path / "missing.obj")
    p = tmp_path / "bad.obj"
    p.write_bytes(b"v 0 0 0\nv 1 2\n")
    with pytest.raises(InputError, match=r"bad.obj:2"):
        read_obj(p)
    p.write_bytes(b"f 1 2 3\n")
    with pytest.raises(InputError, match="no 'v' lines"):
        read_obj(p)
    p.write_bytes(b"v 0 nan 0\n")
    with pytest.raises(InputError, match="not finite"):
        read_obj(p)


def test_wrong_position_shape_is_rejected(full_obj):
    m = read_obj(full_obj)
    with pytest.raises(ValueError, match=r"\(6, 3\)"):
        m.to_bytes(np.zeros((5, 3)))


# Features the reader must not trip over: vp lines, tabs, w, comments after
# data, leading blanks, a '%' in a tail, no final newline.
EDGE = (
    b"mtllib a.mtl\n"
    b"v\t0.5\t0.25\t-1\n"
    b"  v 1 2 3 1.0 # weighted\n"
    b"v 4 5 6# glued comment\n"
    b"vp 0.5 0.5\n"
    b"vt 0 0\nvt 1 0 0\n"
    b"vn 0 0 1\n"
    b"v 7 8 9 # 100% sure\n"
    b"f 1/1/1 2/2/1 3/1/1 # a triangle\n"
    b"f -1 -2 -3\n"
    b"p 4\n"
    b"v 1e-3 -2.5E+1 0"
)


def test_edge_features_round_trip_with_only_v_lines_changed(tmp_path):
    p = tmp_path / "edge.obj"
    p.write_bytes(EDGE)
    m = read_obj(p)
    assert m.n_vertices == 5  # the vp line is not a vertex
    np.testing.assert_array_equal(m.vertices, [[0.5, 0.25, -1], [1, 2, 3], [4, 5, 6], [7, 8, 9], [1e-3, -25, 0]])
    assert m.faces() == [[0, 1, 2], [3, 2, 1]]
    out = m.to_bytes(m.vertices + 1)
    a, b = EDGE.splitlines(keepends=True), out.splitlines(keepends=True)
    assert len(a) == len(b)
    for src, dst in zip(a, b):
        if _is_v(src):
            assert dst.startswith(b"v ")
        else:
            assert src == dst
    assert b[1] == b"v 1.500000 1.250000 0.000000\n"
    assert b[2] == b"v 2.000000 3.000000 4.000000 1.0 # weighted\n"
    assert b[3] == b"v 5.000000 6.000000 7.000000# glued comment\n"
    assert b[8] == b"v 8.000000 9.000000 10.000000 # 100% sure\n"
    assert b[-1] == b"v 1.001000 -24.000000 1.000000"  # still no final newline
    # The reference (printf) writer gives the same bytes.
    assert b"".join(m._iter_bytes_slow(m.vertices + 1)) == out


def _is_v(line):
    s = line.lstrip(b" \t")
    return s[:1] == b"v" and s[1:2] in (b" ", b"\t")


@pytest.mark.parametrize(
    "face, match",
    [
        (b"f 1 2 9\n", r":4: refers to v 9 but the file has 3"),
        (b"f 1 2 -4\n", r":4: 'f' refers to v -4 but only 3"),
        (b"f 1/3 2/1 3/1\n", r"refers to vt 3 but the file has 1"),
        (b"f 1//2 2//1 3//1\n", r"refers to vn 2 but the file has 1"),
        (b"f 0 1 2\n", r"refers to v 0"),
        (b"f 1 2 x\n", r"not made of integers"),
        (b"l 1 5\n", r"refers to v 5"),
    ],
)
def test_out_of_range_references_are_clear_errors(tmp_path, face, match):
    p = tmp_path / "refs.obj"
    p.write_bytes(b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + face + b"vt 0 0\nvn 0 0 1\n")
    with pytest.raises(InputError, match=match):
        read_obj(p)


def test_forward_references_are_allowed(tmp_path):
    p = tmp_path / "fwd.obj"
    p.write_bytes(b"v 0 0 0\nf 1 2 3\nv 1 0 0\nv 0 1 0\n")
    assert read_obj(p).faces() == [[0, 1, 2]]


def test_fast_writer_matches_printf_exactly(tmp_path):
    rng = np.random.default_rng(0)
    n = 20_000
    v = rng.normal(size=(n, 3)) * 10.0 ** rng.integers(-9, 9, size=(n, 3))
    # Exact ties at the 7th decimal (k/128), signed zeros, values that round to -0.
    special = [0.0078125, -0.0078125, 3 / 128, 0.5, -0.0, 0.0, -1e-9, 4e-7, 5e-7, 999999999.4999, 1.0000005, 2.5e-7]
    v[: len(special), 0] = special
    v[: len(special), 1] = -np.array(special)
    p = tmp_path / "m.obj"
    p.write_bytes(b"v 0 0 0\n" * n + b"f 1 2 3\n")
    m = read_obj(p)
    got = m.to_bytes(v)
    want = "".join("v %.6f %.6f %.6f\n" % tuple(r) for r in v).encode() + b"f 1 2 3\n"  # noqa: UP031
    assert got == want
    # Beyond 1e9 the reference formatter takes over, with the same result.
    v[5] = [3e12, -1e10, 1e9]
    want = "".join("v %.6f %.6f %.6f\n" % tuple(r) for r in v).encode() + b"f 1 2 3\n"  # noqa: UP031
    assert m.to_bytes(v) == want


# The vectorised reader (_parse_fast) against the line-by-line reference (_parse_lines).
PLAIN = (b"mtllib m.mtl\nv 0 0 0\nv 1.5 -2e-3 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvn 0 0 1\n"
         b"usemtl skin\nf 1/1/1 2/2/1 3/3/1\nf 1//1 3//1 4//1\nf 1 2 3 4\nv 2 0 0\nf -4/1 -2/2 -1/3\nl 1 2\np 5\n")
VARIANTS = {
    "plain": PLAIN,
    "crlf": PLAIN.replace(b"\n", b"\r\n"),
    "no final newline": PLAIN.rstrip(b"\n"),
    "tabs in v": PLAIN.replace(b"v 1 1 0", b"v\t1 1 0"),
    "colours": PLAIN.replace(b"v 1 1 0", b"v 1 1 0 0.5 0.5 0.5"),
    "comment after v": PLAIN.replace(b"v 1 1 0", b"v 1 1 0 # tip"),
    "indented v": PLAIN.replace(b"v 1 1 0", b"  v 1 1 0"),
    "trailing space": PLAIN.replace(b"v 1 1 0", b"v 1 1 0 "),
    "lone cr": PLAIN.replace(b"vt 0 0\n", b"vt 0 0\r"),
    "double space in f": PLAIN.replace(b"f 1 2 3 4", b"f 1  2 3 4"),
    "tab in f": PLAIN.replace(b"f 1 2 3 4", b"f\t1 2 3 4"),
    "comment after f": PLAIN.replace(b"f 1 2 3 4", b"f 1 2 3 4 # quad"),
    "f last without newline": PLAIN + b"f 1 2 3",
    "v last without newline": PLAIN + b"v 3 3 3",
    "bad vertex ref": PLAIN.replace(b"f 1 2 3 4", b"f 1 2 3 9"),
    "bad negative ref": PLAIN.replace(b"f -4/1", b"f -9/1"),
    "bad texture ref": PLAIN.replace(b"f 1/1/1", b"f 1/7/1"),
    "zero ref": PLAIN.replace(b"f 1 2 3 4", b"f 0 2 3 4"),
    "empty face": PLAIN.replace(b"f 1 2 3 4", b"f"),
    "four slots": PLAIN.replace(b"f 1 2 3 4", b"f 1/1/1/1 2 3"),
    "trailing slash after vn": PLAIN.replace(b"f 1 2 3 4", b"f 1/1/1/ 2 3"),
    "empty slots after vt": PLAIN.replace(b"f 1 2 3 4", b"f 1/1// 2 3"),
    "triple slash": PLAIN.replace(b"f 1 2 3 4", b"f 1///1 2 3"),
    "empty trailing vn": PLAIN.replace(b"f 1 2 3 4", b"f 1/1/ 2/2/ 3/3/"),
    "negative slots": PLAIN + b"f -1/-1/-1 -2/-2/-1 -3/-3/-1\n",
    "negative vt out of range": PLAIN + b"f -1/-4/-1 -2/-2/-1 -3/-3/-1\n",
    "long index": PLAIN.replace(b"f 1 2 3 4", b"f 1 2 3 123456789012345678901"),
    "leading slash": PLAIN.replace(b"f 1 2 3 4", b"f /1 2 3"),
    "bad minus": PLAIN.replace(b"f 1 2 3 4", b"f 1-2 2 3"),
    "short v": PLAIN.replace(b"v 1 1 0", b"v 1 1"),
    "not a number": PLAIN.replace(b"v 1 1 0", b"v 1 x 0"),
    "not finite": PLAIN.replace(b"v 1 1 0", b"v 1 nan 0"),
    "exponents and signs in v": PLAIN.replace(b"v 1 1 0", b"v +1.5E+2 -2.5e-13 .5"),
    "underscore in v": PLAIN.replace(b"v 1 1 0", b"v 1_0 1 0"),
    "two dots in v": PLAIN.replace(b"v 1 1 0", b"v 1.2.3 1 0"),
    "bare exponent in v": PLAIN.replace(b"v 1 1 0", b"v 1e 1 0"),
    "no v": b"f 1 2 3\n",
}


@pytest.mark.parametrize("name", sorted(VARIANTS))
def test_fast_reader_matches_the_reference(tmp_path, name):
    from retarget_cli.io.obj import _parse_fast, _parse_lines, count_vertices

    p = tmp_path / "m.obj"
    p.write_bytes(VARIANTS[name])
    try:
        ref = _parse_lines(p, VARIANTS[name])
    except InputError as exc:
        with pytest.raises(InputError) as got:
            read_obj(p)
        assert str(got.value) == str(exc)
        return
    fast, mesh = _parse_fast(p, VARIANTS[name]), read_obj(p)
    if name in ("plain", "crlf", "no final newline", "double space in f", "tab in f", "f last without newline",
                "empty trailing vn", "negative slots"):
        assert fast is not None, "the fast path should handle this layout"
    for m in (mesh, fast) if fast is not None else (mesh,):
        assert m.vertices.tobytes() == ref.vertices.tobytes()
        assert (m.segments, m.runs, m.tails, m.topology, m.n_faces) == (
            ref.segments, ref.runs, ref.tails, ref.topology, ref.n_faces)
        assert m.to_bytes(m.vertices + 1) == ref.to_bytes(ref.vertices + 1)
    assert count_vertices(p) == ref.n_vertices


def _random_obj(rng) -> bytes:
    """An OBJ file that is usually valid and in the fast reader's layout, with rare oddities and errors."""
    def pick(common, rare, p_rare=0.01):
        return rare[rng.integers(len(rare))] if rng.random() < p_rare else common[rng.integers(len(common))]

    def sep():
        return pick([b" "], [b"  ", b"\t"])

    def v_line():
        n = 3 if rng.random() > 0.02 else int(rng.integers(2, 7))
        nums = b"".join(sep() + pick([b"0", b"1.5", b"-2e-3", b"7", b"0.000001"], [b"x", b"nan", b"1e999"])
                        for _ in range(n))
        return pick([b"v"], [b" v", b"v\t"]) + nums + pick([b""], [b" ", b" # c"])

    def ref():
        return pick([b"1", b"2", b"3", b"-1", b"-2"], [b"0", b"9", b"-9", b"1-", b"12345678901234567"], 0.005)

    def slot():
        forms = [lambda: ref(), lambda: ref() + b"/" + ref(), lambda: ref() + b"/" + ref() + b"/" + ref(),
                 lambda: ref() + b"//" + ref(), lambda: ref() + b"/"]
        if rng.random() < 0.01:
            return [b"1///1", b"/1", b"1/1/1/", b"1/1//1"][rng.integers(4)]
        return forms[rng.integers(len(forms))]()

    def f_line():
        n = int(rng.integers(1, 5)) if rng.random() > 0.01 else 0
        return (pick([b"f", b"l", b"p"], [b"f\t"]) + b"".join(sep() + slot() for _ in range(n))
                + pick([b""], [b" ", b" # q"]))

    others = [b"vt 0 0", b"vn 0 0 1", b"# note", b"", b"g a", b"usemtl m", b"vp 1", b"v"]
    lines = [v_line() for _ in range(int(rng.integers(3, 7)))] + [b"vt 0 0"] * 3 + [b"vn 0 0 1"] * 3
    for _ in range(int(rng.integers(0, 14))):
        r = rng.random()
        lines.append(v_line() if r < 0.3 else f_line() if r < 0.85 else others[rng.integers(len(others))])
    eol = b"\r\n" if rng.random() < 0.2 else b"\n"
    return eol.join(lines) + (eol if rng.random() < 0.9 else b"")


def test_fast_reader_agrees_with_the_reference_on_generated_files(tmp_path):
    from retarget_cli.io.obj import _parse_fast, _parse_lines

    rng = np.random.default_rng(7)
    p = tmp_path / "g.obj"
    n_fast = n_errors = 0
    for _ in range(600):
        data = _random_obj(rng)
        p.write_bytes(data)
        try:
            ref = _parse_lines(p, data)
        except InputError as exc:
            n_errors += 1
            with pytest.raises(InputError) as got:
                read_obj(p)
            assert str(got.value) == str(exc), data
            continue
        n_fast += _parse_fast(p, data) is not None
        m = read_obj(p)
        assert m.vertices.tobytes() == ref.vertices.tobytes(), data
        assert (m.segments, m.runs, m.tails, m.topology, m.n_faces) == (
            ref.segments, ref.runs, ref.tails, ref.topology, ref.n_faces), data
    assert n_fast >= 100 and n_errors >= 20, (n_fast, n_errors)  # both paths exercised


def _uniform_obj(rng, shape: bytes) -> bytes:
    """A mesh whose faces all share one token shape (``a``, ``a/b``, ``a//c``, ``a/b/c``), sometimes with one oddity."""
    nv, nt, nn = 6, 5, 4
    lines = [b"# uniform"] + [b"v %d 0.5 -1" % i for i in range(nv)] + [b"vt 0 0"] * nt + [b"vn 0 0 1"] * nn

    def token():
        v, t, n = (int(rng.integers(1, m + 1)) for m in (nv, nt, nn))
        return {b"a": b"%d" % v, b"a/b": b"%d/%d" % (v, t), b"a//c": b"%d//%d" % (v, n),
                b"a/b/c": b"%d/%d/%d" % (v, t, n)}[shape]

    faces = [b"f " + b" ".join(token() for _ in range(int(rng.integers(3, 6)))) for _ in range(int(rng.integers(1, 9)))]
    if rng.random() < 0.1:
        faces.insert(int(rng.integers(len(faces) + 1)), b"l " + b" ".join(token() for _ in range(2)))
    if rng.random() < 0.6:  # one odd token or line, of the kinds the uniform check must refuse or get right
        odd = [b"1", b"1/1", b"1//1", b"1/1/1", b"1/", b"/1", b"1/1/", b"1//", b"//1", b"1///1", b"007",
               b"0", b"-1", b"99", b"99999999999999999999", b"1/1/1/1", b"1/9", b"1//9", b"1/1/9"]
        k = int(rng.integers(len(faces)))
        toks = faces[k].split(b" ")
        toks[int(rng.integers(1, len(toks)))] = odd[int(rng.integers(len(odd)))]
        faces[k] = b" ".join(toks)
        r = rng.random()
        if r < 0.1:
            faces[k] += b" "
        elif r < 0.2:
            faces[k] = faces[k].replace(b" ", b"  ", 1)
        elif r < 0.25:
            faces[k] = b"f"
    return b"\n".join(lines + faces) + b"\n"


@pytest.mark.parametrize("shape", [b"a", b"a/b", b"a//c", b"a/b/c"])
def test_uniform_face_fast_path_agrees_with_the_reference(tmp_path, shape):
    """The one-pass check of uniform face lines (_uniform_refs) against the line parser, odd files included."""
    from retarget_cli.io import obj

    rng = np.random.default_rng(11)
    p = tmp_path / "u.obj"
    used = refused = errors = 0
    seen = []
    real = obj._uniform_refs
    obj_calls = []

    def spy(*args):
        out = real(*args)
        obj_calls.append(out is not None)
        return out

    for _ in range(300):
        data = _uniform_obj(rng, shape)
        p.write_bytes(data)
        obj_calls.clear()
        try:
            ref = obj._parse_lines(p, data)
        except InputError as exc:
            errors += 1
            with pytest.raises(InputError) as got:
                read_obj(p)
            assert str(got.value) == str(exc), data
            continue
        obj._uniform_refs = spy
        try:
            fast = obj._parse_fast(p, data)
        finally:
            obj._uniform_refs = real
        if obj_calls and obj_calls[0]:
            used += 1
            assert fast is not None, data
        else:
            refused += 1
        seen.append(data)
        for m in (fast, read_obj(p)) if fast is not None else (read_obj(p),):
            assert m.vertices.tobytes() == ref.vertices.tobytes(), data
            assert (m.segments, m.runs, m.tails, m.topology, m.n_faces) == (
                ref.segments, ref.runs, ref.tails, ref.topology, ref.n_faces), data
            assert m.faces() == ref.faces(), data
    assert used >= 60 and refused >= 20 and errors >= 10, (used, refused, errors)


def test_read_vertices_like_equals_read_obj_on_poses_and_odd_files(tmp_path):
    """Poses of a template parse only their v lines; anything else is read in full, with the same result."""
    from retarget_cli.io.obj import _vertices_like, read_vertices_like, write_obj

    base = tmp_path / "base.obj"
    base.write_bytes(b"# head\nmtllib m.mtl\n" + b"".join(b"v %d 0.5 -1\n" % i for i in range(5))
                     + b"vt 0 0\nvt 1 0\nf 1/1 2/2 3/1\nf 3/1 4/2 5/1\n")
    like = read_obj(base)
    rng = np.random.default_rng(3)
    pose = tmp_path / "pose.obj"
    write_obj(pose, like, like.vertices + rng.normal(size=like.vertices.shape) * 1e3)
    data = pose.read_bytes()
    assert _vertices_like(data, like) is not None  # the fast path takes a pose
    variants = {
        "pose": data,
        "other face": data.replace(b"f 3/1 4/2 5/1", b"f 3/1 4/2 1/1"),
        "fewer v": data.replace(data[data.index(b"v "):data.index(b"\n", data.index(b"v ")) + 1], b"", 1),
        "colour column": data.replace(b"\nvt 0 0", b"\nv 1 2 3 4\nvt 0 0"),
        "v not first": data.replace(b"\nv ", b"\n1v ", 1),
        "crlf": data.replace(b"\n", b"\r\n"),
        "exponent": data.replace(b"\nv ", b"\nv 1.5e-3 ", 1).replace(b"1.5e-3 -", b"1.5e-3 ", 1),
        "bad exponent": data.replace(b"\nv ", b"\nv 1e ", 1),
    }
    for name, d in variants.items():
        pose.write_bytes(d)
        try:
            want = read_obj(pose).vertices
        except InputError as exc:
            with pytest.raises(InputError) as got:
                read_vertices_like(pose, like)
            assert str(got.value) == str(exc), name
            continue
        got = read_vertices_like(pose, like)
        assert got.tobytes() == want.tobytes(), name
    with pytest.raises(InputError, match="not found"):
        read_vertices_like(tmp_path / "missing.obj", like)
