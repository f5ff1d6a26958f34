"""``auto-pose``: pose a rig at every frame (or every key frame) from the landmarks (the rig as the artist).

Reads ``keys.json``, ``landmarks.npz`` and ``rig.yaml``; writes into the output
directory ``REGION/key_%05d.obj`` (the rig posed at each key's sliders),
``sliders.csv`` (one row per key frame, the animation CSV that ``edit`` reads),
``curves.csv`` (``frames: all``, the default: one row per frame of the take),
``masks/REGION.txt`` (region masks derived from the rig) and ``targets.yaml``,
which names the rig, the sliders and the curves so that ``apply`` writes the rig's
slider curves. The math is in :mod:`retarget_cli.methods.rigpose` (delta fit, default) and
:func:`retarget_cli.methods.editing.auto_pose` (absolute fit).
"""

from __future__ import annotations

import fnmatch
import json
import logging
import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..config import Command, Flag, Param, check_indices, check_masks, check_strings, output_flag, validate_params
from ..errors import InputError
from ..io.atomic import check_not_input, tracked_outputs, write_text
from ..io.editfiles import write_animation
from ..io.landmarks import load_landmarks
from ..io.livelink import arkit_mapping
from ..io.obj import write_obj
from ..io.rig import load_rig, read_rig
from ..io.rig.vertexmap import read_vertex_map
from ..io.stagefiles import read_keys, write_targets
from ..methods.editing import auto_pose
from ..methods.gaze_rig import DEFAULT_GAZE_RANGE, GAZE_ARKIT, gaze_sliders, rest_gaze, rig_gaze_gains
from ..methods.neutral import find_rest_frame
from ..methods.rigpose import (
    CONTACT_68,
    DEFAULT_RIDGE,
    DEFAULT_SPARSITY,
    DEPTH_RATIO,
    FRONT_68,
    LID_CLOSED_FRACTION,
    Contact,
    contact_references,
    delta_pose,
    depth_sliders,
    frontal_rotation,
    infer_exclusive,
    project,
    rig_landmarks,
    rig_region_masks,
    slider_owners,
    take_lid_closed,
)
from ..methods.tracking.head import estimate_head
from ..methods.tracking.headpose import HeadPose, camera_angles, head_pose, rest_rotation
from ..methods.tracking.headpose import frontalize as frontalize_points
from ._common import NO_CACHE, NO_CACHE_FLAG, Stage, _require, command_cache_dir
from ._neutral import neutral_from_keys
from .map_landmarks import cached_landmark_map
from .pose import NEUTRAL_OBJ, _pose_files, targets_neutral
from .track import held_confidence

log = logging.getLogger(__name__)

#: Declared parameters of ``auto_pose`` (YAML validation, CLI options, manifests, docs/config.md).
PARAMS = [
    Param("keys", "input", str, help="keys.json.", link="select.output"),
    Param("landmarks", "input", str, help="landmarks.npz.", link="track.output"),
    Param("rig", "input", str, help="rig.yaml (a neutral OBJ plus named shape OBJs, or 'source:' a character "
          "file; and 'landmarks:'), or a .glb/.gltf/.vrm character with morph targets."),
    Param("landmark_vertices", "input", str, None,
          "Rig vertex of each landmark (one id per line, or 'landmark vertex' pairs); default the "
          "rig.yaml's 'landmarks:' list, else found automatically (landmark_map.txt in the output).", nullable=True),
    Param("output", "output", str, "targets",
          "Directory for the key OBJs, sliders.csv, masks/ and targets.yaml."),
    Param("fit", "setting", str, "delta",
          "delta: the key frame's landmark displacement from neutral_frame (the actor's face shape "
          "stays out of the sliders); absolute: the landmark positions (Lewis & Anjyo eq. 3).",
          choices=("delta", "absolute")),
    Param("neutral_frame", "setting", int, "auto",
          "The actor's neutral frame (the rig's rest pose; a source frame number): auto takes the one keys.json "
          "records (select's "
          "neutral_frame), else finds the rest frame among the shared keys.", min=0, words=("auto",)),
    Param("frames", "setting", str, "all",
          "all: pose the rig at every frame (targets/curves.csv, which apply then drives it with); keys: "
          "at the key frames only, and apply interpolates their sliders by the weights (Chuang & Bregler §5).",
          choices=("all", "keys")),
    Param("smooth", "setting", float, 3.0,
          "delta fit, frames all: weight of the rig's landmark acceleration across frames, released at "
          "fast events such as blinks; 0: every frame alone.", min=0),
    Param("contact_weight", "setting", float, 4.0,
          "delta fit: weight of each lip and lid gap (68 points), in landmarks, so lips and lids closed on "
          "the actor close on the character; 0: off.", min=0),
    Param("lip_closed", "setting", float, 0.02,
          "Inner-lip gap / mouth width, above the take's closed lips, below which the actor's lips count "
          "as closed (the tracker's noise on closed lips).", min=0),
    Param("lid_closed", "setting", float, "auto",
          f"Lid gap / eye width at or below which the tracked eye counts as closed; auto: {LID_CLOSED_FRACTION} of the eye's open "
          "reading in the take (a 68-point detector reads closed lids at about a third of the open eye: "
          "0.09-0.19 on the shared clips).", min=0, words=("auto",)),
    Param("sparsity", "setting", float, None,
          "L1 weight keeping unneeded sliders at 0, relative to the sliders' mean landmark energy "
          "(null: 0.01).", min=0, nullable=True),
    Param("ridge", "setting", float, None, "Ridge weight, relative likewise (null: 0.001).",
          min=0, nullable=True),
    Param("exclude", "setting", list, ["eyeLook*", "*pupil*"],
          "Slider-name patterns (fnmatch, any case) kept out of the landmark fit and at 0: by default gaze and "
          "pupils, which landmarks without pupils cannot see (the gaze sliders are then set from the iris by "
          "auto_pose.gaze).", validate=check_strings),
    Param("depth_ratio", "setting", float, DEPTH_RATIO,
          "Sliders whose fitted landmark vertices move more than this many times as far in 3D as in the rig's "
          "front view (a jaw thrust: motion along the line of sight, which 2D landmarks see only by a side effect "
          "a few pixels large, so the fit would take it at full weight for small residuals) are kept out of the "
          "fit and at 0, as exclude keeps its own (68 points; on the ICT FaceKit jawForward); off (or null): fitted "
          "like any other.", min=1, nullable=True, words=("off",)),
    Param("gaze", "setting", str, "auto",
          "on: when landmarks.npz has the gaze (track.gaze) and the rig has gaze sliders (eyeLookIn/Out/Up/Down "
          "_L/_R, or named so in rig.yaml's names:), set them from each iris, calibrated on the take's rest "
          "frames and the rig's own iris travel, before the delta fit, which takes what they move as a fixed "
          "offset (so their lids are not fitted twice); auto: as on when the rig's gaze sliders turn its "
          "eyeballs (their travel measured), else as off (a rig whose gaze shapes only move lids and skin, "
          "like the ICT FaceKit's, fits its lids better without them; Live Link's eye columns carry the gaze "
          "either way); horizontal: the in/out sliders only (the up/down reading of the iris is entangled with "
          "the lids); off: the gaze sliders stay as exclude has them.",
          choices=("auto", "on", "horizontal", "off")),
    Param("skip_points", "setting", list, None,
          "Landmarks left out of the fit (default for 68 points: the jaw contour but the chin).",
          nullable=True, validate=check_indices),
    Param("rigid_points", "setting", list, None,
          "Landmarks that give each key frame's head pose (default for 68 points: nose and eye "
          "corners).", nullable=True, validate=check_indices),
    Param("masks", "setting", dict, None,
          "Region name to vertex-mask file, overriding the masks derived from the rig.", nullable=True,
          validate=check_masks),
    Param("frontalize", "setting", bool, False,
          "Remove the head's 3D rotation from the landmarks before the fit (needs landmarks.npz head_angles, "
          "68 points): each frame's landmarks as the face would show them turned as in the take's rest frames, "
          "with the rig's own landmark vertices as the 3D face, so a turn of the head is not read as expression. "
          "Off by default: on the shared real clips (heads turning 2-8 deg) it gains mouth and brow but costs a "
          "little eye, mouth width, eye contact and slider saturation (docs/auto-pose.md); on for large turns."),
    Param("alpha", "setting", float, 0.001, "absolute fit: eq. 3's alpha.", min=0),
    Param("mu", "setting", float, 0.0001, "absolute fit: eq. 3's mu.", min=0),
]

FITS = ("delta", "absolute")
#: Sliders left at 0 by default: gaze and pupils, which 2D landmarks without pupils cannot observe
#: (ARKit-style names; fnmatch patterns, case-insensitive).
DEFAULT_EXCLUDE = ("eyeLook*", "*pupil*")
#: Landmarks of the 68-point layout left out of the fit by default: the jaw contour apart from the chin.
#: On a real face they are the silhouette, which slides over the skin as the head turns; on the rig they
#: are fixed vertices (on d3 they carried 20-40 px of displacement that no expression explains).
CONTOUR_68 = (0, 1, 2, 3, 4, 5, 11, 12, 13, 14, 15, 16)
#: Landmarks of the 68-point layout that do not move with expression: the nose and the eye corners.
RIGID_68 = (27, 28, 29, 30, 31, 32, 33, 34, 35, 36, 39, 42, 45)


def no_landmark_map_error(spec, rig_path) -> InputError:
    """The rig has no landmark map: one line naming ``retarget map-landmarks`` and the ``landmarks:`` key."""
    where = ("in a rig.yaml with 'source: " + Path(rig_path).name + "'") if spec.path == spec.source else "in it"
    return InputError(f"{rig_path}: the rig has no landmark map (the rig vertex of each tracked landmark; found "
                      f"automatically for the 68-point layout only); make one "
                      f"with 'retarget map-landmarks {rig_path} -o map.txt' and name it as 'landmarks: map.txt' "
                      f"{where}, or pass it as --landmark-vertices (auto_pose.landmark_vertices)")


def _rig_landmark_vertices(spec, landmark_vertices, n_points: int, n_vertices: int, rig_path):
    """(landmark ids, vertex ids) from --landmark-vertices, else from rig.yaml's ``landmarks:``."""
    source = landmark_vertices if landmark_vertices is not None else spec.landmarks
    if source is None:
        raise no_landmark_map_error(spec, rig_path)
    if isinstance(source, (str, os.PathLike)):
        return read_vertex_map(source, n_points, n_vertices)
    vx = np.asarray(source, dtype=np.int64)
    if len(vx) != n_points:
        raise InputError(f"{rig_path}: landmarks: lists {len(vx)} vertices but the landmarks file has {n_points}")
    bad = np.flatnonzero(vx >= n_vertices)
    if bad.size:
        raise InputError(f"{rig_path}: landmarks[{int(bad[0])}]: vertex {int(vx[bad[0]])} is outside the mesh "
                         f"({n_vertices} vertices)")
    return np.arange(n_points), vx


def excluded_sliders(names, patterns) -> np.ndarray:
    """Boolean mask of the slider names matching any fnmatch *pattern* (case-insensitive)."""
    pats = [str(p).lower() for p in (patterns or ())]
    return np.array([any(fnmatch.fnmatchcase(n.lower(), p) for p in pats) for n in names], dtype=bool)


def _mask_text(weights: np.ndarray) -> str:
    return "".join(f"{w:.6g}\n" for w in weights)


@validate_params(PARAMS)
def run_auto_pose(*, keys, landmarks, rig, output, landmark_vertices=None, masks=None, fit="delta",
                  neutral_frame="auto", sparsity=None, ridge=None, exclude=DEFAULT_EXCLUDE, skip_points=None,
                  rigid_points=None, alpha=0.001, mu=0.0001, frames="all", smooth=3.0, contact_weight=4.0,
                  lip_closed=0.02, lid_closed="auto", frontalize=False, gaze="auto", depth_ratio=DEPTH_RATIO,
                  base_dir=None, cache_dir=None) -> list[Path]:
    """Pose *rig* at each key frame of *keys* (and every frame with ``frames="all"``); write key OBJs,
    ``sliders.csv``, masks, ``targets.yaml`` (and ``curves.csv``).

    ``fit="delta"`` (default): :func:`retarget_cli.methods.rigpose.delta_pose`, the
    key frame's landmark displacement from *neutral_frame* (Lewis et al.
    2005 §3) reproduced per region by the sliders the region owns; the
    neutral frame poses every slider at 0. ``fit="absolute"``: the landmark
    positions themselves (:func:`retarget_cli.methods.editing.auto_pose`, eq. 3 of
    Lewis & Anjyo 2010 with every landmark as a pin), which turns the
    difference between the actor's and the character's faces into expression.

    Parameters
    ----------
    masks : dict, optional
        Region name to a vertex-mask file (relative to *base_dir*), overriding
        the masks derived from the rig (:func:`retarget_cli.methods.rigpose.rig_region_masks`).
    sparsity, ridge : float, optional
        λ and μ of :func:`retarget_cli.methods.rigpose.fit_sliders` (None: defaults).
    exclude : sequence of str
        Slider-name patterns kept at 0.
    depth_ratio : float, optional
        Sliders that move the fitted landmarks mostly in depth
        (:func:`~retarget_cli.methods.rigpose.depth_sliders`) are kept at 0 too (68 points; None or "off":
        fitted).
    skip_points : sequence of int, optional
        Landmarks left out of the fit (default for 68 points: :data:`CONTOUR_68`).
    rigid_points : sequence of int, optional
        Landmarks that give each frame's head pose (default for 68 points: :data:`RIGID_68`).
    frontalize : bool
        Fit the frontalized landmarks (:func:`frontal_landmarks`) instead of ``stabilized``.
    gaze : {"auto", "on", "horizontal", "off"}
        ``on`` (delta fit): the rig's gaze sliders set from the landmarks' ``gaze`` (:func:`_gaze_preset`) and
        held as a fixed offset by the fit (``delta_pose``'s *preset*); ``auto``: as ``on`` when the rig's gaze
        sliders turn its eyeballs, else as ``off``; ``horizontal``: the in/out ones only.

    Besides the poses, ``coverage.json`` lists each slider as driven, cannot (no fitted landmark moves with it)
    or excluded (left at 0 by choice), per region (:func:`slider_coverage`).
    """

    if fit not in FITS:
        raise InputError(f"fit: expected one of {', '.join(FITS)}, got {fit!r}")
    lid_closed = None if lid_closed == "auto" else lid_closed  # None: the take's (take_lid_closed)
    keys, landmarks, rig_path = _require(keys, "keys file"), _require(landmarks, "landmarks file"), _require(rig, "rig file")
    if landmark_vertices is not None:
        landmark_vertices = _require(landmark_vertices, "landmark-vertex map")
    out = Path(output)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a directory")
    # Everything that is cheap to check, before the rig's OBJs are read.
    spec, kf, lm, key_frames, mask_files = _check_inputs(keys, landmarks, rig_path, landmark_vertices, out,
                                                     skip_points, rigid_points, masks, base_dir)
    lm.points_raw = None  # the tracker's unfiltered points: not used here, not held through the fit
    neutral = neutral_from_keys(neutral_frame, kf, lm, landmarks=landmarks) if fit == "delta" else None
    r = load_rig(rig_path, cache_dir=cache_dir)
    if landmark_vertices is None and spec.landmarks is None and lm.n_points == 68:
        landmark_vertices = cached_landmark_map(rig_path, r, spec, out)
    lm_ids, vx = _rig_landmark_vertices(spec, landmark_vertices, lm.n_points, r.n_vertices, rig_path)
    if frontalize:
        lm, neutral = frontal_landmarks(lm, neutral, r, vx, lm_ids)
    region_rows, rigid = _fit_rows(kf, keys, lm_ids, lm.n_points, skip_points, rigid_points)
    excluded = excluded_sliders(r.names, exclude) | _depth_sliders(r, vx, lm_ids, lm.n_points, region_rows,
                                                                   depth_ratio)
    preset, gaze_mask = _gaze_preset(gaze, fit, lm, r, spec, lm_ids, vx)
    fixed = excluded | gaze_mask
    # the fitted landmarks as the file stores them (float32): the delta fit reads each frame at float64, exactly
    Y, Cf = lm.stabilized[:, lm_ids], lm.confidence[:, lm_ids]
    if fit != "delta" or neutral.shape is not None:
        Y, Cf = Y.astype(np.float64), Cf.astype(np.float64)
    # frames all: each segment of the take (found frames between gaps and cuts) is posed and smoothed apart
    posed = [range(a, b) for a, b in lm.segments] if frames == "all" else [key_frames]
    if fit == "delta":
        Y0 = neutral.landmarks(lm.stabilized)[lm_ids].astype(np.float64)
        C0 = neutral.weights(lm.confidence)[lm_ids].astype(np.float64)
        if neutral.shape is not None:  # a calibration's shape stands in for its frame's landmarks
            Y[neutral.frame], Cf[neutral.frame] = Y0, C0
        contact, front = _contact_rows(lm_ids, lm.n_points)
        lids = _lid_closed(lid_closed, Y, contact, Cf, "the take")
        opts = dict(sparsity=DEFAULT_SPARSITY if sparsity is None else sparsity,
                    ridge=DEFAULT_RIDGE if ridge is None else ridge, contact=contact, front=front,
                    contact_refs=contact_references(Y, contact, Cf, neutral=Y0, lid_closed=lids)
                    if contact else None,
                    contact_weight=contact_weight, lip_closed=lip_closed, lid_closed=lids,
                    smooth=smooth if frames == "all" else 0.0)
        shots = _shot_neutrals(lm, posed, neutral.frame, (Y0, C0), lm_ids, Y, Cf, contact, lid_closed,
                               opts["contact_refs"], keep_home=neutral.record.get("source") != "take") \
            if frames == "all" else None
        T, timing = lm.n_frames, lm.timing()
        del lm  # the take's landmarks: what the fit reads is in Y and Cf (not held through the fit)
        poses, owner, region_sliders = _delta_poses(r, spec, vx, Y, Cf, posed, (Y0, C0), region_rows, fixed,
                                                    rigid, opts, shots=shots, preset=preset, T=T)
    else:
        T, timing = lm.n_frames, lm.timing()
        del lm
        poses, owner, region_sliders = _absolute_poses(r, vx, Y, Cf, [f for part in posed for f in part],
                                                       list(kf.regions), region_rows, fixed, alpha, mu, T=T)
    del Y, Cf
    if frames == "all" and not poses[1].all():
        _hold_gaps(*poses)
    coverage = slider_coverage(r, vx, list(kf.regions), region_rows, owner, excluded, gaze_mask)
    _log_coverage(coverage)
    return _write_keys(out, r, spec, rig_path, kf, key_frames, poses, owner, region_sliders, mask_files, fit,
                       None if neutral is None else neutral.label, timing, every_frame=frames == "all",
                       coverage=coverage)


def rig_face_model(rig, vertices) -> np.ndarray:
    """The rig's 68 landmark vertices at rest as a 3D face for :func:`~retarget_cli.methods.tracking.headpose.head_pose`.

    In camera axes (:func:`~retarget_cli.methods.rigpose.frontal_rotation`: x from the image-left to the
    image-right outer eye corner, y down towards the chin, z away from the viewer), the eye corners' centre at
    the origin, in the rig's units.

    Parameters
    ----------
    rig : BlendshapeRig
    vertices : array_like of int, shape (68,)

    Returns
    -------
    ndarray, shape (68, 3)
    """
    X0 = rig_landmarks(rig, vertices)[0]
    Rc = frontal_rotation(X0, *FRONT_68)
    return (X0 - X0[[36, 39, 42, 45]].mean(0)) @ Rc.T


def _rest_rows(lm, neutral) -> np.ndarray:
    """Rows of the take's rest frames: those a take's rest shape averages (source frames in keys.json), else
    the neutral frame's row."""
    rows = np.array([int(neutral.frame)], dtype=np.int64)
    if neutral.shape is not None and neutral.record.get("source") == "take" and neutral.record.get("frames"):
        src = np.asarray(neutral.record["frames"], dtype=np.int64)
        frames = np.asarray(lm.timing()[0], dtype=np.int64)
        at = np.clip(np.searchsorted(frames, src), 0, len(frames) - 1)
        hit = at[frames[at] == src]
        if hit.size:
            rows = hit
    return rows


def frontal_landmarks(lm, neutral, rig, vx, lm_ids):
    """*lm* with its ``stabilized`` landmarks frontalized: the head's 3D rotation removed (issue 28).

    Each frame's pose is fitted with the rig's own landmark vertices as the 3D face (:func:`rig_face_model`)
    when the rig maps all 68 landmarks, else the stored ``head_angles``/``head_translation`` (the generic
    face) are used; the points are moved to the pose of the take's rest frames (their rotation relative to the
    line of sight, :func:`~retarget_cli.methods.tracking.headpose.rest_rotation`: only the change of pose from
    the rest frames is removed, which is what the delta fit reads) by
    :func:`~retarget_cli.methods.tracking.headpose.frontalize` (the residual back-projected onto the face's
    plane) and the 2D similarity is removed again (:func:`~retarget_cli.methods.tracking.head.estimate_head`,
    default rigid points, frame 0 the reference). A take's rest shape (a *neutral* found in the take) is
    re-averaged over the same frames. *lm* unchanged (with a log line) without ``head_angles``, with another
    layout than 68 points or without a frame size.

    Returns
    -------
    lm : Landmarks
    neutral : Neutral or None
    """
    if lm.head_angles is None or lm.n_points != 68 or min(lm.frame_size) <= 0:
        log.info("frontalize: not applied (landmarks.npz has %s, %d points, frame size %s)",
                 "no head_angles" if lm.head_angles is None else "head_angles", lm.n_points, lm.frame_size.tolist())
        return lm, neutral
    conf = held_confidence(lm.confidence, lm.found)
    size = tuple(int(v) for v in lm.frame_size)
    model = rig_face_model(rig, vx) if np.array_equal(lm_ids, np.arange(68)) else None
    if model is not None:
        pose = head_pose(lm.points, size, confidence=conf, model=model)
        what = "the rig's landmark vertices"
    else:
        tr = np.asarray(lm.head_translation, np.float64)
        pose = HeadPose(camera_angles(np.asarray(lm.head_angles, np.float64), tr), tr, np.full(lm.n_frames, np.nan))
        what = "the generic face (landmarks.npz head_angles)"
    rest = rest_rotation(pose, _rest_rows(lm, neutral)) if neutral is not None else None
    front = frontalize_points(lm.points, pose, size, model=model, rest=rest)
    stab = estimate_head(front, conf)[1].astype(np.float32)
    log.info("frontalize: the head's 3D rotation removed before the fit (3D face: %s; |yaw| up to %.1f, |pitch| up "
             "to %.1f deg)", what, float(np.abs(pose.angles[:, 0]).max()), float(np.abs(pose.angles[:, 1]).max()))
    lm = replace(lm, stabilized=stab)
    if neutral is not None and neutral.shape is not None and neutral.record.get("source") == "take" \
            and neutral.record.get("frames"):
        neutral = replace(neutral, shape=stab[_rest_rows(lm, neutral)].astype(np.float64).mean(0))
    return lm, neutral


def _depth_sliders(r, vx, lm_ids, L: int, region_rows, ratio) -> np.ndarray:
    """:func:`~retarget_cli.methods.rigpose.depth_sliders` over the fitted rows, logged (none without *ratio* or
    without the 68 points' front)."""
    front = _contact_rows(lm_ids, L)[1]
    if ratio is None or ratio == "off" or front is None:
        return np.zeros(r.n_sliders, dtype=bool)
    X0, DL = rig_landmarks(r, vx)
    rows = sorted({i for v in region_rows.values() for i in v})
    depth = depth_sliders(X0, DL, rows, front, ratio=ratio)
    if depth.any():
        log.info("auto-pose leaves %d slider(s) that move the landmarks mostly in depth at 0 (depth_ratio %g): %s",
                 int(depth.sum()), ratio, ", ".join(n for n, d in zip(r.names, depth) if d))
    return depth


def _contact_rows(lm_ids, L: int):
    """:data:`~retarget_cli.methods.rigpose.CONTACT_68` and :data:`~retarget_cli.methods.rigpose.FRONT_68` in rows
    among the mapped landmarks (68 points only; a group with an unmapped point is left out)."""
    if L != 68:
        return None, None
    pos = {int(p): i for i, p in enumerate(lm_ids)}
    out = []
    for c in CONTACT_68:
        pts = [*(p for pair in c.pairs for p in pair), *c.corners]
        if all(p in pos for p in pts):
            out.append(Contact(c.kind, tuple((pos[u], pos[d]) for u, d in c.pairs), (pos[c.corners[0]],
                                                                                    pos[c.corners[1]])))
    front = tuple(pos[p] for p in FRONT_68) if all(p in pos for p in FRONT_68) else None
    return out, front


def _check_inputs(keys, landmarks, rig_path, landmark_vertices, out, skip_points, rigid_points, masks, base_dir):
    """Checks that need no OBJ: outputs that are not inputs, key frames inside the take, landmark
    ids, masks. Returns the rig spec, the keys, the landmarks, the sorted key frames (rows) and the mask files."""

    spec = read_rig(rig_path)
    kf, lm = read_keys(keys), load_landmarks(landmarks)
    if landmark_vertices is None and spec.landmarks is None and lm.n_points != 68:
        raise no_landmark_map_error(spec, rig_path)  # the map is found automatically for 68 points only
    inputs = [keys, landmarks, rig_path, *spec.files()] + ([landmark_vertices] if landmark_vertices else [])
    found_map = ("landmark_map.txt", "landmark_map.png") if landmark_vertices is None and spec.landmarks is None else ()
    for name in ("targets.yaml", "sliders.csv", "curves.csv", *found_map) + ((NEUTRAL_OBJ,) if spec.neutral is None
                                                                             else ()):
        check_not_input(out / name, inputs)
    kf.resolve_rows(lm.timing()[0], landmarks)  # keys are named by source frame: their rows
    key_frames = sorted({f for reg in kf.regions.values() for f in reg["rows"]})
    L = lm.n_points
    for label, pts in (("skip_points", skip_points), ("rigid_points", rigid_points)):
        if pts is not None and any(not isinstance(i, int) or not 0 <= i < L for i in pts):
            raise InputError(f"{label}: expected landmark ids in [0, {L}), got {list(pts)!r}")
    masks = masks or {}
    unknown = sorted(set(masks) - set(kf.regions))
    if unknown:
        raise InputError(f"masks: region {unknown[0]!r} is not a region of {keys} ({', '.join(kf.regions)})")
    mask_files = {name: _require(Path(base_dir or ".") / m, "region mask") for name, m in masks.items()}
    return spec, kf, lm, key_frames, mask_files


def _fit_rows(kf, keys, lm_ids, L: int, skip_points, rigid_points):
    """Each region's rows among the mapped landmarks (without *skip_points*), and the rigid rows."""
    if skip_points is None:
        skip_points = CONTOUR_68 if L == 68 else ()
    if rigid_points is None:
        rigid_points = RIGID_68 if L == 68 else None
    pos = {int(p): i for i, p in enumerate(lm_ids)}  # landmark id -> row among the mapped landmarks
    skip = set(skip_points)
    region_rows = {}
    for name, reg in kf.regions.items():
        rows = [pos[p] for p in reg["points"] if p in pos and p not in skip]
        if not rows:
            raise InputError(f"{keys}: region {name!r} has no landmark with a rig vertex (after skip_points)")
        region_rows[name] = rows
    rigid = None if rigid_points is None else [pos[p] for p in rigid_points if p in pos]
    return region_rows, rigid


def _cut_rows(lm) -> list[int]:
    """Rows of the take where a scene cut goes from one face straight to another (``meta.gaps`` of reason
    ``cut``, the gaps of length 0), sorted."""
    rows = []
    for g in lm.meta.get("gaps") or []:
        if isinstance(g, dict) and g.get("reason") == "cut" and not g.get("frames"):
            start = int(g["start"])
            row = int(np.searchsorted(lm.frames, start)) if lm.frames is not None else start
            if 0 < row < lm.n_frames:
                rows.append(row)
    return sorted(set(rows))


def _shot_neutrals(lm, parts, neutral_frame: int, neutral, lm_ids, Y, Cf, contact, lid_closed, refs,
                   keep_home: bool = False):
    """Per part of *parts* (lists of frames), the neutral it is measured from and its contact references, or
    None for a take without a cut from one face straight to another.

    A scene cut can show another actor, or the same one from another camera: each shot (the frames between
    two such cuts) is measured from its own rest shape (:func:`~retarget_cli.methods.neutral.find_rest_frame`
    over its found frames), and its lips' and lids' references (:func:`contact_references`) are its own: the
    take's rest shape found by ``neutral_frame: auto`` averages frames of every shot, two faces at once. With
    *keep_home* (a neutral frame given, or a calibration), the shot that holds the neutral frame keeps it.

    Returns
    -------
    list of (Y0 (M, 2), C0 (M,), contact references, the lids' closed reading) or None
    """
    cuts = _cut_rows(lm)
    if not cuts:
        return None
    bounds = [0, *cuts, lm.n_frames]
    home = int(np.searchsorted(cuts, neutral_frame, side="right"))
    found = lm.found_mask
    home_lids = _lid_closed(lid_closed, Y, contact, Cf) if keep_home else None
    cache, out = ({home: (neutral[0], neutral[1], refs, home_lids)} if keep_home else {}), []
    for part in parts:
        k = int(np.searchsorted(cuts, part[0], side="right"))
        if k not in cache:
            rows = np.arange(bounds[k], bounds[k + 1])
            rows = rows[found[rows]]
            choice = find_rest_frame(lm.stabilized[rows], lm.confidence[rows])
            y0, c0 = choice.shape[lm_ids], choice.confidence[lm_ids]
            shot_lids = _lid_closed(lid_closed, Y[rows], contact, Cf[rows], f"the shot of rows {bounds[k]}-{bounds[k + 1] - 1}")
            shot_refs = contact_references(Y[rows], contact, Cf[rows], neutral=y0, lid_closed=shot_lids) \
                if contact else None
            cache[k] = (y0, c0, shot_refs, shot_lids)
            log.info("auto-pose: the shot of frames %d-%d (after a scene cut) is measured from its own rest shape "
                     "(rest frame %d)", *(int(lm.timing()[0][r]) for r in (bounds[k], bounds[k + 1] - 1,
                                                                           rows[choice.frame])))
        out.append(cache[k])
    return out


def _lid_closed(lid_closed, Y, contact, Cf, what: str | None = None):
    """``lid_closed`` as given, or (None: ``auto``) the closed-lid reading of the frames *Y* (T, M, 2)
    (:func:`~retarget_cli.methods.rigpose.take_lid_closed`; None without lid pairs), logged as *what*'s."""
    if lid_closed is not None or not contact:
        return lid_closed
    value = take_lid_closed(Y, contact, Cf)
    if value is not None and what:
        log.info("auto-pose: %s's tracked lids count as closed at or below %.3f of the eye width (%s of its open "
                 "eyes' reading)", what, value, LID_CLOSED_FRACTION)
    return value


def _delta_poses(r, spec, vx, Y, Cf, frames, neutral, region_rows, fixed, rigid, opts, shots=None, preset=None,
                 T=None):
    """The delta fit (:func:`retarget_cli.methods.rigpose.delta_pose`, keyword arguments *opts*) of *frames*
    (a list of frame lists, each fitted and smoothed on its own): the poses (``(W (T, n) float64, posed (T,)
    bool)``: each posed row's sliders, one array for the take, not a row object per frame), slider owners,
    sliders by region. *T*: the take's rows (default ``len(Y)``).

    *neutral* is the neutral key's (landmarks (M, 2), confidence (M,)) among the mapped landmarks; *shots*, per
    part of *frames*, the (landmarks, confidence, contact references) that part is measured from instead
    (:func:`_shot_neutrals`).
    """

    exclusive = spec.exclusive
    if exclusive is None:

        _, DL = rig_landmarks(r, vx)
        exclusive = infer_exclusive(project(DL, np.eye(3)), r.names)
        log.info("auto-pose: inferred exclusive pairs %s", exclusive)
    T = len(Y) if T is None else T
    W, posed = np.zeros((T, r.n_sliders)), np.zeros(T, bool)
    rms = []
    for i, part in enumerate(frames):  # a list of frames per segment of the take, each smoothed on its own
        y0, c0, o = (*neutral, opts) if shots is None else (shots[i][0], shots[i][1],
                                                            {**opts, "contact_refs": shots[i][2],
                                                             "lid_closed": shots[i][3]})
        rows = slice(part.start, part.stop) if isinstance(part, range) else part  # a segment: views, no copies
        res = delta_pose(r, vx, y0, Y[rows], weights=Cf[rows], neutral_weights=c0,
                         regions=region_rows, exclusive=exclusive, fixed=fixed, rigid=rigid,
                         preset=None if preset is None else preset[rows],
                         out=W[rows] if isinstance(rows, slice) else None, **o)  # a segment's rows in place
        if not isinstance(rows, slice):
            W[rows] = res["w"]
        posed[rows] = True
        del res["w"]
        rms.extend(res["rms"])
        for f, e in zip(part, res["rms"]):
            log.debug("frame %d: landmark displacement rms %.3f px", f, e)
    owner = res["owner"]
    log.info("auto-pose: %d frames posed in %d segment(s), landmark displacement rms %.3f px (median)", len(rms),
             len(frames), float(np.median(rms)) if rms else 0.0)
    region_sliders = {name: [r.names[j] for j in np.flatnonzero(owner == ri)] for ri, name in enumerate(res["regions"])}
    return (W, posed), owner, region_sliders


def _hold_gaps(W, posed) -> None:
    """Every frame's pose, in place: a frame in a gap of the take (a row of *W* (T, n) not *posed* (T,)) holds
    the last posed frame's (the first's before any); ``apply.gaps`` decides what the exported curves do there."""
    T = len(posed)
    last = np.maximum.accumulate(np.where(posed, np.arange(T), -1))
    src = np.where(last >= 0, last, int(np.argmax(posed)))
    gap = np.flatnonzero(src != np.arange(T))
    W[gap] = W[src[gap]]  # the rows copied from are posed ones, which this does not change
    posed[:] = True


def _absolute_poses(r, vx, Y, Cf, frames, names, region_rows, fixed, alpha, mu, T=None):
    """The absolute fit (:func:`retarget_cli.methods.editing.auto_pose`, Lewis & Anjyo eq. 3) of every key frame;
    poses as :func:`_delta_poses` returns them."""

    T = len(Y) if T is None else T
    W, posed = np.zeros((T, r.n_sliders)), np.zeros(T, bool)
    upper_saved = r.upper.copy()
    r.upper = np.where(fixed, r.lower + 1e-12, r.upper)
    try:
        for f in frames:
            one = auto_pose(r, vx, Y[f], weights=Cf[f], alpha=alpha, mu=mu)
            W[f], posed[f] = np.where(fixed, 0.0, one["w"]), True
            log.info("key %d: rms %.3f px after %d iterations", f, one["rms"], one["iterations"])
    finally:
        r.upper = upper_saved
    # Absolute poses are whole-face poses: every region's key carries every slider.
    _, DL = rig_landmarks(r, vx)
    owner = slider_owners(project(DL, np.eye(3)), [region_rows[n] for n in names])
    owner[fixed] = -1
    region_sliders = {name: [r.names[j] for j in np.flatnonzero(owner == ri)] for ri, name in enumerate(names)}
    return (W, posed), owner, region_sliders


def _write_keys(out, r, spec, rig_path, kf, frames, poses, owner, region_sliders, mask_files, fit, neutral_frame,
                timing, every_frame=False, coverage=None):
    """Key OBJs, region masks, ``sliders.csv``, ``curves.csv`` (*every_frame*: every frame's row of *poses*) and
    ``targets.yaml``; a failure part-way removes what it wrote.

    *poses* is ``(W (T, n), posed (T,) bool)`` (:func:`_delta_poses`); *frames* and the posed rows are rows of the
    take; *timing* (source frame numbers (T,), times (T,))
    names them: the key OBJs, ``targets.yaml``'s keys and the CSVs' ``frame``/``time`` are source frames.
    """
    source, times = timing
    W, posed = poses

    names = list(kf.regions)
    derived = rig_region_masks(r, owner, len(names)) if len(names) > 1 else None
    planned = [out / f"{name}/key_{f:05d}.obj" for name in names for f in kf.regions[name]["frames"]]
    planned += [out / f"masks/{name}.txt" for name in names] + [out / "sliders.csv", out / "targets.yaml"]
    planned += [out / NEUTRAL_OBJ] if spec.neutral is None else []
    planned += [out / "curves.csv"] if every_frame else []
    planned += [out / COVERAGE_JSON] if coverage is not None else []
    regions = {}
    # a failure part-way removes the files written so far; a rerun with other keys removes the old keys' OBJs
    with tracked_outputs(out, "auto-pose", planned=planned) as ledger:
        written = ledger.written
        for ri, name in enumerate(names):
            owned = np.isin(r.names, region_sliders[name])
            regions[name] = {"keys": {}, "sliders": region_sliders[name]}
            for f, row in zip(kf.regions[name]["frames"], kf.regions[name]["rows"]):
                rel = f"{name}/key_{f:05d}.obj"
                write_obj(out / rel, r.template, r.evaluate(np.where(owned, W[row], 0.0)))
                regions[name]["keys"][f] = rel
                written.append(out / rel)
            if name in mask_files:
                regions[name]["vertices"] = os.path.relpath(mask_files[name].resolve(), out.resolve())
            elif derived is not None:
                rel = f"masks/{name}.txt"
                write_text(out / rel, _mask_text(derived[ri]))
                regions[name]["vertices"] = rel
                written.append(out / rel)
        write_animation(out / "sliders.csv", r.names, W[list(frames)], source[frames],
                        meta={"fit": fit, "neutral_frame": neutral_frame})
        written.append(out / "sliders.csv")
        if every_frame:
            every = np.flatnonzero(posed)
            write_animation(out / "curves.csv", r.names, W if len(every) == len(W) else W[every], source[every],
                            times[every])
            written.append(out / "curves.csv")
        if coverage is not None:
            write_text(out / COVERAGE_JSON, json.dumps(coverage, indent=1, sort_keys=True) + "\n")
            written.append(out / COVERAGE_JSON)
        nrel = targets_neutral(out, r, ledger.add)
        rrel = os.path.relpath(Path(rig_path).resolve(), out.resolve())
        where = "" if neutral_frame is None else f", neutral frame {neutral_frame}"
        write_targets(out / "targets.yaml", regions, neutral=nrel, rig=rrel, sliders="sliders.csv",
                      curves="curves.csv" if every_frame else None,
                      comment=f"Written by retarget auto-pose ({fit} fit{where}"
                              + (", every frame posed" if every_frame else "") + ").")
        written.append(out / "targets.yaml")
    return written


def _gaze_preset(mode, fit, lm, r, spec, lm_ids, vx):
    """The gaze sliders' values per frame (T, n) and their mask (n,), or (None, all False) when the gaze is off,
    the fit absolute, the take without gaze or the rig without gaze sliders.

    The rig's gaze sliders are the ARKit columns :data:`~retarget_cli.methods.gaze_rig.GAZE_ARKIT` found among
    its slider names (``eyeLookIn_L``, ``EyeLookInLeft``, ``eyeLookIn.L`` …) or in rig.yaml's ``names:``
    (:func:`~retarget_cli.io.livelink.arkit_mapping`); their iris travel is measured on the rig
    (:func:`~retarget_cli.methods.gaze_rig.rig_gaze_gains`, from the landmark vertices of the eye corners, 68
    points) and the actor's gaze is taken from its median over the take's rest frames
    (:func:`~retarget_cli.methods.neutral.find_rest_frame`'s members).
    """
    none = None, np.zeros(r.n_sliders, bool)
    if mode == "off":
        return none
    if lm.gaze is None:
        log.info("auto-pose: the landmarks have no gaze (track.gaze), so the gaze sliders are not driven")
        return none
    mapping = arkit_mapping(r.names, spec.names or {})
    index = {k: mapping[c][0] for k, c in GAZE_ARKIT.items() if c in mapping and len(mapping[c]) == 1
             and (mode != "horizontal" or k[1] == 0)}
    if not index:
        log.info("auto-pose: the rig has no gaze slider (eyeLookIn/Out/Up/Down_L/R or rig.yaml names:), so the "
                 "take's gaze drives nothing")
        return none
    if fit != "delta":
        log.warning("auto-pose: the gaze sliders are driven by the delta fit only (fit: %s leaves them at 0)", fit)
        return none
    pos = {int(p): i for i, p in enumerate(lm_ids)}
    corners = None
    if lm.n_points == 68 and all(p in pos for p in (36, 39, 42, 45)):
        corners = ((int(vx[pos[36]]), int(vx[pos[39]])), (int(vx[pos[42]]), int(vx[pos[45]])))
    gains = rig_gaze_gains(r, index, corners)
    if mode == "auto" and not all(gains.measured.values()):
        log.info("auto-pose: the rig's gaze sliders (%s) do not turn its eyeballs, so the gaze does not drive them "
                 "(auto_pose.gaze: on drives them with the default iris travel; Live Link's eye columns carry the "
                 "gaze either way)", ", ".join(r.names[j] for j in index.values()))
        return none
    rest = find_rest_frame(lm.stabilized, lm.confidence)
    look_ahead = rest_gaze(lm.gaze, lm.gaze_valid, rest.members)
    P = gaze_sliders(lm.gaze, look_ahead, gains, r.n_sliders, upper=r.upper)
    mask = np.zeros(r.n_sliders, bool)
    mask[list(index.values())] = True
    log.info("auto-pose: gaze drives %s (iris travel at full weight %s eye widths, %s; looking ahead at %s eye "
             "widths, the median of %d rest frames)", ", ".join(r.names[j] for j in index.values()),
             ", ".join(f"{abs(gains.gain[k]):.3f}" for k in index),
             "measured on the rig's eyeballs" if all(gains.measured.values()) else
             f"the default {DEFAULT_GAZE_RANGE} where the rig's eyeballs were not found",
             np.round(look_ahead, 3).tolist(), 0 if rest.members is None else len(rest.members))
    return P, mask


#: The coverage report of auto-pose, beside targets.yaml.
COVERAGE_JSON = "coverage.json"
#: A slider moving every fitted landmark vertex by less than this fraction of the rig's inter-ocular distance
#: (its eye corners' centres; the landmark vertices' RMS spread without 68 points) at full weight cannot be
#: driven by the landmarks.
UNSEEN_FRACTION = 0.01


def slider_coverage(r, vx, region_names, region_rows, owner, excluded, gaze_mask) -> dict:
    """Every slider of the rig in one of three groups, per region: what the landmark path does with it.

    - ``driven``: fitted to the landmarks (a region owns it) and moving a fitted landmark vertex by at least
      :data:`UNSEEN_FRACTION` of the inter-ocular distance at full weight, or a gaze slider set from the iris;
    - ``cannot``: no fitted landmark moves with it (a tongue, the pupils, a shape of the jaw contour that the
      fit skips; excluded or not, since no setting would drive it) or no region owns it: whatever the actor
      does, it stays at 0;
    - ``excluded``: left at 0 by choice (``auto_pose.exclude``, or ``auto_pose.depth_ratio``: it moves the
      landmarks mostly in depth) though landmarks move with it, and not driven by the gaze.

    On the ICT FaceKit every slider but ``PupilDilate_*`` moves a fitted landmark vertex by 3.4 % of the
    inter-ocular distance or more at full weight (``cheekSquint_*`` least), the pupils by 0.01 % at most.

    Parameters
    ----------
    r : BlendshapeRig
    vx : ndarray (M,), int
        Rig vertex of each mapped landmark.
    region_names : list of str
    region_rows : dict
        Region name -> rows among the mapped landmarks that the fit uses.
    owner : ndarray (n,), int
        Region index of each fitted slider, -1 for none.
    excluded, gaze_mask : ndarray (n,), bool

    Returns
    -------
    dict
        ``regions``: region name (or ``none``, for a slider no landmark of any region moves) -> ``{"driven":
        [...], "cannot": [...], "excluded": [...]}``; ``threshold`` (rig units), ``rule`` (one sentence).
    """
    X0, DL = rig_landmarks(r, vx)
    if len(vx) == 68:
        iod = float(np.linalg.norm(X0[36:42].mean(axis=0) - X0[42:48].mean(axis=0)))
    else:
        iod = float(np.sqrt(np.mean(np.sum((X0 - X0.mean(axis=0)) ** 2, axis=1))))
    rows = sorted({i for name in region_names for i in region_rows[name]})
    reach = np.linalg.norm(DL[rows], axis=1).max(axis=0) * np.maximum(np.abs(r.upper), np.abs(r.lower))  # (n,)
    thr = UNSEEN_FRACTION * iod
    home = slider_owners(project(DL, np.eye(3)), [region_rows[n] for n in region_names], tiny=0.0)
    groups = {}
    for j, name in enumerate(r.names):
        if gaze_mask[j]:
            kind = "driven"
        elif reach[j] < thr:  # whether excluded or not: no choice of settings would drive it
            kind = "cannot"
        elif excluded[j]:
            kind = "excluded"
        else:
            kind = "driven" if owner[j] >= 0 else "cannot"
        region = region_names[owner[j]] if owner[j] >= 0 else (region_names[home[j]] if reach[j] > 0 else "none")
        groups.setdefault(region, {"driven": [], "cannot": [], "excluded": []})[kind].append(name)
    return {"regions": groups, "threshold": thr,
            "rule": f"cannot: moves no fitted landmark vertex by {UNSEEN_FRACTION:.0%} of the inter-ocular distance "
                    f"({thr:.4g} rig units) at full weight; excluded: auto_pose.exclude or depth_ratio; "
                    "driven: fitted, or gaze"}


def _log_coverage(coverage: dict) -> None:
    """One log line per group: how many sliders, and which (the report shows them per region)."""
    for kind, what in (("driven", "drives"), ("cannot", "cannot drive (no fitted landmark moves with them)"),
                       ("excluded", "leaves at 0 by choice (exclude, depth_ratio)")):
        names = [n for g in coverage["regions"].values() for n in g[kind]]
        log.info("auto-pose %s %d slider(s)%s", what, len(names), (": " + ", ".join(names)) if names else "")


__all__ = ["CONTOUR_68", "COVERAGE_JSON", "DEFAULT_EXCLUDE", "FITS", "RIGID_68", "excluded_sliders",
           "no_landmark_map_error", "run_auto_pose", "slider_coverage"]


#: The pipeline stage (:mod:`retarget_cli.run.pipeline`).
STAGE = Stage(
    "auto_pose",
    "Pose a rig at every frame (frames: all) or each key frame from its landmarks (the rig as the artist): "
    "key OBJs, their sliders, every frame's curves, region masks and a targets.yaml from which apply writes "
    "the rig's slider curves.",
    PARAMS,
    run_auto_pose,
    extra_inputs=_pose_files,
    uses_base_dir=True,
    uses_cache=True,
)


def _cli_auto_pose(values, out):
    default_exclude = next(p.default for p in PARAMS if p.name == "exclude")
    kw = dict(values, masks=dict(values["masks"]), exclude=list(values["exclude"] or default_exclude))
    cache_dir = command_cache_dir(kw["output"], kw.pop("no_cache"), folder=True)
    return run_auto_pose(**kw, cache_dir=cache_dir)


#: ``auto-pose`` (the CLI builds it: :mod:`retarget_cli.cli.commands`).
COMMAND = Command(
    "auto-pose",
    """Pose RIG at every frame of LANDMARKS (--frames keys: at the key frames of KEYS): the rig as the artist.

    The default delta fit reproduces each frame's landmark displacement
    from the neutral frame, so the actor's face shape stays out of the
    sliders, with the lips and lids kept in contact where the actor's meet;
    apply then writes the rig's slider curves.
    """,
    lambda: [*PARAMS, NO_CACHE],
    (Flag("keys", argument=True, path="file"), Flag("landmarks", argument=True, path="file"),
     Flag("rig", argument=True, path="file"),
     Flag("landmark_vertices", path="file", show_default=False),
     Flag("masks", decls=("--mask",), value="mask", multiple=True, metavar="REGION=FILE", show_default=False,
          help="Vertex mask of a region, overriding the mask derived from the rig. Repeatable."),
     "fit", "neutral_frame", "frames", "gaze", "smooth", "contact_weight", "lip_closed", "lid_closed", "sparsity",
     "ridge", "depth_ratio",
     Flag("exclude", decls=("--exclude",), value="text", multiple=True, metavar="PATTERN", default=None,
          show_default=False,
          help="Slider-name pattern kept out of the landmark fit (repeatable; default eyeLook*, *pupil*: gaze "
               "and pupils; the gaze sliders are then set from the iris, --gaze)."),
     "alpha", "mu",
     output_flag("targets", "Directory for the key OBJs, sliders.csv, masks/ and targets.yaml.", required=False),
     NO_CACHE_FLAG),
    _cli_auto_pose,
    folder_output=True,
)
