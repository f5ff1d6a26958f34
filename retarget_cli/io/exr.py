"""EXR vertex-animation texture (VAT): one row per frame, one column per vertex.

Game engines play an animated mesh by sampling a float texture in the vertex
shader: row ``t`` (frame), column ``i`` (vertex ``i`` in OBJ order), RGB =
the vertex's position or its offset from the neutral. The texture is written
with OpenEXR (float32, ZIP compression) next to a JSON sidecar giving the
frame count, fps, mode and the bounds of the stored values.
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


def vat_sidecar(values: np.ndarray, *, fps: float, mode: str, exr_name: str) -> dict:
    """The sidecar's contents for a (T, N, 3) texture."""
    T, N, _ = values.shape
    return {
        "exr": exr_name,
        "frames": int(T),
        "vertices": int(N),
        "fps": float(fps),
        "mode": mode,
        "layout": "row = frame (row 0 = frame 0), column = vertex in OBJ order, RGB = XYZ, float32",
        "bounds": {"min": [float(v) for v in values.min(axis=(0, 1))],
                   "max": [float(v) for v in values.max(axis=(0, 1))]},
        "version": __version__,
    }


def write_vat(path: str | os.PathLike, values, *, fps: float, mode: str, sidecar: str | os.PathLike) -> None:
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
    """
    import OpenEXR

    if mode not in VAT_MODES:
        raise ParameterError(f"mode: expected one of {', '.join(VAT_MODES)}, got {mode!r}")
    values = np.asarray(values, dtype=np.float32)
    if values.ndim != 3 or values.shape[2] != 3 or values.shape[0] < 1 or values.shape[1] < 1:
        raise ShapeError(f"values: expected shape (T, N, 3), got {values.shape}")
    if not np.all(np.isfinite(values)):
        raise ShapeError("values: texture values must be finite")
    channels = {c: np.ascontiguousarray(values[:, :, i]) for i, c in enumerate("RGB")}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    buf = io.BytesIO()
    OpenEXR.File(header, channels).write(buf)
    write_bytes(path, buf.getvalue())
    write_json(sidecar, vat_sidecar(values, fps=fps, mode=mode, exr_name=Path(path).name))


def read_vat(path: str | os.PathLike) -> np.ndarray:
    """Read a texture written by :func:`write_vat`.

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
