"""Scratch arrays and counters of the exact kernels, allocated once per realisation.

The scratch is a few 2-D arrays whose rows are named below (compact argument lists keep numba's
calls between kernels cheap). An extended input xl = [ζ; f; f'; 1; 0...] (length nxl, see
``_regimes``) holds a modal state and the load at one instant.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from tubeid.dynamics.solver._regimes import ExactTables, aligned

__all__ = ["Work", "make_work", "XL", "X0", "XE", "XS", "F0", "F1", "FS", "DF", "FN", "U_START", "UD_START", "U_END",
           "UD_END", "U_CROSS", "UD_CROSS", "STATS", "N_STATS", "FLAGGED_STEPS", "SWITCHES", "RESCANS", "EVALUATIONS",
           "MAX_SWITCHES"]

#: Rows of Work.X (extended inputs):
XL = 0  # fast path: the running state ζ and the load at the current block start
X0 = 1  # event path: at the start of the current segment
XE = 2  # ... at the end of the sub-step
XS = 3  # ... at a switch instant (the input of the basis-to-basis transform)
#: Rows of Work.L (load vectors, zero beyond m):
F0 = 0  # load at the start of the current load interval
F1 = 1  # its slope
FS = 2  # load at the start of a flagged sub-step
DF = 3  # f'_old - f'_new at a load sample
FN = 4  # slope of the next load interval (computed one interval ahead)
#: Rows of Work.U (one column per stop):
U_START = 0  # u at the start of the current sub-step (fast path) or segment (event path)
UD_START = 1  # u'
U_END = 2  # u at the end of the sub-step
UD_END = 3  # u'
U_CROSS = 4  # u at the earliest crossing found in the segment
UD_CROSS = 5  # u'

#: The int64 ``stats`` counters of one realisation (an array of N_STATS, zeroed by ``_exact``), in
#: slot order. A name here is the counter's key in the diagnostics of ``simulate_with_diagnostics``
#: (``_exact`` reports every one); its slot is the constant below, ``STATS.index(name)``. To add a
#: counter: append its name, add its slot constant the same way, increment ``stats[SLOT]`` in the
#: kernel (``_fastpath``, ``_events``). The kernels do not check bounds: a slot must come from
#: ``STATS``, never a literal.
STATS = ("flagged_steps", "switches", "rescans", "evaluations")
FLAGGED_STEPS = STATS.index("flagged_steps")  # sub-steps the pre-check sent to the event path
SWITCHES = STATS.index("switches")  # regime switches, in the whole run (two per contact)
#: boundary searches of a segment rescanned exactly on ``_events._PIECES`` pieces (the Hermite check on
#: [0, t_c] allowed an earlier dip; with ``refine_all``, also every search whose boundary is not
#: crossed at the segment's end)
RESCANS = STATS.index("rescans")
#: exact evaluations of u, u', u'' inside sub-steps (``_events.evaluate`` through ``_eval``: crossing
#: and minimum searches, rescans)
EVALUATIONS = STATS.index("evaluations")
N_STATS = len(STATS)
#: A sub-step reaching this many switches before its end raises RuntimeError in ``_events.event_step``
#: (chattering or a bad model); the message there states the number as a literal.
MAX_SWITCHES = 200


class Work(NamedTuple):
    """Scratch of the exact kernels (float64 arrays; S stops)."""

    X: np.ndarray  # (4, nxl) extended inputs, rows XL, X0, XE, XS
    L: np.ndarray  # (5, m8) load vectors, rows F0, F1, FS, DF, FN
    U: np.ndarray  # (6, S) u and u' of every stop, rows U_START ... UD_CROSS
    col: np.ndarray  # (ncp,) block rows · X[XL]: u, u' of every stop at the block's sub-step ends
    y: np.ndarray  # (n_obs,) outputs
    ev: np.ndarray  # (3S rounded up to 4, at least 4) stop rows · x: u, u', u'' of stop s at 3s, 3s + 1, 3s + 2
    eval_tau: np.ndarray  # (1,) time of the last exact evaluation (from the segment start)
    E: np.ndarray  # (2, n2p) e^{λ τ} (real and imaginary parts) of the last exp_modes
    A: np.ndarray  # (S, 6, n2p) event search, per stop: Re, Im of a = cu ζ0, λ a, λ² a (segment start ζ0)
    QS: np.ndarray  # (S, 4) ... and its quasi-static part: u = Q0 + Q1 τ, u' = P0 + P1 τ, u'' = P1


def make_work(T: ExactTables, n_obs: int) -> Work:
    """Zeroed scratch for tables T and n_obs outputs (aligned like the tables)."""
    def z(shape):
        return aligned(np.zeros(shape))
    return Work(X=z((4, T.block_rows.shape[2])), L=z((5, T.slope_rows.shape[1])), U=z((6, T.gaps.shape[0])),
                col=z(T.block_rows.shape[1]), y=z(n_obs), ev=z(max(T.stop_rows.shape[1], 4)), eval_tau=z(1),
                E=z((2, T.lam_re.shape[1])), A=z((T.gaps.shape[0], 6, T.lam_re.shape[1])), QS=z((T.gaps.shape[0], 4)))
