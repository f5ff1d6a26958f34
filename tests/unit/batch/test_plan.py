"""Shot-list parsing and validation (retarget_cli.batch.plan): no Dask, nothing runs."""

import shlex
import sys
from pathlib import Path

import pytest

from retarget_cli.batch.plan import format_table, load_plan
from retarget_cli.errors import ConfigError, InputError, MissingExtraError


@pytest.fixture
def listed(small_take, tmp_path):
    def write(text, name="shots.yaml"):
        p = tmp_path / name
        p.write_text(text)
        return p

    return write


def test_base_form_paths_are_absolute_and_outputs_by_name(listed, tmp_path):
    plan = load_plan(listed("base: take/config.yaml\nshots:\n  - {name: s1, video: take/face.mp4, "
                            "set: {select: {k: 5}}}\n  - {name: s2, config: take/config.yaml}\n"))
    s1, s2 = plan.shots
    assert s1.output_dir == (tmp_path / "out" / "s1").resolve()
    assert s2.output_dir == (tmp_path / "take" / "out").resolve()
    assert f"track.video={(tmp_path / 'take' / 'face.mp4').resolve()}" in s1.overrides
    assert "select.k=5" in s1.overrides and s2.overrides == []
    args = shlex.split(s1.command())
    # the retarget that is running, by absolute path (a farm host need not have `retarget` on PATH)
    assert args[:5] == [str(Path(sys.executable).absolute()), "-m", "retarget_cli", "run",
                        str((tmp_path / "take" / "config.yaml").resolve())]


def test_csv_form_equals_yaml_form(listed):
    y = load_plan(listed("base: take/config.yaml\nshots:\n  - {name: s1, video: take/face.mp4, set: {select.k: 5}}\n"))
    c = load_plan(listed("name,base,video,select.k\ns1,take/config.yaml,take/face.mp4,5\n", "shots.csv"))
    assert [(s.name, s.config, s.overrides, s.output_dir) for s in y.shots] == \
        [(s.name, s.config, s.overrides, s.output_dir) for s in c.shots]


@pytest.mark.parametrize("text, message", [
    ("shots:\n  - {name: a, config: take/config.yaml}\n  - {name: a, config: take/config.yaml, output: x}\n",
     "shot a: name: repeats"),
    ("shots:\n  - {name: a, config: take/config.yaml}\n  - {name: b, config: take/config.yaml}\n",
     "shot b: output folder"),
    ("base: take/config.yaml\nshots:\n  - {name: a}\n  - {name: b, output: out/a/inner}\n", "inside that of shot a"),
    ("base: take/config.yaml\nshots:\n  - {name: a, vidoe: x.mp4}\n", "shot a: unknown key 'vidoe'; did you mean 'video'"),
    ("base: take/config.yaml\nshots:\n  - {name: a, video: take/missing.mp4}\n", "shot a: track.video"),
    ("base: take/config.yaml\nshots:\n  - {name: a, set: {select.k: 0}}\n", "select.k: 0 is out of range"),
    ("base: take/config.yaml\nshots:\n  - {name: a, set: {select.kk: 3}}\n", "did you mean 'k'"),
    ("shots:\n  - {name: a}\n", "shot a: config: required"),
    ("base: take/config.yaml\nshots:\n  - {name: ../x}\n", "shots[0]: name"),
])
def test_invalid_lists_are_one_line_errors_naming_shot_and_key(listed, text, message):
    with pytest.raises((ConfigError, InputError)) as err:
        load_plan(listed(text))
    assert message in str(err.value) and "\n" not in str(err.value)


def test_only_patterns(listed):
    plan = load_plan(listed("base: take/config.yaml\nshots:\n  - {name: take01}\n  - {name: take02}\n  - {name: x}\n"))
    assert [s.name for s in plan.select(["take*"])] == ["take01", "take02"]
    with pytest.raises(ConfigError, match="matches no shot"):
        plan.select(["nope"])


def test_table_has_a_row_per_shot_with_its_error():
    rows = [{"name": "a", "status": "done", "attempts": 1, "frames": 60, "confidence": 0.98, "residual_px": 0.1,
             "jitter": 0.02, "seconds": 1.5, "stages": {"track": {"status": "ran", "seconds": 1.25}}, "error": None},
            {"name": "b", "status": "failed", "attempts": 2, "stages": {}, "error": "x.mp4: cannot decode"}]
    lines = format_table(rows).splitlines()
    assert lines[0].split()[:2] == ["shot", "status"] and "track" in lines[0]
    assert lines[1].split()[:2] == ["a", "done"] and "1.25" in lines[1]
    assert lines[2].startswith("b") and lines[2].endswith("x.mp4: cannot decode")


def test_missing_dask_is_a_one_line_error_naming_the_extra(monkeypatch):
    from retarget_cli.batch import engine

    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(MissingExtraError, match=r"extra batch .*retarget\[batch\]"):
        engine.local_cluster(1)
