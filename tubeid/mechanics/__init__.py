"""Mechanics: bundle specifications, finite elements, Craig–Bampton reduction, Z(ω) and J."""

from __future__ import annotations

from typing import TYPE_CHECKING

from tubeid._lazy import attach

if TYPE_CHECKING:  # the lazy exports: imported on first use (tubeid._lazy reads this block)
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

__getattr__, __dir__ = attach(__name__, __file__)
