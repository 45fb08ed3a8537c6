"""Records of the declared model (with effects) on the data's sensors, sampling and block layout."""

from __future__ import annotations

import math

import numpy as np

from tubeid.diagnose._settings import DiagnoseSettings
from tubeid.diagnose._spectra import MeasuredSpectra, block_observations
from tubeid.dynamics.response import ResponseSettings, simulate_responses
from tubeid.errors import SpecificationError
from tubeid.mechanics.effects import apply_effects
from tubeid.mechanics.reduction import reduce
from tubeid.mechanics.spec import BundleSpec, SensorSpec, held_sensor_rule
from tubeid.uncertainty.loads import coherent_forces, force_and_moment
from tubeid.uncertainty.random_matrices import Dispersion

__all__ = ["load_spectrum", "load_dimension", "spec_for", "simulate_series", "simulate_blocks"]


def load_spectrum(spec: BundleSpec, r, settings: DiagnoseSettings):
    """The identification load with parameters r (see :data:`~tubeid.diagnose.LOAD_MODELS`)."""
    tube = spec.a_tube or spec.tubes[0].name
    if settings.load == "force_and_moment":
        return force_and_moment(float(r[0]), float(r[1]), x=settings.load_x, band=spec.band_hz, tube=tube)
    xs = [p.x for p in spec.loads if p.kind == "force" and p.tube == tube]
    if not xs:
        raise SpecificationError("model.loads", spec.loads, f"the distributed load needs force points on tube {tube!r}")
    return coherent_forces(xs, level=float(r[0]), band=spec.band_hz, correlation_length=settings.correlation_length,
                           tube=tube)


def load_dimension(spec: BundleSpec, settings: DiagnoseSettings) -> int:
    """m, the size of the load's SG+ matrix G_m (the number of load components)."""
    return len(load_spectrum(spec, settings.start_r, settings).names)


def spec_for(spec: BundleSpec, sensors, tubes, xs) -> BundleSpec:
    """The declared model with the data's sensors (names, tubes, positions [m])."""
    names = [t.name for t in spec.tubes]
    for s, tube, x in zip(sensors, tubes, xs):
        if tube not in names:
            raise SpecificationError(f"data: sensor {s!r}: tube", tube, f"is not a tube of model {spec.name!r} ({names})")
        t = spec.tubes[names.index(tube)]
        if t.held_end(float(x)) is not None:  # its model displacement, and PSD, is zero: the diagnosis cannot run
            raise SpecificationError(f"data: sensor {s!r}: x", float(x),
                                     f"in model {spec.name!r}: " + held_sensor_rule(s, t, float(x)))
    return spec.replace(sensors=tuple(SensorSpec(name=s, tube=t, x=x) for s, t, x in zip(sensors, tubes, xs)))


def _dt_load(dt: float, bound: float) -> float:
    k = max(1, math.ceil(dt / bound - 1e-9))
    return dt / k


def simulate_series(spec: BundleSpec, r, effects, meas: MeasuredSpectra, n_samples: int, realisations,
                    settings: DiagnoseSettings, *, delta: float = 0.0, load_dispersion: float = 0.0,
                    rngs=None, contact: bool = False):
    """Records (R, n_samples, m) [m] at the data's sensors and sampling, transient discarded (and,
    with ``contact``, the fraction of time each realisation's stops are closed, mean over the
    stops (R,); 0 without stops).

    ``delta``, ``load_dispersion``: dispersions of B's stiffness and of the load spectrum (0 and 0:
    the mean model). ``rngs``: one generator per realisation (the runner's; a fresh generator
    object per call for common random numbers), else the streams ``rng_for(settings.seed,
    "response", realisation)``.
    """
    full = apply_effects(spec, effects)
    model = reduce(full)
    load = load_spectrum(full, r, settings)
    dt = meas.dt
    duration = settings.discard + (n_samples + 2) * dt
    rs = ResponseSettings(duration=duration, dt_load=_dt_load(dt, settings.dt_load_max), output_dt=dt,
                          discard=settings.discard,
                          segment_seconds=min(settings.segment_seconds, duration - settings.discard), keep="series-only")
    disp = Dispersion(stiffness=delta) if delta > 0 else Dispersion()
    kw = {"seed": settings.seed} if rngs is None else {"rngs": list(rngs)}
    ds = simulate_responses(model, load, realisations, dispersion=disp, load_dispersion=float(load_dispersion),
                            settings=rs, **kw)
    y = ds["displacement"].transpose("realisation", "time", "sensor").values[:, :n_samples, :]
    if not contact:
        return y
    cf = ds["contact_fraction"].values
    return y, (cf.mean(axis=1) if cf.size else np.zeros(y.shape[0]))


def simulate_blocks(spec: BundleSpec, r, effects, meas: MeasuredSpectra, n_blocks: int, realisations,
                    settings: DiagnoseSettings, *, delta: float = 0.0, load_dispersion: float = 0.0,
                    rngs=None, observed: tuple[str, ...] = ()) -> dict:
    """Model records cut like the data, per realisation (R of them), each quantity averaged over
    ``n_blocks`` blocks of the data's block length (:func:`~tubeid.diagnose._spectra.block_observations`):
    ``psd`` (R, F, m) [m²/Hz], ``stats`` (R, m, 3) and ``contact`` (R,), the stops' contact fraction
    (see :func:`simulate_series`); and those of ``fine`` (R, F', m) [m²/Hz] at the data's fine
    segment and ``residual`` (R, F, m) [m²/Hz] that ``observed`` names (what the test's statistics read).

    The mean model (``delta`` = ``load_dispersion`` = 0) has one structure and one load spectrum:
    its R "realisations" are then consecutive stretches of one record of the first realisation's
    streams (the same estimator scatter, one set of solver tables).
    """
    realisations = np.atleast_1d(np.asarray(realisations, dtype=int))
    R = realisations.size
    mean_model = delta == 0 and load_dispersion == 0
    if mean_model:
        n_blocks, realisations = n_blocks * R, realisations[:1]
        rngs = None if rngs is None else list(rngs)[:1]
    y, cf = simulate_series(spec, r, effects, meas, n_blocks * meas.block_samples, realisations, settings, delta=delta,
                            load_dispersion=load_dispersion, rngs=rngs, contact=True)
    if mean_model:
        n_blocks //= R
        y = y.reshape(R, n_blocks * meas.block_samples, y.shape[2])
        cf = np.repeat(cf, R)
    blocks = y.reshape(y.shape[0], n_blocks, meas.block_samples, y.shape[2])
    out = block_observations(blocks, meas.dt, settings.segment_seconds, meas.fine_seconds if observed else None,
                             residual="residual" in observed, f_max=settings.max_frequency_hz)
    return {k: out[k] for k in ("psd", "stats", *observed)} | {"contact": cf}
