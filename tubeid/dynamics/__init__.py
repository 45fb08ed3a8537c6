"""Dynamics: the non-linear transient solver, random responses, and response spectra."""

from __future__ import annotations

from typing import TYPE_CHECKING

from tubeid._lazy import attach

if TYPE_CHECKING:  # the lazy exports: imported on first use (tubeid._lazy reads this block)
    from tubeid.dynamics.response import ResponseSettings, simulate_responses
    from tubeid.dynamics.solver import Stop, TransientResult, choose_step, highest_frequency, simulate
    from tubeid.dynamics.spectra import confidence_band, distance, j_s, log_level, psd_dataset, psd_matrix, variance_from_psd

__all__ = [
    "Stop", "TransientResult", "simulate", "highest_frequency", "choose_step",
    "ResponseSettings", "simulate_responses",
    "psd_matrix", "psd_dataset", "variance_from_psd", "confidence_band", "j_s", "distance", "log_level",
]

__getattr__, __dir__ = attach(__name__, __file__)
