"""Benchmark: every tracker on the shared real clips, judged against an independent detector.

For each clip of ``../shared/realdata/videos`` (d3, d9, d12; 512x512) it runs the ``track``
stage (decoding included) with every method and prints, per clip and method:

- frames per second of the whole stage, next to decode-only frames per second of the same video;
- the per-frame Pearson r of mouth opening (inner-lip gap / mouth width), eye opening (lid gap /
  eye width, each eye and their mean) and brow height (brow to eye-corner midpoint / inter-ocular
  distance) against MediaPipe Face Mesh 0.10.14 (``bench/reference``: its own venv, numpy < 2;
  it never drives a tracker);
- the smallest eye opening and the largest mouth opening the track reaches, next to MediaPipe's.

Methods: ``lk`` (from the shipped frame-0 ``.pts``), ``detect`` (the default where the extra is
installed: detections joined with optical flow) and ``detect-raw`` (the detections alone,
``fuse=False``), ``eigenpoints`` and ``facemark`` trained on 6 frames annotated by the detector
(``retarget annotate``); ``markers`` needs painted dots and is listed as not applicable.

Then the default method at 1280x720 and 1920x1080: the clip is scaled (face 720 and 1080 pixels
tall) and padded into a wide frame, written once to ``build/track-real/`` as MJPG, and tracked with
``track --downscale`` chosen as the stage does by default, against decode-only of the same file.

``--pictures DIR`` writes, per clip, the frame of MediaPipe's smallest eye opening (a blink) with
the default track and ``lk`` drawn on it beside MediaPipe's points.

Run: ``python bench/track_real.py [--clips d3,d9,d12] [--methods ...] [--pictures build/track-real]``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
CLIPS = ("d3", "d9", "d12")
METHODS = ("lk", "detect", "detect-raw", "eigenpoints", "facemark", "markers")
MEASURES = ("mouth", "eye", "eye_l", "eye_r", "brow")


def decode_fps(video: Path, gray: bool = True) -> tuple[float, int]:
    from retarget_cli.io.frames import FrameSource

    t0 = time.perf_counter()
    with FrameSource(str(video), gray=gray) as src:
        n = sum(1 for _ in src)
    return n / (time.perf_counter() - t0), n


def measures(points, layout) -> dict:
    from realrig.measures import face_measures

    m = face_measures(points, layout)
    m["eye"] = 0.5 * (m["eye_l"] + m["eye_r"])
    return m


def _inside(P, W, H) -> bool:
    return bool(((P >= 0) & (P <= np.array([W - 1, H - 1]))).all())


def run_method(method: str, video: Path, pts: Path, work: Path):
    """Track *video* with *method* through the stage runner; (points, seconds) or (None, reason)."""
    from retarget_cli.errors import InputError
    from retarget_cli.io.annotations import read_pts
    from retarget_cli.io.landmarks import load_landmarks
    from retarget_cli.stages import run_track
    from retarget_cli.stages.annotate import run_annotate

    out = work / f"{video.stem}-{method}.npz"
    kw = dict(video=str(video), output=str(out))
    if method == "lk":
        kw.update(init=str(pts), method="lk")
    elif method in ("detect", "detect-raw"):
        kw.update(init="auto", method="detect")
        if method == "detect-raw":
            kw["fuse"] = False
    elif method in ("eigenpoints", "facemark"):
        from retarget_cli.io.frames import FrameSource

        with FrameSource(str(video)) as src:
            n = src.frame_count
            W, H = src.frame_size
        # 12 frames spread over the clip; the 6 whose 68 points all lie inside the image (training needs that)
        frames = [round(i * (n - 1) / 11) for i in range(12)]
        ann_dir = work / f"{video.stem}-annotations"
        files = [f for f in run_annotate(video=str(video), frames=frames, output=str(ann_dir))
                 if _inside(read_pts(f), W, H)][:6]
        if len(files) < 5:
            return None, f"only {len(files)} of 12 detector annotations lie inside the image"
        kw.update(init=str(files[0]), annotations=[str(f) for f in files[1:]], method=method)
        if method == "facemark":
            from retarget_cli.stages import run_train_tracker

            model = work / f"{video.stem}-lbf.yaml.gz"
            if not model.exists():
                run_train_tracker(video=str(video), annotations=[str(f) for f in files], output=str(model))
            kw.update(model=str(model), annotations=None, init=str(files[0]))
    else:
        return None, "needs painted markers on the face"
    try:
        t0 = time.perf_counter()
        run_track(**kw)
        dt = time.perf_counter() - t0
    except InputError as exc:
        return None, str(exc)
    return load_landmarks(out).points, dt


def widescreen(video: Path, size: tuple[int, int], out: Path) -> Path:
    """*video* scaled to the frame's height and centred in a *size* frame (black bars), MJPG, once."""
    import cv2

    if out.exists():
        return out
    W, H = size
    cap = cv2.VideoCapture(str(video))
    fps = cap.get(cv2.CAP_PROP_FPS) or 30
    tmp = out.with_suffix(".part.avi")
    wr = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"MJPG"), fps, (W, H))
    while True:
        ok, f = cap.read()
        if not ok:
            break
        s = cv2.resize(f, (H * f.shape[1] // f.shape[0], H), interpolation=cv2.INTER_CUBIC)
        canvas = np.zeros((H, W, 3), np.uint8)
        x0 = (W - s.shape[1]) // 2
        canvas[:, x0:x0 + s.shape[1]] = s
        wr.write(canvas)
    wr.release()
    cap.release()
    tmp.rename(out)
    return out


def blink_picture(clip, video, tracks, ref_pts, ref_eye, out_dir: Path):
    import cv2

    from retarget_cli.io.overlay import draw_overlay
    from retarget_cli.methods.tracking.head import estimate_head

    f = int(np.nanargmin(ref_eye))
    cap = cv2.VideoCapture(str(video))
    cap.set(cv2.CAP_PROP_POS_FRAMES, f)
    ok, img = cap.read()
    cap.release()
    if not ok:
        return None
    tiles = []
    for name, P in tracks.items():
        C = np.ones(P.shape[:2])
        head, _ = estimate_head(P[f:f + 1], C[f:f + 1])
        tile = draw_overlay(img, P[f], C[f], head[0])
        cv2.putText(tile, f"{clip} frame {f}: {name}", (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2,
                    cv2.LINE_AA)
        tiles.append(tile)
    ref = img.copy()
    for x, y in ref_pts[f]:
        if np.isfinite(x):
            cv2.circle(ref, (int(round(x)), int(round(y))), 1, (0, 255, 255), -1, cv2.LINE_AA)
    cv2.putText(ref, f"{clip} frame {f}: MediaPipe (reference)", (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.6,
                (255, 255, 255), 2, cv2.LINE_AA)
    tiles.append(ref)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{clip}_blink_{f:05d}.png"
    cv2.imwrite(str(path), np.hstack(tiles))
    return path


def _parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--videos", type=Path, default=ROOT.parent / "shared" / "realdata" / "videos")
    ap.add_argument("--clips", default=",".join(CLIPS))
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--sizes", default="1280x720,1920x1080", help="Wide frames for the default method ('' none).")
    ap.add_argument("--pictures", type=Path, default=None)
    return ap.parse_args()


def _skip_reason(videos: Path) -> str | None:
    """Why the benchmark cannot run here (no clips, no detector extra), or None."""
    if not videos.is_dir():
        return f"{videos} not found (the shared real clips)"
    try:
        from retarget_cli.methods.tracking.detect import Detector

        Detector()
    except Exception as exc:  # noqa: BLE001 - the extra is missing
        return str(exc)
    return None


def _print_rows(rows) -> None:
    print("| clip | method | frames | frames/s | r mouth | r eyes | r eye L | r eye R | r brow "
          "| min eye | max mouth |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for clip, m, n, fps, why, r, meas in rows:
        if why is not None:
            print(f"| {clip} | {m} | | | n/a: {why} | | | | | | |")
            continue
        ext = f"{np.nanmin(meas['eye']):.3f} | {np.nanmax(meas['mouth']):.3f}"
        if r is None:
            print(f"| {clip} | MediaPipe / {m} | {n} | {fps:.0f} | | | | | | {ext} |")
            continue
        cells = " | ".join(f"{r[k]:.2f}" for k in MEASURES)
        print(f"| {clip} | {m} | {n} | {fps:.0f} | {cells} | {ext} |")


def _print_means(methods, summary) -> None:
    print()
    print("Mean over the clips (lowest clip in brackets):")
    print("| method | r mouth | r eyes | r brow |")
    print("|---|---|---|---|")
    for m in methods:
        if not summary[m]["mouth"]:
            continue
        cells = " | ".join(f"{np.mean(summary[m][k]):.2f} ({np.min(summary[m][k]):.2f})"
                           for k in ("mouth", "eye", "brow"))
        print(f"| {m} | {cells} |")


def _print_sizes(videos: Path, sizes_arg: str, build: Path, work: Path) -> None:
    sizes = [tuple(int(v) for v in s.split("x")) for s in sizes_arg.split(",") if s]
    if not sizes:
        return
    print()
    print("Default method (detect) at production sizes, clip d3 scaled into the frame:")
    print("| size | decode-only frames/s | track frames/s | track / decode |")
    print("|---|---|---|---|")
    for W, H in sizes:
        wide = widescreen(videos / "d3.mp4", (W, H), build / f"d3_{W}x{H}.avi")
        dfps, n = decode_fps(wide)
        P, dt = run_method("detect", wide, None, work)
        print(f"| {W}x{H} | {dfps:.0f} | {len(P) / dt:.0f} | {len(P) / dt / dfps:.2f} |")


def main() -> int:
    from realrig.measures import MEDIAPIPE, MULTIPIE68, pearson
    from reference import ReferenceUnavailable, reference_landmarks

    args = _parse_args()
    why = _skip_reason(args.videos)
    if why is not None:
        print(f"skipped: {why}")
        return 0
    import logging

    logging.disable(logging.WARNING)
    build = ROOT / "build" / "track-real"
    build.mkdir(parents=True, exist_ok=True)
    methods = [m for m in args.methods.split(",") if m]
    rows, summary = [], {m: {k: [] for k in MEASURES} for m in methods}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for clip in args.clips.split(","):
            video, pts = args.videos / f"{clip}.mp4", args.videos / f"{clip}_00000.pts"
            try:
                ref = reference_landmarks(video, log=lambda m: print(m, file=sys.stderr))
            except ReferenceUnavailable as exc:
                print(f"skipped: {exc}")
                return 0
            found = ref["found"]
            rm = measures(np.where(found[:, None, None], ref["points"], np.nan), MEDIAPIPE)
            dfps, n = decode_fps(video)
            rows.append((clip, "decode only", n, dfps, None, None, rm))
            tracks = {}
            for m in methods:
                P, how = run_method(m, video, pts, work)
                if P is None:
                    rows.append((clip, m, n, None, how, None, None))
                    continue
                tracks[m] = P
                tm = measures(P, MULTIPIE68)
                r = {k: pearson(tm[k][:len(found)], rm[k][:len(P)], found[:len(P)]) for k in MEASURES}
                for k in MEASURES:
                    summary[m][k].append(r[k])
                rows.append((clip, m, len(P), len(P) / how, None, r, tm))
            if args.pictures and tracks:
                show = {k: tracks[k] for k in ("detect", "lk") if k in tracks}
                path = blink_picture(clip, video, show, ref["points"], rm["eye"], args.pictures)
                if path:
                    print(f"wrote {path}", file=sys.stderr)

        _print_rows(rows)
        _print_means(methods, summary)
        _print_sizes(args.videos, args.sizes, build, work)
    return 0

if __name__ == "__main__":
    sys.exit(main())
