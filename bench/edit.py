"""Benchmark: direct-manipulation edits (Lewis & Anjyo 2010, eq. 3) on a large rig.

A 100-slider, 25,000-vertex synthetic rig with overlapping shapes
(``synth.overlapping_rig``). Reports the per-rig precomputation, and for 1, 10
and 50 pins the time of one edit (a new pin set: gather B̄, build and factor H,
solve the bounded QP) and of one drag (same pins, new targets: solve only),
against peers measured in the same run on the same edits:

- ``naive``: rebuild the normal equations from the full D each edit (a 0/1
  weight per coordinate over all 75,000 rows) and solve with
  ``scipy.optimize.lsq_linear`` (BVLS);
- ``L-BFGS-B``: ``scipy.optimize.minimize`` on eq. 3 with the gathered B̄;
- ``BVLS``: ``lsq_linear`` on the stacked system ``[B̄; √α I; √μ I]``.

Every peer's optimum is checked against ours. Also compares dense and CSR
storage of D for evaluation. Run: ``python bench/edit.py [--edits N]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from retarget_cli.methods.blas import small_blas
from retarget_cli.methods.editing import DEFAULT_ALPHA, DEFAULT_MU, DirectManipulation
from retarget_cli.methods.rig import BlendshapeRig
from retarget_cli.synth.take import overlapping_rig


def timed(fn, repeat=1):
    best = []
    out = None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best.append(time.perf_counter() - t)
    return out, float(np.median(best))


def one_edit(rig, dense, verts, target, drag, w0, a, mu):
    """Times of (our edit, our drag, naive, L-BFGS-B, BVLS), max |w - peer|, bounded solves used."""
    from scipy.optimize import lsq_linear, minimize

    n, N = rig.n_sliders, rig.n_vertices

    def ours():
        dm = DirectManipulation(rig, verts)
        return dm, dm.solve_targets(target, w0)

    (dm, w), t_edit = timed(ours)
    _, t_drag = timed(lambda: dm.solve_targets(drag, w0))
    rows = rig.rows(verts)
    b = target.ravel() - rig.f0[rows]

    def naive():
        c = np.zeros(3 * N)
        c[rows] = 1.0
        mf = np.zeros(3 * N)
        mf[rows] = b
        Dd = dense.D
        H = Dd.T @ (c[:, None] * Dd) + (a + mu) * np.eye(n)
        q = Dd.T @ (c * mf) + a * w0
        R = np.linalg.cholesky(H).T
        y = np.linalg.solve(R.T, q)
        return lsq_linear(R, y, bounds=(0, 1), method="bvls", tol=1e-12).x

    B = rig.block(rows)

    def f(x):
        res = B @ x - b
        return res @ res + a * np.sum((x - w0) ** 2) + mu * x @ x

    def g(x):
        return 2 * (B.T @ (B @ x - b)) + 2 * a * (x - w0) + 2 * mu * x

    def lbfgs():
        return minimize(f, w0, jac=g, bounds=[(0, 1)] * n, method="L-BFGS-B",
                        options={"ftol": 1e-15, "gtol": 1e-10, "maxiter": 20000}).x

    def bvls():
        B_ = rig.block(rig.rows(verts))
        A = np.vstack([B_, np.sqrt(a) * np.eye(n), np.sqrt(mu) * np.eye(n)])
        rhs = np.concatenate([b, np.sqrt(a) * w0, np.zeros(n)])
        return lsq_linear(A, rhs, bounds=(0, 1), method="bvls", tol=1e-12).x

    with small_blas():
        wn, t_naive = timed(naive)
        wl, t_lbfgs = timed(lbfgs)
        wb, t_bvls = timed(bvls)
    diff = max(np.abs(w - wn).max(), np.abs(w - wb).max(), np.abs(w - wl).max())
    return (t_edit, t_drag, t_naive, t_lbfgs, t_bvls), diff, dm.qp.n_bounded


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--edits", type=int, default=20, help="edits per pin count")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    r, t_gen = timed(lambda: overlapping_rig(n_shapes=100, grid=(125, 200), seed=args.seed))
    rig, t_build = timed(lambda: BlendshapeRig(r["vertices"], r["deltas"], r["names"]))
    _, t_gram = timed(rig.gram)
    n, N = rig.n_sliders, rig.n_vertices
    print(f"rig: {N} vertices, {n} sliders, D density {rig.density:.3f} -> {'CSR' if rig.sparse else 'dense'}")
    print(f"precomputation: rig layout {t_build * 1e3:.0f} ms, D^T D (attenuation) {t_gram * 1e3:.0f} ms")

    dense = BlendshapeRig(r["vertices"], r["deltas"], r["names"], storage="dense")
    sparse = BlendshapeRig(r["vertices"], r["deltas"], r["names"], storage="sparse")
    rng = np.random.default_rng(args.seed)
    W = rng.uniform(0, 1, (64, n))
    for label, w in (("1 frame", W[0]), ("64 frames", W)):
        _, td = timed(lambda w=w: dense.evaluate(w), 5)
        _, ts = timed(lambda w=w: sparse.evaluate(w), 5)
        print(f"evaluate {label}: dense {td * 1e3:.2f} ms, CSR {ts * 1e3:.2f} ms (CSR {td / ts:.2f}x dense)")

    a, m_ = DEFAULT_ALPHA * rig.scale**2, DEFAULT_MU * rig.scale**2
    print("\n| pins | edit (new pins) median / max | drag (same pins) median | naive full-D | L-BFGS-B | BVLS stacked |"
          " bounded solves (edits + drags) | max |w - peer| |")
    print("|---|---|---|---|---|---|---|---|")
    # One untimed edit first: lazy imports and first-call set-up are not edit time.
    v0 = rng.choice(N, 1, replace=False)
    one_edit(rig, dense, v0, rig.evaluate(W[0])[v0], rig.evaluate(W[1])[v0], W[2], a, m_)
    for k in (1, 10, 50):
        t_edit, t_drag, t_naive, t_lbfgs, t_bvls, diff, nb = [], [], [], [], [], 0.0, 0
        for _ in range(args.edits):
            verts = rng.choice(N, k, replace=False)
            w0 = rng.uniform(0, 1, n)
            w_goal = np.clip(w0 + rng.normal(0, 0.3, n), 0, 1)
            target = rig.evaluate(w_goal)[verts] + rng.normal(0, 0.02, (k, 3))
            drag = target + rng.normal(0, 0.02, (k, 3))
            times, d, bounded = one_edit(rig, dense, verts, target, drag, w0, a, m_)
            for lst, t in zip((t_edit, t_drag, t_naive, t_lbfgs, t_bvls), times):
                lst.append(t)
            diff, nb = max(diff, d), nb + bounded
        med = lambda x: float(np.median(x)) * 1e3  # noqa: E731
        e = med(t_edit)
        print(f"| {k} | {e:.2f} / {max(t_edit) * 1e3:.2f} ms | {med(t_drag):.2f} ms | {med(t_naive):.1f} ms "
              f"({med(t_naive) / e:.0f}x) | {med(t_lbfgs):.2f} ms ({med(t_lbfgs) / e:.1f}x) | {med(t_bvls):.2f} ms "
              f"({med(t_bvls) / e:.1f}x) | {nb}/{2 * args.edits} | {diff:.1e} |")
    print("\nratios in brackets: peer time / our edit time (same edits, same run); target: edit <= 10 ms")


if __name__ == "__main__":
    main()
