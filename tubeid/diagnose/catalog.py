"""The catalog of what a model may lack: one class per effect, and everything the loop needs of it.

Each catalog entry (a :class:`Candidate`) knows, for its effect of :mod:`tubeid.mechanics.effects`:

- its **parameters** (names, units, which are fitted) and its **parameter count** (what the
  selection penalises: every fitted continuous parameter, plus one for a fitted placement — the
  tube of an added mass or damping when the model has several tubes);
- its **signature** (:meth:`Candidate.signature`): a cheap score in [0, 1] — the fraction of the
  fitting blocks' squared standardised residual Σz² that its best cheap action removes — and a
  first estimate, from the :class:`Evidence` (the record's fitting spectra against the declared
  model's band, and the :class:`~tubeid.diagnose._surrogate.LinearSurrogate` for placements);
- its **trial grid** (:meth:`Candidate.trials`) around that estimate, and its **refinement
  lines** (:meth:`Candidate.refine`) around a fitted effect for the joint re-fit;
- the **assumptions** it fixes because the data cannot say (listed in report.md).

Adding an effect to the catalog means one class here (and its effect in
:mod:`tubeid.mechanics.effects`).

The effects are placed anywhere the model can carry them: a tone on any tube at any x (its
position from the sensors' amplitude pattern at its frequency), a stop at any node of the
non-linear tube (the solver's non-linear subsystem is that one tube), an added mass or a damping
on any tube (the tube from the surrogate's fit of the residual).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from tubeid.diagnose._spectra import log10
from tubeid.mechanics.effects import AddedMass, Damping, ExtraStop, SensorNoise, Tone
from tubeid.mechanics.spec import BundleSpec

__all__ = ["Evidence", "Candidate", "ToneCandidate", "StopCandidate", "AddedMassCandidate", "DampingCandidate",
           "SensorNoiseCandidate", "CATALOG"]


@dataclass
class Evidence:
    """What the signatures read (all on the Welch bins ``frequency`` (F,) [Hz], m sensors).

    ``fit``: the record's fitting-block auto-PSD (F, m) [m²/Hz]; ``mu``, ``sigma``: mean and
    standard deviation of log10 PSD over the current model's band realisations (F, m)
    [decades]; ``z_stats`` (m, 3): z-scores of the fitting blocks' RMS, skewness and excess
    kurtosis against the realisations; ``rms`` (m,): the fitting blocks' RMS [m]; ``spec``: the
    declared model with the data's sensors and the effects chosen so far; ``surrogate``:
    its :class:`~tubeid.diagnose._surrogate.LinearSurrogate` at the current r; ``band_hz``: the
    load's band (the surrogate is zero above it).
    """

    frequency: np.ndarray
    fit: np.ndarray
    mu: np.ndarray
    sigma: np.ndarray
    z_stats: np.ndarray
    rms: np.ndarray
    spec: BundleSpec
    surrogate: object
    band_hz: float
    _base: np.ndarray | None = field(default=None, repr=False)

    @property
    def sel(self) -> np.ndarray:
        f = self.frequency
        s = np.ones(f.size, bool)
        s[0] = s[-1] = False
        return s

    @property
    def sel_band(self) -> np.ndarray:
        return self.sel & (self.frequency <= self.band_hz)

    def residual(self) -> np.ndarray:
        """d = log10 S_fit − μ (F, m) [decades]."""
        return log10(self.fit) - self.mu

    def removed(self, shift=None, mu=None, sel=None) -> float:
        """Fraction of Σz² (over ``sel``, default all analysis bins) removed when the model's mean
        log PSD becomes ``mu`` or μ + ``shift`` (level refitted), in [0, 1]."""
        sel = self.sel if sel is None else sel
        d0 = self.residual()[sel]
        w = 1.0 / self.sigma[sel] ** 2
        total = _level_free_ss(d0, w)
        m = (self.mu if mu is None else mu) + (0.0 if shift is None else shift)
        d = (log10(self.fit) - m)[sel]
        return 0.0 if total <= 0 else max(0.0, 1.0 - _level_free_ss(d, w) / total)

    def surrogate_shift(self, effects=(), springs=()) -> np.ndarray:
        """log10 S_surrogate(with ``effects`` and grounded ``springs``) − log10 S_surrogate(as is)
        (F, m) [decades]; zero above the load's band."""
        if self._base is None:
            self._base = log10(self.surrogate.psd())
        return np.where(self.frequency[:, None] <= self.band_hz,
                        log10(self.surrogate.psd(effects, springs)) - self._base, 0.0)

    @property
    def sensor_x(self) -> np.ndarray:
        return np.array([s.x for s in self.spec.sensors])

    @property
    def sensor_tube(self) -> list[str]:
        return [s.tube for s in self.spec.sensors]


def _level_free_ss(d, w) -> float:
    off = np.sum(w * d) / np.sum(w)
    return float(np.sum(w * (d - off) ** 2))


def _interior_positions(spec: BundleSpec, tube: str, step_fraction: float = 0.5) -> list[float]:
    t = spec.tube(tube)
    le = t.length / t.n_elements
    return [float(x) for x in np.arange(le * step_fraction, t.length - 1e-9, le * step_fraction)]


def _interior_nodes(spec: BundleSpec, tube: str) -> list[float]:
    t = spec.tube(tube)
    return [float(x) for x in t.nodes[1:-1]]


class Candidate:
    """One catalog entry (see the module docstring). Subclasses set ``name`` (the effect's
    catalog name), ``effect_type``, ``parameters`` ({name: (units, fitted)}) and implement
    :meth:`signature`, :meth:`trials`, :meth:`refine` and :meth:`assumptions`."""

    name: ClassVar[str]
    effect_type: ClassVar[type]
    parameters: ClassVar[dict]
    #: True when :meth:`from_baseline` gives a trial's PSD exactly from another trial's
    exact_from_baseline: ClassVar[bool] = False

    def n_parameters(self, spec: BundleSpec) -> int:
        """The parameter count the selection penalises."""
        return sum(1 for _, fitted in self.parameters.values() if fitted)

    def signature(self, ev: Evidence) -> dict:
        """{"score": float in [0, 1], "estimate": {...}} (plain values)."""
        raise NotImplementedError

    def trials(self, estimate: dict, ev_spec: BundleSpec, points: int, *, rms=None) -> list:
        """The trial effects around ``estimate``."""
        raise NotImplementedError

    def refine(self, effect, spec: BundleSpec) -> dict:
        """{parameter: (values, log, [effects])}: lines of 3 effects around ``effect``, one per
        fitted continuous parameter (the middle one is ``effect``)."""
        raise NotImplementedError

    def with_value(self, effect, parameter: str, value: float):
        """``effect`` with one parameter changed."""
        import dataclasses

        return dataclasses.replace(effect, **{parameter: value})

    def describe(self, effect) -> dict:
        """{parameter: {"value", "units", "fitted"}} of an effect, as reported."""
        return {p: {"value": getattr(effect, p), "units": u, "fitted": bool(fitted)}
                for p, (u, fitted) in self.parameters.items()}

    def from_baseline(self, effect, baseline_psd, remove: bool = False):
        """The PSD (F, m) of the baseline's model with ``effect`` added (or, with ``remove``,
        taken away), when that is exact (``exact_from_baseline``)."""
        raise NotImplementedError(f"{self.name} trials are simulated")

    def assumptions(self, spec: BundleSpec) -> list[str]:
        return []


def _line(effect, cand, parameter, factors, log=True):
    v0 = getattr(effect, parameter)
    values = [v0 * k for k in factors] if log else [v0 + k for k in factors]
    return values, log, [cand.with_value(effect, parameter, float(v)) for v in values]


class ToneCandidate(Candidate):
    """A harmonic force: frequency from the record's scan peak, position from the sensors'
    amplitude pattern at that frequency (the line's amplitude per sensor against the surrogate's
    |H| from every tube at half-element steps, by the cosine of their angle), amplitude from the
    line's power (|H|² A²/4 per side). Trials: the position and its neighbours one element away ×
    ``points`` amplitudes over ±0.45 decades."""

    name = "tone"
    effect_type = Tone
    parameters = {"frequency_hz": ("Hz", True), "amplitude": ("N", True), "tube": ("", False), "x": ("m", True)}

    def signature(self, ev: Evidence) -> dict:
        f, sel = ev.frequency, ev.sel
        z = ev.residual() / ev.sigma
        z = z - np.mean(z[sel])
        per_f = np.where(sel, np.sum(np.clip(z, 0, None) ** 2, axis=1), -np.inf)
        k = int(np.argmax(per_f))
        win = slice(max(1, k - 2), min(f.size - 1, k + 3))
        excess = np.clip(ev.fit[win] - 10.0 ** ev.mu[win], 0.0, None)          # (5, m)
        tot = excess.sum(axis=1)
        f0 = float(np.sum(f[win] * tot) / np.sum(tot)) if np.sum(tot) > 0 else float(f[k])
        opened = ev.mu.copy()
        opened[win] = np.maximum(opened[win], log10(ev.fit[win]))
        score = ev.removed(mu=opened)
        df = f[1] - f[0]
        power = excess.sum(axis=0) * df                                            # |H|² A²/4 per sensor
        cands = [(t.name, x) for t in ev.spec.tubes for x in _interior_positions(ev.spec, t.name)]
        H2 = ev.surrogate.tone_pattern(f0, cands)                                  # (n_c, m)
        # the pattern: the sensors' line amplitudes √power against |H| of each candidate position,
        # compared by the cosine of their angle (dominated by the sensors that see the line best)
        a = np.sqrt(power)
        h = np.sqrt(H2)
        cos2 = (h @ a) ** 2 / np.maximum(np.sum(h**2, axis=1) * np.sum(a**2), 1e-300)
        i = int(np.argmax(cos2))
        tube, x = cands[i]
        amp = float(2.0 * (h[i] @ a) / max(float(np.sum(h[i] ** 2)), 1e-300))
        return {"score": score, "estimate": {"frequency_hz": f0, "tube": tube, "x": float(x), "amplitude": amp}}

    def trials(self, estimate, spec, points, *, rms=None) -> list:
        t = spec.tube(estimate["tube"])
        le = t.length / t.n_elements
        xs = [x for x in (estimate["x"] - le, estimate["x"], estimate["x"] + le) if 0 < x < t.length]
        amps = estimate["amplitude"] * 10.0 ** np.linspace(-0.45, 0.45, points)
        return [Tone(frequency_hz=float(estimate["frequency_hz"]), amplitude=float(a), tube=t.name, x=float(x))
                for x in xs for a in amps]

    def refine(self, effect, spec) -> dict:
        t = spec.tube(effect.tube)
        half = 0.5 * t.length / t.n_elements
        lines = {"amplitude": _line(effect, self, "amplitude", (10**-0.15, 1.0, 10**0.15))}
        if effect.x - half > 0 and effect.x + half < t.length:
            lines["x"] = _line(effect, self, "x", (-half, 0.0, half), log=False)
        return lines

    def assumptions(self, spec) -> list[str]:
        return ["tone: one sinusoidal transverse force (not a moment) with a random phase; its frequency is the "
                "excess-weighted centroid of the record's peak bins (resolution: one Welch bin); its position is "
                "searched on every tube at half-element steps"]


class StopCandidate(Candidate):
    """An added (or changed) symmetric elastic stop at a node of the non-linear tube. Node: the
    surrogate's best grounded spring (stiffness 1e6, 1e7, 1e8 N/m) against the residual; gap:
    the record's RMS at the nearest sensor × 4^[−1.5, 0.5]. Trials: that node and its neighbours
    × ``points`` gaps. Stiffness: the declared stop's (not fitted)."""

    name = "stop"
    effect_type = ExtraStop
    parameters = {"tube": ("", False), "x": ("m", True), "gap": ("m", True), "stiffness": ("N/m", False)}

    def _tube(self, spec):
        return spec.a_tube or spec.tubes[0].name

    def _stiffness(self, spec):
        return spec.stops[0].stiffness if spec.stops else 1e8

    def signature(self, ev: Evidence) -> dict:
        tube = self._tube(ev.spec)
        best = (0.0, None, None)
        for x in _interior_nodes(ev.spec, tube):
            for k in (1e6, 1e7, 1e8):
                s = ev.removed(shift=ev.surrogate_shift(springs=((tube, x, k),)), sel=ev.sel_band)
                if best[1] is None or s > best[0]:
                    best = (s, x, float(k))
        xs = ev.sensor_x
        on = [i for i, t in enumerate(ev.sensor_tube) if t == tube] or list(range(len(xs)))
        j = on[int(np.argmin(np.abs(xs[on] - best[1])))]
        return {"score": best[0], "estimate": {"tube": tube, "x": best[1], "spring": best[2],
                                               "rms_nearest": float(ev.rms[j])}}

    def trials(self, estimate, spec, points, *, rms=None) -> list:
        nodes = _interior_nodes(spec, estimate["tube"])
        i = int(np.argmin(np.abs(np.array(nodes) - estimate["x"])))
        xs = nodes[max(0, i - 1): i + 2]
        gaps = estimate["rms_nearest"] * 4.0 ** np.linspace(-1.5, 0.5, points)
        k = self._stiffness(spec)
        return [ExtraStop(tube=estimate["tube"], x=x, gap=float(g), stiffness=k) for x in xs for g in gaps]

    def refine(self, effect, spec) -> dict:
        return {"gap": _line(effect, self, "gap", (0.5, 1.0, 2.0))}

    def assumptions(self, spec) -> list[str]:
        tube = self._tube(spec)
        return [f"stop: symmetric, undamped, at a node of the non-linear tube {tube!r} (the solver's non-linear "
                f"subsystem is that tube); stiffness {self._stiffness(spec):g} N/m, the declared stop's (gap and "
                "stiffness trade off at this resolution; the gap is fitted)"]


class _TubeFactor(Candidate):
    """Shared by the tube-wide effects: a scalar per tube, the tube from the surrogate."""

    value_name: ClassVar[str]
    scan: ClassVar[tuple]
    spread: ClassVar[float]

    def n_parameters(self, spec) -> int:
        return 1 + (1 if len(spec.tubes) > 1 else 0)

    def _scan_values(self, spec, tube) -> np.ndarray:
        return np.asarray(self.scan, dtype=float)

    def _effect(self, tube, value):
        return self.effect_type(tube, float(value))

    def signature(self, ev: Evidence) -> dict:
        scores = {}
        for t in ev.spec.tubes:
            best = (0.0, None)
            for v in self._scan_values(ev.spec, t.name):
                s = ev.removed(shift=ev.surrogate_shift([self._effect(t.name, v)]), sel=ev.sel_band)
                if best[1] is None or s > best[0]:
                    best = (s, float(v))
            scores[t.name] = best
        order = sorted(scores, key=lambda n: -scores[n][0])
        top = order[0]
        est = {"tube": top, self.value_name: scores[top][1]}
        if len(order) > 1 and scores[order[1]][0] >= 0.8 * scores[top][0] > 0:
            est["second"] = {"tube": order[1], self.value_name: scores[order[1]][1]}
        return {"score": scores[top][0], "estimate": est}

    def trials(self, estimate, spec, points, *, rms=None) -> list:
        out = []
        for e in (estimate, estimate.get("second")):
            if e:
                out += [self._effect(e["tube"], v) for v in e[self.value_name] * np.geomspace(1 / self.spread, self.spread, points)]
        return out

    def refine(self, effect, spec) -> dict:
        return {self.value_name: _line(effect, self, self.value_name, (1 / 1.4, 1.0, 1.4))}


class AddedMassCandidate(_TubeFactor):
    """Added mass on one tube: mass per length × (1 + factor). Tube and first factor from the
    surrogate (factors 0.03–1 on every tube); trials: ``points`` factors over ×/÷ 2 (and the
    second tube when it scores within 20 % of the first)."""

    name = "added_mass"
    effect_type = AddedMass
    parameters = {"tube": ("", True), "factor": ("1", True)}
    value_name = "factor"
    scan = tuple(np.geomspace(0.03, 1.0, 5))
    spread = 2.0

    def assumptions(self, spec) -> list[str]:
        return ["added_mass: uniform along one tube (its mass per length × (1 + factor)); stiffness unchanged"]


class DampingCandidate(_TubeFactor):
    """Modal damping of one tube: the ratio of all its own modes. Tube and first ratio from the
    surrogate (the declared ratio × 0.1 … 10 on every tube, 6 values); trials: ``points`` ratios over ×/÷ 1.7."""

    name = "damping"
    effect_type = Damping
    parameters = {"tube": ("", True), "ratio": ("1", True)}
    value_name = "ratio"
    spread = 1.7

    def _scan_values(self, spec, tube):
        r = spec.tube(tube).damping_ratio
        return np.clip(r * np.array([0.1, 0.3, 0.5, 2.0, 3.3, 10.0]), 1e-4, 0.9)

    def _effect(self, tube, value):
        return Damping(tube, float(min(value, 0.9)))

    def assumptions(self, spec) -> list[str]:
        return ["damping: one modal damping ratio for all the modes of one tube (as declared models carry it)"]


class SensorNoiseCandidate(Candidate):
    """White measurement noise, the same two-sided level on every sensor. First level: the best
    floor added to the band's mean (41 levels from its lowest bin to the record's highest);
    trials: ``points`` levels over ×/÷ 4. Exact from the baseline: S + level."""

    name = "sensor_noise"
    effect_type = SensorNoise
    parameters = {"level": ("m^2/Hz (two-sided)", True)}

    def signature(self, ev: Evidence) -> dict:
        sel = ev.sel
        med = 10.0 ** ev.mu
        lo = math.floor(np.log10(max(float(np.min(med[sel])), 1e-300)))
        hi = math.ceil(np.log10(float(np.max(ev.fit[sel]))))
        best = (0.0, 10.0**lo)
        for N in np.logspace(lo, hi, 41):
            s = ev.removed(mu=log10(med + N))
            if s > best[0]:
                best = (s, float(N))
        return {"score": best[0], "estimate": {"level": best[1]}}

    def trials(self, estimate, spec, points, *, rms=None) -> list:
        return [SensorNoise(level=float(estimate["level"] * 4.0**u)) for u in np.linspace(-1, 1, points)]

    def refine(self, effect, spec) -> dict:
        return {"level": _line(effect, self, "level", (0.5, 1.0, 2.0))}

    exact_from_baseline = True

    def from_baseline(self, effect, baseline_psd, remove: bool = False):
        return np.asarray(baseline_psd) + (-effect.level if remove else effect.level)

    def assumptions(self, spec) -> list[str]:
        return ["sensor_noise: white, the same level on every sensor, independent between sensors"]


#: The catalog, in its order (ties in the choice go to the earlier entry).
CATALOG = {c.name: c for c in (ToneCandidate(), StopCandidate(), AddedMassCandidate(), DampingCandidate(),
                               SensorNoiseCandidate())}
