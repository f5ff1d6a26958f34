"""Benchmark: writing a retargeted OBJ sequence.

Compares ``retarget``'s OBJ writer (template bytes around the ``v`` lines, one
vectorised format per frame) with a naive writer that formats every line in a
Python loop, on the same frames in the same run, and checks both produce the
same bytes. Run: ``python bench/apply.py [--vertices N] [--frames T]``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from retarget_cli.io.obj import format_obj, read_obj, write_obj


def grid_mesh(n_vertices: int):
    side = int(np.ceil(np.sqrt(n_vertices)))
    u, v = np.meshgrid(np.linspace(0, 1, side), np.linspace(0, 1, side))
    verts = np.stack([u.ravel(), v.ravel(), 0.1 * np.sin(6 * u.ravel()) * np.cos(5 * v.ravel())], 1)
    idx = np.arange(side * side).reshape(side, side)
    quads = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], -1).reshape(-1, 4)
    uvs = verts[:, :2]
    return verts, quads, uvs


def naive_write(path: Path, lines: list[bytes], positions: np.ndarray) -> None:
    """The peer: walk the template line by line, formatting each vertex in Python."""
    out = []
    i = 0
    for line in lines:
        if line.startswith(b"v "):
            x, y, z = positions[i]
            out.append(f"v {x:.6f} {y:.6f} {z:.6f}\n".encode())
            i += 1
        else:
            out.append(line)
    path.write_bytes(b"".join(out))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--vertices", type=int, default=25_000)
    ap.add_argument("--frames", type=int, default=100)
    args = ap.parse_args()
    verts, quads, uvs = grid_mesh(args.vertices)
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        src = tmp / "mesh.obj"
        src.write_bytes(format_obj(verts, quads, uvs=uvs, face_uvs=quads, header="mtllib m.mtl\nusemtl skin\n"))
        mesh = read_obj(src)
        lines = src.read_bytes().splitlines(keepends=True)
        frames = verts[None] + 0.01 * rng.standard_normal((args.frames, 1, 3))
        t0 = time.perf_counter()
        for t, p in enumerate(frames):
            write_obj(tmp / f"a_{t:05d}.obj", mesh, p)
        ours = time.perf_counter() - t0
        t0 = time.perf_counter()
        for t, p in enumerate(frames):
            naive_write(tmp / f"b_{t:05d}.obj", lines, p)
        naive = time.perf_counter() - t0
        same = all((tmp / f"a_{t:05d}.obj").read_bytes() == (tmp / f"b_{t:05d}.obj").read_bytes()
                   for t in range(args.frames))
        mb = sum((tmp / f"a_{t:05d}.obj").stat().st_size for t in range(args.frames)) / 1e6
    print(f"OBJ sequence: {mesh.n_vertices} vertices, {len(quads)} quads with UVs, {args.frames} frames, "
          f"{mb / args.frames:.2f} MB/frame; identical bytes: {same}")
    print(f"{'writer':<22}{'s/frame':>10}{'MB/s':>10}")
    print(f"{'retarget (template)':<22}{ours / args.frames:>10.4f}{mb / ours:>10.1f}")
    print(f"{'naive per-line':<22}{naive / args.frames:>10.4f}{mb / naive:>10.1f}")
    print(f"speed-up vs naive: {naive / ours:.2f}x")
    if not same:
        raise SystemExit("outputs differ")


if __name__ == "__main__":
    main()
