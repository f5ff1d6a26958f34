"""Command-line interface: one command per stage plus ``run`` and ``synth``.

This module only parses arguments and reports; the work happens in
:mod:`retarget_cli.stages`, :mod:`retarget_cli.pipeline` and the stage
modules. Heavy libraries (OpenCV, scikit-learn) are imported inside commands so
that ``retarget --help`` stays instant.
"""

from __future__ import annotations

import contextlib
import logging
import sys

import click

from . import __version__
from .config import Param
from .errors import RetargetError

log = logging.getLogger("retarget_cli")

_TYPES = {int: click.INT, float: click.FLOAT, str: click.STRING}


def _param(stage: str, name: str) -> Param:
    from .pipeline import STAGES

    return STAGES[stage].param(name)


def setting(stage: str, name: str, *decls, **extra):
    """A click option built from the stage's declared :class:`Param` (one source of truth)."""
    p = _param(stage, name)
    flag = "--" + p.name.replace("_", "-")
    kw = dict(help=p.help, show_default=True)
    if p.type is bool:
        decls = decls or (f"{flag}/--no-{flag[2:]}",)
        kw.update(default=p.default, is_flag=True)
    else:
        decls = decls or (flag,)
        if p.choices:
            kw["type"] = click.Choice(p.choices)
        elif p.type in (int, float) and (p.min is not None or p.max is not None):
            kw["type"] = (click.IntRange if p.type is int else click.FloatRange)(p.min, p.max)
        else:
            kw["type"] = _TYPES.get(p.type, click.STRING)
        kw["default"] = p.default
    kw.update(extra)
    return click.option(*decls, name, **kw)


def output_option(default=None, help="Output file.", required=True):
    return click.option("-o", "--output", type=click.Path(dir_okay=True), required=required, default=default,
                        help=help, show_default=default is not None)


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


class RetargetGroup(click.Group):
    """Turns library errors into one-line messages with exit status 1."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except (RetargetError, ValueError, OSError) as exc:
            if isinstance(exc, OSError) and not getattr(exc, "filename", None):
                raise
            msg = str(exc)
            if isinstance(exc, OSError):
                msg = f"{exc.filename}: {exc.strerror}"
            click.echo(f"error: {msg}", err=True)
            ctx.exit(1)


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


def _print_outputs(paths):
    for p in paths:
        click.echo(str(p))


@main.command()
@click.argument("video", type=click.Path(dir_okay=False))
@click.option("--init", "init", type=click.Path(dir_okay=False), required=True,
              help="Annotation of the first tracked frame: iBUG .pts (frame from a name like face_00120.pts) "
                   "or a frame,point,x,y CSV.")
@click.option("--annotation", "annotations", multiple=True, type=click.Path(dir_okay=False),
              help="More annotated frames (.pts or CSV); each re-anchors the track. Repeatable.")
@setting("track", "init_frame")
@output_option("landmarks.npz", "Landmarks file.", required=False)
@click.option("--overlay", type=click.Path(dir_okay=False), default=None,
              help="Also write an mp4 with the landmarks (green = confident, red = lost) and the head frame.")
@setting("track", "method")
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
@click.option("--rigid-points", default=None, metavar="SPEC",
              help="Landmarks that define head motion, e.g. 27-31,33,35,36,39,42,45 (default: eye corners "
                   "and nose for 68 points, else all).")
@setting("track", "keep_partial")
def track(video, init, annotations, output, rigid_points, **settings):
    """Track facial landmarks through VIDEO (a video file or an image-sequence pattern such as
    'frames/%05d.png' or 'frames/*.exr'), from one or more annotated frames."""
    from .stages import run_track

    rigid = None
    if rigid_points:
        rigid = _parse_regions([f"r={rigid_points}"])["r"]
        if rigid == "all":
            raise click.BadParameter("expected indices such as 27-31,36,39", param_hint="--rigid-points")
    _print_outputs(run_track(video=video, init=init, annotations=list(annotations), output=output,
                             rigid_points=rigid, progress=progress, **settings))


@main.command("import")
@click.argument("source", type=click.Path())
@output_option("landmarks.npz", "Landmarks file (landmarks.npz contract).", required=False)
@click.option("--fps", type=click.FloatRange(min=0.01, min_open=False), default=None,
              help="Frame rate (default: the source's, else 30).")
@click.option("--frame-size", default=None, metavar="WxH", help="Frame size of the source video, e.g. 1920x1080.")
@click.option("--rigid-points", default=None, metavar="SPEC", help="Landmarks that define head motion.")
@click.option("--smooth-head", type=click.IntRange(0, 301), default=0, show_default=True,
              help="Temporal smoothing of the head track (Savitzky-Golay window in frames).")
def import_(source, output, fps, frame_size, rigid_points, smooth_head):
    """Bring landmarks from another tool into landmarks.npz, with head motion and stabilization.

    SOURCE is a frame,point,x,y CSV, an NPZ with 'points' (T, L, 2) or a folder of .pts files (frame number
    from each name, e.g. face_00120.pts)."""
    from .stages import run_import

    rigid = None
    if rigid_points:
        rigid = _parse_regions([f"r={rigid_points}"])["r"]
    size = None
    if frame_size:
        try:
            size = tuple(int(v) for v in frame_size.lower().split("x"))
            assert len(size) == 2
        except (ValueError, AssertionError):
            raise click.BadParameter(f"expected WxH, got {frame_size!r}", param_hint="--frame-size") from None
    _print_outputs(run_import(source=source, output=output, fps=fps, frame_size=size, rigid_points=rigid,
                              smooth_head=smooth_head))


@main.command()
@click.argument("landmarks", type=click.Path(dir_okay=False))
@output_option("keys.json", "Key frames per region (keys.json).", required=False)
@click.option("-k", "k", type=click.IntRange(1, 1000), default=_param("select", "k").default, show_default=True,
              help=_param("select", "k").help)
@setting("select", "method")
@click.option("--neutral-frame", type=click.IntRange(0), default=_param("select", "neutral_frame").default,
              show_default=True, help=_param("select", "neutral_frame").help)
@click.option("--no-neutral", is_flag=True, help="Let the method choose all k keys.")
@click.option("--region", "regions", multiple=True, metavar="NAME=SPEC",
              help="A region and its landmarks, e.g. mouth=48-67,3-13 or face=all. Repeatable; default face=all.")
@click.option("--template", type=click.Path(dir_okay=False), default=None,
              help="Also write a targets.yaml template for the artist (never overwrites a file select did not write).")
@click.option("--seed", type=click.IntRange(0), default=0, show_default=True, help="Random seed.")
def select(landmarks, output, k, method, neutral_frame, no_neutral, regions, template, seed):
    """Choose key frames from LANDMARKS (PCA extremes, Chuang & Bregler §4.2)."""
    from .stages import run_select

    _print_outputs(run_select(landmarks=landmarks, output=output, template=template, method=method, k=k,
                              regions=_parse_regions(regions), neutral_frame=None if no_neutral else neutral_frame,
                              seed=seed))


def _parse_regions(specs) -> dict | None:
    """``NAME=all`` or ``NAME=a-b,c,...`` (inclusive ranges) to ``{name: "all" | [ids]}``."""
    if not specs:
        return None
    out = {}
    for spec in specs:
        name, sep, body = spec.partition("=")
        try:
            if not sep or not name:
                raise ValueError
            if body == "all":
                out[name] = "all"
                continue
            ids = []
            for part in body.split(","):
                lo, _, hi = part.partition("-")
                ids += list(range(int(lo), int(hi or lo) + 1))
            out[name] = ids
        except ValueError:
            raise click.BadParameter(f"expected NAME=all or NAME=a-b,c,..., got {spec!r}", param_hint="--region") from None
    return out


@main.command()
@click.argument("landmarks", type=click.Path(dir_okay=False))
@click.argument("keys", type=click.Path(dir_okay=False))
@output_option("weights.npz", "Weights file (weights.npz).", required=False)
@click.option("--csv", type=click.Path(dir_okay=False), default=None, help="Also write the weights as CSV.")
@setting("decompose", "solver")
def decompose(landmarks, keys, output, csv, solver):
    """Decompose every frame into non-negative key-shape weights (eq. 4)."""
    from .stages import run_decompose

    _print_outputs(run_decompose(landmarks=landmarks, keys=keys, output=output, csv=csv, solver=solver))


@main.command("pose-keys")
@click.argument("keys", type=click.Path(dir_okay=False))
@click.argument("rig", type=click.Path(dir_okay=False))
@click.option("--poses", type=click.Path(dir_okay=False), required=True,
              help="NPZ with per-frame slider values: 'curves' (T, E) and 'names' (E,).")
@click.option("--mask", "masks", multiple=True, metavar="REGION=FILE",
              help="Vertex mask of a region (needed with several regions). Repeatable.")
@output_option("targets", "Directory for the key OBJs and targets.yaml.", required=False)
def pose_keys(keys, rig, poses, masks, output):
    """Pose RIG at every key frame's known slider values (automatic target keys)."""
    from .stages import run_pose

    parsed = {}
    for m in masks:
        region, sep, path = m.partition("=")
        if not sep or not region or not path:
            raise click.BadParameter(f"expected REGION=FILE, got {m!r}", param_hint="--mask")
        parsed[region] = path
    _print_outputs(run_pose(keys=keys, rig=rig, poses=poses, output=output, masks=parsed))


@main.command()
@click.argument("weights", type=click.Path(dir_okay=False))
@click.argument("targets", type=click.Path(dir_okay=False))
@output_option("frames", "Directory for the OBJ sequence.", required=False)
@setting("apply", "head_motion")
def apply(weights, targets, output, head_motion):
    """Drive the target key shapes in TARGETS with WEIGHTS; write an OBJ sequence."""
    from .stages import run_apply

    written = run_apply(weights=weights, targets=targets, output=output, head_motion=head_motion, progress=progress)
    click.echo(f"{output} ({len(written)} frames)")


@main.command()
@click.argument("config", type=click.Path(dir_okay=False))
@click.option("--force", is_flag=True, help="Rerun every selected stage even if it is up to date.")
@click.option("--from", "start", metavar="STAGE", help="First stage to consider.")
@click.option("--until", "stop", metavar="STAGE", help="Last stage to consider.")
@click.option("--set", "overrides", multiple=True, metavar="STAGE.KEY=VALUE",
              help="Override a config value (YAML syntax), e.g. --set select.k=8. Repeatable.")
def run(config, force, start, stop, overrides):
    """Run the pipeline described by CONFIG, skipping stages that are up to date."""
    from .config import load_config
    from .pipeline import run_pipeline, stage_params

    cfg = load_config(config, stage_params(), overrides)
    for name, status, outs in run_pipeline(cfg, force=force, start=start, stop=stop, progress=progress):
        if log.getEffectiveLevel() <= logging.WARNING:
            click.echo(f"{name}: {status}", err=True)
        for p in outs:
            click.echo(f"{name}\t{p}")


@main.command()
@click.argument("outdir", type=click.Path(file_okay=False))
@click.option("--frames", type=click.IntRange(2, 100000), default=240, show_default=True, help="Number of frames.")
@click.option("--size", default="320x320", show_default=True, help="Frame size WxH in pixels.")
@click.option("--seed", type=click.IntRange(0), default=0, show_default=True, help="Random seed.")
def synth(outdir, frames, size, seed):
    """Write a synthetic performance (video, truth, target rig, config) into OUTDIR."""
    try:
        w, h = (int(v) for v in size.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"expected WxH such as 320x320, got {size!r}", param_hint="--size") from None
    if not (64 <= w <= 4096 and 64 <= h <= 4096):
        raise click.BadParameter(f"width and height must lie in [64, 4096], got {size}", param_hint="--size")
    from .synth import write_take

    written = write_take(outdir, n_frames=frames, size=(w, h), seed=seed)
    for p in written.values():
        click.echo(str(p))


if __name__ == "__main__":  # pragma: no cover
    main()
