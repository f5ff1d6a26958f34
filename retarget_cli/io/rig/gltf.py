"""Read a character rig (a neutral mesh, its morph targets and sliders) from a glTF 2.0, GLB or VRM file.

:func:`read_gltf_rig` is a pure reader: it opens one file (and the external
buffers beside it), writes nothing and returns a :class:`GltfRig` in world
space, in the file's units (metres for glTF).

What is read (glTF 2.0 specification, Khronos 2021):

- the default scene's node tree (``scene``, else the first scene, else every
  root node); node ``matrix`` or translation/rotation/scale, composed from the
  root (§3.5.3);
- every primitive of every chosen mesh: ``POSITION``, ``indices`` and mode
  (triangles, strips and fans become triangles; points and lines add vertices
  but no faces), each morph target's ``POSITION`` (normals and tangents are
  ignored); primitives that share their vertex accessors (one mesh, several
  materials) share their vertices;
- target names from ``mesh.extras.targetNames``, else the first primitive's
  ``extras.targetNames`` (the conventions of Blender, three.js and UniVRM);
- compressed and quantized geometry: ``KHR_mesh_quantization``,
  ``EXT_meshopt_compression``, ``KHR_draco_mesh_compression`` and sparse
  accessors (see :mod:`retarget_cli.io.rig._gltfdata`);
- skins: the mesh is placed at the skeleton's rest pose (the joint nodes' own
  transforms, no animation), where a glTF viewer shows it before any
  animation plays. The skinned node's own transform is ignored, as §3.7.3
  requires; when every joint's world matrix times its inverse bind matrix is
  the same matrix (rest pose = bind pose, the usual case, and where gltfpack
  keeps its dequantization scale) that one matrix places the mesh, else linear
  blend skinning with ``JOINTS_n``/``WEIGHTS_n`` does. Joints are not returned;
- the default morph weights (``mesh.weights``) are not applied: the neutral is
  the base mesh with every weight 0.

Sliders (:attr:`GltfRig.groups`):

- plain glTF: targets with the same name on several meshes are one slider,
  each at weight 1. Names are compared after two rules (both logged at INFO
  when they apply): (1) a prefix ``node.`` shared by *every* target name of a
  mesh is dropped (the blend-shape deformer's name that FBX exports prepend,
  ``h_expressions.MouthOpen_h`` -> ``MouthOpen_h``); (2) a target ``t_X`` on
  one mesh joins the slider ``X`` of another mesh when its own mesh has no
  ``X`` (the Character Generator teeth targets of the VALID avatars,
  ``t_MouthOpen_h`` with the head's ``MouthOpen_h``; measured on
  ``White_F_2_Busi.glb``: the 18 teeth targets with such a head partner move
  the lower teeth like the partner moves the head next to them, cosine
  0.45-0.93, median 0.79, against at most 0.23 for the 13 teeth targets
  without one; see docs/rig-files.md and bench/gltf_rigs.py);
- VRM 0.x (``extensions.VRM.blendShapeMaster.blendShapeGroups``): one slider
  per group, named by its ``presetName`` (``a``, ``blink``, ``joy``, ...) or, for
  ``unknown``, its ``name``; each bind ``(mesh, index, weight 0-100)`` adds the
  target at ``weight / 100`` on every chosen instance of that mesh;
- VRM 1.0 (``extensions.VRMC_vrm.expressions.preset`` / ``custom``): one slider
  per expression, named by its key (``aa``, ``blink``, ``happy``, ...); each
  ``morphTargetBinds`` entry ``(node, index, weight 0-1)`` adds the target of
  that node's mesh.

Groups with no bind left (VRM ``neutral``, or binds on meshes or targets not
chosen) are dropped and logged; when no VRM expression is left the sliders
are the targets grouped by name, as for plain glTF (``kind == "gltf"``). :attr:`GltfRig.raw_groups` always has one
slider per target (its unique name, weight 1): the raw targets. VRM 0.x
avatars face -z, VRM 1.0 and glTF +z; the coordinates are returned as stored.
"""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass, field
from fnmatch import fnmatchcase

import numpy as np

from ._gltfdata import GltfFile, draco_available
from ._names import filter_targets, patterns, slider_keys, unique_names

log = logging.getLogger(__name__)

#: Largest size of the dense ``deltas`` array (K * V * 3 float64) the reader allocates.
MAX_DENSE_BYTES = 1 << 31
#: Joint placements that differ by less than this (relative to the matrix) count as one bind-shape matrix.
_UNIFORM_SKIN_TOL = 1e-4
_DRACO = "KHR_draco_mesh_compression"


@dataclass(frozen=True, eq=False)
class GltfRig:
    """A blendshape rig read from a glTF/GLB/VRM file, in world space.

    Attributes
    ----------
    neutral : ndarray, shape (V, 3), float64
        Every vertex of the chosen meshes (node transforms or skin rest pose
        applied), meshes in scene order, each mesh's primitives concatenated.
    faces : ndarray, shape (F, 3), int64
        Triangles indexing ``neutral``.
    mesh_ranges : list of (str, int, int)
        ``(mesh name, start, stop)``: the rows of ``neutral`` of each mesh. The
        name is the mesh's ``name``; a mesh instanced by several nodes, or two
        meshes with one name, read ``mesh@node``.
    target_names : list of str
        K unique names: the target's name, ``mesh/target`` where a name occurs
        on several of the chosen meshes, ``mesh/#k`` for an unnamed target.
    deltas : ndarray, shape (K, V, 3), float64
        World-space displacement of each target at weight 1; zero on the
        vertices of the other meshes.
    groups : dict of str to list of (int, float)
        Slider name to its ``(target index, weight)`` pairs (see the module docstring).
    raw_groups : dict of str to list of (int, float)
        One slider per target: ``target_names[k] -> [(k, 1.0)]``.
    kind : str
        ``"gltf"``, ``"vrm0"`` or ``"vrm1"``: where ``groups`` comes from.
    target_meshes : list of str
        The mesh name of each target.
    target_refs : list of (int, int)
        ``(node index, morph target index)`` of each target in the file: where
        a writer animates it (a node's ``weights``).
    """

    neutral: np.ndarray
    faces: np.ndarray
    mesh_ranges: list
    target_names: list
    deltas: np.ndarray
    groups: dict
    raw_groups: dict
    kind: str = "gltf"
    target_meshes: list = field(default_factory=list)
    target_refs: list = field(default_factory=list)


@dataclass(frozen=True, eq=False)
class GltfOutline:
    """What :func:`read_gltf_rig` would return, from the file's JSON alone (no geometry decoded).

    Attributes
    ----------
    n_vertices : int
        V, the rows of :attr:`GltfRig.neutral` (from the declared accessor counts).
    mesh_ranges, target_names, target_meshes, groups, raw_groups, kind
        As :class:`GltfRig`'s, equal to them for the same file and filters.
    files : list of Path
        The external buffer files the rig reads (a ``.gltf``'s ``.bin``); empty for a GLB.
    """

    n_vertices: int
    mesh_ranges: list
    target_names: list
    target_meshes: list
    groups: dict
    raw_groups: dict
    kind: str
    files: list


@dataclass
class _Instance:
    """One node that draws a mesh, and what will be read of it."""

    node: int
    mesh: int
    name: str
    node_name: str
    mesh_name: str
    prims: list = field(default_factory=list)  # (index, primitive, vertex offset; -1 - offset when shared)
    n_vertices: int = 0
    n_targets: int = 0
    target_labels: list = field(default_factory=list)  # raw names (None when unnamed)


def read_gltf_rig(path, *, meshes=None, targets=None) -> GltfRig:
    """Read a rig from a glTF 2.0 (``.gltf``/``.glb``) or VRM 0.x/1.0 (``.vrm``) file.

    Parameters
    ----------
    path : str or Path
    meshes : str or list of str, optional
        Glob patterns (``fnmatch``, case-sensitive) on mesh or node names;
        those meshes are read, with or without targets. Default: every mesh
        that has morph targets. Each pattern must match a mesh.
    targets : str or list of str, optional
        Glob patterns on target names (raw or ``mesh/target``); only those
        targets are read. Each pattern must match a target.

    Returns
    -------
    GltfRig

    Raises
    ------
    InputError
        One line naming the file and the entry: malformed or truncated file,
        an accessor, buffer view or compressed stream that does not fit its
        data, an external buffer outside the rig's folder, an unsupported
        required extension, no morph targets, a pattern that matches nothing.
    MissingExtraError
        The file needs ``meshoptimizer`` or ``DracoPy`` (``pip install 'retarget[rigs]'``).
    """
    f = GltfFile(path)
    world = _node_matrices(f)
    instances, table, unique = _prepare(f, meshes, targets)
    n_vertices = sum(inst.n_vertices for inst in instances)
    if len(table) * n_vertices * 24 > MAX_DENSE_BYTES:
        raise f.error(f"{len(table)} targets x {n_vertices} vertices need {len(table) * n_vertices * 24 >> 20} MiB "
                      f"of deltas, more than {MAX_DENSE_BYTES >> 20} MiB: choose meshes= or targets=")
    neutral = np.zeros((n_vertices, 3))
    deltas = np.zeros((len(table), n_vertices, 3))
    slot = {pair: j for j, pair in enumerate(table)}
    faces, ranges, start = [], [], 0
    for i, inst in enumerate(instances):
        place = _placement(f, inst, world)
        block = slice(start, start + inst.n_vertices)
        rows = {k: slot[(i, k)] for k in range(inst.n_targets) if (i, k) in slot}
        with np.errstate(over="ignore", invalid="ignore"):  # overflow is reported once, below
            faces.append(_read_mesh(f, inst, place, neutral[block], deltas[:, block], rows) + start)
        ranges.append((inst.name, start, start + inst.n_vertices))
        start += inst.n_vertices
    if not (np.isfinite(neutral).all() and np.isfinite(deltas).all()):
        raise f.error("positions or target deltas overflow once placed in the scene (not finite)")
    kind, groups = _groups(f, instances, table, unique)
    return GltfRig(neutral=neutral, faces=np.concatenate(faces).astype(np.int64), mesh_ranges=ranges,
                   target_names=unique, deltas=deltas, groups=groups,
                   raw_groups={name: [(k, 1.0)] for k, name in enumerate(unique)}, kind=kind,
                   target_meshes=[instances[i].name for i, _ in table],
                   target_refs=[(instances[i].node, k) for i, k in table])


def node_world_matrices(f: GltfFile) -> list[np.ndarray]:
    """World matrix (4, 4), float64, of every node of an opened file (checked: types, one parent, no cycle, finite)."""
    return _node_matrices(f)


def _prepare(f: GltfFile, meshes, targets):
    """The chosen mesh instances (planned), their ``(instance, target)`` table and the targets' unique names."""
    scene = _scene_instances(f)
    instances = _choose(f, scene, meshes)
    for inst in instances:
        _plan(f, inst)
    table = [(i, k) for i, inst in enumerate(instances) for k in range(inst.n_targets)]
    if not table:
        names = ", ".join(inst.name for inst in (instances if meshes else scene)) or "none in the scene"
        raise f.error(f"no morph targets in {'the chosen meshes' if meshes else 'any mesh'} (meshes: {names})")
    labels, names = [inst.target_labels for inst in instances], [inst.name for inst in instances]
    unique = unique_names(table, labels, names)
    keep = filter_targets(table, unique, labels, names, targets, fail=f.error)
    return instances, [table[j] for j in keep], [unique[j] for j in keep]


def read_gltf_outline(path, *, meshes=None, targets=None) -> GltfOutline:
    """The meshes, targets and sliders of a rig file, from its JSON alone (nothing decoded or decompressed).

    Cheap enough to run before any heavy work (``rig.yaml``'s checks, :func:`~retarget_cli.io.rig.read_rig`):
    the same names, vertex counts and groups as :func:`read_gltf_rig` with the same arguments.

    Raises
    ------
    InputError
        As :func:`read_gltf_rig`, for everything but the binary data.
    """
    f = GltfFile(path)
    instances, table, unique = _prepare(f, meshes, targets)
    ranges, start = [], 0
    for inst in instances:
        ranges.append((inst.name, start, start + inst.n_vertices))
        start += inst.n_vertices
    kind, groups = _groups(f, instances, table, unique)
    return GltfOutline(n_vertices=start, mesh_ranges=ranges, target_names=unique,
                       target_meshes=[instances[i].name for i, _ in table], groups=groups,
                       raw_groups={name: [(k, 1.0)] for k, name in enumerate(unique)}, kind=kind,
                       files=f.external_files())


# ---------------------------------------------------------------------- nodes and scene
def _local_matrix(f: GltfFile, node: dict, where: str) -> np.ndarray:
    """A node's local transform (glTF 2.0 §3.5.3): ``matrix`` (column-major) or T * R * S."""
    m = f.numbers(node, "matrix", where, 16)
    if m is not None:
        return m.reshape(4, 4).T.copy()
    t = f.numbers(node, "translation", where, 3, np.zeros(3))
    q = f.numbers(node, "rotation", where, 4, np.array([0.0, 0.0, 0.0, 1.0]))
    s = f.numbers(node, "scale", where, 3, np.ones(3))
    with np.errstate(over="ignore", invalid="ignore"):
        norm = float(np.sqrt((q.astype(np.longdouble) ** 2).sum()))
    if not 0 < norm < np.inf:
        raise f.error(f"{where}: rotation {np.round(q, 6).tolist()} is not a quaternion")
    x, y, z, w = q / norm
    rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                    [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                    [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    out = np.eye(4)
    out[:3, :3] = rot * s[None, :]
    out[:3, 3] = t
    return out


def _parents(f: GltfFile) -> dict[int, int]:
    nodes = f.items("nodes")
    parent: dict[int, int] = {}
    for i in range(len(nodes)):
        node = f.item("nodes", i, "the file")
        for c in f.field(node, "children", f"node {i}", list, []):
            f.item("nodes", c, f"node {i} children")
            if c == i:
                raise f.error(f"node {i} is its own child")
            if c in parent:
                raise f.error(f"node {c} has two parents (node {parent[c]} and node {i})")
            parent[c] = i
    return parent


def _node_matrices(f: GltfFile) -> list[np.ndarray]:
    """World matrix (4, 4) of every node; a cycle in the node tree is an error."""
    nodes, parent = f.items("nodes"), _parents(f)
    local = [_local_matrix(f, f.item("nodes", i, "the file"), f"node {i}") for i in range(len(nodes))]
    world: list = [None] * len(nodes)
    for i in range(len(nodes)):
        chain, j = [], i
        while j is not None and world[j] is None:
            chain.append(j)
            if len(chain) > len(nodes):
                raise f.error(f"node {i}: its parents form a cycle")
            j = parent.get(j)
        above = np.eye(4) if j is None else world[j]
        for k in reversed(chain):
            with np.errstate(over="ignore", invalid="ignore"):
                above = above @ local[k]
            if not np.isfinite(above).all():
                raise f.error(f"node {k}: its world transform is not finite")
            world[k] = above
    return world


def _scene_instances(f: GltfFile) -> list[_Instance]:
    """The (node, mesh) pairs of the default scene, depth first in file order."""
    nodes, scenes = f.items("nodes"), f.items("scenes")
    if scenes:
        which = f.field(f.json, "scene", "the file", int, 0, low=0)
        roots = f.field(f.item("scenes", which, "scene"), "nodes", f"scene {which}", list, [])
    else:
        children = {c for i in range(len(nodes)) for c in f.item("nodes", i, "the file").get("children", [])}
        roots = [i for i in range(len(nodes)) if i not in children]
    out, stack, seen = [], list(reversed(roots)), set()
    while stack:
        i = stack.pop()
        node = f.item("nodes", i, "the scene")
        if i in seen:
            raise f.error(f"node {i} is reached twice from the scene's roots")
        seen.add(i)
        if "mesh" in node:
            m = f.field(node, "mesh", f"node {i}", int, low=0)
            mesh = f.item("meshes", m, f"node {i}")
            out.append(_Instance(i, m, "", _name(f, node, f"node{i}"), _name(f, mesh, f"mesh{m}")))
        stack.extend(reversed(node.get("children", [])))
    counts = Counter(inst.mesh_name for inst in out)
    for inst in out:
        inst.name = inst.mesh_name if counts[inst.mesh_name] == 1 else f"{inst.mesh_name}@{inst.node_name}"
    counts = Counter(inst.name for inst in out)
    for inst in out:
        if counts[inst.name] > 1:
            inst.name = f"{inst.mesh_name}@node{inst.node}"
    return out


def _name(f: GltfFile, obj: dict, default: str) -> str:
    name = obj.get("name")
    return name if isinstance(name, str) and name else default


def _targets_of(f: GltfFile, mesh: int, where: str = "a node") -> int:
    """The number of morph targets of mesh *mesh* (the most of any primitive)."""
    prims = f.field(f.item("meshes", mesh, where), "primitives", f"mesh {mesh}", list)
    n = 0
    for p, prim in enumerate(prims):
        if not isinstance(prim, dict):
            raise f.error(f"mesh {mesh} primitive {p} is not an object")
        n = max(n, len(f.field(prim, "targets", f"mesh {mesh} primitive {p}", list, [])))
    return n


def _choose(f: GltfFile, instances: list[_Instance], meshes) -> list[_Instance]:
    """The instances *meshes* names (each pattern must match), or those with morph targets."""
    if meshes is None:
        return [inst for inst in instances if _targets_of(f, inst.mesh)]
    chosen = set()
    for pat in patterns(meshes, "meshes"):
        hits = {i for i, inst in enumerate(instances)
                if fnmatchcase(inst.name, pat) or fnmatchcase(inst.mesh_name, pat) or fnmatchcase(inst.node_name, pat)}
        if not hits:
            names = ", ".join(dict.fromkeys(inst.name for inst in instances)) or "none"
            raise f.error(f"meshes: {pat!r} matches no mesh; the file's meshes: {names}")
        chosen |= hits
    return [inst for i, inst in enumerate(instances) if i in chosen]


# ---------------------------------------------------------------------- planning (counts only)
def _plan(f: GltfFile, inst: _Instance):
    """Count the vertices and targets of *inst* from the declared accessor counts (nothing decoded)."""
    mesh = f.item("meshes", inst.mesh, f"node {inst.node}")
    where = f"mesh {inst.mesh} ('{inst.mesh_name}')"
    prims = f.field(mesh, "primitives", where, list)
    shared: dict = {}
    n_targets = None
    for p, prim in enumerate(prims):
        if not isinstance(prim, dict):
            raise f.error(f"{where} primitive {p} is not an object")
        pw = f"{where} primitive {p}"
        attrs = f.field(prim, "attributes", pw, dict)
        tlist = f.field(prim, "targets", pw, list, [])
        if "POSITION" not in attrs:
            log.warning("%s: %s has no POSITION; skipped", f.name, pw)
            continue
        if n_targets is not None and len(tlist) != n_targets:
            raise f.error(f"{where}: primitive {p} has {len(tlist)} morph targets, an earlier one has {n_targets}")
        n_targets = len(tlist)
        key = (f.field(attrs, "POSITION", f"{pw} attributes", int, low=0), tuple(_target_position(f, t, pw, k)
                                                                                for k, t in enumerate(tlist)))
        if _DRACO in f.field(prim, "extensions", pw, dict, {}) or key not in shared:
            count = f.accessor_count(attrs["POSITION"], f"POSITION of {where} primitive {p}")
            shared[key] = (inst.n_vertices, count)
            inst.prims.append((p, prim, inst.n_vertices))
            inst.n_vertices += count
        else:
            inst.prims.append((p, prim, -1 - shared[key][0]))  # shares the vertices at that offset
    inst.n_targets = n_targets or 0
    inst.target_labels = _target_labels(f, mesh, prims, inst.n_targets, where)


def _target_position(f: GltfFile, target, where: str, k: int):
    """The POSITION accessor index of morph target *k* (None when it has none)."""
    if not isinstance(target, dict):
        raise f.error(f"{where} morph target {k} is not an object")
    return f.field(target, "POSITION", f"{where} morph target {k}", int, None, low=0)


def _target_labels(f: GltfFile, mesh: dict, prims: list, n: int, where: str) -> list:
    """The targets' names from ``extras.targetNames`` of the mesh, else of its first primitive (None if unnamed)."""
    names = None
    for obj in [mesh] + prims[:1]:
        extras = obj.get("extras") if isinstance(obj, dict) else None
        if isinstance(extras, dict) and "targetNames" in extras:
            names = extras["targetNames"]
            break
    if names is None:
        return [None] * n
    if not isinstance(names, list) or not all(isinstance(s, str) for s in names):
        log.warning("%s: %s extras.targetNames is not a list of strings; targets unnamed", f.name, where)
        return [None] * n
    if len(names) != n:
        log.warning("%s: %s names %d targets, it has %d", f.name, where, len(names), n)
    return [names[k] if k < len(names) and names[k] else None for k in range(n)]


# ---------------------------------------------------------------------- placement (nodes, skins)
def _placement(f: GltfFile, inst: _Instance, world: list):
    """The mesh's placement: a (4, 4) matrix, or the skin's joint matrices (J, 4, 4) when they differ."""
    node = f.item("nodes", inst.node, "the scene")
    if "skin" not in node:
        return world[inst.node]
    s = f.field(node, "skin", f"node {inst.node}", int, low=0)
    skin = f.item("skins", s, f"node {inst.node}")
    where = f"skin {s}"
    joints = f.field(skin, "joints", where, list)
    if not joints:
        raise f.error(f"{where}: 'joints' is empty")
    for j in joints:
        f.item("nodes", j, f"{where} joints")
    if "inverseBindMatrices" in skin:
        ibm = f.floats(skin["inverseBindMatrices"], f"inverseBindMatrices of {where}", types=("MAT4",))
        if len(ibm) < len(joints):
            raise f.error(f"{where}: {len(ibm)} inverse bind matrices for {len(joints)} joints")
        ibm = ibm[:len(joints)].reshape(-1, 4, 4).transpose(0, 2, 1)
    else:
        ibm = np.broadcast_to(np.eye(4), (len(joints), 4, 4))
    with np.errstate(over="ignore", invalid="ignore"):
        mats = np.stack([world[j] for j in joints]) @ ibm
    if not np.isfinite(mats).all():
        raise f.error(f"{where}: a joint's world matrix times its inverse bind matrix is not finite")
    scale = max(float(np.abs(mats[0]).max()), 1e-12)
    if float(np.abs(mats - mats[0]).max()) <= _UNIFORM_SKIN_TOL * scale:
        return mats[0]
    log.info("%s: mesh '%s': the skeleton's rest pose is not its bind pose; placed by linear blend skinning",
             f.name, inst.name)
    return mats


def _skin_blend(f: GltfFile, mats: np.ndarray, attrs: dict, n: int, where: str) -> np.ndarray:
    """Per-vertex skinning matrices (n, 4, 4): sum of weight * joint matrix over JOINTS_i/WEIGHTS_i."""
    blend = np.zeros((n, 4, 4))
    s = 0
    while f"JOINTS_{s}" in attrs and f"WEIGHTS_{s}" in attrs:
        joints = f.integers(attrs[f"JOINTS_{s}"], f"JOINTS_{s} of {where}", types=("VEC4",))
        weights = f.floats(attrs[f"WEIGHTS_{s}"], f"WEIGHTS_{s} of {where}", types=("VEC4",))
        if len(joints) != n or len(weights) != n:
            raise f.error(f"{where}: JOINTS_{s}/WEIGHTS_{s} have {len(joints)}/{len(weights)} elements for {n} "
                          "vertices")
        if joints.size and int(joints.max()) >= len(mats):
            raise f.error(f"{where}: JOINTS_{s} uses joint {int(joints.max())}, the skin has {len(mats)}")
        for c in range(4):
            blend += weights[:, c, None, None] * mats[joints[:, c]]
        s += 1
    if s == 0:
        raise f.error(f"{where}: skinned, but has no JOINTS_0/WEIGHTS_0")
    return blend


# ---------------------------------------------------------------------- reading geometry
def _triangles(f: GltfFile, idx: np.ndarray, mode: int, where: str) -> np.ndarray:
    """Triangle list (F, 3) from an index sequence and a primitive mode (glTF 2.0 §3.7.2.1)."""
    n = len(idx)
    if mode == 4:
        if n % 3:
            raise f.error(f"{where}: {n} indices do not make triangles")
        return idx.reshape(-1, 3)
    if mode in (5, 6) and n >= 3:
        i = np.arange(n - 2)
        if mode == 5:
            tris = np.stack([idx[i], idx[i + 1 + i % 2], idx[i + 2 - i % 2]], axis=1)
        else:
            tris = np.stack([idx[i + 1], idx[i + 2], np.full(n - 2, idx[0])], axis=1)
        ok = (tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 0] != tris[:, 2])
        return tris[ok]
    if mode not in (0, 1, 2, 3, 5, 6):
        raise f.error(f"{where}: mode {mode} is not a glTF primitive mode")
    log.warning("%s: %s is points or lines (mode %d): vertices read, no faces", f.name, where, mode)
    return np.zeros((0, 3), dtype=np.int64)


def _primitive_geometry(f: GltfFile, prim: dict, attrs: dict, where: str):
    """Local positions (n, 3) and triangles (F, 3), from accessors or Draco."""
    mode = f.field(prim, "mode", where, int, 4)
    ext = f.field(prim, "extensions", where, dict, {})
    count = f.accessor_count(attrs["POSITION"], f"POSITION of {where}")
    if isinstance(ext.get(_DRACO), dict) and (draco_available() or "bufferView" not in f.item(
            "accessors", attrs["POSITION"], where)):
        if mode not in (4, 5):
            raise f.error(f"{where}: {_DRACO} with mode {mode}, it allows triangles or strips")
        pos, tris = f.draco(ext[_DRACO], count, where)
        return pos, tris
    pos = f.floats(attrs["POSITION"], f"POSITION of {where}")
    if "indices" in prim:
        idx = f.integers(prim["indices"], f"indices of {where}")[:, 0]
    else:
        idx = np.arange(count, dtype=np.int64)
    tris = _triangles(f, idx, mode, where)
    return pos, tris


def _read_mesh(f: GltfFile, inst: _Instance, place, neutral: np.ndarray, deltas: np.ndarray, rows: dict):
    """Fill this mesh's rows of *neutral* (n, 3) and *deltas* (K, n, 3); return its triangles (F, 3).

    *rows* maps the mesh's target index to its row in *deltas* (targets not kept are not read).
    """
    faces = []
    for p, prim, offset in inst.prims:
        where = f"mesh '{inst.name}' primitive {p}"
        if offset < 0:  # same vertex accessors as an earlier primitive: only its triangles
            attrs = prim["attributes"]
            count = f.accessor_count(attrs["POSITION"], f"POSITION of {where}")
            _, tris = _primitive_geometry(f, prim, attrs, where)
            faces.append(_checked(f, tris, count, where) + (-1 - offset))
            continue
        attrs = prim["attributes"]
        if place.ndim == 3 and _DRACO in prim.get("extensions", {}):
            raise f.error(f"{where}: a {_DRACO} primitive whose skin's rest pose is not its bind pose (not read)")
        pos, tris = _primitive_geometry(f, prim, attrs, where)
        n = len(pos)
        faces.append(_checked(f, tris, n, where) + offset)
        lin, shift = _transform(f, place, attrs, n, where)
        block = slice(offset, offset + n)
        neutral[block] = _apply(lin, pos) + shift
        for k, target in enumerate(prim.get("targets") or []):
            if k not in rows or not isinstance(target, dict) or "POSITION" not in target:
                continue
            what = f"POSITION of mesh '{inst.name}' target {k}"
            d = f.floats(target["POSITION"], what)
            if len(d) != n:
                raise f.error(f"{what}: {len(d)} elements for the primitive's {n} vertices")
            deltas[rows[k], block] = _apply(lin, d)
    return np.concatenate(faces) if faces else np.zeros((0, 3), dtype=np.int64)


def _checked(f: GltfFile, tris: np.ndarray, n: int, where: str) -> np.ndarray:
    if tris.size and (int(tris.max()) >= n or int(tris.min()) < 0):
        raise f.error(f"{where}: index {int(tris.max())} is out of range for {n} vertices")
    return tris.astype(np.int64)


def _transform(f: GltfFile, place: np.ndarray, attrs: dict, n: int, where: str):
    """Linear part and translation: (3, 3) and (3,), or per vertex (n, 3, 3) and (n, 3) for a blended skin."""
    if place.ndim == 2:
        return place[:3, :3], place[:3, 3]
    blend = _skin_blend(f, place, attrs, n, where)
    return blend[:, :3, :3], blend[:, :3, 3]


def _apply(lin: np.ndarray, v: np.ndarray) -> np.ndarray:
    if lin.ndim == 2:
        return v @ lin.T
    return np.einsum("nij,nj->ni", lin, v)


# ---------------------------------------------------------------------- sliders
def _groups(f: GltfFile, instances: list[_Instance], table: list, unique: list[str]):
    """(kind, slider groups): VRM expressions when the file has them, else targets grouped by name."""
    ext = f.field(f.json, "extensions", "the file", dict, {})
    index = {pair: j for j, pair in enumerate(table)}
    if isinstance(ext.get("VRMC_vrm"), dict):
        kind, groups = "vrm1", _vrm1_groups(f, ext["VRMC_vrm"], instances, index)
    elif isinstance(ext.get("VRM"), dict):
        kind, groups = "vrm0", _vrm0_groups(f, ext["VRM"], instances, index)
    else:
        return "gltf", _name_groups(f, instances, table, unique)
    if groups:
        return kind, groups
    log.warning("%s: no VRM expression moves a chosen target; sliders are the targets grouped by name", f.name)
    return "gltf", _name_groups(f, instances, table, unique)


def _name_groups(f: GltfFile, instances: list[_Instance], table: list, unique: list[str]) -> dict:
    keys = slider_keys(f.name, [inst.target_labels for inst in instances], [inst.name for inst in instances])
    groups: dict[str, list] = {}
    for j, (i, k) in enumerate(table):
        key = keys[i][k]
        if key is None:
            key = unique[j]
        groups.setdefault(key, []).append((j, 1.0))
    return groups


def _add_bind(groups: dict, slider: str, j, weight: float):
    """Add ``weight`` of target row *j* to *slider*; ``j is None`` counts a bind on a target not chosen."""
    binds = groups.setdefault(slider, {})
    binds[j] = binds.get(j, 0.0) + (weight if j is not None else 1)


def _finish(f: GltfFile, groups: dict, names: list[str]) -> dict:
    out = {}
    for name in names:
        binds = dict(groups.get(name, {}))
        dropped = int(binds.pop(None, 0))
        if binds:
            out[name] = list(binds.items())
            if dropped:
                log.info("%s: expression '%s' keeps %d binds, %d are on meshes or targets not chosen", f.name, name,
                         len(binds), dropped)
        else:
            log.info("%s: expression '%s' moves no chosen target; not a slider", f.name, name)
    return out


def _vrm0_groups(f: GltfFile, vrm: dict, instances: list[_Instance], index: dict) -> dict:
    """VRM 0.x blendShapeGroups: binds (mesh index, target index, weight 0-100)."""
    master = f.field(vrm, "blendShapeMaster", "VRM", dict, {})
    by_mesh: dict[int, list[int]] = {}
    for i, inst in enumerate(instances):
        by_mesh.setdefault(inst.mesh, []).append(i)
    groups: dict = {}
    names = []
    for g, group in enumerate(f.field(master, "blendShapeGroups", "VRM blendShapeMaster", list, [])):
        where = f"VRM blendShapeGroups[{g}]"
        if not isinstance(group, dict):
            raise f.error(f"{where} is not an object")
        preset = f.field(group, "presetName", where, str, "")
        name = preset if preset and preset != "unknown" else f.field(group, "name", where, str, "") or f"group{g}"
        name = _fresh(name, names)
        names.append(name)
        groups[name] = {}
        for b, bind in enumerate(f.field(group, "binds", where, list, [])):
            bw = f"{where}.binds[{b}]"
            if not isinstance(bind, dict):
                raise f.error(f"{bw} is not an object")
            mesh = f.field(bind, "mesh", bw, int, low=0)
            k = f.field(bind, "index", bw, int, low=0)
            weight = f.field(bind, "weight", bw, float)
            n = _targets_of(f, mesh, bw)
            if k >= n:
                raise f.error(f"{bw}: morph target {k} of mesh {mesh}, which has {n}")
            for i in by_mesh.get(mesh, [None]):
                _add_bind(groups, name, index.get((i, k)), weight / 100.0)
    return _finish(f, groups, names)


def _vrm1_groups(f: GltfFile, vrmc: dict, instances: list[_Instance], index: dict) -> dict:
    """VRM 1.0 expressions (preset and custom): morphTargetBinds (node index, target index, weight 0-1)."""
    expressions = f.field(vrmc, "expressions", "VRMC_vrm", dict, {})
    by_node = {inst.node: i for i, inst in enumerate(instances)}
    groups: dict = {}
    names = []
    for section in ("preset", "custom"):
        for key, expr in f.field(expressions, section, "VRMC_vrm.expressions", dict, {}).items():
            where = f"VRMC_vrm.expressions.{section}.{key}"
            if not isinstance(expr, dict):
                raise f.error(f"{where} is not an object")
            name = _fresh(key, names)
            names.append(name)
            groups[name] = {}
            for b, bind in enumerate(f.field(expr, "morphTargetBinds", where, list, [])):
                bw = f"{where}.morphTargetBinds[{b}]"
                if not isinstance(bind, dict):
                    raise f.error(f"{bw} is not an object")
                node = f.field(bind, "node", bw, int, low=0)
                k = f.field(bind, "index", bw, int, low=0)
                weight = f.field(bind, "weight", bw, float)
                target = f.item("nodes", node, bw)
                if "mesh" not in target:
                    raise f.error(f"{bw}: node {node} has no mesh")
                n = _targets_of(f, f.field(target, "mesh", f"node {node}", int, low=0))
                if k >= n:
                    raise f.error(f"{bw}: morph target {k} of node {node}'s mesh, which has {n}")
                _add_bind(groups, name, index.get((by_node.get(node), k)), weight)
    return _finish(f, groups, names)


def _fresh(name: str, used: list[str]) -> str:
    out, n = name, 2
    while out in used:
        out, n = f"{name}~{n}", n + 1
    return out


__all__ = ["GltfFile", "GltfOutline", "GltfRig", "read_gltf_outline", "read_gltf_rig", "node_world_matrices",
           "MAX_DENSE_BYTES"]
