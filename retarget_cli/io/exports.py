"""``apply``'s exports: the :data:`EXPORTS` registry and one exporter per format.

``apply`` (:mod:`retarget_cli.stages.apply`) computes the character's frames
and hands them to every exporter the user asked for (``--format``):

1. :meth:`Exporter.check` runs before any mesh is computed (a missing
   optional package, a format that needs a rig), and
   :meth:`Exporter.check_context` once the rig is read, before any frame
   is computed (a format that needs a certain kind of rig);
2. :meth:`Exporter.add` receives the frames chunk by chunk, head motion
   applied (only exporters with ``streams = True``);
3. :meth:`Exporter.finish` writes the files and returns them.

Adding an export is one new exporter class (here or in a module of its own)
and one entry in :data:`EXPORTS`; the ``--format`` choices and help and
docs/config.md are made from the registry (docs/howto-add-export.md).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..methods.gaze_rig import rest_gaze
from ..methods.neutral import find_rest_frame
from .atomic import check_not_input, write_text
from .editfiles import write_animation
from .exr import write_vat
from .gltf import write_glb
from .gltf_animation import copy_groups, is_vrm, write_animated_copy, write_vrma
from .landmarks import load_landmarks
from .livelink import eye_rotation_from_gaze, head_rotation_from_pose, head_rotation_from_similarity, livelink_csv
from .obj import obj_frame_name, read_obj, write_obj
from .objsurface import obj_surface
from .rig.gltf import read_gltf_rig
from .rig.inverse import parse_correctives
from .rig.usd import USD_EXTS
from .stagefiles import weights_csv
from .usd import require_pxr, write_usd_points, write_usd_skel
from .usd_animation import copy_name, target_weights, write_animated_usd

log = logging.getLogger(__name__)


@dataclass
class ExportContext:
    """What every exporter may read about the animation being exported.

    Attributes
    ----------
    out : Path
        The output folder; exporters write only inside it.
    fps : float
    n_frames, n_vertices : int
        T and N.
    template : ObjMesh
        Faces, texture coordinates and materials of the character.
    base : ndarray, shape (N, 3)
        The rest mesh (the neutral).
    positions : callable
        ``positions(slice)`` -> (t, N, 3) meshes without head motion.
    head : ndarray, shape (T, 3, 4) or None
        Head motion, applied to the frames :meth:`Exporter.add` receives.
    regions : dict
        Region name to ``(W (T, K), key frames, residuals)``, as ``weights.npz`` holds them.
    weights, targets, landmarks : Path or None
        The input files (for metadata and the head rotation of Live Link).
    rig : BlendshapeRig or None
        The rig driven, when ``apply`` drives one.
    rig_file : Path or None
        Its ``rig.yaml``.
    curves : ndarray, shape (T, n) or None
        The rig's slider values per frame.
    morph_targets : callable
        ``morph_targets()`` -> (shapes (M, N, 3), names, weights (T, M)) for blendshape formats.
    settings : dict
        ``apply``'s settings (``vat``, ...).
    ledger : TrackedOutputs
        The folder's output manifest (an exporter of many files plans them there).
    frames : ndarray, shape (T,), int64, optional
        Each frame's source frame number (``weights.npz`` ``frame``); default 0 … T−1.
    times : ndarray, shape (T,), float64, optional
        Each frame's time in seconds in the source (``weights.npz`` ``time``); default ``frames / fps``.
    source_fps : float, optional
        The source's own frame rate (frame numbers over it are times); default *fps*.
    found : ndarray, shape (T,), bool, or None
        Whether the face was found in each frame (``landmarks.npz``'s ``found``); None: every frame.
    root_transforms : ndarray, shape (T, 3, 4), or None
        The glTF node's and the USD root's transform with the 3D head rotation
        (:func:`~retarget_cli.methods.blending.head_rotation_transforms`); the streamed meshes get *head* only.
    head_pose : ndarray, shape (T, 6), or None
        The head's 3D pose per frame: yaw, pitch, roll in degrees and the translation (``landmarks.npz``'s
        ``head_angles`` and ``head_translation``); None without them or with ``apply.head_rotation: false``.
    gaps : str
        ``apply.gaps``: ``omit`` leaves the frames of a gap out of the exports that can (curves.csv,
        livelink.csv, the glTF's keys, the USD's time samples); the curves already hold the behaviour's
        values (:func:`retarget_cli.methods.gaps.fill_gaps`).
    """

    out: Path
    fps: float
    n_frames: int
    n_vertices: int
    template: Any
    base: np.ndarray
    positions: Callable
    head: np.ndarray | None
    regions: dict
    weights: Path
    targets: Path
    landmarks: Path | None
    rig: Any
    rig_file: Path | None
    curves: np.ndarray | None
    morph_targets: Callable
    settings: dict
    ledger: Any
    frames: np.ndarray | None = None
    times: np.ndarray | None = None
    source_fps: float | None = None
    found: np.ndarray | None = None
    gaps: str = "ease"
    head_pose: np.ndarray | None = None
    root_transforms: np.ndarray | None = None

    @property
    def node_transforms(self) -> np.ndarray | None:
        """(T, 3, 4) transform of the glTF node and the USD root: *root_transforms* (the 3D head rotation,
        with the 2D head motion when asked), else *head*."""
        return self.head if self.root_transforms is None else self.root_transforms

    def written_rows(self) -> np.ndarray:
        """Rows the row-per-frame exports write (T,) bool: all but the gaps' with ``gaps: omit``."""
        if self.found is None or self.gaps != "omit":
            return np.ones(self.n_frames, bool)
        return np.asarray(self.found, bool)

    def timing(self) -> tuple[np.ndarray, np.ndarray, float]:
        """Source frame numbers (T,), their times in seconds (T,) and the source's rate, defaults filled."""
        return timing(self)


def timing(ctx) -> tuple[np.ndarray, np.ndarray, float]:
    """:meth:`ExportContext.timing` of *ctx*, or of any object with ``fps`` and ``n_frames`` or ``curves``
    (rows 0 … T−1)."""
    rate = float(getattr(ctx, "source_fps", None) or ctx.fps)
    frames = getattr(ctx, "frames", None)
    if frames is None:
        n = getattr(ctx, "n_frames", None)
        frames = np.arange(len(ctx.curves) if n is None else n, dtype=np.int64)
    frames = np.asarray(frames)
    times = getattr(ctx, "times", None)
    times = frames / rate if times is None else np.asarray(times, dtype=np.float64)
    return frames, times, rate


class Exporter:
    """One export format. Subclasses set the class attributes and override what they need.

    Attributes
    ----------
    help : str
        Its files and what they hold, for ``--format``'s help.
    files : tuple of str
        Names of the files it writes in the output folder (checked against the inputs first).
    needs_rig : bool
        Needs ``apply`` to drive a rig (keys posed by ``auto-pose``).
    streams : bool
        Receives the frames through :meth:`add`.
    """

    help = ""
    files: tuple[str, ...] = ()
    needs_rig = False
    streams = False

    def __init__(self, ctx: ExportContext):
        self.ctx = ctx

    @classmethod
    def check(cls) -> None:
        """Raise before any work when this format cannot be written here (e.g. a missing package)."""

    @classmethod
    def check_context(cls, ctx: ExportContext) -> None:
        """Raise before any frame is computed when this format cannot export *ctx* (e.g. the kind of rig)."""

    def add(self, start: int, frames: np.ndarray) -> None:
        """Frames ``start .. start + len(frames)`` (t, N, 3), head motion applied."""

    def finish(self) -> list[Path]:
        """Write the files; return their paths."""
        return []


class ObjExport(Exporter):
    """``frame_%05d.obj``, one per frame, named by its source frame number (``frame_00100.obj`` for source frame
    100 of a take tracked from ``start: 100``; row ``t`` of the weights is ``frame_<frames[t]>.obj``)."""

    help = "frame_%05d.obj (by source frame number)"
    streams = True

    def __init__(self, ctx):
        super().__init__(ctx)
        self.numbers = timing(ctx)[0]
        ctx.ledger.plan([ctx.out / obj_frame_name(f) for f in self.numbers])
        self.written: list[Path] = []

    def add(self, start, frames):
        for i, p in enumerate(frames):
            path = self.ctx.out / obj_frame_name(self.numbers[start + i])
            write_obj(path, self.ctx.template, p)
            self.written.append(path)

    def finish(self):
        return self.written


class CsvExport(Exporter):
    help = "weights.csv"
    files = ("weights.csv",)

    def finish(self):
        path = self.ctx.out / self.files[0]
        frames, times, _ = timing(self.ctx)
        write_text(path, weights_csv(self.ctx.regions, self.ctx.fps, frames, times))
        return [path]


class ExrExport(Exporter):
    help = "animation.exr + animation.json (rows: frames; their source frame numbers and times in both)"
    files = ("animation.exr", "animation.json")
    streams = True

    def __init__(self, ctx):
        super().__init__(ctx)
        self.values = np.empty((ctx.n_frames, ctx.n_vertices, 3), np.float32)
        self.offsets = ctx.settings.get("vat", "offsets") == "offsets"

    def add(self, start, frames):
        self.values[start:start + len(frames)] = frames - (self.ctx.base if self.offsets else 0.0)

    def finish(self):
        exr, sidecar = (self.ctx.out / f for f in self.files)
        frames, times, rate = timing(self.ctx)
        write_vat(exr, self.values, fps=self.ctx.fps, mode=self.ctx.settings.get("vat", "offsets"), sidecar=sidecar,
                  frames=frames, times=times, source_fps=rate)
        return [exr, sidecar]


class GlbExport(Exporter):
    help = "animation.glb"
    files = ("animation.glb",)

    def finish(self):
        c = self.ctx
        mt, names, mw = c.morph_targets()
        path = c.out / self.files[0]
        keep = c.written_rows()  # gaps omit: the gap frames are not keyed (the player interpolates across)
        nodes = c.node_transforms
        write_glb(path, base=c.base, faces=None, targets=mt, target_names=names, weights=mw[keep],
                  fps=c.fps, node_transforms=None if nodes is None else nodes[keep], name=c.template.path.stem,
                  surface=obj_surface(c.template), times=timing(c)[1][keep])
        return [path]


class CurvesExport(Exporter):
    help = "curves.csv + curves.npz: the rig's sliders per frame, with keys posed by auto-pose"
    files = ("curves.csv", "curves.npz")
    needs_rig = True

    def finish(self):
        c = self.ctx
        frames, times, rate = timing(c)
        csv, npz = (c.out / f for f in self.files)
        keep = c.written_rows()
        found = None if c.found is None or np.all(c.found) else np.asarray(c.found, bool)
        hp = c.head_pose
        write_animation(csv, c.rig.names, c.curves[keep], frames[keep], times[keep],
                        found=None if found is None else found[keep], head=None if hp is None else hp[keep])
        write_animation(npz, c.rig.names, c.curves, frames, times, found=found, head=hp,
                        meta={"fps": c.fps, "source_fps": rate, "rig": Path(c.rig_file).name,
                              "weights": Path(c.weights).name, **({} if found is None else {"gaps": c.gaps})})
        return [csv, npz]


class LiveLinkExport(Exporter):
    help = "livelink.csv: Live Link Face CSV of the rig's sliders"
    files = ("livelink.csv",)
    needs_rig = True

    def finish(self):
        c = self.ctx
        frames, _, rate = timing(c)
        return [write_livelink(c.out / self.files[0], c.rig, c.curves, rate, landmarks=c.landmarks, frames=frames,
                               rows=c.written_rows(), head_pose=c.head_pose)]


class UsdExport(Exporter):
    help = "animation.usd: UsdSkel blendshapes or a point cache"
    files = ("animation.usd",)

    @classmethod
    def check(cls):
        require_pxr()

    def finish(self):
        c = self.ctx
        frames, _, rate = timing(c)
        return [write_usd(c.out / self.files[0], c.template, c.base, c.positions, c.n_frames, rate,
                          morph_targets=c.morph_targets if c.rig is not None else None, head=c.node_transforms,
                          frames=frames,
                          keys=c.written_rows())]


class SameExport(Exporter):
    """The rig's own glTF/GLB/VRM or USD file back, animated (:mod:`retarget_cli.io.gltf_animation`,
    :mod:`retarget_cli.io.usd_animation`).

    ``<stem>_animated.glb``: a copy of the source with the curves as a morph-weight animation; for a VRM
    also ``<stem>_animated.vrma``, a VRM Animation of the sliders that are VRM expressions. For a USD
    source ``<stem>_animated.<its suffix>``: the stage flattened, with the curves as time-sampled UsdSkel
    ``blendShapeWeights``.
    """

    help = ("<stem>_animated.glb (+ .vrma for VRM) or .usd*: the rig's own glTF/GLB/VRM or USD file with the "
            "curves as morph-weight or UsdSkel blend-shape animation")
    needs_rig = True
    suffixes = (".glb", ".gltf", ".vrm", *USD_EXTS)

    @classmethod
    def source(cls, ctx) -> Path | None:
        """The file the rig was read from (``Rig.source`` of its spec), or None."""
        spec = getattr(ctx.rig, "spec", None)
        src = getattr(spec, "source", None)
        if src is None:
            return None
        src = Path(src)
        return src if src.is_absolute() or ctx.rig_file is None else Path(ctx.rig_file).parent / src

    @classmethod
    def outputs(cls, ctx, source: Path) -> tuple[Path, ...]:
        if source.suffix.lower() in USD_EXTS:
            return (ctx.out / copy_name(source),)
        return ctx.out / f"{source.stem}_animated.glb", ctx.out / f"{source.stem}_animated.vrma"

    @classmethod
    def check_context(cls, ctx):
        src = cls.source(ctx)
        if src is None or src.suffix.lower() not in cls.suffixes:
            where = f"{ctx.rig_file}: " if ctx.rig_file is not None else ""
            raise InputError(f"{where}apply.formats: same needs a rig read from a .glb/.gltf/.vrm or "
                             ".usd/.usda/.usdc/.usdz file (rig.yaml source:)")
        if src.suffix.lower() in USD_EXTS:
            require_pxr()
        for path in cls.outputs(ctx, src):
            check_not_input(path, [src, ctx.weights, ctx.targets, ctx.landmarks, ctx.rig_file])

    def finish(self):
        c = self.ctx
        src = self.source(c)
        if src.suffix.lower() in USD_EXTS:
            return [self._usd(src)]
        glb, vrma = self.outputs(c, src)
        names = list(c.rig.names)
        groups, missing = copy_groups(read_gltf_rig(src), names)
        if not groups:
            raise InputError(f"{src}: none of the rig's sliders ({', '.join(names[:6])}, ...) is a slider or morph "
                             "target of the file; nothing to animate")
        if missing:
            log.warning("%s: %d slider(s) are not sliders or morph targets of the file and are not in %s: %s",
                        src.name, len(missing), glb.name, ", ".join(missing))
        times = timing(c)[1]
        written = [write_animated_copy(glb, src, c.curves, names, c.fps, groups, lower=c.rig.lower,
                                       upper=c.rig.upper, times=times)]
        if is_vrm(src):
            path = write_vrma(vrma, src, c.curves, names, c.fps, lower=c.rig.lower, upper=c.rig.upper, times=times)
            written += [path] if path is not None else []
        return written


    def _usd(self, src: Path) -> Path:
        c, spec = self.ctx, self.ctx.rig.spec
        names = list(c.rig.names)
        W = target_weights(c.curves, names, spec.sliders, spec.outline.target_names, lower=c.rig.lower,
                           upper=c.rig.upper)
        frames, _, rate = timing(c)
        return write_animated_usd(self.outputs(c, src)[0], src, W, spec.outline.target_names, rate,
                                  meshes=spec.meshes, targets=spec.targets, frames=frames)


#: Export formats by name, in the order ``--format`` lists them.
EXPORTS: dict[str, type[Exporter]] = {
    "obj": ObjExport,
    "csv": CsvExport,
    "exr": ExrExport,
    "glb": GlbExport,
    "curves": CurvesExport,
    "livelink": LiveLinkExport,
    "usd": UsdExport,
    "same": SameExport,
}


def format_choices() -> tuple[str, ...]:
    """The registered format names."""
    return tuple(EXPORTS)


def formats_help() -> str:
    """``name (its files)`` for every registered format, comma-separated."""
    return ", ".join(f"{name} ({cls.help})" for name, cls in EXPORTS.items())


# --------------------------------------------------------------------------- writers the rig exports share


def head_rotation(landmarks, T: int):
    """(T, 3) head yaw, pitch, roll (radians) from ``landmarks.npz``, or None without a landmarks file.

    Roll comes from the tracked 2D head motion; yaw and pitch are 0 (the 2D
    track has no estimate of them).
    """

    if landmarks is None:
        return None
    lm = load_landmarks(landmarks)
    if lm.n_frames != T:
        raise InputError(f"{landmarks}: has {lm.n_frames} frames but the weights have {T}")
    return head_rotation_from_similarity(lm.head)


def eye_rotation(landmarks, T: int):
    """(T, 6) the Live Link eye columns (radians, :func:`~.livelink.eye_rotation_from_gaze`) from
    ``landmarks.npz``'s gaze, looking ahead at its median over the take's rest frames
    (:func:`~retarget_cli.methods.gaze_rig.rest_gaze`, as auto-pose calibrates it); None without a gaze."""

    if landmarks is None:
        return None
    lm = load_landmarks(landmarks)
    if lm.gaze is None or lm.n_frames != T:
        log.info("Live Link Face CSV: %s has no gaze (track.gaze), so the eye rotation columns are 0", landmarks)
        return None
    rest = rest_gaze(lm.gaze, lm.gaze_valid, find_rest_frame(lm.stabilized, lm.confidence).members)
    return eye_rotation_from_gaze(lm.gaze, rest)


def write_livelink(path: Path, rig, curves: np.ndarray, fps: float, *, landmarks=None, frames=None,
                   rows=None, head_pose=None) -> Path:
    """Write the rig's curves as a Live Link Face CSV (:func:`retarget_cli.io.livelink.livelink_csv`).

    Parameters
    ----------
    rig : BlendshapeRig
        Its slider names, and ``rig.yaml``'s ``names:`` mapping (``rig.spec.names``).
    curves : ndarray, shape (T, n)
    landmarks : path-like, optional
        ``landmarks.npz``: HeadRoll from its head motion; without it the head columns are 0.
    fps, frames
        The source's rate and each row's source frame number: the timecodes (:func:`~.livelink.livelink_csv`).
    rows : ndarray, shape (T,), bool, optional
        The rows written (``apply.gaps: omit`` leaves the gaps' out; each row keeps its frame's timecode).
    head_pose : ndarray, shape (T, 6), optional
        The 3D head pose (:attr:`ExportContext.head_pose`): HeadYaw, HeadPitch and HeadRoll from it
        (:func:`~.livelink.head_rotation_from_pose`) instead of the 2D similarity's roll.
    """

    rot = head_rotation(landmarks, len(curves)) if head_pose is None else \
        head_rotation_from_pose(np.asarray(head_pose)[:, :3])
    if rot is None:
        log.info("Live Link Face CSV: no landmarks file, so the head rotation columns are 0")
    eyes = eye_rotation(landmarks, len(curves))
    if rows is not None and not np.all(rows):
        keep = np.asarray(rows, bool)
        curves = np.asarray(curves)[keep]
        frames = (np.arange(len(keep)) if frames is None else np.asarray(frames))[keep]
        rot = None if rot is None else rot[keep]
        eyes = None if eyes is None else eyes[keep]
    names = rig.spec.names if rig.spec is not None else {}
    write_text(path, livelink_csv(curves, rig.names, fps, names=names, head_rotation=rot, frames=frames,
                                  eye_rotation=eyes))
    return path


def rig_shapes(rig, curves: np.ndarray) -> tuple[np.ndarray, list[str], np.ndarray]:
    """The rig's shapes and weights for blendshape formats (glTF morph targets, UsdSkel BlendShapes).

    One shape per slider, driven by its curve; then one per corrective of
    ``rig.yaml`` (Racković et al. 2023, eq. 4: ``w_i w_j (corrective_ij −
    neutral)``), which neither format can express, baked as an extra shape
    ``corrective_<a>_<b>`` driven by the product of its pair's weights.

    Returns
    -------
    shapes : ndarray, shape (M, N, 3)
    names : list of str, length M
    weights : ndarray, shape (T, M)
    """

    D = rig.D.toarray() if rig.sparse else np.asarray(rig.D)
    shapes = [D.T.reshape(rig.n_sliders, -1, 3)]
    names, cols = list(rig.names), [np.asarray(curves, dtype=np.float64)]
    corr = parse_correctives(rig.spec) if rig.spec is not None else []
    for i, j, p in corr:
        mesh = read_obj(p)
        if mesh.n_vertices != rig.n_vertices:
            raise InputError(f"{p}: corrective has {mesh.n_vertices} vertices, the rig has {rig.n_vertices}")
        shapes.append((mesh.vertices - rig.neutral)[None])
        names.append(f"corrective_{rig.names[i]}_{rig.names[j]}")
        cols.append((cols[0][:, i] * cols[0][:, j])[:, None])
    if corr:
        log.info("blendshape exports: %d corrective shapes baked as extra shapes driven by their pairs' "
                 "products (the OBJ/EXR frames are the linear rig)", len(corr))
    return np.concatenate(shapes), names, np.concatenate(cols, axis=1)


def write_usd(path: Path, template, base: np.ndarray, positions, T: int, fps: float, *, morph_targets=None,
              head=None, frames=None, keys=None) -> Path:
    """Write ``animation.usd``: a UsdSkel character with a rig, else a point cache.

    Parameters
    ----------
    template : ObjMesh
        Faces and texture coordinates.
    base : ndarray, shape (N, 3)
        The rest mesh (the rig's neutral).
    positions : callable
        ``positions(slice)`` -> (t, N, 3) meshes without head motion (the point cache).
    morph_targets : callable, optional
        ``morph_targets()`` -> (shapes, names, weights) of the rig (:func:`rig_shapes`); without it a point cache.
    head : ndarray, shape (T, 3, 4), optional
        Head motion, the time-sampled transform of ``/Character``.
    frames : ndarray, shape (T,), optional
        Each frame's source frame number, its time code (*fps* is then the source's rate).
    keys : ndarray, shape (T,), bool, optional
        With a rig, the frames time-sampled (``apply.gaps: omit`` leaves the gaps' out; USD interpolates
        across); the point cache samples every frame.
    """

    surf = obj_surface(template)
    uv = (surf.uv, surf.vt) if surf.has_uv else None
    common = dict(counts=surf.counts, corners=surf.v, fps=fps, uv=uv, transforms=head, name=Path(template.path).stem,
                  frames=frames)
    if morph_targets is not None:
        shapes, names, weights = morph_targets()
        if keys is not None and not np.all(keys):
            keep = np.asarray(keys, bool)
            weights = weights[keep]
            common.update(transforms=None if head is None else np.asarray(head)[keep],
                          frames=(np.arange(T) if frames is None else np.asarray(frames))[keep])
        write_usd_skel(path, points=base, shapes=shapes, names=names, weights=weights, **common)
    else:
        X = np.concatenate([positions(slice(s, min(s + 64, T))) for s in range(0, T, 64)])
        write_usd_points(path, positions=X, **common)
    return path
