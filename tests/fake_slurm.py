"""A fake SLURM for tests: ``sbatch`` and ``scancel`` that run batch scripts as local processes.

``install(bin_dir, state_dir)`` writes ``sbatch`` and ``scancel`` executables into ``bin_dir``
(put it first on ``PATH``). ``sbatch SCRIPT`` starts a detached monitor that runs ``bash SCRIPT``
in its own process group and, like SLURM, kills the whole group when the script's ``#SBATCH -t``
walltime is reached (SIGTERM, then SIGKILL 2 s later); it prints ``Submitted batch job ID``.
``scancel ID`` sends SIGTERM to that group. Every event is a line of ``state_dir/events.log``:
``submit ID``, ``start ID``, ``end ID exit RC``, ``end ID walltime``, ``cancel ID`` (``events``
reads them back; each line of the file starts with its Unix time). Only loopback processes are started; nothing is contacted.
"""

from __future__ import annotations

import fcntl
import os
import pathlib
import re
import signal
import subprocess
import sys
import time

__all__ = ["install", "events"]

_STATE_ENV = "FAKE_SLURM_STATE"


def install(bin_dir: pathlib.Path, state_dir: pathlib.Path) -> None:
    """Write ``sbatch`` and ``scancel`` into ``bin_dir``, keeping their state in ``state_dir``."""
    bin_dir.mkdir(parents=True, exist_ok=True)
    state_dir.mkdir(parents=True, exist_ok=True)
    for command in ("sbatch", "scancel"):
        exe = bin_dir / command
        exe.write_text(f'#!/bin/sh\n{_STATE_ENV}="{state_dir}" exec "{sys.executable}" "{__file__}" {command} "$@"\n')
        exe.chmod(0o755)


def events(state_dir: pathlib.Path) -> list[list[str]]:
    """The logged events, each as its words (``["end", "3", "walltime"]``), without their time stamp."""
    log = state_dir / "events.log"
    return [line.split()[1:] for line in log.read_text().splitlines()] if log.exists() else []


def _log(state: pathlib.Path, *words) -> None:
    with open(state / "events.log", "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        fh.write(f"{time.time():.3f} " + " ".join(str(w) for w in words) + "\n")


def _next_id(state: pathlib.Path) -> int:
    with open(state / "counter", "a+") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        fh.seek(0)
        n = int(fh.read() or 100) + 1
        fh.seek(0)
        fh.truncate()
        fh.write(str(n))
    return n


def _walltime(script: str) -> float:
    m = re.search(r"^#SBATCH\s+(?:-t|--time)[= ]\s*(\d+):(\d+):(\d+)\s*$", script, re.M)
    if not m:
        raise SystemExit("fake sbatch: the script has no '#SBATCH -t HH:MM:SS' line")
    h, mi, s = (int(g) for g in m.groups())
    return float(h * 3600 + mi * 60 + s)


def _sbatch(state: pathlib.Path, script_path: str) -> None:
    walltime = _walltime(pathlib.Path(script_path).read_text())
    job = _next_id(state)
    copy = state / f"job-{job}.sh"  # SLURM runs a copy: dask-jobqueue deletes its file after submitting
    copy.write_text(pathlib.Path(script_path).read_text())
    _log(state, "submit", job)
    with open(state / f"job-{job}.out", "w") as out:
        subprocess.Popen([sys.executable, __file__, "_monitor", str(job), str(copy), str(walltime)],
                         stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
                         env={**os.environ, _STATE_ENV: str(state)})
    print(f"Submitted batch job {job}")


def _monitor(state: pathlib.Path, job: str, script: str, walltime: float) -> None:
    proc = subprocess.Popen(["bash", script], stdin=subprocess.DEVNULL, start_new_session=True)
    (state / f"job-{job}.pgid").write_text(str(proc.pid))
    _log(state, "start", job)
    try:
        rc = proc.wait(timeout=walltime)
    except subprocess.TimeoutExpired:
        _log(state, "end", job, "walltime")
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        return
    _log(state, "end", job, "exit", rc)


def _scancel(state: pathlib.Path, job: str) -> None:
    pgid_file = state / f"job-{job}.pgid"
    for _ in range(50):  # the monitor writes it just after sbatch returns
        if pgid_file.exists():
            break
        time.sleep(0.1)
    _log(state, "cancel", job)
    try:
        os.killpg(int(pgid_file.read_text()), signal.SIGTERM)
    except (FileNotFoundError, ProcessLookupError, ValueError):
        pass  # already over, as scancel of a finished job


if __name__ == "__main__":
    state_dir = pathlib.Path(os.environ[_STATE_ENV])
    command, rest = sys.argv[1], sys.argv[2:]
    if command == "sbatch":
        _sbatch(state_dir, rest[-1])
    elif command == "scancel":
        for job_id in rest:
            _scancel(state_dir, job_id)
    elif command == "_monitor":
        _monitor(state_dir, rest[0], rest[1], float(rest[2]))
    else:
        raise SystemExit(f"fake slurm: unknown command {command}")
