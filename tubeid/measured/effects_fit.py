"""Trace a residual to a catalog effect: signature scores, trial-grid fits, penalised choice.

**Signatures** (:func:`signature_scores`, no simulation). Each candidate effect is given a cheap
approximate action on the model's confidence band; its score is the fraction of the residual
energy Σ d² (d: the band residual of :func:`tubeid.measured.diagnose.band_residual`) that the best
such action removes, in [0, 1]:

- ``tone``: the band is opened upwards on ±2 bins around one frequency f0 (a line adds power
  there only); f0 scanned over all bins.
- ``sensor_noise``: a white level N [m²/Hz] is added to both band edges on every sensor; N scanned
  on a log grid.
- ``added_mass``: the band is compressed in frequency, B(f) → B(f·s), s = √(1 + a) ∈ (1, 1.6]
  (every resonance moves down by the same factor; the true shift is smaller for modes that
  involve other tubes, so this estimate of a is low).
- ``damping``: peakiness p = log10 PSD minus its running median over ±8 bins (≥ 0). Less damping
  makes the measured spectrum peakier than the model's: the log band is raised by
  c·max(p_meas − p_model, 0), c ∈ (0, 1]; more damping blunts the model's peaks: the band is
  lowered by |c|·p_model. The grid centre is the declared ratio × 0.3 or × 3 accordingly.
- ``stop``: no cheap spectral action (it is non-linear); its score comes from the time-domain
  statistics: at the sensor where both the RMS and the excess kurtosis are lowest against the
  model's realisations (z-scores), min(−z_rms, −z_kurtosis)/10 clipped to [0, 1] — a stop
  near a sensor clips its amplitude distribution.

**Fits** (the ``candidates`` stage of :mod:`tubeid.measured.pipeline`, one runner task per
trial): a small trial grid per effect around the estimate of its signature (:func:`candidate_grid`),
each trial simulated with the mean model on the fitting blocks (common random numbers) and scored
by the level-free log-spectral distance (the mean log offset removed, i.e. the load level
profiled out as for a linear model). Fixed by assumption, not fitted: a tone's location
(``load_x`` on the non-linear tube), an added stop's stiffness (the declared stop's), the tube of
added mass and damping (the tube carrying the sensors).
"""

from __future__ import annotations

import math

import numpy as np

from tubeid.mechanics.effects import AddedMass, Damping, ExtraStop, SensorNoise, Tone

__all__ = ["CATALOG", "PARAMETER_COUNT", "signature_scores", "candidate_grid", "effect_parameters"]

#: Candidate effects, in the catalog's order.
CATALOG = ("tone", "stop", "added_mass", "damping", "sensor_noise")
#: Parameters an effect adds (what the selection penalises).
PARAMETER_COUNT = {"tone": 2, "stop": 2, "added_mass": 1, "damping": 1, "sensor_noise": 1}


def _log(P):
    return np.log10(np.maximum(P, 1e-300))


def _residual(lp, llo, lhi):
    return np.where(lp > lhi, lp - lhi, np.where(lp < llo, lp - llo, 0.0))


def _running_median(a: np.ndarray, half: int) -> np.ndarray:
    """Running median along axis 0 over ±half bins (edges: shorter windows)."""
    out = np.empty_like(a)
    n = a.shape[0]
    for k in range(n):
        out[k] = np.median(a[max(0, k - half): k + half + 1], axis=0)
    return out


def signature_scores(f, meas, lower, upper, median, z_stats, sel, sensor_x, tube_damping: float) -> dict:
    """Score and first estimate of each candidate (see the module docstring).

    f (F,) Hz; meas, lower, upper, median (F, m) m²/Hz; z_stats (m, 3) z-scores of RMS, skewness,
    excess kurtosis; sel (F,) bins compared; sensor_x (m,) positions [m]; tube_damping: the declared
    damping ratio of the sensors' tube. Returns {name: {"score": float, "estimate": {...}}}.
    """
    lp, llo, lhi, lmed = _log(meas), _log(lower), _log(upper), _log(median)
    d = _residual(lp, llo, lhi)[sel]
    total = float(np.sum(d**2))
    out: dict = {}

    def removed(lo_new, hi_new):
        r = _residual(lp, lo_new, hi_new)[sel]
        return 0.0 if total <= 0 else max(0.0, 1.0 - float(np.sum(r**2)) / total)

    # tone: open the band upwards around one frequency
    best = (0.0, float(f[1]))
    idx = np.flatnonzero(sel)
    pos = np.clip(_residual(lp, llo, lhi), 0, None).sum(axis=1)
    for k in idx[np.argsort(-pos[idx])[:10]]:
        hi_new = lhi.copy()
        hi_new[max(0, k - 2): k + 3] = np.inf
        s = removed(llo, hi_new)
        if s > best[0]:
            win = slice(max(0, k - 2), k + 3)
            excess = np.clip(meas[win] - median[win], 0, None).sum(axis=1)
            f0 = float(np.sum(f[win] * excess) / np.sum(excess)) if np.sum(excess) > 0 else float(f[k])
            best = (s, f0)
    out["tone"] = {"score": best[0], "estimate": {"frequency_hz": best[1]}}

    # sensor noise: white level added to the band
    levels = np.logspace(math.floor(np.log10(max(np.min(median[sel]), 1e-300))),
                         math.ceil(np.log10(np.max(meas[sel]))), 41)
    scores = [removed(_log(lower + N), _log(upper + N)) for N in levels]
    k = int(np.argmax(scores))
    out["sensor_noise"] = {"score": float(scores[k]), "estimate": {"level": float(levels[k])}}

    # added mass: compress the band in frequency
    best = (0.0, 0.0)
    for s in np.linspace(1.01, 1.6, 60):
        lo_s = np.stack([np.interp(f * s, f, llo[:, j], right=llo[-1, j]) for j in range(llo.shape[1])], axis=1)
        hi_s = np.stack([np.interp(f * s, f, lhi[:, j], right=lhi[-1, j]) for j in range(lhi.shape[1])], axis=1)
        sc = removed(lo_s, hi_s)
        if sc > best[0]:
            best = (sc, s * s - 1.0)
    out["added_mass"] = {"score": best[0], "estimate": {"factor": best[1]}}

    # damping: peaks sharper (measured peakier than the model) or blunter (model peakier)
    p_model = np.clip(lmed - _running_median(lmed, 8), 0, None)
    p_meas = np.clip(lp - _running_median(lp, 8), 0, None)
    sharper = np.clip(p_meas - p_model, 0, None)
    best = (0.0, 0.0)
    for c in np.linspace(-1.0, 1.0, 21):
        if c == 0:
            continue
        shift = c * sharper if c > 0 else c * p_model
        sc = removed(llo + shift, lhi + shift)
        if sc > best[0]:
            best = (sc, c)
    # Grid centre only: less damping when the measured peaks are sharper (c > 0), more otherwise.
    ratio = float(np.clip(tube_damping * (0.3 if best[1] > 0 else 3.0 if best[1] < 0 else 1.0), 1e-4, 0.5))
    out["damping"] = {"score": best[0], "estimate": {"ratio": ratio}}

    # stop: RMS and kurtosis both low at one sensor
    z = np.asarray(z_stats)
    both = np.minimum(-z[:, 0], -z[:, 2])
    j = int(np.argmax(both))
    out["stop"] = {"score": float(np.clip(both[j] / 10.0, 0.0, 1.0)), "estimate": {"x": float(sensor_x[j]), "sensor": j}}
    return out


def candidate_grid(name: str, estimate: dict, *, tube: str, load_x: float, stop_stiffness: float,
                   sensor_rms, points: int, tone_amplitudes=None) -> list:
    """The trial effects of one candidate around its signature estimate (``points`` per grid).

    tone: ``tone_amplitudes`` [N] (default: log-spaced over 10^0 … 10^3);
    sensor_noise: level × 4^[−1, 1]; added_mass: factor from 0.5× to 3× the stretch estimate
    (≥ 0.02); damping: ratio × 3^[−1, 1] (log grid); stop: gap = RMS at the sensor × 4^[−1.5, 0.5].
    """
    u = np.linspace(-1.0, 1.0, points)
    if name == "tone":
        amps = np.logspace(0, 3, points) if tone_amplitudes is None else np.asarray(tone_amplitudes, float)
        return [Tone(frequency_hz=estimate["frequency_hz"], amplitude=float(a), tube=tube, x=load_x) for a in amps]
    if name == "sensor_noise":
        return [SensorNoise(level=float(estimate["level"] * 4.0**v)) for v in u]
    if name == "added_mass":
        a0 = max(estimate["factor"], 0.02)
        return [AddedMass(tube=tube, factor=float(a0 * m)) for m in np.geomspace(0.5, 3.0, points)]
    if name == "damping":
        return [Damping(tube=tube, ratio=float(min(estimate["ratio"] * 3.0**v, 0.9))) for v in u]
    if name == "stop":
        rms = float(sensor_rms[estimate["sensor"]])
        return [ExtraStop(tube=tube, x=estimate["x"], gap=float(rms * 4.0**v), stiffness=stop_stiffness)
                for v in np.linspace(-1.5, 0.5, points)]
    raise ValueError(name)


def effect_parameters(effect) -> dict:
    """Parameters of an effect with units, as reported: {name: {"value": v, "units": u}}."""
    if isinstance(effect, Tone):
        return {"frequency_hz": {"value": effect.frequency_hz, "units": "Hz"}, "amplitude": {"value": effect.amplitude, "units": "N"},
                "tube": {"value": effect.tube, "units": "", "fitted": False}, "x": {"value": effect.x, "units": "m", "fitted": False}}
    if isinstance(effect, SensorNoise):
        return {"level": {"value": effect.level, "units": "m^2/Hz (two-sided)"}}
    if isinstance(effect, AddedMass):
        return {"tube": {"value": effect.tube, "units": "", "fitted": False}, "factor": {"value": effect.factor, "units": "1"}}
    if isinstance(effect, Damping):
        return {"tube": {"value": effect.tube, "units": "", "fitted": False}, "ratio": {"value": effect.ratio, "units": "1"}}
    if isinstance(effect, ExtraStop):
        return {"tube": {"value": effect.tube, "units": "", "fitted": False}, "x": {"value": effect.x, "units": "m"},
                "gap": {"value": effect.gap, "units": "m"}, "stiffness": {"value": effect.stiffness, "units": "N/m", "fitted": False}}
    return {}
