"""Load identification on the record's fitting blocks: r by a trial method, δ_F by maximum likelihood.

*r* by a trial method in two runner stages: a coarse grid of ``r_points`` values per component,
``r_step`` decades apart around ``r0``; then a fine grid of ``r_fine_points`` per component over
± ``r_fine_span`` decades around the coarse minimum moved by its mean log offset (for a linear model
that move is exactly the best level). Distance: mean over sensors and 0 < f ≤ band of
(log10 S̄_model(r) − log10 S_fit)², S̄_model the mean PSD of ``fit_realisations`` records of the
mean model, common random numbers for every trial. r_opt: per component, the vertex of the
parabola in log r through the fine grid's minimum and its neighbours.

*δ_F* (the load dispersion, SG+ of size m = the number of load components) by maximum likelihood
of J_s = ∫‖S_Z(ω)‖²_F dω (MODEL.md §3.5; S_Z the PSD matrix of all sensors, ω over 2π·[−band,
band]): one observation per fitting block, against a Monte Carlo of the stochastic model at
(δ, r_opt) for every δ_F of a grid (common random numbers across the grid), Gaussian kernel
(Silverman). Only when the record has at least ``delta_f_min_blocks`` fitting blocks: a dispersion
is a spread across load states, and two or three blocks cannot show one. The observations are
treated as independent load states; blocks of one continuous record share one, and their joint
likelihood then measures how far that state lies from the mean model. Verdicts: ``flat`` (the
likelihood varies by less than e² over the grid), ``identified`` (both ends excluded by e²), else a
one-sided bound. The band uses the argmax unless the likelihood is flat, excludes neither end, or
peaks at the grid's upper end (J_s above what any admissible dispersion gives: a sign that the
model misses something, which a band widened to that limit would hide); then
``delta_f_fallback``, and the report says why.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from tubeid.diagnose._selection import line_minimum
from tubeid.diagnose._settings import DiagnoseSettings
from tubeid.diagnose._spectra import analysis_bins, log10
from tubeid.seeds import rng_for
from tubeid.uncertainty.random_matrices import delta_max

__all__ = ["r_coarse_grid", "r_fine_grid", "grid_minimum", "r_distance", "scaled_r", "default_delta_f_grid",
           "delta_f_identification", "FLAT_LOG_RATIO"]

#: A likelihood is ``flat`` when max/min over the grid < e^FLAT_LOG_RATIO (≈ 7.4); a grid end is
#: excluded when its likelihood is below the maximum by that factor.
FLAT_LOG_RATIO = 2.0


def _sig6(values) -> np.ndarray:
    """Values to 6 significant digits (stable, readable grid coordinates)."""
    return np.array([float(f"{float(x):.6g}") for x in values])


def r_coarse_grid(start, points: int, step: float) -> list[np.ndarray]:
    """Per component of r: ``points`` values ``step`` decades apart, centred on ``start``."""
    k = np.arange(points) - (points - 1) / 2.0
    return [_sig6(float(x) * 10.0 ** (step * k)) for x in start]


def r_fine_grid(centre, points: int, span: float) -> list[np.ndarray]:
    """Per component of r: ``points`` values over ± ``span`` decades around ``centre``."""
    u = np.linspace(-span, span, points)
    return [_sig6(float(x) * 10.0**u) for x in centre]


def grid_minimum(distance: np.ndarray, axes, refine: bool = True) -> tuple[tuple[float, ...], tuple[int, ...], bool]:
    """Minimum of a distance over a grid of r (one axis per component, log-spaced values).

    Returns (r_opt, index of the discrete minimum, at_boundary). With ``refine``, each component
    is moved to the vertex of the parabola in log10 r through the minimum and its two neighbours
    along that axis (:func:`~tubeid.diagnose._selection.line_minimum`); at a grid end the grid
    value is kept.
    """
    d = np.asarray(distance, dtype=float)
    idx = tuple(int(i) for i in np.unravel_index(int(np.nanargmin(d)), d.shape))
    out, boundary = [], False
    for a, values in enumerate(axes):
        values = np.asarray(values, dtype=float)
        i = idx[a]
        if values.size > 1 and i in (0, values.size - 1):
            boundary = True
        line = d[idx[:a] + (slice(None),) + idx[a + 1:]]
        out.append(line_minimum(values, line, log=True) if refine else float(values[i]))
    return tuple(out), idx, boundary


def r_distance(target: np.ndarray, P: np.ndarray, f: np.ndarray, band_hz: float) -> tuple[float, float]:
    """Log-spectral distance (decades²) of model auto-PSD P (F, m) to ``target`` and the mean log
    offset (decades) over sensors and 0 < f ≤ band."""
    sel = analysis_bins(f) & (f <= band_hz)
    diff = log10(target[sel]) - log10(P[sel])
    return float(np.mean(diff**2)), float(np.mean(diff))


def scaled_r(r, offset) -> tuple[float, ...]:
    """r moved by a log offset of the response PSD (linear-model level step)."""
    return tuple(float(x) * 10.0**offset for x in r)


def default_delta_f_grid(m: int, points: int = 9) -> tuple[float, ...]:
    """δ_F grid: ``points`` values log-spaced from 0.01 to 0.9 δ_max(m) (dense near 0, where the
    paper finds 0.04), 4 decimals. m = 2: 0.01 … 0.589."""
    return tuple(float(x) for x in np.round(np.geomspace(0.01, 0.9 * delta_max(m), points), 4))


def delta_f_identification(samples: xr.DataArray, observations, m: int, settings: DiagnoseSettings) -> dict:
    """δ_F by maximum likelihood of J_s (module docstring), as plain values.

    ``samples``: J_s (delta_F, realisation) Monte Carlo with common random numbers across δ_F;
    ``observations``: the data's J_s, one per fitting block. Returns ``delta_F`` (argmax),
    ``delta_F_used`` (by the band: the argmax or ``delta_f_fallback``) and ``used_reason`` (''
    for the argmax), ``delta_F_std`` (bootstrap over realisations), ``delta_F_std_observations``
    (bootstrap over observations; None with one observation), the grid, ``log_likelihood``
    relative to its maximum (floored at −1000), ``likelihood`` (max 1), ``flat``, ``identified``,
    ``at_boundary`` and ``note``.
    """
    from tubeid.identification.likelihood import likelihood_curve
    from tubeid.identification.loads import delta_f_likelihood

    obs = np.asarray(observations, dtype=float)
    lik = delta_f_likelihood(samples, obs, m=m, n_bootstrap=settings.n_bootstrap,
                             rng=rng_for(settings.seed, "diagnose", "delta_F") if settings.n_bootstrap else None)
    grid = lik["delta_F"].values
    ll = lik["log_likelihood"].values
    note = ""
    if not np.any(np.isfinite(ll)):
        rel = np.full(ll.shape, -1000.0)
        flat, identified, at_boundary = True, False, True
        opt = float(grid[0])
        note = ("no δ_F of the grid gives the observed J_s a non-zero density: δ_F is not identified "
                "(the smallest grid value is used)")
    else:
        rel = np.maximum(ll - np.max(ll), -1000.0)
        flat = bool(np.max(rel) - np.min(rel) < FLAT_LOG_RATIO)
        identified = bool(rel[0] <= -FLAT_LOG_RATIO and rel[-1] <= -FLAT_LOG_RATIO)
        at_boundary = bool(lik.attrs["argmax_at_boundary"])
        opt = float(lik.attrs["argmax"])
        if flat:
            note = ("the likelihood is flat: it varies by less than a factor e^2 over the grid, so these data do "
                    "not identify δ_F (the value used is the argmax, with no precision)")
        elif rel[0] > -FLAT_LOG_RATIO and rel[-1] > -FLAT_LOG_RATIO:
            note = ("neither end of the grid is excluded (likelihood within a factor e^2 of the maximum at both): "
                    "these data do not identify δ_F")
        elif not identified:
            note = ("only an upper bound: small δ_F are not excluded" if rel[0] > -FLAT_LOG_RATIO
                    else "only a lower bound: large δ_F are not excluded")
    used, reason = opt, ""
    if flat or note.startswith("neither") or not np.any(np.isfinite(ll)):
        used, reason = settings.delta_f_fallback, "the likelihood does not identify δ_F"
    elif np.isfinite(ll[-1]) and int(np.argmax(ll)) == ll.size - 1:
        used, reason = settings.delta_f_fallback, (
            "the likelihood is largest at the grid's upper end: the observed J_s exceed what any admissible load "
            "dispersion gives, a sign of a missing effect rather than an estimate of δ_F")
    std_mc = lik.attrs["argmax_std"]
    std_obs = None
    if obs.size > 1 and settings.n_bootstrap > 1 and np.any(np.isfinite(ll)):
        gen = rng_for(settings.seed, "diagnose", "delta_F observations")
        s = samples.transpose("delta_F", ...).values
        arg = [likelihood_curve(s, obs[gen.integers(0, obs.size, obs.size)], grid, "delta_F", n_bootstrap=0).attrs["argmax"]
               for _ in range(settings.n_bootstrap)]
        arg = np.asarray(arg, dtype=float)
        if np.sum(np.isfinite(arg)) > 1:
            std_obs = float(np.nanstd(arg, ddof=1))
    return {
        "delta_F": opt, "delta_F_used": float(used), "used_reason": reason,
        "delta_F_std": float(std_mc) if np.isfinite(std_mc) else None, "delta_F_std_observations": std_obs,
        "grid": [float(x) for x in grid], "log_likelihood": [float(x) for x in rel],
        "likelihood": [float(x) for x in np.exp(rel)], "flat": flat, "identified": identified,
        "at_boundary": at_boundary, "J_s_observed": [float(x) for x in obs],
        "n_realisations": int(samples.sizes["realisation"]), "note": note,
    }
