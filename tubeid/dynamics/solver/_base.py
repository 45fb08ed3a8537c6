"""The solver's specification and result records: :class:`Stop` and :class:`TransientResult`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import xarray as xr

from tubeid._validation import non_negative, numeric_array
from tubeid.errors import Described, SpecificationError

__all__ = ["Stop", "TransientResult", "assemble_result", "stop_labels"]


@dataclass(frozen=True)
class Stop:
    """A symmetric elastic stop acting on u = bᵀq.

    Parameters
    ----------
    b : sequence of float, length N
        The stop's row in the model's coordinates q: u = bᵀq is the displacement at the stop (m).
        Real, finite, not all zero; 1-D, or a single row or column (a matrix is refused); stored as
        a tuple of float. Its length must be the N of the matrices it is used with (checked by
        ``simulate``, ``highest_frequency``).
    gap : float
        g (m), finite, >= 0.
    stiffness : float
        k (N/m), finite, >= 0.
    name : str
        Label of the stop in results (default ``stop<i>``, i its index); the labels of the stops of
        one ``simulate`` call must be distinct.

    Raises
    ------
    tubeid.errors.SpecificationError
        Naming ``stop.b``, ``stop.gap``, ``stop.stiffness`` or ``stop.name`` when it breaks the rule
        above (complex values, bools and strings are not numbers).

    Notes
    -----
    Force on the structure: -b k (|u| - g) sign(u) for |u| > g, none otherwise. A zero gap makes
    the stop a linear spring k b bᵀ (always in contact).
    """

    b: tuple
    gap: float
    stiffness: float
    name: str = ""

    def __post_init__(self):
        # complex values refused (never truncated to their real part), bools and strings are not numbers
        b = numeric_array("stop.b", self.b, finite=False, dtype=float)
        if b.ndim > 1 and sum(d > 1 for d in b.shape) > 1:  # a matrix is not a stop's row: never flattened
            raise SpecificationError("stop.b", Described(f"an array of shape {b.shape}"),
                                     "must be a vector (1-D, or a single row or column)")
        b = b.ravel()
        if b.size == 0 or not np.all(np.isfinite(b)) or not np.any(b != 0):
            raise SpecificationError("stop.b", self.b, "must be a finite, non-zero vector")
        object.__setattr__(self, "b", tuple(float(v) for v in b))
        object.__setattr__(self, "gap", non_negative("stop.gap", self.gap, "m"))
        object.__setattr__(self, "stiffness", non_negative("stop.stiffness", self.stiffness, "N/m"))
        if not isinstance(self.name, str):
            raise SpecificationError("stop.name", Described(type(self.name).__name__), "must be a string")

    @property
    def vector(self) -> np.ndarray:
        """b as a float array (N,)."""
        return np.array(self.b)


def stop_labels(stops) -> list[str]:
    """The label of each stop in results: its name, or ``stop<i>`` (i its index in ``stops``) without
    one. ``simulate`` refuses stops whose labels are not distinct."""
    return [s.name or f"stop{i}" for i, s in enumerate(stops)]


@dataclass(frozen=True)
class TransientResult:
    """Output of :func:`tubeid.dynamics.solver.simulate` (immutable).

    The kept window is [t0, T]: t0 = j0 output_dt the first output sample at or after
    ``discard``, T = (n_t - 1) dt_load the record's end. Coordinates: ``realisation`` (0 ... R-1),
    ``time`` (s), ``sensor`` (the sensor names), ``stop`` (the stop labels, every stop given).

    Parameters
    ----------
    observations : xarray.DataArray (realisation, time, sensor) or None
        y = C q at t = j output_dt, t0 <= t <= T, in the units of C q (None with ``keep="stats"``).
    rms : xarray.DataArray (realisation, sensor)
        Root mean square (not centred) of the observation samples at output_dt in [t0, T], in the
        units of C q.
    contact_fraction : xarray.DataArray (realisation, stop)
        Fraction of [t0, T] with |u| > g (event-exact for the exact method, per step for
        symplectic Euler); 1 for a stop with zero gap.
    contact_events : xarray.DataArray (realisation, stop)
        Number (int64) of open -> contact transitions in [t0, T] (exact method: located in
        sub-steps starting at or after t0; symplectic Euler: steps ending in contact after a step
        ending open); 0 for a stop with zero gap.
    dt : xarray.DataArray (realisation,)
        Integration step used (s).
    method : str
        The method used.
    output_dt : float
        Output sampling (s).
    discard : float
        Discarded transient (s) as given; the kept series starts at the first output sample at
        or after it.
    """

    observations: xr.DataArray | None
    rms: xr.DataArray
    contact_fraction: xr.DataArray
    contact_events: xr.DataArray
    dt: xr.DataArray
    method: str
    output_dt: float
    discard: float

    def to_dataset(self) -> xr.Dataset:
        """All arrays in one Dataset.

        Returns
        -------
        xarray.Dataset
            rms, contact_fraction, contact_events, dt (and observations unless None); method,
            output_dt and discard as attributes.
        """
        data = {
            "rms": self.rms,
            "contact_fraction": self.contact_fraction,
            "contact_events": self.contact_events,
            "dt": self.dt,
        }
        if self.observations is not None:
            data["observations"] = self.observations
        ds = xr.Dataset(data)
        ds.attrs.update(method=self.method, output_dt=self.output_dt, discard=self.discard)
        return ds


def assemble_result(y, rms, contact_fraction, contact_events, dts, stops, sensors, output_dt, j0, method,
                    discard) -> TransientResult:
    """Label the solver's arrays: y (R, n_keep, n_obs) or None, rms (R, n_obs), contact_fraction
    and contact_events (R, S), dts (R,); the kept series starts at output sample j0."""
    R = len(dts)
    stop_names = stop_labels(stops)  # distinct: checked up front (check_stops)
    coords = {"realisation": np.arange(R), "sensor": list(sensors), "stop": stop_names}
    data = {
        "rms": (("realisation", "sensor"), rms, {"long_name": "RMS (not centred) of C q at output_dt, t >= discard"}),
        "contact_fraction": (("realisation", "stop"), contact_fraction, {"long_name": "fraction of time with |u| > gap"}),
        "contact_events": (("realisation", "stop"), contact_events, {"long_name": "number of open -> contact transitions"}),
        "dt": (("realisation",), np.asarray(dts), {"units": "s"}),
    }
    if y is not None:
        coords["time"] = (j0 + np.arange(y.shape[1])) * output_dt
        data["observations"] = (("realisation", "time", "sensor"), y,
                                {"long_name": "observation C q", "time_units": "s"})
    ds = xr.Dataset(data, coords=coords)  # one set of indexes, shared by the arrays below
    return TransientResult(
        observations=ds["observations"] if y is not None else None, rms=ds["rms"],
        contact_fraction=ds["contact_fraction"], contact_events=ds["contact_events"], dt=ds["dt"],
        method=method, output_dt=output_dt, discard=discard)
