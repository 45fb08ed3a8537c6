"""Random reduced models of the linear subsystem B (nonparametric approach) and their functionals.

The mean reduced matrices (M_B, D_B, K_B) of subsystem B are replaced by SE+ random matrices
A = L_Aᵀ G L_A with independent germs G ∈ SG+ for mass, damping and stiffness, with dispersions
``Dispersion(mass, damping, stiffness)`` (0 = deterministic). Realisation r draws its germs from
``rng_for(seed, "subsystem-B", r)``: they do not depend on δ, so a grid of δ shares common random
numbers (the gamma variates are drawn by inverse CDF, see ``sg_plus_from_germs``).

Everything here is vectorised over realisations (and frequencies for Z).
"""

from __future__ import annotations

import numbers
from collections.abc import Iterable

import numpy as np
import xarray as xr
from numpy.typing import ArrayLike

from tubeid._validation import numeric_array, positive
from tubeid._validation import seed as _seed
from tubeid.errors import Described, SpecificationError
from tubeid.mechanics.reduction import J_UNITS, ReducedSubsystem, condensed_stiffness, j_functional
from tubeid.seeds import rng_for
from tubeid.uncertainty.random_matrices import Dispersion, _check_mean, sg_plus_from_germs, sg_plus_germs

__all__ = ["germs_from_rngs", "random_subsystem", "random_j", "j_monte_carlo", "random_condensed_stiffness"]

_MATRICES = ("mass", "damping", "stiffness")
_INT64 = np.iinfo(np.int64)


def realisation_indices(realisations, field: str = "realisations") -> np.ndarray:
    """Realisation indices as a 1-D int array: at least one, distinct integers (never bools or floats).

    An index names a realisation and keys its random streams, so a float (1.9 would be read as 1)
    or a repeated index (the same realisation twice, presented as two) is refused, not truncated.
    Negative indices are keys like any other (the diagnosis labels its probe realisations -2, -3, ...).

    Parameters
    ----------
    realisations : array_like of int
        The indices.
    field : str
        The argument's name in error messages.

    Returns
    -------
    numpy.ndarray
        ``np.asarray(realisations, dtype=int)``, at least 1-D.
    """
    rule = "must be distinct integers (not bools or floats), at least one, in a 1-D sequence"
    try:
        raw = np.atleast_1d(np.asarray(realisations))
    except (TypeError, ValueError):
        raise SpecificationError(field, Described(type(realisations).__name__), rule) from None
    if raw.ndim != 1 or raw.size == 0:
        raise SpecificationError(field, realisations if raw.size <= 8 else Described(f"array of shape {raw.shape}"), rule)
    if raw.dtype.kind == "O":  # Python ints beyond int64, or mixed objects
        if not all(isinstance(v, (numbers.Integral, np.integer)) and not isinstance(v, (bool, np.bool_))
                   and _INT64.min <= v <= _INT64.max for v in raw):
            raise SpecificationError(field, realisations, rule + " within the int64 range")
    elif raw.dtype.kind not in "iu" or (raw.dtype.kind == "u" and raw.max() > _INT64.max):
        raise SpecificationError(field, realisations if raw.size <= 8 else Described(f"array of dtype {raw.dtype}"),
                                 rule)
    out = np.asarray(raw.tolist() if raw.dtype.kind == "O" else raw, dtype=int)
    uniq, counts = np.unique(out, return_counts=True)
    if np.any(counts > 1):
        raise SpecificationError(field, realisations if out.size <= 8 else Described(f"{out.size} indices"),
                                 f"must be distinct: index {int(uniq[np.argmax(counts > 1)])} is repeated (one "
                                 "index is one realisation: a repeat would duplicate it)")
    return out


def _check_dispersion(dispersion) -> Dispersion:
    if not isinstance(dispersion, Dispersion):
        raise SpecificationError("dispersion", dispersion, "must be a tubeid.uncertainty.Dispersion "
                                 "(e.g. Dispersion(stiffness=0.1))")
    return dispersion


def germs_from_rngs(n: int, rngs: Iterable[np.random.Generator]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """SG+ germs of the mass, damping and stiffness matrices, one generator per realisation.

    Each realisation's generator yields, in this fixed order, the mass, damping and stiffness
    germs, so a realisation's matrices never depend on the other realisations of its batch.

    Parameters
    ----------
    n : int
        Size of the reduced matrices.
    rngs : iterable of numpy.random.Generator
        One generator per realisation (R of them).

    Returns
    -------
    dict
        ``{"mass" | "damping" | "stiffness": (normals (R, n(n−1)/2), uniforms (R, n))}``.
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


def random_subsystem(sub: ReducedSubsystem, dispersion: Dispersion, seed: int, realisations: ArrayLike, *,
                     germs: dict[str, tuple[np.ndarray, np.ndarray]] | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random reduced matrices of B for the given realisation indices.

    Parameters
    ----------
    sub : ReducedSubsystem
        The mean reduced subsystem B.
    dispersion : Dispersion
        δ of each matrix (0 keeps it deterministic); checked against ``delta_max(n)``.
    seed : int
        Study seed, an integer >= 0: realisation r draws from ``rng_for(seed, "subsystem-B", r)``
        (unused when ``germs`` are given).
    realisations : array_like of int
        Realisation indices (R of them): distinct integers (:func:`realisation_indices`).
    germs : dict, optional
        Germs from :func:`germs_from_rngs`, used instead of the draws from (seed, realisation).

    Returns
    -------
    tuple of numpy.ndarray
        (M_B, D_B, K_B), each (R, n, n); a deterministic matrix is a broadcast view of the mean.
    """
    realisations = realisation_indices(realisations)
    n = sub.n
    _check_dispersion(dispersion).check(n)
    if germs is None:
        _seed("seed", seed)
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


def random_j(sub: ReducedSubsystem, dispersion: Dispersion, seed: int, realisations: ArrayLike,
             band_hz: float) -> np.ndarray:
    """J of each random realisation of B.

    Parameters
    ----------
    sub : ReducedSubsystem
        The mean reduced subsystem B.
    dispersion : Dispersion
        δ of each matrix.
    seed : int
        Study seed (see :func:`random_subsystem`).
    realisations : array_like of int
        Realisation indices (R of them): distinct integers (:func:`realisation_indices`).
    band_hz : float
        Half-width of the band of J [Hz], a finite number > 0.

    Returns
    -------
    numpy.ndarray
        J [m²·rad/(N²·s)], shape (R,).
    """
    positive("band_hz", band_hz, "Hz")  # before the draws
    M, D, K = random_subsystem(sub, dispersion, seed, realisations)
    return j_functional(M, D, K, sub.n_c, band_hz)


def j_monte_carlo(sub: ReducedSubsystem, deltas: ArrayLike, seed: int, realisations: ArrayLike, band_hz: float,
                  which: str = "stiffness") -> xr.DataArray:
    """Monte Carlo of J(δ) over a δ grid with common random numbers (the same germs at every δ).

    Parameters
    ----------
    sub : ReducedSubsystem
        The mean reduced subsystem B.
    deltas : array_like of float
        Non-empty 1-D grid of dispersions, each below ``delta_max(sub.n)``.
    seed : int
        Study seed (see :func:`random_subsystem`).
    realisations : array_like of int
        Realisation indices: distinct integers (:func:`realisation_indices`).
    band_hz : float
        Half-width of the band of J [Hz], a finite number > 0.
    which : str
        The randomised matrix: ``"stiffness"`` (the paper), ``"mass"``, ``"damping"`` or ``"all"``.

    Returns
    -------
    xarray.DataArray
        ``J`` over (delta, realisation), in m²·rad/(N²·s).
    """
    if which not in (*_MATRICES, "all"):
        raise SpecificationError("which", which, f"must be one of {(*_MATRICES, 'all')}")
    deltas = numeric_array("deltas", deltas, finite=False, dtype=float)  # finite and in range: Dispersion checks
    if deltas.ndim != 1 or deltas.size == 0:
        raise SpecificationError("deltas", deltas.tolist(), "must be a non-empty 1-D grid")
    realisations = realisation_indices(realisations)
    _seed("seed", seed)
    positive("band_hz", band_hz, "Hz")  # checked, not converted: recorded as given
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


def random_condensed_stiffness(sub: ReducedSubsystem, dispersion: Dispersion, seed: int, realisations: ArrayLike,
                               frequency_hz: ArrayLike) -> xr.DataArray:
    """Random condensed dynamic stiffness Z(ω) of B on the interface.

    Parameters
    ----------
    sub : ReducedSubsystem
        The mean reduced subsystem B.
    dispersion : Dispersion
        δ of each matrix.
    seed : int
        Study seed (see :func:`random_subsystem`).
    realisations : array_like of int
        Realisation indices: distinct integers (:func:`realisation_indices`).
    frequency_hz : array_like of float
        Frequencies [Hz], 1-D.

    Returns
    -------
    xarray.DataArray
        ``Z`` [N/m], complex, over (realisation, frequency, interface, interface_).
    """
    realisations = realisation_indices(realisations)
    f = numeric_array("frequency_hz", frequency_hz, dtype=float)
    M, D, K = random_subsystem(sub, dispersion, seed, realisations)
    Z = condensed_stiffness(M, D, K, sub.n_c, 2 * np.pi * f)
    return xr.DataArray(
        Z,
        dims=("realisation", "frequency", "interface", "interface_"),
        coords={"realisation": realisations, "frequency": f},
        name="Z",
        attrs={"units": "N/m", "frequency_units": "Hz"},
    )
