"""The exception types tubeid raises for bad input and for a missing optional dependency.

Every ``SpecificationError`` message names the field, the value and the rule, e.g.
``tubes[1].length = -2.0 m: must be > 0``. Long values are shortened in the message (at most
:data:`VALUE_CHARS` characters, nested containers to a few items and levels, strings and huge
integers with their size stated; fields and rules, which may embed user text, likewise); the
exception keeps the field, value and rule themselves in ``.field``, ``.value`` and ``.rule``.
A ``MissingDependencyError`` names the feature, the package it needs and the extra that installs
it, e.g. ``tubeid report needs matplotlib: pip install "tubeid[plot]"``.
"""

from __future__ import annotations

import pickle
import reprlib
import sys
from typing import Any

__all__ = ["BlockFailed", "SpecificationError", "MissingDependencyError", "Described", "shown", "VALUE_CHARS"]

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

    def repr1(self, x, level):
        return super().repr1(_plain_scalar(x), level)  # also for the items of containers


def _plain_scalar(x):
    """A NumPy scalar as the plain value it holds, so that a message shows ``0.3``, ``128`` or
    ``'c02'``, not ``np.float64(0.3)``, ``np.int64(128)`` or ``np.str_('c02')`` (NumPy ≥ 2 reprs);
    anything else unchanged. NumPy is not imported here: a value can only be its scalar once it is."""
    np = sys.modules.get("numpy")
    if np is None or not isinstance(x, np.generic):
        return x
    if isinstance(x, (np.floating, np.complexfloating)) and x.dtype not in (np.float64, np.complex128):
        return Described(str(x))  # float32 0.3 as "0.3" (its shortest digits), not 0.30000001192092896
    if isinstance(x, (np.bool_, np.number, np.str_, np.bytes_)):
        return x.item()
    return x


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
        super().__init__(f"{_clip(field, VALUE_CHARS)} = {shown(value)}: {_clip(rule, 4 * VALUE_CHARS)}")

    def __reduce__(self):
        # pickled with its field, value and rule (it crosses processes: a task's refusal on a worker); a
        # value that cannot be pickled travels as its description, so the refusal itself always does
        value = self.value
        try:
            pickle.dumps(value)
        except Exception:  # noqa: BLE001 - any failure to pickle the value
            value = Described(shown(value))
        return type(self), (self.field, value, self.rule)


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

    def __reduce__(self):
        return type(self), (self.feature, self.package, self.extra)


class BlockFailed(RuntimeError):
    """A block's task raised: names the block, its coordinates and the cause (chained as ``__cause__``).

    The blocks finished before it are in the store; rerunning the same command resumes (the same
    study definition: a changed one is refused on that store).

    Parameters
    ----------
    where : str
        The study (or pipeline stage) and the block, e.g. ``"study 'bad', block (1,) (r = 2 … 3)"``.
    cause : str
        The task's exception as ``"Type: message"``.
    changed : str, optional
        What to do if what the store was made from changes instead, in the user's command's options
        (the runner says it: for ``tubeid run``, "for a changed study definition: use --new-store ...").
    """

    def __init__(self, where: str, cause: str, changed: str = "") -> None:
        self.where, self.cause, self.changed = where, cause, changed
        super().__init__(f"{where} failed: {_clip(cause, 4 * VALUE_CHARS)}; the blocks finished so far are stored: "
                         "once the cause is fixed, the same command resumes" + (f" ({changed})" if changed else ""))

    def __reduce__(self):
        return type(self), (self.where, self.cause, self.changed)


class Described(str):
    """A description of a bad value (e.g. "array of shape (3, 2)"), shown without quotes in messages.

    Parameters
    ----------
    object : str
        The description.
    """

    def __repr__(self) -> str:
        return str(self)
