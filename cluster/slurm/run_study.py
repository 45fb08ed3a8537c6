"""Run a tubeid study on a SLURM cluster with dask-jobqueue (``pip install dask-jobqueue``).

The dask scheduler runs in this process (on a login node, or better inside a small SLURM job: see
tubeid-run.sbatch); workers are SLURM jobs described by jobqueue.yaml. The store must be on a file
system that this process and every compute node see at the same path (e.g. /scratch or /work).

    python cluster/slurm/run_study.py studies/example_sgplus.py --store /scratch/$USER/sg.zarr --jobs 4
    python cluster/slurm/run_study.py STUDY.py --print-job-script   # check the generated batch script

Rerunning the same command resumes (finished blocks are kept).
"""

from __future__ import annotations

import argparse
import pathlib
import sys

import dask.config
import yaml


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("study")
    p.add_argument("--store", help="Zarr store on a shared file system")
    p.add_argument("--jobs", type=int, default=2, help="SLURM worker jobs")
    p.add_argument("--config", default=str(pathlib.Path(__file__).with_name("jobqueue.yaml")),
                   help="dask-jobqueue settings (YAML)")
    p.add_argument("--print-job-script", action="store_true", help="print the worker batch script and exit")
    args = p.parse_args(argv)

    from dask_jobqueue import SLURMCluster

    from tubeid.errors import SpecificationError
    from tubeid.runner.execute import run

    with open(args.config) as fh:
        dask.config.update(dask.config.config, yaml.safe_load(fh), priority="new")
    with SLURMCluster() as cluster:
        if args.print_job_script:
            print(cluster.job_script())
            return 0
        cluster.scale(jobs=args.jobs)
        print(f"SLURM cluster: {args.jobs} jobs requested; dashboard {cluster.dashboard_link}", file=sys.stderr)
        try:
            run(args.study, args.store, scheduler=cluster.scheduler_address)
        except SpecificationError as exc:
            print(f"tubeid: error: {exc}", file=sys.stderr)
            return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
