"""Declared parameters and YAML config validation.

Every stage declares its parameters once (:class:`Param`); the YAML config,
``retarget run --set`` and the per-stage CLI options are all checked against
those declarations before anything runs. An unknown key is an error that names
the file and the key and suggests the closest valid name; a value out of range
names the key, the value and the allowed range.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ._validate import NAME_RE, closest
from .errors import ConfigError, ParameterError

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
        Allowed values / range, inclusive unless *min_open* / *max_open*. *choices* may be a function returning
        them, read at each check (a registry such as
        :data:`retarget_cli.methods.tracking.TRACKERS` that may grow after import).
    link : str, optional
        ``"stage.param"`` whose output feeds this input by default in
        ``retarget run``.
    words : tuple of str
        Values of an input that name no file (``track.init: auto``): passed
        through as they are, neither resolved as paths nor hashed. A setting's
        words are accepted besides its type (``neutral_frame: auto``).
    validate : callable, optional
        ``validate(value, where)`` checks the items of a list or mapping
        (e.g. :func:`check_regions`) and raises :class:`ConfigError`.
    """

    name: str
    kind: str
    type: type
    default: Any = REQUIRED
    help: str = ""
    choices: tuple | Callable | None = None
    min: float | None = None
    max: float | None = None
    min_open: bool = False
    max_open: bool = False
    nullable: bool = False
    link: str | None = None
    words: tuple = ()
    validate: Callable | None = None

    @property
    def options(self) -> tuple | None:
        """The allowed values (:attr:`choices`, called when it is a function), or None."""
        return tuple(self.choices()) if callable(self.choices) else self.choices

    @property
    def required(self) -> bool:
        return self.default is REQUIRED

    def describe_range(self) -> str:
        if self.options:
            return "one of " + ", ".join(map(str, self.options))
        lo = "-inf" if self.min is None else f"{self.min:g}"
        hi = "inf" if self.max is None else f"{self.max:g}"
        words = "".join(f" or {w}" for w in self.words) if self.kind == "setting" else ""
        return (f"{self.type.__name__} in {'(' if self.min_open else '['}{lo}, {hi}{')' if self.max_open else ']'}"
                + words)

    def check(self, value: Any, where: str) -> Any:
        """Validate and coerce *value*; *where* names it in errors (``file: stage.key``)."""
        if value is None:
            if self.nullable or self.default is None:
                return None
            raise ConfigError(f"{where}: a value is required ({self.describe_range()})")
        if self.kind == "setting" and isinstance(value, str) and value in self.words:
            return value
        coerce = _COERCE.get(self.type)
        if coerce is not None:
            value = coerce(self, value, where)
        if self.options is not None:
            self._check_choices(value, where)
        if self.type in (int, float) and (
            (self.min is not None and (value <= self.min if self.min_open else value < self.min))
            or (self.max is not None and (value >= self.max if self.max_open else value > self.max))
        ):
            raise ConfigError(f"{where}: {value!r} is out of range; expected {self.describe_range()}")
        if self.validate is not None:
            self.validate(value, where)
        return value

    def _check_choices(self, value: Any, where: str) -> None:
        """*value* (or, for a list, each item, once) must be one of :attr:`choices`."""
        if self.type is list:
            bad = [v for v in value if v not in self.options]
            if bad or not value or len(set(value)) != len(value):
                raise ConfigError(f"{where}: expected a non-empty list without repeats of "
                                  f"{', '.join(map(str, self.options))}; got {value!r}")
        elif value not in self.options:
            hint = closest(str(value), [str(c) for c in self.options])
            extra = f"; did you mean {hint!r}?" if hint else ""
            raise ConfigError(f"{where}: {value!r} is not {self.describe_range()}{extra}")


#: A :class:`Flag` field left to what the :class:`Param` says.
UNSET = object()


@dataclass(frozen=True)
class Flag:
    """How one declared :class:`Param` appears on a command line; only what differs from the default is given.

    By default a Param ``name`` is the option ``--name-with-dashes`` (``--name/--no-name`` for a bool) with
    the Param's type, range or choices, default and help.

    Attributes
    ----------
    name : str
        The Param's name (also the runner's keyword).
    decls : tuple of str
        Option strings instead of the default (``("-k",)``, ``("-o", "--output")``).
    argument : bool
        A positional argument; *nargs* -1 takes any number, *required* False makes it optional.
    path : {"file", "folder", "path", "out", "existing"}, optional
        A path: a file (not a folder), a folder, either, an output that may be a folder, or one that exists.
    value : str, optional
        A syntax the command line parses into the value: ``size`` (``WxH``), ``indices`` (``27-31,33``),
        ``frames`` (``0,120`` or ``0-300:60``), ``region`` (``NAME[=SPEC][:K]``), ``mask`` (``REGION=FILE``), ``xyz`` (``X,Y,Z``), ``text`` (a string the
        command reads itself);
        *value_args* are its options as ``(key, value)`` pairs.
    metavar, multiple, show_default, default, help
        As click's options; *default* and *help* replace the Param's.
    """

    name: str
    decls: tuple = ()
    argument: bool = False
    nargs: int = 1
    required: bool | None = None
    path: str | None = None
    value: str | None = None
    value_args: tuple = ()
    metavar: str | None = None
    multiple: bool = False
    show_default: bool = True
    default: Any = UNSET
    help: str | None = None


@dataclass(frozen=True)
class Command:
    """A ``retarget`` command, declared beside the code it runs; the CLI builds every command from these.

    Attributes
    ----------
    name : str
        The command (``pose-keys``).
    help : str
        Its help text (click's docstring conventions: the first sentence is the summary, ``\\b`` keeps a block).
    params : callable
        ``params() -> list of Param``: the declarations its flags name (read at each use: a registry such as
        :data:`~retarget_cli.methods.tracking.TRACKERS` may add settings after import).
    flags : tuple of (Flag or str)
        The arguments and options in the order of ``--help``; a str is a Param name with the default Flag.
    run : callable
        ``run(values, out) -> result``: *values* maps each flag's name to its parsed value; *out* is the
        console (``out.echo(line)`` on stdout, ``out.say(line)`` on stderr unless quiet, ``out.progress``
        the progress-bar factory, ``out.quiet``, ``out.debug``). Raises the tool's errors
        (:class:`~retarget_cli.errors.UsageError` for an unusable command-line value).
    show : callable, optional
        ``show(result, out)``: what the command prints; the default prints each path of *result* on a line.
    guarded : bool
        Writes pass the write guard: only inside the folders of the outputs named (Params of kind
        ``output``), never onto an input.
    folder_output : bool
        ``--output`` names a folder the command writes inside (not a file).
    """

    name: str
    help: str
    params: Callable
    flags: tuple
    run: Callable
    show: Callable | None = None
    guarded: bool = True
    folder_output: bool = False

    def param(self, name: str) -> Param:
        """The declared :class:`Param` *name*."""
        return next(p for p in self.params() if p.name == name)


def show_paths(result, out) -> None:
    """The default :attr:`Command.show`: each written path on its own line."""
    for path in result:
        out.echo(str(path))


# --------------------------------------------------------------------------- type coercion (Param.check)


def _coerce_bool(param: Param, value: Any, where: str) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(f"{where}: expected true or false, got {value!r}")
    return value


def _coerce_int(param: Param, value: Any, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"{where}: expected an integer, got {value!r}")
    return value


def _coerce_float(param: Param, value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{where}: expected a number, got {value!r}")
    try:
        value = float(value)
    except OverflowError:
        value = math.inf
    if not math.isfinite(value):
        raise ConfigError(f"{where}: expected a finite number ({param.describe_range()}), got {value!r}")
    return value


def _coerce_str(param: Param, value: Any, where: str) -> str:
    """Numbers become strings for inputs and outputs (file names like ``0001``), not for settings."""
    if isinstance(value, (int, float)) and not isinstance(value, bool) and param.kind != "setting":
        value = str(value)
    if not isinstance(value, str):
        raise ConfigError(f"{where}: expected a string, got {value!r}")
    return value


def _coerce_container(param: Param, value: Any, where: str):
    if not isinstance(value, param.type):
        raise ConfigError(f"{where}: expected a {'list' if param.type is list else 'mapping'}, got {value!r}")
    return value


_COERCE = {bool: _coerce_bool, int: _coerce_int, float: _coerce_float, str: _coerce_str,
           list: _coerce_container, dict: _coerce_container}


# --------------------------------------------------------------------------- item validators (Param.validate)


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _name_error(where: str, name) -> ConfigError:
    hint = " (quote it: '5')" if not isinstance(name, str) else ""
    return ConfigError(f"{where}: {name!r} is not a valid region name{hint}; expected letters, digits, '_', '.' "
                       "and '-' (no '..', no '/')")


def check_region_name(name, where: str) -> str:
    """A region name used in output paths: ``[A-Za-z0-9_.-]+`` without ``..``."""
    if not isinstance(name, str) or not NAME_RE.match(name) or ".." in name:
        raise _name_error(where, name)
    return name


def check_indices(value, where: str, limit: int = 100_000) -> None:
    """A list of landmark ids: integers in [0, limit)."""
    if not isinstance(value, list) or not all(_is_int(v) and 0 <= v < limit for v in value):
        raise ConfigError(f"{where}: expected a list of landmark ids (integers >= 0), got {str(value)[:80]}")


def check_regions(value, where: str) -> None:
    """``select.regions``: name to ``all``, null, ids or ``{points, k}``."""
    for name, spec in value.items():
        check_region_name(name, where)
        w = f"{where}.{name}"
        if isinstance(spec, dict):
            bad = sorted(map(str, set(spec) - {"points", "k"}))
            if bad:
                raise ConfigError(f"{w}: unknown key {bad[0]!r}; expected 'points' and/or 'k'")
            if "k" in spec and (not _is_int(spec["k"]) or not 1 <= spec["k"] <= 1000):
                raise ConfigError(f"{w}.k: expected an integer in [1, 1000], got {spec['k']!r}")
            spec = spec.get("points")
        if spec is None or spec == "all":
            continue
        check_indices(spec, w)
        if not spec:
            raise ConfigError(f"{w}: expected 'all', null, a non-empty list of landmark ids or {{points, k}}")


def check_masks(value, where: str) -> None:
    """Region name to a mask file path."""
    for name, path in value.items():
        check_region_name(name, where)
        if not isinstance(path, str) or not path:
            raise ConfigError(f"{where}.{name}: expected a mask file path, got {path!r}")


def check_strings(value, where: str) -> None:
    if not all(isinstance(v, str) and v for v in value):
        raise ConfigError(f"{where}: expected a list of strings, got {str(value)[:80]}")


def check_size(value, where: str) -> None:
    """A frame size ``[width, height]`` of positive integers."""
    if len(value) != 2 or not all(_is_int(v) and v > 0 for v in value):
        raise ConfigError(f"{where}: expected [width, height] in pixels, got {value!r}")


def check_vector3(value, where: str) -> None:
    if (len(value) != 3 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
            or not all(math.isfinite(v) for v in value)):
        raise ConfigError(f"{where}: expected [x, y, z] (three finite numbers), got {value!r}")


# --------------------------------------------------------------------------- YAML with limits


#: Limits on a YAML document: expanded node count (alias bombs), aliases and bytes.
YAML_MAX_NODES = 1_000_000
YAML_MAX_ALIASES = 1_000
YAML_MAX_BYTES = 64 << 20


def yaml_loader():
    """PyYAML's safe loader: libyaml's ``CSafeLoader`` (about ten times faster) when PyYAML was built with it,
    else the pure-Python ``SafeLoader``; both build the same nodes and values (their error texts differ in
    wording, not in the line and column they name)."""
    import yaml

    return yaml.CSafeLoader if getattr(yaml, "__with_libyaml__", False) else yaml.SafeLoader


def load_yaml(text, where: str, error=ConfigError, with_line: bool = False):
    """``yaml.safe_load`` (through :func:`yaml_loader`) with limits: at most :data:`YAML_MAX_ALIASES` aliases and
    :data:`YAML_MAX_NODES` nodes once aliases are expanded (a "billion laughs" document
    is refused before it is built), and no key given twice in one mapping (YAML says
    keys are unique; PyYAML would keep the last silently); *text* may be bytes (UTF-8 required).

    Raises
    ------
    error
        One line naming *where*, for invalid UTF-8, invalid YAML, a repeated key (with both lines) or a
        document over the limits.
    """
    import yaml

    if isinstance(text, bytes):
        if len(text) > YAML_MAX_BYTES:
            raise error(f"{where}: larger than {YAML_MAX_BYTES >> 20} MiB; not a settings file")
        try:
            text = text.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise error(f"{where}: not UTF-8 text (byte {exc.start} is {text[exc.start:exc.start + 1]!r})") from None
    loader = None
    try:
        try:
            loader = yaml_loader()(text)
        except UnicodeEncodeError:  # a lone surrogate (a --set value from undecodable argv): libyaml wants UTF-8
            loader = yaml.SafeLoader(text)
        node = loader.get_single_node()
        if node is None:
            return None
        memo: dict[int, int] = {}
        aliases = [0]

        def size(n) -> int:
            key = id(n)
            if key in memo:
                aliases[0] += 1
                if aliases[0] > YAML_MAX_ALIASES:
                    raise error(f"{where}: more than {YAML_MAX_ALIASES} YAML aliases; refusing to expand them")
                return memo[key]
            memo[key] = 1  # a recursive document counts its cycle once
            total = 1
            if isinstance(n, yaml.SequenceNode):
                total += sum(size(c) for c in n.value)
            elif isinstance(n, yaml.MappingNode):
                _no_duplicate_keys(n, where, error)
                total += sum(size(k) + size(v) for k, v in n.value)
            memo[key] = total
            if total > YAML_MAX_NODES:
                raise error(f"{where}: the YAML document expands to more than {YAML_MAX_NODES} values "
                            "(an alias bomb?); refusing to load it")
            return total

        size(node)
        return loader.construct_document(node)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f":{mark.line + 1}" if mark is not None and with_line else ""
        raise error(f"{where}{line}: invalid YAML ({yaml_problem(exc)})") from None
    except RecursionError:
        raise error(f"{where}: the YAML document is nested too deeply") from None
    finally:
        if loader is not None:
            loader.dispose()


def _no_duplicate_keys(node, where: str, error) -> None:
    """A YAML mapping node whose scalar keys are all different (merge keys ``<<`` aside), else *error*."""
    seen: dict = {}
    for k, _ in node.value:
        if not hasattr(k, "value") or not isinstance(k.value, str) or k.tag == "tag:yaml.org,2002:merge":
            continue
        ident = (k.tag, k.value)
        if ident in seen:
            raise error(f"{where}:{k.start_mark.line + 1}: key {k.value!r} given twice in one mapping (first at line "
                        f"{seen[ident] + 1}); YAML keys are unique: remove or merge one")
        seen[ident] = k.start_mark.line


def yaml_problem(exc) -> str:
    """A YAML parser error as one line: its problem and where (``line L, column C``)."""
    mark = getattr(exc, "problem_mark", None)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    return " ".join(str(getattr(exc, "problem", None) or exc).split()) + where


def unknown_key_error(where: str, key: str, valid, error=ConfigError) -> Exception:
    """An unknown key as one line with the closest valid key (or the list); *error*: the class (an input
    file's reader passes :class:`~retarget_cli.errors.InputError`)."""
    hint = closest(key, valid)
    if hint:
        return error(f"{where}: unknown key {key!r}; did you mean {hint!r}?")
    return error(f"{where}: unknown key {key!r}; valid keys: {', '.join(sorted(valid))}")


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


def parse_override(text: str) -> tuple[str | None, str, Any]:
    """Parse ``stage.key=value`` or a top-level ``key=value`` (``seed=3``; value in YAML syntax) from ``--set``.

    Returns ``(stage, key, value)``; *stage* is None for a top-level key.
    """
    if "=" not in text:
        raise ConfigError(f"--set {text!r}: expected STAGE.KEY=VALUE or KEY=VALUE, e.g. select.k=8 or seed=3")
    lhs, rhs = text.split("=", 1)
    if "." in lhs:
        stage, key = (v.strip() for v in lhs.split(".", 1))
    elif lhs.strip() in TOP_LEVEL:
        stage, key = None, lhs.strip()
    else:
        raise ConfigError(f"--set {text!r}: expected STAGE.KEY=VALUE or one of {', '.join(TOP_LEVEL)}=VALUE")
    value = load_yaml(rhs, f"--set {text!r}") if rhs.strip() else None
    return stage, key, value


def _read_raw(path: Path, stages: dict) -> dict:
    """The config file's top-level mapping (sections copied so overrides do not alias the YAML)."""
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found")
    if path.stat().st_size > YAML_MAX_BYTES:
        raise ConfigError(f"{path}: larger than {YAML_MAX_BYTES >> 20} MiB; not a config file")
    raw = load_yaml(path.read_bytes(), str(path), with_line=True)
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: expected a mapping of sections at the top level, got {type(raw).__name__}")
    bad = [k for k in raw if not isinstance(k, str)]
    if bad:
        raise ConfigError(f"{path}: {bad[0]!r} is not a section name; expected one of "
                          f"{', '.join(sorted(set(TOP_LEVEL) | set(stages)))}")
    return {k: (dict(v) if isinstance(v, dict) else v) for k, v in raw.items()}


def _apply_overrides(raw: dict, path: Path, stages: dict, overrides) -> None:
    """Write the ``--set`` *overrides* into *raw* in place."""
    for text in overrides:
        stage, key, value = parse_override(text)
        if stage is None:
            raw[key] = value
            continue
        if stage not in stages:
            raise unknown_key_error(f"--set {text}", stage, stages)
        section = raw.get(stage)
        if section is None:
            section = {}
        if not isinstance(section, dict):
            raise ConfigError(f"{path}: section {stage!r} must be a mapping of settings, got {section!r}")
        raw[stage] = section
        section[key] = value


def _check_section(path: Path, key: str, value: Any, params: dict) -> dict:
    """Section *key* of the config, each setting checked against its :class:`Param` in *params*."""
    if value is None:
        value = {}
    if not isinstance(value, dict):
        raise ConfigError(f"{path}: section {key!r} must be a mapping of settings, got {value!r}")
    checked = {}
    for k, v in value.items():
        if not isinstance(k, str):
            raise unknown_key_error(f"{path}: {key}", repr(k), params)
        if k not in params:
            raise unknown_key_error(f"{path}: {key}", k, params)
        checked[k] = params[k].check(v, f"{path}: {key}.{k}")
    return checked


def _output_dir(path: Path, base: Path, top: dict) -> Path:
    """The absolute output folder; it must not be an existing file."""
    out = top.get("output_dir", TOP_LEVEL["output_dir"].default)
    if not out.strip():
        raise ConfigError(f"{path}: output_dir: expected a folder name, got {out!r}")
    output_dir = (base / out).resolve()
    if output_dir.exists() and not output_dir.is_dir():
        raise ConfigError(f"{path}: output_dir: {output_dir} exists and is not a folder; choose another output_dir")
    return output_dir


def load_config(path: str | os.PathLike, stages: dict, overrides=()) -> Config:
    """Read and validate a run config.

    Parameters
    ----------
    path : path-like
        YAML file.
    stages : dict
        Stage name to its list of :class:`Param` (from :mod:`retarget_cli.run.pipeline`).
    overrides : iterable of str
        ``stage.key=value`` strings that take precedence over the file.

    Raises
    ------
    ConfigError
        For a missing or malformed file, an unknown section or key, a wrong
        type or an out-of-range value; the message names file and key.
    """
    path = Path(path)
    raw = _read_raw(path, stages)
    _apply_overrides(raw, path, stages, overrides)
    valid_top = set(TOP_LEVEL) | set(stages)
    sections = {}
    top = {}
    for key, value in raw.items():
        key = str(key)
        if key not in valid_top:
            raise unknown_key_error(str(path), key, valid_top)
        if key in TOP_LEVEL:
            top[key] = TOP_LEVEL[key].check(value, f"{path}: {key}")
        else:
            sections[key] = _check_section(path, key, value, {p.name: p for p in stages[key]})
    base = path.resolve().parent
    output_dir = _output_dir(path, base, top)
    return Config(path, base, output_dir, top.get("seed", 0), sections)


# --------------------------------------------------------------------------- the Python API checks its arguments too


def _plain(value):
    """A runner's argument as YAML would give it: numpy scalars as Python numbers, paths as strings, tuples as lists."""
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    if isinstance(value, list):
        return [_plain(v) for v in value]
    if hasattr(value, "item") and getattr(value, "shape", None) == ():
        return value.item()
    return value


def validate_params(params):
    """Decorator: check every setting a runner is called with against its :class:`Param` (as scikit-learn's
    ``validate_params`` does), so the Python API refuses what ``retarget run`` and the CLI refuse.

    Only the arguments the caller gives are checked (a runner's own defaults are its declaration's; a test
    checks that). *params* is a list, or a function returning one when extensions add declarations. The
    declarations are kept on the runner as ``params``.

    Raises
    ------
    ParameterError
        Naming the argument and what was expected.
    """
    import functools
    import inspect


    def declared() -> dict:
        return {p.name: p for p in (params() if callable(params) else params) if p.kind == "setting"}

    def decorate(fn):
        signature = inspect.signature(fn)

        @functools.wraps(fn)
        def runner(*args, **kwargs):
            bound = signature.bind(*args, **kwargs)
            settings = declared()
            extra = [n for n, v in signature.parameters.items() if v.kind is inspect.Parameter.VAR_KEYWORD]
            given = dict(bound.arguments)
            for n in extra:  # **settings of extensions: each must be declared
                for name in given.pop(n, {}):
                    if name not in settings:
                        raise ParameterError(f"{fn.__name__}: unexpected setting {name!r}")
                    given[name] = bound.arguments[n][name]
            for name, value in given.items():
                p = settings.get(name)
                if p is not None:
                    try:
                        p.check(_plain(value), name)
                    except ConfigError as exc:
                        raise ParameterError(str(exc)) from None
            return fn(*args, **kwargs)

        runner.params = params
        return runner

    return decorate


def output_flag(default=None, help: str = "Output file.", required: bool = True) -> Flag:
    """The ``-o/--output`` flag of a command (a file, or a folder for a command with ``folder_output``)."""
    return Flag("output", decls=("-o", "--output"), path="out", default=default, help=help,
                required=required, show_default=default is not None)
