"""Mechanics: bundle specifications, finite elements, Craig–Bampton reduction, Z(ω) and J."""

from tubeid.mechanics.assembly import FEModel, assemble
from tubeid.mechanics.library import BUILTIN_MODELS, builtin_spec, resolve_spec
from tubeid.mechanics.reduction import J_UNITS, ReducedModel, ReducedSubsystem, condensed_stiffness, j_functional, reduce
from tubeid.mechanics.spec import BundleSpec, LinkSpec, LoadPoint, ReductionSpec, SensorSpec, StopSpec, TubeSpec, load_spec

__all__ = [
    "BundleSpec", "TubeSpec", "LinkSpec", "StopSpec", "LoadPoint", "SensorSpec", "ReductionSpec",
    "load_spec", "builtin_spec", "resolve_spec", "BUILTIN_MODELS",
    "FEModel", "assemble", "ReducedModel", "ReducedSubsystem", "reduce",
    "condensed_stiffness", "j_functional", "J_UNITS",
]
