"""Shared fixtures of the robustness tests: a tiny synthetic take, run once, copied per test."""

import hashlib
import shutil
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """A 24-frame 96x96 synthetic take with every output of `retarget run` in out/ (made once)."""
    from click.testing import CliRunner

    from retarget_cli.cli.commands import main
    from retarget_cli.synth.take import write_take

    d = tmp_path_factory.mktemp("tiny") / "take"
    write_take(d, n_frames=24, size=(96, 96), seed=0)
    res = CliRunner().invoke(main, ["-q", "run", str(d / "config.yaml")])
    assert res.exit_code == 0, res.output
    return d


@pytest.fixture
def take(tiny_run, tmp_path):
    """A private copy of :func:`tiny_run` that a test may modify."""
    d = tmp_path / "take"
    shutil.copytree(tiny_run, d, symlinks=True)
    return d


def snapshot(root: Path) -> dict[str, str]:
    """Relative path to sha256 of every file under *root*."""
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}
