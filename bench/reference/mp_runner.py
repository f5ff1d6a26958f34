"""Per-frame MediaPipe Face Mesh landmarks of a video (runs inside build/bench-venv-mediapipe only).

Usage: ``python mp_runner.py VIDEO OUT.npz``. Writes ``points`` float32 (T, 478, 2) in image pixels
(MediaPipe's normalised coordinates times the frame width and height; NaN where no face was found),
``found`` bool (T,), ``fps`` float, ``frame_size`` int (2,) = [width, height] and ``mediapipe`` (the
version string). Uses the legacy ``mp.solutions.face_mesh`` graph, whose models
(face_detection_short_range.tflite, face_landmark_with_attention.tflite) ship inside the wheel, so
nothing is downloaded at run time. The file is written to a temporary name and renamed into place.

This is the benchmark's independent reference: it never feeds the retarget pipeline, and mediapipe
(which needs numpy < 2) is never a dependency of the project.
"""

from __future__ import annotations

import os
import sys
import tempfile

import cv2
import mediapipe as mp
import numpy as np


def track(video: str):
    cap = cv2.VideoCapture(video)
    if not cap.isOpened():
        raise SystemExit(f"{video}: cannot open the video")
    fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    pts, found, size = [], [], None
    with mp.solutions.face_mesh.FaceMesh(static_image_mode=False, refine_landmarks=True, max_num_faces=1,
                                         min_detection_confidence=0.5, min_tracking_confidence=0.5) as fm:
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            h, w = frame.shape[:2]
            size = (w, h)
            res = fm.process(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
            if res.multi_face_landmarks:
                lm = res.multi_face_landmarks[0].landmark
                p = np.array([[q.x * w, q.y * h] for q in lm], dtype=np.float32)
                found.append(True)
            else:
                p = np.full((478, 2), np.nan, dtype=np.float32)
                found.append(False)
            pts.append(p)
    cap.release()
    if not pts:
        raise SystemExit(f"{video}: no frames decoded")
    return np.stack(pts), np.array(found, dtype=bool), fps, np.array(size, dtype=np.int64)


def main(argv):
    if len(argv) != 2:
        raise SystemExit("usage: mp_runner.py VIDEO OUT.npz")
    video, out = argv
    points, found, fps, size = track(video)
    d = os.path.dirname(os.path.abspath(out))
    os.makedirs(d, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=d, suffix=".npz.tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez_compressed(f, points=points, found=found, fps=np.float64(fps), frame_size=size,
                                mediapipe=np.array(mp.__version__))
        os.replace(tmp, out)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    print(f"{out}: {len(found)} frames, face found in {int(found.sum())}")


if __name__ == "__main__":
    main(sys.argv[1:])
