"""The head's 3D rotation removed from the landmarks (issue 28): frontalize and the rotation transforms."""

from __future__ import annotations

import numpy as np
import pytest

from retarget_cli.methods.blending import head_rotation_transforms
from retarget_cli.methods.tracking.headpose import (
    FACE_68,
    angles_rotation,
    camera_angles,
    camera_matrix,
    frontalize,
    head_pose,
    sight_angles,
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
