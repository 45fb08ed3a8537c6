"""The package's shared argument checks (``tubeid._validation``): one wording, no booleans or text as numbers."""

import math

import numpy as np
import pytest

from tubeid import _validation as v
from tubeid.errors import SpecificationError


@pytest.mark.parametrize("bad", [True, False, np.bool_(True), "1.0", None, [1.0], 1 + 0j, math.nan, math.inf, -math.inf])
def test_real_refuses_what_is_not_a_finite_number(bad):
    with pytest.raises(SpecificationError, match=r"^x = .*: must be a finite number"):
        v.real("x", bad)


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
