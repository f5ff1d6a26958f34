"""File handling of ``edit``: an animation and ``edits.yaml`` in, edited weights (and OBJs) out."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from .._validate import closest
from ..config import Command, Flag, Param, output_flag, validate_params
from ..errors import InputError
from ..io.atomic import check_not_input, sha256_file, tracked_outputs
from ..io.editfiles import edits_rig, read_animation, read_edits, write_animation
from ..io.obj import FRAME_RE, write_obj
from ..io.rig import load_rig, read_rig
from ..methods.editing import apply_edits
from ._common import NO_CACHE, NO_CACHE_FLAG, _no_progress, _require, command_cache_dir

log = logging.getLogger(__name__)

#: Declared parameters of ``edit``.
PARAMS = [
    Param("animation", "input", str, help="Rig weights over time (CSV or NPZ)."),
    Param("edits", "input", str, help="edits.yaml: pins and attenuations over frame ranges."),
    Param("output", "output", str, help="Edited weights (.csv or .npz, same layout as ANIMATION)."),
    Param("rig", "input", str, None, "rig.yaml, or a .glb/.gltf/.vrm character (default: the 'rig:' named in "
          "EDITS).", nullable=True),
    Param("objs", "output", str, None,
          "Also write the posed OBJ sequence (frame_00000.obj, ...) into this directory.", nullable=True),
]


def _write_frames(out: Path, rig, W, frames, progress=_no_progress) -> list[Path]:
    """Write ``frame_%05d.obj`` (named by frame number) for each pose; remove stale frames of earlier runs."""

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


@validate_params(PARAMS)
def run_edit(*, animation, edits, output, rig=None, objs=None, progress=_no_progress, cache_dir=None) -> list[Path]:
    """Apply ``edits.yaml`` (pins and attenuations over frame ranges) to rig weights over time.

    The rig is *rig* or else the ``rig:`` named in ``edits.yaml``. Writes the
    edited weights to *output* (CSV or NPZ, by extension) and, with *objs*,
    the posed OBJ sequence (``frame_%05d.obj``, by frame number). The
    animation and the edits are checked (against ``rig.yaml`` and the
    neutral's vertex count) before the rig's OBJs are read; *cache_dir* keeps
    the parsed rig (:func:`~retarget_cli.io.rig.load_rig`).
    """

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
    if spec.neutral is not None:
        _require(spec.neutral, "neutral OBJ of the rig")
    todo = read_edits(edits, n_vertices=spec.vertex_count(), frames=frames,
                      expressions=[str(e) for e in spec.library])
    r = load_rig(rig_path, cache_dir=cache_dir)
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


def _cli_edit(values, out):
    kw = dict(values)
    cache_dir = command_cache_dir(kw["output"], kw.pop("no_cache"))
    return run_edit(**kw, progress=out.progress, cache_dir=cache_dir)


#: ``edit`` (the CLI builds it: :mod:`retarget_cli.cli.commands`).
COMMAND = Command(
    "edit",
    """Apply the pins and attenuations of EDITS to the rig weights in ANIMATION (CSV or NPZ).

    Pins are direct manipulation (Lewis & Anjyo 2010, eq. 3); attenuations are
    selected motion attenuation (Lewis et al. 2005, eq. 3).
    """,
    lambda: [*PARAMS, NO_CACHE],
    (Flag("animation", argument=True, path="file"), Flag("edits", argument=True, path="file"),
     output_flag(None, "Edited weights (.csv or .npz, same layout as ANIMATION)."),
     Flag("rig", path="file"), Flag("objs", path="folder"), NO_CACHE_FLAG),
    _cli_edit,
)
