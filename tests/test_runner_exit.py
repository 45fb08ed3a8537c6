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


@pytest.mark.distributed
@pytest.mark.timeout(180)
def test_what_a_study_leaves_open_in_a_worker_is_still_flushed_at_exit(tmp_path):
    """The embedded workers freeze their own long-lived objects out of the garbage collector for a
    quick exit: a study's objects must still be finalised there, even in a reference cycle (a
    buffered file of 40 bytes reaches the disk in every worker that loaded the study). (The runner
    process itself does not finalise such a cycle at exit after an embedded cluster, before and after
    the freeze: Python does not promise it; a file the study closes, or one not in a cycle, is written.)"""
    log = tmp_path / "log"
    (tmp_path / "exits.py").write_text(STUDY.format(path=str(log)))
    proc = subprocess.Popen([sys.executable, "-m", "tubeid", "run", str(tmp_path / "exits.py"), "--store",
                             str(tmp_path / "s.zarr"), "--workers", "2", "--no-progress"], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    _, err = proc.communicate(timeout=170)
    assert proc.returncode == 0, err
    workers = [f for f in tmp_path.glob("log.*") if f.suffix != f".{proc.pid}"]
    assert len(workers) >= 1 and (tmp_path / f"log.{proc.pid}").exists(), sorted(tmp_path.glob("log.*"))
    assert [f.stat().st_size for f in workers] == [40] * len(workers), [(f.name, f.stat().st_size) for f in workers]


@pytest.mark.distributed
def test_the_embedded_workers_freeze_what_they_hold_before_any_study_code():
    from tubeid.runner.execute import _client

    with _client(2, None, None, True) as (client, _):
        frozen = client.run(lambda: __import__("gc").get_freeze_count())
    assert len(frozen) == 2 and all(n > 10_000 for n in frozen.values()), frozen
