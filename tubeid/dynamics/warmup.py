"""Compiling the numba solver up front: is this machine's cache cold, and compile it.

The solver's kernels are compiled by numba on first use and cached on disk (``cache=True``; in the
package's ``__pycache__``, or numba's user-wide cache directory when that is not writable, or
``NUMBA_CACHE_DIR``). A cold cache costs about 55 s of CPU in the first call; a study whose
tasks call the solver declares a :class:`tubeid.runner.Warmup` made of these two functions, so
the runner compiles once per machine, saying so, before the first block instead of sitting at
0 blocks done (``studies/paper.py``)::

    Warmup(MESSAGE, run=compile_solver, needed=cache_is_cold)
"""

from __future__ import annotations

__all__ = ["cache_is_cold", "compile_solver", "MESSAGE"]

MESSAGE = "compiling the solver, once per machine, ~55 s"


def _kernels():
    from tubeid.dynamics.solver import _fastpath

    # the default method's main loop (its callees compile with it); symplectic Euler, a baseline,
    # compiles on first use
    return [_fastpath.run_exact]


def cache_is_cold() -> bool:
    """True if a solver kernel has no compiled version in this machine's numba cache (nor in memory).

    Reads numba's cache index (the overloads compiled for this source file and CPU); a kernel that
    cannot be inspected counts as cold.
    """
    for kernel in _kernels():
        if not hasattr(kernel, "overloads"):  # a plain function (NUMBA_DISABLE_JIT): nothing to compile
            continue
        if kernel.overloads:  # compiled (or loaded) in this process already
            continue
        try:
            if not kernel._cache._cache_file._load_index():
                return True
        except Exception:  # no cache (caching disabled) or another numba layout: compile to be sure
            return True
    return False


def compile_solver() -> None:
    """Compile (or load from the cache) the solver's kernel by a short run of the default method."""
    from tubeid.dynamics.response import ResponseSettings, simulate_responses
    from tubeid.mechanics.library import builtin_spec
    from tubeid.mechanics.reduction import reduce
    from tubeid.uncertainty.loads import force_and_moment

    model = reduce(builtin_spec("paper-simplified"))
    load = force_and_moment(18.0, 20.0)
    simulate_responses(model, load, [0], seed=0, settings=ResponseSettings(duration=0.5, discard=0.0, segment_seconds=0.25))
