"""Uncertainty: SG+/SE+ random matrices, random reduced models, random load spectra, Gaussian loads."""

from __future__ import annotations

from typing import TYPE_CHECKING

from tubeid._lazy import attach

if TYPE_CHECKING:  # the lazy exports: imported on first use (tubeid._lazy reads this block)
    from tubeid.uncertainty.loads import LoadSpectrum, coherent_forces, force_and_moment, randomised, tabulated
    from tubeid.uncertainty.processes import gaussian_loads
    from tubeid.uncertainty.random_matrices import Dispersion, delta_max, se_plus, sg_plus
    from tubeid.uncertainty.random_models import j_monte_carlo, random_condensed_stiffness, random_subsystem

__all__ = [
    "sg_plus", "se_plus", "delta_max", "Dispersion",
    "random_subsystem", "random_condensed_stiffness", "j_monte_carlo",
    "LoadSpectrum", "coherent_forces", "force_and_moment", "tabulated", "randomised", "gaussian_loads",
]

__getattr__, __dir__ = attach(__name__, __file__)
