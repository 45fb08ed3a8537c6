"""Study runner with real processes: `dask scheduler` + 2 `dask worker` started from the command line,
the embedded LocalCluster with 1 and 2 workers, the runner SIGKILLed mid-study and resumed, a worker
SIGKILLed mid-study. Every run must end with a store byte-identical (chunk files and non-volatile
metadata) to an uninterrupted 2-worker local run; no process may be left behind.
"""

import contextlib
import json
import os
import pathlib
import shutil
import socket
import signal
import subprocess
import sys
import time

import psutil
import pytest

import numpy as np

from tubeid.runner.store import open_results
from tubeid.runner.testing import flags, store_digest, write_study

pytestmark = [pytest.mark.distributed, pytest.mark.timeout(180)]

RUNNER = [sys.executable, "-m", "tubeid.runner.cli", "run"]
# 2 deltas x 24 realisations in blocks of 2: 24 tasks of ~10-40 ms of compute each on one core
SIZE = dict(realisations=24, chunk=2, work=3000)
# the tests that interrupt a run (a kill, Ctrl-C) sleep this long in every block (values unchanged):
# the compute alone can finish the 22 blocks left after the kill point before the signal lands
PACE = {"TUBEID_TEST_BLOCK_SECONDS": "0.15"}


def _env(**extra):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    for k in ("DASK_SCHEDULER_ADDRESS", "TUBEID_TEST_FAIL_AT", "TUBEID_TEST_BLOCK_SECONDS"):
        env.pop(k, None)
    env.update(extra)
    return env


def _stop(proc, timeout=10.0):
    """Terminate a process started in its own session, then anything left in that session."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            pass
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait(timeout)


def _session_alive(sid) -> list[int]:
    """Live (non-zombie) processes of a session."""
    out = []
    for p in psutil.process_iter(["pid", "status"]):
        try:
            if os.getsid(p.info["pid"]) == sid and p.info["status"] != psutil.STATUS_ZOMBIE:
                out.append(p.info["pid"])
        except (ProcessLookupError, PermissionError):
            pass
    return out


def _run(args, env=None, check=True):
    proc = subprocess.run(RUNNER + [str(a) for a in args] + ["--no-progress"], env=env or _env(),
                          capture_output=True, text=True, timeout=120)
    if check:
        assert proc.returncode == 0, proc.stderr
    return proc


def _wait_flags(store, at_least, proc, timeout=60.0):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        f = flags(store)
        if f.size and f.sum() >= at_least:
            return int(f.sum())
        assert proc.poll() is None, "runner ended before the kill point"
        time.sleep(0.02)
    raise AssertionError("no progress")


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    return write_study(tmp_path_factory.mktemp("study"), **SIZE)


@pytest.fixture(scope="module")
def reference(study, tmp_path_factory):
    """The uninterrupted run: embedded LocalCluster with 2 workers."""
    store = tmp_path_factory.mktemp("ref") / "ref.zarr"
    _run([study, "--store", store, "--workers", 2])
    assert flags(store).all()
    return store_digest(store)


@contextlib.contextmanager
def _cluster(d, workers=2, threads=1, worker_env=None):
    """`dask scheduler` and ``workers`` `dask worker` processes of ``threads`` threads on 127.0.0.1,
    each in its own session; yields the scheduler's address, stops them all after."""
    from distributed import Client

    sfile = d / "scheduler.json"
    procs = []
    log = open(d / "cluster.log", "w")
    try:
        procs.append(subprocess.Popen([sys.executable, "-m", "dask", "scheduler", "--host", "127.0.0.1", "--port", "0",
                                       "--no-dashboard", "--scheduler-file", str(sfile)],
                                      stdout=log, stderr=log, start_new_session=True, env=_env()))
        t0 = time.monotonic()
        while not (sfile.exists() and sfile.stat().st_size):
            assert time.monotonic() - t0 < 30 and procs[0].poll() is None, "scheduler did not start"
            time.sleep(0.05)
        time.sleep(0.05)
        address = json.loads(sfile.read_text())["address"]
        for i in range(workers):
            procs.append(subprocess.Popen([sys.executable, "-m", "dask", "worker", address, "--nthreads", str(threads),
                                           "--nworkers", "1", "--host", "127.0.0.1", "--no-dashboard",
                                           "--name", f"w{i}"],
                                          stdout=log, stderr=log, start_new_session=True, env=worker_env or _env()))
        with Client(address, timeout="30s") as client:
            client.wait_for_workers(workers, timeout=60)
        yield address
    finally:
        for p in reversed(procs):
            _stop(p)
        log.close()
        left = [pid for p in procs for pid in _session_alive(p.pid)]
        assert not left, f"processes left behind: {left}"


@pytest.fixture(scope="module")
def scheduler(tmp_path_factory):
    """`dask scheduler` and two `dask worker` processes on 127.0.0.1, each in its own session."""
    with _cluster(tmp_path_factory.mktemp("cluster"), worker_env=_env(**PACE)) as address:
        yield address


def test_one_and_two_local_workers_give_identical_stores(study, reference, tmp_path):
    _run([study, "--store", tmp_path / "one.zarr", "--workers", 1])
    assert store_digest(tmp_path / "one.zarr") == reference


def test_external_scheduler_gives_the_local_result(study, reference, scheduler, tmp_path):
    proc = _run([study, "--store", tmp_path / "remote.zarr", "--scheduler", scheduler])
    assert f"running on {scheduler}" in proc.stderr
    assert store_digest(tmp_path / "remote.zarr") == reference


def test_killed_runner_resumes_to_the_identical_store(study, reference, tmp_path):
    store = tmp_path / "killed.zarr"
    args = RUNNER + [str(study), "--store", str(store), "--workers", "2", "--no-progress"]
    proc = subprocess.Popen(args, env=_env(**PACE), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    try:
        _wait_flags(store, 3, proc)
        # partial results are readable with xarray while the study runs: every flagged block is complete
        ds = open_results(store, flags=True)
        done_blocks = np.argwhere(ds.block_done.values == 1)
        for i, j in done_blocks:
            part = ds.x.isel(delta=slice(i, i + 1), realisation=slice(2 * j, 2 * j + 2)).values
            assert np.isfinite(part).all()
        children = psutil.Process(proc.pid).children(recursive=True)
        proc.send_signal(signal.SIGKILL)  # the runner only: its worker processes must exit by themselves
        proc.wait(10)
        done = int(flags(store).sum())
        _, alive = psutil.wait_procs(children, timeout=20)
        assert not [p for p in alive if p.status() != psutil.STATUS_ZOMBIE], "workers outlived the runner"
    finally:
        _stop(proc)
    total = flags(store).size
    assert 3 <= done < total, "the kill must land mid-study"
    resumed = _run([study, "--store", store, "--workers", 2])
    assert f"{done}/{total} blocks already done" in resumed.stderr
    assert store_digest(store) == reference


def test_killed_worker_tasks_are_rescheduled(study, reference, scheduler, tmp_path):
    from distributed import Client

    store = tmp_path / "worker-killed.zarr"
    # the scheduler comes from DASK_SCHEDULER_ADDRESS this time
    proc = subprocess.Popen(RUNNER + [str(study), "--store", str(store), "--no-progress"],
                            env=_env(DASK_SCHEDULER_ADDRESS=scheduler), stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        with Client(scheduler, timeout="30s") as client:
            _wait_flags(store, 2, proc)
            processing = client.processing()
            busy = [w for w, keys in processing.items() if any("tubeid-" in str(k) for k in keys)]
            assert busy, "no worker was running a block at the kill point"
            victim = client.run(os.getpid, workers=[busy[0]])[busy[0]]
            os.kill(victim, signal.SIGKILL)  # the worker process (its nanny restarts it)
            assert int(flags(store).sum()) < flags(store).size
            _, err = proc.communicate(timeout=120)
            assert proc.returncode == 0, err
            assert not psutil.pid_exists(victim) or psutil.Process(victim).status() == psutil.STATUS_ZOMBIE
            client.wait_for_workers(2, timeout=60)  # the nanny replaced it
    finally:
        _stop(proc)
    assert store_digest(store) == reference


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl")
def test_tls_cluster_from_the_cluster_settings(study, reference, tmp_path):
    """cluster/tls: certificates + dask config; a TLS scheduler/worker runs the study; no-cert clients are refused."""
    repo = pathlib.Path(__file__).resolve().parents[1]
    certs = tmp_path / "tls"
    subprocess.run(["bash", str(repo / "cluster/tls/make-certs.sh"), str(certs)], check=True, capture_output=True)
    env = _env(DASK_CONFIG=str(certs))
    with socket.socket() as s:  # a free port for the scheduler
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    address = f"tls://127.0.0.1:{port}"
    procs = [subprocess.Popen([sys.executable, "-m", "dask", "scheduler", "--host", "127.0.0.1", "--port", str(port),
                               "--no-dashboard"], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              start_new_session=True)]
    try:
        procs.append(subprocess.Popen([sys.executable, "-m", "dask", "worker", address, "--nthreads", "1",
                                       "--no-dashboard", "--host", "127.0.0.1"], env=env, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL, start_new_session=True))
        proc = _run([study, "--store", tmp_path / "tls.zarr", "--scheduler", address], env=env)
        assert f"running on {address}" in proc.stderr
        assert store_digest(tmp_path / "tls.zarr") == reference
        plain = _run([study, "--store", tmp_path / "plain.zarr", "--scheduler", address],
                     env=_env(TUBEID_RUNNER__CONNECT_TIMEOUT="5s"), check=False)
        assert plain.returncode == 2 and "cannot connect" in plain.stderr
        assert not (tmp_path / "plain.zarr").exists()
    finally:
        for p in reversed(procs):
            _stop(p)
        assert not [pid for p in procs for pid in _session_alive(p.pid)]


def _ctrl_c(proc) -> str:
    """Send a terminal's Ctrl-C to the runner's whole process group (SIGINT reaches every process
    of the foreground group); wait for it and check no process of it is left. Its stderr."""
    children = psutil.Process(proc.pid).children(recursive=True)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    _, alive = psutil.wait_procs(children, timeout=20)
    assert not [p for p in alive if p.status() != psutil.STATUS_ZOMBIE]
    return err


def test_ctrl_c_stops_cleanly_and_resumes(study, reference, tmp_path):
    store = tmp_path / "interrupted.zarr"
    proc = subprocess.Popen(RUNNER + [str(study), "--store", str(store), "--workers", "2", "--no-progress"],
                            env=_env(**PACE), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        _wait_flags(store, 2, proc)
        err = _ctrl_c(proc)
    finally:
        _stop(proc)
    assert proc.returncode == 130 and "rerun the same command to resume" in err
    assert 2 <= flags(store).sum() < flags(store).size
    _run([study, "--store", store, "--workers", 2])
    assert store_digest(store) == reference


# one block, held by the task (when `gate` names a directory) until `<gate>/open` exists: a task of a
# killed run still running on the cluster, finishing when the test says so
GATED = '''
import pathlib
import time
import numpy as np
from tubeid.runner.study import Output, Study

def task(block, rng, *, scale, gate):
    if gate:
        (pathlib.Path(gate) / "started").touch()
        while not (pathlib.Path(gate) / "open").exists():
            time.sleep(0.02)
    return {"y": scale * np.array([rng(realisation=r).standard_normal() for r in block["realisation"]])}

study = Study(name="gated", seed=5, axes={"realisation": range(4)}, chunks={"realisation": 4}, seed_axes=("realisation",),
              task=task, outputs={"y": Output()}, parameters={"scale": 1.0, "gate": ""})
'''


def _poll(condition, what, timeout=90.0):
    t0 = time.monotonic()
    while not condition():
        assert time.monotonic() - t0 < timeout, f"waited in vain for {what}"
        time.sleep(0.05)


def test_a_task_left_running_by_a_killed_run_never_writes_into_the_next_runs_store(tmp_path):
    """A runner SIGKILLed on an external cluster leaves its running task behind (cancelling does not stop a
    running task); an --overwrite run with other --set values completes meanwhile; then the orphan's
    block is done: its write is refused (the store holds another study hash), so the store stays the
    new run's, exactly, instead of holding the earlier definition's values under valid checksums."""
    from distributed import Client

    from tubeid.runner.execute import run

    study = tmp_path / "gated.py"
    study.write_text(GATED)
    gate = tmp_path / "gate"
    gate.mkdir()
    store = tmp_path / "s.zarr"
    run(study, tmp_path / "ref.zarr", workers=0, quiet=True, overrides={"scale": 2.0})
    reference = store_digest(tmp_path / "ref.zarr")
    # one worker of 2 threads: the orphan holds one, the next run's block runs on the other
    with _cluster(tmp_path, workers=1, threads=2) as address, Client(address, timeout="30s") as client:
        first = subprocess.Popen(RUNNER + [str(study), "--store", str(store), "--scheduler", address, "--set",
                                           f"gate={gate}", "--no-progress"], env=_env(), stdout=subprocess.DEVNULL,
                                 stderr=subprocess.DEVNULL, start_new_session=True)
        try:
            _poll(lambda: (gate / "started").exists() or first.poll() is not None, "the first run's block to start")
            assert first.poll() is None, "the first run ended before its block started"
            os.killpg(first.pid, signal.SIGKILL)
            first.wait(10)
            second = _run([study, "--store", store, "--scheduler", address, "--overwrite", "--set", "scale=2.0"])
            assert "error" not in second.stderr.lower() and store_digest(store) == reference
        finally:
            (gate / "open").touch()  # the orphan finishes its block now
            if first.poll() is None:
                os.killpg(first.pid, signal.SIGKILL)
                first.wait(10)

        def idle():
            return sum(client.run(lambda dask_worker: len(dask_worker.state.executing)).values()) == 0

        _poll(idle, "the orphaned task to end")
    assert store_digest(store) == reference  # not the first definition's values
    status = subprocess.run([sys.executable, "-m", "tubeid.runner.cli", "status", "--verify", str(store)], env=_env(),
                            capture_output=True, text=True, timeout=60)
    assert status.returncode == 0, status.stdout + status.stderr


def test_pipeline_on_an_external_scheduler_gives_the_in_process_result(scheduler, tmp_path):
    """Workers that never saw the pipeline rebuild each stage from its source and the stored earlier results."""
    from tubeid.runner.execute import run
    from tubeid.runner.testing import write_pipeline

    pipeline = write_pipeline(tmp_path, curve=4, around=6, work=200)
    proc = _run([pipeline, "--store", tmp_path / "remote.zarr", "--scheduler", scheduler])
    assert f"running on {scheduler}" in proc.stderr and "stage around: 3 of 3 blocks to compute" in proc.stderr
    run(pipeline, tmp_path / "here.zarr", workers=0, quiet=True)
    assert store_digest(tmp_path / "remote.zarr") == store_digest(tmp_path / "here.zarr")


def test_tcp_to_a_tls_scheduler_is_a_clear_error(tmp_path):
    """`tcp://` to a scheduler that speaks TLS: a refusal naming the scheduler and the remedy, no traceback."""
    repo = pathlib.Path(__file__).resolve().parents[1]
    if shutil.which("openssl") is None:
        pytest.skip("needs openssl")
    certs = tmp_path / "tls"
    subprocess.run(["bash", str(repo / "cluster/tls/make-certs.sh"), str(certs)], check=True, capture_output=True)
    env = _env(DASK_CONFIG=str(certs))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-m", "dask", "scheduler", "--host", "127.0.0.1", "--port", str(port),
                             "--no-dashboard"], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    try:
        time.sleep(1.0)
        study = write_study(tmp_path, realisations=2, chunk=2, work=1)
        out = _run([study, "--store", tmp_path / "s.zarr", "--scheduler", f"tcp://127.0.0.1:{port}"],
                   env=_env(DASK_CONFIG=str(certs), TUBEID_RUNNER__CONNECT_TIMEOUT="4s"), check=False)
    finally:
        _stop(proc)
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    assert f"scheduler = 'tcp://127.0.0.1:{port}': cannot connect within tubeid.runner.connect-timeout = 4s" in out.stderr
    assert "give its tls:// address" in out.stderr
    assert not (tmp_path / "s.zarr").exists()


def test_connect_timeout_comes_from_the_environment(tmp_path):
    """TUBEID_RUNNER__CONNECT_TIMEOUT (the Kubernetes job's variable) reaches the runner's Client."""
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    study = write_study(tmp_path, realisations=2, chunk=2, work=1)
    out = _run([study, "--store", tmp_path / "s.zarr", "--scheduler", f"tcp://127.0.0.1:{port}"],
               env=_env(TUBEID_RUNNER__CONNECT_TIMEOUT="3s"), check=False)
    assert out.returncode == 2 and "connect-timeout = 3s" in out.stderr and "Traceback" not in out.stderr


@pytest.mark.parametrize("scheme, hint", [("", "give its tls:// address"), ("tls://", "needs the client certificates")])
def test_an_unreachable_scheduler_names_the_tls_remedy(scheme, hint):
    """A bare host:port is tcp:// too (the TLS hint applies); tls:// without client certificates says what is missing."""
    import dask.config

    from tubeid.errors import SpecificationError
    from tubeid.runner.execute import _connect

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with dask.config.set({"tubeid.runner.connect-timeout": "2s"}), \
            pytest.raises(SpecificationError, match=rf"scheduler = '{scheme}127.0.0.1:{port}': cannot connect.*{hint}"):
        _connect(f"{scheme}127.0.0.1:{port}")


def _silent_listener():
    """A TCP socket that accepts connections (the kernel's backlog) and never says a word."""
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    s.listen(8)
    return s, s.getsockname()[1]


def test_a_scheduler_that_never_answers_is_refused_within_the_connect_timeout():
    """distributed's connect waits for the peer's handshake without a limit: the runner's does not."""
    import dask.config

    from tubeid.errors import SpecificationError
    from tubeid.runner.execute import _connect

    listener, port = _silent_listener()
    try:
        t0 = time.monotonic()
        with dask.config.set({"tubeid.runner.connect-timeout": "2s"}), \
                pytest.raises(SpecificationError, match=rf"scheduler = 'tcp://127.0.0.1:{port}': cannot connect within"
                                                        r".*no handshake from the peer within 2 s"):
            _connect(f"tcp://127.0.0.1:{port}")
        assert time.monotonic() - t0 < 10.0
    finally:
        listener.close()
    assert dask.config.get("scheduler", None) is None


def test_ctrl_c_while_the_embedded_cluster_starts_prints_one_line(study, reference, tmp_path):
    """A terminal's Ctrl-C while the embedded cluster's worker processes are starting (importing,
    before their preload ignores SIGINT): no worker traceback and no traceback from distributed's exit
    handler. That Ctrl-C is not seen (the workers are spawned with SIGINT ignored); the next one stops
    the run with the resume hint, and the resumed store is the uninterrupted one."""
    store = tmp_path / "start.zarr"
    proc = subprocess.Popen(RUNNER + [str(study), "--store", str(store), "--workers", "2", "--no-progress"],
                            env=_env(**PACE), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        t0 = time.monotonic()
        while not [c for c in psutil.Process(proc.pid).children(recursive=True) if "python" in c.name()]:
            assert proc.poll() is None and time.monotonic() - t0 < 60
            time.sleep(0.01)
        os.killpg(proc.pid, signal.SIGINT)  # a worker process exists: the cluster is starting
        _wait_flags(store, 2, proc)
        err = _ctrl_c(proc)
    finally:
        _stop(proc)
    assert proc.returncode == 130 and "rerun the same command to resume" in err, err
    assert "Traceback" not in err and "Exception ignored" not in err and "KeyboardInterrupt" not in err, err
    _run([study, "--store", store, "--workers", 2])
    assert store_digest(store) == reference


def test_ctrl_c_while_connecting_exits_at_once(tmp_path):
    """Ctrl-C while the runner waits for a scheduler: exit 130 with the resume hint, promptly, no traceback."""
    listener, port = _silent_listener()
    study = write_study(tmp_path, realisations=2, chunk=2, work=1)
    proc = subprocess.Popen(RUNNER + [str(study), "--store", str(tmp_path / "s.zarr"), "--scheduler",
                                      f"tcp://127.0.0.1:{port}", "--no-progress"],
                            env=_env(TUBEID_RUNNER__CONNECT_TIMEOUT="30s"), stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        time.sleep(4.0)  # imports done, waiting for the scheduler's answer
        assert proc.poll() is None
        t0 = time.monotonic()
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=60)
        waited = time.monotonic() - t0
    finally:
        _stop(proc)
        listener.close()
    assert proc.returncode == 130 and "rerun the same command to resume" in err, err
    assert "Traceback" not in err and waited < 10.0, (waited, err)


def test_the_embedded_cluster_admits_only_its_own_client(study, tmp_path):
    """Ephemeral TLS: the embedded scheduler speaks TLS only and refuses a client with other credentials."""
    from distributed import Client
    from distributed.security import Security

    from tubeid.runner.execute import _client

    with _client(1, None, None, True) as (client, where):
        address = client.scheduler.address
        assert address.startswith("tls://127.0.0.1:") and "TLS with ephemeral credentials" in where
        assert client.submit(lambda: 21 * 2, pure=False).result() == 42
        for addr, security in ((address.replace("tls://", "tcp://"), None), (address, Security.temporary())):
            with pytest.raises(Exception):  # plain TCP, or TLS with a certificate the cluster did not issue
                # not the default Client: one that failed to start can leave dask.config's scheduler set
                Client(addr, security=security, timeout="3s", set_as_default=False).close()
        assert client.submit(lambda: 1, pure=False).result() == 1  # still serving its own client


def test_the_runners_own_clients_leave_the_callers_dask_config_alone():
    """The embedded cluster's Client and a Client that failed to connect never become the process's
    default Client nor set dask.config's scheduler: a caller's later xarray/dask compute (a notebook,
    the next test) must not need a Client the runner opened and closed."""
    import dask.config
    from distributed import default_client

    from tubeid.errors import SpecificationError
    from tubeid.runner.execute import _client, _connect

    assert dask.config.get("scheduler", None) is None
    with _client(1, None, None, True) as (client, _):
        assert client.submit(lambda: 2, pure=False).result() == 2
        assert dask.config.get("scheduler", None) is None
        with pytest.raises(ValueError):
            default_client()
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with dask.config.set({"tubeid.runner.connect-timeout": "2s"}), pytest.raises(SpecificationError):
        _connect(f"tcp://127.0.0.1:{port}")
    assert dask.config.get("scheduler", None) is None


def test_the_embedded_workers_leave_ctrl_c_to_the_runner():
    """A terminal's Ctrl-C reaches the embedded worker processes too: they ignore it (the runner stops them)."""
    from tubeid.runner.execute import _client

    with _client(2, None, None, True) as (client, _):
        handlers = client.run(lambda: signal.getsignal(signal.SIGINT) is signal.SIG_IGN)
    assert len(handlers) == 2 and all(handlers.values()), handlers


def _exec_environ_and_mmapped_blocks():
    """In a worker: the variables of its environment at exec time (/proc/self/environ: what glibc
    read) and how many of malloc's blocks a fresh 1 MiB malloc adds to mmapped memory (glibc's
    mallinfo2.hblks; None without glibc)."""
    import ctypes

    with open("/proc/self/environ", "rb") as fh:
        env = dict(e.decode().split("=", 1) for e in fh.read().split(b"\0") if b"=" in e)
    try:
        libc = ctypes.CDLL(None)
        mallinfo2 = libc.mallinfo2
    except (OSError, AttributeError):
        return env, None

    class Info(ctypes.Structure):
        _fields_ = [(f, ctypes.c_size_t) for f in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                   "fsmblks", "uordblks", "fordblks", "keepcost")]

    mallinfo2.restype = Info
    libc.malloc.restype, libc.malloc.argtypes, libc.free.argtypes = ctypes.c_void_p, [ctypes.c_size_t], [ctypes.c_void_p]
    before = mallinfo2().hblks
    p = libc.malloc(1 << 20)
    mapped = mallinfo2().hblks - before
    libc.free(p)
    return env, mapped


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/environ")
def test_the_embedded_workers_start_with_the_configured_environment(monkeypatch):
    """tubeid.runner.worker-environ is in the worker processes' environment from their start (glibc
    reads its allocator variables only then: a 1 MiB array comes from the heap, not from a mapping
    as with dask's 64 KiB trim threshold), a variable in the caller's environment wins, dask's own
    pre-spawn variables stay, and the caller's environment is as before once the cluster is closed."""
    import dask
    import distributed  # noqa: F401  (its configuration defaults)

    from tubeid import config
    from tubeid.runner.execute import _client

    monkeypatch.delenv("MALLOC_MMAP_THRESHOLD_", raising=False)
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    monkeypatch.delenv("TUBEID_TEST_DASK_VAR", raising=False)
    monkeypatch.setenv("TUBEID_TEST_USER_VAR", "mine")
    packaged = config.get("runner.worker-environ")
    dasks = {**dask.config.get("distributed.nanny.pre-spawn-environ"), "TUBEID_TEST_DASK_VAR": "dask"}
    managed = {*dasks, *packaged, "TUBEID_TEST_USER_VAR", "PYTHONHASHSEED"}  # what the nannies write here
    before = {k: os.environ.get(k) for k in managed}
    with dask.config.set({"distributed.nanny.pre-spawn-environ": dasks,
                          "tubeid.runner.worker-environ": {**packaged, "TUBEID_TEST_USER_VAR": "tubeid"}}):
        with _client(1, None, None, True) as (client, _):
            ((env, mapped),) = client.run(_exec_environ_and_mmapped_blocks).values()
    assert {k: env.get(k) for k in ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "TUBEID_TEST_DASK_VAR",
                                    "TUBEID_TEST_USER_VAR")} == {
        "MALLOC_MMAP_THRESHOLD_": str(packaged["MALLOC_MMAP_THRESHOLD_"]),
        "MALLOC_TRIM_THRESHOLD_": str(packaged["MALLOC_TRIM_THRESHOLD_"]),
        "TUBEID_TEST_DASK_VAR": "dask", "TUBEID_TEST_USER_VAR": "mine"}, env
    assert mapped in (0, None), mapped  # None: no glibc here
    assert {k: os.environ.get(k) for k in managed} == before  # the nannies' writes into this process are undone


def test_a_users_client_is_used_and_never_closed(study, reference, tmp_path, capsys):
    """run(client=...) and, without client/workers/scheduler, distributed.default_client(): the user's
    LocalCluster runs the blocks (identical store) and stays open."""
    from distributed import Client, LocalCluster

    from tubeid.runner.execute import run

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                      host="127.0.0.1") as cluster, Client(cluster) as client:
        rep = run(study, tmp_path / "given.zarr", client=client, progress=False)
        err = capsys.readouterr().err
        assert f"running on the given dask Client (scheduler {cluster.scheduler_address})" in err
        assert rep.workers == 2 and store_digest(tmp_path / "given.zarr") == reference
        assert client.status == "running" and client.submit(lambda: 3, pure=False).result() == 3
        rep = run(study, tmp_path / "default.zarr", progress=False)  # the notebook case: nothing said
        err = capsys.readouterr().err
        assert "already open in this process" in err and "distributed.default_client()" in err
        assert rep.workers == 2 and store_digest(tmp_path / "default.zarr") == reference
        assert client.status == "running" and cluster.status.name == "running"
        with pytest.raises(Exception, match="give a client, --workers or --scheduler"):
            run(study, tmp_path / "x.zarr", client=client, workers=2)


WARM = """
import os, pathlib, time
import numpy as np
from tubeid.runner import Output, Study, Warmup

MARK = pathlib.Path(r"MARKDIR")

def needed():
    return not (MARK / "compiled").exists()

def compile_once():
    with open(MARK / "log", "a") as fh:
        fh.write(f"{os.getpid()}\\n")
    time.sleep(0.2)
    (MARK / "compiled").write_text("")

def task(block, rng):
    assert (MARK / "compiled").exists(), "a block ran before the warm-up"
    return {"u": np.asarray(block["r"], float)}

study = Study(name="warm", seed=0, axes={"r": range(8)}, chunks={"r": 2}, task=task, outputs={"u": Output()},
              warmup=Warmup("compiling the test kernel, once per machine", run=compile_once, needed=needed))
"""


@pytest.mark.parametrize("workers", [0, 2])
def test_warmup_runs_once_per_machine_before_the_blocks_and_says_so(tmp_path, workers):
    mark = tmp_path / "mark"
    mark.mkdir()
    path = tmp_path / "warm.py"
    path.write_text(WARM.replace("MARKDIR", str(mark)))
    first = _run([path, "--store", tmp_path / "a.zarr", "--workers", workers])
    assert "tubeid: compiling the test kernel, once per machine" in first.stderr
    assert first.stderr.index("compiling the test kernel") < first.stderr.index("done:")
    assert len((mark / "log").read_text().split()) == 1  # one machine: once, whatever the worker count
    second = _run([path, "--store", tmp_path / "b.zarr", "--workers", workers])
    assert "compiling" not in second.stderr and len((mark / "log").read_text().split()) == 1


SLOW_WARM = """
import pathlib, time
import numpy as np
from tubeid.runner.study import Output, Study, Warmup

def slow_warmup():
    pathlib.Path("MARKFILE").write_text("started")
    time.sleep(120)  # interrupted long before

def task(block, rng):
    return {"u": np.asarray(block["r"], float)}

study = Study(name="slow-warm", seed=0, axes={"r": range(4)}, chunks={"r": 2}, task=task, outputs={"u": Output()},
              warmup=Warmup("a slow warm-up", run=slow_warmup, needed=lambda: True))
"""


def test_ctrl_c_during_the_warmup_is_a_clean_exit(tmp_path):
    """Ctrl-C while one worker warms up and the other waits: exit 130 with the resume hint and nothing else
    (no asyncio "Task exception was never retrieved", no worker process's KeyboardInterrupt traceback)."""
    mark = tmp_path / "warming"
    path = tmp_path / "slow.py"
    path.write_text(SLOW_WARM.replace("MARKFILE", str(mark)))
    proc = subprocess.Popen(RUNNER + [str(path), "--store", str(tmp_path / "s.zarr"), "--workers", "2", "--no-progress"],
                            env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        t0 = time.monotonic()
        while not mark.exists():  # the warm-up has started on a worker: the runner waits for it
            assert proc.poll() is None, f"runner ended before the warm-up: {proc.communicate()[1]}"
            assert time.monotonic() - t0 < 60, "the warm-up did not start"
            time.sleep(0.02)
        err = _ctrl_c(proc)
    finally:
        _stop(proc)
    assert proc.returncode == 130, err
    assert "tubeid: a slow warm-up" in err and "rerun the same command to resume" in err
    assert "Traceback" not in err and "never retrieved" not in err, f"Ctrl-C during the warm-up is not clean:\n{err}"


@pytest.mark.parametrize("env, says", [
    ({"TUBEID_RUNNER__WORKERS": "-1"}, "tubeid.runner.workers (TUBEID_RUNNER__WORKERS) = -1: must be an integer >= 1"),
    ({"TUBEID_RUNNER__WORKERS": "abc"}, "tubeid.runner.workers (TUBEID_RUNNER__WORKERS) = 'abc': must be an integer"),
    ({"TUBEID_RUNNER__THREADS_PER_WORKER": "0"}, "tubeid.runner.threads-per-worker (TUBEID_RUNNER__THREADS_PER_WORKER) = 0"),
    ({"TUBEID_RUNNER__HOST": "999.1.1.1"}, "check tubeid.runner.host and tubeid.runner.dashboard-address"),
])
def test_the_embedded_clusters_settings_are_checked(tmp_path, env, says):
    """Settings of the embedded cluster from the environment: a bad one is one line naming it and its
    variable, status 2, no store (-1 workers used to hang with the store locked; a host the scheduler
    cannot bind to was blamed on an unguarded script, which `tubeid run` is not)."""
    study = write_study(tmp_path, realisations=2, chunk=2, work=1)
    out = subprocess.run(RUNNER + [str(study), "--store", str(tmp_path / "s.zarr"), "--no-progress"], env=_env(**env),
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and says in out.stderr and "Traceback" not in out.stderr, out.stderr
    assert "calls run() outside" not in out.stderr
    assert not (tmp_path / "s.zarr").exists()
