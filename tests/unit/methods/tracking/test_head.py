import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from retarget_cli.methods.tracking.head import apply_similarity, estimate_head, fit_similarity, invert_similarity


def similarity(s, theta, tx, ty):
    c, si = s * np.cos(theta), s * np.sin(theta)
    return np.array([[c, -si, tx], [si, c, ty]])


@settings(max_examples=40, deadline=None)
@given(
    s=st.floats(0.5, 2.0),
    theta=st.floats(-np.pi / 3, np.pi / 3),
    tx=st.floats(-100, 100),
    ty=st.floats(-100, 100),
)
def test_fit_similarity_recovers_known_motion(s, theta, tx, ty):
    src = np.random.default_rng(1).uniform(0, 200, size=(11, 2))
    M = similarity(s, theta, tx, ty)
    dst = apply_similarity(M[None], src[None])
    np.testing.assert_allclose(fit_similarity(src, dst)[0], M, atol=1e-6)


def test_fit_similarity_is_robust_to_one_outlier():
    src = np.random.default_rng(2).uniform(0, 200, size=(11, 2))
    M = similarity(1.1, 0.2, 5, -3)
    dst = apply_similarity(M[None], src[None])
    dst[0, 4] += [40.0, -25.0]
    got = fit_similarity(src, dst, iterations=5)[0]
    plain = fit_similarity(src, dst, iterations=0)[0]
    assert np.abs(got - M).max() < 0.2 * np.abs(plain - M).max()


def test_invert_similarity_round_trips():
    M = np.stack([similarity(1.2, 0.3, 4, 5), similarity(0.8, -0.5, -10, 2)])
    pts = np.random.default_rng(3).normal(size=(2, 7, 2))
    back = apply_similarity(invert_similarity(M), apply_similarity(M, pts))
    np.testing.assert_allclose(back, pts, atol=1e-12)


def test_estimate_head_separates_rigid_motion_from_expression():
    rng = np.random.default_rng(4)
    ref = rng.uniform(50, 250, size=(68, 2))
    T = 5
    stab = np.repeat(ref[None], T, axis=0)
    stab[:, 48:68] += rng.normal(scale=3.0, size=(T, 20, 2))  # mouth moves, rigid points do not
    stab[0] = ref
    heads = np.stack([similarity(1.0 + 0.05 * t, 0.1 * t, 3 * t, -2 * t) for t in range(T)])
    pts = apply_similarity(heads, stab)
    head, got = estimate_head(pts)
    np.testing.assert_allclose(head, heads, atol=1e-6)
    np.testing.assert_allclose(got, stab, atol=1e-6)


def test_estimate_head_rejects_bad_shapes():
    with pytest.raises(ValueError, match=r"\(T, L, 2\)"):
        estimate_head(np.zeros((4, 68)))
    with pytest.raises(ValueError, match="rigid_points"):
        estimate_head(np.zeros((4, 10, 2)), rigid_points=[3, 12])


def _fit_similarity_reference(src, dst, weights, iterations):
    """The straightforward IRLS (the implementation before it was streamlined), for comparison."""
    dst = np.asarray(dst, dtype=np.float64)
    T, L, _ = dst.shape
    src = np.broadcast_to(np.asarray(src, dtype=np.float64), (T, L, 2))
    w0 = np.ones((T, L)) if weights is None else np.asarray(weights, dtype=np.float64).copy()
    w0 = np.where(np.isfinite(dst).all(-1), np.clip(w0, 0, None), 0.0)
    zs = src[..., 0] + 1j * src[..., 1]
    zd = np.nan_to_num(dst[..., 0]) + 1j * np.nan_to_num(dst[..., 1])
    w = w0
    for it in range(iterations + 1):
        wsum = w.sum(1, keepdims=True)
        wsum = np.where(wsum > 0, wsum, 1.0)
        ms = (w * zs).sum(1, keepdims=True) / wsum
        md = (w * zd).sum(1, keepdims=True) / wsum
        cs, cd = zs - ms, zd - md
        den = (w * np.abs(cs) ** 2).sum(1)
        a = (w * np.conj(cs) * cd).sum(1) / np.where(den > 0, den, 1.0)
        a = np.where(den > 0, a, 1.0)
        b = md[:, 0] - a * ms[:, 0]
        if it == iterations:
            break
        r = np.abs(zd - (a[:, None] * zs + b[:, None]))
        scale = 1.4826 * np.median(np.where(w0 > 0, r, np.nan), axis=1, keepdims=True)
        scale = np.nan_to_num(np.maximum(scale, 1e-3), nan=1.0)
        k = 1.345 * scale
        w = w0 * np.where(r <= k, 1.0, k / np.maximum(r, 1e-12))
    return np.stack([np.stack([a.real, -a.imag, b.real], 1), np.stack([a.imag, a.real, b.imag], 1)], 1)


def test_fit_similarity_matches_reference_irls():
    # The compiled kernel sums in loop order (numpy sums pairwise), so the
    # results agree to rounding, not bit for bit.
    rng = np.random.default_rng(3)
    for trial in range(300):
        T, L = int(rng.integers(1, 4)), int(rng.integers(2, 15))
        src = rng.normal(size=(L, 2) if trial % 2 else (T, L, 2)) * 100
        dst = rng.normal(size=(T, L, 2)) * 100
        w = rng.random((T, L))
        w[rng.random((T, L)) < 0.2] = 0  # zero weights (robust scale falls back to 1 px)
        if trial % 5 == 0:
            dst[0, 0, 1] = np.nan
        if trial % 7 == 0:
            dst[-1, -1, 0] = np.inf
        for it in (0, 1, 3):
            for weights in (w, None):
                got = fit_similarity(src, dst, weights, iterations=it)
                assert np.isfinite(got).all()
                # a frame with fewer than two weighted points has no defined
                # similarity: both give whatever the rounding leaves there
                ww = np.ones((T, L)) if weights is None else weights
                posed = ((ww > 0) & np.isfinite(dst).all(-1)).sum(1) >= 2
                np.testing.assert_allclose(got[posed], _fit_similarity_reference(src, dst, weights, it)[posed],
                                           rtol=1e-12, atol=1e-9)
