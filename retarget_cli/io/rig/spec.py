"""``rig.yaml``: a blendshape rig described as a neutral OBJ, one OBJ per slider and their settings, or as a
character file with morph targets (``source: char.glb``; a glTF/GLB/VRM, USD or FBX path is such a rig too).

:func:`read_rig` parses and checks the file (every path absolute, every name known; for a ``source:`` the
character's outline is read for its meshes, targets and sliders: a glTF's JSON alone, no geometry decoded;
a USD or FBX file is read once, and that read kept for :func:`~retarget_cli.io.rig.load_rig`);
:func:`retarget_cli.io.rig.load_rig` reads the meshes it names.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

from ..._validate import closest
from ...config import unknown_key_error
from ...errors import InputError
from ..livelink import check_names_mapping
from ..obj import count_vertices
from ..text import read_yaml_file
from .readers import RIG_FILE_EXTS, read_character_outline
from .vertexmap import check_landmark_list

log = logging.getLogger(__name__)

#: Mesh and scene formats that are not rigs this version reads: given as a rig, a one-line error.
_OTHER_MESH_EXTS = (".obj", ".blend", ".dae", ".abc", ".ply", ".stl",
                    ".3ds", ".ma", ".mb", ".max", ".x3d", ".bvh", ".vrma")


@dataclass
class Rig:
    """A blendshape rig as listed in ``rig.yaml``; every path absolute.

    Attributes
    ----------
    neutral : Path or None
        Neutral OBJ (the rig's ``f0``); None for a ``source:`` rig.
    shapes : dict
        Shape name to OBJ path, in file order; for a ``source:`` rig, slider name to the source file.
    range : tuple
        Default slider range ``(lo, hi)``.
    ranges : dict
        Shape name to its ``(lo, hi)`` (every shape; the default where not overridden).
    shapes_are : {"absolute", "delta"}
        ``absolute``: each OBJ is the whole face at weight 1 (delta = shape - neutral,
        Lewis 2005 §3); ``delta``: each OBJ's vertices are the offsets themselves.
    library : dict
        Expression name to ``{slider: weight}`` over a subset of the sliders.
    correctives : object
        The ``correctives`` value, unparsed (for the inverse rig).
    """

    path: Path
    neutral: Path | None
    shapes: dict
    range: tuple = (0.0, 1.0)
    ranges: dict = field(default_factory=dict)
    shapes_are: str = "absolute"
    library: dict = field(default_factory=dict)
    #: Raw ``correctives`` list from the YAML (parsed by :mod:`retarget_cli.io.rig.inverse`), or None.
    correctives: list | None = None
    #: Rig vertex of each tracked landmark (``landmarks:``; a list of ids, or a map file read by
    #: :func:`read_vertex_map`), or None when the rig does not say.
    landmarks: list | Path | None = None
    #: Pairs of slider names that never act together (``exclusive:``), or None to infer them.
    exclusive: list | None = None
    #: ``names:``: ARKit column to the slider names it averages, for the Live Link Face CSV
    #: (:mod:`retarget_cli.io.livelink`); empty when the rig does not say.
    names: dict = field(default_factory=dict)
    #: ``source:``, the glTF/GLB/VRM, USD or FBX character the rig is read from (also the file itself when
    #: given as the rig), or None for a rig of OBJs (issue 29; read by ``apply --format same``). A source rig
    #: has ``neutral`` None and every slider of ``shapes`` names this file.
    source: Path | None = None
    #: ``meshes:`` / ``targets:``: glob patterns choosing the source's meshes and morph targets (None: the
    #: reader's defaults, every mesh with targets and all their targets).
    meshes: list | None = None
    targets: list | None = None
    #: A source rig's sliders from ``sliders:``: slider name to ``[(target name, weight), ...]``.
    sliders: dict = field(default_factory=dict)
    #: A source rig's :class:`~retarget_cli.io.rig.gltf.GltfOutline` (vertex count, meshes, target names,
    #: external buffers or layers), from :func:`~retarget_cli.io.rig.readers.read_character_outline`; None for
    #: an OBJ rig.
    outline: object = None

    def files(self) -> list[Path]:
        """Every mesh file the rig reads (the landmark map aside): the OBJs, or the source and its buffers."""
        if self.source is not None:
            return [self.source, *self.outline.files]
        return [self.neutral, *self.shapes.values()]

    def vertex_count(self) -> int:
        """The neutral's vertex count, without parsing it (the source's declared counts, or the OBJ's ``v`` lines)."""
        if self.source is not None:
            return int(self.outline.n_vertices)
        return count_vertices(self.neutral)

    def neutral_name(self) -> str:
        """How errors name the neutral: the OBJ's file name, or the source's with its meshes."""
        if self.source is None:
            return self.neutral.name
        return f"{self.source.name} (meshes {', '.join(m for m, _, _ in self.outline.mesh_ranges)})"


RIG_KEYS = ("neutral", "shapes", "shapes_are", "range", "ranges", "library", "correctives", "landmarks", "exclusive",
            "names", "source", "meshes", "targets", "sliders")
#: The keys of a ``source:`` rig (the neutral and the shapes come from the file).
SOURCE_KEYS = ("source", "meshes", "targets", "sliders", "range", "ranges", "library", "landmarks", "exclusive",
               "names")
#: ``sliders:`` words: the file's slider groups (VRM expressions, or targets merged by name), or its raw targets.
SLIDER_SETS = ("groups", "targets")


def _rig_range(value, where: str) -> tuple[float, float]:
    """``t`` (meaning ``[0, t]``) or ``[lo, hi]`` to ``(lo, hi)``."""
    num = (int, float)
    if isinstance(value, num) and not isinstance(value, bool):
        value = [0.0, value]
    if (not isinstance(value, (list, tuple)) or len(value) != 2
            or not all(isinstance(v, num) and not isinstance(v, bool) for v in value) or not value[0] < value[1]):
        raise InputError(f"{where}: expected a number t (range [0, t]) or [lo, hi] with lo < hi, got {value!r}")
    return float(value[0]), float(value[1])


def _slider(name, where: str, shapes: dict) -> str:
    """*name* as a slider of the rig; an unknown one gets the closest name (or the list) in the message."""
    if str(name) not in shapes:
        hint = closest(str(name), shapes)
        raise InputError(f"{where}: unknown slider {name!r}" + (f"; did you mean {hint!r}?" if hint else
                                                                f"; the rig's sliders are {', '.join(shapes)}"))
    return str(name)


def _rig_shapes(path: Path, data) -> dict:
    """The checked top level of ``rig.yaml``: shape name to absolute OBJ path."""
    if not isinstance(data, dict) or not isinstance(data.get("neutral"), str) or not isinstance(data.get("shapes"), dict):
        raise InputError(f"{path}: expected 'neutral: file.obj' and 'shapes: {{name: file.obj}}'")
    for key in data:
        if key not in RIG_KEYS:
            raise unknown_key_error(str(path), str(key), RIG_KEYS, error=InputError)
    if not data["shapes"] or not all(isinstance(v, str) for v in data["shapes"].values()):
        raise InputError(f"{path}: shapes: expected a non-empty mapping of shape names to OBJ files")
    return {str(k): path.parent / v for k, v in data["shapes"].items()}


def _rig_ranges(path: Path, data: dict, shapes: dict, rng: tuple) -> dict:
    """Every slider's ``(lo, hi)``: *rng* unless ``ranges:`` overrides it."""
    over = data.get("ranges") or {}
    if not isinstance(over, dict):
        raise InputError(f"{path}: ranges: expected a mapping of slider names to t or [lo, hi]")
    ranges = {n: rng for n in shapes}
    for name, value in over.items():
        ranges[_slider(name, f"{path}: ranges", shapes)] = _rig_range(value, f"{path}: ranges.{name}")
    return ranges


def _rig_library(path: Path, data: dict, shapes: dict, ranges: dict) -> dict:
    """``library:`` as ``{expression: {slider: weight}}``, each weight within its slider's range."""
    library = {}
    lib = data.get("library") or {}
    if not isinstance(lib, dict):
        raise InputError(f"{path}: library: expected {{expression: {{slider: weight}}}}")
    for expr, vec in lib.items():
        where = f"{path}: library.{expr}"
        if not isinstance(vec, dict) or not vec:
            raise InputError(f"{where}: expected a non-empty mapping of slider names to weights")
        library[str(expr)] = {}
        for name, value in vec.items():
            name = _slider(name, where, shapes)
            lo, hi = ranges[name]
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not lo <= value <= hi:
                raise InputError(f"{where}.{name}: expected a number in the slider's range [{lo:g}, {hi:g}], got {value!r}")
            library[str(expr)][name] = float(value)
    return library


def _rig_landmarks(path: Path, data: dict) -> list | Path | None:
    """``landmarks:``: a list of vertex ids, or a map file (made absolute)."""
    landmarks = data.get("landmarks")
    if isinstance(landmarks, str):
        return path.parent / landmarks
    if landmarks is None:
        return None
    if not isinstance(landmarks, list) or not landmarks:
        raise InputError(f"{path}: landmarks: expected a list of vertex ids (one per landmark, >= 0) or a map "
                         f"file, got {str(landmarks)[:60]!r}")
    for i, v in enumerate(landmarks):
        if not (isinstance(v, int) and not isinstance(v, bool) and v >= 0):
            raise InputError(f"{path}: landmarks[{i}] = {str(v)[:40]!r}: expected a vertex id (an integer >= 0)")
    return landmarks


def _rig_exclusive(path: Path, data: dict, shapes: dict) -> list | None:
    """``exclusive:`` as a list of slider-name pairs, or None."""
    exclusive = data.get("exclusive")
    if exclusive is None:
        return None
    if not isinstance(exclusive, list):
        raise InputError(f"{path}: exclusive: expected a list of [slider, slider] pairs")
    pairs = []
    for i, pair in enumerate(exclusive):
        if not isinstance(pair, list) or len(pair) != 2 or pair[0] == pair[1]:
            raise InputError(f"{path}: exclusive[{i}]: expected a pair of two different slider names, got {pair!r}")
        pairs.append(tuple(_slider(n, f"{path}: exclusive[{i}]", shapes) for n in pair))
    return pairs


def read_rig(path: str | os.PathLike) -> Rig:
    """Read ``rig.yaml``, or a character file (glTF/GLB/VRM, USD, FBX) given as the rig itself.

    Keys: ``neutral``, ``shapes: {name: obj}``, optional ``shapes_are``
    (``absolute`` or ``delta``), ``range`` (``t`` or ``[lo, hi]``, every
    slider), ``ranges`` (per-shape overrides), ``library`` (``{expression:
    {slider: weight}}``), ``correctives`` (kept unparsed), ``landmarks``,
    ``exclusive`` and ``names`` (``{ARKitName: slider or [sliders]}``, for
    the Live Link Face CSV).

    Or, instead of ``neutral``/``shapes``: ``source: char.glb`` (a ``.glb``,
    ``.gltf``, ``.vrm``, ``.usd``/``.usda``/``.usdc``/``.usdz`` or ``.fbx`` beside or below ``rig.yaml``), optional ``meshes``
    and ``targets`` (glob patterns, a string or a list) and ``sliders``
    (``groups``, the default: VRM expressions or targets merged by name;
    ``targets``: one slider per morph target; ``{slider: {target: weight}}``;
    or a list of these), with ``range``, ``ranges``, ``library``,
    ``landmarks``, ``exclusive`` and ``names`` as above. A character file
    given directly is the rig ``source: <it>`` with every default. Only the
    character's outline is read here (:func:`~retarget_cli.io.rig.readers.read_character_outline`);
    ``landmarks:`` vertex ids are checked against its declared vertex count.

    Raises
    ------
    InputError, ConfigError
        Naming the file and the key; unknown keys and slider or target names
        get the closest valid name as a suggestion.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in RIG_FILE_EXTS:
        return _read_source_rig(path, {"source": path.name}, path)
    if suffix in _OTHER_MESH_EXTS:
        raise InputError(f"{path}: a {suffix} file is not a rig this version reads; a rig is a rig.yaml "
                         f"(OBJs, or 'source:' a {', '.join(RIG_FILE_EXTS)} file) or such a file itself")
    data = read_yaml_file(path, "rig")
    if isinstance(data, dict) and "source" in data:
        return _read_source_rig(path, data, None)
    shapes = _rig_shapes(path, data)
    shapes_are = data.get("shapes_are", "absolute")
    if shapes_are not in ("absolute", "delta"):
        raise InputError(f"{path}: shapes_are: expected 'absolute' or 'delta', got {shapes_are!r}")
    rng = _rig_range(data.get("range", [0.0, 1.0]), f"{path}: range")
    ranges = _rig_ranges(path, data, shapes, rng)
    library = _rig_library(path, data, shapes, ranges)
    landmarks = _rig_landmarks(path, data)
    exclusive = _rig_exclusive(path, data, shapes)
    names = check_names_mapping(data.get("names"), shapes, f"{path}: names")
    return Rig(path, path.parent / data["neutral"], shapes, rng, ranges, shapes_are, library, data.get("correctives"),
               landmarks, exclusive, names)


# ---------------------------------------------------------------------- source: a character file
def _source_path(path: Path, data: dict) -> Path:
    """``source:`` made absolute: a character file (:data:`RIG_FILE_EXTS`) that exists."""
    value = data["source"]
    if not isinstance(value, str) or not value:
        raise InputError(f"{path}: source: expected the path of a {', '.join(RIG_FILE_EXTS)} file, got {value!r}")
    source = path.parent / value
    if source.suffix.lower() not in RIG_FILE_EXTS:
        raise InputError(f"{path}: source: {value}: unsupported rig file extension {source.suffix or '(none)'!r}; "
                         f"this version reads {', '.join(RIG_FILE_EXTS)}")
    if not source.is_file():
        raise InputError(f"{path}: source: {value} not found")
    return source


def _patterns(path: Path, data: dict, key: str) -> list | None:
    """``meshes:`` / ``targets:``: a glob pattern or a list of them, or None."""
    value = data.get(key)
    if value is None:
        return None
    pats = [value] if isinstance(value, str) else value
    if not isinstance(pats, list) or not pats or not all(isinstance(p, str) and p for p in pats):
        raise InputError(f"{path}: {key}: expected a glob pattern or a list of them, got {value!r}")
    return list(pats)


def _outline(path: Path, source: Path, meshes, targets):
    """The source's outline; its errors name ``rig.yaml`` too when the rig is one."""
    try:
        return read_character_outline(source, meshes=meshes, targets=targets)
    except InputError as exc:
        if path == source:
            raise
        raise InputError(f"{path}: source {exc}") from None


def _explicit_group(where: str, binds, outline) -> list:
    """One ``sliders:`` entry ``{target: weight}`` as ``[(target name, weight)]``."""
    if not isinstance(binds, dict) or not binds:
        raise InputError(f"{where}: expected a non-empty mapping {{target: weight}}, got {binds!r}")
    group = []
    for target, weight in binds.items():
        if str(target) not in outline.target_names:
            hint = closest(str(target), outline.target_names)
            shown = ", ".join(outline.target_names[:12]) + ("" if len(outline.target_names) <= 12 else
                                                            f", ... ({len(outline.target_names)} in all)")
            raise InputError(f"{where}: unknown target {target!r}" + (f"; did you mean {hint!r}?" if hint else
                                                                      f"; the file's targets: {shown}"))
        if isinstance(weight, bool) or not isinstance(weight, (int, float)) or not math.isfinite(weight):
            raise InputError(f"{where}.{target}: expected a number (the target's weight), got {weight!r}")
        group.append((str(target), float(weight)))
    return group


def _source_sliders(path: Path, value, outline) -> dict:
    """``sliders:`` resolved: slider name to ``[(target name, weight)]``, in order."""
    where = f"{path}: sliders"
    entries = ["groups"] if value is None else value if isinstance(value, list) else [value]
    if not entries:
        raise InputError(f"{where}: expected 'groups', 'targets', {{slider: {{target: weight}}}} or a list of them")
    found, origin, explicit = {}, {}, {}
    for entry in entries:
        if isinstance(entry, str) and entry in SLIDER_SETS:
            groups = outline.groups if entry == "groups" else outline.raw_groups
            for name, binds in groups.items():
                if name in origin:
                    raise InputError(f"{where}: slider {name!r} comes from both {origin[name]} and {entry}; "
                                     "list one of them")
                origin[name] = entry
                found[name] = [(outline.target_names[k], float(w)) for k, w in binds]
        elif isinstance(entry, dict) and entry:
            for name, binds in entry.items():
                if str(name) in explicit:
                    raise InputError(f"{where}.{name}: defined twice")
                explicit[str(name)] = _explicit_group(f"{where}.{name}", binds, outline)
        else:
            raise InputError(f"{where}: expected 'groups', 'targets', a mapping {{slider: {{target: weight}}}} "
                             f"or a list of them, got {entry!r}")
    for name in explicit:
        if name in found:
            log.info("%s: sliders.%s replaces the slider of that name from %s", path, name, origin[name])
    found.update(explicit)
    return found


def _read_source_rig(path: Path, data: dict, direct: Path | None) -> Rig:
    """A rig read from a character file: ``rig.yaml`` with ``source:``, or the file itself (*direct*)."""
    for key in data:
        if key not in SOURCE_KEYS:
            if key in RIG_KEYS:
                raise InputError(f"{path}: {key}: not used with 'source:' (the neutral and the shapes come from "
                                 f"the source file); the keys of a source rig: {', '.join(SOURCE_KEYS)}")
            raise unknown_key_error(str(path), str(key), SOURCE_KEYS, error=InputError)
    source = direct if direct is not None else _source_path(path, data)
    meshes, targets = _patterns(path, data, "meshes"), _patterns(path, data, "targets")
    outline = _outline(path, source, meshes, targets)
    sliders = _source_sliders(path, data.get("sliders"), outline)
    shapes = {name: source for name in sliders}
    rng = _rig_range(data.get("range", [0.0, 1.0]), f"{path}: range")
    ranges = _rig_ranges(path, data, shapes, rng)
    library = _rig_library(path, data, shapes, ranges)
    landmarks = _rig_landmarks(path, data)
    exclusive = _rig_exclusive(path, data, shapes)
    names = check_names_mapping(data.get("names"), shapes, f"{path}: names")
    rig = Rig(path, None, shapes, rng, ranges, "delta", library, None, landmarks, exclusive, names,
              source=source, meshes=meshes, targets=targets, sliders=sliders, outline=outline)
    if isinstance(landmarks, list):
        check_landmark_list(str(path), landmarks, outline.n_vertices, rig.neutral_name())
    return rig


__all__ = ["RIG_FILE_EXTS", "RIG_KEYS", "Rig", "SLIDER_SETS", "SOURCE_KEYS", "read_rig"]
