"""A synthetic take of a turned head (issue 28): a rig's 68 landmark vertices posed at known sliders, turned by
known yaw/pitch/roll and seen through a pinhole camera.

Each expression appears twice, once facing the camera and once turned, so the curves ``auto-pose`` fits to the
two can be compared (a head turn must not read as expression), and the stored head pose against the known
angles. Used by ``bench/head_turn.py`` and the tests.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..io.atomic import write_text
from ..io.landmarks import Landmarks, save_landmarks
from ..methods.rigpose import FRONT_68, frontal_rotation, rig_landmarks
from ..methods.tracking.head import estimate_head
from ..methods.tracking.headpose import angles_rotation, camera_matrix, head_pose, sight_angles

#: The 68-point regions of ``configs/sample.yaml`` (Chuang & Bregler §5).
REGIONS_68 = {
    "brows-eyes": list(range(17, 27)) + list(range(36, 48)),
    "mouth": list(range(3, 14)) + list(range(48, 68)),
}


def posed_landmarks(rig, vertices, weights) -> np.ndarray:
    """The rig's landmark vertices at each row of slider *weights*, in camera axes of its front view.

    Parameters
    ----------
    rig : BlendshapeRig
    vertices : array_like of int, shape (68,)
    weights : ndarray, shape (T, n)

    Returns
    -------
    ndarray, shape (T, 68, 3)
        x right, y down, z away from the viewer (:func:`~retarget_cli.methods.rigpose.frontal_rotation` of the
        rest pose), the rest pose's eye-corner centre at the origin, in the rig's units.
    """
    X0, DL = rig_landmarks(rig, vertices)
    Rc = frontal_rotation(X0, *FRONT_68)
    X = X0[None] + np.einsum("lan,tn->tla", DL, np.asarray(weights, dtype=np.float64))
    return (X - X0[[36, 39, 42, 45]].mean(0)) @ Rc.T


def project_turned(X, angles, *, frame_size=(1280, 720), distance: float | None = None, noise: float = 1.0,
                   seed: int = 0) -> np.ndarray:
    """Image points of 3D faces *X* turned by *angles*, through :func:`~retarget_cli.methods.tracking.headpose.camera_matrix`.

    Parameters
    ----------
    X : ndarray, shape (T, 68, 3)
        Faces in camera axes (:func:`posed_landmarks`).
    angles : ndarray, shape (T, 3)
        ``yaw, pitch, roll`` degrees (:class:`~retarget_cli.methods.tracking.headpose.HeadPose`'s convention).
    distance : float, optional
        The face's distance from the camera, in X's units (default 6.5 outer-eye-corner distances, 60 cm for
        a human face).
    noise : float
        Standard deviation of the Gaussian noise added to every point, pixels.

    Returns
    -------
    ndarray, shape (T, 68, 2)
    """
    X = np.asarray(X, dtype=np.float64)
    if distance is None:
        distance = 6.5 * float(np.linalg.norm(X[0, 45] - X[0, 36]))
    K = camera_matrix(frame_size)
    Y = np.einsum("tij,tlj->tli", angles_rotation(angles), X) + np.array([0.0, 0.0, distance])
    p = Y @ K.T
    rng = np.random.default_rng(seed)
    return p[..., :2] / p[..., 2:] + rng.normal(0.0, noise, size=p.shape[:-1] + (2,))


def write_turned_take(folder, rig, vertices, weights, angles, *, frame_size=(1280, 720), noise: float = 1.0,
                      seed: int = 0, fps: float = 30.0) -> tuple[Path, Path]:
    """``landmarks.npz`` (head motion, stabilized landmarks and the 3D head pose as ``track`` stores them) and
    ``keys.json`` (neutral frame 0, the regions of :data:`REGIONS_68`) of a take posed at *weights* and turned
    by *angles*; the rest pose should be row 0 of *weights*, facing the camera.

    Returns
    -------
    landmarks, keys : Path
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    pts = project_turned(posed_landmarks(rig, vertices, weights), angles, frame_size=frame_size, noise=noise,
                         seed=seed)
    conf = np.ones(pts.shape[:2])
    head, stab = estimate_head(pts, conf)
    pose = head_pose(pts, frame_size, confidence=conf)  # as track stores it: relative to the line of sight
    pose_angles = sight_angles(pose.angles, pose.translation)
    lm_path, keys_path = folder / "landmarks.npz", folder / "keys.json"
    save_landmarks(lm_path, Landmarks(pts, conf, head, stab, fps, np.asarray(frame_size), meta={"tracker": "synth"},
                                      head_angles=pose_angles, head_translation=pose.translation))
    keys = {"landmarks": lm_path.name, "neutral": {"frame": 0, "source": "given", "reason": "synthetic rest pose"},
            "regions": {name: {"points": pts_, "frames": [0]} for name, pts_ in REGIONS_68.items()}}
    write_text(keys_path, json.dumps(keys, sort_keys=True, indent=1) + "\n")
    return lm_path, keys_path
