"""Validation of measured displacement records into one canonical xarray Dataset.

Canonical form (what every reader returns, MODEL.md §5):

- data variable ``displacement``, dims (``time``, ``sensor``), float64, attrs ``units = "m"``;
- coordinate ``time`` (s, float64, uniform, strictly increasing);
- coordinate ``sensor`` (str names) with non-index coordinates ``x`` (m, along the tube) and
  ``tube`` (str) on the ``sensor`` dim;
- attrs ``source`` (file or ``"<memory>"``), ``format`` and ``dt`` (s, = (t[-1] - t[0]) / (n - 1)).

Accepted input units: displacement in ``m``, ``mm``, ``um``/``µm``/``μm``, ``micron``, ``nm``
(converted to metres), either one ``units`` attribute on ``displacement`` or a per-channel ``units``
coordinate on the ``sensor`` dim (used by the CSV and UFF readers; an attribute beside it must name
the same unit, in any spelling: ``um`` and ``µm`` agree); ``x`` in the same length units
(metres when it has no ``units`` attribute); ``time`` in seconds (``s``, ``seconds``, …, or
``"seconds since …"``; seconds when it has no ``units`` attribute). Samples, ``time`` and ``x`` must
be integer or floating numbers: ``bool``, ``timedelta64`` and ``datetime64`` are refused, never read
as counts of their unit.

Refusals (:class:`~tubeid.errors.SpecificationError`; the message names the source, the channel
when there is one, and the rule):

- fewer than 2 samples; no sensor, or more than ``tubeid.io.max-sensors`` (the message states the
  memory of their cross-spectra); duplicate or malformed sensor names;
- integer samples (counts) without an explicit scale: the CF attribute ``scale_factor`` (size of one
  count in ``units``, optional ``add_offset``) on ``displacement``;
- a sensor missing its position (no/NaN ``x``, no/empty ``tube``); with ``tubes`` given, a sensor on
  an unknown tube or off it (``x < 0`` or ``x > length``);
- missing or unknown units;
- non-finite, non-increasing or non-uniform time: uniform means
  ``max |diff(t) - dt| <= UNIFORM_RTOL * dt + 4 * spacing(max |t|)``, the second term the rounding
  of the stamps in their own type (``spacing``: the gap between adjacent numbers of that type there;
  float64, or float32 for float32 stamps as data loggers write them). It matters for float32 stamps
  and for float64 stamps far from 0: epoch seconds (t ≈ 1.7e9 s) are stored to ±1.2e-7 s, 1.2e-4 of a
  1 ms step, whatever the record's length; float32 stamps at 30 s to ±9.5e-7 s. When that rounding exceeds ``UNIFORM_RTOL * dt`` it is allowed only
  while it stays within ``STAMP_RTOL * dt`` (epoch seconds: dt >= ~1 ms); beyond, the stamps are too
  coarse to show uniform sampling and a record that is not exactly uniform is refused, asking for time
  from the record's start, or for float64 stamps when they are float32 (at 1 ms, float32 stamps pass
  up to about 4 s; ``dt`` of accepted rounded stamps carries the rounding of its end points, at most
  ``STAMP_RTOL / (2 (n - 1))`` relative);
- NaN or infinite samples; implausible samples, beyond ± ``tubeid.io.max-displacement`` m (default
  1 m: tube vibrations are micrometres; a sample of metres means wrong units or unscaled counts);
- clipped channels: a channel is clipped at its top (bottom) when more than ``CLIP_FRACTION`` of
  its samples lie within ``CLIP_RTOL * max(|max|, |min|)`` of its maximum (minimum) *and* at least
  ``CLIP_RUN`` of them are consecutive. Continuous (even 16-bit quantised) Gaussian data reach their
  extremes essentially once and never trip it; a constant channel (dead sensor) always does.
  Caveats: a near-sinusoidal signal quantised to < ~12 bits of its range may trip it, and
  clipping of data that are not oversampled (white noise) makes no runs and is not detected;
- with ``min_resolution_hz`` given: a record shorter than one segment of that resolution, i.e.
  ``n * dt < 1 / min_resolution_hz`` (relative slack 1e-9 for rounding). Averaging estimators
  (Welch) need proportionally more and check that themselves.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping

import numpy as np
import xarray as xr

from tubeid._validation import channel_count, is_numeric_dtype, limit, positive, real
from tubeid.errors import Described, SpecificationError

__all__ = [
    "validate_measurements",
    "length_scale",
    "LENGTH_UNITS",
    "TIME_UNITS",
    "UNIFORM_RTOL",
    "STAMP_RTOL",
    "CLIP_FRACTION",
    "CLIP_RTOL",
    "CLIP_RUN",
]

#: Accepted length units and their size in metres.
LENGTH_UNITS: dict[str, float] = {
    "m": 1.0, "metre": 1.0, "metres": 1.0, "meter": 1.0, "meters": 1.0,
    "mm": 1e-3,
    "um": 1e-6, "\u00b5m": 1e-6, "\u03bcm": 1e-6, "micron": 1e-6, "microns": 1e-6,
    "nm": 1e-9,
}
#: Accepted spellings of seconds for the time coordinate.
TIME_UNITS = frozenset({"s", "sec", "second", "seconds"})

#: Relative tolerance on sample spacing. Float64 stamps t_i = i dt counted from 0 stay within it up to ~1e9
#: samples; stamps far from 0 (epoch seconds) are rounded by more, whatever the record's length: their
#: rounding (4 float64 spacings of max |t|) is allowed on top, within STAMP_RTOL (module docstring).
UNIFORM_RTOL = 1e-6
#: Largest rounding of the time stamps, relative to dt, allowed on top of UNIFORM_RTOL.
STAMP_RTOL = 1e-3
#: Clipping rule: fraction of samples at an extreme, closeness to it, and run length.
CLIP_FRACTION = 0.005
CLIP_RTOL = 1e-12
CLIP_RUN = 3
_RESOLUTION_SLACK = 1e-9


def _unit_list() -> str:
    return ", ".join(dict.fromkeys(["m", "mm", "um", "\u00b5m", "micron", "nm"]))


def length_scale(unit, field: str) -> float:
    """Size of ``unit`` in metres; refuses (naming ``field``) a missing or unknown unit."""
    if unit is None or (isinstance(unit, str) and unit.strip() in ("", "NONE")):
        raise SpecificationError(field, unit, f"units missing; must be one of {_unit_list()}")
    key = str(unit).strip()
    if key not in LENGTH_UNITS:
        raise SpecificationError(field, unit, f"unknown unit; must be one of {_unit_list()}")
    return LENGTH_UNITS[key]


def _same_unit(a, b) -> bool:
    """Whether two unit labels name the same unit: known length units compare by their size in
    metres (``um``, ``µm``, ``micron``), anything else by its text."""
    ka, kb = str(a).strip(), str(b).strip()
    if ka in LENGTH_UNITS and kb in LENGTH_UNITS:
        return LENGTH_UNITS[ka] == LENGTH_UNITS[kb]
    return ka == kb


def _where(source: str, channel: str | None, what: str) -> str:
    return f"{source}: channel {channel!r} {what}" if channel is not None else f"{source}: {what}"


def check_options(min_resolution_hz, tubes) -> dict[str, float] | None:
    """Validate the ``min_resolution_hz`` and ``tubes`` options; return tubes as {name: length_m}."""
    if min_resolution_hz is not None:
        positive("min_resolution_hz", min_resolution_hz, "Hz")
    if tubes is None:
        return None
    if not isinstance(tubes, Mapping) or len(tubes) == 0:
        raise SpecificationError("tubes", tubes, "must be a non-empty mapping tube name -> length (m)")
    out: dict[str, float] = {}
    for name, length in tubes.items():
        if not isinstance(name, str) or not name:
            raise SpecificationError("tubes key", name, "must be a non-empty string")
        out[name] = positive(f"tubes[{name!r}]", length, "m")  # never a string ("16") or a bool
    return out


def _as_names(values, source: str, what: str) -> list[str]:
    names = []
    for v in np.asarray(values, dtype=object).ravel():
        if isinstance(v, bytes):
            v = v.decode("utf-8")
        if not isinstance(v, str):
            raise SpecificationError(f"{source}: {what}", v, "must be a string")
        names.append(str(v))
    return names


def layout(ds, source: str) -> dict:
    """Structural reading of a measurement Dataset (no rule checks beyond structure).

    Returns time (float64), values (float64, time x sensor), names, x (NaN where absent), x_units,
    tube ("" where absent), units (one per channel, None where absent), time_units and
    time_dtype (the time stamps' own dtype: float32 stamps are rounded to float32's precision).
    """
    if not isinstance(ds, xr.Dataset):
        raise SpecificationError(f"{source}: measurements", type(ds).__name__, "must be an xarray.Dataset")
    if "displacement" not in ds.data_vars:
        raise SpecificationError(f"{source}: data variables", sorted(map(str, ds.data_vars)),
                                 "must contain 'displacement'")
    da = ds["displacement"]
    if set(da.dims) != {"time", "sensor"} or da.ndim != 2:
        raise SpecificationError(f"{source}: displacement.dims", tuple(da.dims), "must be ('time', 'sensor')")
    da = da.transpose("time", "sensor")
    if not is_numeric_dtype(da.dtype):  # by kind: np.issubdtype(timedelta64, np.integer) is True
        raise SpecificationError(f"{source}: displacement.dtype", str(da.dtype), "must be real numbers")
    values = _unpacked(da, source)
    if "time" not in da.coords:
        raise SpecificationError(f"{source}: time", None, "coordinate 'time' (s) is missing")
    time = da.coords["time"]
    if not is_numeric_dtype(time.dtype):  # timedelta64 would be read as counts of its unit (ms as s)
        raise SpecificationError(f"{source}: time.dtype", str(time.dtype), "time must be numeric seconds")
    if "sensor" not in da.coords:
        raise SpecificationError(f"{source}: sensor", None, "coordinate 'sensor' (names) is missing")
    names = _as_names(da.coords["sensor"].values, source, "sensor name")
    m = len(names)

    def on_sensor(coord: str):
        if coord not in da.coords:
            return None
        c = da.coords[coord]
        if c.dims != ("sensor",):
            raise SpecificationError(f"{source}: {coord}.dims", tuple(c.dims), "must be ('sensor',)")
        return c

    xc = on_sensor("x")
    if xc is None:
        x, x_units = np.full(m, np.nan), None
    else:
        if not is_numeric_dtype(xc.dtype):
            raise SpecificationError(f"{source}: x.dtype", str(xc.dtype), "positions x must be numbers (m)")
        x, x_units = np.asarray(xc.values, dtype=float), xc.attrs.get("units")
    tc = on_sensor("tube")
    tube = [""] * m if tc is None else _as_names(tc.values, source, "tube name")
    uc = on_sensor("units")
    if uc is not None:
        units = _as_names(uc.values, source, "units")
        attr_unit = da.attrs.get("units")
        if attr_unit is not None and any(not _same_unit(u, attr_unit) for u in units):
            raise SpecificationError(f"{source}: displacement.units", attr_unit,
                                     "conflicts with the per-channel 'units' coordinate")
    else:
        units = [da.attrs.get("units")] * m
    return {
        "time": np.asarray(time.values, dtype=float),
        "values": values,
        "names": names,
        "x": x,
        "x_units": x_units,
        "tube": tube,
        "units": units,
        "time_units": time.attrs.get("units"),
        "time_dtype": np.dtype(time.encoding.get("dtype", time.dtype)),
    }


def _unpacked(da: xr.DataArray, source: str) -> np.ndarray:
    """The samples as float64; integer samples (counts) only with an explicit scale.

    The scale is the CF attribute ``scale_factor`` (the size of one count in the variable's
    ``units``; optional ``add_offset``), on ``displacement`` in memory. A NetCDF or Zarr file
    carrying it is unpacked by xarray when read; stored integers without it are refused, also
    when xarray turned them into floats to mask a ``_FillValue``.
    """
    stored = np.dtype(da.encoding.get("dtype", da.dtype))
    packed = "scale_factor" in da.encoding or "scale_factor" in da.attrs
    if np.issubdtype(stored, np.integer) and not packed:
        raise SpecificationError(
            f"{source}: displacement.dtype", str(stored),
            "integer samples (counts) need an explicit scale: give the size of one count in the variable's units "
            "as its CF attribute scale_factor (optionally add_offset), e.g. units = 'um', scale_factor = 0.05")
    if "scale_factor" in da.encoding:  # a file's CF packing, unpacked by xarray: the same rule as in memory
        scale = da.encoding["scale_factor"]
        real(f"{source}: displacement.scale_factor", scale.item() if isinstance(scale, np.generic) else scale,
             low=0.0, low_open=True)
    if np.issubdtype(da.dtype, np.integer):  # in memory, scale_factor in attrs: unpack here
        scale, offset = da.attrs["scale_factor"], da.attrs.get("add_offset", 0.0)
        real(f"{source}: displacement.scale_factor", scale, low=0.0, low_open=True)
        real(f"{source}: displacement.add_offset", offset)
        return np.asarray(da.values, dtype=float) * float(scale) + float(offset)
    return np.asarray(da.values, dtype=float)


def _longest_run(mask: np.ndarray) -> int:
    if not mask.any():
        return 0
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return int((ends - starts).max())


def _check_clipping(col: np.ndarray, name: str, source: str) -> None:
    hi, lo = float(col.max()), float(col.min())
    n = col.size
    if hi == lo and n >= CLIP_RUN:
        raise SpecificationError(_where(source, name, "displacement"), hi,
                                 "channel is constant (dead or clipped/saturated sensor)")
    tol = CLIP_RTOL * max(abs(hi), abs(lo))
    for side, extreme in (("maximum", hi), ("minimum", lo)):
        at = np.abs(col - extreme) <= tol
        count = int(at.sum())
        if count > CLIP_FRACTION * n:
            run = _longest_run(at)
            if run >= CLIP_RUN:
                raise SpecificationError(
                    _where(source, name, f"displacement {side}"), extreme,
                    f"channel looks clipped (flat-topped): {count} of {n} samples "
                    f"(> {CLIP_FRACTION:.1%}) equal its {side} within {CLIP_RTOL:g} relative, "
                    f"{run} consecutive (>= {CLIP_RUN})")


def _stamp_spacing(t_max: float, stored: np.dtype) -> float:
    """The gap between adjacent numbers of the stamps' own floating type at ``t_max`` (float64 for
    integer or float64 stamps): float32 stamps, as data loggers write them, are rounded to it."""
    kind = stored if stored.kind == "f" and stored.itemsize < 8 else np.dtype(np.float64)
    return float(np.spacing(np.asarray(t_max, dtype=kind)))


def _time_checks(t: np.ndarray, time_units, source: str, stored: np.dtype = np.dtype(np.float64)) -> float:
    if time_units is not None:
        tu = str(time_units).strip()
        base = tu.split(" since ")[0].strip() if " since " in tu else tu
        if base not in TIME_UNITS:
            raise SpecificationError(f"{source}: time.units", time_units,
                                     f"time must be in seconds ({', '.join(sorted(TIME_UNITS))})")
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise SpecificationError(f"{source}: time[{bad[0]}]", float(t[bad[0]]), "time stamps must be finite")
    d = np.diff(t)
    bad = np.flatnonzero(d <= 0)
    if bad.size:
        i = int(bad[0])
        raise SpecificationError(f"{source}: time[{i + 1}]", float(t[i + 1]),
                                 f"time must be strictly increasing (time[{i}] = {float(t[i])!r} s)")
    n = t.size
    dt = float((t[-1] - t[0]) / (n - 1))
    dev = np.abs(d - dt)
    i = int(np.argmax(dev))
    if dev[i] > UNIFORM_RTOL * dt:
        # The rounding of the stamps in their own type (float64, or float32 as loggers write them): up to
        # one spacing of max |t| each (t0 + i dt computed or parsed), two per step, and dt from the end
        # points off by as much over n - 1.
        t_max = float(np.max(np.abs(t)))
        spacing = _stamp_spacing(t_max, stored)
        kind = "float32" if spacing > np.spacing(t_max) else "float64"
        rounding = 4.0 * spacing
        if dev[i] > UNIFORM_RTOL * dt + rounding:
            allowed = f"{UNIFORM_RTOL:g}" + (f" + {kind} rounding {rounding / dt:.3g} of stamps up to {t_max:g} s"
                                             if rounding > UNIFORM_RTOL * dt else "")
            raise SpecificationError(
                f"{source}: time[{i + 1}] - time[{i}]", float(d[i]),
                f"time must be uniform: step deviates from dt = {dt!r} s by {dev[i] / dt:.3g} relative "
                f"(> {allowed})")
        if rounding > STAMP_RTOL * dt and kind == "float32":
            raise SpecificationError(
                f"{source}: time", Described(f"float32 stamps up to {t_max:g} s, float32 spacing {spacing:g} s"),
                f"too coarse to show uniform sampling at dt = {dt!r} s: float32 keeps about 7 digits, so their "
                f"rounding moves a step by up to {rounding / dt:.3g} of dt (> {STAMP_RTOL:g}), and the steps deviate "
                f"by {dev[i] / dt:.3g}; store time as float64 (e.g. t0 + i * dt)")
        if rounding > STAMP_RTOL * dt:
            raise SpecificationError(
                f"{source}: time", Described(f"stamps up to {t_max:g} s, float64 spacing {np.spacing(t_max):g} s"),
                f"too coarse to show uniform sampling at dt = {dt!r} s: their rounding moves a step by up to "
                f"{rounding / dt:.3g} of dt (> {STAMP_RTOL:g}), and the steps deviate by {dev[i] / dt:.3g}; give "
                f"time from the record's start (t - t[0]; units 'seconds since <start>' keep the origin)")
    return dt


def validate_measurements(ds: xr.Dataset, *, min_resolution_hz: float | None = None,
                          tubes: Mapping[str, float] | None = None, source: str | None = None,
                          format: str | None = None) -> xr.Dataset:
    """Check a measurement Dataset against the rules of this module; return its canonical form.

    Parameters
    ----------
    ds : xarray.Dataset
        The record: ``displacement`` (time, sensor) with ``x`` and ``tube`` on ``sensor`` (units
        stated; converted to m, m and s). Not modified.
    min_resolution_hz : float, optional
        Refuse records shorter than 1 / min_resolution_hz [s].
    tubes : mapping of str to float, optional
        ``{tube name: length [m]}``; refuse sensors on unknown tubes or off them.
    source : str, optional
        Names the record in messages and in ``attrs["source"]`` (default: ``ds.attrs["source"]``
        or ``"<memory>"``).
    format : str, optional
        Goes to ``attrs["format"]`` (default: ``ds.attrs["format"]`` or ``"memory"``).

    Returns
    -------
    xarray.Dataset
        The canonical form: ``displacement`` (time, sensor) [m] float64, ``x`` [m] and ``tube`` on
        ``sensor``, ``time`` [s].

    Raises
    ------
    SpecificationError
        Naming the record, the sensor or field, the value and the rule.
    """
    tube_lengths = check_options(min_resolution_hz, tubes)
    if source is None:
        source = str(ds.attrs.get("source", "<memory>")) if isinstance(ds, xr.Dataset) else "<memory>"
    source = str(source)
    if format is None:
        format = str(ds.attrs.get("format", "memory")) if isinstance(ds, xr.Dataset) else "memory"
    lay = layout(ds, source)
    t, values, names = lay["time"], lay["values"], lay["names"]
    n, m = values.shape

    # Sensors: names, positions, tubes.
    if m == 0:
        raise SpecificationError(f"{source}: sensor", [], "at least one sensor is required")
    channel_count(f"{source}: sensor", m)
    for name in names:
        if not name or name != name.strip() or any(c in name for c in "\r\n"):
            raise SpecificationError(f"{source}: sensor name", name,
                                     "must be non-empty, without surrounding whitespace or line breaks")
    dup = sorted(k for k, c in Counter(names).items() if c > 1)
    if dup:
        raise SpecificationError(f"{source}: sensor", dup, "duplicate sensor names (each channel needs its own name)")
    if n < 2:
        raise SpecificationError(f"{source}: time", n, "fewer than 2 samples; a record needs at least 2")
    x_scale = 1.0 if lay["x_units"] is None else length_scale(lay["x_units"], f"{source}: x.units")
    x = lay["x"] * x_scale
    for j, name in enumerate(names):
        tube = lay["tube"][j]
        if not math.isfinite(x[j]) or not tube.strip():
            what = "x" if not math.isfinite(x[j]) else "tube"
            raise SpecificationError(_where(source, name, what), x[j] if what == "x" else tube,
                                     "sensor is missing its position (needs a finite x in m and a tube name)")
        if tube_lengths is not None:
            if tube not in tube_lengths:
                raise SpecificationError(_where(source, name, "tube"), tube,
                                         f"unknown tube; known tubes: {sorted(tube_lengths)}")
            length = tube_lengths[tube]
            if not 0.0 <= x[j] <= length:
                raise SpecificationError(_where(source, name, "x"), float(x[j]),
                                         f"sensor is off the tube {tube!r}: must satisfy 0 <= x <= {length!r} m")

    # Units.
    scale = np.array([length_scale(u, _where(source, name, "units")) for u, name in zip(lay["units"], names)])

    # Time.
    dt = _time_checks(t, lay["time_units"], source, lay["time_dtype"])

    # Samples.
    bound = limit("max-displacement")
    for j, name in enumerate(names):
        col = values[:, j]
        bad = np.flatnonzero(~np.isfinite(col))
        if bad.size:
            i = int(bad[0])
            raise SpecificationError(
                _where(source, name, f"displacement[{i}]"), float(col[i]),
                f"samples must be finite: {bad.size} NaN or infinite sample(s), first at t = {float(t[i])!r} s")
        big = np.flatnonzero(np.abs(col) * scale[j] > bound)
        if big.size:
            i = int(big[np.argmax(np.abs(col[big]))])
            raise SpecificationError(
                _where(source, name, f"displacement[{i}]"), Described(f"{col[i] * scale[j]:.6g} m"),
                f"implausible: {big.size} sample(s) beyond ± {bound:g} m (configuration tubeid.io.max-displacement); "
                f"wrong units, or unscaled counts?")
        _check_clipping(col, name, source)

    # Frequency resolution.
    if min_resolution_hz is not None:
        duration, needed = n * dt, 1.0 / float(min_resolution_hz)
        if duration < needed * (1.0 - _RESOLUTION_SLACK):
            raise SpecificationError(
                f"{source}: record duration", duration,
                f"too short for a frequency resolution of {float(min_resolution_hz)!r} Hz: "
                f"n * dt = {n} * {dt!r} s must be >= 1 / min_resolution_hz = {needed!r} s (one segment)")

    return xr.Dataset(
        {"displacement": (("time", "sensor"), values * scale[None, :], {"units": "m"})},
        coords={
            "time": ("time", t.copy(), {"units": "s"}),
            "sensor": ("sensor", np.array(names, dtype=str)),
            "x": ("sensor", x, {"units": "m"}),
            "tube": ("sensor", np.array(lay["tube"], dtype=str)),
        },
        attrs={"source": source, "format": str(format), "dt": dt},
    )
