"""Benchmark: decomposing a long take into key-shape weights.

Compares ``retarget``'s batched NNLS (:func:`retarget_cli.decompose.nnls_batched`),
both its numpy iteration and its compiled kernel (each forced), with the peer,
a per-frame loop over ``scipy.optimize.nnls``, on the same data in the same
run, reports the one-off cost of loading the kernel in a fresh process, and checks that both reach the same objective (relative gap
``(f − f_scipy) / max(f_scipy, 1e-10·‖s_t‖²)``; the floor is the round-off
level of a frame that a key reproduces exactly). Also reports the throughput
of the temporal and sparse solvers.

Data: the synthetic take's 68 source landmarks (136 coordinates per frame,
stabilized, in pixels) driven by its expression curves over T frames at 30 fps,
plus Gaussian noise (0.5 px), with K keys chosen by PCA extremes (``select``)
including frame 0.

Run: ``python bench/decompose.py [--frames T] [--keys 10,22,40] [--scipy-frames N]``.
The scipy loop is timed on the first N frames (default all) and scaled.

``--accuracy`` instead measures the end-to-end retargeting error of each
decomposition setting on synthetic takes (``retarget synth`` then
``retarget run``, error as in ``tests/e2e``: mean vertex error over mean true
expression displacement), the table behind the README's choice of defaults.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def take(T: int, seed: int = 0, noise: float = 0.5) -> np.ndarray:
    from retarget_cli import synth

    curves = synth.expression_curves(T, fps=30.0, seed=seed)
    norm = synth.source_neutral()[None] + np.einsum("te,eld->tld", curves, synth.source_deltas())
    P = synth.place_neutral((320, 320))
    stab = norm @ P[:, :2].T + P[:, 2]
    rng = np.random.default_rng(seed)
    return stab.reshape(T, -1) + rng.normal(scale=noise, size=(T, stab.shape[1] * 2))


def kernel_load() -> float:
    """Seconds a fresh process spends on its first compiled solve (numba import, cache load), best of 3."""
    import subprocess
    import sys

    code = ("import time, numpy as np; t = time.perf_counter(); "
            "from retarget_cli.decompose import nnls_batched; "
            "nnls_batched(np.ones((3, 4)), np.eye(4)[:2], compiled=True); print(time.perf_counter() - t)")
    base = ("import time, numpy as np; t = time.perf_counter(); "
            "from retarget_cli.decompose import nnls_batched; "
            "nnls_batched(np.ones((3, 4)), np.eye(4)[:2], compiled=False); print(time.perf_counter() - t)")
    run = lambda c: float(subprocess.run([sys.executable, "-c", c], capture_output=True, text=True,  # noqa: E731
                                         check=True).stdout)
    return min(run(code) - run(base) for _ in range(3))


def best_of(fn, repeat: int):
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


#: (name, frames, size, seed) of the takes for ``--accuracy``; the last two were held out while choosing alpha.
TAKES = [("e2e", 120, "256x256", 3), ("sample", 240, "320x320", 0), ("400f", 400, "320x320", 1),
         ("held-out 300f", 300, "288x288", 7), ("held-out 200f", 200, "256x256", 11)]
SETTINGS = [f"solver={s} formulation={f} alpha={a}" for s, f, a in [
    ("nnls", "whole", "null"), ("ls", "whole", "null"), ("ridge", "whole", "null"), ("temporal", "whole", "null"),
    ("temporal-causal", "whole", "null"), ("nnls", "convex", "null"), ("nnls", "delta", "null"),
    ("ridge-clipped", "delta", "null"), ("sequential", "delta", "null"), ("temporal", "delta", "0.01"),
    ("sparse", "delta", "0.01"), ("sparse", "delta", "0.05"), ("sparse", "delta", "0.1")]] + [
    "solver=nnls formulation=whole alpha=null confidence=false"]


def accuracy(settings) -> None:
    import tempfile
    from pathlib import Path

    from click.testing import CliRunner

    from retarget_cli.cli import main as cli
    from retarget_cli.io.atomic import load_npz
    from retarget_cli.io.obj import read_obj

    def run(*args):
        r = CliRunner().invoke(cli, list(args))
        if r.exit_code != 0:
            raise SystemExit(f"retarget {' '.join(args)} failed: {r.stderr or r.exception}")

    print("End-to-end retargeted mesh error (% of mean expression displacement) per decompose setting")
    print(f"{'setting':<58}" + "".join(f"{n:>15}" for n, *_ in TAKES))
    rows = {s: [] for s in settings}
    with tempfile.TemporaryDirectory() as tmp:
        for name, n, size, seed in TAKES:
            d = Path(tmp) / name.replace(" ", "_")
            run("synth", str(d), "--frames", str(n), "--size", size, "--seed", str(seed))
            truth = load_npz(d / "truth.npz")["target"].astype(np.float64)
            neutral = read_obj(d / "target" / "neutral.obj").vertices
            disp = np.linalg.norm(truth - neutral, axis=2).mean()
            for s in settings:
                args = ["run", str(d / "config.yaml")]
                for kv in s.split():
                    args += ["--set", f"decompose.{kv}"]
                run(*args)
                got = np.stack([read_obj(f).vertices for f in sorted((d / "out" / "frames").glob("frame_*.obj"))])
                rows[s].append(100 * np.linalg.norm(got - truth, axis=2).mean() / disp)
    for s, errs in rows.items():
        print(f"{s:<58}" + "".join(f"{e:>14.1f}%" for e in errs))


def main() -> None:
    from scipy.optimize import nnls

    from retarget_cli.decompose import _KERNEL_MIN_WORK, cardinality, decompose, jitter, nnls_batched
    from retarget_cli.select import select_keys

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=10_000)
    ap.add_argument("--keys", default="10,22,40")
    ap.add_argument("--scipy-frames", type=int, default=None)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--accuracy", action="store_true", help="End-to-end error of each decompose setting instead.")
    args = ap.parse_args()
    if args.accuracy:
        accuracy(SETTINGS)
        return
    T = args.frames
    X = take(T)
    n_ref = min(args.scipy_frames or T, T)
    print(f"NNLS on a synthetic take: T = {T} frames, D = {X.shape[1]} coordinates, 0.5 px noise; "
          f"scipy timed on {n_ref} frames{' (scaled to T)' if n_ref < T else ''}; best of {args.repeat}")
    print(f"{'K':>4}{'numpy fps':>12}{'compiled fps':>14}{'scipy fps':>12}{'numpy':>8}{'compiled':>10}"
          f"{'max rel. objective gap':>25}")
    worst = 0.0
    for K in (int(k) for k in args.keys.split(",")):
        B = X[select_keys(X, K, include=(0,))]
        nnls_batched(X[:100], B, compiled=True)  # load the kernel outside the timing (see below)
        tn, Wn = best_of(lambda B=B: nnls_batched(X, B, compiled=False), args.repeat)
        tc, Wc = best_of(lambda B=B: nnls_batched(X, B, compiled=True), args.repeat)
        A = np.ascontiguousarray(B.T)  # the peer at its best: no per-call copy of a transposed view
        ts, ref = best_of(lambda A=A: np.array([nnls(A, s)[1] ** 2 for s in X[:n_ref]]), args.repeat)
        ts *= T / n_ref
        gap = 0.0
        for W in (Wn, Wc):
            f = np.sum((X[:n_ref] - W[:n_ref] @ B) ** 2, axis=1)
            gap = max(gap, np.max((f - ref) / np.maximum(ref, 1e-10 * np.sum(X[:n_ref] ** 2, axis=1))))
        worst = max(worst, gap)
        print(f"{K:>4}{T / tn:>12,.0f}{T / tc:>14,.0f}{T / ts:>12,.0f}{ts / tn:>7.1f}x{ts / tc:>9.1f}x{gap:>25.2e}")
    print(f"compiled kernel, once per process: {kernel_load():.2f} s to import numba and load the cached kernel; "
          f"box_qp uses it from T*K >= {_KERNEL_MIN_WORK:,} on")
    print()
    K = 22
    B = X[select_keys(X, K, include=(0,))]
    print(f"Other solvers, K = {K}, formulation delta (neutral: frame 0), default alpha:")
    print(f"{'solver':<18}{'frames/s':>12}{'jitter':>12}{'cardinality':>13}{'mean residual':>15}")
    for solver in ("nnls", "sparse", "temporal-causal", "temporal"):
        t, (W, res) = best_of(lambda s=solver: decompose(X, B, solver=s, formulation="delta", neutral=X[0]), 1)
        print(f"{solver:<18}{T / t:>12,.0f}{jitter(W):>12.2e}{cardinality(W).mean():>13.2f}{res.mean():>15.3f}")
    if worst > 1e-8:
        raise SystemExit(f"batched NNLS objective differs from scipy's by {worst:.2e} (relative)")


if __name__ == "__main__":
    main()
