"""How complete a study store is, read without importing zarr (``tubeid status`` answers at once).

The store's layout is :mod:`tubeid.runner.store`'s. This module reads only what a status needs:
the attributes in a group's ``zarr.json`` and the completion flags. A flag array written
uncompressed (one raw little-endian uint64 per chunk file, as :func:`tubeid.runner.store.init_store`
writes them) is read file by file with NumPy; any other encoding (stores written before, or
metadata this reader does not recognise) and any metadata that does not parse go through zarr
(:func:`tubeid.runner.store.read_flags`, :func:`tubeid.runner.store.read_attrs`), so both paths
give the same answer, and damage is reported the same way: a missing flag chunk reads 0 (not
done), a chunk of the wrong size is listed in ``unreadable_flags`` and reads 0.
"""

from __future__ import annotations

import json
import os
import pathlib

import numpy as np

from tubeid.errors import SpecificationError, shown
from tubeid._paths import local_path
from tubeid.runner._terms import current as _terms
from tubeid.runner.study import RESERVED

__all__ = ["store_status", "pipeline_status", "FLAG", "BOOKKEEPING", "FORMAT", "PIPELINE_FORMAT", "LEGACY_FORMATS",
           "FLAG_CODECS"]

FLAG = "block_done"
BOOKKEEPING = RESERVED
FORMAT = "tubeid-study-store/2"
PIPELINE_FORMAT = "tubeid-pipeline-store/2"
LEGACY_FORMATS = ("tubeid-study-store/1", "tubeid-pipeline-store/1")
#: The status of a pipeline stage after the pipeline ended before it (``tubeid.runner.End``).
NOT_NEEDED = "not needed"
FLAG_CODECS = [{"name": "bytes", "configuration": {"endian": "little"}}]
"""The codecs of a flag array this module reads directly: raw little-endian bytes, no compression."""


def _group_dir(path, group=None) -> pathlib.Path:
    return pathlib.Path(path) / group if group else pathlib.Path(path)


def _attrs(path, group=None) -> dict:
    """The attributes of the root or of ``group`` (its own ``zarr.json``, not the consolidated copy)."""
    try:
        meta = json.loads((_group_dir(path, group) / "zarr.json").read_text(encoding="utf-8"))
        if meta.get("zarr_format") == 3 and meta.get("node_type") == "group" and isinstance(meta.get("attributes", {}), dict):
            return dict(meta.get("attributes", {}))
    except (OSError, ValueError, AttributeError):
        pass
    from tubeid.runner.store import read_attrs  # anything unusual: zarr reads it (or says why not)

    return read_attrs(path, group)


def _stage_names(attrs: dict, path) -> list[str]:
    """A pipeline store's ``stages`` attribute, refused in one line if it is not a list of names (damaged)."""
    stages = attrs.get("stages", [])
    if not isinstance(stages, list) or not all(isinstance(n, str) and n for n in stages):
        raise SpecificationError(_terms().store, str(path), f"has a damaged attribute stages = {shown(stages)} (not a list "
                                 "of stage names): it cannot be read as a pipeline store")
    return stages


def _flags_direct(path, group=None) -> tuple[np.ndarray, list[tuple[int, ...]]] | None:
    """``(flags, unreadable)`` read from the chunk files, or None if the array is not in the raw layout."""
    where = _group_dir(path, group) / BOOKKEEPING / FLAG
    try:
        meta = json.loads((where / "zarr.json").read_text(encoding="utf-8"))
        shape = tuple(int(n) for n in meta["shape"])
        ok = (meta.get("zarr_format") == 3 and meta.get("node_type") == "array" and meta.get("data_type") == "uint64"
              and meta.get("chunk_grid") == {"name": "regular", "configuration": {"chunk_shape": [1] * len(shape)}}
              and meta.get("chunk_key_encoding") == {"name": "default", "configuration": {"separator": "/"}}
              and meta.get("codecs") == FLAG_CODECS and meta.get("fill_value") == 0
              and not meta.get("storage_transformers") and len(shape) >= 1)
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None
    if not ok:
        return None
    flags = np.zeros(shape, dtype=np.uint64)
    bad = []
    for index in np.ndindex(*shape):
        chunk = where.joinpath("c", *(str(i) for i in index))
        try:
            raw = chunk.read_bytes()
        except FileNotFoundError:
            continue  # never written: the fill value, 0
        except OSError:
            raw = b""
        if len(raw) != 8:
            bad.append(tuple(int(i) for i in index))
            continue
        flags[index] = np.frombuffer(raw, dtype="<u8")[0]
    return flags, bad


def _flags(path, group=None) -> tuple[np.ndarray, list[tuple[int, ...]]]:
    direct = _flags_direct(path, group)
    if direct is not None:
        return direct
    from tubeid.runner.store import read_flags

    return read_flags(path, group)


def _flag_shape(path, group=None) -> tuple[int, ...]:
    """The block grid from the consolidated metadata (when the flag array's own metadata is damaged)."""
    from tubeid.runner.store import _group

    return _group(path, group, consolidated=True)[f"{BOOKKEEPING}/{FLAG}"].shape


def store_status(path: str | os.PathLike, group: str | None = None) -> dict:
    """How complete a study store (or one stage of a pipeline store) is; readable while a run writes it.

    Parameters
    ----------
    path : path-like
        The store directory.
    group : str, optional
        A stage of a pipeline store; without it a pipeline store gives :func:`pipeline_status`.

    Returns
    -------
    dict
        ``done``, ``total`` (blocks), ``complete`` (bool), ``attrs`` (provenance), ``lock`` (the record
        of the runner holding the store, or None), ``unreadable_flags`` (block indices), ``damaged``
        ('' or why the flags cannot be read). Flags are trusted here; :func:`tubeid.runner.verify`
        checks them against the data.
    """
    from tubeid.runner.lock import LOCK_NAME, read_lock

    p = local_path(path, field=_terms().store)
    if not p.is_dir():
        raise SpecificationError(_terms().store, str(path), "no such store")
    try:
        root = _attrs(p)
    except Exception as exc:
        _refuse_if_being_created(p)
        raise SpecificationError(_terms().store, str(path), f"is not a readable tubeid study store ({type(exc).__name__}: {exc})") from exc
    if root.get("format") in LEGACY_FORMATS:
        raise SpecificationError(_terms().store, str(path), f"was written by an older tubeid (layout {root.get('format')}): "
                                 "xarray.open_zarr still reads it; rerun its study with --overwrite for the current layout")
    if group is None and root.get("format") == PIPELINE_FORMAT:
        return pipeline_status(p)
    if group is not None:
        if root.get("format") != PIPELINE_FORMAT:
            raise SpecificationError("group", group, f"{path} is a single-study store (it has no stages)")
        if group not in _stage_names(root, path):
            raise SpecificationError("group", group, f"is not a stage of {path} (stages: {root.get('stages')})")
        if not (p / group / "zarr.json").exists():
            raise SpecificationError("group", group, f"stage not started yet in {path}")
    elif root.get("format") != FORMAT:
        _refuse_if_being_created(p)
        raise SpecificationError(_terms().store, str(path), "is not a tubeid study store")
    try:
        attrs = _attrs(p, group) if group else root
    except Exception as exc:
        raise SpecificationError(_terms().store, f"{path} (stage {group})", f"has unreadable group metadata ({type(exc).__name__}): "
                                 "`tubeid run` rebuilds the stage") from exc
    damaged = ""
    try:
        flags, bad = _flags(p, group)
    except Exception as exc:  # the flag array is gone or unreadable: nothing is proven done
        damaged = f"block flags unreadable ({type(exc).__name__}): `tubeid run` repairs them (unproven blocks are recomputed)"
        bad = []
        try:
            flags = np.zeros(_flag_shape(p, group), dtype=np.uint64)
        except Exception:
            flags = np.zeros(0, dtype=np.uint64)
    done, total = int(np.count_nonzero(flags)), int(flags.size)
    complete = done == total and bool(attrs.get("finished")) and not damaged
    return {"done": done, "total": total, "complete": complete, "attrs": attrs, "lock": read_lock(p / LOCK_NAME),
            "unreadable_flags": bad, "damaged": damaged}


def _refuse_if_being_created(p: pathlib.Path) -> None:
    """Say so when the store ``p`` is a run's creation that has not written its root yet: in progress
    (its lock's holder alive), or stopped before its first block (``creation_interrupted``, only
    tubeid's own files, all readable, or a manifest an ``--overwrite`` emptied, user files kept beside
    it); a manifest or lock file that cannot be read is named as such. Return otherwise (also when the
    directory cannot be listed: the caller's message stands)."""
    from tubeid.runner.lock import LOCK_NAME, describe_holder, holder_state, read_lock
    from tubeid.runner.store import MANIFEST_NAME, _own_file, _read_manifest, creation_interrupted

    try:
        entries = list(p.iterdir())
        own_only = bool(entries) and not (p / "zarr.json").exists() and all(_own_file(c.name) for c in entries)
        try:
            emptied = not (p / "zarr.json").exists() and (p / MANIFEST_NAME).is_file() and _read_manifest(p) == {}
        except SpecificationError:
            emptied = False
        if not (own_only or emptied or creation_interrupted(p)):
            return
    except OSError:
        return
    _read_manifest(p)  # an unreadable one is refused by `tubeid run` too: say that instead
    rec = read_lock(p / LOCK_NAME)
    if rec == {}:
        raise SpecificationError(_terms().store, str(p), f"has no results yet and an unreadable lock file {p / LOCK_NAME} (a "
                                 "run writing it now, or one killed while writing it): if no tubeid run is using this "
                                 "store, remove it")
    if rec and holder_state(rec, p / LOCK_NAME)[0] == "alive":
        raise SpecificationError(_terms().store, str(p), f"is being created by a run in progress ({describe_holder(rec)}); "
                                 "it has no block yet")
    if emptied and not own_only:
        raise SpecificationError(_terms().store, str(p), "holds no results: an --overwrite emptied it (the files tubeid did not "
                                 "write are kept) and stopped before it wrote the new store; `tubeid run` makes it anew")
    raise SpecificationError(_terms().store, str(p), "holds only the start of a run that stopped before its first block (no "
                             "result): `tubeid run` with the same study makes it again")


def pipeline_status(path: str | os.PathLike) -> dict:
    """Per-stage status of a pipeline store; readable while a run writes it.

    Parameters
    ----------
    path : path-like
        The pipeline store directory.

    Returns
    -------
    dict
        ``{"attrs", "lock", "stages": {name: {"started", "done", "total", "complete"[, "damaged"]
        [, "needed"]}}, "done", "total", "complete"}``: the root provenance, the lock's holder (or
        None), and blocks per stage and summed over the stages started so far. A stage the pipeline
        ended before (``tubeid.runner.End``; root attribute ``ended``) is not started, complete and
        ``"needed": False``.
    """
    from tubeid.runner.lock import LOCK_NAME, read_lock

    p = local_path(path)
    attrs = _attrs(p)
    names = _stage_names(attrs, path)
    status = attrs.get("stage_status", {})
    if not isinstance(status, dict):
        raise SpecificationError(_terms().store, str(path), f"has a damaged attribute stage_status = {shown(status)} (not "
                                 "a mapping of stage names to states)")
    stages = {}
    for name in names:
        if status.get(name) == NOT_NEEDED:
            stages[name] = {"started": False, "done": 0, "total": 0, "complete": True, "needed": False}
        elif (p / name / "zarr.json").exists():
            st = store_status(p, name)
            stages[name] = {"started": True, "done": st["done"], "total": st["total"], "complete": st["complete"]}
            if st["damaged"]:
                stages[name]["damaged"] = st["damaged"]
        else:
            stages[name] = {"started": False, "done": 0, "total": None, "complete": False}
    return {"attrs": attrs, "stages": stages, "lock": read_lock(p / LOCK_NAME),
            "done": sum(s["done"] for s in stages.values()), "total": sum(s["total"] or 0 for s in stages.values()),
            "complete": all(s["complete"] for s in stages.values())}
