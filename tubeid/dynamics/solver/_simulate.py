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
        Highest frequency with every stop closed (Hz, finite, > 0; see :func:`highest_frequency`).
    dt_load, output_dt : float
        Load and output sampling (s, finite, > 0); the step divides both.
    method : str
        A key of :data:`METHODS` (``"exact"`` or ``"symplectic-euler"``).
    dt : float, optional
        A user step (s, finite, > 0): checked (it must divide dt_load and output_dt within 1e-9
        relative; refused when it can hide contacts or is unstable, warned when inaccurate, see
        Raises and Warns) and returned as given.

    Returns
    -------
    float
        dt=None: the largest step dividing dt_load and output_dt within the method's default
        rule (exact: dt <= 1/(4 f_max); symplectic Euler: 2π f_max dt <= 0.25).

    Raises
    ------
    tubeid.errors.SpecificationError
        Naming the field: an unknown method; f_max, dt_load, output_dt or dt not a finite number
        > 0; a dt that does not divide dt_load or output_dt, or above the method's limit (exact:
        dt > 1/(2 f_max); symplectic Euler: 2π f_max dt >= 2); with dt=None, output_dt and dt_load
        without a common step.

    Warns
    -----
    UserWarning
        A dt above the method's accuracy limit (exact: dt > 1/(3 f_max); symplectic Euler:
        2π f_max dt > 0.5).
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
        Mass, damping, stiffness in the coordinates q (SI units): real, finite, symmetric (a
        relative asymmetry up to 1e-10 is taken as round-off and symmetrised); M and K positive
        definite, D positive semi-definite. A stack is realisation-wise (its R that of ``loads``);
        a single matrix, or a stack of one, is shared by every realisation.
    stops : sequence of Stop
        f_s(u) = k_s (|u| - g_s) sign(u) for |u| > g_s, else 0, u = b_sᵀ q; each b_s of length N.
        At most 3 with a gap > 0 (``_checks.MAX_STOPS``: their 3**S regimes are tabulated); a stop
        with a zero gap is a linear spring added to K. Their labels (the name, default ``stop<i>``)
        must be distinct.
    B : array (N, m) or (N,)
        Load matrix (real, finite); (N,) is one load (m = 1).
    C : array (n_obs, N) or (N,)
        Observation matrix (real, finite); (N,) is one output (n_obs = 1).
    loads : array (R, n_t, m) or (n_t, m)
        Samples of F at t = i dt_load, n_t >= 2 (real, finite; SI units, N for forces), read as
        their continuous piecewise-linear interpolant; (n_t, m) is one realisation. Complex arrays
        are refused (never truncated to their real part); bools and strings are not numbers.
    dt_load : float
        Load sampling (s), finite, > 0. The record lasts T = (n_t - 1) dt_load.
    output_dt : float
        Observation sampling (s), finite, > 0, default 3 ms; at most T, and commensurate with
        dt_load (the integration step divides both).
    dt : float, optional
        Integration step (s), checked as by :func:`choose_step` (it must divide dt_load and
        output_dt; refused above the method's limit, warned above its accuracy limit); None: per
        realisation from :func:`choose_step`.
    method : {"exact", "symplectic-euler"}
        See :data:`METHODS` and the package docstring.
    keep : {"series", "stats"}
        Store the observation series, or only the statistics.
    discard : float
        Transient (s) removed from the series and the statistics, in [0, T): the kept window
        starts at the first output sample at or after it, t0 = j0 output_dt, and must hold one.
    sensor_names : sequence of str, optional
        Labels of the n_obs outputs, distinct strings (default y0, y1, ...); one string is refused.

    Returns
    -------
    TransientResult
        Outputs at t = j output_dt, t0 <= t <= T; the statistics over [t0, T].

    Raises
    ------
    tubeid.errors.SpecificationError
        Before any integration, naming the field, its value and the rule, for an argument outside
        what is stated above (shapes, finiteness, symmetry, definiteness, realisation axes, stops,
        samplings, step, discard, labels, unknown method or keep), and for a series that would need
        more than a share of this machine's memory (``output_dt`` named).

    Warns
    -----
    UserWarning
        A given ``dt`` above the method's accuracy limit (see :func:`choose_step`).
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
