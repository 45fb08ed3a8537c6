"""Transient solver for linear structures with symmetric elastic stops.

Equation (SI units, q in reduced coordinates), from rest (q = q' = 0)::

    M q'' + D q' + K q + Σ_s b_s f_s(b_sᵀ q) = B F(t),     y = C q,
    f_s(u) = k_s (|u| - g_s) sign(u)  if |u| > g_s  else 0.

F is given by samples on a uniform grid of step dt_load and read as their continuous
piecewise-linear interpolant.

Method ``"exact"`` (default). The system is piecewise linear: each stop is open or in contact on
one side, 3**S regimes. In each regime the modal equations are integrated exactly for the
piecewise-linear load; nothing is approximated between regimes except the location of the
switching instants, found by safeguarded Halley iterations on the exact closed form (tolerance:
the fraction ``_regimes.CROSSING_TOL`` of the step), and a switch keeps the state continuous. A
cubic-Hermite pre-check with a margin (``_regimes.MARGIN_SAFETY`` times the Hermite error bound of
the highest mode) decides which sub-steps can contain a switch; the only approximation left is to
miss a grazing excursion shallower than that margin.

Method ``"symplectic-euler"`` (the semi-implicit Euler of industrial modal codes):
v += dt M⁻¹ (B F - D v - K q - f); q += dt v. First order.

Step rule (:func:`choose_step`): f_max is the highest undamped frequency with every stop closed
(:func:`highest_frequency`; it bounds every regime). Exact: default dt <= 1/(4 f_max) (between
events the solution is exact whatever the step; the step sets the pre-check's resolution), a user
step above 1/(2 f_max) is refused (a whole contact oscillation can fall inside one step unseen),
above 1/(3 f_max) warned. Symplectic Euler: default w_max dt <= 0.25, warned above 0.5, refused at
2 (unstable). The paper's 3 ms is the OUTPUT sampling (MODEL.md section 3.7): as an integration
step it is refused by both methods. Speed and accuracy figures: the README ("Performance") and
``tubeid bench transient --json``.

Module map (private modules behind this API):

==================  ===========================================================================
``_base``           :class:`Stop`, :class:`TransientResult` and the labelling of results
``_checks``         every input check, up front: a validated ``Problem``
``_step``           :func:`highest_frequency` and the methods' step rules
``_simulate``       :func:`simulate`, :func:`choose_step` and the registry :data:`METHODS`
``_exact``          method "exact": tables, scratch and kernel call of one realisation
``_regimes``        the regimes' modal tables (numpy) and the exact method's constants
``_work``           named rows of the exact kernels' scratch, and their counters (``STATS``)
``_modal``          numba primitives on the modal state (row products, e^{λτ}, block advance)
``_fastpath``       numba: the main loop (blocks of sub-steps, the event pre-check, outputs)
``_events``         numba: a flagged sub-step integrated exactly (crossing search, switches)
``_symplectic``     method "symplectic-euler" (numba kernel), the reference scheme
``_determinism``    one BLAS thread for the tables: bit-identical results on any worker
``_kernel_cache``   numba's on-disk cache of the kernels keyed on all the solver's sources
==================  ===========================================================================

Where to make a change:

- the crossing tolerance: ``_regimes.CROSSING_TOL`` (a fraction of the step; the tables carry it
  as ``xtol``, read by ``_events._crossing_in`` for the root and for the Newton search of a minimum);
- the pre-check margin's safety factor: ``_regimes.MARGIN_SAFETY`` (the tables carry it in
  ``mcoef``, read by the checks of ``_fastpath`` and ``_events``); the step limits it is tied to:
  ``_step.EXACT_RULE``;
- a counter of the exact kernels (in ``simulate_with_diagnostics``' diagnostics): ``_work.STATS``
  (its comment says how), incremented in ``_fastpath`` or ``_events``; ``_exact`` reports it;
- an output kind (another observed quantity than y = C q): the rows ``output_rows`` built in
  ``_regimes`` (exact method), their evaluation at the output instants in ``_fastpath.run_exact``
  (outputs at accepted sub-step ends, and after a flagged sub-step), ``_symplectic._kernel`` (y at
  step ends), the arrays and statistics of ``_simulate._run`` and the labels of ``_base``
  (``TransientResult``, ``assemble_result``);
- an input check: ``_checks.prepare`` (scalar rules from ``tubeid._validation``);
- a method: a :class:`~tubeid.dynamics.solver._simulate.Method` in ``_simulate.METHODS``.

An edit of any of these files recompiles the cached kernels on the next import (``_kernel_cache``).
"""

from tubeid.dynamics.solver import _events, _fastpath, _modal, _symplectic
from tubeid.dynamics.solver._base import Stop, TransientResult
from tubeid.dynamics.solver._kernel_cache import cached_kernels, key_on_sources, sources_fingerprint
from tubeid.dynamics.solver._simulate import METHODS, check_substeps, choose_step, simulate
from tubeid.dynamics.solver._step import highest_frequency

# before any kernel is called: a cached kernel is recompiled when any of the solver's sources changed
key_on_sources(cached_kernels([_modal, _events, _fastpath, _symplectic]), sources_fingerprint())

__all__ = ["Stop", "TransientResult", "simulate", "choose_step", "check_substeps", "highest_frequency", "METHODS"]
