"""Diagnose measured data against a declared model: a calibrated test, then the effects it lacks.

An application on top of the layers (mechanics → uncertainty → dynamics → identification, run by
the study runner): :func:`diagnose` tests whether a record is one more realisation of the declared
stochastic model (:func:`detection_test`, exact at a stated false-alarm rate, its statistics chosen by
what the declared model is taken to be: :data:`MODEL_FORMS`), and when it is not, selects effects of
the :data:`CATALOG` one at a time by held-out error, re-fitting all of them and the load jointly,
until the record is explained. ``tubeid diagnose`` is its command line.

Modules: :mod:`~tubeid.diagnose.method` (the loop and its context), :mod:`~tubeid.diagnose.stages`
(the runner pipeline), :mod:`~tubeid.diagnose.catalog` (one class per effect),
:mod:`~tubeid.diagnose.report` (report.json, report.md, figures), :mod:`~tubeid.diagnose.cli`.
Every name below is imported on first use (PEP 562).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from tubeid._lazy import attach

if TYPE_CHECKING:  # the lazy exports: imported on first use (tubeid._lazy reads this block)
    from tubeid.diagnose._detection import MODEL_FORMS, STATISTICS, Detection, Observations, detection_test
    from tubeid.diagnose._settings import LOAD_MODELS, MAX_EFFECTS, DiagnoseSettings
    from tubeid.diagnose.catalog import CATALOG, Candidate
    from tubeid.diagnose.method import Diagnosis, diagnose

__all__ = ["diagnose", "DiagnoseSettings", "Diagnosis", "detection_test", "Detection", "Observations", "STATISTICS",
           "MODEL_FORMS", "CATALOG", "Candidate", "LOAD_MODELS", "MAX_EFFECTS"]

__getattr__, __dir__ = attach(__name__, __file__)
