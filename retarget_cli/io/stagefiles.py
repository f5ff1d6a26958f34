"""The small files passed between stages: ``keys.json``, ``weights.npz``,
``targets.yaml`` (``rig.yaml`` is read by :mod:`retarget_cli.io.rig`). Formats: docs/formats.md."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import __version__
from .._validate import check_name
from ..errors import InputError, ParameterError
from .atomic import dumps_json, load_npz, savez, write_json, write_text
from .rig.spec import read_rig
from .text import read_text, read_yaml_file

# --------------------------------------------------------------------------- keys.json


def write_keys(path: str | os.PathLike, landmarks: str | os.PathLike, regions: dict,
               neutral: dict | None = None) -> None:
    """Write ``keys.json``.

    Parameters
    ----------
    path : path-like
    landmarks : path-like
        The landmarks file the frames index into; stored relative to *path*.
    regions : dict
        Region name to ``{"points": [...], "method": str, "frames": [...], "rows": [...], "error": float}``:
        ``frames`` are the key frames' source frame numbers (``landmarks.npz`` ``frames``), ``rows`` the same
        keys as rows of the landmarks file (what the stages index with).
    neutral : dict, optional
        The neutral (rest) frame every region keeps: ``{"frame": int (source frame), "row": int, "source":
        "given" | "take" | "calibration", "reason": str, ...}``; ``decompose`` and ``auto-pose`` with
        ``neutral_frame: auto`` use it. None: no neutral frame (``select --no-neutral``).
    """
    path = Path(path)
    rel = os.path.relpath(Path(landmarks).resolve(), path.resolve().parent)
    doc = {"landmarks": rel, "regions": regions, "version": __version__}
    if neutral is not None:
        doc["neutral"] = neutral
    write_json(path, doc)


@dataclass
class Keys:
    """Parsed ``keys.json``: region name to ``{"points", "frames", "rows", "method", "error"}``.

    ``frames`` name the key frames by source frame number (their labels in ``weights.npz``, ``targets.yaml``
    and the key OBJs' names); ``rows``, the same keys as rows of the landmarks file, are None until
    :meth:`resolve_rows` finds them in the landmarks.
    """

    path: Path
    landmarks: Path | None
    regions: dict = field(default_factory=dict)
    #: The neutral frame's record (``frame`` (source), ``row``, ``source``, ``reason``, ...), or None when
    #: keys.json has none.
    neutral: dict | None = None

    def resolve_rows(self, source_frames: np.ndarray, landmarks) -> None:
        """Set each region's ``rows`` (and the neutral's ``row``): the rows of the landmarks whose source frame
        numbers are its key ``frames``. The frames decide (a ``rows`` list in the file is only their cache, and a
        key list edited by hand needs no ``rows``).

        Parameters
        ----------
        source_frames : ndarray, shape (T,), int, increasing
            The landmarks' source frame number of each row (``Landmarks.timing()[0]``).
        landmarks : path-like
            Named in the error.

        Raises
        ------
        InputError
            For a key frame (or the neutral frame) that is not a frame of the landmarks, naming the region, the
            frame and the take's frames.
        """
        src = np.asarray(source_frames, dtype=np.int64)
        T = len(src)

        def row(f, what):
            r = int(np.searchsorted(src, f))
            if r >= T or src[r] != f:
                span = f"source frames {int(src[0])}-{int(src[-1])}" if T else "no frames"
                raise InputError(f"{self.path}: {what} {f} is outside the take ({T} frames in {landmarks}, "
                                 f"{span})")
            return r

        for name, reg in self.regions.items():
            reg["rows"] = [row(f, f"region {name!r} key frame") for f in reg["frames"]]
        if self.neutral is not None:
            self.neutral["row"] = row(int(self.neutral["frame"]), "neutral frame")


def read_keys(path: str | os.PathLike) -> Keys:
    """Read and check ``keys.json``.

    Raises
    ------
    InputError
        For a missing file, invalid JSON, or a region without integer
        ``points`` and ``frames`` lists.
    """
    path = Path(path)
    try:
        data = json.loads(read_text(path, "keys"))
    except (json.JSONDecodeError, RecursionError) as exc:
        raise InputError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(data, dict) or not isinstance(data.get("regions"), dict) or not data["regions"]:
        raise InputError(f"{path}: expected {{'regions': {{name: {{'points': [...], 'frames': [...]}}}}}}")
    regions = {}
    for name, reg in data["regions"].items():
        check_name(name, f"{path}: region")
        for key in ("points", "frames"):
            vals = reg.get(key) if isinstance(reg, dict) else None
            if not isinstance(vals, list) or not vals or not all(
                    isinstance(v, int) and not isinstance(v, bool) and 0 <= v < 1 << 31 for v in vals):
                raise InputError(f"{path}: region {name!r} key {key!r} must be a non-empty list of integers >= 0 "
                                 f"(not true/false), got {str(vals)[:60]}")
        if len(set(reg["frames"])) != len(reg["frames"]):
            raise InputError(f"{path}: region {name!r} lists a key frame twice")
        regions[name] = {"points": list(reg["points"]), "frames": list(reg["frames"]), "rows": None,
                         "method": reg.get("method"), "error": reg.get("error")}  # rows: Keys.resolve_rows
    lm = data.get("landmarks")
    return Keys(path, (path.parent / lm) if isinstance(lm, str) else None, regions, _neutral_record(data, path))


#: Where a neutral frame recorded in keys.json came from.
NEUTRAL_SOURCES = ("given", "take", "calibration")


def _neutral_record(data: dict, path: Path) -> dict | None:
    """keys.json's ``neutral``: a mapping with an integer ``frame`` >= 0 and a known ``source``, or absent."""
    rec = data.get("neutral")
    if rec is None:
        return None
    frame = rec.get("frame") if isinstance(rec, dict) else None
    if not isinstance(frame, int) or isinstance(frame, bool) or not 0 <= frame < 1 << 31:
        raise InputError(f"{path}: 'neutral' must be {{'frame': integer >= 0, 'source': ...}}, got {str(rec)[:60]}")
    if rec.get("source") not in NEUTRAL_SOURCES:
        raise InputError(f"{path}: neutral.source must be one of {', '.join(NEUTRAL_SOURCES)}, got "
                         f"{rec.get('source')!r}")
    return {**rec, "row": None}  # (Keys.resolve_rows finds it from the frame)


# --------------------------------------------------------------------------- weights.npz


#: Per-region keys of ``weights.npz`` besides the weights themselves (``<region><suffix>``).
WEIGHT_SUFFIXES = ("_frames", "_residual", "_cardinality", "_lost")

#: Top-level arrays of ``weights.npz`` that are no region: each row's source frame number and time (seconds).
TIMING_KEYS = ("frame", "time")


def save_weights(path, regions: dict, meta: dict, extras: dict | None = None, *, frames=None, times=None) -> None:
    """Write ``weights.npz``.

    Parameters
    ----------
    regions : dict
        Region name to ``(weights (T, K), frames (K,), residual (T,))``.
    meta : dict
        Stored as a JSON string under ``meta``.
    extras : dict, optional
        Region name to ``{"cardinality": int (T,), "lost": bool (T,)}``,
        stored as ``<region>_cardinality`` and ``<region>_lost``.
    frames, times : ndarray, shape (T,), optional
        Each row's source frame number (int64) and time in seconds (float64), stored as ``frame`` and ``time``.
    """
    arrays = {}
    for name, (w, kframes, res) in regions.items():
        if name in TIMING_KEYS:
            raise ParameterError(f"region {name!r}: the name is taken by weights.npz's per-frame {name} column")
        arrays[name] = np.asarray(w, dtype=np.float64)
        arrays[f"{name}_frames"] = np.asarray(kframes, dtype=np.int64)
        arrays[f"{name}_residual"] = np.asarray(res, dtype=np.float64)
    if frames is not None:
        arrays["frame"] = np.asarray(frames, dtype=np.int64)
    if times is not None:
        arrays["time"] = np.asarray(times, dtype=np.float64)
    for name, ex in (extras or {}).items():
        if "cardinality" in ex:
            arrays[f"{name}_cardinality"] = np.asarray(ex["cardinality"], dtype=np.int64)
        if "lost" in ex:
            arrays[f"{name}_lost"] = np.asarray(ex["lost"], dtype=bool)
    arrays["meta"] = np.array(json.dumps({"version": __version__, **meta}, sort_keys=True))
    # stored, not deflated: weight curves are float64 noise to zlib (about 2:1 at 40 MB/s, a fifth
    # of a second for a 50,000-frame take) and the file is an intermediate
    savez(path, arrays, compress=False)


def load_weights(path, *, timing: bool = False) -> tuple:
    """Read ``weights.npz``.

    Returns
    -------
    regions : dict
        Region name to ``(weights (T, K), frames (K,), residual (T,))``.
    meta : dict
    frames, times : ndarray, shape (T,)
        With *timing* only: each row's source frame number and time in seconds (``frame`` and ``time``;
        without them frames 0 … T−1 at ``meta['fps']``, default 30).
    """
    path = Path(path)
    data = load_npz(path)
    stored = {k: data.pop(k) for k in TIMING_KEYS if k in data}
    meta = {}
    if "meta" in data:
        m = data.pop("meta")
        try:
            if m.dtype.kind not in "US" or m.size != 1:
                raise ParameterError(f"dtype {m.dtype}, shape {m.shape}")
            meta = json.loads(str(m.ravel()[0]))
        except (ValueError, RecursionError) as exc:
            raise InputError(f"{path}: 'meta' must be one JSON string ({exc})") from None
        if not isinstance(meta, dict):
            raise InputError(f"{path}: 'meta' must be a JSON object, got {type(meta).__name__}")
        fps = meta.get("fps")
        if fps is not None and (isinstance(fps, bool) or not isinstance(fps, (int, float))
                                or not np.isfinite(fps) or fps <= 0):
            raise InputError(f"{path}: meta 'fps' must be a finite number > 0, got {fps!r}")
    regions = {}
    for name in sorted(k for k in data if not k.endswith(WEIGHT_SUFFIXES)):
        check_name(name, f"{path}: region")
        w = data[name]
        frames = data.get(f"{name}_frames")
        if frames is None or w.ndim != 2 or frames.shape != (w.shape[1],):
            raise InputError(f"{path}: region {name!r} needs '{name}' (T, K) and '{name}_frames' (K,)")
        if w.dtype.kind not in "iuf" or frames.dtype.kind not in "iu":
            raise InputError(f"{path}: region {name!r}: '{name}' must hold numbers and '{name}_frames' integers, "
                             f"got {w.dtype} and {frames.dtype}")
        if not np.isfinite(w).all():
            raise InputError(f"{path}: region {name!r}: weights must be finite")
        if np.any(frames < 0):
            raise InputError(f"{path}: region {name!r}: '{name}_frames' must be frame numbers >= 0")
        res = data.get(f"{name}_residual", np.zeros(w.shape[0]))
        regions[name] = (w, frames, res)
    if not regions:
        raise InputError(f"{path}: no weight arrays found")
    T = {w.shape[0] for w, _, _ in regions.values()}
    if len(T) != 1:
        raise InputError(f"{path}: regions have different frame counts {sorted(T)}")
    if not timing:
        return regions, meta
    return (regions, meta, *_timing(stored, path, T.pop(), float(meta.get("fps") or 30.0)))


def _timing(stored: dict, path, T: int, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """``frame`` and ``time`` of ``weights.npz`` checked (T increasing values), or frames 0 … T−1 at *fps*."""
    frames = stored.get("frame")
    if frames is None:
        frames = np.arange(T, dtype=np.int64)
    elif frames.dtype.kind not in "iu" or frames.shape != (T,) or np.any(np.diff(frames) <= 0):
        raise InputError(f"{path}: 'frame' must be {T} increasing integers (one per row), got {frames.dtype} of "
                         f"shape {frames.shape}")
    times = stored.get("time")
    if times is None:
        times = frames / fps
    elif times.dtype.kind not in "iuf" or times.shape != (T,) or not np.isfinite(times).all() \
            or np.any(np.diff(times) <= 0):
        raise InputError(f"{path}: 'time' must be {T} finite increasing seconds (one per row), got {times.dtype} "
                         f"of shape {times.shape}")
    return frames.astype(np.int64), times.astype(np.float64)


def weights_csv(regions: dict, fps: float, frames=None, times=None) -> str:
    """CSV text: ``frame,time`` then one column per ``region:keyframe``.

    *frames*, *times*: each row's source frame number and time in seconds (default: rows 0 … T−1 at *fps*).
    """
    names = sorted(regions)
    T = regions[names[0]][0].shape[0]
    header = ["frame", "time"] + [f"{n}:{int(f)}" for n in names for f in regions[n][1]]
    cols = np.concatenate([regions[n][0] for n in names], axis=1).astype(np.float64)
    # one %-format per row (the same text as f"{v:.6f}" per value, about 4x faster)
    row = "%d,%.6f" + ",%.6f" * cols.shape[1]
    frames = list(range(T)) if frames is None else [int(f) for f in frames]
    times = [f / fps for f in frames] if times is None else [float(t) for t in times]
    lines = [",".join(header)]
    lines += [row % (frames[t], times[t], *vals) for t, vals in enumerate(cols.tolist())]
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- targets.yaml


@dataclass
class Targets:
    """Parsed ``targets.yaml``; every path absolute.

    Attributes
    ----------
    neutral : Path or None
    regions : dict
        Region name to ``{"keys": {frame: Path}, "vertices": Path or None,
        "falloff": float}`` (falloff width in model units, 0 for none).
    """

    path: Path
    neutral: Path | None
    regions: dict
    #: ``rig.yaml`` the keys were posed on (``rig:``; written by ``auto-pose``), or None for sculpted keys.
    rig: Path | None = None
    #: The key frames' slider values (``sliders:``, an animation CSV/NPZ, one row per key frame), or None.
    sliders: Path | None = None
    #: Every frame's slider values (``curves:``, an animation CSV/NPZ, one row per frame of the take; written by
    #: ``auto-pose --frames all``), or None: ``apply`` then drives the rig with them instead of the weights.
    curves: Path | None = None

    def files(self) -> list[Path]:
        """Every file the targets reference (inputs for up-to-date checks)."""
        out = [self.neutral] if self.neutral else []
        for reg in self.regions.values():
            out += list(reg["keys"].values())
            if reg["vertices"]:
                out.append(reg["vertices"])
        if self.rig is not None:
            out += [self.rig, *read_rig(self.rig).files()]
        if self.sliders is not None:
            out.append(self.sliders)
        if self.curves is not None:
            out.append(self.curves)
        return list(dict.fromkeys(out))


def read_targets(path: str | os.PathLike) -> Targets:
    """Read ``targets.yaml`` (paths relative to the file).

    Raises
    ------
    InputError
        Naming the file and the region or key that is malformed.
    """
    path = Path(path)
    data = read_yaml_file(path, "targets")
    if not isinstance(data, dict) or not isinstance(data.get("regions"), dict) or not data["regions"]:
        raise InputError(f"{path}: expected 'regions: {{name: {{keys: {{frame: file.obj}}}}}}'")
    unknown = set(data) - {"neutral", "regions", "rig", "sliders", "curves"}
    if unknown:
        raise InputError(f"{path}: unknown key {sorted(unknown)[0]!r}; expected neutral, regions, rig, sliders, curves")
    for key in ("rig", "sliders", "neutral", "curves"):
        if data.get(key) is not None and not isinstance(data[key], str):
            raise InputError(f"{path}: {key}: expected a file path, got {data[key]!r}")
    if (data.get("rig") is None) != (data.get("sliders") is None):
        raise InputError(f"{path}: 'rig' and 'sliders' go together (keys posed on a rig, with their slider values)")
    if data.get("curves") is not None and data.get("rig") is None:
        raise InputError(f"{path}: 'curves' (every frame's sliders) needs 'rig' and 'sliders'")
    base = path.parent
    regions = {}
    for name, reg in data["regions"].items():
        if not isinstance(reg, dict) or not isinstance(reg.get("keys"), dict) or not reg["keys"]:
            raise InputError(f"{path}: region {name!r} needs 'keys: {{frame: file.obj, ...}}'")
        keys = {}
        for frame, obj in reg["keys"].items():
            if not isinstance(frame, int) or not isinstance(obj, str):
                raise InputError(f"{path}: region {name!r}: key {frame!r} must map an integer frame to an OBJ path")
            keys[frame] = base / obj
        verts = reg.get("vertices")
        unknown = set(reg) - {"keys", "vertices", "falloff", "sliders"}
        if unknown:
            raise InputError(f"{path}: region {name!r}: unknown key {sorted(unknown)[0]!r}; "
                             "expected keys, vertices, falloff, sliders")
        owned = reg.get("sliders")
        if owned is not None and (not isinstance(owned, list) or not all(isinstance(n, str) for n in owned)):
            raise InputError(f"{path}: region {name!r}: sliders: expected a list of the rig's slider names")
        falloff = reg.get("falloff", 0)
        if isinstance(falloff, bool) or not isinstance(falloff, (int, float)) or not falloff >= 0:
            raise InputError(f"{path}: region {name!r}: falloff must be a number >= 0 (model units), got {falloff!r}")
        regions[str(name)] = {"keys": keys, "vertices": base / verts if isinstance(verts, str) else None,
                              "falloff": float(falloff), "sliders": owned}
    neutral = data.get("neutral")
    rig, sliders, curves = data.get("rig"), data.get("sliders"), data.get("curves")
    return Targets(path, base / neutral if isinstance(neutral, str) else None, regions,
                   None if rig is None else base / rig, None if sliders is None else base / sliders,
                   None if curves is None else base / curves)


def targets_yaml(regions: dict, *, neutral: str | None = None, comment: str = "", rig: str | None = None,
                 sliders: str | None = None, curves: str | None = None) -> str:
    """Text of a ``targets.yaml`` (deterministic, commented).

    Parameters
    ----------
    regions : dict
        Region name to ``{"keys": {frame: relpath}, "vertices": relpath or None}``.
    """
    lines = [f"# {c}" if c else "#" for c in comment.splitlines()]
    if neutral:
        lines.append(f"neutral: {json.dumps(neutral)}")
    if rig:
        lines.append(f"rig: {json.dumps(rig)}")
        lines.append(f"sliders: {json.dumps(sliders)}")
        if curves:
            lines.append(f"curves: {json.dumps(curves)}")
    lines.append("regions:")
    for name, reg in regions.items():
        lines.append(f"  {name}:")
        lines.append("    keys:")
        for frame, obj in sorted(reg["keys"].items()):
            lines.append(f"      {int(frame)}: {json.dumps(str(obj))}")
        if reg.get("vertices"):
            lines.append(f"    vertices: {json.dumps(str(reg['vertices']))}")
        if reg.get("falloff"):
            lines.append(f"    falloff: {float(reg['falloff'])!r}")
        if reg.get("sliders") is not None:
            lines.append(f"    sliders: {json.dumps(list(reg['sliders']))}")
    return "\n".join(lines) + "\n"


def write_targets(path, regions: dict, *, neutral=None, comment: str = "", rig=None, sliders=None,
                  curves=None) -> None:
    """Atomically write a ``targets.yaml``; see :func:`targets_yaml`."""
    write_text(path, targets_yaml(regions, neutral=neutral, comment=comment, rig=rig, sliders=sliders,
                                  curves=curves))


def read_vertex_mask(path: Path, n_vertices: int) -> np.ndarray:
    """Read a region mask: vertex ids (one per line, or a JSON list) or one weight per vertex.

    Returns
    -------
    ndarray, shape (N,), float64 in [0, 1]
    """
    text = read_text(path, "region mask") if Path(path).is_file() else None
    if text is None:
        raise InputError(f"{path}: region mask file not found")
    try:
        vals = json.loads(text) if text.lstrip().startswith("[") else [float(t) for t in text.split()]
        if not isinstance(vals, list) or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                 for v in vals):
            raise ParameterError("expected numbers")
        vals = np.asarray(vals, dtype=np.float64)
    except (ValueError, RecursionError) as exc:
        raise InputError(f"{path}: expected vertex ids or per-vertex weights ({exc})") from None
    if vals.ndim != 1 or not np.isfinite(vals).all():
        raise InputError(f"{path}: expected finite vertex ids or per-vertex weights")
    if vals.size == n_vertices and (np.any(vals % 1 != 0) or vals.max(initial=0) <= 1):
        if np.any((vals < 0) | (vals > 1)):
            raise InputError(f"{path}: per-vertex weights must lie in [0, 1]")
        return vals
    if np.any(vals % 1 != 0) or np.any(vals < 0) or np.any(vals >= n_vertices):
        raise InputError(f"{path}: vertex ids must be integers in [0, {n_vertices})")
    mask = np.zeros(n_vertices)
    mask[vals.astype(int)] = 1.0
    return mask


__all__ = [
    "WEIGHT_SUFFIXES", "Keys", "Targets", "dumps_json", "load_weights", "read_keys", "read_targets",
    "read_vertex_mask", "save_weights", "targets_yaml", "weights_csv", "write_keys", "write_targets",
]
