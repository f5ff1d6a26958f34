"""bench/track.py's blink closure: the share of each true blink's drop of eye opening a track reproduces."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "bench"))

from track import blink_closures  # noqa: E402


def _eyes(gap_l, gap_r):
    """(T, 68, 2) points with eyes 10 px wide and the given lid gaps (px) per frame."""
    T = len(gap_l)
    P = np.zeros((T, 68, 2))
    for x0, gap, (a, b, up, lo) in ((0.0, gap_l, (36, 39, (37, 38), (41, 40))),
                                    (30.0, gap_r, (42, 45, (43, 44), (47, 46)))):
        P[:, a] = (x0, 0)
        P[:, b] = (x0 + 10, 0)
        for k, (u, v) in enumerate(zip(up, lo)):
            P[:, u] = np.stack([np.full(T, x0 + 3 + 4 * k), -np.asarray(gap) / 2], 1)
            P[:, v] = np.stack([np.full(T, x0 + 3 + 4 * k), np.asarray(gap) / 2], 1)
    return P


def test_blink_closures_per_eye_and_blink():
    open_ = np.full(60, 3.0)
    left = open_.copy()
    left[10:13] = [1.5, 0.2, 1.5]  # a blink of the left eye
    left[40:42] = [0.2, 0.2]  # and another
    truth = _eyes(left, open_)  # the right eye never closes
    np.testing.assert_allclose(blink_closures(truth, truth), [1.0, 1.0])
    half = _eyes(np.where(left < 3, 3 - (3 - left) / 2, 3), open_)
    np.testing.assert_allclose(blink_closures(half, truth), [0.5, 0.5])
    # a track that closes late by one frame still counts inside the margin; one that never closes gives 0
    np.testing.assert_allclose(blink_closures(_eyes(np.roll(left, 1), open_), truth), [1.0, 1.0])
    np.testing.assert_allclose(blink_closures(_eyes(open_, open_), truth), [0.0, 0.0])
    assert blink_closures(truth, _eyes(open_, open_)).shape == (0,)
