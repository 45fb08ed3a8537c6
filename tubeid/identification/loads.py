"""Identification of the stochastic load: r_opt by the trial method, δ_F by maximum likelihood.

Paper §4 (MODEL.md §3.4–3.5). The mean load spectrum is parametrised by r (here a grid of one or
more positive parameters, e.g. r = (r1, r2) of the force-and-moment model, S_F = diag(r1, r2)):

    D(r) = ∫_B ‖S̄_Z(ω, r) − S_Z,exp(ω)‖²_F dω,     r_opt = argmin_r D(r),

with S̄_Z(ω, r) the Monte Carlo mean over realisations of the stochastic simplified model and B =
2π[−band, band] rad/s (``tubeid.dynamics.spectra.distance``: two-sided PSD per Hz, both signs of ω
counted). If the PSDs are in m²/Hz, D is in (m²/Hz)²·rad/s.

Monte Carlo uncertainty (beyond the paper): a bootstrap over model realisations, one index set per
replicate for the whole grid (common random numbers are kept, so the map stays smooth in every
replicate); if the experimental PSD carries independent records (one extra dimension), they are
resampled too. Each replicate gives a map D_b(r) and its minimiser, hence D_std, percentile bands and
the spread of r_opt.

Refinement of the minimiser, on the 3 × … × 3 block of grid points around the grid minimum
(shifted inwards at a grid edge; axes with fewer than 3 points stay at their grid value), in the
coordinates u = log r (``fit="log"``: a ratio grid r·c^k is evenly spaced) or u = r:

* ``refine="spectrum"`` (default): every value of the mean model spectrum S̄(ω, r) (each bin and
  sensor pair) is fitted by a full quadratic in u by least squares on the block, and the distance
  of that surrogate spectrum to S_exp (same integration rule as D) is minimised over the block
  (damped Newton; projected Newton from the best point of a dense grid if Newton leaves the
  block). S̄ is smooth and nearly linear in r while D is a squared norm with a curved valley, so
  this is far more accurate than fitting D:
  with S̄ linear in r and ``fit="linear"`` it is exact, and with ``fit="log"`` on a grid of ratio
  1.2 its error is 0.03 % where a quadratic fit of D errs by 1–1.5 %.
* ``refine="distance"``: a full quadratic in u fitted to D itself on the block; its stationary
  point, clipped to the block, if its Hessian is positive definite (else the grid minimum).
* ``refine=None``: the grid minimum.

Weighting (beyond the paper, ``weight=``): D_W = ∫_B ‖W ⊙ (S̄ − S_exp)‖²_F dω with a fixed
elementwise weight W(ω). The paper's D is dominated by the few largest resonance peaks, so its
minimiser is noisy and r1, r2 trade off along a valley; ``relative_weight`` (W_ab = 1/√(S_aa S_bb)
of a *model* PSD) spreads the information over the whole band (on the tube bundle, 50 s records:
a spread of r_opt about 3 times smaller). The weight must not be computed from the experimental
PSD itself: it would favour bins where S_exp is low by chance and bias r_opt low (measured: about
−9 % on r1). Computed from the same model realisations as the grid, it biases r_opt slightly high
(measured: +3 % on r2 with 8 realisations); use an independent model run.

δ_F is identified like δ (``tubeid.identification.likelihood``): J_s = ∫_B ‖S_Z(ω)‖²_F dω of each
realisation of the model with random load spectrum, δ_F ↦ p̂_Js(J_s,exp; δ_F) by a Gaussian kernel
estimate (Silverman), maximised over the grid.
"""

from __future__ import annotations

import math
import numbers

import numpy as np
import xarray as xr
from numpy.typing import ArrayLike

from tubeid.dynamics.spectra import distance, j_s, log_band_energies
from tubeid._validation import integer, numeric_array, open_unit, positive, real, replicates
from tubeid.errors import Described as _Desc, SpecificationError
from tubeid.identification.likelihood import _aligned, likelihood_curve
from tubeid.seeds import rng_for
from tubeid.uncertainty.random_matrices import delta_max

__all__ = ["distance_map", "log_band_distance_map", "log_spectral_distance_map", "relative_weight", "refine_grid", "delta_f_likelihood", "D_UNITS", "JS_UNITS"]

#: Unit of D(r) and of J_s for PSDs of displacements in m²/Hz.
D_UNITS = "(m^2/Hz)^2 rad/s"
JS_UNITS = D_UNITS

_SENSOR_DIMS = ("sensor", "sensor_")
_REFINE = ("spectrum", "distance", None)
_CHUNK_ELEMENTS = 4_000_000  # bootstrap work arrays are capped at this many complex values
# An auto-spectrum below -_AUTO_RTOL times the largest auto-spectrum magnitude of its array is negative
# (refused); above it, round-off of a zero level.
_AUTO_RTOL = 1e-9


def _generator(rng, key: str) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    if isinstance(rng, (numbers.Integral, np.integer)) and not isinstance(rng, (bool, np.bool_)) and rng >= 0:
        return rng_for(int(rng), key)
    raise SpecificationError("rng", rng, "must be a numpy.random.Generator or a non-negative integer seed "
                                         "when n_bootstrap > 0")






# ---------------------------------------------------------------------- minimiser refinement
def _design(x: np.ndarray) -> np.ndarray:
    """Quadratic basis φ(x) = (1, x_a, x_a x_b for a <= b) of points x (n, q) -> (n, p)."""
    q = x.shape[1]
    cols = [np.ones(x.shape[0])] + [x[:, a] for a in range(q)]
    cols += [x[:, a] * x[:, b] for a in range(q) for b in range(a, q)]
    return np.column_stack(cols)


def _design_grad(x: np.ndarray) -> np.ndarray:
    """dφ/dx at one point x (q,) -> (p, q)."""
    q = x.size
    rows = [np.zeros(q)] + [np.eye(q)[a] for a in range(q)]
    for a in range(q):
        for b in range(a, q):
            g = np.zeros(q)
            g[a] += x[b]
            g[b] += x[a]
            rows.append(g)
    return np.array(rows)


def _surrogate_hessian(Q, b, x) -> np.ndarray:
    """Hessian of f(x) = φ(x)ᵀQφ(x) − 2φ(x)ᵀb (φ the quadratic basis)."""
    q = x.size
    ph = _design(x[None])[0]
    J = _design_grad(x)
    r = 2.0 * Q @ ph - 2.0 * b  # ∂f/∂φ
    H = 2.0 * J.T @ Q @ J
    for n, (a, c) in enumerate((a, c) for a in range(q) for c in range(a, q)):  # the x_a x_c columns
        if a == c:
            H[a, a] += 2.0 * r[1 + q + n]  # ∂²(x_a²)/∂x_a² = 2
        else:
            H[a, c] += r[1 + q + n]
            H[c, a] += r[1 + q + n]
    return H


def _minimise_in_box(fun, Q, b, c, lo, hi, iterations: int = 50) -> np.ndarray:
    """Minimiser of the surrogate f over the box [lo, hi] (which contains 0, the grid minimum).

    Damped Newton from 0; if it leaves the box, the best point of a dense grid of the box is
    polished by projected Newton (bounds active where the gradient points outwards are fixed).
    """
    q = lo.size

    def projected_newton(x):
        fx, g = fun(x)
        for _ in range(iterations):
            free = ~(((x <= lo) & (g > 0)) | ((x >= hi) & (g < 0)))
            if not np.any(free):
                break
            H = _surrogate_hessian(Q, b, x)[np.ix_(free, free)]
            step = np.zeros(q)
            try:
                np.linalg.cholesky(H)
                step[free] = -np.linalg.solve(H, g[free])
            except np.linalg.LinAlgError:
                step[free] = -g[free] / max(np.max(np.abs(np.diag(H))), 1e-12)
            t = 1.0
            while t > 1e-8:
                xn = np.clip(x + t * step, lo, hi)
                fn, gn = fun(xn)
                if fn <= fx:
                    break
                t *= 0.5
            else:
                break
            moved = np.max(np.abs(xn - x))
            x, fx, g = xn, fn, gn
            if moved < 1e-12:
                break
        return x, fx

    x, fx = projected_newton(np.zeros(q))
    if np.all((x > lo) & (x < hi)):
        return x  # an interior stationary point reached by Newton from the grid minimum
    n = {1: 201, 2: 41, 3: 13}.get(q, 5)
    pts = np.stack([g.ravel() for g in np.meshgrid(*[np.linspace(l_, h_, n) for l_, h_ in zip(lo, hi)],
                                                   indexing="ij")], axis=-1)
    Phi = _design(pts)
    vals = np.einsum("np,pk,nk->n", Phi, Q, Phi) - 2.0 * Phi @ b + c
    x2, f2 = projected_newton(pts[int(np.argmin(vals))])
    return x2 if f2 < fx else x


def _refine_argmin(axes, D, log: bool, method, S=None, E=None, w=None):
    """Grid minimiser and refined minimiser of D (shape = lengths of ``axes``); see the module docstring.

    ``S`` (*grid, K) model mean spectra flattened per grid point, ``E`` (K,) experimental, ``w`` (K,)
    integration weights (D = Σ_k w_k |S_k − E_k|²), needed by ``method="spectrum"``.
    """
    k = len(axes)
    if not np.any(np.isfinite(D)):
        return np.full(k, np.nan), np.full(k, np.nan)
    i = np.unravel_index(np.nanargmin(D), D.shape)
    discrete = np.array([ax[j] for ax, j in zip(axes, i)], dtype=float)
    refined = discrete.copy()
    fit_dims = [d for d in range(k) if D.shape[d] >= 3]
    if method is None or not fit_dims:
        return discrete, refined
    sl = []
    for d in range(k):
        if d in fit_dims:
            s = int(np.clip(i[d] - 1, 0, D.shape[d] - 3))
            sl.append(slice(s, s + 3))
        else:
            sl.append(slice(i[d], i[d] + 1))
    sl = tuple(sl)
    u_ax = [np.log(a) if log else np.asarray(a, float) for a in axes]
    centre, half, lo, hi = [], [], [], []
    for d in fit_dims:
        wnd = u_ax[d][sl[d]]
        c, h = u_ax[d][i[d]], 0.5 * (wnd[-1] - wnd[0])
        centre.append(c)
        half.append(h)
        lo.append((wnd[0] - c) / h)
        hi.append((wnd[-1] - c) / h)
    grids = np.meshgrid(*[(u_ax[d][sl[d]] - c) / h for d, c, h in zip(fit_dims, centre, half)], indexing="ij")
    x = np.stack([g.ravel() for g in grids], axis=-1)  # (3^q, q), C order = block.reshape order
    Phi = _design(x)
    q = len(fit_dims)
    if method == "distance":
        y = D[sl].reshape(x.shape[0])
        if not np.all(np.isfinite(y)):
            return discrete, refined
        scale = np.max(np.abs(y)) or 1.0
        coef, *_ = np.linalg.lstsq(Phi, y / scale, rcond=None)
        g = coef[1:1 + q]
        H = np.zeros((q, q))
        for (a, b), c in zip([(a, b) for a in range(q) for b in range(a, q)], coef[1 + q:]):
            H[a, b] += c
            H[b, a] += c
        try:
            np.linalg.cholesky(H)
        except np.linalg.LinAlgError:
            return discrete, refined  # the quadratic has no minimum: keep the grid point
        xs = np.clip(np.linalg.solve(H, -g), lo, hi)
    else:  # "spectrum": quadratic surrogate of every spectral value, exact D of the surrogate
        Y = S[sl].reshape(x.shape[0], -1)
        C, *_ = np.linalg.lstsq(Phi, Y, rcond=None)  # (p, K)
        Cw = C * w
        scale = float(np.max(D[sl])) or 1.0
        Q = np.real(Cw @ np.conj(C).T) / scale
        b = np.real(Cw @ np.conj(E)) / scale
        c = float(np.sum(w * np.abs(E) ** 2)) / scale

        def fun(xv):
            ph = _design(xv[None])[0]
            val = ph @ Q @ ph - 2.0 * ph @ b + c
            grad = _design_grad(xv).T @ (2.0 * Q @ ph - 2.0 * b)
            return val, grad

        x0 = np.zeros(q)  # the grid minimum itself
        xs = _minimise_in_box(fun, Q, b, c, np.array(lo), np.array(hi))
        if not (np.all(np.isfinite(xs)) and fun(xs)[0] <= fun(x0)[0]):
            return discrete, refined
    for n, d in enumerate(fit_dims):
        u = centre[n] + half[n] * xs[n]
        refined[d] = math.exp(u) if log else u
    return discrete, refined


# ---------------------------------------------------------------------- validation of the inputs
def _as_psd(da, name: str) -> xr.DataArray:
    if not isinstance(da, xr.DataArray):
        raise SpecificationError(name, _Desc(type(da).__name__), "must be an xarray.DataArray")
    if "frequency" not in da.dims:
        raise SpecificationError(f"{name}.dims", da.dims, "must include 'frequency'")
    if not (np.issubdtype(da.dtype, np.floating) or np.issubdtype(da.dtype, np.complexfloating)):
        raise SpecificationError(f"{name}.dtype", str(da.dtype), "must be real or complex floating point")
    present = [d for d in _SENSOR_DIMS if d in da.dims]
    if len(present) == 1:
        raise SpecificationError(f"{name}.dims", da.dims, "must have both 'sensor' and 'sensor_' or neither")
    return da


def _frequency(da, name) -> np.ndarray:
    if "frequency" not in da.coords:
        raise SpecificationError(f"{name}.frequency", None, "a frequency coordinate (Hz) is required")
    return np.asarray(da["frequency"].values, dtype=float)


def _band_slice(f: np.ndarray, band: float) -> slice:
    """Bins needed to integrate up to ``band``: f <= band plus one bin beyond if band is not a bin."""
    n = int(np.searchsorted(f, band * (1 + 1e-12), side="right"))
    if n < f.size and f[n - 1] < band * (1 - 1e-12):
        n += 1
    return slice(0, n)


def _map_dataset(D, boot, refined, discrete, *, grid_dims, axes, psd_model, confidence, units, long_name,
                 relative, relative_name, attrs) -> xr.Dataset:
    """The Dataset of a trial-grid map: D and its bootstrap (``boot`` = (D per replicate, r_opt per
    replicate) or None), r_opt and its bootstrap statistics, and the map-specific ``attrs``."""
    shape = D.shape
    k = len(grid_dims)
    tail = 50.0 * (1.0 - confidence)
    nan_map = np.full(shape, np.nan)
    D_std = D_low = D_high = nan_map
    r_std = r_low = r_high = [math.nan] * k
    r_corr = np.full((k, k), np.nan).tolist()
    if boot is not None:
        Dbs, rb = boot
        if len(rb) > 1:
            D_std = Dbs.std(axis=0, ddof=1)
            r_std = list(np.std(rb, axis=0, ddof=1))
            with np.errstate(divide="ignore", invalid="ignore"):
                r_corr = np.atleast_2d(np.corrcoef(rb, rowvar=False)).tolist()
        D_low, D_high = np.percentile(Dbs, [tail, 100.0 - tail], axis=0)
        r_low, r_high = (list(v) for v in np.percentile(rb, [tail, 100.0 - tail], axis=0))
    i_min = np.unravel_index(np.argmin(D), shape)
    dims = tuple(grid_dims)
    coords = {d: (d, a, dict(psd_model[d].attrs)) for d, a in zip(grid_dims, axes)}
    ds = xr.Dataset(
        {
            "D": (dims, D, {"long_name": long_name, "units": units}),
            "D_std": (dims, D_std, {"long_name": "bootstrap standard deviation of D", "units": units}),
            "D_low": (dims, D_low, {"long_name": f"bootstrap {100 * confidence:g} % interval of D, low", "units": units}),
            "D_high": (dims, D_high, {"long_name": f"bootstrap {100 * confidence:g} % interval of D, high", "units": units}),
            "D_relative": (dims, relative, {"long_name": relative_name, "units": "1"}),
        },
        coords=coords,
        attrs={
            "grid_dims": list(grid_dims),
            "r_opt": [float(v) for v in refined],
            "r_opt_discrete": [float(v) for v in discrete],
            "r_opt_std": [float(v) for v in r_std],
            "r_opt_low": [float(v) for v in r_low],
            "r_opt_high": [float(v) for v in r_high],
            "r_opt_corr": [[float(v) for v in row] for row in r_corr],
            "r_opt_at_boundary": int(any(j in (0, n - 1) for j, n in zip(i_min, shape))),
            "D_min": float(np.min(D)),
            "D_units": units,
            "confidence": confidence,
            **attrs,
        },
    )
    for n, d in enumerate(grid_dims):
        ds.attrs[f"{d}_opt"] = float(refined[n])
        ds.attrs[f"{d}_opt_std"] = float(r_std[n])
    return ds


def _sampling_attrs(band, N, n_exp, n_bootstrap, exp_extra, held_fixed="") -> dict:
    """The settings every trial-grid map records: band, sample sizes and what its bootstrap resamples."""
    return {"band_hz": band, "n_realisations": int(N), "n_experimental_records": int(max(n_exp, 1)),
            "n_bootstrap": n_bootstrap,
            "bootstrap": "model realisation indices resampled jointly across the grid (common random numbers kept)"
                         + ("; experimental records resampled independently" if exp_extra else
                            "; experimental PSD held fixed") + held_fixed}


def _grid_inputs(psd_model, psd_exp, band_hz, n_bootstrap, rng, dim, fit, confidence, key):
    """Validate the inputs of the trial-grid maps; returns a namespace of arrays and settings."""
    # ---- validation, all up front ----
    psd_model = _as_psd(psd_model, "psd_model")
    psd_exp = _as_psd(psd_exp, "psd_exp")
    if not isinstance(dim, str) or dim not in psd_model.dims:
        raise SpecificationError("dim", dim, f"must be a dimension of psd_model {tuple(psd_model.dims)}")
    if fit not in ("log", "linear"):
        raise SpecificationError("fit", fit, "must be 'log' or 'linear'")
    band = positive("band_hz", band_hz, "Hz")
    n_bootstrap = replicates("n_bootstrap", n_bootstrap)
    confidence = open_unit("confidence", confidence)
    sensor_dims = tuple(d for d in _SENSOR_DIMS if d in psd_model.dims)
    if tuple(d for d in _SENSOR_DIMS if d in psd_exp.dims) != sensor_dims:
        raise SpecificationError("psd_exp.dims", psd_exp.dims,
                                 f"must have the sensor dimensions of psd_model {sensor_dims or '(none)'}")
    grid_dims = [d for d in psd_model.dims if d not in (dim, "frequency") + _SENSOR_DIMS]
    if not grid_dims:
        raise SpecificationError("psd_model.dims", psd_model.dims, f"needs at least one grid dimension besides "
                                 f"{dim!r}, 'frequency' and the sensor dimensions")
    axes = []
    for d in grid_dims:
        if d not in psd_model.coords:
            raise SpecificationError(f"psd_model.{d}", None, "a grid dimension needs a numeric coordinate")
        try:
            a = np.asarray(psd_model[d].values, dtype=float)
        except (TypeError, ValueError):
            raise SpecificationError(f"psd_model.{d}", psd_model[d].values, "must be numeric") from None
        if not np.all(np.isfinite(a)) or (a.size > 1 and np.any(np.diff(a) <= 0)):
            raise SpecificationError(f"psd_model.{d}", _Desc(np.array2string(a, threshold=8)),
                                     "must be finite and strictly increasing")
        if fit == "log" and np.any(a <= 0):
            raise SpecificationError(f"psd_model.{d}", _Desc(np.array2string(a, threshold=8)),
                                     "must be > 0 for fit='log'")
        axes.append(a)
    if math.prod(a.size for a in axes) < 2:
        raise SpecificationError("psd_model", _Desc(f"a grid of 1 point ({', '.join(grid_dims)})"),
                                 "needs at least 2 grid points (an axis with 2 or more values): an optimum over a "
                                 "one-point grid is that point, not an identification")
    exp_extra = [d for d in psd_exp.dims if d not in ("frequency",) + _SENSOR_DIMS]
    if len(exp_extra) > 1:
        raise SpecificationError("psd_exp.dims", psd_exp.dims,
                                 "may have at most one dimension besides frequency and sensors (independent records)")
    f = _frequency(psd_model, "psd_model")
    fe = _frequency(psd_exp, "psd_exp")
    if f.shape != fe.shape or not np.allclose(f, fe, rtol=1e-9, atol=1e-12):
        raise SpecificationError("psd_exp.frequency", _Desc(f"{fe.size} bins"),
                                 f"must equal psd_model's frequency grid ({f.size} bins, 0..{f[-1]:g} Hz)")
    for d in sensor_dims:
        if d in psd_model.coords and d in psd_exp.coords and \
                list(psd_model[d].values) != list(psd_exp[d].values):
            raise SpecificationError(f"psd_exp.{d}", list(psd_exp[d].values),
                                     f"must equal psd_model's {psd_model[d].values.tolist()}")
        if psd_model.sizes[d] != psd_exp.sizes[d]:
            raise SpecificationError(f"psd_exp.{d}", psd_exp.sizes[d], f"must have {psd_model.sizes[d]} entries")
    N = psd_model.sizes[dim]
    if N < 1 or (n_bootstrap > 0 and N < 2):
        raise SpecificationError(dim, N, "need at least 2 model realisations for the bootstrap (1 without)")
    sl = _band_slice(f, band)
    # distance_map's distance() checks the grid (starts at 0 Hz, increasing, reaches the band);
    # log_band_distance_map checks it itself
    P = psd_model.transpose(*grid_dims, dim, "frequency", *sensor_dims).isel(frequency=sl).values
    E = psd_exp.transpose(*exp_extra, "frequency", *sensor_dims).isel(frequency=sl).values
    if not np.all(np.isfinite(P)):
        raise SpecificationError("psd_model", _Desc(f"{int(np.sum(~np.isfinite(P)))} non-finite values in the band"),
                                 "must be finite (drop incomplete realisations first)")
    if not np.all(np.isfinite(E)):
        raise SpecificationError("psd_exp", _Desc(f"{int(np.sum(~np.isfinite(E)))} non-finite values in the band"),
                                 "must be finite")
    # an auto-PSD is >= 0. Judged on the spectra every distance compares: the model's mean over realisations
    # S̄ at each grid point, and the experimental PSD (its mean over records when it has them)
    for name, arr, what in (("psd_model", P.mean(axis=len(grid_dims)), f"mean over {dim!r} of the "),
                            ("psd_exp", E.mean(axis=0) if exp_extra else E,
                             f"mean over {exp_extra[0]!r} of the " if exp_extra else "")):
        auto = np.real(np.diagonal(arr, axis1=-2, axis2=-1)) if sensor_dims else np.real(arr)
        low = auto < -_AUTO_RTOL * np.max(np.abs(auto), initial=0.0)
        if np.any(low):
            raise SpecificationError(name, _Desc(f"{int(np.sum(low))} negative auto-spectrum values in the band "
                                                 f"(smallest {float(np.min(auto)):.3g})"),
                                     f"the {what}auto-spectra ("
                                     + ("real part of the diagonal" if sensor_dims else "every value")
                                     + ") must be >= 0: a PSD S_aa(f) is never negative")
    gen = _generator(rng, key) if n_bootstrap > 0 else None
    return dict(psd_model=psd_model, grid_dims=grid_dims, axes=axes, sensor_dims=sensor_dims, exp_extra=exp_extra,
                f=f, band=band, n_bootstrap=n_bootstrap, confidence=confidence, N=N, gen=gen, sl=sl, P=P, E=E)


def distance_map(psd_model: xr.DataArray, psd_exp: xr.DataArray, band_hz: float = 100.0, n_bootstrap: int = 200,
                 rng: np.random.Generator | int | None = None, *, dim: str = "realisation",
                 confidence: float = 0.95, fit: str = "log", refine: str | None = "spectrum",
                 weight: xr.DataArray | None = None) -> xr.Dataset:
    """D(r) = ∫_B ‖S̄(ω, r) − S_exp(ω)‖²_F dω on a parameter grid, its minimiser and their bootstrap.

    ``psd_model``: DataArray with dims (*grid, ``dim``, "frequency"[, "sensor", "sensor_"]) in any
    order, two-sided per Hz (complex, or real for auto-spectra); every other dimension is a grid
    axis and needs a strictly increasing numeric coordinate (positive for ``fit="log"``), e.g.
    r1 [N²/Hz] and r2 [(N·m)²/Hz]. Realisation k should use the same random germs at every grid
    point (common random numbers). ``psd_exp``: DataArray ("frequency"[, "sensor", "sensor_"]) on the
    same frequencies (Hz, from 0) and sensors; one extra dimension is taken as independent
    experimental records: they are averaged, and resampled in the bootstrap. ``band_hz``: B =
    2π[−band, band] rad/s. ``rng``: Generator or seed, required if ``n_bootstrap > 0``. ``fit``,
    ``refine``: refinement of the minimiser (module docstring). ``weight``: None (the paper's D) or
    a fixed DataArray W over ("frequency"[, "sensor", "sensor_"]) (e.g. :func:`relative_weight`):
    D_W = ∫_B ‖W ⊙ (S̄ − S_exp)‖²_F dω.

    Returns a Dataset on the grid: ``D`` (units of the PSD squared × rad/s, e.g. (m²/Hz)²·rad/s;
    with a weight, the ``distance_units`` attribute of W, else "([W][S])^2 rad/s"), bootstrap
    ``D_std``, ``D_low``, ``D_high`` (percentile interval of probability ``confidence``), and
    ``D_relative`` = D / J_s,exp (J_s of the (weighted) experimental PSD; dimensionless).
    Attributes: ``grid_dims``; ``r_opt`` (refined minimiser), ``r_opt_discrete`` (grid minimiser),
    bootstrap ``r_opt_std``, ``r_opt_low``, ``r_opt_high`` (lists in ``grid_dims`` order, refined
    minimiser per replicate) and ``r_opt_corr`` (their correlation matrix, list of lists),
    ``r_opt_at_boundary`` (1 if the grid minimum lies on the grid's edge: widen the grid),
    per-axis copies ``<dim>_opt`` and ``<dim>_opt_std``, ``D_min``, ``J_s_exp`` and the settings.
    The bootstrap covers the Monte Carlo error of the model realisations and, when given as
    records, of the experimental PSD.

    Parameters
    ----------
    psd_model : xarray.DataArray
        Model PSDs (*grid, ``dim``, "frequency"[, "sensor", "sensor_"]) [m²/Hz], as above. Their mean
        over ``dim`` must have auto-spectra >= 0 in the band (every value of a scalar PSD, the real
        part of the diagonal of a matrix one; -1e-9 of the largest is taken as round-off).
    psd_exp : xarray.DataArray
        Experimental PSD ("frequency"[, "sensor", "sensor_"]) [m²/Hz], optionally with one records
        dimension; its auto-spectra (averaged over the records) >= 0 in the band likewise.
    band_hz : float
        B = 2π[−band, band] rad/s [Hz].
    n_bootstrap : int
        Bootstrap replicates (0: none).
    rng : numpy.random.Generator or int, optional
        Stream or seed of the bootstrap; required when ``n_bootstrap > 0``.
    dim : str
        The realisation dimension of ``psd_model``.
    confidence : float
        Probability of the bootstrap percentile intervals, in (0, 1).
    fit : str
        Axis scale of the refinement (module docstring).
    refine : str or None
        Refinement method of the minimiser (module docstring); None: the grid minimiser.
    weight : xarray.DataArray, optional
        A fixed W over ("frequency"[, "sensor", "sensor_"]), e.g. :func:`relative_weight`.

    Returns
    -------
    xarray.Dataset
        ``D``, ``D_std``, ``D_low``, ``D_high``, ``D_relative`` on the grid and the attributes
        listed above.
    """
    # ---- validation, all up front ----
    if refine not in _REFINE:
        raise SpecificationError("refine", refine, f"must be one of {_REFINE}")
    g_ = _grid_inputs(psd_model, psd_exp, band_hz, n_bootstrap, rng, dim, fit, confidence, "distance_map")
    psd_model, grid_dims, axes, sensor_dims, exp_extra, f, band, n_bootstrap, confidence, N, gen, sl, P, E = (
        g_[k] for k in ("psd_model", "grid_dims", "axes", "sensor_dims", "exp_extra", "f", "band", "n_bootstrap",
                        "confidence", "N", "gen", "sl", "P", "E"))
    if weight is not None:
        if not isinstance(weight, xr.DataArray) or not set(weight.dims) <= {"frequency", *sensor_dims} \
                or "frequency" not in weight.dims:
            raise SpecificationError("weight", _Desc(type(weight).__name__ if not isinstance(weight, xr.DataArray)
                                                     else f"DataArray{tuple(weight.dims)}"),
                                     f"must be None or a DataArray over ('frequency'{''.join(', ' + repr(d) for d in sensor_dims)})")
        fw = _frequency(weight, "weight")
        if fw.shape != f.shape or not np.allclose(fw, f, rtol=1e-9, atol=1e-12):
            raise SpecificationError("weight.frequency", _Desc(f"{fw.size} bins"), "must equal psd_model's frequency grid")
        wv = weight.transpose("frequency", *[d for d in sensor_dims if d in weight.dims]).values
        if np.iscomplexobj(wv) or not np.all(np.isfinite(wv)) or np.any(wv < 0):
            raise SpecificationError("weight", _Desc("values"), "must be real, finite and >= 0")
    if weight is not None:  # the weight multiplies S̄ − S_exp, hence (linearly) both spectra
        Wt = weight.transpose("frequency", *[d for d in sensor_dims if d in weight.dims])
        Wt = Wt.expand_dims({d: psd_model.sizes[d] for d in sensor_dims if d not in Wt.dims}).transpose(
            "frequency", *sensor_dims)
        Wv = np.asarray(Wt.isel(frequency=sl).values, dtype=float)
        P, E = P * Wv, E * Wv
    if not sensor_dims:  # scalar PSD: a 1 × 1 matrix per bin (keeps the spectral functionals unambiguous)
        P, E = P[..., None, None], E[..., None, None]
    fb = f[sl]

    # ---- estimate ----
    shape = tuple(a.size for a in axes)
    E_mean = E.mean(axis=0) if exp_extra else E
    S_bar = P.mean(axis=len(grid_dims))
    D = distance(fb, S_bar, E_mean, band)
    js_exp = float(j_s(fb, E_mean, band))
    log = fit == "log"
    F_b = fb.size
    msq = int(np.prod(E_mean.shape[1:]))
    w_bin = j_s(fb, np.sqrt(np.eye(F_b)), band)  # D = Σ_k w_k |ΔS_k|²: the integration weights
    w = np.repeat(w_bin, msq)

    def refine_one(Dmap, Smap, Evec):
        return _refine_argmin(axes, Dmap, log, refine, Smap.reshape(shape + (-1,)), Evec.reshape(-1), w)

    discrete, refined = refine_one(D, S_bar, E_mean)

    # ---- bootstrap: one realisation index set per replicate for the whole grid ----
    G = int(np.prod(shape))
    K = int(np.prod(P.shape[len(grid_dims) + 1:]))  # frequency × sensors
    Pm = np.moveaxis(P.reshape(G, N, K), 1, 0).reshape(N, G * K)  # (N, G·K)
    n_exp = E.shape[0] if exp_extra else 0
    Ef = E.reshape((n_exp, -1)) if exp_extra else None
    boot = None
    if n_bootstrap > 0:
        chunk = max(1, _CHUNK_ELEMENTS // (G * K))
        D_boot, r_boot = [], []
        for start in range(0, n_bootstrap, chunk):
            b = min(chunk, n_bootstrap - start)
            idx = gen.integers(0, N, size=(b, N))
            W = np.zeros((b, N))
            np.add.at(W, (np.repeat(np.arange(b), N), idx.ravel()), 1.0 / N)
            Sb = (W @ Pm).reshape((b,) + shape + P.shape[len(grid_dims) + 1:])
            if exp_extra:
                je = gen.integers(0, n_exp, size=(b, n_exp))
                We = np.zeros((b, n_exp))
                np.add.at(We, (np.repeat(np.arange(b), n_exp), je.ravel()), 1.0 / n_exp)
                Eb = (We @ Ef).reshape((b,) + (1,) * len(shape) + E_mean.shape)
            else:
                Eb = E_mean
            Db = distance(fb, Sb, Eb, band)  # (b, *grid)
            D_boot.append(Db)
            Eb_full = np.broadcast_to(Eb, (b,) + (1,) * len(shape) + E_mean.shape)
            r_boot.extend(refine_one(Db[j], Sb[j], Eb_full[j])[1] for j in range(b))
        boot = (np.concatenate(D_boot), np.asarray(r_boot))

    units = psd_model.attrs.get("units")
    d_units = D_UNITS if units in (None, "m^2/Hz") else f"({units})^2 rad/s"
    if weight is not None:
        d_units = weight.attrs.get("distance_units", "([W][S])^2 rad/s")
    return _map_dataset(
        D, boot, refined, discrete, grid_dims=grid_dims, axes=axes, psd_model=psd_model, confidence=confidence,
        units=d_units, long_name="D(r) = integral over B of ||mean S_model(w, r) - S_exp(w)||_F^2 dw",
        relative=D / js_exp if js_exp > 0 else np.full(shape, np.nan), relative_name="D / J_s,exp",
        attrs={
            "r_opt_method": {"spectrum": f"quadratic surrogate in {'log r' if log else 'r'} of the mean model "
                                         "spectrum on the 3^k grid points around the grid minimum, its distance "
                                         "minimised within them",
                             "distance": f"least-squares quadratic of D in {'log r' if log else 'r'} on the 3^k "
                                         "grid points around the grid minimum, stationary point clipped to them",
                             None: "grid minimum"}[refine],
            "weight": "none (paper's D)" if weight is None else str(weight.attrs.get("long_name", "given")),
            "J_s_exp": js_exp,
            **_sampling_attrs(band, N, n_exp, n_bootstrap, exp_extra),
        })


def relative_weight(psd: xr.DataArray) -> xr.DataArray:
    """W_ab(f) = 1/√(S_aa(f) S_bb(f)) from a reference PSD [1/(m²/Hz)].

    With it, D_W compares the spectra relative to their own level (cross-spectra as coherencies).
    Use a *model* PSD from realisations independent of the grid's (e.g. a separate run of the mean
    model at the grid centre), not the experimental one (module docstring).

    Parameters
    ----------
    psd : xarray.DataArray
        The reference PSD ("frequency"[, "sensor", "sensor_"]) [m²/Hz], finite.

    Returns
    -------
    xarray.DataArray
        W on the same dims; 0 where an auto-spectrum is not positive; attribute
        ``distance_units`` = "rad/s" (the units of D_W).
    """
    psd = _as_psd(psd, "psd")
    extra = [d for d in psd.dims if d not in ("frequency",) + _SENSOR_DIMS]
    if extra:
        raise SpecificationError("psd.dims", psd.dims, "must be ('frequency'[, 'sensor', 'sensor_']); average first")
    if "sensor" in psd.dims:
        a = np.real(np.diagonal(psd.transpose("frequency", "sensor", "sensor_").values, axis1=1, axis2=2))
        prod = a[:, :, None] * a[:, None, :]
    else:
        prod = np.real(psd.values) ** 2
    if not np.all(np.isfinite(prod)):
        raise SpecificationError("psd", _Desc("values"), "must be finite")
    with np.errstate(divide="ignore"):
        W = np.where(prod > 0, 1.0 / np.sqrt(np.where(prod > 0, prod, 1.0)), 0.0)
    dims = ("frequency",) + tuple(d for d in _SENSOR_DIMS if d in psd.dims)
    coords = {d: psd[d] for d in dims if d in psd.coords}
    units = psd.attrs.get("units", "m^2/Hz")
    return xr.DataArray(W, dims=dims, coords=coords, name="weight",
                        attrs={"units": f"1/({units})", "distance_units": "rad/s",
                               "long_name": "relative weight 1/sqrt(S_aa S_bb) of a reference PSD"})


def log_band_distance_map(psd_model: xr.DataArray, psd_exp: xr.DataArray, band_hz: float = 100.0,
                          band_width_hz: float = 5.0, n_bootstrap: int = 200,
                          rng: np.random.Generator | int | None = None, *, dim: str = "realisation",
                          confidence: float = 0.95, refine: bool = True) -> xr.Dataset:
    """Trial-grid identification by a weighted least-squares distance of log band energies (beyond the paper).

    For each auto-spectrum a (sensor) and frequency band b = (k w, (k + 1) w] ⊂ (0, band] (w =
    ``band_width_hz``), the band energy e = Σ_b S_aa Δf [m²] of each model realisation and of each
    experimental record is taken in log. With L̄(r) the mean over realisations at grid point r, L̄_exp
    the mean over records and σ²_ab the variance of one realisation's log energy (model, pooled over
    the grid points),

        D(r) = Σ_ab (L̄_ab(r) − L̄_exp,ab)² / (σ²_ab (1/N + 1/n_exp)),

    the generalised least squares of the band levels: each band counts by its own precision, so the
    bands where r shows (e.g. antisymmetric modes for a moment) are not drowned by the first resonance
    peaks or by bands that fluctuate from one random system to the next, as with the paper's D.
    ``D_relative`` = D / (B·m): the mean squared standardised residual (about 1 near r_opt when the
    experiment is a draw of the model class, plus the grid's discreteness; much larger: the model
    does not explain the experiment). The variance comes from the model, never from the experiment
    (a single record gives none; the experiment is assumed a draw
    of the model class). Inputs, bootstrap (realisations resampled jointly across the grid, records
    independently) and the returned Dataset are those of :func:`distance_map` (``D`` dimensionless);
    the refinement is its ``"spectrum"`` method applied to the log band energies, in log r. The
    comparison assumes each record is estimated like one model realisation (same record length and
    PSD estimator), so that both have the same log-level variance.

    Parameters
    ----------
    psd_model : xarray.DataArray
        Model PSDs (*grid, ``dim``, "frequency"[, "sensor", "sensor_"]) [m²/Hz], as for
        :func:`distance_map`; grid coordinates positive.
    psd_exp : xarray.DataArray
        Experimental PSD ("frequency"[, "sensor", "sensor_"]), optionally with a records dimension.
    band_hz : float
        Upper end of the band [Hz].
    band_width_hz : float
        Width w of the bands [Hz].
    n_bootstrap : int
        Bootstrap replicates (0: none).
    rng : numpy.random.Generator or int, optional
        Stream or seed of the bootstrap; required when ``n_bootstrap > 0``.
    dim : str
        The realisation dimension of ``psd_model``.
    confidence : float
        Probability of the bootstrap percentile intervals, in (0, 1).
    refine : bool
        Refine the grid minimiser (``"spectrum"`` method on the log band energies, in log r).

    Returns
    -------
    xarray.Dataset
        As :func:`distance_map` (``D`` dimensionless, ``D_relative`` the mean squared standardised
        residual).
    """
    if not isinstance(refine, (bool, np.bool_)):
        raise SpecificationError("refine", refine, "must be True or False")
    width = real("band_width_hz", band_width_hz, unit="Hz")
    g_ = _grid_inputs(psd_model, psd_exp, band_hz, n_bootstrap, rng, dim, "log", confidence, "log_band_distance_map")
    grid_dims, axes, sensor_dims, exp_extra, f, band, N, gen = (
        g_[k] for k in ("grid_dims", "axes", "sensor_dims", "exp_extra", "f", "band", "N", "gen"))
    n_bootstrap, confidence, P, E = g_["n_bootstrap"], g_["confidence"], g_["P"], g_["E"]
    fb = f[g_["sl"]]
    if fb.size < 2 or fb[0] != 0.0 or not np.allclose(np.diff(fb), fb[1] - fb[0], rtol=1e-6, atol=0.0) \
            or fb[-1] < band * (1 - 1e-12):
        raise SpecificationError("psd_model.frequency", _Desc(f"{f.size} bins, {f[0]:g}..{f[-1]:g} Hz"),
                                 f"must be a uniform grid from 0 Hz reaching the band {band:g} Hz (at least 2 bins)")
    df = float(fb[1] - fb[0])
    if not (math.isfinite(width) and width > 0) or width < df or width > band:
        raise SpecificationError("band_width_hz", band_width_hz, f"must lie between the bin width {df:g} Hz and the band {band:g} Hz")
    if N < 2:
        raise SpecificationError(dim, N, "needs at least 2 model realisations (the variance of the band levels)")
    if not sensor_dims:
        P, E = P[..., None, None], E[..., None, None]
    n_bands = int(math.floor(band / width + 1e-9))
    edges = width * np.arange(n_bands + 1)
    Lm = log_band_energies(P, fb, edges)  # (*grid, N, K)
    Le = log_band_energies(E, fb, edges)  # ([n_exp,] K)
    if not (np.all(np.isfinite(Lm)) and np.all(np.isfinite(Le))):
        raise SpecificationError("psd", _Desc("band energies"), f"every band of width {width:g} Hz must hold energy > 0 "
                                 "in every realisation and record (widen the bands or drop empty channels)")
    n_exp = Le.shape[0] if exp_extra else 1
    Le_mean = Le.mean(axis=0) if exp_extra else Le
    gax = len(grid_dims)
    Lbar = Lm.mean(axis=gax)  # (*grid, K)
    # variance of one realisation's log band level, pooled over the grid (G (N − 1) degrees of freedom
    # instead of N − 1 at one point: weights from a handful of realisations would let a band that looks
    # quiet by chance decide r_opt)
    var = Lm.var(axis=gax, ddof=1).reshape(-1, Lm.shape[-1]).mean(axis=0)
    var = np.maximum(var, 1e-12 * max(float(np.max(var)), 1e-300))
    w = 1.0 / (var * (1.0 / N + 1.0 / n_exp))

    def dmap(Lb, Le_):
        return np.sum(w * (Lb - Le_) ** 2, axis=-1)

    def argmin(Dm, Lb, Le_):
        return _refine_argmin(axes, Dm, True, "spectrum" if refine else None, Lb, Le_, w)

    D = dmap(Lbar, Le_mean)
    discrete, refined = argmin(D, Lbar, Le_mean)
    boot = None
    if n_bootstrap > 0:
        D_boot, r_boot = [], []
        for _ in range(n_bootstrap):
            idx = gen.integers(0, N, size=N)
            Lb = np.take(Lm, idx, axis=gax).mean(axis=gax)
            Le_b = Le[gen.integers(0, n_exp, size=n_exp)].mean(axis=0) if exp_extra else Le_mean
            Db = dmap(Lb, Le_b)
            D_boot.append(Db)
            r_boot.append(argmin(Db, Lb, Le_b)[1])
        boot = (np.asarray(D_boot), np.asarray(r_boot))
    K = w.size
    return _map_dataset(
        D, boot, refined, discrete, grid_dims=grid_dims, axes=axes, psd_model=g_["psd_model"], confidence=confidence,
        units="1", long_name="D(r) = sum over bands and sensors of (mean log band energy, model - experiment)^2 / its variance",
        relative=D / K, relative_name="D / number of band levels (mean squared standardised residual)",
        attrs={
            "r_opt_method": ("quadratic surrogate in log r of every mean log band energy on the 3^k grid points around "
                             "the grid minimum, its distance minimised within them" if refine else "grid minimum"),
            "weight": "log band energies, inverse model variance (generalised least squares)",
            "band_width_hz": width,
            "n_bands": n_bands,
            "n_levels": int(K),
            **_sampling_attrs(band, N, n_exp, n_bootstrap, exp_extra, "; the band variances held fixed"),
        })


def log_spectral_distance_map(psd_model: xr.DataArray, psd_exp: xr.DataArray, band_hz: float = 100.0,
                              n_bootstrap: int = 200, rng: np.random.Generator | int | None = None, *,
                              dim: str = "realisation", confidence: float = 0.95, refine: bool = True) -> xr.Dataset:
    """Trial-grid identification by the mean squared log10 ratio of the auto-spectra (beyond the paper).

    D(r) = (1/K) Σ_{a, 0 < f ≤ band} (log10 S̄_aa(f, r) − log10 S_exp,aa(f))²  [decades²],

    with S̄ the mean over realisations at grid point r, S_exp the mean over experimental records, a
    the auto-spectra (sensors) and K the number of (sensor, bin) terms; the DC bin is left out. Every
    decade of level counts alike at every frequency, so the minimiser follows the broadband level
    rather than the resonance peaks. Inputs, bootstrap and the returned Dataset are those of
    :func:`distance_map` (``D`` in decades², ``D_relative`` = D); the refinement is its
    ``"spectrum"`` method applied to the log10 mean spectra, in log r. Every auto-spectrum must be
    > 0 in every bin used.

    Parameters
    ----------
    psd_model : xarray.DataArray
        Model PSDs (*grid, ``dim``, "frequency"[, "sensor", "sensor_"]) [m²/Hz], as for
        :func:`distance_map`; grid coordinates strictly increasing and positive.
    psd_exp : xarray.DataArray
        Experimental PSD ("frequency"[, "sensor", "sensor_"]) on the same bins and sensors; one extra
        dimension is taken as independent records (averaged, resampled in the bootstrap).
    band_hz : float
        Upper end of the band [Hz].
    n_bootstrap : int
        Bootstrap replicates (0: none).
    rng : numpy.random.Generator or int, optional
        Stream or seed of the bootstrap; required when ``n_bootstrap > 0``.
    dim : str
        The realisation dimension of ``psd_model``.
    confidence : float
        Probability of the bootstrap percentile intervals, in (0, 1).
    refine : bool
        Refine the grid minimiser (the ``"spectrum"`` method on log10 spectra, in log r).

    Returns
    -------
    xarray.Dataset
        As :func:`distance_map`: ``D`` [decades²], ``D_relative`` (= D), bootstrap ``D_std``,
        ``D_low``, ``D_high``; attributes ``r_opt``, ``r_opt_discrete``, ``r_opt_std``,
        ``r_opt_at_boundary``, ``D_min`` and the settings.
    """
    if not isinstance(refine, (bool, np.bool_)):
        raise SpecificationError("refine", refine, "must be True or False")
    g_ = _grid_inputs(psd_model, psd_exp, band_hz, n_bootstrap, rng, dim, "log", confidence, "log_spectral_distance_map")
    grid_dims, axes, sensor_dims, exp_extra, f, band, N, gen = (
        g_[k] for k in ("grid_dims", "axes", "sensor_dims", "exp_extra", "f", "band", "N", "gen"))
    n_bootstrap, confidence, P, E = g_["n_bootstrap"], g_["confidence"], g_["P"], g_["E"]
    fb = f[g_["sl"]]
    if fb[-1] < band * (1 - 1e-12):  # as the other distances: a band beyond the spectra is not shortened silently
        raise SpecificationError("psd_model.frequency", _Desc(f"{f.size} bins, {f[0]:g}..{f[-1]:g} Hz"),
                                 f"must reach the band {band:g} Hz (band_hz = {band_hz!r})")
    keep = (fb > 0) & (fb <= band * (1 + 1e-12))
    if not np.any(keep):
        raise SpecificationError("psd_model.frequency", _Desc(f"{f.size} bins"), f"must hold bins in (0, {band:g}] Hz")
    if sensor_dims:
        P, E = np.real(np.diagonal(P, axis1=-2, axis2=-1)), np.real(np.diagonal(E, axis1=-2, axis2=-1))
    else:
        P, E = np.real(P)[..., None], np.real(E)[..., None]
    P, E = P[..., keep, :], E[..., keep, :]  # (*grid, N, F', m), ([n_exp,] F', m)
    gax = len(grid_dims)
    P = P.reshape(P.shape[:gax + 1] + (-1,))  # (*grid, N, K)
    E = E.reshape(E.shape[:-2] + (-1,))
    if np.any(P.mean(axis=gax) <= 0) or np.any(E <= 0):
        raise SpecificationError("psd", _Desc("auto-spectra"), f"must be > 0 in every bin of (0, {band:g}] Hz "
                                 "(a log distance needs positive levels)")
    n_exp = E.shape[0] if exp_extra else 1
    Le = np.log10(E.mean(axis=0) if exp_extra else E)
    Lbar = np.log10(P.mean(axis=gax))
    K = Lbar.shape[-1]
    w = np.full(K, 1.0 / K)

    def argmin(Dm, Lb, Le_):
        return _refine_argmin(axes, Dm, True, "spectrum" if refine else None, Lb, Le_, w)

    D = np.sum(w * (Lbar - Le) ** 2, axis=-1)
    discrete, refined = argmin(D, Lbar, Le)
    boot = None
    if n_bootstrap > 0:
        D_boot, r_boot = [], []
        for _ in range(n_bootstrap):
            idx = gen.integers(0, N, size=N)
            with np.errstate(divide="ignore"):
                Lb = np.log10(np.take(P, idx, axis=gax).mean(axis=gax))
            Le_b = np.log10(E[gen.integers(0, n_exp, size=n_exp)].mean(axis=0)) if exp_extra else Le
            Db = np.sum(w * (Lb - Le_b) ** 2, axis=-1)
            D_boot.append(Db)
            r_boot.append(argmin(Db, Lb, Le_b)[1])
        boot = (np.asarray(D_boot), np.asarray(r_boot))
    return _map_dataset(
        D, boot, refined, discrete, grid_dims=grid_dims, axes=axes, psd_model=g_["psd_model"], confidence=confidence,
        units="decades^2", long_name="D(r) = mean over sensors and 0 < f <= band of (log10 mean S_model(f, r) - log10 S_exp(f))^2",
        relative=D, relative_name="D (already relative: mean squared log10 ratio)",
        attrs={
            "r_opt_method": ("quadratic surrogate in log r of every log10 mean spectral value on the 3^k grid points "
                             "around the grid minimum, its distance minimised within them" if refine else "grid minimum"),
            "weight": "log10 auto-spectra, every (sensor, bin) alike",
            "n_levels": int(K),
            **_sampling_attrs(band, N, n_exp, n_bootstrap, exp_extra),
        })


def refine_grid(r_opt: dict[str, float] | ArrayLike, factor: float,
                n: int) -> dict[str, np.ndarray] | tuple[np.ndarray, ...]:
    """A finer ratio grid around ``r_opt`` for a second trial pass.

    For each component r: ``n`` values geometrically spaced from r/factor to r·factor (so r itself
    is a grid point when n is odd).

    Parameters
    ----------
    r_opt : dict of str to float, or array_like
        The centre: a mapping {dim: value} or a sequence of values; values > 0.
    factor : float
        > 1: the half-width as a ratio. Choose it a little wider than the bootstrap spread of
        r_opt (e.g. exp(3·std/r)).
    n : int
        Values per component, ≥ 2.

    Returns
    -------
    dict of str to numpy.ndarray, or tuple of numpy.ndarray
        {dim: values} for a mapping, else one array per component.
    """
    fac = real("factor", factor, low=1.0, low_open=True)
    n = integer("n", n, minimum=2)
    as_map = isinstance(r_opt, dict)
    items = list(r_opt.items()) if as_map else list(enumerate(r_opt if isinstance(r_opt, (list, tuple))
                                                              else np.atleast_1d(r_opt)))
    if not items:
        raise SpecificationError("r_opt", r_opt, "must hold at least one value")
    out = []
    for key, v in items:
        v = positive(f"r_opt[{key!r}]", v)
        out.append((key, v * np.exp(np.linspace(-math.log(fac), math.log(fac), n))))
    return {k: a for k, a in out} if as_map else tuple(a for _, a in out)


def delta_f_likelihood(j_s_samples: xr.DataArray | ArrayLike, j_s_exp: float | ArrayLike,
                       grid: ArrayLike | None = None, *, n_bootstrap: int = 200,
                       rng: np.random.Generator | int | None = None,
                       confidence: float = 0.95, m: int = 2, grid_name: str = "delta_F",
                       units: str = JS_UNITS, observable: str = "J_s", variance_corrected: bool = False) -> xr.Dataset:
    """δ_F ↦ p̂_Js(J_s,exp; δ_F) and δ_F,opt (paper Eq. 5) from Monte Carlo samples of J_s.

    The same likelihood serves another scalar observable of the load's randomness (``observable``,
    e.g. ``"level_difference"``: the log-level difference of two records of one structure, whose
    spread the random B does not reach); its samples and observations then replace J_s's.

    ``j_s_samples``: (delta_F, realisation) values of J_s = ∫_B ‖S_Z(ω)‖²_F dω [``units``], a
    DataArray (its ``grid_name`` coordinate is the grid) or an array with ``grid`` given; common
    random numbers across the grid are expected. ``j_s_exp``: the observed J_s (or several
    independent observations: joint likelihood). Every grid value must lie in the admissible set
    (0, δ_max(m)) of SG+ with m loads (m = 2: √(3/7)). Wraps :func:`likelihood_curve` (Gaussian
    KDE, Silverman bandwidth, bootstrap over realisations jointly across the grid) and adds
    ``delta_F_opt``, ``delta_F_opt_std``, ``delta_F_opt_low``, ``delta_F_opt_high``, ``J_s_exp``,
    ``J_s_units``, and the samples as ``J_s``.

    Parameters
    ----------
    j_s_samples : xarray.DataArray or array_like
        (delta_F, realisation) Monte Carlo values of J_s [``units``].
    j_s_exp : float or array_like
        The observed J_s, or several independent observations.
    grid : array_like, optional
        The δ_F grid (required unless ``j_s_samples`` carries it as a coordinate). When both are
        there the grid must equal the coordinate (the rows are matched to the grid by it, in any
        order; see :func:`likelihood_curve`).
    n_bootstrap : int
        Bootstrap replicates (0: none).
    rng : numpy.random.Generator or int, optional
        Stream or seed of the bootstrap; required when ``n_bootstrap > 0``.
    confidence : float
        Probability of the bootstrap percentile intervals, in (0, 1).
    m : int
        Number of loads (the size of the SG+ matrix whose δ_max bounds the grid).
    grid_name : str
        Name of the grid dimension.
    units : str
        Units of J_s (of the observable).
    observable : str
        Name of the observable: the samples' variable and the ``<observable>_exp`` attribute; not
        one of the result's own variables (``likelihood``, ``log_likelihood``, ...) or coordinates.
    variance_corrected : bool
        :func:`likelihood_curve`'s variance-corrected kernel (for an observable whose spread δ_F
        sets, such as the level difference of record pairs).

    Returns
    -------
    xarray.Dataset
        :func:`~tubeid.identification.likelihood_curve`'s Dataset plus the attributes and ``J_s``
        listed above.
    """
    m = integer("m", m, minimum=1)
    own = ("likelihood", "log_likelihood", "bandwidth", "likelihood_std", "likelihood_low", "likelihood_high",
           grid_name, "realisation")
    if not isinstance(observable, str) or not observable or observable in own:
        raise SpecificationError("observable", observable, "must be a non-empty name other than the result's own "
                                 f"variables and coordinates {list(own)}")
    if isinstance(j_s_samples, xr.DataArray):
        if grid_name not in j_s_samples.dims or j_s_samples.ndim != 2:
            raise SpecificationError("j_s_samples.dims", j_s_samples.dims,
                                     f"must be ({grid_name!r}, realisation)")
        da = j_s_samples.transpose(grid_name, ...)
        if grid is None:
            if grid_name not in da.coords:
                raise SpecificationError(f"j_s_samples.{grid_name}", None, "needs a coordinate (or pass grid)")
            grid = np.sort(np.asarray(da[grid_name].values))  # the rows are matched to it below
        samples = da
    else:
        if grid is None:
            raise SpecificationError("grid", None, "is required when j_s_samples is not a DataArray with a "
                                                   f"{grid_name!r} coordinate")
        samples = j_s_samples
    g = np.atleast_1d(numeric_array("grid", grid, finite=False, dtype=float))  # bools, strings, complex refused
    dmax = delta_max(m)
    if g.ndim != 1 or not np.all(np.isfinite(g)) or np.any(g <= 0) or np.any(g >= dmax):
        raise SpecificationError(grid_name, _Desc(np.array2string(g, threshold=8)),
                                 f"must lie in the admissible set (0, {dmax:.4f}) of SG+ with m = {m}")
    if isinstance(samples, xr.DataArray):  # its rows matched to the grid by its coordinate (refused if they differ)
        if g.size > 1 and not np.all(np.diff(g) > 0):
            raise SpecificationError("grid", _Desc(np.array2string(g, threshold=8)), "must be strictly increasing")
        samples = _aligned(samples, g, grid_name, "j_s_samples").values
    ds = likelihood_curve(samples, j_s_exp, g, grid_name, n_bootstrap=n_bootstrap, rng=rng,
                          confidence=confidence, variance_corrected=variance_corrected)
    long_name = "J_s = integral over B of ||S_Z(w)||_F^2 dw" if observable == "J_s" else observable
    ds[observable] = ((grid_name, "realisation"), np.asarray(samples, dtype=float), {"units": units, "long_name": long_name})
    ds.attrs.update({
        "delta_F_opt": ds.attrs["argmax"],
        "delta_F_opt_std": ds.attrs["argmax_std"],
        "delta_F_opt_low": ds.attrs["argmax_low"],
        "delta_F_opt_high": ds.attrs["argmax_high"],
        f"{observable}_exp": ds.attrs["x_ref"],
        f"{observable}_units": units,
        "delta_F_max": dmax,
        "m": m,
    })
    return ds
