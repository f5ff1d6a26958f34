"""``landmarks.npz``'s ``found`` and ``segment`` (issue 33): round trip, defaults, bad files as one-line errors."""

import numpy as np
import pytest

from retarget_cli.errors import InputError
from retarget_cli.io.atomic import load_npz, savez
from retarget_cli.io.landmarks import Landmarks, load_landmarks, save_landmarks


def _take(T=6, L=5):
    pts = np.random.default_rng(0).random((T, L, 2)).astype(np.float32) * 100
    return Landmarks(pts, np.ones((T, L)), np.tile(np.eye(2, 3), (T, 1, 1)), pts)


def test_found_and_segment_round_trip(tmp_path):
    lm = _take()
    lm.found = np.array([1, 1, 0, 0, 1, 1], bool)
    lm.segment = np.array([0, 0, -1, -1, 1, 1], np.int32)
    save_landmarks(tmp_path / "lm.npz", lm)
    back = load_landmarks(tmp_path / "lm.npz")
    assert back.found.tolist() == lm.found.tolist() and back.segment.tolist() == lm.segment.tolist()
    assert back.segments == [(0, 2), (4, 6)]


def test_without_found_every_frame_is_one_segment(tmp_path):
    save_landmarks(tmp_path / "lm.npz", _take())
    back = load_landmarks(tmp_path / "lm.npz")
    assert back.found is None and back.found_mask.all() and back.segments == [(0, 6)]
    # found alone: the segments are its runs
    back.found = np.array([0, 1, 1, 0, 1, 1], bool)
    assert back.segments == [(1, 3), (4, 6)]


@pytest.mark.parametrize("found, segment, message", [
    (np.array([1, 1, 0, 0, 1], bool), None, "'found' must be 6 booleans"),
    (np.array([1, 1, 2, 0, 1, 1]), None, "'found' must be 6 booleans"),
    (np.array([1, 1, 0, 0, 1, 1], bool), np.array([0, 0, 0, -1, 1, 1]), "frame 2: 'segment' 0 disagrees"),
    (None, np.array([0.5] * 6), "'segment' must be 6 integers"),
])
def test_bad_found_or_segment_is_one_line(tmp_path, found, segment, message):
    save_landmarks(tmp_path / "lm.npz", _take())
    data = dict(load_npz(tmp_path / "lm.npz"))
    if found is not None:
        data["found"] = found
    if segment is not None:
        data["segment"] = segment
    savez(tmp_path / "bad.npz", data)
    with pytest.raises(InputError, match=message) as err:
        load_landmarks(tmp_path / "bad.npz")
    assert "\n" not in str(err.value) and "bad.npz" in str(err.value)
