"""The paper, end to end (Batou & Soize 2008, sections 2–5): a pipeline of runner stages.

The reference model (MODEL.md §1) plays the real bundle: its responses under the paper's 7-point
load are the experimental data. Stages (one Zarr group each; every realisation and grid point is a
runner task; random streams keyed by the realisation, so every grid shares common random numbers):

``delta``         J(δ) Monte Carlo of the stochastic simplified model (random K_B ∈ SE+) over a δ
                  grid → p_J(J_ref; δ), δ_opt, its edge flag and flatness verdict (Figure 5).
``reference``     the "experiment": the reference model and the mean simplified model under the
                  same 7-point load history → response PSDs at P_obs (Figure 4).
``calibration``   realisations of the experiment's generator independent of the experimental record
                  (as many as ``response``, same estimator): the reference model's own 95 % region,
                  against which the coverage of Figure 6 is calibrated (beyond the paper).
``response``      the stochastic simplified model at δ_opt under the 7-point load → 95 %
                  confidence region of the response PSD (Figure 6).
``load_r``        trial grid over r = (r1, r2) of the (T, M) load at x = 8 m, stochastic model at
                  δ_opt → D(r) map and the coarse r_opt.
``load_r_fine``   a finer grid, ± one coarse step around the coarse minimum (beyond the paper).
``load_delta_f``  J_s over a δ_F grid at (δ_opt, r_opt) → p_Js(J_s,exp; δ_F), δ_F,opt; with record
                  pairs of one structure (the synthetic experiment) also their log-level
                  differences → δ_F from the pairs (beyond the paper). Its stage parameters hold
                  r_opt of every distance on the fine grid (``r_identification``, JSON): what the
                  study passed downstream, read by ``tubeid report``.

Proof of identification: ``--set experiment=synthetic`` replaces the reference model by the
stochastic simplified model itself with known TRUTH (δ = 0.3 for the J observations, r = (18, 20),
δ_F = 0.04; 32 structures, each recorded twice under independent loads): the report then compares
what is identified with the truth.

The simplified model is a parameter: ``--set simplified=NAME_OR_SPEC_FILE`` (default the built-in
``paper-simplified``, MODEL.md §2). Its specification's *content* becomes the parameter's value
(JSON), so it is stored with the study and part of its hash (a changed file is never mixed with a
store made from the old one) and workers need no access to the file.

r_opt comes from ``tubeid.identification.identify_r`` (the one home of the trial method):
``--set distance=relative`` weights D(r) by the model's own PSD for the r_opt passed downstream;
``--set distance=bands`` uses the generalised least squares of the log band energies, the best
conditioned without model-form error; ``--set distance=log`` the mean squared log10 ratio.

Sizes: ``--set size=paper`` (default: 200 realisations per δ, 100 for the confidence region and
its calibration, a 10 × 10 grid of r) or ``--set size=quick`` (a look: too small to identify r or
δ_F). ``--set delta=0.45`` imposes δ for the later stages instead of δ_opt (e.g. the paper's value).
Then ``tubeid report STORE``.
"""

import functools
import json

import numpy as np

from tubeid.dynamics import warmup
from tubeid.dynamics.response import ResponseSettings, realisation_streams, simulate_responses
from tubeid.dynamics.spectra import j_s, log_level
from tubeid.errors import SpecificationError
from tubeid.identification.delta import default_delta_grid, reference_j
from tubeid.identification.likelihood import likelihood_curve
from tubeid.identification.trial import DISTANCES, fine_grid, identify_r
from tubeid.mechanics.library import builtin_spec, model_content
from tubeid.mechanics.reduction import J_UNITS, j_functional, j_of_spec, reduce
from tubeid.mechanics.spec import spec_from_dict, spec_to_dict
from tubeid.runner.pipeline import Pipeline
from tubeid.runner.study import Output, Parameter, Study, Warmup
from tubeid.uncertainty.loads import coherent_forces, force_and_moment
from tubeid.uncertainty.random_matrices import DELTA_MIN, Dispersion, delta_max
from tubeid.uncertainty.random_models import germs_from_rngs, random_subsystem

REFERENCE = reduce(builtin_spec("paper-reference"))
BAND = 100.0


class ModelParameter(Parameter):
    """A bundle model given as a built-in name or a .yaml/.toml file; its value becomes the content.

    ``check`` turns the name or path into canonical JSON text ``{"source": ..., "spec": {...}}`` (the
    specification's fields): that text is what the stages receive, store and hash. JSON text already
    in that form is validated and passed through, so the check is idempotent (workers receive it).
    The model must observe the reference's point: subsystem A on the tube ``centre``, its first
    sensor where the reference's P_obs is, and the reference's band.
    """

    def check(self, name, value):
        field = f"parameters.{name}"
        text, spec = model_content(field, value)
        ref = REFERENCE.spec
        p_obs = ref.sensors[0]
        if spec.a_tube != "centre":
            raise SpecificationError(f"{field}: nonlinear tube", spec.a_tube, "must be 'centre' (the reference's subsystem A)")
        if not spec.sensors or (spec.sensors[0].tube, spec.sensors[0].x) != (p_obs.tube, p_obs.x):
            raise SpecificationError(f"{field}: sensors[0]", spec.sensors[0] if spec.sensors else None,
                                     f"must observe the reference's {p_obs.name} (tube {p_obs.tube!r}, x = {p_obs.x:g} m)")
        if spec.band_hz != ref.band_hz:
            raise SpecificationError(f"{field}: band_hz", spec.band_hz, f"must be the reference's {ref.band_hz:g} Hz")
        try:  # the stages compute J of its B: defined (e.g. B damped), refused here rather than in the first block
            j_of_spec(spec, _model(text).subsystem)
        except SpecificationError as exc:
            raise SpecificationError(f"{field}: {exc.field}", exc.value, exc.rule) from None
        return text


@functools.lru_cache(maxsize=4)
def _model(simplified: str):
    """The reduced simplified model of a ``simplified`` parameter value (its JSON content)."""
    return reduce(spec_from_dict(json.loads(simplified)["spec"]))


SIZES = {
    # δ grid step, J realisations per δ, realisations for the confidence region, r grid size per axis,
    # realisations per r (coarse grid), fine r grid size, realisations per fine r, realisations per δ_F,
    # record length (s)
    "paper": dict(delta_step=0.025, n_j=200, n_response=100, n_r=10, n_per_r=4, n_fine=5, n_per_r_fine=32, n_per_delta_f=40,
                  duration=220.0),
    "quick": dict(delta_step=0.05, n_j=60, n_response=12, n_r=4, n_per_r=2, n_fine=3, n_per_r_fine=2, n_per_delta_f=8,
                  duration=40.0),
}
TRUTH = {"delta": 0.3, "r1": 18.0, "r2": 20.0, "delta_F": 0.04}  # the synthetic experiment
N_RECORDS = {"reference": 1, "synthetic": 32}  # experimental records (the paper has one)
N_J_OBSERVATIONS = 100  # synthetic J observations for the model-to-model step (closed form: cheap)
R_RANGE = (1.0, 1000.0)  # N²/Hz and (N·m)²/Hz: the coarse grid spans three decades
# δ_F ∈ (0, √(3/7) = 0.655): dense near 0, where the paper finds 0.04
DELTA_F_GRID = {"paper": [0.005, 0.01, 0.02, 0.03, 0.04, 0.06, 0.09, 0.14, 0.22, 0.35, 0.5], "quick": [0.01, 0.04, 0.16, 0.4]}


def _settings(size):
    return ResponseSettings(duration=SIZES[size]["duration"], discard=2.0, segment_seconds=8.0)


def _frequencies(size):
    """The stored frequency grid: the Welch bins in the band (computed by the same estimator)."""
    from tubeid.dynamics.spectra import psd_matrix

    st = _settings(size)
    f, _ = psd_matrix(np.zeros((int(st.segment_seconds / st.output_dt) + 2, 1)), st.output_dt, segment_seconds=st.segment_seconds)
    return f[f <= BAND]


def _streams(rng, axis, reals, repeat):
    """The base generators of the block's realisations and, for a repeat, the structure's.

    A repeat is a second record of the same structure: B's germs from the first record's stream 0
    (``realisation_streams``), the load spectrum and history from the independent stream "repeat".
    """
    if not repeat:
        return [rng.at({axis: r}) for r in reals], None
    return ([rng.at({axis: r}, "repeat") for r in reals],
            [realisation_streams(None, r, rng.at({axis: r}))[0] for r in reals])


def _psd_block(model, load, block, rng, *, size, dispersion, load_dispersion=0.0, axis="realisation", repeat=False):
    """P_obs auto-PSD (first sensor) of one realisation per coordinate of ``axis`` in the block."""
    reals = [int(r) for r in block[axis]]
    rngs, system = _streams(rng, axis, reals, repeat)
    ds = simulate_responses(model, load, reals, rngs=rngs, dispersion=dispersion, load_dispersion=load_dispersion,
                            settings=_settings(size), system_rngs=system)
    return ds.psd.real.sel(frequency=ds.frequency <= BAND).values[..., 0, 0]  # one sensor: P_obs


# -- stage 1: δ ------------------------------------------------------------------------------------
def j_block(block, rng, *, size, experiment, simplified):
    sub = _model(simplified).subsystem
    germs = germs_from_rngs(sub.n, [rng.at({"realisation": int(r)}) for r in block["realisation"]])
    out = np.empty((len(block["delta"]), len(block["realisation"])))
    for i, d in enumerate(block["delta"]):
        M, D, K = random_subsystem(sub, Dispersion(stiffness=float(d)), 0, block["realisation"], germs=germs)
        out[i] = j_functional(M, D, K, sub.n_c, BAND)
    return {"J": out}


def _j_observed(experiment, simplified):
    """J_ref of the reference model, or J observations of the synthetic experiment (joint likelihood)."""
    if experiment == "reference":
        return reference_j("paper-reference")
    from tubeid.uncertainty.random_models import random_j

    sub = _model(simplified).subsystem
    return [float(v) for v in random_j(sub, Dispersion(stiffness=TRUTH["delta"]), 7, range(10**6, 10**6 + N_J_OBSERVATIONS), BAND)]


def summarize_delta(ds):
    params = json.loads(ds.attrs["parameters"])
    j_obs = _j_observed(params["experiment"], params["simplified"])
    lik = likelihood_curve(ds.J, j_obs, ds.delta.values, "delta", n_bootstrap=200, rng=1)
    a = lik.attrs
    return {"J_ref": j_obs, "delta_opt": a["argmax"], "delta_opt_std": a["argmax_std"],
            "delta_opt_at_grid_edge": bool(a["argmax_at_boundary"]), "delta_likelihood_flat": bool(a["flat"]),
            "delta_lr_interval": [a["lr_interval_low"], a["lr_interval_high"]]}


def delta(results, *, size, experiment, simplified):
    s = SIZES[size]
    sub = _model(simplified).subsystem
    return Study(
        name="delta",
        description="J(delta) Monte Carlo of the stochastic simplified model (random K_B)",
        seed=2008,
        axes={"delta": np.round(default_delta_grid(sub.n, s["delta_step"]), 4), "realisation": range(s["n_j"])},
        chunks={"delta": 64, "realisation": 50},
        seed_axes=("realisation",),
        task=j_block,
        outputs={"J": Output(units=J_UNITS, long_name="J = integral of ||Z(w)^-1||_F^2 over the band")},
        units={"delta": "1"},
        parameters={"size": size, "experiment": experiment, "simplified": simplified},
        model=spec_to_dict(_model(simplified).spec),
        summarize=summarize_delta,
    )


def _admissible(d, simplified):
    """``d`` if it lies in [DELTA_MIN, δ_max) of the simplified model's reduced B (the draws' floor:
    ``tubeid.uncertainty.random_matrices.DELTA_MIN``), else refused."""
    dmax = delta_max(_model(simplified).subsystem.n)
    if not DELTA_MIN <= d < dmax:
        raise SpecificationError("parameters.delta", d, f"must lie in [{DELTA_MIN:g}, {dmax:.4f}), the admissible set "
                                                        "of the simplified model's reduced B (below "
                                                        f"{DELTA_MIN:g} the draws lose their dispersion to round-off)")
    return d


def _delta_for(results, delta, simplified):
    """δ of the later stages: imposed (``--set delta``, > 0) or δ_opt of stage ``delta``."""
    return _admissible(float(delta) if delta > 0 else float(results["delta"].attrs["delta_opt"]), simplified)


class DeltaParameter(Parameter):
    """``delta``: 0 (δ_opt of stage ``delta``) or an imposed δ, which must lie below δ_max of the model
    that parameter ``simplified`` names: checked with it when the study is loaded, before any stage runs."""

    def check_with(self, name, value, values):
        if value > 0:
            _admissible(value, values["simplified"])


# -- stage 2: the experiment and the mean model ------------------------------------------------------
def _experiment_load(experiment):
    return coherent_forces() if experiment == "reference" else force_and_moment(TRUTH["r1"], TRUTH["r2"], x=8.0, band=BAND)


def _experiment_psd(block, rng, *, size, experiment, simplified, axis, repeat=False):
    """PSDs of the experiment's generator: the reference model, or the synthetic truth."""
    load = _experiment_load(experiment)
    if experiment == "reference":
        return _psd_block(REFERENCE, load, block, rng, size=size, dispersion=Dispersion(), axis=axis)
    return _psd_block(_model(simplified), load, block, rng, size=size, dispersion=Dispersion(stiffness=TRUTH["delta"]),
                      load_dispersion=TRUTH["delta_F"], axis=axis, repeat=repeat)


def reference_block(block, rng, *, size, experiment, simplified):
    ref = _experiment_psd(block, rng, size=size, experiment=experiment, simplified=simplified, axis="experiment")
    mean = _psd_block(_model(simplified), _experiment_load(experiment), block, rng, size=size, dispersion=Dispersion(),
                      axis="experiment")
    out = {"psd_reference": ref, "psd_mean": mean}
    if experiment == "synthetic":  # a second record of each record's structure: δ_F from the pairs
        out["psd_repeat"] = _experiment_psd(block, rng, size=size, experiment=experiment, simplified=simplified,
                                            axis="experiment", repeat=True)
    return out


def summarize_reference(ds):
    """The PSD estimator of every record of the study and, in a synthetic experiment, the truth the
    later stages must recover (read by ``tubeid report``)."""
    params = json.loads(ds.attrs["parameters"])
    st = _settings(params["size"])
    out = {"record_seconds": st.duration, "segment_seconds": st.segment_seconds,
           "estimator": f"Welch, Hann window, {st.segment_seconds:g} s segments, 50 % overlap, two-sided per Hz; "
                        f"records of {st.duration:g} s simulated, the first {st.discard:g} s discarded"}
    if params["experiment"] == "synthetic":
        out.update(truth_delta_opt=TRUTH["delta"], truth_r1_opt=TRUTH["r1"], truth_r2_opt=TRUTH["r2"],
                   truth_delta_F_opt=TRUTH["delta_F"])
    return out


def reference(results, *, size, experiment, simplified):
    return Study(
        name="reference",
        description=("reference model (the experiment) and mean simplified model, same 7-point load history" if experiment == "reference"
                     else f"synthetic experiment: stochastic simplified model with known {TRUTH}; mean simplified model, same load history"),
        seed=2008,
        axes={"experiment": range(N_RECORDS[experiment])},
        task=reference_block,
        coords={"frequency": _frequencies(size)},
        outputs={
            "psd_reference": Output(dims=("frequency",), units="m^2/Hz", long_name="PSD at P_obs, reference model (two-sided)"),
            "psd_mean": Output(dims=("frequency",), units="m^2/Hz", long_name="PSD at P_obs, mean simplified model (two-sided)"),
            **({"psd_repeat": Output(dims=("frequency",), units="m^2/Hz",
                                     long_name="PSD at P_obs, a second record of the same structure under an "
                                               "independent load (two-sided)")} if experiment == "synthetic" else {}),
        },
        units={"frequency": "Hz"},
        parameters={"size": size, "experiment": experiment, "simplified": simplified},
        model=spec_to_dict(REFERENCE.spec if experiment == "reference" else _model(simplified).spec),
        summarize=summarize_reference,
    )


# -- stage 2b: the calibration of the coverage -------------------------------------------------------
def calibration_block(block, rng, *, size, experiment, simplified):
    return {"psd": _experiment_psd(block, rng, size=size, experiment=experiment, simplified=simplified, axis="realisation")}


def calibration(results, *, size, experiment, simplified):
    """Independent realisations of the experiment's generator (its streams are this stage's, never the
    record's): their 95 % region is the reference model's own, at the response stage's count and
    estimator, so the fraction of bins where it holds the experimental record calibrates Figure 6's."""
    return Study(
        name="calibration",
        description=("reference model under independent 7-point load histories (its own 95 % region)" if experiment == "reference"
                     else "independent realisations of the synthetic experiment's generator (its own 95 % region)"),
        seed=2008,
        axes={"realisation": range(SIZES[size]["n_response"])},
        chunks={"realisation": 4},
        task=calibration_block,
        coords={"frequency": _frequencies(size)},
        outputs={"psd": Output(dims=("frequency",), units="m^2/Hz", long_name="PSD at P_obs of the experiment's generator (two-sided)")},
        units={"frequency": "Hz"},
        parameters={"size": size, "experiment": experiment, "simplified": simplified},
        model=spec_to_dict(REFERENCE.spec if experiment == "reference" else _model(simplified).spec),
    )


# -- stage 3: confidence region ---------------------------------------------------------------------
def response_block(block, rng, *, size, delta, experiment, simplified):
    return {"psd": _psd_block(_model(simplified), _experiment_load(experiment), block, rng, size=size,
                              dispersion=Dispersion(stiffness=delta))}


def response(results, *, size, delta, experiment, simplified):
    d = _delta_for(results, delta, simplified)
    return Study(
        name="response",
        description=f"stochastic simplified model at delta = {d:.4f} under the 7-point load",
        seed=2008,
        axes={"realisation": range(SIZES[size]["n_response"])},
        chunks={"realisation": 4},
        task=response_block,
        coords={"frequency": _frequencies(size)},
        outputs={"psd": Output(dims=("frequency",), units="m^2/Hz", long_name="PSD at P_obs (two-sided)")},
        units={"frequency": "Hz"},
        parameters={"size": size, "delta": d, "experiment": experiment, "simplified": simplified},
        model=spec_to_dict(_model(simplified).spec),
    )


# -- stage 4: trial grid of r ------------------------------------------------------------------------
def r_block(block, rng, *, size, delta, simplified):
    out = np.empty((len(block["r1"]), len(block["r2"]), len(block["realisation"]), len(_frequencies(size))))
    for i, r1 in enumerate(block["r1"]):
        for j, r2 in enumerate(block["r2"]):
            out[i, j] = _psd_block(_model(simplified), force_and_moment(float(r1), float(r2), x=8.0, band=BAND), block, rng,
                                   size=size, dispersion=Dispersion(stiffness=delta))
    return {"psd": out}


def _r_study(name, r1, r2, size, d, n_per_r, simplified, what=""):
    return Study(
        name=name,
        description=f"trial grid of r = (r1, r2), (T, M) load at x = 8 m, stochastic model at delta = {d:.4f}{what}",
        seed=2008,
        axes={"r1": np.round(r1, 6), "r2": np.round(r2, 6), "realisation": range(n_per_r)},
        chunks={"r1": 1, "r2": 1},
        seed_axes=("realisation",),
        task=r_block,
        coords={"frequency": _frequencies(size)},
        outputs={"psd": Output(dims=("frequency",), units="m^2/Hz", long_name="PSD at P_obs (two-sided)")},
        units={"r1": "N^2/Hz", "r2": "(N m)^2/Hz", "frequency": "Hz"},
        parameters={"size": size, "delta": d, "simplified": simplified},
        model=spec_to_dict(_model(simplified).spec),
    )


def load_r(results, *, size, delta, simplified):
    n = SIZES[size]["n_r"]
    grid = np.geomspace(*R_RANGE, n)
    return _r_study("load_r", grid, grid, size, _delta_for(results, delta, simplified), SIZES[size]["n_per_r"], simplified)


def _experiment(results):
    """The experimental PSD at P_obs, records on ``record`` (several records: averaged and bootstrapped)."""
    return results["reference"].psd_reference.rename(experiment="record")


def _band(results):
    return float(results["reference"].frequency[-1])


def identify_coarse(results, distance):
    """r on the coarse grid (stage ``load_r``) by ``distance``: the centre of the fine grid and, for
    ``relative``, the weight (the coarse grid's mean PSD at the paper D's minimum) of both passes."""
    return identify_r(results["load_r"].psd, _experiment(results), distance=distance, band_hz=_band(results), refine=False)


def identify_fine(results, distance, n_bootstrap=0, rng=None):
    """r_opt on the fine grid (stage ``load_r_fine``) by ``distance``, refined, with the coarse pass's
    weight for ``relative``: the r_opt the study passes downstream (``tubeid.identification.identify_r``)."""
    weight = identify_coarse(results, "relative").weight_psd if distance == "relative" else None
    return identify_r(results["load_r_fine"].psd, _experiment(results), distance=distance, band_hz=_band(results),
                      weight_psd=weight, n_bootstrap=n_bootstrap, rng=rng)


def load_r_fine(results, *, size, delta, distance, simplified):
    coarse = identify_coarse(results, distance)
    grid = fine_grid(coarse, SIZES[size]["n_fine"])  # ± one coarse step around the coarse minimum
    r1c, r2c = coarse.attrs["r_opt_discrete"]
    return _r_study("load_r_fine", grid["r1"], grid["r2"], size, _delta_for(results, delta, simplified),
                    SIZES[size]["n_per_r_fine"], simplified,
                    f", around the coarse minimum ({r1c:.6g}, {r2c:.6g}) of the {distance} distance")


# -- stage 5: δ_F -----------------------------------------------------------------------------------
def delta_f_block(block, rng, *, size, delta, r1, r2, J_s_exp, simplified, distance, r_identification,
                  level_difference_exp=None):
    """J_s per (δ_F, realisation) and, when the experiment has repeated records (``level_difference_exp``
    given), the log-level difference of two records of one structure (``_streams``); ``distance`` and
    ``r_identification`` are provenance (what r is)."""
    load = force_and_moment(r1, r2, x=8.0, band=BAND)
    st = _settings(size)
    reals = [int(r) for r in block["realisation"]]
    pairs = level_difference_exp is not None
    out = {"J_s": np.empty((len(block["delta_F"]), len(reals)))}
    if pairs:
        out["level_difference"] = np.empty_like(out["J_s"])
    for i, dF in enumerate(block["delta_F"]):
        def p_obs(repeat):
            rngs, system = _streams(rng, "realisation", reals, repeat)
            ds = simulate_responses(_model(simplified), load, reals, rngs=rngs, dispersion=Dispersion(stiffness=delta),
                                    load_dispersion=float(dF), settings=st, system_rngs=system)
            sel = ds.frequency.values <= BAND  # the stored grid of the other stages: the same bins
            return ds.frequency.values[sel], ds.psd.values[:, sel, :1, :1]  # P_obs, like the experiment's
        f, P = p_obs(False)
        out["J_s"][i] = [j_s(f, P[k], band=f[-1]) for k in range(len(reals))]
        if pairs:
            out["level_difference"][i] = log_level(f, P.real, BAND) - log_level(f, p_obs(True)[1].real, BAND)
    return out


def summarize_delta_f(ds):
    params = json.loads(ds.attrs["parameters"])
    j_exp = params["J_s_exp"]
    lik = likelihood_curve(ds.J_s, j_exp, ds.delta_F.values, "delta_F", n_bootstrap=200, rng=1)
    a = lik.attrs
    out = {"J_s_exp": j_exp[0] if len(j_exp) == 1 else j_exp, "delta_F_opt": a["argmax"], "delta_F_opt_std": a["argmax_std"],
           "delta_F_opt_at_grid_edge": bool(a["argmax_at_boundary"]), "delta_F_likelihood_flat": bool(a["flat"]),
           "r_opt": [params["r1"], params["r2"]], "r_distance": params["distance"]}
    d_exp = params.get("level_difference_exp")
    if d_exp is not None:
        a = likelihood_curve(ds.level_difference, d_exp, ds.delta_F.values, "delta_F", n_bootstrap=200, rng=1,
                             variance_corrected=True).attrs  # δ_F sets the spread: the kernel must not widen it
        out.update(level_difference_exp=d_exp, delta_F_pairs_opt=a["argmax"], delta_F_pairs_opt_std=a["argmax_std"],
                   delta_F_pairs_opt_at_grid_edge=bool(a["argmax_at_boundary"]),
                   delta_F_pairs_likelihood_flat=bool(a["flat"]),
                   delta_F_pairs_lr_interval=[a["lr_interval_low"], a["lr_interval_high"]])
    return out


def r_identification(results):
    """r_opt of every distance (point estimates, JSON-ready): on the fine grid (placed for the study's
    distance) and, refined, on the coarse grid (where another distance's minimum may lie)."""
    out = {}
    for name in DISTANCES:
        try:
            a = identify_fine(results, name).attrs
            weight = identify_coarse(results, "relative").weight_psd if name == "relative" else None
            c = identify_r(results["load_r"].psd, _experiment(results), distance=name, band_hz=_band(results),
                           weight_psd=weight).attrs
        except SpecificationError as exc:  # e.g. a band without energy: say so instead of failing the study
            out[name] = {"error": str(exc)}
            continue
        out[name] = {"r_opt": a["r_opt"], "r_opt_discrete": a["r_opt_discrete"], "at_grid_edge": a["r_opt_at_boundary"],
                     "D_min": a["D_min"], "D_units": a["D_units"], "weight_source": a["weight_source"],
                     "coarse": {"r_opt": c["r_opt"], "r_opt_discrete": c["r_opt_discrete"],
                                "at_grid_edge": c["r_opt_at_boundary"]}}
    return out


def load_delta_f(results, *, size, delta, distance, simplified):
    ident = r_identification(results)
    if "error" in ident[distance]:
        raise SpecificationError("parameters.distance", distance, f"cannot identify r: {ident[distance]['error']}")
    r1, r2 = (float(v) for v in ident[distance]["r_opt"])
    ref = results["reference"]
    f = ref.frequency.values
    j_exp = [float(j_s(f, rec[:, None, None], band=f[-1])) for rec in ref.psd_reference.values]  # one per record
    extra, outputs = {}, {}
    if "psd_repeat" in ref:  # records in pairs of one structure: the log-level difference of each pair
        extra["level_difference_exp"] = [float(log_level(f, a, BAND) - log_level(f, b, BAND))
                                         for a, b in zip(ref.psd_reference.values, ref.psd_repeat.values)]
        outputs["level_difference"] = Output(units="1", long_name="log level of a record minus that of a second record "
                                                                  "of the same structure (tubeid.dynamics.log_level)")
    d = _delta_for(results, delta, simplified)
    s = SIZES[size]
    return Study(
        name="load_delta_f",
        description=f"J_s over a delta_F grid at delta = {d:.4f}, r = ({r1:.4g}, {r2:.4g})",
        seed=2008,
        axes={"delta_F": DELTA_F_GRID[size], "realisation": range(s["n_per_delta_f"])},
        chunks={"delta_F": 1, "realisation": 4},
        seed_axes=("realisation",),
        task=delta_f_block,
        outputs={"J_s": Output(units="(m^2/Hz)^2 rad/s", long_name="J_s = integral of ||S_Z(w)||_F^2 over the band"),
                 **outputs},
        units={"delta_F": "1"},
        parameters={"size": size, "delta": d, "r1": r1, "r2": r2, "J_s_exp": j_exp, "simplified": simplified,
                    "distance": distance, "r_identification": json.dumps(ident, sort_keys=True), **extra},
        model=spec_to_dict(_model(simplified).spec),
        summarize=summarize_delta_f,
    )


study = Pipeline(
    name="paper",
    seed=2008,
    description=__doc__.splitlines()[0],
    stages=[delta, reference, calibration, response, load_r, load_r_fine, load_delta_f],
    warmup=Warmup(warmup.MESSAGE, run=warmup.compile_solver, needed=warmup.cache_is_cold),
    parameters={
        "size": Parameter("paper", choices=("paper", "quick"), doc="sample sizes: the paper's, or a quick look"),
        "delta": DeltaParameter(0.0, bounds=(0.0, 1.0), doc="delta for the later stages; 0 = delta_opt of stage 'delta' "
                                                       "(must be below the simplified model's delta_max)"),
        "experiment": Parameter("reference", choices=("reference", "synthetic"), doc="the paper's reference model, or the simplified model with known TRUTH"),
        "distance": Parameter("paper", choices=tuple(DISTANCES),
                              doc="D(r) for r_opt (tubeid.identification.DISTANCES): the paper's, weighted by 1/S of the model, "
                                  "GLS of log band energies, or mean squared log10 ratio"),
        "simplified": ModelParameter("paper-simplified", doc="the simplified model: a built-in name or a .yaml/.toml file "
                                                             "(stored and hashed as its content)"),
    },
)
