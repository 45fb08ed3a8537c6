"""Tests of the KDE likelihood curve: scipy oracle, closed forms, and bootstrap statistics.

Model used for the statistical tests: X(θ) = θ + 0.1 Z with the same Z ~ N(0,1) for every θ
(common random numbers). Given the bandwidth h, E p̂(x_ref; θ) = φ(x_ref; θ, 0.01 + h²), whose
maximiser is θ = x_ref exactly. All seeds are fixed; tolerances are stated next to each check.
"""

import math
import statistics

import numpy as np
import pytest
import xarray as xr
from scipy import stats

from tubeid.errors import SpecificationError
from tubeid.identification.likelihood import _refine_argmax, kde_pdf, likelihood_curve, silverman_bandwidth
from tubeid.seeds import rng_for

GRID = np.linspace(0.0, 1.0, 51)
X_REF = 0.37


def _crn_samples(n, seed, grid=GRID):
    z = rng_for(seed, "z").standard_normal(n)
    return grid[:, None] + 0.1 * z


def test_silverman_formula():
    x = rng_for(1, "silverman").gamma(2.0, size=137)
    expected = 1.06 * statistics.stdev(x.tolist()) * 137 ** (-1 / 5)  # stdev: ddof = 1
    assert silverman_bandwidth(x) == pytest.approx(expected, rel=1e-12, abs=0)
    batch = np.stack([x, 3 * x])
    assert np.allclose(silverman_bandwidth(batch), [expected, 3 * expected], rtol=1e-12, atol=0)


def test_kde_matches_scipy_gaussian_kde():
    x = rng_for(2, "kde").standard_t(4, size=300)
    pts = np.linspace(-6, 6, 97)
    h = silverman_bandwidth(x)
    ref = stats.gaussian_kde(x, bw_method=h / x.std(ddof=1))(pts)  # scipy's kernel sd = factor·σ̂ = h
    # both are double-precision sums of 300 terms: agreement to 1e-10 relative (observed ~1e-15)
    np.testing.assert_allclose(kde_pdf(x, pts), ref, rtol=1e-10, atol=0)
    # batched: samples (3, N) with scalar x, against scipy row by row
    batch = np.stack([x, 0.5 * x + 1, x**2])
    ref_b = [stats.gaussian_kde(r, bw_method=silverman_bandwidth(r) / r.std(ddof=1))(0.7)[0] for r in batch]
    np.testing.assert_allclose(kde_pdf(batch, 0.7), ref_b, rtol=1e-10, atol=0)
    # batched with x (M, 1) against samples (3, N) -> (M, 3)
    out = kde_pdf(batch, pts[:, None])
    assert out.shape == (97, 3)
    np.testing.assert_allclose(out[:, 1], stats.gaussian_kde(batch[1], bw_method=silverman_bandwidth(batch[1])
                                                             / batch[1].std(ddof=1))(pts), rtol=1e-10, atol=0)
    # explicit bandwidth; integrates to 1 (trapezoid on a wide fine grid, error << 1e-6)
    xs = np.linspace(-40, 40, 16001)
    assert np.trapezoid(kde_pdf(x, xs, bandwidth=0.3), xs) == pytest.approx(1.0, abs=1e-6)


def test_likelihood_is_kde_and_near_closed_form():
    s = _crn_samples(1000, 3)
    ds = likelihood_curve(s, X_REF, GRID, grid_name="theta", n_bootstrap=200, rng=rng_for(3, "boot"))
    assert ds.likelihood.dims == ("theta",) and np.array_equal(ds.theta.values, GRID)
    np.testing.assert_allclose(ds.likelihood.values, kde_pdf(s, X_REF), rtol=1e-12)
    np.testing.assert_allclose(ds.log_likelihood.values, np.log(kde_pdf(s, X_REF)), rtol=1e-12)
    assert np.all(ds.likelihood_low <= ds.likelihood) and np.all(ds.likelihood <= ds.likelihood_high)
    # closed form of E p̂ given h; where the curve is not negligible (> 5 % of its peak) the
    # estimate must lie within 4 bootstrap standard deviations (observed max ≈ 2.9 over 5 seeds)
    h = ds.bandwidth.values[0]
    expected = stats.norm.pdf(X_REF, GRID, math.sqrt(0.01 + h * h))
    m = expected > 0.05 * expected.max()
    assert np.all(np.abs(ds.likelihood.values[m] - expected[m]) < 4 * ds.likelihood_std.values[m])


def test_argmax_recovers_known_parameter():
    ds = likelihood_curve(_crn_samples(1000, 4), X_REF, GRID, grid_name="theta", n_bootstrap=200,
                          rng=rng_for(4, "boot"))
    a = ds.attrs
    # the sampling sd of this argmax estimator (N = 1000) was measured at 0.0126 over 150 seeds;
    # tolerance 4 × 0.0126 ≈ 0.05, and 4 bootstrap standard deviations
    assert abs(a["argmax"] - X_REF) < 0.05
    assert abs(a["argmax"] - X_REF) < 4 * a["argmax_std"]
    assert a["argmax_low"] <= a["argmax"] <= a["argmax_high"]
    assert abs(a["argmax"] - a["argmax_discrete"]) <= GRID[1] - GRID[0]
    assert a["argmax_at_boundary"] == 0


def test_bootstrap_std_matches_sampling_std():
    # 40 independent data sets: the true sd of p̂ and of the argmax vs the mean bootstrap sd.
    # A sd from 40 replicates has relative SE ≈ 1/√80 ≈ 11 %: accept ratios in [0.7, 1.4] (≈ 3 SE);
    # the argmax sd is noisier (heavier tails), accept [0.6, 1.6]. Measured over 150 sets: 1.00–1.07.
    grid = np.linspace(0.1, 0.6, 11)
    p, p_sd, arg, arg_sd = [], [], [], []
    for seed in range(40):
        ds = likelihood_curve(_crn_samples(200, 100 + seed, grid), X_REF, grid, grid_name="theta",
                              n_bootstrap=100, rng=rng_for(seed, "boot"))
        p.append(ds.likelihood.values)
        p_sd.append(ds.likelihood_std.values)
        arg.append(ds.attrs["argmax"])
        arg_sd.append(ds.attrs["argmax_std"])
    ratio = np.mean(p_sd, axis=0) / np.std(p, axis=0, ddof=1)
    assert np.all((ratio > 0.7) & (ratio < 1.4)), ratio
    r_arg = np.mean(arg_sd) / np.std(arg, ddof=1)
    assert 0.6 < r_arg < 1.6, r_arg


def test_bootstrap_std_shrinks_with_n():
    # KDE variance ~ 1/(N h) ~ N^(-4/5): sd ratio (1600/100)^(2/5) ≈ 3.0; require > 2 at the median
    small = likelihood_curve(_crn_samples(100, 5), X_REF, GRID, n_bootstrap=200, rng=rng_for(5, "b"))
    large = likelihood_curve(_crn_samples(1600, 5), X_REF, GRID, n_bootstrap=200, rng=rng_for(5, "b"))
    core = slice(10, 30)  # θ in [0.2, 0.58], where the likelihood is not negligible
    ratio = small.likelihood_std.values[core] / large.likelihood_std.values[core]
    assert np.median(ratio) > 2.0, ratio
    assert large.attrs["argmax_std"] < small.attrs["argmax_std"]


def test_bootstrap_resamples_jointly_across_grid():
    # Identical rows: with one index set per replicate for all grid values, every replicate's
    # curve is flat, so bootstrap sd and interval are identical along the grid (independent
    # per-row resampling would make them differ).
    z = rng_for(6, "z").standard_normal(300)
    ds = likelihood_curve(np.tile(z, (7, 1)), 0.2, np.arange(7.0), n_bootstrap=50, rng=rng_for(6, "b"))
    for var in ("likelihood_std", "likelihood_low", "likelihood_high"):
        v = ds[var].values
        assert np.all(v == v[0]) and v[0] > 0, var


def test_parabola_refinement():
    grid = np.array([0.0, 0.1, 0.25, 0.3, 0.55, 0.6, 1.0])  # non-uniform
    vertices = np.array([0.2, 0.41, 0.57])
    ll = -3.0 * (grid[None, :] - vertices[:, None]) ** 2 + 1.0  # exact parabolas
    discrete, refined = _refine_argmax(grid, ll)
    np.testing.assert_allclose(refined, vertices, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(discrete, [0.25, 0.3, 0.55])
    # maximum at a grid end or next to a zero likelihood: no refinement
    edge = np.array([[0.0, -1, -2, -3, -4, -5, -6], [-9, -np.inf, 0, -1, -2, -3, -4]])
    d, r = _refine_argmax(grid, edge)
    np.testing.assert_array_equal(r, d)
    np.testing.assert_array_equal(d, [0.0, 0.25])
    # the curve reports either the refined or the discrete maximiser
    s = _crn_samples(300, 7)
    a = likelihood_curve(s, X_REF, GRID, n_bootstrap=0).attrs
    b = likelihood_curve(s, X_REF, GRID, n_bootstrap=0, refine=False).attrs
    assert b["argmax"] == a["argmax_discrete"] and a["argmax"] != a["argmax_discrete"]


def test_far_reference_uses_log_likelihood():
    # x_ref = 5 is ~150 bandwidths beyond every sample: p underflows to 0 but the log-likelihood
    # stays finite and still ranks the grid, so the maximiser is the grid end nearest x_ref.
    ds = likelihood_curve(_crn_samples(200, 10), 5.0, GRID, n_bootstrap=10, rng=1)
    assert np.all(np.isfinite(ds.log_likelihood)) and ds.likelihood.values[-1] == 0.0
    assert np.all(np.diff(ds.log_likelihood.values) > 0)
    assert ds.attrs["argmax"] == 1.0 and ds.attrs["argmax_at_boundary"] == 1


def test_no_bootstrap_dataarray_input_and_netcdf(tmp_path):
    s = _crn_samples(100, 8)
    da = xr.DataArray(s.T, dims=("realisation", "delta"))  # transposed on purpose
    ds = likelihood_curve(da, X_REF, GRID, n_bootstrap=0)
    np.testing.assert_allclose(ds.likelihood.values, kde_pdf(s, X_REF), rtol=1e-12)
    assert np.all(np.isnan(ds.likelihood_std)) and math.isnan(ds.attrs["argmax_std"])
    ds2 = likelihood_curve(s, X_REF, GRID, n_bootstrap=20, rng=3)
    assert np.array_equal(ds2.likelihood_std, likelihood_curve(s, X_REF, GRID, n_bootstrap=20, rng=3).likelihood_std)
    ds2.to_netcdf(tmp_path / "likelihood.nc", engine="h5netcdf")  # attrs are plain floats/ints/strings
    back = xr.load_dataset(tmp_path / "likelihood.nc", engine="h5netcdf")
    np.testing.assert_array_equal(back.likelihood_std, ds2.likelihood_std)
    assert back.attrs["argmax"] == ds2.attrs["argmax"]


def _raises(fn, *needles):
    with pytest.raises(SpecificationError) as exc:
        fn()
    for needle in needles:
        assert needle in str(exc.value), str(exc.value)


def test_refusals():
    s = _crn_samples(50, 9)
    _raises(lambda: likelihood_curve(s[:, :4], X_REF, GRID, n_bootstrap=0), "samples", "at least 5 samples")
    _raises(lambda: likelihood_curve(s[:-1], X_REF, GRID, n_bootstrap=0), "samples = array of shape (50, 50)",
            "(len(grid), N) = (51, N)")
    _raises(lambda: likelihood_curve(s[0], X_REF, GRID, n_bootstrap=0), "samples", "(len(grid), N)")
    bad = s.copy()
    bad[3, 7] = np.nan
    _raises(lambda: likelihood_curve(bad, X_REF, GRID, n_bootstrap=0), "samples", "non-finite", "must be finite")
    _raises(lambda: likelihood_curve(s, X_REF, GRID[::-1], n_bootstrap=0), "grid", "strictly increasing")
    g2 = GRID.copy()
    g2[5] = g2[4]
    _raises(lambda: likelihood_curve(s, X_REF, g2, n_bootstrap=0), "grid", "strictly increasing")
    _raises(lambda: likelihood_curve(s, float("nan"), GRID, n_bootstrap=0), "x_ref = nan")
    _raises(lambda: likelihood_curve(s, X_REF, GRID, n_bootstrap=-1), "n_bootstrap = -1")
    _raises(lambda: likelihood_curve(s, X_REF, GRID, n_bootstrap=10), "rng = None", "n_bootstrap > 0")
    const = np.ones((51, 10))
    _raises(lambda: likelihood_curve(const, 1.0, GRID, n_bootstrap=0), "constant samples at delta = 0", "zero spread")
    _raises(lambda: silverman_bandwidth([1.0]), "at least 2 samples")
    _raises(lambda: kde_pdf(s, np.zeros(3)), "x = array of shape (3,)", "broadcast")
    _raises(lambda: kde_pdf(s[0], 0.1, bandwidth=0.0), "bandwidth = 0.0", "> 0")


def test_bootstrap_with_several_observations_includes_their_sampling_error():
    # 10 observations of X(0.37) = 0.37 + 0.1 Z: the joint-likelihood argmax is close to their mean,
    # whose sampling sd is 0.1/√10 = 0.032 (the model's own Monte Carlo error, N = 200, is ~4x smaller).
    # Over 40 independent (observations, model) sets the true sd of the argmax must match the mean
    # bootstrap sd: ratio in [0.6, 1.6] as in the single-observation test (relative SE of a sd from
    # 40 replicates ≈ 11 %; measured 0.88). Resampling only the model would give a ratio near 0.25.
    grid = np.linspace(0.1, 0.6, 26)
    arg, arg_sd = [], []
    for seed in range(40):
        obs = X_REF + 0.1 * rng_for(seed, "obs").standard_normal(10)
        ds = likelihood_curve(_crn_samples(200, 500 + seed, grid), obs, grid, grid_name="theta",
                              n_bootstrap=60, rng=rng_for(seed, "boot"))
        arg.append(ds.attrs["argmax"])
        arg_sd.append(ds.attrs["argmax_std"])
    true_sd = np.std(arg, ddof=1)
    assert 0.6 < np.mean(arg_sd) / true_sd < 1.6, (np.mean(arg_sd), true_sd)
    assert true_sd == pytest.approx(0.1 / np.sqrt(10), rel=0.35, abs=0)  # the observations dominate


def test_observations_far_from_the_samples_give_a_finite_bootstrap():
    # 50 observations far in the tail: the joint log-likelihood is hugely negative and a replicate's
    # maximum can exceed the curve's by far more than exp can hold; the bootstrap normalises each
    # replicate by its own maximum, so no overflow (an error here) and finite spreads.
    import warnings

    grid = np.linspace(0.1, 0.6, 11)
    s = grid[:, None] + 0.01 * rng_for(1, "far").standard_normal(100)
    obs = 0.9 + 0.01 * np.arange(50)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds = likelihood_curve(s, obs, grid, "theta", n_bootstrap=50, rng=1)
    assert np.all(np.isfinite(ds.likelihood_std.values)) and ds.attrs["argmax"] == pytest.approx(0.6, abs=0)
    assert float(ds.likelihood.max()) == pytest.approx(1.0, abs=0)


def test_edge_and_flat_verdicts_fire_on_cases_built_for_them_and_not_otherwise():
    """X(θ) = θ + 0.1 Z (common Z, N = 200) on θ = 0.1 … 1.0:
    * x_ref = 1.5 beyond the grid: argmax on the upper edge, not flat (Λ in the hundreds);
    * x_ref = 0.55 inside: interior, not flat; the 95 % likelihood-ratio interval is the set where
      the KDE density N(θ, 0.1² + h²) at 0.55 stays within e^1.92 of its maximum, closed form
      0.55 ± √3.84 · √(0.01 + h²) → the grid points 0.35 … 0.75;
    * X(θ) = Z + 0.01 θ: the likelihood barely moves (Λ ≈ 1e-3): flat, interval = the whole grid;
    * independent rows of 8 samples with x_ref = 2 in their tail: the log-likelihood varies by a few
      units across the grid (above the 1.92 of the test) but no grid value's drop exceeds 1.92 + 2
      bootstrap σ of it: Monte Carlo noise, flat."""
    g = np.round(np.arange(0.1, 1.0001, 0.05), 3)
    z = np.random.default_rng(3).standard_normal(200)
    edge = likelihood_curve(g[:, None] + 0.1 * z, 1.5, g, n_bootstrap=200, rng=1).attrs
    assert edge["argmax_at_boundary"] == 1 and edge["argmax"] == 1.0 and not edge["flat"] and edge["n_excluded"] > 10
    inner = likelihood_curve(g[:, None] + 0.1 * z, 0.55, g, n_bootstrap=200, rng=1).attrs
    assert inner["argmax_at_boundary"] == 0 and not inner["flat"]
    h = 1.06 * np.std(z * 0.1, ddof=1) * 200 ** -0.2
    half = np.sqrt(2 * 1.920729410347062) * np.sqrt(np.var(0.1 * z, ddof=1) + h ** 2)
    assert inner["lr_interval_low"] == g[g >= 0.55 - half][0] and inner["lr_interval_high"] == g[g <= 0.55 + half][-1]
    flat = likelihood_curve(z[None, :] + 0.01 * g[:, None], 0.0, g, n_bootstrap=200, rng=1).attrs
    assert flat["flat"] and flat["log_likelihood_range"] < 0.01
    assert (flat["lr_interval_low"], flat["lr_interval_high"]) == (g[0], g[-1])
    noisy = likelihood_curve(np.random.default_rng(0).standard_normal((g.size, 8)), 2.0, g, n_bootstrap=200, rng=1).attrs
    assert noisy["log_likelihood_range"] > 1.92 and noisy["flat"] and noisy["n_excluded"] == 0
    assert likelihood_curve(g[:, None] + 0.1 * z, 0.55, g, n_bootstrap=0).attrs["flat"] == 0


def test_variance_corrected_kernel_removes_the_bias_of_a_dispersion_read_from_a_spread():
    """θ is the standard deviation of a centred Gaussian observable; 40 model samples per θ (common
    random numbers) and 32 observations at θ = 1, repeated 300 times (seeded). Silverman's kernel
    widens each density's variance by 1.12·40^(−0.4) = 26 %, so the uncorrected maximum sits low
    (near 1/√1.26 = 0.89); the variance-corrected one near 1. Measured medians of 300 estimates:
    0.930 and 1.034 (each estimate ±0.19, so a median is known to ±0.013): the corrected median
    within 0.06 of 1, and above the plain one by more than 0.07 (no correction: 0; a correction
    applied twice: a median near 1.15)."""
    from tubeid.seeds import rng_for

    grid = np.linspace(0.5, 2.0, 61)
    plain, corrected = [], []
    for rep in range(300):
        gen = rng_for(2026, "variance-corrected", rep)
        z = gen.standard_normal(40)
        obs = gen.standard_normal(32)
        samples = grid[:, None] * z[None, :]
        plain.append(likelihood_curve(samples, obs, grid, "theta", n_bootstrap=0).attrs["argmax"])
        corrected.append(likelihood_curve(samples, obs, grid, "theta", n_bootstrap=0, variance_corrected=True).attrs["argmax"])
    assert abs(np.median(corrected) - 1.0) <= 0.06, np.median(corrected)
    assert np.median(corrected) - np.median(plain) > 0.07, (np.median(plain), np.median(corrected))


@pytest.mark.parametrize("call, needle", [
    (lambda s: kde_pdf(s, True), r"^x = array of dtype bool, shape \(\): must be an array of real numbers"),  # x = 1
    (lambda s: kde_pdf(s, 0.1, bandwidth=True), r"^bandwidth = array of dtype bool, shape \(\): must be an array"),  # h = 1
    (lambda s: kde_pdf(s, "0.1"), r"^x = array of dtype <U3, shape \(\): must be an array of real numbers"),
    (lambda s: kde_pdf(s, 0.1, bandwidth=np.array([True, False])), r"^bandwidth = array of dtype bool, shape \(2,\)"),
    (lambda s: kde_pdf(s, 0.1 + 1e-3j), r"^x = array of dtype complex128, shape \(\): must be an array of real numbers "
                                        r"\(complex values are not truncated to their real part\)"),
    (lambda s: kde_pdf(s + 1e-3j, 0.1), r"^samples = array of dtype complex128, shape \(30,\): must be an array of real "
                                        r"numbers \(complex values are not truncated to their real part\)"),
    (lambda s: silverman_bandwidth(s + 0j), r"^samples = array of dtype complex128"),
    (lambda s: kde_pdf(s > 0, 0.1), r"^samples = array of dtype bool, shape \(30,\)"),
    (lambda s: likelihood_curve(np.tile(s, (3, 1)) + 1e-3j, 0.1, [0.1, 0.2, 0.3], n_bootstrap=0),
     r"^samples = array of dtype complex128"),
    (lambda s: likelihood_curve(np.tile(s, (3, 1)), 0.1 + 1e-3j, [0.1, 0.2, 0.3], n_bootstrap=0),
     r"^x_ref = array of dtype complex128"),
    (lambda s: likelihood_curve(np.tile(s, (3, 1)), np.array([True, False]), [0.1, 0.2, 0.3], n_bootstrap=0),
     r"^x_ref = array of dtype bool"),
    (lambda s: likelihood_curve(np.tile(s, (3, 1)), "0.1", [0.1, 0.2, 0.3], n_bootstrap=0), r"^x_ref = array of dtype <U3"),
    (lambda s: likelihood_curve(np.tile(s, (3, 1)), 0.1, ["0.1", "0.2", "0.3"], n_bootstrap=0),
     r"^grid = array of dtype <U3"),
    (lambda s: likelihood_curve(np.tile(s, (3, 1)), 0.1, np.array([0.1, 0.2, 0.3]) + 0j, n_bootstrap=0),
     r"^grid = array of dtype complex128"),
])
def test_bools_strings_and_complex_values_are_not_numbers(call, needle):
    """Bools were read as 1/0, complex values lost their imaginary part (ComplexWarning only)."""
    import warnings

    s = _crn_samples(30, 3)[10]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(SpecificationError, match=needle):
            call(s)


def _spread_samples(grid_name="delta", coords=(0.1, 0.2, 0.3)):
    """Samples whose spread grows along the grid (N = 40 each), as a DataArray on (grid_name, realisation)."""
    rng = rng_for(7, "likelihood_alignment")
    vals = np.stack([rng.normal(1.0, s, 40) for s in (0.1, 0.2, 0.3)])
    return xr.DataArray(vals, dims=(grid_name, "realisation"), coords={grid_name: list(coords)})


def test_a_dataarray_is_matched_to_the_grid_by_its_coordinate():
    """The rows were taken in storage order: stored in reverse, the same samples gave another argmax (the
    mirror image over the grid), and a grid that disagrees with the coordinate ([.5, .6, .7]) was accepted."""
    S = _spread_samples()
    ordered = likelihood_curve(S, 1.25, [0.1, 0.2, 0.3], n_bootstrap=0)
    for reordered in (S.isel(delta=[2, 1, 0]), S.isel(delta=[1, 2, 0]).T):
        ds = likelihood_curve(reordered, 1.25, [0.1, 0.2, 0.3], n_bootstrap=0)
        np.testing.assert_array_equal(ds.log_likelihood.values, ordered.log_likelihood.values)
        assert ds.attrs["argmax"] == ordered.attrs["argmax"]
    # an ordered DataArray gives the bits of its plain array
    plain = likelihood_curve(S.values, 1.25, [0.1, 0.2, 0.3], n_bootstrap=0)
    np.testing.assert_array_equal(plain.log_likelihood.values, ordered.log_likelihood.values)
    with pytest.raises(SpecificationError, match=r"^grid = \[0.5 0.6 0.7\]: must equal the 'delta' coordinate of "
                                                 r"samples \(\[0.1 0.2 0.3\]"):
        likelihood_curve(S, 1.25, [0.5, 0.6, 0.7], n_bootstrap=0)
