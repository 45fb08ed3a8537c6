"""``tubeid report STORE [--out DIR]``: the figures and the summary of a paper study store.

The store is the Zarr store of ``studies/paper.py``, one group per stage (each opened with
``xarray.open_zarr(store, group=NAME)``; the stage's ``parameters`` and summary are attributes):

* ``delta``: ``J`` (delta, realisation) [m² rad/(N² s)], attribute ``J_ref`` (one value or several
  observations) → the likelihood of δ (Figure 5).
* ``reference``: ``psd_reference`` (experiment, frequency[, sensor, sensor_]), the experimental
  record(s); ``psd_mean`` (experiment, …), the mean simplified model under the same load history
  (Figure 4); attributes ``estimator``, ``record_seconds`` and, for a synthetic experiment, the
  truth ``truth_<quantity>``.
* ``calibration``: ``psd`` (realisation, …), realisations of the experiment's generator independent
  of the record: the reference model's own 95 % region (the calibration of the coverage).
* ``response``: ``psd`` (realisation, …), the stochastic simplified model at the δ in its
  ``parameters`` (Figure 6).
* ``load_r``, ``load_r_fine``: ``psd`` (r1, r2, realisation, …) on the coarse and the fine trial grid.
* ``load_delta_f``: ``J_s`` (delta_F, realisation), attribute ``J_s_exp``; its ``parameters`` hold
  the r passed downstream (``r1``, ``r2``, ``distance``) and r_opt of every distance
  (``r_identification``, JSON). When the experiment has record pairs of one structure (the
  synthetic one), also ``level_difference`` (delta_F, realisation) and ``level_difference_exp``:
  δ_F from the pairs (``delta_f_pairs_likelihood.png``, beyond the paper).

The report reads what the study stored and passed downstream (δ used, r_opt per distance, δ_opt,
δ_F,opt); it recomputes, with the same functions (``tubeid.identification``), only the bootstrap
spreads, and says so if a recomputed point estimate ever differs from the stored one. PSDs are
two-sided per Hz (m²/Hz), complex or real. Realisations with missing values (a partial run reads
them as NaN) are left out and counted; a missing stage is reported, not fatal (a paper store whose
later stages are not written yet is reported as far as it goes). What is not a paper study store (not
a Zarr group, a Zarr store with none of the groups above, e.g. another study's store, or a tubeid
pipeline store without all of them among its stages, e.g. ``studies/two_stage.py``'s, whose stages
``delta`` and ``response`` share the paper's names) is refused before anything is written, as is an
unknown ``sensor``.

Writes into DIR (default: ``<store>-report`` beside the store), through ``tubeid._outputs.OutputDir``
(a file there that tubeid did not write, e.g. the user's own ``summary.md``, is never overwritten:
the report is refused before anything is written): fig4_mean_model.png, fig5_delta_likelihood.png,
fig6_confidence_region.png, d_map.png, delta_f_likelihood.png (and delta_f_pairs_likelihood.png),
summary.md and summary.json. Outputs
of an earlier report in DIR that this run does not produce are removed (only if unchanged). The
figures are rendered in memory and the files written only once the whole report is computed: a report
that fails or is interrupted (Ctrl-C) before leaves DIR as it was (and no DIR if it created it); one
interrupted while writing removes the report files tubeid wrote there (no mix of two reports), never
another file.

Definitions used in the summary:

* **coverage** of a 95 % region: the fraction of frequency bins in (lo, hi] Hz (bands "0-100",
  "0-35", "35-100") where a record's PSD lies between the 2.5 % and 97.5 % quantiles of the model's
  realisations, averaged over the records (:func:`region_coverage`). ``reference_coverage``: the
  stochastic simplified model's region (stage ``response``) against the experimental record;
  ``reference_self_coverage``: the reference model's own region (stage ``calibration``, as many
  realisations, same estimator) against the same record — what a perfect model would score.
* **grid edge**: the optimum sits on the first or last grid value: a bound, not an estimate.
* **flat** likelihood (``tubeid.identification.likelihood``): the log-likelihood varies across the
  whole grid by less than max(1.92, 2 bootstrap σ): the data exclude no grid value at 95 %.
  A flat or edge optimum is never said to agree with a target value.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from pathlib import Path

import numpy as np
import xarray as xr

from tubeid._outputs import OutputDir
from tubeid._validation import replicates, seed as _seed
from tubeid.dynamics.spectra import confidence_band, j_s
from tubeid.errors import SpecificationError
from tubeid._paths import local_path
from tubeid.identification.likelihood import LR_THRESHOLD, likelihood_curve
from tubeid.identification.loads import JS_UNITS, delta_f_likelihood
from tubeid.identification.trial import DISTANCES, identify_r
from tubeid.seeds import rng_for

__all__ = ["register", "make_report", "region_coverage", "PAPER_VALUES", "STAGES", "OUTPUTS", "COVERAGE_BANDS"]

#: The paper's identified values (Batou & Soize 2008, §5.4–5.6).
PAPER_VALUES = {"delta_opt": 0.45, "r1_opt": 18.0, "r2_opt": 20.0, "delta_F_opt": 0.04}
#: The analysis sections of the report (each reads one or more groups of the store).
STAGES = ("delta", "response", "load_r", "load_delta_f")
#: The groups of a paper study store (the stages of ``studies/paper.py``).
GROUPS = ("delta", "reference", "calibration", "response", "load_r", "load_r_fine", "load_delta_f")
FIGURES = ("fig4_mean_model.png", "fig5_delta_likelihood.png", "fig6_confidence_region.png", "d_map.png",
           "delta_f_likelihood.png", "delta_f_pairs_likelihood.png")
#: Every file the report may write.
OUTPUTS = FIGURES + ("summary.md", "summary.json")
#: Frequency bands of the coverage, (lo, hi] Hz.
COVERAGE_BANDS = {"0-100": (0.0, 100.0), "0-35": (0.0, 35.0), "35-100": (35.0, 100.0)}
J_UNITS_DEFAULT = "m^2 rad/(N^2 s)"
_UNITS = {"delta_opt": "1", "r1_opt": "N^2/Hz", "r2_opt": "(N m)^2/Hz", "delta_F_opt": "1", "delta_F_pairs_opt": "1"}
_LABELS = {"delta_opt": "δ_opt (dispersion of K_B)", "r1_opt": "r1,opt (force T)", "r2_opt": "r2,opt (moment M)",
           "delta_F_opt": "δ_F,opt (load dispersion)",
           "delta_F_pairs_opt": "δ_F,opt from record pairs (beyond the paper)"}
#: Quantities compared with another quantity's target: δ_F identified a second way.
_TARGET_OF = {"delta_F_pairs_opt": "delta_F_opt"}
#: The identified quantities in the order of the tables (the last only when the store has it).
_KEYS = ("delta_opt", "r1_opt", "r2_opt", "delta_F_opt", "delta_F_pairs_opt")
_OPTIONAL = ("delta_F_pairs_opt",)
_SENSOR_DIMS = ("sensor", "sensor_")
_LEVEL = 0.95


# ---------------------------------------------------------------------- small helpers
def _num(v):
    """JSON-safe float (NaN/inf -> None)."""
    if v is None:
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return _num(obj)
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    return obj


def _fmt(v, digits=3):
    if isinstance(v, (list, tuple)):  # several observations
        return f"{len(v)} observations, mean {_fmt(float(np.mean(v)), digits)}"
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return f"{v:.{digits}g}"


def _pct(v):
    return "n/a" if v is None else f"{100 * v:.0f} %"


class _StageMissing(Exception):
    """A stage cannot be analysed; the message says why."""


class _Store:
    """The groups of a paper store, opened once (lazily), with their parameters.

    Opening refuses (``SpecificationError``) what is not a paper study store: a path that is not a
    Zarr group, a Zarr store with none of the paper study's groups (:data:`GROUPS`), and a pipeline
    store of tubeid whose stages (all listed from its start) are not all the paper study's. A paper
    store whose later stages are not written yet is a paper store: the report lists them as missing.
    """

    def __init__(self, path: str):
        self.path = path
        self._groups: dict = {}
        import zarr

        local_path(path)  # never a URL zarr would read elsewhere
        if not os.path.isdir(path):
            raise SpecificationError("store", path, "is not a Zarr store (not a directory): give the store that "
                                     "`tubeid run studies/paper.py` wrote")
        try:
            with warnings.catch_warnings():  # tubeid's own files in a store (its manifest, its lock) are not Zarr nodes
                warnings.simplefilter("ignore")
                root = zarr.open_group(path, mode="r", use_consolidated=False)
                self.root = dict(root.attrs)
                members = set(root.group_keys())
        except Exception as exc:  # zarr raises several not-a-group types across versions
            raise SpecificationError("store", path, f"is not a Zarr store ({type(exc).__name__}): give the store "
                                     "that `tubeid run studies/paper.py` wrote") from None
        from tubeid.runner.status import FORMAT, PIPELINE_FORMAT

        stages = self.root.get("stages")
        stages = set(stages) if isinstance(stages, list) and all(isinstance(n, str) for n in stages) else set()
        fmt, name = self.root.get("format"), self.root.get("study_name")
        if fmt == PIPELINE_FORMAT and stages and not set(GROUPS) <= stages:
            # a tubeid pipeline lists all its stages from the start: another pipeline whose stages share a
            # name with the paper's (studies/two_stage.py: delta, response) is not the paper study
            raise SpecificationError("store", path, f"is not a paper study store: a tubeid pipeline store (pipeline "
                                     f"{name!r}, stages {sorted(stages)}) without the paper study's stages "
                                     f"{', '.join(g for g in GROUPS if g not in stages)} (a paper store is written "
                                     "by `tubeid run studies/paper.py`)")
        if not set(GROUPS) & (members | stages):
            what = (f"a tubeid study store (study {name!r})" if fmt == FORMAT else
                    f"a tubeid pipeline store (pipeline {name!r}, stages {sorted(stages)})"
                    if fmt == PIPELINE_FORMAT else "a Zarr store"
                    + (f" (groups {sorted(members)[:8]})" if members else ""))
            raise SpecificationError("store", path, f"is not a paper study store: {what} with none of the paper "
                                     f"study's groups {', '.join(GROUPS)} (a paper store is written by "
                                     "`tubeid run studies/paper.py`)")
        self.parameters = self._json(self.root.get("parameters"))

    @staticmethod
    def _json(text) -> dict:
        try:
            return json.loads(text) if isinstance(text, str) else dict(text or {})
        except (ValueError, TypeError):
            return {}

    def group(self, name: str) -> xr.Dataset:
        if name not in self._groups:
            try:
                with warnings.catch_warnings():  # stores written group by group may lack consolidated metadata
                    warnings.filterwarnings("ignore", message=".*consolidated metadata.*", category=RuntimeWarning)
                    self._groups[name] = xr.open_zarr(self.path, group=name)
            except (KeyError, FileNotFoundError, ValueError, OSError) as exc:
                status = self.root.get("stage_status")
                state = status.get(name) if isinstance(status, dict) else None
                self._groups[name] = _StageMissing(
                    f"stage not written yet (its state in the store: {state}): the run has not reached it; "
                    "`tubeid status` says how far it is, the same `tubeid run` resumes it" if state == "pending" else
                    f"group '{name}' not found in the store ({type(exc).__name__})")
            except Exception as exc:  # zarr raises several group-not-found types across versions
                self._groups[name] = _StageMissing(f"group '{name}' could not be opened ({type(exc).__name__}: {exc})")
        g = self._groups[name]
        if isinstance(g, _StageMissing):
            raise g
        return g

    def has(self, name: str) -> bool:
        try:
            self.group(name)
            return True
        except _StageMissing:
            return False

    def stage_parameters(self, name: str) -> dict:
        try:
            return self._json(self.group(name).attrs.get("parameters"))
        except _StageMissing:
            return {}


def _variable(ds: xr.Dataset, group: str, name: str) -> xr.DataArray:
    if name not in ds.data_vars:
        raise _StageMissing(f"variable '{name}' missing from group '{group}'")
    return ds[name]


def _attr(ds: xr.Dataset, var: str, name: str):
    if name in ds.attrs:
        return ds.attrs[name]
    if var in ds and name in ds[var].attrs:
        return ds[var].attrs[name]
    return None


def _complete(da: xr.DataArray, dim: str, label: str, notes: list, min_n: int) -> xr.DataArray:
    """Keep the realisations of ``dim`` that are finite everywhere; note how many were dropped."""
    if dim not in da.dims:
        raise _StageMissing(f"{label} has no '{dim}' dimension (dims {tuple(da.dims)})")
    v = da.values
    other = tuple(i for i in range(v.ndim) if da.dims[i] != dim)
    ok = np.all(np.isfinite(v), axis=other)
    n, k = ok.size, int(ok.sum())
    if k < n:
        notes.append(f"{label}: {k} of {n} realisations complete (partial run); the others are left out")
    if k < min_n:
        raise _StageMissing(f"{label}: only {k} complete realisations (need {min_n})")
    return da.isel({dim: np.flatnonzero(ok)}).load()


def _sensor_index(da: xr.DataArray, sensor) -> int:
    if "sensor" not in da.dims:
        return 0
    names = [str(s) for s in da["sensor"].values] if "sensor" in da.coords else []
    if sensor is not None:
        if sensor not in names:
            raise SpecificationError("sensor", sensor, f"not among the store's sensors {names}")
        return names.index(sensor)
    return names.index("P_obs") if "P_obs" in names else 0


def _auto(da: xr.DataArray, sensor) -> xr.DataArray:
    """Real auto-spectrum of the chosen sensor (dims: everything but the sensor dims)."""
    if "sensor" in da.dims:
        i = _sensor_index(da, sensor)
        da = da.isel(sensor=i, sensor_=i, drop=True)
    return xr.DataArray(np.real(da.values), dims=da.dims, coords={d: da[d] for d in da.dims if d in da.coords})


def _sensor_name(da: xr.DataArray, sensor) -> str:
    """The chosen sensor's name; an unknown one is refused (a PSD without a sensor dimension is P_obs's)."""
    if "sensor" in da.dims and "sensor" in da.coords:
        return str(da["sensor"].values[_sensor_index(da, sensor)])
    if "sensor" in da.dims:
        _sensor_index(da, sensor)  # unnamed sensors: none can be chosen by name
    elif sensor is not None and sensor != "P_obs":
        raise SpecificationError("sensor", sensor, "not among the store's sensors ['P_obs'] (its PSDs have no "
                                 "sensor dimension: they are P_obs's, the paper's observation point)")
    return "P_obs"


def _as_written(name) -> str:
    """A sensor's name as a figure shows it: dollar signs escaped (matplotlib would parse ``a$x$`` as TeX)."""
    return str(name).replace("$", r"\$")


def _figure(height=4.4):
    from tubeid._optional import require

    Figure = require("matplotlib.figure", "tubeid report").Figure

    return Figure(figsize=(7.0, height), layout="constrained")


def _in_band(da: xr.DataArray, band: float) -> xr.DataArray:
    return da.sel(frequency=da["frequency"] <= band * (1 + 1e-12))


def _records(store: _Store, notes: list) -> xr.DataArray:
    """The experimental PSD(s), dims (record, frequency[, sensors])."""
    ref = _variable(store.group("reference"), "reference", "psd_reference")
    if "experiment" in ref.dims:
        ref = ref.rename(experiment="record")
    elif "record" not in ref.dims:
        ref = ref.expand_dims(record=[0])
    return _complete(ref, "record", "reference.psd_reference", notes, 1)


def region_coverage(samples, records, *, level: float = _LEVEL, bands=None, dim: str = "realisation") -> dict:
    """Fraction of frequency bins where each record lies inside the samples' quantile region.

    Parameters
    ----------
    samples : xarray.DataArray
        Real PSD realisations (``dim``, "frequency") [m²/Hz], the region's model.
    records : xarray.DataArray
        Real PSD(s) ("frequency") or (record, "frequency") on the same frequencies [m²/Hz].
    level : float
        Probability of the region: between the (1 − level)/2 and (1 + level)/2 quantiles over ``dim``
        (``tubeid.dynamics.spectra.confidence_band``), bounds included.
    bands : mapping, optional
        {name: (lo, hi)} in Hz; a bin f counts in a band when lo < f ≤ hi (DC never counts). Default
        :data:`COVERAGE_BANDS`.

    Returns
    -------
    dict
        {band name: fraction in [0, 1], averaged over the records; None for a band without bins}.
    """
    bands = COVERAGE_BANDS if bands is None else bands
    cb = confidence_band(samples, level, dim=dim)
    if set(records.dims) not in ({"frequency"}, {"record", "frequency"}):
        raise SpecificationError("records.dims", records.dims, "must be ('frequency',) or ('record', 'frequency')")
    if set(samples.dims) != {dim, "frequency"}:
        raise SpecificationError("samples.dims", samples.dims, f"must be ({dim!r}, 'frequency')")
    rec = records if "record" in records.dims else records.expand_dims(record=[0])
    rec = rec.transpose("record", "frequency")
    f = rec["frequency"].values
    if cb.lower.sizes["frequency"] != f.size or not np.allclose(cb["frequency"].values, f):
        raise SpecificationError("records.frequency", f"{f.size} bins", "must equal the samples' frequency grid")
    lo, hi = cb.lower.transpose("frequency").values, cb.upper.transpose("frequency").values
    inside = (rec.values >= lo) & (rec.values <= hi)  # (record, frequency)
    out = {}
    for name, (a, b) in bands.items():
        sel = (f > a) & (f <= b * (1 + 1e-12)) & (f > 0)
        out[name] = float(np.mean(inside[:, sel])) if np.any(sel) else None
    return out


# ---------------------------------------------------------------------- the run
def _describe_run(store: _Store) -> dict:
    """What ran: size, experiment, models, δ source, distance, realisation counts and grids."""
    p = store.parameters
    run: dict = {"size": p.get("size"), "quick": p.get("size") == "quick", "experiment": p.get("experiment"),
                 "distance": p.get("distance"), "pipeline": store.root.get("study_name")}
    simp = store._json(p.get("simplified"))
    run["simplified_model"] = (simp.get("spec", {}) or {}).get("name") if simp else None
    run["simplified_source"] = simp.get("source") if simp else None
    imposed = p.get("delta")
    run["delta_source"] = None if imposed is None else ("imposed (--set delta)" if float(imposed) > 0 else
                                                        "identified (δ_opt of stage 'delta')")
    counts, grids = {}, {}
    for name, var, dims in (("delta", "J", ("delta",)), ("calibration", "psd", ()), ("response", "psd", ()),
                            ("load_r", "psd", ("r1", "r2")), ("load_r_fine", "psd", ("r1", "r2")),
                            ("load_delta_f", "J_s", ("delta_F",))):
        try:
            da = store.group(name)[var]
        except (_StageMissing, KeyError):
            continue
        if "realisation" in da.dims:
            counts[name] = int(da.sizes["realisation"])
        for d in dims:
            if d in da.dims:
                v = da[d].values
                grids[f"{name}.{d}"] = [float(v[0]), float(v[-1]), int(v.size)]
    run["realisations"] = counts
    run["grids"] = grids
    try:
        ref = store.group("reference")
        run["n_records"] = int(ref["psd_reference"].sizes.get("experiment", 1))
        run["record_seconds"] = _num(ref.attrs.get("record_seconds"))
        run["segment_seconds"] = _num(ref.attrs.get("segment_seconds"))
        run["estimator"] = ref.attrs.get("estimator")
    except (_StageMissing, KeyError):
        pass
    run["delta_used"] = _num(store.stage_parameters("response").get("delta"))
    return run


def _targets(store: _Store) -> tuple[dict, str]:
    """What identified values are compared with: the truth of a synthetic experiment, else the paper."""
    try:
        attrs = store.group("reference").attrs
    except _StageMissing:
        return PAPER_VALUES, "paper"
    truth = {k: float(attrs[f"truth_{k}"]) for k in PAPER_VALUES if f"truth_{k}" in attrs}
    return (truth, "truth") if len(truth) == len(PAPER_VALUES) else (PAPER_VALUES, "paper")


# ---------------------------------------------------------------------- likelihoods (δ, δ_F)
def _likelihood_quantity(a: dict, n: int, grid, stored=None, key: str = "", notes=None) -> dict:
    """A likelihood optimum as a summary quantity: value, bootstrap spread, edge and flatness."""
    value = a["argmax"]
    if stored is not None and _num(stored) is not None and abs(float(stored) - value) > 1e-9 * max(abs(value), 1e-300):
        notes.append(f"{key}: the report's recomputed optimum {value:.6g} differs from the study's stored "
                     f"{float(stored):.6g}; the table shows the study's")
        value = float(stored)
    return {"value": value, "std": a["argmax_std"], "low": a["argmax_low"], "high": a["argmax_high"],
            "discrete": a["argmax_discrete"], "at_grid_edge": bool(a["argmax_at_boundary"]), "flat": bool(a["flat"]),
            "log_likelihood_range": a["log_likelihood_range"], "n_excluded": a["n_excluded"],
            "lr_interval": [a["lr_interval_low"], a["lr_interval_high"]], "grid_ends": [float(grid[0]), float(grid[-1])],
            "n_realisations": n}


def _likelihood_figure(curve, dim, q, symbol, target, target_label, admissible, xlabel, title, out, name, written):
    """log p − max log p over the grid: the maximum, its bootstrap band, the 95 % likelihood-ratio level
    and interval, the admissible bound and the target, so that the maximum and the flatness show."""
    fig = _figure()
    ax = fig.add_subplot()
    d = curve[dim].values
    ll = curve.log_likelihood.values
    top = float(np.max(ll))
    rel = ll - top
    scale = float(curve.attrs.get("likelihood_log_scale", 0.0))
    depth = max(6.0, min(float(-np.min(rel)) * 1.05 if np.all(np.isfinite(rel)) else 30.0, 30.0))
    floor = -depth
    if np.all(np.isfinite(curve.likelihood_low.values)):
        with np.errstate(divide="ignore"):
            lo = np.log(curve.likelihood_low.values) + scale - top
            hi = np.log(curve.likelihood_high.values) + scale - top
        ax.fill_between(d, np.maximum(lo, floor), np.maximum(hi, floor), alpha=0.3, color="C0",
                        label=f"bootstrap {100 * curve.attrs['confidence']:g} % band")
    shown = np.maximum(rel, floor)
    ax.plot(d, shown, "o-", color="C0", ms=3, label="log-likelihood − its maximum (Gaussian KDE)")
    if np.any(rel < floor):
        ax.plot(d[rel < floor], shown[rel < floor], "v", color="C0", ms=5, label=f"below {floor:.0f} (clipped)")
    ax.axhline(-LR_THRESHOLD, color="0.4", lw=0.8, ls=":", label=f"−{LR_THRESHOLD:.2f}: 95 % likelihood-ratio level")
    ax.axvspan(*q["lr_interval"], color="C2", alpha=0.12, label=f"95 % likelihood-ratio interval [{q['lr_interval'][0]:.3g}, "
                                                                f"{q['lr_interval'][1]:.3g}]")
    ax.axvline(q["value"], color="C3", label=f"{symbol} = {q['value']:.3f}" + (f" ± {q['std']:.2g}" if _num(q["std"]) else ""))
    if admissible is not None:
        ax.axvline(admissible, color="0.3", ls="-.", lw=1, label=f"admissible bound {admissible:.3f}")
    if target is not None:
        ax.axvline(target, color="k", ls="--", label=f"{target_label}: {symbol} = {target:g}")
    ax.set_ylim(floor * 1.02, max(0.5, 0.05 * depth))
    ax.set_xlabel(xlabel)
    ax.set_ylabel("log p − max log p  (natural log)")
    verdict = ("flat: not identified" if q["flat"] else "maximum at the grid edge" if q["at_grid_edge"]
               else "interior maximum")
    ax.set_title(f"{title}: {verdict}", fontsize=10)
    ax.legend(fontsize=7, loc="lower right")
    out.save_figure(fig, name, dpi=110)
    written.append(name)


def _admissible_bound(store: _Store):
    """δ_max of the simplified model's reduced B (from the stored specification), or None."""
    simp = store._json(store.parameters.get("simplified") or store.stage_parameters("delta").get("simplified"))
    if not simp.get("spec"):
        return None
    from tubeid.mechanics.reduction import reduce
    from tubeid.mechanics.spec import spec_from_dict
    from tubeid.uncertainty.random_matrices import delta_max

    try:
        return float(delta_max(reduce(spec_from_dict(simp["spec"])).subsystem.n))
    except SpecificationError:
        return None


def _stage_delta(store, out, n_bootstrap, seed, written, notes, targets) -> dict:
    ds = store.group("delta")
    J = _variable(ds, "delta", "J")
    if set(J.dims) != {"delta", "realisation"}:
        raise _StageMissing(f"delta.J must have dims (delta, realisation), not {tuple(J.dims)}")
    j_ref = _attr(ds, "J", "J_ref")
    if j_ref is None:
        raise _StageMissing("attribute J_ref missing from group 'delta'")
    J = _complete(J.transpose("delta", "realisation"), "realisation", "delta.J", notes, 5)
    units = J.attrs.get("units") or J_UNITS_DEFAULT
    curve = likelihood_curve(J, j_ref, J["delta"].values, "delta", n_bootstrap=n_bootstrap,
                             rng=rng_for(seed, "report", "delta"))
    q = _likelihood_quantity(curve.attrs, int(J.sizes["realisation"]), J["delta"].values, ds.attrs.get("delta_opt"),
                             "δ_opt", notes)
    admissible = _admissible_bound(store)
    target, label = targets
    _likelihood_figure(curve, "delta", q, "δ_opt", target["delta_opt"], label, admissible,
                       "dispersion δ of K_B (dimensionless)",
                       f"Likelihood of δ (Figure 5), {J.sizes['realisation']} realisations per δ",
                       out, "fig5_delta_likelihood.png", written)
    d = J["delta"].values
    return {"quantities": {"delta_opt": q},
            "details": {"J_ref": j_ref, "J_units": units, "grid": [float(d[0]), float(d[-1]), int(d.size)],
                        "delta_max": admissible}}


def _stage_load_delta_f(store, out, n_bootstrap, seed, written, notes, targets) -> dict:
    ds = store.group("load_delta_f")
    Js = _variable(ds, "load_delta_f", "J_s")
    if set(Js.dims) != {"delta_F", "realisation"}:
        raise _StageMissing(f"load_delta_f.J_s must have dims (delta_F, realisation), not {tuple(Js.dims)}")
    js_exp = _attr(ds, "J_s", "J_s_exp")
    source = "attribute J_s_exp of group 'load_delta_f'"
    if js_exp is None:
        try:
            ref = _records(store, notes)
            band = float(ds.attrs.get("band_hz", 100.0))
            # one J_s per record, like the model samples (J_s of an averaged PSD would be biased low)
            js_exp = [float(j_s(r["frequency"].values, r.values, band)) for r in
                      (ref.isel(record=i) for i in range(ref.sizes["record"]))]
            js_exp = js_exp[0] if len(js_exp) == 1 else js_exp
            source = "computed from reference.psd_reference (one value per record)"
        except (_StageMissing, SpecificationError) as exc:
            raise _StageMissing(f"attribute J_s_exp missing from group 'load_delta_f' and not computable: {exc}") \
                from None
    Js = _complete(Js.transpose("delta_F", "realisation"), "realisation", "load_delta_f.J_s", notes, 5)
    units = Js.attrs.get("units") or JS_UNITS
    try:
        lk = delta_f_likelihood(Js, js_exp, n_bootstrap=n_bootstrap, rng=rng_for(seed, "report", "load_delta_f"),
                                units=units)
    except SpecificationError as exc:
        raise _StageMissing(f"likelihood of δ_F could not be computed: {exc}") from None
    q = _delta_f_quantity(lk, ds.attrs.get("delta_F_opt"), "δ_F,opt", targets, notes,
                          f"Likelihood of δ_F, {Js.sizes['realisation']} realisations per δ_F",
                          out, "delta_f_likelihood.png", written)
    result = {"quantities": {"delta_F_opt": q}, "details": {"J_s_exp": js_exp, "J_s_exp_source": source,
                                                             "J_s_units": units}}
    if "level_difference" in ds:
        _pairs_delta_f(ds, out, n_bootstrap, seed, written, notes, targets, result)
    return result


def _delta_f_quantity(lk, stored, key, targets, notes, title, out, name, written) -> dict:
    """A δ_F likelihood (``delta_f_likelihood``'s Dataset) as a summary quantity, and its figure."""
    q = _likelihood_quantity(lk.attrs, int(lk.sizes["realisation"]), lk["delta_F"].values, stored, key, notes)
    target, label = targets
    _likelihood_figure(lk, "delta_F", q, "δ_F,opt", target["delta_F_opt"], label, lk.attrs["delta_F_max"],
                       "load dispersion δ_F (dimensionless)", title, out, name, written)
    return q


def _pairs_delta_f(ds, out, n_bootstrap, seed, written, notes, targets, result) -> None:
    """δ_F from the log-level differences of record pairs of one structure (``level_difference``)."""
    d_exp = _attr(ds, "level_difference", "level_difference_exp")
    if d_exp is None:
        notes.append("load_delta_f.level_difference is stored without its observations (attribute "
                     "level_difference_exp): δ_F from record pairs is not computed")
        return
    L = _variable(ds, "load_delta_f", "level_difference")
    if set(L.dims) != {"delta_F", "realisation"}:
        notes.append(f"load_delta_f.level_difference has dims {tuple(L.dims)}, not (delta_F, realisation): "
                     "δ_F from record pairs is not computed")
        return
    try:
        L = _complete(L.transpose("delta_F", "realisation"), "realisation", "load_delta_f.level_difference", notes, 5)
    except _StageMissing as exc:  # the paper's δ_F stands without it
        notes.append(f"δ_F from record pairs is not computed: {exc}")
        return
    try:
        lk = delta_f_likelihood(L, d_exp, n_bootstrap=n_bootstrap, rng=rng_for(seed, "report", "load_delta_f", "pairs"),
                                units="1", observable="level_difference", variance_corrected=True)
    except SpecificationError as exc:
        notes.append(f"δ_F from record pairs could not be computed: {exc}")
        return
    n_pairs = len(d_exp) if isinstance(d_exp, (list, tuple)) else 1
    q = _delta_f_quantity(lk, ds.attrs.get("delta_F_pairs_opt"), "δ_F,opt from record pairs", targets, notes,
                          f"δ_F from {n_pairs} record pairs (log-level differences), {L.sizes['realisation']} per δ_F",
                          out, "delta_f_pairs_likelihood.png", written)
    result["quantities"]["delta_F_pairs_opt"] = q
    result["details"]["n_record_pairs"] = n_pairs
    result["details"]["level_difference_exp_std"] = float(np.std(d_exp, ddof=1)) if n_pairs > 1 else None


# ---------------------------------------------------------------------- responses (Figures 4 and 6)
def _stage_response(store, out, sensor, written, notes, run) -> dict:
    recs = _records(store, notes)
    band = min(100.0, float(recs["frequency"].values[-1]))
    name = _sensor_name(recs, sensor)
    rec_auto = _in_band(_auto(recs, sensor), band).transpose("record", "frequency")
    f = rec_auto["frequency"].values
    details: dict = {"sensor": name, "band_hz": band, "n_reference_records": int(recs.sizes["record"]),
                     "delta_used": run.get("delta_used"), "delta_source": run.get("delta_source")}
    ref = store.group("reference")
    if "psd_mean" in ref.data_vars:
        try:
            _figure4(ref.psd_mean, f, rec_auto, name, band, sensor, out, written, notes, details)
        except _StageMissing as exc:
            notes.append(f"reference.psd_mean not used: {exc}")
    else:
        notes.append("reference.psd_mean missing: Figure 4 not drawn")
    regions = {}
    for group, label in (("response", "stochastic simplified model"), ("calibration", "reference model (calibration)")):
        try:
            da = _complete(_variable(store.group(group), group, "psd"), "realisation", f"{group}.psd", notes, 2)
        except _StageMissing as exc:
            notes.append(f"{group}: {exc}")
            continue
        auto = _in_band(_auto(da, sensor), band)
        if auto.sizes["frequency"] != f.size or not np.allclose(auto["frequency"].values, f):
            notes.append(f"{group}.psd is on another frequency grid than the record: not used")
            continue
        regions[group] = auto
    if "response" in regions:
        details["reference_coverage"] = region_coverage(regions["response"], rec_auto)
        details["n_stochastic_realisations"] = int(regions["response"].sizes["realisation"])
    if "calibration" in regions:
        details["reference_self_coverage"] = region_coverage(regions["calibration"], rec_auto)
        details["n_calibration_realisations"] = int(regions["calibration"].sizes["realisation"])
    if "response" in regions:
        _figure6(regions, f, rec_auto, name, band, out, written, details, run)
    else:
        notes.append("response.psd missing: Figure 6 not drawn")
    return {"details": details}


def _figure4(mean, f, rec_auto, name, band, sensor, out, written, notes, details) -> None:
    """Figure 4: reference vs mean simplified model at the sensor; log10 errors below/above 35 Hz."""
    if "experiment" in mean.dims:
        mean = mean.rename(experiment="record")
    extra = [d for d in mean.dims if d not in ("frequency",) + _SENSOR_DIMS]
    for d in extra:
        mean = _complete(mean, d, f"reference.psd_mean ({d})", notes, 1)
    mean_auto = _in_band(_auto(mean, sensor), band)
    if extra:
        mean_auto = mean_auto.mean(extra)
    if mean_auto.sizes["frequency"] != f.size or not np.allclose(mean_auto["frequency"].values, f):
        notes.append("reference.psd_mean is on another frequency grid than psd_reference: Figure 4 not drawn")
        return
    ref_auto = rec_auto.mean("record")
    fig = _figure()
    ax = fig.add_subplot()
    ax.semilogy(f, ref_auto, lw=0.8, color="C0", label="reference model (\"experimental\")"
                + (f", mean of {rec_auto.sizes['record']} records" if rec_auto.sizes["record"] > 1 else ""))
    ax.semilogy(f, mean_auto, lw=1.8, color="C3", label="mean simplified model, same load history")
    ax.set_xlim(0, band)
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel(f"PSD of the displacement at {_as_written(name)} [m²/Hz] (two-sided)")
    pos = (f > 0) & (ref_auto.values > 0) & (mean_auto.values > 0)
    lr = np.abs(np.log10(mean_auto.values[pos] / ref_auto.values[pos]))
    fp = f[pos]
    low = float(np.mean(lr[fp <= 35])) if np.any(fp <= 35) else None
    high = float(np.mean(lr[fp > 35])) if np.any(fp > 35) else None
    details["mean_model_log10_error_0_35_hz"] = low
    details["mean_model_log10_error_35_100_hz"] = high
    ax.set_title(f"Reference vs mean simplified model (Figure 4)\nmean |log10 ratio| {_fmt(low, 2)} "
                 f"(0–35 Hz), {_fmt(high, 2)} (35–100 Hz)", fontsize=9)
    ax.legend(fontsize=8)
    out.save_figure(fig, "fig4_mean_model.png", dpi=110)
    written.append("fig4_mean_model.png")


def _figure6(regions, f, rec_auto, name, band, out, written, details, run) -> None:
    """Figure 6: the stochastic model's 95 % region, the reference record(s) and the calibration region."""
    sto = regions["response"]
    cb = confidence_band(sto, _LEVEL, dim="realisation")
    cov = details["reference_coverage"]
    fig = _figure(4.8)
    ax = fig.add_subplot()
    d_used, source = run.get("delta_used"), (run.get("delta_source") or "").split(" ")[0]
    ax.fill_between(f, cb.lower, cb.upper, color="C1", alpha=0.35, lw=0,
                    label=f"95 % region, stochastic simplified model at δ = {_fmt(d_used)} ({source or 'δ'}), "
                          f"{sto.sizes['realisation']} realisations")
    if "calibration" in regions:
        cal = confidence_band(regions["calibration"], _LEVEL, dim="realisation")
        ax.semilogy(f, cal.lower, color="0.35", lw=0.7, ls="--",
                    label=f"reference model's own 95 % region ({regions['calibration'].sizes['realisation']} "
                          "independent realisations)")
        ax.semilogy(f, cal.upper, color="0.35", lw=0.7, ls="--")
    n_rec = rec_auto.sizes["record"]
    ax.semilogy(f, rec_auto.isel(record=0), lw=1.2, color="C0",
                label="reference model, the experimental record" + (f" (1 of {n_rec})" if n_rec > 1 else ""))
    ax.set_yscale("log")
    ax.set_xlim(0, band)
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel(f"PSD of the displacement at {_as_written(name)} [m²/Hz] (two-sided)")
    self_cov = details.get("reference_self_coverage") or {}
    seg, rec = run.get("segment_seconds"), run.get("record_seconds")
    estimator = (f"Welch PSD, {seg:g} s Hann segments, 50 % overlap, {rec:g} s records" if seg and rec else
                 "Welch PSD (estimator not recorded)")
    ax.set_title(f"Figure 6: the 95 % region covers the record at {_pct(cov['0-100'])} of bins "
                 f"(0–35 Hz {_pct(cov['0-35'])}, 35–100 Hz {_pct(cov['35-100'])})\n"
                 f"calibration: the reference model's own region covers it at {_pct(self_cov.get('0-100'))}\n"
                 f"quantiles 2.5–97.5 % per bin; {estimator}", fontsize=8.5)
    ax.legend(fontsize=7, loc="upper right")
    out.save_figure(fig, "fig6_confidence_region.png", dpi=110)
    written.append("fig6_confidence_region.png")


# ---------------------------------------------------------------------- r (trial method)
def _stage_load_r(store, out, n_bootstrap, seed, written, notes, run, targets) -> dict:
    coarse = _complete(_variable(store.group("load_r"), "load_r", "psd"), "realisation", "load_r.psd", notes, 2)
    try:
        fine = _complete(_variable(store.group("load_r_fine"), "load_r_fine", "psd"), "realisation",
                         "load_r_fine.psd", notes, 2)
        grid_name = "load_r_fine"
    except _StageMissing:
        fine, grid_name = coarse, "load_r"
    try:
        recs = _records(store, notes)
    except _StageMissing as exc:
        raise _StageMissing(f"load_r needs the experimental PSD reference.psd_reference: {exc}") from None
    band = min(100.0, float(fine["frequency"].values[-1]))
    params = store.stage_parameters("load_delta_f")
    try:
        stored = json.loads(params["r_identification"])
        used = params["distance"]
        passed = [float(params["r1"]), float(params["r2"])]
    except (KeyError, TypeError, ValueError):
        stored, used, passed = None, run.get("distance") or "paper", None
        notes.append("the store records no r_opt of the study (stage load_delta_f's parameters): r_opt is computed "
                     f"by the report with tubeid.identification.identify_r on {grid_name}")
    weight = None
    maps, details = {}, {"distance": used, "grid": grid_name}
    for name in DISTANCES:
        try:
            if name == "relative" and weight is None:
                weight = identify_r(coarse, recs, distance="relative", band_hz=band, refine=False).weight_psd
            maps[name] = identify_r(fine, recs, distance=name, band_hz=band, n_bootstrap=n_bootstrap,
                                    rng=rng_for(seed, "report", "load_r", name),
                                    weight_psd=weight if name == "relative" else None)
        except SpecificationError as exc:
            notes.append(f"r_opt with the {name} distance not computed: {exc}")
    if used not in maps:
        raise _StageMissing(f"r_opt with the study's distance {used!r} could not be computed")
    for name, m in maps.items():
        a = m.attrs
        r_opt = list(a["r_opt"])
        if stored is not None and name in stored and "r_opt" in stored[name]:
            if not np.allclose(stored[name]["r_opt"], r_opt, rtol=1e-9, atol=0):
                notes.append(f"r_opt ({name}): the report's recomputation {r_opt} differs from the study's stored "
                             f"{stored[name]['r_opt']}; the summary shows the study's")
            r_opt = list(stored[name]["r_opt"])
        details[f"r_opt_{name}"] = {"note": DISTANCES[name], "r_opt": r_opt, "r_opt_std": a["r_opt_std"],
                                    "r_opt_corr": a["r_opt_corr"], "at_grid_edge": bool(a["r_opt_at_boundary"]),
                                    "D_min": a["D_min"], "D_units": a["D_units"],
                                    "coarse": (stored or {}).get(name, {}).get("coarse")}
    if passed is not None and not np.allclose(passed, details[f"r_opt_{used}"]["r_opt"], rtol=1e-12, atol=0):
        notes.append(f"the r passed downstream {passed} is not the stored r_opt of distance {used!r}")
    if "bands" in maps:  # goodness of fit: about 1 if the experiment is a draw of the model class
        details["r_opt_bands"]["mean_squared_standardised_residual"] = float(maps["bands"].D_relative.min())
    a = maps[used].attrs
    r_used = details[f"r_opt_{used}"]["r_opt"]
    quantities = {}
    for n, d in enumerate(a["grid_dims"]):
        quantities[f"{d}_opt"] = {"value": r_used[n], "std": a["r_opt_std"][n], "low": a["r_opt_low"][n],
                                  "high": a["r_opt_high"][n], "discrete": a["r_opt_discrete"][n],
                                  "at_grid_edge": bool(maps[used].at_grid_edge.values[n]), "flat": False,
                                  "n_realisations": a["n_realisations"]}
        details[f"{d}_grid"] = [float(fine[d].values[0]), float(fine[d].values[-1]), int(fine.sizes[d])]
    details["r_opt_corr"] = a["r_opt_corr"]
    details["n_realisations"] = a["n_realisations"]
    _plot_d_map(maps[used], out, written, targets)
    return {"quantities": quantities, "details": details}


def _grid_ticks(axis, values) -> None:
    """Ticks at the grid values (at most 6, evenly thinned), plain labels, no minor labels: legible at
    every size (log-scale minor labels of a 3-decade axis overlap)."""
    from matplotlib.ticker import FixedFormatter, FixedLocator, NullLocator

    v = np.asarray(values, dtype=float)
    step = max(1, math.ceil(v.size / 6))
    ticks = v[::step]
    axis.set_major_locator(FixedLocator(ticks))
    axis.set_major_formatter(FixedFormatter([f"{t:.3g}" for t in ticks]))
    axis.set_minor_locator(NullLocator())


def _plot_d_map(dm: xr.Dataset, out, written: list, target: tuple[dict, str]):
    """The distance of the r passed downstream over its grid (log colour scale), r_opt and the target."""
    dims = dm.attrs["grid_dims"]
    units = dm.attrs["D_units"]
    axis_units = {"r1": "N²/Hz", "r2": "(N·m)²/Hz"}
    fig = _figure()
    ax = fig.add_subplot()
    distance = dm.attrs.get("distance", "paper")
    if len(dims) == 2:
        d1, d2 = dims
        x, y = dm[d1].values, dm[d2].values

        def edges(v):
            if v.size == 1:
                return np.array([v[0] / 1.1, v[0] * 1.1])
            lv = np.log(v)
            mid = 0.5 * (lv[1:] + lv[:-1])
            return np.exp(np.concatenate([[2 * lv[0] - mid[0]], mid, [2 * lv[-1] - mid[-1]]]))
        Dv = dm.D.transpose(d2, d1).values
        with np.errstate(divide="ignore"):
            mesh = ax.pcolormesh(edges(x), edges(y), np.log10(Dv), shading="flat", cmap="viridis")
        fig.colorbar(mesh, ax=ax, label=f"log10 D  [D in {units}]")
        ax.set_xscale("log")
        ax.set_yscale("log")
        _grid_ticks(ax.xaxis, x)
        _grid_ticks(ax.yaxis, y)
        r, s = dm.attrs["r_opt"], dm.attrs["r_opt_std"]
        ax.errorbar([r[0]], [r[1]], xerr=[[_num(s[0]) or 0]], yerr=[[_num(s[1]) or 0]], fmt="o", color="C3",
                    capsize=3, label=f"r_opt = ({r[0]:.3g}, {r[1]:.3g}) ± bootstrap std")
        rd = dm.attrs["r_opt_discrete"]
        ax.plot([rd[0]], [rd[1]], "s", mfc="none", color="w", label="grid minimum"
                + (" (on the grid edge)" if dm.attrs["r_opt_at_boundary"] else ""))
        if (d1, d2) == ("r1", "r2"):
            targets, label = target
            ax.plot([targets["r1_opt"]], [targets["r2_opt"]], "*", color="k", ms=12,
                    label=f"{label}: r_opt = ({targets['r1_opt']:g}, {targets['r2_opt']:g})")
        ax.set_xlabel(f"{d1} [{axis_units.get(d1, '')}]")
        ax.set_ylabel(f"{d2} [{axis_units.get(d2, '')}]")
        ax.legend(fontsize=8, loc="best")
    else:
        d1 = dims[0]
        others = {d: 0 for d in dims[1:]}
        line = dm.D.isel(others) if others else dm.D
        ax.loglog(dm[d1].values, line.values, "o-", label="D")
        ax.axvline(dm.attrs["r_opt"][0], color="C3", label="r_opt")
        _grid_ticks(ax.xaxis, dm[d1].values)
        ax.set_xlabel(f"{d1} [{axis_units.get(d1, '')}]")
        ax.set_ylabel(f"D [{units}]")
        ax.legend(fontsize=8)
    import textwrap

    ax.set_title(f"Trial method, {distance} distance:\n" + "\n".join(textwrap.wrap(DISTANCES.get(distance, ""), 80)),
                 fontsize=8)
    out.save_figure(fig, "d_map.png", dpi=110)
    written.append("d_map.png")
    return fig


# ---------------------------------------------------------------------- verdicts and summary
def _verdict(key: str, q: dict, targets: dict, label: str, corr=None) -> str:
    """What the run says about one identified quantity (computed from the run only)."""
    v, s = q.get("value"), q.get("std")
    if v is None or not math.isfinite(v):
        return "Not identified."
    if q.get("flat"):
        return (f"Flat likelihood (its log varies by {q['log_likelihood_range']:.2g} across the grid, and no grid "
                "value is excluded by a 95 % likelihood-ratio test beyond 2 bootstrap σ): not identified by these "
                f"data; no agreement with the {label} can be claimed.")
    if q.get("at_grid_edge"):
        return f"On the edge of its grid ({v:.4g}): a bound, not an estimate; no agreement with the {label} can be claimed."
    target = targets[key]
    diff = v - target
    out = ""
    if s is not None and math.isfinite(s) and s > 0:
        z = abs(diff) / s
        out = (f"Agrees with the {label} within 2 σ ({z:.1f} σ)." if z <= 2.0 else
               f"Differs from the {label} by {diff / target:+.0%} ({z:.1f} σ of the Monte Carlo uncertainty).")
    else:
        out = f"Differs from the {label} by {diff / target:+.0%} (no Monte Carlo uncertainty available)."
    lr, grid_ends = q.get("lr_interval"), q.get("grid_ends")
    if lr is not None and grid_ends is not None:
        if lr[1] >= grid_ends[1]:
            out += f" The 95 % likelihood-ratio interval [{lr[0]:.3g}, {lr[1]:.3g}] reaches the grid's upper end: the data do not bound it above."
        elif lr[0] <= grid_ends[0]:
            out += f" The 95 % likelihood-ratio interval [{lr[0]:.3g}, {lr[1]:.3g}] reaches the grid's lower end: the data do not bound it below."
    if key in ("r1_opt", "r2_opt") and corr is not None and math.isfinite(corr) and abs(corr) > 0.5:
        out += f" r1 and r2 trade off (bootstrap correlation {corr:+.2f})."
    return out


def _markdown(summary: dict) -> str:
    run = summary["run"]
    lines = [f"# tubeid report: {summary['store']}", ""]
    if run.get("quick"):
        lines += ["**Quick run** (`--set size=quick`): sample sizes for a look at the pipeline. r and δ_F are not "
                  "identifiable at this size; no value below is a result.", ""]
    counts = run.get("realisations", {})
    grids = run.get("grids", {})

    def grid(name):
        g = grids.get(name)
        return f"{g[2]} values in [{_fmt(g[0])}, {_fmt(g[1])}]" if g else "n/a"

    lines += ["## The run", "",
              f"- Size: {run.get('size') or 'unknown'}; experiment: {run.get('experiment') or 'unknown'}"
              + (f" ({run.get('n_records')} record(s) of {_fmt(run.get('record_seconds'))} s)" if run.get("n_records") else "")
              + f"; simplified model: {run.get('simplified_model') or 'unknown'}"
              + (f" (from {run['simplified_source']})" if run.get("simplified_source") not in (None, run.get("simplified_model")) else "")
              + ".",
              f"- δ of the later stages: {_fmt(run.get('delta_used'), 4)}, {run.get('delta_source') or 'source unknown'}.",
              f"- Distance for r: {run.get('distance') or 'unknown'} ({DISTANCES.get(run.get('distance'), '')}).",
              f"- Realisations: J(δ) {counts.get('delta', 'n/a')} per δ on {grid('delta.delta')}; response region "
              f"{counts.get('response', 'n/a')}; calibration {counts.get('calibration', 'n/a')}; r coarse "
              f"{grid('load_r.r1')} × {grid('load_r.r2')}, {counts.get('load_r', 'n/a')} per point; r fine "
              f"{grid('load_r_fine.r1')} × {grid('load_r_fine.r2')}, {counts.get('load_r_fine', 'n/a')} per point; δ_F {counts.get('load_delta_f', 'n/a')} per value on "
              f"{grid('load_delta_f.delta_F')}.",
              f"- PSD estimator: {run.get('estimator') or 'unknown'}.", "",
              "## Identified values", "",
              "Monte Carlo uncertainty: bootstrap over realisations "
              f"({summary['n_bootstrap']} replicates, seed {summary['seed']}); ± is one standard deviation, "
              "the interval is the bootstrap 95 % percentile interval. The values are those the study stored and "
              "passed downstream.", "",
              f"| quantity | identified | ± MC std | 95 % interval | {summary['target_label']} | units | verdict |",
              "|---|---|---|---|---|---|---|"]
    for key in _KEYS:
        q = summary["quantities"].get(key)
        if q is None and key in _OPTIONAL:
            continue
        if q is None:
            lines.append(f"| {_LABELS[key]} | missing | | | {summary['target_values'][key]:g} | {_UNITS[key]} | stage not available |")
            continue
        lines.append(f"| {_LABELS[key]} | {_fmt(q['value'], 4)} | {_fmt(q['std'], 2)} | "
                     f"[{_fmt(q['low'])}, {_fmt(q['high'])}] | {summary['target_values'][_TARGET_OF.get(key, key)]:g} | "
                     f"{_UNITS[key]} | {q['verdict']} |")
    lines.append("")
    det = summary["details"]
    lines += ["## Figure 6: coverage of the reference", ""]
    cov, self_cov = summary.get("reference_coverage"), summary.get("reference_self_coverage")
    if cov:
        lines.append("| band | stochastic simplified model's region | reference model's own region (calibration) |")
        lines.append("|---|---|---|")
        for b in COVERAGE_BANDS:
            lines.append(f"| {b} Hz | {_pct(cov.get(b))} | {_pct((self_cov or {}).get(b))} |")
        lines.append("")
        lines.append("Fraction of frequency bins where the experimental record lies inside the 95 % region "
                     "(2.5–97.5 % quantiles per bin). The calibration is what a model without model-form error "
                     "scores with as many realisations and the same estimator.")
    else:
        lines.append("Not computed (stage response missing).")
    lines.append("")
    lines += ["## Details", ""]
    if "delta" in det:
        d = det["delta"]
        lines.append(f"- J_ref = {_fmt(d['J_ref'], 6)} {d['J_units']} "
                     + ("(reference model, band ±100 Hz)." if summary["target_label"] == "paper" else "(synthetic experiment)."))
        q = summary["quantities"].get("delta_opt")
        if q:
            lines.append(f"- δ likelihood: log-likelihood range across the grid {_fmt(q['log_likelihood_range'])} "
                         f"({q['n_excluded']} grid values excluded at 95 % beyond 2 bootstrap σ); 95 % likelihood-ratio interval "
                         f"[{_fmt(q['lr_interval'][0])}, {_fmt(q['lr_interval'][1])}]; admissible bound "
                         f"{_fmt(d.get('delta_max'))}.")
    if "response" in det:
        r = det["response"]
        if r.get("mean_model_log10_error_0_35_hz") is not None:
            lines.append(f"- Mean simplified model vs reference at {r['sensor']}: mean |log10 ratio| of the PSD "
                         f"{_fmt(r['mean_model_log10_error_0_35_hz'])} over 0–35 Hz and "
                         f"{_fmt(r['mean_model_log10_error_35_100_hz'])} over 35–100 Hz.")
    if "load_r" in det:
        lr = det["load_r"]
        lines.append(f"- The table's r: {lr['distance']} distance ({DISTANCES[lr['distance']]}) on {lr['grid']}.")
        for name in DISTANCES:
            rr = lr.get(f"r_opt_{name}")
            if rr is None:
                continue
            if name != lr["distance"]:
                lines.append(f"- With the {name} distance: r_opt = ({', '.join(_fmt(v, 4) for v in rr['r_opt'])}) ± "
                             f"({', '.join(_fmt(v, 2) for v in rr['r_opt_std'])})"
                             + (" — on the grid edge." if rr["at_grid_edge"] else "."))
            c = rr.get("coarse")
            if c:
                lines.append(f"  - {name} on the coarse grid (refined): ({', '.join(_fmt(v, 4) for v in c['r_opt'])})"
                             + (" — on the coarse grid's edge." if c["at_grid_edge"] else "."))
        msr = (lr.get("r_opt_bands") or {}).get("mean_squared_standardised_residual")
        if msr is not None:
            # no verdict: the residual's null distribution (band variances estimated from a few
            # realisations, bands correlated) is not computed here, so no threshold would be derived
            lines.append(f"- Log band levels at the grid minimum: mean squared standardised residual {_fmt(msr, 3)} "
                         f"(about 1 for a draw of the model class, larger when the model does not explain the "
                         f"record's band levels within its own scatter; not tested here).")
    if "load_delta_f" in det:
        lines.append(f"- J_s,exp = {_fmt(det['load_delta_f']['J_s_exp'], 6)} {det['load_delta_f']['J_s_units']} "
                     f"({det['load_delta_f']['J_s_exp_source']}).")
        if det["load_delta_f"].get("n_record_pairs"):
            lines.append(f"- δ_F from record pairs (beyond the paper): {det['load_delta_f']['n_record_pairs']} pairs of "
                         "records of one structure each; the observable is the difference of their log levels (mean "
                         "over 5 Hz bands of the log band energy at P_obs), whose spread the random B barely reaches "
                         f"(observed standard deviation {_fmt(det['load_delta_f'].get('level_difference_exp_std'))}).")
    lines.append("")
    if summary["missing"]:
        lines += ["## Missing or incomplete stages", ""] + [f"- {m}" for m in summary["missing"]] + [""]
    if summary["notes"]:
        lines += ["## Notes", ""] + [f"- {n}" for n in summary["notes"]] + [""]
    lines += ["## Figures", ""] + ([f"- [{f}]({f})" for f in summary["figures"]] or ["- none"]) + [""]
    return "\n".join(lines)


def make_report(store, out=None, *, n_bootstrap: int = 200, seed: int = 2008, sensor: str | None = None) -> dict:
    """Analyse every stage of ``store``, write figures, summary.md and summary.json into ``out``.

    Parameters
    ----------
    store : path-like
        A paper study store (module docstring).
    out : path-like, optional
        Output directory (default ``<store>-report``); files there that tubeid did not write are never
        overwritten (the report is refused before anything is written).
    n_bootstrap : int
        Bootstrap replicates of the Monte Carlo spreads (0: none).
    seed : int
        Seed of the bootstrap generators ``rng_for(seed, "report", STAGE)``.
    sensor : str, optional
        Sensor of Figures 4 and 6 (default P_obs, else the first); one the store does not have is
        refused (PSDs without a sensor dimension are P_obs's).

    Returns
    -------
    dict
        The summary (the content of summary.json): ``run`` (what ran), ``quantities`` (each with
        value, bootstrap spread, ``at_grid_edge``, ``flat`` and a computed ``verdict``), ``delta_used``,
        ``delta_opt_at_grid_edge``, ``reference_coverage``, ``reference_self_coverage``, ``details``,
        ``missing`` stages, ``notes`` and ``figures``.

    Raises
    ------
    SpecificationError
        ``store`` is not a paper study store, a bad argument, or a file in ``out`` that tubeid did
        not write: before any output is written (``out`` is not created).
    """
    store = os.fspath(store)
    if not os.path.exists(local_path(store)):
        raise SpecificationError("store", store, "no such Zarr store")
    n_bootstrap = replicates("n_bootstrap", n_bootstrap)
    seed = _seed("seed", seed)
    if sensor is not None and not isinstance(sensor, str):
        raise SpecificationError("sensor", sensor, "must be a sensor name (a string)")
    st = _Store(store)  # refused here, before any output directory exists, unless it is a paper study store
    if sensor is not None:  # an unknown sensor is refused before any work
        try:
            _sensor_name(_variable(st.group("reference"), "reference", "psd_reference"), sensor)
        except _StageMissing:  # no experimental PSD: no figure that names a sensor
            pass
    out_path = Path(out) if out is not None else Path(store.rstrip("/\\").removesuffix(".zarr") + "-report")
    store_dir = Path(local_path(store)).resolve()
    if out_path.resolve() == store_dir or store_dir in out_path.resolve().parents:
        raise SpecificationError("out", str(out), f"is the store {store!r} or inside it: the report is written beside "
                                 "the store, never into it; choose another --out (the default is <store>-report)")
    created = [p for p in (out_path, *out_path.parents) if not (p.exists() or p.is_symlink())]
    od = OutputDir(out_path, "out")
    try:
        for name in OUTPUTS:  # refuse before writing anything, not half-way through
            target = od.path / name
            if (target.exists() or target.is_symlink()) and not od.owned(name):
                raise SpecificationError(f"out/{name}", str(target), "exists and was not written by tubeid (or was "
                                         "changed since): it is left untouched; move it or choose another --out")
        pending = _Pending()
        summary = _analyse(st, store, pending, n_bootstrap, seed, sensor)
    except BaseException:  # refused, failed or interrupted (Ctrl-C) before writing: DIR as it was
        _discard(od, created, outputs=False)
        raise
    try:
        _commit(od, pending, summary)
    except BaseException:  # interrupted while writing: no half-written report is left
        _discard(od, created, outputs=True)
        raise
    return summary


class _Pending:
    """The report's files, rendered in memory while the stages are analysed and written by :func:`_commit`
    once every figure and the summary exist (a report that fails or is interrupted writes nothing)."""

    def __init__(self):
        self.files: dict[str, bytes] = {}

    def write_bytes(self, name: str, data: bytes) -> None:
        self.files[name] = data

    def save_figure(self, fig, name: str, **kwargs) -> None:
        OutputDir.save_figure(self, fig, name, **kwargs)  # rendered as OutputDir renders (here into memory)


def _commit(od: OutputDir, pending: _Pending, summary: dict) -> None:
    """Write the report: first away with an earlier report's summary (its figures are about to change), then
    the figures, the summaries last (a report without summary.md is incomplete), then an earlier report's
    figures that this one does not have (they would mislead)."""
    od.remove([n for n in ("summary.md", "summary.json") if od.owned(n)])
    for name, data in pending.files.items():
        od.write_bytes(name, data)
    od.write_text("summary.json", json.dumps(summary, indent=2, ensure_ascii=False) + "\n")
    od.write_text("summary.md", _markdown(summary))
    stale = [n for n in FIGURES if n not in pending.files and od.owned(n)]
    if stale:
        od.remove(stale)


def _discard(od: OutputDir, created: list, outputs: bool) -> None:
    """After a refusal, a failure or an interruption: with ``outputs`` (it happened while the report was
    being written), remove the report's files tubeid wrote in ``od`` (this report's, and an earlier
    report's that it had begun to replace); then the directories this report created, if nothing else
    is in them. Files tubeid did not write, or that changed since, are always kept."""
    import contextlib

    with contextlib.suppress(Exception):  # the original error or interruption is what the user must see
        if outputs and od.manifest_path.exists():
            od.remove([n for n in OUTPUTS if od.owned(n)])
        if created and od.path == created[0]:
            if od.manifest_path.exists() and not od.entries():  # tubeid's own bookkeeping, recording nothing
                os.unlink(od.manifest_path)
            with contextlib.suppress(OSError):
                os.unlink(od.path / ".tubeid-manifest.lock")
            for d in created:  # deepest first; a directory that holds anything is kept
                with contextlib.suppress(OSError):
                    os.rmdir(d)


def _analyse(st: _Store, store: str, od, n_bootstrap: int, seed: int, sensor) -> dict:
    """Every stage of the store analysed, its figures rendered into ``od``: the summary (make_report)."""
    run = _describe_run(st)
    targets = _targets(st)
    written: list = []
    notes: list = []
    missing: list = []
    stages: dict = {}
    quantities: dict = {}
    details: dict = {}
    runners = {
        "delta": lambda: _stage_delta(st, od, n_bootstrap, seed, written, notes, targets),
        "response": lambda: _stage_response(st, od, sensor, written, notes, run),
        "load_r": lambda: _stage_load_r(st, od, n_bootstrap, seed, written, notes, run, targets),
        "load_delta_f": lambda: _stage_load_delta_f(st, od, n_bootstrap, seed, written, notes, targets),
    }
    for name in STAGES:
        try:
            res = runners[name]()
        except _StageMissing as exc:
            stages[name] = f"missing: {exc}"
            missing.append(f"{name}: {exc}")
            continue
        stages[name] = "ok"
        quantities.update(res.get("quantities", {}))
        details[name] = res.get("details", {})
    corr = None
    if "load_r" in details and len(details["load_r"].get("r_opt_corr", [])) > 1:
        corr = details["load_r"]["r_opt_corr"][0][1]
    target_values, label = targets
    for key, q in quantities.items():
        base = _TARGET_OF.get(key, key)
        if base in PAPER_VALUES:
            q["paper"] = PAPER_VALUES[base]
            q[label] = target_values[base]
            q["units"] = _UNITS[key]
            q["verdict"] = _verdict(base, q, target_values, label, corr)
    resp = details.get("response", {})
    dq = quantities.get("delta_opt")
    summary = _jsonable({
        "store": store, "generated_by": "tubeid report", "seed": seed, "n_bootstrap": n_bootstrap, "run": run,
        "delta_used": run.get("delta_used"), "delta_source": run.get("delta_source"),
        "delta_opt_at_grid_edge": None if dq is None else dq["at_grid_edge"],
        "reference_coverage": resp.get("reference_coverage"), "reference_self_coverage": resp.get("reference_self_coverage"),
        "paper_values": PAPER_VALUES, "target_values": target_values, "target_label": label, "stages": stages,
        "missing": missing, "notes": notes, "quantities": quantities, "details": details, "figures": written,
    })
    return summary


# ---------------------------------------------------------------------- command line
def _run(args) -> int:
    s = make_report(args.store, args.out, n_bootstrap=args.n_bootstrap, seed=args.seed, sensor=args.sensor)
    out = args.out or (args.store.rstrip("/\\").removesuffix(".zarr") + "-report")
    print(f"report written to {out}: {', '.join(s['figures'] + ['summary.md', 'summary.json'])}")
    if s["run"].get("quick"):
        print("  quick run: sizes for a look at the pipeline, not a result")
    for key in _KEYS:
        q = s["quantities"].get(key)
        if q is not None:
            flag = " [flat]" if q.get("flat") else " [grid edge]" if q.get("at_grid_edge") else ""
            print(f"  {key:12s} {_fmt(q['value'], 4):>10s} ± {_fmt(q['std'], 2):<8s} ({s['target_label']} "
                  f"{s['target_values'][_TARGET_OF.get(key, key)]:g}){flag}")
    cov = s.get("reference_coverage")
    if cov:
        print(f"  coverage of the reference, 0-100 Hz: {_pct(cov['0-100'])} "
              f"(calibration: {_pct((s.get('reference_self_coverage') or {}).get('0-100'))})")
    for m in s["missing"]:
        print(f"  missing: {m}")
    return 0


def register(sub) -> None:
    p = sub.add_parser("report", help="figures and summary (Markdown, JSON) of a paper study store")
    p.add_argument("store", help="Zarr store written by studies/paper.py")
    p.add_argument("--out", default=None, help="output directory (default: <store>-report beside the store)")
    p.add_argument("--n-bootstrap", type=int, default=200, help="bootstrap replicates for the Monte Carlo "
                   "uncertainties (default 200)")
    p.add_argument("--seed", type=int, default=2008, help="seed of the bootstrap generators (default 2008)")
    p.add_argument("--sensor", default=None, help="sensor of Figures 4 and 6 (default P_obs, else the first)")
    p.set_defaults(func=_run)
