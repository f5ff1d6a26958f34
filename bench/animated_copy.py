"""The animated copies (``apply --format same``) of the two real rigs of ``../shared/realdata/rigs``, read back
and rendered (issue 29, part 4; not timed).

For ``valid-glb/White_F_2_Busi.glb`` (meshopt + quantization) and ``godette-vrm/Godette_vrm_v4.vrm`` (VRM 0.x):
made-up curves (a jaw-open ramp up and down, a blink), the copy written by
:func:`retarget_cli.io.gltf_animation.write_animated_copy` (and the ``.vrma`` for the VRM), then read back by
``read_gltf_rig`` and by ``pygltflib`` (and tried with ``trimesh``): node and mesh counts, the source's JSON entries
and BIN bytes unchanged, the largest difference between the animation's morph weights (as pygltflib reads them)
and the curves times the bind weights, and the ``.vrma``'s expression tracks against the curves. ``--out DIR``
keeps the files and renders, with :mod:`retarget_cli.methods.render`, frames of the written copy posed at the
animation's own weights (``<stem>_frames.png``: frame 0, the jaw-open peak, the blink).

USD (with usd-core): the ICT FaceKit (``sample_data/ict``, unpacked to ``build/ict-facekit``) written as a UsdSkel
character by ``apply --format usd``'s writer, then its copy by ``apply --format same``'s
(:func:`retarget_cli.io.usd_animation.write_animated_usd`, the rig's 57 sliders): prims and meshes against the
source, the weights UsdSkel's own queries give each mesh at every frame against the curves, the copy read back
through ``read_usd_rig``, the wall time; with ``--out``, frames rendered from the copy's points after
``UsdSkel.BakeSkinning``. Without ``../shared/realdata`` it prints a skip line and exits 0. Nothing is written outside ``--out`` (default: a
temporary folder, removed).

Run: ``python bench/animated_copy.py [--out DIR]``.
"""

from __future__ import annotations

import argparse
import json
import struct
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
RIGS = ROOT.parent / "shared" / "realdata" / "rigs"
VALID = RIGS / "valid-glb" / "White_F_2_Busi.glb"
GODETTE = RIGS / "godette-vrm" / "Godette_vrm_v4.vrm"
T, FPS, JAW_PEAK, BLINK_PEAK = 48, 24.0, 20, 34


def made_up_curves(names: list[str], jaw: str, blink: list[str]) -> np.ndarray:
    """(T, E): *jaw* ramps 0 -> 1 by JAW_PEAK and back to 0 by frame 40; *blink* closes and opens around BLINK_PEAK."""
    C = np.zeros((T, len(names)))
    t = np.arange(T)
    C[:, names.index(jaw)] = np.clip(np.minimum(t / JAW_PEAK, (40 - t) / (40 - JAW_PEAK)), 0, 1)
    for b in blink:
        C[:, names.index(b)] = np.clip(1 - np.abs(t - BLINK_PEAK) / 3, 0, 1)
    return C


def glb_chunks(data: bytes) -> tuple[dict, bytes]:
    n = struct.unpack_from("<I", data, 12)[0]
    m = struct.unpack_from("<I", data, 20 + n)[0]
    return json.loads(data[20:20 + n]), data[28 + n:28 + n + m]


def pyg_floats(g, index: int) -> np.ndarray:
    a = g.accessors[index]
    bv = g.bufferViews[a.bufferView]
    n = {"SCALAR": 1, "VEC3": 3}[a.type]
    return np.frombuffer(g.binary_blob(), "<f4", a.count * n, (bv.byteOffset or 0) + (a.byteOffset or 0)).reshape(
        a.count, n)


def animation(path: Path) -> dict[int, np.ndarray]:
    """{node: (T, n) morph weights} of the copy's last animation, as pygltflib reads the file."""
    import pygltflib

    g = pygltflib.GLTF2().load_binary(str(path))
    anim = g.animations[-1]
    return {ch.target.node: pyg_floats(g, anim.samplers[ch.sampler].output).reshape(T, -1) for ch in anim.channels}


def check_copy(src: Path, out: Path, rig, groups: dict, names: list[str], C: np.ndarray) -> dict[int, np.ndarray]:
    import pygltflib

    from retarget_cli.io.rig.gltf import read_gltf_rig

    src_doc, src_bin = glb_chunks(src.read_bytes())
    doc, binary = glb_chunks(out.read_bytes())
    kept = all(doc[k][:len(v)] == v if isinstance(v, list) else doc[k] == v
               for k, v in src_doc.items() if k != "buffers") and doc["buffers"][1:] == src_doc["buffers"][1:]
    g = pygltflib.GLTF2().load_binary(str(out))
    print(f"- {out.name}: {out.stat().st_size} bytes (source {src.stat().st_size}); pygltflib: {len(g.nodes)} nodes, "
          f"{len(g.meshes)} meshes, {len(g.animations)} animation(s) (source: {len(src_doc['nodes'])}, "
          f"{len(src_doc['meshes'])}, {len(src_doc.get('animations', []))}); source JSON entries unchanged: {kept}; "
          f"source BIN bytes unchanged: {binary[:len(src_bin)] == src_bin}")
    W = animation(out)
    want = {node: np.zeros(w.shape) for node, w in W.items()}
    for e, name in enumerate(names):
        for node, k, w in groups.get(name, []):
            want[node][:, k] += np.clip(C[:, e], 0, 1) * w
    err = max(float(np.abs(W[n] - want[n]).max()) for n in W)
    back = read_gltf_rig(out)
    print(f"  morph weights vs curves x bind weights, every frame, {sum(w.size for w in W.values())} values: "
          f"max |diff| {err:.2e}; read_gltf_rig of the copy: deltas equal the source's: "
          f"{np.array_equal(back.deltas, rig.deltas)}, sliders equal: {back.groups == rig.groups}")
    for what, path in (("the copy", out), ("the source", src)):
        try:
            import trimesh

            scene = trimesh.load(path, force="scene", file_type="glb")
            print(f"  trimesh {trimesh.__version__} loads {what}: {len(scene.geometry)} geometries")
        except Exception as exc:  # report what trimesh says; it is not the reader under test
            print(f"  trimesh does not load {what}: {type(exc).__name__}: {str(exc)[:120]}")
    return W


def render(out: Path, png: Path, W: dict, keep, camera, labels) -> None:
    """Frames of the written copy posed at its animation's weights: neutral + sum_j w_j(t) * delta_j."""
    import cv2

    from retarget_cli.io.rig.gltf import read_gltf_rig
    from retarget_cli.methods.render import MeshRenderer

    every = read_gltf_rig(out, meshes=["*"])
    v = every.neutral
    faces = every.faces[keep(v)[every.faces].all(1)]
    used = np.unique(faces)
    remap = np.full(len(v), -1)
    remap[used] = np.arange(len(used))
    ren = MeshRenderer(remap[faces], v[used], camera=camera, size=(360, 360))
    imgs = []
    for frame, label in labels:
        pose = v.copy()
        for j, (node, k) in enumerate(every.target_refs):
            if node in W:
                pose += W[node][frame, k] * every.deltas[j]
        img = ren.render(pose[used])
        cv2.putText(img, f"frame {frame}: {label}", (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1)
        imgs.append(img)
    cv2.imwrite(str(png), np.hstack(imgs))
    print(f"  rendered from the written file: {png}")


def run_valid(folder: Path, png: bool) -> None:
    from retarget_cli.io.gltf_animation import copy_groups, write_animated_copy
    from retarget_cli.io.rig.gltf import read_gltf_rig
    from retarget_cli.methods.render import Camera

    rig = read_gltf_rig(VALID)
    names = ["MouthOpen_h", "LeyeClose_h", "ReyeClose_h"]
    C = made_up_curves(names, "MouthOpen_h", ["LeyeClose_h", "ReyeClose_h"])
    groups, _ = copy_groups(rig, names)
    out = write_animated_copy(folder / "White_F_2_Busi_animated.glb", VALID, C, names, FPS, groups)
    print(f"## {VALID.name}: sliders {', '.join(names)} ({sum(len(g) for g in groups.values())} targets on "
          f"{len({n for g in groups.values() for n, _, _ in g})} nodes)")
    W = check_copy(VALID, out, rig, groups, names, C)
    if png:
        render(out, folder / "White_F_2_Busi_frames.png", W,
               lambda v: (v[:, 1] > 1.45) & (np.abs(v[:, 0]) < 0.12), Camera(fov=20),
               [(0, "neutral"), (JAW_PEAK, "MouthOpen_h 1"), (BLINK_PEAK, "eyes closed")])


def run_godette(folder: Path, png: bool) -> None:
    import pygltflib

    from retarget_cli.io.gltf_animation import copy_groups, write_animated_copy, write_vrma
    from retarget_cli.io.rig.gltf import read_gltf_rig
    from retarget_cli.methods.render import Camera

    rig = read_gltf_rig(GODETTE)
    names = list(rig.groups)
    C = made_up_curves(names, "a", ["blink"])
    groups, _ = copy_groups(rig, names)
    out = write_animated_copy(folder / "Godette_vrm_v4_animated.glb", GODETTE, C, names, FPS, groups)
    print(f"\n## {GODETTE.name}: {len(names)} sliders ({', '.join(names)}); curves on a and blink")
    W = check_copy(GODETTE, out, rig, groups, names, C)
    vrma = write_vrma(folder / "Godette_vrm_v4_animated.vrma", GODETTE, C, names, FPS)
    g = pygltflib.GLTF2().load_binary(str(vrma))
    ext = g.extensions["VRMC_vrm_animation"]
    by_node = {e["node"]: name for table in ext["expressions"].values() for name, e in table.items()}
    v1 = {"a": "aa", "blink": "blink"}
    err = 0.0
    for ch in g.animations[0].channels:
        x = pyg_floats(g, g.animations[0].samplers[ch.sampler].output)[:, 0]
        src = next((s for s, e in v1.items() if e == by_node[ch.target.node]), None)
        if src is not None:
            err = max(err, float(np.abs(x - C[:, names.index(src)]).max()))
    print(f"- {vrma.name}: {vrma.stat().st_size} bytes; pygltflib: {len(g.nodes)} nodes, "
          f"{len(ext['humanoid']['humanBones'])} humanoid bones, expressions "
          f"{ {k: sorted(v) for k, v in ext['expressions'].items()} }; aa and blink tracks vs curves: max |diff| "
          f"{err:.2e}")
    if png:
        render(out, folder / "Godette_vrm_v4_frames.png", W, lambda v: v[:, 1] > 0.95, Camera(yaw=180, fov=20),
               [(0, "neutral"), (JAW_PEAK, "a 1"), (BLINK_PEAK, "blink 1")])


def run_ict_usd(folder: Path, png: bool) -> None:
    import subprocess
    import time

    import cv2
    from pxr import Usd, UsdGeom, UsdSkel

    from retarget_cli.io.exports import rig_shapes
    from retarget_cli.io.rig import load_rig
    from retarget_cli.io.rig.usd import read_usd_rig
    from retarget_cli.io.usd import write_usd_skel
    from retarget_cli.io.usd_animation import target_weights, write_animated_usd
    from retarget_cli.methods.render import Camera, MeshRenderer

    ict = ROOT / "build" / "ict-facekit" / "rig.yaml"
    if not ict.is_file():
        subprocess.run(["make", str(ict.relative_to(ROOT))], cwd=ROOT, check=True, capture_output=True)
    objs = load_rig(ict)
    shapes, names, W0 = rig_shapes(objs, np.zeros((1, objs.n_sliders)))
    faces = objs.template.faces()
    src = folder / "ict.usd"
    write_usd_skel(src, points=objs.neutral, counts=[len(f) for f in faces], corners=[i for f in faces for i in f],
                   shapes=shapes, names=names, weights=W0, fps=FPS)
    rig = load_rig(src)
    C = made_up_curves(list(rig.names), "jawOpen", ["eyeBlink_L", "eyeBlink_R"])
    t0 = time.perf_counter()
    W = target_weights(C, rig.names, rig.spec.sliders, rig.spec.outline.target_names, lower=rig.lower,
                       upper=rig.upper)
    out = write_animated_usd(folder / "ict_animated.usd", src, W, rig.spec.outline.target_names, FPS)
    secs = time.perf_counter() - t0
    a, b = Usd.Stage.Open(str(src)), Usd.Stage.Open(str(out))
    prims = lambda st: {str(p.GetPath()) for p in st.Traverse()}  # noqa: E731
    meshes = lambda st: sum(p.IsA(UsdGeom.Mesh) for p in st.Traverse())  # noqa: E731
    print(f"\n## the ICT FaceKit as USD ({len(rig.names)} sliders, {rig.n_vertices} vertices): {out.name}, "
          f"{out.stat().st_size} bytes (source {src.stat().st_size}), written in {secs:.1f} s")
    print(f"- prims: source {len(prims(a))}, copy {len(prims(b))}, the same: {prims(a) == prims(b)}; meshes "
          f"{meshes(a)} / {meshes(b)}; timeCodesPerSecond {b.GetTimeCodesPerSecond():g}, time codes "
          f"{b.GetStartTimeCode():g}-{b.GetEndTimeCode():g}")
    cache = UsdSkel.Cache()
    root = UsdSkel.Root(b.GetDefaultPrim())
    cache.Populate(root, Usd.PrimDefaultPredicate)
    (binding,) = cache.ComputeSkelBindings(root, Usd.PrimDefaultPredicate)
    anim = cache.GetSkelQuery(binding.GetSkeleton()).GetAnimQuery()
    (target,) = binding.GetSkinningTargets()
    order = [str(n) for n in target.GetBlendShapeOrder()]
    got = np.array([list(target.GetBlendShapeMapper().Remap(anim.ComputeBlendShapeWeights(Usd.TimeCode(t))))
                    for t in range(T)])
    want = np.clip(C, rig.lower, rig.upper)[:, [list(rig.names).index(n) for n in order]]
    back, first = read_usd_rig(out), read_usd_rig(src)
    print(f"- UsdSkel's weights of the mesh vs the curves, {got.size} values: max |diff| "
          f"{np.abs(got - want).max():.2e}; read_usd_rig of the copy: neutral and deltas equal the source's: "
          f"{np.array_equal(back.neutral, first.neutral) and np.array_equal(back.deltas, first.deltas)}")
    if png:
        assert UsdSkel.BakeSkinning(b.Traverse())
        mesh = UsdGeom.Mesh(b.GetPrimAtPath(str(target.GetPrim().GetPath())))
        face = np.flatnonzero(objs.neutral[:, 1] > objs.neutral[:, 1].min() + 0.35 * np.ptp(objs.neutral[:, 1]))
        tris = first.faces
        ren = MeshRenderer(tris[np.isin(tris, face).all(1)], rig.neutral, camera=Camera(fov=20), size=(360, 360),
                           frame=rig.neutral[face])
        imgs = []
        for frame, label in [(0, "neutral"), (JAW_PEAK, "jawOpen 1"), (BLINK_PEAK, "eyes closed")]:
            pts = np.asarray(mesh.GetPointsAttr().Get(Usd.TimeCode(frame)), np.float64)
            err = np.abs(pts - rig.evaluate(np.clip(C[frame], rig.lower, rig.upper))).max()
            img = ren.render(pts)
            cv2.putText(img, f"frame {frame}: {label}", (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1)
            imgs.append(img)
            print(f"  frame {frame}: baked points vs the rig posed at the curves: max |diff| {err:.1e} cm")
        cv2.imwrite(str(folder / "ict_usd_frames.png"), np.hstack(imgs))
        print(f"  rendered from the written file: {folder / 'ict_usd_frames.png'}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, help="Keep the copies here and render <stem>_frames.png.")
    args = ap.parse_args(argv)
    missing = [p for p in (VALID, GODETTE) if not p.is_file()]
    if missing:
        print(f"SKIP bench/animated_copy.py: {missing[0]} not found (needs ../shared/realdata)")
        return 0
    try:
        import meshoptimizer  # noqa: F401
        import pygltflib  # noqa: F401
    except ImportError as exc:
        print(f"SKIP bench/animated_copy.py: needs {exc.name} (pip install -e '.[dev,rigs]')")
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.out or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        run_valid(folder, args.out is not None)
        run_godette(folder, args.out is not None)
        try:
            import pxr  # noqa: F401
        except ImportError:
            print("SKIP bench/animated_copy.py, USD part: needs usd-core (pip install -e '.[usd]')")
            return 0
        run_ict_usd(folder, args.out is not None)
    return 0


if __name__ == "__main__":
    sys.exit(main())
