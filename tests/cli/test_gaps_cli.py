"""`track` through gaps (issue 33): the face lost and found again, a scene cut, an all-black take.

Clips are made in a temp folder with OpenCV from the 60-frame slice of the real clip (fixture ``real_clip``:
frames 0-59 of sample_data/real/d3.mp4, MIT): frames replaced by black, or the second half shown as another
shot (the same frames, small in a corner of a light background: an abrupt change of the whole picture).
"""

import importlib.util
import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from retarget_cli.cli.commands import main
from retarget_cli.io.landmarks import load_landmarks

HAS_DLIB = importlib.util.find_spec("dlib") is not None and importlib.util.find_spec("face_recognition_models") \
    is not None
pytestmark = pytest.mark.skipif(not HAS_DLIB, reason="needs the optional extra 'detect' (dlib-bin, "
                                                     "face_recognition_models): pip install -e '.[detect]'")
GAP = (20, 35)  # frames replaced by black
CUT = 30


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def frames_of(path):
    cap = cv2.VideoCapture(str(path))
    out = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        out.append(f)
    cap.release()
    return out


def write(path, frames, fps=30.0):
    h, w = frames[0].shape[:2]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    for f in frames:
        vw.write(f)
    vw.release()
    return path


@pytest.fixture(scope="module")
def clean(real_clip, tmp_path_factory):
    out = tmp_path_factory.mktemp("clean") / "lm.npz"
    r = run("-q", "track", real_clip / "d3.avi", "-o", out)
    assert r.exit_code == 0, r.output
    return load_landmarks(out)


def test_the_face_is_found_again_after_a_gap(real_clip, clean, tmp_path):
    fr = frames_of(real_clip / "d3.avi")
    for i in range(*GAP):
        fr[i] = np.zeros_like(fr[i])
    video = write(tmp_path / "gap.avi", fr)
    r = run("-q", "track", video, "-o", tmp_path / "lm.npz")
    assert r.exit_code == 0, r.output
    lm = load_landmarks(tmp_path / "lm.npz")
    a, b = GAP
    expect = np.ones(60, bool)
    expect[a:b] = False
    assert lm.found.tolist() == expect.tolist()
    assert lm.segment.tolist() == [0] * a + [-1] * (b - a) + [1] * (60 - b)
    assert np.all(lm.confidence[a:b] == 0) and lm.confidence[b:].mean() > 0.5
    # the gap holds the last found frame's landmarks: no jump into the gap, none out of it but the face's
    assert np.array_equal(lm.points[a:b], np.repeat(lm.points[a - 1:a], b - a, axis=0))
    assert lm.meta["gaps"] == [{"start": a, "frames": b - a, "reason": "no face", "cut": True,
                                "seconds": round((b - a) / lm.fps, 3)}]
    assert lm.meta["segments"] == 2
    # found again: after a few frames the landmarks are the clean take's (each segment smoothed apart)
    err = np.linalg.norm(lm.points[b + 3:] - clean.points[b + 3:], axis=-1).mean(1)
    assert err.max() < 1.5, err
    before = np.linalg.norm(lm.points[:a - 3] - clean.points[:a - 3], axis=-1).mean(1)
    assert before.max() < 1.5, before


def test_a_scene_cut_starts_a_new_segment(real_clip, clean, tmp_path):
    fr = frames_of(real_clip / "d3.avi")
    h, w = fr[0].shape[:2]
    for i in range(CUT, 60):  # another shot: the face small in a corner of a light background
        img = np.full_like(fr[i], 200)
        img[:h * 3 // 5, :w * 3 // 5] = cv2.resize(fr[i], (w * 3 // 5, h * 3 // 5), interpolation=cv2.INTER_AREA)
        fr[i] = img
    video = write(tmp_path / "cut.avi", fr)
    r = run("-q", "track", video, "-o", tmp_path / "lm.npz")
    assert r.exit_code == 0, r.output
    lm = load_landmarks(tmp_path / "lm.npz")
    assert lm.found.all()
    assert lm.segment.tolist() == [0] * CUT + [1] * (60 - CUT)
    assert lm.meta["gaps"] == [{"start": CUT, "frames": 0, "reason": "cut", "cut": True, "seconds": 0.0}]
    # the second shot's landmarks are the first's scaled into the corner (nothing smoothed across the cut)
    scaled = clean.points[CUT + 1:] * 0.6
    err = np.linalg.norm(lm.points[CUT + 1:] - scaled, axis=-1).mean(1)
    assert err.max() < 2.0, err


def test_an_all_black_take_is_still_a_one_line_error(tmp_path):
    video = write(tmp_path / "black.avi", [np.zeros((160, 160, 3), np.uint8)] * 60)
    r = run("-q", "track", video, "-o", tmp_path / "lm.npz")
    assert r.exit_code == 1
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and "no face found" in lines[0] and "60 frames" in lines[0], r.output
    assert str(video) in lines[0] and "--keep-partial" not in lines[0]
    assert not (tmp_path / "lm.npz").exists()


def test_keep_partial_is_for_truncated_files_only(real_clip, tmp_path):
    """A gap needs no --keep-partial: the take is tracked to its end with the flag or without."""
    fr = frames_of(real_clip / "d3.avi")[:40]
    for i in range(10, 40):
        fr[i] = np.zeros_like(fr[i])
    video = write(tmp_path / "leaves.avi", fr)
    r = run("-q", "track", video, "-o", tmp_path / "lm.npz")
    assert r.exit_code == 0, r.output
    lm = load_landmarks(tmp_path / "lm.npz")
    assert lm.n_frames == 40 and lm.found.sum() == 10
    assert json.loads(json.dumps(lm.meta["gaps"]))[0]["frames"] == 30


def test_without_a_gap_the_track_is_what_it_was(real_clip):
    """gaps=True changes nothing on a take with a face in every frame: the same points as the tracker without it."""
    from retarget_cli.methods.tracking.detect import Detector, track_detect

    frames = [cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) for f in frames_of(real_clip / "d3.avi")[:30]]
    det = Detector()
    P0, C0 = track_detect(iter(frames), detector=det)
    P1, C1, cov = track_detect(iter(frames), detector=det, gaps=True)
    assert cov.found.all() and not cov.cuts.any() and (cov.segment == 0).all()
    assert np.array_equal(P0, P1) and np.array_equal(C0, C1)
