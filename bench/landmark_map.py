"""Benchmark: the landmark map found automatically (``retarget map-landmarks``, issue 29) against the shipped one.

1. ICT FaceKit (``sample_data/ict``, unpacked to ``build/ict-facekit``): the automatic map against the kit's own
   ``idx_to_landmark_verts`` (rig.yaml ``landmarks:``): mean and max 3D distance between the two maps' vertices
   in inter-ocular distances (outer eye corners 36-45 of the shipped map), over all 68 points, without the jaw
   line (0-16), and over the points the delta auto-pose fits (all but the contour 0-5, 11-16); per region; the
   same for every render style on its own and for the sliders' fallback alone (no detector).
2. Which render styles the detector finds a face on: the ICT neutral, the VALID head
   (``../shared/realdata/rigs/valid-glb``) and the Godette VRM (``godette-vrm``), read with ``read_gltf_rig``
   (sliders: its groups); for VALID also the fallback against the detector's map.
3. ``--clips``: the three shared clips (d3, d9, d12) retargeted by ``bench/peer.py --starts 0`` with
   ``configs/real.yaml`` as it is (the shipped map) and with ``auto_pose.landmark_vertices`` set to the
   automatic map; prints both tables' ``ours`` rows (r of mouth, eyes, brow, width against MediaPipe Face Mesh).
   Takes several minutes (two ``retarget run`` per clip, cached under ``build/peer``).

``--png DIR`` writes the contact sheets (ict.png, valid.png, godette.png). Parts 2-3 print a skip line
without ``../shared/realdata``.

Run: ``python bench/landmark_map.py [--png DIR] [--clips]``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
DATA = ROOT.parent / "shared" / "realdata"
ICT = ROOT / "build" / "ict-facekit" / "rig.yaml"
VALID = DATA / "rigs" / "valid-glb" / "White_F_2_Busi.glb"
GODETTE = DATA / "rigs" / "godette-vrm" / "Godette_vrm_v4.vrm"
BUILD = ROOT / "build" / "landmark_map"
#: Points the delta auto-pose fits (retarget_cli.stages.auto_pose.CONTOUR_68 left out).
FITTED = [i for i in range(68) if i not in (0, 1, 2, 3, 4, 5, 11, 12, 13, 14, 15, 16)]


def distances(V, vx, ref) -> np.ndarray:
    return np.linalg.norm(V[vx] - V[ref], axis=1) / np.linalg.norm(V[ref[45]] - V[ref[36]])


def row(label: str, d) -> str:
    return (f"| {label} | {d.mean():.3f} | {d.max():.3f} | {d[17:].mean():.3f} | {d[FITTED].mean():.3f} | "
            + " | ".join(f"{d[list(ids)].mean():.3f}" for ids in REGIONS.values()) + " |")


def gltf_arrays(path):
    from retarget_cli.io.rig.gltf import read_gltf_rig

    g = read_gltf_rig(path)
    names = list(g.groups)
    D = np.stack([sum(w * g.deltas[k] for k, w in g.groups[n]) for n in names])
    return g.neutral, g.faces, D, names


def sheet(lmap, path: Path, title: str) -> None:
    import cv2

    from retarget_cli.methods.landmark_map import draw_sheet

    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), draw_sheet(lmap, title))
    print(f"wrote {path}", file=sys.stderr)


def brow_heights() -> None:
    """Each brow point's height above the outer eye corners' line (IOD) on the shared clips' frame-0 annotations."""
    from retarget_cli.io.annotations import read_pts
    from retarget_cli.methods import landmark_map as lm

    rows = []
    for pts in sorted((DATA / "videos").glob("*_00000.pts")):
        P = np.asarray(read_pts(pts), np.float64)
        axis = P[45] - P[36]
        up = np.array([axis[1], -axis[0]]) / np.linalg.norm(axis)
        rows.append((P[17:27] - (P[36] + P[45]) / 2) @ up / np.linalg.norm(axis))
        print(f"brow heights of {pts.name}: " + " ".join(f"{h:.3f}" for h in rows[-1]) + f" (mean {rows[-1].mean():.3f})")
    if rows:
        mean = np.mean(rows, axis=0)
        mirrored = (mean + mean[::-1]) / 2
        print("mean, mirror pairs averaged (BROW_HEIGHT_68): " + " ".join(f"{h:.3f}" for h in mirrored)
              + f"; in the code: {' '.join(f'{h:.3f}' for h in lm.BROW_HEIGHT_68)}\n")


def ict(det, png) -> Path:
    from retarget_cli.io.rig import load_rig
    from retarget_cli.methods import landmark_map as lm
    from retarget_cli.stages.map_landmarks import map_text, rig_arrays

    if not ICT.is_file():
        subprocess.run(["make", str(ICT.relative_to(ROOT))], cwd=ROOT, check=True, capture_output=True)
    r = load_rig(ICT)
    V, F, D, names = rig_arrays(r)
    ref = r.landmarks[1]
    print("ICT FaceKit: automatic map against the shipped one (distances in inter-ocular distances)\n")
    print("| map | mean | max | mean w/o jaw line | mean of auto-pose's points | "
          + " | ".join(REGIONS) + " |")
    print("|" + "---|" * (5 + len(REGIONS)))
    t = time.perf_counter()
    auto = lm.find_landmark_map(V, F, D, names, detector=det)
    secs = time.perf_counter() - t
    print(row(f"automatic ({auto.found_by}, {secs:.1f} s)", distances(V, auto.vertices, ref)))
    for style in lm.STYLES:
        m = lm.find_landmark_map(V, F, D, names, detector=det, styles=(style,))
        label = f"style {style.name}" + ("" if m.found_by == style.name else " (no face: sliders)")
        print(row(label, distances(V, m.vertices, ref)))
    fb = lm.find_landmark_map(V, F, D, names, detector=None)
    print(row("sliders' fallback only", distances(V, fb.vertices, ref)))
    q = lm.map_quality(V, auto.vertices, yaw=auto.render.yaw)
    qs = lm.map_quality(V, ref)
    print(f"\nsymmetry (mean/max IOD): automatic {q['symmetry_mean']:.3f}/{q['symmetry_max']:.3f}, "
          f"shipped {qs['symmetry_mean']:.3f}/{qs['symmetry_max']:.3f}; shared vertices {q['shared']}\n")
    BUILD.mkdir(parents=True, exist_ok=True)
    out = BUILD / "ict_auto.txt"
    out.write_text(map_text(auto, "rig.yaml"))
    if png:
        sheet(auto, png / "ict.png", "ICT FaceKit")
        sheet(fb, png / "ict_fallback.png", "ICT FaceKit, sliders only")
    return out


def others(det, png) -> None:
    from retarget_cli.methods import landmark_map as lm

    print("Render styles on which the detector finds a face (yes/no), and the map found:\n")
    print("| rig | " + " | ".join(s.name for s in lm.STYLES) + " | found by | symmetry mean/max | shared vertices |")
    print("|" + "---|" * (len(lm.STYLES) + 4))
    for name, path in (("VALID head (GLB)", VALID), ("Godette (VRM 0.x)", GODETTE)):
        V, F, D, names = gltf_arrays(path)
        found = [lm.find_landmark_map(V, F, D, names, detector=det, styles=(s,)).found_by == s.name
                 for s in lm.STYLES]
        m = lm.find_landmark_map(V, F, D, names, detector=det)
        q = lm.map_quality(V, m.vertices, yaw=m.render.yaw)
        print(f"| {name} | " + " | ".join("yes" if f else "no" for f in found)
              + f" | {m.found_by} (yaw {m.render.yaw:.0f}) | {q['symmetry_mean']:.3f}/{q['symmetry_max']:.3f} | "
              f"{len(q['shared'])} groups |")
        if m.found_by != "sliders":
            fb = lm.find_landmark_map(V, F, D, names, detector=None)
            d = distances(V, fb.vertices, m.vertices)
            print(f"|  {name}: sliders' fallback against the detector's map | mean {d.mean():.3f} | "
                  f"w/o jaw {d[17:].mean():.3f} | auto-pose's points {d[FITTED].mean():.3f} |" + " |" * 3)
        if png:
            sheet(m, png / (path.stem.split("_")[0].lower() + ".png"), name)
    print()


def clips(auto_map: Path) -> None:
    import yaml

    sys.path.insert(0, str(HERE))
    from real_rig import _absolutize

    base = ROOT / "configs" / "real.yaml"
    raw = yaml.safe_load(base.read_text())
    cfg = {k: _absolutize(v, base.parent) if k != "output_dir" else v for k, v in raw.items()}
    cfg["auto_pose"]["landmark_vertices"] = str(auto_map)
    variant = BUILD / "real_auto.yaml"
    variant.write_text(yaml.safe_dump(cfg, sort_keys=False))
    rows = {}
    for label, config in (("shipped map", ROOT / "configs" / "real.yaml"), ("automatic map", variant)):
        out = BUILD / f"peer_{label.split()[0]}.json"
        cmd = [sys.executable, str(HERE / "peer.py"), "--starts", "0", "--config", str(config), "--json", str(out)]
        res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
        if res.returncode:
            raise RuntimeError(f"{' '.join(cmd)} failed:\n{res.stderr[-2000:]}")
        if res.stdout.startswith("SKIP"):
            print(res.stdout.strip())
            return
        rows[label] = [r for r in json.loads(out.read_text()) if r.get("system") == "ours"]
    print("The three clips retargeted with each map (bench/peer.py --starts 0, r against MediaPipe Face Mesh):\n")
    keys = ("mouth", "eye_l", "eye_r", "brow", "width")
    print("| clip | map | " + " | ".join(keys) + " |")
    print("|" + "---|" * (2 + len(keys)))
    for label, rs in rows.items():
        for r in rs:
            ref = r["refs"]["mediapipe"]["r"]
            print(f"| {r['clip']} | {label} | " + " | ".join(f"{ref.get(k, float('nan')):.3f}" for k in keys) + " |")
        mean = [np.nanmean([r["refs"]["mediapipe"]["r"].get(k, np.nan) for r in rs]) for k in keys]
        print(f"| mean | {label} | " + " | ".join(f"{v:.3f}" for v in mean) + " |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--png", type=Path, help="Write the contact sheets here.")
    ap.add_argument("--clips", action="store_true", help="Also retarget the three shared clips with each map.")
    args = ap.parse_args(argv)
    from retarget_cli.methods.tracking.detect import Detector, detector_installed

    if not detector_installed():
        print("SKIP bench/landmark_map.py: needs the detector (pip install 'retarget[detect]')")
        return 0
    det = Detector()
    if (DATA / "videos").is_dir():
        brow_heights()
    auto_map = ict(det, args.png)
    if not (VALID.is_file() and GODETTE.is_file()):
        print(f"SKIP bench/landmark_map.py parts 2-3: {VALID if not VALID.is_file() else GODETTE} not found "
              "(needs ../shared/realdata)")
        return 0
    others(det, args.png)
    if args.clips:
        clips(auto_map)
    return 0


from retarget_cli.methods.landmark_map import REGIONS_68 as REGIONS  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
