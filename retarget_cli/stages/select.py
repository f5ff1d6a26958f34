"""File handling of ``select``: ``landmarks.npz`` in, ``keys.json`` (and a ``targets.yaml`` template) out."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..config import TOP_LEVEL, Command, Flag, Param, check_regions, output_flag, validate_params
from ..errors import InputError
from ..io.atomic import check_not_input, write_json, write_text
from ..io.frames import is_sequence, sequence_files
from ..io.landmarks import LOST_CONFIDENCE, load_landmarks
from ..io.select_plots import curve_csv, write_contact_sheet, write_curve_plot
from ..io.stagefiles import write_keys, write_targets
from ..methods.regions import region_specs
from ..methods.selection import curve_winner, evaluation_curve, key_error, select_keys
from ._common import Stage, _no_progress, _require
from ._neutral import choose_neutral

log = logging.getLogger(__name__)

#: Declared parameters of ``select`` (YAML validation, CLI options, manifests, docs/config.md).
PARAMS = [
    Param("landmarks", "input", str, help="landmarks.npz.", link="track.output"),
    Param("video", "input", str, None, "Video, for the contact sheet.", nullable=True, link="track.video"),
    Param("output", "output", str, "keys.json", "Key frames per region."),
    Param("template", "output", str, "targets.template.yaml",
          "targets.yaml template for the artist (never overwritten).", nullable=True),
    Param("evaluate", "output", str, None,
          "CSV of E (eq. 5) against k for every method and region; a JSON summary of the winner at "
          "the chosen k is written beside it (suffix .json).", nullable=True),
    Param("plot", "output", str, None, "Plot of the evaluation (PNG/SVG/PDF; needs matplotlib).",
          nullable=True),
    Param("contact_sheet", "output", str, None,
          "Image of the key frames cropped from the video with their landmarks.", nullable=True),
    Param("method", "setting", str, "greedy", "Selection method (convex-hull chooses its own k).",
          choices=("pca-extremes", "kmeans", "convex-hull", "greedy", "greedy-swap")),
    Param("k", "setting", int, 12, "Number of key shapes per region.", min=1, max=1000),
    Param("kmeans_components", "setting", int, 2, "Principal components clustered by kmeans.",
          min=1, max=10),
    Param("evaluate_k", "setting", int, 40, "Largest k of the evaluation curve.", min=2, max=1000),
    Param("neutral_frame", "setting", int, "auto",
          "Frame always kept as a key, the actor at rest (a source frame number, as landmarks.npz frames): auto finds it (the calibration of track.neutral "
          "when there is one, else the take's frame with closed lips and open eyes nearest its most common "
          "shape; recorded in keys.json for decompose and auto_pose); null to let the method choose all k.",
          min=0, nullable=True, words=("auto",)),
    Param("regions", "setting", dict, None,
          "Region name to 'all', landmark indices, null (68-point preset: brows-eyes, mouth, face) "
          "or {points, k} (default: face: all).", nullable=True, validate=check_regions),
]

#: First line of the targets template ``select`` writes; a file without it is never overwritten.
TEMPLATE_MARK = "# targets.yaml template written by retarget select.\n"


@validate_params(PARAMS)
def run_select(*, landmarks, output, template=None, method="greedy", k=12, regions=None,
               neutral_frame="auto", kmeans_components=2, evaluate=None, plot=None, evaluate_k=40,
               contact_sheet=None, video=None, seed=0, progress=_no_progress) -> list[Path]:
    """Choose key frames per region; write ``keys.json`` and a ``targets.yaml`` template.

    With *evaluate*, also the error curve of every method (CSV), a JSON summary
    of the winner at each region's k (*evaluate* with suffix ``.json``) and,
    with *plot*, the curves as a picture (Fig. 6 of Chuang & Bregler 2002).
    With *contact_sheet*, the key frames cropped from *video* with their landmarks.
    *neutral_frame* (a frame, ``"auto"`` or None) is resolved by
    :func:`retarget_cli.stages._neutral.choose_neutral` and recorded in ``keys.json``.
    """

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
    source = lm.timing()[0]  # each row's source frame number: keys are named by it
    neutral = choose_neutral(neutral_frame, lm, landmarks=landmarks)
    include = () if neutral is None else (neutral.frame,)
    specs = region_specs(regions, lm.n_points, k)
    # what the selection reads: a long take's other arrays are not held through it (the contact sheet's points)
    stab, conf, found = lm.stabilized, lm.confidence, lm.found_mask
    sheet = (lm.points, lm.frames, lm.source_fps) if contact_sheet else None
    del lm
    result, tmpl, curves, chosen_k = {}, {}, {}, {}
    with progress(len(specs) * (7 if evaluate else 1), "select") as bar:
        for name, (idx, rk) in specs.items():
            # the region's rows at float64 (a long take's whole float64 landmarks are not held), the usable ones
            X = stab[:, idx].astype(np.float64).reshape(len(source), -1)
            keep = _usable_frames(X, name, landmarks, include, found, rk,
                                  lost=(conf[:, idx] <= LOST_CONFIDENCE).all(1))
            local = {int(f): i for i, f in enumerate(keep)}
            Xk = X if len(keep) == len(X) else X[keep]
            del X
            inc = tuple(local[int(f)] for f in include)
            try:
                frames = keep[select_keys(Xk, rk, method=method, include=inc, seed=seed, components=kmeans_components)]
                bar.update(1)
                if evaluate:
                    rows = evaluation_curve(Xk, max(evaluate_k, len(frames)), k=len(frames), include=inc,
                                            seed=seed, progress=bar.update)
                    curves[name] = [{**r, "frames": [int(source[keep[f]]) for f in r["frames"]]} for r in rows]
            except ValueError as exc:
                raise InputError(f"{landmarks}: region {name!r}: {exc}") from exc
            err = key_error(Xk, [local[int(f)] for f in frames])
            chosen_k[name] = len(frames)
            labels = [int(source[f]) for f in frames]
            result[name] = {"points": idx, "method": method, "frames": labels, "rows": [int(f) for f in frames],
                            "error": round(err, 6)}
            tmpl[name] = {"keys": {f: f"target/{name}/key_{f:05d}.obj" for f in labels}}
            log.info("region %s: keys %s, E = %.4g (eq. 5)", name, result[name]["frames"], err)
    write_keys(output, landmarks, result, None if neutral is None else neutral.record)
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
        written += _write_evaluation(evaluate, plot, curves, chosen_k, result, method)
    if contact_sheet:

        if not is_sequence(video):
            video = _require(video, "video file")
        write_contact_sheet(contact_sheet, video, sheet[0],
                            {n: (r["points"], r["rows"]) for n, r in result.items()}, source_frames=sheet[1],
                            fps=sheet[2])
        written.append(Path(contact_sheet))
    return written



def _usable_frames(X, name, landmarks, include, found=None, k=None, lost=None) -> np.ndarray:
    """Frames of region *name* (rows of *X*) without lost landmarks, in which the face was found (*found*,
    (T,) bool); the frames in *include* must be among them, and at least *k* of them.

    Frames where a landmark of the region is lost (NaN), or all of them are (*lost*: confidence 0 in every
    point, a frame missing from an image sequence), can be neither keys nor scored by eq. 5; decompose
    interpolates their weights later. Frames in a gap of the take (``landmarks.npz``'s ``found``) hold another
    frame's landmarks: never a key.
    """
    finite = np.isfinite(X).all(1)
    if lost is not None:
        finite &= ~lost
    n_nan = int((~finite & (True if found is None else found)).sum())  # (gap frames are counted apart)
    if found is not None and not found.all():
        gaps = np.flatnonzero(~found)
        bad_inc = [int(f) for f in include if not found[f]]
        if bad_inc:
            raise InputError(f"{landmarks}: neutral frame {bad_inc[0]} is in a gap of the take (no face found "
                             "there); choose another neutral_frame, or auto")
        log.info("%s: region %s: %d frames in gaps (no face; first %d) are left out of key selection", landmarks,
                 name, gaps.size, int(gaps[0]))
        finite &= found
        if k is not None and finite.sum() < k:
            raise InputError(f"{landmarks}: the face was found in {int(found.sum())} of {len(found)} frames, "
                             f"{int(finite.sum())} of them usable for region {name!r}; key selection needs at "
                             f"least k = {k}")
    keep = np.flatnonzero(finite)
    if keep.size == 0:
        raise InputError(f"{landmarks}: region {name!r}: every frame has lost (NaN) landmarks")
    if n_nan:
        log.warning("%s: region %s: %d frames with lost landmarks are left out of key selection",
                    landmarks, name, n_nan)
    bad_inc = [f for f in include if f not in set(keep.tolist())]
    if bad_inc:
        raise InputError(f"{landmarks}: region {name!r}: neutral frame {bad_inc[0]} has lost (NaN) landmarks; "
                         "choose another neutral_frame")
    return keep


def _write_evaluation(evaluate, plot, curves, chosen_k, result, method) -> list[Path]:
    """The evaluation curve (CSV), its summary (JSON beside it) and, with *plot*, its picture."""

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
    written = [Path(evaluate), summary_path]
    if plot:
        write_curve_plot(plot, curves, chosen_k)
        written.append(Path(plot))
    return written


#: The pipeline stage (:mod:`retarget_cli.run.pipeline`).
STAGE = Stage(
    "select",
    "Choose key frames per region (Chuang & Bregler §4.2) and evaluate the methods by E (eq. 5).",
    PARAMS,
    run_select,
    expand_input=lambda name, path: sequence_files(path) if name == "video" and is_sequence(path) else [path],
    uses_seed=True,
    uses_progress=True,
)


def _cli_select(values, out):
    kw = dict(values)
    if kw.get("template") == _param("template").default and kw.get("output"):
        kw["template"] = str(Path(kw["output"]).parent / kw["template"])  # beside the keys, not in the cwd
    if kw.pop("no_neutral"):
        kw["neutral_frame"] = None
    return run_select(**dict(kw, regions=dict(kw["regions"]) or None), progress=out.progress)


def _param(name: str) -> Param:
    return next(p for p in PARAMS if p.name == name)


#: ``--no-neutral`` of the command (in a config: ``neutral_frame: null``).
NO_NEUTRAL = Param("no_neutral", "setting", bool, False, "Let the method choose all k keys.")

#: ``select`` (the CLI builds it: :mod:`retarget_cli.cli.commands`).
COMMAND = Command(
    "select",
    """Choose key frames from LANDMARKS (Chuang & Bregler §4.2) and optionally evaluate every method.""",
    lambda: [*PARAMS, NO_NEUTRAL, TOP_LEVEL["seed"]],
    (Flag("landmarks", argument=True, path="file"),
     output_flag("keys.json", "Key frames per region (keys.json).", required=False),
     Flag("k", decls=("-k",),
          help=_param("k").help + " Ignored by convex-hull, whose size the data sets (a warning says so)."),
     "method", "kmeans_components", "neutral_frame",
     Flag("no_neutral", decls=("--no-neutral",), show_default=False),
     Flag("regions", decls=("--region",), value="region", multiple=True, metavar="NAME[=SPEC][:K]",
          show_default=False,
          help="A region, its landmarks and optionally its own k, e.g. mouth=48-67,3-13:8, face=all, or a "
               "68-point preset by name: brows-eyes, mouth, face (mouth:8). Repeatable; default face=all."),
     Flag("template", path="file", show_default=False,
          help="The targets.yaml template for the artist (default: targets.template.yaml beside the keys file; "
               "never overwrites a file select did not write)."),
     Flag("evaluate", path="file", metavar="CURVE.csv", show_default=False),
     Flag("plot", path="file", metavar="CURVE.png", show_default=False),
     "evaluate_k",
     Flag("contact_sheet", path="file", metavar="KEYS.png", show_default=False),
     Flag("video", path="file", show_default=False, help="The take's video (for --contact-sheet)."),
     Flag("seed", help="Random seed.")),
    _cli_select,
)
