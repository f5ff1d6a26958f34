"""The free peer: MediaPipe Face Landmarker's 52 ARKit-named blendshape scores per frame of a video.

Runs inside ``build/bench-venv-mediapipe`` only (mediapipe 0.10.14, numpy < 2; see ``bench/reference``).

Usage: ``python mp_blendshapes.py VIDEO MODEL.task OUT.npz [--start S] [--end E]``. Decodes the video
sequentially, skips the frames before ``S`` (decoded, not given to the model) and gives frames ``S`` ..
``E - 1`` (default: to the last) to a fresh ``FaceLandmarker`` in ``RunningMode.VIDEO`` (timestamps
``frame / fps`` in ms), as a user who starts the peer at frame ``S`` would. Writes:

- ``scores`` float32 (T, 52): the blendshape scores in ``names`` order (NaN where no face was found);
- ``names`` str (52,): MediaPipe's category names (``_neutral``, ``browDownLeft``, ..., ``noseSneerRight``);
- ``matrices`` float32 (T, 4, 4): the facial transformation matrix (NaN where no face);
- ``found`` bool (T,), ``frames`` int64 (T,): the video frame of each row;
- ``fps`` float (the video's), ``frame_size`` int (2,) ``[width, height]``;
- ``seconds``: wall time of the loop over frames S..E-1 (decode, colour conversion, ``detect_for_video``),
  ``fps_wall`` = T / seconds; ``load_seconds``: building the landmarker (not counted in ``fps_wall``);
- ``mediapipe``: the version string.

The file is written to a temporary name and renamed into place.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import cv2
import mediapipe as mp
import numpy as np
from mediapipe.tasks.python import BaseOptions, vision


def landmarker(model: str):
    opts = vision.FaceLandmarkerOptions(base_options=BaseOptions(model_asset_path=model),
                                        running_mode=vision.RunningMode.VIDEO, num_faces=1,
                                        output_face_blendshapes=True, output_facial_transformation_matrixes=True)
    return vision.FaceLandmarker.create_from_options(opts)


def run(video: str, model: str, start: int, end: int | None) -> dict:
    cap = cv2.VideoCapture(video)
    if not cap.isOpened():
        raise SystemExit(f"{video}: cannot open the video")
    fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0) or 30.0
    t0 = time.perf_counter()
    lmk = landmarker(model)
    load = time.perf_counter() - t0
    names, scores, mats, found, frames, size = None, [], [], [], [], None
    i = 0
    while i < start:  # decode and drop the frames before the start, outside the timed loop
        if not cap.grab():
            raise SystemExit(f"{video}: start frame {start} is past the end ({i} frames)")
        i += 1
    t0 = time.perf_counter()
    with lmk:
        while end is None or i < end:
            ok, frame = cap.read()
            if not ok:
                break
            size = frame.shape[1::-1]
            img = mp.Image(image_format=mp.ImageFormat.SRGB, data=cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
            res = lmk.detect_for_video(img, int(round(i * 1000.0 / fps)))
            if res.face_blendshapes:
                cats = res.face_blendshapes[0]
                if names is None:
                    names = [c.category_name for c in cats]
                scores.append(np.array([c.score for c in cats], np.float32))
                mats.append(np.asarray(res.facial_transformation_matrixes[0], np.float32).reshape(4, 4))
                found.append(True)
            else:
                scores.append(None)
                mats.append(np.full((4, 4), np.nan, np.float32))
                found.append(False)
            frames.append(i)
            i += 1
    secs = time.perf_counter() - t0
    cap.release()
    if not frames:
        raise SystemExit(f"{video}: no frames decoded from {start}")
    if names is None:
        raise SystemExit(f"{video}: no face found in frames {start}-{i - 1}")
    n = len(names)
    S = np.stack([s if s is not None else np.full(n, np.nan, np.float32) for s in scores])
    return {"scores": S, "names": np.array(names), "matrices": np.stack(mats), "found": np.array(found, bool),
            "frames": np.array(frames, np.int64), "fps": np.float64(fps), "frame_size": np.array(size, np.int64),
            "seconds": np.float64(secs), "fps_wall": np.float64(len(frames) / secs if secs > 0 else np.nan),
            "load_seconds": np.float64(load), "mediapipe": np.array(mp.__version__)}


def save(out: str, arrays: dict) -> None:
    d = os.path.dirname(os.path.abspath(out))
    os.makedirs(d, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=d, suffix=".npz.tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez_compressed(f, **arrays)
        os.replace(tmp, out)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def main(argv):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("video")
    ap.add_argument("model")
    ap.add_argument("out")
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--end", type=int, default=None)
    a = ap.parse_args(argv)
    res = run(a.video, a.model, a.start, a.end)
    save(a.out, res)
    print(f"{a.out}: frames {res['frames'][0]}-{res['frames'][-1]}, face in {int(res['found'].sum())}, "
          f"{float(res['fps_wall']):.1f} fps")


if __name__ == "__main__":
    main(sys.argv[1:])
