"""Benchmark: iris locators tried for :mod:`retarget_cli.methods.tracking.gaze` (issue 28), on the shared clips.

Each clip is tracked as ``bench/gaze_head.py`` does (its cache, ``build/gaze_head``); each eye of each frame is
warped to the gaze module's upright patch and masked to the tracked lids, and each locator below finds the iris
centre in it. Scored as ``bench/gaze_head.py`` scores the gaze: Pearson r of the offset (eye widths, held through
closed eyes) against MediaPipe Face Mesh's iris relative to its corners, on eyes whose reference moves (standard
deviation >= 0.05 eye widths), averaged over the eyes and clips.

Locators: ``centroid`` (the module's: pixels darker than the 40th percentile inside the lids, weighted by the
square of the difference, after a 1-pixel blur), its percentile/power/blur variants, ``two-pass`` (the centroid
again inside a disk of the iris's radius, 0.18-0.26 eye widths, around the first), ``contrast`` (the centroid,
rejected and held when the disk around it is not darker than the rest of the eye by 8 or 15 gray levels),
``disk`` (the darkest disk of radius 0.2 eye widths, a template of the iris), ``eroded`` (the lid mask shrunk by a
pixel: lashes out) and ``rows`` (each row's median taken off: the upper lid's shadow out); then the module's own
(:func:`~retarget_cli.methods.tracking.gaze.iris_centre` in the lid mask grown by 2 patch pixels, the centroid's x
averaged with the limbus's, nearly shut eyes' horizontal readings drawn toward the median,
:func:`~retarget_cli.methods.tracking.gaze.draw_unsure`) and its parts taken away one at a time.

Run: ``python bench/gaze_locators.py [--videos d3,d12]`` (after ``bench/gaze_head.py`` has tracked them, or it
tracks them). Without ``../shared/realdata`` it prints a skip line.
"""

from __future__ import annotations

import argparse
import os
import sys
from functools import partial
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from gaze_head import DATA, MOVES_GAZE, pearson, reference_gaze, track  # noqa: E402


def patches(video: Path, lm):
    """Per frame and eye: the upright patch (H, W) float, its lid mask (as tracked, not grown), the lid gap over
    the eye width."""
    import cv2

    from retarget_cli.methods.tracking import gaze as G

    cap = cv2.VideoCapture(str(video))
    P = lm.points.astype(np.float64)
    out = []
    for t in range(lm.n_frames):
        ok, frame = cap.read()
        if not ok:
            break
        gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        row = []
        for eye in G.EYES_68:
            mid, x, y, w = G.eye_frame(P[t], eye)
            patch, A = G._patch(gray, mid, x, y, w)
            gap = np.mean([np.hypot(*(P[t, a] - P[t, b])) for a, b in zip(eye[2], eye[3])])
            row.append((patch, G._eye_mask(P[t], eye, A, grow=0), gap / max(w, 1e-9)))
        out.append(row)
    return out


def centroid(p, m, perc=40.0, power=2, sigma=1.0):
    import cv2

    if m.sum() < 8:
        return None
    g = cv2.GaussianBlur(p, (0, 0), sigma)[m]
    w = np.maximum(np.percentile(g, perc) - g, 0.0) ** power
    if w.sum() <= 0:
        return None
    yx = np.argwhere(m).astype(np.float64)
    return (yx * w[:, None]).sum(axis=0)[::-1] / w.sum()


def _disk(m, c, r):
    yy, xx = np.mgrid[:m.shape[0], :m.shape[1]]
    return (xx - c[0]) ** 2 + (yy - c[1]) ** 2 <= r * r


def two_pass(p, m, radius):
    from retarget_cli.methods.tracking.gaze import _WIDTH

    c = centroid(p, m)
    if c is None:
        return None
    d = m & _disk(m, c, radius * _WIDTH)
    c2 = centroid(p, d, 50.0) if d.sum() >= 8 else None
    return c if c2 is None else c2


def contrast(p, m, level):
    import cv2

    from retarget_cli.methods.tracking.gaze import _WIDTH

    c = centroid(p, m)
    if c is None:
        return None
    inner, outer = m & _disk(m, c, 0.2 * _WIDTH), m & ~_disk(m, c, 0.24 * _WIDTH)
    if inner.sum() < 5 or outer.sum() < 5:
        return None
    g = cv2.GaussianBlur(p, (0, 0), 1.0)
    return c if np.median(g[outer]) - np.median(g[inner]) >= level else None


def disk(p, m):
    import cv2

    from retarget_cli.methods.tracking.gaze import _WIDTH

    g = cv2.GaussianBlur(p, (0, 0), 1.0)
    R = 0.2 * _WIDTH
    n = int(2 * R) + 3
    k = _disk(np.zeros((n, n)), ((n - 1) / 2, (n - 1) / 2), R).astype(np.float64)
    mm = m.astype(np.float64)
    num = cv2.filter2D(g * mm, -1, k, borderType=cv2.BORDER_CONSTANT)
    den = cv2.filter2D(mm, -1, k, borderType=cv2.BORDER_CONSTANT)
    score = np.where((den > 0.3 * k.sum()) & m, num / np.maximum(den, 1e-9), np.inf)
    if not np.isfinite(score).any():
        return None
    i = np.unravel_index(np.argmin(score), score.shape)
    return np.array([i[1], i[0]], dtype=np.float64)


def eroded(p, m):
    import cv2

    m2 = cv2.erode(m.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    return centroid(p, m2 if m2.sum() >= 8 else m)


def rows(p, m):
    q = p.copy()
    for y in range(p.shape[0]):
        if m[y].sum() > 3:
            q[y] -= np.median(p[y, m[y]]) - np.median(p[m])
    return centroid(q, m)


def grown(m, k=None):
    import cv2

    from retarget_cli.methods.tracking.gaze import _GROW

    k = _GROW if k is None else k
    return cv2.dilate(m.astype(np.uint8), np.ones((2 * k + 1, 2 * k + 1), np.uint8)).astype(bool)


def limbus_alone(p, m):
    """The best-scoring limbus centre anywhere in the grown mask (:func:`limbus_x`'s score, argmax)."""
    import cv2

    from retarget_cli.methods.tracking.gaze import _LIMBUS_RADIUS, _WIDTH, _limbus_kernel

    mm = grown(m)
    g = cv2.GaussianBlur(p, (0, 0), 1.0)
    s = cv2.filter2D(cv2.Sobel(g, cv2.CV_64F, 1, 0, ksize=3) * mm, -1, _limbus_kernel(_LIMBUS_RADIUS * _WIDTH),
                     borderType=cv2.BORDER_CONSTANT)
    s = np.where(mm, s, -np.inf)
    i = np.unravel_index(np.argmax(s), s.shape)
    return np.array([i[1], i[0]], dtype=np.float64)


def module(p, m, k=None, limbus=True):
    from retarget_cli.methods.tracking.gaze import iris_centre

    return iris_centre(p, grown(m, k), limbus=limbus)


#: The module's locator and its parts; the second element: draw nearly shut eyes toward the median (``unsure``).
MODULE = {
    "module: grown mask, centroid + limbus, unsure drawn to the median": (module, True),
    "  same, unsure not drawn": (module, False),
    "  centroid alone (grown mask), unsure drawn": (partial(module, limbus=False), True),
    "  centroid alone (grown mask), unsure not drawn": (partial(module, limbus=False), False),
    "  mask not grown, centroid + limbus, unsure drawn": (partial(module, k=0), True),
    "  mask grown by 1 / 3 px (0.025 / 0.075 widths), unsure drawn": None,
    "  limbus alone (argmax in the grown mask), unsure drawn": (limbus_alone, True),
}

LOCATORS = {
    "centroid": centroid,
    **{f"centroid p{pc} w{pw} blur{sg:g}": partial(centroid, perc=pc, power=pw, sigma=sg)
       for pc in (30, 55) for pw in (1, 3) for sg in (1.0, 2.0)},
    **{f"two-pass r{r:g}": partial(two_pass, radius=r) for r in (0.18, 0.22, 0.26)},
    "contrast 8": lambda p, m: contrast(p, m, 8.0),
    "contrast 15": lambda p, m: contrast(p, m, 15.0),
    "disk": disk,
    "eroded": eroded,
    "rows": rows,
}


def score(locate, eyes, ref, closed: float = 0.12, unsure=False) -> list:
    from retarget_cli.methods.tracking.gaze import _PATCH, _WIDTH, _hold, draw_unsure

    T = len(ref)
    off = np.full((T, 2, 2), np.nan)
    for t in range(T):
        for e, (p, m, opening) in enumerate(eyes[t]):
            if opening < closed:
                continue
            c = locate(p, m)
            if c is not None:
                off[t, e] = (c - np.array(_PATCH, dtype=np.float64) / 2.0) / _WIDTH
    if unsure:
        off = draw_unsure(off, np.array([[o for _, _, o in row] for row in eyes]))
    off = _hold(off)
    return [[pearson(off[:, e, k], ref[:, e, k]) for e in range(2) if np.nanstd(ref[:, e, k]) >= MOVES_GAZE]
            for k in range(2)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--videos", default="d3,d12", help="Clips whose gaze moves (d9's does not, by the reference).")
    args = ap.parse_args(argv)
    if not (DATA / "videos").is_dir():
        print(f"skip: {DATA} not found (real clips)")
        return 0
    from reference import reference_landmarks

    from retarget_cli.io.landmarks import load_landmarks

    clips = []
    for name in args.videos.split(","):
        video = DATA / "videos" / f"{name}.mp4"
        lm = load_landmarks(track(video))
        eyes = patches(video, lm)
        ref = reference_landmarks(video, log=lambda m: None)
        T = min(len(ref["points"]), len(eyes))
        clips.append((name, eyes[:T], reference_gaze(np.asarray(ref["points"], np.float64)[:T])))
    print("| locator | gaze h (mean r) | gaze v (mean r) | " + " | ".join(f"{c[0]} h / v" for c in clips) + " |")
    print("|---|---|---|" + "---|" * len(clips))
    rows = [(name, locate, False) for name, locate in LOCATORS.items()]
    for name, v in MODULE.items():
        if v is None:
            rows += [(f"  mask grown by {k} px, centroid + limbus, unsure drawn", partial(module, k=k), True)
                     for k in (1, 3)]
        else:
            rows.append((name, *v))
    for name, locate, unsure in rows:
        per = [score(locate, eyes, ref, unsure=unsure) for _, eyes, ref in clips]
        h = np.mean([np.mean(s[0]) for s in per if s[0]])
        v = np.mean([np.mean(s[1]) for s in per if s[1]])
        cells = " | ".join(f"{np.mean(s[0]):.2f} / {np.mean(s[1]):.2f}" for s in per)
        print(f"| {name} | {h:.3f} | {v:.3f} | {cells} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
