"""Forward selection of effects: the error a candidate is judged by, and the choice.

**The error** of a model (the declared one with some effects, at some r) is how far the record's
log10 PSD lies from the model's prediction — the mean model's PSD over ``fit_realisations``
records — in units of the declared stochastic model's own scatter per bin and sensor σ (the band
before any effect):

    error = mean over sensors and 0 < f < f_Nyquist of ((log10 S_data − log10 S̄_model − o) / σ)²

with o the σ⁻²-weighted mean log offset on the *fitting* blocks (the load level's residual; zero
once r is re-fitted). On the fitting blocks it chooses a candidate's parameters; on the held-out
blocks it judges the candidate: the held-out error. Where the declared model is uncertain (σ
large, e.g. near resonances that the random stiffness of B moves) a misfit weighs little; a narrow
line in a quiet part of the spectrum weighs a lot.

**The choice** (:func:`choose`): among the candidates fitted at a step, the one with the lowest
*penalised* held-out error relative to the current model's, error / current × (1 − penalty)^−k for
an effect with k parameters, if that lies below 1; else no effect is added. The best one — not the
first that improves. When every candidate is judged by the same error (the spectrum's), this is
the lowest penalised error below the current one; when the declared model is simplified, each
candidate is judged by its own feature's error and compared with the current model's in that
feature (:mod:`tubeid.diagnose.stages`), so the ratio puts them on one scale.

**Near ties** (:func:`near_ties`): a candidate that also pays its penalty, with a ratio within
``tie`` (relative) of the chosen one's, was as good at that step. Forward selection must still pick
one first, and fitting it can pull the record back inside the declared model's band (B's random
stiffness), so the test stops the loop with the other one missing (measured: an added mass and a
tone within a few % of each other; the README's "Five more seeds"). The loop therefore offers each
such runner-up once more, alone, at the first step the test calls the record explained; it is
added only if it pays its penalty there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tubeid.diagnose._spectra import analysis_bins, log10

__all__ = ["Scored", "level_offset", "prediction_error", "choose", "near_ties", "line_minimum", "line_extension",
           "keeps_moved_point", "refit_choice"]


@dataclass(frozen=True)
class Scored:
    """A fitted candidate at one step: its ``name``, parameter count ``k``, its best trial's
    fitting-block error ``fit_error`` and its held-out error ``held_out_error``, and the current
    model's held-out error in the same terms ``current`` (None: the one :func:`choose` is given)."""

    name: str
    k: int
    fit_error: float
    held_out_error: float
    current: float | None = None

    def penalised(self, penalty: float) -> float:
        """held_out_error × (1 − penalty)^−k."""
        return self.held_out_error / (1.0 - penalty) ** self.k


def level_offset(measured, model, sigma, f) -> float:
    """σ⁻²-weighted mean of log10(measured / model) over the analysis bins [decades]."""
    sel = analysis_bins(f)
    w = 1.0 / np.asarray(sigma)[sel] ** 2
    return float(np.sum(w * (log10(measured) - log10(model))[sel]) / np.sum(w))


def prediction_error(measured, model, sigma, f, offset: float = 0.0) -> float:
    """The error of the module docstring (dimensionless, ≈ 1 for a record within the scatter)."""
    sel = analysis_bins(f)
    z = (log10(measured) - log10(model) - offset)[sel] / np.asarray(sigma)[sel]
    return float(np.mean(z**2))


def choose(scored, current: float, penalty: float) -> Scored | None:
    """The candidate with the lowest penalised held-out error relative to the current model's (its
    own ``current``, else ``current``: the held-out error of the model so far) if that ratio is
    below 1, else None. Ties go to the fewer parameters, then the catalog order of ``scored``."""
    best = None
    for s in scored:
        now = current if s.current is None else s.current
        if not (np.isfinite(s.held_out_error) and np.isfinite(now) and now > 0):
            continue
        key = (s.penalised(penalty) / now, s.k)
        if best is None or key < best[0]:
            best = (key, s)
    if best is None or not best[0][0] < 1.0:
        return None
    return best[1]


def near_ties(candidates, chosen: str, tie: float) -> dict[str, tuple[float, float]]:
    """The runner-ups near-tied with ``chosen``: {name: (its ratio, the chosen one's)}.

    ``candidates``: dicts with ``name``, ``penalised`` and ``current`` (one step's, as
    :func:`tubeid.diagnose.stages.selection` lists them). A runner-up is near-tied when its ratio
    penalised / current is below 1 and at most the chosen one's × (1 + ``tie``).
    """
    ratios = {c["name"]: c["penalised"] / c["current"] for c in candidates
              if np.isfinite(c["penalised"]) and np.isfinite(c["current"]) and c["current"] > 0}
    if not chosen or chosen not in ratios or tie <= 0:
        return {}
    top = ratios[chosen]
    return {n: (r, top) for n, r in ratios.items() if n != chosen and r < 1.0 and r <= top * (1.0 + tie)}


def line_minimum(values, errors, log: bool) -> float:
    """The minimiser of errors along one line of a trial grid: the vertex of the parabola through
    the discrete minimum and its neighbours (in log10 of the values when ``log``), kept between
    them; the grid value itself at an end of the line."""
    x = np.asarray(values, dtype=float)
    y = np.asarray(errors, dtype=float)
    order = np.argsort(x)
    x, y = x[order], y[order]
    i = int(np.nanargmin(y))
    if i == 0 or i == x.size - 1:
        return float(x[i])
    u = np.log10(x[i - 1: i + 2]) if log else x[i - 1: i + 2]
    y0, y1, y2 = y[i - 1: i + 2]
    den = (u[1] - u[0]) * (y1 - y2) - (u[1] - u[2]) * (y1 - y0)
    if den == 0 or not np.isfinite(den):
        return float(x[i])
    num = (u[1] - u[0]) ** 2 * (y1 - y2) - (u[1] - u[2]) ** 2 * (y1 - y0)
    uv = float(np.clip(u[1] - 0.5 * num / den, u[0], u[2]))
    return float(10.0**uv) if log else uv


def line_extension(values, errors) -> float | None:
    """One more step of a line of positive scale values (log-spaced) whose discrete minimum is at an
    end: the end value moved away from the line by the ratio of its last two values; None when the
    minimum is interior or any of the line's errors is NaN (a failed trial: the line says nothing
    reliable about its end).

    A line of 3 trials bounds a parameter's move to one spacing a step: a parameter fitted far from
    its first estimate (added mass on another tube, sized 0.21 for 0.3 by a line of ×1.4 that ends
    there) needs the line extended where its best is at the edge."""
    x = np.asarray(values, dtype=float)
    y = np.asarray(errors, dtype=float)
    order = np.argsort(x)
    x, y = x[order], y[order]
    if not np.all(np.isfinite(y)):
        return None
    i = int(np.argmin(y))
    if i == 0:
        return float(x[0] ** 2 / x[1])
    if i == x.size - 1:
        return float(x[-1] ** 2 / x[-2])
    return None


def refit_choice(moved: float, best_evaluated: float, extended: float | None = None) -> str:
    """Which point a joint re-fit keeps, from fitting-block errors: ``"extended"`` (the moved point
    with its edge lines one step further, :func:`line_extension`) if it is better than both others,
    else ``"moved"`` if :func:`keeps_moved_point`, else ``"best"`` (the best point the lines
    evaluated). NaN errors never win (a NaN best evaluated error counts as +inf)."""
    if not np.isfinite(best_evaluated):
        best_evaluated = np.inf
    keep = keeps_moved_point(moved, best_evaluated)
    base = moved if keep else best_evaluated
    if extended is not None and extended < base:
        return "extended"
    return "moved" if keep else "best"


def keeps_moved_point(moved_fit_error: float, best_evaluated_fit_error: float) -> bool:
    """The joint re-fit's safeguard: keep the point every line moved to only if its fitting-block
    error is no worse than the best point the lines evaluated (a NaN moved error is not kept)."""
    return bool(moved_fit_error <= best_evaluated_fit_error)
