from pathlib import Path

import pytest
from click.testing import CliRunner

from retarget_cli.cli.commands import main

COMMANDS = sorted(main.commands)


def test_the_stage_commands_exist():
    assert {"track", "select", "decompose", "apply", "run", "synth", "pose-keys"} <= set(COMMANDS)


@pytest.mark.parametrize("command", [None, *COMMANDS])
def test_help_for_every_command(command):
    args = ["--help"] if command is None else [command, "--help"]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert "Usage:" in result.output


def test_misspelt_config_key_is_one_line_with_suggestion(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("select:\n  methd: pca-extremes\n")
    result = CliRunner().invoke(main, ["run", str(cfg)])
    assert result.exit_code == 2  # a config error is a usage error, whichever way it comes in
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1
    assert "unknown key 'methd'" in lines[0] and "did you mean 'method'?" in lines[0] and "c.yaml" in lines[0]


def test_missing_input_file_is_named(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("track: {video: nowhere.mp4, init: nowhere.pts}\n")
    result = CliRunner().invoke(main, ["run", str(cfg)])
    assert result.exit_code == 1
    assert "nowhere.mp4" in result.stderr and "not found" in result.stderr


def test_missing_input_for_a_stage_command(tmp_path):
    result = CliRunner().invoke(main, ["decompose", str(tmp_path / "none.npz"), str(tmp_path / "k.json"),
                                       "-o", str(tmp_path / "w.npz")])
    assert result.exit_code == 1
    assert "none.npz: landmarks file not found" in result.stderr


def test_usage_errors_exit_2(tmp_path):
    result = CliRunner().invoke(main, ["select", str(tmp_path / "x.npz"), "-k", "0"])
    assert result.exit_code == 2
    result = CliRunner().invoke(main, ["synth", str(tmp_path), "--size", "big"])
    assert result.exit_code == 2 and "--size" in result.stderr


def test_invalid_yaml_is_one_line_naming_file_and_position(tmp_path):
    from click.testing import CliRunner

    from retarget_cli.cli.commands import main
    from retarget_cli.errors import InputError
    from retarget_cli.io.stagefiles import read_targets

    bad = tmp_path / "bad.yaml"
    bad.write_text("version: 1\nn_points: 68\n{\n1 2\n")
    (tmp_path / "anim.csv").write_text("frame,smile\n0,0.1\n")
    # a bad config is a usage error (2); a bad edits file is a bad input (1)
    for code, args in ((2, ["run", str(bad)]),
                       (1, ["edit", str(tmp_path / "anim.csv"), str(bad), "--rig",
                            str(Path(__file__).resolve().parents[2] / "sample_data" / "rig.yaml"),
                            "-o", str(tmp_path / "o.csv")])):
        res = CliRunner().invoke(main, args)
        lines = [ln for ln in res.output.splitlines() if ln.strip()]
        assert res.exit_code == code, res.output
        assert len(lines) == 1 and "invalid YAML" in lines[0] and "line 4" in lines[0], res.output
    try:
        read_targets(bad)
    except InputError as exc:
        assert "\n" not in str(exc) and "bad.yaml: invalid YAML" in str(exc)
    else:
        raise AssertionError("read_targets accepted invalid YAML")
