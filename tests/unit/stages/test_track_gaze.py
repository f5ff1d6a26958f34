"""track's gaze (issue 28): each iris located in the frames, filtered like the landmarks, held through a blink,
stored in landmarks.npz."""

import cv2
import numpy as np
import pytest

from retarget_cli.errors import InputError
from retarget_cli.io.landmarks import Landmarks, load_landmarks, save_landmarks
from retarget_cli.methods.tracking.gaze import EYES_68
from retarget_cli.stages._common import _no_progress
from retarget_cli.stages._landmark_filter import FILTER_DEFAULTS
from retarget_cli.stages.track import _track_gaze


def _eye_image(offset: float, closed: bool = False):
    """A 200x120 frame with one eye: white sclera between corners 60 px apart, a dark iris *offset* widths along."""
    img = np.full((120, 200), 150, np.uint8)
    c = np.array([100.0, 60.0])
    corners = c + np.array([[-30, 0], [30, 0]])
    half = 2 if closed else 11
    cv2.ellipse(img, (100, 60), (30, half), 0, 0, 360, 235, -1)
    if not closed:
        iris = (int(round(100 + offset * 60)), 60)
        mask = np.zeros_like(img)
        cv2.ellipse(mask, (100, 60), (30, half), 0, 0, 360, 1, -1)
        disk = np.zeros_like(img)
        cv2.circle(disk, iris, 11, 1, -1)
        img[(disk & mask).astype(bool)] = 40
    pts = np.zeros((68, 2))
    for eye in EYES_68:
        pts[eye[0]], pts[eye[1]] = corners
        for u, lo in zip(eye[2], eye[3]):
            x = 100 + (-10 if u == eye[2][0] else 10)
            pts[u], pts[lo] = (x, 60 - half), (x, 60 + half)
    return img, pts


#: (iris offset in eye widths, eye closed) per frame: looking right, a blink, then looking left
SCRIPT = [(0.15, False)] * 6 + [(0.0, True)] * 3 + [(0.15, False)] * 3 + [(-0.1, False)] * 8


def _video(tmp_path):
    points = []
    for t, (offset, closed) in enumerate(SCRIPT):
        img, pts = _eye_image(offset, closed)
        cv2.imwrite(str(tmp_path / f"f_{t:03d}.png"), img)
        points.append(pts)
    return str(tmp_path / "f_%03d.png"), np.array(points)


@pytest.mark.parametrize("method", ["rts", "none"])
def test_track_gaze_follows_the_iris_and_holds_through_a_blink(tmp_path, method):
    video, points = _video(tmp_path)
    settings = dict(FILTER_DEFAULTS, filter=method)
    g, valid = _track_gaze(video, points, np.ones(points.shape[:2]), None, start=0, end=None, step=1, fps=30.0,
                           settings=settings, progress=_no_progress)
    assert g.shape == (len(SCRIPT), 2, 2) and valid.shape == (len(SCRIPT), 2)
    closed = np.array([c for _, c in SCRIPT])
    assert not valid[closed].any() and valid[~closed].all()
    # the blink holds the gaze where it was (no jump toward the closed lid's centre)
    assert np.all(np.abs(g[closed, :, 0] - 0.15) < 0.03)
    assert np.all(np.abs(g[:6, :, 0] - 0.15) < 0.03) and np.all(np.abs(g[-3:, :, 0] + 0.1) < 0.03)
    assert np.all(np.abs(g[..., 1]) < 0.03)


def test_gaze_round_trips_through_landmarks_npz_and_bad_shapes_are_one_line_errors(tmp_path):
    T = 5
    pts = np.random.default_rng(0).uniform(0, 100, (T, 68, 2))
    heads = np.tile(np.eye(2, 3), (T, 1, 1))
    g = np.linspace(-0.2, 0.2, T * 4).reshape(T, 2, 2)
    valid = np.ones((T, 2), bool)
    valid[2, 1] = False
    save_landmarks(tmp_path / "a.npz", Landmarks(pts, np.ones((T, 68)), heads, pts, gaze=g, gaze_valid=valid))
    lm = load_landmarks(tmp_path / "a.npz")
    np.testing.assert_allclose(lm.gaze, g, atol=1e-6)
    assert lm.gaze_valid.dtype == bool and np.array_equal(lm.gaze_valid, valid)
    save_landmarks(tmp_path / "b.npz", Landmarks(pts, np.ones((T, 68)), heads, pts))
    assert load_landmarks(tmp_path / "b.npz").gaze is None
    data = dict(np.load(tmp_path / "a.npz"))
    data["gaze"] = np.zeros((T, 2, 3))
    np.savez(tmp_path / "bad.npz", **data)
    with pytest.raises(InputError, match=r"bad.npz: 'gaze' must have shape \(5, 2, 2\)"):
        load_landmarks(tmp_path / "bad.npz")
    data["gaze"] = np.full((T, 2, 2), np.nan)
    np.savez(tmp_path / "nan.npz", **data)
    with pytest.raises(InputError, match="'gaze' must be finite; frame 0"):
        load_landmarks(tmp_path / "nan.npz")


#: the iris sweeping left, a long closure (16 frames, d3's squint at frame 117), then seen again
SWEEP = [(0.2 - 0.04 * t, False) for t in range(5)] + [(0.0, True)] * 16 + [(0.11, False)] * 6


@pytest.mark.parametrize("method", [None, "none"])
def test_a_long_closure_after_a_sweep_holds_the_gaze_instead_of_carrying_its_velocity(tmp_path, method):
    points = []
    for t, (offset, closed) in enumerate(SWEEP):
        img, pts = _eye_image(offset, closed)
        cv2.imwrite(str(tmp_path / f"s_{t:03d}.png"), img)
        points.append(pts)
    settings = dict(FILTER_DEFAULTS) if method is None else dict(FILTER_DEFAULTS, filter=method)
    g, valid = _track_gaze(str(tmp_path / "s_%03d.png"), np.array(points), np.ones((len(SWEEP), 68)), None,
                           start=0, end=None, step=1, fps=30.0, settings=settings, progress=_no_progress)
    closed = np.array([c for _, c in SWEEP])
    assert not valid[closed].any()
    # held near the last seen gaze (0.04) or the next (0.11): never carried on past them (the smoother's motion
    # model took d3's iris 1.7 eye widths away)
    assert g[closed, :, 0].min() > -0.05 and g[closed, :, 0].max() < 0.2
