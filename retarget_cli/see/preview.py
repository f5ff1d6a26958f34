"""Side-by-side preview video of a run: source with landmarks | shaded target | weight bars.

Everything is drawn with OpenCV and :mod:`retarget_cli.methods.render` (no plotting
library), so a preview renders at close to the rasteriser's speed.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..errors import InputError, ParameterError
from ..io.atomic import check_not_input, load_npz, write_bytes
from ..io.editfiles import read_animation
from ..io.frames import FrameSource as SourceFrames
from ..io.landmarks import load_landmarks
from ..io.obj import read_obj, read_vertices_like
from ..io.rig import load_rig
from ..io.stagefiles import read_targets
from ..io.video import atomic_video_writer
from ..methods.blending import apply_transforms, head_rotation_transforms
from ..methods.render import Camera, MeshRenderer
from ..run.runfiles import RunFiles, read_run_weights

log = logging.getLogger(__name__)

BACKGROUND = (32, 28, 26)
TEXT = (235, 235, 235)
MUTED = (150, 150, 150)
#: BGR colours cycled over regions.
REGION_COLORS = [(235, 160, 60), (70, 170, 245), (120, 200, 110), (200, 120, 220), (90, 90, 235), (200, 200, 80)]


def describe_frames(numbers) -> str:
    """``source frames 100-198, every 2nd`` for (T,) source frame numbers (for messages)."""
    numbers = np.asarray(numbers)
    if len(numbers) == 0:
        return "no frames"
    text = f"source frames {int(numbers[0])}-{int(numbers[-1])}"
    steps = np.unique(np.diff(numbers))
    if len(steps) == 1 and steps[0] > 1:
        text += f", every {int(steps[0])}{'nd' if steps[0] == 2 else 'rd' if steps[0] == 3 else 'th'}"
    return text


def parse_frames(spec: str | None, numbers) -> range:
    """Rows selected by ``a:b`` of source frame numbers (as ``curves.csv``'s ``frame`` column names them).

    Parameters
    ----------
    spec : str or None
        ``"a:b"`` (the frames numbered ``a <= frame < b``), ``"a:"``, ``":b"`` or a single frame ``"a"``
        (it must be a frame of the take); negative values count rows from the end (``-1`` is the last
        frame). ``None`` selects every frame.
    numbers : int or ndarray, shape (T,), int
        Each row's source frame number (``landmarks.npz`` ``frames``), increasing; an int T means 0 … T−1.

    Returns
    -------
    range
        Rows of the take.

    Raises
    ------
    ParameterError
        For malformed text, a single frame that is not one of the take's, or an empty selection; the message
        names the take's frames.
    """
    numbers = np.arange(numbers) if np.ndim(numbers) == 0 else np.asarray(numbers, dtype=np.int64)
    T = len(numbers)
    if spec is None or spec.strip() in ("", ":"):
        return range(T)
    a, sep, b = spec.partition(":")
    try:
        lo = int(a) if a.strip() else None
        hi = int(b) if b.strip() else None
    except ValueError:
        raise ParameterError(f"--frames: expected a:b with integers, got {spec!r}") from None

    def row(v, *, end=False):  # a frame number to the first row at or after it; a negative value counts rows
        if v is None:
            return T if end else 0
        if v < 0:
            return max(T + v, 0)
        return int(np.searchsorted(numbers, v, side="left"))

    if not sep:
        r = row(lo)
        if lo is not None and lo >= 0 and (r >= T or numbers[r] != lo):
            raise ParameterError(f"--frames {spec}: frame {lo} is not a frame of the take ({T} frames, "
                                 f"{describe_frames(numbers)})")
        rng = range(r, min(r + 1, T))
    else:
        rng = range(row(lo), max(row(lo), row(hi, end=True)))
    if len(rng) == 0:
        raise ParameterError(f"--frames {spec}: selects no frame of the {T}-frame take ({describe_frames(numbers)})")
    return rng


def confidence_color(c: np.ndarray) -> np.ndarray:
    """BGR colours for confidences in [0, 1]: red (lost) through yellow to green (sure).

    Returns
    -------
    ndarray, shape (n, 3), uint8
    """
    c = np.clip(np.nan_to_num(np.asarray(c, dtype=np.float64)), 0, 1)
    g = np.clip(2 * c, 0, 1) * 230
    r = np.clip(2 * (1 - c), 0, 1) * 235
    return np.stack([np.full_like(c, 40), g, r], -1).astype(np.uint8)


def draw_landmarks(img: np.ndarray, points: np.ndarray, conf: np.ndarray, *, scale: float = 1.0,
                   radius: int = 2) -> np.ndarray:
    """Draw landmarks (L, 2) coloured by confidence (L,) onto *img* in place (points scaled by *scale*)."""
    import cv2

    cols = confidence_color(conf)
    for (x, y), col in zip(np.asarray(points, dtype=np.float64) * scale, cols):
        if np.isfinite(x) and np.isfinite(y):
            cv2.circle(img, (int(round(x * 16)), int(round(y * 16))), radius * 16, tuple(int(v) for v in col),
                       -1, cv2.LINE_AA, shift=4)
    return img


def put_text(img, text, org, scale=0.45, color=TEXT, thickness=1):
    import cv2

    cv2.putText(img, text, (int(org[0]), int(org[1])), cv2.FONT_HERSHEY_SIMPLEX, scale, color, thickness, cv2.LINE_AA)


def draw_weight_bars(size: tuple[int, int], weights: dict, vmax: dict, *, current_frame: int | None = None,
                     title: str = "weights") -> np.ndarray:
    """A bar chart of one frame's weights, one row of bars per region.

    Parameters
    ----------
    size : (width, height)
    weights : dict
        Region name to ``(w (K,), key_frames (K,))``.
    vmax : dict
        Region name to the value drawn at full bar height.
    current_frame : int, optional
        A key whose frame equals it is outlined (the take passes through a key).

    Returns
    -------
    ndarray, shape (height, width, 3), uint8 (BGR)
    """
    import cv2

    W, H = size
    img = np.empty((H, W, 3), np.uint8)
    img[:] = BACKGROUND
    put_text(img, title, (8, 18), 0.5)
    n = max(len(weights), 1)
    top, row_h = 28, (H - 28) / n
    for r, (name, (w, frames)) in enumerate(weights.items()):
        col = REGION_COLORS[r % len(REGION_COLORS)]
        y0 = int(top + r * row_h)
        label_h, tick_h = 16, 14
        base = int(top + (r + 1) * row_h) - tick_h - 4
        avail = max(base - (y0 + label_h + 4), 4)
        vm = max(float(vmax.get(name, 1.0)), 1e-9)
        put_text(img, f"{name}  (full = {vm:.2f})", (8, y0 + label_h - 2), 0.42, col)
        K = len(w)
        left, right = 8, W - 8
        slot = (right - left) / max(K, 1)
        bw = max(int(slot * 0.72), 1)
        cv2.line(img, (left, base), (right, base), MUTED, 1)
        if vm > 1.01:  # mark weight 1 when weights exceed it
            y1 = base - int(round(avail / vm))
            cv2.line(img, (left, y1), (right, y1), (90, 90, 90), 1)
        for k in range(K):
            x = int(left + k * slot + (slot - bw) / 2)
            hgt = int(round(np.clip(w[k], 0, vm) / vm * avail))
            if hgt > 0:
                cv2.rectangle(img, (x, base - hgt), (x + bw - 1, base - 1), col, -1)
            if w[k] < 0:  # unconstrained solvers: show negative weights as a red stub below the axis
                neg = int(round(min(-w[k] / vm, 0.25) * avail))
                cv2.rectangle(img, (x, base + 1), (x + bw - 1, base + 1 + neg), (60, 60, 220), -1)
            if current_frame is not None and int(frames[k]) == current_frame:
                cv2.rectangle(img, (x - 1, y0 + label_h + 2), (x + bw, base), TEXT, 1)
            if slot >= 22 or k % max(1, int(np.ceil(22 / slot))) == 0:
                put_text(img, str(int(frames[k])), (x, base + tick_h), 0.3, MUTED)
    return img


class FrameSource:
    """Source frames by row of the landmarks, or blank canvases when there is no video.

    *numbers*: each row's source frame number (``landmarks.npz`` ``frames``: a run from frame 100, every 2nd,
    or an image sequence with gaps); default the row itself. A video or an image sequence
    (:class:`retarget_cli.io.frames.FrameSource`).
    """

    def __init__(self, video: Path | None, frame_size: tuple[int, int], numbers=None):
        self.video = video
        self.frame_size = frame_size
        self.numbers = None if numbers is None else [int(n) for n in numbers]
        self._reader = None
        self._it = None
        self._pos = 0
        self._at = -1
        self._frame = None
        if video is not None:
            self._reader = SourceFrames(video, warn_missing=False)
            self.frame_size = self._reader.frame_size
            self._it = iter(self._reader)

    def get(self, t: int) -> np.ndarray | None:
        """Row *t*'s frame (BGR); rows must be requested in increasing order. ``None`` past the end or without video."""
        if self._it is None:
            return None
        if t < self._pos:
            raise ParameterError(f"frames must be requested in order: asked {t} after {self._pos}")
        self._pos = t
        want = t if self.numbers is None else (self.numbers[t] if t < len(self.numbers) else None)
        if want is None:
            return None
        try:
            while self._at < want:
                self._frame = next(self._it)
                self._at = self._reader.frames[-1]
        except (StopIteration, InputError):
            self._it = None
            return None
        return self._frame if self._at == want else None

    def close(self):
        if self._reader is not None:
            self._reader.close()


def _blank(size, color=(70, 70, 70)) -> np.ndarray:
    W, H = size
    img = np.empty((H, W, 3), np.uint8)
    img[:] = color
    return img


#: The slider curves ``apply`` writes (``formats: curves``), looked for in its output folder, in this order.
CURVE_FILES = ("curves.npz", "curves.csv")


def curves_character(run: RunFiles):
    """The rig and its slider curves of a run whose ``apply`` wrote curves and no OBJ frames, or None.

    The curves are ``curves.npz`` (else ``curves.csv``) in the run's ``frames`` folder; the rig is the one
    its ``targets.yaml`` names (``rig:``, as auto-pose writes it). Head motion (``apply.head_motion``) is
    not in the curves, so the character is shown without it.

    Returns
    -------
    (rig, curves, path, rig_path) or None
        The :class:`~retarget_cli.methods.rig.BlendshapeRig`, the curves (T, E) in the rig's slider order
        (sliders the file does not name at 0), the curves file and the ``rig.yaml``.

    Raises
    ------
    InputError
        A curves file that names a slider the rig does not have.
    """
    if run.frames is None:
        return None
    path = next((run.frames / n for n in CURVE_FILES if (run.frames / n).is_file()), None)
    if path is None:
        return None
    targets = read_targets(run.targets) if run.targets is not None else None
    if targets is None or targets.rig is None:
        log.warning("%s: no targets.yaml naming the rig (rig:), so the curves cannot be shown on the character",
                    path)
        return None
    rig = load_rig(targets.rig)
    names, W, _, _ = read_animation(path)
    index = {n: j for j, n in enumerate(rig.names)}
    unknown = [n for n in names if n not in index]
    if unknown:
        raise InputError(f"{path}: slider {unknown[0]!r} is not a shape of the rig {targets.rig}")
    curves = np.zeros((len(W), len(rig.names)))
    curves[:, [index[n] for n in names]] = W
    log.info("%s: the character is the rig %s posed at these curves (%d frames)", path, targets.rig, len(W))
    return rig, curves, path, targets.rig


def curves_head_turn(character) -> np.ndarray | None:
    """(T, 3, 4) head rotation of the character from the curves' ``head_angles`` (``curves.npz`` with
    ``apply.head_rotation``), about the centre of the rig's rest mesh, or None when the curves have none.

    The preview then turns the character's head as the exports do (the glTF node, the USD root:
    :func:`~retarget_cli.methods.blending.head_rotation_transforms`).
    """
    rig, curves, path = character[:3]
    if Path(path).suffix.lower() != ".npz":
        return None
    data = load_npz(path)
    angles = data.get("head_angles")
    if angles is None or angles.shape != (len(curves), 3) or not np.isfinite(angles).all():
        return None
    base = np.asarray(rig.neutral, dtype=np.float64)
    return head_rotation_transforms(np.asarray(angles, np.float64), pivot=(base.min(0) + base.max(0)) / 2)


class RunData:
    """Arrays of a run loaded once for preview and report (whatever exists).

    The character's frames are ``apply``'s OBJ frames, or, when it wrote none, its rig posed at its slider
    curves (:func:`curves_character`).
    """

    def __init__(self, run: RunFiles):
        self.run = run
        self.lm = load_landmarks(run.landmarks) if run.landmarks else None
        self.regions, self.extras, self.other = ({}, {}, {"meta": {}})
        if run.weights:
            self.regions, self.extras, self.other = read_run_weights(run.weights)
        self.frame_files = run.frame_files()
        self.character = None if self.frame_files else curves_character(run)
        self.head_turn = None if self.character is None else curves_head_turn(self.character)
        lengths = []
        if self.lm is not None:
            lengths.append(self.lm.n_frames)
        if self.regions:
            lengths.append(next(iter(self.regions.values()))[0].shape[0])
        if self.n_character_frames:
            lengths.append(self.n_character_frames)
        if len(set(lengths)) > 1:
            log.warning("%s: landmarks, weights and frames have different lengths %s; using the shortest",
                        run.root, lengths)
        self.n_frames = min(lengths) if lengths else 0
        fps = self.lm.fps if self.lm is not None else self.other["meta"].get("fps")
        self.fps = float(fps) if fps else 30.0
        self._mesh = None

    def source_frames(self) -> np.ndarray:
        """(n_frames,) int64: each row's source frame number (the landmarks', else the weights', else the row)."""
        return self.numbers(self.n_frames)

    def numbers(self, T: int) -> np.ndarray:
        """(T,) int64: the source frame numbers of rows 0 … T−1 (the landmarks', else the weights', else the
        rows themselves), for axes and tables that name frames."""
        for src in (None if self.lm is None else self.lm.timing()[0], self.other.get("frame")):
            if src is not None and len(src) >= T:
                return np.asarray(src[:T], dtype=np.int64)
        return np.arange(T, dtype=np.int64)

    def row_of(self, frame: int) -> int | None:
        """The row whose source frame number is *frame*, or None when no row has it."""
        numbers = self.numbers(self.n_frames)
        r = int(np.searchsorted(numbers, frame))
        return r if r < len(numbers) and numbers[r] == frame else None

    def source_time(self, t: int) -> tuple[int, float]:
        """Row *t*'s source frame number and its time in seconds (the landmarks' timing, else ``t / fps``)."""
        if self.lm is not None and t < self.lm.n_frames:
            frames, times = self.lm.timing()
            return int(frames[t]), float(times[t])
        times = self.other.get("time")
        if times is not None and t < len(times) and self.other.get("frame") is not None:
            return int(self.other["frame"][t]), float(times[t])
        return t, t / self.fps

    @property
    def frame_size(self) -> tuple[int, int]:
        if self.lm is not None and np.all(self.lm.frame_size > 0):
            return int(self.lm.frame_size[0]), int(self.lm.frame_size[1])
        if self.lm is not None:
            hi = np.nanmax(self.lm.points.reshape(-1, 2), 0)
            return int(hi[0] * 1.1) + 1, int(hi[1] * 1.1) + 1
        return 320, 320

    @property
    def n_character_frames(self) -> int:
        """Frames of the character: OBJ frames, else rows of the curves (0 without either)."""
        if self.frame_files:
            return len(self.frame_files)
        return 0 if self.character is None else len(self.character[1])

    @property
    def character_source(self) -> str:
        """What the character's frames are, for captions."""
        if self.frame_files:
            return f"{len(self.frame_files)} OBJ in {self.run.frames}"
        if self.character is not None:
            return f"the rig {self.character[3]} posed at {self.character[2]}"
        return ""

    def mesh(self):
        """The first frame's OBJ, or the curves' rig template (topology and framing), or ``None``."""

        if self._mesh is None and self.frame_files:
            self._mesh = read_obj(self.frame_files[0])
        if self._mesh is None and self.character is not None:
            self._mesh = self.character[0].template
        return self._mesh

    def frame_vertices(self, t: int) -> np.ndarray:
        """Frame *t*'s vertex positions; a pose of the first frame's mesh has only its ``v`` lines parsed (or the
        rig evaluated at the curves' row *t*)."""

        if not self.frame_files:
            rig, curves = self.character[:2]
            v = rig.evaluate(curves[t])
            if self.head_turn is not None and t < len(self.head_turn):
                v = apply_transforms(self.head_turn[t:t + 1], v[None])[0]
            return v
        v = read_vertices_like(self.frame_files[t], self.mesh())
        if len(v) != self.mesh().n_vertices:
            raise InputError(f"{self.frame_files[t]}: {len(v)} vertices, but "
                             f"{self.frame_files[0]} has {self.mesh().n_vertices}")
        return v

    def weights_at(self, t: int) -> dict:
        return {name: (W[t], fr) for name, (W, fr) in self.regions.items()}

    def vmax(self) -> dict:
        return {name: max(1.0, float(np.nanmax(W))) for name, (W, _) in self.regions.items()}


def preview_frames(data: RunData, frames: range, *, height: int = 360, camera=None, shading: str = "gouraud",
                   ) -> Iterator[np.ndarray]:
    """Yield composed preview frames (BGR, all the same even size).

    Parameters
    ----------
    data : RunData
    frames : range
        Frame indices, increasing.
    height : int
        Height of every panel in pixels.
    camera : retarget_cli.methods.render.Camera, optional
    shading : {"gouraud", "flat"}
    """
    import cv2


    camera = camera or Camera()
    src = FrameSource(data.run.video, data.frame_size, None if data.lm is None else data.lm.frames)
    sw, sh = src.frame_size
    scale = height / sh
    left_w = max(int(round(sw * scale)), 16)
    mesh_w = height
    bars_w = max(int(height * 0.9), 200) if data.regions else 0
    total_w = left_w + mesh_w + bars_w
    total_w += total_w % 2
    H = height + height % 2
    renderer = None
    mesh = data.mesh()
    if mesh is not None:
        renderer = MeshRenderer(mesh.faces(), mesh.vertices, camera=camera, size=(mesh_w, height), shading=shading)
    vmax = data.vmax()
    try:
        for t in frames:
            out = np.empty((H, total_w, 3), np.uint8)
            out[:] = BACKGROUND
            frame = src.get(t)
            if frame is None:
                frame = _blank((sw, sh))
            left = cv2.resize(frame, (left_w, height), interpolation=cv2.INTER_AREA)
            if data.lm is not None and t < data.lm.n_frames:
                draw_landmarks(left, data.lm.points[t], data.lm.confidence[t], scale=left_w / sw,
                               radius=max(1, round(height / 150)))
                put_text(left, f"confidence {float(np.mean(data.lm.confidence[t])):.2f}", (8, height - 10), 0.42)
            number, seconds = data.source_time(t)
            put_text(left, f"frame {number}  {seconds:6.2f}s", (8, 18), 0.5)
            out[:height, :left_w] = left
            if renderer is not None and t < data.n_character_frames:
                out[:height, left_w:left_w + mesh_w] = renderer.render(data.frame_vertices(t))
            else:
                put_text(out, "no frames/frame_*.obj or curves (run apply)", (left_w + 8, height // 2), 0.42,
                         MUTED)
            if bars_w:
                out[:height, left_w + mesh_w:left_w + mesh_w + bars_w] = draw_weight_bars(
                    (bars_w, height), data.weights_at(t), vmax, current_frame=number)
            yield out
    finally:
        src.close()


def write_preview(run: RunFiles, output: str | os.PathLike, *, frames: str | None = None, height: int = 360,
                  fps: float | None = None, camera=None, shading: str = "gouraud", progress=None) -> Path:
    """Write the side-by-side preview video of *run* to *output* (atomically).

    Parameters
    ----------
    run : RunFiles
    output : path-like
        ``.mp4`` (mp4v), ``.avi`` (MJPG), ...; or an image (``.png``, ``.jpg``, ...) when *frames*
        selects one frame.
    frames : str, optional
        ``a:b`` range of source frame numbers (see :func:`parse_frames`).
    height : int
        Panel height in pixels (the video is about 2.9 times as wide).
    fps : float, optional
        Defaults to the take's frame rate.
    progress : callable, optional
        ``progress(length, label)`` context manager with ``update(n)``.

    Returns
    -------
    Path
        *output*.
    """

    if not 32 <= int(height) <= 2160:
        raise ParameterError(f"--size: expected a panel height in [32, 2160] pixels, got {height}")
    if fps is not None and not 0 < fps <= 240:
        raise ParameterError(f"--fps: expected a value in (0, 240], got {fps}")
    suffix = Path(output).suffix.lower()
    if suffix not in VIDEO_OUT + IMAGE_OUT:
        raise InputError(f"{output}: unknown output type {Path(output).suffix!r}; expected a video "
                         f"({', '.join(VIDEO_OUT)}) or, for one frame, an image ({', '.join(IMAGE_OUT)})")
    data = RunData(run)
    if data.n_frames == 0:
        raise InputError(f"{run.root}: no frames to preview")
    check_not_input(output, [run.video, run.landmarks, run.weights])
    sel = parse_frames(frames, data.source_frames())
    if suffix in IMAGE_OUT and len(sel) != 1:
        raise ParameterError(f"--frames: an image ({Path(output).name}) holds one frame, but {len(sel)} are "
                             f"selected; pick one with --frames N, or write a video ({', '.join(VIDEO_OUT)})")
    it = preview_frames(data, sel, height=int(height), camera=camera, shading=shading)
    first = next(it)
    if suffix in IMAGE_OUT:
        import cv2

        ok, buf = cv2.imencode(suffix, first)
        if not ok:
            raise InputError(f"{output}: OpenCV cannot encode {suffix}")
        write_bytes(output, buf.tobytes())
        log.info("wrote preview frame %d (%dx%d) to %s", int(data.source_frames()[sel[0]]), first.shape[1],
                 first.shape[0], output)
        return Path(output)
    size = (first.shape[1], first.shape[0])
    from contextlib import nullcontext

    bar_cm = progress(len(sel), "preview") if progress else nullcontext(None)
    with bar_cm as bar, atomic_video_writer(output, fps or data.fps, size) as writer:
        writer.write(first)
        if bar:
            bar.update(1)
        for img in it:
            writer.write(img)
            if bar:
                bar.update(1)
    log.info("wrote %d preview frames (%dx%d) to %s", len(sel), size[0], size[1], output)
    return Path(output)


# --------------------------------------------------------------------------- render command

VIDEO_OUT = (".mp4", ".avi", ".mov", ".m4v", ".mkv")
IMAGE_OUT = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def mesh_sequence(path: str | os.PathLike) -> list[Path]:
    """OBJ files named by *path*: one ``.obj`` file, a directory of them, or a glob pattern.

    A directory's ``frame_*.obj`` are taken in frame order when present, else
    all its ``.obj`` files sorted by name.

    Raises
    ------
    InputError
        If nothing matches.
    """
    import glob
    import re

    text = str(path)
    p = Path(text)
    if p.is_file():
        return [p]
    if p.is_dir():
        frames = sorted(((int(m.group(1)), q) for q in p.iterdir()
                         if (m := re.match(r"frame_(\d+)\.obj$", q.name))), key=lambda x: x[0])
        files = [q for _, q in frames] or sorted(q for q in p.iterdir() if q.suffix.lower() == ".obj")
        if not files:
            raise InputError(f"{p}: directory holds no .obj file")
        return files
    if any(ch in text for ch in "*?["):
        files = sorted(Path(f) for f in glob.glob(text) if f.lower().endswith(".obj"))
        if not files:
            raise InputError(f"{text}: pattern matches no .obj file")
        return files
    raise InputError(f"{text}: no such OBJ file, directory or pattern")


def write_render(source, output, *, size=(512, 512), fps: float = 30.0, camera=None, shading: str = "gouraud",
                 progress=None) -> Path:
    """Render an OBJ to an image, or an OBJ sequence to a video (camera framed on the first mesh).

    Parameters
    ----------
    source : path-like
        OBJ file, directory or glob pattern (see :func:`mesh_sequence`).
    output : path-like
        Image (``.png``, ``.jpg``, ...) for one mesh; video (``.mp4``, ``.avi``) for any number.
    size : (width, height)
    fps : float
    camera : retarget_cli.methods.render.Camera, optional
    shading : {"gouraud", "flat"}
    """
    from contextlib import nullcontext

    import cv2


    files = mesh_sequence(source)
    out = Path(output)
    suffix = out.suffix.lower()
    if suffix not in VIDEO_OUT + IMAGE_OUT:
        raise InputError(f"{out}: unknown output type {out.suffix!r}; expected an image "
                         f"({', '.join(IMAGE_OUT)}) or a video ({', '.join(VIDEO_OUT)})")
    if suffix in IMAGE_OUT and len(files) > 1:
        raise InputError(f"{out}: {len(files)} meshes need a video output ({', '.join(VIDEO_OUT)}), "
                         "or name one OBJ file")
    if not 0 < fps <= 240:
        raise ParameterError(f"--fps: expected a value in (0, 240], got {fps}")
    check_not_input(out, files)
    first = read_obj(files[0])
    renderer = MeshRenderer(first.faces(), first.vertices, camera=camera or Camera(), size=size, shading=shading)
    if suffix in IMAGE_OUT:
        ok, buf = cv2.imencode(suffix, renderer.render(first.vertices))
        if not ok:
            raise InputError(f"{out}: OpenCV cannot encode {suffix}")
        write_bytes(out, buf.tobytes())
        return out
    bar_cm = progress(len(files), "render") if progress else nullcontext(None)
    with bar_cm as bar, atomic_video_writer(out, fps, renderer.size) as writer:
        for i, f in enumerate(files):
            v = first.vertices if i == 0 else read_vertices_like(f, first)  # the faces of the first reused
            if len(v) != first.n_vertices:
                raise InputError(f"{f}: {len(v)} vertices, but {files[0]} has {first.n_vertices}")
            writer.write(renderer.render(v))
            if bar:
                bar.update(1)
    return out
