"""Hostile and careless use of the study runner, counted (the runner's half of the README's reliability table).

Run: ``python tests/reliability_runner.py [--json] [--no-network]`` (about two minutes on 2 cores).
Prints, per class of case, how many were tried and how each ended:

- ``refused``: a clear refusal (``tubeid: error: ...``, exit status 2, no traceback; from Python a
  ``SpecificationError``) with nothing of the store or beside it changed or lost;
- ``repaired``: a damaged store whose damage ``tubeid status --verify`` names (exit 1), ``tubeid show``
  survives without a traceback (and names a missing or undecodable chunk it reads), and a plain
  ``tubeid run`` repairs to a store byte-identical to an undamaged run;
- ``handled``: a race or a stale lock that ends right (exactly one runner, a complete store
  identical to an undisturbed run, one run in its provenance; a stale lock taken over);
- ``wrong``: damage not detected, a store that differs from an undamaged run, a lock kept or taken
  wrongly, or user data changed;
- ``traceback``: any other exception.

``data lost`` counts user files or user arrays changed or deleted, and finished blocks lost by a
refusal. Not collected by pytest (no ``test_`` prefix); the tests named in the README keep each class
from coming back. The hostile inputs of measured files and specifications are counted by
``tests/reliability_inputs.py``.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import errno
import io
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import zarr

from tubeid.cli import main as tubeid_main
from tubeid.errors import SpecificationError
from tubeid.runner import lock as lockmod
from tubeid.runner.execute import run
from tubeid.runner.lock import LOCK_NAME, StoreLock
from tubeid.runner.store import BOOKKEEPING, FLAG, MANIFEST_NAME, read_attrs
from tubeid.runner.testing import store_digest, write_study

SIZE = dict(realisations=8, chunk=2, work=2)  # 8 blocks of (1 delta, 2 realisations)
TUBEID = [sys.executable, "-m", "tubeid"]


def _cli(*args) -> tuple[int | str, str]:
    """The tubeid command in this process: (exit status or "traceback", everything it printed)."""
    buf = io.StringIO()
    try:
        with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
            rc = tubeid_main([str(a) for a in args])
    except SystemExit as exc:
        rc = exc.code
    except Exception as exc:  # noqa: BLE001 - counted
        return "traceback", f"{type(exc).__name__}: {exc}"
    return rc, buf.getvalue()


def _files(folder: Path) -> dict:
    """Digest of every file under ``folder`` (user data and chunks alike)."""
    return {str(f.relative_to(folder)): f.read_bytes() for f in sorted(folder.rglob("*")) if f.is_file()}


def _garbage(f: Path) -> None:
    f.write_bytes(b"\x28\xb5\x2f\xfd not zstd at all" + os.urandom(16))


def _swap(store: Path) -> None:
    """Blocks (0, 1) and (0, 2) exchanged whole: their data chunks and their flags."""
    for a, b in (("x/c/0/1/0", "x/c/0/2/0"), ("count/c/0/1", "count/c/0/2"),
                 (f"{BOOKKEEPING}/{FLAG}/c/0/1", f"{BOOKKEEPING}/{FLAG}/c/0/2")):
        pa, pb = store / a, store / b
        da, db = pa.read_bytes(), pb.read_bytes()
        pa.write_bytes(db)
        pb.write_bytes(da)


def _rewrite_values(store: Path) -> None:
    arr = zarr.open_group(str(store), mode="r+", use_consolidated=False)["x"]
    arr[1:2, 4:6] = 2.0 * arr[1:2, 4:6]


def _nan_values(store: Path) -> None:
    arr = zarr.open_group(str(store), mode="r+", use_consolidated=False)["x"]
    arr[0:1, 4:5] = np.nan  # half of block (0, 2): its chunk stays


DAMAGE = {
    "deleted data chunk": lambda s: (s / "x/c/0/3/0").unlink(),
    "deleted integer chunk (reads as 0)": lambda s: (s / "count/c/1/2").unlink(),
    "garbage data chunk": lambda s: _garbage(s / "count/c/1/1"),
    "emptied data chunk": lambda s: (s / "x/c/1/0/0").write_bytes(b""),
    "truncated data chunk": lambda s: (s / "x/c/0/0/0").write_bytes((s / "x/c/0/0/0").read_bytes()[:20]),
    "changed values (valid chunk)": _rewrite_values,
    "values overwritten with NaN (valid chunk)": _nan_values,
    "deleted array": lambda s: shutil.rmtree(s / "x"),
    "garbage array metadata": lambda s: (s / "count/zarr.json").write_text("{not json"),
    "garbage flag chunk": lambda s: _garbage(s / BOOKKEEPING / FLAG / "c/0/1"),
    "deleted flags": lambda s: shutil.rmtree(s / BOOKKEEPING / FLAG),
    "deleted bookkeeping group": lambda s: shutil.rmtree(s / BOOKKEEPING),
    "deleted coordinate chunk": lambda s: (s / "realisation/c/0").unlink(),
    "two blocks swapped, data and flags": _swap,
}


# damage that `tubeid show` must name (what it reads back is missing or undecodable), beyond not failing
SHOW_NAMES = {"deleted data chunk", "deleted integer chunk (reads as 0)", "garbage data chunk", "emptied data chunk",
              "truncated data chunk", "deleted array", "values overwritten with NaN (valid chunk)"}


def damaged_stores(tmp: Path, study: Path, ref: Path) -> dict:
    out = collections.defaultdict(collections.Counter)
    ref_digest = store_digest(ref)
    for name, damage in DAMAGE.items():
        store = tmp / "damaged.zarr"
        shutil.rmtree(store, ignore_errors=True)
        shutil.copytree(ref, store)
        damage(store)
        rc_v, text_v = _cli("status", store, "--verify")
        rc_s, text_s = _cli("show", store)
        try:
            run(study, store, workers=0, quiet=True)
            same = store_digest(store) == ref_digest
            rc_after, _ = _cli("status", store, "--verify")
        except Exception:  # noqa: BLE001
            out["damaged complete store"]["traceback"] += 1
            continue
        if "traceback" in (rc_v, rc_s):
            outcome = "traceback"
        elif rc_v == 1 and "DAMAGED" in text_v and rc_s == 0 and same and rc_after == 0 and \
                (name not in SHOW_NAMES or "DAMAGED" in text_s):
            outcome = "repaired"
        else:
            outcome = "wrong"
            print(f"  wrong: {name}: verify exit {rc_v}, show names it {'DAMAGED' in text_s}, repaired identical {same}",
                  file=sys.stderr)
        out["damaged complete store"][outcome] += 1
    # damage a runner cannot repair: refused clearly, nothing deleted
    unrepairable = {
        "root metadata deleted": lambda s: (s / "zarr.json").unlink(),
        "root metadata garbage": lambda s: (s / "zarr.json").write_text("{garbage"),
        "garbage lock file": lambda s: (s / LOCK_NAME).write_text("{garbage"),
        "empty lock file": lambda s: (s / LOCK_NAME).write_text(""),
    }
    for name, damage in unrepairable.items():
        store = tmp / "damaged.zarr"
        shutil.rmtree(store, ignore_errors=True)
        shutil.copytree(ref, store)
        damage(store)
        before = _files(store)
        rc, text = _cli("run", study, "--store", store, "--workers", "0", "--no-progress")
        lost = sum(1 for k, v in before.items() if _files(store).get(k) != v)
        out["store tubeid cannot repair (root metadata, lock)"]["refused" if rc == 2 and "tubeid: error:" in text
                                                                 else ("traceback" if rc == "traceback" else "wrong")] += 1
        out["store tubeid cannot repair (root metadata, lock)"]["data lost"] += lost
    return out


VALUES = [("[1.0, float('nan')]", "float64"), ("[float('inf'), 1.0]", "float32"), ("[1e39, 0.0]", "float32"),
          ("[127, 128]", "int8"), ("[-1, 0]", "uint16"), ("[1.5, 2.0]", "int32"), ("[float('nan'), 1.0]", "int64"),
          ("[2, 0]", "bool"), ("[2.0**63, 0.0]", "int64"), ("[2.0**64, 1.0]", "uint64")]
VALUES_STUDY = """
import numpy as np
from tubeid.runner import Output, Study
def task(block, rng):
    return {"y": np.asarray(VALUES) if 4 in block["r"] else np.zeros(len(block["r"]))}
study = Study(name="v", seed=1, axes={"r": range(6)}, chunks={"r": 2}, task=task, outputs={"y": Output(dtype="DTYPE")})
"""


def output_values(tmp: Path) -> dict:
    """A block returning a value its output cannot hold: refused naming it, that block not marked done."""
    from tubeid.runner.store import read_flags

    out = collections.Counter()
    for k, (values, dtype) in enumerate(VALUES):
        src = tmp / f"values{k}.py"
        src.write_text(VALUES_STUDY.replace("VALUES", values).replace("DTYPE", dtype))
        store = tmp / f"values{k}.zarr"
        rc, text = _cli("run", src, "--store", store, "--workers", "0", "--no-progress")
        refused = rc == 2 and "tubeid: error: outputs.y" in text and "block (2,)" in text
        out["refused" if refused and not (read_flags(store)[0] != 0)[2] else
            ("traceback" if rc == "traceback" else "wrong")] += 1
    return out


def parameters(tmp: Path, study: Path) -> dict:
    out = collections.Counter()
    for setting in ("work=2.5", 'work="3"', "work=abc", "work=1e3", "work=True", "work=", "work=-5", "work=10000000",
                    "label=z", "label=1", "nosuch=1"):
        store = tmp / "params.zarr"
        rc, text = _cli("run", study, "--store", store, "--workers", "0", "--no-progress", "--set", setting)
        ok = rc == 2 and "tubeid: error: parameters." in text and not store.exists()
        out["refused" if ok else ("traceback" if rc == "traceback" else "wrong")] += 1
        shutil.rmtree(store, ignore_errors=True)
    return out


def _subprocess_run(study: Path, store: Path, *extra, env: dict | None = None) -> subprocess.Popen:
    return subprocess.Popen([*TUBEID, "run", str(study), "--store", str(store), "--workers", "0", "--no-progress", *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def locks(tmp: Path, study: Path, ref: Path, trials: int) -> dict:
    out = collections.defaultdict(collections.Counter)
    ref_digest = store_digest(ref)
    for k in range(trials):  # two `tubeid run` started at once on the same new store
        store = tmp / f"race{k}.zarr"
        procs = [_subprocess_run(study, store) for _ in range(2)]
        res = [(p.wait(), p.stderr.read()) for p in procs]
        refused = [e for rc, e in res if rc == 2 and "is in use by another tubeid run" in e]
        ok = (sorted(rc for rc, _ in res) == [0, 2] and len(refused) == 1 and "Traceback" not in "".join(e for _, e in res)
              and store_digest(store) == ref_digest and len(read_attrs(store)["runs"]) == 1)
        out["two runs at once on a new store"]["handled" if ok else "wrong"] += 1
    # a runner killed (SIGKILL) after its first finished block leaves its lock and a partial store: the next run
    # takes the lock over and completes identically. The killed run's blocks are paced (0.5 s of sleep each, the
    # values unchanged): unpaced, its 4 blocks of ~10-40 ms could all finish between the poll and the kill.
    from tubeid.runner.store import read_flags

    slow = write_study(tmp, name="slow.py", realisations=8, chunk=2, work=2000)
    slow_ref = tmp / "slow-ref.zarr"
    run(slow, slow_ref, workers=0, quiet=True)
    for k in range(2):
        store = tmp / f"killed{k}.zarr"
        p = _subprocess_run(slow, store, env=dict(os.environ, TUBEID_TEST_BLOCK_SECONDS="0.5"))
        t0 = time.monotonic()
        while time.monotonic() - t0 < 120:
            with contextlib.suppress(Exception):
                if (read_flags(store)[0] != 0).sum() >= 1 + k:
                    break
            time.sleep(0.02)
        p.send_signal(signal.SIGKILL)
        p.wait()
        partial = (store / LOCK_NAME).exists() and not (read_flags(store)[0] != 0).all()
        rc, text = _cli("run", slow, "--store", store, "--workers", "0", "--no-progress")
        ok = partial and rc == 0 and "taking over the stale lock" in text and store_digest(store) == store_digest(slow_ref)
        out["runner killed mid-run (lock and partial store left)"]["handled" if ok else "wrong"] += 1

    def record(store: Path, **fields) -> None:
        rec = lockmod._me()
        rec.update(fields)
        store.mkdir(parents=True, exist_ok=True)
        (store / LOCK_NAME).write_text(json.dumps(rec))

    def dead_pid() -> int:
        p = subprocess.Popen([sys.executable, "-c", "pass"])
        p.wait()
        return p.pid

    old = time.time() - 300
    mine = lockmod._process_start(os.getpid())
    stale = {  # a lock left behind: (record, mtime or None) -> must be taken over
        "dead PID": (dict(pid=dead_pid()), None),
        "PID reused 1 s later": (dict(pid=os.getpid(), pid_start=mine - 1.0), None),
        "another host, no heartbeat for 300 s": (dict(host="other-host", pid=1), old),
        "this host name, another boot, no heartbeat": (dict(boot="another-boot", pid=os.getpid()), old),
    }
    live = {  # a live lock: must be kept (refused naming the holder)
        "this process": (dict(), None),
        "another host, fresh heartbeat": (dict(host="other-host", pid=1), None),
        "this host name, another boot, fresh heartbeat": (dict(boot="another-boot", pid=dead_pid()), None),
    }
    for cases, expect in ((stale, "taken over"), (live, "kept")):
        for name, (fields, mtime) in cases.items():
            store = tmp / "lock.zarr"
            shutil.rmtree(store, ignore_errors=True)
            record(store, **fields)
            if mtime:
                os.utime(store / LOCK_NAME, (mtime, mtime))
            try:
                with StoreLock(store):
                    got = "taken over"
            except SpecificationError as exc:
                got = "kept" if "in use by another tubeid run" in str(exc) else "refused"
            except Exception:  # noqa: BLE001
                got = "traceback"
            out[f"lock of a dead or live holder ({len(stale)} stale, {len(live)} live)"][
                "handled" if got == expect else ("traceback" if got == "traceback" else "wrong")] += 1
    return out


def overwrite(tmp: Path, study: Path, ref: Path) -> dict:
    out = collections.defaultdict(collections.Counter)
    store = tmp / "user.zarr"
    shutil.copytree(ref, store)
    user = {store / "notes.txt": b"mine", store / "x" / "notes.txt": b"mine too", store / "x/c/notes.txt": b"in a chunk dir",
            tmp / "beside.txt": b"beside the store"}
    for f, data in user.items():
        f.write_bytes(data)
    zarr.open_group(str(store / "mine"), mode="w").create_array("a", data=np.arange(5.0), chunks=(5,))
    mine = _files(store / "mine")
    commands = [("run",), ("status",), ("status", "--verify"), ("show",), ("run", "--overwrite"), ("run", "--new-store")]
    for cmd in commands:
        args = ["run", study, "--store", store, "--workers", "0", "--no-progress", *cmd[1:]] if cmd[0] == "run" \
            else [*cmd[:1], store, *cmd[1:]]
        rc, _ = _cli(*args)
        lost = sum(1 for f, data in user.items() if not f.is_file() or f.read_bytes() != data) + \
            (0 if _files(store / "mine") == mine else 1)
        out["user files in and beside a store (4 files + 1 array) x 6 commands"][
            "handled" if rc == 0 and not lost else ("traceback" if rc == "traceback" else "wrong")] += 1
        out["user files in and beside a store (4 files + 1 array) x 6 commands"]["data lost"] += lost
    # refusals: --overwrite on what tubeid cannot prove it wrote
    cases = {}
    d = tmp / "not-a-store"
    d.mkdir()
    (d / "thesis.tex").write_text("years of work")
    cases["a directory that is not a store"] = d
    s = tmp / "nomanifest.zarr"
    shutil.copytree(ref, s)
    (s / MANIFEST_NAME).unlink()
    cases["a store without manifest"] = s
    victim = tmp / "victim.zarr"
    zarr.open_group(str(victim), mode="w").create_array("data", data=np.arange(10.0), chunks=(5,))
    for k, entry in enumerate(["../victim.zarr/data", str(victim / "data"), "link"]):
        s = tmp / f"edited{k}.zarr"
        shutil.copytree(ref, s)
        if entry == "link":
            (s / "link").symlink_to(victim / "data", target_is_directory=True)
        m = json.loads((s / MANIFEST_NAME).read_text())
        m["nodes"][entry] = "array"
        (s / MANIFEST_NAME).write_text(json.dumps(m))
        cases[f"a manifest naming {'a symlink out of the store' if entry == 'link' else entry.replace(str(tmp), '<dir>')}"] = s
    before = {name: _files(p) for name, p in cases.items()}
    victim_before = _files(victim)
    for name, p in cases.items():
        rc, text = _cli("run", study, "--store", p, "--workers", "0", "--no-progress", "--overwrite")
        lost = int(_files(p) != before[name]) + int(_files(victim) != victim_before)
        key = "--overwrite of what tubeid cannot prove it wrote"
        out[key]["refused" if rc == 2 and "tubeid: error:" in text and not lost else
                 ("traceback" if rc == "traceback" else "wrong")] += 1
        out[key]["data lost"] += lost
    return out


def paths_and_names(tmp: Path, study: Path, ref: Path) -> dict:
    """Store paths zarr or the file system would misread, files named like tubeid's, an older layout and a
    full disk while a block is written (the second review of the store, 8873fd6)."""
    out = collections.Counter()
    other = tmp / "paths-prev.zarr"
    shutil.copytree(ref, other)
    (tmp / "paths-prev.zarr::v2").mkdir()
    (tmp / "paths-lnk").symlink_to(tmp / "paths-prev.zarr::v2")
    refusals = [((), ("run", study, "--store", f"{other}::v2.zarr")), ((), ("status", f"{other}::v2.zarr")),
                ((), ("run", study, "--store", f"file://{other}")), ((), ("show", f"file://{other}")),
                (tmp / "paths-prev.zarr::v2", ("run", study, "--store", "out.zarr")),
                ((), ("run", study, "--store", tmp / "paths-lnk" / "out.zarr")),
                ((), ("run", study, "--store", tmp / ("x" * 300))), ((), ("run", study, "--store", "/", "--new-store")),
                ((), ("run", study, "--store", tmp / "paths-new.zarr", "--set", "work=1e-400"))]
    for where, args in refusals:
        before = _files(tmp)
        cwd = os.getcwd()
        try:
            if where:
                os.chdir(where)
            rc, text = _cli(*args, *(["--workers", "0", "--no-progress"] if args[0] == "run" else []))
        finally:
            os.chdir(cwd)
        lost = int(_files(tmp) != before)
        out["refused" if rc == 2 and text.strip().splitlines()[-1].startswith("tubeid") and "Traceback" not in text
            and not lost else ("traceback" if rc == "traceback" else "wrong")] += 1
        out["data lost"] += lost
    # a user's files named like tubeid's own, through --overwrite: kept, the store made anew
    store = tmp / "paths-named.zarr"
    shutil.copytree(ref, store)
    mine = {store / ".tubeid-notes.txt": b"mine", store / ".tubeid-tmp-notes_v2": b"mine, named as a temporary"}
    for f, data in mine.items():
        f.write_bytes(data)
    rc, _ = _cli("run", study, "--store", store, "--workers", "0", "--no-progress", "--overwrite")
    lost = sum(1 for f, data in mine.items() if not f.is_file() or f.read_bytes() != data)
    for f in mine:
        f.unlink(missing_ok=True)
    out["handled" if rc == 0 and not lost and store_digest(store) == store_digest(ref) else
        ("traceback" if rc == "traceback" else "wrong")] += 1
    out["data lost"] += lost
    # an older layout (no record of what it wrote) holding a user's array, consolidated: never replaced
    old = tmp / "paths-layout1.zarr"
    shutil.copytree(ref, old)
    (old / MANIFEST_NAME).unlink()
    meta = json.loads((old / "zarr.json").read_text())
    meta["attributes"]["format"] = "tubeid-study-store/1"
    (old / "zarr.json").write_text(json.dumps(meta))
    zarr.open_group(str(old), mode="r+", use_consolidated=False).create_array("mine", data=np.arange(3.0), chunks=(3,))
    zarr.consolidate_metadata(str(old))
    before = _files(old)
    rc, text = _cli("run", study, "--store", old, "--workers", "0", "--no-progress", "--overwrite")
    lost = int(_files(old) != before)
    out["refused" if rc == 2 and "tubeid: error:" in text and not lost else
        ("traceback" if rc == "traceback" else "wrong")] += 1
    out["data lost"] += lost
    # a full disk while a block's chunk is written: one line naming the block, then the store resumes
    from zarr.storage import _local

    full = tmp / "paths-full.zarr"
    put = _local._put

    def no_space(path, value, *a, **kw):
        if Path(path).parent == full / "x" / "c" / "0" / "1":
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return put(path, value, *a, **kw)

    _local._put = no_space
    try:
        rc, text = _cli("run", study, "--store", full, "--workers", "0", "--no-progress")
    finally:
        _local._put = put
    said = rc == 2 and "block (0, 1)" in text and os.strerror(errno.ENOSPC) in text and "Traceback" not in text
    rc2, _ = _cli("run", study, "--store", full, "--workers", "0", "--no-progress")
    out["handled" if said and rc2 == 0 and store_digest(full) == store_digest(ref) else
        ("traceback" if "traceback" in (rc, rc2) else "wrong")] += 1
    return out


def output_manifest(tmp: Path) -> dict:
    """The output directory of a diagnosis (``OutputDir``) whose manifest was edited to list a file outside it,
    with that file's true checksum: removing tubeid's outputs must refuse, deleting nothing."""
    from tubeid._outputs import OutputDir, file_sha256

    out = collections.Counter()
    victim = tmp / "victim.txt"
    for entry in ("../victim.txt", str(victim), "sub/victim.txt"):
        victim.write_text("precious")
        (tmp / "od" / "sub").mkdir(parents=True, exist_ok=True)
        (tmp / "od" / "sub" / "victim.txt").write_text("precious")
        od = OutputDir(tmp / "od")
        od.write_text("report.md", "x")
        m = json.loads((tmp / "od" / MANIFEST_NAME).read_text())
        m["entries"][entry] = {"kind": "file", "sha256": file_sha256(victim), "size": 8, "written": "then"}
        (tmp / "od" / MANIFEST_NAME).write_text(json.dumps(m))
        try:
            od.remove()
            refused = False
        except SpecificationError:
            refused = True
        except Exception:  # noqa: BLE001
            out["traceback"] += 1
            continue
        lost = int(not victim.is_file()) + int(not (tmp / "od" / "sub" / "victim.txt").is_file())
        out["refused" if refused and not lost else "wrong"] += 1
        out["data lost"] += lost
        shutil.rmtree(tmp / "od")
    return out


def network(tmp: Path, study: Path) -> dict:
    """A TLS scheduler reached by tcp://, a bare address, tls:// without certificates; an unreachable one;
    foreign clients (plain TCP, TLS of other credentials) on the embedded cluster."""
    from distributed import Client
    from distributed.security import Security

    from tubeid.runner.execute import _client

    out = collections.Counter()
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    code = ("import asyncio\nfrom distributed import Scheduler\nfrom distributed.security import Security\n"
            "async def main():\n"
            f"    async with Scheduler(security=Security.temporary(), host='127.0.0.1', port={port}, protocol='tls',"
            " dashboard=False):\n        await asyncio.sleep(120)\nasyncio.run(main())\n")
    sched = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        time.sleep(4.0)
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            closed = s.getsockname()[1]
        env = dict(os.environ, TUBEID_RUNNER__CONNECT_TIMEOUT="5s")
        for address in (f"tcp://127.0.0.1:{port}", f"127.0.0.1:{port}", f"tls://127.0.0.1:{port}",
                        f"tcp://127.0.0.1:{closed}"):
            store = tmp / "net.zarr"
            p = subprocess.run([*TUBEID, "run", str(study), "--store", str(store), "--scheduler", address, "--no-progress"],
                               capture_output=True, text=True, env=env)
            ok = p.returncode == 2 and "tubeid: error: scheduler" in p.stderr and "Traceback" not in p.stderr \
                and not store.exists()
            out["refused" if ok else "wrong"] += 1
    finally:
        sched.kill()
        sched.wait()
    with _client(1, None, None, True) as (client, _):
        address = client.scheduler.address
        for addr, security in ((address.replace("tls://", "tcp://"), None), (address, Security.temporary())):
            try:
                Client(addr, security=security, timeout="3s", set_as_default=False).close()
                out["wrong"] += 1
            except Exception:  # noqa: BLE001 - refused by the cluster
                out["refused"] += 1
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--no-network", action="store_true", help="leave out the scheduler and embedded-cluster cases")
    ap.add_argument("--race-trials", type=int, default=7)
    args = ap.parse_args()
    rows: dict[str, collections.Counter] = {}
    with tempfile.TemporaryDirectory(prefix="tubeid-reliability-") as d:
        tmp = Path(d)
        study = write_study(tmp, **SIZE)
        ref = tmp / "ref.zarr"
        run(study, ref, workers=0, quiet=True)
        for name, counter in damaged_stores(tmp, study, ref).items():
            rows[name] = counter
        rows["NaN, inf, float32 overflow, out of range for int8/uint16/int64/uint64, non-whole or NaN into int, 2 into bool"] = \
            output_values(tmp)
        rows["--set of a wrong type, value out of bounds or choices, unknown name"] = parameters(tmp, study)
        for name, counter in locks(tmp, study, ref, args.race_trials).items():
            rows[name] = counter
        for name, counter in overwrite(tmp, study, ref).items():
            rows[name] = counter
        rows["a diagnosis's output directory: its manifest edited to list ../, an absolute path, a sub-path"] = \
            output_manifest(tmp)
        rows["store paths zarr would read as URLs ('::', file://, from the working directory or a link), a name too "
             "long, / with --new-store, --set 1e-400; a user's .tubeid-* files through --overwrite; an older layout "
             "holding a user's array; a full disk while a block is written"] = paths_and_names(tmp, study, ref)
        if not args.no_network:
            rows["tcp://, bare address, tls:// without certificates to a TLS scheduler; unreachable; foreign "
                 "clients on the embedded cluster"] = network(tmp, study)
    if args.json:
        print(json.dumps({k: dict(v) for k, v in rows.items()}, indent=1))
        return
    cols = ["refused", "repaired", "handled", "wrong", "traceback", "data lost"]
    print("| case | tried | " + " | ".join(cols) + " |")
    print("|---|---|" + "---|" * len(cols))
    for name, c in rows.items():
        tried = sum(c[k] for k in cols if k != "data lost")
        print(f"| {name} | {tried} | " + " | ".join(str(c[k]) for k in cols) + " |")


if __name__ == "__main__":
    main()
