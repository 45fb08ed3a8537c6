"""Load spectra: closed forms, conventions, refusals and the randomised spectrum L^* G L."""

import numpy as np
import pytest
import scipy.stats

from tubeid.errors import SpecificationError
from tubeid.seeds import rng_for
from tubeid.uncertainty.loads import (
    LoadSpectrum,
    check_psd_matrices,
    coherent_forces,
    force_and_moment,
    psd_factor,
    randomised,
    tabulated,
)


def _delay_table(level=2.0, rho=0.6, tau=0.004, band=100.0):
    """Two loads, S_12(f) = level rho exp(-2 i pi f tau): a complex, Hermitian PD table."""
    f = np.linspace(0.0, band, 101)
    S = np.zeros((f.size, 2, 2), dtype=complex)
    S[:, 0, 0] = S[:, 1, 1] = level
    S[:, 0, 1] = level * rho * np.exp(-2j * np.pi * f * tau)
    S[:, 1, 0] = np.conj(S[:, 0, 1])
    return f, S


def test_paper_load_closed_form():
    s = coherent_forces()
    x = np.arange(2.0, 16.0, 2.0)
    assert s.names == tuple(f"F{i}" for i in range(1, 8)) and s.kinds == ("force",) * 7
    assert s.x == tuple(x) and s.tube == "centre" and s.band == 100.0
    assert s.units == ("N^2/Hz",) * 7
    S = s.matrix([-100.0, -37.5, 0.0, 37.5, 100.0])
    # Independent statement of the paper's definition: |S_ij|^2 = gamma_ij S_ii S_jj,
    # gamma_ij = exp(-|x_i - x_j| / lambda), S_ii = 1.3 N^2/Hz, real positive cross-spectra.
    gamma = np.exp(-np.abs(x[:, None] - x[None, :]) / 4.0)
    for Sk in S:
        np.testing.assert_allclose(np.diag(Sk).real, 1.3, rtol=1e-14)
        np.testing.assert_allclose(np.abs(Sk) ** 2, gamma * 1.3 * 1.3, rtol=1e-13)
        assert np.all(Sk.real > 0) and np.all(Sk.imag == 0)
    # Zero outside the band, variance 260 N^2 per force (1.3 N^2/Hz * 200 Hz).
    assert np.all(s.matrix([100.0001, -150.0, 1e4]) == 0)
    np.testing.assert_allclose(np.diag(s.covariance()), 260.0, rtol=1e-14)


def test_force_and_moment():
    s = force_and_moment(18.0, 20.0)
    assert s.names == ("T", "M") and s.kinds == ("force", "moment")
    assert s.units == ("N^2/Hz", "(N m)^2/Hz") and s.x == (8.0, 8.0)
    np.testing.assert_array_equal(s.matrix([3.0, -99.0])[:, :, :].real, np.array([np.diag([18.0, 20.0])] * 2))
    np.testing.assert_array_equal(s.matrix([101.0]), 0)
    np.testing.assert_allclose(s.covariance(), np.diag([3600.0, 4000.0]))


def test_tabulated_interpolation_and_symmetry():
    f, S = _delay_table()
    s = tabulated(f, S, ("a", "b"), ("force", "moment"), (8.0, 8.0))
    assert s.band == 100.0
    # Linear interpolation between the grid points 37 and 38 Hz.
    got = s.matrix([37.25])[0]
    np.testing.assert_allclose(got, 0.75 * S[37] + 0.25 * S[38], rtol=1e-14)
    # S(-f) = conj S(f) and Hermitian; zero beyond the band.
    np.testing.assert_allclose(s.matrix([-37.25])[0], np.conj(got), rtol=1e-14)
    np.testing.assert_allclose(got, np.conj(got.T), rtol=1e-14)
    assert np.all(s.matrix([100.5]) == 0)
    # A band below the last grid frequency cuts the table.
    s2 = tabulated(f, S, ("a", "b"), ("force", "force"), 8.0, band=50.0)
    assert np.all(s2.matrix([50.5]) == 0) and np.all(s2.matrix([49.5]) != 0)
    # Covariance: trapezoid of the piecewise-linear table is exact: 2 * level * band on the diagonal.
    np.testing.assert_allclose(np.diag(s.covariance()), 2 * 2.0 * 100.0, rtol=1e-13)


def test_non_psd_refused_naming_the_frequency():
    f, S = _delay_table()
    bad = S.copy()
    bad[20, 0, 1] = bad[20, 1, 0] = 2.5  # |S_12| > sqrt(S_11 S_22) = 2 at f = 20 Hz
    with pytest.raises(SpecificationError) as e:
        tabulated(f, bad, ("a", "b"), ("force", "force"), 8.0)
    assert e.value.field == "S(f)" and e.value.value == 20.0 and "positive semi-definite" in e.value.rule
    nh = S.copy()
    nh[35, 0, 1] += 0.5  # no longer Hermitian at 35 Hz
    with pytest.raises(SpecificationError) as e:
        tabulated(f, nh, ("a", "b"), ("force", "force"), 8.0)
    assert e.value.value == 35.0 and "Hermitian" in e.value.rule
    cplx0 = S.copy()
    cplx0[0] = np.array([[1.0, 0.5j], [-0.5j, 1.0]])  # Hermitian PD but not real at DC
    with pytest.raises(SpecificationError) as e:
        tabulated(f, cplx0, ("a", "b"), ("force", "force"), 8.0)
    assert e.value.value == 0.0
    with pytest.raises(SpecificationError, match="S\\(f\\) = 0.0"):
        LoadSpectrum(("a", "b"), ("force", "force"), "centre", (1.0, 2.0), 100.0, np.array([[1.0, 2.0], [2.0, 1.0]]))
    # the shared check on its own, with a NaN
    with pytest.raises(SpecificationError) as e:
        check_psd_matrices([1.0, 2.0], np.array([np.eye(2), np.full((2, 2), np.nan)]))
    assert e.value.value == 2.0


@pytest.mark.parametrize(
    "call",
    [
        lambda: coherent_forces(level=0.0),
        lambda: coherent_forces(level=-1.3),
        lambda: coherent_forces(band=0.0),
        lambda: coherent_forces(correlation_length=0.0),
        lambda: coherent_forces(x=()),
        lambda: force_and_moment(0.0, 1.0),
        lambda: force_and_moment(1.0, -2.0),
        lambda: force_and_moment(1.0, 2.0, band=-5.0),
        lambda: force_and_moment(1.0, float("nan")),
        lambda: LoadSpectrum(("a", "a"), ("force", "force"), "c", (0, 1), 10.0, np.eye(2)),
        lambda: LoadSpectrum(("a", "b"), ("force", "torque"), "c", (0, 1), 10.0, np.eye(2)),
        lambda: LoadSpectrum(("a", "b"), ("force", "force"), "c", (0,), 10.0, np.eye(2)),
        lambda: LoadSpectrum(("a", "b"), ("force", "force"), "", (0, 1), 10.0, np.eye(2)),
        lambda: LoadSpectrum(("a", "b"), ("force", "force"), "c", (0, 1), 10.0, np.eye(3)),
        lambda: tabulated([1.0, 2.0], np.array([np.eye(1)] * 2), ("a",), ("force",), 0.0),  # must start at 0
        lambda: tabulated([0.0, 2.0, 1.0], np.array([np.eye(1)] * 3), ("a",), ("force",), 0.0),
        lambda: tabulated([0.0, 2.0], np.array([np.eye(1)] * 2), ("a",), ("force",), 0.0, band=3.0),
        lambda: randomised(force_and_moment(1.0, 2.0), np.eye(3)),
        lambda: randomised(force_and_moment(1.0, 2.0), np.array([[1.0, 2.0], [2.0, 1.0]])),  # indefinite
        lambda: randomised(force_and_moment(1.0, 2.0), np.array([[1.0, 0.1], [0.0, 1.0]])),  # not symmetric
        lambda: randomised(force_and_moment(1.0, 2.0), np.eye(2) * 1j),
        lambda: randomised("not a spectrum", np.eye(2)),
    ],
)
def test_refusals(call):
    with pytest.raises(SpecificationError):
        call()


def test_psd_factor_both_paths():
    rng = rng_for(0, "test", "psd_factor")
    A = rng.standard_normal((5, 4, 4)) + 1j * rng.standard_normal((5, 4, 4))
    S_pd = A @ np.conj(np.swapaxes(A, -1, -2))  # Hermitian PD
    L = psd_factor(S_pd)
    np.testing.assert_allclose(np.conj(np.swapaxes(L, -1, -2)) @ L, S_pd, rtol=0, atol=1e-12 * np.abs(S_pd).max())
    assert np.allclose(np.tril(L[0], -1), 0, atol=0)  # Cholesky path: upper triangular (the paper's L_F)
    B = A[:, :, :2]
    S_sing = B @ np.conj(np.swapaxes(B, -1, -2))  # rank 2: eigen square root path
    L = psd_factor(S_sing)
    np.testing.assert_allclose(np.conj(np.swapaxes(L, -1, -2)) @ L, S_sing, rtol=0, atol=1e-12 * np.abs(S_sing).max())
    assert np.all(psd_factor(np.zeros((3, 2, 2))) == 0)
    # one stack mixing the four cases (real/complex × regular/singular): each bin factored by its own path
    Ar = rng.standard_normal((3, 4, 4))
    mixed = np.concatenate([S_pd[:2], S_sing[:2], (Ar @ np.swapaxes(Ar, 1, 2)).astype(complex),
                            (Ar[:, :, :1] @ np.swapaxes(Ar[:, :, :1], 1, 2)).astype(complex)])
    order = rng.permutation(len(mixed))
    L = psd_factor(mixed[order])
    np.testing.assert_allclose(np.conj(np.swapaxes(L, -1, -2)) @ L, mixed[order], rtol=0, atol=1e-12 * np.abs(mixed).max())
    real_bins = np.all(mixed[order].imag == 0, axis=(1, 2))
    assert np.all(L[real_bins].imag == 0)  # real spectra keep real factors


def test_randomised_closed_form_and_mean_property():
    r = np.array([18.0, 20.0])
    s = force_and_moment(*r)
    G = np.array([[1.2, -0.3], [-0.3, 0.8]])
    sr = randomised(s, G)
    # L = diag(sqrt(r)) (Cholesky of a diagonal matrix): S_F,ij = sqrt(r_i r_j) G_ij in band.
    np.testing.assert_allclose(sr.matrix([10.0])[0].real, np.sqrt(np.outer(r, r)) * G, rtol=1e-14)
    assert np.all(sr.matrix([150.0]) == 0)
    assert sr.mean.germ is None and np.array_equal(sr.mean.matrix([10.0]), s.matrix([10.0]))
    np.testing.assert_allclose(sr.covariance(), 200.0 * np.sqrt(np.outer(r, r)) * G, rtol=1e-14)
    # G = I returns the mean; the map G -> L^* G L is linear, so the antithetic pair I +- E
    # averages exactly to the mean (here on a complex, frequency-dependent table).
    f, S = _delay_table()
    t = tabulated(f, S, ("a", "b"), ("force", "force"), 8.0)
    fq = np.array([-63.3, 0.0, 12.5, 63.3, 99.9])
    np.testing.assert_allclose(randomised(t, np.eye(2)).matrix(fq), t.matrix(fq), rtol=0, atol=1e-13)
    E = np.array([[0.2, 0.1], [0.1, -0.15]])
    avg = 0.5 * (randomised(t, np.eye(2) + E).matrix(fq) + randomised(t, np.eye(2) - E).matrix(fq))
    np.testing.assert_allclose(avg, t.matrix(fq), rtol=0, atol=1e-13)
    Sr = randomised(t, np.eye(2) + E).matrix(fq)
    np.testing.assert_allclose(Sr[0], np.conj(Sr[3]), rtol=1e-14)  # S(-f) = conj S(f) survives
    check_psd_matrices(fq, Sr)


def test_randomised_mean_over_wishart_draws():
    """E[L^* G L] = S̄ for G in SG+ (Wishart, df = (n+1)/delta^2, scale I/df: E[G] = I)."""
    s = coherent_forces()
    m, delta, N = s.m, 0.4, 3000
    df = (m + 1) / delta**2
    Gs = scipy.stats.wishart(df=df, scale=np.eye(m) / df).rvs(size=N, random_state=rng_for(1, "test", "wishart"))
    f = np.array([0.0, 40.0, -40.0])
    samples = np.array([randomised(s, G).matrix(f) for G in Gs])  # (N, 3, m, m)
    mean = samples.mean(axis=0)
    se = samples.std(axis=0) / np.sqrt(N)
    # Monte Carlo: each entry within 4.5 standard errors (49 x 3 entries, fixed seed).
    assert np.all(np.abs(mean - s.matrix(f)) <= 4.5 * se + 1e-12)
    # and the dispersion is visible: the draws are not all the mean.
    assert np.all(samples.std(axis=0)[:, np.arange(m), np.arange(m)] > 0.1)


def test_randomised_singular_mean():
    # Two forces at the same point: S̄ = 2 [[1, 1], [1, 1]] = 4 v v^T (v = (1, 1)/sqrt 2) is
    # singular, so L = sqrt(4) q v^T with q a unit vector (eigen square root). Then
    # L^* G L = (q^* G q) S̄: proportional to S̄, factor a Rayleigh quotient of G.
    s = coherent_forces(x=(4.0, 4.0), level=2.0)
    G = np.array([[1.5, 0.2], [0.2, 0.7]])
    S = randomised(s, G).matrix([10.0])[0]
    Sbar = s.matrix([10.0])[0].real
    c = S.real[0, 0] / Sbar[0, 0]
    np.testing.assert_allclose(S, c * Sbar, rtol=1e-12, atol=1e-14)
    assert np.all(S.imag == 0)  # real S̄ -> real factor -> real S_F (S(-f) = conj S(f) holds)
    lam = np.linalg.eigvalsh(G)
    assert lam[0] - 1e-12 <= c <= lam[-1] + 1e-12
    np.testing.assert_allclose(randomised(s, np.eye(2)).matrix([10.0])[0], Sbar, atol=1e-13)


@pytest.mark.parametrize("call, needle", [
    # raw ValueErrors from numpy before
    (lambda: coherent_forces(x=["a"]), r"^x = array of dtype <U1, shape \(1,\): must be an array of real numbers"),
    (lambda: tabulated(["a", "b"], np.ones((2, 1, 1)), ["T"], ["force"], 8.0), r"^f = array of dtype <U1, shape \(2,\): "
                                                                             r"must be an array of real numbers"),
    (lambda: force_and_moment(1.0, 1.0).matrix("a"), r"^f = array of dtype <U1, shape \(\): must be an array of real"),
    # strings and bools accepted as numbers before
    (lambda: force_and_moment(1.0, 1.0, x=True), r"^x = True: must be a finite number"),
    (lambda: force_and_moment(1.0, 1.0, x="8"), r"^x = '8': must be a finite number"),
    (lambda: coherent_forces(x=["2", "4"]), r"^x = array of dtype <U1, shape \(2,\): must be an array of real numbers"),
    (lambda: coherent_forces(x=[True, False]), r"^x = array of dtype bool, shape \(2,\): must be an array of real numbers"),
    (lambda: tabulated(["0", "50", "100"], np.ones((3, 1, 1)), ["T"], ["force"], 8.0), r"^f = array of dtype <U3"),
    (lambda: tabulated([0.0, 50.0, 100.0], np.ones((3, 1, 1)), ["T"], ["force"], "8"), r"^x = array of dtype <U1"),
    (lambda: force_and_moment(1.0, 1.0).matrix([True]), r"^f = array of dtype bool, shape \(1,\): must be an array"),
    # complex values lost their imaginary part
    (lambda: force_and_moment(1.0, 1.0).matrix(1.0 + 1j), r"^f = array of dtype complex128, shape \(\): must be an "
                                                           r"array of real numbers \(complex values are not truncated"),
    (lambda: coherent_forces(x=np.array([2.0, 4.0]) + 0j), r"^x = array of dtype complex128, shape \(2,\): must be an "
                                                           r"array of real numbers \(complex values are not truncated"),
    (lambda: LoadSpectrum(("a",), ("force",), "c", (True,), 10.0, np.eye(1)), r"^x = array of dtype bool, shape \(1,\)"),
    (lambda: LoadSpectrum(("a",), ("force",), "c", (0.0,), 10.0, np.ones((2, 1, 1)), ["0", "10"]), r"^f = array of dtype <U2"),
    (lambda: check_psd_matrices(["a"], np.eye(1)[None]), r"^f = array of dtype <U1, shape \(1,\): must be an array of real"),
])
def test_numbers_are_real_numbers_not_bools_strings_or_complex(call, needle):
    with pytest.raises(SpecificationError, match=needle):
        call()


def test_valid_numbers_of_any_real_type_are_read_as_before():
    a = coherent_forces(x=[2, np.float32(4.5), np.int64(6)])
    assert a.x == (2.0, 4.5, 6.0)
    assert force_and_moment(1.0, 1.0, x=np.float64(3.0)).x == (3.0, 3.0)
    S = force_and_moment(1.0, 2.0)
    np.testing.assert_array_equal(S.matrix(np.array([-5, 0, 200])), S.matrix([-5.0, 0.0, 200.0]))
    t = tabulated(np.array([0, 50, 100]), np.ones((3, 1, 1)), ["T"], ["force"], 8)
    assert t.frequencies.dtype == float and t.x == (8.0,)
