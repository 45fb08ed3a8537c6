"""The solver's warm-up: the check reads the real kernel's numba cache (tubeid.dynamics.warmup), and the
pipelines whose stages run the solver (studies/paper.py, tubeid diagnose's) declare it."""

import os
import pathlib
import subprocess
import sys

from tubeid.dynamics import warmup

REPO = pathlib.Path(__file__).resolve().parents[1]


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


def _declares_the_solver_warmup(pipeline) -> None:
    """The pipeline's Warmup compiles the solver when its numba cache is cold, announcing it."""
    from tubeid.runner.study import Warmup

    w = pipeline.warmup
    assert isinstance(w, Warmup), f"pipeline {pipeline.name!r} declares no warm-up (warmup={w!r})"
    assert (w.run, w.needed, w.message) == (warmup.compile_solver, warmup.cache_is_cold, warmup.MESSAGE), \
        f"pipeline {pipeline.name!r}: the warm-up {w!r} is not the solver's (tubeid.dynamics.warmup)"


def test_the_paper_study_declares_the_solver_warmup():
    """studies/paper.py's stages call the solver: the first run compiles it up front, saying so."""
    from tubeid.runner.study import load_definition

    pipeline, _, _ = load_definition(REPO / "studies" / "paper.py")
    _declares_the_solver_warmup(pipeline)


def test_the_diagnose_pipeline_declares_the_solver_warmup():
    """tubeid diagnose's pipeline runs the solver in its stages: the same up-front compile."""
    from tubeid.diagnose.stages import study

    _declares_the_solver_warmup(study)


def test_with_numba_jit_disabled_nothing_is_cold():
    """NUMBA_DISABLE_JIT=1 (debugging): the kernels are plain functions, nothing to compile or warn about."""
    out = subprocess.run([sys.executable, "-c", "from tubeid.dynamics import warmup; print(warmup.cache_is_cold())"],
                         capture_output=True, text=True, env=dict(os.environ, NUMBA_DISABLE_JIT="1"), timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "False", out.stderr[-2000:]
