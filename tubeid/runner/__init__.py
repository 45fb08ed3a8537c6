"""The study runner: sweeps defined in Python, run as dask task graphs, stored as labelled Zarr."""

from tubeid.runner.execute import run
from tubeid.runner.store import open_results
from tubeid.runner.study import Output, Parameter, Study, load_study, pointwise

__all__ = ["Study", "Output", "Parameter", "pointwise", "load_study", "run", "open_results"]
