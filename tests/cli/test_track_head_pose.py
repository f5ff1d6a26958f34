"""track stores the 3D head pose (issue 28): head_angles and head_translation in landmarks.npz, off with
--no-head-pose."""

import numpy as np
from click.testing import CliRunner

from retarget_cli.cli.commands import main
from retarget_cli.io.landmarks import load_landmarks


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


def test_track_stores_the_head_pose_and_its_roll_follows_the_2d_head(small_take, tmp_path):
    out = tmp_path / "lm.npz"
    r = run("track", "--method", "lk", small_take / "face.mp4", "--init", small_take / "face_00000.pts", "-o", out)
    assert r.exit_code == 0, r.output
    lm = load_landmarks(out)
    assert lm.head_angles.shape == (lm.n_frames, 3) and lm.head_translation.shape == (lm.n_frames, 3)
    assert np.isfinite(lm.head_angles).all() and (lm.head_translation[:, 2] > 0).all()  # in front of the camera
    # the synthetic take's head moves in the image plane: the 3D roll follows the 2D similarity's rotation
    roll2d = np.degrees(np.arctan2(lm.head[:, 1, 0], lm.head[:, 0, 0]))
    roll3d = lm.head_angles[:, 2] - lm.head_angles[0, 2]
    assert np.ptp(roll2d) > 2
    assert np.corrcoef(roll2d, roll3d)[0, 1] > 0.9
    off = tmp_path / "off.npz"
    r = run("track", "--method", "lk", small_take / "face.mp4", "--init", small_take / "face_00000.pts", "-o", off,
            "--end", 10, "--no-head-pose")
    assert r.exit_code == 0, r.output
    assert load_landmarks(off).head_angles is None
