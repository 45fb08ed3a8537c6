"""Measured data: readers, writers and validation of displacement records (the diagnosis that uses
them is :mod:`tubeid.diagnose`)."""

from tubeid.measured.readers import read_measurements, write_measurements
from tubeid.measured.validation import validate_measurements

__all__ = ["read_measurements", "write_measurements", "validate_measurements"]
