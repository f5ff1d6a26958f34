"""Stage runners: read the input files, call the pure stage function, write
the outputs atomically. The CLI commands and ``retarget run`` both call these.

Each runner returns the list of files it wrote.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import re
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.atomic import check_name, check_not_input, sha256_file, tracked_outputs, write_text
from ..io.vertexmap import read_vertex_map  # noqa: F401  (re-exported; run_auto_pose uses it)
from .filtering import FILTER_DEFAULTS

log = logging.getLogger(__name__)


@contextlib.contextmanager
def _no_progress(length, label):
    class _Bar:
        def update(self, n):
            pass

    yield _Bar()


def _require(path, what: str) -> Path:
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: {what} not found")
    return path


# --------------------------------------------------------------------------- track


def run_track(*, video, init, output, method="auto", window=21, levels=3, fb_threshold=1.0, anchor=True,
              rigid_points=None, annotations=None, init_frame=None, start=0, end=None, step=1, downscale=1.0,
              fps=None, smooth_head=0, overlay=None, keep_partial=False, model=None, fuse=True, base_dir=None,
              progress=_no_progress, filter=FILTER_DEFAULTS["filter"], filter_model=FILTER_DEFAULTS["filter_model"],
              filter_process_noise=FILTER_DEFAULTS["filter_process_noise"],
              filter_measurement_noise=FILTER_DEFAULTS["filter_measurement_noise"],
              filter_robust=FILTER_DEFAULTS["filter_robust"], filter_min_cutoff=FILTER_DEFAULTS["filter_min_cutoff"],
              filter_beta=FILTER_DEFAULTS["filter_beta"], filter_d_cutoff=FILTER_DEFAULTS["filter_d_cutoff"],
              ) -> list[Path]:
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
    (``filter``, ``filter_*``; :mod:`retarget_cli.stages.filtering`): the
    points are filtered before the head motion is estimated, and the tracker's
    own points are kept as ``points_raw``. Annotated frames keep their given
    points and anchor the filter.
    """
    from ..io.annotations import read_annotations
    from ..io.frames import FrameSource, TruncatedInputError
    from ..io.landmarks import Landmarks, save_landmarks
    from ..track.head import apply_similarity, estimate_head, invert_similarity
    from ..track.head import smooth_head as smooth_head_fn
    from ..track.lk import FaceLostError, check_inside, track_lk
    from .detect import detect_frame, init_pts_path, is_auto, write_pts_once
    from .filtering import apply_filter

    fset = {k: v for k, v in locals().items() if k in FILTER_DEFAULTS}
    auto = is_auto(init)
    if not auto:
        init = _require(init, "annotation file")
    extra = [Path(base_dir or ".") / a for a in (annotations or [])]
    for a in extra:
        _require(a, "annotation file")
    if method not in ("auto", "lk", "eigenpoints", "markers", "facemark", "detect"):
        raise ValueError(f"method: expected 'auto', 'detect', 'lk', 'eigenpoints', 'markers' or 'facemark', "
                         f"got {method!r}")
    if method == "auto":
        from ..track.detect import detector_installed

        method = "detect" if detector_installed() else "lk"
        log.info("method auto: tracking with %s%s", method,
                 "" if method == "detect" else " (install the extra 'detect' for the pretrained detector)")
    given = extra if auto else [init, *extra]
    ann, src = read_annotations(given, frame=init_frame) if given else ({}, {})
    need_auto = auto and start not in ann
    detector = None
    if need_auto or method == "detect":
        from ..track.detect import Detector

        detector = Detector()  # fails here, before any decoding, when the extra is not installed
    if ann and method == "detect" and len(next(iter(ann.values()))) != Detector.n_points:
        raise InputError(f"{src[next(iter(ann))]}: method detect places {Detector.n_points} points but the "
                         f"annotation has {len(next(iter(ann.values())))}")
    fitter = None
    if method == "facemark":
        from ..io.facemark import load_facemark

        if not model:
            raise InputError("method facemark needs a model file (--model, or track.model); "
                             "train one with 'retarget train-tracker'")
        fitter = load_facemark(model)
        n_ann = len(next(iter(ann.values()))) if ann else 68
        if fitter.n_points != n_ann:
            raise InputError(f"{model}: the Facemark model was trained for {fitter.n_points} points but "
                             f"{init} has {n_ann}")
    elif model:
        log.warning("model %s is used by method facemark only; ignored by %s", model, method)
    # lk and detect track grayscale frames: convert them in the decoding thread
    with FrameSource(video, start=start, end=end, step=step, fps=fps, gray=method in ("lk", "detect")) as source:
        check_not_input(output, source.files() + given)
        if overlay:
            check_not_input(overlay, source.files() + given)
        init_out = init_pts_path(output, start) if need_auto else None
        if init_out is not None:
            check_not_input(init_out, source.files() + given + [output] + ([overlay] if overlay else []))
        W, H = source.frame_size
        it = iter(source)
        ahead = []
        if need_auto and method != "detect":
            ahead.append(next(it))  # an undecodable video raises TruncatedInputError (an InputError) here
            ann[start] = detect_frame(ahead[0], detector=detector, where=f"{source.path}: frame {start}")
            src[start] = init_out
            write_pts_once(init_out, ann[start])
            log.info("%s: frame %d annotated by the detector; wrote %s", source.path, start, init_out)
        if start not in ann and method != "detect":
            raise InputError(f"{init}: the first tracked frame ({start}) must be annotated; annotated frames: "
                             f"{', '.join(map(str, list(ann)[:8]))} (use --start or --init-frame)")
        index = {}
        for f, P in ann.items():
            try:
                check_inside(P, (W, H), f"frame {f}")
            except ValueError as exc:
                raise InputError(f"{src[f]}: {exc}") from None
            if f < start or (end is not None and f >= end):
                log.info("%s: frame %d is outside the tracked range, ignored", src[f], f)
            elif (f - start) % step:
                raise InputError(f"{src[f]}: frame {f} is not tracked with start {start} and step {step}")
            else:
                index[(f - start) // step] = P
        stopped = []

        def frames():
            try:
                yield from ahead
                yield from it
            except TruncatedInputError as exc:
                stopped.append(exc)

        n_expected = None
        if source.frame_count:
            last = source.frame_count if end is None else min(end, source.frame_count)
            n_expected = max(0, (last - start + step - 1) // step)
        with progress(n_expected, "track") as bar:
            try:
                if method == "eigenpoints":
                    from ..track.eigenpoints import track_eigenpoints

                    if downscale != 1:
                        log.warning("downscale applies to the lk tracker only; eigenpoints uses its own window")
                    points, conf = track_eigenpoints(frames(), index, rigid_points=rigid_points,
                                                     progress=lambda t: bar.update(1))
                elif method == "detect":
                    from ..track.detect import track_detect

                    points, conf = track_detect(frames(), index, detector=detector, downscale=downscale,
                                                fuse=fuse, progress=lambda t: bar.update(1))
                elif method == "markers":
                    from ..track.markers import track_markers

                    points, conf = track_markers(frames(), index, progress=lambda t: bar.update(1))
                elif method == "facemark":
                    from ..track.facemark import track_facemark

                    if downscale != 1:
                        log.warning("downscale applies to the lk tracker only; facemark fits at full resolution")
                    points, conf = track_facemark(frames(), index, model=fitter, rigid_points=rigid_points,
                                                  progress=lambda t: bar.update(1))
                else:
                    points, conf = track_lk(frames(), index, window=window, levels=levels,
                                            fb_threshold=fb_threshold, anchor=anchor, rigid_points=rigid_points,
                                            downscale=downscale, progress=lambda t: bar.update(1))
            except FaceLostError as exc:
                where = source.frames[exc.frame] if exc.frame < len(source.frames) else exc.frame
                msg = f"{source.path}: {str(exc).replace(f'frame {exc.frame}', f'frame {where}')}"
                if not keep_partial or exc.frame < 1:
                    raise InputError(msg + ("; rerun with --keep-partial to keep the frames before it"
                                            if exc.frame >= 1 else "")) from None
                log.warning("%s; keeping the %d frames tracked before it (--keep-partial)", msg, exc.frame)
                points, conf = exc.points, exc.confidence
            except ValueError as exc:
                raise InputError(f"{init_out or init or video}: {exc}") from exc
        if stopped:
            if not keep_partial:
                raise InputError(f"{stopped[0]}; rerun with --keep-partial to keep the {len(points)} frames "
                                 f"tracked up to then")
            log.warning("%s; keeping the %d frames tracked (--keep-partial)", stopped[0], len(points))
        frame_numbers = np.asarray(source.frames[:len(points)], dtype=np.int64)
        files = source.files()
    if need_auto and method == "detect":
        write_pts_once(init_out, points[0])
    points, raw, fmeta = apply_filter(points, conf, fps=source.fps, settings=fset, where=str(video),
                                      anchors=[i for i in index if i < len(points)])
    head, stab = estimate_head(points, conf, rigid_points=rigid_points)
    if smooth_head:
        head = smooth_head_fn(head, smooth_head)
        stab = apply_similarity(invert_similarity(head), points)
    meta = {
        "tracker": method,
        "parameters": {"window": window, "levels": levels, "fb_threshold": fb_threshold, "anchor": anchor,
                       "downscale": downscale, "start": start, "end": end, "step": step,
                       "smooth_head": smooth_head, **({"fuse": fuse} if method == "detect" else {})},
        "filter": fmeta,
        "source": Path(video).name,
        "source_sha256": sha256_file(files[0]) if len(files) == 1 else digest_files(files),
        "annotation": [Path(p).name for p in given + ([init_out] if init_out else [])],
        "annotated_frames": [int(f) for f in ann],
        "init": "auto" if auto else Path(init).name,
    }
    if fitter is not None:
        meta["model"], meta["model_sha256"] = Path(model).name, sha256_file(model)
    save_landmarks(output, Landmarks(points, conf, head, stab, source.fps, np.array([W, H]), None, meta,
                                     frames=frame_numbers, points_raw=raw))
    written = [Path(output)] + ([init_out] if init_out else [])
    log.info("tracked %d frames x %d points; mean confidence %.3f", len(points), points.shape[1], conf.mean())
    if overlay:
        from ..io.overlay import write_overlay

        with FrameSource(video, start=start, end=end, step=step, fps=fps) as again, \
                progress(len(points), "overlay") as bar:
            def upto():
                try:
                    yield from again
                except TruncatedInputError:
                    return
            write_overlay(overlay, upto(), points, conf, head, fps=source.fps, frame_size=(W, H),
                          progress=lambda t: bar.update(1))
        written.append(Path(overlay))
    return written


def run_train_tracker(*, video, annotations, output, fps=None, rigid_points=None, stages=5, trees=4, depth=4,
                      face_size=200, seed=0, progress=_no_progress) -> list[Path]:
    """Train a Facemark LBF model from annotated frames of *video*; write it to *output* atomically.

    *annotations* are ``.pts`` files (frame number ending the name) or
    ``frame,point,x,y`` CSV files, as ``track`` reads them. The model file is
    an OpenCV ``FacemarkLBF`` model (``cv::FileStorage`` YAML, gzip-compressed
    when *output* ends in ``.gz``) for ``track --method facemark --model``.
    """
    from ..io.annotations import read_annotations
    from ..io.facemark import save_lbf_model
    from ..io.frames import FrameSource, TruncatedInputError
    from ..track.facemark import train_lbf
    from ..track.lk import check_inside

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


def run_import(*, source, output, fps=None, frame_size=None, rigid_points=None, smooth_head=0, filter="none",
               filter_model=FILTER_DEFAULTS["filter_model"], filter_process_noise=FILTER_DEFAULTS["filter_process_noise"],
               filter_measurement_noise=FILTER_DEFAULTS["filter_measurement_noise"],
               filter_robust=FILTER_DEFAULTS["filter_robust"], filter_min_cutoff=FILTER_DEFAULTS["filter_min_cutoff"],
               filter_beta=FILTER_DEFAULTS["filter_beta"], filter_d_cutoff=FILTER_DEFAULTS["filter_d_cutoff"],
               ) -> list[Path]:
    """Bring landmarks from another tool into the ``landmarks.npz`` contract.

    *source* is a ``frame,point,x,y`` CSV, an NPZ holding ``points`` (T, L, 2)
    (``confidence``, ``fps``, ``frame_size``, ``frames`` optional), or a
    folder of ``.pts`` files named with their frame number. Head motion and
    stabilization are computed with :func:`~retarget_cli.track.head.estimate_head`
    (the routine ``track`` uses), optionally smoothed in time. The landmark
    filter settings (``filter``, ``filter_*``) are those of :func:`run_track`,
    but *filter* defaults to ``none`` here (imported points stay as given;
    the source's points are kept as ``points_raw`` when a filter is applied).
    Filtering assumes consecutive frames.
    """
    from .filtering import apply_filter

    fset = {k: v for k, v in locals().items() if k in FILTER_DEFAULTS}
    from ..io.annotations import read_annotations, read_csv_landmarks
    from ..io.atomic import load_npz
    from ..io.landmarks import Landmarks, save_landmarks
    from ..track.head import apply_similarity, estimate_head, invert_similarity
    from ..track.head import smooth_head as _smooth

    src = _require(source, "landmarks source")
    check_not_input(output, [src])
    conf = None
    size = frame_size
    if src.is_dir():
        files = sorted(src.glob("*.pts"))
        if not files:
            raise InputError(f"{src}: folder holds no .pts file")
        by_frame, _ = read_annotations(files)
        digest = digest_files(files)
    elif src.suffix.lower() == ".csv":
        by_frame = read_csv_landmarks(src)
        digest = sha256_file(src)
    elif src.suffix.lower() == ".npz":
        data = load_npz(src)
        if "points" not in data:
            raise InputError(f"{src}: missing key 'points' (float (T, L, 2)); found {sorted(data)}")
        P = np.asarray(data["points"], dtype=np.float64)
        if P.ndim != 3 or P.shape[2] != 2 or 0 in P.shape:
            raise InputError(f"{src}: 'points' must have shape (T, L, 2), got {P.shape}")
        frames = np.asarray(data.get("frames", np.arange(len(P))), dtype=np.int64)
        if frames.shape != (len(P),):
            raise InputError(f"{src}: 'frames' must have shape {(len(P),)}, got {frames.shape}")
        by_frame = dict(zip(frames.tolist(), P))
        if "confidence" in data:
            conf = np.asarray(data["confidence"], dtype=np.float64)
            if conf.shape != P.shape[:2]:
                raise InputError(f"{src}: 'confidence' must have shape {P.shape[:2]}, got {conf.shape}")
        fps = fps or (float(data["fps"]) if "fps" in data else None)
        if size is None and "frame_size" in data:
            size = tuple(int(v) for v in np.asarray(data["frame_size"]).ravel()[:2])
        digest = sha256_file(src)
    else:
        raise InputError(f"{src}: unsupported landmarks source; expected a .csv, a .npz or a folder of .pts files")
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


# --------------------------------------------------------------------------- select


#: Default regions of the 68-point layout (the synthetic take's config uses the same lists).
REGION_PRESETS_68 = {
    "brows-eyes": list(range(17, 27)) + list(range(36, 48)),
    "mouth": list(range(3, 14)) + list(range(48, 68)),
    "face": "all",
}


def region_specs(regions, n_points: int, k: int | None = None) -> dict[str, tuple[list[int], int | None]]:
    """Resolve region definitions to ``{name: (landmark ids, k)}``.

    A region is ``"all"``, a list of landmark ids, ``null`` (a preset of the
    68-point layout: ``brows-eyes``, ``mouth``, ``face``) or a mapping
    ``{points: ..., k: ...}`` where either key may be left out (preset points,
    the stage's k).
    """
    regions = regions or {"face": "all"}
    out = {}
    for name, spec in regions.items():
        check_name(name, "regions")
        rk = k
        if isinstance(spec, dict):
            bad = sorted(set(spec) - {"points", "k"})
            if bad:
                raise InputError(f"regions: {name!r} has unknown key {bad[0]!r}; expected 'points' and/or 'k'")
            rk = spec.get("k", k)
            if isinstance(rk, bool) or not isinstance(rk, int) or rk < 1:
                raise InputError(f"regions: {name!r} k must be an integer >= 1, got {rk!r}")
            spec = spec.get("points")
        if spec is None:
            if name not in REGION_PRESETS_68:
                raise InputError(f"regions: {name!r} needs 'points' (presets: {', '.join(REGION_PRESETS_68)})")
            if n_points != 68 and REGION_PRESETS_68[name] != "all":
                raise InputError(f"regions: preset {name!r} is for the 68-point layout but the take has {n_points} points; "
                                 "give its landmark ids")
            spec = REGION_PRESETS_68[name]
        if spec == "all":
            out[name] = (list(range(n_points)), rk)
            continue
        if not isinstance(spec, list) or not spec or not all(isinstance(i, int) and not isinstance(i, bool) for i in spec):
            raise InputError(f"regions: {name!r} must be 'all', a list of landmark indices or {{points, k}}")
        bad = [i for i in spec if not 0 <= i < n_points]
        if bad:
            raise InputError(f"regions: {name!r} names landmark {bad[0]} but the take has {n_points} (0..{n_points - 1})")
        out[name] = (list(spec), rk)
    return out


def region_points(regions, n_points: int) -> dict[str, list[int]]:
    """Resolve region definitions (``"all"`` or index lists) to index lists."""
    return {name: pts for name, (pts, _) in region_specs(regions, n_points).items()}



def run_select(*, landmarks, output, template=None, method="pca-extremes", k=12, regions=None,
               neutral_frame=0, kmeans_components=2, evaluate=None, plot=None, evaluate_k=40,
               contact_sheet=None, video=None, seed=0, progress=_no_progress) -> list[Path]:
    """Choose key frames per region; write ``keys.json`` and a ``targets.yaml`` template.

    With *evaluate*, also the error curve of every method (CSV), a JSON summary
    of the winner at each region's k (*evaluate* with suffix ``.json``) and,
    with *plot*, the curves as a picture (Fig. 6 of Chuang & Bregler 2002).
    With *contact_sheet*, the key frames cropped from *video* with their landmarks.
    """
    from ..io.landmarks import load_landmarks
    from ..io.stagefiles import write_keys, write_targets
    from ..select import curve_winner, evaluation_curve, key_error, select_keys

    landmarks = _require(landmarks, "landmarks file")
    outs = [o for o in (output, template, evaluate, plot, contact_sheet) if o]
    for o in outs:
        check_not_input(o, [landmarks] + ([video] if video else []))
    if evaluate and Path(evaluate).with_suffix(".json") in [Path(o) for o in (output, template, plot, contact_sheet) if o]:
        raise InputError(f"{evaluate}: its summary {Path(evaluate).with_suffix('.json')} would overwrite another output")
    if plot and not evaluate:
        raise InputError(f"{plot}: a plot needs the evaluation (--evaluate curve.csv)")
    if contact_sheet and not video:
        raise InputError(f"{contact_sheet}: a contact sheet needs the video (--video, or select.video)")
    lm = load_landmarks(landmarks)
    stab = lm.stabilized.astype(np.float64)
    include = () if neutral_frame is None else (neutral_frame,)
    if neutral_frame is not None and neutral_frame >= lm.n_frames:
        raise InputError(f"neutral_frame: frame {neutral_frame} is outside the take ({lm.n_frames} frames in {landmarks})")
    specs = region_specs(regions, lm.n_points, k)
    result, tmpl, curves, chosen_k = {}, {}, {}, {}
    with progress(len(specs) * (7 if evaluate else 1), "select") as bar:
        for name, (idx, rk) in specs.items():
            X = stab[:, idx].reshape(lm.n_frames, -1)
            # Frames where a landmark of the region is lost (NaN) can be neither keys
            # nor scored by eq. 5; decompose interpolates their weights later.
            keep = np.flatnonzero(np.isfinite(X).all(1))
            if keep.size == 0:
                raise InputError(f"{landmarks}: region {name!r}: every frame has lost (NaN) landmarks")
            if keep.size < lm.n_frames:
                log.warning("%s: region %s: %d frames with lost landmarks are left out of key selection",
                            landmarks, name, lm.n_frames - keep.size)
            bad_inc = [f for f in include if f not in set(keep.tolist())]
            if bad_inc:
                raise InputError(f"{landmarks}: region {name!r}: neutral frame {bad_inc[0]} has lost (NaN) landmarks; "
                                 "choose another neutral_frame")
            local = {int(f): i for i, f in enumerate(keep)}
            Xk = X[keep]
            inc = tuple(local[int(f)] for f in include)
            try:
                frames = keep[select_keys(Xk, rk, method=method, include=inc, seed=seed, components=kmeans_components)]
                bar.update(1)
                if evaluate:
                    rows = evaluation_curve(Xk, max(evaluate_k, len(frames)), k=len(frames), include=inc,
                                            seed=seed, progress=bar.update)
                    curves[name] = [{**r, "frames": [int(keep[f]) for f in r["frames"]]} for r in rows]
            except ValueError as exc:
                raise InputError(f"{landmarks}: region {name!r}: {exc}") from exc
            err = key_error(Xk, [local[int(f)] for f in frames])
            chosen_k[name] = len(frames)
            result[name] = {"points": idx, "method": method, "frames": [int(f) for f in frames], "error": round(err, 6)}
            tmpl[name] = {"keys": {int(f): f"target/{name}/key_{int(f):05d}.obj" for f in frames}}
            log.info("region %s: keys %s, E = %.4g (eq. 5)", name, result[name]["frames"], err)
    write_keys(output, landmarks, result)
    written = [Path(output)]
    if template:
        t = Path(template)
        if t.exists() and not t.read_text(encoding="utf-8", errors="replace").startswith(TEMPLATE_MARK):
            raise InputError(f"{t}: exists and was not written by 'retarget select'; "
                             "refusing to overwrite it (choose another --template path)")
        write_targets(t, tmpl, comment=TEMPLATE_MARK[2:] + (
            "Sculpt one OBJ per key frame (same topology for all), matching the actor's\n"
            "expression in that frame. Paths are relative to this file. Copy this file\n"
            "before editing: select rewrites it."))
        written.append(t)
    if evaluate:
        from ..io.atomic import write_json
        from ..select_report import curve_csv, write_curve_plot

        write_text(evaluate, curve_csv(curves))
        summary = {"method": method, "regions": {}}
        for name, rows in curves.items():
            try:
                summary["regions"][name] = curve_winner(rows, chosen_k[name])
            except ValueError:  # chosen k below 2: nothing evaluated there
                summary["regions"][name] = {"k": chosen_k[name], "winner": None}
            summary["regions"][name]["selected_error"] = result[name]["error"]
            log.info("region %s: at k = %d the lowest E is %s", name, chosen_k[name], summary["regions"][name]["winner"])
        summary_path = Path(evaluate).with_suffix(".json")
        write_json(summary_path, summary)
        written += [Path(evaluate), summary_path]
        if plot:
            write_curve_plot(plot, curves, chosen_k)
            written.append(Path(plot))
    if contact_sheet:
        from ..select_report import write_contact_sheet

        video = _require(video, "video file")
        write_contact_sheet(contact_sheet, video, lm.points,
                            {n: (r["points"], r["frames"]) for n, r in result.items()})
        written.append(Path(contact_sheet))
    return written


#: First line of the targets template ``select`` writes; a file without it is never overwritten.
TEMPLATE_MARK = "# targets.yaml template written by retarget select.\n"


# --------------------------------------------------------------------------- decompose


#: A landmark whose confidence is at or below this is lost in that frame.
LOST_CONFIDENCE = 1e-3


def run_decompose(*, landmarks, keys, output, csv=None, solver="nnls", formulation="whole", alpha=None, upper=None,
                  neutral_frame=0, confidence=True, lost_fraction=0.5, smooth_space="shape",
                  robust=1.0) -> list[Path]:
    """Weights over the key shapes for every frame and region; writes ``weights.npz``.

    Per region: landmarks with NaN coordinates and confidence 0 are lost;
    rows are weighted by confidence when *confidence* is true; frames where
    more than *lost_fraction* of the region's landmarks are lost (or fewer
    coordinates than weights remain) get weights interpolated from the
    neighbouring frames and are flagged in ``<region>_lost``. With
    ``formulation="delta"`` the weights are stored in whole-face form: the
    neutral key's column holds ``1 − Σ`` of the others, so ``apply`` needs no
    change (Lewis et al. 2005, §3).
    """
    from ..decompose import cardinality, decompose, interpolate_lost, jitter, mean_acceleration, row_residuals
    from ..io.landmarks import load_landmarks
    from ..io.stagefiles import read_keys, save_weights, weights_csv

    landmarks, keys = _require(landmarks, "landmarks file"), _require(keys, "keys file")
    check_not_input(output, [landmarks, keys])
    lm = load_landmarks(landmarks)
    kf = read_keys(keys)
    stab, conf = lm.stabilized, lm.confidence  # float32; a region's rows become float64 once, below
    T = lm.n_frames
    if formulation == "delta" and not 0 <= neutral_frame < T:
        raise InputError(f"neutral_frame: frame {neutral_frame} is outside the take ({T} frames in {landmarks})")
    regions, extras, diagnostics = {}, {}, {}
    for name, reg in kf.regions.items():
        bad = [f for f in reg["frames"] if f >= T]
        if bad:
            raise InputError(f"{keys}: region {name!r} key frame {bad[0]} is outside the take ({T} frames in {landmarks})")
        badp = [p for p in reg["points"] if p >= lm.n_points]
        if badp:
            raise InputError(f"{keys}: region {name!r} landmark {badp[0]} does not exist ({lm.n_points} points in {landmarks})")
        pts, frames = reg["points"], np.array(reg["frames"])
        # (a region of all the points in order needs no gather: at long takes every copy counts)
        every = list(pts) == list(range(lm.n_points))
        P = (stab if every else stab[:, pts]).astype(np.float64)
        C = (conf if every else conf[:, pts]).astype(np.float64)
        nan = ~np.isfinite(P).all(-1)
        if np.any(nan & (C > 0)):
            t, i = np.argwhere(nan & (C > 0))[0]
            raise InputError(f"{landmarks}: landmark {pts[i]} of region {name!r} is NaN in frame {t} "
                             f"but has confidence {C[t, i]:.3g}; expected finite coordinates or confidence 0")
        lost_pt = nan | (C <= LOST_CONFIDENCE)
        n_unknowns = len(frames) - (1 if formulation == "delta" else 0)
        if 2 * len(pts) < n_unknowns:
            raise InputError(f"{keys}: region {name!r} has {len(pts)} landmarks ({2 * len(pts)} coordinates) for "
                             f"{len(frames)} keys; expected at least {(n_unknowns + 1) // 2} landmarks")
        lost = (lost_pt.mean(1) > lost_fraction) | (2 * (~lost_pt).sum(1) < n_unknowns)
        if lost.all():
            raise InputError(f"{landmarks}: region {name!r} is lost in every frame")
        nan_keys = [int(f) for f in frames if nan[f].any()]
        if nan_keys:
            raise InputError(f"{landmarks}: region {name!r} key frame {nan_keys[0]} has NaN landmarks; "
                             "a key shape needs every landmark")
        lost_keys = [int(f) for f in frames if lost_pt[f].any()]
        if lost_keys:
            log.info("region %s: key frame %d has lost landmarks; its key shape may be inaccurate", name, lost_keys[0])
        X = (np.where(nan[..., None], 0.0, P) if nan.any() else P).reshape(T, -1)
        del P
        weight = np.repeat(np.where(lost_pt, 0.0, C if confidence else 1.0), 2, axis=1)
        del C
        kw = {}
        if formulation == "delta":
            if neutral_frame not in reg["frames"]:
                raise InputError(f"{keys}: region {name!r}: formulation 'delta' needs neutral_frame {neutral_frame} "
                                 f"among the key frames {reg['frames']} (set decompose.neutral_frame to one of them)")
            kw["neutral"] = X[neutral_frame]
        try:
            W, _ = decompose(X, X[frames], solver=solver, formulation=formulation, alpha=alpha, upper=upper,
                             confidence=None if np.all(weight == 1) else weight, smooth_space=smooth_space,
                             robust=robust, **kw)
        except ValueError as exc:
            raise InputError(f"{keys}: region {name!r}: {exc}") from exc
        if formulation == "delta":
            j = reg["frames"].index(neutral_frame)
            W[:, j] = 1.0 - (W.sum(1) - W[:, j])
        if lost.any():
            W = interpolate_lost(W, lost)
            log.warning("region %s: lost in %d of %d frames (first: %d); weights interpolated",
                        name, int(lost.sum()), T, int(np.flatnonzero(lost)[0]))
        res = row_residuals(X, W, X[frames])
        card = cardinality(W)
        regions[name] = (W, frames, res)
        extras[name] = {"cardinality": card, "lost": lost}
        diagnostics[name] = {  # 6 significant digits keep the JSON short and deterministic
            "mean_residual_px": float(f"{res[~lost].mean() / np.sqrt(len(pts)):.6g}"),
            "mean_cardinality": float(f"{card.mean():.6g}"),
            "jitter": float(f"{jitter(W):.6g}"),
            # mesh-space jitter: mean acceleration of the reconstructed landmarks, and of the input ones
            "shape_jitter_px": float(f"{mean_acceleration(W @ X[frames]):.6g}"),
            "input_jitter_px": float(f"{mean_acceleration(X[:, ~lost_pt.all(0).repeat(2)]):.6g}"),
            "lost_frames": int(lost.sum()),
        }
        log.info("region %s: %d frames, mean residual %.4g px, mean cardinality %.2f, jitter %.3g", name, T,
                 diagnostics[name]["mean_residual_px"], card.mean(), diagnostics[name]["jitter"])
    meta = {"solver": solver, "formulation": formulation, "alpha": alpha, "upper": upper,
            "smooth_space": smooth_space if solver in ("temporal", "temporal-causal") else None,
            "robust": robust if solver == "temporal" else None,
            "neutral_frame": neutral_frame if formulation == "delta" else None, "confidence": confidence,
            "fps": lm.fps, "landmarks": Path(landmarks).name, "diagnostics": diagnostics}
    save_weights(output, regions, meta, extras)
    written = [Path(output)]
    if csv:
        write_text(csv, weights_csv(regions, lm.fps))
        written.append(Path(csv))
    return written


# --------------------------------------------------------------------------- pose-keys


def run_pose(*, keys, rig, poses, output, masks=None, base_dir=None, cache_dir=None) -> list[Path]:
    """Pose the rig at each key frame's known slider values; write target OBJs and ``targets.yaml``.

    *masks* maps region names to vertex-mask files (relative to *base_dir*),
    copied into ``targets.yaml`` so ``apply`` can blend the regions.
    Every argument is checked before the rig's OBJs are read; *cache_dir*
    keeps the parsed rig (:meth:`~retarget_cli.rig.BlendshapeRig.load`).

    This is the automatic "artist" for takes whose slider values are known
    (synthetic takes, or a performance recorded on a rig).
    """
    from ..io.atomic import load_npz
    from ..io.obj import write_obj
    from ..io.stagefiles import read_keys, read_rig
    from ..rig import BlendshapeRig

    keys, rig_path, poses = _require(keys, "keys file"), _require(rig, "rig file"), _require(poses, "poses file")
    kf, spec = read_keys(keys), read_rig(rig_path)
    data = load_npz(poses)
    if "curves" not in data or "names" not in data:
        raise InputError(f"{poses}: expected 'curves' (T, E) and 'names' (E,)")
    curves, names = data["curves"], [str(n) for n in data["names"]]
    if curves.ndim != 2 or curves.shape[1] != len(names):
        raise InputError(f"{poses}: 'curves' must have shape (T, {len(names)}) for its {len(names)} names, "
                         f"got {curves.shape}")
    missing = [n for n in names if n not in spec.shapes]
    if missing:
        raise InputError(f"{poses}: slider {missing[0]!r} is not a shape of {rig_path}")
    for reg in kf.regions.values():
        for f in reg["frames"]:
            if f >= len(curves):
                raise InputError(f"{keys}: key frame {f} is outside {poses} ({len(curves)} frames)")
    mask_files = _check_masks(kf, keys, masks, base_dir)
    out = Path(output)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a directory")
    planned = [out / f"{name}/key_{f:05d}.obj" for name, reg in kf.regions.items() for f in reg["frames"]]
    inputs = [keys, rig_path, poses, *spec.files(), *mask_files.values()]
    for o in [*planned, out / "targets.yaml"]:
        check_not_input(o, inputs)
    if mask_files:
        from ..io.obj import count_vertices
        from ..io.stagefiles import read_vertex_mask

        n_vertices = count_vertices(_require(spec.neutral, "neutral OBJ of the rig"))
        for mask in mask_files.values():
            read_vertex_mask(mask, n_vertices)
    rig = BlendshapeRig.load(rig_path, cache_dir=cache_dir)
    cols = [rig.index[n] for n in names]
    regions = {}
    with tracked_outputs(out, "pose-keys", planned=[*planned, out / "targets.yaml"]) as written:
        for name, reg in kf.regions.items():
            regions[name] = {"keys": {}}
            for f in reg["frames"]:
                rel = f"{name}/key_{f:05d}.obj"
                w = np.zeros(rig.n_sliders)
                w[cols] = curves[f]
                write_obj(written.add(out / rel), rig.template, rig.evaluate(w))
                regions[name]["keys"][f] = rel
        written.add(_write_targets_yaml(out, kf, keys, regions, masks, base_dir, rig_path, "pose-keys"))
    return written.written


def _check_masks(kf, keys, masks, base_dir) -> dict:
    """Region masks named in *masks* (relative to *base_dir*): regions of *keys*, one per region when
    there are several, files that exist. Returns region name to mask path."""
    masks = masks or {}
    unknown = sorted(set(masks) - set(kf.regions))
    if unknown:
        raise InputError(f"masks: region {unknown[0]!r} is not a region of {keys} ({', '.join(kf.regions)})")
    if len(kf.regions) > 1:
        absent = [r for r in kf.regions if r not in masks]
        if absent:
            raise InputError(f"masks: region {absent[0]!r} needs a vertex mask when {keys} has several regions")
    return {name: _require(Path(base_dir or ".") / mask, "region mask") for name, mask in masks.items()}


def _write_targets_yaml(out: Path, kf, keys, regions, masks, base_dir, rig_path, command) -> Path:
    """Add the region masks to *regions* and write ``out/targets.yaml`` (neutral = the rig's)."""
    from ..io.stagefiles import read_rig, write_targets

    for name, mask in _check_masks(kf, keys, masks, base_dir).items():
        regions[name]["vertices"] = os.path.relpath(mask.resolve(), out.resolve())
    nrel = os.path.relpath(read_rig(rig_path).neutral.resolve(), out.resolve())
    write_targets(out / "targets.yaml", regions, neutral=nrel, comment=f"Written by retarget {command}.")
    return out / "targets.yaml"


def digest_files(paths) -> str:
    """One sha256 over several files' names and contents."""
    h = hashlib.sha256()
    for p in sorted(map(str, paths)):
        h.update(p.encode())
        h.update(sha256_file(p).encode())
    return h.hexdigest()


# --------------------------------------------------------------------------- edit, auto-pose

FRAME_RE = re.compile(r"frame_(\d{5,})\.obj$")



def _write_frames(out: Path, rig, W, frames, progress=_no_progress) -> list[Path]:
    """Write ``frame_%05d.obj`` (named by frame number) for each pose; remove stale frames of earlier runs."""
    from ..io.obj import write_obj

    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a directory")
    out.mkdir(parents=True, exist_ok=True)
    planned = [out / f"frame_{int(f):05d}.obj" for f in frames]
    with tracked_outputs(out, "edit", planned=planned) as written, progress(len(W), "objs") as bar:
        for start in range(0, len(W), 64):
            for f, pos in zip(frames[start:start + 64], rig.evaluate(W[start:start + 64])):
                write_obj(written.add(out / f"frame_{int(f):05d}.obj"), rig.template, pos)
            bar.update(min(64, len(W) - start))
    return written.written


def run_edit(*, animation, edits, output, rig=None, objs=None, progress=_no_progress, cache_dir=None) -> list[Path]:
    """Apply ``edits.yaml`` (pins and attenuations over frame ranges) to rig weights over time.

    The rig is *rig* or else the ``rig:`` named in ``edits.yaml``. Writes the
    edited weights to *output* (CSV or NPZ, by extension) and, with *objs*,
    the posed OBJ sequence (``frame_%05d.obj``, by frame number). The
    animation and the edits are checked (against ``rig.yaml`` and the
    neutral's vertex count) before the rig's OBJs are read; *cache_dir* keeps
    the parsed rig (:meth:`~retarget_cli.rig.BlendshapeRig.load`).
    """
    from ..config import closest
    from ..edit import apply_edits
    from ..io.editfiles import edits_rig, read_animation, read_edits, write_animation
    from ..io.obj import count_vertices
    from ..io.stagefiles import read_rig
    from ..rig import BlendshapeRig

    animation, edits = _require(animation, "animation"), _require(edits, "edits file")
    rig = rig or edits_rig(edits)
    if rig is None:
        raise InputError(f"{edits}: no rig given; add 'rig: path/to/rig.yaml' to the file or pass --rig")
    rig_path = _require(rig, "rig file")
    spec = read_rig(rig_path)
    inputs = [animation, edits, rig_path, *spec.files()]
    check_not_input(output, inputs)
    names, W_in, frames, times = read_animation(animation)
    if objs:
        objs_dir = Path(objs).resolve()
        clash = [p for p in inputs if Path(p).resolve().parent == objs_dir and FRAME_RE.match(Path(p).name)]
        if clash:
            raise InputError(f"{objs}: writing the frames there would overwrite or remove the input {clash[0]}; "
                             "choose another --objs folder")
    unknown = [n for n in names if n not in spec.shapes]
    if unknown:
        hint = closest(unknown[0], list(spec.shapes))
        raise InputError(f"{animation}: slider {unknown[0]!r} is not a shape of {rig_path}"
                         + (f"; did you mean {hint!r}?" if hint else ""))
    _require(spec.neutral, "neutral OBJ of the rig")
    todo = read_edits(edits, n_vertices=count_vertices(spec.neutral), frames=frames,
                      expressions=[str(e) for e in spec.library])
    r = BlendshapeRig.load(rig_path, cache_dir=cache_dir)
    order = names + [n for n in r.names if n not in names]
    W = np.zeros((len(W_in), r.n_sliders))
    W[:, [r.index[n] for n in names]] = W_in
    try:
        W = apply_edits(r, W, frames, todo)
    except ValueError as exc:
        raise InputError(f"{edits}: {exc}") from exc
    write_animation(output, order, W[:, [r.index[n] for n in order]], frames, times,
                    meta={"edits": Path(edits).name, "edits_sha256": sha256_file(edits), "rig": Path(rig_path).name})
    written = [Path(output)]
    if objs:
        written += _write_frames(Path(objs), r, W, frames, progress)
    log.info("applied %d edits to %d frames", len(todo), len(W))
    return written




# --------------------------------------------------------------------------- solve-rig (inverse rig)


def run_solve_rig(*, rig, meshes, output, solver, alpha, tol, max_iter, metrics=None,
                  progress=_no_progress, cache_dir=None) -> tuple[list[Path], dict]:
    """Fit slider weights of a rig with correctives to a mesh sequence (Racković et al. 2023, eq. 8).

    The output paths, ``rig.yaml``, the rig's vertex counts and the meshes
    to fit are checked before the rig's OBJs are parsed; *cache_dir* keeps
    the parsed rig (:func:`~retarget_cli.io.rigfiles.read_quadratic_rig`).

    Returns
    -------
    written : list of Path
    summary : dict
        Means over frames of rmse, cardinality, objective, iterations and seconds, plus sizes.
    """
    from ..inverse_rig import CARDINALITY_THRESHOLD, solve
    from ..io.rigfiles import (
        check_quadratic_rig,
        read_meshes,
        read_quadratic_rig,
        save_inverse_weights,
        write_metrics_csv,
    )

    rig_files, n_vertices = check_quadratic_rig(rig)
    inputs = [*rig_files, meshes]
    check_not_input(output, inputs)
    if metrics is not None:
        check_not_input(metrics, inputs + [output])
    X, sources = read_meshes(meshes, n_vertices)
    qrig, _ = read_quadratic_rig(rig, cache_dir=cache_dir)
    log.info("solve-rig: %d frames, %d vertices, %d shapes, %d correctives, solver %s",
             len(X), qrig.n_vertices, qrig.n_shapes, qrig.n_pairs, solver)
    with progress(len(X), "solve-rig") as bar:
        res = solve(qrig, X, solver=solver, alpha=alpha, tol=tol, max_iter=max_iter, callback=bar.update)
    summary = {
        "frames": len(X), "vertices": qrig.n_vertices, "shapes": qrig.n_shapes, "correctives": qrig.n_pairs,
        "rmse": float(res.rmse.mean()), "cardinality": float(res.cardinality.mean()),
        "objective": float(res.objective.mean()), "iterations": float(res.iterations.mean()),
        "seconds_per_frame": float(res.seconds.mean()),
    }
    meta = {"solver": solver, "alpha": alpha, "tol": tol, "max_iter": max_iter,
            "cardinality_threshold": CARDINALITY_THRESHOLD, "rig": Path(rig).name,
            "summary": {k: v for k, v in summary.items() if k != "seconds_per_frame"}}
    save_inverse_weights(output, res, qrig.names, sources, meta)
    written = [Path(output)]
    if metrics is not None:
        write_metrics_csv(metrics, res, sources)
        written.append(Path(metrics))
    return written, summary


# Stages with modules of their own (imported last: they use the helpers above).
from .apply import APPLY_FILES, APPLY_FORMATS, run_apply  # noqa: E402, F401
from .auto_pose import run_auto_pose  # noqa: E402, F401
