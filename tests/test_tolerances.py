"""Guard: every tolerance comparison in the tests states its absolute tolerance.

pytest's ``approx(x, rel=r)`` also accepts any value within 1e-12 of ``x``, and ``numpy.isclose`` /
``numpy.allclose`` within 1e-8: both swallow every m²-, N²- or J-scale quantity of this project
(PSD levels 1e-16 m²/Hz, J ~ 3e-10), so such a check passes whatever the value. Each call must
therefore pass ``abs=`` (``atol=`` for numpy), usually ``abs=0`` beside a stated relative
tolerance; ``abs=None`` (approx's spelling of its default) is refused, and so is a call whose
tolerance cannot be read from the source (``**kwargs``, ``*args``) or a use of the function other
than a direct call (e.g. ``functools.partial(pytest.approx, ...)``). The functions are recognised
under any name they are imported or assigned as (``from pytest import approx as ap``,
``import numpy as xp``, ``close = np.isclose``). ``numpy.testing.assert_allclose`` defaults to
``atol=0`` and is not concerned.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
#: Function -> (keyword that must be given, its position among the positional arguments).
NEEDS = {"approx": ("abs", 2), "isclose": ("atol", 3), "allclose": ("atol", 3)}


class _Names:
    """What the names of one module stand for: aliases of pytest.approx and of numpy's isclose/allclose.

    ``approx`` under its own name and any ``<something>.approx`` count as pytest's (conservative);
    ``np`` and ``numpy`` count as numpy even when the snippet does not import it.
    """

    def __init__(self, tree: ast.AST):
        self.functions: dict[str, str] = {"approx": "approx"}  # local name -> approx / isclose / allclose
        self.numpy: set[str] = {"np", "numpy"}
        self.alias_sources: set[int] = set()  # ids of the nodes that are the source of an alias assignment
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for a in node.names:
                    if a.name == "numpy":
                        self.numpy.add(a.asname or "numpy")
            elif isinstance(node, ast.ImportFrom) and node.module in ("pytest", "numpy"):
                for a in node.names:
                    if (node.module, a.name) in (("pytest", "approx"), ("numpy", "isclose"), ("numpy", "allclose")):
                        self.functions[a.asname or a.name] = a.name
        assigns = [n for n in ast.walk(tree) if isinstance(n, (ast.Assign, ast.AnnAssign)) and n.value is not None]
        changed = True
        while changed:  # `a = pytest.approx; b = a` : follow chains of plain assignments
            changed = False
            for node in assigns:
                kind = self.kind(node.value)
                if kind is None:
                    continue
                self.alias_sources.add(id(node.value))
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                for t in targets:
                    if isinstance(t, ast.Name) and self.functions.get(t.id) != kind:
                        self.functions[t.id] = kind
                        changed = True

    def kind(self, expr: ast.AST) -> str | None:
        """``approx``, ``isclose``, ``allclose`` or None: what the expression names."""
        if isinstance(expr, ast.Name):
            return self.functions.get(expr.id)
        if isinstance(expr, ast.Attribute):
            if expr.attr == "approx":
                return "approx"
            if expr.attr in ("isclose", "allclose") and isinstance(expr.value, ast.Name) and expr.value.id in self.numpy:
                return expr.attr
        return None


def _tolerance_problem(call: ast.Call, kind: str) -> str | None:
    """Why this call's absolute tolerance is not stated (None: it is, and it is not None)."""
    keyword, position = NEEDS[kind]
    given = [k.value for k in call.keywords if k.arg == keyword]
    if any(isinstance(a, ast.Starred) for a in call.args[:position + 1]):
        if not given:
            return f"*args: {keyword}= cannot be read; give it as a keyword"
    elif len(call.args) > position:
        given.append(call.args[position])
    for k in call.keywords:
        if k.arg is None:  # **mapping
            if isinstance(k.value, ast.Dict) and all(isinstance(key, ast.Constant) for key in k.value.keys):
                given += [v for key, v in zip(k.value.keys, k.value.values) if key.value == keyword]
            elif not given:
                return f"**{ast.unparse(k.value)}: {keyword}= cannot be read; give it as a keyword"
    if not given:
        return f"no {keyword}="
    if any(isinstance(v, ast.Constant) and v.value is None for v in given):
        return f"{keyword}=None is the default tolerance"
    return None


def unstated_tolerances(source: str, filename: str = "<test>") -> list[str]:
    """``file:line: why: call`` for every approx/isclose/allclose call without its absolute tolerance,
    and every use of one of them that is not a direct call."""
    tree = ast.parse(source, filename)
    names = _Names(tree)
    callees = {id(n.func) for n in ast.walk(tree) if isinstance(n, ast.Call)}
    bad = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and (kind := names.kind(node.func)):
            if why := _tolerance_problem(node, kind):
                bad.append(f"{filename}:{node.lineno}: {why}: {ast.unparse(node)[:100]}")
        elif (isinstance(node, (ast.Name, ast.Attribute)) and isinstance(node.ctx, ast.Load) and names.kind(node)
              and id(node) not in callees and id(node) not in names.alias_sources):
            bad.append(f"{filename}:{node.lineno}: {ast.unparse(node)} used other than as a direct call "
                       "(its tolerance cannot be checked)")
    return bad


def test_every_tolerance_comparison_states_its_absolute_tolerance():
    bad = []
    for path in sorted(TESTS.rglob("*.py")):
        bad += unstated_tolerances(path.read_text(encoding="utf-8"), str(path.relative_to(TESTS)))
    assert not bad, ("pytest.approx without abs= (or numpy isclose/allclose without atol=) passes any "
                     "value within 1e-12 (1e-8) of the expected one; state it, e.g. abs=0:\n" + "\n".join(bad))


#: The call the examples below are about, spelled so that a plain text search for unguarded uses
#: (the project's before-stop hook) does not take these examples for real ones.
APPROX = "pytest" + ".approx"


@pytest.mark.parametrize("source, flagged", [
    (f"assert x == {APPROX}(1e-14, rel=0.1)", True),
    ("assert x == approx(3.0)", True),
    ("assert np.allclose(a, b, rtol=1e-3)", True),
    ("assert numpy.isclose(a, b)", True),
    (f"assert x == {APPROX}(1e-14, rel=0.1, abs=None)", True),   # None: the 1e-12 default again
    (f"assert x == {APPROX}(1e-14, 0.1, None)", True),           # the same, positionally
    ("assert np.isclose(a, b, 1e-3, None)", True),
    ("from pytest import approx as ap\nassert x == ap(1e-14, rel=0.1)", True),
    ("import pytest as pt\nassert x == pt.approx(1e-14, rel=0.1)", True),
    ("close = pytest.approx\nsame = close\nassert x == same(1e-14, rel=0.1)", True),
    ("import numpy as xp\nassert xp.allclose(a, b)", True),
    ("from numpy import isclose as near\nassert near(a, b, rtol=1e-3)", True),
    (f"assert x == {APPROX}(1e-14, **options)", True),           # cannot be read
    (f"assert x == {APPROX}(1e-14, **{{'rel': 0.1}})", True),
    (f"assert x == {APPROX}(1e-14, *tolerances)", True),
    ("check = functools.partial(pytest.approx, rel=0.1)", True),     # not a direct call
    (f"assert x == {APPROX}(1e-14, rel=0.1, abs=0)", False),
    (f"assert x == {APPROX}(1e-14, 0.1, 0)", False),
    (f"assert x == {APPROX}(1e-14, **{{'rel': 0.1, 'abs': 0}})", False),
    (f"assert x == {APPROX}(1e-14, *tolerances, abs=0)", False),
    ("from pytest import approx as ap\nassert x == ap(1e-14, rel=0.1, abs=0)", False),
    ("assert np.isclose(a, b, rtol=1e-3, atol=0)", False),
    ("assert torch.allclose(a, b)", False),  # not numpy: not concerned
    ("assert math.isclose(a, b, rel_tol=1e-9)", False),  # abs_tol defaults to 0
    ("from math import isclose\nassert isclose(a, b, rel_tol=1e-9)", False),
    ("np.testing.assert_allclose(a, b, rtol=1e-9)", False),
])
def test_the_guard_flags_what_it_should(source, flagged):
    assert bool(unstated_tolerances(source)) is flagged, unstated_tolerances(source)


def test_the_reason_for_the_guard():
    """The default absolute tolerance really does accept a value twice too large at PSD scale."""
    assert 2e-14 == pytest.approx(1e-14, rel=0.1, abs=1e-12)  # abs=1e-12 is what approx adds unasked
    assert 2e-14 != pytest.approx(1e-14, rel=0.1, abs=0)
