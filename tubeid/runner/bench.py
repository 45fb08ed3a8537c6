"""Runner benchmark (``tubeid bench-runner``): speedup from 1 to 2 workers and runner overhead.

A realisation-bound study (one BLAS-free numpy compute loop per realisation, calibrated here to
about ``block_seconds`` per block) is run on the embedded LocalCluster with each worker count.
Per run: wall = store preparation + first submit .. last result + finalisation (cluster start-up
and worker warm-up are one-off costs, reported separately); compute = sum over tasks of the time
inside the study's task function, measured in the task. Overhead = (workers x wall - compute) /
compute: every worker-second not spent computing (scheduling, transfer, Zarr writes, flags, store
creation, provenance, idle tail). The process's one-off imports are warmed up first (untimed). Targets on a 2-core machine: speedup >= 1.8, overhead < 3 %.
"""

from __future__ import annotations

import pathlib
import tempfile
import time

import numpy as np

__all__ = ["main", "startup", "integrity", "BENCH_STUDY", "MAX_BLOCKS", "MAX_COMPUTE_SECONDS"]

BENCH_STUDY = '''
import numpy as np
from tubeid.runner.study import Output, Parameter, Study

def task(block, rng, *, work):
    out = np.empty((block["realisation"].size, 4))
    for j, r in enumerate(block["realisation"]):
        x = rng(realisation=r).standard_normal(4096)
        for _ in range(work):
            x = np.sin(x) * 1.5 + 0.25
        out[j] = x[:4]
    return {"x": out}

study = Study(name="bench-runner", seed=1, axes={"realisation": range(REALISATIONS)},
              chunks={"realisation": PER_BLOCK}, task=task, coords={"component": range(4)},
              outputs={"x": Output(dims=("component",))}, parameters={"work": Parameter(WORK, bounds=(1, None))})
'''

PER_BLOCK = 4

#: The most blocks the benchmark study takes: each block also costs the runner's fixed work (a task, its
#: Zarr writes and flag), which alone makes 10 000 blocks minutes per worker count.
MAX_BLOCKS = 10_000

#: The most compute one worker count's run is asked for (blocks x block_seconds), in seconds: a day.
MAX_COMPUTE_SECONDS = 86_400.0



def _label(workers: int) -> str:
    """A worker count as the table shows it: ``0`` runs the blocks in this process, which counts as one
    worker in the overhead (``RunReport.workers``) but is not a worker process."""
    return "0 (here)" if workers == 0 else str(workers)


def _calibrate(block_seconds: float) -> int:
    """Loop iterations per realisation so that one block takes about ``block_seconds`` here."""
    x = np.random.default_rng(0).standard_normal(4096)
    n = 200
    t0 = time.perf_counter()
    for _ in range(n):
        x = np.sin(x) * 1.5 + 0.25
    per_iter = (time.perf_counter() - t0) / n
    return max(1, int(block_seconds / PER_BLOCK / per_iter))


def startup(reps: int = 6) -> dict:
    """Seconds to start the embedded cluster (2 workers) and run a first task, plain TCP vs ephemeral TLS.

    Alternates the two ``reps`` times in this process; returns the medians and the ratio.
    """
    import logging
    import statistics

    from distributed import Client, LocalCluster
    from distributed.security import Security

    times = {False: [], True: []}
    for _ in range(reps):
        for tls in (False, True):
            t0 = time.perf_counter()
            sec = Security.temporary() if tls else None
            with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None,
                              silence_logs=logging.CRITICAL, security=sec, protocol="tls://" if tls else None) as c, \
                    Client(c, security=sec) as client:
                client.submit(int, 1, pure=False).result()
            times[tls].append(time.perf_counter() - t0)
    plain, tls = statistics.median(times[False]), statistics.median(times[True])
    print(f"embedded cluster start + first task (2 workers, median of {reps}): plain {plain:.2f} s, "
          f"ephemeral TLS {tls:.2f} s, ratio {tls / plain:.2f}")
    return {"plain": plain, "tls": tls, "ratio": tls / plain}


def integrity(mb: float = 16.0, reps: int = 9) -> dict:
    """Cost of the block checksum against the Zarr write of the same block (``mb`` MB of float64), and of
    verifying it (read back + checksum), medians of ``reps`` in this process."""
    import statistics

    import zarr

    from tubeid.runner.integrity import block_checksum

    n = int(mb * 1e6 / 8)
    a = np.random.default_rng(0).standard_normal(n)
    with tempfile.TemporaryDirectory(prefix="tubeid-bench-") as tmp:
        arr = zarr.create_array(f"{tmp}/a.zarr", shape=(n,), chunks=(n,), dtype="float64")
        ts, tw, tv = [], [], []
        for _ in range(reps):
            t0 = time.perf_counter()
            block_checksum({"u": a}, (0,))
            t1 = time.perf_counter()
            arr[:] = a
            t2 = time.perf_counter()
            block_checksum({"u": arr[:]}, (0,))
            t3 = time.perf_counter()
            ts.append(t1 - t0), tw.append(t2 - t1), tv.append(t3 - t2)
    c, w, v = (statistics.median(x) for x in (ts, tw, tv))
    print(f"block of {mb:g} MB: checksum {1e3 * c:.1f} ms ({mb / c:.0f} MB/s), Zarr write {1e3 * w:.1f} ms "
          f"(checksum / write = {c / w:.2f}), verification (read + checksum) {1e3 * v:.1f} ms")
    return {"checksum": c, "write": w, "verify": v}


def main(blocks: int = 16, block_seconds: float = 1.0, worker_counts=(1, 2)) -> int:
    """Run the benchmark (``tubeid bench-runner``); every argument is checked before anything runs.

    Parameters
    ----------
    blocks : int
        Blocks (tasks) of the benchmark study, in [1, MAX_BLOCKS].
    block_seconds : float
        Target compute seconds per block, > 0 and at most a day; ``blocks`` x ``block_seconds`` at most
        :data:`MAX_COMPUTE_SECONDS`.
    worker_counts : sequence of int
        Worker counts to compare, each in [0, ``tubeid._validation.WORKERS_PER_CORE`` x this process's
        usable cores] (0: in this process), the first the baseline of the speedup.

    Returns
    -------
    int
        0 if the stores of every worker count are identical, else 1.
    """
    from tubeid._validation import integer, real, worker_count
    from tubeid.errors import SpecificationError

    blocks = integer("--blocks", blocks, minimum=1, maximum=MAX_BLOCKS)
    block_seconds = real("--block-seconds", block_seconds, unit="s", low=0.0, low_open=True, high=86400.0)
    if blocks * block_seconds > MAX_COMPUTE_SECONDS:
        raise SpecificationError("--blocks", blocks, f"with --block-seconds = {block_seconds:g}: {blocks * block_seconds:g} s "
                                 f"of compute per worker count, more than {MAX_COMPUTE_SECONDS:g} s (a day)")
    worker_counts = list(worker_counts)
    if not worker_counts:
        raise SpecificationError("--workers", worker_counts, "must name at least one worker count")
    worker_counts = [worker_count("--workers", w) for w in worker_counts]

    from tubeid.runner.execute import run
    from tubeid.runner.testing import store_digest

    work = _calibrate(block_seconds)
    with tempfile.TemporaryDirectory(prefix="tubeid-bench-") as tmp:
        # untimed warm-up in this process: one-off imports (xarray's Zarr backend, dask.array) that
        # any first run of a session pays once, not per run
        warm = pathlib.Path(tmp) / "warm_study.py"
        warm.write_text(BENCH_STUDY.replace("REALISATIONS", str(PER_BLOCK)).replace("PER_BLOCK", str(PER_BLOCK))
                        .replace("WORK", "1"))
        run(warm, pathlib.Path(tmp) / "warm.zarr", workers=0, progress=False, quiet=True)
        study = pathlib.Path(tmp) / "bench_study.py"
        study.write_text(BENCH_STUDY.replace("REALISATIONS", str(blocks * PER_BLOCK))
                         .replace("PER_BLOCK", str(PER_BLOCK)).replace("WORK", str(work)))
        print(f"bench-runner: {blocks} blocks x {PER_BLOCK} realisations, ~{block_seconds:g} s compute per block")
        print(f"{'workers':>7} {'startup s':>9} {'wall s':>8} {'compute s':>9} {'writes s':>8} {'overhead':>9} {'speedup':>8}")
        reports, digests = {}, {}
        for w in worker_counts:
            rep = run(study, pathlib.Path(tmp) / f"w{w}.zarr", workers=w, progress=False, quiet=True)
            reports[w] = rep
            digests[w] = store_digest(rep.store)
            overhead = (rep.workers * rep.wall - rep.compute) / rep.compute
            speedup = reports[worker_counts[0]].wall / rep.wall
            print(f"{_label(w):>7} {rep.startup:>9.2f} {rep.wall:>8.2f} {rep.compute:>9.2f} {rep.write:>8.3f} "
                  f"{100 * overhead:>8.2f}% {speedup:>7.2f}x")
    base = reports[worker_counts[0]]
    for w, rep in reports.items():
        inflation = rep.compute / base.compute - 1
        if abs(inflation) > 0.05:  # same work, more time inside tasks: the cores were shared
            print(f"note: compute inside tasks took {100 * inflation:+.0f} % with {_label(w)} vs {_label(worker_counts[0])}: "
                  "other processes competed for the cores, which lowers the speedup; rerun on an idle machine")
    same = all(d == digests[worker_counts[0]] for d in digests.values())
    print(f"stores identical across worker counts: {'yes' if same else 'NO'}")
    print("targets: speedup >= 1.8 on 2 workers (2 cores), overhead < 3 % of compute; the machine's other "
          "load counts against both")
    return 0 if same else 1
