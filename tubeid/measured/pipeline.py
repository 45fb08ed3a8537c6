"""The runner pipeline of ``tubeid diagnose`` (the method: :mod:`tubeid.measured.diagnose`).

Run by :func:`tubeid.measured.diagnose.diagnose` into ``DIR/diagnose.zarr`` (one Zarr group per
stage); its parameters are plain text: ``data`` (path of the validated record written into DIR),
``data_sha256`` (its content hash, checked by every process that reads it), ``model`` (the
declared model, JSON of ``spec_to_dict``) and ``settings`` (``DiagnoseSettings.to_json()``). All
four are hashed into the store's identity: other data, model or settings never reuse a store.
Every grid point and every Monte Carlo realisation is a runner task; a stage with nothing to
compute (δ_F given, nothing to trace, no effect chosen) holds one ``skipped`` placeholder whose
coordinate says why.

Stages (random streams keyed by the stage, the settings' seed and, where named, the realisation;
trials of one grid share one stream: common random numbers):

``load_r``           coarse trial grid of r, mean model, fitting blocks → log-spectral distance
``load_r_fine``      fine grid around the levelled coarse minimum → r_opt
``load_delta_f``     J_s of block-length records of the stochastic model at (δ, r_opt) over a δ_F
                     grid × realisations → δ_F by maximum likelihood, and the δ_F of the band
                     (the argmax, or the fallback when not identified; skipped when δ_F is given)
``band``             the model band before: stochastic model at (δ, δ_F, r_opt), held-out layout
``probe``            a tone's probe and baseline (only when ``tone`` is a candidate to fit)
``candidates``       trial grids of the leading candidates (mean model, fitting blocks)
``candidate_bands``  the band of each candidate's best trial → held-out errors, the choice
``load_r_after``     fine grid of r with the chosen effect, around the candidate's level
``band_after``       the band with the chosen effect at its r_opt
"""

import importlib
import json

import numpy as np

from tubeid.dynamics import warmup
from tubeid.dynamics.spectra import j_s, psd_matrix
from tubeid.identification.loads import JS_UNITS
from tubeid.measured.effects_fit import PARAMETER_COUNT, candidate_grid
from tubeid.mechanics.effects import effect_from_dict, effect_to_dict
from tubeid.runner.pipeline import Pipeline
from tubeid.runner.study import Output, Parameter, Study, Warmup

__all__ = ["study", "SEED"]

# the module, not the function tubeid.measured.diagnose re-exported by the package
dg = importlib.import_module("tubeid.measured.diagnose")

SEED = 6
R_DIMS = ("r1", "r2")
R_UNITS = {"r1": "N^2/Hz", "r2": "(N m)^2/Hz"}
STATISTICS = ["rms", "skewness", "excess_kurtosis"]


def _realisation_chunk(ctx, n: int) -> int:
    """Realisations per task. With δ = 0 every realisation of a call shares one set of solver
    tables (≈ 60 % of a short record's cost): two tasks, one table each; with δ > 0 each
    realisation has its own random K_B, and tasks of 2 balance the workers."""
    return 2 if ctx.settings.delta > 0 else max(2, -(-n // 2))


def _ctx(p: dict):
    return dg.load_context(p["data"], p["data_sha256"], p["model"], p["settings"])


def _base(data, data_sha256, model, settings) -> dict:
    return {"data": data, "data_sha256": data_sha256, "model": model, "settings": settings}


def _params(ds) -> dict:
    return json.loads(ds.attrs["parameters"])


def _spectral_coords(ctx) -> dict:
    return {"frequency": ctx.meas.frequency, "sensor": list(ctx.meas.sensors)}


def _psd_output(what: str) -> Output:
    return Output(dims=("frequency", "sensor"), units="m^2/Hz", long_name=f"auto-PSD at the sensors, two-sided: {what}")


def _mean_psd(ctx, r, effects, gen) -> np.ndarray:
    """Mean-model auto-PSD (F, m) on the fitting blocks, averaged over ``fit_realisations``."""
    s, meas = ctx.settings, ctx.meas
    P, _ = dg.simulate_blocks(ctx.spec, r, effects, meas, meas.n_fit_blocks, range(s.fit_realisations), s,
                              stochastic=False, rngs=[gen])
    return P.mean(axis=0)


# -- nothing to compute ---------------------------------------------------------------------------------
def nothing(block, rng):
    return {"nothing": np.zeros(len(block["skipped"]))}


def _skipped(name: str, reason: str, summarize=None) -> Study:
    return Study(name=name, seed=SEED, description=f"nothing to compute: {reason}", axes={"skipped": [reason]},
                 task=nothing, outputs={"nothing": Output(units="1", long_name="placeholder: nothing was computed")},
                 summarize=summarize)


# -- trial grids of r ---------------------------------------------------------------------------------
def r_block(block, rng, *, data, data_sha256, model, settings, effects):
    ctx = dg.load_context(data, data_sha256, model, settings)
    eff = dg.effects_from_json(effects)
    dims = [d for d in R_DIMS if d in block]
    shape = tuple(len(block[d]) for d in dims)
    meas = ctx.meas
    psd = np.empty(shape + (meas.frequency.size, len(meas.sensors)))
    dist, off = np.empty(shape), np.empty(shape)
    for idx in np.ndindex(*shape):
        r = tuple(float(block[d][i]) for d, i in zip(dims, idx))
        psd[idx] = _mean_psd(ctx, r, eff, rng(ctx.settings.seed))
        dist[idx], off[idx] = dg.r_distance(meas.fit, psd[idx], meas.frequency, ctx.spec.band_hz)
    return {"psd": psd, "distance": dist, "offset": off}


def _r_minimum(ds, refine):
    dims = [d for d in R_DIMS if d in ds.dims]
    d = ds["distance"].transpose(*dims).values
    r, idx, boundary = dg.grid_minimum(d, [ds[x].values for x in dims], refine=refine)
    return r, idx, boundary, ds["offset"].transpose(*dims).values[idx], d[idx], dims


def summarize_r_coarse(ds):
    r, idx, boundary, off, d, dims = _r_minimum(ds, refine=False)
    return {"r_best": list(r), "offset_best": float(off), "distance_best": float(d), "at_boundary": boundary,
            "r_next": list(dg.scaled_r(r, off))}


def summarize_r_fine(ds):
    r, idx, boundary, off, d, dims = _r_minimum(ds, refine=True)
    return {"r_opt": list(r), "r_discrete": [float(ds[x].values[i]) for x, i in zip(dims, idx)],
            "distance_opt": float(d), "offset_opt": float(off), "at_boundary": boundary}


def _r_study(name, base, ctx, grid, effects, what, summarize) -> Study:
    axes = dict(zip(R_DIMS, grid))
    return Study(
        name=name, seed=SEED,
        description=f"{what}: trial grid of r ({ctx.settings.load} load), mean model, fitting blocks; log-spectral distance",
        axes=axes, chunks={d: 1 for d in axes}, seed_axes=(), task=r_block,
        coords=_spectral_coords(ctx),
        outputs={"psd": _psd_output("mean model, fitting blocks"),
                 "distance": Output(units="decades^2", long_name="mean squared log10 distance to the fitting PSD, 0 < f <= band"),
                 "offset": Output(units="decades", long_name="mean log10(measured / model) over the same bins")},
        units={**{d: R_UNITS[d] for d in axes}, "frequency": "Hz"},
        parameters={**base, "effects": effects}, summarize=summarize)


def load_r(results, *, data, data_sha256, model, settings):
    base = _base(data, data_sha256, model, settings)
    ctx = _ctx(base)
    s = ctx.settings
    return _r_study("load_r", base, ctx, dg.r_coarse_grid(s.start_r, s.r_points, s.r_step), "[]",
                    "coarse", summarize_r_coarse)


def load_r_fine(results, *, data, data_sha256, model, settings):
    base = _base(data, data_sha256, model, settings)
    ctx = _ctx(base)
    s = ctx.settings
    centre = results["load_r"].attrs["r_next"]
    return _r_study("load_r_fine", base, ctx, dg.r_fine_grid(centre, s.r_fine_points, s.r_fine_span), "[]",
                    "fine, around the levelled coarse minimum", summarize_r_fine)


# -- δ_F ----------------------------------------------------------------------------------------------
def delta_f_block(block, rng, *, data, data_sha256, model, settings, r):
    ctx = dg.load_context(data, data_sha256, model, settings)
    s, meas = ctx.settings, ctx.meas
    reals = [int(k) for k in block["realisation"]]
    out = np.empty((len(block["delta_F"]), len(reals)))
    for i, dF in enumerate(block["delta_F"]):
        y = dg.simulate_series(ctx.spec, r, (), meas, meas.block_samples, reals, s, stochastic=True,
                               load_dispersion=float(dF), rngs=[rng(s.seed, realisation=k) for k in reals])
        f, S = psd_matrix(y, meas.dt, segment_seconds=s.segment_seconds)
        out[i] = j_s(f, S, band=ctx.spec.band_hz)
    return {"J_s": out}


def summarize_delta_f(ds):
    ctx = _ctx(_params(ds))
    if dg.skipped(ds):
        v = float(ctx.settings.load_dispersion)
        return {"delta_F": v, "delta_F_used": v, "delta_F_given": True}
    out = dg.delta_f_identification(ds["J_s"], ctx.j_s_observed, ctx.m, ctx.settings)
    out["delta_F_given"] = False
    return out


def load_delta_f(results, *, data, data_sha256, model, settings):
    base = _base(data, data_sha256, model, settings)
    ctx = _ctx(base)
    s = ctx.settings
    if s.load_dispersion is not None:
        return _given_delta_f(base)
    r = [float(v) for v in results["load_r_fine"].attrs["r_opt"]]
    grid = list(ctx.delta_f_grid)
    return Study(
        name="load_delta_f", seed=SEED,
        description=f"J_s of one block's length ({ctx.meas.block_samples * ctx.meas.dt:.4g} s) of the stochastic model at "
                    f"delta = {s.delta}, r = {r}, over a delta_F grid (common random numbers across delta_F)",
        axes={"delta_F": grid, "realisation": range(s.delta_f_realisations)},
        chunks={"delta_F": len(grid), "realisation": _realisation_chunk(ctx, s.delta_f_realisations)},
        seed_axes=("realisation",), task=delta_f_block,
        outputs={"J_s": Output(units=JS_UNITS, long_name="J_s = integral of ||S_Z(w)||_F^2 over the band")},
        units={"delta_F": "1"}, parameters={**base, "r": r}, summarize=summarize_delta_f)


def given_block(block, rng, *, data, data_sha256, model, settings):
    return nothing(block, rng)


def _given_delta_f(base) -> Study:
    """δ_F imposed by the settings: a placeholder whose summary carries the value."""
    s = dg.DiagnoseSettings.from_json(base["settings"])
    reason = f"delta_F given: {s.load_dispersion}"
    return Study(name="load_delta_f", seed=SEED, description=f"nothing to compute: {reason}", axes={"skipped": [reason]},
                 task=given_block, outputs={"nothing": Output(units="1", long_name="placeholder: nothing was computed")},
                 parameters=base, summarize=summarize_delta_f)


# -- bands --------------------------------------------------------------------------------------------
def _band_realisations(ctx, r, effects, dF, reals, rng):
    s = ctx.settings
    return dg.simulate_blocks(ctx.spec, r, effects, ctx.meas, ctx.meas.n_held_out_blocks, reals, s, stochastic=True,
                              load_dispersion=dF, rngs=[rng(s.seed, realisation=k) for k in reals])


def band_block(block, rng, *, data, data_sha256, model, settings, r, effects, load_dispersion):
    ctx = dg.load_context(data, data_sha256, model, settings)
    P, stats = _band_realisations(ctx, r, dg.effects_from_json(effects), load_dispersion,
                                  [int(k) for k in block["realisation"]], rng)
    return {"psd": P, "stats": stats}


def summarize_band(ds):
    if dg.skipped(ds):
        return {}
    ctx = _ctx(_params(ds))
    band = dg.stage_band(ctx, ds)
    err = dg.held_out_error(ctx.meas.held_out, band.lower, band.upper, ctx.meas.frequency)
    thr = band.threshold(ctx.settings)
    return {"error": err, "null_threshold": thr, "explained": bool(err <= thr)}


def _band_outputs():
    return {"psd": _psd_output("stochastic model, averaged over the held-out layout's blocks"),
            "stats": Output(dims=("sensor", "statistic"), units="m | 1 | 1", long_name="RMS [m], skewness, excess kurtosis")}


def _band_study(name, base, ctx, r, effects, dF, what) -> Study:
    s = ctx.settings
    return Study(
        name=name, seed=SEED,
        description=f"{what}: confidence band, stochastic model at delta = {s.delta}, delta_F = {dF:.4g}, r = {list(r)}",
        axes={"realisation": range(s.realisations)}, chunks={"realisation": _realisation_chunk(ctx, s.realisations)},
        task=band_block,
        coords={**_spectral_coords(ctx), "statistic": STATISTICS}, outputs=_band_outputs(), units={"frequency": "Hz"},
        parameters={**base, "r": [float(v) for v in r], "effects": effects, "load_dispersion": float(dF)},
        summarize=summarize_band)


def band(results, *, data, data_sha256, model, settings):
    base = _base(data, data_sha256, model, settings)
    ctx = _ctx(base)
    return _band_study("band", base, ctx, results["load_r_fine"].attrs["r_opt"], "[]",
                       results["load_delta_f"].attrs["delta_F_used"], "before")


# -- tracing and fitting ------------------------------------------------------------------------------------
def _plan(ctx, results):
    return dg.plan_candidates(ctx, dg.stage_band(ctx, results["band"]))


def probe_block(block, rng, *, data, data_sha256, model, settings, r, frequency_hz):
    ctx = dg.load_context(data, data_sha256, model, settings)
    out = np.empty((len(block["probe"]), ctx.meas.frequency.size, len(ctx.meas.sensors)))
    for i, name in enumerate(block["probe"]):
        effects = [dg.tone_probe(ctx, frequency_hz)] if name == "tone" else []
        out[i] = _mean_psd(ctx, r, effects, rng(ctx.settings.seed))
    return {"psd": out}


def probe(results, *, data, data_sha256, model, settings):
    base = _base(data, data_sha256, model, settings)
    ctx = _ctx(base)
    plan = _plan(ctx, results)
    if "tone" not in plan["fit"]:
        return _skipped("probe", "no tone candidate to fit")
    f0 = float(plan["signatures"]["tone"]["estimate"]["frequency_hz"])
    return Study(
        name="probe", seed=SEED, description=f"tone probe ({dg.TONE_PROBE_N} N at {f0:.4g} Hz) and baseline, mean model",
        axes={"probe": ["baseline", "tone"]}, chunks={"probe": 1}, seed_axes=(), task=probe_block,
        coords=_spectral_coords(ctx), outputs={"psd": _psd_output("mean model, fitting blocks")}, units={"frequency": "Hz"},
        parameters={**base, "r": [float(v) for v in results["load_r_fine"].attrs["r_opt"]], "frequency_hz": f0})


def trial_block(block, rng, *, data, data_sha256, model, settings, r, trials):
    ctx = dg.load_context(data, data_sha256, model, settings)
    meas = ctx.meas
    trials = json.loads(trials)
    n = len(block["trial"])
    psd = np.empty((n, meas.frequency.size, len(meas.sensors)))
    dist, off = np.empty(n), np.empty(n)
    for i, k in enumerate(block["trial"]):
        psd[i] = _mean_psd(ctx, r, [effect_from_dict(trials[int(k)]["effect"])], rng(ctx.settings.seed))
        dist[i], off[i] = dg.level_free_distance(meas.fit, psd[i], dg.analysis_bins(meas.frequency))
    return {"psd": psd, "distance": dist, "offset": off}


def candidates(results, *, data, data_sha256, model, settings):
    base = _base(data, data_sha256, model, settings)
    ctx = _ctx(base)
    s = ctx.settings
    plan = _plan(ctx, results)
    if plan["explained"] or not plan["fit"]:
        return _skipped("candidates", "explained within the band" if plan["explained"] else "no candidate signature")
    stop_k = ctx.spec.stops[0].stiffness if ctx.spec.stops else 1e8
    trials = []
    for name in plan["fit"]:
        est = plan["signatures"][name]["estimate"]
        amps = None
        if name == "tone":
            pr = results["probe"]
            amps = dg.tone_amplitudes(ctx, est["frequency_hz"], pr["psd"].sel(probe="baseline").values,
                                      pr["psd"].sel(probe="tone").values)
        grid = candidate_grid(name, est, tube=ctx.tube, load_x=s.load_x, stop_stiffness=stop_k,
                              sensor_rms=ctx.meas.fit_stats[:, 0], points=s.grid_points, tone_amplitudes=amps)
        trials += [{"candidate": name, "effect": effect_to_dict(e)} for e in grid]
    return Study(
        name="candidates", seed=SEED,
        description=f"trial grids of {plan['fit']} (mean model, fitting blocks); level-free log-spectral distance",
        axes={"trial": range(len(trials))}, chunks={"trial": 1}, seed_axes=(), task=trial_block,
        coords=_spectral_coords(ctx),
        outputs={"psd": _psd_output("mean model with the trial effect, fitting blocks"),
                 "distance": Output(units="decades^2", long_name="level-free mean squared log10 distance to the fitting PSD"),
                 "offset": Output(units="decades", long_name="mean log10(measured / model)")},
        units={"frequency": "Hz"},
        parameters={**base, "r": [float(v) for v in results["load_r_fine"].attrs["r_opt"]],
                    "trials": json.dumps(trials, sort_keys=True)})


def candidate_band_block(block, rng, *, data, data_sha256, model, settings, names, r, effects, load_dispersion, error_before):
    ctx = dg.load_context(data, data_sha256, model, settings)
    effects = json.loads(effects)
    reals = [int(k) for k in block["realisation"]]
    P = np.empty((len(block["candidate"]), len(reals), ctx.meas.frequency.size, len(ctx.meas.sensors)))
    stats = np.empty((len(block["candidate"]), len(reals), len(ctx.meas.sensors), 3))
    for i, name in enumerate(block["candidate"]):
        j = names.index(str(name))
        P[i], stats[i] = _band_realisations(ctx, r[j], [effect_from_dict(effects[j])], load_dispersion, reals, rng)
    return {"psd": P, "stats": stats}


def summarize_candidate_bands(ds):
    if dg.skipped(ds):
        return {"chosen": ""}
    p = _params(ds)
    ctx = _ctx(p)
    s, meas = ctx.settings, ctx.meas
    errors, penalised = [], []
    best, chosen = p["error_before"], ""
    for name in p["names"]:
        b = dg.stage_band(ctx, ds.sel(candidate=name))
        e = dg.held_out_error(meas.held_out, b.lower, b.upper, meas.frequency)
        pen = e / (1.0 - s.penalty) ** PARAMETER_COUNT[name]
        errors.append(e)
        penalised.append(pen)
        if pen < best:
            best, chosen = pen, name
    return {"candidate_names": list(p["names"]), "held_out_errors": errors, "penalised_errors": penalised, "chosen": chosen}


def candidate_bands(results, *, data, data_sha256, model, settings):
    base = _base(data, data_sha256, model, settings)
    ctx = _ctx(base)
    s = ctx.settings
    if dg.skipped(results["candidates"]):
        return _skipped("candidate_bands", "no candidate was fitted", summarize_candidate_bands)
    trials = json.loads(_params(results["candidates"])["trials"])
    best = dg.best_trials(ctx, results["candidates"], trials)
    names = list(best)
    r0 = results["load_r_fine"].attrs["r_opt"]
    dF = float(results["load_delta_f"].attrs["delta_F_used"])
    return Study(
        name="candidate_bands", seed=SEED,
        description=f"confidence bands of the best trial of {names} at delta_F = {dF:.4g} (common random numbers across candidates)",
        axes={"candidate": names, "realisation": range(s.realisations)},
        chunks={"candidate": 1, "realisation": _realisation_chunk(ctx, s.realisations)},
        seed_axes=("realisation",), task=candidate_band_block,
        coords={**_spectral_coords(ctx), "statistic": STATISTICS}, outputs=_band_outputs(), units={"frequency": "Hz"},
        parameters={**base, "names": names, "r": [list(dg.scaled_r(r0, best[n][1])) for n in names],
                    "effects": json.dumps([effect_to_dict(best[n][0]) for n in names], sort_keys=True),
                    "load_dispersion": dF, "error_before": float(results["band"].attrs["error"])},
        summarize=summarize_candidate_bands)


# -- re-identification with the chosen effect ------------------------------------------------------------
def _chosen(results):
    """(effect as JSON list, starting r) of the chosen candidate, or None."""
    cb = results["candidate_bands"]
    name = cb.attrs.get("chosen", "")
    if not name:
        return None
    p = _params(cb)
    j = p["names"].index(name)
    return json.dumps([json.loads(p["effects"])[j]], sort_keys=True), p["r"][j]


def load_r_after(results, *, data, data_sha256, model, settings):
    base = _base(data, data_sha256, model, settings)
    ctx = _ctx(base)
    s = ctx.settings
    chosen = _chosen(results)
    if chosen is None:
        return _skipped("load_r_after", "no effect chosen")
    effects, r_c = chosen
    return _r_study("load_r_after", base, ctx, dg.r_fine_grid(r_c, s.r_fine_points, s.r_fine_span), effects,
                    "with the chosen effect, around its level", summarize_r_fine)


def band_after(results, *, data, data_sha256, model, settings):
    base = _base(data, data_sha256, model, settings)
    ctx = _ctx(base)
    chosen = _chosen(results)
    if chosen is None:
        return _skipped("band_after", "no effect chosen", summarize_band)
    return _band_study("band_after", base, ctx, results["load_r_after"].attrs["r_opt"], chosen[0],
                       results["load_delta_f"].attrs["delta_F_used"], "after, with the chosen effect")


study = Pipeline(
    name="diagnose",
    seed=SEED,
    description="tubeid diagnose: load identification (r, delta_F), band, tracing, candidate fits, re-identification",
    stages=[load_r, load_r_fine, load_delta_f, band, probe, candidates, candidate_bands, load_r_after, band_after],
    warmup=Warmup(warmup.MESSAGE, run=warmup.compile_solver, needed=warmup.cache_is_cold),
    parameters={
        "data": Parameter("", doc="path of the validated record (NetCDF written by tubeid diagnose)"),
        "data_sha256": Parameter("", doc="content hash of the record (tubeid.measured.diagnose.data_hash)"),
        "model": Parameter("", doc="declared model: JSON of spec_to_dict"),
        "settings": Parameter("", doc="DiagnoseSettings.to_json()"),
    },
)
