"""run() from a plain script: the embedded cluster's spawned workers re-import that script.

Real processes: the script runs in a fresh interpreter and starts a LocalCluster of 2 workers.
"""

import subprocess
import sys
import textwrap

import pytest

STUDY = textwrap.dedent("""
    from tubeid.runner.study import Output, Study, pointwise

    @pointwise
    def f(point, rng):
        return {'y': float(point['r']) + rng.standard_normal()}

    study = Study(name='tiny', seed=3, axes={'r': range(4)}, chunks={'r': 2}, task=f,
                  outputs={'y': Output(units='m')}, units={'r': '1'})
""")
CALL = 'tubeid.runner.run("tiny.py", "out.zarr", workers=2, progress=False, quiet=True)'


def _script(tmp_path, body):
    (tmp_path / "tiny.py").write_text(STUDY)
    (tmp_path / "drive.py").write_text("import tubeid.runner\n" + body + "\nprint('finished')\n")
    return subprocess.run([sys.executable, "drive.py"], cwd=tmp_path, capture_output=True, text=True, timeout=180)


@pytest.mark.distributed
def test_an_unguarded_script_is_refused_with_the_fix_and_leaves_no_store(tmp_path):
    res = _script(tmp_path, CALL)
    assert res.returncode != 0 and "finished" not in res.stdout
    assert 'put the call under `if __name__ == "__main__":`' in res.stderr
    assert "run() called while a worker process imports" in res.stderr  # the workers say why they stop
    assert "is in use by another tubeid run" not in res.stderr  # not the lock refusal of a re-run
    assert res.stderr.count("Traceback") <= 1, res.stderr  # one error, not one traceback per worker
    assert not (tmp_path / "out.zarr").exists()


@pytest.mark.distributed
def test_a_guarded_script_runs(tmp_path):
    res = _script(tmp_path, 'if __name__ == "__main__":\n    ' + CALL)
    assert res.returncode == 0, res.stderr
    assert "finished" in res.stdout and (tmp_path / "out.zarr" / "zarr.json").exists()
