"""Measured data: readers, writers and validation of displacement records (the diagnosis that uses
them is :mod:`tubeid.diagnose`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from tubeid._lazy import attach

if TYPE_CHECKING:  # the lazy exports: imported on first use (tubeid._lazy reads this block)
    from tubeid.measured.readers import read_measurements, write_measurements
    from tubeid.measured.validation import validate_measurements

__all__ = ["read_measurements", "write_measurements", "validate_measurements"]

__getattr__, __dir__ = attach(__name__, __file__)
