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
              help="iBUG .pts annotation of the first frame.")
@output_option("landmarks.npz", "Landmarks file.", required=False)
@setting("track", "method")
@setting("track", "window")
@setting("track", "levels")
@setting("track", "fb_threshold")
@setting("track", "anchor")
def track(video, init, output, **settings):
    """Track facial landmarks through VIDEO (Lucas-Kanade with drift correction)."""
    from .stages import run_track

    _print_outputs(run_track(video=video, init=init, output=output, progress=progress, **settings))


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
@setting("decompose", "formulation")
@setting("decompose", "alpha")
@setting("decompose", "upper")
@setting("decompose", "neutral_frame")
@setting("decompose", "confidence")
@setting("decompose", "lost_fraction")
@click.option("--summary/--no-summary", default=True, show_default=True,
              help="Print a per-region table of residual, cardinality, jitter and lost frames after the file names.")
def decompose(landmarks, keys, output, csv, summary, **settings):
    """Decompose every frame into key-shape weights (non-negative by default, eq. 4)."""
    from .io.stagefiles import load_weights
    from .stages import run_decompose

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
