"""auto_pose.frontalize (issue 28): the landmarks shown turned as the take's rest frames."""

import numpy as np

from retarget_cli.io.landmarks import Landmarks
from retarget_cli.methods.tracking.head import estimate_head
from retarget_cli.methods.tracking.headpose import FACE_68, angles_rotation, camera_matrix, head_pose, sight_angles
from retarget_cli.stages._neutral import Neutral
from retarget_cli.stages.auto_pose import _rest_rows, frontal_landmarks

SIZE = (640, 480)
START, T = 45, 30
REST = list(range(50, 55))  # source frames of the rest frames: rows 5-9


def _take():
    angles = np.tile([12.0, -6.0, 2.0], (T, 1))             # the actor rests turned away from the lens
    angles[15:] = [-15.0, 10.0, -4.0]                       # and turns further later
    t = np.array([2.0, -1.0, 70.0])
    K = camera_matrix(SIZE)
    Y = np.einsum("tij,lj->tli", angles_rotation(angles), FACE_68) + t
    p = Y @ K.T
    pts = p[..., :2] / p[..., 2:]
    conf = np.ones((T, 68))
    head, stab = estimate_head(pts, conf)
    pose = head_pose(pts, SIZE, confidence=conf)
    lm = Landmarks(pts, conf, head, stab.astype(np.float32), frame_size=np.array(SIZE), frames=np.arange(START, START + T),
                   head_angles=sight_angles(pose.angles, pose.translation), head_translation=pose.translation)
    rows = np.array(REST) - START
    neutral = Neutral(int(rows[2]), stab[rows].mean(0), np.ones(68),
                      {"source": "take", "frame": REST[2], "row": int(rows[2]), "frames": REST})
    return lm, neutral


def test_the_rest_frames_are_read_as_source_frames_and_left_in_place():
    lm, neutral = _take()
    assert _rest_rows(lm, neutral).tolist() == [5, 6, 7, 8, 9]
    # the generic face of landmarks.npz's head_angles (the rig maps fewer than 68 landmarks): no rig needed
    front, nb = frontal_landmarks(lm, neutral, None, None, np.arange(67))
    rest = lm.stabilized[5:10].astype(np.float64)
    assert np.abs(front.stabilized[5:10] - rest).max() < 0.05           # the rest frames stay where they are
    # a face without expression, turned otherwise later, is shown as turned as the rest frames: no expression
    assert np.abs(lm.stabilized[20] - rest[0]).mean() > 5
    assert np.abs(front.stabilized[20] - rest[0]).mean() < 0.1
    np.testing.assert_allclose(nb.shape, front.stabilized[5:10].astype(np.float64).mean(0))
    assert nb.frame == neutral.frame and nb.record is neutral.record
