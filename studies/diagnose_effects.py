"""The measurement campaign of ``tubeid diagnose`` (issue 11): a resumable pipeline of records.

Every point makes one record independently of the diagnosis's code path
(:func:`tubeid.diagnose.testing.make_record`: effects written into the specification by hand, tones
as explicit force columns, noise added with numpy, the solver called directly), 220 s at 3 ms,
sensors c02–c14 on the centre tube at x = 2, 4, …, 14 m (the ``located`` stop-between-sensors case:
c02, c06, c10), and diagnoses it in the task's process (``workers=0``, a temporary store): the
runner parallelises over the points. The record's seed comes from the point's stream, so every
record differs and the store does not depend on workers or blocks.

Stages, in this order (``tubeid run studies/diagnose_effects.py``; interrupted, the same command
resumes; a finished point is never recomputed):

``false_alarm``   the declared model's own records (``paper-reference`` declared and generating),
                  the test only: the alarm rate against the stated 5 %
``power``         a tone 9 dB above its 1 Hz band level (37 Hz at x = 5 m), the centre tube's
                  damping × 3 and × 0.4, the test only
``located``       tones at x = 4, 10, 14 m and on outer1, a stop at a node, a stop between sensors,
                  added mass on outer1, damping of outer2: the full loop, position errors
``two_at_once``   stop + sensor noise, added mass + tone: the full loop
``simplified_false_alarm``  ``paper-simplified`` declared (δ by maximum likelihood of J against the
                  reference, so the simplified model form), the reference's own records, the test
                  only: the alarm rate of the simplified form's statistics under model-form error
``simplified``    the same declared model, reference records with each catalog effect (and added
                  mass × 2 on the centre tube beside the catalog's × 1.3): the full loop

Outputs per point: the test (``detected``, p-values), the effects named (``named``: bit k set for
catalog entry k; ``right``: 1 when exactly the true effects are named), the position error of a
located effect [m], the held-out errors before and after, the time taken [s].
"""

import json
import time

import numpy as np

from tubeid.diagnose import CATALOG, DiagnoseSettings, diagnose
from tubeid.diagnose._detection import STATISTICS
from tubeid.diagnose.testing import HandEffects, make_record
from tubeid.errors import SpecificationError
from tubeid.mechanics.library import model_content
from tubeid.mechanics.spec import spec_from_dict
from tubeid.runner.pipeline import Pipeline
from tubeid.runner.study import Output, Parameter, Study, pointwise

SEED = 11
NAMES = list(CATALOG)
SEVEN = (2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0)
THREE = (2.0, 6.0, 10.0)
TONE = ("centre", 5.0, 37.0, 21.0)  # 21 N at 37 Hz, x = 5 m: ~9 dB above the 1 Hz band level (stored per record)

#: case name -> (effects written by hand, the catalog names that should be named, sensor positions,
#: position of the located effect [m] or None)
CASES = {
    "control": (HandEffects(), (), SEVEN, None),
    "tone_9dB": (HandEffects(tones=(TONE,)), ("tone",), SEVEN, 5.0),
    "damping_x3": (HandEffects(damping={"centre": 0.06}), ("damping",), SEVEN, None),
    "damping_x0.4": (HandEffects(damping={"centre": 0.008}), ("damping",), SEVEN, None),
    "tone_x4": (HandEffects(tones=(("centre", 4.0, 23.0, 30.0),)), ("tone",), SEVEN, 4.0),
    "tone_x10": (HandEffects(tones=(("centre", 10.0, 61.0, 30.0),)), ("tone",), SEVEN, 10.0),
    "tone_x14": (HandEffects(tones=(("centre", 14.0, 47.0, 30.0),)), ("tone",), SEVEN, 14.0),
    "tone_outer1_x9": (HandEffects(tones=(("outer1", 9.0, 37.0, 60.0),)), ("tone",), SEVEN, 9.0),
    "stop_x10": (HandEffects(stops=(("centre", 10.0, 3e-6, 1e8),)), ("stop",), SEVEN, 10.0),
    "stop_x8_between": (HandEffects(stops=(("centre", 8.0, 3e-6, 1e8),)), ("stop",), THREE, 8.0),
    "added_mass_outer1": (HandEffects(density={"outer1": 1.3}), ("added_mass",), SEVEN, None),
    "damping_outer2": (HandEffects(damping={"outer2": 0.005}), ("damping",), SEVEN, None),
    "stop_and_noise": (HandEffects(stops=(("centre", 10.0, 3e-6, 1e8),), noise=1e-16), ("stop", "sensor_noise"), SEVEN, None),
    "mass_and_tone": (HandEffects(density={"outer1": 1.3}, tones=(TONE,)), ("added_mass", "tone"), SEVEN, None),
    "tone": (HandEffects(tones=(TONE,)), ("tone",), SEVEN, None),
    "stop": (HandEffects(stops=(("centre", 10.0, 3e-6, 1e8),)), ("stop",), SEVEN, None),
    "added_mass": (HandEffects(density={"centre": 1.3}), ("added_mass",), SEVEN, None),
    "added_mass_x2": (HandEffects(density={"centre": 2.0}), ("added_mass",), SEVEN, None),
    "damping": (HandEffects(damping={"centre": 0.008}), ("damping",), SEVEN, None),
    "sensor_noise": (HandEffects(noise=1e-16), ("sensor_noise",), SEVEN, None),
}

OUTPUTS = {
    "detected": Output(units="1", long_name="1 if the test detected a departure before any effect"),
    "p_value": Output(units="1", long_name="the test's p-value before any effect"),
    **{f"p_{k}": Output(units="1", finite=False, long_name=f"p-value of the {k} statistic (NaN: not in this model form's test)")
       for k in STATISTICS},
    "named": Output(dtype="int64", units="1", long_name="bit k set: catalog entry k named"),
    "right": Output(units="1", long_name="1 if exactly the true effects are named (test-only stages: NaN)",
                    finite=False),
    "x_error": Output(units="m", long_name="|fitted - true| position of the located effect (NaN: none)",
                      finite=False),
    "error_before": Output(units="1", long_name="held-out error before"),
    "error_after": Output(units="1", long_name="held-out error after"),
    "explained_after": Output(units="1", long_name="1 if the test no longer detects anything after the selection"),
    "tone_db": Output(units="dB", long_name="the tone's line above the broadband level in its 1 Hz band (NaN: no tone)",
                      finite=False),
    "seconds": Output(units="s", long_name="wall time of the diagnosis (this task's process)"),
}


class ModelParameter(Parameter):
    """The declared model: a built-in name or a .yaml/.toml file, checked when the study is loaded (before
    any stage runs); its value becomes the specification's content, so the stages store and hash what
    they diagnose with (a changed file is a changed study) and the workers need no file."""

    def check(self, name, value):
        text, spec = model_content(f"parameters.{name}", value)
        if spec.effects:
            raise SpecificationError(f"parameters.{name}: effects", spec.effects, "diagnose a model without carried effects")
        return text


def _declared(model: str):
    """The model ``diagnose`` receives: a built-in name as is, a ``ModelParameter``'s content as its specification."""
    return spec_from_dict(json.loads(model)["spec"]) if model.lstrip().startswith("{") else model


def _tone_db(case, seed, xs, effects: HandEffects) -> float:
    """The line's power over the broadband power in the 1 Hz band at its frequency, mean over the
    sensors [dB]: the record against the same record without the tone (the same load)."""
    from tubeid.diagnose._spectra import auto_psd

    (_, _, f0, _), = effects.tones
    with_tone = make_record(effects=effects, xs=xs, seed=seed)
    without = make_record(effects=HandEffects(**{**effects.__dict__, "tones": ()}), xs=xs, seed=seed)
    f, P1 = auto_psd(with_tone.displacement.values, 3e-3, 2.0)
    _, P0 = auto_psd(without.displacement.values, 3e-3, 2.0)
    df = f[1] - f[0]
    line = np.sum((P1 - P0)[np.abs(f - f0) <= 2.0], axis=0) * df
    broad = np.mean(P0[np.abs(f - f0) <= 0.5 + 1e-9], axis=0) * 1.0
    return float(10 * np.log10(line.mean() / broad.mean()))


def _diagnose_point(point, rng, *, model, settings: DiagnoseSettings):
    case = point["case"]
    effects, truth, xs, x_true = CASES[case]
    seed = int(rng.integers(2**31))
    data = make_record(effects=effects, xs=xs, seed=seed)
    t0 = time.perf_counter()
    rep = diagnose(data, _declared(model), settings.replace(seed=seed % 10_000), workers=0).report
    seconds = time.perf_counter() - t0
    det = rep["detection"]
    named = [e["name"] for e in rep["effects"]]
    x_err = np.nan
    if x_true is not None and named and "x" in rep["effects"][0]["parameters"]:
        x_err = abs(float(rep["effects"][0]["parameters"]["x"]["value"]) - x_true)
    full = settings.max_effects > 0
    return {"detected": float(det["detected"]), "p_value": det["p_value"],
            **{f"p_{k}": det["p_values"].get(k, np.nan) for k in STATISTICS},
            "named": sum(1 << NAMES.index(n) for n in named),
            "right": float(sorted(named) == sorted(truth)) if full else np.nan, "x_error": x_err,
            "error_before": rep["error_before"], "error_after": rep["error_after"],
            "explained_after": float(rep["explained_after"]),
            "tone_db": _tone_db(case, seed, xs, effects) if effects.tones and case.startswith("tone_9") else np.nan,
            "seconds": seconds}


@pointwise
def test_only(point, rng, *, model, delta_reference=""):
    s = DiagnoseSettings(max_effects=0, delta_reference=delta_reference or None)
    return _diagnose_point(point, rng, model=model, settings=s)


@pointwise
def full_loop(point, rng, *, model, delta_reference=""):
    s = DiagnoseSettings(delta_reference=delta_reference or None)
    return _diagnose_point(point, rng, model=model, settings=s)


def _stage(name, cases, records, task, parameters) -> Study:
    return Study(name=name, seed=SEED, description=f"tubeid diagnose on independent records: {name}",
                 axes={"case": list(cases), "record": range(records)}, chunks={"case": 1, "record": 1},
                 task=task, outputs=OUTPUTS, units={"case": "", "record": "1"}, parameters=parameters)


def false_alarm(results, *, control_records):
    return _stage("false_alarm", ["control"], control_records, test_only, {"model": "paper-reference"})


def power(results, *, records):
    return _stage("power", ["tone_9dB", "damping_x3", "damping_x0.4"], records, test_only, {"model": "paper-reference"})


def located(results):
    return _stage("located", ["tone_x4", "tone_x10", "tone_x14", "tone_outer1_x9", "stop_x10", "stop_x8_between",
                              "added_mass_outer1", "damping_outer2"], 1, full_loop, {"model": "paper-reference"})


def two_at_once(results, *, two_records):
    return _stage("two_at_once", ["stop_and_noise", "mass_and_tone"], two_records, full_loop, {"model": "paper-reference"})


def simplified_false_alarm(results, *, simplified_model, control_records):
    return _stage("simplified_false_alarm", ["control"], control_records, test_only,
                  {"model": simplified_model, "delta_reference": "paper-reference"})


def simplified(results, *, simplified_model, simplified_records):
    return _stage("simplified", ["tone", "stop", "added_mass", "added_mass_x2", "damping", "sensor_noise"],
                  simplified_records, full_loop,
                  {"model": simplified_model, "delta_reference": "paper-reference"})


study = Pipeline(
    name="diagnose-effects",
    seed=SEED,
    description="tubeid diagnose on independent 220 s records: false alarms, power, located, two at once, simplified model",
    stages=[false_alarm, power, located, two_at_once, simplified_false_alarm, simplified],
    parameters={
        "control_records": Parameter(20, bounds=(1, 1000), doc="control records of the false-alarm campaign"),
        "records": Parameter(10, bounds=(1, 1000), doc="records per case of the power campaign"),
        "two_records": Parameter(5, bounds=(1, 1000), doc="records per case of the two-at-once campaign"),
        "simplified_model": ModelParameter("paper-simplified", doc="the simplified model declared (name or specification "
                                           "file; stored as its content)"),
        "simplified_records": Parameter(5, bounds=(1, 1000), doc="records per effect with the simplified model declared"),
    },
)
