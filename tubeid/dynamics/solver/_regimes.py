"""Modal tables of the regimes of one realisation (numpy), read by the exact method's kernels.

A stop is open (code 0), in contact on the + side (+1) or on the - side (-1): 3**S regimes r,
numbered so that code[r, s] = (0, +1, -1)[(r // 3**s) % 3] (regime 0: every stop open). Regimes
with the same stops closed (either side) share K_r = K + Σ_closed k b bᵀ and therefore their
eigen-decomposition: a *basis* (2**S of them, index ``basis[r]``); they differ only in the
equilibrium q_eq = K_r⁻¹ Σ_closed k g code b.

In a basis the first-order system x = [q; q'] is diagonalised, x = x_eq + Σ_i w_i Re(V_i z_i)
(one mode of each complex-conjugate pair kept, w_i = 2; with a real eigenvalue in any basis, every
mode of every basis is kept, w_i = 1), and z_i' = λ_i z_i + W_i F(t). On a load interval
F(t) = f + f' t, the particular solution z_p = α F(t) + β f' (α = -W/λ, β = -W/λ²) is exact, so
the homogeneous part ζ = z - z_p (stored as [Re; Im], modes padded to n2p, a multiple of 8) obeys
ζ(t + s) = e^{λ s} ζ(t); at a load sample ζ += [Re β; Im β] (f'_old - f'_new). Every observable is
a row over the extended input xl = [ζ; f; f'; 1; 0...] (length nxl, a multiple of 8), f the load
at the row's reference time: its homogeneous part plus the quasi-static part a·f + b·f' + c.

A switch between regimes at time t keeps x continuous: ζ_new = T_{b→b'} xl(t) + c_{r→r'}, with
T depending only on the two bases and c on the two equilibria. The particular part can exceed z
itself in the lowest mode (on the paper model by ~10x: one digit of round-off, ~1e-15 relative).
"""

from __future__ import annotations

import collections
import hashlib
import math
import struct
import threading
from typing import NamedTuple

import numpy as np

from tubeid.dynamics.solver._determinism import one_blas_thread

__all__ = ["FINE", "BLOCK_MAX", "MARGIN_SAFETY", "ALIGN", "TABLE_CACHE_BYTES", "ExactTables", "regime_codes", "aligned",
           "build_tables", "cached_tables", "forget_tables", "initial_state"]

#: e^{λτ} on a step [0, h] is tabulated at τ = k h / FINE and completed by a short series.
FINE = 64
#: At most this many sub-steps are advanced as one block (size of the block tables).
BLOCK_MAX = 16
#: Tolerance of the crossing search (Halley on the exact closed form), relative to the sub-step h:
#: ``ExactTables.xtol`` = CROSSING_TOL h (s). The search stops when its bracket is narrower than
#: that or its last step shorter; a switch instant is then located within about CROSSING_TOL h
#: (2.5 ns at h = 250 µs), u off the boundary by about |u'| CROSSING_TOL h; the state x stays
#: continuous across the switch. Also the step tolerance of the Newton search for an interior
#: minimum of the distance (``_events._crossing_in``).
CROSSING_TOL = 1e-5
#: Safety factor of the event pre-check's margin: margin = MARGIN_SAFETY times the cubic-Hermite
#: error bound (w h)⁴/(384 w) max|d'| of a component at w = 2π f_max (``ExactTables.mcoef``; the
#: margin comments of ``_step.EXACT_RULE`` and ``_events`` follow it).
MARGIN_SAFETY = 4.0
#: Byte alignment of every array the kernels read or write: the rows they load as vectors are
#: multiples of 8 doubles, so a 512-bit load of such a row never spans two cache lines.
ALIGN = 64
#: Tables kept per process by :func:`cached_tables` (bytes, least recently used dropped first). An
#: entry counts the tables and the eigenvector matrices V (2N x 2N complex per basis): 0.13 MiB for
#: ``paper-simplified`` (N = 16, one stop), 0.76 MiB for ``paper-reference`` (N = 50) at h = 250 µs.
TABLE_CACHE_BYTES = 64 * 2**20


class ExactTables(NamedTuple):
    """Everything the exact kernels read for one realisation (arrays C-contiguous, float64 unless
    said). nr regimes, nbas bases, S stops, m loads (m8: m rounded up to 8), n2p padded modes,
    nx = 2 n2p, nxl = length of the extended input, nb sub-steps per block, n_obs outputs."""

    # regimes
    basis: np.ndarray  # (nr,) int64: basis of each regime
    codes: np.ndarray  # (nr, S) int64: 0 open, +1 / -1 contact on the + / - side
    lower: np.ndarray  # (nr, S): u must stay above this in the regime (-g, g, or -inf)
    upper: np.ndarray  # (nr, S): ... and below this (g, inf, or -g)
    closed: np.ndarray  # (nr, S): 1.0 where the stop is in contact
    gaps: np.ndarray  # (S,)
    # bases: modal data
    lam_re: np.ndarray  # (nbas, n2p) Re λ (0 on padded modes)
    lam_im: np.ndarray  # (nbas, n2p)
    step_re: np.ndarray  # (nbas, nb + 1, n2p) Re e^{λ mm h}
    step_im: np.ndarray  # (nbas, nb + 1, n2p)
    fine_re: np.ndarray  # (nbas, FINE + 1, n2p) Re e^{λ k h / FINE}
    fine_im: np.ndarray  # (nbas, FINE + 1, n2p)
    slope_rows: np.ndarray  # (nbas, m8, nx): [Re β_l; Im β_l], ζ += Σ_l row_l (f'_old - f'_new)_l
    # rows over xl (per regime: the quasi-static constant depends on the side)
    block_rows: np.ndarray  # (nr, ncp, nxl): row (mm - 1) 2S + 2s + d is u_s (d = 0) or u'_s (d = 1) at mm h,
    #                         f = load at the block start; ncp = nb 2S rounded up to 8
    output_rows: np.ndarray  # (nr, (nb + 1) n_obs, nxl): row mm n_obs + o is y_o at mm h (mm = 0: now)
    stop_rows: np.ndarray  # (nr, 3S rounded up to 4, nxl): rows 3s, 3s + 1, 3s + 2 are u_s, u'_s, u''_s now
    # u_s of the event search: Re Σ_i cu_i ζ_i (u' and u'' with λ_i cu_i, λ_i² cu_i) plus the
    # quasi-static part ueq + au·f + bu·f' (u' : av·f + bv·f'; u'': av·f')
    cu_re: np.ndarray  # (nbas, S, n2p) Re cu
    cu_im: np.ndarray  # (nbas, S, n2p)
    stop_qs: np.ndarray  # (nbas, S, 4, m): au, bu, av, bv
    ueq: np.ndarray  # (nr, S) u at the regime's equilibrium
    # switches: regime r leaves through stop s (side d of an open stop: 0 towards +g, 1 towards -g)
    trans_id: np.ndarray  # (nr, S, 2) int64: transition index (-1: none)
    trans_to: np.ndarray  # (nt,) int64: regime after the transition
    trans_map: np.ndarray  # (nt,) int64: its basis-to-basis transform
    trans_const: np.ndarray  # (nt, nx): c_{r→r'}
    transforms: np.ndarray  # (nu, nx, nxl): T_{b→b'} over xl (constant column zero)
    # step data
    h: float  # sub-step (s)
    nb: int  # sub-steps per block
    mcoef: float  # margin coefficient (s), MARGIN_SAFETY (w h)⁴/(384 w): margin = mcoef (σ/h)⁴ max|d'| on σ
    xtol: float  # crossing search tolerance (s): CROSSING_TOL h


def regime_codes(S: int) -> np.ndarray:
    """(3**S, S) int64: 0 open, +1 contact on the + side, -1 on the - side."""
    codes = np.zeros((3**S, S), dtype=np.int64)
    for r in range(3**S):
        x = r
        for s in range(S):
            codes[r, s] = (0, 1, -1)[x % 3]
            x //= 3
    return codes


def aligned(a: np.ndarray) -> np.ndarray:
    """C-contiguous copy of ``a`` whose data start on an ``ALIGN``-byte boundary (same values)."""
    a = np.asarray(a)
    buf = np.empty(a.nbytes + ALIGN, dtype=np.uint8)
    start = -buf.ctypes.data % ALIGN
    out = buf[start:start + a.nbytes].view(a.dtype).reshape(a.shape)
    out[...] = a
    return out


def _pad(n: int, k: int) -> int:
    return -(-n // k) * k


def _stack(cmat: np.ndarray, n2p: int) -> np.ndarray:
    """[Re c, -Im c] padded to 2 n2p on the last axis: Re(c·z) = row · [Re z; Im z]."""
    n2 = cmat.shape[-1]
    out = np.zeros(cmat.shape[:-1] + (2 * n2p,))
    out[..., :n2] = cmat.real
    out[..., n2p:n2p + n2] = -cmat.imag
    return out


def _padm(a: np.ndarray, n2p: int) -> np.ndarray:
    out = np.zeros(a.shape[:-1] + (n2p,), a.dtype)
    out[..., :a.shape[-1]] = a
    return out


class _Basis(NamedTuple):
    lam: np.ndarray  # (n2,) complex
    Vw: np.ndarray  # (2N, n2) complex: eigenvectors times their weight w
    Vinv: np.ndarray  # (n2, 2N) complex: the kept rows of V⁻¹
    V: np.ndarray  # (2N, 2N) complex: all eigenvectors (diagnostics)


def _bases(M, D, K, stops, codes):
    """Eigen-decomposition of each closed set; (basis index per regime, bases, K_r per basis)."""
    N = M.shape[0]
    Minv = np.linalg.inv(M)
    Minv = 0.5 * (Minv + Minv.T)
    keys, basis = [], np.zeros(len(codes), dtype=np.int64)
    for r, c in enumerate(codes):
        key = tuple(c != 0)
        if key not in keys:
            keys.append(key)
        basis[r] = keys.index(key)
    raw, Ks = [], []
    for key in keys:
        Kr = K + sum((st.stiffness * np.outer(st.vector, st.vector) for st, cl in zip(stops, key) if cl),
                     np.zeros((N, N)))
        A = np.block([[np.zeros((N, N)), np.eye(N)], [-Minv @ Kr, -Minv @ D]])
        lam, V = np.linalg.eig(A)
        raw.append((lam, V))
        Ks.append(Kr)
    all_complex = all(np.all(lam.imag != 0) for lam, _ in raw)
    out = []
    for lam, V in raw:
        Vinv = np.linalg.inv(V)
        if all_complex:
            keep = np.flatnonzero(lam.imag > 0)
            if len(keep) != N:
                raise RuntimeError("eigenvalues are not in conjugate pairs")
            w = 2.0
        else:
            keep = np.arange(2 * N)
            w = 1.0
        out.append(_Basis(lam=lam[keep], Vw=V[:, keep] * w, Vinv=Vinv[keep], V=V))
    return basis, out, Ks, Minv, all_complex


_CACHE: collections.OrderedDict = collections.OrderedDict()  # key -> (tables, diagnostics, bytes)
_CACHE_LOCK = threading.Lock()


def cached_tables(M, D, K, stops, B, C, h: float, ns: int, omega_max: float) -> tuple[ExactTables, dict]:
    """:func:`build_tables`, kept per process under a digest of every input's bytes: a system met
    again (another call with the same matrices, as the trial grids of a study simulate each
    realisation's structure at every grid point) gets the same tables without the eigen-
    decompositions. The tables are read-only for the kernels; at most :data:`TABLE_CACHE_BYTES` are
    kept (least recently used dropped first; a system whose tables alone exceed it is not kept)."""
    key = _table_key(M, D, K, stops, B, C, h, ns, omega_max)
    with _CACHE_LOCK:
        hit = _CACHE.get(key)
        if hit is not None:
            _CACHE.move_to_end(key)
            return hit[0], hit[1]
    T, info = build_tables(M, D, K, stops, B, C, h, ns, omega_max)
    size = sum(a.nbytes for a in T if isinstance(a, np.ndarray)) + sum(V.nbytes for V in info["V"])
    with _CACHE_LOCK:
        _CACHE[key] = (T, info, size)
        total = sum(entry[2] for entry in _CACHE.values())
        while total > TABLE_CACHE_BYTES and _CACHE:  # tables larger than the budget are not kept at all
            total -= _CACHE.popitem(last=False)[1][2]
    return T, info


def forget_tables() -> None:
    """Empty the process's table cache (benchmarks time a realisation with its tables built)."""
    with _CACHE_LOCK:
        _CACHE.clear()


def _table_key(M, D, K, stops, B, C, h, ns, omega_max) -> bytes:
    """Digest of the tables' inputs: shape and float64 bytes of every array (M, D, K, B, C and each
    stop's vector), each stop's gap and stiffness, the step, the sub-steps per load interval and
    omega_max as exact doubles."""
    d = hashlib.blake2b(digest_size=32)
    for a in (M, D, K, B, C, *(s.vector for s in stops)):
        a = np.ascontiguousarray(a, dtype=float)
        d.update(struct.pack("<q", a.ndim) + struct.pack(f"<{a.ndim}q", *a.shape) + a.tobytes())
    d.update(struct.pack("<q", len(stops)))
    for s in stops:
        d.update(struct.pack("<2d", float(s.gap), float(s.stiffness)))
    d.update(struct.pack("<dqd", float(h), int(ns), float(omega_max)))
    return d.digest()


def build_tables(M, D, K, stops, B, C, h: float, ns: int, omega_max: float) -> tuple[ExactTables, dict]:
    """Tables of the regimes of (M, D, K) with ``stops`` (all with a gap), loads B (N, m), outputs
    C (n_obs, N), sub-step h (s), ns sub-steps per load interval, omega_max = 2π f_max (rad/s).

    Returns the tables and a dict of diagnostics (the eigenvector matrices V, whether conjugate
    pairs were halved, number of modes). Computed with one BLAS thread (bit-identical
    whatever the caller's BLAS threads, see ``_determinism``)."""
    with one_blas_thread():
        return _build(M, D, K, stops, B, C, h, ns, omega_max)


def _build(M, D, K, stops, B, C, h, ns, omega_max):
    N = M.shape[0]
    S = len(stops)
    m = B.shape[1]
    n_obs = C.shape[0]
    codes = regime_codes(S)
    nr = len(codes)
    basis, bases, Ks, Minv, all_complex = _bases(M, D, K, stops, codes)
    nbas = len(bases)
    bs = np.array([s.vector for s in stops]).reshape(S, N)
    gaps = np.array([s.gap for s in stops], float)
    # equilibria per regime
    xeq = np.zeros((nr, 2 * N))
    for r in range(nr):
        fr = sum((st.stiffness * st.gap * codes[r, s] * bs[s] for s, st in enumerate(stops)), np.zeros(N))
        xeq[r, :N] = np.linalg.solve(Ks[basis[r]], fr)
    n2 = len(bases[0].lam)
    n2p = _pad(n2, 8)
    nx = 2 * n2p
    nxl = nx + _pad(2 * m + 1, 8)
    nb = min(ns, BLOCK_MAX)
    lam = np.array([bb.lam for bb in bases])  # (nbas, n2)
    Bx = np.vstack([np.zeros_like(B), Minv @ B])
    W = np.array([bb.Vinv @ Bx for bb in bases])  # (nbas, n2, m)
    alpha = -W / lam[:, :, None]
    beta = -W / lam[:, :, None] ** 2
    cu = np.array([bs @ bb.Vw[:N] for bb in bases])  # (nbas, S, n2)
    cv = np.array([bs @ bb.Vw[N:] for bb in bases])
    cy = np.array([C @ bb.Vw[:N] for bb in bases])  # (nbas, n_obs, n2)
    ueq = xeq[:, :N] @ bs.T  # (nr, S)
    yeq = xeq[:, :N] @ C.T  # (nr, n_obs)

    # quasi-static coefficients per basis: Re(c α)·f + Re(c β)·f'
    def qs(c):  # c (nbas, K, n2) -> a, b (nbas, K, m)
        return np.einsum("bkn,bnm->bkm", c, alpha).real, np.einsum("bkn,bnm->bkm", c, beta).real

    au, bu = qs(cu)
    av, bv = qs(cv)
    ay, by = qs(cy)
    Em = np.exp(lam[:, None, :] * (h * np.arange(nb + 1))[None, :, None])  # (nbas, nb + 1, n2)
    Ef = np.exp(lam[:, None, :] * (h * np.arange(FINE + 1) / FINE)[None, :, None])
    tmm = h * np.arange(nb + 1)

    def rows(hom, a, b, c0):
        """Rows over xl: hom (K, n2) complex coefficient of ζ; quasi-static a·f + b·f' + c0."""
        out = np.zeros(hom.shape[:-1] + (nxl,))
        out[..., :nx] = _stack(hom, n2p)
        out[..., nx:nx + m] = a
        out[..., nx + m:nx + 2 * m] = b
        out[..., nx + 2 * m] = c0
        return out

    ncp = _pad(nb * 2 * S, 8)
    qr = basis  # basis of each regime: per-regime views of the per-basis coefficients below
    t1 = tmm[1:, None, None]  # (nb, 1, 1): f(t_mm) = f + f' t_mm, f the load at the block start
    E1 = Em[qr][:, 1:, None, :]  # (nr, nb, 1, n2)
    block = np.zeros((nr, nb, S, 2, nxl))
    block[..., 0, :] = rows(cu[qr][:, None] * E1, au[qr][:, None], au[qr][:, None] * t1 + bu[qr][:, None],
                            ueq[:, None, :])
    block[..., 1, :] = rows(cv[qr][:, None] * E1, av[qr][:, None], av[qr][:, None] * t1 + bv[qr][:, None], 0.0)
    block_rows = np.zeros((nr, ncp, nxl))  # row (mm - 1) 2S + 2s + d
    block_rows[:, :nb * 2 * S] = block.reshape(nr, nb * 2 * S, nxl)
    t0 = tmm[:, None, None]  # (nb + 1, 1, 1)
    output_rows = rows(cy[qr][:, None] * Em[qr][:, :, None, :], ay[qr][:, None], ay[qr][:, None] * t0 + by[qr][:, None],
                       yeq[:, None, :]).reshape(nr, (nb + 1) * n_obs, nxl)  # row mm n_obs + o
    stop = np.zeros((nr, S, 3, nxl))  # u, u', u'' now; u'' = Re(cv λ ζ) + av·f'
    stop[:, :, 0] = rows(cu[qr], au[qr], bu[qr], ueq)
    stop[:, :, 1] = rows(cv[qr], av[qr], bv[qr], 0.0)
    stop[:, :, 2] = rows(cv[qr] * lam[qr][:, None], 0.0, av[qr], 0.0)
    stop_rows = np.zeros((nr, _pad(3 * S, 4), nxl))  # row 3s + k
    stop_rows[:, :3 * S] = stop.reshape(nr, 3 * S, nxl)
    slope_rows = np.zeros((nbas, _pad(m, 8), nx))
    slope_rows[:, :m, :n2] = beta.real.transpose(0, 2, 1)
    slope_rows[:, :m, n2p:n2p + n2] = beta.imag.transpose(0, 2, 1)

    # switches between regimes differing in one stop
    idx = np.concatenate([np.arange(n2), n2p + np.arange(n2)])  # [Re; Im] of n2 modes in the padded layout

    def pmat(q):  # (2 n2, 2 m): [Re z_p; Im z_p] = P [f; f']
        return np.vstack([np.hstack([alpha[q].real, beta[q].real]), np.hstack([alpha[q].imag, beta[q].imag])])

    index = {tuple(c): r for r, c in enumerate(codes)}
    trans_id = -np.ones((nr, S, 2), dtype=np.int64)
    trans_to, trans_map, trans_const, transforms, pairs = [], [], [], [], {}
    for r in range(nr):
        q = basis[r]
        for s in range(S):
            for d, newc in enumerate((1, -1) if codes[r, s] == 0 else (0,)):
                c2 = codes[r].copy()
                c2[s] = newc
                r2 = index[tuple(c2)]
                q2 = basis[r2]
                Vi = bases[q2].Vinv
                if (q, q2) not in pairs:
                    X = np.hstack([bases[q].Vw.real, -bases[q].Vw.imag])  # x - x_eq = X [Re z; Im z]
                    Tc = np.vstack([Vi.real @ X, Vi.imag @ X])
                    T = np.zeros((nx, nxl))
                    T[np.ix_(idx, idx)] = Tc
                    T[idx, nx:nx + 2 * m] = Tc @ pmat(q) - pmat(q2)
                    pairs[(q, q2)] = len(transforms)
                    transforms.append(T)
                off = Vi @ (xeq[r] - xeq[r2])
                const = np.zeros(nx)
                const[idx] = np.concatenate([off.real, off.imag])
                trans_id[r, s, d] = len(trans_to)
                trans_to.append(r2)
                trans_map.append(pairs[(q, q2)])
                trans_const.append(const)
    if not transforms:  # no stop: the kernels index nothing, but numba wants non-empty arrays
        transforms, trans_to, trans_map, trans_const = [np.zeros((nx, nxl))], [0], [0], [np.zeros(nx)]
    lower = np.where(codes == 0, -gaps, np.where(codes == 1, gaps, -np.inf))
    upper = np.where(codes == 0, gaps, np.where(codes == 1, np.inf, -gaps))
    c = np.ascontiguousarray
    tables = ExactTables(
        basis=basis, codes=codes, lower=c(lower, dtype=float), upper=c(upper, dtype=float),
        closed=c((codes != 0).astype(float)), gaps=gaps,
        lam_re=c(_padm(lam, n2p).real), lam_im=c(_padm(lam, n2p).imag),
        step_re=c(_padm(Em, n2p).real), step_im=c(_padm(Em, n2p).imag),
        fine_re=c(_padm(Ef, n2p).real), fine_im=c(_padm(Ef, n2p).imag), slope_rows=slope_rows,
        block_rows=block_rows, output_rows=output_rows, stop_rows=stop_rows,
        cu_re=c(_padm(cu, n2p).real), cu_im=c(_padm(cu, n2p).imag), stop_qs=c(np.stack([au, bu, av, bv], axis=2)),
        ueq=c(ueq),
        trans_id=trans_id, trans_to=np.array(trans_to, dtype=np.int64), trans_map=np.array(trans_map, dtype=np.int64),
        trans_const=c(np.array(trans_const)), transforms=c(np.array(transforms)),
        h=float(h), nb=int(nb), mcoef=MARGIN_SAFETY * (omega_max * h) ** 4 / (384.0 * omega_max),
        xtol=CROSSING_TOL * float(h),
    )
    tables = tables._replace(**{f: aligned(v) for f, v in zip(tables._fields, tables) if isinstance(v, np.ndarray)})
    info = {"V": [bb.V for bb in bases], "half_modes": all_complex, "n_modes": n2,
            "alpha0": alpha[basis[0]], "beta0": beta[basis[0]], "n2p": n2p}
    return tables, info


def initial_state(info: dict, f0: np.ndarray, f1: np.ndarray) -> np.ndarray:
    """ζ at t = 0 for q = q' = 0 in regime 0 (every stop open, no preload): ζ = -z_p(0) = -(α f0 + β f1),
    as [Re; Im] padded (length nx); f0 the first load sample, f1 the first interval's slope."""
    zp = info["alpha0"] @ f0 + info["beta0"] @ f1
    n2p = info["n2p"]
    z = np.zeros(2 * n2p)
    z[:len(zp)] = -zp.real
    z[n2p:n2p + len(zp)] = -zp.imag
    return z
