"""Detection as a calibrated test: is the held-out record a realisation of the declared model?

H0: the held-out record is one more realisation of the declared stochastic model, whose R
realisations (same block layout, same estimators) are given. Each statistic of :data:`STATISTICS`
looks for one kind of departure; each is computed for every one of the N = R + 1 samples (the record
and the R realisations) against the *other* N − 1 samples only. What the samples carry
(:class:`Observations`, sample axis first): auto-PSDs at the test's Welch segment (``psd``) and at a
finer one (``fine``), the conditional PSD of each sensor given the others (``residual``,
1/[S⁻¹]_ii of the PSD matrix S), and the time statistics (RMS, skewness, excess kurtosis).

Statistics that take the declared model's spectral *shape* as right (``model_form="exact"``):

``scan``       the largest, over frequencies, of the mean over sensors of z², with z the
               standardised residual of log10 PSD (per bin: minus the others' mean, divided by
               their standard deviation; the sample's own mean offset over all bins and sensors
               removed first): a narrow line (a tone) touches one or two bins of every sensor.
``gof``        the mean over bands and sensors of the squared standardised residual of the log
               energies of ``band_width_hz`` bands (level removed as above): a broad in-band shift
               (added mass, a stop, a noise floor) moves many bands a little.
``sharpness``  the mean over sensors and 4·``band_width_hz`` chunks of the squared standardised
               log roughness, roughness = the mean square of log10 PSD minus its running mean over
               ±``smooth_bins`` bins: sharper or blunter resonances (damping) change it, whereas a
               random shift of the resonances (what δ does) does not.
``profile``    (below, with the probe on a tube that carries no sensor: the catalog's
               :meth:`~tubeid.diagnose.catalog.AddedMassCandidate.probe`) another tube's added
               mass reaches the sensors through the grids only, a shift ``gof``'s mean over every
               band dilutes and the projection on the probe's direction keeps (measured on the
               reference's outer tubes: README). One-sided: effect-free records of a nominal,
               symmetric bundle sit on its negative side, every draw of B making it less so.

Statistics that a *simplified* declared model can be trusted for (``model_form="simplified"``):
its random subsystem B moves and scales resonances (what δ covers), but a coarser or homogenised B
also misses modes and mis-shapes the spectrum in ways no draw of B reproduces (measured with
``paper-simplified`` against 10 effect-free reference records: ``scan``, ``gof`` and ``sharpness``
give p-values of 0.025–0.15 only, where a calibrated test spreads them over 0.025–1; README).
These six look only at what such a model still gets right — the non-linear tube, its sensors
and its declared damping — each through a local or scale-free feature (:func:`features`), and each
points to the catalog effect that can explain it (``effects``):

``line``       fine resolution (``fine``): the prominence of log10 PSD over a ring of bins 4–8
               bins away (a Hann line stays within ±2 bins, a resonance of the declared damping
               spreads over the ring); the largest, over frequencies, of the mean over sensors of
               the positive part of its standardised residual squared (a scale floor of 0.1 decade).
               → ``tone``.
``floor``      the conditional PSD of each sensor given the others is the part no other sensor
               explains; above the load's band (from band + 4 bins to Nyquist) only the stops'
               impacts drive the structure, whose response there is nearly coherent between
               sensors and leaves it deep and uneven, whereas white sensor noise fills it to a flat
               level N. The feature per sensor is the spread (standard deviation over those bins)
               of its log10; the statistic is the mean over sensors of its standardised log,
               one-sided (flatter). Left out of the test when the record has fewer than
               :data:`FLOOR_MIN_BINS` such bins (Nyquist too close to the band) or its estimate
               averages fewer than 2 segments per sensor (its smallest eigenvalues are then
               round-off). → ``sensor_noise``.
``kurtosis``   the excess kurtosis of each sensor's record (a stop clips the motion near it):
               the largest over sensors of its standardised residual squared. → ``stop``.
``tilt``       fine resolution: the least-squares slope of log10 PSD against log10 f over
               [:data:`TILT_LOW_HZ`, band] per sensor (the rate at which the response falls with
               frequency: the sensors' tube's mass against its stiffness, which a heavier tube
               steepens and a random B barely moves, where a simplified B mis-shapes the detail of
               the spectrum); the absolute standardised mean over sensors (two-sided); left out
               with fewer than :data:`TILT_MIN_BINS` such bins. → ``added_mass``.
``profile``    fine resolution: the spectral profile, the sensors' mean of log10 of the mean power in
               :data:`PROFILE_WIDTH_HZ` bands over [:data:`TILT_LOW_HZ`, band] (level removed),
               projected on the direction the catalog's added mass moves it: w = C⁻¹ (p̄ − μ),
               μ and C the samples' mean and covariance (shrunk by :data:`PROFILE_SHRINK` towards
               its mean variance), p̄ the mean profile of the ``probe`` realisations (the declared
               model with a probe added mass, simulated apart: not samples of the test); the
               standardised projection w·(x − μ), one-sided (towards the probe: the catalog's
               added mass only adds; a lighter tube does not move the profile along −w, the
               shift of a resonance not being linear in the bands). Every draw of B moves the
               profile too, but in other directions: the projection weighs the bands where B's
               draws scatter least. Left out without probe realisations or with fewer than
               :data:`PROFILE_MIN_BANDS` bands. → ``added_mass``.
``resonance``  fine resolution: log roughness (as ``sharpness``, running mean over ±2 Hz) per
               4·``band_width_hz`` chunk in the load band, the first chunk left out (the lowest
               modes are B's, the most uncertain), lines left out (bins within ±2 Hz of a
               prominence above :data:`LINE_MASK_DECADES`: a tone is the line statistic's); the
               absolute mean over chunks and sensors of its standardised residual (sharper or
               blunter resonances everywhere). → ``damping``.

Each statistic's p-value is the fraction of the N samples whose statistic is at least the record's.
The statistics of the test (:data:`MODEL_FORMS`) are combined per sample (:data:`COMBINATIONS`) from
their log values standardised (again against the other samples), u: with the ``exact`` form by the
largest u; with the ``simplified`` form by the smallest tail probability, each statistic's upper
tail above its :data:`TAIL_QUANTILE` quantile extrapolated exponentially with its own mean excess
(the six statistics' tails differ: maxima over frequencies or chunks put 1–2 % of realisations
beyond u = 3 where the profile puts 0.5 %, so the largest u let their heavy tails outrank a
record's profile at 3 σ). p is the combined statistic's rank. Every statistic
of sample i is a fixed function of sample i and of the *set* of the others, so under H0 (the N
samples exchangeable) the record's rank is uniform on 1..N and P(p ≤ α) = ⌊αN⌋/N ≤ α exactly,
whatever the statistics' distributions — no Gaussian or independence assumption, a Monte Carlo
(conformal) test. With R = 39, α = 0.05: exactly 5 %.

What H0 does not cover: the load level r and δ_F are identified on the fitting blocks of the same
record, so the record is exchangeable with the realisations only up to that fit (the level is
removed; the shape's dependence on r through the stop is second order); a given δ larger than the
truth makes the test conservative (fewer false alarms than stated), a smaller one anti-conservative;
with a simplified model, the record is not a realisation of the model at all, and the size of the
``simplified`` statistics is what they measure on effect-free records of the structure, stated in
the README, not exactly α.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import convolve1d, maximum_filter1d, uniform_filter1d

from tubeid._validation import integer, one_of, open_unit, positive
from tubeid.diagnose._spectra import analysis_bins, log10
from tubeid.errors import Described, SpecificationError

__all__ = ["Detection", "Observations", "Statistic", "detection_test", "band_moments", "features", "feature_applies",
           "applicable", "STATISTICS", "MODEL_FORMS", "COMBINATIONS", "LINE_RING_BINS", "SCALE_FLOOR", "PROFILE_WIDTH_HZ",
           "PROFILE_SHRINK", "TAIL_QUANTILE", "TAIL_MIN"]

#: The ring of the line prominence, in fine bins: (inner, outer) distance from the bin.
LINE_RING_BINS = (4, 8)
#: Smallest standard deviation [decades] a prominence is standardised by (the ring's own mean
#: makes some bins nearly constant over the samples).
SCALE_FLOOR = 0.1
#: A fine bin whose prominence exceeds this [decades] is a line: the ``resonance`` roughness leaves
#: out the bins within its smoothing half width of it (resonances of the declared damping stay
#: below it above 20 Hz).
LINE_MASK_DECADES = 1.0
#: Fewest bins above the load's band the ``floor`` statistic needs.
FLOOR_MIN_BINS = 8
#: Half width of the running mean behind the ``resonance`` roughness [Hz].
RESONANCE_SMOOTH_HZ = 2.0
#: Lowest frequency of the ``tilt`` fit [Hz] (below it the Welch estimate's first bins).
TILT_LOW_HZ = 2.0
#: Fewest fine bins between :data:`TILT_LOW_HZ` and the band the ``tilt`` statistic needs.
TILT_MIN_BINS = 8
#: Width of the ``profile`` statistic's bands [Hz] (2 Hz: half the dimension of 1 Hz bands for a
#: covariance estimated from the R + 1 samples; measured better on reference records, README).
PROFILE_WIDTH_HZ = 2.0
#: Shrinkage of the ``profile`` covariance towards its mean variance times the identity (its
#: dimension, the bands, exceeds the realisations).
PROFILE_SHRINK = 0.3
#: Fewest :data:`PROFILE_WIDTH_HZ` bands the ``profile`` statistic needs.
PROFILE_MIN_BANDS = 8
#: Largest standardised value a statistic of the form exp(z) is given (exp stays finite: a band of
#: zeros in one sample must not turn the combination into NaN).
EXP_CAP = 700.0
#: The ``simplified`` combination's tail: above this quantile (over the N samples) of a statistic's
#: standardised value, its tail probability is extrapolated exponentially (module docstring).
TAIL_QUANTILE = 0.9
#: Fewest samples the extrapolated tail holds on average: with N < TAIL_MIN / (1 − TAIL_QUANTILE)
#: samples the quantile is lowered to 1 − TAIL_MIN / N (one sample above it would give every
#: statistic's largest value the same tail probability).
TAIL_MIN = 5


@dataclass(frozen=True)
class Observations:
    """What the statistics read of N samples (sample axis first; the record is sample 0 in a test).
    Fields a statistic does not need may be None (``psd`` too, outside a test).

    Parameters
    ----------
    frequency : numpy.ndarray
        (F,) [Hz], uniform from 0 to Nyquist.
    psd : numpy.ndarray or None
        (N, F, m) auto-PSD [m²/Hz, two-sided].
    frequency_fine : numpy.ndarray or None
        (F',) [Hz] of ``fine``.
    fine : numpy.ndarray or None
        (N, F', m) auto-PSD at a finer Welch segment [m²/Hz].
    residual : numpy.ndarray or None
        (N, F, m) conditional PSD of each sensor given the others [m²/Hz].
    stats : numpy.ndarray or None
        (N, m, 3) RMS [m], skewness, excess kurtosis.
    band_hz : float or None
        The load's band [Hz].
    segments : int or None
        Welch segments each sample's ``psd`` and ``residual`` average (all samples alike).
    probe : numpy.ndarray or None
        (K, F', m) fine auto-PSDs [m²/Hz] of K realisations of the declared model with the probe
        effect (``profile`` statistic), on ``frequency_fine``; not samples of the test.
    """

    frequency: np.ndarray
    psd: np.ndarray | None = None
    frequency_fine: np.ndarray | None = None
    fine: np.ndarray | None = None
    residual: np.ndarray | None = None
    stats: np.ndarray | None = None
    band_hz: float | None = None
    segments: int | None = None
    probe: np.ndarray | None = None

    @property
    def n(self) -> int:
        """The number of samples."""
        return next(int(a.shape[0]) for a in (self.psd, self.fine, self.residual, self.stats) if a is not None)

    @property
    def m(self) -> int:
        """The number of sensors."""
        return next(int(a.shape[-1]) for a in (self.psd, self.residual, self.fine) if a is not None)

    def stacked(self, others: "Observations") -> "Observations":
        """These samples followed by ``others``' (same frequencies and sensors; the probe
        realisations of either).

        Parameters
        ----------
        others : Observations

        Returns
        -------
        Observations
        """
        def cat(a, b):
            return None if a is None or b is None else np.concatenate([a, b])

        return Observations(self.frequency, cat(self.psd, others.psd), self.frequency_fine, cat(self.fine, others.fine),
                            cat(self.residual, others.residual), cat(self.stats, others.stats), self.band_hz,
                            self.segments, self.probe if self.probe is not None else others.probe)


@dataclass(frozen=True)
class Statistic:
    """One statistic of the test: ``compute(obs, band_width_hz, smooth_bins) -> (N,)`` values, large
    = departure; ``needs``: the :class:`Observations` fields it reads besides ``psd``; ``robust``:
    trusted with a simplified declared model (module docstring); ``effects``: the catalog effects
    whose absence it points to (empty: any); ``peak``: its frequency of largest excess for the
    record, or None; ``applies(obs, band_width_hz) -> bool``: whether the observations hold what it
    and its feature read (None: always), else the test leaves it out; ``optional``: those of
    ``needs`` without which the test leaves it out rather than refusing (its feature does not read
    them)."""

    compute: Callable
    needs: tuple[str, ...] = ()
    robust: bool = False
    effects: tuple[str, ...] = ()
    peak: Callable | None = None
    applies: Callable | None = None
    optional: tuple[str, ...] = ()


@dataclass(frozen=True)
class Detection:
    """The result of :func:`detection_test`.

    Parameters
    ----------
    p_value : float
        The combined test's p-value.
    detected : bool
        ``p_value`` ≤ ``false_alarm``.
    false_alarm : float
        The stated rate α.
    size : float
        The exact false-alarm rate ⌊αN⌋/N under H0.
    p_values, values, null_median, excess : dict
        Per statistic combined (those of ``model_form`` whose ``applies`` holds: the
        :attr:`statistics`): its p-value, the record's value, the realisations' median, the
        record's standardised log value (the exact form's combination takes the largest of these;
        the simplified form's first calibrates each one's tail, but the effects are still pointed
        to in the order of these values: :meth:`pointed_effects`).
    scan_frequency_hz : float
        Where the record's line evidence peaks [Hz] (the ``scan``'s, else the ``line``'s; NaN when
        neither is used).
    n_realisations : int
        R.
    model_form : str
        The form whose statistics were combined (:data:`MODEL_FORMS`).
    z : numpy.ndarray or None
        (F, m) the record's standardised log10 PSD residual against all R realisations (level
        removed; 0 at DC and Nyquist); None when the observations carry no ``psd``.
    """

    p_value: float
    detected: bool
    false_alarm: float
    size: float
    p_values: dict
    values: dict
    null_median: dict
    excess: dict
    scan_frequency_hz: float
    n_realisations: int
    model_form: str = "exact"
    z: np.ndarray = field(default=None, repr=False)

    @property
    def statistics(self) -> tuple[str, ...]:
        return tuple(self.p_values)

    def strongest(self) -> str:
        """The statistic with the largest excess: the departure the combined test sees most.

        Returns
        -------
        str
        """
        return max(self.excess, key=lambda k: self.excess[k])

    def pointed_effects(self, available: tuple[str, ...] | None = None) -> tuple[str, ...] | None:
        """The catalog effects the strongest statistic points to (the strongest departure is
        explained first), among ``available``: the statistics are taken by decreasing excess, and the
        first that points to an available effect gives its available effects.

        Parameters
        ----------
        available : tuple of str, optional
            The effects that can still be chosen (None: all).

        Returns
        -------
        tuple of str or None
            None when that statistic points to any effect, and always with the exact form (its
            selection compares every candidate's held-out error; its ``profile`` looks for another
            tube's mass, but a heavier tube elsewhere is not the only departure that moves it); ()
            when no statistic points to an available one.
        """
        if self.model_form == "exact":
            return None
        for name in sorted(self.excess, key=lambda k: -self.excess[k]):
            eff = STATISTICS[name].effects
            if not eff:
                return None
            eff = tuple(e for e in eff if available is None or e in available)
            if eff:
                return eff
        return ()

    def to_dict(self) -> dict:
        """Plain values for report.json (without ``z``).

        Returns
        -------
        dict
        """
        return {"p_value": self.p_value, "detected": self.detected, "false_alarm": self.false_alarm,
                "size": self.size, "model_form": self.model_form, "p_values": dict(self.p_values),
                "statistics": dict(self.values), "null_median": dict(self.null_median), "excess": dict(self.excess),
                "scan_frequency_hz": self.scan_frequency_hz, "n_realisations": self.n_realisations}


def band_moments(samples) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation (ddof 1) over realisations of log10 PSD: samples (R, F, m) →
    (F, m), (F, m) [decades]."""
    L = log10(samples)
    return L.mean(axis=0), L.std(axis=0, ddof=1)


def _loo_z(X: np.ndarray, level_free: bool, floor: float = 0.0) -> np.ndarray:
    """X (N, ...) → z (N, ...): each sample standardised by the mean and std (ddof 1) of the
    others (the std at least ``floor``), after removing its own mean offset from them when
    ``level_free``."""
    N = X.shape[0]
    X = X - X.mean(axis=0)  # shift-invariant; keeps the sums well conditioned
    s1, s2 = X.sum(axis=0), (X**2).sum(axis=0)
    mu = (s1[None] - X) / (N - 1)
    var = ((s2[None] - X**2) - (N - 1) * mu**2) / (N - 2)
    d = X - mu
    if level_free:
        d = d - d.reshape(N, -1).mean(axis=1).reshape((N,) + (1,) * (X.ndim - 1))
    return d / np.sqrt(np.maximum(var, max(floor**2, 1e-30)))


def _bands(f: np.ndarray, width: float) -> np.ndarray:
    """Band index of each frequency for bands [k·width, (k+1)·width)."""
    return np.floor(f / width + 1e-9).astype(int)


def _group_mean(X: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Mean over the frequency axis (1) of X (N, F, m) within each group of ``idx`` → (N, G, m)."""
    groups = np.unique(idx)
    return np.stack([X[:, idx == g].mean(axis=1) for g in groups], axis=1)


def _rank_p(T: np.ndarray) -> float:
    """Fraction of samples whose statistic is >= the record's (sample 0)."""
    return float(np.mean(T >= T[0] - 1e-12 * abs(T[0])))


# -- the features (what each robust statistic standardises; also what the selection fits) --------------


def _log_psd(obs: Observations) -> tuple[np.ndarray, np.ndarray]:
    sel = analysis_bins(obs.frequency)
    return log10(obs.psd)[:, sel], obs.frequency[sel]


def _line_bins(obs: Observations) -> np.ndarray:
    """Fine bins the prominence is read on: from 2 Hz, away from the band edge and Nyquist by the ring."""
    f = obs.frequency_fine
    df = f[1] - f[0]
    outer = LINE_RING_BINS[1] * df
    sel = (f >= 2.0) & (f <= f[-1] - outer - 1e-9)
    if obs.band_hz is not None:
        sel &= np.abs(f - obs.band_hz) > outer + 2 * df
    return sel


def _ring_prominence(L: np.ndarray) -> np.ndarray:
    """log10 PSD (N, F, m) minus its mean over the ring of :data:`LINE_RING_BINS` [decades]."""
    inner, outer = LINE_RING_BINS
    kernel = np.zeros(2 * outer + 1)
    kernel[: outer - inner + 1] = kernel[-(outer - inner + 1):] = 1.0
    return L - convolve1d(L, kernel / kernel.sum(), axis=1, mode="nearest")


def _prominence(obs: Observations) -> np.ndarray:
    """The fine PSD's ring prominence on :func:`_line_bins` (N, F'', m) [decades]."""
    return _ring_prominence(log10(obs.fine))[:, _line_bins(obs)]


def _floor_bins(obs: Observations) -> np.ndarray:
    """Analysis bins above the load's band by 4 bins (all analysis bins when the band is unknown)."""
    f = obs.frequency
    sel = analysis_bins(f)
    if obs.band_hz is not None:
        sel &= f > obs.band_hz + 4 * (f[1] - f[0])
    return sel


def _floor_spread(obs: Observations) -> np.ndarray:
    """Per sensor, the standard deviation over :func:`_floor_bins` of log10 of the conditional PSD (N, m)."""
    return log10(obs.residual[:, _floor_bins(obs)]).std(axis=1)


def _floor_level(obs: Observations) -> np.ndarray:
    """Per sensor, the 10th percentile over :func:`_floor_bins` of log10 of the conditional PSD (N, m)."""
    return np.percentile(log10(obs.residual[:, _floor_bins(obs)]), 10, axis=1)


def _chunks(obs: Observations, band_width_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """The fine analysis bins' 4·band_width chunk index and whether each bin is in a chunk the
    ``resonance`` statistic reads (inside the load band, the first chunk left out)."""
    f = obs.frequency_fine
    fs = f[analysis_bins(f)]
    width = 4.0 * band_width_hz
    top = obs.band_hz if obs.band_hz is not None else fs[-1]
    idx = _bands(fs, width)
    return idx, (idx >= 1) & ((idx + 1) * width <= top + 1e-9)


def _roughness_chunks(obs: Observations, band_width_hz: float) -> np.ndarray:
    """log10 of the mean square of fine log10 PSD minus its running mean (±RESONANCE_SMOOTH_HZ), per
    4·band_width chunk inside the load band, the first chunk left out, lines left out (the bins
    within the half width of a prominence above :data:`LINE_MASK_DECADES`; the running mean over the
    others) (N, C, m)."""
    f = obs.frequency_fine
    h = max(1, int(round(RESONANCE_SMOOTH_HZ / (f[1] - f[0]))))
    L = log10(obs.fine)[:, analysis_bins(f)]
    keep_bin = ~(maximum_filter1d((_ring_prominence(L) > LINE_MASK_DECADES).astype(np.int8), 2 * h + 1, axis=1) > 0)
    w = keep_bin.astype(float)
    running = uniform_filter1d(L * w, 2 * h + 1, axis=1, mode="nearest") / np.maximum(
        uniform_filter1d(w, 2 * h + 1, axis=1, mode="nearest"), 1e-12)
    rough = w * (L - running) ** 2
    idx, keep = _chunks(obs, band_width_hz)
    num, den = _group_mean(rough[:, keep], idx[keep]), _group_mean(w[:, keep], idx[keep])
    return np.log10(np.maximum(num / np.maximum(den, 1e-12), 1e-300))


def _tilt_bins(obs: Observations) -> np.ndarray:
    """Fine analysis bins of the ``tilt`` fit: from :data:`TILT_LOW_HZ` to the load's band (to
    Nyquist when the band is unknown)."""
    f = obs.frequency_fine
    sel = analysis_bins(f) & (f >= TILT_LOW_HZ)
    if obs.band_hz is not None:
        sel &= f <= obs.band_hz + 1e-9
    return sel


def _tilt_slopes(obs: Observations) -> np.ndarray:
    """Per sample and sensor, the least-squares slope of log10 of the fine PSD against log10 f over
    :func:`_tilt_bins` (N, m) [decades per decade]."""
    sel = _tilt_bins(obs)
    x = np.log10(obs.frequency_fine[sel])
    x = x - x.mean()
    L = log10(obs.fine[:, sel])
    return np.einsum("f,nfm->nm", x, L) / np.dot(x, x)


def _profile_bands(obs: Observations) -> np.ndarray:
    """Band index (:data:`PROFILE_WIDTH_HZ` bands) of each of :func:`_tilt_bins`' fine bins."""
    return _bands(obs.frequency_fine[_tilt_bins(obs)], PROFILE_WIDTH_HZ)


def _profile_has_bands(obs: Observations) -> bool:
    """Whether the fine bins hold at least :data:`PROFILE_MIN_BANDS` profile bands."""
    return obs.frequency_fine is not None and np.unique(_profile_bands(obs)).size >= PROFILE_MIN_BANDS


def _profile_of(obs: Observations, fine: np.ndarray) -> np.ndarray:
    """The spectral profile of fine auto-PSDs (N, F', m): the sensors' mean of log10 of the mean
    power per :func:`_profile_bands` band, each sample's mean over the bands removed (N, G) [decades]."""
    P = _group_mean(fine[:, _tilt_bins(obs)], _profile_bands(obs))
    L = np.log10(np.maximum(P, 1e-300)).mean(axis=2)
    return L - L.mean(axis=1, keepdims=True)


def _profile_projection(obs: Observations) -> np.ndarray:
    """w·(x_i − μ) per sample i, x the profile, μ and C the mean and shrunk covariance of all N
    samples and w = C⁻¹ (p̄ − μ), p̄ the probe realisations' mean profile (N,). One direction for
    all samples, a function of their set (the test stays exact); a direction left out per sample
    (μ and C of the others) would give each sample its own estimation error, a null with heavy
    tails (measured on 20 synthetic samples: a largest excess of 145 against 11 with one direction)."""
    X = _profile_of(obs, obs.fine)
    p = _profile_of(obs, obs.probe).mean(axis=0)
    mu = X.mean(axis=0)
    C = np.cov(X, rowvar=False)
    C = (1 - PROFILE_SHRINK) * C + PROFILE_SHRINK * max(float(np.mean(np.diag(C))), 1e-30) * np.eye(C.shape[0])
    return (X - mu) @ np.linalg.solve(C, p - mu)


def applicable(model_form: str, obs: Observations, band_width_hz: float = 5.0) -> tuple[str, ...]:
    """The statistics of ``model_form`` (:data:`MODEL_FORMS`) that ``obs`` holds their ``optional``
    fields for and whose ``applies`` holds (only which fields are present, the frequencies, the band,
    the segment count and the sensor count are read)."""
    return tuple(k for k in MODEL_FORMS[model_form]
                 if all(getattr(obs, f) is not None for f in STATISTICS[k].optional)
                 and feature_applies(k, obs, band_width_hz))


def feature_applies(name: str, obs: Observations, band_width_hz: float = 5.0) -> bool:
    """Whether :func:`features` of ``name`` is informative for ``obs``: its statistic's ``applies``
    (the ``optional`` fields, e.g. the profile's probe realisations, only the statistic reads)."""
    st = STATISTICS[name]
    return st.applies is None or bool(st.applies(obs, band_width_hz))


def features(name: str, obs: Observations, band_width_hz: float = 5.0) -> np.ndarray:
    """The feature a robust statistic standardises, per sample (N, ...): what the selection fits an
    effect to when the declared model is simplified (``line``: prominence (N, F'', m) [decades];
    ``floor``: level and spread of log10 conditional PSD (N, 2, m) [decades]; ``kurtosis``: excess
    kurtosis (N, m); ``resonance``: log roughness (N, C, m); ``tilt``: log-log slopes (N, m);
    ``profile``: the spectral profile (N, G))."""
    if name == "line":
        return _prominence(obs)
    if name == "floor":
        return np.stack([_floor_level(obs), _floor_spread(obs)], axis=1)
    if name == "kurtosis":
        return obs.stats[:, :, 2]
    if name == "resonance":
        return _roughness_chunks(obs, band_width_hz)
    if name == "tilt":
        return _tilt_slopes(obs)
    if name == "profile":
        return _profile_of(obs, obs.fine)
    raise SpecificationError("statistic", name, f"has no feature; one of {[k for k, s in STATISTICS.items() if s.robust]}")


# -- the statistics --------------------------------------------------------------------------------------


def _scan(obs, band_width_hz, smooth_bins):
    L, _ = _log_psd(obs)
    return np.mean(_loo_z(L, level_free=True) ** 2, axis=2).max(axis=1)


def _scan_peak(obs, band_width_hz, smooth_bins):
    L, fs = _log_psd(obs)
    return float(fs[int(np.argmax(np.mean(_loo_z(L, level_free=True)[0] ** 2, axis=1)))])


def _gof(obs, band_width_hz, smooth_bins):
    L, fs = _log_psd(obs)
    B = np.log10(np.maximum(_group_mean(10.0**L, _bands(fs, band_width_hz)), 1e-300))
    return np.mean(_loo_z(B, level_free=True) ** 2, axis=(1, 2))


def _sharpness(obs, band_width_hz, smooth_bins):
    L, fs = _log_psd(obs)
    rough = (L - uniform_filter1d(L, 2 * smooth_bins + 1, axis=1, mode="nearest")) ** 2
    Q = np.log10(np.maximum(_group_mean(rough, _bands(fs, 4 * band_width_hz)), 1e-300))
    return np.mean(_loo_z(Q, level_free=False) ** 2, axis=(1, 2))


def _line_per_f(obs):
    z = _loo_z(_prominence(obs), level_free=False, floor=SCALE_FLOOR)
    return np.mean(np.clip(z, 0.0, None) ** 2, axis=2)


def _line(obs, band_width_hz, smooth_bins):
    return _line_per_f(obs).max(axis=1)


def _line_peak(obs, band_width_hz, smooth_bins):
    return float(obs.frequency_fine[_line_bins(obs)][int(np.argmax(_line_per_f(obs)[0]))])


def _floor(obs, band_width_hz, smooth_bins):
    z = _loo_z(np.log(np.maximum(_floor_spread(obs), 1e-300)), level_free=False)
    return np.exp(np.clip(-z.mean(axis=1), -EXP_CAP, EXP_CAP))


def _kurtosis(obs, band_width_hz, smooth_bins):
    return (_loo_z(obs.stats[:, :, 2], level_free=False) ** 2).max(axis=1)


def _tilt(obs, band_width_hz, smooth_bins):
    return np.exp(np.minimum(np.abs(_loo_z(_tilt_slopes(obs).mean(axis=1), level_free=False)), EXP_CAP))


def _profile(obs, band_width_hz, smooth_bins):
    return np.exp(np.clip(_loo_z(_profile_projection(obs), level_free=False), -EXP_CAP, EXP_CAP))


def _resonance(obs, band_width_hz, smooth_bins):
    return np.exp(np.minimum(np.abs(_loo_z(_roughness_chunks(obs, band_width_hz), level_free=False).mean(axis=(1, 2))),
                              EXP_CAP))


#: The statistics, by name (variants as data, as scipy's ``METHODS``).
STATISTICS: dict[str, Statistic] = {
    "scan": Statistic(_scan, peak=_scan_peak),
    "gof": Statistic(_gof),
    "sharpness": Statistic(_sharpness),
    "line": Statistic(_line, needs=("fine",), robust=True, effects=("tone",), peak=_line_peak,
                      applies=lambda obs, width: bool(np.any(_line_bins(obs)))),
    "floor": Statistic(_floor, needs=("residual",), robust=True, effects=("sensor_noise",),
                       applies=lambda obs, width: int(np.sum(_floor_bins(obs))) >= FLOOR_MIN_BINS
                       and (obs.segments is None or obs.segments >= 2 * obs.m)),
    "kurtosis": Statistic(_kurtosis, needs=("stats",), robust=True, effects=("stop",)),
    "resonance": Statistic(_resonance, needs=("fine",), robust=True, effects=("damping",),
                           applies=lambda obs, width: bool(np.any(_chunks(obs, width)[1]))),
    "tilt": Statistic(_tilt, needs=("fine",), robust=True, effects=("added_mass",),
                      applies=lambda obs, width: int(np.sum(_tilt_bins(obs))) >= TILT_MIN_BINS),
    "profile": Statistic(_profile, needs=("fine", "probe"), robust=True, effects=("added_mass",),
                         applies=lambda obs, width: _profile_has_bands(obs), optional=("probe",)),
}

#: The statistics a test combines, by what the declared model is taken to be.
MODEL_FORMS: dict[str, tuple[str, ...]] = {
    "exact": ("scan", "gof", "sharpness", "profile"),
    "simplified": ("line", "floor", "kurtosis", "resonance", "tilt", "profile"),
}


def _largest(U: np.ndarray) -> np.ndarray:
    """The combined statistic of the ``exact`` form: the largest standardised value (N, K) → (N,)."""
    return U.max(axis=1)


def _tail_calibrated(U: np.ndarray) -> np.ndarray:
    """The combined statistic of the ``simplified`` form (N, K) → (N,): −log of the smallest, over
    the statistics, of each one's tail probability. Per statistic k, over the N samples: t_k its
    q-quantile (q = :data:`TAIL_QUANTILE`, lowered to 1 − :data:`TAIL_MIN`/N for small N) and β_k
    the mean excess over t_k; a value u ≤ t_k has the fraction of samples at least u, a value
    u > t_k has (1 − q)·exp(−(u − t_k)/β_k). A statistic with a heavier tail (a maximum over
    frequencies or chunks) gets a larger β_k, so its largest realisations outrank a lighter-tailed
    statistic's record at a similar standardised value less often (an exponential tail fitted to a
    power-law one corrects only part of it). Every quantity is a function of the sample's own
    value and of the set of N: the test stays exact."""
    N, K = U.shape
    q = min(TAIL_QUANTILE, 1.0 - TAIL_MIN / N)
    logp = np.empty((N, K))
    for k in range(K):
        u = U[:, k]
        t = float(np.quantile(u, q))
        above = u > t
        beta = max(float(np.mean(u[above] - t)) if np.any(above) else 0.0, 1e-12)
        frac = np.mean(u[None, :] >= u[:, None] - 1e-12 * np.abs(u[:, None]), axis=1)
        logp[:, k] = np.where(above, np.log1p(-q) - (u - t) / beta, np.log(frac))
    return -logp.min(axis=1)


#: How each form's statistics are combined into one per sample (the test's p is its rank).
COMBINATIONS: dict[str, Callable[[np.ndarray], np.ndarray]] = {"exact": _largest, "simplified": _tail_calibrated}


def _as_observations(psd, samples, frequency) -> Observations:
    if isinstance(psd, Observations):
        if samples is not None or frequency is not None:
            raise SpecificationError("samples", Described("arrays beside Observations"),
                                     "give either Observations (record first) or psd, samples and frequency")
        return psd
    P0 = np.asarray(psd, dtype=float)
    S = np.asarray(samples, dtype=float)
    f = np.asarray(frequency, dtype=float)
    if P0.ndim != 2 or S.ndim != 3 or S.shape[1:] != P0.shape or f.shape != (P0.shape[0],):
        raise SpecificationError("samples", Described(f"arrays of shapes {P0.shape}, {S.shape}, {f.shape}"),
                                 "must be psd (F, m), samples (R, F, m) and frequency (F,)")
    return Observations(f, np.concatenate([P0[None], S]))


def detection_test(psd: np.ndarray | Observations, samples: np.ndarray | None = None,
                   frequency: np.ndarray | None = None, *, false_alarm: float = 0.05, band_width_hz: float = 5.0,
                   smooth_bins: int = 4, model_form: str = "exact") -> Detection:
    """The calibrated test of the module docstring.

    Parameters
    ----------
    psd : array (F, m) or Observations
        The record's held-out auto-PSD [m²/Hz, two-sided], on ``frequency``; or
        :class:`Observations` of the record (sample 0) and the realisations, carrying what the
        statistics of ``model_form`` need (then ``samples`` and ``frequency`` are not given).
    samples : array (R, F, m)
        The same estimator on R realisations of the declared stochastic model (R ≥ 9).
    frequency : array (F,)
        Frequencies [Hz], uniform from 0 to the Nyquist frequency.
    false_alarm : float
        The stated rate α in (0, 1): ``detected`` when ``p_value`` ≤ α.
    band_width_hz : float
        Width of the bands of the goodness-of-fit [Hz] (the sharpness and resonance chunks: 4 × this).
    smooth_bins : int
        Half width of the running mean behind the sharpness [bins].
    model_form : str
        ``"exact"`` or ``"simplified"``: the statistics combined (:data:`MODEL_FORMS`).

    Returns
    -------
    Detection
    """
    alpha = open_unit("false_alarm", false_alarm)
    width = positive("band_width_hz", band_width_hz, "Hz")
    h = integer("smooth_bins", smooth_bins, minimum=1)
    obs = _as_observations(psd, samples, frequency)
    names = applicable(one_of("model_form", model_form, MODEL_FORMS), obs, width)
    if not names:
        raise SpecificationError("samples", Described(f"observations for the {model_form!r} test"),
                                 "hold nothing any of its statistics can read (record too short or sampled too slowly)")
    N = obs.n
    if N < 10:
        raise SpecificationError("samples", Described(f"{N - 1} realisations"), "need at least 9")
    for name in names:
        for need in STATISTICS[name].needs + (("frequency_fine",) if "fine" in STATISTICS[name].needs else ()):
            if getattr(obs, need) is None:
                raise SpecificationError("samples", Described(f"observations without {need}"),
                                         f"the {name!r} statistic of the {model_form!r} test needs them")
    T = {k: np.asarray(STATISTICS[k].compute(obs, width, h), dtype=float) for k in names}
    U = np.stack([_loo_z(np.log(np.maximum(T[k], 1e-300))[:, None], level_free=False)[:, 0] for k in names], axis=1)
    p = _rank_p(COMBINATIONS[model_form](U))
    peak = next((STATISTICS[k].peak for k in names if STATISTICS[k].peak is not None), None)
    # the record's residual against all R realisations, for the figure and the signatures
    z_all = None
    if obs.psd is not None:
        L = log10(obs.psd)
        sel = analysis_bins(obs.frequency)
        mu, sd = L[1:, sel].mean(axis=0), L[1:, sel].std(axis=0, ddof=1)
        d = L[0, sel] - mu
        z_all = np.zeros(obs.psd.shape[1:])
        z_all[sel] = (d - d.mean()) / np.maximum(sd, 1e-15)
    return Detection(
        p_value=p, detected=bool(p <= alpha), false_alarm=alpha, size=int(alpha * N + 1e-9) / N,
        p_values={k: _rank_p(T[k]) for k in names}, values={k: float(T[k][0]) for k in names},
        null_median={k: float(np.median(T[k][1:])) for k in names}, excess={k: float(U[0, i]) for i, k in enumerate(names)},
        scan_frequency_hz=float("nan") if peak is None else peak(obs, width, h), n_realisations=N - 1,
        model_form=model_form, z=z_all)
