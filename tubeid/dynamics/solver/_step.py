"""The step rule: the highest frequency of a model with its stops and each method's limits on dt.

f_max is the highest undamped eigenfrequency with every stop closed (K + Σ k b bᵀ, M): adding
positive semi-definite stop stiffnesses raises every eigenvalue, so f_max bounds the frequencies
of every regime. A method's :class:`StepRule` states its limits as dt·f_max: the default step is
the largest step dividing both the load sampling and the output sampling within ``default``; a
user step above ``warn`` is accepted with a warning, above ``refuse`` refused.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike

from tubeid._validation import limit, positive
from tubeid.dynamics.solver._base import Stop
from tubeid.dynamics.solver._checks import check_definite, check_stops, matrix_stack
from tubeid.errors import Described, SpecificationError

__all__ = ["StepRule", "EXACT_RULE", "SYMPLECTIC_EULER_RULE", "highest_frequency", "step_for", "check_step",
           "refuse_substeps", "SUBSTEP_SECONDS"]

_TWO_PI = 2.0 * math.pi
_PAPER_NOTE = (" Note: the paper's 3 ms is the output sampling of the response, not an integration step "
               "(MODEL.md section 3.7).")


@dataclass(frozen=True)
class StepRule:
    """Limits of a method's step as dt·f_max (dimensionless; f_max in Hz, dt in s).

    default: the default step satisfies dt·f_max <= default. warn: a user step with dt·f_max >
    warn is accepted with ``warn_message``. refuse: a user step with dt·f_max > refuse (>= when
    ``refuse_at_limit``) is refused with ``refuse_message``. The messages are formatted with dt,
    f_max, w_dt = 2π f_max dt, refuse_dt = refuse/f_max and warn_dt = warn/f_max.
    """

    default: float
    warn: float
    refuse: float
    refuse_at_limit: bool
    refuse_message: str
    warn_message: str


#: Exact method: 4 points per shortest period by default (the Hermite pre-check's error bound
#: (w h)⁴/384 is then 1.6 % of the highest mode's amplitude, its margin ``_regimes.MARGIN_SAFETY``
#: times that); beyond 1/(2 f_max) a whole contact oscillation can fall inside one step unseen;
#: beyond 1/(3 f_max) the bound exceeds 5 %.
EXACT_RULE = StepRule(
    default=1 / 4, warn=1 / 3, refuse=1 / 2, refuse_at_limit=False,
    refuse_message=("exact method needs dt <= 1/(2 f_max) = {refuse_dt:.4g} s (f_max = {f_max:.4g} Hz, highest "
                    "frequency with the stops closed): a coarser step can hide whole contact oscillations."),
    warn_message=("dt = {dt:.4g} s exceeds 1/(3 f_max) = {warn_dt:.4g} s (f_max = {f_max:.4g} Hz): grazing contacts "
                  "may be missed (rule: dt <= 1/(3 f_max), default 1/(4 f_max))"),
)
#: Symplectic Euler: stable for w_max dt < 2; frequency error of the highest mode (w dt)²/24 above
#: ~1 % beyond w_max dt = 0.5; default w_max dt <= 0.25.
SYMPLECTIC_EULER_RULE = StepRule(
    default=0.25 / _TWO_PI, warn=0.5 / _TWO_PI, refuse=2.0 / _TWO_PI, refuse_at_limit=True,
    refuse_message=("symplectic Euler is unstable for dt >= 2/w_max = {refuse_dt:.4g} s (f_max = {f_max:.4g} Hz "
                    "with the stops closed)."),
    warn_message=("dt = {dt:.4g} s gives w_max dt = {w_dt:.3g} > 0.5: symplectic Euler frequency error of the "
                  "highest mode above 1 % (rule: w_max dt <= 0.5, default 0.25)"),
)


def highest_frequency(M: ArrayLike, K: ArrayLike, stops: Sequence[Stop] = ()) -> float | np.ndarray:
    """Highest undamped eigenfrequency (Hz) with every stop closed.

    Parameters
    ----------
    M, K : array (N, N) or (R, N, N)
        Mass and stiffness in the coordinates q (SI units): real, finite, symmetric (relative
        asymmetry up to 1e-10 symmetrised), positive definite. Stacks are realisation-wise; their
        R must be equal, or one of them a single matrix (shared).
    stops : sequence of Stop
        Stops whose b has length N and whose labels are distinct; their stiffness k b bᵀ is added
        to K whatever their gap.

    Returns
    -------
    float or numpy.ndarray
        f_max (Hz): a float when M and K are both (N, N), else an array (R,).

    Raises
    ------
    tubeid.errors.SpecificationError
        Naming the field: M or K not (N, N) or (R, N, N) alike, not finite, not symmetric or not
        positive definite (as ``simulate`` asks); realisation axes that do not match; a stop that
        is not a Stop, whose b is not of length N, or whose label repeats another's.
    """
    Ms = matrix_stack("M", M)
    Ks = matrix_stack("K", K, Ms.shape[1])
    check_definite("M", Ms, True)  # the generalized eigenproblem needs M > 0; K > 0 as simulate asks
    check_definite("K", Ks, True)
    stops = check_stops(stops, Ms.shape[1])
    R = max(len(Ms), len(Ks))
    if len(Ms) not in (1, R) or len(Ks) not in (1, R):
        raise SpecificationError("K.shape", Ks.shape, f"realisation axis must match M ({Ms.shape[0]})")
    closed = sum((s.stiffness * np.outer(s.vector, s.vector) for s in stops), np.zeros(Ms.shape[1:]))
    out = np.empty(R)
    for r in range(R):
        w2 = scipy.linalg.eigh(Ks[r % len(Ks)] + closed, Ms[r % len(Ms)], eigvals_only=True)
        out[r] = math.sqrt(max(w2[-1], 0.0)) / _TWO_PI
    if np.ndim(M) == 2 and np.ndim(K) == 2:
        return float(out[0])
    return out


def check_step(rule: StepRule, dt: float, f_max: float, field_name: str = "dt") -> None:
    """Refuse (SpecificationError) or warn about a user step ``dt`` (s) for highest frequency ``f_max`` (Hz)."""
    x = dt * f_max
    fields = dict(dt=dt, f_max=f_max, w_dt=_TWO_PI * x, refuse_dt=rule.refuse / f_max, warn_dt=rule.warn / f_max)
    if x > rule.refuse or (rule.refuse_at_limit and x >= rule.refuse):
        note = _PAPER_NOTE if dt >= 2.9e-3 else ""
        raise SpecificationError(field_name, dt, rule.refuse_message.format(**fields) + note)
    if x > rule.warn:
        warnings.warn(rule.warn_message.format(**fields), stacklevel=4)


def _frac(x: float) -> Fraction:
    return Fraction(x).limit_denominator(10**12)


def _divides(dt: float, big: float) -> bool:
    """True if ``big`` is an integer multiple of ``dt`` (relative tolerance 1e-9)."""
    r = big / dt
    return abs(r - round(r)) <= 1e-9 * max(r, 1.0) and round(r) >= 1


def step_for(rule: StepRule, f_max, dt_load, output_dt, dt=None) -> float:
    """Integration step (s) under ``rule``: the given ``dt`` (checked: it must divide dt_load and
    output_dt; refused or warned by the rule), or the largest step dividing both within the
    rule's default."""
    f_max = positive("f_max", f_max, "Hz")
    dt_load = positive("dt_load", dt_load, "s")
    output_dt = positive("output_dt", output_dt, "s")
    if dt is not None:
        dt = positive("dt", dt, "s")
        check_step(rule, dt, f_max)
        for nm, big in (("dt_load", dt_load), ("output_dt", output_dt)):
            if not _divides(dt, big):
                raise SpecificationError("dt", dt, f"{nm} = {big} s must be an integer multiple of dt")
        return dt
    a, b = _frac(dt_load), _frac(output_dt)
    base = Fraction(math.gcd(a.numerator * b.denominator, b.numerator * a.denominator), a.denominator * b.denominator)
    base_f = float(base)
    if not (_divides(base_f, dt_load) and _divides(base_f, output_dt)) or base_f < 1e-9 * max(dt_load, output_dt):
        raise SpecificationError("output_dt", output_dt, f"must be commensurate with dt_load = {dt_load} s")
    n = max(1, math.ceil(base_f * f_max / rule.default - 1e-9))
    return base_f / n


#: Order of magnitude of one sub-step of the exact method [s] (machines and models move it by 2× either
#: way: ``tubeid bench transient --json``'s ``seconds_fast_path`` over its steps). Only used to state
#: roughly what a refused run would have cost.
SUBSTEP_SECONDS = 18e-9


def refuse_substeps(rule: StepRule, method: str, h: float, f_max: float, duration: float, M: np.ndarray,
                    K: np.ndarray, stops: Sequence[Stop], duration_field: str = "duration", duration_value=None) -> int:
    """The sub-steps ceil(duration / h) of one realisation; refused beyond ``tubeid.io.max-substeps``.

    The refusal names the cause: the stop whose closed stiffness raises f_max (``stops[i].stiffness``,
    with the stiffness that keeps within the limit) when the model with its stops open would keep
    within it, else the duration (``duration_field``, with the duration that keeps within it at this
    f_max). It states f_max with the stops closed and open, the step, the count and the time they would
    take, roughly, at :data:`SUBSTEP_SECONDS` each.

    Parameters
    ----------
    rule : StepRule
        The method's step rule (its ``default`` limit of dt·f_max estimates the allowed f_max).
    method : str
        The method's name, for the message.
    h : float
        The integration step [s] (chosen or given).
    f_max : float
        The highest frequency with every stop closed [Hz].
    duration : float
        The integrated time of one realisation [s].
    M, K : numpy.ndarray (N, N)
        Mass and the structure's stiffness without any stop.
    stops : sequence of Stop
        Every stop (those with a zero gap too), indexed as the caller's ``stops``.
    duration_field, duration_value : str, object
        How the caller's duration is named and shown (default: ``duration`` and its value).
    """
    n = math.ceil(duration / h - 1e-9)
    bound = limit("max-substeps")
    if n <= bound:
        return n
    f_open = highest_frequency(M, K) if stops else f_max
    cost = (f"with the stops closed the highest frequency is f_max = {f_max:.4g} Hz (open: {f_open:.4g} Hz), and the "
            f"{method} method's step rule (dt·f_max <= {rule.default:.3g}) takes dt = {h:.3g} s: {n:.3g} sub-steps "
            f"per realisation for {duration:g} s, more than {bound:.3g} (configuration tubeid.io.max-substeps; at "
            f"roughly {SUBSTEP_SECONDS * 1e9:g} ns per sub-step, of the order of {n * SUBSTEP_SECONDS:.1g} s per "
            f"realisation)")
    if stops and math.ceil(duration * f_open / rule.default) <= bound:
        # a closed stop adds its stiffness on u = bᵀq: the highest eigenvalue grows as k bᵀM⁻¹b
        f_allowed = bound * rule.default / duration  # the f_max whose default step gives the limit's count
        mobility = [float(s.vector @ np.linalg.solve(M, s.vector)) for s in stops]
        i = max(range(len(stops)), key=lambda j: stops[j].stiffness * mobility[j])
        k_allowed = ((_TWO_PI * f_allowed) ** 2 - (_TWO_PI * f_open) ** 2) / mobility[i]
        raise SpecificationError(f"stops[{i}].stiffness", stops[i].stiffness,
                                 f"{cost}; a stiffness of at most about {k_allowed:.2g} N/m keeps within the limit")
    raise SpecificationError(duration_field, duration if duration_value is None else duration_value,
                             f"{cost}; at most about {h * bound:.3g} s keeps within the limit at this f_max")
