"""Full-size check of ``tubeid diagnose`` (issue 6): is each catalog effect named, and does the error drop?

For every (effect, record): one record of the reference model (``paper-reference``, the paper's 7
coherent forces, sensors on the centre tube at x = 2, 6, 10 m) with that effect switched on (or
none), diagnosed with ``paper-reference`` not declaring it (distributed load, δ = 0.2, δ_F
identified by maximum likelihood of J_s — the default — or ``--set delta_f=paper`` for the paper's
0.04 imposed). Stored: the effect named (index in ``NAMES``), whether it is the right one, the
held-out error before and after (decades), δ_F used and whether its likelihood was flat. The
record's seed comes from the point's generator, so every record differs and the store does not
depend on workers or blocks. Each point's diagnosis runs its own pipeline in this task's process
(``workers=0``, a temporary store): the runner parallelises over the points.
Run: ``tubeid run studies/diagnose_effects.py`` (several minutes per point on one core with δ_F
identified: its Monte Carlo builds the solver tables of a random K_B for every realisation and δ_F).
"""

import numpy as np
import xarray as xr

from tubeid.dynamics.response import ResponseSettings, simulate_responses
from tubeid.measured.diagnose import DiagnoseSettings, diagnose
from tubeid.measured.validation import validate_measurements
from tubeid.mechanics.effects import AddedMass, Damping, ExtraStop, SensorNoise, Tone, apply_effects
from tubeid.mechanics.library import builtin_spec
from tubeid.mechanics.reduction import reduce
from tubeid.mechanics.spec import SensorSpec
from tubeid.runner.study import Output, Parameter, Study, pointwise
from tubeid.uncertainty.loads import coherent_forces

XS = (2.0, 6.0, 10.0)
EFFECTS = {
    "none": [],
    "tone": [Tone(frequency_hz=37.0, amplitude=100.0)],
    "stop": [ExtraStop(tube="centre", x=10.0, gap=3e-6, stiffness=1e8)],
    "added_mass": [AddedMass(tube="centre", factor=0.3)],
    "damping": [Damping(tube="centre", ratio=0.005)],
    "sensor_noise": [SensorNoise(level=1e-16)],
}
NAMES = list(EFFECTS)


def record(effects, duration, seed):
    spec = builtin_spec("paper-reference").replace(sensors=tuple(SensorSpec(f"c{int(x)}", "centre", x) for x in XS))
    ds = simulate_responses(reduce(apply_effects(spec, effects)), coherent_forces(), [0], seed=seed,
                            settings=ResponseSettings(duration=duration + 2.0, discard=2.0, segment_seconds=2.0, keep="series"))
    y = ds.displacement.isel(realisation=0)
    raw = xr.Dataset({"displacement": (("time", "sensor"), y.values, {"units": "m"})},
                     coords={"time": np.arange(y.sizes["time"]) * 3e-3, "sensor": list(y.sensor.values),
                             "x": ("sensor", list(XS)), "tube": ("sensor", ["centre"] * len(XS))})
    return validate_measurements(raw)


@pointwise
def check(point, rng, *, duration, realisations, delta_f):
    seed = int(rng.integers(2**31))
    data = record(EFFECTS[point["effect"]], duration, seed)
    settings = DiagnoseSettings(realisations=realisations, fit_realisations=4, grid_points=4, seed=seed % 1000,
                                load_dispersion=0.04 if delta_f == "paper" else None)
    rep = diagnose(data, "paper-reference", settings, workers=0).report
    load = rep["load"]
    return {"named": NAMES.index(rep["effect"]), "right": float(rep["effect"] == point["effect"]),
            "error_before": rep["error_before"], "error_after": rep["error_after"], "delta_F": load["delta_F"],
            "delta_F_flat": np.nan if load["delta_F_given"] else float(load["delta_F_flat"])}


study = Study(
    name="diagnose-effects",
    description="tubeid diagnose on reference-model records with one catalog effect on",
    seed=6,
    axes={"effect": NAMES, "record": range(3)},
    chunks={"effect": 1, "record": 1},
    task=check,
    outputs={
        "named": Output(dtype="int64", units="1", long_name="index in NAMES of the effect named"),
        "right": Output(units="1", long_name="1 if the effect named is the one switched on"),
        "error_before": Output(units="decades", long_name="held-out error before"),
        "error_after": Output(units="decades", long_name="held-out error after"),
        "delta_F": Output(units="1", long_name="load dispersion of the band (identified or given)"),
        "delta_F_flat": Output(units="1", long_name="1 if the likelihood of delta_F was flat (NaN: given)"),
    },
    units={"effect": "", "record": "1"},
    parameters={"duration": Parameter(128.0, bounds=(16.0, 2000.0), units="s", doc="record length"),
                "realisations": Parameter(32, bounds=(4, 400), doc="band realisations"),
                "delta_f": Parameter("identified", choices=("identified", "paper"),
                                     doc="delta_F identified by maximum likelihood, or the paper's 0.04 imposed")},
)
