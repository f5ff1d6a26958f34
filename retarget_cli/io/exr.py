"""EXR vertex-animation texture (VAT): one row per frame, one column per vertex.

Game engines play an animated mesh by sampling a float texture in the vertex
shader: row ``t`` (frame), column ``i`` (vertex ``i`` in OBJ order), RGB =
the vertex's position or its offset from the neutral. The texture is written
with OpenEXR (float32, ZIP compression) next to a JSON sidecar giving the
frame count, fps, mode and the bounds of the stored values.

Rows are frames in order; each row's source frame number (``landmarks.npz``
``frames``: 100, 102, … for a take tracked with ``start: 100, step: 2``) is
carried in the EXR header (:data:`FRAMES_ATTRIBUTE`, a string of comma-separated
integers: ``"100,102,104"``) and in the
sidecar (``source_frames``, with ``times`` in seconds and ``source_fps``).
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import InputError, ParameterError, ShapeError
from .atomic import write_bytes, write_json

#: Values the texture can hold.
VAT_MODES = ("offsets", "positions")

#: EXR header attribute holding each row's source frame number: a string, T integers separated by commas.
FRAMES_ATTRIBUTE = "retargetFrames"


def vat_sidecar(values: np.ndarray, *, fps: float, mode: str, exr_name: str, frames=None, times=None,
                source_fps=None) -> dict:
    """The sidecar's contents for a (T, N, 3) texture (*frames*, *times*: (T,) source frame numbers and seconds)."""
    T, N, _ = values.shape
    frames = np.arange(T) if frames is None else np.asarray(frames)
    rate = float(source_fps or fps)
    times = frames / rate if times is None else np.asarray(times, dtype=np.float64)
    return {
        "exr": exr_name,
        "frames": int(T),
        "vertices": int(N),
        "fps": float(fps),
        "mode": mode,
        "layout": "row = frame in order (row t = source frame source_frames[t]), column = vertex in OBJ order, "
                  "RGB = XYZ, float32",
        "source_frames": [int(f) for f in frames],
        "times": [round(float(t), 6) for t in times],
        "source_fps": rate,
        "bounds": {"min": [float(v) for v in values.min(axis=(0, 1))],
                   "max": [float(v) for v in values.max(axis=(0, 1))]},
        "version": __version__,
    }


def write_vat(path: str | os.PathLike, values, *, fps: float, mode: str, sidecar: str | os.PathLike, frames=None,
              times=None, source_fps=None) -> None:
    """Atomically write a vertex-animation texture and its JSON sidecar.

    Parameters
    ----------
    path : path-like
        ``.exr`` file.
    values : ndarray, shape (T, N, 3)
        Per frame and vertex: positions or offsets from the neutral.
    fps : float
    mode : {"offsets", "positions"}
        Recorded in the sidecar.
    sidecar : path-like
        JSON file.
    frames : ndarray, shape (T,), int, optional
        Each row's source frame number (default 0 … T−1): the header's :data:`FRAMES_ATTRIBUTE` and the
        sidecar's ``source_frames``.
    times : ndarray, shape (T,), optional
        Each row's time in seconds (default ``frames / source_fps``), in the sidecar.
    source_fps : float, optional
        The source's frame rate (default *fps*), in the sidecar.
    """
    import OpenEXR

    if mode not in VAT_MODES:
        raise ParameterError(f"mode: expected one of {', '.join(VAT_MODES)}, got {mode!r}")
    values = np.asarray(values, dtype=np.float32)
    if values.ndim != 3 or values.shape[2] != 3 or values.shape[0] < 1 or values.shape[1] < 1:
        raise ShapeError(f"values: expected shape (T, N, 3), got {values.shape}")
    if not np.all(np.isfinite(values)):
        raise ShapeError("values: texture values must be finite")
    frames = np.arange(values.shape[0]) if frames is None else np.asarray(frames)
    if frames.shape != (values.shape[0],):
        raise ShapeError(f"frames: expected shape ({values.shape[0]},), one per row, got {frames.shape}")
    channels = {c: np.ascontiguousarray(values[:, :, i]) for i, c in enumerate("RGB")}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              FRAMES_ATTRIBUTE: ",".join(str(int(f)) for f in frames)}
    buf = io.BytesIO()
    OpenEXR.File(header, channels).write(buf)
    write_bytes(path, buf.getvalue())
    write_json(sidecar, vat_sidecar(values, fps=fps, mode=mode, exr_name=Path(path).name, frames=frames, times=times,
                                    source_fps=source_fps))


def read_vat(path: str | os.PathLike) -> np.ndarray:
    """Read a texture written by :func:`write_vat` (its rows' source frame numbers: :func:`read_vat_frames`).

    Returns
    -------
    ndarray, shape (T, N, 3), float32
    """
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: EXR file not found")
    with OpenEXR.File(str(path), separate_channels=True) as f:
        ch = f.channels()
        try:
            return np.stack([np.asarray(ch[c].pixels, dtype=np.float32) for c in "RGB"], axis=-1)
        except KeyError as exc:
            raise InputError(f"{path}: expected R, G and B channels, missing {exc}") from None


def read_vat_frames(path: str | os.PathLike) -> np.ndarray | None:
    """The source frame number of each row of a texture written by :func:`write_vat` (its header's
    :data:`FRAMES_ATTRIBUTE`).

    Returns
    -------
    ndarray, shape (T,), int64, or None
        None for a texture without the attribute (written before it, or by another tool).
    """
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: EXR file not found")
    with OpenEXR.File(str(path)) as f:
        value = f.header().get(FRAMES_ATTRIBUTE)
    if value is None:
        return None
    try:
        return np.array([int(v) for v in str(value).split(",")], dtype=np.int64)
    except ValueError:
        raise InputError(f"{path}: header attribute {FRAMES_ATTRIBUTE}: expected integers separated by commas, got "
                         f"{str(value)[:40]!r}") from None
