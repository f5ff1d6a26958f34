"""File handling of ``solve-rig``: a rig with correctives and meshes in, slider weights out (inverse rig)."""

from __future__ import annotations

import logging
from pathlib import Path

from ..config import Command, Flag, Param, output_flag, validate_params
from ..io.atomic import check_not_input
from ..io.rig.inverse import (
    check_quadratic_rig,
    read_meshes,
    read_quadratic_rig,
    save_inverse_weights,
    write_metrics_csv,
)
from ..methods.inverse_rig import (
    CARDINALITY_THRESHOLD,
    DEFAULT_ALPHA,
    DEFAULT_MAX_ITER,
    DEFAULT_SOLVER,
    DEFAULT_TOL,
    SOLVERS,
    solve,
)
from ._common import NO_CACHE, NO_CACHE_FLAG, _no_progress, command_cache_dir

log = logging.getLogger(__name__)


#: Declared parameters of ``solve-rig``.
PARAMS = [
    Param("rig", "input", str, help="rig.yaml with corrective shapes."),
    Param("meshes", "input", str,
          help="A directory of frame_*.obj, a glob such as 'scans/*.obj', or an NPZ with positions (T, N, 3)."),
    Param("output", "output", str, help="Slider curves (NPZ: curves, names, per-frame metrics)."),
    Param("solver", "setting", str, DEFAULT_SOLVER,
          "lbfgsb (fast, eq. 8), mm (Racković et al. Alg. 2), bounded, ridge (eq. 6), sequential (eq. 7).",
          choices=SOLVERS),
    Param("alpha", "setting", float, DEFAULT_ALPHA,
          "Sparsity weight alpha of eq. 8 (squared mesh units per unit weight).", min=0),
    Param("tol", "setting", float, DEFAULT_TOL,
          "mm/lbfgsb: stop when an iteration lowers the objective by less than tol x it.", min=0,
          min_open=True),
    Param("max_iter", "setting", int, DEFAULT_MAX_ITER, "mm/lbfgsb: iteration cap per frame.", min=1),
    Param("metrics", "output", str, None, "Also write per-frame metrics with wall times as CSV.", nullable=True),
]


@validate_params(PARAMS)
def run_solve_rig(*, rig, meshes, output, solver=DEFAULT_SOLVER, alpha=DEFAULT_ALPHA, tol=DEFAULT_TOL,
                  max_iter=DEFAULT_MAX_ITER, metrics=None,
                  progress=_no_progress, cache_dir=None) -> tuple[list[Path], dict]:
    """Fit slider weights of a rig with correctives to a mesh sequence (Racković et al. 2023, eq. 8).

    The output paths, ``rig.yaml``, the rig's vertex counts and the meshes
    to fit are checked before the rig's OBJs are parsed; *cache_dir* keeps
    the parsed rig (:func:`~retarget_cli.io.rig.inverse.read_quadratic_rig`).

    Returns
    -------
    written : list of Path
    summary : dict
        Means over frames of rmse, cardinality, objective, iterations and seconds, plus sizes.
    """

    rig_files, n_vertices = check_quadratic_rig(rig)
    inputs = [*rig_files, meshes]
    check_not_input(output, inputs)
    if metrics is not None:
        check_not_input(metrics, inputs + [output])
    X, sources = read_meshes(meshes, n_vertices)
    qrig, _ = read_quadratic_rig(rig, cache_dir=cache_dir)
    log.info("solve-rig: %d frames, %d vertices, %d shapes, %d correctives, solver %s",
             len(X), qrig.n_vertices, qrig.n_shapes, qrig.n_pairs, solver)
    with progress(len(X), "solve-rig") as bar:
        res = solve(qrig, X, solver=solver, alpha=alpha, tol=tol, max_iter=max_iter, callback=bar.update)
    summary = {
        "frames": len(X), "vertices": qrig.n_vertices, "shapes": qrig.n_shapes, "correctives": qrig.n_pairs,
        "rmse": float(res.rmse.mean()), "cardinality": float(res.cardinality.mean()),
        "objective": float(res.objective.mean()), "iterations": float(res.iterations.mean()),
        "seconds_per_frame": float(res.seconds.mean()),
    }
    meta = {"solver": solver, "alpha": alpha, "tol": tol, "max_iter": max_iter,
            "cardinality_threshold": CARDINALITY_THRESHOLD, "rig": Path(rig).name,
            "summary": {k: v for k, v in summary.items() if k != "seconds_per_frame"}}
    save_inverse_weights(output, res, qrig.names, sources, meta)
    written = [Path(output)]
    if metrics is not None:
        write_metrics_csv(metrics, res, sources)
        written.append(Path(metrics))
    return written, summary


def _cli_solve_rig(values, out):
    kw = dict(values)
    cache_dir = command_cache_dir(kw["output"], kw.pop("no_cache"))
    written, summary = run_solve_rig(**kw, progress=out.progress, cache_dir=cache_dir)
    return written, summary, kw["solver"], kw["alpha"]


def _show_solve_rig(result, out) -> None:
    written, s, solver, alpha = result
    out.echo(f"{s['frames']} frames, {s['vertices']} vertices, {s['shapes']} shapes, "
             f"{s['correctives']} correctives; solver {solver}, alpha {alpha:g}")
    out.echo(f"mean rmse {s['rmse']:.6g}  cardinality {s['cardinality']:.2f}  objective {s['objective']:.6g}  "
             f"iterations {s['iterations']:.1f}  seconds/frame {s['seconds_per_frame']:.4f}")
    for p in written:
        out.echo(str(p))


#: ``solve-rig`` (the CLI builds it: :mod:`retarget_cli.cli.commands`).
COMMAND = Command(
    "solve-rig",
    """Slider weights in [0, 1] of RIG (with corrective shapes) that reproduce MESHES.

    MESHES is a directory of frame_*.obj, a glob such as 'scans/*.obj', or an
    NPZ with positions (T, N, 3).
    """,
    lambda: [*PARAMS, NO_CACHE],
    (Flag("rig", argument=True, path="file"), Flag("meshes", argument=True),
     output_flag(None, "Slider curves (NPZ: curves, names, per-frame metrics)."),
     "solver", "alpha", "tol", "max_iter", Flag("metrics", path="file"), NO_CACHE_FLAG),
    _cli_solve_rig,
    _show_solve_rig,
)
