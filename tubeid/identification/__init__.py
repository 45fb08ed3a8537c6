"""Identification: likelihood curves (KDE, bootstrap), δ by maximum likelihood, the load (r, δ_F).

The trial method for the load level r has one entry point, :func:`identify_r` (module ``trial``):
every distance (the paper's, relative, log band levels, log spectra) and the coarse-then-fine grid
(:func:`fine_grid`); the distance engines it calls live in ``loads``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from tubeid._lazy import attach

if TYPE_CHECKING:  # the lazy exports: imported on first use (tubeid._lazy reads this block)
    from tubeid.identification.delta import identify_delta, reference_j
    from tubeid.identification.likelihood import kde_pdf, likelihood_curve, silverman_bandwidth
    from tubeid.identification.loads import (delta_f_likelihood, distance_map, log_band_distance_map,
                                            log_spectral_distance_map, refine_grid, relative_weight)
    from tubeid.identification.trial import DISTANCES, fine_grid, identify_r

__all__ = [
    "identify_delta", "reference_j", "likelihood_curve", "kde_pdf", "silverman_bandwidth",
    "identify_r", "fine_grid", "DISTANCES",
    "distance_map", "log_band_distance_map", "log_spectral_distance_map", "relative_weight", "refine_grid",
    "delta_f_likelihood",
]

__getattr__, __dir__ = attach(__name__, __file__)
