"""The one exception type tubeid raises for bad input.

Every message names the field, the value and the rule, e.g.
``tubes[1].length = -2.0 m: must be > 0``. Long values are shortened in the message (at most
:data:`VALUE_CHARS` characters, nested containers to a few items and levels, strings and huge
integers with their size stated; fields and rules, which may embed user text, likewise); the
exception keeps the field, value and rule themselves in ``.field``, ``.value`` and ``.rule``.
"""

import reprlib

__all__ = ["SpecificationError", "Described", "shown", "VALUE_CHARS"]

#: Longest value shown in a message.
VALUE_CHARS = 240


class _Short(reprlib.Repr):
    """A bounded ``repr``: never builds the whole text of a huge value."""

    def __init__(self):
        super().__init__()  # Python 3.11 takes no keyword arguments here
        self.maxlevel = 3
        self.maxtuple = self.maxlist = self.maxarray = self.maxdict = self.maxset = self.maxfrozenset = 8
        self.maxdeque = 8
        self.maxstring = self.maxlong = self.maxother = VALUE_CHARS

    def repr_str(self, x, level):
        if len(x) <= VALUE_CHARS - 40:
            return repr(x)
        return f"{x[:120]!r}…{x[-60:]!r} ({len(x)} characters)"  # head and tail: a path keeps its name

    def repr_Described(self, x, level):
        return x if len(x) <= VALUE_CHARS else f"{x[:120]}…{x[-60:]} ({len(x)} characters)"

    def repr_int(self, x, level):
        if x.bit_length() > 128:  # repr of a huge int is slow, and refused beyond 4300 digits
            return f"<integer of {x.bit_length()} bits>"
        return repr(x)


def shown(value) -> str:
    """``value`` as a message shows it: its ``repr``, shortened to at most :data:`VALUE_CHARS` characters."""
    try:
        text = _Short().repr(value)
    except Exception:  # noqa: BLE001 - a value whose repr fails must not hide the error
        text = f"<{type(value).__name__}>"
    return text if len(text) <= VALUE_CHARS else f"{text[:VALUE_CHARS - 1]}…"


def _clip(text: str, chars: int) -> str:
    """A field or rule that may embed user text (a key, a sensor name), kept to ``chars``."""
    text = str(text)
    return text if len(text) <= chars else f"{text[:chars - 80]}…{text[-60:]} ({len(text)} characters)"


class SpecificationError(ValueError):
    """Bad input: a specification, a parameter, a data file or a store that breaks a rule."""

    def __init__(self, field: str, value, rule: str):
        self.field, self.value, self.rule = field, value, rule
        super().__init__(f"{_clip(field, VALUE_CHARS)} = {shown(value)}: {_clip(rule, 4 * VALUE_CHARS)}")


class Described(str):
    """A description of a bad value (e.g. "array of shape (3, 2)"), shown without quotes in messages."""

    def __repr__(self):
        return str(self)
