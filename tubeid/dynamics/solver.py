"""Fast transient solver for linear structures with symmetric elastic stops.

Equation (SI units, q in reduced coordinates)::

    M q'' + D q' + K q + sum_s b_s f_s(b_s^T q) = B F(t),     y = C q,
    f_s(u) = k_s (|u| - g_s) sign(u)  if |u| > g_s  else 0.

``F`` is given by samples on a uniform grid of step ``dt_load`` and is the continuous
piecewise-linear (PL) interpolant of these samples. Initial state q = q' = 0.

Method ``"exact"`` (default). The system is piecewise linear: each stop is open, in contact on
the + side or on the - side, so there are 3**S regimes. In each regime the first-order
system x = [q; q'] is diagonalised, x = x_eq + sum_i w_i Re(V_i z_i) (only one mode of each
complex-conjugate pair is kept, w_i = 2; real modes keep w_i = 1), and the modal equations
z_i' = lam_i z_i + W_i F(t) are integrated EXACTLY for a PL load:
z(t + s) = e^{lam s} z(t) + P0(s) W F(t) + P1(s) W F', with P0(s) = (e^{lam s} - 1)/lam and
P1(s) = (e^{lam s} - 1 - lam s)/lam^2. A step of length ``dt`` costs O(N) per mode set (the
coefficients are tabulated; W F is formed once per load sample), no matrix product. Between
regimes nothing is approximated except the location of the switching instants, found by
safeguarded Newton on the exact closed form u(t) = b^T q(t) (tolerance ~1e-13 dt). A switch
maps z through a precomputed real transition matrix (continuity of x).

Event detection. At each step end the solver has u and u' exactly. A crossing is flagged when
the distance to the boundary changes sign, or when the cubic Hermite interpolant of
(u, u') over the step has an interior extremum that comes within a margin of the boundary
(margin = 4 (w h)^4/384 max|u'|/w, w = 2 pi f_max: a bound of the Hermite error for a
component at the highest frequency, with safety factor 4). A flagged step is re-examined
exactly on 8 sub-intervals, interior extrema are located by Newton on u' = 0 using the exact
u'', and the first crossing is located by safeguarded Newton. Hence the only approximation
left is to miss a grazing excursion whose depth is below the Hermite error of a 1/8 step.

Step rule (``choose_step``): with f_max the highest undamped frequency with every stop
closed (it bounds every regime), the default step is the largest divisor of dt_load and
output_dt with dt <= 1/(STEP_POINTS_PER_PERIOD f_max) (8 points per shortest period).
A user step dt > 1/(2 f_max) is refused (a whole contact oscillation can then fall inside
one step unseen); dt > 1/(4 f_max) is accepted with a warning (the Hermite pre-check is
then no better than ~1.6 % of the highest mode's amplitude).

Method ``"symplectic-euler"`` (industrial modal codes): v += dt M^-1 (B F - D v - K q - f);
q += dt v. Stable for w_max dt < 2 (w_max with every stop closed): refused beyond; warned
when w_max dt > 0.5 (frequency error of the highest mode (w dt)^2/24 above ~1 %); default
w_max dt <= 0.25. The paper's 3 ms is the OUTPUT sampling (MODEL.md section 3.7): as an
integration step it is refused by both methods.
"""

from __future__ import annotations

import cmath
import math
import warnings
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Sequence

import numba
import numpy as np
import scipy.linalg
import xarray as xr

from tubeid.errors import SpecificationError

__all__ = [
    "Stop",
    "TransientResult",
    "simulate",
    "simulate_baseline",
    "highest_frequency",
    "choose_step",
    "exact_step_flops",
    "STEP_POINTS_PER_PERIOD",
    "MAX_STOPS",
]

#: Default points per period of the highest closed-regime frequency for the exact method.
STEP_POINTS_PER_PERIOD = 8
#: Exact method: a user step above 1/(REFUSE_POINTS f_max) is refused, above 1/(WARN_POINTS f_max) warned.
_EXACT_REFUSE_POINTS = 2.0
_EXACT_WARN_POINTS = 4.0
#: Symplectic Euler: refuse w dt >= 2, warn w dt > 0.5, default w dt <= 0.25.
_SE_STABLE = 2.0
_SE_WARN = 0.5
_SE_DEFAULT = 0.25
#: Safety factor on the Hermite-error margin of the event pre-check.
_MARGIN_SAFETY = 4.0
#: Number of sub-intervals of the exact re-examination of a flagged step.
_N_REFINE = 8
#: At most 3**MAX_STOPS regimes are tabulated.
MAX_STOPS = 3
_METHODS = ("exact", "symplectic-euler")
_KEEPS = ("series", "stats")


# ----------------------------------------------------------------------------------------------
# Specifications and results
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Stop:
    """A symmetric elastic stop acting on u = b^T q.

    b: direction vector (length N of the model's coordinates, stored as a tuple); gap: g >= 0 (m);
    stiffness: k >= 0 (N/m). Force on the structure: -b k (|u| - g) sign(u) for |u| > g.
    A zero gap makes the stop a linear spring k b b^T (always in contact).
    """

    b: tuple
    gap: float
    stiffness: float
    name: str = ""

    def __post_init__(self):
        try:
            b = np.asarray(self.b, dtype=float).ravel()
        except (TypeError, ValueError):
            raise SpecificationError("stop.b", self.b, "must be a vector of real numbers") from None
        if b.size == 0 or not np.all(np.isfinite(b)) or not np.any(b != 0):
            raise SpecificationError("stop.b", self.b, "must be a finite, non-zero vector")
        object.__setattr__(self, "b", tuple(float(v) for v in b))
        for name in ("gap", "stiffness"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
                raise SpecificationError(f"stop.{name}", v, "must be a real number")
            if not math.isfinite(float(v)) or float(v) < 0:
                unit = "m" if name == "gap" else "N/m"
                raise SpecificationError(f"stop.{name}", v, f"must be finite and >= 0 {unit}")
            object.__setattr__(self, name, float(v))
        if not isinstance(self.name, str):
            raise SpecificationError("stop.name", self.name, "must be a string")

    @property
    def vector(self) -> np.ndarray:
        return np.array(self.b)


@dataclass(frozen=True)
class TransientResult:
    """Output of :func:`simulate`.

    observations: DataArray (realisation, time, sensor) in the units of C q (None if keep="stats");
    rms: (realisation, sensor) root mean square (not centred) of the observation samples at
    output_dt for t >= discard; contact_fraction: (realisation, stop) fraction of [discard, T]
    spent with |u| > g (event-exact for the exact method, per step for symplectic Euler);
    contact_events: (realisation, stop) number of open -> contact transitions in [discard, T].
    dt: (realisation,) integration step used (s).
    """

    observations: xr.DataArray | None
    rms: xr.DataArray
    contact_fraction: xr.DataArray
    contact_events: xr.DataArray
    dt: xr.DataArray
    method: str
    output_dt: float
    discard: float

    def to_dataset(self) -> xr.Dataset:
        data = {
            "rms": self.rms,
            "contact_fraction": self.contact_fraction,
            "contact_events": self.contact_events,
            "dt": self.dt,
        }
        if self.observations is not None:
            data["observations"] = self.observations
        ds = xr.Dataset(data)
        ds.attrs.update(method=self.method, output_dt=self.output_dt, discard=self.discard)
        return ds


# ----------------------------------------------------------------------------------------------
# Validation helpers
# ----------------------------------------------------------------------------------------------


def _as_matrix_stack(name, a, n=None):
    try:
        arr = np.asarray(a, dtype=float)
    except (TypeError, ValueError):
        raise SpecificationError(name, type(a).__name__, "must be a real array") from None
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[1] != arr.shape[2] or arr.shape[1] == 0:
        raise SpecificationError(f"{name}.shape", arr.shape, "must be (N, N) or (R, N, N)")
    if n is not None and arr.shape[1] != n:
        raise SpecificationError(f"{name}.shape", arr.shape, f"must have N = {n} like M")
    if not np.all(np.isfinite(arr)):
        raise SpecificationError(name, "non-finite entries", "must be finite")
    scale = np.max(np.abs(arr), axis=(1, 2), keepdims=True)
    if np.any(np.abs(arr - arr.transpose(0, 2, 1)) > 1e-10 * np.maximum(scale, 1e-300)):
        raise SpecificationError(name, "non-symmetric", "must be symmetric (rel. tol 1e-10)")
    return 0.5 * (arr + arr.transpose(0, 2, 1))


def _check_definite(name, arr, strict):
    for r, a in enumerate(arr):
        w = np.linalg.eigvalsh(a)
        top = max(abs(w[-1]), 1e-300)
        if strict and w[0] <= 1e-13 * top:
            raise SpecificationError(name, f"realisation {r}: min eigenvalue {w[0]:.3g}", "must be positive definite")
        if not strict and w[0] < -1e-10 * top:
            raise SpecificationError(name, f"realisation {r}: min eigenvalue {w[0]:.3g}", "must be positive semi-definite")


def _validate_stops(stops, n):
    if isinstance(stops, Stop):
        stops = (stops,)
    try:
        stops = tuple(stops)
    except TypeError:
        raise SpecificationError("stops", stops, "must be a sequence of Stop") from None
    for i, s in enumerate(stops):
        if not isinstance(s, Stop):
            raise SpecificationError(f"stops[{i}]", s, "must be a tubeid.dynamics.solver.Stop")
        if len(s.b) != n:
            raise SpecificationError(f"stops[{i}].b", f"length {len(s.b)}", f"must have length N = {n}")
    return stops


def _positive(name, v):
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not math.isfinite(v) or v <= 0:
        raise SpecificationError(name, v, "must be a finite number > 0 (s)")
    return float(v)


def _frac(x):
    return Fraction(x).limit_denominator(10**12)


def _divides(dt, big):
    """True if ``big`` is an integer multiple of ``dt`` (relative tolerance 1e-9)."""
    r = big / dt
    return abs(r - round(r)) <= 1e-9 * max(r, 1.0) and round(r) >= 1


# ----------------------------------------------------------------------------------------------
# Frequencies and step selection
# ----------------------------------------------------------------------------------------------


def highest_frequency(M, K, stops=()):
    """Highest undamped eigenfrequency (Hz) with every stop closed (K + sum k b b^T, M).

    Adding the positive semi-definite stop stiffnesses raises every eigenvalue, so this bounds the
    frequencies of all regimes. Returns a float for (N, N) matrices, an array (R,) for stacks.
    """
    Ms = _as_matrix_stack("M", M)
    Ks = _as_matrix_stack("K", K, Ms.shape[1])
    stops = _validate_stops(stops, Ms.shape[1])
    R = max(len(Ms), len(Ks))
    if len(Ms) not in (1, R) or len(Ks) not in (1, R):
        raise SpecificationError("K.shape", Ks.shape, f"realisation axis must match M ({Ms.shape[0]})")
    closed = sum((s.stiffness * np.outer(s.vector, s.vector) for s in stops), np.zeros(Ms.shape[1:]))
    out = np.empty(R)
    for r in range(R):
        w2 = scipy.linalg.eigh(Ks[r % len(Ks)] + closed, Ms[r % len(Ms)], eigvals_only=True)
        out[r] = math.sqrt(max(w2[-1], 0.0)) / (2 * math.pi)
    if np.ndim(M) == 2 and np.ndim(K) == 2:
        return float(out[0])
    return out


def _step_limit(f_max, method):
    """Largest admissible default step (s) for a highest frequency f_max (Hz)."""
    if method == "exact":
        return 1.0 / (STEP_POINTS_PER_PERIOD * f_max)
    return _SE_DEFAULT / (2 * math.pi * f_max)


def check_step(dt, f_max, method, *, field_name="dt"):
    """Refuse (SpecificationError) or warn about a user step ``dt`` for highest frequency ``f_max``."""
    note = (" Note: the paper's 3 ms is the output sampling of the response, not an integration "
            "step (MODEL.md section 3.7).") if dt >= 2.9e-3 else ""
    if method == "exact":
        if dt * f_max > 1.0 / _EXACT_REFUSE_POINTS:
            raise SpecificationError(
                field_name, dt,
                f"exact method needs dt <= 1/(2 f_max) = {1 / (2 * f_max):.4g} s (f_max = {f_max:.4g} Hz, "
                f"highest frequency with the stops closed): a coarser step can hide whole contact "
                f"oscillations.{note}")
        if dt * f_max > 1.0 / _EXACT_WARN_POINTS:
            warnings.warn(
                f"dt = {dt:.4g} s exceeds 1/(4 f_max) = {1 / (4 * f_max):.4g} s (f_max = {f_max:.4g} Hz): "
                f"grazing contacts may be missed (rule: dt <= 1/(4 f_max), default 1/(8 f_max))",
                stacklevel=3)
    else:
        w = 2 * math.pi * f_max
        if w * dt >= _SE_STABLE:
            raise SpecificationError(
                field_name, dt,
                f"symplectic Euler is unstable for dt >= 2/w_max = {2 / w:.4g} s (f_max = {f_max:.4g} Hz "
                f"with the stops closed).{note}")
        if w * dt > _SE_WARN:
            warnings.warn(
                f"dt = {dt:.4g} s gives w_max dt = {w * dt:.3g} > 0.5: symplectic Euler frequency error of the "
                f"highest mode above 1 % (rule: w_max dt <= 0.5, default 0.25)", stacklevel=3)


def choose_step(f_max, dt_load, output_dt=3e-3, method="exact", dt=None):
    """Integration step (s) for highest frequency ``f_max`` (Hz).

    dt=None: the largest step dividing both dt_load and output_dt that satisfies the method's
    default rule (exact: dt <= 1/(8 f_max); symplectic Euler: 2 pi f_max dt <= 0.25). A given dt
    must divide dt_load and output_dt; it is refused when unstable and warned when inaccurate
    (see module docstring).
    """
    if method not in _METHODS:
        raise SpecificationError("method", method, f"must be one of {_METHODS}")
    f_max = _positive("f_max", f_max)
    dt_load = _positive("dt_load", dt_load)
    output_dt = _positive("output_dt", output_dt)
    if dt is not None:
        dt = _positive("dt", dt)
        check_step(dt, f_max, method)
        for nm, big in (("dt_load", dt_load), ("output_dt", output_dt)):
            if not _divides(dt, big):
                raise SpecificationError("dt", dt, f"{nm} = {big} s must be an integer multiple of dt")
        return dt
    a, b = _frac(dt_load), _frac(output_dt)
    base = Fraction(math.gcd(a.numerator * b.denominator, b.numerator * a.denominator), a.denominator * b.denominator)
    base_f = float(base)
    if not (_divides(base_f, dt_load) and _divides(base_f, output_dt)) or base_f < 1e-9 * max(dt_load, output_dt):
        raise SpecificationError("output_dt", output_dt, f"must be commensurate with dt_load = {dt_load} s")
    n = max(1, math.ceil(base_f / _step_limit(f_max, method) - 1e-9))
    return base_f / n


# ----------------------------------------------------------------------------------------------
# Modal tables of the regimes (pure numpy; per realisation)
# ----------------------------------------------------------------------------------------------


def _regime_codes(S):
    """(3**S, S) int8: 0 open, +1 contact on + side, -1 contact on - side."""
    codes = np.zeros((3**S, S), dtype=np.int8)
    for r in range(3**S):
        x = r
        for s in range(S):
            codes[r, s] = (0, 1, -1)[x % 3]
            x //= 3
    return codes


def _phi_coeffs(lam, tau):
    """e^{lam tau}, P0(tau), P1(tau) for complex arrays (series for small |lam tau|)."""
    x = lam * tau
    e = np.exp(x)
    small = np.abs(x) < 0.1
    xs = np.where(small, 1.0, x)
    phi1 = np.where(small, 0, (e - 1) / xs)
    phi2 = np.where(small, 0, (e - 1 - x) / xs**2)
    s1 = np.zeros_like(x)
    s2 = np.zeros_like(x)
    term1 = np.ones_like(x)  # x^k/(k+1)!
    term2 = np.full_like(x, 0.5)  # x^k/(k+2)!
    for k in range(14):
        s1 = s1 + term1
        s2 = s2 + term2
        term1 = term1 * x / (k + 2)
        term2 = term2 * x / (k + 3)
    phi1 = np.where(small, s1, phi1)
    phi2 = np.where(small, s2, phi2)
    return e, tau * phi1, tau * tau * phi2


@dataclass
class _Tables:
    """Everything the exact kernel needs for one realisation (arrays stacked over regimes)."""

    lam: np.ndarray  # (nr, n2) complex
    E: np.ndarray  # (nr, 2, n2)  re/im of e^{lam h}
    A: np.ndarray  # (nr, ns, 2, n2) coefficient on W F_k for sub-step j
    Bc: np.ndarray  # (nr, ns, 2, n2) coefficient on W F_{k+1}
    W: np.ndarray  # (nr, m, 2, n2)
    cu: np.ndarray  # (nr, S, 2, n2)  u = ueq + sum Re(cu z)
    cv: np.ndarray  # (nr, S, 2, n2)  u' = sum Re(cv z)
    ueq: np.ndarray  # (nr, S)
    cy: np.ndarray  # (nr, n_obs, 2, n2)
    yeq: np.ndarray  # (nr, n_obs)
    codes: np.ndarray  # (nr, S) int64
    trans_id: np.ndarray  # (nr, S, 2) int64 (-1: none)
    trans_to: np.ndarray  # (nt,) int64
    T: np.ndarray  # (nt, 2 n2, 2 n2)
    c: np.ndarray  # (nt, 2 n2)
    gaps: np.ndarray  # (S,)
    omega_max: float
    cond_max: float = 0.0
    half: bool = True


def _split(a):
    return np.ascontiguousarray(np.stack([a.real, a.imag], axis=-2))


def _build_tables(M, D, K, stops, B, C, h, ns, dt_load):
    N = M.shape[0]
    S = len(stops)
    codes = _regime_codes(S)
    nr = len(codes)
    Minv = np.linalg.inv(M)
    Minv = 0.5 * (Minv + Minv.T)
    bs = [s.vector for s in stops]
    eig = []
    all_complex = True
    for r in range(nr):
        Kr = K.copy()
        fr = np.zeros(N)
        for s, st in enumerate(stops):
            if codes[r, s] != 0:
                Kr += st.stiffness * np.outer(bs[s], bs[s])
                fr += st.stiffness * st.gap * codes[r, s] * bs[s]
        q_eq = np.linalg.solve(Kr, fr)
        A = np.block([[np.zeros((N, N)), np.eye(N)], [-Minv @ Kr, -Minv @ D]])
        lam, V = np.linalg.eig(A)
        if np.any(lam.imag == 0):
            all_complex = False
        eig.append((lam, V, q_eq))
    omega_max = 2 * math.pi * highest_frequency(M, K + sum((st.stiffness * np.outer(b, b) for st, b in zip(stops, bs)), np.zeros((N, N))), ())
    lam_l, V_l, Vinv_l, w_l, xeq_l = [], [], [], [], []
    cond_max = 0.0
    for lam, V, q_eq in eig:
        Vinv = np.linalg.inv(V)
        cond_max = max(cond_max, np.linalg.cond(V))
        if all_complex:
            keep = np.flatnonzero(lam.imag > 0)
            if len(keep) != N:
                raise RuntimeError("eigenvalues are not in conjugate pairs")
            w = np.full(len(keep), 2.0)
        else:
            keep = np.arange(2 * N)
            w = np.ones(2 * N)
        lam_l.append(lam[keep])
        V_l.append(V[:, keep])
        Vinv_l.append(Vinv[keep])
        w_l.append(w)
        xeq_l.append(np.concatenate([q_eq, np.zeros(N)]))
    n2 = len(lam_l[0])
    lam = np.array(lam_l)
    Bx = np.vstack([np.zeros_like(B), Minv @ B])
    W = np.array([Vinv_l[r] @ Bx for r in range(nr)])  # (nr, n2, m)
    e, P0, P1 = _phi_coeffs(lam, h)
    theta = np.arange(ns) / ns
    Acoef = P0[:, None, :] * (1 - theta[None, :, None]) - P1[:, None, :] / dt_load
    Bcoef = P0[:, None, :] * theta[None, :, None] + P1[:, None, :] / dt_load
    cu = np.zeros((nr, S, n2), complex)
    cv = np.zeros((nr, S, n2), complex)
    ueq = np.zeros((nr, S))
    cy = np.zeros((nr, C.shape[0], n2), complex)
    yeq = np.zeros((nr, C.shape[0]))
    for r in range(nr):
        Vw = V_l[r] * w_l[r][None, :]
        for s in range(S):
            cu[r, s] = bs[s] @ Vw[:N]
            cv[r, s] = bs[s] @ Vw[N:]
            ueq[r, s] = bs[s] @ xeq_l[r][:N]
        cy[r] = C @ Vw[:N]
        yeq[r] = C @ xeq_l[r][:N]
    # transitions between regimes differing in one stop
    trans_id = -np.ones((nr, S, 2), dtype=np.int64)
    trans_to, Ts, cs = [], [], []
    index = {tuple(c): r for r, c in enumerate(codes)}
    for r in range(nr):
        Vw = V_l[r] * w_l[r][None, :]
        X = np.hstack([Vw.real, -Vw.imag])  # x - x_eq = X [zr; zi]
        for s in range(S):
            targets = (1, -1) if codes[r, s] == 0 else (0,)
            for d, newc in enumerate(targets):
                c2 = codes[r].copy()
                c2[s] = newc
                r2 = index[tuple(c2)]
                Vi = Vinv_l[r2]
                Tc = np.vstack([Vi.real @ X, Vi.imag @ X])
                off = Vi @ (xeq_l[r] - xeq_l[r2])
                trans_id[r, s, d] = len(Ts)
                trans_to.append(r2)
                Ts.append(Tc)
                cs.append(np.concatenate([off.real, off.imag]))
    if not Ts:
        Ts = [np.zeros((2 * n2, 2 * n2))]
        cs = [np.zeros(2 * n2)]
        trans_to = [0]
    return _Tables(
        lam=np.ascontiguousarray(lam), E=_split(e), A=_split(Acoef), Bc=_split(Bcoef),
        W=_split(np.transpose(W, (0, 2, 1))), cu=_split(cu), cv=_split(cv), ueq=ueq,
        cy=_split(cy), yeq=yeq, codes=codes.astype(np.int64), trans_id=trans_id,
        trans_to=np.array(trans_to, dtype=np.int64), T=np.ascontiguousarray(np.array(Ts)),
        c=np.ascontiguousarray(np.array(cs)), gaps=np.array([s.gap for s in stops], float),
        omega_max=omega_max, cond_max=cond_max, half=all_complex)


# ----------------------------------------------------------------------------------------------
# Numba kernels
# ----------------------------------------------------------------------------------------------

_FM = {"reassoc", "contract"}  # reassociation (vectorised sums) and FMA; no NaN/Inf assumptions


@numba.njit(cache=True)
def _advance_c(lam, z0, g0, gs, sigma, out):
    """out = e^{lam sigma} z0 + P0(sigma) g0 + P1(sigma) gs (exact for a linear forcing g0 + gs t)."""
    for i in range(lam.shape[0]):
        x = lam[i] * sigma
        e = cmath.exp(x)
        if abs(x) < 0.1:
            s1 = 0j
            s2 = 0j
            t1 = 1.0 + 0j
            t2 = 0.5 + 0j
            for k in range(14):
                s1 += t1
                s2 += t2
                t1 = t1 * x / (k + 2)
                t2 = t2 * x / (k + 3)
            p0 = sigma * s1
            p1 = sigma * sigma * s2
        else:
            p0 = sigma * (e - 1.0) / x
            p1 = sigma * sigma * (e - 1.0 - x) / (x * x)
        out[i] = e * z0[i] + p0 * g0[i] + p1 * gs[i]


@numba.njit(cache=True)
def _dist(code, side, g, u, ud, udd):
    """Distance to the boundary (>= 0 inside the current state) and its time derivatives.

    code 0 (open): side 0 is the +g boundary (g - u), side 1 the -g boundary (u + g);
    code +1: u - g; code -1: -g - u.
    """
    if code == 0:
        if side == 0:
            return g - u, -ud, -udd
        return u + g, ud, udd
    if code == 1:
        return u - g, ud, udd
    return -g - u, -ud, -udd


@numba.njit(cache=True)
def _cubic_min(d0, dd0, d1, dd1, sigma):
    """Interior minimum (s in (0,1), value) of the cubic Hermite interpolant; s = -1 if none."""
    a = 2 * d0 + sigma * dd0 - 2 * d1 + sigma * dd1
    b = -3 * d0 - 2 * sigma * dd0 + 3 * d1 - sigma * dd1
    c = sigma * dd0
    best_s = -1.0
    best_v = 1e308
    # p'(s) = 3a s^2 + 2b s + c
    qa = 3 * a
    qb = 2 * b
    if abs(qa) < 1e-300:
        if abs(qb) > 0:
            s = -c / qb
            if 0 < s < 1 and qb > 0:  # p'' = 2b > 0: minimum
                best_s = s
                best_v = ((a * s + b) * s + c) * s + d0
        return best_s, best_v
    disc = qb * qb - 4 * qa * c
    if disc < 0:
        return best_s, best_v
    sq = math.sqrt(disc)
    for sgn in (-1.0, 1.0):
        s = (-qb + sgn * sq) / (2 * qa)
        if 0 < s < 1 and 6 * a * s + 2 * b > 0:
            v = ((a * s + b) * s + c) * s + d0
            if v < best_v:
                best_v = v
                best_s = s
    return best_s, best_v


@numba.njit(cache=True)
def _flag(d0, dd0, d1, dd1, sigma, margin):
    """True if the distance may become negative within the (sub)step."""
    if d1 < 0:
        return True
    d0c = max(d0, 0.0)
    if min(d0c, d1) - 0.15 * sigma * (abs(dd0) + abs(dd1)) >= margin:
        return False
    s, v = _cubic_min(d0c, dd0, d1, dd1, sigma)
    return s >= 0 and v < margin


@numba.njit(cache=True)
def _eval_stops(z, lamr, gnow, cu, cv, ueq, u, ud, udd):
    """u, u', u'' of every stop from the complex modal state z and current modal forcing gnow."""
    S = cu.shape[0]
    n2 = z.shape[0]
    for s in range(S):
        a = ueq[s]
        b = 0.0
        c = 0.0
        for i in range(n2):
            zi = z[i]
            cus = complex(cu[s, 0, i], cu[s, 1, i])
            cvs = complex(cv[s, 0, i], cv[s, 1, i])
            a += (cus * zi).real
            b += (cvs * zi).real
            c += (cvs * (lamr[i] * zi + gnow[i])).real
        u[s] = a
        ud[s] = b
        udd[s] = c


@numba.njit(cache=True)
def _state_at(lamr, z0, g0, gs, tau, cu, cv, ueq, zt, gt, u, ud, udd):
    """Exact state zt at tau after z0, and u, u', u'' of every stop there."""
    _advance_c(lamr, z0, g0, gs, tau, zt)
    for i in range(zt.shape[0]):
        gt[i] = g0[i] + gs[i] * tau
    _eval_stops(zt, lamr, gt, cu, cv, ueq, u, ud, udd)


@numba.njit(cache=True)
def _wf(Wr, f, out_r, out_i):
    """Modal forcing W f (split re/im) for one load sample f."""
    n2 = out_r.shape[0]
    for i in range(n2):
        out_r[i] = 0.0
        out_i[i] = 0.0
    for k in range(f.shape[0]):
        fk = f[k]
        for i in range(n2):
            out_r[i] += Wr[k, 0, i] * fk
            out_i[i] += Wr[k, 1, i] * fk


@numba.njit(cache=True)
def _event_step(r, zr, zi, g0r, g0i, g1r, g1i, Fk, Fk1, theta0, h, dt_load, count,
                lam, W, cu, cv, ueq, codes, trans_id, trans_to, T, c, gaps, mcoef,
                contact_time, n_events, refine_all):
    """Integrate one step [0, h] exactly with event location; updates z, G (in place). Returns r."""
    S = gaps.shape[0]
    n2 = zr.shape[0]
    z = np.empty(n2, np.complex128)
    G0 = np.empty(n2, np.complex128)
    G1 = np.empty(n2, np.complex128)
    for i in range(n2):
        z[i] = complex(zr[i], zi[i])
        G0[i] = complex(g0r[i], g0i[i])
        G1[i] = complex(g1r[i], g1i[i])
    gs = (G1 - G0) / dt_load
    gstart = np.empty(n2, np.complex128)
    zt = np.empty(n2, np.complex128)
    gt = np.empty(n2, np.complex128)
    u0 = np.empty(S)
    ud0 = np.empty(S)
    udd0 = np.empty(S)
    u1 = np.empty(S)
    ud1 = np.empty(S)
    udd1 = np.empty(S)
    nref = 8
    up = np.empty((nref + 1, S))
    udp = np.empty((nref + 1, S))
    uddp = np.empty((nref + 1, S))
    xr_ = np.empty(2 * n2)
    t_loc = 0.0
    just_switched = False
    for it in range(200):
        sigma = h - t_loc
        if sigma <= 0:
            break
        # modal forcing at t_loc: G(theta) = G0 + (G1 - G0) * (theta - theta0_interval)
        for i in range(n2):
            gstart[i] = G0[i] + gs[i] * (t_loc + theta0 * dt_load)
        lr = lam[r]
        cur = cu[r]
        cvr = cv[r]
        uer = ueq[r]
        _eval_stops(z, lr, gstart, cur, cvr, uer, u0, ud0, udd0)
        _state_at(lr, z, gstart, gs, sigma, cur, cvr, uer, zt, gt, u1, ud1, udd1)
        margin_c = mcoef * (sigma / h) ** 4
        flagged = refine_all
        for s in range(S):
            code = codes[r, s]
            nside = 2 if code == 0 else 1
            for side in range(nside):
                d0, dd0, _ = _dist(code, side, gaps[s], u0[s], ud0[s], udd0[s])
                d1, dd1, _ = _dist(code, side, gaps[s], u1[s], ud1[s], udd1[s])
                if _flag(d0, dd0, d1, dd1, sigma, margin_c * max(abs(dd0), abs(dd1))):
                    flagged = True
        if not flagged:
            break
        # exact re-examination on nref sub-intervals
        for s in range(S):
            up[0, s] = u0[s]
            udp[0, s] = ud0[s]
            uddp[0, s] = udd0[s]
        for p in range(1, nref + 1):
            _state_at(lr, z, gstart, gs, sigma * p / nref, cur, cvr, uer, zt, gt, u1, ud1, udd1)
            for s in range(S):
                up[p, s] = u1[s]
                udp[p, s] = ud1[s]
                uddp[p, s] = udd1[s]
        hsub = sigma / nref
        tau_c = 1e308
        s_c = -1
        side_c = -1
        for p in range(nref):
            for s in range(S):
                code = codes[r, s]
                nside = 2 if code == 0 else 1
                for side in range(nside):
                    da, dda, _ = _dist(code, side, gaps[s], up[p, s], udp[p, s], uddp[p, s])
                    db, ddb, _ = _dist(code, side, gaps[s], up[p + 1, s], udp[p + 1, s], uddp[p + 1, s])
                    if p == 0 and just_switched:
                        da = max(da, 0.0)
                    ta = p * hsub
                    tb = ta + hsub
                    bracket = db < 0
                    if not bracket:
                        sm, vm = _cubic_min(max(da, 0.0), dda, db, ddb, hsub)
                        if sm >= 0 and vm < mcoef * (hsub / h) ** 4 * max(abs(dda), abs(ddb)) * 4 + 0.0:
                            # Newton on d' = 0 for the exact interior minimum
                            tm = ta + sm * hsub
                            dm = 0.0
                            for newton in range(8):
                                _state_at(lr, z, gstart, gs, tm, cur, cvr, uer, zt, gt, u1, ud1, udd1)
                                dm, ddm, dddm = _dist(code, side, gaps[s], u1[s], ud1[s], udd1[s])
                                if dm < 0 or dddm <= 0:
                                    break
                                step = -ddm / dddm
                                tn = min(max(tm + step, ta), tb)
                                if abs(tn - tm) < 1e-13 * h:
                                    tm = tn
                                    _state_at(lr, z, gstart, gs, tm, cur, cvr, uer, zt, gt, u1, ud1, udd1)
                                    dm, ddm, dddm = _dist(code, side, gaps[s], u1[s], ud1[s], udd1[s])
                                    break
                                tm = tn
                            if dm < 0:
                                bracket = True
                                tb = tm
                                db = dm
                    if not bracket:
                        continue
                    # safeguarded Newton on [ta, tb]: d(ta) >= 0 > d(tb)
                    a_ = ta
                    b_ = tb
                    da_ = max(da, 0.0)
                    t = a_
                    dcur = da_
                    ddcur = dda
                    for newton in range(100):
                        tn = t - dcur / ddcur if ddcur < 0 else -1.0
                        if not (a_ < tn < b_):
                            tn = 0.5 * (a_ + b_)
                        _state_at(lr, z, gstart, gs, tn, cur, cvr, uer, zt, gt, u1, ud1, udd1)
                        dcur, ddcur, _ = _dist(code, side, gaps[s], u1[s], ud1[s], udd1[s])
                        if dcur >= 0:
                            a_ = tn
                        else:
                            b_ = tn
                        converged = abs(tn - t) < 1e-13 * h or b_ - a_ < 1e-13 * h or dcur == 0
                        t = tn
                        if converged:
                            break
                    if t < tau_c:
                        tau_c = t
                        s_c = s
                        side_c = side
            if s_c >= 0:
                break
        if s_c < 0:
            break  # no crossing: zt at sigma (recompute below)
        # switch regime at tau_c
        _advance_c(lr, z, gstart, gs, tau_c, zt)
        if count:
            for s in range(S):
                if codes[r, s] != 0:
                    contact_time[s] += tau_c
        code = codes[r, s_c]
        tid = trans_id[r, s_c, side_c if code == 0 else 0]
        r_new = trans_to[tid]
        if code == 0 and count:
            n_events[s_c] += 1
        for i in range(n2):
            xr_[i] = zt[i].real
            xr_[n2 + i] = zt[i].imag
        Tm = T[tid]
        cc = c[tid]
        for i in range(n2):
            a = cc[i]
            b = cc[n2 + i]
            for j in range(2 * n2):
                a += Tm[i, j] * xr_[j]
                b += Tm[n2 + i, j] * xr_[j]
            z[i] = complex(a, b)
        r = r_new
        # modal forcing of the load interval in the new regime
        Wn = W[r]
        for i in range(n2):
            ar = 0.0
            ai = 0.0
            br = 0.0
            bi = 0.0
            for k in range(Fk.shape[0]):
                ar += Wn[k, 0, i] * Fk[k]
                ai += Wn[k, 1, i] * Fk[k]
                br += Wn[k, 0, i] * Fk1[k]
                bi += Wn[k, 1, i] * Fk1[k]
            G0[i] = complex(ar, ai)
            G1[i] = complex(br, bi)
        gs = (G1 - G0) / dt_load
        t_loc += tau_c
        just_switched = True
        if it == 199:
            raise RuntimeError("more than 200 regime switches within one step")
    # finish: advance from t_loc to h in regime r
    sigma = h - t_loc
    for i in range(n2):
        gstart[i] = G0[i] + gs[i] * (t_loc + theta0 * dt_load)
    if sigma > 0:
        _advance_c(lam[r], z, gstart, gs, sigma, zt)
    else:
        for i in range(n2):
            zt[i] = z[i]
    if count:
        for s in range(S):
            if codes[r, s] != 0:
                contact_time[s] += sigma
    for i in range(n2):
        zr[i] = zt[i].real
        zi[i] = zt[i].imag
        g0r[i] = G0[i].real
        g0i[i] = G0[i].imag
        g1r[i] = G1[i].real
        g1i[i] = G1[i].imag
    return r


@numba.njit(cache=True, fastmath=_FM)
def _exact_kernel(loads, dt_load, h, ns, out_every, j0, lam, E, A, Bc, W, cu, cv, ueq, cy, yeq,
                  codes, trans_id, trans_to, T, c, gaps, mcoef, y_out, sumsq, contact_time,
                  n_events, refine_all, n_flagged):
    n_int = loads.shape[0] - 1
    n2 = lam.shape[1]
    S = gaps.shape[0]
    n_obs = yeq.shape[1]
    zr = np.zeros(n2)
    zi = np.zeros(n2)
    nzr = np.zeros(n2)
    nzi = np.zeros(n2)
    g0r = np.zeros(n2)
    g0i = np.zeros(n2)
    g1r = np.zeros(n2)
    g1i = np.zeros(n2)
    u0 = np.zeros(S)
    ud0 = np.zeros(S)
    u1 = np.zeros(S)
    ud1 = np.zeros(S)
    r = 0
    for s in range(S):
        u0[s] = ueq[r, s]
    _wf(W[r], loads[0], g1r, g1i)
    step = 0
    count_from = j0 * out_every
    n_keep = y_out.shape[0]
    store = n_keep > 0
    jo = 0
    # output at t = 0
    if j0 == 0:
        for o in range(n_obs):
            y = yeq[r, o]
            sumsq[o] += y * y
            if store:
                y_out[0, o] = y
        jo = 1
    for k in range(n_int):
        for i in range(n2):
            g0r[i] = g1r[i]
            g0i[i] = g1i[i]
        _wf(W[r], loads[k + 1], g1r, g1i)
        for j in range(ns):
            count = step >= count_from
            Er = E[r, 0]
            Ei = E[r, 1]
            Ar = A[r, j, 0]
            Ai = A[r, j, 1]
            Br = Bc[r, j, 0]
            Bi = Bc[r, j, 1]
            for i in range(n2):
                a = zr[i]
                b = zi[i]
                nzr[i] = (Er[i] * a - Ei[i] * b + Ar[i] * g0r[i] - Ai[i] * g0i[i]
                          + Br[i] * g1r[i] - Bi[i] * g1i[i])
                nzi[i] = (Er[i] * b + Ei[i] * a + Ar[i] * g0i[i] + Ai[i] * g0r[i]
                          + Br[i] * g1i[i] + Bi[i] * g1r[i])
            flagged = refine_all
            for s in range(S):
                cur = cu[r, s, 0]
                cui = cu[r, s, 1]
                cvr = cv[r, s, 0]
                cvi = cv[r, s, 1]
                au = 0.0
                av = 0.0
                for i in range(n2):
                    au += cur[i] * nzr[i] - cui[i] * nzi[i]
                    av += cvr[i] * nzr[i] - cvi[i] * nzi[i]
                u1[s] = ueq[r, s] + au
                ud1[s] = av
                code = codes[r, s]
                g = gaps[s]
                if code == 0:
                    if _flag(g - u0[s], -ud0[s], g - u1[s], -ud1[s], h, mcoef * max(abs(ud0[s]), abs(ud1[s]))):
                        flagged = True
                    if _flag(u0[s] + g, ud0[s], u1[s] + g, ud1[s], h, mcoef * max(abs(ud0[s]), abs(ud1[s]))):
                        flagged = True
                elif code == 1:
                    if _flag(u0[s] - g, ud0[s], u1[s] - g, ud1[s], h, mcoef * max(abs(ud0[s]), abs(ud1[s]))):
                        flagged = True
                else:
                    if _flag(-g - u0[s], -ud0[s], -g - u1[s], -ud1[s], h, mcoef * max(abs(ud0[s]), abs(ud1[s]))):
                        flagged = True
            if not flagged:
                for i in range(n2):
                    zr[i] = nzr[i]
                    zi[i] = nzi[i]
                for s in range(S):
                    u0[s] = u1[s]
                    ud0[s] = ud1[s]
                if count:
                    for s in range(S):
                        if codes[r, s] != 0:
                            contact_time[s] += h
            else:
                n_flagged[0] += 1
                r = _event_step(r, zr, zi, g0r, g0i, g1r, g1i, loads[k], loads[k + 1], j / ns, h,
                                dt_load, count, lam, W, cu, cv, ueq, codes, trans_id, trans_to, T, c,
                                gaps, mcoef, contact_time, n_events, refine_all)
                for s in range(S):
                    au = 0.0
                    av = 0.0
                    for i in range(n2):
                        au += cu[r, s, 0, i] * zr[i] - cu[r, s, 1, i] * zi[i]
                        av += cv[r, s, 0, i] * zr[i] - cv[r, s, 1, i] * zi[i]
                    u0[s] = ueq[r, s] + au
                    ud0[s] = av
            step += 1
            if step % out_every == 0:
                jout = step // out_every
                if jout >= j0:
                    for o in range(n_obs):
                        y = yeq[r, o]
                        cr = cy[r, o, 0]
                        ci = cy[r, o, 1]
                        for i in range(n2):
                            y += cr[i] * zr[i] - ci[i] * zi[i]
                        sumsq[o] += y * y
                        if store:
                            y_out[jout - j0, o] = y
    return step


@numba.njit(cache=True)
def _se_kernel(loads, ns, out_every, j0, h, MiK, MiD, MiB, Mib, bmat, gaps, kst, Cm, y_out, sumsq,
               contact_time, n_events):
    """Symplectic Euler: v += h M^-1(B F - D v - K q - sum b f(b^T q)); q += h v."""
    n_int = loads.shape[0] - 1
    N = MiK.shape[0]
    m = loads.shape[1]
    S = gaps.shape[0]
    n_obs = Cm.shape[0]
    q = np.zeros(N)
    v = np.zeros(N)
    a = np.zeros(N)
    f = np.zeros(m)
    fs = np.zeros(S)
    closed = np.zeros(S, np.bool_)
    store = y_out.shape[0] > 0
    count_from = j0 * out_every
    if j0 == 0:
        if store:
            for o in range(n_obs):
                y_out[0, o] = 0.0
    step = 0
    for k in range(n_int):
        for j in range(ns):
            th = j / ns
            for l in range(m):
                f[l] = (1 - th) * loads[k, l] + th * loads[k + 1, l]
            for s in range(S):
                u = 0.0
                for i in range(N):
                    u += bmat[s, i] * q[i]
                if u > gaps[s]:
                    fs[s] = kst[s] * (u - gaps[s])
                elif u < -gaps[s]:
                    fs[s] = kst[s] * (u + gaps[s])
                else:
                    fs[s] = 0.0
            for i in range(N):
                acc = 0.0
                for l in range(m):
                    acc += MiB[i, l] * f[l]
                for l in range(N):
                    acc -= MiK[i, l] * q[l] + MiD[i, l] * v[l]
                for s in range(S):
                    acc -= Mib[s, i] * fs[s]
                a[i] = acc
            for i in range(N):
                v[i] += h * a[i]
                q[i] += h * v[i]
            step += 1
            count = step > count_from
            for s in range(S):
                u = 0.0
                for i in range(N):
                    u += bmat[s, i] * q[i]
                now = abs(u) > gaps[s]
                if count:
                    if now:
                        contact_time[s] += h
                    if now and not closed[s]:
                        n_events[s] += 1
                closed[s] = now
            if step % out_every == 0:
                jout = step // out_every
                if jout >= j0:
                    for o in range(n_obs):
                        y = 0.0
                        for i in range(N):
                            y += Cm[o, i] * q[i]
                        sumsq[o] += y * y
                        if store:
                            y_out[jout - j0, o] = y
    return step


def exact_step_flops(n_modes: int, n_stops: int, n_loads: int, steps_per_load: int) -> float:
    """Floating-point operations per integration step of the exact kernel's fast path.

    Per kept mode: z update 12 mul + 10 add = 22; per stop and mode u and u' = 8. Per load
    sample, W F costs 4 m flops per mode, shared by ``steps_per_load`` steps. Output (every
    output_dt) and event handling are excluded (counted separately by the benchmark).
    """
    return n_modes * (22 + 8 * n_stops + 4 * n_loads / steps_per_load)


# ----------------------------------------------------------------------------------------------
# Public driver
# ----------------------------------------------------------------------------------------------


def _prepare(M, D, K, stops, B, C, loads, dt_load, output_dt, discard, method, keep):
    if method not in _METHODS:
        raise SpecificationError("method", method, f"must be one of {_METHODS}")
    if keep not in _KEEPS:
        raise SpecificationError("keep", keep, f"must be one of {_KEEPS}")
    Ms = _as_matrix_stack("M", M)
    N = Ms.shape[1]
    Ds = _as_matrix_stack("D", D, N)
    Ks = _as_matrix_stack("K", K, N)
    _check_definite("M", Ms, True)
    _check_definite("K", Ks, True)
    _check_definite("D", Ds, False)
    stops = _validate_stops(stops, N)
    if len(stops) > MAX_STOPS:
        raise SpecificationError("stops", f"{len(stops)} stops", f"at most {MAX_STOPS} stops (3**S regimes are tabulated)")
    try:
        Bm = np.asarray(B, dtype=float)
        Cm = np.asarray(C, dtype=float)
        L = np.asarray(loads, dtype=float)
    except (TypeError, ValueError):
        raise SpecificationError("B/C/loads", "non-numeric", "must be real arrays") from None
    if Bm.ndim == 1:
        Bm = Bm[:, None]
    if Bm.ndim != 2 or Bm.shape[0] != N or not np.all(np.isfinite(Bm)):
        raise SpecificationError("B.shape", Bm.shape, f"must be a finite (N={N}, m) matrix")
    if Cm.ndim == 1:
        Cm = Cm[None, :]
    if Cm.ndim != 2 or Cm.shape[1] != N or Cm.shape[0] == 0 or not np.all(np.isfinite(Cm)):
        raise SpecificationError("C.shape", Cm.shape, f"must be a finite (n_obs, N={N}) matrix")
    if L.ndim == 2:
        L = L[None]
    if L.ndim != 3 or L.shape[2] != Bm.shape[1] or L.shape[1] < 2:
        raise SpecificationError("loads.shape", L.shape, f"must be (R, n_t >= 2, m = {Bm.shape[1]})")
    if not np.all(np.isfinite(L)):
        raise SpecificationError("loads", "non-finite samples", "must be finite")
    R = L.shape[0]
    for nm, a in (("M", Ms), ("D", Ds), ("K", Ks)):
        if len(a) not in (1, R):
            raise SpecificationError(f"{nm}.shape", a.shape, f"realisation axis must be 1 or match loads (R = {R})")
    dt_load = _positive("dt_load", dt_load)
    output_dt = _positive("output_dt", output_dt)
    duration = (L.shape[1] - 1) * dt_load
    if isinstance(discard, bool) or not isinstance(discard, (int, float, np.integer, np.floating)) \
            or not math.isfinite(discard) or discard < 0 or discard >= duration:
        raise SpecificationError("discard", discard, f"must be in [0, duration = {duration:.6g} s)")
    # gap-0 stops are linear springs; others keep their regimes
    lin = [s for s in stops if s.gap == 0.0]
    nl = tuple(s for s in stops if s.gap > 0.0)
    if lin:
        extra = sum(s.stiffness * np.outer(s.vector, s.vector) for s in lin)
        Ks = Ks + extra[None]
    return Ms, Ds, Ks, stops, nl, Bm, Cm, np.ascontiguousarray(L), R, N, dt_load, output_dt, duration, float(discard)


def _result(y, rms, cf, ne, dts, stops, Cm, sensor_names, output_dt, j0, method, discard):
    R = len(dts)
    n_obs = Cm.shape[0]
    sensors = list(sensor_names) if sensor_names is not None else [f"y{i}" for i in range(n_obs)]
    if len(sensors) != n_obs:
        raise SpecificationError("sensor_names", sensor_names, f"must have n_obs = {n_obs} names")
    stop_names = [s.name or f"stop{i}" for i, s in enumerate(stops)]
    real = np.arange(R)
    obs = None
    if y is not None:
        t = (j0 + np.arange(y.shape[1])) * output_dt
        obs = xr.DataArray(y, dims=("realisation", "time", "sensor"),
                           coords={"realisation": real, "time": t, "sensor": sensors},
                           attrs={"long_name": "observation C q", "time_units": "s"})
    return TransientResult(
        observations=obs,
        rms=xr.DataArray(rms, dims=("realisation", "sensor"), coords={"realisation": real, "sensor": sensors},
                         attrs={"long_name": "RMS (not centred) of C q at output_dt, t >= discard"}),
        contact_fraction=xr.DataArray(cf, dims=("realisation", "stop"), coords={"realisation": real, "stop": stop_names},
                                      attrs={"long_name": "fraction of time with |u| > gap"}),
        contact_events=xr.DataArray(ne, dims=("realisation", "stop"), coords={"realisation": real, "stop": stop_names},
                                    attrs={"long_name": "number of open -> contact transitions"}),
        dt=xr.DataArray(np.asarray(dts), dims=("realisation",), coords={"realisation": real}, attrs={"units": "s"}),
        method=method, output_dt=output_dt, discard=discard)


def simulate(M, D, K, stops, B, C, loads, dt_load, *, output_dt=3e-3, dt=None, method="exact",
             keep="series", discard=0.0, sensor_names=None, _refine_all=False, _diagnostics=None):
    """Transient response of M q'' + D q' + K q + sum_s b_s f_s(b_s^T q) = B F(t), y = C q.

    M, D, K: (N, N) or (R, N, N) (symmetric; M, K positive definite, D semi-definite), SI units.
    stops: sequence of :class:`Stop`. B: (N, m). C: (n_obs, N). loads: (R, n_t, m) or (n_t, m)
    samples of F at t = i dt_load, read as their continuous piecewise-linear interpolant.
    output_dt: observation sampling (s), default 3 ms; dt: integration step (s), None = per
    realisation from :func:`choose_step`; method "exact" or "symplectic-euler"; keep "series"
    (store the observations) or "stats"; discard: transient (s) removed from the series and the
    statistics (rounded up to the output grid). Outputs at t = j output_dt, t >= discard, t <= T.
    """
    (Ms, Ds, Ks, stops_all, stops_nl, Bm, Cm, L, R, N, dt_load, output_dt, duration,
     discard) = _prepare(M, D, K, stops, B, C, loads, dt_load, output_dt, discard, method, keep)
    n_out_total = int(math.floor(duration / output_dt + 1e-9)) + 1
    j0 = int(math.ceil(discard / output_dt - 1e-9))
    n_keep = n_out_total - j0
    if n_keep < 1:
        raise SpecificationError("discard", discard, "leaves no output sample")
    n_obs = Cm.shape[0]
    S_all = len(stops_all)
    y_all = np.zeros((R, n_keep, n_obs)) if keep == "series" else None
    rms = np.zeros((R, n_obs))
    cf = np.zeros((R, S_all))
    ne = np.zeros((R, S_all), dtype=np.int64)
    dts = np.zeros(R)
    t_count = duration - j0 * output_dt  # counted time window
    nl_index = [i for i, s in enumerate(stops_all) if s.gap > 0.0]
    lin_index = [i for i, s in enumerate(stops_all) if s.gap == 0.0]
    f_cache = {}
    tab_cache = {}
    for r in range(R):
        Mr, Dr, Kr = Ms[r % len(Ms)], Ds[r % len(Ds)], Ks[r % len(Ks)]
        key = (r % len(Ms), r % len(Ks))
        if key not in f_cache:
            f_cache[key] = highest_frequency(Mr, Kr, stops_nl)
        f_max = f_cache[key]
        h = choose_step(f_max, dt_load, output_dt, method, dt)
        ns = int(round(dt_load / h))
        out_every = int(round(output_dt / h))
        n_steps_total = (L.shape[1] - 1) * ns
        # outputs beyond the last full step are not produced; n_out_total already bounded by T
        y_buf = np.zeros((n_keep if keep == "series" else 0, n_obs))
        sumsq = np.zeros(n_obs)
        ct = np.zeros(len(stops_nl))
        nev = np.zeros(len(stops_nl), dtype=np.int64)
        if method == "exact":
            tkey = (r % len(Ms), r % len(Ds), r % len(Ks), h)
            if tkey not in tab_cache:
                tab_cache = {tkey: _build_tables(Mr, Dr, Kr, stops_nl, Bm, Cm, h, ns, dt_load)}
            tb = tab_cache[tkey]
            w = tb.omega_max
            mcoef = _MARGIN_SAFETY * (w * h) ** 4 / (384.0 * w)
            nflag = np.zeros(1, dtype=np.int64)
            _exact_kernel(L[r], dt_load, h, ns, out_every, j0, tb.lam, tb.E, tb.A, tb.Bc, tb.W, tb.cu, tb.cv,
                          tb.ueq, tb.cy, tb.yeq, tb.codes, tb.trans_id, tb.trans_to, tb.T, tb.c, tb.gaps,
                          mcoef, y_buf, sumsq, ct, nev, bool(_refine_all), nflag)
            if _diagnostics is not None:
                _diagnostics.append({"flagged_steps": int(nflag[0]), "steps": n_steps_total,
                                     "cond_V": tb.cond_max, "half_modes": tb.half, "n_modes": tb.lam.shape[1]})
        else:
            Minv = np.linalg.inv(Mr)
            bmat = np.array([s.vector for s in stops_nl]).reshape(len(stops_nl), N)
            _se_kernel(L[r], ns, out_every, j0, h, Minv @ Kr, Minv @ Dr, Minv @ Bm,
                       np.ascontiguousarray((Minv @ bmat.T).T), bmat,
                       np.array([s.gap for s in stops_nl]), np.array([s.stiffness for s in stops_nl]),
                       np.ascontiguousarray(Cm), y_buf, sumsq, ct, nev)
        dts[r] = h
        if y_all is not None:
            y_all[r] = y_buf
        rms[r] = np.sqrt(sumsq / n_keep)
        cf[r, nl_index] = ct / t_count if t_count > 0 else 0.0
        ne[r, nl_index] = nev
        cf[r, lin_index] = 1.0
    return _result(y_all, rms, cf, ne, dts, stops_all, Cm, sensor_names, output_dt, j0, method, discard)


def simulate_baseline(M, D, K, stops, B, C, loads, dt_load, *, output_dt=3e-3, dt=None):
    """Straightforward reference implementation for benchmarks: symplectic Euler, one numpy
    matrix-vector product per step in a Python loop (single realisation, shared matrices).

    Returns the observation series (n_out, n_obs) at output_dt from t = 0. dt=None uses the
    symplectic-Euler default rule of :func:`choose_step`.
    """
    (Ms, Ds, Ks, stops_all, stops_nl, Bm, Cm, L, R, N, dt_load, output_dt, duration,
     _) = _prepare(M, D, K, stops, B, C, loads, dt_load, output_dt, 0.0, "symplectic-euler", "series")
    if len(Ms) != 1 or len(Ks) != 1 or len(Ds) != 1 or R != 1:
        raise SpecificationError("loads.shape", L.shape, "simulate_baseline takes one realisation")
    f_max = highest_frequency(Ms[0], Ks[0], stops_nl)
    h = choose_step(f_max, dt_load, output_dt, "symplectic-euler", dt)
    ns = int(round(dt_load / h))
    out_every = int(round(output_dt / h))
    Minv = np.linalg.inv(Ms[0])
    # first-order update on [q; v]: a = -MiK q - MiD v + MiB F - Mib f_stop
    Afull = np.hstack([-Minv @ Ks[0], -Minv @ Ds[0]])
    MiB = Minv @ Bm
    bmat = np.array([s.vector for s in stops_nl]).reshape(len(stops_nl), N)
    Mib = Minv @ bmat.T
    gaps = np.array([s.gap for s in stops_nl])
    kst = np.array([s.stiffness for s in stops_nl])
    x = np.zeros(2 * N)
    out = [Cm @ x[:N]]
    step = 0
    F = L[0]
    for k in range(F.shape[0] - 1):
        for j in range(ns):
            th = j / ns
            f = (1 - th) * F[k] + th * F[k + 1]
            u = bmat @ x[:N]
            fs = kst * np.sign(u) * np.maximum(np.abs(u) - gaps, 0.0)
            a = Afull @ x + MiB @ f - Mib @ fs
            x[N:] += h * a
            x[:N] += h * x[N:]
            step += 1
            if step % out_every == 0:
                out.append(Cm @ x[:N])
    return np.array(out), h
