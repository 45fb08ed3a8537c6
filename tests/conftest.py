"""Test-session settings: one BLAS thread per process (the tests' matrices are small; several
BLAS threads on 2 cores only contend — measured 55 s vs 9.5 s for one diagnosis under load)."""

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from threadpoolctl import threadpool_limits  # noqa: E402

threadpool_limits(limits=1)
