"""File handling of ``track``, ``train-tracker`` and ``import``: video and annotations in, ``landmarks.npz`` out."""

from __future__ import annotations

import hashlib
import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from itertools import islice
from pathlib import Path

import numpy as np

from .._validate import check_name
from ..config import Command, Flag, Param, check_indices, check_size, check_strings, output_flag, validate_params
from ..errors import FaceLostError, InputError, ParameterError, TruncatedInputError
from ..io.annotations import read_annotations, read_csv_landmarks
from ..io.atomic import (
    CropSpill,
    NpyChunks,
    RowSpill,
    check_not_input,
    digest_files,
    load_npz,
    sha256_file,
    tracked_outputs,
)
from ..io.face_detector import face_detector_file
from ..io.facemark_model import load_facemark, save_lbf_model
from ..io.frames import IMAGE_SUFFIXES, FrameSource, is_sequence, read_image, sequence_files
from ..io.landmarks import Landmarks, save_landmarks
from ..io.overlay import write_overlay
from ..io.video import large_frame_allocations
from ..methods.decomposition.temporal import MARGIN, WINDOW, take_windows
from ..methods.gaps import describe_gaps, gap_summary, segment_ids, segments_of
from ..methods.neutral import align_shape, find_rest_frame
from ..methods.tracking import TRACKERS, method_choices, method_help, tracker_params
from ..methods.tracking.base import check_inside, to_gray
from ..methods.tracking.detect import Detector, detector_installed
from ..methods.tracking.facemark import train_lbf
from ..methods.tracking.gaze import EYES_68, crops_cover, eye_crop
from ..methods.tracking.gaze import gaze as gaze_fn
from ..methods.tracking.head import apply_similarity, estimate_head, fit_head, invert_similarity, stabilized_rows
from ..methods.tracking.head import smooth_head as _smooth
from ..methods.tracking.head import smooth_head as smooth_head_fn
from ..methods.tracking.headpose import head_pose as fit_head_pose
from ..methods.tracking.headpose import sight_angles
from ._common import Stage, _no_progress, _require
from ._landmark_filter import FILTER_DEFAULTS, FILTER_PARAMS, apply_filter
from .annotate import detect_frame, init_pts_path, is_auto, write_pts_once

log = logging.getLogger(__name__)

#: Declared parameters of ``track`` (YAML validation, CLI options, manifests, docs/config.md).
PARAMS = [
    Param("video", "input", str,
          help="Video file (mp4, mov, avi, mkv, m4v) or image-sequence pattern (printf or glob; "
               "png, jpg, exr)."),
    Param("init", "input", str, None,
          "Annotation of the first tracked frame: iBUG .pts or frame,point,x,y CSV, or auto (the "
          "default): the pretrained detector annotates it and writes <output stem>.init_NNNNN.pts "
          "beside the output (needs the extra detect).", nullable=True, words=("auto",)),
    Param("output", "output", str, "landmarks.npz", "Landmarks file (landmarks.npz contract)."),
    Param("overlay", "output", str, None,
          "Also write an mp4 with the landmarks (coloured by confidence) and the head frame.",
          nullable=True),
    Param("neutral", "input", str, None,
          "A calibration image (png, jpg, exr), image sequence or clip of the actor at rest, tracked like the "
          "take (its first frame annotated by the detector where the method needs an annotation); its rest "
          "shape, aligned to the take, is the neutral key of neutral_frame auto.", nullable=True),
    Param("annotations", "setting", list, None,
          "More annotated frames (.pts named like face_00120.pts, or CSV); each re-anchors the track.",
          nullable=True, validate=check_strings),
    Param("init_frame", "setting", int, None,
          "Frame of the init .pts when its name ends in no number (default 0).", min=0, nullable=True),
    Param("start", "setting", int, 0, "First frame to track (0-based).", min=0),
    Param("end", "setting", int, None, "Stop before this frame (default: the last).", min=1,
          nullable=True),
    Param("step", "setting", int, 1, "Track every step-th frame.", min=1, max=1000),
    Param("downscale", "setting", float, 1.0,
          "Track on frames scaled by this factor (coordinates stay at full resolution). auto: method detect "
          "reduces the frames by the largest whole factor that keeps the first frame's eye-corner span at least "
          "90 pixels (faster on large frames, but on the shared clips upscaled to 1080p it tracked d12's eyes "
          "less well: docs/benchmarks.md); the other methods track at full resolution.",
          min=0.05, max=1.0, words=("auto",)),
    Param("fps", "setting", float, None,
          "Frame rate: of an image sequence (default 30), or of a video instead of its container's (which is "
          "refused outside 1-480 fps, e.g. a remux claiming 2344; a missing one is taken as 30 with a warning).",
          min=0.01, nullable=True),
    Param("smooth_head", "setting", int, 0,
          "Temporal smoothing of the head track: Savitzky-Golay window in frames (0: none).",
          min=0, max=301),
    Param("head_pose", "setting", bool, True,
          "Fit the head's 3D rotation and translation per frame (landmarks.npz head_angles, head_translation; "
          "68 points and a known frame size): the head columns of the curves, Live Link, USD and glTF, and the "
          "rotation auto-pose removes before the expression fit."),
    Param("keep_partial", "setting", bool, False,
          "On a truncated video (or a face lost by a tracker that cannot find it again), keep what was tracked up "
          "to then. Method detect keeps tracking through frames without a face (gaps in landmarks.npz's found)."),
    Param("method", "setting", str, "auto", method_help(), choices=method_choices),
    Param("fuse", "setting", bool, True,
          "Method detect: join the detections with optical flow (a Kalman filter along the flow and "
          "a smoother over the take); false keeps each frame's detection as it is."),
    Param("gaze", "setting", bool, True,
          "Locate each iris in the frames (68 points): the gaze, filtered like the landmarks and held through "
          "blinks and gaps, is stored in landmarks.npz ('gaze', 'gaze_valid') for auto_pose's eyeLook sliders "
          "and the Live Link eye columns (method detect keeps each frame's eyes while tracking for it, the other "
          "methods decode the frames again); false: none."),
    Param("model", "input", str, None,
          "Facemark LBF model file for method facemark (written by 'retarget train-tracker').",
          nullable=True),
    Param("window", "setting", int, 21, "Lucas-Kanade window side in pixels (odd).", min=5, max=101),
    Param("levels", "setting", int, 3, "Pyramid levels.", min=0, max=8),
    Param("fb_threshold", "setting", float, 1.0, "Forward-backward error scale in pixels.",
          min=0.01, max=100),
    Param("anchor", "setting", bool, True, "Correct drift against the annotated frame."),
    Param("rigid_points", "setting", list, None,
          "Landmarks that define head motion (default: eye corners and nose for 68 points).",
          nullable=True, validate=check_indices),
    *FILTER_PARAMS,
]

#: Declared parameters of ``train-tracker``.
TRAIN_PARAMS = [
    Param("video", "input", str, help="Video or image-sequence pattern whose frames are annotated."),
    Param("annotations", "input", list, help=".pts files (frame number ending the name) or frame,point,x,y CSV "
          "files; 5 or more frames that span the actor's expressions."),
    Param("output", "output", str, "facemark.yaml",
          "Model file (OpenCV Facemark LBF; gzip-compressed if the name ends in .gz)."),
    Param("fps", "setting", float, None, "Frame rate of an image sequence.", min=0.01, nullable=True),
    Param("rigid_points", "setting", list, None,
          "Landmarks aligning the annotated frames before morphing (default: eye corners and nose for "
          "68 points, else all).", nullable=True, validate=check_indices),
    Param("stages", "setting", int, 5, "Cascade stages.", min=1, max=10),
    Param("trees", "setting", int, 4, "Trees per landmark and stage.", min=1, max=20),
    Param("depth", "setting", int, 4, "Tree depth (OpenCV tree_depth: depth - 1 splits per tree).", min=2, max=8),
    Param("face_size", "setting", int, 200,
          "Frames are scaled down so the first annotated face box is this many pixels on its longer "
          "side (for training and tracking alike); larger is slower.", min=32, max=4096),
    Param("seed", "setting", int, 0, "Seed of every random choice."),
]

#: Declared parameters of ``import`` (the landmark filter of ``track``, rts by default too; see run_import).
IMPORT_PARAMS = [
    Param("source", "input", str, help="frame,point,x,y CSV, NPZ with 'points' (T, L, 2) or a folder of .pts files."),
    Param("output", "output", str, "landmarks.npz", "Landmarks file (landmarks.npz contract)."),
    Param("fps", "setting", float, None, "Frame rate (default: the source's, else 30).", min=0.01, nullable=True),
    Param("frame_size", "setting", list, None, "Frame size of the source video, e.g. 1920x1080.", nullable=True,
          validate=check_size),
    Param("rigid_points", "setting", list, None, "Landmarks that define head motion.", nullable=True,
          validate=check_indices),
    Param("smooth_head", "setting", int, 0,
          "Temporal smoothing of the head track (Savitzky-Golay window in frames).", min=0, max=301),
    *FILTER_PARAMS,
]



#: Frames whose float32 landmarks (raw, stabilized, saved) ``track`` makes at once: a few hundred KB, so that
#: what it holds while saving does not grow with the take.
BLOCK = 512


def _all_track_params() -> list:
    """``track``'s declarations and the settings registered trackers add."""
    return [*PARAMS, *tracker_params(p.name for p in PARAMS)]


@validate_params(_all_track_params)
def run_track(*, video, init=None, output, method="auto", window=21, levels=3, fb_threshold=1.0, anchor=True,
              rigid_points=None, annotations=None, init_frame=None, start=0, end=None, step=1, downscale=1.0,
              fps=None, smooth_head=0, overlay=None, keep_partial=False, model=None, fuse=True, neutral=None,
              gaze=True, base_dir=None, head_pose=True,
              progress=_no_progress, filter=FILTER_DEFAULTS["filter"], filter_model=FILTER_DEFAULTS["filter_model"],
              filter_process_noise=FILTER_DEFAULTS["filter_process_noise"],
              filter_measurement_noise=FILTER_DEFAULTS["filter_measurement_noise"],
              filter_robust=FILTER_DEFAULTS["filter_robust"], filter_min_cutoff=FILTER_DEFAULTS["filter_min_cutoff"],
              filter_beta=FILTER_DEFAULTS["filter_beta"], filter_d_cutoff=FILTER_DEFAULTS["filter_d_cutoff"],
              **settings) -> list[Path]:
    """Track landmarks through *video* (a video file or an image-sequence pattern).

    *init* and *annotations* are ``.pts`` or ``frame,point,x,y`` CSV files; a
    ``.pts`` file's frame is the number ending its name (else *init_frame*).
    Frame numbers are 0-based positions in the source; the first tracked
    frame (*start*) must be annotated. *init* ``None`` or ``"auto"``: the
    pretrained detector annotates the first tracked frame (unless
    *annotations* do), and the annotation it used is written beside *output*
    as ``<output stem>.init_<frame:05d>.pts`` for review. Method ``detect``
    places the landmarks on every frame with the detector joined with optical
    flow (*fuse*; annotated frames are kept as given); ``auto`` is ``detect``
    where its extra is installed, else ``lk``. Writes the ``landmarks.npz`` contract to *output*
    (plus ``frames``, the source frame numbers) and, if asked, an *overlay*
    video. *model* is the Facemark model file of method ``facemark`` (see
    :func:`run_train_tracker`). The ``filter`` and ``filter_*`` arguments are the landmark filter settings
    (``filter``, ``filter_*``; :mod:`retarget_cli.stages._landmark_filter`): the
    points are filtered before the head motion is estimated, and the tracker's
    own points are kept as ``points_raw``. Annotated frames keep their given
    points and anchor the filter. *neutral*: a calibration image or clip of
    the actor at rest, tracked the same way (:func:`_track_neutral`); its
    rest shape is stored as the landmarks' ``neutral``. *gaze* (68 points): each iris located
    (:func:`_track_gaze`), stored as ``gaze`` and ``gaze_valid``.
    """

    fset = {k: v for k, v in locals().items() if k in FILTER_DEFAULTS}
    settings = {p.name: p.default for p in tracker_params(q.name for q in PARAMS)} | settings
    tracker_settings = {"window": window, "levels": levels, "fb_threshold": fb_threshold, "anchor": anchor,
                        "rigid_points": rigid_points, "downscale": downscale, "fuse": fuse, **settings}
    auto = is_auto(init)
    if not auto:
        init = _require(init, "annotation file")
    extra = [_require(Path(base_dir or ".") / a, "annotation file") for a in (annotations or [])]
    method, spec = _tracker(method)
    if downscale == "auto" and method != "detect" and "downscale" in spec.settings:
        tracker_settings["downscale"] = 1.0  # only the detector picks its scale from the face
    given = extra if auto else [init, *extra]
    ann, src = read_annotations(given, frame=init_frame) if given else ({}, {})
    need_auto = auto and start not in ann
    objects = _prepare(spec, method, need_auto=need_auto, ann=ann, src=src, model=model, init=init)
    _warn_unused(spec, method, tracker_settings, model)
    # gray trackers get grayscale frames, converted in the decoding thread
    crops = None  # the eyes' pixels of every frame, kept while tracking for the gaze (CropSpill)
    try:
        with FrameSource(video, start=start, end=end, step=step, fps=fps, gray=spec.gray) as source:
            calib = [] if neutral is None else (sequence_files(neutral) if is_sequence(neutral) else [Path(neutral)])
            init_out = _check_track_outputs(source, given + calib, output, overlay, start, need_auto)
            if gaze and spec.on_frame:
                crops = CropSpill(output)
            W, H = source.frame_size
            it = iter(source)
            ahead = []
            if need_auto and "detector" not in spec.needs:
                ahead.append(_auto_annotate(it, source, start, objects["detector"], init_out, ann, src))
            if start not in ann and "detector" not in spec.needs:
                raise InputError(f"{init}: the first tracked frame ({start}) must be annotated; annotated frames: "
                                 f"{', '.join(map(str, list(ann)[:8]))} (use --start or --init-frame)")
            index = _annotation_index(ann, src, (W, H), start, end, step, missing=source.missing)
            with large_frame_allocations(W * H * 3):
                points, conf, coverage = _run_tracker(spec, source, ahead, it, index, objects, tracker_settings,
                                                      progress=progress, keep_partial=keep_partial,
                                                      where=init_out or init or video,
                                                      on_frame=None if crops is None else _keep_eyes(crops))
            frame_numbers = np.asarray(source.frames[:len(points)], dtype=np.int64)
            files = source.files()
        conf = _lose_missing(conf, frame_numbers, source.missing)
        if need_auto and "detector" in spec.needs:
            write_auto_init(init_out, points[int(np.argmax(coverage.found))] if coverage is not None else points[0])
        found, segment, gaps = _coverage(coverage, len(points), frame_numbers, source, video)
        # the take's per-frame arrays held once each, the float64 points and confidences only (issues #31, #33):
        # the tracker's points go to a file beside the output before the filter writes over them, the stabilized
        # landmarks and the float32 copies are made a block of rows at a time while saving
        conf = np.require(conf, np.float64, ["W"])
        spill = None
        if fset["filter"] != "none":
            spill = RowSpill(output, points.shape, np.float32)
        try:
            if spill is not None:
                for a in range(0, len(points), BLOCK):
                    spill.write(points[a:a + BLOCK])
            points, _, fmeta = filter_segments(points, conf, segment, fps=source.fps, settings=fset, where=str(video),
                                               anchors=[i for i in index if i < len(points)], in_place=True,
                                               keep_raw=False)
            return _finish_track(
                points, conf, spill, fmeta, found=found, segment=segment, gaps=gaps, output=output, video=video,
                source=source, frame_numbers=frame_numbers, files=files, size=(W, H), rigid_points=rigid_points,
                smooth_head=smooth_head, head_pose=head_pose, gaze=gaze, neutral=neutral, overlay=overlay,
                spec=spec, objects=objects, tracker_settings=tracker_settings, fset=fset, progress=progress,
                method=method, settings=settings, given=given, init_out=init_out, ann=ann, auto=auto, init=init,
                model=model, crops=crops, params={"window": window, "levels": levels, "fb_threshold": fb_threshold, "anchor": anchor,
                                     "downscale": downscale, "start": start, "end": end, "step": step,
                                     "smooth_head": smooth_head, "head_pose": head_pose,
                                     **({"fuse": fuse} if "fuse" in spec.settings else {}),
                                     **{k: v for k, v in settings.items() if k in spec.settings}},
                fps=fps)
        finally:
            if spill is not None:
                spill.close()
    finally:
        if crops is not None:
            crops.close()


def _finish_track(points, conf, spill, fmeta, *, found, segment, gaps, output, video, source, frame_numbers, files,
                  size, rigid_points, smooth_head, head_pose, gaze, neutral, overlay, spec, objects,
                  tracker_settings, fset, progress, method, settings, given, init_out, ann, auto, init, model,
                  params, fps, crops=None) -> list[Path]:
    """The rest of :func:`run_track` once the points are filtered: head motion, 3D head pose, gaze, calibration,
    ``landmarks.npz`` (and the overlay). *points* (T, L, 2) and *conf* (T, L) are float64 and writable; *spill*
    holds the tracker's points (or None: no filter)."""
    W, H = size
    start, end, step = params["start"], params["end"], params["step"]
    # a gap frame's confidences are those of the frame whose landmarks it holds while the head is fitted
    # (held_confidence, written into conf and undone after: no copy of the take's confidences)
    undo = _hold_gap_confidence(conf, found)
    stab = None
    gz = None
    want_gaze = gaze and points.shape[1] == 68

    def gaze_pass():
        return _track_gaze(video, points, conf, segment, start=start, end=end, step=step, fps=fps, settings=fset,
                           progress=progress, crops=crops, size=size)

    if neutral is None and not smooth_head and undo is None and want_gaze:
        # no gap frame borrowed confidences (conf is only read): the head fits run on a worker thread while the
        # gaze pass runs (numba's kernel and OpenCV release the GIL); the same results
        with ThreadPoolExecutor(1, thread_name_prefix="retarget-head") as pool:
            heads = pool.submit(_fit_heads, points, conf, rigid_points, (W, H), head_pose)
            gz = gaze_pass()
            head, pose3d = heads.result()
    else:
        if neutral is not None or smooth_head:  # the calibration and the smoothing read them at full precision
            head, stab = estimate_head(points, conf, rigid_points=rigid_points)
            if smooth_head:
                head = smooth_head_fn(head, smooth_head)
                stab = apply_similarity(invert_similarity(head), points)
            pose3d = _head_pose_3d(points, conf, (W, H)) if head_pose else None
        else:
            head, pose3d = _fit_heads(points, conf, rigid_points, (W, H), head_pose)
        if undo is not None:
            conf[undo[0]] = undo[1]
        if want_gaze:
            gz = gaze_pass()
    del undo
    calibration = None
    if neutral is not None:
        calibration = _track_neutral(neutral, spec, objects, tracker_settings, stab, conf, rigid_points=rigid_points,
                                     fps=fps)
    if stab is not None:
        stab = stab.astype(np.float32, copy=False)
    else:  # mapped a block of rows at a time while saving, as estimate_head(dtype=float32) maps them
        inverse = invert_similarity(head)
        stab = NpyChunks(points.shape, np.float32, lambda a, b: stabilized_rows(inverse, points, a, b), BLOCK)
    mean_conf = float(conf.mean())
    meta = {
        "tracker": method,
        "parameters": params,
        "filter": fmeta,
        "source": Path(video).name,
        "source_sha256": sha256_file(files[0]) if len(files) == 1 else digest_files(files),
        "annotation": [Path(p).name for p in given + ([init_out] if init_out else [])],
        "annotated_frames": [int(f) for f in ann],
        "init": "auto" if auto else Path(init).name,
    }
    if "model" in objects:
        meta["model"], meta["model_sha256"] = Path(model).name, sha256_file(model)
    if calibration is not None:
        meta["neutral"] = calibration[2]
    if found is not None:
        meta["gaps"], meta["segments"] = gaps, int(segment.max()) + 1
    shape = points.shape
    save_landmarks(output, Landmarks(NpyChunks(shape, np.float32, lambda a, b: points[a:b], BLOCK),
                                     NpyChunks(shape[:2], np.float32, lambda a, b: conf[a:b], BLOCK),
                                     head, stab, source.fps, np.array([W, H]), None, meta,
                                     frames=frame_numbers, times=source.times(frame_numbers),
                                     points_raw=None if spill is None else spill.chunks(BLOCK),
                                     neutral=None if calibration is None else calibration[0],
                                     neutral_confidence=None if calibration is None else calibration[1],
                                     found=found, segment=segment,
                                     head_angles=None if pose3d is None else pose3d.angles,
                                     head_translation=None if pose3d is None else pose3d.translation,
                                     gaze=None if gz is None else gz[0], gaze_valid=None if gz is None else gz[1]))
    written = [Path(output)] + ([init_out] if init_out else [])
    log.info("tracked %d frames x %d points; mean confidence %.3f", len(points), points.shape[1], mean_conf)
    if overlay:
        _write_track_overlay(overlay, video, points, conf, head, source, start=start, end=end, step=step, fps=fps,
                             progress=progress)
        written.append(Path(overlay))
    return written


def _fit_heads(points, conf, rigid_points, frame_size, head_pose: bool):
    """The 2D head motion (:func:`~retarget_cli.methods.tracking.head.fit_head`) and, with *head_pose*, the
    3D head pose (:func:`_head_pose_3d`, else None) of the landmarks *points* (T, L, 2)."""
    head = fit_head(points, conf, rigid_points=rigid_points)
    return head, (_head_pose_3d(points, conf, frame_size) if head_pose else None)


def _head_pose_3d(points, confidence, frame_size):
    """The 3D head pose of every frame (:func:`~retarget_cli.methods.tracking.headpose.head_pose` on the generic
    face, on the filtered *points*), or None for a layout other than 68 points or an unknown frame size.

    The angles are relative to the line of sight (:func:`~retarget_cli.methods.tracking.headpose.sight_angles`:
    0 for a face that looks into the lens wherever it is in the picture). A frame without a face has the last
    found frame's points and confidences (:func:`held_confidence`), so it
    holds that frame's pose; the frames before the first found one take its pose.
    """
    if points.shape[1] != 68 or min(frame_size) <= 0:
        log.info("head pose: not fitted (%d points, frame size %s; needs 68 points and a frame size)",
                 points.shape[1], tuple(frame_size))
        return None
    pose = fit_head_pose(points, frame_size, confidence=confidence)
    pose = replace(pose, angles=sight_angles(pose.angles, pose.translation))
    log.info("head pose: yaw %.1f..%.1f, pitch %.1f..%.1f, roll %.1f..%.1f deg; reprojection error median %.2f px",
             *np.ravel(np.stack([pose.angles.min(0), pose.angles.max(0)], 1)), float(np.nanmedian(pose.error))
             if np.isfinite(pose.error).any() else float("nan"))
    return pose


#: At most this many frames of a calibration clip (track.neutral) are tracked.
CALIBRATION_MAX_FRAMES = 900


def _calibration_frames(neutral, spec, fps) -> tuple[list, list]:
    """The frames of a calibration (a single image, an image sequence or a clip) and the files read."""
    path = Path(neutral)
    if path.suffix.lower() in IMAGE_SUFFIXES and not is_sequence(path):
        img = read_image(_require(path, "calibration image"))
        return [to_gray(img) if spec.gray else img], [path]
    with FrameSource(path, end=CALIBRATION_MAX_FRAMES, fps=fps, gray=spec.gray) as source:
        frames = []
        try:
            frames.extend(source)
        except TruncatedInputError as exc:
            if not frames:
                raise
            log.warning("%s; using the %d calibration frames read", exc, len(frames))
        if source.frame_count > CALIBRATION_MAX_FRAMES:
            log.info("%s: the first %d of %d frames used as the calibration", path, CALIBRATION_MAX_FRAMES,
                     source.frame_count)
        return frames, source.files()


def _track_neutral(neutral, spec, objects, settings, stab, conf, *, rigid_points, fps):
    """Track the calibration *neutral* like the take; its rest shape aligned to the take (the neutral key).

    The calibration's rest frame is found as the take's would be
    (:func:`~retarget_cli.methods.neutral.find_rest_frame`; a single image is its own), and its landmarks are
    mapped into the take's stabilized coordinates by a similarity on the rigid points
    (:func:`~retarget_cli.methods.neutral.align_shape`).

    Returns
    -------
    shape : ndarray (L, 2), confidence : ndarray (L,), meta : dict
    """
    frames, files = _calibration_frames(neutral, spec, fps)
    objects = dict(objects)
    index = {}
    if "detector" not in spec.needs:  # the tracker needs its first frame annotated: the detector does it
        if "detector" not in objects:
            objects["detector"] = Detector(faces_file=face_detector_file())
        index[0] = detect_frame(frames[0], detector=objects["detector"], where=f"{neutral}: frame 0")
    track = spec.load()
    kw = {k: settings[k] for k in spec.settings} | {k: objects[k] for k in spec.needs}
    try:
        points, cconf = track(iter(frames), index, progress=lambda t: None, **kw)
    except (FaceLostError, ValueError) as exc:
        raise InputError(f"{neutral}: the calibration could not be tracked ({exc})") from None
    if points.shape[1] != stab.shape[1]:
        raise InputError(f"{neutral}: tracked {points.shape[1]} points, the take has {stab.shape[1]}")
    _, cstab = estimate_head(points, cconf, rigid_points=rigid_points)
    try:
        choice = find_rest_frame(cstab, cconf)
        ok = np.isfinite(stab).all(axis=(1, 2))
        shape = align_shape(choice.shape, np.median(np.asarray(stab, np.float64)[ok], axis=0),
                            rigid_points=rigid_points)
    except ValueError as exc:
        raise InputError(f"{neutral}: {exc}") from None
    if not choice.at_rest:
        log.warning("%s: the calibration is not at rest: %s", neutral, choice.reason)
    reason = "one image" if len(points) == 1 else f"{len(points)} frames; {choice.reason}"
    meta = {"file": Path(neutral).name, "sha256": sha256_file(files[0]) if len(files) == 1 else digest_files(files),
            "frames": int(len(points)), "frame": int(choice.frame), "at_rest": bool(choice.at_rest),
            "reason": reason}
    log.info("%s: calibration rest shape from %s", neutral, reason)
    return shape, np.asarray(choice.confidence, dtype=np.float64), meta


def _tracker(method: str):
    """The method (``auto`` resolved) and its :class:`~retarget_cli.methods.tracking.base.TrackerSpec`."""

    if method not in method_choices():
        raise ParameterError(f"method: expected {', '.join(map(repr, method_choices()))}, got {method!r}")
    if method == "auto":

        method = "detect" if detector_installed() else "lk"
        log.info("method auto: tracking with %s%s", method,
                 "" if method == "detect" else " (install the extra 'detect' for the pretrained detector)")
    return method, TRACKERS[method]


def _prepare(spec, method, *, need_auto, ann, src, model, init) -> dict:
    """The objects the tracker needs (``detector``, ``model``), loaded and checked before any decoding."""
    objects = {}
    n_ann = len(next(iter(ann.values()))) if ann else None
    if need_auto or "detector" in spec.needs:

        # fails here, before any decoding, when the extra is not installed
        objects["detector"] = Detector(faces_file=face_detector_file())
        if n_ann is not None and "detector" in spec.needs and n_ann != Detector.n_points:
            raise InputError(f"{src[next(iter(ann))]}: method {method} places {Detector.n_points} points but the "
                             f"annotation has {n_ann}")
    if "model" in spec.needs:

        if not model:
            raise InputError(f"method {method} needs a model file (--model, or track.model); "
                             "train one with 'retarget train-tracker'")
        objects["model"] = fitter = load_facemark(model)
        if fitter.n_points != (n_ann or 68):
            raise InputError(f"{model}: the Facemark model was trained for {fitter.n_points} points but "
                             f"{init} has {n_ann or 68}")
    return objects


def _warn_unused(spec, method, settings: dict, model) -> None:
    """A warning for each tracker setting away from its default that *method* does not use."""
    defaults = {p.name: p.default for p in _all_track_params()}
    for name, value in settings.items():
        if name != "rigid_points" and name not in spec.settings and value != defaults[name]:
            log.warning("%s %s is not used by method %s; ignored", name, value, method)
    if model and "model" not in spec.needs:
        log.warning("model %s is used by method facemark only; ignored by %s", model, method)


def _check_track_outputs(source, given, output, overlay, start, need_auto):
    """Refuse outputs that are inputs; the path of the automatic annotation (or None).

    The outputs are checked against one another without being protected as inputs: a rerun writes
    over its own landmarks file (``check_not_input`` would add it to the run's write guard).
    """

    check_not_input(output, source.files() + given)
    if overlay:
        check_not_input(overlay, source.files() + given)
    init_out = init_pts_path(output, start) if need_auto else None
    if init_out is not None:
        check_not_input(init_out, source.files() + given)
        same = [p for p in (output, overlay) if p is not None and Path(p).resolve() == init_out.resolve()]
        if same:
            raise InputError(f"{same[0]}: is also where the automatic annotation goes ({init_out}); "
                             "choose another output path")
    return init_out


def _init_owner(init_out: Path) -> str:
    """The owner name of the output manifest that lists the automatic annotations of one landmarks file."""
    stem = init_out.name.split(".init_")[0]
    try:
        return check_name(f"track-{stem}", "owner")
    except InputError:
        return "track-" + hashlib.sha256(stem.encode()).hexdigest()[:12]


def write_auto_init(init_out: Path, points) -> Path:
    """Write the automatic annotation *init_out*, recorded in its folder's output manifest.

    The annotation is an output of this run, not an input: a file an earlier
    ``track`` wrote there and that nobody changed since is replaced when the
    tracking settings give other points (a rerun with ``--force`` or another
    setting); one changed by hand is not (:func:`~.annotate.write_pts_once`).
    Annotations of other start frames written earlier for the same landmarks
    file, unchanged since, are removed.
    """

    init_out = Path(init_out)
    with tracked_outputs(init_out.parent, _init_owner(init_out)) as ledger:
        write_pts_once(init_out, points, own=ledger.before.get(init_out.name))
        ledger.add(init_out)
    return init_out


def _auto_annotate(it, source, start, detector, init_out, ann, src):
    """Annotate the first frame with the detector (for a tracker that needs an annotation); returns the frame."""

    frame = next(it)  # an undecodable video raises TruncatedInputError (an InputError) here
    ann[start] = detect_frame(frame, detector=detector, where=f"{source.path}: frame {start}")
    src[start] = init_out
    write_auto_init(init_out, ann[start])
    log.info("%s: frame %d annotated by the detector; wrote %s", source.path, start, init_out)
    return frame


def _lose_missing(conf, frame_numbers, missing):
    """Confidence 0 (lost) on every point of the rows whose frame the image sequence lacks."""
    lost = np.isin(frame_numbers, np.asarray(missing, dtype=np.int64))
    if lost.any():
        conf = np.array(conf, copy=True)
        conf[lost] = 0.0
    return conf


def _annotation_index(ann, src, size, start, end, step, missing=()) -> dict:
    """Annotated frames as ``{row of the tracked sequence: (L, 2)}``, each checked against the frame size.

    An annotation of a frame the image sequence lacks (*missing*) is refused: there is no image under it.
    """

    index = {}
    gone = set(missing)
    for f, P in ann.items():
        try:
            check_inside(P, size, f"frame {f}")
        except ValueError as exc:
            raise InputError(f"{src[f]}: {exc}") from None
        if f in gone:
            raise InputError(f"{src[f]}: annotates frame {f}, which the image sequence lacks (a gap in its "
                             "numbering)")
        if f < start or (end is not None and f >= end):
            log.info("%s: frame %d is outside the tracked range, ignored", src[f], f)
        elif (f - start) % step:
            raise InputError(f"{src[f]}: frame {f} is not tracked with start {start} and step {step}")
        else:
            index[(f - start) // step] = P
    return index


def _run_tracker(spec, source, ahead, it, index, objects, settings, *, progress, keep_partial, where, on_frame=None):
    """Run the tracker over the decoded frames; a truncated video or a lost face per *keep_partial*. *on_frame*: passed
    to a tracker that takes it (:attr:`~retarget_cli.methods.tracking.base.TrackerSpec.on_frame`)."""

    stopped = []

    def frames():
        try:
            yield from ahead
            yield from it
        except TruncatedInputError as exc:
            stopped.append(exc)

    n_expected = None
    if source.frame_count:
        last = source.frame_count if source.end is None else min(source.end, source.frame_count)
        n_expected = max(0, (last - source.start + source.step - 1) // source.step)
    track = spec.load()
    kw = {k: settings[k] for k in spec.settings} | {k: objects[k] for k in spec.needs}
    kw |= {"gaps": True} if spec.gaps else {}
    kw |= {"on_frame": on_frame} if on_frame is not None and spec.on_frame else {}
    coverage = None
    with progress(n_expected, "track") as bar:
        try:
            points, conf, *more = track(_Counted(frames(), n_expected), index, progress=lambda t: bar.update(1),
                                        **kw)
            coverage = more[0] if more else None
        except FaceLostError as exc:
            where_f = source.frames[exc.frame] if exc.frame < len(source.frames) else exc.frame
            msg = f"{source.path}: {str(exc).replace(f'frame {exc.frame}', f'frame {where_f}')}"
            if not keep_partial or exc.frame < 1:
                raise InputError(msg + ("; rerun with --keep-partial to keep the frames before it"
                                        if exc.frame >= 1 else "")) from None
            log.warning("%s; keeping the %d frames tracked before it (--keep-partial)", msg, exc.frame)
            points, conf = exc.points, exc.confidence
        except ValueError as exc:
            raise InputError(f"{where}: {exc}") from exc
    if stopped:
        if not keep_partial:
            raise InputError(f"{stopped[0]}; rerun with --keep-partial to keep the {len(points)} frames "
                             f"tracked up to then")
        log.warning("%s; keeping the %d frames tracked (--keep-partial)", stopped[0], len(points))
    return points, conf, coverage


class _Counted:
    """An iterator of frames that tells how many it expects (``operator.length_hint``): a tracker sizes its
    per-frame arrays once instead of growing them."""

    def __init__(self, it, n):
        self._it, self._n = it, n

    def __iter__(self):
        return self

    def __next__(self):
        return next(self._it)

    def __length_hint__(self) -> int:
        return int(self._n or 0)


def _coverage(coverage, T: int, frame_numbers, source, video):
    """``found``, ``segment`` and the gaps' description of a tracker's coverage (all None without one)."""
    if coverage is None:
        return None, None, None
    gaps = describe_gaps(coverage.found[:T], coverage.status[:T], coverage.cuts[:T], frames=frame_numbers,
                         fps=source.fps)
    segment = segment_ids(coverage.found[:T], coverage.cuts[:T])
    if gaps:
        where = "; ".join(f"{g['reason']} at frame {g['start']}" + (f" for {g['frames']} frames" if g["frames"] else "")
                          for g in gaps[:5])
        log.warning("%s: %s, %d segments tracked apart (%s%s)", video, gap_summary(gaps), int(segment.max()) + 1,
                    where, "; ..." if len(gaps) > 5 else "")
    return coverage.found[:T].astype(bool), segment, gaps


def filter_segments(points, conf, segment, *, fps, settings, where, anchors=(), window=WINDOW, margin=MARGIN,
                    in_place=False, keep_raw=True):
    """:func:`~._landmark_filter.apply_filter` on each segment of the take apart (the whole take without
    *segment*), so that nothing is smoothed across a gap or a scene cut; frames in gaps stay as they are.
    A segment longer than :data:`~retarget_cli.methods.decomposition.temporal.WINDOW` + ``MARGIN`` frames is
    filtered in overlapping windows (:func:`~retarget_cli.methods.decomposition.temporal.take_windows`), so the
    smoother's per-frame state (~16 KB a frame for 68 points) is held for one window at a time; the smoother's
    gain forgets its start within the margin, so the result is the whole segment's to rounding.

    *in_place* (float64 *points* of a take of more than one window): the filtered points are written into
    *points* itself (each window's rows once the next window has read its input, so every window reads the
    tracker's points) and the raw points returned are a float32 copy taken first: the take's landmarks are
    held once at full precision, not twice. *keep_raw* false: no raw points are returned (None; the caller
    kept them already), and none are copied.

    Returns (points (T, L, 2), raw (T, L, 2) or None, meta) like ``apply_filter``.
    """
    whole = segment is None or len(segments_of(segment)) == 1 and (segment >= 0).all()
    if whole and len(take_windows(len(points), window, margin)) == 1:
        out, raw, meta = apply_filter(points, conf, fps=fps, settings=settings, where=where, anchors=anchors)
        return out, raw if keep_raw else None, meta
    in_place = in_place and isinstance(points, np.ndarray) and points.dtype == np.float64
    if settings["filter"] == "none" or not keep_raw:
        raw = None
    elif in_place:
        raw = points.astype(np.float32)
    else:  # the tracker's points themselves (no copy when they are float64: the caller keeps them as the raw points)
        raw = np.asarray(points, dtype=np.float64)
    out = points if in_place else np.array(points, dtype=np.float64)
    meta = {"method": settings["filter"]}
    pending = None  # the last window's rows, written once the next window has read its input (windows overlap)
    for a, b in [(0, len(points))] if whole else segments_of(segment):
        # a long segment is filtered window by window (the smoother's state of one window held at a time)
        for wa, wb, lo, hi in take_windows(b - a, window, margin):
            lo, hi = a + lo, a + hi
            part, _, meta = apply_filter(points[lo:hi], conf[lo:hi], fps=fps, settings=settings, where=where,
                                         anchors=[i - lo for i in anchors if lo <= i < hi])
            if pending is not None:
                out[pending[0]] = pending[1]
            pending = (slice(a + wa, a + wb), part[a + wa - lo:a + wb - lo])
            del part
    if pending is not None:
        out[pending[0]] = pending[1]
        del pending
    if whole:
        return out, raw, meta
    # a gap holds the last found frame's landmarks (after filtering), the first found frame's before any
    found = np.asarray(segment) >= 0
    last = np.maximum.accumulate(np.where(found, np.arange(len(out)), -1))
    src = np.where(last >= 0, last, int(np.argmax(found)))
    gap = np.flatnonzero(src != np.arange(len(out)))
    out[gap] = out[src[gap]]  # in place: the rows copied from are found ones, which this does not change
    return out, raw, meta


def _track_gaze(video, points, conf, segment, *, start, end, step, fps, settings, progress, crops=None, size=None):
    """Each eye's gaze in every tracked frame: each iris located inside the tracked eye
    (:func:`retarget_cli.methods.tracking.gaze.gaze`; a closed eye or a lost frame holds the last seen
    value), then filtered with the landmarks' filter (*settings*, per segment, :func:`filter_segments`) in
    pixels of the eye's median width, the held frames given no weight.

    The frames are the eyes' pixels kept while tracking (*crops*, a :class:`~retarget_cli.io.atomic.CropSpill`
    of frames of *size* ``(W, H)``) where they hold every pixel the gaze reads at the final landmarks
    (:func:`~retarget_cli.methods.tracking.gaze.crops_cover`; the same pixels, so the same gaze), else the
    video decoded again.

    Returns
    -------
    gaze : ndarray (T, 2, 2), float64
        Eye widths (:attr:`retarget_cli.io.landmarks.Landmarks.gaze`).
    valid : ndarray (T, 2), bool
        Frames where the eye's iris was seen.
    """
    T = len(points)
    kept = crops is not None and len(crops) >= T and bool(crops_cover(crops.boxes()[:T], points, conf, size).all())
    if crops is not None:
        log.debug("gaze: %s", "the eyes' pixels kept while tracking" if kept else
                  "the eyes' pixels kept while tracking miss some the gaze reads; decoding the video again")
    with FrameSource(video, start=start, end=end, step=step, fps=fps, gray=True, warn_missing=False) as src, \
            progress(T, "gaze") as bar, large_frame_allocations(src.frame_size[0] * src.frame_size[1] * 3):
        frames = crops.frames(src.frame_size, T) if kept else islice(src, T)  # only the T tracked (truncated video)
        g = gaze_fn(frames, points, confidence=conf, progress=bar.update)
    valid = ~g.held
    P = np.asarray(points, dtype=np.float64)
    width = np.array([np.nanmedian(np.hypot(*(P[:, e[1]] - P[:, e[0]]).T)) for e in EYES_68])
    width = np.where(np.isfinite(width) & (width > 0), width, 1.0)
    px, _, _ = filter_segments(g.offset * width[None, :, None], valid.astype(np.float64), segment, fps=src.fps,
                               settings=settings, where=f"{video} (gaze)")
    out = np.asarray(px, dtype=np.float64) / width[None, :, None]
    # the filter gives the unseen frames no weight, but its motion model carries the last velocity through them
    # (on d3 a 14-frame squint drifted to 1.7 eye widths): an unseen eye holds its last seen, filtered gaze
    for e in range(out.shape[1]):
        seen = valid[:, e]
        if seen.any() and not seen.all():
            last = np.maximum.accumulate(np.where(seen, np.arange(T), -1))
            out[:, e] = out[np.where(last >= 0, last, int(np.argmax(seen))), e]
    log.info("gaze: iris seen in %.1f%% of the eye-frames; horizontal sd %.3f, vertical sd %.3f eye widths",
             100.0 * valid.mean(), float(np.std(out[..., 0])), float(np.std(out[..., 1])))
    return out, valid


#: The eyes' pixels kept for the gaze take at most this many bytes on disk (about 13,000 frames at 1080p, 58,000
#: at 512x512): past it they are dropped and the gaze decodes the video again.
CROPS_MAX_BYTES = 1 << 30


def _keep_eyes(crops):
    """The tracker's ``on_frame``: each frame's eyes (:func:`~retarget_cli.methods.tracking.gaze.eye_crop`) kept in
    *crops*, up to :data:`CROPS_MAX_BYTES`."""

    failed = []

    def keep(t, gray, points):
        if failed:
            return
        try:
            crops.add(gray, eye_crop(points))
        except OSError as exc:  # a full disk, say: the gaze decodes the video again (fewer crops than frames)
            failed.append(exc)
            crops.discard()
            log.warning("%s: the eyes' pixels could not be kept for the gaze (%s); the video is decoded again",
                        crops.path, exc)
            return
        if crops.nbytes > CROPS_MAX_BYTES:  # a long take: its disk freed, the gaze decodes the video again
            failed.append(None)
            crops.discard()
            log.info("the eyes' pixels kept for the gaze passed %d MiB at frame %d; the gaze decodes the video "
                     "again", CROPS_MAX_BYTES >> 20, t)

    return keep


def held_confidence(conf, found):
    """Confidences for the head fit: a gap frame takes those of the frame whose landmarks it holds.

    A gap frame keeps the last found frame's landmarks (confidence 0 in the file); fitting the head with
    that frame's confidences gives it the same head pose instead of a fit with no weight at all.
    """
    if found is None or np.all(found):
        return conf
    f = np.asarray(found, bool)
    last = np.maximum.accumulate(np.where(f, np.arange(len(f)), -1))
    return np.asarray(conf)[np.where(last >= 0, last, int(np.argmax(f)))]


def _hold_gap_confidence(conf, found):
    """:func:`held_confidence` written into *conf* itself: each gap frame's row takes the confidences of the
    frame whose landmarks it holds. Returns what undoes it (the rows and their values), or None (no gap)."""
    if found is None or np.all(found):
        return None
    f = np.asarray(found, bool)
    last = np.maximum.accumulate(np.where(f, np.arange(len(f)), -1))
    src = np.where(last >= 0, last, int(np.argmax(f)))
    rows = np.flatnonzero(src != np.arange(len(f)))
    saved = conf[rows].copy()
    conf[rows] = conf[src[rows]]  # the rows read from are found ones, which this does not change
    return rows, saved


def _write_track_overlay(overlay, video, points, conf, head, source, *, start, end, step, fps, progress):
    """The overlay video: the frames decoded again with the landmarks and the head frame drawn."""

    with FrameSource(video, start=start, end=end, step=step, fps=fps, warn_missing=False) as again, \
            progress(len(points), "overlay") as bar:
        def upto():
            try:
                yield from again
            except TruncatedInputError:
                return
        write_overlay(overlay, upto(), points, conf, head, fps=source.fps, frame_size=source.frame_size,
                      progress=lambda t: bar.update(1))


@validate_params(TRAIN_PARAMS)
def run_train_tracker(*, video, annotations, output, fps=None, rigid_points=None, stages=5, trees=4, depth=4,
                      face_size=200, seed=0, progress=_no_progress) -> list[Path]:
    """Train a Facemark LBF model from annotated frames of *video*; write it to *output* atomically.

    *annotations* are ``.pts`` files (frame number ending the name) or
    ``frame,point,x,y`` CSV files, as ``track`` reads them. The model file is
    an OpenCV ``FacemarkLBF`` model (``cv::FileStorage`` YAML, gzip-compressed
    when *output* ends in ``.gz``) for ``track --method facemark --model``.
    """

    files = [_require(a, "annotation file") for a in (annotations or [])]
    if not files:
        raise InputError("train-tracker: give at least one annotation file (.pts or CSV)")
    ann, src = read_annotations(files)
    last = max(ann)
    images = {}
    with FrameSource(video, end=last + 1, fps=fps) as source:
        check_not_input(output, source.files() + files)
        W, H = source.frame_size
        for f, P in ann.items():
            if source.frame_count and f >= source.frame_count:
                raise InputError(f"{src[f]}: frame {f} is past the last frame of {source.path} "
                                 f"({source.frame_count - 1})")
            if f in source.missing:
                raise InputError(f"{src[f]}: annotates frame {f}, which the image sequence lacks (a gap in its "
                                 "numbering)")
            try:
                check_inside(P, (W, H), f"frame {f}")
            except ValueError as exc:
                raise InputError(f"{src[f]}: {exc}") from None
        try:
            for i, img in enumerate(source):
                if i in ann:
                    images[i] = img
        except TruncatedInputError as exc:
            missing = [f for f in ann if f not in images]
            raise InputError(f"{exc}; annotated frame {missing[0]} ({src[missing[0]]}) could not be read") \
                from None
    missing = [f for f in ann if f not in images]
    if missing:
        raise InputError(f"{src[missing[0]]}: frame {missing[0]} is past the last frame of {video}")
    keys = sorted(ann)
    if len(keys) < 5:
        log.warning("training from %d annotated frame(s); 5 or more that span the expressions work far better",
                    len(keys))
    with progress(stages, "train") as bar:
        try:
            model = train_lbf([images[f] for f in keys], np.stack([ann[f] for f in keys]), stages=stages,
                              trees=trees, depth=depth, rigid_points=rigid_points, face_size=face_size, seed=seed,
                              progress=lambda k: bar.update(1))
        except ValueError as exc:
            raise InputError(f"{files[0]}: {exc}") from exc
    model.info["retarget_frames"] = [int(f) for f in keys]
    model.info["retarget_source"] = Path(video).name
    save_lbf_model(output, model)
    log.info("trained a %d-point Facemark LBF model from %d annotated frames (%d samples); training error %.2f px",
             model.n_points, len(keys), model.info["retarget_samples"], model.info["retarget_train_error_px"])
    return [Path(output)]


def _read_point_source(src: Path):
    """Points by frame from a folder of ``.pts`` files or a ``frame,point,x,y`` CSV, and the source's digest."""

    if src.is_dir():
        files = sorted(src.glob("*.pts"))
        if not files:
            raise InputError(f"{src}: folder holds no .pts file")
        return read_annotations(files)[0], digest_files(files)
    if src.suffix.lower() == ".csv":
        return read_csv_landmarks(src), sha256_file(src)
    raise InputError(f"{src}: unsupported landmarks source; expected a .csv, a .npz or a folder of .pts files")


def _read_npz_source(src: Path, fps, frame_size):
    """Points by frame, confidences (or None), fps and frame size (given ones first) and digest of an NPZ."""

    data = load_npz(src)
    if "points" not in data:
        raise InputError(f"{src}: missing key 'points' (float (T, L, 2)); found {sorted(data)}")
    P = np.asarray(data["points"], dtype=np.float64)
    if P.ndim != 3 or P.shape[2] != 2 or 0 in P.shape:
        raise InputError(f"{src}: 'points' must have shape (T, L, 2), got {P.shape}")
    frames = np.asarray(data.get("frames", np.arange(len(P))), dtype=np.int64)
    if frames.shape != (len(P),):
        raise InputError(f"{src}: 'frames' must have shape {(len(P),)}, got {frames.shape}")
    conf = None
    if "confidence" in data:
        conf = np.asarray(data["confidence"], dtype=np.float64)
        if conf.shape != P.shape[:2]:
            raise InputError(f"{src}: 'confidence' must have shape {P.shape[:2]}, got {conf.shape}")
    fps = fps or (float(data["fps"]) if "fps" in data else None)
    size = frame_size
    if size is None and "frame_size" in data:
        size = tuple(int(v) for v in np.asarray(data["frame_size"]).ravel()[:2])
    return dict(zip(frames.tolist(), P)), conf, fps, size, sha256_file(src)


@validate_params(IMPORT_PARAMS)
def run_import(*, source, output, fps=None, frame_size=None, rigid_points=None, smooth_head=0,
               filter=FILTER_DEFAULTS["filter"],
               filter_model=FILTER_DEFAULTS["filter_model"], filter_process_noise=FILTER_DEFAULTS["filter_process_noise"],
               filter_measurement_noise=FILTER_DEFAULTS["filter_measurement_noise"],
               filter_robust=FILTER_DEFAULTS["filter_robust"], filter_min_cutoff=FILTER_DEFAULTS["filter_min_cutoff"],
               filter_beta=FILTER_DEFAULTS["filter_beta"], filter_d_cutoff=FILTER_DEFAULTS["filter_d_cutoff"],
               ) -> list[Path]:
    """Bring landmarks from another tool into the ``landmarks.npz`` contract.

    *source* is a ``frame,point,x,y`` CSV, an NPZ holding ``points`` (T, L, 2)
    (``confidence``, ``fps``, ``frame_size``, ``frames`` optional), or a
    folder of ``.pts`` files named with their frame number. Head motion and
    stabilization are computed with :func:`~retarget_cli.methods.tracking.head.estimate_head`
    (the routine ``track`` uses), optionally smoothed in time. The landmark
    filter settings (``filter``, ``filter_*``) are those of :func:`run_track`,
    ``rts`` by default as there (it was ``none``; measured on bench/temporal.py's ICT take, 2026-12-02,
    nnls: mesh error 40.4 → 31.5 %, jitter 12.4 → 1.9× the truth's; docs/temporal.md); the source's points
    are kept as ``points_raw``. Filtering assumes consecutive frames: a source with gaps between its
    frames is imported unfiltered, with a warning.
    """

    fset = {k: v for k, v in locals().items() if k in FILTER_DEFAULTS}

    src = _require(source, "landmarks source")
    check_not_input(output, [src])
    if src.suffix.lower() == ".npz" and not src.is_dir():
        by_frame, conf, fps, size, digest = _read_npz_source(src, fps, frame_size)
    else:
        by_frame, digest = _read_point_source(src)
        conf, size = None, frame_size
    frames = np.array(sorted(by_frame), dtype=np.int64)
    points = np.stack([by_frame[f] for f in frames])
    finite = np.isfinite(points).all(-1)
    conf = finite.astype(np.float64) if conf is None else np.where(finite, np.clip(conf, 0, 1), 0.0)
    if not finite.all():
        # a missing point keeps the contract's finite coordinates: carried from its nearest finite frame
        for i in range(points.shape[1]):
            ok = np.flatnonzero(finite[:, i])
            if ok.size == 0:
                raise InputError(f"{src}: landmark {i} has no finite coordinate in any frame")
            near = ok[np.abs(np.arange(len(points))[:, None] - ok[None]).argmin(1)]
            points[:, i] = points[near, i]
    gaps = np.flatnonzero(np.diff(frames) != 1)
    if fset["filter"] != "none" and gaps.size:
        log.warning("%s: frames %d and %d are not consecutive; imported without the %s filter", src,
                    int(frames[gaps[0]]), int(frames[gaps[0] + 1]), fset["filter"])
        fset["filter"] = "none"
    points, raw, fmeta = apply_filter(points, conf, fps=fps or 30.0, settings=fset, where=str(src))
    try:
        head, stab = estimate_head(points, conf, rigid_points=rigid_points)
    except ValueError as exc:
        raise InputError(f"{src}: {exc}") from exc
    if smooth_head:
        head = _smooth(head, smooth_head)
        stab = apply_similarity(invert_similarity(head), points)
    meta = {"tracker": "import", "source": src.name, "source_sha256": digest,
            "parameters": {"smooth_head": smooth_head, "rigid_points": rigid_points}, "filter": fmeta}
    save_landmarks(output, Landmarks(points, conf, head, stab, fps or 30.0,
                                     np.array(size if size else (0, 0)), None, meta, frames=frames,
                                     points_raw=raw))
    log.info("imported %d frames x %d points from %s", len(points), points.shape[1], src)
    return [Path(output)]


def _track_files(kw) -> list[Path]:
    return [Path(kw.get("base_dir") or ".") / a for a in (kw.get("annotations") or [])]


def _track_expand(name, path) -> list[Path]:
    return sequence_files(path) if name in ("video", "neutral") and is_sequence(path) else [path]


#: The pipeline stage (:mod:`retarget_cli.run.pipeline`).
STAGE = Stage(
    "track",
    "Track landmarks through a video from an annotated first frame.",
    PARAMS,
    run_track,
    more_params=lambda: tracker_params(p.name for p in PARAMS),
    extra_inputs=_track_files,
    expand_input=_track_expand,
    uses_progress=True,
    uses_base_dir=True,
)


# --------------------------------------------------------------------------- the commands


def _cli_track(values, out):
    kw = dict(values, annotations=list(values["annotations"]), rigid_points=values["rigid_points"] or None)
    return run_track(**kw, progress=out.progress)


def _cli_train_tracker(values, out):
    kw = dict(values, annotations=list(values["annotations"]), rigid_points=values["rigid_points"] or None)
    return run_train_tracker(**kw, progress=out.progress)


def _cli_import(values, out):
    return run_import(**dict(values, rigid_points=values["rigid_points"] or None))


_FILTER_FLAGS = tuple(p.name for p in FILTER_PARAMS)
_TRACK_FLAGS = (
    Flag("video", argument=True, path="file"),
    Flag("init", path="file", default="auto",
         help="Annotation of the first tracked frame: iBUG .pts (frame from a name like face_00120.pts), "
              "a frame,point,x,y CSV, or auto: the pretrained detector annotates it and writes "
              "<output stem>.init_NNNNN.pts beside the output for review (needs the extra detect)."),
    Flag("annotations", decls=("--annotation",), path="file", multiple=True, show_default=False,
         help="More annotated frames (.pts or CSV); each re-anchors the track. Repeatable."),
    "init_frame",
    output_flag("landmarks.npz", "Landmarks file.", required=False),
    Flag("overlay", path="file", show_default=False,
         help="Also write an mp4 with the landmarks (green = confident, red = lost) and the head frame."),
    Flag("neutral", path="file", show_default=False, metavar="IMAGE_OR_CLIP"),
    "method", "fuse", Flag("model", path="file"), "window", "levels", "fb_threshold", "anchor", "start", "end",
    "step", "downscale", "fps", "smooth_head", "head_pose",
    Flag("rigid_points", decls=("--rigid-points",), value="indices", metavar="SPEC", show_default=False,
         help="Landmarks that define head motion, e.g. 27-31,33,35,36,39,42,45 (default: eye corners "
              "and nose for 68 points, else all)."),
    "keep_partial", "gaze", *_FILTER_FLAGS,
)

#: ``track``, ``train-tracker`` and ``import`` (the CLI builds them: :mod:`retarget_cli.cli.commands`).
COMMANDS = [
    Command(
        "track",
        """Track facial landmarks through VIDEO (a video file or an image-sequence pattern such as
    'frames/%05d.png' or 'frames/*.exr'), from one or more annotated frames (by default the detector
    annotates the first), or with --method detect by a pretrained detector on every frame.""",
        _all_track_params,
        lambda: (*_TRACK_FLAGS, *(p.name for p in tracker_params(q.name for q in PARAMS))),
        _cli_track,
    ),
    Command(
        "train-tracker",
        """Train a Facemark tracking model on annotated frames of VIDEO (a video or an image-sequence pattern).

    ANNOTATIONS are .pts files named with their frame number (face_00120.pts) or frame,point,x,y CSV files,
    as for `track`; 5 or more frames that span the actor's expressions. Use the model with
    `retarget track VIDEO --init face_00000.pts --method facemark --model facemark.yaml`.""",
        lambda: TRAIN_PARAMS,
        (Flag("video", argument=True, path="file"),
         Flag("annotations", argument=True, nargs=-1, required=True, path="file"),
         output_flag("facemark.yaml", "Model file (OpenCV Facemark LBF; gzip-compressed if the name ends in .gz).",
                     required=False),
         "fps", Flag("rigid_points", value="indices", metavar="SPEC"), "stages", "trees", "depth", "face_size",
         "seed"),
        _cli_train_tracker,
    ),
    Command(
        "import",
        """Bring landmarks from another tool into landmarks.npz, with head motion and stabilization.

    SOURCE is a frame,point,x,y CSV, an NPZ with 'points' (T, L, 2) or a folder of .pts files (frame number
    from each name, e.g. face_00120.pts).""",
        lambda: IMPORT_PARAMS,
        (Flag("source", argument=True, path="path"),
         output_flag("landmarks.npz", "Landmarks file (landmarks.npz contract).", required=False),
         "fps", Flag("frame_size", value="size", value_args=(("example", "1920x1080"),), metavar="WxH"),
         Flag("rigid_points", value="indices", metavar="SPEC"), "smooth_head", *_FILTER_FLAGS),
        _cli_import,
    ),
]
