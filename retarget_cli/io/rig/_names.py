"""Target names and slider keys shared by the character readers (glTF/VRM :mod:`.gltf`, USD and FBX :mod:`._scene`).

- :func:`unique_names`: each target's unique name (its own, ``mesh/name`` where several chosen meshes have it,
  ``mesh/#k`` when unnamed, ``~2`` ... for repeats);
- :func:`filter_targets`: the ``targets=`` glob patterns;
- :func:`slider_keys`: the name each target is grouped under into a slider, by the readers' rules: (0, USD and
  FBX only) ``X.X`` is ``X``; (1) a prefix ``node.`` shared by every target of a mesh is dropped; (2) ``t_X``
  joins the slider ``X`` of another mesh when its own mesh has no ``X``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from fnmatch import fnmatchcase

from ...errors import ParameterError

log = logging.getLogger(__name__)


def patterns(value, what: str) -> list[str]:
    """*value* (a glob pattern or a list of them) as a list; a :class:`ParameterError` for anything else."""
    pats = [value] if isinstance(value, str) else list(value)
    if not pats or not all(isinstance(p, str) and p for p in pats):
        raise ParameterError(f"{what}: expected glob patterns (non-empty strings), got {value!r}")
    return pats


def unique_names(table: list, labels: list, meshes: list[str]) -> list[str]:
    """Unique target names of the ``(mesh i, target k)`` pairs of *table*.

    Parameters
    ----------
    table : list of (int, int)
    labels : list of list of (str or None)
        ``labels[i][k]``: target k's name on mesh i (None when unnamed).
    meshes : list of str
        Mesh i's name.
    """
    owners: dict[str, set] = {}
    for i, k in table:
        if labels[i][k] is not None:
            owners.setdefault(labels[i][k], set()).add(i)
    out, used = [], set()
    for i, k in table:
        label = labels[i][k]
        name = f"{meshes[i]}/#{k}" if label is None else label if len(owners[label]) == 1 else f"{meshes[i]}/{label}"
        base, n = name, 2
        while name in used:
            name, n = f"{base}~{n}", n + 1
        used.add(name)
        out.append(name)
    return out


def filter_targets(table: list, unique: list[str], labels: list, meshes: list[str], targets, *,
                   fail: Callable[[str], Exception], noun: str = "morph target") -> list[int]:
    """Indices into *table* of the targets the *targets* patterns keep (all when None).

    A pattern matches a target's unique name, its own name or ``mesh/name``; one that matches none raises
    ``fail(message)``.
    """
    if targets is None:
        return list(range(len(table)))
    keep = set()
    for pat in patterns(targets, "targets"):
        hits = {j for j, (i, k) in enumerate(table)
                if fnmatchcase(unique[j], pat) or fnmatchcase(labels[i][k] or "", pat)
                or fnmatchcase(f"{meshes[i]}/{labels[i][k]}", pat)}
        if not hits:
            shown = ", ".join(unique[:12]) + (f", ... ({len(unique)} in all)" if len(unique) > 12 else "")
            raise fail(f"targets: {pat!r} matches no {noun}; the {noun}s: {shown}")
        keep |= hits
    return sorted(keep)


def slider_keys(name: str, labels: list, meshes: list[str], *, same_as_deformer: bool = False,
                noun: str = "target") -> list[list]:
    """Per mesh, the name each target is grouped under (None when unnamed): rules (0) to (2) of the module.

    Parameters
    ----------
    name : str
        The file, for the log.
    labels : list of list of (str or None)
        Per mesh, the names of the targets the rules look at.
    meshes : list of str
        The meshes' names, for the log.
    same_as_deformer : bool
        Apply rule (0), ``X.X`` -> ``X`` (a deformer holding one channel of its own name: Blender, Assimp).
    """
    keys = []
    for mesh, own in zip(meshes, labels):
        own = list(own)
        if same_as_deformer:
            own = [lab.partition(".")[0] if lab and lab.partition(".")[0] == lab.partition(".")[2] else lab
                   for lab in own]
        heads = {lab.split(".", 1)[0] for lab in own if lab is not None and "." in lab}
        if own and None not in own and len(heads) == 1 and all("." in lab and lab.split(".", 1)[1] for lab in own):
            log.info("%s: mesh '%s': %s names compared without their common prefix '%s.'", name, mesh, noun,
                     heads.pop())
            own = [lab.split(".", 1)[1] for lab in own]
        keys.append(own)
    for i, own in enumerate(keys):
        others = {k for j, ks in enumerate(keys) if j != i for k in ks if k is not None}
        mine = set(own)
        for k, key in enumerate(own):
            if key and key.startswith("t_") and key[2:] in others and key[2:] not in mine:
                log.info("%s: mesh '%s': %s %s joins slider %s (t_X rule)", name, meshes[i], noun, key, key[2:])
                own[k] = key[2:]
    return keys


__all__ = ["filter_targets", "patterns", "slider_keys", "unique_names"]
