"""Every public callable (the ``__all__`` of ``tubeid`` and of each sub-package) is typed and documented.

Checked for each function, each class (its constructor) and each public method a class defines:
every parameter and the return value are annotated; the docstring has a numpydoc ``Parameters``
section naming exactly the parameters of the signature (when there are any) and a ``Returns``
(or ``Yields``) section unless it returns ``None``. ``py.typed`` ships with the package.
"""

import dataclasses
import importlib
import inspect
import pathlib
import re

import pytest

import tubeid

PACKAGES = ["tubeid", "tubeid.mechanics", "tubeid.uncertainty", "tubeid.dynamics", "tubeid.identification",
            "tubeid.measured", "tubeid.runner", "tubeid.diagnose"]

# Names still exempt: their modules are being rewritten by other engineers right now (the solver,
# the runner, the measured-data readers and diagnosis, the load identification). The lead empties
# this list once those rewrites are merged and the names meet the rule.
EXEMPT: set[str] = set()  # names still being rewritten; it may only shrink (empty now)

_SECTION = re.compile(r"^(\s*)(Parameters|Returns|Yields|Raises|Attributes|Notes|Examples|See Also|References|"
                      r"Warns|Other Parameters|Methods)\s*\n\1-{3,}\s*$", re.M)


def sections(doc: str) -> dict[str, str]:
    """The numpydoc sections of a docstring: ``{title: body}``."""
    doc = inspect.cleandoc(doc or "")
    found = list(_SECTION.finditer(doc))
    return {m.group(2): doc[m.end():found[i + 1].start() if i + 1 < len(found) else len(doc)]
            for i, m in enumerate(found)}


def documented_names(body: str) -> set[str]:
    """Parameter names of a ``Parameters`` section: ``name : type`` or ``a, b : type`` lines at its margin."""
    names = set()
    for line in body.splitlines():
        if line.strip() and not line.startswith((" ", "\t")):
            head = line.split(" : ")[0] if " : " in line else line
            names.update(n.strip().lstrip("*") for n in head.split(","))
    return {n for n in names if n}


def _own_methods(cls) -> list[tuple[str, object]]:
    out = []
    for name, member in vars(cls).items():
        if name.startswith("_") or not (inspect.isfunction(member) or isinstance(member, (classmethod, staticmethod))):
            continue
        out.append((name, getattr(cls, name)))
    return out


def problems(qualname: str, fn, doc: str | None, *, skip_first: bool = False, constructor: bool = False) -> list[str]:
    """What ``fn`` (a function, or a class's ``__init__``) lacks: annotations and docstring sections."""
    out = []
    sig = inspect.signature(fn)
    params = [p for p in sig.parameters.values()][1 if skip_first else 0:]
    for p in params:
        if p.annotation is inspect.Parameter.empty:
            out.append(f"{qualname}: parameter {p.name!r} has no annotation")
    returns_none = sig.return_annotation in (None, "None")
    if not constructor and sig.return_annotation is inspect.Signature.empty:
        out.append(f"{qualname}: no return annotation")
    s = sections(doc or "")
    if params:
        if "Parameters" not in s:
            out.append(f"{qualname}: no Parameters section")
        else:
            want = {p.name for p in params}
            got = documented_names(s["Parameters"])
            if want - got:
                out.append(f"{qualname}: parameters not documented: {sorted(want - got)}")
            if got - want:
                out.append(f"{qualname}: documented but not parameters: {sorted(got - want)}")
    if not constructor and not returns_none and not ({"Returns", "Yields"} & set(s)):
        out.append(f"{qualname}: no Returns section")
    return out


def check(qualname: str, obj) -> list[str]:
    if inspect.isclass(obj):
        out = []
        if dataclasses.is_dataclass(obj) or "__init__" in vars(obj) or any(
                "__init__" in vars(b) for b in obj.__mro__[1:] if b.__module__.startswith("tubeid")):
            init = obj.__init__
            if not (dataclasses.is_dataclass(obj) and not [f for f in dataclasses.fields(obj) if f.init]):
                out += problems(qualname, init, obj.__doc__, skip_first=True, constructor=True)
        for name, meth in _own_methods(obj):
            bound = isinstance(inspect.getattr_static(obj, name), (classmethod,)) or inspect.ismethod(meth)
            static = isinstance(inspect.getattr_static(obj, name), staticmethod)
            out += problems(f"{qualname}.{name}", meth, meth.__doc__, skip_first=not (bound or static))
        return out
    if callable(obj):
        return problems(qualname, obj, obj.__doc__)
    return []


def public_callables():
    for package in PACKAGES:
        mod = importlib.import_module(package)
        for name in mod.__all__:
            obj = getattr(mod, name)
            if callable(obj):
                yield f"{package}.{name}", obj


def test_every_public_callable_is_typed_and_documented():
    found = {q: check(q, obj) for q, obj in public_callables() if q not in EXEMPT}
    bad = [p for ps in found.values() for p in ps]
    assert not bad, f"{len(bad)} problems:\n" + "\n".join(bad)


def test_exempt_names_exist_and_are_not_already_compliant():
    """The exemption list only shrinks: a name that now meets the rule (or no longer exists) must leave it."""
    public = dict(public_callables())
    assert EXEMPT <= set(public), f"unknown exempt names: {sorted(EXEMPT - set(public))}"
    compliant = sorted(q for q in EXEMPT if not check(q, public[q]))
    assert not compliant, f"exempt but already compliant, remove from EXEMPT: {compliant}"


@pytest.mark.parametrize("doc, expected", [
    ("Summary.\n\nParameters\n----------\nx, y : float\n    Coordinates.\n*args : int\n    More.\n\n"
     "Returns\n-------\nfloat\n    The sum.\n", ({"x", "y", "args"}, {"Parameters", "Returns"})),
    ("No sections here; Parameters are mentioned in passing.", (set(), set())),
])
def test_docstring_section_parser(doc, expected):
    s = sections(doc)
    assert (documented_names(s.get("Parameters", "")), set(s)) == expected


def test_checker_catches_what_it_claims():
    def missing(a, b: int):
        """Summary.

        Parameters
        ----------
        b : int
            B.
        """
        return a

    def fine(a: int, *, b: float = 1.0) -> float:
        """Summary.

        Parameters
        ----------
        a : int
            A.
        b : float
            B.

        Returns
        -------
        float
        """
        return a * b

    msgs = problems("missing", missing, missing.__doc__)
    assert any("'a' has no annotation" in m for m in msgs)
    assert any("no return annotation" in m for m in msgs)
    assert any("not documented: ['a']" in m for m in msgs)
    assert any("no Returns section" in m for m in msgs)
    assert problems("fine", fine, fine.__doc__) == []


def test_py_typed_ships_with_the_package():
    assert (pathlib.Path(tubeid.__file__).parent / "py.typed").is_file()
    import tomllib

    pyproject = tomllib.loads((pathlib.Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())
    assert "py.typed" in pyproject["tool"]["setuptools"]["package-data"]["tubeid"]
