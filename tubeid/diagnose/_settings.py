"""The settings of a diagnosis: one immutable, validated value (its JSON is the diagnosis's identity)."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from typing import Any

from tubeid import _validation as v
from tubeid.errors import SpecificationError

__all__ = ["DiagnoseSettings", "LOAD_MODELS", "MAX_EFFECTS", "MODEL_FORM_CHOICES"]

#: Identification load models: ``distributed`` — the declared model's force points on the
#: non-linear tube with the paper's coherence exp(−|Δx|/λ) (λ = ``correlation_length``), one
#: parameter r = S_ii [N²/Hz]; ``force_and_moment`` — the paper's §3.4 model T, M at ``load_x``,
#: r = (r1 [N²/Hz], r2 [(N·m)²/Hz]).
LOAD_MODELS = ("distributed", "force_and_moment")

#: What the declared model is taken to be (``model_form``): ``exact`` — the structure up to its random
#: subsystem B (the test combines the statistics that read the spectrum's shape); ``simplified`` —
#: a simplification of the structure (the test and the selection read only the features a
#: simplified model is trusted for; :mod:`tubeid.diagnose._detection`).
MODEL_FORM_CHOICES = ("exact", "simplified")

#: R of the simplified model form's test when ``realisations`` is not given: 159, because the
#: ``profile`` statistic's covariance (50 bands of 2 Hz) and each statistic's tail are estimated from the
#: R + 1 samples (reference records with added mass × 1.3: detected in 8 of 10 at 159, 5 of the
#: same 10 at 79; README).
SIMPLIFIED_REALISATIONS = 159

#: Probe realisations (the ``profile`` statistic's direction) when ``probe_realisations`` is not
#: given: with the simplified form the direction is taken against B's scatter around a mis-shaped
#: mean, 60; with the exact form, 20 (README: what fewer gave).
SIMPLIFIED_PROBE_REALISATIONS = 60
EXACT_PROBE_REALISATIONS = 20

#: The most effects one diagnosis selects (the pipeline holds this many selection steps).
MAX_EFFECTS = 3

_TUPLE_FIELDS = ("r0", "delta_f_grid", "candidates")


@dataclass(frozen=True)
class DiagnoseSettings:
    """Sizes and rules of a diagnosis (seconds, Hz, counts, decades). Every field is checked here,
    before any computation; a bad value is refused naming the field, the value and the rule.

    Parameters
    ----------
    blocks : int
        The record is cut into this many equal time blocks; the even ones fit, the odd ones are
        held out (≥ 2).
    segment_seconds : float
        Welch segment [s] (Hann, 50 % overlap) of the spectra the errors and the exact test read.
    fine_segment_seconds : float
        The longer Welch segment [s] (finer resolution) of the line and resonance statistics, at
        least ``segment_seconds``; on short records at most half a block (said in the report).
    realisations : int or None
        R, the records of the declared stochastic model shaped like the held-out set; the test is
        exact at level ⌊α(R+1)⌋/(R+1) (R = 39, α = 0.05: exactly 5 %). ``None``: 39 for the exact
        model form, :data:`SIMPLIFIED_REALISATIONS` for the simplified one (its six statistics
        have heavy tails under a strongly random B; 1/(R+1) resolves the smallest p-value).
    probe_realisations : int or None
        Realisations of the declared model (with the effects chosen so far) plus the added-mass
        catalog entry's probe, simulated beside the R of each test: the direction of the
        ``profile`` statistic (0: that statistic left out). ``None``: :data:`EXACT_PROBE_REALISATIONS`
        with the exact model form, :data:`SIMPLIFIED_PROBE_REALISATIONS` with the simplified one.
    false_alarm : float
        α, the stated false-alarm rate of the test, in (0, 0.5): the record's first test (is
        anything missing?).
    continuation_alarm : float or None
        The rate of the tests after each step (is anything *still* missing?), in (0, α]. ``None``:
        α / (``max_effects`` − 1), so that on a record the chosen effects explain, the
        ``max_effects`` − 1 tests that could continue the loop raise an alarm — and so a further,
        spurious effect — with probability at most α in all (Bonferroni); without it each of them
        would, at α. The test after the last step, which cannot continue the loop, is at the same
        rate (``explained_after``). The near-tie rule (``tie``) adds a runner-up without an alarm;
        the bound is not about it. Must be at least 1/(R+1), the smallest p-value, when
        ``max_effects`` ≥ 1.
    band_width_hz : float
        Width [Hz] of the bands of the goodness-of-fit of log band energies (chunks of the
        sharpness and resonance statistics: 4 × this).
    level : float
        Probability of the band drawn in residual.png (display only).
    model_form : str or None
        What the declared model is taken to be (:data:`MODEL_FORM_CHOICES`); ``None`` takes
        ``simplified`` when δ is identified against a reference model (``delta_reference``: the
        declared model is then a simplification of it), else ``exact``.
    delta : float
        Dispersion δ of subsystem B's stiffness, given.
    delta_reference : str or None
        A model (built-in name or specification file) against which δ is identified instead, by
        the paper's maximum likelihood of J.
    delta_realisations : int
        Monte Carlo records of J per δ of that identification.
    load : str
        The identification load model (:data:`LOAD_MODELS`).
    correlation_length : float
        λ [m] of the distributed load's coherence exp(−|Δx|/λ).
    load_x : float
        Position [m] of the force-and-moment load.
    r0 : tuple of float or None
        Start of the trial method of r (default: the paper's levels).
    r_points, r_step : int, float
        Points per component and spacing [decades] of the coarse grid of r.
    r_fine_points, r_fine_span : int, float
        Points per component and half span [decades] of the fine grid of r.
    load_dispersion : float or None
        δ_F given; ``None`` identifies it by maximum likelihood of J_s when the record has at
        least ``delta_f_min_blocks`` fitting blocks (one J_s observation each), else the band uses
        ``delta_f_fallback`` and says so.
    delta_f_min_blocks : int
        Fewest fitting blocks that identify δ_F.
    delta_f_grid : tuple of float or None
        Grid of δ_F (``None``: log-spaced up to 0.9 δ_max(m)).
    delta_f_realisations : int
        Monte Carlo records per δ_F.
    delta_f_fallback : float
        The δ_F of the band when δ_F is not identified.
    n_bootstrap : int
        Bootstrap replicates of the likelihoods.
    max_effects : int
        Effects selected at most (0: detection only; at most :data:`MAX_EFFECTS`).
    candidates : tuple of str or None
        Catalog names considered (``None``: the whole catalog).
    fit_realisations : int
        Records of the mean model per trial.
    grid_points : int
        Points per parameter of a trial grid.
    penalty : float
        An effect with k parameters must bring the held-out error below the current one × (1 −
        penalty)^k.
    tie : float
        Near-tie margin (0: off). A candidate whose penalised ratio lies below 1 and within ``tie``
        (relative) of the chosen one's at the same step was as good: the data cannot order the
        two, and fitting the first can hide the second from the test. Such a runner-up, never
        chosen, is fitted once more (alone) at the first step the test calls the record explained,
        and added only if it pays its penalty there.
    discard : float
        Transient dropped from every simulated record [s].
    dt_load_max : float
        Bound on the load's sampling step [s].
    seed : int
        Seed of all random streams (common random numbers across trials).
    max_frequency_hz : float or None
        Upper end [Hz] of every spectrum the diagnosis compares, the record's and the realisations'
        alike (the test's statistics, the errors, the fits). ``None``: the record's Nyquist
        frequency. Set it below the passband edge of the data-acquisition system's anti-alias
        filter: the filter attenuates the record's top bins, which the model (sampled without a
        filter) does not, and every statistic reading them sees a departure. Must lie above the
        declared model's band and below the record's Nyquist frequency (checked against the record).
        The time statistics (RMS, skewness, kurtosis) still read the samples as recorded.
    """

    blocks: int = 4
    segment_seconds: float = 2.0
    fine_segment_seconds: float = 8.0
    realisations: int | None = None
    probe_realisations: int | None = None
    false_alarm: float = 0.05
    continuation_alarm: float | None = None
    band_width_hz: float = 5.0
    level: float = 0.95
    model_form: str | None = None
    delta: float = 0.2
    delta_reference: str | None = None
    delta_realisations: int = 200
    load: str = "distributed"
    correlation_length: float = 4.0
    load_x: float = 8.0
    r0: tuple[float, ...] | None = None
    r_points: int = 3
    r_step: float = 0.5
    r_fine_points: int = 5
    r_fine_span: float = 0.25
    load_dispersion: float | None = None
    delta_f_min_blocks: int = 8
    delta_f_grid: tuple[float, ...] | None = None
    delta_f_realisations: int = 30
    delta_f_fallback: float = 0.04
    n_bootstrap: int = 200
    max_effects: int = 3
    candidates: tuple[str, ...] | None = None
    fit_realisations: int = 2
    grid_points: int = 4
    penalty: float = 0.05
    tie: float = 0.1
    discard: float = 2.0
    dt_load_max: float = 2e-3
    seed: int = 0
    max_frequency_hz: float | None = None

    def __post_init__(self):
        for name in _TUPLE_FIELDS:
            val = getattr(self, name)
            if isinstance(val, list):
                object.__setattr__(self, name, tuple(val))
        f = "settings."
        v.one_of(f + "load", self.load, LOAD_MODELS)
        v.integer(f + "blocks", self.blocks, minimum=2)
        if self.realisations is not None:
            v.integer(f + "realisations", self.realisations, minimum=9)
        v.integer(f + "fit_realisations", self.fit_realisations, minimum=1)
        if self.probe_realisations is not None:
            v.integer(f + "probe_realisations", self.probe_realisations, minimum=0)
        v.integer(f + "delta_realisations", self.delta_realisations, minimum=10)
        v.integer(f + "delta_f_realisations", self.delta_f_realisations, minimum=5)
        v.integer(f + "delta_f_min_blocks", self.delta_f_min_blocks, minimum=2)
        v.replicates(f + "n_bootstrap", self.n_bootstrap)
        v.integer(f + "r_points", self.r_points, minimum=1)
        v.integer(f + "r_fine_points", self.r_fine_points, minimum=3)
        v.integer(f + "max_effects", self.max_effects, minimum=0, maximum=MAX_EFFECTS)
        v.integer(f + "grid_points", self.grid_points, minimum=2)
        v.seed(f + "seed", self.seed)
        if self.model_form is not None:
            v.one_of(f + "model_form", self.model_form, MODEL_FORM_CHOICES)
        for name in ("segment_seconds", "fine_segment_seconds", "load_x", "dt_load_max", "correlation_length", "r_step", "r_fine_span",
                     "band_width_hz"):
            v.positive(f + name, getattr(self, name))
        v.open_unit(f + "level", self.level)
        if self.max_frequency_hz is not None:
            v.positive(f + "max_frequency_hz", self.max_frequency_hz, "Hz")
        v.real(f + "false_alarm", self.false_alarm, low=0.0, high=0.5, low_open=True, high_open=True)
        if self.fine_segment_seconds < self.segment_seconds:
            raise SpecificationError(f + "fine_segment_seconds", self.fine_segment_seconds,
                                     f"must be at least segment_seconds = {self.segment_seconds} s (it is the finer "
                                     "resolution: a longer Welch segment)")
        if self.false_alarm * (self.n_realisations + 1) < 1:
            raise SpecificationError(f + "false_alarm", self.false_alarm,
                                     f"needs realisations + 1 >= 1/false_alarm: with {self.n_realisations} realisations "
                                     f"the smallest p-value is 1/{self.n_realisations + 1}")
        if self.continuation_alarm is not None:
            v.real(f + "continuation_alarm", self.continuation_alarm, low=0.0, high=self.false_alarm, low_open=True)
        if self.max_effects >= 1 and int(self.continuation_rate * (self.n_realisations + 1) + 1e-9) < 1:
            given = "" if self.continuation_alarm is not None else "(false_alarm / (max_effects - 1)) "
            raise SpecificationError(f + "continuation_alarm", self.continuation_rate,
                                     f"{given}needs realisations + 1 >= 1/continuation_alarm: with {self.n_realisations} "
                                     f"realisations the smallest p-value is 1/{self.n_realisations + 1}; give more "
                                     "realisations, a larger continuation_alarm (at most false_alarm) or a smaller max_effects")
        v.real(f + "delta", self.delta, low=0.0, high=1.0, high_open=True)
        if self.delta_reference is not None and (not isinstance(self.delta_reference, str) or not self.delta_reference):
            raise SpecificationError(f + "delta_reference", self.delta_reference,
                                     "must be a built-in model name or a specification file path")
        if self.load_dispersion is not None:
            v.real(f + "load_dispersion", self.load_dispersion, low=0.0, high=1.0, high_open=True)
        v.real(f + "delta_f_fallback", self.delta_f_fallback, low=0.0, high=1.0, high_open=True)
        v.real(f + "penalty", self.penalty, low=0.0, high=1.0, high_open=True)
        v.real(f + "tie", self.tie, low=0.0, high=1.0, high_open=True)
        v.non_negative(f + "discard", self.discard, "s")
        n_r = 2 if self.load == "force_and_moment" else 1
        if self.r0 is not None and (not isinstance(self.r0, tuple) or len(self.r0) != n_r
                                    or not all(v.is_number(x) and x > 0 for x in self.r0)):
            raise SpecificationError(f + "r0", self.r0, f"must be {n_r} number(s) > 0 for the {self.load} load")
        g = self.delta_f_grid
        if g is not None and (not isinstance(g, tuple) or len(g) < 3 or not all(v.is_number(x) and 0 < x < 1 for x in g)
                              or any(b <= a for a, b in zip(g, g[1:]))):
            raise SpecificationError(f + "delta_f_grid", g, "must be >= 3 increasing numbers in (0, 1)")
        c = self.candidates
        if c is not None:
            from tubeid.diagnose.catalog import CATALOG

            if not isinstance(c, tuple) or not c or len(set(c)) != len(c) or any(n not in CATALOG for n in c):
                raise SpecificationError(f + "candidates", c, f"must be distinct names of the catalog {sorted(CATALOG)}")

    @property
    def start_r(self) -> tuple[float, ...]:
        """Starting r of the trial method: ``r0``, else the paper's values for the load model."""
        if self.r0 is not None:
            return tuple(float(x) for x in self.r0)
        return (18.0, 20.0) if self.load == "force_and_moment" else (1.3,)

    @property
    def form(self) -> str:
        """The model form in effect: ``model_form``, or the rule of ``None`` (see the class docstring)."""
        if self.model_form is not None:
            return self.model_form
        return "exact" if self.delta_reference is None else "simplified"

    @property
    def n_realisations(self) -> int:
        """R in effect: ``realisations``, else 39 (exact form) or :data:`SIMPLIFIED_REALISATIONS`."""
        if self.realisations is not None:
            return self.realisations
        return SIMPLIFIED_REALISATIONS if self.form == "simplified" else 39

    @property
    def n_probe_realisations(self) -> int:
        """The probe realisations in effect: ``probe_realisations``, else :data:`EXACT_PROBE_REALISATIONS`
        (exact form) or :data:`SIMPLIFIED_PROBE_REALISATIONS`."""
        if self.probe_realisations is not None:
            return self.probe_realisations
        return SIMPLIFIED_PROBE_REALISATIONS if self.form == "simplified" else EXACT_PROBE_REALISATIONS

    @property
    def continuation_rate(self) -> float:
        """The continuation tests' rate in effect: ``continuation_alarm``, else α / (``max_effects`` − 1)
        (α when ``max_effects`` ≤ 2)."""
        if self.continuation_alarm is not None:
            return self.continuation_alarm
        return self.false_alarm / max(1, self.max_effects - 1)

    def alarm_at(self, step: int) -> float:
        """The test's rate after ``step`` effects.

        Parameters
        ----------
        step : int
            Effects chosen so far (0: the record's first test).

        Returns
        -------
        float
            α (``false_alarm``) at step 0, else :attr:`continuation_rate`.
        """
        return self.false_alarm if step == 0 else self.continuation_rate

    @property
    def test_size(self) -> float:
        """The exact size of the detection test: ⌊α(R+1)⌋/(R+1) ≤ α."""
        n = self.n_realisations + 1
        return int(self.false_alarm * n + 1e-9) / n

    def replace(self, **changes: Any) -> "DiagnoseSettings":
        """New, validated settings with some fields changed.

        Parameters
        ----------
        **changes : Any
            Field names and their new values.

        Returns
        -------
        DiagnoseSettings
        """
        return dataclasses.replace(self, **changes)

    def to_json(self) -> str:
        """Canonical JSON (sorted keys): the settings' identity in a diagnosis store.

        Returns
        -------
        str
        """
        d = dataclasses.asdict(self)
        if d["max_frequency_hz"] is None:  # absent by default: the identity of settings from before the field
            del d["max_frequency_hz"]
        return json.dumps(d, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "DiagnoseSettings":
        """Settings from :meth:`to_json`'s text (validated).

        Parameters
        ----------
        text : str
            JSON of the fields.

        Returns
        -------
        DiagnoseSettings
        """
        d = json.loads(text)
        return cls(**{k: (tuple(x) if k in _TUPLE_FIELDS and x is not None else x) for k, x in d.items()})
