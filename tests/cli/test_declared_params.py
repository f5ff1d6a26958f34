"""A bad value for every declared parameter of every command: one usage error naming the option, exit 2.

As scikit-learn's ``test_public_functions.py`` checks every public function's
parameter validation, this walks the command registry
(:data:`retarget_cli.cli.commands.DECLARED`): for each option whose
declaration admits a wrong value (a choice, a range, a number, a value
syntax) it runs the command with that value and every other argument valid
enough to reach the check.
"""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from retarget_cli.cli.commands import DECLARED, flags_of, main

#: A value each value syntax refuses, and one it accepts.
BAD_SYNTAX = {"size": "12by", "indices": "a-b", "frames": "x", "region": "=", "mask": "nomask", "xyz": "1,2"}
GOOD_SYNTAX = {"size": "64x64", "indices": "1", "frames": "0", "region": "face", "mask": "a=b", "xyz": "0,0,0",
               "text": "x"}


def bad_value(param, flag) -> str | None:
    """A value the declaration refuses, or None when every string is acceptable (a path, a free text)."""
    if flag.value is not None:
        return BAD_SYNTAX.get(flag.value)
    if flag.path is not None or param.type is bool:
        return None
    if param.options:
        return "no-such-choice"
    if param.type in (int, float):
        if param.min is not None:
            return str(param.min if param.min_open else param.min - 1)
        if param.max is not None:
            return str(param.max if param.max_open else param.max + 1)
        return "not-a-number"
    return None


def cases():
    out = []
    for command in DECLARED:
        params = {p.name: p for p in command.params()}
        for flag in flags_of(command):
            if flag.argument:
                continue
            bad = bad_value(params[flag.name], flag)
            if bad is not None:
                out.append(pytest.param(command, flag, bad, id=f"{command.name}-{flag.name}"))
    return out


def _option(flag) -> str:
    return (flag.decls or ("--" + flag.name.replace("_", "-"),))[0].split("/")[0]


def _args(command, tmp_path, bad_flag, bad) -> list[str]:
    """The command line: valid placeholders for the arguments and required options, *bad* for *bad_flag*."""
    args = [command.name]
    for flag in flags_of(command):
        if flag.name == bad_flag.name:
            args += [_option(flag), bad]
        elif flag.argument:
            args += [str(tmp_path)] if flag.path == "existing" else [str(tmp_path / f"{flag.name}.in")]
        elif flag.required:
            args += [_option(flag), GOOD_SYNTAX.get(flag.value, str(tmp_path / f"{flag.name}.x"))]
    return args


def test_every_command_has_checked_parameters():
    """The walk covers every command that declares a constrained option (a registry change cannot hide one)."""
    covered = {c.values[0].name for c in cases()}
    every = {c.name for c in DECLARED}
    # edit's and run's options are paths, flags and free names; cache has only an argument (a choice: below)
    assert covered == every - {"edit", "run", "cache"}


def test_cache_refuses_an_unknown_action():
    res = CliRunner().invoke(main, ["cache", "purge"])
    assert res.exit_code == 2 and "'purge' is not one of 'info', 'clear'" in res.output


@pytest.mark.parametrize("command, flag, bad", cases())
def test_a_bad_value_is_one_usage_error(command, flag, bad, tmp_path):
    res = CliRunner().invoke(main, _args(command, tmp_path, flag, bad))
    assert res.exit_code == 2, res.output
    errors = [ln for ln in res.output.splitlines() if ln.startswith("Error:")]
    assert len(errors) == 1, res.output
    assert f"'{_option(flag)}'" in errors[0] or _option(flag) in errors[0], res.output
    assert "Traceback" not in res.output
    assert not any(tmp_path.iterdir()), "a refused command wrote something"


@pytest.mark.parametrize("setting, value", [("select.k", "0"), ("decompose.solver", "nnlss"),
                                            ("track.window", "2")])
@pytest.mark.parametrize("way", ["file", "--set"])
def test_a_bad_config_value_exits_2_as_on_the_command_line(tmp_path, setting, value, way):
    cfg = tmp_path / "c.yaml"
    stage, key = setting.split(".")
    cfg.write_text(f"{stage}:\n  {key}: {value}\n" if way == "file" else f"{stage}: {{}}\n")
    res = CliRunner().invoke(main, ["run", str(cfg), *(["--set", f"{setting}={value}"] if way == "--set" else [])])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and setting in lines[0] and "Traceback" not in res.output, res.output
