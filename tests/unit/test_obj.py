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
