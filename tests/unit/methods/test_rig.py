"""The rig model (rig.py) and rig.yaml (io/stagefiles.read_rig)."""

from pathlib import Path

import numpy as np
import pytest

from retarget_cli.errors import InputError, RetargetError, ShapeError
from retarget_cli.io.obj import format_obj, read_obj
from retarget_cli.io.rig import load_rig, read_rig
from retarget_cli.methods.rig import BlendshapeRig, parse_axes
from retarget_cli.synth.take import overlapping_rig

SAMPLE = Path(__file__).resolve().parents[3] / "sample_data"


def write_rig(tmp_path, rig, *, shapes_are="absolute", extra="", faces=None):
    """Write a rig dict (vertices, faces, deltas, names) as OBJs plus rig.yaml; return the yaml path."""
    faces = rig["faces"] if faces is None else faces
    (tmp_path / "shapes").mkdir(exist_ok=True)
    (tmp_path / "neutral.obj").write_bytes(format_obj(rig["vertices"], rig["faces"]))
    lines = ["neutral: neutral.obj", f"shapes_are: {shapes_are}", "shapes:"]
    for name, d in zip(rig["names"], rig["deltas"]):
        pos = d if shapes_are == "delta" else rig["vertices"] + d
        (tmp_path / "shapes" / f"{name}.obj").write_bytes(format_obj(pos, faces))
        lines.append(f"  {name}: shapes/{name}.obj")
    (tmp_path / "rig.yaml").write_text("\n".join(lines) + "\n" + extra)
    return tmp_path / "rig.yaml"


def test_sample_rig_yaml_still_reads_with_defaults():
    spec = read_rig(SAMPLE / "rig.yaml")
    assert spec.shapes_are == "absolute" and spec.library == {} and spec.correctives is None
    assert set(spec.ranges.values()) == {(0.0, 1.0)} and list(spec.ranges) == list(spec.shapes)


def test_sample_rig_evaluates_as_neutral_plus_deltas():
    rig = load_rig(SAMPLE / "rig.yaml")
    neutral = read_obj(SAMPLE / "target" / "neutral.obj").vertices
    shapes = [read_obj(p).vertices for p in read_rig(SAMPLE / "rig.yaml").shapes.values()]
    w = np.linspace(0.1, 0.8, rig.n_sliders)
    expected = neutral + sum(wi * (s - neutral) for wi, s in zip(w, shapes))
    np.testing.assert_allclose(rig.evaluate(w), expected, atol=1e-12)
    W = np.stack([w, 0 * w, 1 - w])
    np.testing.assert_allclose(rig.evaluate(W)[0], expected, atol=1e-12)
    np.testing.assert_allclose(rig.evaluate(W)[1], neutral, atol=1e-12)


def test_dense_and_sparse_storage_agree():
    r = overlapping_rig(n_shapes=10, seed=1)
    dense = BlendshapeRig(r["vertices"], r["deltas"], r["names"], storage="dense")
    sparse = BlendshapeRig(r["vertices"], r["deltas"], r["names"], storage="sparse")
    assert not dense.sparse and sparse.sparse
    W = np.random.default_rng(0).uniform(0, 1, (4, 10))
    np.testing.assert_allclose(dense.evaluate(W), sparse.evaluate(W), atol=1e-12)
    np.testing.assert_allclose(dense.gram(), sparse.gram(), atol=1e-12)
    rows = dense.rows([3, 40], "xz")
    np.testing.assert_array_equal(rows, [9, 11, 120, 122])
    np.testing.assert_allclose(dense.block(rows), sparse.block(rows))


def test_delta_and_absolute_shape_files_give_the_same_rig(tmp_path):
    r = overlapping_rig(n_shapes=4, grid=(8, 6), seed=2)
    (tmp_path / "a").mkdir()
    (tmp_path / "d").mkdir()
    a = load_rig(write_rig(tmp_path / "a", r))
    d = load_rig(write_rig(tmp_path / "d", r, shapes_are="delta"))
    w = np.array([0.2, 0.5, 0.0, 1.0])
    np.testing.assert_allclose(a.evaluate(w), d.evaluate(w), atol=2e-6)  # OBJ coordinates carry 6 decimals


def test_ranges_library_and_correctives(tmp_path):
    r = overlapping_rig(n_shapes=3, grid=(5, 5))
    extra = ("range: 1.5\nranges: {s01: [-0.5, 1]}\nlibrary:\n  ah: {s00: 0.8}\n  oo: {s01: 0.5, s02: 0.25}\n"
             "correctives:\n  - {shapes: [s00, s01], obj: c.obj}\n")
    rig = load_rig(write_rig(tmp_path, r, extra=extra))
    np.testing.assert_array_equal(rig.lower, [0, -0.5, 0])
    np.testing.assert_array_equal(rig.upper, [1.5, 1, 1.5])
    assert rig.correctives == [{"shapes": ["s00", "s01"], "obj": "c.obj"}]  # kept raw for the inverse rig
    # w0 from a blend of library expressions; sliders no expression names keep the base pose
    w = rig.expression_blend({"ah": 0.5, "oo": 1.0}, base=[0.1, 0.2, 0.3])
    np.testing.assert_allclose(w, [0.4, 0.5, 0.25])
    w = rig.expression_blend({"ah": 1.0}, base=[0.1, 0.2, 0.3])
    np.testing.assert_allclose(w, [0.8, 0.2, 0.3])
    with pytest.raises(InputError, match="unknown expression 'ahh'; did you mean 'ah'"):
        rig.expression_blend({"ahh": 1.0})


@pytest.mark.parametrize("extra, message", [
    ("library:\n  ah: {s0l: 0.5}\n", r"library.ah: unknown slider 's0l'; did you mean 's01'"),
    ("library:\n  ah: {s01: 1.5}\n", r"library.ah.s01: expected a number in the slider's range \[0, 1\]"),
    ("ranges: {s9: 1}\n", r"ranges: unknown slider 's9'"),
    ("range: [1, 0]\n", r"range: expected a number t"),
    ("libary: {}\n", r"unknown key 'libary'; did you mean 'library'"),
])
def test_bad_rig_yaml_is_a_clear_error(tmp_path, extra, message):
    r = overlapping_rig(n_shapes=2, grid=(4, 4))
    with pytest.raises(RetargetError, match=message):
        read_rig(write_rig(tmp_path, r, extra=extra))


def test_shapes_that_do_not_share_topology_are_rejected(tmp_path):
    r = overlapping_rig(n_shapes=2, grid=(4, 4))
    path = write_rig(tmp_path, r)
    other = np.array(r["faces"])[:, [0, 2, 1, 3]]
    (tmp_path / "shapes" / "s01.obj").write_bytes(format_obj(r["vertices"] + r["deltas"][1], other))
    with pytest.raises(InputError, match=r"s01.obj: face lines differ from .*neutral.obj"):
        load_rig(path)
    (tmp_path / "shapes" / "s01.obj").write_bytes(format_obj(r["vertices"][:-1], r["faces"][:1]))
    with pytest.raises(InputError, match=r"rig.yaml: shapes.s01 \(s01.obj\): 15 vertices, the neutral neutral.obj has 16"):
        load_rig(path)


def test_vertex_ids_outside_the_mesh_are_rejected():
    r = overlapping_rig(n_shapes=2, grid=(4, 4))
    rig = BlendshapeRig(r["vertices"], r["deltas"], r["names"])
    with pytest.raises(ShapeError, match=r"pins: vertex 16 is outside the mesh \(16 vertices, ids 0-15\)"):
        rig.rows([3, 16], where="pins")
    with pytest.raises(ShapeError, match="vertex -1 is outside"):
        rig.rows([-1])
    with pytest.raises(ValueError, match="axes"):
        parse_axes("xw")
    with pytest.raises(ShapeError, match=r"deltas: expected shape \(n, 16, 3\)"):
        BlendshapeRig(r["vertices"], r["deltas"][:, :5], r["names"])
