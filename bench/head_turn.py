"""Benchmark: a turned head must not read as expression (issue 28, item 2), on a synthetic take.

The ICT FaceKit's 68 landmark vertices are posed at random slider weights (a few sliders each, gaze and pupils
at 0 as ``auto-pose`` keeps them), and each expression is seen twice through a pinhole camera (1280x720, focal
1280 px, the face at 60 cm) with 1 px noise: facing the camera, and turned by a known yaw and pitch (uniform
in +-30 deg, roll +-10). ``retarget_cli.synth.head_turn`` writes the take as ``track`` would (the 3D head pose
on the generic face stored as ``head_angles``), and ``auto-pose`` (delta fit, every frame alone: ``smooth 0``)
fits the rig's sliders with and without ``frontalize``. Reported:

- the stored head pose's mean angle error against the known angles (target <= 2 deg);
- the mean absolute slider difference between each turned frame's curves and its frontal twin's, over all
  fitted sliders (target <= 0.05), and each against the true sliders.

Run: ``python bench/head_turn.py [--expressions 60] [--seed 0]``. Needs the unpacked ICT rig
(``make build/ict-facekit/rig.yaml``, or ``--rig``).
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def read_curves(path: Path) -> tuple[list[str], np.ndarray]:
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    head = rows[0]
    start = next(i for i, h in enumerate(head) if h not in ("frame", "time", "found"))
    return head[start:], np.array([[float(v) for v in r[start:]] for r in rows[1:]])


def run(rig_path: Path, n: int, seed: int, max_angle: float, work: Path, max_roll: float = 10.0,
        noise: float = 1.0) -> dict:
    import yaml

    from retarget_cli.io.landmarks import load_landmarks
    from retarget_cli.io.rig import load_rig
    from retarget_cli.stages.auto_pose import DEFAULT_EXCLUDE, excluded_sliders, run_auto_pose
    from retarget_cli.synth.head_turn import write_turned_take

    rig = load_rig(rig_path)
    ids = np.asarray(yaml.safe_load(rig_path.read_text())["landmarks"])
    rng = np.random.default_rng(seed)
    free = ~excluded_sliders(rig.names, DEFAULT_EXCLUDE)
    W = rng.uniform(0, 1, size=(n, rig.n_sliders)) * (rng.uniform(size=(n, rig.n_sliders)) < 0.08) * free
    turned = np.column_stack([rng.uniform(-max_angle, max_angle, (n, 2)), rng.uniform(-max_roll, max_roll, n)])
    weights = np.concatenate([np.zeros((1, rig.n_sliders)), W, W])
    angles = np.concatenate([np.zeros((1 + n, 3)), turned])
    lm_path, keys_path = write_turned_take(work, rig, ids, weights, angles, seed=seed, noise=noise)
    lm = load_landmarks(lm_path)
    err = np.abs(lm.head_angles.astype(np.float64) - angles)
    out = {"frames": len(weights), "angle_mean": err.mean(0), "angle_p95": np.percentile(err, 95, axis=0),
           "angle_all": float(err.mean())}
    for on in (False, True):
        t0 = time.perf_counter()
        dest = work / ("frontal" if on else "plain")
        run_auto_pose(keys=keys_path, landmarks=lm_path, rig=rig_path, output=dest, neutral_frame=0, smooth=0.0,
                      frontalize=on)
        names, C = read_curves(dest / "curves.csv")
        col = [list(names).index(s) for s in np.asarray(rig.names)[free]]
        front, turn = C[1:1 + n][:, col], C[1 + n:][:, col]
        truth = W[:, free]
        out["on" if on else "off"] = {
            "turned_vs_frontal": float(np.abs(turn - front).mean()),
            "turned_vs_frontal_p95": float(np.percentile(np.abs(turn - front).mean(1), 95)),
            "frontal_vs_truth": float(np.abs(front - truth).mean()),
            "turned_vs_truth": float(np.abs(turn - truth).mean()),
            "seconds": time.perf_counter() - t0,
        }
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rig", type=Path, default=ROOT / "build" / "ict-facekit" / "rig.yaml")
    ap.add_argument("--expressions", type=int, default=60)
    ap.add_argument("--max-angle", type=float, default=30.0)
    ap.add_argument("--max-roll", type=float, default=10.0)
    ap.add_argument("--noise", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if not args.rig.is_file():
        print(f"skip: {args.rig} not found (make build/ict-facekit/rig.yaml)")
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        r = run(args.rig, args.expressions, args.seed, args.max_angle, Path(tmp), args.max_roll, args.noise)
    a = r["angle_mean"]
    print(f"## Turned head (ICT landmark vertices, {args.expressions} expressions x frontal/turned, yaw/pitch up "
          f"to +-{args.max_angle:g} deg, roll +-{args.max_roll:g}, {args.noise:g} px noise, seed {args.seed})\n")
    print(f"stored head pose (generic face): mean angle error {r['angle_all']:.2f} deg (yaw {a[0]:.2f}, pitch "
          f"{a[1]:.2f}, roll {a[2]:.2f}; 95th percentile {r['angle_p95'][0]:.2f} / {r['angle_p95'][1]:.2f} / "
          f"{r['angle_p95'][2]:.2f})\n")
    print("| auto_pose.frontalize | turned vs frontal (mean abs slider) | 95th pct per frame | frontal vs truth | "
          "turned vs truth | s |")
    print("|---|---|---|---|---|---|")
    for key in ("off", "on"):
        m = r[key]
        print(f"| {key} | {m['turned_vs_frontal']:.4f} | {m['turned_vs_frontal_p95']:.4f} | "
              f"{m['frontal_vs_truth']:.4f} | {m['turned_vs_truth']:.4f} | {m['seconds']:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
