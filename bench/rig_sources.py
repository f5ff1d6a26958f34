"""Benchmark: characters with morph targets loaded as rigs (``load_rig`` on a .glb/.vrm/.usd/.fbx, issue 29).

Not a timed test: it prints what each rig becomes (meshes, vertices, targets, sliders) and how long
``load_rig`` takes, in one run:

- **cold**: no cache (``read_rig`` on the file's outline, the reader decoding it, the sliders summed,
  the template and the :class:`~retarget_cli.methods.rig.BlendshapeRig` built; for USD and FBX the outline is
  the one read, kept for the load);
- **cached**: a second load from ``rig-<key>.npz`` (sha256 of the file, the cached arrays, the template and
  the rig built again);
- peers in the same run: the reader alone (``read_character``: the decoding that the cache saves), and for the
  ICT FaceKit the same rig loaded from its 58 OBJs, cold and cached.

The rigs: ``../shared/realdata/rigs`` (the VALID avatar, meshopt-compressed, and the Godette VRM 0.x avatar;
a skip line without them) and the ICT FaceKit (sample_data/ict) written in a temporary folder as a GLB by the
writer of ``apply --format glb``, as USD by the writer of ``apply --format usd``, and as FBX by Assimp's FBX
exporter from a one-mesh GLB (with the ``fbx`` extra; a skip line without it); for USD and FBX the largest
difference of ``evaluate`` from the OBJ rig at random weights is printed (FBX vertices matched by position:
the reader welds Assimp's face corners and orders vertices by first use). Each figure is the best of ``--repeat``
runs.

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
from scipy.spatial import cKDTree

from retarget_cli.errors import MissingExtraError
from retarget_cli.io.exports import rig_shapes, write_usd
from retarget_cli.io.gltf import write_glb
from retarget_cli.io.objsurface import obj_surface
from retarget_cli.io.rig import fbx, load_rig
from retarget_cli.io.rig.readers import read_character

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
    g = read_character(path)
    meshes = ", ".join(f"{m} {b - a}" for m, a, b in g.mesh_ranges)
    print(f"{name}: {g.kind}, meshes {meshes}; {rig.n_vertices} vertices, {len(g.target_names)} targets, "
          f"{rig.n_sliders} sliders ({'VRM expressions' if g.kind.startswith('vrm') else 'targets merged by name'}), "
          f"D density {rig.density:.3f}")
    cache = tmp / f"cache-{path.stem}"
    reader = best(lambda: read_character(path), repeat)
    cold = best(lambda: load_rig(path), repeat)
    load_rig(path, cache_dir=cache)
    cached = best(lambda: load_rig(path, cache_dir=cache), repeat)
    size = sum(f.stat().st_size for f in cache.glob("rig-*.npz"))
    print(f"  load_rig cold {cold:.3f} s (the reader alone {reader:.3f} s), cached {cached:.3f} s "
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
    write_usd(d / "ict.usd", objs.template, objs.neutral, None, 1, 30.0, morph_targets=lambda: (shapes, names, W))
    measure("ICT FaceKit as USD (apply's usd writer)", d / "ict.usd", tmp, repeat)
    compare(objs, load_rig(d / "ict.usd"))
    if ict_fbx(d, objs, shapes, names, W):
        measure("ICT FaceKit as FBX (Assimp's FBX exporter)", d / "ict.fbx", tmp, repeat)
        compare(objs, load_rig(d / "ict.fbx"))


def ict_fbx(d: Path, objs, shapes, names, W) -> bool:
    """Write the ICT as FBX with Assimp's exporter from a one-mesh GLB; False (and a skip line) without the extra."""
    try:
        impasse = fbx._impasse(d / "ict.fbx")
    except MissingExtraError as exc:
        print(f"skip ICT FaceKit as FBX: {exc}")
        return False
    tris = [[f[0], f[i], f[i + 1]] for f in objs.template.faces() for i in range(1, len(f) - 1)]
    write_glb(d / "one.glb", base=objs.neutral, faces=np.array(tris), targets=shapes, target_names=names, weights=W,
              fps=30.0)
    impasse.export(impasse.load(str(d / "one.glb"), processing=0), str(d / "ict.fbx"), "fbx", processing=0)
    return True


def compare(objs, rig) -> None:
    """Largest |evaluate| difference from the OBJ rig at 3 random weight vectors, both ways, each vertex against
    the vertices of the other rig at its rest position (within 1e-4 cm: the ICT has coincident vertices)."""
    a, b = cKDTree(objs.neutral), cKDTree(rig.neutral)
    near_obj = b.query_ball_tree(a, 1e-4)  # for each rig vertex, the OBJ vertices at its position
    near_rig = a.query_ball_tree(b, 1e-4)
    missing = sum(not n for n in near_obj) + sum(not n for n in near_rig)
    err = 0.0
    for w in np.random.default_rng(0).uniform(0, 1, (3, objs.n_sliders)):
        eo, er = objs.evaluate(w), rig.evaluate(w)
        err = max(err, max(np.linalg.norm(eo[n] - er[i], axis=1).min() for i, n in enumerate(near_obj) if n),
                  max(np.linalg.norm(er[n] - eo[j], axis=1).min() for j, n in enumerate(near_rig) if n))
    print(f"  vs the OBJ rig: same slider names {list(rig.names) == list(objs.names)}; {rig.n_vertices} vertices for "
          f"the OBJs' {objs.n_vertices}, {missing} without a counterpart at its position; evaluate() differs by "
          f"{err:.1e} cm at most (each vertex against the other rig's vertices at its position)")


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
