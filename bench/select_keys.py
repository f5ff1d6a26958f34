"""Benchmark (named select_keys.py: a script named select.py would shadow the standard library module): key-shape selection on a long synthetic take (Chuang & Bregler §4.2, Fig. 6).

A 5,000-frame, 68-point stabilized take built from the synthetic generator's
expressions (``synth.source_neutral``, ``source_deltas``, ``expression_curves``)
at pixel scale plus Gaussian landmark noise; no video. Reports each method's E
(eq. 5) at k = 10 and 20 (neutral frame 0 kept, as in the default config), the
run time of the whole evaluation curve (k = 2..40, every method), and, as the
peer measured in the same run, the paper's best heuristic (pca-extremes): the
ratio E(greedy) / E(pca-extremes). Also the screened greedy against exhaustive
greedy (every frame scored exactly) on a 400-frame take.

Run: ``python bench/select_keys.py [--frames 5000] [--noise 0.3]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from retarget_cli.methods.decomposition import reconstruction_error
from retarget_cli.methods.selection import evaluation_curve, greedy
from retarget_cli.synth import take as synth


def take(n_frames: int, noise: float, seed: int = 0) -> np.ndarray:
    curves = synth.expression_curves(n_frames, seed=seed)
    shapes = synth.source_neutral()[None] + np.einsum("te,eld->tld", curves, synth.source_deltas())
    pts = shapes * 120.0 + 160.0 + np.random.default_rng(seed).normal(scale=noise, size=shapes.shape)
    return pts.reshape(n_frames, -1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=5000)
    ap.add_argument("--noise", type=float, default=0.3, help="landmark noise, px")
    ap.add_argument("--k-max", type=int, default=40)
    args = ap.parse_args()
    X = take(args.frames, args.noise)
    print(f"take: {X.shape[0]} frames x {X.shape[1] // 2} points, noise {args.noise} px; neutral frame 0 kept")
    t0 = time.perf_counter()
    rows = evaluation_curve(X, args.k_max, k=20, include=(0,))
    t_curve = time.perf_counter() - t0
    t0 = time.perf_counter()
    f10 = greedy(X, 10, include=(0,), swap=True)
    t_swap10 = time.perf_counter() - t0
    rows.append({"curve": "greedy-swap", "k": 10, "error": reconstruction_error(X, X[f10])})
    at = {(r["curve"], r["k"]): r["error"] for r in rows}
    hull = [r for r in rows if r["curve"] == "convex-hull"][0]
    print("\n| method | E at k = 10 (px²) | E at k = 20 (px²) |\n|---|---|---|")
    for c in ("pca-extremes", "kmeans-2pc", "kmeans-3pc", "greedy", "greedy-swap"):
        print(f"| {c} | {at[(c, 10)]:,.0f} | {at[(c, 20)]:,.0f} |")
    print(f"| convex-hull (k = {hull['k']}, its own size) | {hull['error']:,.0f} | |")
    print(f"\nwhole evaluation curve k = 2..{args.k_max}, all methods: {t_curve:.1f} s "
          f"(greedy-swap at k = 20 only; greedy-swap at k = 10 separately: {t_swap10:.1f} s)")
    for k in (10, 20):
        r = at[("greedy", k)] / at[("pca-extremes", k)]
        print(f"k = {k}: E(greedy) / E(pca-extremes) = {r:.3f}  ({1 / r:.2f}x lower)")
        assert at[("greedy", k)] < at[("pca-extremes", k)], "greedy must beat pca-extremes"
    # Screening: the default (16 candidates scored exactly per step) against every frame scored.
    Y = take(400, args.noise, seed=1)
    t0 = time.perf_counter()
    gs = greedy(Y, 20, include=(0,))
    ts = time.perf_counter() - t0
    t0 = time.perf_counter()
    ge = greedy(Y, 20, include=(0,), screen=None)
    te = time.perf_counter() - t0
    for k in (10, 20):
        es, ee = reconstruction_error(Y, Y[gs[:k]]), reconstruction_error(Y, Y[ge[:k]])
        print(f"400 frames, k = {k}: screened greedy E = {es:,.1f}, exhaustive greedy E = {ee:,.1f} (ratio {es / ee:.3f})")
    print(f"400 frames, k = 20: screened {ts:.1f} s, exhaustive {te:.1f} s ({te / ts:.1f}x)")


if __name__ == "__main__":
    main()
