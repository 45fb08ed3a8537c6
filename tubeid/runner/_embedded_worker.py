"""Worker preload of the embedded LocalCluster: its worker processes leave Ctrl-C to the runner.

A terminal's Ctrl-C (SIGINT) reaches the whole foreground process group, the embedded cluster's
worker processes included. The runner answers it: it cancels its tasks, closes the cluster (which
stops these processes) and exits 130 with the resume hint. A worker process that took the signal
as well would end on its own and print a KeyboardInterrupt traceback (an idle one does, e.g. while
another worker runs the warm-up). Workers of a cluster tubeid did not start are not concerned.
"""

from __future__ import annotations

import signal

__all__ = ["dask_setup"]


def dask_setup(worker) -> None:
    """Ignore SIGINT in this worker process (called by distributed in the worker's main thread)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
