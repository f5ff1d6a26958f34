"""The gaze read from the eyes' pixels kept while tracking (CropSpill, eye_crop, crops_cover) is the gaze read
from the whole frames: what ``track`` does instead of decoding the video a second time (issue #31)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from detector_marks import needs_detector

from retarget_cli.io.atomic import CropSpill
from retarget_cli.methods.tracking.gaze import EYES_68, crops_cover, eye_crop, gaze, patch_reads

SAMPLE = Path(__file__).resolve().parents[4] / "sample_data"


def _eyes(rng, T=12, size=(160, 120)):
    """*T* textured gray frames (W, H = *size*) and 68 points whose two eyes are turned, scaled and placed
    anywhere, the first frames' eyes over the image's edges (what a patch reads there is the border's)."""
    W, H = size
    frames, points = [], []
    for t in range(T):
        img = cv2.GaussianBlur(rng.uniform(0, 255, (H, W)), (0, 0), 1.5)
        img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
        P = np.zeros((68, 2))
        w = rng.uniform(12, 30)
        angle = rng.uniform(-0.6, 0.6)
        u = np.array([np.cos(angle), np.sin(angle)])
        n = np.array([-u[1], u[0]])
        centre = [(2.0, 3.0), (W - 3.0, H - 2.0)][t] if t < 2 else rng.uniform([20, 20], [W - 20, H - 20])
        for k, eye in enumerate(EYES_68):
            mid = np.asarray(centre) + (k - 0.5) * 1.6 * w * u
            P[eye[0]], P[eye[1]] = mid - w / 2 * u, mid + w / 2 * u
            for a, b, s in zip(eye[2], eye[3], (-0.2, 0.2)):
                P[a], P[b] = mid + s * w * u - 0.2 * w * n, mid + s * w * u + 0.2 * w * n
        frames.append(img)
        points.append(P)
    return frames, np.array(points)


def _spill(tmp_path, frames, boxes):
    spill = CropSpill(tmp_path / "out.npz")
    for img, b in zip(frames, boxes):
        spill.add(img, b)
    return spill


def test_the_gaze_on_the_pixels_it_reads_only_is_the_gaze_on_the_whole_frames(tmp_path):
    """Each frame kept only where its eye patches read (patch_reads clamped to the image: the smallest box
    crops_cover accepts), the rest of the image left with other frames' pixels: the same gaze, bit for bit."""
    frames, P = _eyes(np.random.default_rng(0))
    size = (frames[0].shape[1], frames[0].shape[0])
    need = patch_reads(P)
    W, H = size
    tight = np.stack([need[..., 0].min(1).clip(0, W - 1), need[..., 1].min(1).clip(0, H - 1),
                      need[..., 2].max(1).clip(1, W), need[..., 3].max(1).clip(1, H)], axis=1)
    with _spill(tmp_path, frames, tight) as spill:
        assert len(spill) == len(frames)
        assert crops_cover(spill.boxes(), P, None, size).all()
        a = gaze(frames, P)
        b = gaze(spill.frames(size), P)
    assert np.isfinite(a.offset).all() and not a.held.all()
    for x, y in zip((a.offset, a.opening, a.held), (b.offset, b.opening, b.held)):
        assert np.array_equal(x, y)
    assert not list(tmp_path.iterdir())  # the spill's file removed on close


def test_a_kept_rectangle_short_of_what_a_patch_reads_is_not_covered(tmp_path):
    frames, P = _eyes(np.random.default_rng(1))
    size = (frames[0].shape[1], frames[0].shape[0])
    boxes = np.array([eye_crop(p) for p in P])
    with _spill(tmp_path, frames, boxes) as spill:
        kept = spill.boxes()
        assert crops_cover(kept, P, None, size).all()
        short = kept.copy()
        short[5, 2] = patch_reads(P[5:6])[0, :, 2].max() - 2  # two columns short on the right of frame 5
        assert crops_cover(short, P, None, size).tolist() == [t != 5 for t in range(len(P))]
        # an eye the gaze skips (a point of confidence below 0.1) needs nothing
        conf = np.ones(P.shape[:2])
        conf[5, [e[1] for e in EYES_68]] = 0.0
        assert crops_cover(short, P, conf, size).all()
        conf[5] = np.nan  # NaN confidences: the gaze reads the eyes, so they must be there
        assert not crops_cover(short, P, conf, size)[5]


def test_landmarks_moved_within_the_margin_are_still_covered():
    """eye_crop keeps CROP_MARGIN eye widths around the patches: the final landmarks may lie a little off those
    tracked so far."""
    frames, P = _eyes(np.random.default_rng(2), size=(400, 300))
    size = (400, 300)
    boxes = np.array([eye_crop(p) for p in P])
    boxes[:, 0::2] = boxes[:, 0::2].clip(0, 400)
    boxes[:, 1::2] = boxes[:, 1::2].clip(0, 300)
    moved = P + np.random.default_rng(3).uniform(-2, 2, P.shape)
    assert crops_cover(boxes, moved, None, size).all()
    assert not crops_cover(boxes, P + [40.0, 0.0], None, size)[2:].any()


@needs_detector
def test_track_reads_the_gaze_from_the_kept_eyes_and_writes_the_file_of_a_second_decoding(tmp_path, monkeypatch,
                                                                                          caplog):
    """run_track with the eyes kept while tracking gives the landmarks.npz of the same run that decodes the video
    again for the gaze (crops_cover refused, or the crops' file could not be written), and leaves no temporary
    file."""
    import retarget_cli.stages.track as track_stage
    from retarget_cli.stages import run_track

    read = []
    frames = CropSpill.frames

    def spy(self, *a, **kw):
        read.append(1)
        return frames(self, *a, **kw)

    monkeypatch.setattr(CropSpill, "frames", spy)
    kw = dict(video=str(SAMPLE / "face.mp4"), init="auto", start=40, end=70)
    run_track(output=str(tmp_path / "a" / "lm.npz"), **kw)
    assert read == [1]
    monkeypatch.setattr(track_stage, "crops_cover", lambda boxes, *a: np.zeros(len(boxes), bool))
    run_track(output=str(tmp_path / "b" / "lm.npz"), **kw)
    assert read == [1]
    # the crops cannot be written (a full disk, say): a warning, the video decoded again, the same file
    monkeypatch.undo()
    add = CropSpill.add

    def full(self, *a):
        if len(self) == 5:
            raise OSError(28, "No space left on device")
        add(self, *a)

    monkeypatch.setattr(CropSpill, "add", full)
    with caplog.at_level("WARNING"):
        run_track(output=str(tmp_path / "c" / "lm.npz"), **kw)
    assert "could not be kept for the gaze" in caplog.text
    # a long take: past CROPS_MAX_BYTES the crops are dropped (their disk freed), the video decoded again
    monkeypatch.undo()
    monkeypatch.setattr(track_stage, "CROPS_MAX_BYTES", 1)
    kept = []
    discard = CropSpill.discard

    def spy_discard(self):
        kept.append((len(self), self.path.is_file()))
        discard(self)
        assert len(self) == 0 and not self.path.is_file()

    monkeypatch.setattr(CropSpill, "discard", spy_discard)
    monkeypatch.setattr(CropSpill, "frames", spy)
    run_track(output=str(tmp_path / "d" / "lm.npz"), **kw)
    assert kept == [(1, True)] and read == [1]  # dropped after the first frame; never read back
    for other in ("b", "c", "d"):
        with np.load(tmp_path / "a" / "lm.npz") as a, np.load(tmp_path / other / "lm.npz") as b:
            assert "gaze" in a.files and a["gaze_valid"].any()
            for k in a.files:
                if k != "meta":
                    assert np.array_equal(a[k], b[k]), (other, k)
    for d in ("a", "b", "c", "d"):
        assert not [p.name for p in (tmp_path / d).iterdir() if ".part" in p.name]


def test_a_crop_spill_takes_gray_uint8_frames_only(tmp_path):
    from retarget_cli.errors import ParameterError

    with CropSpill(tmp_path / "x.npz") as spill, pytest.raises(ParameterError, match="gray uint8"):
        spill.add(np.zeros((4, 4, 3), np.uint8), (0, 0, 2, 2))
