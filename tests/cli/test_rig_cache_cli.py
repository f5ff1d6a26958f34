"""Commands that load a rig: arguments checked before the rig's OBJs are parsed, and where the rig cache goes
(the user's, shared by every run: $RETARGET_CACHE_DIR, which tests/conftest.py points at a temporary folder)."""

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


def test_pose_keys_caches_the_rig_in_the_user_cache(take, monkeypatch, user_cache):
    out = take / "targets"
    res = run("pose-keys", take / "keys.json", take / "rig.yaml", "--poses", take / "truth.npz", "-o", out)
    assert res.exit_code == 0, res.output
    assert len(_caches(user_cache)) == 1
    assert not list(take.rglob(".retarget-cache")) and not list(take.rglob("rig-*.npz"))
    first = {p.name: p.read_bytes() for p in (out / "face").glob("*.obj")}
    monkeypatch.setattr(rigcache, "read_obj", lambda p: pytest.fail(f"{p} parsed although cached"))
    # another output folder: the cache is shared across runs
    res = run("pose-keys", take / "keys.json", take / "rig.yaml", "--poses", take / "truth.npz", "-o", take / "t3")
    assert res.exit_code == 0, res.output
    assert {p.name: p.read_bytes() for p in (take / "t3" / "face").glob("*.obj")} == first and len(first) == 3


def test_no_cache_writes_no_cache(take, user_cache):
    out = take / "t2"
    res = run("pose-keys", take / "keys.json", take / "rig.yaml", "--poses", take / "truth.npz", "-o", out,
              "--no-cache")
    assert res.exit_code == 0, res.output
    assert not user_cache.exists() and not list(take.rglob("rig-*.npz"))


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


def test_edit_caches_in_the_user_cache(take, user_cache):
    (take / "out").mkdir()
    (take / "edits.yaml").write_text("rig: rig.yaml\nedits:\n  - attenuate:\n      frames: [1, 5]\n      select:\n"
                                     "        - {vertices: [0], axes: y}\n")
    res = run("edit", take / "truth.npz", take / "edits.yaml", "-o", take / "out" / "e.csv")
    assert res.exit_code == 0, res.output
    assert len(_caches(user_cache)) == 1 and sorted(p.name for p in (take / "out").iterdir()) == ["e.csv"]


def test_solve_rig_checks_outputs_and_meshes_before_parsing_the_rig(take, no_parse):
    res = CliRunner().invoke(main, ["solve-rig", str(take / "rig.yaml"), str(take / "nothing" / "*.obj"),
                                    "-o", str(take / "curves.npz")])
    assert res.exit_code == 1 and "no such file, directory or matching OBJ files" in res.output
    res = CliRunner().invoke(main, ["solve-rig", str(take / "rig.yaml"), str(take / "target"),
                                    "-o", str(take / "target" / "shapes" / "smile.obj")])
    assert res.exit_code == 1 and "would overwrite the input" in res.output


def test_run_caches_the_rig_in_the_user_cache_shared_by_runs(take, user_cache, monkeypatch):
    (take / "pose.yaml").write_text("output_dir: runout\npose:\n  keys: keys.json\n  rig: rig.yaml\n"
                                    "  poses: truth.npz\n")
    res = run("run", take / "pose.yaml")
    assert res.exit_code == 0, res.output
    assert len(_caches(user_cache)) == 1 and not list((take / "runout").rglob("rig-*.npz"))
    monkeypatch.setattr(rigcache, "read_obj", lambda p: pytest.fail(f"{p} parsed although cached"))
    res = run("run", take / "pose.yaml", "--set", "output_dir=runout2")
    assert res.exit_code == 0, res.output
    monkeypatch.undo()
    res = run("run", take / "pose.yaml", "--force", "--no-cache")
    assert res.exit_code == 0, res.output


def test_bad_cache_size_is_one_line_before_any_stage(take, monkeypatch):
    (take / "pose.yaml").write_text("output_dir: runout\npose:\n  keys: keys.json\n  rig: rig.yaml\n"
                                    "  poses: truth.npz\n")
    monkeypatch.setenv("RETARGET_CACHE_SIZE", "lots")
    res = CliRunner().invoke(main, ["run", str(take / "pose.yaml")])
    assert res.exit_code != 0 and "RETARGET_CACHE_SIZE: expected bytes such as 500M or 2G, got 'lots'" in res.output
    assert "Traceback" not in res.output and not (take / "runout" / "targets").exists()


def test_cache_info_and_clear(take, user_cache):
    res = run("pose-keys", take / "keys.json", take / "rig.yaml", "--poses", take / "truth.npz", "-o", take / "t")
    assert res.exit_code == 0, res.output
    (entry,) = _caches(user_cache)
    mine = user_cache / "rig-notes.txt"  # a file the cache did not write
    mine.write_text("keep me")
    lookalike = user_cache / "rig-0123456789abcdef.npz"  # named like an entry, but not one
    savez(lookalike, {"key": np.array("ffff")})
    res = run("cache")
    assert res.exit_code == 0, res.output
    lines = dict(line.split("\t") for line in res.output.splitlines())
    assert lines["folder"] == str(user_cache) and lines["entries"] == "1"
    assert lines["size"].startswith(f"{entry.stat().st_size / 2**20:.1f} MB of 2048.0 MB")
    res = run("cache", "clear")
    assert res.exit_code == 0 and "removed 1 entry" in res.output, res.output
    assert not entry.exists() and mine.read_text() == "keep me" and lookalike.is_file()
    assert run("cache").output.splitlines()[1] == "entries\t0"


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
