"""Meshes with blend shapes read from a scene file (USD, FBX), assembled into the glTF reader's result.

The USD and FBX readers (:mod:`.usd`, :mod:`.fbx`) list the file's meshes as :class:`SceneMesh`
(world-space points, triangles, named blend shapes whose deltas are read on demand); :func:`assemble`
chooses meshes and targets with the same ``meshes=``/``targets=`` glob rules as
:func:`~retarget_cli.io.rig.gltf.read_gltf_rig` and returns the same
:class:`~retarget_cli.io.rig.gltf.GltfRig`, so :func:`~retarget_cli.io.rig.load_rig` treats every format alike.

Sliders (``groups``) are the targets grouped by name across meshes (each at weight 1), with the two rules of
the glTF reader: a prefix ``node.`` shared by every target of a mesh is dropped before comparing (the
blend-shape deformer's name FBX tools prepend: ``Squish.TopH`` -> ``TopH``), and a target ``t_X`` joins the
slider ``X`` of another mesh when its own mesh has no ``X``; and before them, a name ``X.X`` (a deformer with one
channel of its own name, as Blender and Assimp's FBX exporter write them) is compared as ``X``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from fnmatch import fnmatchcase

import numpy as np

from ...errors import InputError, ParameterError
from .gltf import MAX_DENSE_BYTES, GltfOutline, GltfRig

log = logging.getLogger(__name__)


@dataclass
class SceneMesh:
    """One mesh of a scene file, placed in world space.

    Attributes
    ----------
    name : str
        Unique among the file's meshes (what ``meshes=`` patterns and ``mesh_ranges`` show).
    points : ndarray, shape (n, 3), float64
        World-space vertices.
    faces : ndarray, shape (F, 3), int64
        Triangles into ``points``.
    labels : list of str
        The blend shapes' names, in the file's order.
    deltas : list of callable
        ``deltas[k]()`` -> (n, 3) float64, blend shape k at full weight in world space (read when chosen).
    aliases : tuple of str
        Other names the mesh answers to in ``meshes=`` (a prim path, a node name).
    """

    name: str
    points: np.ndarray
    faces: np.ndarray
    labels: list = field(default_factory=list)
    deltas: list = field(default_factory=list)
    aliases: tuple = ()


def _patterns(value, what: str) -> list[str]:
    pats = [value] if isinstance(value, str) else list(value)
    if not pats or not all(isinstance(p, str) and p for p in pats):
        raise ParameterError(f"{what}: expected glob patterns (non-empty strings), got {value!r}")
    return pats


def _choose(name: str, meshes: list[SceneMesh], patterns) -> list[SceneMesh]:
    """The meshes *patterns* name (each must match one), or every mesh with blend shapes."""
    if patterns is None:
        return [m for m in meshes if m.labels]
    chosen = set()
    for pat in _patterns(patterns, "meshes"):
        hits = {i for i, m in enumerate(meshes) if any(fnmatchcase(s, pat) for s in (m.name, *m.aliases))}
        if not hits:
            shown = ", ".join(m.name for m in meshes[:20]) or "none"
            raise InputError(f"{name}: meshes: {pat!r} matches no mesh; the file's meshes: {shown}"
                             + (f", ... ({len(meshes)} in all)" if len(meshes) > 20 else ""))
        chosen |= hits
    return [m for i, m in enumerate(meshes) if i in chosen]


def _unique_names(chosen: list[SceneMesh], table: list) -> list[str]:
    """The target's name, ``mesh/name`` where it occurs on several meshes, ``~2`` ... for repeats."""
    owners: dict[str, set] = {}
    for i, k in table:
        owners.setdefault(chosen[i].labels[k], set()).add(i)
    out, used = [], set()
    for i, k in table:
        label = chosen[i].labels[k] or f"#{k}"
        name = label if len(owners.get(chosen[i].labels[k], ())) == 1 else f"{chosen[i].name}/{label}"
        base, n = name, 2
        while name in used:
            name, n = f"{base}~{n}", n + 1
        used.add(name)
        out.append(name)
    return out


def _filter(name: str, chosen, table, unique, targets) -> list[int]:
    if targets is None:
        return list(range(len(table)))
    keep = set()
    for pat in _patterns(targets, "targets"):
        hits = {j for j, (i, k) in enumerate(table)
                if fnmatchcase(unique[j], pat) or fnmatchcase(chosen[i].labels[k], pat)
                or fnmatchcase(f"{chosen[i].name}/{chosen[i].labels[k]}", pat)}
        if not hits:
            shown = ", ".join(unique[:12]) + (f", ... ({len(unique)} in all)" if len(unique) > 12 else "")
            raise InputError(f"{name}: targets: {pat!r} matches no blend shape; the blend shapes: {shown}")
        keep |= hits
    return sorted(keep)


def _slider_keys(name: str, chosen: list[SceneMesh], table: list) -> list[str]:
    """The name each kept target is grouped under: ``X.X`` as ``X``, rule (1) common ``prefix.`` dropped, rule (2) ``t_X``."""
    per_mesh: dict[int, list[int]] = {}
    for j, (i, _) in enumerate(table):
        per_mesh.setdefault(i, []).append(j)
    keys = [chosen[i].labels[k] for i, k in table]
    for j, key in enumerate(keys):  # rule (0): a channel named as its own deformer (Blender, Assimp's exporter)
        head, dot, tail = key.partition(".")
        if dot and head == tail:
            keys[j] = head
    for i, rows in per_mesh.items():
        labels = [keys[j] for j in rows]
        heads = {lab.split(".", 1)[0] for lab in labels if "." in lab}
        if len(heads) == 1 and all("." in lab and lab.split(".", 1)[1] for lab in labels):
            log.info("%s: mesh '%s': blend shape names compared without their common prefix '%s.'", name,
                     chosen[i].name, heads.pop())
            for j in rows:
                keys[j] = keys[j].split(".", 1)[1]
    for i, rows in per_mesh.items():
        mine = {keys[j] for j in rows}
        others = {keys[j] for r, js in per_mesh.items() if r != i for j in js}
        for j in rows:
            if keys[j].startswith("t_") and keys[j][2:] in others and keys[j][2:] not in mine:
                log.info("%s: mesh '%s': blend shape %s joins slider %s (t_X rule)", name, chosen[i].name,
                         keys[j], keys[j][2:])
                keys[j] = keys[j][2:]
    return keys


def _plan(name: str, meshes: list[SceneMesh], mesh_patterns, targets):
    chosen = _choose(name, meshes, mesh_patterns)
    table = [(i, k) for i, m in enumerate(chosen) for k in range(len(m.labels))]
    if not table:
        shown = ", ".join(m.name for m in (chosen if mesh_patterns else meshes)[:20]) or "none in the file"
        raise InputError(f"{name}: no blend shapes in {'the chosen meshes' if mesh_patterns else 'any mesh'} "
                         f"(meshes: {shown})")
    unique = _unique_names(chosen, table)
    keep = _filter(name, chosen, table, unique, targets)
    return chosen, [table[j] for j in keep], [unique[j] for j in keep]


def assemble(name: str, meshes: list[SceneMesh], *, mesh_patterns=None, targets=None, kind: str,
             rig_class: Callable = GltfRig, **extra) -> GltfRig:
    """Choose meshes and targets and build the rig: neutral, triangles, mesh ranges, dense deltas, sliders.

    Parameters
    ----------
    name : str
        How errors name the file.
    meshes : list of SceneMesh
        Every mesh of the file, in scene order.
    mesh_patterns, targets : str or list of str, optional
        As :func:`~retarget_cli.io.rig.gltf.read_gltf_rig`'s ``meshes`` and ``targets``.
    kind : str
        The result's ``kind`` (``"usd"``, ``"fbx"``).
    rig_class : type
        :class:`GltfRig` or a subclass; *extra* are its further fields.

    Raises
    ------
    InputError
        No blend shapes, a pattern that matches nothing, too large a delta array, non-finite values.
    """
    chosen, table, unique = _plan(name, meshes, mesh_patterns, targets)
    V = sum(len(m.points) for m in chosen)
    if len(table) * V * 24 > MAX_DENSE_BYTES:
        raise InputError(f"{name}: {len(table)} blend shapes x {V} vertices need {len(table) * V * 24 >> 20} MiB "
                         f"of deltas, more than {MAX_DENSE_BYTES >> 20} MiB: choose meshes: or targets:")
    start = np.cumsum([0] + [len(m.points) for m in chosen])
    neutral = np.concatenate([m.points for m in chosen]).astype(np.float64).reshape(-1, 3)
    faces = np.concatenate([m.faces + start[i] for i, m in enumerate(chosen)]).astype(np.int64).reshape(-1, 3)
    deltas = np.zeros((len(table), V, 3))
    for j, (i, k) in enumerate(table):
        d = np.asarray(chosen[i].deltas[k](), dtype=np.float64)
        if d.shape != chosen[i].points.shape:
            raise InputError(f"{name}: mesh '{chosen[i].name}' blend shape '{chosen[i].labels[k]}': {d.shape} "
                             f"offsets for {len(chosen[i].points)} vertices")
        deltas[j, start[i]:start[i + 1]] = d
    if not (np.isfinite(neutral).all() and np.isfinite(deltas).all()):
        raise InputError(f"{name}: positions or blend shape offsets are not finite (once placed in the scene)")
    groups: dict[str, list] = {}
    for j, key in enumerate(_slider_keys(name, chosen, table)):
        groups.setdefault(key, []).append((j, 1.0))
    return rig_class(neutral=neutral, faces=faces, mesh_ranges=[(m.name, int(start[i]), int(start[i + 1]))
                                                                for i, m in enumerate(chosen)],
                     target_names=unique, deltas=deltas, groups=groups,
                     raw_groups={n: [(k, 1.0)] for k, n in enumerate(unique)}, kind=kind,
                     target_meshes=[chosen[i].name for i, _ in table], target_refs=list(table), **extra)


def outline(rig: GltfRig, files: list) -> GltfOutline:
    """The :class:`GltfOutline` of a rig already read (USD and FBX have no cheaper outline than a read)."""
    return GltfOutline(n_vertices=len(rig.neutral), mesh_ranges=list(rig.mesh_ranges),
                       target_names=list(rig.target_names), target_meshes=list(rig.target_meshes),
                       groups=dict(rig.groups), raw_groups=dict(rig.raw_groups), kind=rig.kind, files=list(files))


__all__ = ["SceneMesh", "assemble", "outline"]
