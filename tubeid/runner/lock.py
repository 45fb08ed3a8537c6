"""One runner per store: a lock file with who holds it, taken atomically, taken over when stale.

The lock is the file ``<store>/.tubeid-lock``: a JSON record of the holder (``host``, ``pid``,
``started``, a random ``token``, and the host's boot id, PID namespace and the process start time,
which tell a live process from a dead one whose PID was reused). A second runner finds the file
and is refused, naming the holder.

**Taking it** is an atomic exclusive create: the record is written completely to a private file,
then hard-linked to the lock name (``link(2)`` fails if the name exists; readers never see a
half-written lock). Where hard links are not supported, ``open(O_CREAT | O_EXCL)`` is used instead.

**Stale locks.** A holder on this host (same host name, boot id and PID namespace) is dead when
its PID is gone or now belongs to a process started at another time. A holder elsewhere (another
host, container or pod; also a host of the same name with another boot id: rebooted, or a second
machine of the same name) cannot be asked: it proves it is alive by a heartbeat, touching the lock
file every ``tubeid.runner.lock-heartbeat`` (default 10 s); its lock is stale when the file's
modification time is older than ``tubeid.runner.lock-stale-after`` (default 60 s), measured on
the file server's clock (against a probe file created beside it), so clock skew between hosts
does not count. Both settings are checked before anything is created (a duration > 0, the heartbeat
shorter than ``lock-stale-after``); a bad one is refused naming the setting and its environment
variable. A lock file that cannot be read (not UTF-8, not JSON) is reported as unreadable, never taken over.

**Taking over a stale lock** must not let two racing runners both win. The lock instance with
token T may be removed only by the one process that creates ``.tubeid-lock.break-T`` exclusively
(the same atomic create); it then checks that the lock still holds token T, removes it, removes
its break file and retries the normal exclusive create, which only one runner can win. A lock
instance never comes back once removed, so the check-then-remove cannot remove a newer lock. A
break file left by a breaker that died is itself broken the same way (its own token).

**Leftovers of a killed runner.** A runner killed while taking the lock or breaking a stale one
leaves its private file (``.tubeid-lock.tmp-<token>``) or its break file (``.tubeid-lock.break-T``,
and their own ``.tmp-`` files); one killed while reading the file server's clock leaves that probe
(``.tubeid-lock.probe-<token>-<8 hex>``, beside the lock or a break file). Whoever takes the lock next
removes those it can prove are such leftovers: the name has that form, the file holds a complete lock
record that matches it (a private file's or a probe's record has the token its name carries; a break
file's is its breaker's, ``<token>-<depth>``
with the depth its name's breaks give) and that record's process is dead (judged as a lock holder
is, above). An empty or unreadable one, one of a live process and a break of the current lock are
left; a sweep that cannot read, judge or remove a file leaves it and never stops the run.

**What it relies on (shared file systems).** Atomic exclusive creation: ``link(2)`` is atomic on
every NFS version and on Lustre, GPFS, CephFS and local file systems; ``O_EXCL`` is atomic on NFSv3
and later (not NFSv2). No ``flock``/``fcntl`` locks are used (they depend on mount options such as
NFS ``nolock`` or Lustre ``flock``). Staleness of a lock from another host relies on the heartbeat:
a holder suspended for longer than ``lock-stale-after`` (a paused VM, a stopped process) may be
taken over; the holder notices at its next heartbeat (its token is gone) and the run stops with an
error instead of writing on. On one host, PID liveness is exact.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import pathlib
import re
import secrets
import socket
import threading
import time

from tubeid.errors import SpecificationError
from tubeid.runner._terms import current as _terms

__all__ = ["StoreLock", "LOCK_NAME", "read_lock", "describe_holder", "holder_state", "LockLost", "lock_settings",
           "remove_leftovers", "refuse_if_held"]

LOCK_NAME = ".tubeid-lock"
_MAX_BREAK_DEPTH = 3


class LockLost(RuntimeError):
    """The store's lock was taken over by another runner while this one held it."""


def lock_settings() -> tuple[float, float]:
    """``(heartbeat, stale_after)`` in seconds, checked (:func:`tubeid.config.check`: each a duration > 0,
    refused naming the setting and its environment variable, and the heartbeat shorter than
    ``lock-stale-after``, else other hosts would take a live run's lock over)."""
    from tubeid import config  # dask's configuration: imported only where a lock is taken or judged

    values = config.check("runner.lock-heartbeat", "runner.lock-stale-after")
    return values["runner.lock-heartbeat"], values["runner.lock-stale-after"]


def _boot_id() -> str:
    try:
        return pathlib.Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        import psutil

        return f"boot-{psutil.boot_time():.0f}"


def _pid_namespace() -> int | None:
    try:
        return os.stat("/proc/self/ns/pid").st_ino
    except OSError:
        return None


def _process_start(pid: int) -> float | None:
    """Start time of process ``pid`` (seconds since the epoch, 0.01 s), None if there is no such process."""
    try:
        import psutil

        return round(psutil.Process(pid).create_time(), 2)
    except Exception:  # psutil.NoSuchProcess, AccessDenied, or psutil missing
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return None
        except PermissionError:
            pass
        return -1.0  # alive, start time unknown


def _me() -> dict:
    pid = os.getpid()
    return {"host": socket.gethostname(), "pid": pid, "started": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "token": secrets.token_hex(12), "boot": _boot_id(), "pid_ns": _pid_namespace(),
            "pid_start": _process_start(pid)}


def read_lock(path: pathlib.Path) -> dict | None:
    """The record of the lock file at ``path``: a dict, ``None`` if there is none, ``{}`` if unreadable
    (not UTF-8 JSON, or without a string ``token`` and an integer ``pid``)."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError:
        return {}
    try:
        rec = json.loads(data.decode("utf-8"))
    except ValueError:  # not UTF-8 (UnicodeDecodeError is a ValueError) or not JSON: damaged
        return {}
    ok = (isinstance(rec, dict) and isinstance(rec.get("token"), str)
          and isinstance(rec.get("pid"), int) and not isinstance(rec.get("pid"), bool))
    return rec if ok else {}  # a record without its token and PID is damaged: judged as unreadable


def _server_age(path: pathlib.Path, me: dict) -> float | None:
    """Seconds since ``path`` was last modified, on the file server's clock; None if it is gone. The probe
    file beside it holds ``me``'s record, so that one left by a process killed before removing it is
    provably a leftover (:func:`remove_leftovers`)."""
    probe = path.with_name(f"{path.name}.probe-{me['token']}-{secrets.token_hex(4)}")
    try:
        fd = os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        try:
            os.write(fd, json.dumps(me, sort_keys=True).encode())
        finally:
            os.close(fd)
        now = os.stat(probe).st_mtime
    except OSError:
        now = time.time()
    finally:
        with contextlib.suppress(OSError):
            os.unlink(probe)
    try:
        return now - os.stat(path).st_mtime
    except FileNotFoundError:
        return None


def holder_state(rec: dict, path: pathlib.Path) -> tuple[str, str]:
    """``("alive" | "dead", why)`` for the holder recorded in ``rec`` (lock file ``path``)."""
    me = _me()
    # Same host: same name, PID namespace and boot. A different boot id under the same name is a reboot,
    # or another machine with the same host name (cloned VMs; every host's initial PID namespace has the
    # same inode): its PIDs mean nothing here, so its lock is judged by its heartbeat like any other host's.
    same_host = rec.get("host") == me["host"] and rec.get("pid_ns") == me["pid_ns"] and rec.get("boot") == me["boot"]
    if same_host:
        start, recorded = _process_start(int(rec.get("pid", -1))), rec.get("pid_start")
        if not isinstance(recorded, (int, float)) or isinstance(recorded, bool):
            recorded = None  # not recorded (or damaged): the PID alone decides
        if start is None:
            return "dead", f"process {rec.get('pid')} no longer exists"
        if recorded not in (None, -1.0) and start != -1.0 and abs(start - recorded) > 0.05:
            return "dead", f"process {rec.get('pid')} exited (its PID now belongs to another process)"
        return "alive", f"process {rec.get('pid')} is running on this host"
    age = _server_age(path, me)
    from tubeid import config  # dask's configuration: imported only where a lock is judged

    stale_after = config.value("runner.lock-stale-after")
    if age is None:
        return "dead", "the lock was just released"
    rebooted = rec.get("host") == me["host"] and rec.get("boot") != me["boot"]
    if age > stale_after:
        return "dead", (f"no heartbeat for {age:.0f} s (> tubeid.runner.lock-stale-after = {stale_after:g} s)"
                        + ("; the host has rebooted since, or it is another host of the same name" if rebooted else ""))
    return "alive", f"its last heartbeat was {max(age, 0):.0f} s ago (stale after {stale_after:g} s)"


def describe_holder(rec: dict) -> str:
    return f"host {rec.get('host')}, pid {rec.get('pid')}, started {rec.get('started')}"


def _create_exclusive(path: pathlib.Path, rec: dict) -> bool:
    """Create ``path`` holding ``rec`` atomically; False if it exists."""
    data = json.dumps(rec, sort_keys=True).encode()
    tmp = path.with_name(f"{path.name}.tmp-{rec['token']}")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    try:
        os.link(tmp, path)
        return True
    except FileExistsError:
        return False
    except OSError:
        # NFS may report an error for a link that succeeded (a lost reply): the link count tells
        with contextlib.suppress(OSError):
            if os.stat(tmp).st_nlink == 2:
                return True
        try:  # no hard links on this file system: exclusive create
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            return False
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        return True
    finally:
        with contextlib.suppress(OSError):
            os.unlink(tmp)


def _break(path: pathlib.Path, rec: dict, me: dict, depth: int = 0) -> None:
    """Remove the dead lock instance ``rec`` at ``path`` unless another breaker holds its break file."""
    brk = path.with_name(f"{path.name}.break-{rec['token']}")
    if not _create_exclusive(brk, dict(me, token=f"{me['token']}-{depth}")):
        other = read_lock(brk)
        if other and depth < _MAX_BREAK_DEPTH and holder_state(other, brk)[0] == "dead":
            _break(brk, other, me, depth + 1)  # its breaker died mid-way: break the break file
        return
    try:
        cur = read_lock(path)
        if cur and cur.get("token") == rec["token"]:  # still the dead instance: only we may remove it
            os.unlink(path)
    finally:
        with contextlib.suppress(OSError):
            os.unlink(brk)


_TOKEN = r"[0-9a-f]{24}(?:-\d+)?"  # a record's token (a breaker's: its own token and depth)
#: a private file of an exclusive create (of the lock or of a break file): its token is the record's
_LEFTOVER_TMP = re.compile(re.escape(LOCK_NAME) + rf"(?:\.break-{_TOKEN})*\.tmp-({_TOKEN})")
#: a break file (of the lock instance T, or of another break file)
_LEFTOVER_BREAK = re.compile(re.escape(LOCK_NAME) + rf"\.break-({_TOKEN})(?:\.break-{_TOKEN})*")
#: the probe file of a clock reading beside the lock or a break file (:func:`_server_age`): its record's token
_LEFTOVER_PROBE = re.compile(re.escape(LOCK_NAME) + rf"(?:\.break-{_TOKEN})*\.probe-({_TOKEN})-[0-9a-f]{{8}}")


def _is_leftover(entry: os.DirEntry, current_token: str) -> bool:
    """Whether the directory entry is provably a leftover (see the module docstring); False when
    anything about it cannot be read or judged."""
    name = entry.name
    tmp = _LEFTOVER_TMP.fullmatch(name) or _LEFTOVER_PROBE.fullmatch(name)  # a private file: its record's token
    brk = _LEFTOVER_BREAK.fullmatch(name)
    if not (tmp or brk) or not entry.is_file(follow_symlinks=False):
        return False
    if brk and brk.group(1) == current_token:  # someone is breaking this very lock (at any depth): not a leftover
        return False
    path = pathlib.Path(entry.path)
    rec = read_lock(path)
    if not rec or rec.get("token") == current_token:
        return False
    token = str(rec.get("token"))
    if tmp and token != tmp.group(1):
        return False
    # a break file's record is its breaker's: token "<24 hex>-<depth>", depth = its number of breaks - 1
    if brk and token != f"{token[:24]}-{name.count('.break-') - 1}":
        return False
    return holder_state(rec, path)[0] == "dead"


def remove_leftovers(store: pathlib.Path, current_token: str) -> list[str]:
    """Remove what runners killed while taking or breaking the lock of ``store`` left (see the module
    docstring), by the holder of the lock with token ``current_token``; returns the names removed.
    Never raises: an entry that cannot be read, judged or removed is left in place."""
    removed = []
    try:
        entries = list(os.scandir(store))
    except OSError:
        return removed
    for entry in entries:
        try:
            if _is_leftover(entry, current_token):
                os.unlink(entry.path)
                removed.append(entry.name)
        except (OSError, ValueError, TypeError, RecursionError):  # unreadable, a damaged record, not ours to remove
            continue
    return sorted(removed)


def _unreadable(path: pathlib.Path) -> str:
    return f"has an unreadable lock file {path}: if no tubeid run is using this store, remove it"


def _in_use(store: pathlib.Path, rec: dict, why: str, advice: str | None, terms=None) -> str:
    advice = advice or f"wait for it to finish (`tubeid status {store}` shows its progress) or {(terms or _terms()).elsewhere}"
    return f"is in use by another tubeid run ({describe_holder(rec)}; {why}): {advice}"


def refuse_if_held(store, *, field: str | None = None, advice: str | None = None) -> None:
    """Refuse (``SpecificationError`` naming ``field``), without taking it, a store whose lock a live run
    holds or whose lock file stays unreadable, as :meth:`StoreLock.acquire` would; a free or stale lock
    passes (the run that takes it breaks a stale one). ``field`` and ``advice`` default to the runner's
    terms in force (:mod:`tubeid.runner._terms`)."""
    store = pathlib.Path(store)
    field = _terms().store if field is None else field
    path = store / LOCK_NAME
    for _ in range(11):
        rec = read_lock(path)
        if rec is None:
            return
        if rec:
            break
        time.sleep(0.05)  # being written by an O_EXCL creator, or damaged
    else:
        raise SpecificationError(field, str(store), _unreadable(path))
    state, why = holder_state(rec, path)
    if state == "alive":
        raise SpecificationError(field, str(store), _in_use(store, rec, why, advice))


class StoreLock:
    """The lock of one store directory (see the module docstring). Use as a context manager.

    Parameters
    ----------
    store : path-like
        The store directory (created if missing; the lock file lives inside it).
    log : callable, optional
        ``log(message)`` for the take-over of a stale lock.
    field, advice : str, optional
        How a refusal names the directory and what it tells the user to do when another run holds it
        (default: wait, ``tubeid status``, or another store, in the runner's terms in force when the
        lock is made, :mod:`tubeid.runner._terms`: ``"store"`` and ``--store`` for ``tubeid run``).
    """

    def __init__(self, store, log=None, *, field: str | None = None, advice: str | None = None):
        self.store = pathlib.Path(store)
        self.terms = _terms()
        self.field = self.terms.store if field is None else field
        self.advice = advice
        self.path = self.store / LOCK_NAME
        self.log = log or (lambda msg: None)
        self.record: dict | None = None
        self.created_store = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.lost: dict | None = None
        self._period = 10.0  # the heartbeat, set (checked) by acquire

    def acquire(self) -> "StoreLock":
        """Take the lock or raise ``SpecificationError`` naming its holder (or a bad lock setting, before
        anything is created)."""
        self._period, _ = lock_settings()
        if not self.store.exists():
            try:
                self.store.mkdir(parents=True)
                self.created_store = True
            except FileExistsError:
                pass
        me = _me()
        unreadable = 0
        for _ in range(50):
            if _create_exclusive(self.path, me):
                self.record = me
                self._start_heartbeat()
                left = remove_leftovers(self.store, me["token"])  # never raises
                if left:
                    self.log(f"tubeid: removed {len(left)} file(s) that runners killed while taking this store's "
                             f"lock left: {', '.join(left)}")
                return self
            rec = read_lock(self.path)
            if rec is None:
                continue  # released meanwhile: try again
            if not rec:  # being written by an O_EXCL creator, or damaged
                unreadable += 1
                if unreadable > 10:
                    raise SpecificationError(self.field, str(self.store), _unreadable(self.path))
                time.sleep(0.05)
                continue
            state, why = holder_state(rec, self.path)
            if state == "alive":
                raise SpecificationError(self.field, str(self.store), _in_use(self.store, rec, why, self.advice, self.terms))
            self.log(f"tubeid: taking over the stale lock of {describe_holder(rec)} ({why})")
            _break(self.path, rec, me)
            time.sleep(0.01)
        raise SpecificationError(self.field, str(self.store), "could not take its lock (too many concurrent runners)")

    def _start_heartbeat(self) -> None:
        self._thread = threading.Thread(target=self._beat, args=(self._period,), name="tubeid-lock-heartbeat", daemon=True)
        self._thread.start()

    def _beat(self, period: float) -> None:
        while not self._stop.wait(period):
            rec = read_lock(self.path)
            if not rec or rec.get("token") != self.record["token"]:
                self.lost = rec or {"host": "?", "pid": "?", "started": "?"}
                return
            with contextlib.suppress(OSError):
                os.utime(self.path)

    def check(self) -> None:
        """Raise ``LockLost`` if another runner took the lock over (seen at the last heartbeat)."""
        if self.lost is not None:
            raise LockLost(f"{self.store}: the lock was taken over by another runner ({describe_holder(self.lost)}) "
                           "while this run held it (no heartbeat for too long?): stopping")

    def release(self) -> None:
        """Stop the heartbeat and remove the lock file if it is still ours."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if self.record is not None:
            rec = read_lock(self.path)
            if rec and rec.get("token") == self.record["token"]:
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(self.path)
            self.record = None

    def __enter__(self) -> "StoreLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()
