"""The record cut into fitting and held-out blocks, and its spectra (two-sided, per Hz)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import xarray as xr

from tubeid.dynamics.spectra import psd_matrix
from tubeid.errors import SpecificationError

__all__ = ["MeasuredSpectra", "measured_spectra", "time_statistics", "auto_psd", "analysis_bins", "log10"]


def log10(P) -> np.ndarray:
    """log10 of a PSD, floored at 1e-300 (a zero bin is not an error, it is very far below)."""
    return np.log10(np.maximum(np.asarray(P, dtype=float), 1e-300))


def analysis_bins(f: np.ndarray) -> np.ndarray:
    """Frequencies every comparison uses: 0 < f < f_Nyquist (the DC and Nyquist bins dropped)."""
    sel = np.ones(np.asarray(f).size, bool)
    sel[0] = sel[-1] = False
    return sel


@dataclass(frozen=True)
class MeasuredSpectra:
    """Welch PSDs of the fitting and held-out blocks of a record (two-sided, m²/Hz).

    ``frequency`` (F,) Hz; ``fit``, ``held_out`` (F, m) auto-PSDs averaged over the blocks of the
    set; ``fit_cross`` (n_fit, F, m, m) complex PSD matrix per fitting block (for J_s); ``stats``,
    ``fit_stats`` (m, 3): RMS [m], skewness, excess kurtosis of the held-out resp. fitting
    samples; ``dt`` [s]; ``block_samples``: samples per block; ``sensors``: names; ``x`` [m] and
    ``tube`` per sensor.
    """

    frequency: np.ndarray
    fit: np.ndarray
    held_out: np.ndarray
    fit_cross: np.ndarray
    stats: np.ndarray
    fit_stats: np.ndarray
    dt: float
    block_samples: int
    n_fit_blocks: int
    n_held_out_blocks: int
    sensors: tuple
    x: tuple
    tube: tuple

    @property
    def block_seconds(self) -> float:
        return self.block_samples * self.dt


def auto_psd(blocks: np.ndarray, dt: float, segment_seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """Records (..., n_t, m) → frequencies (F,) [Hz] and auto-PSDs (..., F, m) [m²/Hz, two-sided]."""
    f, S = psd_matrix(blocks, dt, segment_seconds=segment_seconds)
    return f, np.real(np.diagonal(S, axis1=-2, axis2=-1))


def time_statistics(y: np.ndarray) -> np.ndarray:
    """RMS [m], skewness and excess kurtosis per channel of records y (..., n_t, m) → (..., m, 3)."""
    c = y - y.mean(axis=-2, keepdims=True)
    var = np.mean(c**2, axis=-2)
    sd = np.sqrt(var)
    safe = np.where(var > 0, var, 1.0)
    skew = np.mean(c**3, axis=-2) / safe**1.5
    kurt = np.mean(c**4, axis=-2) / safe**2 - 3.0
    return np.stack([sd, skew, kurt], axis=-1)


def _split(y: np.ndarray, blocks: int) -> tuple[np.ndarray, np.ndarray, int]:
    """(n_t, m) → even blocks, odd blocks (n_b, L, m), L."""
    L = y.shape[-2] // blocks
    cut = y[: L * blocks].reshape(blocks, L, y.shape[-1])
    return cut[0::2], cut[1::2], L


def measured_spectra(data: xr.Dataset, blocks: int, segment_seconds: float) -> MeasuredSpectra:
    """Fitting and held-out spectra of a validated record (``displacement`` (time, sensor) [m])."""
    y = np.asarray(data["displacement"].transpose("time", "sensor").values, dtype=float)
    t = np.asarray(data["time"].values, dtype=float)
    dt = float((t[-1] - t[0]) / (t.size - 1))
    L = y.shape[0] // blocks
    need = 2 * int(round(segment_seconds / (2 * dt)))
    if L < 2 * need:
        raise SpecificationError(
            "data duration", round(t.size * dt, 6),
            f"too short: each of the {blocks} blocks ({L * dt:.4g} s) must hold at least 2 Welch segments "
            f"of {segment_seconds} s (record >= {2 * need * blocks * dt:.4g} s)")
    fit, held, L = _split(y, blocks)
    f, S_fit = psd_matrix(fit, dt, segment_seconds=segment_seconds)
    P_fit = np.real(np.diagonal(S_fit, axis1=-2, axis2=-1))
    _, P_held = auto_psd(held, dt, segment_seconds)
    return MeasuredSpectra(
        frequency=f, fit=P_fit.mean(axis=0), held_out=P_held.mean(axis=0), fit_cross=S_fit,
        stats=time_statistics(held.reshape(-1, y.shape[1])), fit_stats=time_statistics(fit.reshape(-1, y.shape[1])),
        dt=dt, block_samples=L, n_fit_blocks=fit.shape[0], n_held_out_blocks=held.shape[0],
        sensors=tuple(str(s) for s in data["sensor"].values), x=tuple(float(x) for x in data["x"].values),
        tube=tuple(str(x) for x in data["tube"].values))
