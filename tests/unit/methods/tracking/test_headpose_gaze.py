"""3D head pose from 2D landmarks, and gaze inside the tracked eyes (issue 28's methods)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from retarget_cli.methods.tracking.gaze import EYES_68, _eye_mask, _patch, eye_frame, gaze, iris_centre
from retarget_cli.methods.tracking.headpose import (
    FACE_68,
    angles_rotation,
    camera_matrix,
    head_pose,
    rotation_angles,
)


def _project(X, angles, t, K):
    R = angles_rotation(angles)
    Y = X @ R.T + t
    p = Y @ K.T
    return p[:, :2] / p[:, 2:]


def test_angles_round_trip_and_signs():
    rng = np.random.default_rng(0)
    a = rng.uniform(-40, 40, size=(50, 3))
    np.testing.assert_allclose(rotation_angles(angles_rotation(a)), a, atol=1e-9)
    K = camera_matrix((640, 480))
    t = np.array([0.0, 0.0, 60.0])
    nose = FACE_68[30]
    left = _project(FACE_68, [20, 0, 0], t, K)[30]     # turned to the actor's left: nose to the image's right
    up = _project(FACE_68, [0, 20, 0], t, K)[30]       # looking up: nose up in the image
    front = _project(FACE_68, [0, 0, 0], t, K)[30]
    assert left[0] > front[0] + 5 and up[1] < front[1] - 5 and nose[2] < 0


@pytest.mark.parametrize("angles", [(0, 0, 0), (25, 0, 0), (-30, 10, 5), (10, -20, -8), (30, 30, 0)])
def test_head_pose_recovers_known_rotations(angles):
    K = camera_matrix((640, 480))
    frames = np.array([angles, angles]) + np.array([[0, 0, 0], [2, -1, 1]])
    pts = np.stack([_project(FACE_68, a, np.array([1.0, -2.0, 55.0]), K) for a in frames])
    pose = head_pose(pts, (640, 480))
    np.testing.assert_allclose(pose.angles, frames, atol=0.05)
    assert np.all(pose.error < 0.05)


def test_head_pose_with_expression_noise_stays_within_two_degrees():
    """The mouth and brows move (an expression) and every point jitters by 0.5 px: the pose is fitted on the rigid points."""
    rng = np.random.default_rng(1)
    K = camera_matrix((640, 480))
    X = FACE_68.copy()
    X[48:68, 1] += 1.5          # mouth opened
    X[17:27, 1] -= 0.8          # brows raised
    true = rng.uniform(-30, 30, size=(40, 3)) * np.array([1, 1, 0.5])
    pts = np.stack([_project(X, a, np.array([0.0, 0.0, 50.0]), K) for a in true]) + rng.normal(0, 0.5, (40, 68, 2))
    pose = head_pose(pts, (640, 480))
    assert np.mean(np.abs(pose.angles - true)) < 2.0


def _eye_image(offset: float, closed: bool = False, half: int = 11):
    """A 200x120 frame with one eye: white sclera between corners 60 px apart, a dark iris *offset* widths along,
    the lids *half* px above and below the corner line (2 when *closed*)."""
    img = np.full((120, 200), 150, np.uint8)
    c = np.array([100.0, 60.0])
    corners = c + np.array([[-30, 0], [30, 0]])
    half = 2 if closed else half
    cv2.ellipse(img, (100, 60), (30, half), 0, 0, 360, 235, -1)
    if not closed:
        iris = (int(round(100 + offset * 60)), 60)
        mask = np.zeros_like(img)
        cv2.ellipse(mask, (100, 60), (30, half), 0, 0, 360, 1, -1)
        disk = np.zeros_like(img)
        cv2.circle(disk, iris, 11, 1, -1)
        img[(disk & mask).astype(bool)] = 40
    pts = np.zeros((68, 2))
    for eye in EYES_68:
        pts[eye[0]], pts[eye[1]] = corners
        for u, lo in zip(eye[2], eye[3]):
            x = 100 + (-10 if u == eye[2][0] else 10)
            pts[u], pts[lo] = (x, 60 - half), (x, 60 + half)
    return img, pts


@pytest.mark.parametrize("offset", [-0.2, -0.1, 0.0, 0.12, 0.2])
def test_gaze_finds_a_known_iris_offset(offset):
    img, pts = _eye_image(offset)
    g = gaze([img], pts[None])
    assert abs(g.offset[0, 0, 0] - offset) < 0.03
    assert abs(g.offset[0, 0, 1]) < 0.03
    assert not g.held[0, 0]


def test_a_blink_holds_the_gaze():
    frames, points = [], []
    for offset, closed in [(0.15, False), (0.15, False), (0.0, True), (0.0, True), (0.15, False)]:
        img, pts = _eye_image(offset, closed)
        frames.append(img)
        points.append(pts)
    g = gaze(frames, np.array(points))
    assert g.held[2:4, 0].all() and not g.held[[0, 1, 4], 0].any()
    np.testing.assert_allclose(g.offset[2:4, 0], g.offset[1:2, 0].repeat(2, axis=0))
    assert np.all(np.abs(g.offset[:, 0, 0] - 0.15) < 0.03)


@pytest.mark.parametrize("shade", [40, 80])
def test_a_shadow_off_the_iris_pulls_the_centroid_not_the_limbus(shade):
    # a dark band along the outer half of the upper lid (lashes, the lid's shadow), the iris 0.1 widths inward
    img, pts = _eye_image(0.1)
    inside = np.zeros_like(img)
    cv2.ellipse(inside, (100, 60), (30, 11), 0, 0, 360, 1, -1)
    band = np.zeros_like(img)
    cv2.rectangle(band, (72, 50), (88, 58), 1, -1)
    img[(band & inside).astype(bool)] = shade
    eye = EYES_68[0]
    mid, x, y, w = eye_frame(pts, eye)
    patch, A = _patch(img, mid, x, y, w)
    mask = _eye_mask(pts, eye, A)
    centroid = iris_centre(patch, mask, limbus=False)
    both = iris_centre(patch, mask)
    err = [abs((c[0] - 30.0) / 40.0 - 0.1) for c in (centroid, both)]  # patch: 40 px per eye width, centre x 30
    assert err[0] > 0.025          # the centroid is pulled toward the band
    assert err[1] < 0.015          # the limbus average is not
    assert abs(gaze([img], pts[None]).offset[0, 0, 0] - 0.1) < 0.015


def test_a_nearly_shut_eye_is_drawn_toward_the_median_horizontal_gaze():
    # four open frames looking ahead, one open and one nearly shut (lid gap 10/60 widths) looking 0.15 inward
    frames, points = [], []
    for offset, half in [(0.0, 11)] * 4 + [(0.15, 11), (0.15, 5)]:
        img, pts = _eye_image(offset, half=half)
        frames.append(img)
        points.append(pts)
    g = gaze(frames, np.array(points))
    assert not g.held[:, 0].any()
    assert abs(g.offset[4, 0, 0] - 0.15) < 0.03                 # open: read in full
    keep = (10 / 60 - 0.10) / (0.25 - 0.10)                        # the gap's weight between 0.10 and 0.25 widths
    assert abs(g.offset[5, 0, 0] - g.offset[0, 0, 0] - keep * 0.15) < 0.02
    raw = gaze(frames, np.array(points), unsure=(0.0, 0.0))        # without: the shut eye's full reading
    assert abs(raw.offset[5, 0, 0] - 0.15) < 0.04
