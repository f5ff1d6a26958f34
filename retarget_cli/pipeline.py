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
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from . import __version__, stages
from .config import REQUIRED, Config, Param
from .decompose import FORMULATIONS, SOLVERS
from .errors import ConfigError, InputError
from .io.atomic import sha256_file, write_json

log = logging.getLogger(__name__)


@dataclass
class Stage:
    """A pipeline stage: its parameters and the runner that executes it."""

    name: str
    help: str
    params: list
    runner: Callable
    extra_inputs: Callable = field(default=lambda kw: [])
    uses_progress: bool = False
    uses_seed: bool = False
    uses_base_dir: bool = False

    def param(self, name: str) -> Param:
        return next(p for p in self.params if p.name == name)


def _targets_files(kw) -> list[Path]:
    from .io.stagefiles import read_targets

    return read_targets(kw["targets"]).files()


def _pose_files(kw) -> list[Path]:
    from .io.stagefiles import read_rig

    masks = [Path(kw["base_dir"]) / m for m in (kw.get("masks") or {}).values()]
    return read_rig(kw["rig"]).files() + masks


STAGES: dict[str, Stage] = {
    s.name: s
    for s in [
        Stage(
            "track",
            "Track landmarks through a video from an annotated first frame.",
            [
                Param("video", "input", str, help="Video file (mp4, mov, avi)."),
                Param("init", "input", str, help="iBUG .pts annotation of the first frame."),
                Param("output", "output", str, "landmarks.npz", "Landmarks file (landmarks.npz contract)."),
                Param("method", "setting", str, "lk", "Tracker.", choices=("lk",)),
                Param("window", "setting", int, 21, "Lucas-Kanade window side in pixels (odd).", min=5, max=101),
                Param("levels", "setting", int, 3, "Pyramid levels.", min=0, max=8),
                Param("fb_threshold", "setting", float, 1.0, "Forward-backward error scale in pixels.",
                      min=0.01, max=100),
                Param("anchor", "setting", bool, True, "Correct drift against the annotated frame."),
                Param("rigid_points", "setting", list, None,
                      "Landmarks that define head motion (default: eye corners and nose for 68 points).",
                      nullable=True),
            ],
            stages.run_track,
            uses_progress=True,
        ),
        Stage(
            "select",
            "Choose key frames per region by PCA extremes (Chuang & Bregler §4.2).",
            [
                Param("landmarks", "input", str, help="landmarks.npz.", link="track.output"),
                Param("output", "output", str, "keys.json", "Key frames per region."),
                Param("template", "output", str, "targets.template.yaml",
                      "targets.yaml template for the artist (never overwritten).", nullable=True),
                Param("method", "setting", str, "pca-extremes", "Selection method.", choices=("pca-extremes",)),
                Param("k", "setting", int, 12, "Number of key shapes per region.", min=1, max=1000),
                Param("neutral_frame", "setting", int, 0,
                      "Frame always kept as a key (the actor at rest); null to let the method choose all k.",
                      min=0, nullable=True),
                Param("regions", "setting", dict, None,
                      "Region name to landmark indices or 'all' (default: face: all).", nullable=True),
            ],
            stages.run_select,
            uses_seed=True,
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
                      "Region name to vertex-mask file (needed with several regions).", nullable=True),
            ],
            stages.run_pose,
            extra_inputs=_pose_files,
            uses_base_dir=True,
        ),
        Stage(
            "apply",
            "Drive the target key shapes with the weights; write an OBJ sequence.",
            [
                Param("weights", "input", str, help="weights.npz.", link="decompose.output"),
                Param("targets", "input", str, help="targets.yaml.", link="pose.output/targets.yaml"),
                Param("output", "output", str, "frames", "Directory for frame_00000.obj, ..."),
                Param("head_motion", "setting", str, "none", "Head motion on the character.", choices=("none",)),
            ],
            stages.run_apply,
            extra_inputs=_targets_files,
            uses_progress=True,
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
                kw[p.name] = cfg.base_dir / v
                continue
            if p.link:
                src, _, sub = p.link.partition("/")
                lstage, lparam = src.split(".")
                if lstage in cfg.sections:
                    base = resolve(cfg, lstage)[lparam]
                    kw[p.name] = base / sub if sub else base
                    continue
            if v is REQUIRED:
                hint = f" (or add a '{p.link.split('.')[0]}' section)" if p.link else ""
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
    files = [Path(kw[p.name]) for p in stage.params if p.kind == "input" and kw[p.name] is not None]
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
        man = json.loads(path.read_text())
    except json.JSONDecodeError:
        return False, "manifest unreadable"
    stage = STAGES[name]
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


def run_stage(cfg: Config, name: str, kw: dict, progress=None) -> list[Path]:
    """Run one stage and write its manifest after its outputs."""
    stage = STAGES[name]
    inputs = _inputs(stage, kw)
    call = dict(kw)
    if stage.uses_progress and progress is not None:
        call["progress"] = progress
    outputs = stage.runner(**call)
    man = {
        "stage": name,
        "version": __version__,
        "code": code_fingerprint(),
        "settings": _settings(stage, kw, cfg),
        "inputs": {_rel(p, cfg.base_dir): _record(p) for p in inputs},
        "outputs": {_rel(p, cfg.base_dir): _record(p) for p in outputs},
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


def run_pipeline(cfg: Config, *, force: bool = False, start=None, stop=None, progress=None) -> list[tuple]:
    """Run the config's stages in order, skipping those that are up to date.

    Every stage's arguments are resolved (and so checked) before any runs.

    Returns
    -------
    list of (stage, status, outputs)
        *status* is ``"ran"`` or ``"skipped"``; *outputs* are the stage's
        declared output paths (files or directories).
    """
    names = select_stages(cfg, start, stop)
    resolved = {n: resolve(cfg, n) for n in names}
    report = []
    for n in names:
        kw = resolved[n]
        ok, why = (False, "--force") if force else check_up_to_date(cfg, n, kw)
        declared = [kw[p.name] for p in STAGES[n].params if p.kind == "output" and kw[p.name] is not None]
        if ok:
            log.info("%s: up to date, skipped", n)
            report.append((n, "skipped", declared))
            continue
        log.info("%s: running (%s)", n, why)
        run_stage(cfg, n, kw, progress)
        report.append((n, "ran", declared))
    return report
