"""numba primitives on the modal state ζ and the extended input xl = [ζ; f; f'; 1; 0...].

Loops are written for LLVM's loop vectoriser (numba does not run the SLP vectoriser): no array
views in hot code, inner loops over the contiguous last axis, matrix-vector products as eight
(or four) simultaneous reductions rather than one reduction per row. Every function here is
inlined into its caller (numba IR inlining) and reads or writes preallocated arrays only.

ζ is stored as [Re ζ (n2p); Im ζ (n2p)] in the first nx = 2 n2p entries of a 1-D array.
"""

from __future__ import annotations

import inspect
import math

import numba
import numba.core.compiler

from tubeid.dynamics.solver._regimes import FINE

__all__ = ["FASTMATH", "NO_ALIAS", "rows8", "rows", "exp_modes", "diag_mul", "expmul", "block_advance",
           "slope_update", "set_load", "set_load_rows"]

#: Reassociation (vectorised sums) and FMA contraction; no NaN/Inf assumptions (the quick check
#: compares against ±inf bounds).
FASTMATH = frozenset({"reassoc", "contract"})
_FM = set(FASTMATH)


_COMPILER_ARGS = ["self", "typingctx", "targetctx", "library", "args", "return_type", "flags", "locals"]


def _no_alias_compiler() -> type | None:
    """numba's nopython pipeline with ``noalias`` on (a ``Compiler`` subclass) where numba's internal
    compiler API is the one it was written for (as in numba 0.68: that ``Compiler.__init__``
    signature and a ``Flags.noalias`` option); numba's ``Compiler`` itself where that differs; None
    where numba has no such class (then numba's default pipeline is used: the same results, only
    without the speed-up)."""
    try:
        base = numba.core.compiler.Compiler
        same = (list(inspect.signature(base.__init__).parameters) == _COMPILER_ARGS
                and hasattr(numba.core.compiler.Flags(), "noalias"))
    except (TypeError, ValueError, AttributeError):
        return None
    if not same:
        return base

    class _NoAliasCompiler(base):
        def __init__(self, typingctx, targetctx, library, args, return_type, flags, locals):
            flags = flags.copy()
            flags.noalias = True
            super().__init__(typingctx, targetctx, library, args, return_type, flags, locals)

    return _NoAliasCompiler


#: ``numba.njit`` options of the kernels whose array arguments never share memory (``run_exact``,
#: ``evaluate``: tables, scratch, loads and outputs are distinct allocations): numba's nopython
#: pipeline with LLVM ``noalias`` on every pointer argument (numba's internal ``noalias`` flag, the
#: one its parfor lowering sets; :func:`_no_alias_compiler`). LLVM then drops the run-time overlap
#: checks in front of every vectorisable loop (executed per call, and on these short loops often as
#: long as the loop). The arithmetic is unchanged: the results are those of numba's default pipeline,
#: bit for bit. On a numba whose internal compiler API differs, numba's own ``Compiler`` (its default
#: pipeline, no ``noalias``); empty on a numba without that class.
NO_ALIAS: dict = {} if (_pipeline := _no_alias_compiler()) is None else {"pipeline_class": _pipeline}


#: 1/k! for the e^x series of expmul
_E2, _E3, _E4, _E5, _E6, _E7, _E8, _E9 = (1.0 / math.factorial(k) for k in range(2, 10))


@numba.njit(cache=True, _nrt=False, fastmath=_FM, inline="always")
def rows8(A, r, g, x, n, out, o):
    """out[o:o+8] = A[r, g:g+8, :n] · x[:n] (eight simultaneous dot products)."""
    a0 = a1 = a2 = a3 = a4 = a5 = a6 = a7 = 0.0
    for i in range(n):
        xi = x[i]
        a0 += A[r, g, i] * xi
        a1 += A[r, g + 1, i] * xi
        a2 += A[r, g + 2, i] * xi
        a3 += A[r, g + 3, i] * xi
        a4 += A[r, g + 4, i] * xi
        a5 += A[r, g + 5, i] * xi
        a6 += A[r, g + 6, i] * xi
        a7 += A[r, g + 7, i] * xi
    out[o] = a0
    out[o + 1] = a1
    out[o + 2] = a2
    out[o + 3] = a3
    out[o + 4] = a4
    out[o + 5] = a5
    out[o + 6] = a6
    out[o + 7] = a7


@numba.njit(cache=True, _nrt=False, fastmath=_FM, inline="always")
def rows(A, r, g, count, x, n, out, o):
    """out[o:o+count] = A[r, g:g+count, :n] · x[:n]: groups of four simultaneous dot products, then single rows."""
    k = 0
    while k + 4 <= count:
        a0 = a1 = a2 = a3 = 0.0
        for i in range(n):
            xi = x[i]
            a0 += A[r, g + k, i] * xi
            a1 += A[r, g + k + 1, i] * xi
            a2 += A[r, g + k + 2, i] * xi
            a3 += A[r, g + k + 3, i] * xi
        out[o + k] = a0
        out[o + k + 1] = a1
        out[o + k + 2] = a2
        out[o + k + 3] = a3
        k += 4
    while k < count:
        a0 = 0.0
        for i in range(n):
            a0 += A[r, g + k, i] * x[i]
        out[o + k] = a0
        k += 1


@numba.njit(cache=True, _nrt=False, fastmath=_FM, inline="always")
def exp_modes(lam_re, lam_im, fine_re, fine_im, q, h, tau, E):
    """E[0] + i E[1] = e^{λ τ} of every mode of basis q, 0 <= τ <= h: e^{λ k h/FINE} from the table
    times the degree-9 series of e^{λ δ}, δ = τ - k h/FINE in [0, h/FINE). A complex λ has
    |λ| <= 2π f_max, so |λ δ| < π/FINE (0.05) for any accepted step (h <= 1/(2 f_max)):
    truncation < 1e-19 relative (a real λ of an overdamped mode can exceed 2π f_max)."""
    n2p = lam_re.shape[1]
    k = int(tau * (FINE / h))
    if k > FINE:
        k = FINE
    if k < 0:
        k = 0
    d = tau - k * (h / FINE)
    for i in range(n2p):  # Horner written out: one straight-line body per mode (vectorises over i)
        xr = lam_re[q, i] * d
        xi = lam_im[q, i] * d
        pr = xr * _E9 + _E8
        pi = xi * _E9
        t = pr * xr - pi * xi + _E7
        pi = pr * xi + pi * xr
        pr = t
        t = pr * xr - pi * xi + _E6
        pi = pr * xi + pi * xr
        pr = t
        t = pr * xr - pi * xi + _E5
        pi = pr * xi + pi * xr
        pr = t
        t = pr * xr - pi * xi + _E4
        pi = pr * xi + pi * xr
        pr = t
        t = pr * xr - pi * xi + _E3
        pi = pr * xi + pi * xr
        pr = t
        t = pr * xr - pi * xi + _E2
        pi = pr * xi + pi * xr
        pr = t
        t = pr * xr - pi * xi + 1.0
        pi = pr * xi + pi * xr
        pr = t
        t = pr * xr - pi * xi + 1.0
        pi = pr * xi + pi * xr
        pr = t
        E[0, i] = fine_re[q, k, i] * pr - fine_im[q, k, i] * pi
        E[1, i] = fine_re[q, k, i] * pi + fine_im[q, k, i] * pr


@numba.njit(cache=True, _nrt=False, fastmath=_FM, inline="always")
def diag_mul(E, zin, zout):
    """zout[:nx] = E zin[:nx], E = E[0] + i E[1] per mode (a separate loop from exp_modes: each
    vectorises, one loop doing both does not)."""
    n2p = E.shape[1]
    for i in range(n2p):
        a = zin[i]
        b = zin[n2p + i]
        zout[i] = E[0, i] * a - E[1, i] * b
        zout[n2p + i] = E[0, i] * b + E[1, i] * a


@numba.njit(cache=True, _nrt=False, fastmath=_FM, inline="always")
def expmul(lam_re, lam_im, fine_re, fine_im, q, h, tau, zin, zout, E):
    """zout[:nx] = e^{λ τ} zin[:nx] in basis q, 0 <= τ <= h; E (2, n2p) receives e^{λ τ}."""
    exp_modes(lam_re, lam_im, fine_re, fine_im, q, h, tau, E)
    diag_mul(E, zin, zout)


@numba.njit(cache=True, _nrt=False, fastmath=_FM, inline="always")
def block_advance(step_re, step_im, q, n, z):
    """z[:nx] <- e^{λ n h} z[:nx] in basis q (tabulated)."""
    n2p = step_re.shape[2]
    for i in range(n2p):
        a = z[i]
        b = z[n2p + i]
        er = step_re[q, n, i]
        ei = step_im[q, n, i]
        z[i] = er * a - ei * b
        z[n2p + i] = er * b + ei * a


@numba.njit(cache=True, _nrt=False, fastmath=_FM, inline="always")
def slope_update(slope_rows, q, df, z):
    """z[:nx] += Σ_l slope_rows[q, l] df_l, df = f'_old - f'_new padded with zeros to a multiple of
    8: ζ = z - z_p stays continuous when the load slope changes. Eight loads per pass over ζ."""
    n = slope_rows.shape[2]
    for c in range(0, df.shape[0], 8):
        d0 = df[c]
        d1 = df[c + 1]
        d2 = df[c + 2]
        d3 = df[c + 3]
        d4 = df[c + 4]
        d5 = df[c + 5]
        d6 = df[c + 6]
        d7 = df[c + 7]
        for i in range(n):
            z[i] += (((slope_rows[q, c, i] * d0 + slope_rows[q, c + 1, i] * d1)
                      + (slope_rows[q, c + 2, i] * d2 + slope_rows[q, c + 3, i] * d3))
                     + ((slope_rows[q, c + 4, i] * d4 + slope_rows[q, c + 5, i] * d5)
                        + (slope_rows[q, c + 6, i] * d6 + slope_rows[q, c + 7, i] * d7)))


@numba.njit(cache=True, _nrt=False, inline="always")
def set_load(x, nx, m, fs, f1, t):
    """Tail of an extended input xl = [ζ; f; f'; 1]: the load fs + f1 t and its slope f1 (m loads)."""
    for l in range(m):
        x[nx + l] = fs[l] + f1[l] * t
        x[nx + m + l] = f1[l]
    x[nx + 2 * m] = 1.0


@numba.njit(cache=True, _nrt=False, inline="always")
def set_load_rows(x, nx, m, fs, f1, t):
    """``set_load`` (same values) for fs, f1 rows of ``Work.L`` zero beyond m (m8 = m rounded up to
    8 entries) written as whole rows: when xl has room, f and f' are written as rows of m8 (f
    first: its zero pad lanes are overwritten by f', whose pad lanes fall on the 1 written last
    and on xl's zero pad), which LLVM vectorises (m = 7: one 8-wide operation for 7 scalar ones).
    For rows written as whole rows just before (a load after narrower stores of the same bytes
    stalls: ``set_load`` there)."""
    m8 = fs.shape[0]
    if nx + m + m8 > x.shape[0]:
        set_load(x, nx, m, fs, f1, t)
        return
    for l in range(m8):
        x[nx + l] = fs[l] + f1[l] * t
    for l in range(m8):
        x[nx + m + l] = f1[l]
    x[nx + 2 * m] = 1.0
