"""The pretrained landmark detector: `track --method detect`, `--init auto`, `annotate`, its errors.

The real clip (fixture ``real_clip``: frames 0-59 of d3) has a blink at frames
47-50 (lids shut at 48, open again at 53-55, looking down from 56; checked on
the overlay): the detector's eye opening there falls to about half of the
median (0.14 against 0.26).
"""

import json
import sys

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from detector_marks import needs_detector

from retarget_cli.cli.commands import main
from retarget_cli.config import load_config
from retarget_cli.io.annotations import read_pts
from retarget_cli.io.landmarks import load_landmarks
from retarget_cli.run.pipeline import STAGES, _inputs, resolve, run_pipeline, stage_params

BLINK = [47, 48, 49, 50]


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def one_line_error(r):
    """The message of a failed command run with -q (no progress bar)."""
    assert r.exit_code == 1, r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), r.output
    return lines[0]


@pytest.fixture
def black_video(tmp_path):
    path = tmp_path / "black.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25, (160, 160))
    for _ in range(4):
        w.write(np.zeros((160, 160, 3), np.uint8))
    w.release()
    return path


@needs_detector
def test_detector_on_frame_0_agrees_with_the_committed_annotation(real_clip):
    from retarget_cli.methods.tracking.detect import Detector, detect_landmarks

    cap = cv2.VideoCapture(str(real_clip / "d3.avi"))
    ok, frame = cap.read()
    cap.release()
    assert ok
    P, box = detect_landmarks(frame, detector=Detector())
    ref = read_pts(real_clip / "d3_00000.pts")
    err = np.linalg.norm(P - ref, axis=1)
    assert err.mean() < 2.0, err.mean()
    # a whole-pixel shift (the 1-based .pts convention) would show as a mean offset of 1
    assert np.abs(np.median(P - ref, axis=0)).max() < 0.5
    assert box[0] < ref[:, 0].min() + 40 and box[0] + box[2] > ref[:, 0].max() - 40


@needs_detector
def test_track_detect_closes_the_eyes_on_the_blink(real_clip, tmp_path):
    from retarget_cli.methods.tracking.detect import eye_opening

    out, ov = tmp_path / "lm.npz", tmp_path / "overlay.mp4"
    r = run("track", real_clip / "d3.avi", "--method", "detect", "-o", out, "--overlay", ov)
    assert r.exit_code == 0, r.output
    lm = load_landmarks(out)
    assert lm.points.shape == (60, 68, 2) and lm.meta["tracker"] == "detect"
    assert np.isfinite(lm.stabilized).all() and (lm.confidence > 0).all()
    assert ov.stat().st_size > 0 and (tmp_path / "lm.init_00000.pts").is_file()
    e = eye_opening(lm.points)
    open_eyes = np.median(e[:40])
    assert e[BLINK].min() < 0.65 * open_eyes, (e[BLINK], open_eyes)
    assert e[53:56].max() > 0.9 * open_eyes  # and they open again (from 56 on she looks down)
    # lk, anchored to the open eyes of frame 0, does not follow the blink as far
    lk = tmp_path / "lk.npz"
    assert run("track", real_clip / "d3.avi", "--method", "lk", "--init", real_clip / "d3_00000.pts",
               "-o", lk).exit_code == 0
    e_lk = eye_opening(load_landmarks(lk).points)
    assert e[BLINK].min() / open_eyes < e_lk[BLINK].min() / np.median(e_lk[:40])


@needs_detector
def test_track_detect_range_step_downscale(real_clip, tmp_path):
    full, part = tmp_path / "full.npz", tmp_path / "part.npz"
    assert run("track", real_clip / "d3.avi", "--method", "detect", "-o", full, "--end", 20).exit_code == 0
    r = run("track", real_clip / "d3.avi", "--method", "detect", "-o", part, "--start", 4, "--end", 20,
            "--step", 3, "--downscale", 0.5)
    assert r.exit_code == 0, r.output
    a, b = load_landmarks(full), load_landmarks(part)
    assert b.frames.tolist() == [4, 7, 10, 13, 16, 19] and (tmp_path / "part.init_00004.pts").is_file()
    # at half resolution the landmarks stay within a few full-resolution pixels
    assert np.linalg.norm(b.points - a.points[b.frames], axis=2).mean() < 4.0


@needs_detector
def test_init_auto_writes_its_annotation_and_never_overwrites_another(real_clip, tmp_path):
    out = tmp_path / "lk.npz"
    r = run("track", real_clip / "d3.avi", "--method", "lk", "-o", out, "--end", 10)  # init omitted: auto
    assert r.exit_code == 0, r.output
    pts = tmp_path / "lk.init_00000.pts"
    assert str(pts) in r.output
    auto = read_pts(pts)
    assert np.linalg.norm(auto - read_pts(real_clip / "d3_00000.pts"), axis=1).mean() < 2.0
    lm = load_landmarks(out)
    assert np.allclose(lm.points[0], auto, atol=1e-3) and lm.meta["init"] == "auto"
    assert run("track", real_clip / "d3.avi", "--method", "lk", "--init", "auto", "-o", out, "--end", 10).exit_code == 0
    pts.write_text(pts.read_text().replace("version: 1", "version: 1 "))  # edited by hand
    msg = one_line_error(run("-q", "track", real_clip / "d3.avi", "--method", "lk", "-o", out, "--end", 10))
    assert str(pts) in msg and "refusing to overwrite" in msg


@needs_detector
def test_config_without_init_annotates_automatically(real_clip, tmp_path):
    cfg_path = tmp_path / "config.yaml"
    cfg_path.write_text(f"output_dir: out\ntrack: {{video: {real_clip / 'd3.avi'}, end: 5}}\n")
    cfg = load_config(cfg_path, stage_params())
    kw = resolve(cfg, "track")
    assert kw["init"] is None and _inputs(STAGES["track"], kw) == [real_clip / "d3.avi"]
    run_pipeline(cfg)
    man = json.loads((tmp_path / "out" / ".retarget" / "track.json").read_text())
    assert "landmarks.init_00000.pts" in {p.split("/")[-1] for p in man["outputs"]}
    assert [s for _, s, _ in run_pipeline(cfg)] == ["skipped"]


@needs_detector
def test_rerun_with_init_auto_tracks_again_in_place(real_clip, tmp_path):
    """Issue 27 item 6: --force and a changed tracking setting rerun track over its own landmarks and annotation."""
    cfg = tmp_path / "config.yaml"
    cfg.write_text(f"output_dir: out\ntrack: {{video: {real_clip / 'd3.avi'}, init: auto, method: detect, end: 8}}\n")
    out, pts = tmp_path / "out" / "landmarks.npz", tmp_path / "out" / "landmarks.init_00000.pts"
    assert run("run", cfg).exit_code == 0
    first = pts.read_text()
    r = run("run", cfg, "--force")
    assert r.exit_code == 0 and "track: ran" in r.output, r.output
    r = run("run", cfg, "--set", "track.fuse=false")  # another setting: frame 0's points, so the .pts, change
    assert r.exit_code == 0 and "track: ran" in r.output, r.output
    assert pts.read_text() != first
    lm = load_landmarks(out)
    assert np.allclose(read_pts(pts), lm.points[0] if lm.points_raw is None else lm.points_raw[0], atol=1e-3)
    pts.write_text(pts.read_text() + "\n")  # corrected by hand: now the user's, never overwritten
    r = run("-q", "run", cfg, "--force")
    assert r.exit_code == 1 and "refusing to overwrite" in r.output and str(pts) in r.output, r.output


@needs_detector
def test_a_calibration_image_is_the_neutral_of_a_take_that_starts_elsewhere(real_clip, tmp_path):
    """Issue 27 item 2: track.neutral, a separate image of the actor at rest, tracked like the take."""
    from retarget_cli.methods.neutral import face_openings

    cap = cv2.VideoCapture(str(real_clip / "d3.avi"))
    ok, frame = cap.read()  # frame 0: at rest (the take below starts at frame 20)
    cap.release()
    assert ok and cv2.imwrite(str(tmp_path / "calm.png"), frame)
    cfg = tmp_path / "config.yaml"
    cfg.write_text(f"output_dir: out\ntrack: {{video: {real_clip / 'd3.avi'}, start: 20, method: detect, "
                   "neutral: calm.png}\nselect: {k: 6, regions: {brows-eyes: null, mouth: null}}\n"
                   "decompose: {formulation: delta}\n")
    r = run("run", cfg)
    assert r.exit_code == 0, r.output
    lm = load_landmarks(tmp_path / "out" / "landmarks.npz")
    assert lm.neutral.shape == (68, 2) and lm.meta["neutral"]["file"] == "calm.png"
    assert lm.meta["neutral"]["frames"] == 1
    keys = json.loads((tmp_path / "out" / "keys.json").read_text())
    assert keys["neutral"]["source"] == "calibration" and "calm.png" in keys["neutral"]["reason"]
    np.testing.assert_allclose(keys["neutral"]["shape"], lm.neutral, atol=1e-3)
    man = json.loads((tmp_path / "out" / ".retarget" / "decompose.json").read_text())
    assert man["results"]["neutral"]["source"] == "calibration"
    man = json.loads((tmp_path / "out" / ".retarget" / "track.json").read_text())
    assert any(p.endswith("calm.png") for p in man["inputs"])  # an input: a new calibration reruns track
    # the calibration's lips and lids, in the take's coordinates, are frame 0's
    full = tmp_path / "full.npz"
    assert run("track", real_clip / "d3.avi", "--method", "detect", "--end", 2, "-o", full).exit_code == 0
    want, got = face_openings(load_landmarks(full).stabilized[:1]), face_openings(lm.neutral[None])
    for k in want:
        assert abs(got[k][0] - want[k][0]) < 0.02, (k, got[k], want[k])
    iod = np.linalg.norm(lm.stabilized[:, 36] - lm.stabilized[:, 45], axis=1).mean()
    assert abs(np.linalg.norm(lm.neutral[36] - lm.neutral[45]) / iod - 1) < 0.05  # the take's scale


def test_init_auto_in_a_config_names_no_file(tmp_path):
    cfg_path = tmp_path / "config.yaml"
    cfg_path.write_text("track: {video: v.mp4, init: auto}\n")
    (tmp_path / "v.mp4").write_bytes(b"")
    kw = resolve(load_config(cfg_path, stage_params()), "track")
    assert kw["init"] == "auto"
    assert _inputs(STAGES["track"], kw) == [tmp_path.resolve() / "v.mp4"]


@needs_detector
def test_annotate_writes_the_requested_frames(real_clip, tmp_path):
    out = tmp_path / "ann"
    r = run("annotate", real_clip / "d3.avi", "--frames", "0,30-50:20", "-o", out)
    assert r.exit_code == 0, r.output
    files = sorted(p.name for p in out.iterdir())
    assert files == ["d3_00000.pts", "d3_00030.pts", "d3_00050.pts"]
    P0, P30 = read_pts(out / "d3_00000.pts"), read_pts(out / "d3_00030.pts")
    assert P0.shape == (68, 2)
    assert np.linalg.norm(P0 - read_pts(real_clip / "d3_00000.pts"), axis=1).mean() < 2.0
    assert np.abs(P30 - P0).max() > 1.0  # a different frame, not a copy
    msg = one_line_error(run("-q", "annotate", real_clip / "d3.avi", "--frames", "75", "-o", out))
    assert "frame 75" in msg and "past the last frame" in msg


@needs_detector
@pytest.mark.parametrize("args, frame", [
    (["track", "--method", "detect"], 0),
    (["track", "--start", "2"], 2),  # lk with the automatic annotation
    (["annotate", "--frames", "1"], 1),
])
def test_no_face_is_a_one_line_error_naming_the_frame(black_video, tmp_path, args, frame):
    out = ["-o", tmp_path / ("ann" if args[0] == "annotate" else "lm.npz")]
    msg = one_line_error(run("-q", args[0], black_video, *args[1:], *out))
    assert f"frame {frame}: no face found" in msg and str(black_video) in msg
    assert not (tmp_path / "lm.npz").exists()


@pytest.mark.parametrize("args", [["track", "--method", "detect"], ["track"], ["annotate", "--frames", "0"]])
def test_missing_extra_gives_the_install_hint(real_clip, tmp_path, monkeypatch, args):
    monkeypatch.setitem(sys.modules, "dlib", None)  # import dlib raises ImportError
    msg = one_line_error(run("-q", args[0], real_clip / "d3.avi", *args[1:], "-o", tmp_path / "x"))
    assert "retarget[detect]" in msg and "dlib" in msg
    # a hand-made annotation needs no extra
    r = run("track", real_clip / "d3.avi", "--init", real_clip / "d3_00000.pts", "--end", 3, "-o", tmp_path / "a.npz")
    assert r.exit_code == 0, r.output
