"""Benchmark: decomposing a long take into key-shape weights.

Compares ``retarget``'s batched NNLS (:func:`retarget_cli.decompose.nnls_batched`)
with the peer, a per-frame loop over ``scipy.optimize.nnls``, on the same data
in the same run, and checks that both reach the same objective (relative gap
``(f − f_scipy) / max(f_scipy, 1e-10·‖s_t‖²)``; the floor is the round-off
level of a frame that a key reproduces exactly). Also reports the throughput
of the temporal and sparse solvers.

Data: the synthetic take's 68 source landmarks (136 coordinates per frame,
stabilized, in pixels) driven by its expression curves over T frames at 30 fps,
plus Gaussian noise (0.5 px), with K keys chosen by PCA extremes (``select``)
including frame 0.

Run: ``python bench/decompose.py [--frames T] [--keys 10,22,40] [--scipy-frames N]``.
The scipy loop is timed on the first N frames (default all) and scaled.
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


def best_of(fn, repeat: int):
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main() -> None:
    from scipy.optimize import nnls

    from retarget_cli.decompose import decompose, jitter, nnls_batched
    from retarget_cli.select import select_keys

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=10_000)
    ap.add_argument("--keys", default="10,22,40")
    ap.add_argument("--scipy-frames", type=int, default=None)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    T = args.frames
    X = take(T)
    n_ref = min(args.scipy_frames or T, T)
    print(f"NNLS on a synthetic take: T = {T} frames, D = {X.shape[1]} coordinates, 0.5 px noise; "
          f"scipy timed on {n_ref} frames{' (scaled to T)' if n_ref < T else ''}; best of {args.repeat}")
    print(f"{'K':>4}{'batched fps':>14}{'scipy fps':>12}{'speed-up':>10}{'max rel. objective gap':>25}")
    worst = 0.0
    for K in (int(k) for k in args.keys.split(",")):
        B = X[select_keys(X, K, include=(0,))]
        tb, W = best_of(lambda B=B: nnls_batched(X, B), args.repeat)
        ts, ref = best_of(lambda B=B: np.array([nnls(B.T, s)[1] ** 2 for s in X[:n_ref]]), 1)
        ts *= T / n_ref
        f = np.sum((X[:n_ref] - W[:n_ref] @ B) ** 2, axis=1)
        gap = np.max((f - ref) / np.maximum(ref, 1e-10 * np.sum(X[:n_ref] ** 2, axis=1)))
        worst = max(worst, gap)
        print(f"{K:>4}{T / tb:>14,.0f}{T / ts:>12,.0f}{ts / tb:>9.1f}x{gap:>25.2e}")
    print()
    K = 22
    B = X[select_keys(X, K, include=(0,))]
    print(f"Other solvers, K = {K}:")
    print(f"{'solver':<18}{'frames/s':>12}{'jitter':>12}{'mean residual':>15}")
    for solver in ("nnls", "sparse", "temporal-causal", "temporal"):
        t, (W, res) = best_of(lambda s=solver: decompose(X, B, solver=s), 1)
        print(f"{solver:<18}{T / t:>12,.0f}{jitter(W):>12.2e}{res.mean():>15.3f}")
    if worst > 1e-8:
        raise SystemExit(f"batched NNLS objective differs from scipy's by {worst:.2e} (relative)")


if __name__ == "__main__":
    main()
