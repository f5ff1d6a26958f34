"""Posing a rig from landmarks: the delta transfer (rigpose.py) against the absolute fit."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from retarget_cli.methods.editing import auto_pose
from retarget_cli.methods.rig import BlendshapeRig
from retarget_cli.methods.rigpose import (
    CONTACT_68,
    DEFAULT_LID_CLOSED,
    DEFAULT_LIP_CLOSED,
    FRONT_68,
    LID_CLOSED_FRACTION,
    NEUTRAL_OPEN,
    contact_ratios,
    contact_references,
    delta_pose,
    fit_sliders,
    frontal_rotation,
    infer_exclusive,
    lid_antagonists,
    lid_closed_reading,
    project,
    rig_curves,
    rig_region_masks,
    slider_owners,
    take_lid_closed,
)
from retarget_cli.synth.take import expression_curves, landmark_rig, source_neutral


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


# --------------------------------------------------------------------------- contact (issue 27)

LOWER_OUTER, CHIN = [55, 56, 57, 58, 59], [6, 7, 8, 9, 10]
UPPER_INNER, LOWER_INNER, UPPER_OUTER = [61, 62, 63], [65, 66, 67], [49, 50, 51, 52, 53]
MOUTH = list(range(48, 68)) + CHIN
PAIRS = ((61, 67), (62, 66), (63, 65))


def _mouth_rig():
    """68 landmark vertices (the synthetic source face, y up) and three mouth shapes that part or cross the
    lips in combination: mouthShrugLower raises the lower lip and chin, its inner edge furthest (alone it
    crosses the lips), mouthRollUpper raises the upper lip (alone it parts them), jawOpen lowers the jaw."""
    n = source_neutral()
    V = np.column_stack([n[:, 0], -n[:, 1], np.zeros(68)])
    up = np.array([0.0, 1.0, 0.0])
    D = np.zeros((3, 68, 3))
    D[0, LOWER_OUTER + CHIN] = 0.03 * up
    D[0, LOWER_INNER] = 0.045 * up
    D[1, UPPER_INNER] = 0.03 * up
    D[1, UPPER_OUTER] = 0.01 * up
    D[2, LOWER_OUTER + LOWER_INNER + CHIN] = -0.08 * up
    return BlendshapeRig(V, D, ["mouthShrugLower", "mouthRollUpper", "jawOpen"]), V


def _lip_gap(rig, w) -> float:
    """The posed rig's mean inner-lip gap / mouth width, seen from the front (y down the image)."""
    X = rig.evaluate(w)
    gap = np.mean([X[up, 1] - X[lo, 1] for up, lo in PAIRS])
    return float(gap / np.linalg.norm(X[54] - X[48]))


def test_a_closed_lip_pout_keeps_the_lips_closed_on_a_rig_whose_shapes_cross_them_in_combination():
    rig, V = _mouth_rig()
    Y0 = 140.0 * source_neutral() + [150.0, 160.0]
    Yk = Y0.copy()  # a pout with closed lips: lower lip, chin and both inner lips rise together
    Yk[LOWER_OUTER + CHIN + LOWER_INNER + UPPER_INNER, 1] -= 140.0 * 0.03
    Y = np.stack([Y0, Yk])
    rest = _lip_gap(rig, np.zeros(3))
    kw = dict(regions={"mouth": MOUTH}, sparsity=0.0, ridge=1e-6, contact=CONTACT_68, front=FRONT_68)
    plain = delta_pose(rig, np.arange(68), Y0, Yk[None], contact_weight=0.0, **kw)["w"][0]
    assert _lip_gap(rig, plain) - rest < -0.02  # the plain delta fit crosses the lips (the stack of issue 27)
    refs = contact_references(Y, CONTACT_68)
    w = delta_pose(rig, np.arange(68), Y0, Yk[None], contact_refs=refs, **kw)["w"][0]
    assert abs(_lip_gap(rig, w) - rest) <= 0.0075 + 1e-6  # closed: within the contact tolerance of the rest gap
    assert w[0] > 0.3  # still a pout: the lower lip rises
    # lips parted on the actor part on the character by as much of the mouth width
    Yo = Y0.copy()
    Yo[LOWER_INNER + LOWER_OUTER + CHIN, 1] += 140.0 * 0.05
    wo = delta_pose(rig, np.arange(68), Y0, Yo[None], contact_refs=refs, **kw)["w"][0]
    opening = (np.mean(contact_ratios(Yo, CONTACT_68[0])) - np.mean(refs[0])) - DEFAULT_LIP_CLOSED
    assert abs((_lip_gap(rig, wo) - rest) - opening) < 0.01


def test_heavy_extra_rows_do_not_raise_the_sparsity_price_of_the_landmark_fit():
    """The contact gap rows are boosted up to CONTACT_BOOST ** CONTACT_PASSES; the sparsity and ridge terms are
    scaled by the landmark rows alone (scale_rows), or a boosted gap row on one slider prices every other slider
    out of the fit: on d9's pursed lips the ICT pucker stayed at 0 (issue 27)."""
    B = np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 1.0]])  # two landmark rows, then a gap row on slider 1 only
    m = np.array([0.5, 0.0, 0.0])
    weights = np.array([1.0, 1.0, 4.0 * 8.0**4])
    lo, hi = np.zeros(2), np.ones(2)
    scaled = fit_sliders(B, m, lo, hi, weights=weights, sparsity=0.01, ridge=0.0, scale_rows=2)
    assert scaled[0] == pytest.approx(0.5 - 0.01, abs=1e-6)  # priced by the landmarks' h̄ = 1
    everything = fit_sliders(B, m, lo, hi, weights=weights, sparsity=0.01, ridge=0.0)
    assert everything[0] == 0.0  # h̄ over every row: the gap row's weight zeroes slider 0


def _blink_rig(n):
    """A 68-vertex rig of *n* (source_neutral) with one slider, eyeBlink_R: the upper lid onto the lower one."""
    V = np.column_stack([n[:, 0], -n[:, 1], np.zeros(68)])
    D = np.zeros((1, 68, 3))
    for up, lo in ((37, 41), (38, 40)):
        D[0, up, 1] = V[lo, 1] - V[up, 1]
    return BlendshapeRig(V, D, ["eyeBlink_R"])


def test_lids_the_tracker_never_shuts_close_the_rig_eye():
    n = source_neutral()
    rig = _blink_rig(n)
    Y0 = 140.0 * n + [150.0, 160.0]
    T = 40
    Y = np.repeat(Y0[None], T, axis=0)
    width = np.linalg.norm(Y0[39] - Y0[36])
    closed = list(range(20, 24))  # the tracker's closed lids keep a gap of 0.1 of the eye width
    for up, lo in ((37, 41), (38, 40)):
        Y[closed, up, 1] = Y0[lo, 1] - 0.1 * width
    kw = dict(regions={"eye": list(range(36, 42))}, sparsity=0.0, ridge=1e-6, contact=CONTACT_68, front=FRONT_68)
    plain = delta_pose(rig, np.arange(68), Y0, Y, contact_weight=0.0, **kw)["w"][:, 0]
    w = delta_pose(rig, np.arange(68), Y0, Y, **kw)["w"][:, 0]
    assert plain[closed].max() < 0.8  # the delta fit follows the tracker: the character's eye stays open
    assert w[closed].min() > 0.95 and np.abs(np.delete(w, closed)).max() < 0.01


def test_contact_references_are_the_takes_closed_lips_and_open_eyes():
    lips, eye = CONTACT_68[0], CONTACT_68[1]
    n = 140.0 * source_neutral()
    rng = np.random.default_rng(0)
    T = 200
    Y = np.repeat(n[None], T, axis=0) + 0.2 * rng.standard_normal((T, 68, 2))
    open_ = np.arange(T) % 3 == 0  # a third of the frames talk: the lower lip drops by 0.1 of the mouth width
    Y[np.ix_(open_, [65, 66, 67], [1])] += 0.1 * np.linalg.norm(n[54] - n[48])
    refs = contact_references(Y, CONTACT_68)
    np.testing.assert_allclose(refs[0], contact_ratios(n, lips), atol=0.01)  # the cluster of closed lips
    # the open eye: the take's 75th percentile, or the neutral frame's unless that is nearer closed than open
    r = contact_ratios(Y, eye).mean(axis=1)
    p75 = np.percentile(r, 75)
    assert refs[1][0] == pytest.approx(p75)
    for shift, own in ((3.0, True), (-0.5, True), (-5.0, False)):  # wider, a little narrower, squinting
        neutral = n.copy()
        neutral[[37, 38], 1] -= shift
        r_n = contact_ratios(neutral, eye).mean()
        assert contact_references(Y, CONTACT_68, neutral=neutral)[1][0] == pytest.approx(r_n if own else p75)
        r_c = take_lid_closed(Y, CONTACT_68)  # by default the take's: a fraction of its open eyes' reading
        assert (r_n >= r_c + NEUTRAL_OPEN * (p75 - r_c)) == own
    assert DEFAULT_LID_CLOSED is None
    opens = [np.percentile(contact_ratios(Y, e).mean(axis=1), 75) for e in CONTACT_68[1:]]
    assert take_lid_closed(Y, CONTACT_68) == pytest.approx(LID_CLOSED_FRACTION * np.mean(opens))
    assert take_lid_closed(Y, CONTACT_68[:1]) is None  # no lids
    assert lid_closed_reading(0.15, p75) == 0.15  # a number is the closed reading itself
    assert lid_closed_reading(None, p75) == pytest.approx(LID_CLOSED_FRACTION * p75)


def test_the_closed_reading_is_relative_to_the_actors_open_eye():
    """A 68-point tracker reads closed lids at about a third of the open eye, whatever the eye's size: a blink
    at 0.3 of the open reading closes the character's eye, narrowed eyes at 0.6 of it (a smile) stay open in
    part, for a large and a small eye alike; an absolute lid_closed keeps its meaning."""
    n = source_neutral()
    rig = _blink_rig(n)
    eye = CONTACT_68[1]
    kw = dict(regions={"eye": list(range(36, 42))}, sparsity=0.0, ridge=1e-6, contact=CONTACT_68, front=FRONT_68)
    blink, narrow = list(range(20, 24)), list(range(40, 46))
    for aperture in (1.0, 0.8):  # the actor's open eye as the synthetic face's, and a smaller one
        Y0 = 140.0 * n + [150.0, 160.0]
        for up, lo in ((37, 41), (38, 40), (43, 47), (44, 46)):  # both eyes
            Y0[up, 1] = Y0[lo, 1] - aperture * (Y0[lo, 1] - Y0[up, 1])
        r_o = contact_ratios(Y0, eye).mean()
        Y = np.repeat(Y0[None], 60, axis=0)
        for rows, f in ((blink, 0.3), (narrow, 0.6)):
            for up, lo in ((37, 41), (38, 40)):
                Y[rows, up, 1] = Y0[lo, 1] - f * (Y0[lo, 1] - Y0[up, 1])
        assert contact_ratios(Y[narrow[0]], eye).mean() == pytest.approx(0.6 * r_o, rel=0.01)
        w = delta_pose(rig, np.arange(68), Y0, Y, **kw)["w"][:, 0]
        assert w[blink].min() > 0.95  # closed
        assert 0.3 < w[narrow].max() < 0.85  # narrowed, not shut
        assert np.abs(np.delete(w, blink + narrow)).max() < 0.01
        shut = delta_pose(rig, np.arange(68), Y0, Y, lid_closed=0.65 * r_o, **kw)["w"][:, 0]
        assert shut[narrow].min() > 0.95  # at or below an absolute lid_closed the eye is shut


def test_frontal_rotation_snaps_to_the_rig_files_axes():
    n = source_neutral()
    V = np.column_stack([n[:, 0], -n[:, 1], 0.3 * (1 - n[:, 1])])  # the chin in front of the eyes (a 10°+ tilt)
    np.testing.assert_allclose(frontal_rotation(V, *FRONT_68), np.diag([1.0, -1.0, -1.0]))
    turned = V @ Rotation.from_euler("y", 90, degrees=True).as_matrix().T  # a rig facing +x
    R = frontal_rotation(turned, *FRONT_68)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose((turned @ R.T)[:, :2], (V @ np.diag([1.0, -1.0, -1.0]))[:, :2], atol=1e-12)


def test_smoothing_across_frames_removes_jitter_and_keeps_a_three_frame_blink():
    n = source_neutral()
    V = np.column_stack([n[:, 0], -n[:, 1], np.zeros(68)])
    D = np.zeros((2, 68, 3))
    for up, lo in ((37, 41), (38, 40)):
        D[0, up, 1] = V[lo, 1] - V[up, 1]  # eyeBlink_R
    D[1, [17, 18, 19, 20, 21], 1] = 0.05  # browOuterUp_R
    rig = BlendshapeRig(V, D, ["eyeBlink_R", "browOuterUp_R"])
    rng = np.random.default_rng(3)
    T = 90
    truth = np.zeros((T, 2))
    truth[:, 1] = 0.4 + 0.3 * np.sin(np.arange(T) / 9.0)
    truth[44:47, 0] = [0.6, 1.0, 0.6]  # a three-frame blink
    X = np.stack([rig.evaluate(c) for c in truth])
    Y = 140.0 * np.stack([X[:, :, 0], -X[:, :, 1]], axis=2) + [150.0, 160.0] + 0.4 * rng.standard_normal((T, 68, 2))
    Y0 = 140.0 * np.column_stack([V[:, 0], -V[:, 1]]) + [150.0, 160.0]
    kw = dict(regions={"brows-eye": list(range(17, 22)) + list(range(36, 42))}, sparsity=0.0, ridge=1e-6,
              contact_weight=0.0)
    each = delta_pose(rig, np.arange(68), Y0, Y, **kw)["w"]
    smooth = delta_pose(rig, np.arange(68), Y0, Y, smooth=1.0, **kw)["w"]
    calm = np.ones(T - 2, bool)
    calm[40:50] = False

    def jitter(W):
        return np.abs(W[2:] - 2 * W[1:-1] + W[:-2])[calm].mean()

    assert jitter(smooth) < 0.5 * jitter(each)
    assert np.abs(smooth - truth)[1:-1][calm].mean() < np.abs(each - truth)[1:-1][calm].mean()
    assert smooth[45, 0] > 0.9 and smooth[45, 0] > each[45, 0] - 0.05  # the blink keeps its amplitude
    # without the event release the same penalty flattens it
    flat = delta_pose(rig, np.arange(68), Y0, Y, smooth=1.0, smooth_robust=0.0, **kw)["w"]
    assert flat[45, 0] < smooth[45, 0] - 0.1


def test_an_eye_the_fit_sees_shifted_is_not_explained_by_an_opener_and_a_closer_at_once():
    n = source_neutral()
    V = np.column_stack([n[:, 0], -n[:, 1], np.zeros(68)])
    up = np.array([0.0, 1.0, 0.0])
    D = np.zeros((3, 68, 3))
    D[0, [37, 38]] = 0.02 * up        # eyeWide_R: the upper lid up
    D[1, [40, 41]] = 0.02 * up        # eyeSquint_R: the lower lid up
    D[2, [17, 18, 19, 20, 21]] = 0.03 * up  # browOuterUp_R: no lid
    rig = BlendshapeRig(V, D, ["eyeWide_R", "eyeSquint_R", "browOuterUp_R"])
    R = frontal_rotation(V, *FRONT_68)
    pairs = lid_antagonists(V @ R[:2].T, project(D.transpose(1, 2, 0), R), CONTACT_68, rig.lower, rig.upper)
    assert pairs.tolist() == [[0, 1]]
    Y0 = 140.0 * n + [150.0, 160.0]
    Yk = Y0.copy()
    Yk[[37, 38, 40, 41], 1] -= 140.0 * 0.015  # both lids up by as much: the eye moved, it did not open or close
    kw = dict(regions={"eye": list(range(17, 22)) + list(range(36, 42))}, sparsity=0.0, ridge=1e-6,
              contact=CONTACT_68, front=FRONT_68)
    stacked = delta_pose(rig, np.arange(68), Y0, Yk[None], contact_weight=0.0, **kw)["w"][0]
    assert min(stacked[0], stacked[1]) > 0.5  # the plain fit stacks the opener and the closer
    w = delta_pose(rig, np.arange(68), Y0, Yk[None], contact_refs=contact_references(np.stack([Y0, Yk]), CONTACT_68),
                   **kw)["w"][0]
    assert min(w[0], w[1]) == 0.0


def test_an_open_eyes_lid_noise_is_not_a_blink():
    n = source_neutral()
    rig = _blink_rig(n)
    Y0 = 140.0 * n + [150.0, 160.0]
    T = 60
    Y = np.repeat(Y0[None], T, axis=0)
    width = np.linalg.norm(Y0[39] - Y0[36])
    Y[:, [37, 38], 1] += np.random.default_rng(1).uniform(0, 0.02 * width, (T, 1))  # the lid jitters down 0-2 %
    kw = dict(regions={"eye": list(range(36, 42))}, sparsity=0.0, ridge=1e-6, contact=CONTACT_68, front=FRONT_68)
    w = delta_pose(rig, np.arange(68), Y0, Y, **kw)["w"][:, 0]
    plain = delta_pose(rig, np.arange(68), Y0, Y, contact_weight=0.0, **kw)["w"][:, 0]
    assert w.max() < 0.02 < plain.max()  # held open (LID_DEADBAND); the plain delta fit follows the noise


def test_batched_slider_qps_match_one_frame_at_a_time():
    """delta_pose solves each step's QPs for many frames at once (_slider_qps); each frame's answer, exclusive pairs
    included, is _slider_qp's for that frame alone."""
    from retarget_cli.methods.rigpose import _slider_qp, _slider_qps

    rng = np.random.default_rng(4)
    T, r, n = 40, 30, 9
    A = rng.normal(size=(T, r, n))
    b = rng.normal(size=(T, r)) * 2
    CW = rng.uniform(0.0, 1.0, size=(T, r))
    CW[3] = 0.0  # a frame whose rows weigh nothing
    lo, hi = np.r_[-1.0, np.zeros(n - 1)], np.ones(n)
    free = np.ones(n, bool)
    free[5] = False
    pairs = np.array([[1, 2], [3, 4], [2, 6]])
    w, H, q, F = _slider_qps(A, b, lo, hi, CW, sparsity=0.01, ridge=0.001, exclusive=pairs, free=free,
                             scale_rows=20)
    dropped = 0
    for k in range(T):
        wk, Hk, qk, Fk = _slider_qp(A[k], b[k], lo, hi, weights=CW[k], sparsity=0.01, ridge=0.001, exclusive=pairs,
                                    free=free, scale_rows=20)
        np.testing.assert_allclose(w[k], wk, rtol=0, atol=1e-10)
        assert np.array_equal(F[k], Fk) and (H[k] is None) == (Hk is None)
        if Hk is not None:
            np.testing.assert_allclose(H[k], Hk, rtol=1e-12)
            np.testing.assert_allclose(q[k], qk, rtol=1e-12)
        dropped += int((~Fk & free).sum())
    assert H[3] is None and not F[3].any() and dropped > 0  # the exclusive pairs were exercised


def test_a_slider_owned_by_one_region_does_not_move_another_regions_landmarks_for_free():
    # A VRM-style "angry": it closes the eye's lids (its region) and parts the lips a little (another region's
    # points); "squint" closes the lids alone, to 90 % of angry's travel. The actor's lids travel as far as
    # angry's and the lips stay closed. Fitted on the eye's landmarks only, angry wins and the character's lips
    # part; with the other regions' landmarks as rows of target 0, the squint does most of the work.
    n = source_neutral()
    V = np.column_stack([n[:, 0], -n[:, 1], np.zeros(68)])
    D = np.zeros((2, 68, 3))
    for up, lo in ((37, 41), (38, 40)):
        D[:, up, 1] = 0.6 * (V[lo, 1] - V[up, 1])
    D[1, [37, 38], 1] *= 0.9
    part = 0.2 * abs(D[0, 37, 1])  # the rig's y is up: the upper lip rises
    D[0, [61, 62, 63], 1] = part
    D[0, [65, 66, 67], 1] = -part
    rig = BlendshapeRig(V, D, ["angry", "eyeSquint_R"])
    Y0 = 140.0 * n + [150.0, 160.0]
    T = 6
    X = np.stack([rig.evaluate(np.array([1.0, 0.0]))] * T)
    Y = 140.0 * np.stack([X[:, :, 0], -X[:, :, 1]], axis=2) + [150.0, 160.0]
    Y[:, 60:68] = Y0[60:68]  # ... with closed lips
    kw = dict(regions={"eye": list(range(36, 42)), "mouth": list(range(48, 68))}, sparsity=0.01, ridge=1e-6,
              contact_weight=0.0)
    alone = delta_pose(rig, np.arange(68), Y0, Y, spill=0.0, **kw)
    fit = delta_pose(rig, np.arange(68), Y0, Y, **kw)
    assert list(alone["owner"]) == [0, 0]  # both sliders belong to the eye

    def lip_gap(W):  # the inner lips' parting from rest
        return np.array([((rig.evaluate(w) - V)[[61, 62, 63], 1] - (rig.evaluate(w) - V)[[67, 66, 65], 1]).mean()
                         for w in W])

    def lid_travel(W):
        return np.array([(rig.evaluate(w) - V)[[37, 38], 1].mean() / D[0, [37, 38], 1].mean() for w in W])

    assert lip_gap(alone["w"]).min() > 1.8 * part  # eye-only rows: angry at ~1, the lips part
    assert lip_gap(fit["w"]).max() < 0.6 * part  # other regions' rows: the lips stay nearly closed ...
    assert lid_travel(fit["w"]).min() > 0.85  # ... and the lids still close (the squint does it)


def test_a_slider_owned_by_the_eyes_does_not_part_closed_lips_it_moves_by_a_few_pixels(monkeypatch):
    # A stylised face (the mouth a third of its size) and a VRM-style "angry" that lowers the brows, closes the
    # lids and parts the small lips by 0.3 of their width; "eyeSquint" closes the lids alone, to 80 % of angry's
    # travel. The actor lowers the brows and closes the lids as angry does, lips closed. Both sliders are the
    # eyes'; on landmarks alone the lips' parting is a few pixels, cheaper than the brows' miss, so angry wins
    # and the character's lips part: the lips' gap must be a row of the eyes' fit too (SPILL_GAP_CHANGE).
    import retarget_cli.methods.rigpose as rigpose

    n = source_neutral()
    V = np.column_stack([n[:, 0], -n[:, 1], np.zeros(68)])
    c = V[48:68].mean(axis=0)
    V[48:68] = c + 0.3 * (V[48:68] - c)
    width = float(np.linalg.norm(V[54] - V[48]))
    D = np.zeros((2, 68, 3))
    for up, lo in ((37, 41), (38, 40), (43, 47), (44, 46)):
        D[:, up, 1] = 0.6 * (V[lo, 1] - V[up, 1])
    D[1, [37, 38, 43, 44], 1] *= 0.8
    D[0, 17:27, 1] = -0.5 * abs(D[0, 37, 1])
    D[0, [61, 62, 63], 1] = 0.15 * width
    D[0, [65, 66, 67], 1] = -0.15 * width
    rig = BlendshapeRig(V, D, ["angry", "eyeSquint"])
    Y0 = 140.0 * V[:, :2] * [1, -1] + [150.0, 160.0]
    X = np.stack([rig.evaluate(np.array([1.0, 0.0]))] * 6)
    Y = 140.0 * X[:, :, :2] * [1, -1] + [150.0, 160.0]
    Y[:, 48:68] = Y0[48:68]  # ... with closed lips
    kw = dict(regions={"brows-eyes": list(range(17, 27)) + list(range(36, 48)), "mouth": list(range(48, 68))},
              contact=CONTACT_68, front=FRONT_68)

    def lip_gap(W):  # the inner lips' parting from rest, / the mouth's width
        d = [rig.evaluate(w) - V for w in W]
        return np.array([(x[[61, 62, 63], 1] - x[[67, 66, 65], 1]).mean() / width for x in d])

    def lid_travel(W):
        return np.array([(rig.evaluate(w) - V)[[37, 38, 43, 44], 1].mean() / D[0, [37, 38, 43, 44], 1].mean()
                         for w in W])

    fit = delta_pose(rig, np.arange(68), Y0, Y, **kw)
    assert list(fit["owner"]) == [0, 0]
    monkeypatch.setattr(rigpose, "SPILL_GAP_CHANGE", np.inf)  # no foreign gap rows: the landmarks' spill alone
    alone = delta_pose(rig, np.arange(68), Y0, Y, **kw)
    assert lip_gap(alone["w"]).min() > 0.1  # angry carries the lids and brows: the lips part
    assert lip_gap(fit["w"]).max() < DEFAULT_LIP_CLOSED  # the lips' gap as a row: they stay closed ...
    assert lid_travel(fit["w"]).min() > 0.69 and lid_travel(alone["w"]).min() > 0.69  # ... the lids close alike


def test_noise_a_rig_can_follow_is_smoothed_not_taken_for_an_event():
    # Two sliders per brow point: the per-frame fits follow the tracker's noise there, so their residual is far
    # below it and any smoothing's excess over it looked like a fast event (every frame released: the noise
    # kept). With the take's noise as the floor (smooth_noise) the brows are smoothed, and the blink keeps its
    # amplitude.
    n = source_neutral()
    V = np.column_stack([n[:, 0], -n[:, 1], np.zeros(68)])
    brows = [17, 18, 19, 20, 21]
    D = np.zeros((1 + 2 * len(brows), 68, 3))
    for up, lo in ((37, 41), (38, 40)):
        D[0, up, 1] = V[lo, 1] - V[up, 1]  # eyeBlink_R
    for j, p in enumerate(brows):
        D[1 + 2 * j, p, 0] = 0.05  # one brow point sideways
        D[2 + 2 * j, p, 1] = 0.05  # and up
    rig = BlendshapeRig(V, D, ["eyeBlink_R"] + [f"brow{p}{c}" for p in brows for c in "xy"])
    rng = np.random.default_rng(5)
    T = 90
    truth = np.zeros((T, 1 + 2 * len(brows)))
    truth[:, 1:] = 0.5 + 0.2 * np.sin(np.arange(T)[:, None] / 9.0 + np.arange(2 * len(brows)))
    truth[44:47, 0] = [0.6, 1.0, 0.6]  # a three-frame blink
    X = np.stack([rig.evaluate(c) for c in truth])
    Y = 140.0 * np.stack([X[:, :, 0], -X[:, :, 1]], axis=2) + [150.0, 160.0] + 0.6 * rng.standard_normal((T, 68, 2))
    Y0 = 140.0 * np.column_stack([V[:, 0], -V[:, 1]]) + [150.0, 160.0]
    kw = dict(regions={"brows-eye": brows + list(range(36, 42))}, sparsity=0.0, ridge=1e-6, contact=CONTACT_68,
              front=FRONT_68, smooth=1.0)
    old = delta_pose(rig, np.arange(68), Y0, Y, smooth_noise=False, **kw)["w"]
    new = delta_pose(rig, np.arange(68), Y0, Y, **kw)["w"]
    calm = np.ones(T - 2, bool)
    calm[40:50] = False

    def jitter(W):
        return np.abs(W[2:, 1:] - 2 * W[1:-1, 1:] + W[:-2, 1:])[calm].mean()

    assert jitter(new) < 0.6 * jitter(old)
    assert np.abs(new - truth)[:, 1:].mean() < np.abs(old - truth)[:, 1:].mean()
    assert new[45, 0] > 0.9  # the blink keeps its amplitude


def test_the_takes_tracking_noise_is_its_landmarks_jitter_not_its_blinks():
    from retarget_cli.methods.rigpose import tracking_noise

    rng = np.random.default_rng(0)
    T = 600
    truth = np.zeros((T, 3, 2))
    truth[:, :, 0] = 50.0 * np.sin(np.arange(T) / 40.0)[:, None]  # smooth motion
    for t in range(20, T, 60):
        truth[t:t + 3, 1, 1] += [6.0, 10.0, 6.0]  # a blink every two seconds
    P = (truth + rng.normal(0.0, [[0.3, 0.3], [0.6, 0.6], [1.2, 1.2]], (T, 3, 2))).astype(np.float32)
    P[300] = np.nan  # a lost frame
    sigma = tracking_noise(P)
    np.testing.assert_allclose(sigma, [[0.3, 0.3], [0.6, 0.6], [1.2, 1.2]], rtol=0.15)
