"""The character's own glTF/GLB/VRM file back, animated: a copy with the curves as morph-weight animation,
and for VRM a VRM Animation (``.vrma``) of its expressions (issue 29, part 4).

:func:`write_animated_copy` writes a GLB that holds everything of the source
(glTF 2.0 specification, Khronos 2021): its JSON, parsed and written back with
every entry, unknown extensions and extras included, as they were; its BIN
chunk byte for byte (compressed ``EXT_meshopt_compression`` streams,
``KHR_mesh_quantization`` attributes, textures, skins, VRM metadata), and
after it, 4-byte aligned, the new data: one animation (§3.11) with, per node
whose mesh has morph targets, a ``weights`` channel, sampler ``LINEAR``,
input the frame times ``t / fps`` (float32, with ``min``/``max``), output
``T x n_targets`` float32. Each target's weight is the sum over the sliders
that drive it of ``curve x bind weight`` (curves clipped to their slider's
range); a target no slider drives keeps the node's or mesh's default weight
(0 when the file gives none). What changes in the JSON: buffer 0's
``byteLength`` (and its ``uri``, dropped, when the source kept it outside a
GLB BIN chunk); external buffers and images, which would not resolve beside
the copy, become base64 ``data:`` URIs; new ``bufferViews``, ``accessors``
and one more ``animations`` entry are appended. ``extensionsUsed`` is not
touched (an animation needs no extension). GLB chunks after BIN are dropped.

:func:`write_vrma` writes the ``VRMC_vrm_animation`` 1.0 file (VRM
Consortium, vrm-specification/specification/VRMC_vrm_animation-1.0): the
source's humanoid skeleton at rest (its bones' world positions, VRM 0.x
turned to face +z as VRM 1.0 does, no rotation: the VRM T-pose), no bone
animation, and one node per VRM expression that a slider drives, whose
``translation.x`` is the expression's weight in [0, 1] at every frame.
VRM 0.x preset names become VRM 1.0's (``a`` -> ``aa``, ``joy`` ->
``happy``, ``blink_l`` -> ``blinkLeft``, ... as three-vrm maps them), other
0.x groups are custom expressions under their ``name``; ``lookUp``/``Down``/
``Left``/``Right`` are left out (the extension gives gaze to ``lookAt``).

The source is untrusted: it is opened by the rig reader's checked
:class:`~retarget_cli.io.rig.gltf.GltfFile` (container, JSON, extensions,
buffers), and external URIs resolve inside its folder only (no ``..``, no
absolute path, no URL, regular files only).
"""

from __future__ import annotations

import base64
import copy
import json
import logging
import os
import struct
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import ParameterError
from .atomic import write_bytes
from .rig.gltf import GltfFile, GltfRig, node_world_matrices

log = logging.getLogger(__name__)

#: Name of the animation added to the copy and of the ``.vrma``'s.
ANIMATION_NAME = "retarget"
#: Largest external image or buffer embedded into the copy.
MAX_RESOURCE_BYTES = 1 << 30
_FLOAT = 5126
_MESHOPT = "EXT_meshopt_compression"

#: VRM 0.x ``presetName`` -> VRM 1.0 expression (three-vrm's ``VRMExpressionLoaderPlugin.v0v1PresetNameMap``).
VRM0_PRESETS = {"a": "aa", "i": "ih", "u": "ou", "e": "ee", "o": "oh", "blink": "blink", "joy": "happy",
                "angry": "angry", "sorrow": "sad", "fun": "relaxed", "lookup": "lookUp", "lookdown": "lookDown",
                "lookleft": "lookLeft", "lookright": "lookRight", "blink_l": "blinkLeft", "blink_r": "blinkRight",
                "neutral": "neutral"}
#: VRM 1.0 preset expressions (VRMC_vrm-1.0 expressions.md).
VRM1_PRESETS = ("happy", "angry", "sad", "relaxed", "surprised", "aa", "ih", "ou", "ee", "oh", "blink", "blinkLeft",
                "blinkRight", "lookUp", "lookDown", "lookLeft", "lookRight", "neutral")
#: Presets a ``.vrma`` may not animate as expressions (gaze is its ``lookAt``).
_GAZE = ("lookUp", "lookDown", "lookLeft", "lookRight")
_FINGERS = [f"{side}{finger}{joint}" for side in ("left", "right")
            for finger, joints in (("Thumb", ("Metacarpal", "Proximal", "Distal")),
                                   ("Index", ("Proximal", "Intermediate", "Distal")),
                                   ("Middle", ("Proximal", "Intermediate", "Distal")),
                                   ("Ring", ("Proximal", "Intermediate", "Distal")),
                                   ("Little", ("Proximal", "Intermediate", "Distal"))) for joint in joints]
#: VRM 1.0 humanoid bones a ``.vrma`` may hold (its humanBones schema: no eyes).
VRMA_BONES = ("hips", "spine", "chest", "upperChest", "neck", "head", "jaw", "leftUpperLeg", "leftLowerLeg",
              "leftFoot", "leftToes", "rightUpperLeg", "rightLowerLeg", "rightFoot", "rightToes", "leftShoulder",
              "leftUpperArm", "leftLowerArm", "leftHand", "rightShoulder", "rightUpperArm", "rightLowerArm",
              "rightHand", *_FINGERS)
#: Bones the ``.vrma`` humanoid schema requires.
VRMA_REQUIRED_BONES = ("hips", "spine", "head", "leftUpperLeg", "leftLowerLeg", "leftFoot", "rightUpperLeg",
                       "rightLowerLeg", "rightFoot", "leftUpperArm", "leftLowerArm", "leftHand", "rightUpperArm",
                       "rightLowerArm", "rightHand")
#: VRM 0.x thumb bones -> VRM 1.0 (1.0 renamed the thumb joints one step towards the wrist).
_VRM0_THUMBS = {f"{s}Thumb{a}": f"{s}Thumb{b}" for s in ("left", "right")
                for a, b in (("Proximal", "Metacarpal"), ("Intermediate", "Proximal"), ("Distal", "Distal"))}
_IMAGE_MAGIC = ((b"\x89PNG", "image/png"), (b"\xff\xd8\xff", "image/jpeg"), (b"\xabKTX 20", "image/ktx2"),
                (b"GIF8", "image/gif"))


# ---------------------------------------------------------------------- sliders -> targets
def copy_groups(rig: GltfRig, names) -> tuple[dict, list[str]]:
    """The ``(node, morph target, weight)`` binds of each slider *names* of a rig read from the file.

    A name is looked up among ``rig.groups`` (name groups or VRM expressions), then
    ``rig.raw_groups`` (one target each).

    Returns
    -------
    groups : dict of str to list of (int, int, float)
        Slider name to ``(node index, morph target index, weight)``.
    missing : list of str
        The names that are neither (not animated in the copy).
    """
    groups, missing = {}, []
    for name in names:
        binds = rig.groups.get(name, rig.raw_groups.get(name))
        if binds is None:
            missing.append(name)
            continue
        groups[name] = [(*rig.target_refs[j], float(w)) for j, w in binds]
    return groups, missing


def _times(times, T: int, fps: float) -> np.ndarray:
    """Keyframe times in seconds: *times* (each frame's source timestamp) checked, else ``t / fps``."""
    if times is None:
        return np.arange(T) / float(fps)
    t = np.asarray(times, dtype=np.float64)
    if t.shape != (T,) or not np.isfinite(t).all() or np.any(np.diff(t) <= 0):
        raise ParameterError(f"times: expected {T} increasing seconds, got shape {t.shape}")
    return t


def clipped_curves(curves, names, lower=None, upper=None) -> np.ndarray:
    """(T, E) float64 curves, checked (shape, finite), each clipped to its slider's ``[lower, upper]``."""
    C = np.asarray(curves, dtype=np.float64)
    names = list(names)
    if C.ndim != 2 or C.shape[1] != len(names) or len(C) == 0:
        raise ParameterError(f"curves: expected (T >= 1, {len(names)}) values for the {len(names)} sliders, "
                             f"got shape {C.shape}")
    if not np.isfinite(C).all():
        raise ParameterError("curves: values that are not finite")
    lo = np.full(len(names), -np.inf) if lower is None else np.asarray(lower, dtype=np.float64)
    hi = np.full(len(names), np.inf) if upper is None else np.asarray(upper, dtype=np.float64)
    return np.clip(C, lo, hi)


def check_fps(fps) -> None:
    """A :class:`ParameterError` unless *fps* is a positive finite number."""
    if not (isinstance(fps, int | float) and np.isfinite(fps) and fps > 0):
        raise ParameterError(f"fps: expected a positive number, got {fps!r}")


def _curves(curves, names, fps: float, lower, upper) -> np.ndarray:
    C = clipped_curves(curves, names, lower, upper)
    check_fps(fps)
    return C


def _n_targets(f: GltfFile, mesh: int, where: str) -> int:
    prims = f.field(f.item("meshes", mesh, where), "primitives", f"mesh {mesh}", list)
    n = 0
    for p, prim in enumerate(prims):
        if not isinstance(prim, dict):
            raise f.error(f"mesh {mesh} primitive {p} is not an object")
        n = max(n, len(f.field(prim, "targets", f"mesh {mesh} primitive {p}", list, [])))
    return n


def morph_nodes(f: GltfFile) -> dict[int, tuple[int, np.ndarray]]:
    """Every node whose mesh has morph targets: node index -> (n targets, default weights (n,) float64).

    The default is the node's ``weights``, else the mesh's, else 0 (glTF 2.0 §3.7.2.2).
    """
    out = {}
    for i in range(len(f.items("nodes"))):
        node = f.item("nodes", i, "the file")
        if "mesh" not in node:
            continue
        m = f.field(node, "mesh", f"node {i}", int, low=0)
        n = _n_targets(f, m, f"node {i}")
        if n:
            mesh = f.item("meshes", m, f"node {i}")
            default = f.numbers(node, "weights", f"node {i}", n, None)
            if default is None:
                default = f.numbers(mesh, "weights", f"mesh {m}", n, np.zeros(n))
            out[i] = (n, default)
    return out


def target_weights(f: GltfFile, curves: np.ndarray, names, groups: dict) -> dict[int, np.ndarray]:
    """Per morph node, its weights at every frame: node index -> (T, n_targets) float64.

    A target's weight is ``sum_s curves[:, s] * w`` over the binds ``(node, k, w)`` of the sliders *s*
    that drive it; a target no slider drives keeps its default weight.
    """
    nodes = morph_nodes(f)
    if not nodes:
        raise f.error("no node has a mesh with morph targets; nothing to animate")
    T = len(curves)
    index = {name: e for e, name in enumerate(names)}
    weights = {i: np.tile(d, (T, 1)) for i, (_, d) in nodes.items()}
    driven = {i: np.zeros(n, dtype=bool) for i, (n, _) in nodes.items()}
    for name, binds in groups.items():
        if name not in index:
            raise ParameterError(f"groups: slider {name!r} has no curve (sliders: {', '.join(map(str, names))})")
        for node, k, w in binds:
            if node not in nodes or not 0 <= k < nodes[node][0]:
                raise f.error(f"slider {name!r}: node {node} morph target {k} is not a morph target of the file")
            if not driven[node][k]:
                weights[node][:, k] = 0.0
                driven[node][k] = True
            weights[node][:, k] += curves[:, index[name]] * float(w)
    return weights


# ---------------------------------------------------------------------- the copy's buffers
class _Appender:
    """New bufferViews and accessors of buffer 0, appended 4-byte aligned after its bytes."""

    def __init__(self, doc: dict, base: bytes):
        self.doc = doc
        self.data = bytearray(base)

    def floats(self, arr: np.ndarray, atype: str, *, bounds: bool = False) -> int:
        """Append *arr* (count, components) as float32; return the accessor index."""
        arr = np.ascontiguousarray(arr, dtype="<f4")
        self.data += b"\0" * (-len(self.data) % 4)
        views = self.doc.setdefault("bufferViews", [])
        views.append({"buffer": 0, "byteOffset": len(self.data), "byteLength": arr.nbytes})
        self.data += arr.tobytes()
        acc = {"bufferView": len(views) - 1, "componentType": _FLOAT, "count": int(arr.shape[0]), "type": atype}
        if bounds:
            acc["min"] = [float(v) for v in arr.min(axis=0).reshape(-1)]
            acc["max"] = [float(v) for v in arr.max(axis=0).reshape(-1)]
        accessors = self.doc.setdefault("accessors", [])
        accessors.append(acc)
        return len(accessors) - 1


def _data_uri(data: bytes, mime: str) -> str:
    return f"data:{mime};base64," + base64.b64encode(data).decode("ascii")


def _image_mime(image: dict, data: bytes) -> str:
    mime = image.get("mimeType")
    if isinstance(mime, str) and mime:
        return mime
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "image/webp"
    return next((m for magic, m in _IMAGE_MAGIC if data.startswith(magic)), "application/octet-stream")


def _base_buffer(f: GltfFile, doc: dict) -> bytes:
    """The bytes buffer 0 starts with in the copy (the source's BIN chunk, whole); buffer 0 made the BIN chunk's."""
    if not f.items("buffers"):
        doc["buffers"] = [{"byteLength": 0}]
        return b""
    f.item("buffers", 0, "the copy")
    first = doc["buffers"][0]
    if "uri" in first:
        data = bytes(f.buffer(0, "the copy"))
        del first["uri"]
        return data
    ext = first.get("extensions")
    if isinstance(ext, dict) and isinstance(ext.get(_MESHOPT), dict) and ext[_MESHOPT].get("fallback"):
        raise f.error(f"buffer 0 is an {_MESHOPT} fallback (no data), the copy cannot append to it")
    f.buffer(0, "the copy")  # checked: the BIN chunk holds its byteLength
    return bytes(f.bin)


def _embed_external(f: GltfFile, doc: dict) -> None:
    """External buffers (after the first) and images as ``data:`` URIs: their files stay behind in the source folder."""
    for i, buf in enumerate(doc.get("buffers", [])[1:], start=1):
        uri = buf.get("uri") if isinstance(buf, dict) else None
        if isinstance(uri, str) and not uri.startswith("data:"):
            buf["uri"] = _data_uri(bytes(f.buffer(i, "the copy")), "application/octet-stream")
            log.info("%s: buffer %d (%s) embedded in the copy as a data: URI", f.name, i, uri)
    for i, image in enumerate(f.items("images")):
        uri = image.get("uri") if isinstance(image, dict) else None
        if uri is None:
            continue
        if not isinstance(uri, str):
            raise f.error(f"image {i}: 'uri' must be a string")
        if not uri.startswith("data:"):
            data = f.resource(uri, f"image {i}", MAX_RESOURCE_BYTES)
            doc["images"][i]["uri"] = _data_uri(data, _image_mime(image, data))
            log.info("%s: image %d (%s) embedded in the copy as a data: URI", f.name, i, uri)


def _glb(f: GltfFile, doc: dict, binary: bytes, *, sort_keys: bool = False) -> bytes:
    """GLB container (glTF 2.0 §4.4): JSON chunk padded with spaces, BIN chunk padded with zeros.

    The JSON keeps *doc*'s key order (a copy keeps the source's), or sorts it (a new file).
    """
    try:
        js = json.dumps(doc, ensure_ascii=False, separators=(",", ":"), allow_nan=False,
                        sort_keys=sort_keys).encode("utf-8")
    except ValueError:
        raise f.error("the JSON holds a number that is not finite (NaN or Infinity); not written") from None
    except RecursionError:
        raise f.error("the JSON is nested too deeply to write") from None
    js += b" " * (-len(js) % 4)
    binary = bytes(binary) + b"\0" * (-len(binary) % 4)
    body = struct.pack("<II", len(js), 0x4E4F534A) + js
    if binary:
        body += struct.pack("<II", len(binary), 0x004E4942) + binary
    if 12 + len(body) >= 1 << 32:
        raise f.error(f"the copy would be {12 + len(body)} bytes, more than a GLB can hold (4 GiB)")
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def animated_copy_bytes(source, curves, names, fps: float, groups: dict, *, lower=None, upper=None, times=None,
                        name: str = ANIMATION_NAME) -> bytes:
    """The bytes of :func:`write_animated_copy` (see the module docstring).

    Parameters
    ----------
    source : path-like
        The character's ``.glb``, ``.gltf`` or ``.vrm``.
    curves : ndarray, shape (T, E)
        Slider values per frame.
    names : sequence of str
        The E slider names.
    fps : float
    groups : dict of str to list of (int, int, float)
        Slider name to its binds ``(node index, morph target index, weight)`` (:func:`copy_groups`).
    lower, upper : array_like, shape (E,), optional
        Each slider's range; the curves are clipped to it.
    """
    f = GltfFile(source)
    for key in ("bufferViews", "accessors", "animations", "images"):
        f.items(key)  # lists, or absent (checked: the copy appends to them)
    C = _curves(curves, names, fps, lower, upper)
    weights = target_weights(f, C, list(names), groups)
    try:
        doc = copy.deepcopy(f.json)
    except RecursionError:
        raise f.error("the JSON is nested too deeply to copy") from None
    base = _base_buffer(f, doc)
    _embed_external(f, doc)
    out = _Appender(doc, base + b"\0" * (-len(base) % 4))
    times = out.floats(_times(times, len(C), fps)[:, None], "SCALAR", bounds=True)
    channels, samplers = [], []
    for node, W in sorted(weights.items()):
        samplers.append({"input": times, "interpolation": "LINEAR", "output": out.floats(W.reshape(-1, 1), "SCALAR")})
        channels.append({"sampler": len(samplers) - 1, "target": {"node": node, "path": "weights"}})
    doc.setdefault("animations", []).append({"name": name, "channels": channels, "samplers": samplers})
    doc["buffers"][0]["byteLength"] = len(out.data)
    return _glb(f, doc, bytes(out.data))


def write_animated_copy(path: str | os.PathLike, source, curves, names, fps: float, groups: dict, *, times=None,
                        lower=None,
                        upper=None) -> Path:
    """Write an animated copy of *source* to *path* (a GLB), atomically; see :func:`animated_copy_bytes`."""
    write_bytes(path, animated_copy_bytes(source, curves, names, fps, groups, lower=lower, upper=upper, times=times))
    return Path(path)


# ---------------------------------------------------------------------- VRM Animation (.vrma)
def _fresh(name: str, used: set) -> str:
    """The reader's naming of a repeated slider name (``name~2``, ...)."""
    out, n = name, 2
    while out in used:
        out, n = f"{name}~{n}", n + 1
    used.add(out)
    return out


def vrm_expressions(f: GltfFile) -> dict[str, tuple[str, str]]:
    """Each VRM expression of the file as :func:`~retarget_cli.io.rig.gltf.read_gltf_rig` names its slider,
    to ``("preset" or "custom", its VRM 1.0 name)``; empty for a file that is not VRM."""
    ext = f.field(f.json, "extensions", "the file", dict, {})
    out: dict[str, tuple[str, str]] = {}
    used: set = set()
    if isinstance(ext.get("VRMC_vrm"), dict):
        expressions = f.field(ext["VRMC_vrm"], "expressions", "VRMC_vrm", dict, {})
        for section in ("preset", "custom"):
            for key in f.field(expressions, section, "VRMC_vrm.expressions", dict, {}):
                out[_fresh(key, used)] = ("preset" if key in VRM1_PRESETS else "custom", key)
    elif isinstance(ext.get("VRM"), dict):
        master = f.field(ext["VRM"], "blendShapeMaster", "VRM", dict, {})
        for g, group in enumerate(f.field(master, "blendShapeGroups", "VRM blendShapeMaster", list, [])):
            where = f"VRM blendShapeGroups[{g}]"
            if not isinstance(group, dict):
                raise f.error(f"{where} is not an object")
            preset = f.field(group, "presetName", where, str, "")
            label = f.field(group, "name", where, str, "")
            slider = _fresh(preset if preset and preset != "unknown" else label or f"group{g}", used)
            if preset in VRM0_PRESETS:
                out[slider] = ("preset", VRM0_PRESETS[preset])
            else:
                out[slider] = ("custom", label or slider)
    return out


def _humanoid(f: GltfFile) -> tuple[dict[str, int], bool]:
    """The source's humanoid bones as ``{VRM 1.0 bone name: node}`` and whether it is VRM 0.x."""
    ext = f.field(f.json, "extensions", "the file", dict, {})
    bones: dict[str, int] = {}
    if isinstance(ext.get("VRMC_vrm"), dict):
        hum = f.field(ext["VRMC_vrm"], "humanoid", "VRMC_vrm", dict, {})
        for name, bone in f.field(hum, "humanBones", "VRMC_vrm.humanoid", dict, {}).items():
            if isinstance(bone, dict) and name in VRMA_BONES:
                bones[name] = f.field(bone, "node", f"VRMC_vrm.humanoid.humanBones.{name}", int, low=0)
        return bones, False
    hum = f.field(f.field(ext, "VRM", "the file", dict, {}), "humanoid", "VRM", dict, {})
    for b, bone in enumerate(f.field(hum, "humanBones", "VRM.humanoid", list, [])):
        if not isinstance(bone, dict):
            raise f.error(f"VRM.humanoid.humanBones[{b}] is not an object")
        name = f.field(bone, "bone", f"VRM.humanoid.humanBones[{b}]", str, "")
        name = _VRM0_THUMBS.get(name, name)
        if name in VRMA_BONES and name not in bones:
            bones[name] = f.field(bone, "node", f"VRM.humanoid.humanBones[{b}]", int, low=0)
    return bones, True


def _skeleton(f: GltfFile) -> tuple[list[dict], dict[str, int], list[int]]:
    """The ``.vrma``'s bone nodes at rest (T-pose: translations only), ``{bone: node}`` and the root nodes."""
    bones, vrm0 = _humanoid(f)
    missing = [b for b in VRMA_REQUIRED_BONES if b not in bones]
    if missing:
        log.warning("%s: the humanoid has no %s; the .vrma's skeleton lacks them", f.name, ", ".join(missing))
    world = node_world_matrices(f)
    parent: dict[int, int] = {}
    for i in range(len(world)):
        for c in f.item("nodes", i, "the file").get("children", []):
            parent[c] = i
    order = [b for b in VRMA_BONES if b in bones]
    for b in order:
        f.item("nodes", bones[b], f"humanoid bone {b}")
    slot = {bones[b]: j for j, b in enumerate(order)}
    flip = np.array([-1.0, 1.0, -1.0]) if vrm0 else np.ones(3)  # VRM 0.x faces -z; a .vrma faces +z
    nodes, roots = [{"name": b} for b in order], []
    for j, b in enumerate(order):
        up = parent.get(bones[b])
        while up is not None and up not in slot:
            up = parent.get(up)
        pos = world[bones[b]][:3, 3] * flip
        if up is None:
            roots.append(j)
        else:
            pos = pos - world[up][:3, 3] * flip
            nodes[slot[up]].setdefault("children", []).append(j)
        nodes[j]["translation"] = [float(v) for v in pos]
    return nodes, {b: j for j, b in enumerate(order)}, roots


def _expression_tracks(f: GltfFile, C: np.ndarray, names) -> list[tuple[str, str, np.ndarray]]:
    """``(section, VRM 1.0 name, weights (T,) in [0, 1])`` of each slider that is a VRM expression of the file."""
    table = vrm_expressions(f)
    tracks, seen, gaze = [], set(), []
    for e, name in enumerate(names):
        if name not in table:
            continue
        section, expr = table[name]
        if expr in _GAZE:
            gaze.append(name)
        elif (section, expr) in seen:
            log.warning("%s: slider %s is expression %s again; the .vrma keeps the first", f.name, name, expr)
        else:
            seen.add((section, expr))
            tracks.append((section, expr, np.clip(C[:, e], 0.0, 1.0)))
    if gaze:
        log.info("%s: %s not in the .vrma (gaze expressions are its lookAt, not expression tracks)", f.name,
                 ", ".join(gaze))
    return tracks


def vrma_bytes(source, curves, names, fps: float, *, lower=None, upper=None, times=None) -> bytes | None:
    """The bytes of :func:`write_vrma`, or None when no slider is a VRM expression of *source*."""
    f = GltfFile(source)
    C = _curves(curves, names, fps, lower, upper)
    tracks = _expression_tracks(f, C, list(names))
    if not tracks:
        return None
    nodes, bones, roots = _skeleton(f)
    doc = {"asset": {"version": "2.0", "generator": f"retarget {__version__}"}, "scene": 0, "nodes": nodes,
           "extensionsUsed": ["VRMC_vrm_animation"]}
    out = _Appender(doc, b"")
    times = out.floats(_times(times, len(C), fps)[:, None], "SCALAR", bounds=True)
    expressions: dict[str, dict] = {}
    channels, samplers = [], []
    for section, expr, w in tracks:
        nodes.append({"name": f"{section}/{expr}", "translation": [0.0, 0.0, 0.0]})
        roots.append(len(nodes) - 1)
        expressions.setdefault(section, {})[expr] = {"node": len(nodes) - 1}
        xyz = np.zeros((len(w), 3))
        xyz[:, 0] = w
        samplers.append({"input": times, "interpolation": "LINEAR", "output": out.floats(xyz, "VEC3")})
        channels.append({"sampler": len(samplers) - 1, "target": {"node": len(nodes) - 1, "path": "translation"}})
    doc["scenes"] = [{"nodes": roots}]
    doc["animations"] = [{"name": ANIMATION_NAME, "channels": channels, "samplers": samplers}]
    doc["extensions"] = {"VRMC_vrm_animation": {
        "specVersion": "1.0", "humanoid": {"humanBones": {b: {"node": j} for b, j in bones.items()}},
        "expressions": expressions}}
    doc["buffers"] = [{"byteLength": len(out.data)}]
    return _glb(f, doc, bytes(out.data), sort_keys=True)


def write_vrma(path: str | os.PathLike, source, curves, names, fps: float, *, lower=None, upper=None,
               times=None) -> Path | None:
    """Write the VRM Animation of the sliders that are VRM expressions of *source* (atomically), or nothing.

    Parameters
    ----------
    path : path-like
        The ``.vrma`` to write.
    source : path-like
        The VRM 0.x or 1.0 character (``.vrm``).
    curves : ndarray, shape (T, E)
    names : sequence of str
        The E slider names; those that name a VRM expression of *source* (as
        :func:`~retarget_cli.io.rig.gltf.read_gltf_rig` names its sliders) get a track.
    fps : float
    lower, upper : array_like, shape (E,), optional
        Each slider's range; curves are clipped to it, then to [0, 1].

    Returns
    -------
    Path or None
        *path*, or None (nothing written) when no slider is a VRM expression of *source*.
    """
    data = vrma_bytes(source, curves, names, fps, lower=lower, upper=upper, times=times)
    if data is None:
        log.info("%s: no slider is a VRM expression of the file; no .vrma written", Path(source).name)
        return None
    write_bytes(path, data)
    return Path(path)


def is_vrm(source) -> bool:
    """Whether *source* (opened through the checked reader) has VRM 0.x or 1.0 metadata."""
    ext = GltfFile(source).json.get("extensions")
    return isinstance(ext, dict) and (isinstance(ext.get("VRM"), dict) or isinstance(ext.get("VRMC_vrm"), dict))


__all__ = ["ANIMATION_NAME", "animated_copy_bytes", "check_fps", "clipped_curves", "copy_groups", "is_vrm", "morph_nodes", "target_weights",
           "vrm_expressions", "vrma_bytes", "write_animated_copy", "write_vrma"]
