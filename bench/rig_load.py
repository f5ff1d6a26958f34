"""Benchmark: loading a production rig, and writing its OBJ sequence.

The ICT FaceKit (sample_data/ict: 57 shapes + neutral, 26,719 vertices,
2.6 MB per OBJ) is unpacked to a temporary folder with its rig.yaml, then,
in one run:

1. **Rig load.** ``load_rig`` (``retarget_cli.io.rig``) cold (no cache: every OBJ parsed by
   :func:`retarget_cli.io.obj.read_obj`), cold with a cache (parse + write
   ``rig-<key>.npz``) and cached (sha256 of every file + the NPZ), and the
   sha256 of the files alone. Peers over the same 58 files: the line-by-line
   reader that ``read_obj`` used before (``_parse_lines``, same output),
   ``numpy.loadtxt`` on the ``v`` lines only, and trimesh's OBJ loader
   (``process=False``). A whole-process cached load (``python -c``, imports
   included) is timed too.
2. **Parse throughput** of one OBJ (MB/s of OBJ text) for the same readers.
3. **OBJ writing.** 300 frames of the rig (26,719 vertices with UVs and
   faces) written with :func:`retarget_cli.io.obj.write_obj` against a naive
   peer that formats each ``v`` line in Python, frames/s (the naive writer
   does fewer frames; the two must give identical bytes).

Timings share the machine with whatever else runs: each figure is the best of
``--repeat`` runs, and every ratio compares figures of this run.

Run: ``python bench/rig_load.py [--rig-dir DIR] [--frames 300] [--repeat 3]``.
"""

from __future__ import annotations

import argparse
import hashlib
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np

from retarget_cli.io.obj import _parse_lines, read_obj, write_obj
from retarget_cli.io.rig import load_rig, read_rig

SAMPLE = Path(__file__).resolve().parents[1] / "sample_data" / "ict"
RING = 8


def best(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def loadtxt_v(path: Path) -> np.ndarray:
    with open(path, "rb") as fh:
        return np.loadtxt((ln for ln in fh if ln.startswith(b"v ")), usecols=(1, 2, 3), dtype=np.float64)


def trimesh_load(path: Path):
    import trimesh

    return trimesh.load(path, process=False, force="mesh", skip_materials=True)


def naive_write(path: Path, lines: list[bytes], positions: np.ndarray) -> None:
    """The writing peer: walk the template line by line, formatting each vertex in Python."""
    out, i = [], 0
    for line in lines:
        if line.startswith(b"v "):
            x, y, z = positions[i]
            out.append(f"v {x:.6f} {y:.6f} {z:.6f}\n".encode())
            i += 1
        else:
            out.append(line)
    path.write_bytes(b"".join(out))


def unpack(dest: Path) -> Path:
    with tarfile.open(SAMPLE / "ict-facekit-rig.tar.xz") as tar:
        tar.extractall(dest, filter="data")
    rig_dir = dest / "ict-facekit"
    shutil.copy(SAMPLE / "rig.yaml", rig_dir / "rig.yaml")
    return rig_dir


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--rig-dir", type=Path, default=None, help="An unpacked ICT rig with rig.yaml (default: unpack "
                                                                "sample_data/ict to a temporary folder).")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--naive-frames", type=int, default=30)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    if args.rig_dir is None and not (SAMPLE / "ict-facekit-rig.tar.xz").is_file():
        print(f"skipped: {SAMPLE / 'ict-facekit-rig.tar.xz'} not found (the ICT rig is needed)")
        return
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        rig_dir = args.rig_dir or unpack(tmp)
        rig_yaml = rig_dir / "rig.yaml"
        spec = read_rig(rig_yaml)
        files = spec.files()
        mb = sum(f.stat().st_size for f in files) / 1e6
        R = args.repeat
        read_obj(files[0])  # warm the page cache and the imports

        # ------------------------------------------------------------ rig load
        t = {}
        t["cold (no cache)"] = best(lambda: load_rig(rig_yaml), R)
        caches = iter(range(R))
        t["cold + cache write"] = best(lambda: load_rig(rig_yaml, cache_dir=tmp / f"c{next(caches)}"), R)
        t["cached"] = best(lambda: load_rig(rig_yaml, cache_dir=tmp / "c0"), R)
        t["sha256 of the files"] = best(
            lambda: [hashlib.file_digest(open(f, "rb"), "sha256").hexdigest() for f in [rig_yaml, *files]], R)
        cmd = [sys.executable, "-c", "import sys; from retarget_cli.methods.rig import BlendshapeRig; "
               "load_rig(sys.argv[1], cache_dir=sys.argv[2])", str(rig_yaml), str(tmp / "c0")]
        t["cached, whole process"] = best(lambda: subprocess.run(cmd, check=True), R)
        peers = {
            "line reader (before)": lambda: [_parse_lines(f, f.read_bytes()) for f in files],
            "numpy.loadtxt v lines": lambda: [loadtxt_v(f) for f in files],
            "trimesh process=False": lambda: [trimesh_load(f) for f in files],
        }
        for name, fn in peers.items():
            t[name] = best(fn, 1 if "trimesh" in name or "loadtxt" in name else min(R, 2))
        cold, hit = load_rig(rig_yaml), load_rig(rig_yaml, cache_dir=tmp / "c0")
        dense = [r.D.toarray() if r.sparse else r.D for r in (cold, hit)]
        same = dense[0].tobytes() == dense[1].tobytes() and cold.f0.tobytes() == hit.f0.tobytes()
        print(f"ICT rig: {len(files)} OBJs, {cold.n_vertices} vertices, {cold.n_sliders} shapes, {mb:.1f} MB; "
              f"best of {R}")
        print(f"{'rig load':<26}{'s':>8}{'MB/s':>9}{'vs cold':>10}")
        for name, s in t.items():
            print(f"{name:<26}{s:>8.3f}{mb / s:>9.1f}{s / t['cold (no cache)']:>9.2f}x")
        print(f"cold load vs line reader: {t['line reader (before)'] / t['cold (no cache)']:.2f}x faster; "
              f"vs numpy.loadtxt: {t['numpy.loadtxt v lines'] / t['cold (no cache)']:.2f}x; "
              f"vs trimesh: {t['trimesh process=False'] / t['cold (no cache)']:.2f}x")
        print(f"cached load vs cold: {t['cold (no cache)'] / t['cached']:.1f}x faster; cache hit bit-identical: {same}")

        # ------------------------------------------------------------ one OBJ
        one = rig_dir / "jawOpen.obj"
        size = one.stat().st_size / 1e6
        readers = {"read_obj": lambda: read_obj(one), "line reader (before)": lambda: _parse_lines(one, one.read_bytes()),
                   "numpy.loadtxt v lines": lambda: loadtxt_v(one), "trimesh process=False": lambda: trimesh_load(one)}
        print(f"\n{'parse ' + one.name:<26}{'ms':>8}{'MB/s':>9}{'vs read_obj':>13}")
        rt = {name: best(fn, 5) for name, fn in readers.items()}
        for name, s in rt.items():
            print(f"{name:<26}{s * 1e3:>8.1f}{size / s:>9.1f}{s / rt['read_obj']:>12.2f}x")

        # ------------------------------------------------------------ writing
        T, Tn = args.frames, min(args.naive_frames, args.frames)
        rng = np.random.default_rng(0)
        W = rng.uniform(0, 1, (T, hit.n_sliders)) * (rng.uniform(size=(T, hit.n_sliders)) < 0.2)
        lines = (rig_dir / spec.neutral.name).read_bytes().splitlines(keepends=True)
        out = tmp / "frames"
        out.mkdir()
        ours = naive = 0.0
        for k in range(T):
            pos = hit.evaluate(W[k])  # not timed
            t0 = time.perf_counter()
            write_obj(out / f"a_{k % RING}.obj", hit.template, pos)
            ours += time.perf_counter() - t0
            if k < Tn:
                t0 = time.perf_counter()
                naive_write(out / f"b_{k % RING}.obj", lines, pos)
                naive += time.perf_counter() - t0
                if k == Tn - 1:
                    same_bytes = (out / f"a_{k % RING}.obj").read_bytes() == (out / f"b_{k % RING}.obj").read_bytes()
        fsize = (out / "a_0.obj").stat().st_size / 1e6
        print(f"\nwriting {hit.n_vertices}-vertex OBJs ({fsize:.2f} MB each): retarget write_obj {T} frames "
              f"{T / ours:.1f} frames/s ({fsize * T / ours:.0f} MB/s); naive per-line {Tn} frames {Tn / naive:.1f} "
              f"frames/s; ratio {(T / ours) / (Tn / naive):.2f}x; identical bytes: {same_bytes}")
        if not same:
            raise SystemExit("cached rig differs from the cold load")


if __name__ == "__main__":
    main()
