"""Inverse rig with quadratic correctives (Racković et al. 2023): model, MM surrogate, solvers."""

import numpy as np
import pytest

from retarget_cli.errors import InputError, ShapeError
from retarget_cli.methods.inverse_rig import (
    SOLVERS,
    QuadraticRig,
    mm_coefficients,
    mm_frame,
    mm_surrogate,
    quartic_argmin,
    solve,
)


def random_rig(seed=0, n=40, m=6, pairs=((0, 1), (2, 1), (3, 4), (0, 5)), corr_scale=0.8, local=True):
    """Small rig: shapes and correctives with partly overlapping vertex supports."""
    rng = np.random.default_rng(seed)
    neutral = rng.normal(size=(n, 3))
    deltas = rng.normal(size=(m, n, 3))
    if local:
        for k in range(m):
            deltas[k, rng.choice(n, n // 3, replace=False)] = 0.0
    corr = corr_scale * rng.normal(size=(len(pairs), n, 3))
    if local:
        for k in range(len(pairs)):
            corr[k, rng.choice(n, n // 2, replace=False)] = 0.0
    return QuadraticRig(neutral, deltas, list(pairs), corr, names=[f"s{k}" for k in range(m)]), deltas, corr


# ----------------------------------------------------------------------------- model (eq. 4)


def test_forward_evaluation_matches_direct_sum():
    rig, deltas, corr = random_rig(1)
    rng = np.random.default_rng(2)
    W = rng.uniform(size=(5, rig.n_shapes))
    pairs = rig.pairs.tolist()
    for t, w in enumerate(W):
        direct = rig.b0.reshape(-1, 3) + sum(w[k] * deltas[k] for k in range(rig.n_shapes))
        direct = direct + sum(w[i] * w[j] * corr[p] for p, (i, j) in enumerate(pairs))
        np.testing.assert_allclose(rig.evaluate(w), direct, atol=1e-12)
        np.testing.assert_allclose(rig.evaluate(W)[t], direct, atol=1e-12)


def test_D_matrices_and_their_spectra():
    rig, _, corr = random_rig(3)
    for i in range(0, 3 * rig.n_vertices, 7):
        D = rig.D(i).toarray()
        dense = np.zeros((rig.n_shapes, rig.n_shapes))
        for p, (j, k) in enumerate(rig.pairs.tolist()):
            dense[j, k] = dense[k, j] = 0.5 * corr[p].reshape(-1)[i]  # Algorithm 2
        np.testing.assert_allclose(D, dense)
        ev = np.linalg.eigvalsh(dense)
        assert rig.lam_min[i] == pytest.approx(ev[0], abs=1e-12)
        assert rig.lam_max[i] == pytest.approx(ev[-1], abs=1e-12)
        assert rig.sigma[i] == pytest.approx(np.linalg.norm(dense, 2), abs=1e-12)


def test_jacobian_matches_finite_differences_and_its_norm():
    rig, _, _ = random_rig(4)
    w = np.random.default_rng(5).uniform(size=rig.n_shapes)
    J = rig.jacobian(w)
    eps = 1e-6
    for j in range(rig.n_shapes):
        e = np.zeros(rig.n_shapes)
        e[j] = eps
        fd = (rig.evaluate_flat(w + e) - rig.evaluate_flat(w - e)) / (2 * eps)
        np.testing.assert_allclose(J[:, j], fd, atol=1e-7)
    assert rig.jacobian_fro2(w) == pytest.approx(np.sum(J**2), rel=1e-12)


# ----------------------------------------------------------------------------- MM surrogate


@pytest.mark.parametrize("seed", range(6))
def test_surrogate_upper_bounds_objective_and_touches_at_zero(seed):
    """Conditions 1 and 2 (eq. 10, 11) at random feasible points, including corners of the box."""
    rig, _, _ = random_rig(seed, corr_scale=[0.3, 1.0, 3.0][seed % 3])
    rng = np.random.default_rng(100 + seed)
    target = rig.evaluate(rng.uniform(size=rig.n_shapes)) + 0.3 * rng.normal(size=(rig.n_vertices, 3))
    alpha = [0.0, 0.5, 5.0][seed % 3]
    for _ in range(25):
        w = rng.uniform(size=rig.n_shapes)
        w[rng.uniform(size=w.size) < 0.3] = 0.0
        assert mm_surrogate(rig, w, np.zeros_like(w), target, alpha) == pytest.approx(
            rig.objective(w, target, alpha), rel=1e-12)  # Condition 2
        for new in (rng.uniform(size=w.size), rng.integers(0, 2, size=w.size).astype(float),
                    np.clip(w + 0.01 * rng.normal(size=w.size), 0, 1)):
            v = new - w
            psi = mm_surrogate(rig, w, v, target, alpha)
            obj = rig.objective(new, target, alpha)
            assert psi >= obj - 1e-9 * max(1.0, abs(obj))  # Condition 1


def test_quartic_coefficients_reproduce_the_surrogate():
    """q, r, s of eq. 18 (computed from Gram matrices) give ψ(v) − ψ(0) of eq. 15–16 exactly."""
    rig, _, _ = random_rig(7)
    rng = np.random.default_rng(8)
    target = rig.evaluate(rng.uniform(size=rig.n_shapes)) + 0.2 * rng.normal(size=(rig.n_vertices, 3))
    for _ in range(5):
        w = rng.uniform(size=rig.n_shapes)
        v = rng.uniform(size=rig.n_shapes) - w
        q, r, s, obj = mm_coefficients(rig, w, target.reshape(-1) - rig.b0, 0.7)
        d = mm_surrogate(rig, w, v, target, 0.7) - mm_surrogate(rig, w, 0 * v, target, 0.7)
        assert np.sum(q * v + r * v**2 + s * v**4) == pytest.approx(d, rel=1e-9)
        assert obj == pytest.approx(rig.objective(w, target, 0.7), rel=1e-10)
        assert r >= 0 and s >= 0


@pytest.mark.parametrize("alpha", [0.0, 0.3])
def test_mm_objective_never_increases(alpha):
    rig, _, _ = random_rig(9, corr_scale=2.0)
    rng = np.random.default_rng(10)
    for _ in range(3):
        target = rig.evaluate(rng.uniform(size=rig.n_shapes)) + 0.1 * rng.normal(size=(rig.n_vertices, 3))
        hist: list = []
        w, it = mm_frame(rig, target.reshape(-1) - rig.b0, rng.uniform(size=rig.n_shapes), alpha=alpha,
                         tol=1e-15, max_iter=400, history=hist)
        h = np.array(hist)
        assert len(h) == it + 1 and it > 10
        assert np.all(np.diff(h) <= 1e-12 * h[0])  # eq. 13
        assert h[-1] < 0.9 * h[0]
        assert np.all((w >= 0) & (w <= 1))


def test_mm_stops_at_tolerance_or_max_iter():
    rig, _, _ = random_rig(11)
    target = rig.evaluate(np.full(rig.n_shapes, 0.4))
    b = target.reshape(-1) - rig.b0
    _, it_cap = mm_frame(rig, b, np.zeros(rig.n_shapes), alpha=0.0, tol=1e-300, max_iter=7)
    assert it_cap == 7
    _, it_tol = mm_frame(rig, b, np.zeros(rig.n_shapes), alpha=0.0, tol=1e-3, max_iter=100000)
    assert 1 < it_tol < 100000


# ----------------------------------------------------------------------------- quartic step (eq. 17)


def _grid_min(q, r, s, lo, hi, n=20001):
    x = np.linspace(lo, hi, n)
    f = q * x + r * x**2 + s * x**4
    k = int(np.argmin(f))
    return x[k], f[k], (hi - lo) / (n - 1)


def test_quartic_step_matches_dense_grid_search():
    rng = np.random.default_rng(12)
    cases = []
    for _ in range(300):
        lo = -rng.uniform(0, 1)
        hi = lo + 1.0
        q = rng.normal() * 10 ** rng.uniform(-2, 3)
        s = rng.choice([0.0, rng.uniform(0, 1) * 10 ** rng.uniform(-2, 4)])
        r = rng.choice([rng.uniform(0, 1) * 10 ** rng.uniform(-2, 4), -rng.uniform(0, 50), 0.0])
        cases.append((q, r, s, lo, hi))
    cases += [(0.0, 1.0, 1.0, -0.5, 0.5), (3.0, 0.0, 0.0, -0.2, 0.8), (0.0, -10.0, 40.0, -1.0, 0.0),
              (1.0, -30.0, 20.0, -0.9, 0.1)]
    q, r, s, lo, hi = map(np.array, zip(*cases))
    v = quartic_argmin(q, r, s, lo, hi)
    assert np.all((v >= lo) & (v <= hi))
    for k, (qk, rk, sk, lk, hk) in enumerate(cases):
        xg, fg, h = _grid_min(qk, rk, sk, lk, hk)
        fv = qk * v[k] + rk * v[k] ** 2 + sk * v[k] ** 4
        scale = abs(qk) + abs(rk) + abs(sk)
        assert fv <= fg + 1e-9 * scale, (cases[k], v[k], xg)
        if rk >= 0 and (rk > 0 or sk > 0):  # strictly convex: unique minimiser
            assert abs(v[k] - xg) <= 2 * h + 1e-6, (cases[k], v[k], xg)


def test_quartic_rejects_negative_s():
    with pytest.raises(ValueError, match="s:"):
        quartic_argmin(1.0, 1.0, -1.0, 0.0, 1.0)


# ----------------------------------------------------------------------------- solvers


def _orthogonal_linear_rig(seed=13, n=30, m=5):
    """Shapes on disjoint vertex sets (orthogonal columns of B), no correctives."""
    rng = np.random.default_rng(seed)
    deltas = np.zeros((m, n, 3))
    for k, idx in enumerate(np.array_split(rng.permutation(n), m)):
        deltas[k, idx] = rng.normal(size=(len(idx), 3))
    return QuadraticRig(rng.normal(size=(n, 3)), deltas)


def test_zero_correctives_every_solver_agrees_with_bounded_least_squares():
    # Orthogonal shapes, alpha = 0, targets pushing weights outside [0, 1]: the
    # problem decouples, so ridge (clipped), sequential, mm and lbfgsb are all exact.
    rig = _orthogonal_linear_rig()
    rng = np.random.default_rng(14)
    X = rig.evaluate(rng.uniform(-0.5, 1.5, size=(6, rig.n_shapes))) + 0.05 * rng.normal(size=(6, rig.n_vertices, 3))
    ref = solve(rig, X, solver="bounded", alpha=0.0).weights
    assert np.any(ref == 0) and np.any(ref == 1)
    for name in SOLVERS:
        got = solve(rig, X, solver=name, alpha=0.0, tol=1e-14, max_iter=20000).weights
        np.testing.assert_allclose(got, ref, atol=2e-5, err_msg=name)


def test_zero_correctives_quadratic_solvers_match_bounded_with_alpha():
    # Overlapping (correlated) shapes and alpha > 0: mm and lbfgsb solve the same convex problem as bounded.
    rig, _, _ = random_rig(15, pairs=())
    rng = np.random.default_rng(16)
    X = rig.evaluate(rng.uniform(-0.3, 1.2, size=(4, rig.n_shapes))) + 0.1 * rng.normal(size=(4, rig.n_vertices, 3))
    ref = solve(rig, X, solver="bounded", alpha=0.5)
    for name in ("mm", "lbfgsb"):
        got = solve(rig, X, solver=name, alpha=0.5, tol=1e-15, max_iter=100000)
        np.testing.assert_allclose(got.objective, ref.objective, rtol=1e-6, err_msg=name)
        np.testing.assert_allclose(got.weights, ref.weights, atol=2e-3, err_msg=name)
    # ridge recovers exact interior weights when alpha = 0
    W = rng.uniform(0.1, 0.9, size=(3, rig.n_shapes))
    for name in ("ridge", "bounded", "lbfgsb"):
        np.testing.assert_allclose(solve(rig, rig.evaluate(W), solver=name, alpha=0.0, tol=1e-14).weights, W,
                                   atol=1e-6, err_msg=name)


def test_fast_solver_reaches_mm_objective_with_correctives():
    rig, _, _ = random_rig(17, corr_scale=1.5)
    rng = np.random.default_rng(18)
    W = np.clip(rng.uniform(-0.3, 1.0, size=(5, rig.n_shapes)), 0, 1)
    X = rig.evaluate(W) + 0.02 * rng.normal(size=(5, rig.n_vertices, 3))
    mm = solve(rig, X, solver="mm", alpha=0.1, tol=1e-13, max_iter=50000)
    fast = solve(rig, X, solver="lbfgsb", alpha=0.1, tol=1e-12)
    assert np.all(fast.objective <= mm.objective * 1.01)
    # the quadratic model fits better than any linear solver
    lin = solve(rig, X, solver="bounded", alpha=0.1)
    assert mm.rmse.mean() < lin.rmse.mean()


@pytest.mark.parametrize("solver", SOLVERS)
def test_weights_stay_in_unit_interval(solver):
    rig, _, _ = random_rig(19, corr_scale=2.0)
    rng = np.random.default_rng(20)
    X = rig.evaluate(rng.uniform(-3, 4, size=(6, rig.n_shapes))) + rng.normal(size=(6, rig.n_vertices, 3))
    X[0] = rig.b0.reshape(-1, 3) - 50 * (X[1] - rig.b0.reshape(-1, 3))  # far outside the rig's range
    res = solve(rig, X, solver=solver, alpha=0.2, max_iter=300)
    assert res.weights.shape == (6, rig.n_shapes)
    assert np.all((res.weights >= 0) & (res.weights <= 1))
    assert res.weights.max() == 1.0 or res.weights.min() == 0.0  # bounds are actually active
    for field in ("rmse", "objective"):
        assert np.all(np.isfinite(getattr(res, field)))
    assert np.all(res.cardinality == (res.weights > 0.01).sum(1))


def test_solver_metrics_are_consistent():
    rig, _, _ = random_rig(21)
    W = np.random.default_rng(22).uniform(size=(3, rig.n_shapes))
    res = solve(rig, rig.evaluate(W), solver="lbfgsb", alpha=0.0, tol=1e-14)
    assert res.rmse.max() < 1e-5 and res.objective.max() < 1e-9
    R = rig.evaluate(res.weights) - rig.evaluate(W)
    np.testing.assert_allclose(res.rmse, np.sqrt((R**2).sum(axis=(1, 2)) / rig.n_vertices))
    assert np.all(res.iterations >= 1) and np.all(res.seconds >= 0)


# ----------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("pairs, msg", [
    ([(0, 1), (1, 0)], "duplicate corrective pair"),
    ([(0, 1), (0, 1)], "duplicate corrective pair"),
    ([(0, 9)], "out of range"),
    ([(2, 2)], "two different shapes"),
])
def test_bad_pairs_are_rejected(pairs, msg):
    rng = np.random.default_rng(0)
    with pytest.raises(ShapeError, match=msg):
        QuadraticRig(rng.normal(size=(5, 3)), rng.normal(size=(3, 5, 3)), pairs, rng.normal(size=(len(pairs), 5, 3)))


def test_bad_shapes_and_options_are_rejected():
    rig, _, _ = random_rig(23)
    with pytest.raises(ShapeError, match=r"targets: expected shape \(T, 40, 3\)"):
        solve(rig, np.zeros((2, 39, 3)))
    with pytest.raises(ValueError, match="solver"):
        solve(rig, np.zeros((1, 40, 3)), solver="magic")
    with pytest.raises(ValueError, match="alpha"):
        solve(rig, np.zeros((1, 40, 3)), alpha=-1)
    with pytest.raises(ShapeError, match="correctives"):
        QuadraticRig(np.zeros((4, 3)), np.zeros((2, 4, 3)), [(0, 1)], np.zeros((1, 5, 3)))
    assert InputError  # imported for the file-level tests in test_rigfiles


def test_lbfgsb_stops_relative_to_the_objective_not_to_its_start():
    """tol is relative to f (documented), not to f(w0): from a start far above the minimum it still gets close."""
    rng = np.random.default_rng(41)
    n, m = 60, 8
    deltas = rng.normal(size=(m, n, 3)) + 0.5 * rng.normal(size=(1, n, 3))  # correlated shapes: many iterations
    rig = QuadraticRig(rng.normal(size=(n, 3)), deltas)
    X = rig.evaluate(rng.uniform(0.2, 0.8, size=(1, m))) + 1e-3 * rng.normal(size=(1, n, 3))
    ref = solve(rig, X, solver="bounded", alpha=0.0)
    got = solve(rig, X, solver="lbfgsb", alpha=0.0, tol=1e-9, init=np.ones(m))
    f0 = np.array([rig.objective(np.ones(m), x.reshape(-1), 0.0) for x in X])
    assert np.all(f0 > 1e4 * ref.objective)  # the start is far above the minimum
    assert np.all(got.objective <= ref.objective * (1 + 1e-5))


def test_corrective_spectra_are_computed_for_mm_only():
    rng = np.random.default_rng(42)
    n, m = 30, 4
    rig = QuadraticRig(rng.normal(size=(n, 3)), rng.normal(size=(m, n, 3)), [(0, 1), (1, 2)],
                       rng.normal(size=(2, n, 3)))
    X = rig.evaluate(rng.uniform(0, 1, size=(2, m)))
    for solver in ("lbfgsb", "bounded", "ridge"):
        solve(rig, X, solver=solver)
        assert rig._spectra is None, solver
    solve(rig, X, solver="mm", max_iter=5)
    assert rig._spectra is not None and rig.sigma.shape == (3 * n,)
