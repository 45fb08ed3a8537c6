# studies/pi.py
import numpy as np
from tubeid.runner import Output, Parameter, Study, pointwise

@pointwise                                   # per-point function -> block task
def estimate(point, rng, *, samples):        # rng: this point's generator
    x, y = rng.random((2, samples))
    return {"pi": 4 * np.mean(x * x + y * y <= 1)}

study = Study(name="pi", seed=1, axes={"realisation": range(256)}, chunks={"realisation": 32},
              task=estimate, outputs={"pi": Output(units="1")},
              parameters={"samples": Parameter(100_000, bounds=(1, 10**7), doc="points per realisation")})
