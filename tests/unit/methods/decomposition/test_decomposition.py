import numpy as np
import pytest
from scipy.optimize import nnls

from retarget_cli.methods.decomposition import decompose, reconstruction_error


def test_nnls_matches_scipy_per_frame():
    rng = np.random.default_rng(0)
    B = rng.normal(size=(6, 40))
    S = rng.normal(size=(25, 40))
    W, res = decompose(S, B)
    for t in range(len(S)):
        w_ref, r_ref = nnls(B.T, S[t])
        np.testing.assert_allclose(W[t], w_ref, atol=1e-10)
        assert res[t] == pytest.approx(r_ref, rel=1e-10)
    assert W.min() >= 0


def test_exact_non_negative_combinations_are_recovered():
    rng = np.random.default_rng(1)
    B = rng.normal(size=(5, 30))
    W_true = rng.uniform(0, 1, size=(12, 5))
    W, res = decompose(W_true @ B, B)
    np.testing.assert_allclose(W, W_true, atol=1e-9)
    assert res.max() < 1e-9


def test_ls_fits_at_least_as_well_as_nnls_but_goes_negative():
    rng = np.random.default_rng(2)
    base = rng.normal(size=30)
    B = base + 0.05 * rng.normal(size=(8, 30))  # near-collinear keys
    S = base + 0.05 * rng.normal(size=(20, 30))
    W_ls, r_ls = decompose(S, B, solver="ls")
    W_nn, r_nn = decompose(S, B, solver="nnls")
    assert np.all(r_ls <= r_nn + 1e-9)
    assert W_ls.min() < 0 <= W_nn.min()
    assert np.abs(W_ls).max() > np.abs(W_nn).max()


def test_reconstruction_error_is_eq5_sum_of_squares():
    rng = np.random.default_rng(3)
    B = rng.normal(size=(3, 10))
    S = rng.normal(size=(7, 10))
    _, res = decompose(S, B)
    assert reconstruction_error(S, B) == pytest.approx(np.sum(res**2))


def test_bad_input():
    with pytest.raises(ValueError, match=r"keys: expected shape \(K, 10\)"):
        decompose(np.zeros((4, 10)), np.zeros((3, 9)))
    with pytest.raises(ValueError, match="NaN"):
        decompose(np.full((4, 10), np.nan), np.zeros((3, 10)))
    with pytest.raises(ValueError, match="solver"):
        decompose(np.zeros((4, 10)), np.zeros((3, 10)), solver="magic")


# --------------------------------------------------------------------------- every solver, known answers

from scipy.optimize import lsq_linear  # noqa: E402

from retarget_cli.methods.decomposition import (  # noqa: E402
    DEFAULT_ALPHA,
    SOLVERS,
    _spread,
    box_qp,
    cardinality,
    interpolate_lost,
    jitter,
    nnls_batched,
)


def orthogonal_keys(K=4, D=12, seed=0):
    """Keys with orthogonal rows of different lengths: every solver has a closed form per key."""
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(D, K)))
    return q.T * np.array([1.0, 2.0, 0.5, 3.0])[:K, None]


def objective_gap(S, B, W):
    """(f - f_scipy) / max(f_scipy, 1e-10 |s|^2) per frame."""
    f = np.sum((S - W @ B) ** 2, axis=1)
    ref = np.array([nnls(B.T, s)[1] ** 2 for s in S])
    return (f - ref) / np.maximum(ref, 1e-10 * np.sum(S**2, axis=1))


def test_ls_recovers_signed_combinations():
    rng = np.random.default_rng(4)
    B = rng.normal(size=(5, 20))
    W_true = rng.normal(size=(9, 5))
    W, res = decompose(W_true @ B, B, solver="ls")
    np.testing.assert_allclose(W, W_true, atol=1e-9)
    assert res.max() < 1e-9


@pytest.mark.parametrize("upper", [None, 0.7])
def test_bounded_sparse_sequential_and_nnls_closed_forms_on_orthogonal_keys(upper):
    B = orthogonal_keys()
    rng = np.random.default_rng(5)
    S = rng.normal(size=(30, 4)) @ B + 0.1 * rng.normal(size=(30, 12))
    proj = (S @ B.T) / np.sum(B**2, axis=1)  # per-key least-squares weight
    hi = np.inf if upper is None else upper
    np.testing.assert_allclose(decompose(S, B, solver="nnls", upper=upper)[0], np.clip(proj, 0, hi), atol=1e-9)
    np.testing.assert_allclose(decompose(S, B, solver="bounded", upper=upper)[0],
                               np.clip(proj, 0, 1.0 if upper is None else upper), atol=1e-9)
    np.testing.assert_allclose(decompose(S, B, solver="sequential", upper=upper)[0], np.clip(proj, 0, hi), atol=1e-9)
    lam = DEFAULT_ALPHA["sparse"] * _spread(B)
    want = np.clip((S @ B.T - lam / 2) / np.sum(B**2, axis=1), 0, hi)
    np.testing.assert_allclose(decompose(S, B, solver="sparse", upper=upper)[0], want, atol=1e-9)


def test_sequential_visits_keys_by_mean_offset_and_removes_their_contribution():
    # Two overlapping keys: the larger is fitted first and explains the frame alone.
    b1 = np.array([2.0, 2.0, 0.0])
    b2 = np.array([1.0, 0.0, 0.0])
    W, _ = decompose(np.array([[2.0, 2.0, 0.0]]), np.stack([b2, b1]), solver="sequential")
    np.testing.assert_allclose(W, [[0.0, 1.0]], atol=1e-12)


def test_ridge_is_the_closed_form_and_clipped_ridge_clips_it():
    rng = np.random.default_rng(6)
    B = rng.normal(size=(6, 25))
    S = rng.normal(size=(8, 25))
    lam = 0.3 * _spread(B)
    want = np.linalg.solve(B @ B.T + lam * np.eye(6), B @ S.T).T  # Rackovic et al. eq. 6
    np.testing.assert_allclose(decompose(S, B, solver="ridge", alpha=0.3)[0], want, atol=1e-10)
    np.testing.assert_allclose(decompose(S, B, solver="ridge-clipped", alpha=0.3)[0], np.clip(want, 0, 1), atol=1e-10)
    np.testing.assert_allclose(decompose(S, B, solver="ridge-clipped", alpha=0.3, upper=0.2)[0],
                               np.clip(want, 0, 0.2), atol=1e-10)


def test_temporal_causal_pulls_towards_the_previous_frame():
    B = orthogonal_keys(K=1, D=5)
    b2 = float(B[0] @ B[0])
    S = np.array([1.0, 0.2, 0.2])[:, None] * B[0]
    lam = 0.5 * _spread(B)
    W, _ = decompose(S, B, solver="temporal-causal", alpha=0.5, smooth_space="weights")
    w1 = (0.2 * b2 + lam * 1.0) / (b2 + lam)  # Lewis & Anjyo eq. 2 with w0 = previous frame
    w2 = (0.2 * b2 + lam * w1) / (b2 + lam)
    np.testing.assert_allclose(W[:, 0], [1.0, w1, w2], atol=1e-10)
    W0, _ = decompose(S, B, solver="temporal-causal", alpha=0.0)
    np.testing.assert_allclose(W0, decompose(S, B)[0], atol=1e-10)


def test_temporal_whole_take_keeps_exact_linear_motion_and_matches_lsq_linear():
    rng = np.random.default_rng(7)
    B = rng.normal(size=(3, 10))
    t = np.linspace(0, 1, 20)[:, None]
    W_true = 0.2 + t * np.array([0.5, 0.1, 0.0]) + (1 - t) * np.array([0.0, 0.3, 0.4])
    W, res = decompose(W_true @ B, B, solver="temporal", alpha=5.0)  # zero residual and zero roughness
    np.testing.assert_allclose(W, W_true, atol=1e-8)
    # Noisy frames: the joint solve reaches the optimum of the sparse bound-constrained problem.
    from scipy import sparse

    S = W_true @ B + 0.3 * rng.normal(size=(20, 10))
    lam = 2.0 * _spread(B)
    W, _ = decompose(S, B, solver="temporal", alpha=2.0, smooth_space="weights")
    D2 = sparse.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(18, 20))
    A = sparse.vstack([sparse.kron(sparse.identity(20), B.T), np.sqrt(lam) * sparse.kron(D2, sparse.identity(3))])
    b = np.concatenate([S.ravel(), np.zeros(18 * 3)])
    ref = lsq_linear(A.toarray(), b, bounds=(0, np.inf), method="bvls", tol=1e-14).x
    f = lambda x: np.sum((A @ x - b) ** 2)
    assert f(W.ravel()) <= f(ref) * (1 + 1e-8)
    assert W.min() >= 0


def test_shape_space_temporal_matches_lsq_linear_and_causal_formula():
    from scipy import sparse

    rng = np.random.default_rng(9)
    B = rng.normal(size=(3, 10))
    W_true = 0.2 + np.linspace(0, 1, 20)[:, None] * np.array([0.5, 0.1, 0.0])
    S = W_true @ B + 0.3 * rng.normal(size=(20, 10))
    W, _ = decompose(S, B, solver="temporal", alpha=2.0)  # shape space: λ = alpha, penalty ‖D₂ W B‖²
    D2 = sparse.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(18, 20))
    A = sparse.vstack([sparse.kron(sparse.identity(20), B.T), np.sqrt(2.0) * sparse.kron(D2, B.T)])
    b = np.concatenate([S.ravel(), np.zeros(18 * 10)])
    ref = lsq_linear(A.toarray(), b, bounds=(0, np.inf), method="bvls", tol=1e-14).x
    f = lambda x: np.sum((A @ x - b) ** 2)  # noqa: E731
    assert f(W.ravel()) <= f(ref) * (1 + 1e-8)
    # causal: each frame minimises ‖S_t − Bᵀw‖² + λ‖Bᵀ(w − w_{t−1})‖², w ≥ 0
    Wc, _ = decompose(S, B, solver="temporal-causal", alpha=0.7)
    for t in (5, 12):
        Ac = np.vstack([B.T, np.sqrt(0.7) * B.T])
        bc = np.concatenate([S[t], np.sqrt(0.7) * (B.T @ Wc[t - 1])])
        want = lsq_linear(Ac, bc, bounds=(0, np.inf), method="bvls", tol=1e-14).x
        np.testing.assert_allclose(Wc[t], want, atol=1e-7)


def test_shape_space_temporal_lowers_mesh_jitter_below_weight_space_at_equal_residual():
    rng = np.random.default_rng(5)
    T, K, D = 300, 8, 40
    base = rng.normal(size=(4, D))
    B = np.vstack([base, base + 0.3 * rng.normal(size=(4, D))])  # pairs of similar keys
    t = np.arange(T)[:, None]
    W_true = np.clip(0.3 + 0.3 * np.sin(2 * np.pi * t / 150 + np.arange(K)), 0, None)
    S = W_true @ B + 0.3 * rng.normal(size=(T, D))
    target = B + 0.3 * rng.normal(size=B.shape)  # the character's keys: other shapes, same weights

    def residual(W):
        return np.mean(np.sum((S - W @ B) ** 2, 1))

    def mesh_jitter(W, keys):
        return np.mean(np.sum(np.diff(W @ keys, n=2, axis=0) ** 2, 1))

    Ww, _ = decompose(S, B, solver="temporal", alpha=0.1, smooth_space="weights")
    goal = residual(Ww)
    lo, hi = -3.0, 2.0  # bisect log10(alpha) of the shape-space solver to the same residual
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        Ws, _ = decompose(S, B, solver="temporal", alpha=10**mid)
        lo, hi = (mid, hi) if residual(Ws) < goal else (lo, mid)
        if abs(residual(Ws) / goal - 1) < 1e-3:
            break
    assert abs(residual(Ws) / goal - 1) < 1e-3
    assert mesh_jitter(Ws, B) < 0.5 * mesh_jitter(Ww, B)
    assert mesh_jitter(Ws, target) < 0.8 * mesh_jitter(Ww, target)


# --------------------------------------------------------------------------- batched NNLS is exact


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("case", ["random", "rank-deficient", "duplicated", "more-keys-than-coordinates", "fits"])
def test_batched_nnls_matches_scipy_objective(case, compiled):
    rng = np.random.default_rng(8)
    B = rng.normal(size=(12, 30))
    if case == "rank-deficient":
        B[5] = B[1] + B[2]
        B[7] = 0.5 * B[3]
    elif case == "duplicated":
        B[4] = B[9] = B[0]
    elif case == "more-keys-than-coordinates":
        B = rng.normal(size=(40, 20))
    S = rng.normal(size=(400, B.shape[1]))
    if case == "fits":  # frames that the keys reproduce exactly, including the keys themselves
        S = np.vstack([B, rng.uniform(0, 1, size=(50, 12)) @ B])
    W = nnls_batched(S, B, compiled=compiled)
    assert W.min() >= 0
    assert objective_gap(S, B, W).max() <= 1e-8


def weighted_gap(S, B, C, W):
    """Relative objective gap to scipy's nnls on the rows scaled by sqrt(c), per frame."""
    rw = np.sqrt(C)
    ref = np.array([nnls(B.T * r[:, None], s * r)[1] ** 2 for s, r in zip(S, rw)])
    f = np.sum(C * (S - W @ B) ** 2, axis=1)
    return (f - ref) / np.maximum(ref, np.maximum(1e-10 * np.sum(C * S**2, axis=1), 1e-300))


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("case", ["random", "rank-deficient", "duplicated", "more-keys-than-coordinates",
                                  "fits", "paired", "zero-rows"])
def test_weighted_batched_nnls_matches_scipy(case, compiled):
    """Every frame with its own confidence row (its own Hessian B C_t Bᵀ) is solved exactly, like scipy."""
    rng = np.random.default_rng(31)
    B = rng.normal(size=(12, 30))
    if case == "rank-deficient":
        B[5] = B[1] + B[2]
        B[7] = 0.5 * B[3]
    elif case == "duplicated":
        B[4] = B[9] = B[0]
    elif case == "more-keys-than-coordinates":
        B = rng.normal(size=(40, 20))
    T, D = (100 if len(B) > B.shape[1] else 300), B.shape[1]
    S = rng.normal(size=(T, D))
    if case == "fits":
        S = np.vstack([B, rng.uniform(0, 1, size=(50, len(B))) @ B])
        T = len(S)
    C = rng.uniform(0.05, 1.0, size=(T, D))
    if case == "paired":  # x and y of a landmark share a confidence (the halved product)
        C = np.repeat(C[:, : D // 2], 2, axis=1)
    elif case == "zero-rows":  # some coordinates lost, and one frame lost entirely
        C[rng.uniform(size=C.shape) < 0.3] = 0.0
        C[7] = 0.0
    W = nnls_batched(S, B, confidence=C, compiled=compiled)
    assert W.shape == (T, len(B)) and W.min() >= 0 and np.isfinite(W).all()
    assert weighted_gap(S, B, C, W).max() <= 1e-8


def test_weighted_decompose_agrees_with_one_call_per_frame():
    """decompose with a confidence row per frame equals solving each frame alone with its weighted Hessian."""
    from retarget_cli.methods.decomposition import box_qp

    rng = np.random.default_rng(32)
    B = rng.normal(size=(6, 16))
    S = rng.uniform(0, 1, size=(40, 6)) @ B + 0.1 * rng.normal(size=(40, 16))
    C = rng.uniform(0.5, 1.0, size=(40, 16))
    for solver, kw in (("nnls", {}), ("bounded", {"upper": 0.5}), ("sparse", {"alpha": 0.05}),
                       ("ridge", {}), ("nnls", {"formulation": "convex"})):
        W, _ = decompose(S, B, solver=solver, confidence=C, **kw)
        for t in (0, 17, 39):
            one, _ = decompose(S[t:t + 1], B, solver=solver, confidence=C[t:t + 1], **kw)
            Bc = B * C[t]
            H, q = Bc @ B.T, Bc @ S[t]
            f = lambda w, H=H, q=q: 0.5 * w @ H @ w - q @ w  # noqa: E731
            assert f(W[t]) <= f(one[0]) + 1e-9 * max(1.0, abs(f(one[0]))), (solver, t)
            if solver == "nnls" and not kw:
                ref = box_qp(H, q[None], lower=0.0)[0]
                assert f(W[t]) <= f(ref) + 1e-9 * max(1.0, abs(f(ref)))
        if kw.get("formulation") == "convex":
            np.testing.assert_allclose(W.sum(1), 1.0, atol=1e-9)
        if solver == "bounded":
            assert W.max() <= 0.5


def test_batched_nnls_on_near_collinear_face_like_keys():
    """Whole-face keys are nearly collinear (one huge eigenvalue): the case of the benchmark."""
    rng = np.random.default_rng(9)
    mean = rng.uniform(50, 250, size=60)
    B = mean + 3 * rng.normal(size=(15, 60))
    S = rng.dirichlet(np.ones(15), size=300) @ B + 0.5 * rng.normal(size=(300, 60))
    for compiled in (True, False):
        assert objective_gap(S, B, nnls_batched(S, B, compiled=compiled)).max() <= 1e-8


def test_box_qp_matches_bvls_with_upper_bounds():
    rng = np.random.default_rng(10)
    B = rng.normal(size=(8, 20))
    S = 2 * rng.normal(size=(60, 20))
    X = box_qp(B @ B.T, S @ B.T, lower=0.0, upper=0.4)
    for s, x in zip(S, X):
        ref = lsq_linear(B.T, s, bounds=(0, 0.4), method="bvls", tol=1e-14).x
        f = lambda w, s=s: np.sum((B.T @ w - s) ** 2)
        assert f(x) <= f(ref) + 1e-8 * max(f(ref), 1e-10 * s @ s)
    assert X.min() >= 0 and X.max() <= 0.4


# --------------------------------------------------------------------------- constraints


@pytest.mark.parametrize("solver", ["nnls", "bounded", "ls", "ridge", "sparse", "temporal-causal"])
def test_convex_weights_sum_to_one(solver):
    rng = np.random.default_rng(11)
    B = rng.normal(size=(6, 16))
    S = rng.normal(size=(40, 16))
    W, _ = decompose(S, B, solver=solver, formulation="convex")
    np.testing.assert_allclose(W.sum(1), 1.0, atol=1e-9)
    if solver != "ls" and solver != "ridge":
        assert W.min() >= 0


def test_convex_recovers_convex_combinations():
    rng = np.random.default_rng(12)
    B = rng.normal(size=(5, 20))
    W_true = rng.dirichlet(np.ones(5), size=10)
    W, _ = decompose(W_true @ B, B, formulation="convex")
    np.testing.assert_allclose(W, W_true, atol=1e-8)


@pytest.mark.parametrize("solver", ["nnls", "bounded", "ridge-clipped", "temporal", "temporal-causal", "sparse",
                                    "sequential"])
def test_bounds_hold(solver):
    rng = np.random.default_rng(13)
    B = rng.normal(size=(6, 16))
    S = 3 * rng.normal(size=(40, 16))
    W, _ = decompose(S, B, solver=solver, upper=0.5)
    assert W.min() >= 0 and W.max() <= 0.5
    assert np.isclose(W.max(), 0.5)  # the bound is active somewhere, so it was enforced


def test_delta_recovers_weights_relative_to_the_neutral():
    rng = np.random.default_rng(14)
    S0 = rng.normal(size=20)
    keys = np.vstack([S0, S0 + rng.normal(size=(4, 20))])  # the neutral is key 0
    W_true = rng.uniform(0, 0.8, size=(12, 4))
    frames = S0 + W_true @ (keys[1:] - S0)
    W, res = decompose(frames, keys, formulation="delta", neutral=S0, upper=1.0)
    assert np.all(W[:, 0] == 0)  # a key equal to the neutral has no delta
    np.testing.assert_allclose(W[:, 1:], W_true, atol=1e-8)
    assert res.max() < 1e-8
    with pytest.raises(ValueError, match="neutral"):
        decompose(frames, keys, formulation="delta")


def test_every_solver_runs_with_confidence_weights_and_ignores_zero_weight_rows():
    rng = np.random.default_rng(15)
    B = rng.normal(size=(4, 12))
    W_true = rng.uniform(0, 1, size=(10, 4))
    S = W_true @ B
    S[:, :3] += 100.0  # corrupted coordinates ...
    C = np.ones_like(S)
    C[:, :3] = 0.0  # ... with zero confidence
    W, _ = decompose(S, B, confidence=C)
    np.testing.assert_allclose(W, W_true, atol=1e-8)
    for solver in SOLVERS:
        W, res = decompose(S, B, solver=solver, confidence=C)
        assert W.shape == (10, 4) and np.all(np.isfinite(W))


def test_unsupported_combinations_and_bad_options_are_errors():
    S, B = np.zeros((3, 4)), np.eye(4)[:2]
    with pytest.raises(ValueError, match="does not support formulation 'convex'"):
        decompose(S, B, solver="sequential", formulation="convex")
    with pytest.raises(ValueError, match="formulation"):
        decompose(S, B, formulation="barycentric")
    with pytest.raises(ValueError, match="alpha"):
        decompose(S, B, solver="ridge", alpha=-1)
    with pytest.raises(ValueError, match="confidence"):
        decompose(S, B, confidence=np.ones((3, 5)))


# --------------------------------------------------------------------------- temporal smoothing, Figs. 4-5


def test_whole_take_temporal_lowers_jitter_at_a_small_residual_cost():
    rng = np.random.default_rng(16)
    T, K = 300, 6
    B = rng.normal(size=(K, 40))
    t = np.arange(T)[:, None]
    W_true = 0.5 + 0.4 * np.sin(2 * np.pi * t / 120 + np.arange(K))
    S = W_true @ B + 0.4 * rng.normal(size=(T, 40))
    W_n, r_n = decompose(S, B, solver="nnls")
    W_t, r_t = decompose(S, B, solver="temporal", alpha=0.1, smooth_space="weights")
    assert jitter(W_t) < 0.5 * jitter(W_n)
    assert np.mean(r_t**2) < 1.05 * np.mean(r_n**2)
    # ... and the smooth weights are closer to the truth.
    assert np.abs(W_t - W_true).mean() < np.abs(W_n - W_true).mean()


def test_nnls_beats_ls_in_the_target_domain_figs_4_5():
    """Chuang & Bregler Figs. 4-5: near-collinear source keys, target keys that differ slightly."""
    rng = np.random.default_rng(17)
    K, D = 21, 40  # 21 lip keys as in the paper
    base = rng.normal(size=D)
    src = base + 0.02 * rng.normal(size=(K, D))  # near-collinear tracked key shapes
    tgt = src + 0.02 * rng.normal(size=(K, D))  # traced target keys: close, not identical
    W_true = rng.dirichlet(np.ones(K) * 0.3, size=50)
    frames = W_true @ src + 0.01 * rng.normal(size=(50, D))  # tracking noise
    W_ls, r_ls = decompose(frames, src, solver="ls")
    W_nn, r_nn = decompose(frames, src, solver="nnls")
    assert r_ls.mean() <= r_nn.mean()  # LS fits the source better (Fig. 4a) ...
    err_ls = np.linalg.norm(W_ls @ tgt - W_true @ tgt, axis=1).mean()
    err_nn = np.linalg.norm(W_nn @ tgt - W_true @ tgt, axis=1).mean()
    assert err_nn < 0.75 * err_ls  # ... but distorts the target (Fig. 4b vs 5b)
    assert W_ls.min() < 0 <= W_nn.min()  # cancelling positive and negative weights
    assert np.abs(W_ls).sum(1).mean() > 1.5 * np.abs(W_nn).sum(1).mean()


# --------------------------------------------------------------------------- diagnostics


def test_cardinality_jitter_and_interpolation():
    W = np.array([[0.0, 0.5], [0.005, 0.02], [1.0, 0.0], [0.0, 0.0]])
    np.testing.assert_array_equal(cardinality(W), [1, 1, 1, 0])
    assert jitter(np.outer(np.arange(5.0), [1, 2])) == 0.0  # linear motion has no jitter
    assert jitter(np.array([[0.0], [1.0], [0.0]])) == pytest.approx(4.0)
    lost = np.array([False, True, True, False])
    np.testing.assert_allclose(interpolate_lost(np.array([[0.0], [9.0], [9.0], [3.0]]), lost)[:, 0], [0, 1, 2, 3])
    np.testing.assert_allclose(interpolate_lost(np.array([[9.0], [2.0]]), [True, False])[:, 0], [2, 2])
    with pytest.raises(ValueError, match="every frame is lost"):
        interpolate_lost(np.zeros((2, 1)), [True, True])


# --------------------------------------------------------------------------- box_qp internals


def test_stacked_cholesky_solves_match_lapack():
    from retarget_cli.methods.decomposition.boxqp import _cholesky_solve_stacked

    rng = np.random.default_rng(21)
    m, n = 7, 200
    G = rng.normal(size=(n, m, m + 3))
    H = G @ G.transpose(0, 2, 1)
    H[5] = 0.0  # a singular system is flagged, not silently solved
    b = rng.normal(size=(n, m))
    e = (rng.uniform(size=(n, m)) < 0.8).astype(float)
    s = rng.normal(size=n)
    A = np.concatenate([H, b[:, None, :], e[:, None, :]], axis=1).transpose(1, 2, 0).copy()
    x, nu, ok = _cholesky_solve_stacked(A[: m + 1].copy())
    assert nu is None and not ok[5] and ok.sum() == n - 1
    np.testing.assert_allclose(x.T[ok], np.linalg.solve(H[ok], b[ok][..., None])[..., 0], rtol=1e-9, atol=1e-9)
    x, nu, ok = _cholesky_solve_stacked(A, s)
    for t in np.flatnonzero(ok)[:20]:  # KKT system of min ½xᵀHx − bᵀx s.t. eᵀx = s
        K = np.block([[H[t], e[t][:, None]], [e[t][None, :], np.zeros((1, 1))]])
        ref = np.linalg.solve(K, np.concatenate([b[t], [s[t]]]))
        np.testing.assert_allclose(np.concatenate([x[:, t], [nu[t]]]), ref, rtol=1e-8, atol=1e-8)


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("bounds", [dict(), dict(upper=0.3), dict(sum_to=1.0), dict(upper=0.6, sum_to=1.0)])
def test_box_qp_fast_paths_agree_with_lapack_path(bounds, compiled, monkeypatch):
    """The compiled kernel, the vectorised Cholesky and the Schur-complement start agree with plain LAPACK solves."""
    from retarget_cli.methods.decomposition import boxqp as dec

    rng = np.random.default_rng(22)
    mean = rng.uniform(50, 250, size=40)
    B = mean + 3 * rng.normal(size=(14, 40))
    S = rng.dirichlet(np.ones(14), size=900) @ B + 0.5 * rng.normal(size=(900, 40))
    H, Q = B @ B.T, S @ B.T
    fast = box_qp(H, Q, **bounds, compiled=compiled)
    monkeypatch.setattr(dec, "_VECTOR_MIN", 10**9)
    monkeypatch.setattr(dec, "_SCHUR_MAX_COND", 0.0)
    slow = box_qp(H, Q, **bounds, compiled=False)
    f = lambda W: 0.5 * np.einsum("tk,kl,tl->t", W, H, W) - np.einsum("tk,tk->t", Q, W)  # noqa: E731
    assert np.all(f(fast) <= f(slow) + 1e-9 * np.abs(f(slow)))
    np.testing.assert_allclose(fast, slow, atol=1e-6)


def test_long_weighted_take_same_result_on_one_or_two_threads(monkeypatch):
    """The chunks of a long weighted take are fixed by size: solving them side by side changes nothing."""
    import retarget_cli.methods.decomposition.boxqp as dm

    rng = np.random.default_rng(5)
    K, T = 22, dm._KERNEL_MIN_WORK_WEIGHTED // 22 + 300  # compiled kernel, several chunks
    B = rng.normal(size=(K, 40))
    S = rng.uniform(0, 1, (T, K)) @ B + rng.normal(scale=0.05, size=(T, 40))
    C = rng.uniform(0.7, 1.0, (T, 20)).repeat(2, axis=1)
    out = {}
    for n in (1, 2):
        monkeypatch.setattr(dm, "_SOLVE_THREADS", n)
        out[n], _ = decompose(S, B, confidence=C)
    assert out[1].tobytes() == out[2].tobytes()
    assert np.all(out[1] >= 0) and np.abs(out[1]).sum() > 0
    # the per-frame optimum: as good as scipy's on a sample of frames
    for t in rng.choice(T, 20, replace=False):
        r = np.sqrt(C[t])
        ref = nnls(B.T * r[:, None], S[t] * r)[0]
        f = lambda w, t=t: np.sum(C[t] * (S[t] - w @ B) ** 2)  # noqa: E731
        assert f(out[1][t]) <= f(ref) * (1 + 1e-8) + 1e-12


def test_prefetch_kernel_only_for_solves_that_use_it():
    import retarget_cli.methods.decomposition.boxqp as dm

    assert not dm.prefetch_kernel(dm._KERNEL_MIN_WORK_WEIGHTED - 1, weighted=True)
    assert not dm.prefetch_kernel(dm._KERNEL_MIN_WORK - 1, weighted=False)
    assert dm.prefetch_kernel(dm._KERNEL_MIN_WORK_WEIGHTED, weighted=True)
    dm._await_kernel(True)
    assert not dm._PREFETCH[True].is_alive()  # loaded in the background; a solve waits for it
    assert False not in dm._PREFETCH  # no load started for the uniform-confidence kernel


def test_sparse_box_qp_solves_a_banded_problem_with_per_variable_bounds_like_the_dense_solver():
    from scipy import sparse

    from retarget_cli.methods.decomposition import box_qp
    from retarget_cli.methods.decomposition.temporal import sparse_box_qp

    rng = np.random.default_rng(5)
    T, K = 40, 3
    A = rng.standard_normal((T, 4, K))
    blocks = np.einsum("tri,trj->tij", A, A) + 0.01 * np.eye(K)
    D2 = np.diff(np.eye(T), 2, axis=0)
    H = sparse.block_diag(list(blocks)) + 0.5 * sparse.kron(D2.T @ D2, np.eye(K))
    q = 2.0 * rng.standard_normal(T * K)
    lo = np.where(rng.random(T * K) < 0.3, -0.5, 0.0)
    hi = np.where(rng.random(T * K) < 0.5, 1.0, np.inf)
    x, settled = sparse_box_qp(sparse.csr_matrix(H), q, lo, hi, np.zeros(T * K))
    ref = box_qp(H.toarray(), q[None], lower=lo, upper=hi)[0]
    assert settled
    assert np.all(x >= lo) and np.all(x <= hi)
    assert ((lo < x) & (x < hi)).sum() < T * K and ((x == lo) | (x == hi)).any()  # bounds are active
    np.testing.assert_allclose(x, ref, atol=1e-6)
