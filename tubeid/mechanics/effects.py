"""The effect catalog: physical effects a model may lack, as specification extensions.

Each effect is a frozen, validated value with a catalog ``name``; :func:`apply_effects` returns a
new :class:`BundleSpec` with the effects switched on, usable in any study:

=============== ===================================================== ===========================
name            parameters                                            how it enters the model
=============== ===================================================== ===========================
``tone``        frequency_hz [Hz], amplitude [N], tube, x [m]         a sinusoidal force, random
                                                                      phase per realisation
``stop``        tube, x [m], gap [m], stiffness [N/m]                 an additional elastic stop,
                                                                      or a changed one at that x
``added_mass``  tube, factor [1]                                      mass per length × (1+factor)
``damping``     tube, ratio [1]                                       the tube's modal damping
``sensor_noise`` level [m²/Hz, two-sided]                             white noise on every sensor
=============== ===================================================== ===========================

``tone`` and ``sensor_noise`` are kept in ``BundleSpec.effects`` and honoured by the response
simulation; the structural effects rewrite the tubes and stops.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar

from tubeid import _validation as v
from tubeid.errors import SpecificationError
from tubeid.mechanics.spec import BundleSpec, StopSpec

__all__ = ["Tone", "ExtraStop", "AddedMass", "Damping", "SensorNoise", "EFFECTS", "apply_effects", "effect_from_dict", "effect_to_dict"]


def _tube(field: str, value) -> str:
    if not isinstance(value, str) or not value:
        raise SpecificationError(field, value, "must be a tube name (a non-empty string)")
    return value


@dataclass(frozen=True)
class Tone:
    """A harmonic force F(t) = amplitude·cos(2π f t + φ) [N] at (tube, x); φ uniform per realisation."""

    frequency_hz: float
    amplitude: float
    tube: str = "centre"
    x: float = 8.0
    name: ClassVar[str] = "tone"

    def __post_init__(self):
        v.positive("tone.frequency_hz", self.frequency_hz, "Hz")
        v.non_negative("tone.amplitude", self.amplitude, "N")
        _tube("tone.tube", self.tube)
        v.real("tone.x", self.x, unit="m")


@dataclass(frozen=True)
class ExtraStop:
    """An additional symmetric elastic stop, or a changed gap/stiffness of the stop at (tube, x)."""

    tube: str
    x: float
    gap: float
    stiffness: float
    name: ClassVar[str] = "stop"

    def __post_init__(self):
        _tube("stop.tube", self.tube)
        v.real("stop.x", self.x, unit="m")
        v.non_negative("stop.gap", self.gap, "m")
        v.positive("stop.stiffness", self.stiffness, "N/m")


@dataclass(frozen=True)
class AddedMass:
    """Fluid added mass: the tube's mass per unit length multiplied by (1 + factor)."""

    tube: str
    factor: float
    name: ClassVar[str] = "added_mass"

    def __post_init__(self):
        _tube("added_mass.tube", self.tube)
        v.non_negative("added_mass.factor", self.factor)


@dataclass(frozen=True)
class Damping:
    """The modal damping ratio of a tube's own modes."""

    tube: str
    ratio: float
    name: ClassVar[str] = "damping"

    def __post_init__(self):
        _tube("damping.tube", self.tube)
        v.real("damping.ratio", self.ratio, low=0.0, high=1.0, high_open=True)


@dataclass(frozen=True)
class SensorNoise:
    """White measurement noise added to every sensor: two-sided PSD ``level`` [m²/Hz]."""

    level: float
    name: ClassVar[str] = "sensor_noise"

    def __post_init__(self):
        v.non_negative("sensor_noise.level", self.level, "m^2/Hz")


EFFECTS = {cls.name: cls for cls in (Tone, ExtraStop, AddedMass, Damping, SensorNoise)}


def effect_from_dict(data: dict, where: str = "effects[0]"):
    """An effect from plain data with a ``kind`` key naming its catalog entry."""
    if not isinstance(data, dict) or "kind" not in data:
        raise SpecificationError(where, data, f"must be a mapping with 'kind' in {sorted(EFFECTS)}")
    kind = data["kind"]
    if not isinstance(kind, str) or kind not in EFFECTS:
        raise SpecificationError(f"{where}.kind", kind, f"must be one of {sorted(EFFECTS)}")
    cls = EFFECTS[kind]
    known = {f.name for f in dataclasses.fields(cls)}
    args = {k: v for k, v in data.items() if k != "kind"}
    for k in args:
        if k not in known:
            raise SpecificationError(f"{where}.{k}", args[k], f"unknown field of {kind}; known: {sorted(known)}")
    try:
        return cls(**args)
    except TypeError as exc:
        raise SpecificationError(where, data, f"missing fields for {kind} ({exc})") from None


def effect_to_dict(effect) -> dict:
    return {"kind": effect.name, **dataclasses.asdict(effect)}


def apply_effects(spec: BundleSpec, effects) -> BundleSpec:
    """A new specification with ``effects`` switched on (see the module table)."""
    tubes = list(spec.tubes)
    stops = list(spec.stops)
    carried = list(spec.effects)
    names = [t.name for t in tubes]
    for i, e in enumerate(effects):
        if isinstance(e, dict):
            e = effect_from_dict(e, f"effects[{i}]")
        if isinstance(e, (AddedMass, Damping)):
            if e.tube not in names:
                raise SpecificationError(f"effects[{i}].tube", e.tube, f"no such tube; tubes are {names}")
            k = names.index(e.tube)
            t = tubes[k]
            tubes[k] = dataclasses.replace(t, density=t.density * (1 + e.factor)) if isinstance(e, AddedMass) else dataclasses.replace(t, damping_ratio=e.ratio)
        elif isinstance(e, ExtraStop):
            new = StopSpec(tube=e.tube, x=e.x, gap=e.gap, stiffness=e.stiffness)
            same = [j for j, s in enumerate(stops) if s.tube == e.tube and abs(s.x - e.x) < 1e-9]
            if same:
                stops[same[0]] = new
            else:
                stops.append(new)
        elif isinstance(e, (Tone, SensorNoise)):
            carried.append(e)
        else:
            raise SpecificationError(f"effects[{i}]", e, f"is not a catalog effect ({sorted(EFFECTS)})")
    return spec.replace(tubes=tuple(tubes), stops=tuple(stops), effects=tuple(carried))
