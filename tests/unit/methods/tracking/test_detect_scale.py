"""``track_detect(downscale="auto")``: the frames reduced by a whole factor chosen from the first face, coordinates
at full resolution; the cut test's thumbnail of a large frame."""

from pathlib import Path

import cv2
import numpy as np
import pytest
from detector_marks import needs_detector

from retarget_cli.methods.gaps import CUT_THUMB, CutDetector
from retarget_cli.methods.tracking import detect
from retarget_cli.methods.tracking.detect import AUTO_SPAN, Detector, auto_downscale, track_detect

SAMPLE = Path(__file__).resolve().parents[4] / "sample_data"
FRAMES = 12


@pytest.mark.parametrize("span, factor", [(40.0, 1.0), (AUTO_SPAN, 1.0), (2 * AUTO_SPAN - 1, 1.0),
                                          (2 * AUTO_SPAN, 0.5), (275.0, 1 / 3), (float("nan"), 1.0), (0.0, 1.0)])
def test_auto_downscale_is_the_largest_whole_reduction_keeping_the_span(span, factor):
    assert auto_downscale(span) == factor


@pytest.fixture(scope="module")
def d3():
    """The first frames of the bundled real clip (512x512, eye-corner span about 130 px), gray."""
    cap = cv2.VideoCapture(str(SAMPLE / "real" / "d3.mp4"))
    frames = []
    while len(frames) < FRAMES:
        ok, f = cap.read()
        assert ok
        frames.append(cv2.cvtColor(f, cv2.COLOR_BGR2GRAY))
    cap.release()
    return frames


@pytest.fixture(scope="module")
def detector():
    return Detector()


@needs_detector
def test_auto_keeps_a_512_clip_at_full_resolution_byte_for_byte(d3, detector):
    full = track_detect(iter(d3), detector=detector, downscale=1.0)
    auto = track_detect(iter(d3), detector=detector, downscale="auto")
    for a, b in zip(full, auto):
        assert a.tobytes() == b.tobytes()


@needs_detector
def test_auto_tracks_an_upscaled_clip_at_half_and_reports_full_resolution(d3, detector, caplog):
    """d3 upscaled 2x (1024x1024: span about 260 px) is tracked at 1/2, so on frames close to the original: the
    points, halved, agree with the original clip's within a pixel on average, and the run is deterministic."""
    big = [cv2.resize(g, (1024, 1024), interpolation=cv2.INTER_LINEAR) for g in d3]
    ref, _ = track_detect(iter(d3), detector=detector)
    with caplog.at_level("INFO", logger=detect.__name__):
        pts, conf = track_detect(iter(big), detector=detector, downscale="auto")
    assert "tracking at 1/2" in caplog.text
    assert pts.shape == (FRAMES, 68, 2) and conf.shape == (FRAMES, 68)
    # pixel centres: x_full = (x_half + 0.5) * 2 - 0.5; the original's x = (x_full + 0.5) / 2 - 0.5
    back = (pts + 0.5) / 2 - 0.5
    err = np.linalg.norm(back - ref, axis=-1)
    assert err.mean() < 1.0 and np.median(err) < 1.0, (err.mean(), np.median(err))
    again, _ = track_detect(iter(big), detector=detector, downscale="auto")
    assert again.tobytes() == pts.tobytes()
    # not the same as tracking the upscaled frames at full resolution (the factor was used)
    full, _ = track_detect(iter(big[:3]), detector=detector, downscale=1.0)
    assert full.tobytes() != pts[:3].tobytes()


@needs_detector
def test_auto_uses_an_annotated_first_frame_for_the_span(d3, detector, caplog):
    big = [cv2.resize(g, (1024, 1024), interpolation=cv2.INTER_LINEAR) for g in d3[:4]]
    first, _ = track_detect(iter(big[:1]), detector=detector, downscale=1.0)
    calls = []
    real = detector.detect
    detector.detect = lambda g: calls.append(g.shape) or real(g)
    try:
        pts, _ = track_detect(iter(big), {0: first[0]}, detector=detector, downscale="auto")
    finally:
        del detector.detect
    assert calls == []  # no whole-frame search: the annotation gave the span and the box
    assert np.array_equal(pts[0], first[0])


def test_auto_refuses_another_word(d3):
    from retarget_cli.errors import ShapeError

    with pytest.raises(ShapeError, match="downscale"):
        track_detect(iter(d3[:1]), detector=object(), downscale="half")


def test_cut_thumbnail_of_a_large_frame_is_the_area_average_within_a_level():
    """A 1920x1080 frame (ratio to the thumbnail not whole): reduced by a whole factor first, the thumbnail
    stays within two grey levels of OpenCV's one-step area average (rounding twice; a cut is a mean change of
    :data:`~retarget_cli.methods.gaps.CUT_THRESHOLD`, about 30 levels); a 512x512 frame is unchanged."""
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (1080, 1920)).astype(np.float32), (0, 0), 6.0)
    img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    thumb, hist = CutDetector.features(img)
    direct = cv2.resize(img, (CUT_THUMB, CUT_THUMB), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
    assert thumb.shape == (CUT_THUMB, CUT_THUMB)
    diff = np.abs(thumb - direct) * 255
    assert diff.max() <= 2.01 and diff.mean() < 0.5, (diff.max(), diff.mean())
    assert np.isclose(hist.sum(), 1.0)
    small = img[:512, :512]
    t2, _ = CutDetector.features(small)
    assert np.array_equal(t2, cv2.resize(small, (CUT_THUMB, CUT_THUMB), interpolation=cv2.INTER_AREA)
                          .astype(np.float32) / 255)
