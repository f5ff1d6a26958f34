"""The neutral (rest) frame that ``select``, ``decompose`` and ``auto-pose`` share (``neutral_frame``).

One decision, recorded once: ``select`` resolves ``neutral_frame`` (a frame
given, or ``auto``: the calibration of ``track.neutral`` when the landmarks
carry one, else the rest frame and rest shape found in the take by
:func:`retarget_cli.methods.neutral.find_rest_frame`) and writes it into
``keys.json`` (with the neutral key's landmarks for ``auto``); ``decompose``
and ``auto-pose`` with ``auto`` take what keys.json records, so the three
agree. Without a record (keys from an older
``select``, or ``--no-neutral``) they search the same way among the key
frames every region shares, which gives both the same frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..methods.neutral import find_rest_frame, nearest_frame
from ._common import report_result

log = logging.getLogger(__name__)

#: The value of ``neutral_frame`` that finds the rest pose.
AUTO = "auto"


@dataclass
class Neutral:
    """The neutral key: a frame of the take and, for a calibration, the shape that stands in for its landmarks.

    Attributes
    ----------
    frame : int
        Row of the take (``landmarks.npz``); the key every region keeps.
    shape : ndarray (L, 2) or None
        The neutral key's landmarks (stabilized coordinates of the take): the take's rest shape (the median
        of its calm frames nearest rest) or a calibration's; None: the frame's own landmarks (a frame given).
    confidence : ndarray (L,) or None
        Their confidence (with *shape*).
    record : dict
        ``frame`` (its source frame number: its label in keys.json, weights.npz and targets.yaml), ``row``,
        ``source`` (``given``, ``take``, ``calibration``), ``reason``, for ``take`` ``at_rest``,
        ``measures`` and ``frames`` (those averaged), and ``shape`` and ``confidence`` as lists: what
        keys.json holds; the manifests and the report say it without the arrays.
    """

    frame: int
    shape: np.ndarray | None
    confidence: np.ndarray | None
    record: dict

    @property
    def label(self) -> int:
        """The neutral key's source frame number (``record["frame"]``)."""
        return int(self.record["frame"])

    def landmarks(self, stabilized: np.ndarray) -> np.ndarray:
        """The neutral key's landmarks (L, 2): the calibration's shape, or the frame's own."""
        return np.asarray(stabilized[self.frame] if self.shape is None else self.shape)

    def weights(self, confidence: np.ndarray) -> np.ndarray:
        """The neutral key's landmark confidence (L,)."""
        return np.asarray(confidence[self.frame] if self.confidence is None else self.confidence)


#: Keys of a neutral record that hold arrays (keys.json only; left out of manifests and logs).
ARRAY_KEYS = ("shape", "confidence")


def _source(lm) -> np.ndarray:
    """(T,) int64: the source frame number of each row of *lm*."""
    return lm.timing()[0]


def _given(frame: int, lm, landmarks) -> Neutral:
    """``neutral_frame`` as given: a source frame number (``landmarks.npz`` ``frames``)."""
    src = _source(lm)
    rows = np.flatnonzero(src == frame)
    if not len(rows):
        raise InputError(f"neutral_frame: frame {frame} is not a frame of the take ({landmarks}: {lm.n_frames} "
                         f"frames, source frames {int(src[0])}-{int(src[-1])})")
    row = int(rows[0])
    return Neutral(row, None, None, {"frame": int(frame), "row": row, "source": "given",
                                     "reason": f"frame {frame}: neutral_frame as given"})


def _with_arrays(record: dict, shape: np.ndarray, confidence: np.ndarray) -> dict:
    """*record* with the neutral key's landmarks and confidence as JSON lists (4 decimals)."""
    return {**record, "shape": [[round(float(x), 4), round(float(y), 4)] for x, y in shape],
            "confidence": [round(float(c), 4) for c in confidence]}


def _found(lm, landmarks, candidates=None) -> Neutral:
    """The rest frame of the take and its rest shape (:func:`~retarget_cli.methods.neutral.find_rest_frame`),
    warned about when no frame is at rest."""
    try:
        choice = find_rest_frame(lm.stabilized, lm.confidence, candidates=candidates, numbers=_source(lm))
    except ValueError as exc:
        raise InputError(f"{landmarks}: neutral_frame auto: {exc}") from None
    n = len(choice.members)
    reason = choice.reason + (f"; the neutral key's landmarks are the mean of the {n} calm frames nearest the "
                              "rest shape" if n > 1 else "")
    if not choice.at_rest:
        log.warning("%s: neutral_frame auto: %s", landmarks, reason)
    else:
        log.info("neutral_frame auto: %s", reason)
    src = _source(lm)
    record = {**choice.record(), "frame": int(src[choice.frame]), "row": int(choice.frame), "source": "take",
              "reason": reason, "frames": [int(src[f]) for f in choice.members],
              "rows": [int(f) for f in choice.members]}
    return Neutral(choice.frame, choice.shape, choice.confidence, _with_arrays(record, choice.shape,
                                                                               choice.confidence))


def _calibration(lm, landmarks) -> Neutral:
    """The calibration of ``track.neutral`` as the neutral key, labelled with the take's frame nearest it."""
    row = nearest_frame(lm.stabilized, lm.confidence, lm.neutral)
    frame = int(_source(lm)[row])
    info = lm.meta.get("neutral") if isinstance(lm.meta.get("neutral"), dict) else {}
    what = info.get("file", "the calibration")
    reason = (f"the rest shape of {what} ({info.get('reason', 'tracked like the take')}), aligned to the take; "
              f"it stands in for the landmarks of frame {frame}, the take's frame nearest it")
    log.info("neutral_frame auto: %s", reason)
    shape = np.asarray(lm.neutral, dtype=np.float64)
    conf = np.asarray(lm.neutral_confidence, dtype=np.float64)
    record = {"frame": frame, "row": int(row), "source": "calibration", "file": what, "at_rest": bool(info.get("at_rest", True)),
              "reason": reason}
    return Neutral(int(row), shape, conf, _with_arrays(record, shape, conf))


def summary(record: dict) -> dict:
    """*record* without its arrays (for manifests and reports)."""
    return {k: v for k, v in record.items() if k not in ARRAY_KEYS}


def choose_neutral(neutral_frame, lm, *, landmarks) -> Neutral | None:
    """``select``'s neutral frame: None (no neutral), a frame given, or ``auto`` (calibration, else found).

    Reports the choice for the stage's manifest (``results.neutral``).
    """
    if neutral_frame is None:
        return None
    if neutral_frame == AUTO:
        out = _calibration(lm, landmarks) if lm.neutral is not None else _found(lm, landmarks)
    else:
        out = _given(int(neutral_frame), lm, landmarks)
    report_result("neutral", summary(out.record))
    return out


def shared_key_frames(keys) -> list[int]:
    """The key frames every region of *keys* (:class:`~retarget_cli.io.stagefiles.Keys`) has, as rows."""
    sets = [set(r["rows"]) for r in keys.regions.values()]  # (after Keys.resolve_rows)
    return sorted(set.intersection(*sets)) if sets else []


def _recorded(keys, lm, landmarks) -> Neutral:
    """The neutral keys.json records (its landmarks and confidence when it holds them)."""
    rec = keys.neutral
    if rec.get("row") is None:
        keys.resolve_rows(_source(lm), landmarks)
    frame, row = int(rec["frame"]), int(rec["row"])
    shape = conf = None
    if rec.get("shape") is not None:
        try:
            shape = np.asarray(rec["shape"], dtype=np.float64)
            conf = np.asarray(rec.get("confidence") or np.ones(len(shape)), dtype=np.float64)
        except (TypeError, ValueError):
            shape = None
        if shape is None or shape.shape != (lm.n_points, 2) or conf.shape != (lm.n_points,) or \
                not np.isfinite(shape).all() or not np.isfinite(conf).all():
            raise InputError(f"{keys.path}: neutral.shape must be {lm.n_points} [x, y] pairs (and neutral.confidence "
                             f"{lm.n_points} numbers), one per landmark of {landmarks}")
    log.info("neutral_frame auto: frame %d, as %s records", frame, keys.path)
    return Neutral(row, shape, conf, dict(rec))


def neutral_from_keys(neutral_frame, keys, lm, *, landmarks) -> Neutral:
    """``decompose``'s and ``auto-pose``'s neutral: a frame given, or ``auto``: the one keys.json records.

    Without a record, the rest frame among the key frames every region shares (all frames when they share
    none). Reports the choice for the stage's manifest (``results.neutral``).
    """
    if neutral_frame != AUTO:
        out = _given(int(neutral_frame), lm, landmarks)
    elif keys.neutral is not None:
        out = _recorded(keys, lm, landmarks)
    else:
        shared = shared_key_frames(keys)
        out = _found(lm, landmarks, candidates=shared or None)
        out.record["reason"] += f" ({keys.path} records no neutral frame)"
    report_result("neutral", summary(out.record))
    return out


__all__ = ["ARRAY_KEYS", "AUTO", "Neutral", "choose_neutral", "neutral_from_keys", "shared_key_frames", "summary"]
