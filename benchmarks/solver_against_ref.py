"""The transient solver of this checkout against the solver of another git revision, in one process.

    python benchmarks/solver_against_ref.py [--ref REV] [--repeat 5] [--duration 220]

The reference solver is read from ``git show REV:tubeid/dynamics/solver.py`` (the single-module
solver before it became a package; default: the last commit of main that has it) into a
temporary module: it is importable here only, never from the package. Both solvers integrate
the same realisations of the paper's stochastic simplified model (random K_B at δ = 0.45, random
load spectrum at δ_F = 0.04, Gaussian loads) interleaved, best of ``--repeat``, and the script
prints the split of one realisation (load generation, tables, fast path, events, PSD) and the
ratios new/reference. The fast path is the same integration with the gap opened (no contact);
events are the difference. Timings are only meaningful as ratios (the machine is shared); the
default clock is this thread's CPU time (``--clock wall`` for elapsed time), less disturbed by
other processes.

``--processes N``: instead, N pairs of fresh processes, the reference's and this checkout's
alternated, each timing only its own solver (best of ``--repeat``) on the same inputs; prints each
pair's integration times and ratio. Two solvers loaded in one process run at different speeds (the
second one loaded is slower on the event-free path, in either order), so this is the unbiased
comparison. ``--dt-load`` (s): the load sampling (default 2 ms, ``ResponseSettings``'; the
solver's step is set by f_max either way).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def load_reference(ref: str):
    src = subprocess.run(["git", "-C", ROOT, "show", f"{ref}:tubeid/dynamics/solver.py"], check=True,
                         capture_output=True, text=True).stdout
    d = os.path.join(tempfile.gettempdir(), f"tubeid-ref-solver-{ref}")  # stable: numba caches it
    os.makedirs(d, exist_ok=True)
    path = os.path.join(d, "reference_solver.py")
    if not os.path.exists(path) or open(path).read() != src:
        with open(path, "w") as f:
            f.write(src)
    spec = importlib.util.spec_from_file_location("reference_solver", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["reference_solver"] = mod
    spec.loader.exec_module(mod)
    return mod


def realisation(k: int, duration: float, delta: float = 0.45, delta_f: float = 0.04, seed: int = 1,
                clock=time.perf_counter, dt_load: float = 2e-3):
    """(M, D, K, loads, stops args, seconds of load generation) of realisation k."""
    from tubeid.dynamics.response import _load_points, realisation_streams
    from tubeid.mechanics.library import builtin_spec
    from tubeid.mechanics.reduction import reduce
    from tubeid.uncertainty.loads import coherent_forces, randomised
    from tubeid.uncertainty.processes import gaussian_loads
    from tubeid.uncertainty.random_matrices import Dispersion, sg_plus
    from tubeid.uncertainty.random_models import germs_from_rngs, random_subsystem

    model = reduce(builtin_spec("paper-simplified"))
    load = coherent_forces()
    B = model.load_matrix(_load_points(load))
    C = model.sensor_matrix()
    stops = [(tuple(b), s.gap, s.stiffness) for b, s in zip(model.stop_vectors(), model.spec.stops)]
    streams = realisation_streams(seed, k)
    t0 = clock()
    MB, DB, KB = random_subsystem(model.subsystem, Dispersion(stiffness=delta), 0, [k],
                                  germs=germs_from_rngs(model.subsystem.n, [streams[0]]))
    M, D, K = (a[0] for a in model.matrices(MB, DB, KB))
    spectrum = randomised(load, sg_plus(len(load.names), delta_f, rng=streams[1]))
    F = gaussian_loads(spectrum, duration, dt_load, [streams[2]])[0]
    return (M, D, K, B, C, F, stops), clock() - t0


_FIRST_CALL = """
import sys, time
sys.path.insert(0, {bench!r})
import solver_against_ref as b
mod = b.load_reference({ref!r}) if {which!r} == "ref" else __import__("tubeid.dynamics.solver", fromlist=["x"])
case, _ = b.realisation(0, 3.0)
M, D, K, B, C, F, stops = case
st = [mod.Stop(b=x, gap=g, stiffness=k) for x, g, k in stops]
w, c = time.perf_counter(), time.process_time()
mod.simulate(M, D, K, st, B, C, F, 1e-3)
print(time.perf_counter() - w, time.process_time() - c)
"""


def compile_times(ref: str, n: int) -> None:
    """First call of the exact method in fresh processes with an empty numba cache, both solvers
    alternately: wall and CPU seconds (the kernels' compilation dominates)."""
    load_reference(ref)  # write the reference module once, outside the timed processes
    out = {"ref": [], "new": []}
    for _ in range(n):
        for which in ("ref", "new"):
            with tempfile.TemporaryDirectory() as cache:
                env = dict(os.environ, NUMBA_CACHE_DIR=cache)
                code = _FIRST_CALL.format(bench=os.path.dirname(os.path.abspath(__file__)), ref=ref, which=which)
                res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
                out[which].append(tuple(float(v) for v in res.stdout.split()[-2:]))
    for which, v in out.items():
        print(f"{which}: first call with an empty numba cache, wall " + ", ".join(f"{w:.1f}" for w, _ in v)
              + " s; CPU " + ", ".join(f"{c:.1f}" for _, c in v) + " s")
    print(f"ratio new/ref (CPU, mean): {np.mean([c for _, c in out['new']]) / np.mean([c for _, c in out['ref']]):.2f}; "
          f"load average {os.getloadavg()[0]:.2f}")


def process_pairs(a) -> None:
    """--processes: a.processes pairs of child processes (reference first, then this checkout), each
    running one solver only; prints each pair's integration and event-free times and ratios."""
    load_reference(a.ref)  # write the reference module once, outside the timed processes
    args = [sys.executable, os.path.abspath(__file__), "--ref", a.ref, "--repeat", str(a.repeat), "--duration",
            str(a.duration), "--realisations", str(a.realisations), "--clock", a.clock, "--dt-load", str(a.dt_load)]
    for which in ("ref", "new"):  # compile or load each solver's numba cache outside the timed pairs
        subprocess.run(args[:1] + [args[1], "--ref", a.ref, "--repeat", "1", "--duration", "3", "--only", which],
                       check=True, capture_output=True)
    ratios = []
    for i in range(a.processes):
        t = {}
        for which in ("ref", "new"):
            out = subprocess.run(args + ["--only", which], check=True, capture_output=True, text=True).stdout
            t[which] = [float(v) for v in out.split()[-2:]]
        ratios.append(t["ref"][0] / t["new"][0])
        print(f"pair {i + 1}: integration {t['ref'][0]:.4f} s ({a.ref}) against {t['new'][0]:.4f} s (this checkout), "
              f"{ratios[-1]:.2f}x; event-free path {t['ref'][1]:.4f} s against {t['new'][1]:.4f} s, "
              f"{t['ref'][1] / t['new'][1]:.2f}x", flush=True)
    print(f"integration ratio {a.ref}/this checkout: median {np.median(ratios):.2f}x over {a.processes} pairs "
          f"({a.realisations} realisation(s) of {a.duration:g} s, load sampled at {a.dt_load:g} s, best of "
          f"{a.repeat}, {a.clock} time); load average {os.getloadavg()[0]:.2f}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ref", default="cd43bc9")
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--duration", type=float, default=220.0)
    p.add_argument("--realisations", type=int, default=1)
    p.add_argument("--clock", choices=("cpu", "wall"), default="cpu")
    p.add_argument("--compile", type=int, default=0, metavar="N",
                   help="instead: time the first call (cold numba cache) of each solver in N fresh processes each")
    p.add_argument("--dt-load", type=float, default=2e-3)
    p.add_argument("--processes", type=int, default=0, metavar="N",
                   help="instead: N pairs of fresh processes, one solver each, alternated")
    p.add_argument("--only", choices=("ref", "new"), help=argparse.SUPPRESS)  # a child of --processes
    a = p.parse_args()
    if a.compile:
        return compile_times(a.ref, a.compile)
    if a.processes:
        return process_pairs(a)
    clock = time.thread_time if a.clock == "cpu" else time.perf_counter
    from tubeid.dynamics.spectra import psd_matrix

    old = load_reference(a.ref) if a.only != "new" else None  # a child of --processes loads its solver only
    new = None if a.only == "ref" else importlib.import_module("tubeid.dynamics.solver")
    cases = [realisation(k, a.duration, clock=clock, dt_load=a.dt_load) for k in range(a.realisations)]
    t_load = min(c[1] for c in cases)

    def run(mod, case, opened=False):
        M, D, K, B, C, F, stops = case[0]
        st = [mod.Stop(b=b, gap=1e9 if opened else g, stiffness=k) for b, g, k in stops]
        t0 = clock()
        y = mod.simulate(M, D, K, st, B, C, F, a.dt_load, output_dt=3e-3, discard=2.0).observations.values[0]
        return clock() - t0, y

    if a.only:  # one solver in this process: print its best integration and fast-path times
        mod = old if a.only == "ref" else new
        run(mod, (cases[0][0][:5] + (cases[0][0][5][:3001],) + cases[0][0][6:], 0))
        best = [min(sum(run(mod, c, opened)[0] for c in cases) / len(cases) for _ in range(a.repeat))
                for opened in (False, True)]
        print(*best)
        return
    for mod in (old, new):  # compile / load the caches
        run(mod, (cases[0][0][:5] + (cases[0][0][5][:3001],) + cases[0][0][6:], 0))
    best = {}
    for _ in range(a.repeat):
        for name, mod in (("ref", old), ("new", new)):
            for opened in (False, True):
                t = sum(run(mod, c, opened)[0] for c in cases) / len(cases)
                key = (name, opened)
                best[key] = min(best.get(key, np.inf), t)
    y = run(new, cases[0])[1]
    t0 = clock()
    psd_matrix(y, 3e-3, segment_seconds=8.0)
    t_psd = clock() - t0
    t_load = min(t_load, min(realisation(0, a.duration, clock=clock, dt_load=a.dt_load)[1] for _ in range(3)))
    print(f"load average {os.getloadavg()[0]:.2f}; {a.realisations} realisation(s) of {a.duration:g} s, best of "
          f"{a.repeat}, {a.clock} time")
    print(f"load generation {t_load:.4f} s, PSD {t_psd:.4f} s (common to both)")
    for name in ("ref", "new"):
        full, fast = best[(name, False)], best[(name, True)]
        print(f"{name}: integration {full:.4f} s = fast path {fast:.4f} s + events {full - fast:.4f} s; "
              f"per realisation {t_load + full + t_psd:.4f} s")
    r = lambda k: best[("new", k)] / best[("ref", k)]  # noqa: E731
    ev = (best[("new", False)] - best[("new", True)]) / (best[("ref", False)] - best[("ref", True)])
    tot = (t_load + best[("new", False)] + t_psd) / (t_load + best[("ref", False)] + t_psd)
    print(f"ratios new/ref: integration {r(False):.3f}, fast path {r(True):.3f}, events {ev:.3f}, per realisation {tot:.3f}")


if __name__ == "__main__":
    main()
