import os
import shutil
from pathlib import Path

import pytest

from retarget_cli.synth.take import write_take


@pytest.fixture(autouse=True, scope="session")
def session_user_cache(tmp_path_factory):
    """A temporary user rig cache for the whole session, set before any other session fixture runs a pipeline
    (``tiny_run``): no test ever writes into the user's ~/.cache."""
    keys = ("RETARGET_CACHE_DIR", "RETARGET_CACHE_SIZE")
    old = {k: os.environ.get(k) for k in keys}
    os.environ["RETARGET_CACHE_DIR"] = str(tmp_path_factory.mktemp("session-user-cache"))
    os.environ.pop("RETARGET_CACHE_SIZE", None)
    yield Path(os.environ["RETARGET_CACHE_DIR"]) / "rigs"
    for k, v in old.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


@pytest.fixture(autouse=True)
def user_cache(session_user_cache, tmp_path_factory, monkeypatch):
    """Every test gets its own empty user rig cache ($RETARGET_CACHE_DIR), never the user's ~/.cache."""
    d = tmp_path_factory.mktemp("user-cache")
    monkeypatch.setenv("RETARGET_CACHE_DIR", str(d))
    monkeypatch.delenv("RETARGET_CACHE_SIZE", raising=False)
    return d / "rigs"


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


SAMPLE = __import__("pathlib").Path(__file__).resolve().parents[1] / "sample_data"


@pytest.fixture(scope="session")
def ict_rig_dir(tmp_path_factory):
    """The ICT FaceKit (sample_data/ict, MIT) unpacked once per session, with its rig.yaml beside the OBJs."""
    import tarfile

    d = tmp_path_factory.mktemp("ict")
    with tarfile.open(SAMPLE / "ict" / "ict-facekit-rig.tar.xz") as tar:
        tar.extractall(d, filter="data")
    rig_dir = d / "ict-facekit"
    shutil.copy(SAMPLE / "ict" / "rig.yaml", rig_dir / "rig.yaml")
    return rig_dir


@pytest.fixture(scope="session")
def real_clip(tmp_path_factory):
    """The first 60 frames of the real clip sample_data/real/d3.mp4 (MIT) and its frame-0 annotation."""
    import cv2

    d = tmp_path_factory.mktemp("real_clip")
    cap = cv2.VideoCapture(str(SAMPLE / "real" / "d3.mp4"))
    fps = cap.get(cv2.CAP_PROP_FPS)
    out = None
    for _ in range(60):
        ok, frame = cap.read()
        assert ok, "sample_data/real/d3.mp4 has fewer than 60 frames"
        if out is None:
            h, w = frame.shape[:2]
            out = cv2.VideoWriter(str(d / "d3.avi"), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
        out.write(frame)
    cap.release()
    out.release()
    shutil.copy(SAMPLE / "real" / "d3_00000.pts", d / "d3_00000.pts")
    return d
