"""The lowest versions pyproject.toml admits, as pip constraints: ``name==lower`` for every ``name>=lower``.

    python tools/lower_bounds.py [EXTRA ...]            the constraints of the dependencies and of the extras named
    python tools/lower_bounds.py --wheels [EXTRA ...]   the names among them that must install from wheels

pip has no ``--resolution lowest`` (uv's ``lowest-direct``): ``pip install -c constraints.txt`` with these pins
installs exactly the lower bound of each direct dependency, so a bound that names a release that does not exist, has
no wheel for the oldest supported Python (``--only-binary`` on the ``--wheels`` names) or does not work fails
``.ci/run``'s lower-bounds job, and the bound in pyproject.toml is raised to one that does. Indirect dependencies
resolve as pip likes within these pins. Requirements without a ``>=`` bound are left out.
"""

from __future__ import annotations

import re
import sys
import tomllib
from pathlib import Path

PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"

#: Distributions that publish only a source archive (no wheel at any version): built from it like any user's install.
SDIST_ONLY = {"face-recognition-models"}

_REQ = re.compile(r"^\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*(?:\[[^\]]*\])?\s*([^;]*)")


def canonical(name: str) -> str:
    """The PEP 503 normalised name (``face_recognition_models`` -> ``face-recognition-models``)."""
    return re.sub(r"[-_.]+", "-", name).lower()


def lower_bounds(extras=()) -> dict[str, str]:
    """``{name: lowest version}`` of the project's dependencies and of *extras*, in pyproject.toml's order.

    Raises
    ------
    SystemExit
        On an extra that pyproject.toml does not declare.
    """
    project = tomllib.loads(PYPROJECT.read_text())["project"]
    optional = project.get("optional-dependencies", {})
    unknown = [e for e in extras if e not in optional]
    if unknown:
        raise SystemExit(f"lower_bounds: {PYPROJECT.name} has no extra {unknown[0]!r} (extras: {', '.join(optional)})")
    reqs = list(project.get("dependencies", [])) + [r for e in extras for r in optional[e]]
    out = {}
    for req in reqs:
        m = _REQ.match(req)
        if not m:
            raise SystemExit(f"lower_bounds: cannot read the requirement {req!r} of {PYPROJECT.name}")
        for spec in m.group(2).split(","):
            spec = spec.strip()
            if spec.startswith(">="):
                out[m.group(1)] = spec[2:].strip()
    return out


def main(argv) -> int:
    wheels = "--wheels" in argv
    bounds = lower_bounds([a for a in argv if a != "--wheels"])
    if wheels:
        print(",".join(n for n in bounds if canonical(n) not in SDIST_ONLY))
    else:
        print("# The lowest versions pyproject.toml admits (tools/lower_bounds.py)")
        print("\n".join(f"{n}=={v}" for n, v in bounds.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
