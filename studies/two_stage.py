# studies/two_stage.py
import numpy as np
from tubeid.runner.pipeline import Pipeline
from tubeid.runner.study import Output, Parameter, Study, pointwise

SEED = 2008
N = {"paper": 200, "quick": 40}

@pointwise
def j_point(point, rng):                       # rng keyed by (SEED, "delta", realisation)
    return {"J": (point["delta"] - 0.45) ** 2 + 0.1 * rng.standard_normal()}

@pointwise
def response_point(point, rng, *, delta):      # delta_opt arrives as a parameter: stored and hashed
    return {"u": delta * rng.standard_normal()}

def delta_opt(ds):                             # stored as stage attributes when the stage completes
    return {"delta_opt": float(ds.J.mean("realisation").idxmin("delta"))}

def delta(results, *, size):                   # stage "delta" (the function's name)
    return Study(name="delta", seed=SEED, axes={"delta": np.round(np.arange(0.05, 0.9, 0.05), 2),
                 "realisation": range(N[size])}, seed_axes=("realisation",), task=j_point,
                 outputs={"J": Output()}, summarize=delta_opt)

def response(results, *, size):                # runs once "delta" is complete
    d = results["delta"].attrs["delta_opt"]
    return Study(name="response", seed=SEED, axes={"realisation": range(N[size])}, task=response_point,
                 outputs={"u": Output(units="m")}, parameters={"delta": d})

study = Pipeline(name="two-stage", seed=SEED, stages=[delta, response],
                 parameters={"size": Parameter("paper", choices=["paper", "quick"])})
