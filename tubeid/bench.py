"""``tubeid bench``: speed of the hot paths, as ratios against straightforward baselines run in
the same process (never timed assertions). Sections:

* ``j`` — Monte Carlo of J(δ): vectorised closed-form J (poles of B, batched over realisations)
  against a straightforward loop over realisations and frequencies (Simpson on 2001 points of
  [0, Ω], relative quadrature error 5e-4 on the mean model — already less accurate than the
  closed form, which agrees with refined quadrature to 1e-9).
* ``transient`` — 220 s realisations of the simplified model, 4 per solver call as in the paper
  study (see ``tubeid.dynamics.bench``); ``--compile-time`` adds the kernels' compilation time in a
  new process with an empty numba cache.
"""

from __future__ import annotations

import json
import time

import numpy as np

__all__ = ["bench_j", "register"]


def _baseline_j(M, D, K, n_c: int, band_hz: float, n_freq: int = 2001) -> float:
    import scipy.integrate

    omega = np.linspace(0.0, 2 * np.pi * band_hz, n_freq)
    g = np.empty(n_freq)
    n = M.shape[0]
    y, c = slice(0, n - n_c), slice(n - n_c, n)
    for i, w in enumerate(omega):
        A = K - w * w * M + 1j * w * D
        Z = A[c, c] - A[c, y] @ np.linalg.solve(A[y, y], A[y, c])
        g[i] = np.sum(np.abs(np.linalg.inv(Z)) ** 2)
    return 2.0 * scipy.integrate.simpson(g, x=omega)


def bench_j(n_realisations: int = 200, n_deltas: int = 10, n_baseline: int = 4, seed: int = 1) -> dict:
    """J evaluations per second (vectorised) and the speedup over the straightforward loop.

    Parameters
    ----------
    n_realisations : int
        Realisations of B per δ in the vectorised Monte Carlo, >= 1.
    n_deltas : int
        Dispersions δ, >= 1, evenly spaced from 0.05 to 0.95 δ_max of ``paper-simplified``'s B.
    n_baseline : int
        Realisations (at the largest δ) the loop computes, in [1, n_realisations]: the first ones of the
        Monte Carlo, against which ``j_baseline_relative_difference`` is taken.
    seed : int
        Seed of the realisations, >= 0.

    Returns
    -------
    dict
        ``j_evaluations_per_second`` (vectorised), ``j_baseline_evaluations_per_second`` (loop),
        ``j_speedup`` (their ratio), ``j_baseline_relative_difference`` (largest relative difference of
        the loop's J from the closed form's, same realisations), ``j_monte_carlo`` (what was timed).
    """
    from tubeid._validation import integer, seed as _seed
    from tubeid.mechanics.library import builtin_spec
    from tubeid.mechanics.reduction import reduce
    from tubeid.uncertainty.random_matrices import Dispersion, delta_max
    from tubeid.uncertainty.random_models import j_monte_carlo, random_subsystem

    n_realisations = integer("n_realisations", n_realisations, minimum=1)
    n_deltas = integer("n_deltas", n_deltas, minimum=1)
    n_baseline = integer("n_baseline", n_baseline, minimum=1, maximum=n_realisations)
    seed = _seed("seed", seed)
    sub = reduce(builtin_spec("paper-simplified")).subsystem
    deltas = np.linspace(0.05, 0.95 * delta_max(sub.n), n_deltas)  # inside the admissible set of this B
    j_monte_carlo(sub, deltas[:1], seed, np.arange(4), 100.0)  # warm-up
    t0 = time.perf_counter()
    J = j_monte_carlo(sub, deltas, seed, np.arange(n_realisations), 100.0)
    t_fast = time.perf_counter() - t0
    M, D, K = random_subsystem(sub, Dispersion(stiffness=float(deltas[-1])), seed, np.arange(n_baseline))
    t0 = time.perf_counter()
    Jb = np.array([_baseline_j(M[r], D[r], K[r], sub.n_c, 100.0) for r in range(n_baseline)])
    t_base = (time.perf_counter() - t0) / n_baseline
    rel = float(np.max(np.abs(Jb / J.isel(delta=-1).values[:n_baseline] - 1)))
    fast = J.size / t_fast
    return {
        "j_evaluations_per_second": fast,
        "j_baseline_evaluations_per_second": 1.0 / t_base,
        "j_speedup": fast * t_base,
        "j_baseline_relative_difference": rel,
        "j_monte_carlo": f"{n_deltas} deltas x {n_realisations} realisations, n_reduced={sub.n}",
    }


#: How a refusal names ``bench_transient``'s arguments that the command line sets.
OPTIONS = {"psd_sets": "--psd-sets", "dt_load": "--dt-load"}


def _run(args) -> int:
    from tubeid.errors import SpecificationError

    transient = {"psd_sets": args.psd_sets, "dt_load": args.dt_load}
    if args.section == "j":  # an option of the other section is refused, not ignored
        given = [(OPTIONS[k], v) for k, v in transient.items() if v is not None]
        given += [("--compile-time", True)] if args.compile_time else []
        if given:
            raise SpecificationError(given[0][0], given[0][1], "applies to the transient section only "
                                     "(tubeid bench transient, or tubeid bench for both sections)")
    transient = {k: v for k, v in transient.items() if v is not None}
    out: dict = {}
    if args.section in ("transient", "all"):
        from tubeid.dynamics.bench import bench_transient, check_transient

        check_transient(**transient, names=OPTIONS)  # before any section runs
    if args.section in ("j", "all"):
        out.update(bench_j())
    if args.section in ("transient", "all"):
        out.update(bench_transient(compile_time=args.compile_time, names=OPTIONS, **transient))
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        w = max(len(k) for k in out)
        for k, v in out.items():
            print(f"{k:<{w}}  {v:.4g}" if isinstance(v, float) else f"{k:<{w}}  {v}")
    return 0


def register(sub) -> None:
    p = sub.add_parser("bench", help="benchmark the hot paths against in-process baselines")
    p.add_argument("section", nargs="?", default="all", choices=("all", "j", "transient"),
                   help="what to benchmark: j (Monte Carlo of J), transient (realisations of the solver chain), all (default)")
    p.add_argument("--json", action="store_true", help="print a JSON object")
    p.add_argument("--compile-time", action="store_true",
                   help="transient: also time the solver's compilation in a new process (empty numba cache)")
    p.add_argument("--psd-sets", type=int, default=None, metavar="N",
                   help="transient: the step error of the PSD over N independent sets of realisations (its scatter; "
                        "default 1)")
    p.add_argument("--dt-load", type=float, default=None, metavar="S",
                   help="transient: the load sampling [s] (default: the response settings')")
    p.set_defaults(func=_run)
