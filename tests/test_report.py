"""``tubeid report``: figures and summaries of a paper store, built here directly with xarray."""

import json

import matplotlib.image
import numpy as np
import pytest
import xarray as xr

from tubeid.cli import main
from tubeid.identification.likelihood import likelihood_curve
from tubeid.identification.loads import delta_f_likelihood, distance_map
from tubeid.seeds import rng_for

F = np.arange(0.0, 150.5, 0.5)  # Hz, 0 .. 150 (a Welch grid beyond the 100 Hz band)
SENS = ["P_obs"]
N_BOOT = 50
# sensor names are fixed-length strings, which zarr 3 stores with an as yet unspecified data type
pytestmark = pytest.mark.filterwarnings("ignore::zarr.errors.UnstableSpecificationWarning")
FIGURES = ["fig4_mean_model.png", "fig5_delta_likelihood.png", "fig6_confidence_region.png", "d_map.png",
           "delta_f_likelihood.png"]


def _lorentz(f0, zeta=0.02):
    return 1.0 / ((1 - (F / f0) ** 2) ** 2 + (2 * zeta * F / f0) ** 2)


# response shapes per unit of r1 [N²/Hz] and r2 [(N m)²/Hz]: PSD levels 1e-16 .. 1e-12 m²/Hz as in the paper
A = 2e-15 * (_lorentz(5.8) + 0.1 * _lorentz(45.0)) + 1e-18
B = 1e-15 * (_lorentz(16.0) + 0.2 * _lorentz(70.0)) + 1e-18


def _matrix(x, real):
    """(..., frequency) -> (..., frequency, sensor, sensor_) complex, or the real scalar PSD."""
    return x if real else (x + 0j)[..., None, None]


def _dims(lead, real):
    return lead + ("frequency",) + (() if real else ("sensor", "sensor_"))


def _coords(real, **extra):
    c = {"frequency": ("frequency", F, {"units": "Hz"}), **extra}
    if not real:
        c.update(sensor=SENS, sensor_=SENS)
    return c


def _groups(real=False, nan_realisations=0):
    rng = np.random.default_rng(1)
    deltas = np.round(np.arange(0.05, 0.851, 0.05), 3)
    z = rng.standard_normal(40)  # common random numbers across δ
    J = 3e-9 * np.exp(deltas[:, None] * z[None, :] - deltas[:, None] ** 2 / 2)
    if nan_realisations:
        J[:, -nan_realisations:] = np.nan  # blocks not yet written by the runner
    delta = xr.Dataset({"J": (("delta", "realisation"), J, {"units": "m^2 rad/(N^2 s)"})},
                       coords={"delta": deltas, "realisation": np.arange(40)}, attrs={"J_ref": 3.4e-9})

    truth = 18.0 * A + 20.0 * B
    ref = truth * (1 + 0.15 * rng.standard_normal((3, F.size)))
    mean = 16.0 * A + 23.0 * B * (1 + (F > 35))  # the mean simplified model misses 35–100 Hz
    sto = mean * np.exp(0.6 * rng.standard_normal((30, 1)) + 0.3 * rng.standard_normal((30, F.size)))
    response = xr.Dataset(
        {"psd_reference": (_dims(("realisation_ref",), real), _matrix(ref, real), {"units": "m^2/Hz"}),
         "psd_mean": (_dims((), real), _matrix(mean, real), {"units": "m^2/Hz"}),
         "psd_stochastic": (_dims(("realisation",), real), _matrix(sto, real), {"units": "m^2/Hz"})},
        coords=_coords(real), attrs={"delta_opt": 0.45})

    r1 = 18.0 * 1.25 ** np.arange(-2, 3) * 1.04
    r2 = 20.0 * 1.25 ** np.arange(-2, 3) * 0.97
    eps, eta = (1 + 0.1 * rng.standard_normal((2, 6, F.size)))
    psd = r1[:, None, None, None] * A * eps + r2[None, :, None, None] * B * eta
    load_r = xr.Dataset({"psd": (_dims(("r1", "r2", "realisation"), real), _matrix(psd, real), {"units": "m^2/Hz"})},
                        coords=_coords(real, r1=("r1", r1, {"units": "N^2/Hz"}),
                                       r2=("r2", r2, {"units": "(N m)^2/Hz"})))

    dF = np.round(np.arange(0.02, 0.62, 0.04), 3)
    zs = rng.standard_normal(30)
    Js = 2e-23 * np.exp(dF[:, None] * zs[None, :])
    load_delta_f = xr.Dataset({"J_s": (("delta_F", "realisation"), Js, {"units": "(m^2/Hz)^2 rad/s"})},
                              coords={"delta_F": dF}, attrs={"J_s_exp": 2.1e-23})
    return {"delta": delta, "response": response, "load_r": load_r, "load_delta_f": load_delta_f}


def _write(path, groups):
    for i, (name, ds) in enumerate(groups.items()):
        ds.to_zarr(path, group=name, mode="w" if i == 0 else "a", consolidated=False)
    return str(path)


def _run(store, out, *extra):
    return main(["report", store, "--out", str(out), "--n-bootstrap", str(N_BOOT), *extra])


@pytest.fixture(scope="module")
def full(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("report")
    groups = _groups()
    store = _write(tmp / "paper.zarr", groups)
    out = tmp / "out"
    assert _run(store, out) == 0
    return groups, out, json.loads((out / "summary.json").read_text())


def test_figures_are_valid_png_images(full):
    _, out, summary = full
    assert sorted(summary["figures"]) == sorted(FIGURES)
    for name in FIGURES:
        data = (out / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n"
        img = matplotlib.image.imread(out / name)
        assert img.ndim == 3 and img.shape[0] > 200 and img.shape[1] > 300
        assert np.ptp(img[..., :3]) > 0.5  # not blank


def test_summary_values_are_those_of_the_identification_functions(full):
    groups, _, s = full
    q = s["quantities"]
    d = groups["delta"]
    curve = likelihood_curve(d.J, d.attrs["J_ref"], d.delta.values, "delta", n_bootstrap=N_BOOT,
                             rng=rng_for(2008, "report", "delta"))
    assert q["delta_opt"]["value"] == pytest.approx(curve.attrs["argmax"], rel=1e-12, abs=0)
    assert q["delta_opt"]["std"] == pytest.approx(curve.attrs["argmax_std"], rel=1e-12, abs=0)
    assert q["delta_opt"]["low"] == pytest.approx(curve.attrs["argmax_low"], rel=1e-12, abs=0)

    dm = distance_map(groups["load_r"].psd, groups["response"].psd_reference, n_bootstrap=N_BOOT,
                      rng=rng_for(2008, "report", "load_r"))
    for n, key in enumerate(("r1_opt", "r2_opt")):
        assert q[key]["value"] == pytest.approx(dm.attrs["r_opt"][n], rel=1e-12, abs=0)
        assert q[key]["std"] == pytest.approx(dm.attrs["r_opt_std"][n], rel=1e-12, abs=0)
    assert s["details"]["load_r"]["D_min"] == pytest.approx(dm.attrs["D_min"], rel=1e-12, abs=0)
    # the synthetic store was built around r = (18, 20) with 15 % noise on 3 records
    assert q["r1_opt"]["value"] == pytest.approx(18.0, rel=0.1, abs=0)
    assert q["r2_opt"]["value"] == pytest.approx(20.0, rel=0.1, abs=0)

    lf = groups["load_delta_f"]
    lk = delta_f_likelihood(lf.J_s, lf.attrs["J_s_exp"], n_bootstrap=N_BOOT, rng=rng_for(2008, "report", "load_delta_f"))
    assert q["delta_F_opt"]["value"] == pytest.approx(lk.attrs["delta_F_opt"], rel=1e-12, abs=0)
    assert q["delta_F_opt"]["std"] == pytest.approx(lk.attrs["delta_F_opt_std"], rel=1e-12, abs=0)

    for key, paper in [("delta_opt", 0.45), ("r1_opt", 18.0), ("r2_opt", 20.0), ("delta_F_opt", 0.04)]:
        assert q[key]["paper"] == paper
        assert q[key]["comment"].startswith(("Agrees", "Differs"))
    assert s["missing"] == [] and set(s["stages"].values()) == {"ok"}


def test_response_metrics(full):
    groups, _, s = full
    r = s["details"]["response"]
    assert r["sensor"] == "P_obs" and r["delta_opt_used"] == 0.45
    # the synthetic mean model is off by a factor 2 on the moment part above 35 Hz only
    assert r["mean_model_log10_error_35_100_hz"] > r["mean_model_log10_error_0_35_hz"]
    # coverage: recomputed independently from the stored arrays (quantile band, bins 0 < f <= band)
    resp = groups["response"]
    sto = resp.psd_stochastic.real
    ref = resp.psd_reference.real.mean("realisation_ref")
    if "sensor" in sto.dims:
        sto = sto.isel(sensor=0, sensor_=0)
        ref = ref.isel(sensor=0, sensor_=0)
    lo, hi = sto.quantile(0.025, "realisation"), sto.quantile(0.975, "realisation")
    f = ref.frequency.values
    sel = (f > 0) & (f <= r["band_hz"])
    inside = ((ref >= lo) & (ref <= hi)).values[sel]
    assert r["confidence_region_coverage"] == pytest.approx(float(np.mean(inside)), abs=1e-12)


def test_markdown_table(full):
    _, out, s = full
    md = (out / "summary.md").read_text()
    assert "| quantity | identified | ± MC std |" in md
    for row in ("δ_opt", "r1,opt", "r2,opt", "δ_F,opt"):
        line = next(li for li in md.splitlines() if li.startswith(f"| {row}"))
        assert line.count("|") == 8
    assert f"{s['quantities']['r1_opt']['value']:.4g}" in md
    assert "| 0.45 |" in md and "| 18 |" in md and "| 20 |" in md and "| 0.04 |" in md
    assert "Missing" not in md


def test_missing_and_partial_stages_are_reported(tmp_path):
    groups = _groups(nan_realisations=10)
    store = _write(tmp_path / "partial.zarr", {"delta": groups["delta"], "load_r": groups["load_r"]})
    out = tmp_path / "out"
    assert _run(store, out) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["figures"] == ["fig5_delta_likelihood.png"]
    assert s["stages"]["delta"] == "ok"
    for name in ("response", "load_r", "load_delta_f"):
        assert s["stages"][name].startswith("missing")
    assert any("response.psd_reference" in m for m in s["missing"])  # load_r needs the experimental PSD
    assert any("30 of 40 realisations" in n for n in s["notes"])
    ok = groups["delta"].isel(realisation=slice(0, 30))
    curve = likelihood_curve(ok.J, 3.4e-9, ok.delta.values, "delta", n_bootstrap=N_BOOT,
                             rng=rng_for(2008, "report", "delta"))
    assert s["quantities"]["delta_opt"]["value"] == pytest.approx(curve.attrs["argmax"], rel=1e-12, abs=0)
    assert "r1_opt" not in s["quantities"]
    md = (out / "summary.md").read_text()
    assert "## Missing or incomplete stages" in md and "load_delta_f" in md
    assert "| r1,opt (force T) | missing |" in md
    assert not (out / "d_map.png").exists()


def test_real_scalar_psds_give_the_same_report(tmp_path, full):
    _, _, complex_summary = full
    store = _write(tmp_path / "real.zarr", _groups(real=True))
    assert _run(store, tmp_path / "out") == 0
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    for key in ("r1_opt", "r2_opt"):
        assert s["quantities"][key]["value"] == pytest.approx(complex_summary["quantities"][key]["value"], rel=1e-10, abs=0)
    assert s["details"]["response"]["confidence_region_coverage"] == pytest.approx(
        complex_summary["details"]["response"]["confidence_region_coverage"], abs=0)
    assert sorted(s["figures"]) == sorted(FIGURES)


def test_j_s_exp_falls_back_to_the_reference_psd(tmp_path):
    groups = _groups()
    groups["load_delta_f"].attrs = {}
    store = _write(tmp_path / "nojs.zarr", groups)
    assert _run(store, tmp_path / "out") == 0
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert s["details"]["load_delta_f"]["J_s_exp_source"].startswith("computed from response.psd_reference")


def test_unknown_store_is_a_clean_error(tmp_path, capsys):
    assert main(["report", str(tmp_path / "nope.zarr")]) == 2
    assert "no such Zarr store" in capsys.readouterr().err


def test_a_short_stochastic_response_is_noted_not_fatal(tmp_path):
    groups = _groups()
    sto = groups["response"]["psd_stochastic"]
    groups["response"]["psd_stochastic"] = sto.where(sto.realisation < 1)  # one complete realisation only
    store = _write(tmp_path / "short.zarr", {"response": groups["response"]})
    assert _run(store, tmp_path / "out") == 0
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert s["stages"]["response"] == "ok" and s["figures"] == ["fig4_mean_model.png"]
    assert any("psd_stochastic not used" in n for n in s["notes"])
