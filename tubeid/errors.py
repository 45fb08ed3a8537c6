"""The exception types tubeid raises for bad input and for a missing optional dependency.

Every ``SpecificationError`` message names the field, the value and the rule, e.g.
``tubes[1].length = -2.0 m: must be > 0``. A ``MissingDependencyError`` names the feature, the
package it needs and the extra that installs it, e.g.
``tubeid report needs matplotlib: pip install "tubeid[plot]"``.
"""

from __future__ import annotations

from typing import Any

__all__ = ["SpecificationError", "MissingDependencyError", "Described"]


class SpecificationError(ValueError):
    """Bad input: a specification, a parameter, a data file or a store that breaks a rule.

    Parameters
    ----------
    field : str
        Where the bad value sits, e.g. ``"tubes[1].length"`` or ``"--set"``.
    value : object
        The bad value (shown with ``repr``; wrap a description in ``Described`` to show it as is).
    rule : str
        The rule it breaks, e.g. ``"must be > 0"``.
    """

    def __init__(self, field: str, value: Any, rule: str) -> None:
        self.field, self.value, self.rule = field, value, rule
        super().__init__(f"{field} = {value!r}: {rule}")


class MissingDependencyError(ImportError):
    """A feature needs a package of one of tubeid's optional extras, and it is not installed.

    An ``ImportError`` (code that catches those keeps working) whose message says what to install.

    Parameters
    ----------
    feature : str
        What needs the package, as a user would name it, e.g. ``"tubeid report"``.
    package : str
        The distribution to install, e.g. ``"matplotlib"``.
    extra : str
        tubeid's extra that installs it, e.g. ``"plot"`` (``pip install "tubeid[plot]"``).
    """

    def __init__(self, feature: str, package: str, extra: str) -> None:
        self.feature, self.package, self.extra = feature, package, extra
        super().__init__(f'{feature} needs {package}: pip install "tubeid[{extra}]"', name=package)


class Described(str):
    """A description of a bad value (e.g. "array of shape (3, 2)"), shown without quotes in messages.

    Parameters
    ----------
    object : str
        The description.
    """

    def __repr__(self) -> str:
        return str(self)
