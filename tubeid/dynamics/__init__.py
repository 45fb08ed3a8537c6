"""Dynamics: the non-linear transient solver and response spectra (PSD, confidence regions)."""

from tubeid.dynamics.spectra import confidence_band, distance, j_s, psd_dataset, psd_matrix, variance_from_psd

__all__ = ["psd_matrix", "psd_dataset", "variance_from_psd", "confidence_band", "j_s", "distance"]
