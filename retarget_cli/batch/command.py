"""``retarget batch``: every shot of a shot list through the pipeline on Dask, as a declared command.

The plan (shot list, output folders, pending shots) is :mod:`.plan`; running
the shots on a cluster and the summary files are :mod:`.engine`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time

from ..config import Command, Flag
from ..errors import RetargetError, UsageError
from ..io.atomic import guard_writes
from . import engine
from .plan import format_table, load_plan, pending


def _cpus() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _on_event(out):
    def on_event(kind, res, c):
        eta = "" if c["eta"] is None else f", ETA {time.strftime('%H:%M:%S', time.gmtime(c['eta']))}"
        what = {"done": f"done in {res.get('seconds')} s", "failed": f"FAILED: {res['error']}",
                "retry": f"failed, retrying (attempt {res['attempts'] + 1}): {res['error']}"}[kind]
        out.say(f"[{c['done'] + c['failed']}/{c['total']}] {res['name']} {what}  "
                f"({c['done']} done, {c['failed']} failed, {c['running']} to go{eta})")

    return on_event


def _run_on_cluster(values, chosen, out) -> list:
    scheduler = values["scheduler"]
    engine.quiet_dask(logging.INFO if out.debug else logging.ERROR)
    with contextlib.ExitStack() as stack:
        if scheduler is not None:
            client = stack.enter_context(engine.connect(scheduler))
        else:
            cluster = stack.enter_context(engine.local_cluster(values["jobs"] or _cpus()))
            client = stack.enter_context(cluster.get_client())
        link = engine.dashboard_link(client)
        n_workers = len(client.scheduler_info().get("workers", {}))
        out.say(f"batch: {len(chosen)} shots on {n_workers} workers ({scheduler or 'local cluster'})"
                + (f", dashboard {link}" if link else ""))
        return engine.run_batch(client, chosen, retries=values["retries"], force=values["force"],
                                report=values["report"], on_event=_on_event(out))


def _cli_batch(values, out):
    plan = load_plan(values["shots"], output_dir=values["output_dir"])
    chosen = plan.select(values["only"])
    if values["emit_commands"]:
        for shot in chosen:
            if pending(shot, force=values["force"]):
                out.echo(shot.command(force=values["force"]))
        return None
    if values["scheduler"] is not None and values["jobs"] is not None:
        raise UsageError("--jobs sets the size of the local cluster; it cannot be used with --scheduler",
                         bad_value=False)
    results = _run_on_cluster(values, chosen, out)
    earlier = engine.previous_results(plan.output_dir)
    names = {r["name"] for r in results}
    merged = [next(r for r in results if r["name"] == s.name) if s.name in names else earlier[s.name]
              for s in plan.shots if s.name in names or s.name in earlier]
    with guard_writes(roots=[plan.output_dir], inputs=[plan.path], label=f"the batch folder {plan.output_dir}"):
        written = engine.write_summary(plan.output_dir, plan.path, merged)
    return results, written


def _show_batch(result, out) -> None:
    if result is None:  # --emit-commands printed the commands
        return
    results, written = result
    out.echo(format_table(results))
    for p in written:
        out.echo(str(p))
    failed = [r["name"] for r in results if r["status"] == "failed"]
    if failed:
        raise RetargetError(f"{len(failed)} of {len(results)} shots failed: {', '.join(failed)}")


#: ``batch`` (the CLI builds it: :mod:`retarget_cli.cli.commands`); it guards its batch folder itself.
COMMAND = Command(
    "batch",
    """Run every shot of the shot list SHOTS (YAML or CSV) through the pipeline on Dask.

    Each shot runs `retarget run` into its own output folder (resumable by its
    manifests); a failed shot is retried, then reported, and never stops the
    others. Writes batch.json and index.html into the batch folder and a
    summary table on stdout. See README, "Many shots".
    """,
    lambda: engine.PARAMS,
    (Flag("shots", argument=True, path="file"),
     Flag("jobs", decls=("-j", "--jobs"), show_default=False),
     Flag("scheduler", metavar="ADDRESS", show_default=False),
     "retries",
     Flag("only", multiple=True, metavar="PATTERN", show_default=False, default=None),
     Flag("force", decls=("--force",), show_default=False),
     Flag("emit_commands", decls=("--emit-commands",), show_default=False),
     Flag("report", decls=("--report",), show_default=False),
     Flag("output_dir", decls=("-o", "--output-dir"), path="folder", show_default=False)),
    _cli_batch,
    _show_batch,
    guarded=False,
)
