"""Input checks of the solver, all up front: :func:`prepare` turns the arguments of ``simulate``
into a validated :class:`Problem` or raises :class:`~tubeid.errors.SpecificationError` naming the
field, the value and the rule. Scalar rules come from :mod:`tubeid._validation`."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tubeid._validation import numeric_array, one_of, positive, real
from tubeid.dynamics.solver._base import Stop, stop_labels
from tubeid.errors import Described, SpecificationError

__all__ = ["MAX_STOPS", "KEEPS", "Problem", "matrix_stack", "check_definite", "check_stops", "prepare"]

#: At most this many stops with a gap: their 3**S regimes are tabulated.
MAX_STOPS = 3
#: What ``simulate`` keeps: the observation series, or only the statistics.
KEEPS = ("series", "stats")


def matrix_stack(name: str, a, n: int | None = None) -> np.ndarray:
    """A symmetric (R, N, N) float array from an (N, N) or (R, N, N) one (symmetrised; relative
    asymmetry up to 1e-10 is accepted as round-off); complex, bool and string arrays are refused."""
    arr = numeric_array(name, a, finite=False, dtype=float)  # finiteness: below, with its own message
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[1] != arr.shape[2] or arr.shape[1] == 0:
        raise SpecificationError(f"{name}.shape", arr.shape, "must be (N, N) or (R, N, N)")
    if n is not None and arr.shape[1] != n:
        raise SpecificationError(f"{name}.shape", arr.shape, f"must have N = {n} like M")
    if not np.all(np.isfinite(arr)):
        raise SpecificationError(name, Described("non-finite entries"), "must be finite")
    scale = np.max(np.abs(arr), axis=(1, 2), keepdims=True)
    if np.any(np.abs(arr - arr.transpose(0, 2, 1)) > 1e-10 * np.maximum(scale, 1e-300)):
        raise SpecificationError(name, Described("non-symmetric"), "must be symmetric (rel. tol 1e-10)")
    return 0.5 * (arr + arr.transpose(0, 2, 1))


def check_definite(name: str, arr: np.ndarray, strict: bool) -> None:
    """Every matrix of the stack positive definite (strict) or semi-definite, relative to its largest eigenvalue."""
    for r, a in enumerate(arr):
        w = np.linalg.eigvalsh(a)
        top = max(abs(w[-1]), 1e-300)
        if strict and w[0] <= 1e-13 * top:
            raise SpecificationError(name, Described(f"realisation {r}: min eigenvalue {w[0]:.3g}"),
                                     "must be positive definite")
        if not strict and w[0] < -1e-10 * top:
            raise SpecificationError(name, Described(f"realisation {r}: min eigenvalue {w[0]:.3g}"),
                                     "must be positive semi-definite")


def check_stops(stops, n: int) -> tuple[Stop, ...]:
    """A tuple of :class:`Stop` whose vectors have length n and whose labels (the name, default
    ``stop<i>``) are distinct."""
    if isinstance(stops, Stop):
        stops = (stops,)
    try:
        stops = tuple(stops)
    except TypeError:
        raise SpecificationError("stops", stops, "must be a sequence of Stop") from None
    for i, s in enumerate(stops):
        if not isinstance(s, Stop):
            raise SpecificationError(f"stops[{i}]", s, "must be a tubeid.dynamics.Stop")
        if len(s.b) != n:
            raise SpecificationError(f"stops[{i}].b", Described(f"length {len(s.b)}"), f"must have length N = {n}")
    labels = stop_labels(stops)
    for i, name in enumerate(labels):
        if name in labels[:i]:
            j = labels.index(name)
            raise SpecificationError(f"stops[{i}].name", name,
                                     f"must differ from the label of stops[{j}] (a stop's name, default stop<i>, "
                                     "labels its results)")
    return stops


@dataclass(frozen=True)
class Problem:
    """A validated call of ``simulate``.

    M, D, K: (1 or R, N, N) stacks (symmetric; realisation r uses index r % len); the stiffness of
    zero-gap stops is already added to K. stops: all stops as given; gapped: those with a gap
    (index in ``stops`` in ``gapped_index``), the only ones the integrators see. B (N, m), C
    (n_obs, N), loads (R, n_t, m) C-contiguous. Times in s; outputs at t = j output_dt for
    j0 <= j < j0 + n_keep.
    """

    M: np.ndarray
    D: np.ndarray
    K: np.ndarray
    stops: tuple
    gapped: tuple
    gapped_index: tuple
    linear_index: tuple
    B: np.ndarray
    C: np.ndarray
    loads: np.ndarray
    dt_load: float
    output_dt: float
    duration: float
    discard: float
    j0: int
    n_keep: int
    sensors: tuple

    @property
    def R(self) -> int:
        return self.loads.shape[0]

    def matrices(self, r: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(M, D, K) of realisation r."""
        return self.M[r % len(self.M)], self.D[r % len(self.D)], self.K[r % len(self.K)]


def prepare(M, D, K, stops, B, C, loads, dt_load, output_dt, discard, method, methods, keep,
            sensor_names=None) -> Problem:
    """Check every argument of ``simulate`` (see its docstring) and return the :class:`Problem`."""
    one_of("method", method, methods)
    one_of("keep", keep, KEEPS)
    Ms = matrix_stack("M", M)
    N = Ms.shape[1]
    Ds = matrix_stack("D", D, N)
    Ks = matrix_stack("K", K, N)
    check_definite("M", Ms, True)
    check_definite("K", Ks, True)
    check_definite("D", Ds, False)
    stops = check_stops(stops, N)
    gapped_index = tuple(i for i, s in enumerate(stops) if s.gap > 0.0)
    if len(gapped_index) > MAX_STOPS:
        raise SpecificationError("stops", Described(f"{len(gapped_index)} stops with a gap"),
                                 f"at most {MAX_STOPS} (3**S regimes are tabulated)")
    # complex values refused (never truncated to their real part), bools and strings are not numbers;
    # finiteness is checked below
    Bm = numeric_array("B", B, finite=False, dtype=float)
    Cm = numeric_array("C", C, finite=False, dtype=float)
    L = numeric_array("loads", loads, finite=False, dtype=float)
    if Bm.ndim == 1:
        Bm = Bm[:, None]
    if Bm.ndim != 2 or Bm.shape[0] != N or not np.all(np.isfinite(Bm)):
        raise SpecificationError("B.shape", Bm.shape, f"must be a finite (N={N}, m) matrix")
    if Cm.ndim == 1:
        Cm = Cm[None, :]
    if Cm.ndim != 2 or Cm.shape[1] != N or Cm.shape[0] == 0 or not np.all(np.isfinite(Cm)):
        raise SpecificationError("C.shape", Cm.shape, f"must be a finite (n_obs, N={N}) matrix")
    if L.ndim == 2:
        L = L[None]
    if L.ndim != 3 or L.shape[2] != Bm.shape[1] or L.shape[1] < 2:
        raise SpecificationError("loads.shape", L.shape, f"must be (R, n_t >= 2, m = {Bm.shape[1]})")
    if not np.all(np.isfinite(L)):
        raise SpecificationError("loads", Described("non-finite samples"), "must be finite")
    R = L.shape[0]
    for nm, a in (("M", Ms), ("D", Ds), ("K", Ks)):
        if len(a) not in (1, R):
            raise SpecificationError(f"{nm}.shape", a.shape, f"realisation axis must be 1 or match loads (R = {R})")
    dt_load = positive("dt_load", dt_load, "s")
    output_dt = positive("output_dt", output_dt, "s")
    duration = (L.shape[1] - 1) * dt_load
    if output_dt > duration * (1 + 1e-9):  # one sample at t = 0 of a response from rest: rms 0
        raise SpecificationError("output_dt", output_dt, f"must not exceed the record's duration (n_t − 1) dt_load = "
                                 f"{duration:g} s")
    discard = real("discard", discard, unit="s", low=0.0, high=duration, high_open=True)
    n_out_total = int(math.floor(duration / output_dt + 1e-9)) + 1
    j0 = int(math.ceil(discard / output_dt - 1e-9))
    if n_out_total - j0 < 1:
        raise SpecificationError("discard", discard, "leaves no output sample")
    n_obs = Cm.shape[0]
    if isinstance(sensor_names, (str, bytes)):
        raise SpecificationError("sensor_names", sensor_names, "must be a sequence of names, not one string")
    sensors = tuple(sensor_names) if sensor_names is not None else tuple(f"y{i}" for i in range(n_obs))
    if len(sensors) != n_obs:
        raise SpecificationError("sensor_names", sensor_names, f"must have n_obs = {n_obs} names")
    for i, name in enumerate(sensors):
        if not isinstance(name, str):
            raise SpecificationError(f"sensor_names[{i}]", name, "must be a string")
        if name in sensors[:i]:
            raise SpecificationError(f"sensor_names[{i}]", name,
                                     f"must differ from sensor_names[{sensors.index(name)}] (names label the outputs)")
    linear = [s for s in stops if s.gap == 0.0]
    if linear:  # zero-gap stops are linear springs
        Ks = Ks + sum(s.stiffness * np.outer(s.vector, s.vector) for s in linear)[None]
    return Problem(M=Ms, D=Ds, K=Ks, stops=stops, gapped=tuple(stops[i] for i in gapped_index),
                   gapped_index=gapped_index, linear_index=tuple(i for i, s in enumerate(stops) if s.gap == 0.0),
                   B=np.ascontiguousarray(Bm), C=np.ascontiguousarray(Cm), loads=np.ascontiguousarray(L),
                   dt_load=dt_load, output_dt=output_dt, duration=duration, discard=discard, j0=j0,
                   n_keep=n_out_total - j0, sensors=sensors)
