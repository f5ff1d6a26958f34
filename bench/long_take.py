"""Benchmark: a long 1080p take through the whole documented path with flat memory (issues #31 item 4, #33).

The take: d12 (``../shared/realdata/videos``, 512x512, 25 fps) scaled uniformly to 1080 rows (bilinear) and
centred on a black 1920x1080 frame (as ``bench/speed_peer.py`` upscales), looped back and forth (no cut of its
own), with a black gap of 1-3 s (seeded) every 30 s from 15 s on: twenty gaps in 10 minutes, as
``bench/gaps.py --long`` makes them at 256x256. One video as long as the longest take asked for is written
once with OpenCV (mp4v) to ``build/long_take/`` (11 MB a half minute; 10 minutes: 15,000 frames, ~0.2 GB);
the shorter takes are its first frames (``track.end``), whose gaps are the longer take's first gaps.

Each take runs ``retarget run configs/real.yaml`` (video swapped, ``track.init: auto``, ``track.end`` the
take's length, the ICT rig of ``build/ict-facekit``; track -> select -> decompose -> auto_pose -> apply with
curves, Live Link and glb) in a fresh child process into a fresh output folder. The child wraps
:func:`retarget_cli.run.pipeline.run_stage` to read its own peak RSS (``VmHWM`` of ``/proc/self/status``) at
the end of each stage and reset it (``/proc/self/clear_refs``, 5) at the start of the next, so each stage's
peak is its own (it includes what the process already held when the stage started: the modules, the
detector, memory an earlier stage freed but the allocator kept); the whole run's peak is the largest.
Printed: frames, wall time, peak RSS per stage and overall, gaps made and reported (start and length right),
and the whole run's peak against the first (shortest) take's.

``--from-landmarks FILE`` skips ``track`` (a 10-minute 1080p take is hours of tracking on a loaded 2-core
machine): the rows of *FILE* (a shorter run's ``landmarks.npz``) before its first gap, looped back and forth
to each length without gaps (one segment: the longest case for the solvers across frames), written into a
fresh output folder, then ``retarget run --from select``. The loop repeats the clip's few hundred shapes,
which ``select`` counts once: ``--jitter PX`` adds seeded noise so that every frame is a distinct candidate,
as in a real take. ``--until STAGE`` stops after that stage.

Target (#31): the 10-minute take's peak under 1 GB and within 10 % of the 1-minute take's.

Run: ``python bench/long_take.py [--minutes 1,5,10] [--rig build/ict-facekit/rig.yaml] [--keep]``.
Without ``../shared/realdata`` it prints a skip line and exits 0.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
DATA = ROOT.parent / "shared" / "realdata"
BUILD = ROOT / "build" / "long_take"
CLIP = "d12"
SIZE = (1920, 1080)
GAP_EVERY = 30.0     # seconds between gap starts
GAP_FIRST = 15.0     # seconds before the first gap
GAP_SECONDS = (1.0, 3.0)
STAGES = ("track", "select", "decompose", "pose", "auto_pose", "apply")


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def gaps_for(frames: int, fps: float) -> list[tuple[int, int]]:
    """``(start, frames)`` of the black gaps of a take of *frames* frames; a shorter take's are a prefix."""
    rng = np.random.default_rng(0)
    out = []
    for start in np.arange(int(GAP_FIRST * fps), frames - int(4 * fps), int(GAP_EVERY * fps)):
        out.append((int(start), int(round(rng.uniform(*GAP_SECONDS) * fps))))
    return out


def source_frames():
    import cv2

    cap = cv2.VideoCapture(str(DATA / "videos" / f"{CLIP}.mp4"))
    fps = cap.get(cv2.CAP_PROP_FPS) or 25.0
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(f)
    cap.release()
    return frames, fps


def upscale(frame, size=SIZE):
    """*frame* scaled uniformly to the height of *size* (bilinear), centred on black."""
    import cv2

    W, H = size
    h, w = frame.shape[:2]
    nw = min(W, int(round(w * H / h)))
    canvas = np.zeros((H, W, 3), np.uint8)
    x0 = (W - nw) // 2
    canvas[:, x0:x0 + nw] = cv2.resize(frame, (nw, H), interpolation=cv2.INTER_LINEAR)
    return canvas


def make_take(minutes: float) -> tuple[Path, float]:
    """The looped 1080p take of at least *minutes* (an existing longer one is reused), and its frame rate."""
    import cv2

    BUILD.mkdir(parents=True, exist_ok=True)
    have = sorted(BUILD.glob(f"{CLIP}-{SIZE[0]}x{SIZE[1]}-*min.mp4"),
                  key=lambda p: float(p.stem.rsplit("-", 1)[1][:-3]))
    for p in have:
        if float(p.stem.rsplit("-", 1)[1][:-3]) >= minutes:
            cap = cv2.VideoCapture(str(p))
            fps = cap.get(cv2.CAP_PROP_FPS)
            cap.release()
            return p, fps
    src, fps = source_frames()
    T = int(round(minutes * 60 * fps))
    gap_at = {s + k for s, n in gaps_for(T, fps) for k in range(n)}
    path = BUILD / f"{CLIP}-{SIZE[0]}x{SIZE[1]}-{minutes:g}min.mp4"
    tmp = path.with_name(f".{path.stem}.part.mp4")
    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, SIZE)
    black = np.zeros((SIZE[1], SIZE[0], 3), np.uint8)
    n = len(src)
    t0 = time.perf_counter()
    for t in range(T):
        i = t % (2 * n - 2)  # back and forth through the clip: the loop has no cut of its own
        i = i if i < n else 2 * n - 2 - i
        writer.write(black if t in gap_at else upscale(src[i]))
        if t % 1500 == 0:
            log(f"  writing {path.name}: frame {t}/{T} ({time.perf_counter() - t0:.0f} s)")
    writer.release()
    os.replace(tmp, path)
    log(f"wrote {path.relative_to(ROOT)} ({T} frames, {path.stat().st_size / 1e6:.0f} MB)")
    return path, fps


# The child: the documented path in this process, its peak RSS read and reset around each stage.
CHILD = r"""
import json, resource, sys, time
import retarget_cli.run.pipeline as P

def status(key):
    with open('/proc/self/status') as f:
        for line in f:
            if line.startswith(key + ':'):
                return int(line.split()[1]) / 1024.0
    return float('nan')

def reset_peak():
    try:
        with open('/proc/self/clear_refs', 'w') as f:
            f.write('5')
        return True
    except OSError:
        return False

stages = []
orig = P.run_stage

def run_stage(cfg, name, kw, *a, **k):
    before, resettable = status('VmRSS'), reset_peak()
    t = time.perf_counter()
    try:
        return orig(cfg, name, kw, *a, **k)
    finally:
        stages.append({'stage': name, 'rss_before_mb': before, 'peak_mb': status('VmHWM'),
                       'rss_after_mb': status('VmRSS'), 'seconds': time.perf_counter() - t,
                       'reset': resettable})

P.run_stage = run_stage
from retarget_cli.entry import main
sys.argv = ['retarget', '-q', 'run', *sys.argv[1:]]
rc = 0
try:
    main()
except SystemExit as e:
    rc = e.code or 0
print('LONGTAKE ' + json.dumps({'rc': rc, 'stages': stages,
      'ru_maxrss_mb': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}), file=sys.stderr)
sys.exit(rc)
"""


def tiled_landmarks(source: Path, T: int, path: Path, jitter: float = 0.0) -> None:
    """A take of *T* rows without gaps: the rows of *source* before its first gap, back and forth; with
    *jitter* (pixels), seeded Gaussian noise of that deviation added to its points and stabilized landmarks,
    so that every frame is a distinct shape (as in a real long take; a loop repeats the clip's few hundred)."""
    from retarget_cli.io.landmarks import load_landmarks, save_landmarks

    lm = load_landmarks(source)
    n = lm.n_frames
    if lm.found is not None and not lm.found.all():
        n = int(np.argmin(lm.found))
    idx = np.arange(T) % (2 * n - 2)
    idx = np.where(idx < n, idx, 2 * n - 2 - idx)
    meta = {k: v for k, v in lm.meta.items() if k not in ("gaps", "segments")}
    lm.meta = meta
    for key in ("points", "confidence", "head", "stabilized", "points_raw", "head_angles", "head_translation",
                "gaze", "gaze_valid"):
        v = getattr(lm, key, None)
        if v is not None:
            setattr(lm, key, v[idx])
    if jitter > 0:
        rng = np.random.default_rng(0)
        lm.points = (lm.points + rng.normal(0.0, jitter, lm.points.shape)).astype(lm.points.dtype)
        lm.stabilized = (lm.stabilized + rng.normal(0.0, jitter, lm.stabilized.shape)).astype(lm.stabilized.dtype)
    lm.frames, lm.times = np.arange(T, dtype=np.int64), np.arange(T) / lm.fps
    lm.found, lm.segment = None, None
    path.parent.mkdir(parents=True, exist_ok=True)
    save_landmarks(path, lm)


def run_take(video: Path, fps: float, minutes: float, args) -> dict:
    """``retarget run`` of ``--config`` on the first *minutes* of *video* in a child process; its figures.

    With ``--from-landmarks``, *video* is a landmarks file: tiled to the take's length without gaps
    (:func:`tiled_landmarks`) into the output folder, and the run starts at ``select``.
    """
    import yaml

    T = int(round(minutes * 60 * fps))
    work = BUILD / ("stages" if args.from_landmarks else "runs") / f"{minutes:g}min"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    raw = yaml.safe_load(args.config.read_text()) or {}
    cfg = dict(raw)
    cfg["output_dir"] = str(work / "run")
    cfg["track"] = {**raw.get("track", {}), "video": str(args.video_for_config or video), "init": "auto",
                    "start": 0, "end": T}
    cfg["auto_pose"] = {**raw.get("auto_pose", {}), "rig": str(args.rig.resolve())}
    (work / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    extra = []
    if args.from_landmarks:
        tiled_landmarks(args.from_landmarks, T, work / "run" / "landmarks.npz", args.jitter)
        extra = ["--from", "select"]
    if args.until:
        extra += ["--until", args.until]
    t = time.perf_counter()
    res = subprocess.run([sys.executable, "-c", CHILD, str(work / "config.yaml"), *extra], cwd=ROOT,
                         capture_output=True, text=True)
    secs = time.perf_counter() - t
    line = [ln for ln in res.stderr.splitlines() if ln.startswith("LONGTAKE ")]
    if res.returncode or not line:
        raise RuntimeError(f"long take {minutes:g} min failed:\n{res.stderr.strip()[-2000:]}")
    out = json.loads(line[-1][len("LONGTAKE "):])
    run = work / "run"
    with np.load(run / "landmarks.npz") as d:
        reported = json.loads(str(d["meta"])).get("gaps", [])
        tracked = len(d["points"])
    curves = sorted(run.rglob("curves.npz"))
    rows, finite = 0, True
    if curves:  # (none with --until before apply)
        with np.load(curves[0]) as d:
            rows = len(d["curves"])
            finite = bool(np.isfinite(d["curves"]).all())
    want = [] if args.from_landmarks else gaps_for(T, fps)
    got = [(int(g["start"]), int(g["frames"])) for g in reported if g.get("reason") != "cut"]
    out.update(minutes=minutes, frames=T, tracked=tracked, curve_rows=rows, finite=finite, seconds=secs,
               gaps=len(want), reported=len(got), all_reported=got == want,
               peak_mb=max(s["peak_mb"] for s in out["stages"]))
    if not args.keep:
        shutil.rmtree(run, ignore_errors=True)
    return out


def report(rows: list) -> str:
    first = rows[0]
    names = [s["stage"] for s in first["stages"]]
    lines = ["| take | frames | curve rows | gaps made / reported right | wall time | "
             + " | ".join(f"{n} peak" for n in names) + " | whole run peak | vs first |",
             "|---" * (7 + len(names)) + "|"]
    for r in rows:
        per = {s["stage"]: s["peak_mb"] for s in r["stages"]}
        cells = " | ".join(f"{per.get(n, float('nan')):.1f} MB" for n in names)
        growth = 100.0 * (r["peak_mb"] / first["peak_mb"] - 1.0)
        lines.append(f"| {r['minutes']:g} min | {r['frames']:,} | {r['curve_rows']:,}{'' if r['finite'] else ' NOT finite'}"
                     f" | {r['gaps']} / {r['reported']} ({'yes' if r['all_reported'] else 'NO'}) | "
                     f"{r['seconds']:.0f} s ({r['frames'] / r['seconds']:.1f} fps) | {cells} | "
                     f"{r['peak_mb']:.1f} MB | {growth:+.1f} % |")
    return "\n".join(lines)


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--minutes", default="1,5,10", help="take lengths in minutes, shortest first (default 1,5,10)")
    p.add_argument("--config", type=Path, default=ROOT / "configs" / "real.yaml")
    p.add_argument("--rig", type=Path, default=ROOT / "build" / "ict-facekit" / "rig.yaml",
                   help="the ICT rig.yaml (make build/ict-facekit/rig.yaml)")
    p.add_argument("--make-only", action="store_true", help="only write the take's video")
    p.add_argument("--keep", action="store_true", help="keep each run's output folder")
    p.add_argument("--json", type=Path, help="also write the figures to this JSON file")
    p.add_argument("--from-landmarks", type=Path,
                   help="skip track: a landmarks.npz (a shorter run's) tiled to each length without gaps, "
                        "then select .. apply")
    p.add_argument("--jitter", type=float, default=0.0,
                   help="with --from-landmarks: Gaussian noise (pixels, seeded) added to the tiled landmarks so "
                        "that every frame is distinct (default 0: the loop repeats the clip's frames)")
    p.add_argument("--until", choices=STAGES[1:], help="the last stage run (default: apply)")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    if not (DATA / "videos" / f"{CLIP}.mp4").is_file():
        print(f"SKIP bench/long_take.py: {DATA} not found (the shared real data)")
        return 0
    minutes = [float(m) for m in args.minutes.split(",") if m]
    args.video_for_config = None
    if args.from_landmarks:
        with np.load(args.from_landmarks) as d:
            fps = float(d["fps"])
        video, args.video_for_config = args.from_landmarks, DATA / "videos" / f"{CLIP}.mp4"
    else:
        video, fps = make_take(max(minutes))
    if args.make_only:
        return 0
    if not args.rig.is_file():
        print(f"SKIP bench/long_take.py: {args.rig} not found (make build/ict-facekit/rig.yaml)")
        return 0
    rows = []
    for m in minutes:
        rows.append(run_take(video, fps, m, args))
        if args.json:  # after each take: a long series stopped half way keeps what it measured
            args.json.write_text(json.dumps(rows, indent=1))
        log(f"{m:g} min: peak {rows[-1]['peak_mb']:.1f} MB, {rows[-1]['seconds']:.0f} s; "
            + ", ".join(f"{st['stage']} {st['peak_mb']:.0f} MB" for st in rows[-1]["stages"]))
    what = (f"{args.from_landmarks.name} looped without gaps"
            + (f", jitter {args.jitter:g} px" if args.jitter else "")
            + f", `retarget run {args.config.name} --from select" + (f" --until {args.until}`" if args.until else "`")
            if args.from_landmarks else f"{CLIP} at {SIZE[0]}x{SIZE[1]} looped, a 1-3 s black gap every 30 s; "
            f"`retarget run {args.config.name}` (video swapped, init auto)")
    print(f"Long take: {what}, in a fresh process; peak RSS per stage (VmHWM, reset at each stage's start):\n")
    print(report(rows))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
