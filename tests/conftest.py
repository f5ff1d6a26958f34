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


@pytest.fixture
def truncated_avi(small_take, tmp_path):
    """The small take re-encoded as MJPG avi and cut in half: the container announces more frames than decode."""
    import cv2

    cap = cv2.VideoCapture(str(small_take / "face.mp4"))
    avi = tmp_path / "full.avi"
    w = cv2.VideoWriter(str(avi), cv2.VideoWriter_fourcc(*"MJPG"), 30, (192, 192))
    while True:
        ok, f = cap.read()
        if not ok:
            break
        w.write(f)
    cap.release()
    w.release()
    data = avi.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: len(data) // 2])
    return cut
