"""Tests of the SG+ / SE+ generators against closed-form moments and the scipy Wishart oracle.

Statistical tolerances: every Monte-Carlo check uses a fixed seed and a tolerance of a stated
number of standard errors (SE) computed from the theory or from the sample itself, so a correct
generator passes with overwhelming probability and the result is deterministic.
"""

import math

import numpy as np
import pytest
from scipy import stats

from tubeid.errors import SpecificationError
from tubeid.seeds import rng_for
from tubeid.uncertainty.random_matrices import (
    Dispersion,
    delta_max,
    se_plus,
    sg_plus,
    sg_plus_dispersion,
    sg_plus_from_germs,
)


def _sg_plus_j_from_zero(n, delta, m, rng):
    """The known public bug: Gamma shapes with j counted from 0 (independent loop implementation)."""
    sigma = delta / math.sqrt(n + 1)
    out = np.empty((m, n, n))
    for r in range(m):
        L = np.zeros((n, n))
        for j in range(n):  # j = 0..n-1 used directly in the shape: wrong by +1/2
            L[j, j] = sigma * math.sqrt(2 * rng.gamma((n + 1) / (2 * delta**2) + (1 - j) / 2))
            for k in range(j + 1, n):
                L[j, k] = sigma * rng.standard_normal()
        out[r] = L.T @ L
    return out


def test_delta_max_values():
    # MODEL.md: n = 22 gives sqrt(23/27), n = 2 gives sqrt(3/7)
    assert delta_max(22) == pytest.approx(math.sqrt(23 / 27), rel=1e-15, abs=0)
    assert delta_max(2) == pytest.approx(math.sqrt(3 / 7), rel=1e-15, abs=0)
    assert delta_max(1) == pytest.approx(math.sqrt(2 / 6), rel=1e-15, abs=0)


def test_shapes_symmetry_positivity_and_reproducibility():
    G = sg_plus(3, 0.5, (4, 5), rng=rng_for(1, "t"))
    assert G.shape == (4, 5, 3, 3)
    assert np.array_equal(G, np.swapaxes(G, -1, -2))
    assert np.all(np.linalg.eigvalsh(G) > 0)
    assert sg_plus(3, 0.5, rng=rng_for(1, "t")).shape == (3, 3)
    assert sg_plus(3, 0.5, 7, rng=rng_for(1, "t")).shape == (7, 3, 3)
    assert sg_plus(3, 0.5, (0,), rng=rng_for(1, "t")).shape == (0, 3, 3)
    # same generator state / same seed -> same draws; integer seeds accepted
    assert np.array_equal(sg_plus(4, 0.3, 10, rng=rng_for(5, "a")), sg_plus(4, 0.3, 10, rng=rng_for(5, "a")))
    assert np.array_equal(sg_plus(4, 0.3, 10, rng=3), sg_plus(4, 0.3, 10, rng=3))
    # n = 1: G = 2σ²V scalar with E = 1
    g1 = sg_plus(1, 0.4, 20000, rng=rng_for(2, "n1"))
    se = math.sqrt(2 * 0.4**2 / 2 / 20000)  # Var(G11) = 2δ²/(n+1)
    assert abs(g1.mean() - 1) < 5 * se


@pytest.mark.parametrize("n, delta, m", [(2, 0.6, 40000), (17, 0.5, 20000), (5, 0.74, 30000)])
def test_mean_and_variance(n, delta, m):
    G = sg_plus(n, delta, m, rng=rng_for(11, "moments", n, delta))
    var_th = delta**2 * (1 + np.eye(n)) / (n + 1)
    # E[G] = I: SE from the exact variance; 5 SE per entry
    se_mean = np.sqrt(var_th / m)
    assert np.all(np.abs(G.mean(axis=0) - np.eye(n)) < 5 * se_mean)
    # Var(G_jk) = δ²(1+δ_jk)/(n+1): SE of a sample variance = std((x - x̄)²)/√m; 5 SE per entry
    dev2 = (G - G.mean(axis=0)) ** 2
    se_var = dev2.std(axis=0, ddof=1) / math.sqrt(m)
    assert np.all(np.abs(G.var(axis=0, ddof=1) - var_th) < 5 * se_var)
    # dispersion estimator: δ̂² = mean ||G - I||²_F / n; SE from the sample; 5 SE
    f = np.sum((G - np.eye(n)) ** 2, axis=(-2, -1)) / n
    assert abs(sg_plus_dispersion(G) ** 2 - delta**2) < 5 * f.std(ddof=1) / math.sqrt(m)


def _functionals(G):
    return {
        "G11": G[:, 0, 0],
        "G12": G[:, 0, 1],
        "trace": np.trace(G, axis1=1, axis2=2),
        "lambda_min": np.linalg.eigvalsh(G)[:, 0],
    }


@pytest.mark.parametrize("n, delta", [(2, 0.6), (6, 0.3), (17, 0.8)])
def test_agrees_with_scipy_wishart(n, delta):
    m = 3000
    df, scale = (n + 1) / delta**2, np.eye(n) * delta**2 / (n + 1)
    ours = _functionals(sg_plus(n, delta, m, rng=rng_for(21, "ks-ours", n, delta)))
    ref = _functionals(stats.wishart(df=df, scale=scale).rvs(size=m, random_state=rng_for(21, "ks-ref", n, delta)))
    for key in ours:
        # fixed seeds; two-sample KS; p > 1e-3 (a correct generator fails with probability 1e-3 per seed)
        p = stats.ks_2samp(ours[key], ref[key]).pvalue
        assert p > 1e-3, (key, p)


def test_ks_has_power_against_j_from_zero_bug():
    # Self-check of the oracle test: with the j-from-0 bug, the trace distribution is rejected.
    n, delta, m = 2, 0.6, 3000
    bad = _sg_plus_j_from_zero(n, delta, m, rng_for(22, "bug"))
    ref = stats.wishart(df=(n + 1) / delta**2, scale=np.eye(n) * delta**2 / (n + 1)).rvs(
        size=m, random_state=rng_for(22, "ref"))
    assert stats.ks_2samp(np.trace(bad, axis1=1, axis2=2), np.trace(ref, axis1=1, axis2=2)).pvalue < 1e-6


def test_catches_j_counted_from_zero():
    # Bug: E[G_jj] = 1 + δ²/(n+1). Diagonal entries are uncorrelated (Wishart, identity scale) with
    # variance 2δ²/(n+1), so the mean diagonal over m draws has SE = sqrt(2δ²/((n+1) n m)).
    n, delta, m = 2, 0.6, 20000
    se = math.sqrt(2 * delta**2 / ((n + 1) * n * m))
    bias = delta**2 / (n + 1)
    assert bias > 6 * se  # design: the bug is detectable (here ~49 SE)
    G = sg_plus(n, delta, m, rng=rng_for(31, "bug-check"))
    diag_mean = np.mean(np.diagonal(G, axis1=1, axis2=2))
    assert abs(diag_mean - 1) < 3 * se
    # and the same criterion rejects the buggy generator
    bad = _sg_plus_j_from_zero(n, delta, m, rng_for(31, "bug-impl"))
    assert abs(np.mean(np.diagonal(bad, axis1=1, axis2=2)) - 1) > 3 * se


def test_se_plus_mean_and_variance():
    rng = rng_for(41, "mean")
    n, delta, m = 4, 0.5, 40000
    B = rng.standard_normal((n, n))
    mean = 1e7 * (B @ B.T + 0.5 * np.eye(n))  # SPD, stiffness-like scale (N/m)
    A = se_plus(mean, delta, m, rng=rng_for(41, "draws"), name="K_B")
    assert A.shape == (m, n, n)
    # A is Wishart(ν = (n+1)/δ², scale = mean·δ²/(n+1)): Var(A_jk) = δ²/(n+1)·(M_jk² + M_jj M_kk)
    d = np.diag(mean)
    var_th = delta**2 / (n + 1) * (mean**2 + np.outer(d, d))
    assert np.all(np.abs(A.mean(axis=0) - mean) < 5 * np.sqrt(var_th / m))  # 5 SE per entry
    dev2 = (A - A.mean(axis=0)) ** 2
    assert np.all(np.abs(A.var(axis=0, ddof=1) - var_th) < 5 * dev2.std(axis=0, ddof=1) / math.sqrt(m))
    assert np.all(np.linalg.eigvalsh(A[:100]) > 0)


def _raises(fn, *needles):
    with pytest.raises(SpecificationError) as exc:
        fn()
    msg = str(exc.value)
    for needle in needles:
        assert needle in msg, msg
    return msg


def test_refusals_delta_and_n():
    rng = rng_for(0, "x")
    dm = delta_max(3)
    _raises(lambda: sg_plus(3, 0.0, rng=rng), "delta = 0.0", "(0, 0.707107)")
    _raises(lambda: sg_plus(3, dm, rng=rng), f"delta = {dm!r}", "0 < delta < delta_max(n=3)")
    _raises(lambda: sg_plus(3, 0.9, rng=rng), "delta = 0.9", "open interval")
    _raises(lambda: sg_plus(3, -0.1, rng=rng), "delta = -0.1")
    _raises(lambda: sg_plus(3, float("nan"), rng=rng), "delta = nan")
    _raises(lambda: sg_plus(0, 0.1, rng=rng), "n = 0", "integer >= 1")
    _raises(lambda: sg_plus(2.5, 0.1, rng=rng), "n = 2.5", "integer >= 1")
    _raises(lambda: sg_plus(3, 0.1, (-1,), rng=rng), "size = (-1,)")
    _raises(lambda: sg_plus(3, 0.1, rng=None), "rng = None")
    _raises(lambda: se_plus(np.eye(3), 0.8, rng=rng, name="K_B"), "delta[K_B] = 0.8")


def test_refusals_mean():
    rng = rng_for(0, "y")
    _raises(lambda: se_plus([[1.0, 2.0], [2.0, 1.0]], 0.3, rng=rng, name="K_B"),
            "K_B = ", "must be symmetric positive definite", "not positive definite")
    _raises(lambda: se_plus([[1.0, 0.0], [0.0, 0.0]], 0.3, rng=rng), "mean = ", "not positive definite")
    _raises(lambda: se_plus([[2.0, 0.5], [0.1, 2.0]], 0.3, rng=rng, name="M_B"),
            "M_B = ", "must be symmetric positive definite", "not symmetric")
    _raises(lambda: se_plus(np.ones((2, 3)), 0.3, rng=rng, name="K_B"), "K_B = array of shape (2, 3)", "square")
    _raises(lambda: se_plus(np.ones((2, 2, 2)), 0.3, rng=rng), "mean = array of shape (2, 2, 2)", "square")
    _raises(lambda: se_plus([[np.inf]], 0.3, rng=rng), "mean = ", "finite")


def test_dispersion_spec_and_estimator_refusals():
    d = Dispersion(stiffness=0.45)
    assert d.check(22) is d and not d.is_deterministic
    assert Dispersion().is_deterministic
    _raises(lambda: Dispersion(mass=-0.1), "dispersion.mass = -0.1", ">= 0")
    _raises(lambda: Dispersion(damping=float("inf")), "dispersion.damping = inf")
    _raises(lambda: Dispersion(stiffness=0.7).check(2), "dispersion.stiffness = 0.7", "delta_max(n=2)")
    with pytest.raises(Exception):
        d.stiffness = 0.1  # frozen
    _raises(lambda: sg_plus_dispersion(np.ones((3, 2))), "G = array of shape (3, 2)")
    _raises(lambda: sg_plus_dispersion(np.ones((0, 2, 2))), "at least one realisation")


@pytest.mark.parametrize("call, needle", [
    (lambda: se_plus(np.eye(2) * (1 + 1e-3j), 0.3, rng=1), r"^mean = array of dtype complex128, shape \(2, 2\): must "
                                                          r"be an array of real numbers \(complex values are not"),
    (lambda: se_plus(np.eye(2) * (1 + 1e-3j), 0.3, rng=1, name="K_B"), r"^K_B = array of dtype complex128"),
    (lambda: se_plus(np.eye(2, dtype=bool), 0.3, rng=1), r"^mean = array of dtype bool, shape \(2, 2\): must be an"),
    (lambda: se_plus([["1", "0"], ["0", "1"]], 0.3, rng=1), r"^mean = array of dtype <U1, shape \(2, 2\)"),
    (lambda: sg_plus_dispersion(np.eye(2)[None] + 0j), r"^G = array of dtype complex128, shape \(1, 2, 2\)"),
    (lambda: sg_plus_from_germs(2, 0.3, np.zeros(1) + 1j, np.full(2, 0.5)), r"^normals = array of dtype complex128"),
    (lambda: sg_plus_from_germs(2, 0.3, np.zeros(1), np.full(2, 0.5) + 0j), r"^uniforms = array of dtype complex128"),
])
def test_complex_bool_or_string_matrices_are_refused_not_truncated(call, needle):
    """A complex mean lost its imaginary part with only a ComplexWarning; bools and strings were read as numbers."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # refused before any ComplexWarning
        with pytest.raises(SpecificationError, match=needle):
            call()


def test_real_matrices_given_as_lists_are_read_as_before():
    np.testing.assert_array_equal(se_plus([[2, 0], [0, 2]], 0.3, rng=5), se_plus(np.eye(2) * 2.0, 0.3, rng=5))


@pytest.mark.parametrize("delta", [1e-13, 1e-155, 1e-170])
def test_a_dispersion_too_small_to_draw_is_refused(delta):
    """δ = 1e-155 gave an all-NaN matrix, δ <= 1e-162 a ZeroDivisionError, δ = 1e-20 draws of dispersion 0.7 δ."""
    from tubeid.uncertainty.random_matrices import sg_plus

    with pytest.raises(SpecificationError, match=r"^delta = .*: must be at least 1e-12 when not 0"):
        sg_plus(3, delta, rng=1)


def test_the_smallest_dispersion_allowed_is_still_drawn_accurately():
    from tubeid.uncertainty.random_matrices import DELTA_MIN, sg_plus, sg_plus_dispersion

    for n in (1, 3, 20):
        ref = sg_plus_dispersion(sg_plus(n, 1e-6, 20000, rng=1)) / 1e-6
        assert sg_plus_dispersion(sg_plus(n, DELTA_MIN, 20000, rng=1)) / DELTA_MIN / ref == pytest.approx(1, rel=1e-5, abs=0)
