"""The record cut into fitting and held-out blocks, and its spectra (two-sided, per Hz)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import xarray as xr

from tubeid.dynamics.spectra import auto_psd as welch_auto_psd
from tubeid.dynamics.spectra import psd_matrix
from tubeid.errors import SpecificationError

__all__ = ["MeasuredSpectra", "measured_spectra", "time_statistics", "auto_psd", "analysis_bins", "log10",
           "conditional_psd", "block_observations", "kept_bins", "fine_segment", "welch_segments"]


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
    ``tube`` per sensor; ``frequency_fine`` (F',) [Hz], ``fit_fine``, ``held_out_fine`` (F', m):
    auto-PSDs at the fine segment ``fine_seconds`` [s]; ``fit_residual``, ``held_out_residual`` (F, m):
    conditional PSDs (:func:`conditional_psd`) of the set's block-averaged PSD matrix.
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
    fine_seconds: float = 0.0
    frequency_fine: np.ndarray | None = None
    fit_fine: np.ndarray | None = None
    held_out_fine: np.ndarray | None = None
    fit_residual: np.ndarray | None = None
    held_out_residual: np.ndarray | None = None

    @property
    def block_seconds(self) -> float:
        return self.block_samples * self.dt


#: Eigenvalues of a PSD matrix below this fraction of its largest are numerical zeros (round-off of
#: the estimate): :func:`conditional_psd` floors them there.
EIGEN_FLOOR = 1e-14


def conditional_psd(S: np.ndarray) -> np.ndarray:
    """Conditional PSD of each channel given the others, 1/[S⁻¹]_ii, of Hermitian PSD matrices S
    (..., m, m) → (..., m) [m²/Hz]: the part of channel i no linear combination of the others
    explains (S_ii for one channel). Eigenvalues are floored at :data:`EIGEN_FLOOR` of the largest:
    a singular matrix (fewer averaged segments than channels) gives values at that floor, not zero
    or infinity; an all-zero matrix gives zeros."""
    w, V = np.linalg.eigh(np.asarray(S))
    top = w[..., -1:]
    floor = np.where(top > 0, EIGEN_FLOOR * top, 1.0)
    inv = np.einsum("...ik,...k->...i", np.abs(V) ** 2, 1.0 / np.maximum(w, floor))
    return np.where(top > 0, 1.0 / inv, 0.0)


def welch_segments(samples: int, dt: float, segment_seconds: float, blocks: int = 1) -> int:
    """How many Welch segments (50 % overlap, as :func:`tubeid.dynamics.spectra.psd_matrix`) an
    estimate averages over ``blocks`` records of ``samples`` samples each."""
    nper = 2 * int(round(segment_seconds / (2.0 * dt)))
    step = nper - min(int(round(0.5 * nper)), nper - 1)
    return blocks * ((samples - nper) // step + 1) if samples >= nper else 0


def fine_segment(block_seconds: float, fine_seconds: float) -> float:
    """The fine Welch segment [s] used on blocks of ``block_seconds``: ``fine_seconds``, at most half
    a block (so each block holds at least three half-overlapping segments)."""
    return min(float(fine_seconds), 0.5 * float(block_seconds))


def kept_bins(f: np.ndarray, f_max: float | None) -> slice:
    """The bins of a spectrum on frequencies ``f`` (uniform from 0) that the diagnosis keeps: all of
    them when ``f_max`` is None, else those at or below ``f_max`` [Hz] and the next one (the edge
    bin :func:`analysis_bins` drops, as it drops the Nyquist bin of a whole spectrum)."""
    if f_max is None:
        return slice(None)
    return slice(0, min(int(np.searchsorted(f, f_max * (1 + 1e-12), side="right")) + 1, f.size))


def block_observations(blocks: np.ndarray, dt: float, segment_seconds: float, fine_seconds: float | None,
                       residual: bool = True, f_max: float | None = None) -> dict:
    """What the test's statistics read of records cut into blocks (..., n_blocks, L, m), each
    quantity averaged over the blocks: ``psd`` (..., F, m) at ``segment_seconds``, ``stats``
    (..., m, 3) of all the blocks' samples and the frequencies ``frequency`` (F,) [Hz]; unless
    ``fine_seconds`` is None (nothing reads them), also ``fine`` (..., F', m) at ``fine_seconds``
    with ``frequency_fine`` (F',) [Hz] and, with ``residual``, ``residual`` (..., F, m) [m²/Hz]
    from the block-averaged PSD matrix. Spectra end at ``f_max`` [Hz] (:func:`kept_bins`; None:
    at the Nyquist frequency); ``stats`` read every sample."""
    y = blocks.reshape(blocks.shape[:-3] + (-1, blocks.shape[-1]))
    if fine_seconds is not None and residual:  # the cross spectra are read
        f, S = psd_matrix(blocks, dt, segment_seconds=segment_seconds)
        k = kept_bins(f, f_max)
        f, S = f[k], S[..., k, :, :]
        # the diagonal averaged as the auto-PSDs are (a complex mean divides by a complex count: 1 ulp
        # off the real mean for block counts that are not powers of 2)
        out = {"frequency": f, "psd": np.real(np.diagonal(S, axis1=-2, axis2=-1)).mean(axis=-3),
               "residual": conditional_psd(S.mean(axis=-4))}
    else:  # the auto-PSDs only: psd_matrix's diagonal, bit for bit
        f, P = auto_psd(blocks, dt, segment_seconds)
        k = kept_bins(f, f_max)
        out = {"frequency": f[k], "psd": P[..., k, :].mean(axis=-3)}
    out["stats"] = time_statistics(y)
    if fine_seconds is not None:
        ff, Pf = auto_psd(blocks, dt, fine_seconds)
        k = kept_bins(ff, f_max)
        out |= {"frequency_fine": ff[k], "fine": Pf[..., k, :].mean(axis=-3)}
    return out


def auto_psd(blocks: np.ndarray, dt: float, segment_seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """Records (..., n_t, m) → frequencies (F,) [Hz] and auto-PSDs (..., F, m) [m²/Hz, two-sided]."""
    return welch_auto_psd(blocks, dt, segment_seconds=segment_seconds)


def time_statistics(y: np.ndarray) -> np.ndarray:
    """RMS [m], skewness and excess kurtosis per channel of records y (..., n_t, m) → (..., m, 3)."""
    c = y - y.mean(axis=-2, keepdims=True)
    c2 = c * c  # products, not c**3 and c**4: numpy's power calls pow() per element (8x slower)
    var = np.mean(c2, axis=-2)
    sd = np.sqrt(var)
    safe = np.where(var > 0, var, 1.0)
    skew = np.mean(c2 * c, axis=-2) / safe**1.5
    kurt = np.mean(c2 * c2, axis=-2) / safe**2 - 3.0
    return np.stack([sd, skew, kurt], axis=-1)


def _split(y: np.ndarray, blocks: int) -> tuple[np.ndarray, np.ndarray, int]:
    """(n_t, m) → even blocks, odd blocks (n_b, L, m), L."""
    L = y.shape[-2] // blocks
    cut = y[: L * blocks].reshape(blocks, L, y.shape[-1])
    return cut[0::2], cut[1::2], L


def measured_spectra(data: xr.Dataset, blocks: int, segment_seconds: float, fine_seconds: float = 8.0,
                     f_max: float | None = None) -> MeasuredSpectra:
    """Fitting and held-out spectra of a validated record (``displacement`` (time, sensor) [m]);
    the fine segment is :func:`fine_segment` of the block length and ``fine_seconds``; spectra end
    at ``f_max`` [Hz] (:func:`kept_bins`; None: at the Nyquist frequency)."""
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
    fine = fine_segment(L * dt, fine_seconds)
    f, S_fit = psd_matrix(fit, dt, segment_seconds=segment_seconds)
    k = kept_bins(f, f_max)
    f, S_fit = f[k], S_fit[..., k, :, :]
    o_fit = block_observations(fit, dt, segment_seconds, fine, f_max=f_max)
    o_held = block_observations(held, dt, segment_seconds, fine, f_max=f_max)
    return MeasuredSpectra(
        frequency=f, fit=o_fit["psd"], held_out=o_held["psd"], fit_cross=S_fit,
        stats=time_statistics(held.reshape(-1, y.shape[1])), fit_stats=time_statistics(fit.reshape(-1, y.shape[1])),
        dt=dt, block_samples=L, n_fit_blocks=fit.shape[0], n_held_out_blocks=held.shape[0],
        sensors=tuple(str(s) for s in data["sensor"].values), x=tuple(float(x) for x in data["x"].values),
        tube=tuple(str(x) for x in data["tube"].values), fine_seconds=fine, frequency_fine=o_fit["frequency_fine"],
        fit_fine=o_fit["fine"], held_out_fine=o_held["fine"], fit_residual=o_fit["residual"],
        held_out_residual=o_held["residual"])
