"""Which catalog effects leave a record inside the declared simplified model's band (not a test).

    python benchmarks/effect_inside_band.py [CASE,...] [SEED,...] [--delta D] [--realisations R]

For each case of ``studies/diagnose_effects.py``'s ``CASES`` (default: the simplified campaign's
control, tone, stop, added_mass, damping, sensor_noise; ``added_mass_xF``: the centre tube's density
× F) and seed, a 220 s record of the reference
model with the effect written by hand (``tubeid.diagnose.testing.make_record``, 7 sensors c02–c14),
and R realisations (default 40) of ``paper-simplified`` with the same sensors at δ (default 0.627,
MODEL.md §2's δ_opt) under the record's own load (coherent forces, 1.3 N²/Hz: the true level, so
this isolates the model's band from the load identification). Printed per record: the fraction of
the (0, 100] Hz bins of all sensors' auto-PSDs (Welch, 8 s) inside the model's 2.5–97.5 % band, over
0–35 and 35–100 Hz too; then the same fraction for each model realisation against the others' band
(leave one out: what a draw of the model scores). An effect whose records score like the control is
inside the model's uncertainty: no test of "outside the band" can name it without alarming on the
control as often. Then, per 20 Hz chunk, the log-frequency shift (−25 … +25 %) that best correlates
the record's smoothed log-PSDs with the model's mean, in standard deviations of the same shift over
the model's realisations (a frequency signature the band's coverage cannot see); and the tilt, the
least-squares slope of log10 PSD against log10 f over 2–100 Hz averaged over the sensors (what
the simplified form's ``tilt`` statistic reads), in standard deviations of the model's; and the
profile projection (what the ``profile`` statistic reads, computed here apart from its code): the
sensors' mean of log10 of the mean power in 1 Hz bands over 2–100 Hz, level removed, projected on
C⁻¹(p̄ − μ), μ and C (shrunk by 0.3 towards its mean variance) of the first half of the model's
realisations, p̄ the mean profile of 20 realisations of the model with the centre tube's density ×
1.25 (the probe), in standard deviations of the projection over the second half.
"""

from __future__ import annotations

import argparse
import importlib.util
import pathlib

import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]
DEFAULT_CASES = "control,tone,stop,added_mass,damping,sensor_noise"


def _cases():
    spec = importlib.util.spec_from_file_location("diagnose_effects", REPO / "studies" / "diagnose_effects.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.CASES


def _coverage(P, lo, hi, f):
    inside = (P >= lo) & (P <= hi)
    return inside.mean(), inside[f <= 35].mean(), inside[f > 35].mean()


CHUNKS = ((2.0, 20.0), (20.0, 40.0), (40.0, 60.0), (60.0, 80.0))  # a shifted 80-100 Hz chunk would leave the band
SHIFTS = np.linspace(-0.25, 0.25, 101)


def _smooth(L, k=8):
    kernel = np.ones(k) / k
    return np.apply_along_axis(lambda v: np.convolve(v, kernel, mode="same"), 0, L)


def _shifts(L, mean, f):
    """Best log-frequency shift per chunk of log-PSDs L (F, sensors) against the model's mean."""
    S = _smooth(L)
    out = []
    for lo, hi in CHUNKS:
        sel = (f > lo) & (f <= hi)
        A = S[sel] - S[sel].mean(0)
        score = []
        for c in SHIFTS:
            M = np.stack([np.interp(f[sel] * np.exp(c), f, mean[:, j]) for j in range(mean.shape[1])], 1)
            B = M - M.mean(0)
            score.append(np.sum(A * B) / np.sqrt(np.sum(A * A) * np.sum(B * B)))
        out.append(SHIFTS[int(np.argmax(score))])
    return np.array(out)


def _tilt(P, f):
    """Mean over sensors of the least-squares slope of log10 PSD against log10 f over 2–100 Hz."""
    sel = (f >= 2.0) & (f <= 100.0)
    return float(np.mean(np.polyfit(np.log10(f[sel]), np.log10(P[sel]), 1)[0]))


def _profile(P, f):
    """Sensor-mean log10 of the mean power per 1 Hz band over 2–100 Hz, level removed: P (R, F, m) → (R, G)."""
    sel = (f >= 2.0) & (f <= 100.0)
    band = np.floor(f[sel] + 1e-9).astype(int)
    L = np.stack([np.log10(P[:, sel][:, band == b].mean(axis=1)).mean(axis=1) for b in np.unique(band)], axis=1)
    return L - L.mean(axis=1, keepdims=True)


def main() -> None:
    """Print the coverage of each record and of the model's own draws."""
    from tubeid.diagnose.testing import make_record, sensors
    from tubeid.dynamics.response import ResponseSettings, simulate_responses
    from tubeid.dynamics.spectra import psd_matrix
    from tubeid.mechanics.library import builtin_spec
    from tubeid.mechanics.reduction import reduce
    from tubeid.uncertainty.loads import coherent_forces
    from tubeid.uncertainty.random_matrices import Dispersion

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("cases", nargs="?", default=DEFAULT_CASES, help="comma-separated case names")
    p.add_argument("seeds", nargs="?", default="1,2,3", help="comma-separated record seeds")
    p.add_argument("--delta", type=float, default=0.627, help="dispersion of the simplified model's K_B")
    p.add_argument("--realisations", type=int, default=40, help="realisations of the simplified model")
    a = p.parse_args()
    cases = _cases()
    xs = (2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0)
    model = reduce(builtin_spec("paper-simplified").replace(sensors=sensors(xs)))
    ds = simulate_responses(model, coherent_forces(level=1.3), range(a.realisations), seed=2026,
                            dispersion=Dispersion(stiffness=a.delta), settings=ResponseSettings(segment_seconds=8.0))
    f = ds.frequency.values
    sel = (f > 0) & (f <= 100)
    P = np.real(np.diagonal(ds.psd.values, axis1=-2, axis2=-1))[:, sel]  # (R, F, sensors)
    lo, hi = np.percentile(P, [2.5, 97.5], axis=0)
    fs = f[sel][:, None] * np.ones(P.shape[-1])
    fb = f[sel]
    mean = np.mean([_smooth(np.log(x)) for x in P], axis=0)
    model_shifts = np.array([_shifts(np.log(x), mean, fb) for x in P])
    mu, sd = model_shifts.mean(0), model_shifts.std(0, ddof=1)
    tilts = np.array([_tilt(x, fb) for x in P])
    from tubeid.diagnose.testing import HandEffects

    probe = simulate_responses(reduce(HandEffects(density={"centre": 1.25}).spec(builtin_spec("paper-simplified")
                                                                                .replace(sensors=sensors(xs)))),
                               coherent_forces(level=1.3), range(10_000, 10_020), seed=2026,
                               dispersion=Dispersion(stiffness=a.delta), settings=ResponseSettings(segment_seconds=8.0))
    X = _profile(P, fb)
    half = X.shape[0] // 2
    mu_p = X[:half].mean(axis=0)
    C = np.cov(X[:half], rowvar=False)
    C = 0.7 * C + 0.3 * np.mean(np.diag(C)) * np.eye(C.shape[0])
    probe_profile = _profile(np.real(np.diagonal(probe.psd.values, axis1=-2, axis2=-1))[:, sel], fb).mean(axis=0)
    w = np.linalg.solve(C, probe_profile - mu_p)
    proj = (X[half:] - mu_p) @ w
    print(f"paper-simplified at delta = {a.delta}, {a.realisations} realisations; coverage 0-100 / 0-35 / 35-100 Hz; "
          f"frequency shift per chunk {CHUNKS} in model standard deviations (those: {np.round(sd, 3).tolist()}); "
          f"tilt in model standard deviations (the model's: mean {tilts.mean():.3f}, standard deviation "
          f"{tilts.std(ddof=1):.3f} decade per decade); profile projection in standard deviations of the second half's")
    for case in a.cases.split(","):
        if case.startswith("added_mass_x") and case not in cases:

            effects, positions = HandEffects(density={"centre": float(case.removeprefix("added_mass_x"))}), xs
        else:
            effects, _, positions, _ = cases[case]
        for seed in (int(s) for s in a.seeds.split(",")):
            rec = make_record("paper-reference", effects, xs=positions, seed=seed)
            fr, S = psd_matrix(rec.displacement.values, 3e-3, segment_seconds=8.0)
            R = np.real(np.diagonal(S, axis1=-2, axis2=-1))[(fr > 0) & (fr <= 100)]
            c = _coverage(R, lo, hi, fs)
            z = (_shifts(np.log(R), mean, fb) - mu) / sd
            t = (_tilt(R, fb) - tilts.mean()) / tilts.std(ddof=1)
            pr = (float((_profile(R[None], fb)[0] - mu_p) @ w) - proj.mean()) / proj.std(ddof=1)
            print(f"{case:14s} seed {seed}: {c[0]:.3f} / {c[1]:.3f} / {c[2]:.3f}   shifts {np.round(z, 1).tolist()}"
                  f"   tilt {t:+.2f}   profile {pr:+.2f}", flush=True)
    own = []
    for i in range(P.shape[0]):
        rest = np.delete(P, i, axis=0)
        lo_i, hi_i = np.percentile(rest, [2.5, 97.5], axis=0)
        own.append(_coverage(P[i], lo_i, hi_i, fs)[0])
    q = np.percentile(own, [5, 50, 95])
    print(f"the model's own draws (leave one out), 0-100 Hz: 5 / 50 / 95 % quantiles {q[0]:.3f} / {q[1]:.3f} / {q[2]:.3f}")
    zmax = [np.max(np.abs((model_shifts[i] - np.delete(model_shifts, i, 0).mean(0)) / np.delete(model_shifts, i, 0).std(0, ddof=1)))
            for i in range(len(model_shifts))]
    q = np.percentile(zmax, [50, 90, 95])
    print(f"the model's own draws (leave one out), largest |shift| over the chunks in standard deviations: "
          f"50 / 90 / 95 % quantiles {q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f}")


if __name__ == "__main__":
    main()
