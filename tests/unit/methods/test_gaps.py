"""Gaps in a take (retarget_cli.methods.gaps): segments, gap descriptions, scene cuts, curves across a gap."""

import numpy as np
import pytest

from retarget_cli.errors import ShapeError
from retarget_cli.methods.gaps import (
    LOW_CONFIDENCE,
    NO_FACE,
    CutDetector,
    describe_gaps,
    fill_gaps,
    gap_summary,
    segment_ids,
    segments,
    segments_of,
)


def test_segments_split_at_gaps_and_cuts():
    found = np.array([0, 1, 1, 1, 0, 0, 1, 1, 1, 1], bool)
    cuts = np.zeros(10, bool)
    cuts[8] = True  # a cut between two found frames
    assert segments(found) == [(1, 4), (6, 10)]
    assert segments(found, cuts) == [(1, 4), (6, 8), (8, 10)]
    ids = segment_ids(found, cuts)
    assert ids.tolist() == [-1, 0, 0, 0, -1, -1, 1, 1, 2, 2]
    assert segments_of(ids) == [(1, 4), (6, 8), (8, 10)]
    assert segments(np.zeros(4, bool)) == []


def test_describe_gaps_says_where_how_long_and_why():
    found = np.array([1, 1, 0, 0, 0, 1, 1, 0, 0, 1, 1, 1], bool)
    status = np.where(found, 0, NO_FACE)
    status[7:9] = LOW_CONFIDENCE
    cuts = np.zeros(12, bool)
    cuts[2] = True   # cut to black
    cuts[10] = True  # cut between two faces
    gaps = describe_gaps(found, status, cuts, frames=np.arange(100, 112), fps=25.0)
    assert gaps == [
        {"start": 102, "frames": 3, "reason": "no face", "cut": True, "seconds": 0.12},
        {"start": 107, "frames": 2, "reason": "low confidence", "cut": False, "seconds": 0.08},
        {"start": 110, "frames": 0, "reason": "cut", "cut": True, "seconds": 0.0},
    ]
    assert gap_summary(gaps) == "3 gaps (cut 1, low confidence 1, no face 1), 5 frames"
    assert describe_gaps(np.ones(5, bool)) == [] and gap_summary([]) == "no gaps"
    # a gap at the end of the take
    assert describe_gaps(np.array([1, 1, 0, 0], bool)) == [{"start": 2, "frames": 2, "reason": "no face",
                                                            "cut": False}]


def test_fill_gaps_hold_ease_omit():
    T = 40
    V = np.tile(np.linspace(0.2, 0.9, T)[:, None], (1, 2))
    V[10:30] = 123.0  # whatever stands in the gap is replaced
    found = np.ones(T, bool)
    found[10:30] = False
    held = fill_gaps(V, found, behaviour="hold")
    assert np.all(held[10:30] == V[9]) and np.array_equal(held[found], V[found])
    assert np.array_equal(fill_gaps(V, found, behaviour="omit"), held)
    eased = fill_gaps(V, found, behaviour="ease", rest=[0.0, 0.0], ease_frames=5)
    assert np.array_equal(eased[found], V[found])
    assert np.all(eased[15:25] == 0.0)  # at rest between the eases
    down, up = eased[10:15, 0], eased[25:30, 0]
    assert np.all(np.diff(down) < 0) and np.all(np.diff(up) > 0)  # monotone to rest and back
    assert 0 < down[0] < V[9, 0] and V[30, 0] > up[-1] > 0  # no jump at either end
    # a gap shorter than two eases eases half-way each side; an end gap eases on its one side only
    short = fill_gaps(V, found, behaviour="ease", ease_frames=50)
    assert np.all(np.diff(short[9:20, 0]) < 0) and np.all(np.diff(short[19:31, 0]) > 0)
    tail = np.ones(T, bool)
    tail[35:] = False
    end = fill_gaps(V, tail, behaviour="ease", ease_frames=3)
    assert np.all(end[38:] == 0) and 0 < end[35, 0] < V[34, 0]
    head = fill_gaps(V, ~np.r_[np.ones(4, bool), np.zeros(T - 4, bool)], behaviour="hold")
    assert np.all(head[:4] == V[4])
    assert np.all(fill_gaps(V, np.zeros(T, bool), rest=[1.0, 2.0]) == [1.0, 2.0])


def test_fill_gaps_checks_its_inputs():
    with pytest.raises(ShapeError, match="behaviour"):
        fill_gaps(np.zeros((3, 2)), np.ones(3, bool), behaviour="jump")
    with pytest.raises(ShapeError, match="found"):
        fill_gaps(np.zeros((3, 2)), np.ones(4, bool))
    with pytest.raises(ShapeError, match="rest"):
        fill_gaps(np.zeros((3, 2)), np.ones(3, bool), rest=[0.0])


def test_cut_detector_sees_a_cut_not_motion():
    rng = np.random.default_rng(0)
    a = (rng.random((120, 160)) * 60 + 80).astype(np.uint8)
    a[30:90, 50:110] = 220  # a bright "face"
    moved = np.roll(a, 6, axis=1)  # the face moves a little
    other = (rng.random((120, 160)) * 60 + 10).astype(np.uint8)  # another shot, darker
    cut = CutDetector()
    assert cut(a) is False  # the first frame
    assert cut(moved) is False and cut.last[0] < 0.12
    assert cut(other) is True
    assert cut(other) is False
    assert cut(np.dstack([a, a, a])) is True  # colour frames too


def test_cut_histogram_counts_every_fourth_pixel_in_bins_of_sixteen_gray_levels():
    """CutDetector.features' histogram is numpy's bincount of gray >> 4 over every 4th pixel (OpenCV counts it),
    for every gray level and odd frame sizes."""
    rng = np.random.default_rng(0)
    for h, w in ((64, 64), (135, 241), (480, 512)):
        g = rng.integers(0, 256, (h, w), dtype=np.uint8)
        n = g[::4, ::4].size
        g[::4, ::4] = (np.arange(n) % 256).astype(np.uint8).reshape(g[::4, ::4].shape)  # every level, where sampled
        _, hist = CutDetector.features(g)
        ref = np.bincount((g[::4, ::4] >> 4).ravel(), minlength=16).astype(np.float64)
        assert np.array_equal(hist, ref / ref.sum())
