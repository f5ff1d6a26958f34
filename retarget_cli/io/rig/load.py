"""Load a blendshape rig (:class:`~retarget_cli.methods.rig.BlendshapeRig`) from its ``rig.yaml`` and meshes,
or from a character file with morph targets or blend shapes (``source: char.glb``, or the glTF/GLB/VRM, USD or FBX
file itself)."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import numpy as np

from ...errors import InputError, ParameterError
from ...methods.rig import BlendshapeRig
from ..obj import obj_from_arrays
from .cache import cached_arrays, load_rig_meshes
from .readers import read_character
from .spec import read_rig
from .vertexmap import check_landmark_list, read_vertex_map

log = logging.getLogger(__name__)


def load_rig(path: str | os.PathLike, *, storage: str = "auto", cache_dir=None) -> BlendshapeRig:
    """Load a rig from ``rig.yaml`` (see :func:`~retarget_cli.io.rig.spec.read_rig`) or a character file.

    Whole-face shapes (``shapes_are: absolute``) become deltas
    ``d_k = b_k - f0`` (Lewis et al. 2005, §3). Every OBJ's vertex count
    is checked against the neutral's before any OBJ is parsed, and so are
    the ``landmarks:`` vertex ids.

    A ``source:`` rig (or a character file given as the rig) is read by the
    reader of its suffix (:func:`~retarget_cli.io.rig.readers.read_character`:
    glTF/GLB/VRM, USD, FBX): ``f0`` is the
    base mesh of the chosen meshes (every morph weight 0) and each slider's
    delta is the weighted sum of its targets' deltas, ``d_s = sum_k w_sk t_k``
    (a VRM expression, or the targets that share the slider's name across
    meshes, or ``sliders:``). The template that writes OBJ frames has one
    ``o`` object per mesh and its triangles (no UVs or materials).

    Parameters
    ----------
    path : path-like
        The ``rig.yaml``, or a ``.glb``/``.gltf``/``.vrm``, USD or ``.fbx`` file.
    storage : {"auto", "dense", "sparse"}
        See :class:`BlendshapeRig`.
    cache_dir : path-like, optional
        Keep the parsed OBJs in ``cache_dir/rig-<key>.npz``, keyed by the
        sha256 of ``rig.yaml`` and every file it references
        (:mod:`retarget_cli.io.rig.cache`); a later load of the same files
        reads that instead of the OBJs or the character file. None: no cache.

    Raises
    ------
    InputError
        For a malformed ``rig.yaml``, a missing OBJ, a shape whose vertex
        count differs from the neutral's (naming the ``shapes.<name>``
        entry and both counts), a landmark vertex outside the neutral, or
        shapes that do not share the neutral's topology (naming both files).
    """
    spec = read_rig(path)
    if spec.source is not None:
        return _load_source_rig(spec, storage, cache_dir)
    extra = [spec.landmarks] if isinstance(spec.landmarks, Path) else []
    for p in [*spec.files(), *extra]:
        if not Path(p).is_file():
            raise InputError(f"{path}: {p} not found")
    landmarks = []

    def check(n_vertices):
        if isinstance(spec.landmarks, Path):
            landmarks.append(read_vertex_map(spec.landmarks, None, n_vertices))
        elif spec.landmarks is not None:
            ids = check_landmark_list(str(path), spec.landmarks, n_vertices, spec.neutral.name)
            landmarks.append((np.arange(len(ids)), ids))

    entries = [("neutral", spec.neutral), *((f"shapes.{k}", p) for k, p in spec.shapes.items())]
    template, V = load_rig_meshes(path, entries, extra_files=extra, cache_dir=cache_dir, check=check)
    neutral = template.vertices
    D = V[1:] - neutral[None] if spec.shapes_are == "absolute" else V[1:]
    names = list(spec.shapes)
    lower = np.array([spec.ranges[n][0] for n in names])
    upper = np.array([spec.ranges[n][1] for n in names])
    rig = BlendshapeRig(neutral, D, names, lower=lower, upper=upper, library=spec.library, storage=storage,
              template=template, correctives=spec.correctives)
    #: The parsed ``rig.yaml`` (:class:`~retarget_cli.io.rig.spec.Rig`).
    rig.spec = spec
    #: ``landmarks:`` checked against the neutral, as (landmark ids (L,), vertex ids (L,)) like
    #: :func:`~retarget_cli.io.rig.vertexmap.read_vertex_map`; None when rig.yaml has none.
    rig.landmarks = landmarks[0] if landmarks else None
    return rig


def _source_arrays(spec) -> dict:
    """Read the character file: neutral (V, 3), triangles, mesh ranges and one delta field per slider, sparse.

    The slider deltas are kept as the moving rows only (``rows`` (nnz,), ``values`` (nnz, 3), ``offsets``
    (S + 1,)): a face's sliders move a small part of a whole-body mesh.
    """
    g = read_character(spec.source, meshes=spec.meshes, targets=spec.targets)
    if g.target_names != spec.outline.target_names or len(g.neutral) != spec.outline.n_vertices:
        raise InputError(f"{spec.source}: changed while it was read (its targets or vertex count differ)")
    index = {name: k for k, name in enumerate(g.target_names)}
    rows, values, offsets = [], [], [0]
    for binds in spec.sliders.values():
        d = np.zeros_like(g.neutral)
        for target, weight in binds:
            d += weight * g.deltas[index[target]]
        moving = np.flatnonzero(np.any(d != 0, axis=1))
        rows.append(moving)
        values.append(d[moving])
        offsets.append(offsets[-1] + len(moving))
    return {"neutral": g.neutral, "faces": g.faces, "rows": np.concatenate(rows).astype(np.int32),
            "values": np.concatenate(values).reshape(-1, 3), "offsets": np.asarray(offsets, dtype=np.int64),
            "meshes": np.array(json.dumps(g.mesh_ranges))}


def _check_source_arrays(spec):
    """A check of cached source arrays against the rig's outline (raises ParameterError)."""
    n, s = spec.outline.n_vertices, len(spec.sliders)

    def check(a):
        if a["neutral"].shape != (n, 3) or a["neutral"].dtype != np.float64 or a["offsets"].shape != (s + 1,):
            raise ParameterError(f"neutral {a['neutral'].shape} or sliders {len(a['offsets']) - 1} differ")
        if a["values"].shape != (int(a["offsets"][-1]), 3) or a["rows"].shape != (int(a["offsets"][-1]),):
            raise ParameterError("slider rows and values differ in length")
        if a["rows"].size and (a["rows"].min() < 0 or a["rows"].max() >= n):
            raise ParameterError("slider rows outside the mesh")
    return check


def _load_source_rig(spec, storage: str, cache_dir) -> BlendshapeRig:
    """:func:`load_rig` of a rig read from a character file (``source:``)."""
    landmarks = None
    extra = []
    if isinstance(spec.landmarks, Path):
        if not spec.landmarks.is_file():
            raise InputError(f"{spec.path}: {spec.landmarks} not found")
        landmarks = read_vertex_map(spec.landmarks, None, spec.outline.n_vertices)
        extra = [spec.landmarks]
    elif spec.landmarks is not None:
        ids = check_landmark_list(str(spec.path), spec.landmarks, spec.outline.n_vertices, spec.neutral_name())
        landmarks = (np.arange(len(ids)), ids)
    files = [f for f in [*spec.files(), *extra] if Path(f).resolve() != Path(spec.path).resolve()]
    a = cached_arrays(spec.path, files, lambda: _source_arrays(spec), cache_dir=cache_dir, kind="source",
                      check=_check_source_arrays(spec))
    neutral = a["neutral"]
    names = list(spec.sliders)
    D = np.zeros((len(names), len(neutral), 3))
    for k in range(len(names)):
        lo, hi = int(a["offsets"][k]), int(a["offsets"][k + 1])
        D[k, a["rows"][lo:hi]] = a["values"][lo:hi]
    template = obj_from_arrays(spec.source, neutral, a["faces"], objects=[tuple(m) for m in json.loads(str(a["meshes"]))])
    lower = np.array([spec.ranges[n][0] for n in names])
    upper = np.array([spec.ranges[n][1] for n in names])
    rig = BlendshapeRig(neutral, D, names, lower=lower, upper=upper, library=spec.library, storage=storage,
                        template=template)
    rig.spec = spec
    rig.landmarks = landmarks
    log.info("rig %s: %d sliders over %d targets, %d vertices (%s)", spec.path, len(names),
             len(spec.outline.target_names), len(neutral), spec.source.name)
    return rig
