"""The ``tubeid`` command line. Each feature module registers its own sub-commands."""

from __future__ import annotations

import argparse
import importlib
import sys

__all__ = ["main"]

# Modules exposing ``register(subparsers)``; one line per feature.
COMMAND_MODULES = [
    "tubeid.mechanics.cli",
    "tubeid.bench",
    "tubeid.runner.cli",
    "tubeid.diagnose.cli",
    "tubeid.report",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tubeid", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    from tubeid.errors import SpecificationError

    from threadpoolctl import threadpool_limits

    args = build_parser().parse_args(argv)
    try:
        # the hot paths are many small matrices (N ≈ 20–50): BLAS threads only contend with the
        # worker processes and with each other; dask workers are pinned to 1 thread by their nanny
        with threadpool_limits(limits=1):
            return int(args.func(args) or 0)
    except SpecificationError as exc:
        print(f"tubeid: error: {exc}", file=sys.stderr)
        return 2
