"""Benchmark: ``retarget``'s documented path against the free peer on real footage, side by side (issue 27).

The peer is what a user would pick instead: MediaPipe Face Landmarker's 52 ARKit-named blendshape scores
(``../shared/realdata/peers/face_landmarker.task``, Tasks API, ``RunningMode.VIDEO``; run by
``bench/reference/mp_blendshapes.py`` in the MediaPipe venv of ``bench/reference``) mapped by name onto
the ICT FaceKit's sliders with the rules of the Live Link export (``canonical_name``: case, ``_L``/``Left``;
then ``rig.yaml``'s ``names:``, e.g. ``browInnerUp`` drives ``browInnerUp_L`` and ``browInnerUp_R``).
Sliders no ARKit name reaches (``cheekRaiser_*``, ``PupilDilate_*``) stay 0; a frame where the peer finds
no face holds the last found scores. MediaPipe's sides are the subject's, as ARKit's and the ICT rig's
(checked on d3: ``eyeBlinkLeft - eyeBlinkRight`` follows the image-right eye closing, r 0.86 against the
Face Mesh lid gaps; ``eyeBlink_L`` closes the ICT character's image-right eye), so no side is swapped.

Per clip (d3, d9, d12 of ``../shared/realdata/videos``) and per *start*:

- ``0``: the clip as it is, from frame 0;
- ``smile``, ``frown``, ``open``: started where the actor is not at rest. The start is chosen by the
  MediaPipe Face Mesh reference over the whole clip, after a 5-frame running median of each measure:
  the largest mouth width (``smile``: mouth corners / outer eye corners), the lowest brow height
  (``frown``: brows to eye corners / inter-ocular distance) and the largest mouth opening (``open``:
  inner-lip gap / mouth width), among the frames with a face that leave at least ``--frames`` frames
  (default 60) before the clip's end and lie more than 15 frames from the starts chosen before it, in
  the order 0, smile, frown, open (d3's widest smile is also a wide-open mouth).

Each start runs from its frame to the clip's end, or ``--frames`` frames. Systems:

- ``ours``: the documented path, ``configs/real.yaml`` (``--config``) with only ``track.video``,
  ``track.start``/``end`` and ``track.init: auto`` changed (the frame-0 ``.pts`` does not fit other
  starts; ``auto`` is used at start 0 too, so that every start runs the same way) and the rig path
  pointed at the unpacked rig; ``retarget run``, then its ``frames/curves.npz``. fps = frames / wall
  time of the whole ``retarget run`` (decode, detection, tracking, select, decompose, auto-pose, apply,
  process start-up and rig loading included);
- ``peer``: the peer from the same start frame (a fresh landmarker; frames before the start are decoded,
  not shown to it); fps = frames / wall time of its own loop (decode + ``detect_for_video``; model
  loading excluded);
- ``tracker`` (r only): our tracked 68 points themselves (the run's ``landmarks.npz``), the ceiling of
  what the rig stage can keep.

The rig's 68 landmark vertices (``rig.yaml`` ``landmarks:``) are posed at each system's curves and
projected frontally (``bench/real_rig.py``'s ``RigContext``), then scored against two references: MediaPipe
Face Mesh 0.10.14 (``bench/reference``) and raw per-frame dlib 68 points (HOG detector, upsampled once
when no face is found at full size, the largest face, the ``face_recognition_models`` 68-point predictor;
no tracking, no filter; cached). Frames where a reference finds no face are left out of its scores.

Measures (``bench/realrig/measures.py``, plus mouth width here):

- r mouth, eye L, eye R, brow, width: Pearson r over frames of inner-lip gap / mouth width, lid gap /
  eye width (eye L = the image's left eye), brow height, mouth width / inter-ocular distance;
- lip contact: among the frames where the reference sees the lips closed (inner-lip gap < 0.02 of the
  mouth width), the fraction where the character's are too: its inner-lip gap / mouth width within
  0.02 of the rig's own rest value (0.016), either side: lips that cross (a negative gap, which the
  ICT lips reach at 0.1-0.45 of the mouth width under mouthPress + mouthShrugLower + mouthRoll*) are
  not closed lips; the table also counts those frames where the character's lips are parted (gap above
  the band) and crossed (below it);
- eye contact: the same per eye (frames x 2 eyes pooled): the reference's lid gap < 0.05 of the eye
  width (closed lids are at about 0 for MediaPipe, the open eye at 0.2-0.35; dlib rarely goes below
  0.05), the character's lid gap / eye width within 0.05 of the rig's with ``eyeBlink_L`` =
  ``eyeBlink_R`` = 1 (0.013). 0.05 of an eye width is about 0.015 of the inter-ocular distance, as
  0.02 of a mouth width is 0.011;
- jitter: the character's mean landmark acceleration ``|x[t+1] - 2 x[t] + x[t-1]|`` over the 68
  projected points and the frames, divided by its inter-ocular distance (x 1000 in the table);
- saturated: the fraction of frames with a slider at 1 (>= 0.99);
- fps as above.

Prints a markdown table per reference (rows clip x start x system, then a mean row per system).
``--png DIR``: per clip, ``<clip>.png`` with one row per start: at the start frame and at the run's
frame where the actor is nearest rest (lips closed, eyes open, the other MediaPipe measures nearest their
medians over such frames; :func:`rest_like_frame`), the video frame,
our character and the peer's character (the ICT mesh posed at the curves, the project's software
rasteriser, framed as in ``bench/real_rig.py --png``).

Caches under ``build/peer`` keyed by the video, the start/end, the config, the model and the sources of
``retarget_cli`` (``--fresh`` reruns both systems, not the references). Without ``../shared/realdata``
it prints a skip line and exits 0.

Run: ``python bench/peer.py [--videos d3,d9,d12] [--frames N] [--starts 0,smile,frown,open] [--png DIR]``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
import warnings
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

from realrig.measures import MEDIAPIPE, MULTIPIE68, distance, face_measures, pearson  # noqa: E402

DATA = ROOT.parent / "shared" / "realdata"
BUILD = ROOT / "build" / "peer"
RUNNER = HERE / "reference" / "mp_blendshapes.py"
STARTS = ("0", "smile", "frown", "open")
SYSTEMS = ("ours", "peer")
R_MEASURES = ("mouth", "eye_l", "eye_r", "brow", "width")
LIP_CLOSED = 0.02   # inner-lip gap / mouth width
EYE_CLOSED = 0.05   # lid gap / eye width
MIN_FRAMES = 60     # a non-rest start leaves at least this many frames (without --frames)
SMOOTH = 5          # running median (frames) before the start rules' argmax/argmin
APART = 15          # a start is at least this many frames from the starts chosen before it
FLAT = 0.01         # a reference series with a smaller standard deviation barely moves: its r is noise
SATURATED = 0.99    # a slider at or above this is saturated


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- retarget_cli, in one place


def retarget_api():
    """Every ``retarget_cli`` name this benchmark imports (``bench/real_rig.py``'s ``load_rig`` loads the rig)."""
    from types import SimpleNamespace

    from retarget_cli.io.livelink import ARKIT_SHAPES, arkit_mapping, canonical_name, check_names_mapping
    from retarget_cli.methods.render import Camera, MeshRenderer, View
    from retarget_cli.methods.tracking.detect import detector_installed, predictor_model_path

    return SimpleNamespace(ARKIT_SHAPES=ARKIT_SHAPES, arkit_mapping=arkit_mapping, canonical_name=canonical_name,
                           check_names_mapping=check_names_mapping, Camera=Camera, MeshRenderer=MeshRenderer, View=View,
                           detector_installed=detector_installed, predictor_model_path=predictor_model_path)


# --------------------------------------------------------------------------- helpers


def sha_text(*parts) -> str:
    h = hashlib.sha256()
    for p in parts:
        h.update(p if isinstance(p, bytes) else str(p).encode())
        h.update(b"\0")
    return h.hexdigest()


def running_median(x, k: int = SMOOTH) -> np.ndarray:
    """Centred running median of *x* (T,) over *k* frames (NaN-aware; edges use what there is)."""
    x = np.asarray(x, np.float64)
    h = k // 2
    pad = np.concatenate([np.full(h, np.nan), x, np.full(h, np.nan)])
    win = np.lib.stride_tricks.sliding_window_view(pad, k)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows give NaN
        return np.nanmedian(win, axis=1)


def mouth_width(points, layout) -> np.ndarray:
    """Mouth width: outer mouth corners / outer eye corners, (T,)."""
    return distance(points, *layout.mouth_corners) / distance(points, layout.eye_l[2], layout.eye_r[3])


def measures(points, layout) -> dict:
    """``face_measures`` plus ``width`` (:func:`mouth_width`)."""
    out = face_measures(points, layout)
    out["width"] = mouth_width(points, layout)
    return out


def jitter(points) -> float:
    """Mean |second difference| of the (T, 68, 2) points over points and frames, / mean inter-ocular distance."""
    p = np.asarray(points, np.float64)
    if len(p) < 3:
        return float("nan")
    acc = np.linalg.norm(p[2:] - 2 * p[1:-1] + p[:-2], axis=2).mean()
    iod = distance(p, MULTIPIE68.eye_l[2], MULTIPIE68.eye_r[3]).mean()
    return float(acc / iod)


# --------------------------------------------------------------------------- references


def dlib_raw(video: Path) -> dict:
    """Raw per-frame dlib 68 points of every frame of *video* (no tracking, no filter), cached.

    Returns ``points`` (T, 68, 2) float64 pixels (NaN where no face) and ``found`` (T,) bool.
    """
    import cv2
    import dlib
    from reference import sha256_file

    out = BUILD / "reference" / f"dlib-{video.stem}-{sha256_file(video)[:12]}.npz"
    if out.is_file():
        with np.load(out) as d:
            return {"points": d["points"], "found": d["found"]}
    detector = dlib.get_frontal_face_detector()
    predictor = dlib.shape_predictor(str(retarget_api().predictor_model_path()))
    cap = cv2.VideoCapture(str(video))
    pts, found = [], []
    t = time.perf_counter()
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        rects = detector(gray, 0) or detector(gray, 1)
        if rects:
            r = max(rects, key=lambda q: q.width() * q.height())
            pts.append(np.array([[p.x, p.y] for p in predictor(gray, r).parts()], np.float64))
        else:
            pts.append(np.full((68, 2), np.nan))
        found.append(bool(rects))
    cap.release()
    res = {"points": np.stack(pts), "found": np.array(found, bool)}
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, **res)
    os.replace(tmp, out)
    log(f"{video.stem}: raw dlib on {len(found)} frames ({int(res['found'].sum())} with a face) in "
        f"{time.perf_counter() - t:.0f} s -> {out.relative_to(ROOT)}")
    return res


def references(video: Path) -> dict:
    """Both references for the whole clip: name -> dict(points, found, layout, m (measures))."""
    from reference import reference_landmarks

    mp = reference_landmarks(video, log=log)
    dl = dlib_raw(video)
    out = {}
    for name, ref, layout in (("mediapipe", mp, MEDIAPIPE), ("dlib", dl, MULTIPIE68)):
        out[name] = {"points": ref["points"], "found": np.asarray(ref["found"], bool), "layout": layout,
                     "m": measures(ref["points"], layout)}
    return out


def choose_starts(ref: dict, n_video: int, frames: int | None, wanted) -> dict:
    """Start frame per label (see the module docstring), from the MediaPipe reference.

    Labels are taken in :data:`STARTS` order; each rule's frame is searched outside :data:`APART` frames of
    the starts already chosen, so that the starts differ (d3's widest smile is also a wide-open mouth).
    """
    m, found = ref["m"], ref["found"]
    last = n_video - (frames or MIN_FRAMES)
    ok = found & (np.arange(n_video) <= max(last, 0))
    rules = {"smile": (m["width"], np.nanargmax), "frown": (m["brow"], np.nanargmin),
             "open": (m["mouth"], np.nanargmax)}
    picks = {}
    for label in (s for s in STARTS if s in wanted):
        if label == "0":
            picks[label] = 0
            continue
        free = ok.copy()
        for f in picks.values():
            free[max(0, f - APART):f + APART + 1] = False
        if not free.any():
            log(f"start {label}: no frame left {APART} frames away from {sorted(picks.values())}; not run")
            continue
        series, pick = rules[label]
        picks[label] = int(pick(np.where(free, running_median(series), np.nan)))
    return picks


# --------------------------------------------------------------------------- the two systems


def run_ours(video: Path, start: int, end: int, ctx, work: Path, args, neutral: int | None = None) -> dict:
    """The documented path on frames [start, end): ``retarget run`` of ``--config`` with video/start/end/init swapped.

    *neutral*: a video frame set as ``select.neutral_frame`` (``--neutral reference``; decompose and auto_pose
    follow keys.json), else the config's. Returns ``curves`` (T, E) in the rig's slider order, ``frames`` (T,)
    video frames, ``points`` (T, 68, 2) the tracked landmarks, ``neutral`` the video frame the run used as
    neutral (-1 when keys.json records none), ``seconds`` (wall time of ``retarget run``).
    """
    import yaml
    from real_rig import _absolutize

    cache = work / "ours.npz"
    if cache.is_file() and not args.fresh:
        with np.load(cache) as d:
            return {k: d[k] for k in d.files}
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    raw = yaml.safe_load(args.config.read_text()) or {}
    cfg = {k: _absolutize(v, args.config.parent) if k != "output_dir" else v for k, v in raw.items()}
    cfg["output_dir"] = str(work / "run")
    cfg.setdefault("track", {}).update(video=str(video), init="auto", start=int(start), end=int(end))
    if isinstance(cfg.get("auto_pose"), dict):
        cfg["auto_pose"]["rig"] = str(args.rig_yaml)
    if neutral is not None:
        cfg.setdefault("select", {})["neutral_frame"] = int(neutral)  # a source frame number, as keys.json records it
        for stage in ("decompose", "auto_pose"):
            if isinstance(cfg.get(stage), dict):
                cfg[stage]["neutral_frame"] = "auto"
    (work / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    cmd = [sys.executable, "-m", "retarget_cli", "-q", "run", str(work / "config.yaml")]
    t = time.perf_counter()
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    secs = time.perf_counter() - t
    if res.returncode:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{res.stderr.strip()}")
    out = {"seconds": np.float64(secs), **_read_run(work / "run", ctx, start, end)}
    np.savez(cache, **out)
    return out


def _read_run(run: Path, ctx, start: int, end: int) -> dict:
    """``curves.npz`` (rows = the take's frames, 0-based) and ``landmarks.npz`` (video frames) of one run."""
    found = sorted(run.rglob("curves.npz"))
    if not found:
        raise RuntimeError(f"{run}: the run wrote no curves.npz")
    with np.load(found[0]) as d:
        names, C = [str(n) for n in d["names"]], np.asarray(d["curves"], np.float64)
    with np.load(run / "landmarks.npz") as d:
        frames = np.asarray(d["frames"], np.int64) if "frames" in d.files else start + np.arange(len(d["points"]))
        points = np.asarray(d["points"], np.float64)
    rec = json.loads((run / "keys.json").read_text()).get("neutral") if (run / "keys.json").is_file() else None
    neutral = int(rec["frame"]) if isinstance(rec, dict) else -1  # a source (video) frame number already
    if len(C) != len(frames) or not np.array_equal(frames, np.arange(start, end)):
        raise RuntimeError(f"{run}: {len(C)} curve rows for tracked frames {frames[0]}-{frames[-1]} "
                           f"({len(frames)}), expected {start}-{end - 1}")
    out = np.zeros((len(C), len(ctx.names)))
    for j, n in enumerate(names):
        if n not in ctx.rig.index:
            raise RuntimeError(f"{found[0]}: slider {n!r} is not in the rig")
        out[:, ctx.rig.index[n]] = C[:, j]
    return {"curves": out, "frames": frames, "points": points, "neutral": np.int64(neutral)}


def run_peer(video: Path, start: int, end: int, path: Path, args) -> dict:
    """The peer's raw output on frames [start, end) (``bench/reference/mp_blendshapes.py``), cached at *path*."""
    from reference import venv_python

    if not path.is_file() or args.fresh:
        cmd = [str(venv_python()), str(RUNNER), str(video), str(args.model), str(path), "--start", str(start),
               "--end", str(end)]
        res = subprocess.run(cmd, capture_output=True, text=True)
        if res.returncode:
            raise RuntimeError(f"{' '.join(cmd)} failed:\n{res.stderr.strip()[-2000:]}")
    with np.load(path) as d:
        out = {k: d[k] for k in d.files}
    if not np.array_equal(out["frames"], np.arange(start, end)):
        raise RuntimeError(f"{path}: frames {out['frames'][0]}-{out['frames'][-1]}, expected {start}-{end - 1}")
    return out


def peer_mapping(ctx, rig_yaml: Path, peer_names) -> tuple[dict, list]:
    """Peer score column -> rig slider indices, by the Live Link export's rules; and the unmapped peer names."""
    import yaml

    api = retarget_api()
    spec = yaml.safe_load(rig_yaml.read_text()) or {}
    names = api.check_names_mapping(spec.get("names"), ctx.names, f"{rig_yaml}: names")
    columns = api.arkit_mapping(ctx.names, names)            # ARKit column -> slider indices
    by_canon = {api.canonical_name(a): a for a in api.ARKIT_SHAPES}
    mapping, unmapped = {}, []
    for j, n in enumerate(peer_names):
        col = by_canon.get(api.canonical_name(str(n)))
        if col is None or col not in columns:
            unmapped.append(str(n))
            continue
        mapping[j] = columns[col]
    return mapping, unmapped


def peer_curves(peer: dict, mapping: dict, n_sliders: int) -> np.ndarray:
    """The peer's scores as rig curves (T, E): each mapped slider takes its column's score; lost frames hold."""
    S = np.asarray(peer["scores"], np.float64).copy()
    ok = np.asarray(peer["found"], bool) & np.all(np.isfinite(S), axis=1)
    if not ok.any():
        raise RuntimeError("the peer found no face")
    idx = np.where(ok, np.arange(len(S)), -1)
    idx = np.maximum.accumulate(idx)
    idx[idx < 0] = int(np.argmax(ok))
    S = S[idx]
    C = np.zeros((len(S), n_sliders))
    for j, sliders in mapping.items():
        C[:, sliders] = S[:, [j]]
    return C


# --------------------------------------------------------------------------- scores


def rig_constants(ctx) -> dict:
    """The rig's own rest measures and its eye measures with both eyes blinked (eyeBlink_L = eyeBlink_R = 1)."""
    w0 = np.zeros((1, len(ctx.names)))
    blink = w0.copy()
    for n in ("eyeBlink_L", "eyeBlink_R"):
        blink[0, ctx.rig.index[n]] = 1.0
    return {"rest": measures(ctx.landmarks_2d(w0), MULTIPIE68), "blink": measures(ctx.landmarks_2d(blink), MULTIPIE68)}


def contact(ref_m: dict, found, char_m: dict, rig: dict) -> dict:
    """Lip and lid contact counts over the reference-closed frames (eye-frames for the lids).

    ``<c>_n``: reference-closed; ``<c>_k``: the character's gap within the tolerance of the rig's closed
    gap; ``<c>_open``: above it (parted); ``<c>_cross``: below it (crossed), for ``c`` in ``lip``, ``eye``.
    """
    out = {}
    pairs = {"lip": [("mouth", rig["rest"]["mouth"][0], LIP_CLOSED)],
             "eye": [(e, rig["blink"][e][0], EYE_CLOSED) for e in ("eye_l", "eye_r")]}
    for c, items in pairs.items():
        n = k = above = below = 0
        for m, closed, tol in items:
            ref = found & (ref_m[m] < tol)
            d = char_m[m][ref] - closed
            n += int(ref.sum())
            k += int((np.abs(d) <= tol).sum())
            above += int((d > tol).sum())
            below += int((d < -tol).sum())
        out.update({f"{c}_n": n, f"{c}_k": k, f"{c}_open": above, f"{c}_cross": below})
    return out


def score(points, layout, refs: dict, frames, rig: dict | None) -> dict:
    """Per reference: r of every measure (and contact counts when *rig* is given) of *points* (T, L, 2)."""
    m = measures(points, layout)
    out = {}
    for name, ref in refs.items():
        found = ref["found"][frames]
        ref_m = {k: v[frames] for k, v in ref["m"].items()}
        row = {"r": {k: pearson(m[k], ref_m[k], found) for k in R_MEASURES}, "n": int(found.sum()),
               "flat": [k for k in R_MEASURES if not np.nanstd(ref_m[k][found]) >= FLAT]}
        if rig is not None:
            row.update(contact(ref_m, found, m, rig))
        out[name] = row
    return out


def rest_like_frame(ref: dict, frames) -> int:
    """The frame of *frames* where the actor is nearest rest, by the MediaPipe reference.

    Among the frames with the lips closed and both eyes open (the contact thresholds), the one whose mouth
    width, brow height and eye openings are nearest (z-scored) their medians over the clip's such frames;
    without any, the frame of *frames* with the smallest mouth opening.
    """
    m, found = ref["m"], ref["found"]
    calm = found & (m["mouth"] < LIP_CLOSED) & (m["eye_l"] >= EYE_CLOSED) & (m["eye_r"] >= EYE_CLOSED)
    if not calm[frames].any():
        return int(frames[int(np.nanargmin(np.where(found[frames], m["mouth"][frames], np.nan)))])
    z = np.zeros(len(frames))
    for k in ("width", "brow", "eye_l", "eye_r"):
        x = m[k][calm]
        z += ((m[k][frames] - np.median(x)) / (np.std(x) + 1e-9)) ** 2
    return int(frames[int(np.argmin(np.where(calm[frames], z, np.inf)))])


# --------------------------------------------------------------------------- per clip


def run_clip(clip: str, ctx, rig: dict, args) -> dict:
    """Both systems on every start of *clip*: rows of scores, plus what the pictures need."""
    from real_rig import code_tag
    from reference import sha256_file

    video = args.data / "videos" / f"{clip}.mp4"
    refs = references(video)
    n = len(refs["mediapipe"]["found"])
    starts = choose_starts(refs["mediapipe"], n, args.frames, args.starts)
    log(f"{clip}: {n} frames; starts {', '.join(f'{k} {v}' for k, v in starts.items())}")
    cfg_key = sha_text(args.config.read_bytes(), args.rig_yaml.read_bytes())[:8]
    peer_key = sha_text(sha256_file(args.model), RUNNER.read_bytes())[:8]
    base = BUILD / f"{clip}-{sha256_file(video)[:12]}"
    out = {"clip": clip, "video": video, "n": n, "rows": [], "runs": []}
    for label, start in starts.items():
        end = n if args.frames is None else min(n, start + args.frames)
        frames = np.arange(start, end)
        d = base / f"s{start}-e{end}"
        rest = rest_like_frame(refs["mediapipe"], frames)
        forced = rest if args.neutral == "reference" else None
        tag = f"ours-{cfg_key}-{code_tag(bench=False)}" + ("" if forced is None else f"-n{forced}")
        ours = run_ours(video, start, end, ctx, d / tag, args, neutral=forced)
        peer = run_peer(video, start, end, d / f"peer-{peer_key}.npz", args)
        mapping, unmapped = peer_mapping(ctx, args.rig_yaml, peer["names"])
        curves = {"ours": ours["curves"], "peer": peer_curves(peer, mapping, len(ctx.names))}
        fps = {"ours": len(frames) / float(ours["seconds"]), "peer": float(peer["fps_wall"])}
        common = {"clip": clip, "start": label, "frame": start, "T": len(frames), "neutral": int(ours["neutral"]),
                  "rest": rest}
        for system in SYSTEMS:
            L = ctx.landmarks_2d(curves[system])
            sat = float(np.mean(curves[system].max(axis=1) >= SATURATED))
            out["rows"].append({**common, "system": system, "jitter": jitter(L), "fps": fps[system], "sat": sat,
                                "refs": score(L, MULTIPIE68, refs, frames, rig)})
        out["rows"].append({**common, "system": "tracker", "jitter": float("nan"), "fps": float("nan"), "sat": None,
                            "refs": score(ours["points"], MULTIPIE68, refs, frames, None)})
        out["runs"].append({"start": label, "frame": start, "frames": frames, "curves": curves, "rest": rest})
        lost = int((~peer["found"]).sum())
        log(f"{clip} {label} (frames {start}-{end - 1}): ours {fps['ours']:.1f} fps (neutral frame "
            f"{int(ours['neutral'])}; the reference's rest frame {rest}), peer {fps['peer']:.1f} fps"
            + (f", peer lost the face on {lost} frames" if lost else "")
            + (f"; peer names mapped to no slider: {', '.join(unmapped)}" if unmapped else ""))
    return out


# --------------------------------------------------------------------------- report


def fmt(x, spec=".2f") -> str:
    return "—" if x is None or not np.isfinite(x) else format(x, spec)


def frac(k: int, n: int) -> str:
    return "— (0)" if not n else f"{100.0 * k / n:.0f} % ({n})"


def contact_cell(s: dict, c: str) -> str:
    """``k % of n (parted a, crossed b)`` for contact *c* (``lip``, ``eye``)."""
    n = s[f"{c}_n"]
    if not n:
        return "— (0)"
    return f"{100.0 * s[f'{c}_k'] / n:.0f} % of {n} (parted {s[f'{c}_open']}, crossed {s[f'{c}_cross']})"


def _line(clip, start, system, row: dict, ref: str) -> str:
    s = row["refs"][ref]
    r = s["r"]
    cells = [clip, start, system, *(fmt(r[m]) for m in R_MEASURES)]
    if "lip_n" in s:
        cells += [contact_cell(s, "lip"), contact_cell(s, "eye")]
    else:
        cells += ["—", "—"]
    sat = "—" if row["sat"] is None else f"{100 * row['sat']:.0f} %"
    cells += [fmt(1000 * row["jitter"], ".1f"), sat, fmt(row["fps"], ".1f")]
    return "| " + " | ".join(cells) + " |"


def table(rows: list, ref: str) -> str:
    """One markdown table against reference *ref*: a line per clip x start x system, then a mean per system."""
    lines = ["| clip | start (frame, frames) | system | r mouth | r eye L | r eye R | r brow | r width | "
             "lip contact (of ref-closed frames) | eye contact (of ref-closed eye-frames) | jitter ×1000 | saturated | fps |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        lines.append(_line(row["clip"], f"{row['start']} ({row['frame']}, {row['T']})", row["system"], row, ref))
    for system in (*SYSTEMS, "tracker"):
        got = [row for row in rows if row["system"] == system]
        if not got:
            continue
        mean = {"r": {m: float(np.nanmean([g["refs"][ref]["r"][m] for g in got])) for m in R_MEASURES}}
        if system != "tracker":
            for k in (f"{c}_{x}" for c in ("lip", "eye") for x in ("n", "k", "open", "cross")):
                mean[k] = sum(g["refs"][ref][k] for g in got)
        T = sum(g["T"] for g in got)
        fps = T / sum(g["T"] / g["fps"] for g in got) if system != "tracker" else float("nan")
        sat = None if system == "tracker" else sum(g["sat"] * g["T"] for g in got) / T
        agg = {"refs": {ref: mean}, "jitter": float(np.mean([g["jitter"] for g in got])), "fps": fps, "sat": sat}
        lines.append(_line("**mean**", f"{len(got)} runs", system, agg, ref))
        moving = {"r": {m: moving_mean(got, ref, m) for m in R_MEASURES}}
        lines.append(_line("**mean, moving**", "runs whose reference series moves", system,
                           {"refs": {ref: moving}, "jitter": float("nan"), "fps": float("nan"), "sat": None}, ref))
    return "\n".join(lines)


def moving_mean(rows: list, ref: str, measure: str) -> float:
    """Mean r of *measure* over the *rows* whose reference series moves (std >= FLAT; NaN when none does).

    Over a reference series that barely moves, r compares two noises; the peer shares its network with the
    MediaPipe reference, so its noise there is not independent of the reference's. Both means are printed.
    """
    vals = [g["refs"][ref]["r"][measure] for g in rows if measure not in g["refs"][ref]["flat"]]
    return float(np.nanmean(vals)) if vals else float("nan")


def flat_notes(rows: list) -> list:
    """Runs where a reference's series barely moves (std < FLAT): r there measures noise, not following."""
    out = []
    for row in rows:
        if row["system"] != "ours":
            continue
        bits = [f"{', '.join(s['flat'])} ({ref})" for ref, s in row["refs"].items() if s["flat"]]
        if bits:
            out.append(f"- {row['clip']} {row['start']} ({row['frame']}): {'; '.join(bits)}")
    return out


def losses(rows: list, margin: float = 0.02) -> list:
    """Where ours is behind the peer: r by more than *margin*, contact, jitter (one line per clip x start)."""
    out = []
    key = {(r["clip"], r["start"], r["system"]): r for r in rows}
    for (clip, start, system), ours in key.items():
        if system != "ours":
            continue
        peer = key[(clip, start, "peer")]
        bits = []
        for ref in ours["refs"]:
            a, b = ours["refs"][ref], peer["refs"][ref]
            bits += [f"{m} {a['r'][m]:.2f} vs {b['r'][m]:.2f} ({ref})" for m in R_MEASURES if m != "brow"
                     and np.isfinite(a["r"][m]) and np.isfinite(b["r"][m]) and a["r"][m] < b["r"][m] - margin]
            for c in ("lip", "eye"):
                if a[f"{c}_n"] and a[f"{c}_k"] < b[f"{c}_k"]:
                    bits.append(f"{c} contact {frac(a[f'{c}_k'], a[f'{c}_n'])} vs "
                                f"{100.0 * b[f'{c}_k'] / b[f'{c}_n']:.0f} % ({ref})")
        if ours["jitter"] > peer["jitter"]:
            bits.append(f"jitter {ours['jitter'] / peer['jitter']:.1f}× the peer's")
        if bits:
            out.append(f"- {clip} {start} ({ours['frame']}): " + "; ".join(bits))
    return out


# --------------------------------------------------------------------------- pictures


def _renderer(ctx, size: int):
    """The project's rasteriser framed on the face, as ``bench/real_rig.py --png`` does."""
    api = retarget_api()
    rig = ctx.rig
    face_ids = np.arange(min(9409, rig.n_vertices))  # the face (the kit's README: vertices 0-9408)
    cam = api.Camera(yaw=0.0, pitch=0.0, fov=20.0, fill=1.05)
    renderer = api.MeshRenderer(rig.template.faces(), rig.neutral, camera=cam, size=(size, size))
    renderer.view = api.View.fit(rig.neutral[face_ids], cam, (size, size))
    return renderer


def _text(img, text, y, scale=0.45):
    """White text on a dark band, baseline at *y*."""
    import cv2

    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    cv2.rectangle(img, (2, y - h - 3), (min(img.shape[1] - 1, 10 + w), y + base), (30, 30, 30), -1)
    cv2.putText(img, text, (6, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)


def _triplet(cap, renderer, ctx, run: dict, f: int, what: str, size: int) -> list:
    """Video frame *f*, our character and the peer's at that frame."""
    import cv2

    cap.set(cv2.CAP_PROP_POS_FRAMES, int(f))
    ok, frame = cap.read()
    frame = cv2.resize(frame, (size, size)) if ok else np.zeros((size, size, 3), np.uint8)
    _text(frame, f"frame {f} ({what})", 18)
    panels = [frame]
    t = int(f - run["frames"][0])
    for system, C in run["curves"].items():
        img = renderer.render(ctx.rig.evaluate(C[t]))
        _text(img, system, 18, 0.55)
        top = [i for i in np.argsort(-C[t])[:3] if C[t, i] > 0.05]
        for k, i in enumerate(top):
            _text(img, f"{ctx.names[i]} {C[t, i]:.2f}", size - 8 - 16 * (len(top) - 1 - k), 0.4)
        panels.append(img)
    return panels


def write_pngs(results: list, ctx, outdir: Path, size: int = 256) -> list:
    """Per clip, one row per start: [start frame: video | ours | peer] [the actor nearest rest in the run: same]."""
    import cv2

    renderer = _renderer(ctx, size)
    outdir.mkdir(parents=True, exist_ok=True)
    written = []
    for res in results:
        cap = cv2.VideoCapture(str(res["video"]))
        rows = []
        for run in res["runs"]:
            left = _triplet(cap, renderer, ctx, run, run["frame"], f"start {run['start']}", size)
            right = _triplet(cap, renderer, ctx, run, run["rest"], "actor nearest rest", size)
            gap = np.full((size, 8, 3), 255, np.uint8)
            rows.append(np.concatenate([*left, gap, *right], axis=1))
        cap.release()
        p = outdir / f"{res['clip']}.png"
        cv2.imwrite(str(p), np.concatenate(rows, axis=0))
        written.append(p)
    return written


# --------------------------------------------------------------------------- main


def parse_args(argv):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DATA, help="The realdata folder (default ../shared/realdata).")
    ap.add_argument("--videos", default="d3,d9,d12", help="Clips of ../shared/realdata/videos (comma-separated).")
    ap.add_argument("--frames", type=int, default=None, help="At most N frames from each start (default: to the end).")
    ap.add_argument("--starts", default=",".join(STARTS), help=f"Comma-separated, from {', '.join(STARTS)}.")
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "real.yaml", help="The documented path's config.")
    ap.add_argument("--model", type=Path, default=None, help="The peer's bundle (default DATA/peers/face_landmarker.task).")
    ap.add_argument("--fresh", action="store_true", help="Rerun both systems (not the references).")
    ap.add_argument("--neutral", choices=("config", "reference"), default="config",
                    help="Our neutral frame: the config's (default), or, standing in for one chosen by hand, the "
                         "run's frame nearest rest by the MediaPipe reference (rest_like_frame).")
    ap.add_argument("--png", type=Path, default=None, metavar="DIR", help="Write one picture per clip here.")
    ap.add_argument("--json", type=Path, default=None, help="Also write the rows as JSON.")
    args = ap.parse_args(argv)
    args.starts = [s for s in args.starts.split(",") if s]
    bad = [s for s in args.starts if s not in STARTS]
    if bad:
        ap.error(f"--starts: unknown {bad[0]!r}; expected some of {', '.join(STARTS)}")
    if args.frames is not None and args.frames < 3:
        ap.error("--frames: expected at least 3")
    args.config = args.config.resolve()
    args.model = (args.model or args.data / "peers" / "face_landmarker.task").resolve()
    return args


def unavailable(args, clips) -> str | None:
    """Why the benchmark cannot run here (a skip line), or None."""
    rig_tar = args.data / "ict-facekit" / "ict-facekit-rig.tar.xz"
    need = [rig_tar, args.model, *[args.data / "videos" / f"{c}.mp4" for c in clips]]
    missing = [p for p in need if not p.is_file()]
    if missing:
        return f"{missing[0]} not found (needs ../shared/realdata)"
    if not retarget_api().detector_installed():
        return "raw dlib reference needs dlib and its model (the extra 'detect')"
    from reference import ReferenceUnavailable, ensure_venv

    try:
        ensure_venv(log=log)
    except ReferenceUnavailable as exc:
        return f"no MediaPipe venv ({exc})"
    return None


def main(argv=None) -> int:
    args = parse_args(argv)
    clips = [c for c in args.videos.split(",") if c]
    why = unavailable(args, clips)
    if why:
        print(f"SKIP bench/peer.py: {why}")
        return 0
    from real_rig import load_rig

    ctx = load_rig(args.data / "ict-facekit" / "ict-facekit-rig.tar.xz")
    args.rig_yaml = ROOT / "build" / "real_rig" / "ict-facekit" / "rig.yaml"  # where load_rig unpacks it
    rig = rig_constants(ctx)
    t = time.perf_counter()
    results = [run_clip(c, ctx, rig, args) for c in clips]
    rows = [r for res in results for r in res["rows"]]
    print(f"retarget (documented path, {args.config.name}, track.init auto) against the peer (MediaPipe Face "
          f"Landmarker blendshapes by name) on the ICT rig; frames {'all' if args.frames is None else args.frames} "
          f"per start; our neutral frame {'from the config' if args.neutral == 'config' else 'the reference rest frame'}."
          "\n")
    print("Neutral frames (ours; the reference's rest frame): " + "; ".join(
        f"{r['clip']} {r['start']} {r['neutral']} ({r['rest']})" for r in rows if r["system"] == "ours") + "\n")
    log(f"scored in {time.perf_counter() - t:.0f} s (cached runs reused unless --fresh)")
    for ref, title in (("mediapipe", "MediaPipe Face Mesh 0.10.14"), ("dlib", "raw per-frame dlib 68 points")):
        print(f"Against {title}:\n")
        print(table(rows, ref))
        print()
    print(f"Reference series that barely move (std < {FLAT}; their r is noise):")
    print("\n".join(flat_notes(rows)) or "- none")
    print()
    print("Where ours is behind the peer (r by more than 0.02, contact, jitter):")
    print("\n".join(losses(rows)) or "- nowhere")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1, default=float))
    if args.png:
        for p in write_pngs(results, ctx, args.png):
            log(f"wrote {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
