"""The ``tubeid`` command line.

The top-level parser is built from a static table of commands (``COMMANDS``: name, module, one-line
help): only the chosen command's module is imported, and it registers its own sub-parser(s) with
``register(subparsers)``. ``tubeid --help`` and ``tubeid --version`` import no numerical library.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence
from typing import NamedTuple

from tubeid._version import __version__

__all__ = ["main", "build_parser", "COMMANDS", "Command"]


class Command(NamedTuple):
    """One ``tubeid`` sub-command.

    Parameters
    ----------
    name : str
        The sub-command, e.g. ``"run"``.
    module : str
        The module whose ``register(subparsers)`` defines its parser (and those of its siblings).
    help : str
        Its one-line help in ``tubeid --help``; the module's ``add_parser(help=...)`` must agree.
    needs : tuple of str
        Optional dependencies (import names, keys of ``tubeid._optional.EXTRAS``) checked before the
        command runs, so that it fails at once, naming the extra, rather than after its computation.
    settings : bool
        Whether tubeid's configuration (``tubeid.yaml``, ``TUBEID_...`` variables) is checked as a whole
        before the command runs (:func:`tubeid.config.check`): a bad setting is one line naming it, its
        variable, the value and the rule, before anything is read, created or started. False for the
        commands that only read a store (``status`` imports no dask).
    """

    name: str
    module: str
    help: str
    needs: tuple[str, ...] = ()
    settings: bool = True


COMMANDS: tuple[Command, ...] = (
    Command("run", "tubeid.runner.cli",
            "run or resume a study or pipeline (a studies/*.py file) into a Zarr store"),
    Command("status", "tubeid.runner.cli",
            "blocks done / total of a study store, per stage for a pipeline (works while it runs)", settings=False),
    Command("show", "tubeid.runner.cli", "summary of a study store: provenance and labelled results",
            settings=False),
    Command("report", "tubeid.report", "figures and summary (Markdown, JSON) of a paper study store",
            needs=("matplotlib",)),
    Command("diagnose", "tubeid.diagnose.cli",
            "test measured data against a declared model; name the effects it lacks", needs=("matplotlib",)),
    Command("model", "tubeid.mechanics.cli", "summarise a built-in model or a specification file"),
    Command("bench", "tubeid.bench", "benchmark the hot paths against in-process baselines"),
    Command("bench-runner", "tubeid.runner.cli",
            "benchmark the runner: speedup 1 -> 2 workers, overhead vs compute"),
)

DESCRIPTION = """\
Identify a probabilistic model of the turbulent-flow loads on a tube bundle (steam generators,
heat exchangers) from measured tube vibrations, carrying the uncertainty of the simplified model
and of the load model (Batou & Soize 2008). Studies run as dask task graphs on this machine or a
cluster and write labelled Zarr stores that xarray opens.

start here:
  tubeid run studies/paper.py          the paper study -> results/paper.zarr (rerun to resume)
  tubeid status results/paper.zarr     how far it is (works while it runs)
  tubeid report results/paper.zarr     its figures and summary
  tubeid diagnose DATA                 identify the load on measured data; trace what the model misses
  tubeid model paper-simplified        summarise a bundle model"""

EPILOG = """\
'tubeid COMMAND --help' gives a command's options. Configuration: tubeid/tubeid.yaml, overridden by
~/.config/dask/*.yaml or TUBEID_RUNNER__<KEY>=value variables. Documentation: README.md."""


def _chosen(argv: Sequence[str]) -> str | None:
    """The sub-command named on the command line (the first argument that is not an option)."""
    return next((a for a in argv if not a.startswith("-")), None)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``tubeid`` argument parser, with ``command``'s own sub-parser(s) fully defined.

    Parameters
    ----------
    command : str, optional
        The sub-command about to be parsed. Only its module is imported, and every command that
        module registers gets its real parser; the others are placeholders that carry their help
        line for ``tubeid --help``. ``None`` (or an unknown name) imports nothing.

    Returns
    -------
    argparse.ArgumentParser
        The parser.
    """
    parser = argparse.ArgumentParser(prog="tubeid", description=DESCRIPTION, epilog=EPILOG,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"tubeid {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", title="commands")
    module = next((c.module for c in COMMANDS if c.name == command), None)
    if module is not None:
        importlib.import_module(module).register(sub)
    for c in COMMANDS:
        if c.module != module:
            sub.add_parser(c.name, help=c.help, add_help=False)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``tubeid`` command line.

    Parameters
    ----------
    argv : sequence of str, optional
        The arguments after ``tubeid`` (default: ``sys.argv[1:]``).

    Returns
    -------
    int
        The exit status: 0 on success, 2 for a refused input (a ``SpecificationError``) or a
        missing optional dependency, both reported in one line on stderr; 1 for an error in a study's
        own code (a failing task, or a study file that raises while being executed: the traceback of
        the study's code, then one line); 130 when interrupted (Ctrl-C, SIGINT), said in one line
        (``run`` adds how to resume); a command may return others (141, silently, when the reader of
        its output went away, as ``tubeid status STORE | head -1``; 74 when a write of its output
        failed otherwise, e.g. on a full disk, buffered or not, said in one line on stderr).
    """
    try:
        return _main(argv)
    except KeyboardInterrupt:  # Ctrl-C anywhere (importing, parsing, computing): one line, no traceback
        try:
            print("\ntubeid: interrupted", file=sys.stderr)
        except (OSError, ValueError):
            pass
        return 130  # 128 + SIGINT, as a shell reports a process ended by Ctrl-C


class _OutputFailed(Exception):
    """A write to stdout failed other than by a closed pipe (e.g. ENOSPC on a full disk); the cause is the OSError."""


class _Stdout:
    """``sys.stdout`` while a command runs: a write or flush that fails with an OSError other than
    BrokenPipeError raises :class:`_OutputFailed`, so that the failure is told apart from the command's
    own file errors whether or not the stream is buffered (``PYTHONUNBUFFERED=1`` writes at each print).
    Everything else is the wrapped stream's."""

    def __init__(self, stream) -> None:
        self._stream = stream

    def write(self, text):
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            raise
        except OSError as exc:
            raise _OutputFailed() from exc

    def flush(self) -> None:
        try:
            self._stream.flush()
        except BrokenPipeError:
            raise
        except OSError as exc:
            raise _OutputFailed() from exc

    def __getattr__(self, name):
        return getattr(self._stream, name)


def _output_failed(exc: OSError) -> int:
    """Say once that the output could not be written; later writes (at interpreter exit) go nowhere."""
    print(f"tubeid: error: cannot write the output: {exc}", file=sys.stderr)
    try:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    except (OSError, ValueError):  # a stdout without a file descriptor (e.g. captured in a test)
        pass
    return 74  # EX_IOERR


def _main(argv: Sequence[str] | None) -> int:
    stdout = sys.stdout
    sys.stdout = _Stdout(stdout)  # every write of the command, argparse's help and version included
    try:
        return _parse_and_run(argv)
    except _OutputFailed as exc:  # e.g. a full disk: said once, not again at interpreter exit
        return _output_failed(exc.__cause__)
    finally:
        if isinstance(sys.stdout, _Stdout):
            sys.stdout = stdout


def _parse_and_run(argv: Sequence[str] | None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = _chosen(argv)
    needs = next((c.needs for c in COMMANDS if c.name == command), ())
    if needs and not {"-h", "--help"} & set(argv):  # before importing the command: fail at once
        from tubeid._optional import require
        from tubeid.errors import MissingDependencyError

        try:
            for module in needs:
                require(module, f"tubeid {command}")
        except MissingDependencyError as exc:
            print(f"tubeid: error: {exc}", file=sys.stderr)
            return 2
    try:
        args = build_parser(command).parse_args(argv)
    except SystemExit as exc:  # `tubeid run STUDY.py --help`: the study's own parameters after the options
        if exc.code == 0 and command == "run" and {"-h", "--help"} & set(argv):
            from tubeid.errors import SpecificationError
            from tubeid.runner.cli import study_help

            try:
                text = study_help(argv)
            except SpecificationError as err:
                print(f"tubeid: error: {err}", file=sys.stderr)
                return 2
            if text:
                print("\n" + text)
        if exc.code == 0:  # --help, --version: their text meets a write error here, not at interpreter exit
            try:
                sys.stdout.flush()
            except BrokenPipeError:
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
                return 128 + 13
        raise

    from threadpoolctl import threadpool_limits

    from tubeid.errors import BlockFailed, MissingDependencyError, SpecificationError

    try:
        if next(c.settings for c in COMMANDS if c.name == args.command):
            from tubeid import config

            config.check()  # every setting, before the command reads, creates or starts anything
        # the hot paths are many small matrices (N ≈ 20–50): BLAS threads only contend with the
        # worker processes and with each other; dask workers are pinned to 1 thread by their nanny
        with threadpool_limits(limits=1):
            status = int(args.func(args) or 0)
        sys.stdout.flush()  # output still buffered (stdout a pipe or a file) meets its error here, not at exit
        return status
    except (SpecificationError, MissingDependencyError) as exc:
        print(f"tubeid: error: {exc}", file=sys.stderr)
        return 2
    except BlockFailed as exc:  # a bug in a study's code: its traceback, then which block and how to resume
        import traceback

        if exc.__cause__ is not None:
            traceback.print_exception(exc.__cause__, file=sys.stderr)
        print(f"tubeid: error: {exc}", file=sys.stderr)
        return 1
    except BrokenPipeError:  # the reader of stdout went away (`tubeid status STORE | head`): stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at interpreter exit
        return 128 + 13  # as a process ended by SIGPIPE
    except Exception as exc:
        # a study file that raised while being executed (tubeid.runner.study.StudyRaised, not imported here):
        # likewise the traceback of the study's own frames, then one line
        trace = getattr(exc, "user_traceback", None)
        if not isinstance(trace, str):
            raise
        print(trace, end="", file=sys.stderr)
        print(f"tubeid: error: {exc}", file=sys.stderr)
        return 1
