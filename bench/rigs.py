"""Benchmark (issue 29, "Done when"): the shared clips onto rigs read from character files, map found automatically.

Not a timed test: every figure is a correlation or a distance. Two parts, each on the three shared clips
(d3, d9, d12 of ``../shared/realdata/videos``, whole clips) through the documented path: ``configs/real.yaml``
with only ``track.video``, ``track.init: auto`` and ``auto_pose.rig`` changed (``bench/peer.py``'s
:func:`~peer.run_ours`, which also sets ``track.start``/``end`` to the whole clip).

(a) **The ICT FaceKit read from a GLB that ``retarget`` wrote.** The OBJ rig's run on d3 (``apply.formats``
    of ``configs/real.yaml`` include ``glb``) writes ``frames/animation.glb``: one morph target per rig
    slider. A ``rig.yaml`` with ``source:`` that file and the kit's ``range:``, ``exclusive:`` and ``names:``,
    and **no** ``landmarks:``, is the GLB rig: ``auto-pose`` finds the map itself (its ``landmark_map.txt``).
    Each clip runs on the OBJ rig with the shipped map and on the GLB rig; both are scored as ``bench/peer.py``
    scores the documented path (its functions, imported): the kit's shipped landmark vertices posed at the
    curves, projected frontally, r of mouth and eye openings (and brow, mouth width) against MediaPipe Face
    Mesh 0.10.14. Target: mouth and eye r within 0.03 of the OBJ path's. The automatic map's distance to the
    shipped one (inter-ocular distances, GLB vertex ids turned into the OBJ's by position).

(b) **The VALID avatar** (``rigs/valid-glb/White_F_2_Busi.glb``) **and the Godette VRM**
    (``rigs/godette-vrm/Godette_vrm_v4.vrm``) given as the rig, no hand-made file: no ``rig.yaml``, no map,
    no names. The character's mouth opening and eye openings are measured on the rig's own lip and lid
    vertices (:data:`MEASURE_VERTICES`, chosen by hand once for this benchmark and never given to the
    pipeline), posed at the run's curves and projected face-on, and correlated with the actor's (MediaPipe
    Face Mesh). Targets: r >= 0.8 (mouth), >= 0.65 (eyes). The tracker's own 68 points give the ceiling.

``--png DIR``: one picture per rig (``ict-glb.png``, ``valid.png``, ``godette.png``): three frames of d3 (the
actor at rest, the widest mouth, the most closed eyes, by MediaPipe), each the video frame beside the character
posed at that frame's curves (the project's software rasteriser, ``MeshRenderer``; the VRM faces -z); and
``rigs.png``, the three stacked at a smaller size (the README's picture).

Runs are cached under ``build/rigs`` keyed by the video, the config, the rig file and the ``retarget_cli``
sources (``--fresh`` reruns them). Without ``../shared/realdata`` it prints a skip line and exits 0.

Run: ``python bench/rigs.py [--videos d3,d9,d12] [--only ict,valid,godette] [--png DIR]``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path
from types import SimpleNamespace

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

import peer  # noqa: E402  (bench/peer.py: the documented path's run and its scoring)
from realrig.measures import MULTIPIE68, opening, pearson  # noqa: E402

DATA = peer.DATA
BUILD = ROOT / "build" / "rigs"
CONFIG = ROOT / "configs" / "real.yaml"
ICT_YAML = ROOT / "sample_data" / "ict" / "rig.yaml"
#: The two characters, under the realdata folder's rigs/.
RIGS = {"valid": Path("valid-glb") / "White_F_2_Busi.glb", "godette": Path("godette-vrm") / "Godette_vrm_v4.vrm"}
TITLES = {"ict": "ICT FaceKit (GLB written by retarget, map found)", "valid": "VALID avatar (GLB)",
          "godette": "Godette (VRM 0.x)"}
#: Camera yaw that shows each character's face (a VRM 0.x avatar faces -z).
YAW = {"ict": 0.0, "valid": 0.0, "godette": 180.0}
#: Characters whose eyes and mouth are textured pieces laid on the skin: untextured they would not show, so the
#: pictures draw every piece but the skin (the largest connected piece) dark.
PIECES_DARK = ("godette",)
TARGETS = {"mouth": 0.8, "eye": 0.65}
SAME_AS_OBJ = 0.03   # (a): |r GLB - r OBJ| for mouth and eyes

#: The rig vertices each character's measures are taken on: per measure (upper, lower, corner on the image's
#: left, corner on the image's right), the character seen face-on. Chosen by hand once for this benchmark, from
#: renders of the neutral (and of ``MouthOpen_h`` / ``a`` at 1 for the inner lips) with every visible vertex's id
#: drawn beside it (the project's rasteriser, 2048 px, zoomed on the mouth and on each eye): the inner-lip
#: vertices on the midline where the opened lips part, the lid-margin vertices at the middle of each eye
#: opening, the corners at the ends of the lip line and of the eye opening. Checked on the rig: each lid measure
#: closes under its blink slider only (VALID ``ReyeClose_h``/``LeyeClose_h``: 0.33 -> 0.01; Godette
#: ``blink_r``/``blink_l``: 0.93 -> 0.17) and the mouth opens under jaw-open (VALID ``MouthOpen_h`` 0.46,
#: Godette ``a`` 0.45). The pipeline never sees them: it finds its own 68-point map.
MEASURE_VERTICES = {
    "valid": {"mouth": (14622, 15002, 14925, 14756),     # H_DDS_HighRes (head mesh) ids
              "eye_l": (13518, 13548, 13532, 14114),     # the character's right eye (image left)
              "eye_r": (15735, 15711, 15770, 15743)},
    "godette": {"mouth": (607, 109, 602, 605),          # FaceMesh ids
                "eye_l": (548, 488, 566, 95),
                "eye_r": (514, 444, 46, 533)},
}


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- runs


def _run_args(rig_path: Path, fresh: bool) -> SimpleNamespace:
    """What :func:`peer.run_ours` reads of its arguments: the config, the rig and ``--fresh``."""
    return SimpleNamespace(config=CONFIG, rig_yaml=Path(rig_path), fresh=fresh)


def _rig_key(rig_path: Path) -> str:
    """sha of the rig: rig.yaml and the file it names (or the character file itself)."""
    from reference import sha256_file

    rig_path = Path(rig_path)
    parts = [rig_path.read_bytes()] if rig_path.suffix in (".yaml", ".yml") else []
    src = rig_path.parent / "ict.glb" if rig_path.suffix in (".yaml", ".yml") else rig_path
    if src.is_file():
        parts.append(sha256_file(src))
    return peer.sha_text(CONFIG.read_bytes(), *parts)[:8]


def run_documented(clip: str, system: str, rig_path: Path, ctx, args) -> dict:
    """The documented path on the whole *clip* with *rig_path* as ``auto_pose.rig`` (cached); peer's reader."""
    from real_rig import code_tag
    from reference import sha256_file

    video = args.data / "videos" / f"{clip}.mp4"
    n = len(peer.references(video)["mediapipe"]["found"])
    work = BUILD / f"{clip}-{sha256_file(video)[:12]}" / system / f"ours-{_rig_key(rig_path)}-{code_tag(bench=False)}"
    out = peer.run_ours(video, 0, n, ctx, work, _run_args(rig_path, args.fresh))
    out["work"] = work
    log(f"{clip} {system}: {n} frames, {float(out['seconds']):.0f} s ({work.relative_to(ROOT)})")
    return out


def ict_glb_rig(obj_run: Path) -> Path:
    """``build/rigs/ict-glb/rig.yaml``: the GLB the OBJ run wrote, as a ``source:`` rig without ``landmarks:``."""
    import yaml

    glb = obj_run / "run" / "frames" / "animation.glb"
    if not glb.is_file():
        raise RuntimeError(f"{glb}: the OBJ run wrote no GLB (configs/real.yaml apply.formats needs glb)")
    d = BUILD / "ict-glb"
    d.mkdir(parents=True, exist_ok=True)
    if not (d / "ict.glb").is_file() or (d / "ict.glb").read_bytes() != glb.read_bytes():
        shutil.copy(glb, d / "ict.glb")
    shipped = yaml.safe_load(ICT_YAML.read_text())
    spec = {"source": "ict.glb", **{k: shipped[k] for k in ("range", "exclusive", "names") if k in shipped}}
    text = ("# The ICT FaceKit as retarget's apply --format glb wrote it (bench/rigs.py); no landmarks: the map is\n"
            "# found automatically by auto-pose.\n" + yaml.safe_dump(spec, sort_keys=False))
    if not (d / "rig.yaml").is_file() or (d / "rig.yaml").read_text() != text:
        (d / "rig.yaml").write_text(text)
    return d / "rig.yaml"


# --------------------------------------------------------------------------- (a) the ICT through its GLB


def glb_to_obj_ids(glb_rig, obj_rig, ids) -> np.ndarray:
    """GLB vertex ids -> the OBJ's: the GLB holds the OBJ's vertices first, in order, then copies split at UV seams."""
    from scipy.spatial import cKDTree

    ids = np.asarray(ids, np.int64)
    N = obj_rig.n_vertices
    out = ids.copy()
    far = ids >= N
    if far.any():
        _, k = cKDTree(obj_rig.neutral).query(glb_rig.neutral[ids[far]])
        out[far] = k
    return out


def read_map(path: Path) -> np.ndarray:
    """Vertex ids of a ``landmark_map.txt`` (one per line, ``#`` comments)."""
    vals = [line.split("#", 1)[0].strip() for line in path.read_text().splitlines()]
    return np.array([int(v) for v in vals if v], np.int64)


def part_a(clips, refs, args) -> dict:
    """Both ICT systems on every clip: peer's score rows, the automatic map's distance to the shipped one."""
    from real_rig import load_rig as load_ict

    from retarget_cli.io.rig import load_rig
    from retarget_cli.methods import landmark_map as lm

    ctx = load_ict(args.data / "ict-facekit" / "ict-facekit-rig.tar.xz")  # build/real_rig/ict-facekit
    obj_yaml = ROOT / "build" / "real_rig" / "ict-facekit" / "rig.yaml"
    consts = peer.rig_constants(ctx)
    rows, maps, runs = [], {}, {}
    glb_yaml = None
    for clip in clips:
        frames = np.arange(len(refs[clip]["mediapipe"]["found"]))
        obj = run_documented(clip, "ict-obj", obj_yaml, ctx, args)
        if glb_yaml is None:  # the GLB written by the first OBJ run is the rig of every GLB run
            glb_yaml = ict_glb_rig(obj["work"])
        glb = run_documented(clip, "ict-glb", glb_yaml, ctx, args)
        runs[clip] = {"ours": glb, "frames": frames}
        for system, run in (("OBJ, shipped map", obj), ("GLB, map found", glb)):
            rows.append({"clip": clip, "system": system,
                         "refs": peer.score(ctx.landmarks_2d(run["curves"]), MULTIPIE68, refs[clip], frames, consts)})
        maps[clip] = read_map(glb["work"] / "run" / "targets" / "landmark_map.txt")
    glb_rig, ship = load_rig(glb_yaml), ctx.vertices
    dist = {}
    for clip, vx in maps.items():
        ids = glb_to_obj_ids(glb_rig, ctx.rig, vx)
        d = np.linalg.norm(ctx.rig.neutral[ids] - ctx.rig.neutral[ship], axis=1)
        d /= np.linalg.norm(ctx.rig.neutral[ship[45]] - ctx.rig.neutral[ship[36]])
        dist[clip] = {"mean": float(d.mean()), "max": float(d.max()),
                      **{k: float(d[list(v)].mean()) for k, v in lm.REGIONS_68.items()}}
    return {"rows": rows, "dist": dist, "ctx": ctx, "runs": runs, "glb_yaml": glb_yaml}


def table_a(res: dict) -> str:
    keys = ("mouth", "eye_l", "eye_r", "brow", "width")
    lines = ["| clip | rig | r mouth | r eye L | r eye R | r brow | r width |", "|---|---|---|---|---|---|---|"]
    for row in res["rows"]:
        r = row["refs"]["mediapipe"]["r"]
        lines.append(f"| {row['clip']} | {row['system']} | " + " | ".join(peer.fmt(r[k], ".3f") for k in keys) + " |")
    for system in dict.fromkeys(row["system"] for row in res["rows"]):
        got = [row["refs"]["mediapipe"]["r"] for row in res["rows"] if row["system"] == system]
        lines.append(f"| **mean** | {system} | "
                     + " | ".join(peer.fmt(float(np.nanmean([g[k] for g in got])), ".3f") for k in keys) + " |")
    return "\n".join(lines)


def verdict_a(res: dict) -> list:
    out = []
    by = {}
    for row in res["rows"]:
        by.setdefault(row["system"], []).append(row["refs"]["mediapipe"]["r"])
    (a, ra), (b, rb) = list(by.items())[:2]
    for k in ("mouth", "eye_l", "eye_r"):
        x, y = float(np.nanmean([g[k] for g in ra])), float(np.nanmean([g[k] for g in rb]))
        ok = abs(y - x) <= SAME_AS_OBJ
        out.append(f"- mean r {k}: {b} {y:.3f}, {a} {x:.3f}: difference {y - x:+.3f} "
                   f"({'within' if ok else 'NOT within'} {SAME_AS_OBJ}{'' if ok or y < x else '; higher'})")
    means = [d["mean"] for d in res["dist"].values()]
    d0 = next(iter(res["dist"].values()))
    ok = max(means) <= SAME_AS_OBJ
    out.append(f"- the automatic map lies {d0['mean']:.3f} inter-ocular distances from the shipped one on average "
               f"(max {d0['max']:.3f}; jaw {d0['jaw']:.3f}, brows {d0['brow_right']:.3f}/{d0['brow_left']:.3f}, "
               f"nose {d0['nose']:.3f}, eyes {d0['eye_right']:.3f}/{d0['eye_left']:.3f}, mouth {d0['mouth']:.3f}; "
               f"the same map on every clip: {len(set(np.round(means, 6))) == 1}): "
               f"{'within' if ok else 'NOT within'} {SAME_AS_OBJ}")
    return out


# --------------------------------------------------------------------------- (b) the two characters


def character_measures(rig, name: str, curves) -> dict:
    """Mouth and eye openings of character *name* on its :data:`MEASURE_VERTICES`, posed at *curves* (T, E)."""
    spec = MEASURE_VERTICES[name]
    ids = sorted({v for quad in spec.values() for v in quad})
    pos = {v: k for k, v in enumerate(ids)}
    rows = rig.rows(np.array(ids))
    X = (rig.f0[rows] + np.asarray(curves) @ rig.block(rows).T).reshape(len(curves), -1, 3)
    sign = -1.0 if abs(YAW[name]) == 180 else 1.0   # face-on: a -z-facing character's +x is the image's left
    P = np.stack([sign * X[..., 0], -X[..., 1]], -1)
    return {m: opening(P, [pos[u]], [pos[lo]], pos[a], pos[b]) for m, (u, lo, a, b) in spec.items()}


def part_b(clips, refs, args) -> dict:
    from retarget_cli.io.rig import load_rig
    from retarget_cli.methods import landmark_map as lm

    out = {"rows": [], "runs": {}, "rigs": {}, "maps": {}}
    for name in args.only:
        if name == "ict":
            continue
        path = args.data / "rigs" / RIGS[name]
        rig = load_rig(path)
        ctx = SimpleNamespace(rig=rig, names=rig.names)
        out["rigs"][name] = rig
        for clip in clips:
            frames = np.arange(len(refs[clip]["mediapipe"]["found"]))
            run = run_documented(clip, name, path, ctx, args)
            C = run["curves"]  # in the rig's slider order (peer's reader)
            mine = character_measures(rig, name, C)
            ref = refs[clip]["mediapipe"]
            found = ref["found"][frames]
            tracked = peer.measures(run["points"], MULTIPIE68)
            r = {k: pearson(mine[k], ref["m"][k][frames], found) for k in mine}
            ceiling = {k: pearson(tracked[k], ref["m"][k][frames], found) for k in mine}
            top = np.argsort(-C.mean(0))[:5]
            out["rows"].append({"rig": name, "clip": clip, "r": r, "tracker": ceiling,
                                "sliders": [(rig.names[i], float(C[:, i].mean())) for i in top]})
            out["runs"].setdefault(name, {})[clip] = {"ours": {"curves": C}, "frames": frames}
            mp = run["work"] / "run" / "targets" / "landmark_map.txt"
            if mp.is_file() and name not in out["maps"]:
                vx = read_map(mp)
                head = mp.read_text().splitlines()[1]  # "# found by retarget map-landmarks from <how>, yaw <y>. ..."
                how = head.split(" from ", 1)[-1].split(", yaw", 1)[0]
                q = lm.map_quality(rig.neutral, vx, yaw=YAW[name])
                out["maps"][name] = {"how": how, "symmetry": (q["symmetry_mean"], q["symmetry_max"])}
    return out


def table_b(res: dict) -> str:
    lines = ["| rig | clip | r mouth | r eye L | r eye R | tracker's own points (ceiling): mouth / eye L / eye R | "
             "sliders most used (mean weight) |", "|---|---|---|---|---|---|---|"]
    for row in res["rows"]:
        r, c = row["r"], row["tracker"]
        lines.append(f"| {row['rig']} | {row['clip']} | {peer.fmt(r['mouth'], '.3f')} | {peer.fmt(r['eye_l'], '.3f')}"
                     f" | {peer.fmt(r['eye_r'], '.3f')} | {c['mouth']:.2f} / {c['eye_l']:.2f} / {c['eye_r']:.2f} | "
                     + ", ".join(f"{n} {w:.2f}" for n, w in row["sliders"][:3]) + " |")
    for name in dict.fromkeys(row["rig"] for row in res["rows"]):
        got = [row["r"] for row in res["rows"] if row["rig"] == name]
        ceil = [row["tracker"] for row in res["rows"] if row["rig"] == name]
        m = {k: float(np.nanmean([g[k] for g in got])) for k in ("mouth", "eye_l", "eye_r")}
        c = {k: float(np.nanmean([g[k] for g in ceil])) for k in ("mouth", "eye_l", "eye_r")}
        lines.append(f"| **{name}** | mean | {m['mouth']:.3f} | {m['eye_l']:.3f} | {m['eye_r']:.3f} | "
                     f"{c['mouth']:.2f} / {c['eye_l']:.2f} / {c['eye_r']:.2f} | |")
    return "\n".join(lines)


def verdict_b(res: dict) -> list:
    out = []
    for name in dict.fromkeys(row["rig"] for row in res["rows"]):
        got = [row for row in res["rows"] if row["rig"] == name]
        mouth = float(np.nanmean([g["r"]["mouth"] for g in got]))
        eyes = float(np.nanmean([(g["r"]["eye_l"] + g["r"]["eye_r"]) / 2 for g in got]))
        low = [f"{g['clip']} {k} {g['r'][k]:.2f}" for g in got for k, t in
               (("mouth", TARGETS["mouth"]), ("eye_l", TARGETS["eye"]), ("eye_r", TARGETS["eye"])) if g["r"][k] < t]
        ok = mouth >= TARGETS["mouth"] and eyes >= TARGETS["eye"]
        mp = res["maps"].get(name, {})
        out.append(f"- {name}: mean r mouth {mouth:.3f} (target {TARGETS['mouth']}), eyes {eyes:.3f} "
                   f"(target {TARGETS['eye']}): {'met' if ok else 'NOT met'}"
                   + (f"; below target on {', '.join(low)}" if low else "; every clip at target")
                   + (f"; map: {mp['how']}, symmetry mean/max {mp['symmetry'][0]:.3f}/{mp['symmetry'][1]:.3f} IOD"
                      if mp else ""))
    return out


# --------------------------------------------------------------------------- pictures


def picks(ref: dict, frames) -> dict:
    """Frames of the clip to show (by the actor, MediaPipe): at rest, the widest mouth, the most closed eyes."""
    m, found = ref["m"], ref["found"]
    mouth = np.where(found, peer.running_median(m["mouth"]), np.nan)
    eyes = np.where(found, peer.running_median(0.5 * (m["eye_l"] + m["eye_r"])), np.nan)
    return {"rest": peer.rest_like_frame(ref, frames), "open mouth": int(np.nanargmax(mouth)),
            "closed eyes": int(np.nanargmin(eyes))}


def renderer_for(rig, name: str, size: int):
    """The project's rasteriser framed on the face (the vertices the sliders move), face-on; vertex colours."""
    from retarget_cli.methods import landmark_map as lm
    from retarget_cli.methods.render import Camera, MeshRenderer, triangulate
    from retarget_cli.stages.map_landmarks import rig_arrays

    V, F, D, _ = rig_arrays(rig)
    region = lm.face_region(V, lm.motion_weights(D))
    cam = Camera(yaw=YAW[name], fov=20.0, fill=1.0)
    ren = MeshRenderer(F, V, camera=cam, size=(size, size), background=(60, 60, 60), frame=V[region])
    colors = np.tile(np.array([150.0, 170.0, 215.0]), (len(V), 1))
    if name in PIECES_DARK:
        pieces = lm.mesh_pieces(V, triangulate(F))
        colors[pieces != np.bincount(pieces).argmax()] = (70.0, 55.0, 60.0)
    return ren, colors


def face_crop(frame, points, size: int):
    """*frame* cropped to a square around the actor's face (MediaPipe *points*, 1.6x their box), at *size*."""
    H, W = frame.shape[:2]
    ok = np.isfinite(points).all(1)
    if not ok.any():
        return cv2_resize(frame, size)
    lo, hi = points[ok].min(0), points[ok].max(0)
    c, half = (lo + hi) / 2, 0.8 * float((hi - lo).max())
    half = min(half, W / 2, H / 2)
    x0, y0 = (int(np.clip(c[0] - half, 0, W - 2 * half)), int(np.clip(c[1] - half, 0, H - 2 * half)))
    return cv2_resize(frame[y0:y0 + int(2 * half), x0:x0 + int(2 * half)], size)


def cv2_resize(img, size: int):
    import cv2

    return cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)


def rig_picture(name: str, rig, run: dict, video: Path, ref: dict, size: int):
    """One row: per picked frame, the video frame (cropped square on the face) and the character."""
    import cv2

    clip = video.stem
    ren, colors = renderer_for(rig, name, size)
    cap = cv2.VideoCapture(str(video))
    panels = []
    for label, f in picks(ref, run["frames"]).items():
        cap.set(cv2.CAP_PROP_POS_FRAMES, int(f))
        ok, frame = cap.read()
        frame = face_crop(frame, ref["points"][f], size) if ok else np.zeros((size, size, 3), np.uint8)
        peer._text(frame, f"{clip} {f}: {label}", 16, 0.4)
        img = ren.render(rig.evaluate(run["ours"]["curves"][f]), vertex_colors=colors)
        panels += [frame, img, np.full((size, 4, 3), 255, np.uint8)]
    cap.release()
    row = np.concatenate(panels[:-1], axis=1)
    band = np.full((22, row.shape[1], 3), 30, np.uint8)
    peer._text(band, TITLES[name], 16, 0.45)
    return np.concatenate([band, row], axis=0)


def write_pngs(outdir: Path, a: dict | None, b: dict | None, refs: dict, data: Path, clip: str = "d3") -> list:
    import cv2

    outdir.mkdir(parents=True, exist_ok=True)
    todo = []
    if a is not None and clip in a["runs"]:
        from retarget_cli.io.rig import load_rig

        todo.append(("ict", load_rig(a["glb_yaml"]), a["runs"][clip]))
    for name, rig in (b or {}).get("rigs", {}).items():
        if clip in b["runs"].get(name, {}):
            todo.append((name, rig, b["runs"][name][clip]))
    written, small = [], []
    for name, rig, run in todo:
        video = data / "videos" / f"{clip}.mp4"
        big = rig_picture(name, rig, run, video, refs[clip]["mediapipe"], 256)
        p = outdir / f"{'ict-glb' if name == 'ict' else name}.png"
        cv2.imwrite(str(p), big)
        written.append(p)
        small.append(rig_picture(name, rig, run, video, refs[clip]["mediapipe"], 128))
    if small:
        p = outdir / "rigs.png"
        # 6 bits a channel: the README's picture stays under 300 KB (video frames compress poorly in PNG)
        cv2.imwrite(str(p), np.concatenate(small, axis=0) & 0xFC, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        written.append(p)
    return written


# --------------------------------------------------------------------------- main


def parse_args(argv):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DATA, help="The realdata folder (default ../shared/realdata).")
    ap.add_argument("--videos", default="d3,d9,d12", help="Clips of ../shared/realdata/videos (comma-separated).")
    ap.add_argument("--only", default="ict,valid,godette", help="Rigs: ict (part a), valid, godette (part b).")
    ap.add_argument("--fresh", action="store_true", help="Rerun the documented path (not the references).")
    ap.add_argument("--png", type=Path, default=None, metavar="DIR", help="Write one picture per rig here.")
    args = ap.parse_args(argv)
    args.only = [s for s in args.only.split(",") if s]
    bad = [s for s in args.only if s not in ("ict", *RIGS)]
    if bad:
        ap.error(f"--only: unknown {bad[0]!r}; expected some of ict, {', '.join(RIGS)}")
    args.model = args.data / "peers" / "face_landmarker.task"
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    clips = [c for c in args.videos.split(",") if c]
    why = peer.unavailable(args, clips)
    missing = [args.data / "rigs" / p for n, p in RIGS.items() if n in args.only and not (args.data / "rigs" / p).is_file()]
    if why or missing:
        print(f"SKIP bench/rigs.py: {why or f'{missing[0]} not found (needs ../shared/realdata)'}")
        return 0
    refs = {c: peer.references(args.data / "videos" / f"{c}.mp4") for c in clips}
    print(f"The documented path ({CONFIG.relative_to(ROOT)}, track.init auto, whole clips {', '.join(clips)}) "
          "against MediaPipe Face Mesh 0.10.14.\n")
    a = b = None
    if "ict" in args.only:
        a = part_a(clips, refs, args)
        print("(a) The ICT FaceKit: its OBJs with the shipped map, and the GLB retarget wrote with no landmarks: "
              "(scored on the kit's shipped landmark vertices, as bench/peer.py does):\n")
        print(table_a(a))
        print()
        print("\n".join(verdict_a(a)))
        print()
    if any(n in args.only for n in RIGS):
        b = part_b(clips, refs, args)
        print("(b) The characters given as the rig (no rig.yaml, no map): openings on their own lip and lid vertices "
              "(chosen by hand for the benchmark):\n")
        print(table_b(b))
        print()
        print("\n".join(verdict_b(b)))
    if args.png:
        for p in write_pngs(args.png, a, b, refs, args.data):
            log(f"wrote {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
