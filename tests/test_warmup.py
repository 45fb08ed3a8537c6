"""The solver's warm-up check reads the real kernel's numba cache (tubeid.dynamics.warmup)."""

import os
import subprocess
import sys

from tubeid.dynamics import warmup


def test_an_empty_numba_cache_is_cold_in_a_new_process(tmp_path):
    """A process pointed at an empty NUMBA_CACHE_DIR must see a cold cache (a stale kernel name, or a
    check that never reads the index, would answer warm or raise)."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))
    code = "from tubeid.dynamics import warmup; print(warmup.cache_is_cold())"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "True", out.stderr


def test_the_kernel_checked_is_the_one_the_default_method_runs():
    """After a run of the default method in this process the check answers warm: it inspects the
    kernel that run compiled (or loaded), not another one."""
    warmup.compile_solver()
    assert warmup.cache_is_cold() is False
    assert all(k.overloads for k in warmup._kernels())
