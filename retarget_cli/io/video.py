"""Video reading and writing with OpenCV."""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..methods.tracking.base import to_gray
from .atomic import check_write, part_name

log = logging.getLogger(__name__)

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".m4v")

#: Frames decoded ahead by :class:`VideoReader` (the bound of its queue).
PREFETCH = 4

#: glibc's ``mallopt`` parameters ``M_TRIM_THRESHOLD`` and ``M_MMAP_THRESHOLD``.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: The mmap threshold the console script fixes (:data:`retarget_cli.entry.MMAP_THRESHOLD`), and glibc's
#: default trim threshold: what :func:`large_frame_allocations` restores.
MMAP_THRESHOLD, TRIM_THRESHOLD = 1 << 20, 128 << 10
#: Inside :func:`large_frame_allocations`: blocks below the first come from the heap, and up to the second of
#: free heap is kept for the next frame's blocks.
LARGE_FRAME_MMAP, LARGE_FRAME_TRIM = 8 << 20, 32 << 20


@contextlib.contextmanager
def large_frame_allocations(frame_bytes: int):
    """Per-frame blocks of a loop over frames of *frame_bytes* bytes (a BGR frame) kept on the heap.

    Above the 1 MiB mmap threshold the console script fixes (for a long take's memory:
    :func:`retarget_cli.entry.fix_mmap_threshold`), every block OpenCV and numpy make per frame of a large
    video (the gray frame, Lucas-Kanade's pyramids and derivative buffers: 2.8 MB for a 1080p face) is a
    fresh mapping whose pages fault in and are given back each time: on d9 at 1080p, 8.4-9.7 of ``track``'s
    32-40 CPU seconds were system time, 0.7-0.9 with this (docs/benchmarks.md, issue #31). Inside the block, glibc (only) serves blocks
    under :data:`LARGE_FRAME_MMAP` from the heap and keeps up to :data:`LARGE_FRAME_TRIM` of it free; after,
    the thresholds are set to the console script's (:data:`MMAP_THRESHOLD`, :data:`TRIM_THRESHOLD`; glibc has no
    getter: a process that had left the mmap threshold dynamic has it fixed at 1 MiB from then on) and the
    free heap given back (``malloc_trim``). Frames of at most
    :data:`MMAP_THRESHOLD` bytes: nothing changes. Arrays and results are the same either way.
    """
    libc = _glibc() if frame_bytes > MMAP_THRESHOLD else None
    if libc is None:
        yield
        return
    libc.mallopt(_M_MMAP_THRESHOLD, LARGE_FRAME_MMAP)
    libc.mallopt(_M_TRIM_THRESHOLD, LARGE_FRAME_TRIM)
    try:
        yield
    finally:
        libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)
        libc.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)
        libc.malloc_trim(0)


def _glibc():
    """The C library with ``mallopt`` and ``malloc_trim`` typed (None where it is not glibc)."""
    import ctypes

    try:
        libc = ctypes.CDLL(None)
        libc.mallopt.argtypes, libc.mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
        libc.malloc_trim.argtypes, libc.malloc_trim.restype = [ctypes.c_size_t], ctypes.c_int
    except (OSError, AttributeError):
        return None
    return libc


def _reader(cap, convert, reuse: bool):
    """``read() -> frame or None`` of *cap*, each frame passed through *convert*.

    *reuse*: decode each frame into the buffer of the one before (``cv2.VideoCapture.read(image)``) when
    *convert* made a new array of it (the decoded frame is then seen by no one else). A 1080p BGR frame is
    6 MB: above the mmap threshold the console script fixes (:func:`retarget_cli.entry.fix_mmap_threshold`),
    a new one is mapped and its pages faulted in for every frame (2.1 s of system CPU per 587 1080p frames).
    """
    buf = None

    def read():
        nonlocal buf
        ok, frame = cap.read() if buf is None else cap.read(buf)
        if not ok:
            return None
        out = convert(frame)
        buf = frame if reuse and out is not frame and not np.shares_memory(out, frame) else None
        return out

    return read


class _Failed:
    """An exception raised by the decoding thread, to re-raise in the consumer."""

    def __init__(self, exc: BaseException):
        self.exc = exc


def decode_frames(cap, prefetch: int = PREFETCH, gray: bool = False, reuse: bool | None = None) -> Iterator[np.ndarray]:
    """Frames of ``cap.read()`` until it fails, decoded ahead in a background thread.

    OpenCV releases the GIL while it decodes, so decoding the next frames
    overlaps whatever the consumer does with the current one. The thread
    stops at the first failed read (exactly where a sequential loop stops),
    when the consumer closes the generator, or on an exception, which is
    re-raised in the consumer after the frames decoded before it.

    Parameters
    ----------
    cap : cv2.VideoCapture or any object with ``read() -> (ok, frame)``
        Must not be read by anyone else until the generator is closed.
    prefetch : int
        Bound of the queue of decoded frames; 0 reads sequentially in the
        caller's thread.
    gray : bool
        Convert colour frames to grayscale (``cv2.COLOR_BGR2GRAY``) in the
        decoding thread, off the consumer's time (a ``cv2.VideoCapture`` then
        decodes each colour frame into the buffer of the one before: see
        :func:`_reader`).
    reuse : bool, optional
        Decode into the previous frame's buffer as *gray* does for a ``cv2.VideoCapture`` (default: *gray*
        and *cap* is one); *cap*'s ``read`` must then take the buffer as ``read(image)``.

    Yields
    ------
    ndarray
        Each frame, in order.
    """
    import cv2

    convert = to_gray if gray else (lambda frame: frame)
    read = _reader(cap, convert, gray and isinstance(cap, cv2.VideoCapture) if reuse is None else bool(reuse))
    if prefetch <= 0:
        while (frame := read()) is not None:
            yield frame
        return
    q: queue.Queue = queue.Queue(maxsize=prefetch)
    stop = threading.Event()
    end = object()

    def put(item) -> bool:
        while not stop.is_set():
            try:
                q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def run() -> None:
        item = end
        try:
            while not stop.is_set():
                frame = read()
                if frame is None:
                    break
                if not put(frame):
                    return
        except BaseException as exc:  # handed to the consumer
            item = _Failed(exc)
        put(item)

    thread = threading.Thread(target=run, name="retarget-decode", daemon=True)
    thread.start()
    try:
        while True:
            item = q.get()
            if item is end:
                return
            if isinstance(item, _Failed):
                raise item.exc
            yield item
    finally:
        stop.set()
        thread.join()


class VideoReader:
    """Frames of a video file, read sequentially.

    Parameters
    ----------
    path : path-like
        mp4, mov, avi, mkv or m4v file readable by OpenCV.
    prefetch : int
        Frames decoded ahead in a background thread while the caller works
        on the current one (see :func:`decode_frames`); 0 decodes in the
        caller's thread.
    gray : bool
        Yield grayscale frames, converted in the decoding thread.

    Attributes
    ----------
    fps : float
        The container's rate as OpenCV reports it (0 or NaN when it gives none; see
        :func:`retarget_cli.io.frames.plausible_fps`).
    frame_size : tuple of int
        ``(width, height)``.
    frame_count : int
        The container's frame count (may be an estimate; 0 if unknown).
    """

    def __init__(self, path: str | os.PathLike, *, prefetch: int = PREFETCH, gray: bool = False):
        import cv2

        self.path = Path(path)
        self.prefetch = int(prefetch)
        self.gray = bool(gray)
        self._decoding = None
        if not self.path.is_file():
            raise InputError(f"{self.path}: video file not found")
        if self.path.suffix.lower() not in VIDEO_SUFFIXES:
            raise InputError(
                f"{self.path}: unsupported video type {self.path.suffix!r}; expected one of {', '.join(VIDEO_SUFFIXES)}"
            )
        self._cap = cv2.VideoCapture(str(self.path))
        if not self._cap.isOpened():
            raise InputError(f"{self.path}: OpenCV cannot open this video (corrupt file or unsupported codec)")
        self.fps = float(self._cap.get(cv2.CAP_PROP_FPS))  # as the container says (0 or NaN: none)
        self.frame_size = (
            int(self._cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
            int(self._cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
        )
        self.frame_count = max(int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT)), 0)

    def __iter__(self) -> Iterator[np.ndarray]:
        """Yield BGR uint8 frames of shape (H, W, 3), or (H, W) when the reader is *gray*.

        Raises
        ------
        InputError
            If the video yields no frame at all.
        """
        n = 0
        with contextlib.closing(self.decoded()) as frames:
            for frame in frames:
                n += 1
                yield frame
        self.frames_read = n
        if n == 0:
            raise InputError(f"{self.path}: no frame could be decoded (empty or corrupt video)")
        if self.frame_count and n < self.frame_count:
            log.warning("%s: container announces %d frames but only %d decoded; the file may be truncated",
                        self.path, self.frame_count, n)

    def decoded(self) -> Iterator[np.ndarray]:
        """The raw decoded frames (:func:`decode_frames` on this reader), without the end-of-video checks."""
        if self._decoding is not None:
            self._decoding.close()  # one reader of the capture at a time
        self._decoding = decode_frames(self._cap, self.prefetch, self.gray)
        return self._decoding

    def close(self) -> None:
        if self._decoding is not None:
            self._decoding.close()  # stop the decoding thread before releasing the capture
        self._cap.release()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


@contextlib.contextmanager
def atomic_video_writer(path: str | os.PathLike, fps: float, frame_size: tuple[int, int]):
    """An OpenCV ``VideoWriter`` writing to a temp file renamed onto *path* on success.

    Parameters
    ----------
    path : path-like
        Destination; its suffix picks the container (``.mp4`` uses ``mp4v``).
    fps : float
    frame_size : (width, height)

    Yields
    ------
    cv2.VideoWriter
    """
    import cv2

    path = Path(path)
    check_write(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = str(part_name(path, path.suffix))
    writer = None
    try:
        fourcc = cv2.VideoWriter_fourcc(*("mp4v" if path.suffix.lower() in (".mp4", ".m4v", ".mov") else "MJPG"))
        writer = cv2.VideoWriter(tmp, fourcc, float(fps), tuple(int(v) for v in frame_size))
        if not writer.isOpened():
            raise InputError(f"{path}: OpenCV cannot write this video type")
        yield writer
        writer.release()
        if os.path.getsize(tmp) == 0:
            raise InputError(f"{path}: the video writer produced an empty file")
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        if writer is not None:
            writer.release()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
