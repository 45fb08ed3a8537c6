"""Gaussian load synthesis: second-order statistics, Gaussianity, reproducibility, the
piecewise-linear pre-compensation, refusals.

Statistical tolerances use N_eff, the equivalent number of independent averages of a Welch
band average: K segments (1 s Hann, 50 % overlap) times B bins divided by 2.0, the variance
inflation of overlapping segments and correlated Hann bins (measured on white noise in
tests/test_spectra.py::test_welch_band_average_variance_factor). A real-part cross-spectrum
estimate then has std sqrt((S_ii S_jj + S_ij^2) / (2 N_eff)) (Gaussian process, real S_ij).
"""

import numpy as np
import pytest
import scipy.integrate
import scipy.stats

from tubeid.dynamics.spectra import psd_matrix
from tubeid.errors import SpecificationError
from tubeid.seeds import rng_for
from tubeid.uncertainty.loads import coherent_forces, force_and_moment, randomised, tabulated
from tubeid.uncertainty.processes import gaussian_loads, synthesis_grid

DT = 1e-3
WELCH_INFLATION = 2.0


def _rngs(seed, tag, reals):
    return [rng_for(seed, tag, r) for r in reals]


@pytest.fixture(scope="module")
def paper_loads():
    s = coherent_forces()
    x = gaussian_loads(s, 60.0, DT, _rngs(11, "paper", range(2)), interpolation="none")
    return s, x


def test_shape_and_grid(paper_loads):
    s, x = paper_loads
    n_t, N = synthesis_grid(60.0, DT)
    assert n_t == 60001 and N >= n_t
    assert x.shape == (2, 60001, 7) and x.dtype == np.float64


def test_variance_is_integral_of_psd(paper_loads):
    s, x = paper_loads
    var = np.mean(x**2, axis=(0, 1))  # centred process
    # 260 N^2 = 1.3 N^2/Hz * 200 Hz. For a flat band-limited process (two-sided width 2B, B = 100 Hz)
    # the mean-square estimate over T has relative std 1/sqrt(B T); T = 2 x 60 s -> 0.91 %.
    # 4 % > 4 sigma.
    np.testing.assert_allclose(np.diag(s.covariance()), 260.0)
    np.testing.assert_allclose(var, 260.0, rtol=0.04)
    # Cross-covariances: int S_ij df = 260 exp(-|dx|/8); std <= 0.91 % of 260 (same argument).
    cov = np.einsum("rti,rtj->ij", x, x) / (x.shape[0] * x.shape[1])
    np.testing.assert_allclose(cov, s.covariance(), rtol=0, atol=0.04 * 260.0)


def test_cross_spectra_recovered_by_welch(paper_loads):
    s, x = paper_loads
    f, S = psd_matrix(x, DT, segment_seconds=1.0)  # Δf = 1 Hz
    S = S.mean(axis=0)
    K = 2 * (2 * 60 - 1)  # segments: 2 realisations x 119
    n_eff = K * 10 / WELCH_INFLATION
    zs = []
    for lo in range(0, 90, 10):  # 10-Hz bands, away from the band edge (leakage at 100 Hz)
        sel = (f > lo) & (f <= lo + 10)
        assert sel.sum() == 10
        est = S[sel].mean(axis=0)
        tgt = s.matrix([lo + 5.0])[0].real
        d = np.diag(tgt)
        sigma = np.sqrt((d[:, None] * d[None, :] + tgt**2) / (2 * n_eff))
        zs.append(((est.real - tgt) / sigma)[np.triu_indices(7)])
        # imaginary parts: target 0, std sqrt((S_ii S_jj - S_ij^2)/(2 N_eff)) (0 on the diagonal)
        sig_im = np.sqrt(np.maximum(d[:, None] * d[None, :] - tgt**2, 0) / (2 * n_eff))
        iu = np.triu_indices(7, 1)
        assert np.all(np.abs(est.imag[iu]) < 4.5 * sig_im[iu])
    zs = np.array(zs)
    # 252 correlated comparisons: all within 4.5 sigma, and the mean square z is ~1 (calibrated
    # error model; a factor-of-two error in any level or in the coherence would blow it up).
    assert np.abs(zs).max() < 4.5
    assert 0.5 < np.mean(zs**2) < 1.7


def test_complex_cross_spectrum_phase():
    # S_12(f) = level rho exp(-2 i pi f tau): load 1 lags load 2 by tau (R_12(t) = rho R(t - tau)).
    level, rho, tau = 2.0, 0.8, 0.004
    f = np.linspace(0.0, 100.0, 101)
    S = np.zeros((f.size, 2, 2), dtype=complex)
    S[:, 0, 0] = S[:, 1, 1] = level
    S[:, 0, 1] = level * rho * np.exp(-2j * np.pi * f * tau)
    S[:, 1, 0] = np.conj(S[:, 0, 1])
    s = tabulated(f, S, ("a", "b"), ("force", "force"), 8.0)
    x = gaussian_loads(s, 60.0, DT, _rngs(5, "phase", range(2)), interpolation="none")
    # Time domain, independent of any PSD code: corr(x_1(t + tau), x_2(t)) = rho at lag tau = 4 samples.
    lag = int(round(tau / DT))
    c = np.mean(x[:, lag:, 0] * x[:, :-lag, 1]) / np.sqrt(np.mean(x[..., 0] ** 2) * np.mean(x[..., 1] ** 2))
    assert abs(c - rho) < 0.02  # std of a correlation estimate ~ (1 - rho^2)/sqrt(B T) ~ 0.3 %
    fe, Se = psd_matrix(x, DT, segment_seconds=1.0)
    band = (fe > 0) & (fe <= 90)
    demod = (Se[:, band, 0, 1] * np.exp(2j * np.pi * fe[band] * tau)).mean()
    # average over 2 x 119 segments x 90 bins / 2: sigma ~ level sqrt((1 + rho^2)/(2 * 10710)) ~ 0.02 -> 4 sigma
    assert abs(demod - level * rho) < 0.08


def test_gaussian_marginals(paper_loads):
    s, x = paper_loads
    # Flat band-limited spectrum: R(tau) ~ sinc(2 B tau) vanishes every 5 ms, so samples 5 steps
    # apart are (nearly) uncorrelated: thinned series are ~iid N(0, 260).
    z = x[:, ::5, :] / np.sqrt(260.0)
    for ch in (0, 3, 6):
        sample = z[..., ch].ravel()  # 24002 values
        assert scipy.stats.kstest(sample, "norm").pvalue > 1e-3
        assert scipy.stats.normaltest(sample).pvalue > 1e-3
    # The test can fail: uniform amplitudes of the same variance are rejected.
    u = rng_for(0, "uniform").uniform(-np.sqrt(3), np.sqrt(3), 24002)
    assert scipy.stats.normaltest(u).pvalue < 1e-6


def test_reproducible_per_realisation():
    s = force_and_moment(18.0, 20.0)
    a = gaussian_loads(s, 2.0, DT, _rngs(7, "load", [0, 1, 2]))
    b = gaussian_loads(s, 2.0, DT, _rngs(7, "load", [2]))
    c = gaussian_loads(s, 2.0, DT, _rngs(7, "load", [1, 2]))
    np.testing.assert_array_equal(a[2], b[0])
    np.testing.assert_array_equal(a[1:], c)
    assert not np.allclose(a[0], a[1], atol=0)
    d = gaussian_loads(s, 2.0, DT, _rngs(8, "load", [2]))
    assert not np.allclose(b, d, atol=0)


def test_out_receives_the_same_values_and_bad_out_is_refused():
    s = force_and_moment(18.0, 20.0)
    a = gaussian_loads(s, 2.0, DT, _rngs(7, "load", [0, 1]))
    batch = np.full((3, a.shape[1], 2), np.nan)  # a batch's rows, as simulate_responses writes them
    r = gaussian_loads(s, 2.0, DT, _rngs(7, "load", [1]), out=batch[1:2])
    assert r is not None and np.shares_memory(r, batch)
    np.testing.assert_array_equal(batch[1], a[1])
    assert np.isnan(batch[0]).all() and np.isnan(batch[2]).all()  # nothing beyond the rows given
    for bad in (np.empty((1, a.shape[1] - 1, 2)), np.empty((1, a.shape[1], 2), dtype=np.float32),
                np.empty((1, 2, a.shape[1])).transpose(0, 2, 1), [[0.0]]):
        with pytest.raises(SpecificationError, match="out"):
            gaussian_loads(s, 2.0, DT, _rngs(7, "load", [1]), out=bad)


def test_randomised_spectrum_covariance():
    # Loads from L^* G L: covariance 200 Hz * sqrt(r_i r_j) G_ij (off-diagonal appears).
    r = np.array([18.0, 20.0])
    G = np.array([[1.2, 0.5], [0.5, 0.9]])
    s = randomised(force_and_moment(*r), G)
    x = gaussian_loads(s, 60.0, DT, _rngs(3, "rand", range(2)), interpolation="none")
    cov = np.einsum("rti,rtj->ij", x, x) / (x.shape[0] * x.shape[1])
    ref = 200.0 * np.sqrt(np.outer(r, r)) * G
    # relative std ~ 0.9 % of sqrt(ref_ii ref_jj) (see test_variance_is_integral_of_psd): 4 %.
    scale = np.sqrt(np.outer(np.diag(ref), np.diag(ref)))
    assert np.all(np.abs(cov - ref) < 0.04 * scale)


def test_linear_interpolation_compensation():
    """Piecewise-linear reading: PSD of the interpolant = PSD of the samples x sinc^4(f dt)."""
    s = force_and_moment(1.0, 1.0)
    R, T = 4, 60.0
    out = {}
    for interp in ("linear", "none"):
        x = gaussian_loads(s, T, DT, _rngs(3, "lin", range(R)), interpolation=interp)
        t = np.arange(x.shape[1]) * DT
        tf = np.arange((x.shape[1] - 1) * 8 + 1) * DT / 8  # x8 linear upsampling (np.interp)
        xu = np.stack([np.stack([np.interp(tf, t, x[r, :, c]) for c in range(2)], -1) for r in range(R)])
        f, S = psd_matrix(xu, DT / 8, segment_seconds=1.0)
        f0, S0 = psd_matrix(x, DT, segment_seconds=1.0)
        n = f0.size
        assert np.allclose(f[:n], f0, atol=0)
        up = np.diagonal(S, axis1=-2, axis2=-1).real.mean(axis=(0, -1))[:n]
        raw = np.diagonal(S0, axis1=-2, axis2=-1).real.mean(axis=(0, -1))
        out[interp] = (up, raw)
    sinc4 = np.sinc(f0 * DT) ** 4
    inband = (f0 > 0) & (f0 <= 99)
    # (1) the sinc^4 law itself, per bin, on the same data (generator-independent): within 0.5 %
    #     (measured 0.1 %: Welch leakage of the images and the cyclostationary interpolant).
    for interp in out:
        up, raw = out[interp]
        np.testing.assert_allclose(up[inband] / raw[inband], sinc4[inband], rtol=5e-3)
    # (2) "linear": the upsampled (continuous) load has the target PSD 1 N^2/Hz in band.
    #     10-Hz bands (and 90-99 Hz): N_eff = 4 x 119 x 2 channels x 10 / 2 = 4760 -> sigma 1.45 %; 4 sigma.
    up_lin = out["linear"][0]
    for lo, hi in [(i, i + 10) for i in range(0, 90, 10)] + [(90, 99)]:
        sel = (f0 > lo) & (f0 <= hi)
        assert abs(up_lin[sel].mean() - 1.0) < 4 * np.sqrt(WELCH_INFLATION / (4 * 119 * 2 * sel.sum()))
    # (3) "none": the samples have the target PSD, so the continuous load drops by sinc^4 (6.4 % at
    #     100 Hz for dt = 1 ms). Same random numbers in both modes, so the ratio is sharp.
    ratio = out["none"][0][inband] / out["linear"][0][inband]
    np.testing.assert_allclose(ratio, sinc4[inband], rtol=1e-3)
    assert np.sinc(0.1) ** 4 == pytest.approx(0.936, abs=1e-3)
    edge = (f0 > 90) & (f0 <= 99)
    assert out["none"][0][edge].mean() < 0.97  # visibly below target (predicted 0.942, sigma 1.45 %)


def test_linear_mode_sample_variance():
    # With "linear", the samples carry int S / sinc^4(f dt) df (> int S): closed form by quadrature.
    s = force_and_moment(1.0, 1.0)
    rngs = lambda: _rngs(4, "var", range(2))  # noqa: E731
    xl = gaussian_loads(s, 30.0, DT, rngs(), interpolation="linear")
    xn = gaussian_loads(s, 30.0, DT, rngs(), interpolation="none")
    gain = 2 * scipy.integrate.quad(lambda f: np.sinc(f * DT) ** -4, 0, 100)[0] / 200.0
    assert gain == pytest.approx(1.0224, abs=1e-4)
    # same random numbers: the ratio of mean squares is a |X_k|^2-weighted mean of 1/sinc^4,
    # spread of 1/sinc^4 over the band ~7 % / sqrt(#bins = 3000) -> 0.2 % is > 10 sigma
    ratio = np.mean(xl**2, axis=(0, 1)) / np.mean(xn**2, axis=(0, 1))
    np.testing.assert_allclose(ratio, gain, rtol=2e-3)


def test_refusals():
    s = force_and_moment(1.0, 1.0)
    g = _rngs(0, "x", [0])
    with pytest.raises(SpecificationError, match="dt"):
        gaussian_loads(s, 1.0, 5e-3, g)  # Nyquist 100 Hz = band: does not resolve it
    with pytest.raises(SpecificationError, match="interpolation"):
        gaussian_loads(s, 1.0, DT, g, interpolation="cubic")
    with pytest.raises(SpecificationError, match="rngs"):
        gaussian_loads(s, 1.0, DT, g[0])
    with pytest.raises(SpecificationError, match="rngs"):
        gaussian_loads(s, 1.0, DT, [])
    with pytest.raises(SpecificationError, match="rngs"):
        gaussian_loads(s, 1.0, DT, [42])
    with pytest.raises(SpecificationError, match="duration"):
        gaussian_loads(s, 1e-4, DT, g)
    with pytest.raises(SpecificationError, match="duration"):
        gaussian_loads(s, -1.0, DT, g)
    with pytest.raises(SpecificationError, match="dt"):
        gaussian_loads(s, 1.0, 0.0, g)
    with pytest.raises(SpecificationError, match="spectrum"):
        gaussian_loads(np.eye(2), 1.0, DT, g)


def test_non_psd_spectrum_refused_naming_frequency():
    class Bad:
        """Duck-typed spectrum that is indefinite above 30 Hz."""
        names = ("a", "b")
        band = 100.0

        def matrix(self, f):
            f = np.atleast_1d(f)
            S = np.zeros((f.size, 2, 2), dtype=complex)
            S[:, 0, 0] = S[:, 1, 1] = 1.0
            S[:, 0, 1] = S[:, 1, 0] = np.where(np.abs(f) > 30.0, 1.5, 0.5)
            return S

    with pytest.raises(SpecificationError) as e:
        gaussian_loads(Bad(), 1.0, DT, _rngs(0, "bad", [0]))
    assert e.value.field == "S(f)" and 30.0 < e.value.value <= 31.0 and "positive semi-definite" in e.value.rule


def _per_bin_reference(spectrum, duration, dt, rng, interpolation):
    """Straightforward synthesis (module docstring, term by term): one Cholesky factor per FFT
    bin of S(f_k) df / sinc^4, the same draws (bins 0..K, (K+1, m, 2) normals), numpy's irfft."""
    n_t, N = synthesis_grid(duration, dt)
    df = 1.0 / (N * dt)
    K = int(np.floor(spectrum.band / df * (1 + 1e-12)))
    fk = np.arange(K + 1) * df
    z = rng.standard_normal((K + 1, spectrum.m, 2))
    coef = np.zeros((N // 2 + 1, spectrum.m), dtype=complex)
    for k in range(K + 1):
        P = spectrum.matrix([fk[k]])[0] * df
        if interpolation == "linear":
            P = P / np.sinc(fk[k] * dt) ** 4
        w = (z[k, :, 0] + 1j * z[k, :, 1]) / np.sqrt(2.0)
        coef[k] = np.linalg.cholesky(P) @ w
    coef[0] = np.sqrt(2.0) * coef[0].real
    return np.fft.irfft(coef * N, n=N, axis=0)[:n_t]


@pytest.mark.parametrize("which", ["constant", "randomised", "tabulated"])
@pytest.mark.parametrize("interpolation", ["linear", "none"])
def test_matches_per_bin_reference(which, interpolation):
    # The fast path factorises a constant spectrum once and scales it per bin; tabulated spectra
    # are factorised per bin. Both must equal the per-bin formula with the same random numbers up
    # to round-off of the single-precision transform (2e-6 relative to the largest sample: measured
    # ~1.4e-7; the float64 reference's own round-off is ~1e-15).
    f = np.linspace(0.0, 100.0, 11)
    S = np.zeros((f.size, 2, 2), dtype=complex)
    S[:, 0, 0], S[:, 1, 1] = 1.0 + f / 50.0, 2.0
    S[:, 0, 1] = 0.6 * np.exp(-0.02j * f)
    S[:, 1, 0] = np.conj(S[:, 0, 1])
    spec = {"constant": coherent_forces(),
            "randomised": randomised(coherent_forces(), np.eye(7) + 0.1 * np.ones((7, 7))),
            "tabulated": tabulated(f, S, ("a", "b"), ("force", "force"), 8.0)}[which]
    x = gaussian_loads(spec, 3.0, DT, [rng_for(2, "ref", 0)], interpolation=interpolation)[0]
    ref = _per_bin_reference(spec, 3.0, DT, rng_for(2, "ref", 0), interpolation)
    assert x.shape == ref.shape
    assert np.max(np.abs(x - ref)) < 2e-6 * np.max(np.abs(ref))
