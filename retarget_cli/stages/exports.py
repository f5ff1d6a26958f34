"""``apply``'s exports for rig users: Live Link Face CSV and USD (their file handling).

:func:`~retarget_cli.stages.apply.run_apply` computes the curves or the
meshes; the functions here turn them into files (writers in
:mod:`retarget_cli.io.livelink` and :mod:`retarget_cli.io.usd`).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.atomic import write_text

log = logging.getLogger(__name__)


def head_rotation(landmarks, T: int):
    """(T, 3) head yaw, pitch, roll (radians) from ``landmarks.npz``, or None without a landmarks file.

    Roll comes from the tracked 2D head motion; yaw and pitch are 0 (the 2D
    track has no estimate of them).
    """
    from ..io.landmarks import load_landmarks
    from ..io.livelink import head_rotation_from_similarity

    if landmarks is None:
        return None
    lm = load_landmarks(landmarks)
    if lm.n_frames != T:
        raise InputError(f"{landmarks}: has {lm.n_frames} frames but the weights have {T}")
    return head_rotation_from_similarity(lm.head)


def write_livelink(path: Path, rig, curves: np.ndarray, fps: float, *, landmarks=None) -> Path:
    """Write the rig's curves as a Live Link Face CSV (:func:`retarget_cli.io.livelink.livelink_csv`).

    Parameters
    ----------
    rig : BlendshapeRig
        Its slider names, and ``rig.yaml``'s ``names:`` mapping (``rig.spec.names``).
    curves : ndarray, shape (T, n)
    landmarks : path-like, optional
        ``landmarks.npz``: HeadRoll from its head motion; without it the head columns are 0.
    """
    from ..io.livelink import livelink_csv

    rot = head_rotation(landmarks, len(curves))
    if rot is None:
        log.info("Live Link Face CSV: no landmarks file, so the head rotation columns are 0")
    names = rig.spec.names if rig.spec is not None else {}
    write_text(path, livelink_csv(curves, rig.names, fps, names=names, head_rotation=rot))
    return path


def rig_shapes(rig, curves: np.ndarray) -> tuple[np.ndarray, list[str], np.ndarray]:
    """The rig's shapes and weights for blendshape formats (glTF morph targets, UsdSkel BlendShapes).

    One shape per slider, driven by its curve; then one per corrective of
    ``rig.yaml`` (Racković et al. 2023, eq. 4: ``w_i w_j (corrective_ij −
    neutral)``), which neither format can express, baked as an extra shape
    ``corrective_<a>_<b>`` driven by the product of its pair's weights.

    Returns
    -------
    shapes : ndarray, shape (M, N, 3)
    names : list of str, length M
    weights : ndarray, shape (T, M)
    """
    from ..io.obj import read_obj
    from ..io.rigfiles import parse_correctives

    D = rig.D.toarray() if rig.sparse else np.asarray(rig.D)
    shapes = [D.T.reshape(rig.n_sliders, -1, 3)]
    names, cols = list(rig.names), [np.asarray(curves, dtype=np.float64)]
    corr = parse_correctives(rig.spec) if rig.spec is not None else []
    for i, j, p in corr:
        mesh = read_obj(p)
        if mesh.n_vertices != rig.n_vertices:
            raise InputError(f"{p}: corrective has {mesh.n_vertices} vertices, the rig has {rig.n_vertices}")
        shapes.append((mesh.vertices - rig.neutral)[None])
        names.append(f"corrective_{rig.names[i]}_{rig.names[j]}")
        cols.append((cols[0][:, i] * cols[0][:, j])[:, None])
    if corr:
        log.info("blendshape exports: %d corrective shapes baked as extra shapes driven by their pairs' "
                 "products (the OBJ/EXR frames are the linear rig)", len(corr))
    return np.concatenate(shapes), names, np.concatenate(cols, axis=1)


def write_usd(path: Path, template, base: np.ndarray, positions, T: int, fps: float, *, rig_out=None,
              head=None) -> Path:
    """Write ``animation.usd``: a UsdSkel character with a rig, else a point cache.

    Parameters
    ----------
    template : ObjMesh
        Faces and texture coordinates.
    base : ndarray, shape (N, 3)
        The rest mesh (the rig's neutral).
    positions : callable
        ``positions(slice)`` -> (t, N, 3) meshes without head motion (the point cache).
    rig_out : (BlendshapeRig, curves (T, n)), optional
    head : ndarray, shape (T, 3, 4), optional
        Head motion, the time-sampled transform of ``/Character``.
    """
    from ..io.objsurface import obj_surface
    from ..io.usd import write_usd_points, write_usd_skel

    surf = obj_surface(template)
    uv = (surf.uv, surf.vt) if surf.has_uv else None
    common = dict(counts=surf.counts, corners=surf.v, fps=fps, uv=uv, transforms=head, name=Path(template.path).stem)
    if rig_out is not None:
        shapes, names, weights = rig_shapes(*rig_out)
        write_usd_skel(path, points=base, shapes=shapes, names=names, weights=weights, **common)
    else:
        X = np.concatenate([positions(slice(s, min(s + 64, T))) for s in range(0, T, 64)])
        write_usd_points(path, positions=X, **common)
    return path


__all__ = ["head_rotation", "rig_shapes", "write_livelink", "write_usd"]
