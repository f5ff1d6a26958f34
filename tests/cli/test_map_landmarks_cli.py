"""``retarget map-landmarks``: the map file, the contact sheet, --points corrections, one-line errors; auto-pose's cache."""

import logging

import numpy as np
import pytest
from click.testing import CliRunner

from retarget_cli.cli.commands import main
from retarget_cli.io.obj import format_obj
from retarget_cli.io.rig import load_rig, read_rig
from retarget_cli.io.rig.vertexmap import read_vertex_map
from retarget_cli.methods import landmark_map as lm
from retarget_cli.stages import map_landmarks
from tests.unit.methods.test_landmark_map import sphere_head


@pytest.fixture
def head_rig(tmp_path, monkeypatch):
    """The synthetic stylised head as a rig folder (no landmarks:); the detector is kept out (no face anyway)."""
    V, quads, D, names, _ = sphere_head()
    d = tmp_path / "rig"
    d.mkdir()
    (d / "neutral.obj").write_bytes(format_obj(V, quads))
    for n, dl in zip(names, D):
        (d / f"{n}.obj").write_bytes(format_obj(V + dl, quads))
    (d / "rig.yaml").write_text("neutral: neutral.obj\nshapes:\n" + "".join(f"  {n}: {n}.obj\n" for n in names))
    monkeypatch.setattr(map_landmarks, "_detector", lambda: None)
    return d / "rig.yaml"


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def test_map_landmarks_writes_a_map_auto_pose_reads_and_a_sheet(head_rig, tmp_path):
    out, sheet = tmp_path / "out" / "map.txt", tmp_path / "out" / "map.png"
    res = run("map-landmarks", head_rig, "-o", out, "--sheet", sheet)
    assert res.exit_code == 0, res.output
    lms, vx = read_vertex_map(out, 68, load_rig(head_rig).n_vertices)
    assert len(vx) == 68 and list(lms) == list(range(68))
    assert sheet.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = res.output
    assert "found by: sliders" in text and "inter-ocular distance" in text and "symmetry" in text
    assert "eye_left" in text and "6 sliders:blink" in text
    # same inputs, same bytes
    first = (out.read_bytes(), sheet.read_bytes())
    assert run("map-landmarks", head_rig, "-o", out, "--sheet", sheet).exit_code == 0
    assert (out.read_bytes(), sheet.read_bytes()) == first


def test_points_file_corrects_by_vertex_and_by_sheet_pixel(head_rig, tmp_path):
    base = tmp_path / "base.txt"
    assert run("map-landmarks", head_rig, "-o", base).exit_code == 0
    _, before = read_vertex_map(base, 68, load_rig(head_rig).n_vertices)
    r = load_rig(head_rig)
    m = map_landmarks.find_map(r, detector=None)
    v = int(m.vertices[33])
    x, y = (m.render.xy[v] + 0.5) * lm.SHEET_SCALE - 0.5
    pts = tmp_path / "fix.txt"
    pts.write_text(f"# corrections\n0 7\n30 {x:.3f} {y:.3f}\n")
    out = tmp_path / "fixed.txt"
    res = run("map-landmarks", head_rig, "-o", out, "--points", pts)
    assert res.exit_code == 0, res.output
    _, after = read_vertex_map(out, 68, r.n_vertices)
    assert after[0] == 7 and after[30] == v
    assert np.array_equal(np.delete(after, [0, 30]), np.delete(before, [0, 30]))
    assert "2 user" in res.output


@pytest.mark.parametrize("content, message", [
    ("0 1 2 3\n", "fix.txt:1: expected 'index vertex' or 'index x y'"),
    ("68 5\n", "fix.txt:1: landmark 68 does not exist"),
    ("3 5\n3 6\n", "fix.txt:2: landmark 3 is corrected twice (also on line 1)"),
    ("3 999999\n", "fix.txt:1: vertex 999999 is outside the mesh"),
    ("3 -4 10\n", "fix.txt:1: pixel (-4, 10) is outside the contact sheet"),
    ("a b\n", "fix.txt:1: expected 'index vertex' or 'index x y'"),
])
def test_bad_points_files_are_one_line_errors(head_rig, tmp_path, content, message):
    pts = tmp_path / "fix.txt"
    pts.write_text(content)
    res = run("map-landmarks", head_rig, "-o", tmp_path / "m.txt", "--points", pts)
    assert res.exit_code == 1
    assert message in res.output and "Traceback" not in res.output
    assert not (tmp_path / "m.txt").exists()


def test_command_errors_are_one_line(head_rig, tmp_path):
    res = run("map-landmarks", tmp_path / "missing.yaml", "-o", tmp_path / "m.txt")
    assert res.exit_code != 0 and "Traceback" not in res.output
    res = run("map-landmarks", head_rig, "-o", tmp_path / "m.txt", "--sheet", tmp_path / "m.jpg")
    assert res.exit_code == 1 and "m.jpg: the contact sheet is a PNG" in res.output
    res = run("map-landmarks", head_rig, "-o", head_rig)
    assert res.exit_code != 0 and "Traceback" not in res.output
    assert read_rig(head_rig)  # the input is untouched
    res = run("map-landmarks", head_rig, "-o", tmp_path / "m.txt", "--yaw", "400")
    assert res.exit_code == 2


def test_auto_pose_map_is_found_once_and_refound_when_the_rig_changes(head_rig, tmp_path, caplog):
    r, spec = load_rig(head_rig), read_rig(head_rig)
    folder = tmp_path / "targets"
    with caplog.at_level(logging.WARNING):
        path = map_landmarks.cached_landmark_map(head_rig, r, spec, folder)
    assert path == folder / "landmark_map.txt" and (folder / "landmark_map.png").is_file()
    assert "landmark_map.png" in caplog.text and "map-landmarks --points" in caplog.text
    mtime = path.stat().st_mtime_ns
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert map_landmarks.cached_landmark_map(head_rig, r, spec, folder) == path
    assert path.stat().st_mtime_ns == mtime and not caplog.text  # reused, no new warning
    head_rig.write_text(head_rig.read_text() + "# edited\n")
    map_landmarks.cached_landmark_map(head_rig, r, read_rig(head_rig), folder)
    assert map_landmarks.DIGEST_PREFIX in path.read_text() and path.stat().st_mtime_ns != mtime
    _, vx = read_vertex_map(path, 68, r.n_vertices)
    assert len(vx) == 68
