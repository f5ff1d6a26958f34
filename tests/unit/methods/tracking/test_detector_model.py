"""The detector's model file (track.detect.predictor_model_path): found without ``pkg_resources``, or a one-line error.

``face_recognition_models`` imports ``pkg_resources`` (setuptools), which Python 3.12+ virtual environments do not
have, so the model is located through the distribution's metadata and never by importing that package. Under
``RETARGET_REQUIRE_DETECTOR=1`` (``make test``, ``.ci/run``) the tests marked ``needs_detector`` run and fail when the
detector cannot load its model.
"""

import importlib.metadata
import json
import subprocess
import sys
from pathlib import Path

import pytest
from detector_marks import needs_detector

from retarget_cli.errors import MissingExtraError
from retarget_cli.methods.tracking import detect

SAMPLE = Path(__file__).resolve().parents[4] / "sample_data"

# Run in a fresh interpreter where ``import pkg_resources`` fails, as in a Python 3.12+ venv.
WITHOUT_PKG_RESOURCES = """
import json, sys
sys.modules["pkg_resources"] = None  # any import of it now raises ImportError
import cv2, numpy as np
from retarget_cli.io.annotations import read_pts
from retarget_cli.methods.tracking.detect import Detector, detect_landmarks, detector_installed
cap = cv2.VideoCapture(sys.argv[1])
ok, frame = cap.read()
cap.release()
det = Detector()
P, box = detect_landmarks(frame, detector=det)
err = float(np.linalg.norm(P - read_pts(sys.argv[2]), axis=1).mean())
print(json.dumps({"installed": detector_installed(), "model": str(det.model_path), "points": list(P.shape),
                  "err": err, "imported": sorted(m for m in ("face_recognition_models", "pkg_resources")
                                                 if sys.modules.get(m) is not None)}))
"""


@needs_detector
def test_detector_loads_its_model_and_finds_the_face_without_pkg_resources():
    r = subprocess.run([sys.executable, "-c", WITHOUT_PKG_RESOURCES, str(SAMPLE / "real" / "d3.mp4"),
                        str(SAMPLE / "real" / "d3_00000.pts")], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["installed"] and out["imported"] == []
    assert Path(out["model"]).name == "shape_predictor_68_face_landmarks.dat" and Path(out["model"]).is_file()
    assert out["points"] == [68, 2] and out["err"] < 2.0, out  # frame 0 of d3 against its committed annotation


@needs_detector
def test_model_found_beside_the_package_when_the_metadata_lists_no_files(monkeypatch):
    path = detect.predictor_model_path()
    monkeypatch.setattr(importlib.metadata, "files", lambda name: None)
    assert detect.predictor_model_path() == path


def test_a_missing_model_package_is_a_one_line_error_naming_the_extra(monkeypatch):
    monkeypatch.setattr(detect, "MODEL_PACKAGE", "no_such_model_package_for_retarget")
    with pytest.raises(MissingExtraError) as e:
        detect.predictor_model_path()
    msg = str(e.value)
    assert "no_such_model_package_for_retarget is not installed" in msg and "retarget[detect]" in msg
    assert "\n" not in msg
    assert not detect.detector_installed()


@needs_detector
def test_a_corrupt_model_file_is_a_one_line_error(monkeypatch, tmp_path):
    bad = tmp_path / "shape_predictor_68_face_landmarks.dat"
    bad.write_bytes(b"not a dlib model")
    monkeypatch.setattr(detect, "predictor_model_path", lambda: bad)
    with pytest.raises(MissingExtraError) as e:
        detect.Detector()
    msg = str(e.value)
    assert str(bad) in msg and "could not load" in msg and "retarget[detect]" in msg and "\n" not in msg
