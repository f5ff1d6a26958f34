"""Memory that must not grow with the take's length (issues #31 item 4, #33), measured cheaply: the traced
allocations (``tracemalloc``) of one step at two lengths of a short synthetic take. The figures on real long
takes are ``bench/long_take.py``'s and ``bench/gaps.py --long``'s (docs/benchmarks.md)."""

import tracemalloc

import cv2
import numpy as np

from retarget_cli.io.editfiles import read_animation, write_animation
from retarget_cli.methods.tracking.detect import FlowFusion


def _traced_peak(fn) -> int:
    """Bytes *fn* allocated at its peak, beyond what was allocated when it started."""
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        fn()
        return tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()


def test_an_animation_csv_is_written_a_row_at_a_time(tmp_path):
    """57 sliders a frame: the whole text held before writing would be ~1.5 KB a frame (lines, joined, encoded)."""
    names = [f"s{j}" for j in range(57)]
    peaks = {}
    for T in (1500, 3000):
        W = np.random.default_rng(T).uniform(0, 1, (T, 57))
        frames, times = np.arange(T), np.arange(T) / 30.0
        path = tmp_path / f"c{T}.csv"
        peaks[T] = _traced_peak(lambda p=path, w=W, f=frames, t=times: write_animation(p, names, w, f, t))
        back = read_animation(path)
        assert np.abs(back[1] - W).max() <= 5e-7 and len(back[1]) == T
    per_frame = (peaks[3000] - peaks[1500]) / 1500
    assert per_frame < 64, f"writing the CSV grows by {per_frame:.0f} bytes a frame"


def test_the_fusion_smoother_runs_in_place():
    """The Rauch-Tung-Striebel pass over a segment allocates nothing per frame (the forward state is smoothed in
    place; stacking the per-frame state would be ~6 KB a frame for 68 points)."""
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (160, 160)).astype(np.float32), (0, 0), 2.0).astype(np.uint8)
    P0 = rng.uniform(50, 110, (68, 2))
    P0[36], P0[39], P0[42], P0[45] = (55, 70), (70, 70), (90, 70), (105, 70)
    T = 300
    fuser = FlowFusion()
    fwd = np.stack([fuser.step(img, P0 + rng.normal(0, 1.0, P0.shape), np.ones(68)) for _ in range(T)])
    out = {}
    peak = _traced_peak(lambda: out.setdefault("xs", fuser.smooth()))
    xs = out["xs"]
    assert xs.shape == (T, 68, 2) and np.array_equal(xs[-1], fwd[-1]) and not np.array_equal(xs[0], fwd[0])
    assert np.abs(xs - P0).std() < np.abs(fwd - P0).std()  # smoothed: steadier than the forward pass
    assert peak < 64 * 1024, f"smoothing {T} frames allocated {peak / 1024:.0f} KB"


def test_stabilized_landmarks_in_float32_chunks_are_the_float64_ones_rounded(monkeypatch):
    """``estimate_head(dtype=float32)`` maps a long take a chunk at a time: the float64 result rounded, to the bit."""
    from retarget_cli.methods.tracking import head as head_mod

    monkeypatch.setattr(head_mod, "CHUNK", 64)  # several chunks and a short tail on a short take
    rng = np.random.default_rng(3)
    T = 300
    P = rng.normal(size=(68, 2))[None] * 40 + 200 + np.cumsum(rng.normal(size=(T, 1, 2)), axis=0) \
        + rng.normal(size=(T, 68, 2))
    C = rng.uniform(0.2, 1.0, (T, 68))
    h64, s64 = head_mod.estimate_head(P, C)
    h32, s32 = head_mod.estimate_head(P, C, dtype=np.float32)
    assert s32.dtype == np.float32 and np.array_equal(h32, h64)
    assert s32.tobytes() == s64.astype(np.float32).tobytes()
