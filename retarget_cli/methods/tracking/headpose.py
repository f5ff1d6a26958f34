"""Head rotation in 3D: per-frame yaw, pitch and roll from 68 tracked landmarks against a 3D face.

Chuang & Bregler (2002, §3) separate the head's rigid motion from the
expression; :mod:`.head` does it with a 2D similarity (roll, scale,
translation). A head that turns out of the image plane needs the 3D rotation:
each frame's pose is the rotation ``R`` and translation ``t`` that project a
3D face ``X`` onto the tracked points, ``x ≈ π(K (R X + t))`` with a pinhole
camera ``K`` (the perspective-n-point problem, solved by OpenCV's
``solvePnP``: an EPnP start, Lepetit et al. 2009, refined by Levenberg–Marquardt
on the reprojection error), fitted on points that expressions move little (the
nose, the eye corners), with each frame started from the previous pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import ShapeError

#: A generic 3D face, the 68 Multi-PIE landmarks (0-based) in centimetres, in OpenCV camera axes for a face
#: looking into the camera (x to the image's right = the actor's left, y down, z away from the camera), the
#: eye corners' centre at the origin. Taken from the ICT FaceKit's neutral (MIT licence, sample_data/ict):
#: its 68 landmark vertices (rig.yaml ``landmarks:``).
FACE_68 = np.array([
    (-7.36, -0.33, 5.24), (-7.28, 1.85, 4.97), (-6.94, 3.80, 4.37), (-6.56, 5.70, 3.73),
    (-5.72, 7.83, 2.77), (-4.30, 9.55, 1.55), (-3.05, 10.25, 0.13), (-1.54, 10.60, -1.37),
    (-0.00, 10.91, -1.53), (1.54, 10.60, -1.37), (3.05, 10.25, 0.13), (4.30, 9.55, 1.55),
    (5.72, 7.83, 2.77), (6.56, 5.70, 3.73), (6.94, 3.80, 4.37), (7.28, 1.85, 4.97),
    (7.36, -0.33, 5.24), (-5.82, -1.86, 0.99), (-4.93, -2.63, -0.09), (-3.79, -2.91, -0.93),
    (-2.41, -2.85, -1.58), (-1.17, -2.57, -1.83), (1.17, -2.57, -1.83), (2.41, -2.85, -1.58),
    (3.79, -2.91, -0.93), (4.93, -2.63, -0.09), (5.82, -1.86, 0.99), (-0.00, -0.40, -1.84),
    (-0.00, 0.71, -2.62), (-0.00, 1.73, -3.41), (-0.00, 2.94, -4.17), (-1.25, 4.49, -1.97),
    (-0.60, 4.48, -2.52), (-0.00, 4.55, -2.67), (0.60, 4.48, -2.52), (1.25, 4.49, -1.97),
    (-4.46, -0.09, 0.30), (-3.87, -0.53, -0.46), (-2.78, -0.59, -0.63), (-1.84, 0.09, -0.30),
    (-2.73, 0.26, -0.51), (-3.86, 0.27, -0.33), (1.84, 0.09, -0.30), (2.78, -0.59, -0.63),
    (3.87, -0.53, -0.46), (4.46, -0.09, 0.30), (3.86, 0.27, -0.33), (2.73, 0.26, -0.51),
    (-2.53, 6.86, -1.29), (-1.70, 6.12, -2.32), (-0.73, 5.76, -2.83), (-0.00, 5.82, -2.94),
    (0.73, 5.76, -2.83), (1.70, 6.12, -2.32), (2.53, 6.86, -1.29), (1.80, 7.40, -2.00),
    (1.03, 7.64, -2.49), (-0.00, 7.72, -2.65), (-1.03, 7.64, -2.49), (-1.80, 7.40, -2.00),
    (-2.21, 6.83, -1.23), (-1.00, 6.64, -2.19), (-0.00, 6.67, -2.38), (1.00, 6.64, -2.19),
    (2.21, 6.83, -1.23), (1.07, 6.72, -2.14), (-0.00, 6.74, -2.35), (-1.07, 6.72, -2.14),
])

#: Landmarks the pose is fitted on: the nose bridge and base (27-35) and the eye corners (36, 39, 42, 45);
#: expressions move them least.
POSE_POINTS_68 = (27, 28, 29, 30, 31, 32, 33, 34, 35, 36, 39, 42, 45)


@dataclass(frozen=True)
class HeadPose:
    """Per-frame 3D head pose.

    Attributes
    ----------
    angles : ndarray (T, 3), float64
        ``yaw, pitch, roll`` in degrees, 0 for a face looking into the camera: yaw > 0 when the actor turns
        to their left (the nose moves to the image's right), pitch > 0 when the actor looks up, roll > 0 when
        the head tilts toward the actor's left shoulder (clockwise in the image). ``R = R_y(yaw) R_x(pitch)
        R_z(roll)`` in camera axes (signs as stated above).
    translation : ndarray (T, 3), float64
        The face's origin (between the eye corners) in camera axes, in the 3D face's units (cm).
    error : ndarray (T,), float64
        Root-mean-square reprojection error of the fitted points, pixels.
    """

    angles: np.ndarray
    translation: np.ndarray
    error: np.ndarray


def camera_matrix(frame_size, focal: float | None = None) -> np.ndarray:
    """A pinhole camera for a frame of *frame_size* ``(width, height)``: principal point at the centre.

    *focal* in pixels defaults to the frame's larger side (a horizontal field of view of about 53°, that
    of a typical phone or webcam); the pose's angles depend little on it.
    """
    w, h = (float(v) for v in frame_size)
    f = float(focal) if focal else max(w, h)
    return np.array([[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]])


def rotation_angles(R: np.ndarray) -> np.ndarray:
    """``(yaw, pitch, roll)`` in degrees of rotation matrices ``R = R_y(a) R_x(b) R_z(c)`` (see :class:`HeadPose`).

    Parameters
    ----------
    R : ndarray (..., 3, 3)

    Returns
    -------
    ndarray (..., 3)
    """
    R = np.asarray(R, dtype=np.float64)
    pitch = np.arcsin(np.clip(-R[..., 1, 2], -1.0, 1.0))
    yaw = np.arctan2(R[..., 0, 2], R[..., 2, 2])
    roll = np.arctan2(R[..., 1, 0], R[..., 1, 1])
    # camera y points down: a face turning to the actor's left rotates by -a about y, looking up by -b about x
    return np.degrees(np.stack([-yaw, -pitch, roll], axis=-1))


def angles_rotation(angles) -> np.ndarray:
    """The rotation matrices (..., 3, 3) of ``(yaw, pitch, roll)`` degrees: the inverse of :func:`rotation_angles`."""
    a = np.radians(np.asarray(angles, dtype=np.float64))
    y, p, r = -a[..., 0], -a[..., 1], a[..., 2]
    cy, sy, cp, sp, cr, sr = np.cos(y), np.sin(y), np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    one, zero = np.ones_like(y), np.zeros_like(y)
    Ry = np.stack([np.stack([cy, zero, sy], -1), np.stack([zero, one, zero], -1), np.stack([-sy, zero, cy], -1)], -2)
    Rx = np.stack([np.stack([one, zero, zero], -1), np.stack([zero, cp, -sp], -1), np.stack([zero, sp, cp], -1)], -2)
    Rz = np.stack([np.stack([cr, -sr, zero], -1), np.stack([sr, cr, zero], -1), np.stack([zero, zero, one], -1)], -2)
    return Ry @ Rx @ Rz


def sight_rotation(translation) -> np.ndarray:
    """The camera-axes rotation (..., 3, 3) of a face at *translation* (..., 3) that looks into the lens.

    It turns the 3D face's depth axis (+z, away from the camera for a face looking into it on the optical
    axis) onto the line of sight from the camera to the face: ``angles_rotation((−atan2(x, z), asin(y/|t|), 0))``.
    """
    t = np.asarray(translation, dtype=np.float64)
    u = t / np.maximum(np.linalg.norm(t, axis=-1, keepdims=True), 1e-300)
    a = np.stack([-np.degrees(np.arctan2(u[..., 0], u[..., 2])), np.degrees(np.arcsin(np.clip(u[..., 1], -1, 1))),
                  np.zeros(u.shape[:-1])], axis=-1)
    return angles_rotation(a)


def sight_angles(angles, translation) -> np.ndarray:
    """Head angles (..., 3) relative to the line of sight, from :func:`head_pose`'s camera-relative *angles*.

    ``R_sight = S(t)ᵀ R_camera`` with ``S`` of :func:`sight_rotation`: 0 for a face that looks into the lens
    wherever it is in the picture, as a viewer (and a 2D measure such as the nose's offset between the eye
    corners) sees it. A face beside the optical axis that looks into the lens is turned in camera axes by
    ``atan(x / z)`` (14° at a third of a 512-pixel frame's width from its centre, the camera's focal the
    frame's side); MediaPipe Face Landmarker's facial transformation matrix reports the rotation as seen
    (bench/gaze_head.py: d12's yaw r against it 0.16 camera-relative, 0.88 relative to the line of sight).
    """
    R = np.swapaxes(sight_rotation(translation), -1, -2) @ angles_rotation(angles)
    return rotation_angles(R)


def camera_angles(angles, translation) -> np.ndarray:
    """The inverse of :func:`sight_angles`: camera-relative angles (..., 3) of line-of-sight *angles*."""
    return rotation_angles(sight_rotation(translation) @ angles_rotation(angles))


def head_pose(points, frame_size, *, confidence=None, model=None, pose_points=POSE_POINTS_68,
              focal: float | None = None) -> HeadPose:
    """The 3D head pose of every frame from its 2D landmarks (perspective-n-point on a 3D face).

    Parameters
    ----------
    points : ndarray (T, 68, 2)
        Tracked landmarks, image pixels.
    frame_size : (int, int)
        ``(width, height)`` of the frames.
    confidence : ndarray (T, 68), optional
        Points below 0.1 are left out of a frame's fit (a frame with fewer than 6 left keeps the previous pose).
    model : ndarray (68, 3) or (T, 68, 3), optional
        The 3D face (default :data:`FACE_68`); the rig's own landmark vertices, in camera axes, when it has them;
        one face per frame (the rig deformed by each frame's fitted sliders: the joint pose and expression fit
        of :func:`~retarget_cli.stages.auto_pose.frontal_landmarks`).
    pose_points : sequence of int
        Landmarks fitted.
    focal : float, optional
        Focal length in pixels (see :func:`camera_matrix`).

    Returns
    -------
    HeadPose
    """
    import cv2

    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (68, 2):
        raise ShapeError(f"points: expected shape (T, 68, 2), got {P.shape}")
    X = _models(model, len(P))
    idx = np.asarray(pose_points, dtype=int)
    K = camera_matrix(frame_size, focal)
    C = None if confidence is None else np.asarray(confidence, dtype=np.float64)
    T = len(P)
    angles, trans, err = np.zeros((T, 3)), np.zeros((T, 3)), np.full(T, np.nan)
    rvec = tvec = None
    for t in range(T):
        use = idx if C is None else idx[C[t, idx] >= 0.1]
        use = use[np.all(np.isfinite(P[t, use]), axis=1)]
        if len(use) >= 6:
            obj, img = X[t, use], P[t, use]
            if rvec is None:
                ok, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_EPNP)
                if not ok:
                    rvec = tvec = None
            if rvec is not None:
                ok, r, tv = cv2.solvePnP(obj, img, K, None, rvec.copy(), tvec.copy(), useExtrinsicGuess=True,
                                         flags=cv2.SOLVEPNP_ITERATIVE)
                if ok and tv[2, 0] > 0:
                    rvec, tvec = r, tv
                proj = cv2.projectPoints(obj, rvec, tvec, K, None)[0].reshape(-1, 2)
                err[t] = float(np.sqrt(np.mean(np.sum((proj - img) ** 2, axis=1))))
        if rvec is not None:
            angles[t] = rotation_angles(cv2.Rodrigues(rvec)[0])
            trans[t] = tvec.ravel()
        elif t:
            angles[t], trans[t] = angles[t - 1], trans[t - 1]
    return HeadPose(angles, trans, err)


def _models(model, T: int) -> np.ndarray:
    """The 3D face of each of *T* frames (T, 68, 3): *model* (68, 3) repeated (a view), or (T, 68, 3) as given."""
    X = np.asarray(FACE_68 if model is None else model, dtype=np.float64)
    if X.shape == (68, 3):
        return np.broadcast_to(X, (T, 68, 3))
    if X.shape != (T, 68, 3):
        raise ShapeError(f"model: expected shape (68, 3) or ({T}, 68, 3), got {X.shape}")
    return X


#: Frontalization modes of :func:`frontalize`.
FRONTAL_MODES = ("backproject", "subtract")


def _project_cam(Y, K) -> np.ndarray:
    """Pinhole projection of camera-axes points ``Y`` (..., 3) through ``K``: pixels (..., 2)."""
    return Y[..., :2] / Y[..., 2:3] * K[[0, 1], [0, 1]] + K[:2, 2]


def _jacobian(Y, K) -> np.ndarray:
    """d pixel / d camera point of :func:`_project_cam` at ``Y`` (..., 3): (..., 2, 3)."""
    z = Y[..., 2]
    f = K[[0, 1], [0, 1]]
    J = np.zeros(Y.shape[:-1] + (2, 3))
    J[..., 0, 0] = f[0] / z
    J[..., 1, 1] = f[1] / z
    J[..., 0, 2] = -f[0] * Y[..., 0] / z ** 2
    J[..., 1, 2] = -f[1] * Y[..., 1] / z ** 2
    return J


def frontalize(points, pose: HeadPose, frame_size, *, model=None, focal: float | None = None,
               mode: str = "backproject", min_cos: float = 0.2, rest=None) -> np.ndarray:
    """The landmarks as a face looking into the camera would show them: the head's 3D rotation removed.

    Chuang & Bregler (2002, §3) remove the head's rigid motion before the expression is decomposed; the
    2D similarity of :mod:`.head` removes roll, scale and translation but reads a turn of the head out of
    the image plane as expression. Per frame ``t``, with the pose ``(R_t, t_t)`` of :func:`head_pose` and
    the 3D face ``X``, each landmark's residual ``d = x − π(R_t X + t_t)`` (the expression, and the actor's
    face where it differs from the model) is carried to the frontal pose ``(S_t, t_t)``, the face at the same
    place looking into the lens (:func:`sight_rotation`):

    - ``mode="backproject"`` (default): the residual is taken to be a displacement ``D = (dx, dy, 0)`` in
      the face's own plane (an expression moves the skin along the face far more than in depth), solved
      from ``d = J(R_t X + t_t) R_t D`` (``J`` the projection's 2×3 Jacobian) and shown frontally,
      ``x' = π(S_t X + t_t) + J(S_t X + t_t) S_t D``. It undoes the foreshortening of a turned face (a mouth corner's
      sideways motion reads ``cos(yaw)`` smaller at a yaw), which plain subtraction keeps. Where the face's
      plane is seen at a grazing angle (``|det(J R_t[:, :2])|`` below *min_cos* times its frontal value),
      the residual is subtracted as in ``subtract``;
    - ``mode="subtract"``: ``x' = x − π(R_t X + t_t) + π(S_t X + t_t)``, the rigid rotation's projected effect
      replaced by the frontal one, the residual kept as seen.

    With *rest* (a rotation relative to the line of sight, :func:`rest_rotation`), the frontal pose is
    ``(S_t A, t_t)`` instead: each frame shown as turned as the rest frames are (``A``), so that only the
    change of pose from the rest frames is removed, which is all a delta fit against those frames reads
    (Lewis et al. 2005 §3); a fixed offset between the fitted pose and the actor's (a 3D face that is not the
    actor's reads a few degrees of pitch) then moves no landmark.

    The translation is kept, so :func:`.head.estimate_head` on the result still removes scale and
    translation (and the little roll left).

    Parameters
    ----------
    points : ndarray (T, 68, 2)
        Landmarks in image pixels (those the pose was fitted on).
    pose : HeadPose
        Their :func:`head_pose` (camera-relative angles (T, 3) degrees, translation (T, 3) in the model's units).
    frame_size : (int, int)
        ``(width, height)``.
    model : ndarray (68, 3) or (T, 68, 3), optional
        The 3D face the pose was fitted with (default :data:`FACE_68`), camera axes; one per frame for a pose
        fitted on faces deformed by the expression (:func:`head_pose`).
    focal : float, optional
        The focal length the pose was fitted with (:func:`camera_matrix`).
    mode : {"backproject", "subtract"}
    min_cos : float
        The grazing-angle limit of ``backproject``.
    rest : ndarray (3, 3), optional
        The rest frames' rotation relative to the line of sight (default: the identity, looking into the lens).

    Returns
    -------
    ndarray (T, 68, 2), float64
    """
    if mode not in FRONTAL_MODES:
        raise ShapeError(f"mode: expected one of {', '.join(FRONTAL_MODES)}, got {mode!r}")
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (68, 2):
        raise ShapeError(f"points: expected shape (T, 68, 2), got {P.shape}")
    T = len(P)
    X = _models(model, T)
    if pose.angles.shape != (T, 3) or pose.translation.shape != (T, 3):
        raise ShapeError(f"pose: expected angles and translation of shape ({T}, 3), got {pose.angles.shape} and "
                         f"{pose.translation.shape}")
    K = camera_matrix(frame_size, focal)
    R = angles_rotation(pose.angles)                                   # (T, 3, 3)
    tr = np.asarray(pose.translation, dtype=np.float64)
    Yt = np.einsum("tij,tlj->tli", R, X) + tr[:, None]                 # posed model, camera axes (T, 68, 3)
    S = sight_rotation(tr)                                             # (T, 3, 3): looking into the lens
    if rest is not None:
        A = np.asarray(rest, dtype=np.float64)
        if A.shape != (3, 3):
            raise ShapeError(f"rest: expected a rotation of shape (3, 3), got {A.shape}")
        S = S @ A                                                      # as turned as the rest frames
    Yf = np.einsum("tij,tlj->tli", S, X) + tr[:, None]                 # the same face looking into the camera
    ok = (Yt[..., 2] > 0).all(1) & (Yf[..., 2] > 0).all(1) & np.isfinite(P).all((1, 2))
    out = P.copy()
    if not ok.any():
        return out
    Yt, Yf, R, S, Pk = Yt[ok], Yf[ok], R[ok], S[ok], P[ok]
    d = Pk - _project_cam(Yt, K)                                       # residual: expression + identity
    front = _project_cam(Yf, K)
    if mode == "subtract":
        out[ok] = front + d
        return out
    M = np.einsum("tlij,tjk->tlik", _jacobian(Yt, K), R[:, :, :2])     # (T', 68, 2, 2): in-plane D -> pixels
    M0 = np.einsum("tlij,tjk->tlik", _jacobian(Yf, K), S[:, :, :2])   # the same, frontal
    det, det0 = np.linalg.det(M), np.linalg.det(M0)
    good = np.abs(det) >= min_cos * np.abs(det0)
    Msafe = np.where(good[..., None, None], M, M0)
    D = np.linalg.solve(Msafe, d[..., None])[..., 0]                   # (T', 68, 2) face-plane displacement
    moved = front + np.einsum("tlij,tlj->tli", M0, D)
    out[ok] = np.where(good[..., None], moved, front + d)
    return out


def rest_rotation(pose: HeadPose, frames) -> np.ndarray:
    """The mean rotation (3, 3) of *frames* (rows of *pose*) relative to the line of sight: :func:`frontalize`'s *rest*.

    Each frame's ``S(t_t)ᵀ R_t`` (:func:`sight_rotation`), averaged as matrices and projected back onto the
    rotations (the chordal L2 mean: the nearest rotation to the mean matrix, by SVD).

    Parameters
    ----------
    pose : HeadPose
        Camera-relative angles (T, 3) and translations (T, 3).
    frames : sequence of int
        Rows of the rest frames.

    Returns
    -------
    ndarray (3, 3)
    """
    rows = np.asarray(frames, dtype=np.int64).reshape(-1)
    if rows.size == 0:
        raise ShapeError("frames: expected at least one rest frame")
    Rs = np.swapaxes(sight_rotation(pose.translation[rows]), -1, -2) @ angles_rotation(pose.angles[rows])
    U, _, Vt = np.linalg.svd(Rs.mean(0))
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)))])
    return U @ D @ Vt
