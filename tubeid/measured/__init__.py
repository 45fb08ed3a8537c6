"""Measured data: readers, writers and validation of multi-channel displacement records."""

from tubeid.measured.readers import read_measurements, write_measurements
from tubeid.measured.validation import validate_measurements

__all__ = ["read_measurements", "write_measurements", "validate_measurements"]
