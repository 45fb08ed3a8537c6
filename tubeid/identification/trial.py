"""The trial method for the load level r: one entry point, every distance, coarse then fine.

Paper §4 (MODEL.md §3.4): the mean load spectrum is parametrised by r (here r = (r1, r2) of the
force-and-moment model, or any grid of positive parameters); the stochastic simplified model is run
at every point of a trial grid, and r_opt minimises a distance between its mean response PSD and
the experimental one. This module is the one place where that identification is done: the paper
study (``studies/paper.py``), its report and the diagnosis call :func:`identify_r`; the distances
themselves are the engines of :mod:`tubeid.identification.loads`.

Distances (``DISTANCES``, registered as data; the name is stored with every result):

``"paper"``     D(r) = ∫_B ‖S̄_Z(ω, r) − S_Z,exp(ω)‖²_F dω, the paper's (``distance_map``): dominated
                by the largest resonance peaks.
``"relative"``  the same with every element weighted by W_ab = 1/√(S_aa S_bb) of a *model* PSD
                (``relative_weight``): the spectra compared relative to their own level. The weight
                comes from ``weight_psd`` when given, else from this grid's own mean PSD at the grid
                minimum of the paper's D (a second identification then uses the first one's
                ``weight_psd``, so a coarse and a fine pass use one weight).
``"bands"``     generalised least squares of the log energies of ``band_width_hz`` bands, each band
                weighted by the inverse of its Monte Carlo variance (``log_band_distance_map``).
``"log"``       the mean squared log10 ratio of the auto-spectra over 0 < f ≤ band, every bin alike
                (``log_spectral_distance_map``).

Coarse then fine: ``identify_r`` on a coarse grid, :func:`fine_grid` around its grid minimum (± one
coarse step per axis by default), ``identify_r`` on the fine grid (with the coarse result's
``weight_psd`` for ``"relative"``). The refined minimiser (``refine=True``) fits a quadratic
surrogate in log r of the mean spectra (or of their log band levels) on the 3^k grid points around
the grid minimum and minimises its distance within them (module docstring of ``loads``).

PSDs are two-sided per Hz (m²/Hz for displacements); r in the grid's units (N²/Hz, (N·m)²/Hz).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import xarray as xr

from tubeid._validation import allocation, integer, is_number, one_of, positive, replicates
from tubeid.errors import Described as _Desc, SpecificationError
from tubeid.identification.loads import (distance_map, log_band_distance_map, log_spectral_distance_map,
                                         refine_grid, relative_weight)

__all__ = ["identify_r", "fine_grid", "DISTANCES"]

#: The distances of the trial method: name → what it is (stored with every result as ``distance_description``).
DISTANCES = {
    "paper": "the paper's D = integral over the band of ||mean S_model(w, r) - S_exp(w)||_F^2 dw",
    "relative": "D weighted elementwise by 1/sqrt(S_aa S_bb) of a model PSD (the spectra relative to their own level)",
    "bands": "generalised least squares of the log band energies (inverse model variance per band and sensor)",
    "log": "mean squared log10 ratio of the auto-spectra over 0 < f <= band, every bin alike",
}


def _mean_at_minimum(psd_grid: xr.DataArray, dm: xr.Dataset, dim: str) -> xr.DataArray:
    """The grid's mean PSD (over ``dim``) at the grid minimum of the map ``dm``."""
    at = {d: v for d, v in zip(dm.attrs["grid_dims"], dm.attrs["r_opt_discrete"])}
    psd = psd_grid.sel(at).mean(dim)
    return psd.load() if hasattr(psd, "load") else psd


def identify_r(psd_grid: xr.DataArray, psd_exp: xr.DataArray, *, distance: str = "paper", band_hz: float = 100.0,
               weight_psd: xr.DataArray | None = None, refine: bool = True, n_bootstrap: int = 0,
               rng: np.random.Generator | int | None = None,
               dim: str = "realisation", confidence: float = 0.95, band_width_hz: float = 5.0) -> xr.Dataset:
    """r_opt of a trial grid against an experiment, by one of the :data:`DISTANCES`.

    Parameters
    ----------
    psd_grid
        Model PSDs, dims (*grid, ``dim``, "frequency"[, "sensor", "sensor_"]) in any order, two-sided
        per Hz, complex or real (auto-spectra). Every other dimension is a grid axis with a strictly
        increasing positive coordinate (e.g. r1 [N²/Hz], r2 [(N·m)²/Hz]). Realisation k should use
        the same random germs at every grid point (common random numbers). Auto-spectra (their mean
        over ``dim``) must be >= 0 in the band.
    psd_exp
        Experimental PSD ("frequency"[, "sensor", "sensor_"]) on the same frequencies (Hz, from 0)
        and sensors; one extra dimension holds independent records (averaged; resampled by the
        bootstrap). Auto-spectra (averaged over the records) >= 0 in the band.
    distance
        A key of :data:`DISTANCES`.
    band_hz
        Upper end of the band B = 2π[−band, band] rad/s [Hz].
    weight_psd
        ``"relative"`` only: the model PSD ("frequency"[, sensors]) the weight 1/√(S_aa S_bb) is
        computed from; default: this grid's mean PSD at the grid minimum of the paper's D. Pass the
        ``weight_psd`` of a coarse pass to a fine pass so both use one weight.
    refine
        True: the refined minimiser (quadratic surrogate of the spectra in log r around the grid
        minimum); False: the grid minimum.
    n_bootstrap, rng
        Bootstrap replicates of the Monte Carlo error (realisations resampled jointly across the
        grid, records independently) and their generator or seed (required if ``n_bootstrap`` > 0).
        The point estimate does not depend on them.
    dim
        The realisation dimension of ``psd_grid``.
    confidence
        Probability of the bootstrap percentile intervals.
    band_width_hz
        ``"bands"`` only: the width of the bands [Hz].

    Returns
    -------
    xarray.Dataset
        On the grid dims: ``D`` (units in its ``units`` attribute: (m²/Hz)²·rad/s for ``"paper"``,
        rad/s for ``"relative"``, 1 for ``"bands"``, decades² for ``"log"``), ``D_relative`` and the
        bootstrap ``D_std``/``D_low``/``D_high``. On dimension ``parameter`` (the grid dims' names):
        ``r_opt`` (refined, or the grid minimum when ``refine`` is False), ``r_opt_discrete`` (grid
        minimum), ``r_opt_std``, ``r_opt_low``, ``r_opt_high`` (bootstrap; NaN without). For
        ``"relative"``: ``weight_psd``. Attributes: ``distance``, ``distance_description``,
        ``grid_dims``, ``r_opt``, ``r_opt_discrete``, ``r_opt_std``, ``r_opt_low``,
        ``r_opt_high``, ``r_opt_corr`` (lists in ``grid_dims`` order), ``r_opt_at_boundary``
        (bool: the grid minimum lies on an edge of an axis with more than one value: widen it), ``D_min``, ``D_units``,
        ``refined`` (bool), ``weight_source`` and the engine's settings (``n_realisations``,
        ``n_experimental_records``, ``n_bootstrap``, ``bootstrap``, ...).
    """
    distance = one_of("distance", distance, tuple(DISTANCES))
    if not isinstance(refine, (bool, np.bool_)):
        raise SpecificationError("refine", refine, "must be True or False")
    band = positive("band_hz", band_hz, "Hz")
    n_bootstrap = replicates("n_bootstrap", n_bootstrap)
    if weight_psd is not None and distance != "relative":
        raise SpecificationError("weight_psd", _Desc(type(weight_psd).__name__), f"is only used by distance='relative', not {distance!r}")
    common = dict(band_hz=band, n_bootstrap=n_bootstrap, rng=rng, dim=dim, confidence=confidence)
    weight_source = "none"
    if distance == "paper":
        dm = distance_map(psd_grid, psd_exp, refine="spectrum" if refine else None, **common)
    elif distance == "relative":
        if weight_psd is None:
            paper = distance_map(psd_grid, psd_exp, band_hz=band, n_bootstrap=0, dim=dim, refine=None)
            weight_psd = _mean_at_minimum(psd_grid, paper, dim)
            weight_source = ("mean model PSD at r = (" + ", ".join(f"{v:.6g}" for v in paper.attrs["r_opt_discrete"])
                             + "), the paper D's grid minimum on the grid the weight was computed from")
        else:
            if not isinstance(weight_psd, xr.DataArray):
                raise SpecificationError("weight_psd", _Desc(type(weight_psd).__name__), "must be an xarray.DataArray")
            weight_source = str(weight_psd.attrs.get("weight_source", "given"))
        dm = distance_map(psd_grid, psd_exp, refine="spectrum" if refine else None,
                          weight=relative_weight(weight_psd), **common)
    elif distance == "bands":
        dm = log_band_distance_map(psd_grid, psd_exp, band_width_hz=band_width_hz, refine=bool(refine), **common)
    else:
        dm = log_spectral_distance_map(psd_grid, psd_exp, refine=bool(refine), **common)
    a = dm.attrs
    dims = list(a["grid_dims"])
    r_opt = a["r_opt"] if refine else a["r_opt_discrete"]
    out = dm.assign_coords(parameter=("parameter", dims))
    units = [str(psd_grid[d].attrs.get("units", "")) for d in dims]
    for name, values, what in (("r_opt", r_opt, "r_opt"), ("r_opt_discrete", a["r_opt_discrete"], "grid minimum"),
                               ("r_opt_std", a["r_opt_std"], "bootstrap standard deviation of r_opt"),
                               ("r_opt_low", a["r_opt_low"], f"bootstrap {100 * a['confidence']:g} % interval of r_opt, low"),
                               ("r_opt_high", a["r_opt_high"], f"bootstrap {100 * a['confidence']:g} % interval of r_opt, high")):
        out[name] = xr.DataArray(np.asarray(values, dtype=float), dims=("parameter",),
                                 attrs={"long_name": what, "units": "; ".join(units)})
    edge = [bool(fine_ax.size > 1 and v in (fine_ax[0], fine_ax[-1]))
            for fine_ax, v in ((np.asarray(psd_grid[d].values, dtype=float), r) for d, r in zip(dims, a["r_opt_discrete"]))]
    out["at_grid_edge"] = xr.DataArray(np.asarray(edge), dims=("parameter",),
                                       attrs={"long_name": "the grid minimum lies on the first or last value of this axis"})
    if distance == "relative":
        wp = xr.DataArray(np.asarray(weight_psd.values), dims=weight_psd.dims,
                          coords={d: weight_psd[d] for d in weight_psd.dims if d in weight_psd.coords},
                          attrs={"long_name": "model PSD the relative weight 1/sqrt(S_aa S_bb) is computed from",
                                 "units": str(psd_grid.attrs.get("units", "m^2/Hz")), "weight_source": weight_source})
        out["weight_psd"] = wp
    out.attrs.update(distance=distance, distance_description=DISTANCES[distance], r_opt=[float(v) for v in r_opt],
                     r_opt_at_boundary=bool(any(edge)), refined=bool(refine), weight_source=weight_source)
    for n, d in enumerate(dims):
        out.attrs[f"{d}_opt"] = float(r_opt[n])
    return out


def fine_grid(coarse: xr.Dataset, n: int, *, steps: float = 1.0,
              centre: Mapping[str, float] | Sequence[float] | None = None) -> dict[str, np.ndarray]:
    """A finer trial grid around a coarse identification's grid minimum.

    Parameters
    ----------
    coarse
        A result of :func:`identify_r` (its grid coordinates and ``r_opt_discrete``).
    n
        Values per axis (odd: the centre is a grid point), ≥ 2.
    steps
        Half-width of the fine grid in coarse steps: each axis spans centre·c^(−steps) …
        centre·c^(steps), c the ratio between the coarse values next to the centre (the larger one
        at an uneven spacing). Axes with one value stay at that value.
    centre
        Override of the centre, each value a number > 0 in the grid's units: a dict keyed by every
        grid dim (no other key), or a sequence in ``grid_dims`` order (a number for a one-dim grid);
        default: the coarse grid minimum.

    Returns
    -------
    dict
        {grid dim: values (geometric, increasing)}, in ``grid_dims`` order, in the grid's units.
    """
    if not isinstance(coarse, xr.Dataset) or "r_opt_discrete" not in coarse.attrs or "grid_dims" not in coarse.attrs:
        raise SpecificationError("coarse", _Desc(type(coarse).__name__), "must be a result of identify_r")
    n = integer("n", n, minimum=2)
    steps = positive("steps", steps)
    dims = list(coarse.attrs["grid_dims"])
    allocation("n", n, 8.0 * float(n) ** len(dims), f"a grid of {n}^{len(dims)} points (each a trial's simulations)")
    disc = [float(v) for v in coarse.attrs["r_opt_discrete"]]
    if centre is None:
        centre = disc
    elif isinstance(centre, Mapping):
        if set(centre) != set(dims):
            unknown = [k for k in centre if k not in dims]
            missing = [d for d in dims if d not in centre]
            raise SpecificationError("centre", centre, f"must be keyed by the grid dims {dims}"
                                     + (f" (unknown: {unknown})" if unknown else "")
                                     + (f" (missing: {missing})" if missing else ""))
        centre = [positive(f"centre[{d!r}]", centre[d]) for d in dims]
    else:
        if is_number(centre):
            centre = [centre]
        elif isinstance(centre, (str, bytes)):
            raise SpecificationError("centre", centre, f"must be a dict keyed by the grid dims {dims} or a sequence "
                                     "of numbers in that order")
        try:
            centre = list(np.atleast_1d(centre)) if isinstance(centre, np.ndarray) else list(centre)
        except TypeError:
            raise SpecificationError("centre", _Desc(type(centre).__name__), f"must be a dict keyed by the grid dims "
                                     f"{dims} or a sequence of numbers in that order") from None
        if len(centre) != len(dims):
            raise SpecificationError("centre", centre, f"must hold one value per grid dim {dims}")
        centre = [positive(f"centre[{i}]", v) for i, v in enumerate(centre)]
    out = {}
    for d, c, m in zip(dims, centre, disc):
        ax = np.asarray(coarse[d].values, dtype=float)
        if ax.size == 1:
            out[d] = np.array([c])
            continue
        i = int(np.argmin(np.abs(ax - m)))
        ratios = [ax[j + 1] / ax[j] for j in (i - 1, i) if 0 <= j < ax.size - 1]
        out[d] = refine_grid([c], max(ratios) ** steps, n)[0]
    return out

