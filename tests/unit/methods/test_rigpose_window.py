"""A long take posed in windows (rigpose.smoothing_windows): the memory of one window, the result of the whole take."""

import numpy as np
import pytest

from retarget_cli.errors import ShapeError
from retarget_cli.methods.rig import BlendshapeRig
from retarget_cli.methods.rigpose import _BATCH, SMOOTH_MARGIN, SMOOTH_WINDOW, delta_pose, smoothing_windows
from retarget_cli.synth.take import source_neutral


def _take(T=600, seed=3):
    """A two-slider rig (a lid, a brow) and a noisy take of it: a slow brow and a three-frame blink every 97."""
    n = source_neutral()
    V = np.column_stack([n[:, 0], -n[:, 1], np.zeros(68)])
    D = np.zeros((2, 68, 3))
    for up, lo in ((37, 41), (38, 40)):
        D[0, up, 1] = V[lo, 1] - V[up, 1]
    D[1, [17, 18, 19, 20, 21], 1] = 0.05
    rig = BlendshapeRig(V, D, ["eyeBlink_R", "browOuterUp_R"])
    truth = np.zeros((T, 2))
    truth[:, 1] = 0.4 + 0.3 * np.sin(np.arange(T) / 9.0)
    for b in range(30, T - 3, 97):
        truth[b:b + 3, 0] = [0.6, 1.0, 0.6]
    X = np.stack([rig.evaluate(c) for c in truth])
    rng = np.random.default_rng(seed)
    Y = 140.0 * np.stack([X[:, :, 0], -X[:, :, 1]], axis=2) + [150.0, 160.0] + 0.4 * rng.standard_normal((T, 68, 2))
    Y0 = 140.0 * np.column_stack([V[:, 0], -V[:, 1]]) + [150.0, 160.0]
    kw = dict(regions={"brows-eye": list(range(17, 22)) + list(range(36, 42))}, sparsity=0.0, ridge=1e-6,
              contact_weight=0.0)
    return rig, Y0, Y, kw


@pytest.mark.parametrize("K", [1, 5, 575, 576, 577, 2304, 3000, 15000])
def test_smoothing_windows_tile_the_take_and_bound_what_is_held(K):
    wins = smoothing_windows(K)
    assert wins[0][0] == 0 and wins[-1][1] == K
    for (a, b, lo, hi), nxt in zip(wins, wins[1:] + [None]):
        assert lo <= a < b <= hi <= K
        assert a - lo <= SMOOTH_MARGIN and hi - b <= SMOOTH_MARGIN
        assert hi - lo <= SMOOTH_WINDOW + 2 * SMOOTH_MARGIN  # the memory of one window, whatever K
        if nxt is not None:
            assert nxt[0] == b
    if K <= SMOOTH_WINDOW + SMOOTH_MARGIN:
        assert wins == [(0, K, 0, K)]
    assert smoothing_windows(K, None) == [(0, K, 0, K)]


def test_smoothing_windows_refuse_an_empty_window():
    with pytest.raises(ShapeError, match="take windows"):
        smoothing_windows(100, 0, 10)


def test_a_take_posed_in_windows_is_the_take_posed_at_once():
    rig, Y0, Y, kw = _take()
    v = np.arange(68)
    for smooth in (0.0, 1.0):
        whole = delta_pose(rig, v, Y0, Y, smooth=smooth, smooth_window=None, **kw)
        # windows aligned to the batches: each frame's own fit is bit for bit the same; a margin of a whole batch
        # leaves nothing of the smoothing's coupling
        same = delta_pose(rig, v, Y0, Y, smooth=smooth, smooth_window=_BATCH, smooth_margin=_BATCH, **kw)
        assert np.array_equal(same["w"], whole["w"]) and np.array_equal(same["rms"], whole["rms"])
    # small windows, not aligned to the batches, and the defaults (600 frames: two windows): within rounding of
    # the whole take's smoothing
    small = delta_pose(rig, v, Y0, Y, smooth=1.0, smooth_window=64, smooth_margin=32, **kw)
    assert np.abs(small["w"] - whole["w"]).max() < 1e-9
    assert len(smoothing_windows(len(Y))) == 2
    default = delta_pose(rig, v, Y0, Y, smooth=1.0, **kw)
    assert np.abs(default["w"] - whole["w"]).max() < 1e-9
    # a margin too short to let the coupling die out shows: the test can tell windows apart
    short = delta_pose(rig, v, Y0, Y, smooth=1.0, smooth_window=40, smooth_margin=2, **kw)
    assert np.abs(short["w"] - whole["w"]).max() > 1e-6
