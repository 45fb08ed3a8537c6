"""``tubeid report STORE [--out DIR]``: the figures and the summary of a paper study store.

The store is a Zarr store with one group per stage of the paper (Batou & Soize 2008); each group
is opened with ``xarray.open_zarr(store, group=NAME)``:

* ``delta``: ``J`` (delta, realisation) [m² rad/(N² s)], attribute ``J_ref`` → δ_opt (Figure 5).
* ``response``: ``psd_reference`` (realisation_ref, frequency, sensor, sensor_), the reference
  model under the paper's 7-point load, i.e. the "experimental" data; ``psd_mean`` (frequency,
  sensor, sensor_; any extra dimension is averaged), the mean simplified model; ``psd_stochastic``
  (realisation, …), the stochastic simplified model at δ_opt; attribute ``delta_opt``
  (Figures 4 and 6).
* ``load_r``: ``psd`` (r1, r2, realisation, frequency, sensor, sensor_), coordinates r1 [N²/Hz]
  and r2 [(N m)²/Hz] → D(r) and r_opt (needs ``response.psd_reference``).
* ``load_delta_f``: ``J_s`` (delta_F, realisation), attribute ``J_s_exp`` → δ_F,opt.

PSDs are two-sided per Hz (m²/Hz), complex, or real (auto-spectra; with or without the sensor
dimensions). Realisations with missing values (a partially run study reads them as NaN) are left
out and counted; a missing or unusable stage is reported, not fatal.

Writes into DIR (default: ``<store>-report`` beside the store): fig4_mean_model.png,
fig5_delta_likelihood.png, fig6_confidence_region.png, d_map.png, delta_f_likelihood.png,
summary.md and summary.json. Monte Carlo uncertainties are bootstrap estimates over realisations
(generators ``tubeid.seeds.rng_for(seed, "report", STAGE)``, ``--seed`` default 2008).
"""

from __future__ import annotations

import json
import math
import os
import warnings
from pathlib import Path

import numpy as np
import xarray as xr
import zarr

from tubeid.dynamics.spectra import confidence_band, j_s
from tubeid.errors import SpecificationError
from tubeid.identification.likelihood import likelihood_curve
from tubeid.identification.loads import JS_UNITS, delta_f_likelihood, distance_map, log_band_distance_map, relative_weight
from tubeid.seeds import rng_for

__all__ = ["register", "make_report", "PAPER_VALUES", "STAGES"]

#: The paper's identified values (Batou & Soize 2008, §5.4–5.6).
PAPER_VALUES = {"delta_opt": 0.45, "r1_opt": 18.0, "r2_opt": 20.0, "delta_F_opt": 0.04}
STAGES = ("delta", "response", "load_r", "load_delta_f")
J_UNITS_DEFAULT = "m^2 rad/(N^2 s)"
_UNITS = {"delta_opt": "1", "r1_opt": "N^2/Hz", "r2_opt": "(N m)^2/Hz", "delta_F_opt": "1"}
_LABELS = {"delta_opt": "δ_opt (dispersion of K_B)", "r1_opt": "r1,opt (force T)", "r2_opt": "r2,opt (moment M)",
           "delta_F_opt": "δ_F,opt (load dispersion)"}
_SENSOR_DIMS = ("sensor", "sensor_")

_CAUSES = {
    "delta_opt": "the likelihood is flat (the paper's Figure 5 varies by only 7 % over δ in [0.1, 0.6]), so its "
                 "maximum moves with choices the paper does not state: the size of the reduced matrices of B "
                 "(Craig–Bampton modes kept), which matrices are randomised (K_B only here) and the kernel bandwidth.",
    "r": "D is dominated by the first resonance peaks at the sensors, where r1 and r2 trade off along a valley "
         "of D (bootstrap correlation of r1 and r2: {corr}); the paper does not state its observation channels, "
         "record length, PSD estimator or its 100 trial values, and the simplified model differs from the "
         "reference above 35 Hz (Figure 4), which the two load parameters partly absorb.",
    "delta_F_opt": "δ_F is identified from one value J_s,exp, whose own sampling variability is not in the "
                   "bootstrap (it covers the model realisations only): one observation only says how far J_s,exp "
                   "lies from the typical J_s, so δ_F is weakly determined, and the reference/simplified model "
                   "mismatch shifts J_s,exp.",
}


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


class _StageMissing(Exception):
    """A stage cannot be analysed; the message says why."""


def _open_group(store: str, name: str) -> xr.Dataset:
    try:
        with warnings.catch_warnings():  # stores written group by group may lack consolidated metadata
            warnings.filterwarnings("ignore", message=".*consolidated metadata.*", category=RuntimeWarning)
            return xr.open_zarr(store, group=name)
    except (KeyError, FileNotFoundError, ValueError, OSError) as exc:
        raise _StageMissing(f"group '{name}' not found in the store ({type(exc).__name__})") from None
    except Exception as exc:  # zarr raises several group-not-found types across versions
        raise _StageMissing(f"group '{name}' could not be opened ({type(exc).__name__}: {exc})") from None


def _open_response(store: str) -> xr.Dataset:
    """The response data, from ``studies/paper.py``'s layout (group ``reference`` with
    ``psd_reference``/``psd_mean`` on ``experiment``, group ``response`` with ``psd``) or from a
    single ``response`` group holding ``psd_reference``, ``psd_mean`` and ``psd_stochastic``."""
    try:
        ref = _open_group(store, "reference")
    except _StageMissing:
        return _open_group(store, "response")
    data = {}
    if "psd_reference" in ref.data_vars:
        data["psd_reference"] = ref.psd_reference.rename(experiment="realisation_ref") if "experiment" in ref.psd_reference.dims else ref.psd_reference
    if "psd_mean" in ref.data_vars:
        data["psd_mean"] = ref.psd_mean
    try:
        resp = _open_group(store, "response")
        if "psd" in resp.data_vars:
            data["psd_stochastic"] = resp.psd
    except _StageMissing:
        pass
    return xr.Dataset(data, attrs=ref.attrs)


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
    if "sensor" in da.dims and "sensor" in da.coords:
        return str(da["sensor"].values[_sensor_index(da, sensor)])
    return sensor or "P_obs"


def _figure():
    from tubeid._optional import require

    Figure = require("matplotlib.figure", "tubeid report").Figure

    return Figure(figsize=(7.0, 4.4), layout="constrained")


def _save(fig, out: Path, name: str, written: list) -> None:
    path = out / name
    fig.savefig(path, dpi=110)
    written.append(name)


def _in_band(da: xr.DataArray, band: float) -> xr.DataArray:
    return da.sel(frequency=da["frequency"] <= band * (1 + 1e-12))


# ---------------------------------------------------------------------- stages
def _stage_delta(store, out, n_bootstrap, seed, written, notes) -> dict:
    ds = _open_group(store, "delta")
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
    a = curve.attrs
    d = curve["delta"].values
    _likelihood_figure(store, curve, "delta", "delta_opt", a["argmax"], n_bootstrap, "C0",
                       "dispersion δ of K_B (dimensionless)", f"p_J(J_ref; δ)  [1/({units})]",
                       f"Likelihood of δ (Figure 5), {J.sizes['realisation']} realisations per δ",
                       out, "fig5_delta_likelihood.png", written)
    q = {"value": a["argmax"], "std": a["argmax_std"], "low": a["argmax_low"], "high": a["argmax_high"],
         "discrete": a["argmax_discrete"], "at_boundary": bool(a["argmax_at_boundary"]),
         "n_realisations": int(J.sizes["realisation"])}
    return {"quantities": {"delta_opt": q}, "details": {"J_ref": j_ref, "J_units": units,
                                                         "grid": [float(d[0]), float(d[-1]), int(d.size)]}}


def _likelihood_figure(store, curve, dim, key, optimum, n_bootstrap, color, xlabel, ylabel, title, out, name, written):
    """A likelihood curve with its bootstrap band, the optimum and the value it is compared with."""
    targets, label = _targets(store)
    symbol = {"delta_opt": "δ_opt", "delta_F_opt": "δ_F,opt"}[key]
    fig = _figure()
    ax = fig.add_subplot()
    d = curve[dim].values
    if n_bootstrap > 0:
        ax.fill_between(d, curve.likelihood_low, curve.likelihood_high, alpha=0.3, color=color,
                        label=f"bootstrap {100 * curve.attrs['confidence']:g} % band")
    ax.plot(d, curve.likelihood, "o-", color=color, ms=3, label=f"{ylabel.split('  ')[0]} (Gaussian KDE)")
    ax.axvline(optimum, color="C3", label=f"{symbol} = {optimum:.3f}")
    ax.axvline(targets[key], color="k", ls="--", label=f"{label}: {symbol} = {targets[key]:g}")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend(fontsize=8)
    _save(fig, out, name, written)


def _stage_response(store, out, sensor, written, notes) -> dict:
    ds = _open_response(store)
    band = float(ds.attrs.get("band_hz", 100.0))
    found = {v: ds[v] for v in ("psd_reference", "psd_mean", "psd_stochastic") if v in ds.data_vars}
    if "psd_reference" not in found:
        raise _StageMissing("variable 'psd_reference' missing from group 'response'")
    for v in ("psd_mean", "psd_stochastic"):
        if v not in found:
            notes.append(f"response.{v} missing: {'Figure 4' if v == 'psd_mean' else 'Figure 6'} not drawn")
    ref = _complete(found["psd_reference"], "realisation_ref", "response.psd_reference", notes, 1)
    name = _sensor_name(ref, sensor)
    ref_auto = _in_band(_auto(ref, sensor).mean("realisation_ref"), band)
    f = ref_auto["frequency"].values
    details: dict = {"sensor": name, "band_hz": band, "delta_opt_used": ds.attrs.get("delta_opt"),
                     "n_reference_records": int(ref.sizes["realisation_ref"])}
    for part, draw in (("psd_mean", _figure4), ("psd_stochastic", _figure6)):
        if part in found:
            try:
                draw(found[part], ds, f, ref_auto, name, band, sensor, out, written, notes, details)
            except _StageMissing as exc:
                notes.append(f"response.{part} not used: {exc}")
    return {"details": details}


def _figure4(mean, ds, f, ref_auto, name, band, sensor, out, written, notes, details) -> None:
    """Figure 4: reference vs mean simplified model at the sensor; log10 errors below/above 35 Hz."""
    extra = [d for d in mean.dims if d not in ("frequency",) + _SENSOR_DIMS]
    for d in extra:
        mean = _complete(mean, d, f"response.psd_mean ({d})", notes, 1)
    mean_auto = _in_band(_auto(mean, sensor), band)
    if extra:
        mean_auto = mean_auto.mean(extra)
    if mean_auto.sizes["frequency"] != f.size or not np.allclose(mean_auto["frequency"].values, f):
        notes.append("response.psd_mean is on another frequency grid than psd_reference: Figure 4 not drawn")
    else:
        fig = _figure()
        ax = fig.add_subplot()
        ax.semilogy(f, ref_auto, lw=0.8, color="C0", label="reference model (\"experimental\")")
        ax.semilogy(f, mean_auto, lw=1.8, color="C3", label="mean simplified model")
        ax.set_xlim(0, band)
        ax.set_xlabel("frequency [Hz]")
        ax.set_ylabel(f"PSD of the displacement at {name} [m²/Hz] (two-sided)")
        ax.set_title("Reference vs mean simplified model (Figure 4)")
        ax.legend(fontsize=8)
        _save(fig, out, "fig4_mean_model.png", written)
        pos = (f > 0) & (ref_auto.values > 0) & (mean_auto.values > 0)
        lr = np.abs(np.log10(mean_auto.values[pos] / ref_auto.values[pos]))
        fp = f[pos]
        details["mean_model_log10_error_0_35_hz"] = float(np.mean(lr[fp < 35])) if np.any(fp < 35) else None
        details["mean_model_log10_error_35_100_hz"] = float(np.mean(lr[fp >= 35])) if np.any(fp >= 35) else None


def _figure6(sto, ds, f, ref_auto, name, band, sensor, out, written, notes, details) -> None:
    """Figure 6: 95 % region of the stochastic simplified model vs the reference; coverage."""
    sto = _complete(sto, "realisation", "response.psd_stochastic", notes, 2)
    sto_auto = _in_band(_auto(sto, sensor), band)
    if sto_auto.sizes["frequency"] != f.size or not np.allclose(sto_auto["frequency"].values, f):
        notes.append("response.psd_stochastic is on another frequency grid than psd_reference: "
                     "Figure 6 not drawn")
    else:
        cb = confidence_band(sto_auto, 0.95, dim="realisation")
        fig = _figure()
        ax = fig.add_subplot()
        ax.fill_between(f, cb.lower, cb.upper, color="C1", alpha=0.35, lw=0,
                        label=f"95 % region, stochastic simplified model ({sto.sizes['realisation']} realisations)")
        ax.semilogy(f, cb.lower, lw=0.6, color="C1")
        ax.semilogy(f, cb.upper, lw=0.6, color="C1")
        ax.semilogy(f, ref_auto, lw=1.6, color="C0", label="reference model")
        ax.set_yscale("log")
        ax.set_xlim(0, band)
        ax.set_xlabel("frequency [Hz]")
        ax.set_ylabel(f"PSD of the displacement at {name} [m²/Hz] (two-sided)")
        dopt = ds.attrs.get("delta_opt")
        ax.set_title("Confidence region of the response (Figure 6)"
                     + (f", δ = {float(dopt):.3g}" if dopt is not None else ""))
        ax.legend(fontsize=8)
        _save(fig, out, "fig6_confidence_region.png", written)
        sel = f > 0
        inside = (ref_auto.values >= cb.lower.values) & (ref_auto.values <= cb.upper.values)
        details["confidence_region_coverage"] = float(np.mean(inside[sel]))
        details["n_stochastic_realisations"] = int(sto.sizes["realisation"])


def _stage_load_r(store, out, n_bootstrap, seed, sensor, written, notes) -> dict:
    try:  # the refined grid around the coarse minimum, when the study made one
        ds, grid_name = _open_group(store, "load_r_fine"), "load_r_fine"
    except _StageMissing:
        ds, grid_name = _open_group(store, "load_r"), "load_r"
    psd = _variable(ds, grid_name, "psd")
    try:
        resp = _open_response(store)
        ref = _variable(resp, "response", "psd_reference")
    except _StageMissing as exc:
        raise _StageMissing(f"load_r needs the experimental PSD response.psd_reference: {exc}") from None
    band = float(ds.attrs.get("band_hz", resp.attrs.get("band_hz", 100.0)))
    band = min(band, float(psd.frequency.values[-1]))  # a stored grid may stop one bin short of the band
    psd = _complete(psd, "realisation", f"{grid_name}.psd", notes, 2)
    ref = _complete(ref, "realisation_ref", "response.psd_reference", notes, 1)
    try:
        dm = distance_map(psd, ref, band_hz=band, n_bootstrap=n_bootstrap, rng=rng_for(seed, "report", "load_r"))
    except SpecificationError as exc:
        raise _StageMissing(f"D(r) could not be computed: {exc}") from None
    maps = {"paper": dm}
    # beyond the paper: D weighted by the mean simplified model's own PSD, and the log band levels (GLS)
    if "psd_mean" in resp.data_vars:
        try:
            mean = resp["psd_mean"]
            extra = [d for d in mean.dims if d not in ("frequency",) + _SENSOR_DIMS]
            mean = mean.mean(extra) if extra else mean
            maps["relative"] = distance_map(psd, ref, band_hz=band, n_bootstrap=n_bootstrap,
                                            rng=rng_for(seed, "report", "load_r", "relative"), weight=relative_weight(mean.load()))
        except SpecificationError as exc:
            notes.append(f"relative-weighted D not computed: {exc}")
    try:
        maps["bands"] = log_band_distance_map(psd, ref, band_hz=band, n_bootstrap=n_bootstrap,
                                              rng=rng_for(seed, "report", "load_r", "bands"))
    except SpecificationError as exc:
        notes.append(f"log-band distance not computed: {exc}")
    used = _study_parameters(store).get("distance", "paper")
    if used not in maps:
        notes.append(f"the study's distance {used!r} could not be recomputed; the table uses the paper's D")
        used = "paper"
    a = maps[used].attrs
    # D_min, D_units, D_min_relative: always the paper's D (the summary line says so)
    quantities, details = {}, {"distance": used, "D_min": dm.attrs["D_min"], "D_units": dm.attrs["D_units"],
                               "D_min_relative": dm.attrs["D_min"] / dm.attrs["J_s_exp"] if dm.attrs["J_s_exp"] > 0 else None,
                               "r_opt_corr": a["r_opt_corr"], "grid_dims": a["grid_dims"],
                               "n_realisations": a["n_realisations"], "n_reference_records": a["n_experimental_records"]}
    for n, d in enumerate(a["grid_dims"]):
        quantities[f"{d}_opt"] = {"value": a["r_opt"][n], "std": a["r_opt_std"][n], "low": a["r_opt_low"][n],
                                  "high": a["r_opt_high"][n], "discrete": a["r_opt_discrete"][n],
                                  "at_boundary": bool(a["r_opt_at_boundary"]), "n_realisations": a["n_realisations"]}
        details[f"{d}_grid"] = [float(dm[d].values[0]), float(dm[d].values[-1]), int(dm.sizes[d])]
    for name, m in maps.items():
        details[f"r_opt_{name}"] = {"note": _DISTANCES[name], "r_opt": m.attrs["r_opt"], "r_opt_std": m.attrs["r_opt_std"],
                                    "r_opt_corr": m.attrs["r_opt_corr"], "at_boundary": bool(m.attrs["r_opt_at_boundary"])}
    if "bands" in maps:  # goodness of fit: about 1 if the experiment is a draw of the model class
        details["r_opt_bands"]["mean_squared_standardised_residual"] = float(maps["bands"].D_relative.min())
    _plot_d_map(maps[used], out, written, _targets(store))
    return {"quantities": quantities, "details": details}


def _plot_d_map(dm: xr.Dataset, out: Path, written: list, target: tuple[dict, str]) -> None:
    dims = dm.attrs["grid_dims"]
    units = dm.attrs["D_units"]
    axis_units = {"r1": "N²/Hz", "r2": "(N·m)²/Hz"}
    fig = _figure()
    ax = fig.add_subplot()
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
        from matplotlib.ticker import FuncFormatter

        plain = FuncFormatter(lambda v, _: f"{v:g}")
        for axis in (ax.xaxis, ax.yaxis):
            axis.set_major_formatter(plain)
            axis.set_minor_formatter(plain)
        r, s = dm.attrs["r_opt"], dm.attrs["r_opt_std"]
        ax.errorbar([r[0]], [r[1]], xerr=[[_num(s[0]) or 0]], yerr=[[_num(s[1]) or 0]], fmt="o", color="C3",
                    capsize=3, label=f"r_opt = ({r[0]:.3g}, {r[1]:.3g}) ± bootstrap std")
        rd = dm.attrs["r_opt_discrete"]
        ax.plot([rd[0]], [rd[1]], "s", mfc="none", color="w", label="grid minimum")
        if (d1, d2) == ("r1", "r2"):
            targets, label = target
            ax.plot([targets["r1_opt"]], [targets["r2_opt"]], "*", color="k", ms=12,
                    label=f"{label}: r_opt = ({targets['r1_opt']:g}, {targets['r2_opt']:g})")
        ax.set_xlabel(f"{d1} [{axis_units.get(d1, '')}]")
        ax.set_ylabel(f"{d2} [{axis_units.get(d2, '')}]")
        ax.legend(fontsize=8, loc="best")
        ax.set_title("Trial method: D(r) = ∫ ||S̄_Z(ω, r) − S_Z,exp(ω)||²_F dω" if units != "1" else
                     "Trial method: D(r) = Σ (log band level, model − experiment)² / variance")
    else:
        d1 = dims[0]
        others = {d: 0 for d in dims[1:]}
        line = dm.D.isel(others) if others else dm.D
        ax.loglog(dm[d1].values, line.values, "o-", label="D")
        ax.axvline(dm.attrs["r_opt"][0], color="C3", label="r_opt")
        ax.set_xlabel(f"{d1} [{axis_units.get(d1, '')}]")
        ax.set_ylabel(f"D [{units}]")
        ax.legend(fontsize=8)
        ax.set_title("Trial method: D(r)" + (" (first slice of the other axes)" if others else ""))
    _save(fig, out, "d_map.png", written)


def _stage_load_delta_f(store, out, n_bootstrap, seed, written, notes) -> dict:
    ds = _open_group(store, "load_delta_f")
    Js = _variable(ds, "load_delta_f", "J_s")
    if set(Js.dims) != {"delta_F", "realisation"}:
        raise _StageMissing(f"load_delta_f.J_s must have dims (delta_F, realisation), not {tuple(Js.dims)}")
    js_exp = _attr(ds, "J_s", "J_s_exp")
    source = "attribute J_s_exp of group 'load_delta_f'"
    if js_exp is None:
        try:
            ref = _variable(_open_response(store), "response", "psd_reference")
            ref = _complete(ref, "realisation_ref", "response.psd_reference", notes, 1)
            band = float(ds.attrs.get("band_hz", 100.0))
            recs = [r.transpose("frequency", ...) for _, r in ref.groupby("realisation_ref", squeeze=False)]
            # one J_s per record, like the model samples (J_s of an averaged PSD would be biased low)
            js_exp = [float(j_s(r["frequency"].values, r.squeeze("realisation_ref", drop=True).values, band)) for r in recs]
            js_exp = js_exp[0] if len(js_exp) == 1 else js_exp
            source = "computed from response.psd_reference (one value per record)"
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
    a = lk.attrs
    _likelihood_figure(store, lk, "delta_F", "delta_F_opt", a["delta_F_opt"], n_bootstrap, "C2",
                       "load dispersion δ_F (dimensionless)", f"p_Js(J_s,exp; δ_F)  [1/({units})]",
                       f"Likelihood of δ_F, {Js.sizes['realisation']} realisations per δ_F",
                       out, "delta_f_likelihood.png", written)
    q = {"value": a["delta_F_opt"], "std": a["delta_F_opt_std"], "low": a["delta_F_opt_low"],
         "high": a["delta_F_opt_high"], "discrete": a["argmax_discrete"], "at_boundary": bool(a["argmax_at_boundary"]),
         "n_realisations": int(Js.sizes["realisation"])}
    return {"quantities": {"delta_F_opt": q}, "details": {"J_s_exp": js_exp, "J_s_exp_source": source,
                                                           "J_s_units": units}}


# ---------------------------------------------------------------------- summary
_DISTANCES = {
    "paper": "the paper's D = integral of ||mean S_model - S_exp||_F^2 dw",
    "relative": "beyond the paper: D weighted by 1/sqrt(S_aa S_bb) of the mean simplified model's PSD",
    "bands": "beyond the paper: generalised least squares of the log band energies (5 Hz bands, inverse model variance)",
}


def _study_parameters(store: str) -> dict:
    """The pipeline's parameter values (root attribute ``parameters``), or {} when absent."""
    try:
        return json.loads(dict(zarr.open_group(str(store), mode="r").attrs).get("parameters", "{}"))
    except Exception:  # not a pipeline store, or an older layout: the defaults apply
        return {}


def _targets(store: str) -> tuple[dict, str]:
    """What identified values are compared with: the truth of a synthetic experiment, else the paper."""
    try:
        attrs = _open_group(store, "reference").attrs
    except _StageMissing:
        return PAPER_VALUES, "paper"
    truth = {k: float(attrs[f"truth_{k}"]) for k in PAPER_VALUES if f"truth_{k}" in attrs}
    return (truth, "truth") if len(truth) == len(PAPER_VALUES) else (PAPER_VALUES, "paper")


def _comment(key: str, q: dict, corr=None, targets=PAPER_VALUES, label="paper") -> str:
    paper = targets[key]
    v, s = q.get("value"), q.get("std")
    if v is None or not math.isfinite(v):
        return "Not identified."
    edge = " The optimum lies on the edge of the grid: widen the grid." if q.get("at_boundary") else ""
    diff = v - paper
    if s is not None and math.isfinite(s) and s > 0:
        z = abs(diff) / s
        if z <= 2.0:
            return f"Agrees with the {label} within the Monte Carlo uncertainty ({z:.1f} σ).{edge}"
        zs = f" ({z:.1f} σ of the Monte Carlo uncertainty)"
    else:
        zs = " (no Monte Carlo uncertainty available)"
    if label != "paper":
        return f"Differs from the {label} by {diff / paper:+.0%}{zs}.{edge}"
    cause = _CAUSES["r" if key in ("r1_opt", "r2_opt") else key]
    if "{corr}" in cause:
        cause = cause.format(corr=f"{corr:+.2f}" if corr is not None and math.isfinite(corr) else "n/a")
    return f"Differs from the paper by {diff / paper:+.0%}{zs}. Likely cause: {cause}{edge}"


def _markdown(summary: dict) -> str:
    lines = [f"# tubeid report: {summary['store']}", "",
             "Identification of the stochastic loads on the tube bundle (Batou & Soize 2008) from a "
             "`tubeid` study store. Monte Carlo uncertainty: bootstrap over realisations "
             f"({summary['n_bootstrap']} replicates, seed {summary['seed']}); ± is one standard deviation, "
             "the interval is the bootstrap 95 % percentile interval.", "",
             f"| quantity | identified | ± MC std | 95 % interval | {summary['target_label']} | units | comment |",
             "|---|---|---|---|---|---|---|"]
    for key in ("delta_opt", "r1_opt", "r2_opt", "delta_F_opt"):
        q = summary["quantities"].get(key)
        if q is None:
            lines.append(f"| {_LABELS[key]} | missing | | | {summary['target_values'][key]:g} | {_UNITS[key]} | stage not available |")
            continue
        lines.append(f"| {_LABELS[key]} | {_fmt(q['value'], 4)} | {_fmt(q['std'], 2)} | "
                     f"[{_fmt(q['low'])}, {_fmt(q['high'])}] | {summary['target_values'][key]:g} | {_UNITS[key]} | {q['comment']} |")
    lines.append("")
    det = summary["details"]
    if "delta" in det:
        lines.append(f"- J_ref = {_fmt(det['delta']['J_ref'], 6)} {det['delta']['J_units']} "
                     + ("(reference model, band ±100 Hz)." if summary["target_label"] == "paper" else "(synthetic experiment)."))
    if "response" in det:
        r = det["response"]
        if r.get("mean_model_log10_error_0_35_hz") is not None:
            lines.append(f"- Mean simplified model vs reference at {r['sensor']}: mean |log10 ratio| of the PSD "
                         f"{_fmt(r['mean_model_log10_error_0_35_hz'])} over 0–35 Hz and "
                         f"{_fmt(r['mean_model_log10_error_35_100_hz'])} over 35–100 Hz (the paper sees the "
                         "differences in 35–100 Hz).")
        if r.get("confidence_region_coverage") is not None:
            lines.append(f"- The reference PSD lies inside the 95 % region of the stochastic simplified model at "
                         f"{100 * r['confidence_region_coverage']:.0f} % of the frequency bins in 0–{r['band_hz']:g} Hz.")
    if "load_r" in det:
        lr = det["load_r"]
        lines.append(f"- The paper's D(r): minimum {_fmt(lr['D_min'])} {lr['D_units']} "
                     f"({_fmt(100 * lr['D_min_relative'] if lr['D_min_relative'] is not None else None)} % of "
                     "J_s,exp); bootstrap correlation of the r components: "
                     f"{_fmt(lr['r_opt_corr'][0][1] if len(lr['r_opt_corr']) > 1 else None, 2)}.")
        lines.append(f"- The table's r uses {_DISTANCES[lr.get('distance', 'paper')]} (the study's `distance`).")
        for name in _DISTANCES:
            rr = lr.get(f"r_opt_{name}")
            if rr is not None and name != lr.get("distance", "paper"):
                lines.append(f"- With {_DISTANCES[name]}: r_opt = ({', '.join(_fmt(v, 4) for v in rr['r_opt'])}) ± "
                             f"({', '.join(_fmt(v, 2) for v in rr['r_opt_std'])}).")
        msr = (lr.get("r_opt_bands") or {}).get("mean_squared_standardised_residual")
        if msr is not None:
            verdict = ("no sign of model-form error (values of a few come from the grid's discreteness and the "
                       "δ used)" if msr < 10 else
                       "the model does not explain the experiment within its own scatter (model-form error): "
                       "r from the band levels is then not meaningful")
            lines.append(f"- Log band levels at the grid minimum: mean squared standardised residual {_fmt(msr, 3)} "
                         f"(about 1 for a draw of the model class at a grid point): {verdict}.")
    if "load_delta_f" in det:
        lines.append(f"- J_s,exp = {_fmt(det['load_delta_f']['J_s_exp'], 6)} {det['load_delta_f']['J_s_units']} "
                     f"({det['load_delta_f']['J_s_exp_source']}).")
    lines.append("")
    if summary["missing"]:
        lines.append("## Missing or incomplete stages")
        lines.append("")
        lines += [f"- {m}" for m in summary["missing"]]
        lines.append("")
    if summary["notes"]:
        lines.append("## Notes")
        lines.append("")
        lines += [f"- {n}" for n in summary["notes"]]
        lines.append("")
    lines.append("## Figures")
    lines.append("")
    lines += [f"- [{f}]({f})" for f in summary["figures"]] or ["- none"]
    lines.append("")
    return "\n".join(lines)


def make_report(store, out=None, *, n_bootstrap: int = 200, seed: int = 2008, sensor: str | None = None) -> dict:
    """Analyse every stage of ``store``, write figures, summary.md and summary.json into ``out``.

    Returns the summary (the content of summary.json). Missing stages are listed in
    ``summary["missing"]`` instead of failing.
    """
    store = os.fspath(store)
    if not os.path.exists(store):
        raise SpecificationError("store", store, "no such Zarr store")
    if isinstance(n_bootstrap, bool) or not isinstance(n_bootstrap, (int, np.integer)) or n_bootstrap < 0:
        raise SpecificationError("n_bootstrap", n_bootstrap, "must be an integer >= 0")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise SpecificationError("seed", seed, "must be a non-negative integer")
    out = Path(out) if out is not None else Path(store.rstrip("/\\").removesuffix(".zarr") + "-report")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SpecificationError("out", str(out), f"cannot create the output directory ({exc})") from None
    written: list = []
    notes: list = []
    missing: list = []
    stages: dict = {}
    quantities: dict = {}
    details: dict = {}
    runners = {
        "delta": lambda: _stage_delta(store, out, n_bootstrap, seed, written, notes),
        "response": lambda: _stage_response(store, out, sensor, written, notes),
        "load_r": lambda: _stage_load_r(store, out, n_bootstrap, seed, sensor, written, notes),
        "load_delta_f": lambda: _stage_load_delta_f(store, out, n_bootstrap, seed, written, notes),
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
    targets, label = _targets(store)
    for key, q in quantities.items():
        if key in PAPER_VALUES:
            q["paper"] = PAPER_VALUES[key]
            q[label] = targets[key]
            q["units"] = _UNITS[key]
            q["comment"] = _comment(key, q, corr, targets, label)
    summary = _jsonable({
        "store": store, "generated_by": "tubeid report", "seed": seed, "n_bootstrap": n_bootstrap,
        "paper_values": PAPER_VALUES, "target_values": targets, "target_label": label, "stages": stages, "missing": missing, "notes": notes,
        "quantities": quantities, "details": details, "figures": written,
    })
    (out / "summary.json").write_text(json.dumps(summary, indent=2, ensure_ascii=False) + "\n", encoding="utf-8")
    (out / "summary.md").write_text(_markdown(summary), encoding="utf-8")
    return summary


# ---------------------------------------------------------------------- command line
def _run(args) -> int:
    s = make_report(args.store, args.out, n_bootstrap=args.n_bootstrap, seed=args.seed, sensor=args.sensor)
    out = args.out or (args.store.rstrip("/\\").removesuffix(".zarr") + "-report")
    print(f"report written to {out}: {', '.join(s['figures'] + ['summary.md', 'summary.json'])}")
    for key in ("delta_opt", "r1_opt", "r2_opt", "delta_F_opt"):
        q = s["quantities"].get(key)
        if q is not None:
            print(f"  {key:12s} {_fmt(q['value'], 4):>10s} ± {_fmt(q['std'], 2):<8s} ({s['target_label']} {s['target_values'][key]:g})")
    for m in s["missing"]:
        print(f"  missing: {m}")
    return 0


def register(sub) -> None:
    p = sub.add_parser("report", help="figures and summary (Markdown, JSON) of a paper study store")
    p.add_argument("store", help="Zarr store written by the paper study (groups delta, response, load_r, load_delta_f)")
    p.add_argument("--out", default=None, help="output directory (default: <store>-report beside the store)")
    p.add_argument("--n-bootstrap", type=int, default=200, help="bootstrap replicates for the Monte Carlo "
                   "uncertainties (default 200)")
    p.add_argument("--seed", type=int, default=2008, help="seed of the bootstrap generators (default 2008)")
    p.add_argument("--sensor", default=None, help="sensor of Figures 4 and 6 (default P_obs, else the first)")
    p.set_defaults(func=_run)
