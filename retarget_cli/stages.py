"""Stage runners: read the input files, call the pure stage function, write
the outputs atomically. The CLI commands and ``retarget run`` both call these.

Each runner returns the list of files it wrote.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import re
from pathlib import Path

import numpy as np

from . import __version__
from .errors import InputError
from .io.atomic import check_not_input, sha256_file, write_text

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


def run_track(*, video, init, output, method="lk", window=21, levels=3, fb_threshold=1.0, anchor=True,
              rigid_points=None, annotations=None, init_frame=None, start=0, end=None, step=1, downscale=1.0,
              fps=None, smooth_head=0, overlay=None, keep_partial=False, base_dir=None,
              progress=_no_progress) -> list[Path]:
    """Track landmarks through *video* (a video file or an image-sequence pattern).

    *init* and *annotations* are ``.pts`` or ``frame,point,x,y`` CSV files; a
    ``.pts`` file's frame is the number ending its name (else *init_frame*).
    Frame numbers are 0-based positions in the source; the first tracked
    frame (*start*) must be annotated. Writes the ``landmarks.npz`` contract
    to *output* (plus ``frames``, the source frame numbers) and, if asked, an
    *overlay* video.
    """
    from .io.annotations import read_annotations
    from .io.frames import FrameSource, TruncatedInputError
    from .io.landmarks import Landmarks, save_landmarks
    from .track.head import apply_similarity, estimate_head, invert_similarity
    from .track.head import smooth_head as smooth_head_fn
    from .track.lk import FaceLostError, check_inside, track_lk

    init = _require(init, "annotation file")
    extra = [Path(base_dir or ".") / a for a in (annotations or [])]
    for a in extra:
        _require(a, "annotation file")
    if method not in ("lk", "eigenpoints", "markers"):
        raise ValueError(f"method: expected 'lk', 'eigenpoints' or 'markers', got {method!r}")
    ann, src = read_annotations([init, *extra], frame=init_frame)
    with FrameSource(video, start=start, end=end, step=step, fps=fps) as source:
        check_not_input(output, source.files() + [init, *extra])
        if overlay:
            check_not_input(overlay, source.files() + [init, *extra])
        W, H = source.frame_size
        if start not in ann:
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
                yield from source
            except TruncatedInputError as exc:
                stopped.append(exc)

        n_expected = None
        if source.frame_count:
            last = source.frame_count if end is None else min(end, source.frame_count)
            n_expected = max(0, (last - start + step - 1) // step)
        with progress(n_expected, "track") as bar:
            try:
                if method == "eigenpoints":
                    from .track.eigenpoints import track_eigenpoints

                    if downscale != 1:
                        log.warning("downscale applies to the lk tracker only; eigenpoints uses its own window")
                    points, conf = track_eigenpoints(frames(), index, rigid_points=rigid_points,
                                                     progress=lambda t: bar.update(1))
                elif method == "markers":
                    from .track.markers import track_markers

                    points, conf = track_markers(frames(), index, progress=lambda t: bar.update(1))
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
                raise InputError(f"{init}: {exc}") from exc
        if stopped:
            if not keep_partial:
                raise InputError(f"{stopped[0]}; rerun with --keep-partial to keep the {len(points)} frames "
                                 f"tracked up to then")
            log.warning("%s; keeping the %d frames tracked (--keep-partial)", stopped[0], len(points))
        frame_numbers = np.asarray(source.frames[:len(points)], dtype=np.int64)
        files = source.files()
    head, stab = estimate_head(points, conf, rigid_points=rigid_points)
    if smooth_head:
        head = smooth_head_fn(head, smooth_head)
        stab = apply_similarity(invert_similarity(head), points)
    meta = {
        "tracker": method,
        "parameters": {"window": window, "levels": levels, "fb_threshold": fb_threshold, "anchor": anchor,
                       "downscale": downscale, "start": start, "end": end, "step": step,
                       "smooth_head": smooth_head},
        "source": Path(video).name,
        "source_sha256": sha256_file(files[0]) if len(files) == 1 else digest_files(files),
        "annotation": [Path(p).name for p in [init, *extra]],
        "annotated_frames": [int(f) for f in ann],
    }
    save_landmarks(output, Landmarks(points, conf, head, stab, source.fps, np.array([W, H]), None, meta,
                                     frames=frame_numbers))
    written = [Path(output)]
    log.info("tracked %d frames x %d points; mean confidence %.3f", len(points), points.shape[1], conf.mean())
    if overlay:
        from .io.overlay import write_overlay

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


def run_import(*, source, output, fps=None, frame_size=None, rigid_points=None, smooth_head=0) -> list[Path]:
    """Bring landmarks from another tool into the ``landmarks.npz`` contract.

    *source* is a ``frame,point,x,y`` CSV, an NPZ holding ``points`` (T, L, 2)
    (``confidence``, ``fps``, ``frame_size``, ``frames`` optional), or a
    folder of ``.pts`` files named with their frame number. Head motion and
    stabilization are computed with :func:`~retarget_cli.track.head.estimate_head`
    (the routine ``track`` uses), optionally smoothed in time.
    """
    from .io.annotations import read_annotations, read_csv_landmarks
    from .io.atomic import load_npz
    from .io.landmarks import Landmarks, save_landmarks
    from .track.head import apply_similarity, estimate_head, invert_similarity
    from .track.head import smooth_head as _smooth

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
    try:
        head, stab = estimate_head(points, conf, rigid_points=rigid_points)
    except ValueError as exc:
        raise InputError(f"{src}: {exc}") from exc
    if smooth_head:
        head = _smooth(head, smooth_head)
        stab = apply_similarity(invert_similarity(head), points)
    meta = {"tracker": "import", "source": src.name, "source_sha256": digest,
            "parameters": {"smooth_head": smooth_head, "rigid_points": rigid_points}}
    save_landmarks(output, Landmarks(points, conf, head, stab, fps or 30.0,
                                     np.array(size if size else (0, 0)), None, meta, frames=frames))
    log.info("imported %d frames x %d points from %s", len(points), points.shape[1], src)
    return [Path(output)]


# --------------------------------------------------------------------------- select


def region_points(regions, n_points: int) -> dict[str, list[int]]:
    """Resolve region definitions (``"all"`` or index lists) to index lists."""
    regions = regions or {"face": "all"}
    out = {}
    for name, pts in regions.items():
        if pts == "all":
            out[name] = list(range(n_points))
            continue
        if not isinstance(pts, list) or not pts or not all(isinstance(i, int) for i in pts):
            raise InputError(f"regions: {name!r} must be 'all' or a list of landmark indices")
        bad = [i for i in pts if not 0 <= i < n_points]
        if bad:
            raise InputError(f"regions: {name!r} names landmark {bad[0]} but the take has {n_points} (0..{n_points - 1})")
        out[name] = list(pts)
    return out


def run_select(*, landmarks, output, template=None, method="pca-extremes", k=12, regions=None,
               neutral_frame=0, seed=0) -> list[Path]:
    """Choose key frames per region; write ``keys.json`` and a ``targets.yaml`` template."""
    from .decompose import reconstruction_error
    from .io.landmarks import load_landmarks
    from .io.stagefiles import write_keys, write_targets
    from .select import select_keys

    landmarks = _require(landmarks, "landmarks file")
    check_not_input(output, [landmarks])
    lm = load_landmarks(landmarks)
    stab = lm.stabilized.astype(np.float64)
    result, tmpl = {}, {}
    for name, idx in region_points(regions, lm.n_points).items():
        X = stab[:, idx].reshape(lm.n_frames, -1)
        try:
            include = () if neutral_frame is None else (neutral_frame,)
            frames = select_keys(X, k, method=method, include=include)
        except ValueError as exc:
            raise InputError(f"{landmarks}: region {name!r}: {exc}") from exc
        err = reconstruction_error(X, X[frames])
        result[name] = {"points": idx, "method": method, "frames": [int(f) for f in frames], "error": round(err, 6)}
        tmpl[name] = {"keys": {int(f): f"target/{name}/key_{int(f):05d}.obj" for f in frames}}
        log.info("region %s: keys %s, E = %.4g (eq. 5)", name, result[name]["frames"], err)
    write_keys(output, landmarks, result)
    written = [Path(output)]
    if template:
        check_not_input(template, [landmarks])
        t = Path(template)
        if t.exists() and not t.read_text(encoding="utf-8", errors="replace").startswith(TEMPLATE_MARK):
            raise InputError(f"{t}: exists and was not written by 'retarget select'; "
                             "refusing to overwrite it (choose another --template path)")
        write_targets(t, tmpl, comment=TEMPLATE_MARK[2:] + (
            "Sculpt one OBJ per key frame (same topology for all), matching the actor's\n"
            "expression in that frame. Paths are relative to this file. Copy this file\n"
            "before editing: select rewrites it."))
        written.append(t)
    return written


#: First line of the targets template ``select`` writes; a file without it is never overwritten.
TEMPLATE_MARK = "# targets.yaml template written by retarget select.\n"


# --------------------------------------------------------------------------- decompose


def run_decompose(*, landmarks, keys, output, csv=None, solver="nnls") -> list[Path]:
    """Weights over the key shapes for every frame and region; writes ``weights.npz``."""
    from .decompose import decompose
    from .io.landmarks import load_landmarks
    from .io.stagefiles import read_keys, save_weights, weights_csv

    landmarks, keys = _require(landmarks, "landmarks file"), _require(keys, "keys file")
    check_not_input(output, [landmarks, keys])
    lm = load_landmarks(landmarks)
    kf = read_keys(keys)
    stab = lm.stabilized.astype(np.float64)
    regions = {}
    for name, reg in kf.regions.items():
        bad = [f for f in reg["frames"] if f >= lm.n_frames]
        if bad:
            raise InputError(f"{keys}: region {name!r} key frame {bad[0]} is outside the take ({lm.n_frames} frames in {landmarks})")
        badp = [p for p in reg["points"] if p >= lm.n_points]
        if badp:
            raise InputError(f"{keys}: region {name!r} landmark {badp[0]} does not exist ({lm.n_points} points in {landmarks})")
        X = stab[:, reg["points"]].reshape(lm.n_frames, -1)
        W, res = decompose(X, X[reg["frames"]], solver=solver)
        regions[name] = (W, np.array(reg["frames"]), res)
        log.info("region %s: %d frames, mean residual %.4g px", name, len(W), res.mean() / np.sqrt(len(reg["points"])))
    meta = {"solver": solver, "fps": lm.fps, "landmarks": Path(landmarks).name}
    save_weights(output, regions, meta)
    written = [Path(output)]
    if csv:
        write_text(csv, weights_csv(regions, lm.fps))
        written.append(Path(csv))
    return written


# --------------------------------------------------------------------------- pose-keys


def run_pose(*, keys, rig, poses, output, masks=None, base_dir=None) -> list[Path]:
    """Pose the rig at each key frame's known slider values; write target OBJs and ``targets.yaml``.

    *masks* maps region names to vertex-mask files (relative to *base_dir*),
    copied into ``targets.yaml`` so ``apply`` can blend the regions.

    This is the automatic "artist" for takes whose slider values are known
    (synthetic takes, or a performance recorded on a rig).
    """
    from .io.atomic import load_npz
    from .io.obj import check_same_topology, read_obj, write_obj
    from .io.stagefiles import read_keys, read_rig, write_targets

    keys, rig_path, poses = _require(keys, "keys file"), _require(rig, "rig file"), _require(poses, "poses file")
    kf, rig = read_keys(keys), read_rig(rig_path)
    data = load_npz(poses)
    if "curves" not in data or "names" not in data:
        raise InputError(f"{poses}: expected 'curves' (T, E) and 'names' (E,)")
    curves, names = data["curves"], [str(n) for n in data["names"]]
    missing = [n for n in names if n not in rig.shapes]
    if missing:
        raise InputError(f"{poses}: slider {missing[0]!r} is not a shape of {rig_path}")
    neutral = read_obj(rig.neutral)
    shapes = [read_obj(rig.shapes[n]) for n in names]
    check_same_topology([neutral, *shapes])
    D = np.stack([s.vertices - neutral.vertices for s in shapes])
    out = Path(output)
    written, regions = [], {}
    for name, reg in kf.regions.items():
        regions[name] = {"keys": {}}
        for f in reg["frames"]:
            if f >= len(curves):
                raise InputError(f"{keys}: key frame {f} is outside {poses} ({len(curves)} frames)")
            rel = f"{name}/key_{f:05d}.obj"
            write_obj(out / rel, neutral, neutral.vertices + np.tensordot(curves[f], D, axes=1))
            regions[name]["keys"][f] = rel
            written.append(out / rel)
    masks = masks or {}
    unknown = sorted(set(masks) - set(kf.regions))
    if unknown:
        raise InputError(f"masks: region {unknown[0]!r} is not a region of {keys} ({', '.join(kf.regions)})")
    if len(kf.regions) > 1:
        absent = [r for r in kf.regions if r not in masks]
        if absent:
            raise InputError(f"masks: region {absent[0]!r} needs a vertex mask when {keys} has several regions")
    for name, mask in masks.items():
        mask = Path(base_dir or ".") / mask
        _require(mask, "region mask")
        regions[name]["vertices"] = os.path.relpath(mask.resolve(), out.resolve())
    nrel = os.path.relpath(rig.neutral.resolve(), out.resolve())
    write_targets(out / "targets.yaml", regions, neutral=nrel, comment="Written by retarget pose-keys.")
    written.append(out / "targets.yaml")
    return written


# --------------------------------------------------------------------------- apply

FRAME_RE = re.compile(r"frame_(\d{5,})\.obj$")


def run_apply(*, weights, targets, output, head_motion="none", progress=_no_progress) -> list[Path]:
    """Drive the target key shapes with the weights; write ``frame_%05d.obj`` into *output*."""
    from .apply import blend_keys, blend_regions
    from .io.obj import check_same_topology, read_obj
    from .io.stagefiles import load_weights, read_targets, read_vertex_mask

    weights, targets = _require(weights, "weights file"), _require(targets, "targets file")
    if head_motion != "none":
        raise ValueError(f"head_motion: expected 'none', got {head_motion!r}")
    regions, _ = load_weights(weights)
    tg = read_targets(targets)
    missing = sorted(set(regions) - set(tg.regions))
    if missing:
        raise InputError(f"{targets}: no targets for region {missing[0]!r} of {weights}")
    per_region, meshes = [], []
    for name, (W, frames, _) in sorted(regions.items()):
        keyfiles = tg.regions[name]["keys"]
        absent = [int(f) for f in frames if int(f) not in keyfiles]
        if absent:
            raise InputError(f"{targets}: region {name!r} has no target shape for key frame {absent[0]}")
        objs = [read_obj(keyfiles[int(f)]) for f in frames]
        meshes += objs
        per_region.append((name, W, objs))
    neutral = read_obj(tg.neutral) if tg.neutral else None
    check_same_topology(([neutral] if neutral else []) + meshes)
    template = neutral or meshes[0]
    N = template.n_vertices
    masks = None
    if len(per_region) > 1:
        if neutral is None:
            raise InputError(f"{targets}: several regions need a 'neutral' mesh to blend them")
        masks = []
        for name, _, _ in per_region:
            vf = tg.regions[name]["vertices"]
            if vf is None:
                raise InputError(f"{targets}: region {name!r} needs 'vertices' (its mask) when there are several regions")
            masks.append(read_vertex_mask(vf, N))
    out = Path(output)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a directory")
    out.mkdir(parents=True, exist_ok=True)
    keysets = [np.stack([m.vertices for m in objs]) for _, _, objs in per_region]
    T = per_region[0][1].shape[0]
    written = []
    chunk = 64
    with progress(T, "apply") as bar:
        for start in range(0, T, chunk):
            sl = slice(start, min(start + chunk, T))
            res = [blend_keys(W[sl], B) for (_, W, _), B in zip(per_region, keysets)]
            pos = res[0] if masks is None else blend_regions(res, masks, neutral.vertices)
            for i, p in enumerate(pos):
                path = out / f"frame_{start + i:05d}.obj"
                from .io.obj import write_obj

                write_obj(path, template, p)
                written.append(path)
            bar.update(sl.stop - sl.start)
    # Remove frames left over from a longer previous run (only files this stage names).
    for stale in out.iterdir():
        m = FRAME_RE.match(stale.name)
        if m and int(m.group(1)) >= T:
            stale.unlink()
    log.info("wrote %d frames of %d vertices to %s", T, N, out)
    return written


def digest_files(paths) -> str:
    """One sha256 over several files' names and contents."""
    h = hashlib.sha256()
    for p in sorted(map(str, paths)):
        h.update(p.encode())
        h.update(sha256_file(p).encode())
    return h.hexdigest()


__all__ = ["run_track", "run_import", "run_select", "run_decompose", "run_pose", "run_apply", "__version__", "json"]
