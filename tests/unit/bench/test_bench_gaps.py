"""bench/gaps.py's scoring helpers: frames away from a change, flat reference series, the clean clip's encoding."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "bench"))

import gaps  # noqa: E402


def test_away_leaves_out_margin_frames_each_side():
    changed = np.zeros(30, bool)
    changed[15] = True
    ok = gaps.away(changed, margin=5)
    assert not ok[10:21].any()
    assert ok[:10].all() and ok[21:].all()


def test_flat_on_marks_a_reference_that_barely_moves():
    rng = np.random.default_rng(0)
    T = 60
    m = {"mouth": 0.001 * rng.standard_normal(T),           # closed throughout: std far below FLAT
         "eye_l": 0.3 + 0.05 * np.sin(np.arange(T) / 3.0),  # blinks: moves
         "eye_r": np.r_[np.zeros(30), 0.2 * rng.random(30)]}  # still on the first half only
    ref = {"m": m, "found": np.ones(T, bool)}
    assert gaps.flat_on(ref, np.arange(T)) == ["mouth"]
    assert gaps.flat_on(ref, np.arange(30)) == ["mouth", "eye_r"]
    ref["found"][30:] = False  # frames without a reference face do not count
    assert "eye_r" in gaps.flat_on(ref, np.arange(T))


def test_reencoded_is_the_clip_through_the_variants_encoder(tmp_path, monkeypatch):
    pytest.importorskip("cv2")
    rng = np.random.default_rng(1)
    frames = [np.clip(rng.normal(128, 40, (48, 64, 3)), 0, 255).astype(np.uint8) for _ in range(6)]
    monkeypatch.setattr(gaps, "DATA", tmp_path / "data")
    monkeypatch.setattr(gaps, "BUILD", tmp_path / "build")
    gaps.write_video(tmp_path / "data" / "videos" / "c.mp4", frames, 25.0)
    path = gaps.reencoded("c")
    assert path.parent == tmp_path / "build" / "videos" and path.is_file()
    got, fps = gaps.read_video(path)
    assert len(got) == 6 and got[0].shape == (48, 64, 3) and fps == pytest.approx(25.0)
    stamp = path.stat().st_mtime_ns
    assert gaps.reencoded("c") == path and path.stat().st_mtime_ns == stamp  # made once
