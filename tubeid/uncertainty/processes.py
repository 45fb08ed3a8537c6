"""Gaussian vector load processes from a matrix PSD: FFT spectral representation (Shinozuka).

Synthesis (periodic, period N dt): with N the FFT length (``scipy.fft.next_fast_len`` of the
number of output samples n_t, real transforms) and Δf = 1 / (N dt),

    F(t_j) = sum_{k=-N/2}^{N/2} X_k exp(2 i pi f_k t_j),   f_k = k Δf,   X_{-k} = conj X_k,

where for 1 <= k with f_k <= band, X_k = A_k (a_k + i b_k) / sqrt(2) is a circular complex
Gaussian vector with E[X_k X_k^*] = A_k A_k^* = S(f_k) Δf (a_k, b_k ~ N(0, I_m); A_k a PSD-safe
factor of S(f_k) Δf, see :func:`tubeid.uncertainty.loads.psd_factor`), and X_0 =
Re(A_0 (a_0 + i b_0)) is real with covariance S(0) Δf (the DC bin is included, so the sample variance is the Riemann sum
of int S df over the whole band). Bins above the band are zero; the Nyquist bin is zero
because 1/(2 dt) > band is required. Real output via ``irfft``. The N-periodic series is cut
to its first n_t = round(duration / dt) + 1 samples, t_j = j dt, j = 0..n_t-1 (any window of a
stationary periodic process is stationary; n_t <= N).

Resulting series are exactly Gaussian and stationary with Cov(F(t+τ), F(t)) = sum_k S(f_k) Δf
exp(2 i pi f_k τ), the Riemann sum of int S(f) exp(2 i pi f τ) df.

``interpolation`` says how the consumer reads the samples:

* ``"none"``: the samples themselves have the target PSD in band.
* ``"linear"`` (default; a transient solver treating the load as piecewise linear between
  samples): the continuous piecewise-linear interpolant of samples with PSD S_s has
  (phase-averaged) PSD S_s(f) sinc^4(f dt) + out-of-band images, sinc(u) = sin(pi u)/(pi u).
  The synthesis PSD is S(f) / sinc^4(f dt) in band, so the *interpolant* has the target S in
  band; the samples themselves then carry slightly more power (for a flat spectrum to 100 Hz at
  dt = 1 ms, sample variance +2.24 %; at the band edge the compensation factor is 1/0.936).

Randomness: one ``numpy.random.Generator`` per realisation (e.g. ``rng_for(seed, "load", r)``);
realisation r depends only on ``rngs[r]``, so results do not depend on the batch composition.
Memory: about R * N * m * 24 bytes (complex coefficients plus real output).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import scipy.fft

from tubeid.errors import SpecificationError
from tubeid.uncertainty.loads import check_psd_matrices, psd_factor

__all__ = ["gaussian_loads", "synthesis_grid", "INTERPOLATIONS"]

INTERPOLATIONS = ("linear", "none")


def synthesis_grid(duration: float, dt: float) -> tuple[int, int]:
    """(n_t, N): number of output samples round(duration/dt) + 1 and the FFT length N >= n_t."""
    duration = _positive("duration", duration, "s")
    dt = _positive("dt", dt, "s")
    n_steps = int(round(duration / dt))
    if n_steps < 1:
        raise SpecificationError("duration", duration, f"must be at least one time step dt = {dt:g} s")
    n_t = n_steps + 1
    return n_t, int(scipy.fft.next_fast_len(n_t, real=True))


def gaussian_loads(spectrum, duration: float, dt: float, rngs: Sequence[np.random.Generator],
                   interpolation: str = "linear") -> np.ndarray:
    """Realisations of the centred stationary Gaussian load with two-sided PSD ``spectrum.matrix(f)``.

    spectrum : a LoadSpectrum (or any object with ``matrix(f)``, ``band`` [Hz] and ``names``).
    duration, dt : s; output samples at t_j = j dt, j = 0 .. round(duration/dt).
    rngs : one numpy Generator per realisation.
    interpolation : "linear" (pre-compensated for piecewise-linear reading) or "none".

    Returns float64 array (R, n_t, m), units of each load (N or N m). See module docstring.
    """
    if interpolation not in INTERPOLATIONS:
        raise SpecificationError("interpolation", interpolation, f"must be one of {INTERPOLATIONS}")
    for attr in ("matrix", "band", "names"):
        if not hasattr(spectrum, attr):
            raise SpecificationError("spectrum", type(spectrum).__name__, f"must have a '{attr}' (a LoadSpectrum)")
    band = _positive("spectrum.band", spectrum.band, "Hz")
    n_t, N = synthesis_grid(duration, dt)
    dt = float(dt)
    if not 1.0 / (2.0 * dt) > band:
        raise SpecificationError("dt", dt, f"must resolve the band: Nyquist 1/(2 dt) = {1 / (2 * dt):g} Hz "
                                 f"must exceed band = {band:g} Hz")
    if isinstance(rngs, np.random.Generator) or not isinstance(rngs, Sequence) or len(rngs) == 0:
        raise SpecificationError("rngs", type(rngs).__name__, "must be a non-empty sequence of numpy Generators "
                                 "(one per realisation)")
    for r, g in enumerate(rngs):
        if not isinstance(g, np.random.Generator):
            raise SpecificationError(f"rngs[{r}]", type(g).__name__, "must be a numpy.random.Generator")
    m = len(spectrum.names)

    df = 1.0 / (N * dt)
    K = int(np.floor(band / df * (1 + 1e-12)))  # bins 0..K lie in |f| <= band
    K = min(K, (N - 1) // 2)  # never the Nyquist bin (1/(2dt) > band makes this a no-op)
    fk = np.arange(K + 1) * df
    S = np.asarray(spectrum.matrix(fk))
    if S.shape != (K + 1, m, m):
        raise SpecificationError("spectrum.matrix(f)", S.shape, f"must have shape (len(f), {m}, {m})")
    check_psd_matrices(fk, S, field="S(f)")
    power = S * df
    if interpolation == "linear":
        power = power / (np.sinc(fk * dt) ** 4)[:, None, None]
    A = psd_factor(power)  # A^* A = S df  ->  B = A^* satisfies B B^* = S df
    B = np.conj(np.swapaxes(A, -1, -2))

    R = len(rngs)
    coef = np.zeros((R, N // 2 + 1, m), dtype=complex)
    for r, g in enumerate(rngs):  # draws only: one generator per realisation
        z = g.standard_normal((K + 1, m, 2))
        zc = (z[..., 0] + 1j * z[..., 1]) / np.sqrt(2.0)
        coef[r, : K + 1] = (B @ zc[..., None])[..., 0]
    # DC: real Gaussian with covariance S(0) df. For w = a + i b (E[w w^*] = 2 I), Re(B w) has
    # covariance Re(B B^*) = S(0) df whatever the (possibly complex) factor B of the real S(0).
    coef[:, 0] = np.sqrt(2.0) * coef[:, 0].real
    coef *= N  # irfft divides by N
    x = scipy.fft.irfft(coef, n=N, axis=1)
    return np.ascontiguousarray(x[:, :n_t, :], dtype=np.float64)


def _positive(name, value, unit) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise SpecificationError(name, value, f"must be a number ({unit})") from None
    if not np.isfinite(v) or v <= 0:
        raise SpecificationError(name, value, f"must be > 0 and finite ({unit})")
    return v
