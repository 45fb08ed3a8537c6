"""Load spectra: matrix-valued power spectral densities of the stochastic loads F(t).

Convention (everywhere in tubeid): **two-sided PSD per Hz**. For loads F(t) in R^m with
correlation R(tau) = E[F(t + tau) F(t)^T],

    S(f) = int R(tau) exp(-2 i pi f tau) dtau,   S_ab(f) = lim E[F̂_a(f) conj(F̂_b(f))] / T,

so S(-f) = conj(S(f)) = S(f)^T, S(f) is Hermitian positive semi-definite and
Cov(F) = int_{-inf}^{inf} S(f) df. Frequencies are in Hz; a force contributes N^2/Hz, a
moment (N m)^2/Hz.

A :class:`LoadSpectrum` is either *constant in the band* (one m x m matrix for |f| <= band,
zero outside) or *tabulated* (matrices on a grid 0 = f_0 < ... < f_K, linearly interpolated,
zero for |f| > band). Optionally it carries a *germ* G (an m x m SPD matrix, one draw of
Soize's ensemble SG+ made by the caller); it then represents the randomised spectrum of
Batou & Soize (2008, Section 3.1)

    S_F(f) = L(f)^* G L(f),   S̄(f) = L(f)^* L(f),

with S̄ the mean spectrum. L(f) is the upper-triangular Cholesky factor (the paper's choice)
wherever S̄(f) is positive definite; where S̄(f) is singular (e.g. zero outside the band, or
two loads at the same point) L(f) = diag(sqrt(lambda)) V^* from the eigendecomposition
S̄ = V diag(lambda) V^*, which still satisfies L^* L = S̄, so E[S_F] = S̄ when E[G] = I.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike

from tubeid._validation import numeric_array, positive, real
from tubeid.errors import SpecificationError

__all__ = [
    "LoadSpectrum",
    "coherent_forces",
    "force_and_moment",
    "tabulated",
    "randomised",
    "check_psd_matrices",
    "psd_factor",
    "KIND_UNITS",
]

#: PSD unit of each load kind (two-sided, per Hz).
KIND_UNITS = {"force": "N^2/Hz", "moment": "(N m)^2/Hz"}

# Relative tolerances of the Hermitian-PSD check: asymmetry and negative eigenvalues are
# compared with the largest eigenvalue magnitude of the same matrix (round-off of user data).
_HERMITIAN_RTOL = 1e-8
_PSD_RTOL = 1e-9
# A matrix whose smallest eigenvalue is below this fraction of its largest is treated as
# singular by psd_factor (eigen square root instead of Cholesky).
_SINGULAR_RTOL = 1e-10


def check_psd_matrices(f, S, field: str = "S(f)") -> None:
    """Refuse a stack of PSD matrices that is not Hermitian positive semi-definite.

    ``f`` (F,) frequencies in Hz, ``S`` (F, m, m). Raises ``SpecificationError(field, f_bad,
    rule)`` naming the first offending frequency (Hz). This is the one place tubeid checks
    spectral matrices. Tolerances: asymmetry and negative eigenvalues up to 1e-8 resp. 1e-9
    of the matrix's largest eigenvalue magnitude are accepted as round-off.
    """
    f = numeric_array("f", f, finite=False, dtype=float).reshape(-1)
    S = np.asarray(S)
    if S.ndim != 3 or S.shape[1] != S.shape[2] or S.shape[0] != f.size:
        raise SpecificationError(field, getattr(S, "shape", None),
                                 f"must have shape (len(f), m, m) = ({f.size}, m, m)")
    if not np.all(np.isfinite(f)):
        raise SpecificationError("f", f[~np.isfinite(f)][0], "frequencies must be finite (Hz)")
    finite = np.all(np.isfinite(S), axis=(1, 2))
    if not np.all(finite):
        k = int(np.argmin(finite))
        raise SpecificationError(field, float(f[k]), f"at f = {f[k]:g} Hz the matrix has non-finite entries")
    if S.shape[0] == 0:
        return
    Sh = 0.5 * (S + np.conj(np.swapaxes(S, 1, 2)))
    lam = np.linalg.eigvalsh(Sh)  # ascending
    scale = np.max(np.abs(lam), axis=1)
    asym = np.max(np.abs(S - np.conj(np.swapaxes(S, 1, 2))), axis=(1, 2))
    bad_h = asym > _HERMITIAN_RTOL * np.maximum(scale, np.finfo(float).tiny)
    bad_h &= asym > 0
    if np.any(bad_h):
        k = int(np.argmax(bad_h))
        raise SpecificationError(field, float(f[k]),
                                 f"at f = {f[k]:g} Hz the matrix is not Hermitian "
                                 f"(max |S - S^*| = {asym[k]:.3g})")
    bad_p = lam[:, 0] < -_PSD_RTOL * scale
    if np.any(bad_p):
        k = int(np.argmax(bad_p))
        raise SpecificationError(field, float(f[k]),
                                 f"at f = {f[k]:g} Hz the matrix is not positive semi-definite "
                                 f"(smallest eigenvalue {lam[k, 0]:.3g} < 0)")


def psd_factor(S) -> np.ndarray:
    """A factor L with L^* L = S for each Hermitian PSD matrix of a stack S (..., m, m).

    Upper-triangular Cholesky factor (L = C^*, S = C C^*) where S is positive definite;
    L = diag(sqrt(max(lambda, 0))) V^* (eigendecomposition; real V for real S) where S is
    singular, i.e. its smallest eigenvalue is <= 1e-10 times its largest (a zero matrix gives
    L = 0). For singular complex S, L (hence L^* G L, not its mean) depends on the arbitrary
    phases of the eigenvectors: the factorisation is not unique there.
    """
    S = np.asarray(S, dtype=complex)
    shape = S.shape
    S2 = S.reshape((-1,) + shape[-2:])
    S2 = 0.5 * (S2 + np.conj(np.swapaxes(S2, -1, -2)))
    # Real matrices are factored in real arithmetic (real eigenvectors: a complex eigenvector phase
    # would make L^* G L non-real where S is real, e.g. at f = 0 or for a constant real spectrum).
    # Eigenvalues only to classify; Cholesky where regular; full eigh only where singular.
    real = np.all(S2.imag == 0, axis=(1, 2))
    lam = np.empty(S2.shape[:2])
    if np.any(real):
        lam[real] = np.linalg.eigvalsh(S2[real].real)
    if not np.all(real):
        lam[~real] = np.linalg.eigvalsh(S2[~real])
    regular = lam[:, 0] > _SINGULAR_RTOL * np.max(np.abs(lam), axis=1)
    L = np.zeros_like(S2)
    for part in (regular & real, regular & ~real):
        if np.any(part):
            C = np.linalg.cholesky(S2[part].real if np.all(real[part]) else S2[part])
            L[part] = np.conj(np.swapaxes(C, -1, -2))
    for part in (~regular & real, ~regular & ~real):
        if np.any(part):
            lam_p, V = np.linalg.eigh(S2[part].real if np.all(real[part]) else S2[part])
            L[part] = np.sqrt(np.clip(lam_p, 0.0, None))[:, :, None] * np.conj(np.swapaxes(V, -1, -2))
    return L.reshape(shape)


def _tuple_str(field_name, values, m=None):
    if isinstance(values, str):
        values = (values,)
    values = tuple(values)
    for v in values:
        if not isinstance(v, str) or not v:
            raise SpecificationError(field_name, v, "must be a non-empty string")
    if m is not None and len(values) != m:
        raise SpecificationError(field_name, values, f"must have one entry per load ({m})")
    return values


@dataclass(frozen=True, eq=False)
class LoadSpectrum:
    """Two-sided matrix PSD (per Hz) of m loads acting on one tube. Validated when made, immutable.

    Parameters
    ----------
    names : tuple of str
        Load names (unique).
    kinds : tuple of str
        ``"force"`` (N, PSD in N^2/Hz) or ``"moment"`` (N m, PSD in (N m)^2/Hz), one per load.
    tube : str
        Name of the tube the loads act on.
    x : tuple of float
        Position of each load along the tube (m).
    band : float
        Hz; S(f) = 0 for |f| > band.
    values : numpy.ndarray
        (m, m) matrix constant for |f| <= band when ``frequencies`` is None, else (K, m, m)
        matrices at ``frequencies`` (linear interpolation in f); Hermitian positive semi-definite.
    frequencies : numpy.ndarray, optional
        None, or the table grid in Hz: 0 = f_0 < f_1 < ... with f_last >= band.
    germ : numpy.ndarray, optional
        None (deterministic spectrum), or G (m x m real SPD): the spectrum is then L^* G L with
        S̄ = L^* L the spectrum described by ``values`` (see the module docstring).
    """

    names: tuple
    kinds: tuple
    tube: str
    x: tuple
    band: float
    values: np.ndarray
    frequencies: np.ndarray | None = None
    germ: np.ndarray | None = field(default=None)

    def __post_init__(self) -> None:
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen dataclass)
        names = _tuple_str("names", self.names)
        m = len(names)
        if m == 0:
            raise SpecificationError("names", names, "at least one load")
        if len(set(names)) != m:
            raise SpecificationError("names", names, "load names must be unique")
        kinds = _tuple_str("kinds", self.kinds, m)
        for k in kinds:
            if k not in KIND_UNITS:
                raise SpecificationError("kinds", k, f"must be one of {sorted(KIND_UNITS)}")
        if not isinstance(self.tube, str) or not self.tube:
            raise SpecificationError("tube", self.tube, "must be a non-empty string")
        x = tuple(float(v) for v in np.atleast_1d(numeric_array("x", self.x, finite=False, dtype=float)))
        if len(x) != m or not all(np.isfinite(x)):
            raise SpecificationError("x", self.x, f"must be {m} finite positions (m)")
        band = positive("band", self.band, "Hz")
        values = np.asarray(self.values)
        if not (np.issubdtype(values.dtype, np.number)):
            raise SpecificationError("values", self.values, "must be numeric PSD matrices")
        values = values.astype(complex)
        if self.frequencies is None:
            if values.shape != (m, m):
                raise SpecificationError("values", values.shape, f"must be ({m}, {m}) for a constant spectrum")
            check_psd_matrices([0.0], values[None], field="S(f)")
            if np.max(np.abs(values.imag), initial=0.0) > _HERMITIAN_RTOL * max(np.max(np.abs(values)), 1e-300):
                raise SpecificationError("S(f)", 0.0, "a spectrum constant through f = 0 must be real "
                                         "(S(-f) = conj S(f) for a real process)")
            values = values.real.astype(complex)
            freqs = None
        else:
            freqs = numeric_array("f", self.frequencies, finite=False, dtype=float)
            if freqs.ndim != 1 or freqs.size < 2 or not np.all(np.isfinite(freqs)):
                raise SpecificationError("f", self.frequencies, "must be a 1-D grid of >= 2 finite frequencies (Hz)")
            if freqs[0] != 0.0:
                raise SpecificationError("f", float(freqs[0]), "the table must start at f = 0 Hz")
            if np.any(np.diff(freqs) <= 0):
                raise SpecificationError("f", self.frequencies, "must be strictly increasing")
            if values.shape != (freqs.size, m, m):
                raise SpecificationError("S", values.shape, f"must have shape ({freqs.size}, {m}, {m})")
            if freqs[-1] < band:
                raise SpecificationError("band", band, f"must be <= the last tabulated frequency {freqs[-1]:g} Hz")
            check_psd_matrices(freqs, values, field="S(f)")
            imag0 = np.max(np.abs(values[0].imag))
            if imag0 > _HERMITIAN_RTOL * max(np.max(np.abs(values[0])), 1e-300):
                raise SpecificationError("S(f)", 0.0, "at f = 0 Hz the matrix must be real "
                                         "(S(-f) = conj S(f) for a real process)")
            values = values.copy()
            values[0] = values[0].real
            freqs = freqs.copy()
            freqs.setflags(write=False)
        values = values.copy()
        values.setflags(write=False)
        germ = self.germ
        if germ is not None:
            germ = _check_germ(germ, m)
        set_("names", names)
        set_("kinds", kinds)
        set_("x", x)
        set_("band", band)
        set_("values", values)
        set_("frequencies", freqs)
        set_("germ", germ)

    # ------------------------------------------------------------------ properties
    @property
    def m(self) -> int:
        """Number of loads."""
        return len(self.names)

    @property
    def units(self) -> tuple:
        """PSD unit of each load's auto-spectrum: "N^2/Hz" or "(N m)^2/Hz"."""
        return tuple(KIND_UNITS[k] for k in self.kinds)

    @property
    def mean(self) -> "LoadSpectrum":
        """The mean spectrum S̄ (this spectrum without its germ G)."""
        if self.germ is None:
            return self
        return LoadSpectrum(self.names, self.kinds, self.tube, self.x, self.band,
                            self.values, self.frequencies, None)

    # ------------------------------------------------------------------ evaluation
    def _mean_matrix(self, fa: np.ndarray) -> np.ndarray:
        """S̄(|f|) for fa >= 0, shape (F, m, m)."""
        m = self.m
        inband = fa <= self.band
        out = np.zeros((fa.size, m, m), dtype=complex)
        if self.frequencies is None:
            out[inband] = self.values
            return out
        fg, V = self.frequencies, self.values
        fi = fa[inband]
        idx = np.clip(np.searchsorted(fg, fi, side="right") - 1, 0, fg.size - 2)
        w = ((fi - fg[idx]) / (fg[idx + 1] - fg[idx]))[:, None, None]
        out[inband] = (1.0 - w) * V[idx] + w * V[idx + 1]
        return out

    def matrix(self, f: ArrayLike) -> np.ndarray:
        """The PSD matrices S(f), two-sided per Hz, with S(-f) = conj S(f).

        Parameters
        ----------
        f : float or array_like
            Frequencies [Hz], any sign, scalar or 1-D.

        Returns
        -------
        numpy.ndarray
            Complex, shape (len(f), m, m), Hermitian positive semi-definite; entry (a, b) in
            [load_a][load_b]/Hz (N^2/Hz, N^2 m/Hz, (N m)^2/Hz).
        """
        f = numeric_array("f", f, finite=False, dtype=float)
        if f.ndim > 1:
            raise SpecificationError("f", f.shape, "must be a scalar or a 1-D array of frequencies (Hz)")
        f = np.atleast_1d(f)
        if not np.all(np.isfinite(f)):
            raise SpecificationError("f", f, "frequencies must be finite (Hz)")
        fa = np.abs(f)
        if self.frequencies is None:
            S = np.zeros((f.size, self.m, self.m), dtype=complex)
            inband = fa <= self.band
            if self.germ is None:
                S[inband] = self.values
            else:
                L = psd_factor(self.values)
                S[inband] = np.conj(L.T) @ self.germ @ L
            return S  # real in band: no conjugation needed for f < 0
        S = self._mean_matrix(fa)
        if self.germ is not None:
            L = psd_factor(S)
            S = np.conj(np.swapaxes(L, -1, -2)) @ self.germ @ L
        neg = f < 0
        S[neg] = np.conj(S[neg])
        return S

    def covariance(self) -> np.ndarray:
        """Cov(F) = int S(f) df over all f.

        Exact for constant spectra and for tabulated mean spectra (trapezoid of a piecewise
        linear function); for a tabulated spectrum with a germ, trapezoid on the grid refined
        64 times (L^* G L is not linear between grid points).

        Returns
        -------
        numpy.ndarray
            Real (m, m) covariance (N^2, N^2 m, (N m)^2).
        """
        if self.frequencies is None:
            return 2.0 * self.band * self.matrix([0.0])[0].real
        fg = self.frequencies
        if self.germ is not None:
            fine = np.concatenate([np.linspace(a, b, 65)[:-1] for a, b in zip(fg[:-1], fg[1:])] + [fg[-1:]])
            fg = fine
        grid = np.union1d(fg[fg <= self.band], [self.band])
        S = self.matrix(grid)
        return 2.0 * np.trapezoid(S.real, grid, axis=0)




def _check_germ(G, m) -> np.ndarray:
    G = np.asarray(G)
    if G.shape != (m, m) or not np.issubdtype(G.dtype, np.number) or np.iscomplexobj(G):
        raise SpecificationError("G", getattr(G, "shape", G), f"must be a real ({m}, {m}) matrix")
    G = G.astype(float)
    if not np.all(np.isfinite(G)):
        raise SpecificationError("G", G, "must be finite")
    if not np.allclose(G, G.T, rtol=0, atol=1e-12 * np.max(np.abs(G))):
        raise SpecificationError("G", G, "must be symmetric")
    G = 0.5 * (G + G.T)
    try:
        np.linalg.cholesky(G)
    except np.linalg.LinAlgError:
        raise SpecificationError("G", G, "must be positive definite (a draw of SG+)") from None
    G = G.copy()
    G.setflags(write=False)
    return G


# ---------------------------------------------------------------------- constructors
def coherent_forces(x: Sequence[float] = (2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0), level: float = 1.3,
                    band: float = 100.0, correlation_length: float = 4.0, tube: str = "centre") -> LoadSpectrum:
    """The paper's spatially coherent transverse forces (MODEL.md §1).

    S_ii = level (N^2/Hz) and S_ij = level * exp(-|x_i - x_j| / (2 lambda)) for |f| <= band
    (Hz), zero outside: the coherence exp(-|x_i - x_j| / lambda) is defined on the squared
    modulus, |S_ij|^2 = gamma_ij S_ii S_jj. Default: 7 forces, 260 N^2 each.

    Parameters
    ----------
    x : sequence of float
        Positions of the forces along the tube (m).
    level : float
        Auto-spectrum S_ii (N^2/Hz, two-sided), > 0.
    band : float
        The PSD is zero for |f| > band (Hz).
    correlation_length : float
        lambda (m), > 0.
    tube : str
        The tube the forces act on.

    Returns
    -------
    LoadSpectrum
        Constant in the band, loads named ``"F1"``..``"Fm"``.
    """
    x = np.atleast_1d(numeric_array("x", x, finite=False, dtype=float))
    if x.ndim != 1 or x.size == 0 or not np.all(np.isfinite(x)):
        raise SpecificationError("x", x, "must be a non-empty list of finite positions (m)")
    level = positive("level", level, "N^2/Hz")
    lam = positive("correlation_length", correlation_length, "m")
    S = level * np.exp(-np.abs(x[:, None] - x[None, :]) / (2.0 * lam))
    m = x.size
    return LoadSpectrum(tuple(f"F{i + 1}" for i in range(m)), ("force",) * m, tube, tuple(x), band, S)


def force_and_moment(r1: float, r2: float, x: float = 8.0, band: float = 100.0,
                     tube: str = "centre") -> LoadSpectrum:
    """The identification load model: a force T and a moment M at one point (paper Eq. 7).

    Independent, constant on |f| <= band: S = diag(r1, r2).

    Parameters
    ----------
    r1 : float
        PSD of the force T (N^2/Hz, two-sided), > 0.
    r2 : float
        PSD of the moment M ((N m)^2/Hz, two-sided), > 0.
    x : float
        Their position along the tube (m).
    band : float
        The PSD is zero for |f| > band (Hz).
    tube : str
        The tube they act on.

    Returns
    -------
    LoadSpectrum
        Loads ``("T", "M")`` of kinds ``("force", "moment")``.
    """
    r1 = positive("r1", r1, "N^2/Hz")
    r2 = positive("r2", r2, "(N m)^2/Hz")
    x = real("x", x, unit="m")
    return LoadSpectrum(("T", "M"), ("force", "moment"), tube, (x, x), band, np.diag([r1, r2]))


def tabulated(f: ArrayLike, S: ArrayLike, names: Sequence[str], kinds: Sequence[str], x: float | Sequence[float],
              tube: str = "centre", band: float | None = None) -> LoadSpectrum:
    """User-defined PSD matrices on a frequency grid.

    Linear interpolation in f between grid points, S(-f) = conj S(f), zero for |f| > band.
    Every matrix must be Hermitian PSD (the first offending frequency is named) and S(0) real.

    Parameters
    ----------
    f : array_like
        Grid [Hz], 0 = f_0 < ... < f_{K-1}.
    S : array_like
        Two-sided PSD matrices per Hz, shape (K, m, m).
    names : sequence of str
        Load names (m, unique).
    kinds : sequence of str
        ``"force"`` or ``"moment"`` per load.
    x : float or sequence of float
        Position of each load (m); one number for all.
    tube : str
        The tube they act on.
    band : float, optional
        Zero above this frequency [Hz] (default: the last grid frequency).

    Returns
    -------
    LoadSpectrum
        The tabulated spectrum.
    """
    f = numeric_array("f", f, finite=False, dtype=float)
    if band is None:
        if f.ndim != 1 or f.size == 0:
            raise SpecificationError("f", f, "must be a 1-D grid of frequencies (Hz)")
        band = float(f[-1])
    names = _tuple_str("names", names)
    kinds = _tuple_str("kinds", kinds)
    x = np.atleast_1d(numeric_array("x", x, finite=False, dtype=float))
    if x.size == 1 and len(names) > 1:
        x = np.full(len(names), float(x[0]))
    return LoadSpectrum(names, kinds, tube, tuple(x), band, np.asarray(S), f)


def randomised(spectrum: LoadSpectrum, G: ArrayLike) -> LoadSpectrum:
    """The randomised spectrum S_F(f) = L(f)^* G L(f), S̄(f) = L(f)^* L(f) (paper Section 3.1).

    The same G serves all frequencies, so the load stays stationary. Applying ``randomised`` to
    an already randomised spectrum replaces its germ (it randomises the mean). L is the Cholesky
    factor, or an eigen square root where S̄ is singular (module docstring).

    Parameters
    ----------
    spectrum : LoadSpectrum
        The mean spectrum S̄ (its germ, if any, is ignored).
    G : array_like
        One m x m real SPD draw of SG+ (the caller draws it, e.g. with ``sg_plus`` and a
        ``rng_for`` stream).

    Returns
    -------
    LoadSpectrum
        With ``germ`` = G; ``result.mean`` is ``spectrum.mean`` (E[S_F] = S̄ when E[G] = I).
    """
    if not isinstance(spectrum, LoadSpectrum):
        raise SpecificationError("spectrum", type(spectrum).__name__, "must be a LoadSpectrum")
    G = _check_germ(G, spectrum.m)
    return LoadSpectrum(spectrum.names, spectrum.kinds, spectrum.tube, spectrum.x, spectrum.band,
                        spectrum.values, spectrum.frequencies, G)
