"""Where the exact solver's compiled main loop spends its time, line by line (a sampling profile).

    python benchmarks/kernel_profile.py [--calls 30] [--open] [--top 25] [--model paper-reference]
    python benchmarks/kernel_profile.py --split [--calls 30] [--model paper-reference] [--dt SECONDS]

Needs Linux ``perf`` (its software event ``cpu-clock``: it works in virtual machines without hardware
counters) and binutils' ``objdump``. A child process runs under ``perf record``: it compiles the
kernels with ``NUMBA_DEBUGINFO=1`` into an empty numba cache (a temporary directory), then
calls ``simulate`` ``--calls`` times on realisation 0 of the bench model (``paper-simplified``,
δ = 0.45, δ_F = 0.04, 220 s, the load sampled at 2 ms; ``--model paper-reference``: the mean
reference model, N = 50, under the mean coherent load drawn from that realisation's load stream;
``--open``: the gap opened, so the event-free path alone). The samples that fall in numba-compiled
code are attributed to its functions (``run_exact``, and those that stay calls, e.g. ``evaluate``),
and those in ``run_exact`` to source lines through the DWARF line table of its object code, read
from the numba cache file.

numba attributes every line it inlines into ``run_exact`` to ``_fastpath.py``: a line number may
belong to ``_fastpath.py``, ``_modal.py`` or ``_events.py``, so each reported line shows that line
(its enclosing function and text) in each of the three that has it (the instructions tell which).
Percentages are of the samples in numba-compiled code. The debug build's code differs a little from
the normal build's: it keeps numba's ``min``, ``max`` and ``int`` as calls (``builtins.ol_min`` ...),
which the normal build inlines; the split, not the total, is the point.

``--split`` profiles nothing: it times the normal build (``split``) with the stop active and with
the gap opened, and prints the events' cost per switch and the realisation's counters as JSON;
``--dt`` sets its integration step.
"""

from __future__ import annotations

import argparse
import ast
import bisect
import collections
import io
import json
import os
import pathlib
import pickle
import shutil
import subprocess
import sys
import tempfile

HERE = pathlib.Path(__file__).resolve().parent
SOLVER = HERE.parent / "tubeid" / "dynamics" / "solver"
FILES = ("_fastpath.py", "_modal.py", "_events.py")
KERNEL = "_ZN6tubeid8dynamics6solver9_fastpath9run_exact"
MODELS = ("paper-simplified", "paper-reference")


def workload(model: str) -> tuple:
    """(M, D, K, B, C, F, stops as (b, gap, stiffness)) of the profiled realisation: realisation 0 of
    the bench (``paper-simplified``, δ = 0.45, δ_F = 0.04) or the mean ``paper-reference`` under the
    mean 7-point coherent load (the paper study's experiment) drawn from that realisation's load stream."""
    if model == "paper-simplified":
        if str(HERE) not in sys.path:
            sys.path.insert(0, str(HERE))
        from solver_against_ref import realisation

        return realisation(0, 220.0)[0]
    from tubeid.dynamics.response import _load_points, realisation_streams
    from tubeid.mechanics.library import builtin_spec
    from tubeid.mechanics.reduction import reduce
    from tubeid.uncertainty.loads import coherent_forces
    from tubeid.uncertainty.processes import gaussian_loads

    reduced = reduce(builtin_spec(model))
    load = coherent_forces()
    M, D, K = reduced.mean_matrices
    F = gaussian_loads(load, 220.0, 2e-3, [realisation_streams(1, 0)[2]])[0]
    stops = [(tuple(b), s.gap, s.stiffness) for b, s in zip(reduced.stop_vectors(), reduced.spec.stops)]
    return M, D, K, reduced.load_matrix(_load_points(load)), reduced.sensor_matrix(), F, stops


def split(model: str, calls: int, dt: float | None = None) -> dict:
    """The normal build's wall time per ``simulate`` call with the stop active and with the gap
    opened (minimum over ``calls`` of each, the two alternated call by call so that both see the
    same phases of the machine; the same step: the stop's stiffness still sets f_max), the
    realisation's counters with the stop active (switches, flagged sub-steps, exact evaluations,
    sub-steps) and with the gap opened (switches: none), and the events' cost per switch:
    (active - opened) / switches. ``dt``: the integration step (default: the solver's rule).

    A call's time holds everything ``simulate`` does (the checks, f_max's eigenvalues, the kernel,
    the labelled result) except the regime tables: the first call builds them into the process's
    cache and the timed calls reuse them (``tubeid bench transient`` empties that cache and so
    counts the build)."""
    import time

    from tubeid.dynamics.solver import Stop, simulate
    from tubeid.dynamics.solver._simulate import simulate_with_diagnostics

    M, D, K, B, C, F, stops = workload(model)
    kw = dict(output_dt=3e-3, discard=2.0, dt=dt)
    systems = {"active": [Stop(b=b, gap=g, stiffness=k) for b, g, k in stops],
               "opened": [Stop(b=b, gap=1e9, stiffness=k) for b, g, k in stops]}
    best = {}
    for name, st in systems.items():
        simulate(M, D, K, st, B, C, F, 2e-3, **kw)  # compile or load the kernels, build the tables
        best[name] = float("inf")
    for _ in range(calls):
        for name, st in systems.items():
            t0 = time.perf_counter()
            simulate(M, D, K, st, B, C, F, 2e-3, **kw)
            best[name] = min(best[name], time.perf_counter() - t0)
    active = simulate_with_diagnostics(M, D, K, systems["active"], B, C, F, 2e-3, **kw)[1][0]
    opened = simulate_with_diagnostics(M, D, K, systems["opened"], B, C, F, 2e-3, **kw)[1][0]
    return {"model": model, "n_dof": M.shape[0], "dt": dt, "calls": calls,
            "seconds_stop_active": best["active"], "seconds_gap_opened": best["opened"],
            "steps": active["steps"], "switches": active["switches"], "flagged_steps": active["flagged_steps"],
            "evaluations": active["evaluations"], "switches_gap_opened": opened["switches"],
            "microseconds_per_switch": 1e6 * (best["active"] - best["opened"]) / active["switches"]}


def child(out: pathlib.Path, calls: int, opened: bool, model: str = "paper-simplified") -> None:
    """Run the workload; write the compiled functions' addresses to ``out`` once compiled."""
    from tubeid.dynamics.solver import Stop, simulate
    from tubeid.dynamics.solver._fastpath import run_exact

    M, D, K, B, C, F, stops = workload(model)
    stops = [Stop(b=b, gap=1e9 if opened else g, stiffness=k) for b, g, k in stops]

    def once():
        simulate(M, D, K, stops, B, C, F, 2e-3, output_dt=3e-3, discard=2.0)

    once()
    funcs = {}
    for cres in run_exact.overloads.values():
        lib = cres.library
        for f in lib._final_module.functions:
            if not f.is_declaration:
                funcs[f.name] = lib.get_pointer_to_function(f.name)
    out.write_text(json.dumps(funcs))
    for _ in range(calls):
        once()


def short(mangled: str) -> str:
    """``module.function`` of a numba-mangled name (``_ZN6tubeid...8evaluateB...``)."""
    parts, i = [], 3 if mangled.startswith("_ZN") else mangled.find("_ZN") + 3
    while 0 < i < len(mangled) and mangled[i].isdigit():
        j = i
        while mangled[j].isdigit():
            j += 1
        n = int(mangled[i:j])
        parts.append(mangled[j:j + n])
        i = j + n
    parts = [x for x in parts if x not in ("_3clocals_3e", "impl")]  # numba's "<locals>.impl" of an overload
    prefix = "cfunc." if mangled.startswith("cfunc.") else ""
    return prefix + ".".join(parts[-2:]) if parts else mangled[:40]


def kernel_object(cache: pathlib.Path) -> bytes:
    """The ELF object of ``run_exact`` from its numba cache file (``_fastpath.run_exact-*.nbc``)."""
    def walk(o):
        if isinstance(o, bytes) and o[:4] == b"\x7fELF":
            yield o
        elif isinstance(o, (tuple, list)):
            for x in o:
                yield from walk(x)
        elif isinstance(o, dict):
            for x in o.values():
                yield from walk(x)

    for f in cache.rglob("_fastpath.run_exact-*.nbc"):
        unpickler = pickle.Unpickler(io.BytesIO(f.read_bytes()))  # numba's cache: pickles one after another
        try:
            while True:
                for elf in walk(unpickler.load()):
                    return elf
        except EOFError:
            pass
    raise SystemExit(f"kernel_profile: no compiled run_exact found in {cache}")


def enclosing_functions(path: pathlib.Path) -> dict[int, str]:
    """line number -> name of the innermost function defined around it."""
    tree = ast.parse(path.read_text())
    out = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef):
            for line in range(node.lineno, node.end_lineno + 1):
                if line not in out or node.lineno > out[line][1]:
                    out[line] = (node.name, node.lineno)
    return {k: v[0] for k, v in out.items()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--calls", type=int, default=30)
    p.add_argument("--open", action="store_true", help="the gap opened: the event-free path alone")
    p.add_argument("--top", type=int, default=25)
    p.add_argument("--model", choices=MODELS, default=MODELS[0],
                   help="the bench's random simplified model (default) or the mean reference model")
    p.add_argument("--split", action="store_true",
                   help="no profile: time per call (stop active, gap opened) and the events' cost per switch")
    p.add_argument("--dt", type=float, default=None,
                   help="with --split: the integration step [s] (default: the solver's)")
    p.add_argument("--child", help=argparse.SUPPRESS)
    a = p.parse_args()
    if a.calls < 1:
        p.error(f"--calls must be at least 1, not {a.calls}")
    if a.dt is not None and not a.split:
        p.error("--dt applies to --split only (the profile runs the solver's own step)")
    if a.split and a.open:
        p.error("--split times both the stop active and the gap opened; --open applies to the profile")
    if a.child:
        return child(pathlib.Path(a.child), a.calls, a.open, a.model)
    if a.split:
        print(json.dumps(split(a.model, a.calls, a.dt), indent=2))
        return
    for tool in ("perf", "objdump", "nm"):
        if shutil.which(tool) is None:
            raise SystemExit(f"kernel_profile: needs `{tool}` on PATH")
    with tempfile.TemporaryDirectory(prefix="tubeid-kprof-") as tmp:
        tmp = pathlib.Path(tmp)
        env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp / "cache"), NUMBA_DEBUGINFO="1")
        cmd = [sys.executable, __file__, "--child", str(tmp / "funcs.json"), "--calls", str(a.calls),
               "--model", a.model]
        cmd += ["--open"] if a.open else []
        subprocess.run(["perf", "record", "-q", "-e", "cpu-clock", "-F", "10000", "-o", str(tmp / "perf.data"), *cmd],
                       env=env, check=True)
        script = subprocess.run(["perf", "script", "-F", "ip", "-i", str(tmp / "perf.data")], capture_output=True,
                                text=True, check=True).stdout
        ips = [int(x, 16) for x in script.split()]
        funcs = json.loads((tmp / "funcs.json").read_text())
        obj = tmp / "run_exact.o"
        obj.write_bytes(kernel_object(tmp / "cache"))
        nm = subprocess.run(["nm", "-S", "--defined-only", str(obj)], capture_output=True, text=True, check=True).stdout
        sym = next(line.split() for line in nm.splitlines() if line.split()[-1].startswith(KERNEL))
        k_value, k_size = int(sym[0], 16), int(sym[1], 16)
        lines = []
        dump = subprocess.run(["objdump", "--dwarf=decodedline", str(obj)], capture_output=True, text=True).stdout
        for row in dump.splitlines():
            f = row.split()
            if len(f) >= 3 and f[0].endswith(".py") and f[1].isdigit() and f[2].startswith("0x"):
                lines.append((int(f[2], 16), int(f[1])))
        lines.sort()
        addrs = [x[0] for x in lines]

    starts = sorted((addr, name) for name, addr in funcs.items())
    kernel_addr = next(addr for name, addr in funcs.items() if name.startswith(KERNEL))
    by_func, by_line = collections.Counter(), collections.Counter()
    for ip in ips:
        if kernel_addr <= ip < kernel_addr + k_size:
            by_func["_fastpath.run_exact"] += 1
            i = bisect.bisect_right(addrs, ip - kernel_addr + k_value) - 1
            while i > 0 and lines[i][1] == 0:  # line 0: compiler-generated, the previous line's
                i -= 1
            by_line[lines[i][1] if i >= 0 else 0] += 1
            continue
        i = bisect.bisect_right(starts, (ip, "\uffff")) - 1
        if i >= 0 and ip - starts[i][0] < 0x10000:
            by_func[short(starts[i][1])] += 1
    total = sum(by_func.values())
    if not total:
        raise SystemExit("kernel_profile: no sample fell in numba-compiled code")
    print(f"{total} samples in numba-compiled code ({len(ips)} in all); {a.model}, "
          f"{'gap opened' if a.open else 'stop active'}, {a.calls} calls of simulate")
    for name, c in by_func.most_common():
        print(f"  {100 * c / total:5.1f} %  {name}")
    where = {f: enclosing_functions(SOLVER / f) for f in FILES}
    text = {f: (SOLVER / f).read_text().splitlines() for f in FILES}
    print(f"\nrun_exact by source line (top {a.top}); that line in each candidate file (function: text):")
    for line, c in by_line.most_common(a.top):
        print(f"  {100 * c / total:5.1f} %  line {line}")
        for f in FILES:
            if line in where[f]:
                print(f"           {f[1:-3]:8s} {where[f][line]}: {text[f][line - 1].strip()[:80]}")


if __name__ == "__main__":
    main()
