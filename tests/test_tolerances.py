"""Guard: every tolerance comparison in the tests states its absolute tolerance.

``pytest.approx(x, rel=r)`` also accepts any value within 1e-12 of ``x``, and ``numpy.isclose`` /
``numpy.allclose`` within 1e-8: both swallow every m²-, N²- or J-scale quantity of this project
(PSD levels 1e-16 m²/Hz, J ~ 3e-10), so such a check passes whatever the value. Each call must
therefore pass ``abs=`` (``atol=`` for numpy), usually ``abs=0`` beside a stated relative
tolerance. ``numpy.testing.assert_allclose`` defaults to ``atol=0`` and is not concerned.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
#: Function name -> keyword that must be given.
NEEDS = {"approx": "abs", "isclose": "atol", "allclose": "atol"}


def _callee(node: ast.Call) -> str | None:
    f = node.func
    if isinstance(f, ast.Attribute):
        return f.attr
    if isinstance(f, ast.Name):
        return f.id
    return None


def unstated_tolerances(source: str, filename: str = "<test>") -> list[str]:
    """``file:line: call`` for every approx/isclose/allclose call without its absolute tolerance."""
    bad = []
    for node in ast.walk(ast.parse(source, filename)):
        if isinstance(node, ast.Call):
            name = _callee(node)
            if name == "approx" or (name in ("isclose", "allclose") and _is_numpy(node)):
                keywords = {k.arg for k in node.keywords}
                if NEEDS[name] not in keywords and None not in keywords:  # None: **kwargs, cannot tell
                    bad.append(f"{filename}:{node.lineno}: {ast.unparse(node)[:100]}")
    return bad


def _is_numpy(node: ast.Call) -> bool:
    f = node.func
    return isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name) and f.value.id in ("np", "numpy")


def test_every_tolerance_comparison_states_its_absolute_tolerance():
    bad = []
    for path in sorted(TESTS.glob("*.py")):
        bad += unstated_tolerances(path.read_text(encoding="utf-8"), path.name)
    assert not bad, ("pytest.approx without abs= (or numpy isclose/allclose without atol=) passes any "
                     "value within 1e-12 (1e-8) of the expected one; state it, e.g. abs=0:\n" + "\n".join(bad))


@pytest.mark.parametrize("line, flagged", [
    ("assert x == pytest.approx(1e-14, rel=0.1)", True),
    ("assert x == approx(3.0)", True),
    ("assert np.allclose(a, b, rtol=1e-3)", True),
    ("assert numpy.isclose(a, b)", True),
    ("assert x == pytest.approx(1e-14, rel=0.1, abs=0)", False),
    ("assert np.isclose(a, b, rtol=1e-3, atol=0)", False),
    ("assert torch.allclose(a, b)", False),  # not numpy: not concerned
    ("assert math.isclose(a, b, rel_tol=1e-9)", False),  # abs_tol defaults to 0
    ("np.testing.assert_allclose(a, b, rtol=1e-9)", False),
])
def test_the_guard_flags_what_it_should(line, flagged):
    assert bool(unstated_tolerances(line)) is flagged


def test_the_reason_for_the_guard():
    """The default absolute tolerance really does accept a value twice too large at PSD scale."""
    assert 2e-14 == pytest.approx(1e-14, rel=0.1, abs=1e-12)  # abs=1e-12 is what approx adds unasked
    assert 2e-14 != pytest.approx(1e-14, rel=0.1, abs=0)
