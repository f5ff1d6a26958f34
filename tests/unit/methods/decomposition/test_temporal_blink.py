"""A 3-frame blink in a synthetic take survives the default landmark filter and the temporal solver."""

import inspect

import numpy as np

from retarget_cli.methods.decomposition import decompose
from retarget_cli.methods.regions import REGION_PRESETS_68
from retarget_cli.methods.selection import select_keys
from retarget_cli.stages import run_decompose
from retarget_cli.stages._landmark_filter import FILTER_DEFAULTS, apply_filter
from retarget_cli.synth.take import (
    EXPRESSIONS,
    apply_similarity,
    expression_curves,
    head_motion,
    place_neutral,
    source_deltas,
    source_neutral,
    target_rig,
)

EYES = REGION_PRESETS_68["brows-eyes"]
LIDS = [37, 38, 40, 41, 43, 44, 46, 47]   # upper and lower eyelids of the 68-point layout


def _take(T=300, seed=2, noise=0.3):
    curves = expression_curves(T, seed=seed)
    bl, br = EXPRESSIONS.index("blink_l"), EXPRESSIONS.index("blink_r")
    curves[:, [bl, br]] = 0.0
    for t0 in (60, 200):                      # two blinks of 3 frames: one for the keys, one to measure
        curves[t0:t0 + 3, bl] = curves[t0:t0 + 3, br] = [0.6, 1.0, 0.6]
    norm = source_neutral()[None] + np.einsum("te,eld->tld", curves, source_deltas())
    P = place_neutral((320, 320))
    stab = norm @ P[:, :2].T + P[:, 2]
    head = head_motion(T, size=(320, 320), seed=seed)
    pts = apply_similarity(head, stab) + np.random.default_rng(seed).normal(0, noise, stab.shape)
    return curves, head, pts


def _amplitude(x, truth, t0=200):
    """Least-squares scale of the blink displacement at its peak (against 2 frames before / after) onto the truth's."""
    a, p, b = t0 - 2, t0 + 1, t0 + 4
    dt = truth[p] - 0.5 * (truth[a] + truth[b])
    dg = x[p] - 0.5 * (x[a] + x[b])
    return float(np.sum(dg * dt) / np.sum(dt * dt))


def test_three_frame_blink_keeps_90_percent_through_filter_and_temporal_solver():
    from retarget_cli.methods.tracking.head import estimate_head

    curves, head, pts = _take()
    conf = np.ones(pts.shape[:2])
    filt, raw, _ = apply_filter(pts, conf, fps=30.0, settings=dict(FILTER_DEFAULTS), where="take", anchors=[0])
    # the filter alone: the eyelid landmarks keep the blink (against the noise-free points)
    clean = _take(noise=0.0)[2]
    assert _amplitude(filt[:, LIDS], clean[:, LIDS]) >= 0.9
    _, stab = estimate_head(filt, conf)
    X = stab[:, EYES].reshape(len(stab), -1)
    keys = select_keys(X, 8, method="greedy", include=(0,))
    robust = inspect.signature(run_decompose).parameters["robust"].default   # decompose's default
    W, _ = decompose(X, X[keys], solver="temporal", formulation="delta", neutral=X[0], robust=robust)
    # the character: the synthetic target rig driven by the weights over its keys posed at the true curves
    rig = target_rig(seed=2)
    K = rig["vertices"][None] + np.einsum("ke,end->knd", curves[keys], rig["deltas"])
    truth = rig["vertices"][None] + np.einsum("te,end->tnd", curves, rig["deltas"])
    Wf = W.copy()
    Wf[:, list(keys).index(0)] += 1.0 - W.sum(1)   # delta weights in whole-face form, as decompose stores them
    got = np.einsum("tk,knd->tnd", Wf, K)
    bl = EXPRESSIONS.index("blink_l")
    lid = np.linalg.norm(rig["deltas"][bl], axis=1) > 0.2 * np.linalg.norm(rig["deltas"][bl], axis=1).max()
    assert _amplitude(got[:, lid], truth[:, lid]) >= 0.9
    # without event preservation the same solver flattens the blink
    W0, _ = decompose(X, X[keys], solver="temporal", formulation="delta", neutral=X[0], robust=0.0)
    W0[:, list(keys).index(0)] += 1.0 - W0.sum(1)
    assert _amplitude(np.einsum("tk,knd->tnd", W0, K)[:, lid], truth[:, lid]) < 0.85


def _one_point_blink(seed):
    """Frames (T, 40) of 20 points: three smooth expressions moving every point, and a 3-frame event of one point."""
    rng = np.random.default_rng(seed)
    T = 200
    t = np.arange(T)
    B = np.zeros((4, 40))
    B[0, 1] = 3.0                                   # the event's key moves one point 3 px
    B[1:] = rng.normal(0, 2.0, (3, 40))
    W = np.zeros((T, 4))
    W[:, 1:] = 0.5 + 0.4 * np.sin(t[:, None] / np.array([17.0, 23.0, 31.0]))
    W[100:103, 0] = [0.6, 1.0, 0.6]
    return W @ B + rng.normal(0, 0.3, (T, 40)), B, W


def test_an_event_of_one_point_is_released_by_the_per_point_test():
    from retarget_cli.methods.decomposition import temporal_events

    peaks = {}
    for pf in (np.inf, 5.0):  # inf: the region-wide test alone
        got = [temporal_events(S, B, lam=1.0, robust=1.0, point_factor=pf) for S, B, _ in map(_one_point_blink, range(6))]
        peaks[pf] = np.mean([g[101, 0] for g in got])
        smooth_err = np.mean([np.abs(g[:, 1:] - W[:, 1:]).mean()
                              for g, (_, _, W) in zip(got, map(_one_point_blink, range(6)))])
        assert smooth_err < 0.02                     # the smooth expressions are followed either way
    # the region test misses the event (a third of it smoothed away); the per-point test keeps it
    assert peaks[np.inf] < 0.8
    assert abs(peaks[5.0] - 1.0) < 0.1


def test_per_frame_weighted_solves_match_box_qp_frame_by_frame():
    """temporal_events' unsmoothed reference W0 with confidences: every frame solved together, as one at a time."""
    from retarget_cli.methods.decomposition import box_qp
    from retarget_cli.methods.decomposition.temporal import _per_frame

    rng = np.random.default_rng(2)
    B = rng.normal(size=(6, 40))
    S = rng.normal(size=(50, 40))
    C = rng.uniform(0.0, 1.0, size=(50, 40))
    W0 = _per_frame(S, B, C, 0.1, chunk=16)
    one = np.concatenate([box_qp((B * C[t]) @ B.T, ((S[t] * C[t]) @ B.T)[None], lower=0.0, upper=0.1)
                          for t in range(len(S))])
    np.testing.assert_allclose(W0, one, rtol=0, atol=1e-10)
    assert (W0 == 0).any() and (W0 == 0.1).any()  # bounds active: the QP, not a plain solve
