"""Detection + optical flow fusion (track.detect.FlowFusion) and the default tracker on a synthetic blink."""

from pathlib import Path

import cv2
import numpy as np
import pytest
from detector_marks import needs_detector

from retarget_cli.methods.tracking.detect import FlowFusion, FusionSettings, eye_opening

SAMPLE = Path(__file__).resolve().parents[4] / "sample_data"


def _face_points(rng):
    """68 points of a face-like layout in a 200x200 frame: eye corners 36, 39, 42, 45 set for the span."""
    P = rng.uniform(60, 140, (68, 2))
    P[36], P[39], P[42], P[45] = (70, 90), (90, 90), (110, 90), (130, 90)
    return P


def _textured(seed=0, size=200):
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (size, size)).astype(np.float32), (0, 0), 2.0)
    return cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def _shift(img, dx):
    M = np.float32([[1, 0, dx], [0, 1, 0]])
    return cv2.warpAffine(img, M, (img.shape[1], img.shape[0]), borderMode=cv2.BORDER_REFLECT)


def test_fusion_averages_detection_jitter_along_the_flow():
    """A textured frame moving 1 px/frame: detections with 2 px jitter (0.05 of the 40 px eye-corner span,
    the noise the settings declare) come out much steadier."""
    rng = np.random.default_rng(1)
    base, P0 = _textured(), _face_points(rng)
    T = 40
    truth = np.stack([P0 + [t * 1.0, 0] for t in range(T)])
    det = truth + rng.normal(0, 2.0, truth.shape)
    fuser = FlowFusion(FusionSettings(sigma_detection=0.05, lid_lip_motion=0.01))
    fwd = np.stack([fuser.step(_shift(base, t * 1.0), det[t], np.ones(68)) for t in range(T)])
    smooth = fuser.smooth()
    err = lambda X: np.sqrt(((X[5:] - truth[5:]) ** 2).sum(-1).mean())  # noqa: E731
    assert err(fwd) < 0.6 * err(det), (err(fwd), err(det))
    assert err(smooth) < 0.8 * err(fwd), (err(smooth), err(fwd))


def test_fusion_follows_a_change_of_shape_the_flow_misses():
    """Static frames (flow 0) but the detection jumps 8 px for 3 frames: the track reaches >= 90 % of it."""
    rng = np.random.default_rng(2)
    img, P0 = _textured(3), _face_points(rng)
    det = np.repeat(P0[None], 30, axis=0)
    det[12:15, 37:42, 1] += 8.0  # an eyelid closing for 3 frames
    fuser = FlowFusion()
    for t in range(30):
        fuser.step(img, det[t], np.ones(68))
    out = fuser.smooth()
    assert (out[12:15, 37:42, 1] - P0[37:42, 1] >= 0.9 * 8.0).all(), out[12:15, 37:42, 1] - P0[37:42, 1]
    # and steady points are not dragged along
    assert np.abs(out[:, 48:] - P0[48:]).max() < 0.1


def test_fusion_without_a_detection_follows_the_flow():
    img, P0 = _textured(4), _face_points(np.random.default_rng(3))
    fuser = FlowFusion()
    fuser.step(img, P0, np.ones(68))
    x = fuser.step(_shift(img, 3.0), None, None)
    assert np.abs(np.median(x - P0, axis=0) - [3.0, 0.0]).max() < 0.3


def test_annotated_frames_are_taken_exactly_and_reset_forgets_the_track():
    img, P0 = _textured(5), _face_points(np.random.default_rng(4))
    fuser = FlowFusion(FusionSettings(sigma_detection=0.05))
    fuser.step(img, P0, np.ones(68))
    exact = P0 + 0.7
    np.testing.assert_allclose(fuser.step(img, exact, np.ones(68), exact=True), exact, atol=1e-9)
    far = P0 + 40.0
    np.testing.assert_array_equal(fuser.step(img, far, np.ones(68), reset=True), far)


@needs_detector
def test_default_tracker_follows_a_synthetic_blink_that_lk_misses(tmp_path):
    """sample_data's take blinks at frame 70 (truth eye opening 0.02 of the eye width against 0.31 open).

    The default method (detect, fused with flow) closes the eyes about half way there; lk, anchored to
    the open eyes of the annotation, hardly moves. The issue's target (90 % of the true closure) is not
    reached: dlib's predictor itself stops at 0.14-0.15 on the closed frames (it puts the lids on the
    two edges of the dark lash band the closed eye shows, the upper lid 0.12 eye widths above the
    truth), at any frame scale (0.5-3x) and with the box placed from the truth; the fusion keeps
    what it detects (test_fusion_keeps_the_detectors_blink).
    """
    from retarget_cli.io.landmarks import load_landmarks
    from retarget_cli.run.pipeline import stage_params
    from retarget_cli.stages import run_track

    assert {p.name: p.default for p in stage_params()["track"]}["method"] == "auto"
    with np.load(SAMPLE / "truth_landmarks.npz") as d:
        truth = eye_opening(d["points"][40:100])
    blink = slice(27, 34)  # frames 67-73
    true_closure = np.median(truth) - truth[blink].min()
    assert true_closure > 0.25

    def closure(**kw):
        out = tmp_path / f"{kw.get('method', 'default')}.npz"
        run_track(video=str(SAMPLE / "face.mp4"), output=str(out), start=40, end=100, **kw)
        lm = load_landmarks(out)
        e = eye_opening(lm.points)
        return (np.median(e) - e[blink].min()) / true_closure, lm.meta["tracker"]

    fused, tracker = closure(init="auto", filter="none")  # the tracker alone (the landmark filter: test_filter)
    assert tracker == "detect"
    lk, _ = closure(init=str(tmp_path / "default.init_00040.pts"), method="lk", filter="none")
    assert fused >= 0.45, fused
    assert lk < 0.1, lk


@needs_detector
def test_fusion_keeps_the_detectors_blink():
    """On sample_data's blink (frames 67-73) the fused track closes the eyes as far as the raw detections.

    Optical flow cannot follow a closing lid (its window sees the skin stretch, not the lid's edge), so
    the fusion must not pull the lid points back towards the flow: the closure of the fused track is at
    least 95 % of the raw detector's (both measured like the default-tracker test above).
    """
    from retarget_cli.io.frames import FrameSource
    from retarget_cli.methods.tracking.detect import Detector, track_detect

    with FrameSource(str(SAMPLE / "face.mp4"), start=40, end=100, gray=True) as src:
        frames = list(src)
    det = Detector()
    blink = slice(27, 34)

    def closure(points):
        e = eye_opening(points)
        return np.median(e) - e[blink].min()

    raw, _ = track_detect(frames, detector=det, fuse=False)
    fused, _ = track_detect(frames, detector=det)
    assert closure(raw) > 0.1, closure(raw)  # the detector does see a blink
    assert closure(fused) >= 0.95 * closure(raw), (closure(fused), closure(raw))


@needs_detector
def test_track_cli_no_fuse_keeps_the_raw_detections(tmp_path):
    """`retarget track --no-fuse --filter none` gives the detector's own points; the default fuses them."""
    from click.testing import CliRunner

    from retarget_cli.cli.commands import main
    from retarget_cli.io.landmarks import load_landmarks

    runs = {}
    for name, extra in (("raw", ["--no-fuse"]), ("fused", [])):
        out = tmp_path / f"{name}.npz"
        r = CliRunner().invoke(main, ["track", str(SAMPLE / "face.mp4"), "--method", "detect", "--end", "20",
                                      "--filter", "none", "-o", str(out), *extra])
        assert r.exit_code == 0, r.output
        runs[name] = load_landmarks(out)
    assert runs["raw"].meta["parameters"]["fuse"] is False and runs["fused"].meta["parameters"]["fuse"] is True
    assert not np.allclose(runs["raw"].points[1:], runs["fused"].points[1:], atol=1e-3)


@needs_detector
def test_threaded_tracker_gives_the_sequential_result():
    """track_detect with its worker threads (the next frame prepared, the flow beside the predictor) returns
    the very arrays of the sequential loop, with and without gaps (scene-cut test) and fusion."""
    from retarget_cli.io.frames import FrameSource
    from retarget_cli.methods.tracking.detect import Detector, track_detect

    with FrameSource(str(SAMPLE / "face.mp4"), start=40, end=100, gray=True) as src:
        frames = list(src)
    frames[30:] = frames[30:][::-1]  # a jump in the take: the cut test and a fresh detection on the way
    det = Detector()
    for kw in ({}, {"gaps": True}, {"fuse": False, "gaps": True}):
        seq = track_detect(frames, detector=det, threads=False, **kw)
        par = track_detect(iter(frames), detector=det, threads=True, **kw)
        assert len(seq) == len(par) == (3 if kw.get("gaps") else 2)
        for a, b in zip(seq[:2], par[:2]):
            assert a.shape[0] == len(frames)
            assert np.array_equal(a, b), kw
        if kw.get("gaps"):
            assert np.array_equal(seq[2].cuts, par[2].cuts) and np.array_equal(seq[2].status, par[2].status)


@needs_detector
def test_threaded_tracker_raises_a_bad_frame_where_the_sequential_one_does():
    from retarget_cli.errors import ShapeError
    from retarget_cli.io.frames import FrameSource
    from retarget_cli.methods.tracking.detect import Detector, track_detect

    with FrameSource(str(SAMPLE / "face.mp4"), start=40, end=50, gray=True) as src:
        frames = list(src)
    frames[6] = frames[6].astype(np.float32)
    det = Detector()
    for threads in (False, True):
        seen = []
        with pytest.raises(ShapeError, match="uint8"):
            track_detect(frames, detector=det, threads=threads, progress=seen.append)
        assert seen == list(range(6)), threads  # frames 0-5 tracked, then the error


@needs_detector
def test_track_stage_head_fits_beside_the_gaze_pass_give_the_sequential_file(tmp_path, monkeypatch):
    """run_track fits the head on a worker thread while the gaze pass runs; the file is the one of the same
    work done one after the other (an executor that runs each job when it is submitted)."""
    from concurrent.futures import Future

    import retarget_cli.stages.track as track_stage
    from retarget_cli.stages import run_track

    class InPlace:
        submitted = 0

        def __init__(self, *a, **kw):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def submit(self, fn, *args):
            InPlace.submitted += 1
            f = Future()
            f.set_result(fn(*args))
            return f

    kw = dict(video=str(SAMPLE / "face.mp4"), init="auto", start=40, end=70)
    run_track(output=str(tmp_path / "a.npz"), **kw)
    monkeypatch.setattr(track_stage, "ThreadPoolExecutor", InPlace)
    run_track(output=str(tmp_path / "b.npz"), **kw)
    assert InPlace.submitted == 1
    with np.load(tmp_path / "a.npz") as a, np.load(tmp_path / "b.npz") as b:
        assert "gaze" in a.files and "head_angles" in a.files
        for k in a.files:
            if k != "meta":
                assert np.array_equal(a[k], b[k]), k


@needs_detector
def test_threaded_tracker_ends_a_take_whose_face_has_left():
    """The face leaves and does not come back: the take ends as the sequential loop ends it. (The race this
    guards, a flow still queued behind two frame preparations when the pool was shut down before the last
    segment's smoother took it, shows with the real clip: tests/cli/test_gaps_cli.py's keep-partial test.)"""
    from retarget_cli.io.frames import FrameSource
    from retarget_cli.methods.tracking.detect import Detector, track_detect

    with FrameSource(str(SAMPLE / "face.mp4"), start=40, end=80, gray=True) as src:
        frames = list(src)
    frames[10:] = [np.zeros_like(f) for f in frames[10:]]
    det = Detector()
    seq = track_detect(frames, detector=det, threads=False, gaps=True)
    par = track_detect(iter(frames), detector=det, threads=True, gaps=True)
    for a, b in zip(seq[:2], par[:2]):
        assert a.shape[0] == len(frames)
        assert np.array_equal(a, b)
    assert np.array_equal(seq[2].status, par[2].status)
