"""Frame sources for tracking: video files and image sequences, with frame ranges.

A source is a video file read with OpenCV, or an image sequence given as a
printf pattern (``shots/face_%05d.png``) or a glob pattern
(``shots/*.exr``). PNG and JPEG frames are read with OpenCV; EXR frames with
OpenEXR (linear light, converted to 8-bit sRGB for tracking). A video's frames
are numbered 0, 1, ... in decoding order; a sequence's by the number in each
file's name, counted from the first file's (frame 0), so a number missing from
the sequence is a missing frame: it keeps its place in time and is reported
(:attr:`FrameSource.missing`) for the tracker to mark lost. ``start``/``end``/``step``
select a range of these frame numbers.

A frame rate that is missing (0, NaN) is replaced by 30 with a warning; one
outside :data:`FPS_RANGE` (a remuxed clip claiming 2344 fps) is refused unless
the caller gives the rate (``track.fps``).

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

#: Frame rates taken as plausible from a container or a setting, frames per second (both ends included).
FPS_RANGE = (1.0, 480.0)

#: The rate assumed when the source gives none.
DEFAULT_FPS = 30.0




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
    return [f for _, f in numbered_sequence(pattern)]


_LAST_NUMBER = re.compile(r"(\d+)(?!.*\d)")


def numbered_sequence(pattern) -> list[tuple[int, Path]]:
    """Files matching a printf or glob *pattern* with the frame number of each, in frame order.

    A printf pattern's number is the one ``%d`` stands for; a glob's is the
    last number in each file's name when every file has one and no two share
    it, else the file's place in natural order. Numbers count from the first
    file's (frame 0), so a gap in the numbering is a gap in the frames.

    Raises
    ------
    InputError
        If nothing matches, a match has an unsupported suffix, or two files
        of a printf pattern carry the same number (``img_7.png``, ``img_007.png``).
    """
    pattern = str(pattern)
    if _PRINTF.search(pattern):
        rx = _printf_regex(pattern)
        cands = _glob.glob(_PRINTF.sub("*", pattern))
        numbered = sorted(((int(m.group(1)), Path(c)) for c in cands if (m := rx.match(c))), key=lambda x: x[0])
        for (a, fa), (b, fb) in zip(numbered, numbered[1:]):
            if a == b:
                raise InputError(f"{fb}: frame number {a} again (also {fa.name}); one file per frame number")
    else:
        files = [Path(p) for p in sorted(_glob.glob(pattern), key=_natural_key)]
        found = [_LAST_NUMBER.search(f.name) for f in files]
        numbers = [int(m.group(1)) for m in found if m]
        if len(numbers) == len(files) and len(set(numbers)) == len(numbers) and numbers == sorted(numbers):
            numbered = list(zip(numbers, files))
        else:
            numbered = list(enumerate(files))
    files = [f for _, f in numbered]
    if not files:
        raise InputError(f"{pattern}: no image file matches this pattern")
    bad = [f for f in files if f.suffix.lower() not in IMAGE_SUFFIXES]
    if bad:
        raise InputError(f"{bad[0]}: unsupported image type {bad[0].suffix!r}; expected one of "
                         f"{', '.join(IMAGE_SUFFIXES)}")
    first = numbered[0][0]
    return [(n - first, f) for n, f in numbered]


def plausible_fps(fps, where, given=None) -> float:
    """The frame rate to use: *given* (a setting) if any, else the source's *fps* when plausible.

    A missing rate (None, 0, NaN) becomes :data:`DEFAULT_FPS` with a warning naming *where*.

    Raises
    ------
    InputError
        If the source's rate lies outside :data:`FPS_RANGE` and none is given, or *given* does.
    """
    lo, hi = FPS_RANGE
    if given is not None:
        given = float(given)
        if not (lo <= given <= hi):
            raise InputError(f"{where}: fps {given:g} is outside {lo:g}-{hi:g}")
        return given
    rate = float(fps) if fps is not None else 0.0
    if not np.isfinite(rate) or rate <= 0:
        log.warning("%s: no frame rate in the file; using %g fps (set track.fps, --fps, to the true rate)", where,
                    DEFAULT_FPS)
        return DEFAULT_FPS
    if not (lo <= rate <= hi):
        raise InputError(f"{where}: the file claims {rate:g} fps, outside the plausible {lo:g}-{hi:g} "
                         "(a remuxed or damaged file?); give the true rate with track.fps (--fps)")
    return rate


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
        Frame rate: an image sequence's (default 30), or a video's instead of the container's
        (:func:`plausible_fps`).
    gray : bool
        Yield grayscale frames (H, W); a video's are converted in its decoding thread.
    warn_missing : bool
        Warn once about numbers missing from a sequence (a second reader of the same frames says nothing).

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
    missing : list of int
        Frame numbers an image sequence lacks (gaps in its numbering); such a frame yields the image before it
        again, and the caller marks its row lost.
    source_fps : float
        The source's own rate (frame ``n`` is at ``n / source_fps`` seconds).
    """

    def __init__(self, spec, *, start: int = 0, end: int | None = None, step: int = 1, fps: float | None = None,
                 gray: bool = False, warn_missing: bool = True):
        if start < 0 or step < 1 or (end is not None and end <= start):
            raise InputError(f"frame range: expected 0 <= start < end and step >= 1, got start={start}, "
                             f"end={end}, step={step}")
        self.spec, self.start, self.end, self.step = str(spec), start, end, step
        self.frames: list[int] = []
        self.missing: list[int] = []
        self.gray = bool(gray)
        if is_sequence(spec):
            numbered = numbered_sequence(spec)
            self._files = dict(numbered)
            self._video = None
            first = read_image(numbered[0][1])
            self.frame_size = (first.shape[1], first.shape[0])
            self.frame_count = numbered[-1][0] + 1
            self.missing = sorted(set(range(self.frame_count)) - set(self._files))
            base_fps = plausible_fps(fps, self.spec) if fps is not None else DEFAULT_FPS
            self.path = Path(self.spec)
            if warn_missing:
                self._warn_missing(numbered)
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
            base_fps = plausible_fps(self._video.fps, p, given=fps)
            self.path = p
        #: The source's frame rate (frame n is at time n / source_fps).
        self.source_fps = base_fps
        self.fps = base_fps / step
        last = (self.frame_count - 1) if self.frame_count else None
        if last is not None and start > last:
            raise InputError(f"{self.spec}: --start {start} is past the last frame ({last})")

    def _warn_missing(self, numbered) -> None:
        """One warning line for the numbers missing from the sequence (lost frames)."""
        if not self.missing:
            return
        m = self.missing
        runs = [f"{m[0]}" if len(m) == 1 else f"{m[0]}-{m[-1]}" if m[-1] - m[0] == len(m) - 1 else
                ", ".join(map(str, m[:5])) + (", ..." if len(m) > 5 else "")]
        log.warning("%s: %d frame(s) missing from the numbering (frame %s, counted from %s); kept as lost frames "
                    "(confidence 0) at their time", self.spec, len(m), runs[0], numbered[0][1].name)

    def times(self, frames) -> np.ndarray:
        """Time in seconds of source frame numbers *frames*: ``frame / source_fps``; shape (T,), float64."""
        return np.asarray(frames, dtype=np.float64) / self.source_fps

    def files(self) -> list[Path]:
        """The files read: the video, or every image of the sequence."""
        return list(self._files.values()) if self._files is not None else [self.path]

    def _wanted(self, i: int) -> bool:
        return i >= self.start and (i - self.start) % self.step == 0

    def _sequence(self):
        """The sequence's frames; a missing number yields the frame before it again (its row is lost)."""
        stop = self.frame_count if self.end is None else min(self.end, self.frame_count)
        held = None
        for i in range(self.start, stop, self.step):
            f = self._files.get(i)
            if f is None:
                if held is None:  # the range starts in a gap: the nearest earlier file stands in
                    held = self._check(max(n for n in self._files if n < i))
                img = held
            else:
                img = held = self._check(i)
            self.frames.append(i)
            yield to_gray(img) if self.gray else img

    def _check(self, i: int) -> np.ndarray:
        f = self._files[i]
        img = read_image(f)
        if (img.shape[1], img.shape[0]) != self.frame_size:
            raise InputError(f"{f}: frame {i} is {img.shape[1]}x{img.shape[0]}, the sequence is "
                             f"{self.frame_size[0]}x{self.frame_size[1]}")
        return img

    def __iter__(self):
        end = self.end
        if self._files is not None:
            yield from self._sequence()
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


__all__ = ["FrameSource", "TruncatedInputError", "is_sequence", "sequence_files", "numbered_sequence", "read_image",
           "plausible_fps", "IMAGE_SUFFIXES", "FPS_RANGE"]
