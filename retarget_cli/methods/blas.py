"""BLAS thread limits for many small products and solves (the decomposition, the trackers' fits)."""

from __future__ import annotations

import contextlib


def one_blas_thread(n_rows: int):
    """Limit BLAS to one thread for large batches: the many small products run faster unthreaded."""
    return contextlib.nullcontext() if n_rows < 512 else small_blas()


_CONTROLLER = None


@contextlib.contextmanager
def small_blas():
    """Run BLAS single-threaded: for many small products and solves threads only add overhead.

    Measured (``bench/edit.py``, 2 busy cores): bounded solves on a
    100-slider rig took 2-3x longer with OpenBLAS's default threads. The
    controller is created once: inspecting the loaded libraries costs about
    half a millisecond.
    """
    global _CONTROLLER
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:  # pragma: no cover - threadpoolctl ships with scikit-learn
        yield
        return
    if _CONTROLLER is None:
        _CONTROLLER = ThreadpoolController()
    with _CONTROLLER.limit(limits=1, user_api="blas"):
        yield
