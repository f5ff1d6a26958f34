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

from ...errors import InputError
from ._names import filter_targets, patterns, slider_keys, unique_names
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


def _choose(name: str, meshes: list[SceneMesh], mesh_patterns) -> list[SceneMesh]:
    """The meshes *patterns* name (each must match one), or every mesh with blend shapes."""
    if mesh_patterns is None:
        return [m for m in meshes if m.labels]
    chosen = set()
    for pat in patterns(mesh_patterns, "meshes"):
        hits = {i for i, m in enumerate(meshes) if any(fnmatchcase(s, pat) for s in (m.name, *m.aliases))}
        if not hits:
            shown = ", ".join(m.name for m in meshes[:20]) or "none"
            raise InputError(f"{name}: meshes: {pat!r} matches no mesh; the file's meshes: {shown}"
                             + (f", ... ({len(meshes)} in all)" if len(meshes) > 20 else ""))
        chosen |= hits
    return [m for i, m in enumerate(meshes) if i in chosen]


def _slider_keys(name: str, chosen: list[SceneMesh], table: list) -> list[str]:
    """The name each kept target is grouped under (:func:`._names.slider_keys`, with ``X.X`` read as ``X``)."""
    rows: dict[int, list[int]] = {}
    for j, (i, _) in enumerate(table):
        rows.setdefault(i, []).append(j)
    meshes = list(rows)
    keys = slider_keys(name, [[chosen[i].labels[table[j][1]] for j in rows[i]] for i in meshes],
                       [chosen[i].name for i in meshes], same_as_deformer=True, noun="blend shape")
    out = [""] * len(table)
    for i, own in zip(meshes, keys):
        for j, key in zip(rows[i], own):
            out[j] = key
    return out


def _plan(name: str, meshes: list[SceneMesh], mesh_patterns, targets):
    chosen = _choose(name, meshes, mesh_patterns)
    table = [(i, k) for i, m in enumerate(chosen) for k in range(len(m.labels))]
    if not table:
        shown = ", ".join(m.name for m in (chosen if mesh_patterns else meshes)[:20]) or "none in the file"
        raise InputError(f"{name}: no blend shapes in {'the chosen meshes' if mesh_patterns else 'any mesh'} "
                         f"(meshes: {shown})")
    labels, names = [[lab or None for lab in m.labels] for m in chosen], [m.name for m in chosen]
    unique = unique_names(table, labels, names)
    keep = filter_targets(table, unique, labels, names, targets, noun="blend shape",
                          fail=lambda message: InputError(f"{name}: {message}"))
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
