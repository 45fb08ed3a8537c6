"""The one exception type tubeid raises for bad input.

Every message names the field, the value and the rule, e.g.
``tubes[1].length = -2.0 m: must be > 0``.
"""

__all__ = ["SpecificationError", "Described"]


class SpecificationError(ValueError):
    """Bad input: a specification, a parameter, a data file or a store that breaks a rule."""

    def __init__(self, field: str, value, rule: str):
        self.field, self.value, self.rule = field, value, rule
        super().__init__(f"{field} = {value!r}: {rule}")


class Described(str):
    """A description of a bad value (e.g. "array of shape (3, 2)"), shown without quotes in messages."""

    def __repr__(self):
        return str(self)
