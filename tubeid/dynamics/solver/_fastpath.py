"""The exact method's main loop: load intervals, blocks of sub-steps, the event pre-check.

Per load interval (ns sub-steps of h; the load is linear on it) the running state ζ gets the
slope update, then blocks of up to nb sub-steps are taken. For a block, u and u' of every stop
at its nb sub-step ends are one product of the block rows with xl = [ζ; f; f'; 1] (f the load at
the block start); if every sub-step is clear of every boundary of the current regime by more
than the Hermite margin (a sufficient test on the block's values, branch-free), the block is
accepted at once and ζ advanced by the diagonal e^{λ n h} (n <= nb the block's sub-steps).
Otherwise the sub-steps are checked one by one with the Hermite pre-check
(``_events.hermite_flag``); the sub-steps before the first flagged one are accepted, and the
flagged one is integrated exactly by ``_events.event_step``.
Outputs falling on accepted sub-step ends are rows of the same kind.
"""

from __future__ import annotations

import numba

from tubeid.dynamics.solver._events import event_step, hermite_flag
from tubeid.dynamics.solver._modal import _FM, NO_ALIAS, block_advance, rows, rows8, set_load, slope_update
from tubeid.dynamics.solver._work import DF, F0, F1, FLAGGED_STEPS, FN, FS, U_END, U_START, UD_END, UD_START, XL

__all__ = ["run_exact"]


@numba.njit(cache=True, _nrt=False, fastmath=_FM, **NO_ALIAS)
def run_exact(loads, dt_load, ns, out_every, j0, r0, T, W, y_out, sumsq, contact_time, n_events, refine_all, stats):
    """Integrate one realisation; returns the number of sub-steps.

    loads (n_t, m): samples at t = k dt_load (piecewise-linear load); ns sub-steps per load
    interval; outputs every out_every sub-steps, stored from output sample j0 on into y_out
    (n_keep, n_obs) (or not stored if y_out has no rows) and summed as squares into sumsq; contact
    time and open -> contact events counted from output sample j0 on. r0: initial regime (0: every
    stop open), W.X[XL, :nx]: initial ζ. refine_all: send every sub-step to the exact event path (test
    hook). T: ``ExactTables``, W: ``Work``. stats: the int64 counters of ``_work.STATS`` (length
    N_STATS), incremented (flagged sub-steps here, the others in ``_events.event_step``). No two
    array arguments may share memory (compiled with ``NO_ALIAS``).
    """
    n_int = loads.shape[0] - 1
    m = loads.shape[1]
    h = T.h
    nb = T.nb
    mcoef = T.mcoef
    nx = 2 * T.lam_re.shape[1]
    nxl = W.X.shape[1]
    S = T.gaps.shape[0]
    S2 = 2 * S
    n_obs = y_out.shape[1]
    store = y_out.shape[0] > 0
    xl = W.X[XL]
    col = W.col
    U = W.U
    f0 = W.L[F0]
    f1 = W.L[F1]
    fs = W.L[FS]
    df = W.L[DF]
    fnext = W.L[FN]
    r = r0
    q = T.basis[r]
    for l in range(m):
        f1[l] = (loads[1, l] - loads[0, l]) / dt_load
        fnext[l] = f1[l]
    step = 0
    count_from = j0 * out_every
    to_out = out_every  # sub-steps to the next output sample
    jout = 0  # index of the last output sample
    if j0 == 0 and store:
        for o in range(n_obs):
            y_out[0, o] = 0.0
    for k in range(n_int):
        for l in range(m):
            f0[l] = loads[k, l]
            df[l] = f1[l] - fnext[l]
            f1[l] = fnext[l]
        if k + 1 < n_int:  # the next slope one interval ahead: its divisions overlap this interval's work
            for l in range(m):
                fnext[l] = (loads[k + 2, l] - loads[k + 1, l]) / dt_load
        if k > 0:
            slope_update(T.slope_rows, q, df, xl)
        j = 0
        while j < ns:
            mb = min(nb, ns - j)
            # u, u' at the ends of the next mb sub-steps: col = block rows of regime r · [ζ; f_j; f'; 1]
            set_load(xl, nx, m, f0, f1, j * h)
            for g in range(0, mb * S2, 8):
                rows8(T.block_rows, r, g, xl, nxl, col, g)
            # sufficient test for the whole block: every sub-step's end values clear of the regime's
            # bounds by the Hermite margin plus the bound 0.15 σ (|d0'| + |d1'|) of the cubic's dip
            # (slack = smallest clearance minus margin; branch-free)
            slack = -1.0 if refine_all else 1e308
            for s in range(S):
                lo = T.lower[r, s]
                hi = T.upper[r, s]
                ua = U[U_START, s]
                va = U[UD_START, s]
                for mm in range(mb):
                    a = col[mm * S2 + 2 * s]
                    b = col[mm * S2 + 2 * s + 1]
                    mg = mcoef * max(abs(va), abs(b)) + 0.15 * h * (abs(va) + abs(b))
                    slack = min(slack, min(min(ua, a) - lo, hi - max(ua, a)) - mg)
                    ua = a
                    va = b
            clear = slack >= 0.0
            flag_m = -1
            if not clear:
                for mm in range(1, mb + 1):
                    flagged = refine_all
                    base = (mm - 1) * S2
                    for s in range(S):
                        a = col[base + 2 * s]
                        b = col[base + 2 * s + 1]
                        if mm == 1:
                            ua = U[U_START, s]
                            va = U[UD_START, s]
                        else:
                            ua = col[base - S2 + 2 * s]
                            va = col[base - S2 + 2 * s + 1]
                        g = T.gaps[s]
                        code = T.codes[r, s]
                        mg = mcoef * max(abs(va), abs(b))
                        if code == 0:
                            if hermite_flag(g - ua, -va, g - a, -b, h, mg) or hermite_flag(ua + g, va, a + g, b, h, mg):
                                flagged = True
                        elif code == 1:
                            if hermite_flag(ua - g, va, a - g, b, h, mg):
                                flagged = True
                        else:
                            if hermite_flag(-g - ua, -va, -g - a, -b, h, mg):
                                flagged = True
                    if flagged:
                        flag_m = mm
                        break
            n_acc = mb if flag_m < 0 else flag_m - 1
            if n_acc > 0:
                # contact time of the accepted sub-steps step+1 .. step+n_acc counted after count_from
                n_cnt = min(n_acc, max(0, step + n_acc - count_from))
                if n_cnt > 0:
                    for s in range(S):
                        contact_time[s] += n_cnt * h * T.closed[r, s]
                # outputs at the accepted sub-step ends that fall on the output grid
                mm = to_out
                while mm <= n_acc:
                    jout += 1
                    if jout >= j0:
                        rows(T.output_rows, r, mm * n_obs, n_obs, xl, nxl, W.y, 0)
                        for o in range(n_obs):
                            y = W.y[o]
                            sumsq[o] += y * y
                            if store:
                                y_out[jout - j0, o] = y
                    mm += out_every
                to_out = mm - n_acc
                block_advance(T.step_re, T.step_im, q, n_acc, xl)
                base = (n_acc - 1) * S2
                for s in range(S):
                    U[U_START, s] = col[base + 2 * s]
                    U[UD_START, s] = col[base + 2 * s + 1]
                j += n_acc
                step += n_acc
            if flag_m >= 0:
                stats[FLAGGED_STEPS] += 1
                for l in range(m):
                    fs[l] = f0[l] + f1[l] * (j * h)
                base = (flag_m - 1) * S2
                for s in range(S):  # u, u' at h (at 0 they are in U_START, UD_START)
                    U[U_END, s] = col[base + 2 * s]
                    U[UD_END, s] = col[base + 2 * s + 1]
                r = event_step(T, W, r, m, step >= count_from, contact_time, n_events, refine_all, stats)
                q = T.basis[r]
                for s in range(S):
                    U[U_START, s] = U[U_END, s]
                    U[UD_START, s] = U[UD_END, s]
                j += 1
                step += 1
                to_out -= 1
                if to_out == 0:
                    to_out = out_every
                    jout += 1
                    if jout >= j0:
                        set_load(xl, nx, m, f0, f1, j * h)
                        rows(T.output_rows, r, 0, n_obs, xl, nxl, W.y, 0)
                        for o in range(n_obs):
                            y = W.y[o]
                            sumsq[o] += y * y
                            if store:
                                y_out[jout - j0, o] = y
    return step
