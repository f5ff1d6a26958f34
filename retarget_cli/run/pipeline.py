"""The pipeline's stages in order, and the up-to-date-aware runner behind ``retarget run``.

Each stage is declared beside its runner (``STAGE`` in
:mod:`retarget_cli.stages`): its inputs, outputs and settings
(:class:`~retarget_cli.config.Param`). After a stage succeeds, its manifest
(:mod:`retarget_cli.run.manifest`) records what it ran with; a later run skips the
stage while all of it still matches, as make and DVC do.
"""

from __future__ import annotations

import ctypes
import logging
import os
import time
from pathlib import Path

from .. import stages
from ..config import REQUIRED, Command, Config, Flag, Param, load_config
from ..errors import ConfigError, InputError, OutputError, RetargetError
from ..io.atomic import folder_lock, guard_writes, hash_memo, remove_stale_parts
from ..io.rig.cache import cache_limit, hash_memo_dir, rig_cache_dir
from ..stages._common import Stage, collect_results
from .manifest import check_unchanged, manifest_matches, record_inputs, write_manifest

log = logging.getLogger(__name__)














#: The pipeline's stages in order; each is declared beside its runner in retarget_cli/stages/.
STAGES: dict[str, Stage] = {
    s.STAGE.name: s.STAGE
    for s in (stages.track, stages.select, stages.decompose, stages.pose, stages.auto_pose, stages.apply)
}

ORDER = list(STAGES)




#: Declared options of ``run``.
RUN_PARAMS = [
    Param("config", "input", str, help="The run's YAML config."),
    Param("force", "setting", bool, False, "Rerun every selected stage even if it is up to date."),
    Param("start", "setting", str, None, "First stage to consider.", nullable=True),
    Param("stop", "setting", str, None, "Last stage to consider.", nullable=True),
    Param("overrides", "setting", list, None,
          "Override a config value (YAML syntax), e.g. --set select.k=8 or --set output_dir=/scratch/take01. "
          "Repeatable.", nullable=True),
    Param("no_cache", "setting", bool, False,
          "Read rigs' files every time instead of keeping them parsed in the user's rig cache "
          "($RETARGET_CACHE_DIR, else ~/.cache/retarget; see `retarget cache`)."),
]


def stage_params() -> dict[str, list[Param]]:
    """Stage name to its parameter list (for :func:`retarget_cli.config.load_config`)."""
    return {name: s.params for name, s in STAGES.items()}


def _rel(path: Path, base: Path) -> str:
    return os.path.relpath(path, base)


def resolve(cfg: Config, name: str) -> dict:
    """Keyword arguments for a stage's runner: paths made absolute, defaults and links filled.

    Raises
    ------
    ConfigError
        If a required key is missing and no earlier stage provides it.
    """
    stage = STAGES[name]
    given = cfg.sections.get(name, {})
    kw = {}
    for p in stage.params:
        v = given.get(p.name, p.default)
        if p.kind == "input":
            if p.name in given and v is not None:
                kw[p.name] = v if v in p.words else cfg.base_dir / v
                continue
            linked = False
            for link in (p.link or "").split("|") if p.link else ():
                src, _, sub = link.partition("/")
                lstage, lparam = src.split(".")
                if lstage in cfg.sections:
                    base = resolve(cfg, lstage)[lparam]
                    kw[p.name] = base / sub if sub else base
                    linked = True
                    break
            if linked:
                continue
            if v is REQUIRED:
                sections = " or ".join(f"'{link.split('.')[0]}'" for link in p.link.split("|")) if p.link else ""
                hint = f" (or add a {sections} section)" if p.link else ""
                raise ConfigError(f"{cfg.path}: {name}.{p.name} is required{hint}")
            kw[p.name] = None
        elif p.kind == "output":
            kw[p.name] = None if v is None else cfg.output_dir / v
        else:
            kw[p.name] = None if v is REQUIRED else v
    if stage.uses_seed:
        kw["seed"] = cfg.seed
    if stage.uses_base_dir:
        kw["base_dir"] = cfg.base_dir
    return kw






def _inputs(stage: Stage, kw: dict) -> list[Path]:
    files = [f for p in stage.params if p.kind == "input" and kw[p.name] is not None and kw[p.name] not in p.words
             for f in stage.expand_input(p.name, Path(kw[p.name]))]
    for f in files:
        if not f.exists():
            raise InputError(f"{f}: input of stage '{stage.name}' not found")
    return files + [Path(f) for f in stage.extra_inputs(kw)]


def manifest_path(cfg: Config, name: str) -> Path:
    """Stage *name*'s manifest: ``<output_dir>/.retarget/<name>.json``."""
    return cfg.output_dir / ".retarget" / f"{name}.json"


def _settings(stage: Stage, kw: dict, cfg: Config) -> dict:
    out = {}
    for k, v in kw.items():
        out[k] = _rel(v, cfg.base_dir) if isinstance(v, Path) else v
    return out






def check_up_to_date(cfg: Config, name: str, kw: dict) -> tuple[bool, str]:
    """Whether stage *name*'s manifest still matches; returns (ok, reason)."""
    stage = STAGES[name]
    return manifest_matches(manifest_path(cfg, name), settings=_settings(stage, kw, cfg),
                            inputs=lambda: _inputs(stage, kw), base=cfg.base_dir)


def cache_dir(cfg: Config) -> Path:
    """Where a run keeps parsed rigs (:mod:`retarget_cli.io.rig.cache`): the user's rig cache, shared by every
    run (:func:`~retarget_cli.io.rig.cache.rig_cache_dir`), whatever *cfg*."""
    cache_limit()  # a bad $RETARGET_CACHE_SIZE stops the run before any stage
    return rig_cache_dir()


def run_stage(cfg: Config, name: str, kw: dict, progress=None, cache: bool = True) -> list[Path]:
    """Run one stage and write its manifest after its outputs.

    The inputs are hashed before the stage starts and checked unchanged when it ends
    (:func:`~retarget_cli.run.manifest.check_unchanged`): an input replaced while the stage ran fails it, and
    no manifest vouches for bytes the stage did not read.

    The manifest also records the stage's wall-clock run time (``seconds``,
    for reports; not part of the up-to-date check) and what the stage reported
    finding (``results``, e.g. the neutral frame ``neutral_frame: auto`` chose). Stages that load a rig
    get :func:`cache_dir` unless *cache* is False (the cache is not a setting
    and not an output).
    """
    stage = STAGES[name]
    inputs = record_inputs(_inputs(stage, kw))  # hashed before the stage reads them
    call = dict(kw)
    if stage.uses_progress and progress is not None:
        call["progress"] = progress
    if stage.uses_cache:
        call["cache_dir"] = cache_dir(cfg) if cache else None
    t0 = time.perf_counter()
    with collect_results() as results:
        try:
            outputs = stage.runner(**call)
        except OSError as exc:
            if isinstance(exc, RetargetError) or not exc.errno:
                raise
            where = f"{exc.filename}: " if exc.filename else ""
            raise OutputError(f"stage '{name}': {where}{exc.strerror or exc} (errno {exc.errno})") from exc
    seconds = round(time.perf_counter() - t0, 3)
    check_unchanged(inputs, name)
    write_manifest(manifest_path(cfg, name), name, settings=_settings(stage, kw, cfg), inputs=inputs,
                   outputs=outputs, base=cfg.base_dir, seconds=seconds, results=results)
    return outputs


def release_memory() -> bool:
    """Give the memory a finished stage freed back to the system: glibc's ``malloc_trim(0)``; elsewhere nothing.

    numpy arrays smaller than glibc's mmap threshold (which rises to 32 MB as larger arrays are freed) come
    from the heap, and what a stage frees there stays in the process: without a trim each stage of a long
    take starts from what the stages before it peaked at (measured: ``bench/long_take.py``,
    docs/benchmarks.md). Returns whether anything was trimmed.
    """
    try:
        trim = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):  # not glibc
        return False
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return bool(trim(0))


def select_stages(cfg: Config, start: str | None = None, stop: str | None = None) -> list[str]:
    """Stages present in *cfg*, in pipeline order, restricted to ``start..stop``."""
    names = [n for n in ORDER if n in cfg.sections]
    if not names:
        raise ConfigError(f"{cfg.path}: no stage sections; expected some of {', '.join(ORDER)}")
    for label, s in (("--from", start), ("--until", stop)):
        if s is not None and s not in names:
            raise ConfigError(f"{label} {s}: not a stage of {cfg.path} (stages: {', '.join(names)})")
    i = names.index(start) if start else 0
    j = names.index(stop) + 1 if stop else len(names)
    if i >= j:
        raise ConfigError(f"--from {start} comes after --until {stop}")
    return names[i:j]


def run_pipeline(cfg: Config, *, force: bool = False, start=None, stop=None, progress=None,
                 cache: bool = True) -> list[tuple]:
    """Run the config's stages in order, skipping those that are up to date.

    Every stage's arguments are resolved (and so checked) before any runs.
    *cache* False: stages that load a rig parse its OBJs instead of using
    :func:`cache_dir`, and the files' hashes are not looked up in, nor kept in, the user's memo
    (:func:`~retarget_cli.io.rig.cache.hash_memo_dir`; the files are still hashed once per process).

    Returns
    -------
    list of (stage, status, outputs)
        *status* is ``"ran"`` or ``"skipped"``; *outputs* are the stage's
        declared output paths (files or directories).
    """
    names = select_stages(cfg, start, stop)
    resolved = {n: resolve(cfg, n) for n in names}
    everything = dict(resolved)
    for n in ORDER:
        if n in cfg.sections and n not in everything:
            try:
                everything[n] = resolve(cfg, n)
            except ConfigError:
                pass
    inputs = check_outputs(cfg, everything)
    if cache:
        cache_limit()  # a bad $RETARGET_CACHE_SIZE stops the run before any stage
    report = []
    with folder_lock(cfg.output_dir, "output_dir"), hash_memo(hash_memo_dir() if cache else None), \
            guard_writes(roots=[cfg.output_dir], inputs=inputs, label=f"output_dir of {cfg.path}"):
        remove_stale_parts(cfg.output_dir)
        for n in names:
            kw = resolved[n]
            ok, why = (False, "--force") if force else check_up_to_date(cfg, n, kw)
            declared = [kw[p.name] for p in STAGES[n].params if p.kind == "output" and kw[p.name] is not None]
            if ok:
                log.info("%s: up to date, skipped", n)
                report.append((n, "skipped", declared))
                continue
            log.info("%s: running (%s)", n, why)
            run_stage(cfg, n, kw, progress, cache=cache)
            release_memory()
            report.append((n, "ran", declared))
    return report


def _inside(path: Path, folders) -> bool:
    return any(path == f or path.is_relative_to(f) for f in folders)


def run_inputs(cfg: Config, resolved: dict) -> list[Path]:
    """Every file the user gives the run (all stages'), resolved: no stage may write or delete one.

    Inputs a stage takes from an earlier stage's output are not among them;
    files a stage's input references (a rig's OBJs, a targets.yaml's keys)
    are, unless they lie inside a declared output (key OBJs a run posed).
    """
    outs = [Path(kw[p.name]).resolve() for n, kw in resolved.items() for p in STAGES[n].params
            if p.kind == "output" and kw.get(p.name) is not None]
    files = [cfg.path.resolve()]
    for n, kw in resolved.items():
        stage, given = STAGES[n], cfg.sections.get(n, {})
        for p in stage.params:
            v = kw.get(p.name)
            if p.kind != "input" or p.name not in given or v is None or v in p.words:
                continue
            try:
                files += [Path(f).resolve() for f in stage.expand_input(p.name, Path(v))]
            except (RetargetError, OSError, ValueError):
                files.append(Path(v).resolve())
        try:
            extra = [Path(f).resolve() for f in stage.extra_inputs(kw)]
        except (RetargetError, OSError, ValueError, KeyError, TypeError):
            extra = []  # the stage reports an unreadable input itself
        files += [f for f in extra if not _inside(f, outs)]
    return list(dict.fromkeys(files))


def check_outputs(cfg: Config, resolved: dict) -> list[Path]:
    """Check every declared output before any stage runs: inside ``output_dir``, not an input of the run.

    Returns
    -------
    list of Path
        The run's inputs (:func:`run_inputs`), for the write guard.

    Raises
    ------
    ConfigError
        Naming the config key of the output.
    """
    inputs = run_inputs(cfg, resolved)
    protected = set(inputs)
    root = cfg.output_dir.resolve()
    for n, kw in resolved.items():
        given = cfg.sections.get(n, {})
        for p in STAGES[n].params:
            if p.kind != "output" or kw.get(p.name) is None:
                continue
            out = Path(kw[p.name]).resolve()
            value = given.get(p.name, p.default)
            if not _inside(out, [root]):
                raise ConfigError(f"{cfg.path}: {n}.{p.name}: {value!r} lies outside output_dir ({root}); "
                                  "outputs are paths inside output_dir")
            if out in protected:
                raise ConfigError(f"{cfg.path}: {n}.{p.name}: {value!r} is an input of this run; "
                                  "choose another output name")
    return inputs


def _cli_run(values, out) -> list:
    cfg = load_config(values["config"], stage_params(), values["overrides"])
    for name, status, outs in run_pipeline(cfg, force=values["force"], start=values["start"], stop=values["stop"],
                                           progress=out.progress, cache=not values["no_cache"]):
        out.say(f"{name}: {status}")
        for p in outs:
            out.echo(f"{name}\t{p}")
    return []


#: ``run`` (the CLI builds it: :mod:`retarget_cli.cli.commands`); each run guards its own output_dir.
COMMAND = Command(
    "run",
    """Run the pipeline described by CONFIG, skipping stages that are up to date.""",
    lambda: RUN_PARAMS,
    (Flag("config", argument=True, path="file"),
     Flag("force", decls=("--force",), show_default=False),
     Flag("start", decls=("--from",), metavar="STAGE", show_default=False),
     Flag("stop", decls=("--until",), metavar="STAGE", show_default=False),
     Flag("overrides", decls=("--set",), multiple=True, metavar="STAGE.KEY=VALUE", show_default=False, default=None),
     Flag("no_cache", decls=("--no-cache",), show_default=False)),
    _cli_run,
    guarded=False,
)
