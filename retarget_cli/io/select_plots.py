"""Pictures and tables for the artist: the key-selection evaluation (Chuang &
Bregler 2002, Fig. 6) and a contact sheet of the key frames.

Every file is written atomically and deterministically (same inputs, same bytes).
"""

from __future__ import annotations

import io
import logging
import os
from pathlib import Path

import numpy as np

from ..errors import InputError
from .atomic import write_bytes, write_json, write_text
from .frames import FrameSource

log = logging.getLogger(__name__)

#: Line styles after the paper's Figure 6 (solid blue PCA, dashed green/magenta clustering, red dot hull).
STYLES = {
    "pca-extremes": dict(color="tab:blue", linestyle="-", marker=None),
    "kmeans-2pc": dict(color="tab:green", linestyle="--", marker=None),
    "kmeans-3pc": dict(color="m", linestyle="--", marker=None),
    "convex-hull": dict(color="r", linestyle="none", marker="o"),
    "greedy": dict(color="k", linestyle="-", marker=None),
    "greedy-swap": dict(color="tab:orange", linestyle="none", marker="*"),
}


def curve_csv(rows_by_region: dict[str, list[dict]]) -> str:
    """CSV ``region,curve,method,k,error,frames`` (frames separated by spaces)."""
    lines = ["region,curve,method,k,error,frames"]
    for region, rows in rows_by_region.items():
        for r in rows:
            lines.append(f"{region},{r['curve']},{r['method']},{r['k']},{r['error']:.6f},"
                         + " ".join(map(str, r["frames"])))
    return "\n".join(lines) + "\n"


def write_curve_plot(path: str | os.PathLike, rows_by_region: dict[str, list[dict]], chosen_k: dict[str, int]) -> None:
    """E (eq. 5) against the number of keys, one panel per region, styled like Fig. 6 (PNG, SVG or PDF)."""
    try:
        import matplotlib
    except ImportError:
        raise InputError(f"{path}: plotting needs matplotlib; install it with pip install 'retarget[report]'") from None
    matplotlib.use("Agg", force=True)
    from matplotlib.figure import Figure

    regions = list(rows_by_region)
    fig = Figure(figsize=(5.0 * len(regions), 4.0), dpi=100)
    axes = fig.subplots(1, len(regions), squeeze=False)[0]
    for ax, region in zip(axes, regions):
        rows = rows_by_region[region]
        for curve, style in STYLES.items():
            pts = sorted((r["k"], r["error"]) for r in rows if r["curve"] == curve)
            if pts:
                ks, es = zip(*pts)
                ax.plot(ks, es, label=curve, linewidth=1.5, markersize=7, **style)
        if region in chosen_k:
            ax.axvline(chosen_k[region], color="0.6", linewidth=0.8, linestyle=":")
        ax.set_title(region)
        ax.set_xlabel("number of key shapes")
        ax.set_ylabel("reconstruction error E (eq. 5), px²")
        ax.set_yscale("log")
        ax.grid(True, which="both", color="0.9")
        ax.legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fmt = Path(path).suffix.lower().lstrip(".") or "png"
    meta = {"Software": None} if fmt == "png" else ({"CreationDate": None} if fmt == "pdf" else {"Date": None})
    fig.savefig(buf, format=fmt, metadata=meta)
    write_bytes(path, buf.getvalue())


def write_contact_sheet(path: str | os.PathLike, video: str | os.PathLike, points: np.ndarray,
                        keys: dict[str, tuple[list[int], list[int]]], *, tile: int = 200, columns: int = 6,
                        source_frames=None, fps=None) -> None:
    """Key frames cropped from *video* with their landmarks, labelled with frame number and region.

    Parameters
    ----------
    path : path-like
        PNG (or any image type OpenCV writes).
    video : path-like
    points : ndarray, shape (T, L, 2)
        Image-space landmarks (``landmarks.npz`` ``points``).
    keys : dict
        Region name to (landmark ids, key frames).
    tile : int
        Side of each square tile in pixels.
    columns : int
    source_frames : ndarray, shape (T,), optional
        The source frame number of each row of *points* (``landmarks.npz`` ``frames``); default the row.
    fps : float, optional
        The source's frame rate (a video's own when None).
    """
    import cv2


    rows = sorted({f for _, frames in keys.values() for f in frames})
    number = (lambda f: int(f)) if source_frames is None else (lambda f: int(source_frames[f]))
    wanted = {number(f): f for f in rows}
    images = {}
    with FrameSource(video, end=max(wanted) + 1, fps=fps, warn_missing=False) as reader:
        for img in reader:
            n = reader.frames[-1]
            if n in wanted and n not in reader.missing:
                images[wanted[n]] = img
    missing = [f for f in rows if f not in images]
    if missing:
        raise InputError(f"{video}: key frame {missing[0]} (source frame {number(missing[0])}) is beyond the end "
                         "of the video or missing from the sequence")
    tiles = []
    for region, (ids, frames) in keys.items():
        for f in frames:
            img = images[f]
            P = points[f]
            lo, hi = P.min(0), P.max(0)
            c, half = (lo + hi) / 2, max(float((hi - lo).max()) * 0.65, 8.0)
            s = tile / (2 * half)
            M = np.array([[s, 0, tile / 2 - s * c[0]], [0, s, tile / 2 - s * c[1]]])
            crop = cv2.warpAffine(img, M, (tile, tile), flags=cv2.INTER_AREA, borderValue=(40, 40, 40))
            Q = P * s + M[:, 2]
            inside = np.zeros(len(P), bool)
            inside[ids] = True
            for q, on in zip(Q, inside):
                cv2.circle(crop, (int(round(q[0])), int(round(q[1]))), 2 if on else 1,
                           (0, 255, 0) if on else (160, 160, 160), -1, cv2.LINE_AA)
            cv2.rectangle(crop, (0, 0), (tile, 18), (0, 0, 0), -1)
            cv2.putText(crop, f"{region}  frame {f}", (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1,
                        cv2.LINE_AA)
            tiles.append(crop)
    rows = -(-len(tiles) // columns)
    sheet = np.full((rows * tile, min(columns, len(tiles)) * tile, 3), 255, np.uint8)
    for i, t in enumerate(tiles):
        r, col = divmod(i, columns)
        sheet[r * tile:(r + 1) * tile, col * tile:(col + 1) * tile] = t
    ok, buf = cv2.imencode(Path(path).suffix or ".png", sheet)
    if not ok:
        raise InputError(f"{path}: OpenCV cannot write this image type")
    write_bytes(path, buf.tobytes())
    log.info("contact sheet: %d key frames -> %s", len(tiles), path)


def write_summary(path, summary: dict) -> None:
    write_json(path, summary)


__all__ = ["curve_csv", "write_curve_plot", "write_contact_sheet", "write_summary", "write_text"]
