"""Random reduced models of the linear subsystem B (nonparametric approach) and their functionals.

The mean reduced matrices (M_B, D_B, K_B) of subsystem B are replaced by SE+ random matrices
A = L_Aᵀ G L_A with independent germs G ∈ SG+ for mass, damping and stiffness, with dispersions
``Dispersion(mass, damping, stiffness)`` (0 = deterministic). Realisation r draws its germs from
``rng_for(seed, "subsystem-B", r)``: they do not depend on δ, so a grid of δ shares common random
numbers (the gamma variates are drawn by inverse CDF, see ``sg_plus_from_germs``).

Everything here is vectorised over realisations (and frequencies for Z).
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from tubeid.errors import SpecificationError
from tubeid.mechanics.reduction import J_UNITS, ReducedSubsystem, condensed_stiffness, j_functional
from tubeid.seeds import rng_for
from tubeid.uncertainty.random_matrices import Dispersion, _check_mean, sg_plus_from_germs, sg_plus_germs

__all__ = ["germs_from_rngs", "random_subsystem", "random_j", "j_monte_carlo", "random_condensed_stiffness"]

_MATRICES = ("mass", "damping", "stiffness")


def germs_from_rngs(n: int, rngs) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """SG+ germs of the mass, damping and stiffness matrices, one generator per realisation.

    Each realisation's generator yields, in this fixed order, the mass, damping and stiffness
    germs, so a realisation's matrices never depend on the other realisations of its batch.
    """
    out = {k: ([], []) for k in _MATRICES}
    for rng in rngs:
        for k in _MATRICES:
            z, u = sg_plus_germs(n, rng=rng)
            out[k][0].append(z)
            out[k][1].append(u)
    return {k: (np.array(z).reshape(len(z), -1), np.array(u).reshape(len(u), -1)) for k, (z, u) in out.items()}


def _germs(n: int, seed: int, realisations) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    return germs_from_rngs(n, (rng_for(seed, "subsystem-B", int(r)) for r in realisations))


def random_subsystem(sub: ReducedSubsystem, dispersion: Dispersion, seed: int, realisations, *, germs=None):
    """Random (M_B, D_B, K_B), each of shape (R, n, n), for the given realisation indices.

    ``germs`` (from :func:`germs_from_rngs`) replaces the draws from ``(seed, realisation)``.
    Deterministic matrices (dispersion 0) are broadcast views of the mean.
    """
    realisations = np.atleast_1d(np.asarray(realisations, dtype=int))
    n = sub.n
    dispersion.check(n)
    germs = _germs(n, seed, realisations) if germs is None else germs
    out = []
    for k, mean, name in zip(_MATRICES, (sub.M, sub.D, sub.K), ("M_B", "D_B", "K_B")):
        delta = getattr(dispersion, k)
        if delta == 0.0:
            out.append(np.broadcast_to(mean, (len(realisations), n, n)))
            continue
        LA = _check_mean(mean, name)
        G = sg_plus_from_germs(n, delta, *germs[k])
        A = LA.T @ G @ LA
        out.append(0.5 * (A + np.swapaxes(A, -1, -2)))
    return tuple(out)


def random_j(sub: ReducedSubsystem, dispersion: Dispersion, seed: int, realisations, band_hz: float) -> np.ndarray:
    """J [m²·rad/(N²·s)] of each random realisation, shape (R,)."""
    M, D, K = random_subsystem(sub, dispersion, seed, realisations)
    return j_functional(M, D, K, sub.n_c, band_hz)


def j_monte_carlo(sub: ReducedSubsystem, deltas, seed: int, realisations, band_hz: float, which: str = "stiffness") -> xr.DataArray:
    """Monte Carlo of J(δ) over a δ grid with common random numbers: DataArray (delta, realisation).

    ``which``: the randomised matrix ("stiffness" as in the paper, "mass", "damping" or "all").
    """
    if which not in (*_MATRICES, "all"):
        raise SpecificationError("which", which, f"must be one of {(*_MATRICES, 'all')}")
    deltas = np.asarray(deltas, dtype=float)
    if deltas.ndim != 1 or deltas.size == 0:
        raise SpecificationError("deltas", deltas.tolist(), "must be a non-empty 1-D grid")
    realisations = np.atleast_1d(np.asarray(realisations, dtype=int))
    germs = _germs(sub.n, seed, realisations)
    J = np.empty((deltas.size, realisations.size))
    for i, d in enumerate(deltas):
        disp = Dispersion(**({k: d for k in _MATRICES} if which == "all" else {which: d}))
        J[i] = j_functional(*random_subsystem(sub, disp, seed, realisations, germs=germs), sub.n_c, band_hz)
    return xr.DataArray(
        J,
        dims=("delta", "realisation"),
        coords={"delta": deltas, "realisation": realisations},
        name="J",
        attrs={"units": J_UNITS, "long_name": "J = ∫ ‖Z(ω)⁻¹‖²_F dω", "band_hz": band_hz, "randomised": which, "seed": seed},
    )


def random_condensed_stiffness(sub: ReducedSubsystem, dispersion: Dispersion, seed: int, realisations, frequency_hz) -> xr.DataArray:
    """Random Z(ω) [N/m]: DataArray (realisation, frequency, interface, interface_)."""
    realisations = np.atleast_1d(np.asarray(realisations, dtype=int))
    f = np.asarray(frequency_hz, dtype=float)
    M, D, K = random_subsystem(sub, dispersion, seed, realisations)
    Z = condensed_stiffness(M, D, K, sub.n_c, 2 * np.pi * f)
    return xr.DataArray(
        Z,
        dims=("realisation", "frequency", "interface", "interface_"),
        coords={"realisation": realisations, "frequency": f},
        name="Z",
        attrs={"units": "N/m", "frequency_units": "Hz"},
    )
