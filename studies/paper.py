"""Paper stage 1: model-to-model likelihood of the model dispersion δ (paper §2.4, Figure 5).

For every (δ, realisation): one random stiffness K_B ∈ SE+ of the simplified model's reduced
linear subsystem and its J = ∫ ‖Z(ω)⁻¹‖²_F dω (closed form). Germs are keyed by the realisation
only, so every δ shares common random numbers. Then ``tubeid.identification.likelihood_curve``
on the stored J gives p_J(J_ref; δ) and δ_opt (see ``tubeid report``).
Run: ``tubeid run studies/paper.py``.
"""

import numpy as np

from tubeid.identification.delta import default_delta_grid, reference_j
from tubeid.mechanics.library import builtin_spec
from tubeid.mechanics.spec import spec_to_dict
from tubeid.mechanics.reduction import J_UNITS, j_functional, reduce
from tubeid.runner.study import Output, Parameter, Study
from tubeid.uncertainty.random_matrices import Dispersion
from tubeid.uncertainty.random_models import germs_from_rngs, random_subsystem

SUB = reduce(builtin_spec("paper-simplified")).subsystem


def j_block(block, rng, *, band_hz):
    rngs = [rng.at({"realisation": int(r)}) for r in block["realisation"]]
    germs = germs_from_rngs(SUB.n, rngs)
    out = np.empty((len(block["delta"]), len(block["realisation"])))
    for i, d in enumerate(block["delta"]):
        M, D, K = random_subsystem(SUB, Dispersion(stiffness=float(d)), 0, block["realisation"], germs=germs)
        out[i] = j_functional(M, D, K, SUB.n_c, band_hz)
    return {"J": out}


study = Study(
    name="paper",
    description=f"J(delta) Monte Carlo of the stochastic simplified model; J_ref = {reference_j('paper-reference'):.6e} {J_UNITS}",
    seed=2008,
    axes={"delta": np.round(default_delta_grid(SUB.n), 4), "realisation": range(200)},
    chunks={"delta": 35, "realisation": 50},
    seed_axes=("realisation",),
    task=j_block,
    outputs={"J": Output(units=J_UNITS, long_name="J = integral of ||Z(w)^-1||_F^2 over the band")},
    units={"delta": "1", "realisation": "1"},
    parameters={"band_hz": Parameter(100.0, bounds=(1e-3, 1e4), units="Hz", doc="band of analysis")},
    model=spec_to_dict(builtin_spec("paper-simplified")),
)
