"""Run a study or a pipeline: validate, prepare the store, submit one dask task per unfinished block, finalise.

Everything that can be refused (study definition, parameters, store path, store identity) is
checked before any task is submitted (for a pipeline stage built from earlier results: before
that stage's tasks). Tasks are idempotent (a block always writes the same bytes to the same
chunks, its flag last), so a rescheduled task after a worker death, a concurrent duplicate or a
resumed run cannot change the result. A pipeline runs its stages in order on the same cluster; the
runner builds each stage once and sends it to every worker once (``stage_payload``); a
stage that cannot be sent that way (e.g. a task that is a lambda) is rebuilt by each worker from the
pipeline source and the earlier stages' stored results (once per process), which checks that it gets
the stage hash the client computed. As soon as the cluster runs,
every worker loads the definition (``load_ahead``) while the runner creates the store and builds
the first stage: the first blocks do not wait for the study's imports.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import functools
import importlib.util
import logging
import os
import pathlib
import sys
import time

from typing import TYPE_CHECKING

from tubeid import config
from tubeid.errors import BlockFailed, SpecificationError
from tubeid.runner.integrity import repair_structure, verify
from tubeid.runner.lock import StoreLock
from tubeid._paths import local_path
from tubeid._validation import usable_cores, worker_count
from tubeid.runner._terms import current as _terms
from tubeid.runner.pipeline import End, Pipeline, stage_hash
from tubeid.runner.status import NOT_NEEDED
from tubeid.runner.store import (append_history, block_flags, check_blocks, check_stage, check_store, history_line,
                                 init_pipeline_store, init_stage, init_store, now, prepare_path, read_attrs, remove_store,
                                 remove_temporaries, restore_consolidated, _forget_nodes, _own_file, _read_manifest, _remove_nodes,
                                 set_flags, tubeid_version, update_attrs, write_block)
from tubeid.runner.study import Study, _plain, load_definition, load_study

if TYPE_CHECKING:
    import distributed

__all__ = ["run", "run_block", "run_stage_block", "stage_study", "RunReport", "PipelineReport", "default_store",
           "scheduler_address"]


@dataclasses.dataclass
class RunReport:
    """What a run did. Times in seconds (wall clock of this process; compute/write summed over tasks).

    Parameters
    ----------
    store : pathlib.Path
        The store written.
    total, computed, skipped : int
        Blocks of the study; computed by this run; found done (and verified) and not recomputed.
    workers : int
        Worker processes used (0: in this process).
    startup, prepare, tasks, finalise : float
        Cluster start or connection; store creation and checks; first submit to last result;
        provenance update [s].
    compute, write : float
        Sums over tasks of the study task itself and of its region and flag writes [s].
    warmup : float
        The once-per-machine warm-up (e.g. compiling), 0 if none was needed [s].
    repaired : int
        Finished blocks verification could not prove, recomputed: damaged ones, or all of them in a
        store whose checksums an earlier tubeid made by another rule.
    dashboard : str
        The dask dashboard's address ('' if none).
    """

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
    warmup: float = 0.0       # once-per-machine warm-up (e.g. compiling), 0 if none was needed
    repaired: int = 0         # finished blocks verification could not prove (damaged, or an earlier checksum rule): recomputed
    dashboard: str = ""

    @property
    def wall(self) -> float:
        """Run wall time excluding cluster start-up."""
        return self.prepare + self.tasks + self.finalise


@dataclasses.dataclass
class PipelineReport:
    """What a pipeline run did: one ``RunReport`` per stage, plus cluster start-up and root bookkeeping.

    Parameters
    ----------
    store : pathlib.Path
        The pipeline store written.
    stages : dict of str to RunReport
        Per stage run or skipped (its ``prepare`` includes building the stage from the earlier
        results).
    workers : int
        Worker processes used (0: in this process).
    startup, prepare, finalise : float
        Cluster start or connection; root store creation and checks; root provenance update [s].
    warmup : float
        The pipeline's once-per-machine warm-up [s].
    dashboard : str
        The dask dashboard's address ('' if none).
    """

    store: pathlib.Path
    stages: dict = dataclasses.field(default_factory=dict)
    workers: int = 0
    startup: float = 0.0
    prepare: float = 0.0      # root store creation / checks
    finalise: float = 0.0     # root provenance update
    warmup: float = 0.0       # the pipeline's once-per-machine warm-up
    dashboard: str = ""

    total = property(lambda self: sum(r.total for r in self.stages.values()))
    computed = property(lambda self: sum(r.computed for r in self.stages.values()))
    skipped = property(lambda self: sum(r.skipped for r in self.stages.values()))
    compute = property(lambda self: sum(r.compute for r in self.stages.values()))
    repaired = property(lambda self: sum(r.repaired for r in self.stages.values()))

    @property
    def wall(self) -> float:
        """Run wall time excluding cluster start-up."""
        return self.prepare + sum(r.wall for r in self.stages.values()) + self.finalise


def run_block(store: str, source: str, overrides: dict, index: tuple[int, ...]) -> dict:
    """Worker side: compute one block from the study source and write it (data, then flag), only into
    a store that still holds this study (its hash): a task an earlier run left running on a cluster
    never writes into the store that replaced it (``StaleWrite``)."""
    study, _, key = load_study(source=source, overrides=overrides)
    block = study.block(index)
    t0 = time.perf_counter()
    outputs = study.compute_block(block)
    t1 = time.perf_counter()
    write_block(store, study, block, outputs, expected_hash=key)
    t2 = time.perf_counter()
    return {"index": tuple(index), "compute": t1 - t0, "write": t2 - t1, "pid": os.getpid()}


_STAGES: dict[tuple, object] = {}


_OPENED: collections.OrderedDict = collections.OrderedDict()
_OPENED_MAX = 64
#: A stage of at most this many bytes is read into memory when opened (stage functions and summaries
#: read the earlier stages' arrays many times: lazily opened, each access read the store again); a
#: larger one stays lazy. Loaded stages kept per process hold at most ``_LOADED_BUDGET`` bytes.
_LOAD_MAX_BYTES = 16 * 2**20
_LOADED_BUDGET = 256 * 2**20


def _open_stage(store, name: str, attrs: dict):
    """Stage ``name`` of ``store`` opened without dask (read into memory when small:
    ``_LOAD_MAX_BYTES``), kept per process (at most ``_OPENED_MAX``, ``_LOADED_BUDGET`` bytes
    loaded) under its stage hash and ``finished`` time: a stage recomputed or repaired since has
    another ``finished`` time, so an entry is always the stage as it stands complete in the store."""
    import xarray as xr

    key = (str(store), name, attrs.get("stage_hash"), attrs.get("finished"))
    if key in _OPENED:
        _OPENED.move_to_end(key)
        return _OPENED[key][0]
    ds = xr.open_zarr(str(store), group=name, chunks=None)
    loaded = ds.nbytes <= _LOAD_MAX_BYTES
    if loaded:
        ds = ds.load()
    _OPENED[key] = (ds, ds.nbytes if loaded else 0)
    while len(_OPENED) > _OPENED_MAX or (len(_OPENED) > 1 and sum(b for _, b in _OPENED.values()) > _LOADED_BUDGET):
        _OPENED.popitem(last=False)
    return ds


def stage_study(pipeline: Pipeline, key: str, store, name: str):
    """Build stage ``name`` from the earlier stages' stored results: ``(study, stage hash)``, or
    ``(End, None)`` when the pipeline ends before it.

    The earlier stages are opened from ``store`` without dask (lazy numpy-backed arrays), with the
    attributes their ``summarize`` wrote; the stage hash covers their hashes and summaries too.
    """
    from tubeid.runner.store import store_status

    names = pipeline.stage_names
    results, upstream = {}, []
    for earlier in names[:names.index(name)]:
        st = store_status(store, earlier)
        if not st["complete"]:
            raise SpecificationError(f"stages.{name}", name, f"needs stage {earlier!r} complete in {store}")
        results[earlier] = _open_stage(store, earlier, st["attrs"])
        a = st["attrs"]
        upstream.append((earlier, a["stage_hash"], {k: a[k] for k in a.get("summary_keys", [])}))
    study = pipeline.stage(name, results)
    if isinstance(study, End):
        return study, None
    return study, stage_hash(key, study, upstream)


def load_ahead(source: str, overrides: dict) -> None:
    """Worker side, first thing on the cluster: execute the study or pipeline definition as the first
    block would (:func:`~tubeid.runner.study.load_definition` keeps it per process), while the runner
    does its own part. Only a cache fill: a failure is left to the first block, which loads the
    definition again and raises it, naming the block."""
    try:
        load_definition(source=source, overrides=overrides)
    except Exception:  # raised again, with the block's label, by the block that needs the definition
        pass


def stage_payload(study) -> tuple[bytes, str] | None:
    """Runner side: the built stage as sent to the workers, ``(pickle, fingerprint)``, or None.

    Pickled by reference (plain :mod:`pickle`): the study's functions are found by name in the
    worker's copy of the definition, which every worker executes anyway, so a worker gets the
    runner's stage without calling its stage function again (an identification from earlier results
    is then computed once per stage, not once per process). A stage whose parts cannot be pickled by
    reference (a lambda or a nested function as its task) gives None: each worker rebuilds it."""
    import pickle

    try:
        return pickle.dumps(study, protocol=pickle.HIGHEST_PROTOCOL), study.fingerprint()
    except Exception:  # PicklingError, a lambda's AttributeError, RecursionError, a __reduce__ that raises...
        return None


def _unpack_stage(payload: tuple[bytes, str] | None):
    """Worker side: the runner's stage from ``stage_payload`` (the definition loaded first), or
    None if there is none or it does not unpickle to the same fingerprint (then it is rebuilt)."""
    if payload is None:
        return None
    import pickle

    blob, fingerprint = payload
    try:
        study = pickle.loads(blob)
    except Exception:  # a definition that differs here (it should not): rebuilt and checked instead
        return None
    return study if isinstance(study, Study) and study.fingerprint() == fingerprint else None


def run_stage_block(store: str, source: str, overrides: dict, name: str, expected_hash: str,
                    index: tuple[int, ...], *, payload: tuple[bytes, str] | None = None) -> dict:
    """Worker side: compute one block of pipeline stage ``name`` and write it into its group.

    ``payload`` (:func:`stage_payload`): the stage as the runner built it; without it (or if it does
    not unpickle to the runner's stage) the stage is rebuilt here from the store and must get
    ``expected_hash``. The block is written only into a stage group that still holds
    ``expected_hash`` (``StaleWrite``: a task an earlier run left running on a cluster)."""
    ck = (store, expected_hash)
    if ck not in _STAGES:
        pipeline, _, key = load_definition(source=source, overrides=overrides)
        shipped = _unpack_stage(payload)
        if shipped is not None:
            _STAGES[ck] = shipped
    if ck not in _STAGES:
        study, h = stage_study(pipeline, key, store, name)
        if h is None or h != expected_hash:
            got = "as End" if h is None else f"with hash {h[:12]}"
            raise RuntimeError(f"stage {name!r} was rebuilt {got} on this worker, with hash {expected_hash[:12]} by "
                               "the runner: the stage function must be deterministic (and read the same store)")
        _STAGES[ck] = study
    study = _STAGES[ck]
    block = study.block(index)
    t0 = time.perf_counter()
    outputs = study.compute_block(block)
    t1 = time.perf_counter()
    write_block(store, study, block, outputs, group=name, expected_hash=expected_hash)
    t2 = time.perf_counter()
    return {"index": tuple(index), "compute": t1 - t0, "write": t2 - t1, "pid": os.getpid()}


def _summary(study, store, group=None) -> dict:
    """The study's ``summarize`` values (plain, checked against provenance names) plus ``summary_keys``."""
    if study.summarize is None:
        return {}
    import xarray as xr

    ds = (xr.open_zarr(str(store), group=group, chunks=None) if group else xr.open_zarr(str(store), chunks=None))
    attrs = dict(ds.attrs)
    values = study.summarize(ds)
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
    return config.value("runner.store-root") / f"{study_name}.zarr"


def scheduler_address(explicit: str | None = None) -> str | None:
    """``explicit``, else ``tubeid.runner.scheduler-address``, else ``DASK_SCHEDULER_ADDRESS``, else None."""
    return explicit or config.value("runner.scheduler-address") or os.environ.get("DASK_SCHEDULER_ADDRESS") or None


def _log(msg, quiet):
    if not quiet:
        print(msg, file=sys.stderr, flush=True)


def _probe(address: str, seconds: float) -> None:
    """Open one comm to ``address`` (its handshake included) and close it, within ``seconds``; raise
    what failed. distributed's connect waits for the peer's handshake without a time limit, so a
    Client to a peer that accepts TCP and never answers would wait for ever."""
    import asyncio
    import threading

    from distributed.comm import connect
    from distributed.security import Security

    async def attempt():
        try:  # distributed's own limit first (its message names the failure), then the handshake's
            comm = await asyncio.wait_for(connect(address, timeout=seconds, **Security().get_connection_args("client")),
                                          seconds + 1.0)
        except asyncio.TimeoutError:
            raise TimeoutError(f"connected, but no handshake from the peer within {seconds:g} s (is it a dask "
                               "scheduler?)") from None
        await comm.close()

    outcome = {}

    def target():  # its own event loop: the caller may be running one (a notebook)
        try:
            asyncio.run(attempt())
        except BaseException as exc:  # noqa: BLE001 - handed to the caller
            outcome["error"] = exc

    thread = threading.Thread(target=target, name="tubeid-connect-probe", daemon=True)
    thread.start()
    thread.join(seconds + 6.0)
    if thread.is_alive():
        raise TimeoutError(f"no answer within {seconds:g} s")
    if "error" in outcome:
        raise outcome["error"]


def _connect(scheduler: str):
    """A Client to ``scheduler``, or a SpecificationError saying why not (never a library traceback)."""
    from distributed import Client

    if not isinstance(scheduler, str) or not scheduler.strip():
        raise SpecificationError("scheduler", scheduler, "must be a scheduler address such as tcp://host:8786")
    timeout = config.get("runner.connect-timeout")  # as configured, for the message
    seconds = config.value("runner.connect-timeout")  # refused as a setting, not as a connection failure
    # Never the process's default Client (the runner passes its Client explicitly): a default one sets
    # dask.config's scheduler, which a Client that failed to connect leaves behind. Built in two steps
    # so that a Client that failed to connect is closed here (not by the garbage collector at exit,
    # when its event loop is gone: a stall of twice the timeout and a traceback), Ctrl-C included.
    client = None
    try:
        _probe(scheduler, seconds)
        client = Client.__new__(Client)
        client.__init__(scheduler, timeout=seconds, set_as_default=False)
        return client
    except BaseException as exc:  # unreachable, refused, silent, TLS expected or misconfigured, timed out; or Ctrl-C
        if client is not None:
            with contextlib.suppress(BaseException):
                client.close(timeout=5)
        if not isinstance(exc, Exception):
            raise
        text = f"{type(exc).__name__}: {exc}"
        if scheduler.startswith("tcp://") or "://" not in scheduler:  # no scheme is tcp:// too
            hint = ("; if the scheduler uses TLS, give its tls:// address and the client certificates (DASK_CONFIG, "
                    "see cluster/tls)")
        elif scheduler.startswith("tls://") and "ssl_context" in text:  # no client certificates configured
            hint = "; a tls:// scheduler needs the client certificates in the dask configuration (DASK_CONFIG, see cluster/tls)"
        else:
            hint = ""
        raise SpecificationError("scheduler", scheduler,
                                 f"cannot connect within tubeid.runner.connect-timeout = {timeout} ({text[:300]}){hint}") from exc


def _embedded_security():
    """Ephemeral TLS credentials for the embedded cluster (only processes holding them may connect)."""
    if not config.value("runner.embedded-tls"):
        return None
    try:
        from distributed.security import Security

        return Security.temporary()
    except ImportError as exc:  # the `cryptography` package is missing
        raise SpecificationError("runner.embedded-tls", True, f"needs the `cryptography` package ({exc}); install it "
                                 "or set tubeid.runner.embedded-tls: false (any local user could then submit work "
                                 "to the embedded cluster)") from exc


_UNGUARDED = ("the worker processes of the embedded cluster import the script that starts them, so a script that "
              "calls tubeid.runner.run() at module level runs it again in every worker: put the call under "
              "`if __name__ == \"__main__\":` (a notebook or `tubeid run` needs nothing)")


def _spawned_reimport() -> str | None:
    """The script's path when run() is called from a script that a process started by
    multiprocessing's spawn is re-importing (it then runs as ``__mp_main__``); else None."""
    frame = sys._getframe(1)
    while frame is not None:
        if frame.f_globals.get("__name__") == "__mp_main__":
            return str(frame.f_globals.get("__file__", "the parent's script"))
        frame = frame.f_back
    return None


def _refuse_in_a_spawned_reimport() -> None:
    """Stop a worker process that reached run() by re-importing an unguarded script: one line on
    stderr and exit status 1 (a traceback per worker would bury the cause)."""
    script = _spawned_reimport()
    if script is not None:
        raise SystemExit(f"tubeid: error: run() called while a worker process imports {script}: " + _UNGUARDED)


def _main_script() -> str | None:
    """The script this process runs (None in a notebook, an interactive session or ``python -c``)."""
    path = getattr(sys.modules.get("__main__"), "__file__", None)
    return str(path) if path and pathlib.Path(path).is_file() else None


def _embedded_settings(workers: int | None) -> tuple[int, int, str, str]:
    """(worker processes, threads per worker, host, dashboard address) of the embedded cluster:
    ``workers`` if given, else the configuration, checked here (a refusal names the setting and its
    environment variable, :func:`tubeid.config.value`) rather than by the cluster, which would hang on
    0 workers or fail deep inside."""
    n = workers or config.value("runner.workers") or usable_cores()
    return (int(n), config.value("runner.threads-per-worker"), config.value("runner.host"),
            config.value("runner.dashboard-address"))


def _is_tubeid_command(script: str) -> bool:
    """Whether this process is the ``tubeid`` command (its console script or ``python -m tubeid``),
    whose call of run() is guarded: a cluster that does not start is not an unguarded script's doing."""
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    return pathlib.Path(script).name == "tubeid" or (spec is not None and spec.name.split(".")[0] == "tubeid")


@contextlib.contextmanager
def _spawning_without_ctrl_c():
    """Ignore SIGINT in this process while the embedded cluster spawns its worker processes (main
    thread only; the previous handler is put back after).

    A terminal's Ctrl-C reaches the whole foreground process group. A worker process still
    importing, before its preload ignores SIGINT, would print a KeyboardInterrupt traceback, and a
    LocalCluster interrupted while starting leaves distributed's exit handler a traceback of its own.
    An ignored SIGINT is inherited as ignored by the spawned interpreters (a handler is not), so the
    workers ignore it from their first instruction. The cost: a Ctrl-C during the cluster's start
    (about a second) is not seen; the next one is answered as usual."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@contextlib.contextmanager
def _client(workers: int | None, scheduler: str | None, client, quiet: bool):
    """``(client, where)``: the Client to run on and a description of it for the progress line.

    ``client`` if given (never closed here); else a new Client to ``scheduler``; else, if ``workers``
    is None, the Client already open in this process (``distributed.default_client()``, e.g. a
    notebook's dask-jobqueue or dask-kubernetes cluster; never closed here); else an embedded
    loopback LocalCluster authenticated by ephemeral TLS.
    """
    import dask
    from distributed import LocalCluster

    if client is not None:
        client.run(_warm)
        yield client, f"the given dask Client (scheduler {client.scheduler.address})"
        return
    if scheduler:
        own = _connect(scheduler)
        with own:
            own.run(_warm)
            yield own, scheduler
        return
    if workers is None:
        from distributed import default_client

        try:
            existing = default_client()
        except ValueError:
            existing = None
        if existing is not None and existing.status == "running":
            existing.run(_warm)
            yield existing, (f"the dask Client already open in this process (scheduler {existing.scheduler.address}, "
                             "from distributed.default_client())")
            return
    from distributed import Client

    n, threads, host, dashboard = _embedded_settings(workers)
    security = _embedded_security()
    environ = _worker_environ()
    # each nanny also writes the variables into this process's environment (dask's pre-spawn rule):
    # put them back when the cluster is gone, so that a later cluster (and subprocess) sees the caller's
    saved = {k: os.environ.get(k) for k in {*environ, "PYTHONHASHSEED"}}
    try:
        with dask.config.set({"distributed.scheduler.allowed-failures": config.value("runner.allowed-failures"),
                              "distributed.nanny.pre-spawn-environ": environ}):
            try:
                with _spawning_without_ctrl_c():
                    cluster = LocalCluster(n_workers=n, threads_per_worker=threads, processes=True, host=host,
                                           dashboard_address=dashboard, silence_logs=logging.CRITICAL, security=security,
                                           protocol="tls://" if security is not None else None,
                                           preload=["tubeid.runner._embedded_worker"])  # Ctrl-C is the runner's
            except Exception as exc:
                script = _main_script()
                if script is None:
                    raise
                why = (f"; if {script} calls run() outside `if __name__ == \"__main__\":`, that is why: {_UNGUARDED}"
                       if not _is_tubeid_command(script) else "")
                raise SpecificationError("embedded cluster", f"{n} workers on {host}, dashboard {dashboard}",
                                         f"did not start ({type(exc).__name__}: {exc}); check tubeid.runner.host and "
                                         f"tubeid.runner.dashboard-address (TUBEID_RUNNER__HOST, "
                                         f"TUBEID_RUNNER__DASHBOARD_ADDRESS){why}") from None
        with cluster, Client(cluster, security=security, set_as_default=False) as own:
            own.run(_warm)  # imports once per worker, before the clock of the first task starts
            tls = ", TLS with ephemeral credentials" if security is not None else ""
            yield own, f"embedded LocalCluster ({len(cluster.workers)} single-threaded worker processes{tls})"
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def _worker_environ() -> dict:
    """dask's ``distributed.nanny.pre-spawn-environ`` with ``tubeid.runner.worker-environ`` over it:
    the environment the embedded cluster's nannies set before starting a worker process (a variable
    already in this process's environment wins there; a None value leaves the variable unset).
    Names are upper-case environment variable names; glibc's ``MALLOC_*`` values are byte counts
    (glibc ignores anything else, and a trim threshold alone then fixes the mmap threshold at 128 KiB)."""
    import dask

    extra = config.value("runner.worker-environ")  # names and values checked there
    base = dask.config.get("distributed.nanny.pre-spawn-environ", default=None) or {}
    if not isinstance(base, dict):
        raise SpecificationError("distributed.nanny.pre-spawn-environ", base, "must be a mapping of environment "
                                 "variable names to values")
    return {**base, **extra}


def _warm() -> None:
    import tubeid.runner.store  # noqa: F401  (xarray, zarr)


def _call_pickled(blob: bytes):
    """Worker side: call a function sent as cloudpickle bytes."""
    import cloudpickle

    return cloudpickle.loads(blob)()


def _warm_up(client, warmup, quiet) -> float:
    """Do ``warmup`` once per machine where it is needed, saying so first; returns the seconds it took."""
    if warmup is None:
        return 0.0
    t0 = time.perf_counter()
    if client is None:
        if warmup.needed():
            _log(f"tubeid: {warmup.message}", quiet)
            warmup.run()
    else:
        info = client.scheduler_info(n_workers=-1)["workers"]
        per_host = {}
        for addr, w in sorted(info.items()):
            per_host.setdefault(w.get("host", addr), addr)
        chosen = list(per_host.values())
        import cloudpickle  # a study file's functions go by value (workers cannot import the study's module)

        needed = client.run(_call_pickled, cloudpickle.dumps(warmup.needed), workers=chosen)
        todo = [a for a in chosen if needed.get(a)]
        if not todo:
            return 0.0
        _log(f"tubeid: {warmup.message} ({len(todo)} of {len(chosen)} machines)", quiet)
        futures = [client.submit(_call_pickled, cloudpickle.dumps(warmup.run), workers=[a], allow_other_workers=False, pure=False,
                                 key=f"tubeid-warmup-{i}-{time.time_ns()}") for i, a in enumerate(todo)]
        try:
            # each future awaited alone, not client.gather: an interrupted gather (Ctrl-C) orphans
            # distributed's inner waits, which print "Task exception was never retrieved ... AllExit"
            for fut in futures:
                fut.result()
        except BaseException:
            client.cancel(futures)  # an interrupted (or failed) warm-up is not left running on the cluster
            raise
    dt = time.perf_counter() - t0
    if dt > 0.05:
        _log(f"tubeid: warm-up done in {dt:.1f} s", quiet)
    return dt


@contextlib.contextmanager
def _loading_ahead(client, ctx):
    """While the body runs, every worker of ``client`` loads the definition (:func:`load_ahead`, one
    task pinned to each, submitted before any block); the futures are held meanwhile (a released
    future's task is forgotten), never waited for, and those not finished when the body ends (it
    raised, or a worker never ran its task) are cancelled. Nothing for ``client`` None."""
    futures = []
    if client is not None:
        workers = sorted(client.scheduler_info(n_workers=-1)["workers"])
        futures = [client.submit(load_ahead, ctx.source, ctx.overrides, workers=[a], allow_other_workers=False,
                                 pure=False, key=f"tubeid-load-ahead-{i}-{time.time_ns()}")
                   for i, a in enumerate(workers)]
    try:
        yield
    finally:
        pending = [f for f in futures if not f.done()]
        if pending:
            with contextlib.suppress(Exception):  # a client already gone (the body's error says why) cancels nothing
                client.cancel(pending)


def _record_resume(path, quiet) -> None:
    """Append this start to the store's runs and history; warn when another tubeid version started it."""
    attrs = read_attrs(path)
    if attrs.get("tubeid_version") != tubeid_version():
        _log(f"tubeid: warning: {path} was started with tubeid {attrs.get('tubeid_version')}, "
             f"resuming with {tubeid_version()}; use --overwrite if the results may differ", quiet)
    update_attrs(path, runs=list(attrs.get("runs", [])) + [now()],
                 history=(attrs.get("history", "") + "\n" if attrs.get("history") else "") + history_line("resumed"))


def _verify_and_repair(study, path, group, quiet, where) -> int:
    """Verify a resumed store (or stage): repair its structure if damaged, clear the damaged blocks' flags.

    Returns the number of finished blocks to recompute: damaged ones, or all of them when the store's
    checksums were made by an earlier rule (written by an earlier tubeid: they cannot be proven).
    """
    ver = verify(path, group)
    if ver.other_rule is not None:  # written by an earlier tubeid: not damage, but its blocks cannot be proven
        other_rule = ver.other_rule
        repair_structure(study, path, group)  # the bookkeeping attributes now state this tubeid's rule
        ver = verify(path, group)
        bad = ver.to_recompute
        _log(f"tubeid: {where}: its block checksums were made by an earlier tubeid's rule ({other_rule!r}): "
             f"{len(bad)} of {ver.checked + len(ver.unreadable_flags)} finished blocks cannot be proven under this "
             "tubeid's rule and are recomputed (their values should not change)", quiet)
        if bad:
            set_flags(path, bad, 0, group)
            update_attrs(path, group, finished="")
            append_history(path, group, f"{len(bad)} block(s) made under an earlier checksum rule, recomputed")
        return len(bad)
    if ver.structure:  # metadata or coordinates damaged: rewrite them from the study, then check the blocks
        repaired = repair_structure(study, path, group)
        _log(f"tubeid: {where}: " + "; ".join(ver.structure[:3]) + f": rewrote {len(repaired)} metadata/coordinate "
             "file(s) from the study: " + ", ".join(repaired[:5]) + (" ..." if len(repaired) > 5 else ""), quiet)
        ver = verify(path, group)
    bad = ver.to_recompute
    if bad:
        _log(f"tubeid: {where}: {len(bad)} of {ver.checked + len(ver.unreadable_flags)} finished blocks are damaged; "
             "recomputing them:\n  " + "\n  ".join(ver.lines()), quiet)
        set_flags(path, bad, 0, group)
        if group:
            update_attrs(path, group, finished="")
        else:
            update_attrs(path, finished="")
        append_history(path, group, f"{len(bad)} damaged block(s) found by verification, recomputed")
    return len(bad)


def run(study_path: str | os.PathLike, store: str | os.PathLike | None = None, *, workers: int | None = None,
        scheduler: str | None = None, client: distributed.Client | None = None,
        overrides: dict | None = None, new_store: bool = False, overwrite: bool = False, verify_blocks: bool = True,
        progress: bool | None = None, quiet: bool = False) -> RunReport | PipelineReport:
    """Run (or resume) the study in ``study_path`` into the Zarr ``store``; see ``tubeid run --help``.

    Parameters
    ----------
    study_path : path-like
        A study file defining ``study = Study(...)`` or ``study = Pipeline(...)``.
    store : path-like, optional
        The Zarr store (default: ``<tubeid.runner.store-root>/<study name>.zarr``).
    workers : int, optional
        Size of an embedded LocalCluster (single-threaded worker processes, TLS-authenticated);
        0 runs the blocks in this process, for debugging.
    scheduler : str, optional
        Address of an existing scheduler (default: configuration, then ``DASK_SCHEDULER_ADDRESS``).
    client : distributed.Client, optional
        An open Client to run on (e.g. a dask-jobqueue or dask-kubernetes cluster's); never closed
        here. Without ``client``, ``workers`` or ``scheduler``, the Client already open in this
        process (``distributed.default_client()``) is used if there is one, else an embedded cluster.
        Its workers must see ``store`` at the same path and import tubeid.
    overrides : dict, optional
        Parameter values replacing the study's (validated; part of the store's identity).
    new_store, overwrite : bool
        If the store holds another study: write ``<store>-<hash8>.zarr`` beside it, or replace what
        tubeid wrote in it (files tubeid did not write are kept).
    verify_blocks : bool
        On a resume (complete or not), check every finished block against its checksum first and
        recompute the damaged ones (default True).
    progress, quiet : bool
        Progress bar on stderr (default: configuration); no messages at all.

    Returns
    -------
    RunReport or PipelineReport
        What the run did (blocks computed, skipped, repaired; timings).
    """
    _refuse_in_a_spawned_reimport()
    config.check()  # the whole configuration, before the study file runs and anything is created or started
    base, source, _ = load_definition(study_path)  # validates the definition as written
    # each --set value as its parameter's check makes it (e.g. a model file read into its content, checked
    # now, never from a cache): the workers and the study hash get that, not the raw text
    overrides = {k: base.parameters[k].check(k, v) if k in base.parameters else v for k, v in dict(overrides or {}).items()}
    study, source, key = load_definition(study_path, source=source, overrides=overrides)
    if workers is not None:
        workers = worker_count("workers", workers)
    if client is not None and (workers is not None or scheduler):
        raise SpecificationError("client", client, "give a client, --workers or --scheduler, not several")
    if client is not None and not hasattr(client, "submit"):
        raise SpecificationError("client", client, "must be a distributed.Client")
    scheduler = scheduler_address(scheduler) if workers is None and client is None else scheduler
    if scheduler and workers is not None:
        raise SpecificationError("workers", workers, "give either --workers or --scheduler, not both")
    terms = _terms()
    if store is None:
        path = local_path(default_store(study.name), field=f"{terms.store} (the default one, named after study "
                                                           f"{study.name!r}: give {terms.option}, or rename the study)")
    else:
        path = local_path(store, field=terms.store)
    if new_store and _holds_another(path, key):
        path = pathlib.Path(os.path.abspath(path))  # "." and ".." name no directory to write beside
        if not path.name:
            raise SpecificationError(terms.store, str(store), "is the root directory: a new store has no name to write "
                                     "<store>-<hash8>.zarr beside it; give the store's own path")
        path = path.with_name(f"{path.name.removesuffix('.zarr')}-{key[:8]}.zarr")
    path = prepare_path(path).resolve()
    if not overwrite:
        check_store(path, key)  # refused before taking the lock (and leaving a lock file) if it is not ours
    else:
        remove_store(path, dry_run=True)  # refused up front if it is not a tubeid store
    progress = config.value("runner.progress") if progress is None else progress
    lock = StoreLock(path, log=lambda m: _log(m, quiet))
    lock.acquire()
    try:
        state = "new" if overwrite else check_store(path, key)  # again, holding the lock
        readable = _remove_temporaries(path, quiet) if state == "resume" else True
        if overwrite:
            kept = remove_store(path)
            if kept:
                _log(f"tubeid: --overwrite kept {len(kept)} file(s) tubeid did not write in {path}: "
                     + ", ".join(kept[:5]) + (" ..." if len(kept) > 5 else ""), quiet)
        ctx = _Run(study=study, source=source, key=key, study_path=study_path, path=path, state=state,
                   workers=workers, scheduler=scheduler, client=client, overrides=overrides, verify=verify_blocks,
                   progress=progress and not quiet, quiet=quiet, lock=lock)
        report = _run_pipeline(ctx) if isinstance(study, Pipeline) else _run_study(ctx)
        if readable:
            _remove_temporaries(path, quiet)  # a worker killed mid-write, its block since rerun elsewhere
        return report
    finally:
        lock.release()
        if lock.created_store and path.is_dir() and all(_own_file(f.name) for f in path.iterdir()):
            for f in path.iterdir():  # refused or failed before anything was written: leave no trace
                f.unlink()
            path.rmdir()


def _holds_another(path: pathlib.Path, key: str) -> bool:
    """Whether ``--new-store`` diverts from ``path``: it exists and cannot take this study as it is (another
    study definition, files tubeid did not write, an older layout), so ``<store>-<hash8>.zarr`` is written
    beside it (a symbolic link too: tubeid never writes through one); a missing path or a store of this very
    study is used as given (a resume)."""
    if path.is_symlink():
        return True
    try:
        check_store(path, key)
    except SpecificationError:
        return True
    return False


def _remove_temporaries(path, quiet) -> bool:
    """Remove the temporary files of writes killed before their rename (the caller holds the lock).
    A store whose manifest cannot be read keeps them (nothing is provably tubeid's) and the run goes
    on: returns False then (said once), else True."""
    try:
        left = remove_temporaries(path)
    except SpecificationError as exc:
        _log(f"tubeid: note: temporary files of interrupted writes, if any, are left in place: {exc}", quiet)
        return False
    if left:
        _log(f"tubeid: removed {len(left)} temporary file(s) an interrupted write left in {path}: "
             + ", ".join(left[:3]) + (" ..." if len(left) > 3 else ""), quiet)
    return True


@dataclasses.dataclass
class _Run:
    study: object
    source: str
    key: str
    study_path: object
    path: pathlib.Path
    state: str
    workers: int | None
    scheduler: str | None
    client: object
    overrides: dict
    verify: bool
    progress: bool
    quiet: bool
    lock: StoreLock
    verified: dict = dataclasses.field(default_factory=dict)  # pipeline stage -> damaged blocks found already

    def cluster(self):
        if self.workers == 0 and self.client is None:
            return contextlib.nullcontext((None, "this process"))
        return _client(self.workers, self.scheduler, self.client, self.quiet)


def _run_study(ctx: _Run) -> RunReport:
    study, path, quiet = ctx.study, ctx.path, ctx.quiet
    report = RunReport(store=path, total=study.n_blocks, computed=0, skipped=0, workers=0)
    if ctx.state == "resume":
        check_blocks(path, study)
        if ctx.verify:
            report.repaired = _verify_and_repair(study, path, None, quiet, str(path))
        if block_flags(path).all():
            report.skipped = study.n_blocks
            if not read_attrs(path).get("finished"):  # every block written, but stopped before the finalisation
                update_attrs(path, finished=now(), **_summary(study, path))
            else:  # stopped between the final attributes and their consolidation: consolidated again
                restore_consolidated(path)
            checked = f"{study.n_blocks} blocks, verified" if ctx.verify else f"{study.n_blocks} blocks, not verified"
            _log(f"tubeid: {path} is complete ({checked}): nothing to do", quiet)
            return report
    t0 = time.perf_counter()
    with ctx.cluster() as (client, where), _loading_ahead(None if study.in_process else client, ctx):
        report.startup = time.perf_counter() - t0
        t0 = time.perf_counter()
        if ctx.state == "new":
            init_store(study, path, source=ctx.source, study_hash=ctx.key, study_file=str(ctx.study_path),
                       overrides=ctx.overrides)
            _log(f"tubeid: new store {path} ({study.n_blocks} blocks)", quiet)
        else:
            _record_resume(path, quiet)
        flags = block_flags(path)
        todo = [b.index for b in study.blocks() if not flags[b.index]]
        report.skipped = study.n_blocks - len(todo)
        if ctx.state == "resume":
            _log(f"tubeid: resuming {path}: {report.skipped}/{study.n_blocks} blocks already done", quiet)
        report.prepare = time.perf_counter() - t0
        fn = functools.partial(run_block, str(path), ctx.source, ctx.overrides)
        if client is not None:
            _describe_cluster(client, where, report, quiet)
        report.warmup = _warm_up(client, study.warmup, quiet) if todo else 0.0
        if client is None or study.in_process:
            _run_here(fn, todo, report, ctx.progress, lock=ctx.lock, label=functools.partial(_block_label, study))
        else:
            _run_dask(client, fn, f"tubeid-{ctx.key[:10]}", todo, report, ctx.progress, lock=ctx.lock,
                      label=functools.partial(_block_label, study))
    t0 = time.perf_counter()
    if not block_flags(path).all():
        raise RuntimeError(f"{path}: run ended with unfinished blocks")  # should not happen
    update_attrs(path, finished=now(), **_summary(study, path),
                 add_history=f"complete: {report.computed} block(s) computed, {report.skipped} already done")
    report.finalise = time.perf_counter() - t0
    _log(f"tubeid: done: {report.computed} blocks computed, {report.skipped} already done; store {path}", quiet)
    return report


def _verify_complete_pipeline(ctx: _Run, report: PipelineReport) -> bool:
    """A complete pipeline store: verify every stage here (no cluster needed); True if all are intact."""
    for name in ctx.study.stage_names:
        study, shash = stage_study(ctx.study, ctx.key, ctx.path, name)
        if isinstance(study, End):  # the pipeline ended here: nothing after it was computed
            return True
        check_stage(ctx.path, name, shash)
        check_blocks(ctx.path, study, name)
        ctx.verified[name] = _verify_and_repair(study, ctx.path, name, ctx.quiet, f"stage {name}")
        if ctx.verified[name] or not block_flags(ctx.path, name).all():
            return False  # the stages after it are verified when they are resumed
        report.stages[name] = RunReport(store=ctx.path, total=study.n_blocks, computed=0, skipped=study.n_blocks, workers=0)
    return True


def _run_pipeline(ctx: _Run) -> PipelineReport:
    from tubeid.runner.store import pipeline_status

    pipeline, path, quiet = ctx.study, ctx.path, ctx.quiet
    report = PipelineReport(store=path)
    if ctx.state == "resume" and (st := pipeline_status(path))["complete"]:
        t0 = time.perf_counter()
        # a run stopped before its last consolidation: consolidated first (the stages are read next)
        restore_consolidated(path, [n for n, s in st["stages"].items() if s["started"]])
        if not ctx.verify or _verify_complete_pipeline(ctx, report):
            report.prepare = time.perf_counter() - t0
            checked = "verified" if ctx.verify else "not verified"
            _record_complete_pipeline(path)
            _log(f"tubeid: {path} is complete ({len(pipeline.stages)} stages, {checked}): nothing to do", quiet)
            return report
        report.stages.clear()
    t0 = time.perf_counter()
    with ctx.cluster() as (client, where), _loading_ahead(client, ctx):
        report.startup = time.perf_counter() - t0
        t0 = time.perf_counter()
        if ctx.state == "new":
            init_pipeline_store(pipeline, path, source=ctx.source, study_hash=ctx.key, study_file=str(ctx.study_path),
                                overrides=ctx.overrides)
            _log(f"tubeid: new pipeline store {path} (stages {', '.join(pipeline.stage_names)})", quiet)
        else:
            _record_resume(path, quiet)
            _log(f"tubeid: resuming pipeline store {path}", quiet)
        if client is not None:
            _describe_cluster(client, where, report, quiet)
        report.prepare = time.perf_counter() - t0
        report.warmup = _warm_up(client, pipeline.warmup, quiet)
        for name in pipeline.stage_names:
            stage_report = _run_stage(ctx, name, client)
            if stage_report is None:  # the pipeline ended before this stage
                break
            report.stages[name] = stage_report
            report.workers = max(report.workers, report.stages[name].workers)
    t0 = time.perf_counter()
    update_attrs(path, finished=now(),
                 add_history=f"complete: {report.computed} block(s) computed, {report.skipped} already done")
    report.finalise = time.perf_counter() - t0
    ran = (f"{len(report.stages)} of {len(pipeline.stages)} stages, the rest not needed"
           if len(report.stages) < len(pipeline.stages) else f"{len(pipeline.stages)} stages")
    _log(f"tubeid: done: {report.computed} blocks computed, {report.skipped} already done ({ran}); store {path}", quiet)
    return report


def _record_complete_pipeline(path) -> None:
    """A pipeline store found complete on a resume: record at the root what an interrupted run did not
    (``finished``, every needed stage's ``stage_status`` "complete": a run stopped between finishing
    a stage and recording it left "running"), in one write; else consolidate again the metadata a
    run stopped before its last consolidation left without."""
    from tubeid.runner.store import pipeline_status

    st = pipeline_status(path)
    attrs = st["attrs"]
    status = dict(attrs.get("stage_status") or {})
    stale = [n for n, s in st["stages"].items() if s.get("needed", True) and status.get(n) != "complete"]
    changes = {}
    if stale:
        status.update({n: "complete" for n in stale})
        changes["stage_status"] = status
    if not attrs.get("finished"):  # every stage done, but stopped before the finalisation
        changes["finished"] = now()
    started = [n for n, s in st["stages"].items() if s["started"]]
    restore_consolidated(path, started)  # the groups' first: the root's consolidation below nests them
    if changes:
        update_attrs(path, add_history="complete (found so on a resume)", **changes)


def _stage_state(path, name, state):
    """Record stage ``name``'s state at the root and consolidate the root (also when the state is
    unchanged: the stage's group may have changed without it)."""
    status = dict(read_attrs(path).get("stage_status", {}))
    status[name] = state
    update_attrs(path, stage_status=status)


def _end_pipeline(ctx: _Run, name: str, reason: str) -> None:
    """The pipeline ends before stage ``name``: it and the later stages are not needed (groups a run
    of other code may have left for them, tubeid's own, are removed); one root update."""
    pipeline, path = ctx.study, ctx.path
    later = pipeline.stage_names[pipeline.stage_names.index(name):]
    left = {n: k for n, k in _read_manifest(path).items() if any(n == s or n.startswith(s + "/") for s in later)}
    if left:
        _remove_nodes(path, left)
        _forget_nodes(path, left)
    status = dict(read_attrs(path).get("stage_status", {}))
    status.update({n: NOT_NEEDED for n in later})
    update_attrs(path, stage_status=status, ended={"stage": name, "reason": reason})
    _log(f"tubeid: the pipeline ends before stage {name}: {reason}", ctx.quiet)


def _run_stage(ctx: _Run, name: str, client) -> RunReport | None:
    """Run (or resume) one stage; None when the pipeline ends before it (:class:`End`)."""
    pipeline, path, quiet = ctx.study, ctx.path, ctx.quiet
    t0 = time.perf_counter()
    study, shash = stage_study(pipeline, ctx.key, path, name)  # refused here (before its tasks) if invalid
    if isinstance(study, End):
        _end_pipeline(ctx, name, study.reason)
        return None
    if read_attrs(path).get("ended"):  # an earlier run ended the pipeline here or before; this one goes on
        update_attrs(path, ended=None)
    _STAGES[(str(path), shash)] = study  # the in-process runner reuses it
    state = check_stage(path, name, shash)
    report = RunReport(store=path, total=study.n_blocks, computed=0, skipped=0, workers=0)
    if state == "resume":
        check_blocks(path, study, name)
        if ctx.verify:
            report.repaired = ctx.verified[name] if name in ctx.verified else \
                _verify_and_repair(study, path, name, quiet, f"stage {name}")
        attrs = read_attrs(path, name)
        if block_flags(path, name).all() and attrs.get("finished"):
            report.skipped = study.n_blocks
            # a run stopped after the stage's final attributes may not have consolidated them, nor
            # recorded the stage complete at the root: both are done now
            restore_consolidated(path, [name])
            if dict(read_attrs(path).get("stage_status") or {}).get(name) != "complete":
                _stage_state(path, name, "complete")
            report.prepare = time.perf_counter() - t0
            _log(f"tubeid: stage {name}: complete ({study.n_blocks} blocks)", quiet)
            return report
        update_attrs(path, name, runs=list(attrs.get("runs", [])) + [now()], root=False)
    else:
        init_stage(study, path, name, pipeline_name=pipeline.name, pipeline_hash=ctx.key, stage_hash=shash,
                   references=pipeline.references, root=False)
    if not study.in_process:  # an in-process stage (a placeholder) is complete within milliseconds: its state once
        _stage_state(path, name, "running")  # consolidates the root, with the group's change above
    flags = block_flags(path, name)
    todo = [b.index for b in study.blocks() if not flags[b.index]]
    report.skipped = study.n_blocks - len(todo)
    _log(f"tubeid: stage {name}: {len(todo)} of {study.n_blocks} blocks to compute", quiet)
    report.prepare = time.perf_counter() - t0
    fn = functools.partial(run_stage_block, str(path), ctx.source, ctx.overrides, name, shash)
    if todo:
        report.warmup = _warm_up(client, study.warmup, quiet)
    if client is None or study.in_process:
        _run_here(fn, todo, report, ctx.progress, desc=name, lock=ctx.lock,
                  label=functools.partial(_block_label, study, stage=name))
    else:
        report.workers = len(client.scheduler_info(n_workers=-1)["workers"])
        payload = stage_payload(study) if todo else None
        # sent once to every worker, not with every block (a stage with large axes is megabytes)
        sent = client.scatter([payload], broadcast=True, hash=False)[0] if payload is not None else None
        try:
            _run_dask(client, fn, f"tubeid-{shash[:10]}-{name}", todo, report, ctx.progress, desc=name, lock=ctx.lock,
                      label=functools.partial(_block_label, study, stage=name),
                      kwargs={"payload": sent} if sent is not None else None)
        finally:
            if sent is not None:
                with contextlib.suppress(Exception):  # a client already gone: nothing left to release
                    sent.release()
    t0 = time.perf_counter()
    if not block_flags(path, name).all():
        raise RuntimeError(f"{path}: stage {name} ended with unfinished blocks")  # should not happen
    update_attrs(path, name, finished=now(), root=False, **_summary(study, path, name),
                 add_history=f"stage complete: {report.computed} block(s) computed, {report.skipped} already done")
    _stage_state(path, name, "complete")  # consolidates the root, with the group's change above
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


def _block_label(study, index, stage: str | None = None) -> str:
    """``study 'name', block (i, j) (dim = first … last, ...)``: which block, for an error message."""
    block = study.block(index)
    parts = []
    for dim, values in block.coords.items():
        values = list(values)
        parts.append(f"{dim} = {values[0]}" if len(values) == 1 else f"{dim} = {values[0]} … {values[-1]}")
    what = f"stage {stage!r}" if stage else f"study {study.name!r}"
    return f"{what}, block {tuple(int(i) for i in index)} ({', '.join(parts)})"


def _failed(exc: Exception, label) -> BaseException:
    """The exception to raise for a block whose task raised ``exc``: a refusal stays a refusal (its field,
    value and rule; a value the task checks, a full disk) with the block named after its rule; anything
    else becomes :class:`~tubeid.errors.BlockFailed` naming the block."""
    if isinstance(exc, SpecificationError):
        return SpecificationError(exc.field, exc.value, f"{exc.rule} (in {label})")
    t = _terms()
    return BlockFailed(label, f"{type(exc).__name__}: {exc}", f"for {t.changed}: {t.beside}, or use --overwrite")


def _run_here(fn, todo, report, progress, desc=None, lock=None, label=lambda index: f"block {index}"):
    """Run ``fn(index)`` for every block index in this process."""
    report.workers = 1
    t0 = time.perf_counter()
    with _bar(report.total, report.skipped, progress, desc) as bar:
        for index in todo:
            if lock is not None:
                lock.check()
            try:
                res = fn(index)
            except Exception as exc:
                raise _failed(exc, label(index)) from exc
            _account(report, res, bar)
    report.tasks = time.perf_counter() - t0


def _describe_cluster(client, where, report, quiet):
    info = client.scheduler_info(n_workers=-1)
    report.workers = len(info["workers"])
    link = (getattr(client, "dashboard_link", "") or "") if "dashboard" in info.get("services", {}) else ""
    report.dashboard = link
    if link and importlib.util.find_spec("bokeh") is None:
        link += ' (its plots need bokeh: pip install "tubeid[dashboard]")'
    _log(f"tubeid: running on {where}" + (f"; dashboard {link}" if link else ""), quiet)


def _run_dask(client, fn, prefix, todo, report, progress, desc=None, lock=None, label=lambda index: f"block {index}",
              kwargs=None):
    """Submit ``fn(index, **kwargs)`` for every block index (task key ``<prefix>-block-<index>``) and wait
    for all (a future in ``kwargs`` reaches ``fn`` as its value)."""
    from distributed import as_completed

    t1 = time.perf_counter()
    futures = [client.submit(fn, index, pure=False, key=f"{prefix}-block-{'-'.join(map(str, index))}", **(kwargs or {}))
               for index in todo]
    index_of = {fut.key: index for fut, index in zip(futures, todo)}
    try:
        with _bar(report.total, report.skipped, progress, desc) as bar:
            for fut in as_completed(futures, loop=client.loop):  # the runner's Client is not the default one
                if lock is not None:
                    lock.check()
                try:
                    res = fut.result()
                except Exception as exc:
                    raise _failed(exc, label(index_of[fut.key])) from exc
                _account(report, res, bar)
                # the block is in the store: let the cluster forget its result, or a worker that
                # leaves (lifetime, pre-emption) would make the scheduler recompute every finished
                # block it held, ahead of the blocks not yet run (a livelock with short lifetimes)
                fut.release()
    except BaseException:
        client.cancel(futures)
        raise
    report.tasks = time.perf_counter() - t1
