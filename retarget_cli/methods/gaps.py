"""Gaps in a take: frames where the face is not there, the segments between them, and curves across them.

A real take has moments without a usable face: the actor turns away or walks
out of shot, a hand passes in front, the editor cut two takes together. The
tracker marks each frame found or not (``landmarks.npz``'s ``found``) and
starts a new *segment* after a gap or at a scene cut (an abrupt change of the
whole image), so that later stages smooth each segment on its own and nothing
jumps across a gap. Everything here is arrays in, arrays out:

* :func:`segments` and :func:`segment_ids`: the runs of found frames, split at cuts;
* :func:`describe_gaps`: where each gap is, how long, and why (no face, cut, low confidence);
* :class:`CutDetector`: a scene cut as an abrupt whole-image change between two frames;
* :func:`fill_gaps`: a curve's values in the gap frames per the declared behaviour
  (``hold``, ``ease``, ``omit``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ShapeError

#: Why a frame has no face: the detector found none, or what it found was not trusted.
NO_FACE, LOW_CONFIDENCE = 1, 2
#: Reason of a gap by its frames' status code, and of a zero-length gap at a scene cut.
REASONS = {NO_FACE: "no face", LOW_CONFIDENCE: "low confidence"}
CUT = "cut"

#: Behaviours of curves across a gap (``apply.gaps``): hold the last pose, ease to the rest pose and back,
#: or leave the gap frames out of the exports that can (CSV rows, glTF keys).
GAP_BEHAVIOURS = ("ease", "hold", "omit")

#: Side of the thumbnails :class:`CutDetector` compares, in pixels.
CUT_THUMB = 32
#: A cut changes the picture and its grey levels at once: the mean absolute difference of two consecutive
#: thumbnails (grey levels in 0-1) above :data:`CUT_THRESHOLD` and the total-variation distance of their
#: 16-bin grey histograms above :data:`CUT_HISTOGRAM`. On the three shared clips (talking heads, 512x512)
#: consecutive frames differ by at most 0.078 and 0.056 (d12's fast head turns); a cut from one clip to
#: another by 0.17-0.21 and 0.35-0.51, and to black by 0.42 (thumbnails).
CUT_THRESHOLD = 0.12
CUT_HISTOGRAM = 0.2


def _flag(found, name: str = "found") -> np.ndarray:
    a = np.asarray(found)
    if a.ndim != 1:
        raise ShapeError(f"{name}: expected shape (T,), got {a.shape}")
    return a.astype(bool)


def segments(found, cuts=None) -> list[tuple[int, int]]:
    """Runs of found frames, split where a scene cut starts a frame.

    Parameters
    ----------
    found : array_like of bool, shape (T,)
        The face was found in the frame.
    cuts : array_like of bool, shape (T,), optional
        A scene cut happened just before the frame (it starts a new segment).

    Returns
    -------
    list of (start, stop)
        Half-open frame ranges, in order; each holds found frames only.
    """
    f = _flag(found)
    c = np.zeros(len(f), bool) if cuts is None else _flag(cuts, "cuts")
    if c.shape != f.shape:
        raise ShapeError(f"cuts: expected shape {f.shape} like found, got {c.shape}")
    starts = np.flatnonzero(f & (np.r_[True, ~f[:-1]] | c))
    out = []
    for i, s in enumerate(starts):
        end = starts[i + 1] if i + 1 < len(starts) else len(f)
        lost = np.flatnonzero(~f[s:end])
        out.append((int(s), int(s + lost[0]) if lost.size else int(end)))
    return out


def segment_ids(found, cuts=None) -> np.ndarray:
    """Segment index of every frame (:func:`segments`, in order); -1 in the gaps. Shape (T,), int32."""
    f = _flag(found)
    ids = np.full(len(f), -1, np.int32)
    for i, (a, b) in enumerate(segments(f, cuts)):
        ids[a:b] = i
    return ids


def segments_of(segment) -> list[tuple[int, int]]:
    """The ``(start, stop)`` ranges of a per-frame segment index (T,) (-1: in a gap), in order."""
    s = np.asarray(segment)
    if s.ndim != 1:
        raise ShapeError(f"segment: expected shape (T,), got {s.shape}")
    out = []
    edges = np.flatnonzero(np.diff(s) != 0) + 1
    for a, b in zip(np.r_[0, edges], np.r_[edges, len(s)]):
        if len(s) and s[a] >= 0:
            out.append((int(a), int(b)))
    return out


def describe_gaps(found, status=None, cuts=None, frames=None, fps: float | None = None) -> list[dict]:
    """Every gap of a take: where it starts, how long it lasts and why.

    A gap is a run of frames without a face; its reason is the most common
    status of its frames (``no face`` or ``low confidence``), and ``cut`` is
    true when a scene cut started it. A scene cut between two found frames is
    a gap of length 0 with reason ``cut`` (the segments on either side are
    smoothed apart all the same).

    Parameters
    ----------
    found : array_like of bool, shape (T,)
    status : array_like of int, shape (T,), optional
        Per frame 0 (found), :data:`NO_FACE` or :data:`LOW_CONFIDENCE`; default :data:`NO_FACE` where not found.
    cuts : array_like of bool, shape (T,), optional
    frames : array_like of int, shape (T,), optional
        Source frame number of each row (default the row).
    fps : float, optional
        Adds ``seconds`` to each gap.

    Returns
    -------
    list of dict
        ``{"start", "frames", "reason", "cut"}`` (plus ``"seconds"``), ``start`` a source frame number.
    """
    f = _flag(found)
    T = len(f)
    st = np.where(f, 0, NO_FACE) if status is None else np.asarray(status)
    c = np.zeros(T, bool) if cuts is None else _flag(cuts, "cuts")
    num = np.arange(T) if frames is None else np.asarray(frames)
    if st.shape != (T,) or c.shape != (T,) or num.shape != (T,):
        raise ShapeError(f"status, cuts and frames: expected shape ({T},) like found")
    out = []
    t = 0
    while t < T:
        if f[t]:
            if c[t] and t > 0 and f[t - 1]:
                out.append({"start": int(num[t]), "frames": 0, "reason": CUT, "cut": True})
            t += 1
            continue
        end = t + int(np.argmax(f[t:])) if f[t:].any() else T
        codes, counts = np.unique(st[t:end][st[t:end] > 0], return_counts=True)
        code = int(codes[np.argmax(counts)]) if codes.size else NO_FACE
        out.append({"start": int(num[t]), "frames": int(end - t), "reason": REASONS.get(code, "no face"),
                    "cut": bool(c[t] or (end < T and c[end]))})
        t = end
    if fps:
        for g in out:
            g["seconds"] = round(g["frames"] / float(fps), 3)
    return out


def gap_summary(gaps: list[dict]) -> str:
    """One line for logs and summaries: ``3 gaps (no face 2, cut 1), 95 frames`` or ``no gaps``."""
    if not gaps:
        return "no gaps"
    by = {}
    for g in gaps:
        by[g["reason"]] = by.get(g["reason"], 0) + 1
    kinds = ", ".join(f"{k} {n}" for k, n in sorted(by.items()))
    return f"{len(gaps)} gap{'s' if len(gaps) != 1 else ''} ({kinds}), {sum(g['frames'] for g in gaps)} frames"


class CutDetector:
    """A scene cut: an abrupt change of the whole image between two consecutive frames.

    Each frame is reduced to a :data:`CUT_THUMB`-pixel grey thumbnail (area
    averaging, so noise and small motion wash out) and a 16-bin grey
    histogram; a cut is a mean absolute difference of two consecutive
    thumbnails above *threshold* together with a histogram distance (half the
    L1 distance, in [0, 1]) above *histogram*. A talking head moving its face
    and head changes a few percent of the thumbnail and less of the histogram;
    a cut to another shot, or to black, changes most of both.

    Parameters
    ----------
    threshold, histogram : float
        Default :data:`CUT_THRESHOLD` and :data:`CUT_HISTOGRAM`.
    """

    def __init__(self, threshold: float = CUT_THRESHOLD, histogram: float = CUT_HISTOGRAM):
        self.threshold, self.histogram = float(threshold), float(histogram)
        self._prev = None
        self.last = (0.0, 0.0)

    @staticmethod
    def features(frame) -> tuple[np.ndarray, np.ndarray]:
        """The frame (H, W) or (H, W, 3), uint8, as a (CUT_THUMB, CUT_THUMB) grey thumbnail in [0, 1] and
        its 16-bin grey histogram (16,) summing to 1."""
        import cv2

        g = np.asarray(frame)
        if g.ndim == 3:
            g = cv2.cvtColor(g, cv2.COLOR_BGR2GRAY)
        if g.ndim != 2 or g.size == 0 or g.dtype != np.uint8:
            raise ShapeError(f"frame: expected uint8 (H, W) or (H, W, 3), got {np.asarray(frame).dtype} "
                             f"{np.asarray(frame).shape}")
        small = g
        h, w = g.shape
        n = min(h, w) // (4 * CUT_THUMB)
        if n > 1 and (h % CUT_THUMB or w % CUT_THUMB):
            # OpenCV's area averaging is slow when the ratio is not whole (about 20 ms for a 1080p frame): first
            # reduce by a whole factor n (its fast path; the last h % n rows and w % n columns left out), to a
            # frame still at least 4 times the thumbnail's side
            small = cv2.resize(g[:h - h % n, :w - w % n], (w // n, h // n), interpolation=cv2.INTER_AREA)
        thumb = cv2.resize(small, (CUT_THUMB, CUT_THUMB), interpolation=cv2.INTER_AREA)
        # the 16 bins of gray >> 4 of every 4th pixel, counted by OpenCV (half of numpy's bincount's time on a 1080p
        # frame, which widens every pixel to an int64 first); the same integer counts
        hist = cv2.calcHist([np.ascontiguousarray(g[::4, ::4])], [0], None, [16], [0, 256]).ravel().astype(np.float64)
        return thumb.astype(np.float32) / 255.0, hist / hist.sum()

    def __call__(self, frame, features=None) -> bool:
        """Whether *frame* starts a new shot (False for the first frame); :attr:`last` keeps the two
        differences to the frame before. *features*: :meth:`features` of *frame* when already computed (in
        another thread, say); *frame* is then not read."""
        feats = self.features(frame) if features is None else features
        prev, self._prev = self._prev, feats
        if prev is None:
            self.last = (0.0, 0.0)
            return False
        self.last = (float(np.abs(feats[0] - prev[0]).mean()), float(0.5 * np.abs(feats[1] - prev[1]).sum()))
        return self.last[0] > self.threshold and self.last[1] > self.histogram


@dataclass(frozen=True)
class Coverage:
    """Where a tracker found the face, per frame (what :func:`~retarget_cli.methods.tracking.detect.track_detect`
    returns with ``gaps=True``).

    Attributes
    ----------
    found : ndarray (T,), bool
    status : ndarray (T,), int8
        0 found, :data:`NO_FACE` or :data:`LOW_CONFIDENCE`.
    cuts : ndarray (T,), bool
        A scene cut just before the frame.
    """

    found: np.ndarray
    status: np.ndarray
    cuts: np.ndarray

    @property
    def segment(self) -> np.ndarray:
        """:func:`segment_ids` of the coverage."""
        return segment_ids(self.found, self.cuts)


def _ease(n: int) -> np.ndarray:
    """Smoothstep from 0 to 1 over *n* frames, excluding both ends: shape (n,)."""
    x = np.arange(1, n + 1) / (n + 1)
    return x * x * (3 - 2 * x)


def fill_gaps(values, found, *, behaviour: str = "ease", rest=None, ease_frames: int = 10) -> np.ndarray:
    """A curve's values in the gap frames per the declared behaviour.

    ``hold``: the last found frame's values (the first found frame's before it).
    ``ease``: from the last found pose to *rest* and back to the next found
    pose, each way a smoothstep ``3x² - 2x³`` over *ease_frames* frames (or half
    the gap when it is shorter), *rest* held between; a gap at the start or
    end of the take eases from or to *rest* on its one side. ``omit``: as
    ``hold`` in the values (so every consumer gets finite numbers); the
    exports that can leave frames out do so by the ``found`` flag.

    Parameters
    ----------
    values : array_like, shape (T, E)
        Curves (rig sliders, weights); the values of gap frames are ignored.
    found : array_like of bool, shape (T,)
    behaviour : {"ease", "hold", "omit"}
    rest : array_like, shape (E,), optional
        The rest pose (default zeros: a rig's neutral).
    ease_frames : int
        Frames of each ease.

    Returns
    -------
    ndarray, shape (T, E), float64
        *values* with the gap frames filled; found frames unchanged. Without
        any found frame, *rest* everywhere.
    """
    V = np.array(values, dtype=np.float64)
    if V.ndim != 2:
        raise ShapeError(f"values: expected shape (T, E), got {V.shape}")
    f = _flag(found)
    if f.shape != (len(V),):
        raise ShapeError(f"found: expected shape ({len(V)},) like values, got {f.shape}")
    if behaviour not in GAP_BEHAVIOURS:
        raise ShapeError(f"behaviour: expected one of {', '.join(GAP_BEHAVIOURS)}, got {behaviour!r}")
    r = np.zeros(V.shape[1]) if rest is None else np.asarray(rest, dtype=np.float64).reshape(-1)
    if r.shape != (V.shape[1],):
        raise ShapeError(f"rest: expected shape ({V.shape[1]},), got {r.shape}")
    if not f.any():
        return np.broadcast_to(r, V.shape).copy()
    T = len(V)
    t = 0
    while t < T:
        if f[t]:
            t += 1
            continue
        end = t + int(np.argmax(f[t:])) if f[t:].any() else T
        before = V[t - 1] if t > 0 else None
        after = V[end] if end < T else None
        V[t:end] = _fill_one(end - t, before, after, r, behaviour, int(ease_frames))
        t = end
    return V


def _fill_one(n: int, before, after, rest, behaviour: str, ease_frames: int) -> np.ndarray:
    """The *n* frames of one gap between the poses *before* and *after* (either None at an end of the take)."""
    if behaviour in ("hold", "omit"):
        return np.broadcast_to(before if before is not None else after, (n, len(rest))).copy()
    out = np.broadcast_to(rest, (n, len(rest))).copy()
    both = before is not None and after is not None
    m = max(0, min(ease_frames, n // 2 if both else n))
    if m == 0:
        return out
    s = _ease(m)[:, None]
    if before is not None:
        out[:m] = before + (rest - before) * s
    if after is not None:
        out[n - m:] = rest + (after - rest) * s
    return out
