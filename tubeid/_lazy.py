"""Lazy package namespaces (PEP 562): a name is imported from its module on first access.

A package's ``__init__.py`` lists its exports once, as the imports of an ``if TYPE_CHECKING:``
block (which type checkers and IDEs read as ordinary imports), and ends with::

    __getattr__, __dir__ = attach(__name__, __file__)

``attach`` reads that block from the source file and resolves ``package.NAME`` by importing the
named module when ``NAME`` is first used; a sub-module (``package.runner``) is imported the same
way. So ``import tubeid`` costs a few milliseconds and ``tubeid --help`` imports no numerical
library, while ``from tubeid import Study`` and ``tubeid.Study`` still work.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import os
import pkgutil
import sys
import types
from collections.abc import Callable
from typing import Any

__all__ = ["attach", "lazy_table"]


def lazy_table(path: str) -> dict[str, tuple[str, str]]:
    """The lazy exports of a package: ``{name: (module, attribute)}`` from its ``TYPE_CHECKING`` block.

    Parameters
    ----------
    path : str
        The package's ``__init__.py``.

    Returns
    -------
    dict of str to (str, str)
        For each name bound by an ``from MODULE import ATTR [as NAME]`` inside the module's
        top-level ``if TYPE_CHECKING:`` block, the absolute module name and the attribute.
    """
    with open(path, encoding="utf-8") as fh:
        tree = ast.parse(fh.read(), filename=path)
    table: dict[str, tuple[str, str]] = {}
    for node in tree.body:
        if isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING":
            for stmt in node.body:
                if isinstance(stmt, ast.ImportFrom) and stmt.level == 0 and stmt.module:
                    for alias in stmt.names:
                        table[alias.asname or alias.name] = (stmt.module, alias.name)
    return table


def attach(package: str, path: str) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """Module-level ``__getattr__`` and ``__dir__`` that import ``package``'s exports on first use.

    Parameters
    ----------
    package : str
        The package's ``__name__``.
    path : str
        The package's ``__file__``; its ``if TYPE_CHECKING:`` block lists the exports
        (see ``lazy_table``).

    Returns
    -------
    __getattr__ : callable
        ``__getattr__(name)``: the export ``name`` (imported from its module and cached in the
        package's namespace), or the sub-module ``package.name``; ``AttributeError`` otherwise.
    __dir__ : callable
        ``__dir__()``: the public names: ``__all__``, every lazy export and the sub-modules
        imported so far (not the helpers the ``__init__`` itself uses).
    """
    table = lazy_table(path)
    # A name that is also a sub-module's (``tubeid.measured.diagnose``: the function and its module):
    # importing the sub-module sets that package attribute to the module, after which __getattr__
    # would never be asked for the function. The package keeps the exported object instead, as an
    # eager ``from .diagnose import diagnose`` did (the sub-module stays in ``sys.modules``).
    shadowed = table.keys() & {m.name for m in pkgutil.iter_modules([os.path.dirname(path)])}
    if shadowed:
        class _Package(types.ModuleType):
            def __setattr__(self, name: str, value: Any) -> None:
                if name in shadowed and getattr(value, "__name__", None) == f"{package}.{name}":
                    return
                super().__setattr__(name, value)

        sys.modules[package].__class__ = _Package

    def __getattr__(name: str) -> Any:
        namespace = importlib.import_module(package).__dict__
        if name in table:
            module, attr = table[name]
            value = getattr(importlib.import_module(module), attr)
            namespace[name] = value
            return value
        if not name.startswith("__") and importlib.util.find_spec(f"{package}.{name}") is not None:
            return importlib.import_module(f"{package}.{name}")
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__() -> list[str]:
        namespace = importlib.import_module(package).__dict__
        modules = {k for k, v in namespace.items()
                   if not k.startswith("_") and isinstance(v, types.ModuleType) and v.__name__ == f"{package}.{k}"}
        return sorted(set(namespace.get("__all__", ())) | set(table) | modules)

    return __getattr__, __dir__
