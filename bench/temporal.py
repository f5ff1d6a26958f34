"""Benchmark: temporal quality (mesh error, jitter, blink amplitude) per landmark smoother and solver.

Takes (600 frames each by default):

- ``synthetic``: ``retarget synth`` with its default perturbations, tracked
  by ``retarget track`` (Lucas–Kanade, unfiltered), bilateral blinks of 4–8
  frames;
- ``stressed``: the same with bench/track.py's stressed perturbations (sensor
  noise 5, blur 1, JPEG 40, lighting 2.5, head motion 2.5x faster);
- ``ict``: a cross-identity take built from the ICT FaceKit rig
  (sample_data/ict): the actor is ``identity000`` and the character
  ``identity001`` (other face shapes on the rig's topology, each with the
  rig's expression deltas added); known expression curves over 14 ARKit
  shapes with smooth bumps plus bilateral blinks of 2–5 frames; the actor's
  68 landmark vertices projected orthographically with smooth head motion
  (yaw/pitch ±5°, roll ±8°, translation, scale) and 0.5 px Gaussian noise.

For each take, the landmarks are filtered by each smoother (``none``,
``one-euro``, ``rts`` without and with event preservation), then the real
``select`` (greedy, regions brows-eyes and mouth, k 12) and ``decompose``
stage runners run on them, and the retargeted mesh is the character's key
shapes (the character posed at each key frame's true curves: the synthetic
artist of ``retarget pose-keys``) blended with the weights and the region
masks, as ``apply`` does. Reported per smoother × solver:

- mesh error: mean vertex error against the true animation, % of the mean
  true expression displacement (ICT: face vertices only);
- jitter: mean vertex acceleration, as a ratio to the true animation's;
- blink amplitude: per blink event, the least-squares scale of the mesh's
  blink displacement (peak frame against the frames just before and after)
  onto the truth's, over the vertices the blink moves; mean over events, %.

With ``--ideal PX`` the synthetic takes skip the tracker: their landmarks are the true ones plus PX of white
noise (as the ICT take's), which tells what the smoothers and solvers change from what the tracker loses.

Run: ``python bench/temporal.py [--frames 600] [--seeds 0,1,2] [--takes synthetic,stressed,ict] [--tracker lk]
[--ideal 0.5] [--fixed-keys] [--all]``.
"""

from __future__ import annotations

import argparse
import tarfile
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from retarget_cli.io.landmarks import Landmarks, load_landmarks, save_landmarks
from retarget_cli.io.stagefiles import load_weights
from retarget_cli.methods.blending import blend_keys, blend_regions
from retarget_cli.methods.decomposition import mean_acceleration
from retarget_cli.methods.tracking.head import estimate_head
from retarget_cli.stages import REGION_PRESETS_68, run_decompose, run_select, run_track
from retarget_cli.stages._landmark_filter import FILTER_DEFAULTS, apply_filter

REPO = Path(__file__).resolve().parents[1]
#: Perturbations of the stressed take (as bench/track.py).
STRESS = dict(noise=5.0, blur=1.0, jpeg=40, light=2.5, speed=2.5)

#: Smoothers: name -> filter settings (track.filter*); "rts (default)" is track's default.
SMOOTHERS = {
    "none": {"filter": "none"},
    "one-euro": {"filter": "one-euro"},
    "rts (plain)": {"filter": "rts", "filter_robust": 0.0},
    "rts (default)": {"filter": "rts"},
}
#: Solvers: name -> decompose settings (the stage defaults for the rest: temporal robust 1, alpha 1 in shape space).
SOLVERS = {
    "sparse delta 0.05": dict(solver="sparse", formulation="delta", alpha=0.05),
    "nnls whole": dict(solver="nnls", formulation="whole"),
    "temporal weights 0.1": dict(solver="temporal", formulation="delta", alpha=0.1, smooth_space="weights",
                                 robust=0.0),
    "temporal shape r0": dict(solver="temporal", formulation="delta", robust=0.0),
    "temporal shape": dict(solver="temporal", formulation="delta"),
    "temporal shape r2": dict(solver="temporal", formulation="delta", robust=2.0),
    "temporal-causal shape": dict(solver="temporal-causal", formulation="delta"),
}
#: Rows measured by default: (smoother, solver). The baseline is the first: today's sample config, unfiltered.
ROWS = [("none", "sparse delta 0.05"), ("none", "nnls whole"), ("none", "temporal shape"),
        ("rts (default)", "sparse delta 0.05"), ("rts (default)", "temporal shape r2"),
        ("rts (default)", "temporal shape")]
#: Every combination (--all).
ALL_ROWS = ([("none", s) for s in SOLVERS] + [(f, s) for f in ("one-euro", "rts (plain)", "rts (default)")
                                              for s in SOLVERS if s != "temporal weights 0.1"])


@dataclass
class Take:
    points: np.ndarray        # (T, 68, 2) image landmarks, unfiltered
    confidence: np.ndarray    # (T, 68)
    fps: float
    size: tuple
    curves: np.ndarray        # (T, E) true expression curves
    neutral: np.ndarray       # (N, 3) character neutral
    deltas: np.ndarray        # (E, N, 3) character expression deltas
    masks: dict               # region -> (N,) character vertex weights
    blinks: list              # curve columns of the blinks
    measure: np.ndarray       # vertex indices the metrics use
    truth_points: np.ndarray  # (T, 68, 2) true image landmarks (before tracking / noise)

    def mesh(self, curves):
        return self.neutral[None] + np.einsum("te,end->tnd", curves, self.deltas)


# --------------------------------------------------------------------------- takes


def synthetic_take(d: Path, frames: int, seed: int, perturb: dict, tracker: str = "lk",
                   ideal: float | None = None) -> Take:
    """A ``retarget synth`` take tracked by *tracker*; with *ideal* (px), the true landmarks plus that much noise.

    *ideal* stands in for a tracker without bias, so the smoothers and solvers are measured on what they
    can change (white measurement noise) apart from what the tracker loses.
    """
    from retarget_cli.io.atomic import load_npz
    from retarget_cli.synth.take import EXPRESSIONS, target_region_masks, target_rig, write_take

    write_take(d, n_frames=frames, seed=seed, **perturb)
    truth_points = load_landmarks(d / "truth_landmarks.npz").points.astype(np.float64)
    if ideal is None:
        run_track(video=d / "face.mp4", init=d / "face_00000.pts", output=d / "raw.npz", filter="none",
                  method=tracker)
        lm = load_landmarks(d / "raw.npz")
        points, confidence = lm.points.astype(np.float64), lm.confidence.astype(np.float64)
    else:
        lm = load_landmarks(d / "truth_landmarks.npz")
        points = truth_points + np.random.default_rng([seed, 18]).normal(0, ideal, truth_points.shape)
        confidence = np.ones(points.shape[:2])
    rig = target_rig(seed=seed)
    curves = load_npz(d / "truth.npz")["curves"].astype(np.float64)
    return Take(points, confidence, lm.fps, tuple(lm.frame_size),
                curves, rig["vertices"].astype(np.float64), rig["deltas"].astype(np.float64),
                target_region_masks(rig), [EXPRESSIONS.index("blink_l"), EXPRESSIONS.index("blink_r")],
                np.arange(len(rig["vertices"])), truth_points)


ICT_SHAPES = {  # region of each expression used by the ICT take
    "browInnerUp_L": "brows-eyes", "browInnerUp_R": "brows-eyes", "browDown_L": "brows-eyes",
    "browDown_R": "brows-eyes", "eyeSquint_L": "brows-eyes", "eyeSquint_R": "brows-eyes",
    "eyeBlink_L": "brows-eyes", "eyeBlink_R": "brows-eyes",
    "jawOpen": "mouth", "mouthSmile_L": "mouth", "mouthSmile_R": "mouth", "mouthPucker": "mouth",
    "mouthFunnel": "mouth", "mouthFrown_L": "mouth",
}
ICT_FACE_VERTICES = 9409


def _bumps(rng, T, fps, n_events):
    """Smooth activation: raised-cosine bumps of 0.6-1.8 s, peaks 0.5-1, random starts."""
    t = np.arange(T) / fps
    c = np.zeros(T)
    for _ in range(n_events):
        s, dur, peak = rng.uniform(0.3, t[-1]), rng.uniform(0.6, 1.8), rng.uniform(0.5, 1.0)
        u = (t - s) / dur
        c += np.where((u > 0) & (u < 1), peak * 0.5 * (1 - np.cos(2 * np.pi * np.clip(u, 0, 1))), 0.0)
    return np.clip(c, 0, 1)


def ict_curves(T: int, fps: float, seed: int) -> tuple[np.ndarray, list]:
    """Curves (T, E) over :data:`ICT_SHAPES` and the blink events (start, length)."""
    rng = np.random.default_rng([seed, 16])
    names = list(ICT_SHAPES)
    C = np.zeros((T, len(names)))
    for e, n in enumerate(names):
        if not n.startswith("eyeBlink"):
            C[:, e] = _bumps(rng, T, fps, max(1, int(T / fps / 6)))
    events, t = [], int(rng.integers(20, 60))
    while t < T - 10:
        n = int(rng.integers(2, 6))  # 2-5 frames
        prof = np.sin(np.pi * np.arange(1, n + 1) / (n + 1))
        prof /= prof.max()
        for b in ("eyeBlink_L", "eyeBlink_R"):
            C[t:t + n, names.index(b)] = prof
        events.append((t, n))
        t += int(rng.integers(int(1.5 * fps), int(3.5 * fps)))
    C[0] = 0
    return C, events


def ict_take(tmp: Path, frames: int, seed: int, fps: float = 30.0) -> Take:
    import yaml

    from retarget_cli.io.obj import read_obj

    d = tmp / "ict"
    with tarfile.open(REPO / "sample_data" / "ict" / "ict-facekit-rig.tar.xz") as tf:
        members = [m for m in tf.getmembers() if Path(m.name).stem in
                   {"generic_neutral_mesh", "identity000", "identity001", *ICT_SHAPES}]
        tf.extractall(d, members=members, filter="data")
    root = d / "ict-facekit"
    spec = yaml.safe_load((REPO / "sample_data" / "ict" / "rig.yaml").read_text())
    lmv = np.asarray(spec["landmarks"], dtype=np.int64)
    V0 = read_obj(root / "generic_neutral_mesh.obj").vertices.astype(np.float64)
    deltas = np.stack([read_obj(root / f"{n}.obj").vertices - V0 for n in ICT_SHAPES])
    actor0 = read_obj(root / "identity000.obj").vertices.astype(np.float64)
    char0 = read_obj(root / "identity001.obj").vertices.astype(np.float64)
    curves, _ = ict_curves(frames, fps, seed)
    # actor landmarks in 3D, then projected with head motion
    L3 = actor0[lmv][None] + np.einsum("te,eld->tld", curves, deltas[:, lmv])
    rng = np.random.default_rng([seed, 17])
    t = np.arange(frames) / fps

    def wave(amp):
        f, ph = rng.uniform(0.05, 0.3, 2), rng.uniform(0, 2 * np.pi, 2)
        return amp * 0.5 * (np.sin(2 * np.pi * f[0] * t + ph[0]) + np.sin(2 * np.pi * f[1] * t + ph[1]))

    yaw, pitch, roll = np.radians(wave(5)), np.radians(wave(5)), np.radians(wave(8))
    scale, tx, ty = 13.0 * (1 + wave(0.05)), 256 + wave(20), 256 + wave(20)
    centre = L3[0].mean(0)
    P = np.empty((frames, len(lmv), 2))
    for i in range(frames):
        cy, sy, cp, sp, cr, sr = np.cos(yaw[i]), np.sin(yaw[i]), np.cos(pitch[i]), np.sin(pitch[i]), \
            np.cos(roll[i]), np.sin(roll[i])
        R = (np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]]) @ np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
             @ np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]]))
        X = (L3[i] - centre) @ R.T
        P[i, :, 0] = tx[i] + scale[i] * X[:, 0]
        P[i, :, 1] = ty[i] - scale[i] * X[:, 1]   # image y down, model y up
    P_true = P.copy()
    P += rng.normal(0, 0.5, P.shape)
    # character masks: each region's share of its expressions' displacement
    mags = {r: sum(np.linalg.norm(deltas[e], axis=1) for e, n in enumerate(ICT_SHAPES) if ICT_SHAPES[n] == r)
            for r in ("brows-eyes", "mouth")}
    total = sum(mags.values())
    moving = total > 1e-4 * total.max()
    masks = {r: np.where(moving, m / np.where(moving, total, 1.0), 0.0) for r, m in mags.items()}
    names = list(ICT_SHAPES)
    return Take(P, np.ones(P.shape[:2]), fps, (512, 512), curves, char0, deltas, masks,
                [names.index("eyeBlink_L"), names.index("eyeBlink_R")], np.arange(ICT_FACE_VERTICES), P_true)


# --------------------------------------------------------------------------- metrics


def blink_events(c: np.ndarray) -> list[tuple[int, int, int]]:
    """(start, peak, end) of each run of a blink curve above 0.02."""
    on = c > 0.02
    out, t = [], 0
    while t < len(c):
        if on[t]:
            s = t
            while t < len(c) and on[t]:
                t += 1
            if c[s:t].max() > 0.5:
                out.append((s, s + int(np.argmax(c[s:t])), t))
        t += 1
    return out


def blink_amplitude(got, truth, take: Take) -> float:
    """Mean over blink events of the mesh's blink displacement scaled onto the truth's (%)."""
    amps = []
    for col in take.blinks:
        mag = np.linalg.norm(take.deltas[col][take.measure], axis=1)
        moved = np.flatnonzero(mag > 0.2 * mag.max())
        for s, p, e in blink_events(take.curves[:, col]):
            a, b = s - 2, e + 1
            if a < 0 or b >= len(got):
                continue
            dt = truth[p, moved] - 0.5 * (truth[a, moved] + truth[b, moved])
            dg = got[p, moved] - 0.5 * (got[a, moved] + got[b, moved])
            amps.append(float(np.sum(dg * dt) / np.sum(dt * dt)))
    return 100 * float(np.mean(amps)) if amps else float("nan")


#: Eyelid landmarks of the 68-point Multi-PIE layout (upper and lower lid of each eye, corners left out).
LIDS = [37, 38, 40, 41, 43, 44, 46, 47]


def lid_blink(points, take: Take) -> float:
    """Blink amplitude of the eyelid landmarks (%): as :func:`blink_amplitude`, image points against the true points.

    Separates the loss of the tracker and the landmark filter (this column) from that of the keys and the
    solver (the mesh's ``blink`` column).
    """
    amps = []
    ref = take.truth_points[:, LIDS]
    got = np.asarray(points)[:, LIDS]
    for s, p, e in blink_events(take.curves[:, take.blinks[0]]):
        a, b = s - 2, e + 1
        if a < 0 or b >= len(got):
            continue
        dt = ref[p] - 0.5 * (ref[a] + ref[b])
        dg = got[p] - 0.5 * (got[a] + got[b])
        amps.append(float(np.sum(dg * dt) / np.sum(dt * dt)))
    return 100 * float(np.mean(amps)) if amps else float("nan")


# --------------------------------------------------------------------------- pipeline


def landmarks_file(take: Take, smoother: dict, path: Path) -> Path:
    settings = {**FILTER_DEFAULTS, **smoother}
    pts, raw, meta = apply_filter(take.points, take.confidence, fps=take.fps, settings=settings, where="bench",
                                  anchors=[0])
    head, stab = estimate_head(pts, take.confidence)
    save_landmarks(path, Landmarks(pts, take.confidence, head, stab, take.fps, np.array(take.size), None,
                                   {"filter": meta}, points_raw=raw))
    return path


def retarget(take: Take, lm: Path, keys: Path, out: Path, settings: dict) -> np.ndarray:
    run_decompose(landmarks=lm, keys=keys, output=out, **settings)
    regions, _ = load_weights(out)
    names = list(take.masks)
    parts = []
    for r in names:
        W, frames, _ = regions[r]
        K = take.mesh(take.curves[frames])[:, take.measure]   # the character posed at the key frames
        parts.append(blend_keys(W, K))
    return blend_regions(parts, [take.masks[r][take.measure] for r in names], take.neutral[take.measure])


def bench_take(name: str, take: Take, d: Path, rows_wanted=ROWS, fixed_keys: bool = False) -> list[tuple]:
    truth = take.mesh(take.curves)[:, take.measure]
    V0 = take.neutral[take.measure]
    disp = np.linalg.norm(truth - V0, axis=2).mean()
    acc_truth = mean_acceleration(truth)
    regions = {r: REGION_PRESETS_68[r] for r in ("brows-eyes", "mouth")}
    rows = []
    files = {}
    if fixed_keys:  # one key set for every row: selected on the unfiltered landmarks
        fixed = d / "keys-fixed.json"
        run_select(landmarks=landmarks_file(take, SMOOTHERS["none"], d / "fixed.landmarks.npz"), output=fixed,
                   template=None, method="greedy", k=12, regions=regions)
    for fname, solver in rows_wanted:
        if fname not in files:
            lm = landmarks_file(take, SMOOTHERS[fname], d / f"{fname.split()[0]}{len(files)}.landmarks.npz")
            keys = fixed if fixed_keys else d / f"keys{len(files)}.json"
            if not fixed_keys:
                run_select(landmarks=lm, output=keys, template=None, method="greedy", k=12, regions=regions)
            files[fname] = (lm, keys, lid_blink(load_landmarks(lm).points, take))
        lm, keys, lids = files[fname]
        t0 = time.perf_counter()
        got = retarget(take, lm, keys, d / "weights.npz", SOLVERS[solver])
        sec = time.perf_counter() - t0
        err = 100 * np.linalg.norm(got - truth, axis=2).mean() / disp
        rows.append((name, fname, solver, err, mean_acceleration(got) / acc_truth, blink_amplitude(got, truth, take),
                     lids, sec))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--seeds", default="0", help="comma-separated seeds; figures are means over them")
    ap.add_argument("--takes", default="synthetic,stressed,ict")
    ap.add_argument("--tracker", default="lk", help="retarget track --method of the synthetic takes")
    ap.add_argument("--ideal", type=float, default=None, metavar="PX",
                    help="synthetic takes: the true landmarks plus PX of white noise instead of the tracker "
                         "(separates what the smoothers and solvers change from what the tracker loses)")
    ap.add_argument("--all", action="store_true", help="every smoother x solver (about 4x longer)")
    ap.add_argument("--fixed-keys", action="store_true",
                    help="select the keys once per take on the unfiltered landmarks (isolates smoother and solver "
                         "from key selection)")
    args = ap.parse_args()
    takes = args.takes.split(",")
    seeds = [int(s) for s in args.seeds.split(",")]
    rows = {}
    t_all = time.perf_counter()
    for seed in seeds:
        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            for name in takes:
                d = tmp / name
                d.mkdir()
                if name == "synthetic":
                    take = synthetic_take(d, args.frames, seed, {}, args.tracker, args.ideal)
                elif name == "stressed":
                    take = synthetic_take(d, args.frames, seed, STRESS, args.tracker, args.ideal)
                elif name == "ict":
                    take = ict_take(d, args.frames, seed)
                else:
                    raise SystemExit(f"unknown take {name!r}; expected synthetic, stressed, ict")
                base = None
                for row in bench_take(name, take, d, ALL_ROWS if args.all else ROWS, args.fixed_keys):
                    base = row[3] if base is None else base
                    rows.setdefault(row[:3], []).append((*row[3:], 100 * (row[3] / base - 1)))
    source = f"true landmarks + {args.ideal:g} px noise" if args.ideal is not None else f"tracker {args.tracker}"
    print(f"temporal quality, {args.frames} frames, seeds {args.seeds}, {source}"
          f"{', keys fixed (selected on the unfiltered landmarks)' if args.fixed_keys else ''} "
          f"({time.perf_counter() - t_all:.0f} s); mesh error in % of the mean true expression displacement; "
          f"jitter = mean vertex acceleration / truth's; blink = mesh blink amplitude, lid blink = of the eyelid "
          f"landmarks after tracking and filtering; means over the seeds, vs baseline also its worst seed")
    worst = "  (worst)" if len(seeds) > 1 else ""
    print(f"{'take':<10}{'smoother':<15}{'solver':<23}{'mesh error':>11}{'jitter':>9}{'blink':>8}{'lid blink':>11}"
          f"{'vs baseline':>13}{worst}{'decompose s':>13}")
    for (take, f, s), vals in rows.items():
        err, jit, blink, lids, sec, rel = np.mean(vals, axis=0)
        w = f"{max(v[-1] for v in vals):>+8.0f}%" if worst else ""
        print(f"{take:<10}{f:<15}{s:<23}{err:>10.1f}%{jit:>8.2f}x{blink:>7.0f}%{lids:>10.0f}%{rel:>+12.0f}%{w}"
              f"{sec:>13.2f}")


if __name__ == "__main__":
    main()
