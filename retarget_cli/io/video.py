"""Video reading and writing with OpenCV."""

from __future__ import annotations

import contextlib
import logging
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..errors import InputError

log = logging.getLogger(__name__)

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".m4v")


class VideoReader:
    """Frames of a video file, read sequentially.

    Parameters
    ----------
    path : path-like
        mp4, mov, avi, mkv or m4v file readable by OpenCV.

    Attributes
    ----------
    fps : float
    frame_size : tuple of int
        ``(width, height)``.
    frame_count : int
        The container's frame count (may be an estimate; 0 if unknown).
    """

    def __init__(self, path: str | os.PathLike):
        import cv2

        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(f"{self.path}: video file not found")
        if self.path.suffix.lower() not in VIDEO_SUFFIXES:
            raise InputError(
                f"{self.path}: unsupported video type {self.path.suffix!r}; expected one of {', '.join(VIDEO_SUFFIXES)}"
            )
        self._cap = cv2.VideoCapture(str(self.path))
        if not self._cap.isOpened():
            raise InputError(f"{self.path}: OpenCV cannot open this video (corrupt file or unsupported codec)")
        self.fps = float(self._cap.get(cv2.CAP_PROP_FPS)) or 30.0
        self.frame_size = (
            int(self._cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
            int(self._cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
        )
        self.frame_count = max(int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT)), 0)

    def __iter__(self) -> Iterator[np.ndarray]:
        """Yield BGR uint8 frames of shape (H, W, 3).

        Raises
        ------
        InputError
            If the video yields no frame at all.
        """
        n = 0
        while True:
            ok, frame = self._cap.read()
            if not ok:
                break
            n += 1
            yield frame
        self.frames_read = n
        if n == 0:
            raise InputError(f"{self.path}: no frame could be decoded (empty or corrupt video)")
        if self.frame_count and n < self.frame_count:
            log.warning("%s: container announces %d frames but only %d decoded; the file may be truncated",
                        self.path, self.frame_count, n)

    def close(self) -> None:
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
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    fourcc = cv2.VideoWriter_fourcc(*("mp4v" if path.suffix.lower() in (".mp4", ".m4v", ".mov") else "MJPG"))
    writer = cv2.VideoWriter(tmp, fourcc, float(fps), tuple(int(v) for v in frame_size))
    try:
        if not writer.isOpened():
            raise InputError(f"{path}: OpenCV cannot write this video type")
        yield writer
        writer.release()
        if os.path.getsize(tmp) == 0:
            raise InputError(f"{path}: the video writer produced an empty file")
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        writer.release()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
