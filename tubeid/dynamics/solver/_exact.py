"""Method ``"exact"``: per realisation, the regime tables, the scratch and one call of the kernel.

The system is piecewise linear; in each regime its modal equations are integrated exactly for the
piecewise-linear load (``_regimes``), switching instants are located on the exact closed form
(``_events``), and the main loop takes blocks of sub-steps between events (``_fastpath``).
Between events the solution is exact whatever the step: the step sets only the resolution of the
event pre-check.
"""

from __future__ import annotations

import math

import numpy as np

from tubeid.dynamics.solver._fastpath import run_exact
from tubeid.dynamics.solver._regimes import cached_tables, initial_state
from tubeid.dynamics.solver._work import N_STATS, STATS, XL, make_work

__all__ = ["integrate_exact"]


def integrate_exact(problem, r: int, h: float, f_max: float, y_out, sumsq, contact_time, n_events,
                    refine_all: bool = False, diagnose: bool = False) -> dict:
    """Realisation r of a :class:`~tubeid.dynamics.solver._checks.Problem` at sub-step h (s), f_max
    (Hz) the highest frequency with the stops closed; writes the outputs into y_out (n_keep or 0,
    n_obs), sumsq (n_obs,), contact_time (S,) (s) and n_events (S,) of the gapped stops.
    The tables come from :func:`~tubeid.dynamics.solver._regimes.cached_tables` (built once per system
    and process). Returns diagnostics: the counters of ``_work``, and with ``diagnose`` the
    table properties (condition number of the eigenvectors, halved conjugate pairs, modes)."""
    M, D, K = problem.matrices(r)
    ns = int(round(problem.dt_load / h))
    T, info = cached_tables(M, D, K, problem.gapped, problem.B, problem.C, h, ns, 2 * math.pi * f_max)
    loads = problem.loads[r]
    W = make_work(T, problem.C.shape[0])
    nx = 2 * T.lam_re.shape[1]
    W.X[XL, :nx] = initial_state(info, loads[0], (loads[1] - loads[0]) / problem.dt_load)
    stats = np.zeros(N_STATS, dtype=np.int64)
    steps = run_exact(loads, problem.dt_load, ns, int(round(problem.output_dt / h)), problem.j0, np.int64(0), T, W,
                      y_out, sumsq, contact_time, n_events, bool(refine_all), stats)
    out = {"steps": int(steps), **{name: int(stats[slot]) for slot, name in enumerate(STATS)}}
    if diagnose:
        out.update(cond_V=max(float(np.linalg.cond(V)) for V in info["V"]), half_modes=info["half_modes"],
                   n_modes=info["n_modes"])
    return out
