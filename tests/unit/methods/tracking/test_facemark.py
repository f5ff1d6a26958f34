"""Facemark LBF: training in OpenCV's layout, OpenCV's fit, tracking, lost face, bad model files."""

import numpy as np
import pytest

from retarget_cli.errors import InputError, ShapeError
from retarget_cli.io.atomic import load_npz
from retarget_cli.io.facemark_model import lbf_model_text, load_facemark, save_lbf_model
from retarget_cli.io.video import VideoReader
from retarget_cli.methods.tracking.facemark import face_box, track_facemark, train_lbf
from retarget_cli.methods.tracking.lk import FaceLostError

#: Small cascade so the suite stays quick (the defaults are larger; see the README for their accuracy).
FAST = dict(stages=3, trees=2, depth=3, copies=4, candidates=50)
ANNOTATED = [0, 12, 24, 36, 48]


@pytest.fixture(scope="module")
def clip(small_take_template):
    frames = list(VideoReader(small_take_template / "face.mp4"))
    truth = load_npz(small_take_template / "truth_landmarks.npz")["points"].astype(np.float64)
    return frames, truth


@pytest.fixture(scope="module")
def trained(clip, tmp_path_factory):
    frames, truth = clip
    model = train_lbf([frames[f] for f in ANNOTATED], truth[ANNOTATED], **FAST)
    path = tmp_path_factory.mktemp("facemark") / "model.yaml"
    save_lbf_model(path, model)
    return model, path


def test_opencv_fit_matches_the_numpy_cascade_it_was_trained_with(clip, trained):
    frames, truth = clip
    model, path = trained
    fitter = load_facemark(path)
    assert fitter.n_points == 68 and fitter.info["retarget_annotated_frames"] == 5
    import cv2

    for t in (3, 20, 41, 59):
        gray = cv2.cvtColor(frames[t], cv2.COLOR_BGR2GRAY)
        box = face_box(truth[t] + (2.0, -3.0))
        np.testing.assert_allclose(fitter.fit(gray, box), model.predict(gray, box), atol=1e-3)


def test_tracks_within_bound_from_five_annotated_frames(clip, trained):
    frames, truth = clip
    pts, conf = track_facemark(frames, {0: truth[0]}, model=load_facemark(trained[1]))
    err = np.linalg.norm(pts - truth, axis=2)
    assert pts.shape == truth.shape and conf.shape == truth.shape[:2]
    assert err.mean() < 0.8, err.mean()  # measured 0.43 px
    assert np.percentile(err.mean(1), 90) < 1.5
    np.testing.assert_array_equal(pts[0], truth[0])
    assert np.all(conf[0] == 1) and conf.mean() > 0.8


def test_gzip_model_and_deterministic_training(clip, trained, tmp_path):
    frames, truth = clip
    model, path = trained
    again = train_lbf([frames[f] for f in ANNOTATED], truth[ANNOTATED], **FAST)
    assert lbf_model_text(again) == path.read_text()
    gz = tmp_path / "model.yaml.gz"
    save_lbf_model(gz, model)
    assert gz.stat().st_size < path.stat().st_size
    import cv2

    gray = cv2.cvtColor(frames[7], cv2.COLOR_BGR2GRAY)
    box = face_box(truth[7])
    np.testing.assert_allclose(load_facemark(gz).fit(gray, box), load_facemark(path).fit(gray, box), atol=1e-6)


def test_lost_face_is_reported_not_papered_over(clip, trained):
    frames, truth = clip
    blanked = [f if t < 30 else np.full_like(f, 128) for t, f in enumerate(frames)]
    with pytest.raises(FaceLostError, match="lost from frame 30") as info:
        track_facemark(blanked, {0: truth[0]}, model=load_facemark(trained[1]))
    assert info.value.frame == 30 and info.value.points.shape == (30, 68, 2)
    # a face that comes back within lost_frames keeps being tracked, with confidence 0 while it is gone
    gap = [f if not 30 <= t < 34 else np.full_like(f, 128) for t, f in enumerate(frames)]
    pts, conf = track_facemark(gap, {0: truth[0]}, model=load_facemark(trained[1]))
    assert np.all(conf[30:34] == 0) and conf[40:].mean() > 0.8
    assert np.linalg.norm(pts[40:] - truth[40:], axis=2).mean() < 1.0


def test_bad_models_and_point_counts(clip, trained, tmp_path):
    frames, truth = clip
    with pytest.raises(InputError, match="nothere.yaml: Facemark model file not found"):
        load_facemark(tmp_path / "nothere.yaml")
    other = tmp_path / "other.yaml"
    other.write_text("%YAML:1.0\n---\nfoo: 1\n")
    with pytest.raises(InputError, match="other.yaml: not a Facemark LBF model"):
        load_facemark(other)
    junk = tmp_path / "junk.yaml"
    junk.write_bytes(b"\x00\x01 not yaml {{{")
    with pytest.raises(InputError, match="junk.yaml: not a Facemark LBF model"):
        load_facemark(junk)
    with pytest.raises(ShapeError, match="annotations have 10 points but the Facemark model was trained for 68"):
        track_facemark(frames[:3], {0: truth[0, :10]}, model=load_facemark(trained[1]))
    with pytest.raises(ShapeError, match=r"shapes: expected \(2, L, 2\)"):
        train_lbf(frames[:2], truth[:3], **FAST)


def test_working_face_size_scales_training_and_tracking_alike(clip, tmp_path):
    frames, truth = clip
    model = train_lbf([frames[f] for f in ANNOTATED], truth[ANNOTATED], **FAST, face_size=80)
    assert model.info["retarget_face_size"] == 80
    save_lbf_model(tmp_path / "small.yaml", model)
    fitter = load_facemark(tmp_path / "small.yaml")
    assert fitter.face_size == 80
    pts, conf = track_facemark(frames, {0: truth[0], 30: truth[30]}, model=fitter)
    np.testing.assert_array_equal(pts[[0, 30]], truth[[0, 30]])  # annotations returned at full resolution
    err = np.linalg.norm(pts - truth, axis=2).mean()
    assert err < 0.9, err  # measured 0.55 px (0.43 at full resolution) with frames scaled by about 0.7
