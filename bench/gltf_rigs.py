"""Measurements of read_gltf_rig on the two real rigs of ``../shared/realdata/rigs`` (issue 29; not timed).

For ``valid-glb/White_F_2_Busi.glb`` (meshopt + quantization) and ``godette-vrm/Godette_vrm_v4.vrm``
(VRM 0.x): vertices and targets per mesh, bounding boxes, the head's height, which targets move the
chin and the upper lids (and by how much), and the check behind the ``t_X -> X`` name rule: for each
teeth target ``t_X`` with a head target ``X``, the cosine between the teeth's displacement and the
head target's displacement averaged at the 8 head vertices nearest each teeth vertex, the rank of
``X`` among all 65 head targets by that cosine, and the magnitude ratio; the teeth targets without a
partner give the baseline. ``--png DIR`` renders (with retarget_cli.methods.render) the VALID head neutral,
mouth-open and eyes-closed, its mouth with and without the teeth joined to the slider, and Godette's
face at a few presets. Without ``../shared/realdata`` it prints a skip line and exits 0.

Run: ``python bench/gltf_rigs.py [--png DIR]``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
RIGS = ROOT.parent / "shared" / "realdata" / "rigs"
VALID = RIGS / "valid-glb" / "White_F_2_Busi.glb"
GODETTE = RIGS / "godette-vrm" / "Godette_vrm_v4.vrm"


def _ranges(rig) -> dict:
    return {name: slice(a, b) for name, a, b in rig.mesh_ranges}


def _table(rig) -> None:
    print("| mesh | vertices | targets | bbox min (m) | bbox max (m) |\n|---|---|---|---|---|")
    for name, a, b in rig.mesh_ranges:
        v = rig.neutral[a:b]
        print(f"| {name} | {b - a} | {rig.target_meshes.count(name)} | {np.round(v.min(0), 3).tolist()} | "
              f"{np.round(v.max(0), 3).tolist()} |")


def _movers(rig, part: slice, verts: np.ndarray, axis: int, n: int = 3) -> list:
    """Targets of *part* by their mean displacement along *axis* at *verts* (most negative first)."""
    ks = [k for k in range(len(rig.target_names)) if rig.deltas[k, part][verts].any()]
    vals = sorted((float(rig.deltas[k, part][verts, axis].mean()), rig.target_names[k]) for k in ks)
    return [(name, round(v * 1000, 1)) for v, name in vals[:n]]


def valid(png: Path | None) -> None:
    from scipy.spatial import cKDTree

    from retarget_cli.io.rig.gltf import read_gltf_rig

    rig = read_gltf_rig(VALID)
    every = read_gltf_rig(VALID, meshes=["*"])
    print(f"## {VALID.name}: {rig.kind}, {len(rig.target_names)} targets, {len(rig.groups)} sliders\n")
    _table(every)
    r = _ranges(rig)
    head, teeth = r["H_DDS_HighRes"], r["h_TeethDown"]
    hv = rig.neutral[head]
    face = (np.abs(rig.deltas[:, head]) > 1e-4).any(axis=(0, 2))
    lo, hi = hv[face].min(0), hv[face].max(0)
    cand = np.nonzero((np.abs(hv[:, 0]) < 0.004) & (hv[:, 1] > 1.48) & (hv[:, 1] < 1.51))[0]
    chin = cand[np.argmax(hv[cand, 2])]
    print(f"\nbody height {np.ptp(hv[:, 1]):.3f} m; head crown {hv[:, 1].max():.3f} m, chin (front-most midline "
          f"vertex under the lips) {hv[chin].round(3).tolist()}: crown to chin {hv[:, 1].max() - hv[chin, 1]:.3f} m")
    print(f"face region (vertices any head target moves, {face.sum()}): size {np.round(hi - lo, 3).tolist()} m")
    near = np.linalg.norm(hv - hv[chin], axis=1) < 0.005
    print(f"chin (5 mm around it) moved down most by (mm): {_movers(rig, head, near, 1, 5)}")
    er = _ranges(every)
    for eye in ("h_L_eye", "h_R_eye"):
        ev = every.neutral[er[eye]]
        c, rad = ev.mean(0), float(np.linalg.norm(ev - ev.mean(0), axis=1).max())
        d = hv - c
        lid = (np.abs(d[:, 0]) < 0.6 * rad) & (d[:, 1] > 0) & (d[:, 1] < 1.2 * rad) & (d[:, 2] > 0)
        print(f"upper lid over {eye} ({lid.sum()} vertices) moved down most by (mm): {_movers(rig, head, lid, 1)}")
    print("\nt_X rule: teeth target vs the head target X near the teeth\n")
    print("| teeth target | head partner | cosine | rank of 65 | magnitude ratio |\n|---|---|---|---|---|")
    short = {k: rig.target_names[k].split(".", 1)[-1] for k in range(len(rig.target_names))}
    heads = {short[k]: k for k in range(len(rig.target_names)) if rig.target_meshes[k] == "H_DDS_HighRes"}
    _, nn = cKDTree(hv).query(rig.neutral[teeth], k=8)
    near_head = np.stack([rig.deltas[k, head][nn].mean(1) for k in heads.values()])  # (65, T, 3)
    lone = []
    for k in (k for k in range(len(rig.target_names)) if rig.target_meshes[k] == "h_TeethDown"):
        dt = rig.deltas[k, teeth]
        cos = (near_head * dt).sum((1, 2)) / np.maximum(np.linalg.norm(near_head, axis=(1, 2)) * np.linalg.norm(dt),
                                                       1e-30)
        x = short[k][2:] if short[k].startswith("t_") else None
        if x in heads:
            j = list(heads).index(x)
            ratio = np.linalg.norm(dt) / np.linalg.norm(near_head[j])
            print(f"| {short[k]} | {x} | {cos[j]:.3f} | {int((cos > cos[j]).sum()) + 1} | {ratio:.2f} |")
        else:
            lone.append(float(cos.max()))
    print(f"\n{len(lone)} teeth targets without a head partner: best cosine with any head target at most "
          f"{max(lone):.3f}")
    if png:
        _valid_png(rig, png)


def _crop(rig, keep_vertex: np.ndarray):
    """Faces with every vertex kept, re-indexed, and the kept vertex ids."""
    faces = rig.faces[keep_vertex[rig.faces].all(1)]
    used = np.unique(faces)
    remap = np.full(len(rig.neutral), -1)
    remap[used] = np.arange(len(used))
    return remap[faces], used


def _label(img, text, x=8, y=22):
    import cv2

    cv2.putText(img, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1)
    return img


def _pose(rig, weights: dict) -> np.ndarray:
    out = rig.neutral.copy()
    for slider, a in weights.items():
        for k, w in rig.groups[slider]:
            out += a * w * rig.deltas[k]
    return out


def _valid_png(rig, out: Path) -> None:
    import cv2

    from retarget_cli.io.rig.gltf import read_gltf_rig
    from retarget_cli.methods.render import Camera, MeshRenderer

    every = read_gltf_rig(VALID, meshes=["*"])
    v = every.neutral
    faces, used = _crop(every, (v[:, 1] > 1.45) & (np.abs(v[:, 0]) < 0.12))
    rows = []
    for cam in (Camera(fov=20), Camera(yaw=60, fov=20)):
        ren = MeshRenderer(faces, v[used], camera=cam, size=(360, 360))
        rows.append([_label(ren.render(_pose(every, w)[used]), t) for w, t in
                     (({}, "neutral"), ({"MouthOpen_h": 1}, "MouthOpen_h"),
                      ({"LeyeClose_h": 1, "ReyeClose_h": 1}, "L/ReyeClose_h"))])
    cv2.imwrite(str(out / "valid_head.png"), np.vstack([np.hstack(r) for r in rows]))
    faces, used = _crop(every, (v[:, 1] > 1.47) & (v[:, 1] < 1.57) & (np.abs(v[:, 0]) < 0.045) & (v[:, 2] > 0.05))
    ren = MeshRenderer(faces, v[used], camera=Camera(pitch=22, fov=15, fill=1.0), size=(360, 360))
    rows = []
    for s in ("MouthOpen_h", "Shout_h"):
        k = next(k for k, _ in every.groups[s] if every.target_meshes[k] == "H_DDS_HighRes")
        rows.append(np.hstack([_label(ren.render(v[used]), "neutral"),
                               _label(ren.render(_pose(every, {s: 1})[used]), f"{s} slider (head + t_)"),
                               _label(ren.render((v + every.deltas[k])[used]), f"{s} head target only")]))
    cv2.imwrite(str(out / "valid_mouth.png"), np.vstack(rows))


def godette(png: Path | None) -> None:
    from retarget_cli.io.rig.gltf import read_gltf_rig

    rig = read_gltf_rig(GODETTE)
    every = read_gltf_rig(GODETTE, meshes=["*"])
    print(f"\n## {GODETTE.name}: {rig.kind}, {len(rig.target_names)} targets, {len(rig.groups)} sliders "
          f"({', '.join(rig.groups)})\n")
    _table(every)
    print("\n| target | max displacement (mm) | vertices moved (> 10 % of max) | direction at the max |\n|---|---|---|---|")
    for name, d in zip(rig.target_names, rig.deltas):
        m = np.linalg.norm(d, axis=1)
        i = int(np.argmax(m))
        print(f"| {name} | {1000 * m[i]:.1f} | {(m > 0.1 * m[i]).sum()} | {np.round(d[i] / m[i], 2).tolist()} |")
    if png:
        import cv2

        from retarget_cli.methods.render import Camera, MeshRenderer

        ren = MeshRenderer(rig.faces, rig.neutral, camera=Camera(yaw=180, fov=20), size=(320, 320))  # VRM 0.x faces -z
        imgs = [_label(ren.render(_pose(rig, {s: 1} if s else {})), s or "neutral")
                for s in (None, "a", "o", "blink", "angry")]
        cv2.imwrite(str(png / "godette.png"), np.hstack(imgs))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--png", type=Path, help="Write valid_head.png, valid_mouth.png and godette.png here.")
    args = ap.parse_args(argv)
    missing = [p for p in (VALID, GODETTE) if not p.is_file()]
    if missing:
        print(f"SKIP bench/gltf_rigs.py: {missing[0]} not found (needs ../shared/realdata)")
        return 0
    try:
        import meshoptimizer  # noqa: F401
    except ImportError:
        print("SKIP bench/gltf_rigs.py: needs meshoptimizer (pip install 'retarget[rigs]')")
        return 0
    if args.png:
        args.png.mkdir(parents=True, exist_ok=True)
    valid(args.png)
    godette(args.png)
    return 0


if __name__ == "__main__":
    sys.exit(main())
