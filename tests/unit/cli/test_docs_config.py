"""docs/config.md is generated from the declared parameters and must match them."""

from __future__ import annotations

from pathlib import Path

from retarget_cli import config
from retarget_cli.cli.docs_config import COMMAND, declared_stages, render_config_reference

DOC = Path(__file__).resolve().parents[3] / "docs" / "config.md"


def test_config_reference_is_up_to_date():
    assert DOC.exists(), f"docs/config.md is missing; run `{COMMAND}`"
    assert DOC.read_text(encoding="utf-8") == render_config_reference(), \
        f"docs/config.md is stale; run `{COMMAND}`"


def test_every_declared_parameter_is_in_the_reference():
    text = render_config_reference()
    sections = text.split("\n## ")
    stages = declared_stages()
    assert {"track", "select", "decompose", "apply"} <= set(stages)
    for name, (_, params) in stages.items():
        assert params, f"stage {name} declares no parameters"
        section = next((s for s in sections if s.startswith(f"`{name}`")), None)
        assert section is not None, f"stage {name} missing"
        for p in params:
            assert f"| `{p.name}` | {p.kind} |" in section, f"{name}.{p.name} missing"
    for key in config.TOP_LEVEL:
        assert f"| `{key}` |" in sections[0] + sections[1]


def test_reference_shows_defaults_ranges_and_links():
    text = render_config_reference()
    assert "| `k` | setting | int | `12` | [1, 1000] |" in text
    assert "| `landmarks` | input | str | from `track.output` |" in text
    assert "`rts`, `one-euro`, `none`" in text
    assert "| `downscale` | setting | float | `1.0` | [0.05, 1]; or `auto` |" in text


def test_a_changed_declaration_changes_the_reference(monkeypatch):
    import dataclasses

    from retarget_cli.cli import docs_config

    stages = docs_config.declared_stages()
    help_text, params = stages["select"]
    changed = [dataclasses.replace(p, default=13) if p.name == "k" else p for p in params]
    monkeypatch.setattr(docs_config, "declared_stages", lambda: {**stages, "select": (help_text, changed)})
    text = docs_config.render_config_reference()
    assert "| `k` | setting | int | `13` | [1, 1000] |" in text
    assert text != DOC.read_text(encoding="utf-8")
