"""Benchmark: the pretrained detector (``track --method detect``) against ``lk`` on the shared real clips.

For each clip of ``../shared/realdata/videos`` (d3, d9, d12) it runs, in the
same process and on the same grayscale frames (decoded once, beforehand, so
decoding is in neither timing):

- ``lk`` from the shipped frame-0 ``.pts``;
- ``detect`` (dlib's HOG face box on the first frame, 68-point shape predictor on every frame);

and prints per clip: frames/s of each and their ratio, and min / max of the
per-frame eye opening (mean lid gap 37-41, 38-40, 43-47, 44-46 over eye
width, 0-based ids) and inner-lip mouth opening (62-66 over 60-64). With
``--pictures DIR`` it also writes PNGs of both tracks drawn on the frame of
the detector's smallest eye opening (a blink) and widest mouth, and with
``--reference DIR`` (a folder of ``<clip>.npz`` holding MediaPipe-derived
``eye``/``mouth`` per frame, or 68-point ``points``) the Pearson r of each
track's openings against it.

Run: ``python bench/track_detect_real.py [--videos ../shared/realdata/videos] [--pictures build/detect-bench]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CLIPS = ("d3", "d9", "d12")


def read_gray(path: Path) -> tuple[list[np.ndarray], list[np.ndarray]]:
    import cv2

    cap = cv2.VideoCapture(str(path))
    colour, gray = [], []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        colour.append(f)
        gray.append(cv2.cvtColor(f, cv2.COLOR_BGR2GRAY))
    cap.release()
    return colour, gray


def reference_openings(ref_dir: Path | None, clip: str):
    """(eye, mouth) per frame from ``ref_dir/<clip>.npz``, or None."""
    from retarget_cli.track.detect import eye_opening, mouth_opening

    if ref_dir is None or not (ref_dir / f"{clip}.npz").is_file():
        return None
    d = np.load(ref_dir / f"{clip}.npz")
    if "eye" in d and "mouth" in d:
        return np.asarray(d["eye"], float), np.asarray(d["mouth"], float)
    if "points" in d and d["points"].shape[1] == 68:
        return eye_opening(d["points"]), mouth_opening(d["points"])
    return None


def pearson(a, b) -> float:
    n = min(len(a), len(b))
    a, b = np.asarray(a[:n], float), np.asarray(b[:n], float)
    ok = np.isfinite(a) & np.isfinite(b)
    return float(np.corrcoef(a[ok], b[ok])[0, 1])


def main() -> int:
    from retarget_cli.io.annotations import read_pts
    from retarget_cli.io.overlay import draw_overlay
    from retarget_cli.track.detect import Detector, eye_opening, mouth_opening, track_detect
    from retarget_cli.track.head import estimate_head
    from retarget_cli.track.lk import track_lk

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--videos", type=Path, default=ROOT.parent / "shared" / "realdata" / "videos")
    ap.add_argument("--clips", default=",".join(CLIPS))
    ap.add_argument("--pictures", type=Path, default=None, help="Write overlay PNGs here.")
    ap.add_argument("--reference", type=Path, default=None,
                    help="Folder of <clip>.npz with per-frame 'eye' and 'mouth' (or 68 'points') of an independent "
                         "detector.")
    args = ap.parse_args()
    if not args.videos.is_dir():
        print(f"skipped: {args.videos} not found (the shared real clips)")
        return 0
    try:
        det = Detector()
    except Exception as exc:  # the extra is missing
        print(f"skipped: {exc}")
        return 0
    import cv2

    rows = []
    for clip in args.clips.split(","):
        colour, gray = read_gray(args.videos / f"{clip}.mp4")
        init = read_pts(args.videos / f"{clip}_00000.pts")
        t0 = time.perf_counter()
        lk, lk_conf = track_lk(gray, init)
        t_lk = time.perf_counter() - t0
        t0 = time.perf_counter()
        dt, dt_conf = track_detect(gray, detector=det)
        t_dt = time.perf_counter() - t0
        n = len(gray)
        ref = reference_openings(args.reference, clip)
        openings = {}
        for name, P in (("lk", lk), ("detect", dt)):
            e, m = eye_opening(P), mouth_opening(P)
            openings[name] = (e, m)
            rs = (pearson(m, ref[1]), pearson(e, ref[0])) if ref is not None else (np.nan, np.nan)
            rows.append((clip, name, n, n / (t_lk if name == "lk" else t_dt), e.min(), e.max(), m.min(), m.max(), *rs))
        rows.append((clip, "detect / lk speed", n, t_lk / t_dt) + (np.nan,) * 6)
        if args.pictures:
            args.pictures.mkdir(parents=True, exist_ok=True)
            e, m = openings["detect"]
            for what, f in (("blink", int(np.argmin(e))), ("mouth", int(np.argmax(m)))):
                tiles = []
                for name, P, C in (("lk", lk, lk_conf), ("detect", dt, dt_conf)):
                    head, _ = estimate_head(P[f:f + 1], C[f:f + 1])
                    img = draw_overlay(colour[f], P[f], C[f], head[0])
                    ee, mm = openings[name][0][f], openings[name][1][f]
                    cv2.putText(img, f"{clip} {f} {name}: eye {ee:.2f} mouth {mm:.2f}", (8, 24),
                                cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2, cv2.LINE_AA)
                    tiles.append(img)
                out = args.pictures / f"{clip}_{what}_{f:05d}.png"
                cv2.imwrite(str(out), np.hstack(tiles))
                print(f"wrote {out}", file=sys.stderr)
    print("| clip | method | frames | frames/s | eye min | eye max | mouth min | mouth max | r mouth | r eyes |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for clip, name, n, fps, *v in rows:
        if name.startswith("detect /"):
            print(f"| {clip} | {name} | {n} | {fps:.2f}x | | | | | | |")
            continue
        cells = " | ".join("" if not np.isfinite(x) else f"{x:.3f}" for x in v)
        print(f"| {clip} | {name} | {n} | {fps:.0f} | {cells} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
