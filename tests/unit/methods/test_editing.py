"""Direct manipulation (Lewis & Anjyo 2010) and selected motion attenuation (Lewis et al. 2005):
the papers' statements as assertions, on a synthetic rig whose shapes overlap."""

import numpy as np
import pytest
from scipy.optimize import lsq_linear
from scipy.spatial.transform import Rotation

from retarget_cli.errors import ShapeError
from retarget_cli.methods.editing import (
    AttenuateEdit,
    DirectManipulation,
    Pin,
    PinEdit,
    apply_edits,
    attenuate,
    attenuation_matrix,
    auto_pose,
    direct_manipulation,
    ease_profile,
    fit_orthographic,
)
from retarget_cli.methods.rig import BlendshapeRig
from retarget_cli.synth.take import expression_curves, landmark_rig, overlapping_rig


@pytest.fixture(scope="module")
def rig():
    r = overlapping_rig(n_shapes=24, grid=(24, 20), seed=0)
    return BlendshapeRig(r["vertices"], r["deltas"], r["names"])


def busy_vertices(rig, k):
    """The k vertices moved by the most shapes (interference is strongest there)."""
    D = rig.block(np.arange(3 * rig.n_vertices)).reshape(rig.n_vertices, 3, -1)
    count = (np.linalg.norm(D, axis=1) > 0.02).sum(1)
    return [int(v) for v in np.argsort(-count, kind="stable")[:k]]


def test_the_test_rig_has_overlapping_shapes(rig):
    v = busy_vertices(rig, 1)[0]
    assert np.count_nonzero(np.linalg.norm(rig.block(rig.rows([v])), axis=0)) >= 4


# --------------------------------------------------------------------------- direct manipulation


def test_pinned_vertex_reaches_a_reachable_target(rig):
    rng = np.random.default_rng(1)
    w0 = rng.uniform(0.2, 0.5, rig.n_sliders)
    w_goal = np.clip(w0 + rng.normal(0, 0.2, rig.n_sliders), 0, 1)
    v = busy_vertices(rig, 3)
    target = rig.evaluate(w_goal)[v]
    drag = np.linalg.norm(target - rig.evaluate(w0)[v])
    # soft constraints (eq. 2/3): the miss shrinks with alpha; the default meets them to 5 % of the drag
    miss = [np.linalg.norm(rig.evaluate(direct_manipulation(rig, v, target, w0, alpha=a))[v] - target)
            for a in (0.1, 0.01, 0.001)]
    assert miss[0] > miss[1] > miss[2]
    w = direct_manipulation(rig, v, target, w0)
    assert np.linalg.norm(rig.evaluate(w)[v] - target) < 0.05 * drag
    # with alpha -> 0 the pins are met to numerical precision
    w = direct_manipulation(rig, v, target, w0, alpha=1e-8, mu=0)
    assert np.linalg.norm(rig.evaluate(w)[v] - target) < 1e-4 * drag


def test_partial_constraints_use_only_the_given_axes(rig):
    v = busy_vertices(rig, 1)
    w0 = np.full(rig.n_sliders, 0.3)
    start = rig.evaluate(w0)[v]
    target = start + [[0.0, 0.05, 0.0]]
    w = direct_manipulation(rig, v, target + [[5.0, 0, 5.0]], w0, axes="y", alpha=1e-6, mu=0, bounded=False)
    assert abs(rig.evaluate(w)[v][0, 1] - target[0, 1]) < 1e-6  # x and z targets (wildly off) are ignored


def test_solve_picks_the_smallest_slider_change_among_pin_solutions(rig):
    """Lewis & Anjyo: 'we find the movement that causes the smallest change in sliders'."""
    rng = np.random.default_rng(2)
    w0 = rng.uniform(0.3, 0.6, rig.n_sliders)
    v = busy_vertices(rig, 1)
    rows = rig.rows(v)
    B = rig.block(rows)
    target = rig.evaluate(w0)[v] + rng.normal(0, 0.02, (1, 3))
    w = direct_manipulation(rig, v, target, w0, alpha=1e-9, mu=0, bounded=False)
    m = target.ravel() - rig.f0[rows]
    np.testing.assert_allclose(B @ w, m, atol=1e-6)  # satisfies the pin
    np.testing.assert_allclose(w - w0, np.linalg.pinv(B) @ (m - B @ w0), atol=1e-5)  # minimum-norm change
    null = np.linalg.svd(B)[2][B.shape[0]:]  # other solutions: add null-space directions
    for z in rng.normal(size=(20, null.shape[0])):
        other = w + 0.05 * z @ null
        np.testing.assert_allclose(B @ other, m, atol=1e-6)
        assert np.linalg.norm(other - w0) > np.linalg.norm(w - w0)


def test_a_single_pin_changes_many_sliders(rig):
    """Lewis & Anjyo, Fig. 6 / eq. 4: X = (B̄ᵀB̄ + αI)⁻¹B̄ᵀ is dense, so one pin moves many sliders."""
    v = busy_vertices(rig, 1)
    w0 = np.full(rig.n_sliders, 0.4)
    w = direct_manipulation(rig, v, rig.evaluate(w0)[v] + [[0.02, 0.02, 0.02]], w0, mu=0, bounded=False)
    moved = np.abs(w - w0) > 1e-3
    assert moved.sum() >= 4
    shapes_at_v = np.linalg.norm(rig.block(rig.rows(v)), axis=0) > 0
    np.testing.assert_array_equal(moved, shapes_at_v)  # exactly the sliders that touch the vertex


def test_closed_form_is_eq_4(rig):
    v = busy_vertices(rig, 2)
    B = rig.block(rig.rows(v))
    alpha = 0.1 * rig.scale**2
    w0 = np.full(rig.n_sliders, 0.5)
    target = rig.evaluate(w0)[v] + 0.03
    X = np.linalg.solve(B.T @ B + alpha * np.eye(rig.n_sliders), B.T)
    k = np.linalg.solve(B.T @ B + alpha * np.eye(rig.n_sliders), alpha * w0)
    m = target.ravel() - rig.f0[rig.rows(v)]
    w = direct_manipulation(rig, v, target, w0, alpha=0.1, mu=0, bounded=False)
    np.testing.assert_allclose(w, X @ m + k, atol=1e-10)


def test_bounds_hold_on_a_haphazard_drag_and_match_a_reference_qp(rig):
    """Lewis & Anjyo Fig. 5: an unreasonable drag; eq. 3 keeps 0 <= w <= t."""
    v = busy_vertices(rig, 2)
    w0 = np.full(rig.n_sliders, 0.5)
    target = rig.evaluate(w0)[v] + [[1.0, -1.0, 0.5], [-1.0, 0.8, 0.3]]  # far beyond what the rig can do
    free = direct_manipulation(rig, v, target, w0, bounded=False)
    assert free.min() < 0 or free.max() > 1  # the closed form leaves the slider range
    w = direct_manipulation(rig, v, target, w0)
    assert w.min() >= 0 and w.max() <= 1
    # same optimum as the full augmented least squares solved by scipy directly
    rows = rig.rows(v)
    a, mu = 0.01 * rig.scale**2, 0.001 * rig.scale**2
    A = np.vstack([rig.block(rows), np.sqrt(a) * np.eye(24), np.sqrt(mu) * np.eye(24)])
    b = np.concatenate([target.ravel() - rig.f0[rows], np.sqrt(a) * w0, np.zeros(24)])
    ref = lsq_linear(A, b, bounds=(0, 1), method="trf", tol=1e-14).x
    np.testing.assert_allclose(w, ref, atol=1e-6)


def test_per_pin_weights_favour_the_heavier_pin(rig):
    v = busy_vertices(rig, 2)
    w0 = np.full(rig.n_sliders, 0.5)
    target = rig.evaluate(w0)[v] + [[0.1, 0.0, 0.0], [-0.1, 0.0, 0.0]]  # conflicting neighbours
    err = []
    for weights in ([10.0, 1.0], [1.0, 10.0]):
        w = direct_manipulation(rig, v, target, w0, weights=weights)
        err.append(np.linalg.norm(rig.evaluate(w)[v] - target, axis=1))
    assert err[0][0] < err[0][1] and err[1][1] < err[1][0]


def test_bad_pins_are_clear_errors(rig):
    with pytest.raises(ShapeError, match=r"pins: vertex 480 is outside the mesh \(480 vertices"):
        DirectManipulation(rig, [0, 480])
    dm = DirectManipulation(rig, [0, 1])
    with pytest.raises(ShapeError, match=r"targets: expected shape \(2, 3\)"):
        dm.solve_targets(np.zeros((3, 3)), np.zeros(12))


# --------------------------------------------------------------------------- attenuation


def test_attenuation_with_alpha_to_zero_returns_w1(rig):
    W1 = np.random.default_rng(3).uniform(0, 1, (6, rig.n_sliders))
    W2 = attenuate(rig, W1, busy_vertices(rig, 3), alpha=1e-10)
    np.testing.assert_allclose(W2, W1, atol=1e-6)


def test_attenuation_with_large_alpha_holds_selected_and_frees_the_rest(rig):
    """Lewis et al. 2005 §5: large α keeps the selected coordinates still; the others keep most motion."""
    rng = np.random.default_rng(4)
    sel = busy_vertices(rig, 2)
    W1 = rng.uniform(0.2, 0.8, (8, rig.n_sliders))
    W2 = attenuate(rig, W1, sel, alpha=1e6)
    before = rig.evaluate(W1) - rig.neutral
    after = rig.evaluate(W2) - rig.neutral
    sel_ratio = np.linalg.norm(after[:, sel]) / np.linalg.norm(before[:, sel])
    rest = np.setdiff1d(np.arange(rig.n_vertices), sel)
    keep = np.linalg.norm(after[:, rest]) / np.linalg.norm(before[:, rest])
    assert sel_ratio < 0.05
    assert keep > 0.5


def test_attenuation_selects_axes_separately(rig):
    """Lewis et al. 2005 Fig. 4: only the y coordinates of two vertices are held."""
    sel = busy_vertices(rig, 2)
    W1 = np.full((1, rig.n_sliders), 0.7)
    W2 = attenuate(rig, W1, sel, axes="y", alpha=1e6)
    d1 = rig.evaluate(W1)[0, sel] - rig.neutral[sel]
    d2 = rig.evaluate(W2)[0, sel] - rig.neutral[sel]
    assert np.abs(d2[:, 1]).max() < 0.05 * np.abs(d1[:, 1]).max()
    assert np.abs(d2[:, [0, 2]]).max() > 0.2 * np.abs(d1[:, [0, 2]]).max()  # x, z still move


def test_default_alpha_is_unselected_over_selected_coordinates(rig):
    _, alpha = attenuation_matrix(rig, rig.rows([1, 2], "xy"))
    assert alpha == (3 * rig.n_vertices - 4) / 4
    M, _ = attenuation_matrix(rig, rig.rows([1, 2], "xy"), alpha=2.0)
    G = rig.gram()
    S = rig.block(rig.rows([1, 2], "xy"))
    P, Q = G - S.T @ S, S.T @ S
    np.testing.assert_allclose(M, np.linalg.solve(P + 2.0 * Q, P), atol=1e-8)  # eq. 3


def test_bounded_attenuation_stays_in_range(rig):
    W1 = np.random.default_rng(5).uniform(0.5, 1.0, (10, rig.n_sliders))
    sel = busy_vertices(rig, 5)
    free = attenuate(rig, W1, sel, alpha=1e4)
    assert free.min() < 0 or free.max() > 1
    W2 = attenuate(rig, W1, sel, alpha=1e4, bounded=True)
    assert W2.min() >= 0 and W2.max() <= 1


# --------------------------------------------------------------------------- batch edits


def test_ease_profile():
    s = ease_profile(np.arange(20), 5, 9, ease_in=3, ease_out=2)
    assert np.all(s[:2] == 0) and np.all(s[5:10] == 1) and np.all(s[12:] == 0)
    assert 0 < s[2] < s[3] < s[4] < 1 and 1 > s[10] > s[11] > 0


def test_pin_edit_over_a_frame_range_with_ease(rig):
    T = 30
    frames = np.arange(T)
    W = 0.3 + 0.2 * np.sin(np.linspace(0, 3, T))[:, None] * np.linspace(0.5, 1, rig.n_sliders)
    v = busy_vertices(rig, 1)[0]
    goal = rig.evaluate(W[15])[v] + [0.0, 0.02, 0.0]
    edit = PinEdit(frames=(10, 20), pins=[Pin(vertex=v, position=tuple(goal))], ease_in=3, ease_out=3, alpha=1e-4)
    out = apply_edits(rig, W, frames, [edit])
    np.testing.assert_array_equal(out[:7], W[:7])
    np.testing.assert_array_equal(out[24:], W[24:])
    drift = np.linalg.norm(rig.evaluate(W[10:21])[:, v] - goal, axis=1)
    err = np.linalg.norm(rig.evaluate(out[10:21])[:, v] - goal, axis=1)
    assert np.all(err < 0.05 * drift.max() + 1e-4)
    assert out.min() >= 0 and out.max() <= 1
    mid = np.linalg.norm(out[8] - W[8])
    assert 0 < mid < np.linalg.norm(out[10] - W[10]) + 1e-12  # fading in


def test_pin_to_another_vertex_and_attenuate_to_reference_frame(rig):
    T = 12
    frames = np.arange(100, 100 + T)
    W = np.linspace(0.1, 0.9, T)[:, None] * np.ones(rig.n_sliders)
    a = busy_vertices(rig, 1)[0]
    b = a + 24  # the grid neighbour above: a "lip seal" in y
    seal = PinEdit(frames=(103, 106), pins=[Pin(vertex=a, to_vertex=b, axes="y")], alpha=1e-6, mu=0)
    out = apply_edits(rig, W, frames, [seal])
    for t in range(3, 7):
        assert abs(rig.evaluate(out[t])[a, 1] - rig.evaluate(W[t])[b, 1]) < 1e-4
    hold = AttenuateEdit(frames=(102, 111), select=[([a], "xyz")], alpha=1e6)
    out = apply_edits(rig, W, frames, [hold])
    moved = np.linalg.norm(rig.evaluate(out[2:])[:, a] - rig.evaluate(W[2])[a], axis=1)
    free = np.linalg.norm(rig.evaluate(W[2:])[:, a] - rig.evaluate(W[2])[a], axis=1)
    assert moved.max() < 0.05 * free.max()


# --------------------------------------------------------------------------- auto-pose


def test_fit_orthographic_recovers_a_known_camera():
    X = np.random.default_rng(6).normal(size=(40, 3)) * [1, 1, 0.3]
    R = Rotation.from_euler("xyz", [180 + 10, -15, 5], degrees=True).as_matrix()
    Y = 120 * (X @ R.T)[:, :2] + [160, 150]
    s, R2, t = fit_orthographic(X, Y)
    assert abs(s - 120) < 1e-6 and np.abs(R2 - R).max() < 1e-6 and np.abs(t - [160, 150]).max() < 1e-6


def test_auto_pose_recovers_the_sliders_of_a_synthetic_animation():
    L = landmark_rig(seed=0)
    rig = BlendshapeRig(L["vertices"], L["deltas"], L["names"])
    curves = expression_curves(90, seed=3)
    R = Rotation.from_euler("xyz", [180 + 6, 10, -4], degrees=True).as_matrix()
    keys = [int(f) for f in np.argsort(-curves.sum(1))[:5]]
    for f in keys:
        Y = 150 * (rig.evaluate(curves[f])[L["landmark_vertices"]] @ R.T)[:, :2] + [160, 170]
        res = auto_pose(rig, L["landmark_vertices"], Y)
        assert np.abs(res["w"] - curves[f]).max() < 0.01, f
        assert res["rms"] < 0.05 and abs(res["scale"] - 150) < 0.5
