"""Craig–Bampton reduction, condensed dynamic stiffness Z(ω) on the interface, and J.

Reduced coordinates of the whole bundle are ordered ``(y_A, y_B, u_c)``: fixed-interface modal
coordinates of subsystem A (the non-linear tube), of subsystem B (the linear rest), then the
physical interface DOFs u_c [m] (A's transverse displacements at the grid nodes). Physical DOFs are
u = T q. Subsystem B alone, reduced, has coordinates ``(y_B, u_c)`` and matrices ``M_B, D_B, K_B``
(size n = n_modes_B + n_c): these are what the nonparametric approach randomises.

Condensed dynamic stiffness of B on the interface (MODEL.md §3.1):
Z(ω) = A_cc − A_cy A_yy⁻¹ A_yc, A(ω) = −ω² M_B + iω D_B + K_B   [N/m].

J = ∫_{−Ω}^{Ω} ‖Z(ω)⁻¹‖²_F dω with Ω = 2π·band_hz, in **m²·rad/(N²·s)** (compliance squared times
rad/s). :func:`j_functional` evaluates it in closed form from the poles of B: with the quadratic
eigenpairs (λ_k, φ_k) of (M_B, D_B, K_B), Z(ω)⁻¹ = [A(iω)⁻¹]_cc = Σ_k φ_k,c φ_k,cᵀ / (a_k (iω − λ_k)),
a_k = φ_kᵀ(2λ_k M + D)φ_k, and each pair of poles integrates analytically over the band:
∫ dω / ((iω − λ_k)(−iω − λ̄_l)) = −(I(λ_k) + I(λ̄_l)) / (λ_k + λ̄_l), I(a) = −i[Log(iΩ − a) − Log(−iΩ − a)],
evaluated in a form without cancellation (:func:`_log_integral`), so poles far above the band (a very stiff B)
keep J's full precision. No frequency grid, hence no quadrature error near the lightly damped resonances.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import scipy.linalg

from tubeid._validation import integer, numeric_array, positive
from tubeid.errors import Described, SpecificationError
from tubeid.mechanics.assembly import FEModel, assemble
from tubeid.mechanics.spec import BundleSpec, LoadPoint, SensorSpec

__all__ = [
    "J_UNITS",
    "ReducedSubsystem",
    "ReducedModel",
    "craig_bampton",
    "reduce",
    "condensed_stiffness",
    "j_functional",
    "j_of_spec",
    "j_quadrature",
]

J_UNITS = "m^2 rad/(N^2 s)"


def _select_modes(w2: np.ndarray, n_modes: int | None, cutoff_hz: float | None) -> np.ndarray:
    keep = np.ones(w2.shape, dtype=bool)
    if cutoff_hz is not None:
        keep &= np.sqrt(np.clip(w2, 0, None)) / (2 * np.pi) <= cutoff_hz
    idx = np.flatnonzero(keep)
    return idx if n_modes is None else idx[:n_modes]


def craig_bampton(M: np.ndarray, K: np.ndarray, internal: np.ndarray, interface: np.ndarray, n_modes: int | None = None, cutoff_hz: float | None = None):
    """Craig–Bampton basis of a substructure.

    Returns ``(Phi, Psi, freqs_hz)``: fixed-interface modes Φ (mass-normalised on the internal
    DOFs, kept by count and/or cut-off), static constraint modes Ψ = −K_ii⁻¹ K_ic, and the kept
    fixed-interface frequencies. Physical internal DOFs: u_i = Φ y + Ψ u_c.
    """
    Kii = K[np.ix_(internal, internal)]
    Mii = M[np.ix_(internal, internal)]
    if len(internal) == 0:
        return np.zeros((0, 0)), np.zeros((0, len(interface))), np.zeros(0)
    w2, phi = scipy.linalg.eigh(Kii, Mii)
    keep = _select_modes(w2, n_modes, cutoff_hz)
    Psi = -np.linalg.solve(Kii, K[np.ix_(internal, interface)]) if len(interface) else np.zeros((len(internal), 0))
    return phi[:, keep], Psi, np.sqrt(np.clip(w2[keep], 0, None)) / (2 * np.pi)


@dataclass(frozen=True, eq=False)
class ReducedSubsystem:
    """Reduced linear subsystem B: coordinates (y_B, u_c); the last ``n_c`` are the interface DOFs.

    Parameters
    ----------
    M, D, K : numpy.ndarray
        Reduced mass, damping and stiffness matrices, shape (n, n), symmetric.
    n_c : int
        Number of interface DOFs (the last ``n_c`` coordinates, in m).
    mode_frequencies_hz : numpy.ndarray
        Frequencies of the kept fixed-interface modes [Hz].
    """

    M: np.ndarray
    D: np.ndarray
    K: np.ndarray
    n_c: int
    mode_frequencies_hz: np.ndarray

    @property
    def n(self) -> int:
        """Size of the reduced matrices (the SG+ dimension when they are randomised)."""
        return self.M.shape[-1]


@dataclass(frozen=True, eq=False)
class ReducedModel:
    """Craig–Bampton reduced model of a whole bundle (stops open), q = (y_A, y_B, u_c), u = T q.

    Made by :func:`reduce`. :meth:`matrices` embeds (possibly random, batched) B matrices into the
    global ones.

    Parameters
    ----------
    fe : FEModel
        The full finite-element model.
    T : numpy.ndarray
        Shape (n_dof, N): physical DOFs u = T q.
    A_part : tuple of numpy.ndarray
        The (M, D, K) contributions of subsystem A in reduced coordinates, each (N, N).
    subsystem : ReducedSubsystem
        The reduced subsystem B.
    b_index : numpy.ndarray
        Positions of B's coordinates (y_B, u_c) in q.
    """

    fe: FEModel
    T: np.ndarray
    A_part: tuple[np.ndarray, np.ndarray, np.ndarray] = field(repr=False)
    subsystem: ReducedSubsystem = field(repr=False)
    b_index: np.ndarray = field(repr=False)

    @property
    def spec(self) -> BundleSpec:
        """The bundle specification."""
        return self.fe.spec

    @property
    def N(self) -> int:
        """Number of reduced coordinates."""
        return self.T.shape[1]

    def matrices(self, M_B: np.ndarray | None = None, D_B: np.ndarray | None = None,
                 K_B: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Global (M, D, K) with B's reduced matrices replaced by the given ones.

        Parameters
        ----------
        M_B, D_B, K_B : numpy.ndarray, optional
            Replacements for B's reduced matrices, shape (..., n, n) with optional leading batch
            axes; None keeps the mean (deterministic) matrix.

        Returns
        -------
        tuple of numpy.ndarray
            (M, D, K), each (..., N, N), broadcast over the batch axes.
        """
        out = []
        for a_mat, b_new, b_mean in zip(self.A_part, (M_B, D_B, K_B), (self.subsystem.M, self.subsystem.D, self.subsystem.K)):
            b = b_mean if b_new is None else np.asarray(b_new)
            g = np.broadcast_to(a_mat, b.shape[:-2] + a_mat.shape).copy()
            ix = np.ix_(self.b_index, self.b_index)
            g[(...,) + ix] += b
            out.append(g)
        return tuple(out)

    @cached_property
    def mean_matrices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Global (M, D, K) of the mean model, each (N, N)."""
        return self.matrices()

    def load_matrix(self, points: tuple[LoadPoint, ...] | None = None) -> np.ndarray:
        """Generalised load influence matrix.

        Parameters
        ----------
        points : tuple of LoadPoint, optional
            The load points (default: the specification's ``loads``).

        Returns
        -------
        numpy.ndarray
            Shape (N, m): Tᵀ times the physical influence matrix.
        """
        return self.T.T @ self.fe.load_matrix(points)

    def sensor_matrix(self, sensors: tuple[SensorSpec, ...] | None = None) -> np.ndarray:
        """Observation matrix in reduced coordinates.

        Parameters
        ----------
        sensors : tuple of SensorSpec, optional
            The sensors (default: the specification's ``sensors``).

        Returns
        -------
        numpy.ndarray
            Shape (n_sensors, N): sensor displacements [m] = matrix @ q.
        """
        return self.fe.sensor_matrix(sensors) @ self.T

    def stop_vectors(self) -> np.ndarray:
        """The stops' observation rows in reduced coordinates.

        Returns
        -------
        numpy.ndarray
            Shape (n_stops, N): u_stop = b·q [m].
        """
        return self.fe.stop_vectors() @ self.T

    def eigenfrequencies(self, n: int | None = 10) -> np.ndarray:
        """Undamped eigenfrequencies of the reduced mean model (stops open).

        Parameters
        ----------
        n : int, optional
            How many, lowest first; None for all.

        Returns
        -------
        numpy.ndarray
            Frequencies [Hz], ascending.
        """
        M, _, K = self.mean_matrices
        f = np.sqrt(np.clip(scipy.linalg.eigh(K, M, eigvals_only=True), 0, None)) / (2 * np.pi)
        return f if n is None else f[:n]


def reduce(model: BundleSpec | FEModel) -> ReducedModel:
    """Craig–Bampton reduction of both subsystems of a bundle, as its ``reduction`` field says.

    Parameters
    ----------
    model : BundleSpec or FEModel
        The bundle (assembled first when a specification is given).

    Returns
    -------
    ReducedModel
        q = (y_A, y_B, u_c); its ``subsystem`` is the reduced B that the nonparametric model
        randomises.
    """
    fe = model if isinstance(model, FEModel) else assemble(model)
    spec = fe.spec
    red = spec.reduction
    n = fe.n_dof
    c = fe.interface
    a_name = spec.a_tube
    is_a = np.array([d[0] == a_name for d in fe.dofs])
    a_int = np.array([i for i in np.flatnonzero(is_a) if i not in set(c)], dtype=int)
    b_int = np.flatnonzero(~is_a)
    MA, DA, KA = fe.parts["A"]
    MB, DB, KB = fe.parts["B"]
    # A is reduced with its own matrices; B with its own (interface held fixed for both).
    Phi_a, Psi_a, _ = craig_bampton(MA, KA, a_int, c, red.a_modes, red.a_cutoff_hz)
    Phi_b, Psi_b, f_b = craig_bampton(MB, KB, b_int, c, red.b_modes, red.b_cutoff_hz)
    na, nb, nc = Phi_a.shape[1], Phi_b.shape[1], len(c)
    T = np.zeros((n, na + nb + nc))
    T[np.ix_(a_int, np.arange(na))] = Phi_a
    T[np.ix_(a_int, na + nb + np.arange(nc))] = Psi_a
    T[np.ix_(b_int, na + np.arange(nb))] = Phi_b
    T[np.ix_(b_int, na + nb + np.arange(nc))] = Psi_b
    T[c, na + nb + np.arange(nc)] = 1.0
    A_part = tuple(T.T @ m @ T for m in (MA, DA, KA))
    b_index = np.arange(na, na + nb + nc)
    sub = tuple((T.T @ m @ T)[np.ix_(b_index, b_index)] for m in (MB, DB, KB))
    sub = tuple(0.5 * (s + s.T) for s in sub)
    A_part = tuple(0.5 * (s + s.T) for s in A_part)
    return ReducedModel(fe=fe, T=T, A_part=A_part, subsystem=ReducedSubsystem(*sub, n_c=nc, mode_frequencies_hz=f_b), b_index=b_index)


# -- frequency-domain functionals of subsystem B ---------------------------------------------------
#: M, D and K must be symmetric: max |A − Aᵀ| <= SYMMETRY_RTOL · max |A| for each of them.
SYMMETRY_RTOL = 1e-8


def _check_functional_inputs(M, D, K, n_c) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """M, D, K as real finite symmetric (..., n, n) arrays of one n with broadcastable batch axes, and
    n_c an integer in [1, n]; each refused naming it."""
    out = []
    for name, a in (("M", M), ("D", D), ("K", K)):
        a = numeric_array(name, a, dtype=float)  # real and finite: complex, bool, strings, NaN refused
        if a.ndim < 2 or a.shape[-1] != a.shape[-2] or a.shape[-1] < 1:
            raise SpecificationError(name, Described(f"array of shape {a.shape}"),
                                     "must be a square matrix (..., n, n) with n >= 1 (optional batch axes)")
        out.append(a)
    n = out[0].shape[-1]
    for name, a in zip(("D", "K"), out[1:]):
        if a.shape[-1] != n:
            raise SpecificationError(name, Described(f"array of shape {a.shape}"), f"must be (..., {n}, {n}) like M")
    try:
        np.broadcast_shapes(*(a.shape[:-2] for a in out))
    except ValueError:
        raise SpecificationError("M, D, K", Described(f"batch shapes {[a.shape[:-2] for a in out]}"),
                                 "their batch axes must broadcast together") from None
    for name, a in zip(("M", "D", "K"), out):
        scale = float(np.max(np.abs(a), initial=0.0))
        asym = float(np.max(np.abs(a - np.swapaxes(a, -1, -2)), initial=0.0))
        if asym > SYMMETRY_RTOL * scale:
            raise SpecificationError(name, Described(f"matrix with max |{name} - {name}ᵀ| = {asym:.3g} "
                                                     f"(max |entry| = {scale:.3g})"),
                                     f"must be symmetric (within {SYMMETRY_RTOL:g} of its largest |entry|)")
    n_c = integer("n_c", n_c, minimum=1, maximum=n)
    return out[0], out[1], out[2], n_c


def condensed_stiffness(M: np.ndarray, D: np.ndarray, K: np.ndarray, n_c: int, omega: np.ndarray) -> np.ndarray:
    """Condensed dynamic stiffness Z(ω) = A_cc − A_cy A_yy⁻¹ A_yc on the interface [N/m].

    Parameters
    ----------
    M, D, K : numpy.ndarray
        Reduced matrices of B, shape (..., n, n) with optional batch axes (broadcast together);
        real, finite and symmetric (max |A − Aᵀ| <= :data:`SYMMETRY_RTOL` · max |A|); the last
        ``n_c`` coordinates are the interface.
    n_c : int
        Number of interface coordinates, an integer in [1, n].
    omega : array_like
        Angular frequencies [rad/s], a non-empty 1-D array of real finite numbers (any sign).

    Returns
    -------
    numpy.ndarray
        Complex, shape (..., len(omega), n_c, n_c).
    """
    M, D, K, n_c = _check_functional_inputs(M, D, K, n_c)
    w = numeric_array("omega", omega, dtype=float)
    if w.ndim != 1 or w.size == 0:
        raise SpecificationError("omega", Described(f"array of shape {w.shape}"),
                                 "must be a non-empty 1-D array of angular frequencies (rad/s)")
    M, D, K = (x[..., None, :, :] for x in (M, D, K))
    w = w[:, None, None]
    A = K - w**2 * M + 1j * w * D
    y, cc = slice(0, A.shape[-1] - n_c), slice(A.shape[-1] - n_c, None)
    Ayy, Ayc, Acy, Acc = A[..., y, y], A[..., y, cc], A[..., cc, y], A[..., cc, cc]
    if Ayy.shape[-1] == 0:
        return Acc
    return Acc - Acy @ np.linalg.solve(Ayy, Ayc)


def _check_mass(M: np.ndarray, n_c: int) -> None:
    """M positive definite, else refused naming the cause.

    M_B mixes units: its fixed-interface modal coordinates have unit mass, its interface coordinates a
    mass in kg (B's mass moved by a static mode), so its eigenvalue ratio says nothing by itself (a
    density of 1e10 kg/m³ made the paper's M_B look singular). It is refused when its least eigenvalue is
    at most 1e-12 of its largest both as it is and scaled to a unit diagonal (D^-1/2 M D^-1/2, D = diag M):
    then either an interface coordinate carries almost no mass (below 1e-6 of the largest eigenvalue, or
    none: the links joining B to A are far softer than B, whose static modes then hardly move it), or the
    fixed-interface modes, with the static modes, span more than B's DOFs."""
    ev = np.linalg.eigvalsh(M)
    if np.any(ev[..., 0] <= 1e-12 * ev[..., -1]):
        with np.errstate(divide="ignore", invalid="ignore"):
            share = np.nan_to_num(np.diagonal(M, axis1=-2, axis2=-1)[..., M.shape[-1] - n_c:] / ev[..., -1:], nan=0.0)
        if float(np.min(share)) < 1e-6:
            rule = (f"the reduced mass must be positive definite: an interface coordinate of B carries only "
                    f"{float(np.min(share)):.2g} of its largest reduced mass, so the links joining B to A there are "
                    "far softer than B (B is hardly coupled: Z -> 0 and J grows without bound as the links soften; "
                    "B's static modes hardly move it): stiffen the links (links[*].stiffness) or remove them, or "
                    "make B's tubes less stiff (youngs_modulus)")
            raise SpecificationError("M_B", f"min eigenvalue {float(np.min(ev[..., 0])):.3g}", rule)
        d = np.sqrt(np.diagonal(M, axis1=-2, axis2=-1))
        scaled = np.linalg.eigvalsh(M / (d[..., :, None] * d[..., None, :]))
        if np.any(scaled[..., 0] <= 1e-12 * scaled[..., -1]):
            rule = ("the reduced mass must be positive definite: keep fewer fixed-interface modes of B "
                    "(reduction.b_modes / b_cutoff_hz); with every mode kept the massless interface makes M_B singular")
            raise SpecificationError("M_B", f"min eigenvalue {float(np.min(ev[..., 0])):.3g}", rule)


def _log_integral(a: np.ndarray, Omega: float) -> np.ndarray:
    """I(a) = ∫_{−Ω}^{Ω} dω/(iω − a) for Re(a) < 0, to full relative precision in its real and imaginary parts.

    With a = −α + iβ (α > 0): Re I = atan((Ω − β)/α) + atan((Ω + β)/α) = atan2(2Ωα, α² + β² − Ω²) and
    Im I = −½ ln[(α² + (Ω − β)²) / (α² + (Ω + β)²)], the latter through log1p(−4Ωβ / (α² + (Ω + β)²)) when the
    ratio is near 1. The plain difference of logarithms −i[Log(iΩ − a) − Log(−iΩ − a)] cancels for a pole far
    outside the band (|a| ≫ Ω: it keeps about 16 − log10(|a|/Ω) digits), and J needs Re I of a lightly damped
    pole (Re I ≈ 2Ωα/|a|², a fraction α/|a| of |I|): a stiff subsystem B, whose poles lie 1e8 times above the band
    with damping ratios near 1e-7, lost every digit of J that way. Scaling by max(α, |β|, Ω) keeps the squares
    in range.
    """
    alpha, beta = -a.real, a.imag
    scale = np.maximum(np.maximum(np.abs(alpha), np.abs(beta)), Omega)
    al, be, om = alpha / scale, beta / scale, Omega / scale
    real = np.arctan2(2.0 * om * al, al * al + be * be - om * om)
    below, above = al * al + (om - be) ** 2, al * al + (om + be) ** 2  # |iΩ − a|², |−iΩ − a|² (scaled)
    x = -4.0 * om * be / above  # below / above − 1, without cancellation
    near = np.abs(x) < 0.5
    log_ratio = np.where(near, np.log1p(np.where(near, x, 0.0)), np.log(below) - np.log(above))
    return real - 0.5j * log_ratio


def j_functional(M: np.ndarray, D: np.ndarray, K: np.ndarray, n_c: int, band_hz: float) -> np.ndarray:
    """J = ∫_{−Ω}^{Ω} ‖Z(ω)⁻¹‖²_F dω with Ω = 2π·band_hz, in closed form from the poles of B.

    Parameters
    ----------
    M, D, K : numpy.ndarray
        Reduced matrices of B, shape (..., n, n) with optional batch axes (broadcast together);
        real, finite and symmetric (max |A − Aᵀ| <= :data:`SYMMETRY_RTOL` · max |A|); the last
        ``n_c`` coordinates are the interface. M must be positive definite and every pole damped.
    n_c : int
        Number of interface coordinates, an integer in [1, n].
    band_hz : float
        Half-width of the band [Hz], a finite number > 0.

    Returns
    -------
    numpy.ndarray
        J [m²·rad/(N²·s)] (``J_UNITS``), shape (...) — a 0-d array without batch axes.
    """
    M, D, K, n_c = _check_functional_inputs(M, D, K, n_c)
    band_hz = positive("band_hz", band_hz, "Hz")
    n = M.shape[-1]
    _check_mass(M, n_c)
    Omega = 2 * np.pi * band_hz
    MinvK = np.linalg.solve(M, K)
    MinvD = np.linalg.solve(M, D)
    batch = MinvK.shape[:-2]
    S = np.zeros(batch + (2 * n, 2 * n))
    S[..., :n, n:] = np.eye(n)
    S[..., n:, :n] = -MinvK
    S[..., n:, n:] = -MinvD
    lam, V = np.linalg.eig(S)
    if np.any(lam.real >= 0):
        raise SpecificationError("damping", "D_B", "every pole of subsystem B must be damped (Re λ < 0) for J to be finite")
    phi = V[..., :n, :]
    a = np.einsum("...ik,...ik->...k", phi, (2 * lam[..., None, :]) * (M @ phi) + D @ phi)
    v = phi[..., n - n_c :, :]
    C = np.einsum("...cl,...ck->...lk", v.conj(), v)  # C[l, k] = v_l^H v_k
    coef = C**2 / (a[..., None, :] * a.conj()[..., :, None])  # [l, k]
    Ik = _log_integral(lam, Omega)
    Il = _log_integral(lam.conj(), Omega)
    P = -(Ik[..., None, :] + Il[..., :, None]) / (lam[..., None, :] + lam.conj()[..., :, None])
    return np.real(np.sum(coef * P, axis=(-2, -1)))


def j_of_spec(spec: BundleSpec, sub: ReducedSubsystem) -> float:
    """J of a specification's mean reduced B over its band, refusals naming the specification's fields.

    Parameters
    ----------
    spec : BundleSpec
        The bundle.
    sub : ReducedSubsystem
        Its reduced B (``reduce(spec).subsystem``), with n_c >= 1.

    Returns
    -------
    float
        J [m²·rad/(N²·s)] (:func:`j_functional`). An undamped pole of B is refused naming the first
        tube of B whose ``damping_ratio`` is 0 (``tubes[i].damping_ratio``) when there is one.
    """
    try:
        return float(j_functional(sub.M, sub.D, sub.K, sub.n_c, spec.band_hz))
    except SpecificationError as exc:
        if exc.field != "damping":
            raise
        for i, t in enumerate(spec.tubes):
            if t.name != spec.a_tube and t.damping_ratio == 0:
                raise SpecificationError(
                    f"tubes[{i}].damping_ratio", t.damping_ratio,
                    f"tube {t.name!r} is in subsystem B (every tube but the non-linear tube {spec.a_tube!r}), whose "
                    "every pole must be damped (Re λ < 0) for J = ∫ ‖Z(ω)⁻¹‖²_F dω: with damping ratio 0 its modes "
                    "are undamped (links are undamped too) and an undamped pole in the band makes J infinite; "
                    "give it a damping ratio in (0, 1)") from None
        raise


def j_quadrature(M, D, K, n_c: int, band_hz: float, n_freq: int = 20001) -> np.ndarray:
    """J by composite Simpson quadrature of ‖Z(ω)⁻¹‖²_F on [0, Ω], doubled (Z(−ω) = conj Z(ω)).

    A straightforward reference, independent of the pole expansion of :func:`j_functional`.
    """
    if n_freq % 2 == 0:
        n_freq += 1
    import scipy.integrate

    omega = np.linspace(0.0, 2 * np.pi * band_hz, n_freq)
    Z = condensed_stiffness(M, D, K, n_c, omega)
    g = np.sum(np.abs(np.linalg.inv(Z)) ** 2, axis=(-2, -1))
    return 2.0 * scipy.integrate.simpson(g, x=omega, axis=-1)
