"""The rest pose found in a take (retarget_cli/methods/neutral.py): issue 27, item 2."""

import numpy as np
import pytest

from retarget_cli.methods.neutral import align_shape, face_openings, find_rest_frame, nearest_frame, rest_shape
from retarget_cli.synth.take import EXPRESSIONS, expression_curves, place_neutral, source_deltas, source_neutral

E = {n: i for i, n in enumerate(EXPRESSIONS)}


def landmarks_of(curves, *, size=(320, 320), noise=0.3, seed=0):
    """Stabilized 68-point landmarks (T, 68, 2) of the synthetic face at *curves*, with tracker-like noise."""
    norm = source_neutral()[None] + np.einsum("te,eld->tld", curves, source_deltas())
    P = place_neutral(size)
    stab = norm @ P[:, :2].T + P[:, 2]
    return stab + noise * np.random.default_rng(seed).standard_normal(stab.shape)


def smiling_start(T=150, seed=3, frames=30):
    """Expression curves whose first *frames* frames smile (released over 6 frames)."""
    curves = expression_curves(T, seed=seed)
    ramp = np.clip((frames + 6 - np.arange(T)) / 6.0, 0.0, 1.0)
    curves[:, E["smile"]] = np.maximum(curves[:, E["smile"]], ramp)
    return curves


def test_a_take_whose_first_30_frames_smile_rests_after_them():
    curves = smiling_start()
    at_rest = curves.max(axis=1) < 0.02
    assert not at_rest[:30].any() and at_rest.sum() > 10  # the take does rest, later
    choice = find_rest_frame(landmarks_of(curves), np.ones((len(curves), 68)))
    assert choice.at_rest and at_rest[choice.frame], (choice.frame, curves[choice.frame].round(2))
    assert "lips closed" in choice.reason and f"frame {choice.frame}" in choice.reason
    # the rest shape is the mean of rest frames: nearer the true neutral than any single noisy frame
    truth = landmarks_of(np.zeros((1, len(EXPRESSIONS))), noise=0.0)[0]
    assert curves[choice.members].max() < 0.1
    err = np.linalg.norm(choice.shape - truth, axis=1).mean()
    single = np.linalg.norm(landmarks_of(curves)[choice.frame] - truth, axis=1).mean()
    assert err < 0.5 * single, (err, single)


def test_blinks_open_mouths_and_low_confidence_frames_are_not_rest():
    T = 120
    curves = np.zeros((T, len(EXPRESSIONS)))
    curves[:, E["jaw_open"]] = 0.8  # the mouth open everywhere but frames 60-79
    curves[60:80, E["jaw_open"]] = 0.0
    curves[60:70, E["blink_l"]] = curves[60:70, E["blink_r"]] = 1.0  # ... where the eyes blink at first
    conf = np.ones((T, 68))
    conf[70:76] = 0.2  # and the tracker is unsure for a while
    choice = find_rest_frame(landmarks_of(curves), conf)
    assert 76 <= choice.frame < 80, choice.frame
    with pytest.raises(ValueError, match="candidates"):
        find_rest_frame(landmarks_of(curves), conf, candidates=[T])
    assert find_rest_frame(landmarks_of(curves), conf, candidates=[0, 5, 62]).frame == 62


def test_a_take_without_a_rest_frame_takes_the_least_open_mouth_and_says_so():
    T = 90
    curves = np.zeros((T, len(EXPRESSIONS)))
    curves[:, E["jaw_open"]] = 0.6 + 0.3 * np.sin(np.arange(T) / 7.0) ** 2
    choice = find_rest_frame(landmarks_of(curves, noise=0.1), None)
    assert not choice.at_rest and "no frame of the take has the lips closed" in choice.reason
    assert curves[choice.frame, E["jaw_open"]] < 0.62
    assert face_openings(landmarks_of(curves[choice.frame:choice.frame + 1], noise=0))["lip_gap"][0] > 0.05


def test_another_layout_takes_the_most_common_shape():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(20, 2)) * 40 + 200, rng.normal(size=(20, 2)) * 40 + 200
    P = np.concatenate([np.repeat(b[None], 35, 0), np.repeat(a[None], 65, 0)]) + rng.normal(size=(100, 20, 2))
    choice = find_rest_frame(P)
    assert choice.frame >= 35 and "68-point" in choice.reason
    assert np.abs(choice.shape - a).mean() < 0.5
    rs = rest_shape(P)
    assert rs.calm.all() and not rs.openings


def test_lost_landmarks_and_bad_shapes():
    curves = smiling_start(T=60, frames=10)
    P = landmarks_of(curves)
    P[:, 5] = np.nan
    with pytest.raises(ValueError, match="no frame has every landmark finite"):
        find_rest_frame(P)
    with pytest.raises(ValueError, match="expected shape"):
        find_rest_frame(np.zeros((5, 68)))
    P = landmarks_of(curves)
    P[40:, 50] = np.nan  # every later frame loses a lip landmark: the rest is found among the others
    assert find_rest_frame(P).frame < 40


def test_a_calibration_shape_aligned_to_the_take_and_its_nearest_frame():
    curves = smiling_start(T=80)
    take = landmarks_of(curves)
    rest = landmarks_of(np.zeros((1, len(EXPRESSIONS))), noise=0.0)[0]
    th = np.deg2rad(12.0)
    R = 1.3 * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    elsewhere = rest @ R.T + [40.0, -25.0]  # filmed closer, tilted, off centre
    aligned = align_shape(elsewhere, np.median(take, axis=0))
    assert np.linalg.norm(aligned - rest, axis=1).max() < 1.0
    f = nearest_frame(take, None, aligned)
    assert curves[f].max() < 0.02
    with pytest.raises(ValueError, match="shape"):
        nearest_frame(take, None, aligned[:10])


def test_a_closed_lip_smile_held_longer_than_the_rest_is_not_the_rest_pose():
    """Issue 33's d9 shot: most frames with the lips closed and the eyes open are a closed-lip smile; the rest
    frames are fewer, and the mouth is open (speech) in between. The rest is the narrower mouth."""
    T = 150
    curves = np.zeros((T, len(EXPRESSIONS)))
    curves[:60, E["smile"]] = 1.0   # a closed-lip smile, held
    curves[60:110, E["jaw_open"]] = 0.5 + 0.3 * np.sin(np.arange(50) / 4.0) ** 2  # talking
    # frames 110-149: at rest (40 frames, fewer than the smile's 60)
    P = landmarks_of(curves)
    closed = face_openings(P)["lip_gap"] < 0.05
    assert closed[:60].sum() > closed[110:].sum() > 10  # the smile is the majority of the closed-lip frames
    rs = rest_shape(P, np.ones((T, 68)))
    assert not rs.calm[:60].any() and rs.calm[110:].sum() > 10
    choice = find_rest_frame(P, np.ones((T, 68)))
    assert choice.frame >= 110 and choice.at_rest, (choice.frame, curves[choice.frame].round(2))
    assert (choice.members >= 110).all(), choice.members
