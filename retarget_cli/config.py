"""Declared parameters and YAML config validation.

Every stage declares its parameters once (:class:`Param`); the YAML config,
``retarget run --set`` and the per-stage CLI options are all checked against
those declarations before anything runs. An unknown key is an error that names
the file and the key and suggests the closest valid name; a value out of range
names the key, the value and the allowed range.
"""

from __future__ import annotations

import difflib
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import ConfigError

REQUIRED = object()


@dataclass(frozen=True)
class Param:
    """One stage parameter.

    Attributes
    ----------
    name : str
        YAML key (``snake_case``); the CLI option is ``--name-with-dashes``.
    kind : {"input", "output", "setting"}
        Inputs are paths relative to the config file; outputs are paths
        relative to ``output_dir``; settings are values.
    type : type
        ``int``, ``float``, ``str``, ``bool``, ``list`` or ``dict``.
    default : object
        :data:`REQUIRED` when the key must be given.
    choices, min, max : optional
        Allowed values / inclusive range.
    link : str, optional
        ``"stage.param"`` whose output feeds this input by default in
        ``retarget run``.
    words : tuple of str
        Values of an input that name no file (``track.init: auto``): passed
        through as they are, neither resolved as paths nor hashed.
    """

    name: str
    kind: str
    type: type
    default: Any = REQUIRED
    help: str = ""
    choices: tuple | None = None
    min: float | None = None
    max: float | None = None
    nullable: bool = False
    link: str | None = None
    words: tuple = ()

    @property
    def required(self) -> bool:
        return self.default is REQUIRED

    def describe_range(self) -> str:
        if self.choices:
            return "one of " + ", ".join(map(str, self.choices))
        lo = "-inf" if self.min is None else f"{self.min:g}"
        hi = "inf" if self.max is None else f"{self.max:g}"
        return f"{self.type.__name__} in [{lo}, {hi}]"

    def check(self, value: Any, where: str) -> Any:
        """Validate and coerce *value*; *where* names it in errors (``file: stage.key``)."""
        if value is None:
            if self.nullable or self.default is None:
                return None
            raise ConfigError(f"{where}: a value is required ({self.describe_range()})")
        t = self.type
        if t is bool:
            if not isinstance(value, bool):
                raise ConfigError(f"{where}: expected true or false, got {value!r}")
        elif t is int:
            if isinstance(value, bool) or not isinstance(value, int):
                raise ConfigError(f"{where}: expected an integer, got {value!r}")
        elif t is float:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f"{where}: expected a number, got {value!r}")
            value = float(value)
        elif t is str:
            if isinstance(value, (int, float)) and not isinstance(value, bool) and self.kind != "setting":
                value = str(value)
            if not isinstance(value, str):
                raise ConfigError(f"{where}: expected a string, got {value!r}")
        elif t in (list, dict):
            if not isinstance(value, t):
                raise ConfigError(f"{where}: expected a {'list' if t is list else 'mapping'}, got {value!r}")
        if self.choices is not None and t is list:
            bad = [v for v in value if v not in self.choices]
            if bad or not value or len(set(value)) != len(value):
                raise ConfigError(f"{where}: expected a non-empty list without repeats of "
                                  f"{', '.join(map(str, self.choices))}; got {value!r}")
        elif self.choices is not None and value not in self.choices:
            hint = closest(str(value), [str(c) for c in self.choices])
            extra = f"; did you mean {hint!r}?" if hint else ""
            raise ConfigError(f"{where}: {value!r} is not {self.describe_range()}{extra}")
        if t in (int, float) and (
            (self.min is not None and value < self.min) or (self.max is not None and value > self.max)
        ):
            raise ConfigError(f"{where}: {value!r} is out of range; expected {self.describe_range()}")
        return value


def yaml_problem(exc) -> str:
    """A YAML parser error as one line: its problem and where (``line L, column C``)."""
    mark = getattr(exc, "problem_mark", None)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    return " ".join(str(getattr(exc, "problem", None) or exc).split()) + where


def closest(name: str, candidates) -> str | None:
    """The candidate most similar to *name*, or None when nothing is close."""
    hits = difflib.get_close_matches(name, list(candidates), n=1, cutoff=0.5)
    return hits[0] if hits else None


def unknown_key_error(where: str, key: str, valid) -> ConfigError:
    hint = closest(key, valid)
    if hint:
        return ConfigError(f"{where}: unknown key {key!r}; did you mean {hint!r}?")
    return ConfigError(f"{where}: unknown key {key!r}; valid keys: {', '.join(sorted(valid))}")


#: Top-level config keys that are not stage sections.
TOP_LEVEL = {
    "output_dir": Param("output_dir", "setting", str, "out", "Directory for every output, relative to the config file."),
    "seed": Param("seed", "setting", int, 0, "Seed for every random choice.", min=0),
}


@dataclass
class Config:
    """A validated run configuration.

    Attributes
    ----------
    path : Path
        The YAML file.
    base_dir : Path
        Directory input paths are relative to (the YAML file's).
    output_dir : Path
        Absolute output directory.
    seed : int
    sections : dict
        Stage name to its validated ``{key: value}`` (only keys the user gave).
    """

    path: Path
    base_dir: Path
    output_dir: Path
    seed: int
    sections: dict = field(default_factory=dict)


def parse_override(text: str) -> tuple[str, str, Any]:
    """Parse ``stage.key=value`` (value in YAML syntax) from ``--set``.

    A top-level key (``output_dir=...``, ``seed=...``) comes back with stage ``""``.
    """
    import yaml

    lhs = text.split("=", 1)[0].strip()
    if "=" not in text or ("." not in lhs and lhs not in TOP_LEVEL):
        raise ConfigError(f"--set {text!r}: expected STAGE.KEY=VALUE, e.g. select.k=8 (or output_dir=..., seed=...)")
    lhs, rhs = text.split("=", 1)
    stage, key = lhs.split(".", 1) if lhs.strip() not in TOP_LEVEL else ("", lhs)
    try:
        value = yaml.safe_load(rhs) if rhs.strip() else None
    except yaml.YAMLError as exc:
        raise ConfigError(f"--set {text!r}: value is not valid YAML ({exc})") from exc
    return stage.strip(), key.strip(), value


def load_config(path: str | os.PathLike, stages: dict, overrides=()) -> Config:
    """Read and validate a run config.

    Parameters
    ----------
    path : path-like
        YAML file.
    stages : dict
        Stage name to its list of :class:`Param` (from :mod:`retarget_cli.pipeline`).
    overrides : iterable of str
        ``stage.key=value`` strings that take precedence over the file.

    Raises
    ------
    ConfigError
        For a missing or malformed file, an unknown section or key, a wrong
        type or an out-of-range value; the message names file and key.
    """
    import yaml

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found")
    try:
        raw = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark else str(path)
        raise ConfigError(f"{where}: invalid YAML ({yaml_problem(exc)})") from exc
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: expected a mapping of sections at the top level, got {type(raw).__name__}")
    raw = {k: (dict(v) if isinstance(v, dict) else v) for k, v in raw.items()}
    for text in overrides:
        stage, key, value = parse_override(text)
        if not stage:
            raw[key] = value
            continue
        if stage not in stages:
            raise unknown_key_error(f"--set {text}", stage, stages)
        section = raw.setdefault(stage, {}) or {}
        raw[stage] = section
        section[key] = value
    valid_top = set(TOP_LEVEL) | set(stages)
    sections = {}
    top = {}
    for key, value in raw.items():
        key = str(key)
        if key not in valid_top:
            raise unknown_key_error(str(path), key, valid_top)
        if key in TOP_LEVEL:
            top[key] = TOP_LEVEL[key].check(value, f"{path}: {key}")
            continue
        if value is None:
            value = {}
        if not isinstance(value, dict):
            raise ConfigError(f"{path}: section {key!r} must be a mapping of settings, got {value!r}")
        params = {p.name: p for p in stages[key]}
        checked = {}
        for k, v in value.items():
            k = str(k)
            if k not in params:
                raise unknown_key_error(f"{path}: {key}", k, params)
            checked[k] = params[k].check(v, f"{path}: {key}.{k}")
        sections[key] = checked
    base = path.resolve().parent
    out = top.get("output_dir", TOP_LEVEL["output_dir"].default)
    return Config(path, base, (base / out).resolve(), top.get("seed", 0), sections)
