"""VideoReader decodes ahead in a thread without changing what it yields or reports."""

import logging
import threading

import cv2
import numpy as np
import pytest

from retarget_cli.errors import InputError
from retarget_cli.io.frames import FrameSource, TruncatedInputError
from retarget_cli.io.video import VideoReader, decode_frames


def _plain(path):
    """Sequential OpenCV reading, the reference."""
    cap = cv2.VideoCapture(str(path))
    out = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        out.append(f)
    cap.release()
    return out


def _decode_threads():
    return [t for t in threading.enumerate() if t.name == "retarget-decode"]


@pytest.fixture
def truncated(truncated_avi):
    """An MJPG avi cut in half (``tests/conftest.py``)."""
    return truncated_avi


@pytest.mark.parametrize("prefetch", [0, 1, 4])
def test_prefetching_reader_yields_identical_frames(small_take, prefetch):
    ref = _plain(small_take / "face.mp4")
    with VideoReader(small_take / "face.mp4", prefetch=prefetch) as r:
        got = list(r)
        assert r.frames_read == len(ref) == 60
    assert len(got) == len(ref)
    for a, b in zip(got, ref):
        np.testing.assert_array_equal(a, b)
    assert len({id(f) for f in got}) == len(got)  # each frame its own array
    assert not _decode_threads()


@pytest.mark.parametrize("prefetch", [0, 4])
def test_gray_reader_decodes_into_one_buffer_and_yields_fresh_frames(small_take, monkeypatch, prefetch):
    """A gray reader hands OpenCV the previous colour frame to decode into (no new 6 MB array per 1080p
    frame), and every gray frame it yields is still an array of its own."""
    given = []

    class Capture:  # (a Python subclass of cv2.VideoCapture crashes the garbage collector)
        def __init__(self, path):
            self.cap = cv2.VideoCapture(str(path))

        def read(self, image=None):
            given.append(image)
            return self.cap.read() if image is None else self.cap.read(image)

    ref = [cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) for f in _plain(small_take / "face.mp4")]
    with VideoReader(small_take / "face.mp4", prefetch=prefetch, gray=True) as r:  # the real capture
        np.testing.assert_array_equal(np.stack(list(r)), np.stack(ref))
    got = list(decode_frames(Capture(small_take / "face.mp4"), prefetch=prefetch, gray=True, reuse=True))
    assert len(got) == len(ref) == 60
    for a, b in zip(got, ref):
        np.testing.assert_array_equal(a, b)
    assert given[0] is None and all(g is not None for g in given[1:])
    assert len({id(g) for g in given[1:]}) == 1  # one colour buffer throughout
    assert not any(np.shares_memory(a, b) for a, b in zip(got, got[1:]))
    given.clear()
    colour = list(decode_frames(Capture(small_take / "face.mp4"), prefetch=prefetch))
    assert len({id(f) for f in colour}) == 60 and given == [None] * 61  # colour frames are handed out: never reused


@pytest.mark.parametrize("prefetch", [0, 4])
def test_gray_reader_converts_every_frame(small_take, tmp_path, prefetch):
    import cv2

    ref = [cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) for f in _plain(small_take / "face.mp4")]
    with VideoReader(small_take / "face.mp4", prefetch=prefetch, gray=True) as r:
        got = list(r)
    assert len(got) == len(ref) == 60
    for a, b in zip(got, ref):
        assert a.shape == b.shape == ref[0].shape[:2]
        np.testing.assert_array_equal(a, b)
    with FrameSource(small_take / "face.mp4", start=2, end=9, step=3, gray=True) as src:
        picked = list(src)
    assert src.frames == [2, 5, 8]
    for f, a in zip(src.frames, picked):
        np.testing.assert_array_equal(a, ref[f])
    for i in range(3):  # an image sequence too
        cv2.imwrite(str(tmp_path / f"f_{i:03d}.png"), _plain(small_take / "face.mp4")[i])
    with FrameSource(tmp_path / "f_%03d.png", gray=True) as src:
        seq = list(src)
    assert [a.shape for a in seq] == [ref[0].shape] * 3
    np.testing.assert_array_equal(seq[2], ref[2])


@pytest.mark.parametrize("prefetch", [0, 4])
def test_truncated_video_still_reported(truncated, caplog, prefetch):
    ref = _plain(truncated)
    with caplog.at_level(logging.WARNING, logger="retarget_cli.io.video"):
        with VideoReader(truncated, prefetch=prefetch) as r:
            n = sum(1 for _ in r)
            assert r.frames_read == n == len(ref)
            assert 0 < n < r.frame_count == 60
    assert f"container announces 60 frames but only {n} decoded" in caplog.text
    assert "cut.avi" in caplog.text
    # the frame source used by `retarget track` names the last frame read
    with FrameSource(truncated) as src:
        with pytest.raises(TruncatedInputError, match=rf"decoding stopped after frame {n - 1} ") as exc:
            for _ in src:
                pass
        assert exc.value.last_frame == n - 1 and src.frames == list(range(n))


def test_empty_decode_is_an_error(tmp_path):
    bad = tmp_path / "x.mp4"
    bad.write_bytes(b"\x00" * 2048)
    with pytest.raises(InputError, match="x.mp4"):
        with VideoReader(bad) as r:
            list(r)


def test_stopping_early_stops_the_decoding_thread(small_take):
    r = VideoReader(small_take / "face.mp4")
    it = iter(r)
    first = [next(it) for _ in range(3)]
    assert _decode_threads()  # decoding ahead
    r.close()
    assert not _decode_threads()
    np.testing.assert_array_equal(first[2], _plain(small_take / "face.mp4")[2])
    # a frame source stopped at --end reads exactly the frames before it
    with FrameSource(small_take / "face.mp4", end=10, step=3) as src:
        got = list(src)
    assert src.frames == [0, 3, 6, 9] and len(got) == 4
    assert not _decode_threads()


def test_decoding_errors_reach_the_consumer_in_order():
    class Cap:
        def __init__(self):
            self.n = 0

        def read(self):
            self.n += 1
            if self.n == 4:
                raise RuntimeError("decoder crashed")
            return True, np.full((2, 2), self.n, np.uint8)

    got = []
    with pytest.raises(RuntimeError, match="decoder crashed"):
        for f in decode_frames(Cap(), prefetch=2):
            got.append(int(f[0, 0]))
    assert got == [1, 2, 3]
    assert not _decode_threads()


def test_large_frame_allocations_keep_blocks_on_the_heap_and_restore(monkeypatch):
    """Around a loop over frames above the 1 MiB mmap threshold the thresholds are raised, then restored and the
    free heap trimmed, also when the loop raises; smaller frames leave the allocator alone."""
    import retarget_cli.io.video as video

    calls = []

    class Libc:
        def mallopt(self, param, value):
            calls.append(("mallopt", param, value))
            return 1

        def malloc_trim(self, pad):
            calls.append(("trim", pad))
            return 1

    monkeypatch.setattr(video, "_glibc", lambda: Libc())
    with video.large_frame_allocations(512 * 480 * 3):
        pass
    assert calls == []
    with pytest.raises(RuntimeError), video.large_frame_allocations(1920 * 1080 * 3):
        assert calls == [("mallopt", -3, video.LARGE_FRAME_MMAP), ("mallopt", -1, video.LARGE_FRAME_TRIM)]
        raise RuntimeError("a frame failed")
    assert calls[2:] == [("mallopt", -3, video.MMAP_THRESHOLD), ("mallopt", -1, video.TRIM_THRESHOLD), ("trim", 0)]
    assert video.MMAP_THRESHOLD == __import__("retarget_cli.entry", fromlist=["x"]).MMAP_THRESHOLD


def test_large_frame_allocations_on_this_libc():
    """The real C library: glibc takes the settings (the block runs either way)."""
    import platform

    import retarget_cli.io.video as video

    libc = video._glibc()
    if platform.libc_ver()[0] == "glibc":
        assert libc is not None and libc.mallopt(video._M_MMAP_THRESHOLD, video.MMAP_THRESHOLD) == 1
    with video.large_frame_allocations(1920 * 1080 * 3):
        a = np.ones((1080, 1920), np.uint8)
    assert int(a.sum()) == 1920 * 1080
