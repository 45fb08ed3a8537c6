"""Worker preload of the embedded LocalCluster: Ctrl-C is the runner's, and a quick exit.

A terminal's Ctrl-C (SIGINT) reaches the whole foreground process group, the embedded cluster's
worker processes included. The runner answers it: it cancels its tasks, closes the cluster (which
stops these processes) and exits 130 with the resume hint. A worker process that took the signal
as well would end on its own and print a KeyboardInterrupt traceback (an idle one does, e.g. while
another worker runs the warm-up). Workers of a cluster tubeid did not start are not concerned.

Under the ``tubeid`` command, the objects a worker process holds when it starts (distributed's, its
imports') are frozen out of the garbage collector (``gc.freeze``): they live as long as the process,
and at its exit the interpreter no longer traverses and tears them down one by one, which made
closing the cluster take most of a second or more. Frozen objects are never collected, so this is
done only where no code of the user's can have run yet: not when the process re-imported a user's
script (multiprocessing's spawn runs the parent's main script as ``__mp_main__``; ``tubeid``'s own
entry point is not re-imported). A study's objects (its module, files it opens, objects in
reference cycles) are created later and finalised at exit as usual (tested:
``tests/test_runner_exit.py``).
"""

from __future__ import annotations

import gc
import os
import signal
import sys

__all__ = ["dask_setup"]


def _inert_start() -> bool:
    """True when no code of a user's can have run in this process: it did not re-import a user's
    script as ``__mp_main__`` (none, or ``tubeid``'s own console script)."""
    path = getattr(sys.modules.get("__mp_main__"), "__file__", None)  # set only for a re-imported script
    return not path or os.path.basename(path) == "tubeid"


def dask_setup(worker) -> None:
    """Ignore SIGINT in this worker process (called by distributed in the worker's main thread); under
    the ``tubeid`` command, freeze the objects it holds so far (before any study code runs)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if _inert_start():
        gc.freeze()
