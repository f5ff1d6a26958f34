"""Benchmark: characters with morph targets loaded as rigs (``load_rig`` on a .glb/.vrm, issue 29).

Not a timed test: it prints what each rig becomes (meshes, vertices, targets, sliders) and how long
``load_rig`` takes, in one run:

- **cold**: no cache (``read_rig`` on the file's JSON, ``read_gltf_rig`` decoding it, the sliders summed,
  the template and the :class:`~retarget_cli.methods.rig.BlendshapeRig` built);
- **cached**: a second load from ``rig-<key>.npz`` (sha256 of the file, the cached arrays, the template and
  the rig built again);
- peers in the same run: ``read_gltf_rig`` alone (the decoding that the cache saves), and for the ICT FaceKit
  the same rig loaded from its 58 OBJs, cold and cached.

The rigs: ``../shared/realdata/rigs`` (the VALID avatar, meshopt-compressed, and the Godette VRM 0.x avatar;
a skip line without them) and the ICT FaceKit (sample_data/ict) written as a GLB by the writer of
``apply --format glb`` in a temporary folder. Each figure is the best of ``--repeat`` runs.

Run: ``python bench/rig_sources.py [--repeat 3]``.
"""

from __future__ import annotations

import argparse
import shutil
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np

from retarget_cli.io.exports import rig_shapes
from retarget_cli.io.gltf import write_glb
from retarget_cli.io.objsurface import obj_surface
from retarget_cli.io.rig import load_rig
from retarget_cli.io.rig.gltf import read_gltf_rig

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "realdata" / "rigs"
RIGS = {"VALID White_F_2_Busi.glb": REAL / "valid-glb" / "White_F_2_Busi.glb",
        "Godette_vrm_v4.vrm": REAL / "godette-vrm" / "Godette_vrm_v4.vrm"}


def best(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def measure(name: str, path: Path, tmp: Path, repeat: int) -> None:
    rig = load_rig(path)
    g = read_gltf_rig(path)
    meshes = ", ".join(f"{m} {b - a}" for m, a, b in g.mesh_ranges)
    print(f"{name}: {g.kind}, meshes {meshes}; {rig.n_vertices} vertices, {len(g.target_names)} targets, "
          f"{rig.n_sliders} sliders ({'VRM expressions' if g.kind != 'gltf' else 'targets merged by name'}), "
          f"D density {rig.density:.3f}")
    cache = tmp / f"cache-{path.stem}"
    reader = best(lambda: read_gltf_rig(path), repeat)
    cold = best(lambda: load_rig(path), repeat)
    load_rig(path, cache_dir=cache)
    cached = best(lambda: load_rig(path, cache_dir=cache), repeat)
    size = sum(f.stat().st_size for f in cache.glob("rig-*.npz"))
    print(f"  load_rig cold {cold:.3f} s (read_gltf_rig alone {reader:.3f} s), cached {cached:.3f} s "
          f"({cold / cached:.1f}x faster; cache file {size / 2**20:.1f} MiB)")


def ict_glb(tmp: Path, repeat: int) -> None:
    with tarfile.open(ROOT / "sample_data" / "ict" / "ict-facekit-rig.tar.xz") as tar:
        tar.extractall(tmp, filter="data")
    d = tmp / "ict-facekit"
    shutil.copy(ROOT / "sample_data" / "ict" / "rig.yaml", d / "rig.yaml")
    objs = load_rig(d / "rig.yaml")
    shapes, names, W = rig_shapes(objs, np.zeros((1, objs.n_sliders)))
    write_glb(d / "ict.glb", base=objs.neutral, faces=None, targets=shapes, target_names=names, weights=W, fps=30.0,
              surface=obj_surface(objs.template))
    cold = best(lambda: load_rig(d / "rig.yaml"), repeat)
    load_rig(d / "rig.yaml", cache_dir=tmp / "cache-ict-objs")
    cached = best(lambda: load_rig(d / "rig.yaml", cache_dir=tmp / "cache-ict-objs"), repeat)
    print(f"ICT FaceKit from its 58 OBJs: {objs.n_vertices} vertices, {objs.n_sliders} sliders; load_rig cold "
          f"{cold:.3f} s, cached {cached:.3f} s")
    measure("ICT FaceKit as a GLB (apply's glb writer)", d / "ict.glb", tmp, repeat)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as t:
        tmp = Path(t)
        ict_glb(tmp, args.repeat)
        for name, path in RIGS.items():
            if not path.is_file():
                print(f"skip {name}: {path} not found")
                continue
            measure(name, path, tmp, args.repeat)


if __name__ == "__main__":
    main()
