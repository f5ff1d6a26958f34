"""Benchmark: real takes with gaps (issue 33): a face that leaves the picture and comes back costs nothing else.

Per shared clip (d3, d9, d12 of ``../shared/realdata/videos``), three variants are made with OpenCV in
``build/gaps`` (mp4v, the clip's size and frame rate), each as long as the clip:

- ``black``: 2 s of black frames from a third of the clip on (the frames replaced, so frame numbers match);
- ``slide``: from a third of the clip on, the picture slides sideways out of the frame in 0.5 s (black
  behind it), stays out 1 s and slides back in 0.5 s;
- ``cut``: from the middle on, the frames of another shared clip at the same frame numbers (d3 -> d9,
  d9 -> d3, d12 -> d3; as long as the shorter of the two; scaled uniformly to the first clip's frame size
  and centred on black where the sizes differ: d9 is 512x480).

Each variant and each clean clip runs the documented path (``configs/real.yaml`` with the video swapped and
``track.init: auto``: ``bench/peer.py``'s :func:`run_ours`, cached under ``build/gaps``). Checked and printed:
the run finishes with a row of curves for every frame (finite); the gaps ``track`` reported; the gap frames
follow ``apply.gaps`` (default ``ease``: the middle of a 2 s gap at the rest pose, all sliders 0); and on the
frames away from the changed ones (5 frames excluded each side), Pearson r of the character's mouth opening
and eye openings (the ICT landmark vertices posed at the curves, ``bench/peer.py``'s :func:`score`) against
the reference, beside the clean clip's r on the same frames (the cut's second part against the other clip's
clean run, framed as the cut shows it when the sizes differ: d9 letterboxed to 512x512 after d3; a measure
whose reference barely moves on those frames, std < ``bench/peer.py``'s FLAT, is marked flat and left out of
the worst difference: its r is noise, e.g. d3's mouth, closed from frame 97 to 182). The clean
runs are of the clip written through the same encoder as the variants (:func:`write_video`, mp4v), so the
frames away from the change are the same pixels in both: the variants are re-encoded, and re-encoding alone
moves the tracked landmarks (d12, frames 5-85: mouth r 0.78 from the original file, 0.89 from its mp4v copy,
same rest frame). Target: every difference within 0.03. Each part of a cut is also scored against the same
frames run as a take of their own (the shot alone, :func:`shot_alone`: its own rest pose, no cut), which says
what the cut itself costs, apart from what a shorter take holds (a shot with no rest frame of its own). The reference is MediaPipe Face Mesh 0.10.14
(``bench/reference``) where its venv can be made, else raw per-frame dlib (say which in the output).

``--long MINUTES`` (e.g. ``1,3``): also a synthetic long take per length: d12 scaled to 256x256 and looped,
with a gap (black, 1-3 s, seeded) every 30 s, tracked by ``retarget track`` in a child process; prints its
peak RSS (``resource.getrusage`` of the child), wall time, and whether every gap was reported.

Run: ``python bench/gaps.py [--videos d3,d9,d12] [--variants black,slide,cut] [--long 1,3] [--fresh]
[--reference auto|dlib]``.
Without ``../shared/realdata`` it prints a skip line and exits 0.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

from realrig.measures import MEDIAPIPE, MULTIPIE68  # noqa: E402

DATA = ROOT.parent / "shared" / "realdata"
BUILD = ROOT / "build" / "gaps"
VARIANTS = ("black", "slide", "cut")
CUT_TO = {"d3": "d9", "d9": "d3", "d12": "d3"}
MARGIN = 5          # frames excluded each side of the changed frames
TOLERANCE = 0.03    # |r(variant) - r(clean)| on the same frames
MEASURES = ("mouth", "eye_l", "eye_r")


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def read_video(path: Path) -> tuple[list, float]:
    import cv2

    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(f)
    fps = cap.get(cv2.CAP_PROP_FPS) or 30.0
    cap.release()
    return frames, fps


def write_video(path: Path, frames, fps: float) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    h, w = frames[0].shape[:2]
    tmp = path.with_name(path.stem + ".tmp" + path.suffix)
    vw = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    for f in frames:
        vw.write(f)
    vw.release()
    os.replace(tmp, path)


def fit(img, w: int, h: int):
    """*img* scaled uniformly to fit a *w* x *h* frame, centred on black (d9 is 512x480, d3 and d12 512x512)."""
    import cv2

    ih, iw = img.shape[:2]
    if (iw, ih) == (w, h):
        return img.copy()
    k = min(w / iw, h / ih)
    sw, sh = int(round(iw * k)), int(round(ih * k))
    out = np.zeros((h, w, 3), img.dtype)
    x, y = (w - sw) // 2, (h - sh) // 2
    out[y:y + sh, x:x + sw] = cv2.resize(img, (sw, sh), interpolation=cv2.INTER_AREA)
    return out


def fitted(other: str, clip: str) -> Path | None:
    """*other* whole, framed to *clip*'s size as the cut shows it (:func:`fit`); None when the sizes match."""
    frames, fps = read_video(DATA / "videos" / f"{other}.mp4")
    first, _ = read_video(DATA / "videos" / f"{clip}.mp4")
    h, w = first[0].shape[:2]
    if frames[0].shape[:2] == (h, w):
        return None
    path = BUILD / "videos" / f"{other}_fit{w}x{h}.mp4"
    if not path.is_file():
        write_video(path, [fit(f, w, h) for f in frames], fps)
    return path


def reencoded(clip: str) -> Path:
    """*clip* whole, written through :func:`write_video` as the variants are (made once): the clean run's video."""
    path = BUILD / "videos" / f"{clip}_mp4v.mp4"
    if not path.is_file():
        frames, fps = read_video(DATA / "videos" / f"{clip}.mp4")
        write_video(path, frames, fps)
    return path


def make_variant(clip: str, variant: str) -> tuple[Path, dict]:
    """The variant's video (made once) and what changed: ``changed`` (T,) bool, ``source`` per frame."""
    frames, fps = read_video(DATA / "videos" / f"{clip}.mp4")
    T = len(frames)
    src = [clip] * T
    changed = np.zeros(T, bool)
    out = [f.copy() for f in frames]
    g0 = T // 3
    if variant == "black":
        n = int(round(2 * fps))
        for i in range(g0, g0 + n):
            out[i][:] = 0
        changed[g0:g0 + n] = True
    elif variant == "slide":
        s, hold = int(round(0.5 * fps)), int(round(1 * fps))
        W = out[0].shape[1]
        shifts = list(np.linspace(0, W, s + 1)[1:]) + [W] * hold + list(np.linspace(W, 0, s + 1)[:-1])
        for k, dx in enumerate(shifts):
            i, dx = g0 + k, int(round(dx))
            img = np.zeros_like(frames[i])
            if dx < W:
                img[:, dx:] = frames[i][:, :W - dx]
            out[i] = img
        changed[g0:g0 + len(shifts)] = True
    elif variant == "cut":
        other, _ = read_video(DATA / "videos" / f"{CUT_TO[clip]}.mp4")
        T = min(T, len(other))
        out, src, changed = out[:T], src[:T], changed[:T]
        h = T // 2
        for i in range(h, T):
            out[i] = fit(other[i], out[0].shape[1], out[0].shape[0])
            src[i] = CUT_TO[clip]
        changed[h] = True  # the cut itself: the frames either side are excluded
    path = BUILD / "videos" / f"{clip}_{variant}.mp4"
    if not path.is_file():
        write_video(path, out, fps)
    return path, {"changed": changed, "source": np.array(src), "fps": fps}


def away(changed: np.ndarray, margin: int = MARGIN) -> np.ndarray:
    """Frames more than *margin* frames from any changed frame."""
    near = changed.copy()
    for d in range(1, margin + 1):
        near[d:] |= changed[:-d]
        near[:-d] |= changed[d:]
    return ~near


def reference_for(clip: str, kind: str) -> dict:
    """The clip's reference (MediaPipe Face Mesh, else raw dlib) as ``bench/peer.py`` scores against."""
    from peer import dlib_raw, measures

    video = DATA / "videos" / f"{clip}.mp4"
    if kind == "mediapipe":
        from reference import reference_landmarks

        ref, layout = reference_landmarks(video, log=log), MEDIAPIPE
    else:
        ref, layout = dlib_raw(video), MULTIPIE68
    return {"points": ref["points"], "found": np.asarray(ref["found"], bool), "layout": layout,
            "m": measures(ref["points"], layout)}


def reference_kind() -> str:
    try:
        from reference import ReferenceUnavailable, ensure_venv

        ensure_venv(log=log)
        return "mediapipe"
    except (ReferenceUnavailable, OSError) as exc:
        log(f"MediaPipe reference unavailable ({exc}); scoring against raw per-frame dlib")
        return "dlib"


def run(video: Path, T: int, ctx, work: Path, args) -> dict:
    from peer import run_ours

    out = run_ours(video, 0, T, ctx, work, args)
    lm = np.load(work / "run" / "landmarks.npz")
    out["found"] = lm["found"] if "found" in lm.files else np.ones(T, bool)
    out["gaps"] = json.loads(str(lm["meta"])).get("gaps", [])
    return out


def r_on(curves, ctx, ref: dict, frames: np.ndarray) -> dict:
    """Pearson r of each measure of the character posed at *curves* rows *frames* against *ref* there."""
    from peer import score

    pts = ctx.landmarks_2d(curves[frames])
    row = score(pts, MULTIPIE68, {"ref": ref}, frames, None)["ref"]
    return {m: row["r"][m] for m in MEASURES}


def flat_on(ref: dict, frames: np.ndarray) -> list[str]:
    """The measures whose reference series barely moves on *frames* (``bench/peer.py``'s FLAT: r there is noise)."""
    from peer import FLAT

    found = ref["found"][frames]
    return [m for m in MEASURES if not np.nanstd(ref["m"][m][frames][found]) >= FLAT]


def shot_alone(clip: str, part: str, info: dict, ctx, args) -> np.ndarray:
    """The curves of one shot of a cut run as a take of its own: *part*'s frames of the clean video (the other clip
    framed as the cut shows it), from the shot's first frame to its last, as rows of the whole cut (0 elsewhere)."""
    from peer import run_ours

    rows = np.flatnonzero(info["source"] == part)
    start, end = int(rows[0]), int(rows[-1]) + 1
    video = reencoded(clip) if part == clip else (fitted(part, clip) or reencoded(part))
    out = run_ours(video, start, end, ctx, BUILD / "runs" / f"{clip}_cut_{part}_alone", args)
    C = np.zeros((len(info["source"]), out["curves"].shape[1]))
    C[start:end] = out["curves"]
    return C


def check_variant(clip: str, variant: str, ctx, refs: dict, clean: dict, args) -> dict:
    video, info = make_variant(clip, variant)
    T = len(info["changed"])
    t = time.perf_counter()
    res = run(video, T, ctx, BUILD / "runs" / f"{clip}_{variant}", args)
    secs = time.perf_counter() - t
    C = res["curves"]
    complete = C.shape[0] == T and bool(np.isfinite(C).all())
    ok_frames = away(info["changed"])
    row = {"clip": clip, "variant": variant, "frames": T, "complete": complete, "gaps": res["gaps"],
           "found": int(res["found"].sum()), "seconds": round(float(res.get("seconds", secs)), 1), "r": {}}
    # the gap frames follow apply.gaps (ease): the middle of each gap longer than 2 eases is at rest
    mids = [g["start"] + g["frames"] // 2 for g in res["gaps"] if g["frames"] >= 2 * args.ease_frames + 2]
    row["rest_in_gaps"] = bool(all(np.abs(C[m]).max() < 1e-9 for m in mids)) if mids else None
    for part in sorted(set(info["source"].tolist())):
        sel = np.flatnonzero(ok_frames & (info["source"] == part))
        if sel.size < 10:
            continue
        r_var = r_on(C, ctx, refs[part], sel)
        r_cln = r_on(clean.get(f"{part}@{clip}", clean[part])["curves"], ctx, refs[part], sel)
        row["r"][part] = {"n": int(sel.size), "variant": r_var, "clean": r_cln, "flat": flat_on(refs[part], sel),
                          "diff": {m: r_var[m] - r_cln[m] for m in MEASURES}}
        if variant == "cut":  # the shot's own frames as a take: what the cut costs beyond the shot's content
            r_alone = r_on(shot_alone(clip, part, info, ctx, args), ctx, refs[part], sel)
            row["r"][part].update(alone=r_alone, diff_alone={m: r_var[m] - r_alone[m] for m in MEASURES})
    return row


def fmt_alone(row: dict) -> list[str]:
    """The cut's parts against each shot run as a take of its own (:func:`shot_alone`)."""
    lines = []
    for part, s in row["r"].items():
        if "alone" not in s:
            continue
        moving = [m for m in MEASURES if m not in s["flat"]]
        worst = min((s["diff_alone"][m] for m in moving), default=0.0)
        cells = " | ".join(f"{s['variant'][m]:.3f} / {s['alone'][m]:.3f}" + (" (flat)" if m in s["flat"] else "")
                           for m in MEASURES)
        lines.append(f"| {row['clip']} | {part} ({s['n']}) | {cells} | {worst:+.3f} "
                     f"{'ok' if worst >= -TOLERANCE else 'MISS'} |")
    return lines


def fmt_row(row: dict) -> list[str]:
    lines = []
    gaps = "; ".join(f"{g['reason']}@{g['start']}+{g['frames']}" for g in row["gaps"]) or "none"
    for part, s in row["r"].items():
        moving = [m for m in MEASURES if m not in s["flat"]]
        worst = max((abs(s["diff"][m]) for m in moving), default=0.0)
        cells = " | ".join(f"{s['variant'][m]:.3f} / {s['clean'][m]:.3f}" + (" (flat)" if m in s["flat"] else "")
                           for m in MEASURES)
        lines.append(f"| {row['clip']} | {row['variant']} | {part} ({s['n']}) | {row['frames']} "
                     f"{'yes' if row['complete'] else 'NO'} | {gaps} | {row['rest_in_gaps']} | {cells} | "
                     f"{worst:.3f} {'ok' if worst <= TOLERANCE else 'MISS'} |")
    return lines


# --------------------------------------------------------------------------- the long take


def long_take(minutes: float, args) -> dict:
    """A synthetic long take (d12 at 256x256, looped, a 1-3 s black gap every 30 s) through ``retarget track``."""
    import cv2

    frames, fps = read_video(DATA / "videos" / "d12.mp4")
    small = [cv2.resize(f, (256, 256), interpolation=cv2.INTER_AREA) for f in frames]
    T = int(round(minutes * 60 * fps))
    rng = np.random.default_rng(0)
    gaps = []
    for start in np.arange(int(15 * fps), T - int(4 * fps), int(30 * fps)):
        gaps.append((int(start), int(round(rng.uniform(1, 3) * fps))))
    path = BUILD / "videos" / f"long_{minutes:g}min.mp4"
    if not path.is_file():
        import cv2 as _cv

        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.stem + ".tmp.mp4")
        vw = _cv.VideoWriter(str(tmp), _cv.VideoWriter_fourcc(*"mp4v"), fps, (256, 256))
        black = np.zeros_like(small[0])
        gap_at = {s + k for s, n in gaps for k in range(n)}
        n_src = len(small)
        for t in range(T):
            # ping-pong through the clip so the loop has no cut of its own
            i = t % (2 * n_src - 2)
            i = i if i < n_src else 2 * n_src - 2 - i
            vw.write(black if t in gap_at else small[i])
        vw.release()
        os.replace(tmp, path)
    out = BUILD / "long" / f"long_{minutes:g}min.npz"
    out.parent.mkdir(parents=True, exist_ok=True)
    code = ("import resource, sys; from retarget_cli.entry import main; "
            "sys.argv=['retarget','-q','track',sys.argv[1],'-o',sys.argv[2]]; "
            "rc=0\ntry:\n main()\nexcept SystemExit as e:\n rc=e.code or 0\n"
            "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr); sys.exit(rc)")
    t = time.perf_counter()
    res = subprocess.run([sys.executable, "-c", code, str(path), str(out)], cwd=ROOT, capture_output=True, text=True)
    secs = time.perf_counter() - t
    if res.returncode:
        raise RuntimeError(f"long take {minutes} min: {res.stderr.strip()[-500:]}")
    rss_mb = int(res.stderr.strip().splitlines()[-1]) / 1024
    d = np.load(out)
    reported = json.loads(str(d["meta"])).get("gaps", [])
    want = [(s, n) for s, n in gaps]
    got = [(g["start"], g["frames"]) for g in reported if g["reason"] != "cut"]
    return {"minutes": minutes, "frames": T, "gaps": len(gaps), "reported": len(got),
            "all_reported": got == want, "peak_rss_mb": round(rss_mb, 1), "seconds": round(secs, 1),
            "fps": round(T / secs, 1)}


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--videos", default="d3,d9,d12")
    p.add_argument("--variants", default=",".join(VARIANTS))
    p.add_argument("--config", type=Path, default=ROOT / "configs" / "real.yaml")
    p.add_argument("--long", default="", help="minutes of the synthetic long takes, e.g. 1,3 (default: none)")
    p.add_argument("--fresh", action="store_true", help="rerun the pipeline (the variants' videos are kept)")
    p.add_argument("--reference", choices=("auto", "dlib"), default="auto",
                   help="auto: MediaPipe Face Mesh where its venv can be made, else raw dlib; dlib: raw dlib")
    p.add_argument("--data", type=Path, default=DATA)
    args = p.parse_args(argv)
    args.ease_frames = 12  # apply.gap_ease 0.4 s at 30 fps
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    if not (args.data / "videos").is_dir():
        print(f"SKIP bench/gaps.py: {args.data} not found (the shared real data)")
        return 0
    from real_rig import load_rig

    clips = [c for c in args.videos.split(",") if c]
    variants = [v for v in args.variants.split(",") if v]
    rows = []
    if clips and variants:
        ctx = load_rig(args.data / "ict-facekit" / "ict-facekit-rig.tar.xz")
        args.rig_yaml = ROOT / "build" / "real_rig" / "ict-facekit" / "rig.yaml"
        kind = reference_kind() if args.reference == "auto" else "dlib"
        needed = sorted(set(clips) | ({CUT_TO[c] for c in clips} if "cut" in variants else set()))
        refs = {c: reference_for(c, kind) for c in needed}
        clean = {}
        for c in needed:
            path = reencoded(c)  # the same encoder as the variants: the same pixels away from the change
            n = len(read_video(path)[0])
            clean[c] = run(path, n, ctx, BUILD / "runs" / f"{path.stem}_clean", args)
            log(f"{c}: clean run ({path.name}), {n} frames")
        for c in clips if "cut" in variants else ():  # the other clip framed as in the cut, where sizes differ
            path = fitted(CUT_TO[c], c)
            if path is not None:
                n = len(read_video(path)[0])
                clean[f"{CUT_TO[c]}@{c}"] = run(path, n, ctx, BUILD / "runs" / f"{path.stem}_clean", args)
                log(f"{CUT_TO[c]} framed as {c}: clean run, {n} frames")
        for c in clips:
            for v in variants:
                rows.append(check_variant(c, v, ctx, refs, clean, args))
                log(f"{c} {v}: done")
        print(f"Gaps on the shared clips (documented path, {args.config.name}, init auto; apply.gaps ease); r against "
              f"{'MediaPipe Face Mesh 0.10.14' if kind == 'mediapipe' else 'raw per-frame dlib'} on the frames "
              f"{MARGIN}+ frames away from the changed ones: variant / clean, mouth | eye L | eye R.\n")
        print("| clip | variant | frames scored (from) | frames, curves for all | gaps reported | gap middles at rest "
              "| mouth | eye L | eye R | worst diff |")
        print("|---|---|---|---|---|---|---|---|---|---|")
        for row in rows:
            print("\n".join(fmt_row(row)))
        alone = [line for row in rows for line in fmt_alone(row)]
        if alone:
            print("\nEach part of a cut against the same frames run as a take of their own (the shot alone: its own "
                  "rest pose, no cut), variant / shot alone, and the largest loss:\n")
            print("| clip | part (frames scored) | mouth | eye L | eye R | largest loss |")
            print("|---|---|---|---|---|---|")
            print("\n".join(alone))
    for m in [float(x) for x in args.long.split(",") if x]:
        r = long_take(m, args)
        print(f"\nlong take {m:g} min ({r['frames']} frames, 256x256): {r['gaps']} gaps made, {r['reported']} "
              f"reported ({'all, at the right frames' if r['all_reported'] else 'NOT all'}); track peak RSS "
              f"{r['peak_rss_mb']} MB; {r['seconds']} s ({r['fps']} fps)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
