"""``tubeid run | status | show | bench-runner``: the study runner's sub-commands."""

from __future__ import annotations

import argparse
import ast
import json
import math
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
    else:
        for number in _floats(value):
            if not math.isfinite(number) or (number != 0.0 and abs(number) < sys.float_info.min):
                raise argparse.ArgumentTypeError(f"{text!r}: a number beyond a float's range (read as {number!r}; "
                                                 f"a float lies within ±{sys.float_info.max:.4g}, and is 0 or at "
                                                 f"least {sys.float_info.min:.4g} in magnitude)")
        if any(number == 0.0 for number in _floats(value)) and _underflows(text.split("=", 1)[1]):
            raise argparse.ArgumentTypeError(f"{text!r}: a number beyond a float's range (read as 0.0; a float is 0 "
                                             f"or at least {sys.float_info.min:.4g} in magnitude)")
    return name.strip(), value


def _floats(value):
    """The floats in a literal (nested in lists, tuples, sets and dicts too)."""
    if isinstance(value, float):
        yield value
    elif isinstance(value, (list, tuple, set, frozenset)):
        for item in value:
            yield from _floats(item)
    elif isinstance(value, dict):
        for item in (*value.keys(), *value.values()):
            yield from _floats(item)


def _underflows(text: str) -> bool:
    """Whether a float literal in ``text`` with a non-zero digit reads as 0.0 (1e-400)."""
    import re

    for m in re.finditer(r"(?<![\w.])(\d+\.?\d*|\.\d+)[eE]([-+]?\d+)", text):
        if any(c in "123456789" for c in m.group(1)) and float(m.group(0)) == 0.0:
            return True
    return False


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
    s.add_argument("--overwrite", action="store_true",
                   help="replace the store at --store (only what tubeid wrote in it is removed; other files are kept)")
    p.add_argument("--no-verify", action="store_true",
                   help="on a resume, trust the finished blocks' flags instead of checking every block's checksum")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_run)

    p = sub.add_parser("status", help="blocks done / total of a study store, per stage for a pipeline (works while it runs)")
    p.add_argument("store", help="the study or pipeline store (a .zarr directory written by tubeid run)")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--verify", action="store_true",
                   help="read every finished block back and check its checksum; exit code 1 if anything is damaged")
    p.set_defaults(func=_status)

    p = sub.add_parser("show", help="summary of a study store: provenance and labelled results")
    p.add_argument("store", help="the study or pipeline store (a .zarr directory written by tubeid run)")
    p.add_argument("--source", action="store_true", help="also print the study source text")
    p.add_argument("--stage", action="append", help="pipeline store: show only this stage (repeatable)")
    p.add_argument("--full", action="store_true",
                   help=f"print every parameter value whole (else one whose JSON text is longer than {LONG_VALUE} "
                        "characters is cut)")
    p.set_defaults(func=_show)

    p = sub.add_parser("bench-runner", help="benchmark the runner: speedup 1 -> 2 workers, overhead vs compute")
    p.add_argument("--blocks", type=int, default=16, help="blocks (tasks) in the benchmark study")
    p.add_argument("--block-seconds", type=float, default=1.0, help="target compute seconds per block")
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="worker counts to compare")
    p.add_argument("--startup", action="store_true",
                   help="instead: embedded cluster start-up, plain TCP vs ephemeral TLS (6 alternating starts)")
    p.add_argument("--integrity", action="store_true",
                   help="instead: cost of the block checksum against the Zarr write, and of verification")
    p.set_defaults(func=_bench)


def study_help(argv) -> str | None:
    """The parameters of the study that ``tubeid run ... --help`` names, as text (None if it names none).

    Parameters
    ----------
    argv : sequence of str
        The ``tubeid`` arguments (``run STUDY.py ... --help``).

    Raises
    ------
    SpecificationError
        The study file named cannot be loaded (missing, not Python, no ``study``, a refused definition).
    """
    import argparse as _argparse

    parser = _argparse.ArgumentParser(add_help=False)
    sub = parser.add_subparsers(dest="command")
    register(sub)
    run_parser = sub.choices["run"]
    run_parser.exit = run_parser.error = lambda *a, **k: (_ for _ in ()).throw(ValueError())  # no exit here
    try:
        args, _ = parser.parse_known_args([a for a in argv if a not in ("-h", "--help")])
    except (ValueError, SystemExit):
        return None
    if getattr(args, "command", None) != "run" or not getattr(args, "study", None):
        return None
    from tubeid.errors import shown
    from tubeid.runner.study import load_definition  # numpy and the rest: only when a study is named

    study = load_definition(args.study)[0]
    lines = [f"parameters of {args.study} (study {study.name!r}; --set NAME=VALUE):"]
    for name, p in study.parameters.items():
        value = shown(p.value)
        if len(repr(p.value)) > LONG_VALUE:  # e.g. a model's specification, stored as its content
            value = f"{repr(p.value)[:40]}... ({len(repr(p.value))} characters)"
        lines.append(f"  {name} = {value}  ({p.describe()})")
    if len(lines) == 1:
        lines.append("  none")
    return "\n".join(lines)


def _run(args) -> int:
    from tubeid.runner.execute import run

    new_store = args.new_store
    try:
        run(args.study, args.store, workers=args.workers, scheduler=args.scheduler,
            overrides=dict(args.overrides), new_store=new_store, overwrite=args.overwrite,
            verify_blocks=not args.no_verify, progress=False if args.no_progress else None)
    except KeyboardInterrupt:
        print("\ntubeid: interrupted; finished blocks are kept: rerun the same command to resume", file=sys.stderr)
        return 130
    return 0


def _stage_line(name, st) -> str:
    if st.get("needed") is False:
        return f"  {name}: not needed"
    if not st["started"]:
        return f"  {name}: not started"
    pct = 100.0 * st["done"] / max(st["total"], 1)
    state = "complete" if st["complete"] else "incomplete"
    damaged = f"; DAMAGED: {st['damaged']}" if st.get("damaged") else ""
    return f"  {name}: {st['done']}/{st['total']} blocks done ({pct:.1f} %), {state}{damaged}"


def _damaged(name: str, value) -> str:
    """How a store attribute of an unexpected type (a damaged or hand-edited store) is shown."""
    from tubeid.errors import shown

    return f"DAMAGED (attribute {name} = {shown(value)})"


def _runs(a: dict) -> str:
    runs = a.get("runs", [])
    return str(len(runs)) if isinstance(runs, list) else _damaged("runs", runs)


def _ended_line(a: dict) -> str | None:
    ended = a.get("ended")
    if not ended:
        return None
    if isinstance(ended, dict) and "stage" in ended and "reason" in ended:
        return f"  ended before stage {ended['stage']}: {ended['reason']}"
    return f"  ended: {_damaged('ended', ended)}"


def _summary_line(a: dict) -> str | None:
    """``summary: k = v, ...`` of the attributes a study's ``summarize`` wrote (named in ``summary_keys``)."""
    keys = a.get("summary_keys")
    if not keys:
        return None
    if not isinstance(keys, list) or not all(isinstance(k, str) for k in keys):
        return f"  summary: {_damaged('summary_keys', keys)}"
    return "  summary: " + ", ".join(f"{k} = {a[k]}" if k in a else f"{k} = DAMAGED (attribute missing)" for k in keys)


def _text(a: dict, name: str) -> str | None:
    """A text attribute (``model_specification``, ``study_source``): None if absent, shown damaged if not text."""
    value = a.get(name)
    if value is None or isinstance(value, str):
        return value
    return _damaged(name, value)


def _lock_line(st) -> str | None:
    from tubeid.runner.lock import describe_holder, holder_state, LOCK_NAME
    import pathlib

    rec = st.get("lock")
    if rec is None:
        return None
    if not rec:
        return "  lock file unreadable"
    state, why = holder_state(rec, pathlib.Path(st["path"]) / LOCK_NAME)
    return (f"  {'being written' if state == 'alive' else 'stale lock'} by {describe_holder(rec)} ({why})")


def _verifications(store, st):
    from tubeid.runner.integrity import verify

    if "stages" in st:
        return {name: verify(store, name) for name, s in st["stages"].items() if s["started"]}
    return {None: verify(store)}


def _status(args) -> int:
    from tubeid.runner.status import store_status  # no zarr import: status answers at once

    st = store_status(args.store)
    st["path"] = args.store
    a = st["attrs"]
    keys = ("study_name", "study_hash", "started", "finished")
    checks = _verifications(args.store, st) if args.verify else {}
    damaged = any(not v.ok for v in checks.values())
    if args.json:
        extra = {"stages": st["stages"]} if "stages" in st else {}
        if args.verify:
            extra["verified"] = {str(k): {"checked": v.checked, "ok": v.ok, "findings": v.lines(limit=1000)}
                                 for k, v in checks.items()}
        extra["lock"] = st.get("lock")
        if a.get("ended"):
            extra["ended"] = a["ended"]
        print(json.dumps({k: st[k] for k in ("done", "total", "complete")} | {k: a.get(k) for k in keys} | extra))
        return 1 if damaged else 0
    if "stages" in st:
        n_done = sum(s["complete"] for s in st["stages"].values())
        state = "complete" if st["complete"] else "incomplete"
        print(f"pipeline {a.get('study_name')}: {n_done}/{len(st['stages'])} stages complete, {state}")
        for name, s in st["stages"].items():
            print(_stage_line(name, s))
        if _ended_line(a):
            print(_ended_line(a))
    else:
        pct = 100.0 * st["done"] / max(st["total"], 1)
        state = "complete" if st["complete"] else "incomplete"
        print(f"{a.get('study_name')}: {st['done']}/{st['total']} blocks done ({pct:.1f} %), {state}")
        if st["damaged"]:
            print(f"  DAMAGED: {st['damaged']}")
    print(f"  started {a.get('started')}" + (f", finished {a['finished']}" if a.get("finished") else "")
          + f", runs: {_runs(a)}")
    line = _lock_line(st)
    if line:
        print(line)
    for group, v in checks.items():
        where = f"stage {group}" if group else "blocks"
        if v.ok:
            print(f"  verified: {where}: {v.checked} finished blocks match their checksums")
        else:
            print(f"  DAMAGED: {where}:\n    " + "\n    ".join(v.lines())
                  + "\n    rerun `tubeid run` on its study to repair (only the damaged blocks are recomputed)")
    return 1 if damaged else 0


def _print_dataset(ds, store, group=None) -> None:
    """The dataset without its attributes, then summary statistics of each output written so far.

    Each variable is read once (no dask). A chunk that cannot be decoded never ends in a traceback:
    the output's statistics are replaced by the damaged chunks' names (from the store's verification).
    """
    import numpy as np

    shown = ds.copy()
    shown.attrs = {}
    unreadable = {}
    for name, var in shown.data_vars.items():
        if var.size <= 50_000_000:
            try:
                var.load()  # read once, printed with its values (an unloaded variable's repr imports dask)
            except Exception as exc:
                unreadable[name] = exc
    print(shown)
    damage = None
    finished = _finished_blocks(store, group)
    node = lambda name: f"{group}/{name}" if group else name  # noqa: E731 - the output's node, as verify names it
    for name, var in shown.data_vars.items():
        if var.size > 50_000_000:
            continue
        # a chunk that cannot be decoded, or a finished block without its chunk or with missing values (a deleted
        # chunk or array reads as the fill value): the store's verification names the damage, if any
        suspect = name in unreadable or (finished is not None and _looks_damaged(store, node(name), var, finished))
        if suspect and damage is None:
            from tubeid.runner.integrity import verify

            damage = verify(store, group)
        # a damaged block of this output: its chunk or array named, or changed values (verification cannot
        # tell which output of the block changed)
        bad = [f"block {i}: {r}" for i, r in sorted(damage.damaged.items())
               if f"{node(name)}/c/" in r or f"array {node(name)} " in r or not ("/c/" in r or "array " in r)
               ] if suspect else []
        if name in unreadable:
            print(f"  {name} [{var.attrs.get('units', '')}]: DAMAGED, cannot be read ({type(unreadable[name]).__name__}); "
                  + ("; ".join(bad[:5]) or "see `tubeid status --verify`")
                  + ("" if len(bad) <= 5 else f"; ... {len(bad) - 5} more")
                  + "; rerun `tubeid run` on its study to recompute")
            continue
        v = np.asarray(var.values, dtype=float)
        ok = np.isfinite(v)
        stats = f"mean {v[ok].mean():.6g}, min {v[ok].min():.6g}, max {v[ok].max():.6g}" if ok.any() else "no data yet"
        print(f"  {name} [{var.attrs.get('units', '')}]: {stats} ({ok.mean():.0%} written)"
              + (f"; DAMAGED: {'; '.join(bad[:5])}" + ("" if len(bad) <= 5 else f"; ... {len(bad) - 5} more")
                 + "; rerun `tubeid run` on its study to recompute" if bad else ""))


def _finished_blocks(store, group):
    """``(axes, chunks, flags)`` of the store's finished blocks (None if the bookkeeping is unreadable)."""
    from tubeid.runner.store import BOOKKEEPING, _group, read_flags

    try:
        attrs = _group(store, group, consolidated=False)[BOOKKEEPING].attrs
        return list(attrs["axes"]), [int(c) for c in attrs["chunks"]], read_flags(store, group)[0] != 0
    except Exception:  # damaged bookkeeping: `status` says so
        return None


def _looks_damaged(store, node: str, var, finished) -> bool:
    """Whether output ``var`` (node ``node``) may be damaged in a finished block: a chunk file is missing (a
    deleted chunk or array reads as the fill value: NaN, or 0 for integers) or a float value is not finite.
    Only a hint (a block equal to the fill value has no chunk file; an output may declare non-finite values):
    the store's verification decides."""
    import pathlib

    import numpy as np

    from tubeid.runner.integrity import chunk_key

    axes, chunks, done = finished
    if not set(axes) <= set(var.dims):
        return False
    if any(not (pathlib.Path(store) / chunk_key(node, index, var.ndim)).is_file() for index in zip(*np.nonzero(done))):
        return True
    if var.dtype.kind not in "fc":
        return False
    for k, c in enumerate(chunks):  # block grid -> values (numpy only: a new xarray object would import dask.array)
        done = np.repeat(done, c, axis=k)
    order = [d for d in var.dims if d in axes]
    done = np.transpose(done, [axes.index(d) for d in order])[tuple(slice(0, var.sizes[d]) for d in order)]
    mask = np.broadcast_to(done.reshape([var.sizes[d] if d in axes else 1 for d in var.dims]), var.shape)
    return not bool(np.isfinite(np.asarray(var.values)[mask]).all())


#: ``tubeid show`` cuts a parameter's value whose JSON text is longer than this (e.g. a model
#: specification that a study stores as a parameter, thousands of characters), unless ``--full``.
LONG_VALUE = 80


def _parameters(text, full: bool) -> str:
    """A store's ``parameters`` attribute (JSON text of an object) as it is stored, except that a
    value whose JSON text is longer than ``LONG_VALUE`` characters is cut to its first 40, with its
    length (whole if ``full``). Anything else is printed as it is."""
    import json

    try:
        values = json.loads(text)
    except (TypeError, ValueError):
        return str(text)
    if not isinstance(values, dict):
        return str(text)
    parts = []
    for name, value in values.items():
        shown = json.dumps(value)
        if len(shown) > LONG_VALUE and not full:
            shown = f"{shown[:40]}... ({len(shown)} characters; --full prints it)"
        parts.append(f"{json.dumps(name)}: {shown}")
    return "{" + ", ".join(parts) + "}"


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
          f"parameters {_parameters(a.get('parameters'), args.full)}")
    print(f"  blocks {a['blocks_done']}/{a['blocks_total']}; started {a.get('started')}; "
          f"finished {a.get('finished') or '-'}")
    spec = _text(a, "model_specification")
    if spec:
        print("  model specification: " + (spec.splitlines() or [""])[0][:100] + " ...")
    if _summary_line(a):
        print(_summary_line(a))
    _print_dataset(ds, args.store)
    if args.source:
        print("\n# study source\n" + (_text(a, "study_source") or ""))
    return 0


def _show_pipeline(args, st) -> int:
    from tubeid.errors import SpecificationError
    from tubeid.runner.store import open_results

    a = st["attrs"]
    for name in args.stage or []:
        if name not in st["stages"]:
            raise SpecificationError("--stage", name, f"is not a stage of {args.store} (stages: {list(st['stages'])})")
    print(f"pipeline {a.get('study_name')} (file {a.get('study_file')}, hash {str(a.get('study_hash'))[:12]})")
    print(f"  tubeid {a.get('tubeid_version')}, seed {a.get('seed')}, parameters {_parameters(a.get('parameters'), args.full)}")
    print(f"  started {a.get('started')}; finished {a.get('finished') or '-'}; stages:")
    for name, s in st["stages"].items():
        print(_stage_line(name, s))
    if _ended_line(a):
        print(_ended_line(a))
    for name, s in st["stages"].items():
        if (args.stage and name not in args.stage) or not s["started"]:
            continue
        ds = open_results(args.store, name, chunks=None)
        sa = ds.attrs
        print(f"\nstage {name} (hash {str(sa.get('stage_hash'))[:12]}): {sa.get('title')}")
        print(f"  streams keyed by {sa.get('stream_key')} + {sa.get('seed_axes')}, "
              f"parameters {_parameters(sa.get('parameters'), args.full)}")
        if _summary_line(sa):
            print(_summary_line(sa))
        _print_dataset(ds, args.store, name)
    if args.source:
        print("\n# pipeline source\n" + (_text(a, "study_source") or ""))
    return 0


def _bench(args) -> int:
    from tubeid.runner import bench

    if args.startup or args.integrity:
        if args.startup:
            bench.startup()
        if args.integrity:
            bench.integrity()
        return 0
    return bench.main(blocks=args.blocks, block_seconds=args.block_seconds, worker_counts=args.workers)


def main(argv: list[str] | None = None) -> int:
    """Stand-alone entry point (``python -m tubeid.runner.cli run ...``): the ``tubeid`` command itself."""
    from tubeid.cli import main as tubeid_main

    return tubeid_main(argv)


if __name__ == "__main__":
    raise SystemExit(main())
