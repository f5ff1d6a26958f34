"""Command-line interface: one command per stage plus ``run`` and ``synth``.

This module only parses arguments and reports; the work happens in
:mod:`retarget_cli.stages`, :mod:`retarget_cli.run.pipeline` and the stage
modules. Heavy libraries (OpenCV, scikit-learn) are imported inside commands so
that ``retarget --help`` stays instant.
"""

from __future__ import annotations

import contextlib
import logging
import sys

import click

from .. import __version__
from ..batch import engine
from ..batch.engine import PARAMS as BATCH_PARAMS
from ..batch.plan import format_table, load_plan, pending
from ..config import Param, load_config
from ..errors import INTERRUPTED_EXIT_STATUS, RetargetError
from ..io.atomic import guard_writes, remove_stale_parts
from ..io.exports import formats_help
from ..io.stagefiles import load_weights
from ..methods.render import Camera
from ..methods.tracking import tracker_params
from ..run.pipeline import RUN_PARAMS, STAGES, run_pipeline, stage_params
from ..run.runfiles import locate_run
from ..see import settings as see
from ..see.preview import write_preview, write_render
from ..see.report import write_report
from ..stages import annotate as detect
from ..stages import (
    run_apply,
    run_auto_pose,
    run_decompose,
    run_edit,
    run_import,
    run_pose,
    run_select,
    run_solve_rig,
    run_track,
    run_train_tracker,
)
from ..stages.annotate import run_annotate
from ..stages.track import PARAMS as TRACK_PARAMS
from ..synth.take import write_take
from .types import IndexList, Size

log = logging.getLogger("retarget_cli")

_TYPES = {int: click.INT, float: click.FLOAT, str: click.STRING}


def _param(command: str, name: str) -> Param:
    """The declared :class:`Param` *name* of a pipeline stage or a command (:func:`command_params`)."""
    return next(p for p in command_params(command) if p.name == name)


def command_params(command: str) -> list[Param]:
    """The declarations of a pipeline stage (``track``, ``auto_pose``, ...) or of another command."""

    if command in STAGES:
        return STAGES[command].params
    from ..stages import edit, solve_rig, track

    return {"train-tracker": track.TRAIN_PARAMS, "import": track.IMPORT_PARAMS, "annotate": detect.PARAMS,
            "edit": edit.PARAMS, "solve-rig": solve_rig.PARAMS, "render": see.RENDER_PARAMS,
            "preview": see.PREVIEW_PARAMS, "report": see.REPORT_PARAMS, "synth": see.SYNTH_PARAMS,
            "batch": _batch_params(), "run": _run_params()}[command]


def _batch_params():
    return BATCH_PARAMS


def _run_params():
    return RUN_PARAMS


def setting(command: str, name: str, *decls, **extra):
    """A click option built from the command's declared :class:`Param` (one source of truth)."""
    decls, kw = _option_spec(_param(command, name), decls, extra)
    return click.option(*decls, name, **kw)


def _option_spec(p: Param, decls=(), extra=None) -> tuple[tuple, dict]:
    """Click option declarations and keywords for *p*: its flag, help, type, range or choices, default."""
    flag = "--" + p.name.replace("_", "-")
    kw = dict(help=p.help, show_default=True)
    if p.type is bool:
        decls = decls or (f"{flag}/--no-{flag[2:]}",)
        kw.update(default=p.default, is_flag=True)
    else:
        decls = decls or (flag,)
        if p.options:
            kw["type"] = click.Choice(p.options)
        elif p.type in (int, float) and (p.min is not None or p.max is not None):
            kw["type"] = (click.IntRange if p.type is int else click.FloatRange)(p.min, p.max, min_open=p.min_open,
                                                                                 max_open=p.max_open)
        else:
            kw["type"] = _TYPES.get(p.type, click.STRING)
        kw["default"] = p.default
    kw.update(extra or {})
    return decls, kw


def output_option(default=None, help="Output file.", required=True):
    return click.option("-o", "--output", type=click.Path(dir_okay=True), required=required, default=default,
                        help=help, show_default=default is not None)


def no_cache_option(f):
    return click.option("--no-cache", is_flag=True,
                        help="Read the rig's OBJs every time instead of keeping them parsed in a .retarget-cache "
                             "folder in the output's folder.")(f)


def _cache_dir(output, no_cache: bool, *, output_is_dir: bool = False):
    """The rig cache of a single command: ``.retarget-cache`` in the folder the output goes to."""
    from pathlib import Path

    if no_cache:
        return None
    folder = Path(output) if output_is_dir else Path(output).parent
    return folder / ".retarget-cache"


@contextlib.contextmanager
def progress(length, label):
    """A click progress bar on stderr (hidden when stderr is not a terminal or with -q)."""
    quiet = logging.getLogger("retarget_cli").getEffectiveLevel() > logging.WARNING
    if length is None or quiet:
        class _Null:
            def update(self, n):
                pass

        yield _Null()
        return
    with click.progressbar(length=length, label=label, file=sys.stderr) as bar:
        yield bar


#: Parameters of the stage commands that name outputs (everything else that is a path is an input).
OUTPUT_PARAMS = ("output", "csv", "overlay", "template", "evaluate", "plot", "contact_sheet", "metrics", "objs",
                 "outdir")
#: Commands whose ``--output``/OUTDIR is a folder (the command writes inside it).
DIR_OUTPUT_COMMANDS = ("apply", "pose-keys", "auto-pose", "annotate", "synth")


def one_line(exc: BaseException) -> str:
    """An exception as the one-line message the CLI prints.

    The tool's own errors (:class:`~retarget_cli.errors.RetargetError`), an
    ``OSError`` naming a file and running out of memory are the user's to fix and
    print their message; anything else is a bug and says so.
    """
    if isinstance(exc, OSError) and getattr(exc, "filename", None):
        return f"{exc.filename}: {exc.strerror or exc}"
    if isinstance(exc, MemoryError):
        return "out of memory" + (f" ({exc})" if str(exc) else "") + "; is an input far larger than expected?"
    msg = " ".join(str(exc).split())
    if isinstance(exc, RetargetError) and msg:
        return msg
    return (f"internal error ({type(exc).__name__}{': ' + msg[:300] if msg else ''}); "
            "rerun with -vv for the traceback")


def exit_status(exc: BaseException) -> int:
    """The exit status for *exc*: its own for the tool's errors, else 1."""
    return getattr(exc, "exit_status", 1) if isinstance(exc, RetargetError) else 1


def _input_files(value) -> list:
    """The files a path-valued argument stands for (a folder's files, a glob's matches, REGION=FILE's file)."""
    import glob
    from pathlib import Path

    if isinstance(value, (tuple, list)):
        return [f for v in value for f in _input_files(v)]
    if not isinstance(value, str) or not value:
        return []
    if "=" in value and not Path(value).exists():
        value = value.partition("=")[2]
    p = Path(value)
    if p.is_dir():
        return sorted(f for f in p.iterdir() if f.is_file())[:100_000]
    if any(c in value for c in "*?["):
        return sorted(glob.glob(value))[:100_000]
    return [p]


class GuardedCommand(click.Command):
    """A stage command whose writes pass the write guard (:func:`retarget_cli.io.atomic.guard_writes`).

    Writes may go inside the folder of each output the user named (or into
    the output folder itself) and never onto a file the command reads.
    Temporary files a killed run left there are removed first.
    """

    def invoke(self, ctx):
        if self.name in ("run", "batch"):  # the pipeline guards each run's output_dir; batch its batch folder
            return super().invoke(ctx)
        from pathlib import Path


        roots, files, inputs, recursive = [], [], [], []
        for name, value in ctx.params.items():
            if value is None or isinstance(value, bool):
                continue
            if name in OUTPUT_PARAMS:
                if not isinstance(value, str):
                    continue
                out = Path(value)
                folder = name in ("objs", "outdir") or (name == "output" and self.name in DIR_OUTPUT_COMMANDS)
                roots.append(out if folder else out.parent)
                recursive.append(folder)
                files.append(out)
            elif isinstance(value, (str, tuple, list)):
                inputs += _input_files(value)
        with guard_writes(roots=roots, files=files, inputs=inputs,
                          label="the folders of the outputs given on the command line"):
            for root, rec in zip(roots, recursive):
                remove_stale_parts(root, recursive=rec)
            return super().invoke(ctx)


class RetargetGroup(click.Group):
    """Turns every error into a one-line message and a non-zero exit (``-vv`` adds the traceback).

    Errors: exit status 1; Ctrl-C: exit status 130.
    """

    command_class = GuardedCommand

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except (click.exceptions.Exit, click.ClickException, click.exceptions.Abort):
            raise
        except KeyboardInterrupt:
            log.debug("interrupted", exc_info=True)
            click.echo("error: interrupted", err=True)
            ctx.exit(INTERRUPTED_EXIT_STATUS)
        except Exception as exc:
            log.debug("traceback of the error below", exc_info=True)
            click.echo(f"error: {one_line(exc)}", err=True)
            ctx.exit(exit_status(exc))


@click.group(cls=RetargetGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="retarget")
@click.option("-v", "--verbose", count=True, help="More log output on stderr (-vv for debug).")
@click.option("-q", "--quiet", is_flag=True, help="Only errors on stderr.")
def main(verbose: int, quiet: bool):
    """Retarget a video of an actor's face onto a blendshape character.

    \b
    Stages:  track -> select -> decompose -> apply   (chained by `retarget run`)
    Example: retarget synth demo/ && retarget run demo/config.yaml
    """
    level = logging.ERROR if quiet else (logging.DEBUG if verbose > 1 else logging.INFO if verbose else logging.WARNING)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr, force=True)
    logging.getLogger("retarget_cli").setLevel(level)


def _formats_help() -> str:
    return formats_help()


def _print_outputs(paths):
    for p in paths:
        click.echo(str(p))


@main.command()
@click.argument("video", type=click.Path(dir_okay=False))
@click.option("--init", "init", type=click.Path(dir_okay=False), default="auto", show_default=True,
              help="Annotation of the first tracked frame: iBUG .pts (frame from a name like face_00120.pts), "
                   "a frame,point,x,y CSV, or auto: the pretrained detector annotates it and writes "
                   "<output stem>.init_NNNNN.pts beside the output for review (needs the extra detect).")
@click.option("--annotation", "annotations", multiple=True, type=click.Path(dir_okay=False),
              help="More annotated frames (.pts or CSV); each re-anchors the track. Repeatable.")
@setting("track", "init_frame")
@output_option("landmarks.npz", "Landmarks file.", required=False)
@click.option("--overlay", type=click.Path(dir_okay=False), default=None,
              help="Also write an mp4 with the landmarks (green = confident, red = lost) and the head frame.")
@setting("track", "method")
@setting("track", "fuse")
@setting("track", "model", type=click.Path(dir_okay=False))
@setting("track", "window")
@setting("track", "levels")
@setting("track", "fb_threshold")
@setting("track", "anchor")
@setting("track", "start")
@setting("track", "end")
@setting("track", "step")
@setting("track", "downscale")
@setting("track", "fps")
@setting("track", "smooth_head")
@click.option("--rigid-points", type=IndexList(), default=None, metavar="SPEC",
              help="Landmarks that define head motion, e.g. 27-31,33,35,36,39,42,45 (default: eye corners "
                   "and nose for 68 points, else all).")
@setting("track", "keep_partial")
@setting("track", "filter")
@setting("track", "filter_model")
@setting("track", "filter_process_noise")
@setting("track", "filter_measurement_noise")
@setting("track", "filter_robust")
@setting("track", "filter_min_cutoff")
@setting("track", "filter_beta")
@setting("track", "filter_d_cutoff")
def track(video, init, annotations, output, rigid_points, **settings):
    """Track facial landmarks through VIDEO (a video file or an image-sequence pattern such as
    'frames/%05d.png' or 'frames/*.exr'), from one or more annotated frames (by default the detector
    annotates the first), or with --method detect by a pretrained detector on every frame."""

    rigid = rigid_points or None
    _print_outputs(run_track(video=video, init=init, annotations=list(annotations), output=output,
                             rigid_points=rigid, progress=progress, **settings))


def _add_tracker_options(command: click.Command) -> None:
    """``retarget track`` options for the settings registered trackers declare (:attr:`TrackerSpec.params`)."""

    for p in tracker_params(q.name for q in TRACK_PARAMS):
        decls, kw = _option_spec(p)
        command.params.append(click.Option([*decls, p.name], **kw))


_add_tracker_options(track)


@main.command("train-tracker")
@click.argument("video", type=click.Path(dir_okay=False))
@click.argument("annotations", nargs=-1, required=True, type=click.Path(dir_okay=False))
@output_option("facemark.yaml", "Model file (OpenCV Facemark LBF; gzip-compressed if the name ends in .gz).",
               required=False)
@setting("train-tracker", "fps")
@setting("train-tracker", "rigid_points", type=IndexList(), metavar="SPEC")
@setting("train-tracker", "stages")
@setting("train-tracker", "trees")
@setting("train-tracker", "depth")
@setting("train-tracker", "face_size")
@setting("train-tracker", "seed")
def train_tracker(video, annotations, output, fps, rigid_points, stages, trees, depth, face_size, seed):
    """Train a Facemark tracking model on annotated frames of VIDEO (a video or an image-sequence pattern).

    ANNOTATIONS are .pts files named with their frame number (face_00120.pts) or frame,point,x,y CSV files,
    as for `track`; 5 or more frames that span the actor's expressions. Use the model with
    `retarget track VIDEO --init face_00000.pts --method facemark --model facemark.yaml`."""

    rigid = rigid_points or None
    _print_outputs(run_train_tracker(video=video, annotations=list(annotations), output=output, fps=fps,
                                     rigid_points=rigid, stages=stages, trees=trees, depth=depth,
                                     face_size=face_size, seed=seed,
                                     progress=progress))


@main.command()
@click.argument("video", type=click.Path(dir_okay=False))
@click.option("--frames", "frames", required=True, metavar="LIST",
              help="Frames to annotate (0-based), e.g. 0,120,240 or 0-300:60 (every 60th from 0 to 300).")
@output_option(None, "Directory for the .pts files.")
@setting("annotate", "fps")
def annotate(video, frames, output, fps):
    """Place the 68 landmarks on chosen frames of VIDEO with the pretrained detector (needs the extra detect).

    Writes OUTPUT/<video stem>_<frame:05d>.pts (iBUG .pts, as `track --init/--annotation` and
    `train-tracker` read them); check them by eye before training or re-anchoring on them."""

    _print_outputs(run_annotate(video=video, frames=_parse_frames(frames), output=output, fps=fps))


def _parse_frames(spec: str) -> list[int]:
    """``0,120,240`` or ranges ``a-b`` (inclusive) with an optional step ``a-b:s``."""
    out = []
    for tok in spec.replace(" ", "").split(","):
        if not tok:
            continue
        try:
            if "-" in tok:
                rng, _, st = tok.partition(":")
                a, b = (int(v) for v in rng.split("-"))
                out += list(range(a, b + 1, int(st) if st else 1))
            else:
                out.append(int(tok))
        except ValueError:
            raise click.BadParameter(f"expected frame numbers such as 0,120 or 0-300:60, got {tok!r}",
                                     param_hint="--frames") from None
    if not out:
        raise click.BadParameter("give at least one frame", param_hint="--frames")
    return out


@main.command("import")
@click.argument("source", type=click.Path())
@output_option("landmarks.npz", "Landmarks file (landmarks.npz contract).", required=False)
@setting("import", "fps")
@setting("import", "frame_size", type=Size(example="1920x1080"), metavar="WxH")
@setting("import", "rigid_points", type=IndexList(), metavar="SPEC")
@setting("import", "smooth_head")
@setting("import", "filter")
@setting("import", "filter_model")
@setting("import", "filter_process_noise")
@setting("import", "filter_measurement_noise")
@setting("import", "filter_robust")
@setting("import", "filter_min_cutoff")
@setting("import", "filter_beta")
@setting("import", "filter_d_cutoff")
def import_(source, output, fps, frame_size, rigid_points, smooth_head, **filters):
    """Bring landmarks from another tool into landmarks.npz, with head motion and stabilization.

    SOURCE is a frame,point,x,y CSV, an NPZ with 'points' (T, L, 2) or a folder of .pts files (frame number
    from each name, e.g. face_00120.pts)."""

    rigid, size = rigid_points or None, frame_size
    _print_outputs(run_import(source=source, output=output, fps=fps, frame_size=size, rigid_points=rigid,
                              smooth_head=smooth_head, **filters))


@main.command()
@click.argument("landmarks", type=click.Path(dir_okay=False))
@output_option("keys.json", "Key frames per region (keys.json).", required=False)
@click.option("-k", "k", type=click.IntRange(1, 1000), default=_param("select", "k").default, show_default=True,
              help=_param("select", "k").help + " Ignored by convex-hull, whose size the data sets (a warning says so).")
@setting("select", "method")
@setting("select", "kmeans_components")
@click.option("--neutral-frame", type=click.IntRange(0), default=_param("select", "neutral_frame").default,
              show_default=True, help=_param("select", "neutral_frame").help)
@click.option("--no-neutral", is_flag=True, help="Let the method choose all k keys.")
@click.option("--region", "regions", multiple=True, metavar="NAME[=SPEC][:K]",
              help="A region, its landmarks and optionally its own k, e.g. mouth=48-67,3-13:8, face=all, or a "
                   "68-point preset by name: brows-eyes, mouth, face (mouth:8). Repeatable; default face=all.")
@click.option("--template", type=click.Path(dir_okay=False), default=None,
              help="Also write a targets.yaml template for the artist (never overwrites a file select did not write).")
@click.option("--evaluate", type=click.Path(dir_okay=False), default=None, metavar="CURVE.csv",
              help=_param("select", "evaluate").help)
@click.option("--plot", type=click.Path(dir_okay=False), default=None, metavar="CURVE.png",
              help=_param("select", "plot").help)
@setting("select", "evaluate_k")
@click.option("--contact-sheet", type=click.Path(dir_okay=False), default=None, metavar="KEYS.png",
              help=_param("select", "contact_sheet").help)
@click.option("--video", type=click.Path(dir_okay=False), default=None, help="The take's video (for --contact-sheet).")
@click.option("--seed", type=click.IntRange(0), default=0, show_default=True, help="Random seed.")
def select(landmarks, output, k, method, kmeans_components, neutral_frame, no_neutral, regions, template, evaluate,
           plot, evaluate_k, contact_sheet, video, seed):
    """Choose key frames from LANDMARKS (Chuang & Bregler §4.2) and optionally evaluate every method."""

    _print_outputs(run_select(landmarks=landmarks, output=output, template=template, method=method, k=k,
                              regions=_parse_regions(regions), neutral_frame=None if no_neutral else neutral_frame,
                              kmeans_components=kmeans_components, evaluate=evaluate, plot=plot,
                              evaluate_k=evaluate_k, contact_sheet=contact_sheet, video=video, seed=seed,
                              progress=progress))


def _parse_regions(specs) -> dict | None:
    """``NAME``, ``NAME=all`` or ``NAME=a-b,c,...`` (inclusive ranges), each optionally ``:K``, to region specs."""
    if not specs:
        return None
    out = {}
    for spec in specs:
        head, colon, kk = spec.rpartition(":") if ":" in spec else (spec, "", "")
        name, sep, body = head.partition("=")
        try:
            if not name or (sep and not body):
                raise ValueError
            k = int(kk) if colon else None
            if k is not None and k < 1:
                raise ValueError
            if not sep:
                pts = None
            elif body == "all":
                pts = "all"
            else:
                pts = []
                for part in body.split(","):
                    lo, _, hi = part.partition("-")
                    pts += list(range(int(lo), int(hi or lo) + 1))
            out[name] = pts if k is None else {"points": pts, "k": k}
        except ValueError:
            raise click.BadParameter(f"expected NAME, NAME=all or NAME=a-b,c,... optionally followed by :K, got {spec!r}",
                                     param_hint="--region") from None
    return out


@main.command()
@click.argument("landmarks", type=click.Path(dir_okay=False))
@click.argument("keys", type=click.Path(dir_okay=False))
@output_option("weights.npz", "Weights file (weights.npz).", required=False)
@click.option("--csv", type=click.Path(dir_okay=False), default=None, help="Also write the weights as CSV.")
@setting("decompose", "solver")
@setting("decompose", "formulation")
@setting("decompose", "alpha")
@setting("decompose", "upper")
@setting("decompose", "neutral_frame")
@setting("decompose", "confidence")
@setting("decompose", "lost_fraction")
@setting("decompose", "smooth_space")
@setting("decompose", "robust")
@click.option("--summary/--no-summary", default=True, show_default=True,
              help="Print a per-region table of residual, cardinality, jitter and lost frames after the file names.")
def decompose(landmarks, keys, output, csv, summary, **settings):
    """Decompose every frame into key-shape weights (non-negative by default, eq. 4)."""

    written = run_decompose(landmarks=landmarks, keys=keys, output=output, csv=csv, **settings)
    _print_outputs(written)
    if summary:
        diag = load_weights(written[0])[1].get("diagnostics", {})
        click.echo(f"{'region':<16}{'residual px':>12}{'cardinality':>12}{'jitter':>12}{'lost':>6}")
        for name, d in sorted(diag.items()):
            click.echo(f"{name:<16}{d['mean_residual_px']:>12.4f}{d['mean_cardinality']:>12.2f}"
                       f"{d['jitter']:>12.3g}{d['lost_frames']:>6d}")


@main.command("pose-keys")
@click.argument("keys", type=click.Path(dir_okay=False))
@click.argument("rig", type=click.Path(dir_okay=False))
@click.option("--poses", type=click.Path(dir_okay=False), required=True,
              help="NPZ with per-frame slider values: 'curves' (T, E) and 'names' (E,).")
@click.option("--mask", "masks", multiple=True, metavar="REGION=FILE",
              help="Vertex mask of a region (needed with several regions). Repeatable.")
@output_option("targets", "Directory for the key OBJs and targets.yaml.", required=False)
@no_cache_option
def pose_keys(keys, rig, poses, masks, output, no_cache):
    """Pose RIG at every key frame's known slider values (automatic target keys)."""

    _print_outputs(run_pose(keys=keys, rig=rig, poses=poses, output=output, masks=_parse_masks(masks),
                            cache_dir=_cache_dir(output, no_cache, output_is_dir=True)))


def _parse_masks(masks) -> dict:
    """``REGION=FILE`` options to ``{region: file}``."""
    parsed = {}
    for m in masks:
        region, sep, path = m.partition("=")
        if not sep or not region or not path:
            raise click.BadParameter(f"expected REGION=FILE, got {m!r}", param_hint="--mask")
        parsed[region] = path
    return parsed


@main.command()
@click.argument("weights", type=click.Path(dir_okay=False))
@click.argument("targets", type=click.Path(dir_okay=False))
@output_option("frames", "Directory for the OBJ sequence and the other exports.", required=False)
@click.option("--format", "formats", default="obj", show_default=True, metavar="LIST",
              help=f"Comma-separated exports: {_formats_help()}.")
@click.option("--landmarks", type=click.Path(dir_okay=False), default=None,
              help="landmarks.npz whose head motion --head-motion 2d applies.")
@setting("apply", "head_motion")
@setting("apply", "scale")
@click.option("--pivot", default=None, metavar="X,Y,Z", help=_param("apply", "pivot").help)
@setting("apply", "vat")
@setting("apply", "drive")
@no_cache_option
def apply(weights, targets, output, formats, landmarks, head_motion, scale, pivot, vat, drive, no_cache):
    """Drive the character in TARGETS with WEIGHTS; write an OBJ sequence, rig curves and other exports.

    With a TARGETS written by auto-pose (it names the rig), every frame's rig
    sliders follow from the weights and the meshes are the rig posed at them.
    """

    if pivot is not None:
        try:
            pivot = [float(v) for v in pivot.split(",")]
            if len(pivot) != 3:
                raise ValueError
        except ValueError:
            raise click.BadParameter(f"expected X,Y,Z, got {pivot!r}", param_hint="--pivot") from None
    fmts = [f.strip() for f in formats.split(",") if f.strip()]
    written = run_apply(weights=weights, targets=targets, output=output, landmarks=landmarks, formats=fmts,
                        head_motion=head_motion, scale=scale, pivot=pivot, vat=vat, drive=drive, progress=progress,
                        cache_dir=_cache_dir(output, no_cache, output_is_dir=True))
    n = sum(p.suffix == ".obj" for p in written)
    click.echo(f"{output} ({n} frames)")
    for p in written:
        if p.suffix != ".obj":
            click.echo(str(p))


@main.command()
@click.argument("animation", type=click.Path(dir_okay=False))
@click.argument("edits", type=click.Path(dir_okay=False))
@output_option(None, "Edited weights (.csv or .npz, same layout as ANIMATION).")
@setting("edit", "rig", type=click.Path(dir_okay=False))
@setting("edit", "objs", type=click.Path(file_okay=False))
@no_cache_option
def edit(animation, edits, output, rig, objs, no_cache):
    """Apply the pins and attenuations of EDITS to the rig weights in ANIMATION (CSV or NPZ).

    Pins are direct manipulation (Lewis & Anjyo 2010, eq. 3); attenuations are
    selected motion attenuation (Lewis et al. 2005, eq. 3).
    """

    _print_outputs(run_edit(animation=animation, edits=edits, rig=rig, output=output, objs=objs, progress=progress,
                            cache_dir=_cache_dir(output, no_cache)))


@main.command("auto-pose")
@click.argument("keys", type=click.Path(dir_okay=False))
@click.argument("landmarks", type=click.Path(dir_okay=False))
@click.argument("rig", type=click.Path(dir_okay=False))
@click.option("--landmark-vertices", type=click.Path(dir_okay=False), default=None,
              help=_param("auto_pose", "landmark_vertices").help)
@click.option("--mask", "masks", multiple=True, metavar="REGION=FILE",
              help="Vertex mask of a region, overriding the mask derived from the rig. Repeatable.")
@setting("auto_pose", "fit")
@setting("auto_pose", "neutral_frame")
@setting("auto_pose", "sparsity")
@setting("auto_pose", "ridge")
@click.option("--exclude", "exclude", multiple=True, metavar="PATTERN",
              help="Slider-name pattern kept at 0 (repeatable; default eyeLook*, *pupil*: gaze and pupils).")
@setting("auto_pose", "alpha")
@setting("auto_pose", "mu")
@output_option("targets", "Directory for the key OBJs, sliders.csv, masks/ and targets.yaml.", required=False)
@no_cache_option
def auto_pose(keys, landmarks, rig, landmark_vertices, masks, fit, neutral_frame, sparsity, ridge, exclude, alpha,
              mu, output, no_cache):
    """Pose RIG at every key frame of KEYS from its LANDMARKS: the rig as the artist.

    The default delta fit reproduces each key frame's landmark displacement
    from the neutral frame, so the actor's face shape stays out of the
    sliders; apply then writes the rig's slider curves.
    """

    _print_outputs(run_auto_pose(keys=keys, landmarks=landmarks, rig=rig, landmark_vertices=landmark_vertices,
                                 output=output, masks=_parse_masks(masks), fit=fit, neutral_frame=neutral_frame,
                                 sparsity=sparsity, ridge=ridge,
                                 exclude=list(exclude) if exclude else list(_param("auto_pose", "exclude").default),
                                 alpha=alpha, mu=mu, cache_dir=_cache_dir(output, no_cache, output_is_dir=True)))


@main.command("solve-rig")
@click.argument("rig", type=click.Path(dir_okay=False))
@click.argument("meshes")
@output_option(None, "Slider curves (NPZ: curves, names, per-frame metrics).")
@setting("solve-rig", "solver")
@setting("solve-rig", "alpha")
@setting("solve-rig", "tol", type=click.FloatRange(0, min_open=True))
@setting("solve-rig", "max_iter")
@setting("solve-rig", "metrics", type=click.Path(dir_okay=False))
@no_cache_option
def solve_rig(rig, meshes, output, solver, alpha, tol, max_iter, metrics, no_cache):
    """Slider weights in [0, 1] of RIG (with corrective shapes) that reproduce MESHES.

    MESHES is a directory of frame_*.obj, a glob such as 'scans/*.obj', or an
    NPZ with positions (T, N, 3).
    """

    written, s = run_solve_rig(rig=rig, meshes=meshes, output=output, solver=solver, alpha=alpha, tol=tol,
                               max_iter=max_iter, metrics=metrics, progress=progress,
                               cache_dir=_cache_dir(output, no_cache))
    click.echo(f"{s['frames']} frames, {s['vertices']} vertices, {s['shapes']} shapes, "
               f"{s['correctives']} correctives; solver {solver}, alpha {alpha:g}")
    click.echo(f"mean rmse {s['rmse']:.6g}  cardinality {s['cardinality']:.2f}  objective {s['objective']:.6g}  "
               f"iterations {s['iterations']:.1f}  seconds/frame {s['seconds_per_frame']:.4f}")
    _print_outputs(written)


@main.command()
@click.argument("config", type=click.Path(dir_okay=False))
@setting("run", "force", "--force", show_default=False)
@setting("run", "start", "--from", metavar="STAGE", show_default=False)
@setting("run", "stop", "--until", metavar="STAGE", show_default=False)
@setting("run", "overrides", "--set", multiple=True, metavar="STAGE.KEY=VALUE", show_default=False, default=None)
@setting("run", "no_cache", "--no-cache", show_default=False)
def run(config, force, start, stop, overrides, no_cache):
    """Run the pipeline described by CONFIG, skipping stages that are up to date."""

    cfg = load_config(config, stage_params(), overrides)
    for name, status, outs in run_pipeline(cfg, force=force, start=start, stop=stop, progress=progress,
                                           cache=not no_cache):
        if log.getEffectiveLevel() <= logging.WARNING:
            click.echo(f"{name}: {status}", err=True)
        for p in outs:
            click.echo(f"{name}\t{p}")


@main.command()
@click.argument("shots", type=click.Path(dir_okay=False))
@setting("batch", "jobs", "-j", "--jobs", show_default=False)
@setting("batch", "scheduler", metavar="ADDRESS", show_default=False)
@setting("batch", "retries")
@setting("batch", "only", multiple=True, metavar="PATTERN", show_default=False, default=None)
@setting("batch", "force", "--force", show_default=False)
@setting("batch", "emit_commands", "--emit-commands", show_default=False)
@setting("batch", "report", "--report", show_default=False)
@setting("batch", "output_dir", "-o", "--output-dir", type=click.Path(file_okay=False), show_default=False)
def batch(shots, jobs, scheduler, retries, only, force, emit_commands, report, output_dir):
    """Run every shot of the shot list SHOTS (YAML or CSV) through the pipeline on Dask.

    Each shot runs `retarget run` into its own output folder (resumable by its
    manifests); a failed shot is retried, then reported, and never stops the
    others. Writes batch.json and index.html into the batch folder and a
    summary table on stdout. See README, "Many shots".
    """
    import time as _time


    plan = load_plan(shots, output_dir=output_dir)
    chosen = plan.select(only)
    if emit_commands:
        for shot in chosen:
            if pending(shot, force=force):
                click.echo(shot.command(force=force))
        return
    if scheduler is not None and jobs is not None:
        raise click.UsageError("--jobs sets the size of the local cluster; it cannot be used with --scheduler")
    quiet = log.getEffectiveLevel() > logging.WARNING

    def say(msg):
        if not quiet:
            click.echo(msg, err=True)

    def on_event(kind, res, c):
        eta = "" if c["eta"] is None else f", ETA {_time.strftime('%H:%M:%S', _time.gmtime(c['eta']))}"
        what = {"done": f"done in {res.get('seconds')} s", "failed": f"FAILED: {res['error']}",
                "retry": f"failed, retrying (attempt {res['attempts'] + 1}): {res['error']}"}[kind]
        say(f"[{c['done'] + c['failed']}/{c['total']}] {res['name']} {what}  "
            f"({c['done']} done, {c['failed']} failed, {c['running']} to go{eta})")

    engine.quiet_dask(logging.INFO if log.isEnabledFor(logging.DEBUG) else logging.ERROR)
    with contextlib.ExitStack() as stack:
        if scheduler is not None:
            client = stack.enter_context(engine.connect(scheduler))
        else:
            import os as _os

            cpus = len(_os.sched_getaffinity(0)) if hasattr(_os, "sched_getaffinity") else (_os.cpu_count() or 1)
            cluster = stack.enter_context(engine.local_cluster(jobs or cpus))
            client = stack.enter_context(cluster.get_client())
        link = engine.dashboard_link(client)
        n_workers = len(client.scheduler_info().get("workers", {}))
        say(f"batch: {len(chosen)} shots on {n_workers} workers ({scheduler or 'local cluster'})"
            + (f", dashboard {link}" if link else ""))
        results = engine.run_batch(client, chosen, retries=retries, force=force, report=report, on_event=on_event)
    earlier = engine.previous_results(plan.output_dir)
    names = {r["name"] for r in results}
    merged = [next(r for r in results if r["name"] == s.name) if s.name in names else earlier[s.name]
              for s in plan.shots if s.name in names or s.name in earlier]

    with guard_writes(roots=[plan.output_dir], inputs=[plan.path], label=f"the batch folder {plan.output_dir}"):
        written = engine.write_summary(plan.output_dir, plan.path, merged)
    click.echo(format_table(results))
    for p in written:
        click.echo(str(p))
    failed = [r["name"] for r in results if r["status"] == "failed"]
    if failed:
        click.echo(f"error: {len(failed)} of {len(results)} shots failed: {', '.join(failed)}", err=True)
        click.get_current_context().exit(1)


def _camera_options(f):
    """--yaw/--pitch/--fov/--distance/--shading, shared by render, preview and report."""
    opts = [setting("render", name) for name in ("yaw", "pitch", "fov", "distance", "shading")]
    for opt in reversed(opts):
        f = opt(f)
    return f


def _camera(yaw, pitch, fov, distance):
    return Camera(yaw=yaw, pitch=pitch, fov=fov, distance=distance)


@main.command()
@click.argument("mesh", metavar="MESH_OR_SEQUENCE")
@output_option(None, "Image (.png, .jpg) for one OBJ; video (.mp4, .avi) for a sequence.")
@setting("render", "size", type=Size(square=True, example="512x512"), default="512", metavar="WxH")
@setting("render", "fps")
@_camera_options
def render(mesh, output, size, fps, yaw, pitch, fov, distance, shading):
    """Render an OBJ (to an image) or an OBJ sequence (a directory or glob, to a video).

    Uses the built-in software rasteriser (no GPU or display needed); the camera
    is framed on the first mesh and stays fixed.
    """

    out = write_render(mesh, output, size=size, fps=fps, camera=_camera(yaw, pitch, fov, distance),
                       shading=shading, progress=progress)
    click.echo(str(out))


@main.command()
@click.argument("run_path", metavar="RUN_DIR_OR_CONFIG", type=click.Path(exists=True))
@output_option("preview.mp4", "Video file.", required=False)
@setting("preview", "frames", metavar="A:B", show_default=False)
@setting("preview", "size")
@setting("preview", "fps")
@setting("preview", "video", type=click.Path(dir_okay=False))
@_camera_options
def preview(run_path, output, frames, size, fps, video, yaw, pitch, fov, distance, shading):
    """Side-by-side video of a run: tracked source | retargeted character | weights.

    RUN_DIR_OR_CONFIG is a config YAML (paths resolved as `retarget run` does) or
    a run's output directory with the default file names.
    """

    run_files = locate_run(run_path, video=video)
    try:
        out = write_preview(run_files, output, frames=frames, height=size, fps=fps,
                            camera=_camera(yaw, pitch, fov, distance), shading=shading, progress=progress)
    except ValueError as exc:
        if str(exc).startswith("--frames"):
            raise click.BadParameter(str(exc)) from None
        raise
    click.echo(str(out))


@main.command()
@click.argument("run_path", metavar="RUN_DIR_OR_CONFIG", type=click.Path(exists=True))
@output_option("report.html", "HTML file (self-contained: images embedded).", required=False)
@setting("report", "video", type=click.Path(dir_okay=False))
@setting("report", "worst")
@setting("report", "truth", type=click.Path(dir_okay=False))
@_camera_options
def report(run_path, output, video, worst, truth, yaw, pitch, fov, distance, shading):
    """One self-contained HTML page about a run: summary, tracking, keys, weights, residuals.

    On a synthetic take, also the mesh error and jitter against the truth.

    Needs matplotlib: pip install 'retarget[report]'.
    """

    run_files = locate_run(run_path, video=video)
    out = write_report(run_files, output, worst=worst, camera=_camera(yaw, pitch, fov, distance), shading=shading,
                       progress=progress, truth=truth)
    click.echo(str(out))


@main.command()
@click.argument("outdir", type=click.Path(file_okay=False))
@setting("synth", "frames")
@setting("synth", "size", type=Size(lo=64, hi=4096), default="320x320", metavar="WxH")
@setting("synth", "seed")
def synth(outdir, frames, size, seed):
    """Write a synthetic performance (video, truth, target rig, config) into OUTDIR."""
    w, h = size

    written = write_take(outdir, n_frames=frames, size=(w, h), seed=seed)
    for p in written.values():
        click.echo(str(p))


if __name__ == "__main__":  # pragma: no cover
    main()
