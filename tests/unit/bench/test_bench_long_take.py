"""bench/long_take.py's tiled take: the clip's rows back and forth, and with --jitter every frame distinct."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "bench"))

import long_take  # noqa: E402

from retarget_cli.io.landmarks import Landmarks, load_landmarks, save_landmarks  # noqa: E402


def _clip(tmp_path, n=7):
    rng = np.random.default_rng(0)
    P = rng.normal(200, 30, (n, 68, 2)).astype(np.float32)
    lm = Landmarks(points=P, confidence=np.ones((n, 68), np.float32), head=np.tile(np.eye(2, 3, dtype=np.float32), (n, 1, 1)),
                   stabilized=P.copy(), fps=30.0)
    path = tmp_path / "clip.npz"
    save_landmarks(path, lm)
    return path, P


def test_a_tiled_take_goes_back_and_forth_through_the_clip(tmp_path):
    src, P = _clip(tmp_path)
    long_take.tiled_landmarks(src, 20, tmp_path / "t.npz")
    lm = load_landmarks(tmp_path / "t.npz")
    idx = [0, 1, 2, 3, 4, 5, 6, 5, 4, 3, 2, 1, 0, 1, 2, 3, 4, 5, 6, 5]
    assert np.array_equal(lm.points, P[idx]) and np.array_equal(lm.frames, np.arange(20))


def test_jitter_makes_every_frame_distinct_and_stays_small(tmp_path):
    src, P = _clip(tmp_path)
    long_take.tiled_landmarks(src, 20, tmp_path / "j.npz", jitter=0.05)
    lm = load_landmarks(tmp_path / "j.npz")
    base = P[[0, 1, 2, 3, 4, 5, 6, 5, 4, 3, 2, 1, 0, 1, 2, 3, 4, 5, 6, 5]]
    assert len(np.unique(lm.stabilized.reshape(20, -1).round(6), axis=0)) == 20
    assert 0 < np.abs(lm.stabilized - base).max() < 0.5 and 0 < np.abs(lm.points - base).max() < 0.5
