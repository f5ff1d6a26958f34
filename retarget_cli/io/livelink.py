"""Live Link Face CSV: the take layout of Epic's Live Link Face app, which Blender, Maya, Houdini and Unreal import.

One header line, then one line per frame::

    Timecode,BlendShapeCount,EyeBlinkLeft,...,TongueOut,HeadYaw,HeadPitch,HeadRoll,LeftEyeYaw,...,RightEyeRoll
    00:00:00:00.000,61,0.000000,...

``BlendShapeCount`` is 61: the 52 ARKit blendshape coefficients followed by
the head's yaw, pitch and roll and the two eyes' yaw, pitch and roll (radians; the eyes' from the
tracked gaze, :func:`eye_rotation_from_gaze`). The
``Timecode`` is ``HH:MM:SS:FF.mmm``: hours, minutes, seconds, the frame within
the second at the take's frame rate, and the thousandths of a frame.

Rig sliders map to ARKit columns by name (:func:`arkit_mapping`): case is
ignored and the side may be written ``_L``/``_R``, ``.L``/``.R`` or
``Left``/``Right`` (``eyeBlink_L`` -> ``EyeBlinkLeft``);
``rig.yaml``'s ``names:`` maps the rest (an ARKit column to one slider or to
a list of sliders, averaged). Columns no slider maps to are 0.
"""

from __future__ import annotations

import logging
import math
import re

import numpy as np

from .._validate import closest
from ..errors import InputError, ParameterError, ShapeError

log = logging.getLogger(__name__)

#: The 52 ARKit blendshape columns in Live Link Face's CSV order (which puts Right before Left for
#: JawRight/JawLeft and MouthRight/MouthLeft). Order taken from the LIVE_LINK_FACE_HEADER of the
#: Blender Live Link Face add-on (github.com/nmfisher/blender_livelinkface, bpylivelinkface.py),
#: which reads the app's CSV exports column by column.
ARKIT_SHAPES = (
    "EyeBlinkLeft", "EyeLookDownLeft", "EyeLookInLeft", "EyeLookOutLeft", "EyeLookUpLeft", "EyeSquintLeft",
    "EyeWideLeft", "EyeBlinkRight", "EyeLookDownRight", "EyeLookInRight", "EyeLookOutRight", "EyeLookUpRight",
    "EyeSquintRight", "EyeWideRight", "JawForward", "JawRight", "JawLeft", "JawOpen", "MouthClose", "MouthFunnel",
    "MouthPucker", "MouthRight", "MouthLeft", "MouthSmileLeft", "MouthSmileRight", "MouthFrownLeft",
    "MouthFrownRight", "MouthDimpleLeft", "MouthDimpleRight", "MouthStretchLeft", "MouthStretchRight",
    "MouthRollLower", "MouthRollUpper", "MouthShrugLower", "MouthShrugUpper", "MouthPressLeft", "MouthPressRight",
    "MouthLowerDownLeft", "MouthLowerDownRight", "MouthUpperUpLeft", "MouthUpperUpRight", "BrowDownLeft",
    "BrowDownRight", "BrowInnerUp", "BrowOuterUpLeft", "BrowOuterUpRight", "CheekPuff", "CheekSquintLeft",
    "CheekSquintRight", "NoseSneerLeft", "NoseSneerRight", "TongueOut",
)
#: The nine rotation columns after the blendshapes (radians).
ROTATIONS = ("HeadYaw", "HeadPitch", "HeadRoll", "LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll", "RightEyeYaw",
             "RightEyePitch", "RightEyeRoll")
#: Every column of the file.
COLUMNS = ("Timecode", "BlendShapeCount", *ARKIT_SHAPES, *ROTATIONS)
#: The value of ``BlendShapeCount``: 52 shapes + 9 rotations.
BLENDSHAPE_COUNT = len(ARKIT_SHAPES) + len(ROTATIONS)

_SIDE = re.compile(r"^(.*?)(?:[_.\-\s]?(left|right)|[_.\-\s]([lr]))$", re.IGNORECASE)


def canonical_name(name: str) -> str:
    """A slider or ARKit name reduced for matching: lower case, alphanumerics only, the side spelled out.

    ``eyeBlink_L``, ``EyeBlink.L``, ``eyeblinkLeft`` and ``EyeBlinkLeft`` all give ``eyeblinkleft``;
    ``jawLeft`` stays ``jawleft``.
    """
    m = _SIDE.match(name)
    if m and m.group(1):
        stem, side = m.group(1), (m.group(2) or m.group(3)).lower()
        side = {"l": "left", "r": "right"}.get(side, side)
        name = stem + side
    return re.sub(r"[^0-9a-z]", "", name.lower())


_ARKIT_BY_CANON = {canonical_name(a): a for a in ARKIT_SHAPES}


def check_names_mapping(names, sliders, where: str) -> dict[str, list[str]]:
    """Check ``rig.yaml``'s ``names:`` (ARKit column -> slider or list of sliders).

    Returns
    -------
    dict
        ARKit column (as in :data:`ARKIT_SHAPES`) to the list of slider names it averages.

    Raises
    ------
    InputError
        Naming *where* and the entry: not a mapping, an ARKit name that is not
        one of the 52 columns, or a slider the rig does not have.
    """

    if names is None:
        return {}
    if not isinstance(names, dict):
        raise InputError(f"{where}: expected a mapping of ARKit names to a slider or a list of sliders, "
                         f"got {type(names).__name__}")
    out = {}
    sliders = list(sliders)
    for key, value in names.items():
        col = _ARKIT_BY_CANON.get(canonical_name(str(key)))
        if col is None:
            hint = closest(str(key), ARKIT_SHAPES)
            raise InputError(f"{where}.{key}: not an ARKit blendshape" + (f"; did you mean {hint!r}?" if hint else ""))
        vals = value if isinstance(value, list) else [value]
        if not vals or not all(isinstance(v, str) for v in vals):
            raise InputError(f"{where}.{key}: expected a slider name or a non-empty list of slider names, got {value!r}")
        for v in vals:
            if v not in sliders:
                hint = closest(v, sliders)
                raise InputError(f"{where}.{key}: unknown slider {v!r}" + (f"; did you mean {hint!r}?" if hint else ""))
        out[col] = list(vals)
    return out


def arkit_mapping(sliders, names=None) -> dict[str, list[int]]:
    """Which sliders drive each ARKit column.

    Parameters
    ----------
    sliders : sequence of str, length n
        The rig's slider names.
    names : dict, optional
        Checked ``names:`` (:func:`check_names_mapping`); it wins over the
        automatic match by name.

    Returns
    -------
    dict
        ARKit column to the slider indices whose mean it is; columns with no
        slider are absent.
    """
    sliders = list(sliders)
    index = {s: i for i, s in enumerate(sliders)}
    out: dict[str, list[int]] = {}
    for i, s in enumerate(sliders):
        col = _ARKIT_BY_CANON.get(canonical_name(s))
        if col is not None and col not in out:
            out[col] = [i]
    for col, vals in (names or {}).items():
        out[col] = [index[v] for v in vals]
    return out


def timecode(frame: int, fps: float) -> str:
    """``HH:MM:SS:FF.mmm`` of frame *frame* of a take at *fps* starting at 00:00:00:00.

    ``FF`` is the frame within the second, ``mmm`` the thousandths of a frame
    (0 at integer rates).
    """
    t = frame / fps
    sec = int(math.floor(t + 1e-9))
    milli = int(round((t - sec) * fps * 1000))
    ff, mmm = divmod(milli, 1000)
    h, rem = divmod(sec, 3600)
    m, s = divmod(rem, 60)
    return f"{h:02d}:{m:02d}:{s:02d}:{ff:02d}.{mmm:03d}"


def parse_timecode(text: str, fps: float) -> float:
    """Seconds of a ``HH:MM:SS:FF[.mmm]`` timecode at *fps*.

    Raises
    ------
    ValueError
        If *text* is not a timecode.
    """
    m = re.fullmatch(r"(\d+):(\d{2}):(\d{2}):(\d+)(?:\.(\d+))?", text.strip())
    if m is None:
        raise ParameterError(f"not a HH:MM:SS:FF.mmm timecode: {text!r}")
    h, mi, s, ff = (int(g) for g in m.groups()[:4])
    sub = float("0." + m.group(5)) if m.group(5) else 0.0
    return h * 3600 + mi * 60 + s + (ff + sub) / fps


def livelink_table(curves, sliders, *, names=None, head_rotation=None,
                   eye_rotation=None) -> tuple[np.ndarray, list[str]]:
    """The 61 value columns per frame.

    Parameters
    ----------
    curves : ndarray, shape (T, n)
        Slider values per frame.
    sliders : sequence of str, length n
    names : dict, optional
        Checked ``names:`` mapping (:func:`check_names_mapping`).
    head_rotation : ndarray, shape (T, 3), optional
        Head yaw, pitch, roll in radians; zeros when None.
    eye_rotation : ndarray, shape (T, 6), optional
        LeftEyeYaw, LeftEyePitch, LeftEyeRoll, RightEyeYaw, RightEyePitch, RightEyeRoll in radians
        (:func:`eye_rotation_from_gaze`); zeros when None.

    Returns
    -------
    values : ndarray, shape (T, 61)
        In :data:`COLUMNS` order after ``Timecode`` and ``BlendShapeCount``.
    unmapped : list of str
        ARKit columns no slider maps to (written as 0).
    """
    C = np.asarray(curves, dtype=np.float64)
    if C.ndim != 2 or C.shape[1] != len(sliders):
        raise ShapeError(f"curves: expected shape (T, {len(sliders)}), got {C.shape}")
    T = C.shape[0]
    mapping = arkit_mapping(sliders, names)
    values = np.zeros((T, BLENDSHAPE_COUNT))
    unmapped = []
    for j, col in enumerate(ARKIT_SHAPES):
        if col in mapping:
            values[:, j] = C[:, mapping[col]].mean(axis=1)
        else:
            unmapped.append(col)
    if head_rotation is not None:
        H = np.asarray(head_rotation, dtype=np.float64)
        if H.shape != (T, 3):
            raise ShapeError(f"head_rotation: expected shape ({T}, 3), got {H.shape}")
        values[:, len(ARKIT_SHAPES):len(ARKIT_SHAPES) + 3] = H
    if eye_rotation is not None:
        E = np.asarray(eye_rotation, dtype=np.float64)
        if E.shape != (T, 6):
            raise ShapeError(f"eye_rotation: expected shape ({T}, 6), got {E.shape}")
        values[:, len(ARKIT_SHAPES) + 3:] = E
    return values, unmapped


def livelink_csv(curves, sliders, fps: float, *, names=None, head_rotation=None, frames=None,
                 eye_rotation=None) -> str:
    """A Live Link Face CSV (text) of slider curves; see the module docstring for the layout.

    Parameters are those of :func:`livelink_table`, plus *fps*, the source's
    frame rate (timecodes), and *frames*, each row's source frame number (the
    timecode of row t is ``timecode(frames[t], fps)``; default 0 … T−1).
    Unmapped ARKit columns are listed in one warning.
    """
    if not fps > 0:
        raise ShapeError(f"fps: expected > 0, got {fps}")
    values, unmapped = livelink_table(curves, sliders, names=names, head_rotation=head_rotation,
                                      eye_rotation=eye_rotation)
    if unmapped:
        log.warning("Live Link Face CSV: no rig slider maps to %d ARKit columns (written as 0): %s; "
                    "map them with 'names:' in rig.yaml", len(unmapped), ", ".join(unmapped))
    numbers = range(len(values)) if frames is None else [int(f) for f in frames]
    if len(numbers) != len(values):
        raise ShapeError(f"frames: expected {len(values)} frame numbers, got {len(numbers)}")
    lines = [",".join(COLUMNS)]
    for t, row in enumerate(values):
        cells = [f"{v:.6f}" for v in row]
        lines.append(f"{timecode(numbers[t], fps)},{BLENDSHAPE_COUNT}," + ",".join(c if c != "-0.000000" else "0.000000"
                                                                        for c in cells))
    return "\n".join(lines) + "\n"


def head_rotation_from_similarity(head) -> np.ndarray:
    """Head (yaw, pitch, roll) in radians from the tracked 2D head motion.

    Roll is the rotation of the image-plane similarity (``landmarks.npz``'s
    ``head``), made counter-clockwise-positive as seen by the camera (image y
    points down); yaw and pitch are 0, since the 2D track has no estimate of
    them.

    Parameters
    ----------
    head : ndarray, shape (T, 2, 3)

    Returns
    -------
    ndarray, shape (T, 3)
    """
    A = np.asarray(head, dtype=np.float64)
    if A.ndim != 3 or A.shape[1:] != (2, 3):
        raise ShapeError(f"head: expected shape (T, 2, 3), got {A.shape}")
    out = np.zeros((len(A), 3))
    out[:, 2] = -np.arctan2(A[:, 1, 0], A[:, 0, 0])
    return out


def head_rotation_from_pose(angles) -> np.ndarray:
    """Live Link's HeadYaw, HeadPitch, HeadRoll (radians) from the 3D head pose (``landmarks.npz`` ``head_angles``).

    The columns are radians, as :data:`ROTATIONS` and :func:`head_rotation_from_similarity` write them: yaw > 0
    when the actor turns to their left, pitch > 0 when they look up, and roll counter-clockwise-positive as
    seen by the camera (the sign of :func:`head_rotation_from_similarity`'s roll; ``head_angles``'s roll is
    positive towards the actor's left shoulder, clockwise in the image, so it changes sign).

    Parameters
    ----------
    angles : ndarray, shape (T, 3)
        ``yaw, pitch, roll`` in degrees (:class:`~retarget_cli.methods.tracking.headpose.HeadPose`).

    Returns
    -------
    ndarray, shape (T, 3)
    """
    A = np.asarray(angles, dtype=np.float64)
    if A.ndim != 2 or A.shape[1] != 3:
        raise ShapeError(f"head angles: expected shape (T, 3), got {A.shape}")
    return np.radians(A) * np.array([1.0, 1.0, -1.0])


#: Eyeball radius in eye widths (about 12 mm over a 30 mm eye): an iris offset of *d* eye widths is a turn of
#: ``asin(d / EYEBALL_RADIUS)``.
EYEBALL_RADIUS = 0.4


def eye_rotation_from_gaze(gaze, rest=None) -> np.ndarray:
    """The Live Link eye columns from the tracked gaze (``landmarks.npz``'s ``gaze``), radians.

    Each iris's offset from *rest* (looking ahead), in eye widths, is the eyeball's turn
    ``asin(offset / EYEBALL_RADIUS)`` (clipped at ±90°). The signs are ARKit's face frame (x toward the
    actor's left, y up, z toward the camera, right-handed): yaw > 0 turns the eye toward the actor's left,
    pitch > 0 turns it down. Roll is 0.

    Parameters
    ----------
    gaze : ndarray, shape (T, 2, 2)
        Eye 0 the actor's right (image left), ``[..., 0]`` > 0 toward the image's right, ``[..., 1]`` > 0 down.
    rest : ndarray, shape (2, 2), optional
        The gaze looking ahead (default 0).

    Returns
    -------
    ndarray, shape (T, 6)
        LeftEyeYaw, LeftEyePitch, LeftEyeRoll, RightEyeYaw, RightEyePitch, RightEyeRoll.
    """
    G = np.asarray(gaze, dtype=np.float64)
    if G.ndim != 3 or G.shape[1:] != (2, 2):
        raise ShapeError(f"gaze: expected shape (T, 2, 2), got {G.shape}")
    d = G - (0.0 if rest is None else np.asarray(rest, dtype=np.float64)[None])
    a = np.arcsin(np.clip(d / EYEBALL_RADIUS, -1.0, 1.0))
    out = np.zeros((len(G), 6))
    out[:, 0:2] = a[:, 1]  # the actor's left eye: image right
    out[:, 3:5] = a[:, 0]
    return out


__all__ = ["ARKIT_SHAPES", "BLENDSHAPE_COUNT", "COLUMNS", "EYEBALL_RADIUS", "ROTATIONS", "arkit_mapping",
           "canonical_name", "check_names_mapping", "eye_rotation_from_gaze", "head_rotation_from_pose",
           "head_rotation_from_similarity", "livelink_csv", "livelink_table",
           "parse_timecode", "timecode"]
