"""Soize's random-matrix ensembles SG+ and SE+ (nonparametric model uncertainty).

Conventions (MODEL.md §3.3):

* ``G ∈ SG+`` of size n and dispersion δ: ``G = Lᵀ L`` with L upper triangular,
  ``σ = δ/√(n+1)``, ``L_jk = σ·N(0,1)`` for j < k and ``L_jj = σ·√(2 V_j)`` with
  ``V_j ~ Gamma(shape (n+1)/(2δ²) + (1 − j)/2, scale 1)``, **j counted from 1**.
  Then E[G] = I, Var(G_jk) = δ²(1 + δ_jk)/(n+1) and δ² = E‖G − I‖²_F / n.
  G is Wishart with (n+1)/δ² degrees of freedom and scale I·δ²/(n+1) (Bartlett decomposition).
* Admissible dispersion: 0 < δ < δ_max(n) = √((n+1)/(n+5)) (E‖G⁻¹‖² finite).
* ``A ∈ SE+`` with mean A̲ (symmetric positive definite): ``A = L_Aᵀ G L_A`` with A̲ = L_Aᵀ L_A
  (L_A upper triangular, Cholesky). Then E[A] = A̲ and A has the units of A̲.

Random draws come from a ``numpy.random.Generator`` (or a seed, mapped through
``tubeid.seeds.rng_for(seed, <function name>)``); realisations are vectorised over ``size``.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, fields

import numpy as np

from tubeid._validation import allocation, numeric_array
from tubeid.errors import Described as _Desc, SpecificationError
from tubeid.seeds import rng_for

#: ``size`` arguments: a count of realisations or a shape of them
Size = int | tuple[int, ...]
#: ``rng`` arguments: a generator, or a non-negative seed mapped through ``rng_for(seed, <function name>)``
RngLike = np.random.Generator | int

__all__ = ["delta_max", "sg_plus", "sg_plus_germs", "sg_plus_from_germs", "se_plus", "sg_plus_dispersion", "Dispersion"]


def delta_max(n: int) -> float:
    """Upper bound (excluded) of the SG+ dispersion for matrices of size n: √((n+1)/(n+5)).

    Parameters
    ----------
    n : int
        Matrix size, ≥ 1.

    Returns
    -------
    float
        δ_max(n) (dimensionless).
    """
    n = _check_size_n(n, "n")
    return math.sqrt((n + 1) / (n + 5))


def _check_size_n(n, field: str) -> int:
    if isinstance(n, (bool, np.bool_)) or not isinstance(n, (numbers.Integral, np.integer)) or n < 1:
        raise SpecificationError(field, n, "must be an integer >= 1")
    return int(n)


#: Smallest non-zero dispersion drawn. G − I is of order δ while G's entries near 1 carry an absolute
#: round-off of ~1e-16: measured with a fixed seed (20000 draws, n = 1…60), the draws' dispersion
#: departs from δ by ~1e-6 relative at δ = 1e-12, ~1e-3 at 1e-14, ×1.6 at 1e-16; at 1e-20 it reads
#: 0.7 δ (gammaincinv has no resolution left), at 1e-155 the draw is NaN, below ~1e-162 it fails.
DELTA_MIN = 1e-12


def _check_delta(delta, n: int, field: str = "delta") -> float:
    dmax = math.sqrt((n + 1) / (n + 5))
    rule = f"must satisfy 0 < {field} < delta_max(n={n}) = {dmax:.6g}, i.e. lie in the open interval (0, {dmax:.6g})"
    if isinstance(delta, (bool, np.bool_)) or not isinstance(delta, (numbers.Real, np.floating, np.integer)):
        raise SpecificationError(field, delta, rule)
    d = float(delta)
    if not (math.isfinite(d) and 0.0 < d < dmax):
        raise SpecificationError(field, delta, rule)
    if d < DELTA_MIN:
        raise SpecificationError(field, delta, f"must be at least {DELTA_MIN:g} when not 0 (below it the draws' "
                                 "deviation from the mean, of order delta, is lost in float round-off and their "
                                 "dispersion is no longer delta)")
    return d


def _check_shape(size) -> tuple[int, ...]:
    if isinstance(size, (numbers.Integral, np.integer)) and not isinstance(size, (bool, np.bool_)):
        size = (size,)
    try:
        shape = tuple(size)
    except TypeError:
        raise SpecificationError("size", size, "must be a non-negative integer or a tuple of them") from None
    for s in shape:
        if isinstance(s, (bool, np.bool_)) or not isinstance(s, (numbers.Integral, np.integer)) or s < 0:
            raise SpecificationError("size", size, "must be a non-negative integer or a tuple of them")
    return tuple(int(s) for s in shape)


def _as_rng(rng, name: str) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    if isinstance(rng, (numbers.Integral, np.integer)) and not isinstance(rng, (bool, np.bool_)) and rng >= 0:
        return rng_for(int(rng), name)
    raise SpecificationError("rng", rng, "must be a numpy.random.Generator or a non-negative integer seed")


def sg_plus(n: int, delta: float, size: Size = (), *, rng: RngLike) -> np.ndarray:
    """Draw realisations of G ∈ SG+: exactly the generator of MODEL.md §3.3 (j counted from 1).

    Parameters
    ----------
    n : int
        Matrix size, ≥ 1.
    delta : float
        Dispersion, :data:`DELTA_MIN` = 1e-12 <= δ < ``delta_max(n)``.
    size : int or tuple of int
        Realisations (leading shape); ``()`` for one matrix.
    rng : numpy.random.Generator or int
        The random stream, or a non-negative seed.

    Returns
    -------
    numpy.ndarray
        Symmetric positive-definite matrices (dimensionless), shape ``(*size, n, n)``; E[G] = I.
    """
    n = _check_size_n(n, "n")
    d = _check_delta(delta, n)
    shape = _check_shape(size)
    gen = _as_rng(rng, "sg_plus")
    # one construction: germs (normals, uniforms) → G, so a δ grid with the same seed is smooth
    return sg_plus_from_germs(n, d, *sg_plus_germs(n, shape, rng=gen))


def sg_plus_germs(n: int, size: Size = (), *, rng: RngLike) -> tuple[np.ndarray, np.ndarray]:
    """The δ-free random germs of SG+.

    With :func:`sg_plus_from_germs` they give common random numbers across a δ grid: the same
    germs map smoothly to G(δ) for every δ (the gamma variates by inverse CDF), so a likelihood
    curve over δ is smooth.

    Parameters
    ----------
    n : int
        Matrix size, ≥ 1.
    size : int or tuple of int
        Realisations (leading shape).
    rng : numpy.random.Generator or int
        The random stream, or a non-negative seed.

    Returns
    -------
    normals : numpy.ndarray
        Standard normals, shape ``(*size, n(n−1)/2)`` (the strict upper triangle of L, row-major).
    uniforms : numpy.ndarray
        Uniforms on [0, 1), shape ``(*size, n)`` (the diagonal's gamma variates by inverse CDF).
    """
    n = _check_size_n(n, "n")
    shape = _check_shape(size)
    allocation("n, size", (n, shape), 8.0 * math.prod(shape) * (2 * n * n + n * (n + 1) // 2),
               f"{math.prod(shape)} draw(s) of {n} x {n} matrices (the germs, L and G)")
    gen = _as_rng(rng, "sg_plus_germs")
    return gen.standard_normal(shape + (n * (n - 1) // 2,)), gen.random(shape + (n,))


def sg_plus_from_germs(n: int, delta: float, normals: np.ndarray, uniforms: np.ndarray) -> np.ndarray:
    """G ∈ SG+(n, δ) from germs (see :func:`sg_plus_germs`); same law as :func:`sg_plus`.

    V_j = F⁻¹_Gamma(a_j)(u_j) with a_j = (n+1)/(2δ²) + (1 − j)/2, j counted from 1.

    Parameters
    ----------
    n : int
        Matrix size, ≥ 1.
    delta : float
        Dispersion, :data:`DELTA_MIN` = 1e-12 <= δ < ``delta_max(n)``.
    normals : array_like
        Standard normals, shape ``(*size, n(n−1)/2)``.
    uniforms : array_like
        Uniforms in (0, 1), shape ``(*size, n)``.

    Returns
    -------
    numpy.ndarray
        Shape ``(*size, n, n)``.
    """
    import scipy.special

    n = _check_size_n(n, "n")
    d = _check_delta(delta, n)
    normals = numeric_array("normals", normals, finite=False, dtype=float)
    uniforms = numeric_array("uniforms", uniforms, finite=False, dtype=float)
    sigma = d / math.sqrt(n + 1)
    j = np.arange(1, n + 1)
    a = (n + 1) / (2.0 * d * d) + (1.0 - j) / 2.0
    iu = np.triu_indices(n, k=1)
    L = np.zeros(uniforms.shape[:-1] + (n, n))
    L[..., iu[0], iu[1]] = sigma * normals
    L[..., j - 1, j - 1] = sigma * np.sqrt(2.0 * scipy.special.gammaincinv(a, uniforms))
    G = np.swapaxes(L, -1, -2) @ L
    return 0.5 * (G + np.swapaxes(G, -1, -2))


def _check_mean(mean, name: str) -> np.ndarray:
    m = numeric_array(name, mean, finite=False, dtype=float)  # complex, bool, strings refused; finite: below
    if m.ndim != 2 or m.shape[0] != m.shape[1] or m.shape[0] < 1:
        raise SpecificationError(name, _Desc(f"array of shape {m.shape}"), "must be a square matrix (n, n) with n >= 1")
    if not np.all(np.isfinite(m)):
        raise SpecificationError(name, _Desc("matrix with non-finite entries"), "must be finite")
    scale = np.max(np.abs(m))
    asym = np.max(np.abs(m - m.T))
    if asym > 1e-10 * scale:
        raise SpecificationError(
            name, _Desc(f"matrix with max |{name} - {name}ᵀ| = {asym:.3g} (max |entry| = {scale:.3g})"),
            "must be symmetric positive definite (it is not symmetric)")
    m = 0.5 * (m + m.T)
    try:
        low = np.linalg.cholesky(m)
    except np.linalg.LinAlgError:
        low = None
    if low is None or not np.all(np.diag(low) > 0):
        lam = np.linalg.eigvalsh(m)
        raise SpecificationError(
            name, _Desc(f"matrix with smallest eigenvalue {lam[0]:.3g}"),
            "must be symmetric positive definite (it is not positive definite)")
    return low.T  # upper L_A with mean = L_Aᵀ L_A


def se_plus(mean: np.ndarray, delta: float, size: Size = (), *, rng: RngLike, name: str = "mean") -> np.ndarray:
    """Draw realisations of A ∈ SE+ with E[A] = ``mean``: A = L_Aᵀ G L_A, G ∈ SG+(n, δ), mean = L_Aᵀ L_A.

    Parameters
    ----------
    mean : array_like
        The mean matrix A̲, (n, n), symmetric positive definite.
    delta : float
        Dispersion, :data:`DELTA_MIN` = 1e-12 <= δ < ``delta_max(n)``.
    size : int or tuple of int
        Realisations (leading shape).
    rng : numpy.random.Generator or int
        The random stream, or a non-negative seed.
    name : str
        Labels ``mean`` in error messages (e.g. ``"K_B"``); δ errors then read ``delta[K_B]``.

    Returns
    -------
    numpy.ndarray
        Shape ``(*size, n, n)``, in the units of ``mean``.
    """
    LA = _check_mean(mean, name)
    n = LA.shape[0]
    _check_delta(delta, n, "delta" if name == "mean" else f"delta[{name}]")
    shape = _check_shape(size)
    G = sg_plus(n, delta, shape, rng=_as_rng(rng, "se_plus"))
    A = LA.T @ G @ LA
    return 0.5 * (A + np.swapaxes(A, -1, -2))


def sg_plus_dispersion(G: np.ndarray) -> float:
    """Sample estimate of δ = √(E‖G − I‖²_F / n).

    Parameters
    ----------
    G : array_like
        Realisations, shape (..., n, n), at least one.

    Returns
    -------
    float
        The estimated dispersion.
    """
    g = numeric_array("G", G, finite=False, dtype=float)
    if g.ndim < 2 or g.shape[-1] != g.shape[-2] or g.shape[-1] < 1:
        raise SpecificationError("G", _Desc(f"array of shape {g.shape}"), "must have shape (..., n, n) with n >= 1")
    if g.size == 0:
        raise SpecificationError("G", _Desc(f"array of shape {g.shape}"), "must hold at least one realisation")
    if not np.all(np.isfinite(g)):
        raise SpecificationError("G", _Desc("array with non-finite entries"), "must be finite")
    n = g.shape[-1]
    dev = g - np.eye(n)
    return float(np.sqrt(np.mean(np.sum(dev * dev, axis=(-2, -1))) / n))


@dataclass(frozen=True)
class Dispersion:
    """SG+ dispersions of a random reduced model; 0 = deterministic.

    ``check(n)`` additionally requires each non-zero field to be < delta_max(n) for reduced
    matrices of size n.

    Parameters
    ----------
    mass, damping, stiffness : float
        Dispersion δ of each reduced matrix of B, a finite number ≥ 0.
    """

    mass: float = 0.0
    damping: float = 0.0
    stiffness: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (numbers.Real, np.floating, np.integer)) \
                    or not math.isfinite(float(v)) or float(v) < 0:
                raise SpecificationError(f"dispersion.{f.name}", v, "must be a finite number >= 0 (0 = deterministic)")
            object.__setattr__(self, f.name, float(v))

    @property
    def is_deterministic(self) -> bool:
        """True when no matrix is randomised."""
        return self.mass == 0.0 and self.damping == 0.0 and self.stiffness == 0.0

    def check(self, n: int) -> "Dispersion":
        """Validate the non-zero dispersions against ``delta_max(n)``.

        Parameters
        ----------
        n : int
            Size of the reduced matrices.

        Returns
        -------
        Dispersion
            ``self``; a dispersion at or above the bound raises ``SpecificationError``.
        """
        n = _check_size_n(n, "n")
        for f in fields(self):
            v = getattr(self, f.name)
            if v != 0.0:
                _check_delta(v, n, f"dispersion.{f.name}")
        return self
