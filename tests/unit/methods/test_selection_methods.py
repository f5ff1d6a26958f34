"""Every selection method: distinct valid frames, determinism, rigid invariance, errors (issue 4)."""

import numpy as np
import pytest

from retarget_cli.methods.decomposition import reconstruction_error
from retarget_cli.methods.selection import (
    METHODS,
    _centre,
    _check,
    _Greedy,
    _nnls_gram,
    convex_hull_keys,
    curve_winner,
    evaluation_curve,
    greedy,
    pca_extremes,
    select_keys,
)


def landmark_take(n_frames=90, seed=0, noise=0.2):
    """(T, 2L) flattened 2D landmarks: 20 points around (150, 120) px, 5 expressions plus noise."""
    rng = np.random.default_rng(seed)
    neutral = rng.normal(size=(20, 2)) * 30 + (150, 120)
    deltas = rng.normal(size=(5, 20, 2)) * 4
    w = rng.uniform(0, 1, size=(n_frames, 5)) ** 3
    w[0] = 0
    pts = neutral + np.einsum("te,eld->tld", w, deltas) + rng.normal(scale=noise, size=(n_frames, 20, 2))
    return pts.reshape(n_frames, -1)


def rigid(X, angle_deg, shift):
    a = np.deg2rad(angle_deg)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    P = X.reshape(len(X), -1, 2) @ R.T + shift
    return P.reshape(len(X), -1)


@pytest.mark.parametrize("method", [m for m in METHODS if m != "convex-hull"])
@pytest.mark.parametrize("include", [(), (0,)])
def test_k_distinct_valid_frames(method, include):
    X = landmark_take()
    for k in (2, 5, 9):
        f = select_keys(X, k, method=method, include=include)
        assert len(f) == k == len(set(f.tolist()))
        assert f.min() >= 0 and f.max() < len(X)
        assert set(include) <= set(f.tolist())


def test_convex_hull_size_is_the_data_s_and_k_is_ignored_with_a_warning(caplog):
    X = landmark_take()
    hull = convex_hull_keys(X, include=(0,))
    assert hull[0] == 0 and len(set(hull.tolist())) == len(hull) >= 3
    with caplog.at_level("WARNING"):
        got = select_keys(X, 50, method="convex-hull", include=(0,))
    np.testing.assert_array_equal(got, np.sort(hull))
    assert "is ignored" in caplog.text


@pytest.mark.parametrize("method", METHODS)
def test_deterministic_for_a_seed(method):
    X = landmark_take()
    a = select_keys(X, 7, method=method, include=(0,), seed=3)
    b = select_keys(X.copy(), 7, method=method, include=(0,), seed=3)
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("method", METHODS)
def test_invariant_to_translating_and_rotating_the_landmarks(method):
    # PCA-based methods: PCA scores with a sign fixed by the scores are rigid-invariant.
    # greedy / greedy-swap: E is measured on landmarks centred on the take's mean point.
    X = landmark_take()
    ref = select_keys(X, 8, method=method, include=(0,), seed=1)
    for angle, shift in ((0, (37.0, -12.0)), (25, (0.0, 0.0)), (-140, (500.0, 80.0))):
        got = select_keys(rigid(X, angle, shift), 8, method=method, include=(0,), seed=1)
        np.testing.assert_array_equal(ref, got, err_msg=f"{method}: rotation {angle}, shift {shift}")


def test_pca_extremes_recovers_known_extreme_poses_in_a_landmark_take():
    rng = np.random.default_rng(4)
    neutral = rng.normal(size=(20, 2)) * 30 + 100
    deltas = rng.normal(size=(4, 20, 2)) * np.array([9, 7, 5, 3])[:, None, None]
    w = rng.uniform(-0.4, 0.4, size=(160, 4)) * rng.uniform(0, 1, size=(160, 1))
    extremes = {11: (0, 1), 40: (0, -1), 77: (1, 1), 120: (1, -1), 150: (2, 1), 33: (2, -1)}
    for f, (e, s) in extremes.items():
        w[f] = 0
        w[f, e] = s
    X = (neutral + np.einsum("te,eld->tld", w, deltas)).reshape(160, -1)
    assert set(extremes) == set(pca_extremes(X, 6).tolist())


def test_greedy_error_decreases_with_k_and_beats_pca_extremes():
    X = landmark_take(120, seed=2)
    order = greedy(X, 12, include=(0,))
    E = [reconstruction_error(X, X[order[:k]]) for k in range(2, 13)]
    assert all(b <= a + 1e-9 for a, b in zip(E, E[1:]))
    assert E[-1] < E[0] / 4
    for k in (4, 8, 12):
        p = pca_extremes(X, k, include=(0,))
        assert reconstruction_error(X, X[order[:k]]) < reconstruction_error(X, X[p])


def test_greedy_swap_never_worse_than_greedy():
    X = landmark_take(100, seed=5)
    Xc = _centre(X, 2)
    for k in (4, 7):
        g = greedy(X, k, include=(0,))
        s = greedy(X, k, include=(0,), swap=True)
        assert reconstruction_error(Xc, Xc[s]) <= reconstruction_error(Xc, Xc[g]) + 1e-9


def test_exhaustive_greedy_adds_the_frame_that_most_reduces_e():
    # screen=None scores every frame exactly: check each step against brute force with decompose.
    X = landmark_take(40, seed=7)
    Xc = _centre(X, 2)
    order = greedy(X, 5, include=(0,), screen=None)
    for k in range(1, 5):
        errs = [reconstruction_error(Xc, Xc[list(order[:k]) + [c]]) if c not in order[:k] else np.inf
                for c in range(len(X))]
        assert order[k] == int(np.argmin(errs))


def test_screened_greedy_agrees_with_exhaustive_in_the_first_steps():
    X = landmark_take(60, seed=7)
    np.testing.assert_array_equal(greedy(X, 6, include=(0,))[:5], greedy(X, 6, include=(0,), screen=None)[:5])


def test_internal_nnls_is_exact_against_decompose():
    X = _centre(landmark_take(80, seed=1), 2)
    _, _, uid = _check(X, 2, ())
    g = _Greedy(X, uid)
    keys = [0, 5, 17, 33, 60, 71]
    g.set_keys(keys)
    np.testing.assert_allclose(g.err.sum(), reconstruction_error(X, X[keys]), rtol=1e-9)
    # Warm-started addition of one key (the path greedy uses) gives the same E as a cold solve.
    E, upd = g.try_add(44, X @ X[44])
    np.testing.assert_allclose(E, reconstruction_error(X, X[keys + [44]]), rtol=1e-9)


def test_nnls_gram_satisfies_kkt():
    rng = np.random.default_rng(0)
    B = rng.normal(size=(6, 15))
    Q = rng.normal(size=(40, 15))
    w, ok = _nnls_gram(B @ B.T, Q @ B.T, np.zeros((40, 6)))
    assert ok.all() and (w >= 0).all()
    grad = (Q - w @ B) @ B.T
    assert np.all(grad <= 1e-9) and np.allclose(grad[w > 0], 0, atol=1e-9)


@pytest.mark.parametrize("method", METHODS)
def test_static_take_and_too_many_keys_are_clear_errors(method):
    with pytest.raises(ValueError, match="same shape"):
        select_keys(np.ones((50, 10)), 2, method=method)
    X = np.repeat(np.eye(3, 10) * 5 + 1, 5, axis=0)
    if method != "convex-hull":
        with pytest.raises(ValueError, match="only 3 distinct frames"):
            select_keys(X, 4, method=method)


def test_evaluation_curve_and_winner():
    X = landmark_take(70, seed=3)
    rows = evaluation_curve(X, 8, k=5, include=(0,))
    curves = {r["curve"] for r in rows}
    assert curves == {"pca-extremes", "kmeans-2pc", "kmeans-3pc", "convex-hull", "greedy", "greedy-swap"}
    g = [r for r in rows if r["curve"] == "greedy"]
    assert [r["k"] for r in g] == list(range(2, 9))
    assert len([r for r in rows if r["curve"] == "greedy-swap"]) == 1
    for r in rows:
        np.testing.assert_allclose(r["error"], reconstruction_error(X, X[r["frames"]]))
    win = curve_winner(rows, 5)
    assert win["error"] == min(win["errors"].values()) and win["winner"] in ("greedy", "greedy-swap")


@pytest.mark.parametrize("seed", [0, 1])
def test_batched_trials_choose_the_keys_of_the_one_by_one_reference(seed, monkeypatch):
    # try_many (every screened candidate's trial NNLS in one compiled call) against try_add, one
    # candidate at a time: the same keys, in the same order, for several k, include sets and screens.
    X = landmark_take(150, seed=seed, noise=0.5)
    cases = [(3, (), 16), (8, (0,), 16), (12, (0, 77), 16), (6, (5,), None), (5, (0,), 4)]
    for k, include, screen in cases:
        monkeypatch.setattr(_Greedy, "BATCHED", False)
        ref = greedy(X, k, include=include, screen=screen)
        ref_swap = greedy(X, k, include=include, screen=screen, swap=True)
        monkeypatch.setattr(_Greedy, "BATCHED", True)
        got = greedy(X, k, include=include, screen=screen)
        np.testing.assert_array_equal(got, ref, err_msg=f"k={k}, include={include}, screen={screen}")
        np.testing.assert_array_equal(greedy(X, k, include=include, screen=screen, swap=True), ref_swap)


def test_batched_trials_give_the_reference_error_and_weights():
    X = _centre(landmark_take(80, seed=4), 2)
    _, _, uid = _check(X, 2, ())
    g = _Greedy(X, uid)
    keys = [0, 9, 23, 41]
    g.set_keys(keys)
    sel = np.array([3, 44, 60, 9 + 1])
    XC = X @ X[sel].T
    for (E, upd), c, j in zip(g.try_many(sel, XC), sel, range(len(sel))):
        E_ref, upd_ref = g.try_add(int(c), XC[:, j])
        np.testing.assert_allclose(E, E_ref, rtol=1e-10)
        np.testing.assert_allclose(E, reconstruction_error(X, X[keys + [int(c)]]), rtol=1e-9)
        np.testing.assert_array_equal(upd[0], upd_ref[0])  # the same frames re-solved
        np.testing.assert_allclose(upd[1], upd_ref[1], atol=1e-9)


def test_nnls_gram_pairs_kernel_satisfies_kkt_and_flags_what_it_cannot_solve():
    from retarget_cli.methods.decomposition._qp_kernel import nnls_gram_pairs

    rng = np.random.default_rng(2)
    Bs = [rng.normal(size=(5, 12)), rng.normal(size=(5, 12))]
    Q = rng.normal(size=(30, 12))
    which = np.repeat([0, 1], 15)
    G = np.stack([B @ B.T for B in Bs])
    b = np.stack([Bs[s] @ q for s, q in zip(which, Q)])
    W = np.zeros((30, 5))
    ok = np.empty(30, bool)
    nnls_gram_pairs(G, which, b, W, 1e-11 * np.einsum("nkk->nk", G).max(1), 25, ok)
    assert ok.all() and (W >= 0).all()
    for s, q, w in zip(which, Q, W):
        grad = Bs[s] @ (q - w @ Bs[s])
        assert np.all(grad <= 1e-9) and np.allclose(grad[w > 0], 0, atol=1e-9)
        w_ref, _ = _nnls_gram(G[s], (Bs[s] @ q)[None], np.zeros((1, 5)))
        np.testing.assert_allclose(w, w_ref[0], atol=1e-10)


def test_batched_trials_finish_what_the_kernel_leaves_with_the_numpy_iteration(monkeypatch):
    from retarget_cli.methods.decomposition import _qp_kernel

    kernel = _qp_kernel.nnls_gram_pairs
    left = []

    def leaves_every_other(G, which, B, W, tol, max_iter, ok):
        kernel(G, which, B, W, tol, max_iter, ok)
        ok[::2] = False
        W[::2] = -1.0  # garbage where not ok: the caller must not use it
        left.append(len(ok[::2]))

    X = _centre(landmark_take(80, seed=6), 2)
    _, _, uid = _check(X, 2, ())
    g = _Greedy(X, uid)
    g.set_keys([0, 12, 30])
    sel = np.array([5, 50, 66])
    XC = X @ X[sel].T
    ref = [g.try_add(int(c), XC[:, j]) for j, c in enumerate(sel)]
    monkeypatch.setattr(_qp_kernel, "nnls_gram_pairs", leaves_every_other)
    got = g.try_many(sel, XC)
    assert left and left[0] > 0
    for (E, upd), (E_ref, upd_ref) in zip(got, ref):
        np.testing.assert_allclose(E, E_ref, rtol=1e-12)
        assert (upd[1] >= 0).all()
        np.testing.assert_allclose(upd[1], upd_ref[1], atol=1e-9)
