"""Example study: a realisation-bound Monte Carlo estimate of π (the runner's smallest sweep).

Each realisation draws ``samples`` points in the unit square and returns 4 × the fraction inside
the quarter disc (variance ≈ π(4 − π)/samples). Run: ``tubeid run studies/example_pi.py``, then
``tubeid show results/example-pi.zarr``.
"""

import numpy as np

from tubeid.runner.study import Output, Parameter, Study, pointwise


@pointwise
def estimate(point, rng, *, samples):
    x, y = rng.random((2, samples))
    return {"pi": 4.0 * np.count_nonzero(x * x + y * y <= 1.0) / samples}


study = Study(
    name="example-pi",
    seed=314159,
    axes={"realisation": range(256)},
    chunks={"realisation": 32},
    task=estimate,
    outputs={"pi": Output(units="1", long_name="Monte Carlo estimate of pi")},
    parameters={"samples": Parameter(200_000, bounds=(1, 10**8), doc="points per realisation")},
)
