"""Example study: Monte Carlo of the SG+ random-matrix ensemble over a grid of dispersions δ.

For each (δ, realisation) one G ∈ SG+ of size n is drawn; the study stores ‖G − I‖²_F / n (whose
mean over realisations is δ², MODEL.md §3.3) and quantiles of the eigenvalues of G. The random streams are
keyed by the realisation only (``seed_axes``), so every δ uses common random numbers: the curves
over δ are smooth, as a likelihood grid needs. Run: ``tubeid run studies/example_sgplus.py``.
"""

import numpy as np

from tubeid.errors import SpecificationError
from tubeid.runner.study import Output, Parameter, Study, pointwise
from tubeid.uncertainty.random_matrices import delta_max, sg_plus


@pointwise
def draw(point, rng, *, n):
    G = sg_plus(n, point["delta"], rng=rng)
    eigenvalues = np.linalg.eigvalsh(G)
    return {"dispersion": np.sum((G - np.eye(n)) ** 2) / n, "eigenvalues": np.quantile(eigenvalues, QUANTILES)}


def admissible(study):
    n = study.values["n"]
    bad = study.axes["delta"][(study.axes["delta"] <= 0) | (study.axes["delta"] >= delta_max(n))]
    if bad.size:
        raise SpecificationError("axes.delta", bad.tolist(), f"SG+ needs 0 < delta < sqrt((n+1)/(n+5)) = {delta_max(n):.4f}")


QUANTILES = [0.0, 0.25, 0.5, 0.75, 1.0]
study = Study(
    name="example-sgplus",
    description="SG+ ensemble: squared dispersion and eigenvalues over a delta grid",
    seed=20080101,
    axes={"delta": np.round(np.linspace(0.05, 0.60, 12), 4), "realisation": range(400)},
    chunks={"delta": 4, "realisation": 100},
    seed_axes=("realisation",),
    task=draw,
    coords={"quantile": QUANTILES},
    outputs={
        "dispersion": Output(units="1", long_name="||G - I||_F^2 / n (mean = delta^2)"),
        "eigenvalues": Output(dims=("quantile",), units="1", long_name="quantiles of the eigenvalues of G"),
    },
    units={"delta": "1", "realisation": "1", "quantile": "1"},
    parameters={"n": Parameter(6, bounds=(1, 64), doc="matrix size")},
    check=admissible,
)
