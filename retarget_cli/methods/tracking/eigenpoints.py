"""Eigen-points tracking (Covell & Bregler 1996), as used by Chuang & Bregler (2002, §3).

Training (§3, "A tracking model is trained from an annotated face database"):

1. each annotated frame is pre-warped by the affine map that takes its rigid
   points onto those of the first annotation (affine motion removed);
2. the database is enlarged by morphing between the pre-warped frames
   (landmarks interpolated, images warped piecewise-affinely onto the
   in-between shape and cross-dissolved), and by small known affine
   perturbations of every sample, so the model also learns how a residual
   misalignment moves the landmarks;
3. PCA on the joint vector ``[pixel intensities, landmark coordinates]``
   (each block scaled to unit total variance) keeps the largest eigenvectors.

Tracking ("each frame is then projected onto the basis set of eigenvectors
using only the pixel intensity values"): the frame is pre-warped by the
current affine estimate, its normalised pixels are projected onto the pixel
part of the eigenvectors (regularised least squares), the landmark part of
the same combination gives the landmarks; the affine map is re-estimated
from the rigid landmarks read off, and warp/projection are iterated until the
update is below a tenth of a pixel.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable

import numpy as np

from ...errors import ShapeError
from .base import check_inside, normalize_annotations
from .head import default_rigid_points

log = logging.getLogger(__name__)


def _affine(src, dst) -> np.ndarray:
    """Least-squares affine (2, 3) mapping src (N, 2) onto dst (N, 2)."""
    A = np.concatenate([src, np.ones((len(src), 1))], axis=1)
    X, *_ = np.linalg.lstsq(A, dst, rcond=None)
    return X.T


def _compose(M, N) -> np.ndarray:
    """Affine ``M ∘ N`` (apply N first), both (2, 3)."""
    return np.concatenate([M[:, :2] @ N[:, :2], (M[:, :2] @ N[:, 2] + M[:, 2])[:, None]], axis=1)


def _apply(M, P) -> np.ndarray:
    return P @ M[:, :2].T + M[:, 2]


def morph_pairs(images, points, size, morphs: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Morphs between every pair of aligned annotated frames (training-set enlargement).

    Covell & Bregler enlarge the eigen-points training set by morphing
    between annotated frames (Chuang & Bregler 2002, §3): for each pair and
    each of *morphs* blend factors ``a`` strictly between 0 and 1, both images
    are warped piecewise-affinely (Delaunay triangles of the landmarks plus
    the image's corners and edge midpoints) onto the blended landmarks and
    cross-dissolved.

    Parameters
    ----------
    images : sequence of ndarray, each shape (H, W), float32
        Frames already aligned with one another (same *size*).
    points : sequence of ndarray, each shape (L, 2)
        Their landmarks.
    size : tuple of int
        ``(W, H)``.
    morphs : int
        Blends per pair.

    Returns
    -------
    list of (ndarray (H, W), ndarray (L, 2))
    """
    from scipy.spatial import Delaunay

    W, H = size
    L = len(points[0])
    corners = np.array([[0, 0], [W - 1, 0], [0, H - 1], [W - 1, H - 1], [W / 2, 0], [W / 2, H - 1],
                        [0, H / 2], [W - 1, H / 2]], float)
    out = []
    for i in range(len(images)):
        for j in range(i + 1, len(images)):
            vi, vj = np.concatenate([points[i], corners]), np.concatenate([points[j], corners])
            for a in np.linspace(0, 1, morphs + 2)[1:-1]:
                v = (1 - a) * vi + a * vj
                tri = Delaunay(v).simplices
                wi = _piecewise_warp(images[i], vi, v, tri, size)
                wj = _piecewise_warp(images[j], vj, v, tri, size)
                out.append(((1 - a) * wi + a * wj, v[:L]))
    return out


def _piecewise_warp(image, src_pts, dst_pts, tri, size) -> np.ndarray:
    """Warp *image* so that mesh vertices *src_pts* land on *dst_pts* (same triangles *tri*)."""
    import cv2

    W, H = size
    d, s = dst_pts[tri], src_pts[tri]
    Dm = np.concatenate([d, np.ones((len(d), 3, 1))], axis=2)
    det = np.linalg.det(Dm)
    ok = np.abs(det) > 1e-6
    Dm[~ok] = np.eye(3)
    A = np.linalg.solve(Dm, s)
    coef = np.zeros((len(d) + 1, 6), np.float32)
    coef[0] = (1, 0, 0, 0, 1, 0)
    coef[1:, 0], coef[1:, 1], coef[1:, 2] = A[:, 0, 0], A[:, 1, 0], A[:, 2, 0]
    coef[1:, 3], coef[1:, 4], coef[1:, 5] = A[:, 0, 1], A[:, 1, 1], A[:, 2, 1]
    idmap = np.zeros((H, W), np.int32)
    ip = np.round(d * 16).astype(np.int32)
    for i in np.flatnonzero(ok):
        cv2.fillConvexPoly(idmap, ip[i], int(i + 1), cv2.LINE_8, 4)
    c = coef[idmap]
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    mx = c[..., 0] * xx + c[..., 1] * yy + c[..., 2]
    my = c[..., 3] * xx + c[..., 4] * yy + c[..., 5]
    return cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


class EigenPoints:
    """Coupled appearance/landmark PCA model in a normalised face frame.

    Parameters
    ----------
    images : list of ndarray (H, W) uint8
        Annotated frames (grey).
    shapes : ndarray, shape (N, L, 2)
        Their landmarks, image pixels.
    rigid_points : sequence of int, optional
    width : int, optional
        Width in pixels of the normalised face window; default a third of
        the first annotation's face box (with its margin), within 64-128 px.
        The landmarks are read at this resolution, so the error in image
        pixels grows with the face unless the window does (measured on the
        synthetic 1280x720 take: 2.80 px at 64, 1.98 px at 128; beyond that
        it barely improves and the cost grows).
    morphs : int
        In-between shapes per pair of annotated frames.
    jitter : float
        Largest translation (model pixels) of the misalignment examples.
    variance : float
        Fraction of the joint variance kept.
    seed : int
    """

    def __init__(self, images, shapes, *, rigid_points=None, width: int | None = None, morphs: int = 3,
                 jitter: float = 3.0, variance: float = 0.98, seed: int = 0):
        import cv2

        S = np.asarray(shapes, dtype=np.float64)
        if S.ndim != 3 or S.shape[2] != 2 or len(S) != len(images):
            raise ShapeError(f"shapes: expected ({len(images)}, L, 2), got {S.shape}")
        N, L, _ = S.shape
        self.rigid = default_rigid_points(L) if rigid_points is None else np.asarray(rigid_points, dtype=int)
        # model frame: the first annotation's box scaled to `width` pixels
        lo, hi = S[0].min(0), S[0].max(0)
        margin = 0.12 * (hi - lo)
        lo, hi = lo - margin, hi + margin
        if width is None:
            width = int(np.clip(round((hi - lo)[0] / 3), 64, 128))
        k = width / (hi - lo)[0]
        self.size = (int(width), int(np.ceil((hi - lo)[1] * k)))
        self.to_model = np.array([[k, 0, -k * lo[0]], [0, k, -k * lo[1]]])  # first frame -> model
        # 1. pre-warp every annotated frame: its rigid points onto the first one's
        base = _apply(self.to_model, S[0])
        self.canon = base
        pre_img, pre_pts = [], []
        for img, P in zip(images, S):
            M = _affine(P[self.rigid], base[self.rigid])
            pre_img.append(cv2.warpAffine(img, M, self.size, flags=cv2.INTER_AREA if k < 1 else cv2.INTER_LINEAR,
                                          borderMode=cv2.BORDER_REPLICATE).astype(np.float32))
            pre_pts.append(_apply(M, P))
        # 2. enlarge by morphing between pairs of pre-warped frames
        W, H = self.size
        samples_img, samples_pts = list(pre_img), list(pre_pts)
        for img, P in morph_pairs(pre_img, pre_pts, self.size, morphs):
            samples_img.append(img)
            samples_pts.append(P)
        # ... and by small known misalignments (so the landmarks read off reveal them)
        rng = np.random.default_rng(seed)
        X_img, X_pts = [], []
        c = np.array([W / 2, H / 2])
        for img, P in zip(samples_img, samples_pts):
            for r in range(5):
                if r == 0:
                    J = np.eye(2, 3)
                else:
                    ang = rng.uniform(-0.05, 0.05)
                    sc = 1 + rng.uniform(-0.04, 0.04)
                    R = sc * np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
                    J = np.concatenate([R, (c - R @ c + rng.uniform(-jitter, jitter, 2))[:, None]], 1)
                X_img.append(self._features(cv2.warpAffine(img, J, self.size, borderMode=cv2.BORDER_REPLICATE)))
                X_pts.append(_apply(J, P).ravel())
        X_img, X_pts = np.array(X_img), np.array(X_pts)
        # 3. PCA on the joint vector, blocks scaled to unit total variance
        self.mean_img, self.mean_pts = X_img.mean(0), X_pts.mean(0)
        Ci, Cp = X_img - self.mean_img, X_pts - self.mean_pts
        self.s_img = np.sqrt((Ci**2).sum(1).mean()) + 1e-9
        self.s_pts = np.sqrt((Cp**2).sum(1).mean()) + 1e-9
        Xj = np.concatenate([Ci / self.s_img, Cp / self.s_pts], axis=1)
        # eigenvectors through the (samples x samples) Gram matrix: far fewer samples than pixels
        ev, U = np.linalg.eigh(Xj @ Xj.T)
        order = np.argsort(ev)[::-1]
        ev, U = np.clip(ev[order], 0, None), U[:, order]
        keep = ev > 1e-10 * ev[0]
        var = ev[keep]
        Vt = (U[:, keep].T @ Xj) / np.sqrt(var)[:, None]
        n = int(np.searchsorted(np.cumsum(var) / var.sum(), variance) + 1)
        self.n_modes = n
        self.B_img = Vt[:n, : X_img.shape[1]].T
        self.B_pts = Vt[:n, X_img.shape[1]:].T
        self.var = var[:n] / len(Xj)
        self.n_points = L
        # regularised least-squares projector onto the pixel part of the eigenvectors
        A = self.B_img.T @ self.B_img + np.diag(1e-6 / np.maximum(self.var, 1e-12))
        self._proj = np.linalg.solve(A, self.B_img.T)
        R = Ci / self.s_img
        coef = np.linalg.lstsq(self.B_img, R.T, rcond=None)[0]
        self.train_residual = float(np.median(np.linalg.norm(R.T - self.B_img @ coef, axis=0)
                                              / np.maximum(np.linalg.norm(R, axis=1), 1e-9)))
        log.info("eigenpoints: %d samples from %d annotated frames, %d modes", len(Xj), N, n)

    @staticmethod
    def _features(img) -> np.ndarray:
        """Pixels normalised for gain and offset (lighting)."""
        x = np.asarray(img, np.float64).ravel()
        x = x - x.mean()
        return x / (x.std() + 1e-6)

    def read(self, model_img) -> np.ndarray:
        """Landmarks (L, 2) in model pixels from a pre-warped image (projection on the pixel part)."""
        r = (self._features(model_img) - self.mean_img) / self.s_img
        coef = self._proj @ r
        return (self.mean_pts + self.s_pts * (self.B_pts @ coef)).reshape(-1, 2)

    def residual(self, gray, M) -> float:
        """Relative reconstruction residual of the pixels pre-warped by *M* (model fit quality)."""
        import cv2

        img = cv2.warpAffine(gray, M, self.size, flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_REPLICATE)
        r = (self._features(img) - self.mean_img) / self.s_img
        coef = self._proj @ r
        return float(np.linalg.norm(r - self.B_img @ coef) / max(np.linalg.norm(r), 1e-9))

    def fit(self, gray, M, *, iterations: int = 8, tol: float = 0.1):
        """Iterate pre-warp and projection from the model-to-image affine *M* (2, 3).

        Returns
        -------
        points : ndarray, shape (L, 2)
            Image pixels.
        M : ndarray, shape (2, 3)
            Refined model-to-image affine.
        """
        import cv2

        pts = None
        for _ in range(iterations):
            img = cv2.warpAffine(gray, M, self.size, flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_REPLICATE)
            P = self.read(img)
            new = _apply(M, P)
            # residual misalignment: the rigid points read off vs their canonical place
            D = _affine(self.canon[self.rigid], P[self.rigid])
            M = _compose(M, D)
            if pts is not None and np.abs(new - pts).max() < tol:
                pts = new
                break
            pts = new
        img = cv2.warpAffine(gray, M, self.size, flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_REPLICATE)
        return _apply(M, self.read(img)), M


def track_eigenpoints(frames: Iterable[np.ndarray], annotations, *, rigid_points=None, width: int | None = None,
                      morphs: int = 3, iterations: int = 8, seed: int = 0, progress=None):
    """Track landmarks with an eigen-points model trained on the annotated frames.

    The annotated frames are read first (frames are buffered), the model is
    trained on them, then every frame is tracked from the previous frame's
    affine estimate. Annotated frames return their annotation.

    Parameters
    ----------
    frames : iterable of ndarray (H, W, 3) or (H, W), uint8
    annotations : ndarray (L, 2) or dict of int to ndarray (L, 2)
        Annotated frames by index in *frames* (0 must be among them).
    rigid_points : sequence of int, optional
        Points defining the affine pre-warp; default
        :func:`~retarget_cli.methods.tracking.head.default_rigid_points`.
    width : int, optional
        Width of the normalised face window in pixels (default: see
        :class:`EigenPoints`).
    morphs : int
        In-between shapes per pair of annotated frames.
    iterations : int
        Maximum warp/projection iterations per frame.
    seed : int
    progress : callable, optional

    Returns
    -------
    points : ndarray, shape (T, L, 2)
    confidence : ndarray, shape (T, L)
        ``exp(-(r - r0) / 0.1)`` from the frame's relative pixel reconstruction
        residual ``r`` beyond the median training residual ``r0`` (the same
        for every point of a frame).
    """
    import cv2

    ann = normalize_annotations(annotations)
    if 0 not in ann:
        raise ShapeError(f"annotations: the first frame must be annotated; annotated frames are {list(ann)[:5]}")
    grays = [cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) if f.ndim == 3 else f for f in frames]
    if not grays:
        raise ShapeError("frames: the sequence is empty")
    h, w = grays[0].shape
    for f, P in ann.items():
        if f >= len(grays):
            raise ShapeError(f"annotations: frame {f} is past the last frame ({len(grays) - 1})")
        check_inside(P, (w, h), f"annotations: frame {f}")
    keys = list(ann)
    model = EigenPoints([grays[f] for f in keys], np.stack([ann[f] for f in keys]), rigid_points=rigid_points,
                        width=width, morphs=morphs, seed=seed)
    pts, conf = [], []
    M = None
    for t, g in enumerate(grays):
        if t in ann:
            P = ann[t]
            M = _affine(model.canon[model.rigid], P[model.rigid])
            c = 1.0
        else:
            P, M = model.fit(g, M, iterations=iterations)
            c = float(np.exp(-max(model.residual(g, M) - model.train_residual, 0.0) / 0.1))
        pts.append(P)
        conf.append(np.full(model.n_points, c))
        if progress is not None:
            progress(t)
    return np.stack(pts), np.clip(np.stack(conf), 0, 1)
