"""retarget_cli.see.truth: a run's meshes and landmarks against a synthetic take's ground truth."""

import numpy as np
import pytest

from retarget_cli.errors import InputError, ShapeError
from retarget_cli.see.truth import load_truth_animation, mesh_against_truth, points_against_truth


def test_mesh_error_and_jitter_ratio_on_known_animations():
    t = np.arange(20, dtype=np.float64)
    truth = np.zeros((20, 4, 3))
    truth[:, :, 0] = np.sin(t / 3)[:, None]               # every vertex moves along x
    got = truth + np.array([0.0, 0.1, 0.0])             # a constant offset: same acceleration
    m = mesh_against_truth(got, truth)
    assert m["error_mean"] == pytest.approx(0.1)
    disp = np.abs(np.sin(t / 3)).mean()
    assert m["error_pct"] == pytest.approx(100 * 0.1 / disp)
    assert m["jitter_ratio"] == pytest.approx(1.0)
    np.testing.assert_allclose(m["error_per_frame"], 0.1)
    shaky = got.copy()
    shaky[::2, :, 2] += 0.05                           # alternating frames: acceleration 0.1 per frame in z
    assert mesh_against_truth(shaky, truth)["jitter_ratio"] > 1.5
    with pytest.raises(ShapeError):
        mesh_against_truth(got[:10], truth)


def test_points_against_truth_ignores_lost_points_in_the_error():
    truth = np.zeros((5, 3, 2))
    got = truth + 1.0
    got[2, 1] = np.nan
    m = points_against_truth(got, truth)
    assert m["error_px"] == pytest.approx(np.sqrt(2))
    assert np.isfinite(m["jitter"])


def test_load_truth_needs_the_target_array(tmp_path):
    from retarget_cli.io.atomic import savez

    p = tmp_path / "t.npz"
    savez(p, {"target": np.zeros((3, 5, 2))})
    with pytest.raises(InputError, match=r"'target' has shape \(3, 5, 2\)"):
        load_truth_animation(p)
    savez(p, {"curves": np.zeros((3, 2))})
    with pytest.raises(InputError, match="no 'target' array"):
        load_truth_animation(p)
    nan = np.ones((3, 5, 3))
    nan[2, 1, 0] = np.nan
    savez(p, {"target": nan})
    with pytest.raises(InputError, match="'target' frame 2 is not finite"):
        load_truth_animation(p)
    savez(p, {"target": np.ones((3, 5, 3), np.float32)})
    assert load_truth_animation(p).dtype == np.float64


def test_report_passes_over_a_truth_npz_beside_the_video_that_is_not_a_synthetic_truth(tmp_path, caplog):
    from retarget_cli.io.atomic import savez
    from retarget_cli.run.runfiles import RunFiles
    from retarget_cli.see.report import find_truth

    run = RunFiles(root=tmp_path / "out", video=tmp_path / "face.mp4")
    assert find_truth(run) == (None, None)                      # nothing beside the video
    savez(tmp_path / "truth.npz", {"curves": np.zeros((4, 2))})  # the user's own file of that name
    with caplog.at_level("WARNING"):
        assert find_truth(run) == (None, None)
    assert "no 'target' array" in caplog.text
    with pytest.raises(InputError, match="no 'target' array"):  # named explicitly: an error
        find_truth(run, tmp_path / "truth.npz")
    savez(tmp_path / "truth.npz", {"target": np.zeros((4, 5, 3))})
    path, target = find_truth(run)
    assert path == tmp_path / "truth.npz" and target.shape == (4, 5, 3)
