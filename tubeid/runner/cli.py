"""``tubeid run | status | show | bench-runner``: the study runner's sub-commands."""

from __future__ import annotations

import argparse
import ast
import json
import sys

__all__ = ["register", "main"]


def _setting(text: str) -> tuple[str, object]:
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"{text!r}: expected NAME=VALUE")
    name, value = text.split("=", 1)
    try:
        value = ast.literal_eval(value)
    except (ValueError, SyntaxError):
        pass  # a plain string
    return name.strip(), value


def register(sub) -> None:
    p = sub.add_parser("run", help="run or resume a study or pipeline (a studies/*.py file) into a Zarr store",
                       description="Run a study as one dask task per block (a pipeline: its stages in order); "
                                   "rerun the same command to resume.")
    p.add_argument("study", help="study file defining `study = Study(...)` or `study = Pipeline(...)`")
    p.add_argument("--store", help="Zarr store path (default: <tubeid.runner.store-root>/<study name>.zarr)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--workers", type=int, help="embedded LocalCluster worker processes (default: one per core; "
                   "0 = sequentially in this process)")
    g.add_argument("--scheduler", help="address of an existing dask scheduler (default: DASK_SCHEDULER_ADDRESS)")
    p.add_argument("--set", dest="overrides", action="append", type=_setting, default=[], metavar="NAME=VALUE",
                   help="override a study (or pipeline) parameter (validated; part of the study's identity)")
    s = p.add_mutually_exclusive_group()
    s.add_argument("--new-store", action="store_true",
                   help="if the store holds another study definition, write <store>-<hash>.zarr instead")
    s.add_argument("--overwrite", action="store_true", help="replace whatever is at --store")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_run)

    p = sub.add_parser("status", help="blocks done / total of a study store, per stage for a pipeline (works while it runs)")
    p.add_argument("store", help="the study or pipeline store (a .zarr directory written by tubeid run)")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=_status)

    p = sub.add_parser("show", help="summary of a study store: provenance and labelled results")
    p.add_argument("store", help="the study or pipeline store (a .zarr directory written by tubeid run)")
    p.add_argument("--source", action="store_true", help="also print the study source text")
    p.add_argument("--stage", action="append", help="pipeline store: show only this stage (repeatable)")
    p.set_defaults(func=_show)

    p = sub.add_parser("bench-runner", help="benchmark the runner: speedup 1 -> 2 workers, overhead vs compute")
    p.add_argument("--blocks", type=int, default=16, help="blocks (tasks) in the benchmark study")
    p.add_argument("--block-seconds", type=float, default=1.0, help="target compute seconds per block")
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="worker counts to compare")
    p.set_defaults(func=_bench)


def _run(args) -> int:
    from tubeid.runner.execute import run

    new_store = args.new_store
    try:
        run(args.study, args.store, workers=args.workers, scheduler=args.scheduler,
            overrides=dict(args.overrides), new_store=new_store, overwrite=args.overwrite,
            progress=False if args.no_progress else None)
    except KeyboardInterrupt:
        print("\ntubeid: interrupted; finished blocks are kept: rerun the same command to resume", file=sys.stderr)
        return 130
    return 0


def _stage_line(name, st) -> str:
    if not st["started"]:
        return f"  {name}: not started"
    pct = 100.0 * st["done"] / st["total"]
    state = "complete" if st["complete"] else "incomplete"
    return f"  {name}: {st['done']}/{st['total']} blocks done ({pct:.1f} %), {state}"


def _status(args) -> int:
    from tubeid.runner.store import store_status

    st = store_status(args.store)
    a = st["attrs"]
    keys = ("study_name", "study_hash", "started", "finished")
    if args.json:
        extra = {"stages": st["stages"]} if "stages" in st else {}
        print(json.dumps({k: st[k] for k in ("done", "total", "complete")} | {k: a.get(k) for k in keys} | extra))
        return 0
    if "stages" in st:
        n_done = sum(s["complete"] for s in st["stages"].values())
        state = "complete" if st["complete"] else "incomplete"
        print(f"pipeline {a.get('study_name')}: {n_done}/{len(st['stages'])} stages complete, {state}")
        for name, s in st["stages"].items():
            print(_stage_line(name, s))
    else:
        pct = 100.0 * st["done"] / st["total"]
        state = "complete" if st["complete"] else "incomplete"
        print(f"{a.get('study_name')}: {st['done']}/{st['total']} blocks done ({pct:.1f} %), {state}")
    print(f"  started {a.get('started')}" + (f", finished {a['finished']}" if a.get("finished") else "")
          + f", runs: {len(a.get('runs', []))}")
    return 0


def _print_dataset(ds) -> None:
    """The dataset without its attributes, then summary statistics of each output written so far."""
    import numpy as np

    shown = ds.copy()
    shown.attrs = {}
    for name, var in shown.data_vars.items():
        if var.size <= 50_000_000:
            var.load()  # read once, printed with its values (an unloaded variable's repr imports dask)
    print(shown)
    for name, var in shown.data_vars.items():
        if var.size <= 50_000_000:
            v = np.asarray(var.values, dtype=float)
            ok = np.isfinite(v)
            stats = f"mean {v[ok].mean():.6g}, min {v[ok].min():.6g}, max {v[ok].max():.6g}" if ok.any() else "no data yet"
            print(f"  {name} [{var.attrs.get('units', '')}]: {stats} ({ok.mean():.0%} written)")


def _show(args) -> int:
    from tubeid.errors import SpecificationError
    from tubeid.runner.store import open_results, store_status

    st = store_status(args.store)
    if "stages" in st:
        return _show_pipeline(args, st)
    if args.stage:
        raise SpecificationError("--stage", args.stage[0], f"{args.store} is a single-study store (it has no stages)")
    ds = open_results(args.store, chunks=None)  # no dask: the values are read once, here
    a = ds.attrs
    print(f"study {a.get('study_name')} (file {a.get('study_file')}, hash {str(a.get('study_hash'))[:12]})")
    print(f"  tubeid {a.get('tubeid_version')}, seed {a.get('seed')} over {a.get('seed_axes')}, "
          f"parameters {a.get('parameters')}")
    print(f"  blocks {a['blocks_done']}/{a['blocks_total']}; started {a.get('started')}; "
          f"finished {a.get('finished') or '-'}")
    if a.get("model_specification"):
        print("  model specification: " + a["model_specification"].splitlines()[0][:100] + " ...")
    if a.get("summary_keys"):
        print("  summary: " + ", ".join(f"{k} = {a[k]}" for k in a["summary_keys"]))
    _print_dataset(ds)
    if args.source:
        print("\n# study source\n" + a.get("study_source", ""))
    return 0


def _show_pipeline(args, st) -> int:
    from tubeid.errors import SpecificationError
    from tubeid.runner.store import open_results

    a = st["attrs"]
    for name in args.stage or []:
        if name not in st["stages"]:
            raise SpecificationError("--stage", name, f"is not a stage of {args.store} (stages: {list(st['stages'])})")
    print(f"pipeline {a.get('study_name')} (file {a.get('study_file')}, hash {str(a.get('study_hash'))[:12]})")
    print(f"  tubeid {a.get('tubeid_version')}, seed {a.get('seed')}, parameters {a.get('parameters')}")
    print(f"  started {a.get('started')}; finished {a.get('finished') or '-'}; stages:")
    for name, s in st["stages"].items():
        print(_stage_line(name, s))
    for name, s in st["stages"].items():
        if (args.stage and name not in args.stage) or not s["started"]:
            continue
        ds = open_results(args.store, name, chunks=None)
        sa = ds.attrs
        print(f"\nstage {name} (hash {str(sa.get('stage_hash'))[:12]}): {sa.get('title')}")
        print(f"  streams keyed by {sa.get('stream_key')} + {sa.get('seed_axes')}, parameters {sa.get('parameters')}")
        if sa.get("summary_keys"):
            print("  summary: " + ", ".join(f"{k} = {sa[k]}" for k in sa["summary_keys"]))
        _print_dataset(ds)
    if args.source:
        print("\n# pipeline source\n" + a.get("study_source", ""))
    return 0


def _bench(args) -> int:
    from tubeid.runner.bench import main as bench_main

    return bench_main(blocks=args.blocks, block_seconds=args.block_seconds, worker_counts=args.workers)


def main(argv: list[str] | None = None) -> int:
    """Stand-alone entry point (``python -m tubeid.runner.cli run ...``): the ``tubeid`` command itself."""
    from tubeid.cli import main as tubeid_main

    return tubeid_main(argv)


if __name__ == "__main__":
    raise SystemExit(main())
