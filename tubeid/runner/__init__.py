"""The study runner: sweeps defined in Python, run as dask task graphs, stored as labelled Zarr."""

from __future__ import annotations

from typing import TYPE_CHECKING

from tubeid._lazy import attach

if TYPE_CHECKING:  # the lazy exports: imported on first use (tubeid._lazy reads this block)
    from tubeid.runner.execute import PipelineReport, RunReport, run
    from tubeid.runner.integrity import Verification, verify
    from tubeid.runner.pipeline import End, Pipeline
    from tubeid.runner.status import pipeline_status, store_status
    from tubeid.runner.store import open_pipeline, open_results
    from tubeid.runner.study import Output, Parameter, RngFactory, Study, Warmup, load_study, pointwise

__all__ = [
    "Study", "Output", "Parameter", "pointwise", "load_study", "run", "open_results", "RunReport", "RngFactory",
    "store_status", "Pipeline", "End", "PipelineReport", "open_pipeline", "pipeline_status", "Warmup", "verify",
    "Verification",
]

__getattr__, __dir__ = attach(__name__, __file__)
