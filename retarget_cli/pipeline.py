"""Stage registry and the up-to-date-aware runner behind ``retarget run``.

Each stage declares its inputs, outputs and settings (:class:`~retarget_cli.config.Param`).
After a stage succeeds, a manifest ``<output_dir>/.retarget/<stage>.json``
records its resolved settings, the sha256 of every input and output, and the
version. A later run skips the stage while all of these still match, as make
and DVC do; the manifest is written last, so a run killed midway is rerun.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from . import __version__, stages
from .config import (
    REQUIRED,
    Config,
    Param,
    check_indices,
    check_masks,
    check_regions,
    check_strings,
    check_vector3,
)
from .decompose import FORMULATIONS, SOLVERS
from .errors import ConfigError, InputError, RetargetError
from .io.atomic import guard_writes, remove_stale_parts, sha256_file, write_json

log = logging.getLogger(__name__)


@dataclass
class Stage:
    """A pipeline stage: its parameters and the runner that executes it."""

    name: str
    help: str
    params: list
    runner: Callable
    extra_inputs: Callable = field(default=lambda kw: [])
    #: Maps a declared input (param name, path) to the files it stands for (an image-sequence pattern).
    expand_input: Callable = field(default=lambda name, path: [path])
    uses_progress: bool = False
    uses_seed: bool = False
    uses_base_dir: bool = False
    #: The runner takes ``cache_dir`` (the run's ``<output_dir>/.retarget/cache``, for parsed rigs).
    uses_cache: bool = False

    def param(self, name: str) -> Param:
        return next(p for p in self.params if p.name == name)


def _targets_files(kw) -> list[Path]:
    from .io.stagefiles import read_targets

    return read_targets(kw["targets"]).files()


def _track_files(kw) -> list[Path]:
    return [Path(kw.get("base_dir") or ".") / a for a in (kw.get("annotations") or [])]


from .stages.filtering import FILTER_PARAMS  # noqa: E402  (declared beside the stage code)


def _track_expand(name, path) -> list[Path]:
    from .io.frames import is_sequence, sequence_files

    return sequence_files(path) if name == "video" and is_sequence(path) else [path]


def _pose_files(kw) -> list[Path]:
    from .io.stagefiles import read_rig

    masks = [Path(kw["base_dir"]) / m for m in (kw.get("masks") or {}).values()]
    spec = read_rig(kw["rig"])
    extra = [spec.landmarks] if isinstance(spec.landmarks, Path) else []
    return spec.files() + extra + masks


STAGES: dict[str, Stage] = {
    s.name: s
    for s in [
        Stage(
            "track",
            "Track landmarks through a video from an annotated first frame.",
            [
                Param("video", "input", str,
                      help="Video file (mp4, mov, avi, mkv, m4v) or image-sequence pattern (printf or glob; "
                           "png, jpg, exr)."),
                Param("init", "input", str, None,
                      "Annotation of the first tracked frame: iBUG .pts or frame,point,x,y CSV, or auto (the "
                      "default): the pretrained detector annotates it and writes <output stem>.init_NNNNN.pts "
                      "beside the output (needs the extra detect).", nullable=True, words=("auto",)),
                Param("output", "output", str, "landmarks.npz", "Landmarks file (landmarks.npz contract)."),
                Param("overlay", "output", str, None,
                      "Also write an mp4 with the landmarks (coloured by confidence) and the head frame.",
                      nullable=True),
                Param("annotations", "setting", list, None,
                      "More annotated frames (.pts named like face_00120.pts, or CSV); each re-anchors the track.",
                      nullable=True, validate=check_strings),
                Param("init_frame", "setting", int, None,
                      "Frame of the init .pts when its name ends in no number (default 0).", min=0, nullable=True),
                Param("start", "setting", int, 0, "First frame to track (0-based).", min=0),
                Param("end", "setting", int, None, "Stop before this frame (default: the last).", min=1,
                      nullable=True),
                Param("step", "setting", int, 1, "Track every step-th frame.", min=1, max=1000),
                Param("downscale", "setting", float, 1.0,
                      "Track on frames scaled by this factor (coordinates stay at full resolution).",
                      min=0.05, max=1.0),
                Param("fps", "setting", float, None, "Frame rate of an image sequence (default 30).",
                      min=0.01, nullable=True),
                Param("smooth_head", "setting", int, 0,
                      "Temporal smoothing of the head track: Savitzky-Golay window in frames (0: none).",
                      min=0, max=301),
                Param("keep_partial", "setting", bool, False,
                      "On a truncated video or a lost face, keep what was tracked up to then."),
                Param("method", "setting", str, "auto",
                      "Tracker: detect (dlib's pretrained 68-point detector on every frame joined with optical "
                      "flow; needs the extra detect) or lk (Lucas-Kanade, one or more annotated frames) or "
                      "eigenpoints (the paper's tracker, trained on the annotated frames; give 5 or more) or "
                      "markers (painted dots on the landmarks) or facemark (OpenCV Facemark LBF with --model, see "
                      "train-tracker); auto: detect where the extra is installed, else lk.",
                      choices=("auto", "detect", "lk", "eigenpoints", "markers", "facemark")),
                Param("fuse", "setting", bool, True,
                      "Method detect: join the detections with optical flow (a Kalman filter along the flow and "
                      "a smoother over the take); false keeps each frame's detection as it is."),
                Param("model", "input", str, None,
                      "Facemark LBF model file for method facemark (written by 'retarget train-tracker').",
                      nullable=True),
                Param("window", "setting", int, 21, "Lucas-Kanade window side in pixels (odd).", min=5, max=101),
                Param("levels", "setting", int, 3, "Pyramid levels.", min=0, max=8),
                Param("fb_threshold", "setting", float, 1.0, "Forward-backward error scale in pixels.",
                      min=0.01, max=100),
                Param("anchor", "setting", bool, True, "Correct drift against the annotated frame."),
                Param("rigid_points", "setting", list, None,
                      "Landmarks that define head motion (default: eye corners and nose for 68 points).",
                      nullable=True, validate=check_indices),
                *FILTER_PARAMS,
            ],
            stages.run_track,
            extra_inputs=_track_files,
            expand_input=_track_expand,
            uses_progress=True,
            uses_base_dir=True,
        ),
        Stage(
            "select",
            "Choose key frames per region (Chuang & Bregler §4.2) and evaluate the methods by E (eq. 5).",
            [
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
                Param("neutral_frame", "setting", int, 0,
                      "Frame always kept as a key (the actor at rest); null to let the method choose all k.",
                      min=0, nullable=True),
                Param("regions", "setting", dict, None,
                      "Region name to 'all', landmark indices, null (68-point preset: brows-eyes, mouth, face) "
                      "or {points, k} (default: face: all).", nullable=True, validate=check_regions),
            ],
            stages.run_select,
            uses_seed=True,
            uses_progress=True,
        ),
        Stage(
            "decompose",
            "Non-negative weights over the key shapes for every frame (eq. 4).",
            [
                Param("landmarks", "input", str, help="landmarks.npz.", link="track.output"),
                Param("keys", "input", str, help="keys.json.", link="select.output"),
                Param("output", "output", str, "weights.npz", "Weights per region."),
                Param("csv", "output", str, None, "Also write the weights as CSV.", nullable=True),
                Param("solver", "setting", str, "nnls",
                      "Solver: nnls (eq. 4), ls, bounded, ridge, ridge-clipped, temporal, temporal-causal, sparse, "
                      "sequential.", choices=SOLVERS),
                Param("formulation", "setting", str, "whole",
                      "whole (eq. 3), convex (weights sum to 1) or delta (relative to neutral_frame).",
                      choices=FORMULATIONS),
                Param("alpha", "setting", float, None,
                      "Regularisation of ridge, temporal, temporal-causal, sparse, relative to the keys' spread "
                      "(null: the solver's default).", min=0, nullable=True),
                Param("upper", "setting", float, None,
                      "Upper bound on every weight (bounded and ridge-clipped use 1 when null).", min=1e-6,
                      nullable=True),
                Param("neutral_frame", "setting", int, 0, "Neutral frame S_0 of formulation delta (must be a key).",
                      min=0),
                Param("confidence", "setting", bool, True, "Weight each landmark by its tracking confidence."),
                Param("lost_fraction", "setting", float, 0.5,
                      "A region is lost in a frame when more than this fraction of its landmarks is lost; "
                      "its weights there are interpolated.", min=0, max=1),
                Param("smooth_space", "setting", str, "shape",
                      "What temporal and temporal-causal smooth: shape (the reconstructed landmarks, ||D2 W S||^2; "
                      "alpha is then absolute) or weights (||D2 W||^2).", choices=("shape", "weights")),
                Param("robust", "setting", float, 1.0,
                      "temporal only: release the smoothness penalty around frames whose excess residual (over the "
                      "unsmoothed fit, in units of its median) exceeds this, so blinks keep their amplitude; 0: off.",
                      min=0),
            ],
            stages.run_decompose,
        ),
        Stage(
            "pose",
            "Pose a rig at each key frame's known slider values (automatic target key shapes).",
            [
                Param("keys", "input", str, help="keys.json.", link="select.output"),
                Param("rig", "input", str, help="rig.yaml: neutral OBJ plus named shape OBJs."),
                Param("poses", "input", str, help="NPZ with 'curves' (T, E) and 'names' (E,)."),
                Param("output", "output", str, "targets", "Directory for the key OBJs and targets.yaml."),
                Param("masks", "setting", dict, None,
                      "Region name to vertex-mask file (needed with several regions).", nullable=True,
                      validate=check_masks),
            ],
            stages.run_pose,
            extra_inputs=_pose_files,
            uses_base_dir=True,
            uses_cache=True,
        ),
        Stage(
            "auto_pose",
            "Pose a rig at each key frame from its landmarks (the rig as the artist): key OBJs, their sliders, "
            "region masks and a targets.yaml from which apply writes the rig's slider curves.",
            [
                Param("keys", "input", str, help="keys.json.", link="select.output"),
                Param("landmarks", "input", str, help="landmarks.npz.", link="track.output"),
                Param("rig", "input", str, help="rig.yaml: neutral OBJ plus named shape OBJs (and 'landmarks:')."),
                Param("landmark_vertices", "input", str, None,
                      "Rig vertex of each landmark (one id per line, or 'landmark vertex' pairs); default the "
                      "rig.yaml's 'landmarks:' list.", nullable=True),
                Param("output", "output", str, "targets",
                      "Directory for the key OBJs, sliders.csv, masks/ and targets.yaml."),
                Param("fit", "setting", str, "delta",
                      "delta: the key frame's landmark displacement from neutral_frame (the actor's face shape "
                      "stays out of the sliders); absolute: the landmark positions (Lewis & Anjyo eq. 3).",
                      choices=("delta", "absolute")),
                Param("neutral_frame", "setting", int, 0, "The actor's neutral frame (the rig's rest pose).", min=0),
                Param("sparsity", "setting", float, None,
                      "L1 weight keeping unneeded sliders at 0, relative to the sliders' mean landmark energy "
                      "(null: 0.01).", min=0, nullable=True),
                Param("ridge", "setting", float, None, "Ridge weight, relative likewise (null: 0.001).",
                      min=0, nullable=True),
                Param("exclude", "setting", list, ["eyeLook*", "*pupil*"],
                      "Slider-name patterns (fnmatch, any case) kept at 0: by default gaze and pupils, which "
                      "landmarks without pupils cannot see.", validate=check_strings),
                Param("skip_points", "setting", list, None,
                      "Landmarks left out of the fit (default for 68 points: the jaw contour but the chin).",
                      nullable=True, validate=check_indices),
                Param("rigid_points", "setting", list, None,
                      "Landmarks that give each key frame's head pose (default for 68 points: nose and eye "
                      "corners).", nullable=True, validate=check_indices),
                Param("masks", "setting", dict, None,
                      "Region name to vertex-mask file, overriding the masks derived from the rig.", nullable=True,
                      validate=check_masks),
                Param("alpha", "setting", float, 0.001, "absolute fit: eq. 3's alpha.", min=0),
                Param("mu", "setting", float, 0.0001, "absolute fit: eq. 3's mu.", min=0),
            ],
            stages.run_auto_pose,
            extra_inputs=_pose_files,
            uses_base_dir=True,
            uses_cache=True,
        ),
        Stage(
            "apply",
            "Drive the target key shapes with the weights; write an OBJ sequence and other exports.",
            [
                Param("weights", "input", str, help="weights.npz.", link="decompose.output"),
                Param("targets", "input", str, help="targets.yaml.",
                      link="auto_pose.output/targets.yaml|pose.output/targets.yaml"),
                Param("landmarks", "input", str, None, "landmarks.npz, for its head motion (head_motion: 2d).",
                      nullable=True, link="track.output"),
                Param("output", "output", str, "frames",
                      "Directory for frame_00000.obj, ..., weights.csv, animation.exr/.json, animation.glb."),
                Param("formats", "setting", list, ["obj"],
                      "Exports: any of obj, csv, exr, glb, curves (the rig's slider curves: curves.csv, curves.npz; "
                      "needs keys posed on a rig), livelink (Live Link Face CSV; needs a rig), usd (animation.usd; "
                      "needs usd-core).", choices=("obj", "csv", "exr", "glb", "curves", "livelink", "usd")),
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
                Param("vat", "setting", str, "offsets", "EXR texture holds offsets from the neutral or positions.",
                      choices=("offsets", "positions")),
            ],
            stages.run_apply,
            extra_inputs=_targets_files,
            uses_progress=True,
            uses_cache=True,
        ),
    ]
}

ORDER = list(STAGES)


def code_fingerprint() -> str:
    """sha256 over the package's source files: a code change reruns every stage."""
    import hashlib

    h = hashlib.sha256(__version__.encode())
    root = Path(__file__).parent
    for f in sorted(root.rglob("*.py")):
        h.update(f.relative_to(root).as_posix().encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def stage_params() -> dict[str, list[Param]]:
    """Stage name to its parameter list (for :func:`retarget_cli.config.load_config`)."""
    return {name: s.params for name, s in STAGES.items()}


def _rel(path: Path, base: Path) -> str:
    return os.path.relpath(path, base)


def resolve(cfg: Config, name: str) -> dict:
    """Keyword arguments for a stage's runner: paths made absolute, defaults and links filled.

    Raises
    ------
    ConfigError
        If a required key is missing and no earlier stage provides it.
    """
    stage = STAGES[name]
    given = cfg.sections.get(name, {})
    kw = {}
    for p in stage.params:
        v = given.get(p.name, p.default)
        if p.kind == "input":
            if p.name in given and v is not None:
                kw[p.name] = v if v in p.words else cfg.base_dir / v
                continue
            linked = False
            for link in (p.link or "").split("|") if p.link else ():
                src, _, sub = link.partition("/")
                lstage, lparam = src.split(".")
                if lstage in cfg.sections:
                    base = resolve(cfg, lstage)[lparam]
                    kw[p.name] = base / sub if sub else base
                    linked = True
                    break
            if linked:
                continue
            if v is REQUIRED:
                sections = " or ".join(f"'{link.split('.')[0]}'" for link in p.link.split("|")) if p.link else ""
                hint = f" (or add a {sections} section)" if p.link else ""
                raise ConfigError(f"{cfg.path}: {name}.{p.name} is required{hint}")
            kw[p.name] = None
        elif p.kind == "output":
            kw[p.name] = None if v is None else cfg.output_dir / v
        else:
            kw[p.name] = None if v is REQUIRED else v
    if stage.uses_seed:
        kw["seed"] = cfg.seed
    if stage.uses_base_dir:
        kw["base_dir"] = cfg.base_dir
    return kw


def _record(path: Path) -> dict:
    st = path.stat()
    return {"sha256": sha256_file(path), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def _matches(path: Path, rec: dict) -> bool:
    try:
        st = path.stat()
    except FileNotFoundError:
        return False
    if st.st_size != rec.get("size"):
        return False
    if st.st_mtime_ns == rec.get("mtime_ns"):
        return True
    return sha256_file(path) == rec.get("sha256")


def _inputs(stage: Stage, kw: dict) -> list[Path]:
    files = [f for p in stage.params if p.kind == "input" and kw[p.name] is not None and kw[p.name] not in p.words
             for f in stage.expand_input(p.name, Path(kw[p.name]))]
    for f in files:
        if not f.exists():
            raise InputError(f"{f}: input of stage '{stage.name}' not found")
    return files + [Path(f) for f in stage.extra_inputs(kw)]


def _settings(stage: Stage, kw: dict, cfg: Config) -> dict:
    out = {}
    for k, v in kw.items():
        out[k] = _rel(v, cfg.base_dir) if isinstance(v, Path) else v
    return out


def manifest_path(cfg: Config, name: str) -> Path:
    return cfg.output_dir / ".retarget" / f"{name}.json"


def check_up_to_date(cfg: Config, name: str, kw: dict) -> tuple[bool, str]:
    """Whether stage *name*'s manifest still matches; returns (ok, reason)."""
    path = manifest_path(cfg, name)
    if not path.is_file():
        return False, "never run"
    try:
        man = json.loads(path.read_text(encoding="utf-8"))
    except ValueError:  # invalid JSON or not UTF-8
        return False, "manifest unreadable"
    stage = STAGES[name]
    if not isinstance(man, dict):
        return False, "manifest unreadable"
    if man.get("version") != __version__ or man.get("code") != code_fingerprint():
        return False, "retarget version or code changed"
    if man.get("settings") != _settings(stage, kw, cfg):
        return False, "settings changed"
    inputs = _inputs(stage, kw)
    if sorted(man.get("inputs", {})) != sorted(_rel(p, cfg.base_dir) for p in inputs):
        return False, "input files changed"
    for p in inputs:
        if not _matches(p, man["inputs"][_rel(p, cfg.base_dir)]):
            return False, f"{_rel(p, cfg.base_dir)} changed"
    for rel, rec in man.get("outputs", {}).items():
        if not _matches(cfg.base_dir / rel, rec):
            return False, f"output {rel} missing or modified"
    return True, "up to date"


def cache_dir(cfg: Config) -> Path:
    """Where a run keeps parsed rigs (:mod:`retarget_cli.io.rigcache`): ``<output_dir>/.retarget/cache``."""
    return cfg.output_dir / ".retarget" / "cache"


def run_stage(cfg: Config, name: str, kw: dict, progress=None, cache: bool = True) -> list[Path]:
    """Run one stage and write its manifest after its outputs.

    The manifest also records the stage's wall-clock run time (``seconds``,
    for reports; not part of the up-to-date check). Stages that load a rig
    get :func:`cache_dir` unless *cache* is False (the cache is not a setting
    and not an output).
    """
    stage = STAGES[name]
    inputs = _inputs(stage, kw)
    call = dict(kw)
    if stage.uses_progress and progress is not None:
        call["progress"] = progress
    if stage.uses_cache:
        call["cache_dir"] = cache_dir(cfg) if cache else None
    t0 = time.perf_counter()
    outputs = stage.runner(**call)
    seconds = round(time.perf_counter() - t0, 3)
    man = {
        "stage": name,
        "version": __version__,
        "code": code_fingerprint(),
        "settings": _settings(stage, kw, cfg),
        "inputs": {_rel(p, cfg.base_dir): _record(p) for p in inputs},
        "outputs": {_rel(p, cfg.base_dir): _record(p) for p in outputs},
        "seconds": seconds,
    }
    write_json(manifest_path(cfg, name), man)
    return outputs


def select_stages(cfg: Config, start: str | None = None, stop: str | None = None) -> list[str]:
    """Stages present in *cfg*, in pipeline order, restricted to ``start..stop``."""
    names = [n for n in ORDER if n in cfg.sections]
    if not names:
        raise ConfigError(f"{cfg.path}: no stage sections; expected some of {', '.join(ORDER)}")
    for label, s in (("--from", start), ("--until", stop)):
        if s is not None and s not in names:
            raise ConfigError(f"{label} {s}: not a stage of {cfg.path} (stages: {', '.join(names)})")
    i = names.index(start) if start else 0
    j = names.index(stop) + 1 if stop else len(names)
    if i >= j:
        raise ConfigError(f"--from {start} comes after --until {stop}")
    return names[i:j]


def run_pipeline(cfg: Config, *, force: bool = False, start=None, stop=None, progress=None,
                 cache: bool = True) -> list[tuple]:
    """Run the config's stages in order, skipping those that are up to date.

    Every stage's arguments are resolved (and so checked) before any runs.
    *cache* False: stages that load a rig parse its OBJs instead of using
    :func:`cache_dir`.

    Returns
    -------
    list of (stage, status, outputs)
        *status* is ``"ran"`` or ``"skipped"``; *outputs* are the stage's
        declared output paths (files or directories).
    """
    names = select_stages(cfg, start, stop)
    resolved = {n: resolve(cfg, n) for n in names}
    everything = dict(resolved)
    for n in ORDER:
        if n in cfg.sections and n not in everything:
            try:
                everything[n] = resolve(cfg, n)
            except ConfigError:
                pass
    inputs = check_outputs(cfg, everything)
    report = []
    with guard_writes(roots=[cfg.output_dir], inputs=inputs, label=f"output_dir of {cfg.path}"):
        remove_stale_parts(cfg.output_dir)
        for n in names:
            kw = resolved[n]
            ok, why = (False, "--force") if force else check_up_to_date(cfg, n, kw)
            declared = [kw[p.name] for p in STAGES[n].params if p.kind == "output" and kw[p.name] is not None]
            if ok:
                log.info("%s: up to date, skipped", n)
                report.append((n, "skipped", declared))
                continue
            log.info("%s: running (%s)", n, why)
            run_stage(cfg, n, kw, progress, cache=cache)
            report.append((n, "ran", declared))
    return report


def _inside(path: Path, folders) -> bool:
    return any(path == f or path.is_relative_to(f) for f in folders)


def run_inputs(cfg: Config, resolved: dict) -> list[Path]:
    """Every file the user gives the run (all stages'), resolved: no stage may write or delete one.

    Inputs a stage takes from an earlier stage's output are not among them;
    files a stage's input references (a rig's OBJs, a targets.yaml's keys)
    are, unless they lie inside a declared output (key OBJs a run posed).
    """
    outs = [Path(kw[p.name]).resolve() for n, kw in resolved.items() for p in STAGES[n].params
            if p.kind == "output" and kw.get(p.name) is not None]
    files = [cfg.path.resolve()]
    for n, kw in resolved.items():
        stage, given = STAGES[n], cfg.sections.get(n, {})
        for p in stage.params:
            v = kw.get(p.name)
            if p.kind != "input" or p.name not in given or v is None or v in p.words:
                continue
            try:
                files += [Path(f).resolve() for f in stage.expand_input(p.name, Path(v))]
            except (RetargetError, OSError, ValueError):
                files.append(Path(v).resolve())
        try:
            extra = [Path(f).resolve() for f in stage.extra_inputs(kw)]
        except (RetargetError, OSError, ValueError, KeyError, TypeError):
            extra = []  # the stage reports an unreadable input itself
        files += [f for f in extra if not _inside(f, outs)]
    return list(dict.fromkeys(files))


def check_outputs(cfg: Config, resolved: dict) -> list[Path]:
    """Check every declared output before any stage runs: inside ``output_dir``, not an input of the run.

    Returns
    -------
    list of Path
        The run's inputs (:func:`run_inputs`), for the write guard.

    Raises
    ------
    ConfigError
        Naming the config key of the output.
    """
    inputs = run_inputs(cfg, resolved)
    protected = set(inputs)
    root = cfg.output_dir.resolve()
    for n, kw in resolved.items():
        given = cfg.sections.get(n, {})
        for p in STAGES[n].params:
            if p.kind != "output" or kw.get(p.name) is None:
                continue
            out = Path(kw[p.name]).resolve()
            value = given.get(p.name, p.default)
            if not _inside(out, [root]):
                raise ConfigError(f"{cfg.path}: {n}.{p.name}: {value!r} lies outside output_dir ({root}); "
                                  "outputs are paths inside output_dir")
            if out in protected:
                raise ConfigError(f"{cfg.path}: {n}.{p.name}: {value!r} is an input of this run; "
                                  "choose another output name")
    return inputs
