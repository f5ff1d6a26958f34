"""Wavefront OBJ reading and vertex-only rewriting.

A target character is read once into an :class:`ObjMesh`: the vertex
positions as an array plus the file's bytes split around the ``v`` lines.
Writing a new pose replaces only the three coordinates of each ``v`` line;
every other byte of the file (``vt``, ``vn``, faces, groups, materials,
comments, line endings, extra ``v`` columns such as colours) is kept exactly.
Vertices are never reordered or merged.
"""

from __future__ import annotations

import hashlib
import io
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError, ShapeError
from .atomic import write_bytes

#: printf format of one coordinate in written ``v`` lines.
COORD_FORMAT = "%.6f"


#: An OBJ of a frame sequence (``apply`` and ``edit`` write ``frame_%05d.obj``, by source frame number).
FRAME_RE = re.compile(r"frame_(\d+)\.obj$")


def obj_frame_name(frame: int) -> str:
    """The file name of source frame *frame* in a frame sequence: ``frame_00100.obj`` (at least 5 digits)."""
    return f"frame_{int(frame):05d}.obj"


@dataclass
class ObjMesh:
    """An OBJ file as vertex positions plus everything else, byte for byte.

    Attributes
    ----------
    path : Path
        File it was read from.
    vertices : ndarray, shape (N, 3), float64
        ``v`` line positions in file order.
    segments : list of bytes
        ``len(segments) == len(runs) + 1``; the text before, between and
        after runs of consecutive ``v`` lines.
    runs : list of (start, stop)
        Vertex index ranges of each run of consecutive ``v`` lines.
    tails : list of bytes
        Per vertex, what follows the three coordinates (extra columns and the
        line ending). Shared by reference when all are equal.
    topology : str
        sha256 of the face, line, point and group lines: equal for meshes with
        the same connectivity.
    """

    path: Path
    vertices: np.ndarray
    segments: list = field(repr=False)
    runs: list = field(repr=False)
    tails: list = field(repr=False)
    topology: str = ""
    n_faces: int = 0
    _tails_cache: object = field(default=None, repr=False, compare=False)

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    def faces(self) -> list[list[int]]:
        """Face vertex indices (0-based, negative indices resolved), n-gons kept.

        Returns
        -------
        list of list of int
            One list of vertex ids per ``f`` line, in file order.
        """
        faces = []
        n_seen = 0
        # Walk segments and runs in order so relative (negative) indices resolve
        # against the number of vertices defined so far, as the OBJ spec says.
        for i, seg in enumerate(self.segments):
            for line in seg.splitlines():
                tok = line.split(b"#", 1)[0].split()
                if tok and tok[0] == b"f":
                    ids = []
                    for t in tok[1:]:
                        v = int(t.split(b"/")[0])
                        ids.append(v - 1 if v > 0 else n_seen + v)
                    faces.append(ids)
            if i < len(self.runs):
                n_seen = self.runs[i][1]
        return faces

    def to_bytes(self, positions: np.ndarray) -> bytes:
        """The file's bytes with the vertex coordinates replaced by *positions*.

        Each ``v`` line becomes ``v X Y Z`` (``%.6f``) followed by whatever
        followed the third coordinate in the template (``w``, colours, a
        comment, the line ending), byte for byte.

        Parameters
        ----------
        positions : ndarray, shape (N, 3)
            New vertex positions, same order as :attr:`vertices`.
        """
        return b"".join(self.iter_bytes(positions))

    def iter_bytes(self, positions: np.ndarray) -> list:
        """:meth:`to_bytes` as a list of byte chunks (written without joining)."""
        positions = np.asarray(positions, dtype=np.float64)
        if positions.shape != self.vertices.shape:
            raise ShapeError(
                f"positions for {self.path.name}: expected shape {self.vertices.shape}, got {positions.shape}"
            )
        if not np.all(np.isfinite(positions)):
            bad = int(np.argwhere(~np.isfinite(positions))[0, 0])
            raise ShapeError(f"positions for {self.path.name}: vertex {bad} is not finite")
        tails = self._tail_matrix()
        if tails is None or np.abs(positions).max(initial=0.0) >= _FAST_LIMIT:
            return self._iter_bytes_slow(positions)
        block, offsets = _format_v_lines(positions, tails)
        view = memoryview(block)
        out = [self.segments[0]]
        for i, (start, stop) in enumerate(self.runs):
            out.append(view[offsets[start]:offsets[stop]])
            out.append(self.segments[i + 1])
        return out

    def _iter_bytes_slow(self, positions: np.ndarray) -> list:
        """Reference implementation: one ``%``-format per run (or per line)."""
        out = [self.segments[0]]
        uniform = len(set(map(id, self.tails))) <= 1 if self.tails else True
        for i, (start, stop) in enumerate(self.runs):
            block = positions[start:stop]
            if uniform:
                tail = self.tails[start].decode("latin-1")
                fmt = ("v " + " ".join([COORD_FORMAT] * 3) + tail.replace("%", "%%")) * (stop - start)
                out.append((fmt % tuple(block.ravel())).encode("latin-1"))
            else:
                lines = [
                    (f"v {COORD_FORMAT} {COORD_FORMAT} {COORD_FORMAT}" % tuple(p)).encode() + t
                    for p, t in zip(block, self.tails[start:stop])
                ]
                out.append(b"".join(lines))
            out.append(self.segments[i + 1])
        return out

    def _tail_matrix(self):
        """Per-vertex tails as a zero-padded (N, L) uint8 matrix, or None when the
        fast writer cannot represent them (a NUL byte, or very long tails)."""
        if self._tails_cache is None:
            width = max(map(len, self.tails))
            if width > _MAX_TAIL or any(b"\0" in t for t in set(self.tails)):
                self._tails_cache = False
            else:
                mat = np.zeros((len(self.tails), width), np.uint8)
                uniq: dict[bytes, list[int]] = {}
                for i, t in enumerate(self.tails):
                    uniq.setdefault(t, []).append(i)
                for t, rows in uniq.items():
                    if t:
                        mat[np.asarray(rows), : len(t)] = np.frombuffer(t, np.uint8)
                self._tails_cache = mat
        return None if self._tails_cache is False else self._tails_cache


#: Coordinates at or above this magnitude go through the reference formatter.
_FAST_LIMIT = 1e9
#: Longest per-vertex tail (bytes after z) the vectorised writer handles.
_MAX_TAIL = 256
_ZERO, _MINUS, _DOT, _SPACE, _V = 48, 45, 46, 32, 118


def _format_v_lines(positions: np.ndarray, tails: np.ndarray) -> tuple[bytes, np.ndarray]:
    """``v`` lines for all vertices, exactly as ``"v %.6f %.6f %.6f" + tail``.

    Vectorised fixed-point formatting: each coordinate is rounded to an
    integer number of millionths, its digits are written into a byte matrix
    (one row per line, padding bytes 0) and the padding is squeezed out.
    Rounding matches C's ``%.6f`` (correctly rounded, ties to even): the
    float product ``|x| * 1e6`` decides the rounding unless it lies within a
    few ulps of a half-integer, and those few values are formatted with
    ``%.6f`` itself.

    Parameters
    ----------
    positions : ndarray, shape (N, 3), finite, ``|x| < 1e9``
    tails : ndarray, shape (N, L), uint8
        Bytes after the third coordinate, zero-padded.

    Returns
    -------
    block : bytes
        All lines concatenated.
    offsets : ndarray, shape (N + 1,)
        Byte offset of each line in *block* (last entry: ``len(block)``).
    """
    N = positions.shape[0]
    a = np.abs(positions)
    y = a * 1e6
    q = np.rint(y)
    frac = y - np.floor(y)
    ambiguous = np.abs(frac - 0.5) <= y * 1e-15
    q = q.astype(np.uint64)
    if ambiguous.any():
        for i, j in zip(*np.nonzero(ambiguous)):
            q[i, j] = int((COORD_FORMAT % a[i, j]).replace(".", ""))
    ip = q // np.uint64(1_000_000)
    fp = (q - ip * np.uint64(1_000_000)).astype(np.uint32)
    ip = ip.astype(np.uint32)
    n_int = len(str(int(ip.max(initial=0))))
    field = 1 + n_int + 1 + 6  # sign, integer digits, point, six decimals
    width = 1 + 3 * (1 + field) + tails.shape[1]
    mat = np.empty((N, width), np.uint8)
    mat[:, 0] = _V
    coords = mat[:, 1 : 1 + 3 * (1 + field)].reshape(N, 3, 1 + field)
    coords[:, :, 0] = _SPACE
    coords[:, :, 1] = np.where(np.signbit(positions), _MINUS, 0)
    ten = np.uint32(10)
    for k in range(1 + field - 1, 1 + field - 7, -1):
        nxt = fp // ten
        coords[:, :, k] = fp - nxt * ten + _ZERO
        fp = nxt
    coords[:, :, 2 + n_int] = _DOT
    rest = ip
    for k in range(1 + n_int, 1, -1):
        nxt = rest // ten
        coords[:, :, k] = rest - nxt * ten + _ZERO
        rest = nxt
    for j in range(n_int - 1):  # leading zeros of the integer part become padding
        col = coords[:, :, 2 + j]
        col[ip < 10 ** (n_int - 1 - j)] = 0
    if tails.shape[1]:
        mat[:, width - tails.shape[1]:] = tails
    keep = mat != 0
    offsets = np.zeros(N + 1, np.int64)
    np.cumsum(keep.sum(1), out=offsets[1:])
    return mat[keep].tobytes(), offsets


#: A ``v`` line: optional indentation, ``v``, then x y z (a ``#`` starts a comment).
_V_RE = re.compile(rb"[ \t]*v[ \t]+([^ \t#]+)[ \t]+([^ \t#]+)[ \t]+([^ \t#]+)")
#: Element lines whose vertex, texture and normal indices are checked.
_ELEMENTS = (b"f", b"l", b"p")


def _is_v_line(line: bytes) -> bool:
    s = line.lstrip(b" \t")
    return s[:1] == b"v" and s[1:2] in (b" ", b"\t")


def _check_refs(path, lineno, line, head, counts, max_pos) -> None:
    """Check the indices of an ``f``/``l``/``p`` line: negative ones against the
    elements defined so far, positive ones (recorded in *max_pos*) later
    against the whole file."""
    body = line.split(b"#", 1)[0].split()[1:]
    if not body:
        raise InputError(f"{path}:{lineno}: '{head.decode()}' line has no vertex indices")
    for tok in body:
        parts = tok.split(b"/")
        if len(parts) > 3 or not parts[0]:
            raise InputError(f"{path}:{lineno}: bad vertex reference {tok.decode(errors='replace')!r}")
        for slot, part in enumerate(parts):
            if not part:
                continue
            try:
                idx = int(part)
            except ValueError:
                raise InputError(
                    f"{path}:{lineno}: vertex reference {tok.decode(errors='replace')!r} is not made of integers"
                ) from None
            kind = ("v", "vt", "vn")[slot]
            if idx == 0 or (idx < 0 and counts[kind] + idx < 0):
                raise InputError(
                    f"{path}:{lineno}: '{head.decode()}' refers to {kind} {idx} but only {counts[kind]} "
                    f"'{kind}' lines precede it (indices are 1-based; negative ones count back)"
                )
            if idx > max_pos[kind][0]:
                max_pos[kind] = (idx, lineno)


#: Bytes that :meth:`bytes.split` treats as whitespace (a head is followed by one of them).
_WS = np.zeros(256, bool)
_WS[[9, 10, 11, 12, 13, 32]] = True


#: Heads and slashes of element lines become separators for ``numpy.fromstring``.
_ELEM_SEP = bytes.maketrans(b"flp/", b"    ")


def _blocks(mask: np.ndarray) -> list[tuple[int, int]]:
    """Runs of consecutive True entries of a boolean array, as (start, stop) pairs."""
    edges = np.diff(np.concatenate(([0], mask.view(np.int8), [0])))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()))


_DIGITS = b"0123456789"
#: Token shapes of uniform element lines (the token with its digits removed) and the slots
#: (0 v, 1 vt, 2 vn) of a token's indices; " //" is "a/b/c", or "a//c" with two indices.
_UNIFORM_SLOTS = {b" ": (0,), b" /": (0, 1), b" //": (0, 1, 2)}


def _uniform_refs(eblock: bytes, skeleton: bytes, heads: np.ndarray):
    """Indices and slots of element lines that all share one token shape, or None.

    The fast path for meshes whose faces are all written alike (``a b c``,
    ``a/b c/d …``, ``a//b …`` or ``a/b/c …``, any number of tokens per line):
    LF line ends, single spaces, no signs, no comments. With the digits
    removed every line is then its head followed by the same token repeated,
    which two whole-block byte operations check, and every slot of every
    token holds an index exactly when the block holds ``tokens × slots``
    integers, so the slot of each index is its place in its token.

    Parameters
    ----------
    eblock : bytes
        The element lines, joined, already known to hold only a head, digits,
        ``/``, ``-`` and whitespace per line.
    skeleton : bytes
        *eblock* without its digits (``f / / /`` for the line ``f 1/2 3/4 5/6``).
    heads : ndarray of uint8, shape (n_lines,)
        First byte of each line (``f``, ``l`` or ``p``).

    Returns
    -------
    (value, slots) : ndarray of int64, tuple of int
        Every index in file order, and the slots of a token's indices (index
        ``i`` is in slot ``slots[i % len(slots)]``); or None when the lines
        are not uniform (the general path then decides).
    """
    if not eblock.endswith(b"\n") or b"-" in eblock or b"\t" in eblock or b"\r" in eblock:
        return None
    if b"f\n" in skeleton or b"l\n" in skeleton or b"p\n" in skeleton:
        return None  # a line without indices
    token = b" " + skeleton[2:skeleton.find(b"\n")].split(b" ", 1)[0]  # the first line's first token
    slots = _UNIFORM_SLOTS.get(token)
    if slots is None:
        return None
    rest = np.empty(2 * len(heads), np.uint8)
    rest[0::2], rest[1::2] = heads, 10
    if skeleton.replace(token, b"") != rest.tobytes():
        return None  # a token of another shape, or doubled or trailing spaces
    n_tokens = skeleton.count(b" ")
    # (an index too large for int64 saturates, and is then out of range like any other)
    value = np.fromstring(eblock.translate(_ELEM_SEP), dtype=np.int64, sep=" ")
    if value.size != n_tokens * len(slots):
        if not (token == b" //" and value.size == 2 * n_tokens and eblock.count(b"//") == n_tokens):
            return None  # an empty slot (other than every token's vt in "a//c")
        slots = (0, 2)
    if value.size == 0 or value.min() < 1:
        return None
    return value, slots


def _parse_fast(path: Path, data: bytes) -> ObjMesh | None:
    """Vectorised :func:`read_obj` for the common layout, or None to use :func:`_parse_lines`.

    Applies when every ``v`` line is exactly ``v x y z`` plus a line ending
    (single spaces, LF or CRLF), no line starts with whitespace, there is no
    lone CR, and element lines hold only integers, ``/``, ``-`` and
    whitespace. It builds the same :class:`ObjMesh` as :func:`_parse_lines`
    (coordinates converted by the same call, tails, segments, topology hash)
    and checks the same indices; on anything it cannot vouch for, including
    every error, it returns None so that the reference parser decides (and
    names the line).
    """
    lines = _line_table(data)
    if lines is None:
        return None
    buf, starts, ends, c0, is_v, is_vt, is_vn, is_el = lines
    fast_v = _fast_vertices(data, buf, starts, ends, is_v)
    if fast_v is None:
        return None
    vertices, runs_l, spans, n_cr = fast_v
    nv = len(vertices)
    tails = [b"\r\n" if n_cr else b"\n"] * nv
    runs, segments = _runs_and_segments(data, runs_l, spans)
    counts = {"v": nv, "vt": int(is_vt.sum()), "vn": int(is_vn.sum())}
    el = np.flatnonzero(is_el)
    topo = hashlib.sha256()
    if el.size:
        eblock = b"".join(data[int(starts[i]):int(ends[j - 1])] for i, j in _blocks(is_el))
        refs = _element_refs(eblock, c0, el, starts, ends)
        if refs is None or not _refs_in_range(refs, counts, (is_v, is_vt, is_vn), el):
            return None
        _hash_elements(topo, data, eblock, el, starts, ends, uniform=refs[1])
    n_faces = int(np.count_nonzero(c0[el] == 102))
    return ObjMesh(path, vertices, segments, runs, tails, topo.hexdigest(), n_faces)


def _line_table(data: bytes):
    """Line starts and ends of *data* and what each line is (``v``, ``vt``, ``vn``, element), or None.

    None when a line starts with whitespace, a lone CR ends a line, or there is no ``v`` line.
    """
    n = len(data)
    if n == 0:
        return None
    buf = np.frombuffer(data + b"\n\n\n", np.uint8)  # padding: look-ahead past the last line
    body = buf[:n]
    nl = np.flatnonzero(body == 10)
    if b"\r" in data and np.any(buf[np.flatnonzero(body == 13) + 1] != 10):
        return None  # a lone CR ends a line for bytes.splitlines
    starts = np.concatenate(([0], nl + 1))
    ends = np.concatenate((nl + 1, [n]))
    if starts[-1] == n:
        starts, ends = starts[:-1], ends[:-1]
    c0, c1, c2 = buf[starts], buf[starts + 1], buf[starts + 2]
    c1 = np.where(starts + 1 < ends, c1, 10)
    c2 = np.where(starts + 2 < ends, c2, 10)
    if np.any((c0 == 32) | (c0 == 9) | (c0 == 11) | (c0 == 12)):
        return None
    is_v = (c0 == 118) & ((c1 == 32) | (c1 == 9))
    if not is_v.any():
        return None
    is_vt = (c0 == 118) & (c1 == 116) & _WS[c2]
    is_vn = (c0 == 118) & (c1 == 110) & _WS[c2]
    is_el = ((c0 == 102) | (c0 == 108) | (c0 == 112)) & _WS[c1]
    return buf, starts, ends, c0, is_v, is_vt, is_vn, is_el


def _v_block(vblock: bytes, n: int) -> np.ndarray | None:
    """The (n, 3) float64 vertices of a block of whitelisted ``v x y z`` lines, or ``None`` when it is not exactly that."""
    try:
        vertices = np.loadtxt(io.BytesIO(vblock), dtype=np.float64, delimiter=" ", usecols=(1, 2, 3),
                              comments=None, ndmin=2)
    except ValueError:
        return None
    if vertices.shape != (n, 3) or not np.all(np.isfinite(vertices)):
        return None
    return vertices


def _fast_vertices(data: bytes, buf, starts, ends, is_v):
    """The ``v`` lines, each ``v x y z`` + LF or CRLF, converted as the reference parser does; or None.

    Returns the vertices (V, 3), the runs of consecutive ``v`` lines, their byte spans and the count of CRs.
    """
    nv = int(is_v.sum())
    runs_l = _blocks(is_v)
    spans = [(int(starts[a]), int(ends[b - 1])) for a, b in runs_l]
    if buf[spans[-1][1] - 1] != 10:
        return None  # the last v line has no line ending
    vblock = b"".join(data[a:b] for a, b in spans) if len(spans) > 1 else data[spans[0][0]:spans[0][1]]
    n_cr = vblock.count(b"\r")
    if (vblock.count(b" ") != 3 * nv or n_cr not in (0, nv)
            or any(c in vblock for c in (b"\t", b"#", b"\x0b", b"\x0c"))):
        return None
    # Every line is "v" + three single-space separated tokens; when the tokens
    # hold only decimal-number bytes and 'v' appears only as the heads,
    # numpy.loadtxt's C reader converts them (correctly rounded, as float() is)
    # in one pass. Anything it rejects goes to the reference parser.
    if vblock.count(b"v") != nv or vblock.translate(None, b"0123456789+-.eEv \r\n"):
        return None
    vertices = _v_block(vblock, nv)
    return None if vertices is None else (vertices, runs_l, spans, n_cr)


def _runs_and_segments(data: bytes, runs_l, spans):
    """The vertex runs (first, end) and the text segments between them, as :class:`ObjMesh` keeps them."""
    runs, segments, prev, cum = [], [], 0, 0
    for (a, b), (s, e) in zip(runs_l, spans):
        segments.append(data[prev:s])
        runs.append((cum, cum + b - a))
        cum += b - a
        prev = e
    segments.append(data[prev:])
    return runs, segments


def _element_refs(eblock: bytes, c0, el, starts, ends):
    """The indices of the element lines by slot (0 v, 1 vt, 2 vn), or None when they need the reference parser.

    Returns ``(by_slot, uniform, signs)``: *uniform* is whether every line shares one token shape (then no
    index has a sign); *signs* locates the indices for negative (relative) references otherwise.
    """
    skeleton = eblock.translate(None, _DIGITS)
    if len(skeleton.translate(None, b"/- \t\r\n")) != el.size:
        return None  # some byte other than the heads is not an index, '/', '-' or whitespace
    uniform = _uniform_refs(eblock, skeleton, c0[el])
    if uniform is not None:
        value, slots = uniform
        return {k: value[j::len(slots)] for j, k in enumerate(slots)}, True, None
    general = _general_refs(eblock, el, starts, ends)
    if general is None:
        return None
    value, kind, lstart, ps = general
    return {k: value[kind == k] for k in range(3)}, False, (kind, lstart, ps)


def _general_refs(eblock: bytes, el, starts, ends):
    """Indices of element lines of any token shape and the slot of each; or None."""
    lens = ends[el] - starts[el]
    lstart = np.cumsum(lens) - lens
    eb = np.frombuffer(eblock + b"   ", np.uint8).copy()
    eb[lstart] = 32  # heads become separators
    ws = eb < 45
    tok = ~ws
    tok[1:] &= ws[:-1]
    if not np.logical_or.reduceat(tok, lstart).all():
        return None  # an element line without indices
    part = (eb >= 48) | (eb == 45)
    pstart = part.copy()
    pstart[1:] &= ~part[:-1]
    pend = part.copy()
    pend[:-1] &= ~part[1:]
    ps, pe = np.flatnonzero(pstart), np.flatnonzero(pend)
    if ps.size == 0 or (pe - ps).max() > 14:
        return None
    if b"-" in eblock:
        mpos = np.flatnonzero(eb == 45)
        if not (pstart[mpos].all() and np.all(eb[mpos + 1] >= 48)):
            return None  # '-' not the sign of an index
    kind = _slots(eblock, eb, ws, ps, pe) if b"/" in eblock else np.zeros(ps.size, np.int64)
    if kind is None:
        return None
    value = np.fromstring(eblock.translate(_ELEM_SEP), dtype=np.int64, sep=" ")
    if value.size != ps.size or np.any(value == 0):
        return None
    return value, kind, lstart, ps


def _slots(eblock: bytes, eb, ws, ps, pe):
    """The slot (0 v, 1 vt, 2 vn) of each index in ``v/vt/vn`` tokens, or None for an empty or fourth slot."""
    if b"///" in eblock or b" /" in eblock or b"\t/" in eblock:
        return None  # an empty vertex slot, or more than v/vt/vn
    # slot of each index: its place among the token's indices, plus one after an empty vt ("v//vn")
    j = np.arange(ps.size)
    kind = j - np.maximum.accumulate(np.where(ws[ps - 1], j, 0))
    kind += (eb[ps - 1] == 47) & (eb[ps - 2] == 47)
    after = eb[pe + 1] == 47
    if kind.max() > 2 or np.any(after & (kind == 2)) or np.any(after & (kind == 1) & (eb[pe + 2] == 47)):
        return None  # a fourth slot
    return kind


def _refs_in_range(refs, counts: dict, masks, el) -> bool:
    """Whether every index names an existing v/vt/vn line (negative ones counted back from their line)."""
    by_slot, uniform, signs = refs
    for k, (name, mask) in enumerate(zip(("v", "vt", "vn"), masks)):
        vals = by_slot.get(k)
        if vals is None or vals.size == 0:
            continue
        if vals.max() > counts[name]:
            return False
        if uniform:
            continue  # (uniform lines have no signs)
        kind, lstart, ps = signs
        neg = vals < 0
        if neg.any():
            line = el[np.searchsorted(lstart, ps[kind == k][neg], side="right") - 1]
            if np.any(np.cumsum(mask)[line] + vals[neg] < 0):
                return False
    return True


def _hash_elements(topo, data: bytes, eblock: bytes, el, starts, ends, *, uniform: bool) -> None:
    """Add the element lines to the topology hash with whitespace normalised, as :func:`_parse_lines` does."""
    plain = uniform or (b"\t" not in eblock and b"\r" not in eblock)
    if plain and not uniform:
        ob = np.frombuffer(eblock + b"\n", np.uint8)
        sp = ob == 32
        plain = not np.any(sp[:-1] & (sp[1:] | (ob[1:] == 10)))  # no double or trailing space
    if plain:
        topo.update(eblock if eblock.endswith(b"\n") else eblock + b"\n")
    else:
        for i in el.tolist():
            topo.update(b" ".join(data[int(starts[i]):int(ends[i])].split()) + b"\n")


def count_vertices(path: str | os.PathLike) -> int:
    """Number of ``v`` lines of an OBJ file, without parsing it.

    The count equals ``read_obj(path).n_vertices`` for any file :func:`read_obj`
    accepts; it is meant for checking many meshes against each other before
    parsing any.

    Raises
    ------
    InputError
        If the file is missing or unreadable.
    """
    path = Path(path)
    data = _read_bytes(path)
    return count_vertices_bytes(data)


def count_vertices_bytes(data: bytes) -> int:
    """:func:`count_vertices` of an OBJ file's bytes."""
    buf = np.frombuffer(data + b"\n\n", np.uint8)
    starts = np.concatenate(([0], np.flatnonzero(buf[:len(data)] == 10) + 1))
    c0 = buf[starts]
    lone_cr = b"\r" in data and np.any(buf[np.flatnonzero(buf[:len(data)] == 13) + 1] != 10)
    if lone_cr or np.any((c0 == 32) | (c0 == 9)):
        return sum(map(_is_v_line, data.splitlines()))
    c1 = buf[starts + 1]
    return int(np.count_nonzero((c0 == 118) & ((c1 == 32) | (c1 == 9))))


def read_obj(path: str | os.PathLike) -> ObjMesh:
    """Read an OBJ file.

    Every line is kept (see :class:`ObjMesh`); ``v`` lines are parsed, and the
    vertex, texture and normal indices of ``f``, ``l`` and ``p`` lines are
    checked against the ``v``, ``vt`` and ``vn`` lines of the file.

    Parameters
    ----------
    path : path-like
        OBJ file: ``v`` with optional ``w`` or colours, ``vt``/``vn``/``vp``,
        faces ``v``, ``v/vt``, ``v//vn``, ``v/vt/vn`` with positive or
        negative (relative) indices, n-gons, lines, points, groups,
        materials, comments (also after data), LF or CRLF line endings, tabs,
        no final newline.

    Returns
    -------
    ObjMesh

    Raises
    ------
    InputError
        If the file is missing, has no vertices, a ``v`` line has fewer than
        three numbers, or an element refers to a vertex, texture coordinate or
        normal that does not exist (the line number is given).
    """
    path = Path(path)
    data = _read_bytes(path)
    mesh = _parse_fast(path, data)
    mesh = mesh if mesh is not None else _parse_lines(path, data)
    check_coordinates(path, mesh.vertices)
    return mesh


#: Largest vertex coordinate magnitude read from an OBJ: beyond it a coordinate is a broken file, not a model
#: (a 1e308 passes the finite check, then overflows float32 exports and squared distances).
MAX_COORDINATE = 1e12


def check_coordinates(path, vertices: np.ndarray) -> None:
    """Raise when a vertex coordinate's magnitude exceeds :data:`MAX_COORDINATE` (the file and vertex named)."""
    big = np.abs(vertices) > MAX_COORDINATE
    if big.any():
        i, k = (int(v) for v in np.argwhere(big)[0])
        raise InputError(f"{path}: vertex {i} ('v' line {i + 1}) has {'xyz'[k]} = {vertices[i, k]:g}, beyond "
                         f"±{MAX_COORDINATE:g}; expected coordinates of a model")


def _read_bytes(path: Path) -> bytes:
    """An OBJ file's bytes; a missing or unreadable file is a one-line :class:`InputError`."""
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"{path}: OBJ file not found") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read OBJ ({exc.strerror})") from exc


def read_vertices_like(path: str | os.PathLike, like: ObjMesh) -> np.ndarray:
    """Vertex positions of an OBJ file, parsing only its ``v`` lines when it is a pose of *like*.

    A pose written by :func:`write_obj` from *like* (a sequence of frames of
    one mesh) differs from it in the coordinates of its ``v`` lines only.
    When every other byte of the file is *like*'s (one run of ``v`` lines,
    the same text before and after it) and the run is *like*'s number of
    plain ``v x y z`` lines, the faces need no second look: only the
    coordinates are converted (by the same call as :func:`read_obj`, so the
    result is identical). Anything else is read by :func:`read_obj`.

    Parameters
    ----------
    path : path-like
    like : ObjMesh
        A mesh of the same sequence (e.g. its first frame).

    Returns
    -------
    ndarray, shape (M, 3)
        ``read_obj(path).vertices``; *M* differs from ``like.n_vertices``
        only when the file is not a pose of *like* (the caller checks).

    Raises
    ------
    InputError
        As :func:`read_obj`.
    """
    path = Path(path)
    data = _read_bytes(path)
    vertices = _vertices_like(data, like)
    if vertices is None:
        mesh = _parse_fast(path, data)
        vertices = (mesh if mesh is not None else _parse_lines(path, data)).vertices
    check_coordinates(path, vertices)
    return vertices


def _vertices_like(data: bytes, like: ObjMesh) -> np.ndarray | None:
    """The ``v`` block of *data* converted, if *data* is *like* with other coordinates; else None."""
    if len(like.runs) != 1 or like.runs[0] != (0, like.n_vertices):
        return None
    head, tail = like.segments
    n = like.n_vertices
    if len(data) <= len(head) + len(tail) or not data.startswith(head) or not data.endswith(tail):
        return None
    vblock = data[len(head):len(data) - len(tail)]
    if (vblock.count(b"\n") != n or not vblock.endswith(b"\n") or vblock.count(b" ") != 3 * n
            or vblock.count(b"v") != n or not vblock.startswith(b"v ") or vblock.count(b"\nv ") != n - 1
            or vblock.translate(None, b"0123456789+-.eEv \n")):
        return None  # every line "v" and three numbers (the byte whitelist of _parse_fast)
    return _v_block(vblock, n)


def _parse_lines(path: Path, data: bytes) -> ObjMesh:
    """Reference parser of :func:`read_obj`: one Python pass over the lines.

    Handles every file :func:`read_obj` accepts and raises its errors (with
    line numbers); :func:`_parse_fast` defers to it for anything unusual.
    """
    lines = data.splitlines(keepends=True)
    segments: list[bytes] = []
    runs: list[tuple[int, int]] = []
    tails: list[bytes] = []
    coords: list[bytes] = []
    topo = hashlib.sha256()
    n_faces = 0
    seg: list[bytes] = []
    run_start = None
    shared_tails: dict[bytes, bytes] = {}
    counts = {"v": 0, "vt": 0, "vn": 0}
    max_pos = {"v": (0, 0), "vt": (0, 0), "vn": (0, 0)}
    for lineno, line in enumerate(lines, 1):
        if _is_v_line(line):
            if run_start is None:
                segments.append(b"".join(seg))
                seg = []
                run_start = len(tails)
            body = line.rstrip(b"\r\n")
            m = _V_RE.match(body)
            if m is None:
                raise InputError(f"{path}:{lineno}: 'v' line needs x y z, got {body.decode(errors='replace')!r}")
            coords.extend(m.groups())
            # Keep whatever follows z (w, colours, a comment) plus the original line ending.
            tail = body[m.end():] + line[len(body):]
            tails.append(shared_tails.setdefault(tail, tail))
            counts["v"] += 1
            continue
        if run_start is not None:
            runs.append((run_start, len(tails)))
            run_start = None
        seg.append(line)
        head = line.split(None, 1)[0] if line.strip() else b""
        if head in _ELEMENTS:
            _check_refs(path, lineno, line, head, counts, max_pos)
            n_faces += head == b"f"
            topo.update(b" ".join(line.split()) + b"\n")
        elif head in (b"vt", b"vn"):
            counts[head.decode()] += 1
    if run_start is not None:
        runs.append((run_start, len(tails)))
    segments.append(b"".join(seg))
    if not tails:
        raise InputError(f"{path}: OBJ has no 'v' lines")
    for kind, (idx, lineno) in max_pos.items():
        if idx > counts[kind]:
            raise InputError(f"{path}:{lineno}: refers to {kind} {idx} but the file has {counts[kind]} '{kind}' lines")
    try:
        vertices = np.array(coords, dtype=np.float64).reshape(-1, 3)
    except ValueError as exc:
        raise InputError(f"{path}: a 'v' line has a coordinate that is not a number ({exc})") from exc
    if not np.all(np.isfinite(vertices)):
        bad = int(np.argwhere(~np.isfinite(vertices))[0, 0])
        raise InputError(f"{path}: vertex {bad} is not finite")
    return ObjMesh(path, vertices, segments, runs, tails, topo.hexdigest(), n_faces)


def write_obj(path: str | os.PathLike, mesh: ObjMesh, positions: np.ndarray) -> None:
    """Atomically write *mesh* with its vertices moved to *positions*.

    Parameters
    ----------
    path : path-like
        Destination file.
    mesh : ObjMesh
        Template; every non-coordinate byte is copied from it.
    positions : ndarray, shape (N, 3)
    """
    write_bytes(path, mesh.to_bytes(positions))


def check_same_topology(meshes: list[ObjMesh]) -> None:
    """Raise if the meshes differ in vertex count or connectivity.

    Raises
    ------
    InputError
        Naming the first mesh and the first one that differs from it.
    """
    ref = meshes[0]
    for m in meshes[1:]:
        if m.n_vertices != ref.n_vertices:
            raise InputError(
                f"{m.path}: has {m.n_vertices} vertices but {ref.path} has {ref.n_vertices}; "
                "key shapes must share one topology"
            )
        if m.topology != ref.topology:
            raise InputError(
                f"{m.path}: face lines differ from {ref.path}; key shapes must share one topology"
            )


def format_obj(vertices: np.ndarray, faces, *, uvs=None, face_uvs=None, header: str = "") -> bytes:
    """Build a new OBJ file from arrays (used for generated meshes).

    Parameters
    ----------
    vertices : ndarray, shape (N, 3)
    faces : ndarray, shape (F, n) of int
        0-based vertex ids per face (triangles, quads, ...).
    uvs : ndarray, shape (M, 2), optional
        Texture coordinates written as ``vt`` lines.
    face_uvs : ndarray, shape (F, n) of int, optional
        0-based ``vt`` ids per face corner; written as ``v/vt``.
    header : str
        Lines written first (comments, ``mtllib``, ``usemtl``), ending in ``\\n``.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64) + 1
    parts = [header]
    parts.append(("v " + " ".join([COORD_FORMAT] * 3) + "\n") * len(vertices) % tuple(vertices.ravel()))
    if uvs is not None:
        uvs = np.asarray(uvs, dtype=np.float64)
        parts.append(("vt %.6f %.6f\n" * len(uvs)) % tuple(uvs.ravel()))
    n = faces.shape[1]
    if face_uvs is not None:
        fu = np.asarray(face_uvs, dtype=np.int64) + 1
        inter = np.stack([faces, fu], axis=-1).reshape(len(faces), -1)
        fmt = "f " + " ".join(["%d/%d"] * n) + "\n"
        parts.append((fmt * len(faces)) % tuple(inter.ravel()))
    else:
        fmt = "f " + " ".join(["%d"] * n) + "\n"
        parts.append((fmt * len(faces)) % tuple(faces.ravel()))
    return "".join(parts).encode("ascii")


def obj_from_arrays(path: str | os.PathLike, vertices: np.ndarray, faces, *, objects=()) -> ObjMesh:
    """An :class:`ObjMesh` template for a mesh that has no OBJ file (a character read from a GLB).

    The text is ``o <name>`` before each object's vertices, ``v`` lines, then that object's faces; it is
    parsed as :func:`read_obj` parses a file (so a frame written from it reads back with the same
    topology), and :attr:`ObjMesh.vertices` are *vertices* themselves, not their printed values.

    Parameters
    ----------
    path : path-like
        What the template is named after (written meshes, the glb export's node name); not read.
    vertices : ndarray, shape (N, 3), float64
    faces : ndarray, shape (F, 3), int
        0-based triangles.
    objects : sequence of (str, int, int)
        ``(name, start, stop)`` vertex ranges in order, covering ``0..N`` (a face goes after the
        object of its last vertex); empty: one unnamed object.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    n = len(vertices)
    objects = list(objects) or [(None, 0, n)]
    if objects[0][1] != 0 or objects[-1][2] != n or any(a[2] != b[1] for a, b in zip(objects, objects[1:])):
        raise ShapeError(f"objects: expected vertex ranges covering 0..{n} in order, got "
                         f"{[(s, e) for _, s, e in objects]}")
    if faces.size and (faces.min() < 0 or faces.max() >= n):
        raise ShapeError(f"faces: vertex ids must lie in [0, {n})")
    owner = np.searchsorted([stop for _, _, stop in objects], faces.max(axis=1), side="right") if len(faces) else []
    order = np.argsort(owner, kind="stable")
    counts = np.bincount(np.asarray(owner, dtype=np.int64), minlength=len(objects))
    parts, f0 = [], 0
    for k, (name, start, stop) in enumerate(objects):
        if name is not None:
            clean = "".join(c if c.isprintable() else "_" for c in str(name)).strip() or f"object{k}"
            parts.append(f"o {clean}\n".encode())
        parts.append(b"v 0 0 0\n" * (stop - start))
        block = faces[order[f0:f0 + counts[k]]] + 1
        f0 += counts[k]
        parts.append((("f %d %d %d\n" * len(block)) % tuple(block.ravel())).encode("ascii"))
    data = b"".join(parts)
    mesh = _parse_fast(Path(path), data) or _parse_lines(Path(path), data)
    mesh.vertices = vertices.copy()
    return mesh
