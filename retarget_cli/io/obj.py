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
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError, ShapeError
from .atomic import atomic_open

#: printf format of one coordinate in written ``v`` lines.
COORD_FORMAT = "%.6f"


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
                tok = line.split()
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

        Parameters
        ----------
        positions : ndarray, shape (N, 3)
            New vertex positions, same order as :attr:`vertices`.
        """
        positions = np.asarray(positions, dtype=np.float64)
        if positions.shape != self.vertices.shape:
            raise ShapeError(
                f"positions for {self.path.name}: expected shape {self.vertices.shape}, got {positions.shape}"
            )
        if not np.all(np.isfinite(positions)):
            bad = int(np.argwhere(~np.isfinite(positions))[0, 0])
            raise ShapeError(f"positions for {self.path.name}: vertex {bad} is not finite")
        out = [self.segments[0]]
        uniform = len(set(map(id, self.tails))) <= 1 if self.tails else True
        for i, (start, stop) in enumerate(self.runs):
            block = positions[start:stop]
            if uniform:
                tail = self.tails[start].decode("latin-1")
                fmt = ("v " + " ".join([COORD_FORMAT] * 3) + tail) * (stop - start)
                out.append((fmt % tuple(block.ravel())).encode("latin-1"))
            else:
                lines = [
                    (f"v {COORD_FORMAT} {COORD_FORMAT} {COORD_FORMAT}" % tuple(p)).encode() + t
                    for p, t in zip(block, self.tails[start:stop])
                ]
                out.append(b"".join(lines))
            out.append(self.segments[i + 1])
        return b"".join(out)


def _is_v_line(line: bytes) -> bool:
    return line.startswith((b"v ", b"v\t"))


def read_obj(path: str | os.PathLike) -> ObjMesh:
    """Read an OBJ file.

    Parameters
    ----------
    path : path-like
        OBJ file. Any valid OBJ is accepted; only ``v`` lines are interpreted.

    Returns
    -------
    ObjMesh

    Raises
    ------
    InputError
        If the file is missing, has no vertices, or a ``v`` line has fewer than
        three numbers (the line number is given).
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"{path}: OBJ file not found") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read OBJ ({exc.strerror})") from exc
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
    for lineno, line in enumerate(lines, 1):
        if _is_v_line(line):
            if run_start is None:
                segments.append(b"".join(seg))
                seg = []
                run_start = len(tails)
            body = line.rstrip(b"\r\n")
            ending = line[len(body):]
            tok = body.split()
            if len(tok) < 4:
                raise InputError(f"{path}:{lineno}: 'v' line needs x y z, got {body.decode(errors='replace')!r}")
            coords.extend(tok[1:4])
            # Keep whatever follows z (w, colours) plus the original line ending.
            rest = b" " + b" ".join(tok[4:]) if len(tok) > 4 else b""
            tail = rest + ending
            tails.append(shared_tails.setdefault(tail, tail))
        else:
            if run_start is not None:
                runs.append((run_start, len(tails)))
                run_start = None
            seg.append(line)
            head = line.split(None, 1)[0] if line.strip() else b""
            if head in (b"f", b"l", b"p"):
                n_faces += head == b"f"
                topo.update(b" ".join(line.split()) + b"\n")
    if run_start is not None:
        runs.append((run_start, len(tails)))
    segments.append(b"".join(seg))
    if not tails:
        raise InputError(f"{path}: OBJ has no 'v' lines")
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
    data = mesh.to_bytes(positions)
    with atomic_open(path, "wb") as fh:
        fh.write(data)


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
