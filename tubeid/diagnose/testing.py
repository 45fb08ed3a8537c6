"""Records for testing a diagnosis, made independently of the diagnosis's own code path.

The diagnosis models an effect through :func:`tubeid.mechanics.effects.apply_effects` and
simulates through :func:`tubeid.dynamics.simulate_responses`. The records here do neither: every
effect is written by hand — a second entry in the specification's ``stops``, a tube's density or
damping ratio changed in its ``TubeSpec``, a tone as an explicit harmonic force column, sensor noise
as white Gaussian samples added with numpy — and the transient is run through the solver's own
API (:func:`tubeid.dynamics.simulate`), optionally with its ``symplectic-euler`` integrator at a
small step instead of the exact one. They are the "measured data" of the tests and of
``studies/diagnose_effects.py``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import xarray as xr

from tubeid.dynamics.solver import Stop, simulate
from tubeid.errors import SpecificationError
from tubeid.measured.validation import validate_measurements
from tubeid.mechanics.library import resolve_spec
from tubeid.mechanics.reduction import reduce
from tubeid.mechanics.spec import BundleSpec, LoadPoint, SensorSpec, StopSpec
from tubeid.seeds import rng_for
from tubeid.uncertainty.loads import coherent_forces
from tubeid.uncertainty.processes import gaussian_loads

__all__ = ["HandEffects", "make_record", "sensors"]


def sensors(xs, tube: str = "centre", prefix: str = "c") -> tuple[SensorSpec, ...]:
    """Sensors named ``c02``, ``c04``, … on ``tube`` at positions ``xs`` [m]."""
    return tuple(SensorSpec(f"{prefix}{int(round(x)):02d}", tube, float(x)) for x in xs)


@dataclasses.dataclass(frozen=True)
class HandEffects:
    """Effects written by hand into a record (every field optional).

    ``stops``: extra (tube, x [m], gap [m], stiffness [N/m]); ``density``: {tube: factor}
    multiplying its density; ``damping``: {tube: ratio}; ``tones``: (tube, x [m], frequency [Hz],
    amplitude [N]); ``noise``: white sensor noise, two-sided level [m²/Hz].
    """

    stops: tuple = ()
    density: dict = dataclasses.field(default_factory=dict)
    damping: dict = dataclasses.field(default_factory=dict)
    tones: tuple = ()
    noise: float = 0.0

    def spec(self, spec: BundleSpec) -> BundleSpec:
        """The specification with the structural effects written in."""
        tubes = []
        for t in spec.tubes:
            changes = {}
            if t.name in self.density:
                changes["density"] = t.density * float(self.density[t.name])
            if t.name in self.damping:
                changes["damping_ratio"] = float(self.damping[t.name])
            tubes.append(dataclasses.replace(t, **changes))
        stops = spec.stops + tuple(StopSpec(tube=a, x=float(x), gap=float(g), stiffness=float(k)) for a, x, g, k in self.stops)
        return spec.replace(tubes=tuple(tubes), stops=stops)


def make_record(model="paper-reference", effects: HandEffects = HandEffects(), *, xs=(2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0),
                duration: float = 220.0, seed: int = 0, level: float = 1.3, dt: float = 3e-3, dt_load: float = 1e-3,
                discard: float = 2.0, method: str = "exact", step: float | None = None) -> xr.Dataset:
    """One validated record (``displacement`` (time, sensor) [m]) of ``model`` under its coherent
    point forces (level ``level`` [N²/Hz], the paper's coherence) with ``effects`` written by hand.

    ``xs``: sensor positions on the centre tube [m]; ``duration`` [s] kept after ``discard`` [s];
    ``dt`` output sampling [s]; ``method``/``step``: the solver's integrator and step (None: its
    default rule). Random draws: ``rng_for(seed, "record", name)`` for the load, the tones' phases
    and the noise.
    """
    spec = effects.spec(resolve_spec(model).replace(sensors=sensors(xs)))
    m = reduce(spec)
    tube = spec.a_tube or spec.tubes[0].name
    load = coherent_forces([p.x for p in spec.loads if p.tube == tube], level=level, band=spec.band_hz, tube=tube)
    total = duration + discard + 2 * dt
    F = gaussian_loads(load, total, dt_load, [rng_for(seed, "record", "load")])[0]            # (n_t, m)
    points = [LoadPoint(name=n, tube=tube, x=float(x)) for n, x in zip(load.names, load.x)]
    if effects.tones:
        bad = [f0 for _, _, f0, _ in effects.tones if f0 >= 0.5 / dt_load]
        if bad:
            raise SpecificationError("effects.tones.frequency", bad[0], f"must lie below 1/(2 dt_load) = {0.5 / dt_load:g} Hz")
        t = np.arange(F.shape[0]) * dt_load
        phase = rng_for(seed, "record", "tones").uniform(0.0, 2 * np.pi, len(effects.tones))
        # amplitude over sinc²(f0 dt_load): the solver's piecewise-linear reading of the samples attenuates
        # the line by that factor, so the record's force is the tone asked for
        cols = [amp / np.sinc(f0 * dt_load) ** 2 * np.cos(2 * np.pi * f0 * t + ph)
                for (_, _, f0, amp), ph in zip(effects.tones, phase)]
        F = np.column_stack([F, *cols])
        points += [LoadPoint(name=f"tone{i}", tube=tb, x=float(x)) for i, (tb, x, _, _) in enumerate(effects.tones)]
    M, D, K = m.mean_matrices
    stops = [Stop(b=tuple(b), gap=s.gap, stiffness=s.stiffness, name=f"stop{i}")
             for i, (b, s) in enumerate(zip(m.stop_vectors(), spec.stops))]
    res = simulate(M, D, K, stops, m.load_matrix(tuple(points)), m.sensor_matrix(), F, dt_load, output_dt=dt,
                   method=method, dt=step, keep="series", discard=discard, sensor_names=[s.name for s in spec.sensors])
    y = res.observations.transpose("realisation", "time", "sensor").values[0]
    n = int(round(duration / dt))
    y = y[:n]
    if effects.noise > 0:
        y = y + np.sqrt(effects.noise / dt) * rng_for(seed, "record", "noise").standard_normal(y.shape)
    raw = xr.Dataset({"displacement": (("time", "sensor"), y, {"units": "m"})},
                     coords={"time": np.arange(n) * dt, "sensor": [s.name for s in spec.sensors],
                             "x": ("sensor", [s.x for s in spec.sensors]), "tube": ("sensor", [s.tube for s in spec.sensors])})
    return validate_measurements(raw)
