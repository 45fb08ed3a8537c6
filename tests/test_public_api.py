"""The public surface is small, explicit and pinned: changing it is a deliberate act."""

import importlib

import pytest

import tubeid

PINNED = {
    "tubeid": [
        "__version__", "SpecificationError", "rng_for",
        "BundleSpec", "TubeSpec", "LinkSpec", "StopSpec", "LoadPoint", "SensorSpec", "ReductionSpec",
        "builtin_spec", "load_spec", "reduce",
        "sg_plus", "Dispersion", "coherent_forces", "force_and_moment", "gaussian_loads",
        "identify_delta", "likelihood_curve", "read_measurements",
        "Study", "Output", "Parameter", "open_results",
    ],
    "tubeid.mechanics": [
        "BundleSpec", "TubeSpec", "LinkSpec", "StopSpec", "LoadPoint", "SensorSpec", "ReductionSpec",
        "load_spec", "builtin_spec", "resolve_spec", "BUILTIN_MODELS",
        "FEModel", "assemble", "ReducedModel", "ReducedSubsystem", "reduce",
        "condensed_stiffness", "j_functional", "J_UNITS",
    ],
    "tubeid.uncertainty": [
        "sg_plus", "se_plus", "delta_max", "Dispersion",
        "random_subsystem", "random_condensed_stiffness", "j_monte_carlo",
        "LoadSpectrum", "coherent_forces", "force_and_moment", "tabulated", "randomised", "gaussian_loads",
    ],
    "tubeid.dynamics": [
        "Stop", "TransientResult", "simulate", "highest_frequency", "choose_step",
        "ResponseSettings", "simulate_responses",
        "psd_matrix", "psd_dataset", "variance_from_psd", "confidence_band", "j_s", "distance", "log_level",
    ],
    "tubeid.identification": [
        "identify_delta", "reference_j", "likelihood_curve", "kde_pdf", "silverman_bandwidth",
        "identify_r", "fine_grid", "DISTANCES",
        "distance_map", "log_band_distance_map", "log_spectral_distance_map", "relative_weight", "refine_grid",
        "delta_f_likelihood",
    ],
    "tubeid.measured": ["read_measurements", "write_measurements", "validate_measurements"],
    "tubeid.diagnose": ["diagnose", "DiagnoseSettings", "Diagnosis", "detection_test", "Detection", "Observations",
                        "STATISTICS", "MODEL_FORMS", "CATALOG", "Candidate", "LOAD_MODELS", "MAX_EFFECTS"],
    "tubeid.runner": [
        "Study", "Output", "Parameter", "pointwise", "load_study", "run", "open_results", "RunReport", "RngFactory",
        "store_status", "Pipeline", "End", "PipelineReport", "open_pipeline", "pipeline_status", "Warmup", "verify",
        "Verification",
    ],

}


@pytest.mark.parametrize("module", sorted(PINNED))
def test_public_api_is_pinned(module):
    mod = importlib.import_module(module)
    assert sorted(mod.__all__) == sorted(PINNED[module])
    for name in mod.__all__:
        assert hasattr(mod, name), f"{module}.{name} is exported but missing"


def test_every_module_declares_all():
    import pkgutil

    missing = []
    for info in pkgutil.walk_packages(tubeid.__path__, "tubeid."):
        if info.name.endswith("__main__"):
            continue
        mod = importlib.import_module(info.name)
        if not hasattr(mod, "__all__"):
            missing.append(info.name)
    assert not missing, f"modules without __all__: {missing}"
