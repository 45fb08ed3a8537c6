"""Measured data: readers, writers and validation of displacement records, and the diagnosis loop."""

from tubeid.measured.diagnose import DiagnoseSettings, Diagnosis, diagnose
from tubeid.measured.readers import read_measurements, write_measurements
from tubeid.measured.validation import validate_measurements

__all__ = ["read_measurements", "write_measurements", "validate_measurements", "diagnose", "DiagnoseSettings", "Diagnosis"]
