"""The face measures of bench/real_rig.py (bench/realrig/measures.py) on synthetic point sets."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "bench"))

from realrig.measures import (  # noqa: E402
    MEDIAPIPE,
    MULTIPIE68,
    brow_height,
    face_measures,
    frontal,
    opening,
    pearson,
)


def synthetic_face(layout, *, mouth=0.3, eye_l=0.25, eye_r=0.35, brow=0.4, n_points=None):
    """Points in *layout* with known openings: mouth width 60, eye widths 30, eye centres 70 apart.

    Unused points stay at the origin. Returns (n_points, 2), image-like (y down).
    """
    p = np.zeros((n_points or layout.n_points, 2))
    L = layout
    a, b = L.mouth_corners
    p[a], p[b] = (-30, 50), (30, 50)
    for u, lo in zip(L.lip_upper, L.lip_lower):
        p[u], p[lo] = (0, 50 - 30 * mouth), (0, 50 + 30 * mouth)   # gap = 60 * mouth
    for (up, low, ca, cb), cx, op in ((L.eye_l, -35, eye_l), (L.eye_r, 35, eye_r)):
        p[ca], p[cb] = (cx - 15, 0), (cx + 15, 0)
        for k, (u, lo) in enumerate(zip(up, low)):
            x = cx - 5 + 5 * k
            p[u], p[lo] = (x, -15 * op), (x, 15 * op)               # gap = 30 * opening
    iod = 100.0  # outer corners at -50 and +50
    for idx, cx in ((L.brow_l, -35), (L.brow_r, 35)):
        xs = np.linspace(cx - 12, cx + 12, len(idx))
        for i, x in zip(idx, xs):
            p[i] = (x, -brow * iod)
    return p


def rotate(p, angle, scale=1.0, shift=(0.0, 0.0)):
    c, s = np.cos(angle), np.sin(angle)
    return scale * p @ np.array([[c, -s], [s, c]]).T + np.asarray(shift)


@pytest.mark.parametrize("layout", [MULTIPIE68, MEDIAPIPE], ids=lambda x: x.name)
def test_known_openings(layout):
    p = synthetic_face(layout, mouth=0.3, eye_l=0.25, eye_r=0.35, brow=0.4)
    m = face_measures(p, layout)
    assert m["mouth"] == pytest.approx([0.3], abs=1e-12)
    assert m["eye_l"] == pytest.approx([0.25], abs=1e-12)
    assert m["eye_r"] == pytest.approx([0.35], abs=1e-12)
    assert m["brow"] == pytest.approx([0.4], abs=1e-12)


@pytest.mark.parametrize("layout", [MULTIPIE68, MEDIAPIPE], ids=lambda x: x.name)
def test_invariant_to_similarity(layout):
    p = synthetic_face(layout, mouth=0.1, eye_l=0.2, eye_r=0.05, brow=0.33)
    ref = face_measures(p, layout)
    moved = face_measures(rotate(p, 0.4, 2.5, (300, 200)), layout)
    for k in ref:
        assert moved[k] == pytest.approx(ref[k], abs=1e-12)


def test_crossed_lips_are_negative():
    p = synthetic_face(MULTIPIE68, mouth=-0.05)
    assert face_measures(p, MULTIPIE68)["mouth"][0] == pytest.approx(-0.05, abs=1e-12)


def test_frames_axis_and_eyes_kept_apart():
    frames = np.stack([synthetic_face(MULTIPIE68, eye_l=0.3 - 0.1 * t, eye_r=0.3) for t in range(3)])
    m = face_measures(frames, MULTIPIE68)
    assert m["eye_l"] == pytest.approx([0.3, 0.2, 0.1], abs=1e-12)
    assert m["eye_r"] == pytest.approx([0.3, 0.3, 0.3], abs=1e-12)


def test_opening_and_brow_functions_directly():
    p = np.array([[0, 0], [10, 0], [5, -2], [5, 3], [5, -20], [-10, 0], [20, 0]], dtype=float)
    assert opening(p, [2], [3], 0, 1)[0] == pytest.approx(0.5)
    assert brow_height(p, [4], 0, 1, 5, 6)[0] == pytest.approx(20 / 30)


def test_wrong_point_count_is_refused():
    with pytest.raises(ValueError, match="68 points"):
        face_measures(np.zeros((478, 2)), MULTIPIE68)


def test_frontal_flips_y_and_drops_z():
    assert frontal([[1.0, 2.0, 3.0]]).tolist() == [[1.0, -2.0]]


def test_pearson():
    a = np.arange(10.0)
    assert pearson(a, 3 * a + 1) == pytest.approx(1.0)
    assert pearson(a, -a) == pytest.approx(-1.0)
    b = a.copy()
    b[4] = np.nan
    assert pearson(a, b) == pytest.approx(1.0)
    assert np.isnan(pearson(a, np.ones(10)))
    mask = np.zeros(10, bool)
    mask[:2] = True
    assert np.isnan(pearson(a, a, mask))
