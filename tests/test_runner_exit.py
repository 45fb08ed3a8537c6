"""The end of a run: what the embedded workers and the runner process do at exit."""

import subprocess
import sys

import pytest

STUDY = '''
import numpy as np
from tubeid.runner import Output, Study, pointwise


class _Log:  # a module-level writer in a reference cycle: only the garbage collector finalises it
    def __init__(self, path):
        self.me = self
        self.f = open(path, "a")


_log = _Log({path!r} + "." + str(__import__("os").getpid()))
_log.f.write("x" * 40)  # buffered: on disk only when the file object is finalised


@pointwise
def point(point, rng):
    return {{"v": rng.random()}}


study = Study(name="exits", seed=1, axes={{"realisation": range(4)}}, chunks={{"realisation": 1}}, task=point,
              outputs={{"v": Output(units="1")}})
'''


def _run_logging_study(tmp_path, workers: int) -> int:
    """`tubeid run` of STUDY (each process that loads it writes 40 buffered bytes to log.<pid>); its pid."""
    (tmp_path / "exits.py").write_text(STUDY.format(path=str(tmp_path / "log")))
    proc = subprocess.Popen([sys.executable, "-m", "tubeid", "run", str(tmp_path / "exits.py"), "--store",
                             str(tmp_path / "s.zarr"), "--workers", str(workers), "--no-progress"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    _, err = proc.communicate(timeout=110)
    assert proc.returncode == 0, err
    return proc.pid


@pytest.mark.distributed
@pytest.mark.timeout(180)
def test_what_a_study_leaves_open_in_a_worker_is_still_flushed_at_exit(tmp_path):
    """The embedded workers freeze their own long-lived objects out of the garbage collector for a
    quick exit: a study's objects must still be finalised there, even in a reference cycle (a
    buffered file of 40 bytes reaches the disk in every worker that loaded the study). (The runner
    process itself does not finalise such a cycle at exit after an embedded cluster, before and after
    the freeze: Python does not promise it; a file the study closes, or one not in a cycle, is written.)"""
    pid = _run_logging_study(tmp_path, workers=2)
    workers = [f for f in tmp_path.glob("log.*") if f.suffix != f".{pid}"]
    assert len(workers) >= 1 and (tmp_path / f"log.{pid}").exists(), sorted(tmp_path.glob("log.*"))
    assert [f.stat().st_size for f in workers] == [40] * len(workers), [(f.name, f.stat().st_size) for f in workers]


FROZEN = '''
import gc
import numpy as np
from tubeid.runner import Output, Study, pointwise


@pointwise
def point(point, rng):
    return {"frozen": float(gc.get_freeze_count())}


study = Study(name="frozen", seed=1, axes={"realisation": range(2)}, chunks={"realisation": 1}, task=point,
              outputs={"frozen": Output(units="1")})
'''

SCRIPT = '''
import sys
from tubeid.runner import run

if __name__ == "__main__":
    run(sys.argv[1], sys.argv[2], workers=2, quiet=True)
'''


@pytest.mark.distributed
@pytest.mark.timeout(180)
def test_the_embedded_workers_freeze_only_under_the_tubeid_command(tmp_path):
    """Under `tubeid run` the workers freeze what they hold at start (before any study code); under a
    user's script that calls run() (which every worker re-imports) they do not: that script's objects
    and the loaded study must stay collectable."""
    import xarray as xr

    (tmp_path / "frozen.py").write_text(FROZEN)
    (tmp_path / "script.py").write_text(SCRIPT)
    cli = subprocess.run([sys.executable, "-m", "tubeid", "run", str(tmp_path / "frozen.py"), "--store",
                          str(tmp_path / "cli.zarr"), "--workers", "2", "--no-progress"], capture_output=True, text=True,
                         timeout=170)
    assert cli.returncode == 0, cli.stderr
    script = subprocess.run([sys.executable, str(tmp_path / "script.py"), str(tmp_path / "frozen.py"),
                             str(tmp_path / "script.zarr")], capture_output=True, text=True, timeout=170)
    assert script.returncode == 0, script.stderr
    assert (xr.open_zarr(tmp_path / "cli.zarr").frozen.values > 10_000).all()
    assert (xr.open_zarr(tmp_path / "script.zarr").frozen.values == 0).all()


@pytest.mark.timeout(120)
def test_what_a_study_leaves_open_in_the_runner_is_still_flushed_at_exit(tmp_path):
    """The runner process finalises a study's objects at exit, a reference cycle included (run in the
    process, where nothing else holds the study's module). A quick exit by freezing the runner's own
    imports (``gc.freeze`` before the study is loaded, as the workers do) was tried and fails this:
    the frozen modules of tubeid's runner come to hold the study, and frozen objects are never
    collected."""
    pid = _run_logging_study(tmp_path, workers=0)
    assert (tmp_path / f"log.{pid}").stat().st_size == 40
