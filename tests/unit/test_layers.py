"""The package's real imports against the layer table of docs/architecture.md.

The table is the single statement of which folder may import which; this test
reads it, reads every import of every module (at the top and inside functions)
and fails on an import against the table, an import cycle, or an internal
import hidden inside a function that is not a declared lazy one.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "retarget_cli"
DOC = ROOT / "docs" / "architecture.md"

#: Internal modules that may be imported inside a function: the numba kernels, compiled on first use.
LAZY_ALLOWED = ("retarget_cli.methods.decomposition._qp_kernel", "retarget_cli.methods.tracking._kernels")
#: Modules whose internal imports are all inside functions: the console script, so that a Ctrl-C while the
#: CLI's modules load is still one line and exit status 130 (its docstring says why).
LAZY_IMPORTERS = ("retarget_cli.entry",)


def read_layers(text: str) -> tuple[dict[str, str], dict[str, set[str]]]:
    """The layer table: ``{module prefix: layer}`` and ``{layer: layers it may import}``.

    Rows look like ``| cli | `cli/`, `entry`, `__main__` | everything below |``: the
    first cell names the layer, the second its folders (``name/``) and modules
    (``name``), the third the layers it may import (``everything below`` = every
    earlier row), always including itself.
    """
    rows = re.findall(r"^\| *([a-z]+) *\| *((?:`[^`]+`[, ]*)+)\|([^|\n]*)\|", text, flags=re.M)
    if not rows:
        raise AssertionError("docs/architecture.md has no layer table")
    owner, allowed, order = {}, {}, []
    for layer, where, may in rows:
        for item in re.findall(r"`([^`]+)`", where):
            name = "" if item == "__init__" else "." + item.strip("/").replace("/", ".")
            owner["retarget_cli" + name] = layer
        may = may.strip()
        if may.startswith("everything below"):
            allowed[layer] = set(order)
        else:
            allowed[layer] = {m for m in re.findall(r"`([a-z]+)`", may)}
        allowed[layer].add(layer)
        order.append(layer)
    return owner, allowed


def layer_of(module: str, owner: dict[str, str]) -> str | None:
    best = max((p for p in owner if module == p or (p != "retarget_cli" and module.startswith(p + "."))), key=len,
               default=None)
    return owner[best] if best else None


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def resolve(node: ast.ImportFrom | ast.Import, module: str, is_package: bool, known: set[str]) -> list[str]:
    """The internal modules an import statement loads (``from .a import b`` loads ``a.b`` if it is a module)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names if a.name.split(".")[0] == "retarget_cli"]
    if node.level:
        base = module.split(".") if is_package else module.split(".")[:-1]
        base = base[:len(base) - node.level + 1]
        target = ".".join(base + ([node.module] if node.module else []))
    else:
        target = node.module or ""
    if target.split(".")[0] != "retarget_cli":
        return []
    out = []
    for a in node.names:
        sub = f"{target}.{a.name}"
        out.append(sub if sub in known else target)
    return out


def import_graph(root: Path) -> list[tuple[str, str, int, bool]]:
    """Every internal import of the package under *root*: (importer, imported, line, at module level)."""
    files = {module_name(p, root): p for p in root.rglob("*.py")}
    known = set(files)
    edges = []
    for mod, path in files.items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        top = {id(n) for n in tree.body}
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for target in resolve(node, mod, path.name == "__init__.py", known):
                    if target != mod:
                        edges.append((mod, target, node.lineno, id(node) in top))
    return edges


def violations(root: Path, doc_text: str) -> list[str]:
    """Every import of the package under *root* that breaks the layer table in *doc_text*."""
    owner, allowed = read_layers(doc_text)
    problems = []
    edges = import_graph(root)
    for mod, target, line, at_top in edges:
        a, b = layer_of(mod, owner), layer_of(target, owner)
        where = f"{mod.replace('.', '/')}.py:{line}"
        if a is None:
            problems.append(f"{where}: {mod} is in no layer of docs/architecture.md")
        elif b is None:
            problems.append(f"{where}: imports {target}, which is in no layer")
        elif b not in allowed[a]:
            problems.append(f"{where}: layer {a} imports {target} (layer {b}); it may import {sorted(allowed[a])}")
        if not at_top and target not in LAZY_ALLOWED and mod not in LAZY_IMPORTERS:
            problems.append(f"{where}: imports {target} inside a function; internal imports go at the top")
    problems += [f"import cycle: {' -> '.join(c)}" for c in cycles([(m, t) for m, t, _, top in edges if top])]
    return problems


def cycles(edges) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan), each as a closed path."""
    graph: dict[str, set[str]] = {}
    for a, b in edges:
        graph.setdefault(a, set()).add(b)
        graph.setdefault(b, set())
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp) + [sorted(comp)[0]])

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_package_follows_the_layer_table():
    assert violations(PACKAGE, DOC.read_text(encoding="utf-8")) == []


def test_every_module_has_a_layer():
    owner, _ = read_layers(DOC.read_text(encoding="utf-8"))
    lost = [module_name(p, PACKAGE) for p in PACKAGE.rglob("*.py") if layer_of(module_name(p, PACKAGE), owner) is None]
    assert lost == []


def test_package_root_holds_only_cross_cutting_modules():
    root = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert root == ["__init__.py", "__main__.py", "_validate.py", "config.py", "entry.py", "errors.py"]


def _copy_package(tmp_path: Path) -> Path:
    import shutil

    dst = tmp_path / "retarget_cli"
    shutil.copytree(PACKAGE, dst, ignore=shutil.ignore_patterns("__pycache__"))
    return dst


@pytest.mark.parametrize("line, expected", [
    ("from ..cli import commands", "layer stages imports retarget_cli.cli.commands (layer cli)"),
    ("from ..run.pipeline import STAGES", "layer stages imports retarget_cli.run.pipeline (layer run)"),
])
def test_a_stage_importing_upward_fails(tmp_path, line, expected):
    pkg = _copy_package(tmp_path)
    stage = pkg / "stages" / "select.py"
    stage.write_text(stage.read_text() + f"\n{line}\n")
    found = violations(pkg, DOC.read_text(encoding="utf-8"))
    assert any(expected in v for v in found), found


def test_a_cycle_and_a_hidden_import_fail(tmp_path):
    pkg = _copy_package(tmp_path)
    io_obj = pkg / "io" / "obj.py"
    io_obj.write_text(io_obj.read_text() + "\nfrom .rig.cache import load_rig_meshes\n\n\ndef _f():\n"
                      "    from .landmarks import load_landmarks\n")
    found = violations(pkg, DOC.read_text(encoding="utf-8"))
    assert any(v.startswith("import cycle:") and "retarget_cli.io.obj" in v for v in found), found
    assert any("imports retarget_cli.io.landmarks inside a function" in v for v in found), found
