"""Facemark model files: OpenCV ``FacemarkLBF`` models (``cv::FileStorage`` YAML).

:func:`save_lbf_model` writes an :class:`~retarget_cli.methods.tracking.facemark.LbfModel`
in the layout ``cv2.face.createFacemarkLBF().loadModel`` reads, plus keys of
our own (``retarget_*``: box margin, training report) that OpenCV ignores.
:func:`load_facemark` loads such a file, or any other OpenCV LBF model, into
a :class:`FacemarkFitter`.
"""

from __future__ import annotations

import gzip
import json
import os
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import InputError
from .atomic import write_bytes, write_text

#: Format marker written into our model files.
MODEL_FORMAT = "retarget-facemark-lbf-1"


def lbf_model_text(model) -> str:
    """The ``cv::FileStorage`` YAML document of an LBF model (deterministic)."""
    import cv2


    S, L, T, n_nodes, _ = model.feats.shape
    fs = cv2.FileStorage("model.yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY
                         | cv2.FILE_STORAGE_WRITE_BASE64)
    fs.write("stages_n", int(S))
    fs.write("tree_n", int(T))
    fs.write("tree_depth", int(model.depth))
    fs.write("n_landmarks", int(L))
    fs.write("regressor_meanshape", np.ascontiguousarray(model.mean_shape, np.float64))
    for k in range(S):
        for i in range(L):
            for j in range(T):
                fs.write(f"tree_{k}_{i}_{j}", np.ascontiguousarray(model.feats[k, i, j], np.float64))
                fs.startWriteStruct(f"thresholds_{k}_{i}_{j}", cv2.FileNode_SEQ | cv2.FileNode_FLOW)
                for v in model.thresholds[k, i, j]:
                    fs.write("", int(v))
                fs.endWriteStruct()
        fs.write(f"weights_{k}", np.ascontiguousarray(model.weights[k], np.float32))
    fs.write("retarget_format", MODEL_FORMAT)
    fs.write("retarget_version", __version__)
    fs.write("retarget_info", json.dumps(model.info, sort_keys=True))
    return fs.releaseAndGetString()


def save_lbf_model(path: str | os.PathLike, model) -> None:
    """Write *model* atomically; a name ending in ``.gz`` is gzip-compressed (OpenCV reads both)."""
    text = lbf_model_text(model)
    if str(path).endswith(".gz"):
        write_bytes(path, gzip.compress(text.encode("utf-8"), mtime=0))
    else:
        write_text(path, text)


class FacemarkFitter:
    """A loaded ``cv2.face`` Facemark model with what the tracker needs to know about it.

    Attributes
    ----------
    path : Path
    n_points : int
    box_margin : float
        Margin of the face box around the landmarks the model was trained with.
    face_size : int or None
        Working face size of the model (see :func:`~retarget_cli.methods.tracking.facemark.train_lbf`);
        None (other LBF models): frames are fitted at full resolution.
    info : dict
        The ``retarget_info`` of our models (empty for other LBF models).
    """

    def __init__(self, path, facemark, n_points: int, box_margin: float, info: dict, face_size=None):
        self.path, self._fm, self.n_points, self.box_margin, self.info = Path(path), facemark, n_points, \
            box_margin, info
        self.face_size = face_size

    def fit(self, gray, box) -> np.ndarray | None:
        """Landmarks (L, 2) fitted in face box ``(x, y, w, h)``, or None if OpenCV's fit failed."""
        ok, landmarks = self._fm.fit(gray, np.asarray([box], np.int32))
        if not ok or not len(landmarks):
            return None
        P = np.asarray(landmarks[0], np.float64).reshape(-1, 2)
        return P if P.shape == (self.n_points, 2) and np.isfinite(P).all() else None


def load_facemark(path: str | os.PathLike) -> FacemarkFitter:
    """Load an OpenCV Facemark LBF model file.

    Raises
    ------
    InputError
        Naming *path*: missing, not a ``cv::FileStorage`` document, or not an
        LBF model (no ``stages_n``/``n_landmarks``; AAM and Kazemi models
        cannot be used: see the README).
    """
    import cv2

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: Facemark model file not found (train one with 'retarget train-tracker')")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        ok = fs.isOpened()
    except (cv2.error, SystemError):  # OpenCV's parser raises on malformed documents
        ok = False
    if not ok:
        raise InputError(f"{path}: not a Facemark LBF model (not an OpenCV FileStorage YAML/XML document)")
    try:
        node_l, node_s = fs.getNode("n_landmarks"), fs.getNode("stages_n")
        if node_l.empty() or node_s.empty():
            raise InputError(f"{path}: not a Facemark LBF model (no 'n_landmarks'/'stages_n'); "
                             "only LBF models can be used (AAM and Kazemi models are not supported)")
        n_points = int(node_l.real())
        info_node = fs.getNode("retarget_info")
        info = json.loads(info_node.string()) if not info_node.empty() else {}
        w = fs.getNode("weights_0").mat() if not fs.getNode("weights_0").empty() else None
    finally:
        fs.release()
    if n_points < 1 or w is None or w.shape[0] != 2 * n_points:
        raise InputError(f"{path}: inconsistent Facemark LBF model (n_landmarks {n_points}, "
                         f"weights_0 of shape {None if w is None else w.shape}; expected {2 * n_points} rows)")
    fm = cv2.face.createFacemarkLBF()
    quiet = cv2.FileStorage("%YAML:1.0\n---\nverbose: 0\n", cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    fm.read(quiet.root())  # OpenCV prints "loading data from ..." on stdout unless verbose is off
    try:
        fm.loadModel(str(path))
    except cv2.error as exc:
        raise InputError(f"{path}: OpenCV could not load the Facemark LBF model: "
                         f"{str(exc).strip().splitlines()[-1]}") from None
    return FacemarkFitter(path, fm, n_points, float(info.get("retarget_box_margin", 0.1)), info,
                          info.get("retarget_face_size"))
