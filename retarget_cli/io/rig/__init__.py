"""Reading a character rig: one home for everything a rig is made of.

- :mod:`.spec`: ``rig.yaml`` (:func:`read_rig`, :class:`Rig`), with OBJs or ``source:`` a character file;
- :mod:`.load`: the rig's meshes as a :class:`~retarget_cli.methods.rig.BlendshapeRig` (:func:`load_rig`);
- :mod:`.gltf`: glTF/GLB/VRM characters (:func:`~.gltf.read_gltf_rig`, :func:`~.gltf.read_gltf_outline`);
- :mod:`.cache`: parsed meshes kept between runs, keyed by the files' sha256;
- :mod:`.vertexmap`: landmark-to-vertex maps;
- :mod:`.inverse`: the quadratic correctives of an inverse-rig (``solve-rig``).

A new rig file format is a module here that returns the same :class:`~retarget_cli.methods.rig.BlendshapeRig`.
"""

from .load import load_rig
from .spec import RIG_KEYS, Rig, read_rig

__all__ = ["RIG_KEYS", "Rig", "load_rig", "read_rig"]
