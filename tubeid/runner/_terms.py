"""The words the runner's refusals use for a store and for the options that act on it.

A refusal about a store names a field (the store) and often advises an option: write elsewhere, write a
new store beside it, or what rebuilds its bookkeeping. ``tubeid run`` calls these ``store``,
``--store``, ``--new-store`` and ``--no-verify``; a command that drives the runner under options of its
own (``tubeid diagnose``: its store is ``--out``'s ``diagnose.zarr``, with no ``--store``, no
``--new-store``) says its words with :func:`speaking`, and every refusal raised meanwhile in that
thread (or task) is worded in them from the start. No runner message spells one of these options
itself (``tests/test_diagnose.py`` checks the source); ``--overwrite``, ``--workers`` and
``--scheduler``, which both commands have with the same meaning, are spelled as they are.
Imports nothing heavy (``tubeid status`` needs no zarr).
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses

__all__ = ["Terms", "RUN", "current", "speaking"]


@dataclasses.dataclass(frozen=True)
class Terms:
    """How refusals name a store and the options acting on it, in the words of the user's command.

    Every field is required: a command speaking its own terms must say each of them.

    Parameters
    ----------
    store : str
        The field a refusal about the store names, e.g. ``"store"``.
    option : str
        The option that gives the store, e.g. ``"--store"``.
    elsewhere : str
        Advice: write to another store, e.g. ``"choose another --store"``.
    beside : str
        Advice: keep this store and write a new one, e.g. ``"use --new-store to write a new store beside it"``;
        a command without such an option says ``elsewhere`` again.
    rebuild : str
        What, run again, rebuilds a store's lost bookkeeping by verifying its blocks, e.g.
        ``"`tubeid run` without --no-verify"``.
    changed : str
        What the user changes that makes a store another one, e.g. ``"a changed study definition"``.
    """

    store: str
    option: str
    elsewhere: str
    beside: str
    rebuild: str
    changed: str

    @property
    def elsewhere_or_beside(self) -> str:
        """Both pieces of advice, once if they are the same (a command without a ``--new-store``)."""
        return self.elsewhere if self.beside == self.elsewhere else f"{self.elsewhere}, or {self.beside}"


#: ``tubeid run``'s own words (the default)
RUN = Terms(store="store", option="--store", elsewhere="choose another --store", beside="use --new-store to write a new store beside it",
            rebuild="`tubeid run` without --no-verify", changed="a changed study definition")

_CURRENT: contextvars.ContextVar[Terms] = contextvars.ContextVar("tubeid_runner_terms", default=RUN)


def current() -> Terms:
    """The terms in force: :data:`RUN` unless a caller is :func:`speaking` others."""
    return _CURRENT.get()


@contextlib.contextmanager
def speaking(terms: Terms):
    """Word the runner's refusals raised within the block (this thread or task) in ``terms``."""
    if not isinstance(terms, Terms):
        raise TypeError(f"terms must be a Terms, not {type(terms).__name__}")
    token = _CURRENT.set(terms)
    try:
        yield terms
    finally:
        _CURRENT.reset(token)
