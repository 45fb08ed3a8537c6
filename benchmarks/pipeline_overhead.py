"""Where a pipeline run's wall time goes besides its blocks' compute, from the runner's own report.

    python benchmarks/pipeline_overhead.py STUDY STORE [--set NAME=VALUE ...] [--workers N]

Runs ``STUDY`` (e.g. ``studies/paper.py``) into the new store ``STORE`` through
``tubeid.runner.run`` on the embedded cluster and prints, from the ``PipelineReport``: the cluster's
start-up, then per stage its ``prepare`` (building the stage in the runner), ``tasks`` (first submit
to last result), ``finalise``, the blocks' summed ``compute`` and ``write``, and its *overhead*:
prepare + tasks + finalise - (compute + write) / workers, the wall time the stage spends beyond its
blocks' work shared evenly over the workers (tails, the workers' stage builds, bookkeeping). The
last line gives the in-process total, the sum of the stages' overheads and the run's wall time
minus the blocks' work per worker. The process's own exit is not in it (``time`` the command for that).
Run it from outside the checkout being measured to time another tree (``PYTHONPATH=TREE``).
"""

from __future__ import annotations

import argparse
import time

T0 = time.perf_counter()

from tubeid.runner import run  # noqa: E402  (the import is part of what is timed)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("study")
    parser.add_argument("store", help="a new store (refused if it holds another study)")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    parser.add_argument("--workers", type=int, default=None)
    args = parser.parse_args()
    overrides = dict(kv.split("=", 1) for kv in args.set)
    t_import = time.perf_counter() - T0
    rep = run(args.study, args.store, workers=args.workers, overrides=overrides, progress=False, quiet=True)
    total = time.perf_counter() - T0
    n = max(rep.workers, 1)
    print(f"import {t_import:.2f} s, cluster start-up {rep.startup:.2f} s, workers {n}")
    print(f"{'stage':14s} {'blocks':>6s} {'prepare':>8s} {'tasks':>8s} {'finalise':>8s} {'compute':>8s} "
          f"{'write':>6s} {'overhead':>8s}")
    overhead = work = 0.0
    for name, r in rep.stages.items():
        o = r.prepare + r.tasks + r.finalise - (r.compute + r.write) / n
        overhead += o
        work += (r.compute + r.write) / n
        print(f"{name:14s} {r.computed:6d} {r.prepare:8.2f} {r.tasks:8.2f} {r.finalise:8.2f} {r.compute:8.2f} "
              f"{r.write:6.2f} {o:8.2f}")
    print(f"total {total:.2f} s in this process; stage overheads {overhead:.2f} s; total minus work per worker "
          f"{total - work:.2f} s")


if __name__ == "__main__":
    main()
