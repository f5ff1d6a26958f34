"""dlib's frontal face detector kept as a file in the user's cache (io/face_detector.py)."""

from pathlib import Path

import cv2
import numpy as np
from detector_marks import needs_detector

from retarget_cli.io.face_detector import DETECTOR_FOLDER, face_detector_file
from retarget_cli.methods.tracking.detect import Detector

SAMPLE = Path(__file__).resolve().parents[3] / "sample_data"


def _frames(n=3, every=60):
    cap = cv2.VideoCapture(str(SAMPLE / "real" / "d3.mp4"))
    out = []
    for i in range(n * every):
        ok, f = cap.read()
        assert ok
        if i % every == 0:
            out.append(cv2.cvtColor(f, cv2.COLOR_BGR2GRAY))
    cap.release()
    return out


@needs_detector
def test_cached_detector_finds_the_same_boxes_and_scores(tmp_path):
    env = {"RETARGET_CACHE_DIR": str(tmp_path / "cache")}
    file = face_detector_file(env)
    assert file is not None and file.parent == tmp_path / "cache" / DETECTOR_FOLDER and file.stat().st_size > 1000
    mtime = file.stat().st_mtime_ns
    assert face_detector_file(env) == file and file.stat().st_mtime_ns == mtime  # read, not written again
    assert not [p for p in file.parent.iterdir() if p != file]  # no temporary left
    own, cached = Detector(), Detector(faces_file=file)
    for g in _frames():
        for up in (0, 1):
            a, b = own.faces.run(g, up, 0.0), cached.faces.run(g, up, 0.0)
            assert [(r.left(), r.top(), r.right(), r.bottom()) for r in a[0]] == \
                   [(r.left(), r.top(), r.right(), r.bottom()) for r in b[0]]
            assert list(a[1]) == list(b[1]) and len(a[0]) == 1


@needs_detector
def test_no_file_when_the_cache_keeps_nothing(tmp_path):
    env = {"RETARGET_CACHE_DIR": str(tmp_path / "cache"), "RETARGET_CACHE_SIZE": "0"}
    assert face_detector_file(env) is None
    assert not (tmp_path / "cache").exists()


@needs_detector
def test_an_unreadable_file_falls_back_to_dlibs_own_detector(tmp_path, caplog):
    bad = tmp_path / "frontal_face.svm"
    bad.write_bytes(b"not a detector")
    det = Detector(faces_file=bad)
    assert "not a face detector dlib can read" in caplog.text
    boxes = det.detect(_frames(1)[0])
    assert boxes.shape == (1, 4) and np.all(boxes[:, 2:] > 100)
