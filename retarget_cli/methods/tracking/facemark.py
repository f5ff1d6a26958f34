"""Facemark tracking: OpenCV's ``cv2.face`` LBF landmark regressor, trained on the actor's own frames.

Chuang & Bregler (2002, §3) track with a model trained from a handful of
labelled frames of the performer. This module does the same with the local
binary features (LBF) cascade of Ren et al. (2014) as implemented by OpenCV's
``cv2.face.FacemarkLBF``:

- **training** (:func:`train_lbf`): the Python bindings of OpenCV 5.0 expose
  neither ``addTrainingSample``/``training`` nor the parameters, and OpenCV's
  own LBF training finds its face boxes with a Haar cascade. So the cascade
  is trained here, in numpy, with the boxes taken from the annotations, and
  written in the file format ``FacemarkLBF::loadModel`` reads (a
  ``cv::FileStorage`` document: ``stages_n``, ``tree_n``, ``tree_depth``,
  ``n_landmarks``, ``regressor_meanshape``, ``tree_k_i_j``,
  ``thresholds_k_i_j``, ``weights_k``). :meth:`LbfModel.predict` is a numpy
  copy of OpenCV's inference (same crop, same pixel-difference features, same
  similarity normalisation), so the cascade is trained against exactly what
  OpenCV will compute; a test checks both agree.
- **augmentation**: a handful of annotated frames is too little for a
  regression cascade, so the training set is enlarged the way eigen-points
  does it (Covell & Bregler; Chuang & Bregler §3): frames are aligned by the
  similarity of their rigid points, in-between expressions are made by
  morphing every pair (piecewise-affine warp and cross-dissolve), and every
  sample gets a random roll, scale and shift of the whole image and a random
  gain, offset and noise. There are no mirror images: a flip would need a
  left/right remapping of the point indices that an arbitrary layout lacks.
- **tracking** (:func:`track_facemark`): the face box of the first frame comes
  from its annotation; each later frame is fitted in the box of the previous
  frame's landmarks (centre and size smoothed), and fitted a second time in
  the box of the first fit's landmarks. The second fit is the result; the
  distance between the two fits gives the confidence (see there).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from ...errors import FaceLostError, ShapeError
from .base import check_inside, normalize_annotations
from .base import to_gray as _gray
from .eigenpoints import morph_pairs
from .head import default_rigid_points, fit_similarity

log = logging.getLogger(__name__)

#: Margin added on each side of the landmarks' bounding box, as a fraction of its size.
BOX_MARGIN = 0.1
#: Default working face size: frames whose first annotated face box is larger (longer side, pixels)
#: are scaled down so it is this size, for training and tracking alike.
FACE_SIZE = 200


def working_scale(shape, face_size) -> float:
    """Factor (<= 1) scaling frames so the face box of *shape* (L, 2) has *face_size* pixels on its longer side."""
    if not face_size:
        return 1.0
    return min(1.0, float(face_size) / float(face_box(shape)[2:].max()))


def _scaled(gray, k: float):
    """*gray* resized by *k* (area averaging); identity for k = 1."""
    import cv2

    if k == 1.0:
        return gray
    return cv2.resize(gray, (max(1, round(gray.shape[1] * k)), max(1, round(gray.shape[0] * k))),
                      interpolation=cv2.INTER_AREA)


def _to_scaled(P, k: float):
    """Pixel-centre coordinates in a frame resized by *k* (``(x + 0.5) k - 0.5``)."""
    return (np.asarray(P, np.float64) + 0.5) * k - 0.5 if k != 1.0 else np.asarray(P, np.float64)


def _from_scaled(P, k: float):
    return (np.asarray(P, np.float64) + 0.5) / k - 0.5 if k != 1.0 else np.asarray(P, np.float64)


def face_box(points, *, margin: float = BOX_MARGIN) -> np.ndarray:
    """Integer face box ``(x, y, w, h)`` around landmarks, the box convention of our models.

    Parameters
    ----------
    points : ndarray, shape (L, 2)
    margin : float
        Fraction of the landmarks' extent added on each side.

    Returns
    -------
    ndarray of int64, shape (4,)
    """
    P = np.asarray(points, dtype=np.float64)
    lo, hi = P.min(0), P.max(0)
    ext = np.maximum(hi - lo, 1.0)
    lo, hi = lo - margin * ext, hi + margin * ext
    x0, y0 = np.round(lo).astype(np.int64)
    x1, y1 = np.round(hi).astype(np.int64)
    return np.array([x0, y0, max(x1 - x0, 2), max(y1 - y0, 2)], dtype=np.int64)


def _crop_box(shape_hw, box):
    """OpenCV's ``FacemarkLBFImpl::fitImpl`` crop: (x0, y0, w, h) of the crop and the box inside it."""
    rows, cols = shape_hw
    bx, by, bw, bh = (int(v) for v in box)
    min_x = max(0.0, float(bx - bw // 2))
    max_x = min(cols - 1.0, float(bx + bw + bw // 2))
    min_y = max(0.0, float(by - bh // 2))
    max_y = min(rows - 1.0, float(by + bh + bh // 2))
    x0, y0 = int(min_x), int(min_y)
    w, h = int(max_x - min_x), int(max_y - min_y)
    return (x0, y0, w, h), (bx - min_x, by - min_y, float(bw), float(bh))


def _similarity(shape1, shape2):
    """OpenCV LBF ``calcSimilarityTransform``: ``shape1 ≈ scale R shape2`` for (N, L, 2) batches.

    The scale is OpenCV's (``sqrt(norm(calcCovarMatrix(., COVAR_COLS)))`` of
    each centred shape, i.e. ``|x - y| / sqrt(2)``), reproduced exactly so the
    trained cascade matches OpenCV's inference.

    Returns
    -------
    scale : ndarray (N,)
    R : ndarray (N, 2, 2)
    """
    a = shape1 - shape1.mean(-2, keepdims=True)
    b = shape2 - shape2.mean(-2, keepdims=True)
    s1 = np.linalg.norm(a[..., 0] - a[..., 1], axis=-1) / np.sqrt(2)
    s2 = np.linalg.norm(b[..., 0] - b[..., 1], axis=-1) / np.sqrt(2)
    s1, s2 = np.maximum(s1, 1e-12), np.maximum(s2, 1e-12)
    a, b = a / s1[..., None, None], b / s2[..., None, None]
    num = (a[..., 1] * b[..., 0]).sum(-1) - (a[..., 0] * b[..., 1]).sum(-1)
    den = (a[..., 0] * b[..., 0]).sum(-1) + (a[..., 1] * b[..., 1]).sum(-1)
    nrm = np.maximum(np.hypot(num, den), 1e-12)
    sn, cs = num / nrm, den / nrm
    R = np.stack([np.stack([cs, -sn], -1), np.stack([sn, cs], -1)], -2)
    return s1 / s2, R


class _Crops:
    """Training crops packed in one buffer, for vectorised pixel lookups."""

    def __init__(self, crops):
        self.w = np.array([c.shape[1] for c in crops], np.int64)
        self.h = np.array([c.shape[0] for c in crops], np.int64)
        self.offset = np.concatenate([[0], np.cumsum(self.w * self.h)[:-1]]).astype(np.int64)
        self.buf = np.concatenate([c.ravel() for c in crops])  # uint8: memory

    def lookup(self, rows, x, y):
        """Pixel values at float (x, y) for samples *rows*, as OpenCV reads them (clamp, truncate)."""
        w, h = self.w[rows], self.h[rows]
        xi = np.clip(x, 0.0, (w - 1).astype(np.float64)).astype(np.int64)
        yi = np.clip(y, 0.0, (h - 1).astype(np.float64)).astype(np.int64)
        return self.buf[self.offset[rows] + yi * w + xi].astype(np.int32)


@dataclass
class LbfModel:
    """An LBF cascade in OpenCV's layout.

    Attributes
    ----------
    mean_shape : ndarray (L, 2)
        Mean shape in box-normalised coordinates (box centre 0, half-size 1).
    feats : ndarray (S, L, T, 2**D, 4)
        Per stage, landmark, tree and node: the two pixel offsets of the
        node's pixel-difference feature, in mean-shape units.
    thresholds : ndarray (S, L, T, 2**D) int
    weights : ndarray (S, 2L, L*T*2**(D-1)) float32
        Global linear regression from the binary features to the shape update.
    depth : int
        OpenCV's ``tree_depth`` D (D - 1 splits per tree).
    info : dict
        Extra keys stored in the model file (box margin, training report).
    """

    mean_shape: np.ndarray
    feats: np.ndarray
    thresholds: np.ndarray
    weights: np.ndarray
    depth: int
    info: dict = field(default_factory=dict)

    @property
    def n_points(self) -> int:
        return int(self.mean_shape.shape[0])

    def _codes(self, stage, crops: _Crops, rows, cur, bx, scale, R):
        """Leaf index of every tree for each sample (OpenCV ``generateLBF``), shape (N, L*T)."""
        F, TH = self.feats[stage], self.thresholds[stage]
        L, T = F.shape[:2]
        n = len(rows)
        idx = np.ones((n, L, T), np.int64)
        code = np.zeros((n, L, T), np.int64)
        li = np.arange(L)[None, :, None]
        ti = np.arange(T)[None, None, :]
        for _ in range(1, self.depth):
            f = F[li, ti, idx]  # (n, L, T, 4)
            p = _place(f, scale, R, bx, cur)
            r = rows[:, None, None]
            d = crops.lookup(r, p[..., 0], p[..., 1]) - crops.lookup(r, p[..., 2], p[..., 3])
            right = d >= TH[li, ti, idx]
            code = code * 2 + right
            idx = 2 * idx + right
        base = 1 << (self.depth - 1)
        return (np.arange(L * T)[None] * base + code.reshape(n, L * T)).astype(np.int64)

    def _run(self, crops: _Crops, boxes, stages=None):
        """Cascade from the mean shape for packed crops with their boxes (N, 4) in crop pixels."""
        rows = np.arange(len(boxes))
        bx = _box_params(boxes)
        cur = _reproject(bx, np.broadcast_to(self.mean_shape, (len(boxes),) + self.mean_shape.shape))
        for k in range(len(self.weights) if stages is None else stages):
            cur = self._step(k, crops, rows, cur, bx)
        return cur

    def _step(self, k, crops, rows, cur, bx):
        proj = _project(bx, cur)
        scale, R = _similarity(proj, self.mean_shape[None])
        codes = self._codes(k, crops, rows, cur, bx, scale, R)
        Wt = self.weights[k].T.astype(np.float64)  # (F, 2L)
        delta = np.zeros((len(rows), Wt.shape[1]))
        for j in range(codes.shape[1]):  # one active leaf per tree: sum their weight rows
            delta += Wt[codes[:, j]]
        delta = delta.reshape(len(rows), -1, 2)  # (N, L, 2), mean-shape frame
        upd = scale[:, None, None] * np.einsum("nij,nlj->nli", R, delta)
        return _reproject(bx, proj + upd)

    def predict(self, gray, box) -> np.ndarray:
        """Landmarks (L, 2) in image pixels, computed as OpenCV's ``FacemarkLBF::fit`` does.

        Parameters
        ----------
        gray : ndarray (H, W) uint8
        box : sequence of 4 int
            Face box ``(x, y, w, h)``.
        """
        (x0, y0, w, h), inner = _crop_box(gray.shape, box)
        crop = gray[y0:y0 + h, x0:x0 + w]
        pts = self._run(_Crops([crop]), np.array([inner]))[0]
        return pts + (x0, y0)


def _box_params(boxes):
    b = np.asarray(boxes, np.float64)
    half = b[:, 2:] / 2
    return np.concatenate([b[:, :2] + half, half], axis=1)  # centre x, y, half-size x, y


def _project(bx, shapes):
    return (shapes - bx[:, None, :2]) / bx[:, None, 2:]


def _reproject(bx, shapes):
    return shapes * bx[:, None, 2:] + bx[:, None, :2]


def _place(f, scale, R, bx, cur):
    """Image positions (..., 4) of feature offsets *f* (n, L, T[, P], 4) around the current landmarks."""
    extra = f.ndim - 4
    sh = (slice(None),) + (None,) * (2 + extra)
    s = scale[sh]
    Rm = R.reshape((len(R),) + (1,) * (2 + extra) + (2, 2))
    out = np.empty_like(f)
    for c in (0, 2):
        x, y = f[..., c], f[..., c + 1]
        xr = s * (Rm[..., 0, 0] * x + Rm[..., 0, 1] * y)
        yr = s * (Rm[..., 1, 0] * x + Rm[..., 1, 1] * y)
        cx = cur[(slice(None), slice(None)) + (None,) * (1 + extra) + (0,)]
        cy = cur[(slice(None), slice(None)) + (None,) * (1 + extra) + (1,)]
        out[..., c] = xr * bx[:, 2][sh] + cx
        out[..., c + 1] = yr * bx[:, 3][sh] + cy
    return out


def _sim_matrix(src, dst) -> np.ndarray:
    """(2, 3) least-squares similarity taking points *src* (N, 2) onto *dst* (N, 2)."""
    M = fit_similarity(src, dst[None], iterations=0)[0]
    return np.asarray(M, np.float64)


def augment(images, shapes, *, rigid_points=None, morphs: int = 3, copies: int = 12, roll: float = 15.0,
            scale: float = 0.1, jitter: float = 0.06, photometric: bool = True, seed: int = 0):
    """Enlarge a few annotated frames into a training set for the cascade.

    1. every frame is aligned to the first by the similarity of its rigid
       points and cut out on a canvas around the face;
    2. in-between expressions: every pair is morphed (*morphs* shapes between
       them; piecewise-affine warp onto the interpolated shape and
       cross-dissolve, as eigen-points does, Chuang & Bregler §3);
    3. each of those gets *copies* variants: a random roll (±*roll* degrees)
       and scale (±*scale*) of the whole canvas, a face box displaced by up to
       *jitter* of its size and resized by up to *jitter* (the box the tracker
       derives from the previous frame is never exactly on the face), and a
       random gain, offset and sensor noise.

    No mirror images: they would need a left/right remapping of the indices.

    Parameters
    ----------
    images : list of ndarray (H, W) uint8
    shapes : ndarray (K, L, 2)
        Landmarks of *images*, pixels.

    Returns
    -------
    crops : list of ndarray uint8
        The crops OpenCV's LBF fit would take for each sample's box.
    boxes : ndarray (N, 4)
        Each sample's face box inside its crop (x, y, w, h), float.
    truth : ndarray (N, L, 2)
        Each sample's landmarks inside its crop.
    """
    import cv2


    S = np.asarray(shapes, np.float64)
    K, L, _ = S.shape
    rigid = default_rigid_points(L) if rigid_points is None else np.asarray(rigid_points, int)
    rng = np.random.default_rng(seed)
    b0 = face_box(S[0])
    side = int(np.ceil(2.9 * max(b0[2], b0[3])))
    size = (side, side)
    centre0 = b0[:2] + b0[2:] / 2
    shift = np.array([side / 2, side / 2]) - centre0
    base_img, base_pts = [], []
    for img, P in zip(images, S):
        M = _sim_matrix(P[rigid], S[0][rigid])
        M[:, 2] += shift
        base_img.append(cv2.warpAffine(img, M, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
                        .astype(np.float32))
        base_pts.append(P @ M[:, :2].T + M[:, 2])
    W = H = side
    samples = list(zip(base_img, base_pts)) + morph_pairs(base_img, base_pts, size, morphs)
    crops, boxes, truth = [], [], []
    c = np.array([W / 2, H / 2])
    for img, P in samples:
        for r in range(copies):
            if r == 0:
                A = np.eye(2, 3)
            else:
                ang = np.deg2rad(rng.uniform(-roll, roll))
                sc = 1 + rng.uniform(-scale, scale)
                Rm = sc * np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
                A = np.concatenate([Rm, (c - Rm @ c)[:, None]], 1)
            warped = cv2.warpAffine(img, A, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            Q = P @ A[:, :2].T + A[:, 2]
            if photometric and r:
                warped = warped * rng.uniform(0.8, 1.2) + rng.uniform(-15, 15)
                warped = warped + rng.normal(0, rng.uniform(0, 3), warped.shape)
            warped = np.clip(np.round(warped), 0, 255).astype(np.uint8)
            box = face_box(Q).astype(np.float64)
            if r:
                wh = box[2:] * (1 + rng.uniform(-jitter, jitter))
                ctr = box[:2] + box[2:] / 2 + rng.uniform(-jitter, jitter, 2) * box[2:]
                box = np.concatenate([np.round(ctr - wh / 2), np.round(wh)])
            (x0, y0, w, h), inner = _crop_box(warped.shape, box)
            crops.append(warped[y0:y0 + h, x0:x0 + w])
            boxes.append(inner)
            truth.append(Q - (x0, y0))
    return crops, np.array(boxes), np.stack(truth)


def _grow_tree(dens, Y, depth, rng):
    """One regression tree on pixel-difference features (OpenCV ``RandomTree::splitNode``).

    Parameters
    ----------
    dens : ndarray (n, P) int
        Candidate feature values of the tree's samples.
    Y : ndarray (n, 2)
        The landmark's regression targets.

    Returns
    -------
    choice : ndarray (2**depth,) int
        Candidate index per node (0 where unused).
    thr : ndarray (2**depth,) int
    """
    n_nodes = 1 << depth
    choice = np.zeros(n_nodes, np.int64)
    thr = np.zeros(n_nodes, np.int64)
    members = {1: np.arange(len(Y))}
    Y2 = (Y**2).sum(1)
    for idx in range(1, n_nodes // 2):
        rows = members.pop(idx, np.zeros(0, np.int64))
        if rows.size == 0:
            members[2 * idx] = members[2 * idx + 1] = rows
            continue
        D = dens[rows]  # (n, P)
        n = len(rows)
        srt = np.sort(D, axis=0)
        q = (n * rng.uniform(0.05, 0.95, D.shape[1])).astype(np.int64)
        t = srt[q, np.arange(D.shape[1])]
        left = D < t[None]  # (n, P)
        yl, y2l = left.T.astype(np.float64) @ Y[rows], left.T.astype(np.float64) @ Y2[rows]
        nl = left.sum(0).astype(np.float64)
        ya, y2a = Y[rows].sum(0), Y2[rows].sum()
        nr = n - nl
        sse = (y2l - (yl**2).sum(1) / np.maximum(nl, 1)) + ((y2a - y2l) - ((ya - yl) ** 2).sum(1) / np.maximum(nr, 1))
        best = int(np.argmin(sse))
        total = y2a - (ya**2).sum() / n
        if not total - sse[best] > 0:
            best, tt = 0, 0
        else:
            tt = int(t[best])
        choice[idx], thr[idx] = best, tt
        go_left = dens[rows, best] < tt
        members[2 * idx], members[2 * idx + 1] = rows[go_left], rows[~go_left]
    return choice, thr


def train_lbf(images, shapes, *, stages: int = 5, trees: int = 4, depth: int = 4, candidates: int = 200,
              radii=(0.3, 0.2, 0.15, 0.12, 0.10, 0.10, 0.08, 0.06, 0.06, 0.05), ridge: float = 1.0,
              bagging: float = 0.7, rigid_points=None, morphs: int = 3, copies: int = 12,
              face_size: int | None = FACE_SIZE, seed: int = 0, progress=None) -> LbfModel:
    """Train an LBF cascade (Ren et al. 2014, OpenCV layout) from a few annotated frames of one actor.

    Parameters
    ----------
    images : list of ndarray (H, W) or (H, W, 3), uint8
        Annotated frames (at least 1; 5 or more that span the expressions work far better).
    shapes : ndarray (K, L, 2)
        Their landmarks in pixels.
    stages : int
        Cascade stages (1-10).
    trees : int
        Trees per landmark and stage.
    depth : int
        OpenCV ``tree_depth``: each tree makes ``depth - 1`` binary splits.
    candidates : int
        Random pixel-difference features drawn per tree (the best one is kept at each node).
    radii : sequence of float
        Per stage, the radius (mean-shape units, box half-size = 1) of the
        disc the feature pixels are drawn from around their landmark.
    ridge : float
        Ridge penalty of the global linear regression, per training sample.
    bagging : float
        Fraction of the samples each tree is grown on.
    rigid_points, morphs, copies : see :func:`augment`.
    face_size : int or None
        Frames are scaled down (never up) so the first annotated face box
        has this many pixels on its longer side; the tracker scales its
        frames the same way (None: full resolution). Bounds training time
        and memory on high-resolution video.
    seed : int
    progress : callable, optional
        Called with the stage number after each stage.

    Returns
    -------
    LbfModel
    """
    import scipy.sparse as sp

    S = np.asarray(shapes, np.float64)
    if S.ndim != 3 or S.shape[2] != 2 or len(S) != len(images) or len(S) == 0:
        raise ShapeError(f"shapes: expected ({len(images)}, L, 2) for {len(images)} images, got {S.shape}")
    if not 1 <= stages <= len(radii):
        raise ShapeError(f"stages: expected 1..{len(radii)}, got {stages}")
    if depth < 2 or trees < 1 or candidates < 1:
        raise ShapeError(f"depth >= 2, trees >= 1, candidates >= 1 expected; got {depth}, {trees}, {candidates}")
    grays = [_gray(np.asarray(im)) for im in images]
    for k, (g, P) in enumerate(zip(grays, S)):
        check_inside(P, (g.shape[1], g.shape[0]), f"annotated frame {k}")
    scale0 = working_scale(S[0], face_size)
    grays = [_scaled(g, scale0) for g in grays]
    S = _to_scaled(S, scale0)
    rng = np.random.default_rng(seed)
    crops, boxes, truth = augment(grays, S, rigid_points=rigid_points, morphs=morphs, copies=copies,
                                  seed=int(rng.integers(2**31)))
    N, L = truth.shape[:2]
    packed = _Crops(crops)
    bx = _box_params(boxes)
    gt = _project(bx, truth)
    mean_shape = gt.mean(0)
    n_nodes = 1 << depth
    model = LbfModel(mean_shape, np.zeros((stages, L, trees, n_nodes, 4)),
                     np.zeros((stages, L, trees, n_nodes), np.int64),
                     np.zeros((stages, 2 * L, L * trees * (n_nodes // 2)), np.float32), depth)
    rows_all = np.arange(N)
    cur = _reproject(bx, np.broadcast_to(mean_shape, gt.shape))
    n_bag = max(1, int(round(bagging * N)))
    for k in range(stages):
        proj = _project(bx, cur)
        scale, R = _similarity(proj, mean_shape[None])
        # targets in the mean-shape frame: OpenCV applies scale * R to the regressed update
        Y = np.einsum("nji,nlj->nli", R, gt - proj) / scale[:, None, None]
        for lm in range(L):
            for t in range(trees):
                bag = np.sort(rng.choice(N, n_bag, replace=False)) if n_bag < N else rows_all
                # candidate offsets uniform in the disc of radius radii[k] (rejection sampling, as OpenCV)
                cand = np.zeros((0, 4))
                while len(cand) < candidates:
                    u = rng.uniform(-1, 1, (2 * candidates, 4))
                    ok = ((u[:, :2] ** 2).sum(1) <= 1) & ((u[:, 2:] ** 2).sum(1) <= 1)
                    cand = np.concatenate([cand, u[ok]])
                cand = cand[:candidates] * radii[k]
                p = _place(np.broadcast_to(cand, (len(bag), 1, 1, candidates, 4)), scale[bag], R[bag], bx[bag],
                           cur[bag][:, lm:lm + 1])
                rr = bag[:, None, None, None]
                d = (packed.lookup(rr, p[..., 0], p[..., 1]) - packed.lookup(rr, p[..., 2], p[..., 3]))[:, 0, 0]
                choice, thr = _grow_tree(d, Y[bag, lm], depth, rng)
                model.feats[k, lm, t] = cand[choice]
                model.feats[k, lm, t, 0] = 0
                model.thresholds[k, lm, t] = thr
        codes = model._codes(k, packed, rows_all, cur, bx, scale, R)
        F = model.weights.shape[2]
        X = sp.csr_matrix((np.ones(codes.size), codes.ravel(), np.arange(0, codes.size + 1, codes.shape[1])),
                          shape=(N, F))
        G = (X @ X.T).toarray()
        # ridge in the dual (N x N): every sample has L*T active features, the Gram diagonal
        A = np.linalg.solve(G + ridge * codes.shape[1] * np.eye(N), Y.reshape(N, -1))
        model.weights[k] = np.asarray(X.T @ A).T.astype(np.float32)
        cur = model._step(k, packed, rows_all, cur, bx)
        err = np.linalg.norm(cur - truth, axis=2).mean()
        log.info("facemark training: stage %d of %d, mean training error %.2f px", k + 1, stages, err)
        if progress is not None:
            progress(k)
    model.info = {"retarget_box_margin": BOX_MARGIN, "retarget_face_size": face_size,
                  "retarget_train_error_px": float(err / scale0),
                  "retarget_samples": int(N), "retarget_annotated_frames": int(len(S))}
    return model


class _Appearance:
    """Normalised face patches of the annotated frames, to tell a face from whatever else a fit lands on."""

    def __init__(self, shape, rigid, width: int = 48):
        lo, hi = shape.min(0), shape.max(0)
        k = width / max((hi - lo).max(), 1.0)
        self.canon = (shape - (lo + hi) / 2) * k + width / 2
        self.rigid, self.size, self.refs = rigid, (width, width), []

    def patch(self, gray, P) -> np.ndarray:
        import cv2

        M = _sim_matrix(P[self.rigid], self.canon[self.rigid])
        x = cv2.warpAffine(gray, M, self.size, flags=cv2.INTER_AREA, borderMode=cv2.BORDER_REPLICATE).astype(
            np.float64).ravel()
        x -= x.mean()
        return x / max(np.linalg.norm(x), 1e-9)

    def add(self, gray, P) -> None:
        self.refs.append(self.patch(gray, P))

    def score(self, gray, P) -> float:
        """Highest normalised cross-correlation with a reference patch (1 = same appearance)."""
        x = self.patch(gray, P)
        return float(max(x @ r for r in self.refs))


def track_facemark(frames: Iterable[np.ndarray], annotations, *, model, smooth: float = 0.5, tau: float = 0.02,
                   min_similarity: float = 0.5, lost_frames: int = 10, lost_spread: float = 0.1,
                   rigid_points=None, progress=None):
    """Track landmarks with a Facemark model, following the face box from frame to frame.

    Each frame is fitted twice: first in the box of the previous frame's
    landmarks (its centre and size exponentially smoothed with weight
    *smooth* on the past), then in the box of the first fit's landmarks. The
    second fit is kept. A cascaded regressor that has found the face gives
    the same landmarks from both boxes; where it has not, the result follows
    the box. The confidence of point ``i`` is ``exp(-d_i / (tau * s))``, with
    ``d_i`` the distance between the two fits of that point and ``s`` the box
    size (mean of width and height): 1 for a stable fit, ``exp(-1)`` at a
    disagreement of *tau* of the face size. It is 0 for every point of a
    frame where OpenCV's fit failed or where the fitted face does not look
    like the annotated ones: the frame, aligned by the similarity of its
    rigid points, must have a normalised cross-correlation of at least
    *min_similarity* with one of the annotated frames aligned the same way (a
    regressor always returns a face-like shape, even on a blank frame).
    Annotated frames return their annotation with confidence 1, re-centre
    the box and become appearance references.

    Parameters
    ----------
    frames : iterable of ndarray (H, W, 3) or (H, W), uint8
    annotations : ndarray (L, 2) or dict of int to ndarray (L, 2)
        Annotated frames by index in *frames*; frame 0 must be among them.
    model : object
        ``model.fit(gray, box) -> (L, 2) or None``, ``model.n_points``,
        ``model.box_margin`` and ``model.face_size`` (frames are scaled as in
        training, see :func:`train_lbf`; e.g.
        :class:`~retarget_cli.io.facemark_model.FacemarkFitter`).
    smooth : float
        Weight of the previous box in the box used for the next frame (0-1).
    tau : float
        Disagreement (fraction of the face size) at which confidence is ``exp(-1)``.
    min_similarity : float
        Normalised cross-correlation below which a frame's face is not found.
    lost_frames : int
        Raise :class:`~retarget_cli.methods.tracking.lk.FaceLostError` after this many
        frames in a row where the face was not found or the median
        disagreement exceeds *lost_spread* of the face size.
    lost_spread : float
    rigid_points : sequence of int, optional
        Points aligning the appearance check; default
        :func:`~retarget_cli.methods.tracking.head.default_rigid_points`.
    progress : callable, optional
        Called with the frame index after each frame.

    Returns
    -------
    points : ndarray (T, L, 2)
    confidence : ndarray (T, L)
    """
    ann = normalize_annotations(annotations)
    if 0 not in ann:
        raise ShapeError(f"annotations: the first frame must be annotated; annotated frames are {list(ann)[:5]}")
    L = next(iter(ann.values())).shape[0]
    if L != model.n_points:
        raise ShapeError(f"annotations have {L} points but the Facemark model was trained for {model.n_points}")
    if not 0 <= smooth < 1:
        raise ShapeError(f"smooth: expected a value in [0, 1), got {smooth}")
    rigid = default_rigid_points(L) if rigid_points is None else np.asarray(rigid_points, int)
    k = working_scale(ann[0], model.face_size)
    look = _Appearance(_to_scaled(ann[0], k), rigid)
    margin = model.box_margin
    pts, conf = [], []
    box = None
    bad = 0
    for t, frame in enumerate(frames):
        g = _gray(frame)
        if t in ann:
            check_inside(ann[t], (g.shape[1], g.shape[0]), f"annotations: frame {t}")
        g = _scaled(g, k)
        h, w = g.shape
        if t in ann:
            P, c = _to_scaled(ann[t], k), np.ones(L)
            box = face_box(P, margin=margin).astype(np.float64)
            look.add(g, P)
            bad = 0
        else:
            first = model.fit(g, np.round(box).astype(np.int64))
            second = None if first is None else model.fit(g, face_box(first, margin=margin))
            size = box[2:].mean()
            found = second is not None and second.min() > -0.5 * size and second[:, 0].max() < w + 0.5 * size \
                and second[:, 1].max() < h + 0.5 * size and look.score(g, second) >= min_similarity
            if not found:
                P, c, spread = (pts[-1] if second is None else second), np.zeros(L), np.inf
            else:
                d = np.linalg.norm(second - first, axis=1)
                P, c = second, np.exp(-d / (tau * size))
                spread = float(np.median(d)) / size
            bad = bad + 1 if spread > lost_spread else 0
            if bad >= lost_frames:
                f0 = t - bad + 1
                raise FaceLostError(
                    f"the face was lost from frame {f0}: for {bad} frames in a row the Facemark fit failed, did not "
                    f"settle (median disagreement above {lost_spread:g} of the face size) or did not look like the "
                    f"annotated face (similarity below {min_similarity:g})",
                    f0, _from_scaled(np.stack(pts[:f0]), k), np.stack(conf[:f0]))
            if not bad:
                box = smooth * box + (1 - smooth) * face_box(P, margin=margin)
        pts.append(np.asarray(P, np.float64))
        conf.append(c)
        if progress is not None:
            progress(t)
    if not pts:
        raise ShapeError("frames: the sequence is empty")
    out = _from_scaled(np.stack(pts), k)
    for t in ann:  # annotated frames exactly as given
        if t < len(out):
            out[t] = ann[t]
    return out, np.clip(np.stack(conf), 0, 1)
