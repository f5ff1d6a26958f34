"""LK on a region of interest gives the full-frame result (issue 3, throughput)."""

import cv2
import numpy as np
import pytest

from retarget_cli.io.atomic import load_npz
from retarget_cli.io.video import VideoReader
from retarget_cli.methods.tracking.lk import _ANCHOR_LEVELS, _Box, _Reference, flow_forward_backward, track_lk

TOP, LEFT, SIZE = 40, 300, (640, 480)


@pytest.fixture(scope="module")
def padded(small_take_template):
    """The 192x192 take pasted into a 640x480 frame, so the face box is a real crop of it."""
    w, h = SIZE
    frames = [cv2.copyMakeBorder(f, TOP, h - 192 - TOP, LEFT, w - 192 - LEFT, cv2.BORDER_CONSTANT,
                                 value=(90, 100, 110)) for f in VideoReader(small_take_template / "face.mp4")]
    truth = load_npz(small_take_template / "truth_landmarks.npz")["points"].astype(np.float64) + [LEFT, TOP]
    return frames, truth


LK = dict(winSize=(21, 21), maxLevel=3, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 0.001))


def test_box_is_aligned_crop_around_points(padded):
    _, truth = padded
    box = _Box(truth[0].astype(np.float32), SIZE, 21, 3)
    assert (box.x0, box.y0) != (0, 0) or (box.x1, box.y1) != SIZE
    assert box.x1 - box.x0 < SIZE[0]  # a real crop
    assert box.x0 % 8 == 0 and box.y0 % 8 == 0  # pyramid levels sample the full frame's pixels
    margin = (21 // 2 + 8) * 8
    assert box.x0 <= truth[0, :, 0].min() - margin or box.x0 == 0
    assert box.x1 >= min(truth[0, :, 0].max() + margin, SIZE[0])
    assert box.y1 >= min(truth[0, :, 1].max() + margin, SIZE[1])
    # no finite point: the whole frame; tiny images keep their full size
    full = _Box(np.full((3, 2), np.nan), SIZE, 21, 3)
    assert (full.x0, full.y0, full.x1, full.y1) == (0, 0, *SIZE)
    small = _Box(np.array([[5.0, 5.0]]), (100, 90), 21, 3)
    assert (small.x0, small.y0, small.x1, small.y1) == (0, 0, 100, 90)
    # near an edge the crop keeps enough rows/columns for every pyramid level
    edge = _Box(np.array([[630.0, 470.0]]), SIZE, 21, 3)
    assert edge.x1 - edge.x0 >= 23 * 8 and edge.y1 - edge.y0 >= 23 * 8


def test_box_flow_equals_full_frame_flow(padded):
    frames, truth = padded
    g = [cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) for f in frames[:6]]
    for t in range(1, 6):
        p = truth[t - 1].astype(np.float32).reshape(-1, 1, 2)
        full, e_full = flow_forward_backward(g[t - 1], g[t], p, LK)
        box = _Box(p, SIZE, 21, 3)
        crop, e_crop = box.flow(box.crop(g[t - 1]), box.crop(g[t]), p, LK)
        np.testing.assert_array_equal(np.isfinite(e_full), np.isfinite(e_crop))
        # the same flow up to float32 rounding of the coordinates
        assert np.abs(crop - full).max() < 5e-3
        assert np.abs(e_crop - e_full)[np.isfinite(e_full)].max() < 5e-3


def test_anchor_template_lies_inside_the_anchor_box(padded):
    """The anchor pass runs on crops: the warped annotated frame must not reach outside its box."""
    frames, truth = padded
    g = cv2.cvtColor(frames[0], cv2.COLOR_BGR2GRAY)
    ref = _Reference(g, truth[0], np.zeros_like(truth[0]), 21)
    est = truth[25]
    tmpl, c_t = ref.template(est, est, 21 * 2**_ANCHOR_LEVELS // 2 + 8)  # as track_lk calls it
    box = _Box(np.concatenate([c_t, est]), SIZE, 21, _ANCHOR_LEVELS)
    inside = np.zeros(tmpl.shape, dtype=bool)
    inside[box.y0:box.y1, box.x0:box.x1] = True
    assert inside.sum() < inside.size  # a real crop
    assert tmpl[~inside].max() == 0  # nothing is drawn outside it, so cropping loses nothing
    assert tmpl[inside].mean() > 20


def test_roi_tracking_matches_full_frame_tracking(padded):
    frames, truth = padded
    roi, c_roi = track_lk(frames, truth[0])
    full, c_full = track_lk(frames, truth[0], roi=False)
    d = np.linalg.norm(roi - full, axis=2)
    # Float32 rounding differs between crop and frame coordinates (~1e-3 px per
    # LK call); the tracker's per-point choices can amplify a few of these, as
    # they do for the same video shifted by a whole pixel. Most points agree tightly: median 0.001 px with
    # OpenCV 5.0, 0.016 with 4.8-4.12 and 0.020 with 4.13 (pyramidal LK's float32 arithmetic differs between
    # releases; the error against the truth is the same either way, asserted below).
    assert np.median(d) < 0.03, np.median(d)
    assert d.mean() < 0.05 and np.quantile(d, 0.95) < 0.2, (d.mean(), np.quantile(d, 0.95))
    assert np.abs(c_roi - c_full).mean() < 0.01
    err = lambda p: np.linalg.norm(p - truth, axis=2).mean()  # noqa: E731
    assert abs(err(roi) - err(full)) < 0.02, (err(roi), err(full))
