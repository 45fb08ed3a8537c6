"""Reproducible random streams: one generator per (study seed, task identity).

Every random draw in tubeid comes from ``rng_for(seed, *key)``. The key is the identity of
what is drawn (e.g. ``("stiffness", realisation)``), never a block index or a worker, so that
results are bit-identical whatever the number of workers, the order, retries or resumes.
"""

from __future__ import annotations

import hashlib

import numpy as np

from tubeid._validation import seed as _checked_seed

#: a part of a random-stream key: an int, a float or a string (anything with a stable ``repr``; a NumPy
#: scalar counts as the equal Python scalar)
KeyPart = int | float | str

__all__ = ["rng_for", "key_to_ints"]


def key_to_ints(*key: KeyPart) -> tuple[int, ...]:
    """Map a key of ints, floats and strings to non-negative 32-bit ints, stable across runs and machines.

    Parameters
    ----------
    *key : int, float or str
        The parts of the key; an int in [0, 2³²) maps to itself, anything else to the two 32-bit
        words of the BLAKE2b-64 digest of its ``repr``. A NumPy scalar (``np.float64(0.5)``,
        ``np.int64(-1)``, ``np.str_("load")``) is first made the equal Python scalar (``.item()``),
        so it gives the stream of that scalar on every NumPy version (NumPy 2 spells
        ``repr(np.float64(0.5))`` as ``'np.float64(0.5)'``, NumPy 1 as ``'0.5'``).

    Returns
    -------
    tuple of int
        The ``spawn_key`` of the stream. The parts are concatenated without separators, so a
        string and the two ints of its digest give the same spawn key: ``key_to_ints("load") ==
        key_to_ints(*key_to_ints("load"))``. Two keys whose parts have the same kinds in the same
        positions (the name of what is drawn, then ints, as every call site builds them) cannot
        meet this; a bool part counts as the int 0 or 1.
    """
    out: list[int] = []
    for part in key:
        if isinstance(part, np.generic):  # a NumPy scalar: hashed as the equal Python scalar
            part = part.item()
        if isinstance(part, (bool, np.bool_)):
            out.append(int(part))
        elif isinstance(part, (int, np.integer)) and 0 <= int(part) < 2**32:
            out.append(int(part))
        else:
            digest = hashlib.blake2b(repr(part).encode(), digest_size=8).digest()
            out.extend(np.frombuffer(digest, dtype="<u4").tolist())
    return tuple(out)


def rng_for(seed: int, *key: KeyPart) -> np.random.Generator:
    """A PCG64 generator for ``seed`` and the task identity ``key``.

    Parameters
    ----------
    seed : int
        The study seed: an integer ≥ 0 (Python or NumPy; never ``bool``).
    *key : int, float or str
        What is drawn, e.g. ``("stiffness", realisation)`` — never a block index or a worker.

    Returns
    -------
    numpy.random.Generator
        ``PCG64(SeedSequence(seed, spawn_key=key_to_ints(*key)))``: the same key gives the same
        stream everywhere; different keys give independent streams.
    """
    seed = _checked_seed("seed", seed)
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed, spawn_key=key_to_ints(*key))))
