"""Landmark filters (retarget_cli.methods.tracking.filter): RTS smoother and One-Euro filter."""

import numpy as np
import pytest

from retarget_cli.methods.tracking.filter import filter_points, motion_model, one_euro, rts_smooth


def _dense_map(y, c, model, q, r, prior_var):
    """The same model's MAP estimate as one dense weighted least-squares problem over all states."""
    F, Q = motion_model(model, q)
    n = F.shape[0]
    T = len(y)
    Lq = np.linalg.cholesky(np.linalg.inv(Q))  # Q^-1 = Lq Lq^T
    rows, rhs = [], []
    # prior x_0 ~ N([y_first, 0...], prior_var I)
    first = int(np.argmax(c > 1e-3))
    m0 = np.zeros(n)
    m0[0] = y[first]
    A0 = np.zeros((n, T * n))
    A0[:, :n] = np.eye(n) / np.sqrt(prior_var)
    rows.append(A0)
    rhs.append(m0 / np.sqrt(prior_var))
    for t in range(T):
        if c[t] > 1e-3:
            a = np.zeros((1, T * n))
            a[0, t * n] = np.sqrt(c[t]) / r
            rows.append(a)
            rhs.append(np.array([np.sqrt(c[t]) * y[t] / r]))
    for t in range(T - 1):
        a = np.zeros((n, T * n))
        a[:, (t + 1) * n:(t + 2) * n] = Lq.T
        a[:, t * n:(t + 1) * n] = -Lq.T @ F
        rows.append(a)
        rhs.append(np.zeros(n))
    A, b = np.vstack(rows), np.concatenate(rhs)
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    return x.reshape(T, n)[:, 0]


@pytest.mark.parametrize("model", ["cv", "ca"])
def test_rts_equals_dense_least_squares(model):
    rng = np.random.default_rng(4)
    T, L = 40, 3
    t = np.arange(T)
    truth = np.stack([np.stack([10 * np.sin(t / 7 + k), 5 * np.cos(t / 5 + k)], -1) for k in range(L)], 1)
    y = truth + rng.normal(0, 0.7, truth.shape)
    conf = rng.uniform(0.2, 1.0, (T, L))
    conf[10:14, 1] = 0.0
    q, r, pv = 0.3, 0.7, 1e4
    out = rts_smooth(y, conf, model=model, process_noise=q, measurement_noise=r, prior_var=pv)
    for j in range(L):
        for k in range(2):
            ref = _dense_map(y[:, j, k], conf[:, j], model, q, r, pv)
            np.testing.assert_allclose(out[:, j, k], ref, atol=1e-8, rtol=0)
    # and it smooths: closer to the truth than the measurements
    assert np.mean((out - truth) ** 2) < 0.6 * np.mean((y - truth) ** 2)


@pytest.mark.parametrize("method", ["rts", "one-euro"])
def test_confidence_zero_is_filled_from_neighbours(method):
    T = 60
    t = np.arange(T, dtype=float)
    truth = np.stack([100 + 0.8 * t, 50 + 0.3 * t], -1)[:, None, :]  # steady drift, one point
    y = truth.copy()
    conf = np.ones((T, 1))
    y[25:35, 0] = [0.0, 0.0]   # a lost point reported at a wrong place ...
    conf[25:35, 0] = 0.0       # ... with confidence 0
    out = filter_points(y, conf, method=method)
    gap = slice(25, 35)
    # not left where it was, but following its neighbours' motion
    assert np.all(np.linalg.norm(out[gap, 0] - y[gap, 0], axis=1) > 50)
    err = np.linalg.norm(out[gap, 0] - truth[gap, 0], axis=1)
    assert err.max() < (0.5 if method == "rts" else 3.0)


def test_robust_rts_keeps_a_three_frame_blink():
    rng = np.random.default_rng(0)
    T = 120
    blink = np.zeros(T)
    blink[60:63] = [0.6, 1.0, 0.6]
    truth = np.zeros((T, 1, 2))
    truth[:, 0, 1] = 6.0 * blink + 0.02 * np.arange(T)
    y = truth + rng.normal(0, 0.3, truth.shape)
    plain = rts_smooth(y, model="ca", process_noise=0.05, measurement_noise=0.5)
    robust = rts_smooth(y, model="ca", process_noise=0.05, measurement_noise=0.5, robust=3.0)
    b = slice(60, 63)

    def amp(p):  # least-squares amplitude of the blink over its frames, against the truth's
        base = 0.5 * (p[55, 0, 1] + p[67, 0, 1]) + 0.02 * (np.arange(60, 63) - 61)
        return float((p[b, 0, 1] - base) @ blink[b] / (6.0 * blink[b] @ blink[b]))

    assert amp(plain) < 0.8          # plain smoothing flattens the blink ...
    assert amp(robust) >= 0.9        # ... the robust one keeps it
    quiet = slice(5, 50)             # and still smooths where nothing happens
    assert np.mean((robust[quiet] - truth[quiet]) ** 2) < 0.5 * np.mean((y[quiet] - truth[quiet]) ** 2)


def test_robust_rts_groups_release_the_small_points_of_an_event():
    """An eye: two upper-lid points move 6 px in a 3-frame blink, two lower-lid points 1.2 px."""
    rng = np.random.default_rng(3)
    T = 120
    blink = np.zeros(T)
    blink[60:63] = [0.6, 1.0, 0.6]
    move = np.array([6.0, 6.0, 1.2, 1.2])
    truth = np.zeros((T, 4, 2))
    truth[:, :, 1] = blink[:, None] * move + 0.02 * np.arange(T)[:, None]
    y = truth + rng.normal(0, 0.3, truth.shape)
    kw = dict(model="ca", process_noise=0.05, measurement_noise=0.5, robust=3.0)
    alone = rts_smooth(y, **kw)
    pooled = rts_smooth(y, **kw, groups=[[0, 1, 2, 3]])
    b = slice(60, 63)

    def amp(p, i):
        base = 0.5 * (p[55, i, 1] + p[67, i, 1]) + 0.02 * (np.arange(60, 63) - 61)
        return float((p[b, i, 1] - base) @ blink[b] / (move[i] * blink[b] @ blink[b]))

    assert min(amp(alone, 0), amp(alone, 1)) >= 0.9     # the upper lid is flagged on its own
    assert max(amp(alone, 2), amp(alone, 3)) < 0.8      # the lower lid is not: smoothed away
    assert min(amp(pooled, i) for i in range(4)) >= 0.9  # pooled over the eye, every point keeps the blink
    quiet = slice(5, 50)
    assert np.mean((pooled[quiet] - truth[quiet]) ** 2) < 0.5 * np.mean((y[quiet] - truth[quiet]) ** 2)
    with pytest.raises(ValueError, match="groups"):
        rts_smooth(y, **kw, groups=[[0, 4]])


def test_one_euro_is_causal_and_smooths():
    rng = np.random.default_rng(1)
    T = 200
    truth = np.zeros((T, 2, 2))
    truth[:, :, 0] = np.linspace(0, 20, T)[:, None]
    y = truth + rng.normal(0, 0.5, truth.shape)
    out = one_euro(y, fps=30, min_cutoff=1.0, beta=0.05)
    y2 = y.copy()
    y2[150:] += 100.0
    out2 = one_euro(y2, fps=30, min_cutoff=1.0, beta=0.05)
    np.testing.assert_array_equal(out[:150], out2[:150])  # the future does not change the past
    d2 = lambda p: np.mean(np.diff(p[20:], n=2, axis=0) ** 2)  # noqa: E731
    assert d2(out) < 0.2 * d2(y)


def test_filter_rejects_bad_shapes():
    from retarget_cli.errors import ShapeError

    with pytest.raises(ShapeError, match="points"):
        rts_smooth(np.zeros((5, 3)))
    with pytest.raises(ShapeError, match="confidence"):
        rts_smooth(np.zeros((5, 3, 2)), np.ones((5, 2)))
    with pytest.raises(ValueError, match="filter"):
        filter_points(np.zeros((5, 3, 2)), method="kalman")


def test_import_with_filter_keeps_points_raw(tmp_path):
    from retarget_cli.io.annotations import write_csv_landmarks
    from retarget_cli.io.landmarks import load_landmarks
    from retarget_cli.stages import run_import

    rng = np.random.default_rng(2)
    T = 40
    t = np.arange(T)[:, None]
    base = np.stack([100 + 40 * np.cos(np.linspace(0, 6, 68)), 100 + 40 * np.sin(np.linspace(0, 6, 68))], -1)
    P = base[None] + 0.2 * t[..., None] + rng.normal(0, 0.5, (T, 68, 2))
    write_csv_landmarks(tmp_path / "lm.csv", P)
    run_import(source=tmp_path / "lm.csv", output=tmp_path / "f.npz", filter="rts")
    lm = load_landmarks(tmp_path / "f.npz")
    np.testing.assert_allclose(lm.points_raw, P, atol=1e-3)
    assert np.abs(lm.points - lm.points_raw).max() > 0.1       # filtered ...
    d2 = lambda p: np.mean(np.diff(p, n=2, axis=0) ** 2)  # noqa: E731
    assert d2(lm.points) < 0.1 * d2(lm.points_raw)           # ... and smoother
    assert lm.meta["filter"]["method"] == "rts"
    run_import(source=tmp_path / "lm.csv", output=tmp_path / "n.npz", filter="none")  # as given
    assert load_landmarks(tmp_path / "n.npz").points_raw is None
    run_import(source=tmp_path / "lm.csv", output=tmp_path / "d.npz")  # import's default (issue 27): rts, as track
    np.testing.assert_allclose(load_landmarks(tmp_path / "d.npz").points, lm.points)
