"""Declarative, validated, immutable specification of a tube bundle.

Units are SI throughout: metres, kilograms, seconds, newtons, pascals. A bundle is a set of
Euler–Bernoulli tubes (transverse displacement ``y`` and rotation ``theta`` per node), linear
springs between two tubes' points or to the ground, symmetric elastic stops, load points and
sensors. The *non-linear tube* (subsystem A of the paper) is the tube that carries the stops;
everything else is the linear subsystem B, and the coupling interface is the set of A's nodes
where a link joins A to B.

A specification is built in Python or read from YAML/TOML by :func:`load_spec`. Every rule is
checked when the object is made; a broken rule raises :class:`~tubeid.errors.SpecificationError`
naming the field (``tubes[1].length``), the value and the rule. Numbers must be numbers (``"16"``
in quotes is refused, never converted). Limits (configuration ``tubeid.io``): at most ``max-dof``
degrees of freedom in the bundle and ``max-sensors`` sensors, load points or tones, each refusal
stating the memory it would take.

Files: YAML is read with PyYAML's safe loader with three changes: **aliases** (``*name``, also in
``<<:`` merges) are refused, so a specification cannot expand beyond its own size (an "alias bomb"
is refused at its first alias); a key given twice in a mapping is refused (YAML would keep the last
silently); and a number with an exponent but no dot or exponent sign (``7.5e8``, ``1e6``), text
under YAML 1.1, is read as the number a user means, as YAML 1.2 does.
A file larger than ``tubeid.io.max-specification-bytes`` is refused before it is parsed.
"""

from __future__ import annotations

import dataclasses
import functools
import io
import math
import pathlib
import re
from dataclasses import dataclass, field
from typing import Any, Mapping

from tubeid._validation import byte_size, channel_count, integer, limit, non_negative, on_tube, positive, real
from tubeid.errors import Described, SpecificationError

__all__ = [
    "TubeSpec",
    "LinkSpec",
    "StopSpec",
    "LoadPoint",
    "SensorSpec",
    "ReductionSpec",
    "BundleSpec",
    "load_spec",
    "spec_from_dict",
    "spec_to_dict",
]

END_CONDITIONS = ("clamped", "pinned", "free")
LOAD_KINDS = ("force", "moment")
_NODE_TOL = 1e-9  # m: a position closer than this to a node is that node
#: A link's or stop's stiffness k must lie within [1/STIFFNESS_RATIO, STIFFNESS_RATIO] times the element
#: stiffness 12 EI/Le³ of the tube(s) it acts on (the softer one): the assembled stiffness matrix adds k to
#: the tube's own diagonal entries (24 EI/Le³ at an inner node), so outside this range the smaller of the
#: two keeps fewer than 8 of the 16 digits of a double. Beyond the upper bound the tubes' stiffness is
#: lost to round-off (measured on the paper's simplified model: its grid links at 5e8 times the element
#: stiffness move the first eigenfrequency by 3e-7, at 5e13 times by 9 %, silently); below the lower bound
#: the spring itself is lost. The built-in models' springs and stops are 0.83 to 7.8 times the element
#: stiffness (``python benchmarks/stiffness_range.py``).
STIFFNESS_RATIO = 1e8



def _check_dof(field: str, value, n_dof: int, what: str) -> None:
    """Refuse a model of more than ``tubeid.io.max-dof`` degrees of freedom, stating its memory."""
    bound = int(limit("max-dof"))
    if n_dof > bound:
        if n_dof < 10**15:
            count, memory = str(n_dof), byte_size(24.0 * n_dof**2)
        else:  # beyond float range for a huge int: state the order of magnitude
            digits = int(n_dof.bit_length() * math.log10(2))
            count, memory = f"about 10^{digits}", f"about 10^{2 * digits + 1} B"
        raise SpecificationError(
            field, value,
            f"{what} would have {count} degrees of freedom, at most {bound} (configuration tubeid.io.max-dof): "
            f"its dense mass, damping and stiffness matrices alone take 3 × 8 B × N² = {memory}")


@dataclass(frozen=True)
class TubeSpec:
    """One tube: a hollow circular Euler beam meshed with equal Hermite elements.

    Parameters
    ----------
    name : str
        Unique name, used by links, stops, loads and sensors.
    length : float
        Length [m].
    outer_radius : float
        Outer radius of the section [m].
    wall : float
        Wall thickness [m], at most ``outer_radius``.
    density : float
        Density [kg/m³].
    youngs_modulus : float
        Young's modulus [Pa].
    n_elements : int
        Number of equal Hermite (cubic) elements.
    ends : tuple of (str, str)
        End conditions at x = 0 and x = length, each ``clamped``, ``pinned`` or ``free``.
    damping_ratio : float
        Modal damping ratio in [0, 1) applied on the tube's own modes (with its end conditions,
        without links): D = M Φ diag(2 ξ ω) Φᵀ M.
    """

    name: str
    length: float
    outer_radius: float
    wall: float
    density: float
    youngs_modulus: float
    n_elements: int = 8
    ends: tuple[str, str] = ("clamped", "clamped")
    damping_ratio: float = 0.02

    def validate(self, where: str) -> None:
        """Check every field; refuse the first broken rule.

        Parameters
        ----------
        where : str
            How the tube is named in messages, e.g. ``"tubes[1]"``.

        Raises
        ------
        SpecificationError
            Naming ``where.field``, the value and the rule.
        """
        if not isinstance(self.name, str) or not self.name:
            raise SpecificationError(f"{where}.name", self.name, "must be a non-empty string")
        for f in ("length", "outer_radius", "wall", "density", "youngs_modulus"):
            positive(f"{where}.{f}", getattr(self, f))
        if self.wall > self.outer_radius:
            raise SpecificationError(f"{where}.wall", self.wall, f"must be <= outer_radius ({self.outer_radius} m)")
        if not isinstance(self.n_elements, int) or isinstance(self.n_elements, bool) or self.n_elements < 1:
            raise SpecificationError(f"{where}.n_elements", self.n_elements, "must be an integer >= 1")
        _check_dof(f"{where}.n_elements", self.n_elements, 2 * (self.n_elements + 1), "this tube alone")
        # The element matrices' scales (mass ρA·Le, ρA·Le³; stiffness EI/Le³, EI/Le) with a margin of 1e3 for
        # their coefficients and sums, and of their eigenvalues with a margin of 1e10: finite and > 0 in
        # floating point (no overflow, no cancellation or underflow to 0).
        try:
            le = self.length / self.n_elements
            rho_a, ei = self.density * self.area, self.youngs_modulus * self.inertia
            omega2 = ei / (rho_a * le**4)  # the scale of the eigenvalues ω²: its inverse must be finite too
            scales = (self.area, self.inertia, 1e3 * rho_a * le, 1e3 * rho_a * le**3, 1e3 * ei / le**3, 1e3 * ei / le,
                      1e10 * omega2, 1e10 / omega2)
        except (OverflowError, ZeroDivisionError):  # beyond the range of doubles, or underflow to 0
            scales = (math.inf,)
        if not all(math.isfinite(v) and v > 0 for v in scales):
            raise SpecificationError(
                where, Described(f"length {self.length!r} m, outer_radius {self.outer_radius!r} m, wall {self.wall!r} m, "
                                 f"density {self.density!r}, youngs_modulus {self.youngs_modulus!r}"),
                "the section's area and inertia and the element mass and stiffness must be finite numbers > 0 "
                "in floating point (a value is beyond the range of doubles)")
        if not isinstance(self.ends, tuple) or len(self.ends) != 2 or any(e not in END_CONDITIONS for e in self.ends):
            raise SpecificationError(f"{where}.ends", self.ends, f"must be two of {END_CONDITIONS}")
        if non_negative(f"{where}.damping_ratio", self.damping_ratio) >= 1.0:
            raise SpecificationError(f"{where}.damping_ratio", self.damping_ratio, "must be in [0, 1)")

    @property
    def area(self) -> float:
        """Cross-section area [m²]."""
        ri = self.outer_radius - self.wall
        return math.pi * (self.outer_radius**2 - ri**2)

    @property
    def inertia(self) -> float:
        """Second moment of area [m⁴]."""
        ri = self.outer_radius - self.wall
        return math.pi / 4.0 * (self.outer_radius**4 - ri**4)

    @property
    def element_stiffness(self) -> float:
        """Transverse stiffness scale of one element, 12 EI/Le³ [N/m] (the y–y entry of its stiffness matrix)."""
        return 12.0 * self.youngs_modulus * self.inertia / (self.length / self.n_elements) ** 3

    @property
    def nodes(self) -> tuple[float, ...]:
        """Node abscissae [m]."""
        return tuple(self.length * k / self.n_elements for k in range(self.n_elements + 1))

    def node_index(self, x: float) -> int | None:
        """The index of the node at ``x``.

        Parameters
        ----------
        x : float
            Abscissa along the tube [m].

        Returns
        -------
        int or None
            The node index (0 at x = 0) when ``x`` is a node within 1e-9 m (relative to the
            length when it exceeds 1 m), else None.
        """
        k = round(x / self.length * self.n_elements)
        return k if abs(k * self.length / self.n_elements - x) <= _NODE_TOL * max(1.0, self.length) else None

    def held_end(self, x: float) -> str | None:
        """The clamped or pinned end ``x`` sits at, where the tube's displacement is identically zero.

        Parameters
        ----------
        x : float
            Abscissa along the tube [m].

        Returns
        -------
        str or None
            ``"clamped end x = 0.0 m"`` (or pinned, or at x = length) when ``x`` is that end's node
            (within the tolerance of :meth:`node_index`) and the end is clamped or pinned; None for a
            point inside the tube or at a free end.
        """
        end = self.end_at(x)
        return f"{end[0]} end x = {end[1]!r} m" if end is not None and end[0] in ("clamped", "pinned") else None

    def end_at(self, x: float) -> tuple[str, float] | None:
        """The end ``x`` sits at, with its condition.

        Parameters
        ----------
        x : float
            Abscissa along the tube [m].

        Returns
        -------
        tuple of (str, float) or None
            ``(condition, abscissa)``, e.g. ``("pinned", 16.0)``, when ``x`` is an end's node (within the
            tolerance of :meth:`node_index`); None for a point inside the tube.
        """
        k = self.node_index(x)
        for index, end, at in ((0, self.ends[0], 0.0), (self.n_elements, self.ends[1], self.length)):
            if k == index:
                return end, at
        return None


def held_sensor_rule(name: str, tube: TubeSpec, x: float) -> str:
    """The rule refusing sensor ``name`` at ``x`` on ``tube`` when that is a clamped or pinned end."""
    return (f"sensor {name!r} is at the {tube.held_end(x)} of tube {tube.name!r}: the model's displacement there is "
            f"identically zero (a clamped or pinned end does not move), so nothing can be compared or identified; "
            f"a sensor must lie inside the tube (0 < x < {tube.length!r} m) or at a free end")


def held_load_rule(what: str, tube: TubeSpec, x: float, kind: str) -> str | None:
    """The rule refusing a load that would do nothing, else None.

    The finite-element model removes the degrees of freedom an end holds (clamped: y and θ; pinned: y),
    so a load on a removed one has a zero column: a force (on y) at a clamped or pinned end, a moment
    (on θ) at a clamped end. A moment at a pinned end turns its free rotation and acts; so does any load
    at a free end.

    Parameters
    ----------
    what : str
        How the load is named in the rule, e.g. ``"load 'F1'"``.
    tube : TubeSpec
        The tube it acts on.
    x : float
        Its abscissa [m] (on the tube).
    kind : str
        ``"force"`` or ``"moment"``.

    Returns
    -------
    str or None
        The rule, or None when the load acts.
    """
    end = tube.end_at(x)
    if end is None or end[0] == "free" or (kind == "moment" and end[0] == "pinned"):
        return None
    held = "displacement y" if kind == "force" else "rotation θ"
    where = ("inside the tube (0 < x < {L!r} m) or at a free end" if kind == "force" else
             "inside the tube (0 < x < {L!r} m), at a free end or at a pinned end (whose rotation is free)")
    return (f"{what}, a {kind}, is at the {end[0]} end x = {end[1]!r} m of tube {tube.name!r}, whose {held} the model "
            f"holds at zero: the {kind} would do nothing; a {kind} must lie " + where.format(L=tube.length))


@dataclass(frozen=True)
class LinkSpec:
    """A linear spring between two tubes' transverse displacements, or from one to the ground.

    Parameters
    ----------
    tube : str
        The tube at one end.
    x : float
        Its abscissa on ``tube`` [m]; must be a node.
    stiffness : float
        Spring stiffness [N/m], > 0.
    to_tube : str, optional
        The tube at the other end; None ties ``tube`` to the ground.
    to_x : float, optional
        The abscissa on ``to_tube`` [m] (a node); default: the same ``x``.
    """

    tube: str
    x: float
    stiffness: float
    to_tube: str | None = None
    to_x: float | None = None

    @property
    def other_x(self) -> float:
        """The abscissa of the other end [m]: ``to_x``, or ``x`` when it is not given."""
        return self.x if self.to_x is None else self.to_x


@dataclass(frozen=True)
class StopSpec:
    """A symmetric elastic stop: f = −k (|u| − g) sign(u) for |u| > g, else 0 (undamped).

    Parameters
    ----------
    tube : str
        The tube it acts on (all stops sit on the non-linear tube, subsystem A).
    x : float
        Its abscissa [m].
    gap : float
        Gap g [m], ≥ 0.
    stiffness : float
        Contact stiffness k [N/m], > 0.
    """

    tube: str
    x: float
    gap: float
    stiffness: float


@dataclass(frozen=True)
class LoadPoint:
    """A point where a load is applied.

    Parameters
    ----------
    name : str
        Unique name among the loads (the channel name of load spectra).
    tube : str
        The tube it acts on.
    x : float
        Its abscissa [m]: inside the tube, at a free end, or (a moment) at a pinned end; a force at a
        clamped or pinned end, or a moment at a clamped end, acts on a degree of freedom the end holds
        and is refused (:func:`held_load_rule`).
    kind : str
        ``"force"`` (transverse, N, on ``y``) or ``"moment"`` (N·m, on ``theta``).
    """

    name: str
    tube: str
    x: float
    kind: str = "force"


@dataclass(frozen=True)
class SensorSpec:
    """A transverse-displacement sensor (m).

    Parameters
    ----------
    name : str
        Unique name among the sensors.
    tube : str
        The tube it measures.
    x : float
        Its abscissa [m] (between nodes the Hermite shape functions interpolate): inside the tube
        or at a free end; a clamped or pinned end, whose displacement is identically zero, is
        refused.
    """

    name: str
    tube: str
    x: float


@dataclass(frozen=True)
class ReductionSpec:
    """Craig–Bampton fixed-interface modes kept per subsystem, by count and/or by cut-off frequency.

    None keeps every mode; with both a count and a cut-off, the stricter wins. Default: B keeps
    its modes below 300 Hz (3× the paper's band; J then converges to 1e-7 relative), A keeps all.
    B cannot keep *every* mode: its interface DOFs carry no mass of their own, so the reduced mass
    M_B would be singular.

    Parameters
    ----------
    b_modes : int, optional
        Fixed-interface modes of B kept (≥ 0), lowest first.
    b_cutoff_hz : float, optional
        Keep B's modes below this frequency [Hz].
    a_modes : int, optional
        Modes of A kept.
    a_cutoff_hz : float, optional
        Keep A's modes below this frequency [Hz].
    """

    b_modes: int | None = None
    b_cutoff_hz: float | None = 300.0
    a_modes: int | None = None
    a_cutoff_hz: float | None = None

    def validate(self, where: str = "reduction") -> None:
        """Check every field; refuse the first broken rule.

        Parameters
        ----------
        where : str
            How the reduction is named in messages.

        Raises
        ------
        SpecificationError
            Naming ``where.field``, the value and the rule.
        """
        for f in ("b_modes", "a_modes"):
            v = getattr(self, f)
            if v is not None and (not isinstance(v, int) or isinstance(v, bool) or v < 0):
                raise SpecificationError(f"{where}.{f}", v, "must be None or an integer >= 0")
        for f in ("b_cutoff_hz", "a_cutoff_hz"):
            v = getattr(self, f)
            if v is not None:
                positive(f"{where}.{f}", v)


@dataclass(frozen=True)
class BundleSpec:
    """A tube bundle: tubes, links, stops, load points, sensors, analysis band and reduction.

    Immutable and validated when made (sequences are stored as tuples).

    Parameters
    ----------
    name : str
        Name of the bundle.
    tubes : sequence of TubeSpec
        At least one tube, names unique.
    links : sequence of LinkSpec
        Springs between tubes or to the ground.
    stops : sequence of StopSpec
        Elastic stops, all on the non-linear tube.
    loads : sequence of LoadPoint
        Load points, names unique, none on a degree of freedom a clamped or pinned end holds.
    sensors : sequence of SensorSpec
        Displacement sensors, names unique, none at a clamped or pinned end.
    band_hz : float
        The frequency band of analysis [−band_hz, band_hz] Hz.
    nonlinear_tube : str, optional
        The tube of subsystem A (default: the tube carrying the stops).
    reduction : ReductionSpec
        Modes kept by the Craig–Bampton reduction.
    assumptions : str
        Free text shown in the documentation of built-in models.
    effects : sequence
        Load-side effects of ``tubeid.mechanics.effects`` (``Tone``, ``SensorNoise``).
    """

    name: str
    tubes: tuple[TubeSpec, ...]
    links: tuple[LinkSpec, ...] = ()
    stops: tuple[StopSpec, ...] = ()
    loads: tuple[LoadPoint, ...] = ()
    sensors: tuple[SensorSpec, ...] = ()
    band_hz: float = 100.0
    nonlinear_tube: str | None = None
    reduction: ReductionSpec = field(default_factory=ReductionSpec)
    assumptions: str = ""
    effects: tuple = ()

    def __post_init__(self) -> None:
        for f in ("tubes", "links", "stops", "loads", "sensors", "effects"):
            object.__setattr__(self, f, tuple(getattr(self, f)))
        self.validate()

    # -- validation -------------------------------------------------------------------------
    def validate(self) -> None:
        """Check every rule across the fields (called when the object is made).

        Raises
        ------
        SpecificationError
            Naming the field (``tubes[1].length``, ``stops[0].x``), the value and the rule.
        """
        if not isinstance(self.name, str) or not self.name:
            raise SpecificationError("name", self.name, "must be a non-empty string")
        if not isinstance(self.assumptions, str):
            raise SpecificationError("assumptions", self.assumptions, "must be text")
        if not self.tubes:
            raise SpecificationError("tubes", [], "a bundle needs at least one tube")
        names = [t.name for t in self.tubes]
        for i, t in enumerate(self.tubes):
            if not isinstance(t, TubeSpec):
                raise SpecificationError(f"tubes[{i}]", t, "must be a TubeSpec")
            t.validate(f"tubes[{i}]")
            if names.index(t.name) != i:
                raise SpecificationError(f"tubes[{i}].name", t.name, "tube names must be unique")
        _check_dof("tubes", Described(f"{len(self.tubes)} tubes"), sum(2 * (t.n_elements + 1) for t in self.tubes),
                   "the bundle")
        channel_count("sensors", len(self.sensors), "sensors")
        channel_count("loads", len(self.loads) + sum(1 for e in self.effects if type(e).__name__ == "Tone"),
                      "load points and tones")
        positive("band_hz", self.band_hz)
        if not isinstance(self.reduction, ReductionSpec):
            raise SpecificationError("reduction", self.reduction, "must be a ReductionSpec")
        self.reduction.validate()
        for what, items, cls in (("links", self.links, LinkSpec), ("stops", self.stops, StopSpec),
                                 ("loads", self.loads, LoadPoint), ("sensors", self.sensors, SensorSpec)):
            for i, item in enumerate(items):
                if not isinstance(item, cls):
                    raise SpecificationError(f"{what}[{i}]", item, f"must be a {cls.__name__}")

        def tube_of(where: str, name: str) -> TubeSpec:
            if name not in names:
                raise SpecificationError(where, name, f"no such tube; tubes are {names}")
            return self.tubes[names.index(name)]

        def stiffness_in_range(where: str, k: float, tubes: tuple[TubeSpec, ...], what: str) -> None:
            soft = min(tubes, key=lambda t: t.element_stiffness)
            ke = soft.element_stiffness
            if not (ke / STIFFNESS_RATIO <= k <= ke * STIFFNESS_RATIO):
                raise SpecificationError(
                    where, k, f"is {k / ke:.3g} times the element stiffness 12 EI/Le³ = {ke:.4g} N/m of tube "
                    f"{soft.name!r}: must be within 1e-8 to 1e8 times it, [{ke / STIFFNESS_RATIO:.3g}, "
                    f"{ke * STIFFNESS_RATIO:.3g}] N/m (beyond, the assembled stiffness keeps fewer than 8 of the 16 "
                    f"digits of the tube's own stiffness, below, of the {what}'s: results would be silently wrong; "
                    f"1e3 times it models a rigid {what}: on the paper's models, eigenfrequencies below 100 Hz within 0.14 % "
                    "of rigid)")

        for i, link in enumerate(self.links):
            w = f"links[{i}]"
            t = tube_of(f"{w}.tube", link.tube)
            on_tube(f"{w}.x", t, link.x)
            positive(f"{w}.stiffness", link.stiffness)
            if t.node_index(link.x) is None:
                raise SpecificationError(f"{w}.x", link.x, f"must be a node of tube {t.name!r} (nodes {list(t.nodes)})")
            if link.to_x is not None and link.to_tube is None:
                raise SpecificationError(f"{w}.to_x", link.to_x, "needs to_tube (a link to the ground has no to_x)")
            if link.to_tube is not None:
                o = tube_of(f"{w}.to_tube", link.to_tube)
                on_tube(f"{w}.to_x", o, link.other_x)
                if o.node_index(link.other_x) is None:
                    raise SpecificationError(f"{w}.to_x", link.other_x, f"must be a node of tube {o.name!r}")
                if o.name == t.name and abs(link.other_x - link.x) < _NODE_TOL:
                    raise SpecificationError(f"{w}.to_tube", link.to_tube, "a link cannot join a point to itself")
            held = t.held_end(link.x)
            if held is not None and (link.to_tube is None or o.held_end(link.other_x) is not None):
                other = "the ground" if link.to_tube is None else f"the {o.held_end(link.other_x)} of tube {o.name!r}"
                raise SpecificationError(f"{w}.x", link.x, f"the link joins the {held} of tube {t.name!r} to {other}: "
                                         "neither end moves, so it would never act; a link needs a moving end")
            stiffness_in_range(f"{w}.stiffness", link.stiffness,
                               (t,) if link.to_tube is None else (t, tube_of(f"{w}.to_tube", link.to_tube)), "link")
        for i, s in enumerate(self.stops):
            w = f"stops[{i}]"
            t = tube_of(f"{w}.tube", s.tube)
            on_tube(f"{w}.x", t, s.x)
            non_negative(f"{w}.gap", s.gap, "m")
            k = real(f"{w}.stiffness", s.stiffness, unit="N/m")
            if k <= 0:
                rule = "must be > 0 (a stop pushes back; with a zero gap a negative stiffness would make the tube unstable)"
                raise SpecificationError(f"{w}.stiffness", s.stiffness, rule)
            stiffness_in_range(f"{w}.stiffness", k, (t,), "stop")
            if t.held_end(s.x) is not None:
                raise SpecificationError(f"{w}.x", s.x, f"the stop is at the {t.held_end(s.x)} of tube {t.name!r}, "
                                         "which does not move: it would never act; a stop must lie inside the tube "
                                         f"(0 < x < {t.length!r} m) or at a free end")
        for what, items in (("loads", self.loads), ("sensors", self.sensors)):
            seen: set[str] = set()
            for i, p in enumerate(items):
                w = f"{what}[{i}]"
                if not isinstance(p.name, str) or not p.name or p.name in seen:
                    raise SpecificationError(f"{w}.name", p.name, "must be a unique non-empty string")
                seen.add(p.name)
                t = tube_of(f"{w}.tube", p.tube)
                on_tube(f"{w}.x", t, p.x)
                if what == "sensors" and t.held_end(p.x) is not None:
                    raise SpecificationError(f"{w}.x", p.x, held_sensor_rule(p.name, t, p.x))
                if what == "loads":
                    if p.kind not in LOAD_KINDS:
                        raise SpecificationError(f"{w}.kind", p.kind, f"must be one of {LOAD_KINDS}")
                    rule = held_load_rule(f"load {p.name!r}", t, p.x, p.kind)
                    if rule is not None:
                        raise SpecificationError(f"{w}.x", p.x, rule)
        from tubeid.mechanics.effects import SensorNoise, Tone

        for i, e in enumerate(self.effects):
            if not isinstance(e, (Tone, SensorNoise)):
                raise SpecificationError(f"effects[{i}]", e, "must be a tone or sensor_noise effect (use apply_effects for structural effects)")
            if isinstance(e, Tone):
                t = tube_of(f"effects[{i}].tube", e.tube)
                on_tube(f"effects[{i}].x", t, e.x)
                rule = held_load_rule("the tone", t, e.x, "force")
                if rule is not None:
                    raise SpecificationError(f"effects[{i}].x", e.x, rule)
        a = self.a_tube
        if a is not None:
            tube_of("nonlinear_tube", a)
            for i, s in enumerate(self.stops):
                if s.tube != a:
                    raise SpecificationError(f"stops[{i}].tube", s.tube, f"all stops must be on the non-linear tube {a!r}")

    # -- derived ------------------------------------------------------------------------------
    @property
    def a_tube(self) -> str | None:
        """Name of the non-linear tube (subsystem A), or None for a purely linear bundle."""
        if self.nonlinear_tube is not None:
            return self.nonlinear_tube
        return self.stops[0].tube if self.stops else None

    def tube(self, name: str) -> TubeSpec:
        """The tube called ``name``.

        Parameters
        ----------
        name : str
            A tube name.

        Returns
        -------
        TubeSpec
            The tube; ``SpecificationError`` when there is none of that name.
        """
        for t in self.tubes:
            if t.name == name:
                return t
        raise SpecificationError("tube", name, f"no such tube; tubes are {[t.name for t in self.tubes]}")

    def replace(self, **changes: Any) -> "BundleSpec":
        """A new, validated specification with some fields changed.

        Parameters
        ----------
        **changes
            Field names and their new values.

        Returns
        -------
        BundleSpec
            The new specification (this one is unchanged).
        """
        return dataclasses.replace(self, **changes)


# -- dictionaries and files ----------------------------------------------------------------------
_CLASSES = {"tubes": TubeSpec, "links": LinkSpec, "stops": StopSpec, "loads": LoadPoint, "sensors": SensorSpec}


def _build(cls, data: Any, where: str):
    if not isinstance(data, Mapping):
        raise SpecificationError(where, data, "must be a table/mapping")
    known = {f.name for f in dataclasses.fields(cls)}
    for key in data:
        if key not in known:
            raise SpecificationError(f"{where}.{key}", data[key], f"unknown field; known fields are {sorted(known)}")
    required = {f.name for f in dataclasses.fields(cls) if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING}
    for key in sorted(required - set(data)):
        raise SpecificationError(f"{where}.{key}", None, "is required")
    kwargs = dict(data)
    if "ends" in kwargs:
        if not isinstance(kwargs["ends"], (list, tuple)):
            raise SpecificationError(f"{where}.ends", kwargs["ends"], f"must be a list of two of {END_CONDITIONS}")
        kwargs["ends"] = tuple(kwargs["ends"])
    return cls(**kwargs)


def spec_from_dict(data: Mapping[str, Any]) -> BundleSpec:
    """Build and validate a :class:`BundleSpec` from plain data (as read from YAML or TOML).

    Parameters
    ----------
    data : mapping
        The fields of ``BundleSpec``, with lists of mappings for tubes, links, stops, loads,
        sensors and effects; unknown fields are refused.

    Returns
    -------
    BundleSpec
        The validated specification.
    """
    if not isinstance(data, Mapping):
        raise SpecificationError("specification", type(data).__name__, "must be a mapping at top level")
    data = dict(data)
    known = {f.name for f in dataclasses.fields(BundleSpec)}
    for key in data:
        if key not in known:
            raise SpecificationError(key, data[key], f"unknown field; known fields are {sorted(known)}")
    for key, cls in _CLASSES.items():
        items = data.get(key) or []  # an empty YAML list reads as None
        if not isinstance(items, (list, tuple)):
            raise SpecificationError(key, items, "must be a list")
        data[key] = tuple(_build(cls, item, f"{key}[{i}]") for i, item in enumerate(items))
    if "reduction" in data:
        data["reduction"] = _build(ReductionSpec, data["reduction"], "reduction")
    if "effects" in data:
        from tubeid.mechanics.effects import effect_from_dict

        items = data["effects"] or []
        if not isinstance(items, (list, tuple)):
            raise SpecificationError("effects", items, "must be a list")
        data["effects"] = tuple(effect_from_dict(e, f"effects[{i}]") for i, e in enumerate(items))
    if "name" not in data:
        raise SpecificationError("name", None, "is required")
    return BundleSpec(**data)


def spec_to_dict(spec: BundleSpec) -> dict[str, Any]:
    """Plain-data form of a specification (round-trips through :func:`spec_from_dict`).

    Parameters
    ----------
    spec : BundleSpec
        The specification.

    Returns
    -------
    dict
        Lists and plain values only (JSON-, YAML- and TOML-ready).
    """
    from tubeid.mechanics.effects import effect_to_dict

    out = dataclasses.asdict(spec)
    out["effects"] = [effect_to_dict(e) for e in spec.effects]
    for t in out["tubes"]:
        t["ends"] = list(t["ends"])
    for key in _CLASSES:
        out[key] = list(out[key])
    return out


_MAX_DEPTH = 32  # nesting levels of a YAML specification (it needs 4)


@functools.cache
def _spec_loader():
    """PyYAML's safe loader without aliases, reading ``7.5e8`` as a number (see the module docstring)."""
    import yaml

    class SpecLoader(yaml.SafeLoader):
        depth = 0

        def compose_node(self, parent, index):
            if self.check_event(yaml.AliasEvent):
                event = self.peek_event()
                raise yaml.composer.ComposerError(
                    None, None, f"alias *{event.anchor} refused: aliases are not allowed in specifications "
                    f"(write the value out)", event.start_mark)
            if self.depth >= _MAX_DEPTH:
                raise yaml.composer.ComposerError(
                    None, None, f"nested more than {_MAX_DEPTH} levels deep", self.peek_event().start_mark)
            self.depth += 1
            try:
                return super().compose_node(parent, index)
            finally:
                self.depth -= 1

        def construct_mapping(self, node, deep=False):
            seen = set()
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=True)
                try:
                    duplicate = key in seen
                    seen.add(key)
                except TypeError:  # an unhashable key: PyYAML refuses it itself
                    continue
                if duplicate:
                    raise yaml.constructor.ConstructorError(
                        "while reading a mapping", node.start_mark,
                        f"key {key!r} given twice (the last would silently win)", key_node.start_mark)
            return super().construct_mapping(node, deep=deep)

    # YAML 1.2 core-schema floats with an exponent that YAML 1.1 leaves as text: 1e6, 7.5e8, 2.E-3.
    SpecLoader.add_implicit_resolver(
        "tag:yaml.org,2002:float",
        re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9][0-9_]*)[eE][-+]?[0-9]+$"),
        list("-+0123456789."))
    return SpecLoader


def _read_yaml(text: str, source: str):
    import yaml

    stream = io.StringIO(text)
    stream.name = source  # named in PyYAML's marks
    try:
        return yaml.load(stream, Loader=_spec_loader())  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        raise SpecificationError("specification file", source, f"is not valid YAML ({_yaml_problem(exc)})") from None
    except (ValueError, RecursionError) as exc:
        _unreadable(source, exc)


def _yaml_problem(exc) -> str:
    """PyYAML's error in one line: ``line L, column C: PROBLEM (CONTEXT at line L, column C)``.

    PyYAML's own message spreads the problem, its context and their positions (with the source line
    and a caret) over several lines; the file is named by the message this goes into."""
    def at(mark):
        return f"line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""

    def one_line(text):
        return " ".join(str(text).split())

    problem, context = getattr(exc, "problem", None), getattr(exc, "context", None)
    p_mark, c_mark = getattr(exc, "problem_mark", None), getattr(exc, "context_mark", None)
    if problem is None and context is None:
        return one_line(exc)
    out = ": ".join(filter(None, (at(p_mark), one_line(problem or ""))))
    if context:
        where = at(c_mark) if c_mark is not None and (p_mark is None or (c_mark.line, c_mark.column) !=
                                                         (p_mark.line, p_mark.column)) else ""
        out += f" ({one_line(context)}{' at ' + where if where else ''})" if out else one_line(context)
    note = getattr(exc, "note", None)
    return out + (f"; {one_line(note)}" if note else "")


def _unreadable(source: str, exc: Exception):
    """Parsers' own limits as refusals: an integer of more than 4300 digits, nesting beyond the stack."""
    what = "is nested too deeply" if isinstance(exc, RecursionError) else f"cannot be read ({exc})"
    raise SpecificationError("specification file", source, what) from None


def _read_toml(text: str, source: str):
    import tomllib

    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SpecificationError("specification file", source, f"is not valid TOML ({exc})") from None
    except (ValueError, RecursionError) as exc:
        _unreadable(source, exc)


def load_spec(path: str | pathlib.Path) -> BundleSpec:
    """Read a bundle specification from a ``.yaml``/``.yml`` or ``.toml`` file.

    Parameters
    ----------
    path : str or path-like
        The file; its suffix chooses the format. YAML: safe loading without aliases, ``7.5e8`` read
        as a number (module docstring). At most ``tubeid.io.max-specification-bytes``, UTF-8.

    Returns
    -------
    BundleSpec
        The validated specification. Any bad input raises
        :class:`~tubeid.errors.SpecificationError` naming the file or field, the value and the rule.
    """
    p = pathlib.Path(path)
    source = str(p)
    if p.suffix not in (".yaml", ".yml", ".toml"):
        raise SpecificationError("specification file", source, "must end in .yaml, .yml or .toml")
    if not p.is_file():
        raise SpecificationError("specification file", source, "does not exist or is not a file")
    size, bound = p.stat().st_size, limit("max-specification-bytes")
    if size > bound:
        raise SpecificationError("specification file", source,
                                 f"is {byte_size(size)}, larger than {byte_size(bound)} "
                                 f"(configuration tubeid.io.max-specification-bytes)")
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise SpecificationError("specification file", source, f"is not UTF-8 text ({exc})") from None
    data = _read_toml(text, source) if p.suffix == ".toml" else _read_yaml(text, source)
    return spec_from_dict(data)
