import numpy as np
import pytest

from retarget_cli.methods.selection import pca_extremes, select_keys


def take_from_poses(n_frames=200, seed=0):
    """A take that blends 6 known extreme poses with smooth weights below 1."""
    rng = np.random.default_rng(seed)
    neutral = rng.normal(size=40)
    poses = rng.normal(size=(6, 40)) * np.array([8, 7, 6, 5, 4, 3])[:, None]
    w = rng.uniform(0, 0.5, size=(n_frames, 6)) ** 2
    extreme_frames = np.arange(6) * 30 + 7
    w[extreme_frames] = np.eye(6)
    return neutral + w @ poses, extreme_frames


def test_returns_k_distinct_valid_frames():
    X, _ = take_from_poses()
    for k in (1, 2, 5, 12, 31):
        f = select_keys(X, k)
        assert len(f) == k == len(set(f.tolist()))
        assert f.min() >= 0 and f.max() < len(X)


def test_recovers_the_extreme_poses():
    X, extremes = take_from_poses()
    got = set(pca_extremes(X, 12).tolist())
    assert set(extremes.tolist()) <= got


def test_invariant_to_translating_the_landmarks():
    X, _ = take_from_poses()
    shifted = X + np.tile([13.0, -7.0], 20)
    np.testing.assert_array_equal(select_keys(X, 8), select_keys(shifted, 8))


def test_static_take_and_too_many_keys_are_clear_errors():
    with pytest.raises(ValueError, match="same shape"):
        select_keys(np.ones((50, 10)), 2)
    X = np.repeat(np.eye(3, 10), 5, axis=0)
    with pytest.raises(ValueError, match="only 3 distinct frames"):
        select_keys(X, 4)
