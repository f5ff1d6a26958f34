"""``retarget batch``: shots of a plan (:mod:`retarget_cli.batch.plan`) as Dask tasks, and the batch summary.

Each shot is one task that runs the normal pipeline (:func:`retarget_cli.run.pipeline.run_pipeline`)
into its own output folder, exactly as ``retarget run CONFIG --set ...`` would:
its manifests make a rerun skip finished stages, so a task that a dead worker
left half done simply runs again (on another worker) and finishes it. Tasks go
to a :class:`distributed.LocalCluster` of single-threaded worker processes or
to an existing scheduler, through the same :func:`run_batch`. Files are read
and written where the shot list names them: nothing is copied to the workers
(a cluster needs the paths on a shared filesystem).

Written into the batch folder: ``batch.json`` (one summary per shot) and
``index.html`` (a table linking each shot's ``report.html`` when it has one).
"""

from __future__ import annotations

import html
import json
import logging
import os
import socket
import time
from pathlib import Path

from .. import __version__
from ..config import Param, load_config
from ..errors import InputError, MissingExtraError, RetargetError
from ..io.atomic import load_npz, write_json, write_text
from ..io.stagefiles import load_weights
from ..run.pipeline import ORDER, manifest_path, resolve, run_pipeline, stage_params
from ..run.runfiles import locate_run
from ..see.report import write_report
from .plan import gaps_cell

log = logging.getLogger(__name__)

#: Declared options of ``batch``.
PARAMS = [
    Param("shots", "input", str, help="Shot list (YAML or CSV)."),
    Param("jobs", "setting", int, None,
          "Worker processes of the local cluster, one thread each (default: the CPUs available).", min=1, max=1024,
          nullable=True),
    Param("scheduler", "setting", str, None,
          "Use an existing Dask scheduler (tcp://host:8786, or a scheduler file .json) instead of a local cluster; "
          "every path must be visible to its workers.", nullable=True),
    Param("retries", "setting", int, 1,
          "Further attempts of a shot that failed (or whose worker died) before it is reported.", min=0, max=100),
    Param("only", "setting", list, None, "Only the shots whose name matches (fnmatch, e.g. 'take0*'). Repeatable.",
          nullable=True),
    Param("force", "setting", bool, False, "Rerun every stage of the selected shots even if it is up to date."),
    Param("emit_commands", "setting", bool, False,
          "Print one self-contained 'retarget run ...' per pending shot (for a farm manager) and exit."),
    Param("report", "setting", bool, False,
          "Also write each shot's report.html (needs the extra report), linked from index.html."),
    Param("output_dir", "output", str, None,
          "Batch folder for batch.json and index.html, and default parent of the shot folders (default: the shot "
          "list's output_dir, else 'out' beside it).", nullable=True),
]

#: Environment of LocalCluster workers: one thread for BLAS, OpenMP, numba and OpenCV (one shot per core).
WORKER_ENV = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
    "VECLIB_MAXIMUM_THREADS": "1",
    "NUMBA_NUM_THREADS": "1",
}
#: Marks the files this module writes, so that it never overwrites one it did not create.
MARK = "retarget batch"


def _distributed():
    try:
        import distributed
    except ImportError:
        raise MissingExtraError("retarget batch needs Dask: install the extra batch "
                          "(pip install 'retarget[batch]', included by make)") from None
    return distributed


# ----------------------------------------------------------------------------- the task (runs on a worker)


def shot_metrics(cfg) -> dict:
    """Frames, mean tracking confidence, the take's gaps, and the decomposition's mean residual and jitter of a run.

    Reads the run's ``landmarks.npz`` and ``weights.npz`` (``None`` for what
    is missing). *gaps* is the list ``track`` recorded (where, how long, why:
    :func:`retarget_cli.methods.gaps.describe_gaps`), None for landmarks without a ``found`` flag. *residual_px* and *jitter* are the means over the regions of
    the decompose stage's diagnostics (``mean_residual_px``, ``jitter``).
    """
    import numpy as np


    out = {"frames": None, "confidence": None, "residual_px": None, "jitter": None, "gaps": None}
    if "track" in cfg.sections:
        lm = Path(resolve(cfg, "track")["output"])
        if lm.is_file():
            data = load_npz(lm)
            out["frames"] = int(data["points"].shape[0])
            if "confidence" in data:
                out["confidence"] = float(f"{float(np.mean(data['confidence'])):.6g}")
            out["gaps"] = _gaps_of(data)
    if "decompose" in cfg.sections:
        w = Path(resolve(cfg, "decompose")["output"])
        if w.is_file():
            _, meta = load_weights(w)
            diag = list((meta.get("diagnostics") or {}).values())
            if diag:
                out["residual_px"] = float(f"{np.mean([d['mean_residual_px'] for d in diag]):.6g}")
                out["jitter"] = float(f"{np.mean([d['jitter'] for d in diag]):.6g}")
    return out


def _gaps_of(data: dict) -> list | None:
    """The gaps ``landmarks.npz`` records in its meta (None when it has no ``found`` flag)."""
    if "found" not in data:
        return None
    try:
        gaps = json.loads(str(data["meta"].ravel()[0])).get("gaps") if "meta" in data else None
    except (ValueError, AttributeError):
        gaps = None
    return gaps if isinstance(gaps, list) else []


def _report_stale(cfg, report: Path) -> bool:
    if not report.is_file():
        return True
    mdir = cfg.output_dir / ".retarget"
    newest = max((p.stat().st_mtime_ns for p in mdir.glob("*.json")), default=0)
    return report.stat().st_mtime_ns < newest


def run_shot(name: str, config: str, overrides: list, *, force: bool = False, cache: bool = True,
             report: bool = False) -> dict:
    """Run one shot's pipeline (the Dask task; also callable directly).

    Exactly ``retarget run CONFIG --set OVERRIDE ... [--force]``, with BLAS,
    OpenMP and OpenCV limited to one thread. With *report*, also writes
    ``<output_dir>/report.html`` when it is missing or older than a manifest.

    Returns
    -------
    dict
        ``name``, ``output_dir``, ``stages`` (stage to ``{"status": "ran" |
        "skipped", "seconds"}``: this run's time for a stage that ran, its
        manifest's for one skipped), ``seconds`` (wall time), ``worker``
        (host and pid) and :func:`shot_metrics`.

    Raises
    ------
    RetargetError, ValueError, OSError
        As ``retarget run`` does; the batch records the message.
    """
    import cv2
    from threadpoolctl import threadpool_limits


    cv2.setNumThreads(1)
    t0 = time.perf_counter()
    with threadpool_limits(1):
        cfg = load_config(config, stage_params(), overrides)
        done = run_pipeline(cfg, force=force, cache=cache)
        stages = {}
        for n, status, _ in done:
            man = json.loads(manifest_path(cfg, n).read_text(encoding="utf-8"))
            stages[n] = {"status": status, "seconds": man.get("seconds")}
        result = {"name": name, "output_dir": str(cfg.output_dir), "stages": stages, **shot_metrics(cfg)}
        if report:
            rep = cfg.output_dir / "report.html"
            if _report_stale(cfg, rep):

                write_report(locate_run(cfg.output_dir), rep)
    result["seconds"] = round(time.perf_counter() - t0, 3)
    result["worker"] = f"{socket.gethostname()}:{os.getpid()}"
    return result


# ----------------------------------------------------------------------------- the client side


def quiet_dask(level: int = logging.ERROR) -> None:
    """Set the level of Dask's loggers (``distributed`` sets its own to INFO on import)."""
    import dask

    _distributed()
    dask.config.set({"logging.distributed": logging.getLevelName(level).lower()})
    for name in list(logging.root.manager.loggerDict):
        if name == "distributed" or name.startswith(("distributed.", "bokeh", "tornado")):
            logging.getLogger(name).setLevel(level)


def local_cluster(jobs: int):
    """A LocalCluster of *jobs* single-threaded worker processes with :data:`WORKER_ENV` (no dashboard port clash)."""
    distributed = _distributed()
    return distributed.LocalCluster(n_workers=jobs, threads_per_worker=1, processes=True, env=dict(WORKER_ENV),
                                    dashboard_address=":0", silence_logs=logging.WARNING)


def connect(scheduler: str):
    """A Client of an existing scheduler: ``tcp://host:8786`` or a scheduler file (``.json``)."""
    distributed = _distributed()
    try:
        if scheduler.endswith(".json") and Path(scheduler).is_file():
            return distributed.Client(scheduler_file=scheduler, timeout="30s")
        return distributed.Client(scheduler, timeout="30s")
    except OSError as exc:
        raise InputError(f"--scheduler {scheduler}: cannot connect ({exc})") from None


def dashboard_link(client) -> str | None:
    """The dashboard's address when the scheduler serves one (needs bokeh), else None."""
    try:
        if "dashboard" in (client.scheduler_info().get("services") or {}):
            return client.dashboard_link
    except (OSError, KeyError, AttributeError):  # pragma: no cover - informational only
        pass
    return None


def _error_text(exc: BaseException) -> str:
    distributed = _distributed()
    if isinstance(exc, distributed.KilledWorker):
        return "the worker running this shot died (KilledWorker)"
    if isinstance(exc, (RetargetError, ValueError)) and str(exc):
        msg = str(exc)
    elif isinstance(exc, OSError) and exc.filename:
        msg = f"{exc.filename}: {exc.strerror}"
    else:
        msg = f"{type(exc).__name__}: {exc}"
    return " ".join(msg.split())


def run_batch(client, shots: list, *, retries: int = 1, force: bool = False, cache: bool = True,
              report: bool = False, on_event=None) -> list[dict]:
    """Run *shots* (:class:`retarget_cli.batch.plan.Shot`) as independent tasks on *client*; never stops on a failure.

    A shot that fails (an error, or its worker dying more often than the
    scheduler allows) is submitted again up to *retries* times, then
    reported. Results come back in the order of *shots*.

    Parameters
    ----------
    client : distributed.Client
    shots : list of Shot
    retries : int
        Further attempts after a failure.
    on_event : callable, optional
        Called as ``on_event(kind, result, counts)`` with *kind* ``"done"``,
        ``"failed"`` or ``"retry"``, the shot's summary, and ``counts`` (dict:
        ``done``, ``failed``, ``running``, ``total``, ``eta`` seconds or None).

    Returns
    -------
    list of dict
        Per shot: :func:`run_shot`'s result plus ``status`` (``"done"`` or
        ``"failed"``), ``attempts`` and ``error`` (None or one line).
    """
    distributed = _distributed()
    t0 = time.perf_counter()

    def submit(shot, attempt):
        return client.submit(run_shot, shot.name, str(shot.config), list(shot.overrides), force=force, cache=cache,
                             report=report, key=f"shot-{shot.name}-{attempt}-{os.getpid()}-{time.time_ns()}",
                             pure=False)

    attempts = {s.name: 1 for s in shots}
    by_future = {}
    pending = distributed.as_completed()
    for s in shots:
        f = submit(s, 1)
        by_future[f.key] = s
        pending.add(f)
    results: dict = {}
    counts = {"done": 0, "failed": 0, "running": len(shots), "total": len(shots), "eta": None}
    for fut in pending:
        shot = by_future.pop(fut.key)
        if fut.status == "finished":
            res = dict(fut.result(), status="done", attempts=attempts[shot.name], error=None)
            kind = "done"
        else:
            try:
                exc = fut.exception()
            except BaseException as lost:  # cancelled: the scheduler lost the task
                exc = lost
            res = {"name": shot.name, "output_dir": str(shot.output_dir), "stages": {}, "frames": None,
                   "confidence": None, "residual_px": None, "jitter": None, "gaps": None, "seconds": None,
                   "status": "failed", "attempts": attempts[shot.name], "error": _error_text(exc)}
            if attempts[shot.name] <= retries:
                attempts[shot.name] += 1
                f = submit(shot, attempts[shot.name])
                by_future[f.key] = shot
                pending.add(f)
                kind = "retry"
            else:
                kind = "failed"
        fut.release()
        if kind != "retry":
            results[shot.name] = res
            counts[kind] += 1
            counts["running"] = len(shots) - counts["done"] - counts["failed"]
            finished = counts["done"] + counts["failed"]
            counts["eta"] = (time.perf_counter() - t0) / finished * counts["running"] if counts["running"] else 0.0
        if on_event is not None:
            on_event(kind, res, dict(counts))
    return [results[s.name] for s in shots]


# ----------------------------------------------------------------------------- summary files


def _ours(path: Path, test) -> None:
    if path.exists() and not test(path):
        raise InputError(f"{path}: exists and was not written by retarget batch; refusing to overwrite it "
                         "(choose another batch folder)")


def _is_our_json(path: Path) -> bool:
    try:
        return json.loads(path.read_text(encoding="utf-8")).get("written_by") == MARK
    except (OSError, ValueError, AttributeError):
        return False


def _is_our_html(path: Path) -> bool:
    try:
        with open(path, encoding="utf-8") as fh:
            return f"<!-- {MARK} -->" in fh.read(4096)
    except (OSError, UnicodeDecodeError):
        return False


def previous_results(batch_dir) -> dict:
    """Shot name to its summary in an earlier ``batch.json`` of *batch_dir* (empty when none)."""
    path = Path(batch_dir) / "batch.json"
    if not path.is_file() or not _is_our_json(path):
        return {}
    return {r["name"]: r for r in json.loads(path.read_text(encoding="utf-8")).get("shots", [])}


def write_summary(batch_dir, shot_list, results: list) -> list[Path]:
    """Write ``batch.json`` and ``index.html`` into *batch_dir* atomically; returns both paths.

    ``index.html`` links each shot's ``report.html`` when the shot's output
    folder has one, else the folder itself.

    Raises
    ------
    InputError
        If either file exists and was not written by ``retarget batch``.
    """

    batch_dir = Path(batch_dir)
    js, index = batch_dir / "batch.json", batch_dir / "index.html"
    _ours(js, _is_our_json)
    _ours(index, _is_our_html)
    for r in results:
        rep = Path(r["output_dir"]) / "report.html"
        r["report"] = str(rep) if rep.is_file() else None
    counts = {k: sum(r["status"] == k for r in results) for k in ("done", "failed")}
    write_json(js, {"written_by": MARK, "version": __version__, "shot_list": str(Path(shot_list).resolve()),
                    "counts": counts, "shots": results})
    write_text(index, index_html(batch_dir, shot_list, results))
    return [js, index]


def index_html(batch_dir, shot_list, results: list) -> str:
    """The HTML index page: one row per shot, linking its ``report.html`` (relative links)."""

    esc = html.escape
    stage_cols = [n for n in ORDER if any(n in (r.get("stages") or {}) for r in results)]
    rows = []
    for r in results:
        target = r.get("report") or r["output_dir"]
        href = os.path.relpath(target, batch_dir).replace(os.sep, "/")
        label = "report" if r.get("report") else "folder"
        st = r.get("stages") or {}
        cells = [f'<td><a href="{esc(href)}">{esc(r["name"])}</a> ({label})</td>',
                 f'<td class="{esc(r["status"])}">{esc(r["status"])}</td>']
        for k in ("attempts", "frames", "confidence", "residual_px", "jitter", "seconds"):
            v = r.get(k)
            cells.append(f"<td>{'-' if v is None else esc(f'{v:.4g}' if isinstance(v, float) else str(v))}</td>")
        cells.append(f"<td>{esc(gaps_cell(r.get('gaps'), detail=True))}</td>")
        for n in stage_cols:
            s = st.get(n)
            text = "-" if s is None else "skip" if s["status"] == "skipped" else f"{s['seconds']:.2f}"
            cells.append(f"<td>{text}</td>")
        cells.append(f"<td>{esc(r.get('error') or '')}</td>")
        rows.append("<tr>" + "".join(cells) + "</tr>")
    head = "".join(f"<th>{esc(h)}</th>" for h in
                   ["shot", "status", "tries", "frames", "confidence", "residual px", "jitter", "seconds", "gaps",
                    *[f"{n} s" for n in stage_cols], "error"])
    n_fail = sum(r["status"] == "failed" for r in results)
    return f"""<!DOCTYPE html>
<!-- {MARK} -->
<html><head><meta charset="utf-8"><title>retarget batch: {esc(Path(shot_list).name)}</title>
<style>body{{font-family:sans-serif;margin:2em}}table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:3px 8px;text-align:left}}.failed{{color:#b00;font-weight:bold}}
.done{{color:#070}}</style></head><body>
<h1>retarget batch: {esc(Path(shot_list).name)}</h1>
<p>{len(results)} shots, {len(results) - n_fail} done, {n_fail} failed.</p>
<table><tr>{head}</tr>
{chr(10).join(rows)}
</table></body></html>
"""
