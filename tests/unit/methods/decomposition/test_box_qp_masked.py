"""box_qp_masked: every frame's box-constrained QP over its own free variables, in one compiled call."""

import numpy as np
import pytest
from scipy.optimize import lsq_linear

from retarget_cli.errors import ParameterError
from retarget_cli.methods.decomposition.boxqp import box_qp_masked, box_qp_weighted


def _problems(rng, T, K, r, cond):
    """Least-squares problems ``min ‖A_t x − b_t‖²`` with singular values from 1 down to 1/cond, as QPs."""
    A = np.empty((T, r, K))
    for t in range(T):
        U, _ = np.linalg.qr(rng.normal(size=(r, K)))
        V, _ = np.linalg.qr(rng.normal(size=(K, K)))
        A[t] = (U * np.geomspace(1.0, 1.0 / cond, K)) @ V.T
    b = rng.normal(size=(T, r))
    H = A.transpose(0, 2, 1) @ A
    q = (A.transpose(0, 2, 1) @ b[..., None])[..., 0]
    return A, b, H, q


@pytest.mark.parametrize("cond", [10.0, 1e4])
def test_each_frame_is_the_bounded_least_squares_solution_on_its_free_set(cond):
    rng = np.random.default_rng(7)
    T, K, r = 60, 12, 30
    A, b, H, q = _problems(rng, T, K, r, cond)
    lo, hi = np.r_[-0.5, -0.2, np.zeros(K - 2)], np.r_[np.full(K - 1, 0.3), np.inf]
    free = rng.uniform(size=(T, K)) < 0.7
    free[0] = True
    free[1] = False  # nothing free: the frame is 0
    X = box_qp_masked(H, q, free, lower=lo, upper=hi)
    assert np.all(X[~free] == 0.0) and not X[1].any()
    active = 0
    for t in range(T):
        F = np.flatnonzero(free[t])
        if not F.size:
            continue
        ref = lsq_linear(A[t][:, F], b[t], bounds=(lo[F], hi[F]), method="bvls", tol=1e-14, lsmr_tol=None).x
        # the same minimiser: compare the objective's solutions in the Hessian's norm and entrywise
        np.testing.assert_allclose(X[t, F], ref, rtol=0, atol=1e-9 * cond)
        active += int(np.sum((X[t, F] <= lo[F]) | (X[t, F] >= hi[F])))
    assert active > T  # the bounds were exercised


def test_kkt_conditions_hold_and_match_the_solve_by_free_set_on_ill_conditioned_frames():
    rng = np.random.default_rng(11)
    T, K, r = 80, 16, 40
    _, _, H, q = _problems(rng, T, K, r, 1e7)
    lo, hi = np.zeros(K), np.ones(K)
    free = np.ones((T, K), dtype=bool)
    free[rng.uniform(size=(T, K)) < 0.2] = False
    X = box_qp_masked(H, q, free, lower=lo, upper=hi)
    for t in range(T):
        F = np.flatnonzero(free[t])
        x, g = X[t, F], H[t][np.ix_(F, F)] @ X[t, F] - q[t, F]
        tol = 1e-8 * (np.abs(q[t]).max() + np.abs(np.diag(H[t])).max())
        assert np.all(x >= lo[F]) and np.all(x <= hi[F])
        inner = (x > lo[F]) & (x < hi[F])
        assert np.all(np.abs(g[inner]) <= tol)  # stationary where free of its bounds
        assert np.all(g[x <= lo[F]] >= -tol) and np.all(g[x >= hi[F]] <= tol)  # multipliers of the right sign
        iu, ju = np.triu_indices(len(F))
        ref = box_qp_weighted(H[t][np.ix_(F, F)][iu, ju][None], q[t, F][None], lower=lo[F], upper=hi[F],
                              compiled=False)[0]
        np.testing.assert_allclose(x, ref, rtol=0, atol=1e-6)


def test_a_range_without_zero_is_refused():
    H = np.eye(2)[None]
    with pytest.raises(ParameterError):
        box_qp_masked(H, np.ones((1, 2)), np.ones((1, 2), bool), lower=0.1, upper=1.0)


def test_sparse_box_qp_slices_large_systems_with_the_kernel_to_the_same_bits(monkeypatch):
    """The compiled slicing of a large system's reduced matrices gives scipy's matrices: the same iterates."""
    from scipy import sparse

    from retarget_cli.methods.decomposition import temporal
    from retarget_cli.methods.decomposition._qp_kernel import principal_csc

    rng = np.random.default_rng(3)
    T, k = 120, 6
    Hb = np.stack([(lambda a: a.T @ a)(rng.normal(size=(10, k))) for _ in range(T)])
    blocks = sparse.block_diag(list(Hb), format="csr")
    D2 = temporal._second_difference(T)
    H = (blocks + 5.0 * sparse.kron(D2.T @ D2, sparse.eye(k), format="csr")).tocsr()
    q = rng.normal(size=T * k) * 3
    lo, hi = np.r_[np.full(k - 1, 0.0), -1.0][np.tile(np.arange(k), T)], np.ones(T * k)
    x0 = rng.uniform(-0.5, 1.5, size=T * k)
    keep = np.flatnonzero(rng.uniform(size=T * k) < 0.6)
    Hc = H.tocsc()
    ptr, rows, vals = principal_csc(Hc.indptr, Hc.indices, Hc.data, keep, T * k)
    ref = Hc[keep][:, keep].tocsc()
    assert np.array_equal(ptr, ref.indptr) and np.array_equal(rows, ref.indices) and np.array_equal(vals, ref.data)
    monkeypatch.setattr(temporal, "_SLICE_KERNEL_MIN_NNZ", 10**12)
    x_scipy, ok_scipy = temporal.sparse_box_qp(H, q, lo, hi, x0)
    monkeypatch.setattr(temporal, "_SLICE_KERNEL_MIN_NNZ", 0)
    x_kernel, ok_kernel = temporal.sparse_box_qp(H, q, lo, hi, x0)
    assert ok_scipy and ok_kernel and np.array_equal(x_kernel, x_scipy)
    assert np.sum((x_kernel <= lo) | (x_kernel >= hi)) > T  # bounds at zero and nonzero values were active
