"""auto_pose after a scene cut (issue 33): each shot is measured from its own rest shape."""

import numpy as np

from retarget_cli.io.landmarks import Landmarks
from retarget_cli.methods.neutral import find_rest_frame
from retarget_cli.stages.auto_pose import _cut_rows, _shot_neutrals

T = 40


def _take(gaps):
    rng = np.random.default_rng(0)
    base = rng.random((68, 2)) * 100
    pts = base + 0.2 * rng.standard_normal((T, 68, 2))
    pts[20:] += 5.0 * rng.standard_normal((68, 2))  # another actor after the cut
    lm = Landmarks(pts, np.ones((T, 68)), np.tile(np.eye(2, 3), (T, 1, 1)), pts, frames=np.arange(100, 100 + T),
                   meta={"gaps": gaps})
    return lm


def test_a_cut_between_two_faces_gives_the_second_shot_its_own_neutral():
    lm = _take([{"start": 120, "frames": 0, "reason": "cut", "cut": True}])
    assert _cut_rows(lm) == [20]
    ids = np.arange(68)
    neutral = (lm.stabilized[3].astype(np.float64), np.ones(68))
    parts = [list(range(0, 20)), list(range(20, T))]
    shots = _shot_neutrals(lm, parts, 3, neutral, ids, lm.stabilized, lm.confidence, None, 0.15, "refs")
    for shot, rows in zip(shots, (slice(0, 20), slice(20, T))):  # each shot its own rest shape
        want = find_rest_frame(lm.stabilized[rows], lm.confidence[rows])
        assert np.allclose(shot[0], want.shape) and shot[2] is None
    # a neutral frame given (or a calibration): the shot that holds it keeps it
    kept = _shot_neutrals(lm, parts, 3, neutral, ids, lm.stabilized, lm.confidence, None, 0.15, "refs",
                          keep_home=True)
    assert kept[0][0] is neutral[0] and kept[0][2] == "refs" and np.allclose(kept[1][0], shots[1][0])
    # the second actor's rest is far from the first's: measured from the first, rest would read as expression
    assert np.abs(shots[1][0] - shots[0][0]).mean() > 2.0


def test_no_face_to_face_cut_no_shots():
    ids = np.arange(68)
    for gaps in ([], [{"start": 120, "frames": 10, "reason": "no face", "cut": True}]):
        lm = _take(gaps)
        assert _cut_rows(lm) == []
        assert _shot_neutrals(lm, [list(range(T))], 3, (None, None), ids, lm.stabilized, lm.confidence, None,
                              0.15, None) is None
