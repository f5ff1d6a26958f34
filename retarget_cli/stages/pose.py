"""File handling of ``pose-keys``: the rig posed at each key frame's known slider values, ``targets.yaml`` out."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from ..config import Command, Flag, Param, check_masks, output_flag, validate_params
from ..errors import InputError
from ..io.atomic import check_not_input, load_npz, tracked_outputs
from ..io.obj import write_obj
from ..io.rig import load_rig, read_rig
from ..io.stagefiles import read_keys, read_vertex_mask, write_targets
from ._common import NO_CACHE, NO_CACHE_FLAG, Stage, _require, command_cache_dir

log = logging.getLogger(__name__)

#: The neutral that ``pose-keys`` and ``auto-pose`` write beside the keys when the rig has no neutral OBJ
#: (a rig read from a ``.glb``/``.gltf``/``.vrm``), so that ``targets.yaml`` names one.
NEUTRAL_OBJ = "neutral.obj"

#: Declared parameters of ``pose`` (YAML validation, CLI options, manifests, docs/config.md).
PARAMS = [
    Param("keys", "input", str, help="keys.json.", link="select.output"),
    Param("rig", "input", str, help="rig.yaml (a neutral OBJ plus named shape OBJs, or 'source:' a character "
          "file), or a .glb/.gltf/.vrm character with morph targets."),
    Param("poses", "input", str, help="NPZ with 'curves' (T, E) and 'names' (E,)."),
    Param("output", "output", str, "targets", "Directory for the key OBJs and targets.yaml."),
    Param("masks", "setting", dict, None,
          "Region name to vertex-mask file (needed with several regions).", nullable=True,
          validate=check_masks),
]


@validate_params(PARAMS)
def run_pose(*, keys, rig, poses, output, masks=None, base_dir=None, cache_dir=None) -> list[Path]:
    """Pose the rig at each key frame's known slider values; write target OBJs and ``targets.yaml``.

    *masks* maps region names to vertex-mask files (relative to *base_dir*),
    copied into ``targets.yaml`` so ``apply`` can blend the regions.
    Every argument is checked before the rig's OBJs are read; *cache_dir*
    keeps the parsed rig (:func:`~retarget_cli.io.rig.load_rig`).

    This is the automatic "artist" for takes whose slider values are known
    (synthetic takes, or a performance recorded on a rig).
    """

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
    # a key is named by its source frame: the poses' row of that frame (their 'frames', else row = frame number)
    pose_frames = np.asarray(data["frames"]) if "frames" in data else np.arange(len(curves))
    if pose_frames.shape != (len(curves),):
        raise InputError(f"{poses}: 'frames' must have shape ({len(curves)},), one per row of 'curves'")
    pose_row = {int(f): i for i, f in enumerate(pose_frames)}
    for reg in kf.regions.values():
        for f in reg["frames"]:
            if f not in pose_row:
                raise InputError(f"{keys}: key frame {f} is outside {poses} ({len(curves)} frames, "
                                 f"{int(pose_frames[0]) if len(curves) else '-'} to "
                                 f"{int(pose_frames[-1]) if len(curves) else '-'})")
    mask_files = _check_masks(kf, keys, masks, base_dir)
    out = Path(output)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a directory")
    planned = [out / f"{name}/key_{f:05d}.obj" for name, reg in kf.regions.items() for f in reg["frames"]]
    planned += [out / NEUTRAL_OBJ] if spec.neutral is None else []
    inputs = [keys, rig_path, poses, *spec.files(), *mask_files.values()]
    for o in [*planned, out / "targets.yaml"]:
        check_not_input(o, inputs)
    if mask_files:
        if spec.neutral is not None:
            _require(spec.neutral, "neutral OBJ of the rig")
        n_vertices = spec.vertex_count()
        for mask in mask_files.values():
            read_vertex_mask(mask, n_vertices)
    rig = load_rig(rig_path, cache_dir=cache_dir)
    cols = [rig.index[n] for n in names]
    regions = {}
    with tracked_outputs(out, "pose-keys", planned=[*planned, out / "targets.yaml"]) as written:
        for name, reg in kf.regions.items():
            regions[name] = {"keys": {}}
            for f in reg["frames"]:
                rel = f"{name}/key_{f:05d}.obj"
                w = np.zeros(rig.n_sliders)
                w[cols] = curves[pose_row[f]]
                write_obj(written.add(out / rel), rig.template, rig.evaluate(w))
                regions[name]["keys"][f] = rel
        neutral = targets_neutral(out, rig, written.add)
        written.add(_write_targets_yaml(out, kf, keys, regions, masks, base_dir, neutral, "pose-keys"))
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


def targets_neutral(out: Path, rig, add) -> str:
    """``targets.yaml``'s ``neutral:`` relative to *out*: the rig's neutral OBJ, or, for a rig read from a
    character file (no neutral OBJ), :data:`NEUTRAL_OBJ` written into *out* (passed to *add*) from the rig."""
    if rig.spec.neutral is not None:
        return os.path.relpath(rig.spec.neutral.resolve(), out.resolve())
    write_obj(add(out / NEUTRAL_OBJ), rig.template, rig.neutral)
    return NEUTRAL_OBJ


def _write_targets_yaml(out: Path, kf, keys, regions, masks, base_dir, neutral: str, command) -> Path:
    """Add the region masks to *regions* and write ``out/targets.yaml`` (*neutral* relative to *out*)."""

    for name, mask in _check_masks(kf, keys, masks, base_dir).items():
        regions[name]["vertices"] = os.path.relpath(mask.resolve(), out.resolve())
    write_targets(out / "targets.yaml", regions, neutral=neutral, comment=f"Written by retarget {command}.")
    return out / "targets.yaml"


def _pose_files(kw) -> list[Path]:
    masks = [Path(kw["base_dir"]) / m for m in (kw.get("masks") or {}).values()]
    spec = read_rig(kw["rig"])
    extra = [spec.landmarks] if isinstance(spec.landmarks, Path) else []
    return spec.files() + extra + masks


#: The pipeline stage (:mod:`retarget_cli.run.pipeline`).
STAGE = Stage(
    "pose",
    "Pose a rig at each key frame's known slider values (automatic target key shapes).",
    PARAMS,
    run_pose,
    extra_inputs=_pose_files,
    uses_base_dir=True,
    uses_cache=True,
)


def _cli_pose(values, out):
    kw = dict(values, masks=dict(values["masks"]))
    cache_dir = command_cache_dir(kw["output"], kw.pop("no_cache"), folder=True)
    return run_pose(**kw, cache_dir=cache_dir)


#: ``pose-keys`` (the CLI builds it: :mod:`retarget_cli.cli.commands`).
COMMAND = Command(
    "pose-keys",
    """Pose RIG at every key frame's known slider values (automatic target keys).""",
    lambda: [*PARAMS, NO_CACHE],
    (Flag("keys", argument=True, path="file"), Flag("rig", argument=True, path="file"),
     Flag("poses", path="file", required=True, show_default=False,
          help="NPZ with per-frame slider values: 'curves' (T, E) and 'names' (E,)."),
     Flag("masks", decls=("--mask",), value="mask", multiple=True, metavar="REGION=FILE", show_default=False,
          help="Vertex mask of a region (needed with several regions). Repeatable."),
     output_flag("targets", "Directory for the key OBJs and targets.yaml.", required=False),
     NO_CACHE_FLAG),
    _cli_pose,
    folder_output=True,
)
