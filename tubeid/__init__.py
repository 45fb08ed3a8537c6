"""tubeid — robust identification of turbulent-flow loads on tube bundles from measured vibrations.

The method of Batou & Soize (2008): a simplified bundle model with nonparametric model
uncertainty (δ), a stochastic load model (r, δ_F), identified by maximum likelihood and trial
grids, run as dask task graphs into labelled Zarr stores. Sub-packages: ``mechanics``,
``uncertainty``, ``dynamics``, ``identification``, ``measured``, ``runner``.
"""

from importlib.metadata import PackageNotFoundError, version

from tubeid.errors import SpecificationError
from tubeid.identification import identify_delta, likelihood_curve
from tubeid.mechanics import BundleSpec, LinkSpec, LoadPoint, ReductionSpec, SensorSpec, StopSpec, TubeSpec, builtin_spec, load_spec, reduce
from tubeid.measured import read_measurements
from tubeid.runner import Output, Parameter, Study, open_results
from tubeid.seeds import rng_for
from tubeid.uncertainty import Dispersion, coherent_forces, force_and_moment, gaussian_loads, sg_plus

try:
    __version__ = version("tubeid")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    __version__ = "0.0.0"

__all__ = [
    "__version__",
    "SpecificationError",
    "rng_for",
    # mechanics
    "BundleSpec", "TubeSpec", "LinkSpec", "StopSpec", "LoadPoint", "SensorSpec", "ReductionSpec",
    "builtin_spec", "load_spec", "reduce",
    # uncertainty
    "sg_plus", "Dispersion", "coherent_forces", "force_and_moment", "gaussian_loads",
    # identification
    "identify_delta", "likelihood_curve",
    # measured data
    "read_measurements",
    # runner
    "Study", "Output", "Parameter", "open_results",
]
