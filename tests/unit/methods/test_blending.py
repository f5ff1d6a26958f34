import numpy as np
import pytest

from retarget_cli.methods.blending import (
    apply_transforms,
    blend_regions,
    falloff_mask,
    head_motion_transforms,
    mesh_edges,
    region_weights,
)
from retarget_cli.methods.tracking.head import apply_similarity, fit_similarity


def grid(nx=30, ny=20, step=0.1):
    u, v = np.meshgrid(np.arange(nx) * step, np.arange(ny) * step)
    V = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], 1)
    idx = np.arange(nx * ny).reshape(ny, nx)
    F = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], -1).reshape(-1, 4)
    return V, [list(f) for f in F]


def test_mesh_edges_include_quad_diagonals():
    E = mesh_edges([[0, 1, 2, 3]], 4)
    assert E.tolist() == [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]


def test_falloff_is_linear_in_distance_and_lipschitz():
    V, F = grid()
    E = mesh_edges(F, len(V))
    m = (V[:, 0] <= 1.0 + 1e-9).astype(float)  # columns x <= 1.0
    w = 0.5
    out = falloff_mask(m, vertices=V, edges=E, width=w)
    assert np.all(out >= m)
    x = V[:, 0]
    # Along the rows, distance to the mask is x - 1: weight 1 - (x - 1) / w, then 0.
    np.testing.assert_allclose(out, np.clip(1 - (x - 1.0) / w, 0, 1), atol=1e-9)
    lengths = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)
    assert np.all(np.abs(out[E[:, 0]] - out[E[:, 1]]) <= lengths / w + 1e-9)


def test_soft_masks_stay_lipschitz():
    V, F = grid()
    E = mesh_edges(F, len(V))
    m = np.random.default_rng(0).uniform(size=len(V)) * (V[:, 1] < 0.8)
    w = 0.4
    out = falloff_mask(m, vertices=V, edges=E, width=w)
    lengths = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)
    assert np.all(out >= m - 1e-12)
    assert np.all(np.abs(out[E[:, 0]] - out[E[:, 1]]) <= lengths / w + 1e-9)


def _blend_two_regions(falloff):
    V, F = grid()
    left = (V[:, 0] < 1.45).astype(float)
    right = 1.0 - left
    Wt = region_weights([left, right], vertices=V, faces=F, falloff=falloff)
    # Each region's result moves the whole mesh differently (in z and in y).
    A = V + np.array([0, 0, 1.0])
    B = V + np.array([0, 0.5, -0.5])
    out = blend_regions([A[None], B[None]], list(Wt[:-1]), V)[0]
    return V, F, Wt, out - V


def test_region_weights_sum_to_one_and_blend_without_seams():
    V, F, Wt, disp = _blend_two_regions([0.6, 0.6])
    np.testing.assert_allclose(Wt.sum(0), 1.0, atol=1e-12)
    assert np.all(Wt >= 0)
    E = mesh_edges(F, len(V))
    lengths = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)
    jump = np.linalg.norm(disp[E[:, 0]] - disp[E[:, 1]], axis=1)
    # Displacements differ by |A - B| = 1.66 at most; weights change by at most
    # 2 * length / w across an edge after normalisation.
    bound = 2 * lengths / 0.6 * np.linalg.norm([0, 0.5, 1.5])
    assert np.all(jump <= bound + 1e-9)
    assert jump.max() < 0.4
    # Without a falloff the same masks tear the mesh at the boundary.
    V, F, Wt0, disp0 = _blend_two_regions([0.0, 0.0])
    jump0 = np.linalg.norm(disp0[E[:, 0]] - disp0[E[:, 1]], axis=1)
    assert jump0.max() > 1.5


def test_separate_pupil_region_gets_no_bleed_from_the_face():
    V, F = grid()
    n = len(V)
    # A pupil: a separate quad shell in front of the grid, not connected to it.
    pupil = np.array([[1.0, 1.0, 0.2], [1.1, 1.0, 0.2], [1.1, 1.1, 0.2], [1.0, 1.1, 0.2]])
    V2 = np.concatenate([V, pupil])
    F2 = F + [[n, n + 1, n + 2, n + 3]]
    face = np.concatenate([(V[:, 1] > 0.5).astype(float), np.zeros(4)])
    eye = np.concatenate([np.zeros(n), np.ones(4)])
    Wt = region_weights([face, eye], vertices=V2, faces=F2, falloff=[1.0, 0.0])
    np.testing.assert_array_equal(Wt[0, n:], 0.0)  # geodesic: the shell is unreachable
    np.testing.assert_array_equal(Wt[1, n:], 1.0)
    assert Wt[0, :n][V[:, 1] > 0.5].min() == 1.0 and 0 < Wt[0, :n][np.isclose(V[:, 1], 0.3)].min() < 1


def test_falloff_needs_the_mesh():
    with pytest.raises(ValueError, match="falloff needs"):
        region_weights([np.ones(3)], falloff=[1.0])


def _similarity(s, theta, tx, ty):
    c, sn = s * np.cos(theta), s * np.sin(theta)
    return np.array([[c, -sn, tx], [sn, c, ty]])


@pytest.mark.parametrize("reference", [0, 2])
def test_head_motion_recovers_a_known_similarity(reference):
    rng = np.random.default_rng(1)
    X = rng.normal(size=(200, 3)) * [5, 6, 2] + [0, 1, 3]  # a character, y up
    heads = np.stack([_similarity(1.0, 0, 0, 0), _similarity(1.1, 0.2, 5, -3),
                      _similarity(0.9, -0.35, -12, 7), _similarity(1.05, 0.1, 2, 1)])
    k, P, c = 0.05, np.array([0.3, 1.0, 2.0]), np.array([160.0, 150.0])
    T = head_motion_transforms(heads, units_per_pixel=k, pivot=P, image_pivot=c, reference=reference)
    out = apply_transforms(T, np.broadcast_to(X, (4, *X.shape)))

    def project(Y):  # model (y up) -> reference-frame pixels (y down)
        return c + (Y[..., :2] - P[:2]) * [1, -1] / k

    rel = np.stack([np.vstack([h, [0, 0, 1]]) @ np.linalg.inv(np.vstack([heads[reference], [0, 0, 1]]))
                    for h in heads])[:, :2]
    # On screen the character moves exactly as the head did...
    np.testing.assert_allclose(project(out), apply_similarity(rel, np.broadcast_to(project(X), (4, 200, 2))),
                               atol=1e-9)
    # ...and the similarity fitted to it is the one we put in.
    fitted = fit_similarity(project(X), project(out), iterations=0)
    np.testing.assert_allclose(fitted, rel, atol=1e-9)
    # Uniform scale: depth about the pivot scales by s too; the reference frame is still.
    s = np.hypot(rel[:, 0, 0], rel[:, 1, 0])
    np.testing.assert_allclose(out[..., 2] - P[2], s[:, None] * (X[:, 2] - P[2]), atol=1e-9)
    np.testing.assert_allclose(out[reference], X, atol=1e-9)


def test_morph_targets_reproduce_the_region_blend():
    from retarget_cli.methods.blending import blend_keys, morph_targets, morph_weights

    rng = np.random.default_rng(2)
    V, F = grid(8, 6)
    n = len(V)
    keys = [V + rng.normal(size=(3, n, 3)) * 0.1, V + rng.normal(size=(2, n, 3)) * 0.1]
    W = [rng.uniform(0, 0.8, size=(5, 3)), rng.uniform(0, 0.8, size=(5, 2))]
    masks = region_weights([(V[:, 0] < 0.4) * 1.0, (V[:, 0] > 0.3) * 1.0], vertices=V, faces=F, falloff=[0.2, 0.2])[:-1]
    want = blend_regions([blend_keys(w, k) for w, k in zip(W, keys)], list(masks), V)
    D, mw = morph_targets(keys, masks, V), morph_weights(W)
    assert D.shape == (7, n, 3) and mw.shape == (5, 7)
    np.testing.assert_allclose(V[None] + np.einsum("tm,mnd->tnd", mw, D), want, atol=1e-12)
    # One region, no neutral: relative to the first key.
    D1 = morph_targets([keys[0]], None, keys[0][0])
    got = keys[0][0] + np.einsum("tm,mnd->tnd", morph_weights([W[0]]), D1)
    np.testing.assert_allclose(got, blend_keys(W[0], keys[0]), atol=1e-12)
