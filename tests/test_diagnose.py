"""tubeid.diagnose: the calibrated test, the catalog, the selection and the loop on independent records.

Test records never come from the diagnosis's own code path: :func:`tubeid.diagnose.testing.make_record`
writes each effect into the specification by hand (a second ``stops`` entry, a changed density or
damping ratio), adds tones as explicit force columns and noise with numpy, and calls the solver
directly (one case with its ``symplectic-euler`` integrator). Effects sit away from the sensors and
from x = 8 m, and the trial method of r starts away from the truth (r0 = 4 N²/Hz, truth 1.3).

Default sizes: 3 sensors (c02, c06, c10), 48 s records, δ = 0 (the declared model generates the
data but for the effect), 19 band realisations (a test of exact size 1/20 = 5 %). ``-m slow``: the
issue's 220 s × 7-sensor cases.
"""

import dataclasses
import json
import shutil
import subprocess
import sys
import time
import unittest.mock

import numpy as np
import pytest
import scipy.linalg
import scipy.stats
import xarray as xr
import zarr

from tubeid.cli import main
from tubeid.diagnose import CATALOG, DiagnoseSettings, detection_test, diagnose
from tubeid.diagnose._selection import Scored, choose, line_minimum, near_ties, prediction_error
from tubeid.diagnose._detection import MODEL_FORMS, Observations
from tubeid.diagnose._spectra import conditional_psd, measured_spectra, time_statistics
from tubeid.diagnose._surrogate import LinearSurrogate
from tubeid.diagnose.catalog import Evidence
from tubeid.diagnose.method import data_hash, load_context
from tubeid.diagnose.testing import HandEffects, make_record, sensors
from tubeid.errors import SpecificationError
from tubeid.measured import read_measurements, validate_measurements, write_measurements
from tubeid.mechanics import builtin_spec
from tubeid.mechanics.assembly import assemble
from tubeid.mechanics.effects import AddedMass, Damping, ExtraStop, SensorNoise, Tone
from tubeid.mechanics.spec import LoadPoint, spec_to_dict
from tubeid.runner.store import store_status, update_attrs
from tubeid.runner.testing import clear_flag, store_digest
from tubeid.uncertainty import coherent_forces

XS = (2.0, 6.0, 10.0)
SEVEN = (2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0)
SMALL = DiagnoseSettings(realisations=19, delta=0.0, fit_realisations=2, grid_points=4, r0=(4.0,), r_points=1,
                         r_fine_points=3, max_effects=2)


def record(effects=HandEffects(), duration=48.0, seed=11, **kw):
    return make_record(effects=effects, xs=XS, duration=duration, seed=seed, **kw)


# ------------------------------------------------------------------------------------ the test


def _spectra(rng, N, F=120, m=3, line=None, shift=0.0, sharp=1.0, scale=1.0):
    """N synthetic Welch-like spectra (N, F, m): resonances at random positions (as a random
    stiffness moves them), a random level, chi-square estimator scatter; optionally a line at bin
    ``line``, a broad tilt ``shift`` [decades per band edge], resonances ``sharp`` × sharper or at
    ``scale`` × their frequencies."""
    f = np.linspace(0.0, 166.0, F)
    out = np.empty((N, F, m))
    for i in range(N):
        f0 = np.array([20.0, 55.0, 90.0]) * scale * (1 + 0.03 * rng.standard_normal(3))
        peaks = sum(1.0 / (1 + ((f - c) / (1.5 / sharp)) ** 2) for c in f0)
        base = 1e-15 * (1 + 30 * peaks)[:, None] * np.exp(-f / 40.0)[:, None] * np.array([1.0, 0.6, 0.3])
        base *= 10 ** (0.1 * rng.standard_normal() + shift * (f / 166.0)[:, None])
        out[i] = base * rng.chisquare(60, size=(F, m)) / 60
        if line is not None:
            out[i, line] *= 20.0
    return f, out


def test_the_test_is_exact_on_exchangeable_samples():
    """The record and the realisations drawn from one law (random resonances, levels, scatter): over
    400 independent draws the test rejects at 5 % within the binomial tolerance (exact size 1/20:
    expected 20 rejections, sd 4.4; the 3-sd interval is 7–33). Each statistic's p-value is uniform
    (Kolmogorov–Smirnov at 1 %)."""
    rng = np.random.default_rng(1)
    rejected, ps = 0, {k: [] for k in ("scan", "gof", "sharpness")}
    for _ in range(400):
        f, P = _spectra(rng, 20)
        d = detection_test(P[0], P[1:], f, false_alarm=0.05)
        assert d.size == 0.05 and d.n_realisations == 19
        rejected += d.detected
        for k in ps:
            ps[k].append(d.p_values[k])
    assert 7 <= rejected <= 33, rejected
    for k, v in ps.items():  # discrete uniform on {1/20, ..., 1}: jitter within a step before the KS test
        u = np.asarray(v) - rng.uniform(0, 1 / 20, len(v))
        assert scipy.stats.kstest(u, "uniform").pvalue > 0.01, k


@pytest.mark.parametrize("what", ["line", "shift", "sharp"])
def test_the_test_sees_a_line_a_broad_shift_and_sharper_resonances(what):
    """Each departure, applied to the record only, is detected at the smallest p-value (1/20) by
    the statistic built for it; the line's frequency is where the scan peaks."""
    rng = np.random.default_rng(2)
    f, P = _spectra(rng, 19)
    kw = {"line": {"line": 29}, "shift": {"shift": 0.5}, "sharp": {"sharp": 3.0}}[what]
    _, rec = _spectra(rng, 1, **kw)
    d = detection_test(rec[0], P, f)
    stat = {"line": "scan", "shift": "gof", "sharp": "sharpness"}[what]
    assert d.detected and d.p_value == 0.05 and d.p_values[stat] == 0.05, d
    if what == "line":
        assert d.scan_frequency_hz == pytest.approx(f[29], abs=0)


def test_the_test_refuses_what_it_cannot_calibrate():
    f, P = _spectra(np.random.default_rng(3), 12)
    with pytest.raises(SpecificationError, match="samples"):
        detection_test(P[0], P[1:5], f)  # 4 realisations
    with pytest.raises(SpecificationError, match="samples"):
        detection_test(P[0, :, :2], P[1:], f)
    with pytest.raises(SpecificationError, match="false_alarm"):
        detection_test(P[0], P[1:], f, false_alarm=1.5)
    with pytest.raises(SpecificationError, match="settings.false_alarm"):
        DiagnoseSettings(realisations=9, false_alarm=0.05)  # smallest p-value 1/10 > 5 %


def test_the_tests_after_a_step_share_the_false_alarm_rate_between_them():
    """Bonferroni over the tests that could continue the loop: α / (max_effects − 1) each by
    default, refused where R cannot resolve it, at most α when given."""
    s = DiagnoseSettings()
    assert (s.alarm_at(0), s.alarm_at(1), s.alarm_at(2)) == (0.05, 0.025, 0.025)
    assert DiagnoseSettings(max_effects=2).alarm_at(1) == 0.05
    assert DiagnoseSettings(false_alarm=0.1, continuation_alarm=0.04, realisations=49).alarm_at(2) == 0.04
    with pytest.raises(SpecificationError, match=r"settings.continuation_alarm = 0.025.*1/20"):
        DiagnoseSettings(realisations=19)  # 0.025 < 1/20
    with pytest.raises(SpecificationError, match=r"settings.continuation_alarm = 0.1"):
        DiagnoseSettings(continuation_alarm=0.1)  # above α
    assert DiagnoseSettings(realisations=19, max_effects=1).continuation_rate == 0.05  # the test after step 1
    with pytest.raises(SpecificationError, match=r"settings.continuation_alarm = 0.001"):
        DiagnoseSettings(realisations=19, max_effects=1, continuation_alarm=0.001)  # step 1's test could never detect
    assert DiagnoseSettings(realisations=19, max_effects=0, continuation_alarm=0.001).max_effects == 0  # no test after


def _observations(rng, N, m=3, *, line=None, floor=None, kurtosis=None, sharp=1.0, tilt=0.0, scale=1.0, probe=0):
    """N synthetic samples of what the simplified form's statistics read (:class:`Observations`):
    fine spectra (``_spectra`` at 4 × the resolution), conditional PSDs that are deep and uneven
    above the 100 Hz band (a structure driven there only by impacts) with a per-sample level, and
    excess kurtoses scattered per sensor. The departures of the record: a ``line`` at fine bin k,
    a white ``floor`` [m²/Hz] added to the conditional PSD, a ``kurtosis`` of −1 at sensor k,
    resonances ``sharp`` × sharper, fine spectra steeper by ``tilt`` decades per decade of
    frequency, resonances at ``scale`` × their frequencies (a heavier tube: below 1). Every
    sample's fine spectra are tilted by a random log-log slope (standard deviation 0.2 decades per
    decade: what the random B of ``paper-simplified`` at δ = 0.63 gives, 0.23). ``probe``: that many
    probe realisations (fine spectra of the same law with resonances at 0.95 × theirs: the
    direction of the ``profile`` statistic)."""
    f = np.linspace(0.0, 166.0, 120)
    ff = np.linspace(0.0, 166.0, 480)
    x = np.log10(np.maximum(ff, 1.0) / 20.0)

    def tilted(fine, n, tilt=0.0):
        return fine * 10.0 ** ((0.2 * rng.standard_normal((n, 1, 1)) - tilt) * x[None, :, None])

    fine = tilted(_spectra(rng, N, F=480, m=m, line=line, sharp=sharp, scale=scale)[1], N, tilt)
    probes = tilted(_spectra(rng, probe, F=480, m=m, scale=0.95)[1], probe) if probe else None
    _, psd = _spectra(rng, N, m=m)
    level = 10.0 ** (-15.0 - 6.0 * (f > 100.0))[None, :, None] * 10 ** (0.2 * rng.standard_normal((N, 1, 1)))
    residual = level * 10.0 ** (0.7 * rng.standard_normal((N, f.size, m)))
    if floor is not None:
        residual = residual + floor
    stats = np.stack([np.full((N, m), 2e-6), np.zeros((N, m)), 0.1 * rng.standard_normal((N, m))], axis=2)
    if kurtosis is not None:
        stats[:, kurtosis, 2] -= 1.0
    return Observations(f, psd, ff, fine, residual, stats, 100.0, probe=probes)


def test_the_simplified_test_is_exact_on_exchangeable_samples():
    """The simplified form's statistics (line, floor, kurtosis, resonance, tilt, profile with 10 probe
    realisations) on samples of one law: over 300 draws the combined test rejects at 5 % within the
    binomial tolerance (exact size 1/20: expected 15, sd 3.8; 3 sd: 4–26), and each statistic's p-value is uniform (KS at 1 % for the
    six together: 1/600 each; the floor's is 0.004 with these draws, 0.1–0.4 with others)."""
    rng = np.random.default_rng(4)
    rejected, ps = 0, {k: [] for k in MODEL_FORMS["simplified"]}
    for _ in range(300):
        d = detection_test(_observations(rng, 20, probe=10), model_form="simplified")
        assert d.size == 0.05 and d.statistics == MODEL_FORMS["simplified"]
        rejected += d.detected
        for k in ps:
            ps[k].append(d.p_values[k])
    assert 4 <= rejected <= 26, rejected
    for k, v in ps.items():
        u = np.asarray(v) - rng.uniform(0, 1 / 20, len(v))
        assert scipy.stats.kstest(u, "uniform").pvalue > 0.01 / len(ps), k


def test_the_simplified_combination_extrapolates_each_tail_by_hand():
    """One statistic, u = 0, 1, …, 58, 80 over N = 60 samples: its 0.9 quantile is 53.1 and the six
    values above it exceed it by 0.9, 1.9, 2.9, 3.9, 4.9 and 26.9 (β = 6.9, their mean; the median
    would be 3.4), so u = 80 has tail probability 0.1·e^(−26.9/6.9) and u = 30 the fraction 30/60
    of samples at least 30; two statistics combine by the smaller. With N = 10 (fewer than
    TAIL_MIN = 5 samples above a 0.9 quantile) the quantile is lowered to 0.5: u = 0, …, 8, 12 has
    t = 4.5, excesses 0.5, 1.5, 2.5, 3.5, 7.5 (β = 3.1), and u = 12 the probability 0.5·e^(−7.5/3.1)."""
    from tubeid.diagnose._detection import COMBINATIONS

    u = np.arange(60.0)
    u[-1] = 80.0
    c = COMBINATIONS["simplified"](u[:, None])
    assert c[59] == pytest.approx(-np.log(0.1) + 26.9 / 6.9, rel=1e-12, abs=0)
    assert c[30] == pytest.approx(-np.log(0.5), rel=1e-12, abs=0)
    assert c[0] == pytest.approx(0.0, abs=1e-12)
    # a second statistic, 0 but at sample 30 (100): its quantile 0, one excess of 100 (β = 100)
    two = COMBINATIONS["simplified"](np.column_stack([u, np.where(u == 30.0, 100.0, 0.0)]))
    assert two[30] == pytest.approx(-np.log(0.1) + 1.0, rel=1e-12, abs=0)
    assert two[59] == pytest.approx(c[59], rel=1e-12, abs=0)
    small = np.r_[np.arange(9.0), 12.0]
    assert COMBINATIONS["simplified"](small[:, None])[9] == pytest.approx(-np.log(0.5) + 7.5 / 3.1, rel=1e-12, abs=0)


def test_the_simplified_test_keeps_its_power_with_few_realisations():
    """R = 9 (N = 10, α = 0.1: the record must rank first), a line in the record, 40 draws: the
    tail-calibrated combination detects about as often as the largest standardised value (23 and
    25 of 40 with these draws). With a 0.9 quantile and one sample above it, every statistic's
    largest value had the same tail probability and the record tied with a realisation: 0 of 40."""
    import tubeid.diagnose._detection as detection

    counts = {}
    for name, comb in (("largest", detection.COMBINATIONS["exact"]), ("tail", detection.COMBINATIONS["simplified"])):
        rng = np.random.default_rng(1)
        with pytest.MonkeyPatch.context() as mp:
            mp.setitem(detection.COMBINATIONS, "simplified", comb)
            counts[name] = sum(detection_test(_observations(rng, 1, line=201).stacked(_observations(rng, 9, probe=5)),
                                              model_form="simplified", false_alarm=0.1).detected for _ in range(40))
    assert counts["largest"] >= 15 and counts["tail"] >= counts["largest"] - 5, counts


def test_a_heavy_tailed_statistic_no_longer_outranks_a_light_tailed_records_excess():
    """A statistic with Student-t (2 dof) realisations beside a Gaussian one whose record sits at
    3.2: the largest standardised value ranks the record behind the t realisations above 3.2 (p >
    5 %), the tail-calibrated combination of the simplified form ranks it first or second."""
    from tubeid.diagnose._detection import COMBINATIONS, _rank_p

    rng = np.random.default_rng(8)
    heavy, light = rng.standard_t(2, 80), rng.standard_normal(80)
    heavy[0], light[0] = 0.0, 3.2
    assert np.sum(heavy > 3.2) >= 4 and np.sum(light[1:] > 3.2) == 0  # what the test needs of the draw
    U = np.column_stack([heavy, light])
    assert _rank_p(COMBINATIONS["exact"](U)) > 0.05
    assert _rank_p(COMBINATIONS["simplified"](U)) <= 2 / 80


@pytest.mark.parametrize("what", ["line", "floor", "kurtosis", "resonance", "tilt", "tilt-", "profile"])
def test_the_simplified_test_sees_each_departure_with_the_statistic_built_for_it(what):
    """A line, a white floor, a clipped sensor, sharper resonances, a spectrum falling faster (or
    slower: the tilt is two-sided) with frequency, resonances lower than the model's (at 0.945 ×,
    beyond the probe realisations' 0.95 ×), each in the record only, against 79 realisations and 20 probe
    realisations: the statistic built for it gives the smallest p-value
    (1/80), the test detects (p = 1/80 or 2/80: on this toy law another statistic's tail can beat
    the record's) and points to its catalog effect. (On this toy law the profile's own power depends
    on the draw: at 0.945 × its p is 1/80 for seeds 5, 7, 8, 9 and 6/80 for seed 6, the test's 8/80;
    the real records are its measure: the slow test and the README.)"""
    rng = np.random.default_rng(5)
    kw = {"line": {"line": 201}, "floor": {"floor": 1e-19}, "kurtosis": {"kurtosis": 1},
          "resonance": {"sharp": 3.0}, "tilt": {"tilt": 1.0}, "tilt-": {"tilt": -1.0},
          "profile": {"scale": 0.945}}[what]
    what = what.rstrip("-")
    rec = _observations(rng, 1, **kw)
    band = _observations(rng, 79, probe=20)
    d = detection_test(rec.stacked(band), model_form="simplified")
    assert d.detected and d.p_value <= 2 / 80 and d.p_values[what] == 1 / 80, d
    effect = {"line": "tone", "floor": "sensor_noise", "kurtosis": "stop", "resonance": "damping",
              "tilt": "added_mass", "profile": "added_mass"}[what]
    assert effect in d.pointed_effects()
    if what == "line":
        assert d.scan_frequency_hz == pytest.approx(rec.frequency_fine[201], abs=0)


def test_the_exact_form_adds_the_profile_where_there_are_probe_realisations():
    """With probe realisations the exact form combines the profile with scan, gof and sharpness;
    without them the three alone. Over 200 draws of exchangeable samples (10 probe realisations) the
    four together reject at 5 % within the binomial tolerance (exact size 1/20: expected 10, sd 3.1;
    3 sd: 1–19). A record whose fine spectra alone have their resonances at 0.945 × (what the
    profile reads; its auto-PSD ``psd``, which scan, gof and sharpness read, is of the samples' law)
    is detected by the profile; the exact form's screening still points to every candidate
    (``None``), where the same observations read by the simplified form point to added mass."""
    rng = np.random.default_rng(13)
    rejected = 0
    for _ in range(200):
        d = detection_test(_observations(rng, 20, probe=10))
        assert d.statistics == MODEL_FORMS["exact"] == ("scan", "gof", "sharpness", "profile")
        rejected += d.detected
    assert 1 <= rejected <= 19, rejected
    obs = _observations(rng, 20, probe=10)
    assert detection_test(dataclasses.replace(obs, probe=None)).statistics == ("scan", "gof", "sharpness")
    rec = _observations(np.random.default_rng(5), 1, scale=0.945)
    band = _observations(np.random.default_rng(6), 79, probe=20)
    d = detection_test(rec.stacked(band))
    assert d.detected and d.p_values["profile"] == 1 / 80 and d.strongest() == "profile", d
    assert min(d.p_values[k] for k in ("scan", "gof", "sharpness")) > 0.05, d  # only the profile sees it
    assert d.pointed_effects() is None
    assert "added_mass" in detection_test(rec.stacked(band), model_form="simplified").pointed_effects()


def test_the_tilt_reads_the_band_only():
    """The tilt's slope is fitted from 2 Hz to the band: the record's fine spectra × 100 above the
    band (what stop impacts or a noise floor do there) or below 2 Hz leave its value unchanged, the
    same × (f/20 Hz)^−1 inside the band moves it by −1 decade per decade."""
    from tubeid.diagnose._detection import features

    rng = np.random.default_rng(12)
    obs = _observations(rng, 2)
    f = obs.frequency_fine
    base = features("tilt", obs)
    for outside in (f > 100.5, f < 1.9):
        moved = features("tilt", dataclasses.replace(obs, fine=obs.fine * np.where(outside, 100.0, 1.0)[None, :, None]))
        np.testing.assert_allclose(moved, base, rtol=1e-12)
    inband = (f >= 2.0) & (f <= 100.0)
    steeper = np.where(inband, (np.maximum(f, 1.0) / 20.0) ** -1.0, 1.0)
    moved = features("tilt", dataclasses.replace(obs, fine=obs.fine * steeper[None, :, None]))
    np.testing.assert_allclose(moved - base, -1.0, rtol=1e-9)


def test_the_strongest_departure_points_to_the_effect_explained_first():
    """A line and sharper resonances at once (a strong tone also sharpens the spectrum through the
    stop): both statistics fire, the line's excess is the larger, so only the tone is a candidate
    of the first step; the exact form's statistics point to every effect (None)."""
    rng = np.random.default_rng(8)
    obs = _observations(rng, 1, line=201, sharp=1.8).stacked(_observations(rng, 19))
    d = detection_test(obs, model_form="simplified")
    assert d.p_values["line"] == d.p_values["resonance"] == 0.05, d.p_values
    assert d.strongest() == "line" and d.pointed_effects() == ("tone",), d.excess
    f, P = _spectra(rng, 20, line=29)
    assert detection_test(P[0], P[1:], f).pointed_effects() is None


def test_the_floor_is_left_out_without_bins_above_the_band():
    """A record whose Nyquist frequency is the band's: the floor statistic has nothing to read and
    the simplified test combines the four others."""
    rng = np.random.default_rng(6)
    obs = _observations(rng, 20)
    obs = dataclasses.replace(obs, band_hz=165.0)
    assert detection_test(obs, model_form="simplified").statistics == ("line", "kurtosis", "resonance", "tilt")


def test_what_a_simplified_test_cannot_read_is_left_out_not_a_crash():
    """The floor needs bins above the band and at least 2 averaged segments per sensor; the
    resonance a 4·band_width chunk inside the band after the first; the tilt 8 fine bins between
    2 Hz and the band; the line fine bins. Each left
    out when its observations cannot hold it; the profile without probe realisations or with fewer
    than 8 bands of 2 Hz (a band of 17 Hz holds 8 from 2 Hz, 15.5 Hz 7). The test then combines the others. Observations
    without ``psd`` (the simplified statistics do not read it) are tested too (no display residual)."""
    rng = np.random.default_rng(9)
    obs = _observations(rng, 20, probe=10)
    assert detection_test(dataclasses.replace(obs, segments=5), model_form="simplified").statistics == (
        "line", "kurtosis", "resonance", "tilt", "profile")  # 5 segments for 3 sensors
    assert detection_test(dataclasses.replace(obs, segments=6), model_form="simplified").statistics == MODEL_FORMS["simplified"]
    assert detection_test(dataclasses.replace(obs, probe=None), model_form="simplified").statistics == (
        "line", "floor", "kurtosis", "resonance", "tilt")
    assert detection_test(obs, model_form="simplified", band_width_hz=30.0).statistics == ("line", "floor", "kurtosis",
                                                                                           "tilt", "profile")
    narrow = dataclasses.replace(obs, band_hz=4.0)  # 6 fine bins in [2, 4] Hz: no tilt, no resonance chunk, 3 bands
    assert detection_test(narrow, model_form="simplified").statistics == ("line", "floor", "kurtosis")
    short = dataclasses.replace(obs, band_hz=8.5)  # 4 bands of 2 Hz from 2 Hz: no profile; the tilt has its 8 bins
    assert "tilt" in detection_test(short, model_form="simplified").statistics
    assert "profile" not in detection_test(short, model_form="simplified").statistics
    assert "profile" not in detection_test(dataclasses.replace(obs, band_hz=15.5), model_form="simplified").statistics
    assert "profile" in detection_test(dataclasses.replace(obs, band_hz=17.0), model_form="simplified").statistics
    d = detection_test(dataclasses.replace(obs, psd=None), model_form="simplified")
    assert d.z is None and np.isfinite(d.p_value)


def test_added_mass_is_fitted_to_the_profile_only_where_the_record_holds_its_bands(monkeypatch):
    """With the simplified form the added mass is fitted to the profile's feature (its catalog
    entry's ``feature``), which needs 8 bands of 2 Hz from 2 Hz below the load's band; with a band
    of 8.5 Hz it falls back to the first robust statistic pointing to it, the tilt (the profile's
    feature would be 4 bands; below 4 Hz identically 0, and added mass never chosen). The probe
    realisations are not needed for the feature."""
    import types

    from tubeid.diagnose import stages

    obs = dataclasses.replace(_observations(np.random.default_rng(2), 3), probe=None)
    ctx = types.SimpleNamespace(settings=DiagnoseSettings())
    for band, expected in ((100.0, "profile"), (17.0, "profile"), (8.5, "tilt")):
        monkeypatch.setattr(stages, "record_observations", lambda c, w, b=band: dataclasses.replace(obs, band_hz=b))
        assert stages.feature_name(ctx, "added_mass") == expected, band
    assert stages.feature_name(ctx, "tone") == "line"


def test_the_strongest_statistic_with_a_candidate_left_points():
    """When the strongest departure's effect is chosen already (or not a candidate), the next
    statistic by excess that points to an available effect decides; none left: ()."""
    from tubeid.diagnose import Detection

    d = Detection(p_value=0.05, detected=True, false_alarm=0.05, size=0.05, p_values={}, values={}, null_median={},
                  excess={"line": 6.0, "kurtosis": 3.0, "floor": 1.0}, scan_frequency_hz=37.0, n_realisations=19,
                  model_form="simplified")
    assert d.pointed_effects() == ("tone",)
    assert d.pointed_effects(("stop", "sensor_noise")) == ("stop",)
    assert d.pointed_effects(("added_mass",)) == ()


def test_conditional_psd_is_the_schur_complement():
    """1/[S⁻¹]_ii against S_ii − S_i,r S_r,r⁻¹ S_r,i computed directly, for random Hermitian
    positive-definite 4 × 4 matrices (and S_ii for one channel)."""
    rng = np.random.default_rng(7)
    A = rng.standard_normal((5, 4, 6)) + 1j * rng.standard_normal((5, 4, 6))
    S = A @ A.conj().transpose(0, 2, 1)
    got = conditional_psd(S)
    for k in range(5):
        for i in range(4):
            r = [j for j in range(4) if j != i]
            want = S[k, i, i] - S[k, i, r] @ np.linalg.solve(S[k][np.ix_(r, r)], S[k, r, i])
            assert got[k, i] == pytest.approx(want.real, rel=1e-9, abs=0)
    assert conditional_psd(S[:, :1, :1])[:, 0] == pytest.approx(S[:, 0, 0].real, rel=1e-12, abs=0)


def test_conditional_psd_of_a_singular_matrix_is_small_and_finite():
    """A rank-one PSD matrix (fewer averaged segments than channels): each channel is explained by
    the others up to round-off, so its conditional PSD sits at the eigenvalue floor (1e-14 of the
    largest), finite and positive — not 0, not an overflow; an all-zero matrix gives zeros."""
    v = np.array([1.0, 2.0, 3.0]) * 1e-11
    lam = float(v @ v)
    r = conditional_psd(np.outer(v, v))
    assert np.all(np.isfinite(r)) and np.all(r > 0) and np.all(r <= 1e-13 * lam), r / lam
    assert np.all(conditional_psd(np.zeros((2, 3, 3))) == 0.0)


# ------------------------------------------------------------------------------- the selection


def test_the_choice_is_the_best_penalised_held_out_error_not_the_first_improvement():
    """Two candidates both improve on the current error (1.0); the second is better once penalised,
    so it is chosen: taking the first improving candidate fails here. A better raw error with more
    parameters can lose to the penalty; nothing below the current error: no choice."""
    a, b = Scored("tone", 3, 0.5, 0.70), Scored("damping", 1, 0.6, 0.72)
    assert choose([a, b], current=1.0, penalty=0.1).name == "damping"   # 0.70/0.729 = 0.960 > 0.72/0.9 = 0.8
    assert choose([a, b], current=1.0, penalty=0.0).name == "tone"
    c = Scored("stop", 2, 0.5, 0.5)
    assert choose([a, b, c], current=1.0, penalty=0.1).name == "stop"    # 0.617, the lowest
    assert choose([a, b], current=0.75, penalty=0.1) is None
    assert choose([Scored("tone", 1, 1.0, np.nan)], current=1.0, penalty=0.1) is None


def test_near_ties_are_the_runner_ups_that_paid_within_the_margin_of_the_chosen_ratio():
    """Ratios penalised / current: the chosen tone 0.793; the added mass 0.796 (0.4 % away: a near tie,
    as measured on a record with both), damping 0.892 (12 % away: not at a 10 % margin, yes at 15 %),
    sensor noise 1.055 (does not pay: never). Each candidate's ratio uses its own current error."""
    c = [{"name": "tone", "penalised": 0.793, "current": 1.0}, {"name": "added_mass", "penalised": 1.592, "current": 2.0},
         {"name": "damping", "penalised": 0.892, "current": 1.0}, {"name": "sensor_noise", "penalised": 1.055, "current": 1.0}]
    assert near_ties(c, "tone", 0.10) == {"added_mass": (pytest.approx(0.796, rel=1e-12, abs=0), 0.793)}
    assert set(near_ties(c, "tone", 0.15)) == {"added_mass", "damping"}
    assert near_ties(c, "tone", 0.0) == {} and near_ties(c, "", 0.1) == {}
    assert near_ties(c, "added_mass", 0.10) == {"tone": (0.793, pytest.approx(0.796, rel=1e-12, abs=0))}
    paid = [{"name": "tone", "penalised": 0.97, "current": 1.0}, {"name": "damping", "penalised": 1.01, "current": 1.0}]
    assert near_ties(paid, "tone", 0.10) == {}  # within 10 % but it does not pay its penalty


def test_a_near_tied_runner_up_is_offered_once_after_the_record_is_explained(monkeypatch):
    """The bookkeeping of ``stages.runner_ups`` on stand-in stages: step 1 chose the tone with the added
    mass near-tied; explained after step 1 → step 2 offers the mass alone, with the signature of step
    1's screen. After step 2 (a continuation, itself with a near tie) nothing is offered again: each tie
    is resolved once. Held effects and far runner-ups are never offered; no ties when ``tie`` = 0."""
    import types

    import xarray as xr

    from tubeid.diagnose import stages

    def band(detected, screen=None):
        ds = xr.Dataset(attrs={"detected": detected})
        if screen is not None:
            ds.attrs["screen"] = json.dumps(screen)
        return ds

    sig = {n: {"estimate": {"n": n}, "score": 1.0} for n in ("tone", "added_mass", "damping")}
    results = {"band": band(True, sig), "step1_trials": xr.Dataset(), "step1_band": band(False),
               "step2_trials": xr.Dataset(), "step2_band": band(False)}
    sel = {1: {"chosen": "tone", "candidates": [{"name": "tone", "penalised": 0.793, "current": 1.0},
                                                {"name": "added_mass", "penalised": 0.80, "current": 1.0},
                                                {"name": "damping", "penalised": 0.95, "current": 1.0}]},
           2: {"chosen": "added_mass", "candidates": [{"name": "added_mass", "penalised": 0.5, "current": 1.0},
                                                       {"name": "damping", "penalised": 0.51, "current": 1.0}]}}
    monkeypatch.setattr(stages, "selection", lambda ctx, res, j: sel[j])
    ctx = types.SimpleNamespace(settings=DiagnoseSettings())
    up = stages.runner_ups(ctx, results, 2, {"tone"})
    assert list(up) == ["added_mass"] and up["added_mass"]["signature"] == sig["added_mass"]
    assert up["added_mass"]["step"] == 1 and up["added_mass"]["chosen"] == "tone"
    assert stages.runner_ups(ctx, results, 2, {"tone", "added_mass"}) == {}
    assert stages.runner_ups(ctx, results, 3, {"tone", "added_mass"}) == {}  # step 2 was the continuation
    assert stages.runner_ups(types.SimpleNamespace(settings=DiagnoseSettings(tie=0.0)), results, 2, {"tone"}) == {}
    with pytest.raises(SpecificationError, match="settings.tie"):
        DiagnoseSettings(tie=-0.1)


def test_a_runner_up_tried_later_or_offered_once_is_not_offered_again_and_a_rejected_continuation_stops(monkeypatch):
    """More bookkeeping of the near-tie rule on stand-in stages. (a) The mass, tied with the tone at step
    1, was a candidate again at the regular step 2 (with the tone fitted) and did not pay: its tie is
    resolved, not offered after step 2. (b) A continuation offered the mass and damping, damping was
    added: the mass is not offered again. (c) A continuation whose effect makes the test detect again
    is rejected: the loop stops there and says so."""
    import types

    import xarray as xr

    from tubeid.diagnose import stages

    def band(detected, screen=None, params=None):
        ds = xr.Dataset(attrs={"detected": detected})
        if screen is not None:
            ds.attrs["screen"] = json.dumps(screen)
        if params is not None:
            ds.attrs["parameters"] = json.dumps(params)
        return ds

    sig = {n: {"estimate": {"n": n}, "score": 1.0} for n in ("tone", "added_mass", "damping")}
    tied = {"chosen": "tone", "candidates": [{"name": "tone", "penalised": 0.793, "current": 1.0},
                                             {"name": "added_mass", "penalised": 0.80, "current": 1.0},
                                             {"name": "damping", "penalised": 0.85, "current": 1.0}]}
    ctx = types.SimpleNamespace(settings=DiagnoseSettings())
    # (a) step 2 regular: the record still detected after step 1
    sel = {1: tied, 2: {"chosen": "damping", "candidates": [{"name": "added_mass", "penalised": 1.3, "current": 1.0},
                                                            {"name": "damping", "penalised": 0.6, "current": 1.0}]}}
    monkeypatch.setattr(stages, "selection", lambda c, res, j: sel[j])
    a = {"band": band(True, sig), "step1_trials": xr.Dataset(), "step1_band": band(True, sig),
         "step2_trials": xr.Dataset(), "step2_band": band(False)}
    assert stages.runner_ups(ctx, a, 3, {"tone", "damping"}) == {}
    # (b) step 2 a continuation (explained after step 1) that added damping
    b = {**a, "step1_band": band(False)}
    assert stages.runner_ups(ctx, b, 2, {"tone"}).keys() == {"added_mass", "damping"}
    sel[2] = {"chosen": "damping", "candidates": [{"name": "added_mass", "penalised": 0.95, "current": 1.0},
                                                  {"name": "damping", "penalised": 0.6, "current": 1.0}]}
    assert stages.runner_ups(ctx, b, 3, {"tone", "damping"}) == {}
    # (c) the continuation's effect made the test detect again
    effects = json.dumps([{"kind": "tone"}, {"kind": "damping"}])
    c = {**b, "step2_band": band(True, sig, {"effects": effects, "r": [1.0]})}
    assert stages.continuation_rejected(c, 2) and not stages.continuation_rejected(a, 2)
    st3 = stages.state_before(ctx, c, 3)
    assert not st3["active"] and "made the test detect again: not kept" in st3["reason"]


def test_candidates_judged_on_their_own_features_are_compared_relative_to_the_current_model():
    """With the simplified form each candidate is judged by its own feature's error against the
    current model's in that feature: a tone that halves its line error (20 → 10) beats a noise
    floor that lowers its floor error by 10 % (1.0 → 0.9) although its error is larger; a
    candidate that does not pay its penalty relative to its own current error is never chosen."""
    tone, noise = Scored("tone", 3, 9.0, 10.0, 20.0), Scored("sensor_noise", 1, 0.8, 0.9, 1.0)
    assert choose([noise, tone], current=1.0, penalty=0.05).name == "tone"
    assert choose([Scored("sensor_noise", 1, 0.8, 0.97, 1.0)], current=0.1, penalty=0.05) is None  # 0.97/0.95 > 1


def test_the_refit_keeps_the_moved_point_only_if_it_is_no_worse_than_the_best_evaluated_one():
    from tubeid.diagnose._selection import keeps_moved_point

    # measured (stop at 10 m, seed 42): r and the gap each moved to their line's end, together 3.46
    # where the evaluated point (r moved alone) had 1.89
    assert not keeps_moved_point(3.46, 1.89)
    assert keeps_moved_point(0.81, 2.50) and keeps_moved_point(1.0, 1.0)
    assert not keeps_moved_point(float("nan"), 1.0)


def test_a_line_whose_best_is_at_an_end_is_extended_one_step_and_kept_only_if_better():
    from tubeid.diagnose._selection import line_extension, refit_choice

    # measured (added mass on outer1 × 1.3, seed 1): the line 0.107 / 0.15 / 0.21 (×1.4) gave fit errors
    # 1.57 / 1.24 / 0.84: the next step is 0.21 × 1.4 = 0.294
    assert line_extension([0.15, 0.107, 0.21], [1.24, 1.57, 0.84]) == pytest.approx(0.21 * 1.4, rel=1e-3, abs=0)
    assert line_extension([0.5, 1.0, 2.0], [0.2, 0.5, 0.9]) == pytest.approx(0.25, rel=1e-12, abs=0)
    assert line_extension([0.5, 1.0, 2.0], [0.9, 0.5, 0.7]) is None  # interior
    assert line_extension([0.5, 1.0, 2.0], [0.9, 0.5, float("nan")]) is None
    # a damping ratio moved by its line or extension stops at 0.9, as its scan does (1 is no damping ratio)
    assert CATALOG["damping"].combine(Damping("outer1", 0.7), {"ratio": 0.7 * 1.4 ** 2}, None).ratio == 0.9
    assert refit_choice(0.84, 0.84, 0.61) == "extended"
    assert refit_choice(0.84, 0.84, 0.90) == "moved" and refit_choice(0.84, 0.84) == "moved"
    assert refit_choice(3.46, 1.89, 1.95) == "best" and refit_choice(3.46, 1.89, 1.5) == "extended"
    assert refit_choice(0.8, 1.0, float("nan")) == "moved"
    assert refit_choice(0.5, 1.0, 0.7) == "moved" and refit_choice(0.5, 1.0, 0.5) == "moved"  # not better than moved
    assert refit_choice(0.5, float("nan"), 0.4) == "extended" and refit_choice(0.5, float("nan")) == "moved"


def test_the_refit_extends_its_edge_lines_and_the_check_decides(monkeypatch):
    """The stages' wiring with fitting errors given by hand (no simulation): an added mass's line
    0.107 / 0.15 / 0.21 with its best at the end and r's line with an interior best; the check's two
    trials are the moved point (mass 0.21) and the extended one (mass 0.294, r the same); the
    extended point is kept only when its error is the lowest, and a NaN trial never wins."""
    from types import SimpleNamespace

    import xarray as xr

    from tubeid.diagnose import stages
    from tubeid.mechanics.effects import effect_from_dict, effect_to_dict

    mass = AddedMass("outer1", 0.15)
    trials = [{"effects": [effect_to_dict(mass)], "r": [1.3]}]
    lines = []
    for what, par, values in (("r", "r", [1.3 * 10**-0.1, 1.3, 1.3 * 10**0.1]), ("effect", "factor", [0.15 / 1.4, 0.15, 0.21])):
        idx = []
        for v in values:
            if v in (1.3, 0.15):
                idx.append(0)
                continue
            trials.append({"effects": [effect_to_dict(AddedMass("outer1", v) if what == "effect" else mass)],
                           "r": [v if what == "r" else 1.3]})
            idx.append(len(trials) - 1)
        lines.append({"what": what, "index": 0, "parameter": par, "log": True, "values": values, "trials": idx})
    refit = xr.Dataset(attrs={"parameters": json.dumps({"trials": json.dumps(trials), "lines": json.dumps(lines)}),
                              "name": "refit"})
    errors = {"refit": [1.24, 1.40, 1.30, 1.57, 0.84], "check": [0.80, 0.61]}
    monkeypatch.setattr(stages, "fit_errors", lambda ctx, results, ds: errors[ds.attrs["name"]])
    monkeypatch.setattr(stages, "_surrogate", lambda *a: None)
    ctx = SimpleNamespace(spec=None)
    results = {"step1_refit": refit, "step1_check": xr.Dataset(attrs={"name": "check"})}
    rf = stages.refit_result(ctx, results, 1)
    moved, ext = json.loads(rf["effects"]), json.loads(rf["extended"]["effects"])
    assert effect_from_dict(moved[0]).factor == pytest.approx(0.21, rel=1e-12, abs=0)
    assert effect_from_dict(ext[0]).factor == pytest.approx(0.294, rel=1e-12, abs=0)
    assert rf["r"] == rf["extended"]["r"] and 1.3 < rf["r"][0] < 1.3 * 10**0.1  # r's best is interior: not extended
    assert [ln["extension"] is None for ln in rf["lines"]] == [True, False]
    pt = stages.refit_point(ctx, results, 1, rf)
    assert pt["point"] == "extended" and pt["effects"] == rf["extended"]["effects"] and pt["extended_fit_error"] == 0.61
    errors["check"] = [0.80, 0.90]
    pt = stages.refit_point(ctx, results, 1, rf)
    assert pt["point"] == "moved" and pt["effects"] == rf["effects"]
    errors["check"] = [0.90, 0.86]  # both worse than the best trial (0.84, the line's end)
    pt = stages.refit_point(ctx, results, 1, rf)
    assert pt["point"] == "best" and pt["fallback"] and effect_from_dict(json.loads(pt["effects"])[0]).factor == 0.21
    errors["refit"] = [1.24, float("nan"), 1.30, 1.57, 0.84]  # a failed trial of r's line: never the best
    rf = stages.refit_result(ctx, results, 1)
    assert rf["best_trial"]["fit_error"] == 0.84


def test_a_second_refit_sweep_runs_where_the_first_did_not_bracket_and_ends_the_step(monkeypatch):
    """Fitting errors by hand (no simulation): r's line with its best at an end calls for a second
    sweep (a stop's gap and r trade off: lines evaluated one at a time mis-place both); lines that
    all bracket their minimum, with the moved point kept, do not; a kept point other than the moved
    one does. The second sweep is centred at the point the first kept, draws the first sweep's
    streams, and its own kept point is where the step's band is computed."""
    from types import SimpleNamespace

    import xarray as xr

    from tubeid.diagnose import stages
    from tubeid.mechanics.effects import effect_from_dict, effect_to_dict

    stop = ExtraStop("centre", 10.0, 2.32e-6, 1e8)
    trials = [{"effects": [effect_to_dict(stop)], "r": [1.408]},
              {"effects": [effect_to_dict(stop)], "r": [1.408 * 10**-0.1]},
              {"effects": [effect_to_dict(stop)], "r": [1.408 * 10**0.1]},
              {"effects": [effect_to_dict(ExtraStop("centre", 10.0, 1.16e-6, 1e8))], "r": [1.408]},
              {"effects": [effect_to_dict(ExtraStop("centre", 10.0, 4.64e-6, 1e8))], "r": [1.408]}]
    lines = [{"what": "r", "index": 0, "parameter": "r1", "log": True, "values": [1.408 * 10**-0.1, 1.408, 1.408 * 10**0.1],
              "trials": [1, 0, 2]},
             {"what": "effect", "index": 0, "parameter": "gap", "log": True, "values": [1.16e-6, 2.32e-6, 4.64e-6],
              "trials": [3, 0, 4]}]
    refit = xr.Dataset(attrs={"parameters": json.dumps({"trials": json.dumps(trials), "lines": json.dumps(lines)}),
                              "name": "refit"})
    errors = {"refit": [2.42, 1.49, 4.60, 14.1, 3.20], "check": [0.55, 2.36]}  # the seed-6 stop record's numbers
    monkeypatch.setattr(stages, "fit_errors", lambda ctx, results, ds: errors[ds.attrs["name"]])
    monkeypatch.setattr(stages, "_surrogate", lambda *a: None)
    ctx = SimpleNamespace(spec=None)
    results = {"step1_refit": refit, "step1_check": xr.Dataset(attrs={"name": "check"})}
    assert "r1" in stages.sweep_reason(ctx, results, 1, 1) and "gap" not in stages.sweep_reason(ctx, results, 1, 1)
    errors["refit"] = [2.42, 2.60, 4.60, 14.1, 3.20]  # both lines bracket, the moved point is kept: no second sweep
    assert stages.sweep_reason(ctx, results, 1, 1) == ""
    errors["check"] = [2.50]  # the moved point worse than the centre: the best evaluated point is kept
    assert "best point was kept" in stages.sweep_reason(ctx, results, 1, 1)
    errors["refit"], errors["check"] = [2.42, 1.49, 4.60, 14.1, 3.20], [0.55, 2.36]
    kept = stages.refit_point(ctx, results, 1)
    assert kept["point"] == "moved"
    # the second sweep's stage: centred at that point, the first sweep's streams
    base = {"data": "", "data_sha256": "", "model": "", "settings": ""}
    monkeypatch.setattr(stages, "_ctx", lambda p: SimpleNamespace(spec=builtin_spec("paper-reference"),
                                                                  settings=DiagnoseSettings(), meas=None))

    @dataclasses.dataclass(frozen=True)
    class Stage:  # what _refit reads of the trial study it makes
        name: str
        trials: list
        parameters: dict
        stream_key: tuple

    monkeypatch.setattr(stages, "_trial_study", lambda name, base, ctx, trials, what: Stage(name, trials, {}, (name,)))
    results["step1_trials"] = xr.Dataset()
    st = stages._builder("refit2")(1, results, base)
    centre = st.trials[0]
    assert centre["r"] == json.loads(json.dumps(kept["r"])) and centre["effects"] == json.loads(kept["effects"])
    assert st.stream_key == ("step1_refit",) and st.name == "step1_refit2"
    gap = effect_from_dict(centre["effects"][0]).gap
    assert gap == pytest.approx(stages.line_minimum([1.16e-6, 2.32e-6, 4.64e-6], [14.1, 2.42, 3.20], True), rel=1e-12, abs=0)
    # where the first sweep kept its best evaluated point (the moved one worse), the second starts there
    errors["check"] = [2.50, 2.36]
    assert stages.refit_point(ctx, results, 1)["point"] == "best"
    centre = stages._builder("refit2")(1, results, base).trials[0]
    assert centre["r"] == [1.408 * 10**-0.1] and effect_from_dict(centre["effects"][0]).gap == 2.32e-6
    # the step's band is computed at the last sweep's kept point
    results["step1_refit2"] = xr.Dataset(attrs={"name": "refit"})
    monkeypatch.setattr(stages, "refit_point", lambda ctx, results, k, rf=None, sweep=1: {"sweep": sweep})
    assert stages.final_point(ctx, results, 1) == {"sweep": 2}
    results["step1_refit2"] = xr.Dataset(coords={"skipped": ["sweep 1 bracketed every parameter"]})
    assert stages.final_point(ctx, results, 1) == {"sweep": 1}


def test_a_tones_amplitude_is_refitted_along_its_profile_not_by_simulated_trials(monkeypatch):
    """The joint re-fit's amplitude line of a tone is derived from the centre trial and one baseline
    trial (the same model without the tone): the record's line has 4 × the centre's power, so the
    line's best is 2 × the centre's amplitude (the profile's grid is 10^0.05 apart; the parabola's
    vertex is within 1 %), reported in increasing order; the baseline is never the best trial; the
    other lines (r, the tone's x) stay simulated."""
    from types import SimpleNamespace

    import xarray as xr

    from tubeid.diagnose import stages
    from tubeid.mechanics.effects import effect_from_dict, effect_to_dict

    f = np.arange(0.0, 50.5, 0.5)
    floor = np.full((f.size, 2), 1e-14) * np.array([1.0, 2.0])
    shape = np.where(np.abs(f - 20.0) <= 1.0, np.exp(-((f - 20.0) / 0.5) ** 2), 0.0)[:, None] * np.array([3e-13, 1e-13])
    tone = Tone(20.0, 50.0, "centre", 5.0)
    record = floor + 4.0 * shape
    trials = [{"effects": [effect_to_dict(tone)], "r": [1.3]},
              {"effects": [effect_to_dict(tone)], "r": [1.3 * 10**-0.1]},
              {"effects": [effect_to_dict(tone)], "r": [1.3 * 10**0.1]},
              {"effects": [], "r": [1.3], "baseline": 0},
              {"effects": [effect_to_dict(Tone(20.0, 50.0, "centre", 4.0))], "r": [1.3]},
              {"effects": [effect_to_dict(Tone(20.0, 50.0, "centre", 6.0))], "r": [1.3]}]
    psds = np.stack([floor + shape, 1.1 * floor + shape, 0.9 * floor + shape, floor, floor + 0.5 * shape, floor + 0.2 * shape])
    lines = [{"what": "r", "index": 0, "parameter": "r1", "log": True, "values": [1.3 * 10**-0.1, 1.3, 1.3 * 10**0.1],
              "trials": [1, 0, 2]},
             {"what": "effect", "index": 0, "parameter": "amplitude", "log": True, "baseline": 3},
             {"what": "effect", "index": 0, "parameter": "x", "log": False, "values": [4.0, 5.0, 6.0], "trials": [4, 0, 5]}]
    refit = xr.Dataset(attrs={"parameters": json.dumps({"trials": json.dumps(trials), "lines": json.dumps(lines)})})
    sigma = np.full(floor.shape, 0.1)
    ctx = SimpleNamespace(spec=None, meas=SimpleNamespace(frequency=f, fit=record), settings=SimpleNamespace(form="exact"))
    monkeypatch.setattr(stages, "_trial_psds", lambda ds, trials: psds)
    monkeypatch.setattr(stages, "_sigma", lambda results: sigma)
    monkeypatch.setattr(stages, "fit_errors", lambda ctx, results, ds: [prediction_error(record, q, sigma, f) for q in psds])
    monkeypatch.setattr(stages, "_surrogate", lambda *a: None)
    rf = stages.refit_result(ctx, {"step1_refit": refit}, 1)
    amp = next(ln for ln in rf["lines"] if ln["parameter"] == "amplitude")
    assert len(amp["values"]) == 21 and amp["values"] == sorted(amp["values"]) and amp["extension"] is None
    assert amp["best"] == pytest.approx(100.0, rel=0.01, abs=0)
    assert effect_from_dict(json.loads(rf["effects"])[0]).amplitude == amp["best"]  # no surrogate: no compensation
    best = json.loads(rf["best_trial"]["effects"])
    assert best and effect_from_dict(best[0]).amplitude == pytest.approx(100.0, rel=0.01, abs=0)
    assert rf["best_trial"]["fit_error"] == min(amp["errors"])  # a derived point; never the baseline (no tone)
    # a record without the line: the baseline (the model without the tone) fits it exactly, yet it is no
    # point of the re-fit (the step's effect would be dropped): the best point keeps the tone
    ctx.meas.fit = floor
    monkeypatch.setattr(stages, "fit_errors", lambda ctx, results, ds: [prediction_error(floor, q, sigma, f) for q in psds])
    rf = stages.refit_result(ctx, {"step1_refit": refit}, 1)
    assert json.loads(rf["best_trial"]["effects"]) and rf["best_trial"]["fit_error"] > 0


def test_line_minimum_is_the_parabola_vertex_in_log_and_keeps_an_end():
    x = np.array([0.5, 1.0, 2.0])
    y = (np.log10(x) - np.log10(1.3)) ** 2
    assert line_minimum(x, y, log=True) == pytest.approx(1.3, rel=1e-12, abs=0)
    assert line_minimum([4.0, 5.0, 6.0], [(v - 5.4) ** 2 for v in (4.0, 5.0, 6.0)], log=False) == pytest.approx(5.4, rel=1e-12, abs=0)
    assert line_minimum(x, [0.0, 1.0, 2.0], log=True) == 0.5


def test_prediction_error_is_the_mean_squared_standardised_log_residual():
    f = np.arange(6.0)
    meas = np.full((6, 1), 1e-14)
    model = meas * 10.0 ** np.array([0, 0.1, -0.2, 0.0, 0.3, 5.0])[:, None]
    sigma = np.full((6, 1), 0.1)
    # bins 1..4 only: z = -1, 2, 0, -3 -> mean z² = 14/4
    assert prediction_error(meas, model, sigma, f) == pytest.approx(3.5, rel=1e-12, abs=0)


# -------------------------------------------------------------------------- surrogate, catalog


def _direct_pattern(spec, f0, tube, x):
    """|u_sensors|² per unit force at (tube, x), f0 [Hz]: the full FE model solved directly, stops open."""
    fe = assemble(spec)
    w = 2 * np.pi * f0
    u = scipy.linalg.solve(fe.K - w**2 * fe.M + 1j * w * fe.D, fe.load_matrix((LoadPoint("t", tube, x),)))
    return np.abs(fe.sensor_matrix() @ u).ravel() ** 2


def test_surrogate_transfer_matches_direct_solves():
    """Stops open (c = 0). (1) The modal first-order form against a direct solve of the same reduced
    matrices: 1e-8 relative (algebra). (2) Against the full FE model (no reduction) solved
    directly: a force on the centre tube (subsystem A, every mode kept) within 1e-4; a force on
    outer1 (inside B, whose fixed-interface modes above 300 Hz are dropped) within 2 %, the size of
    that truncation at 37 Hz ((37/300)² ≈ 1.5 %)."""
    from tubeid.mechanics import reduce

    spec = builtin_spec("paper-reference").replace(sensors=sensors((2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0)))
    sur = LinearSurrogate(spec, coherent_forces(), np.arange(334) / 2.0)
    sur.contact = 0.0
    m = reduce(spec)
    M, D, K = m.mean_matrices
    w = 2 * np.pi * 37.0
    for (tube, x), rtol in ((("centre", 5.0), 1e-4), (("outer1", 9.0), 2e-2)):
        pattern = sur.tone_pattern(37.0, [(tube, x)])[0]
        q = np.linalg.solve(K - w**2 * M + 1j * w * D, m.load_matrix((LoadPoint("t", tube, x),)))
        np.testing.assert_allclose(pattern, np.abs(m.sensor_matrix() @ q).ravel() ** 2, rtol=1e-8)
        np.testing.assert_allclose(pattern, _direct_pattern(spec, 37.0, tube, x), rtol=rtol)


def _evidence(spec, fit, mu, sigma=0.05):
    f = np.arange(fit.shape[0]) / 2.0
    sur = LinearSurrogate(spec, coherent_forces(), f)
    sur.contact = 0.0
    return Evidence(frequency=f, fit=fit, mu=mu, sigma=np.full(mu.shape, sigma), z_stats=np.zeros((mu.shape[1], 3)),
                    rms=np.full(mu.shape[1], 2e-6), spec=spec, surrogate=sur, band_hz=100.0)


def test_tone_signature_finds_frequency_position_and_amplitude_of_a_line_computed_directly():
    """The record's fitting PSD = a smooth band + a line of a 30 N force at (outer3, 9 m), 37 Hz,
    computed by the full FE model solved directly (|H|² A²/4 over one bin of 0.5 Hz): the signature
    names 37 Hz, outer1 (the four outer tubes are identical and seen alike from the centre tube's
    sensors: the first in the model's order, as report.md says), x within half an element of 9 m,
    and the amplitude within 10 %."""
    spec = builtin_spec("paper-reference").replace(sensors=sensors(XS)).replace(stops=())
    F = 334
    mu = np.full((F, 3), -14.0)
    fit = 10.0**mu
    k = 74  # 37 Hz
    fit[k] += _direct_pattern(spec, 37.0, "outer3", 9.0) * 30.0**2 / 4 / 0.5
    est = CATALOG["tone"].signature(_evidence(spec, fit, mu))["estimate"]
    assert est["frequency_hz"] == pytest.approx(37.0, abs=0.05)
    assert est["tube"] == "outer1" and abs(est["x"] - 9.0) <= 1.0, est
    assert est["amplitude"] == pytest.approx(30.0, rel=0.1, abs=0)
    assert [q[0] for q in est["positions"]].count("outer1") >= 1 and not {"outer2", "outer3", "outer4"} & {
        q[0] for q in est["positions"]}, est["positions"]


@pytest.mark.parametrize("name, effect", [("added_mass", lambda t: AddedMass(t, 0.3)), ("damping", lambda t: Damping(t, 0.005))])
def test_alike_tubes_are_reported_as_the_first_in_the_models_order(name, effect):
    """The record's fitting PSD = the surrogate's with the effect on outer3 or outer4: the four outer
    tubes, identical and tied alike to the centre tube, score alike to round-off (1e-13), so the
    signature names outer1, the first of them in the model's order (as report.md says), and its
    runner-up is the centre tube, not another twin."""
    spec = builtin_spec("paper-reference").replace(sensors=sensors(XS)).replace(stops=())
    f = np.arange(241) / 2.0
    sur = LinearSurrogate(spec, coherent_forces(), f)
    sur.contact = 0.0
    base = sur.psd()
    for tube in ("outer3", "outer4"):
        ev = _evidence(spec, sur.psd([effect(tube)]), np.log10(np.maximum(base, 1e-300)))
        est = CATALOG[name].signature(ev)["estimate"]
        assert est["tube"] == "outer1" and est["second"]["tube"] == "centre", est


def test_noise_signature_and_exact_trials():
    spec = builtin_spec("paper-reference").replace(sensors=sensors(XS))
    F = 334
    mu = np.log10(1e-14 * np.exp(-np.arange(F) / 30.0))[:, None] * np.ones(3)
    fit = 10.0**mu + 3e-18
    est = CATALOG["sensor_noise"].signature(_evidence(spec, fit, mu))["estimate"]
    assert 3e-18 / 1.6 <= est["level"] <= 3e-18 * 1.6  # the scan's step is 10^0.2 = 1.58
    e = SensorNoise(level=2e-18)
    np.testing.assert_array_equal(CATALOG["sensor_noise"].from_baseline(e, fit), fit + 2e-18)
    np.testing.assert_allclose(CATALOG["sensor_noise"].from_baseline(e, fit + 2e-18, remove=True), fit, rtol=1e-12)


def test_a_stop_is_placed_by_the_sensor_whose_kurtosis_departs_most():
    """A record whose spectrum matches the model but whose kurtosis at the sensor at 10 m lies 5 band
    standard deviations below the model's: the stop's trials sit at the node of that sensor and its
    neighbours (8, 10, 12 m), whatever the surrogate's spring fit of a flat residual says; with a
    departure below 3 standard deviations the exact form keeps the surrogate's placement, the
    simplified one the kurtosis's."""
    spec = builtin_spec("paper-reference").replace(sensors=sensors(XS))
    mu = np.log10(1e-14 * np.exp(-np.arange(334) / 30.0))[:, None] * np.ones(3)
    ev = _evidence(spec, 10.0**mu, mu)
    ev.z_stats[2, 2] = -5.0
    est = CATALOG["stop"].signature(ev)["estimate"]
    assert est["x"] == 10.0
    assert sorted({t.x for t in CATALOG["stop"].trials(est, spec, 3)}) == [8.0, 10.0, 12.0]
    weak = _evidence(spec, 10.0**mu, mu)
    weak.z_stats[2, 2] = -2.0
    assert CATALOG["stop"].signature(dataclasses.replace(weak, form="simplified"))["estimate"]["x"] == 10.0
    surrogate_x = CATALOG["stop"].signature(_evidence(spec, 10.0**mu, mu))["estimate"]["x"]
    assert surrogate_x != 10.0 and CATALOG["stop"].signature(weak)["estimate"]["x"] == surrogate_x
    # sensors on another tube only: their kurtosis says nothing of where on the stop's tube
    other = builtin_spec("paper-reference").replace(sensors=sensors((3.0, 10.0, 14.0), tube="outer1"))
    ev = _evidence(other, 10.0**mu, mu)
    ev.z_stats[2, 2] = -9.0
    est = CATALOG["stop"].signature(dataclasses.replace(ev, form="simplified"))["estimate"]
    assert est["tube"] == "centre" and est["x"] == CATALOG["stop"].signature(_evidence(other, 10.0**mu, mu))["estimate"]["x"]


def test_tone_variants_scale_the_line_power_with_the_amplitude_squared():
    """Derived tone trials: within ±2 bins of f0 the excess over the baseline × k² (power ∝ A²),
    the rest of the spectrum as simulated."""
    f = np.arange(100) / 2.0
    base = np.full((100, 2), 1e-15)
    psd = base * (1 + 0.1 * np.random.default_rng(0).random((100, 2)))
    psd[58:61] += 4e-14                                  # the line around 29.5 Hz
    tone = Tone(29.5, 10.0, "centre", 5.0)
    for e, q in CATALOG["tone"].variants(tone, psd, base, f):
        k = e.amplitude / 10.0
        win = np.abs(f - 29.5) <= 1.0
        np.testing.assert_allclose(q[win], psd[win] + (k * k - 1) * (psd - base)[win], rtol=1e-12)
        np.testing.assert_array_equal(q[~win], psd[~win])
    amps = sorted(e.amplitude for e, _ in CATALOG["tone"].variants(tone, psd, base, f))
    assert amps[0] == pytest.approx(10 * 10**-0.5, rel=1e-12, abs=0) and len(amps) == 20


def test_catalog_entries_declare_parameters_grids_and_refinement_lines():
    spec = builtin_spec("paper-reference").replace(sensors=sensors(XS))
    counts = {n: c.n_parameters(spec) for n, c in CATALOG.items()}
    assert counts == {"tone": 3, "stop": 2, "added_mass": 2, "damping": 2, "sensor_noise": 1}
    one_tube = spec.replace(tubes=spec.tubes[:1], links=())
    assert CATALOG["damping"].n_parameters(one_tube) == 1
    grid = CATALOG["stop"].trials({"tube": "centre", "x": 9.0, "rms_nearest": 2e-6}, spec, 4)
    assert sorted({e.x for e in grid}) == [6.0, 8.0, 10.0] and len(grid) == 12  # nodes around the estimate × gaps
    assert all(isinstance(e, ExtraStop) and e.stiffness == 1e8 for e in grid)
    # damping: the surrogate's tube and direction, not its size (it gave 0.2 for a true 0.06 = 3 × the declared 0.02)
    more = CATALOG["damping"].trials({"tube": "centre", "ratio": 0.2, "second": {"tube": "outer4", "ratio": 0.002}}, spec, 4)
    centre = [e.ratio for e in more if e.tube == "centre"]
    assert len(more) == 8 and all(r > 0.02 for r in centre) and min(centre) < 0.06 < max(centre)  # a grid step: × 2.25
    assert all(e.ratio < 0.02 for e in more if e.tube == "outer4")
    less = [e.ratio for e in CATALOG["damping"].trials({"tube": "centre", "ratio": 0.002}, spec, 4)]
    assert all(r < 0.02 for r in less) and min(less) < 0.008 < max(less)  # 0.4 × declared
    tone = Tone(37.0, 20.0, "centre", 5.0)
    lines = CATALOG["tone"].refine(tone, spec)
    assert set(lines) == {"x"} and lines["x"][0] == [4.0, 5.0, 6.0] and lines["x"][2][1] == tone
    assert CATALOG["tone"].profiled == "amplitude"  # its line is the profile, derived (test of the wiring below)
    for name in CATALOG:
        assert CATALOG[name].assumptions(spec), name


def test_effects_are_validated():
    for make, field in ((lambda: ExtraStop("centre", 5.0, -1e-6, 1e8), "stop.gap"),
                        (lambda: ExtraStop("centre", 5.0, 1e-6, 0.0), "stop.stiffness"),
                        (lambda: Tone(37.0, 1.0, "centre", "5"), "tone.x"),
                        (lambda: Damping("centre", 1.0), "damping.ratio"),
                        (lambda: AddedMass("", 0.3), "added_mass.tube")):
        with pytest.raises(SpecificationError, match=field):
            make()


# -------------------------------------------------------------------------------- spectra, input


def test_measured_spectra_of_white_noise_match_the_two_sided_level():
    """White noise of variance σ² sampled at dt has two-sided PSD σ² dt. 4 blocks of 100 s, 2 s
    segments: each half averages ~200 segments × 332 bins; the mean over bins has a relative
    standard error < 0.5 %; tolerance 3 %."""
    dt, sigma = 3e-3, 2e-6
    n = int(400 / dt)
    y = sigma * np.random.default_rng(5).standard_normal((n, 2))
    raw = validate_measurements(_raw(y, dt, ["a", "b"], [2.0, 6.0]))
    m = measured_spectra(raw, 4, 2.0)
    for P in (m.fit, m.held_out):
        np.testing.assert_allclose(P[1:-1].mean(axis=0), sigma**2 * dt, rtol=0.03)
    assert m.n_fit_blocks == m.n_held_out_blocks == 2
    np.testing.assert_allclose(m.stats[:, 0], sigma, rtol=0.02)


def _raw(y, dt, names, xs):
    import xarray as xr

    return xr.Dataset({"displacement": (("time", "sensor"), y, {"units": "m"})},
                      coords={"time": np.arange(y.shape[0]) * dt, "sensor": names, "x": ("sensor", xs),
                              "tube": ("sensor", ["centre"] * len(names))})


def test_block_psds_are_the_same_bits_with_and_without_the_cross_spectra():
    """The records' auto-PSDs come from the PSD matrix where the conditional PSD needs it and from the
    auto-PSDs alone elsewhere (simulated trials): the same bits for any number of blocks (a complex
    mean over 3, 5 or 6 blocks was 1 ulp off the real one)."""
    from tubeid.diagnose._spectra import block_observations

    rng = np.random.default_rng(3)
    for nb in (2, 3, 5, 6):
        x = rng.standard_normal((2, nb, 4000, 5)) * 1e-6
        full = block_observations(x, 3e-3, 2.0, 4.0, residual=True)
        np.testing.assert_array_equal(full["psd"], block_observations(x, 3e-3, 2.0, 4.0, residual=False)["psd"])
        np.testing.assert_array_equal(full["psd"], block_observations(x, 3e-3, 2.0, None)["psd"])


def test_time_statistics_match_scipy():
    y = np.random.default_rng(2).gamma(2.0, size=(5000, 2))
    st = time_statistics(y)
    np.testing.assert_allclose(st[:, 0], y.std(axis=0), rtol=1e-12)
    np.testing.assert_allclose(st[:, 1], scipy.stats.skew(y, axis=0), rtol=1e-10)
    np.testing.assert_allclose(st[:, 2], scipy.stats.kurtosis(y, axis=0), rtol=1e-10)


def test_bad_input_is_refused(tmp_path, capsys):
    with pytest.raises(SpecificationError, match="settings.blocks"):
        DiagnoseSettings(blocks=1)
    with pytest.raises(SpecificationError, match="settings.load"):
        DiagnoseSettings(load="wind")
    with pytest.raises(SpecificationError, match="settings.r0"):
        DiagnoseSettings(r0=(1.0, 2.0))
    with pytest.raises(SpecificationError, match="settings.candidates"):
        DiagnoseSettings(candidates=("tone", "gremlin"))
    with pytest.raises(SpecificationError, match="settings.max_effects"):
        DiagnoseSettings(max_effects=4)
    with pytest.raises(SpecificationError, match="settings.delta_reference"):
        DiagnoseSettings(delta_reference="")
    with pytest.raises(SpecificationError, match="settings.probe_realisations"):
        DiagnoseSettings(probe_realisations=-1)
    data = record(duration=6.0)
    with pytest.raises(SpecificationError, match="too short"):
        diagnose(data, "paper-reference", SMALL)
    bad = data.assign_coords(tube=("sensor", ["centre", "centre", "nowhere"]))
    with pytest.raises(SpecificationError, match="unknown tube"):
        diagnose(bad, "paper-reference", SMALL)
    data = record(duration=16.0)
    with pytest.raises(SpecificationError, match="settings.load_dispersion"):  # SG+ of size m = 7: δ_max = 0.816
        diagnose(data, "paper-reference", DiagnoseSettings(load_dispersion=0.9))
    with pytest.raises(SpecificationError, match="settings.delta"):  # reduced B of the reference: δ_max = 0.953
        diagnose(data, "paper-reference", DiagnoseSettings(delta=0.97))
    with pytest.raises(SpecificationError):
        diagnose(data, "paper-reference", DiagnoseSettings(delta_reference="no-such-model"))
    assert main(["diagnose", "nowhere.nc", "--set", "nonsense=1"]) == 2  # refused before reading anything
    assert "--set nonsense" in capsys.readouterr().err


@pytest.mark.parametrize("tube", [0, 1])
def test_a_declared_model_with_an_undamped_tube_is_refused_before_any_run(tmp_path, capsys, tube):
    """A declared tube at damping ratio 0 ran four stages and then ended in numpy's traceback
    ('Geometric sequence cannot include zero': the damping candidate's trials scale the declared ratio);
    with B undamped, J is infinite. Refused before anything is written, naming the tube's field."""
    import yaml

    d = spec_to_dict(builtin_spec("paper-simplified"))
    d["tubes"][tube]["damping_ratio"] = 0.0
    spec = tmp_path / "undamped.yaml"
    spec.write_text(yaml.safe_dump(d))
    name = d["tubes"][tube]["name"]
    rule = rf"^model\.tubes\[{tube}\]\.damping_ratio = 0\.0: tube '{name}' is declared undamped: a diagnosis needs"
    with pytest.raises(SpecificationError, match=rule):
        diagnose(record(duration=16.0), str(spec), SMALL)
    assert main(["diagnose", str(tmp_path / "none.nc"), "--model", str(spec), "--out", str(tmp_path / "o")]) == 2
    assert "Traceback" not in capsys.readouterr().err and not (tmp_path / "o").exists()


@pytest.mark.parametrize("x, end", [(0.0, "clamped end x = 0.0 m"), (16.0, "clamped end x = 16.0 m")])
def test_a_record_with_a_sensor_at_a_clamped_end_is_refused_before_any_run(tmp_path, capsys, x, end):
    """Its model displacement is zero: the diagnosis failed deep in its pipeline ('loads = non-finite
    samples ... r1 = 1e95'). Refused before any run, naming the sensor, its x, the tube and the rule."""
    dt = 3e-3
    y = 1e-6 * np.random.default_rng(5).standard_normal((int(16.0 / dt), 3))
    data = xr.Dataset({"displacement": (("time", "sensor"), y, {"units": "m"})},
                      coords={"time": np.arange(y.shape[0]) * dt, "sensor": ["c02", "end", "c10"],
                              "x": ("sensor", [2.0, x, 10.0]), "tube": ("sensor", ["centre"] * 3)})
    rule = f"data: sensor 'end': x = {x!r}: in model 'paper-simplified': sensor 'end' is at the {end} of tube 'centre'"
    with pytest.raises(SpecificationError) as exc:
        diagnose(data, "paper-simplified", SMALL, out=tmp_path / "out")
    assert str(exc.value).startswith(rule) and "identically zero" in str(exc.value)
    assert not (tmp_path / "out").exists()  # refused before any work
    path = tmp_path / "end.nc"
    data.to_netcdf(path, engine="h5netcdf")
    assert main(["diagnose", str(path), "--out", str(tmp_path / "cli"), "--workers", "0"]) == 2
    err = capsys.readouterr().err
    assert rule in err and "Traceback" not in err


def test_the_simplified_form_refuses_what_it_cannot_do(monkeypatch):
    """A fine segment shorter than the test's, and candidates none of which a simplified model's
    statistics point to, are refused by name before any computation."""
    with pytest.raises(SpecificationError, match="settings.fine_segment_seconds"):
        DiagnoseSettings(fine_segment_seconds=1.0)
    data = record(duration=24.0)
    from tubeid.diagnose import _detection

    # every catalog effect has a robust statistic now: the guard is tested with added mass's pointers removed
    for name in ("tilt", "profile"):
        monkeypatch.setitem(_detection.STATISTICS, name, dataclasses.replace(_detection.STATISTICS[name], effects=()))
    with pytest.raises(SpecificationError, match="settings.candidates"):
        diagnose(data, "paper-simplified", SIMPLIFIED.replace(candidates=("added_mass",)))


def test_a_record_sampled_at_twice_the_band_is_diagnosed_without_the_floor():
    """Sampled at 200 Hz (Nyquist = the 100 Hz band: no bins above it), a tone record against
    ``paper-simplified`` in the simplified form: the floor is left out of the test and of the
    signatures (it used to crash the noise signature), the tone is named."""
    data = make_record(effects=HandEffects(tones=(("centre", 4.6, 29.0, 100.0),)), xs=SEVEN, duration=48.0, seed=11,
                       dt=0.005)
    rep = diagnose(data, "paper-simplified", SIMPLIFIED).report
    assert "floor" not in rep["detection"]["p_values"] and rep["detection"]["detected"]
    assert [e["name"] for e in rep["effects"]] == ["tone"], rep["steps"]
    assert any("sensor_noise" in a for a in rep["assumptions"] if a.startswith("model form"))


def test_context_reads_the_record_and_refuses_a_changed_one(tmp_path):
    data = record(duration=12.0)
    path = write_measurements(data, tmp_path / "d.nc")
    h = data_hash(data)
    assert data_hash(read_measurements(path)) == h  # the hash survives a NetCDF round trip
    model = json.dumps(spec_to_dict(builtin_spec("paper-reference")), sort_keys=True)
    settings = DiagnoseSettings(blocks=2).to_json()
    ctx = load_context(str(path), h, model, settings)
    assert ctx.m == 7 and ctx.j_s_observed.shape == (1,) and not ctx.identify_delta_f
    write_measurements(record(duration=12.0, seed=12), path)
    with pytest.raises(SpecificationError, match="content changed"):
        load_context(str(path), h, model, settings.replace('"blocks": 2', '"blocks": 2 '))  # not cached: read again


# ------------------------------------------------------------------------------- the loop


def _cli(*args):
    """``tubeid ARGS`` in a new process: its stdout."""
    res = subprocess.run([sys.executable, "-m", "tubeid", *map(str, args)], capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    return res.stdout


def _set_args(settings: dict) -> list[str]:
    return [a for k, v in settings.items() for a in ("--set", f"{k}={v!r}")]


CONTROL_SET = {"realisations": 19, "delta": 0.0, "fit_realisations": 1, "r0": (4.0,), "r_fine_points": 3, "max_effects": 2}


@pytest.fixture(scope="module")
def control(tmp_path_factory):
    """The control record (no effect) diagnosed through the command line in a new process
    (``--workers 0``), from an output directory that already holds the user's files: the input
    record itself (named like tubeid's copies, ``data-site1.nc``) and a backup
    (``data-site2-backup.nc``).

    Numba: a solver compiled in a process and the same solver loaded from numba's cache can differ
    in the last bits (amplified by the chaotic stop), so blocks from a process that compiled it
    cannot be compared bit for bit with blocks from processes that loaded it. A first, small
    diagnosis in its own process writes the cache; the reference and the cluster's workers (test
    below) both load it."""
    tmp = tmp_path_factory.mktemp("control")
    warm = write_measurements(record(duration=16.0), tmp / "warm.nc")
    _cli("diagnose", warm, "--model", "paper-reference", "--out", tmp / "warm", "--workers", 0, "--no-progress",
         *_set_args({**CONTROL_SET, "realisations": 9, "false_alarm": 0.1}))
    out = tmp / "diag"
    out.mkdir()
    path = write_measurements(record(), out / "data-site1.nc")
    shutil.copy(path, out / "data-site2-backup.nc")
    user = {p.name: p.read_bytes() for p in out.iterdir()}
    stdout = _cli("diagnose", path, "--model", "paper-reference", "--out", out, "--workers", 0, "--no-progress",
                  *_set_args(CONTROL_SET))
    return {"path": path, "out": out, "report": json.loads((out / "report.json").read_text()), "stdout": stdout,
            "chunks": _chunks(out / "diagnose.zarr"), "user": user}


def _chunks(store):
    """Byte digest of every data and coordinate file of a store (attributes excluded: they name the
    store's directory, through the path of the record it reads)."""
    return {k: v for k, v in store_digest(store).items() if not k.startswith("attrs")}


def _same_report(a, b):
    a, b = dict(a), dict(b)
    a.pop("runner"), b.pop("runner")
    assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def test_control_is_none_through_the_command_line(control):
    """No effect: the test does not detect anything (p > 5 %), the answer is ``none`` and no step
    runs; report.json holds the p-values, report.md the assumptions; the user's files are intact."""
    rep, out = control["report"], control["out"]
    assert rep["effect"] == "none" and rep["effects"] == [] and rep["steps"] == [], rep
    det = rep["detection"]
    assert not det["detected"] and det["p_value"] > 0.05 and set(det["p_values"]) == set(MODEL_FORMS["exact"])
    assert det["size"] == 0.05 and det["n_realisations"] == 19
    assert rep["explained_before"] and rep["explained_after"] and rep["error_after"] == rep["error_before"]
    assert rep["load"]["delta_F_given"] and "fitting blocks" in rep["load"]["delta_F_source"]
    assert 1.0 <= rep["load"]["r_before"][0] <= 1.7  # started at 4.0; truth 1.3
    assert rep["stop_reason"] == "nothing detected"
    md = (out / "report.md").read_text()
    assert "none" in md and "p = " in md and "stop: symmetric" in md
    # the tone's, added mass's and damping's assumptions each say alike tubes cannot be told apart
    assert "its probe's (factor 0.25 on 'outer1')" in md and md.count("cannot be told apart") == 3
    assert (out / "residual.png").stat().st_size > 10_000
    assert "effect: none" in control["stdout"] and "nothing detected" in control["stdout"]
    for name, content in control["user"].items():
        assert (out / name).read_bytes() == content, name


def test_user_files_survive_every_command_and_overwrite_removes_only_the_manifest(control, tmp_path):
    """``--overwrite`` in a directory holding the input record and a backup named like tubeid's
    copies: both survive byte for byte; the files it wrote are replaced; a user's ``report.md``
    (not in the manifest) makes the run refuse before any work and is left as it was."""
    out = tmp_path / "d"
    shutil.copytree(control["out"], out)
    src = out / "data-site1.nc"
    settings = DiagnoseSettings(**{**CONTROL_SET, "seed": 3})
    with pytest.raises(SpecificationError, match="other data, model or settings"):
        diagnose(src, "paper-reference", settings, out=out)
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.name.startswith("data-site")}
    diagnose(src, "paper-reference", settings, out=out, overwrite=True)
    for name, content in before.items():
        assert (out / name).read_bytes() == content, name
    rep = json.loads((out / "report.json").read_text())
    assert rep["settings"]["seed"] == 3
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    (fresh / "report.md").write_text("my notes\n")
    with pytest.raises(SpecificationError, match="report.md"):
        diagnose(src, "paper-reference", settings, out=fresh)
    assert (fresh / "report.md").read_text() == "my notes\n"
    assert not (fresh / "diagnose.zarr").exists()


def test_a_partial_store_resumes_on_two_workers_to_the_uninterrupted_result(control, tmp_path):
    """The control's store made partial as a run killed during the band leaves it (its first task,
    the mean model and the test's realisations, unwritten; later stages never started); the same diagnosis resumes it on a real LocalCluster of
    2 worker processes: only the missing tasks run, the stored results are byte-identical to the
    uninterrupted in-process run's and the report is equal. A changed record, other settings or
    another model are refused before any work, leaving the store as it was."""
    out = control["out"]
    store = out / "diagnose.zarr"
    status = zarr.open_group(str(store), mode="r").attrs["stage_status"]
    assert status["step1_trials"] == status["step3_band"] == "not needed"  # the loop ended: no placeholder stages
    assert not (store / "step1_trials").exists()
    update_attrs(store, ended=None, stage_status={**status, **{n: "pending" for n, v in status.items() if v == "not needed"}})
    g = zarr.open_group(str(store), mode="r+", path="band")
    first = g["psd"].chunks[0]
    assert 0 < first < g["psd"].shape[0]
    real = g["realisation"][:]
    assert real[0] == -1 and list(real[1:first]) == list(range(first - 1))  # the test's own realisations
    g["psd"][:first] = np.nan  # the first task (δ = 0: two tasks, the second the probe realisations)
    clear_flag(store, (0,), "band")
    update_attrs(store, "band", finished="")
    assert store_status(store)["complete"] is False
    settings = DiagnoseSettings(**CONTROL_SET)
    d = diagnose(control["path"], "paper-reference", settings, out=out, workers=2)
    assert d.report["runner"]["workers"] == 2
    st = d.report["runner"]["stages"]
    assert (st["load_r"]["computed"], st["load_r"]["reused"]) == (0, 3)
    assert (st["band"]["computed"], st["band"]["reused"]) == (1, 1)
    assert _chunks(store) == control["chunks"]
    _same_report(d.report, control["report"])
    before = store_digest(store)
    changed = write_measurements(record(seed=12), tmp_path / "other.nc")
    with pytest.raises(SpecificationError, match="other data, model or settings"):
        diagnose(changed, "paper-reference", settings, out=out)
    with pytest.raises(SpecificationError, match="other data, model or settings"):
        diagnose(control["path"], "paper-simplified", settings, out=out)
    assert store_digest(store) == before


def test_the_records_copy_is_netcdf3_and_an_earlier_netcdf4_copy_is_replaced_on_resume(tmp_path):
    """The validated record's copy in --out is NetCDF-3 (the core install writes and reads it, the
    ``io`` extra not needed) and holds the record exactly. A directory where an earlier tubeid wrote
    the copy as NetCDF-4 (readable with the ``io`` extra only) resumes its store, and its copy is
    rewritten as NetCDF-3 under the same name (the store's parameters hold its path)."""
    from tubeid._outputs import OutputDir

    data = record(duration=16.0)
    settings = DiagnoseSettings(**{**CONTROL_SET, "realisations": 9, "false_alarm": 0.1, "max_effects": 0})
    out = tmp_path / "out"
    diagnose(data, "paper-reference", settings, out=out)
    (copy,) = out.glob("data-*.nc")
    assert copy.read_bytes()[:4] in (b"CDF\x01", b"CDF\x02")
    assert data_hash(read_measurements(copy)) == data_hash(data)
    earlier = write_measurements(data, tmp_path / "earlier.nc", format="netcdf4")
    OutputDir(out).write_bytes(copy.name, earlier.read_bytes())  # as tubeid wrote it before
    assert copy.read_bytes()[:8] == b"\x89HDF\r\n\x1a\n"
    d = diagnose(data, "paper-reference", settings, out=out)
    assert d.report["runner"]["tasks_computed"] == 0 and d.report["runner"]["tasks_reused"] > 0  # resumed
    assert copy.read_bytes()[:4] in (b"CDF\x01", b"CDF\x02") and OutputDir(out).owned(copy.name)
    assert data_hash(read_measurements(copy)) == data_hash(data)


# ----------------------------------------------------------- the output directory: refusals first, one run at a time

FAST = DiagnoseSettings(**{**CONTROL_SET, "realisations": 9, "false_alarm": 0.1, "max_effects": 0})


@pytest.fixture(scope="module")
def done(tmp_path_factory):
    """A completed fast diagnosis (in this process): its record and its output directory (copy it to use it)."""
    tmp = tmp_path_factory.mktemp("done")
    path = write_measurements(record(duration=16.0), tmp / "rec.nc")
    diagnose(path, "paper-reference", FAST, out=tmp / "out")
    return {"path": path, "out": tmp / "out", "other": write_measurements(record(duration=16.0, seed=12), tmp / "other.nc")}


def _tree(root):
    """Every entry under ``root`` (links not followed): a file's bytes, a link's target, or "dir"."""
    import os
    import pathlib

    tree = {}
    for where, dirs, files in os.walk(root):
        for name in dirs + files:
            p = pathlib.Path(where) / name
            rel = p.relative_to(root).as_posix()
            tree[rel] = ("link", os.readlink(p)) if p.is_symlink() else p.read_bytes() if p.is_file() else "dir"
    return tree


@pytest.mark.parametrize("case", ["edited report", "linked store", "foreign store"])
def test_a_refused_overwrite_removes_and_writes_nothing(done, tmp_path, case):
    """``--overwrite`` of a completed directory that it must refuse (the user edited report.md; diagnose.zarr
    is a symbolic link; diagnose.zarr was replaced by a Zarr store tubeid has no record of writing) is refused
    before anything is removed or written: the reports, the record's copy, the store all stay byte for byte,
    and the message names diagnose's own options (--out), not the runner's."""
    out = tmp_path / "out"
    shutil.copytree(done["out"], out, symlinks=True)
    store = out / "diagnose.zarr"
    if case == "edited report":
        with open(out / "report.md", "a") as fh:
            fh.write("my notes\n")
        match = r"out/report.md.*changed since"
    elif case == "linked store":
        store.rename(tmp_path / "elsewhere.zarr")
        store.symlink_to(tmp_path / "elsewhere.zarr")
        match = r"out/diagnose.zarr.*symbolic link"
    else:
        shutil.rmtree(store)
        zarr.open_group(str(store), mode="w", attributes={"mine": 1})
        match = r"out/diagnose.zarr.*no manifest"
    before = _tree(tmp_path)
    with pytest.raises(SpecificationError, match=match) as exc:
        diagnose(done["path"], "paper-reference", FAST.replace(seed=4), out=out, overwrite=True)
    assert "choose another --out" in str(exc.value)
    assert "--store" not in str(exc.value) and "--new-store" not in str(exc.value)
    assert _tree(tmp_path) == before


def test_a_held_store_lock_refuses_before_anything_is_removed(done, tmp_path):
    """A run holding the store's lock (``tubeid run`` on it, or an earlier tubeid's diagnosis): a diagnosis
    with ``--overwrite`` is refused naming --out before it removes or writes anything."""
    from tubeid.runner.lock import StoreLock

    out = tmp_path / "out"
    shutil.copytree(done["out"], out)
    with StoreLock(out / "diagnose.zarr"):
        before = _tree(out)
        with pytest.raises(SpecificationError, match=r"out/diagnose.zarr.*in use by another tubeid run") as exc:
            diagnose(done["other"], "paper-reference", FAST, out=out, overwrite=True)
        assert "choose another --out" in str(exc.value) and "--store" not in str(exc.value)
        assert _tree(out) == before


def test_the_runners_refusals_name_diagnoses_options(done, tmp_path, monkeypatch):
    """A refusal raised inside the runner (here its store lock, taken by another run after diagnose's own
    checks) names --out, not ``tubeid run``'s --store / --new-store."""
    from tubeid.diagnose import method
    from tubeid.runner.lock import StoreLock

    monkeypatch.setattr(method, "_refuse_store_in_use", lambda store: None)  # the holder comes after the checks
    out = tmp_path / "out"
    shutil.copytree(done["out"], out)
    with StoreLock(out / "diagnose.zarr"), pytest.raises(SpecificationError, match="in use") as exc:
        diagnose(done["path"], "paper-reference", FAST, out=out, overwrite=True)
    assert exc.value.field == "out/diagnose.zarr" and "choose another --out" in str(exc.value)
    assert "--store" not in str(exc.value) and "--new-store" not in str(exc.value)



@pytest.mark.parametrize("reference, rule", [("no-such-model", "unknown built-in model"),
                                             ("missing.yaml", "does not exist or is not a file")])
def test_an_unknown_delta_reference_is_refused_naming_the_setting(tmp_path, reference, rule):
    """An unknown reference model (a name or a missing file) is refused naming settings.delta_reference, the
    option the user gave (it said ``model = 'no-such-model'`` beside the declared --model, or ``specification
    file = ...``), before any run."""
    with pytest.raises(SpecificationError, match=rule) as exc:
        diagnose(record(duration=24.0), "paper-reference", DiagnoseSettings(delta_reference=str(tmp_path / reference)
                                                                            if reference.endswith(".yaml") else reference))
    assert exc.value.field == "settings.delta_reference" and reference in str(exc.value.value)


def _options(command: str) -> set[str]:
    """The long options of ``tubeid COMMAND`` (its parser, as the command line builds it)."""
    from tubeid.cli import build_parser

    sub = next(a for a in build_parser(command)._actions if a.dest == "command").choices[command]
    return {o for a in sub._actions for o in a.option_strings if o.startswith("--")}


def _strings(module_path):
    """Every string literal of a module's code (f-string pieces included), docstrings left out."""
    import ast

    tree = ast.parse(module_path.read_text())
    docs = {id(node.body[0].value) for node in ast.walk(tree)
            if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body
            and isinstance(node.body[0], ast.Expr) and isinstance(node.body[0].value, ast.Constant)}
    return [(n.lineno, n.value) for n in ast.walk(tree)
            if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs]


def test_no_runner_message_names_an_option_diagnose_lacks():
    """The runner's messages (everything diagnose runs: the runner but its commands' own modules, the path
    checks, the errors) spell no option of ``tubeid run`` that ``tubeid diagnose`` lacks (--store,
    --new-store, --no-verify, ...): such advice comes from the terms in force (tubeid.runner._terms), which
    diagnose says in its own options; and diagnose's terms name only options it has, every one of them."""
    import pathlib
    import re

    import tubeid
    from tubeid.diagnose.method import _TERMS
    from tubeid.runner import _terms

    run_only = _options("run") - _options("diagnose")
    assert {"--store", "--new-store", "--no-verify"} <= run_only
    src = pathlib.Path(tubeid.__file__).parent
    runner_only = {"cli.py", "bench.py", "testing.py", "_terms.py", "_embedded_worker.py"}  # tubeid run's own words
    modules = [f for f in sorted((src / "runner").glob("*.py")) if f.name not in runner_only]
    modules += [src / "_paths.py", src / "errors.py", src / "_validation.py"]
    found = [(f.name, line, option) for f in modules for line, text in _strings(f)
             for option in re.findall(r"--[a-z][a-z-]*", text) if option in run_only]
    assert found == []
    assert {f.name for f in dataclasses.fields(_terms.Terms)} == set(vars(_TERMS))
    for name, words in vars(_TERMS).items():
        assert words and set(re.findall(r"--[a-z][a-z-]*", words)) <= _options("diagnose"), (name, words)


def test_the_runners_store_refusals_in_diagnoses_terms(tmp_path):
    """The runner's refusals about a store, raised while diagnose speaks its terms (as it does around its
    calls into the runner), name the store ``out/diagnose.zarr`` and advise --out / --overwrite, never
    ``tubeid run``'s --store, --new-store or --no-verify; outside, the same refusals keep ``tubeid run``'s."""
    from tubeid.diagnose.method import _TERMS
    from tubeid.runner import store as st
    from tubeid.runner._terms import speaking
    from tubeid.runner.execute import _failed

    other = tmp_path / "other.zarr"  # another study's store
    zarr.open_group(str(other), mode="w", attributes={"format": st.FORMAT, "study_hash": "b" * 64})
    legacy = tmp_path / "legacy.zarr"
    zarr.open_group(str(legacy), mode="w", attributes={"format": sorted(st.LEGACY_FORMATS)[0]})
    foreign = tmp_path / "foreign.zarr"  # a Zarr store tubeid has no record of writing
    zarr.open_group(str(foreign), mode="w", attributes={"mine": 1})
    stage = tmp_path / "stage.zarr"
    zarr.open_group(str(stage), mode="w").create_group("fit", attributes={"stage_hash": "c" * 64})
    (tmp_path / "file").write_text("")
    refusals = {
        "another study": lambda: st.check_store(other, "a" * 64),
        "older layout": lambda: st.check_store(legacy, "a" * 64),
        "no manifest": lambda: st.remove_store(foreign, dry_run=True),
        "a file": lambda: st.prepare_path(tmp_path / "file"),
        "other stage": lambda: st.check_stage(stage, "fit", "d" * 64),
        "no flags": lambda: st.block_flags(stage, "fit"),
        "block failed": lambda: (_ for _ in ()).throw(_failed(ZeroDivisionError("x"), "block (1,)")),
    }
    for case, refuse in refusals.items():
        with speaking(_TERMS), pytest.raises((SpecificationError, RuntimeError)) as exc:
            refuse()
        said = str(exc.value)
        for option in ("--store", "--new-store", "--no-verify", "tubeid run"):
            assert option not in said, (case, said)
        assert "--out" in said or "--overwrite" in said, (case, said)
        if isinstance(exc.value, SpecificationError):
            assert exc.value.field == "out/diagnose.zarr", (case, said)
        with pytest.raises((SpecificationError, RuntimeError)) as exc:  # tubeid run's own words
            refuse()
        assert "--store" in str(exc.value) or "--new-store" in str(exc.value) or "--no-verify" in str(exc.value), case


_PAUSED = """
import json, pathlib, sys, time
from tubeid.diagnose import DiagnoseSettings, diagnose
from tubeid.runner import execute
record, out, ready, go, settings = sys.argv[1:]
run = execute.run
def paused(*args, **kwargs):  # the copy written, the store not yet locked by the runner
    pathlib.Path(ready).write_text("")
    while not pathlib.Path(go).exists():
        time.sleep(0.05)
    return run(*args, **kwargs)
execute.run = paused
diagnose(record, "paper-reference", DiagnoseSettings(**json.loads(settings)), out=out, workers=0)
"""


def test_a_second_run_with_overwrite_leaves_a_running_diagnosis_intact(done, tmp_path):
    """Run A (another process) is under way in --out (its record's copy written, its store not locked yet);
    run B on other data with ``--overwrite`` is refused, naming --out, before it removes or writes anything;
    A then finishes its diagnosis."""
    out, ready, go = tmp_path / "out", tmp_path / "ready", tmp_path / "go"
    settings = json.dumps(dataclasses.asdict(FAST), default=list)
    a = subprocess.Popen([sys.executable, "-c", _PAUSED, str(done["path"]), str(out), str(ready), str(go), settings],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        for _ in range(6000):
            if ready.exists() or a.poll() is not None:
                break
            time.sleep(0.05)
        assert ready.exists(), a.communicate()[1][-3000:]
        before = _tree(out)
        assert any(n.startswith("data-") for n in before)
        with pytest.raises(SpecificationError, match=r"out = .*in use by another tubeid run") as exc:
            diagnose(done["other"], "paper-reference", FAST, out=out, overwrite=True)
        assert "choose another --out" in str(exc.value) and "--store" not in str(exc.value)
        assert _tree(out) == before
    finally:
        go.write_text("")
        _, err = a.communicate(timeout=600)
    assert a.returncode == 0, err[-3000:]
    assert json.loads((out / "report.json").read_text())["runner"]["tasks_computed"] > 0
    assert [p.name for p in out.glob("data-*.nc")] == [f"data-{data_hash(read_measurements(done['path']))[:16]}.nc"]


def test_out_is_refused_before_anything_is_created_if_it_is_the_record_or_inside_it_or_a_url(tmp_path):
    """--out that is a Zarr record itself or a directory inside it (the user's data: never written into),
    or a path zarr reads as a URL ('::'), is refused naming out before anything is created; the record's
    own directory is fine (the record untouched)."""
    rec = write_measurements(record(duration=16.0), tmp_path / "rec.zarr")
    before = _tree(tmp_path)
    for out, match in ((rec, "is the record being diagnosed"), (rec / "sub", "lies inside the record"),
                       (tmp_path / "o::x", "local directory path")):
        with pytest.raises(SpecificationError, match=rf"^out = .*{match}"):
            diagnose(rec, "paper-reference", FAST, out=out)
        assert _tree(tmp_path) == before, out
    assert main(["diagnose", str(rec), "--out", str(rec), "--model", "paper-reference", "--no-progress"]) == 2
    assert _tree(tmp_path) == before
    diagnose(rec, "paper-reference", FAST, out=tmp_path)  # the record's directory
    assert {k: v for k, v in _tree(tmp_path).items() if k.startswith("rec.zarr")} == before
    assert (tmp_path / "report.json").exists()


def _check_named(rep, names):
    assert sorted(e["name"] for e in rep["effects"]) == sorted(names), json.dumps(rep["steps"], indent=1, default=str)[:4000]
    assert rep["detection"]["detected"] and rep["error_after"] < rep["error_before"]


@pytest.fixture(scope="module")
def tone_between():
    """A 100 N tone at 29 Hz on the centre tube at x = 4.6 m (between nodes and sensors, away from
    8 m), written as a force column, seen by 7 sensors during 96 s: the diagnosis's report. With
    48 s the trial positions' fitting errors are too noisy and the answer flips with any small
    change of the record (measured: on ``outer4`` at x = 1 m for 1 of seeds 11–14, and for 4 of
    seeds 11–16 before the tone columns were scaled by 1.003 for the solver's linear reading); with
    96 s, seeds 11–16, on the centre tube at 4.51–5.0 m in 6 of 6, named alone in 5 (an earlier
    machine); on another CPU (which rounds the chaotic records differently) and with the amplitude
    re-fitted along its profile: on the centre tube at 4.51–4.53 m, 84–87 N, in 5 of 6 (seed 13:
    ``outer1`` at 8.5 m)."""
    data = make_record(effects=HandEffects(tones=(("centre", 4.6, 29.0, 100.0),)), xs=SEVEN, duration=96.0, seed=11)
    return diagnose(data, "paper-reference", SMALL).report


def test_a_tone_between_sensors_is_named_and_located(tone_between):
    """Named ``tone``, its frequency within one bin (0.5 Hz), its position within one element (2 m),
    its amplitude."""
    rep = tone_between
    _check_named(rep, ["tone"])
    p = {k: v["value"] for k, v in rep["effects"][0]["parameters"].items()}
    assert abs(p["frequency_hz"] - 29.0) <= 0.5 and p["tube"] == "centre" and abs(p["x"] - 4.6) <= 2.0, p
    # the amplitude, tied to the position (|H(x)| A is what the sensors see): within 30 % once the
    # position is within 0.5 m (seeds 11–16, the amplitude re-fitted along its profile: 84–87 N at
    # 4.51–4.53 m; with a line of 3 simulated amplitudes, this record gave 60 N at 4.52 m on one CPU)
    assert abs(p["x"] - 4.6) > 0.5 or abs(p["amplitude"] / 100.0 - 1) <= 0.3, p


@pytest.mark.xfail(strict=True, reason="known limit (issue 11): the fitted tone (84 N at 4.52 m for 100 N at 4.6 m) "
                   "leaves the line's residual above the test's null (scan 331 against a null median of 9.6, p = 0.05 "
                   "with 19 realisations: a line's power is nearly deterministic, so its bins' scatter is small), so "
                   "the record is not explained after the selection")
def test_a_tone_between_sensors_is_explained_after_the_selection(tone_between):
    """After the tone is fitted, the calibrated test no longer detects anything."""
    assert tone_between["explained_after"], tone_between["detection_after"]


def test_sensor_noise_is_chosen_over_a_first_improving_candidate_and_the_load_refitted():
    """White noise of 3e-17 m²/Hz added with numpy: the tone (first in the catalog) also lowers the
    held-out error a little, so the choice must be the best one, ``sensor_noise``; with the noise
    re-fitted jointly with r, r stays near the truth (1.3 N²/Hz, not inflated by the floor) and
    the level within a factor 2."""
    rep = diagnose(record(HandEffects(noise=3e-17)), "paper-reference", SMALL).report
    _check_named(rep, ["sensor_noise"])
    step = rep["steps"][0]
    improving = [c["name"] for c in step["candidates"] if c["held_out_error"] < step["error_current"]]
    assert improving[0] != "sensor_noise", improving  # a first-improving rule would not choose it
    level = rep["effects"][0]["parameters"]["level"]["value"]
    assert 3e-17 / 2 <= level <= 3e-17 * 2
    assert 1.3 / 1.25 <= rep["load"]["r_after"][0] <= 1.3 * 1.25


def test_two_effects_at_once_are_both_named():
    """A second stop at x = 4 m (a node between the sensors at 2 and 6 m; gap 3 µm) and sensor noise
    at once, both written by hand: both named, the stop within one element of 4 m. The first test at
    α = 0.1, the one after step 1 at the continuation rate 0.05."""
    settings = SMALL.replace(false_alarm=0.1, continuation_alarm=0.05)
    rep = diagnose(record(HandEffects(stops=(("centre", 4.0, 3e-6, 1e8),), noise=3e-17)), "paper-reference", settings).report
    assert rep["detection"]["false_alarm"] == 0.1
    assert [s["detection_after"]["false_alarm"] for s in rep["steps"]] == [0.05] * len(rep["steps"])
    _check_named(rep, ["stop", "sensor_noise"])
    stop = next(e for e in rep["effects"] if e["name"] == "stop")
    assert abs(stop["parameters"]["x"]["value"] - 4.0) <= 2.0
    assert len(rep["steps"]) >= 2 and [s["chosen"] for s in rep["steps"][:2]] != [None, None]


def test_added_mass_on_another_tube_from_a_symplectic_euler_record():
    """The density of outer1 written into the specification (× 1.5: factor 0.5, between the trial
    grid's 0.45 and 1.35) and the record integrated by the solver's symplectic Euler at its
    default step (a second integrator): named ``added_mass`` on an outer tube (the four are
    identical and seen alike from the centre tube's sensors), factor within 30 %, the record
    explained after. Damping competes (it also lowers the held-out error): the held-out choice
    between the two decides."""
    data = record(HandEffects(density={"outer1": 1.5}), duration=36.0, method="symplectic-euler")
    rep = diagnose(data, "paper-reference", SMALL.replace(candidates=("added_mass", "damping", "sensor_noise"),
                                                           max_effects=1)).report
    _check_named(rep, ["added_mass"])
    p = rep["effects"][0]["parameters"]
    assert p["tube"]["value"].startswith("outer") and abs(p["factor"]["value"] - 0.5) <= 0.15, p
    damping = next(c for c in rep["steps"][0]["candidates"] if c["name"] == "damping")
    assert damping["held_out_error"] < rep["steps"][0]["error_current"]
    assert rep["explained_after"]


def test_delta_identified_by_maximum_likelihood_against_a_reference():
    """``delta_reference``: δ of the declared simplified model (MODEL.md §2's equivalent-beam model)
    by the paper's maximum likelihood of J against ``paper-reference``: interior, as MODEL.md
    measures (0.627 ± 0.056 with 200 realisations; here 60 → within 3 × 0.1), and the test then
    runs at that δ."""
    model = "/work/shared/models/paper-simplified.toml"
    import os

    if not os.path.exists(model):
        model = "paper-simplified"
    data = record(duration=24.0)
    rep = diagnose(data, model, SMALL.replace(delta_reference="paper-reference", delta_realisations=60, max_effects=0,
                                              realisations=9, false_alarm=0.1, n_bootstrap=20)).report
    d = rep["delta"]
    assert "maximum likelihood" in d["delta_source"] and not d["delta_at_grid_edge"]
    assert abs(d["delta"] - 0.627) <= 0.3, d


SIMPLIFIED = SMALL.replace(model_form="simplified", delta=0.6, max_effects=1, probe_realisations=20)


@pytest.mark.parametrize("case", ["control", "tone", "sensor_noise", "added_mass"])
def test_a_simplified_model_declared_tells_model_uncertainty_from_a_missing_effect(case):
    """Records of ``paper-reference`` (made by hand, another code path), ``paper-simplified``
    declared at δ = 0.6 (about what the paper's maximum likelihood gives, MODEL.md §2) with the
    simplified model form: the model's own errors (+25 % mass, +42 % EI of B, a coarse mesh) are not
    an alarm; a tone, a noise floor and the centre tube's density × 2 are named, each by the
    statistic built for it. (The exact form's false alarms on such records are measured at full
    size by the campaign.)"""
    eff = {"control": HandEffects(), "tone": HandEffects(tones=(("centre", 4.6, 29.0, 100.0),)),
           "sensor_noise": HandEffects(noise=3e-17), "added_mass": HandEffects(density={"centre": 2.0})}[case]
    data = make_record(effects=eff, xs=SEVEN, duration=48.0, seed=11)
    rep = diagnose(data, "paper-simplified", SIMPLIFIED).report
    assert rep["model_form"] == "simplified" and rep["detection"]["model_form"] == "simplified"
    # the probe realisations reached the test, and are not among its samples
    assert set(rep["detection"]["p_values"]) == set(MODEL_FORMS["simplified"])
    assert rep["detection"]["n_realisations"] == SIMPLIFIED.n_realisations
    if case == "control":
        assert not rep["detection"]["detected"] and rep["effects"] == [], rep["detection"]
    else:
        assert [e["name"] for e in rep["effects"]] == [case], json.dumps(rep["steps"], default=str)[:3000]
        built = {"tone": ("line",), "sensor_noise": ("floor",), "added_mass": ("tilt", "profile")}[case]
        assert max(rep["detection"]["excess"][k] for k in built) == max(rep["detection"]["excess"].values())
        fitted = {c["name"]: c["feature"] for c in rep["steps"][0]["candidates"]}
        assert fitted[case] == {"tone": "line", "sensor_noise": "floor", "added_mass": "profile"}[case], fitted


# ------------------------------------------------------------------------------------- slow


@pytest.mark.slow
@pytest.mark.parametrize("seed", [31, 32])
def test_full_size_simplified_names_the_catalogs_added_mass(seed):
    """The issue's target with the simplified model declared: 220 s, 7 sensors, ``paper-simplified``
    with δ by maximum likelihood against ``paper-reference`` (default settings otherwise), the
    centre tube's density × 1.3 written by hand into the reference: named ``added_mass`` alone on
    the centre tube by the ``profile`` statistic and sized by its feature, with the diagnosis's
    default seed (record seeds beyond the README's). Not a rate: the campaign, where every record
    has its own diagnosis seed, names 4 of its 5 (README)."""
    rep = diagnose(make_record(effects=HandEffects(density={"centre": 1.3}), xs=SEVEN, seed=seed), "paper-simplified",
                   DiagnoseSettings(delta_reference="paper-reference"), workers=2).report
    named = [(e["name"], e["parameters"]["tube"]["value"]) for e in rep["effects"]]
    assert named == [("added_mass", "centre")], rep["steps"]
    assert rep["detection"]["excess"]["profile"] == max(rep["detection"]["excess"].values()), rep["detection"]
    # sized by the profile's feature: 0.35–0.4 on records 1–5 (the tilt's gave 0.52–0.63; README)
    assert 0.2 <= rep["effects"][0]["parameters"]["factor"]["value"] <= 0.48, rep["effects"]


@pytest.mark.slow
@pytest.mark.parametrize("seed", [41, 42])
def test_full_size_another_tubes_added_mass_is_found_by_the_exact_forms_profile(seed):
    """220 s, 7 sensors on the centre tube, ``paper-reference`` declared, default settings: outer3's
    density × 1.3 written by hand into the reference (not the probe's tube, outer1; the four outer
    tubes are alike) is detected with the profile as the strongest departure (without it: p =
    0.125–0.8 on such records, README) and named added mass on an outer tube (the sensors cannot
    tell them apart: the first is reported), sized within a factor of 2 of 0.3."""
    rep = diagnose(make_record(effects=HandEffects(density={"outer3": 1.3}), xs=SEVEN, seed=seed), "paper-reference",
                   DiagnoseSettings(), workers=2).report
    det = rep["detection"]
    assert det["detected"] and det["excess"]["profile"] == max(det["excess"].values()), det
    named = [(e["name"], e["parameters"]["tube"]["value"]) for e in rep["effects"]]
    assert named == [("added_mass", "outer1")], rep["steps"]
    assert 0.15 <= rep["effects"][0]["parameters"]["factor"]["value"] <= 0.6, rep["effects"]


@pytest.mark.slow
@pytest.mark.parametrize("case", ["control", "tone", "damping_x3", "stop_and_noise", "mass_and_tone"])
def test_full_size(case):
    """The issue's setting: 220 s, 7 sensors c02–c14, default settings, ``paper-reference`` declared."""
    eff = {"control": HandEffects(), "tone": HandEffects(tones=(("centre", 5.0, 37.0, 21.0),)),
           "damping_x3": HandEffects(damping={"centre": 0.06}),
           "stop_and_noise": HandEffects(stops=(("centre", 10.0, 3e-6, 1e8),), noise=1e-16),
           "mass_and_tone": HandEffects(density={"outer1": 1.3}, tones=(("centre", 5.0, 37.0, 21.0),))}[case]
    truth = {"control": [], "tone": ["tone"], "damping_x3": ["damping"], "stop_and_noise": ["stop", "sensor_noise"],
             "mass_and_tone": ["added_mass", "tone"]}[case]
    rep = diagnose(make_record(effects=eff, xs=SEVEN, seed=23), "paper-reference", DiagnoseSettings(seed=1), workers=2).report
    named = [e["name"] for e in rep["effects"]]
    if case == "stop_and_noise":
        # the issue's target for two at once is both named; an extra `damping` after a stop (the stop's
        # fit leaves a departure the test still sees) is open in issue 11 — on one CPU seed 23 gets it,
        # on another not: the chaotic record rounds differently
        assert set(truth) <= set(named) and len(named) <= len(truth) + 1, rep["steps"]
    else:
        assert sorted(named) == sorted(truth), rep["steps"]


@pytest.mark.slow
def test_a_near_tied_runner_up_is_named_after_the_record_is_explained():
    """Added mass (outer1 × 1.3) + the 9 dB tone, 220 s, seed 26 (``benchmarks/diagnose_records.py
    mass_and_tone 26``), the exact form's profile left out (``probe_realisations=0``, as before it
    read another tube's mass): at step 1 the tone and the mass are near-tied (within ``tie``; measured
    0.775 and 0.787 on one machine, the tone first; on another CPU, which rounds the chaotic record
    differently, the mass went first). Whichever goes first, both are named: when the first leaves
    the record explained (the test no longer detects anything), the other is offered once more as a
    continuation and added — without the rule the answer would be the first alone; when the test
    still detects, the other is the next step's plain choice. With the default settings (the
    profile) both are named too."""
    from tubeid.diagnose._selection import near_ties

    eff = HandEffects(density={"outer1": 1.3}, tones=(("centre", 5.0, 37.0, 21.0),))
    data = make_record(effects=eff, xs=SEVEN, seed=26)
    settings = DiagnoseSettings(probe_realisations=0)
    rep = diagnose(data, "paper-reference", settings, workers=2).report
    _check_named(rep, ["tone", "added_mass"])
    first, second = rep["steps"][:2]
    other = ({"tone", "added_mass"} - {first["chosen"]}).pop()
    assert other in near_ties(first["candidates"], first["chosen"], settings.tie), first["candidates"]
    assert second["chosen"] == other
    if not first["detection_after"]["detected"]:  # the rule's path
        assert second["continuation"][other]["chosen"] == first["chosen"]
    else:
        assert second["continuation"] is None
    assert rep["explained_after"]
    rep = diagnose(data, "paper-reference", DiagnoseSettings(), workers=2).report
    _check_named(rep, ["tone", "added_mass"])


def test_a_store_of_another_diagnosis_version_is_refused_saying_so(tmp_path):
    """Same data, model and settings but another pipeline (tubeid's stages changed): not "other data"."""
    import zarr

    from tubeid.diagnose.method import _check_store

    overrides = {"data": "d.nc", "data_sha256": "ab" * 32, "model": "{}", "settings": "{}"}
    store = tmp_path / "diagnose.zarr"
    zarr.open_group(str(store), mode="w", attributes={"study_hash": "old", "parameters": json.dumps(overrides),
                                                      "tubeid_version": "0.0.9"})
    with pytest.raises(SpecificationError, match="same data, model and settings diagnosed by another version") as e:
        _check_store(store, "new", overrides)
    assert "tubeid 0.0.9" in str(e.value) and "--overwrite" in str(e.value)
    with pytest.raises(SpecificationError, match="a diagnosis of other data, model or settings"):
        _check_store(store, "new", {**overrides, "settings": '{"blocks": 6}'})
    _check_store(store, "old", overrides)  # its own: accepted


def test_the_probe_realisations_are_simulated_only_where_the_profile_reads_them(tmp_path):
    """The band stages hold ``n_probe_realisations`` probe realisations (−2, −3, …) when added mass
    is a candidate (60 with the simplified form, 20 with the exact one, unless given), and none
    without added mass among the candidates or with ``probe_realisations = 0``; the probe is the
    catalog's added mass on the tube with the most sensors (simplified form) or on the first tube
    without a sensor (exact form; checked on paper-reference's tubes too)."""
    from tubeid.diagnose.stages import OBSERVED, _band_observed, _probes

    data = record(duration=24.0)
    path = write_measurements(data, tmp_path / "d.nc")
    model = json.dumps(spec_to_dict(builtin_spec("paper-simplified")), sort_keys=True)
    path_ctx = []
    exact = SMALL.replace(probe_realisations=None)
    for settings, expected in ((SIMPLIFIED, [-2 - k for k in range(20)]),
                               (SIMPLIFIED.replace(probe_realisations=None), [-2 - k for k in range(60)]),
                               (exact, [-2 - k for k in range(20)]),
                               (exact.replace(probe_realisations=2), [-2, -3]),
                               (exact.replace(probe_realisations=0), []),
                               (SIMPLIFIED.replace(candidates=("tone", "stop")), []),
                               (exact.replace(candidates=("tone", "stop")), []),
                               (SIMPLIFIED.replace(probe_realisations=3), [-2, -3, -4]),
                               (SIMPLIFIED.replace(probe_realisations=0), [])):
        ctx = load_context(str(path), data_hash(data), model, settings.to_json())
        assert _probes(ctx) == expected, settings
        # what the band stages store: all the simplified form reads, else the fine PSDs with probes
        assert _band_observed(ctx) == (OBSERVED if settings.form == "simplified" else ("fine",) if expected else ())
        path_ctx.append(ctx)
    probe = CATALOG["added_mass"].probe(path_ctx[0].spec)
    assert (probe.tube, probe.factor) == ("centre", 0.25)
    assert CATALOG["added_mass"].probe(path_ctx[0].spec, "exact").tube == "equivalent"
    reference = builtin_spec("paper-reference")
    assert CATALOG["added_mass"].probe(reference, "exact").tube == "outer1"  # the first tube without a sensor
    assert CATALOG["added_mass"].probe(reference, "simplified").tube == "centre"
    with pytest.raises(SpecificationError, match="form"):
        CATALOG["added_mass"].probe(reference, "Exact")
    everywhere = reference.replace(sensors=reference.sensors + sum(
        (sensors((4.0,), tube=t, prefix="o" + t[-1]) for t in ("outer1", "outer2", "outer3", "outer4")), ()))
    assert CATALOG["added_mass"].probe(everywhere, "exact").tube == "centre"  # every tube has one: the sensors'
    mixed = builtin_spec("paper-reference").replace(
        sensors=sensors((4.0,), tube="outer2", prefix="o") + sensors((2.0, 6.0), tube="outer1", prefix="p"))
    assert CATALOG["added_mass"].probe(mixed).tube == "outer1"  # the tube with the most sensors, not the first


def test_the_figures_show_names_as_written_not_as_tex(tmp_path):
    """A sensor or effect named with dollar signs (c$\\nope$) is a name: matplotlib's TeX parser failed on it
    after report.json and report.md were written."""
    import types

    from tubeid._outputs import OutputDir
    from tubeid.diagnose.report import write_files

    f = np.linspace(0.0, 100.0, 51)
    band = np.full((f.size, 2), 1e-12)
    diag = types.SimpleNamespace(
        frequency=f, sensors=["c$\\nope$", "c06"], measured=2 * band, bands={"before": (band, 3 * band)},
        report={"settings": {"level": 0.95}, "effects": [{"name": "tone at $x$"}], "load": {"delta_F_given": True}})
    figures = {}
    save = OutputDir.save_figure

    def keep(self, fig, name, **kw):
        figures[name] = fig
        return save(self, fig, name, **kw)

    with unittest.mock.patch("tubeid.diagnose.report.markdown", return_value="report\n"), \
            unittest.mock.patch.object(OutputDir, "save_figure", keep):
        out = write_files(diag, tmp_path / "out")
    assert (out / "residual.png").stat().st_size > 1000 and OutputDir(out, field="out").owned("residual.png")
    first = figures["residual.png"].axes[0]
    assert first.title.get_text() == "c\\$\\nope\\$: before"  # shown as c$\nope$
    assert any("mathdefault" in t.get_text() for t in first.get_yticklabels())  # the log ticks' own math kept


def test_the_campaign_study_checks_its_declared_model_and_stores_its_content(tmp_path):
    """studies/diagnose_effects.py: ``--set simplified_model=NAME`` with a typo used to be accepted and fail only in
    the fifth stage, after hours of the first four; a specification file was stored by its path, so a resume after
    the file was edited mixed records diagnosed with two models in one stage. Now a bad name, a missing file and a
    model carrying effects are refused when the file is loaded (no store), and a file's content is the value the
    stages store and hash (an edited file: another stage, refused on resume rather than mixed)."""
    import pathlib

    import yaml

    from tubeid.mechanics.spec import spec_from_dict
    from tubeid.runner.execute import run
    from tubeid.runner.study import load_definition

    study = pathlib.Path(__file__).resolve().parents[1] / "studies" / "diagnose_effects.py"
    for value, match in (("no-such-model", "unknown built-in model"), (str(tmp_path / "none.yaml"), "does not exist"),
                         (3, "must be a built-in model name")):
        rule = r"parameters\.simplified_model = .*" + match
        with pytest.raises(SpecificationError, match=rule):  # when the file is loaded: before anything runs
            load_definition(study, overrides={"simplified_model": value})
        with pytest.raises(SpecificationError, match=rule):
            run(study, tmp_path / "s.zarr", workers=0, quiet=True, overrides={"simplified_model": value})
        assert not (tmp_path / "s.zarr").exists()
    with_effects = spec_to_dict(dataclasses.replace(builtin_spec("paper-simplified"), effects=(Tone(37.0, 20.0),)))
    carrying = tmp_path / "carrying.yaml"
    carrying.write_text(yaml.safe_dump(with_effects))
    with pytest.raises(SpecificationError, match=r"parameters\.simplified_model: effects = .*without carried effects"):
        load_definition(study, overrides={"simplified_model": str(carrying)})

    d = spec_to_dict(builtin_spec("paper-simplified"))
    spec = tmp_path / "declared.yaml"
    spec.write_text(yaml.safe_dump(d))
    pipeline = load_definition(study, overrides={"simplified_model": str(spec)})[0]
    first = pipeline.values["simplified_model"]
    assert json.loads(first)["source"] == str(spec)
    assert spec_to_dict(spec_from_dict(json.loads(first)["spec"])) == spec_to_dict(builtin_spec("paper-simplified"))
    stage = dict(zip([f.__name__ for f in pipeline.stages], pipeline.stages))["simplified_false_alarm"]
    built = stage({}, simplified_model=first, control_records=1)
    assert built.values["model"] == first  # the content reaches the task, its parameters and so the stage's hash
    d["tubes"][0]["damping_ratio"] = 0.03
    spec.write_text(yaml.safe_dump(d))
    # the same process (a notebook): the edited file is read again, not the content of the first load
    edited = load_definition(study, overrides={"simplified_model": str(spec)})[0].values["simplified_model"]
    assert edited != first and stage({}, simplified_model=edited, control_records=1).values["model"] == edited


def test_max_frequency_keeps_an_anti_alias_filter_out_of_the_diagnosis():
    """A data-acquisition system filters its channels below the Nyquist frequency (anti-alias); the
    model's realisations are sampled without a filter. A control record passed through a typical
    filter (8th-order Butterworth at 0.4 × the sampling rate, 1 kHz here) is detected at the smallest
    p-value, every statistic reading the attenuated top bins (gof 1 → 300). With
    ``max_frequency_hz`` below the filter's edge, the filtered record gives the raw record's
    statistics and p-value: the compared spectra end there, record and realisations alike. The
    filter is applied forward and backward (zero phase): a causal one delays the record by its
    group delay, a record shifted in time, whose estimates differ by their own scatter."""
    import scipy.signal

    dt = 1e-3
    raw = record(duration=24.0, dt=dt)
    sos = scipy.signal.butter(8, 0.4 / dt, fs=1 / dt, output="sos")
    filtered = raw.copy(data={"displacement": scipy.signal.sosfiltfilt(sos, raw["displacement"].values, axis=0)})
    s = SMALL.replace(max_effects=0)
    assert diagnose(filtered, "paper-reference", s).report["detection"]["p_value"] == pytest.approx(1 / 20, abs=0)
    cut = s.replace(max_frequency_hz=250.0)  # |H|² = 1 - 5e-4 there
    a = diagnose(raw, "paper-reference", cut).report["detection"]
    b = diagnose(filtered, "paper-reference", cut).report["detection"]
    assert b["p_value"] == a["p_value"] > 1 / 20
    assert b["statistics"] == pytest.approx(a["statistics"], rel=1e-6, abs=0)
    for bad in (100.0, 500.0):  # the model band; the record's Nyquist frequency
        with pytest.raises(SpecificationError, match=r"^settings\.max_frequency_hz = "):
            diagnose(raw, "paper-reference", s.replace(max_frequency_hz=bad))
