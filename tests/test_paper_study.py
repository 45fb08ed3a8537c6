"""The paper study end to end at its quick size: pipeline → store → report (proof of identification).

The experiment is the stochastic simplified model with known δ = 0.3 (``--set experiment=synthetic``).
At the quick size only δ is identifiable: its 100 J observations against 60 realisations per δ give
a bootstrap spread (model realisations and observations resampled) of about 0.03 (measured 0.282 ±
0.028): the tolerance is 3 bootstrap σ. r and δ_F need the paper size (2 realisations of 40 s per grid
point cannot hold them); their recovery at small size is tested in ``test_load_identification.py``.
"""

import json
import pathlib

import pytest

from tubeid.report import make_report
from tubeid.runner import open_pipeline, run

STUDY = pathlib.Path(__file__).resolve().parents[1] / "studies" / "paper.py"


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    path = tmp_path_factory.mktemp("paper") / "paper.zarr"
    run(STUDY, path, workers=0, quiet=True, overrides={"size": "quick", "experiment": "synthetic", "distance": "bands"})
    return path


def test_every_stage_is_stored_with_labels(store):
    res = open_pipeline(store)
    assert list(res) == ["delta", "reference", "response", "load_r", "load_r_fine", "load_delta_f"]
    assert res["delta"].J.dims == ("delta", "realisation")
    assert res["load_r"].psd.dims == ("r1", "r2", "realisation", "frequency")
    assert res["reference"].psd_reference.sizes["experiment"] == 32
    assert res["load_r"].r1.attrs.get("units") == "N^2/Hz"
    params = json.loads(res["load_delta_f"].attrs["parameters"])
    assert params["r1"] > 0 and params["r2"] > 0 and len(params["J_s_exp"]) == 32


def test_report_recovers_delta_and_compares_with_the_truth(store, tmp_path):
    s = make_report(str(store), tmp_path, n_bootstrap=50)
    assert s["target_label"] == "truth" and s["target_values"]["delta_opt"] == 0.3
    q = s["quantities"]["delta_opt"]
    assert 0 < q["std"] < 0.06 and abs(q["value"] - 0.3) < 3 * q["std"], q
    lr = s["details"]["load_r"]
    assert lr["distance"] == "bands" and {"r_opt_paper", "r_opt_relative", "r_opt_bands"} <= set(lr)
    for key in ("r1_opt", "r2_opt"):  # quick size: too coarse to hold r, but it must be a number on the grid
        r = s["quantities"][key]
        g = lr[f"{key[:2]}_grid"]
        assert g[0] <= r["value"] <= g[1], (key, r, g)
    for name in ("fig4_mean_model.png", "fig5_delta_likelihood.png", "fig6_confidence_region.png", "d_map.png", "delta_f_likelihood.png"):
        assert (tmp_path / name).stat().st_size > 10_000
    assert "| truth |" in (tmp_path / "summary.md").read_text()


@pytest.mark.slow
def test_full_synthetic_proof_recovers_the_truth(tmp_path):
    """The full proof (paper size, ~2–4 min on 2 cores): ``experiment=synthetic``, ``distance=bands``.
    Measured: δ 0.2715 ± 0.020 (truth 0.3), r (18.83 ± 0.67, 20.08 ± 1.3) (truth (18, 20)), δ_F
    0.010 ± 0.054 (truth 0.04, a flat likelihood: the stiffness dispersion dominates J_s). Tolerances: r within 10 % (the issue's; 2.6 and 1.5 bootstrap σ), δ and δ_F within 2
    bootstrap σ (σ includes the Monte Carlo error of the model and the sampling of the observations)."""
    path = tmp_path / "synthetic.zarr"
    run(STUDY, path, quiet=True, progress=False, overrides={"experiment": "synthetic", "distance": "bands"})
    s = make_report(str(path), tmp_path / "report", n_bootstrap=200)
    q = s["quantities"]
    for key, truth in (("r1_opt", 18.0), ("r2_opt", 20.0)):
        assert abs(q[key]["value"] / truth - 1) < 0.10, (key, q[key])
    for key, truth in (("delta_opt", 0.3), ("delta_F_opt", 0.04)):
        assert 0 < q[key]["std"] and abs(q[key]["value"] - truth) <= 2 * q[key]["std"], (key, q[key])
