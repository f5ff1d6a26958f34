"""``landmarks.npz``: the contract between ``track`` and every later stage.

See the README's "File formats" section. A file holding only ``points`` is
accepted too (landmarks from another tracker); the head motion and the
stabilized landmarks are then computed with :func:`retarget_cli.methods.tracking.head.estimate_head`,
the same routine ``track`` uses.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import InputError, ParameterError
from ..methods.gaps import segments as gap_segments
from ..methods.gaps import segments_of
from ..methods.tracking.head import estimate_head
from .atomic import NpyChunks, load_npz, savez

#: A landmark whose confidence is at or below this is lost in that frame.
LOST_CONFIDENCE = 1e-3


@dataclass
class Landmarks:
    """Tracked landmarks of one take.

    Attributes
    ----------
    points : ndarray, shape (T, L, 2), float32
        Image pixels, x right, y down, OpenCV pixel-centre convention.
    confidence : ndarray, shape (T, L), float32
        In [0, 1]; 0 means lost or occluded.
    head : ndarray, shape (T, 2, 3), float32
        Similarity mapping stabilized coordinates to image pixels.
    stabilized : ndarray, shape (T, L, 2), float32
        Landmarks with the head motion removed.
    fps : float
    frame_size : ndarray, shape (2,), int
        ``[width, height]``; ``[0, 0]`` when unknown.
    names : ndarray, shape (L,), str, optional
    meta : dict
    frames : ndarray, shape (T,), int, optional
        Source frame number of each row (when a range or step was tracked).
    times : ndarray, shape (T,), float64, optional
        Time of each row in seconds, from its source frame number and the source's frame rate
        (``track`` writes it; :meth:`timing` fills it in for files without it).
    points_raw : ndarray, shape (T, L, 2), float32, optional
        The tracker's points before the landmark filter (``track.filter``);
        ``points`` are then the filtered ones.
    neutral : ndarray, shape (L, 2), float32, optional
        The actor's rest shape from a separate calibration image or clip
        (``track.neutral``), in this take's stabilized coordinates;
        ``neutral_frame: auto`` uses it as the neutral key's shape.
    neutral_confidence : ndarray, shape (L,), float32, optional
        Its landmarks' confidence (given with *neutral*).
    found : ndarray, shape (T,), bool, optional
        Whether the face was found in the frame (a take with gaps); a frame
        without it keeps the last found frame's landmarks with confidence 0.
        Absent: every frame (:attr:`found_mask`).
    segment : ndarray, shape (T,), int32, optional
        Segment of each frame (a run of found frames between gaps and scene
        cuts, smoothed on its own), -1 in the gaps. Absent: one segment of
        the found frames (:attr:`segments`).
    head_angles : ndarray, shape (T, 3), float32, optional
        The head's 3D rotation relative to the line of sight from the camera, ``yaw, pitch, roll`` in degrees
        (0: looking into the lens, wherever the face is in the picture; yaw > 0 turned
        to the actor's left, pitch > 0 looking up, roll > 0 tilted to the actor's left shoulder), fitted on
        ``points`` (:func:`retarget_cli.methods.tracking.headpose.head_pose`); a frame without a face holds
        the last found frame's.
    head_translation : ndarray, shape (T, 3), float32, optional
        The face's origin (between the eye corners) in camera axes (x right, y down, z away), in the 3D
        face's units (cm for the generic face); given with *head_angles*.
    gaze : ndarray, shape (T, 2, 2), float32, optional
        Each iris's offset from its eye corners' midpoint in eye widths (``track.gaze``;
        :func:`retarget_cli.methods.tracking.gaze.gaze`, filtered like the landmarks): eye 0 is the actor's
        right (image left), ``[..., 0]`` along the corner line (> 0 toward the image's right: the actor looks
        to their left), ``[..., 1]`` across it (> 0 down). Held through blinks, lost frames and gaps.
    gaze_valid : ndarray, shape (T, 2), bool, optional
        Whether the eye's iris was seen in the frame (False: held from a frame where it was).
    """

    points: np.ndarray
    confidence: np.ndarray
    head: np.ndarray
    stabilized: np.ndarray
    fps: float = 30.0
    frame_size: np.ndarray = field(default_factory=lambda: np.zeros(2, dtype=np.int64))
    names: np.ndarray | None = None
    meta: dict = field(default_factory=dict)
    frames: np.ndarray | None = None
    points_raw: np.ndarray | None = None
    neutral: np.ndarray | None = None
    neutral_confidence: np.ndarray | None = None
    times: np.ndarray | None = None
    found: np.ndarray | None = None
    segment: np.ndarray | None = None
    head_angles: np.ndarray | None = None
    head_translation: np.ndarray | None = None
    gaze: np.ndarray | None = None
    gaze_valid: np.ndarray | None = None

    @property
    def found_mask(self) -> np.ndarray:
        """``found`` (T,) bool, every frame when the file has none."""
        return np.ones(self.n_frames, bool) if self.found is None else np.asarray(self.found, bool)

    @property
    def segments(self) -> list[tuple[int, int]]:
        """The take's segments as half-open ``(start, stop)`` row ranges (:mod:`retarget_cli.methods.gaps`)."""
        if self.segment is not None:
            return segments_of(self.segment)
        return gap_segments(self.found_mask)

    @property
    def source_fps(self) -> float:
        """The source's frame rate: ``fps`` times the ``step`` tracked (from ``meta``), when rows are numbered."""
        step = (self.meta.get("parameters") or {}).get("step", 1) if isinstance(self.meta, dict) else 1
        step = step if isinstance(step, int) and not isinstance(step, bool) and step >= 1 else 1
        return float(self.fps * (step if self.frames is not None else 1))

    def timing(self) -> tuple[np.ndarray, np.ndarray]:
        """Source frame number (int64) and time in seconds (float64) of each row, shapes (T,).

        Without ``frames`` the rows are frames 0 … T−1; without ``times`` a frame's time is its number over
        the source's rate (``fps`` × the ``step`` tracked, from ``meta``).
        """
        frames = np.arange(self.n_frames, dtype=np.int64) if self.frames is None else np.asarray(self.frames, np.int64)
        if self.times is not None:
            return frames, np.asarray(self.times, dtype=np.float64)
        return frames, frames / self.source_fps

    @property
    def n_frames(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_points(self) -> int:
        return int(self.points.shape[1])


def save_landmarks(path: str | os.PathLike, lm: Landmarks) -> None:
    """Atomically write *lm* in the ``landmarks.npz`` contract.

    ``points``, ``confidence``, ``stabilized`` and ``points_raw`` may be
    :class:`~retarget_cli.io.atomic.NpyChunks` of float32: written a block of rows at a time, so a long take's
    float32 copies are never held whole (the bytes are those of the arrays they give).
    """
    T, L = lm.points.shape[:2]
    arrays = {
        "points": _float32(lm.points),
        "confidence": _float32(lm.confidence),
        "head": np.asarray(lm.head, dtype=np.float32),
        "stabilized": _float32(lm.stabilized),
        "fps": np.float64(lm.fps),
        "frame_size": np.asarray(lm.frame_size, dtype=np.int64),
    }
    for key, shape in (("confidence", (T, L)), ("head", (T, 2, 3)), ("stabilized", (T, L, 2))):
        if arrays[key].shape != shape:
            raise ParameterError(f"{key}: expected shape {shape}, got {arrays[key].shape}")
    if lm.names is not None:
        arrays["names"] = np.asarray(lm.names, dtype=str)
    if lm.frames is not None:
        arrays["frames"] = np.asarray(lm.frames, dtype=np.int64)
        if arrays["frames"].shape != (T,):
            raise ParameterError(f"frames: expected shape {(T,)}, got {arrays['frames'].shape}")
    if lm.times is not None:
        arrays["times"] = np.asarray(lm.times, dtype=np.float64)
        if arrays["times"].shape != (T,):
            raise ParameterError(f"times: expected shape {(T,)}, got {arrays['times'].shape}")
    if lm.points_raw is not None:
        arrays["points_raw"] = _float32(lm.points_raw)
        if arrays["points_raw"].shape != (T, L, 2):
            raise ParameterError(f"points_raw: expected shape {(T, L, 2)}, got {arrays['points_raw'].shape}")
    if lm.neutral is not None:
        arrays["neutral"] = np.asarray(lm.neutral, dtype=np.float32)
        conf = np.ones(L) if lm.neutral_confidence is None else lm.neutral_confidence
        arrays["neutral_confidence"] = np.asarray(conf, dtype=np.float32)
        if arrays["neutral"].shape != (L, 2) or arrays["neutral_confidence"].shape != (L,):
            raise ParameterError(f"neutral: expected shapes {(L, 2)} and {(L,)}, got {arrays['neutral'].shape} "
                                 f"and {arrays['neutral_confidence'].shape}")
    for key, value, dtype, shape in (("found", lm.found, bool, (T,)), ("segment", lm.segment, np.int32, (T,)),
                                     ("head_angles", lm.head_angles, np.float32, (T, 3)),
                                     ("head_translation", lm.head_translation, np.float32, (T, 3))):
        if value is not None:
            arrays[key] = np.asarray(value, dtype=dtype)
            if arrays[key].shape != shape:
                raise ParameterError(f"{key}: expected shape {shape}, got {arrays[key].shape}")
    arrays.update(_gaze_arrays(lm, T))
    meta = {"version": __version__, **lm.meta}
    arrays["meta"] = np.array(json.dumps(meta, sort_keys=True))
    savez(path, arrays)


def _float32(value):
    """*value* as float32: an array, or an :class:`~retarget_cli.io.atomic.NpyChunks` of float32 as it is."""
    if isinstance(value, NpyChunks):
        if value.dtype != np.float32:
            raise ParameterError(f"expected float32 rows, got {value.dtype}")
        return value
    return np.asarray(value, dtype=np.float32)


def _gaze_arrays(lm: Landmarks, T: int) -> dict:
    """``gaze`` (T, 2, 2) float32 and ``gaze_valid`` (T, 2) bool of *lm*, checked; {} without a gaze."""
    if lm.gaze is None:
        return {}
    valid = np.ones((T, 2), bool) if lm.gaze_valid is None else lm.gaze_valid
    out = {"gaze": np.asarray(lm.gaze, dtype=np.float32), "gaze_valid": np.asarray(valid, dtype=bool)}
    if out["gaze"].shape != (T, 2, 2) or out["gaze_valid"].shape != (T, 2):
        raise ParameterError(f"gaze: expected shapes {(T, 2, 2)} and {(T, 2)}, got {out['gaze'].shape} "
                             f"and {out['gaze_valid'].shape}")
    return out


def _numeric(data: dict, key: str, path) -> np.ndarray:
    """``data[key]`` if it holds real numbers (ints or floats), else an InputError naming the file and key."""
    a = data[key]
    if a.dtype.kind not in "iuf" or a.dtype.names is not None:
        raise InputError(f"{path}: {key!r} must hold numbers (float or int), got dtype {a.dtype}")
    return a


def _points(data: dict, path) -> np.ndarray:
    """``points`` as float32 (T, L, 2) with T, L >= 1."""
    if "points" not in data:
        raise InputError(f"{path}: missing key 'points' (float (T, L, 2)); found {sorted(data)}")
    points = _numeric(data, "points", path).astype(np.float32, copy=False)  # (freshly read: no copy needed)
    if points.ndim != 3 or points.shape[2] != 2 or points.shape[0] == 0 or points.shape[1] == 0:
        raise InputError(f"{path}: 'points' must have shape (T, L, 2) with T, L >= 1, got {points.shape}")
    return points


def _confidence(data: dict, path, points: np.ndarray) -> np.ndarray:
    """``confidence`` (T, L) in [0, 1]; absent, 1 where the point is finite and 0 elsewhere."""
    T, L, _ = points.shape
    if data.get("confidence") is None:
        return np.where(np.isfinite(points).all(-1), 1.0, 0.0).astype(np.float32)
    conf = _numeric(data, "confidence", path)
    if conf.shape != (T, L):
        raise InputError(f"{path}: 'confidence' must have shape {(T, L)}, got {conf.shape}")
    bad = ~(np.isfinite(conf) & (conf >= 0) & (conf <= 1))
    if bad.any():
        t, i = (int(v) for v in np.argwhere(bad)[0])
        raise InputError(f"{path}: 'confidence' must be finite and in [0, 1]; frame {t} landmark {i} has "
                         f"{conf[t, i]!r}")
    return conf


def _head(data: dict, path, points: np.ndarray, conf: np.ndarray, rigid_points) -> tuple[np.ndarray, np.ndarray]:
    """``head`` (T, 2, 3) and ``stabilized`` (T, L, 2) from the file, or estimated when both are absent."""
    T, L, _ = points.shape
    if ("head" in data) != ("stabilized" in data):
        raise InputError(f"{path}: 'head' and 'stabilized' must be given together or not at all")
    if "head" not in data:
        return estimate_head(points, conf, rigid_points=rigid_points)
    head, stab = _numeric(data, "head", path), _numeric(data, "stabilized", path)
    if head.shape != (T, 2, 3):
        raise InputError(f"{path}: 'head' must have shape {(T, 2, 3)}, got {head.shape}")
    if stab.shape != (T, L, 2):
        raise InputError(f"{path}: 'stabilized' must have shape {(T, L, 2)}, got {stab.shape}")
    if not np.isfinite(head).all():
        t = int(np.flatnonzero(~np.isfinite(head).reshape(T, -1).all(1))[0])
        raise InputError(f"{path}: 'head' must be finite; frame {t} is not")
    return head, stab


def _points_raw(data: dict, path, T: int, L: int) -> np.ndarray | None:
    raw = data.get("points_raw")
    if raw is not None and (raw.dtype.kind != "f" or raw.shape != (T, L, 2)):
        raise InputError(f"{path}: 'points_raw' must be floats of shape {(T, L, 2)} like 'points', got "
                         f"{raw.dtype} of shape {raw.shape}")
    return raw


def _neutral(data: dict, path, L: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``neutral`` (L, 2) and ``neutral_confidence`` (L,), both finite, or (None, None) when absent."""
    if "neutral" not in data:
        return None, None
    shape = _numeric(data, "neutral", path)
    conf = _numeric(data, "neutral_confidence", path) if "neutral_confidence" in data else np.ones(L)
    if shape.shape != (L, 2) or conf.shape != (L,):
        raise InputError(f"{path}: 'neutral' and 'neutral_confidence' must have shapes {(L, 2)} and {(L,)}, got "
                         f"{shape.shape} and {conf.shape}")
    if not (np.isfinite(shape).all() and np.isfinite(conf).all() and (conf >= 0).all() and (conf <= 1).all()):
        raise InputError(f"{path}: 'neutral' must be finite and 'neutral_confidence' in [0, 1]")
    return shape.astype(np.float32), conf.astype(np.float32)


def _gaze(data: dict, path, T: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``gaze`` (T, 2, 2) finite and ``gaze_valid`` (T, 2) bool, or (None, None) when absent."""
    if "gaze" not in data:
        return None, None
    g = _numeric(data, "gaze", path)
    if g.shape != (T, 2, 2):
        raise InputError(f"{path}: 'gaze' must have shape {(T, 2, 2)} (frames, eyes, along/across), got {g.shape}")
    if not np.isfinite(g).all():
        t = int(np.flatnonzero(~np.isfinite(g).reshape(T, -1).all(1))[0])
        raise InputError(f"{path}: 'gaze' must be finite; frame {t} is not")
    v = data.get("gaze_valid")
    if v is None:
        v = np.ones((T, 2), bool)
    elif v.dtype.kind not in "biu" or v.shape != (T, 2) or not np.isin(v, (0, 1)).all():
        raise InputError(f"{path}: 'gaze_valid' must be booleans of shape {(T, 2)}, got {v.dtype} of shape {v.shape}")
    return g.astype(np.float32), v.astype(bool)


def _fps(data: dict, path) -> float:
    if "fps" not in data:
        return 30.0
    f = _numeric(data, "fps", path)
    if f.size != 1 or f.ndim > 1 or not np.isfinite(f).all() or not float(f.ravel()[0]) > 0:
        raise InputError(f"{path}: 'fps' must be one finite number > 0, got {f.ravel()[:4].tolist()} "
                         f"(shape {f.shape})")
    return float(f.ravel()[0])


def _frame_size(data: dict, path) -> np.ndarray:
    """``[width, height]`` as int64; ``[0, 0]`` when absent."""
    if "frame_size" not in data:
        return np.zeros(2, dtype=np.int64)
    fs = _numeric(data, "frame_size", path)
    if fs.shape != (2,) or not np.isfinite(fs).all() or np.any(fs < 0) or np.any(fs % 1 != 0) \
            or np.any(fs > 1 << 20):
        raise InputError(f"{path}: 'frame_size' must be [width, height] (integers >= 0), got {fs.tolist()}")
    return fs.astype(np.int64)


def _frames(data: dict, path, T: int) -> np.ndarray | None:
    frames = data.get("frames")
    if frames is None:
        return None
    if frames.dtype.kind not in "iu" or frames.shape != (T,):
        raise InputError(f"{path}: 'frames' must be {T} integers (one per row of 'points'), got "
                         f"{frames.dtype} of shape {frames.shape}")
    return frames.astype(np.int64)


def _found(data: dict, path, T: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``found`` (T,) bool and ``segment`` (T,) int32 (-1 exactly where not found), or None where absent."""
    found, seg = data.get("found"), data.get("segment")
    if found is not None:
        if found.dtype.kind not in "biu" or found.shape != (T,) or not np.isin(found, (0, 1)).all():
            raise InputError(f"{path}: 'found' must be {T} booleans (one per row of 'points'), got {found.dtype} "
                             f"of shape {found.shape}")
        found = found.astype(bool)
    if seg is not None:
        if seg.dtype.kind not in "iu" or seg.shape != (T,):
            raise InputError(f"{path}: 'segment' must be {T} integers (one per row of 'points'), got {seg.dtype} "
                             f"of shape {seg.shape}")
        seg = seg.astype(np.int32)
        if found is not None and not np.array_equal(seg >= 0, found):
            t = int(np.flatnonzero((seg >= 0) != found)[0])
            raise InputError(f"{path}: frame {t}: 'segment' {int(seg[t])} disagrees with 'found' {bool(found[t])} "
                             "(expected -1 exactly where the face was not found)")
    return found, seg


def _head_3d(data: dict, path, T: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``head_angles`` and ``head_translation`` (T, 3) float32, finite and given together, or (None, None)."""
    if ("head_angles" in data) != ("head_translation" in data):
        raise InputError(f"{path}: 'head_angles' and 'head_translation' must be given together or not at all")
    if "head_angles" not in data:
        return None, None
    out = []
    for key in ("head_angles", "head_translation"):
        a = _numeric(data, key, path)
        if a.shape != (T, 3):
            raise InputError(f"{path}: {key!r} must have shape {(T, 3)} (one row per frame), got {a.shape}")
        if not np.isfinite(a).all():
            t = int(np.flatnonzero(~np.isfinite(a).all(1))[0])
            raise InputError(f"{path}: {key!r} must be finite; frame {t} is not")
        out.append(a.astype(np.float32))
    return out[0], out[1]


def _times(data: dict, path, T: int) -> np.ndarray | None:
    if "times" not in data:
        return None
    t = _numeric(data, "times", path)
    if t.shape != (T,) or not np.isfinite(t).all() or np.any(np.diff(t) <= 0):
        raise InputError(f"{path}: 'times' must be {T} finite increasing seconds (one per row of 'points'), got "
                         f"shape {t.shape}")
    return t.astype(np.float64)


def _names(data: dict, path, L: int) -> np.ndarray | None:
    names = data.get("names")
    if names is not None and (names.dtype.kind not in "US" or names.shape != (L,)):
        raise InputError(f"{path}: 'names' must be {L} strings (one per landmark), got {names.dtype} of shape "
                         f"{names.shape}")
    return names


def _meta(data: dict, path) -> dict:
    """``meta``: one JSON string holding an object; ``{}`` when absent."""
    if "meta" not in data:
        return {}
    m = data["meta"]
    if m.dtype.kind not in "US" or m.size != 1:
        raise InputError(f"{path}: 'meta' must be one JSON string, got {m.dtype} of shape {m.shape}")
    try:
        meta = json.loads(str(m.ravel()[0]))
    except (json.JSONDecodeError, RecursionError) as exc:
        raise InputError(f"{path}: 'meta' is not a JSON string ({exc})") from None
    if not isinstance(meta, dict):
        raise InputError(f"{path}: 'meta' must be a JSON object, got {type(meta).__name__}")
    return meta


def peek_frames(path: str | os.PathLike) -> int | None:
    """Number of frames in a ``landmarks.npz`` from its ``points`` header alone, or None if unreadable.

    Reads a few hundred bytes (no array data, no checks): for decisions made
    before the file is loaded, such as whether to start loading the compiled
    kernel in the background; :func:`load_landmarks` reports any problem.
    """
    import zipfile

    try:
        with zipfile.ZipFile(path) as zf, zf.open("points.npy") as fh:
            version = np.lib.format.read_magic(fh)
            read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape = read(fh)[0]
        return int(shape[0]) if len(shape) else None
    except Exception:
        return None


def load_landmarks(path: str | os.PathLike, *, rigid_points=None) -> Landmarks:
    """Read a ``landmarks.npz`` file, completing optional keys.

    Parameters
    ----------
    path : path-like
    rigid_points : sequence of int, optional
        Used only when the file has no ``head``/``stabilized`` keys.

    Raises
    ------
    InputError
        Naming the file and the key when ``points`` is missing or a key has
        the wrong shape.
    """
    path = Path(path)
    data = load_npz(path)
    points = _points(data, path)
    T, L, _ = points.shape
    conf = _confidence(data, path, points)
    head, stab = _head(data, path, points, conf, rigid_points)
    raw = _points_raw(data, path, T, L)
    fps = _fps(data, path)
    frame_size = _frame_size(data, path)
    frames = _frames(data, path, T)
    times = _times(data, path, T)
    names = _names(data, path, L)
    meta = _meta(data, path)
    neutral, neutral_conf = _neutral(data, path, L)
    found, segment = _found(data, path, T)
    head_angles, head_translation = _head_3d(data, path, T)
    gz, gz_valid = _gaze(data, path, T)
    return Landmarks(
        points=points,
        confidence=conf.astype(np.float32, copy=False),
        head=np.asarray(head, dtype=np.float32),
        stabilized=np.asarray(stab, dtype=np.float32),
        fps=fps,
        frame_size=frame_size,
        names=names,
        frames=frames,
        times=times,
        meta=meta,
        points_raw=None if raw is None else raw.astype(np.float32, copy=False),
        neutral=neutral,
        neutral_confidence=neutral_conf,
        found=found,
        segment=segment,
        head_angles=head_angles,
        head_translation=head_translation,
        gaze=gz,
        gaze_valid=gz_valid,
    )
