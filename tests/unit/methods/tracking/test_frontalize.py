"""The head's 3D rotation removed from the landmarks (issue 28): frontalize and the rotation transforms."""

from __future__ import annotations

import numpy as np
import pytest

from retarget_cli.errors import ShapeError
from retarget_cli.methods.blending import head_rotation_transforms
from retarget_cli.methods.tracking.headpose import (
    FACE_68,
    angles_rotation,
    camera_angles,
    camera_matrix,
    frontalize,
    head_pose,
    rest_rotation,
    rotation_angles,
    sight_angles,
    sight_rotation,
)

SIZE = (1280, 720)


def _project(X, angles, t):
    K = camera_matrix(SIZE)
    Y = X @ angles_rotation(angles).T + t
    p = Y @ K.T
    return p[:, :2] / p[:, 2:]


def _expression():
    X = FACE_68.copy()
    X[48:68, 1] += 1.0          # mouth down
    X[48, 0] -= 0.8             # mouth corners out
    X[54, 0] += 0.8
    X[17:27, 1] -= 0.5          # brows up
    return X


@pytest.mark.parametrize("angles", [(30, 0, 0), (-30, 20, 5), (20, -30, -8)])
def test_frontalize_shows_the_turned_expression_as_facing_the_camera(angles):
    X, t = _expression(), np.array([1.0, -2.0, 55.0])
    obs = _project(X, angles, t)[None]
    front = _project(X, camera_angles((0, 0, 0), t), t)  # the same face at the same place, looking into the lens
    pose = head_pose(obs, SIZE)
    back = frontalize(obs, pose, SIZE)[0]
    sub = frontalize(obs, pose, SIZE, mode="subtract")[0]
    turned = np.abs(obs[0] - front).mean()
    assert turned > 10                                   # the turn moves the points by many pixels
    assert np.abs(back - front).mean() < 0.1             # back-projected: the frontal view within 0.1 px
    assert np.abs(sub - front).mean() > np.abs(back - front).mean()  # subtraction keeps the foreshortening


def _open_jaw_smile():
    X = FACE_68.copy()
    X[list(range(5, 12)) + [56, 57, 58, 65, 66, 67], 1] += 2.0   # the jaw open: chin and lower lip down
    X[list(range(5, 12)) + [56, 57, 58, 65, 66, 67], 2] += 0.8   # and back
    X[[48, 60], 0] -= 0.8                                         # a smile: the corners out and up
    X[[54, 64], 0] += 0.8
    X[[48, 54, 60, 64], 1] -= 0.5
    X[[31, 32], 0] -= 0.25                                        # the nose's wings pulled out and up
    X[[34, 35], 0] += 0.25
    X[31:36, 1] -= 0.3
    return X


def _angle_error(pose, angles):
    R = np.swapaxes(angles_rotation(pose.angles), -1, -2) @ angles_rotation(angles)
    return np.degrees(np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1, 1)))


def test_the_pose_fitted_on_the_deformed_face_recovers_a_known_pose_an_open_jaw_biases_at_rest():
    # joint pose and expression fit: a 3D face per frame (the rest face deformed by the expression) keeps an open
    # jaw and a smile out of the pose, which the rest face alone reads as a turn
    X = _open_jaw_smile()
    angles = np.array([(25.0, -10.0, 4.0), (-15.0, 20.0, -6.0), (5.0, 5.0, 0.0)])
    t = np.array([2.0, 1.0, 55.0])
    obs = np.stack([_project(X, a, t) for a in angles])
    chin_up = tuple(range(6, 11)) + tuple(range(17, 68))         # every point but the jaw contour's sides
    for points in ((27, 28, 29, 30, 31, 32, 33, 34, 35, 36, 39, 42, 45), chin_up):
        rest = _angle_error(head_pose(obs, SIZE, pose_points=points), angles)
        joint = _angle_error(head_pose(obs, SIZE, model=np.broadcast_to(X, (3, 68, 3)), pose_points=points),
                             angles)
        assert rest.mean() > 1.0                                 # the expression leaks into the rest-only pose
        assert joint.max() < 0.05                                # the deformed face's pose is exact
    with pytest.raises(ShapeError, match="model"):
        head_pose(obs, SIZE, model=np.zeros((2, 68, 3)))


def test_frontalize_relative_to_the_rest_pose_removes_only_the_change_of_pose():
    t = np.array([3.0, -1.0, 60.0])
    rest_angles, turned = np.array([12.0, -6.0, 2.0]), np.array([-18.0, 14.0, -5.0])
    X = _expression()
    obs = np.stack([_project(FACE_68, rest_angles, t), _project(FACE_68, rest_angles, t), _project(X, turned, t)])
    pose = head_pose(obs, SIZE)
    A = rest_rotation(pose, [0, 1])
    np.testing.assert_allclose(A, sight_rotation(t).T @ angles_rotation(rest_angles), atol=1e-3)  # S(t)ᵀ R
    out = frontalize(obs, pose, SIZE, rest=A)
    assert np.abs(out[:2] - obs[:2]).max() < 0.05                # the rest frames are left where they are
    as_rest = _project(X, rotation_angles(sight_rotation(t) @ A), t)  # the expression turned as the rest frames
    plain = frontalize(obs, pose, SIZE)[2]
    assert np.abs(out[2] - as_rest).mean() < 0.1
    assert np.abs(plain - as_rest).mean() > 5                    # without rest: shown looking into the lens
    with pytest.raises(ShapeError, match="rest"):
        frontalize(obs, pose, SIZE, rest=np.eye(2))
    with pytest.raises(ShapeError, match="rest frame"):
        rest_rotation(pose, [])


def test_sight_angles_are_zero_for_a_face_that_looks_into_the_lens_off_axis():
    t = np.array([[12.0, -6.0, 50.0], [0.0, 0.0, 60.0], [-8.0, 9.0, 40.0]])
    cam = camera_angles(np.zeros((3, 3)), t)
    assert abs(cam[0, 0]) > 10 and abs(cam[1]).max() < 1e-9    # turned in camera axes beside the optical axis
    pts = np.stack([_project(FACE_68, a, tt) for a, tt in zip(cam, t)])
    pose = head_pose(pts, SIZE)
    np.testing.assert_allclose(sight_angles(pose.angles, pose.translation), 0, atol=0.05)
    a = np.random.default_rng(2).uniform(-30, 30, (3, 3))
    np.testing.assert_allclose(sight_angles(camera_angles(a, t), t), a, atol=1e-9)


def test_frontalize_is_the_identity_for_a_face_looking_into_the_camera():
    X, t = _expression(), np.array([0.0, 0.0, 60.0])
    obs = _project(X, (0, 0, 0), t)[None] + np.random.default_rng(0).normal(0, 0.5, (1, 68, 2))
    pose = head_pose(obs, SIZE)
    assert np.abs(frontalize(obs, pose, SIZE) - obs).max() < 1.0


def test_head_rotation_transforms_turn_the_model_the_actors_way():
    """Yaw > 0 (the actor turns to their left): the character's nose (model +z, y up) moves to its left (+x)."""
    nose = np.array([0.0, 0.0, 10.0])
    A = head_rotation_transforms(np.array([[20.0, 0, 0], [0, 20.0, 0], [0, 0, 0]]), pivot=np.zeros(3))
    moved = A[:, :, :3] @ nose + A[:, :, 3]
    assert moved[0, 0] > 3 and abs(moved[0, 1]) < 1e-9       # yaw: to the character's left
    assert moved[1, 1] > 3                                   # pitch up: the nose rises
    np.testing.assert_allclose(moved[2], nose)
    np.testing.assert_allclose(A[:, :, :3] @ A[:, :, :3].transpose(0, 2, 1), np.tile(np.eye(3), (3, 1, 1)),
                               atol=1e-12)


def test_head_rotation_after_the_2d_motion_leaves_the_3d_roll_to_it():
    angles = np.array([[15.0, -10.0, 8.0]])
    A2 = np.array([[[0.0, -1.0, 0.0, 1.0], [1.0, 0.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0]]])  # a 90° roll and a shift
    P = np.array([0.5, 1.0, -2.0])
    both = head_rotation_transforms(angles, pivot=P, transforms=A2, keep_roll=False)
    alone = head_rotation_transforms(angles * [1, 1, 0], pivot=P)
    X = np.random.default_rng(4).normal(size=(5, 3))
    want = (X @ alone[0, :, :3].T + alone[0, :, 3]) @ A2[0, :, :3].T + A2[0, :, 3]
    np.testing.assert_allclose(X @ both[0, :, :3].T + both[0, :, 3], want, atol=1e-12)
