"""File handling of ``decompose``: ``landmarks.npz`` and ``keys.json`` in, ``weights.npz`` out."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..config import Command, Flag, Param, output_flag, validate_params
from ..errors import InputError
from ..io.atomic import check_not_input, write_text
from ..io.landmarks import LOST_CONFIDENCE, load_landmarks, peek_frames
from ..io.stagefiles import load_weights, read_keys, save_weights, weights_csv
from ..methods.decomposition import (
    FORMULATIONS,
    SOLVERS,
    cardinality,
    decompose,
    interpolate_lost,
    jitter,
    mean_acceleration,
    prefetch_kernel,
    row_residuals,
)
from ._common import Stage, _require
from ._neutral import neutral_from_keys

log = logging.getLogger(__name__)

#: Declared parameters of ``decompose`` (YAML validation, CLI options, manifests, docs/config.md).
PARAMS = [
    Param("landmarks", "input", str, help="landmarks.npz.", link="track.output"),
    Param("keys", "input", str, help="keys.json.", link="select.output"),
    Param("output", "output", str, "weights.npz", "Weights per region."),
    Param("csv", "output", str, None, "Also write the weights as CSV.", nullable=True),
    Param("solver", "setting", str, "temporal",
          "Solver: nnls (eq. 4), ls, bounded, ridge, ridge-clipped, temporal, temporal-causal, sparse, "
          "sequential.", choices=SOLVERS),
    Param("formulation", "setting", str, "whole",
          "whole (eq. 3), convex (weights sum to 1) or delta (relative to neutral_frame).",
          choices=FORMULATIONS),
    Param("alpha", "setting", float, None,
          "Regularisation of ridge, temporal, temporal-causal, sparse, relative to the keys' spread "
          "(null: the solver's default).", min=0, nullable=True),
    Param("upper", "setting", float, None,
          "Upper bound on every weight (bounded and ridge-clipped use 1 when null).", min=1e-6,
          nullable=True),
    Param("neutral_frame", "setting", int, "auto",
          "Neutral frame S_0 of formulation delta (a source frame number; must be a key of every region): auto takes the one "
          "keys.json records (select's neutral_frame), else finds the rest frame among the shared keys.",
          min=0, words=("auto",)),
    Param("confidence", "setting", bool, True, "Weight each landmark by its tracking confidence."),
    Param("lost_fraction", "setting", float, 0.5,
          "A region is lost in a frame when more than this fraction of its landmarks is lost; "
          "its weights there are interpolated.", min=0, max=1),
    Param("smooth_space", "setting", str, "shape",
          "What temporal and temporal-causal smooth: shape (the reconstructed landmarks, ||D2 W S||^2; "
          "alpha is then absolute) or weights (||D2 W||^2).", choices=("shape", "weights")),
    Param("robust", "setting", float, 1.0,
          "temporal only: release the smoothness penalty around frames whose excess residual (over the "
          "unsmoothed fit, in units of its median) exceeds this, so blinks keep their amplitude; 0: off.",
          min=0),
]


#: Row weight given to a frame without one measured landmark, so its solve stays defined (its weights are then
#: interpolated from its neighbours).
BLANK_WEIGHT = 1e-6


@validate_params(PARAMS)
def run_decompose(*, landmarks, keys, output, csv=None, solver="temporal", formulation="whole", alpha=None, upper=None,
                  neutral_frame="auto", confidence=True, lost_fraction=0.5, smooth_space="shape",
                  robust=1.0) -> list[Path]:
    """Weights over the key shapes for every frame and region; writes ``weights.npz``.

    Per region: landmarks with NaN coordinates and confidence 0 are lost;
    rows are weighted by confidence when *confidence* is true; frames where
    more than *lost_fraction* of the region's landmarks are lost (or fewer
    coordinates than weights remain) get weights interpolated from the
    neighbouring frames and are flagged in ``<region>_lost``. With
    ``formulation="delta"`` the weights are stored in whole-face form: the
    neutral key's column holds ``1 − Σ`` of the others, so ``apply`` needs no
    change (Lewis et al. 2005, §3).
    """

    landmarks, keys = _require(landmarks, "landmarks file"), _require(keys, "keys file")
    check_not_input(output, [landmarks, keys])
    kf = read_keys(keys)
    if solver in ("nnls", "bounded", "sparse") and formulation != "convex":  # a long take: load the kernel meanwhile
        n_keys = max((len(r["frames"]) for r in kf.regions.values()), default=0)
        prefetch_kernel((peek_frames(landmarks) or 0) * n_keys, weighted=confidence)
    lm = load_landmarks(landmarks)
    # not read here: a long take's other per-frame arrays are not held through the solves
    lm.points_raw = lm.head = lm.head_angles = lm.head_translation = lm.gaze = lm.gaze_valid = None
    frames, times = lm.timing()
    kf.resolve_rows(frames, landmarks)  # keys are named by source frame: their rows
    stab, conf = lm.stabilized, lm.confidence  # float32; a region's rows become float64 once, below
    neutral = neutral_from_keys(neutral_frame, kf, lm, landmarks=landmarks) if formulation == "delta" else None
    regions, extras, diagnostics = {}, {}, {}
    for name, reg in kf.regions.items():
        regions[name], extras[name], diagnostics[name] = _decompose_region(
            name, reg, lm, stab, conf, landmarks=landmarks, keys=keys, solver=solver, formulation=formulation,
            alpha=alpha, upper=upper, neutral=neutral, confidence=confidence,
            lost_fraction=lost_fraction, smooth_space=smooth_space, robust=robust)
    meta = {"solver": solver, "formulation": formulation, "alpha": alpha, "upper": upper,
            "smooth_space": smooth_space if solver in ("temporal", "temporal-causal") else None,
            "robust": robust if solver == "temporal" else None,
            "neutral_frame": None if neutral is None else neutral.label,
            "neutral": None if neutral is None else neutral.record, "confidence": confidence,
            "fps": lm.fps, "source_fps": lm.source_fps, "landmarks": Path(landmarks).name,
            "diagnostics": diagnostics}
    save_weights(output, regions, meta, extras, frames=frames, times=times)
    written = [Path(output)]
    if csv:
        write_text(csv, weights_csv(regions, lm.fps, frames, times))
        written.append(Path(csv))
    return written



def _decompose_region(name, reg, lm, stab, conf, *, landmarks, keys, solver, formulation, alpha, upper, neutral,
                      confidence, lost_fraction, smooth_space, robust):
    """One region's weights (T, K) with its lost frames interpolated; its extras and diagnostics.

    With formulation delta, *neutral* (:class:`~retarget_cli.stages._neutral.Neutral`) is S_0: its frame's
    key column holds 1 - the others' sum, and a calibration's shape stands in for that key's landmarks.

    Returns
    -------
    (W, key frames (source frame numbers), residuals), {"cardinality", "lost"}, diagnostics : tuple
    """

    T = lm.n_frames
    badp = [p for p in reg["points"] if p >= lm.n_points]
    if badp:
        raise InputError(f"{keys}: region {name!r} landmark {badp[0]} does not exist ({lm.n_points} points in {landmarks})")
    pts, frames = reg["points"], np.array(reg["rows"])
    label = dict(zip(reg["rows"], reg["frames"]))  # row -> source frame number, for messages
    # (a region of all the points in order needs no gather: at long takes every copy counts)
    every = list(pts) == list(range(lm.n_points))
    P = (stab if every else stab[:, pts]).astype(np.float64)
    C = (conf if every else conf[:, pts]).astype(np.float64)
    nan = ~np.isfinite(P).all(-1)
    if np.any(nan & (C > 0)):
        t, i = np.argwhere(nan & (C > 0))[0]
        raise InputError(f"{landmarks}: landmark {pts[i]} of region {name!r} is NaN in frame {lm.timing()[0][t]} "
                         f"but has confidence {C[t, i]:.3g}; expected finite coordinates or confidence 0")
    lost_pt = nan | (C <= LOST_CONFIDENCE)
    n_unknowns = len(frames) - (1 if formulation == "delta" else 0)
    if 2 * len(pts) < n_unknowns:
        raise InputError(f"{keys}: region {name!r} has {len(pts)} landmarks ({2 * len(pts)} coordinates) for "
                         f"{len(frames)} keys; expected at least {(n_unknowns + 1) // 2} landmarks")
    lost = (lost_pt.mean(1) > lost_fraction) | (2 * (~lost_pt).sum(1) < n_unknowns)
    if lost.all():
        raise InputError(f"{landmarks}: region {name!r} is lost in every frame")
    nan_keys = [label[int(f)] for f in frames if nan[f].any()]
    if nan_keys:
        raise InputError(f"{landmarks}: region {name!r} key frame {nan_keys[0]} has NaN landmarks; "
                         "a key shape needs every landmark")
    lost_keys = [label[int(f)] for f in frames if lost_pt[f].any()]
    if lost_keys:
        log.info("region %s: key frame %d has lost landmarks; its key shape may be inaccurate", name, lost_keys[0])
    X = (np.where(nan[..., None], 0.0, P) if nan.any() else P).reshape(T, -1)
    del P
    weight = np.repeat(np.where(lost_pt, 0.0, C if confidence else 1.0), 2, axis=1)
    del C
    blank = ~weight.any(1)  # a frame with no measurement at all (a gap in an image sequence): interpolated below;
    weight[blank] = BLANK_WEIGHT  # a vanishing weight keeps the per-frame solves defined without pulling a neighbour
    kw = {}
    K = X[frames]
    if formulation == "delta":
        if neutral.frame not in reg["rows"]:
            raise InputError(f"{keys}: region {name!r}: formulation 'delta' needs neutral_frame {neutral.label} "
                             f"among the key frames {reg['frames']} (set decompose.neutral_frame to one of them)")
        j = reg["rows"].index(neutral.frame)
        if neutral.shape is not None:  # a calibration's rest shape is the neutral key
            K = K.copy()
            K[j] = np.asarray(neutral.shape, dtype=np.float64)[pts].reshape(-1)
        kw["neutral"] = K[j]
    try:
        W, res = decompose(X, K, solver=solver, formulation=formulation, alpha=alpha, upper=upper,
                         confidence=None if np.all(weight == 1) else weight, smooth_space=smooth_space,
                         robust=robust, **kw)
    except ValueError as exc:
        raise InputError(f"{keys}: region {name!r}: {exc}") from exc
    if formulation == "delta":
        W[:, j] = 1.0 - (W.sum(1) - W[:, j])
    if lost.any():
        W = interpolate_lost(W, lost)
        log.warning("region %s: lost in %d of %d frames (first: %d); weights interpolated",
                    name, int(lost.sum()), T, int(lm.timing()[0][np.flatnonzero(lost)[0]]))
    if lost.any() or formulation == "delta":  # (else decompose's residual is this one already)
        res = row_residuals(X, W, K)
    card = cardinality(W)
    diagnostics = {  # 6 significant digits keep the JSON short and deterministic
        "mean_residual_px": float(f"{res[~lost].mean() / np.sqrt(len(pts)):.6g}"),
        "mean_cardinality": float(f"{card.mean():.6g}"),
        "jitter": float(f"{jitter(W):.6g}"),
        # mesh-space jitter: mean acceleration of the reconstructed landmarks, and of the input ones
        "shape_jitter_px": float(f"{mean_acceleration(W @ K):.6g}"),
        "input_jitter_px": float(f"{mean_acceleration(X[:, ~lost_pt.all(0).repeat(2)]):.6g}"),
        "lost_frames": int(lost.sum()),
    }
    log.info("region %s: %d frames, mean residual %.4g px, mean cardinality %.2f, jitter %.3g", name, T,
             diagnostics["mean_residual_px"], card.mean(), diagnostics["jitter"])
    return (W, np.array(reg["frames"], dtype=np.int64), res), {"cardinality": card, "lost": lost}, diagnostics


#: The pipeline stage (:mod:`retarget_cli.run.pipeline`).
STAGE = Stage(
    "decompose",
    "Non-negative weights over the key shapes for every frame (eq. 4).",
    PARAMS,
    run_decompose,
)


#: ``--summary/--no-summary`` of the command.
SUMMARY = Param("summary", "setting", bool, True,
                "Print a per-region table of residual, cardinality, jitter and lost frames after the file names.")


def _cli_decompose(values, out):
    kw = dict(values)
    summary = kw.pop("summary")
    return run_decompose(**kw), summary


def _show_decompose(result, out) -> None:
    written, summary = result
    for p in written:
        out.echo(str(p))
    if summary:
        diag = load_weights(written[0])[1].get("diagnostics", {})
        out.echo(f"{'region':<16}{'residual px':>12}{'cardinality':>12}{'jitter':>12}{'lost':>6}")
        for name, d in sorted(diag.items()):
            out.echo(f"{name:<16}{d['mean_residual_px']:>12.4f}{d['mean_cardinality']:>12.2f}"
                     f"{d['jitter']:>12.3g}{d['lost_frames']:>6d}")


#: ``decompose`` (the CLI builds it: :mod:`retarget_cli.cli.commands`).
COMMAND = Command(
    "decompose",
    """Decompose every frame into key-shape weights (non-negative by default, eq. 4).""",
    lambda: [*PARAMS, SUMMARY],
    (Flag("landmarks", argument=True, path="file"), Flag("keys", argument=True, path="file"),
     output_flag("weights.npz", "Weights file (weights.npz).", required=False),
     Flag("csv", path="file", show_default=False, help="Also write the weights as CSV."),
     "solver", "formulation", "alpha", "upper", "neutral_frame", "confidence", "lost_fraction", "smooth_space",
     "robust", "summary"),
    _cli_decompose,
    _show_decompose,
)
