"""Method ``"symplectic-euler"``: the semi-implicit Euler of industrial modal-transient codes.

v += dt M⁻¹ (B F - D v - K q - Σ_s b_s f_s(b_sᵀ q)); q += dt v, with F the piecewise-linear load
at the start of the step. First order; stable for w_max dt < 2 (w_max with every stop closed).
Contact time and events are counted per step (u sampled at step ends).
"""

from __future__ import annotations

import numba
import numpy as np

from tubeid.dynamics.solver._determinism import one_blas_thread

__all__ = ["integrate_symplectic"]


@numba.njit(cache=True)
def _kernel(loads, ns, out_every, j0, h, MiK, MiD, MiB, Mib, bmat, gaps, kst, Cm, y_out, sumsq, contact_time,
            n_events):
    n_int = loads.shape[0] - 1
    N = MiK.shape[0]
    m = loads.shape[1]
    S = gaps.shape[0]
    n_obs = Cm.shape[0]
    q = np.zeros(N)
    v = np.zeros(N)
    a = np.zeros(N)
    f = np.zeros(m)
    fs = np.zeros(S)
    closed = np.zeros(S, np.bool_)
    store = y_out.shape[0] > 0
    count_from = j0 * out_every
    if j0 == 0 and store:
        for o in range(n_obs):
            y_out[0, o] = 0.0
    step = 0
    for k in range(n_int):
        for j in range(ns):
            th = j / ns
            for l in range(m):
                f[l] = (1 - th) * loads[k, l] + th * loads[k + 1, l]
            for s in range(S):
                u = 0.0
                for i in range(N):
                    u += bmat[s, i] * q[i]
                if u > gaps[s]:
                    fs[s] = kst[s] * (u - gaps[s])
                elif u < -gaps[s]:
                    fs[s] = kst[s] * (u + gaps[s])
                else:
                    fs[s] = 0.0
            for i in range(N):
                acc = 0.0
                for l in range(m):
                    acc += MiB[i, l] * f[l]
                for l in range(N):
                    acc -= MiK[i, l] * q[l] + MiD[i, l] * v[l]
                for s in range(S):
                    acc -= Mib[s, i] * fs[s]
                a[i] = acc
            for i in range(N):
                v[i] += h * a[i]
                q[i] += h * v[i]
            step += 1
            count = step > count_from
            for s in range(S):
                u = 0.0
                for i in range(N):
                    u += bmat[s, i] * q[i]
                now = abs(u) > gaps[s]
                if count:
                    if now:
                        contact_time[s] += h
                    if now and not closed[s]:
                        n_events[s] += 1
                closed[s] = now
            if step % out_every == 0:
                jout = step // out_every
                if jout >= j0:
                    for o in range(n_obs):
                        y = 0.0
                        for i in range(N):
                            y += Cm[o, i] * q[i]
                        sumsq[o] += y * y
                        if store:
                            y_out[jout - j0, o] = y
    return step


def integrate_symplectic(problem, r: int, h: float, f_max: float, y_out, sumsq, contact_time, n_events,
                         refine_all: bool = False, diagnose: bool = False) -> dict:
    """Realisation r of a :class:`~tubeid.dynamics.solver._checks.Problem` at step h (s); writes
    the outputs into y_out (n_keep or 0, n_obs), sumsq (n_obs,), contact_time (S,) (s) and n_events
    (S,) of the gapped stops. ``refine_all`` and ``diagnose`` are the exact method's (unused). Returns
    diagnostics (steps)."""
    M, D, K = problem.matrices(r)
    stops = problem.gapped
    N = M.shape[0]
    ns = int(round(problem.dt_load / h))
    out_every = int(round(problem.output_dt / h))
    with one_blas_thread():
        Minv = np.linalg.inv(M)
        bmat = np.array([s.vector for s in stops]).reshape(len(stops), N)
        MiK, MiD, MiB = Minv @ K, Minv @ D, Minv @ problem.B
        Mib = np.ascontiguousarray((Minv @ bmat.T).T)
    steps = _kernel(problem.loads[r], ns, out_every, problem.j0, h, MiK, MiD, MiB, Mib, bmat,
                    np.array([s.gap for s in stops]), np.array([s.stiffness for s in stops]), problem.C,
                    y_out, sumsq, contact_time, n_events)
    return {"steps": int(steps)}
