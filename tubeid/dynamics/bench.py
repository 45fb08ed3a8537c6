"""Benchmark of the transient solver on the paper's chain, and this machine's FLOP rate.

``bench_transient`` times realisations of the paper's stochastic simplified model end to end
(random stiffness, random load spectrum, Gaussian load generation, exact integration, Welch PSD),
several per ``simulate`` call as the study's tasks run them, against the same chain with the
straightforward per-step numpy loop (``simulate_baseline``), in the same process, and splits the
integration into its fast path (same run with the gap opened: no contact, same step and tables)
and event handling; ``compile_seconds`` times the kernels' compilation in a new process. ``measure_flop_rate`` measures this core's
double-precision FLOP rate with a numba loop of independent fused multiply-adds on L1-resident
arrays (SIMD peak-like throughput) and with scalar FMA chains; the flop bound of the fast path is
its flop count (``exact_step_flops``) divided by the SIMD rate.
"""

from __future__ import annotations

import math
import time

import numba
import numpy as np

from tubeid._validation import allocation, integer, real, seed as _seed
from tubeid.dynamics.solver import Stop, choose_step, highest_frequency, simulate
from tubeid.dynamics.solver._checks import prepare
from tubeid.dynamics.solver._regimes import BLOCK_MAX, forget_tables
from tubeid.dynamics.solver._simulate import METHODS, simulate_with_diagnostics

__all__ = ["bench_transient", "check_transient", "measure_flop_rate", "simulate_baseline", "exact_step_flops",
           "compile_seconds", "MAX_PSD_SETS"]


# ----------------------------------------------------------------------------------------------
# Baseline and flop model of the solver
# ----------------------------------------------------------------------------------------------


def simulate_baseline(M, D, K, stops, B, C, loads, dt_load, *, output_dt=3e-3, dt=None):
    """Straightforward reference implementation for benchmarks: symplectic Euler, one numpy
    matrix-vector product per step in a Python loop (one realisation, shared matrices).

    Returns ``(series, h)``: the observation series (n_out, n_obs) at output_dt from t = 0 and the
    step h. dt=None uses the symplectic-Euler default rule of ``choose_step``.
    """
    P = prepare(M, D, K, stops, B, C, loads, dt_load, output_dt, 0.0, "symplectic-euler", tuple(METHODS), "series")
    if len(P.M) != 1 or len(P.K) != 1 or len(P.D) != 1 or P.R != 1:
        raise ValueError("simulate_baseline takes one realisation")
    M, D, K = P.matrices(0)
    N = M.shape[0]
    h = choose_step(highest_frequency(M, K, P.gapped), P.dt_load, P.output_dt, "symplectic-euler", dt)
    ns = int(round(P.dt_load / h))
    out_every = int(round(P.output_dt / h))
    Minv = np.linalg.inv(M)
    Afull = np.hstack([-Minv @ K, -Minv @ D])  # first-order update on [q; v]: a = -MiK q - MiD v + MiB F - Mib f_stop
    MiB = Minv @ P.B
    bmat = np.array([s.vector for s in P.gapped]).reshape(len(P.gapped), N)
    Mib = Minv @ bmat.T
    gaps = np.array([s.gap for s in P.gapped])
    kst = np.array([s.stiffness for s in P.gapped])
    x = np.zeros(2 * N)
    out = [P.C @ x[:N]]
    step = 0
    F = P.loads[0]
    for k in range(F.shape[0] - 1):
        for j in range(ns):
            th = j / ns
            f = (1 - th) * F[k] + th * F[k + 1]
            u = bmat @ x[:N]
            fs = kst * np.sign(u) * np.maximum(np.abs(u) - gaps, 0.0)
            a = Afull @ x + MiB @ f - Mib @ fs
            x[N:] += h * a
            x[:N] += h * x[N:]
            step += 1
            if step % out_every == 0:
                out.append(P.C @ x[:N])
    return np.array(out), h


def exact_step_flops(n_modes: int, n_stops: int, n_loads: int, steps_per_block: int, n_obs: int = 0,
                     steps_per_output: int = 1, steps_per_interval: int | None = None) -> float:
    """Floating-point operations per integration step of the exact method's fast path (useful
    work, padding excluded).

    Per step and stop, u and u' from the tabulated rows over [ζ; F_j; F'; 1]: 2 dot products of
    length 2 n_modes + 2 m + 1 (2 flops per term). Per block of ``steps_per_block`` steps, the
    diagonal advance (6 flops per mode). Per load interval (``steps_per_interval`` steps, default
    the block), the slope update of the homogeneous state (4 flops per mode and load). Per output,
    n_obs dot products of the same length. Event handling is excluded (timed separately).
    """
    spi = steps_per_block if steps_per_interval is None else steps_per_interval
    row = 2 * n_modes + 2 * n_loads + 1
    return (2 * n_stops * 2 * row + 6 * n_modes / steps_per_block + 4 * n_modes * n_loads / spi
            + n_obs * 2 * row / steps_per_output)


# ----------------------------------------------------------------------------------------------
# Machine FLOP rate
# ----------------------------------------------------------------------------------------------


@numba.njit(cache=True, fastmath={"contract"})
def _fma_simd(b, c, n_iter):
    acc = np.empty(64)
    for i in range(64):
        acc[i] = 0.5 + 1e-3 * i
    for _ in range(n_iter):
        for i in range(64):
            acc[i] = acc[i] * b + c
    return acc.sum()


@numba.njit(cache=True, fastmath={"contract"})
def _fma_scalar(b, c, n_iter):
    x0 = x1 = x2 = x3 = x4 = x5 = x6 = x7 = 0.5
    y0 = y1 = y2 = y3 = y4 = y5 = y6 = y7 = 0.25
    for _ in range(n_iter):
        x0 = x0 * b + c
        x1 = x1 * b + c
        x2 = x2 * b + c
        x3 = x3 * b + c
        x4 = x4 * b + c
        x5 = x5 * b + c
        x6 = x6 * b + c
        x7 = x7 * b + c
        y0 = y0 * b + c
        y1 = y1 * b + c
        y2 = y2 * b + c
        y3 = y3 * b + c
        y4 = y4 * b + c
        y5 = y5 * b + c
        y6 = y6 * b + c
        y7 = y7 * b + c
    return x0 + x1 + x2 + x3 + x4 + x5 + x6 + x7 + y0 + y1 + y2 + y3 + y4 + y5 + y6 + y7


def _rate(fn, flops_per_iter, seconds):
    fn(0.999999, 1e-7, 10)
    n = 1000
    while True:
        t0 = time.perf_counter()
        fn(0.999999, 1e-7, n)
        dt = time.perf_counter() - t0
        if dt > seconds:
            return flops_per_iter * n / dt
        n *= 4


def measure_flop_rate(seconds=0.1, repeat=3):
    """(simd, scalar) double-precision FLOP/s of this core (1 FMA = 2 flops), best of ``repeat``.

    simd: acc[i] = acc[i] b + c over a 64-double local array (numba vectorises it: AVX-512 FMAs,
    a peak-like rate). scalar: 16 independent scalar FMA chains (full pipeline, no SIMD), the
    rate of well-scheduled unvectorised code."""
    simd = max(_rate(_fma_simd, 128, seconds) for _ in range(repeat))
    scalar = max(_rate(_fma_scalar, 32, seconds) for _ in range(repeat))
    return simd, scalar


# ----------------------------------------------------------------------------------------------
# Benchmark
# ----------------------------------------------------------------------------------------------


#: The most independent sets ``psd_sets`` takes: each set integrates ``n_psd_realisations`` realisations at two
#: steps (about 1 s per set of 4 here at the default settings), and the scatter of the step error is
#: summarised by quantiles that 1000 sets already give to within a few percent.
MAX_PSD_SETS = 1000


def check_transient(*, duration: float = 220.0, seed: int = 1, baseline_window: float = 1.0, bands_hz: float = 5.0,
                    n_psd_realisations: int = 4, realisations_per_call: int = 4, repeat: int = 3, psd_sets: int = 1,
                    dt_load: float | None = None, names: dict[str, str] | None = None) -> tuple[int, "ResponseSettings"]:
    """Check the arguments of :func:`bench_transient`, before any work.

    Parameters
    ----------
    duration, seed, baseline_window, bands_hz, n_psd_realisations, realisations_per_call, repeat, psd_sets, dt_load
        As for :func:`bench_transient`.
    names : dict, optional
        How a refusal names an argument, e.g. ``{"dt_load": "--dt-load"}`` (default: its own name).

    Returns
    -------
    psd_sets : int
        The set count.
    settings : ResponseSettings
        The response settings of the run (``dt_load`` the default when None).

    Raises
    ------
    SpecificationError
        An argument out of its range: ``dt_load`` also when it does not resolve the load's band, or
        when the loads of one simulate call (``realisations_per_call`` realisations) and one synthesis
        would take more than half of this machine's memory.
    """
    from tubeid.dynamics.response import ResponseSettings
    from tubeid.errors import SpecificationError
    from tubeid.uncertainty.loads import coherent_forces
    from tubeid.uncertainty.processes import resolving_step, synthesis_grid

    name = (lambda k: (names or {}).get(k, k))
    psd_sets = integer(name("psd_sets"), psd_sets, minimum=1, maximum=MAX_PSD_SETS)
    for key, value in (("n_psd_realisations", n_psd_realisations), ("realisations_per_call", realisations_per_call),
                       ("repeat", repeat)):
        integer(name(key), value, minimum=1)
    _seed(name("seed"), seed)
    st = ResponseSettings(duration=duration)
    real(name("baseline_window"), baseline_window, unit="s", low=0.0, high=st.duration, low_open=True)
    real(name("bands_hz"), bands_hz, unit="Hz", low=0.0, high=100.0, low_open=True)
    if dt_load is None:
        return psd_sets, st
    load = coherent_forces()
    dt_load = resolving_step(name("dt_load"), dt_load, load.band)
    try:
        st = ResponseSettings(duration=st.duration, dt_load=dt_load)
    except SpecificationError as exc:  # the only new value is dt_load
        raise SpecificationError(name("dt_load"), dt_load, exc.rule) from None
    n_t, N = synthesis_grid(st.duration, st.dt_load)
    m = len(load.names)
    allocation(name("dt_load"), dt_load, 8.0 * m * (realisations_per_call * n_t + (N // 2 + 1) + N / 2),
               f"the loads of {realisations_per_call} realisation(s) of {m} load(s) over {n_t} samples and one synthesis")
    return psd_sets, st


def bench_transient(duration: float = 220.0, delta: float = 0.45, delta_f: float = 0.04, seed: int = 1,
                    baseline_window: float = 1.0, bands_hz: float = 5.0, n_psd_realisations: int = 4,
                    realisations_per_call: int = 4, repeat: int = 3, compile_time: bool = False,
                    psd_sets: int = 1, dt_load: float | None = None, names: dict[str, str] | None = None) -> dict:
    """Realisations of the paper's stochastic simplified model, end to end, on one core.

    A realisation: random stiffness (δ = ``delta``), random load spectrum (the paper's 7-point load
    with δ_F = ``delta_f``), Gaussian load generation, exact integration, Welch PSD at the stop
    node. ``realisations_per_call`` realisations go through one ``simulate`` call, as the paper
    study's tasks do (4 per task); ``seconds_per_realisation`` is that batch's time divided by its
    size (best of ``repeat``), ``seconds_per_realisation_one_per_call`` the same with one
    realisation per call. The baseline is the same chain with the straightforward per-step numpy
    loop (``simulate_baseline``, timed on ``baseline_window`` s and extrapolated linearly: its cost
    per step is constant).

    ``seconds_fast_path``: the same integration with the gaps opened (no contact: same step,
    tables and outputs); ``seconds_event_handling`` is the difference, shared by the
    ``flagged_steps`` (sub-steps sent to the exact event path). ``psd_error_vs_fine_step``: max over
    ``bands_hz``-wide bands of 0–100 Hz of the relative difference of the band-averaged PSD at the
    stop node between the default step and a 4× smaller step, each averaged over
    ``n_psd_realisations`` realisations run at both steps on the same loads (the runs are chaotic:
    a single realisation scatters by 2–5 % per band whatever the solver). Memory: the peak traced
    allocation of one realisation plus 200 kept results (PSD + statistics), per worker.
    ``compile_time``: also time a new process that compiles the kernels into an empty numba cache
    against one that loads them (``seconds_compile``). ``psd_sets`` > 1: the same error for that many
    independent sets of ``n_psd_realisations`` (the first is the one above), summarised as
    ``psd_error_sets`` (median, 90th percentile, maximum): the statistic's own scatter, against which
    a change of the solver is judged (at most :data:`MAX_PSD_SETS`). ``dt_load``: the load sampling [s]
    (default: ``ResponseSettings``'). Every argument is checked before any work (:func:`check_transient`;
    ``names``: how a refusal names them).
    """
    import tracemalloc

    from tubeid.dynamics.response import ResponseSettings, _load_points, realisation_streams
    from tubeid.dynamics.spectra import psd_matrix
    from tubeid.mechanics.library import builtin_spec
    from tubeid.mechanics.reduction import reduce
    from tubeid.uncertainty.loads import coherent_forces, randomised
    from tubeid.uncertainty.processes import gaussian_loads
    from tubeid.uncertainty.random_matrices import Dispersion, sg_plus
    from tubeid.uncertainty.random_models import germs_from_rngs, random_subsystem

    psd_sets, st = check_transient(duration=duration, seed=seed, baseline_window=baseline_window, bands_hz=bands_hz,
                                   n_psd_realisations=n_psd_realisations, realisations_per_call=realisations_per_call,
                                   repeat=repeat, psd_sets=psd_sets, dt_load=dt_load, names=names)
    model = reduce(builtin_spec("paper-simplified"))
    load = coherent_forces()
    B = model.load_matrix(_load_points(load))
    C = model.sensor_matrix()
    stops = [Stop(b=tuple(b), gap=s.gap, stiffness=s.stiffness) for b, s in zip(model.stop_vectors(), model.spec.stops)]
    opened = [Stop(b=s.b, gap=1e9, stiffness=s.stiffness) for s in stops]

    def draw(k, spectrum_dispersion=delta_f, seed_=seed, out=None):
        """Matrices and loads of realisation k (the response chain's streams); the loads written
        into ``out`` (1, n_t, m) if given, as ``simulate_responses`` writes a batch's rows."""
        streams = realisation_streams(seed_, k)
        MB, DB, KB = random_subsystem(model.subsystem, Dispersion(stiffness=delta), 0, [k],
                                      germs=germs_from_rngs(model.subsystem.n, [streams[0]]))
        M, D, K = (a[0] for a in model.matrices(MB, DB, KB))
        spectrum = load if spectrum_dispersion == 0 else randomised(load, sg_plus(len(load.names), spectrum_dispersion,
                                                                                   rng=streams[1]))
        return M, D, K, gaussian_loads(spectrum, st.duration, st.dt_load, [streams[2]], out=out)[0]

    def integrate(M, D, K, F, stops_=stops, dt=None):
        return simulate(M, D, K, stops_, B, C, F, st.dt_load, output_dt=st.output_dt, dt=dt,
                        discard=st.discard).observations.values

    def chain(ks):
        """(load generation, integration, PSD) seconds for realisations ks in one simulate call (their
        regime tables built in it, as a study's realisation does: the process's table cache emptied)."""
        forget_tables()
        t0 = time.perf_counter()
        F = np.empty((len(ks), int(round(st.duration / st.dt_load)) + 1, len(load.names)))
        drawn = [draw(k, out=F[i:i + 1]) for i, k in enumerate(ks)]
        t1 = time.perf_counter()
        M, D, K = (np.stack(a) for a in list(zip(*drawn))[:3])
        y = integrate(M, D, K, F)
        t2 = time.perf_counter()
        for r in range(len(ks)):
            psd_matrix(y[r], st.output_dt, segment_seconds=st.segment_seconds)
        return np.array([t1 - t0, t2 - t1, time.perf_counter() - t2]), (M, D, K, F)

    batch = list(range(realisations_per_call))
    # compile or load the kernels: realisation 0 over discard + 22 s (24 s at the default settings)
    M0, D0, K0, F0 = draw(0)
    integrate(M0[None], D0[None], K0[None], F0[None, :int(round((st.discard + 22.0) / st.dt_load)) + 1])
    best, best_one = None, None
    for _ in range(repeat):
        times, mats = chain(batch)
        best = times if best is None or times.sum() < best.sum() else best
        one = chain(batch[:1])[0]
        best_one = one if best_one is None or one.sum() < best_one.sum() else best_one
    n = len(batch)
    M, D, K, F = mats
    t_fast = math.inf
    for _ in range(repeat):
        forget_tables()
        t0 = time.perf_counter()
        integrate(M, D, K, F, stops_=opened)  # same f_max (the stops' stiffness counts), same step
        t_fast = min(t_fast, time.perf_counter() - t0)
    diag = simulate_with_diagnostics(M, D, K, stops, B, C, F, st.dt_load, output_dt=st.output_dt,
                                     discard=st.discard)[1]
    flagged = sum(d["flagged_steps"] for d in diag) / n
    switches = sum(d["switches"] for d in diag) / n
    n_b = int(round(baseline_window / st.dt_load)) + 1
    t0 = time.perf_counter()
    simulate_baseline(M[0], D[0], K[0], stops, B, C, F[0, :n_b], st.dt_load, output_dt=st.output_dt)
    t_base = (time.perf_counter() - t0) * duration / baseline_window
    f_max = highest_frequency(M[0], K[0], stops)
    h = choose_step(f_max, st.dt_load, st.output_dt)

    def psd_error(seed_):
        """Largest band error of the realisation-averaged PSD, default step against h/4."""
        coarse, fine = [], []
        for k in range(n_psd_realisations):  # chaotic runs: compare realisation-averaged PSDs
            Mk, Dk, Kk, Fk = draw(k, spectrum_dispersion=0, seed_=seed_)
            hk = choose_step(highest_frequency(Mk, Kk, stops), st.dt_load, st.output_dt)
            f, S = psd_matrix(integrate(Mk, Dk, Kk, Fk, dt=hk)[0], st.output_dt, segment_seconds=st.segment_seconds)
            coarse.append(S.real[:, 0, 0])
            fine.append(psd_matrix(integrate(Mk, Dk, Kk, Fk, dt=hk / 4)[0], st.output_dt,
                                   segment_seconds=st.segment_seconds)[1].real[:, 0, 0])
        p, p4 = np.mean(coarse, axis=0), np.mean(fine, axis=0)
        errs = []
        for lo in np.arange(0.0, 100.0, bands_hz):
            sel = (f >= lo) & (f < lo + bands_hz)
            errs.append(abs(p[sel].mean() / p4[sel].mean() - 1))
        return float(max(errs)), S

    first, S = psd_error(seed + 1000)
    set_errors = [first] + [psd_error(seed + 1000 * (j + 1))[0] for j in range(1, psd_sets)]
    tracemalloc.start()
    chain(batch[:1])
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    kept = S.nbytes + 64 * 8
    simd, _ = measure_flop_rate()
    steps = int(round(duration / h))
    ns = int(round(st.dt_load / h))
    flops = exact_step_flops(M.shape[1], len(stops), B.shape[1], min(ns, BLOCK_MAX), C.shape[0],
                             int(round(st.output_dt / h)), ns)
    per_real = best.sum() / n
    t_load, t_int, t_psd = best / n
    out = {
        "seconds_per_realisation": per_real,
        "seconds_load_generation": t_load,
        "seconds_integration": t_int,
        "seconds_psd": t_psd,
        "realisations_per_call": n,
        "seconds_per_realisation_one_per_call": float(best_one.sum()),
        "baseline_seconds_per_realisation": t_load + t_base + t_psd,
        "speedup": (t_load + t_base + t_psd) / per_real,
        "integration_speedup": t_base / t_int,
        "flop_bound_seconds": flops * steps / simd,
        "flop_bound_how": f"{flops:.0f} flops/step (exact_step_flops: fast path, events excluded) x {steps} steps / {simd / 1e9:.1f} GFLOP/s (numba FMA loop measured in this process)",
        "seconds_fast_path": t_fast / n,
        "seconds_event_handling": t_int - t_fast / n,
        "flagged_steps": flagged,
        "switches": switches,
        "microseconds_per_flagged_step": 1e6 * (t_int - t_fast / n) / max(flagged, 1),
        "psd_error_vs_fine_step": set_errors[0],
        "psd_error_bands_hz": bands_hz,
        "psd_error_realisations": n_psd_realisations,
        "integration_step_s": h,
        "f_max_hz": f_max,
        "memory_per_worker_200_realisations_mb": (peak + 200 * kept) / 2**20,
        "model": f"paper-simplified, N = {M.shape[1]}, delta = {delta}, delta_F = {delta_f}, {duration:g} s, 7-point load",
    }
    if psd_sets > 1:
        out["psd_error_sets"] = {"sets": psd_sets, "median": float(np.median(set_errors)),
                                 "p90": float(np.quantile(set_errors, 0.9)), "max": float(max(set_errors))}
    if compile_time:
        out.update(compile_seconds())
    return out


_COMPILE_SCRIPT = """
import time
t0 = time.perf_counter()
import numpy as np
from tubeid.dynamics.solver import Stop, simulate
t1 = time.perf_counter()
M = np.diag([1.0, 2.0]); K = np.array([[3e4, -1e4], [-1e4, 2e4]]); D = 1e-3 * K
simulate(M, D, K, [Stop((1.0, 0.0), 1e-4, 1e5)], np.ones((2, 1)), np.eye(2), np.ones((11, 1)), 1e-3)
print(time.perf_counter() - t1)
"""


def compile_seconds() -> dict:
    """Seconds of the first ``simulate`` call of a new process with an empty numba cache (the
    kernels are compiled) and with the cache that process wrote (they are loaded)."""
    import os
    import subprocess
    import sys
    import tempfile

    out = {}
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        for key in ("seconds_compile", "seconds_cache_load"):
            res = subprocess.run([sys.executable, "-c", _COMPILE_SCRIPT], env=env, capture_output=True, text=True,
                                 check=True)
            out[key] = float(res.stdout.strip().splitlines()[-1])
    return out
