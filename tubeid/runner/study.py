"""What a study is: sweep axes, a block task, labelled outputs, validated parameters.

A study file (``studies/*.py``) defines a module-level ``study = Study(...)``. The sweep is the
Cartesian product of the ``axes`` (ordered: dim -> coordinate values); it is cut into blocks of
``chunks[dim]`` points per axis, one dask task and one set of whole Zarr chunks per block. The
``task`` is called as ``task(block, rng, **parameters)`` where ``block`` maps each axis to the
1-D coordinates of the block and ``rng(**coords)`` returns the generator of one point, keyed
by its coordinates on ``seed_axes`` only (never by block or worker), so results do not depend on
chunking, worker count, order, retries or resumes. It returns ``{output name: array}`` with shape
(block sizes along the axes in order) + (sizes of the output's extra dims).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import inspect
import itertools
import json
import math
import pathlib
import sys
import types
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from tubeid import _validation
from tubeid.errors import Described, SpecificationError, shown
from tubeid.seeds import rng_for

__all__ = ["Study", "Output", "Parameter", "Warmup", "pointwise", "load_study", "load_definition", "study_hash", "Block",
           "RngFactory", "check_name", "COORDINATE_DEFAULTS", "RESERVED", "StudyRaised", "read_source"]

_PLAIN = (bool, int, float, str, type(None))

RESERVED = "_tubeid"
"""Name of the bookkeeping sub-group of a store: no axis, coordinate, output or stage may take it."""

COORDINATE_DEFAULTS: dict[str, tuple[str | None, str]] = {
    # dim: (units, long_name) used when a study declares none; units None: a label, no units (CF)
    "realisation": ("1", "Monte Carlo realisation index"),
    "experiment": ("1", "experimental record index"),
    "record": ("1", "record index"),
    "trial": ("1", "trial index"),
    "delta": ("1", "dispersion parameter delta of the random matrices"),
    "delta_F": ("1", "dispersion parameter delta_F of the random load spectrum"),
    "frequency": ("Hz", "frequency"),
    "time": ("s", "time"),
    "quantile": ("1", "quantile level"),
    "sensor": (None, "sensor name"),
    "component": (None, "component"),
    "statistic": (None, "statistic"),
}
"""Units and long names of common axes, for coordinates a study gives none (``Study.units`` / ``long_names``)."""


def _plain(value, field):
    """Check that ``value`` is a plain JSON value (stored in the provenance and hashed)."""
    if isinstance(value, (list, tuple)):
        return [_plain(v, field) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if not isinstance(value, _PLAIN) or (isinstance(value, float) and not math.isfinite(value)):
        raise SpecificationError(field, value, "must be a plain finite value (bool, int, float, str or a list of them)")
    return value


def check_name(field: str, name) -> str:
    """A study, pipeline or stage name: non-empty, no spaces or slashes, not starting with a dot."""
    if not isinstance(name, str) or not name or name.startswith(".") or any(c in name for c in "/\\ "):
        raise SpecificationError(field, name, "must be a non-empty string without spaces or slashes")
    return name


def _scalar(value):
    """A numpy scalar as the equivalent Python scalar (stable seed keys: repr(0.1) not 'np.float64(0.1)')."""
    return value.item() if isinstance(value, np.generic) else value


_TYPES = {bool: "a boolean (True or False)", int: "an integer", float: "a number", str: "a string",
          list: "a list"}


def _type_of(value) -> type | None:
    """The parameter type a default value implies (None: any plain value)."""
    for t in (bool, int, float, str):  # bool before int: True is an int in Python
        if isinstance(value, t):
            return t
    return list if isinstance(value, (list, tuple)) else None


@dataclasses.dataclass(frozen=True)
class Parameter:
    """A study parameter: its value and what is admissible.

    Parameters
    ----------
    value : object
        The default: a plain value (bool, int, float, str, None or a list of them).
    choices : sequence, optional
        The admissible values.
    bounds : tuple of (float or None, float or None), optional
        Inclusive ``(low, high)``; ``None`` leaves that end open.
    units : str
        Units, for the reader (e.g. ``"N^2/Hz"``).
    doc : str
        What the parameter does, for the reader (``tubeid run --help``, ``show``).
    type : type, optional
        One of ``bool, int, float, str, list``; default: the type of ``value`` (an int value
        admits integers only, a float value any real number, converted to float; a ``None`` value
        admits any plain value).
    """

    value: Any
    choices: Sequence | None = None
    bounds: tuple[float | None, float | None] | None = None
    units: str = ""
    doc: str = ""
    type: type | None = None

    def __post_init__(self):
        if self.type is not None and self.type not in _TYPES:
            raise SpecificationError("parameter type", self.type, f"must be one of {[t.__name__ for t in _TYPES]}")

    def check(self, name: str, value: Any) -> Any:
        """``value`` made plain, if admissible.

        Parameters
        ----------
        name : str
            The parameter's name (for the message: ``parameters.NAME``).
        value : object
            The proposed value (e.g. from ``--set NAME=VALUE``, already parsed).

        Returns
        -------
        object
            The value as the study receives it (an int admitted by a float parameter becomes a float).

        Raises
        ------
        SpecificationError
            Wrong type, not among the choices or outside the bounds.
        """
        field = f"parameters.{name}"
        value = _plain(value, field)
        want = self.type if self.type is not None else _type_of(self.value)
        if want is not None:
            ok = {bool: lambda v: isinstance(v, bool),
                  int: lambda v: isinstance(v, int) and not isinstance(v, bool),
                  float: lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
                  str: lambda v: isinstance(v, str),
                  list: lambda v: isinstance(v, list)}[want](value)
            if not ok:
                default = f" (the default is {shown(self.value)})" if self.type is None else ""
                raise SpecificationError(field, value, f"must be {_TYPES[want]}{default}")
            if want is float:
                try:
                    value = float(value)
                except OverflowError:  # an int beyond a float's range
                    raise SpecificationError(field, value, f"must be a number a float can hold (within "
                                             f"±{sys.float_info.max:.4g})") from None
        if self.choices is not None and value not in list(self.choices):
            raise SpecificationError(field, value, "must be one of [" + ", ".join(shown(c) for c in self.choices) + "]")
        if self.bounds is not None:
            lo, hi = self.bounds
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise SpecificationError(field, value, "must be a number")
            if (lo is not None and value < lo) or (hi is not None and value > hi):
                raise SpecificationError(field, value, f"must be >= {lo}" if hi is None else f"must be <= {hi}"
                                         if lo is None else f"must lie in [{lo}, {hi}]")
        return value

    def describe(self) -> str:
        """What the parameter admits, for ``tubeid run STUDY.py --help``.

        Returns
        -------
        str
            Its type (or choices), bounds, units and doc, e.g. ``"an integer in [1, 64]: matrix size"``.
        """
        want = self.type if self.type is not None else _type_of(self.value)
        parts = [_TYPES[want] if want is not None else "any plain value"]
        if self.choices is not None:
            parts = ["one of [" + ", ".join(shown(c) for c in self.choices) + "]"]
        if self.bounds is not None:
            lo, hi = self.bounds
            parts.append(f">= {lo}" if hi is None else f"<= {hi}" if lo is None else f"in [{lo}, {hi}]")
        if self.units:
            parts.append(f"[{self.units}]")
        return " ".join(parts) + (f": {self.doc}" if self.doc else "")

    def check_with(self, name: str, value: Any, values: Mapping[str, Any]) -> None:
        """Rules that involve other parameters, checked once every parameter has its value.

        Nothing by default; a subclass overrides it for an admissible set that depends on another
        parameter (e.g. δ below the δ_max of the model named by another parameter). Called by
        :meth:`Parameterised.check_parameters`, i.e. whenever a study file is loaded (``tubeid run``,
        before any store is touched or any task runs) and by ``with_parameters``.

        Parameters
        ----------
        name : str
            The parameter's name (for the message: ``parameters.NAME``).
        value : object
            Its value, as :meth:`check` made it.
        values : mapping of str to object
            Every parameter's value (each as its own :meth:`check` made it).

        Raises
        ------
        SpecificationError
            Naming ``parameters.NAME``, the value and the rule.
        """


@dataclasses.dataclass(frozen=True)
class Output:
    """A result variable of a study.

    Parameters
    ----------
    dims : tuple of str
        Extra dimensions beyond the study axes (their coordinates in ``Study.coords``).
    dtype : str
        A numeric numpy dtype; the task's values are cast to it (integer dtypes refuse values
        outside their range or not whole, instead of wrapping).
    units : str
        CF ``units`` attribute.
    long_name : str
        CF ``long_name`` attribute.
    finite : bool
        If True (default) every value a block returns must be finite (NaN or infinity fails the
        block, which is then not marked done); False stores NaN/inf as given (e.g. "not defined
        here").
    """

    dims: tuple[str, ...] = ()
    dtype: str = "float64"
    units: str = ""
    long_name: str = ""
    finite: bool = True

    def __post_init__(self):
        object.__setattr__(self, "dims", tuple(self.dims))
        try:
            dt = np.dtype(self.dtype)
        except TypeError as exc:
            raise SpecificationError("output.dtype", self.dtype, "must be a numpy dtype") from exc
        if dt.kind not in "biufc":
            raise SpecificationError("output.dtype", self.dtype, "must be a numeric dtype")
        if not isinstance(self.finite, bool):
            raise SpecificationError("output.finite", self.finite, "must be True or False")

    def cast(self, name: str, values: ArrayLike, block_index: Sequence[int]) -> np.ndarray:
        """``values`` as this output's dtype, refusing what the cast would silently change.

        Parameters
        ----------
        name : str
            The output's name (for the message: ``outputs.NAME``).
        values : array_like
            What a block's task returned for this output.
        block_index : sequence of int
            The block's index per axis (for the message).

        Returns
        -------
        numpy.ndarray
            ``values`` in this output's dtype.

        Raises
        ------
        SpecificationError
            Naming the output, the block and the rule: a non-finite value (unless
            ``finite=False``); for an integer dtype, a value outside its range, not whole or not
            finite; for a bool dtype, a value other than 0/1.
        """
        arr = np.asarray(values)
        dt = np.dtype(self.dtype)
        field = f"outputs.{name}"

        def refuse(mask, rule):
            bad = np.argwhere(mask)[0]
            where = tuple(int(i) for i in bad)
            raise SpecificationError(field, Described(f"{shown(arr[where])} at position {where} of block {tuple(block_index)}"),
                                     rule)

        if arr.dtype.kind not in "biufc":
            raise SpecificationError(field, Described(f"{arr.dtype} values from block {tuple(block_index)}"),
                                     f"must be numbers castable to {dt}")
        if arr.dtype.kind in "fc" and (dt.kind in "biu" or self.finite):
            finite = np.isfinite(arr)
            if not finite.all():
                rule = (f"must be finite: {dt} cannot hold NaN or infinity" if dt.kind in "biu" else
                        "must be finite (declare Output(finite=False) to store NaN or infinity)")
                refuse(~finite, rule)
        if dt.kind in "iu" and arr.dtype.kind in "biufc":
            if arr.dtype.kind == "c":
                raise SpecificationError(field, Described(f"complex values from block {tuple(block_index)}"),
                                         f"must be real to be stored as {dt}")
            info = np.iinfo(dt)
            if arr.dtype.kind == "f":
                refuse_if = arr != np.round(arr)
                if refuse_if.any():
                    refuse(refuse_if, f"must be whole numbers to be stored as {dt}")
            if arr.size and arr.dtype.kind in "iuf":
                # floats against the exclusive bound max + 1 (a power of two, exact): int64's max rounds up to
                # 2**63 as a float, so 2.0**63 > max is False and the cast would wrap it
                out = (arr < info.min) | ((arr >= float(info.max) + 1.0) if arr.dtype.kind == "f" else (arr > info.max))
                if out.any():
                    refuse(out, f"must lie in [{info.min}, {info.max}], the range of {dt} (not wrapped)")
        if dt.kind == "b" and arr.dtype.kind != "b":
            bad = (arr != 0) & (arr != 1)
            if np.any(bad):
                refuse(bad, "must be 0 or 1 (or booleans) to be stored as bool")
        if dt.kind == "f" and arr.dtype.kind == "c":
            bad = np.imag(arr) != 0
            if bad.any():
                refuse(bad, f"must be real to be stored as {dt} (declare dtype='complex128')")
            arr = arr.real
        with np.errstate(over="ignore", invalid="ignore"):  # an overflow is refused just below
            cast = arr.astype(dt, copy=False)
        if dt.kind in "fc" and self.finite and not np.isfinite(cast).all():
            refuse(~np.isfinite(cast), f"must be finite once stored as {dt} (a value overflows it)")
        return cast


@dataclasses.dataclass(frozen=True)
class Warmup:
    """Work a study's tasks need done once per machine before the first block (e.g. compiling numba code).

    The runner calls ``needed`` on one worker of each host and, where it says True, prints
    ``message`` and calls ``run`` there, before submitting any block (in the calling process for
    ``--workers 0``). Functions defined in a study file are sent to the workers by value.

    Parameters
    ----------
    message : str
        What the runner prints before doing it, e.g. "compiling the solver, once per machine, ~55 s".
    run : callable
        ``run()`` does the work in a worker process (idempotent; its result is ignored).
    needed : callable
        ``needed() -> bool``: cheaply, in a worker process, whether the work is still to do on that
        machine (e.g. a cold numba cache).
    """

    message: str
    run: Callable[[], Any]
    needed: Callable[[], bool]

    def __post_init__(self):
        if not isinstance(self.message, str) or not self.message:
            raise SpecificationError("warmup.message", self.message, "must be a non-empty string")
        for f in ("run", "needed"):
            if not callable(getattr(self, f)):
                raise SpecificationError(f"warmup.{f}", getattr(self, f), "must be callable without arguments")


@dataclasses.dataclass(frozen=True)
class Block:
    """One block of the sweep: its index per axis, slice per axis and coordinates per axis."""

    index: tuple[int, ...]
    slices: dict[str, slice]
    coords: dict[str, np.ndarray]

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(s.stop - s.start for s in self.slices.values())


class Parameterised:
    """Shared by :class:`Study` and ``Pipeline``: a ``parameters`` mapping of :class:`Parameter`."""

    @property
    def values(self) -> dict[str, Any]:
        """The parameter values (passed to the task or to the stage functions)."""
        return {name: p.value for name, p in self.parameters.items()}

    def with_parameters(self, overrides: Mapping[str, Any]):
        """A copy with some parameter values replaced (unknown names and inadmissible values refused,
        also those inadmissible together: :meth:`check_parameters`)."""
        params = dict(self.parameters)
        for name, value in overrides.items():
            if name not in params:
                raise SpecificationError(f"parameters.{name}", value, f"unknown parameter (known: {sorted(params)})")
            params[name] = dataclasses.replace(params[name], value=params[name].check(name, value))
        return dataclasses.replace(self, parameters=params).check_parameters()

    def check_parameters(self):
        """Check the rules between parameters (each :class:`Parameter`'s ``check_with``); returns ``self``."""
        values = self.values
        for name, p in self.parameters.items():
            p.check_with(name, values[name], values)
        return self


@dataclasses.dataclass(frozen=True)
class Study(Parameterised):
    """A parameter sweep run as one dask task per block (see the module docstring).

    Parameters
    ----------
    name : str
        Identifier (the store's file name).
    seed : int
        Non-negative study seed; every random draw derives from it and the point's coordinates.
    axes : mapping of str to array_like
        Ordered ``{dim: coordinate values}`` of the sweep.
    task : callable
        ``task(block, rng, **parameters) -> {output: array}``: ``block`` maps each axis to the
        block's coordinates, ``rng`` is a :class:`RngFactory`; see :func:`pointwise`.
    outputs : mapping of str to Output
        ``{name: Output}``: the result variables.
    chunks : mapping of str to int
        ``{dim: points per block}``; missing dims use ``tubeid.runner.default-chunk``.
    coords : mapping of str to array_like
        Coordinates of the outputs' extra dims.
    units : mapping of str to str
        ``{dim: units}`` of the coordinates.
    seed_axes : tuple of str, optional
        Axes whose coordinates key the random streams (default: all axes; ``("realisation",)``
        gives common random numbers across the other axes).
    parameters : mapping of str to object
        ``{name: plain value or Parameter}``, passed to ``task`` as keywords.
    model : object, optional
        The model specification, stored as text in the provenance.
    check : callable, optional
        ``check(study)`` raising ``SpecificationError`` for rules that involve several fields
        (e.g. an axis range that depends on a parameter).
    description : str
        One line for ``show`` and the store's ``title``.
    summarize : callable, optional
        ``summarize(dataset) -> str``: a short text ``tubeid show`` prints.
    stream_key : tuple of str
        Prefix of every random stream key (in a pipeline: the stage name, unless the stage gives one,
        e.g. an earlier stage's name to draw the same streams as that stage).
    long_names : mapping of str to str
        ``{dim: long_name}`` of the coordinates (CF).
    references : str
        CF ``references`` attribute (e.g. the paper).
    warmup : Warmup, optional
        Work needed once per machine before the first block.
    in_process : bool
        Run the blocks in the runner's own process, not on the cluster: for a study whose whole
        work costs less than a round trip to the workers (e.g. a pipeline stage's placeholder).
        The values do not depend on it (it is not part of :meth:`fingerprint`).
    """

    name: str
    seed: int
    axes: Mapping[str, Any]
    task: Callable
    outputs: Mapping[str, Output]
    chunks: Mapping[str, int] = dataclasses.field(default_factory=dict)
    coords: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    units: Mapping[str, str] = dataclasses.field(default_factory=dict)
    seed_axes: tuple[str, ...] | None = None
    parameters: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    model: Any = None
    check: Callable | None = None
    description: str = ""
    summarize: Callable | None = None
    stream_key: tuple[str, ...] = ()
    long_names: Mapping[str, str] = dataclasses.field(default_factory=dict)
    references: str = ""
    warmup: Warmup | None = None
    in_process: bool = False

    def __post_init__(self):
        from tubeid import config

        check_name("name", self.name)
        _validation.seed("seed", self.seed)
        if not self.axes:
            raise SpecificationError("axes", dict(self.axes), "must name at least one axis")
        axes = {}
        for dim, values in self.axes.items():
            arr = np.asarray(list(values) if isinstance(values, range) else values)
            if arr.ndim != 1 or arr.size == 0:
                raise SpecificationError(f"axes.{dim}", _short(values), "must be a non-empty 1-D sequence")
            if arr.dtype.kind not in "biufU":
                raise SpecificationError(f"axes.{dim}", _short(values), "must hold numbers or strings")
            if len(np.unique(arr)) != arr.size:
                raise SpecificationError(f"axes.{dim}", _short(values), "coordinates must be distinct")
            axes[dim] = arr
        object.__setattr__(self, "axes", axes)
        chunks = {}
        for dim, c in self.chunks.items():
            if dim not in axes:
                raise SpecificationError(f"chunks.{dim}", c, f"is not an axis (axes: {list(axes)})")
        for dim in axes:
            c = self.chunks[dim] if dim in self.chunks else config.value("runner.default-chunk")  # refused by name
            if isinstance(c, bool) or not isinstance(c, (int, np.integer)) or c < 1:
                raise SpecificationError(f"chunks.{dim}", c, "must be a positive integer")
            chunks[dim] = min(int(c), axes[dim].size)
        object.__setattr__(self, "chunks", chunks)
        coords = {}
        for dim, values in self.coords.items():
            if dim in axes:
                raise SpecificationError(f"coords.{dim}", _short(values), "is an axis; give its values in axes")
            arr = np.asarray(values)
            if arr.ndim != 1 or arr.size == 0:
                raise SpecificationError(f"coords.{dim}", _short(values), "must be a non-empty 1-D sequence")
            coords[dim] = arr
        object.__setattr__(self, "coords", coords)
        if not callable(self.task):
            raise SpecificationError("task", self.task, "must be callable as task(block, rng, **parameters)")
        if not self.outputs:
            raise SpecificationError("outputs", dict(self.outputs), "must declare at least one output")
        for name, out in self.outputs.items():
            if not isinstance(out, Output):
                raise SpecificationError(f"outputs.{name}", out, "must be an Output")
            for dim in out.dims:
                if dim not in coords:
                    raise SpecificationError(f"outputs.{name}.dims", out.dims, f"dim {dim!r} needs coordinates in Study.coords")
            if name in axes or name in coords or name == RESERVED:
                raise SpecificationError(f"outputs.{name}", name, "clashes with a dimension or reserved name")
        seed_axes = tuple(axes) if self.seed_axes is None else tuple(self.seed_axes)
        for dim in seed_axes:
            if dim not in axes:
                raise SpecificationError("seed_axes", seed_axes, f"{dim!r} is not an axis (axes: {list(axes)})")
        object.__setattr__(self, "seed_axes", seed_axes)
        params = {}
        for name, p in self.parameters.items():
            p = p if isinstance(p, Parameter) else Parameter(p)
            params[name] = dataclasses.replace(p, value=p.check(name, p.value))
        object.__setattr__(self, "parameters", params)
        if self.summarize is not None and not callable(self.summarize):
            raise SpecificationError("summarize", self.summarize, "must be callable as summarize(ds) -> dict")
        key = tuple(self.stream_key)
        if not all(isinstance(k, str) for k in key):
            raise SpecificationError("stream_key", key, "must be a tuple of strings")
        object.__setattr__(self, "stream_key", key)
        for field, mapping in (("units", self.units), ("long_names", self.long_names)):
            for dim, text in mapping.items():
                if dim not in axes and dim not in coords:
                    raise SpecificationError(f"{field}.{dim}", text, f"is not a coordinate (axes {list(axes)}, coords {list(coords)})")
                if not isinstance(text, str):
                    raise SpecificationError(f"{field}.{dim}", text, "must be a string")
        if RESERVED in axes or RESERVED in coords:
            raise SpecificationError("axes", RESERVED, "is reserved for the store's bookkeeping")
        if not isinstance(self.references, str):
            raise SpecificationError("references", self.references, "must be a string")
        if not isinstance(self.in_process, bool):
            raise SpecificationError("in_process", self.in_process, "must be True or False")
        if self.warmup is not None and not isinstance(self.warmup, Warmup):
            raise SpecificationError("warmup", self.warmup, "must be a tubeid.runner.Warmup")
        self._check_signature()
        if self.check is not None:
            self.check(self)

    # -- parameters ---------------------------------------------------------------------------
    def _check_signature(self):
        try:
            sig = inspect.signature(self.task)
        except (TypeError, ValueError):
            return
        kw = {n: p for n, p in list(sig.parameters.items())[2:]}
        if any(p.kind is p.VAR_KEYWORD for p in kw.values()):
            return
        for name in self.parameters:
            if name not in kw:
                raise SpecificationError(f"parameters.{name}", self.parameters[name].value,
                                         f"unknown parameter: the task accepts {sorted(kw)}")
        for name, p in kw.items():
            if p.default is p.empty and p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD) and name not in self.parameters:
                raise SpecificationError(f"parameters.{name}", None, "required by the task but not given")

    def coordinate_attrs(self, dim: str) -> dict[str, str]:
        """CF attributes of a coordinate.

        Parameters
        ----------
        dim : str
            An axis or an extra dimension of the outputs.

        Returns
        -------
        dict of str to str
            ``long_name`` always, ``units`` unless the coordinate is a label (strings).
        """
        values = self.axes[dim] if dim in self.axes else self.coords[dim]
        d_units, d_long = COORDINATE_DEFAULTS.get(dim, (None, dim))
        units = self.units.get(dim, d_units)
        attrs = {"long_name": self.long_names.get(dim, d_long)}
        if units is not None and values.dtype.kind != "U" and units != "":
            attrs["units"] = units
        return attrs

    # -- geometry -----------------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(a.size for a in self.axes.values())

    @property
    def block_grid(self) -> tuple[int, ...]:
        """Number of blocks along each axis."""
        return tuple(-(-a.size // self.chunks[d]) for d, a in self.axes.items())

    @property
    def n_blocks(self) -> int:
        return math.prod(self.block_grid)

    def block(self, index: Sequence[int]) -> Block:
        """One block of the sweep.

        Parameters
        ----------
        index : sequence of int
            The block's index along each axis (within :attr:`block_grid`).

        Returns
        -------
        Block
            Its index, slices and coordinates per axis.
        """
        slices, coords = {}, {}
        for (dim, values), i in zip(self.axes.items(), index):
            c = self.chunks[dim]
            slices[dim] = slice(i * c, min((i + 1) * c, values.size))
            coords[dim] = values[slices[dim]]
        return Block(tuple(int(i) for i in index), slices, coords)

    def blocks(self) -> Iterator[Block]:
        """All blocks, in C order of their indices.

        Yields
        ------
        Block
            Each block of the sweep.
        """
        for index in itertools.product(*(range(n) for n in self.block_grid)):
            yield self.block(index)

    # -- randomness ---------------------------------------------------------------------------
    @property
    def rng(self) -> "RngFactory":
        """The factory passed to the task: ``rng(**seed-axis coords)`` -> Generator of one point."""
        return RngFactory(int(self.seed), self.seed_axes, self.stream_key)

    def compute_block(self, block: Block) -> dict[str, np.ndarray]:
        """Run the task on one block; check and cast its outputs.

        Parameters
        ----------
        block : Block
            The block (from :meth:`block`).

        Returns
        -------
        dict of str to numpy.ndarray
            Each output's values, shape ``block.shape`` + its extra dims, in its dtype.
        """
        result = self.task(block.coords, self.rng, **self.values)
        if not isinstance(result, Mapping):
            if len(self.outputs) != 1:
                raise SpecificationError("task result", type(result).__name__, "must be a dict {output name: array}")
            result = {next(iter(self.outputs)): result}
        if set(result) != set(self.outputs):
            raise SpecificationError("task result", sorted(result), f"must have exactly the outputs {sorted(self.outputs)}")
        out = {}
        for name, spec in self.outputs.items():
            arr = np.asarray(result[name])
            shape = block.shape + tuple(self.coords[d].size for d in spec.dims)
            if arr.shape != shape:
                raise SpecificationError(f"task result {name}.shape", arr.shape, f"must be {shape} for block {block.index}")
            out[name] = spec.cast(name, arr, block.index)
        return out

    def describe_model(self) -> str:
        """The model specification as text.

        Returns
        -------
        str
            ``to_yaml``/``to_text``/``to_json`` of the model, JSON of a dataclass or mapping, or
            ``''`` if the study has none.
        """
        m = self.model
        if m is None:
            return ""
        for attr in ("to_yaml", "to_text", "to_json"):
            if callable(getattr(m, attr, None)):
                return str(getattr(m, attr)())
        if dataclasses.is_dataclass(m):
            m = dataclasses.asdict(m)
        if isinstance(m, (Mapping, list, tuple)):
            return json.dumps(m, default=repr, indent=1)
        return m if isinstance(m, str) else repr(m)

    def fingerprint(self) -> str:
        """Canonical JSON of everything that defines the results (axes, chunks, seeds, parameters...).

        Equal fingerprints in two processes mean the same sweep; a pipeline hashes it into the
        stage hash, so any value a stage was built from (e.g. an identified delta_opt passed as a
        parameter or used in an axis) is part of the stage's identity.

        Returns
        -------
        str
            The JSON text (keys sorted).
        """
        return json.dumps({
            "name": self.name, "seed": int(self.seed), "stream_key": list(self.stream_key),
            "axes": {d: a.tolist() for d, a in self.axes.items()}, "chunks": dict(self.chunks),
            "coords": {d: a.tolist() for d, a in self.coords.items()}, "units": dict(self.units),
            "seed_axes": list(self.seed_axes), "parameters": self.values, "long_names": dict(self.long_names),
            "references": self.references,
            "outputs": {n: dataclasses.asdict(o) for n, o in self.outputs.items()},
            "model": self.describe_model(), "description": self.description,
            "task": getattr(self.task, "__qualname__", type(self.task).__name__),
        }, sort_keys=True)


def _short(values, n=6):
    values = list(values) if not isinstance(values, (str, bytes)) else values
    return values if len(values) <= n else f"{values[:n]}... ({len(values)} values)"


def pointwise(fn: Callable) -> Callable:
    """Make a block task from a per-point function.

    Parameters
    ----------
    fn : callable
        ``fn(point, rng, **parameters) -> {output: array}`` (or one array for a single output):
        ``point`` maps each axis to its scalar coordinate; ``rng`` is that point's generator (keyed
        by the seed axes).

    Returns
    -------
    callable
        ``task(block, rng, **parameters)`` for :class:`Study`: the per-point outputs stacked over
        the block; it keeps ``fn``'s signature (its keyword parameters are checked by the study).
    """
    sig = inspect.signature(fn)

    @functools.wraps(fn)
    def task(block, rng, **parameters):
        dims = list(block)
        sizes = [len(block[d]) for d in dims]
        collected: dict[str, np.ndarray] = {}
        for flat, idx in enumerate(itertools.product(*(range(n) for n in sizes))):
            point = {d: _scalar(block[d][i]) for d, i in zip(dims, idx)}
            res = fn(point, rng.at(point), **parameters)
            if not isinstance(res, Mapping):
                res = {None: res}
            for name, value in res.items():
                value = np.asarray(value)
                if name not in collected:
                    collected[name] = np.empty(tuple(sizes) + value.shape, dtype=value.dtype)
                collected[name][idx] = value
        return collected[None] if list(collected) == [None] else collected

    task.__signature__ = sig  # keep the parameter names visible to Study validation
    return task


@dataclasses.dataclass(frozen=True)
class RngFactory:
    """Generators keyed by (study seed, prefix, a point's coordinates on the seed axes, optional stream names).

    ``rng(realisation=3)`` (exactly the seed axes as keywords) or ``rng.at(point)`` (a full point;
    coordinates on other axes are ignored). ``rng("loads", realisation=3)`` gives an independent
    named stream at the same point. Never keyed by block or worker.

    Parameters
    ----------
    seed : int
        The study seed.
    seed_axes : tuple of str
        The axes whose coordinates key the streams.
    prefix : tuple of str
        The study's ``stream_key`` (in a pipeline: the stage name, so stages draw independent
        streams while keeping common random numbers across a stage's non-seed axes).
    """

    seed: int
    seed_axes: tuple[str, ...]
    prefix: tuple[str, ...] = ()

    def __call__(self, *stream, **coords) -> np.random.Generator:
        if set(coords) != set(self.seed_axes):
            raise SpecificationError("rng coordinates", sorted(coords), f"must be exactly the seed axes {list(self.seed_axes)}")
        return rng_for(self.seed, *self.prefix, *(_scalar(coords[d]) for d in self.seed_axes), *stream)

    def at(self, point: Mapping[str, Any], *stream: str | int) -> np.random.Generator:
        """The generator of one point.

        Parameters
        ----------
        point : mapping of str to object
            The point's coordinate on every axis (those off the seed axes are ignored).
        *stream : str or int
            Optional names of an independent stream at the same point.

        Returns
        -------
        numpy.random.Generator
            ``rng_for(seed, *prefix, *seed-axis coordinates, *stream)``.
        """
        return self(*stream, **{d: point[d] for d in self.seed_axes})


def study_hash(source: str, overrides: Mapping[str, Any] | None = None) -> str:
    """SHA-256 of the study source text and the parameter overrides (the study's identity)."""
    plain = {str(k): _plain(v, f"parameters.{k}") for k, v in dict(overrides or {}).items()}
    h = hashlib.sha256(source.encode())
    h.update(b"\0" + json.dumps(plain, sort_keys=True).encode())
    return h.hexdigest()


#: The definitions as written, executed once per process: {hash of the source alone: study or pipeline}
_DEFINITIONS: dict[str, Any] = {}


def load_definition(path: str | pathlib.Path | None = None, *, source: str | None = None,
                    overrides: Mapping[str, Any] | None = None):
    """Execute a study file (or its ``source`` text) and return ``(study or pipeline, source, hash)``.

    The file defines a module-level ``study = Study(...)`` or ``study = Pipeline(...)``. Its execution
    is kept per process by the source's hash, so a worker executes each source once; ``overrides`` are
    applied at every call, never kept: a parameter whose check reads a file (a model specification)
    sees the file as it is now, also in a process that loaded the study before the file was edited.
    """
    from tubeid.runner.pipeline import Pipeline

    if source is None:
        p = pathlib.Path(path)
        if p.is_dir():
            raise SpecificationError("study", str(path), "is a directory: give a study file (e.g. studies/pi.py)")
        if not p.is_file():
            raise SpecificationError("study", str(path), "no such study file")
        source = read_source(p)
    overrides = dict(overrides or {})
    key = study_hash(source, overrides)
    written = study_hash(source, {})
    if written not in _DEFINITIONS:
        module = types.ModuleType(f"tubeid_study_{written[:12]}")
        module.__file__ = str(path or "<study>")
        try:
            code = compile(source, module.__file__, "exec")
        except SyntaxError as exc:
            raise SpecificationError("study", str(path), f"is not valid Python: {exc}") from exc
        sys.modules[module.__name__] = module  # dataclasses and pickling look modules up here
        with contextlib.suppress(Exception):  # its functions (e.g. a Warmup's) reach workers by value
            import cloudpickle

            cloudpickle.register_pickle_by_value(module)
        try:
            exec(code, module.__dict__)
        except SpecificationError:  # a definition tubeid refused (e.g. Study(axes={})): one line, as any refusal
            sys.modules.pop(module.__name__, None)
            raise
        except Exception as exc:  # a bug in the study's own code
            sys.modules.pop(module.__name__, None)
            raise StudyRaised(module.__file__, exc) from exc
        study = getattr(module, "study", None)
        if not isinstance(study, (Study, Pipeline)):
            raise SpecificationError("study", str(path), "must define a module-level `study = Study(...)` or `Pipeline(...)`")
        _DEFINITIONS[written] = study
    study = _DEFINITIONS[written]
    return (study.with_parameters(overrides) if overrides else study.check_parameters()), source, key


def read_source(path: str | pathlib.Path) -> str:
    """The text of a Python file, decoded as Python decodes a source file.

    UTF-8 unless a coding line (PEP 263) names another encoding; a UTF-8 byte-order mark is dropped;
    line endings read as ``\\n`` (universal newlines, as ``Path.read_text``, so the text, and the study
    hash, of a UTF-8 file are those it always had). A file that cannot be decoded is refused naming it.
    """
    import io
    import tokenize

    p = pathlib.Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise SpecificationError("study", str(path), f"cannot be read ({exc.strerror or exc})") from None
    try:
        encoding, _ = tokenize.detect_encoding(io.BytesIO(data).readline)
    except SyntaxError as exc:  # an unknown or inconsistent coding line, or no coding line and not UTF-8
        encoding, why = None, exc.msg if isinstance(exc.msg, str) else str(exc)
    if encoding is not None:
        try:
            return io.TextIOWrapper(io.BytesIO(data), encoding=encoding).read()
        except (UnicodeDecodeError, LookupError) as exc:
            why = " ".join(str(exc).split())
    try:
        data.decode("utf-8")
    except UnicodeDecodeError as exc:
        if encoding in (None, "utf-8", "utf-8-sig"):  # no coding line: say where it is not UTF-8
            why = f"byte {data[exc.start]:#04x} at position {exc.start} is not UTF-8"
    raise SpecificationError("study", str(path), f"cannot be decoded ({why}): a study file is UTF-8 unless a coding "
                             "line on its first or second line names another encoding (PEP 263, e.g. "
                             "`# -*- coding: latin-1 -*-`)")


def _library_dirs() -> tuple[str, ...]:
    """Directories whose frames are not a study's own: tubeid's package, the standard library, site-packages."""
    import os
    import sysconfig

    import tubeid

    dirs = {os.path.dirname(os.path.abspath(tubeid.__file__))}
    paths = sysconfig.get_paths()
    dirs.update(paths[k] for k in ("stdlib", "platstdlib", "purelib", "platlib") if paths.get(k))
    return tuple(os.path.join(os.path.abspath(d), "") for d in dirs)


def _users_traceback(exc: BaseException, study_file: str) -> str:
    """``exc``'s traceback (chained exceptions included) with only the study's own frames: the study file's
    and those of the user's other modules, never tubeid's, the standard library's or site-packages'."""
    import os
    import traceback

    library = _library_dirs()

    def own(frame) -> bool:
        name = frame.filename
        if name == study_file:
            return True
        if name.startswith("<"):  # <frozen importlib...>, <string>
            return False
        return not os.path.abspath(name).startswith(library)

    te = traceback.TracebackException(type(exc), exc, exc.__traceback__)
    seen = set()
    todo = [te]
    while todo:
        t = todo.pop()
        if id(t) in seen:
            continue
        seen.add(id(t))
        t.stack = traceback.StackSummary.from_list([f for f in t.stack if own(f)])
        todo += [c for c in (t.__cause__, t.__context__) if c is not None]
    return "".join(te.format())


class StudyRaised(RuntimeError):
    """A study file raised while being executed: a bug in its own code (a refusal, ``SpecificationError``,
    passes unchanged). The message is one line, ``study = 'r.py': raised RuntimeError: boom while being
    executed``; ``user_traceback`` is the exception's traceback reduced to the study's own frames (what
    ``tubeid`` prints before that line, as it does for a failing task); the exception is ``__cause__``.

    Parameters
    ----------
    study_file : str
        The study file as it was named.
    cause : BaseException or str
        The exception (or its ``"Type: message"`` text).
    user_traceback : str, optional
        The traceback text (default: computed from ``cause``).
    """

    def __init__(self, study_file: str, cause, user_traceback: str | None = None) -> None:
        from tubeid.errors import shown

        if isinstance(cause, BaseException):
            if user_traceback is None:
                user_traceback = _users_traceback(cause, study_file)
            cause = f"{type(cause).__name__}: {cause}" if str(cause) else type(cause).__name__
        self.study_file, self.cause, self.user_traceback = study_file, cause, user_traceback or ""
        text = " ".join(str(cause).split())
        text = text if len(text) <= 480 else f"{text[:400]}…{text[-60:]}"
        super().__init__(f"study = {shown(study_file)}: raised {text} while being executed")

    def __reduce__(self):
        return type(self), (self.study_file, self.cause, self.user_traceback)


def load_study(path: str | pathlib.Path | None = None, *, source: str | None = None,
               overrides: Mapping[str, Any] | None = None) -> tuple[Study, str, str]:
    """Execute a study file that defines a single :class:`Study`.

    Parameters
    ----------
    path : str or pathlib.Path, optional
        The study file (a ``studies/*.py``), unless ``source`` is given.
    source : str, optional
        The file's text instead of a path.
    overrides : mapping of str to object, optional
        Parameter values replacing the defaults (``--set``), each checked by its :class:`Parameter`.

    Returns
    -------
    tuple of (Study, str, str)
        The study, its source text and the hash of (source, overrides).
    """
    study, source, key = load_definition(path, source=source, overrides=overrides)
    if not isinstance(study, Study):
        raise SpecificationError("study", str(path or "<study>"), "must define a `Study` (this file defines a Pipeline)")
    return study, source, key
