"""The package's shared argument checks (``tubeid._validation``): one wording, no booleans or text as numbers."""

import math
import warnings

import numpy as np
import pytest

from tubeid import _validation as v
from tubeid.errors import SpecificationError


@pytest.mark.parametrize("bad", [True, False, np.bool_(True), "1.0", None, [1.0], 1 + 0j, math.nan, math.inf, -math.inf])
def test_real_refuses_what_is_not_a_finite_number(bad):
    with pytest.raises(SpecificationError, match=r"^x = .*: must be a finite number"):
        v.real("x", bad)


def test_numpy_values_are_shown_as_plain_numbers_and_strings_in_messages():
    """NumPy 2 reprs a scalar as ``np.float64(0.3)``: a message shows the value it holds, inside
    containers too (float32 by its own shortest digits); arrays keep their repr."""
    from tubeid.errors import shown

    with pytest.raises(SpecificationError) as info:
        v.real("delta", np.float64(-1.0), low=0.0)
    assert str(info.value) == "delta = -1.0: must be a finite number >= 0"
    with pytest.raises(SpecificationError) as info:
        v.integer("n", np.float64(3.0))
    assert str(info.value) == "n = 3.0: must be an integer"
    with pytest.raises(SpecificationError) as info:
        v.one_of("k", 5, (np.int64(1), np.int64(2)))
    assert str(info.value) == "k = 5: must be one of 1, 2"
    assert shown(np.int64(128)) == "128" and shown(np.float32(0.3)) == "0.3" and shown(np.bool_(True)) == "True"
    assert shown(np.str_("c02")) == "'c02'" and shown(np.complex64(1 + 2j)) == "(1+2j)"
    assert shown([np.float64(0.1), (np.int8(-5), {"a": np.float16(0.5)})]) == "[0.1, (-5, {'a': 0.5})]"
    assert shown(np.array([1.0, 2.0])) == "array([1., 2.])"


def test_real_converts_numpy_and_python_numbers_to_float():
    for good in (3, 3.5, np.float32(2.5), np.int64(4), np.float64(-1e300)):
        out = v.real("x", good)
        assert type(out) is float and out == float(good)


def test_bounds_open_and_closed():
    assert v.real("x", 0.0, low=0.0) == 0.0
    with pytest.raises(SpecificationError, match=r"> 0"):
        v.real("x", 0.0, low=0.0, low_open=True)
    with pytest.raises(SpecificationError, match=r"in \(0, 1\)"):
        v.open_unit("confidence", 1.0)
    with pytest.raises(SpecificationError, match=r"in \(0, 1\)"):
        v.open_unit("confidence", 0.0)
    assert v.open_unit("confidence", 0.95) == 0.95
    with pytest.raises(SpecificationError, match=r"<= 2"):
        v.real("x", 2.0000001, high=2.0)


def test_positive_and_non_negative_name_field_value_rule_and_unit():
    with pytest.raises(SpecificationError) as e:
        v.positive("tubes[0].length", -2.0, "m")
    assert str(e.value) == "tubes[0].length = -2.0: must be a finite number > 0 (m)"
    assert v.non_negative("gap", 0) == 0.0
    with pytest.raises(SpecificationError, match=">= 0"):
        v.non_negative("gap", -1e-300)


@pytest.mark.parametrize("bad", [True, 3.0, "3", np.float64(3.0), None])
def test_integer_refuses_bools_floats_and_text(bad):
    with pytest.raises(SpecificationError, match="must be an integer"):
        v.integer("n", bad)


def test_integer_bounds():
    assert v.integer("n", np.int32(5), minimum=0, maximum=5) == 5
    with pytest.raises(SpecificationError, match=r"integer in \[0, 5\]"):
        v.integer("n", 6, minimum=0, maximum=5)
    with pytest.raises(SpecificationError, match=r">= 2"):
        v.integer("n", 1, minimum=2)


def test_one_of_and_seed():
    assert v.one_of("distance", "paper", ("paper", "bands")) == "paper"
    with pytest.raises(SpecificationError, match="must be one of 'paper', 'bands'"):
        v.one_of("distance", "Paper", ("paper", "bands"))
    with pytest.raises(SpecificationError):
        v.one_of("k", "1", (1, 2))  # text never matches a number
    assert v.seed("seed", 0) == 0
    for bad in (-1, True, 1.0):
        with pytest.raises(SpecificationError, match="non-negative integer"):
            v.seed("seed", bad)


def test_the_former_copies_now_agree_on_booleans():
    """The three ``_positive`` copies disagreed: the solver's refused True, the loads' accepted "1.3"."""
    from tubeid.dynamics.solver import choose_step
    from tubeid.uncertainty.loads import force_and_moment

    with pytest.raises(SpecificationError, match="r1 = True"):
        force_and_moment(True, 1.0)
    with pytest.raises(SpecificationError, match="r1 = '1.3'"):
        force_and_moment("1.3", 1.0)
    with pytest.raises(SpecificationError, match="f_max = True"):
        choose_step(True, 1e-3, 3e-3)


def test_is_numeric_dtype_by_kind():
    """np.issubdtype(timedelta64, np.integer) is True: the kind decides, not the type hierarchy."""
    assert np.issubdtype(np.dtype("m8[ms]"), np.integer)
    for dt in ("i1", "u8", "f4", "f8"):
        assert v.is_numeric_dtype(dt)
    for dt in ("m8[ms]", "M8[s]", "?", "U3", "O", "c16"):
        assert not v.is_numeric_dtype(dt)
    assert v.is_numeric_dtype("c16", complex_ok=True) and not v.is_numeric_dtype("m8[s]", complex_ok=True)


@pytest.mark.parametrize("bad", [np.array([True, False]), ["1.0", "2.0"], np.array(["1.0"], dtype=object),
                                 np.arange(3) * np.timedelta64(1, "ms"), np.array(["2024-01-01"], "M8[D]"),
                                 np.array([1 + 1j]), [[1.0, 2.0], [3.0]], [1.0, None], [True, False], [2**2000]])
def test_numeric_array_refuses_what_is_not_real_numbers(bad):
    with pytest.raises(SpecificationError, match=r"^S = .*: must be an array of real numbers"):
        v.numeric_array("S", bad)


def test_numeric_array_complex_finite_and_conversion():
    with pytest.raises(SpecificationError, match=r"^S = 2 NaN or infinite value\(s\), first at index \(1,\): must be finite"):
        v.numeric_array("S", [1.0, np.nan, np.inf])
    assert np.isnan(v.numeric_array("S", [1.0, np.nan], finite=False)[1])
    with warnings.catch_warnings():  # finite values whose sum overflows are finite: no refusal, no warning
        warnings.simplefilter("error")
        assert v.numeric_array("S", np.array([1e308, 1e308])).tolist() == [1e308, 1e308]
    z = v.numeric_array("S", np.array([1 + 1j, 2]), complex_ok=True)
    assert z.dtype == np.complex128
    assert v.numeric_array("S", [1, np.float32(2.5), 1 + 0j], complex_ok=True).dtype == np.complex128
    out = v.numeric_array("x", [1, np.float64(2.5)])  # a list mixing Python and NumPy numbers
    assert out.dtype == np.float64 and out.tolist() == [1.0, 2.5]
    ints = np.arange(3)
    assert v.numeric_array("x", ints) is ints and v.numeric_array("x", ints, dtype=float).dtype == np.float64


def test_boolean_duration_and_byte_count():
    """The checks of configuration values: true/false only; a duration or a size as dask writes them."""
    assert v.boolean("b", np.bool_(False)) is False
    for bad in (0, 1, "no", "true", None):
        with pytest.raises(SpecificationError, match=r"^b = .*: must be true or false$"):
            v.boolean("b", bad)
    assert v.duration("t", "2 minutes") == 120.0 and v.duration("t", 3) == 3.0 and v.duration("t", "500ms") == 0.5
    for bad in ("abc", 0, -1, "nan", math.inf, True, None, [1], 10**400):
        with pytest.raises(SpecificationError, match=r"^t = .*: must be a duration > 0, e\.g\. 10s"):
            v.duration("t", bad)
    assert v.byte_count("n", "2 GiB") == 2.0 * 2**30 and v.byte_count("n", 1000) == 1000.0
    for bad, shown in (("abc", "'abc'"), ("0 B", "'0 B'"), (0, "0"), (-5, "-5"), (True, "True"), (None, "None"),
                       (math.nan, "nan"), (10**400, "<integer of")):
        with pytest.raises(SpecificationError) as err:
            v.byte_count("n", bad)
        assert str(err.value).startswith(f"n = {shown}") and "must be a size in bytes > 0" in str(err.value)


def test_allocation_refuses_beyond_the_machines_memory_share_naming_size_and_purpose():
    total = v._physical_memory()
    assert total is not None and total > 2**28  # this machine says how much memory it has
    v.allocation("x", 1, v.MEMORY_SHARE * total * 0.99, "y")  # within the share: nothing to say
    with pytest.raises(SpecificationError, match=r"^duration = 1000000000\.0: needs [\d.]+ \w+ for the loads: more than "
                                                 r"50% of this machine's memory"):
        v.allocation("duration", 1e9, v.MEMORY_SHARE * total * 1.01, "the loads")


def test_huge_requests_are_refused_before_anything_is_allocated():
    """A record of 1e9 s (TiB of loads) or an output step of 1e-11 s (TiB of series): refused up front,
    naming the field, not a MemoryError from numpy (or the kernel's OOM killer under overcommit)."""
    from tubeid.dynamics import ResponseSettings, simulate, simulate_responses
    from tubeid.mechanics import builtin_spec, reduce
    from tubeid.uncertainty import gaussian_loads
    from tubeid.uncertainty.loads import force_and_moment

    load = force_and_moment(1e-2, 1e-2, x=8.0)
    with pytest.raises(SpecificationError, match=r"^settings\.duration = 1000000000\.0: needs [\d.]+ TiB for the loads of 1 "):
        simulate_responses(reduce(builtin_spec("paper-simplified")), load, [0], seed=1,
                           settings=ResponseSettings(duration=1e9, discard=1.0, segment_seconds=2.0))
    with pytest.raises(SpecificationError, match=r"^duration = 1000000000\.0: needs [\d.]+ TiB for the synthesis of 1 "):
        gaussian_loads(load, 1e9, 2e-3, [np.random.default_rng(1)])
    M, K = np.eye(2), np.diag([1e4, 4e4])
    with pytest.raises(SpecificationError, match=r"^output_dt = 1e-11: needs [\d.]+ \w+ for the series of 1 "):
        simulate(M, 0.01 * K, K, [], np.eye(2)[:, :1], np.eye(2), np.zeros((1001, 1)), 1e-3, output_dt=1e-11,
                 keep="series")


def test_sg_plus_beyond_the_machines_memory_is_refused_before_any_draw():
    from tubeid.uncertainty import sg_plus

    with pytest.raises(SpecificationError, match=r"^n, size = \(1000000, \(\)\): needs [\d.]+ TiB for 1 draw\(s\) of "
                                                 r"1000000 x 1000000 matrices"):
        sg_plus(10**6, 0.5, rng=1)
    with pytest.raises(SpecificationError, match=r"^n, size = \(10, \(1000000000,\)\): needs [\d.]+ TiB for 1000000000 "):
        sg_plus(10, 0.5, size=10**9, rng=1)
    assert sg_plus(3, 0.5, size=2, rng=1).shape == (2, 3, 3)


def test_on_tube_is_the_one_check_of_a_point_on_a_tube():
    """The specification, the FE model's load and sensor matrices and ``simulate_responses`` share one
    check of a point on a tube (``_validation.on_tube``), not a private method of the FE model."""
    import inspect
    from types import SimpleNamespace

    import tubeid.dynamics.response as response
    from tubeid.mechanics.assembly import FEModel

    tube = SimpleNamespace(name="centre", length=16.0)
    assert v.on_tube("x", tube, 16.0 + 5e-10) == 16.0 + 5e-10  # within the node tolerance
    assert v.on_tube("x", tube, 0) == 0.0 and type(v.on_tube("x", tube, 0)) is float
    with pytest.raises(SpecificationError, match=r"^x = 16.5: the point is off tube 'centre' of length 16 m: "
                                                 r"must be in \[0, 16\] m$"):
        v.on_tube("x", tube, 16.5, "the point")
    with pytest.raises(SpecificationError, match=r"^stops\[0\]\.x = -1.0: is off tube 'centre': must be in \[0, 16.0\] m$"):
        v.on_tube("stops[0].x", tube, -1.0)
    with pytest.raises(SpecificationError, match=r"^x = nan: must be a finite number \(m\)$"):
        v.on_tube("x", tube, math.nan, "the point")
    assert not hasattr(FEModel, "_check_on_tube")
    assert "fe._" not in inspect.getsource(response)  # no private member of the FE model


def test_bootstrap_replicates_beyond_the_limit_are_refused_up_front_everywhere(tmp_path):
    """``tubeid report --n-bootstrap 100000000`` ran for minutes, its memory growing, with no word: every
    bootstrap count (the identification functions, ``tubeid report``, diagnose's settings) is checked by
    ``_validation.replicates`` against ``tubeid.io.max-bootstrap`` (default 100 000) before any work."""
    import pathlib
    import re

    import dask.config

    from tubeid.diagnose import DiagnoseSettings
    from tubeid.identification import likelihood_curve
    from tubeid.report import make_report

    assert v.replicates("n_bootstrap", 0) == 0 and v.replicates("n_bootstrap", 100_000) == 100_000
    with pytest.raises(SpecificationError, match=r"^n_bootstrap = 100001: must be at most 100000 \(configuration "
                                                 r"tubeid\.io\.max-bootstrap\): .* 0\.22% there$"):
        v.replicates("n_bootstrap", 100_001)
    with pytest.raises(SpecificationError, match=r"^n_bootstrap = -1: must be an integer >= 0$"):
        v.replicates("n_bootstrap", -1)
    grid = np.linspace(0.0, 1.0, 11)
    J = grid[:, None] + 0.1 * np.random.default_rng(1).standard_normal(50)  # (grid, samples)
    with dask.config.set({"tubeid.io.max-bootstrap": 20}):
        assert v.replicates("n", 20) == 20
        with pytest.raises(SpecificationError, match=r"^n_bootstrap = 21: must be at most 20 "):
            likelihood_curve(J, 0.4, grid, n_bootstrap=21, rng=1)
        assert likelihood_curve(J, 0.4, grid, n_bootstrap=20, rng=1).attrs["n_bootstrap"] == 20
        with pytest.raises(SpecificationError, match=r"^settings\.n_bootstrap = 21: must be at most 20 "):
            DiagnoseSettings(n_bootstrap=21)
        with pytest.raises(SpecificationError, match=r"^n_bootstrap = 21: must be at most 20 "):
            make_report(tmp_path, n_bootstrap=21)
    # every module that takes a bootstrap count checks it with the one shared rule, none with its own
    root = pathlib.Path(v.__file__).parent
    for path in root.rglob("*.py"):
        text = path.read_text()
        assert not re.search(r"integer\([^)]*n_bootstrap", text), path
        assert not re.search(r"SpecificationError\(\s*\"n_bootstrap\"", text), path


def test_worker_counts_beyond_four_per_usable_core_are_refused_before_anything_starts(tmp_path, monkeypatch):
    """``tubeid run --workers 1000000`` (or the configuration's runner.workers) asked the embedded cluster
    for a million processes; ``bench-runner --workers`` had the same bound on its own. One rule now,
    ``_validation.worker_count``: at most WORKERS_PER_CORE per core this process may use."""
    import pathlib

    import dask.config

    import tubeid.runner.execute as execute
    from tubeid import config

    monkeypatch.setattr(v, "usable_cores", lambda: 3)
    assert v.worker_count("workers", 12) == 12 and v.worker_count("workers", 0) == 0
    with pytest.raises(SpecificationError, match=r"^workers = 13: must be at most 12: 4 worker processes per core "
                                                 r"this process may use \(3 here\)"):
        v.worker_count("workers", 13)
    with pytest.raises(SpecificationError, match=r"^workers = -1: must be an integer >= 0$"):
        v.worker_count("workers", -1)

    def never(*args, **kwargs):  # a million processes must never be asked for, even when this test fails
        raise AssertionError("the cluster was started")

    monkeypatch.setattr(execute, "_client", never)
    study = pathlib.Path(v.__file__).parents[1] / "studies" / "pi.py"
    with pytest.raises(SpecificationError, match=r"^workers = 1000000: must be at most 12"):
        execute.run(study, tmp_path / "pi.zarr", workers=10**6, quiet=True)
    with dask.config.set({"tubeid.runner.workers": 10**6}):
        with pytest.raises(SpecificationError, match=r"runner.workers .*1000000.*must be at most 12"):
            config.check()
    assert not (tmp_path / "pi.zarr").exists()
