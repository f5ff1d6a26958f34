"""`retarget track` inputs, errors and options; `retarget import` round trip."""

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from retarget_cli.cli.commands import main
from retarget_cli.io.annotations import read_pts, write_csv_landmarks, write_pts
from retarget_cli.io.atomic import load_npz, savez
from retarget_cli.io.landmarks import load_landmarks


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture
def truth(small_take):
    return load_npz(small_take / "truth_landmarks.npz")


def error(npz, truth, frames):
    return np.linalg.norm(load_npz(npz)["points"] - truth["points"][frames], axis=2).mean()


def test_track_video_range_step_and_overlay(small_take, truth, tmp_path):
    out, ov = tmp_path / "lm.npz", tmp_path / "overlay.mp4"
    r = run("track", "--method", "lk", small_take / "face.mp4", "--init", small_take / "face_00000.pts", "-o", out,
            "--end", 30, "--step", 2, "--overlay", ov)
    assert r.exit_code == 0, r.output
    lm = load_npz(out)
    np.testing.assert_array_equal(lm["frames"], np.arange(0, 30, 2))
    assert lm["fps"] == pytest.approx(15.0)
    assert error(out, truth, slice(0, 30, 2)) < 0.8
    cap = cv2.VideoCapture(str(ov))
    assert cap.get(cv2.CAP_PROP_FRAME_COUNT) == 15
    ok, frame = cap.read()
    assert ok and frame.shape == (192, 192, 3)


def test_track_image_sequence_png_and_exr_with_csv_annotation(small_take, truth, tmp_path):
    cap = cv2.VideoCapture(str(small_take / "face.mp4"))
    seq = tmp_path / "seq"
    seq.mkdir()
    import OpenEXR

    for i in range(12):
        ok, frame = cap.read()
        assert ok
        cv2.imwrite(str(seq / f"f_{i + 1:04d}.png"), frame)
        lin = ((frame[..., ::-1].astype(np.float32) / 255) ** 2.2).astype(np.float32)  # approx. linear light
        OpenEXR.File({"type": OpenEXR.scanlineimage}, {"RGB": lin}).write(str(seq / f"e_{i:03d}.exr"))
    csv = tmp_path / "ann.csv"
    write_csv_landmarks(csv, truth["points"][:1])
    out = tmp_path / "png.npz"
    r = run("track", "--method", "lk", str(seq / "f_%04d.png"), "--init", csv, "-o", out)
    assert r.exit_code == 0, r.output
    assert error(out, truth, slice(0, 12)) < 0.8
    out2 = tmp_path / "exr.npz"
    r = run("track", "--method", "lk", str(seq / "e_*.exr"), "--init", csv, "-o", out2, "--fps", 24)
    assert r.exit_code == 0, r.output
    assert load_npz(out2)["fps"] == 24
    assert error(out2, truth, slice(0, 12)) < 1.0


def test_track_several_pts_reanchor(small_take, truth, tmp_path):
    write_pts(tmp_path / "face_00020.pts", truth["points"][20])
    out = tmp_path / "lm.npz"
    r = run("track", small_take / "face.mp4", "--init", small_take / "face_00000.pts",
            "--annotation", tmp_path / "face_00020.pts", "-o", out, "--end", 30)
    assert r.exit_code == 0, r.output
    np.testing.assert_allclose(load_npz(out)["points"][20], truth["points"][20], atol=2e-3)


def test_track_start_must_be_annotated(small_take, tmp_path):
    r = run("track", "--method", "lk", small_take / "face.mp4", "--init", small_take / "face_00000.pts", "--start", 5,
            "-o", tmp_path / "x.npz")
    assert r.exit_code == 1 and "first tracked frame (5) must be annotated" in r.output


def test_track_point_count_mismatch_names_both_counts(small_take, tmp_path):
    P = read_pts(small_take / "face_00000.pts")
    write_pts(tmp_path / "face_00010.pts", P[:67])
    r = run("track", small_take / "face.mp4", "--init", small_take / "face_00000.pts",
            "--annotation", tmp_path / "face_00010.pts", "-o", tmp_path / "x.npz")
    assert r.exit_code == 1
    assert "face_00010.pts: frame 10 has 67 points but" in r.output and "has 68" in r.output


def test_track_point_outside_image(small_take, tmp_path):
    P = read_pts(small_take / "face_00000.pts")
    P[3] = (250, 40)
    write_pts(tmp_path / "bad.pts", P)
    r = run("track", small_take / "face.mp4", "--init", tmp_path / "bad.pts", "-o", tmp_path / "x.npz")
    assert r.exit_code == 1 and "bad.pts: frame 0: point 3" in r.output and "192x192" in r.output


def test_truncated_video_stops_naming_file_and_last_frame(small_take, truncated_avi, tmp_path):
    cut = truncated_avi
    out = tmp_path / "x.npz"
    r = run("track", cut, "--init", small_take / "face_00000.pts", "-o", out)
    assert r.exit_code == 1
    assert "cut.avi: decoding stopped after frame" in r.output and "--keep-partial" in r.output
    assert not out.exists()
    r = run("track", cut, "--init", small_take / "face_00000.pts", "-o", out, "--keep-partial")
    assert r.exit_code == 0, r.output
    T = load_npz(out)["points"].shape[0]
    assert 5 < T < 60


def test_lost_face_is_reported(small_take, tmp_path):
    cap = cv2.VideoCapture(str(small_take / "face.mp4"))
    seq = tmp_path / "seq"
    seq.mkdir()
    for i in range(30):
        ok, frame = cap.read()
        if i >= 8:
            frame = np.full_like(frame, 128)  # the face leaves the picture
        cv2.imwrite(str(seq / f"{i:03d}.png"), frame)
    r = run("track", "--method", "lk", str(seq / "*.png"), "--init", small_take / "face_00000.pts", "-o", tmp_path / "x.npz")
    assert r.exit_code == 1 and "the face was lost from frame" in r.output


def test_import_round_trip_csv_npz_pts(small_take, truth, tmp_path):
    P = truth["points"].astype(np.float64)
    csv = tmp_path / "lm.csv"
    write_csv_landmarks(csv, P)
    folder = tmp_path / "pts"
    for f in (0, 5, 9):
        write_pts(folder / f"face_{f:05d}.pts", P[f])
    savez(tmp_path / "other.npz", {"points": P.astype(np.float32), "fps": np.float64(25)})
    for src, frames in ((csv, np.arange(60)), (folder, np.array([0, 5, 9])), (tmp_path / "other.npz", np.arange(60))):
        out = tmp_path / f"{src.stem}.landmarks.npz"
        r = run("import", src, "-o", out, "--filter", "none")
        assert r.exit_code == 0, r.output
        lm = load_landmarks(out)
        np.testing.assert_allclose(lm.points, P[frames], atol=1e-3)
        # head motion computed: matches the truth's head relative to the first imported frame
        np.testing.assert_allclose(lm.head[0], np.eye(2, 3), atol=1e-6)
        np.testing.assert_array_equal(load_npz(out)["frames"], frames)
    # back to CSV and in again: identical points
    lm = load_landmarks(tmp_path / "lm.landmarks.npz")
    write_csv_landmarks(tmp_path / "again.csv", lm.points)
    assert run("import", tmp_path / "again.csv", "-o", tmp_path / "again.npz", "--filter", "none").exit_code == 0
    np.testing.assert_allclose(load_landmarks(tmp_path / "again.npz").points, lm.points, atol=1e-4)


def test_import_filters_like_track_unless_the_frames_have_gaps(truth, tmp_path):
    rng = np.random.default_rng(0)
    P = truth["points"].astype(np.float64) + 0.8 * rng.standard_normal(truth["points"].shape)
    write_csv_landmarks(tmp_path / "noisy.csv", P)
    assert run("import", tmp_path / "noisy.csv", "-o", tmp_path / "f.npz").exit_code == 0
    data = load_npz(tmp_path / "f.npz")
    np.testing.assert_allclose(data["points_raw"], P, atol=1e-3)  # the source's points are kept
    err = lambda X: np.abs(X - truth["points"]).mean()  # noqa: E731
    assert err(data["points"]) < 0.7 * err(P)  # rts by default, as track
    assert '"method": "rts"' in str(data["meta"])
    folder = tmp_path / "pts"
    for f in (0, 5, 9):
        write_pts(folder / f"face_{f:05d}.pts", P[f])
    r = run("import", folder, "-o", tmp_path / "g.npz")
    assert r.exit_code == 0
    np.testing.assert_allclose(load_landmarks(tmp_path / "g.npz").points, P[[0, 5, 9]], atol=1e-3)
    assert "frames 0 and 5 are not consecutive; imported without the rts filter" in r.output


def test_import_bad_inputs(tmp_path):
    (tmp_path / "bad.csv").write_text("frame,point,x,y\n0,0,1,2\n0,1,3,4\n1,0,1,2\n")
    r = run("import", tmp_path / "bad.csv", "-o", tmp_path / "x.npz")
    assert r.exit_code == 1 and "frame 1 has 1 points but frame 0 has 2" in r.output
    (tmp_path / "hdr.csv").write_text("f,p,x,y\n")
    r = run("import", tmp_path / "hdr.csv", "-o", tmp_path / "x.npz")
    assert r.exit_code == 1 and "expected the header 'frame,point,x,y'" in r.output


def test_track_eigenpoints_from_five_annotations(small_take, truth, tmp_path):
    extra = []
    for f in (10, 20, 30, 40):
        write_pts(tmp_path / f"face_{f:05d}.pts", truth["points"][f])
        extra += ["--annotation", tmp_path / f"face_{f:05d}.pts"]
    out = tmp_path / "eig.npz"
    r = run("track", small_take / "face.mp4", "--init", small_take / "face_00000.pts", *extra,
            "--method", "eigenpoints", "-o", out, "--end", 50)
    assert r.exit_code == 0, r.output
    assert error(out, truth, slice(0, 50)) < 1.0
    assert '"tracker": "eigenpoints"' in str(load_npz(out)["meta"])


def test_run_config_with_image_sequence_and_annotations(small_take, truth, tmp_path):
    cap = cv2.VideoCapture(str(small_take / "face.mp4"))
    seq = small_take / "seq"
    seq.mkdir()
    for i in range(20):
        ok, frame = cap.read()
        cv2.imwrite(str(seq / f"{i:04d}.jpg"), frame, [cv2.IMWRITE_JPEG_QUALITY, 95])
    write_pts(small_take / "face_00010.pts", truth["points"][10])
    cfg = small_take / "track.yaml"
    cfg.write_text("output_dir: out2\ntrack:\n  video: seq/%04d.jpg\n  init: face_00000.pts\n"
                   "  annotations: [face_00010.pts]\n  smooth_head: 5\n")
    r = run("run", cfg)
    assert r.exit_code == 0, r.output
    lm = load_npz(small_take / "out2" / "landmarks.npz")
    assert lm["points"].shape == (20, 68, 2)
    np.testing.assert_allclose(lm["head"][0], np.eye(2, 3), atol=1e-6)
    r = run("run", cfg)
    assert r.exit_code == 0 and "track: skipped" in r.stderr
    # changing one frame of the sequence reruns the stage
    img = cv2.imread(str(seq / "0005.jpg"))
    cv2.imwrite(str(seq / "0005.jpg"), 255 - img)
    r = run("run", cfg)
    assert r.exit_code == 0
    assert "track: ran" in r.stderr


def test_track_markers_cli(tmp_path):
    from retarget_cli.synth.take import write_take

    d = tmp_path / "dots"
    write_take(d, n_frames=30, size=(192, 192), seed=4, dots=1.6)
    out = tmp_path / "m.npz"
    r = run("track", d / "face.mp4", "--init", d / "face_00000.pts", "--method", "markers", "-o", out)
    assert r.exit_code == 0, r.output
    truth = load_npz(d / "truth_landmarks.npz")
    assert np.linalg.norm(load_npz(out)["points"] - truth["points"], axis=2).mean() < 0.8
