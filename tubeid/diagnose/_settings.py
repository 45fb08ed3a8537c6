"""The settings of a diagnosis: one immutable, validated value (its JSON is the diagnosis's identity)."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass

from tubeid import _validation as v
from tubeid.errors import SpecificationError

__all__ = ["DiagnoseSettings", "LOAD_MODELS", "MAX_EFFECTS"]

#: Identification load models: ``distributed`` — the declared model's force points on the
#: non-linear tube with the paper's coherence exp(−|Δx|/λ) (λ = ``correlation_length``), one
#: parameter r = S_ii [N²/Hz]; ``force_and_moment`` — the paper's §3.4 model T, M at ``load_x``,
#: r = (r1 [N²/Hz], r2 [(N·m)²/Hz]).
LOAD_MODELS = ("distributed", "force_and_moment")

#: The most effects one diagnosis selects (the pipeline holds this many selection steps).
MAX_EFFECTS = 3

_TUPLE_FIELDS = ("r0", "delta_f_grid", "candidates")


@dataclass(frozen=True)
class DiagnoseSettings:
    """Sizes and rules of a diagnosis (seconds, Hz, counts, decades). Every field is checked here,
    before any computation; a bad value is refused naming the field, the value and the rule.

    Split and spectra
        ``blocks``: the record is cut into this many equal time blocks, the even ones fit, the odd
        ones are held out (≥ 2). ``segment_seconds`` [s]: Welch segment (Hann, 50 % overlap).
    Detection (the calibrated test, :func:`tubeid.diagnose.detection_test`)
        ``realisations`` R: records of the declared stochastic model shaped like the held-out set;
        the test is exact at level ⌊α(R+1)⌋/(R+1) (R = 39, α = 0.05: exactly 5 %).
        ``false_alarm`` α: the stated false-alarm rate. ``band_width_hz`` [Hz]: the bands of the
        goodness-of-fit of log band energies. ``level``: probability of the band drawn in
        residual.png (display only).
    Model uncertainty
        ``delta``: dispersion δ of subsystem B's stiffness, given; ``delta_reference``: a model
        (built-in name or specification file) from which δ is identified instead, by the paper's
        maximum likelihood of J (``delta_realisations`` Monte Carlo records per δ).
    Load
        ``load`` (:data:`LOAD_MODELS`), ``correlation_length`` [m], ``load_x`` [m]; ``r0``: the
        start of the trial method (default: the paper's levels), ``r_points`` and ``r_step``
        [decades] its coarse grid, ``r_fine_points`` and ``r_fine_span`` [decades] its fine grid.
        ``load_dispersion``: δ_F given; ``None`` identifies it by maximum likelihood of J_s when
        the record has at least ``delta_f_min_blocks`` fitting blocks (one J_s observation each;
        fewer cannot identify a dispersion), else the band uses ``delta_f_fallback`` and says so.
        ``delta_f_grid`` (``None``: log-spaced up to 0.9 δ_max(m)), ``delta_f_realisations``,
        ``n_bootstrap``.
    Selection
        ``max_effects``: effects selected at most (0: detection only). ``candidates``: catalog
        names considered (``None``: the whole catalog). ``fit_realisations``: records of the mean
        model per trial. ``grid_points``: points per parameter of a trial grid. ``penalty``: an
        effect with k parameters must bring the held-out error below the current one × (1 −
        penalty)^k.
    Simulation
        ``discard`` [s]: transient dropped; ``dt_load_max`` [s]: load sampling bound; ``seed``: all
        random streams (common random numbers across trials).
    """

    blocks: int = 4
    segment_seconds: float = 2.0
    realisations: int = 39
    false_alarm: float = 0.05
    band_width_hz: float = 5.0
    level: float = 0.95
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
    discard: float = 2.0
    dt_load_max: float = 1e-3
    seed: int = 0

    def __post_init__(self):
        for name in _TUPLE_FIELDS:
            val = getattr(self, name)
            if isinstance(val, list):
                object.__setattr__(self, name, tuple(val))
        f = "settings."
        v.one_of(f + "load", self.load, LOAD_MODELS)
        v.integer(f + "blocks", self.blocks, minimum=2)
        v.integer(f + "realisations", self.realisations, minimum=9)
        v.integer(f + "fit_realisations", self.fit_realisations, minimum=1)
        v.integer(f + "delta_realisations", self.delta_realisations, minimum=10)
        v.integer(f + "delta_f_realisations", self.delta_f_realisations, minimum=5)
        v.integer(f + "delta_f_min_blocks", self.delta_f_min_blocks, minimum=2)
        v.integer(f + "n_bootstrap", self.n_bootstrap, minimum=0)
        v.integer(f + "r_points", self.r_points, minimum=1)
        v.integer(f + "r_fine_points", self.r_fine_points, minimum=3)
        v.integer(f + "max_effects", self.max_effects, minimum=0, maximum=MAX_EFFECTS)
        v.integer(f + "grid_points", self.grid_points, minimum=2)
        v.seed(f + "seed", self.seed)
        for name in ("segment_seconds", "load_x", "dt_load_max", "correlation_length", "r_step", "r_fine_span",
                     "band_width_hz"):
            v.positive(f + name, getattr(self, name))
        v.open_unit(f + "level", self.level)
        v.real(f + "false_alarm", self.false_alarm, low=0.0, high=0.5, low_open=True, high_open=True)
        if self.false_alarm * (self.realisations + 1) < 1:
            raise SpecificationError(f + "false_alarm", self.false_alarm,
                                     f"needs realisations + 1 >= 1/false_alarm: with {self.realisations} realisations "
                                     f"the smallest p-value is 1/{self.realisations + 1}")
        v.real(f + "delta", self.delta, low=0.0, high=1.0, high_open=True)
        if self.delta_reference is not None and (not isinstance(self.delta_reference, str) or not self.delta_reference):
            raise SpecificationError(f + "delta_reference", self.delta_reference,
                                     "must be a built-in model name or a specification file path")
        if self.load_dispersion is not None:
            v.real(f + "load_dispersion", self.load_dispersion, low=0.0, high=1.0, high_open=True)
        v.real(f + "delta_f_fallback", self.delta_f_fallback, low=0.0, high=1.0, high_open=True)
        v.real(f + "penalty", self.penalty, low=0.0, high=1.0, high_open=True)
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
    def test_size(self) -> float:
        """The exact size of the detection test: ⌊α(R+1)⌋/(R+1) ≤ α."""
        n = self.realisations + 1
        return int(self.false_alarm * n + 1e-9) / n

    def replace(self, **changes) -> "DiagnoseSettings":
        """New, validated settings with some fields changed."""
        return dataclasses.replace(self, **changes)

    def to_json(self) -> str:
        """Canonical JSON (sorted keys): the settings' identity in a diagnosis store."""
        return json.dumps(dataclasses.asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "DiagnoseSettings":
        d = json.loads(text)
        return cls(**{k: (tuple(x) if k in _TUPLE_FIELDS and x is not None else x) for k, x in d.items()})
