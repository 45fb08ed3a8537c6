"""cluster/slurm/run_study.py: a study outlives its SLURM jobs' walltime.

The scheduler-side logic runs for real (dask-jobqueue's ``SLURMCluster``, ``adapt``, the workers'
``--lifetime``) against a fake ``sbatch``/``scancel`` on ``PATH`` (tests/fake_slurm.py) that runs
each batch script as a local process group and kills it at its walltime, as SLURM does.
"""

import importlib.util
import os
import pathlib
import subprocess
import sys

import pytest
import yaml

import fake_slurm  # tests/fake_slurm.py (pytest puts tests/ on sys.path)
from tubeid.errors import SpecificationError
from tubeid.runner.execute import run
from tubeid.runner.store import store_status
from tubeid.runner.testing import store_digest

pytest.importorskip("dask_jobqueue")

REPO = pathlib.Path(__file__).resolve().parents[1]
SCRIPT = REPO / "cluster" / "slurm" / "run_study.py"


def _script_module():
    spec = importlib.util.spec_from_file_location("run_study", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("text, seconds", [
    ("45", 45 * 60), ("45:30", 45 * 60 + 30), ("02:00:00", 7200), ("1-0", 86400), ("1-02:03", 93780),
    ("2-00:00:10", 172810),
])
def test_slurm_time_formats(text, seconds):
    assert _script_module().slurm_seconds(text) == seconds


@pytest.mark.parametrize("extra, walltime, rule", [
    ([], "02:00:00", "needs --lifetime"),
    (["--lifetime", "118m", "--lifetime-stagger", "2m"], "02:00:00", "must be below the walltime"),
    (["--lifetime", "5m", "--lifetime-stagger", "5m"], "02:00:00", "--lifetime > --lifetime-stagger"),
    (["--lifetime", "soon"], "02:00:00", "must be durations"),
    (["--lifetime", "1h"], "2h", "must be a SLURM time"),
])
def test_lifetime_settings_that_cannot_outlive_the_walltime_are_refused(extra, walltime, rule):
    with pytest.raises(SpecificationError, match=rule):
        _script_module().worker_lifetime({"walltime": walltime, "worker-extra-args": extra})


def test_shipped_settings_retire_workers_before_the_walltime():
    settings = yaml.safe_load((REPO / "cluster/slurm/jobqueue.yaml").read_text())["jobqueue"]["slurm"]
    life, stagger, walltime = _script_module().worker_lifetime(settings)
    assert (life, stagger, walltime) == (6600.0, 300.0, 7200.0)


STUDY = """
import time
import numpy as np
from tubeid.runner.study import Output, Study

def task(block, rng):
    time.sleep(0.25 * len(block["r"]))   # no CPU: the test machine is shared
    return {"y": np.array([rng(r=r).standard_normal() for r in block["r"]])}

study = Study(name="slurm-walltime", seed=11, axes={"r": range(100)}, chunks={"r": 1}, task=task,
              outputs={"y": Output(units="1")})
"""


@pytest.mark.distributed
@pytest.mark.timeout(480)
def test_workers_past_their_lifetime_are_replaced_and_the_study_completes(tmp_path):
    """2 jobs of 1 worker, each retiring after 10 ± 1 s (walltime 25 s); a block sleeps 0.25 s, so
    the first two workers can write at most 2 × 11 / 0.25 = 88 of the 100 blocks, whatever the
    machine's load: the study completes only if the ended jobs are resubmitted. The store must be
    byte-identical to an in-process run, and no job may reach its walltime. (A worker's start-up,
    seconds on a loaded machine, counts in its lifetime; with a lifetime barely above start-up
    plus one block the study would livelock, which is why production lifetimes are hours.)"""
    bin_dir, state = tmp_path / "bin", tmp_path / "slurm"
    fake_slurm.install(bin_dir, state)
    (tmp_path / "study.py").write_text(STUDY)
    shipped = yaml.safe_load((REPO / "cluster/slurm/jobqueue.yaml").read_text())
    slurm = shipped["jobqueue"]["slurm"]
    slurm.update({"cores": 1, "processes": 1, "memory": "1GB", "walltime": "00:00:25", "python": sys.executable,
                  "local-directory": str(tmp_path / "scratch"), "job-script-prologue": [], "death-timeout": 30,
                  "worker-extra-args": ["--lifetime", "10s", "--lifetime-stagger", "1s"],
                  "scheduler-options": {"host": "127.0.0.1", "dashboard_address": "127.0.0.1:0"}})
    shipped["distributed"] = {"deploy": {"lost-worker-timeout": "1s"}}
    config = tmp_path / "jobqueue.yaml"
    config.write_text(yaml.safe_dump(shipped))
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}", "TUBEID_RUNNER__PROGRESS": "false"}
    res = subprocess.run([sys.executable, str(SCRIPT), str(tmp_path / "study.py"), "--store", str(tmp_path / "s.zarr"),
                          "--jobs", "2", "--config", str(config)],
                         capture_output=True, text=True, env=env, cwd=tmp_path, timeout=400)
    log = fake_slurm.events(state)
    assert res.returncode == 0, res.stderr[-3000:] + f"\n{log}"
    assert "2 worker jobs kept running" in res.stderr

    st = store_status(tmp_path / "s.zarr")
    assert st["complete"] and st["done"] == 100
    run(tmp_path / "study.py", tmp_path / "local.zarr", workers=0, progress=False, quiet=True)
    assert store_digest(tmp_path / "s.zarr") == store_digest(tmp_path / "local.zarr")

    submitted = [e[1] for e in log if e[0] == "submit"]
    retired = [j for j in submitted if "Reason: worker-lifetime-reached" in (state / f"job-{j}.out").read_text()]
    assert len(submitted) >= 4, log                # the 2 first jobs and at least 2 replacements
    assert len(retired) >= 2, log                  # their workers retired at the end of their lifetime
    assert not [e for e in log if e[:1] == ["end"] and e[2:] == ["walltime"]], log  # none reached the walltime


def _refusal(tmp_path, *args):
    """run_study.py with a fake sbatch on PATH: (exit status, stderr, jobs submitted)."""
    bin_dir, state = tmp_path / "bin", tmp_path / "slurm"
    fake_slurm.install(bin_dir, state)
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}", "TUBEID_RUNNER__PROGRESS": "false"}
    res = subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], capture_output=True, text=True, env=env,
                         cwd=tmp_path, timeout=120)
    return res.returncode, res.stderr, [e for e in fake_slurm.events(state) if e[0] == "submit"]


@pytest.mark.parametrize("config, rule", [
    ("missing.yaml", "cannot be read (No such file or directory)"),
    ("README.md", "is not YAML (mapping values are not allowed here, line 1)"),
    ("list.yaml", "must hold a YAML mapping of settings (jobqueue: slurm: ...), not a list"),
])
def test_a_bad_config_file_is_one_line(tmp_path, config, rule):
    """`--config` missing, not YAML, or not a mapping: each ended in a traceback (FileNotFoundError, yaml's
    ScannerError, AttributeError); now one line naming the option, the file and the rule, exit status 2."""
    (tmp_path / "README.md").write_text("Run: it: like this\n")
    (tmp_path / "list.yaml").write_text("- jobqueue\n")
    status, err, submitted = _refusal(tmp_path, REPO / "studies" / "pi.py", "--config", tmp_path / config)
    assert status == 2 and err == f"tubeid: error: --config = {str(tmp_path / config)!r}: {rule}\n", err
    assert not submitted


@pytest.mark.parametrize("args, rule", [
    (["no-such-study.py"], "study = 'no-such-study.py': no such study file"),
    ([REPO / "studies" / "pi.py", "--set", "samples=0"], "parameters.samples = 0: must lie in [1, 10000000]"),
])
def test_a_bad_study_is_refused_before_the_cluster_starts(tmp_path, args, rule):
    """A missing study file used to be refused only after the SLURM cluster had started and printed "2 worker
    jobs kept running"; run_study.py had no --set at all. Both are now checked before any cluster or job."""
    config = tmp_path / "jobqueue.yaml"
    shipped = yaml.safe_load((REPO / "cluster/slurm/jobqueue.yaml").read_text())
    shipped["jobqueue"]["slurm"].update({"python": sys.executable, "scheduler-options": {"host": "127.0.0.1"}})
    config.write_text(yaml.safe_dump(shipped))
    status, err, submitted = _refusal(tmp_path, *args, "--store", tmp_path / "s.zarr", "--config", config)
    assert status == 2 and err == f"tubeid: error: {rule}\n", err
    assert not submitted and not (tmp_path / "s.zarr").exists()


def test_the_runner_job_script_names_its_arguments_when_they_are_missing(tmp_path):
    """`sbatch tubeid-run.sbatch` without STORE: bash's "$2: unbound variable" in the job's log; now the usage."""
    env = {**os.environ, "TUBEID_VENV": str(pathlib.Path(sys.executable).parents[1]), "SLURM_SUBMIT_DIR": str(REPO)}
    for args in ([], ["studies/pi.py"]):
        res = subprocess.run(["bash", str(REPO / "cluster/slurm/tubeid-run.sbatch"), *args], capture_output=True,
                             text=True, env=env, cwd=tmp_path, timeout=60)
        assert res.returncode != 0 and "usage: sbatch cluster/slurm/tubeid-run.sbatch STUDY.py STORE [JOBS]" in res.stderr
        assert "unbound variable" not in res.stderr.replace("usage", "")
