import numpy as np
import pytest
from scipy.optimize import nnls

from retarget_cli.decompose import decompose, reconstruction_error


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
