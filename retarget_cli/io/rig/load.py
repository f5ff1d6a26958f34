"""Load a blendshape rig (:class:`~retarget_cli.methods.rig.BlendshapeRig`) from its ``rig.yaml`` and meshes."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ...errors import InputError
from ...methods.rig import BlendshapeRig
from .cache import load_rig_meshes
from .spec import read_rig
from .vertexmap import check_landmark_list, read_vertex_map


def load_rig(path: str | os.PathLike, *, storage: str = "auto", cache_dir=None) -> BlendshapeRig:
    """Load a rig from ``rig.yaml`` (see :func:`~retarget_cli.io.rig.spec.read_rig`).

    Whole-face shapes (``shapes_are: absolute``) become deltas
    ``d_k = b_k - f0`` (Lewis et al. 2005, §3). Every OBJ's vertex count
    is checked against the neutral's before any OBJ is parsed, and so are
    the ``landmarks:`` vertex ids.

    Parameters
    ----------
    path : path-like
        The ``rig.yaml``.
    storage : {"auto", "dense", "sparse"}
        See :class:`BlendshapeRig`.
    cache_dir : path-like, optional
        Keep the parsed OBJs in ``cache_dir/rig-<key>.npz``, keyed by the
        sha256 of ``rig.yaml`` and every file it references
        (:mod:`retarget_cli.io.rig.cache`); a later load of the same files
        reads that instead of the OBJs. None: no cache.

    Raises
    ------
    InputError
        For a malformed ``rig.yaml``, a missing OBJ, a shape whose vertex
        count differs from the neutral's (naming the ``shapes.<name>``
        entry and both counts), a landmark vertex outside the neutral, or
        shapes that do not share the neutral's topology (naming both files).
    """
    spec = read_rig(path)
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
