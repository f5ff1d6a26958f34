"""Gaze on a rig: the iris offsets of :mod:`retarget_cli.methods.tracking.gaze` as the rig's gaze sliders.

The actor's gaze (each iris's offset from its eye corners, in eye widths) is
calibrated twice. Against the actor: the rest frames' median gaze is "looking
ahead", so an actor whose irises sit a little off the corners' midpoint at
rest (or a locator with a bias of its own) does not make the character squint
sideways. Against the rig: each gaze slider's own range, the distance its
shape moves the rig's iris at full weight in the rig's eye widths, measured on
the rig's eyeball vertices (:func:`rig_gaze_gains`); a rig whose gaze shapes
turn no eyeball (the ICT FaceKit's move the skin around it) takes
:data:`DEFAULT_GAZE_RANGE`. So the character's iris moves by
the same fraction of its eye as the actor's.

The gaze sliders are then set, not fitted: the expression fit
(:func:`retarget_cli.methods.rigpose.delta_pose`, its ``preset``) takes their
landmark displacement as a fixed offset, so a rig whose eyeLookDown also
lowers the lids (the ICT FaceKit's) does not close the eye twice: the lids'
gap rows ask the other sliders (blink, squint, wide) for the difference
between the actor's eye opening and the one the gaze already gives.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ShapeError

#: Gaze sliders in ARKit naming: (eye, axis, sign) -> the ARKit column. Eye 0 is the actor's right (image
#: left), the character's right (``_R``); axis 0 along the eye (> 0 toward the image's right: the actor
#: looks to their left), 1 across (> 0 down). Looking to their left, the right eye turns in (toward the nose)
#: and the left eye out.
GAZE_ARKIT = {
    (0, 0, 1): "EyeLookInRight", (0, 0, -1): "EyeLookOutRight",
    (0, 1, 1): "EyeLookDownRight", (0, 1, -1): "EyeLookUpRight",
    (1, 0, 1): "EyeLookOutLeft", (1, 0, -1): "EyeLookInLeft",
    (1, 1, 1): "EyeLookDownLeft", (1, 1, -1): "EyeLookUpLeft",
}

#: The iris's travel at a gaze slider's full weight, in eye widths, for a rig whose eyeballs cannot be
#: measured: an eyeball of radius about 0.4 eye widths turned by about 30 degrees (ARKit's eyeLook at 1).
DEFAULT_GAZE_RANGE = 0.2

#: A vertex belongs to an eyeball when each of its eye's four gaze sliders moves it by at least this fraction
#: of that slider's largest displacement (lids move with up/down, not with in/out).
_EYEBALL_SHARE = 0.2
#: A slider whose iris moves less than this (eye widths, relative to the corners) at full weight moves no eyeball:
#: its shape is the skin's response to the gaze (the ICT FaceKit's: its eyeballs, vertices 21451-24590, are turned
#: by a transform, and its eyeLook shapes move the lids and corners with the eye-blend mesh in front of them).
_MIN_TRAVEL = 0.02
#: The eyeball's vertices must move rigidly under each gaze slider (:func:`_rigid_residual` at most this).
_RIGID_RESIDUAL = 0.05
#: The eye's opening at rest, in eye widths from the corners' midpoint: (along the eye, across it).
_OPENING = (0.3, 0.12)


@dataclass(frozen=True)
class GazeGains:
    """Per gaze slider, the iris's signed travel at full weight in eye widths along its axis.

    Attributes
    ----------
    index : dict
        ``(eye, axis, sign)`` -> slider index (the sliders the rig has).
    gain : dict
        ``(eye, axis, sign)`` -> signed travel in eye widths (> 0 in the direction of its axis).
    measured : dict
        ``(eye, axis, sign)`` -> True where the gain was measured on the rig's eyeball vertices, False where it is
        :data:`DEFAULT_GAZE_RANGE`.
    """

    index: dict
    gain: dict
    measured: dict


def _column(rig, j: int) -> np.ndarray:
    col = rig.D[:, [j]]
    col = col.toarray() if hasattr(col, "toarray") else np.asarray(col)
    return col.reshape(-1, 3)


def _rigid_residual(X: np.ndarray, D: np.ndarray) -> float:
    """How far the move ``X`` (N, 3) -> ``X + D`` is from a rigid one: the residual of the best rotation and
    translation (Kabsch's least-squares fit) over the displacement's norm (0 for an eyeball turned whole)."""
    Y = X + D
    a, b = X - X.mean(axis=0), Y - Y.mean(axis=0)
    U, _, Vt = np.linalg.svd(a.T @ b)
    R = (U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt).T
    return float(np.linalg.norm(a @ R.T - b) / max(float(np.linalg.norm(D)), 1e-300))


def rig_gaze_gains(rig, index: dict, corners=None) -> GazeGains:
    """Each gaze slider's iris travel at full weight, measured on the rig's eyeball vertices.

    An eye's eyeball is the set of vertices that all four of its gaze sliders (in, out, up, down) move (by at
    least :data:`_EYEBALL_SHARE` of each slider's largest displacement), provided each slider moves that set
    rigidly (:func:`_rigid_residual` at most :data:`_RIGID_RESIDUAL`: an eyeball turned whole, not skin);
    its iris, those of them seen in the eye's opening at rest (within 0.3 eye widths of the corners' midpoint
    along the eye, 0.12 across it: :data:`_OPENING`) on the front half of their depth (the rig's +z faces
    the viewer, +y is up). A slider's gain is its iris vertices' mean displacement relative to the corners'
    along the eye's axis (from corner to corner, or down across it) over the eye's width, as the actor's
    gaze is measured. Where no eyeball is found, or a slider moves its iris less than :data:`_MIN_TRAVEL`,
    the gain is :data:`DEFAULT_GAZE_RANGE` (the ARKit meaning of a gaze slider at 1: the eye turned about as
    far as it goes). The ICT FaceKit takes the default: its eyeballs (vertices 21451-24590) are turned by a
    transform, not by its eyeLook shapes, which move the lids, the corners and the eye-blend mesh in front
    of the eyeball (residual 0.16-0.42 of a rigid move).

    Parameters
    ----------
    rig : BlendshapeRig
    index : dict
        ``(eye, axis, sign)`` -> slider index (:data:`GAZE_ARKIT`'s keys).
    corners : sequence of (int, int), optional
        Per eye, the rig vertices of its corners in the image's left-to-right order (for 68 points the
        landmark vertices of points 36, 39 and 42, 45). Without them every gain is the default.

    Returns
    -------
    GazeGains
    """
    gain = {k: float(k[2]) * DEFAULT_GAZE_RANGE for k in index}
    measured = {k: False for k in index}
    if corners is None:
        return GazeGains(dict(index), gain, measured)
    X = rig.f0.reshape(-1, 3)
    for e in (0, 1):
        keys = [k for k in index if k[0] == e]
        if len(keys) != 4:
            continue
        cols = {k: _column(rig, index[k]) for k in keys}
        mags = [np.linalg.norm(c, axis=1) for c in cols.values()]
        ball = np.logical_and.reduce([m >= _EYEBALL_SHARE * max(m.max(), 1e-300) for m in mags])
        a, b = corners[e]
        along = X[b] - X[a]
        width = float(np.linalg.norm(along))
        if width <= 0:
            continue
        along /= width
        down = np.array([0.0, -1.0, 0.0]) - along * (-along[1])  # the rig's down, square to the eye's axis
        down /= max(float(np.linalg.norm(down)), 1e-300)
        if max(_rigid_residual(X[ball], c[ball]) for c in cols.values()) > _RIGID_RESIDUAL:
            continue  # not an eyeball turned by the shapes: the skin's response to the gaze (the default gain)
        rel = X - (X[a] + X[b]) / 2.0
        seen = ball & (np.abs(rel @ along) < _OPENING[0] * width) & (np.abs(rel @ down) < _OPENING[1] * width)
        if seen.sum() < 8:
            continue
        iris = seen & (X[:, 2] >= np.median(X[seen, 2]))
        for k in keys:
            # the iris's travel relative to the eye's corners, as the actor's gaze is measured
            d = cols[k][iris].mean(axis=0) - (cols[k][a] + cols[k][b]) / 2.0
            g = float(d @ (along if k[1] == 0 else down)) / width
            if g * k[2] > _MIN_TRAVEL:  # moves the iris within the eye, the way its name says
                gain[k], measured[k] = g, True
    return GazeGains(dict(index), gain, measured)


def gaze_sliders(offset, rest, gains: GazeGains, n_sliders: int, upper=None) -> np.ndarray:
    """Gaze slider values per frame from the actor's gaze.

    Per eye and axis, the offset from *rest* over the slider's gain (:func:`rig_gaze_gains`) on the slider
    whose direction it is, clipped to [0, its upper bound]; the opposite slider stays at 0.

    Parameters
    ----------
    offset : ndarray (T, 2, 2)
        Eye widths (:attr:`retarget_cli.io.landmarks.Landmarks.gaze`).
    rest : ndarray (2, 2)
        The actor's gaze looking ahead (:func:`rest_gaze`).
    gains : GazeGains
    n_sliders : int
    upper : ndarray (n_sliders,), optional
        Slider upper bounds (default 1).

    Returns
    -------
    ndarray (T, n_sliders), float64
        0 but at the gaze sliders.
    """
    G = np.asarray(offset, dtype=np.float64)
    if G.ndim != 3 or G.shape[1:] != (2, 2):
        raise ShapeError(f"gaze: expected shape (T, 2, 2), got {G.shape}")
    d = G - np.asarray(rest, dtype=np.float64)[None]
    out = np.zeros((len(G), n_sliders))
    up = np.ones(n_sliders) if upper is None else np.asarray(upper, dtype=np.float64)
    for k, j in gains.index.items():
        e, axis, _ = k
        out[:, j] = np.clip(d[:, e, axis] / gains.gain[k], 0.0, up[j])
    return out


def rest_gaze(offset, valid=None, members=None) -> np.ndarray:
    """The actor's gaze looking ahead: the median over the rest frames *members* (all frames without them) of
    the frames where the eye's iris was seen.

    Parameters
    ----------
    offset : ndarray (T, 2, 2)
    valid : ndarray (T, 2), bool, optional
    members : array_like of int, optional
        Rows of the rest frames (:attr:`retarget_cli.methods.neutral.RestChoice.members`).

    Returns
    -------
    ndarray (2, 2)
    """
    G = np.asarray(offset, dtype=np.float64)
    V = np.ones(G.shape[:2], bool) if valid is None else np.asarray(valid, bool)
    rows = np.arange(len(G)) if members is None or not len(members) else np.asarray(members, dtype=np.int64)
    out = np.zeros((2, 2))
    for e in (0, 1):
        ok = rows[V[rows, e]]
        if not ok.size:  # no rest frame shows this iris: every frame where it was seen
            ok = np.flatnonzero(V[:, e])
        if ok.size:
            out[e] = np.median(G[ok, e], axis=0)
    return out


__all__ = ["DEFAULT_GAZE_RANGE", "GAZE_ARKIT", "GazeGains", "gaze_sliders", "rest_gaze", "rig_gaze_gains"]
