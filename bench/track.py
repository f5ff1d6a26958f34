"""Benchmark: tracking speed against decode-only reading, and end-to-end accuracy.

Generates a synthetic take with ``retarget synth`` (ground truth known), then
measures in the same run:

- decode-only frames/s of the video (the peer: reading with OpenCV and nothing else);
- ``track`` (LK) frames/s on the same video, and the ratio;
- landmark error against the truth (mean, first and last 10 % of frames);
- the retargeted OBJ sequence's mean vertex error relative to the mean
  ground-truth expression displacement, after ``retarget run``.

Run: ``python bench/track.py [--frames 600] [--size 320x320] [--seed 0]``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from retarget_cli.config import load_config
from retarget_cli.io.atomic import load_npz
from retarget_cli.io.obj import read_obj
from retarget_cli.io.video import VideoReader
from retarget_cli.pipeline import run_pipeline, stage_params
from retarget_cli.synth import write_take


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--size", default="320x320")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        write_take(d, n_frames=args.frames, size=(w, h), seed=args.seed)
        t0 = time.perf_counter()
        with VideoReader(d / "face.mp4") as r:
            n = sum(1 for _ in r)
        decode = time.perf_counter() - t0
        cfg = load_config(d / "config.yaml", stage_params())
        t0 = time.perf_counter()
        run_pipeline(cfg, stop="track")
        track = time.perf_counter() - t0
        run_pipeline(cfg)
        got, truth = load_npz(d / "out" / "landmarks.npz"), load_npz(d / "truth_landmarks.npz")
        err = np.linalg.norm(got["points"] - truth["points"], axis=2).mean(1)
        tenth = max(len(err) // 10, 1)
        target = load_npz(d / "truth.npz")["target"].astype(np.float64)
        neutral = read_obj(d / "target" / "neutral.obj").vertices
        frames = sorted((d / "out" / "frames").glob("frame_*.obj"))
        out = np.stack([read_obj(f).vertices for f in frames])
        rel = np.linalg.norm(out - target, axis=2).mean() / np.linalg.norm(target - neutral, axis=2).mean()
    print(f"synthetic take: {n} frames at {w}x{h}, seed {args.seed}")
    print(f"{'reader':<24}{'frames/s':>10}")
    print(f"{'decode only (OpenCV)':<24}{n / decode:>10.1f}")
    print(f"{'track (lk)':<24}{n / track:>10.1f}")
    print(f"track throughput vs decode-only: {decode / track:.3f}x")
    print(f"landmark error px: mean {err.mean():.3f}, first 10% {err[:tenth].mean():.3f}, "
          f"last 10% {err[-tenth:].mean():.3f} (drift ratio {err[-tenth:].mean() / err[:tenth].mean():.2f})")
    print(f"retargeted mesh error: {100 * rel:.1f}% of the mean expression displacement")


if __name__ == "__main__":
    main()
