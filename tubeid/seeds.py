"""Reproducible random streams: one generator per (study seed, task identity).

Every random draw in tubeid comes from ``rng_for(seed, *key)``. The key is the identity of
what is drawn (e.g. ``("stiffness", realisation)``), never a block index or a worker, so that
results are bit-identical whatever the number of workers, the order, retries or resumes.
"""

from __future__ import annotations

import hashlib

import numpy as np

__all__ = ["rng_for", "key_to_ints"]


def key_to_ints(*key) -> tuple[int, ...]:
    """Map a key of ints, floats and strings to a tuple of non-negative 32-bit ints (stable across runs)."""
    out: list[int] = []
    for part in key:
        if isinstance(part, (bool, np.bool_)):
            out.append(int(part))
        elif isinstance(part, (int, np.integer)) and 0 <= int(part) < 2**32:
            out.append(int(part))
        else:
            digest = hashlib.blake2b(repr(part).encode(), digest_size=8).digest()
            out.extend(np.frombuffer(digest, dtype="<u4").tolist())
    return tuple(out)


def rng_for(seed: int, *key) -> np.random.Generator:
    """A PCG64 generator for ``seed`` and the task identity ``key`` (ints, floats or strings)."""
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        from tubeid.errors import SpecificationError

        raise SpecificationError("seed", seed, "must be a non-negative integer")
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(int(seed), spawn_key=key_to_ints(*key))))
