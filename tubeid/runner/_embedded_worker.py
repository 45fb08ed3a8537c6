"""Worker preload of the embedded LocalCluster: Ctrl-C is the runner's, and a quick exit.

A terminal's Ctrl-C (SIGINT) reaches the whole foreground process group, the embedded cluster's
worker processes included. The runner answers it: it cancels its tasks, closes the cluster (which
stops these processes) and exits 130 with the resume hint. A worker process that took the signal
as well would end on its own and print a KeyboardInterrupt traceback (an idle one does, e.g. while
another worker runs the warm-up). Workers of a cluster tubeid did not start are not concerned.

The objects the worker process holds when it starts (distributed's, its imports') are frozen out of
the garbage collector (``gc.freeze``): they live as long as the process, and at its exit the
interpreter no longer traverses and tears them down one by one, which made closing the cluster
take most of a second. This runs before any study code: what a study creates (its module, open files,
objects in reference cycles) is collected and finalised at exit as usual.
"""

from __future__ import annotations

import gc
import signal

__all__ = ["dask_setup"]


def dask_setup(worker) -> None:
    """Ignore SIGINT in this worker process (called by distributed in the worker's main thread) and
    freeze the objects it holds so far (before any study code runs)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    gc.freeze()
