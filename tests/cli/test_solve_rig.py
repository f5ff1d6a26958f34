"""``retarget solve-rig`` and the files around it: rig.yaml correctives, mesh sequences, the output NPZ."""

import json

import numpy as np
import pytest
from click.testing import CliRunner

from retarget_cli.cli.commands import main
from retarget_cli.errors import InputError, RetargetError
from retarget_cli.io.atomic import load_npz
from retarget_cli.io.obj import format_obj, read_obj
from retarget_cli.io.rig import read_rig
from retarget_cli.io.rig.inverse import read_meshes, read_quadratic_rig

SHAPES = ["smile", "jaw_open", "blink", "pucker"]
CORRECTIVES = [("smile", "jaw_open"), ("jaw_open", "pucker")]


def _grid(side=7):
    u, v = np.meshgrid(np.linspace(-1, 1, side), np.linspace(-1, 1, side))
    verts = np.stack([u.ravel(), v.ravel(), 0.3 * np.cos(u.ravel())], 1)
    idx = np.arange(side * side).reshape(side, side)
    quads = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], -1).reshape(-1, 4)
    return verts, quads


def write_rig(d, correctives=CORRECTIVES, extra_yaml=""):
    """A small rig on disk: neutral, four shapes, corrective OBJs (neutral + corrective delta)."""
    rng = np.random.default_rng(0)
    verts, quads = _grid()
    (d / "shapes").mkdir(parents=True, exist_ok=True)
    (d / "correctives").mkdir(exist_ok=True)
    (d / "neutral.obj").write_bytes(format_obj(verts, quads))
    deltas = 0.3 * rng.normal(size=(len(SHAPES), len(verts), 3))
    for name, dlt in zip(SHAPES, deltas):
        (d / "shapes" / f"{name}.obj").write_bytes(format_obj(verts + dlt, quads))
    lines = ["neutral: neutral.obj", "shapes:"] + [f"  {n}: shapes/{n}.obj" for n in SHAPES]
    corr = 0.4 * rng.normal(size=(len(correctives), len(verts), 3))
    if correctives:
        lines.append("correctives:")
    for (a, b), c in zip(correctives, corr):
        (d / "correctives" / f"{a}_{b}.obj").write_bytes(format_obj(verts + c, quads))
        lines.append(f"  - {{shapes: [{a}, {b}], obj: correctives/{a}_{b}.obj}}")
    (d / "rig.yaml").write_text("\n".join(lines) + "\n" + extra_yaml)
    return d / "rig.yaml", verts, quads


def write_frames(d, rig_yaml, W):
    rig, _ = read_quadratic_rig(rig_yaml)
    _, quads = _grid()
    d.mkdir(parents=True, exist_ok=True)
    for t, pos in enumerate(rig.evaluate(W)):
        (d / f"frame_{t:05d}.obj").write_bytes(format_obj(pos, quads))
    return rig


def test_read_rig_keeps_correctives_and_still_rejects_unknown_keys(tmp_path):
    rig_yaml, _, _ = write_rig(tmp_path)
    spec = read_rig(rig_yaml)
    assert [c["shapes"] for c in spec.correctives] == [list(p) for p in CORRECTIVES]
    (tmp_path / "bad.yaml").write_text("neutral: neutral.obj\nshapes: {}\ncorrectivs: []\n")
    with pytest.raises(RetargetError, match="unknown key .correctivs.; did you mean .correctives."):
        read_rig(tmp_path / "bad.yaml")


def test_quadratic_rig_from_files_matches_the_objs(tmp_path):
    rig_yaml, _, _ = write_rig(tmp_path)
    rig, files = read_quadratic_rig(rig_yaml)
    assert rig.names == tuple(SHAPES) and rig.n_pairs == 2 and len(files) == 1 + 1 + 4 + 2
    assert rig.pairs.tolist() == [[0, 1], [1, 3]]
    from retarget_cli.io.obj import read_obj

    verts = read_obj(tmp_path / "neutral.obj").vertices
    smile = read_obj(tmp_path / "shapes/smile.obj").vertices
    corr = read_obj(tmp_path / "correctives/smile_jaw_open.obj").vertices
    w = np.zeros(4)
    w[0] = 1.0
    np.testing.assert_allclose(rig.evaluate(w), smile, atol=1e-12)
    w[1] = 0.5  # the corrective enters with weight 1 * 0.5 on top of both shapes
    jaw = read_obj(tmp_path / "shapes/jaw_open.obj").vertices
    np.testing.assert_allclose(rig.evaluate(w), smile + 0.5 * (jaw - verts) + 0.5 * (corr - verts), atol=1e-12)


@pytest.mark.parametrize("entries, msg", [
    ("  - {shapes: [smile, frown], obj: correctives/smile_jaw_open.obj}", "unknown shape 'frown'"),
    ("  - {shapes: [smile, jaw_open], obj: correctives/smile_jaw_open.obj}\n"
     "  - {shapes: [jaw_open, smile], obj: correctives/smile_jaw_open.obj}", r"duplicate pair \[jaw_open, smile\]"),
    ("  - {shapes: [smile, smile], obj: correctives/smile_jaw_open.obj}", "two different shapes"),
    ("  - {shapes: [smile], obj: correctives/smile_jaw_open.obj}", "'shapes' must name two shapes"),
    ("  - {shapes: [smile, jaw_open], file: x.obj}", "expected keys 'shapes' and 'obj'"),
    ("  - {shapes: [smile, blink], obj: correctives/missing.obj}", "missing.obj: OBJ file not found"),
])
def test_bad_corrective_entries_are_named(tmp_path, entries, msg):
    rig_yaml, _, _ = write_rig(tmp_path)
    text = rig_yaml.read_text().split("correctives:")[0] + "correctives:\n" + entries + "\n"
    rig_yaml.write_text(text)
    with pytest.raises(InputError, match=msg) as exc:
        read_quadratic_rig(rig_yaml)
    assert "rig.yaml" in str(exc.value) or "missing.obj" in str(exc.value)


def test_corrective_with_another_vertex_count_is_rejected(tmp_path):
    rig_yaml, verts, quads = write_rig(tmp_path)
    (tmp_path / "correctives" / "smile_jaw_open.obj").write_bytes(format_obj(verts[:-1], quads[:-6]))
    with pytest.raises(InputError, match=r"rig.yaml: correctives\[0\] \(smile_jaw_open.obj\): 48 vertices, "
                                         r"the neutral neutral.obj has 49"):
        read_quadratic_rig(rig_yaml)


def test_meshes_with_wrong_vertex_count_give_clear_errors(tmp_path):
    rig_yaml, verts, quads = write_rig(tmp_path)
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "frame_00000.obj").write_bytes(format_obj(verts, quads))
    (frames / "frame_00001.obj").write_bytes(format_obj(verts[:-2], quads[:-6]))
    with pytest.raises(InputError, match="frame_00001.obj: frame 1 has 47 vertices, the rig has 49"):
        read_meshes(frames, 49)
    np.savez(tmp_path / "pos.npz", positions=np.zeros((3, 40, 3)))
    with pytest.raises(InputError, match="'positions' has 40 vertices per frame, the rig has 49"):
        read_meshes(tmp_path / "pos.npz", 49)
    np.savez(tmp_path / "other.npz", points=np.zeros((3, 49, 3)))
    with pytest.raises(InputError, match="expected an array 'positions'"):
        read_meshes(tmp_path / "other.npz", 49)
    with pytest.raises(InputError, match="no such file"):
        read_meshes(str(tmp_path / "nothing" / "*.obj"), 49)


def test_mesh_sequences_are_read_in_natural_order(tmp_path):
    _, verts, quads = write_rig(tmp_path)
    d = tmp_path / "scans"
    d.mkdir()
    for k in (10, 2, 1):
        (d / f"scan_{k}.obj").write_bytes(format_obj(verts + k, quads))
    X, names = read_meshes(str(d / "scan_*.obj"), len(verts))
    assert names == ["scan_1.obj", "scan_2.obj", "scan_10.obj"]
    np.testing.assert_allclose(X[:, 0, 0], verts[0, 0] + np.array([1, 2, 10]), atol=1e-6)


@pytest.mark.parametrize("solver", ["lbfgsb", "mm"])
def test_solve_rig_recovers_known_weights(tmp_path, solver):
    rig_yaml, _, _ = write_rig(tmp_path)
    W = np.random.default_rng(1).uniform(0.05, 0.95, size=(5, 4))
    write_frames(tmp_path / "frames", rig_yaml, W)
    out = tmp_path / "w.npz"
    args = ["solve-rig", str(rig_yaml), str(tmp_path / "frames"), "-o", str(out), "--solver", solver,
            "--alpha", "0", "--tol", "1e-14", "--max-iter", "20000"]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    data = load_npz(out)
    np.testing.assert_allclose(data["curves"], W, atol=1e-4)
    assert list(data["names"]) == SHAPES
    assert data["rmse"].max() < 1e-5 and data["cardinality"].tolist() == [4] * 5
    assert set(data) >= {"objective", "iterations", "sources", "meta"}
    meta = json.loads(str(data["meta"]))
    assert meta["solver"] == solver and meta["summary"]["frames"] == 5
    assert "5 frames, 49 vertices, 4 shapes, 2 correctives" in res.stdout
    assert "mean rmse" in res.stdout and str(out) in res.stdout


def test_delta_rig_gives_the_same_result_as_the_equivalent_absolute_rig(tmp_path):
    """``shapes_are: delta``: shape and corrective OBJs are offsets, not neutral + offset (solve-rig)."""
    rig_yaml, verts, quads = write_rig(tmp_path / "abs")
    rig = write_frames(tmp_path / "frames", rig_yaml, np.random.default_rng(3).uniform(0.05, 0.95, size=(4, 4)))
    d = tmp_path / "delta"
    (d / "shapes").mkdir(parents=True)
    (d / "correctives").mkdir()
    (d / "neutral.obj").write_bytes(format_obj(verts, quads))
    for name in SHAPES:  # the offsets, read back from the absolute OBJs
        off = read_obj(tmp_path / "abs" / "shapes" / f"{name}.obj").vertices - read_obj(d / "neutral.obj").vertices
        (d / "shapes" / f"{name}.obj").write_bytes(format_obj(off, quads))
    for a, b in CORRECTIVES:
        off = (read_obj(tmp_path / "abs" / "correctives" / f"{a}_{b}.obj").vertices
               - read_obj(d / "neutral.obj").vertices)
        (d / "correctives" / f"{a}_{b}.obj").write_bytes(format_obj(off, quads))
    (d / "rig.yaml").write_text((tmp_path / "abs" / "rig.yaml").read_text() + "shapes_are: delta\n")
    delta_rig, _ = read_quadratic_rig(d / "rig.yaml")
    np.testing.assert_allclose(delta_rig.evaluate(np.full((1, 4), 0.7)), rig.evaluate(np.full((1, 4), 0.7)),
                               atol=1e-5)
    curves = []
    for y in (rig_yaml, d / "rig.yaml"):
        out = tmp_path / f"{y.parent.name}.npz"
        res = CliRunner().invoke(main, ["solve-rig", str(y), str(tmp_path / "frames"), "-o", str(out)])
        assert res.exit_code == 0, res.output
        curves.append(load_npz(out)["curves"])
    assert curves[0].max() > 0.1
    np.testing.assert_allclose(curves[1], curves[0], atol=1e-5)


def test_solve_rig_output_is_deterministic_and_metrics_csv(tmp_path):
    rig_yaml, _, _ = write_rig(tmp_path)
    rig = write_frames(tmp_path / "frames", rig_yaml, np.random.default_rng(2).uniform(0, 1, size=(4, 4)))
    np.savez(tmp_path / "pos.npz", positions=rig.evaluate(np.full((3, 4), 0.5)))
    outs = []
    for k in range(2):
        out = tmp_path / f"w{k}.npz"
        res = CliRunner().invoke(main, ["solve-rig", str(rig_yaml), str(tmp_path / "frames"), "-o", str(out),
                                        "--metrics", str(tmp_path / f"m{k}.csv")])
        assert res.exit_code == 0, res.output
        outs.append(out.read_bytes())
    assert outs[0] == outs[1]
    lines = (tmp_path / "m0.csv").read_text().splitlines()
    assert lines[0] == "frame,source,rmse,cardinality,objective,iterations,seconds" and len(lines) == 5
    assert lines[1].startswith("0,frame_00000.obj,")
    res = CliRunner().invoke(main, ["solve-rig", str(rig_yaml), str(tmp_path / "pos.npz"), "-o",
                                    str(tmp_path / "n.npz"), "--solver", "bounded"])
    assert res.exit_code == 0, res.output
    assert load_npz(tmp_path / "n.npz")["curves"].shape == (3, 4)


def test_solve_rig_errors_are_one_line(tmp_path):
    rig_yaml, verts, quads = write_rig(tmp_path)
    (tmp_path / "frames").mkdir()
    (tmp_path / "frames" / "frame_00000.obj").write_bytes(format_obj(verts[:-1], quads[:-6]))
    res = CliRunner().invoke(main, ["solve-rig", str(rig_yaml), str(tmp_path / "frames"), "-o", str(tmp_path / "w.npz")])
    assert res.exit_code == 1
    assert res.stderr.count("\n") == 1 and "frame 0 has 48 vertices, the rig has 49" in res.stderr
    rig_yaml.write_text(rig_yaml.read_text().replace("[smile, jaw_open]", "[smile, grin]"))
    res = CliRunner().invoke(main, ["solve-rig", str(rig_yaml), str(tmp_path / "frames"), "-o", str(tmp_path / "w.npz")])
    assert res.exit_code == 1 and "unknown shape 'grin'" in res.stderr and "rig.yaml" in res.stderr
    res = CliRunner().invoke(main, ["solve-rig", str(rig_yaml), str(tmp_path / "frames"), "-o", "x.npz",
                                    "--solver", "nope"])
    assert res.exit_code == 2
