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


def test_an_npz_is_streamed_to_its_file_not_built_in_memory(tmp_path):
    """``savez`` deflates each member into the temporary file as it goes: before, the archive, a copy of it and
    two copies of the largest member were held (~5 KB a frame for a take's landmarks); the bytes are unchanged."""
    import io
    import zipfile

    from retarget_cli.io import atomic

    def in_memory(arrays) -> bytes:  # the former implementation: the whole archive built in a buffer
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
            for name, arr in arrays.items():
                info = zipfile.ZipInfo(f"{name}.npy", date_time=atomic._ZIP_EPOCH)
                info.compress_type, info.external_attr = zipfile.ZIP_DEFLATED, 0o644 << 16
                member = io.BytesIO()
                np.lib.format.write_array(member, np.asanyarray(arr), allow_pickle=False)
                zf.writestr(info, member.getvalue())
        return buf.getvalue()

    peaks = {}
    for T in (2000, 4000):
        rng = np.random.default_rng(T)
        arrays = {"points": rng.normal(200, 30, (T, 68, 2)).astype(np.float32),
                  "confidence": rng.uniform(0, 1, (T, 68)).astype(np.float32),
                  "fortran": np.asfortranarray(rng.normal(size=(T, 3))), "meta": np.array('{"a": 1}'),
                  "empty": np.zeros((0, 68, 2), np.float32)}
        path = tmp_path / f"t{T}.npz"
        peaks[T] = _traced_peak(lambda p=path, a=arrays: atomic.savez(p, a))
        assert path.read_bytes() == in_memory(arrays)
    per_frame = (peaks[4000] - peaks[2000]) / 2000
    assert per_frame < 64, f"writing the npz grows by {per_frame:.0f} bytes a frame"


def test_rows_given_a_block_at_a_time_or_spilled_to_a_file_save_as_the_array(tmp_path):
    """``NpyChunks`` (rows made while saving) and ``RowSpill`` (rows kept in a file beside the output) give the
    bytes of the whole float32 array; the spill file is a ``.part`` beside the output, removed on close."""
    from retarget_cli.io.atomic import PART_RE, NpyChunks, RowSpill, savez

    rng = np.random.default_rng(5)
    P = rng.normal(200, 30, (1000, 68, 2))
    C = rng.uniform(0, 1, (1000, 68))
    savez(tmp_path / "whole.npz", {"points": P.astype(np.float32), "confidence": C.astype(np.float32)})
    out = tmp_path / "out" / "landmarks.npz"
    with RowSpill(out, P.shape, np.float32) as spill:
        for a in range(0, len(P), 300):
            spill.write(P[a:a + 300])
        assert spill.path.parent == out.parent and PART_RE.match(spill.path.name)
        savez(out, {"points": spill.chunks(block=128),
                    "confidence": NpyChunks(C.shape, np.float32, lambda a, b: C[a:b], block=77)})
    assert not spill.path.exists() and sorted(p.name for p in out.parent.iterdir()) == ["landmarks.npz"]
    assert out.read_bytes() == (tmp_path / "whole.npz").read_bytes()


def test_gap_confidences_held_in_place_are_held_confidence_and_undone():
    """``track`` fits the head with each gap frame holding its source frame's confidences written into the
    take's own array (no copy of it), then puts the gap rows back as they were."""
    from retarget_cli.stages.track import _hold_gap_confidence, held_confidence

    rng = np.random.default_rng(2)
    found = np.ones(40, bool)
    found[:3] = found[10:15] = found[30:] = False
    conf = np.where(found[:, None], rng.uniform(0.2, 1, (40, 68)), 0.0)
    before = conf.copy()
    undo = _hold_gap_confidence(conf, found)
    assert np.array_equal(conf, held_confidence(before, found))
    conf[undo[0]] = undo[1]
    assert np.array_equal(conf, before)
    assert _hold_gap_confidence(conf, np.ones(40, bool)) is None


def test_the_head_alone_and_stabilized_rows_are_estimate_heads():
    """``fit_head`` is ``estimate_head``'s head; ``stabilized_rows`` over any blocks its stabilized landmarks."""
    from retarget_cli.methods.tracking.head import estimate_head, fit_head, invert_similarity, stabilized_rows

    rng = np.random.default_rng(4)
    T = 500
    P = rng.normal(size=(68, 2))[None] * 40 + 200 + np.cumsum(rng.normal(size=(T, 1, 2)), axis=0) \
        + rng.normal(size=(T, 68, 2))
    C = rng.uniform(0.2, 1.0, (T, 68))
    head, stab = estimate_head(P, C)
    assert np.array_equal(fit_head(P, C), head)
    inv = invert_similarity(head)
    rows = np.concatenate([stabilized_rows(inv, P, a, min(T, a + 123)) for a in range(0, T, 123)])
    assert np.array_equal(rows, stab)


def test_the_console_script_fixes_the_mmap_threshold():
    """On glibc the console script keeps the mmap threshold fixed (mallopt accepts it); elsewhere it is a no-op."""
    import platform

    from retarget_cli.entry import fix_mmap_threshold

    assert fix_mmap_threshold() is (platform.libc_ver()[0] == "glibc")


def test_greedy_ranks_a_long_take_in_blocks_of_frames(monkeypatch):
    """select's screen ranks 512 candidates against the take ``RANK_COLUMNS`` frames at a time: a take of more
    frames than that grows by what it holds per frame (its rows, weights, errors), not by a (512, T) product
    and its temporaries (~7 KB a frame when formed whole), and the keys are the same."""
    from retarget_cli.methods import selection

    rng = np.random.default_rng(0)

    def take(T, D=20):  # every frame distinct: each is a candidate
        return rng.normal(size=(T, 3)) @ rng.normal(size=(3, D)) + 0.05 * rng.normal(size=(T, D))

    X1, X4 = take(1000), take(4000)
    whole = selection.greedy(X4, 8, include=(0,))  # RANK_COLUMNS (8,192) above T: one block of columns
    monkeypatch.setattr(selection, "RANK_COLUMNS", 256)
    peaks, keys = {}, {}
    for T, X in ((1000, X1), (4000, X4)):
        peaks[T] = _traced_peak(lambda X=X, T=T: keys.setdefault(T, selection.greedy(X, 8, include=(0,))))
    assert np.array_equal(keys[4000], whole)
    per_frame = (peaks[4000] - peaks[1000]) / 3000
    assert per_frame < 3000, f"greedy's selection grows by {per_frame:.0f} bytes a frame"


def test_an_animation_csv_is_read_into_an_array_not_lists_of_floats(tmp_path):
    """``read_animation`` parses each row into a preallocated array: holding every row as a list of Python floats
    first was ~3.7 KB a frame for 57 sliders (measured); the values are those written."""
    names = [f"s{j}" for j in range(57)]
    peaks = {}
    for T in (1500, 6000):
        W = np.random.default_rng(T).uniform(0, 1, (T, 57))
        path = tmp_path / f"c{T}.csv"
        write_animation(path, names, W, np.arange(T), np.arange(T) / 30.0)
        out = {}
        peaks[T] = _traced_peak(lambda p=path, o=out: o.setdefault("a", read_animation(p)))
        back = out["a"]
        assert back[0] == names and np.abs(back[1] - W).max() <= 5e-7 and np.array_equal(back[2], np.arange(T))
    per_frame = (peaks[6000] - peaks[1500]) / 4500
    assert per_frame < 2500, f"reading the CSV grows by {per_frame:.0f} bytes a frame"


def test_delta_pose_writes_a_segment_into_the_takes_array():
    """``delta_pose(out=...)``: the sliders written into the caller's rows (no second (T, n) copy), as returned
    without it; a wrong shape or dtype is refused."""
    import pytest

    from retarget_cli.errors import ShapeError
    from retarget_cli.methods.rig import BlendshapeRig
    from retarget_cli.methods.rigpose import delta_pose
    from retarget_cli.synth.take import source_neutral

    n = source_neutral()
    V = np.column_stack([n[:, 0], -n[:, 1], np.zeros(68)])
    D = np.zeros((2, 68, 3))
    D[0, [37, 38], 1] = V[[41, 40], 1] - V[[37, 38], 1]
    D[1, 17:22, 1] = 0.05
    rig = BlendshapeRig(V, D, ["eyeBlink_R", "browOuterUp_R"])
    rng = np.random.default_rng(1)
    truth = rng.uniform(0, 1, (40, 2))
    X = np.stack([rig.evaluate(c) for c in truth])
    Y = 140.0 * np.stack([X[:, :, 0], -X[:, :, 1]], axis=2) + 150.0 + 0.2 * rng.standard_normal((40, 68, 2))
    Y0 = 140.0 * np.column_stack([V[:, 0], -V[:, 1]]) + 150.0
    kw = dict(regions={"brows-eye": list(range(17, 22)) + list(range(36, 42))}, sparsity=0.0, ridge=1e-6,
              contact_weight=0.0, smooth=1.0)
    alone = delta_pose(rig, np.arange(68), Y0, Y[10:30], **kw)["w"]
    W = np.full((40, 2), 7.0)
    res = delta_pose(rig, np.arange(68), Y0, Y[10:30], out=W[10:30], **kw)
    assert np.shares_memory(res["w"], W) and np.array_equal(W[10:30], alone)
    assert (W[:10] == 7.0).all() and (W[30:] == 7.0).all() and np.abs(alone[:, 1] - truth[10:30, 1]).max() < 0.1
    with pytest.raises(ShapeError, match="out"):
        delta_pose(rig, np.arange(68), Y0, Y[10:30], out=np.zeros((20, 2), np.float32), **kw)


def test_the_rest_shape_holds_one_float64_copy_of_the_take():
    """``rest_shape`` (``neutral_frame: auto``) of a float32 take: one float64 copy, scaled in place, and the
    members' medians partitioned in place; before, the input's float64 copy, its finite copy and the scaled
    copy were held together (3.6 KB a frame traced on a looped d9 take, 2.65 KB after)."""
    from retarget_cli.methods.neutral import rest_shape
    from retarget_cli.synth.take import source_neutral

    rng = np.random.default_rng(6)
    n = source_neutral()[:, :2] * 100.0
    peaks, rests = {}, {}
    for T in (1500, 6000):
        P = (n + rng.normal(0, 1.0, (T, 68, 2))).astype(np.float32)
        C = rng.uniform(0.5, 1.0, (T, 68)).astype(np.float32)
        peaks[T] = _traced_peak(lambda P=P, C=C, T=T: rests.setdefault(T, rest_shape(P, C)))
        assert rests[T].members.sum() > 0 and np.isfinite(rests[T].distance[rests[T].usable]).all()
    per_frame = (peaks[6000] - peaks[1500]) / 4500
    assert per_frame < 3100, f"the rest shape grows by {per_frame:.0f} bytes a frame"
