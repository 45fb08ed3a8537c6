"""The driver: ``simulate`` checks its arguments, picks each realisation's step and runs the
chosen method, registered as data in :data:`METHODS`."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from tubeid._validation import allocation, one_of, positive
from tubeid.dynamics.solver._base import Stop, TransientResult, assemble_result
from tubeid.dynamics.solver._checks import prepare
from tubeid.dynamics.solver._determinism import one_blas_thread
from tubeid.dynamics.solver._exact import integrate_exact
from tubeid.dynamics.solver._step import (EXACT_RULE, SYMPLECTIC_EULER_RULE, StepRule, highest_frequency,
                                          refuse_substeps, step_for)
from tubeid.dynamics.solver._symplectic import integrate_symplectic
from tubeid.errors import Described

__all__ = ["Method", "METHODS", "choose_step", "check_substeps", "simulate", "simulate_with_diagnostics"]


class Method(NamedTuple):
    """An integration method: its step rule and its integrator
    ``integrate(problem, r, h, f_max, y_out, sumsq, contact_time, n_events, refine_all=, diagnose=) -> dict``
    (writes realisation r's outputs, returns diagnostics)."""

    step_rule: StepRule
    integrate: Callable[..., dict]
    exact_events: bool  # contact time and events located exactly (else sampled at step ends)


#: The methods of ``simulate(method=...)``.
METHODS = {
    "exact": Method(EXACT_RULE, integrate_exact, True),
    "symplectic-euler": Method(SYMPLECTIC_EULER_RULE, integrate_symplectic, False),
}


def choose_step(f_max: float, dt_load: float, output_dt: float = 3e-3, method: str = "exact",
                dt: float | None = None) -> float:
    """Integration step (s) for highest frequency ``f_max`` (Hz).

    Parameters
    ----------
    f_max : float
        Highest frequency with every stop closed (Hz, see :func:`highest_frequency`).
    dt_load, output_dt : float
        Load and output sampling (s); the step divides both.
    method : str
        A key of :data:`METHODS`.
    dt : float, optional
        A user step: checked (must divide dt_load and output_dt; refused when unstable or able to
        hide contacts, warned when inaccurate) and returned.

    Returns
    -------
    float
        dt=None: the largest step dividing dt_load and output_dt within the method's default
        rule (exact: dt <= 1/(4 f_max); symplectic Euler: 2π f_max dt <= 0.25).
    """
    one_of("method", method, METHODS)
    return step_for(METHODS[method].step_rule, f_max, dt_load, output_dt, dt)


def check_substeps(M: ArrayLike, K: ArrayLike, stops: Sequence[Stop], duration: float, dt_load: float,
                   output_dt: float = 3e-3, method: str = "exact", dt: float | None = None,
                   duration_field: str = "duration") -> int:
    """The sub-steps one realisation of ``duration`` takes; refused beyond ``tubeid.io.max-substeps``.

    ``simulate`` makes this check itself, for every realisation before any is integrated; a caller
    calls it to refuse before preparing the loads.

    Parameters
    ----------
    M, K : array (N, N)
        Mass and stiffness without the stops (symmetric, SI units).
    stops : sequence of Stop
        The stops, as ``simulate`` takes them (a refusal names ``stops[i].stiffness``).
    duration : float
        Integrated time [s] of one realisation.
    dt_load, output_dt, method, dt
        As for :func:`simulate`.
    duration_field : str
        How a refusal names the duration (e.g. ``"settings.duration"``).

    Returns
    -------
    int
        ceil(duration / step) with the step of :func:`choose_step`.
    """
    one_of("method", method, METHODS)
    stops = tuple(stops)
    f_max = highest_frequency(M, K, stops)
    rule = METHODS[method].step_rule
    h = step_for(rule, f_max, dt_load, output_dt, dt)
    return refuse_substeps(rule, method, h, f_max, positive("duration", duration, "s"), np.asarray(M, dtype=float),
                           np.asarray(K, dtype=float), stops, duration_field)


def simulate(M: ArrayLike, D: ArrayLike, K: ArrayLike, stops: Sequence[Stop], B: ArrayLike, C: ArrayLike,
             loads: ArrayLike, dt_load: float, *, output_dt: float = 3e-3, dt: float | None = None,
             method: str = "exact", keep: str = "series", discard: float = 0.0,
             sensor_names: Sequence[str] | None = None) -> TransientResult:
    """Transient response of M q'' + D q' + K q + Σ_s b_s f_s(b_sᵀ q) = B F(t), y = C q, from rest.

    Parameters
    ----------
    M, D, K : array (N, N) or (R, N, N)
        Mass, damping, stiffness (real, symmetric; M and K positive definite, D semi-definite; SI
        units). A stack is realisation-wise; a single matrix is shared by every realisation.
    stops : sequence of Stop
        f_s(u) = k_s (|u| - g_s) sign(u) for |u| > g_s, else 0. At most 3 with a gap > 0. Their
        labels (the name, default ``stop<i>``) must be distinct.
    B : array (N, m)
        Load matrix (real).
    C : array (n_obs, N)
        Observation matrix (real).
    loads : array (R, n_t, m) or (n_t, m)
        Samples of F at t = i dt_load (real), read as their continuous piecewise-linear interpolant.
        Complex arrays are refused (never truncated to their real part); bools and strings are not
        numbers.
    dt_load : float
        Load sampling (s).
    output_dt : float
        Observation sampling (s), default 3 ms; at most the record's duration (n_t − 1) dt_load.
    dt : float, optional
        Integration step (s); None: per realisation from :func:`choose_step`.
    method : {"exact", "symplectic-euler"}
        See :data:`METHODS` and the package docstring.
    keep : {"series", "stats"}
        Store the observation series, or only the statistics.
    discard : float
        Transient (s) removed from the series and the statistics (rounded up to the output grid).
    sensor_names : sequence of str, optional
        Labels of the n_obs outputs, distinct strings (default y0, y1, ...).

    Returns
    -------
    TransientResult
        Outputs at t = j output_dt, discard <= t <= T = (n_t - 1) dt_load.
    """
    return _run(M, D, K, stops, B, C, loads, dt_load, output_dt, dt, method, keep, discard, sensor_names, False,
                False)[0]


def simulate_with_diagnostics(M: ArrayLike, D: ArrayLike, K: ArrayLike, stops: Sequence[Stop], B: ArrayLike,
                              C: ArrayLike, loads: ArrayLike, dt_load: float, *, output_dt: float = 3e-3,
                              dt: float | None = None, method: str = "exact", keep: str = "series",
                              discard: float = 0.0, sensor_names: Sequence[str] | None = None,
                              refine_all: bool = False) -> tuple[TransientResult, list[dict]]:
    """``simulate`` plus one dict of diagnostics per realisation (steps; for the exact method the
    flagged sub-steps, switches, rescans, exact evaluations and table properties). Tests and
    benchmarks only: ``refine_all=True`` sends every sub-step of the exact method through the exact
    event path (every boundary searched), the reference for the pre-check."""
    return _run(M, D, K, stops, B, C, loads, dt_load, output_dt, dt, method, keep, discard, sensor_names, refine_all,
                True)


def _run(M, D, K, stops, B, C, loads, dt_load, output_dt, dt, method, keep, discard, sensor_names, refine_all,
         diagnose):
    P = prepare(M, D, K, stops, B, C, loads, dt_load, output_dt, discard, method, tuple(METHODS), keep, sensor_names)
    integrator = METHODS[method]
    R, n_obs, S = P.R, P.C.shape[0], len(P.stops)
    if keep == "series":
        allocation("output_dt", output_dt, 8.0 * R * P.n_keep * n_obs,
                   f"the series of {R} realisation(s): {P.n_keep} samples of {n_obs} output(s)")
    y_all = np.zeros((R, P.n_keep, n_obs)) if keep == "series" else None
    rms = np.zeros((R, n_obs))
    cf = np.zeros((R, S))
    ne = np.zeros((R, S), dtype=np.int64)
    dts = np.zeros(R)
    t_count = P.duration - P.j0 * P.output_dt  # counted time window
    f_cache, diagnostics, steps = {}, [], []
    for r in range(R):  # every realisation's step first: a refused cost is refused before any integration
        Mr, _, Kr = P.matrices(r)
        key = (r % len(P.M), r % len(P.K))
        if key not in f_cache:
            with one_blas_thread():
                f_max = highest_frequency(Mr, Kr, P.gapped)
            h = step_for(integrator.step_rule, f_max, P.dt_load, P.output_dt, dt)
            structure = Kr - sum((P.stops[i].stiffness * np.outer(P.stops[i].vector, P.stops[i].vector)
                                  for i in P.linear_index), np.zeros_like(Kr))  # K without the zero-gap stops
            refuse_substeps(integrator.step_rule, method, h, f_max, P.duration, Mr, structure, P.stops, "loads",
                            Described(f"{P.loads.shape[1]} samples at dt_load = {P.dt_load:g} s"))
            f_cache[key] = f_max, h
        steps.append(f_cache[key])
    for r in range(R):
        f_max, h = steps[r]
        y_buf = y_all[r] if y_all is not None else np.zeros((0, n_obs))
        sumsq = np.zeros(n_obs)
        ct = np.zeros(len(P.gapped))
        nev = np.zeros(len(P.gapped), dtype=np.int64)
        diagnostics.append(integrator.integrate(P, r, h, f_max, y_buf, sumsq, ct, nev, refine_all=refine_all,
                                                diagnose=diagnose))
        dts[r] = h
        rms[r] = np.sqrt(sumsq / P.n_keep)
        cf[r, list(P.gapped_index)] = ct / t_count if t_count > 0 else 0.0
        ne[r, list(P.gapped_index)] = nev
        cf[r, list(P.linear_index)] = 1.0
    return assemble_result(y_all, rms, cf, ne, dts, P.stops, P.sensors, P.output_dt, P.j0, method, P.discard), diagnostics
