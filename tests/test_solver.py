"""Tests of tubeid.dynamics.solver against independent references (scipy DOP853, closed forms)."""

import json
import math
import os
import pathlib
import subprocess
import sys
import warnings

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from tubeid.dynamics.solver import (
    Stop,
    choose_step,
    highest_frequency,
    simulate,
)
from tubeid.dynamics.solver._simulate import simulate_with_diagnostics
from tubeid.errors import SpecificationError
from tubeid.seeds import rng_for

DT_LOAD = 1e-3


def chain(n=4, m=1.0, k=4e4, xi=0.02, wall=True):
    """Spring-mass chain clamped at both ends, modal damping ratio xi (undamped stops)."""
    M = np.eye(n) * m
    K = np.zeros((n, n))
    for i in range(n):
        K[i, i] += k if (i == 0 or i == n - 1) and wall else 0.0
        if i + 1 < n:
            K[i, i] += k
            K[i + 1, i + 1] += k
            K[i, i + 1] -= k
            K[i + 1, i] -= k
    w2, P = np.linalg.eigh(K)
    D = M @ P @ np.diag(2 * xi * np.sqrt(w2)) @ P.T @ M
    return M, D, K


def reference(M, D, K, stops, B, C, F, dt_load):
    """DOP853 (rtol 1e-11), one solve_ivp call per load interval so that the PL kinks of F are
    step boundaries; the stop force is evaluated from u directly (no regimes, no modes)."""
    N = M.shape[0]
    Minv = np.linalg.inv(M)
    tgrid = np.arange(F.shape[0]) * dt_load

    def rhs(t, x):
        q, v = x[:N], x[N:]
        f = np.array([np.interp(t, tgrid, F[:, j]) for j in range(F.shape[1])])
        acc = B @ f - D @ v - K @ q
        for s in stops:
            u = s.vector @ q
            acc -= s.vector * s.stiffness * np.sign(u) * max(abs(u) - s.gap, 0.0)
        return np.concatenate([v, Minv @ acc])

    x = np.zeros(2 * N)
    out = [C @ x[:N]]
    for k in range(F.shape[0] - 1):
        sol = solve_ivp(rhs, (tgrid[k], tgrid[k + 1]), x, method="DOP853", rtol=1e-11, atol=1e-18)
        x = sol.y[:, -1]
        out.append(C @ x[:N])
    return np.array(out)


def contact_setup(n_t=201, seed=3):
    M, D, K = chain()
    N = M.shape[0]
    b = np.zeros(N)
    b[1] = 1.0
    B = np.zeros((N, 2))
    B[2, 0] = 1.0
    B[0, 1] = 1.0
    F = 30.0 * rng_for(seed, "solver-test-load").normal(size=(n_t, 2))
    # gap from the linear response so that contact occurs a good part of the time
    lin = simulate(M, D, K, [], B, b[None, :], F, DT_LOAD, output_dt=DT_LOAD)
    gap = float(np.quantile(np.abs(lin.observations.values[0, :, 0]), 0.4))
    return M, D, K, Stop(b, gap, 1e6), B, np.eye(N), F


def test_exact_matches_solve_ivp_with_contact():
    M, D, K, stop, B, C, F = contact_setup()
    res = simulate(M, D, K, [stop], B, C, F, DT_LOAD, output_dt=DT_LOAD)
    cf = float(res.contact_fraction.values[0, 0])
    assert 0.2 < cf < 0.8, cf  # the stop really is active
    assert res.contact_events.values[0, 0] >= 5
    ref = reference(M, D, K, [stop], B, C, F, DT_LOAD)
    y = res.observations.values[0]
    err = np.max(np.abs(y - ref)) / np.max(np.abs(ref))
    # Measured 6.3e-7 here: the switch instants are located within CROSSING_TOL = 1e-5 of the step
    # (1.7e-8 in the two-stop test below; solve_ivp itself is good to ~1e-8). 1e-6 still catches any
    # event mislocated by more than ~1e-6 of a period (the brief asks 1e-3).
    assert err < 1e-6, err
    # contact fraction from the dense reference (fine grid from solve_ivp is not needed: the
    # output grid estimate agrees to within a few output samples)
    u_ref = ref[:, 1]
    cf_grid = np.mean(np.abs(u_ref) > stop.gap)
    assert abs(cf_grid - cf) < 0.05


def test_two_stops_and_overdamped_mode_match_solve_ivp():
    """Generic case: two stops (9 regimes), one real (overdamped) eigenvalue -> full mode set."""
    M, D, K = chain(n=3)
    D = D.copy()
    D[2, 2] += 2000.0  # overdamps one mode: real eigenvalues, no conjugate-pair halving
    N = 3
    B = np.ones((N, 1))
    F = 40.0 * rng_for(5, "solver-test-2stops").normal(size=(151, 1))
    s1 = Stop(np.array([1.0, 0, 0]), 2e-4, 5e5, name="a")
    s2 = Stop(np.array([0, 1.0, -1.0]), 1e-4, 2e5, name="b")
    res, diag = simulate_with_diagnostics(M, D, K, [s1, s2], B, np.eye(N), F, DT_LOAD, output_dt=DT_LOAD)
    assert not diag[0]["half_modes"]
    assert np.all(res.contact_events.values > 0)
    ref = reference(M, D, K, [s1, s2], B, np.eye(N), F, DT_LOAD)
    err = np.max(np.abs(res.observations.values[0] - ref)) / np.max(np.abs(ref))
    assert err < 1e-6, err


def test_linear_matches_solve_ivp_and_closed_form_ramp():
    M, D, K = chain()
    N = 4
    B = np.zeros((N, 1))
    B[3, 0] = 1.0
    F = 10.0 * rng_for(1, "solver-lin").normal(size=(101, 1))
    far = Stop(np.eye(N)[1], 1.0, 1e6)  # never reached
    res = simulate(M, D, K, [far], B, np.eye(N), F, DT_LOAD, output_dt=DT_LOAD)
    assert res.contact_events.values[0, 0] == 0
    ref = reference(M, D, K, [], B, np.eye(N), F, DT_LOAD)
    err = np.max(np.abs(res.observations.values[0] - ref)) / np.max(np.abs(ref))
    assert err < 1e-9, err  # exact integration of a linear system with PL load: roundoff only

    # single DOF, ramp load F = a t: x = (a/k)(t - c/k) + e^{-xi w t}(A cos wd t + B sin wd t)
    m, k, xi, a = 2.0, 8e3, 0.05, 3.0
    w = math.sqrt(k / m)
    c = 2 * xi * w * m
    wd = w * math.sqrt(1 - xi**2)
    t = np.arange(501) * DT_LOAD
    A_ = a * c / k**2
    B_ = (-a / k + xi * w * A_) / wd
    x = (a / k) * (t - c / k) + np.exp(-xi * w * t) * (A_ * np.cos(wd * t) + B_ * np.sin(wd * t))
    res = simulate([[m]], [[c]], [[k]], [], [[1.0]], [[1.0]], (a * t)[:, None], DT_LOAD, output_dt=DT_LOAD)
    err = np.max(np.abs(res.observations.values[0, :, 0] - x)) / np.max(np.abs(x))
    assert err < 1e-10, err


def test_symplectic_euler_agrees_with_exact_at_small_step():
    M, D, K, stop, B, C, F = contact_setup(n_t=101)
    ex = simulate(M, D, K, [stop], B, C, F, DT_LOAD, output_dt=DT_LOAD)
    se = simulate(M, D, K, [stop], B, C, F, DT_LOAD, output_dt=DT_LOAD, dt=1e-6, method="symplectic-euler")
    y_ex, y_se = ex.observations.values[0], se.observations.values[0]
    err = np.max(np.abs(y_ex - y_se)) / np.max(np.abs(y_ex))
    # first-order scheme, w_max dt = 1.1e-3: the global error is O(dt) ~ 1e-3 of the response
    assert err < 5e-3, err
    assert abs(float(ex.contact_fraction[0, 0]) - float(se.contact_fraction[0, 0])) < 0.01
    # and it is really first order: at dt = 1e-5 the error is about 10x larger
    se10 = simulate(M, D, K, [stop], B, C, F, DT_LOAD, output_dt=DT_LOAD, dt=1e-5, method="symplectic-euler")
    err10 = np.max(np.abs(y_ex - se10.observations.values[0])) / np.max(np.abs(y_ex))
    assert 4 < err10 / err < 25, (err, err10)


def test_batch_equals_one_by_one_bitwise():
    M, D, K, stop, B, C, F0 = contact_setup(n_t=81)
    rng = rng_for(7, "batch")
    R = 3
    Ks = np.array([K * (1 + 0.1 * rng.uniform()) for _ in range(R)])
    loads = np.array([F0 * (1 + 0.2 * r) for r in range(R)])
    batch = simulate(M, D, Ks, [stop], B, C, loads, DT_LOAD, output_dt=2e-3)
    for r in range(R):
        one = simulate(M, D, Ks[r], [stop], B, C, loads[r], DT_LOAD, output_dt=2e-3)
        assert np.array_equal(batch.observations.values[r], one.observations.values[0])
        assert np.array_equal(batch.rms.values[r], one.rms.values[0])
        assert np.array_equal(batch.contact_fraction.values[r], one.contact_fraction.values[0])


def test_tables_are_built_once_per_system_and_reused_bit_identically(monkeypatch):
    """The exact method's tables are kept per process under a digest of their inputs: the same
    system simulated again (another call, as a trial grid simulates each realisation at every grid
    point) builds nothing and gives the bits of a cold build; changing any input the tables depend
    on (1 ulp of D, the gap, the step, B) builds anew; at most TABLE_CACHE_BYTES are kept."""
    from tubeid.dynamics.solver import _regimes

    M, D, K, stop, B, C, F = contact_setup(n_t=81)
    builds = []
    real = _regimes.build_tables

    def counting(*args):
        builds.append(args)
        return real(*args)

    monkeypatch.setattr(_regimes, "build_tables", counting)
    monkeypatch.setattr(_regimes, "_CACHE", type(_regimes._CACHE)())

    def run(D_=D, stop_=stop, B_=B, dt=None, dt_load=DT_LOAD):
        return simulate(M, D_, K, [stop_], B_, C, F, dt_load, output_dt=2e-3, dt=dt).observations.values

    cold = run()
    assert len(builds) == 1
    again = run()
    assert len(builds) == 1 and np.array_equal(again, cold)  # the same bits, nothing rebuilt
    D2 = D.copy()
    D2[1, 1] = np.nextafter(D2[1, 1], np.inf)
    h = choose_step(highest_frequency(M, K, [stop]), DT_LOAD, 2e-3)
    B2 = B.copy()
    B2[2, 0] = 2.0
    for kwargs in ({"D_": D2}, {"stop_": Stop(stop.b, stop.gap * 1.5, stop.stiffness)}, {"dt": h / 2}, {"B_": B2},
                   {"dt": h / 2, "dt_load": DT_LOAD / 2}):  # the last: the same sub-steps per load interval
        n = len(builds)
        run(**kwargs)
        assert len(builds) == n + 1, kwargs  # a new system: new tables
    n = len(builds)
    assert np.array_equal(run(), cold) and len(builds) == n  # the first system is still kept
    size = next(iter(_regimes._CACHE.values()))[2]
    monkeypatch.setattr(_regimes, "TABLE_CACHE_BYTES", int(1.5 * size))  # room for one system's tables
    D3 = D.copy()
    D3[0, 0] *= 1.01
    run(D_=D3)
    assert len(_regimes._CACHE) == 1
    n = len(builds)
    assert np.array_equal(run(), cold) and len(builds) == n + 1  # evicted, rebuilt, the same bits
    monkeypatch.setattr(_regimes, "TABLE_CACHE_BYTES", size // 2)  # one system's tables exceed it: none kept
    run(D_=D3)
    assert len(_regimes._CACHE) == 0


def test_event_precheck_misses_nothing():
    """Default detection (Hermite pre-check with margin) vs exact re-examination of every step."""
    M, D, K, stop, B, C, F = contact_setup(n_t=1001)
    a, d1 = simulate_with_diagnostics(M, D, K, [stop], B, C, F, DT_LOAD, output_dt=DT_LOAD)
    b, d2 = simulate_with_diagnostics(M, D, K, [stop], B, C, F, DT_LOAD, output_dt=DT_LOAD, refine_all=True)
    assert d1[0]["flagged_steps"] < d2[0]["flagged_steps"] == d2[0]["steps"]
    assert a.contact_events.values[0, 0] == b.contact_events.values[0, 0] > 20
    ya, yb = a.observations.values[0], b.observations.values[0]
    # same events -> same piecewise-exact solution up to roundoff (no chaos at this amplitude in 1 s)
    assert np.max(np.abs(ya - yb)) < 1e-8 * np.max(np.abs(yb))



def test_the_exact_solution_does_not_depend_on_the_step_on_a_bundle_with_many_contacts():
    """Between events the method is exact whatever the sub-step: on the paper's mean simplified
    bundle (its stop, the 7-point coherent load, 1 s: about 200 switches), four steps (0.25 ms by
    the rule, 1/3, 0.2 and 0.125 ms, so 8, 6, 10 and 16 sub-steps per 2 ms load sample: other
    blocks, other switch positions within them) give the same switches and the same response to
    ~1e-11 (measured; asserted 1e-8). Longer records diverge (chaotic runs: on the bench's random
    realisation ~1e-6 of the peak after 5 s, of its order after 20 s)."""
    from tubeid.dynamics.response import _load_points
    from tubeid.mechanics.library import builtin_spec
    from tubeid.mechanics.reduction import reduce
    from tubeid.uncertainty.loads import coherent_forces
    from tubeid.uncertainty.processes import gaussian_loads

    model = reduce(builtin_spec("paper-simplified"))
    load = coherent_forces()
    M, D, K = model.mean_matrices
    B, C = model.load_matrix(_load_points(load)), model.sensor_matrix()
    stops = [Stop(b=tuple(b), gap=s.gap, stiffness=s.stiffness) for b, s in zip(model.stop_vectors(), model.spec.stops)]
    F = gaussian_loads(load, 1.0, 2e-3, [rng_for(1, "step-independence")])[0]
    runs = [simulate_with_diagnostics(M, D, K, stops, B, C, F, 2e-3, output_dt=1e-3, dt=dt)
            for dt in (None, 1e-3 / 3, 2e-4, 1.25e-4)]
    assert [float(r.dt.values[0]) for r, _ in runs] == [2.5e-4, 1e-3 / 3, 2e-4, 1.25e-4]
    switches = [d[0]["switches"] for _, d in runs]
    assert switches[0] > 100 and len(set(switches)) == 1
    y0 = runs[0][0].observations.values[0, :, 0]
    cf0 = runs[0][0].contact_fraction.values[0, 0]
    assert 0.2 < cf0 < 0.8
    for r, _ in runs[1:]:
        assert np.max(np.abs(r.observations.values[0, :, 0] - y0)) < 1e-8 * np.max(np.abs(y0))
        assert abs(r.contact_fraction.values[0, 0] - cf0) < 1e-6


def test_zero_gap_is_linear_spring():
    M, D, K = chain()
    b = np.eye(4)[1]
    B = np.ones((4, 1))
    F = rng_for(2, "gap0").normal(size=(51, 1))
    a = simulate(M, D, K, [Stop(b, 0.0, 3e4)], B, np.eye(4), F, DT_LOAD, output_dt=DT_LOAD)
    c = simulate(M, D, K + 3e4 * np.outer(b, b), [], B, np.eye(4), F, DT_LOAD, output_dt=DT_LOAD)
    np.testing.assert_allclose(a.observations.values, c.observations.values, rtol=0, atol=1e-12 * np.abs(c.observations.values).max())
    assert a.contact_fraction.values[0, 0] == 1.0


def test_keep_stats_and_discard():
    M, D, K, stop, B, C, F = contact_setup(n_t=201)
    full = simulate(M, D, K, [stop], B, C, F, DT_LOAD, output_dt=2e-3)
    st = simulate(M, D, K, [stop], B, C, F, DT_LOAD, output_dt=2e-3, keep="stats")
    assert st.observations is None
    assert np.array_equal(full.rms.values, st.rms.values)
    y = full.observations.values[0]
    np.testing.assert_allclose(full.rms.values[0], np.sqrt(np.mean(y**2, axis=0)), rtol=1e-12)
    dis = simulate(M, D, K, [stop], B, C, F, DT_LOAD, output_dt=2e-3, discard=0.05)
    assert dis.observations.time.values[0] == pytest.approx(0.05, abs=0)
    np.testing.assert_array_equal(dis.observations.values[0], y[25:])
    np.testing.assert_allclose(dis.rms.values[0], np.sqrt(np.mean(y[25:] ** 2, axis=0)), rtol=1e-12)
    assert set(dis.to_dataset().data_vars) >= {"observations", "rms", "contact_fraction", "contact_events"}


def test_highest_frequency_and_choose_step():
    m, k, ks = 2.0, 1e4, 3e4
    f = highest_frequency([[m]], [[k]], [Stop([1.0], 1e-3, ks)])
    assert f == pytest.approx(math.sqrt((k + ks) / m) / (2 * math.pi), rel=1e-12, abs=0)
    dt = choose_step(950.0, 1e-3, 3e-3)
    assert dt <= 1 / (4 * 950.0)
    for big in (1e-3, 3e-3):
        assert abs(big / dt - round(big / dt)) < 1e-9
    assert choose_step(950.0, 1e-3, 3e-3) == pytest.approx(1e-3 / 4, abs=0)  # 4 points per period of f_max
    dse = choose_step(950.0, 1e-3, 3e-3, method="symplectic-euler")
    assert 2 * math.pi * 950 * dse <= 0.25
    # incommensurate dt_load and output_dt still get a common divisor
    dt2 = choose_step(100.0, 0.7e-3, 3e-3)
    assert abs(0.7e-3 / dt2 - round(0.7e-3 / dt2)) < 1e-9 and abs(3e-3 / dt2 - round(3e-3 / dt2)) < 1e-9


@pytest.mark.parametrize("M, K, field", [
    (-np.eye(2), np.eye(2), "M"),  # numpy's LinAlgError from inside scipy's eigh without the check
    (np.diag([1.0, 0.0]), np.eye(2), "M"),
    (np.eye(2), -np.eye(2), "K"),  # silently 0 Hz without the check (sqrt of max(w2, 0))
])
def test_highest_frequency_refuses_matrices_simulate_refuses(M, K, field):
    """M and K must be positive definite, as ``simulate`` asks: a clear refusal naming the field,
    not a LinAlgError from inside scipy nor a silent 0 Hz."""
    with pytest.raises(SpecificationError, match=rf"^{field} = .*must be positive definite"):
        highest_frequency(M, K)
    with pytest.raises(SpecificationError, match=rf"^{field} = .*must be positive definite"):
        simulate(M, 0 * np.eye(2), K, [], np.ones(2), np.eye(2), np.ones((3, 1)), 1e-3, output_dt=1e-3)


def test_step_refusals_and_warnings():
    M, D, K, stop, B, C, F = contact_setup(n_t=31)
    fmax = highest_frequency(M, K, [stop])
    stiff = Stop(stop.b, stop.gap, 1e8)  # f_max ~ 1.6 kHz, like the paper's ~950 Hz
    with pytest.raises(SpecificationError, match="output sampling"):
        simulate(M, D, K, [stiff], B, C, F, DT_LOAD, output_dt=3e-3, dt=3e-3)
    with pytest.raises(SpecificationError, match="output sampling"):
        simulate(M, D, K, [stiff], B, C, F, DT_LOAD, output_dt=3e-3, dt=3e-3, method="symplectic-euler")
    with pytest.raises(SpecificationError, match="multiple"):
        simulate(M, D, K, [stop], B, C, F, DT_LOAD, dt=0.3e-3)
    f_stiff = highest_frequency(M, K, [stiff])
    with pytest.raises(SpecificationError, match="1/\\(2 f_max\\)"):
        simulate(M, D, K, [stiff], B, C, F, DT_LOAD, dt=1e-3)  # 1 ms > 1/(2 f_max)
    n = math.ceil(2 * f_stiff * DT_LOAD * (1 + 1e-12))  # largest divisor step <= 1/(2 f_max)
    assert DT_LOAD / n > 1 / (3 * f_stiff)  # ... which is in the warned band
    with pytest.warns(UserWarning, match="1/\\(3 f_max\\)"):
        simulate(M, D, K, [stiff], B, C, F, DT_LOAD, dt=DT_LOAD / n)
    n4 = math.ceil(4 * f_stiff * DT_LOAD * (1 - 1e-12))  # a step just within the default rule ...
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        simulate(M, D, K, [stiff], B, C, F, DT_LOAD, dt=DT_LOAD / n4)  # ... is accepted silently
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        simulate(M, D, K, [stop], B, C, F, DT_LOAD)  # default step: no warning
    # symplectic Euler: stable but w dt > 0.5 warns; w dt >= 2 refused
    w = 2 * math.pi * fmax
    dt_w = 1e-3 / math.ceil(1e-3 / (1.0 / w))  # w dt in (0.5, 1]
    with pytest.warns(UserWarning, match="symplectic Euler"):
        simulate(M, D, K, [stop], B, C, F, DT_LOAD, dt=dt_w, method="symplectic-euler")
    with pytest.raises(SpecificationError, match="unstable"):
        simulate(M, D, K, [stiff], B, C, F, DT_LOAD, dt=DT_LOAD / 4, method="symplectic-euler")  # w dt ~ 2.5


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(gap=-1e-6, stiffness=1e8),
        dict(gap=1e-6, stiffness=-1.0),
        dict(gap=float("nan"), stiffness=1.0),
        dict(gap=1e-6, stiffness=float("inf")),
        dict(gap="1", stiffness=1.0),
    ],
)
def test_stop_validation(kwargs):
    with pytest.raises(SpecificationError):
        Stop([1.0, 0.0], **kwargs)


def test_input_validation():
    M, D, K = chain()
    B = np.ones((4, 1))
    F = np.zeros((11, 1))
    with pytest.raises(SpecificationError, match="stop.b"):
        Stop([0.0, 0.0], 1e-6, 1.0)
    with pytest.raises(SpecificationError, match="length"):
        simulate(M, D, K, [Stop([1.0, 0.0], 1e-6, 1.0)], B, np.eye(4), F, DT_LOAD)
    with pytest.raises(SpecificationError, match="symmetric"):
        simulate(M, D, K + np.triu(np.ones((4, 4)), 1), [], B, np.eye(4), F, DT_LOAD)
    with pytest.raises(SpecificationError, match="positive definite"):
        simulate(M, D, -K, [], B, np.eye(4), F, DT_LOAD)
    with pytest.raises(SpecificationError, match="loads.shape"):
        simulate(M, D, K, [], B, np.eye(4), np.zeros((11, 2)), DT_LOAD)
    with pytest.raises(SpecificationError, match="discard"):
        simulate(M, D, K, [], B, np.eye(4), F, DT_LOAD, discard=1.0)
    with pytest.raises(SpecificationError, match="method"):
        simulate(M, D, K, [], B, np.eye(4), F, DT_LOAD, method="euler")


def test_exact_evaluation_matches_block_rows_numpy_exp_and_its_derivatives():
    """The event path's exact evaluation of u, u', u'' (tabulated e^{lam tau} times a short series,
    then the segment's modal coefficients) against: the fast path's block rows at tau = h (other
    tables, other formula), numpy's complex exp for the propagated modal state, and finite
    differences of itself; every regime, random homogeneous state and piecewise-linear load."""
    from tubeid.dynamics.solver import _events, _modal, _regimes, _work

    M, D, K, stop, B, C, F = contact_setup()
    f_max = highest_frequency(M, K, [stop])
    h = choose_step(f_max, DT_LOAD)
    ns = int(round(DT_LOAD / h))
    tb, info = _regimes.build_tables(M, D, K, (stop,), B, C, h, ns, 2 * math.pi * f_max)
    rng = rng_for(4, "exact-evaluation")
    n2, m = info["n_modes"], B.shape[1]
    n2p = tb.lam_re.shape[1]
    nx = 2 * n2p
    W = _work.make_work(tb, C.shape[0])
    lam = tb.lam_re[:, :n2] + 1j * tb.lam_im[:, :n2]

    def evaluate(r, tau):
        _events.evaluate(tb.lam_re, tb.lam_im, tb.fine_re, tb.fine_im, tb.basis[r], h, tau, W.A, W.QS, W.E, W.ev)
        return W.ev[:3].copy()

    for r in range(len(tb.codes)):
        x0 = np.zeros(tb.block_rows.shape[2])  # [zeta; f; f'; 1] at the segment start
        x0[:n2], x0[n2p:n2p + n2] = rng.normal(size=(2, n2)) * 1e-6
        f0, fdot = rng.normal(size=m), rng.normal(size=m) / DT_LOAD
        x0[nx:nx + m], x0[nx + m:nx + 2 * m], x0[nx + 2 * m] = f0, fdot, 1.0
        W.X[_work.X0] = x0
        W.L[_work.FS, :m], W.L[_work.F1, :m] = f0, fdot
        _events.segment_coefficients(tb, W, r, m, 0.0)
        # u, u' at tau = h against the block rows (table e^{lam h}, quasi-static rows at mm = 1):
        # same quantity from different tables, round-off only (1e-12 of the scale)
        u, ud, udd = evaluate(r, h)
        col = tb.block_rows[r, :2] @ x0
        assert abs(col[0] - u) <= 1e-12 * abs(u) and abs(col[1] - ud) <= 1e-12 * abs(ud), (r, col[:2], u, ud)
        for tau in (0.0, 0.37 * h, h):
            # the propagated homogeneous state: e^{lam tau} z to 1e-14 relative (table times a
            # degree-9 series: truncation < 1e-19, the rest is round-off)
            _modal.expmul(tb.lam_re, tb.lam_im, tb.fine_re, tb.fine_im, tb.basis[r], h, tau, x0, W.X[_work.XS], W.E)
            zt = W.X[_work.XS]
            zc = x0[:n2] + 1j * x0[n2p:n2p + n2]
            want = np.exp(lam[tb.basis[r]] * tau) * zc
            got = zt[:n2] + 1j * zt[n2p:n2p + n2]
            assert np.max(np.abs(got - want)) <= 1e-14 * np.max(np.abs(want))
            # u' and u'' against central differences of u and u' (step 1e-3 h: truncation ~1e-7
            # of the scale at the highest frequency, round-off ~1e-10): tolerance 1e-5
            e = 1e-3 * h
            t1, t2 = (tau - e, tau + e) if 0 < tau < h else ((tau, tau + 2 * e) if tau == 0 else (tau - 2 * e, tau))
            ua, uda, _ = evaluate(r, t1)
            ub, udb, _ = evaluate(r, t2)
            um, udm, uddm = evaluate(r, 0.5 * (t1 + t2))
            assert abs((ub - ua) / (t2 - t1) - udm) <= 1e-5 * max(abs(udm), abs(um) / h), (r, tau)
            assert abs((udb - uda) / (t2 - t1) - uddm) <= 1e-5 * max(abs(uddm), abs(udm) / h), (r, tau)


# ------------------------------------------------------------------ bit-identity across processes

_BIT_IDENTITY_SCRIPT = """
import hashlib, json
from tubeid.dynamics.solver import Stop, simulate
from tubeid.dynamics.solver import _fastpath
from tubeid.mechanics import builtin_spec, reduce
from tubeid.seeds import rng_for
model = reduce(builtin_spec("paper-reference"))  # 50 coordinates: its tables depend on BLAS threads
M, D, K = model.mean_matrices
stops = [Stop(b=tuple(b), gap=s.gap, stiffness=s.stiffness) for b, s in zip(model.stop_vectors(), model.spec.stops)]
B, C = model.load_matrix(), model.sensor_matrix()
F = 40.0 * rng_for(11, "bit-identity").standard_normal((3001, B.shape[1]))
y = simulate(M, D, K, stops, B, C, F, 1e-3, output_dt=1e-3).observations.values
st = _fastpath.run_exact.stats
import tubeid
print(json.dumps({"sha256": hashlib.sha256(y.tobytes()).hexdigest(), "compiled": sum(st.cache_misses.values()),
                  "tubeid": tubeid.__file__,
                  "loaded": sum(st.cache_hits.values()), "contacts": int((abs(y[0, :, 0]) > 0).sum())}))
"""


def _run_in_subprocess(blas_threads: int, cache_dir, pythonpath=None) -> dict:
    """The paper-reference model with contact for 3 s in a new process: hash of the series and
    whether the kernel was compiled or loaded from numba's cache (``pythonpath``: import tubeid from
    there)."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS=str(blas_threads), OMP_NUM_THREADS=str(blas_threads),
               MKL_NUM_THREADS=str(blas_threads))
    env["NUMBA_CACHE_DIR"] = str(cache_dir)
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath)
    res = subprocess.run([sys.executable, "-c", _BIT_IDENTITY_SCRIPT], capture_output=True, text=True, env=env,
                         timeout=900, cwd=pythonpath)  # `-c` puts the working directory first on sys.path
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


def test_results_do_not_depend_on_the_blas_threads_of_the_process():
    """Dask workers run with one BLAS thread, a Python session may use several: the tables are
    computed with one thread whatever the caller's setting (without that, on this 50-coordinate
    model 1 and 2 threads give series that differ after a fraction of a second)."""
    from threadpoolctl import threadpool_limits

    from tubeid.mechanics import builtin_spec, reduce

    model = reduce(builtin_spec("paper-reference"))
    M, D, K = model.mean_matrices
    stops = [Stop(b=tuple(b), gap=s.gap, stiffness=s.stiffness) for b, s in zip(model.stop_vectors(), model.spec.stops)]
    B, C = model.load_matrix(), model.sensor_matrix()
    F = 40.0 * rng_for(11, "bit-identity").standard_normal((3001, B.shape[1]))
    series = []
    for threads in (1, 2):
        with threadpool_limits(limits=threads):
            series.append(simulate(M, D, K, stops, B, C, F, DT_LOAD, output_dt=DT_LOAD).observations.values)
    assert np.array_equal(series[0], series[1])


@pytest.mark.slow
def test_compiled_and_cached_kernels_give_the_same_bits(tmp_path):
    """A process compiling the kernels into an empty numba cache and a process loading them from
    that cache (with another BLAS thread count) produce the same bytes."""
    cold = _run_in_subprocess(2, tmp_path / "numba-cache")
    warm = _run_in_subprocess(1, tmp_path / "numba-cache")
    assert cold["compiled"] >= 1 and cold["loaded"] == 0, cold  # the first process really compiled ...
    assert warm["loaded"] >= 1 and warm["compiled"] == 0, warm  # ... and the second really loaded
    assert cold["sha256"] == warm["sha256"], (cold, warm)


def test_the_noalias_pipeline_falls_back_on_another_numba_compiler_api(monkeypatch):
    """The kernels' LLVM ``noalias`` pipeline hooks numba's internal Compiler; a numba whose Compiler
    takes other arguments (or has no ``noalias`` flag) gets numba's Compiler itself, one without that
    class numba's default pipeline: never a failure at import or at the first call."""
    import numba.core.compiler

    from tubeid.dynamics.solver import _modal

    here = _modal._no_alias_compiler()
    assert here is not None and issubclass(here, numba.core.compiler.Compiler)
    monkeypatch.setattr(_modal, "_COMPILER_ARGS", _modal._COMPILER_ARGS + ["pipeline"])
    assert _modal._no_alias_compiler() is numba.core.compiler.Compiler
    monkeypatch.delattr(numba.core.compiler, "Compiler")
    assert _modal._no_alias_compiler() is None
    monkeypatch.undo()
    for options in ({"pipeline_class": here}, {"pipeline_class": numba.core.compiler.Compiler}, {}):
        @numba.njit(**options)
        def add(a, b, out):
            for i in range(a.shape[0]):
                out[i] = a[i] + b[i]

        out = np.empty(3)
        add(np.arange(3.0), np.ones(3), out)
        assert out.tolist() == [1.0, 2.0, 3.0]


def test_every_cached_kernel_is_keyed_on_all_the_solver_sources(tmp_path):
    """numba keys a cached kernel on its own file's stamp; the solver's are keyed on a fingerprint of
    every solver source, which changes with any of them."""
    import shutil

    from tubeid.dynamics import solver
    from tubeid.dynamics.solver import _events, _fastpath, _kernel_cache, _modal, _symplectic

    kernels = _kernel_cache.cached_kernels([_modal, _events, _fastpath, _symplectic])
    names = {k.py_func.__name__ for k in kernels}
    assert {"run_exact", "event_step", "evaluate", "set_load", "_kernel"} <= names
    fingerprint = _kernel_cache.sources_fingerprint()
    assert {k._cache._cache_file._source_stamp for k in kernels} == {fingerprint}
    copy = tmp_path / "solver"
    shutil.copytree(pathlib.Path(solver.__file__).parent, copy, ignore=shutil.ignore_patterns("__pycache__"))
    assert _kernel_cache.sources_fingerprint(copy) == fingerprint
    (copy / "_work.py").write_text((copy / "_work.py").read_text() + "\n")
    assert _kernel_cache.sources_fingerprint(copy) != fingerprint


@pytest.mark.slow
def test_an_edit_of_a_callee_recompiles_the_cached_main_loop(tmp_path):
    """The main loop compiles _modal's primitives into its own code: after an edit of _modal.py alone,
    the next process runs the edited code, not the cached main loop (with numba's own key it did)."""
    import shutil

    import tubeid

    src = tmp_path / "src"
    shutil.copytree(pathlib.Path(tubeid.__file__).parent, src / "tubeid", ignore=shutil.ignore_patterns("__pycache__"))
    cache = tmp_path / "numba-cache"
    first = _run_in_subprocess(1, cache, src)
    again = _run_in_subprocess(1, cache, src)
    assert first["tubeid"].startswith(str(src)), first  # the copy is what runs
    assert first["compiled"] >= 1 and again["loaded"] >= 1 and again["compiled"] == 0
    assert again["sha256"] == first["sha256"]
    modal = src / "tubeid" / "dynamics" / "solver" / "_modal.py"
    text = modal.read_text()
    at = text.index("x[nx + l] = fs[l] + f1[l] * t", text.index("def set_load("))
    modal.write_text(text[:at] + "x[nx + l] = 1.001 * fs[l] + f1[l] * t" + text[at + len("x[nx + l] = fs[l] + f1[l] * t"):])
    edited = _run_in_subprocess(1, cache, src)
    assert edited["compiled"] >= 1 and edited["sha256"] != first["sha256"], edited


@pytest.mark.parametrize("which", ["M", "D", "K", "B", "C", "loads"])
def test_complex_inputs_are_refused_not_truncated(which):
    """numpy dropped the imaginary part with only a ComplexWarning: refused, naming the argument."""
    M, D, K = chain()
    args = dict(M=M, D=D, K=K, B=np.ones((4, 1)), C=np.eye(4), loads=np.zeros((11, 1)))
    args[which] = args[which] + 1e-3j
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no ComplexWarning on the way
        with pytest.raises(SpecificationError, match=rf"^{which} = array of dtype complex128, shape \(\d+, \d+\): "
                                                     r"must be an array of real numbers \(complex values are not "
                                                     r"truncated to their real part\)"):
            simulate(args["M"], args["D"], args["K"], [], args["B"], args["C"], args["loads"], DT_LOAD)


@pytest.mark.parametrize("b, needle", [
    ((1.0 + 1e-3j, 0.0, 0.0, 0.0), r"^stop.b = array of dtype complex128, shape \(4,\): must be an array of real numbers "
                                   r"\(complex values are not truncated"),
    ((True, False, False, False), r"^stop.b = array of dtype bool, shape \(4,\): must be an array of real numbers"),
    (("1", "0", "0", "0"), r"^stop.b = array of dtype <U1, shape \(4,\): must be an array of real numbers")])
def test_stop_vector_must_hold_real_numbers(b, needle):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(SpecificationError, match=needle):
            Stop(b, 1e-6, 1.0)


def test_a_matrix_given_as_a_stop_row_is_refused_not_flattened():
    """b is one row of the model's coordinates: a (2, 2) matrix was flattened into a 4-vector and
    accepted silently; a single row or column is a vector and is kept."""
    with pytest.raises(SpecificationError, match=r"^stop\.b = an array of shape \(2, 2\): must be a vector "
                                                 r"\(1-D, or a single row or column\)$"):
        Stop(b=[[1.0, 0.0], [0.0, 1.0]], gap=0.0, stiffness=1.0)
    for b in ([[1.0, 0.0, 2.0]], [[1.0], [0.0], [2.0]], [1.0, 0.0, 2.0]):
        assert Stop(b=b, gap=0.0, stiffness=1.0).b == (1.0, 0.0, 2.0)


def test_bool_and_string_arrays_are_refused():
    M, D, K = chain()
    with pytest.raises(SpecificationError, match=r"^C = array of dtype bool, shape \(4, 4\): must be an array of real numbers"):
        simulate(M, D, K, [], np.ones((4, 1)), np.eye(4, dtype=bool), np.zeros((11, 1)), DT_LOAD)
    with pytest.raises(SpecificationError, match=r"^B = array of dtype <U1, shape \(4, 1\): must be an array of real numbers"):
        simulate(M, D, K, [], [["1"], ["0"], ["0"], ["0"]], np.eye(4), np.zeros((11, 1)), DT_LOAD)


def test_stop_labels_must_be_distinct():
    """The default label stop<i> collided with a user's name (the stop coordinate read ['stop1', 'stop1']):
    refused up front, as two stops given one name."""
    M, D, K = chain()
    B, C, F = np.ones((4, 1)), np.eye(4)[:2], np.zeros((11, 1))
    e0, e1 = np.eye(4)[0], np.eye(4)[1]
    with pytest.raises(SpecificationError, match=r"stops\[1\].name = 'stop1': must differ from the label of stops\[0\]"):
        simulate(M, D, K, [Stop(e0, 1e-3, 1e4, name="stop1"), Stop(e1, 1e-3, 1e4)], B, C, F, DT_LOAD)
    with pytest.raises(SpecificationError, match=r"stops\[1\].name = 'a': must differ from the label of stops\[0\]"):
        simulate(M, D, K, [Stop(e0, 1e-3, 1e4, name="a"), Stop(e1, 1e-3, 1e4, name="a")], B, C, F, DT_LOAD)
    res = simulate(M, D, K, [Stop(e0, 1e-3, 1e4, name="stop1"), Stop(e1, 1e-3, 1e4, name="x")], B, C, F, DT_LOAD)
    assert list(res.contact_events.stop.values) == ["stop1", "x"]
    # the defaults stay as they were: stop<i>
    res = simulate(M, D, K, [Stop(e0, 1e-3, 1e4), Stop(e1, 1e-3, 1e4)], B, C, F, DT_LOAD)
    assert list(res.contact_events.stop.values) == ["stop0", "stop1"]


def test_sensor_names_must_be_distinct_strings():
    """Repeated sensor names labelled two outputs alike; a bare string was split into its characters."""
    M, D, K = chain()
    B, C, F = np.ones((4, 1)), np.eye(4)[:2], np.zeros((11, 1))
    with pytest.raises(SpecificationError, match=r"sensor_names\[1\] = 'a': must differ from sensor_names\[0\]"):
        simulate(M, D, K, [], B, C, F, DT_LOAD, sensor_names=["a", "a"])
    with pytest.raises(SpecificationError, match=r"sensor_names = 'ab': must be a sequence of names"):
        simulate(M, D, K, [], B, C, F, DT_LOAD, sensor_names="ab")
    with pytest.raises(SpecificationError, match=r"sensor_names\[0\] = 0: must be a string"):
        simulate(M, D, K, [], B, C, F, DT_LOAD, sensor_names=[0, 1])
    assert list(simulate(M, D, K, [], B, C, F, DT_LOAD, sensor_names=["a", "b"]).rms.sensor.values) == ["a", "b"]
    assert list(simulate(M, D, K, [], B, C, F, DT_LOAD).rms.sensor.values) == ["y0", "y1"]  # the default y<i>


def test_an_output_step_longer_than_the_record_is_refused():
    """output_dt = 5 s on a 1 s record returned one sample at t = 0 (rms 0.0) beside a contact fraction."""
    F = rng_for(3, "long_output_dt").standard_normal((1001, 1))
    args = (np.eye(1), 0.1 * np.eye(1), 100.0 * np.eye(1), [], np.eye(1), np.eye(1), F, DT_LOAD)
    with pytest.raises(SpecificationError, match=r"^output_dt = 5.0: must not exceed the record's duration "
                                                 r"\(n_t − 1\) dt_load = 1 s"):
        simulate(*args, output_dt=5.0)
    assert simulate(*args, output_dt=1.0).observations.sizes["time"] == 2  # the whole record still allowed


def _stiff_stop_problem(k, n_t):
    """The paper's simplified model with its stop of stiffness ``k`` (gap 1.5 µm), zero loads of n_t samples."""
    from tubeid.mechanics import builtin_spec, reduce

    model = reduce(builtin_spec("paper-simplified"))
    M, D, K = model.mean_matrices
    stop = Stop(b=tuple(model.stop_vectors()[0]), gap=1.5e-6, stiffness=k)
    return M, D, K, stop, model.load_matrix(), model.sensor_matrix(), np.zeros((n_t, model.load_matrix().shape[1]))


_STIFF_STOP_SCRIPT = """
import numpy as np
from tubeid.dynamics.solver import Stop, simulate
from tubeid.errors import SpecificationError
from tubeid.mechanics import builtin_spec, reduce
model = reduce(builtin_spec("paper-simplified"))
M, D, K = model.mean_matrices
stop = Stop(b=tuple(model.stop_vectors()[0]), gap=1.5e-6, stiffness=1e24)
try:
    simulate(M, D, K, [stop], model.load_matrix(), model.sensor_matrix(), np.zeros((110001, 7)), 2e-3)
except SpecificationError as exc:
    print(exc)
"""


def test_a_stop_far_too_stiff_is_refused_by_the_sub_steps_it_would_take_before_any_integration():
    """A 1e24 N/m stop makes f_max 1.3e10 Hz: the step rule's 1.9e-11 s step takes 1.15e13 sub-steps for
    220 s (measured at 9-23 ns each: 28 to 73 hours per realisation). It ran; it is now refused at once,
    naming the stop's stiffness, with the count the public step functions give. (In a process of its
    own: the kernels hold the interpreter, so a hang could not be ended from inside.)"""
    import re

    M, D, K, stop, B, C, F = _stiff_stop_problem(1e24, 2)
    n = math.ceil(220.0 / choose_step(highest_frequency(M, K, [stop]), 2e-3, 3e-3) - 1e-9)
    assert 1.1e13 < n < 1.2e13
    try:
        res = subprocess.run([sys.executable, "-c", _STIFF_STOP_SCRIPT], capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail("simulate with a 1e24 N/m stop still ran after 60 s instead of refusing")
    assert res.returncode == 0, res.stderr[-3000:]
    assert re.match(rf"^stops\[0\]\.stiffness = 1e\+24: with the stops closed the highest frequency is f_max = "
                    rf"1\.303e\+10 Hz \(open: 940\.5 Hz\), and the exact method's step rule .* "
                    rf"{re.escape(f'{n:.3g}')} sub-steps per realisation for 220 s, more than 1e\+09 \(configuration "
                    r"tubeid\.io\.max-substeps", res.stdout), res.stdout


def test_the_sub_step_limit_names_the_stop_or_the_duration_and_the_value_that_keeps_within_it():
    """With the limit lowered to 1e4 (the configuration's tubeid.io.max-substeps): a 1e12 N/m stop for
    0.2 s takes ~1.04e4 sub-steps and is refused naming it, and the stiffness the message says keeps
    within the limit runs; the paper's stop for 4 s (16 000 sub-steps) is refused naming the duration."""
    import re

    import dask.config

    M, D, K, stop, B, C, F = _stiff_stop_problem(1e12, 201)  # 0.2 s at 1 ms
    n = math.ceil(0.2 / choose_step(highest_frequency(M, K, [stop]), 1e-3, 1e-3) - 1e-9)
    assert n > 1e4
    with dask.config.set({"tubeid.io.max-substeps": 1e4}):
        with pytest.raises(SpecificationError, match=rf"^stops\[0\]\.stiffness = 1000000000000\.0: .* {re.escape(f'{n:.3g}')} sub-steps "
                                                     r"per realisation for 0\.2 s, more than 1e\+04 .*; a stiffness of at "
                                                     r"most about .* N/m keeps within the limit$") as err:
            simulate(M, D, K, [stop], B, C, F, 1e-3, output_dt=1e-3)
        k_ok = float(re.search(r"at most about (\S+) N/m", str(err.value)).group(1))
        assert 1e11 < k_ok < 1e12
        ok = Stop(stop.b, stop.gap, k_ok)
        assert math.ceil(0.2 / choose_step(highest_frequency(M, K, [ok]), 1e-3, 1e-3) - 1e-9) <= 1e4
        simulate(M, D, K, [ok], B, C, F, 1e-3, output_dt=1e-3)
        _, _, _, paper, _, _, F4 = _stiff_stop_problem(1e8, 4001)  # 4 s: 16 000 sub-steps of 0.25 ms
        with pytest.raises(SpecificationError, match=r"^loads = 4001 samples at dt_load = 0\.001 s: .* 1\.6e\+04 "
                                                     r"sub-steps per realisation for 4 s, .*; at most about 2\.5 s keeps "
                                                     r"within the limit at this f_max$"):
            simulate(M, D, K, [paper], B, C, F4, 1e-3, output_dt=1e-3)


def test_a_counter_added_to_stats_gets_a_slot_inside_the_array():
    """``_work.STATS`` is the one list of the kernels' counters: N_STATS and every slot derive from
    it. The kernels do not check bounds, so a slot past a hard-coded N_STATS writes outside the
    ``stats`` array silently (no error, no diagnostics key). Checked by growing STATS in a copy of
    ``_work``'s source."""
    import inspect

    from tubeid.dynamics.solver import _work

    src = inspect.getsource(_work)
    line = "STATS = (" + ", ".join(f'"{name}"' for name in _work.STATS) + ")"
    assert src.count(line) == 1
    ns = {"__name__": "grown_work"}
    exec(compile(src.replace(line, line[:-1] + ', "new_counter")'), "grown_work", "exec"), ns)
    assert ns["STATS"][-1] == "new_counter"
    assert ns["N_STATS"] == len(_work.STATS) + 1
    slots = {name: ns[name.upper()] for name in _work.STATS}
    assert sorted(slots.values()) == list(range(len(_work.STATS)))  # distinct, inside the array
    assert {name: getattr(_work, name.upper()) for name in _work.STATS} == slots


def test_the_diagnostics_report_every_counter_of_stats(monkeypatch):
    """``_exact`` reports each name of ``STATS`` from its slot (a counter added there needs no second
    list): with one more name (an extra slot nothing increments) the report gains that key, 0,
    and the other counters are unchanged."""
    from tubeid.dynamics.solver import _exact, _work

    M, D, K, stop, B, C, F = contact_setup()
    before = simulate_with_diagnostics(M, D, K, [stop], B, C, F, DT_LOAD, output_dt=DT_LOAD)[1][0]
    assert set(_work.STATS) <= set(before) and before["switches"] > 0
    monkeypatch.setattr(_exact, "STATS", _work.STATS + ("new_counter",))
    monkeypatch.setattr(_exact, "N_STATS", _work.N_STATS + 1)
    after = simulate_with_diagnostics(M, D, K, [stop], B, C, F, DT_LOAD, output_dt=DT_LOAD)[1][0]
    assert after.pop("new_counter") == 0
    assert after == before
