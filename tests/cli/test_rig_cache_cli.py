"""Commands that load a rig: arguments checked before the rig's OBJs are parsed, and where the rig cache goes."""

import numpy as np
import pytest
from click.testing import CliRunner

from retarget_cli.cli.commands import main
from retarget_cli.io.atomic import savez
from retarget_cli.io.rig import cache as rigcache
from retarget_cli.io.stagefiles import write_keys


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


@pytest.fixture
def take(small_take):
    write_keys(small_take / "keys.json", small_take / "truth_landmarks.npz",
               {"face": {"points": [0, 1], "frames": [0, 7, 20], "method": "test", "error": 0.0}})
    return small_take


@pytest.fixture
def no_parse(monkeypatch):
    """Make any full parse of a rig OBJ fail the test."""
    def fail(path):
        raise AssertionError(f"{path} was parsed")

    monkeypatch.setattr(rigcache, "read_obj", fail)


def _caches(d):
    return sorted(d.glob("rig-*.npz")) if d.is_dir() else []


def test_pose_keys_caches_the_rig_in_the_output_folder(take, monkeypatch):
    out = take / "targets"
    res = run("pose-keys", take / "keys.json", take / "rig.yaml", "--poses", take / "truth.npz", "-o", out)
    assert res.exit_code == 0, res.output
    assert len(_caches(out / ".retarget-cache")) == 1
    assert not (take / ".retarget-cache").exists()
    first = {p.name: p.read_bytes() for p in (out / "face").glob("*.obj")}
    monkeypatch.setattr(rigcache, "read_obj", lambda p: pytest.fail(f"{p} parsed although cached"))
    res = run("pose-keys", take / "keys.json", take / "rig.yaml", "--poses", take / "truth.npz", "-o", out)
    assert res.exit_code == 0, res.output
    assert {p.name: p.read_bytes() for p in (out / "face").glob("*.obj")} == first and len(first) == 3


def test_no_cache_writes_no_cache(take):
    out = take / "t2"
    res = run("pose-keys", take / "keys.json", take / "rig.yaml", "--poses", take / "truth.npz", "-o", out,
              "--no-cache")
    assert res.exit_code == 0, res.output
    assert not (out / ".retarget-cache").exists()


def test_pose_keys_checks_poses_and_masks_before_parsing_the_rig(take, no_parse):
    bad = take / "bad.npz"
    savez(bad, {"curves": np.zeros((30, 1)), "names": np.array(["smiel"])})
    res = CliRunner().invoke(main, ["pose-keys", str(take / "keys.json"), str(take / "rig.yaml"),
                                    "--poses", str(bad), "-o", str(take / "t")])
    assert res.exit_code == 1 and "slider 'smiel' is not a shape" in res.output
    res = CliRunner().invoke(main, ["pose-keys", str(take / "keys.json"), str(take / "rig.yaml"),
                                    "--poses", str(take / "truth.npz"), "--mask", "face=nope.txt",
                                    "-o", str(take / "t")])
    assert res.exit_code == 1 and "nope.txt: region mask not found" in res.output
    short = take / "short.npz"
    savez(short, {"curves": np.zeros((10, 1)), "names": np.array(["smile"])})
    res = CliRunner().invoke(main, ["pose-keys", str(take / "keys.json"), str(take / "rig.yaml"),
                                    "--poses", str(short), "-o", str(take / "t")])
    assert res.exit_code == 1 and "key frame 20 is outside" in res.output


def test_edit_checks_its_arguments_before_parsing_the_rig(take, no_parse):
    (take / "edits.yaml").write_text("rig: rig.yaml\nedits:\n  - pin:\n      frames: [1, 5]\n      constraints:\n"
                                     "        - {vertex: 999999, position: [0, 0, 0]}\n")
    res = CliRunner().invoke(main, ["edit", str(take / "truth.npz"), str(take / "edits.yaml"),
                                    "-o", str(take / "e.csv")])
    assert res.exit_code == 1 and "999999" in res.output
    res = CliRunner().invoke(main, ["edit", str(take / "truth.npz"), str(take / "edits.yaml"),
                                    "-o", str(take / "truth.npz")])
    assert res.exit_code == 1 and "would overwrite the input" in res.output
    res = CliRunner().invoke(main, ["edit", str(take / "truth.npz"), str(take / "edits.yaml"),
                                    "-o", str(take / "target" / "neutral.obj")])
    assert res.exit_code == 1 and "would overwrite the input" in res.output


def test_edit_caches_beside_its_output(take):
    (take / "out").mkdir()
    (take / "edits.yaml").write_text("rig: rig.yaml\nedits:\n  - attenuate:\n      frames: [1, 5]\n      select:\n"
                                     "        - {vertices: [0], axes: y}\n")
    res = run("edit", take / "truth.npz", take / "edits.yaml", "-o", take / "out" / "e.csv")
    assert res.exit_code == 0, res.output
    assert len(_caches(take / "out" / ".retarget-cache")) == 1


def test_solve_rig_checks_outputs_and_meshes_before_parsing_the_rig(take, no_parse):
    res = CliRunner().invoke(main, ["solve-rig", str(take / "rig.yaml"), str(take / "nothing" / "*.obj"),
                                    "-o", str(take / "curves.npz")])
    assert res.exit_code == 1 and "no such file, directory or matching OBJ files" in res.output
    res = CliRunner().invoke(main, ["solve-rig", str(take / "rig.yaml"), str(take / "target"),
                                    "-o", str(take / "target" / "shapes" / "smile.obj")])
    assert res.exit_code == 1 and "would overwrite the input" in res.output


def test_run_caches_the_rig_under_the_run_folder(take):
    (take / "pose.yaml").write_text("output_dir: runout\npose:\n  keys: keys.json\n  rig: rig.yaml\n"
                                    "  poses: truth.npz\n")
    res = run("run", take / "pose.yaml")
    assert res.exit_code == 0, res.output
    assert len(_caches(take / "runout" / ".retarget" / "cache")) == 1
    assert not (take / "runout" / "targets" / ".retarget-cache").exists()
    res = run("run", take / "pose.yaml", "--force", "--no-cache")
    assert res.exit_code == 0, res.output


def test_edit_objs_folder_must_not_hold_input_frames(take, no_parse):
    (take / "frames").mkdir()
    (take / "frames" / "frame_00000.obj").write_bytes((take / "target" / "neutral.obj").read_bytes())
    (take / "rig2.yaml").write_text((take / "rig.yaml").read_text().replace("target/neutral.obj",
                                                                             "frames/frame_00000.obj"))
    (take / "edits.yaml").write_text("rig: rig2.yaml\nedits:\n  - attenuate:\n      frames: [1, 5]\n      select:\n"
                                     "        - {vertices: [0], axes: y}\n")
    res = CliRunner().invoke(main, ["edit", str(take / "truth.npz"), str(take / "edits.yaml"),
                                    "-o", str(take / "e.csv"), "--objs", str(take / "frames")])
    assert res.exit_code == 1 and "would overwrite or remove the input" in res.output
