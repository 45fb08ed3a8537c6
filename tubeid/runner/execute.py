"""Run a study: validate, prepare the store, submit one dask task per unfinished block, finalise.

Everything that can be refused (study definition, parameters, store path, store identity) is
checked before any task is submitted. Tasks are idempotent (a block always writes the same bytes
to the same chunks, its flag last), so a rescheduled task after a worker death, a concurrent
duplicate or a resumed run cannot change the result.
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib.util
import logging
import os
import pathlib
import sys
import time

from tubeid import config
from tubeid.errors import SpecificationError
from tubeid.runner.store import (block_flags, check_store, init_store, now, prepare_path, read_attrs,
                                 tubeid_version, update_attrs, write_block)
from tubeid.runner.study import load_study

__all__ = ["run", "run_block", "RunReport", "default_store", "scheduler_address"]


@dataclasses.dataclass
class RunReport:
    """What a run did. Times in seconds (wall clock of this process; compute/write summed over tasks)."""

    store: pathlib.Path
    total: int
    computed: int
    skipped: int
    workers: int
    startup: float = 0.0      # cluster start or connection
    prepare: float = 0.0      # store creation / checks
    tasks: float = 0.0        # first submit -> last result
    finalise: float = 0.0     # provenance update
    compute: float = 0.0      # sum over tasks of the study task itself
    write: float = 0.0        # sum over tasks of the region + flag writes
    dashboard: str = ""

    @property
    def wall(self) -> float:
        """Run wall time excluding cluster start-up."""
        return self.prepare + self.tasks + self.finalise


def run_block(store: str, source: str, overrides: dict, index: tuple[int, ...]) -> dict:
    """Worker side: compute one block from the study source and write it (data, then flag)."""
    study, _, _ = load_study(source=source, overrides=overrides)
    block = study.block(index)
    t0 = time.perf_counter()
    outputs = study.compute_block(block)
    t1 = time.perf_counter()
    write_block(store, study, block, outputs)
    t2 = time.perf_counter()
    return {"index": tuple(index), "compute": t1 - t0, "write": t2 - t1, "pid": os.getpid()}


def default_store(study_name: str) -> pathlib.Path:
    return pathlib.Path(config.get("runner.store-root", "results")) / f"{study_name}.zarr"


def scheduler_address(explicit: str | None = None) -> str | None:
    """``explicit``, else ``tubeid.runner.scheduler-address``, else ``DASK_SCHEDULER_ADDRESS``, else None."""
    return explicit or config.get("runner.scheduler-address") or os.environ.get("DASK_SCHEDULER_ADDRESS") or None


def _log(msg, quiet):
    if not quiet:
        print(msg, file=sys.stderr, flush=True)


@contextlib.contextmanager
def _client(workers: int | None, scheduler: str | None, quiet: bool):
    """A distributed Client: to ``scheduler`` if given, else to an embedded loopback LocalCluster."""
    import dask
    from distributed import Client, LocalCluster

    if scheduler:
        try:
            client = Client(scheduler, timeout=config.get("runner.connect-timeout", "20s"))
        except (OSError, TypeError, ValueError) as exc:  # unreachable, refused, or TLS misconfigured
            raise SpecificationError("scheduler", scheduler, f"cannot connect: {type(exc).__name__}: {exc}") from exc
        with client:
            client.run(_warm)
            yield client
        return
    n = workers or config.get("runner.workers") or os.cpu_count() or 1
    with dask.config.set({"distributed.scheduler.allowed-failures": config.get("runner.allowed-failures", 3)}):
        cluster = LocalCluster(n_workers=int(n), threads_per_worker=int(config.get("runner.threads-per-worker", 1)),
                               processes=True, host=config.get("runner.host", "127.0.0.1"),
                               dashboard_address=config.get("runner.dashboard-address", "127.0.0.1:0"),
                               silence_logs=logging.CRITICAL)
    with cluster, Client(cluster) as client:
        client.run(_warm)  # imports once per worker, before the clock of the first task starts
        yield client


def _warm() -> None:
    import tubeid.runner.store  # noqa: F401  (xarray, zarr)


def run(study_path, store=None, *, workers: int | None = None, scheduler: str | None = None,
        overrides: dict | None = None, new_store: bool = False, overwrite: bool = False,
        progress: bool | None = None, quiet: bool = False) -> RunReport:
    """Run (or resume) the study in ``study_path`` into the Zarr ``store``; see ``tubeid run --help``.

    workers: embedded LocalCluster size (default: configuration, else one per core; 0 runs the
    blocks sequentially in this process, for debugging); scheduler: address of an existing
    scheduler (default: configuration, then DASK_SCHEDULER_ADDRESS).
    """
    overrides = dict(overrides or {})
    study, source, key = load_study(study_path, overrides=overrides)  # validates the definition
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 0):
        raise SpecificationError("workers", workers, "must be a non-negative integer")
    scheduler = scheduler_address(scheduler) if workers is None else scheduler
    if scheduler and workers is not None:
        raise SpecificationError("workers", workers, "give either --workers or --scheduler, not both")
    path = pathlib.Path(store) if store is not None else default_store(study.name)
    if new_store:
        path = path.with_name(f"{path.name.removesuffix('.zarr')}-{key[:8]}.zarr")
    path = prepare_path(path).resolve()
    state = "new" if overwrite else check_store(path, key)
    progress = config.get("runner.progress", True) if progress is None else progress

    report = RunReport(store=path, total=study.n_blocks, computed=0, skipped=0, workers=0)
    if state == "resume" and block_flags(path).all():
        report.skipped = study.n_blocks
        _log(f"tubeid: {path} is complete ({study.n_blocks} blocks): nothing to do", quiet)
        return report
    t0 = time.perf_counter()
    with (contextlib.nullcontext() if workers == 0 else _client(workers, scheduler, quiet)) as client:
        report.startup = time.perf_counter() - t0
        t0 = time.perf_counter()
        if state == "new":
            init_store(study, path, source=source, study_hash=key, study_file=str(study_path), overrides=overrides)
            _log(f"tubeid: new store {path} ({study.n_blocks} blocks)", quiet)
        else:
            attrs = read_attrs(path)
            if attrs.get("tubeid_version") != tubeid_version():
                _log(f"tubeid: warning: {path} was started with tubeid {attrs.get('tubeid_version')}, "
                     f"resuming with {tubeid_version()}; use --overwrite if the results may differ", quiet)
            update_attrs(path, runs=list(attrs.get("runs", [])) + [now()])
        flags = block_flags(path)
        todo = [b.index for b in study.blocks() if not flags[b.index]]
        report.skipped = study.n_blocks - len(todo)
        if state == "resume":
            _log(f"tubeid: resuming {path}: {report.skipped}/{study.n_blocks} blocks already done", quiet)
        report.prepare = time.perf_counter() - t0
        show = progress and not quiet
        if client is None:
            _run_here(study, path, source, overrides, todo, report, show)
        else:
            _run_dask(client, scheduler, path, source, overrides, key, todo, report, show, quiet)
    t0 = time.perf_counter()
    if not block_flags(path).all():
        raise RuntimeError(f"{path}: run ended with unfinished blocks")  # should not happen
    update_attrs(path, finished=now())
    report.finalise = time.perf_counter() - t0
    _log(f"tubeid: done: {report.computed} blocks computed, {report.skipped} already done; store {path}", quiet)
    return report


def _bar(total, initial, enabled):
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=initial, unit="block", disable=not enabled, file=sys.stderr,
                dynamic_ncols=True, smoothing=0.1)


def _account(report, res, bar):
    report.computed += 1
    report.compute += res["compute"]
    report.write += res["write"]
    bar.update(1)


def _run_here(study, path, source, overrides, todo, report, progress):
    report.workers = 1
    t0 = time.perf_counter()
    with _bar(report.total, report.skipped, progress) as bar:
        for index in todo:
            _account(report, run_block(str(path), source, overrides, index), bar)
    report.tasks = time.perf_counter() - t0


def _run_dask(client, scheduler, path, source, overrides, key, todo, report, progress, quiet):
    from distributed import as_completed

    info = client.scheduler_info(n_workers=-1)
    report.workers = len(info["workers"])
    link = (getattr(client, "dashboard_link", "") or "") if "dashboard" in info.get("services", {}) else ""
    report.dashboard = link
    if link and importlib.util.find_spec("bokeh") is None:
        link += " (its plots need bokeh>=3.1 installed)"
    where = scheduler or f"embedded LocalCluster ({report.workers} single-threaded worker processes)"
    _log(f"tubeid: running on {where}" + (f"; dashboard {link}" if link else ""), quiet)
    t1 = time.perf_counter()
    futures = [client.submit(run_block, str(path), source, overrides, index, pure=False,
                             key=f"tubeid-{key[:10]}-block-{'-'.join(map(str, index))}")
               for index in todo]
    try:
        with _bar(report.total, report.skipped, progress) as bar:
            for fut in as_completed(futures):
                _account(report, fut.result(), bar)
    except BaseException:
        client.cancel(futures)
        raise
    report.tasks = time.perf_counter() - t1
