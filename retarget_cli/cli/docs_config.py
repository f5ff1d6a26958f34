"""Generate the config reference (``docs/config.md``) from the declared parameters.

Every stage declares its parameters once (:class:`retarget_cli.config.Param`);
this module renders them as Markdown, so the reference cannot drift from the
code. ``tests/unit/cli/test_docs_config.py`` fails when ``docs/config.md`` differs
from :func:`render_config_reference`. Regenerate with::

    python -m retarget_cli.cli.docs_config > docs/config.md

Only public names are used: :func:`retarget_cli.run.pipeline.stage_params` (or
``STAGES``, a mapping of stage name to an object with ``params`` and ``help``),
:data:`retarget_cli.config.TOP_LEVEL` and the attributes of ``Param``.
"""

from __future__ import annotations

import sys

from .. import config
from ..run import pipeline

COMMAND = "python -m retarget_cli.cli.docs_config > docs/config.md"

_INTRO = f"""\
# Config reference

<!-- Generated from the Param declarations by `{COMMAND}`; do not edit by hand
(tests/unit/cli/test_docs_config.py fails when this file is stale). -->

A config is YAML with one section per stage; a stage runs when its section is
present (`retarget run CONFIG`). Input paths are relative to the config file,
outputs relative to `output_dir`. Unknown keys are errors that name the file
and suggest the closest valid key; values are checked (type, range, choices)
before anything runs. Any value can be overridden on the command line with
`--set STAGE.KEY=VALUE` (or `--set seed=3`, `--set output_dir=out2`). The
stage's own command takes the same settings as options (`track.fb_threshold`
is `retarget track --fb-threshold`).

Columns: **kind** is `input` (a file read, hashed in the manifest), `output`
(a file written) or `setting` (a value); **default** `required` means the key
must be given; `from track.output` means that under `retarget run` the input
defaults to that stage's output (on the command line it is an argument);
**range / choices** is what validation accepts (`null` allowed where it says
so).

Method-specific meaning is in the method pages: [tracking](tracking.md),
[selection](selection.md), [decomposition](decomposition.md),
[auto-pose](auto-pose.md), [apply](apply.md), [temporal quality](temporal.md);
file layouts in [formats](formats.md).
"""


def _code(value) -> str:
    text = str(value).replace("|", "\\|")
    return f"`{text}`"


def _cell(text: str) -> str:
    """One Markdown table cell: no newlines, escaped pipes."""
    return " ".join(str(text).split()).replace("|", "\\|")


def _type_name(p) -> str:
    t = getattr(p, "type", None)
    return getattr(t, "__name__", str(t))


def _num(x) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def _default(p) -> str:
    link = getattr(p, "link", None)
    if link and (p.default is config.REQUIRED or p.default is None):
        return f"from `{link}`"
    if p.default is config.REQUIRED:
        return "required"
    if p.default is None:
        return "none"
    if isinstance(p.default, bool):
        return _code("true" if p.default else "false")
    if isinstance(p.default, (list, tuple)):
        return _code("[" + ", ".join(map(str, p.default)) + "]")
    if isinstance(p.default, dict):
        return _code("{" + ", ".join(f"{k}: {v}" for k, v in p.default.items()) + "}")
    return _code(repr(p.default) if isinstance(p.default, float) else p.default)


def _range(p) -> str:
    parts = []
    if p.options:
        joined = ", ".join(_code(c) for c in p.options)
        parts.append(("any of " if p.type is list else "") + joined)
    elif p.min is not None or p.max is not None:
        lo = "−∞" if p.min is None else _num(p.min)
        hi = "∞" if p.max is None else _num(p.max)
        parts.append(f"{'(' if p.min_open else '['}{lo}, {hi}{')' if p.max_open else ']'}")
    words = getattr(p, "words", ())
    if words:
        parts.append("or " + ", ".join(_code(w) for w in words))
    if getattr(p, "nullable", False):
        parts.append("or `null`")
    return "; ".join(parts)


def _table(params) -> list[str]:
    lines = ["| name | kind | type | default | range / choices | help |", "|---|---|---|---|---|---|"]
    for p in params:
        lines.append("| " + " | ".join([
            f"`{p.name}`", p.kind, _type_name(p), _cell(_default(p)), _cell(_range(p)), _cell(p.help),
        ]) + " |")
    return lines


def declared_stages() -> dict[str, tuple[str, list]]:
    """Stage name to ``(help, params)``, in pipeline order.

    Uses :func:`retarget_cli.run.pipeline.stage_params` when it exists, else the
    ``params`` of each entry of ``STAGES``; the help text is the stage's
    ``help`` attribute (empty when it has none).
    """
    stages = getattr(pipeline, "STAGES", {})
    if hasattr(pipeline, "stage_params"):
        declared = pipeline.stage_params()
    else:  # pragma: no cover - older layouts
        declared = {name: s.params for name, s in stages.items()}
    return {name: (getattr(stages.get(name), "help", "") or "", list(params)) for name, params in declared.items()}


def render_config_reference() -> str:
    """The config reference as Markdown.

    Returns
    -------
    str
        A page with the top-level keys and, per stage in pipeline order, a
        table ``name | kind | type | default | range / choices | help``
        rendered from the stage's declared :class:`~retarget_cli.config.Param` s.
    """
    out = [_INTRO, "## Top level", ""]
    out += _table(config.TOP_LEVEL.values())
    for name, (help_text, params) in declared_stages().items():
        out += ["", f"## `{name}`", ""]
        if help_text:
            out += [_cell(help_text), ""]
        out += _table(params)
    return "\n".join(out) + "\n"


def main() -> None:
    """Print the reference to stdout (``python -m retarget_cli.cli.docs_config > docs/config.md``)."""
    sys.stdout.write(render_config_reference())


if __name__ == "__main__":
    main()
