"""Event search of the exact method: a flagged sub-step integrated exactly, switches located.

Pre-check (also used by the fast path). The distance d to a boundary of the current regime
(g - u and u + g when open, u - g in contact on the + side, -g - u on the - side) is known with
its derivative at both ends of a (sub)step. The (sub)step is flagged when d changes sign, or when
the cubic Hermite interpolant of (d, d') has an interior minimum that comes within a margin of
the boundary: margin = mcoef (σ/h)⁴ max|d'|, mcoef = MARGIN_SAFETY (w h)⁴/(384 w), w = 2π f_max
(``_regimes.MARGIN_SAFETY`` times the Hermite error bound of a component at the highest frequency).
The only approximation of the method is to miss a grazing excursion shallower than that bound.

A flagged sub-step is integrated exactly. Every evaluation of u, u', u'' inside it is exact
(e^{λτ} from the table at τ = k h/FINE times the series of the rest, then one row product);
interior minima are located by Newton on d' = 0, the first crossing by safeguarded Halley
iterations (tolerance T.xtol = CROSSING_TOL h) from the root of the Hermite cubic; if the Hermite
check on [0, t_c] still allows an earlier dip, [0, t_c] is rescanned exactly on _PIECES pieces. A
sub-step reaching MAX_SWITCHES switches before its end raises RuntimeError. A switch maps
xl(t_c) through the basis-to-basis transform (x continuous); u and u' continue from their values
at the crossing; the end state of the remaining segment is propagated and its u, u' pre-checked,
and a crossing is searched only if that check flags the segment.
"""

from __future__ import annotations

import math

import numba

from tubeid.dynamics.solver._modal import _FM, NO_ALIAS, diag_mul, exp_modes, expmul, rows, rows8, set_load_rows
from tubeid.dynamics.solver._work import (EVALUATIONS, F1, FS, MAX_SWITCHES, RESCANS, SWITCHES, U_CROSS, U_END,
                                          U_START, UD_CROSS, UD_END, UD_START, X0, XE, XL, XS)

__all__ = ["distance", "cubic_min", "hermite_flag", "cubic_first_root", "segment_coefficients", "evaluate", "event_step"]

_PIECES = 8  # exact rescan of a segment on this many pieces (the RESCANS counter)

# The scalar helpers below are inlined by LLVM (``forceinline``: the same instructions, so the same
# values) into the main loop, which calls them per pre-checked sub-step and per crossing search;
# ``evaluate`` stays a call (inlined at its several call sites it makes the kernel slower).


@numba.njit(cache=True, forceinline=True)
def distance(code, side, g, u, ud, udd):
    """Distance to a boundary (>= 0 inside the current regime) and its two time derivatives.

    code 0 (open): side 0 is the +g boundary (g - u), side 1 the -g boundary (u + g);
    code +1: u - g; code -1: -g - u.
    """
    if code == 0:
        if side == 0:
            return g - u, -ud, -udd
        return u + g, ud, udd
    if code == 1:
        return u - g, ud, udd
    return -g - u, -ud, -udd


@numba.njit(cache=True, forceinline=True)
def cubic_min(d0, dd0, d1, dd1, sigma):
    """Interior minimum (s in (0, 1), value) of the cubic Hermite interpolant of (d, d') given at
    both ends of a segment of length sigma; s = -1 if none."""
    a = 2 * d0 + sigma * dd0 - 2 * d1 + sigma * dd1
    b = -3 * d0 - 2 * sigma * dd0 + 3 * d1 - sigma * dd1
    c = sigma * dd0
    best_s = -1.0
    best_v = 1e308
    qa = 3 * a  # p'(s) = 3a s² + 2b s + c
    qb = 2 * b
    if abs(qa) < 1e-300:
        if abs(qb) > 0:
            s = -c / qb
            if 0 < s < 1 and qb > 0:  # p'' = 2b > 0: minimum
                best_s = s
                best_v = ((a * s + b) * s + c) * s + d0
        return best_s, best_v
    disc = qb * qb - 4 * qa * c
    if disc < 0:
        return best_s, best_v
    sq = math.sqrt(disc)
    for sgn in (-1.0, 1.0):
        s = (-qb + sgn * sq) / (2 * qa)
        if 0 < s < 1 and 6 * a * s + 2 * b > 0:
            v = ((a * s + b) * s + c) * s + d0
            if v < best_v:
                best_v = v
                best_s = s
    return best_s, best_v


@numba.njit(cache=True, forceinline=True)
def hermite_flag(d0, dd0, d1, dd1, sigma, margin):
    """True if the distance may come within ``margin`` of the boundary (or cross it) in the segment."""
    if d1 < 0:
        return True
    d0c = max(d0, 0.0)
    if min(d0c, d1) - 0.15 * sigma * (abs(dd0) + abs(dd1)) >= margin:
        return False
    s, v = cubic_min(d0c, dd0, d1, dd1, sigma)
    return s >= 0 and v < margin


@numba.njit(cache=True, forceinline=True)
def cubic_first_root(d0, dd0, d1, dd1, sigma, smax):
    """First s in (0, smax] (s: position in units of sigma, smax <= 1) where the cubic Hermite
    interpolant of (d, d') becomes negative (-1 if none): the starting guess of the exact search.
    If the cubic is monotone on [0, smax] and changes sign, its only root is refined from the
    secant guess by 4 safeguarded Newton steps; otherwise the sign change is located on 16 points
    and refined by 4 Illinois steps."""
    a = 2 * d0 + sigma * dd0 - 2 * d1 + sigma * dd1
    b = -3 * d0 - 2 * sigma * dd0 + 3 * d1 - sigma * dd1
    c = sigma * dd0
    vmax = ((a * smax + b) * smax + c) * smax + d0
    qa = 3 * a  # critical points of p(s) = a s³ + b s² + c s + d0: 3a s² + 2b s + c = 0
    qb = 2 * b
    inside = False
    if abs(qa) > 1e-300:
        disc = qb * qb - 4 * qa * c
        if disc >= 0:
            sq = math.sqrt(disc)
            r1 = (-qb - sq) / (2 * qa)
            r2 = (-qb + sq) / (2 * qa)
            inside = (0 < r1 < smax) or (0 < r2 < smax)
    elif abs(qb) > 0:
        inside = 0 < -c / qb < smax
    if not inside and d0 >= 0 > vmax:
        lo = 0.0
        hi = smax
        s = smax * d0 / (d0 - vmax)
        for _ in range(4):
            v = ((a * s + b) * s + c) * s + d0
            if v >= 0:
                lo = s
            else:
                hi = s
            dv = (qa * s + qb) * s + c
            sn = s - v / dv if dv != 0 else 0.5 * (lo + hi)
            if not (lo < sn < hi):
                sn = 0.5 * (lo + hi)
            s = sn
        return s
    n = 16
    prev = d0
    for k in range(1, n + 1):
        s = smax * k / n
        v = ((a * s + b) * s + c) * s + d0
        if v < 0:
            lo = s - smax / n
            hi = s
            flo = prev
            fhi = v
            side = 0
            for _ in range(4):
                mid = (lo * fhi - hi * flo) / (fhi - flo)
                if not (lo < mid < hi):
                    mid = 0.5 * (lo + hi)
                fm = ((a * mid + b) * mid + c) * mid + d0
                if fm >= 0:
                    lo = mid
                    flo = fm
                    if side == 1:
                        fhi *= 0.5
                    side = 1
                else:
                    hi = mid
                    fhi = fm
                    if side == -1:
                        flo *= 0.5
                    side = -1
            return hi if fhi == 0 else (lo * fhi - hi * flo) / (fhi - flo) if flo > 0 > fhi else hi
        prev = v
    return -1.0


@numba.njit(cache=True, _nrt=False, fastmath=_FM, inline="always")
def segment_coefficients(T, W, r, m, t0):
    """W.A, W.QS for the segment starting at t0 from ζ0 = W.X[X0] in regime r (load W.L[FS] +
    W.L[F1] t): u_s(t0 + τ) = Re Σ_i a_i e^{λ_i τ} + Q0 + Q1 τ, a = cu ζ0; u' and u'' likewise with
    λ a and λ² a (v = q' : cv = λ cu)."""
    q = T.basis[r]
    n2p = T.lam_re.shape[1]
    x0 = W.X[X0]
    fs = W.L[FS]
    f1 = W.L[F1]
    for s in range(T.gaps.shape[0]):
        for i in range(n2p):
            zr = x0[i]
            zi = x0[n2p + i]
            ar = T.cu_re[q, s, i] * zr - T.cu_im[q, s, i] * zi
            ai = T.cu_re[q, s, i] * zi + T.cu_im[q, s, i] * zr
            lr = T.lam_re[q, i]
            li = T.lam_im[q, i]
            br = lr * ar - li * ai
            bi = lr * ai + li * ar
            W.A[s, 0, i] = ar
            W.A[s, 1, i] = ai
            W.A[s, 2, i] = br
            W.A[s, 3, i] = bi
            W.A[s, 4, i] = lr * br - li * bi
            W.A[s, 5, i] = lr * bi + li * br
        q0 = T.ueq[r, s]
        q1 = 0.0
        p0 = 0.0
        p1 = 0.0
        for l in range(m):
            f = fs[l] + f1[l] * t0
            q0 += T.stop_qs[q, s, 0, l] * f + T.stop_qs[q, s, 1, l] * f1[l]
            q1 += T.stop_qs[q, s, 0, l] * f1[l]
            p0 += T.stop_qs[q, s, 2, l] * f + T.stop_qs[q, s, 3, l] * f1[l]
            p1 += T.stop_qs[q, s, 2, l] * f1[l]
        W.QS[s, 0] = q0
        W.QS[s, 1] = q1
        W.QS[s, 2] = p0
        W.QS[s, 3] = p1


@numba.njit(cache=True, _nrt=False, fastmath=_FM, **NO_ALIAS)
def evaluate(lam_re, lam_im, fine_re, fine_im, q, h, tau, A, QS, E, ev):
    """Exact u, u', u'' of every stop at tau from the segment start (ev[3s], ev[3s + 1],
    ev[3s + 2]), from the segment's coefficients A, QS (``segment_coefficients``) and E = e^{λ tau}
    (left in E). One compiled body for every call site (short argument list: a cheap call). No two
    array arguments may share memory (``NO_ALIAS``)."""
    exp_modes(lam_re, lam_im, fine_re, fine_im, q, h, tau, E)
    n2p = E.shape[1]
    for s in range(A.shape[0]):
        u = 0.0
        ud = 0.0
        udd = 0.0
        for i in range(n2p):
            er = E[0, i]
            ei = E[1, i]
            u += A[s, 0, i] * er - A[s, 1, i] * ei
            ud += A[s, 2, i] * er - A[s, 3, i] * ei
            udd += A[s, 4, i] * er - A[s, 5, i] * ei
        ev[3 * s] = u + QS[s, 0] + QS[s, 1] * tau
        ev[3 * s + 1] = ud + QS[s, 2] + QS[s, 3] * tau
        ev[3 * s + 2] = udd + QS[s, 3]


@numba.njit(cache=True, _nrt=False, inline="always")
def _eval(T, W, r, m, t0, tau, s, code, side, stats):
    """evaluate() at tau, recorded in W.eval_tau and the counters; returns the distance to the
    boundary (code, side) of stop s and its two derivatives there."""
    evaluate(T.lam_re, T.lam_im, T.fine_re, T.fine_im, T.basis[r], T.h, tau, W.A, W.QS, W.E, W.ev)
    W.eval_tau[0] = tau
    stats[EVALUATIONS] += 1
    return distance(code, side, T.gaps[s], W.ev[3 * s], W.ev[3 * s + 1], W.ev[3 * s + 2])


@numba.njit(cache=True, _nrt=False, fastmath=_FM, inline="always")
def _crossing_in(T, W, r, m, t0, ta, tb, da, dda, db, ddb, code, side, s, margin, stats):
    """First crossing (d < 0) in (ta, tb] of the exact solution, given d and d' at the ends; -1 if
    none; ta, tb and the result in s from the segment start). Cubic Hermite guess, exact Newton on
    d' = 0 for an interior minimum (at most 12 steps, step tolerance T.xtol), then safeguarded
    Halley iterations on d for the root (at most 100, tolerance T.xtol). With a root, W.ev holds
    u, u', u'' at the returned instant (see ``evaluate``)."""
    h = T.h
    sig = tb - ta
    da = max(da, 0.0)
    if db < 0:
        lo = ta
        hi = tb
        sg = cubic_first_root(da, dda, db, ddb, sig, 1.0)
        guess = ta + sg * sig if sg > 0 else 0.5 * (ta + tb)
    else:
        sm, vm = cubic_min(da, dda, db, ddb, sig)
        if sm < 0 or vm >= margin:
            return -1.0
        tm = ta + sm * sig
        dm = 1.0
        for _ in range(12):
            dm, ddm, dddm = _eval(T, W, r, m, t0, tm, s, code, side, stats)
            if dm < 0 or dddm <= 0:
                break
            tn = min(max(tm - ddm / dddm, ta), tb)
            if abs(tn - tm) < T.xtol:
                break
            tm = tn
        if dm >= 0:
            return -1.0
        lo = ta
        hi = tm
        sg = cubic_first_root(da, dda, db, ddb, sig, sm)
        guess = ta + sg * sig if sg > 0 else 0.5 * (lo + hi)
    t = min(max(guess, lo), hi)
    for _ in range(100):
        d, dd, ddd = _eval(T, W, r, m, t0, t, s, code, side, stats)
        if d >= 0:
            lo = t
        else:
            hi = t
        if d == 0 or hi - lo < T.xtol:
            return t
        # Halley step (u'' comes with the evaluation): cubic convergence from the Hermite guess
        den = 2 * dd * dd - d * ddd
        tn = t - 2 * d * dd / den if den != 0 else -1.0
        if not (lo < tn < hi):
            tn = t - d / dd if dd != 0 else -1.0
            if not (lo < tn < hi):
                tn = 0.5 * (lo + hi)
        if abs(tn - t) < T.xtol:
            return t  # converged; W.ev holds u, u', u'' at t
        t = tn
    _eval(T, W, r, m, t0, t, s, code, side, stats)
    return t


@numba.njit(cache=True, _nrt=False, fastmath=_FM, inline="always")
def _first_crossing(T, W, r, m, t0, code, side, s, sigma, d0, dd0, d1, dd1, scan, stats):
    """Earliest crossing in (0, sigma] of one boundary (-1 if none). The candidate is verified: if
    the cubic Hermite check on [0, t_c] allows an earlier dip, [0, t_c] is rescanned exactly on
    _PIECES pieces. scan=True scans the whole segment exactly on _PIECES pieces (test hook). Each
    rescan counts in stats[RESCANS]. With a crossing, W.ev holds u, u', u'' there (within the
    T.xtol tolerance)."""
    h = T.h
    mcoef = T.mcoef
    tc = sigma
    if not scan:
        margin = mcoef * (sigma / h) ** 4 * max(abs(dd0), abs(dd1))
        tc = _crossing_in(T, W, r, m, t0, 0.0, sigma, d0, dd0, d1, dd1, code, side, s, margin, stats)
        if tc <= 0:
            return tc
        dc, ddc, _x = distance(code, side, T.gaps[s], W.ev[3 * s], W.ev[3 * s + 1], W.ev[3 * s + 2])
        mc = mcoef * (tc / h) ** 4 * max(abs(dd0), abs(ddc))
        sm, vm = cubic_min(max(d0, 0.0), dd0, max(dc, 0.0), ddc, tc)
        if sm < 0 or vm >= mc:
            return tc
    stats[RESCANS] += 1
    ta = 0.0
    da = d0
    dda = dd0
    for p in range(1, _PIECES + 1):
        tb = tc * p / _PIECES
        db, ddb, _x = _eval(T, W, r, m, t0, tb, s, code, side, stats)
        mp = mcoef * ((tb - ta) / h) ** 4 * max(abs(dda), abs(ddb))
        t2 = _crossing_in(T, W, r, m, t0, ta, tb, da, dda, db, ddb, code, side, s, mp, stats)
        if t2 >= 0:
            return t2
        ta = tb
        da = db
        dda = ddb
    if scan:
        return -1.0
    _eval(T, W, r, m, t0, tc, s, code, side, stats)  # callers read u, u' at the returned crossing from W.ev
    return tc


@numba.njit(cache=True, _nrt=False, fastmath=_FM, inline="always")
def event_step(T, W, r, m, count, contact_time, n_events, refine_all, stats):
    """Integrate one sub-step [0, h] exactly from ζ = W.X[XL, :nx] in regime r with event location;
    returns the final regime and leaves ζ at h in W.X[XL, :nx]. The load over the sub-step is
    W.L[FS] + W.L[F1] t (m loads). On entry W.U holds u, u' at 0 (rows U_START, UD_START) and at h
    (U_END, UD_END, from the fast path's rows); on return U_END, UD_END hold u, u' at h. ``count``:
    add contact time and contact events (the sub-step is inside the kept window). stats: the
    counters of ``_work.STATS`` (switches, rescans, evaluations counted here). Raises RuntimeError
    when the sub-step reaches MAX_SWITCHES switches before its end. Inlined into the main loop: a
    call would pass every table and scratch array of T and W."""
    S = T.gaps.shape[0]
    h = T.h
    nx = 2 * T.lam_re.shape[1]
    nxl = W.X.shape[1]
    X, U, ev = W.X, W.U, W.ev
    x0, xe, xs, xl = X[X0], X[XE], X[XS], X[XL]
    fs, f1 = W.L[FS], W.L[F1]
    n_rows = T.stop_rows.shape[1]
    t_loc = 0.0
    just_switched = False
    W.eval_tau[0] = -1.0
    for i in range(nx):
        x0[i] = xl[i]
    for it in range(MAX_SWITCHES + 1):
        if it == MAX_SWITCHES:
            raise RuntimeError("more than 200 regime switches within one step")
        q = T.basis[r]
        sigma = h - t_loc
        set_load_rows(x0, nx, m, fs, f1, t_loc)
        if just_switched:  # end state of the remaining segment, kept in case no event occurs
            expmul(T.lam_re, T.lam_im, T.fine_re, T.fine_im, q, h, sigma, x0, xe, W.E)
            set_load_rows(xe, nx, m, fs, f1, h)
            rows(T.stop_rows, r, 0, n_rows, xe, nxl, ev, 0)
            for s in range(S):
                U[U_END, s] = ev[3 * s]
                U[UD_END, s] = ev[3 * s + 1]
        tau_c = 1e308
        s_c = -1
        side_c = -1
        coefficients = False  # W.A, W.QS of this segment computed
        for s in range(S):
            code = T.codes[r, s]
            g = T.gaps[s]
            for side in range(2 if code == 0 else 1):
                d0, dd0, _x = distance(code, side, g, U[U_START, s], U[UD_START, s], 0.0)
                d1, dd1, _x = distance(code, side, g, U[U_END, s], U[UD_END, s], 0.0)
                if just_switched:
                    d0 = max(d0, 0.0)
                margin = T.mcoef * (sigma / h) ** 4 * max(abs(dd0), abs(dd1))
                if not (refine_all or hermite_flag(d0, dd0, d1, dd1, sigma, margin)):
                    continue
                if not coefficients:
                    segment_coefficients(T, W, r, m, t_loc)
                    coefficients = True
                tc = _first_crossing(T, W, r, m, t_loc, code, side, s, sigma, d0, dd0, d1, dd1,
                                     refine_all and d1 >= 0, stats)
                if tc >= 0 and tc < tau_c:
                    tau_c = tc
                    s_c = s
                    side_c = side
                    for k in range(S):  # u, u' at the crossing (its last evaluation) start the next segment
                        U[U_CROSS, k] = ev[3 * k]
                        U[UD_CROSS, k] = ev[3 * k + 1]
        if s_c < 0:
            if just_switched:
                for i in range(nx):
                    xl[i] = xe[i]
            else:  # u, u' at h already in U (fast path)
                expmul(T.lam_re, T.lam_im, T.fine_re, T.fine_im, q, h, sigma, x0, xl, W.E)
            if count:
                for s in range(S):
                    contact_time[s] += sigma * T.closed[r, s]
            return r
        # switch at tau_c: x continuous, ζ_new = T_{b→b'} xl(tau_c) + c; u, u' continuous
        stats[SWITCHES] += 1
        if W.eval_tau[0] != tau_c:  # e^{λ tau_c}, unless the last evaluation left it in W.E
            exp_modes(T.lam_re, T.lam_im, T.fine_re, T.fine_im, q, h, tau_c, W.E)
        diag_mul(W.E, x0, xs)
        set_load_rows(xs, nx, m, fs, f1, t_loc + tau_c)
        for s in range(S):
            U[U_START, s] = U[U_CROSS, s]
            U[UD_START, s] = U[UD_CROSS, s]
        if count:
            for s in range(S):
                contact_time[s] += tau_c * T.closed[r, s]
        code = T.codes[r, s_c]
        tid = T.trans_id[r, s_c, side_c if code == 0 else 0]
        if code == 0 and count:
            n_events[s_c] += 1
        u = T.trans_map[tid]
        for g8 in range(0, nx, 8):
            rows8(T.transforms, u, g8, xs, nxl, x0, g8)
        for i in range(nx):
            x0[i] += T.trans_const[tid, i]
        r = T.trans_to[tid]
        t_loc += tau_c
        just_switched = True
        W.eval_tau[0] = -1.0  # xs no longer matches the new segment
        if h - t_loc <= 1e-14 * h:
            for i in range(nx):
                xl[i] = x0[i]
            set_load_rows(x0, nx, m, fs, f1, h)
            rows(T.stop_rows, r, 0, n_rows, x0, nxl, ev, 0)
            for s in range(S):
                U[U_END, s] = ev[3 * s]
                U[UD_END, s] = ev[3 * s + 1]
            return r
    return r
