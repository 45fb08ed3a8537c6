"""Measured data: readers, writers and validation of displacement records, and the diagnosis loop."""

from __future__ import annotations

from typing import TYPE_CHECKING

from tubeid._lazy import attach

if TYPE_CHECKING:  # the lazy exports: imported on first use (tubeid._lazy reads this block)
    from tubeid.measured.diagnose import DiagnoseSettings, Diagnosis, diagnose
    from tubeid.measured.readers import read_measurements, write_measurements
    from tubeid.measured.validation import validate_measurements

__all__ = ["read_measurements", "write_measurements", "validate_measurements", "diagnose", "DiagnoseSettings", "Diagnosis"]

__getattr__, __dir__ = attach(__name__, __file__)
