"""Run a study or a pipeline: validate, prepare the store, submit one dask task per unfinished block, finalise.

Everything that can be refused (study definition, parameters, store path, store identity) is
checked before any task is submitted (for a pipeline stage built from earlier results: before
that stage's tasks). Tasks are idempotent (a block always writes the same bytes to the same
chunks, its flag last), so a rescheduled task after a worker death, a concurrent duplicate or a
resumed run cannot change the result. A pipeline runs its stages in order on the same cluster; a
worker rebuilds a stage from the pipeline source and the earlier stages' stored results (once per
process) and checks that it gets the stage hash the client computed.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import importlib.util
import logging
import os
import pathlib
import sys
import time

from tubeid import config
from tubeid.errors import SpecificationError
from tubeid.runner.pipeline import Pipeline, stage_hash
from tubeid.runner.store import (block_flags, check_blocks, check_stage, check_store, init_pipeline_store, init_stage, init_store, now,
                                 prepare_path, read_attrs, tubeid_version, update_attrs, write_block)
from tubeid.runner.study import _plain, load_definition, load_study

__all__ = ["run", "run_block", "run_stage_block", "stage_study", "RunReport", "PipelineReport", "default_store",
           "scheduler_address"]


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


@dataclasses.dataclass
class PipelineReport:
    """What a pipeline run did: one ``RunReport`` per stage run or skipped (``prepare`` includes
    building the stage from the earlier results), plus cluster start-up and root bookkeeping."""

    store: pathlib.Path
    stages: dict = dataclasses.field(default_factory=dict)
    workers: int = 0
    startup: float = 0.0
    prepare: float = 0.0      # root store creation / checks
    finalise: float = 0.0     # root provenance update
    dashboard: str = ""

    total = property(lambda self: sum(r.total for r in self.stages.values()))
    computed = property(lambda self: sum(r.computed for r in self.stages.values()))
    skipped = property(lambda self: sum(r.skipped for r in self.stages.values()))
    compute = property(lambda self: sum(r.compute for r in self.stages.values()))

    @property
    def wall(self) -> float:
        """Run wall time excluding cluster start-up."""
        return self.prepare + sum(r.wall for r in self.stages.values()) + self.finalise


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


_STAGES: dict[tuple, object] = {}


def stage_study(pipeline: Pipeline, key: str, store, name: str):
    """Build stage ``name`` from the earlier stages' stored results: ``(study, stage hash)``.

    The earlier stages are opened from ``store`` without dask (lazy numpy-backed arrays), with the
    attributes their ``summarize`` wrote; the stage hash covers their hashes and summaries too.
    """
    import xarray as xr

    from tubeid.runner.store import FLAG, store_status

    names = pipeline.stage_names
    results, upstream = {}, []
    for earlier in names[:names.index(name)]:
        st = store_status(store, earlier)
        if not st["complete"]:
            raise SpecificationError(f"stages.{name}", name, f"needs stage {earlier!r} complete in {store}")
        results[earlier] = xr.open_zarr(str(store), group=earlier, chunks=None).drop_vars(FLAG)
        a = st["attrs"]
        upstream.append((earlier, a["stage_hash"], {k: a[k] for k in a.get("summary_keys", [])}))
    study = pipeline.stage(name, results)
    return study, stage_hash(key, study, upstream)


def run_stage_block(store: str, source: str, overrides: dict, name: str, expected_hash: str,
                    index: tuple[int, ...]) -> dict:
    """Worker side: compute one block of pipeline stage ``name`` and write it into its group."""
    ck = (store, expected_hash)
    if ck not in _STAGES:
        pipeline, _, key = load_definition(source=source, overrides=overrides)
        study, h = stage_study(pipeline, key, store, name)
        if h != expected_hash:
            raise RuntimeError(f"stage {name!r} was rebuilt with hash {h[:12]} on this worker, {expected_hash[:12]} by "
                               "the runner: the stage function must be deterministic (and read the same store)")
        _STAGES[ck] = study
    study = _STAGES[ck]
    block = study.block(index)
    t0 = time.perf_counter()
    outputs = study.compute_block(block)
    t1 = time.perf_counter()
    write_block(store, study, block, outputs, group=name)
    t2 = time.perf_counter()
    return {"index": tuple(index), "compute": t1 - t0, "write": t2 - t1, "pid": os.getpid()}


def _summary(study, store, group=None) -> dict:
    """The study's ``summarize`` values (plain, checked against provenance names) plus ``summary_keys``."""
    if study.summarize is None:
        return {}
    import xarray as xr

    from tubeid.runner.store import FLAG

    ds = (xr.open_zarr(str(store), group=group, chunks=None) if group else xr.open_zarr(str(store), chunks=None))
    attrs = dict(ds.attrs)
    values = study.summarize(ds.drop_vars(FLAG))
    if not isinstance(values, dict):
        raise SpecificationError("summarize", type(values).__name__, "must return a dict {name: plain value}")
    out = {}
    reserved = (set(attrs) - set(attrs.get("summary_keys", []))) | {"summary_keys", "blocks_done", "blocks_total"}
    for k, v in values.items():
        if not isinstance(k, str) or k in reserved:
            raise SpecificationError("summarize", k, "must name new attributes (not provenance names)")
        out[k] = _plain(v, f"summarize.{k}")
    out["summary_keys"] = sorted(out)
    return out


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


def _record_resume(path, quiet) -> None:
    """Append this start to the store's runs; warn when another tubeid version started it."""
    attrs = read_attrs(path)
    if attrs.get("tubeid_version") != tubeid_version():
        _log(f"tubeid: warning: {path} was started with tubeid {attrs.get('tubeid_version')}, "
             f"resuming with {tubeid_version()}; use --overwrite if the results may differ", quiet)
    update_attrs(path, runs=list(attrs.get("runs", [])) + [now()])


def run(study_path, store=None, *, workers: int | None = None, scheduler: str | None = None,
        overrides: dict | None = None, new_store: bool = False, overwrite: bool = False,
        progress: bool | None = None, quiet: bool = False) -> RunReport:
    """Run (or resume) the study in ``study_path`` into the Zarr ``store``; see ``tubeid run --help``.

    workers: embedded LocalCluster size (default: configuration, else one per core; 0 runs the
    blocks sequentially in this process, for debugging); scheduler: address of an existing
    scheduler (default: configuration, then DASK_SCHEDULER_ADDRESS).
    """
    base, source, _ = load_definition(study_path)  # validates the definition as written
    # each --set value as its parameter's check makes it (e.g. a model file read into its content, checked
    # now, never from a cache): the workers and the study hash get that, not the raw text
    overrides = {k: base.parameters[k].check(k, v) if k in base.parameters else v for k, v in dict(overrides or {}).items()}
    study, source, key = load_definition(study_path, source=source, overrides=overrides)
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

    if isinstance(study, Pipeline):
        return _run_pipeline(study, source, key, study_path, path, state, workers, scheduler, overrides, progress, quiet)

    report = RunReport(store=path, total=study.n_blocks, computed=0, skipped=0, workers=0)
    if state == "resume":
        check_blocks(path, study)
    if state == "resume" and block_flags(path).all():
        report.skipped = study.n_blocks
        if not read_attrs(path).get("finished"):  # every block written, but stopped before the finalisation
            update_attrs(path, finished=now(), **_summary(study, path))
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
            _record_resume(path, quiet)
        flags = block_flags(path)
        todo = [b.index for b in study.blocks() if not flags[b.index]]
        report.skipped = study.n_blocks - len(todo)
        if state == "resume":
            _log(f"tubeid: resuming {path}: {report.skipped}/{study.n_blocks} blocks already done", quiet)
        report.prepare = time.perf_counter() - t0
        show = progress and not quiet
        fn = functools.partial(run_block, str(path), source, overrides)
        if client is None:
            _run_here(fn, todo, report, show)
        else:
            _describe_cluster(client, scheduler, report, quiet)
            _run_dask(client, fn, f"tubeid-{key[:10]}", todo, report, show)
    t0 = time.perf_counter()
    if not block_flags(path).all():
        raise RuntimeError(f"{path}: run ended with unfinished blocks")  # should not happen
    update_attrs(path, finished=now(), **_summary(study, path))
    report.finalise = time.perf_counter() - t0
    _log(f"tubeid: done: {report.computed} blocks computed, {report.skipped} already done; store {path}", quiet)
    return report


def _run_pipeline(pipeline, source, key, study_path, path, state, workers, scheduler, overrides, progress, quiet):
    from tubeid.runner.store import pipeline_status

    report = PipelineReport(store=path)
    if state == "resume" and pipeline_status(path)["complete"]:
        _log(f"tubeid: {path} is complete ({len(pipeline.stages)} stages): nothing to do", quiet)
        return report
    show = progress and not quiet
    t0 = time.perf_counter()
    with (contextlib.nullcontext() if workers == 0 else _client(workers, scheduler, quiet)) as client:
        report.startup = time.perf_counter() - t0
        t0 = time.perf_counter()
        if state == "new":
            init_pipeline_store(pipeline, path, source=source, study_hash=key, study_file=str(study_path),
                                overrides=overrides)
            _log(f"tubeid: new pipeline store {path} (stages {', '.join(pipeline.stage_names)})", quiet)
        else:
            _record_resume(path, quiet)
            _log(f"tubeid: resuming pipeline store {path}", quiet)
        if client is not None:
            _describe_cluster(client, scheduler, report, quiet)
        report.prepare = time.perf_counter() - t0
        for name in pipeline.stage_names:
            report.stages[name] = _run_stage(pipeline, name, source, key, path, overrides, client, show, quiet)
            report.workers = max(report.workers, report.stages[name].workers)
    t0 = time.perf_counter()
    update_attrs(path, finished=now())
    report.finalise = time.perf_counter() - t0
    _log(f"tubeid: done: {report.computed} blocks computed, {report.skipped} already done "
         f"({len(pipeline.stages)} stages); store {path}", quiet)
    return report


def _stage_state(path, name, state):
    status = dict(read_attrs(path).get("stage_status", {}))
    status[name] = state
    update_attrs(path, stage_status=status)


def _run_stage(pipeline, name, source, key, path, overrides, client, show, quiet) -> RunReport:
    t0 = time.perf_counter()
    study, shash = stage_study(pipeline, key, path, name)  # refused here (before its tasks) if invalid
    _STAGES[(str(path), shash)] = study  # the in-process runner reuses it
    state = check_stage(path, name, shash)
    report = RunReport(store=path, total=study.n_blocks, computed=0, skipped=0, workers=0)
    if state == "resume":
        check_blocks(path, study, name)
        attrs = read_attrs(path, name)
        if block_flags(path, name).all() and attrs.get("finished"):
            report.skipped = study.n_blocks
            report.prepare = time.perf_counter() - t0
            _log(f"tubeid: stage {name}: complete ({study.n_blocks} blocks)", quiet)
            return report
        update_attrs(path, name, runs=list(attrs.get("runs", [])) + [now()])
    else:
        init_stage(study, path, name, pipeline_name=pipeline.name, pipeline_hash=key, stage_hash=shash)
    _stage_state(path, name, "running")
    flags = block_flags(path, name)
    todo = [b.index for b in study.blocks() if not flags[b.index]]
    report.skipped = study.n_blocks - len(todo)
    _log(f"tubeid: stage {name}: {len(todo)} of {study.n_blocks} blocks to compute", quiet)
    report.prepare = time.perf_counter() - t0
    fn = functools.partial(run_stage_block, str(path), source, overrides, name, shash)
    if client is None:
        _run_here(fn, todo, report, show, desc=name)
    else:
        report.workers = len(client.scheduler_info(n_workers=-1)["workers"])
        _run_dask(client, fn, f"tubeid-{shash[:10]}-{name}", todo, report, show, desc=name)
    t0 = time.perf_counter()
    if not block_flags(path, name).all():
        raise RuntimeError(f"{path}: stage {name} ended with unfinished blocks")  # should not happen
    update_attrs(path, name, finished=now(), **_summary(study, path, name))
    _stage_state(path, name, "complete")
    report.finalise = time.perf_counter() - t0
    return report


def _bar(total, initial, enabled, desc=None):
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=initial, unit="block", disable=not enabled, file=sys.stderr,
                dynamic_ncols=True, smoothing=0.1, desc=desc)


def _account(report, res, bar):
    report.computed += 1
    report.compute += res["compute"]
    report.write += res["write"]
    bar.update(1)


def _run_here(fn, todo, report, progress, desc=None):
    """Run ``fn(index)`` for every block index in this process."""
    report.workers = 1
    t0 = time.perf_counter()
    with _bar(report.total, report.skipped, progress, desc) as bar:
        for index in todo:
            _account(report, fn(index), bar)
    report.tasks = time.perf_counter() - t0


def _describe_cluster(client, scheduler, report, quiet):
    info = client.scheduler_info(n_workers=-1)
    report.workers = len(info["workers"])
    link = (getattr(client, "dashboard_link", "") or "") if "dashboard" in info.get("services", {}) else ""
    report.dashboard = link
    if link and importlib.util.find_spec("bokeh") is None:
        link += " (its plots need bokeh>=3.1 installed)"
    where = scheduler or f"embedded LocalCluster ({report.workers} single-threaded worker processes)"
    _log(f"tubeid: running on {where}" + (f"; dashboard {link}" if link else ""), quiet)


def _run_dask(client, fn, prefix, todo, report, progress, desc=None):
    """Submit ``fn(index)`` for every block index (task key ``<prefix>-block-<index>``) and wait for all."""
    from distributed import as_completed

    t1 = time.perf_counter()
    futures = [client.submit(fn, index, pure=False, key=f"{prefix}-block-{'-'.join(map(str, index))}")
               for index in todo]
    try:
        with _bar(report.total, report.skipped, progress, desc) as bar:
            for fut in as_completed(futures):
                _account(report, fut.result(), bar)
    except BaseException:
        client.cancel(futures)
        raise
    report.tasks = time.perf_counter() - t1
