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

from tubeid._validation import one_of
from tubeid.diagnose._settings import MODEL_FORM_CHOICES
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
    load's band (the surrogate is zero above it). When the declared model is simplified (``form``),
    the spectrum's residual mixes the effect with the model's own errors, so the signatures read
    the robust test instead where they can: ``line_frequency_hz``, where its line statistic peaks
    [Hz], and ``floor_level``, the record's noise-floor level [m²/Hz] (the median over sensors of
    the 10th percentile of the conditional PSD).
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
    form: str = "exact"
    line_frequency_hz: float | None = None
    floor_level: float | None = None
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

    def removed(self, shift=None, mu=None, sel=None, scaled: bool = False) -> float:
        """Fraction of Σz² (over ``sel``, default all analysis bins) removed when the model's mean
        log PSD becomes ``mu`` or μ + ``shift`` (level refitted), in [0, 1]. ``scaled``: μ + β
        ``shift`` with the best β in [0, 1] (the surrogate's resonances are sharper than the
        non-linear model's, so it overstates how far a shifted peak moves the spectrum)."""
        sel = self.sel if sel is None else sel
        d0 = self.residual()[sel]
        w = 1.0 / self.sigma[sel] ** 2
        total = _level_free_ss(d0, w)
        if total <= 0:
            return 0.0
        if scaled and shift is not None:
            dc = d0 - np.sum(w * d0) / np.sum(w)
            sh = np.asarray(shift)[sel]
            sc = sh - np.sum(w * sh) / np.sum(w)
            den = float(np.sum(w * sc * sc))
            beta = 0.0 if den <= 0 else float(np.clip(np.sum(w * dc * sc) / den, 0.0, 1.0))
            return max(0.0, 1.0 - float(np.sum(w * (dc - beta * sc) ** 2)) / total)
        m = (self.mu if mu is None else mu) + (0.0 if shift is None else shift)
        d = (log10(self.fit) - m)[sel]
        return max(0.0, 1.0 - _level_free_ss(d, w) / total)

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
    #: With the simplified form, the robust statistic whose feature the entry is fitted to and judged
    #: by (None: the first robust statistic that points to it).
    feature: ClassVar[str | None] = None
    #: The parameter :meth:`variants` varies (None: none). Its line in the joint re-fit is derived
    #: like the trial grid's, from the centre and the same model without the effect (one simulation),
    #: not simulated point by point (:meth:`refine` leaves it out).
    profiled: ClassVar[str | None] = None

    def n_parameters(self, spec: BundleSpec) -> int:
        """The parameter count the selection penalises.

        Parameters
        ----------
        spec : BundleSpec
            The declared model (its tubes: a placement on one of several is a parameter).

        Returns
        -------
        int
        """
        return sum(1 for _, fitted in self.parameters.values() if fitted)

    def signature(self, ev: Evidence) -> dict:
        """The effect's cheap score and first estimate.

        Parameters
        ----------
        ev : Evidence

        Returns
        -------
        dict
            {"score": float in [0, 1], "estimate": {...}} (plain values).
        """
        raise NotImplementedError

    def trials(self, estimate: dict, ev_spec: BundleSpec, points: int, *, rms: np.ndarray | None = None) -> list:
        """The trial effects around ``estimate``.

        Parameters
        ----------
        estimate : dict
            The signature's estimate.
        ev_spec : BundleSpec
            The declared model with the data's sensors.
        points : int
            Points per parameter (``grid_points``).
        rms : numpy.ndarray, optional
            The record's RMS per sensor [m] (unused by the catalog's entries).

        Returns
        -------
        list
            Effects of :mod:`tubeid.mechanics.effects`.
        """
        raise NotImplementedError

    def refine(self, effect: object, spec: BundleSpec, surrogate: object = None) -> dict:
        """Lines of 3 effects around ``effect`` for the joint re-fit, one per fitted continuous
        parameter but :attr:`profiled` (the middle one is ``effect``).

        Parameters
        ----------
        effect : object
            A fitted effect of this entry's type.
        spec : BundleSpec
            The declared model with the data's sensors.
        surrogate : LinearSurrogate, optional
            The :class:`~tubeid.diagnose._surrogate.LinearSurrogate` at the current point.

        Returns
        -------
        dict
            {parameter: (values, log, [effects])}.
        """
        raise NotImplementedError

    def combine(self, effect: object, best: dict, spec: BundleSpec, surrogate: object = None) -> object:
        """The effect at the lines' minimisers.

        Parameters
        ----------
        effect : object
            The effect the lines were drawn around.
        best : dict
            {parameter: value}, the lines' minimisers.
        spec : BundleSpec
            The declared model with the data's sensors.
        surrogate : LinearSurrogate, optional
            The surrogate at the lines' centre.

        Returns
        -------
        object
            The effect with those values.
        """
        for par, value in best.items():
            effect = self.with_value(effect, par, value)
        return effect

    def with_value(self, effect: object, parameter: str, value: float) -> object:
        """``effect`` with one parameter changed.

        Parameters
        ----------
        effect : object
        parameter : str
        value : float

        Returns
        -------
        object
        """
        import dataclasses

        return dataclasses.replace(effect, **{parameter: value})

    def describe(self, effect: object) -> dict:
        """An effect's parameters as reported.

        Parameters
        ----------
        effect : object

        Returns
        -------
        dict
            {parameter: {"value", "units", "fitted"}}.
        """
        return {p: {"value": getattr(effect, p), "units": u, "fitted": bool(fitted)}
                for p, (u, fitted) in self.parameters.items()}

    def from_baseline(self, effect: object, baseline_psd: np.ndarray, remove: bool = False) -> np.ndarray:
        """The auto-PSD of the baseline's model with ``effect`` added (or taken away), when that
        is exact (``exact_from_baseline``).

        Parameters
        ----------
        effect : object
        baseline_psd : numpy.ndarray
            (F, m) [m²/Hz].
        remove : bool
            Take the effect away instead.

        Returns
        -------
        numpy.ndarray
            (F, m) [m²/Hz].
        """
        raise NotImplementedError(f"{self.name} trials are simulated")

    def variants(self, effect: object, psd: np.ndarray, baseline_psd: np.ndarray, frequency: np.ndarray) -> list:
        """Trials derived from a simulated one without simulation (default: none).

        Parameters
        ----------
        effect : object
            The simulated trial's effect.
        psd, baseline_psd : numpy.ndarray
            (F, m) PSDs [m²/Hz] of that trial and of the same model without the effect.
        frequency : numpy.ndarray
            (F,) [Hz].

        Returns
        -------
        list
            [(effect, psd (F, m))].
        """
        return []

    def assumptions(self, spec: BundleSpec) -> list[str]:
        """What the entry fixes because the data cannot say (listed in report.md).

        Parameters
        ----------
        spec : BundleSpec
            The declared model with the data's sensors.

        Returns
        -------
        list of str
        """
        return []


def _line(effect, cand, parameter, factors, log=True):
    v0 = getattr(effect, parameter)
    values = [v0 * k for k in factors] if log else [v0 + k for k in factors]
    return values, log, [cand.with_value(effect, parameter, float(v)) for v in values]


class ToneCandidate(Candidate):
    """A harmonic force: frequency from the record's scan peak, position from the sensors'
    amplitude pattern at that frequency (the line's amplitude per sensor against the surrogate's
    |H| from every tube at half-element steps, by the cosine of their angle), amplitude from the
    line's power (|H|² A²/4 per side). Trials: the four best positions at least an element apart
    (a few sensors leave the pattern ambiguous), each simulated at its estimated amplitude and
    profiled over ±0.5 decades of amplitude without simulation (:meth:`variants`). With a
    simplified model the line's bin is where the test's line statistic peaks."""

    name = "tone"
    effect_type = Tone
    parameters = {"frequency_hz": ("Hz", True), "amplitude": ("N", True), "tube": ("", False), "x": ("m", True)}
    #: The amplitude's re-fit line is its profile (:meth:`variants`): trials simulated at other
    #: amplitudes differ from the centre's far from the line too (the stop makes the response chaotic),
    #: and that noise in every bin outweighs the few bins a line touches (measured: a 100 N tone sized
    #: 60 N by a simulated line whose fitting errors were 1.98 / 2.02 / 2.21).
    profiled = "amplitude"

    def signature(self, ev: Evidence) -> dict:
        f, sel = ev.frequency, ev.sel
        z = ev.residual() / ev.sigma
        z = z - np.mean(z[sel])
        per_f = np.where(sel, np.sum(np.clip(z, 0, None) ** 2, axis=1), -np.inf)
        if ev.line_frequency_hz is not None and np.isfinite(ev.line_frequency_hz):
            k = int(np.argmin(np.abs(f - ev.line_frequency_hz)))
        else:
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
        amps = 2.0 * (h @ a) / np.maximum(np.sum(h**2, axis=1), 1e-300)
        positions = []
        for i in np.argsort(-cos2, kind="stable"):
            # identical tubes score alike to round-off: the first of them in the model's order (a later
            # twin lands on that position, already kept, and is skipped below)
            i = int(np.flatnonzero(np.abs(cos2 - cos2[i]) <= 1e-9 * cos2[i])[0])
            tube, x = cands[i]
            le = ev.spec.tube(tube).length / ev.spec.tube(tube).n_elements
            if any(t == tube and abs(x - x2) <= le for t, x2, _, _ in positions):
                continue  # the same position, or within an element of a better one
            positions.append((tube, float(x), float(amps[i]), float(cos2[i])))
            if len(positions) == 4:
                break
        tube, x, amp, _ = positions[0]
        return {"score": score, "estimate": {"frequency_hz": f0, "tube": tube, "x": x, "amplitude": amp,
                                             "positions": [list(q) for q in positions]}}

    #: amplitude factors of the derived trials (:meth:`variants`)
    profile = tuple(10.0 ** np.linspace(-0.5, 0.5, 21))

    def trials(self, estimate, spec, points, *, rms=None) -> list:
        return [Tone(frequency_hz=float(estimate["frequency_hz"]), amplitude=float(amp), tube=tube, x=float(x))
                for tube, x, amp, _ in estimate["positions"]]

    def variants(self, effect, psd, baseline_psd, frequency) -> list:
        """The line scaled to other amplitudes A·k: within ±2 bins of f0 the trial's excess over the
        baseline (the same model without the tone, the same random streams) times k² (a line's
        power is ∝ A²); elsewhere the trial as simulated."""
        f = np.asarray(frequency)
        win = np.abs(f - effect.frequency_hz) <= 2.0 * (f[1] - f[0]) + 1e-9
        excess = np.where(win[:, None], np.clip(np.asarray(psd) - np.asarray(baseline_psd), 0.0, None), 0.0)
        return [(self.with_value(effect, "amplitude", float(effect.amplitude * k)), np.asarray(psd) + (k * k - 1.0) * excess)
                for k in self.profile if k != 1.0]

    @staticmethod
    def _compensation(effect, xs, surrogate) -> np.ndarray:
        """Amplitude factors keeping the line's total power at the sensors when the tone moves to
        ``xs`` (the surrogate's Σ|H|² at f0): position and amplitude are otherwise tied."""
        if surrogate is None:
            return np.ones(len(xs))
        H2 = surrogate.tone_pattern(effect.frequency_hz, [(effect.tube, effect.x)] + [(effect.tube, x) for x in xs]).sum(axis=1)
        return np.sqrt(H2[0] / np.maximum(H2[1:], 1e-300))

    def refine(self, effect, spec, surrogate=None) -> dict:
        t = spec.tube(effect.tube)
        half = 0.5 * t.length / t.n_elements
        lines = {}
        xs = [effect.x - half, effect.x, effect.x + half]
        if xs[0] > 0 and xs[2] < t.length:
            comp = self._compensation(effect, xs, surrogate)
            lines["x"] = (xs, False, [effect if x == effect.x else
                                      Tone(effect.frequency_hz, float(effect.amplitude * g), effect.tube, float(x))
                                      for x, g in zip(xs, comp)])
        return lines

    def combine(self, effect, best, spec, surrogate=None):
        """The amplitude line's minimiser at the old position, compensated for the move to the x
        line's minimiser (the x line's trials were compensated the same way)."""
        amp = best.get("amplitude", effect.amplitude)
        if "x" in best:
            amp *= float(self._compensation(effect, [best["x"]], surrogate)[0])
        return Tone(effect.frequency_hz, float(amp), effect.tube, float(best.get("x", effect.x)))

    def assumptions(self, spec) -> list[str]:
        return ["tone: one sinusoidal transverse force (not a moment) with a random phase; its frequency is the "
                "excess-weighted centroid of the record's peak bins (resolution: one Welch bin); its position is "
                "searched on every tube at half-element steps; " + _TWINS]


class StopCandidate(Candidate):
    """An added (or changed) symmetric elastic stop at a node of the non-linear tube. Node: the node
    nearest the sensor of that tube whose excess kurtosis departs most from the model's (a stop
    clips the motion near it) when that departure is clear (|z| ≥ :attr:`KURTOSIS_Z`) or the declared model
    is simplified, else the surrogate's best grounded spring (stiffness 1e6, 1e7, 1e8 N/m) against
    the residual; gap: the record's RMS at the nearest sensor × 4^[−1.5, 0.5]. Trials: that node
    and its neighbours × ``points`` gaps. Stiffness: the declared stop's (not fitted)."""

    name = "stop"
    effect_type = ExtraStop
    #: A sensor's kurtosis this many band standard deviations from the model's places the stop.
    KURTOSIS_Z = 3.0
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
        on = [i for i, t in enumerate(ev.sensor_tube) if t == tube]
        if on:  # the kurtosis of the stop's own tube's sensors (another tube's position means nothing here)
            j = on[int(np.argmax(np.abs(ev.z_stats[on, 2])))]
            if ev.form == "simplified" or abs(ev.z_stats[j, 2]) >= self.KURTOSIS_Z:
                nodes = np.array(_interior_nodes(ev.spec, tube))
                best = (best[0], float(nodes[int(np.argmin(np.abs(nodes - xs[j])))]), best[2])
        on = on or list(range(len(xs)))
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

    def refine(self, effect, spec, surrogate=None) -> dict:
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
                s = ev.removed(shift=ev.surrogate_shift([self._effect(t.name, v)]), sel=ev.sel_band, scaled=True)
                if best[1] is None or s > best[0]:
                    best = (s, float(v))
            scores[t.name] = best
        order = sorted(scores, key=lambda n: -scores[n][0])
        best = scores[order[0]][0]

        def twin(n):  # identical tubes seen alike: their scores differ by round-off only
            return abs(scores[n][0] - best) <= 1e-9 * max(best, 1e-300)

        top = next(n for n in scores if twin(n))  # the first of the best's twins in the model's order
        est = {"tube": top, self.value_name: scores[top][1]}
        # the runner-up: the best tube that is not a twin of the first
        others = [n for n in order if not twin(n)]
        if others:
            est["second"] = {"tube": others[0], self.value_name: scores[others[0]][1]}
        return {"score": scores[top][0], "estimate": est}

    def _trial_values(self, value, points) -> np.ndarray:
        return value * np.geomspace(1 / self.spread, self.spread, points)

    def trials(self, estimate, spec, points, *, rms=None) -> list:
        out = []
        for e in (estimate, estimate.get("second")):
            if e:
                out += [self._effect(e["tube"], v) for v in self._trial_values(e[self.value_name], points)]
        return out

    def refine(self, effect, spec, surrogate=None) -> dict:
        return {self.value_name: _line(effect, self, self.value_name, (1 / 1.4, 1.0, 1.4))}


#: What a tube's fit cannot say, in the added-mass and damping assumptions.
_TWINS = ("tubes the sensors see alike (identical tubes tied alike to the rest: their fits tie) cannot be told "
          "apart; the first of them in the model's order is reported")


class AddedMassCandidate(_TubeFactor):
    """Added mass on one tube: mass per length × (1 + factor). The two best tubes by the
    surrogate's fit of the residual (factors 0.03–1, amplitude of the shift free: the surrogate's
    sharper resonances overstate a shift); trials on each: ``points`` factors from 0.05 to 1.35
    (log-spaced: the surrogate does not size a shift of resonances)."""

    name = "added_mass"
    effect_type = AddedMass
    parameters = {"tube": ("", True), "factor": ("1", True)}
    value_name = "factor"
    scan = tuple(np.geomspace(0.03, 1.0, 5))
    #: Fitted to the spectral profile: the reference's × 1.3, × 1.6 and × 2 records sized 0.32, 0.63
    #: and 0.96, where the tilt's slopes gave 0.52–0.63 for × 1.3 (README).
    feature = "profile"
    #: The factor of the probe whose simulated realisations give the ``profile`` statistic its
    #: direction: inside the trial grid, not its edge.
    probe_factor = 0.25

    def probe(self, spec, form: str = "simplified") -> AddedMass:
        """The probe effect of the ``profile`` statistic, :attr:`probe_factor` on one tube. With the
        ``simplified`` form, the tube that carries the most sensors (ties: the first in sensor
        order): its own resonances, which the simplified model mis-shapes, move. With the ``exact``
        form, the first tube (in the specification's order) that carries no sensor, or the sensors'
        tube if every tube carries one: the sensors' own tube's mass moves their resonances, which
        the exact form's ``gof`` sees, whereas another tube's mass reaches the sensors through the
        grids only, a shift that ``gof``'s mean over every band dilutes (README). An added mass on
        a tube unlike the probe's moves the profile in another direction, which the statistic does
        not look for."""
        tubes = [s.tube for s in spec.sensors]
        if one_of("form", form, MODEL_FORM_CHOICES) == "exact":
            free = [t.name for t in spec.tubes if t.name not in tubes]
            if free:
                return AddedMass(free[0], self.probe_factor)
        return AddedMass(max(dict.fromkeys(tubes), key=tubes.count), self.probe_factor)

    def _trial_values(self, value, points) -> np.ndarray:
        return np.geomspace(0.05, 1.35, points)

    def assumptions(self, spec) -> list[str]:
        return ["added_mass: uniform along one tube (its mass per length × (1 + factor)); stiffness unchanged; "
                + _TWINS]


class DampingCandidate(_TubeFactor):
    """Modal damping of one tube: the ratio of all its own modes. The two best tubes and their
    ratios from the surrogate (the declared ratio × 0.1 … 10, 6 values). The surrogate tells the
    tube and the direction (more or less damping than declared) but not the size (measured: 0.2
    for a true 0.06, the declared 0.02 × 3), so the trials on each tube are ``points`` ratios
    log-spaced from the declared ratio × 1.5 to the surrogate's × 1.7 (or from its ÷ 1.7 to the
    declared ÷ 1.5), never only around the surrogate's value. With a simplified model the
    surrogate's direction is not trusted (the residual mixes the model's own errors): 2 ×
    ``points`` ratios log-spaced from the declared ÷ 3 to × 3."""

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

    def with_value(self, effect, parameter, value):
        """The ratio changed, at most 0.9 as in the scan (a re-fit line or its extension can reach past
        it: a ratio of 1 or more is no damping ratio)."""
        return self._effect(effect.tube, value)

    @staticmethod
    def _between(declared: float, estimated: float, points: int) -> np.ndarray:
        """``points`` ratios from beyond the declared ratio to beyond the surrogate's, on its side."""
        if estimated >= declared:
            return np.geomspace(declared * 1.5, max(estimated, declared * 1.5) * 1.7, points)
        return np.geomspace(max(min(estimated, declared / 1.5) / 1.7, 1e-4), declared / 1.5, points)

    def signature(self, ev: Evidence) -> dict:
        out = super().signature(ev)
        out["estimate"]["both_sides"] = ev.form == "simplified"
        return out

    def trials(self, estimate, spec, points, *, rms=None) -> list:
        out = []
        for e in (estimate, estimate.get("second")):
            if e:
                declared = spec.tube(e["tube"]).damping_ratio
                values = (declared * np.geomspace(1 / 3, 3, 2 * points) if estimate.get("both_sides")
                          else self._between(declared, e[self.value_name], points))
                out += [self._effect(e["tube"], v) for v in values]
        return out

    def assumptions(self, spec) -> list[str]:
        return ["damping: one modal damping ratio for all the modes of one tube (as declared models carry it); " + _TWINS]


class SensorNoiseCandidate(Candidate):
    """White measurement noise, the same two-sided level on every sensor. First level: the best
    floor added to the band's mean (41 levels from its lowest bin to the record's highest) — with a
    simplified model, the record's noise-floor level (:class:`Evidence`); trials: ``points``
    levels over ×/÷ 4. Exact from the baseline: S + level (auto-PSDs)."""

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
        if ev.form == "simplified" and ev.floor_level is not None:
            best = (ev.removed(mu=log10(med + ev.floor_level)), float(ev.floor_level))
        return {"score": best[0], "estimate": {"level": best[1]}}

    def trials(self, estimate, spec, points, *, rms=None) -> list:
        return [SensorNoise(level=float(estimate["level"] * 4.0**u)) for u in np.linspace(-1, 1, points)]

    def refine(self, effect, spec, surrogate=None) -> dict:
        return {"level": _line(effect, self, "level", (0.5, 1.0, 2.0))}

    exact_from_baseline = True

    def from_baseline(self, effect, baseline_psd, remove: bool = False):
        return np.asarray(baseline_psd) + (-effect.level if remove else effect.level)

    def assumptions(self, spec) -> list[str]:
        return ["sensor_noise: white, the same level on every sensor, independent between sensors"]


#: The catalog, in its order (ties in the choice go to the earlier entry).
CATALOG = {c.name: c for c in (ToneCandidate(), StopCandidate(), AddedMassCandidate(), DampingCandidate(),
                               SensorNoiseCandidate())}
