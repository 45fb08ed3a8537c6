"""The runner pipeline of ``tubeid diagnose`` (the method: :mod:`tubeid.diagnose.method`).

Run by :func:`tubeid.diagnose.diagnose` into ``DIR/diagnose.zarr`` (one Zarr group per stage). Its
parameters are plain text: ``data`` (path of the validated record written into DIR),
``data_sha256`` (its content hash, checked by every process that reads it), ``model`` (the
declared model, JSON of ``spec_to_dict``) and ``settings`` (``DiagnoseSettings.to_json()``); all
four are hashed into the store's identity. Every grid point and Monte Carlo realisation is a
runner task; a stage with nothing to compute holds one ``skipped`` placeholder whose coordinate
says why (written by the runner's own process, not sent to the cluster). Random streams are keyed by the stage, the settings' seed and, where named, the
realisation; the trials of one stage share one stream (common random numbers).

``delta_ml``        J(δ) of the declared model's random B → δ by maximum likelihood of J_ref of
                    ``delta_reference`` (skipped when δ is given)
``load_r``          coarse trial grid of r (mean model, fitting blocks) → log-spectral distance
``load_r_fine``     fine grid around the levelled coarse minimum → r_opt
``load_delta_f``    J_s over a δ_F grid × realisations → δ_F (skipped when given or too few blocks)
``band``            R realisations of the stochastic model, held-out layout → the calibrated test,
                    and (when something is detected) the signatures of the catalog for step 1
``step{k}_trials``  the catalog's trial grids (mean model, fitting blocks, chosen effects held)
                    → the choice of step k by held-out error (the simplified form: by the pointing
                    statistic's feature, :class:`FeatureErrors`); after a step that explained the
                    record, only the near-tied runner-ups of earlier steps (:func:`runner_ups`)
``step{k}_refit``   lines of 3 trials around (r — exact form only —, every chosen effect's
                    parameters; a tone's amplitude along its profile, derived from one trial
                    without the tone) → joint re-fit
``step{k}_check``   the point the re-fit's lines moved to, evaluated (kept only if no worse than the
                    best trial the lines evaluated), and the same point with the log lines whose
                    best was at an end moved one step further (kept if better than both)
``step{k}_refit2``  a second sweep of the same lines around the point the first kept, when a line
``step{k}_check2``  of the first did not bracket its minimum or the moved point was not kept
                    (:func:`sweep_reason`; alternating the lines until they bracket: r and a stop's
                    gap trade off, and lines evaluated one at a time mis-place both); skipped else
``step{k}_band``    R realisations with the re-fitted effects → the test after step k (and the
                    signatures for step k + 1)

With the simplified model form the band and trial stages also store what its statistics read: the
fine-segment PSD and the conditional PSD (and, for trials, per fitting-layout record with the time
statistics); with the exact form the band stages store the fine-segment PSD when they hold probe
realisations (the ``profile`` statistic reads it).

Every band stage also holds, as realisation −1, the mean model's prediction at its point (fitting
layout, ``fit_realisations`` records): the held-out error of that point; when added mass is a
candidate, as realisations −2, −3, …, ``n_probe_realisations`` realisations with the added-mass
catalog entry's probe on top of its effects (the ``profile`` statistic's direction; not samples of
the test).
"""

import dataclasses
import functools
import importlib
import json

import numpy as np

from tubeid.diagnose._detection import SCALE_FLOOR, STATISTICS as TEST_STATISTICS, Observations, applicable, \
    band_moments, detection_test, feature_applies, features
from tubeid.diagnose._load import delta_f_identification, grid_minimum, r_coarse_grid, r_distance, r_fine_grid, scaled_r
from tubeid.diagnose._selection import (Scored, choose, level_offset, line_extension, line_minimum, near_ties, prediction_error,
                                        refit_choice)
from tubeid.diagnose._settings import MAX_EFFECTS, DiagnoseSettings
from tubeid.diagnose._simulate import load_spectrum, simulate_blocks, simulate_series
from tubeid.diagnose._spectra import welch_segments
from tubeid.diagnose.catalog import CATALOG, Evidence
from tubeid.dynamics import warmup
from tubeid.dynamics.spectra import j_s, psd_matrix
from tubeid.identification.loads import JS_UNITS
from tubeid.mechanics.effects import apply_effects, effect_from_dict, effect_to_dict
from tubeid.runner.pipeline import End, Pipeline
from tubeid.runner.study import Output, Parameter, Study, Warmup

__all__ = ["study", "SEED", "STEP_STAGES", "REFIT_SWEEPS", "skipped", "absent", "state_before", "selection",
           "refit_result", "refit_point", "sweep_reason", "sweeps_done", "final_point", "point_result"]

method = importlib.import_module("tubeid.diagnose.method")

SEED = 6
R_DIMS = ("r1", "r2")
R_UNITS = {"r1": "N^2/Hz", "r2": "(N m)^2/Hz"}
STATISTICS = ["rms", "skewness", "excess_kurtosis"]
#: The stages of one selection step, in order.
#: Re-fit sweeps of a step at most (the second runs only where the first did not bracket every
#: parameter or did not keep its moved point: :func:`sweep_reason`).
REFIT_SWEEPS = 2
STEP_STAGES = ("trials", *(f"{kind}{'' if sweep == 1 else sweep}" for sweep in range(1, REFIT_SWEEPS + 1)
                           for kind in ("refit", "check")), "band")


def _ctx(p: dict):
    return method.load_context(p["data"], p["data_sha256"], p["model"], p["settings"])


def _base(data, data_sha256, model, settings) -> dict:
    return {"data": data, "data_sha256": data_sha256, "model": model, "settings": settings}


def _params(ds) -> dict:
    return json.loads(ds.attrs["parameters"])


def skipped(ds) -> bool:
    """Whether a stage had nothing to compute (its only axis is ``skipped``)."""
    return "skipped" in ds.dims


def absent(results, name: str) -> bool:
    """Whether stage ``name`` computed nothing: a placeholder (:func:`skipped`), or not built because
    the pipeline ended before it (:class:`~tubeid.runner.End`: the loop had no step left)."""
    return name not in results or skipped(results[name])


def _spectral_coords(ctx) -> dict:
    return {"frequency": ctx.meas.frequency, "sensor": list(ctx.meas.sensors)}


def _psd_output(what: str, *, finite: bool = True) -> Output:
    return Output(dims=("frequency", "sensor"), units="m^2/Hz", long_name=f"auto-PSD at the sensors, two-sided: {what}",
                  finite=finite)


def _mean_model(ctx, r, effects, gen, observed: tuple[str, ...] | None = None) -> dict:
    """The mean model on the fitting layout, ``fit_realisations`` records (:func:`simulate_blocks`;
    ``observed`` None: what the model form's trials read)."""
    s, meas = ctx.settings, ctx.meas
    return simulate_blocks(ctx.spec, r, effects, meas, meas.n_fit_blocks, range(s.fit_realisations), s, rngs=[gen],
                           observed=_form_observed(ctx) if observed is None else observed)


def _mean_psd(ctx, r, effects, gen) -> np.ndarray:
    """Mean-model auto-PSD (F, m) on the fitting layout, averaged over ``fit_realisations`` records."""
    return _mean_model(ctx, r, effects, gen, observed=())["psd"].mean(axis=0)


def _simplified(ctx) -> bool:
    """The declared model is taken as a simplification: the robust statistics and their features."""
    return ctx.settings.form == "simplified"


#: The observations the simplified form's statistics read beyond the auto-PSD and time statistics.
OBSERVED = ("fine", "residual")


def _form_observed(ctx) -> tuple[str, ...]:
    """What of :data:`OBSERVED` the model form's statistics and features read: all of it with the
    simplified form, nothing with the exact one."""
    return OBSERVED if _simplified(ctx) else ()


def _band_observed(ctx) -> tuple[str, ...]:
    """What of :data:`OBSERVED` the band stages store: the model form's, and with the exact form the
    fine PSDs when there are probe realisations (its ``profile`` statistic reads them)."""
    return _form_observed(ctx) or (("fine",) if _probes(ctx) else ())


def _observation_outputs(ctx, what: str, per: tuple = (), observed: tuple[str, ...] | None = None) -> dict:
    """The outputs of ``observed`` (None: :func:`_form_observed`) over the extra dims ``per``."""
    observed = _form_observed(ctx) if observed is None else observed
    outputs = {"fine": Output(dims=per + ("frequency_fine", "sensor"), units="m^2/Hz", finite=False,
                              long_name=f"auto-PSD at the sensors, two-sided, fine Welch segment: {what}"),
               "residual": Output(dims=per + ("frequency", "sensor"), units="m^2/Hz", finite=False,
                                  long_name=f"conditional PSD of each sensor given the others, two-sided: {what}")}
    return {k: outputs[k] for k in observed}


def _observation_coords(ctx, per_record: bool = False, observed: tuple[str, ...] | None = None) -> tuple[dict, dict]:
    """Coordinates and units of :func:`_observation_outputs`' dims (``per_record``: with the
    ``fit_realisation`` dim of the trials; ``observed`` as there)."""
    if not (_form_observed(ctx) if observed is None else observed):
        return {}, {}
    coords = {"frequency_fine": ctx.meas.frequency_fine}
    if per_record:
        coords["fit_realisation"] = list(range(ctx.settings.fit_realisations))
    return coords, {"frequency_fine": "Hz", **({"fit_realisation": "1"} if per_record else {})}


def _segments(ctx, which: str) -> int:
    """Welch segments a ``"fit"`` or ``"held_out"`` layout's spectra average."""
    m = ctx.meas
    blocks = m.n_fit_blocks if which == "fit" else m.n_held_out_blocks
    return welch_segments(m.block_samples, m.dt, ctx.settings.segment_seconds, blocks)


def record_observations(ctx, which: str) -> Observations:
    """The record's ``"fit"`` or ``"held_out"`` blocks as one sample."""
    m = ctx.meas
    stats = {"fit": m.fit_stats, "held_out": m.stats}[which]
    return Observations(m.frequency, getattr(m, which)[None], m.frequency_fine, getattr(m, f"{which}_fine")[None],
                        getattr(m, f"{which}_residual")[None], stats[None], ctx.spec.band_hz, _segments(ctx, which))


def _realisation_chunk(delta: float, n: int) -> int:
    """Realisations per task. With δ = 0 every realisation of a call shares one set of solver
    tables: two tasks, one table each; with δ > 0 each realisation has its own random K_B, and
    tasks of 2 balance the workers."""
    return 2 if delta > 0 else max(2, -(-n // 2))


# -- nothing to compute ---------------------------------------------------------------------------------
def nothing(block, rng, **_):
    return {"nothing": np.zeros(len(block["skipped"]))}


def _skipped(name: str, reason: str, summarize=None, parameters=None) -> Study:
    return Study(name=name, seed=SEED, description=f"nothing to compute: {reason}", axes={"skipped": [reason]},
                 task=nothing, outputs={"nothing": Output(units="1", long_name="placeholder: nothing was computed")},
                 summarize=summarize, parameters=parameters or {}, in_process=True)


# -- δ by the paper's maximum likelihood of J -----------------------------------------------------------------
def delta_block(block, rng, *, data, data_sha256, model, settings, j_reference):
    from tubeid.mechanics.reduction import reduce
    from tubeid.uncertainty.random_models import j_monte_carlo

    ctx = method.load_context(data, data_sha256, model, settings)
    sub = reduce(ctx.spec).subsystem
    J = j_monte_carlo(sub, [float(d) for d in block["delta"]], ctx.settings.seed,
                      [int(k) for k in block["realisation"]], ctx.spec.band_hz)
    return {"J": J.values}


def summarize_delta(ds):
    p = _params(ds)
    s = DiagnoseSettings.from_json(p["settings"])
    if skipped(ds):
        return {"delta": float(s.delta), "delta_source": "given"}
    from tubeid.identification.likelihood import likelihood_curve

    lik = likelihood_curve(ds["J"].transpose("delta", "realisation").values, p["j_reference"], ds["delta"].values,
                           "delta", n_bootstrap=s.n_bootstrap, rng=s.seed)
    ll = lik["log_likelihood"].values
    rel = ll - np.nanmax(ll)
    return {"delta": float(lik.attrs["argmax"]), "delta_source": f"maximum likelihood of J against {s.delta_reference}",
            "delta_std": float(lik.attrs["argmax_std"]), "delta_at_grid_edge": bool(lik.attrs["argmax_at_boundary"]),
            "delta_flat": bool(np.nanmax(rel) - np.nanmin(rel) < 2.0), "J_reference": float(p["j_reference"]),
            "delta_grid": [float(d) for d in ds["delta"].values], "delta_log_likelihood": [float(v) for v in rel]}


def delta_ml(results, *, data, data_sha256, model, settings):
    base = _base(data, data_sha256, model, settings)
    ctx = _ctx(base)
    s = ctx.settings
    if s.delta_reference is None:
        return _skipped("delta_ml", f"delta given: {s.delta}", summarize_delta, base)
    from tubeid.identification.delta import default_delta_grid, reference_j
    from tubeid.mechanics.reduction import reduce

    grid = [float(d) for d in np.round(default_delta_grid(reduce(ctx.spec).subsystem.n), 4)]
    return Study(
        name="delta_ml", seed=SEED, description=f"J(delta) of the declared model's random B against J of {s.delta_reference}",
        axes={"delta": grid, "realisation": range(s.delta_realisations)},
        chunks={"delta": len(grid), "realisation": s.delta_realisations}, seed_axes=(), task=delta_block,
        outputs={"J": Output(units="m^2 rad/(N^2 s)", long_name="J = integral of ||Z^-1||_F^2 over the band")},
        units={"delta": "1"}, parameters={**base, "j_reference": float(reference_j(s.delta_reference))},
        summarize=summarize_delta)


def _delta(results) -> float:
    return float(results["delta_ml"].attrs["delta"])


# -- trial grids of r ---------------------------------------------------------------------------------
def r_block(block, rng, *, data, data_sha256, model, settings, effects):
    ctx = method.load_context(data, data_sha256, model, settings)
    eff = method.effects_from_json(effects)
    dims = [d for d in R_DIMS if d in block]
    shape = tuple(len(block[d]) for d in dims)
    meas = ctx.meas
    psd = np.empty(shape + (meas.frequency.size, len(meas.sensors)))
    dist, off = np.empty(shape), np.empty(shape)
    for idx in np.ndindex(*shape):
        r = tuple(float(block[d][i]) for d, i in zip(dims, idx))
        psd[idx] = _mean_psd(ctx, r, eff, rng(ctx.settings.seed))
        dist[idx], off[idx] = r_distance(meas.fit, psd[idx], meas.frequency, ctx.spec.band_hz)
    return {"psd": psd, "distance": dist, "offset": off}


def _r_minimum(ds, refine):
    dims = [d for d in R_DIMS if d in ds.dims]
    d = ds["distance"].transpose(*dims).values
    r, idx, boundary = grid_minimum(d, [ds[x].values for x in dims], refine=refine)
    return r, idx, boundary, ds["offset"].transpose(*dims).values[idx], d[idx], dims


def summarize_r_coarse(ds):
    r, idx, boundary, off, d, dims = _r_minimum(ds, refine=False)
    return {"r_best": list(r), "offset_best": float(off), "distance_best": float(d), "at_boundary": boundary,
            "r_next": list(scaled_r(r, off))}


def summarize_r_fine(ds):
    r, idx, boundary, off, d, dims = _r_minimum(ds, refine=True)
    return {"r_opt": list(r), "r_discrete": [float(ds[x].values[i]) for x, i in zip(dims, idx)],
            "distance_opt": float(d), "offset_opt": float(off), "at_boundary": boundary}


def _r_study(name, base, ctx, grid, what, summarize) -> Study:
    axes = dict(zip(R_DIMS, grid))
    return Study(
        name=name, seed=SEED,
        description=f"{what}: trial grid of r ({ctx.settings.load} load), mean model, fitting blocks; log-spectral distance",
        axes=axes, chunks={d: 1 for d in axes}, seed_axes=(), task=r_block, coords=_spectral_coords(ctx),
        outputs={"psd": _psd_output("mean model, fitting blocks"),
                 "distance": Output(units="decades^2", long_name="mean squared log10 distance to the fitting PSD, 0 < f <= band"),
                 "offset": Output(units="decades", long_name="mean log10(measured / model) over the same bins")},
        units={**{d: R_UNITS[d] for d in axes}, "frequency": "Hz"}, parameters={**base, "effects": "[]"},
        summarize=summarize)


def load_r(results, *, data, data_sha256, model, settings):
    base = _base(data, data_sha256, model, settings)
    ctx = _ctx(base)
    s = ctx.settings
    return _r_study("load_r", base, ctx, r_coarse_grid(s.start_r, s.r_points, s.r_step), "coarse", summarize_r_coarse)


def load_r_fine(results, *, data, data_sha256, model, settings):
    base = _base(data, data_sha256, model, settings)
    ctx = _ctx(base)
    s = ctx.settings
    return _r_study("load_r_fine", base, ctx, r_fine_grid(results["load_r"].attrs["r_next"], s.r_fine_points, s.r_fine_span),
                    "fine, around the levelled coarse minimum", summarize_r_fine)


# -- δ_F ----------------------------------------------------------------------------------------------
def delta_f_block(block, rng, *, data, data_sha256, model, settings, r, delta):
    ctx = method.load_context(data, data_sha256, model, settings)
    s, meas = ctx.settings, ctx.meas
    reals = [int(k) for k in block["realisation"]]
    out = np.empty((len(block["delta_F"]), len(reals)))
    for i, dF in enumerate(block["delta_F"]):
        y = simulate_series(ctx.spec, r, (), meas, meas.block_samples, reals, s, delta=delta,
                            load_dispersion=float(dF), rngs=[rng(s.seed, realisation=k) for k in reals])
        f, S = psd_matrix(y, meas.dt, segment_seconds=s.segment_seconds)
        out[i] = j_s(f, S, band=ctx.spec.band_hz)
    return {"J_s": out}


def summarize_delta_f(ds):
    p = _params(ds)
    ctx = _ctx(p)
    s = ctx.settings
    if skipped(ds):
        given = s.load_dispersion is not None
        v = float(s.load_dispersion if given else s.delta_f_fallback)
        why = ("given" if given else f"the record has {ctx.meas.n_fit_blocks} fitting blocks, fewer than "
               f"delta_f_min_blocks = {s.delta_f_min_blocks}: one J_s per block cannot show a dispersion")
        return {"delta_F": v, "delta_F_used": v, "delta_F_given": True, "delta_F_source": why}
    out = delta_f_identification(ds["J_s"], ctx.j_s_observed, ctx.m, s)
    out["delta_F_given"] = False
    out["delta_F_source"] = "maximum likelihood of J_s"
    return out


def load_delta_f(results, *, data, data_sha256, model, settings):
    base = _base(data, data_sha256, model, settings)
    ctx = _ctx(base)
    s = ctx.settings
    if not ctx.identify_delta_f:
        reason = (f"delta_F given: {s.load_dispersion}" if s.load_dispersion is not None
                  else f"delta_F not identifiable from {ctx.meas.n_fit_blocks} fitting blocks")
        return _skipped("load_delta_f", reason, summarize_delta_f, base)
    r = [float(v) for v in results["load_r_fine"].attrs["r_opt"]]
    grid = list(ctx.delta_f_grid)
    d = _delta(results)
    return Study(
        name="load_delta_f", seed=SEED,
        description=f"J_s of one block's length ({ctx.meas.block_seconds:.4g} s) of the stochastic model at "
                    f"delta = {d:.4g}, r = {r}, over a delta_F grid (common random numbers across delta_F)",
        axes={"delta_F": grid, "realisation": range(s.delta_f_realisations)},
        chunks={"delta_F": len(grid), "realisation": _realisation_chunk(d, s.delta_f_realisations)},
        seed_axes=("realisation",), task=delta_f_block,
        outputs={"J_s": Output(units=JS_UNITS, long_name="J_s = integral of ||S_Z(w)||_F^2 over the band")},
        units={"delta_F": "1"}, parameters={**base, "r": r, "delta": d}, summarize=summarize_delta_f)


# -- bands and the test ----------------------------------------------------------------------------------
#: The band stages' realisation that holds the mean model's prediction (fitting layout).
MEAN_MODEL = -1
#: The band stages' realisations from this one down (−2, −3, …) are the probe's: the model with the
#: added-mass catalog entry's probe, the ``profile`` statistic's direction.
PROBE = -2


def _probes(ctx) -> list[int]:
    """The probe realisations of a band stage: ``n_probe_realisations`` when added mass is a
    candidate, else none."""
    if "added_mass" not in ctx.candidate_names:
        return []
    return [PROBE - k for k in range(ctx.settings.n_probe_realisations)]


def band_block(block, rng, *, data, data_sha256, model, settings, r, effects, delta, load_dispersion, step):
    ctx = method.load_context(data, data_sha256, model, settings)
    s, meas = ctx.settings, ctx.meas
    eff = method.effects_from_json(effects)
    reals = [int(k) for k in block["realisation"]]
    observed = _band_observed(ctx)
    keys = ("psd", "stats", "contact") + observed
    out = {}
    mean = [i for i, k in enumerate(reals) if k == MEAN_MODEL]
    for i in mean:  # the mean model's prediction, fitting layout, fit_realisations records
        o = _mean_model(ctx, r, eff, rng(s.seed, realisation=MEAN_MODEL), observed=observed)
        for k in keys:
            out.setdefault(k, np.empty((len(reals),) + o[k].shape[1:]))[i] = o[k].mean(axis=0)
    probe = [CATALOG["added_mass"].probe(ctx.spec, s.form)]
    for rows, with_effects in (([i for i, k in enumerate(reals) if k >= 0], eff),
                               ([i for i, k in enumerate(reals) if k <= PROBE], eff + probe)):
        if rows:
            o = simulate_blocks(ctx.spec, r, with_effects, meas, meas.n_held_out_blocks, [reals[i] for i in rows], s,
                                delta=delta, load_dispersion=load_dispersion,
                                rngs=[rng(s.seed, realisation=reals[i]) for i in rows], observed=observed)
            for k in keys:
                out.setdefault(k, np.empty((len(reals),) + o[k].shape[1:]))[rows] = o[k]
    return out


def band_samples(ds) -> tuple[np.ndarray, np.ndarray]:
    """The stochastic model's realisations of a band stage: psd (R, F, m), stats (R, m, 3)."""
    b = ds.sel(realisation=ds["realisation"].values[ds["realisation"].values >= 0])
    return (b["psd"].transpose("realisation", "frequency", "sensor").values,
            b["stats"].transpose("realisation", "sensor", "statistic").values)


def band_observations(ctx, ds) -> Observations:
    """The stochastic model's realisations of a band stage as :class:`Observations` (R samples; the
    probe realisations' fine PSDs, if any, as its ``probe``)."""
    real = ds["realisation"].values
    b = ds.sel(realisation=real[real >= 0])
    P, stats = band_samples(ds)
    get = (lambda k, d: b[k].transpose("realisation", d, "sensor").values if k in b else None)
    probe = None
    if np.any(real <= PROBE) and "fine" in ds:
        probe = ds["fine"].sel(realisation=real[real <= PROBE])
        probe = probe.transpose("realisation", "frequency_fine", "sensor").values
    return Observations(ctx.meas.frequency, P, ctx.meas.frequency_fine, get("fine", "frequency_fine"),
                        get("residual", "frequency"), stats, ctx.spec.band_hz, _segments(ctx, "held_out"), probe)


def mean_prediction(ds) -> np.ndarray:
    """The mean model's prediction (F, m) stored in a band stage."""
    return ds["psd"].sel(realisation=MEAN_MODEL).transpose("frequency", "sensor").values


def evidence(ctx, ds, detection=None) -> Evidence:
    """The :class:`~tubeid.diagnose.catalog.Evidence` of a band stage (its model, r and realisations;
    with the simplified form, where the test's ``detection`` saw a line and the record's noise floor)."""
    from tubeid.diagnose._detection import band_moments as moments
    from tubeid.diagnose._surrogate import LinearSurrogate

    p = _params(ds)
    effects = method.effects_from_json(p["effects"])
    spec = apply_effects(ctx.spec, effects)
    P, stats = band_samples(ds)
    mu, sd = moments(P)
    z = (ctx.meas.fit_stats - stats.mean(axis=0)) / np.maximum(stats.std(axis=0, ddof=1), 1e-300)
    sur = LinearSurrogate(spec, load_spectrum(spec, p["r"], ctx.settings), ctx.meas.frequency)
    robust = {}
    if _simplified(ctx):
        rec = record_observations(ctx, "fit")
        floor = "floor" in applicable("simplified", rec, ctx.settings.band_width_hz)
        robust = {"form": "simplified",
                  "floor_level": float(10.0 ** np.median(features("floor", rec)[0, 0])) if floor else None,
                  "line_frequency_hz": None if detection is None else float(detection.scan_frequency_hz)}
    ev = Evidence(frequency=ctx.meas.frequency, fit=ctx.meas.fit, mu=mu, sigma=np.maximum(sd, 1e-6), z_stats=z,
                  rms=ctx.meas.fit_stats[:, 0], spec=spec, surrogate=sur, band_hz=ctx.spec.band_hz, **robust)
    sur.contact = float(np.mean(ds["contact"].sel(realisation=ds["realisation"].values >= 0).values))
    return ev


def summarize_band(ds):
    if skipped(ds):
        return {"detected": False}
    p = _params(ds)
    ctx = _ctx(p)
    s = ctx.settings
    obs = record_observations(ctx, "held_out").stacked(band_observations(ctx, ds))
    det = detection_test(obs, false_alarm=s.alarm_at(p["step"]), band_width_hz=s.band_width_hz, model_form=s.form)
    out = {"detection": json.dumps(det.to_dict(), sort_keys=True), "detected": det.detected, "p_value": det.p_value}
    chosen = [e["kind"] for e in json.loads(p["effects"])]
    available = tuple(n for n in ctx.candidate_names if n not in chosen)
    pointed = det.pointed_effects(available)
    remaining = [n for n in available if pointed is None or n in pointed]
    if det.detected and available and not remaining:
        out["screen_reason"] = (f"the departures the test sees ({', '.join(sorted(det.excess, key=lambda k: -det.excess[k]))}"
                                f", strongest first) point to no candidate left ({', '.join(available)})")
    if det.detected and p["step"] < s.max_effects and remaining:
        ev = evidence(ctx, ds, det)
        screen = {n: CATALOG[n].signature(ev) for n in remaining}
        out["screen"] = json.dumps(screen, sort_keys=True, default=float)
        out["contact_weight"] = ev.surrogate.contact
    return out


def _band_study(name, base, ctx, r, effects, delta, dF, step, what) -> Study:
    s = ctx.settings
    observed = _band_observed(ctx)
    obs_coords, obs_units = _observation_coords(ctx, observed=observed)
    return Study(
        name=name, seed=SEED,
        description=f"{what}: stochastic model at delta = {delta:.4g}, delta_F = {dF:.4g}, r = {list(r)}, held-out layout",
        axes={"realisation": [MEAN_MODEL, *range(s.n_realisations), *_probes(ctx)]},
        chunks={"realisation": _realisation_chunk(delta, s.n_realisations + 1 + len(_probes(ctx)))}, task=band_block,
        coords={**_spectral_coords(ctx), "statistic": STATISTICS, **obs_coords},
        outputs={"psd": _psd_output("stochastic model, averaged over the held-out layout's blocks (realisation -1: the "
                                    "mean model's prediction, fitting layout; -2 and below: with the added-mass probe)"),
                 "stats": Output(dims=("sensor", "statistic"), units="m | 1 | 1", long_name="RMS [m], skewness, excess kurtosis"),
                 "contact": Output(units="1", long_name="fraction of time the stops are closed (mean over the stops)"),
                 **_observation_outputs(ctx, "stochastic model, held-out layout (realisation -1: mean model, fitting layout; "
                                                        "-2 and below: with the added-mass probe)", observed=observed)},
        units={"frequency": "Hz", **obs_units},
        parameters={**base, "r": [float(v) for v in r], "effects": effects, "delta": float(delta),
                    "load_dispersion": float(dF), "step": int(step)},
        summarize=summarize_band)


def band(results, *, data, data_sha256, model, settings):
    base = _base(data, data_sha256, model, settings)
    ctx = _ctx(base)
    return _band_study("band", base, ctx, results["load_r_fine"].attrs["r_opt"], "[]", _delta(results),
                       results["load_delta_f"].attrs["delta_F_used"], 0, "the declared model")


# -- selection steps -------------------------------------------------------------------------------------
def _sigma(results) -> np.ndarray:
    """σ of log10 PSD per bin and sensor of the band before any effect: the unit of every error."""
    return np.maximum(band_moments(band_samples(results["band"])[0])[1], 1e-6)


def _errors(ctx, psd, sigma) -> tuple[float, float, float]:
    """(level offset on the fitting blocks, fitting error, held-out error) of a model PSD."""
    f, meas = ctx.meas.frequency, ctx.meas
    o = level_offset(meas.fit, psd, sigma, f)
    return o, prediction_error(meas.fit, psd, sigma, f, o), prediction_error(meas.held_out, psd, sigma, f, o)


def state_before(ctx, results, k: int) -> dict:
    """Where step k starts: {"active", "reason", "effects" (JSON list), "r", "screen" ({name:
    signature}) and "band" (the stage whose test decided)}."""
    s = ctx.settings
    prev_band = "band" if k == 1 else f"step{k - 1}_band"
    if k == 1:
        effects, r = "[]", [float(v) for v in results["load_r_fine"].attrs["r_opt"]]
    else:
        bk = results[f"step{k - 1}_band"]
        if skipped(bk):
            return {"active": False, "reason": f"step {k - 1} added no effect"}
        effects, r = _params(bk)["effects"], [float(v) for v in _params(bk)["r"]]
    if k > s.max_effects:
        return {"active": False, "reason": f"max_effects = {s.max_effects}"}
    b = results[prev_band]
    if b.attrs.get("detected", False) and continuation_rejected(results, k - 1):
        return {"active": False, "reason": f"the near-tied runner-up added at step {k - 1} made the test detect again: "
                                           f"not kept (the answer is that of step {k - 2})"}
    if not b.attrs.get("detected", False):
        pending = {} if k == 1 else runner_ups(ctx, results, k, {e["kind"] for e in json.loads(effects)})
        if pending:  # explained, but a near-tied runner-up was never tried with the other fitted
            return {"active": True, "reason": "", "effects": effects, "r": r, "band": prev_band,
                    "screen": {n: v["signature"] for n, v in pending.items()},
                    "continuation": {n: {key: v[key] for key in ("step", "ratio", "chosen", "chosen_ratio")}
                                     for n, v in pending.items()}}
        return {"active": False, "reason": "nothing detected" if k == 1 else f"explained after step {k - 1}"}
    if "screen" not in b.attrs:
        return {"active": False, "reason": b.attrs.get("screen_reason", "every catalog candidate is chosen")}
    return {"active": True, "reason": "", "effects": effects, "r": r, "screen": json.loads(b.attrs["screen"]),
            "band": prev_band}


def continuation_rejected(results, k: int) -> bool:
    """Whether step k was a continuation (its starting band explained the record) that added an
    effect after which the test detects again: that effect is not kept."""
    if k < 2 or absent(results, f"step{k}_trials") or absent(results, f"step{k}_band"):
        return False
    return (not results[f"step{k - 1}_band"].attrs.get("detected", False)
            and bool(results[f"step{k}_band"].attrs.get("detected", False)))


def runner_ups(ctx, results, k: int, held: set) -> dict:
    """Near-tied runner-ups of steps 1 … k − 1 (:func:`tubeid.diagnose._selection.near_ties`) still
    to be offered: not held now, not a candidate of a later step (tried there with the effects chosen
    since), not offered at an earlier continuation step. {name: {"signature" (from the screen of the
    step where it tied), "step", "ratio", "chosen", "chosen_ratio"}}; a continuation's own
    runner-ups are not offered again (each tie is resolved once)."""
    tie = ctx.settings.tie
    pending, offered = {}, set()
    for j in range(1, k):
        tr = results[f"step{j}_trials"]
        if tie <= 0 or skipped(tr):
            break
        prev = "band" if j == 1 else f"step{j - 1}_band"
        sel = selection(ctx, results, j)
        if j > 1 and not results[prev].attrs.get("detected", False):  # step j was itself a continuation
            offered |= {c["name"] for c in sel["candidates"]}
            continue
        for c in sel["candidates"]:  # tried here with the effects chosen since: its tie is resolved
            pending.pop(c["name"], None)
        screen = json.loads(results[prev].attrs["screen"])
        for name, (ratio, top) in near_ties(sel["candidates"], sel["chosen"], tie).items():
            if name in screen and name not in pending:
                pending[name] = {"signature": screen[name], "step": j, "ratio": ratio, "chosen": sel["chosen"],
                                 "chosen_ratio": top}
    return {n: v for n, v in pending.items() if n not in held and n not in offered}


def trial_block(block, rng, *, data, data_sha256, model, settings, trials, lines=""):
    ctx = method.load_context(data, data_sha256, model, settings)
    trials = json.loads(trials)
    meas = ctx.meas
    n, R = len(block["trial"]), ctx.settings.fit_realisations
    out = {"psd": np.full((n, meas.frequency.size, len(meas.sensors)), np.nan)}
    if _simplified(ctx):
        out |= {"fine": np.full((n, R, meas.frequency_fine.size, len(meas.sensors)), np.nan),
                "residual": np.full((n, R, meas.frequency.size, len(meas.sensors)), np.nan),
                "stats": np.full((n, R, len(meas.sensors), 3), np.nan)}
    for i, k in enumerate(block["trial"]):
        t = trials[int(k)]
        if not t.get("analytic"):
            o = _mean_model(ctx, t["r"], [effect_from_dict(e) for e in t["effects"]], rng(ctx.settings.seed))
            out["psd"][i] = o["psd"].mean(axis=0)
            for key in ("fine", "residual", "stats") if "fine" in out else ():
                out[key][i] = o[key]
    return out


def _trial_study(name, base, ctx, trials, what) -> Study:
    obs_coords, obs_units = _observation_coords(ctx, per_record=True)
    per = ("fit_realisation",)
    outputs = {"psd": _psd_output("mean model with the trial's effects, fitting layout (NaN: derived exactly from "
                                  "another trial)", finite=False),
               **_observation_outputs(ctx, "mean model with the trial's effects, per fitting-layout record", per)}
    if _simplified(ctx):
        outputs["stats"] = Output(dims=per + ("sensor", "statistic"), units="m | 1 | 1", finite=False,
                                  long_name="RMS [m], skewness, excess kurtosis per fitting-layout record")
        obs_coords["statistic"] = STATISTICS
    return Study(
        name=name, seed=SEED, description=what, axes={"trial": range(len(trials))}, chunks={"trial": 1}, seed_axes=(),
        task=trial_block, coords={**_spectral_coords(ctx), **obs_coords}, outputs=outputs,
        units={"frequency": "Hz", **obs_units}, parameters={**base, "trials": json.dumps(trials, sort_keys=True)})


def trial_observations(ctx, ds, trials) -> list[Observations]:
    """Per trial of a simplified-form trial stage, its fitting-layout records as :class:`Observations`."""
    fine, residual, stats = (ds[k].transpose("trial", "fit_realisation", *dims).values for k, dims in
                             (("fine", ("frequency_fine", "sensor")), ("residual", ("frequency", "sensor")),
                              ("stats", ("sensor", "statistic"))))
    return [Observations(ctx.meas.frequency, None, ctx.meas.frequency_fine, fine[i], residual[i], stats[i],
                         ctx.spec.band_hz, _segments(ctx, "fit")) for i in range(len(trials))]


def feature_name(ctx, candidate: str) -> str:
    """The robust statistic whose feature a candidate is fitted to with the simplified form: its
    catalog entry's ``feature`` when the record's fitting blocks can give it
    (:func:`~tubeid.diagnose._detection.feature_applies`: the profile needs its bands), else the
    first robust statistic that points to it."""
    own = CATALOG[candidate].feature
    if own is not None and feature_applies(own, record_observations(ctx, "fit"), ctx.settings.band_width_hz):
        return own
    return next(k for k, st in TEST_STATISTICS.items() if st.robust and candidate in st.effects)


#: With the simplified form, the line's error is read where the record or the trial has a line: bins
#: whose prominence stands this many band standard deviations from the band's mean.
LINE_EXCESS_Z = 3.0


class FeatureErrors:
    """Errors of the simplified form: for a robust statistic's feature φ (:func:`features`), the
    mean of ((φ(record) − φ̄(trial)) / σ)², φ̄ the mean over the trial's fitting-layout records and σ
    the standard deviation of φ over the realisations of the band before any effect (at least
    :data:`SCALE_FLOOR` for the line's prominence), on the record's fitting or held-out blocks. The
    line's mean is over the bins where the record or the trial stands :data:`LINE_EXCESS_Z` from the
    band's mean (a line touches a few of a thousand bins; all of them when none does)."""

    def __init__(self, ctx, results):
        self.ctx = ctx
        self.band = band_observations(ctx, results["band"])
        self.record = {w: record_observations(ctx, w) for w in ("fit", "held_out")}
        self._cache = {}

    def _unit(self, name):
        if name not in self._cache:
            w = self.ctx.settings.band_width_hz
            phi = features(name, self.band, w)
            sd = np.maximum(phi.std(axis=0, ddof=1), SCALE_FLOOR if name == "line" else 1e-6)
            self._cache[name] = (phi.mean(axis=0), sd, {k: features(name, o, w)[0] for k, o in self.record.items()})
        return self._cache[name]

    def __call__(self, name: str, obs: Observations) -> tuple[float, float]:
        """(fitting-block error, held-out error) of a trial's observations in feature ``name``."""
        mu, sd, rec = self._unit(name)
        phi = features(name, obs, self.ctx.settings.band_width_hz).mean(axis=0)
        out = []
        for k in ("fit", "held_out"):
            z2 = ((rec[k] - phi) / sd) ** 2
            if name == "line":
                mask = (np.abs(rec[k] - mu) > LINE_EXCESS_Z * sd) | (np.abs(phi - mu) > LINE_EXCESS_Z * sd)
                z2 = z2[mask] if np.any(mask) else z2
            out.append(float(np.mean(z2)))
        return tuple(out)


def _trials(k, results, base):
    ctx = _ctx(base)
    s = ctx.settings
    st = state_before(ctx, results, k)
    name = f"step{k}_trials"
    if not st["active"]:
        return End(st["reason"])  # the loop ends: no stage of this step or a later one is built
    held = json.loads(st["effects"])
    trials = [{"candidate": "", "effects": held, "r": st["r"]}]
    for n, sig in sorted(st["screen"].items(), key=lambda kv: list(CATALOG).index(kv[0])):
        cand = CATALOG[n]
        for e in cand.trials(sig["estimate"], ctx.spec, s.grid_points):
            trials.append({"candidate": n, "effects": held + [effect_to_dict(e)], "r": st["r"],
                           "analytic": _analytic(ctx, cand)})
    what = (f"step {k}: trial grids of {sorted(st['screen'])} (mean model, fitting blocks, chosen effects held)"
            + (": near-tied runner-ups, the record explained" if st.get("continuation") else ""))
    return _trial_study(name, base, ctx, trials, what)


def _analytic(ctx, cand) -> bool:
    """Whether a candidate's trials are derived from another trial's PSD instead of simulated: exact
    for the auto-PSDs only, so never with the simplified form (its features need the records)."""
    return cand.exact_from_baseline and not _simplified(ctx)


def _trial_psds(ds, trials, centre=0) -> np.ndarray:
    """The trials' PSDs (T, F, m), the analytic ones derived from trial ``centre``."""
    psd = ds["psd"].transpose("trial", "frequency", "sensor").values.copy()
    base_effects = {json.dumps(e, sort_keys=True) for e in trials[centre]["effects"]}
    for i, t in enumerate(trials):
        if t.get("analytic"):
            new = [effect_from_dict(e) for e in t["effects"] if json.dumps(e, sort_keys=True) not in base_effects]
            old = [effect_from_dict(e) for e in trials[centre]["effects"]
                   if json.dumps(e, sort_keys=True) not in {json.dumps(x, sort_keys=True) for x in t["effects"]}]
            p = psd[centre].copy()
            for e in old:
                p = CATALOG[e.name].from_baseline(e, p, remove=True)
            for e in new:
                p = CATALOG[e.name].from_baseline(e, p)
            psd[i] = p
    return psd


def _variants(ctx, trials, psd, obs) -> None:
    """Append the derived trials (a tone's amplitude profile) to ``trials``, ``psd`` and, with the
    simplified form, ``obs`` (the fine PSD of each record scaled the same way), in place."""
    for i in range(1, len(trials)):
        t = trials[i]
        effect = effect_from_dict(t["effects"][-1])
        cand = CATALOG[t["candidate"]]
        derived = cand.variants(effect, psd[i], psd[0], ctx.meas.frequency)
        if obs is not None and derived:
            ff = ctx.meas.frequency_fine
            per = [cand.variants(effect, obs[i].fine[j], obs[0].fine[j], ff) for j in range(obs[i].n)]
        for v, (e, q) in enumerate(derived):
            trials.append({**t, "effects": t["effects"][:-1] + [effect_to_dict(e)], "derived": i})
            psd.append(q)
            if obs is not None:
                obs.append(dataclasses.replace(obs[i], fine=np.stack([p[v][1] for p in per])))


def selection(ctx, results, k: int) -> dict:
    """The choice of step k from its trials (see :mod:`tubeid.diagnose._selection`): {"current"
    (the held-out error of the model so far), "candidates" ([{name, k, fit_error, held_out_error,
    current, penalised, trials, effect, offset, feature}]), "chosen" (name or ""), "effects" (JSON list with
    the chosen effect), "r" (levelled by the chosen trial's offset)}.

    Exact form: every error is the spectrum's (:func:`_errors`). Simplified form: a candidate's
    errors, and the current model's it is compared with, are those of the feature of the robust
    statistic that points to it (:class:`FeatureErrors`); r is not levelled."""
    s = ctx.settings
    ds = results[f"step{k}_trials"]
    trials = list(json.loads(_params(ds)["trials"]))
    psd = list(_trial_psds(ds, trials))
    obs = trial_observations(ctx, ds, trials) if _simplified(ctx) else None
    _variants(ctx, trials, psd, obs)
    sigma = _sigma(results)
    spectrum = [_errors(ctx, p, sigma) for p in psd]
    fe = FeatureErrors(ctx, results) if obs is not None else None
    scored, info = [], []
    for n in dict.fromkeys(t["candidate"] for t in trials[1:]):
        idx = [i for i, t in enumerate(trials) if t["candidate"] == n]
        if fe is None:
            errs, feat = {j: spectrum[j] for j in [0, *idx]}, "spectrum"
        else:
            feat = feature_name(ctx, n)
            errs = {j: (0.0, *fe(feat, obs[j])) for j in [0, *idx]}
        i = min(idx, key=lambda j: errs[j][1])
        kk = CATALOG[n].n_parameters(ctx.spec)
        sc = Scored(n, kk, errs[i][1], errs[i][2], errs[0][2])
        scored.append(sc)
        info.append({"name": n, "k": kk, "feature": feat, "fit_error": errs[i][1], "held_out_error": errs[i][2],
                     "current": errs[0][2], "penalised": sc.penalised(s.penalty), "trials": len(idx),
                     "effect": trials[i]["effects"][-1], "offset": errs[i][0], "trial": i})
    current = spectrum[0][2]
    c = choose(scored, current, s.penalty)
    out = {"current": current, "candidates": info, "chosen": "" if c is None else c.name}
    if c is not None:
        best = next(x for x in info if x["name"] == c.name)
        out["effects"] = json.dumps(trials[best["trial"]]["effects"], sort_keys=True)
        out["r"] = list(scaled_r(trials[0]["r"], best["offset"]))
    return out


def _surrogate(ctx, results, effects, r, band_stage):
    """The linear surrogate of the declared model with ``effects`` at ``r``, its contact weight
    from the band stage ``band_stage``."""
    from tubeid.diagnose._surrogate import LinearSurrogate

    spec = apply_effects(ctx.spec, effects)
    sur = LinearSurrogate(spec, load_spectrum(spec, r, ctx.settings), ctx.meas.frequency)
    ds = results[band_stage]
    sur.contact = float(np.mean(ds["contact"].sel(realisation=ds["realisation"].values >= 0).values))
    return sur


def _stage_name(k: int, kind: str, sweep: int = 1) -> str:
    """The stage of step k's ``kind`` ("refit" or "check") in re-fit sweep ``sweep`` (1: no suffix)."""
    return f"step{k}_{kind}" + ("" if sweep == 1 else str(sweep))


def sweep_reason(ctx, results, k: int, sweep: int) -> str:
    """Why step k needs re-fit sweep ``sweep`` + 1 around the point sweep ``sweep`` kept ("" if it
    does not): a line whose discrete minimum is at an end (it did not bracket its parameter: the
    moves of lines evaluated one at a time are then biased where parameters trade off, e.g. r
    against a stop's gap), or a kept point other than the moved one."""
    rf = refit_result(ctx, results, k, sweep=sweep)
    ends = [ln["parameter"] for ln in rf["lines"] if np.isfinite(ln["errors"]).any()
            and int(np.nanargmin(ln["errors"])) in (0, len(ln["errors"]) - 1)]
    pt = refit_point(ctx, results, k, rf, sweep=sweep)
    why = [f"the lines of {', '.join(ends)} did not bracket their minimum"] if ends else []
    if pt["point"] != "moved":
        why.append(f"the {pt['point']} point was kept, not the moved one")
    return "; ".join(why)


def _refit(k, results, base, sweep=1):
    ctx = _ctx(base)
    name = _stage_name(k, "refit", sweep)
    if sweep == 1:
        sel = selection(ctx, results, k)
        if not sel["chosen"]:
            return End(f"no candidate pays its penalty at step {k}")
        effects, r = [effect_from_dict(e) for e in json.loads(sel["effects"])], [float(v) for v in sel["r"]]
    else:
        if absent(results, _stage_name(k, "refit", sweep - 1)):
            return _skipped(name, f"no re-fit sweep {sweep - 1}")
        why = sweep_reason(ctx, results, k, sweep - 1)
        if not why:
            return _skipped(name, f"sweep {sweep - 1} bracketed every parameter and kept its moved point")
        pt = refit_point(ctx, results, k, sweep=sweep - 1)
        effects, r = method.effects_from_json(pt["effects"]), [float(v) for v in pt["r"]]
    centre = {"effects": [effect_to_dict(e) for e in effects], "r": r}
    trials, lines = [dict(centre)], []
    for j in range(0 if _simplified(ctx) else len(r)):  # simplified: r held (the features are level-free)
        values = [r[j] * 10.0**u for u in (-0.1, 0.0, 0.1)]
        idx = []
        for v in values:
            if v == r[j]:
                idx.append(0)
                continue
            rr = list(r)
            rr[j] = float(v)
            trials.append({"effects": centre["effects"], "r": rr})
            idx.append(len(trials) - 1)
        lines.append({"what": "r", "index": j, "parameter": R_DIMS[j], "log": True, "values": values, "trials": idx})
    sur = _surrogate(ctx, results, effects, r, "band" if k == 1 else f"step{k - 1}_band")
    for i, e in enumerate(effects):
        cand = CATALOG[e.name]
        if cand.profiled is not None:  # its line is derived from the centre and this baseline (refit_result)
            trials.append({"effects": [x for j, x in enumerate(centre["effects"]) if j != i], "r": r, "baseline": i})
            lines.append({"what": "effect", "index": i, "parameter": cand.profiled, "log": True,
                          "baseline": len(trials) - 1})
        for par, (values, log, variants) in cand.refine(e, ctx.spec, sur).items():
            idx = []
            for v, ev in zip(values, variants):
                if ev == e:
                    idx.append(0)
                    continue
                eff = list(centre["effects"])
                eff[i] = effect_to_dict(ev)
                trials.append({"effects": eff, "r": r, "analytic": _analytic(ctx, cand)})
                idx.append(len(trials) - 1)
            lines.append({"what": "effect", "index": i, "parameter": par, "log": log, "values": [float(v) for v in values],
                          "trials": idx})
    st = _trial_study(name, base, ctx, trials, f"step {k}: joint re-fit of r and {[e.name for e in effects]} (lines of 3"
                                               + (")" if sweep == 1 else f", sweep {sweep}: {why})"))
    # every sweep draws the first one's streams (common random numbers): its centre's error is the point's it starts from
    return dataclasses.replace(st, parameters={**st.parameters, "lines": json.dumps(lines, sort_keys=True)},
                               stream_key=(_stage_name(k, "refit"),))


def fit_errors(ctx, results, ds) -> list[float]:
    """The fitting-block error of every trial of a re-fit or check stage: the spectrum's (exact form),
    else the sum over the trial's effects of their features' errors (:class:`FeatureErrors`)."""
    trials = json.loads(_params(ds)["trials"])
    if not _simplified(ctx):
        sigma = _sigma(results)  # once: its moments run over every realisation of the band
        return [prediction_error(ctx.meas.fit, q, sigma, ctx.meas.frequency) for q in _trial_psds(ds, trials)]
    fe = FeatureErrors(ctx, results)
    names = list(dict.fromkeys(feature_name(ctx, e["kind"]) for e in trials[0]["effects"]))
    return [sum(fe(n, o)[0] for n in names) for o in trial_observations(ctx, ds, trials)]


def _profiled_line(ctx, results, ds, trials, ln, centre_fit_error) -> tuple[list, list, list]:
    """A profiled parameter's re-fit line (``Candidate.profiled``): the centre trial and its
    :meth:`~tubeid.diagnose.catalog.Candidate.variants` against the baseline trial ``ln["baseline"]``
    (the same model without the effect, the same streams) → (values, fitting errors, effect lists
    as dicts), by increasing value. Errors as :func:`fit_errors` computes them; the derived points'
    are estimates (their PSDs derived, not simulated), compared as they are with the simulated
    points' when the re-fit keeps its best evaluated point (a second sweep then simulates it)."""
    i, jb, f = ln["index"], ln["baseline"], ctx.meas.frequency
    effect = effect_from_dict(trials[0]["effects"][i])
    cand = CATALOG[effect.name]
    psd = _trial_psds(ds, trials)
    derived = cand.variants(effect, psd[0], psd[jb], f)
    if _simplified(ctx):
        obs = trial_observations(ctx, ds, trials)
        ff = ctx.meas.frequency_fine
        per = [cand.variants(effect, obs[0].fine[j], obs[jb].fine[j], ff) for j in range(obs[0].n)]
        fe = FeatureErrors(ctx, results)
        names = list(dict.fromkeys(feature_name(ctx, e["kind"]) for e in trials[0]["effects"]))
        errs = [sum(fe(n, dataclasses.replace(obs[0], fine=np.stack([q[v][1] for q in per])))[0] for n in names)
                for v in range(len(derived))]
    else:
        sigma = _sigma(results)
        errs = [prediction_error(ctx.meas.fit, q, sigma, f) for _, q in derived]
    effects = [[effect_to_dict(e) if j == i else x for j, x in enumerate(trials[0]["effects"])] for e, _ in derived]
    rows = sorted(zip([getattr(effect, ln["parameter"])] + [getattr(e, ln["parameter"]) for e, _ in derived],
                      [centre_fit_error] + errs, [trials[0]["effects"]] + effects), key=lambda row: row[0])
    return tuple(list(col) for col in zip(*rows))


def refit_result(ctx, results, k: int, sweep: int = 1) -> dict:
    """The joint re-fit of step k: each line's minimiser (fitting blocks, no level profiling: r is
    one of the lines, exact form) → {"effects" (JSON), "r" (the moved point), "lines" ([{what,
    parameter, values, errors, best, extension}]), "extended" ({"effects", "r"}: the moved point with
    every simulated log line whose best is at an end one step further, or None when none is),
    "centre_fit_error", "best_trial" ({"effects", "r", "fit_error"}: the best trial the lines
    evaluated, a profiled line's derived points included, the baselines of those lines not)}; of re-fit
    sweep ``sweep``."""
    ds = results[_stage_name(k, "refit", sweep)]
    p = _params(ds)
    trials, lines = json.loads(p["trials"]), json.loads(p["lines"])
    fit_err = fit_errors(ctx, results, ds)
    centre = [effect_from_dict(e) for e in trials[0]["effects"]]
    r, r_ext = list(trials[0]["r"]), list(trials[0]["r"])
    report, best_of, ext_of = [], {}, {}
    # every evaluated point but the profiled lines' baselines (models without a chosen effect): (error, effects, r)
    evaluated = [(fit_err[j], t["effects"], t["r"]) for j, t in enumerate(trials) if "baseline" not in t]
    for ln in lines:
        if "baseline" in ln:
            values, errs, effs = _profiled_line(ctx, results, ds, trials, ln, fit_err[0])
            evaluated += [(e, x, trials[0]["r"]) for e, x in zip(errs, effs) if x != trials[0]["effects"]]
            ext = None  # the profile spans ±0.5 decades: a step further would add a simulation for little
        else:
            values, errs = ln["values"], [fit_err[i] for i in ln["trials"]]
            # a log line (every scale: r, gaps, factors, ratios, levels) at its edge is extended one
            # step in the check; a tone's position line is not (its grid is the tube's half-element nodes)
            ext = line_extension(values, errs) if ln["log"] else None
        best = line_minimum(values, errs, ln["log"])
        report.append({**{k_: ln[k_] for k_ in ("what", "index", "parameter")}, "values": [float(v) for v in values],
                       "errors": errs, "best": best, "extension": ext})
        if ln["what"] == "r":
            r[ln["index"]] = best
            r_ext[ln["index"]] = best if ext is None else ext
        else:
            best_of.setdefault(ln["index"], {})[ln["parameter"]] = best
            ext_of.setdefault(ln["index"], {})[ln["parameter"]] = best if ext is None else ext
    sur = _surrogate(ctx, results, centre, trials[0]["r"], "band" if k == 1 else f"step{k - 1}_band")
    effects, extended = list(centre), list(centre)
    for i, best in best_of.items():
        effects[i] = CATALOG[centre[i].name].combine(centre[i], best, ctx.spec, sur)
    for i, ext in ext_of.items():  # a scale moved by a ratio stays positive; a damping ratio stops at 0.9
        extended[i] = CATALOG[centre[i].name].combine(centre[i], ext, ctx.spec, sur)
    moved = {"effects": method.effects_to_json(effects), "r": [float(v) for v in r]}
    ext_point = {"effects": method.effects_to_json(extended), "r": [float(v) for v in r_ext]}
    errs = np.array([e for e, _, _ in evaluated], dtype=float)
    b = int(np.nanargmin(errs)) if np.isfinite(errs).any() else 0
    return {**moved, "lines": report, "extended": None if ext_point == moved else ext_point,
            "centre_fit_error": fit_err[0],
            "best_trial": {"effects": json.dumps(evaluated[b][1], sort_keys=True), "r": [float(v) for v in evaluated[b][2]],
                           "fit_error": evaluated[b][0]}}


def _check(k, results, base, sweep=1):
    """The point every line of the re-fit moved to, evaluated (the lines were evaluated one at a time;
    together the moves can overshoot when parameters trade off, e.g. a stop's gap against r). Drawn
    with the re-fit's streams (common random numbers), so its error compares with the re-fit's."""
    ctx = _ctx(base)
    name = _stage_name(k, "check", sweep)
    if absent(results, _stage_name(k, "refit", sweep)):  # a sweep after the first that was not needed
        return _skipped(name, f"no re-fit sweep {sweep}")
    rf = refit_result(ctx, results, k, sweep=sweep)
    trials = [{"effects": json.loads(p["effects"]), "r": p["r"]} for p in (rf, rf["extended"]) if p is not None]
    st = _trial_study(name, base, ctx, trials, f"step {k}: the re-fit's moved point (and with its edge lines one step "
                                               "further), evaluated" + ("" if sweep == 1 else f" (sweep {sweep})"))
    return dataclasses.replace(st, stream_key=(_stage_name(k, "refit"),))


def refit_point(ctx, results, k: int, rf: dict | None = None, sweep: int = 1) -> dict:
    """Where re-fit sweep ``sweep`` of step k ends (:func:`~tubeid.diagnose._selection.refit_choice`):
    the re-fit's extended point if its fitting-block error is lower than both others, else its moved
    point if no worse than the best point the re-fit evaluated, else that point → {"effects" (JSON),
    "r", "moved_fit_error", "best_fit_error", "extended_fit_error" (None: no line at an end), "point"
    ("moved", "best" or "extended"), "fallback" (bool: "best")}. ``rf``: :func:`refit_result` if at
    hand. A sweep after the first evaluates its centre, the point the previous sweep kept, with the
    same streams: the best point it evaluated is never worse than that one."""
    rf = refit_result(ctx, results, k, sweep=sweep) if rf is None else rf
    errs = fit_errors(ctx, results, results[_stage_name(k, "check", sweep)])
    moved, extended = errs[0], (errs[1] if rf["extended"] is not None else None)
    best = rf["best_trial"]
    which = refit_choice(moved, best["fit_error"], extended)
    chosen = {"best": best, "moved": rf, "extended": rf["extended"]}[which]
    return {"effects": chosen["effects"], "r": chosen["r"], "moved_fit_error": moved, "best_fit_error": best["fit_error"],
            "extended_fit_error": extended, "point": which, "fallback": which == "best"}


def sweeps_done(results, k: int) -> int:
    """How many re-fit sweeps step k ran (0: no effect chosen)."""
    return sum(1 for sweep in range(1, REFIT_SWEEPS + 1) if not absent(results, _stage_name(k, "refit", sweep)))


def final_point(ctx, results, k: int) -> dict:
    """The point step k's band is computed at: :func:`refit_point` of its last re-fit sweep."""
    return refit_point(ctx, results, k, sweep=sweeps_done(results, k))


def _band_k(k, results, base):
    ctx = _ctx(base)
    name = f"step{k}_band"
    pt = final_point(ctx, results, k)
    return _band_study(name, base, ctx, pt["r"], pt["effects"], _delta(results),
                       results["load_delta_f"].attrs["delta_F_used"], k, f"after step {k}")


def point_result(ctx, results, k: int) -> dict:
    """The mean model at the point of band stage k (0: before any effect; k: after step k's
    re-fit): {"effects", "r", "offset", "fit_error", "held_out_error"}."""
    ds = results["band" if k == 0 else f"step{k}_band"]
    p = _params(ds)
    o, fe, he = _errors(ctx, mean_prediction(ds), _sigma(results))
    return {"effects": json.loads(p["effects"]), "r": p["r"], "offset": o, "fit_error": fe, "held_out_error": he}


def _builder(kind: str):
    """The stage builder of ``kind`` (a key of :data:`STEP_STAGES`)."""
    base = kind.rstrip("0123456789")
    sweep = int(kind[len(base):] or 1)
    fn = {"trials": _trials, "refit": _refit, "check": _check, "band": _band_k}[base]
    return fn if sweep == 1 else functools.partial(fn, sweep=sweep)


def _step_stage(k: int, kind: str):
    build = _builder(kind)

    def stage(results, *, data, data_sha256, model, settings):
        return build(k, results, _base(data, data_sha256, model, settings))

    stage.__name__ = stage.__qualname__ = f"step{k}_{kind}"
    return stage


study = Pipeline(
    name="diagnose",
    seed=SEED,
    description="tubeid diagnose: delta, load (r, delta_F), the calibrated test, forward selection of effects with joint re-fits",
    stages=[delta_ml, load_r, load_r_fine, load_delta_f, band,
            *[_step_stage(k, kind) for k in range(1, MAX_EFFECTS + 1) for kind in STEP_STAGES]],
    warmup=Warmup(warmup.MESSAGE, run=warmup.compile_solver, needed=warmup.cache_is_cold),
    parameters={
        "data": Parameter("", doc="path of the validated record (NetCDF written by tubeid diagnose)"),
        "data_sha256": Parameter("", doc="content hash of the record (tubeid.diagnose.method.data_hash)"),
        "model": Parameter("", doc="declared model: JSON of spec_to_dict"),
        "settings": Parameter("", doc="DiagnoseSettings.to_json()"),
    },
)
