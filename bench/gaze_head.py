"""Benchmark: gaze and 3D head pose (issue 28's methods) against MediaPipe, and head pose on known rotations.

Real clips (``../shared/realdata/videos``): each is tracked with ``retarget track --method detect`` (the
documented tracker), then

- gaze (:func:`retarget_cli.methods.tracking.gaze.gaze`): each iris's offset from its eye corners, in eye
  widths, correlated (Pearson r) with MediaPipe Face Mesh's iris centre (points 468/473) relative to its own
  corners (33-133, 362-263), on eyes whose reference gaze moves (standard deviation >= 0.05 eye widths);
  likewise the gaze the pipeline stores (track's landmarks.npz ``gaze``: the same, filtered like the
  landmarks, an unseen eye holding its last seen value); the peer's own gaze (Face Landmarker's
  eyeLookIn/Out/Up/Down scores) is scored against the same reference;
- head pose (:func:`retarget_cli.methods.tracking.headpose.head_pose`, camera-relative, and the pipeline's
  stored ``head_angles``, relative to the line of sight): yaw, pitch, roll against the rotation of Face
  Landmarker's facial transformation matrix, where the reference moves (sd >= 2 degrees).
  That matrix is fitted on the whole face mesh, mouth included, so a strong expression moves it too: a third
  table regresses the reference's own inner-lip gap out of each angle and gives the partial r of the stored
  angles and the reference's (the gap out of both), where what is left still moves by 2 degrees.

Synthetic: the ICT FaceKit's 68 landmark vertices posed at random slider weights (expressions), turned by
known yaw/pitch/roll up to +-30 degrees, projected by a pinhole camera with 1 px noise: the mean angle error.

Run: ``python bench/gaze_head.py [--videos d3,d9,d12]``. Without ``../shared/realdata`` the real part prints
a skip line. Caches under ``build/gaze_head`` (the tracked landmarks.npz, whose stored gaze is the one of the
code that tracked them: delete ``build/gaze_head/*.landmarks.npz`` after changing the gaze locator).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

DATA = ROOT.parent / "shared" / "realdata"
BUILD = ROOT / "build" / "gaze_head"
MOVES_GAZE = 0.05
MOVES_HEAD = 2.0
#: MediaPipe Face Mesh: (left corner in the image, right corner, iris centre) of the actor's right and left eye.
MP_EYES = ((33, 133, 468), (362, 263, 473))
#: MediaPipe Face Mesh: inner lips (upper, lower) and the inner mouth corners.
MP_LIPS = (13, 14, 78, 308)


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def pearson(a, b) -> float:
    ok = np.isfinite(a) & np.isfinite(b)
    return float(np.corrcoef(a[ok], b[ok])[0, 1]) if ok.sum() > 2 and np.std(a[ok]) > 0 else float("nan")


def reference_gaze(points) -> np.ndarray:
    """MediaPipe iris offsets (T, 2, 2) like :class:`~retarget_cli.methods.tracking.gaze.Gaze`'s."""
    out = np.full((len(points), 2, 2), np.nan)
    for e, (lc, rc, ic) in enumerate(MP_EYES):
        L, R, C = points[:, lc], points[:, rc], points[:, ic]
        d = R - L
        w = np.linalg.norm(d, axis=1)
        x = d / w[:, None]
        y = np.stack([-x[:, 1], x[:, 0]], axis=1)
        m = (L + R) / 2
        out[:, e, 0] = np.sum((C - m) * x, axis=1) / w
        out[:, e, 1] = np.sum((C - m) * y, axis=1) / w
    return out


def peer_gaze(scores, names) -> np.ndarray:
    """The peer's eyeLook scores as signed offsets (T, 2, 2): > 0 toward the image's right / down."""
    names = [str(n) for n in names]

    def s(n):
        return scores[:, names.index(n)]

    out = np.zeros((len(scores), 2, 2))
    out[:, 0, 0] = s("eyeLookInRight") - s("eyeLookOutRight")   # actor's right eye looking in = image right
    out[:, 1, 0] = s("eyeLookOutLeft") - s("eyeLookInLeft")
    out[:, 0, 1] = s("eyeLookDownRight") - s("eyeLookUpRight")
    out[:, 1, 1] = s("eyeLookDownLeft") - s("eyeLookUpLeft")
    return out


def matrix_angles(M) -> np.ndarray:
    """Yaw, pitch, roll (degrees, :class:`HeadPose`'s convention) of Face Landmarker's matrices (T, 4, 4)."""
    from retarget_cli.methods.tracking.headpose import rotation_angles

    F = np.diag([1.0, -1.0, -1.0])  # its camera looks down -z with y up; OpenCV's down +z with y down
    return rotation_angles(F @ np.asarray(M, dtype=np.float64)[:, :3, :3] @ F)


def frames_of(video: Path) -> list:
    import cv2

    cap = cv2.VideoCapture(str(video))
    out = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        out.append(f)
    return out


def track(video: Path) -> Path:
    out = BUILD / f"{video.stem}.landmarks.npz"
    if not out.is_file():
        BUILD.mkdir(parents=True, exist_ok=True)
        subprocess.run([sys.executable, "-m", "retarget_cli", "-q", "track", str(video), "--method", "detect",
                        "-o", str(out)], check=True, capture_output=True)
    return out


def peer(video: Path, n: int) -> dict:
    from reference import venv_python

    path = BUILD / f"{video.stem}.peer.npz"
    if not path.is_file():
        cmd = [str(venv_python()), str(HERE / "reference" / "mp_blendshapes.py"), str(video),
               str(DATA / "peers" / "face_landmarker.task"), str(path), "--start", "0", "--end", str(n)]
        subprocess.run(cmd, check=True, capture_output=True)
    with np.load(path) as d:
        return {k: d[k] for k in d.files}


def real_clip(name: str) -> dict:
    from reference import reference_landmarks

    from retarget_cli.io.landmarks import load_landmarks
    from retarget_cli.methods.tracking.gaze import gaze
    from retarget_cli.methods.tracking.headpose import head_pose

    video = DATA / "videos" / f"{name}.mp4"
    lm = load_landmarks(track(video))
    frames = frames_of(video)
    t0 = time.perf_counter()
    g = gaze(frames, lm.points, confidence=lm.confidence)
    t_gaze = time.perf_counter() - t0
    t0 = time.perf_counter()
    hp = head_pose(lm.points, lm.frame_size, confidence=lm.confidence)
    t_head = time.perf_counter() - t0
    ref = reference_landmarks(video, log=log)
    T = min(len(ref["points"]), lm.n_frames)
    G = reference_gaze(np.asarray(ref["points"], np.float64)[:T])
    pr = peer(video, T)
    P = peer_gaze(pr["scores"][:T], pr["names"])
    A = matrix_angles(pr["matrices"][:T])
    row = {"clip": name, "frames": T, "gaze_s": t_gaze, "head_s": t_head}
    for k, axis in enumerate(("h", "v")):
        stored_gaze = None if lm.gaze is None else lm.gaze[:T].astype(np.float64)
        for who, est in (("ours", g.offset[:T]), ("stored", stored_gaze), ("peer", P)):
            if est is None:
                row[f"{who}_{axis}"] = float("nan")
                continue
            rs = [pearson(est[:, e, k], G[:, e, k]) for e in range(2) if np.nanstd(G[:, e, k]) >= MOVES_GAZE]
            row[f"{who}_{axis}"] = float(np.mean(rs)) if rs else float("nan")
    stored = lm.head_angles  # the pipeline's: track's head_angles, relative to the line of sight
    # the matrix is fitted on the whole mesh: the part of each angle that follows the mouth (the reference's own
    # inner-lip gap over its mouth width, regressed out) is expression, not head motion
    R = np.asarray(ref["points"], np.float64)[:T]
    gap = np.linalg.norm(R[:, MP_LIPS[1]] - R[:, MP_LIPS[0]], axis=1) / \
        np.linalg.norm(R[:, MP_LIPS[3]] - R[:, MP_LIPS[2]], axis=1)
    X = np.c_[np.ones(T), gap]
    for k, axis in enumerate(("yaw", "pitch", "roll")):
        moves = np.std(A[:, k]) >= MOVES_HEAD
        row[axis] = pearson(hp.angles[:T, k], A[:, k]) if moves else float("nan")
        row[f"{axis}_stored"] = pearson(stored[:T, k].astype(np.float64), A[:, k]) \
            if moves and stored is not None else float("nan")
        row[f"{axis}_sd"] = float(np.std(A[:, k]))
        free = A[:, k] - X @ np.linalg.lstsq(X, A[:, k], rcond=None)[0]
        row[f"{axis}_mouth_r"] = pearson(A[:, k], gap)
        row[f"{axis}_free_sd"] = float(np.std(free))
        row[f"{axis}_free_stored"] = float("nan")
        if np.std(free) >= MOVES_HEAD and stored is not None:  # partial r: the lip gap out of both
            h = stored[:T, k].astype(np.float64)
            row[f"{axis}_free_stored"] = pearson(h - X @ np.linalg.lstsq(X, h, rcond=None)[0], free)
    return row


def synthetic(n: int = 400, seed: int = 0) -> dict:
    """Mean angle error on the ICT's landmark vertices with expressions, turned by known angles."""
    import tarfile
    import tempfile

    import yaml

    from retarget_cli.io.rig import load_rig
    from retarget_cli.methods.tracking.headpose import angles_rotation, camera_matrix, head_pose

    tar = ROOT / "sample_data" / "ict" / "ict-facekit-rig.tar.xz"
    rig_dir = BUILD / "ict-facekit"
    if not (rig_dir / "rig.yaml").is_file():
        BUILD.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=BUILD) as tmp, tarfile.open(tar) as tf:
            tf.extractall(tmp, filter="data")
            (Path(tmp) / "ict-facekit" / "rig.yaml").write_text((ROOT / "sample_data" / "ict" / "rig.yaml").read_text())
            os.replace(Path(tmp) / "ict-facekit", rig_dir)
    rig = load_rig(rig_dir / "rig.yaml")
    ids = np.asarray(yaml.safe_load((rig_dir / "rig.yaml").read_text())["landmarks"])
    rng = np.random.default_rng(seed)
    W = rng.uniform(0, 1, size=(n, rig.n_sliders)) * (rng.uniform(size=(n, rig.n_sliders)) < 0.08)
    X = np.stack([rig.evaluate(w)[ids] for w in W])                       # (n, 68, 3), y up, z to the viewer
    X = X * np.array([1.0, -1.0, -1.0])                                   # OpenCV camera axes
    X -= X[:, [36, 39, 42, 45]].mean(axis=1, keepdims=True)
    true = rng.uniform(-30, 30, size=(n, 3)) * np.array([1.0, 1.0, 0.5])
    K = camera_matrix((1280, 720))
    Y = np.einsum("nij,nlj->nli", angles_rotation(true), X) + np.array([0.0, 0.0, 60.0])
    p = Y @ K.T
    pts = p[..., :2] / p[..., 2:] + rng.normal(0, 1.0, size=(n, 68, 2))
    est = np.concatenate([head_pose(pts[i:i + 1], (1280, 720)).angles for i in range(n)])
    err = np.abs(est - true)
    return {"frames": n, "mean": err.mean(axis=0), "p95": np.percentile(err, 95, axis=0)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--videos", default="d3,d9,d12")
    args = ap.parse_args(argv)
    s = synthetic()
    print("## Head pose on known rotations (ICT landmark vertices with expressions, 1 px noise)\n")
    print(f"{s['frames']} poses, yaw/pitch up to +-30 deg, roll +-15: mean error yaw {s['mean'][0]:.2f}, pitch "
          f"{s['mean'][1]:.2f}, roll {s['mean'][2]:.2f} deg (95th percentile {s['p95'][0]:.2f} / {s['p95'][1]:.2f} / "
          f"{s['p95'][2]:.2f})\n")
    if not (DATA / "videos").is_dir():
        print(f"skip: {DATA} not found (real clips)")
        return 0
    rows = [real_clip(v) for v in args.videos.split(",")]
    print("## Real clips against MediaPipe (Pearson r; '-' where the reference does not move)\n")
    print("| clip | frames | gaze h ours | gaze h stored | gaze h peer | gaze v ours | gaze v stored | gaze v peer | "
          "yaw | pitch | roll | head sd yaw/pitch/roll | gaze + head s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")

    def f(x):
        return "-" if not np.isfinite(x) else f"{x:.2f}"

    for r in rows:
        print(f"| {r['clip']} | {r['frames']} | {f(r['ours_h'])} | {f(r['stored_h'])} | {f(r['peer_h'])} | "
              f"{f(r['ours_v'])} | {f(r['stored_v'])} | {f(r['peer_v'])} | {f(r['yaw'])} | {f(r['pitch'])} | "
              f"{f(r['roll'])} | {r['yaw_sd']:.1f} / {r['pitch_sd']:.1f} / {r['roll_sd']:.1f} | "
              f"{r['gaze_s'] + r['head_s']:.1f} |")
    print("\n## Head pose stored by the pipeline (track's landmarks.npz head_angles, relative to the line of sight) "
          "against MediaPipe (Pearson r; '-' where the reference does not move)\n")
    print("| clip | yaw | pitch | roll | reference sd yaw/pitch/roll |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['clip']} | {f(r['yaw_stored'])} | {f(r['pitch_stored'])} | {f(r['roll_stored'])} | "
              f"{r['yaw_sd']:.1f} / {r['pitch_sd']:.1f} / {r['roll_sd']:.1f} |")
    print("\n## The reference's head angles with the mouth regressed out (its inner-lip gap; the matrix is fitted on "
          "the whole mesh, so an opening mouth moves it): r of each angle with the lip gap, the sd left, and the partial "
          "r of the stored angle and the reference's with the lip gap out of both ('-' where the reference's left moves "
          "by less than the threshold)\n")
    print("| clip | r with the mouth yaw/pitch/roll | sd left yaw/pitch/roll | partial r, stored: yaw | pitch | roll |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['clip']} | {r['yaw_mouth_r']:.2f} / {r['pitch_mouth_r']:.2f} / {r['roll_mouth_r']:.2f} | "
              f"{r['yaw_free_sd']:.1f} / {r['pitch_free_sd']:.1f} / {r['roll_free_sd']:.1f} | "
              f"{f(r['yaw_free_stored'])} | {f(r['pitch_free_stored'])} | {f(r['roll_free_stored'])} |")
    for key in ("ours_h", "stored_h", "peer_h", "ours_v", "stored_v", "peer_v", "yaw", "pitch", "roll", "yaw_stored",
                "pitch_stored", "roll_stored"):
        vals = [r[key] for r in rows if np.isfinite(r[key])]
        print(f"mean {key}: {np.mean(vals):.3f} over {len(vals)} clips" if vals else f"mean {key}: -")
    return 0


if __name__ == "__main__":
    sys.exit(main())
