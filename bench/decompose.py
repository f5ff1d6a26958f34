"""Benchmark: decomposing a long take into key-shape weights.

Compares ``retarget``'s batched NNLS (:func:`retarget_cli.methods.decomposition.nnls_batched`),
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

Real tracking gives every landmark its own confidence in every frame, so each
frame has its own Hessian ``B C_t Bᵀ``. Two more rows measure that case, with
confidences drawn in [0.7, 1] for every point of every frame (both coordinates
of a point share it, as ``track`` writes them), K = 22:

* in-process (``--weighted-frames``, default 5,000):
  ``nnls_batched(..., confidence=C)`` (numpy iteration and compiled kernel,
  each forced, and the default choice by size) against ``scipy.optimize.nnls``
  per frame on the rows scaled by ``√c``, formed before the timing;
* whole process (``--process-frames``, default 50,000): ``retarget decompose``
  on a ``landmarks.npz`` + ``keys.json`` against a ``python`` process that
  loads the same file and runs the same scipy loop, writing its weights.

Both check the objective ``Σ_d c_{t,d} r_{t,d}²`` against scipy's (same
relative gap as above, floor ``1e-10·Σ c s²``). ``--quick`` runs the weighted
rows only.

``--accuracy`` instead measures the end-to-end retargeting error of each
decomposition setting on synthetic takes (``retarget synth`` then
``retarget run``, error as in ``tests/e2e``: mean vertex error over mean true
expression displacement), the table behind the README's choice of defaults.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np


def take(T: int, seed: int = 0, noise: float = 0.5) -> np.ndarray:
    from retarget_cli.synth import take as synth

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
            "from retarget_cli.methods.decomposition import nnls_batched; "
            "nnls_batched(np.ones((3, 4)), np.eye(4)[:2], compiled=True); print(time.perf_counter() - t)")
    base = ("import time, numpy as np; t = time.perf_counter(); "
            "from retarget_cli.methods.decomposition import nnls_batched; "
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

    from retarget_cli.cli.commands import main as cli
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


def confidences(T: int, L: int, seed: int = 1) -> np.ndarray:
    """(T, 2L) row weights: one confidence in [0.7, 1] per point and frame, shared by its x and y."""
    return np.random.default_rng(seed).uniform(0.7, 1.0, (T, L)).repeat(2, axis=1)


def weighted_gap(X, B, C, W, ref_f) -> float:
    f = np.sum(C * (X - W @ B) ** 2, axis=1)
    return float(np.max((f - ref_f) / np.maximum(ref_f, 1e-10 * np.sum(C * X**2, axis=1))))


def weighted_row(T: int, repeat: int, K: int = 22) -> float:
    """In-process weighted NNLS against the scipy loop; returns the worst objective gap."""
    from scipy.optimize import nnls

    from retarget_cli.methods.decomposition.boxqp import _KERNEL_MIN_WORK_WEIGHTED, nnls_batched
    from retarget_cli.methods.selection import select_keys

    X = take(T)
    B = X[select_keys(X, K, include=(0,))]
    C = confidences(T, X.shape[1] // 2)
    rw = np.sqrt(C)
    A = [np.ascontiguousarray(B.T * r[:, None]) for r in rw]  # the peer's weighted rows, formed untimed
    b = X * rw
    nnls_batched(X[:100], B, confidence=C[:100], compiled=True)  # load the kernel outside the timing
    ts, ref = best_of(lambda: np.array([nnls(A[t], b[t])[0] for t in range(T)]), repeat)
    ref_f = np.sum(C * (X - ref @ B) ** 2, axis=1)
    print(f"Weighted NNLS, confidences in [0.7, 1] on every point: T = {T}, K = {K}, D = {X.shape[1]}; "
          f"best of {repeat}")
    print(f"{'path':<34}{'frames/s':>12}{'vs scipy':>10}{'max rel. objective gap':>25}")
    print(f"{'scipy.optimize.nnls per frame':<34}{T / ts:>12,.0f}{1:>9.1f}x{0:>25.2e}")
    worst = 0.0
    default = "compiled" if T * K >= _KERNEL_MIN_WORK_WEIGHTED else "numpy"
    for name, comp in (("retarget, numpy iteration", False), ("retarget, compiled kernel", True),
                       (f"retarget, default ({default})", None)):
        t, W = best_of(lambda comp=comp: nnls_batched(X, B, confidence=C, compiled=comp), repeat)
        gap = weighted_gap(X, B, C, W, ref_f)
        worst = max(worst, gap)
        print(f"{name:<34}{T / t:>12,.0f}{ts / t:>9.1f}x{gap:>25.2e}")
    print(f"(the default uses the compiled kernel from T*K >= {_KERNEL_MIN_WORK_WEIGHTED:,}: a fresh process "
          f"spends about half a second loading it)")
    return worst


PEER = """
import sys, numpy as np
from scipy.optimize import nnls
d = np.load(sys.argv[1]); frames = [int(f) for f in sys.argv[3].split(",")]
X = d["stabilized"].astype(np.float64).reshape(len(d["stabilized"]), -1)
rw = np.sqrt(np.repeat(d["confidence"].astype(np.float64), 2, axis=1))
BT = X[frames].T
W = np.array([nnls(BT * r[:, None], x * r)[0] for x, r in zip(X, rw)])
np.savez(sys.argv[2], W=W)
"""


def process_row(T: int, repeat: int, K: int = 22) -> float:
    """Whole-process ``retarget decompose`` against a scipy-loop process; returns the objective gap."""
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    from retarget_cli.io.landmarks import Landmarks, save_landmarks
    from retarget_cli.io.stagefiles import load_weights, write_keys
    from retarget_cli.methods.selection import select_keys

    X = take(T)
    L = X.shape[1] // 2
    frames = [int(f) for f in select_keys(X, K, include=(0,))]
    C = confidences(T, L)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        pts = X.reshape(T, L, 2).astype(np.float32)
        head = np.tile(np.array([[1.0, 0, 0], [0, 1.0, 0]], dtype=np.float32), (T, 1, 1))
        save_landmarks(tmp / "landmarks.npz", Landmarks(points=pts, confidence=C[:, ::2].astype(np.float32),
                                                        head=head, stabilized=pts))
        write_keys(tmp / "keys.json", tmp / "landmarks.npz",
                   {"face": {"points": list(range(L)), "method": "bench", "frames": frames, "error": 0.0}})
        exe = Path(sys.executable).with_name("retarget")
        ours = [str(exe), "-q", "decompose", str(tmp / "landmarks.npz"), str(tmp / "keys.json"),
                "-o", str(tmp / "out" / "weights.npz"), "--no-summary"]
        peer = [sys.executable, "-c", PEER, str(tmp / "landmarks.npz"), str(tmp / "peer.npz"),
                ",".join(map(str, frames))]
        run = lambda cmd: subprocess.run(cmd, check=True, capture_output=True)  # noqa: E731
        t_ours, _ = best_of(lambda: run(ours), repeat)
        t_peer, _ = best_of(lambda: run(peer), repeat)
        W = load_weights(tmp / "out" / "weights.npz")[0]["face"][0]
        ref = np.load(tmp / "peer.npz")["W"]
    Xf = pts.reshape(T, -1).astype(np.float64)
    B, Cf = Xf[frames], np.repeat(C[:, ::2].astype(np.float32).astype(np.float64), 2, axis=1)
    gap = weighted_gap(Xf, B, Cf, W, np.sum(Cf * (Xf - ref @ B) ** 2, axis=1))
    print(f"\nWhole process, {T:,} frames, K = {K}, confidences in [0.7, 1]: `retarget decompose` {t_ours:.2f} s, "
          f"scipy nnls loop process {t_peer:.2f} s: {t_peer / t_ours:.1f}x; max rel. objective gap {gap:.2e} "
          f"(best of {repeat}; load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores: both processes "
          f"wait for a core on a busy machine)")
    return gap


def main() -> None:
    from scipy.optimize import nnls

    from retarget_cli.methods.decomposition import cardinality, decompose, jitter, nnls_batched
    from retarget_cli.methods.decomposition.boxqp import _KERNEL_MIN_WORK
    from retarget_cli.methods.selection import select_keys

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=10_000)
    ap.add_argument("--keys", default="10,22,40")
    ap.add_argument("--scipy-frames", type=int, default=None)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--accuracy", action="store_true", help="End-to-end error of each decompose setting instead.")
    ap.add_argument("--weighted-frames", type=int, default=5000)
    ap.add_argument("--process-frames", type=int, default=50_000)
    ap.add_argument("--quick", action="store_true", help="Only the two weighted rows.")
    args = ap.parse_args()
    if args.accuracy:
        accuracy(SETTINGS)
        return
    wgap = max(weighted_row(args.weighted_frames, args.repeat), process_row(args.process_frames, min(args.repeat, 2)))
    if wgap > 1e-8:
        raise SystemExit(f"weighted batched NNLS objective differs from scipy's by {wgap:.2e} (relative)")
    if args.quick:
        return
    print()
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
