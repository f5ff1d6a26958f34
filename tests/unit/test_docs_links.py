"""Every relative link in README.md, CONTRIBUTING.md and docs/*.md resolves.

A link is ``[text](target)`` or ``![alt](target)`` outside fenced code; a
target without a scheme must name an existing file (relative to the page) and,
with ``#anchor`` on a Markdown page, a heading of that page (GitHub's slugs).
"""

from __future__ import annotations

import re
import unicodedata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PAGES = sorted([ROOT / "README.md", ROOT / "CONTRIBUTING.md", *(ROOT / "docs").glob("*.md")])
LINK_RE = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def _prose(text: str) -> list[str]:
    """Lines outside fenced code blocks, inline code removed."""
    out, fenced = [], False
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if not fenced:
            out.append(re.sub(r"`[^`]*`", "", line))
    return out


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = heading.strip().lower()
    text = re.sub(r"<[^>]+>", "", text)
    kept = []
    for ch in text:
        cat = unicodedata.category(ch)
        if ch in " -_" or cat[0] in "LNM":
            kept.append(ch)
    return "".join(kept).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    found, seen, fenced = set(), {}, False
    for line in page.read_text(encoding="utf-8").splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        m = None if fenced else re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line)
        if m:
            base = slug(m.group(1))
            n = seen.get(base, 0)
            seen[base] = n + 1
            found.add(base if n == 0 else f"{base}-{n}")
    return found


def broken_links(page: Path, root: Path = ROOT) -> list[str]:
    """One message per link of *page* that does not resolve (named relative to *root*)."""
    bad = []
    for line in _prose(page.read_text(encoding="utf-8")):
        for target in LINK_RE.findall(line):
            if re.match(r"[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
                continue
            path, _, anchor = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            if not dest.exists():
                bad.append(f"{page.relative_to(root)}: {target} (no such file)")
            elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
                bad.append(f"{page.relative_to(root)}: {target} (no heading #{anchor} in {dest.name})")
    return bad


def test_slug_matches_github():
    assert slug("Pretrained detector: `detect`, `--init auto`, `annotate`") == \
        "pretrained-detector-detect---init-auto-annotate"
    assert slug("Rig editing (`bench/edit.py`)") == "rig-editing-bencheditpy"
    assert slug("`edits.yaml`") == "editsyaml"


def test_checker_finds_a_broken_link(tmp_path):
    page = tmp_path / "p.md"
    page.write_text("# Title\n[ok](#title) [gone](missing.md) [bad](#nope)\n```\n[code](ignored.md)\n```\n")
    bad = broken_links(page.resolve(), tmp_path.resolve())
    assert bad == ["p.md: missing.md (no such file)", "p.md: #nope (no heading #nope in p.md)"]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page):
    assert page.exists(), f"{page.relative_to(ROOT)} is missing"
    bad = broken_links(page)
    assert not bad, "broken links:\n" + "\n".join(bad)
