"""The actor's rest pose in a take, found rather than assumed (``neutral_frame: auto``).

The delta formulation reads every frame relative to a neutral key S_0
(Lewis et al. 2005, §3; the neutral key of Chuang & Bregler 2002, §4.2 is
kept among the keys), and the delta auto-pose fit poses the rig at rest
there. A neutral that is not at rest leaks its expression into every frame
with the opposite sign: on a clip whose actor smiles in frame 0 the character
frowns and pouts for the whole take (issue 27). :func:`find_rest_frame` picks
the frame of the take where the face is nearest rest:

1. **usable frames**: every landmark finite, and a mean confidence at least
   :data:`MIN_CONFIDENCE_FRACTION` of the take's median;
2. **calm frames** (68-point layout): the lips closed, as far as this take
   closes them (the inner-lip gap within :data:`LIP_BAND` mouth widths of its
   2nd percentile), both eyes open (each eye's opening at least
   :data:`EYE_OPEN_FRACTION` of its 90th percentile), and the mouth no
   wider than :data:`MOUTH_WIDE` above the take's median mouth width (a
   closed-lip smile closes the lips too: held for most of the closed-lip
   frames, it would otherwise be the mode below; dropped when no closed-lip
   frame is that narrow);
3. **the rest shape**: the per-landmark median of the calm frames, moved
   towards the mode of their distribution by :data:`MODE_ITERATIONS` rounds
   of taking the median of the nearest :data:`MODE_KEEP` of them (so that a
   smile held for a third of the calm frames does not pull it); the mean of
   the nearest :data:`AVERAGED` of them (at least :data:`MIN_MEMBERS`) is the
   neutral key's landmarks (a single frame would carry its tracking noise
   into every frame of a delta fit);
4. **the frame**: the calm frame whose landmarks, per region (brows and
   eyes; mouth), are nearest that shape, each region's distance in units of
   its median over the calm frames, summed in squares and averaged over
   :data:`HOLD` frames centred on it (a pose held, not a frame passed
   through).

With another layout there are no lips or eyes to test: every usable frame is
calm and the whole face is one region. When no frame has the lips closed
(:data:`LIPS_CLOSED` mouth widths) the take has no rest frame: the least
expressive frame is chosen all the same, and :attr:`RestChoice.at_rest` is
False so the caller warns.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .tracking.head import apply_similarity, default_rigid_points, fit_similarity

#: Frames whose mean landmark confidence is below this fraction of the take's median are not candidates.
MIN_CONFIDENCE_FRACTION = 0.5
#: Lips count as closed within this many mouth widths of the take's smallest inner-lip gap (its 2nd percentile).
LIP_BAND = 0.02
#: An inner-lip gap (mouth widths) above which the lips are parted: the take has no rest frame when even the
#: chosen frame's is larger.
LIPS_CLOSED = 0.05
#: An eye counts as open when its opening is at least this fraction of its 90th percentile over the take.
EYE_OPEN_FRACTION = 0.7
#: A calm frame's mouth (corner to corner) is at most this fraction wider than the take's median mouth width
#: over its usable frames: wider is a smile, even with the lips closed (issue 33, d9 after a cut).
MOUTH_WIDE = 0.12
#: Rounds of moving the rest shape towards the mode, and the fraction of the calm frames (the nearest) whose
#: median it is after each round.
MODE_ITERATIONS = 3
MODE_KEEP = 0.5
#: The neutral key's landmarks are the mean of this fraction of the calm frames nearest the rest shape (at
#: least MIN_MEMBERS of them).
AVERAGED = 0.25
MIN_MEMBERS = 5
#: Frames over which the distance from the rest shape is averaged (odd; a held pose, not a passing frame).
HOLD = 5

#: 68-point (Multi-PIE / iBUG) landmarks of the measures, 0-based.
_LIP_UPPER, _LIP_LOWER, _MOUTH_CORNERS = (61, 62, 63), (67, 66, 65), (48, 54)
_EYES = (((37, 38), (41, 40), 36, 39), ((43, 44), (47, 46), 42, 45))
#: The regions whose distances from the rest shape are summed (68 points): brows and eyes; the lips.
REGIONS_68 = {"brows-eyes": tuple(range(17, 27)) + tuple(range(36, 48)), "mouth": tuple(range(48, 68))}


@dataclass
class RestChoice:
    """The frame :func:`find_rest_frame` chose, and why.

    Attributes
    ----------
    frame : int
        Row of the take.
    at_rest : bool
        False when no frame of the take is at rest (the lips are parted even
        in the chosen frame): the least expressive frame was taken instead.
    reason : str
        One sentence for the manifest, the report and the log.
    measures : dict
        ``lip_gap`` and ``eye_open`` (left, right) at the chosen frame (68
        points), ``calm`` and ``usable`` frame counts, ``distance`` (the
        frame's summed squared region distance, in units of the calm frames'
        median; about the number of regions for a typical calm frame),
        ``averaged`` (how many frames the rest shape is the median of).
    shape : ndarray (L, 2), float64
        The take's rest shape: the per-landmark median of the calm frames
        nearest it (*members*), in the stabilized coordinates given. A single
        frame carries its tracking noise into every frame of a delta fit; the
        median of the frames held at rest does not.
    confidence : ndarray (L,), float64
        The median confidence of those frames (1 without confidences).
    members : ndarray of int
        The frames whose median *shape* is.
    """

    frame: int
    at_rest: bool
    reason: str
    measures: dict = field(default_factory=dict)
    shape: np.ndarray | None = None
    confidence: np.ndarray | None = None
    members: np.ndarray | None = None

    def record(self) -> dict:
        """A JSON-ready summary (``keys.json``, manifests)."""
        return {"frame": int(self.frame), "at_rest": bool(self.at_rest), "reason": self.reason,
                "measures": {k: _round(v) for k, v in self.measures.items()}}


def _round(v):
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_round(x) for x in v]
    if isinstance(v, (float, np.floating)):
        return float(f"{float(v):.4g}")
    return int(v) if isinstance(v, (np.integer,)) else v


def _signed_gap(P: np.ndarray, upper, lower, a: int, b: int) -> np.ndarray:
    """Mean signed gap of *lower* below *upper*, normal to the line from corner *a* to *b*, over its length.

    Parameters
    ----------
    P : ndarray (T, L, 2), float64
        Image-like points (y down).

    Returns
    -------
    ndarray (T,), float64
        Positive when open; negative when the lower points cross above the upper ones.
    """
    d = P[:, b] - P[:, a]
    width = np.linalg.norm(d, axis=1)
    n = np.stack([-d[:, 1], d[:, 0]], axis=1) / np.maximum(width, 1e-12)[:, None]
    gap = np.einsum("tkc,tc->tk", P[:, list(lower)] - P[:, list(upper)], n).mean(axis=1)
    return gap / np.maximum(width, 1e-12)


def face_openings(points) -> dict:
    """Lip gap and eye openings of 68-point landmarks (Multi-PIE / iBUG layout).

    Parameters
    ----------
    points : array_like (T, 68, 2)
        Image-like coordinates (x right, y down), e.g. the stabilized landmarks.

    Returns
    -------
    dict of ndarray (T,), float64
        ``lip_gap``: the inner-lip gap (61-67, 62-66, 63-65) over the mouth
        width (48-54); ``eye_l``, ``eye_r``: each eye's lid gap over its width
        (the image's left eye first).
    """
    P = np.asarray(points, dtype=np.float64)
    out = {"lip_gap": _signed_gap(P, _LIP_UPPER, _LIP_LOWER, *_MOUTH_CORNERS)}
    for name, (up, low, a, b) in zip(("eye_l", "eye_r"), _EYES):
        out[name] = _signed_gap(P, up, low, a, b)
    return out


def _usable(P: np.ndarray, confidence) -> np.ndarray:
    """Frames with every landmark finite and a mean confidence of at least MIN_CONFIDENCE_FRACTION of the median."""
    ok = np.isfinite(P).all(axis=(1, 2))
    if confidence is not None:
        c = np.where(np.isfinite(confidence), confidence, 0.0).mean(axis=1)
        if ok.any():
            ok &= c >= MIN_CONFIDENCE_FRACTION * np.median(c[ok])
    return ok


def _calm(openings: dict, usable: np.ndarray, width: np.ndarray | None = None) -> np.ndarray:
    """Usable frames with the lips closed (as far as the take closes them), both eyes open and, given the mouth
    *width* (T,), the mouth no wider than MOUTH_WIDE above its median over the usable frames (unless that
    leaves no frame)."""
    gap = openings["lip_gap"]
    calm = usable & (gap <= np.percentile(gap[usable], 2) + LIP_BAND)
    for eye in ("eye_l", "eye_r"):
        e = openings[eye]
        calm &= e >= EYE_OPEN_FRACTION * np.percentile(e[usable], 90)
    if width is not None:
        narrow = calm & (width <= (1.0 + MOUTH_WIDE) * np.median(width[usable]))
        if narrow.any():
            calm = narrow
    return calm


def _distances(P: np.ndarray, centre: np.ndarray, regions, calm: np.ndarray) -> np.ndarray:
    """Sum over *regions* of the squared RMS landmark distance from *centre*, each in units of its calm median."""
    z = np.zeros(len(P))
    for idx in regions:
        d = np.sqrt(((P[:, idx] - centre[idx]) ** 2).sum(-1).mean(-1))
        scale = np.median(d[calm])
        z += (d / (scale if scale > 0 else 1.0)) ** 2
    return z


def _held(z: np.ndarray, usable: np.ndarray, hold: int) -> np.ndarray:
    """*z* averaged over *hold* frames centred on each frame (usable frames only; edges use what there is)."""
    if hold <= 1:
        return z
    h = hold // 2
    v = np.where(usable, z, 0.0)
    w = usable.astype(np.float64)
    kernel = np.ones(2 * h + 1)
    num, den = np.convolve(v, kernel, "same"), np.convolve(w, kernel, "same")
    return np.where(den > 0, num / np.maximum(den, 1e-12), np.inf)


@dataclass
class RestShape:
    """The take's rest shape and every frame's distance from it (:func:`rest_shape`).

    Attributes
    ----------
    distance : ndarray (T,), float64
        Each frame's held distance (step 4); ``inf`` where unusable.
    calm, usable : ndarray (T,), bool
        The candidate frames (steps 1-2; every usable frame without the 68-point measures or when none is
        calm) and the usable ones.
    members : ndarray (T,), bool
        The calm frames nearest the rest shape in the last round of step 3: the shape is their median.
    openings : dict
        :func:`face_openings` of the take (empty without 68 points).
    """

    distance: np.ndarray
    calm: np.ndarray
    usable: np.ndarray
    members: np.ndarray
    openings: dict


def rest_shape(stabilized, confidence=None) -> RestShape:
    """The take's rest shape and every frame's distance from it (steps 1-4 of the module docstring).

    Parameters
    ----------
    stabilized : array_like (T, L, 2)
        Landmarks with the head motion removed.
    confidence : array_like (T, L), optional

    Returns
    -------
    RestShape
    """
    P = np.asarray(stabilized, dtype=np.float64)
    if P.ndim != 3 or P.shape[2] != 2 or len(P) == 0:
        raise ValueError(f"stabilized: expected shape (T, L, 2) with T >= 1, got {P.shape}")
    conf = None if confidence is None else np.asarray(confidence, dtype=np.float64)
    if conf is not None and conf.shape != P.shape[:2]:
        raise ValueError(f"confidence: expected shape {P.shape[:2]}, got {conf.shape}")
    usable = _usable(P, conf)
    if not usable.any():
        raise ValueError("no frame has every landmark finite")
    Q = np.where(np.isfinite(P), P, 0.0)
    T, L = P.shape[:2]
    del P, conf  # a long take: one (T, L, 2) float64 copy held below, scaled in place
    iod = np.median(np.linalg.norm(Q[usable, 36] - Q[usable, 45], axis=1)) if L == 68 else \
        np.median(np.ptp(Q[usable], axis=1).max(axis=1))
    Q /= iod if iod > 0 else 1.0
    if L == 68:
        openings = face_openings(Q)
        calm = _calm(openings, usable, np.linalg.norm(Q[:, _MOUTH_CORNERS[1]] - Q[:, _MOUTH_CORNERS[0]], axis=1))
        regions = [list(r) for r in REGIONS_68.values()]
    else:
        openings, calm, regions = {}, usable.copy(), [list(range(L))]
    if not calm.any():
        calm = usable.copy()
    members = calm
    for _ in range(MODE_ITERATIONS):  # (the members' copy partitioned in place: the same medians, one copy)
        z = _distances(Q, np.median(Q[members], axis=0, overwrite_input=True), regions, calm)
        nearer = calm & (z <= np.quantile(z[calm], MODE_KEEP))
        if nearer.sum() < MIN_MEMBERS:
            break
        members = nearer
    z = _distances(Q, np.median(Q[members], axis=0, overwrite_input=True), regions, calm)
    order = np.flatnonzero(calm)[np.argsort(z[calm], kind="stable")]
    members = np.zeros(T, bool)
    members[order[:max(MIN_MEMBERS, int(round(AVERAGED * len(order))))]] = True
    z = np.where(usable, z, np.inf)
    return RestShape(_held(z, usable, HOLD), calm, usable, members, openings)


def find_rest_frame(stabilized, confidence=None, *, candidates=None, numbers=None) -> RestChoice:
    """The frame of the take where the actor's face is nearest rest, and the take's rest shape
    (see the module docstring).

    Parameters
    ----------
    stabilized : array_like (T, L, 2)
        Landmarks with the head motion removed (``landmarks.npz``'s ``stabilized``).
    confidence : array_like (T, L), optional
        Per-landmark tracking confidence in [0, 1].
    candidates : sequence of int, optional
        Restrict the choice to these frames (e.g. the key frames every region
        shares); the rest shape is still that of the whole take.
    numbers : array_like (T,) of int, optional
        Each row's source frame number, to name the frame in the reason (default: the row).

    Returns
    -------
    RestChoice

    Raises
    ------
    ValueError
        For arrays of the wrong shape, no usable frame, or no usable candidate.
    """
    rs = rest_shape(stabilized, confidence)
    dist, calm, usable, openings = rs.distance, rs.calm, rs.usable, rs.openings
    T = len(dist)
    allowed = np.zeros(T, bool)
    if candidates is None:
        allowed[:] = True
    else:
        idx = np.asarray(list(candidates), dtype=np.int64)
        if idx.size == 0 or idx.min() < 0 or idx.max() >= T:
            raise ValueError(f"candidates: expected frames in [0, {T}), got {list(idx)[:8]}")
        allowed[idx] = True
    pick_from = allowed & calm & usable
    if not pick_from.any():
        pick_from = allowed & usable
    if not pick_from.any():
        raise ValueError("no candidate frame has every landmark finite")
    frame = int(np.argmin(np.where(pick_from, dist, np.inf)))
    P = np.asarray(stabilized, dtype=np.float64)
    members = np.flatnonzero(rs.members)
    shape = P[members].mean(axis=0)
    conf = np.ones(P.shape[1]) if confidence is None else \
        np.median(np.asarray(confidence, dtype=np.float64)[members], axis=0)
    measures = {"usable": int(usable.sum()), "calm": int(calm.sum()), "distance": float(dist[frame]),
                "averaged": int(members.size)}
    label = frame if numbers is None else int(np.asarray(numbers)[frame])
    if not openings:
        return RestChoice(frame, True, f"frame {label}: the usable frame nearest the take's most common shape "
                                       f"({int(usable.sum())} of {T} frames usable; no lips or eyes to test "
                                       "without the 68-point layout)", measures, shape, conf, members)
    gap, el, er = (float(openings[k][frame]) for k in ("lip_gap", "eye_l", "eye_r"))
    measures.update(lip_gap=gap, eye_open=[el, er])
    at_rest = gap <= LIPS_CLOSED
    where = "" if candidates is None else f" among {int(allowed.sum())} candidate frames"
    if at_rest:
        reason = (f"frame {label}: lips closed (gap {gap:.3f} of the mouth width) and eyes open "
                  f"({el:.2f}, {er:.2f} of their widths), nearest the take's rest shape{where} "
                  f"({int(calm.sum())} of {T} frames had closed lips and open eyes)")
    else:
        reason = (f"frame {label}: no frame of the take has the lips closed; the least expressive frame{where} "
                  f"(lip gap {gap:.3f} of the mouth width, eyes {el:.2f}, {er:.2f}): the character's lips "
                  "stay closed where the actor's are this open")
    return RestChoice(frame, bool(at_rest), reason, measures, shape, conf, members)


def nearest_frame(stabilized, confidence, shape) -> int:
    """The usable frame of the take nearest *shape* (regions as in :func:`find_rest_frame`, each in units of its
    median distance over the usable frames).

    Parameters
    ----------
    stabilized : array_like (T, L, 2)
    confidence : array_like (T, L) or None
    shape : array_like (L, 2)
        In the take's stabilized coordinates (:func:`align_shape`).

    Returns
    -------
    int
    """
    P = np.asarray(stabilized, dtype=np.float64)
    S = np.asarray(shape, dtype=np.float64)
    if S.shape != P.shape[1:]:
        raise ValueError(f"shape: expected {P.shape[1:]}, got {S.shape}")
    usable = _usable(P, None if confidence is None else np.asarray(confidence, dtype=np.float64))
    if not usable.any():
        raise ValueError("no frame has every landmark finite")
    regions = [list(r) for r in REGIONS_68.values()] if P.shape[1] == 68 else [list(range(P.shape[1]))]
    z = _distances(np.where(np.isfinite(P), P, 0.0), S, regions, usable)
    return int(np.argmin(np.where(usable, z, np.inf)))


def align_shape(shape, reference, *, rigid_points=None) -> np.ndarray:
    """Map a rest shape from another recording into a take's stabilized coordinates.

    A similarity (:func:`retarget_cli.methods.tracking.head.fit_similarity`) fitted on the rigid
    landmarks (eye corners and nose for 68 points) takes *shape* onto *reference*, so a calibration
    filmed at another distance or angle in the image plane lines up with the take.

    Parameters
    ----------
    shape : array_like (L, 2)
        The calibration's rest shape (its own stabilized coordinates).
    reference : array_like (L, 2)
        The take's stabilized shape to align to (e.g. its per-landmark median).
    rigid_points : sequence of int, optional
        Default :func:`retarget_cli.methods.tracking.head.default_rigid_points`.

    Returns
    -------
    ndarray (L, 2), float64
    """
    S = np.asarray(shape, dtype=np.float64)
    R = np.asarray(reference, dtype=np.float64)
    if S.shape != R.shape or S.ndim != 2 or S.shape[1] != 2:
        raise ValueError(f"shape, reference: expected two (L, 2) arrays of one shape, got {S.shape} and {R.shape}")
    rigid = default_rigid_points(len(S)) if rigid_points is None else np.asarray(rigid_points, dtype=np.int64)
    head = fit_similarity(S[rigid], R[rigid][None])
    return apply_similarity(head, S[None])[0]


__all__ = ["AVERAGED", "EYE_OPEN_FRACTION", "HOLD", "LIPS_CLOSED", "LIP_BAND", "MIN_CONFIDENCE_FRACTION", "MIN_MEMBERS", "MODE_ITERATIONS", "MOUTH_WIDE",
           "MODE_KEEP", "REGIONS_68", "RestChoice", "RestShape", "align_shape", "face_openings", "find_rest_frame",
           "nearest_frame", "rest_shape"]
