"""Matrix PSD estimation (two-sided per Hz), Parseval, the confidence band, J_s and D."""

import numpy as np
import pytest
import scipy.signal
import xarray as xr

from tubeid.dynamics.spectra import (auto_psd, confidence_band, distance, j_s, log_level, psd_dataset, psd_matrix,
                                     variance_from_psd)
from tubeid.errors import SpecificationError
from tubeid.seeds import rng_for


def test_white_noise_level():
    # iid N(0, sigma^2) at dt: two-sided PSD sigma^2 dt, flat from 0 to Nyquist.
    sigma, dt = 3.0, 2e-3
    x = sigma * rng_for(0, "white").standard_normal((2**18, 1))
    f, S = psd_matrix(x, dt, segment_seconds=1024 * dt)
    assert f[0] == 0 and f[-1] == pytest.approx(0.5 / dt, abs=0) and S.shape == (513, 1, 1)
    level = S[:, 0, 0].real / (sigma**2 * dt)
    # overall mean level: ~511 segments x 513 bins -> relative std < 0.3 %; 1.5 % tolerance.
    assert level[1:-1].mean() == pytest.approx(1.0, rel=0.015, abs=0)
    # per bin (~511 Hann segments, 50 % overlap: relative std ~ sqrt(1.08 / 511) = 4.6 %): all within
    # 6 sigma, and the spread matches.
    assert np.all(np.abs(level[1:-1] - 1) < 6 * 0.046)
    assert np.std(level[1:-1]) == pytest.approx(0.046, rel=0.15, abs=0)
    # a one-sided (x2) or per-rad/s (/2pi) convention would be off by 100 % or 84 %.


def test_matches_scipy_csd_and_convention():
    rng = rng_for(1, "csd")
    x = rng.standard_normal((4096, 3))
    x[:, 1] += 0.5 * x[:, 0]
    dt = 0.01
    f, S = psd_matrix(x, dt, segment_seconds=2.56)
    assert np.allclose(S, np.conj(np.swapaxes(S, -1, -2)), atol=0)  # Hermitian per bin
    # scipy two-sided oracle: return_onesided=False, keep f >= 0 (Nyquist appears at -fs/2 there).
    for a in range(3):
        for b in range(3):
            f2, P = scipy.signal.csd(x[:, b], x[:, a], fs=1 / dt, nperseg=256, detrend=False,
                                     return_onesided=False)
            keep = f2 >= 0
            np.testing.assert_allclose(f[:-1], f2[keep])
            np.testing.assert_allclose(S[:-1, a, b], P[keep], rtol=1e-12, atol=1e-15)
            np.testing.assert_allclose(S[-1, a, b], P[f2 == -50.0][0], rtol=1e-12)  # Nyquist bin


def test_auto_psd_is_psd_matrix_diagonal_and_scipy_welch():
    """The auto-PSDs alone: bit-identical to the diagonal of the matrix estimate (batched records,
    Hann, 50 % overlap) and, against scipy's two-sided Welch, equal to round-off (1e-12)."""
    rng = rng_for(2, "auto")
    x = rng.standard_normal((2, 3, 4096, 4)) * 1e-6
    dt = 0.01
    f, S = psd_matrix(x, dt, segment_seconds=2.56)
    fa, P = auto_psd(x, dt, segment_seconds=2.56)
    assert P.shape == (2, 3, f.size, 4) and P.dtype == np.float64
    assert np.array_equal(fa, f) and np.array_equal(P, np.real(np.diagonal(S, axis1=-2, axis2=-1)))
    f2, W = scipy.signal.welch(x[1, 2, :, 3], fs=1 / dt, nperseg=256, detrend=False, return_onesided=False)
    keep = f2 >= 0
    np.testing.assert_allclose(P[1, 2, :-1, 3], W[keep], rtol=1e-12, atol=0)


def test_phase_convention_with_a_delay():
    # x_1(t) = y(t - d dt)  =>  S_12(f) = S_yy(f) exp(-2 i pi f d dt)   (S_ab = E[X_a conj X_b])
    dt, d = 1e-3, 3
    y = rng_for(2, "delay").standard_normal(200_000)
    x = np.stack([np.roll(y, d), y], axis=-1)
    f, S = psd_matrix(x, dt, segment_seconds=0.5)
    sel = (f > 0) & (f < 300)
    expected_phase = -2 * np.pi * f[sel] * d * dt
    err = np.angle(S[sel, 0, 1] * np.exp(-1j * expected_phase))
    assert np.max(np.abs(err)) < 0.05  # coherence 1: phase noise ~ bias of the shifted window, small
    assert np.allclose(np.abs(S[sel, 0, 1]), S[sel, 1, 1].real, rtol=0.02, atol=0)


def test_parseval():
    rng = rng_for(3, "parseval")
    x = rng.standard_normal((2, 8000, 2)) * np.array([1.0, 5.0])
    # boxcar, one segment: discrete Parseval exactly (DC and Nyquist once)
    f, S = psd_matrix(x, 0.01, segment_seconds=80.0, window="boxcar", overlap=0.0)
    np.testing.assert_allclose(variance_from_psd(f, S), np.mean(x**2, axis=-2), rtol=1e-12)
    # auto-spectra input (..., F) too
    auto = np.diagonal(S, axis1=-2, axis2=-1)
    np.testing.assert_allclose(variance_from_psd(f, np.moveaxis(auto, -1, 0)), np.mean(x**2, axis=-2).T, rtol=1e-12)
    # Welch (Hann, 50 %): each segment's window-weighted mean square, averaged. The Hann weights
    # at 50 % overlap sum to a constant except on the first and last half segments, so the
    # estimate equals the time mean square up to an edge effect of order (segment / record) and
    # the fluctuation of the edge samples: 1 s segments on 80 s -> well under 1 %.
    f, S = psd_matrix(x, 0.01, segment_seconds=1.0)
    np.testing.assert_allclose(variance_from_psd(f, S), np.mean(x**2, axis=-2), rtol=1e-2)


def test_welch_band_average_variance_factor():
    """Basis of the statistical tolerances elsewhere: Var of a 10-bin band average of a Welch
    estimate (1 s Hann segments, 50 % overlap, K = 119 per 60 s) is ~ 2.0 / (K * 10) relative."""
    dt = 1e-3
    x = rng_for(4, "welchvar").standard_normal((40, 60001, 1))
    f, S = psd_matrix(x, dt, segment_seconds=1.0)
    a = S[..., 0, 0].real / dt
    bands = a[:, 1:491].reshape(40, 49, 10).mean(-1)  # 1960 band averages
    factor = bands.var() * 119 * 10
    # chi-square std of a variance estimate from ~ 1960 / (bin correlation) values: ~ 5 %.
    assert factor == pytest.approx(2.0, rel=0.15, abs=0)


def test_batched_equals_loop():
    x = rng_for(5, "batch").standard_normal((2, 3, 1000, 2))
    f, S = psd_matrix(x, 0.01, segment_seconds=1.0, detrend="linear")
    assert S.shape == (2, 3, 51, 2, 2)
    for i in range(2):
        for j in range(3):
            _, Sij = psd_matrix(x[i, j], 0.01, segment_seconds=1.0, detrend="linear")
            np.testing.assert_allclose(S[i, j], Sij, rtol=1e-13)


def test_psd_dataset_labels():
    rng = rng_for(6, "ds")
    x = rng.standard_normal((3, 2000, 2))
    da = psd_dataset(x, 0.01, segment_seconds=1.0, sensors=["P_obs", "mid"])
    assert da.dims == ("realisation", "frequency", "sensor", "sensor_")
    assert da.attrs["units"] == "m^2/Hz" and da["frequency"].attrs["units"] == "Hz"
    assert list(da["sensor"].values) == ["P_obs", "mid"]
    _, S = psd_matrix(x, 0.01, segment_seconds=1.0)
    np.testing.assert_array_equal(da.values, S)
    # DataArray input with time coordinate and sensor position/tube coordinates
    xa = xr.DataArray(x, dims=("realisation", "time", "sensor"),
                      coords={"time": np.arange(2000) * 0.01, "sensor": ["a", "b"],
                              "x": ("sensor", [6.0, 8.0]), "tube": ("sensor", ["centre", "centre"])},
                      attrs={"units": "m"})
    da2 = psd_dataset(xa, segment_seconds=1.0)
    np.testing.assert_array_equal(da2.values, S)
    assert da2.attrs["dt"] == pytest.approx(0.01, abs=0) and list(da2["x"].values) == [6.0, 8.0]
    assert list(da2["x_"].values) == [6.0, 8.0]
    # transposed input: dims are found by name
    da3 = psd_dataset(xa.transpose("sensor", "time", "realisation"), segment_seconds=1.0)
    np.testing.assert_allclose(da3.values, S, rtol=1e-13)
    with pytest.raises(SpecificationError):
        psd_dataset(x)  # dt needed for arrays
    with pytest.raises(SpecificationError):
        psd_dataset(x, 0.01, sensors=["one"])


def test_confidence_band_quantiles():
    rng = rng_for(7, "cb")
    scale = np.array([1.0, 2.0, 5.0])
    vals = rng.exponential(size=(4000, 3)) * scale
    da = xr.DataArray(vals, dims=("realisation", "frequency"), coords={"frequency": [1.0, 2.0, 3.0]},
                      attrs={"units": "m^2/Hz"})
    cb = confidence_band(da, 0.95)
    np.testing.assert_allclose(cb["lower"].values, np.quantile(vals, 0.025, axis=0), rtol=1e-14)
    np.testing.assert_allclose(cb["upper"].values, np.quantile(vals, 0.975, axis=0), rtol=1e-14)
    assert cb["lower"].attrs["units"] == "m^2/Hz" and cb.attrs["level"] == 0.95
    # exponential quantiles x_q = -scale ln(1 - q); an empirical quantile from N draws has std
    # sqrt(q (1 - q) / N) / pdf(x_q) (asymptotic): 2.7 % relative at 0.975, 10 % at 0.025. 4 sigma.
    for q, got in ((0.025, cb["lower"].values), (0.975, cb["upper"].values)):
        xq = -scale * np.log(1 - q)
        sd = np.sqrt(q * (1 - q) / 4000) / ((1 - q) / scale)
        assert np.all(np.abs(got - xq) < 4 * sd)
    # about 95 % of fresh draws fall in the band
    fresh = rng.exponential(size=(4000, 3)) * scale
    inside = (fresh >= cb["lower"].values) & (fresh <= cb["upper"].values)
    assert inside.mean() == pytest.approx(0.95, abs=0.01)
    ds = confidence_band(xr.Dataset({"psd": da}), 0.9)
    assert set(ds.data_vars) == {"psd_lower", "psd_upper"}
    for bad in (dict(level=1.0), dict(level=0.0), dict(dim="delta")):
        with pytest.raises(SpecificationError):
            confidence_band(da, **bad)
    with pytest.raises(SpecificationError):
        confidence_band(vals)
    with pytest.raises(SpecificationError):
        confidence_band(da.astype(complex))


def test_j_s_and_distance_closed_forms():
    r1, r2, band = 18.0, 20.0, 100.0
    f = np.linspace(0.0, 250.0, 501)  # 0.5 Hz grid
    S = np.zeros((f.size, 2, 2), dtype=complex)
    S[f <= band] = np.diag([r1, r2])
    # J_s = (r1^2 + r2^2) * 2 (both signs) * 2 pi (rad/s per Hz) * band
    assert j_s(f, S, band) == pytest.approx((r1**2 + r2**2) * 2 * 2 * np.pi * band, rel=1e-14, abs=0)
    # complex off-diagonal c counts twice (|S_12|^2 + |S_21|^2)
    c = 3.0 - 4.0j
    S2 = S.copy()
    S2[f <= band, 0, 1] = c
    S2[f <= band, 1, 0] = np.conj(c)
    assert j_s(f, S2, band) == pytest.approx((r1**2 + r2**2 + 2 * abs(c) ** 2) * 4 * np.pi * band, rel=1e-14, abs=0)
    # band not on the grid: integrate to the edge (interpolated integrand of a constant)
    assert j_s(f, S2, 99.7) == pytest.approx((r1**2 + r2**2 + 2 * abs(c) ** 2) * 4 * np.pi * 99.7, rel=1e-14, abs=0)
    # scalar PSD a f on [0, B]: J = 4 pi a^2 B^3 / 3 (trapezoid error (Δf/B)^2 / 2 ~ 1.3e-5)
    a = 0.01
    assert j_s(f, a * f, band) == pytest.approx(4 * np.pi * a**2 * band**3 / 3, rel=2e-5, abs=0)
    # batched
    both = np.stack([S, S2])
    np.testing.assert_allclose(j_s(f, both, band), [j_s(f, S, band), j_s(f, S2, band)], rtol=1e-14)
    # D between constant diag(r) and diag(r') = |r - r'|^2 * 4 pi band
    Sexp = np.zeros_like(S)
    Sexp[f <= band] = np.diag([15.0, 21.0])
    assert distance(f, S, Sexp, band) == pytest.approx((3.0**2 + 1.0**2) * 4 * np.pi * band, rel=1e-14, abs=0)
    assert distance(f, S, S, band) == 0.0
    with pytest.raises(SpecificationError):
        j_s(f, S, 300.0)  # grid does not cover the band
    with pytest.raises(SpecificationError):
        j_s(f[1:], S[1:], band)  # must start at 0 Hz
    with pytest.raises(SpecificationError):
        j_s(f, S, -1.0)
    with pytest.raises(SpecificationError):
        distance(f, S, S[:10], band)


def test_log_level_closed_forms():
    """Mean over 5 Hz bands and sensors of log(Σ S Δf): white S0 gives log(5 S0) exactly; a PSD
    rising as f gives the mean of log(∫ band) (rectangle sums on the grid, computed here by hand);
    a factor c on the PSD moves the level by log c; only the auto-spectra count."""
    f = np.arange(0.0, 150.0 + 1e-9, 0.125)
    S0 = 3e-12
    assert log_level(f, np.full(f.size, S0)) == pytest.approx(np.log(5.0 * S0), rel=1e-14, abs=0)
    ramp = 1e-12 * (1.0 + f)
    by_hand = np.mean([np.log(ramp[(f > a) & (f <= a + 5.0)].sum() * 0.125) for a in range(0, 100, 5)])
    assert log_level(f, ramp) == pytest.approx(by_hand, rel=1e-14, abs=0)
    S = np.zeros((f.size, 2, 2), dtype=complex)
    S[:, 0, 0], S[:, 1, 1], S[:, 0, 1] = S0, ramp, 5e-12j  # the cross-spectrum is ignored
    both = (np.log(5.0 * S0) + by_hand) / 2
    assert log_level(f, S) == pytest.approx(both, rel=1e-14, abs=0)
    assert log_level(f, 7.0 * S) - log_level(f, S) == pytest.approx(np.log(7.0), rel=1e-12, abs=0)
    np.testing.assert_allclose(log_level(f, np.stack([S, 2 * S])), [both, both + np.log(2.0)], rtol=1e-14)
    assert log_level(f, np.full(f.size, S0), band=50.0, band_width=10.0) == pytest.approx(np.log(10.0 * S0), rel=1e-14, abs=0)
    # a grid ending within one bin below the band (a Welch grid of 99.9 Hz): the last band ends there
    g = np.arange(0.0, 99.95, 0.1)
    assert log_level(g, np.full(g.size, S0)) == pytest.approx(np.log(5.0 * S0), rel=0.03, abs=0)
    for kw, field in ((dict(band=200.0), "band"), (dict(band_width=7.0), "band_width"),
                      (dict(band_width=0.01), "band_width"), (dict(band=0.0), "band ="), (dict(band=-100.0), "band =")):
        with pytest.raises(SpecificationError, match=field):
            log_level(f, np.full(f.size, S0), **kw)
    with pytest.raises(SpecificationError, match=r"\(1201, 2, 3\)"):  # the shape given, not a padded one
        log_level(f, np.zeros((f.size, 2, 3)))
    hole = np.full(f.size, S0)
    hole[(f > 20) & (f <= 25)] = 0.0
    with pytest.raises(SpecificationError, match="without energy"):
        log_level(f, hole)
    with pytest.raises(SpecificationError, match="without energy"):
        log_level(f, -hole)  # negative energy: refused too, without a warning from the log
    with pytest.raises(SpecificationError, match="uniform grid from 0"):
        log_level(f[1:], np.full(f.size - 1, S0))


def test_refusals():
    x = np.zeros((1000, 2))
    for kw in (dict(segment_seconds=0.0), dict(segment_seconds=20.0), dict(overlap=1.0), dict(overlap=-0.1),
               dict(detrend="quadratic"), dict(window="nonsense")):
        with pytest.raises(SpecificationError):
            psd_matrix(x, 0.01, **kw)
    with pytest.raises(SpecificationError):
        psd_matrix(x, 0.0)
    with pytest.raises(SpecificationError):
        psd_matrix(np.zeros(100), 0.01)
    with pytest.raises(SpecificationError):
        psd_matrix(np.full((100, 1), np.nan), 0.01)
    with pytest.raises(SpecificationError):
        variance_from_psd(np.array([1.0, 2.0]), np.ones((2, 1, 1)))


def test_the_default_window_is_scipys_periodic_hann_and_others_are_scipys():
    """The default "hann" is computed without scipy.signal (see spectra._window); the PSDs must not
    change by it: the window equals scipy's to round-off (bit-identical on the scipy this was
    written against), for even and odd lengths; any other window is scipy's own."""
    from tubeid.dynamics.spectra import _window

    for n in (1, 2, 3, 7, 256, 1001, 4000):
        np.testing.assert_allclose(_window("hann", n), scipy.signal.get_window("hann", n), rtol=0, atol=1e-15)
    for spec in ("hamming", ("tukey", 0.3), "boxcar"):
        assert np.array_equal(_window(spec, 300), scipy.signal.get_window(spec, 300))
    x = rng_for(3, "hann").standard_normal((4000, 2))
    _, S = psd_matrix(x, 0.01, segment_seconds=5.0)
    _, S_scipy = psd_matrix(x, 0.01, segment_seconds=5.0, window=scipy.signal.get_window("hann", 500))
    np.testing.assert_allclose(S, S_scipy, rtol=1e-13, atol=0)


def test_importing_the_dynamics_does_not_import_scipy_signal():
    """scipy.signal costs ~0.5 s to import, in the runner and in every worker of a study: the
    default estimator must not need it (a detrend or another window imports it when used)."""
    import subprocess
    import sys

    code = ("import sys, numpy as np, tubeid.dynamics.response, tubeid.dynamics.spectra as s\n"
            "s.psd_matrix(np.ones((64, 1)), 0.01, segment_seconds=0.2)\n"
            "assert 'scipy.signal' not in sys.modules, 'imported'\n"
            "s.psd_matrix(np.ones((64, 1)), 0.01, segment_seconds=0.2, detrend='linear')\n"
            "assert 'scipy.signal' in sys.modules\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr


def test_a_window_given_as_weights():
    """``window`` may be the weights themselves (as the docstring says): the same estimate as the
    named window; a wrong length or a non-finite weight is refused naming the field."""
    x = rng_for(4, "weights").standard_normal((3000, 2))
    _, S = psd_matrix(x, 0.01, segment_seconds=4.0, window="hamming")
    _, S_w = psd_matrix(x, 0.01, segment_seconds=4.0, window=list(scipy.signal.get_window("hamming", 400)))
    assert np.array_equal(S, S_w)
    for bad in (np.ones(399), np.ones((400, 1)), np.r_[np.ones(399), np.nan], ["a"] * 400):
        with pytest.raises(SpecificationError, match="window"):
            psd_matrix(x, 0.01, segment_seconds=4.0, window=bad)


# --------------------------------------------------------------------------- input validation (review)
def _welch_inputs():
    x = rng_for(5, "validation").standard_normal((2000, 2))
    f, S = psd_matrix(x, 0.01, segment_seconds=2.0)
    return x, f, S


def test_psd_dataset_time_must_be_seconds_and_agree_with_a_given_dt():
    """A timedelta64 time coordinate was read as bare counts (1 ms steps gave dt = 1.0 s), and a given
    dt silently overrode a time coordinate that disagreed with it."""
    y = rng_for(5, "psd_dataset").standard_normal((4000, 1))
    steps = np.arange(4000) * np.timedelta64(1, "ms")
    for t in (steps, np.datetime64("2024-01-01T00:00:00") + steps):
        da = xr.DataArray(y, dims=("time", "sensor"), coords={"time": t, "sensor": ["a"]})
        with pytest.raises(SpecificationError, match=r"^x\.time\.dtype = .*numeric seconds"):
            psd_dataset(da)
        with pytest.raises(SpecificationError, match=r"^x\.time\.dtype = "):
            psd_dataset(da, dt=1e-3)
    da = xr.DataArray(y, dims=("time", "sensor"), coords={"time": 2.0 + np.arange(4000) * 1e-3, "sensor": ["a"]})
    with pytest.raises(SpecificationError, match=r"^dt = 0\.01: disagrees with the step of the time coordinate"):
        psd_dataset(da, dt=0.01)
    with pytest.raises(SpecificationError, match=r"^dt = True: must be a finite number > 0"):
        psd_dataset(da, dt=True)
    # a dt that agrees (to 1e-6) is accepted: the coordinate's estimate, to the relative difference of the dts
    np.testing.assert_allclose(psd_dataset(da, dt=1e-3 * (1 + 1e-8)).values, psd_dataset(da).values, rtol=1e-7)


def test_variance_from_psd_refuses_a_descending_grid_non_finite_and_shapeless_spectra():
    _, f, S = _welch_inputs()
    with pytest.raises(SpecificationError, match=r"^f = .*must increase from 0 Hz"):
        variance_from_psd(-f, S)  # was a negative variance
    with pytest.raises(SpecificationError, match=r"^S = .*NaN or infinite.*must be finite"):
        variance_from_psd(f, S * np.nan)  # was NaN
    with pytest.raises(SpecificationError, match=r"^S = \(\): must be \(\.\.\., 101, m, m\)"):
        variance_from_psd(f, 1.0)  # was an IndexError
    with pytest.raises(SpecificationError, match=r"^f = "):
        variance_from_psd(f * np.nan, S)


def test_j_s_and_distance_refuse_non_finite_spectra_and_text_frequencies():
    _, f, S = _welch_inputs()
    with pytest.raises(SpecificationError, match=r"^S = .*must be finite"):
        j_s(f, S * np.nan, 10)
    with pytest.raises(SpecificationError, match=r"^S_exp = .*must be finite"):
        distance(f, S, S * np.nan, 10)
    with pytest.raises(SpecificationError, match=r"^S_model = .*must be finite"):
        distance(f, np.where(f[:, None, None] > 3, np.inf, S), S, 10)
    with pytest.raises(SpecificationError, match=r"^f = .*must be an array of real numbers"):
        j_s(["a", "b"], S[:2], band=1)  # was a raw ValueError
    with pytest.raises(SpecificationError, match=r"^band = True: must be a finite number > 0 \(Hz\)"):
        j_s(f, S, band=True)


@pytest.mark.parametrize("kw, field", [(dict(band="x"), "band"), (dict(band=None), "band"), (dict(band=True), "band"),
                                       (dict(band_width="x"), "band_width"), (dict(band_width=True), "band_width"),
                                       (dict(band_width=None), "band_width")])
def test_log_level_band_and_band_width_must_be_numbers(kw, field):
    """Text and None raised raw ValueError/TypeError; True passed as 1 Hz."""
    _, f, S = _welch_inputs()
    args = dict(band=10.0, band_width=0.5) | kw
    with pytest.raises(SpecificationError, match=rf"^{field} = .*: must be a finite number > 0 \(Hz\)"):
        log_level(f, S, **args)


def test_log_level_refuses_a_descending_grid_and_non_finite_spectra():
    _, f, S = _welch_inputs()
    with pytest.raises(SpecificationError, match=r"^f = .*increasing"):
        log_level(-f, S, band=10.0, band_width=0.5)
    with pytest.raises(SpecificationError, match=r"^S = .*must be finite"):
        log_level(f, S * np.nan, band=10.0, band_width=0.5)


def test_psd_matrix_refuses_bool_numbers_complex_records_and_an_all_zero_window():
    x = rng_for(5, "psd_matrix").standard_normal((1000, 2))
    with pytest.raises(SpecificationError, match=r"^dt = True: must be a finite number > 0 \(s\)"):
        psd_matrix(x, True, segment_seconds=100)
    with pytest.raises(SpecificationError, match=r"^dt = '0.01': "):
        psd_matrix(x, "0.01")
    with pytest.raises(SpecificationError, match=r"^segment_seconds = True: must be a finite number > 0 \(s\)"):
        psd_matrix(x, 0.01, segment_seconds=True)
    for ov in (False, "0.5"):
        with pytest.raises(SpecificationError, match=r"^overlap = .*: must be a finite number in \[0, 1\)"):
            psd_matrix(x, 0.01, overlap=ov)
    with pytest.raises(SpecificationError, match=r"^window = .*must not all be zero"):
        psd_matrix(x, 0.01, window=np.zeros(200))  # was a ZeroDivisionError
    with pytest.raises(SpecificationError, match=r"^window = .*must not all be zero"):
        psd_matrix(x, 0.01, window=np.full(200, 1e-200))  # Σw² underflows to 0
    for bad in (x + 1j * x, x > 0, np.ones((1000, 2), "m8[s]")):
        with pytest.raises(SpecificationError, match=r"^x = array of dtype .*must be an array of real numbers"):
            psd_matrix(bad, 0.01)  # complex was truncated to its real part, with only a ComplexWarning
        with pytest.raises(SpecificationError, match=r"^x = "):
            auto_psd(bad, 0.01)
    with pytest.raises(SpecificationError, match=r"^window = .*real numbers"):
        psd_matrix(x, 0.01, window=np.hanning(200) * (1 + 1j))


def test_window_weights_may_be_negative():
    """Negative weights are allowed (documented): scipy's own flat-top window has some, and the
    estimate |FFT(w x)|² dt / Σw² stays a non-negative density."""
    w = scipy.signal.get_window("flattop", 200)
    assert w.min() < 0
    x = rng_for(5, "flattop").standard_normal((1000, 2))
    _, S = psd_matrix(x, 0.01, window="flattop")
    _, S_w = psd_matrix(x, 0.01, window=w)
    assert np.array_equal(S, S_w) and np.all(np.real(np.diagonal(S, axis1=-2, axis2=-1)) >= 0)


def test_confidence_band_level_must_be_a_number():
    samples = xr.DataArray(rng_for(5, "band").random((10, 4)), dims=("realisation", "frequency"))
    for bad in ("0.9", True):
        with pytest.raises(SpecificationError, match=r"^level = .*: must be a finite number in \(0, 1\)"):
            confidence_band(samples, bad)


def test_an_overlap_that_would_hold_one_segment_per_sample_is_refused():
    """overlap = 0.9999 on 8 s segments materialised a segment per sample (MemoryError)."""
    x = rng_for(5, "overlap").standard_normal((20000, 1))
    with pytest.raises(SpecificationError, match=r"^overlap = 0.9999: must be at most 0.95 \(a hop of at least 5% "):
        psd_matrix(x, 3e-3, segment_seconds=8.0, overlap=0.9999)
    assert psd_matrix(x, 3e-3, segment_seconds=8.0, overlap=0.95)[1].shape[-1] == 1
