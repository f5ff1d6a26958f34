"""Per-frame pretrained landmark detection: dlib's HOG face detector and 68-point shape predictor.

The 68 Multi-PIE landmarks are placed on every frame by dlib's ensemble of
regression trees (Kazemi & Sullivan 2014) shipped in ``face_recognition_models``
as ``shape_predictor_68_face_landmarks.dat``. Unlike the flow trackers, nothing
anchors a frame to an annotated one, so eyelids close and lips open as the
predictor sees them.

The face box of each frame comes from the previous frame's landmarks: the
HOG detector (Dalal & Triggs 2005, as in ``dlib.get_frontal_face_detector``)
runs only on the first frame and when the landmarks look lost; its box is
remembered relative to the eye corners and nose (an offset and a size in
units of the eye-corner span, turned with the eye line), so the box handed
to the predictor keeps the framing it was trained with.

Coordinates: dlib's part ``(x, y)`` is the integer index of a pixel, whose
centre is ``(x, y)`` in the 0-based pixel-centre convention of
``landmarks.npz``, so they are used as they are (``.pts`` files add 1).

dlib is imported lazily: without the optional extra ``detect`` the first
call raises a one-line :class:`~retarget_cli.errors.MissingExtraError` saying which
extra to install. The model file is located through ``importlib.metadata`` (the
files the installed ``face_recognition_models`` distribution records) without
importing that package, whose ``__init__`` needs ``pkg_resources`` (setuptools),
which Python 3.12+ virtual environments do not have.
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import itertools
import logging
import operator
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import MissingExtraError, ShapeError
from ..gaps import LOW_CONFIDENCE, NO_FACE, Coverage, CutDetector
from .facemark import _from_scaled, _scaled, _to_scaled
from .lk import FaceLostError, _Box

log = logging.getLogger(__name__)

#: What to install for this module.
INSTALL_HINT = "pip install 'retarget[detect]' (the optional extra 'detect': dlib-bin and face_recognition_models)"

#: Points whose centre and eye-corner span place the face box (eye corners and nose).
BOX_POINTS = (27, 28, 29, 30, 31, 33, 35, 36, 39, 42, 45)

#: Detector box relative to :data:`BOX_POINTS` when no detection calibrated it (an annotated first
#: frame): offset of the box centre in eye-corner spans (x along the eye line, y down) and side.
#: Mean over every 20th frame of the three shared clips (d3, d9, d12), rounded.
DEFAULT_BOX = (0.0, 0.2, 2.35)


class _Rows:
    """Rows of one shape appended one at a time into a preallocated float64 array (no list of per-frame arrays).

    *capacity* rows are reserved (``np.empty``: pages untouched until written cost no memory); when full the
    array grows by half. :attr:`array` is the filled part, a view.
    """

    def __init__(self, shape, capacity: int = 256):
        self._a = np.empty((max(int(capacity), 1), *shape))
        self.n = 0

    def append(self, row) -> None:
        if self.n == len(self._a):
            grown = np.empty((self.n + self.n // 2 + 1, *self._a.shape[1:]))
            grown[:self.n] = self._a
            self._a = grown
        self._a[self.n] = row
        self.n += 1

    def __len__(self) -> int:
        return self.n

    @property
    def array(self) -> np.ndarray:
        return self._a[:self.n]


#: The package that ships the 68-point model, and the model's file name in it.
MODEL_PACKAGE, MODEL_FILE = "face_recognition_models", "shape_predictor_68_face_landmarks.dat"


def predictor_model_path() -> Path:
    """The installed ``shape_predictor_68_face_landmarks.dat`` of ``face_recognition_models``.

    Found without importing the package (its ``__init__`` imports ``pkg_resources``, absent from
    Python 3.12+ virtual environments): first beside the package as the import system would find it
    (``importlib.util.find_spec``, which does not run the package's code; instant), else among the files its
    distribution records (``importlib.metadata``, which reads its whole RECORD: up to a second).

    Raises
    ------
    MissingExtraError
        If the package is not installed or has no model file (names the extra to install).
    """
    spec = importlib.util.find_spec(MODEL_PACKAGE)
    for folder in (spec.submodule_search_locations or []) if spec else []:
        path = Path(folder) / "models" / MODEL_FILE
        if path.is_file():
            return path
    try:
        files = importlib.metadata.files(MODEL_PACKAGE) or []
    except importlib.metadata.PackageNotFoundError:
        files = []
    for f in files:
        if f.name == MODEL_FILE and Path(f.locate()).is_file():
            return Path(f.locate())
    what = f"{MODEL_PACKAGE} is not installed" if spec is None else f"{MODEL_PACKAGE} has no {MODEL_FILE}"
    raise MissingExtraError(f"the landmark detector needs its model ({what}): {INSTALL_HINT}")


def detector_installed() -> bool:
    """Whether the optional extra ``detect`` is usable: dlib importable and the model file installed."""
    if importlib.util.find_spec("dlib") is None:
        return False
    try:
        predictor_model_path()
    except MissingExtraError:
        return False
    return True


class Detector:
    """dlib's frontal face detector and 68-point shape predictor, loaded from installed packages.

    Parameters
    ----------
    upsample : int
        Times the frame is upsampled before face detection when no face is found at its size
        (HOG finds faces of about 80 pixels and up).
    faces_file : path-like, optional
        The frontal face detector saved by dlib (``fhog_object_detector.save``;
        :func:`retarget_cli.io.face_detector.face_detector_file` keeps one in the user's cache): loaded in
        milliseconds instead of rebuilt from dlib's compiled-in copy (seconds). A file dlib cannot read is
        logged and the copy is used.

    Raises
    ------
    MissingExtraError
        If dlib or the model package is not installed (names the extra to install).
    """

    n_points = 68

    def __init__(self, upsample: int = 1, faces_file=None):
        try:
            import dlib
        except ImportError as exc:
            raise MissingExtraError(f"the landmark detector needs {exc.name or 'dlib'}: {INSTALL_HINT}") from None
        self._dlib = dlib
        self.upsample = int(upsample)
        self.model_path = predictor_model_path()
        self.faces = None
        if faces_file is not None:
            try:
                self.faces = dlib.fhog_object_detector(str(faces_file))
            except RuntimeError as exc:
                log.warning("%s: not a face detector dlib can read (%s); using dlib's own", faces_file,
                            (str(exc).strip().splitlines() or ["RuntimeError"])[0])
        if self.faces is None:
            self.faces = dlib.get_frontal_face_detector()
        try:
            self.predictor = dlib.shape_predictor(str(self.model_path))
        except RuntimeError as exc:  # dlib's deserialize error on a truncated or foreign file
            why = (str(exc).strip().splitlines() or ["RuntimeError"])[0]
            raise MissingExtraError(f"{self.model_path}: dlib could not load the landmark model ({why}); "
                                    f"reinstall: {INSTALL_HINT}") from None

    def detect(self, gray) -> np.ndarray:
        """Face boxes ``(K, 4)`` as ``[left, top, width, height]`` in pixels, strongest first."""
        gray = np.ascontiguousarray(gray)
        for up in range(self.upsample + 1):
            rects, scores, _ = self.faces.run(gray, up, 0.0)
            if len(rects):
                order = np.argsort(-np.asarray(scores), kind="stable")
                return np.array([[rects[i].left(), rects[i].top(), rects[i].width(), rects[i].height()]
                                 for i in order], np.float64)
        return np.zeros((0, 4))

    @staticmethod
    def pixel_box(box) -> tuple[int, int, int, int]:
        """The whole-pixel box ``(left, top, w, h)`` the predictor fits for *box* ``[left, top, w, h]``: two
        boxes with the same pixel box give the same landmarks on the same frame."""
        x, y, w, h = (int(round(v)) for v in box)
        return x, y, max(w, 1), max(h, 1)

    def landmarks(self, gray, box) -> np.ndarray:
        """The 68 landmarks ``(68, 2)`` (0-based pixel centres) of the face in *box* ``[left, top, w, h]``."""
        x, y, w, h = self.pixel_box(box)
        rect = self._dlib.rectangle(x, y, x + w - 1, y + h - 1)
        shape = self.predictor(np.ascontiguousarray(gray), rect)
        return np.array([[p.x, p.y] for p in shape.parts()], np.float64)


def _gray(frame) -> np.ndarray:
    import cv2

    frame = np.asarray(frame)
    if frame.ndim == 3:
        frame = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    if frame.dtype != np.uint8:
        raise ShapeError(f"frames: expected uint8 images, got {frame.dtype}")
    return frame


def choose_face(boxes, previous=None) -> int | None:
    """Index of the face to follow among *boxes* ``(K, 4)``: the largest, or the one nearest *previous*.

    Nearest means the smallest centre distance to the *previous* box ``[left, top, w, h]``;
    None when *boxes* is empty.
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    if not len(boxes):
        return None
    if previous is None:
        return int(np.argmax(boxes[:, 2] * boxes[:, 3]))
    p = np.asarray(previous, np.float64)
    d = np.linalg.norm(boxes[:, :2] + boxes[:, 2:] / 2 - (p[:2] + p[2:] / 2), axis=1)
    return int(np.argmin(d))


def _frame_of(P) -> tuple[np.ndarray, float, np.ndarray]:
    """Centre, eye-corner span and rotation (2, 2) (eye line to x) of the landmarks *P* (68, 2)."""
    c = P[list(BOX_POINTS)].mean(0)
    d = (P[42] + P[45]) / 2 - (P[36] + P[39]) / 2
    s = float(np.hypot(*d))
    if s < 1e-6:
        return c, 1e-6, np.eye(2)
    u = d / s
    return c, s, np.array([[u[0], -u[1]], [u[1], u[0]]])


def calibrate_box(points, box) -> tuple[float, float, float]:
    """The detector *box* ``[left, top, w, h]`` relative to the landmarks *points* (68, 2).

    Returns
    -------
    (ox, oy, side) : offset of the box centre along and across the eye line and the box side,
        in eye-corner spans (see :func:`box_from_points`).
    """
    c, s, R = _frame_of(np.asarray(points, np.float64))
    box = np.asarray(box, np.float64)
    o = R.T @ (box[:2] + box[2:] / 2 - c) / s
    return float(o[0]), float(o[1]), float(box[2:].mean() / s)


def box_from_points(points, calibration=DEFAULT_BOX) -> np.ndarray:
    """Square face box ``[left, top, w, h]`` for the landmarks *points* (68, 2), framed like a detection.

    The inverse of :func:`calibrate_box`: centre ``c + s R (ox, oy)`` and side
    ``side * s``, with ``c`` the mean of :data:`BOX_POINTS`, ``s`` the
    eye-corner span and ``R`` the rotation of the eye line.
    """
    ox, oy, side = calibration
    c, s, R = _frame_of(np.asarray(points, np.float64))
    centre = c + s * (R @ np.array([ox, oy]))
    w = side * s
    return np.array([centre[0] - w / 2, centre[1] - w / 2, w, w])


def detect_landmarks(gray, *, detector: Detector, previous=None, boxes=None):
    """Find a face on one frame and place its 68 landmarks.

    Parameters
    ----------
    gray : ndarray (H, W) or (H, W, 3), uint8
    detector : Detector
    previous : ndarray (4,), optional
        Box ``[left, top, w, h]`` to stay near among several faces (default: the largest face).
    boxes : ndarray (K, 4), optional
        The face detector's boxes on *gray* when already known (as :meth:`Detector.detect` returns them):
        the detector is not run again.

    Returns
    -------
    points : ndarray (68, 2) or None
        None when no face is found.
    box : ndarray (4,) or None
        The detected face box.
    """
    g = _gray(gray)
    boxes = detector.detect(g) if boxes is None else boxes
    i = choose_face(boxes, previous)
    if i is None:
        return None, None
    return detector.landmarks(g, boxes[i]), boxes[i]


@dataclass(frozen=True)
class FusionSettings:
    """Noise model of :class:`FlowFusion`, lengths in eye-corner spans ``s`` of the face.

    Attributes
    ----------
    sigma_detection : float
        Standard deviation of a detected point at confidence 1; a point of confidence ``c`` has
        variance ``(sigma_detection s)**2 / c``.
    sigma_motion : float
        Standard deviation per frame of the motion that optical flow does not explain.
    flow_gain : float
        The flow's forward-backward error ``e`` (pixels) adds ``(flow_gain e)**2`` to the motion variance.
    gate : float
        Innovation gate in standard deviations: a detection farther than this from the flow's
        prediction is a change of shape the flow missed (a blink, a lip closure), and the
        prediction's variance is raised to the innovation's so the detection is followed.
    lid_lip_motion : float
        *sigma_motion* of the eye and inner-lip points (:data:`LID_LIP_POINTS`), which lean on
        the detections: flow there follows the skin under a closing lid, not its edge.
    """

    sigma_detection: float = 0.012
    sigma_motion: float = 0.01
    flow_gain: float = 1.0
    gate: float = 3.0
    lid_lip_motion: float = 0.1


#: The eyes' and inner lips' points (0-based Multi-PIE ids 36-47, 60-67): lids close over the eye and
#: lips over the mouth, where optical flow follows the skin's texture rather than the edge, so these
#: points lean on the detections (blinks keep the detector's amplitude; the corners move with the lids
#: so the measured openings stay consistent). Chosen on the shared clips: see bench/track_real.py.
LID_LIP_POINTS = tuple(range(36, 48)) + tuple(range(60, 68))


#: ``downscale="auto"``: frames are reduced by the largest whole factor ``n`` that keeps the face's eye-corner span
#: at least this many pixels (``n = floor(span / AUTO_SPAN)``, at least 1). The three shared clips at their own
#: size (512x512) have spans of 91 (d12), 118 (d9) and 131 (d3) pixels on their first frame, so they are tracked
#: at full resolution, and the same clips upscaled to 1920x1080 (spans 192-275) at a half (d9, d12) or a third (d3).
AUTO_SPAN = 90.0
#: ``downscale="auto"``: the first frame's face is looked for on the frame reduced by the whole factor that brings
#: its shorter side to at most this many pixels (the detector upsamples it once when it finds no face there).
PROBE_SIDE = 540


def auto_downscale(span: float, target: float = AUTO_SPAN) -> float:
    """The factor ``1 / n`` of ``downscale="auto"`` for a face of eye-corner span *span* pixels.

    ``n = max(1, floor(span / target))``: the largest whole reduction that keeps the span at least *target*
    pixels (a whole factor keeps area averaging exact and fast, and pixel centres map back exactly).
    """
    if not np.isfinite(span) or span <= 0:
        return 1.0
    return 1.0 / max(1, int(span // float(target)))


def _probe_scale(first, annotation, detector: Detector) -> tuple[float, np.ndarray | None]:
    """``downscale="auto"``: the factor for a take whose first frame is *first* (gray, full resolution).

    The eye-corner span comes from *annotation* (68, 2) when the first frame is annotated, else from the
    detector's fit on the frame reduced to at most :data:`PROBE_SIDE` pixels on its shorter side. Returns the
    factor (1.0 when no face is found) and the detector's boxes at that factor when the probe ran at it (so
    the first frame is not searched twice), else None.
    """
    if annotation is not None:
        return auto_downscale(_frame_of(np.asarray(annotation, np.float64))[1]), None
    k0 = 1.0 / max(1, min(first.shape[:2]) // PROBE_SIDE)
    g0 = _scaled(first, k0)
    boxes = detector.detect(g0)
    i = choose_face(boxes)
    if i is None:
        log.info("downscale auto: no face on the first frame; tracking at full resolution")
        return 1.0, None
    span = _frame_of(detector.landmarks(g0, boxes[i]))[1] / k0
    k = auto_downscale(span)
    log.info("downscale auto: eye-corner span %.0f px on the first frame; tracking at 1/%d", span, round(1 / k))
    return k, (boxes if k == k0 else None)


#: While no face is there (``gaps=True``), after *lost_frames* frames the whole-frame face detector runs on
#: every this-many-th frame only (and at a scene cut), so a long gap costs little.
SEARCH_EVERY = 5
#: A face whose landmarks' mean confidence is below this is not trusted (``gaps=True``): the frame is a gap of
#: reason "low confidence". On the three shared clips the lowest per-frame mean is 0.31 (d12; 0.66 on d9, 0.77 on d3).
MIN_FOUND_CONFIDENCE = 0.05

#: Variance standing for "no information" (finite so that gains stay defined).
_NO_INFORMATION = 1e12


class FlowFusion:
    """Per-point Kalman filter and Rauch-Tung-Striebel smoother joining detections and optical flow.

    Each landmark ``x_t`` (2,) follows the frame-to-frame motion that pyramidal
    Lucas-Kanade flow measures between consecutive frames, ``u_t``, plus white
    noise: ``x_t = x_{t-1} + u_t + w_t``, ``w_t ~ N(0, q_t I)``; the detector
    measures it, ``D_t = x_t + v_t``, ``v_t ~ N(0, r_t I)``. Per frame
    (:meth:`step`), the forward pass predicts ``x^-_t = x_{t-1} + u_t``,
    ``P^-_t = P_{t-1} + q_t``, and updates with the gain
    ``K = P^-_t / (P^-_t + r_t)``: ``x_t = x^-_t + K (D_t - x^-_t)``,
    ``P_t = (1 - K) P^-_t``. :meth:`smooth` runs the Rauch-Tung-Striebel
    backward pass of this model (transition identity):
    ``x^s_t = x_t + G_t (x^s_{t+1} - x^-_{t+1})``, ``G_t = P_t / P^-_{t+1}``.

    The detector's per-frame jitter is averaged away along the flow, the
    flow's drift is pulled back to the detections, and where a detection
    leaves the prediction by more than ``gate`` standard deviations (the flow
    lost an eyelid or a lip) the prediction's variance is raised to the
    innovation's, so the gain is close to 1 and the smoother does not blur
    across the event: eyelids close and lips part as the detector sees them.
    A point whose flow fails (forward-backward error infinite) moves with the
    median flow of the others and takes the detection as it is.

    Parameters
    ----------
    settings : FusionSettings, optional
    window, levels : int
        Lucas-Kanade window side and pyramid levels.
    """

    def __init__(self, settings: FusionSettings | None = None, *, window: int = 21, levels: int = 3,
                 capacity: int = 256):
        import cv2

        self.settings = settings or FusionSettings()
        self.window, self.levels = int(window), int(levels)
        self._lk = dict(winSize=(self.window, self.window), maxLevel=self.levels,
                        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01))
        self._g = None
        self._x = None
        self._P = None
        # the filter's per-frame state, in preallocated arrays (a segment's rows, not lists of per-frame arrays)
        self._capacity, self._xf = int(capacity), None
        self._pending = None  # (frame, future) of start_flow

    def start_flow(self, g, pool) -> None:
        """Begin the flow of the current estimate to the frame *g* on *pool* (a
        :class:`concurrent.futures.Executor`), for the :meth:`step` of *g* to take.

        OpenCV's Lucas-Kanade releases the GIL, so the flow runs on another core while the caller fits the
        frame's detection. The flow reads the state as it is now (the previous frame and estimate); the
        result is the one :meth:`step` would compute itself, whatever the timing. Nothing is started
        before the first frame of a track.
        """
        self._take_flow(None)
        self._pending = None if self._x is None else (g, pool.submit(self._flow, g, self._g, self._x))

    def _take_flow(self, g):
        """The flow :meth:`start_flow` began for *g*, or None; a flow begun is waited for even when not taken
        (none outlives its frame)."""
        pending, self._pending = self._pending, None
        if pending is None:
            return None
        if pending[1].cancelled():  # the pool was shut down before it ran (an error ended the take): not taken
            return None
        flow = pending[1].result()
        return flow if pending[0] is g else None

    def _flow(self, g, g_prev=None, x=None) -> tuple[np.ndarray, np.ndarray]:
        """Flow of the estimate *x* (L, 2) (default: the current one) from the frame *g_prev* (default: the
        previous one) to *g*.

        Returns the displacement (L, 2) and the motion variance ``q`` (L,). Both frames are cropped
        to the points' box (:class:`~retarget_cli.methods.tracking.lk._Box`), so the cost does not grow with
        the video's resolution.
        """

        x = self._x if x is None else x
        g_prev = self._g if g_prev is None else g_prev
        box = _Box(x, (g.shape[1], g.shape[0]), self.window, self.levels)
        moved, fb = box.flow(box.crop(g_prev), box.crop(g), x.astype(np.float32).reshape(-1, 1, 2), self._lk)
        ok = np.isfinite(fb)
        u = moved.reshape(-1, 2).astype(np.float64) - x
        if not ok.any():
            return np.zeros_like(x), np.full(len(x), _NO_INFORMATION)
        u[~ok] = np.median(u[ok], axis=0)
        _, span, _ = _frame_of(x)
        sigma = np.full(len(x), self.settings.sigma_motion)
        if len(x) == 68:
            sigma[list(LID_LIP_POINTS)] = self.settings.lid_lip_motion
        q = (sigma * span) ** 2 + (self.settings.flow_gain * np.where(ok, fb, 0.0)) ** 2
        return u, np.where(ok, q, _NO_INFORMATION)

    def step(self, g, detection, confidence, *, exact: bool = False, reset: bool = False) -> np.ndarray:
        """Filter one frame.

        Parameters
        ----------
        g : ndarray (H, W), uint8
            The frame the detection was made on.
        detection : ndarray (L, 2) or None
            Detected points; None when the frame has no face (the flow's prediction is kept).
        confidence : ndarray (L,) or None
            Per-point confidence in (0, 1] of *detection*.
        exact : bool
            The detection is an annotation: taken as it is.
        reset : bool
            The face was found afresh: forget the track (no flow from the previous frame).

        Returns
        -------
        ndarray (L, 2)
            The forward (causal) estimate of this frame.
        """
        st = self.settings
        flow = self._take_flow(g)
        if self._x is None or reset:
            if detection is None:
                raise ShapeError("fusion: the first frame of a track needs a detection")
            xp = np.asarray(detection, np.float64).copy()
            Pp = np.full(len(xp), _NO_INFORMATION)
        else:
            u, q = self._flow(g) if flow is None else flow
            xp, Pp = self._x + u, np.minimum(self._P + q, _NO_INFORMATION)
        if detection is None:
            x, P = xp, Pp
        else:
            D = np.asarray(detection, np.float64)
            _, span, _ = _frame_of(D)
            c = np.clip(np.asarray(confidence, np.float64), 1e-3, 1.0)
            r = np.full(len(D), 1e-12) if exact else (st.sigma_detection * span) ** 2 / c
            v = D - xp
            m = 0.5 * (v * v).sum(axis=1)  # per-axis squared innovation
            jump = m > st.gate ** 2 * (Pp + r)
            Pp = np.where(jump, np.maximum(Pp, m), Pp)
            K = Pp / (Pp + r)
            x, P = xp + K[:, None] * v, (1.0 - K) * Pp
        self._g, self._x, self._P = g, x, P
        if self._xf is None:
            L = len(x)
            self._xf, self._xp = _Rows((L, 2), self._capacity), _Rows((L, 2), self._capacity)
            self._Pf, self._Pp = _Rows((L,), self._capacity), _Rows((L,), self._capacity)
        self._xf.append(x)
        self._Pf.append(P)
        self._xp.append(xp)
        self._Pp.append(Pp)
        return x

    def __len__(self) -> int:
        """Frames filtered so far."""
        return 0 if self._xf is None else len(self._xf)

    def smooth(self) -> np.ndarray:
        """Rauch-Tung-Striebel estimates of every frame so far, shape (T, L, 2).

        The smoother runs in place over the forward estimates (no copy of the segment's state): call it once,
        when the segment ends; the fuser is spent after it.
        """
        self._take_flow(None)
        if self._xf is None:
            return np.zeros((0, 0, 2))
        xs, Pf, xp, Pp = self._xf.array, self._Pf.array, self._xp.array, self._Pp.array
        for t in range(len(xs) - 2, -1, -1):  # xs[t + 1] is already smoothed: the same arithmetic as into a copy
            G = Pf[t] / Pp[t + 1]
            xs[t] = xs[t] + G[:, None] * (xs[t + 1] - xp[t + 1])
        self._x = self._P = self._g = None
        return xs


def track_detect(frames: Iterable[np.ndarray], annotations=None, *, detector: Detector | None = None,
                 downscale: float | str = 1.0, tau: float = 0.05, max_jump: float = 0.5, max_disagreement: float = 0.08,
                 lost_frames: int = 25, fuse: bool = True, fusion: FusionSettings | None = None, progress=None,
                 gaps: bool = False, search_every: int = SEARCH_EVERY, min_confidence: float = MIN_FOUND_CONFIDENCE,
                 cuts: CutDetector | None = None, threads: bool = True, on_frame=None):
    """Landmarks on every frame by the pretrained detector, the face box following the previous frame.

    Per frame: the predictor fits the box of the previous frame's landmarks
    (:func:`box_from_points`, calibrated on the last detection), then fits
    again in the box of that fit (unless that box rounds to the same pixels:
    the fit would be the first again); the second fit is kept. The confidence of
    point ``i`` is ``exp(-d_i / (tau * s))`` with ``d_i`` the distance between
    the two fits and ``s`` the eye-corner span. The landmarks look lost when
    the median disagreement exceeds *max_disagreement* of ``s``, or the box
    moved by more than *max_jump* of its side or changed its size by more
    than that fraction; the face detector then runs on the whole frame (the
    face nearest the previous box), as on the first frame. A frame with no
    face keeps the previous landmarks (moved by the flow when *fuse*) with
    confidence 0. Annotated frames return their annotation with confidence 1
    and re-place the box. The confidences are the detector's, with or without
    fusion.

    Parameters
    ----------
    frames : iterable of ndarray (H, W) or (H, W, 3), uint8
    annotations : dict of int to ndarray (68, 2), optional
        Annotated frames by index in *frames* (0-based pixel centres).
    detector : Detector, optional
        Default: a new :class:`Detector`.
    downscale : float or "auto"
        Detect and fit on frames scaled by this factor (0 < downscale <= 1); coordinates stay at full resolution.
        ``"auto"``: ``1 / n`` for the face of the first frame (:func:`auto_downscale`: the largest whole ``n``
        keeping its eye-corner span at least :data:`AUTO_SPAN` pixels; found as :func:`_probe_scale` says).
    tau, max_jump, max_disagreement : float
    lost_frames : int
        Raise :class:`~retarget_cli.methods.tracking.lk.FaceLostError` after this many frames in a row without a face.
    fuse : bool
        Join the detections with optical flow (:class:`FlowFusion`: a Kalman filter along the
        flow and a Rauch-Tung-Striebel smoother over the take). False: the detections as they are,
        each frame on its own.
    fusion : FusionSettings, optional
        Noise model of the fusion.
    progress : callable, optional
        Called with the frame index after each frame.
    gaps : bool
        Keep tracking through frames without a face (a take with gaps): such a frame is marked not found,
        keeps the last found frame's landmarks with confidence 0, and the face is looked for again (the
        whole-frame detector on every frame for *lost_frames* frames, then on every *search_every*-th and
        at every scene cut); each run of found frames (a segment, split at scene cuts found by *cuts*) is
        fused and smoothed on its own. A face whose mean confidence is below *min_confidence* counts as
        not found. Returns a third value, the :class:`~retarget_cli.methods.gaps.Coverage`.
    search_every : int
    min_confidence : float
    cuts : CutDetector, optional
        Scene-cut test of ``gaps=True`` (default :class:`~retarget_cli.methods.gaps.CutDetector`).
    threads : bool
        Overlap the per-frame work on two worker threads (OpenCV releases the GIL): the next frame's
        grayscale, scaling and scene-cut thumbnail, and the fusion's optical flow while the shape predictor
        fits the frame. Each result is taken in frame order, so the output is the same as with False
        (everything in the caller's thread), whatever the timing.
    on_frame : callable, optional
        Called after each frame ``t`` as ``on_frame(t, gray, points)``: the frame in gray at full resolution
        (H, W), uint8, and its landmarks (68, 2) at full resolution as tracked up to that frame (the fusion's
        forward estimate, before the take is smoothed; a frame without a face: those it holds). The stage keeps
        the eyes' pixels with it for the gaze (no second decoding of the video).

    Returns
    -------
    points : ndarray (T, 68, 2), float64
    confidence : ndarray (T, 68), float64
        In [0, 1]; 0 where no face was found.
    coverage : Coverage
        With ``gaps=True`` only.

    Raises
    ------
    FaceLostError
        No face on the first frame (``frame`` 0, nothing tracked) or for *lost_frames* frames in a row;
        with ``gaps=True``, no face in any frame.
    """
    det = detector or Detector()
    hint = None
    capacity = operator.length_hint(frames, 0) or 256  # the take's frames, when the source knows them
    if isinstance(downscale, str):
        if downscale != "auto":
            raise ShapeError(f"downscale: expected a value in (0, 1] or 'auto', got {downscale!r}")
        frames = iter(frames)
        first = next(frames, None)
        if first is None:
            raise ShapeError("frames: the sequence is empty")
        ann0 = (annotations or {}).get(0)
        first = _gray(first)
        downscale, hint = _probe_scale(first, None if ann0 is None else np.asarray(ann0, np.float64), det)
        frames = itertools.chain([first], frames)
    ann = _checked_annotations(annotations, downscale)
    k = float(downscale)
    cuts = (cuts or CutDetector()) if gaps else None
    pool = ThreadPoolExecutor(2, thread_name_prefix="retarget-track") if threads else None
    track = _DetectTrack(det, ann, k, (lambda: FlowFusion(fusion, capacity=capacity)) if fuse else None, tau=tau,
                         max_jump=max_jump, max_disagreement=max_disagreement, lost_frames=lost_frames, gaps=gaps,
                         search_every=search_every, min_confidence=min_confidence, cuts=cuts, hint=hint,
                         capacity=capacity, pool=pool)
    try:
        for t, (g, feats, full) in enumerate(_prepared(frames, k, cuts, pool)):
            track.frame(t, g, feats)
            if on_frame is not None:
                on_frame(t, full, track.pts.array[-1])
            if progress is not None:
                progress(t)
        if not track.pts:
            raise ShapeError("frames: the sequence is empty")
        track.end_segment()  # while the pool lives: the last segment may wait for a flow begun on it
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
    if gaps and not any(track.found):
        raise FaceLostError(f"frame 0: no face found by the detector, nor in any of the {len(track.pts)} frames "
                            "of the take", 0, np.zeros((0, 68, 2)), np.zeros((0, 68)))
    out = track.points()  # the rows as the tracker stored them (a view, not a copy)
    for t in ann:  # annotated frames exactly as given
        if t < len(out):
            out[t] = ann[t]
    conf = track.conf.array
    np.clip(conf, 0, 1, out=conf)
    if not gaps:
        return out, conf
    return out, conf, Coverage(np.array(track.found, bool), np.array(track.status, np.int8),
                               np.array(track.cut, bool))


def _prepare_frame(frame, k: float, cuts: CutDetector | None):
    """A frame as :class:`_DetectTrack` takes it: grayscale at the detection scale *k* (H', W'), its
    scene-cut features (:meth:`~retarget_cli.methods.gaps.CutDetector.features`; None without *cuts*) and the
    frame in gray at full resolution (H, W)."""
    full = _gray(frame)
    g = _scaled(full, k)
    return g, (None if cuts is None else cuts.features(g)), full


def _prepared(frames, k: float, cuts: CutDetector | None, pool=None):
    """:func:`_prepare_frame` of each of *frames*, in order; with *pool* the next frame is prepared there while
    the caller works on the current one (one frame ahead)."""
    if pool is None:
        for frame in frames:
            yield _prepare_frame(frame, k, cuts)
        return
    it = iter(frames)
    ahead = None
    for frame in it:
        ahead = pool.submit(_prepare_frame, frame, k, cuts)
        break
    while ahead is not None:
        current, ahead = ahead.result(), None
        for frame in it:
            ahead = pool.submit(_prepare_frame, frame, k, cuts)
            break
        yield current


def _checked_annotations(annotations, downscale: float) -> dict[int, np.ndarray]:
    """*downscale* checked and the annotations of :func:`track_detect` as float arrays (68, 2) by frame."""
    if not 0 < downscale <= 1:
        raise ShapeError(f"downscale: expected a value in (0, 1], got {downscale}")
    ann = {int(t): np.asarray(P, np.float64) for t, P in (annotations or {}).items()}
    for t, P in ann.items():
        if P.shape != (68, 2):
            raise ShapeError(f"annotations: frame {t} has shape {P.shape}; the detector places (68, 2) points")
    return ann


class _DetectTrack:
    """State of :func:`track_detect` between frames (face box, frames without a face) and its per-frame step.

    Landmarks are at the detection scale *k* inside and at full resolution in
    :attr:`pts`; :attr:`conf` holds the confidences. *fusion* makes a new
    :class:`FlowFusion` (None: no fusion); each segment has its own, smoothed
    when the segment ends (:meth:`end_segment`). Other parameters as in
    :func:`track_detect`.
    """

    def __init__(self, det, ann, k, fusion, *, tau, max_jump, max_disagreement, lost_frames, gaps=False,
                 search_every=SEARCH_EVERY, min_confidence=MIN_FOUND_CONFIDENCE, cuts=None, hint=None, capacity=256,
                 pool=None):
        self.det, self.ann, self.k, self.fusion, self.pool = det, ann, k, fusion, pool
        self.hint = hint  # the face detector's boxes on the first frame at scale k, when already known
        self.tau, self.max_jump, self.max_disagreement, self.lost_frames = tau, max_jump, max_disagreement, lost_frames
        self.gaps, self.search_every, self.min_confidence, self.cuts = gaps, max(1, int(search_every)), \
            float(min_confidence), cuts
        self.calib, self.P_prev, self.box_prev, self.missing = DEFAULT_BOX, None, None, 0
        self.fuser, self.seg_start = (fusion() if fusion is not None else None), 0
        # each frame's landmarks and confidences in preallocated arrays (*capacity* frames, growing past them)
        self.pts, self.conf = _Rows((68, 2), capacity), _Rows((68,), capacity)
        self.found: list[bool] = []
        self.status: list[int] = []
        self.cut: list[bool] = []

    def frame(self, t: int, g, cut_features=None) -> None:
        """Landmarks of frame *t* (grayscale at the detection scale) appended to :attr:`pts` and :attr:`conf`;
        *cut_features*: the scene-cut test's features of *g* when already computed."""
        if t > 0:
            self.hint = None
        if self.fuser is not None and self.pool is not None:
            self.fuser.start_flow(g, self.pool)  # on another core while the predictor fits the frame
        cut = bool(self.cuts(g, cut_features)) and t > 0 if self.cuts is not None else False
        self.cut.append(cut)
        P, c, fresh, status = None, None, False, NO_FACE
        if t in self.ann:
            P, c, fresh = _to_scaled(self.ann[t], self.k), np.ones(68), True
        elif self.P_prev is not None and self.missing == 0 and not cut:
            P, c = self._follow(t, g)
        if P is None and self._search(cut):
            P, c = self._detect(g)
            fresh = True
        if P is not None and self.gaps and t not in self.ann and float(np.mean(c)) < self.min_confidence:
            log.debug("frame %d: landmarks of mean confidence %.3f not trusted", t, float(np.mean(c)))
            P, status = None, LOW_CONFIDENCE
        if P is None:
            self._no_face(t, g, status)
            return
        if self.gaps and (cut or self.missing) and t > 0:
            self.end_segment()  # a new segment: smoothed apart from the one before
        self.missing = 0
        self.P_prev, self.box_prev = P, box_from_points(P, self.calib)
        if self.fuser is not None:
            P = self.fuser.step(g, P, c, exact=t in self.ann, reset=fresh and t not in self.ann)
        self.pts.append(_from_scaled(P, self.k))
        self.conf.append(c)
        self.found.append(True)
        self.status.append(0)

    def _search(self, cut: bool) -> bool:
        """Whether to run the whole-frame face detector on this frame (always, unless a long gap goes on)."""
        if not self.gaps or cut or self.missing < self.lost_frames:
            return True
        return (self.missing - self.lost_frames) % self.search_every == 0

    def end_segment(self) -> None:
        """Smooth the segment that ends here (the frames fused since the last segment started) in place."""
        fuser = self.fuser
        if fuser is not None and len(fuser):
            n = len(fuser)
            found = self.seg_start + np.flatnonzero(self.found[self.seg_start:])
            pts = self.pts.array
            if len(found) == n:  # (without gaps every frame was fused, lost ones included: see _no_face)
                pts[found] = _from_scaled(fuser.smooth(), self.k)
            else:
                pts[self.seg_start:] = _from_scaled(fuser.smooth(), self.k)
            self.fuser = self.fusion()
        self.seg_start = len(self.pts)

    def points(self) -> np.ndarray:
        """Every frame's landmarks (T, 68, 2); a frame without a face holds the last found frame's (the first's
        before any)."""
        out = self.pts.array
        if self.gaps:
            found = np.array(self.found, bool)
            last = np.maximum.accumulate(np.where(found, np.arange(len(out)), -1))
            first = int(np.argmax(found))
            src = np.where(last >= 0, last, first)
            gap = np.flatnonzero(src != np.arange(len(out)))
            out[gap] = out[src[gap]]  # in place: the rows copied from are found ones, which this does not change
        return out
    def _follow(self, t: int, g):
        """Fit twice from the previous frame's box: (points, confidence), or (None, None) when they look lost."""
        det, calib = self.det, self.calib
        box = box_from_points(self.P_prev, calib)
        first = det.landmarks(g, box)
        box1 = box_from_points(first, calib)
        # the second fit in the same whole-pixel box would repeat the first (2-7 % of the frames of d3, d9, d12)
        second = first.copy() if det.pixel_box(box1) == det.pixel_box(box) else det.landmarks(g, box1)
        _, s, _ = _frame_of(second)
        d = np.linalg.norm(second - first, axis=1)
        jump = np.linalg.norm((box1[:2] + box1[2:] / 2) - (box[:2] + box[2:] / 2)) / box[2]
        grow = abs(np.log(box1[2] / box[2]))
        if np.median(d) <= self.max_disagreement * s and jump <= self.max_jump and grow <= np.log1p(self.max_jump):
            return second, np.exp(-d / (self.tau * s))
        log.debug("frame %d: landmarks look lost (disagreement %.3f, jump %.2f); detecting the face",
                  t, np.median(d) / s, jump)
        return None, None

    def _detect(self, g):
        """The face detector on the whole frame (and the box recalibrated): (points, confidence), or (None, None)."""
        det = self.det
        hint, self.hint = self.hint, None
        found, fbox = detect_landmarks(g, detector=det, previous=self.box_prev, boxes=hint)
        if found is None:
            return None, None
        self.calib = calibrate_box(found, fbox)
        box = box_from_points(found, self.calib)  # (fbox again, to rounding: then the fit is found's own)
        again = found.copy() if det.pixel_box(box) == det.pixel_box(fbox) else det.landmarks(g, box)
        _, s, _ = _frame_of(again)
        return found, np.exp(-np.linalg.norm(again - found, axis=1) / (self.tau * s))

    def _no_face(self, t: int, g, status: int = NO_FACE) -> None:
        """Frame *t* has no face: keep the previous landmarks with confidence 0, or raise :class:`FaceLostError`
        (without *gaps*)."""
        self.found.append(False)
        self.status.append(status)
        if self.gaps:
            self.missing += 1
            self.pts.append(self.pts.array[-1] if len(self.pts) else np.zeros((68, 2)))
            self.conf.append(np.zeros(68))
            return
        if t == 0:
            raise FaceLostError("frame 0: no face found by the detector (annotate this frame by hand with --init, "
                                "or start at another frame)", 0, np.zeros((0, 68, 2)),
                                np.zeros((0, 68)))
        self.missing += 1
        if self.missing >= self.lost_frames:
            f0 = t - self.missing + 1
            raise FaceLostError(f"the face was lost from frame {f0}: no face found for {self.missing} frames "
                                f"in a row", f0, self.pts.array[:f0].copy(), self.conf.array[:f0].copy())
        fuser = self.fuser
        self.pts.append(self.pts.array[-1] if fuser is None else _from_scaled(fuser.step(g, None, None, exact=False), self.k))
        self.conf.append(np.zeros(68))




def eye_opening(points) -> np.ndarray:
    """Mean lid gap over eye width of both eyes, per frame: points (T, 68, 2) -> (T,).

    Left eye: ``(|p37 - p41| + |p38 - p40|) / 2 / |p36 - p39|`` (0-based ids), right eye the same with 42-47.
    """
    P = np.asarray(points, np.float64)
    n = np.linalg.norm

    def one(a, b, c, d, e, f):
        return (n(P[..., b, :] - P[..., f, :], axis=-1) + n(P[..., c, :] - P[..., e, :], axis=-1)) / 2 / \
            n(P[..., a, :] - P[..., d, :], axis=-1)

    return (one(36, 37, 38, 39, 40, 41) + one(42, 43, 44, 45, 46, 47)) / 2


def mouth_opening(points) -> np.ndarray:
    """Inner-lip gap over inner mouth width, per frame: ``|p62 - p66| / |p60 - p64|`` (0-based ids); (T, 68, 2) -> (T,)."""
    P = np.asarray(points, np.float64)
    return np.linalg.norm(P[..., 62, :] - P[..., 66, :], axis=-1) / np.linalg.norm(P[..., 60, :] - P[..., 64, :],
                                                                                      axis=-1)
