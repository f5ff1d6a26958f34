"""A slow pure-Python decoder of EXT_meshopt_compression streams, written from the extension's text (Appendix A).

Independent of the ``meshoptimizer`` wrapper the reader uses: the tests decode the real rig's streams with both.
Covers mode 0 (attributes, header 0xa0, no filter) and mode 1 (triangles, header 0xe1).
"""

from __future__ import annotations

import numpy as np


def _unzigzag8(v: int) -> int:
    return (~(v >> 1)) & 0xFF if v & 1 else v >> 1


def _group_deltas(src: bytes, pos: int, mode: int) -> tuple[list[int], int]:
    """The 16 zigzagged byte deltas of one group and the position after it."""
    if mode == 0:
        return [0] * 16, pos
    if mode == 3:
        return list(src[pos:pos + 16]), pos + 16
    bits = 2 if mode == 1 else 4
    packed = src[pos:pos + 2 * bits]
    pos += 2 * bits
    sentinel = (1 << bits) - 1
    out = []
    for byte in packed:
        for s in range(8 // bits):
            v = (byte >> (8 - bits * (s + 1))) & sentinel
            if v == sentinel:
                v, pos = src[pos], pos + 1
            out.append(v)
    return out, pos


def decode_attributes(src: bytes, count: int, stride: int, limit: int | None = None) -> bytes:
    """Mode 0, version 0: the first *limit* (default all) of *count* elements of *stride* bytes."""
    assert src[0] == 0xA0, hex(src[0])
    base = bytearray(src[len(src) - stride:])  # the tail's baseline element ends the stream
    out = bytearray(count * stride)
    pos, done = 1, 0
    per_block = min((8192 // stride) & ~15, 256)
    limit = count if limit is None else min(limit, count)
    while done < limit:
        n = min(count - done, per_block)
        groups = (n + 15) // 16
        for k in range(stride):
            header = src[pos:pos + (groups + 3) // 4]
            pos += (groups + 3) // 4
            deltas = []
            for g in range(groups):
                d, pos = _group_deltas(src, pos, (header[g // 4] >> (2 * (g % 4))) & 3)
                deltas += d
            value = base[k]
            for e in range(n):
                value = (value + _unzigzag8(deltas[e])) & 0xFF
                out[(done + e) * stride + k] = value
            base[k] = value
        done += n
    return bytes(out[:limit * stride])


class _Triangles:
    """Decoder state of mode 1: the edge and vertex FIFOs, ``next`` and ``last``."""

    def __init__(self, src: bytes, count: int):
        self.src, self.data = src, 1 + count // 3
        self.edges, self.verts = [(0, 0)] * 16, [0] * 16
        self.next = self.last = 0

    def varint(self) -> int:
        v = shift = 0
        while True:
            b = self.src[self.data]
            self.data += 1
            v |= (b & 0x7F) << shift
            shift += 7
            if not b & 0x80:
                return v

    def index(self) -> int:
        v = self.varint()
        self.last = (self.last + (~(v >> 1) if v & 1 else v >> 1)) & 0xFFFFFFFF
        return self.last

    def fresh(self) -> int:
        self.next += 1
        return self.next - 1

    def push_edge(self, a, b):
        self.edges = [(a, b)] + self.edges[:15]

    def push_vertex(self, a):
        self.verts = [a] + self.verts[:15]

    def edge_code(self, x: int, y: int):
        a, b = self.edges[x]
        if y == 0:
            c = self.fresh()
        elif y < 13:
            c = self.verts[y]
        elif y < 15:
            c = self.last - 1 if y == 13 else self.last + 1
            self.last = c
        else:
            c = self.index()
        if y == 0 or y >= 13:
            self.push_vertex(c)
        self.push_edge(c, b)
        self.push_edge(a, c)
        return a, b, c

    def free_code(self, y: int, codeaux: bytes):
        if y < 14:
            zw, explicit = codeaux[y], False
        else:
            zw, explicit = self.src[self.data], True
            self.data += 1
            if zw == 0:
                self.next = 0
        z, w = zw >> 4, zw & 15
        a = self.index() if explicit and y == 15 else self.fresh()
        b = self.fresh() if z == 0 else self.index() if explicit and z == 15 else self.verts[z - 1]
        c = self.fresh() if w == 0 else self.index() if explicit and w == 15 else self.verts[w - 1]
        self.push_edge(b, a)
        self.push_edge(c, b)
        self.push_edge(a, c)
        self.push_vertex(a)
        if z == 0 or (explicit and z == 15):
            self.push_vertex(b)
        if w == 0 or (explicit and w == 15):
            self.push_vertex(c)
        return a, b, c


def decode_triangles(src: bytes, count: int) -> np.ndarray:
    """Mode 1 (header 0xe1): *count* indices, int64."""
    assert src[0] == 0xE1, hex(src[0])
    state, codeaux, out = _Triangles(src, count), src[len(src) - 16:], []
    for code in src[1:1 + count // 3]:
        x, y = code >> 4, code & 15
        out += state.edge_code(x, y) if x < 15 else state.free_code(y, codeaux)
    return np.array(out, dtype=np.int64)
