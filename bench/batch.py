"""Benchmark: `retarget batch` on 1 and 2 Dask workers against a plain `retarget run` loop.

Eight synthetic takes (``retarget synth``, 300 frames) are each run three
ways, measured in the same session on the same takes, every stage forced:

- loop: ``retarget run CONFIG --force`` once per take, one after the other
  (what a user does without ``batch``);
- ``retarget batch shots.yaml --jobs 1 --force`` (one worker process);
- ``retarget batch shots.yaml --jobs 2 --force`` (two worker processes).

Wall times include the cluster's start and stop. A first ``retarget run`` warms
numba's on-disk cache so that no side pays its compilation. Printed: shots per
minute of each, the scaling ratio from 1 to 2 workers (target >= 1.7 on two
idle cores) and the engine's overhead per shot against the loop (1 worker vs
the loop; target <= 5 %). The outputs of the batch must equal the loop's, byte
for byte. On a machine shared with other jobs the ratio measures what the
cores had to spare.

Run: ``python bench/batch.py [--shots 8] [--frames 300] [--size 256x256]``.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BIN = Path(sys.executable).parent


def retarget(*args, capture=True):
    exe = BIN / "retarget"
    return subprocess.run([str(exe), *map(str, args)], check=True, capture_output=capture, text=True)


def tree(d: Path) -> dict:
    return {p.relative_to(d).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(d.rglob("*"))
            if p.is_file() and ".retarget" not in p.parts and not p.name.endswith(".part")}


def timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shots", type=int, default=8)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--size", default="256x256")
    ap.add_argument("--dir", default=None, help="Working folder (default: a temporary one).")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-batch-", dir=a.dir) as tmp:
        root = Path(tmp)
        names = [f"take{i:02d}" for i in range(a.shots)]
        t = timed(lambda: [retarget("synth", root / n, "--frames", a.frames, "--size", a.size, "--seed", i)
                           for i, n in enumerate(names)])
        print(f"synth: {a.shots} takes of {a.frames} frames ({a.size}) in {t:.1f} s")
        lines = ["output_dir: batch", "shots:"] + [f"  - {{name: {n}, config: {n}/config.yaml}}" for n in names]
        (root / "shots.yaml").write_text("\n".join(lines) + "\n")
        retarget("run", root / names[0] / "config.yaml")  # warm numba's cache
        loop = timed(lambda: [retarget("run", root / n / "config.yaml", "--force") for n in names])
        ref = {n: tree(root / n / "out") for n in names}
        env_jobs = {}
        for jobs in (1, 2):
            env_jobs[jobs] = timed(lambda j=jobs: retarget("-q", "batch", root / "shots.yaml", "--jobs", j, "--force"))
            same = all(tree(root / n / "out") == ref[n] for n in names)
            print(f"batch --jobs {jobs}: outputs identical to the loop's: {same}")
            if not same:
                raise SystemExit("batch outputs differ from the loop's")
    n = a.shots
    print(f"{'way':<18}{'seconds':>9}{'shots/min':>11}")
    for label, s in (("run loop", loop), ("batch --jobs 1", env_jobs[1]), ("batch --jobs 2", env_jobs[2])):
        print(f"{label:<18}{s:>9.1f}{60 * n / s:>11.2f}")
    print(f"scaling 1 -> 2 workers: {env_jobs[1] / env_jobs[2]:.2f}x (target >= 1.7)")
    print(f"engine overhead vs the run loop: {100 * (env_jobs[1] - loop) / loop:+.1f} % "
          f"({(env_jobs[1] - loop) / n:+.2f} s per shot; target <= 5 %)")
    print(f"cpus available: {len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else os.cpu_count()}, "
          f"load average at the end: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
