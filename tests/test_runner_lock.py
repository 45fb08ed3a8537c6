"""One runner per store: the lock is exclusive, names its holder, is taken over when stale (by exactly one
of several racing runners), follows a heartbeat for other hosts, notices when it is lost; two `tubeid run`
started at once on the same new store leave one complete, readable store with its whole provenance.
"""

import json
import multiprocessing
import os
import pathlib
import socket
import subprocess
import sys
import time

import pytest

from tubeid.errors import SpecificationError
from tubeid.runner import lock as lockmod
from tubeid.runner.lock import LOCK_NAME, LockLost, StoreLock, read_lock
from tubeid.runner.store import open_results, store_status
from tubeid.runner.testing import store_digest


def _dead_pid() -> int:
    """A PID that belonged to a process of this host that has exited (and been reaped)."""
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def _write_record(store: pathlib.Path, name: str = LOCK_NAME, **fields) -> dict:
    rec = lockmod._me()
    rec.update(fields)
    store.mkdir(parents=True, exist_ok=True)
    (store / name).write_text(json.dumps(rec))
    return rec


def test_a_held_lock_refuses_a_second_runner_naming_the_holder(tmp_path):
    store = tmp_path / "s.zarr"
    with StoreLock(store) as held:
        rec = read_lock(store / LOCK_NAME)
        assert rec["pid"] == os.getpid() and rec["host"] == socket.gethostname() and rec["started"]
        with pytest.raises(SpecificationError, match=rf"in use by another tubeid run \(host {socket.gethostname()}, "
                                                     rf"pid {os.getpid()}, started .*is running on this host"):
            StoreLock(store).acquire()
        assert held.created_store
    assert not (store / LOCK_NAME).exists()  # released
    with StoreLock(store):  # and free again
        pass


def test_a_lock_of_a_dead_process_is_taken_over(tmp_path):
    store = tmp_path / "s.zarr"
    _write_record(store, pid=_dead_pid())
    logged = []
    with StoreLock(store, log=logged.append):
        assert read_lock(store / LOCK_NAME)["pid"] == os.getpid()
    assert "no longer exists" in logged[0]
    # a PID now used by another process (here: this one) with another start time is dead too
    _write_record(store, pid_start=12345.0)
    assert lockmod.holder_state(read_lock(store / LOCK_NAME), store / LOCK_NAME)[0] == "dead"
    # a PID reused a second later (the usual case) is told apart too; the holder's own start time is alive
    mine = lockmod._process_start(os.getpid())
    for start, state in ((mine - 1.0, "dead"), (mine + 1.0, "dead"), (mine, "alive")):
        _write_record(store, pid_start=start)
        assert lockmod.holder_state(read_lock(store / LOCK_NAME), store / LOCK_NAME)[0] == state, start
    # another boot id under this host's name: rebooted, or another machine of the same name (cloned VMs)
    # whose runner is alive: judged by the heartbeat, never by this host's PIDs
    _write_record(store, boot="another-boot", pid=os.getpid())
    assert lockmod.holder_state(read_lock(store / LOCK_NAME), store / LOCK_NAME)[0] == "alive"
    with pytest.raises(SpecificationError, match="last heartbeat was"):
        StoreLock(store).acquire()
    _write_record(store, boot="another-boot", pid=_dead_pid())
    assert lockmod.holder_state(read_lock(store / LOCK_NAME), store / LOCK_NAME)[0] == "alive"
    old = time.time() - 90
    os.utime(store / LOCK_NAME, (old, old))
    state, why = lockmod.holder_state(read_lock(store / LOCK_NAME), store / LOCK_NAME)
    assert state == "dead" and "no heartbeat for 9" in why and "rebooted since" in why


def _racer(store, barrier, results):
    barrier.wait()
    try:
        lk = StoreLock(store).acquire()
        time.sleep(0.3)  # hold it while the others try
        results.put(("won", os.getpid()))
        lk.release()
    except SpecificationError as exc:
        results.put(("refused", str(exc)))


@pytest.mark.parametrize("breaker", ["none", "dead breaker"])
def test_racers_for_a_stale_lock_have_exactly_one_winner(tmp_path, breaker):
    ctx = multiprocessing.get_context("fork")
    for trial in range(5):
        store = tmp_path / f"s{trial}.zarr"
        stale = _write_record(store, pid=_dead_pid())
        if breaker == "dead breaker":  # a runner died while breaking it: its break file is left behind
            _write_record(store, name=f"{LOCK_NAME}.break-{stale['token']}", pid=_dead_pid())
        n = 6
        barrier, results = ctx.Barrier(n), ctx.Queue()
        procs = [ctx.Process(target=_racer, args=(store, barrier, results)) for _ in range(n)]
        for p in procs:
            p.start()
        out = [results.get(timeout=60) for _ in range(n)]
        for p in procs:
            p.join(30)
        winners = [o for o in out if o[0] == "won"]
        assert len(winners) == 1, out
        assert all("in use by another tubeid run" in o[1] for o in out if o[0] == "refused")
        assert not (store / LOCK_NAME).exists()
        assert not list(store.glob(f"{LOCK_NAME}.break-*")), "break files left behind"


KILLED_TAKING_THE_LOCK = """
import os, sys
from tubeid.runner import lock
os.link = lambda *a: os._exit(9)  # killed between writing its private file and linking it to the lock name
lock.StoreLock(sys.argv[1]).acquire()
"""


def _left_by_a_killed(script: str, store: pathlib.Path, kind: str) -> list[str]:
    """Run ``script`` on the new directory ``store`` in a process it kills (exit 9): the one file it leaves,
    named ``.tubeid-lock<kind>...``."""
    store.mkdir()
    killed = subprocess.run([sys.executable, "-c", script, str(store)], capture_output=True, text=True)
    assert killed.returncode == 9, killed.stderr
    left = [f.name for f in store.iterdir()]
    assert len(left) == 1 and left[0].startswith(f"{LOCK_NAME}{kind}"), left
    return left


def test_a_runner_killed_while_taking_the_lock_leaves_nothing_after_the_next_run(tmp_path):
    """A real process killed between its private file and the link: the next holder removes the file,
    and only the files it can prove are such leftovers of a dead process (name, complete record, token)."""
    store = tmp_path / "s.zarr"
    left = _left_by_a_killed(KILLED_TAKING_THE_LOCK, store, ".tmp-")
    token = read_lock(store / left[0])["token"]
    # look-alikes that prove nothing: a live process's private file, a token that is not the name's,
    # an empty one (killed before its record was written), a user's file, a link to a dead record
    _write_record(store, name=f"{LOCK_NAME}.tmp-{'a' * 24}", token="a" * 24)  # this process: alive
    _write_record(store, name=f"{LOCK_NAME}.tmp-{'b' * 24}", token="c" * 24, pid=_dead_pid())
    (store / f"{LOCK_NAME}.tmp-{'d' * 24}").write_bytes(b"")
    _write_record(store, name=f"{LOCK_NAME}.tmp-notes", token="notes", pid=_dead_pid())
    _write_record(store, name=f"{LOCK_NAME}.tmp-{'f' * 24}.bak", token="f" * 24, pid=_dead_pid())  # a user's copy
    _write_record(tmp_path, name="elsewhere", token="e" * 24, pid=_dead_pid())
    (store / f"{LOCK_NAME}.tmp-{'e' * 24}").symlink_to(tmp_path / "elsewhere")
    kept = sorted(f.name for f in store.iterdir() if f.name != left[0])
    logged = []
    with StoreLock(store, log=logged.append):
        assert sorted(f.name for f in store.iterdir() if f.name != LOCK_NAME) == kept
    assert len(logged) == 1 and "removed 1 file(s)" in logged[0] and token in logged[0]
    assert (tmp_path / "elsewhere").exists()


def test_a_break_file_of_a_dead_breaker_is_removed_unless_it_breaks_the_current_lock(tmp_path):
    """A breaker's record carries its depth ("<token>-<depth>", depth = the name's breaks - 1); dead ones
    are removed (on another host: by a stale heartbeat), live ones and any break of the current lock kept."""
    store = tmp_path / "s.zarr"
    gone = _write_record(store, name=f"{LOCK_NAME}.break-{'1' * 24}", token=f"{'7' * 24}-0", pid=_dead_pid())
    nested = f"{LOCK_NAME}.break-{'2' * 24}.break-{gone['token']}"
    _write_record(store, name=nested, token=f"{'3' * 24}-1", pid=_dead_pid())
    breaker_tmp = f"{LOCK_NAME}.break-{'4' * 24}.tmp-{'5' * 24}-0"
    _write_record(store, name=breaker_tmp, token=f"{'5' * 24}-0", pid=_dead_pid())
    stale = _write_record(store, name=f"{LOCK_NAME}.break-{'8' * 24}", token=f"{'8' * 24}-0", host="other-host", pid=1)
    old = time.time() - 90
    os.utime(store / f"{LOCK_NAME}.break-{'8' * 24}", (old, old))
    keep = [_write_record(store, name=f"{LOCK_NAME}.break-{'6' * 24}", token=f"{'6' * 24}-0"),  # this process: alive
            _write_record(store, name=f"{LOCK_NAME}.break-{'9' * 24}", token=f"{'9' * 24}-0", host="other-host", pid=1),
            _write_record(store, name=f"{LOCK_NAME}.break-{'a' * 24}", token="b" * 24, pid=_dead_pid())]  # no depth
    assert stale["host"] == "other-host" and keep[0]["pid"] == os.getpid()
    with StoreLock(store) as held:
        names = sorted(f.name for f in store.iterdir())
        assert names == sorted([LOCK_NAME] + [f"{LOCK_NAME}.break-{c * 24}" for c in "69a"]), names
        # a break of the lock now held, or of its break file, is someone's take-over in progress: never a leftover
        mine = f"{LOCK_NAME}.break-{held.record['token']}"
        _write_record(store, name=mine, token=f"{'c' * 24}-0", pid=_dead_pid())
        _write_record(store, name=f"{mine}.break-{'c' * 24}-0", token=f"{'d' * 24}-1", pid=_dead_pid())
        assert lockmod.remove_leftovers(store, held.record["token"]) == []


KILLED_READING_THE_CLOCK = """
import os, sys
from tubeid.runner import lock
real = os.stat
def stat(path, *a, **k):
    if ".probe-" in os.fspath(path):
        os._exit(9)  # killed between creating the probe and removing it
    return real(path, *a, **k)
os.stat = stat
lock._server_age(lock.pathlib.Path(sys.argv[1]) / lock.LOCK_NAME, lock._me())
"""


def test_a_probe_left_by_a_runner_killed_while_reading_the_clock_is_removed(tmp_path):
    """The probe holds its process's record: a dead one's is removed by the next holder, a live one's, an
    empty one (a user's look-alike, or a probe of an earlier tubeid) and one whose token is not its name's kept."""
    store = tmp_path / "s.zarr"
    left = _left_by_a_killed(KILLED_READING_THE_CLOCK, store, ".probe-")
    rec = read_lock(store / left[0])
    assert rec and left[0].startswith(f"{LOCK_NAME}.probe-{rec['token']}-") and rec["pid"] != os.getpid()
    _write_record(store, name=f"{LOCK_NAME}.probe-{'a' * 24}-0123abcd", token="a" * 24)  # this process: alive
    _write_record(store, name=f"{LOCK_NAME}.probe-{'b' * 24}-0123abcd", token="c" * 24, pid=_dead_pid())
    (store / f"{LOCK_NAME}.probe-{'d' * 24}-0123abcd").write_bytes(b"")
    gone = _write_record(store, name=f"{LOCK_NAME}.break-{'1' * 24}.probe-{'e' * 24}-89abcdef", token="e" * 24,
                         pid=_dead_pid())
    kept = sorted(f.name for f in store.iterdir() if f.name != left[0] and "e" * 24 not in f.name)
    logged = []
    with StoreLock(store, log=logged.append):
        assert sorted(f.name for f in store.iterdir() if f.name != LOCK_NAME) == kept
    assert len(logged) == 1 and "removed 2 file(s)" in logged[0] and gone["token"] in logged[0]
    assert rec["token"] in logged[0]


def test_the_sweep_never_costs_the_run(tmp_path):
    """A leftover that cannot be removed (a sticky shared directory, another user's file) or a damaged
    record: left in place, the lock taken and released as usual."""
    store = tmp_path / "s.zarr"
    _write_record(store, name=f"{LOCK_NAME}.tmp-{'1' * 24}", token="1" * 24, pid=None)  # damaged: no PID
    _write_record(store, name=f"{LOCK_NAME}.tmp-{'2' * 24}", token="2" * 24, pid=_dead_pid(), pid_start="x")
    (store / f"{LOCK_NAME}.tmp-{'3' * 24}").mkdir()  # a directory of that name
    real = os.unlink

    def refused(path, *a, **k):
        if str(path).endswith("2" * 24):
            raise PermissionError(1, "Operation not permitted", str(path))
        return real(path, *a, **k)

    os.unlink = refused
    try:
        with StoreLock(store) as held:
            assert read_lock(store / LOCK_NAME)["token"] == held.record["token"]
    finally:
        os.unlink = real
    assert not (store / LOCK_NAME).exists()  # released
    assert sorted(f.name for f in store.iterdir()) == [f"{LOCK_NAME}.tmp-{c * 24}" for c in "123"]
    with StoreLock(store):  # and, removable now, the dead one goes
        assert not (store / f"{LOCK_NAME}.tmp-{'2' * 24}").exists()


def test_a_lock_from_another_host_needs_a_stale_heartbeat(tmp_path):
    import dask.config

    store = tmp_path / "s.zarr"
    _write_record(store, host="other-host", pid=1)
    with pytest.raises(SpecificationError, match=r"host other-host.*last heartbeat was \d+ s ago"):
        StoreLock(store).acquire()
    old = time.time() - 90
    os.utime(store / LOCK_NAME, (old, old))
    with dask.config.set({"tubeid.runner.lock-stale-after": "120s"}):  # configurable: 90 s is not stale yet
        with pytest.raises(SpecificationError, match="stale after 120 s"):
            StoreLock(store).acquire()
    logged = []
    with StoreLock(store, log=logged.append):  # default 60 s: stale
        pass
    assert "no heartbeat for 9" in logged[0] and "other-host" in logged[0]


def test_the_heartbeat_keeps_the_lock_fresh_and_notices_a_takeover(tmp_path):
    import dask.config

    store = tmp_path / "s.zarr"
    with dask.config.set({"tubeid.runner.lock-heartbeat": "0.05s"}):
        lk = StoreLock(store).acquire()
    try:
        old = time.time() - 1000
        os.utime(store / LOCK_NAME, (old, old))
        time.sleep(0.3)
        assert time.time() - os.stat(store / LOCK_NAME).st_mtime < 5  # touched again
        lk.check()
        _write_record(store, host="other-host", token="someone-else")  # taken over meanwhile
        time.sleep(0.3)
        with pytest.raises(LockLost, match="taken over by another runner"):
            lk.check()
    finally:
        lk.release()
    assert read_lock(store / LOCK_NAME)["token"] == "someone-else"  # not ours: not removed


RUNNER = [sys.executable, "-m", "tubeid.runner.cli", "run"]
# 4 blocks that each sleep 0.5 s (no CPU): the first runner holds the store for >= 2 s whatever the load
SLEEPY = """
import time
import numpy as np
from tubeid.runner import Output, Study

def task(block, rng):
    time.sleep(0.5)
    return {"u": np.array([rng(realisation=r).standard_normal() for r in block["realisation"]])}

study = Study(name="sleepy", seed=3, axes={"realisation": range(8)}, chunks={"realisation": 2}, task=task,
              outputs={"u": Output(units="m")})
"""


def test_two_runs_started_at_once_on_a_new_store(tmp_path):
    """`tubeid run` twice at once on the same new store, several times: one runs, the other is refused
    clearly; the store is complete, identical to a lone run's and its provenance records one run."""
    study = tmp_path / "sleepy.py"
    study.write_text(SLEEPY)
    env = dict(os.environ)
    env.pop("DASK_SCHEDULER_ADDRESS", None)
    subprocess.run(RUNNER + [str(study), "--store", str(tmp_path / "alone.zarr"), "--workers", "0", "--no-progress"],
                   check=True, capture_output=True, env=env)
    reference = store_digest(tmp_path / "alone.zarr")
    for trial in range(3):
        store = tmp_path / f"race{trial}.zarr"
        cmd = RUNNER + [str(study), "--store", str(store), "--workers", "0", "--no-progress"]
        procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env) for _ in range(2)]
        outs = [p.communicate(timeout=120) for p in procs]
        codes = sorted(p.returncode for p in procs)
        errs = [e for _, e in outs]
        assert codes == [0, 2], errs
        refused = next(e for p, (_, e) in zip(procs, outs) if p.returncode == 2)
        assert "is in use by another tubeid run" in refused and "Traceback" not in refused
        assert sum("new store" in e for e in errs) == 1
        st = store_status(store)
        assert st["complete"] and len(st["attrs"]["runs"]) == 1 and st["attrs"]["study_source"] == SLEEPY
        assert st["lock"] is None and store_digest(store) == reference
        assert open_results(store).u.notnull().all()


def test_a_lock_file_that_is_not_utf8_is_unreadable_not_a_crash(tmp_path, capsys):
    """A lock file of bytes that are not UTF-8 is damaged like a lock of JSON garbage: ``status`` says
    "lock file unreadable", ``run`` refuses in one line naming it (no UnicodeDecodeError traceback)."""
    from tubeid.cli import main
    from tubeid.runner.execute import run
    from tubeid.runner.testing import write_study

    study = write_study(tmp_path, realisations=2)
    store = tmp_path / "lk.zarr"
    run(study, store, workers=0, quiet=True)
    (store / LOCK_NAME).write_bytes(b"\xff garbage")
    assert read_lock(store / LOCK_NAME) == {}
    assert main(["status", str(store)]) == 0
    out, err = capsys.readouterr()
    assert "  lock file unreadable" in out and err == ""
    assert main(["run", str(study), "--store", str(store), "--workers", "0", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"tubeid: error: store = {str(store)!r}: has an unreadable lock file") and err.count("\n") == 1
    assert (store / LOCK_NAME).read_bytes() == b"\xff garbage"  # not ours: left for the user


@pytest.mark.parametrize("variable, value, rule", [
    ("TUBEID_RUNNER__LOCK_HEARTBEAT", "abc", "must be a duration > 0"),
    ("TUBEID_RUNNER__LOCK_HEARTBEAT", "-1", "must be a duration > 0"),
    ("TUBEID_RUNNER__LOCK_HEARTBEAT", "0", "must be a duration > 0"),
    ("TUBEID_RUNNER__LOCK_STALE_AFTER", "nan", "must be a duration > 0"),
    ("TUBEID_RUNNER__LOCK_HEARTBEAT", "90s", "must be shorter than tubeid.runner.lock-stale-after = 60 s"),
])
def test_a_bad_lock_setting_is_refused_before_the_store_is_created(tmp_path, variable, value, rule):
    """``TUBEID_RUNNER__LOCK_HEARTBEAT=abc tubeid run ...``: one line naming the setting and its environment
    variable, status 2, and no store directory holding only a lock file (it used to be a KeyError traceback
    once the lock file existed)."""
    from tubeid.runner.testing import write_study

    study = write_study(tmp_path, realisations=2)
    store = tmp_path / "ev3.zarr"
    env = {k: v for k, v in os.environ.items() if not k.startswith("TUBEID_RUNNER__LOCK")} | {variable: value}
    env.pop("DASK_SCHEDULER_ADDRESS", None)
    proc = subprocess.run(RUNNER + [str(study), "--store", str(store), "--workers", "0", "--no-progress"],
                          capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 2, proc.stderr
    key = variable.removeprefix("TUBEID_RUNNER__").lower().replace("_", "-")
    assert proc.stderr.startswith(f"tubeid: error: tubeid.runner.{key} ({variable}) = "), proc.stderr
    assert rule in proc.stderr and proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
    assert not store.exists()


def test_the_lock_settings_are_checked_before_anything_is_created(tmp_path):
    import dask.config

    store = tmp_path / "s.zarr"
    with dask.config.set({"tubeid.runner.lock-heartbeat": "abc"}):
        with pytest.raises(SpecificationError, match=r"tubeid\.runner\.lock-heartbeat \(TUBEID_RUNNER__LOCK_HEARTBEAT\) "
                                                     r"= 'abc': must be a duration > 0"):
            StoreLock(store).acquire()
    assert not store.exists()
    with dask.config.set({"tubeid.runner.lock-heartbeat": 30, "tubeid.runner.lock-stale-after": "20s"}):
        with pytest.raises(SpecificationError, match="must be shorter than tubeid.runner.lock-stale-after = 20 s"):
            StoreLock(store).acquire()
    assert not store.exists()
    assert lockmod.lock_settings() == (10.0, 60.0)  # the defaults
