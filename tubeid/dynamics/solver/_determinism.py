"""Bit-identical results whatever the caller's BLAS threads.

The tables of a realisation (eigenvectors, their inverse, products with the load matrix) come
from LAPACK/BLAS, and OpenBLAS's results for the model sizes here depend on its thread count: on
paper-reference's 50 coordinates, 1 and 2 threads give inverse eigenvectors that differ in the
last bits (about 1e-12 relative in the slope and transition tables), which the chaotic stop
amplifies into visibly different series after a few seconds. Dask workers run with one BLAS
thread (their nanny sets it) while a Python session or a ``--workers 0`` run may use several, so
every table is computed under :func:`one_blas_thread`: the runner's promise (bit-identical stores on
any number of workers and in-process) then holds. numba's compiled kernels do not call BLAS, and
code compiled in the process equals code loaded from numba's on-disk cache (checked by
``tests/test_solver.py``).
"""

from __future__ import annotations

import contextlib

import numpy  # noqa: F401  (loads numpy's BLAS before the controller looks for libraries)
import scipy.linalg  # noqa: F401  (and scipy's)

__all__ = ["one_blas_thread"]

_controller = None


def one_blas_thread():
    """Context manager limiting every loaded BLAS library to one thread."""
    global _controller
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:  # pragma: no cover - threadpoolctl is a dependency
        return contextlib.nullcontext()
    if _controller is None:
        _controller = ThreadpoolController()
    return _controller.limit(limits=1, user_api="blas")
