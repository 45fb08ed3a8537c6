"""Matrix PSD estimation (Welch) and the spectral functionals of the identification.

Convention: **two-sided PSD per Hz**, S_ab(f) = lim E[X̂_a(f) conj(X̂_b(f))] / T, i.e. the
Fourier transform of R_ab(tau) = E[x_a(t + tau) x_b(t)]; S(-f) = conj S(f), and
Var(x_a) = int_{-inf}^{inf} S_aa(f) df. Estimates are returned for f >= 0 only (0 .. Nyquist);
the negative half is implied by S(-f) = conj S(f).

Estimator: Welch (``scipy.signal.csd``): segments of ``segment_seconds`` (an even number of
samples, so the last bin is the Nyquist frequency), window (Hann by default), overlap (50 % by
default), "density" scaling; the one-sided output of scipy is halved except at DC and Nyquist to
give the two-sided density. A record of duration T split into 2 s segments with 50 % overlap
averages about T - 1 segments: each bin has a relative standard deviation ~ 1/sqrt(0.75 (T - 1)).

Functionals (ω in rad/s, dω = 2π df):

    J_s = int_B ||S(ω)||_F^2 dω,   D = int_B ||S_model(ω) - S_exp(ω)||_F^2 dω,

over B: ω ∈ 2π [-band, band], both signs counted (||S(-f)||_F = ||S(f)||_F, so the integral is
2 * 2π * int_0^band ||S(f)||_F^2 df, trapezoid rule in f). If S is in m^2/Hz, J_s and D are in
(m^2/Hz)^2 rad/s.

The *log level* of a record (:func:`log_level`) is the mean, over the bands (a, a + w] that tile
(0, band] and over the sensors, of the natural log of the band energy Σ_{f in band} S_aa(f) Δf
[m²]: a scale factor c on the PSD moves it by exactly log c, and it averages the estimation noise of
many bands (J_s, dominated by a few resonance bins, does not).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import xarray as xr
from numpy.typing import ArrayLike

from tubeid._validation import is_numeric_dtype, numeric_array, open_unit, positive, real
from tubeid.errors import Described, SpecificationError

__all__ = ["psd_matrix", "auto_psd", "psd_dataset", "variance_from_psd", "confidence_band", "j_s", "distance", "log_level",
           "log_band_energies"]

_DETRENDS = (False, "constant", "linear")


def _window(window: Any, n: int) -> np.ndarray:
    """``scipy.signal.get_window(window, n)`` (periodic, for spectral analysis). The default
    ``"hann"`` is computed here as scipy computes it (0.5 + 0.5 cos of ``linspace(-π, π, n + 1)``,
    the last point dropped): importing ``scipy.signal`` costs ~0.5 s, paid by every process that
    imports this module (a study's workers, each ``tubeid`` command). Other windows import it.
    An array is the window itself: 1-D, finite real numbers, of length n (the segment's samples).
    Negative weights are allowed (scipy's own ``"flattop"`` has some); all-zero weights are refused
    by the caller (:func:`_welch_transforms`), as is any window whose Σw² is not finite and > 0."""
    if not isinstance(window, (str, tuple)):
        w = numeric_array("window", window, finite=False, dtype=float)
        if w.shape != (n,) or not np.all(np.isfinite(w)):
            raise SpecificationError("window", f"array of shape {w.shape}", f"must be 1-D and finite, with one weight "
                                                                             f"per sample of a segment ({n})")
        return w
    if window == "hann":
        if n <= 1:
            return np.ones(n)
        fac = np.linspace(-np.pi, np.pi, n + 1)
        w = np.zeros(n + 1)
        w += 0.5 * np.cos(0.0 * fac)
        w += 0.5 * np.cos(fac)
        return w[:-1]
    import scipy.signal

    return scipy.signal.get_window(window, n)


#: Largest Welch overlap: a hop of at least 5 % of the segment (the segments take at most 20 times the
#: record's memory; 0.9999 made one segment per sample and a MemoryError).
MAX_OVERLAP = 0.95


def _segment_length(segment_seconds, dt, n_t) -> int:
    seg = positive("segment_seconds", segment_seconds, "s")
    nper = 2 * int(round(seg / (2.0 * dt)))
    if nper < 2:
        raise SpecificationError("segment_seconds", segment_seconds, f"must span at least 2 samples of dt = {dt:g} s")
    if nper > n_t:
        raise SpecificationError("segment_seconds", segment_seconds,
                                 f"segment of {nper} samples is longer than the record ({n_t} samples, "
                                 f"{n_t * dt:g} s)")
    return nper


def psd_matrix(x: ArrayLike, dt: float, segment_seconds: float = 2.0, window: Any = "hann", overlap: float = 0.5,
               detrend: bool | str = False) -> tuple[np.ndarray, np.ndarray]:
    """Welch estimate of the two-sided matrix PSD per Hz of real records.

    Parameters
    ----------
    x : array_like
        Real records, shape (..., n_t, m), finite (complex, boolean or time-typed records are
        refused, never truncated or reinterpreted).
    dt : float
        Sample interval (s), a finite number > 0.
    segment_seconds : float
        Welch segment length (s; rounded to an even number of samples, at most the record).
    window : str, tuple or array_like
        Any ``scipy.signal.get_window`` specification, or the weights themselves (n finite real
        numbers for a segment of n samples; negative weights allowed, as in scipy's ``"flattop"``,
        but not all zero).
    overlap : float
        Fraction of a segment shared with the next, in [0, 0.95] (:data:`MAX_OVERLAP`).
    detrend : bool or str
        False, ``"constant"`` or ``"linear"`` (per segment).

    Returns
    -------
    f : numpy.ndarray
        (F,) in Hz from 0 to the Nyquist frequency 1/(2 dt) inclusive.
    S : numpy.ndarray
        (..., F, m, m) complex, S[..., k, a, b] = S_ab(f_k) in [x]^2/Hz, Hermitian per bin.
    """
    f, X, scale = _welch_transforms(x, dt, segment_seconds, window, overlap, detrend)
    m = X.shape[-3]
    S = np.einsum("...asf,...bsf->...fab", X, np.conj(X)) * (scale / X.shape[-2])
    idx = np.arange(m)
    S[..., idx, idx] = S[..., idx, idx].real
    return f, S


def auto_psd(x: ArrayLike, dt: float, segment_seconds: float = 2.0, window: Any = "hann", overlap: float = 0.5,
             detrend: bool | str = False) -> tuple[np.ndarray, np.ndarray]:
    """The diagonal of :func:`psd_matrix` (same arguments, same estimator) without the cross
    spectra: m products per bin and segment instead of m².

    Returns
    -------
    f : numpy.ndarray
        (F,) in Hz from 0 to the Nyquist frequency.
    P : numpy.ndarray
        (..., F, m) real, P[..., k, a] = S_aa(f_k) in [x]^2/Hz.
    """
    f, X, scale = _welch_transforms(x, dt, segment_seconds, window, overlap, detrend)
    P = np.sum(X.real**2 + X.imag**2, axis=-2) * (scale / X.shape[-2])  # (..., m, F)
    return f, np.moveaxis(P, -2, -1)


def _welch_transforms(x, dt, segment_seconds, window, overlap, detrend) -> tuple[np.ndarray, np.ndarray, float]:
    """The checked arguments' Welch segments, windowed and transformed: f (F,) [Hz], X (..., m,
    n_seg, F) and the density scale dt/Σw² [s]."""
    x = numeric_array("x", x, finite=False, dtype=float)  # real: complex records are refused, not truncated
    if x.ndim < 2:
        raise SpecificationError("x", x.shape, "must have shape (..., n_t, m)")
    if not np.all(np.isfinite(x)):
        raise SpecificationError("x", "non-finite", "records must be finite")
    dt = positive("dt", dt, "s")
    n_t = x.shape[-2]
    nper = _segment_length(segment_seconds, dt, n_t)
    ov = real("overlap", overlap, low=0.0, high=1.0, high_open=True)
    if ov > MAX_OVERLAP:  # every segment is transformed at once: memory grows as 1/(1 − overlap)
        raise SpecificationError("overlap", overlap, f"must be at most {MAX_OVERLAP:g} (a hop of at least "
                                 f"{1 - MAX_OVERLAP:.0%} of the segment: the segments, held at once, take "
                                 "1/(1 − overlap) times the record's memory)")
    noverlap = min(int(round(ov * nper)), nper - 1)
    if detrend is not False and detrend not in _DETRENDS:
        raise SpecificationError("detrend", detrend, f"must be one of {_DETRENDS}")
    try:
        win = _window(window, nper)
    except SpecificationError:
        raise
    except (ValueError, TypeError) as exc:
        raise SpecificationError("window", window, f"not a scipy window ({exc})") from None
    sum_w2 = float(np.sum(win * win))
    if not (math.isfinite(sum_w2) and sum_w2 > 0):
        raise SpecificationError("window", Described(f"weights with sum of squares {sum_w2!r}"),
                                 "the weights must not all be zero (the density is scaled by 1/Σw², finite and > 0)")

    xt = np.moveaxis(x, -1, -2)  # (..., m, n_t)
    # Welch as scipy.signal.csd (no boundary padding, segments from t = 0, mean over segments), but
    # one FFT per channel instead of one csd per channel pair: S_ab = mean_s X_a conj(X_b) / (fs Σw²).
    step = nper - noverlap
    seg = np.lib.stride_tricks.sliding_window_view(xt, nper, axis=-1)[..., ::step, :]  # (..., m, n_seg, nper)
    if detrend:
        import scipy.signal  # only here: see _window

        seg = scipy.signal.detrend(seg, type=detrend, axis=-1)
    X = np.fft.rfft(seg * win, axis=-1)  # (..., m, n_seg, F)
    return np.asarray(np.fft.rfftfreq(nper, dt), dtype=float), X, dt / sum_w2


def psd_dataset(x: ArrayLike | xr.DataArray, dt: float | None = None, segment_seconds: float = 2.0,
                window: Any = "hann", overlap: float = 0.5, detrend: bool | str = False,
                sensors: Sequence[str] | None = None, dims: Sequence[str] | None = None,
                units: str = "m") -> xr.DataArray:
    """Labelled Welch matrix PSD (see :func:`psd_matrix` for the estimator).

    Parameters
    ----------
    x : array_like or xarray.DataArray
        Records (..., n_t, m), or a DataArray with dims (..., "time", "sensor") whose uniform
        "time" coordinate (s) gives dt and whose coordinates (sensor names, and non-index "x",
        "tube" on "sensor") are carried over. The time coordinate must be numbers of seconds: a
        ``timedelta64`` or ``datetime64`` coordinate is refused (convert it, e.g.
        ``t / np.timedelta64(1, "s")``), never read as counts of its unit.
    dt : float, optional
        Sample interval (s); required for array input. For a DataArray with a time coordinate
        (of at least 2 samples), a given dt must agree with the coordinate's uniform step
        (relative 1e-6); a disagreement is refused.
    segment_seconds : float
        Welch segment length (s).
    window : str, tuple or array_like
        Any ``scipy.signal.get_window`` specification.
    overlap : float
        Segment overlap fraction in [0, 1).
    detrend : bool or str
        False, ``"constant"`` or ``"linear"``.
    sensors : sequence of str, optional
        Channel names for array input (default ``"s0"``, ``"s1"``, ...).
    dims : sequence of str, optional
        Names of the leading dims for array input (default ``("realisation",)`` for one,
        else ``"batch0"``, ...).
    units : str
        Unit of x (a DataArray's ``units`` attribute wins).

    Returns
    -------
    xarray.DataArray
        ``psd`` with dims (*leading, "frequency", "sensor", "sensor_"), ``units`` attribute
        f"{units}^2/Hz" (two-sided), frequency in Hz.
    """
    coords: dict = {}
    sensor_extra = {}
    if dt is not None:
        dt = positive("dt", dt, "s")
    if isinstance(x, xr.DataArray):
        if "time" not in x.dims or "sensor" not in x.dims:
            raise SpecificationError("x.dims", x.dims, "must contain 'time' and 'sensor'")
        lead = [d for d in x.dims if d not in ("time", "sensor")]
        xv = x.transpose(*lead, "time", "sensor")
        if "time" in x.coords and not is_numeric_dtype(x["time"].dtype):
            raise SpecificationError("x.time.dtype", str(x["time"].dtype),
                                     "time must be numeric seconds (convert a timedelta64 coordinate with "
                                     "t / np.timedelta64(1, 's'))")
        if dt is None and ("time" not in x.coords or x.sizes["time"] < 2):
            raise SpecificationError("x.time", None, "a time coordinate (s) is needed when dt is not given")
        if "time" in x.coords and x.sizes["time"] >= 2:
            t = np.asarray(x["time"].values, dtype=float)
            steps = np.diff(t)
            dt_time = float(np.mean(steps))
            if not np.allclose(steps, dt_time, rtol=1e-6, atol=0):
                raise SpecificationError("x.time", "non-uniform", "sampling must be uniform")
            if dt is None:
                dt = dt_time
            elif not abs(dt - dt_time) <= 1e-6 * abs(dt_time):
                raise SpecificationError("dt", dt, f"disagrees with the step of the time coordinate x.time, "
                                                   f"{dt_time!r} s (relative tolerance 1e-6)")
        dims_lead = tuple(lead)
        for d in lead:
            if d in x.coords:
                coords[d] = x[d].values
        sensor_names = x["sensor"].values if "sensor" in x.coords else np.array([f"s{i}" for i in range(x.sizes["sensor"])])
        for name, c in x.coords.items():
            if name != "sensor" and c.dims == ("sensor",):
                sensor_extra[name] = c.values
        units = x.attrs.get("units", units)
        data = xv.values
    else:
        data = np.asarray(x)
        if dt is None:
            raise SpecificationError("dt", None, "is required for array input (s)")
        if data.ndim < 2:
            raise SpecificationError("x", data.shape, "must have shape (..., n_t, m)")
        nlead = data.ndim - 2
        if dims is None:
            dims_lead = ("realisation",) if nlead == 1 else tuple(f"batch{i}" for i in range(nlead))
        else:
            dims_lead = tuple(dims)
            if len(dims_lead) != nlead:
                raise SpecificationError("dims", dims, f"must name the {nlead} leading dimension(s)")
        m = data.shape[-1]
        sensor_names = np.array([f"s{i}" for i in range(m)] if sensors is None else list(sensors))
        if sensor_names.size != m:
            raise SpecificationError("sensors", sensors, f"must name the {m} channels")
    f, S = psd_matrix(data, dt, segment_seconds=segment_seconds, window=window, overlap=overlap, detrend=detrend)
    coords["frequency"] = ("frequency", f, {"units": "Hz"})
    coords["sensor"] = sensor_names
    coords["sensor_"] = sensor_names
    for name, vals in sensor_extra.items():
        coords[name] = ("sensor", vals)
        coords[name + "_"] = ("sensor_", vals)
    return xr.DataArray(
        S, dims=dims_lead + ("frequency", "sensor", "sensor_"), coords=coords, name="psd",
        attrs={"units": f"{units}^2/Hz", "convention": "two-sided PSD per Hz, f >= 0 stored, S(-f) = conj S(f)",
               "estimator": f"Welch, window={window!r}, segment={segment_seconds} s, overlap={overlap}",
               "dt": float(dt)})


def variance_from_psd(f: ArrayLike, S: ArrayLike, nyquist_last: bool = True) -> np.ndarray:
    """Variances int_{-inf}^{inf} S_aa(f) df from the f >= 0 half of a two-sided PSD.

    Rectangle rule on the symmetric bins: Δf (S(0) + 2 sum_{0<f_k<f_N} S(f_k) + S(f_N)), the DC
    bin and, if ``nyquist_last``, the Nyquist bin counted once (exact discrete Parseval for a
    periodogram).

    Parameters
    ----------
    f : array_like
        Uniform grid 0, Δf, 2Δf, ... (Hz), Δf > 0: increasing from 0.
    S : array_like
        (..., F, m, m) matrix PSD or (..., F) auto-spectra, two-sided per Hz, finite.
    nyquist_last : bool
        Whether the last bin is the Nyquist frequency (as :func:`psd_matrix` returns).

    Returns
    -------
    numpy.ndarray
        (..., m) for matrices, (...) for auto-spectra, in [x]^2.
    """
    f = numeric_array("f", f, dtype=float)
    S = numeric_array("S", S, complex_ok=True)
    if f.ndim != 1 or f.size < 2 or f[0] != 0.0:
        raise SpecificationError("f", f, "must be a 1-D uniform grid starting at 0 Hz")
    df = f[1] - f[0]
    if not df > 0:
        raise SpecificationError("f", Described(f"{f.size} bins, f[1] = {f[1]:g} Hz"), "must increase from 0 Hz (Δf > 0)")
    if not np.allclose(np.diff(f), df, rtol=1e-9, atol=0):
        raise SpecificationError("f", f, "must be uniform")
    if S.ndim == 0:
        raise SpecificationError("S", S.shape, f"must be (..., {f.size}, m, m) or (..., {f.size})")
    if S.ndim >= 3 and S.shape[-1] == S.shape[-2] and S.shape[-3] == f.size:
        auto = np.diagonal(S, axis1=-2, axis2=-1).real  # (..., F, m)
        axis = -2
    elif S.shape[-1] == f.size:
        auto = S.real
        axis = -1
    else:
        raise SpecificationError("S", S.shape, f"must be (..., {f.size}, m, m) or (..., {f.size})")
    w = np.full(f.size, 2.0)
    w[0] = 1.0
    if nyquist_last:
        w[-1] = 1.0
    w = w * df
    shape = [1] * auto.ndim
    shape[axis] = f.size
    return np.sum(auto * w.reshape(shape), axis=axis)


def confidence_band(psd_samples: xr.DataArray | xr.Dataset, level: float = 0.95,
                    dim: str = "realisation") -> xr.Dataset:
    """Per-frequency confidence band of PSD realisations by the quantile method.

    For each remaining coordinate (frequency, sensor, ...), the empirical quantiles
    (1 - level)/2 and (1 + level)/2 over ``dim`` (linear interpolation between order
    statistics, numpy's default).

    Parameters
    ----------
    psd_samples : xarray.DataArray or xarray.Dataset
        Real PSD values (take ``.real`` of auto-spectra first), at least 2 along ``dim``.
    level : float
        Probability of the band, in (0, 1).
    dim : str
        The dimension of the realisations.

    Returns
    -------
    xarray.Dataset
        ``lower`` and ``upper`` (for a Dataset input: ``<name>_lower``, ``<name>_upper``),
        attributes ``level``, ``method`` and ``n_samples``; units are kept.
    """
    if not isinstance(psd_samples, (xr.DataArray, xr.Dataset)):
        raise SpecificationError("psd_samples", type(psd_samples).__name__, "must be an xarray DataArray or Dataset")
    p = open_unit("level", level)
    if dim not in psd_samples.dims:
        raise SpecificationError("dim", dim, f"is not a dimension of the samples {tuple(psd_samples.dims)}")
    if psd_samples.sizes[dim] < 2:
        raise SpecificationError(dim, psd_samples.sizes[dim], "need at least 2 realisations")
    qs = [(1.0 - p) / 2.0, (1.0 + p) / 2.0]
    if isinstance(psd_samples, xr.DataArray):
        if np.iscomplexobj(psd_samples.values):
            raise SpecificationError("psd_samples", "complex", "quantiles need real values (use .real of auto-spectra)")
        q = psd_samples.quantile(qs, dim=dim)
        units = psd_samples.attrs.get("units")
        out = xr.Dataset({"lower": q.isel(quantile=0, drop=True), "upper": q.isel(quantile=1, drop=True)})
        if units is not None:
            out["lower"].attrs["units"] = units
            out["upper"].attrs["units"] = units
    else:
        out = xr.Dataset()
        for name, da in psd_samples.data_vars.items():
            if dim not in da.dims:
                continue
            if np.iscomplexobj(da.values):
                raise SpecificationError(f"psd_samples[{name!r}]", "complex", "quantiles need real values")
            q = da.quantile(qs, dim=dim)
            out[f"{name}_lower"] = q.isel(quantile=0, drop=True).assign_attrs(da.attrs)
            out[f"{name}_upper"] = q.isel(quantile=1, drop=True).assign_attrs(da.attrs)
    out.attrs.update({"level": p, "method": f"per-frequency empirical quantiles {qs[0]:g}, {qs[1]:g} over '{dim}'",
                      "n_samples": int(psd_samples.sizes[dim])})
    return out


def _check_band_grid(f, band, npts):
    f = numeric_array("f", f, finite=False, dtype=float)
    band = positive("band", band, "Hz")
    if f.ndim != 1 or f.size < 2 or not np.all(np.isfinite(f)):
        raise SpecificationError("f", f, "must be a 1-D grid of >= 2 finite frequencies (Hz)")
    if f[0] != 0.0:
        raise SpecificationError("f", float(f[0]), "the grid must start at 0 Hz (f >= 0 half of a two-sided PSD)")
    if np.any(np.diff(f) <= 0):
        raise SpecificationError("f", f, "must be strictly increasing")
    if f[-1] < band * (1 - 1e-12):
        raise SpecificationError("band", band, f"exceeds the grid's last frequency {f[-1]:g} Hz")
    if npts != f.size:
        raise SpecificationError("S", npts, f"frequency axis (-3) must have len(f) = {f.size}")
    return f, band


def j_s(f: ArrayLike, S: ArrayLike, band: float = 100.0) -> np.ndarray:
    """J_s = int_B ||S(ω)||_F^2 dω over ω ∈ 2π[-band, band] (rad/s), both signs counted.

    Computed as 2 * 2π * int_0^band ||S(f)||_F^2 df with the trapezoid rule on the grid,
    ||S||_F^2 linearly interpolated at f = band if band is not a grid point.

    Parameters
    ----------
    f : array_like
        (F,) increasing grid in Hz from 0 (the f >= 0 half of a two-sided PSD), reaching ``band``.
    S : array_like
        (..., F, m, m) two-sided PSD per Hz, or (..., F) for a scalar PSD; finite.
    band : float
        Half-width of the band (Hz).

    Returns
    -------
    numpy.ndarray
        Shape (...), in [S]^2 * rad/s, e.g. (m^2/Hz)^2 rad/s.
    """
    return _j_s(f, numeric_array("S", S, complex_ok=True), band)


def _j_s(f, S: np.ndarray, band) -> np.ndarray:
    """:func:`j_s` of a checked (numeric, finite) S."""
    if S.ndim >= 3 and S.shape[-1] == S.shape[-2] and S.shape[-3] == np.size(f):
        n2 = np.sum(np.abs(S) ** 2, axis=(-2, -1))
    elif S.ndim >= 1:
        n2 = np.abs(S) ** 2
    else:
        raise SpecificationError("S", S.shape, "must be (..., F, m, m) or (..., F)")
    f, band = _check_band_grid(f, band, n2.shape[-1])
    inside = f <= band * (1 + 1e-12)
    fi = f[inside]
    vals = n2[..., inside]
    if fi[-1] < band * (1 - 1e-12):  # close the interval at the band edge
        k = fi.size
        edge = n2[..., k - 1] + (n2[..., k] - n2[..., k - 1]) * (band - f[k - 1]) / (f[k] - f[k - 1])
        fi = np.append(fi, band)
        vals = np.concatenate([vals, edge[..., None]], axis=-1)
    return 2.0 * 2.0 * np.pi * np.trapezoid(vals, fi, axis=-1)


def log_band_energies(P: np.ndarray, f: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """log of Σ_{f in (a, b]} S(f) Δf per band and auto-spectrum: P (..., F, m, m) → (..., B·m).

    ``f`` is the uniform grid of P (Δf = f[1] − f[0]), ``edges`` the B + 1 band edges [Hz]; a band
    without energy (≤ 0) gives −inf (the caller refuses it, naming its own field).
    """
    auto = np.real(np.diagonal(P, axis1=-2, axis2=-1))  # (..., F, m)
    df = float(f[1] - f[0])
    cols = [auto[..., (f > a) & (f <= b), :].sum(axis=-2) * df for a, b in zip(edges[:-1], edges[1:])]
    e = np.stack(cols, axis=-2)  # (..., B, m)
    e = e.reshape(e.shape[:-2] + (-1,))
    return np.where(e > 0, np.log(np.where(e > 0, e, 1.0)), -np.inf)


def log_level(f: ArrayLike, S: ArrayLike, band: float = 100.0, band_width: float = 5.0) -> np.ndarray:
    """The log level of a response: mean over bands and sensors of the log band energy (module docstring).

    Parameters
    ----------
    f : array_like
        (F,) uniform grid in Hz from 0 (the f >= 0 half of a two-sided PSD), reaching ``band`` to
        within one bin (the last band then ends at the last bin).
    S : array_like
        (..., F, m, m) two-sided PSD matrix per Hz (its auto-spectra are used), or (..., F) scalar;
        finite.
    band : float
        Upper end of the bands [Hz]; the bands (a, a + band_width] tile (0, band].
    band_width : float
        Width of each band [Hz]: at least the bin width, dividing ``band`` into whole bands.

    Returns
    -------
    numpy.ndarray
        Shape (...): natural log of band energies in [S]·Hz (e.g. m²), averaged.
    """
    S = numeric_array("S", S, complex_ok=True)
    f = numeric_array("f", f, dtype=float)
    if f.ndim != 1:
        raise SpecificationError("f", Described(f"array of shape {f.shape}"), "must be a 1-D uniform grid from 0 Hz")
    shape = S.shape
    if S.ndim >= 3 and S.shape[-1] == S.shape[-2] and S.shape[-3] == f.size:
        pass  # (..., F, m, m)
    elif S.ndim >= 1 and S.shape[-1] == f.size:
        S = S[..., None, None]  # (..., F) scalar
    else:
        raise SpecificationError("S", shape, f"must be (..., F, m, m) or (..., F) with F = len(f) = {f.size}")
    if f.size < 2 or f[0] != 0 or not f[1] > f[0] or not np.allclose(np.diff(f), f[1] - f[0], rtol=1e-9, atol=0):
        raise SpecificationError("f", Described(f"{f.size} bins" + (f" from {f[0]:g} Hz" if f.size else "")),
                                 "must be a uniform grid from 0 Hz, increasing (Δf > 0)")
    band = positive("band", band, "Hz")
    if not f[-1] >= band - (f[1] - f[0]) * (1 + 1e-9):
        raise SpecificationError("band", band, f"must lie within one bin above the grid's last frequency {f[-1]:g} Hz")
    width = positive("band_width", band_width, "Hz")
    n = band / width
    if not (math.isfinite(width) and width >= (f[1] - f[0]) * (1 - 1e-9)) or abs(n - round(n)) > 1e-9 * n:
        raise SpecificationError("band_width", band_width, f"must be at least the bin width {f[1] - f[0]:g} Hz and "
                                                           f"divide the band {band:g} Hz into whole bands")
    L = log_band_energies(S, f, width * np.arange(int(round(n)) + 1))
    if not np.all(np.isfinite(L)):
        raise SpecificationError("S", "a band without energy", f"every {width:g} Hz band of (0, {band:g}] Hz must "
                                                               "hold energy > 0 in every auto-spectrum")
    return L.mean(axis=-1)


def distance(f: ArrayLike, S_model: ArrayLike, S_exp: ArrayLike, band: float = 100.0) -> np.ndarray:
    """D = int_B ||S_model(ω) - S_exp(ω)||_F^2 dω over ω ∈ 2π[-band, band] (rad/s).

    Same rule as :func:`j_s`.

    Parameters
    ----------
    f : array_like
        (F,) grid in Hz from 0.
    S_model, S_exp : array_like
        Two-sided PSDs per Hz on the grid f, (..., F, m, m) or (..., F), finite; shapes broadcast.
    band : float
        Half-width of the band (Hz).

    Returns
    -------
    numpy.ndarray
        The broadcast leading shape, in [S]^2 * rad/s.
    """
    S_model = numeric_array("S_model", S_model, complex_ok=True)
    S_exp = numeric_array("S_exp", S_exp, complex_ok=True)
    try:
        diff = S_model - S_exp
    except ValueError:
        raise SpecificationError("S_exp", np.shape(S_exp), f"must broadcast with S_model {np.shape(S_model)}") from None
    return _j_s(f, diff, band)
