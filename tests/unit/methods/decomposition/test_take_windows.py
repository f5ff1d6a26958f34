"""Solvers across frames on a long take, window by window (temporal.take_windows): one window's memory, the
whole take's result to rounding."""

import numpy as np
import pytest

from retarget_cli.errors import ShapeError
from retarget_cli.methods.decomposition.temporal import (
    MARGIN,
    WINDOW,
    take_windows,
    temporal_events,
    temporal_windows,
)
from retarget_cli.stages._landmark_filter import FILTER_DEFAULTS
from retarget_cli.stages.track import filter_segments


@pytest.mark.parametrize("T", [1, 7, WINDOW + MARGIN, WINDOW + MARGIN + 1, 5000, 18000])
def test_take_windows_tile_the_take_and_bound_what_is_held(T):
    wins = take_windows(T)
    assert wins[0][0] == 0 and wins[-1][1] == T
    for (a, b, lo, hi), nxt in zip(wins, wins[1:] + [None]):
        assert lo <= a < b <= hi <= T
        assert hi - lo <= WINDOW + 2 * MARGIN
        if nxt is not None:
            assert nxt[0] == b and b - a == WINDOW
    assert (len(wins) == 1) == (T <= WINDOW + MARGIN)
    with pytest.raises(ShapeError, match="take windows"):
        take_windows(T + WINDOW + MARGIN, 0)


def _keys_take(T=900, seed=0):
    """A take of 6 keys' weights (slow sines, a 3-frame spike every 151 frames) seen through noise."""
    rng = np.random.default_rng(seed)
    B = rng.normal(size=(6, 40))
    t = np.arange(T)
    W = 0.5 + 0.4 * np.sin(t[:, None] / (7.0 + 3 * np.arange(6)) + np.arange(6))
    W[::151, 2] += 1.5
    S = W @ B + 0.05 * rng.normal(size=(T, 40))
    C = rng.uniform(0.5, 1.0, size=(T, 40))
    return S, B, C


def test_temporal_solver_in_windows_is_the_whole_take_to_rounding():
    S, B, C = _keys_take()
    kw = dict(lam=2.0, upper=None, shape_space=True, robust=3.0)
    whole = temporal_events(S, B, confidence=C, **kw)
    assert np.array_equal(temporal_windows(S, B, confidence=C, **kw), whole)  # short enough: one window
    win = temporal_windows(S, B, confidence=C, window=200, margin=100, **kw)
    assert np.abs(win - whole).max() < 1e-6
    # too short a margin shows: the test can tell the windows apart
    assert np.abs(temporal_windows(S, B, confidence=C, window=200, margin=2, **kw) - whole).max() > 1e-4


def test_landmark_filter_in_windows_is_the_whole_segment_to_rounding():
    rng = np.random.default_rng(0)
    T = 600
    t = np.arange(T)
    P = rng.normal(size=(68, 2))[None] * 30 + 200 + 5 * np.sin(t / 17.0)[:, None, None]
    P = P + rng.normal(size=(T, 68, 2)) * 0.7
    P[::97, 36:42, 1] += 6  # blinks: the robust filter lets go there
    C = rng.uniform(0.3, 1.0, (T, 68))
    kw = dict(fps=25.0, settings=dict(FILTER_DEFAULTS), where="take", anchors=[0])
    whole, raw, meta = filter_segments(P, C, None, window=None, **kw)
    win, raw_w, meta_w = filter_segments(P, C, None, window=150, margin=100, **kw)
    assert np.abs(win - whole).max() < 1e-6 and np.array_equal(raw_w, raw) and meta_w == meta
    assert np.abs(filter_segments(P, C, None, window=150, margin=2, **kw)[0] - whole).max() > 1e-4
    seg = np.zeros(T, np.int32)  # two segments around a gap, each filtered in windows
    seg[280:300], seg[300:] = -1, 1
    a = filter_segments(P, C, seg, window=None, **kw)[0]
    b = filter_segments(P, C, seg, window=100, margin=100, **kw)[0]
    assert np.abs(a - b).max() < 1e-6


def test_landmark_filter_in_place_is_byte_identical_to_the_copy():
    """``in_place``: each window's rows are written into the tracker's points once the next window has read its
    input (windows overlap), so the result is the copy's to the bit, and the raw points come back as float32."""
    rng = np.random.default_rng(1)
    T = 700
    P = rng.normal(size=(68, 2))[None] * 30 + 200 + np.cumsum(rng.normal(size=(T, 68, 2)) * 0.5, axis=0)
    C = rng.uniform(0.3, 1.0, (T, 68))
    kw = dict(fps=25.0, settings=dict(FILTER_DEFAULTS), where="take", anchors=[0, 333])
    seg = np.zeros(T, np.int32)
    seg[250:270], seg[270:] = -1, 1
    for segment in (None, seg):
        ref, raw, _ = filter_segments(P, C, segment, window=100, margin=60, **kw)
        mine = P.copy()
        out, raw32, _ = filter_segments(mine, C, segment, window=100, margin=60, in_place=True, **kw)
        assert out is mine and out.tobytes() == ref.tobytes()
        assert raw32.dtype == np.float32 and np.array_equal(raw32, P.astype(np.float32)) and raw.dtype == np.float64
        # without the delayed writes the next window would read filtered rows: the result would differ
        assert not np.array_equal(ref, P)
