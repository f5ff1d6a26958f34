"""Every runner's signature matches its Param declarations, and the Python API checks its settings."""

import inspect

import pytest

from retarget_cli import stages
from retarget_cli.config import REQUIRED
from retarget_cli.errors import ParameterError
from retarget_cli.stages.annotate import run_annotate

RUNNERS = [stages.run_track, stages.run_train_tracker, stages.run_import, run_annotate, stages.run_select,
           stages.run_decompose, stages.run_pose, stages.run_auto_pose, stages.run_apply, stages.run_edit,
           stages.run_solve_rig]
#: Arguments that are plumbing, not settings: the progress bar, the rig cache, the config's folder, the run's seed.
PLUMBING = {"progress", "cache_dir", "base_dir", "seed"}


def _plain(v):
    return list(v) if isinstance(v, tuple) else v


@pytest.mark.parametrize("runner", RUNNERS, ids=lambda f: f.__name__)
def test_signature_matches_declaration(runner):
    sig = inspect.signature(runner)
    params = runner.params() if callable(runner.params) else runner.params
    declared = {p.name: p for p in params}
    args = {n: a for n, a in sig.parameters.items()
            if (n not in PLUMBING or n in declared) and a.kind is not inspect.Parameter.VAR_KEYWORD}
    assert sorted(args) == sorted(declared), (runner.__name__, set(args) ^ set(declared))
    for name, p in declared.items():
        default = args[name].default
        if p.default is REQUIRED:
            assert default is inspect.Parameter.empty, (runner.__name__, name, default)
        elif p.kind == "output" and default in (inspect.Parameter.empty, None):
            pass  # a default output name is the config's and the CLI's; the Python API says what to write
        else:
            assert _plain(default) == _plain(p.default), (runner.__name__, name, default, p.default)


def test_python_api_refuses_a_bad_setting(tmp_path):
    with pytest.raises(ParameterError, match="method"):
        stages.run_select(landmarks=tmp_path / "lm.npz", output=tmp_path / "k.json", method="biggest")
    with pytest.raises(ParameterError, match="k: 0 is out of range"):
        stages.run_select(landmarks=tmp_path / "lm.npz", output=tmp_path / "k.json", k=0)
    with pytest.raises(ParameterError, match="alpha"):
        stages.run_decompose(landmarks=tmp_path / "lm.npz", keys=tmp_path / "k.json", output=tmp_path / "w.npz",
                             alpha=float("nan"))
