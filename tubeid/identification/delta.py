"""Maximum-likelihood identification of the model dispersion δ (paper §2.4, MODEL.md §3.2).

J_ref = ∫ ‖Z_ref(ω)⁻¹‖²_F dω of the reference ("real") bundle is compared with the random
variable J(δ) of the stochastic simplified model; p_J(J_ref; δ) is a Gaussian kernel density
estimate (Silverman) of a Monte Carlo of J(δ) with common random numbers across the δ grid, and
δ_opt = argmax_δ p_J(J_ref; δ). The Monte Carlo uncertainty of the curve and of δ_opt is a
bootstrap over realisations (jointly across the grid).
"""

from __future__ import annotations

import os

import numpy as np
import xarray as xr
from numpy.typing import ArrayLike

from tubeid._validation import integer, numeric_array
from tubeid.errors import SpecificationError
from tubeid._validation import seed as _seed
from tubeid.identification.likelihood import likelihood_curve
from tubeid.mechanics.library import resolve_spec
from tubeid.mechanics.reduction import J_UNITS, j_of_spec, reduce
from tubeid.mechanics.spec import BundleSpec
from tubeid.uncertainty.random_matrices import delta_max
from tubeid.uncertainty.random_models import j_monte_carlo

__all__ = ["reference_j", "default_delta_grid", "identify_delta"]


def reference_j(reference: BundleSpec | str | os.PathLike = "paper-reference") -> float:
    """J of a deterministic bundle model (the paper's J_ref for the reference model).

    Parameters
    ----------
    reference : BundleSpec, str or path-like
        A specification, a built-in name or a ``.yaml``/``.toml`` file.

    Returns
    -------
    float
        J [m²·rad/(N²·s)] over the model's band. A bundle without an A–B interface (no stops, or
        no link from the non-linear tube to the others: n_c = 0) is refused.
    """
    spec = resolve_spec(reference)
    sub = reduce(spec).subsystem
    _check_interface("reference", spec, sub)
    return j_of_spec(spec, sub)


def _check_interface(field: str, spec: BundleSpec, sub) -> None:
    """J needs an A–B interface: refused, naming the model and why, when it has none (n_c = 0)."""
    if sub.n_c == 0:
        why = ("it has no stops, so no non-linear tube A" if spec.a_tube is None and not spec.nonlinear_tube
               else f"no link joins its non-linear tube {spec.a_tube!r} to another tube")
        raise SpecificationError(field, spec.name, f"has no A–B interface DOF (n_c = 0: {why}): J = ∫ ‖Z(ω)⁻¹‖²_F dω "
                                 "is defined on the interface only")


def default_delta_grid(n: int, step: float = 0.025) -> np.ndarray:
    """δ = step, 2·step, … strictly inside the admissible set (0, δ_max(n)).

    Parameters
    ----------
    n : int
        Size of the randomised reduced matrices.
    step : float
        Grid step.

    Returns
    -------
    numpy.ndarray
        The grid, increasing.
    """
    return np.arange(step, delta_max(n) - 1e-9, step)


def identify_delta(
    model: BundleSpec | str | os.PathLike = "paper-simplified",
    reference: BundleSpec | str | os.PathLike = "paper-reference",
    *,
    j_reference: float | ArrayLike | None = None,
    deltas: ArrayLike | None = None,
    n_realisations: int = 200,
    seed: int = 2008,
    which: str = "stiffness",
    n_bootstrap: int = 200,
) -> xr.Dataset:
    """δ_opt and the likelihood curve δ ↦ p_J(J_ref; δ) (module docstring).

    Parameters
    ----------
    model : BundleSpec, str or path-like
        The simplified model whose reduced B is randomised.
    reference : BundleSpec, str or path-like
        The reference model giving J_ref (unused when ``j_reference`` is given).
    j_reference : float or array_like, optional
        Observed J value(s) [m²·rad/(N²·s)]; several are independent observations (joint
        likelihood), each finite and >= 0. Default: J of ``reference``.
    deltas : array_like, optional
        δ grid, at least 3 values (default: ``default_delta_grid(n)``).
    n_realisations : int
        Monte Carlo realisations per δ (common random numbers across the grid).
    seed : int
        Seed of the Monte Carlo and of the bootstrap.
    which : str
        The randomised matrix: ``"stiffness"`` (the paper), ``"mass"``, ``"damping"`` or ``"all"``.
    n_bootstrap : int
        Bootstrap replicates of the curve and of δ_opt.

    Returns
    -------
    xarray.Dataset
        On ``delta``: the likelihood and its bootstrap band (see ``likelihood_curve``) and ``J``
        (delta, realisation); attributes ``delta_opt``, ``delta_opt_std``, ``delta_opt_low``,
        ``delta_opt_high``, ``J_ref``, ``J_units`` and the settings.
    """
    # checked up front (recorded as given): bools, strings and floats are not counts or seeds
    n_realisations = integer("n_realisations", n_realisations, minimum=1)
    _seed("seed", seed)
    given = None if deltas is None else numeric_array("deltas", deltas, finite=False, dtype=float)
    if given is not None and (given.ndim != 1 or given.size < 3):
        raise SpecificationError("deltas", given.tolist(), "must be a 1-D grid of at least 3 values (a maximum "
                                 "inside the grid needs a value on each side of it)")
    if j_reference is not None:
        jr = numeric_array("j_reference", j_reference, dtype=float)  # real and finite
        if jr.ndim > 1 or jr.size == 0 or np.any(jr < 0):
            raise SpecificationError("j_reference", j_reference, "must be a finite number >= 0 (J = ∫ ‖Z(ω)⁻¹‖²_F dω "
                                     "is never negative) or a 1-D array of them")
    spec = resolve_spec(model)
    sub = reduce(spec).subsystem
    _check_interface("model", spec, sub)
    j_of_spec(spec, sub)  # the mean model's J is defined (refusals name the specification's fields), before the draws
    j_ref = reference_j(reference) if j_reference is None else j_reference
    grid = default_delta_grid(sub.n) if deltas is None else given
    J = j_monte_carlo(sub, grid, seed, np.arange(n_realisations), spec.band_hz, which=which)
    ds = likelihood_curve(J, j_ref, grid, "delta", n_bootstrap=n_bootstrap, rng=seed)
    ds["J"] = J
    ds.attrs.update(
        delta_opt=ds.attrs["argmax"],
        delta_opt_std=ds.attrs["argmax_std"],
        delta_opt_low=ds.attrs["argmax_low"],
        delta_opt_high=ds.attrs["argmax_high"],
        J_ref=j_ref if np.ndim(j_ref) == 0 else list(np.atleast_1d(j_ref)),
        J_units=J_UNITS,
        model=spec.name,
        reference=str(reference) if j_reference is None else "given",
        randomised=which,
        n_reduced=sub.n,
        delta_max=delta_max(sub.n),
        seed=seed,
    )
    return ds
