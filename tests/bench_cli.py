"""Wall time of ``tubeid --help``, ``--version``, ``status`` and ``show`` in fresh interpreters (not a test).

    python tests/bench_cli.py STORE [--runs 7] [--baseline DIR]

Each command runs in a new ``python -m tubeid`` process from an empty directory. *cold* is the first
run after deleting the source tree's ``tubeid/__pycache__`` directories (tubeid's bytecode is
recompiled; the OS file cache and the other libraries' bytecode stay warm); *warm* is the median of
``--runs`` further runs. ``--baseline DIR`` runs the same commands with another source tree first on
``PYTHONPATH`` (e.g. ``git archive OLD tubeid | tar -x -C DIR``) and prints the ratios: only those
are meaningful on a shared machine; the load average is printed with the times.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

__all__ = ["main"]


def _time(tree: pathlib.Path, args: list[str], cwd: str) -> float:
    env = dict(os.environ, PYTHONPATH=str(tree))
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "tubeid", *args], env=env, cwd=cwd, capture_output=True, check=True)
    return time.perf_counter() - t


def _check_tree(tree: pathlib.Path) -> None:
    """Exit if ``tubeid`` in a fresh interpreter with ``tree`` on PYTHONPATH is not ``tree``'s (an
    installed tubeid, e.g. an editable install, comes first and every tree would time the same code)."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    where = subprocess.run([sys.executable, "-c", "import tubeid; print(tubeid.__file__)"], env=env,
                           cwd=tempfile.gettempdir(), capture_output=True, text=True, check=True).stdout.strip()
    if pathlib.Path(where).resolve().parent != (tree / "tubeid").resolve():
        sys.exit(f"bench_cli: `import tubeid` gives {where}, not {tree / 'tubeid'}: an installed tubeid shadows "
                 "PYTHONPATH; run from an environment holding tubeid's dependencies but not tubeid "
                 "(pip install . && pip uninstall tubeid)")


def main() -> None:
    """Print cold and warm times per command and tree, then the ratios to the baseline."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("store", help="a study store for status and show")
    p.add_argument("--runs", type=int, default=7, help="warm runs per command")
    p.add_argument("--baseline", help="another source tree holding tubeid/ (e.g. an older commit)")
    args = p.parse_args()
    store = str(pathlib.Path(args.store).resolve())
    trees = {"this": pathlib.Path(__file__).resolve().parents[1]}
    if args.baseline:
        trees = {"baseline": pathlib.Path(args.baseline).resolve(), **trees}
    commands = [["--help"], ["--version"], ["status", store], ["show", store]]
    for tree in trees.values():
        _check_tree(tree)
    print("load average before: " + ", ".join(f"{x:.1f}" for x in os.getloadavg()))
    warm: dict[tuple[str, str], float] = {}
    with tempfile.TemporaryDirectory() as cwd:
        for command in commands:
            for name, tree in trees.items():
                for cache in (tree / "tubeid").rglob("__pycache__"):
                    shutil.rmtree(cache)
                try:
                    cold = _time(tree, command, cwd)
                except subprocess.CalledProcessError:
                    print(f"{name:8s} tubeid {command[0]:10s} (not supported)")
                    continue
                runs = [_time(tree, command, cwd) for _ in range(args.runs)]
                warm[name, command[0]] = statistics.median(runs)
                print(f"{name:8s} tubeid {command[0]:10s} cold {cold:5.2f} s   warm median {statistics.median(runs):5.2f} s "
                      f"(min {min(runs):.2f}, max {max(runs):.2f})", flush=True)
    print("load average after:  " + ", ".join(f"{x:.1f}" for x in os.getloadavg()))
    for command in commands:
        key = command[0]
        if ("baseline", key) in warm and ("this", key) in warm:
            print(f"ratio this/baseline, tubeid {key}: {warm['this', key] / warm['baseline', key]:.3f}")


if __name__ == "__main__":
    main()
