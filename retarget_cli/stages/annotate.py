"""File handling of the pretrained landmark detector: automatic annotation for ``track --init auto``
and the ``annotate`` command (iBUG ``.pts`` files for chosen frames).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..config import Command, Flag, Param, output_flag, validate_params
from ..errors import InputError
from ..io.annotations import pts_text, write_pts
from ..io.atomic import check_not_input, sha256_file
from ..io.face_detector import face_detector_file
from ..io.frames import FrameSource, TruncatedInputError
from ..methods.tracking.detect import Detector, detect_landmarks

log = logging.getLogger(__name__)

#: Declared parameters of ``annotate``.
PARAMS = [
    Param("video", "input", str, help="Video or image-sequence pattern."),
    Param("frames", "setting", list, help="Frames to annotate (0-based), e.g. 0,120,240 or 0-300:60 (every 60th "
          "from 0 to 300)."),
    Param("output", "output", str, help="Directory for the .pts files."),
    Param("fps", "setting", float, None, "Frame rate of an image sequence.", min=0.01, nullable=True),
]

#: The value of ``track.init`` (and ``--init``) that asks for automatic annotation.
AUTO = "auto"


def is_auto(init) -> bool:
    """Whether *init* asks for automatic annotation (``None`` or ``"auto"``)."""
    return init is None or str(init) == AUTO


def init_pts_path(output, frame: int) -> Path:
    """Where ``track --init auto`` writes the annotation it used: ``<output stem>.init_<frame:05d>.pts``."""
    output = Path(output)
    return output.with_name(f"{output.stem}.init_{int(frame):05d}.pts")


def write_pts_once(path, points, *, own: dict | None = None) -> Path:
    """Write *points* (L, 2; 0-based pixels) as iBUG ``.pts`` to *path*, never replacing another file.

    An existing *path* is left alone when it already holds exactly these
    points (a rerun); holding anything else (for example an annotation
    corrected by hand) it is an error, unless it is still the file this tool
    wrote there: *own* is that file's record (``{"size", "sha256"}``, from the
    folder's output manifest, :func:`retarget_cli.io.atomic.read_output_manifest`),
    and a file that still matches it is replaced.
    """

    path = Path(path)
    if path.exists():
        if path.is_file() and path.read_text(encoding="utf-8", errors="replace") == pts_text(points):
            return path
        if own is not None and path.is_file() and not path.is_symlink() and \
                path.stat().st_size == own.get("size") and sha256_file(path) == own.get("sha256"):
            write_pts(path, points)
            return path
        raise InputError(f"{path}: exists and differs from the detected annotation; refusing to overwrite it "
                         f"(track from it with --init {path}, or move it away)")
    write_pts(path, points)
    return path


#: What to do when the detector finds no face on the first tracked frame (``track``'s options).
TRACK_HINT = "annotate this frame by hand with --init, or start at another frame with --start"


def detect_frame(gray, *, detector, where: str, hint: str = TRACK_HINT) -> np.ndarray:
    """The 68 detected landmarks (68, 2) of one frame; *where* names the frame in the error when no face is found,
    *hint* says what to do (in terms of the options of the command that asked)."""

    points, _ = detect_landmarks(gray, detector=detector)
    if points is None:
        raise InputError(f"{where}: no face found by the detector ({hint})")
    return points


@validate_params(PARAMS)
def run_annotate(*, video, frames, output, fps=None) -> list[Path]:
    """Detect the face on the chosen *frames* of *video* and write ``<video stem>_<frame:05d>.pts`` into *output*.

    Frame numbers are 0-based positions in the source. Files already there
    are replaced only when they hold the same points (see :func:`write_pts_once`).
    """

    frames = sorted({int(f) for f in frames})
    if not frames:
        raise InputError("annotate: give at least one frame number (--frames 0,120,...)")
    if frames[0] < 0:
        raise InputError(f"annotate: frame {frames[0]} is negative; frames are 0-based")
    detector = Detector(faces_file=face_detector_file())
    out = Path(output)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a directory")
    stem = Path(str(video)).stem.replace("*", "").replace("%", "") or "frames"
    found = {}
    with FrameSource(video, end=frames[-1] + 1, fps=fps, gray=True) as source:
        if source.frame_count and frames[-1] >= source.frame_count:
            raise InputError(f"{source.path}: frame {frames[-1]} is past the last frame ({source.frame_count - 1})")
        targets = [out / f"{stem}_{f:05d}.pts" for f in frames]
        for t in targets:
            check_not_input(t, source.files())
        wanted = set(frames)
        gone = [f for f in frames if f in set(source.missing)]
        if gone:
            raise InputError(f"{source.path}: frame {gone[0]} is missing from the image sequence (a gap in its "
                             "numbering)")
        try:
            for img in source:
                i = source.frames[-1]
                if i in wanted:
                    found[i] = detect_frame(img, detector=detector, where=f"{source.path}: frame {i}",
                                            hint="choose other --frames, or place this frame's points by hand in "
                                                 "an iBUG .pts file")
        except TruncatedInputError as exc:
            missing = [f for f in frames if f not in found]
            raise InputError(f"{exc}; frame {missing[0]} could not be read") from None
    missing = [f for f in frames if f not in found]
    if missing:
        raise InputError(f"{video}: frame {missing[0]} is past the last frame")
    out.mkdir(parents=True, exist_ok=True)
    written = [write_pts_once(t, found[f]) for f, t in zip(frames, targets)]
    log.info("annotated %d frames of %s", len(written), video)
    return written


#: ``annotate`` (the CLI builds it: :mod:`retarget_cli.cli.commands`).
COMMAND = Command(
    "annotate",
    """Place the 68 landmarks on chosen frames of VIDEO with the pretrained detector (needs the extra detect).

    Writes OUTPUT/<video stem>_<frame:05d>.pts (iBUG .pts, as `track --init/--annotation` and
    `train-tracker` read them); check them by eye before training or re-anchoring on them.""",
    lambda: PARAMS,
    (Flag("video", argument=True, path="file"),
     Flag("frames", value="frames", required=True, metavar="LIST", show_default=False,
          help="Frames to annotate (0-based), e.g. 0,120,240 or 0-300:60 (every 60th from 0 to 300)."),
     output_flag(None, "Directory for the .pts files."),
     "fps"),
    lambda values, out: run_annotate(**values),
    folder_output=True,
)
