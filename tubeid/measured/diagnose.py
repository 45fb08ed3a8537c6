"""Close the loop with measured data: residual → missing effect → augmented model → error before/after.

``diagnose(data, model)`` runs the five steps of issue 6 on a validated measurement Dataset
(``displacement`` (time, sensor) with ``x`` and ``tube`` on ``sensor``, see
:mod:`tubeid.measured.validation`). Every Monte Carlo simulation and every trial of a grid is a
task of the runner pipeline :mod:`tubeid.measured.pipeline` (one Zarr store in ``out``, resumable;
``workers=0`` runs the tasks in this process, ``workers=N`` on an embedded dask LocalCluster,
``scheduler=`` on an existing one); this module holds the method and assembles the report.

1. **Split and spectra.** The record is cut into ``blocks`` equal contiguous time blocks; the even
   blocks (0, 2, …) are the *fitting* segments, the odd ones the *held-out* segments. Each block
   gives a Welch PSD matrix per sensor pair (Hann, 50 % overlap, ``segment_seconds``; two-sided per
   Hz); auto-PSDs are averaged over the blocks of a set.
2. **Load identification** on the fitting segments for the declared model (δ, the dispersion of
   subsystem B's stiffness, given: default 0.2). The load is ``distributed`` (the model's force
   points on the non-linear tube, coherence exp(−|Δx|/λ), one level r [N²/Hz]) or the paper's
   ``force_and_moment`` at ``load_x`` (r = (r1 [N²/Hz], r2 [(N·m)²/Hz])).

   *r* by a trial method in two runner stages: a coarse grid of ``r_points`` values per component,
   ``r_step`` decades apart around ``r0``; then a fine grid of ``r_fine_points`` per component over
   ± ``r_fine_span`` decades around the coarse minimum moved by its mean log offset (for a linear
   model that move is exactly the best level). Distance: mean over sensors and 0 < f ≤ band of
   (log10 S̄_model(r) − log10 S_fit)², S̄_model the mean PSD of ``fit_realisations`` records of the
   mean model (δ = δ_F = 0), common random numbers for every trial. r_opt: the fine grid's minimum
   refined by the vertex of the parabola in log r through it and its neighbours (per component).

   *δ_F* (the load dispersion, SG+ of size m = the number of load components) by maximum
   likelihood of J_s = ∫‖S_Z(ω)‖²_F dω (MODEL.md §3.5; S_Z the PSD matrix of all sensors, ω over
   2π·[−band, band]): the observations are one J_s per fitting block; the model's distribution is
   a Monte Carlo of ``delta_f_realisations`` records of one block's length of the stochastic model
   at (δ, r_opt) for every δ_F of a grid in (0, √((m+1)/(m+5))) (common random numbers: the same
   realisation streams at every δ_F), estimated by a Gaussian kernel (Silverman), the joint
   likelihood of the observations maximised over the grid
   (:func:`tubeid.identification.loads.delta_f_likelihood`). Its uncertainty: the bootstrap std
   over the Monte Carlo realisations (``delta_F_std``) and over the observations
   (``delta_F_std_observations``). The observations are treated as independent draws, which
   holds when each fitting block comes from an independent load state (separate records,
   operating points); blocks of one continuous record share one load state, and their joint
   likelihood then measures how far that state lies from the mean model rather than the spread
   of states. The likelihood is reported ``flat`` when it varies by less than a factor
   e² ≈ 7.4 over the whole grid (δ_F not identified by these data), ``identified`` when both ends
   of the grid are excluded by that factor. The band uses the argmax, except when the likelihood
   is flat, excludes neither end, or is largest at the grid's upper end: then ``delta_f_fallback``
   (the paper's 0.04), and the report says why. An argmax at the largest admissible δ_F means the
   observed J_s exceed what any admissible load dispersion makes them — not an estimate but a
   sign that the model misses something (what the loop looks for: a missing damping, measured,
   inflates the peak-dominated J_s and drove δ_F there), and a band widened to that limit would
   hide it. ``load_dispersion`` = a number imposes δ_F instead.
3. **Residual** of the held-out PSD against the stochastic model's confidence band at
   (δ, δ_F, r_opt) (per sensor and frequency, ``level`` 0.95, Monte Carlo of ``realisations``
   records with the held-out blocks' length, so the band includes the same estimator scatter as
   the data): d(f, s) = log10(S_meas / upper) above the band, log10(S_meas / lower) below it, 0
   inside. **The error** is the RMS of d over all sensors and frequencies 0 < f < f_Nyquist, in
   decades. Time-domain statistics (RMS, skewness, excess kurtosis per sensor) are compared with
   the model's realisations as z-scores.
4. **Tracing and fitting** (:mod:`tubeid.measured.effects_fit`): candidate effects of the catalog
   ranked by signature (computed on the *fitting* blocks against the same band, so nothing of the
   held-out blocks enters a fit), the leading ones fitted by trial grids (runner tasks; a tone's
   amplitude grid is centred by a probe simulation), each best fit's band simulated and scored by
   its error on the held-out segments; the choice penalises parameters.
5. **Re-identification** of r with the chosen effect (coarse and fine grids again, from the
   chosen candidate's level) and the final held-out error; δ_F is kept.

``none`` is answered when the held-out error before is within what the model's own realisations
show (leave-one-out null: each realisation compared with the band of the others; the threshold is
their ``null_quantile`` quantile times ``null_margin``), or when no candidate improves the error
by the required factor. ``explained_after`` says whether the final error is within the null of the
augmented model; when it is not, the residual is only partly explained (report.md warns).

Choice of the declared model matters: ``paper-simplified`` seen from sensors at x = 2, 6, 10 m on
reference-model data leaves 60–80 % of the bins outside the δ = 0.2 band (error ≈ 0.65 decades,
null ≈ 0.1) — model uncertainty that no single catalog effect explains; the tool then answers
``none`` with ``explained_before = explained_after = false`` rather than inventing an effect.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import xarray as xr

from tubeid.dynamics.response import ResponseSettings, simulate_responses
from tubeid.dynamics.spectra import j_s, psd_matrix
from tubeid.errors import SpecificationError
from tubeid.mechanics.effects import Tone, apply_effects, effect_from_dict, effect_to_dict
from tubeid.mechanics.library import resolve_spec
from tubeid.mechanics.reduction import reduce
from tubeid.mechanics.spec import BundleSpec, SensorSpec, spec_from_dict, spec_to_dict
from tubeid.measured.validation import validate_measurements
from tubeid.seeds import rng_for
from tubeid.uncertainty.loads import coherent_forces, force_and_moment
from tubeid.uncertainty.random_matrices import Dispersion, delta_max

__all__ = [
    "DiagnoseSettings",
    "MeasuredSpectra",
    "ModelBand",
    "Diagnosis",
    "DiagnoseContext",
    "measured_spectra",
    "model_band",
    "band_residual",
    "held_out_error",
    "time_statistics",
    "simulate_blocks",
    "simulate_series",
    "load_spectrum",
    "load_dimension",
    "analysis_bins",
    "r_coarse_grid",
    "r_fine_grid",
    "grid_minimum",
    "default_delta_f_grid",
    "delta_f_identification",
    "plan_candidates",
    "data_hash",
    "load_context",
    "diagnose",
    "ERROR_METRIC",
    "LOAD_MODELS",
    "FLAT_LOG_RATIO",
    "PIPELINE_FILE",
]

#: Identification load models: ``distributed`` — the declared model's force points on the
#: non-linear tube with the paper's coherence exp(−|Δx|/λ) (λ = ``correlation_length``), one
#: parameter r = S_ii [N²/Hz]; ``force_and_moment`` — the paper's §3.4 model T, M at ``load_x``,
#: r = (r1 [N²/Hz], r2 [(N·m)²/Hz]).
LOAD_MODELS = ("distributed", "force_and_moment")

#: What ``error_before`` / ``error_after`` measure (one sentence, written into report.json).
ERROR_METRIC = (
    "RMS over all sensors and frequencies 0 < f < f_Nyquist of the log10 distance (decades) of the "
    "measured held-out Welch PSD outside the model's per-frequency confidence band (0 inside the band)"
)

#: A δ_F likelihood is ``flat`` when max/min over the grid < e^FLAT_LOG_RATIO (≈ 7.4); a grid end
#: is excluded when its likelihood is below the maximum by that factor.
FLAT_LOG_RATIO = 2.0

#: The runner pipeline definition run by :func:`diagnose` (workers load it by its source text).
PIPELINE_FILE = Path(__file__).with_name("pipeline.py")

_TUPLE_FIELDS = ("r0", "delta_f_grid")


@dataclass(frozen=True)
class DiagnoseSettings:
    """Sizes and rules of a diagnosis (seconds, Hz, counts, decades).

    ``blocks``: the record is cut into this many equal time blocks (even ones fit, odd ones are
    held out; ≥ 2). ``segment_seconds``: Welch segment [s]. ``realisations``: Monte Carlo size of
    the confidence band; ``fit_realisations``: records of the mean model per trial of the load
    identification and of the effect grids. ``level``: probability of the band. ``delta``:
    dispersion of B's stiffness (given). ``load_dispersion``: δ_F; ``None`` (default) identifies
    it by maximum likelihood of J_s over ``delta_f_grid`` (``None``: :func:`default_delta_f_grid`)
    with ``delta_f_realisations`` Monte Carlo records per grid value and ``n_bootstrap``
    bootstrap replicates (``delta_f_fallback``: the band's δ_F when the likelihood does not
    identify it, see the module docstring); a number imposes it. ``load``: see :data:`LOAD_MODELS`;
    ``correlation_length`` [m] of the distributed load; ``load_x`` [m]: position of the
    force-and-moment load on the non-linear tube. ``r0``: starting r (N²/Hz, (N·m)²/Hz; default
    the paper's levels). ``r_points``, ``r_step`` [decades], ``r_fine_points``, ``r_fine_span``
    [decades]: the coarse and fine trial grids of r (see the module docstring). ``n_fit``:
    leading candidates whose parameters are fitted (those whose signature score is below
    ``min_relative_score`` × the best score are not). ``grid_points``: points per candidate trial
    grid. ``penalty``: an effect with k fitted parameters must bring the held-out error below
    error_before × (1 − penalty)^k. ``null_quantile``, ``null_margin``: the `none` rule.
    ``discard`` [s]: transient dropped from every simulation. ``dt_load_max`` [s]: load sampling
    bound (the simulation's load step is the data's dt divided by the smallest integer that
    brings it below this). ``seed``: all random streams (common random numbers across trials).
    """

    blocks: int = 4
    segment_seconds: float = 2.0
    realisations: int = 40
    fit_realisations: int = 4
    level: float = 0.95
    delta: float = 0.2
    load_dispersion: float | None = None
    delta_f_grid: tuple[float, ...] | None = None
    delta_f_realisations: int = 30
    delta_f_fallback: float = 0.04
    n_bootstrap: int = 200
    load: str = "distributed"
    correlation_length: float = 4.0
    load_x: float = 8.0
    r0: tuple[float, ...] | None = None
    r_points: int = 3
    r_step: float = 0.5
    r_fine_points: int = 5
    r_fine_span: float = 0.25
    n_fit: int = 2
    min_relative_score: float = 0.2
    grid_points: int = 4
    penalty: float = 0.1
    null_quantile: float = 0.95
    null_margin: float = 1.25
    discard: float = 2.0
    dt_load_max: float = 1e-3
    seed: int = 0

    def __post_init__(self):
        def is_num(v):
            return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

        def num(name, lo=0.0, strict=True, hi=math.inf):
            v = getattr(self, name)
            if not is_num(v) or (v <= lo if strict else v < lo) or v >= hi:
                rel = ">" if strict else ">="
                raise SpecificationError(f"settings.{name}", v, f"must be a finite number {rel} {lo}" + ("" if hi == math.inf else f" and < {hi}"))

        def count(name, lo):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < lo:
                raise SpecificationError(f"settings.{name}", v, f"must be an integer >= {lo}")

        if self.load not in LOAD_MODELS:
            raise SpecificationError("settings.load", self.load, f"must be one of {LOAD_MODELS}")
        count("blocks", 2)
        count("realisations", 4)
        count("fit_realisations", 1)
        count("delta_f_realisations", 5)
        count("n_bootstrap", 0)
        count("r_points", 1)
        count("r_fine_points", 3)
        count("n_fit", 1)
        count("grid_points", 2)
        count("seed", 0)
        for name in ("segment_seconds", "load_x", "dt_load_max", "correlation_length", "r_step", "r_fine_span"):
            num(name)
        num("level", hi=1.0)
        num("null_quantile", hi=1.0)
        num("delta", strict=False, hi=1.0)
        if self.load_dispersion is not None:
            num("load_dispersion", strict=False, hi=1.0)
        num("delta_f_fallback", strict=False, hi=1.0)
        num("penalty", strict=False, hi=1.0)
        num("min_relative_score", strict=False, hi=1.0)
        num("null_margin", lo=1.0, strict=False)
        num("discard", strict=False)
        n_r = 2 if self.load == "force_and_moment" else 1
        for name in _TUPLE_FIELDS:
            v = getattr(self, name)
            if isinstance(v, list):
                object.__setattr__(self, name, tuple(v))
        if self.r0 is not None and (not isinstance(self.r0, tuple) or len(self.r0) != n_r
                                    or not all(is_num(v) and v > 0 for v in self.r0)):
            raise SpecificationError("settings.r0", self.r0, f"must be {n_r} number(s) > 0 for the {self.load} load")
        g = self.delta_f_grid
        if g is not None and (not isinstance(g, tuple) or len(g) < 3 or not all(is_num(v) and 0 < v < 1 for v in g)
                              or any(b <= a for a, b in zip(g, g[1:]))):
            raise SpecificationError("settings.delta_f_grid", g, "must be >= 3 increasing numbers in (0, 1)")

    @property
    def start_r(self) -> tuple[float, ...]:
        """Starting r of the trial method: ``r0``, else the paper's values for the load model."""
        if self.r0 is not None:
            return tuple(float(v) for v in self.r0)
        return (18.0, 20.0) if self.load == "force_and_moment" else (1.3,)

    def to_json(self) -> str:
        """Canonical JSON (sorted keys): the settings' identity in a diagnosis store."""
        return json.dumps(dataclasses.asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "DiagnoseSettings":
        d = json.loads(text)
        return cls(**{k: (tuple(v) if k in _TUPLE_FIELDS and v is not None else v) for k, v in d.items()})


# ----------------------------------------------------------------------------------------------
# Measured spectra
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MeasuredSpectra:
    """Welch PSDs of the fitting and held-out blocks of a record (two-sided, m²/Hz).

    ``frequency`` (F,) Hz; ``fit``, ``held_out`` (F, m) auto-PSDs averaged over the blocks of the
    set; ``held_out_blocks`` (n_h, F, m) per block; ``fit_cross`` (n_f, F, m, m) complex PSD
    matrix per fitting block (for J_s); ``stats``, ``fit_stats`` (m, 3): RMS [m], skewness, excess
    kurtosis of the held-out resp. fitting samples; ``dt`` [s]; ``block_samples``: samples per
    block; ``sensors``: names; ``x``, ``tube`` per sensor.
    """

    frequency: np.ndarray
    fit: np.ndarray
    held_out: np.ndarray
    held_out_blocks: np.ndarray
    fit_cross: np.ndarray
    stats: np.ndarray
    fit_stats: np.ndarray
    dt: float
    block_samples: int
    n_fit_blocks: int
    n_held_out_blocks: int
    sensors: tuple
    x: tuple
    tube: tuple


def _auto_psd(blocks: np.ndarray, dt: float, segment_seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """(..., n_t, m) -> f (F,), auto-PSD (..., F, m), two-sided per Hz."""
    f, S = psd_matrix(blocks, dt, segment_seconds=segment_seconds)
    return f, np.real(np.diagonal(S, axis1=-2, axis2=-1))


def time_statistics(y: np.ndarray) -> np.ndarray:
    """RMS [m], skewness and excess kurtosis per channel of records y (..., n_t, m) -> (..., m, 3)."""
    c = y - y.mean(axis=-2, keepdims=True)
    var = np.mean(c**2, axis=-2)
    sd = np.sqrt(var)
    safe = np.where(var > 0, var, 1.0)
    skew = np.mean(c**3, axis=-2) / safe**1.5
    kurt = np.mean(c**4, axis=-2) / safe**2 - 3.0
    return np.stack([sd, skew, kurt], axis=-1)


def _split(y: np.ndarray, blocks: int) -> tuple[np.ndarray, np.ndarray, int]:
    """(..., n_t, m) -> even blocks, odd blocks (..., n_b, L, m), L."""
    L = y.shape[-2] // blocks
    cut = y[..., : L * blocks, :].reshape(y.shape[:-2] + (blocks, L, y.shape[-1]))
    return cut[..., 0::2, :, :], cut[..., 1::2, :, :], L


def measured_spectra(data: xr.Dataset, settings: DiagnoseSettings = DiagnoseSettings()) -> MeasuredSpectra:
    """Fitting and held-out spectra of a validated record (see the module docstring, step 1)."""
    y = np.asarray(data["displacement"].transpose("time", "sensor").values, dtype=float)
    t = np.asarray(data["time"].values, dtype=float)
    dt = float((t[-1] - t[0]) / (t.size - 1))
    L = y.shape[0] // settings.blocks
    need = 2 * int(round(settings.segment_seconds / (2 * dt)))
    if L < 2 * need:
        raise SpecificationError(
            "data duration", t.size * dt,
            f"too short: each of the {settings.blocks} blocks ({L * dt:.4g} s) must hold at least 2 Welch segments "
            f"of {settings.segment_seconds} s (record >= {2 * need * settings.blocks * dt:.4g} s)")
    fit, held, L = _split(y, settings.blocks)
    f, S_fit = psd_matrix(fit, dt, segment_seconds=settings.segment_seconds)
    P_fit = np.real(np.diagonal(S_fit, axis1=-2, axis2=-1))
    _, P_held = _auto_psd(held, dt, settings.segment_seconds)
    stats = time_statistics(held.reshape(-1, y.shape[1]))
    fit_stats = time_statistics(fit.reshape(-1, y.shape[1]))
    return MeasuredSpectra(
        frequency=f, fit=P_fit.mean(axis=0), held_out=P_held.mean(axis=0), held_out_blocks=P_held, fit_cross=S_fit,
        stats=stats, fit_stats=fit_stats, dt=dt, block_samples=L, n_fit_blocks=fit.shape[0],
        n_held_out_blocks=held.shape[0], sensors=tuple(str(s) for s in data["sensor"].values),
        x=tuple(float(v) for v in data["x"].values), tube=tuple(str(v) for v in data["tube"].values))


# ----------------------------------------------------------------------------------------------
# Model simulations on the data's grid
# ----------------------------------------------------------------------------------------------


def _dt_load(dt: float, bound: float) -> float:
    k = max(1, math.ceil(dt / bound - 1e-9))
    return dt / k


def load_spectrum(spec: BundleSpec, r, settings: DiagnoseSettings):
    """The identification load with parameters r (see :data:`LOAD_MODELS`)."""
    tube = spec.a_tube or spec.tubes[0].name
    if settings.load == "force_and_moment":
        return force_and_moment(float(r[0]), float(r[1]), x=settings.load_x, band=spec.band_hz, tube=tube)
    xs = [p.x for p in spec.loads if p.kind == "force" and p.tube == tube]
    if not xs:
        raise SpecificationError("model.loads", spec.loads, f"the distributed load needs force points on tube {tube!r}")
    return coherent_forces(xs, level=float(r[0]), band=spec.band_hz, correlation_length=settings.correlation_length, tube=tube)


def load_dimension(spec: BundleSpec, settings: DiagnoseSettings) -> int:
    """m, the size of the load's SG+ matrix G_m (the number of load components)."""
    return len(load_spectrum(spec, settings.start_r, settings).names)


def default_delta_f_grid(m: int, points: int = 9) -> tuple[float, ...]:
    """δ_F grid: ``points`` values log-spaced from 0.01 to 0.9 δ_max(m) (dense near 0, where the
    paper finds 0.04), 4 decimals. m = 2: 0.01 … 0.589."""
    return tuple(float(v) for v in np.round(np.geomspace(0.01, 0.9 * delta_max(m), points), 4))


def simulate_series(spec: BundleSpec, r, effects, meas: MeasuredSpectra, n_samples: int, realisations,
                    settings: DiagnoseSettings, *, stochastic: bool, load_dispersion: float = 0.0,
                    rngs=None) -> np.ndarray:
    """Records (R, n_samples, m) at the data's sensors and sampling, transient discarded.

    ``stochastic``: with the model dispersion δ of ``settings`` and the load dispersion
    ``load_dispersion``, else the mean model. ``rngs``: one generator per realisation (the
    runner's; a fresh generator object per call for common random numbers), else the streams
    ``rng_for(settings.seed, "response", r)``.
    """
    full = apply_effects(spec, effects)
    model = reduce(full)
    load = load_spectrum(full, r, settings)
    dt = meas.dt
    duration = settings.discard + (n_samples + 2) * dt
    rs = ResponseSettings(duration=duration, dt_load=_dt_load(dt, settings.dt_load_max), output_dt=dt,
                          discard=settings.discard, segment_seconds=min(settings.segment_seconds, duration - settings.discard),
                          keep="series")
    disp = Dispersion(stiffness=settings.delta) if stochastic and settings.delta > 0 else Dispersion()
    kw = {"seed": settings.seed} if rngs is None else {"rngs": list(rngs)}
    ds = simulate_responses(model, load, realisations, dispersion=disp,
                            load_dispersion=float(load_dispersion) if stochastic else 0.0, settings=rs, **kw)
    return ds["displacement"].transpose("realisation", "time", "sensor").values[:, :n_samples, :]


def simulate_blocks(spec: BundleSpec, r, effects, meas: MeasuredSpectra, n_blocks: int, realisations,
                    settings: DiagnoseSettings, *, stochastic: bool, load_dispersion: float = 0.0,
                    rngs=None) -> tuple[np.ndarray, np.ndarray]:
    """Model records cut like the data: auto-PSD per realisation (R, F, m) averaged over ``n_blocks``
    blocks of the data's block length, and time statistics (R, m, 3).

    ``stochastic``: see :func:`simulate_series`; else the mean model, and the R "realisations" are
    consecutive stretches of one record of the first realisation (same estimator scatter, one
    set of solver tables).
    """
    realisations = np.atleast_1d(np.asarray(realisations, dtype=int))
    R = realisations.size
    if not stochastic:
        n_blocks, realisations = n_blocks * R, realisations[:1]
        rngs = None if rngs is None else list(rngs)[:1]
    y = simulate_series(spec, r, effects, meas, n_blocks * meas.block_samples, realisations, settings,
                        stochastic=stochastic, load_dispersion=load_dispersion, rngs=rngs)
    if not stochastic:
        n_blocks //= R
        y = y.reshape(R, n_blocks * meas.block_samples, y.shape[2])
    blocks = y.reshape(y.shape[0], n_blocks, meas.block_samples, y.shape[2])
    _, P = _auto_psd(blocks, meas.dt, settings.segment_seconds)
    return P.mean(axis=1), time_statistics(y)


def _spec_for(spec: BundleSpec, meas: MeasuredSpectra) -> BundleSpec:
    """The declared model with the data's sensors (names, tubes, positions)."""
    names = [t.name for t in spec.tubes]
    for s, tube, x in zip(meas.sensors, meas.tube, meas.x):
        if tube not in names:
            raise SpecificationError(f"data: sensor {s!r}: tube", tube, f"is not a tube of model {spec.name!r} ({names})")
    sensors = tuple(SensorSpec(name=s, tube=tube, x=x) for s, tube, x in zip(meas.sensors, meas.tube, meas.x))
    return spec.replace(sensors=sensors)


def _log(P):
    return np.log10(np.maximum(P, 1e-300))


def analysis_bins(f: np.ndarray) -> np.ndarray:
    """Frequencies used by every comparison: 0 < f < f_Nyquist (DC and Nyquist bins dropped)."""
    sel = np.ones(f.size, bool)
    sel[0] = sel[-1] = False
    return sel


# ----------------------------------------------------------------------------------------------
# Trial grids of r
# ----------------------------------------------------------------------------------------------


def _sig6(values) -> np.ndarray:
    """Values to 6 significant digits (stable, readable grid coordinates)."""
    return np.array([float(f"{float(v):.6g}") for v in values])


def r_coarse_grid(start, points: int, step: float) -> list[np.ndarray]:
    """Per component of r: ``points`` values ``step`` decades apart, centred on ``start``."""
    k = np.arange(points) - (points - 1) / 2.0
    return [_sig6(float(v) * 10.0 ** (step * k)) for v in start]


def r_fine_grid(centre, points: int, span: float) -> list[np.ndarray]:
    """Per component of r: ``points`` values over ± ``span`` decades around ``centre``."""
    u = np.linspace(-span, span, points)
    return [_sig6(float(v) * 10.0**u) for v in centre]


def grid_minimum(distance: np.ndarray, axes, refine: bool = True) -> tuple[tuple[float, ...], tuple[int, ...], bool]:
    """Minimum of a distance over a grid of r (one axis per component, log-spaced values).

    Returns (r_opt, index of the discrete minimum, at_boundary). With ``refine``, each component
    is moved to the vertex of the parabola in log10 r through the minimum and its two neighbours
    along that axis (kept within them); at a grid end the grid value is kept.
    """
    d = np.asarray(distance, dtype=float)
    idx = tuple(int(i) for i in np.unravel_index(int(np.nanargmin(d)), d.shape))
    out, boundary = [], False
    for a, values in enumerate(axes):
        values = np.asarray(values, dtype=float)
        i = idx[a]
        x = np.log10(values)
        xv = x[i]
        if values.size > 1 and i in (0, values.size - 1):
            boundary = True
        if refine and 0 < i < values.size - 1:
            line = d[idx[:a] + (slice(None),) + idx[a + 1:]]
            x0, x1, x2 = x[i - 1: i + 2]
            y0, y1, y2 = line[i - 1: i + 2]
            den = (x1 - x0) * (y1 - y2) - (x1 - x2) * (y1 - y0)
            if den != 0 and np.isfinite(den):
                num = (x1 - x0) ** 2 * (y1 - y2) - (x1 - x2) ** 2 * (y1 - y0)
                xv = float(np.clip(x1 - 0.5 * num / den, x0, x2))
        out.append(float(10.0**xv))
    return tuple(out), idx, boundary


def r_distance(target: np.ndarray, P: np.ndarray, f: np.ndarray, band_hz: float) -> tuple[float, float]:
    """Log-spectral distance (decades²) of model auto-PSD P (F, m) to ``target`` and the mean log
    offset (decades) over sensors and 0 < f ≤ band."""
    sel = analysis_bins(f) & (f <= band_hz)
    diff = _log(target[sel]) - _log(P[sel])
    return float(np.mean(diff**2)), float(np.mean(diff))


def level_free_distance(target, P, sel) -> tuple[float, float]:
    """Level-free log distance (decades²) and the log offset (decades) of model P to target."""
    diff = _log(target[sel]) - _log(P[sel])
    off = float(np.mean(diff))
    return float(np.mean((diff - off) ** 2)), off


def scaled_r(r, offset) -> tuple[float, ...]:
    """r moved by a log offset of the response PSD (linear-model level step)."""
    return tuple(float(v) * 10.0**offset for v in r)


# ----------------------------------------------------------------------------------------------
# δ_F: maximum likelihood of J_s
# ----------------------------------------------------------------------------------------------


def delta_f_identification(samples: xr.DataArray, observations, m: int, settings: DiagnoseSettings) -> dict:
    """δ_F by maximum likelihood of J_s (module docstring, step 2), as plain values.

    ``samples``: J_s (delta_F, realisation) Monte Carlo with common random numbers across δ_F;
    ``observations``: the data's J_s, one per fitting block. Returns ``delta_F`` (parabola-refined
    argmax), ``delta_F_used`` (by the band: the argmax or ``delta_f_fallback``, see the module
    docstring) and ``used_reason`` ('' for the argmax), ``delta_F_std`` (bootstrap over realisations), ``delta_F_std_observations``
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
        "delta_F": opt,
        "delta_F_used": float(used),
        "used_reason": reason,
        "delta_F_std": float(std_mc) if np.isfinite(std_mc) else None,
        "delta_F_std_observations": std_obs,
        "grid": [float(v) for v in grid],
        "log_likelihood": [float(v) for v in rel],
        "likelihood": [float(v) for v in np.exp(rel)],
        "flat": flat,
        "identified": identified,
        "at_boundary": at_boundary,
        "J_s_observed": [float(v) for v in obs],
        "n_realisations": int(samples.sizes["realisation"]),
        "note": note,
    }


# ----------------------------------------------------------------------------------------------
# Band, residual, error
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ModelBand:
    """Monte Carlo confidence band of the held-out PSD: ``samples`` (R, F, m) m²/Hz, ``lower``,
    ``upper``, ``median`` (F, m), ``stats`` (R, m, 3) time statistics, ``null`` (R,) leave-one-out
    errors of the realisations themselves (decades)."""

    samples: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    median: np.ndarray
    stats: np.ndarray
    null: np.ndarray

    @classmethod
    def from_samples(cls, P, stats, f, level: float) -> "ModelBand":
        """The band, median and leave-one-out null of realisations P (R, F, m) on frequencies f."""
        P = np.asarray(P, dtype=float)
        lo, hi = _quantiles(P, level)
        null = np.empty(P.shape[0])
        for i in range(P.shape[0]):
            l_i, h_i = _quantiles(np.delete(P, i, axis=0), level)
            null[i] = held_out_error(P[i], l_i, h_i, f)
        return cls(samples=P, lower=lo, upper=hi, median=np.median(P, axis=0), stats=np.asarray(stats, float), null=null)

    def threshold(self, settings: DiagnoseSettings) -> float:
        """The `none` threshold: the null's ``null_quantile`` quantile × ``null_margin`` (decades)."""
        return float(np.quantile(self.null, settings.null_quantile) * settings.null_margin)


def _quantiles(samples, level):
    lo, hi = np.quantile(samples, [(1 - level) / 2, (1 + level) / 2], axis=0)
    return lo, hi


def band_residual(P, lower, upper) -> np.ndarray:
    """d = log10(P/upper) above the band, log10(P/lower) below it, 0 inside (decades)."""
    lp = _log(P)
    return np.where(lp > _log(upper), lp - _log(upper), np.where(lp < _log(lower), lp - _log(lower), 0.0))


def held_out_error(P, lower, upper, f) -> float:
    """The error metric (see :data:`ERROR_METRIC`), decades."""
    sel = analysis_bins(f)
    d = band_residual(P, lower, upper)[sel]
    return float(np.sqrt(np.mean(d**2)))


def model_band(spec: BundleSpec, r, effects, meas: MeasuredSpectra, settings: DiagnoseSettings,
               load_dispersion: float = 0.0) -> ModelBand:
    """The stochastic model's band over ``realisations`` simulations shaped like the held-out set,
    computed in this process (the pipeline runs the same simulations as runner tasks)."""
    P, stats = simulate_blocks(spec, r, effects, meas, meas.n_held_out_blocks, range(settings.realisations),
                               settings, stochastic=True, load_dispersion=load_dispersion)
    return ModelBand.from_samples(P, stats, meas.frequency, settings.level)


# ----------------------------------------------------------------------------------------------
# Context shared by the pipeline's stages and tasks
# ----------------------------------------------------------------------------------------------


def data_hash(data: xr.Dataset) -> str:
    """SHA-256 of a validated record's content: time, displacement (time × sensor), sensor names,
    positions and tubes (independent of the file format and of attributes)."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(data["time"].values, dtype="<f8").tobytes())
    h.update(np.ascontiguousarray(data["displacement"].transpose("time", "sensor").values, dtype="<f8").tobytes())
    h.update(json.dumps([[str(s) for s in data["sensor"].values], [float(v) for v in data["x"].values],
                         [str(v) for v in data["tube"].values]]).encode())
    return h.hexdigest()


@dataclass(frozen=True)
class DiagnoseContext:
    """What every stage and task of a diagnosis needs: ``settings``, the declared model ``spec0``
    and ``spec`` (with the data's sensors), the spectra ``meas``, the load dimension ``m`` and
    the observed J_s per fitting block ``j_s_observed`` [(m²/Hz)² rad/s]."""

    settings: DiagnoseSettings
    spec0: BundleSpec
    spec: BundleSpec
    meas: MeasuredSpectra
    m: int
    j_s_observed: np.ndarray

    @property
    def delta_f_grid(self) -> tuple[float, ...]:
        return self.settings.delta_f_grid or default_delta_f_grid(self.m)

    @property
    def tube(self) -> str:
        """The tube of the fixed-location candidates (the non-linear tube if it carries sensors)."""
        sensor_tubes = sorted(set(self.meas.tube))
        return self.spec.a_tube if self.spec.a_tube in sensor_tubes else sensor_tubes[0]


def _context(data: xr.Dataset, spec0: BundleSpec, settings: DiagnoseSettings) -> DiagnoseContext:
    dt = float(data.attrs.get("dt", np.diff(data["time"].values[:2])[0]))
    if 1.0 / (2.0 * dt) < spec0.band_hz:
        raise SpecificationError("data dt", dt, f"the Nyquist frequency 1/(2 dt) must reach the model band {spec0.band_hz} Hz")
    meas = measured_spectra(data, settings)
    spec = _spec_for(spec0, meas)
    m = load_dimension(spec, settings)
    dmax = delta_max(m)
    for name in ("load_dispersion", "delta_f_fallback"):
        v = getattr(settings, name)
        if v is not None and v >= dmax:
            raise SpecificationError(f"settings.{name}", v, f"must be < δ_max = {dmax:.4f} for the {settings.load} load "
                                     f"(SG+ of size m = {m})")
    grid = settings.delta_f_grid or default_delta_f_grid(m)
    if max(grid) >= dmax:
        raise SpecificationError("settings.delta_f_grid", grid, f"must lie in (0, {dmax:.4f}) for the {settings.load} load (m = {m})")
    obs = j_s(meas.frequency, meas.fit_cross, band=spec.band_hz)
    return DiagnoseContext(settings=settings, spec0=spec0, spec=spec, meas=meas, m=m, j_s_observed=np.atleast_1d(obs))


_CONTEXTS: dict[tuple, DiagnoseContext] = {}


def load_context(data: str, data_sha256: str, model: str, settings: str) -> DiagnoseContext:
    """The context of a diagnosis from the pipeline's plain parameters (cached per process):
    ``data`` the path of the validated record, ``data_sha256`` its :func:`data_hash` (refused if
    the file no longer matches), ``model`` the declared model as JSON (``spec_to_dict``),
    ``settings`` :meth:`DiagnoseSettings.to_json`."""
    key = (data, data_sha256, model, settings)
    if key not in _CONTEXTS:
        from tubeid.measured.readers import read_measurements

        if not data:
            raise SpecificationError("parameters.data", data, "the pipeline needs the path of the record")
        spec0 = spec_from_dict(json.loads(model))
        ds = read_measurements(data, tubes={t.name: t.length for t in spec0.tubes})
        if data_hash(ds) != data_sha256:
            raise SpecificationError("data", data, f"its content changed since this diagnosis started (sha256 {data_sha256[:12]})")
        _CONTEXTS[key] = _context(ds, spec0, DiagnoseSettings.from_json(settings))
    return _CONTEXTS[key]


def effects_from_json(text: str) -> list:
    """Effects from their JSON list form (``effect_to_dict``)."""
    return [effect_from_dict(e, f"effects[{i}]") for i, e in enumerate(json.loads(text))]


def effects_to_json(effects) -> str:
    return json.dumps([effect_to_dict(e) for e in effects], sort_keys=True)


# ----------------------------------------------------------------------------------------------
# Candidates
# ----------------------------------------------------------------------------------------------


TONE_PROBE_N = 10.0  # N: amplitude of the probe simulation that scales a tone's first guess


def plan_candidates(ctx: DiagnoseContext, band: ModelBand) -> dict:
    """Error before, `none` rule, signatures and the candidates to fit, from the band before.

    Returns {"error", "threshold", "explained", "z" (m, 3), "signatures", "ranked", "fit" (names to
    fit, in rank order), "not_fitted" ({name: reason})}.
    """
    from tubeid.measured.effects_fit import CATALOG, signature_scores

    s, meas = ctx.settings, ctx.meas
    f = meas.frequency
    err = held_out_error(meas.held_out, band.lower, band.upper, f)
    threshold = band.threshold(s)
    z = (meas.fit_stats - band.stats.mean(axis=0)) / np.maximum(band.stats.std(axis=0, ddof=1), 1e-300)
    sig = signature_scores(f, meas.fit, band.lower, band.upper, band.median, z, analysis_bins(f),
                           np.asarray(meas.x), ctx.spec.tube(ctx.tube).damping_ratio)
    ranked = sorted(CATALOG, key=lambda n: -sig[n]["score"])
    explained = err <= threshold
    fit, not_fitted = [], {}
    if not explained:
        top = sig[ranked[0]]["score"]
        for name in ranked[: s.n_fit]:
            if sig[name]["score"] < s.min_relative_score * top or sig[name]["score"] <= 0:
                not_fitted[name] = "signature too weak"
            else:
                fit.append(name)
    return {"error": err, "threshold": threshold, "explained": bool(explained), "z": z, "signatures": sig,
            "ranked": ranked, "fit": fit, "not_fitted": not_fitted}


def tone_probe(ctx: DiagnoseContext, frequency_hz: float) -> Tone:
    return Tone(frequency_hz=frequency_hz, amplitude=TONE_PROBE_N, tube=ctx.tube, x=ctx.settings.load_x)


def tone_amplitudes(ctx: DiagnoseContext, frequency_hz: float, P_baseline, P_probe) -> np.ndarray:
    """Amplitude grid of a tone from the probe (mean-model PSDs without and with a TONE_PROBE_N
    tone, common random numbers): the excess power the probe adds within ±2 bins of f0 against
    the measured excess over the baseline; a line's power is ∝ A² in a linear model, so
    A0 = probe · √(measured / probe excess); grid A0 · 10^[−0.5, 0.5] (``grid_points``)."""
    f, meas = ctx.meas.frequency, ctx.meas
    k = int(np.argmin(np.abs(f - frequency_hz)))
    win = slice(max(1, k - 2), k + 3)
    P0, P1 = np.asarray(P_baseline), np.asarray(P_probe)
    added = float(np.sum(np.clip(P1[win] - P0[win], 0, None)))
    wanted = float(np.sum(np.clip(meas.fit[win] - P0[win], 0, None)))
    a0 = TONE_PROBE_N * math.sqrt(wanted / added) if added > 0 and wanted > 0 else TONE_PROBE_N
    return a0 * 10.0 ** np.linspace(-0.5, 0.5, ctx.settings.grid_points)


# ----------------------------------------------------------------------------------------------
# The loop
# ----------------------------------------------------------------------------------------------


@dataclass
class Diagnosis:
    """Result of :func:`diagnose`. ``report`` is what report.json holds; ``frequency``, ``measured``
    (held-out PSD, (F, m)), ``before``/``after`` (:class:`ModelBand`) feed the figure; ``store``:
    the pipeline store (None when it lived in a temporary directory)."""

    report: dict
    frequency: np.ndarray
    measured: np.ndarray
    sensors: tuple
    before: ModelBand
    after: ModelBand | None
    store: Path | None = None

    @property
    def effect(self) -> str:
        return self.report["effect"]

    def write(self, out) -> Path:
        """Write report.json, report.md, residual.png (and delta_f.png when δ_F was identified)
        into directory ``out`` (created)."""
        from tubeid.measured.diagnose_report import write_files

        return write_files(self, out)


def _resolve_data(data, spec0: BundleSpec) -> xr.Dataset:
    tubes = {t.name: t.length for t in spec0.tubes}
    if isinstance(data, xr.Dataset):
        return validate_measurements(data, tubes=tubes)
    from tubeid.measured.readers import read_measurements

    return read_measurements(data, tubes=tubes)


def _check_out(store: Path, key: str) -> None:
    """Refuse a store in ``out`` made from other data, model or settings (before any work)."""
    if not store.exists():
        return
    from tubeid.runner.store import read_attrs

    try:
        attrs = read_attrs(store)
    except Exception:
        raise SpecificationError("out", str(store.parent), f"{store.name} exists but is not a diagnosis store; "
                                 "choose another --out or use --overwrite") from None
    if attrs.get("study_hash") != key:
        raise SpecificationError(
            "out", str(store.parent),
            f"holds a diagnosis of other data, model or settings ({store.name}, hash {str(attrs.get('study_hash'))[:12]} "
            f"vs {key[:12]} now): refusing to mix them; choose another --out or use --overwrite")


def diagnose(data, model="paper-simplified", settings: DiagnoseSettings = DiagnoseSettings(), *, out=None,
             workers: int | None = 0, scheduler: str | None = None, overwrite: bool = False,
             progress: bool | None = False, quiet: bool = True) -> Diagnosis:
    """Run the loop of the module docstring on ``data`` (a measurement Dataset or a path readable by
    :func:`tubeid.measured.read_measurements`) for the declared ``model`` (built-in name, spec file
    or :class:`BundleSpec`). Returns a :class:`Diagnosis`.

    ``out``: directory of the pipeline store ``diagnose.zarr``, of the validated record it reads
    (``data-<sha256[:16]>.nc``) and of the report files (written when ``out`` is given; else a
    temporary directory is used and removed). Running again with the same ``out``, data, model and
    settings resumes or reuses the store; other data, model or settings are refused unless
    ``overwrite``. ``workers``: 0 (default) runs every task in this process; N > 0 an embedded
    LocalCluster of N single-threaded workers; None: the runner's default (configuration, else
    one per core) unless ``scheduler`` (an existing dask scheduler's address) is given.
    """
    from tubeid.runner.execute import run
    from tubeid.runner.study import study_hash

    if not isinstance(settings, DiagnoseSettings):
        raise SpecificationError("settings", type(settings).__name__, "must be a DiagnoseSettings")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 0):
        raise SpecificationError("workers", workers, "must be a non-negative integer")
    spec0 = resolve_spec(model)
    if spec0.effects:
        raise SpecificationError("model.effects", spec0.effects, "diagnose a model without carried effects")
    data = _resolve_data(data, spec0)
    ctx = _context(data, spec0, settings)  # everything that can be refused, before any run
    h = data_hash(data)

    tmp = tempfile.TemporaryDirectory(prefix="tubeid-diagnose-") if out is None else None
    try:
        outdir = Path(tmp.name if tmp is not None else out)
        if outdir.exists() and not outdir.is_dir():
            raise SpecificationError("out", str(outdir), "exists and is not a directory")
        outdir.mkdir(parents=True, exist_ok=True)
        store = outdir / "diagnose.zarr"
        data_path = (outdir / f"data-{h[:16]}.nc").resolve()
        overrides = {"data": str(data_path), "data_sha256": h, "model": json.dumps(spec_to_dict(spec0), sort_keys=True),
                     "settings": settings.to_json()}
        if not overwrite:
            _check_out(store, study_hash(PIPELINE_FILE.read_text(), overrides))
        else:
            for old in outdir.glob("data-*.nc"):
                if old != data_path:
                    old.unlink()
        if not data_path.exists():
            from tubeid.measured.readers import write_measurements

            part = data_path.with_name(f".{data_path.name}.{os.getpid()}.part")
            write_measurements(data, part, format="netcdf")
            os.replace(part, data_path)
        _CONTEXTS[(overrides["data"], h, overrides["model"], overrides["settings"])] = ctx
        report = run(PIPELINE_FILE, store, workers=workers, scheduler=scheduler, overrides=overrides,
                     overwrite=overwrite, progress=progress, quiet=quiet)
        diagnosis = assemble(store, ctx)
        diagnosis.report["runner"] = {
            "store": str(store.resolve()) if tmp is None else None, "workers": report.workers,
            "tasks_computed": report.computed, "tasks_reused": report.skipped,
            "stages": {n: {"computed": r.computed, "reused": r.skipped, "seconds": round(r.wall, 3)}
                       for n, r in report.stages.items()}}
        if tmp is None:
            diagnosis.store = store.resolve()
            diagnosis.write(outdir)
        return diagnosis
    finally:
        if tmp is not None:
            tmp.cleanup()


# ----------------------------------------------------------------------------------------------
# Report from the store
# ----------------------------------------------------------------------------------------------


def skipped(ds: xr.Dataset) -> bool:
    """Whether a pipeline stage had nothing to compute (its only axis is ``skipped``)."""
    return "skipped" in ds.dims


def stage_band(ctx: DiagnoseContext, ds: xr.Dataset) -> ModelBand:
    """The :class:`ModelBand` of a stored band stage (psd (realisation, frequency, sensor))."""
    return ModelBand.from_samples(ds["psd"].transpose("realisation", "frequency", "sensor").values,
                                  ds["stats"].transpose("realisation", "sensor", "statistic").values,
                                  ctx.meas.frequency, ctx.settings.level)


def best_trials(ctx: DiagnoseContext, ds: xr.Dataset, trials: list) -> dict:
    """Best trial per candidate of a stored candidates stage: {name: (effect, offset, distance, n)}."""
    d = ds["distance"].values
    off = ds["offset"].values
    out = {}
    for name in dict.fromkeys(t["candidate"] for t in trials):
        idx = [i for i, t in enumerate(trials) if t["candidate"] == name]
        k = min(idx, key=lambda i: d[i])
        out[name] = (effect_from_dict(trials[k]["effect"]), float(off[k]), float(d[k]), len(idx))
    return out


def _open(store, name) -> xr.Dataset:
    from tubeid.runner.store import open_results

    return open_results(store, name).load()


def assemble(store, ctx: DiagnoseContext) -> Diagnosis:
    """Build the :class:`Diagnosis` from a complete pipeline store."""
    from tubeid.measured.effects_fit import PARAMETER_COUNT, effect_parameters

    s, meas, spec0 = ctx.settings, ctx.meas, ctx.spec0
    f = meas.frequency
    st = {n: _open(store, n) for n in ("load_r", "load_r_fine", "load_delta_f", "band", "candidates",
                                       "candidate_bands", "load_r_after", "band_after")}
    r_before = tuple(st["load_r_fine"].attrs["r_opt"])
    dF = st["load_delta_f"].attrs
    before = stage_band(ctx, st["band"])
    plan = plan_candidates(ctx, before)
    sig, ranked = plan["signatures"], plan["ranked"]
    candidates = {n: {"signature_score": round(sig[n]["score"], 4), "estimate": sig[n]["estimate"],
                      "parameters": PARAMETER_COUNT[n]} for n in ranked}
    for n, why in plan["not_fitted"].items():
        candidates[n]["not_fitted"] = why
    chosen, after, err_after, thr_after, r_after = None, None, plan["error"], plan["threshold"], r_before
    if not skipped(st["candidates"]):
        trials = json.loads(json.loads(st["candidates"].attrs["parameters"])["trials"])
        best = best_trials(ctx, st["candidates"], trials)
        cb = st["candidate_bands"].attrs
        for name, err_c, pen in zip(cb["candidate_names"], cb["held_out_errors"], cb["penalised_errors"]):
            effect, off, dist, n = best[name]
            candidates[name].update({"fitted": effect_parameters(effect), "held_out_error": err_c,
                                     "penalised_error": pen, "trials": n, "fit_distance": dist,
                                     "r": list(scaled_r(r_before, off))})
        if cb["chosen"]:
            chosen = best[cb["chosen"]][0]
            r_after = tuple(st["load_r_after"].attrs["r_opt"])
            after = stage_band(ctx, st["band_after"])
            err_after = float(st["band_after"].attrs["error"])
            thr_after = float(st["band_after"].attrs["null_threshold"])
    for n in candidates:
        candidates[n]["score"] = candidates[n].get("penalised_error", None)
    z = plan["z"]
    units_r = ["N^2/Hz"] if s.load == "distributed" else ["N^2/Hz", "(N m)^2/Hz"]
    from tubeid.identification.loads import JS_UNITS

    load = {"model": s.load, "r_before": list(r_before), "r_after": list(r_after), "units": units_r,
            "r_trials": int(st["load_r"].sizes.get("r1", 0) * st["load_r"].sizes.get("r2", 1)
                            + st["load_r_fine"].sizes.get("r1", 0) * st["load_r_fine"].sizes.get("r2", 1)),
            "r_fine_at_boundary": bool(st["load_r_fine"].attrs["at_boundary"]),
            "delta": s.delta, "delta_F": float(dF["delta_F"]), "delta_F_given": bool(dF["delta_F_given"]),
            "load_dispersion": float(dF["delta_F_used"]), "m": ctx.m}
    if not dF["delta_F_given"]:
        load.update({
            "delta_F_std": dF.get("delta_F_std"), "delta_F_std_observations": dF.get("delta_F_std_observations"),
            "delta_F_flat": bool(dF["flat"]), "delta_F_identified": bool(dF["identified"]),
            "delta_F_at_boundary": bool(dF["at_boundary"]), "delta_F_note": dF["note"],
            "load_dispersion_reason": dF["used_reason"] or "the maximum-likelihood δ_F",
            "delta_F_likelihood": {"grid": dF["grid"], "log_likelihood": dF["log_likelihood"], "likelihood": dF["likelihood"],
                                   "n_realisations": dF["n_realisations"], "n_observations": len(dF["J_s_observed"])},
            "J_s_observed": dF["J_s_observed"], "J_s_units": JS_UNITS,
            "delta_F_method": ("maximum likelihood of J_s = integral of ||S_Z||_F^2 over the band, one observation per "
                               "fitting block (treated as independent), Gaussian KDE (Silverman) of the Monte Carlo J_s at "
                               "each grid value; std: bootstrap over realisations / over observations")})
    report = {
        "effect": "none" if chosen is None else chosen.name,
        "parameters": {} if chosen is None else effect_parameters(chosen),
        "error_before": plan["error"],
        "error_after": err_after,
        "metric": ERROR_METRIC + f"; {meas.n_held_out_blocks} held-out blocks of {meas.block_samples * meas.dt:.4g} s "
                  f"not used for fitting; band level {s.level}, {s.realisations} realisations.",
        "explained_before": plan["explained"],
        "explained_after": bool(err_after <= thr_after),
        "null_threshold": plan["threshold"],
        "null_threshold_after": thr_after,
        "candidates": [dict(name=n, **candidates[n]) for n in ranked],
        "score_rule": ("candidates are ranked by signature_score (fraction of the residual energy their cheap "
                       "signature removes); the fitted ones are scored by held-out error / (1 - penalty)^k, k = "
                       f"parameters, penalty = {s.penalty}; the lowest below error_before wins"),
        "model": spec0.name,
        "load": load,
        "sensors": [{"name": n, "tube": t, "x": x} for n, t, x in zip(meas.sensors, meas.tube, meas.x)],
        "time_statistics_z": {n: dict(zip(("rms", "skewness", "excess_kurtosis"), map(float, z[j])))
                              for j, n in enumerate(meas.sensors)},
        "settings": json.loads(s.to_json()),
    }
    return Diagnosis(report=report, frequency=f, measured=meas.held_out, sensors=meas.sensors, before=before, after=after)
