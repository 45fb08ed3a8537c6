"""Random responses of the stochastic non-linear model: what one Monte Carlo realisation computes.

Realisation r of the stochastic simplified model (paper §2.5, §3, MODEL.md §3.5):

1. random reduced matrices of subsystem B (SE+, dispersions ``Dispersion``), germs from stream 0;
2. random load spectrum S_F = L_F* G_m L_F, G_m ∈ SG+(m, δ_F) (one per realisation), stream 1;
3. a Gaussian load history with PSD S_F (FFT spectral representation), stream 2;
4. the non-linear transient response with the elastic stops (``tubeid.dynamics.solver``), plus
   the specification's carried effects: ``tone`` forces (random phase, stream 3) and
   ``sensor_noise`` (white, added to the sampled responses, stream 3);
5. by default only the response PSD matrix at the sensors (Welch: Hann window, 50 % overlap,
   ``segment_seconds`` segments; two-sided per Hz) and summary statistics are kept.

The four streams of realisation r are children (``Generator.spawn``) of one generator keyed by
(seed, r) — or of the generator the runner gives for that realisation — so a realisation is the
same whatever its batch, and grids over δ, r or δ_F share common random numbers.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import xarray as xr
from numpy.typing import ArrayLike

from tubeid._validation import allocation, non_negative, on_tube, one_of, positive, real
from tubeid._validation import seed as _seed
from tubeid.dynamics.solver import METHODS, Stop, check_substeps, simulate
from tubeid.dynamics.spectra import psd_matrix
from tubeid.errors import Described, SpecificationError
from tubeid.mechanics.reduction import ReducedModel
from tubeid.mechanics.spec import LoadPoint, held_load_rule
from tubeid.seeds import rng_for
from tubeid.uncertainty.loads import LoadSpectrum, randomised
from tubeid.uncertainty.processes import gaussian_loads
from tubeid.uncertainty.random_matrices import Dispersion, _check_delta, sg_plus
from tubeid.uncertainty.random_models import germs_from_rngs, random_subsystem, realisation_indices

__all__ = ["ResponseSettings", "realisation_streams", "simulate_responses"]


#: What a response realisation keeps (``ResponseSettings.keep``).
KEEP = ("psd", "series", "series-only")


@dataclass(frozen=True)
class ResponseSettings:
    """Time and spectral settings of a response realisation. Validated when made, immutable.

    Parameters
    ----------
    duration : float
        Simulated time [s] (220 s as the paper).
    dt_load : float
        Load sampling [s], at most ``duration`` (the solver reads the load as piecewise linear between samples; 2 ms:
        Nyquist 250 Hz for the 100 Hz band, the sinc⁴ pre-compensation of ``gaussian_loads`` (x1.31
        at 100 Hz) gives the interpolant the target PSD in band, its images above 400 Hz carry 0.09 %
        of the load power; tones are pre-compensated by 1/sinc²(f0 dt_load) likewise; the
        integration step is set by f_max, not by dt_load).
    output_dt : float
        Response sampling [s] (3 ms as the paper), at most duration − discard; unless ``keep`` is
        ``"series-only"``, its Nyquist frequency 1/(2 output_dt) must reach the load's band
        (checked by ``simulate_responses``).
    discard : float
        Initial transient removed [s], in [0, duration).
    segment_seconds : float
        Welch segment [s] (Hann window, 50 % overlap), at most the kept record (duration − discard)
        and at least 2 output samples (unless ``keep`` is ``"series-only"``).
    method : str
        The solver's method, a key of ``tubeid.dynamics.solver.METHODS`` (``tubeid.dynamics.simulate``).
    keep : str
        ``"psd"`` (the PSD and statistics only), ``"series"`` (also the displacement series) or
        ``"series-only"`` (the series and statistics, no PSD: for a caller that estimates its own).
    """

    duration: float = 220.0
    dt_load: float = 2e-3
    output_dt: float = 3e-3
    discard: float = 2.0
    segment_seconds: float = 8.0
    method: str = "exact"
    keep: str = "psd"

    def __post_init__(self) -> None:
        # checked, not converted: the values stay as given (they are recorded in the results' attributes)
        for f in ("duration", "dt_load", "output_dt", "segment_seconds"):
            positive(f"settings.{f}", getattr(self, f), "s")
        real("settings.discard", self.discard, unit="s")
        if not (0 <= self.discard < self.duration):
            raise SpecificationError("settings.discard", self.discard, f"must be in [0, duration = {self.duration}) s")
        if self.segment_seconds > self.duration - self.discard:
            raise SpecificationError("settings.segment_seconds", self.segment_seconds, "must not exceed duration − discard")
        if self.keep not in KEEP:
            raise SpecificationError("settings.keep", self.keep, f"must be one of {KEEP}")
        one_of("settings.method", self.method, METHODS)
        if self.dt_load > self.duration:
            raise SpecificationError("settings.dt_load", self.dt_load, f"must not exceed duration = {self.duration} s "
                                     "(a load record of at least 2 samples)")
        if self.output_dt > self.duration - self.discard:
            raise SpecificationError("settings.output_dt", self.output_dt,
                                     f"must not exceed duration − discard = {self.duration - self.discard:g} s")
        if self.keep != "series-only":  # psd_matrix's rule, before the run instead of after it
            import math

            from tubeid.dynamics.spectra import _segment_length

            n_t = int(math.floor(self.duration / self.output_dt + 1e-9)) + 1 - \
                int(math.ceil(self.discard / self.output_dt - 1e-9))
            try:
                _segment_length(self.segment_seconds, self.output_dt, n_t)
            except SpecificationError as exc:
                raise SpecificationError("settings.segment_seconds", self.segment_seconds,
                                         exc.rule.replace("dt = ", "output_dt = ")) from None


def realisation_streams(seed: int | None, realisation: int,
                        rng: np.random.Generator | None = None) -> list[np.random.Generator]:
    """The four independent generators of one realisation.

    Parameters
    ----------
    seed : int or None
        Study seed; the base generator is ``rng_for(seed, "response", realisation)``.
    realisation : int
        Realisation index.
    rng : numpy.random.Generator, optional
        Base generator to use instead (e.g. the runner's for this realisation).

    Returns
    -------
    list of numpy.random.Generator
        Children of the base generator for the model, the load spectrum, the load process and
        the effects, in that order.
    """
    base = rng if rng is not None else rng_for(seed, "response", int(realisation))
    return base.spawn(4)


def _generators(field: str, gens, count: int) -> list[np.random.Generator] | None:
    """``gens`` as a list of ``count`` generators (None stays None), else refused naming ``field``."""
    if gens is None:
        return None
    rule = f"must be a sequence of numpy.random.Generator, one per realisation ({count})"
    if isinstance(gens, (np.random.Generator, str, bytes)):
        raise SpecificationError(field, Described(type(gens).__name__), rule)
    try:
        gens = list(gens)
    except TypeError:
        raise SpecificationError(field, Described(type(gens).__name__), rule) from None
    if len(gens) != count:
        raise SpecificationError(field, Described(f"{len(gens)} generators"), rule)
    for i, g in enumerate(gens):
        if not isinstance(g, np.random.Generator):
            raise SpecificationError(f"{field}[{i}]", Described(type(g).__name__), "must be a numpy.random.Generator")
    return gens


def _load_points(load: LoadSpectrum) -> tuple[LoadPoint, ...]:
    return tuple(LoadPoint(name=n, tube=load.tube, x=float(x), kind=k) for n, k, x in zip(load.names, load.kinds, load.x))


def simulate_responses(
    model: ReducedModel,
    load: LoadSpectrum,
    realisations: ArrayLike,
    *,
    seed: int | None = None,
    rngs: Sequence[np.random.Generator] | None = None,
    dispersion: Dispersion = Dispersion(),
    load_dispersion: float = 0.0,
    settings: ResponseSettings = ResponseSettings(),
    system_rngs: Sequence[np.random.Generator] | None = None,
) -> xr.Dataset:
    """Monte Carlo responses of the stochastic non-linear model at its sensors (module docstring).

    Parameters
    ----------
    model : ReducedModel
        The reduced (mean) model, with its stops, sensors and carried effects.
    load : LoadSpectrum
        The mean load spectrum, acting on the model's tube at its load positions (each within
        [0, length] of that tube: a load off the tube is refused, and so is a load on a degree of
        freedom a clamped or pinned end holds, see ``tubeid.mechanics.spec.held_load_rule``).
    realisations : array_like of int
        Realisation indices (R of them): distinct integers (not bools or floats; each keys its
        realisation's streams, a repeat would duplicate a realisation).
    seed : int, optional
        Study seed, an integer >= 0: realisation r draws from ``rng_for(seed, "response", r)``.
    rngs : sequence of numpy.random.Generator, optional
        One generator per realisation instead (e.g. the runner's); ``seed`` or ``rngs`` is required.
    dispersion : Dispersion
        SE+ dispersions of B's reduced matrices (default: the mean model).
    load_dispersion : float
        δ_F of the random load spectrum, >= 0 (0: the mean spectrum).
    settings : ResponseSettings
        Time and spectral settings.
    system_rngs : sequence of numpy.random.Generator, optional
        One generator per realisation for B's germs instead of the realisation's stream 0: give
        generators in the same state to realisations that must share one structure (several
        records of one system under independent loads). Consumed.

    Returns
    -------
    xarray.Dataset
        Over ``realisation``: ``psd`` (realisation, frequency, sensor, sensor_) two-sided PSD
        matrix [m²/Hz] (complex; not with ``keep="series-only"``), ``rms`` (realisation, sensor)
        [m], ``contact_fraction`` and ``contact_events`` (realisation, stop); with ``keep="series"``
        or ``"series-only"`` also ``displacement`` (realisation, time [s], sensor) [m]. Every
        variable and the ``time`` and ``frequency`` coordinates carry their ``units`` attribute
        where they have one.
    """
    realisations = realisation_indices(realisations)
    if rngs is None and seed is None:
        raise SpecificationError("seed", None, "give a seed or one generator per realisation")
    if seed is not None:
        _seed("seed", seed)
    if not isinstance(model, ReducedModel):
        raise SpecificationError("model", Described(type(model).__name__), "must be a ReducedModel (tubeid.mechanics.reduce)")
    if not isinstance(load, LoadSpectrum):
        raise SpecificationError("load", Described(type(load).__name__), "must be a LoadSpectrum (tubeid.uncertainty)")
    # every load on the model's tube, within [0, length]: checked before any work (the Hermite shape
    # functions would extrapolate a point off the tube into a large, meaningless load)
    tube_names = [t.name for t in model.spec.tubes]
    if load.tube not in tube_names:
        raise SpecificationError("load.tube", load.tube, f"no such tube in model {model.spec.name!r}; tubes are {tube_names}")
    for i, (name, kind, x) in enumerate(zip(load.names, load.kinds, load.x)):
        tube = model.spec.tube(load.tube)
        on_tube(f"load.x[{i}]", tube, x, f"load {name!r}")
        rule = held_load_rule(f"load {name!r}", tube, x, kind)  # a zero load column, silently
        if rule is not None:
            raise SpecificationError(f"load.x[{i}]", x, rule)
    if not isinstance(dispersion, Dispersion):
        raise SpecificationError("dispersion", dispersion, "must be a tubeid.uncertainty.Dispersion "
                                 "(e.g. Dispersion(stiffness=0.1))")
    non_negative("load_dispersion", load_dispersion)  # checked, not converted: recorded as given
    if load_dispersion != 0.0:
        _check_delta(load_dispersion, len(load.names), "load_dispersion")
    if not isinstance(settings, ResponseSettings):
        raise SpecificationError("settings", Described(type(settings).__name__), "must be a ResponseSettings")
    if settings.keep != "series-only" and 0.5 / settings.output_dt < load.band:
        raise SpecificationError("settings.output_dt", settings.output_dt,
                                 f"its Nyquist frequency 1/(2 output_dt) = {0.5 / settings.output_dt:g} Hz must not lie "
                                 f"below the load band {load.band:g} Hz (the response PSD would be aliased)")
    rngs = _generators("rngs", rngs, len(realisations))
    system_rngs = _generators("system_rngs", system_rngs, len(realisations))
    streams = [realisation_streams(seed, r, None if rngs is None else rngs[i]) for i, r in enumerate(realisations)]
    sub = model.subsystem
    dispersion.check(sub.n)
    germs = germs_from_rngs(sub.n, [s[0] for s in streams] if system_rngs is None else system_rngs)
    if dispersion.is_deterministic:  # one model for every realisation: the solver builds its tables once
        M, D, K = model.mean_matrices
    else:
        M, D, K = model.matrices(*random_subsystem(sub, dispersion, 0, realisations, germs=germs))
    m = len(load.names)
    n_load = int(round(settings.duration / settings.dt_load)) + 1
    n_out = int(round(settings.duration / settings.output_dt)) + 1
    per_realisation = 8.0 * (2 * n_load * m + (n_out * len(model.spec.sensors) if settings.keep != "psd" else 0))
    allocation("settings.duration", settings.duration, len(realisations) * per_realisation,
               f"the loads{' and series' if settings.keep != 'psd' else ''} of {len(realisations)} realisation(s)")
    stops = [Stop(b=tuple(b), gap=s.gap, stiffness=s.stiffness, name=f"stop{i}")
             for i, (b, s) in enumerate(zip(model.stop_vectors(), model.spec.stops))]
    # the mean model's cost, before the loads are drawn (simulate checks every realisation's own again)
    check_substeps(model.mean_matrices[0], model.mean_matrices[2], stops, settings.duration, settings.dt_load,
                   settings.output_dt, settings.method, duration_field="settings.duration")
    loads = np.empty((len(realisations), n_load, m))
    for i, s in enumerate(streams):
        spectrum = load if load_dispersion == 0.0 else randomised(load, sg_plus(m, load_dispersion, rng=s[1]))
        gaussian_loads(spectrum, settings.duration, settings.dt_load, [s[2]], interpolation="linear",
                       out=loads[i:i + 1])
    from tubeid.mechanics.effects import SensorNoise, Tone

    tones = [e for e in model.spec.effects if isinstance(e, Tone)]
    noise = sum(e.level for e in model.spec.effects if isinstance(e, SensorNoise))
    points = _load_points(load) + tuple(LoadPoint(name=f"tone{i}", tube=e.tube, x=e.x) for i, e in enumerate(tones))
    if tones:
        t = np.arange(loads.shape[1]) * settings.dt_load
        phases = np.array([s[3].uniform(0, 2 * np.pi, len(tones)) for s in streams])  # (R, n_tones)
        f0 = np.array([e.frequency_hz for e in tones])
        nyquist = 0.5 / settings.dt_load
        if np.any(f0 >= nyquist):
            raise SpecificationError("effects.tone.frequency_hz", float(f0[np.argmax(f0 >= nyquist)]),
                                     f"must lie below the load sampling's Nyquist frequency 1/(2 dt_load) = {nyquist:g} Hz")
        # the solver reads the samples as their piecewise-linear interpolant, whose component at f0 is
        # sinc²(f0 dt_load) times the tone's: pre-compensated, as gaussian_loads does in band
        amp = np.array([e.amplitude for e in tones]) / np.sinc(f0 * settings.dt_load) ** 2
        extra = amp * np.cos(2 * np.pi * f0 * t[None, :, None] + phases[:, None, :])
        loads = np.concatenate([loads, extra], axis=2)
    B = model.load_matrix(points)
    C = model.sensor_matrix()
    names = [s.name for s in model.spec.sensors]
    res = simulate(M, D, K, stops, B, C, loads, settings.dt_load, output_dt=settings.output_dt, method=settings.method,
                   keep="series", discard=settings.discard, sensor_names=names)
    y = res.observations.transpose("realisation", "time", "sensor")
    if noise > 0:  # two-sided white PSD `noise` [m²/Hz] sampled at output_dt: variance noise/output_dt
        sigma = np.sqrt(noise / settings.output_dt)
        y = y.copy(data=y.values + sigma * np.stack([s[3].standard_normal(y.shape[1:]) for s in streams]))
        rms = np.sqrt(np.mean(y.values**2, axis=1))  # the noisy signal, like the PSD
        res = dataclasses.replace(res, rms=res.rms.copy(data=rms.reshape(res.rms.shape)))
    ds = xr.Dataset(
        {
            "rms": res.rms.assign_coords(realisation=realisations),
            "contact_fraction": res.contact_fraction.assign_coords(realisation=realisations),
            "contact_events": res.contact_events.assign_coords(realisation=realisations),
        },
        coords={"realisation": realisations, "sensor": names},
        attrs={
            "model": model.spec.name, "loads": list(load.names), "load_dispersion": load_dispersion,
            "dispersion": [dispersion.mass, dispersion.damping, dispersion.stiffness],
            "duration": settings.duration, "discard": settings.discard, "output_dt": settings.output_dt,
            "welch": f"hann window, {settings.segment_seconds} s segments, 50 % overlap; two-sided per Hz",
            "method": settings.method,
        },
    )
    ds["rms"].attrs["units"] = "m"
    if settings.keep != "series-only":
        f, S = psd_matrix(y.values, settings.output_dt, segment_seconds=settings.segment_seconds)
        ds = ds.assign_coords(frequency=("frequency", f, {"units": "Hz"}), sensor_=names)
        ds["psd"] = (("realisation", "frequency", "sensor", "sensor_"), S,
                     {"units": "m^2/Hz", "long_name": "two-sided response PSD matrix"})
    if settings.keep != "psd":
        ds["displacement"] = y.assign_coords(realisation=realisations).assign_attrs(units="m")
        ds["time"].attrs["units"] = "s"
    return ds
