"""``apply``: drive the character with the weights (Chuang & Bregler 2002, §5) and export the result.

Two ways to drive it, chosen by ``targets.yaml``:

- **key shapes** (sculpted, or posed by ``pose-keys``): each region's frame is
  ``Σ_k w_k B_k`` over its target key shapes, regions blended by their masks;
- **a rig** (``targets.yaml`` names ``rig:`` and ``sliders:``, as ``auto-pose``
  writes it): every frame's rig sliders are the ``curves:`` it names (``auto-pose
  --frames all``, the rig posed at every frame), or else follow from the weights and
  the key frames' sliders (:func:`retarget_cli.methods.rigpose.rig_curves`); they are
  written as curves (``curves.csv``, ``curves.npz``), and the meshes are the rig posed
  at them, so correctives aside every shell the rig moves (teeth, tongue, eyes)
  moves.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..config import Command, Flag, Param, check_vector3, output_flag, validate_params
from ..errors import InputError, ParameterError
from ..io.atomic import TrackedOutputs, check_not_input
from ..io.editfiles import read_animation
from ..io.exports import EXPORTS, ExportContext, format_choices, formats_help, rig_shapes
from ..io.landmarks import load_landmarks
from ..io.obj import check_same_topology, read_obj
from ..io.rig import load_rig
from ..io.stagefiles import load_weights, read_targets, read_vertex_mask
from ..methods.blending import (
    apply_transforms,
    blend_keys,
    blend_regions,
    head_motion_transforms,
    head_rotation_transforms,
    morph_targets,
    morph_weights,
    region_weights,
)
from ..methods.gaps import GAP_BEHAVIOURS, fill_gaps, gap_summary
from ..methods.rigpose import rig_curves
from ._common import NO_CACHE, NO_CACHE_FLAG, Stage, _no_progress, _require, command_cache_dir

log = logging.getLogger(__name__)

#: Declared parameters of ``apply`` (YAML validation, CLI options, manifests, docs/config.md).
PARAMS = [
    Param("weights", "input", str, help="weights.npz.", link="decompose.output"),
    Param("targets", "input", str, help="targets.yaml.",
          link="auto_pose.output/targets.yaml|pose.output/targets.yaml"),
    Param("landmarks", "input", str, None, "landmarks.npz, for its head motion (head_motion: 2d).",
          nullable=True, link="track.output"),
    Param("output", "output", str, "frames",
          "Directory for frame_00000.obj, ..., weights.csv, animation.exr/.json, animation.glb."),
    Param("formats", "setting", list, ["obj"], "Exports, any of: " + formats_help() + ".",
          choices=format_choices),
    Param("drive", "setting", str, "auto",
          "What drives the character: auto (the rig when targets.yaml names one, else the key shapes), "
          "rig, or keys (blend the key OBJs with the region masks).", choices=("auto", "rig", "keys")),
    Param("head_motion", "setting", str, "none",
          "Head motion on the character: none, or 2d (roll, scale, translation in the image plane).",
          choices=("none", "2d")),
    Param("scale", "setting", float, None,
          "Model units per image pixel for head translation (default: neutral mesh width / "
          "frame-0 landmark width).", min=1e-12, nullable=True),
    Param("pivot", "setting", list, None,
          "[x, y, z] in model units: centre of head roll and scale (default: centre of the "
          "neutral mesh's bounding box).", nullable=True, validate=check_vector3),
    Param("head_rotation", "setting", bool, True,
          "The head's 3D rotation (landmarks.npz head_angles, from track.head_pose): head_yaw/pitch/roll and "
          "head_x/y/z columns in the curves, Live Link's HeadYaw/HeadPitch/HeadRoll, and the rotation of the glTF "
          "node and the USD root about the pivot (with head_motion 2d: its yaw and pitch added to the 2D motion). "
          "The OBJ/EXR meshes are not turned."),
    Param("vat", "setting", str, "offsets", "EXR texture holds offsets from the neutral or positions.",
          choices=("offsets", "positions")),
    Param("gaps", "setting", str, "ease",
          "The rig's curves in the gaps of a take (frames without a face, landmarks.npz's found; needs "
          "landmarks): ease (to the rest pose and back), hold (the last pose), or omit (those rows left out of "
          "curves.csv and livelink.csv and those keys of the glTF and USD; the OBJ/EXR meshes hold the last pose).",
          choices=GAP_BEHAVIOURS),
    Param("gap_ease", "setting", float, 0.4, "gaps ease: seconds of each ease, to the rest pose and back.",
          min=0, max=60),
]

DRIVES = ("auto", "rig", "keys")


def _check_formats(formats) -> list[str]:
    if isinstance(formats, str):
        formats = [f.strip() for f in formats.split(",") if f.strip()]
    formats = list(formats or [])
    bad = [f for f in formats if f not in EXPORTS]
    if bad or not formats:
        raise ParameterError(f"formats: expected a non-empty list of {', '.join(EXPORTS)}, got {formats!r}")
    if len(set(formats)) != len(formats):
        raise ParameterError(f"formats: {formats!r} names a format twice")
    return formats


def _head_transforms(landmarks, T: int, neutral: np.ndarray, scale, pivot) -> np.ndarray:
    """(T, 3, 4) head-motion transforms from ``landmarks.npz`` (see :func:`~retarget_cli.methods.blending.head_motion_transforms`)."""

    if landmarks is None:
        raise InputError("head_motion 2d needs the landmarks file (--landmarks, or a 'track' section)")
    lm = load_landmarks(_require(landmarks, "landmarks file"))
    if lm.n_frames != T:
        raise InputError(f"{landmarks}: has {lm.n_frames} frames but the weights have {T}")
    # Reference frame 0: stabilized coordinates are frame-0 pixels (head[0] is the identity).
    ok = lm.confidence[0] > 0
    ref = lm.stabilized[0][ok if ok.any() else slice(None)].astype(np.float64)
    lo, hi = neutral.min(0), neutral.max(0)
    width_px = float(np.ptp(ref[:, 0]))
    if scale is None:
        if width_px <= 0:
            raise InputError(f"{landmarks}: landmarks of frame 0 have no horizontal extent; set apply.scale")
        scale = float(hi[0] - lo[0]) / width_px
    centre = (lo + hi) / 2
    P = centre if pivot is None else np.asarray(pivot, dtype=np.float64)
    if P.shape != (3,):
        raise ParameterError(f"pivot: expected [x, y, z] in model units, got {pivot!r}")
    c = ref.mean(0) + (P[:2] - centre[:2]) * [1.0, -1.0] / scale
    log.info("head motion: %.4g model units per pixel, pivot %s", scale, np.round(P, 4).tolist())
    return head_motion_transforms(lm.head.astype(np.float64), units_per_pixel=scale, pivot=P, image_pivot=c)


def _key_driver(regions, tg, targets, weights):
    """Key-shape driving: (positions(slice), template, base, glb targets, glb names, glb weights)."""

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
        raw = []
        for name, _, _ in per_region:
            vf = tg.regions[name]["vertices"]
            if vf is None:
                raise InputError(f"{targets}: region {name!r} needs 'vertices' (its mask) when there are several regions")
            raw.append(read_vertex_mask(vf, N))
        falloff = [tg.regions[name].get("falloff", 0.0) for name, _, _ in per_region]
        faces = template.faces() if any(falloff) else None
        masks = list(region_weights(raw, vertices=neutral.vertices, faces=faces, falloff=falloff)[:-1])
    base = neutral.vertices if neutral else meshes[0].vertices
    keysets = [np.stack([m.vertices for m in objs]) for _, _, objs in per_region]

    def positions(sl):
        res = [blend_keys(W[sl], B) for (_, W, _), B in zip(per_region, keysets)]
        return res[0] if masks is None else blend_regions(res, masks, neutral.vertices)

    def glb():
        names = []
        for name, (_, frames, _) in sorted(regions.items()):
            names += [f"{name}:{int(f)}" for f in frames] + [f"{name}:rest"]
        return (morph_targets(keysets, None if masks is None else np.stack(masks), base), names,
                morph_weights([W for _, W, _ in per_region]))

    return positions, template, base, glb, None


def rig_key_sliders(regions, tg, targets, rig):
    """Per region, the sliders of its key frames in the weights' column order (only the sliders it owns).

    Returns
    -------
    list of ndarray, each shape (K_r, n), in sorted region order
    """

    names, S, frames, _ = read_animation(tg.sliders)
    unknown = [n for n in names if n not in rig.index]
    if unknown:
        raise InputError(f"{tg.sliders}: slider {unknown[0]!r} is not a shape of {tg.rig}")
    row = {int(f): i for i, f in enumerate(frames)}
    full = np.zeros((len(S), rig.n_sliders))
    full[:, [rig.index[n] for n in names]] = S
    out = []
    for name, (_, kframes, _) in sorted(regions.items()):
        owned = tg.regions[name].get("sliders")
        keep = np.ones(rig.n_sliders, dtype=bool)
        if owned is not None:
            bad = [n for n in owned if n not in rig.index]
            if bad:
                raise InputError(f"{targets}: region {name!r}: slider {bad[0]!r} is not a shape of {tg.rig}")
            keep = np.isin(rig.names, owned)
        absent = [int(f) for f in kframes if int(f) not in row]
        if absent:
            raise InputError(f"{tg.sliders}: no sliders for key frame {absent[0]} of region {name!r}")
        out.append(np.where(keep, full[[row[int(f)] for f in kframes]], 0.0))
    return out


def rig_frame_sliders(tg, rig, T: int, source=None) -> np.ndarray:
    """Every frame's sliders from ``targets.yaml``'s ``curves:`` (``auto-pose --frames all``), clipped to the
    rig's ranges; shape (T, n). Its frames must be the weights' source frames *source* (T,) (default 0 … T−1)."""
    names, C, frames, _ = read_animation(tg.curves)
    unknown = [n for n in names if n not in rig.index]
    if unknown:
        raise InputError(f"{tg.curves}: slider {unknown[0]!r} is not a shape of {tg.rig}")
    source = np.arange(T) if source is None else np.asarray(source)
    if len(frames) != T or not np.array_equal(frames, source):
        raise InputError(f"{tg.curves}: {len(frames)} frames ({int(frames[0]) if len(frames) else '-'} to "
                         f"{int(frames[-1]) if len(frames) else '-'}), the weights have frames {int(source[0])} to "
                         f"{int(source[-1])}: rerun auto-pose")
    out = np.zeros((T, rig.n_sliders))
    out[:, [rig.index[n] for n in names]] = C
    return np.clip(out, rig.lower, rig.upper)


def _rig_driver(regions, tg, targets, cache_dir, gap_fill=None, source=None):
    """Rig driving: curves from the weights (the gaps' frames by *gap_fill*), meshes from the rig at the curves."""

    rig = load_rig(tg.rig, cache_dir=cache_dir)
    if tg.curves is not None:
        curves = rig_frame_sliders(tg, rig, next(iter(regions.values()))[0].shape[0], source)
    else:
        S = rig_key_sliders(regions, tg, targets, rig)
        curves = rig_curves([W for _, (W, _, _) in sorted(regions.items())], S, rig.lower, rig.upper)
    if gap_fill is not None:
        curves = gap_fill(curves, np.clip(0.0, rig.lower, rig.upper))

    def positions(sl):
        return rig.evaluate(curves[sl])

    def glb():
        return rig_shapes(rig, curves)

    return positions, rig.template, rig.neutral, glb, (rig, curves)


@validate_params(PARAMS)
def run_apply(*, weights, targets, output, landmarks=None, formats=("obj",), head_motion="none", scale=None,
              pivot=None, vat="offsets", drive="auto", gaps="ease", gap_ease=0.4, head_rotation=True,
              progress=_no_progress, cache_dir=None) -> list[Path]:
    """Drive the character with the weights and export the result.

    Writes into *output*: ``frame_%05d.obj`` (streamed, chunk by chunk),
    ``weights.csv``, ``animation.exr`` + ``animation.json`` (vertex-animation
    texture), ``animation.glb`` and, when driving a rig, ``curves.csv`` +
    ``curves.npz`` (every frame's slider values, clipped to the rig's ranges),
    as *formats* asks.

    Parameters
    ----------
    drive : {"auto", "rig", "keys"}
        ``auto``: the rig when ``targets.yaml`` names one (``auto-pose``
        output), else the key shapes; ``keys`` blends the key OBJs with the
        region masks even when a rig is named.
    gaps : {"ease", "hold", "omit"}
        The rig's curves in the frames of a gap (*landmarks*' ``found``; :func:`retarget_cli.methods.gaps.fill_gaps`
        with the rig's rest pose, eases of *gap_ease* seconds); ``omit`` also leaves those frames out of
        ``curves.csv`` and ``livelink.csv``. ``curves.npz`` carries ``found``, ``curves.csv`` a ``found`` column.
    """

    weights, targets = _require(weights, "weights file"), _require(targets, "targets file")
    formats = _check_formats(formats)
    _check_choice("head_motion", head_motion, ("none", "2d"))
    _check_choice("vat", vat, ("offsets", "positions"))
    _check_choice("drive", drive, DRIVES)
    regions, meta, frames, times = load_weights(weights, timing=True)
    fps = float(meta.get("fps") or 30.0)
    tg = read_targets(targets)
    use_rig = _check_drive(regions, tg, targets, weights, formats, drive)
    out = Path(output)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a directory")
    for f in formats:
        for name in EXPORTS[f].files:
            check_not_input(out / name, [weights, targets, landmarks, *tg.files()])
    T = next(iter(regions.values()))[0].shape[0]
    found = _found_frames(landmarks, T) if use_rig else None
    if use_rig:
        def gap_fill(curves, rest):
            if found is None:
                return curves
            return fill_gaps(curves, found, behaviour=gaps, rest=rest, ease_frames=int(round(gap_ease * fps)))
        positions, template, base, glb, rig_out = _rig_driver(regions, tg, targets, cache_dir, gap_fill, frames)
    else:
        positions, template, base, glb, rig_out = _key_driver(regions, tg, targets, weights)
    head = _head_transforms(landmarks, T, base, scale, pivot) if head_motion == "2d" else None
    pose3d = _head_pose(landmarks, T) if head_rotation else None
    root = None
    if pose3d is not None:
        P = (base.min(0) + base.max(0)) / 2 if pivot is None else np.asarray(pivot, dtype=np.float64)
        root = head_rotation_transforms(pose3d[:, :3], pivot=P, transforms=head, keep_roll=head is None)
    out.mkdir(parents=True, exist_ok=True)
    ledger = TrackedOutputs(out, "apply")  # the output manifest of the folder: what apply wrote there
    rig, curves = rig_out if rig_out is not None else (None, None)
    ctx = ExportContext(out=out, fps=fps, n_frames=T, n_vertices=template.n_vertices, template=template, base=base,
                        positions=positions, head=head, regions=regions, weights=weights, targets=targets,
                        landmarks=landmarks, rig=rig, rig_file=tg.rig, curves=curves, morph_targets=glb,
                        settings={"vat": vat}, ledger=ledger, frames=frames, times=times,
                        source_fps=meta.get("source_fps"), found=found, gaps=gaps, head_pose=pose3d,
                        root_transforms=root)
    for f in formats:
        EXPORTS[f].check_context(ctx)
    exporters = [EXPORTS[f](ctx) for f in EXPORTS if f in formats]
    _stream(exporters, ctx, progress)
    for e in exporters:
        ledger.written.extend(e.finish())
    ledger.commit()  # removes what an earlier apply wrote and this one did not (frames past T, other formats)
    log.info("wrote %d frames of %d vertices to %s (%s; driven by %s)", T, template.n_vertices, out,
             ", ".join(formats), "the rig" if use_rig else "the key shapes")
    return ledger.written


def _head_pose(landmarks, T: int) -> np.ndarray | None:
    """(T, 6) yaw, pitch, roll (degrees) and translation of the head from *landmarks*, or None without them."""
    if landmarks is None:
        return None
    lm = load_landmarks(landmarks)
    if lm.head_angles is None:
        log.info("%s: no head_angles (track.head_pose off, or an older file); no 3D head rotation in the exports",
                 landmarks)
        return None
    if lm.n_frames != T:
        raise InputError(f"{landmarks}: has {lm.n_frames} frames but the weights have {T}")
    return np.concatenate([lm.head_angles, lm.head_translation], axis=1).astype(np.float64)


def _found_frames(landmarks, T: int) -> np.ndarray | None:
    """``found`` (T,) of *landmarks* when the take has gaps (None without a file, a flag or a gap)."""
    if landmarks is None:
        return None
    lm = load_landmarks(landmarks)
    if lm.found is None or lm.found.all():
        return None
    if lm.n_frames != T:
        raise InputError(f"{landmarks}: has {lm.n_frames} frames but the weights have {T}")
    log.info("%s: %s; the curves there follow apply.gaps", landmarks, gap_summary(lm.meta.get("gaps") or []))
    return lm.found_mask


def _check_choice(name: str, value, allowed) -> None:
    """*value* must be one of *allowed* (a one-line error naming the setting)."""
    if value not in allowed:
        expected = " or ".join(map(repr, allowed)) if len(allowed) == 2 else "one of " + ", ".join(allowed)
        raise ParameterError(f"{name}: expected {expected}, got {value!r}")


def _check_drive(regions, tg, targets, weights, formats, drive) -> bool:
    """Whether the rig drives the character; every format's needs checked (before any mesh is read)."""
    missing = sorted(set(regions) - set(tg.regions))
    if missing:
        raise InputError(f"{targets}: no targets for region {missing[0]!r} of {weights}")
    use_rig = tg.rig is not None and drive != "keys"
    if drive == "rig" and tg.rig is None:
        raise InputError(f"{targets}: drive rig needs a targets.yaml that names 'rig' and 'sliders' (from auto-pose)")
    for f in formats:
        if EXPORTS[f].needs_rig and not use_rig:
            raise InputError(f"{targets}: format {f} needs keys posed on a rig (a targets.yaml from auto-pose)")
        EXPORTS[f].check()
    return use_rig


def _stream(exporters, ctx, progress, chunk: int = 64) -> None:
    """The frames, chunk by chunk with head motion applied, to every exporter that streams."""

    streams = [e for e in exporters if e.streams]
    if not streams:
        return
    T = ctx.n_frames
    with progress(T, "apply") as bar:
        for start in range(0, T, chunk):
            sl = slice(start, min(start + chunk, T))
            pos = ctx.positions(sl)
            if ctx.head is not None:
                pos = apply_transforms(ctx.head[sl], pos)
            for e in streams:
                e.add(start, pos)
            bar.update(sl.stop - sl.start)


__all__ = ["DRIVES", "rig_key_sliders", "run_apply"]


def _targets_files(kw) -> list[Path]:
    return read_targets(kw["targets"]).files()


#: The pipeline stage (:mod:`retarget_cli.run.pipeline`).
STAGE = Stage(
    "apply",
    "Drive the target key shapes with the weights; write an OBJ sequence and other exports.",
    PARAMS,
    run_apply,
    extra_inputs=_targets_files,
    uses_progress=True,
    uses_cache=True,
)


def _cli_apply(values, out):
    kw = dict(values, formats=[f.strip() for f in values["formats"].split(",") if f.strip()])
    cache_dir = command_cache_dir(kw["output"], kw.pop("no_cache"), folder=True)
    return kw["output"], run_apply(**kw, progress=out.progress, cache_dir=cache_dir)


def _show_apply(result, out) -> None:
    output, written = result
    out.echo(f"{output} ({sum(p.suffix == '.obj' for p in written)} frames)")
    for p in written:
        if p.suffix != ".obj":
            out.echo(str(p))


#: ``apply`` (the CLI builds it: :mod:`retarget_cli.cli.commands`).
COMMAND = Command(
    "apply",
    """Drive the character in TARGETS with WEIGHTS; write an OBJ sequence, rig curves and other exports.

    With a TARGETS written by auto-pose (it names the rig), every frame's rig
    sliders follow from the weights and the meshes are the rig posed at them.
    """,
    lambda: [*PARAMS, NO_CACHE],
    (Flag("weights", argument=True, path="file"), Flag("targets", argument=True, path="file"),
     output_flag("frames", "Directory for the OBJ sequence and the other exports.", required=False),
     Flag("formats", decls=("--format",), value="text", default="obj", metavar="LIST",
          help=f"Comma-separated exports: {formats_help()}."),
     Flag("landmarks", path="file", show_default=False,
          help="landmarks.npz whose head motion --head-motion 2d applies and whose gaps --gaps fills."),
     "head_motion", "head_rotation", "scale", Flag("pivot", value="xyz", metavar="X,Y,Z", show_default=False), "vat", "drive",
     "gaps", "gap_ease", NO_CACHE_FLAG),
    _cli_apply,
    _show_apply,
    folder_output=True,
)
