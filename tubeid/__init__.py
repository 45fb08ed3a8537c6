"""tubeid — robust identification of turbulent-flow loads on tube bundles from measured vibrations.

The method of Batou & Soize (2008): a simplified bundle model with nonparametric model
uncertainty (δ), a stochastic load model (r, δ_F), identified by maximum likelihood and trial
grids, run as dask task graphs into labelled Zarr stores. Sub-packages: ``mechanics``,
``uncertainty``, ``dynamics``, ``identification``, ``measured``, ``runner``.

Every name below is imported on first use (PEP 562), so ``import tubeid`` loads no numerical
library; ``from tubeid import Study`` and ``tubeid.Study`` work as usual.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from tubeid._lazy import attach
from tubeid._version import __version__

if TYPE_CHECKING:  # the lazy exports: imported on first use (tubeid._lazy reads this block)
    from tubeid.errors import SpecificationError
    from tubeid.identification.delta import identify_delta
    from tubeid.identification.likelihood import likelihood_curve
    from tubeid.measured.readers import read_measurements
    from tubeid.mechanics.library import builtin_spec
    from tubeid.mechanics.reduction import reduce
    from tubeid.mechanics.spec import (BundleSpec, LinkSpec, LoadPoint, ReductionSpec, SensorSpec, StopSpec, TubeSpec,
                                       load_spec)
    from tubeid.runner.store import open_results
    from tubeid.runner.study import Output, Parameter, Study
    from tubeid.seeds import rng_for
    from tubeid.uncertainty.loads import coherent_forces, force_and_moment
    from tubeid.uncertainty.processes import gaussian_loads
    from tubeid.uncertainty.random_matrices import Dispersion, sg_plus


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

__getattr__, __dir__ = attach(__name__, __file__)
