"""Identification: likelihood curves (KDE, bootstrap) and the maximum likelihood of δ."""

from tubeid.identification.delta import identify_delta, reference_j
from tubeid.identification.likelihood import kde_pdf, likelihood_curve, silverman_bandwidth

__all__ = ["identify_delta", "reference_j", "likelihood_curve", "kde_pdf", "silverman_bandwidth"]
