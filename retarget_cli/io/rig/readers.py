"""The rig readers by file suffix: glTF/GLB/VRM (:mod:`.gltf`), USD (:mod:`.usd`), FBX (:mod:`.fbx`).

Each reader returns a :class:`~retarget_cli.io.rig.gltf.GltfRig` (neutral, triangles, mesh ranges, target names,
world-space deltas, slider groups) and has an outline (:class:`~retarget_cli.io.rig.gltf.GltfOutline`: the same
names, counts and groups) that ``rig.yaml``'s checks read first. glTF's outline comes from its JSON alone; USD and
FBX have none cheaper than a read, so their outline reads the file once and keeps that result for the
:func:`read_character` that follows (same file, size, modification time and filters).
"""

from __future__ import annotations

import os
from pathlib import Path

from ...errors import InputError
from . import _scene
from .fbx import FBX_EXTS, read_fbx_rig
from .gltf import GltfOutline, GltfRig, read_gltf_outline, read_gltf_rig
from .usd import USD_EXTS, read_usd_rig

#: glTF-family suffixes (outline from the JSON alone; ``apply --format same`` writes these back).
GLTF_EXTS = (".glb", ".gltf", ".vrm")
#: Suffix -> reader ``f(path, *, meshes=None, targets=None) -> GltfRig``.
READERS = {**{e: read_gltf_rig for e in GLTF_EXTS}, **{e: read_usd_rig for e in USD_EXTS},
           **{e: read_fbx_rig for e in FBX_EXTS}}
#: Every suffix read as a rig.
RIG_FILE_EXTS = tuple(READERS)

_kept: dict = {}


def _key(path: Path, meshes, targets):
    st = os.stat(path)
    freeze = lambda v: None if v is None else (v,) if isinstance(v, str) else tuple(v)
    return (str(path.resolve()), st.st_size, st.st_mtime_ns, freeze(meshes), freeze(targets))


def _reader(path: Path):
    reader = READERS.get(path.suffix.lower())
    if reader is None:
        raise InputError(f"{path}: unsupported rig file extension {path.suffix or '(none)'!r}; "
                         f"this version reads {', '.join(RIG_FILE_EXTS)}")
    return reader


def read_character(path, *, meshes=None, targets=None) -> GltfRig:
    """Read a character file as a rig with the reader of its suffix (see :data:`READERS`)."""
    path = Path(path)
    reader = _reader(path)
    if reader is not read_gltf_rig and path.is_file():
        kept = _kept.pop(_key(path, meshes, targets), None)
        if kept is not None:
            return kept
    return reader(path, meshes=meshes, targets=targets)


def read_character_outline(path, *, meshes=None, targets=None) -> GltfOutline:
    """The meshes, targets and sliders :func:`read_character` would return (``files``: the other files it reads)."""
    path = Path(path)
    reader = _reader(path)
    if reader is read_gltf_rig:
        return read_gltf_outline(path, meshes=meshes, targets=targets)
    rig = reader(path, meshes=meshes, targets=targets)
    _kept.clear()  # one read kept at most
    _kept[_key(path, meshes, targets)] = rig
    return _scene.outline(rig, getattr(rig, "layers", None) or [])


__all__ = ["GLTF_EXTS", "READERS", "RIG_FILE_EXTS", "read_character", "read_character_outline"]
