"""The blendshape rig model: ``f = f0 + D w``.

A rig is a neutral face ``f0`` (N vertices) plus n named delta shapes, the
columns of ``D`` (Lewis et al. 2005, §3; the lecture slides' "coordinate
differences": ``p(t) = b0 + D w(t)``). Whole-face shapes ``b_k`` become deltas
``d_k = b_k - f0``. Each slider has a range ``[lo, hi]`` (``[0, t]`` in Lewis &
Anjyo 2010), and a rig may carry an expression library: named weight vectors
``w_e`` over a subset of the sliders (Lewis & Anjyo 2010, "Unifying
whole-expression and delta blendshape views").

Coordinates are packed ``xyzxyz...``: row ``3 v + a`` of ``D`` is axis ``a``
of vertex ``v``. ``D`` is kept as a dense array or a CSR sparse matrix,
whichever evaluates faster for its density (:data:`SPARSE_BELOW`, measured by
``bench/edit.py``).
"""

from __future__ import annotations

import logging

import numpy as np

from .._validate import check_array, closest
from ..errors import InputError, ParameterError, ShapeError

log = logging.getLogger(__name__)

#: Keep ``D`` sparse (CSR) when fewer than this fraction of its entries are
#: non-zero. Measured on random 75,000 x 100 matrices (25,000 vertices, 100
#: sliders, one BLAS thread): CSR evaluated one frame 2.5-13x faster than dense
#: at densities 0.01-0.4, and 64 frames at once 1.5x faster at density 0.2 but
#: 0.7x at 0.4; ``bench/edit.py`` repeats the comparison on its rig.
SPARSE_BELOW = 0.25

#: Axis letters to coordinate offsets.
AXES = {"x": 0, "y": 1, "z": 2}


def parse_axes(axes) -> tuple[int, ...]:
    """``"xz"`` (or ``["x", "z"]``, or None for all) to sorted axis offsets ``(0, 2)``.

    Raises
    ------
    ValueError
        For an empty selection or a letter other than x, y, z.
    """
    if axes is None:
        return (0, 1, 2)
    letters = list(axes) if isinstance(axes, str) else list(axes)
    if not letters or any(a not in AXES for a in letters) or len(set(letters)) != len(letters):
        raise ParameterError(f"axes: expected a non-empty combination of x, y, z such as 'xy', got {axes!r}")
    return tuple(sorted(AXES[a] for a in letters))


class BlendshapeRig:
    """A delta blendshape rig ``f = f0 + D w`` (Lewis et al. 2005, §3).

    Parameters
    ----------
    neutral : array_like, shape (N, 3)
        ``f0``.
    deltas : array_like, shape (n, N, 3)
        One displacement field per slider.
    names : sequence of str, length n
        Slider names (unique).
    lower, upper : array_like, shape (n,), optional
        Slider ranges; default ``[0, 1]`` (Lewis & Anjyo 2010: ``0 <= w <= t``).
    library : dict, optional
        Expression name to ``{slider: weight}`` (a subset of the sliders).
    storage : {"auto", "dense", "sparse"}
        How ``D`` is kept; ``auto`` chooses by density (:data:`SPARSE_BELOW`).
    template : ObjMesh, optional
        The neutral OBJ, used to write posed meshes byte-for-byte.
    correctives : object, optional
        ``rig.yaml``'s ``correctives`` value, unparsed.

    Attributes
    ----------
    D : ndarray or scipy.sparse.csr_array, shape (3N, n)
        Delta matrix, rows packed ``xyzxyz``.
    f0 : ndarray, shape (3N,)
        Neutral, packed the same way.
    scale : float
        Displacement scale σ: RMS over sliders of each shape's largest vertex
        displacement. The editing regularisers are in units of σ² so they mean
        the same in millimetres or metres.
    """

    def __init__(self, neutral, deltas, names, *, lower=None, upper=None, library=None, storage="auto",
                 template=None, correctives=None):
        import scipy.sparse as sp

        neutral = check_array(neutral, "neutral", ndim=2)
        if neutral.shape[1] != 3:
            raise ShapeError(f"neutral: expected shape (N, 3), got {neutral.shape}")
        deltas = check_array(deltas, "deltas", ndim=3)
        if deltas.shape[1:] != neutral.shape:
            raise ShapeError(f"deltas: expected shape (n, {neutral.shape[0]}, 3) to match the neutral, got {deltas.shape}")
        names = tuple(str(n) for n in names)
        n = deltas.shape[0]
        if len(names) != n:
            raise ShapeError(f"names: expected {n} slider names, got {len(names)}")
        if len(set(names)) != n:
            dup = next(x for x in names if names.count(x) > 1)
            raise ParameterError(f"names: slider {dup!r} appears twice")
        self.names = names
        self.index = {name: i for i, name in enumerate(names)}
        self.lower = np.zeros(n) if lower is None else check_array(lower, "lower", ndim=1)
        self.upper = np.ones(n) if upper is None else check_array(upper, "upper", ndim=1)
        if self.lower.shape != (n,) or self.upper.shape != (n,) or np.any(self.lower >= self.upper):
            raise ShapeError(f"lower, upper: expected shape ({n},) each with lower < upper")
        self.neutral = neutral
        self.f0 = neutral.ravel().copy()
        Dd = np.ascontiguousarray(deltas.transpose(1, 2, 0).reshape(-1, n))
        self.density = float(np.count_nonzero(Dd)) / max(Dd.size, 1)
        peaks = np.sqrt(np.max((deltas**2).sum(axis=2), axis=1)) if n else np.zeros(0)
        live = peaks[peaks > 0]
        #: RMS over sliders of each shape's largest vertex displacement (rig units).
        self.scale = float(np.sqrt(np.mean(live**2))) if live.size else 1.0
        if storage not in ("auto", "dense", "sparse"):
            raise ParameterError(f"storage: expected 'auto', 'dense' or 'sparse', got {storage!r}")
        self.sparse = storage == "sparse" or (storage == "auto" and self.density < SPARSE_BELOW)
        self.D = sp.csr_array(Dd) if self.sparse else Dd
        self.template = template
        self.correctives = correctives
        self.spec = None  # the parsed rig.yaml, set by load()
        self.landmarks = None  # rig.yaml's landmarks, checked: (landmark ids, vertex ids), set by load()
        self.library = {}
        for expr, vec in (library or {}).items():
            self.library[str(expr)] = {self._slider(s, f"library {expr!r}"): float(v) for s, v in vec.items()}
        self._gram = None
        dead = [names[i] for i in np.flatnonzero(np.asarray(abs(self.D).sum(axis=0)).ravel() == 0)]
        if dead:
            log.warning("rig sliders %s move no vertex", ", ".join(dead))

    # ------------------------------------------------------------------ basics

    @property
    def n_vertices(self) -> int:
        return int(self.neutral.shape[0])

    @property
    def n_sliders(self) -> int:
        return len(self.names)

    def _slider(self, name, where: str) -> str:
        if name not in self.index:
            hint = closest(str(name), self.names)
            raise InputError(f"{where}: unknown slider {name!r}" + (f"; did you mean {hint!r}?" if hint else
                                                                    f"; the rig's sliders are {', '.join(self.names)}"))
        return str(name)

    def check_vertices(self, vertices, where: str = "vertices") -> np.ndarray:
        """Vertex ids as int64, each in ``[0, N)``; a clear error otherwise."""
        v = np.asarray(vertices)
        if v.ndim == 0:
            v = v[None]
        if v.ndim != 1 or v.size == 0 or (v.dtype.kind == "f" and np.any(v % 1 != 0)) or v.dtype.kind not in "iuf":
            raise ShapeError(f"{where}: expected a non-empty list of integer vertex ids, got {vertices!r}")
        v = v.astype(np.int64)
        bad = v[(v < 0) | (v >= self.n_vertices)]
        if bad.size:
            raise ShapeError(f"{where}: vertex {int(bad[0])} is outside the mesh "
                             f"({self.n_vertices} vertices, ids 0-{self.n_vertices - 1})")
        return v

    def rows(self, vertices, axes=None, where: str = "vertices") -> np.ndarray:
        """Coordinate rows of ``D`` for *vertices* and *axes* (``"xyz"`` subset), vertex-major.

        Returns
        -------
        ndarray, shape (len(vertices) * len(axes),), int64
        """
        v = self.check_vertices(vertices, where)
        a = np.asarray(parse_axes(axes))
        return (3 * v[:, None] + a[None, :]).ravel()

    def block(self, rows) -> np.ndarray:
        """Dense rows of ``D``: the ``B̄`` of Lewis & Anjyo (2010), shape (len(rows), n)."""
        B = self.D[np.asarray(rows)]
        return B.toarray() if self.sparse else np.array(B)

    def gram(self) -> np.ndarray:
        """``DᵀD``, shape (n, n), computed once and cached."""
        if self._gram is None:
            G = self.D.T @ self.D
            self._gram = np.asarray(G.toarray() if self.sparse else G)
        return self._gram

    # ------------------------------------------------------------------ evaluation

    def evaluate(self, w) -> np.ndarray:
        """Posed vertices ``f0 + D w``.

        Parameters
        ----------
        w : array_like, shape (n,) or (T, n)

        Returns
        -------
        ndarray, shape (N, 3) or (T, N, 3)
        """
        w = np.asarray(w, dtype=np.float64)
        if w.shape[-1:] != (self.n_sliders,) or w.ndim not in (1, 2):
            raise ShapeError(f"w: expected shape ({self.n_sliders},) or (T, {self.n_sliders}), got {w.shape}")
        if w.ndim == 1:
            return (self.f0 + self.D @ w).reshape(-1, 3)
        F = np.asarray(self.D @ w.T).T + self.f0
        return F.reshape(len(w), -1, 3)

    def coords(self, rows, w) -> np.ndarray:
        """Posed coordinates of some rows only, ``f0[rows] + D[rows] w``; w (n,) or (T, n)."""
        rows = np.asarray(rows)
        B = self.block(rows)
        return self.f0[rows] + np.asarray(w) @ B.T

    # ------------------------------------------------------------------ library

    def weights(self, values: dict, where: str = "weights") -> np.ndarray:
        """A full weight vector from ``{slider: value}`` (others 0)."""
        w = np.zeros(self.n_sliders)
        for name, v in values.items():
            w[self.index[self._slider(name, where)]] = float(v)
        return w

    def expression_blend(self, blend: dict, base=None, where: str = "expressions") -> np.ndarray:
        """``w0`` from a blend of library expressions (Lewis & Anjyo 2010, whole-expression/delta unification).

        The blend ``Σ c_e w_e`` sets every slider some blended expression
        specifies; the other sliders keep *base* (0 when None), since a library
        vector may cover only a subset of the sliders (e.g. only the mouth).

        Parameters
        ----------
        blend : dict
            Expression name to coefficient ``c_e``.
        base : array_like, shape (n,), optional

        Returns
        -------
        ndarray, shape (n,)
        """

        w = np.zeros(self.n_sliders) if base is None else np.array(base, dtype=np.float64)
        covered = np.zeros(self.n_sliders, dtype=bool)
        total = np.zeros(self.n_sliders)
        for expr, c in blend.items():
            if expr not in self.library:
                hint = closest(str(expr), self.library)
                known = ", ".join(self.library) or "none"
                raise InputError(f"{where}: unknown expression {expr!r}" + (f"; did you mean {hint!r}?" if hint else
                                                                            f"; the rig's library has {known}"))
            for name, v in self.library[expr].items():
                i = self.index[name]
                covered[i] = True
                total[i] += float(c) * v
        w[covered] = total[covered]
        return w


__all__ = ["AXES", "BlendshapeRig", "SPARSE_BELOW", "parse_axes"]
