"""Posing a rig from landmarks: the delta transfer (rigpose.py) against the absolute fit."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from retarget_cli.methods.editing import auto_pose
from retarget_cli.methods.rig import BlendshapeRig
from retarget_cli.methods.rigpose import (
    delta_pose,
    fit_sliders,
    infer_exclusive,
    rig_curves,
    rig_region_masks,
    slider_owners,
)
from retarget_cli.synth.take import expression_curves, landmark_rig


def _rigs(seed=1, identity=0.08):
    """The synthetic landmark rig as the character, and an actor of another identity with the same expressions."""
    L = landmark_rig(seed=seed)
    character = BlendshapeRig(L["vertices"], L["deltas"], L["names"])
    rng = np.random.default_rng(seed)
    # Another face: larger (expressions in proportion) and of another shape (per-vertex offsets).
    V = 1.1 * L["vertices"] + identity * rng.standard_normal(L["vertices"].shape) * [1, 1, 0.3]
    actor = BlendshapeRig(V, 1.1 * L["deltas"], L["names"])
    return L, character, actor


def _observe(rig, vertices, curves, R, scale=140.0, shift=(150.0, 160.0)):
    return np.stack([scale * (rig.evaluate(c)[vertices] @ R.T)[:, :2] + shift for c in curves])


def test_delta_pose_recovers_sliders_across_identities_where_the_absolute_fit_does_not():
    L, character, actor = _rigs()
    v = L["landmark_vertices"]
    T = 120
    curves = expression_curves(T, seed=4)
    curves[0] = 0.0  # the actor's neutral frame
    R = Rotation.from_euler("xyz", [180 - 5, 8, 3], degrees=True).as_matrix()
    Y = _observe(actor, v, curves, R)
    keys = sorted(int(f) for f in np.argsort(-curves.sum(1))[:8])
    res = delta_pose(character, v, Y[0], Y[keys], sparsity=0.001, ridge=1e-5)
    delta_err = np.abs(res["w"] - curves[keys]).max()
    absolute = np.stack([auto_pose(character, v, Y[f])["w"] for f in keys])
    absolute_err = np.abs(absolute - curves[keys]).max()
    assert delta_err < 0.05, delta_err
    assert absolute_err > 3 * delta_err, (absolute_err, delta_err)
    # The neutral frame poses every slider at exactly 0; the absolute fit reads the other face as expression.
    neutral = delta_pose(character, v, Y[0], Y[:1])["w"][0]
    assert np.all(neutral == 0.0)
    assert auto_pose(character, v, Y[0])["w"].max() > 0.1


def test_delta_pose_follows_a_head_turn_with_rigid_points():
    L, character, actor = _rigs(identity=0.0)
    v = L["landmark_vertices"]
    curves = expression_curves(60, seed=2)
    curves[0] = 0.0
    R0 = Rotation.from_euler("xyz", [180, 0, 0], degrees=True)
    turn = Rotation.from_euler("y", 15, degrees=True)
    Y0 = _observe(actor, v, curves[:1], R0.as_matrix())[0]
    f = int(np.argmax(curves.sum(1)))
    Yf = _observe(actor, v, curves[f:f + 1], (R0 * turn).as_matrix())
    rigid = [27, 28, 29, 30, 31, 32, 33, 34, 35, 36, 39, 42, 45]
    with_pose = delta_pose(character, v, Y0, Yf, rigid=rigid, sparsity=0.001, ridge=1e-5)["w"][0]
    without = delta_pose(character, v, Y0, Yf, sparsity=0.001, ridge=1e-5)["w"][0]
    assert np.abs(with_pose - curves[f]).max() < 0.1
    assert np.abs(without - curves[f]).max() > 2 * np.abs(with_pose - curves[f]).max()


def test_fit_sliders_keeps_one_of_each_exclusive_pair():
    rng = np.random.default_rng(0)
    B = rng.standard_normal((40, 4))
    B[:, 1] = -B[:, 0] + 0.3 * rng.standard_normal(40)  # 0 and 1 nearly oppose each other
    m = B @ np.array([0.6, 0.0, 0.3, 0.0]) + 0.4 * rng.standard_normal(40)
    free = fit_sliders(B, m, 0.0, 1.0, sparsity=0.0, ridge=0.0)
    pair = fit_sliders(B, m, 0.0, 1.0, sparsity=0.0, ridge=0.0, exclusive=np.array([[0, 1]]))
    assert np.all(free >= 0) and np.all(free <= 1)
    assert min(pair[0], pair[1]) == 0.0 and max(pair[0], pair[1]) > 0.1
    # a larger L1 weight switches more sliders off
    assert np.count_nonzero(fit_sliders(B, m, 0.0, 1.0, sparsity=2.0)) < np.count_nonzero(free)
    # inferred from opposing landmark displacements: (L, 2, n) with n = 3, the first two opposed
    P = np.stack([B[:20, :3], B[20:, :3]], 1)
    assert infer_exclusive(P, ["a", "b", "c"]) == [("a", "b")]


def test_rig_curves_are_the_weighted_key_sliders_and_reproduce_the_key_blend():
    L, character, _ = _rigs()
    rng = np.random.default_rng(3)
    K = 5
    S = rng.uniform(0, 1, (K, character.n_sliders))
    S[0] = 0  # the neutral key
    W = rng.dirichlet(np.ones(K), size=30)  # delta formulation: whole-face weights summing to 1
    C = rig_curves([W], [S])
    np.testing.assert_allclose(C, W @ S)
    keys = character.evaluate(S)
    blend = np.einsum("tk,knc->tnc", W, keys)
    np.testing.assert_allclose(character.evaluate(C), blend, atol=1e-12)
    # clipping to the slider ranges
    assert rig_curves([W * 3], [S], character.lower, character.upper).max() <= 1.0


def test_slider_owners_and_masks_from_the_rig():
    L, character, _ = _rigs()
    v = L["landmark_vertices"]
    from retarget_cli.methods.rigpose import project, rig_landmarks

    _, DL = rig_landmarks(character, v)
    B = project(DL, np.eye(3))
    regions = [list(range(17, 27)) + list(range(36, 48)), list(range(48, 68))]
    owner = slider_owners(B, regions)
    names = list(character.names)
    for name, want in (("blink_l", 0), ("brow_raise", 0), ("jaw_open", 1), ("smile", 1)):
        if name in names:
            assert owner[names.index(name)] == want, name
    M = rig_region_masks(character, owner, 2)
    disp = np.abs(L["deltas"]).sum(axis=(0, 2)) > 0
    assert np.all(M[:, disp].sum(0) == pytest.approx(1.0))
    assert np.all(M[:, ~disp] == 0)
