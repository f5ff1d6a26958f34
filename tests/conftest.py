import shutil

import pytest

from retarget_cli.synth import write_take


@pytest.fixture(scope="session")
def small_take_template(tmp_path_factory):
    """A short synthetic take (60 frames, 192x192), generated once per session."""
    d = tmp_path_factory.mktemp("small_take")
    write_take(d, n_frames=60, size=(192, 192), seed=1)
    return d


@pytest.fixture
def small_take(small_take_template, tmp_path):
    """A private copy of the short take that a test may modify."""
    d = tmp_path / "take"
    shutil.copytree(small_take_template, d)
    return d
