"""Detection as a calibrated test: is the held-out record a realisation of the declared model?

H0: the held-out auto-PSDs of the record (F frequencies × m sensors) are one more realisation of
the declared stochastic model, whose R realisations (same block layout, same estimator) are given.
Three statistics look for what the model lacks, each computed for every one of the N = R + 1
samples (the record and the R realisations) against the *other* N − 1 samples only:

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

The level is removed from every sample because it is what the load identification fits (r) and
carries its error; the statistics see the spectra's shape. Each statistic's p-value is the
fraction of the N samples whose statistic is at least the record's; the three are combined by the
largest of their log values standardised (again against the other samples): p is that combined
statistic's rank. Every statistic of sample i is a fixed function of sample i and of the *set* of
the others, so under H0 (the N samples exchangeable) the record's rank is uniform on 1..N and
P(p ≤ α) = ⌊αN⌋/N ≤ α exactly, whatever the statistics' distributions — no Gaussian or
independence assumption, a Monte Carlo (conformal) test. With R = 39, α = 0.05: exactly 5 %.

What H0 does not cover: the load level r and δ_F are identified on the fitting blocks of the same
record, so the record is exchangeable with the realisations only up to that fit (the level is
removed; the shape's dependence on r through the stop is second order); a given δ larger than the
truth makes the test conservative (fewer false alarms than stated), a smaller one anti-conservative.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import uniform_filter1d

from tubeid._validation import integer, open_unit, positive
from tubeid.diagnose._spectra import analysis_bins, log10
from tubeid.errors import Described, SpecificationError

__all__ = ["Detection", "detection_test", "band_moments", "STATISTICS"]

#: The statistics of the test, in the order they are reported.
STATISTICS = ("scan", "gof", "sharpness")


@dataclass(frozen=True)
class Detection:
    """The result of :func:`detection_test`.

    ``p_value``: the combined test's p-value; ``detected``: ``p_value`` ≤ ``false_alarm``;
    ``size``: the exact false-alarm rate ⌊αN⌋/N; ``p_values``, ``statistics`` (the record's) and
    ``null_median`` (the realisations'): per statistic of :data:`STATISTICS`;
    ``scan_frequency_hz``: where the record's scan statistic peaks; ``z`` (F, m): the record's
    standardised residual against all R realisations (level removed; 0 at DC and Nyquist);
    ``n_realisations``: R.
    """

    p_value: float
    detected: bool
    false_alarm: float
    size: float
    p_values: dict
    statistics: dict
    null_median: dict
    scan_frequency_hz: float
    n_realisations: int
    z: np.ndarray = field(repr=False)

    def to_dict(self) -> dict:
        """Plain values for report.json (without ``z``)."""
        return {"p_value": self.p_value, "detected": self.detected, "false_alarm": self.false_alarm,
                "size": self.size, "p_values": dict(self.p_values), "statistics": dict(self.statistics),
                "null_median": dict(self.null_median), "scan_frequency_hz": self.scan_frequency_hz,
                "n_realisations": self.n_realisations}


def band_moments(samples) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation (ddof 1) over realisations of log10 PSD: samples (R, F, m) →
    (F, m), (F, m) [decades]."""
    L = log10(samples)
    return L.mean(axis=0), L.std(axis=0, ddof=1)


def _loo_z(X: np.ndarray, level_free: bool) -> np.ndarray:
    """X (N, ...) → z (N, ...): each sample standardised by the mean and std (ddof 1) of the
    others, after removing its own mean offset from them when ``level_free``."""
    N = X.shape[0]
    X = X - X.mean(axis=0)  # shift-invariant; keeps the sums well conditioned
    s1, s2 = X.sum(axis=0), (X**2).sum(axis=0)
    mu = (s1[None] - X) / (N - 1)
    var = ((s2[None] - X**2) - (N - 1) * mu**2) / (N - 2)
    d = X - mu
    if level_free:
        d = d - d.reshape(N, -1).mean(axis=1).reshape((N,) + (1,) * (X.ndim - 1))
    return d / np.sqrt(np.maximum(var, 1e-30))


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


def detection_test(psd, samples, frequency, *, false_alarm: float = 0.05, band_width_hz: float = 5.0,
                   smooth_bins: int = 4) -> Detection:
    """The calibrated test of the module docstring.

    Parameters
    ----------
    psd : array (F, m)
        The record's held-out auto-PSD [m²/Hz, two-sided], on ``frequency``.
    samples : array (R, F, m)
        The same estimator on R realisations of the declared stochastic model (R ≥ 9).
    frequency : array (F,)
        Frequencies [Hz], uniform from 0 to the Nyquist frequency.
    false_alarm : float
        The stated rate α in (0, 1): ``detected`` when ``p_value`` ≤ α.
    band_width_hz : float
        Width of the bands of the goodness-of-fit [Hz] (the sharpness uses 4 × this).
    smooth_bins : int
        Half width of the running mean behind the sharpness [bins].

    Returns
    -------
    Detection
    """
    alpha = open_unit("false_alarm", false_alarm)
    width = positive("band_width_hz", band_width_hz, "Hz")
    h = integer("smooth_bins", smooth_bins, minimum=1)
    P0 = np.asarray(psd, dtype=float)
    S = np.asarray(samples, dtype=float)
    f = np.asarray(frequency, dtype=float)
    if P0.ndim != 2 or S.ndim != 3 or S.shape[1:] != P0.shape or f.shape != (P0.shape[0],):
        raise SpecificationError("samples", Described(f"arrays of shapes {P0.shape}, {S.shape}, {f.shape}"),
                                 "must be psd (F, m), samples (R, F, m) and frequency (F,)")
    if S.shape[0] < 9:
        raise SpecificationError("samples", Described(f"{S.shape[0]} realisations"), "need at least 9")
    sel = analysis_bins(f)
    N = S.shape[0] + 1
    L = log10(np.concatenate([P0[None], S]))[:, sel]          # (N, F', m)
    fs = f[sel]
    # scan: narrow lines
    z = _loo_z(L, level_free=True)
    per_f = np.mean(z**2, axis=2)                                # (N, F')
    scan = per_f.max(axis=1)
    # gof: log band energies
    idx = _bands(fs, width)
    B = np.log10(np.maximum(_group_mean(10.0**L, idx), 1e-300))
    gof = np.mean(_loo_z(B, level_free=True) ** 2, axis=(1, 2))
    # sharpness: log roughness per chunk of 4 bands
    rough = (L - uniform_filter1d(L, 2 * h + 1, axis=1, mode="nearest")) ** 2
    Q = np.log10(np.maximum(_group_mean(rough, _bands(fs, 4 * width)), 1e-300))
    sharp = np.mean(_loo_z(Q, level_free=False) ** 2, axis=(1, 2))
    T = {"scan": scan, "gof": gof, "sharpness": sharp}
    U = np.stack([_loo_z(np.log(T[k])[:, None], level_free=False)[:, 0] for k in STATISTICS], axis=1)
    p = _rank_p(U.max(axis=1))
    # the record's residual against all R realisations, for the figure and the signatures
    mu, sd = L[1:].mean(axis=0), L[1:].std(axis=0, ddof=1)
    d = L[0] - mu
    z_all = np.zeros(P0.shape)
    z_all[sel] = (d - d.mean()) / np.maximum(sd, 1e-15)
    return Detection(
        p_value=p, detected=bool(p <= alpha), false_alarm=alpha, size=int(alpha * N + 1e-9) / N,
        p_values={k: _rank_p(T[k]) for k in STATISTICS}, statistics={k: float(T[k][0]) for k in STATISTICS},
        null_median={k: float(np.median(T[k][1:])) for k in STATISTICS},
        scan_frequency_hz=float(fs[int(np.argmax(per_f[0]))]), n_realisations=N - 1, z=z_all)
