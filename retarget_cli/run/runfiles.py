"""Find a run's files for ``preview`` and ``report``: from a config or a run directory.

A config gives every stage's resolved paths (the same resolution ``retarget
run`` uses). A run directory is searched for the default names. Everything is
optional: a consumer uses what exists, so a run stopped after ``decompose`` or
landmarks from another tracker still get a preview and a report.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

import numpy as np

from ..config import load_config
from ..errors import InputError
from ..io.atomic import load_npz
from ..io.frames import is_sequence, sequence_files
from ..io.obj import FRAME_RE
from .pipeline import ORDER, resolve, stage_params

log = logging.getLogger(__name__)

#: File names looked for in a run directory (the stages' defaults).
DEFAULT_NAMES = {
    "landmarks": ("landmarks.npz",),
    "keys": ("keys.json",),
    "weights": ("weights.npz",),
    "frames": ("frames",),
    "targets": ("targets/targets.yaml", "targets.yaml"),
    "curve": ("select_curve.csv", "curve.csv"),
}

@dataclass
class RunFiles:
    """The files of one run; ``None`` for what does not exist.

    Attributes
    ----------
    root : Path
        The run's output directory.
    config : Path or None
    video, landmarks, keys, weights, targets, curve : Path or None
    frames : Path or None
        Directory of ``frame_*.obj``.
    manifests : dict
        Stage name to its parsed manifest (``.retarget/STAGE.json``), in
        pipeline order.
    """

    root: Path
    config: Path | None = None
    video: Path | None = None
    landmarks: Path | None = None
    keys: Path | None = None
    weights: Path | None = None
    frames: Path | None = None
    targets: Path | None = None
    curve: Path | None = None
    manifests: dict = field(default_factory=dict)

    def frame_files(self) -> list[Path]:
        """``frame_*.obj`` of :attr:`frames` in frame order (empty if none)."""
        if self.frames is None:
            return []
        found = []
        for p in self.frames.iterdir():
            m = FRAME_RE.match(p.name)
            if m:
                found.append((int(m.group(1)), p))
        return [p for _, p in sorted(found)]


def _existing(p) -> Path | None:
    return Path(p) if p is not None and Path(p).exists() else None


def _rebase(known_rel: str, known_abs: Path, rel: str) -> Path | None:
    """Resolve *rel* against the unknown directory *B* that satisfies ``B / known_rel == known_abs``.

    Manifests store paths relative to the config's directory, which a run
    directory alone does not name; one output whose location is known pins
    down as much of it as the other path needs. ``None`` when it cannot.
    """
    kparts = PurePosixPath(known_rel.replace(os.sep, "/")).parts
    up = 0
    while up < len(kparts) and kparts[up] == "..":
        up += 1
    rest = kparts[up:]
    known_abs = Path(os.path.abspath(known_abs))
    if len(rest) == 0 or tuple(known_abs.parts[-len(rest):]) != tuple(rest):
        return None
    anchor = known_abs.parents[len(rest) - 1]  # = B's ancestor `up` levels above B
    if Path(rel).is_absolute():
        return Path(rel)
    parts = PurePosixPath(rel.replace(os.sep, "/")).parts
    up2 = 0
    while up2 < len(parts) and parts[up2] == "..":
        up2 += 1
    if up2 < up:
        return None  # would need the names of directories below the anchor
    base = anchor
    for _ in range(up2 - up):
        base = base.parent
    return base.joinpath(*parts[up2:])


def _read_manifests(root: Path) -> dict:
    out = {}
    mdir = root / ".retarget"
    for name in ORDER + sorted(p.stem for p in mdir.glob("*.json") if p.stem not in ORDER) if mdir.is_dir() else []:
        p = mdir / f"{name}.json"
        if not p.is_file():
            continue
        try:
            man = json.loads(p.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError):
            log.warning("%s: unreadable manifest, ignored", p)
            continue
        if isinstance(man, dict):
            out[name] = man
    return out


def _video_from_manifests(root: Path, manifests: dict, landmarks: Path | None) -> Path | None:
    track = manifests.get("track") or {}
    video = (track.get("settings") or {}).get("video")
    if not isinstance(video, str):
        return None
    base = track.get("base")
    if isinstance(base, str) and _source_exists(Path(base) / video):
        return Path(base) / video
    for rel in (track.get("outputs") or {}):
        known = (root / Path(rel).name) if landmarks is None else landmarks
        if Path(rel).name == known.name:
            cand = _rebase(rel, known, video)
            if cand is not None and _source_exists(cand):
                return cand
    log.warning("%s: the source video the track manifest names (%s) was not found from here; the source panel "
                "is blank: give it with --video", root, video)
    return None


def _source_exists(path: Path) -> bool:
    """Whether *path* is a video file or an image-sequence pattern that matches files."""
    if is_sequence(path):
        try:
            return bool(sequence_files(path))
        except InputError:
            return False
    return path.is_file()


def locate_run(path, *, video=None) -> RunFiles:
    """Find the files of the run at *path* (a config YAML or a run directory).

    Parameters
    ----------
    path : path-like
        ``config.yaml`` (paths resolved as ``retarget run`` does) or the run's
        output directory (default file names; the source video is found
        through the track manifest when it can be).
    video : path-like, optional
        The source video, overriding what the run names.

    Raises
    ------
    InputError
        If *path* does not exist, or the run has neither landmarks nor
        weights nor frames (nothing to show).
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such run directory or config file")
    if path.is_file():
        rf = _from_config(path)
    else:
        rf = RunFiles(root=path)
        for attr, names in DEFAULT_NAMES.items():
            for n in names:
                if (path / n).exists():
                    setattr(rf, attr, path / n)
                    break
        rf.manifests = _read_manifests(path)
        rf.video = _video_from_manifests(path, rf.manifests, rf.landmarks)
    if video is not None:
        if not _source_exists(Path(video)):
            raise InputError(f"{video}: video file or image sequence not found")
        rf.video = Path(video)
    if rf.frames is not None and not rf.frames.is_dir():
        rf.frames = None
    if rf.landmarks is None and rf.weights is None and not rf.frame_files():
        raise InputError(f"{path}: no landmarks.npz, weights.npz or frames/frame_*.obj found; "
                         "expected a run directory or a config whose stages have run")
    return rf


def _from_config(path: Path) -> RunFiles:
    cfg = load_config(path, stage_params())
    kw = {name: resolve(cfg, name) for name in cfg.sections}
    rf = RunFiles(root=cfg.output_dir, config=path)

    def first(*pairs):
        for stage, key in pairs:
            if stage in kw and kw[stage].get(key) is not None:
                found = _existing(kw[stage][key])
                if found is not None:
                    return found
        return None

    rf.video = first(("track", "video"))
    if rf.video is None and "track" in kw and is_sequence(kw["track"]["video"]) \
            and _source_exists(Path(kw["track"]["video"])):
        rf.video = Path(kw["track"]["video"])
    elif rf.video is None and "track" in kw:
        log.warning("%s: track.video (%s) was not found; the source panel is blank: give it with --video", path,
                    kw["track"]["video"])
    rf.landmarks = first(("track", "output"), ("select", "landmarks"), ("decompose", "landmarks"))
    rf.keys = first(("select", "output"), ("decompose", "keys"))
    rf.weights = first(("decompose", "output"), ("apply", "weights"))
    rf.frames = first(("apply", "output"))
    rf.targets = first(("apply", "targets"))
    if rf.targets is None and "pose" in kw and kw["pose"].get("output") is not None:
        rf.targets = _existing(Path(kw["pose"]["output"]) / "targets.yaml")
    # select's evaluation curve, if that stage declares one (e.g. 'evaluate'); else the default name
    rf.curve = first(("select", "evaluate"), ("select", "curve"))
    if rf.curve is None:
        for n in DEFAULT_NAMES["curve"]:
            rf.curve = rf.curve or _existing(cfg.output_dir / n)
    rf.manifests = _read_manifests(cfg.output_dir)
    return rf


# --------------------------------------------------------------------------- lenient readers


def read_run_weights(path) -> tuple[dict, dict, dict]:
    """Read ``weights.npz`` tolerating extra keys from newer writers.

    A region is a 2-D array ``NAME`` that has a matching ``NAME_frames``;
    every other ``NAME_*`` array is a per-region extra (``residual`` today;
    diagnostics such as ``cardinality`` or ``jitter`` when present).

    Returns
    -------
    regions : dict
        Region name to ``(weights (T, K), frames (K,))``, sorted by name.
    extras : dict
        Region name to ``{suffix: array}`` (e.g. ``{"residual": (T,)}``).
    other : dict
        Top-level arrays that belong to no region, plus ``meta`` parsed
        from JSON under the key ``"meta"`` (a dict).
    """
    path = Path(path)
    data = load_npz(path)
    meta = {}
    if "meta" in data:
        try:
            meta = json.loads(str(data.pop("meta")))
        except json.JSONDecodeError:
            meta = {}
    regions = {}
    for name in sorted(data):
        w = data[name]
        fr = data.get(f"{name}_frames")
        if fr is not None and w.ndim == 2 and fr.shape == (w.shape[1],):
            regions[name] = (np.asarray(w, dtype=np.float64), np.asarray(fr, dtype=np.int64))
    if not regions:
        raise InputError(f"{path}: no region weights found (expected 'NAME' (T, K) with 'NAME_frames' (K,))")
    extras = {r: {} for r in regions}
    used = set(regions) | {f"{r}_frames" for r in regions}
    # longest region names first so 'mouth_inner_residual' is not taken as region 'mouth'
    for key in sorted(data):
        if key in used:
            continue
        for r in sorted(regions, key=len, reverse=True):
            if key.startswith(r + "_"):
                extras[r][key[len(r) + 1:]] = data[key]
                used.add(key)
                break
    other = {k: v for k, v in data.items() if k not in used}
    other["meta"] = meta
    return regions, extras, other
