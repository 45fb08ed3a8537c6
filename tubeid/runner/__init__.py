"""The study runner: sweeps defined in Python, run as dask task graphs, stored as labelled Zarr."""

from tubeid.runner.execute import PipelineReport, RunReport, run
from tubeid.runner.pipeline import Pipeline
from tubeid.runner.store import open_pipeline, open_results, pipeline_status, store_status
from tubeid.runner.integrity import Verification, verify
from tubeid.runner.study import Output, Parameter, RngFactory, Study, Warmup, load_study, pointwise

__all__ = [
    "Study", "Output", "Parameter", "pointwise", "load_study", "run", "open_results", "RunReport", "RngFactory",
    "store_status", "Pipeline", "PipelineReport", "open_pipeline", "pipeline_status", "Warmup", "verify", "Verification",
]
