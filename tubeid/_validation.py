"""Argument checks shared by the whole package: one place, one wording.

Every check raises :class:`tubeid.errors.SpecificationError` naming the field, the value and the
rule (``tubes[0].length = -2.0: must be a finite number > 0 (m)``) and returns the value converted
to its plain Python type. Booleans are never numbers here (``True`` is not 1), strings are never
numbers (a specification reader that wants to accept ``"7.5e8"`` converts it before checking), and
NaN or infinity is refused wherever a number is asked for.

This module is private: the public functions of each sub-package call it up front, before any
computation, in the manner of scikit-learn's ``_param_validation``.
"""

from __future__ import annotations

import math
import numbers
import os
from collections.abc import Iterable
from typing import Any

import numpy as np

from tubeid.errors import Described, SpecificationError, shown

__all__ = ["real", "positive", "non_negative", "integer", "open_unit", "one_of", "seed", "is_number", "limit",
           "byte_size", "channel_count", "is_numeric_dtype", "numeric_array", "duration", "byte_count", "boolean",
           "allocation", "MEMORY_SHARE", "on_tube"]


def _unit(unit: str | None) -> str:
    return f" ({unit})" if unit else ""


def is_number(value: Any) -> bool:
    """True for a real number (Python or NumPy), never for ``bool``, strings or complex values."""
    return (isinstance(value, (numbers.Real, np.floating, np.integer))
            and not isinstance(value, (bool, np.bool_)))


def real(field: str, value: Any, *, unit: str | None = None, low: float | None = None, high: float | None = None,
         low_open: bool = False, high_open: bool = False) -> float:
    """A finite real number, optionally within [low, high] (either end open), as ``float``.

    Parameters
    ----------
    field : str
        What the value is, as the user wrote it (``"tubes[0].length"``, ``"dt"``).
    value : object
        The value to check.
    unit : str, optional
        Shown in the rule, e.g. ``"m"``.
    low, high : float, optional
        Bounds; ``None`` for none.
    low_open, high_open : bool
        Whether the bound itself is excluded.

    Returns
    -------
    float
    """
    rule = "must be a finite number"
    if low is not None and high is not None:
        rule += f" in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
    elif low is not None:
        rule += f" {'>' if low_open else '>='} {low:g}"
    elif high is not None:
        rule += f" {'<' if high_open else '<='} {high:g}"
    rule += _unit(unit)
    if not is_number(value):
        raise SpecificationError(field, value, rule)
    try:
        v = float(value)
    except OverflowError:  # an int beyond the float range
        raise SpecificationError(field, value, rule) from None
    if not math.isfinite(v):
        raise SpecificationError(field, value, rule)
    if low is not None and (v < low or (low_open and v == low)):
        raise SpecificationError(field, value, rule)
    if high is not None and (v > high or (high_open and v == high)):
        raise SpecificationError(field, value, rule)
    return v


def positive(field: str, value: Any, unit: str | None = None) -> float:
    """A finite number > 0, as ``float``."""
    return real(field, value, unit=unit, low=0.0, low_open=True)


def non_negative(field: str, value: Any, unit: str | None = None) -> float:
    """A finite number >= 0, as ``float``."""
    return real(field, value, unit=unit, low=0.0)


def integer(field: str, value: Any, *, minimum: int | None = None, maximum: int | None = None) -> int:
    """An integer (Python or NumPy, never ``bool`` or a float such as 3.0) within [minimum, maximum]."""
    if minimum is not None and maximum is not None:
        rule = f"must be an integer in [{minimum}, {maximum}]"
    elif minimum is not None:
        rule = f"must be an integer >= {minimum}"
    elif maximum is not None:
        rule = f"must be an integer <= {maximum}"
    else:
        rule = "must be an integer"
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (numbers.Integral, np.integer)):
        raise SpecificationError(field, value, rule)
    v = int(value)
    if (minimum is not None and v < minimum) or (maximum is not None and v > maximum):
        raise SpecificationError(field, value, rule)
    return v


#: The most worker processes per usable core an embedded cluster may start: beyond, they only
#: oversubscribe the machine (and thousands of processes exhaust it).
WORKERS_PER_CORE = 4


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity where the system has one), at least 1."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def worker_count(field: str, value: Any, minimum: int = 0) -> int:
    """A number of worker processes to start here: an integer in [minimum, WORKERS_PER_CORE x usable cores]."""
    n = integer(field, value, minimum=minimum)
    cores = usable_cores()
    if n > WORKERS_PER_CORE * cores:
        raise SpecificationError(field, value, f"must be at most {WORKERS_PER_CORE * cores}: {WORKERS_PER_CORE} worker "
                                 f"processes per core this process may use ({cores} here); more only oversubscribe "
                                 "the machine (for a larger cluster give --scheduler)")
    return n


def replicates(field: str, value: Any) -> int:
    """A bootstrap's replicate count B: an integer >= 0 (0: no bootstrap), at most ``tubeid.io.max-bootstrap``.

    Time and memory grow as B (every replicate re-evaluates the criterion on resampled data and its
    values are kept); the Monte Carlo error of a bootstrap standard deviation is about 1/sqrt(2 B) of
    it, 0.2 % at the default limit of 100 000, so more buys nothing the data can tell.
    """
    n = integer(field, value, minimum=0)
    bound = int(limit("max-bootstrap"))
    if n > bound:
        raise SpecificationError(field, value, f"must be at most {bound} (configuration tubeid.io.max-bootstrap): "
                                 f"time and memory grow with the replicates, and the bootstrap's own Monte Carlo "
                                 f"error on a standard deviation, about 1/sqrt(2 B), is already "
                                 f"{1 / math.sqrt(2 * bound):.2%} there")
    return n


def open_unit(field: str, value: Any) -> float:
    """A number in the open interval (0, 1) (a probability or confidence level), as ``float``."""
    return real(field, value, low=0.0, high=1.0, low_open=True, high_open=True)


def one_of(field: str, value: Any, choices: Iterable) -> Any:
    """``value`` if it is one of ``choices`` (compared with ``==``, strings never match numbers)."""
    choices = tuple(choices)
    for c in choices:
        if type(c) is type(value) and c == value or (c is None and value is None):
            return value
    raise SpecificationError(field, value, f"must be one of {', '.join(shown(c) for c in choices)}")


def is_numeric_dtype(dtype: Any, *, complex_ok: bool = False) -> bool:
    """True for an integer or floating dtype (also complex with ``complex_ok``); never ``bool``,
    strings, objects, or ``timedelta64``/``datetime64``.

    Decided by the dtype's kind, not ``np.issubdtype(dtype, np.integer)``: that is True for
    ``timedelta64``, whose values would be read as bare counts of its unit (milliseconds as seconds).
    """
    return np.dtype(dtype).kind in ("iufc" if complex_ok else "iuf")


def _finite_sum(arr: np.ndarray) -> bool:
    with np.errstate(over="ignore", invalid="ignore"):  # finite values may sum beyond the float range
        return bool(np.isfinite(arr.sum()))


def numeric_array(field: str, value: Any, *, complex_ok: bool = False, finite: bool = True,
                  dtype: Any = None) -> np.ndarray:
    """``value`` as an array of real (or, with ``complex_ok``, complex) numbers, finite unless told.

    Refused (naming ``field``): what does not form a regular array, bools, strings,
    ``timedelta64``/``datetime64`` and complex values unless allowed (never truncated to their real
    part), and NaN or infinity when ``finite``. An object array (a list mixing Python and NumPy
    numbers) passes when every element is a number in the sense of :func:`is_number` (or a complex
    number with ``complex_ok``). The check reads the dtype ``np.asarray`` gives: a list that NumPy
    converts to floats as a whole (``[1.0, True]``) is not searched element by element.

    Parameters
    ----------
    field : str
        What the array is (``"x"``, ``"S"``).
    value : array_like
        The values.
    complex_ok : bool
        Whether complex values are allowed.
    finite : bool
        Whether NaN and infinity are refused.
    dtype : numpy dtype, optional
        The dtype of the returned array (``np.asarray(value, dtype=dtype)``, e.g. ``float``);
        default: as ``np.asarray(value)`` makes it.

    Returns
    -------
    numpy.ndarray
    """
    kind = "real or complex numbers" if complex_ok else "real numbers"
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError):  # ragged nesting
        raise SpecificationError(field, Described(type(value).__name__), f"must be an array of {kind}") from None
    if arr.dtype.kind == "O":
        def number(v):
            return is_number(v) or (complex_ok and isinstance(v, (numbers.Complex, np.complexfloating))
                                    and not isinstance(v, (bool, np.bool_)))
        if not all(number(v) for v in arr.flat):
            raise SpecificationError(field, Described(f"array of dtype object, shape {arr.shape}"),
                                     f"must be an array of {kind}")
        try:
            arr = np.asarray(arr.tolist(), dtype=complex if any(np.iscomplexobj(v) for v in arr.flat) else float)
        except OverflowError:  # an int beyond the float range
            raise SpecificationError(field, Described(f"array of dtype object, shape {arr.shape}"),
                                     f"must be an array of {kind} within the float range") from None
    elif not is_numeric_dtype(arr.dtype, complex_ok=complex_ok):
        raise SpecificationError(field, Described(f"array of dtype {arr.dtype}, shape {arr.shape}"),
                                 f"must be an array of {kind}" + ("" if complex_ok or arr.dtype.kind != "c" else
                                                                  " (complex values are not truncated to their "
                                                                  "real part)"))
    if dtype is not None:
        arr = np.asarray(arr, dtype=dtype)
    # a finite sum means every value is finite (a NaN or an infinity makes the sum NaN or infinite):
    # one pass without a boolean temporary; the elements are looked at only when the sum is not finite
    if finite and arr.size and arr.dtype.kind in "fc" and not _finite_sum(arr) and not np.all(np.isfinite(arr)):
        where = "" if arr.ndim == 0 else \
            f", first at index {tuple(int(i) for i in np.argwhere(~np.isfinite(arr))[0])}"
        raise SpecificationError(field, Described(f"{int(np.sum(~np.isfinite(arr)))} NaN or infinite value(s)"
                                                  f"{where}"), "must be finite")
    return arr


def on_tube(field: str, tube: Any, x: Any, what: str | None = None) -> float:
    """``x`` [m] as ``float`` when it lies on ``tube`` (anything with ``name`` and ``length``): a finite
    number in [0, length], to the specification's node tolerance (``tubeid.mechanics.spec``: 1e-9 m).

    ``what`` names the point in the rule (``"load 'T'"``: "load 'T' is off tube 'centre' of length
    16 m: ..."); without it the rule is "is off tube 'centre': must be in [0, 16.0] m".
    """
    from tubeid.mechanics.spec import _NODE_TOL

    xv = real(field, x, unit="m")
    if not (-_NODE_TOL <= xv <= tube.length + _NODE_TOL):
        rule = (f"{what} is off tube {tube.name!r} of length {tube.length:g} m: must be in [0, {tube.length:g}] m"
                if what else f"is off tube {tube.name!r}: must be in [0, {tube.length}] m")
        raise SpecificationError(field, x, rule)
    return xv


def seed(field: str, value: Any) -> int:
    """A seed: a non-negative integer."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (numbers.Integral, np.integer)) or value < 0:
        raise SpecificationError(field, value, "must be a non-negative integer")
    return int(value)


def boolean(field: str, value: Any) -> bool:
    """``True`` or ``False`` (also NumPy's), never a number or a string such as ``"no"``."""
    if not isinstance(value, (bool, np.bool_)):
        raise SpecificationError(field, value, "must be true or false")
    return bool(value)


def duration(field: str, value: Any) -> float:
    """A duration > 0 in seconds, as ``float``: a number of seconds or a text dask reads (``"10s"``,
    ``"2 minutes"``); never ``bool``, NaN or infinity."""
    from dask.utils import parse_timedelta

    try:
        seconds = None if isinstance(value, (bool, np.bool_)) or value is None else \
            float(parse_timedelta(value, default="s"))
    except (KeyError, ValueError, TypeError, AttributeError, OverflowError):  # dask's errors for what it cannot parse
        seconds = None
    if seconds is None or not math.isfinite(seconds) or seconds <= 0:
        raise SpecificationError(field, value, "must be a duration > 0, e.g. 10s (a bare number is seconds)")
    return seconds


def byte_count(field: str, value: Any) -> float:
    """A size > 0 in bytes: a number, or a text dask reads (``"2 GiB"``, ``"500 kB"``)."""
    rule = 'must be a size in bytes > 0, e.g. "2 GiB" (a bare number is bytes)'
    given = value
    if isinstance(value, str):
        from dask.utils import parse_bytes

        try:
            value = parse_bytes(value)
        except (ValueError, TypeError, OverflowError):
            raise SpecificationError(field, given, rule) from None
    try:
        return real(field, value, low=0.0, low_open=True)
    except SpecificationError:
        raise SpecificationError(field, given, rule) from None


# -- resource limits (configuration section ``tubeid.io``) ----------------------------------------
def limit(key: str) -> float:
    """The configured limit ``tubeid.io.<key>`` as a number > 0 (sizes such as ``"2 GiB"`` in bytes).

    A bad configured value is refused naming the setting and its environment variable
    (:func:`tubeid.config.value`).
    """
    from tubeid import config

    return config.value(f"io.{key}")


def byte_size(nbytes: float) -> str:
    """``nbytes`` for people: ``"14.90 GiB"``."""
    from dask.utils import format_bytes

    return format_bytes(int(nbytes)) if nbytes < 2**63 else f"{nbytes:.3g} B"


#: Largest share of this machine's physical memory one request may ask for (:func:`allocation`).
MEMORY_SHARE = 0.5


def _physical_memory() -> float | None:
    """This machine's physical memory [bytes], or None where the system does not say."""
    try:
        return float(os.sysconf("SC_PAGE_SIZE")) * float(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        return None


def allocation(field: str, value: Any, nbytes: float, what: str) -> None:
    """Refuse, before anything is allocated, a request whose arrays need more than :data:`MEMORY_SHARE`
    of this machine's physical memory, naming ``field``, its ``value``, the size and ``what`` it is for
    (numpy would raise a MemoryError from deep inside, or, with the kernel's overcommit, let the
    process be killed once the pages are touched)."""
    total = _physical_memory()
    if total is not None and nbytes > MEMORY_SHARE * total:
        raise SpecificationError(field, value, f"needs {byte_size(nbytes)} for {what}: more than "
                                 f"{MEMORY_SHARE:.0%} of this machine's memory ({byte_size(total)})")


#: Frequency bins over which :func:`channel_count` states the memory of the cross-spectra.
ESTIMATE_BINS = 1000


def channel_count(field: str, count: int, noun: str = "sensors") -> int:
    """``count`` channels (sensors, load points) if within ``tubeid.io.max-sensors``; else refused
    with a memory estimate.

    Every analysis of several channels keeps their cross-spectral matrices (frequency × channel ×
    channel, complex128): 16·m² bytes per frequency bin and realisation, quoted over
    :data:`ESTIMATE_BINS` bins.
    """
    bound = int(limit("max-sensors"))
    if count > bound:
        per_bin = 16.0 * count * count
        raise SpecificationError(
            field, Described(f"{count} {noun}"),
            f"at most {bound} (configuration tubeid.io.max-sensors): cross-spectra grow as the square of the "
            f"count, {count} × {count} complex values take {byte_size(per_bin)} per frequency bin, "
            f"{byte_size(per_bin * ESTIMATE_BINS)} per realisation over {ESTIMATE_BINS} bins")
    return count
