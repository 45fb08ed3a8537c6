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
Each realisation draws exactly (K + 1) x m x 2 standard normals (bins 0..K, |f_k| <= band, in
that order); bins outside the band consume nothing.

Cost. A spectrum constant in the band (a ``LoadSpectrum`` without frequency grid, germ or not,
or any spectrum whose matrices are equal at every in-band bin) is checked and factorised ONCE:
B_k = c_k B with B B^* = S and the scalar c_k = sqrt(df)/sinc^2(f_k dt) (Cholesky factors
scale exactly like this; for a singular S the eigen factor is used, same law). Tabulated
spectra are factorised per bin (an interpolated factor is not a factor of the interpolated
matrix). The transform is one ``scipy.fft.irfft`` per load on a contiguous axis (workers=1),
N = next_fast_len(n_t), in single precision: the load changes by ~2e-7 of itself (a white floor
~135 dB below it); the draws and factors stay float64, the output is float64. Its time is
``seconds_load_generation`` of ``tubeid bench transient``. Memory: about R * N * m * 16 bytes
(complex64 coefficients, the float32 transform, the float64 output).
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Sequence

import numpy as np
import scipy.fft

from tubeid.errors import SpecificationError
from tubeid._validation import allocation, positive
from tubeid.uncertainty.loads import check_psd_matrices, psd_factor

if TYPE_CHECKING:
    from tubeid.uncertainty.loads import LoadSpectrum

__all__ = ["gaussian_loads", "synthesis_grid", "INTERPOLATIONS"]

INTERPOLATIONS = ("linear", "none")


def synthesis_grid(duration: float, dt: float) -> tuple[int, int]:
    """The sample count and FFT length of a synthesis.

    Parameters
    ----------
    duration : float
        Record length [s], at least one step.
    dt : float
        Sampling step [s].

    Returns
    -------
    n_t : int
        Number of output samples, round(duration/dt) + 1.
    N : int
        FFT length (``scipy.fft.next_fast_len(n_t, real=True)``), N >= n_t.
    """
    duration = positive("duration", duration, "s")
    dt = positive("dt", dt, "s")
    n_steps = int(round(duration / dt))
    if n_steps < 1:
        raise SpecificationError("duration", duration, f"must be at least one time step dt = {dt:g} s")
    n_t = n_steps + 1
    return n_t, int(scipy.fft.next_fast_len(n_t, real=True))


def resolving_step(field: str, dt: float, band: float) -> float:
    """A sampling step [s] whose Nyquist frequency 1/(2 dt) exceeds ``band`` [Hz], as ``float``.

    Parameters
    ----------
    field : str
        How a refusal names the step (``"dt"``, ``"--dt-load"``).
    dt : float
        The step [s], > 0.
    band : float
        The load's band [Hz], > 0.

    Returns
    -------
    float
        ``dt``.
    """
    dt = positive(field, dt, "s")
    if not 1.0 / (2.0 * dt) > band:
        raise SpecificationError(field, dt, f"must resolve the band: Nyquist 1/(2 dt) = {1 / (2 * dt):g} Hz "
                                 f"must exceed band = {band:g} Hz")
    return dt


def gaussian_loads(spectrum: LoadSpectrum, duration: float, dt: float, rngs: Sequence[np.random.Generator],
                   interpolation: str = "linear", out: np.ndarray | None = None) -> np.ndarray:
    """Realisations of the centred stationary Gaussian load with two-sided PSD ``spectrum.matrix(f)``.

    See the module docstring for the synthesis, its law and its cost.

    Parameters
    ----------
    spectrum : LoadSpectrum
        The load PSD (or any object with ``matrix(f)``, ``band`` [Hz] and ``names``).
    duration : float
        Record length [s].
    dt : float
        Sampling step [s]; output samples at t_j = j dt, j = 0 .. round(duration/dt). Its
        Nyquist frequency 1/(2 dt) must exceed the band.
    rngs : sequence of numpy.random.Generator
        One generator per realisation; realisation r depends on ``rngs[r]`` only.
    interpolation : str
        ``"linear"`` (pre-compensated so that the piecewise-linear interpolant has the target
        PSD in band) or ``"none"`` (the samples have it).
    out : numpy.ndarray, optional
        A writeable C-contiguous float64 array of shape (R, n_t, m) to write the result into
        (e.g. a batch's rows: no new array, no copy by the caller); the values are the same.

    Returns
    -------
    numpy.ndarray
        float64, shape (R, n_t, m), in the units of each load (N or N m): ``out`` if given.
    """
    if interpolation not in INTERPOLATIONS:
        raise SpecificationError("interpolation", interpolation, f"must be one of {INTERPOLATIONS}")
    for attr in ("matrix", "band", "names"):
        if not hasattr(spectrum, attr):
            raise SpecificationError("spectrum", type(spectrum).__name__, f"must have a '{attr}' (a LoadSpectrum)")
    band = positive("spectrum.band", spectrum.band, "Hz")
    n_t, N = synthesis_grid(duration, dt)
    dt = resolving_step("dt", dt, band)
    if isinstance(rngs, np.random.Generator) or not isinstance(rngs, Sequence) or len(rngs) == 0:
        raise SpecificationError("rngs", type(rngs).__name__, "must be a non-empty sequence of numpy Generators "
                                 "(one per realisation)")
    for r, g in enumerate(rngs):
        if not isinstance(g, np.random.Generator):
            raise SpecificationError(f"rngs[{r}]", type(g).__name__, "must be a numpy.random.Generator")
    m = len(spectrum.names)
    R = len(rngs)
    if out is not None:
        ok = (isinstance(out, np.ndarray) and out.dtype == np.float64 and out.flags.c_contiguous
              and out.flags.writeable)
        if not ok or out.shape != (R, n_t, m):
            raise SpecificationError("out", getattr(out, "shape", type(out).__name__),
                                     f"must be a writeable C-contiguous float64 array of shape (R, n_t, m) = "
                                     f"{(R, n_t, m)}")

    df = 1.0 / (N * dt)
    K = int(np.floor(band / df * (1 + 1e-12)))  # bins 0..K lie in |f| <= band
    K = min(K, (N - 1) // 2)  # never the Nyquist bin (1/(2dt) > band makes this a no-op)
    allocation("duration", duration, R * m * ((N // 2 + 1) * 8.0 + N * 4.0 + (0 if out is not None else n_t * 8.0)),
               f"the synthesis of {R} realisation(s) of {m} load(s) over {n_t} samples")
    scale = _bin_scale(K, N, dt, interpolation)
    B = _factors(spectrum, K, df, m)  # (m, m): one factor for every in-band bin, or (K + 1, m, m)

    # FFT axis last (contiguous transforms), single precision (see the module docstring).
    coef = np.empty((R, m, N // 2 + 1), dtype=np.complex64)
    coef[:, :, K + 1:] = 0.0  # bins 0..K are written below
    for r, g in enumerate(rngs):  # draws only for bins 0..K: one generator per realisation
        z = g.standard_normal((K + 1, m, 2))
        zc = z.view(np.complex128)[..., 0]
        np.multiply(zc, np.sqrt(0.5), out=zc)  # (a + i b) / sqrt(2), in place
        if B.ndim == 2:
            np.multiply(B @ zc.T, scale, out=coef[r, :, : K + 1])
        else:
            np.multiply((B @ zc[..., None])[..., 0].T, scale, out=coef[r, :, : K + 1])
    # DC: real Gaussian with covariance S(0) df. For w = a + i b (E[w w^*] = 2 I), Re(B w) has
    # covariance Re(B B^*) = S(0) df whatever the (possibly complex) factor B of the real S(0).
    coef[:, :, 0] = np.float32(np.sqrt(2.0)) * coef[:, :, 0].real
    x = scipy.fft.irfft(coef, n=N, axis=-1, workers=1, overwrite_x=True)  # coef is scratch
    out = np.empty((R, n_t, m)) if out is None else out
    np.copyto(out, np.swapaxes(x[:, :, :n_t], 1, 2))  # float32 -> float64: exact
    return out


@functools.lru_cache(maxsize=8)
def _bin_scale(K: int, N: int, dt: float, interpolation: str) -> np.ndarray:
    """Per-bin amplitude scale of bins 0..K (read-only): coef_k = N sqrt(df) c_k B_k w_k, df =
    1/(N dt), c_k = 1/sinc^2(f_k dt) ("linear") or 1; N undoes irfft's 1/N. B_k B_k^* = S(f_k),
    so E[X X^*] = c_k^2 S(f_k) df. Cached: it depends on the grid only (every realisation of a
    study has the same)."""
    df = 1.0 / (N * dt)
    fk = np.arange(K + 1) * df
    scale = np.full(K + 1, N * np.sqrt(df))
    if interpolation == "linear":
        scale /= np.sinc(fk * dt) ** 2
    scale.setflags(write=False)
    return scale


def _factors(spectrum, K, df, m) -> np.ndarray:
    """B with B B^* = S(f): one (m, m) factor when S is the same matrix at every bin f_k = k df,
    k = 0..K (constant spectrum), else one per bin (K + 1, m, m). Each distinct matrix is checked once."""
    from tubeid.uncertainty.loads import LoadSpectrum

    if isinstance(spectrum, LoadSpectrum) and spectrum.frequencies is None:
        S = np.asarray(spectrum.matrix(np.zeros(1)))  # f_0 = 0: constant on |f| <= band (germ included)
        per_bin = False
    else:
        fk = np.arange(K + 1) * df
        S = np.asarray(spectrum.matrix(fk))
        if S.shape != (fk.size, m, m):
            raise SpecificationError("spectrum.matrix(f)", S.shape, f"must have shape (len(f), {m}, {m})")
        per_bin = not np.all(S == S[:1])
        if not per_bin:
            S = S[:1]
    if not isinstance(spectrum, LoadSpectrum):  # a LoadSpectrum was checked when built (interpolation and germ keep it PSD)
        check_psd_matrices(fk[: len(S)], S, field="S(f)")
    A = psd_factor(S)  # A^* A = S  ->  B = A^* satisfies B B^* = S
    B = np.conj(np.swapaxes(A, -1, -2))
    return B if per_bin else B[0]


