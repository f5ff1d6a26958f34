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
              rigid_points=None, progress=_no_progress) -> list[Path]:
    """Track landmarks through *video* from the ``.pts`` annotation of its first frame.

    Writes the ``landmarks.npz`` contract to *output*.
    """
    from .io.annotations import read_pts
    from .io.landmarks import Landmarks, save_landmarks
    from .io.video import VideoReader
    from .track.head import estimate_head
    from .track.lk import track_lk

    video, init = _require(video, "video file"), _require(init, "annotation file")
    check_not_input(output, [video, init])
    if method != "lk":
        raise ValueError(f"method: expected 'lk', got {method!r}")
    P0 = read_pts(init)
    with VideoReader(video) as reader:
        W, H = reader.frame_size
        with progress(reader.frame_count or None, "track") as bar:
            try:
                points, conf = track_lk(reader, P0, window=window, levels=levels, fb_threshold=fb_threshold,
                                        anchor=anchor, rigid_points=rigid_points,
                                        progress=lambda t: bar.update(1))
            except ValueError as exc:
                raise InputError(f"{init}: {exc}") from exc
        fps = reader.fps
    lost = conf < 1e-3
    if np.all(lost[1:]) and len(conf) > 1:
        raise InputError(f"{video}: the face was lost in every frame after the first")
    head, stab = estimate_head(points, conf, rigid_points=rigid_points)
    meta = {
        "tracker": "lk",
        "parameters": {"window": window, "levels": levels, "fb_threshold": fb_threshold, "anchor": anchor},
        "source": Path(video).name,
        "source_sha256": sha256_file(video),
        "annotation": Path(init).name,
    }
    save_landmarks(output, Landmarks(points, conf, head, stab, fps, np.array([W, H]), None, meta))
    log.info("tracked %d frames x %d points; mean confidence %.3f", len(points), points.shape[1], conf.mean())
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


#: A landmark whose confidence is at or below this is lost in that frame.
LOST_CONFIDENCE = 1e-3


def run_decompose(*, landmarks, keys, output, csv=None, solver="nnls", formulation="whole", alpha=None, upper=None,
                  neutral_frame=0, confidence=True, lost_fraction=0.5) -> list[Path]:
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
    from .decompose import cardinality, decompose, interpolate_lost, jitter
    from .io.landmarks import load_landmarks
    from .io.stagefiles import read_keys, save_weights, weights_csv

    landmarks, keys = _require(landmarks, "landmarks file"), _require(keys, "keys file")
    check_not_input(output, [landmarks, keys])
    lm = load_landmarks(landmarks)
    kf = read_keys(keys)
    stab = lm.stabilized.astype(np.float64)
    conf = lm.confidence.astype(np.float64)
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
        P, C = stab[:, pts], conf[:, pts]
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
        X = np.where(nan[..., None], 0.0, P).reshape(T, -1)
        weight = np.repeat(np.where(lost_pt, 0.0, C if confidence else 1.0), 2, axis=1)
        kw = {}
        if formulation == "delta":
            if neutral_frame not in reg["frames"]:
                raise InputError(f"{keys}: region {name!r}: formulation 'delta' needs neutral_frame {neutral_frame} "
                                 f"among the key frames {reg['frames']} (set decompose.neutral_frame to one of them)")
            kw["neutral"] = X[neutral_frame]
        try:
            W, _ = decompose(X, X[frames], solver=solver, formulation=formulation, alpha=alpha, upper=upper,
                             confidence=None if np.all(weight == 1) else weight, **kw)
        except ValueError as exc:
            raise InputError(f"{keys}: region {name!r}: {exc}") from exc
        if formulation == "delta":
            j = reg["frames"].index(neutral_frame)
            W[:, j] = 1.0 - (W.sum(1) - W[:, j])
        if lost.any():
            W = interpolate_lost(W, lost)
            log.warning("region %s: lost in %d of %d frames (first: %d); weights interpolated",
                        name, int(lost.sum()), T, int(np.flatnonzero(lost)[0]))
        res = np.linalg.norm(X - W @ X[frames], axis=1)
        card = cardinality(W)
        regions[name] = (W, frames, res)
        extras[name] = {"cardinality": card, "lost": lost}
        diagnostics[name] = {  # 6 significant digits keep the JSON short and deterministic
            "mean_residual_px": float(f"{res[~lost].mean() / np.sqrt(len(pts)):.6g}"),
            "mean_cardinality": float(f"{card.mean():.6g}"),
            "jitter": float(f"{jitter(W):.6g}"),
            "lost_frames": int(lost.sum()),
        }
        log.info("region %s: %d frames, mean residual %.4g px, mean cardinality %.2f, jitter %.3g", name, T,
                 diagnostics[name]["mean_residual_px"], card.mean(), diagnostics[name]["jitter"])
    meta = {"solver": solver, "formulation": formulation, "alpha": alpha, "upper": upper,
            "neutral_frame": neutral_frame if formulation == "delta" else None, "confidence": confidence,
            "fps": lm.fps, "landmarks": Path(landmarks).name, "diagnostics": diagnostics}
    save_weights(output, regions, meta, extras)
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


__all__ = ["run_track", "run_select", "run_decompose", "run_pose", "run_apply", "__version__", "json"]
