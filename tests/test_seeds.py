"""Random streams: rng_for(seed, *key) is numpy's PCG64 seeded by SeedSequence(seed, spawn_key=key).

The key is the identity of what is drawn; its order is part of it (a grid point i and a realisation
j are two axes: (i, j) and (j, i) are different draws). The mapping of a key to the spawn key is
rebuilt here from its documented rule (ints as they are, anything else as the two little-endian
32-bit words of the 8-byte BLAKE2b digest of its repr), not from tubeid's code.
"""

import hashlib

import numpy as np
import pytest

from tubeid.errors import SpecificationError
from tubeid.seeds import key_to_ints, rng_for


def _spawn_key(*key):
    out = []
    for part in key:
        if isinstance(part, int) and 0 <= part < 2**32:
            out.append(part)
        else:
            out.extend(int.from_bytes(hashlib.blake2b(repr(part).encode(), digest_size=8).digest()[i:i + 4], "little")
                       for i in (0, 4))
    return tuple(out)


def _reference(seed, *key):
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed, spawn_key=_spawn_key(*key))))


@pytest.mark.parametrize("seed, key", [(0, ()), (2009, ("stiffness", 7)), (1, ("response", 3, 11)),
                                       (5, ("grid", 2.5, "x")), (2**40, (2**33, -1))])
def test_streams_are_seed_sequences_of_the_documented_key(seed, key):
    a, b = rng_for(seed, *key), _reference(seed, *key)
    np.testing.assert_array_equal(a.standard_normal(5), b.standard_normal(5))
    np.testing.assert_array_equal(a.integers(0, 2**63, 3), b.integers(0, 2**63, 3))


def test_pinned_draws_do_not_change_between_versions():
    """Stored studies resume only if the same key gives the same numbers in every version."""
    assert rng_for(2009, "stiffness", 7).integers(0, 2**32, 3).tolist() == [4219177022, 1161629110, 869015176]


def test_two_key_axes_are_not_interchangeable():
    """(point, realisation) = (1, 2) and (2, 1) are two different draws; so are keys of different length."""
    draws = {key: rng_for(3, "response", *key).standard_normal(4).tobytes() for key in [(1, 2), (2, 1), (1,), (1, 2, 0), (2,)]}
    assert len(set(draws.values())) == len(draws)
    assert rng_for(3, "a", "b").standard_normal() != rng_for(3, "b", "a").standard_normal()
    assert rng_for(3, 1).standard_normal() != rng_for(4, 1).standard_normal()


def test_a_bad_seed_is_refused():
    for bad in (-1, 1.5, "7", None):
        with pytest.raises(SpecificationError, match="seed"):
            rng_for(bad)


def test_a_bool_seed_is_refused():
    """True was the seed 1 (``isinstance(True, int)``)."""
    for bad in (True, False, np.True_):
        with pytest.raises(SpecificationError, match=r"^seed = .*: must be a non-negative integer"):
            rng_for(bad)
    assert rng_for(np.int64(1)).random() == rng_for(1).random()  # NumPy integers remain seeds


@pytest.mark.parametrize("numpy_part, python_part", [
    (np.float64(0.5), 0.5), (np.float32(0.5), 0.5), (np.int64(-3), -3), (np.int64(2**40), 2**40),
    (np.str_("load"), "load"), (np.uint32(7), 7), (np.float64(1e-300), 1e-300)])
def test_a_numpy_scalar_key_is_the_equal_python_scalar(numpy_part, python_part):
    """Keys are hashed by repr, and NumPy 2 spells repr(np.float64(0.5)) 'np.float64(0.5)' (NumPy 1:
    '0.5'): a NumPy scalar is made the Python scalar first, so the stream is the same on any NumPy."""
    assert key_to_ints("x", numpy_part, 3) == key_to_ints("x", python_part, 3)
    assert rng_for(0, numpy_part).integers(0, 2**63, 2).tolist() == rng_for(0, python_part).integers(0, 2**63, 2).tolist()


@pytest.mark.parametrize("key, first", [
    ((0,), [5874934615388537135, 2488343231644625808]),
    ((7, "stiffness", 3), [4949791200326276079, 5328522082621220973]),
    ((1, 0.5), [7071166186965270895, 690187961085608116]),
    ((1, -3), [5123363935254244807, 1118225479178977256]),
    ((1, 2**40), [7886795206730228152, 6090838656833696939]),
    ((1, "load", 2.5, "x"), [3061924418888104004, 8952257964961971245]),
    ((0, 1e-300), [3593740204082058847, 1048970735203124454]),
    ((3, "\u00b5m", -0.0), [7537559135934562441, 906480096577395168]),
])
def test_python_keys_keep_their_streams(key, first):
    """Recorded before NumPy scalars were normalised: the streams of Python keys did not change."""
    assert rng_for(*key).integers(0, 2**63, 2).tolist() == first
