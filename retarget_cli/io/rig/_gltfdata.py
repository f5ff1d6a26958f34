"""The bytes of a glTF 2.0 file for the rig reader: container, buffers, buffer views and accessors.

Follows the glTF 2.0 specification (Khronos, 2021): the GLB container (§4.4),
buffers and buffer views (§3.6), accessors with strides, normalization and
sparse storage (§3.6.2, §3.11); the geometry extensions
``KHR_mesh_quantization`` (integer attributes, dequantized by the accessor's
normalization), ``EXT_meshopt_compression`` (buffer views, decoded by the
``meshoptimizer`` wrapper of Kapoulkine's library) and
``KHR_draco_mesh_compression`` (primitives, decoded by ``DracoPy``).

A rig file from the internet is untrusted input. Every JSON value is read
through a checked getter, and every declared count, offset and length is
checked against the bytes actually present *before* anything is allocated or
decompressed: an accessor must fit in its buffer view, a buffer view in its
buffer, a buffer in the GLB BIN chunk or in its file; a meshopt stream must
be large enough for the size it claims (the codecs' best ratios: 64:1 for
attribute streams version 0, 1024:1 for version 1, one byte per triangle,
one byte per index). External buffers are files beside the rig only (no
``..``, no absolute path, no URL; ``data:`` URIs are decoded). Anything
wrong is one :class:`~retarget_cli.errors.InputError` line naming the file
and the entry.
"""

from __future__ import annotations

import base64
import binascii
import json
import logging
import math
import struct
from pathlib import Path
from urllib.parse import unquote

import numpy as np

from ...errors import InputError, MissingExtraError

log = logging.getLogger(__name__)

#: Largest element count of one accessor or meshopt stream (bounds every allocation).
MAX_ELEMENTS = 1 << 24

#: glTF componentType -> little-endian numpy dtype.
COMPONENTS = {5120: np.dtype("<i1"), 5121: np.dtype("<u1"), 5122: np.dtype("<i2"), 5123: np.dtype("<u2"),
              5125: np.dtype("<u4"), 5126: np.dtype("<f4")}
#: glTF accessor type -> number of components (MAT2/MAT3 with padded columns are not read).
TYPES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
#: Divisor of a normalized integer component (glTF 2.0 §3.11, KHR_mesh_quantization).
_NORM = {5120: 127.0, 5121: 255.0, 5122: 32767.0, 5123: 65535.0}

_GLB_MAGIC, _JSON_CHUNK, _BIN_CHUNK = b"glTF", 0x4E4F534A, 0x004E4942
_MESHOPT = "EXT_meshopt_compression"
_DRACO = "KHR_draco_mesh_compression"
#: Required extensions this reader decodes.
GEOMETRY_EXTENSIONS = ("KHR_mesh_quantization", _MESHOPT, _DRACO)
#: Required extensions that do not change geometry (materials, textures, lights, avatar metadata).
_IRRELEVANT_PREFIXES = ("KHR_materials_", "KHR_texture_", "EXT_texture_", "MSFT_texture_", "KHR_lights_",
                        "EXT_lights_", "KHR_xmp", "VRMC_", "KHR_animation_pointer")
_IRRELEVANT = {"VRM", "KHR_texture_basisu", "EXT_texture_webp", "EXT_texture_avif"}
_MESHOPT_RATIO = {0xA0: 64, 0xA1: 1024}
_MESHOPT_MODES = ("ATTRIBUTES", "TRIANGLES", "INDICES")
_MESHOPT_FILTERS = ("NONE", "OCTAHEDRAL", "QUATERNION", "EXPONENTIAL")
_REQUIRED = object()
_KIND_TEXT = {int: "an integer", float: "a number", str: "a string", list: "a list", dict: "an object",
              bool: "true or false"}


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


class GltfFile:
    """A parsed glTF/GLB/VRM file: its JSON and lazily loaded, checked binary data.

    Parameters
    ----------
    path : str or Path
        A ``.glb``/``.vrm`` (GLB container, recognised by its magic bytes) or
        a ``.gltf`` JSON file.

    Raises
    ------
    InputError
        Unreadable file, malformed container or JSON, or a required extension
        this reader does not support.
    """

    def __init__(self, path):
        self.path = Path(path)
        self.name = self.path.name
        try:
            data = self.path.read_bytes()
        except FileNotFoundError:
            raise InputError(f"{self.path}: rig file not found") from None
        except OSError as exc:
            raise InputError(f"{self.path}: cannot read rig file ({exc.strerror})") from exc
        self.bin = None
        if data[:4] == _GLB_MAGIC:
            text, self.bin = self._glb_chunks(data)
        else:
            text = data
        self.json = self._parse_json(text)
        self._buffers: dict[int, memoryview] = {}
        self._views: dict[int, memoryview] = {}
        self._check_required()

    # ------------------------------------------------------------------ container
    def error(self, message: str) -> InputError:
        """An :class:`InputError` ``"<file>: <message>"`` (one line)."""
        return InputError(f"{self.name}: {message}")

    def _glb_chunks(self, data: bytes):
        if len(data) < 12:
            raise self.error(f"GLB header is {len(data)} bytes, expected 12")
        _, version, length = struct.unpack_from("<4sII", data, 0)
        if version != 2:
            raise self.error(f"GLB version {version}, this reader reads glTF 2.0 (version 2)")
        if length > len(data):
            raise self.error(f"truncated: the GLB header declares {length} bytes, the file has {len(data)}")
        pos, chunks = 12, []
        while pos + 8 <= length:
            size, kind = struct.unpack_from("<II", data, pos)
            if pos + 8 + size > length:
                raise self.error(f"truncated: GLB chunk {len(chunks)} at byte {pos} declares {size} bytes, "
                                 f"only {length - pos - 8} remain")
            chunks.append((kind, memoryview(data)[pos + 8:pos + 8 + size]))
            pos += 8 + size
        if not chunks or chunks[0][0] != _JSON_CHUNK:
            raise self.error("GLB has no JSON chunk first")
        binary = chunks[1][1] if len(chunks) > 1 and chunks[1][0] == _BIN_CHUNK else None
        return bytes(chunks[0][1]), binary

    def _parse_json(self, text: bytes) -> dict:
        try:
            doc = json.loads(bytes(text).decode("utf-8"))
        except UnicodeDecodeError as exc:
            raise self.error(f"the JSON is not UTF-8 (byte {exc.start})") from None
        except json.JSONDecodeError as exc:
            raise self.error(f"malformed JSON: {exc.msg} at line {exc.lineno} column {exc.colno}") from None
        except RecursionError:
            raise self.error("malformed JSON: nested too deeply") from None
        if not isinstance(doc, dict):
            raise self.error("the JSON is not an object")
        asset = doc.get("asset")
        version = asset.get("version") if isinstance(asset, dict) else None
        if not isinstance(version, str) or not version.startswith("2."):
            raise self.error(f"asset.version is {_short(version)}, this reader reads glTF 2.0")
        return doc

    def _check_required(self):
        required = self.field(self.json, "extensionsRequired", "the file", list, [])
        for name in required:
            if not isinstance(name, str):
                raise self.error(f"extensionsRequired holds {_short(name)}, expected extension names")
            if name in GEOMETRY_EXTENSIONS or name in _IRRELEVANT or name.startswith(_IRRELEVANT_PREFIXES):
                continue
            raise self.error(f"requires the glTF extension {name}, which this reader does not decode "
                             f"(geometry extensions read: {', '.join(GEOMETRY_EXTENSIONS)})")

    # ------------------------------------------------------------------ checked JSON
    def field(self, obj: dict, key: str, where: str, kind=int, default=_REQUIRED, low=None):
        """``obj[key]`` checked to be of *kind* (int, float, str, list, dict, bool) and ``>= low``."""
        if key not in obj:
            if default is _REQUIRED:
                raise self.error(f"{where}: '{key}' is missing")
            return default
        value = obj[key]
        if kind is float:
            ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
        elif kind is int:
            ok = isinstance(value, int) and not isinstance(value, bool)
        else:
            ok = isinstance(value, kind)
        if not ok:
            raise self.error(f"{where}: '{key}' must be {_KIND_TEXT[kind]}, got {_short(value)}")
        if low is not None and value < low:
            raise self.error(f"{where}: '{key}' must be >= {low}, got {value}")
        return value

    def items(self, key: str) -> list:
        """The top-level array *key* (``[]`` when absent)."""
        return self.field(self.json, key, "the file", list, [])

    def item(self, key: str, index, where: str) -> dict:
        """Entry *index* of the top-level array *key*, range-checked; *where* says who refers to it."""
        array = self.items(key)
        if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index < len(array):
            raise self.error(f"{where} refers to {key[:-1]} {_short(index)}, the file has {len(array)}")
        entry = array[index]
        if not isinstance(entry, dict):
            raise self.error(f"{key[:-1]} {index} is not an object")
        return entry

    def numbers(self, obj: dict, key: str, where: str, size: int, default=None) -> np.ndarray | None:
        """A list of *size* finite numbers as float64, or *default* when absent."""
        value = self.field(obj, key, where, list, None)
        if value is None:
            return default
        if len(value) != size or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value):
            raise self.error(f"{where}: '{key}' must be {size} numbers, got {_short(value)}")
        out = np.asarray(value, dtype=np.float64)
        if not np.isfinite(out).all():
            raise self.error(f"{where}: '{key}' has a value that is not finite")
        return out

    # ------------------------------------------------------------------ buffers
    def buffer(self, index, where: str) -> memoryview:
        """The bytes of buffer *index* (exactly its ``byteLength``), loaded once."""
        if isinstance(index, int) and index in self._buffers:
            return self._buffers[index]
        buf = self.item("buffers", index, where)
        name = f"buffer {index}"
        length = self.field(buf, "byteLength", name, int, low=1)
        uri = self.field(buf, "uri", name, str, None)
        if uri is None:
            data = self._bin_buffer(buf, index, length)
        elif uri.startswith("data:"):
            data = self._data_uri(uri, name)
        else:
            data = self._external(uri, name, length)
        if len(data) < length:
            raise self.error(f"truncated: {name} declares {length} bytes, its data has {len(data)}")
        self._buffers[index] = memoryview(data)[:length]
        return self._buffers[index]

    def _bin_buffer(self, buf: dict, index: int, length: int):
        ext = self.field(buf, "extensions", f"buffer {index}", dict, {})
        if isinstance(ext.get(_MESHOPT), dict) and ext[_MESHOPT].get("fallback"):
            raise self.error(f"buffer {index} is the {_MESHOPT} fallback (no data) but a bufferView reads it "
                             "without the extension")
        if index != 0 or self.bin is None:
            raise self.error(f"buffer {index} has no uri and the file has no GLB BIN chunk for it")
        return self.bin

    def _data_uri(self, uri: str, where: str) -> bytes:
        head, sep, payload = uri.partition(",")
        if not sep or not head.endswith(";base64"):
            raise self.error(f"{where}: only base64 data: URIs are read, got {_short(uri)}")
        try:
            return base64.b64decode(payload, validate=True)
        except (binascii.Error, ValueError):
            raise self.error(f"{where}: the data: URI is not valid base64") from None

    def _external_path(self, uri: str, where: str) -> tuple[str, Path]:
        """The relative name and resolved path of an external buffer; refused outside the rig's folder."""
        rel = unquote(uri)
        first = rel.split("/", 1)[0]
        if (":" in first or rel.startswith(("/", "\\")) or "\\" in rel or "\0" in rel
                or ".." in rel.split("/") or not rel.strip("/")):
            raise self.error(f"{where}: uri {_short(uri)} is not a relative path inside the rig's folder "
                             "(no '..', no absolute path, no URL)")
        base = self.path.parent.resolve()
        target = (base / rel).resolve()
        if not target.is_relative_to(base):
            raise self.error(f"{where}: uri {_short(uri)} resolves outside the rig's folder")
        return rel, target

    def external_files(self) -> list[Path]:
        """The external buffer files the rig reads (checked like :meth:`buffer` checks them; nothing read)."""
        out = []
        for index in range(len(self.items("buffers"))):
            buf = self.item("buffers", index, "the file")
            uri = self.field(buf, "uri", f"buffer {index}", str, None)
            if uri is not None and not uri.startswith("data:"):
                out.append(self._external_path(uri, f"buffer {index}")[1])
        return list(dict.fromkeys(out))

    def _external(self, uri: str, where: str, length: int) -> bytes:
        rel, target = self._external_path(uri, where)
        if target.exists() and not target.is_file():  # a FIFO or device would block or never end
            raise self.error(f"{where}: external buffer {rel} is not a regular file")
        try:
            with open(target, "rb") as fh:
                return fh.read(length)
        except FileNotFoundError:
            raise self.error(f"{where}: external buffer {rel} not found beside the rig") from None
        except OSError as exc:
            raise self.error(f"{where}: cannot read external buffer {rel} ({exc.strerror})") from None

    def resource(self, uri: str, where: str, limit: int) -> bytes:
        """The bytes of a ``uri`` (an image's, a buffer's): a base64 ``data:`` URI or a file inside the rig's folder.

        Checked as buffers are (no ``..``, no absolute path, no URL, regular files only); more than *limit*
        bytes is an error.
        """
        data = self._data_uri(uri, where) if uri.startswith("data:") else self._external(uri, where, limit + 1)
        if len(data) > limit:
            raise self.error(f"{where}: uri {_short(uri)} holds more than {limit} bytes")
        return data

    # ------------------------------------------------------------------ buffer views
    def view(self, index, where: str) -> memoryview:
        """The bytes of bufferView *index* (decompressed when it has ``EXT_meshopt_compression``)."""
        if isinstance(index, int) and index in self._views:
            return self._views[index]
        bv = self.item("bufferViews", index, where)
        name = f"bufferView {index}"
        length = self.field(bv, "byteLength", name, int, low=1)
        ext = self.field(bv, "extensions", name, dict, {})
        compressed = isinstance(ext.get(_MESHOPT), dict)
        if compressed and _meshopt() is not None:
            data = self._meshopt_view(index, bv, ext[_MESHOPT], length)
        else:
            offset = self.field(bv, "byteOffset", name, int, 0, low=0)
            buf_index = self.field(bv, "buffer", name, int, low=0)
            if compressed and self._placeholder(buf_index, name):
                require_meshopt(self)
            buf = self.buffer(buf_index, name)
            if offset + length > len(buf):
                raise self.error(f"{name} (bytes {offset}..{offset + length}) runs past the end of buffer "
                                 f"{buf_index} ({len(buf)} bytes)")
            data = buf[offset:offset + length]
        self._views[index] = data
        return data

    def _placeholder(self, index, where: str) -> bool:
        """Whether buffer *index* has no data of its own (a meshopt fallback without uri)."""
        buf = self.item("buffers", index, where)
        ext = self.field(buf, "extensions", f"buffer {index}", dict, {})
        fallback = isinstance(ext.get(_MESHOPT), dict) and ext[_MESHOPT].get("fallback") is True
        return "uri" not in buf and (fallback or index != 0 or self.bin is None)

    def view_stride(self, index) -> int | None:
        """The declared ``byteStride`` of bufferView *index* (None when absent); the index was checked by view()."""
        bv = self.item("bufferViews", index, "an accessor")
        return self.field(bv, "byteStride", f"bufferView {index}", int, None, low=1)

    def _meshopt_args(self, index: int, ext: dict, length: int):
        where = f"bufferView {index} ({_MESHOPT})"
        count = self.field(ext, "count", where, int, low=1)
        stride = self.field(ext, "byteStride", where, int, low=1)
        mode = self.field(ext, "mode", where, str)
        filt = self.field(ext, "filter", where, str, "NONE")
        if mode not in _MESHOPT_MODES:
            raise self.error(f"{where}: mode {_short(mode)}, expected one of {', '.join(_MESHOPT_MODES)}")
        if filt not in _MESHOPT_FILTERS:
            raise self.error(f"{where}: filter {_short(filt)}, expected one of {', '.join(_MESHOPT_FILTERS)}")
        bad = None
        if mode == "ATTRIBUTES" and (stride % 4 or stride > 256):
            bad = "ATTRIBUTES needs a byteStride divisible by 4 and at most 256"
        elif mode != "ATTRIBUTES" and (stride not in (2, 4) or filt != "NONE"):
            bad = f"{mode} needs a byteStride of 2 or 4 and no filter"
        elif mode == "TRIANGLES" and count % 3:
            bad = "TRIANGLES needs a count divisible by 3"
        elif (filt == "OCTAHEDRAL" and stride not in (4, 8)) or (filt == "QUATERNION" and stride != 8):
            bad = f"filter {filt} does not allow byteStride {stride}"
        if bad:
            raise self.error(f"{where}: {bad} (byteStride {stride}, count {count})")
        if count * stride != length:
            raise self.error(f"{where}: {count} elements of {stride} bytes do not make the bufferView's "
                             f"byteLength {length}")
        if count > MAX_ELEMENTS:
            raise self.error(f"{where}: {count} elements, more than this reader's limit of {MAX_ELEMENTS}")
        return where, count, stride, mode, filt

    def _meshopt_view(self, index: int, bv: dict, ext: dict, length: int) -> memoryview:
        where, count, stride, mode, filt = self._meshopt_args(index, ext, length)
        declared = self.field(bv, "byteStride", f"bufferView {index}", int, None)
        if declared is not None and declared != stride:
            raise self.error(f"{where}: byteStride {stride}, the bufferView says {declared}")
        src_index = self.field(ext, "buffer", where, int, low=0)
        offset = self.field(ext, "byteOffset", where, int, 0, low=0)
        size = self.field(ext, "byteLength", where, int, low=1)
        buf = self.buffer(src_index, where)
        if offset + size > len(buf):
            raise self.error(f"{where}: compressed bytes {offset}..{offset + size} run past the end of buffer "
                             f"{src_index} ({len(buf)} bytes)")
        src = bytes(buf[offset:offset + size])
        _meshopt_fits(self, where, src, count, stride, mode)
        return memoryview(_meshopt_decode(self, where, src, count, stride, mode, filt))

    # ------------------------------------------------------------------ accessors
    def accessor(self, index, what: str, *, types=("VEC3",)) -> tuple[np.ndarray, int, bool]:
        """The elements of accessor *index*, in their stored component type.

        Parameters
        ----------
        index : int
        what : str
            What refers to the accessor, for messages (``"POSITION of mesh 'Head' target 3"``).
        types : tuple of str
            Accepted accessor types.

        Returns
        -------
        values : ndarray, shape (count, components), the accessor's component dtype
        component_type : int
        normalized : bool
        """
        acc = self.item("accessors", index, what)
        where = f"accessor {index} ({what})"
        count = self.field(acc, "count", where, int, low=1)
        ctype = self.field(acc, "componentType", where, int)
        atype = self.field(acc, "type", where, str)
        normalized = self.field(acc, "normalized", where, bool, False)
        if ctype not in COMPONENTS:
            raise self.error(f"{where}: componentType {ctype} is not a glTF component type")
        if atype not in types:
            raise self.error(f"{where}: type {_short(atype)}, expected {' or '.join(types)}")
        if count > MAX_ELEMENTS:
            raise self.error(f"{where}: count {count} is more than this reader's limit of {MAX_ELEMENTS}")
        dtype, ncomp = COMPONENTS[ctype], TYPES[atype]
        if "bufferView" in acc:
            bv = self.field(acc, "bufferView", where, int, low=0)
            offset = self.field(acc, "byteOffset", where, int, 0, low=0)
            values = self._strided(where, bv, offset, count, dtype, ncomp)
        else:
            values = np.zeros((count, ncomp), dtype=dtype)
        if "sparse" in acc:
            self._apply_sparse(where, self.field(acc, "sparse", where, dict), values)
        return values, ctype, normalized

    def _strided(self, where: str, bv: int, offset: int, count: int, dtype, ncomp: int) -> np.ndarray:
        data = self.view(bv, where)
        elem = dtype.itemsize * ncomp
        stride = self.view_stride(bv) or elem
        if stride < elem:
            raise self.error(f"{where}: bufferView {bv} has byteStride {stride}, smaller than an element "
                             f"({elem} bytes)")
        if offset + stride * (count - 1) + elem > len(data):
            raise self.error(f"{where}: {count} elements of {stride} bytes from byte {offset} run past the end of "
                             f"bufferView {bv} ({len(data)} bytes)")
        arr = np.ndarray((count, ncomp), dtype=dtype, buffer=data, offset=offset, strides=(stride, dtype.itemsize))
        return arr.copy()

    def _apply_sparse(self, where: str, sparse: dict, values: np.ndarray):
        count = self.field(sparse, "count", f"{where} sparse", int, low=1)
        if count > len(values):
            raise self.error(f"{where}: sparse count {count} is more than the accessor's {len(values)} elements")
        idx_obj = self.field(sparse, "indices", f"{where} sparse", dict)
        val_obj = self.field(sparse, "values", f"{where} sparse", dict)
        ictype = self.field(idx_obj, "componentType", f"{where} sparse indices", int)
        if ictype not in (5121, 5123, 5125):
            raise self.error(f"{where}: sparse indices componentType {ictype}, expected 5121, 5123 or 5125")
        indices = self._packed(f"{where} sparse indices", idx_obj, count, COMPONENTS[ictype], 1)[:, 0]
        update = self._packed(f"{where} sparse values", val_obj, count, values.dtype, values.shape[1])
        if int(indices.max()) >= len(values):
            raise self.error(f"{where}: sparse index {int(indices.max())} is out of range for "
                             f"{len(values)} elements")
        values[indices.astype(np.int64)] = update

    def _packed(self, where: str, obj: dict, count: int, dtype, ncomp: int) -> np.ndarray:
        bv = self.field(obj, "bufferView", where, int, low=0)
        offset = self.field(obj, "byteOffset", where, int, 0, low=0)
        data = self.view(bv, where)
        elem = dtype.itemsize * ncomp
        if offset + elem * count > len(data):
            raise self.error(f"{where}: {count} elements of {elem} bytes from byte {offset} run past the end of "
                             f"bufferView {bv} ({len(data)} bytes)")
        return np.ndarray((count, ncomp), dtype=dtype, buffer=data, offset=offset).copy()

    def floats(self, index, what: str, *, types=("VEC3",)) -> np.ndarray:
        """Accessor *index* as float64, integers dequantized (glTF 2.0 §3.11; KHR_mesh_quantization).

        Normalized ``int8``/``int16`` become ``max(c / 127, -1)`` / ``max(c / 32767, -1)``, normalized
        ``uint8``/``uint16`` ``c / 255`` / ``c / 65535``; integers that are not normalized keep their value.

        Returns
        -------
        ndarray, shape (count, components), float64
        """
        values, ctype, normalized = self.accessor(index, what, types=types)
        out = values.astype(np.float64)
        if normalized:
            if ctype not in _NORM:
                raise self.error(f"accessor {index} ({what}): componentType {ctype} cannot be normalized")
            out = np.maximum(out / _NORM[ctype], -1.0)
        bad = ~np.isfinite(out)
        if bad.any():
            raise self.error(f"accessor {index} ({what}): {int(bad.any(axis=1).sum())} elements are not finite")
        return out

    def integers(self, index, what: str, *, types=("SCALAR",)) -> np.ndarray:
        """Accessor *index* of unsigned integers (indices, joints) as int64, shape (count, components)."""
        values, ctype, _ = self.accessor(index, what, types=types)
        if ctype not in (5121, 5123, 5125):
            raise self.error(f"accessor {index} ({what}): componentType {ctype}, expected an unsigned integer "
                             "type (5121, 5123, 5125)")
        return values.astype(np.int64)

    def accessor_count(self, index, what: str) -> int:
        """The declared ``count`` of accessor *index* (checked, nothing read)."""
        acc = self.item("accessors", index, what)
        count = self.field(acc, "count", f"accessor {index} ({what})", int, low=1)
        if count > MAX_ELEMENTS:
            raise self.error(f"accessor {index} ({what}): count {count} is more than this reader's limit of "
                             f"{MAX_ELEMENTS}")
        return count

    # ------------------------------------------------------------------ Draco
    def draco(self, ext: dict, vertex_count: int, what: str) -> tuple[np.ndarray, np.ndarray]:
        """Decode a ``KHR_draco_mesh_compression`` primitive.

        Parameters
        ----------
        ext : dict
            The primitive's extension object (``bufferView``, ``attributes``).
        vertex_count : int
            The POSITION accessor's declared count, which the decoded mesh must match.
        what : str
            The primitive, for messages.

        Returns
        -------
        positions : ndarray, shape (N, 3), float64
        triangles : ndarray, shape (F, 3), int64
        """
        where = f"{what} ({_DRACO})"
        bv = self.field(ext, "bufferView", where, int, low=0)
        attrs = self.field(ext, "attributes", where, dict)
        uid = self.field(attrs, "POSITION", f"{where} attributes", int, low=0)
        data = bytes(self.view(bv, where))
        mesh = _draco_decode(self, where, data)
        attr = mesh.get_attribute_by_unique_id(uid)
        faces = getattr(mesh, "faces", None)
        if attr is None or faces is None or not len(faces):
            raise self.error(f"{where}: the Draco data has no triangles or no attribute {uid} for POSITION")
        pos = np.asarray(attr["data"], dtype=np.float64).reshape(len(attr["data"]), -1)
        if pos.shape != (vertex_count, 3):
            raise self.error(f"{where}: Draco decoded {pos.shape[0]} positions of {pos.shape[1]} components, "
                             f"the POSITION accessor declares {vertex_count} VEC3")
        if not np.isfinite(pos).all():
            raise self.error(f"{where}: Draco positions that are not finite")
        return pos, np.asarray(faces, dtype=np.int64).reshape(-1, 3)


# ---------------------------------------------------------------------- decoders
def _meshopt():
    """The ``meshoptimizer`` module, or None when it is not installed."""
    try:
        import meshoptimizer
    except ImportError:
        return None
    return meshoptimizer


def require_meshopt(f: GltfFile):
    """``meshoptimizer``, or a one-line :class:`MissingExtraError` naming the extension and the extra."""
    mod = _meshopt()
    if mod is None:
        raise MissingExtraError(f"{f.name}: {_MESHOPT} needs the meshoptimizer package, the optional extra "
                                "'rigs': pip install 'retarget[rigs]'")
    return mod


def draco_available() -> bool:
    """Whether ``DracoPy`` imports."""
    try:
        import DracoPy  # noqa: F401
    except ImportError:
        return False
    return True


def _draco_decode(f: GltfFile, where: str, data: bytes):
    try:
        import DracoPy
    except ImportError:
        raise MissingExtraError(f"{f.name}: {_DRACO} needs the DracoPy package, the optional extra 'rigs': "
                                "pip install 'retarget[rigs]'") from None
    try:
        return DracoPy.decode(data)
    except Exception as exc:  # DracoPy raises ValueError, RuntimeError or its own FileTypeException
        raise f.error(f"{where}: the Draco data does not decode ({type(exc).__name__})") from None


def _meshopt_fits(f: GltfFile, where: str, src: bytes, count: int, stride: int, mode: str):
    """Refuse, before decoding, a stream too short for what it claims (the codecs' best ratios)."""
    head = src[0]
    if mode == "ATTRIBUTES":
        ratio = _MESHOPT_RATIO.get(head)
        if ratio is None:
            raise f.error(f"{where}: attribute stream header 0x{head:02x}, expected 0xa0 or 0xa1")
        if count * stride > ratio * len(src):
            raise f.error(f"{where}: {len(src)} compressed bytes cannot hold {count} elements of {stride} bytes "
                          f"(the attribute codec compresses at most {ratio}:1)")
    elif mode == "TRIANGLES":
        if head not in (0xE0, 0xE1):
            raise f.error(f"{where}: triangle stream header 0x{head:02x}, expected 0xe1")
        if count // 3 > len(src):
            raise f.error(f"{where}: {len(src)} compressed bytes cannot hold {count // 3} triangles "
                          "(at least one byte each)")
    else:
        if head != 0xD1:
            raise f.error(f"{where}: index stream header 0x{head:02x}, expected 0xd1")
        if count > len(src):
            raise f.error(f"{where}: {len(src)} compressed bytes cannot hold {count} indices (at least one byte each)")


def _meshopt_decode(f: GltfFile, where: str, src: bytes, count: int, stride: int, mode: str, filt: str) -> bytes:
    """Decode one meshopt stream to ``count * stride`` bytes (Kapoulkine, EXT_meshopt_compression, App. A/B).

    The wrapper's ``decode_vertex_buffer`` is called with its default dtype (its
    ``dtype=`` argument sizes the output by element count, not bytes, and
    overflows it) and the float32 result reinterpreted as bytes; the index
    decoders return uint32 arrays whose first ``count * stride`` bytes are the
    2- or 4-byte indices.
    """
    mo = require_meshopt(f)
    try:
        if mode == "ATTRIBUTES":
            out = np.ascontiguousarray(mo.decode_vertex_buffer(count, stride, src)).view(np.uint8).reshape(-1)
            if filt == "OCTAHEDRAL":
                out = mo.decode_filter_oct(out, count, stride)
            elif filt == "QUATERNION":
                out = mo.decode_filter_quat(out, count, stride)
            elif filt == "EXPONENTIAL":
                out = mo.decode_filter_exp(out, count, stride)
        elif mode == "TRIANGLES":
            out = mo.decode_index_buffer(count, stride, src).view(np.uint8)
        else:
            out = mo.decode_index_sequence(count, stride, src).view(np.uint8)
    except (RuntimeError, ValueError) as exc:
        raise f.error(f"{where}: the {mode} stream of {len(src)} bytes does not decode to {count} elements of "
                      f"{stride} bytes ({exc})") from None
    out = np.asarray(out, dtype=np.uint8).reshape(-1)[:count * stride]
    if out.size != count * stride:
        raise f.error(f"{where}: decoded {out.size} bytes, expected {count * stride}")
    return out.tobytes()
