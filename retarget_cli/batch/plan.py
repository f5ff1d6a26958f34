"""Shot lists for ``retarget batch``: parsing, validation and planning (no execution).

A shot list names many shots; each becomes one ``retarget run CONFIG --set ...``
into its own output folder, so every shot keeps its own manifests and a batch
resumes for free. Two YAML forms (and a CSV equivalent of the first)::

    output_dir: out            # batch.json and index.html; default parent of shot folders
    base: base.yaml            # shared config for shots without their own 'config'
    shots:
      - name: take01
        video: takes/take01.mp4
        init: takes/take01_00000.pts          # optional (default: the base's, else auto)
        annotations: [takes/take01_00120.pts] # optional
        set: {select.k: 8}                    # optional overrides of the config (or {select: {k: 8}})
      - name: take02
        config: take02/config.yaml            # a complete config: its own output_dir

Paths are relative to the shot list. A shot's output folder is its ``output``
when given, else ``<output_dir>/<name>`` for a shot on the shared base, else
its own config's ``output_dir``. Every shot is checked before anything runs
(unknown keys, missing files, values out of range, duplicate names, output
folders that collide); errors are one line naming the shot list, the shot and
the key.
"""

from __future__ import annotations

import csv
import fnmatch
import math
import re
import shlex
import sys
from dataclasses import dataclass, field
from pathlib import Path

from .._validate import closest
from ..config import TOP_LEVEL, load_config, load_yaml, unknown_key_error, yaml_problem
from ..errors import ConfigError, InputError
from ..io.frames import is_sequence, sequence_files
from ..io.text import read_text
from ..run.pipeline import ORDER, STAGES, check_up_to_date, resolve, select_stages, stage_params

#: Keys of a shot entry (besides ``STAGE.KEY`` columns of a CSV).
SHOT_KEYS = ("name", "config", "video", "init", "annotations", "set", "seed", "output")
#: Top-level keys of a YAML shot list.
LIST_KEYS = ("shots", "base", "output_dir")
#: Settings that hold paths relative to the config (so relative to the shot list when given there).
PATH_SETTINGS = {("track", "annotations"), ("pose", "masks"), ("auto_pose", "masks")}

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


@dataclass
class Shot:
    """One planned shot.

    Attributes
    ----------
    name : str
    config : Path
        Absolute path of the config the shot runs (its own or the shared base).
    overrides : list of str
        ``--set`` strings (``stage.key=value``, values in YAML syntax, paths absolute).
    output_dir : Path
        Absolute output folder.
    stages : list of str
        The stages the shot runs, in pipeline order.
    """

    name: str
    config: Path
    overrides: list = field(default_factory=list)
    output_dir: Path | None = None
    stages: list = field(default_factory=list)

    def command(self, *, force: bool = False, program=None) -> str:
        """The shell command that runs this shot alone (shell-quoted, self-contained: absolute paths).

        *program*: the command's words before ``run``; default the ``retarget`` that is running
        (:func:`running_program`: this interpreter with ``-m retarget_cli``), so the line needs nothing on ``PATH``.
        """
        args = [*(running_program() if program is None else [program] if isinstance(program, str) else program),
                "run", str(self.config)]
        for o in self.overrides:
            args += ["--set", o]
        if force:
            args.append("--force")
        return " ".join(shlex.quote(a) for a in args)


def running_program() -> list[str]:
    """The words that start the ``retarget`` now running: its interpreter (absolute) and ``-m retarget_cli``."""
    return [str(Path(sys.executable).absolute()), "-m", "retarget_cli"]


@dataclass
class Plan:
    """A validated shot list: the batch folder and the shots in list order."""

    path: Path
    output_dir: Path
    shots: list

    def select(self, patterns) -> list:
        """Shots whose name matches any of the fnmatch *patterns* (all when none).

        Raises
        ------
        ConfigError
            If a pattern matches no shot.
        """
        if not patterns:
            return list(self.shots)
        for pat in patterns:
            if not any(fnmatch.fnmatchcase(s.name, pat) for s in self.shots):
                hint = closest(pat, [s.name for s in self.shots])
                extra = f"; did you mean {hint!r}?" if hint else ""
                raise ConfigError(f"--only {pat}: matches no shot of {self.path}{extra}")
        return [s for s in self.shots if any(fnmatch.fnmatchcase(s.name, p) for p in patterns)]


def yaml_value(value) -> str:
    """*value* in YAML flow syntax that :func:`yaml.safe_load` reads back as *value* (for ``--set``)."""
    import yaml

    text = yaml.safe_dump(value, default_flow_style=True, width=math.inf, allow_unicode=True)
    text = text.removesuffix("\n").removesuffix("\n...").strip()
    if yaml.safe_load(text) != value:  # pragma: no cover - safe_dump round-trips its own output
        raise ConfigError(f"value {value!r} cannot be written as a --set value")
    return text


# ----------------------------------------------------------------------------- reading


def _read_entries(path: Path) -> tuple[dict, list]:
    """The shot list's top-level settings and its raw shot entries (dicts)."""
    if not path.is_file():
        raise InputError(f"{path}: shot list not found")
    if path.suffix.lower() == ".csv":
        return {}, _read_csv(path)
    if path.suffix.lower() not in (".yaml", ".yml"):
        raise InputError(f"{path}: expected a shot list .yaml, .yml or .csv")
    raw = load_yaml(read_text(path, "shot list"), str(path))
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: expected a mapping with 'shots:' at the top level")
    for key in raw:
        if key not in LIST_KEYS:
            raise unknown_key_error(str(path), str(key), LIST_KEYS)
    shots = raw.get("shots")
    if not isinstance(shots, list) or not shots:
        raise ConfigError(f"{path}: shots: expected a non-empty list of shots, got {shots!r}")
    for i, s in enumerate(shots):
        if not isinstance(s, dict):
            raise ConfigError(f"{path}: shots[{i}]: expected a mapping (name:, video: or config:, ...), got {s!r}")
    top = {k: v for k, v in raw.items() if k != "shots"}
    return top, [dict(s) for s in shots]


def _csv_header(path: Path, rows: list[list[str]]) -> list[str]:
    """The checked header row of a shot-list CSV."""
    if len(rows) < 2:
        raise ConfigError(f"{path}: expected a header row (name, video or config, ...) and at least one shot")
    header = [h.strip() for h in rows[0]]
    if "name" not in header:
        raise ConfigError(f"{path}: header: a 'name' column is required (columns: {', '.join(header)})")
    for h in header:
        if h not in SHOT_KEYS and h != "base" and "." not in h:
            raise unknown_key_error(f"{path}: header", h, (*SHOT_KEYS, "base", "STAGE.KEY"))
    if "set" in header:
        raise ConfigError(f"{path}: header: give overrides as STAGE.KEY columns (e.g. select.k), not 'set'")
    return header


def _csv_cell(entry: dict, h: str, cell: str, where: str) -> None:
    """Store one non-empty CSV *cell* of column *h* in the shot *entry* (*where* is ``PATH:LINE``)."""
    import yaml

    if h == "annotations":
        entry[h] = [a.strip() for a in cell.split(";") if a.strip()]
    elif "." in h:
        try:
            entry.setdefault("set", {})[h] = yaml.safe_load(cell)
        except yaml.YAMLError as exc:
            raise ConfigError(f"{where}: {h}: value is not valid YAML ({yaml_problem(exc)})") from exc
    elif h == "seed":
        try:
            entry[h] = int(cell)
        except ValueError:
            raise ConfigError(f"{where}: seed: expected an integer, got {cell!r}") from None
    else:
        entry[h] = cell


def _read_csv(path: Path) -> list[dict]:
    """CSV rows as shot entries: empty cells are absent; ``STAGE.KEY`` columns become ``set``; values YAML."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from exc
    rows = list(csv.reader(text.splitlines()))
    rows = [r for r in rows if any(c.strip() for c in r)]
    header = _csv_header(path, rows)
    out = []
    for line, row in enumerate(rows[1:], start=2):
        if len(row) > len(header):
            raise ConfigError(f"{path}:{line}: {len(row)} cells for {len(header)} columns")
        entry: dict = {}
        for h, cell in zip(header, row):
            cell = cell.strip()
            if cell:
                _csv_cell(entry, h, cell, f"{path}:{line}")
        entry["_line"] = line
        out.append(entry)
    return out


# ----------------------------------------------------------------------------- planning


def _flatten_set(value, where: str) -> dict:
    """``{select.k: 8}`` or ``{select: {k: 8}}`` to ``{"select.k": 8}``."""
    if not isinstance(value, dict):
        raise ConfigError(f"{where}: expected a mapping of STAGE.KEY: value, got {value!r}")
    flat = {}
    for k, v in value.items():
        k = str(k)
        if "." in k or k in TOP_LEVEL:
            flat[k] = v
        elif isinstance(v, dict):
            for kk, vv in v.items():
                flat[f"{k}.{kk}"] = vv
        else:
            raise ConfigError(f"{where}: {k}: expected STAGE.KEY (e.g. select.k) or a mapping {k}: {{KEY: value}}")
    return flat


def _absolute(value, base: Path):
    """Make relative path strings (or lists / dict values of them) absolute against *base*."""
    if isinstance(value, str):
        return str((base / value).resolve()) if not Path(value).is_absolute() else value
    if isinstance(value, list):
        return [_absolute(v, base) for v in value]
    if isinstance(value, dict):
        return {k: _absolute(v, base) for k, v in value.items()}
    return value


def _check_file(path: Path, where: str) -> None:
    if is_sequence(path) and not path.exists():
        try:
            sequence_files(path)
        except InputError as exc:
            raise InputError(f"{where}: {exc}") from None
    elif not path.is_file():
        raise InputError(f"{where}: {path}: file not found")


def _shot_where(entry: dict, i: int, list_path: Path) -> tuple[str, str]:
    """The shot's checked name and the ``LIST: shot NAME`` prefix of its messages; unknown keys refused."""
    name = entry.get("name")
    label = f"line {entry['_line']}" if "_line" in entry else f"shots[{i}]"
    if not isinstance(name, str) or not _NAME.match(name):
        raise ConfigError(f"{list_path}: {label}: name: expected letters, digits, '.', '_' or '-' (not starting "
                          f"with '.', '_' or '-'), got {name!r}")
    where = f"{list_path}: shot {name}"
    for key in entry:
        if key not in SHOT_KEYS and key not in ("base", "_line"):
            raise unknown_key_error(where, key, SHOT_KEYS)
    return name, where


def _shot_config(entry: dict, top: dict, base_dir: Path, where: str) -> Path:
    """The shot's own ``config:`` or the shared ``base:``, resolved and required to exist."""
    own = entry.get("config")
    shared = entry.get("base", top.get("base"))
    if own is None and shared is None:
        raise ConfigError(f"{where}: config: required (or give a shared 'base:' config in the shot list)")
    config_rel = own if own is not None else shared
    if not isinstance(config_rel, str):
        raise ConfigError(f"{where}: {'config' if own is not None else 'base'}: expected a path, got {config_rel!r}")
    config = (base_dir / config_rel).resolve()
    if not config.is_file():
        raise InputError(f"{where}: {'config' if own is not None else 'base'}: {config}: config file not found")
    return config


def _shot_sets(entry: dict, where: str, stages: dict, base_dir: Path) -> dict:
    """The shot's overrides as ``{"STAGE.KEY": value}``, keys checked, list-relative paths made absolute."""
    sets: dict = {}
    for key, stage_key in (("video", "track.video"), ("init", "track.init"), ("annotations", "track.annotations")):
        if key in entry:
            sets[stage_key] = entry[key]
    if "set" in entry:
        sets.update(_flatten_set(entry["set"], f"{where}: set"))
    if "seed" in entry:
        sets["seed"] = entry["seed"]
    # Paths given in the shot list are relative to it: make them absolute (the config's own stay as they are).
    for k, v in list(sets.items()):
        stage, _, key = k.partition(".")
        if stage not in stages or not key:
            if k in TOP_LEVEL:
                continue
            raise unknown_key_error(f"{where}: set", k, sorted(f"{s}.KEY" for s in stages))
        param = next((p for p in stages[stage] if p.name == key), None)
        if param is None:
            raise unknown_key_error(f"{where}: set: {stage}", key, [p.name for p in stages[stage]])
        if (param.kind == "input" and isinstance(v, str) and v not in param.words) or (stage, key) in PATH_SETTINGS:
            sets[k] = _absolute(v, base_dir)
    if "output_dir" in sets:
        raise ConfigError(f"{where}: set: output_dir: give the shot's 'output:' instead")
    return sets


def _shot_output(entry: dict, name: str, where: str, base_dir: Path, out_root: Path) -> Path | None:
    """The shot's output folder: its ``output:``, else OUT_ROOT/NAME for a shared base, else None (the config's)."""
    if "output" in entry:
        if not isinstance(entry["output"], str):
            raise ConfigError(f"{where}: output: expected a folder path, got {entry['output']!r}")
        return (base_dir / entry["output"]).resolve()
    if entry.get("config") is None:
        return out_root / name
    return None  # the config's own output_dir


def _check_inputs(cfg, resolved: dict, where: str) -> None:
    """User-given input files of the resolved stages must exist (outputs of earlier stages are exempt)."""

    produced = {Path(kw[p.name]).resolve() for n, kw in resolved.items() for p in STAGES[n].params
                if p.kind == "output" and kw[p.name] is not None}
    for n, kw in resolved.items():
        for p in STAGES[n].params:
            v = kw.get(p.name)
            if p.kind != "input" or v is None or v in p.words or p.name not in cfg.sections[n]:
                continue
            path = Path(v).resolve()
            if path in produced or any(q in path.parents for q in produced):
                continue
            _check_file(path, f"{where}: {n}.{p.name}")
        if n == "track":
            for a in kw.get("annotations") or []:
                _check_file(cfg.base_dir / a, f"{where}: track.annotations")


def _shot(entry: dict, i: int, list_path: Path, top: dict, out_root: Path, stages: dict) -> Shot:
    base_dir = list_path.resolve().parent
    name, where = _shot_where(entry, i, list_path)
    config = _shot_config(entry, top, base_dir, where)
    sets = _shot_sets(entry, where, stages, base_dir)
    out = _shot_output(entry, name, where, base_dir, out_root)
    overrides = [f"{k}={yaml_value(v)}" for k, v in sets.items()]
    if out is not None:
        overrides.append(f"output_dir={yaml_value(str(out))}")
    try:
        cfg = load_config(config, stages, overrides)
        names = select_stages(cfg)
        resolved = {n: resolve(cfg, n) for n in names}
    except (ConfigError, InputError) as exc:
        raise type(exc)(f"{where}: {exc}") from None
    # User-given input files must exist now (outputs of earlier stages appear as the shot runs).
    _check_inputs(cfg, resolved, where)
    return Shot(name, config, overrides, cfg.output_dir, names)


def load_plan(path, *, output_dir=None) -> Plan:
    """Read and validate a shot list (YAML or CSV) completely, before anything runs.

    Parameters
    ----------
    path : path-like
        The shot list.
    output_dir : path-like, optional
        Batch folder (``batch.json``, ``index.html``, default parent of the
        shot folders), overriding the list's ``output_dir`` (default ``out``
        beside the list).

    Raises
    ------
    ConfigError, InputError
        One line naming the shot list, the shot and the key: an unknown key,
        a missing file, a value out of range, a repeated name, or output
        folders that are the same or nested.
    """

    path = Path(path)
    top, entries = _read_entries(path)
    for key in ("base", "output_dir"):
        if key in top and not isinstance(top[key], str):
            raise ConfigError(f"{path}: {key}: expected a path, got {top[key]!r}")
    base_dir = path.resolve().parent
    root = Path(output_dir).resolve() if output_dir is not None else (base_dir / top.get("output_dir", "out")).resolve()
    stages = stage_params()
    shots, seen = [], {}
    for i, e in enumerate(entries):
        shot = _shot(e, i, path, top, root, stages)
        if shot.name in seen:
            raise ConfigError(f"{path}: shot {shot.name}: name: repeats the name of shot {seen[shot.name] + 1} "
                              "of the list; names must be unique")
        seen[shot.name] = i
        shots.append(shot)
    _check_collisions(path, root, shots)
    return Plan(path, root, shots)


def _check_collisions(path: Path, root: Path, shots: list) -> None:
    by_dir: dict = {}
    for s in shots:
        d = s.output_dir
        if d == root:
            raise ConfigError(f"{path}: shot {s.name}: output folder {d} is the batch folder; give the shot an "
                              "'output:' of its own")
        if d in by_dir:
            raise ConfigError(f"{path}: shot {s.name}: output folder {d} is also that of shot {by_dir[d]}; give "
                              "one of them an 'output:' of its own")
        by_dir[d] = s.name
    for s in shots:
        for parent in s.output_dir.parents:
            if parent in by_dir:
                raise ConfigError(f"{path}: shot {s.name}: output folder {s.output_dir} is inside that of shot "
                                  f"{by_dir[parent]}; shot output folders must not nest")


def pending(shot: Shot, *, force: bool = False) -> bool:
    """Whether *shot* has a stage that is not up to date (what ``retarget run`` would run)."""

    if force:
        return True
    cfg = load_config(shot.config, stage_params(), shot.overrides)
    for n in shot.stages:
        try:
            ok, _ = check_up_to_date(cfg, n, resolve(cfg, n))
        except InputError:
            return True
        if not ok:
            return True
    return False


# ----------------------------------------------------------------------------- summary table

#: Summary columns of the stdout table (besides one column of seconds per stage).
TABLE_COLUMNS = ("shot", "status", "tries", "frames", "confidence", "residual_px", "jitter", "seconds")


def _fmt(v, digits=3) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}g}"
    return str(v)


def format_table(results: list) -> str:
    """The batch summary as an aligned text table (one row per shot; stage columns: seconds, or 'skip').

    Parameters
    ----------
    results : list of dict
        Shot summaries as written to ``batch.json`` (``name``, ``status``,
        ``attempts``, ``frames``, ``confidence``, ``residual_px``,
        ``jitter``, ``seconds``, ``stages``, ``error``).
    """

    stage_cols = [n for n in ORDER if any(n in (r.get("stages") or {}) for r in results)]
    head = [*TABLE_COLUMNS, *stage_cols, "error"]
    rows = []
    for r in results:
        st = r.get("stages") or {}
        cells = [r["name"], r["status"], _fmt(r.get("attempts")), _fmt(r.get("frames")),
                 _fmt(r.get("confidence")), _fmt(r.get("residual_px")), _fmt(r.get("jitter")),
                 _fmt(r.get("seconds"))]
        for n in stage_cols:
            s = st.get(n)
            cells.append("-" if s is None else ("skip" if s["status"] == "skipped" else f"{s['seconds']:.2f}"))
        cells.append(" ".join(str(r.get("error") or "").split()))
        rows.append(cells)
    widths = [max(len(str(x[i])) for x in [head, *rows]) for i in range(len(head) - 1)]
    lines = []
    for cells in [head, *rows]:
        lines.append("  ".join(c.ljust(w) for c, w in zip(cells[:-1], widths)) + "  " + cells[-1])
    return "\n".join(ln.rstrip() for ln in lines)
