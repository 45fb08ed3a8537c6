"""Maximum-likelihood curves from Monte-Carlo samples (Gaussian KDE, Silverman bandwidth).

Used to identify a dispersion (δ for the model uncertainty, δ_F for the load uncertainty): for
each value θ of a grid, N Monte-Carlo realisations X_k(θ) of a scalar observable (e.g. J(δ)) give
a kernel estimate of its pdf, evaluated at the reference value x_ref; the likelihood curve is
θ ↦ p̂(x_ref; θ) and θ_opt its maximiser.

Conventions:

* Kernel: Gaussian; bandwidth h = 1.06 σ̂ N^(−1/5) (Silverman's rule, Soize's convention),
  σ̂ the sample standard deviation with ddof = 1, computed per grid value.
* Common random numbers: row θ of ``samples`` should reuse the same random germs for every θ,
  so the curve is smooth; the bootstrap therefore resamples realisation *indices* jointly
  across the grid (one index set per replicate for all θ), which preserves that coupling.
* Argmax refinement: the discrete maximiser of the log-likelihood is refined by the vertex of the
  parabola through the log-likelihood at the best grid point and its two neighbours (exact for a
  Gaussian-shaped likelihood; stays within those neighbours). At a grid end, or when a neighbour
  has likelihood 0, the grid value itself is returned.
* The pdf has the inverse unit of the samples (e.g. 1/J if the samples are values of J).
* Flat likelihood: with d(θ) = max log p − log p(θ) the log likelihood ratio of each grid value
  against the best and σ(θ) its bootstrap standard deviation, a grid value is *excluded* when
  d(θ) > χ²₁(0.95)/2 + 2 σ(θ) = 1.92 + 2 σ(θ) — a 95 % likelihood-ratio test that the Monte Carlo
  error cannot overturn. The curve is ``flat`` when no grid value is excluded: the data (at this
  Monte Carlo size) prefer no part of the grid. The likelihood-ratio interval {θ : d(θ) ≤ 1.92}
  is reported on the grid (``lr_interval_low``/``_high``); when it reaches an end of the grid the
  data do not bound θ on that side.
"""

from __future__ import annotations

import math
import numbers

import numpy as np
import xarray as xr
from numpy.typing import ArrayLike
from scipy.special import logsumexp

from tubeid._validation import numeric_array, replicates
from tubeid.errors import Described as _Desc, SpecificationError
from tubeid.seeds import rng_for

__all__ = ["silverman_bandwidth", "kde_pdf", "likelihood_curve"]

_SILVERMAN = 1.06
_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
_CHUNK_ELEMENTS = 4_000_000  # bootstrap work arrays are capped at this many float64 values
#: Half the 95 % quantile of χ² with one degree of freedom: the log-likelihood drop of a 95 % likelihood-ratio interval.
LR_THRESHOLD = 1.920729410347062


def _as_samples(samples, field: str, min_n: int) -> np.ndarray:
    # complex samples are not truncated to their real part, bools and strings are not numbers
    s = numeric_array(field, samples, finite=False, dtype=float)
    if s.ndim < 1 or s.shape[-1] < min_n:
        raise SpecificationError(field, _Desc(f"array of shape {s.shape}"),
                                 f"must have at least {min_n} samples along its last axis")
    if not np.all(np.isfinite(s)):
        raise SpecificationError(field, _Desc(f"array with {int(np.sum(~np.isfinite(s)))} non-finite values"),
                                 "must be finite")
    return s


#: A given grid equals the samples' grid coordinate when every value agrees within this fraction of
#: the largest |grid value| (round-off of a grid written out again, e.g. np.linspace against a list).
GRID_RTOL = 1e-9


def _aligned(da: xr.DataArray, g: np.ndarray, grid_name: str, field: str) -> xr.DataArray:
    """``da`` (dims (grid_name, ...)) put in the order of the strictly increasing grid ``g`` by its
    ``grid_name`` coordinate, when it has one; a coordinate whose values are not those of ``g`` is
    refused naming both. An already ordered ``da`` is returned as it is (the same values)."""
    if grid_name not in da.coords:
        return da
    try:
        c = np.asarray(da[grid_name].values, dtype=float)
    except (TypeError, ValueError):
        c = None
    order = None if c is None else np.argsort(c, kind="stable")
    tol = GRID_RTOL * float(np.max(np.abs(g), initial=0.0))
    if c is None or c.shape != g.shape or not np.all(np.abs(c[order] - g) <= tol):
        shown_c = np.array2string(np.asarray(da[grid_name].values), threshold=8)
        raise SpecificationError("grid", _Desc(np.array2string(g, threshold=8)),
                                 f"must equal the {grid_name!r} coordinate of {field} ({shown_c}; in any order, "
                                 f"within {GRID_RTOL:g} of the largest |value|): the samples are matched to the "
                                 "grid by that coordinate")
    if np.any(order != np.arange(order.size)):
        da = da.isel({grid_name: order})
    return da


def _silverman(s: np.ndarray) -> np.ndarray:
    return _SILVERMAN * s.std(axis=-1, ddof=1) * s.shape[-1] ** (-0.2)


def silverman_bandwidth(samples: ArrayLike) -> np.ndarray | float:
    """Silverman's bandwidth h = 1.06 σ̂ N^(−1/5) (σ̂ with ddof = 1) along the last axis.

    Parameters
    ----------
    samples : array_like
        (..., N) finite samples, N ≥ 2, not all equal.

    Returns
    -------
    float or numpy.ndarray
        h in the units of the samples, shape (...) (a float for 1-D samples).
    """
    s = _as_samples(samples, "samples", 2)
    h = _silverman(s)
    if np.any(h <= 0):
        raise SpecificationError("samples", _Desc("constant samples"), "must not all be equal (zero spread, h = 0)")
    return float(h) if h.ndim == 0 else h


def _log_kde(s: np.ndarray, x, h: np.ndarray) -> np.ndarray:
    """log p̂(x) for samples s (..., N), x broadcastable to s.shape[:-1], bandwidths h (s.shape[:-1])."""
    x = np.asarray(x, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # far beyond the samples: log p̂ = -inf
        u = (x[..., None] - s) / h[..., None]
        out = logsumexp(-0.5 * u * u, axis=-1) - math.log(s.shape[-1]) - np.log(h) - _LOG_SQRT_2PI
    return np.where(h > 0, out, -np.inf)


def kde_pdf(samples: ArrayLike, x: ArrayLike, bandwidth: ArrayLike | None = None) -> np.ndarray | float:
    """Gaussian KDE p̂(x) = (1/N) Σ_k φ((x − X_k)/h)/h, vectorised.

    Parameters
    ----------
    samples : array_like
        (..., N): the last axis holds the N realisations.
    x : array_like
        Where to evaluate; broadcasts against ``samples.shape[:-1]`` (e.g. samples (N,) and x
        (M,) → M values; samples (G, N) and a scalar x → G values).
    bandwidth : array_like, optional
        h > 0, broadcasting likewise; default: Silverman's rule per batch entry.

    Returns
    -------
    float or numpy.ndarray
        p̂(x), in the inverse unit of the samples (a float when the result is 0-d).
    """
    s = _as_samples(samples, "samples", 2)
    xa = numeric_array("x", x, finite=False, dtype=float)
    if not np.all(np.isfinite(xa)):
        raise SpecificationError("x", x, "must be finite")
    if bandwidth is None:
        h = np.asarray(silverman_bandwidth(s))
    else:
        h = numeric_array("bandwidth", bandwidth, finite=False, dtype=float)
        if not np.all(np.isfinite(h) & (h > 0)):
            raise SpecificationError("bandwidth", bandwidth, "must be finite and > 0")
    try:
        shape = np.broadcast_shapes(xa.shape, s.shape[:-1], h.shape)
    except ValueError:
        raise SpecificationError("x", _Desc(f"array of shape {xa.shape}"),
                                 f"must broadcast against samples.shape[:-1] = {s.shape[:-1]}") from None
    h = np.broadcast_to(h, shape)
    s = np.broadcast_to(s, shape + (s.shape[-1],))
    p = np.exp(_log_kde(s, np.broadcast_to(xa, shape), h))
    return float(p) if p.ndim == 0 else p


def _shrunk(s: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Samples (..., N) moved toward their mean by √(1 − h²/σ̂²): their KDE with bandwidth h (...)
    then has the samples' variance σ̂² (variance-corrected KDE, Jones 1991; needs h < σ̂, true of
    Silverman's h for N ≥ 2)."""
    m = s.mean(axis=-1, keepdims=True)
    sd = s.std(axis=-1, ddof=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.sqrt(np.clip(1.0 - (np.asarray(h)[..., None] / sd) ** 2, 0.0, None))
    return m + (s - m) * k


def _refine_argmax(grid: np.ndarray, ll: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Discrete and parabola-refined maximisers of ll (..., G) over grid (G,); NaN if ll is -inf everywhere."""
    i = np.argmax(ll, axis=-1)
    best = np.take_along_axis(ll, i[..., None], axis=-1)[..., 0]
    discrete = np.where(np.isfinite(best), grid[i], np.nan)
    refined = discrete.copy()
    G = grid.size
    if G < 3:
        return discrete, refined
    inner = (i > 0) & (i < G - 1)
    j = np.clip(i, 1, G - 2)
    x0, x1, x2 = grid[j - 1], grid[j], grid[j + 1]
    y0 = np.take_along_axis(ll, (j - 1)[..., None], axis=-1)[..., 0]
    y1 = np.take_along_axis(ll, j[..., None], axis=-1)[..., 0]
    y2 = np.take_along_axis(ll, (j + 1)[..., None], axis=-1)[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        num = (x1 - x0) ** 2 * (y1 - y2) - (x1 - x2) ** 2 * (y1 - y0)
        den = (x1 - x0) * (y1 - y2) - (x1 - x2) * (y1 - y0)
        vertex = x1 - 0.5 * num / den
    ok = inner & np.isfinite(y0) & np.isfinite(y1) & np.isfinite(y2) & (den != 0) & np.isfinite(vertex)
    # the middle point is the maximum, so the vertex lies in [x0, x2]; clip guards round-off
    refined = np.where(ok, np.clip(vertex, x0, x2), discrete)
    return discrete, refined


def likelihood_curve(samples: ArrayLike | xr.DataArray, x_ref: float | ArrayLike, grid: ArrayLike,
                     grid_name: str = "delta", n_bootstrap: int = 200,
                     rng: np.random.Generator | int | None = None, *, confidence: float = 0.95,
                     refine: bool = True, variance_corrected: bool = False) -> xr.Dataset:
    """Likelihood θ ↦ p̂(x_ref; θ) from Monte-Carlo samples, with a bootstrap.

    Bootstrap replicates resample realisation indices jointly across the grid; each replicate
    recomputes its Silverman bandwidth. With several observations each replicate also resamples
    them (with replacement), so ``argmax_std`` includes the sampling error of the observations, not
    only the Monte Carlo error of the model; each replicate's likelihood is then taken relative to its
    own maximum, like the curve. Without bootstrap, the bootstrap fields are NaN.

    Parameters
    ----------
    samples : array_like or xarray.DataArray
        (len(grid), N), N ≥ 5: ``samples[g, k]`` is realisation k of the observable at ``grid[g]``
        (common random numbers across the grid); a DataArray with a ``grid_name`` dimension is
        transposed first and, when it has a ``grid_name`` coordinate, matched to ``grid`` by it
        (rows in any order; a coordinate whose values differ from ``grid`` by more than
        :data:`GRID_RTOL` of its largest |value| is refused).
    x_ref : float or array_like
        One observation, or a 1-D array of independent observations (the log-likelihood is then
        the sum of their log-densities, and ``likelihood`` their product divided by its maximum
        over the grid, ``exp(likelihood_log_scale)``, to stay finite).
    grid : array_like
        Strictly increasing 1-D grid of θ.
    grid_name : str
        Name of the grid dimension.
    n_bootstrap : int
        Bootstrap replicates (0: none).
    rng : numpy.random.Generator or int, optional
        Stream or non-negative seed of the bootstrap; required when ``n_bootstrap > 0``.
    confidence : float
        Probability of the percentile intervals, in (0, 1).
    refine : bool
        Refine the maximiser by the parabola through the best grid point and its neighbours.
    variance_corrected : bool
        Move each grid value's samples toward their mean by √(1 − h²/σ̂²) before the kernel estimate,
        so that its variance is the samples' σ̂² instead of σ̂² + h² (Jones 1991). The Silverman
        kernel widens every density by (1 + 1.12 N^(−0.4)) in variance (×1.26 at N = 40); when θ
        sets the spread of the observable (a dispersion read from a symmetric, nearly Gaussian
        difference) the uncorrected maximum then sits at a θ whose spread is too small
        (`tests/test_likelihood.py`). Off by default (the paper's estimator).

    Returns
    -------
    xarray.Dataset
        On dimension ``grid_name``: ``likelihood`` (1/unit of the samples), ``log_likelihood``,
        ``bandwidth``, and bootstrap ``likelihood_std``, ``likelihood_low``, ``likelihood_high``;
        attributes ``argmax`` (parabola-refined if ``refine``), ``argmax_discrete``,
        ``argmax_std``, ``argmax_low``, ``argmax_high``, ``argmax_at_boundary`` (0/1), the
        flatness verdict (module docstring) ``log_likelihood_range`` (max − min of the
        log-likelihood over the grid), ``n_excluded`` (grid values excluded at 95 % beyond 2
        bootstrap σ), ``flat`` (0/1: none is), ``lr_interval_low``, ``lr_interval_high`` (grid
        values), and the settings used.
    """
    # ---- validation (all up front) ----
    if not isinstance(grid_name, str) or not grid_name:
        raise SpecificationError("grid_name", grid_name, "must be a non-empty string")
    g = numeric_array("grid", grid, finite=False, dtype=float)
    if g.ndim != 1 or g.size < 1 or not np.all(np.isfinite(g)):
        raise SpecificationError("grid", _Desc(f"array of shape {g.shape}"), "must be a non-empty finite 1-D array")
    if g.size > 1 and not np.all(np.diff(g) > 0):
        raise SpecificationError("grid", _Desc(np.array2string(g, threshold=8)), "must be strictly increasing")
    if isinstance(samples, xr.DataArray) and grid_name in samples.dims and samples.ndim == 2:
        samples = _aligned(samples.transpose(grid_name, ...), g, grid_name, "samples").values
    s = _as_samples(samples, "samples", 5)
    if s.ndim != 2 or s.shape[0] != g.size:
        raise SpecificationError("samples", _Desc(f"array of shape {s.shape}"),
                                 f"must have shape (len(grid), N) = ({g.size}, N) with N >= 5")
    xs = np.atleast_1d(numeric_array("x_ref", x_ref, finite=False, dtype=float))
    if isinstance(x_ref, (bool, np.bool_)) or xs.ndim != 1 or xs.size == 0 or not np.all(np.isfinite(xs)):
        raise SpecificationError("x_ref", x_ref, "must be a finite real number or a 1-D array of them")
    x_ref = float(xs[0]) if xs.size == 1 else xs
    n_bootstrap = replicates("n_bootstrap", n_bootstrap)
    if not (isinstance(confidence, (numbers.Real, np.floating)) and 0 < float(confidence) < 1):
        raise SpecificationError("confidence", confidence, "must lie in the open interval (0, 1)")
    if n_bootstrap > 0:
        if isinstance(rng, np.random.Generator):
            gen = rng
        elif isinstance(rng, (numbers.Integral, np.integer)) and not isinstance(rng, (bool, np.bool_)) and rng >= 0:
            gen = rng_for(int(rng), "likelihood_curve")
        else:
            raise SpecificationError("rng", rng, "must be a numpy.random.Generator or a non-negative integer seed "
                                                 "when n_bootstrap > 0")
    h = _silverman(s)
    if np.any(h <= 0):
        bad = g[np.argmax(h <= 0)]
        raise SpecificationError("samples", _Desc(f"constant samples at {grid_name} = {bad:g}"),
                                 "must not all be equal (zero spread, h = 0)")
    def joint(samples_, h_):  # independent observations: log-likelihoods add
        if variance_corrected:
            samples_ = _shrunk(samples_, h_)
        return sum(_log_kde(samples_, float(x), h_) for x in xs)

    ll = joint(s, h)  # log-sum-exp: finite even where the likelihood itself underflows to 0
    if not np.any(np.isfinite(ll)):
        raise SpecificationError("x_ref", x_ref if xs.size == 1 else _Desc(f"{xs.size} observations"),
                                 f"lies so far from the samples that its log-likelihood is -inf at every "
                                 f"{grid_name} of the grid (the kernel density underflows): no maximum to find")
    # several observations: their joint density can overflow; report it relative to its maximum
    log_scale = float(np.max(ll)) if xs.size > 1 else 0.0
    discrete, refined = _refine_argmax(g, ll)
    argmax = float(refined if refine else discrete)

    # ---- bootstrap: resample realisation indices jointly across the grid ----
    G, N = s.shape
    nan_curve = np.full(G, np.nan)
    std = low = high = nan_curve
    a_std = a_low = a_high = math.nan
    drop_std = np.zeros(G)
    if n_bootstrap > 0:
        chunk = max(1, _CHUNK_ELEMENTS // (G * N))
        boot_p, boot_arg, boot_range = [], [], []
        for start in range(0, n_bootstrap, chunk):
            b = min(chunk, n_bootstrap - start)
            idx = gen.integers(0, N, size=(b, N))
            res = np.moveaxis(s[:, idx], 0, 1)  # (b, G, N), same indices for every grid value
            h_b = _silverman(res)
            if xs.size > 1:  # the observations are a finite sample too: resample them with replacement
                kde_res = _shrunk(res, h_b) if variance_corrected else res
                per_obs = np.stack([_log_kde(kde_res, float(x), h_b) for x in xs])  # (n_obs, b, G)
                pick = gen.integers(0, xs.size, size=(b, xs.size))
                lb = per_obs[pick.T, np.arange(b)[None, :], :].sum(axis=0)
            else:
                lb = joint(res, h_b)
            # several observations: each replicate relative to its own maximum, as the curve itself
            # (a replicate's joint density can exceed the curve's maximum by far more than exp can hold)
            scale_b = np.max(lb, axis=-1, keepdims=True) if xs.size > 1 else 0.0
            with np.errstate(invalid="ignore"):
                boot_p.append(np.exp(lb - scale_b))
            d_b, r_b = _refine_argmax(g, lb)
            boot_arg.append(r_b if refine else d_b)
            boot_range.append(np.max(lb, axis=-1, keepdims=True) - lb)
        bp, ba = np.concatenate(boot_p), np.concatenate(boot_arg)
        tail = 50.0 * (1.0 - float(confidence))
        std = bp.std(axis=0, ddof=1) if n_bootstrap > 1 else nan_curve
        low, high = np.percentile(bp, [tail, 100.0 - tail], axis=0)
        drops = np.concatenate(boot_range)  # (n_bootstrap, G): each replicate's log ratio to its own best
        if n_bootstrap > 1:
            with np.errstate(invalid="ignore"):
                drop_std = np.where(np.all(np.isfinite(drops), axis=0), np.std(drops, axis=0, ddof=1), np.inf)
        if np.any(np.isfinite(ba)):
            a_std = float(np.nanstd(ba, ddof=1)) if np.sum(np.isfinite(ba)) > 1 else math.nan
            a_low, a_high = (float(v) for v in np.nanpercentile(ba, [tail, 100.0 - tail]))

    p = np.exp(ll - log_scale)
    top = float(np.max(ll))
    with np.errstate(invalid="ignore"):
        lr_range = float(top - np.min(ll)) if math.isfinite(top) else math.nan
    with np.errstate(invalid="ignore"):
        excluded = (top - ll) > LR_THRESHOLD + 2.0 * drop_std
    flat = not bool(np.any(excluded))
    inside = np.flatnonzero(ll >= top - LR_THRESHOLD) if math.isfinite(top) else np.array([], dtype=int)
    lr_low, lr_high = (float(g[inside[0]]), float(g[inside[-1]])) if inside.size else (math.nan, math.nan)
    dims = (grid_name,)
    ds = xr.Dataset(
        {
            "likelihood": (dims, p, {"long_name": f"p(x_ref; {grid_name})", "units": "1/unit of samples"}),
            "log_likelihood": (dims, ll, {"long_name": f"log p(x_ref; {grid_name})"}),
            "bandwidth": (dims, h, {"long_name": "Silverman bandwidth 1.06 σ̂ N^(-1/5)", "units": "unit of samples"}),
            "likelihood_std": (dims, std, {"long_name": "bootstrap standard deviation of the likelihood"}),
            "likelihood_low": (dims, low, {"long_name": f"bootstrap {100 * confidence:g} % interval, low"}),
            "likelihood_high": (dims, high, {"long_name": f"bootstrap {100 * confidence:g} % interval, high"}),
        },
        coords={grid_name: (dims, g)},
        attrs={
            "argmax": argmax,
            "argmax_discrete": float(discrete),
            "argmax_std": a_std,
            "argmax_low": a_low,
            "argmax_high": a_high,
            "argmax_at_boundary": int(np.argmax(ll) in (0, G - 1)),
            "log_likelihood_range": lr_range,
            "n_excluded": int(np.sum(excluded)),
            "flat": int(flat),
            "flat_rule": f"no grid value has max log p - log p > {LR_THRESHOLD:.2f} + 2 bootstrap std of that difference",
            "lr_interval_low": lr_low,
            "lr_interval_high": lr_high,
            "argmax_method": ("parabola through the log-likelihood at the discrete maximum and its two neighbours"
                              if refine else "discrete grid maximum"),
            "x_ref": x_ref if xs.size == 1 else xs.tolist(),
            "n_observations": int(xs.size),
            "likelihood_log_scale": log_scale,
            "n_samples": N,
            "n_bootstrap": n_bootstrap,
            "confidence": float(confidence),
            "kernel": "gaussian, Silverman h = 1.06 sigma N^(-1/5), sigma with ddof=1, per grid value"
                      + ("; variance-corrected (samples shrunk by sqrt(1 - h^2/sigma^2))" if variance_corrected else ""),
            "bootstrap": "realisation indices resampled jointly across the grid (common random numbers kept); "
                         "bandwidth recomputed per replicate; percentile intervals"
                         + ("; observations resampled with replacement" if xs.size > 1 else ""),
        },
    )
    return ds
