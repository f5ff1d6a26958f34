"""``rig.yaml``: a blendshape rig described as a neutral OBJ, one OBJ per slider and their settings.

:func:`read_rig` parses and checks the file (every path absolute, every name known);
:func:`retarget_cli.io.rig.load_rig` reads the meshes it names.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from ..._validate import closest
from ...config import unknown_key_error
from ...errors import InputError
from ..livelink import check_names_mapping
from ..text import read_yaml_file


@dataclass
class Rig:
    """A blendshape rig as listed in ``rig.yaml``; every path absolute.

    Attributes
    ----------
    neutral : Path
        Neutral OBJ (the rig's ``f0``).
    shapes : dict
        Shape name to OBJ path, in file order.
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
    neutral: Path
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
    #: The glTF/GLB/VRM file the rig was read from, or None for a rig of OBJs (issue 29; read by
    #: ``apply --format same``). Always None here until ``rig.yaml`` takes ``source:``.
    source: Path | None = None

    def files(self) -> list[Path]:
        return [self.neutral, *self.shapes.values()]


RIG_KEYS = ("neutral", "shapes", "shapes_are", "range", "ranges", "library", "correctives", "landmarks", "exclusive",
            "names")


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
    if landmarks is not None and (
            not isinstance(landmarks, list) or not landmarks
            or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in landmarks)):
        raise InputError(f"{path}: landmarks: expected a list of vertex ids (one per landmark, >= 0) or a map "
                         f"file, got {str(landmarks)[:60]!r}")
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
    """Read ``rig.yaml``.

    Keys: ``neutral``, ``shapes: {name: obj}``, optional ``shapes_are``
    (``absolute`` or ``delta``), ``range`` (``t`` or ``[lo, hi]``, every
    slider), ``ranges`` (per-shape overrides), ``library`` (``{expression:
    {slider: weight}}``), ``correctives`` (kept unparsed), ``landmarks``,
    ``exclusive`` and ``names`` (``{ARKitName: slider or [sliders]}``, for
    the Live Link Face CSV).

    Raises
    ------
    InputError, ConfigError
        Naming the file and the key; unknown keys and slider names get the
        closest valid name as a suggestion.
    """
    path = Path(path)
    data = read_yaml_file(path, "rig")
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


__all__ = ["RIG_KEYS", "Rig", "read_rig"]
