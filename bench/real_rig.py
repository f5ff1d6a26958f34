"""Benchmark: real footage onto the ICT FaceKit rig, judged against an independent detector (issue 14).

For each clip of ``../shared/realdata/videos`` (d3, d9, d12): track it with ``retarget track``
(default ``--method lk`` from the clip's frame-0 ``.pts``), turn the landmarks into the rig's
slider curves with each *variant*, pose the rig's 68 landmark vertices at those curves
(``f0[v] + D[v] @ curves``, projected frontally) and correlate, over frames, the character's mouth
opening (inner-lip gap / mouth width), eye openings (lid gap / eye width, each eye) and brow height
(brow to eye-corner midpoint / inter-ocular distance) with the actor's, measured by MediaPipe Face
Mesh 0.10.14 (``bench/reference``: its own venv, never part of the pipeline). Definitions:
``bench/realrig/measures.py``.

Variants (each a function ``(landmarks.npz, rig context, work dir) -> curves (T, E)``, registered
in :data:`VARIANTS`):

- ``curves``: the documented path's ``curves.npz``: runs ``retarget run`` on ``--config`` (default
  ``configs/real.yaml``) with this clip's video, annotation and tracker; skipped with a note while
  that config or its curves output does not exist;
- ``absolute``: today's path: ``select`` one region ``face`` (k = ``--keys``), the absolute
  ``auto-pose`` of every key frame (``retarget_cli.methods.editing.auto_pose``, as ``retarget auto-pose`` does),
  ``decompose`` (the sample config's solver sparse, formulation delta, alpha 0.05), then
  ``curves = Σ_k w_k · sliders_k`` (what ``apply`` makes of one region);
- ``direct``: ``retarget_cli.methods.editing.auto_pose`` on every frame, no keys.

Row ``tracker`` is the ceiling: the same measures on our tracked 68 points against MediaPipe.

Targets (issue 14): mean r >= 0.8 for the mouth, >= 0.7 for the eyes, every slider < 0.05 at the
neutral frame (frame 0 for the variants without a config; for ``curves``, the frame its run's keys.json
records: ``neutral_frame: auto`` finds it). Prints a markdown table; caches landmarks, reference and per-variant curves under
``build/real_rig`` and ``build/reference``, keyed by the inputs and by a hash of the retarget_cli
sources (``--fresh`` recomputes the curves). ``--png DIR``
writes, per clip, frame 0, the actor's widest mouth and most closed eyes (by MediaPipe): the video frame beside the
character of each variant. Without ``../shared/realdata`` it prints a skip line and exits 0.

Run: ``python bench/real_rig.py [--videos d3,d9,d12] [--frames N] [--tracker lk] [--variants
absolute,direct,curves] [--png DIR]``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

from realrig.measures import MEASURES, MEDIAPIPE, MULTIPIE68, face_measures, frontal, pearson  # noqa: E402

DATA = ROOT.parent / "shared" / "realdata"
BUILD = ROOT / "build" / "real_rig"
RIG_YAML = ROOT / "sample_data" / "ict" / "rig.yaml"
RETARGET = [sys.executable, "-m", "retarget_cli"]
#: Settings of the documented path's decompose (configs/sample.yaml).
DECOMPOSE_ARGS = ["--solver", "sparse", "--formulation", "delta", "--alpha", "0.05", "--neutral-frame", "0"]
TARGETS = {"mouth": 0.8, "eye_l": 0.7, "eye_r": 0.7}
NEUTRAL_MAX = 0.05


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def retarget(*args) -> None:
    """Run one ``retarget`` command (quiet; its stderr shows on failure)."""
    cmd = [*RETARGET, "-q", *map(str, args)]
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if res.returncode:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{res.stderr.strip()}")


# --------------------------------------------------------------------------- the rig


@dataclass
class RigContext:
    """The ICT rig loaded once per process, with its 68 landmark vertices."""

    rig: object
    vertices: np.ndarray              # (68,) landmark vertex ids (rig.yaml ``landmarks:``)
    rows: np.ndarray = field(init=False)
    f0: np.ndarray = field(init=False)  # (68*3,)
    D: np.ndarray = field(init=False)   # (68*3, E)

    def __post_init__(self):
        self.rows = self.rig.rows(self.vertices)
        self.f0 = self.rig.f0[self.rows]
        self.D = self.rig.block(self.rows)

    @property
    def names(self):
        return self.rig.names

    def landmarks_2d(self, curves) -> np.ndarray:
        """Frontal projection of the landmark vertices posed at *curves* (T, E) -> (T, 68, 2)."""
        X = self.f0 + np.asarray(curves) @ self.D.T
        return frontal(X.reshape(len(X), -1, 3))


def load_rig(rig_tar: Path) -> RigContext:
    import shutil
    import tarfile

    import yaml


    d = BUILD / "ict-facekit"
    if not (d / "rig.yaml").is_file():
        BUILD.mkdir(parents=True, exist_ok=True)
        with tarfile.open(rig_tar) as tar:
            tar.extractall(BUILD, filter="data")
        shutil.copy(RIG_YAML, d / "rig.yaml")
    t = time.perf_counter()
    from retarget_cli.io.rig import load_rig as load_blendshape_rig

    rig = load_blendshape_rig(d / "rig.yaml")
    log(f"rig: {rig.n_vertices} vertices, {rig.n_sliders} sliders, loaded in {time.perf_counter() - t:.1f} s")
    lm = np.asarray(yaml.safe_load((d / "rig.yaml").read_text())["landmarks"], dtype=np.int64)
    return RigContext(rig, lm)


# --------------------------------------------------------------------------- variants


def variant_absolute(landmarks: Path, ctx: RigContext, work: Path, *, keys: int = 16, **_) -> np.ndarray:
    """Today's documented path: select (face, k keys), absolute auto-pose, decompose, Σ w_k sliders_k."""
    from retarget_cli.io.landmarks import load_landmarks
    from retarget_cli.io.stagefiles import load_weights, read_keys
    from retarget_cli.methods.editing import auto_pose

    retarget("select", landmarks, "-o", work / "keys.json", "--region", "face=all", "-k", keys)
    lm = load_landmarks(landmarks)
    kf = read_keys(work / "keys.json").regions["face"]["frames"]
    # What run_auto_pose does per key frame (without writing the key OBJs).
    S = {f: auto_pose(ctx.rig, ctx.vertices, lm.stabilized[f].astype(np.float64), weights=lm.confidence[f])["w"]
         for f in kf}
    retarget("decompose", landmarks, work / "keys.json", "-o", work / "weights.npz", "--no-summary", *DECOMPOSE_ARGS)
    W, frames, _ = load_weights(work / "weights.npz")[0]["face"]
    return W @ np.stack([S[int(f)] for f in frames])


def variant_direct(landmarks: Path, ctx: RigContext, work: Path, **_) -> np.ndarray:
    """``retarget_cli.methods.editing.auto_pose`` on every frame from the neutral (no keys)."""
    from retarget_cli.io.landmarks import load_landmarks
    from retarget_cli.methods.editing import auto_pose

    lm = load_landmarks(landmarks)
    return np.stack([auto_pose(ctx.rig, ctx.vertices, lm.stabilized[t].astype(np.float64),
                               weights=lm.confidence[t])["w"] for t in range(lm.n_frames)])


def variant_delta_direct(landmarks: Path, ctx: RigContext, work: Path, **_) -> np.ndarray:
    """The delta fit of ``auto-pose`` (same defaults) on every frame, no keys."""
    from retarget_cli.io.landmarks import load_landmarks
    from retarget_cli.io.rig import read_rig
    from retarget_cli.methods.regions import REGION_PRESETS_68
    from retarget_cli.methods.rigpose import delta_pose
    from retarget_cli.stages.auto_pose import CONTOUR_68, DEFAULT_EXCLUDE, RIGID_68, excluded_sliders

    lm = load_landmarks(landmarks)
    Y = lm.stabilized.astype(np.float64)
    regions = {n: [p for p in REGION_PRESETS_68[n] if p not in CONTOUR_68] for n in ("brows-eyes", "mouth")}
    spec = read_rig(BUILD / "ict-facekit" / "rig.yaml")
    res = delta_pose(ctx.rig, ctx.vertices, Y[0], Y, weights=lm.confidence, neutral_weights=lm.confidence[0],
                     regions=regions, exclusive=spec.exclusive, rigid=list(RIGID_68),
                     fixed=excluded_sliders(ctx.rig.names, DEFAULT_EXCLUDE))
    return res["w"]


class Skip(Exception):
    """A variant that cannot run here (the reason is reported in the table's notes)."""


def _absolutize(value, base: Path):
    """Relative paths in a config section that exist relative to *base*, made absolute."""
    if isinstance(value, dict):
        return {k: _absolutize(v, base) for k, v in value.items()}
    if isinstance(value, list):
        return [_absolutize(v, base) for v in value]
    if isinstance(value, str) and not os.path.isabs(value) and (base / value).exists():
        return str((base / value).resolve())
    return value


def variant_curves(landmarks: Path, ctx: RigContext, work: Path, *, config: Path, video: Path, init: Path,
                   tracker: str, frames=None, **_) -> np.ndarray:
    """The documented path from one config: ``retarget run`` then its ``curves.npz`` (curves, names, frames)."""
    import yaml

    if not config.is_file():
        raise Skip(f"{config.relative_to(ROOT) if config.is_relative_to(ROOT) else config} does not exist yet")
    raw = yaml.safe_load(config.read_text()) or {}
    cfg = {k: _absolutize(v, config.parent) if k != "output_dir" else v for k, v in raw.items()}
    cfg["output_dir"] = str(work / "run")
    cfg.setdefault("track", {}).update(video=str(video), init=str(init), method=tracker)
    if frames is not None:
        cfg["track"]["end"] = int(frames)
    (work / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    retarget("run", work / "config.yaml")
    found = sorted((work / "run").rglob("curves.npz"))
    if not found:
        raise Skip(f"{config.name}: the run wrote no curves.npz")
    with np.load(found[0]) as d:
        names, C = [str(n) for n in d["names"]], np.asarray(d["curves"], dtype=np.float64)
        rows = np.asarray(d["frames"]) if "frames" in d else np.arange(len(C))
    from retarget_cli.io.landmarks import load_landmarks

    lm = load_landmarks(landmarks)
    want = lm.frames if lm.frames is not None else np.arange(lm.n_frames)
    pos = {int(f): i for i, f in enumerate(rows)}
    missing = [int(f) for f in want if int(f) not in pos]
    if missing:
        raise RuntimeError(f"{found[0]}: no curves for frame {missing[0]} (it has frames {rows[0]}-{rows[-1]})")
    C = C[[pos[int(f)] for f in want]]
    out = np.zeros((len(C), len(ctx.names)))
    for j, n in enumerate(names):
        if n not in ctx.rig.index:
            raise RuntimeError(f"{found[0]}: slider {n!r} is not in the rig")
        out[:, ctx.rig.index[n]] = C[:, j]
    return out


#: Variant name -> (function, description). Add one here; see variant_curves for the signature.
VARIANTS = {
    "curves": (variant_curves, "documented path: `retarget run` config, its curves.npz"),
    "absolute": (variant_absolute, "today: select face k, absolute auto-pose keys, decompose, Σ w·sliders"),
    "direct": (variant_direct, "per-frame absolute auto_pose, no keys"),
    "delta-direct": (variant_delta_direct, "per-frame delta fit (auto-pose's), no keys"),
}


# --------------------------------------------------------------------------- per clip


def track(video: Path, init: Path, tracker: str, extra: list, frames: int | None) -> Path:
    """``retarget track`` once per (video, annotation, tracker, extra arguments); cached in build/."""
    from reference import sha256_file

    from retarget_cli.io.landmarks import load_landmarks, save_landmarks

    tag = "-".join([tracker, *[a.lstrip("-").replace("=", "_").replace("/", "_") for a in extra]])
    d = BUILD / f"{video.stem}-{sha256_file(video)[:12]}-{sha256_file(init)[:8]}-{code_tag(bench=False)}"
    full = d / f"track-{tag}.npz"
    if not full.is_file():
        d.mkdir(parents=True, exist_ok=True)
        t = time.perf_counter()
        retarget("track", video, "--init", init, "--method", tracker, "-o", full, *extra)
        log(f"{video.stem}: tracked ({tracker}) in {time.perf_counter() - t:.1f} s")
    if frames is None:
        return full
    cut = d / f"track-{tag}-first{frames}.npz"
    if not cut.is_file():
        lm = load_landmarks(full)
        n = min(frames, lm.n_frames)
        for k in ("points", "confidence", "head", "stabilized"):
            setattr(lm, k, getattr(lm, k)[:n])
        if lm.frames is not None:
            lm.frames = lm.frames[:n]
        save_landmarks(cut, lm)
    return cut


def code_tag(*, bench: bool = True) -> str:
    """sha256[:10] of every retarget_cli source file (and this script): cached results follow the code."""
    import hashlib

    h = hashlib.sha256()
    files = sorted((ROOT / "retarget_cli").rglob("*.py"))
    for f in [Path(__file__).resolve(), *files] if bench else files:
        h.update(str(f.relative_to(ROOT)).encode() + b"\0" + f.read_bytes())
    return h.hexdigest()[:10]


def neutral_max(curves, frame: int = 0) -> float:
    return float(np.max(curves[frame]))


def run_neutral_frame(work: Path) -> int:
    """The neutral frame of a variant's run: the one its keys.json records (the documented path's
    ``neutral_frame: auto``), else 0 (the variants without a config use frame 0)."""
    keys = work / "run" / "keys.json"
    rec = json.loads(keys.read_text()).get("neutral") if keys.is_file() else None
    return int(rec["frame"]) if isinstance(rec, dict) else 0


def correlations(values: dict, ref: dict, mask) -> dict:
    return {m: pearson(values[m], ref[m], mask) for m in MEASURES}


def run_clip(name: str, ctx: RigContext, args) -> dict:
    from reference import reference_landmarks

    from retarget_cli.io.landmarks import load_landmarks

    video, init = args.data / "videos" / f"{name}.mp4", args.data / "videos" / f"{name}_00000.pts"
    ref = reference_landmarks(video, log=log)
    lm_path = track(video, init, args.tracker, args.track_arg, args.frames)
    lm = load_landmarks(lm_path)
    T = lm.n_frames
    src = lm.frames if lm.frames is not None else np.arange(T)
    rp = ref["points"][src]
    found = ref["found"][src]
    ref_m = face_measures(rp, MEDIAPIPE)
    out = {"clip": name, "frames": T, "found": int(found.sum()), "rows": {}, "notes": [], "curves": {},
           "ref": ref_m, "src_frames": src}
    out["rows"]["tracker"] = {"r": correlations(face_measures(lm.points, MULTIPIE68), ref_m, found),
                              "neutral": float("nan"), "seconds": float("nan")}
    for v in args.variants:
        fn, _ = VARIANTS[v]
        work = lm_path.parent / f"{lm_path.stem}-{v}" / f"k{args.keys}-{args.code}"
        cache = work / "bench-curves.npz"
        t = time.perf_counter()
        if cache.is_file() and not args.fresh:
            with np.load(cache) as d:
                C, secs = d["curves"], float(d["seconds"])
            log(f"{name} {v}: cached curves ({cache.relative_to(ROOT)})")
        else:
            work.mkdir(parents=True, exist_ok=True)
            try:
                C = fn(lm_path, ctx, work, keys=args.keys, config=args.config, video=video, init=init,
                       tracker=args.tracker, frames=args.frames)
            except Skip as exc:
                out["notes"].append(f"{name} {v}: skipped ({exc})")
                continue
            secs = time.perf_counter() - t
            np.savez(cache, curves=C, names=np.array(ctx.names), seconds=secs)
        if C.shape != (T, len(ctx.names)):
            raise RuntimeError(f"variant {v}: curves of shape {C.shape}, expected ({T}, {len(ctx.names)})")
        char_m = face_measures(ctx.landmarks_2d(C), MULTIPIE68)
        f0 = run_neutral_frame(work)
        out["rows"][v] = {"r": correlations(char_m, ref_m, found), "neutral": neutral_max(C, f0), "seconds": secs,
                          "active0": int(np.sum(C[f0] > NEUTRAL_MAX)), "neutral_frame": f0}
        out["curves"][v] = C
        log(f"{name} {v}: {secs:.1f} s, r mouth {out['rows'][v]['r']['mouth']:.3f}")
    return out


# --------------------------------------------------------------------------- report


def fmt(x, spec=".2f") -> str:
    return "—" if x is None or not np.isfinite(x) else format(x, spec)


def table(results: list, variants: list) -> str:
    head = ("| clip | variant | r mouth | r eye L | r eye R | r brow | max slider at the neutral frame (frame) | "
            "sliders > 0.05 there | s |\n"
            "|---|---|---|---|---|---|---|---|---|")
    lines = [head]
    rows = ["tracker", *variants]
    for res in results:
        for v in rows:
            if v not in res["rows"]:
                continue
            row = res["rows"][v]
            r = row["r"]
            lines.append(f"| {res['clip']} ({res['frames']}) | {v} | {fmt(r['mouth'])} | {fmt(r['eye_l'])} | "
                         f"{fmt(r['eye_r'])} | {fmt(r['brow'])} | {fmt(row['neutral'])}"
                         f"{'' if 'neutral_frame' not in row else ' (' + str(row['neutral_frame']) + ')'} | "
                         f"{row.get('active0', '—')} | {fmt(row['seconds'], '.1f')} |")
    for v in rows:
        got = [res["rows"][v] for res in results if v in res["rows"]]
        if not got:
            continue
        mean = {m: float(np.nanmean([g["r"][m] for g in got])) for m in MEASURES}
        neutral = [g["neutral"] for g in got]
        secs = [g["seconds"] for g in got]
        lines.append(f"| **mean** | {v} | {fmt(mean['mouth'])} | {fmt(mean['eye_l'])} | {fmt(mean['eye_r'])} | "
                     f"{fmt(mean['brow'])} | {fmt(max(neutral))} (max) | — | {fmt(sum(secs), '.1f')} (sum) |")
    return "\n".join(lines)


def verdict(results: list, variants: list) -> list:
    out = []
    for v in variants:
        got = [res["rows"][v] for res in results if v in res["rows"]]
        if not got:
            continue
        mean = {m: float(np.nanmean([g["r"][m] for g in got])) for m in MEASURES}
        ok = [f"{m} {mean[m]:.2f} {'>=' if mean[m] >= t else '<'} {t}" for m, t in TARGETS.items()]
        nm = max(g["neutral"] for g in got)
        ok.append(f"neutral-frame max slider {nm:.3f} {'<' if nm < NEUTRAL_MAX else '>='} {NEUTRAL_MAX}")
        met = all(mean[m] >= t for m, t in TARGETS.items()) and nm < NEUTRAL_MAX
        out.append(f"- {v}: {'targets met' if met else 'targets NOT met'} ({'; '.join(ok)})")
    return out


# --------------------------------------------------------------------------- pictures


def write_pngs(results: list, ctx: RigContext, outdir: Path, data: Path, size: int = 384) -> list:
    """Per clip: frame 0, the widest mouth, the most closed eyes (MediaPipe): video frame | character per variant."""
    import cv2

    from retarget_cli.methods.render import Camera, MeshRenderer, View

    rig = ctx.rig
    faces = rig.template.faces()
    face_ids = np.arange(min(9409, rig.n_vertices))  # the face (the kit's README: vertices 0-9408)
    cam = Camera(yaw=0.0, pitch=0.0, fov=20.0, fill=1.05)
    renderer = MeshRenderer(faces, rig.neutral, camera=cam, size=(size, size))
    renderer.view = View.fit(rig.neutral[face_ids], cam, (size, size))  # frame the face, render the whole head
    outdir.mkdir(parents=True, exist_ok=True)
    written = []
    for res in results:
        ref, src = res["ref"], res["src_frames"]
        eyes = 0.5 * (ref["eye_l"] + ref["eye_r"])
        picks = {"neutral": 0, "widest-mouth": int(np.nanargmax(ref["mouth"])), "eyes-closed": int(np.nanargmin(eyes))}
        cap = cv2.VideoCapture(str(data / "videos" / f"{res['clip']}.mp4"))
        for label, t in picks.items():
            cap.set(cv2.CAP_PROP_POS_FRAMES, int(src[t]))
            ok, frame = cap.read()
            frame = cv2.resize(frame, (size, size)) if ok else np.zeros((size, size, 3), np.uint8)
            cv2.putText(frame, f"{res['clip']} frame {int(src[t])} ({label})", (8, 20), cv2.FONT_HERSHEY_SIMPLEX,
                        0.5, (255, 255, 255), 1, cv2.LINE_AA)
            panels = [frame]
            for v, C in res["curves"].items():
                img = renderer.render(rig.evaluate(C[t]))
                top = ", ".join(f"{rig.names[i]} {C[t, i]:.2f}" for i in np.argsort(-C[t])[:3])
                cv2.putText(img, v, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1, cv2.LINE_AA)
                cv2.putText(img, top, (8, size - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (255, 255, 255), 1,
                            cv2.LINE_AA)
                panels.append(img)
            p = outdir / f"{res['clip']}-{label}.png"
            cv2.imwrite(str(p), np.concatenate(panels, axis=1))
            written.append(p)
        cap.release()
    return written


# --------------------------------------------------------------------------- main


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DATA, help="The realdata folder (default ../shared/realdata).")
    ap.add_argument("--videos", default="d3,d9,d12", help="Clips of ../shared/realdata/videos (comma-separated).")
    ap.add_argument("--frames", type=int, default=None, help="Only the first N frames of each clip.")
    ap.add_argument("--tracker", default="lk", help="retarget track --method (lk, detect, ...).")
    ap.add_argument("--track-arg", action="append", default=[], metavar="ARG",
                    help="Extra argument for retarget track (repeatable), e.g. --track-arg=--window=31.")
    ap.add_argument("--variants", default="curves,absolute,direct",
                    help=f"Comma-separated, from {', '.join(VARIANTS)}.")
    ap.add_argument("--keys", type=int, default=16, help="k of variant absolute's select (12-24).")
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "real.yaml",
                    help="Config of variant curves (its track section is pointed at each clip).")
    ap.add_argument("--fresh", action="store_true", help="Recompute the variants' curves (not the cached "
                                                         "tracking or reference).")
    ap.add_argument("--png", type=Path, default=None, metavar="DIR", help="Write comparison pictures here.")
    ap.add_argument("--json", type=Path, default=None, help="Also write the figures as JSON.")
    args = ap.parse_args(argv)
    args.variants = [v for v in args.variants.split(",") if v]
    bad = [v for v in args.variants if v not in VARIANTS]
    if bad:
        ap.error(f"--variants: unknown {bad[0]!r}; expected some of {', '.join(VARIANTS)}")
    args.config = args.config.resolve()
    clips = [c for c in args.videos.split(",") if c]
    rig_tar = args.data / "ict-facekit" / "ict-facekit-rig.tar.xz"
    missing = [p for p in [rig_tar, *[args.data / "videos" / f"{c}.mp4" for c in clips]] if not p.is_file()]
    if missing:
        print(f"SKIP bench/real_rig.py: {missing[0]} not found (needs ../shared/realdata)")
        return 0
    from reference import ReferenceUnavailable, ensure_venv

    try:
        ensure_venv(log=log)
    except ReferenceUnavailable as exc:
        print(f"SKIP bench/real_rig.py: no MediaPipe reference ({exc})")
        return 0
    args.code = code_tag()
    ctx = load_rig(rig_tar)
    results = [run_clip(c, ctx, args) for c in clips]
    print(f"Real footage onto the ICT rig ({ctx.rig.n_sliders} sliders), tracker {args.tracker}, actor measured "
          f"by MediaPipe Face Mesh 0.10.14; Pearson r over frames; eye L = image-left eye.\n")
    print(table(results, args.variants))
    print()
    for note in (n for r in results for n in r["notes"]):
        print(f"- {note}")
    for line in verdict(results, args.variants):
        print(line)
    if args.json:
        args.json.write_text(json.dumps([{k: res[k] for k in ("clip", "frames", "found", "rows", "notes")}
                                         for res in results], indent=1))
    if args.png:
        for p in write_pngs(results, ctx, args.png, args.data):
            log(f"wrote {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
