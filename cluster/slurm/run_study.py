"""Run a tubeid study on a SLURM cluster with dask-jobqueue (``pip install "tubeid[slurm]"``).

The dask scheduler runs in this process (on a login node, or better inside a small SLURM job: see
tubeid-run.sbatch); workers are SLURM jobs described by jobqueue.yaml. The store must be on a file
system that this process and every compute node see at the same path (e.g. /scratch or /work).

    python cluster/slurm/run_study.py studies/example_sgplus.py --store /scratch/$USER/sg.zarr --jobs 4
    python cluster/slurm/run_study.py STUDY.py --print-job-script   # check the generated batch script

Runs longer than a job's walltime: ``--jobs`` worker jobs are kept running for the whole study
(``cluster.adapt(minimum_jobs=N, maximum_jobs=N)``). Each worker retires by itself after its
``--lifetime`` (jobqueue.yaml's ``worker-extra-args``, staggered by ``--lifetime-stagger`` so that
the jobs do not all end together), before SLURM's walltime kills it: its running block is
rescheduled, and the adaptive loop submits a new job in its place. Lifetime + stagger must be
below the walltime (checked here). Rerunning the same command resumes (finished blocks are kept).
"""

from __future__ import annotations

import argparse
import pathlib
import re
import sys

import dask.config
import yaml

CONFIG = pathlib.Path(__file__).with_name("jobqueue.yaml")


def slurm_seconds(walltime: str) -> float:
    """Seconds of a SLURM time limit: ``MM``, ``MM:SS``, ``HH:MM:SS``, ``D-HH``, ``D-HH:MM``, ``D-HH:MM:SS``.

    Parameters
    ----------
    walltime : str
        The ``--time`` value as SLURM reads it.

    Returns
    -------
    float
        The limit in seconds.
    """
    from tubeid.errors import SpecificationError

    m = re.fullmatch(r"(?:(\d+)-)?(\d+)(?::(\d+))?(?::(\d+))?", str(walltime).strip())
    if not m:
        raise SpecificationError("jobqueue.slurm.walltime", walltime,
                                 "must be a SLURM time: MM, MM:SS, HH:MM:SS, D-HH, D-HH:MM or D-HH:MM:SS")
    days, a, b, c = m.groups()
    if days is not None:  # D-HH[:MM[:SS]]
        h, mi, s = int(a), int(b or 0), int(c or 0)
    elif c is not None:   # HH:MM:SS
        h, mi, s = int(a), int(b), int(c)
    else:                 # MM[:SS]
        h, mi, s = 0, int(a), int(b or 0)
    return float(((int(days or 0) * 24 + h) * 60 + mi) * 60 + s)


def worker_lifetime(settings: dict) -> tuple[float, float, float]:
    """The workers' lifetime, its stagger and the job walltime, in seconds, checked against each other.

    Parameters
    ----------
    settings : dict
        The ``jobqueue.slurm`` configuration: ``walltime`` and ``worker-extra-args`` with
        ``--lifetime`` and ``--lifetime-stagger`` (dask durations, e.g. ``"110m"``).

    Returns
    -------
    lifetime, stagger, walltime : float
        Seconds. A worker retires after ``lifetime ± stagger``.

    Raises
    ------
    SpecificationError
        Without ``--lifetime`` (every job would run into its walltime and never be replaced), or
        when ``lifetime + stagger`` is not below the walltime (SLURM would kill the worker first).
    """
    from dask.utils import parse_timedelta

    from tubeid.errors import SpecificationError

    args = [str(a) for a in settings.get("worker-extra-args") or []]
    walltime = slurm_seconds(settings.get("walltime"))

    def option(name: str, default: str | None) -> str | None:
        for i, a in enumerate(args):
            if a == name and i + 1 < len(args):
                return args[i + 1]
            if a.startswith(name + "="):
                return a.split("=", 1)[1]
        return default

    lifetime, stagger = option("--lifetime", None), option("--lifetime-stagger", "0s")
    field = "jobqueue.slurm.worker-extra-args"
    if lifetime is None:
        raise SpecificationError(field, args, "needs --lifetime below the walltime (and --lifetime-stagger): "
                                 "without it every job runs into its walltime and is never replaced")
    try:
        life_s, stagger_s = float(parse_timedelta(lifetime)), float(parse_timedelta(stagger))
    except (ValueError, KeyError, TypeError) as exc:
        raise SpecificationError(field, args, f"--lifetime/--lifetime-stagger must be durations ({exc})") from exc
    if not (life_s > stagger_s >= 0):
        raise SpecificationError(field, args, "needs --lifetime > --lifetime-stagger >= 0")
    if life_s + stagger_s >= walltime:
        raise SpecificationError(field, args, f"--lifetime + --lifetime-stagger = {life_s + stagger_s:g} s must be below "
                                 f"the walltime ({settings.get('walltime')} = {walltime:g} s), leaving time to start "
                                 "and to hand over")
    return life_s, stagger_s, walltime


def read_config(path: str) -> dict:
    """The dask-jobqueue settings of a YAML file (a mapping; an empty file is no settings).

    Raises
    ------
    SpecificationError
        A file that cannot be read, is not YAML, or does not hold a mapping.
    """
    from tubeid.errors import SpecificationError

    try:
        with open(path) as fh:
            settings = yaml.safe_load(fh)
    except OSError as exc:
        raise SpecificationError("--config", path, f"cannot be read ({exc.strerror or exc})") from None
    except yaml.YAMLError as exc:
        where = getattr(exc, "problem_mark", None)
        raise SpecificationError("--config", path, f"is not YAML ({getattr(exc, 'problem', None) or exc}"
                                 + (f", line {where.line + 1}" if where else "") + ")") from None
    if settings is None:
        return {}
    if not isinstance(settings, dict):
        raise SpecificationError("--config", path, f"must hold a YAML mapping of settings (jobqueue: slurm: ...), "
                                 f"not a {type(settings).__name__}")
    return settings


def main(argv: list[str] | None = None) -> int:
    """Run a study on SLURM worker jobs that are replaced as their lifetime ends.

    Parameters
    ----------
    argv : list of str, optional
        Command-line arguments (default: ``sys.argv[1:]``); see ``--help``.

    Returns
    -------
    int
        Exit status: 0 done, 2 refused (bad settings or study, dask-jobqueue missing), 130 interrupted.
    """
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("study", help="study or pipeline file (e.g. studies/example_sgplus.py)")
    p.add_argument("--store", help="Zarr store on a shared file system")
    p.add_argument("--jobs", type=int, default=2, help="SLURM worker jobs kept running (each replaced when it ends)")
    p.add_argument("--config", default=str(CONFIG), help="dask-jobqueue settings (YAML)")
    p.add_argument("--print-job-script", action="store_true", help="print the worker batch script and exit")
    from tubeid.runner.cli import _setting

    p.add_argument("--set", dest="overrides", action="append", type=_setting, default=[], metavar="NAME=VALUE",
                   help="override a study (or pipeline) parameter, as `tubeid run --set`")
    args = p.parse_args(argv)

    from tubeid import _validation
    from tubeid._optional import require
    from tubeid.errors import MissingDependencyError, SpecificationError

    try:
        SLURMCluster = require("dask_jobqueue", "cluster/slurm/run_study.py").SLURMCluster
        jobs = _validation.integer("--jobs", args.jobs, minimum=1)
        dask.config.update(dask.config.config, read_config(args.config), priority="new")
        life, stagger, walltime = worker_lifetime(dask.config.get("jobqueue.slurm"))
        from tubeid.runner.execute import run
        from tubeid.runner.study import load_definition

        if not args.print_job_script:  # the study and its --set refused before any job is submitted
            load_definition(args.study, overrides=dict(args.overrides))

        with SLURMCluster() as cluster:
            if args.print_job_script:
                print(cluster.job_script())
                return 0
            cluster.adapt(minimum_jobs=jobs, maximum_jobs=jobs)
            print(f"tubeid: SLURM: {jobs} worker jobs kept running (walltime {walltime:g} s; each worker retires "
                  f"after {life:g} ± {stagger:g} s and its job is replaced); dashboard {cluster.dashboard_link}",
                  file=sys.stderr)
            run(args.study, args.store, scheduler=cluster.scheduler_address, overrides=dict(args.overrides))
    except (SpecificationError, MissingDependencyError) as exc:
        print(f"tubeid: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("\ntubeid: interrupted; finished blocks are kept: rerun the same command to resume", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
