"""Frame sources for tracking: video files and image sequences, with frame ranges.

A source is a video file read with OpenCV, or an image sequence given as a
printf pattern (``shots/face_%05d.png``) or a glob pattern
(``shots/*.exr``). PNG and JPEG frames are read with OpenCV; EXR frames with
OpenEXR (linear light, converted to 8-bit sRGB for tracking). Frames are
numbered 0, 1, ... in reading order (sequence files sorted by the number in
their name); ``start``/``end``/``step`` select a range.

A video that stops decoding before the frame count its container announces
is reported (:class:`TruncatedInputError`) with the file and the last frame
read, so the caller can stop or keep what was tracked up to then.
"""

from __future__ import annotations

import glob as _glob
import logging
import re
from pathlib import Path

import numpy as np

from ..errors import InputError, TruncatedInputError  # noqa: F401  (TruncatedInputError re-exported)
from ..methods.tracking.base import to_gray
from .video import VIDEO_SUFFIXES, VideoReader

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr")
_PRINTF = re.compile(r"%(0?\d*)d")




def is_sequence(spec) -> bool:
    """Whether *spec* is an image-sequence pattern (printf or glob) rather than a file."""
    name = str(spec)
    return bool(_PRINTF.search(name)) or any(c in name for c in "*?[")


def sequence_files(pattern) -> list[Path]:
    """Files matching a printf or glob *pattern*, in frame order.

    Raises
    ------
    InputError
        If nothing matches or a match has an unsupported suffix.
    """
    pattern = str(pattern)
    if _PRINTF.search(pattern):
        rx = _printf_regex(pattern)
        cands = _glob.glob(_PRINTF.sub("*", pattern))
        files = sorted(((int(m.group(1)), Path(c)) for c in cands if (m := rx.match(c))), key=lambda x: x[0])
        files = [f for _, f in files]
    else:
        files = [Path(p) for p in sorted(_glob.glob(pattern), key=_natural_key)]
    if not files:
        raise InputError(f"{pattern}: no image file matches this pattern")
    bad = [f for f in files if f.suffix.lower() not in IMAGE_SUFFIXES]
    if bad:
        raise InputError(f"{bad[0]}: unsupported image type {bad[0].suffix!r}; expected one of "
                         f"{', '.join(IMAGE_SUFFIXES)}")
    return files


def _printf_regex(pattern: str) -> re.Pattern:
    out, pos = [], 0
    for m in _PRINTF.finditer(pattern):
        out.append(re.escape(pattern[pos:m.start()]))
        out.append(r"(\d+)")
        pos = m.end()
    out.append(re.escape(pattern[pos:]))
    return re.compile("^" + "".join(out) + "$")


def _natural_key(s: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", s)]


def read_image(path) -> np.ndarray:
    """One frame as BGR uint8 (H, W, 3); EXR linear light is converted to 8-bit sRGB.

    Raises
    ------
    InputError
        If the file cannot be read.
    """
    import cv2

    path = Path(path)
    if path.suffix.lower() == ".exr":
        import OpenEXR

        try:
            with OpenEXR.File(str(path)) as f:
                ch = f.channels()
                if "RGB" in ch:
                    rgb = np.asarray(ch["RGB"].pixels, dtype=np.float32)
                elif all(c in ch for c in "RGB"):
                    rgb = np.dstack([np.asarray(ch[c].pixels, dtype=np.float32) for c in "RGB"])
                elif "Y" in ch:
                    rgb = np.repeat(np.asarray(ch["Y"].pixels, dtype=np.float32)[..., None], 3, axis=2)
                else:
                    raise InputError(f"{path}: EXR has no RGB or Y channels (found {sorted(ch)})")
        except InputError:
            raise
        except Exception as exc:  # OpenEXR raises plain exceptions on corrupt files
            raise InputError(f"{path}: cannot read EXR image ({exc})") from exc
        x = np.clip(np.nan_to_num(rgb), 0, 1)
        srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
        return np.ascontiguousarray((srgb[..., ::-1] * 255 + 0.5).astype(np.uint8))
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise InputError(f"{path}: cannot read image (missing, corrupt or unsupported)")
    return img


class FrameSource:
    """Frames of a video file or image sequence, restricted to ``range(start, end, step)``.

    Parameters
    ----------
    spec : path-like
        Video file, or printf/glob pattern of an image sequence.
    start, end, step : int
        Frames ``start, start + step, ...`` below ``end`` (``None``: to the last).
    fps : float, optional
        Frame rate of an image sequence (videos report their own); default 30.
    gray : bool
        Yield grayscale frames (H, W); a video's are converted in its decoding thread.

    Attributes
    ----------
    fps : float
        Of the selected frames (the source's rate divided by *step*).
    frame_size : (int, int)
        ``(width, height)``.
    frame_count : int
        Frames in the source (0 if unknown).
    frames : list of int
        Source numbers of the frames yielded so far.
    """

    def __init__(self, spec, *, start: int = 0, end: int | None = None, step: int = 1, fps: float | None = None,
                 gray: bool = False):
        if start < 0 or step < 1 or (end is not None and end <= start):
            raise InputError(f"frame range: expected 0 <= start < end and step >= 1, got start={start}, "
                             f"end={end}, step={step}")
        self.spec, self.start, self.end, self.step = str(spec), start, end, step
        self.frames: list[int] = []
        self.gray = bool(gray)
        if is_sequence(spec):
            self._files = sequence_files(spec)
            self._video = None
            first = read_image(self._files[0])
            self.frame_size = (first.shape[1], first.shape[0])
            self.frame_count = len(self._files)
            base_fps = fps or 30.0
            self.path = Path(self.spec)
        else:
            p = Path(spec)
            if p.suffix.lower() in IMAGE_SUFFIXES:
                raise InputError(f"{p}: a single image; give an image-sequence pattern such as "
                                 f"{p.with_name('frame_%05d' + p.suffix)} or {p.parent / ('*' + p.suffix)}")
            if p.suffix.lower() not in VIDEO_SUFFIXES and p.is_file():
                raise InputError(f"{p}: unsupported input type {p.suffix!r}; expected a video "
                                 f"({', '.join(VIDEO_SUFFIXES)}) or an image-sequence pattern")
            self._video = VideoReader(p, gray=gray)
            self._files = None
            self.frame_size = self._video.frame_size
            self.frame_count = self._video.frame_count
            base_fps = self._video.fps
            self.path = p
        self.fps = base_fps / step
        last = (self.frame_count - 1) if self.frame_count else None
        if last is not None and start > last:
            raise InputError(f"{self.spec}: --start {start} is past the last frame ({last})")

    def files(self) -> list[Path]:
        """The files read: the video, or every image of the sequence."""
        return list(self._files) if self._files is not None else [self.path]

    def _wanted(self, i: int) -> bool:
        return i >= self.start and (i - self.start) % self.step == 0

    def __iter__(self):
        end = self.end
        if self._files is not None:
            for i, f in enumerate(self._files):
                if end is not None and i >= end:
                    return
                if not self._wanted(i):
                    continue
                img = read_image(f)
                if (img.shape[1], img.shape[0]) != self.frame_size:
                    raise InputError(f"{f}: frame {i} is {img.shape[1]}x{img.shape[0]}, the sequence is "
                                     f"{self.frame_size[0]}x{self.frame_size[1]}")
                self.frames.append(i)
                yield to_gray(img) if self.gray else img
            return
        decoded = self._video.decoded()  # decoded ahead in a background thread
        i = -1
        while end is None or i + 1 < end:
            frame = next(decoded, None)
            if frame is None:
                break
            i += 1
            if self._wanted(i):
                self.frames.append(i)
                yield frame
        decoded.close()
        if i < 0:
            raise TruncatedInputError(f"{self.path}: no frame could be decoded (empty or corrupt video)", -1)
        announced = self.frame_count if end is None else min(self.frame_count, end)
        if self.frame_count and i + 1 < announced:
            raise TruncatedInputError(
                f"{self.path}: decoding stopped after frame {i} (last frame read) of the {self.frame_count} "
                f"the container announces; the file is truncated or corrupt", i)
        if i < self.start:
            raise InputError(f"{self.path}: --start {self.start} is past the last frame ({i})")

    def close(self) -> None:
        if self._video is not None:
            self._video.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


__all__ = ["FrameSource", "TruncatedInputError", "is_sequence", "sequence_files", "read_image", "IMAGE_SUFFIXES"]
