"""A store that can prove its contents: block checksums, verification, repair of what tubeid can rebuild.

Every block's completion flag is the checksum of the values it wrote (:func:`block_checksum`: 63
bits of SHA-256 over the outputs in name order, each as its name, dtype, shape and little-endian
bytes; SHA-256 because CPUs hash it in hardware), written after the data. :func:`verify` reads a store back without executing anything from
it: every flagged block's outputs are read and checksummed again, every coordinate is compared with
the checksum recorded when the store was made, and every array's metadata must be readable. It
names what is damaged: a deleted or undecodable chunk (``x/c/0/3``), a deleted array, a changed
value, an undecodable flag chunk. :func:`repair_structure` (run by ``tubeid run``, which has the
study definition) rewrites the metadata and coordinates from a freshly built empty store of the
same study (byte-identical by construction); the damaged blocks' flags are then cleared and the
runner recomputes exactly those blocks.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import pathlib
import tempfile
from collections.abc import Mapping, Sequence

import numpy as np

from tubeid._paths import local_path

__all__ = ["block_checksum", "values_checksum", "verify", "repair_structure", "Verification", "CHECKSUM_RULE",
           "chunk_key"]

CHECKSUM_RULE = ("first 64 bits (little-endian) of SHA-256 over the block's index, then its outputs in name order "
                 "(name, dtype, shape, little-endian values), lowest bit set")


def _bytes(a: np.ndarray):
    """The values as bytes: little-endian, C order (a view when the array already is), strings as text."""
    a = np.asarray(a)
    if a.dtype.kind in "OUST":
        return "\0".join(str(v) for v in a.ravel()).encode()
    a = np.ascontiguousarray(a.astype(a.dtype.newbyteorder("<"), copy=False))
    return memoryview(a.reshape(-1)).cast("B") if a.size else b""


def block_checksum(outputs: Mapping[str, np.ndarray], index: Sequence[int]) -> int:
    """Checksum of one block's outputs as stored, at its place in the store.

    Parameters
    ----------
    outputs : mapping of str to ndarray
        ``{output name: the block's values}`` in their stored dtype (any order).
    index : sequence of int
        The block's index per axis: the same values at another block (e.g. two blocks' chunks and
        flags swapped) give another checksum.

    Returns
    -------
    int
        63 bits of SHA-256 (see ``CHECKSUM_RULE``), never 0 (a flag of 0 means "not done").
    """
    h = hashlib.sha256()
    h.update(f"block {tuple(int(i) for i in index)}\0".encode())
    for name in sorted(outputs):
        a = np.asarray(outputs[name])
        h.update(f"{name}\0{a.dtype.name}\0{a.shape}\0".encode())
        h.update(_bytes(a))
    return int.from_bytes(h.digest()[:8], "little") | 1


def values_checksum(values) -> str:
    """Hex checksum of a coordinate's values (numbers by their float64 bytes, strings by their text)."""
    a = np.asarray(values)
    if a.dtype.kind in "biuf":
        a = a.astype("<f8")
    return hashlib.sha256(_bytes(a)).hexdigest()[:16]


def chunk_key(node: str, index, ndim: int) -> str:
    """The chunk file of block ``index`` of array ``node`` (whole along its extra dims)."""
    parts = [str(int(i)) for i in index] + ["0"] * (ndim - len(index))
    return f"{node}/c/" + "/".join(parts)


@dataclasses.dataclass
class Verification:
    """What :func:`verify` found in a store (or a pipeline stage).

    Parameters
    ----------
    group : str or None
        The pipeline stage verified (None: a single-study store).
    checked : int
        Finished blocks whose checksum was recomputed.
    total : int
        Blocks of the store (or stage).
    damaged : dict
        ``{block index: reason}`` of finished blocks whose data do not match (to recompute); the
        reason names the chunk (``x/c/0/3/0 missing``, ``... undecodable``) or the array.
    unreadable_flags : list
        Block indices whose flag chunk cannot be decoded (recomputed too).
    structure : list of str
        Damaged metadata or coordinates (rewritten from the study by ``tubeid run``).
    other_rule : str or None
        The checksum rule the store's blocks were made by when it is not this tubeid's
        (:data:`CHECKSUM_RULE`): a store written by an earlier tubeid, not a damaged one; its blocks
        cannot be verified.
    """

    group: str | None = None
    checked: int = 0
    total: int = 0
    damaged: dict = dataclasses.field(default_factory=dict)
    unreadable_flags: list = dataclasses.field(default_factory=list)
    structure: list = dataclasses.field(default_factory=list)
    other_rule: str | None = None

    @property
    def ok(self) -> bool:
        return not (self.damaged or self.unreadable_flags or self.structure)

    @property
    def to_recompute(self) -> list[tuple[int, ...]]:
        return sorted(set(self.damaged) | set(self.unreadable_flags))

    def lines(self, limit: int = 10) -> list[str]:
        """Human-readable findings.

        Parameters
        ----------
        limit : int
            At most this many lines per kind (structure, blocks), then a count of the rest.

        Returns
        -------
        list of str
        """
        out = list(self.structure[:limit])
        if len(self.structure) > limit:
            out.append(f"... and {len(self.structure) - limit} more")
        items = [f"block {i}: {r}" for i, r in sorted(self.damaged.items())]
        items += [f"block {i}: flag chunk undecodable" for i in self.unreadable_flags]
        out += items[:limit]
        if len(items) > limit:
            out.append(f"... and {len(items) - limit} more blocks")
        return out


def _open(path, group):
    from tubeid.runner.store import _group

    return _group(path, group, consolidated=False)


def _bookkeeping_attrs(path, group, ver: Verification) -> dict | None:
    from tubeid.runner.store import BOOKKEEPING, _group, _node

    try:
        return dict(_open(path, group)[BOOKKEEPING].attrs)
    except Exception as exc:
        ver.structure.append(f"bookkeeping group {_node(group, BOOKKEEPING)} unreadable ({type(exc).__name__})")
    try:  # the copy in the consolidated metadata
        return dict(_group(path, None, consolidated=True)[_node(group, BOOKKEEPING)].attrs)
    except Exception:
        return None


def verify(path: str | os.PathLike, group: str | None = None) -> Verification:
    """Check every finished block of a study store (or of a pipeline stage) against its checksum.

    Reads the store only (nothing stored in it is executed), chunk by chunk, so that a damaged
    chunk is named rather than raised.

    Parameters
    ----------
    path : path-like
        The store directory.
    group : str, optional
        The stage of a pipeline store (``None``: a single-study store).

    Returns
    -------
    Verification
        Blocks checked, damaged blocks with the reason (chunk key), undecodable flags, damaged
        metadata or coordinates.
    """
    from tubeid.runner.store import BOOKKEEPING, FLAG, _node, read_flags

    local_path(path)  # never a URL zarr would read elsewhere
    ver = Verification(group=group)
    attrs = _bookkeeping_attrs(path, group, ver)
    if attrs is None:
        ver.structure.append("block layout unknown: no block can be verified")
        return ver
    if attrs.get("checksum") != CHECKSUM_RULE:
        ver.other_rule = str(attrs.get("checksum"))
        ver.structure.append(f"block checksums made by another rule ({attrs.get('checksum')!r}, this tubeid: "
                             f"{CHECKSUM_RULE!r}): its blocks cannot be verified")
        return ver
    g = _open(path, group)
    for dim, expected in attrs.get("coordinates", {}).items():
        try:
            got = values_checksum(g[dim][...])
        except Exception as exc:
            ver.structure.append(f"coordinate {_node(group, dim)} unreadable ({type(exc).__name__})")
            continue
        if got != expected:
            ver.structure.append(f"coordinate {_node(group, dim)} changed (checksum {got} != {expected})")
    try:
        flags, ver.unreadable_flags = read_flags(path, group)
    except Exception as exc:
        ver.structure.append(f"flag array {_node(group, f'{BOOKKEEPING}/{FLAG}')} unreadable ({type(exc).__name__}): "
                             "every block is recomputed")
        return ver
    ver.total = int(flags.size)
    chunks = [int(c) for c in attrs["chunks"]]
    arrays, missing = {}, {}
    for name in attrs["outputs"]:
        try:
            arrays[name] = g[name]
        except Exception as exc:
            missing[name] = f"array {_node(group, name)} missing or unreadable ({type(exc).__name__})"
            ver.structure.append(missing[name])
    for index in zip(*np.nonzero(flags)):
        index = tuple(int(i) for i in index)
        ver.checked += 1
        if missing:
            ver.damaged[index] = "; ".join(missing.values())
            continue
        values, errors = {}, []
        for name, arr in arrays.items():
            region = tuple(slice(i * c, min((i + 1) * c, n)) for i, c, n in zip(index, chunks, arr.shape))
            try:
                values[name] = arr[region]
            except Exception as exc:
                errors.append(f"chunk {chunk_key(_node(group, name), index, arr.ndim)} undecodable "
                              f"({type(exc).__name__}: {str(exc)[:80]})")
        if errors:
            ver.damaged[index] = "; ".join(errors)
        elif block_checksum(values, index) != int(flags[index]):
            gone = [chunk_key(_node(group, n), index, a.ndim) for n, a in arrays.items()
                    if not _chunk_exists(path, chunk_key(_node(group, n), index, a.ndim))]
            ver.damaged[index] = ("checksum mismatch: " + (f"chunk {', '.join(gone)} missing" if gone else
                                                          "values differ from what the block wrote"))
    return ver


def _chunk_exists(path, key: str) -> bool:
    return (pathlib.Path(path) / key).is_file()


def repair_structure(study, path, group: str | None = None) -> list[str]:
    """Rewrite the metadata and coordinate files of ``study``'s layout in ``path`` (or stage ``group``)
    that are missing or differ from a fresh empty store of the same study; returns their keys.

    The group's own ``zarr.json`` (its provenance) is never rewritten; data chunks and flags are
    left to the block verification (a damaged block is recomputed, not copied).
    """
    from tubeid.runner.store import MANIFEST_NAME, _consolidate, _write_empty, _quiet

    target = pathlib.Path(path) / group if group else pathlib.Path(path)
    repaired = []
    with tempfile.TemporaryDirectory(prefix="tubeid-skeleton-") as tmp:
        if group:
            import zarr

            with _quiet():
                zarr.open_group(tmp, mode="w", zarr_format=3)
        _write_empty(study, tmp, {}, group=group)
        base = pathlib.Path(tmp) / group if group else pathlib.Path(tmp)
        for f in sorted(base.rglob("*")):
            rel = f.relative_to(base).as_posix()
            if not f.is_file() or rel == "zarr.json" or rel.startswith(".tubeid-") or rel == MANIFEST_NAME:
                continue
            dest = target / rel
            data = f.read_bytes()
            try:
                same = dest.read_bytes() == data
            except OSError:
                same = False
            if not same:
                dest.parent.mkdir(parents=True, exist_ok=True)
                fd, tmpf = tempfile.mkstemp(prefix=".tubeid-tmp-", dir=dest.parent)
                with os.fdopen(fd, "wb") as fh:
                    fh.write(data)
                os.replace(tmpf, dest)
                repaired.append(f"{group}/{rel}" if group else rel)
    if repaired:
        _consolidate(path, group)
    return repaired
