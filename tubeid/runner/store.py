"""The Zarr store of a study: layout, provenance, per-block writes, checksummed completion flags.

Layout: one variable per output with dims (study axes..., extra dims...), chunked exactly by
blocks along the axes (whole along extra dims), so each block owns whole chunks; coordinates with
CF ``units`` and ``long_name``. Unwritten float chunks read as NaN (the fill value). The
bookkeeping lives in the sub-group ``_tubeid`` (hidden from ``xarray.open_zarr(store)``): the array
``block_done`` (uint64, dims ``block_<axis>``, one chunk per block), 0 until the block is written,
then the block's checksum (:func:`tubeid.runner.integrity.block_checksum` of the values it
wrote), written after the block's data; its attributes hold the block layout and checksums of the
coordinates. The root attributes hold the CF global attributes (``Conventions``, ``title``,
``references``, ``history``, ``source``) and the provenance: ``tubeid_version``, ``study_name``,
``study_file``, ``study_source``, ``study_hash``, ``seed``, ``seed_axes``, ``parameters`` (JSON),
``model_specification``, ``started`` (first start, UTC ISO 8601), ``runs`` (every start),
``finished`` ('' until complete), and the values returned by the study's ``summarize`` (names
listed in ``summary_keys``).

A pipeline store holds the same layout once per stage, in a Zarr group named after the stage
(``xarray.open_zarr(store, group="delta")``; its bookkeeping in ``delta/_tubeid``), whose
attributes hold the stage's provenance (``stage_name``, ``stage_hash``, ``pipeline_hash``, seeds,
parameters, times, summary). The root group holds no arrays; its attributes hold the pipeline
provenance (``format`` = ``tubeid-pipeline-store/2``, source, hash, seed, parameters, ``stages``,
``stage_status``, times). Metadata is consolidated per group and at the root after every change.

What tubeid wrote is listed in the manifest ``<store>/.tubeid-manifest.json`` (every group and
array it created, before creating it); ``--overwrite`` removes only those nodes' metadata and
chunk files (and tubeid's own ``.tubeid-*`` files), never anything else put in the store. The
lock of the runner writing the store is ``<store>/.tubeid-lock`` (:mod:`tubeid.runner.lock`).

Every attribute update of a group is one write of its ``zarr.json`` (``finished`` never lands
without the summary). A store or stage group gets its provenance last, once its arrays and flags
exist: a group the manifest lists without it, in which no block was written, is tubeid's own
creation interrupted (:func:`creation_interrupted`), which a run removes and makes again. A block is
written only into a store (stage group) that holds the study (stage) hash it was computed for,
checked before its data and again before its flag (:class:`StaleWrite`: a task an earlier, killed
run left running on a cluster). A store path that is a symbolic link is refused.
"""

from __future__ import annotations

import contextlib
import datetime
import errno
import functools
import json
import os
import pathlib
import re
import tempfile
import warnings
from typing import TYPE_CHECKING

import numpy as np
import zarr

from tubeid.errors import SpecificationError
from tubeid._paths import local_path
from tubeid.runner._terms import current as _terms
from tubeid.runner.status import BOOKKEEPING, FLAG, FORMAT, LEGACY_FORMATS, PIPELINE_FORMAT, pipeline_status, store_status

if TYPE_CHECKING:  # imported where used: `tubeid status` needs no xarray
    import xarray as xr

__all__ = ["init_store", "init_pipeline_store", "init_stage", "check_store", "check_stage", "check_blocks", "block_flags",
           "read_flags", "write_block", "update_attrs", "read_attrs", "open_results", "open_pipeline", "store_status",
           "pipeline_status", "is_pipeline", "prepare_path", "remove_store", "StaleWrite", "creation_interrupted",
           "restore_consolidated", "FLAG", "BOOKKEEPING", "MANIFEST_NAME",
           "REFERENCES", "now", "history_line"]

STAGE_FORMAT = "tubeid-pipeline-stage/2"
BLOCKS_FORMAT = "tubeid-blocks/1"
MANIFEST_NAME = ".tubeid-manifest.json"
CONVENTIONS = "CF-1.10"
REFERENCES = ("A. Batou and C. Soize, Experimental identification of stochastic processes using an uncertain "
              "computational non-linear dynamical model, ICIPE 2008, Journal of Physics: Conference Series 135 "
              "(2008) 012014, doi:10.1088/1742-6596/135/1/012014")
"""Default CF ``references`` of a store: the method tubeid implements (a study may give its own)."""


def now() -> str:
    """Current UTC time, ISO 8601 to the millisecond."""
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="milliseconds")


def history_line(what: str) -> str:
    """One CF ``history`` line: ``<UTC time> tubeid <version>: <what>``."""
    return f"{now()} tubeid {tubeid_version()}: {what}"


@functools.lru_cache(maxsize=1)
def tubeid_version() -> str:
    """The installed tubeid's version (read once per process: the metadata lookup scans sys.path)."""
    try:
        from importlib.metadata import version

        return version("tubeid")
    except Exception:  # not installed (running from a source tree)
        return "unknown"


_QUIET = ("Consolidated metadata", "is not recognized as a component")


@contextlib.contextmanager
def _quiet():
    """Silence zarr's notes on consolidated metadata and on files it does not own (a user's, tubeid's lock)."""
    with warnings.catch_warnings():
        for text in _QUIET:
            warnings.filterwarnings("ignore", message=f".*{text}.*")
        yield


#: Errors of the file system itself (full, over quota, read-only, no permission, a file too large,
#: I/O): reported as what they are, never blamed on something in the store.
_SYSTEM_ERRNOS = frozenset(getattr(errno, name) for name in ("ENOSPC", "EDQUOT", "EFBIG", "EROFS", "EACCES", "EPERM",
                                                                "EIO", "EMFILE", "ENFILE", "ENOMEM", "ESTALE")
                           if hasattr(errno, name))


def _system_error(exc: BaseException) -> OSError | None:
    """The file system's own error behind ``exc`` (itself, or its cause or context), if it is one."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, OSError) and exc.errno in _SYSTEM_ERRNOS:
            return exc
        exc = exc.__cause__ or exc.__context__
    return None


def cannot_write(path, exc: OSError) -> SpecificationError:
    """``cannot write <file>: <strerror>``: a write the file system refused (the store stays resumable)."""
    where = exc.filename or path
    return SpecificationError(_terms().store, str(path), f"cannot write {where}: {exc.strerror or os.strerror(exc.errno)} "
                              "(the store is left as it is: rerun once that is fixed, and it resumes)")


@contextlib.contextmanager
def _zarr_writes(path):
    """Turn a zarr failure while tubeid writes metadata into a clear refusal (never a library traceback):
    the file system's own error (a full disk, a quota, a read-only mount, permissions) as what it is,
    anything else as something in the store that confuses zarr."""
    try:
        yield
    except SpecificationError:
        raise
    except Exception as exc:
        system = _system_error(exc)
        if system is not None:
            raise cannot_write(path, system) from exc
        raise SpecificationError(
            _terms().store, str(path),
            f"cannot be written by zarr ({type(exc).__name__}: {str(exc)[:200]}): something in it that tubeid did "
            "not write (e.g. a directory holding a zarr.json that is not Zarr metadata) confuses zarr; tubeid "
            "left it in place: move it out of the store and rerun") from exc


def _consolidate(path, group=None, root: bool = True):
    """Consolidate the metadata of ``group`` (if any), then (``root``) of the root, which nests every
    group's: its cost grows with the number of groups, so a caller about to change the root anyway
    passes ``root=False`` and lets that change consolidate it."""
    with _quiet(), _zarr_writes(path):
        if group:
            zarr.consolidate_metadata(str(path), path=group)
        if root or not group:
            zarr.consolidate_metadata(str(path))


def _group(path, group=None, mode="r", consolidated=None):
    kw = {} if consolidated is None else {"use_consolidated": consolidated}
    with _quiet():
        return zarr.open_group(str(path), mode=mode, path=group, **kw) if group else zarr.open_group(str(path), mode=mode, **kw)


def _node(group, name):
    return f"{group}/{name}" if group else name


def _flag_dims(study):
    return tuple(f"block_{d}" for d in study.axes)


def prepare_path(path) -> pathlib.Path:
    """Refuse up front a store path that cannot be written (missing rights, a file in the way), that zarr
    would read as a URL (:func:`local_path`), or that is a symbolic link (also a dangling one): tubeid
    would create, write and with ``--overwrite`` replace what it points to, somewhere else than the path
    given. Links among its parent directories are followed as usual."""
    t = _terms()
    p = local_path(path, field=t.store)
    if p.is_symlink():
        raise SpecificationError(t.store, str(p), f"is a symbolic link (to {os.readlink(p)}): tubeid does not write "
                                 f"through a link; give the directory it points to, or {t.elsewhere}")
    if p.exists() and not p.is_dir():
        raise SpecificationError(t.store, str(p), f"exists and is not a directory (Zarr store): {t.elsewhere}")
    target = p if p.exists() else p.parent
    while not target.exists():  # the nearest existing ancestor must let us create the rest
        target = target.parent
    try:
        fd, probe = tempfile.mkstemp(prefix=".tubeid-probe-", dir=target)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise SpecificationError(t.store, str(p), f"is not writable ({exc.strerror} in {target})") from exc
    return p


_TOKEN = r"[0-9a-f]{24}(?:-\d+)?"  # a lock record's token (a breaker's: its own token and depth)
#: the exact names of tubeid's own files at the top of a store: the manifest, the lock and the files
#: taking, breaking and ageing it leave (:mod:`tubeid.runner.lock`), and ``tempfile.mkstemp``'s
#: ``.tubeid-tmp-`` / ``.tubeid-probe-`` + 8 characters. A user's file that merely starts with
#: ``.tubeid-`` is not one of them.
_OWN_NAME = re.compile(r"\.tubeid-(?:manifest\.json|(?:tmp|probe)-[a-z0-9_]{8}"
                       rf"|lock(?:\.break-{_TOKEN})*(?:\.tmp-{_TOKEN}|\.probe-{_TOKEN}-[0-9a-f]{{8}})?)")
#: the temporary file of a manifest write (:func:`_write_manifest`) killed before its rename, the only
#: tubeid temporary at a store's top: its name, and it is empty or begins as a manifest does (a user's
#: file merely named so is kept; the lock's leftovers are the lock's to judge)
_MANIFEST_TMP = re.compile(r"\.tubeid-tmp-[a-z0-9_]{8}")
_MANIFEST_HEAD = b'{\n "tubeid_manifest": '


def _manifest_leftover(f: pathlib.Path) -> bool:
    """Whether ``f``, at a store's top, is the temporary file a killed manifest write left
    (:data:`_MANIFEST_TMP`); a zarr metadata write's temporary there is one too."""
    if not (f.is_file() and not f.is_symlink()):
        return False
    if _ZARR_META_TMP.fullmatch(f.name):
        return True
    if not _MANIFEST_TMP.fullmatch(f.name):
        return False
    try:
        with open(f, "rb") as fh:
            head = fh.read(len(_MANIFEST_HEAD))
    except OSError:
        return False
    return _MANIFEST_HEAD.startswith(head)  # empty, cut short, or a manifest's whole head


def _own_file(name: str) -> bool:
    """tubeid's own files at the top of a store, by their exact names (:data:`_OWN_NAME`)."""
    return bool(_OWN_NAME.fullmatch(name))


def _group_meta(d: pathlib.Path) -> dict | None:
    """The ``zarr.json`` of the group directory ``d`` as JSON, or None if it is missing or not a group's."""
    try:
        meta = json.loads((d / "zarr.json").read_bytes())
    except (OSError, ValueError):
        return None
    return meta if isinstance(meta, dict) and meta.get("node_type") == "group" else None


def _holds_results(p: pathlib.Path, nodes: dict, group: str | None) -> bool:
    """Whether any array the manifest lists under ``group`` (None: the whole store) has a chunk file
    other than a coordinate's (``dimension_names`` = its own name, written while the store is
    created): a flag (every finished block writes one) or a block's data."""
    for node, kind in nodes.items():
        if kind != "array" or not isinstance(node, str) or (group and not node.startswith(group + "/")):
            continue
        d = p / node
        c = d / "c"
        if not c.is_dir() and not c.is_symlink():
            continue
        try:
            meta = json.loads((d / "zarr.json").read_bytes())
            coordinate = meta.get("dimension_names") == [node.rsplit("/", 1)[-1]]
        except (OSError, ValueError, AttributeError):
            coordinate = False
        if not coordinate and (c.is_symlink() or any(f.is_file() or f.is_symlink() for f in c.rglob("*"))):
            return True
    return False


def creation_interrupted(path, group: str | None = None) -> bool:
    """Whether the root of the store ``path`` (or its ``group``) is tubeid's own creation stopped before
    its attributes were written: the manifest lists the group (recorded before creating it), its
    ``zarr.json`` is missing (zarr's temporary ``zarr.<hex>.partial`` perhaps beside it) or is a group
    without tubeid's attributes (which :func:`_write_empty` writes last, in one write), and no block
    was ever written in it (no flag or data chunk). Such a group holds no result: a run removes what
    the manifest lists of it and creates it again. A group the manifest does not list, or that holds
    results (a store whose metadata was damaged or deleted), is never taken for one."""
    p = pathlib.Path(path)
    d = p / group if group else p
    try:
        nodes = _read_manifest(p)
    except SpecificationError:  # unreadable: nothing is provably tubeid's
        return False
    if nodes.get(group or "") != "group" or not d.is_dir() or d.is_symlink():
        return False
    f = d / "zarr.json"
    if f.exists() or f.is_symlink():
        meta = _group_meta(d) if f.is_file() and not f.is_symlink() else None
        attrs = meta.get("attributes", {}) if meta else None
        if not isinstance(attrs, dict) or "format" in attrs:
            return False
    return not _holds_results(p, nodes, group)


def check_store(path, study_hash: str) -> str:
    """``"new"`` if there is no store at ``path`` (or only tubeid's own creation of it, interrupted:
    :func:`creation_interrupted`, made again by the run); ``"resume"`` if it holds this study; else refuse."""
    p, t = pathlib.Path(path), _terms()
    if not p.exists() or (p.is_dir() and not (p / "zarr.json").exists() and all(_own_file(c.name) for c in p.iterdir())):
        return "new"
    if p.is_dir() and creation_interrupted(p):
        return "new"
    if not (p / "zarr.json").exists():
        try:
            recorded = _read_manifest(p)
        except SpecificationError:  # an unreadable manifest: nothing is provably tubeid's
            recorded = None
        if recorded == {} and (p / MANIFEST_NAME).is_file():  # emptied by an --overwrite killed before it wrote anew
            return "new"
        ours = bool(recorded) and recorded.get("") == "group"
        if ours:  # tubeid made it, and blocks were written in it (else: an interrupted creation, made again)
            raise SpecificationError(t.store, str(p), "exists and is not a tubeid study store any more: its root "
                                     "metadata (zarr.json) is missing, yet it holds blocks tubeid wrote (an --overwrite "
                                     "that was interrupted, or damage), of a study it cannot name; rerun with "
                                     f"--overwrite (which removes only what tubeid wrote) or {t.elsewhere}")
        raise SpecificationError(t.store, str(p), "exists and is not a tubeid study store (it holds files tubeid did not "
                                 f"write); {t.elsewhere}")
    try:
        attrs = read_attrs(p)
    except Exception as exc:
        raise SpecificationError(t.store, str(p), f"exists but is not a readable Zarr store ({type(exc).__name__}: "
                                 f"{exc}); {t.elsewhere} or use --overwrite") from exc
    fmt = attrs.get("format")
    if fmt in LEGACY_FORMATS:
        raise SpecificationError(t.store, str(p), f"was written by an older tubeid (layout {fmt}): xarray.open_zarr "
                                 f"still reads it; to run, {t.beside} (it kept no record of what it wrote, so "
                                 "tubeid does not replace it: remove it yourself to reuse the path)")
    if fmt not in (FORMAT, PIPELINE_FORMAT):
        raise SpecificationError(t.store, str(p), f"exists but is not a tubeid study store; {t.elsewhere} or use --overwrite")
    if attrs.get("study_hash") != study_hash:
        raise SpecificationError(
            t.store, str(p),
            f"was made by a different study definition (study {attrs.get('study_name')!r}, hash "
            f"{str(attrs.get('study_hash'))[:12]} here vs {study_hash[:12]} now); refusing to mix them: "
            f"{t.beside} or use --overwrite to replace it")
    return "resume"


# -- the manifest: what tubeid wrote, and removing only that ---------------------------------------------
def _read_manifest(p: pathlib.Path) -> dict:
    f = p / MANIFEST_NAME
    if not f.exists():
        return {}
    try:
        doc = json.loads(f.read_text())
        nodes = doc["nodes"]
        if not isinstance(nodes, dict):
            raise TypeError
        return nodes
    except (ValueError, KeyError, TypeError, OSError):
        raise SpecificationError(_terms().store, str(p), f"has an unreadable manifest {MANIFEST_NAME}: tubeid cannot tell "
                                 "what it wrote there and will not delete or replace anything in it") from None


def _record_nodes(p: pathlib.Path, nodes: dict) -> None:
    """Add ``{node path: "group" | "array"}`` to the manifest (atomic replace; the caller holds the lock)."""
    entries = _read_manifest(p)
    entries.update(nodes)
    _write_manifest(p, entries)


def _write_manifest(p: pathlib.Path, entries: dict) -> None:
    """Write the manifest (atomic replace); a write the file system refuses (full, read-only) is
    reported as such, the manifest left as it was."""
    doc = {"tubeid_manifest": 1, "nodes": dict(sorted(entries.items()))}
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(prefix=".tubeid-tmp-", dir=p)
        with os.fdopen(fd, "w") as fh:
            json.dump(doc, fh, indent=1)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, p / MANIFEST_NAME)
    except OSError as exc:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        if _system_error(exc) is None:
            raise
        raise cannot_write(p, exc) from exc


def _forget_nodes(p: pathlib.Path, nodes) -> None:
    """Drop ``nodes`` (removed: :func:`_remove_nodes`) from the manifest (atomic replace; the caller
    holds the lock): a directory a user makes there later is not taken for tubeid's."""
    entries = {n: k for n, k in _read_manifest(p).items() if n not in nodes}
    _write_manifest(p, entries)


_CHUNK = re.compile(r"^c(/\d+)*$")
#: zarr's atomic writes: ``Path.with_suffix(".<32 hex>.partial")`` of the file they replace, so
#: ``zarr.json`` → ``zarr.<hex>.partial`` and chunk ``3`` → ``3.<hex>.partial``
_ZARR_META_TMP = re.compile(r"zarr\.[0-9a-f]{32}\.partial")
_ZARR_CHUNK_TMP = re.compile(r"\d+\.[0-9a-f]{32}\.partial")
#: tubeid's own: ``tempfile.mkstemp(prefix=".tubeid-tmp-")`` (8 characters of ``[a-z0-9_]``)
_TUBEID_TMP = re.compile(r"\.tubeid-tmp-[a-z0-9_]{8}")


def _own_regular_file(f: pathlib.Path, root: pathlib.Path) -> bool:
    """A regular file (not a link) that resolves inside the store ``root``."""
    return f.is_file() and not f.is_symlink() and root in f.resolve().parents


def _node_files(p: pathlib.Path, node: str, kind: str) -> list[pathlib.Path]:
    """The files of one recorded node: its ``zarr.json``, its chunks (arrays) and the temporary files
    of atomic writes (:func:`_is_temporary`); never a file behind a link or outside the store (a
    chunk directory that is a link is not entered)."""
    d = p / node if node else p
    root = p.resolve()
    out = [f for f in (d / "zarr.json",) if _own_regular_file(f, root)]
    out += [f for f in d.glob("*") if (_manifest_leftover(f) if d == p else _is_temporary(f, chunk=False))
            and _own_regular_file(f, root)]
    c = d / "c"
    if kind == "array" and c.is_dir() and not c.is_symlink():
        for top, dirs, files in os.walk(c):  # does not descend into linked directories
            rel = pathlib.Path(top).relative_to(d).as_posix()
            if not _CHUNK.match(rel):
                continue
            for name in files:
                f = pathlib.Path(top) / name
                if (_CHUNK.match(f"{rel}/{name}") or _is_temporary(f, chunk=True)) and _own_regular_file(f, root):
                    out.append(f)
    return out


def _is_temporary(f: pathlib.Path, chunk: bool) -> bool:
    """A temporary file of an atomic write, by its name: zarr's (``zarr.<32 hex>.partial`` beside a
    node's metadata, ``<digits>.<32 hex>.partial`` among its chunks, ``chunk``) or tubeid's
    (``.tubeid-tmp-`` and mkstemp's 8 characters)."""
    return bool((_ZARR_CHUNK_TMP if chunk else _ZARR_META_TMP).fullmatch(f.name) or _TUBEID_TMP.fullmatch(f.name))


def remove_temporaries(path) -> list[str]:
    """Remove the temporary files that atomic writes left in the store ``path``'s recorded nodes.

    A write killed between creating its temporary file and renaming it (``SIGKILL``, a lost node)
    leaves it behind (:func:`_is_temporary`: zarr's ``zarr.<32 hex>.partial`` and
    ``<digits>.<32 hex>.partial``, tubeid's ``.tubeid-tmp-`` + 8 characters); nothing reads them, but
    a resumed store would then differ from one run without interruption. Only regular files of the
    nodes the manifest records, inside the store, with those exact names are removed: tubeid wrote
    them. The caller holds the store's lock (no write of ours is in flight). Returns their paths,
    relative to the store.
    """
    p = pathlib.Path(path)
    nodes = _read_manifest(p)
    _check_nodes(p, nodes)
    removed = []
    for node, kind in nodes.items():
        for f in _node_files(p, node, kind):
            if _manifest_leftover(f) if f.parent == p else _is_temporary(f, chunk=f.parent != (p / node if node else p)):
                f.unlink()
                removed.append(f.relative_to(p).as_posix())
    return sorted(removed)


def _check_nodes(p: pathlib.Path, nodes: dict) -> None:
    """Refuse a manifest naming a node outside the store (``..``, an absolute path, a symlink leading out):
    tubeid never wrote there, so nothing is deleted (the manifest was edited or damaged)."""
    root = p.resolve()

    def inside(node) -> bool:
        if not isinstance(node, str):
            return False
        pure = pathlib.PurePosixPath(node)
        if node and (pure.is_absolute() or ".." in pure.parts or "\\" in node):
            return False
        d = (p / node).resolve() if node else root
        return d == root or root in d.parents

    outside = [n for n in nodes if not inside(n)]
    if outside:
        t = _terms()
        raise SpecificationError(t.store, str(p), f"its manifest {MANIFEST_NAME} lists {outside[:3]} outside the store: "
                                 "tubeid never writes there, so it deletes nothing (the manifest was edited or damaged; "
                                 f"remove the store yourself, or {t.elsewhere})")


def _remove_nodes(p: pathlib.Path, nodes: dict) -> None:
    """Remove the files of ``nodes`` and the directories this leaves empty (deepest first)."""
    _check_nodes(p, nodes)
    dirs = set()
    for node, kind in nodes.items():
        for f in _node_files(p, node, kind):
            f.unlink()
            dirs.update(parent for parent in f.parents if parent != p and p in parent.parents)
    for d in sorted(dirs, key=lambda d: len(d.parts), reverse=True):
        with contextlib.suppress(OSError):  # not empty: something tubeid did not write is inside
            d.rmdir()


def remove_store(path, *, keep_lock: bool = True, dry_run: bool = False) -> list[str]:
    """Remove what tubeid wrote in the store ``path`` (its manifest's nodes and its own files).

    Anything else in the store (a user's file or array) is kept, with the directories holding it;
    returns those files' paths (relative to the store). The manifest itself is kept, emptied (one
    atomic replace, after the nodes are gone): a run killed before it writes the new store leaves a
    directory still provably tubeid's, which the next run (with or without ``--overwrite``) takes as
    new. A directory that holds no tubeid store is refused (``SpecificationError``), as is a store
    whose manifest is unreadable. ``dry_run``: only the refusals, nothing removed.
    """
    p, t = pathlib.Path(path), _terms()
    if not p.exists():
        return []
    if not p.is_dir():
        raise SpecificationError(t.store, str(p), "is a file, not a store directory")
    manifest = (p / MANIFEST_NAME).exists()
    nodes = _read_manifest(p)  # {} without a manifest, or for a store an earlier --overwrite emptied
    if nodes:
        pass
    elif (p / "zarr.json").exists():  # a Zarr hierarchy tubeid has no record of writing
        try:
            fmt = read_attrs(p).get("format")
        except Exception:
            fmt = None
        why = (f"was written by an older tubeid (layout {fmt}), which kept no record of what it wrote"
               if fmt in LEGACY_FORMATS else f"has no manifest ({MANIFEST_NAME}) of what tubeid wrote")
        raise SpecificationError(t.store, str(p), f"{why}: refusing to delete anything in it (remove it yourself, "
                                 f"or {t.elsewhere_or_beside})")
    elif not (manifest or all(_own_file(c.name) for c in p.iterdir())):
        raise SpecificationError(t.store, str(p), f"exists and is not a tubeid store: refusing to delete it ({t.elsewhere})")
    _check_nodes(p, nodes)
    if dry_run:
        return []
    _remove_nodes(p, nodes)
    if (p / MANIFEST_NAME).exists():
        _write_manifest(p, {})
    from tubeid.runner.lock import LOCK_NAME

    for f in p.iterdir():
        if _manifest_leftover(f) or (not keep_lock and f.name == LOCK_NAME and f.is_file() and not f.is_symlink()):
            f.unlink()
    return sorted(f.relative_to(p).as_posix() for f in p.rglob("*") if f.is_file() and not _own_file(f.name))


def _fresh_root(path, fmt: str, definition, *, source: str, study_hash: str, study_file: str, overrides) -> tuple[pathlib.Path, dict]:
    """The provenance shared by study and pipeline roots (the caller removed any earlier store; what an
    interrupted creation of it left, :func:`creation_interrupted`, is removed here: the nodes the
    manifest lists, nothing else)."""
    p = pathlib.Path(path)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        if _system_error(exc) is None:
            raise
        raise cannot_write(p, exc) from exc
    left = _read_manifest(p)
    if left:
        _remove_nodes(p, left)
        _forget_nodes(p, left)
    t = now()
    cmd = f"tubeid run {study_file}" + "".join(f" --set {k}={v!r}" for k, v in sorted(dict(overrides or {}).items()))
    return p, {
        "Conventions": CONVENTIONS,
        "title": definition.description or definition.name,
        "references": getattr(definition, "references", "") or REFERENCES,
        "source": f"tubeid {tubeid_version()}",
        "history": history_line(f"created by `{cmd}`"),
        "format": fmt,
        "tubeid_version": tubeid_version(),
        "study_name": definition.name,
        "study_file": str(study_file),
        "study_hash": study_hash,
        "study_source": source,
        "seed": int(definition.seed),
        "parameters": json.dumps(definition.values, sort_keys=True),
        "parameter_overrides": json.dumps(dict(overrides or {}), sort_keys=True),
        "started": t,
        "runs": [t],
        "finished": "",
    }


def init_store(study, path, *, source: str, study_hash: str, study_file: str = "", overrides=None) -> None:
    """Create the store (the caller removed any earlier one): coordinates, empty outputs, zero flags, provenance."""
    p, attrs = _fresh_root(path, FORMAT, study, source=source, study_hash=study_hash, study_file=study_file, overrides=overrides)
    attrs.update(seed_axes=list(study.seed_axes), model_specification=study.describe_model())
    _write_empty(study, p, attrs)


def bookkeeping_attrs(study) -> dict:
    """Attributes of a study's ``_tubeid`` group: block layout, outputs, checksums of the coordinates."""
    from tubeid.runner.integrity import CHECKSUM_RULE, values_checksum

    return {"format": BLOCKS_FORMAT, "axes": list(study.axes), "chunks": [int(study.chunks[d]) for d in study.axes],
            "outputs": sorted(study.outputs), "checksum": CHECKSUM_RULE,
            "coordinates": {d: values_checksum(v) for d, v in {**study.axes, **study.coords}.items()}}


def _write_empty(study, p, attrs, group=None, root: bool = True) -> None:
    """Write coordinates, lazy empty outputs and zero flags of ``study`` (at the root or in ``group``).

    The nodes are recorded in the manifest first; written with ``mode="a"`` (which creates and never
    deletes: files already in the directory that tubeid did not write stay).
    """
    import dask.array as da
    import xarray as xr

    axes = list(study.axes)
    block_chunks = tuple(study.chunks[d] for d in axes)
    data_vars = {}
    for name, out in study.outputs.items():
        extra = tuple(study.coords[d].size for d in out.dims)
        arr = da.empty(study.shape + extra, chunks=block_chunks + extra, dtype=out.dtype)
        out_attrs = {"long_name": out.long_name or name, **({"units": out.units} if out.units else {})}
        data_vars[name] = (tuple(axes) + out.dims, arr, out_attrs)
    coords = {}
    for dim, values in {**study.axes, **study.coords}.items():
        if values.dtype.kind == "U":  # variable-length strings (fixed-width UTF-32 has no Zarr v3 spec)
            values = values.astype(object)
        coords[dim] = (dim, values, study.coordinate_attrs(dim))
    ds = xr.Dataset(data_vars, coords=coords)  # the group's attributes come last (below)
    root = pathlib.Path(p)
    nodes = {group or "": "group", _node(group, BOOKKEEPING): "group", _node(group, f"{BOOKKEEPING}/{FLAG}"): "array"}
    nodes.update({_node(group, n): "array" for n in [*data_vars, *coords]})
    _record_nodes(root, nodes)
    with _quiet(), _zarr_writes(p):
        ds.to_zarr(str(p), group=group, mode="a", compute=False, consolidated=False)
        g = _group(p, group, mode="r+", consolidated=False)
        bk = g.create_group(BOOKKEEPING, attributes=bookkeeping_attrs(study))
        bk.create_array(FLAG, shape=study.block_grid, chunks=(1,) * len(axes), dtype="uint64", fill_value=0,
                        compressors=None,  # FLAG_CODECS: 8 raw bytes per block, read without zarr by `tubeid status`
                        dimension_names=_flag_dims(study),
                        attributes={"long_name": "block completion flag: 0 = not written, else the block's checksum"})
        # the provenance (the store's identity) last, in one write: a group without it is a creation
        # that was interrupted (creation_interrupted), never a store that lacks its bookkeeping
        g.update_attributes(attrs)
    _consolidate(p, group, root=root)


def init_pipeline_store(pipeline, path, *, source: str, study_hash: str, study_file: str = "", overrides=None) -> None:
    """Create a pipeline store (the caller removed any earlier one): the root group and its provenance."""
    p, attrs = _fresh_root(path, PIPELINE_FORMAT, pipeline, source=source, study_hash=study_hash, study_file=study_file, overrides=overrides)
    attrs.update(stages=pipeline.stage_names, stage_status={n: "pending" for n in pipeline.stage_names})
    _record_nodes(p, {"": "group"})
    with _quiet(), _zarr_writes(p):
        zarr.open_group(str(p), mode="a", zarr_format=3, attributes=attrs)
    _consolidate(p)


def init_stage(study, path, name: str, *, pipeline_name: str, pipeline_hash: str, stage_hash: str,
               references: str = "", root: bool = True) -> None:
    """Create (or replace) the group of stage ``name``: the layout of a study store, stage provenance.

    A stage group already there (e.g. from a run stopped while creating it) is removed first, only
    what the manifest says tubeid wrote. ``root=False``: the root's consolidated metadata is left
    for the caller's next change of the root (see :func:`_consolidate`).
    """
    p = pathlib.Path(path)
    nodes = {n: k for n, k in _read_manifest(p).items() if n == name or n.startswith(name + "/")}
    _remove_nodes(p, nodes)
    t = now()
    attrs = {
        "Conventions": CONVENTIONS,
        "title": study.description or name,
        "references": study.references or references or REFERENCES,
        "source": f"tubeid {tubeid_version()}",
        "history": history_line(f"stage {name} of pipeline {pipeline_name} created"),
        "format": STAGE_FORMAT,
        "tubeid_version": tubeid_version(),
        "pipeline_name": pipeline_name,
        "pipeline_hash": pipeline_hash,
        "stage_name": name,
        "stage_hash": stage_hash,
        "seed": int(study.seed),
        "stream_key": list(study.stream_key),
        "seed_axes": list(study.seed_axes),
        "parameters": json.dumps(study.values, sort_keys=True),
        "model_specification": study.describe_model(),
        "started": t,
        "runs": [t],
        "finished": "",
    }
    _write_empty(study, p, attrs, group=name, root=root)


def check_stage(path, name: str, stage_hash: str) -> str:
    """``"new"`` if stage ``name`` has no readable group yet, or only tubeid's own creation of it,
    interrupted (:func:`creation_interrupted`: :func:`init_stage` makes it again); ``"resume"`` if it
    holds this stage; else refuse."""
    p = pathlib.Path(path) / name
    if not (p / "zarr.json").exists():
        return "new"
    try:
        attrs = read_attrs(path, name)
    except Exception:  # its group metadata is damaged: the stage is rebuilt
        return "new"
    if "format" not in attrs and "stage_hash" not in attrs:
        if creation_interrupted(path, name):
            return "new"
        raise SpecificationError(_terms().store, f"{path} (stage {name})", f"holds a group {name!r} without stage provenance "
                                 "(its attributes were lost, or tubeid did not write it): tubeid cannot tell which "
                                 f"stage it holds and leaves it in place; {_terms().beside}, or use --overwrite (which "
                                 "removes only what tubeid wrote)")
    if attrs.get("stage_hash") != stage_hash:
        raise SpecificationError(
            _terms().store, f"{path} (stage {name})",
            f"holds stage {name!r} built from different inputs (hash {str(attrs.get('stage_hash'))[:12]} here vs "
            f"{stage_hash[:12]} now: an earlier stage's result or the code that derives this stage from it changed); "
            f"refusing to mix them: {_terms().beside}, or use --overwrite")
    return "resume"


def update_attrs(path, group=None, *, add_history: str = "", root: bool = True, **attrs) -> None:
    """Update the attributes (provenance) of the root or of ``group``, with ``add_history`` (if any)
    a new line of its CF ``history``, in one write; then re-consolidate the metadata (of the group
    only with ``root=False``: the caller changes the root next, see :func:`_consolidate`)."""
    g = _group(path, group, mode="r+", consolidated=False)
    if add_history:
        old = g.attrs.get("history", "")
        attrs["history"] = (old + "\n" if old else "") + history_line(add_history)
    with _quiet(), _zarr_writes(path):
        # one write of the group's zarr.json (``g.attrs.update`` writes it once per key): a kill never
        # leaves ``finished`` without the summary written with it
        g.update_attributes(attrs)
    _consolidate(path, group, root=root)


def restore_consolidated(path, groups=()) -> bool:
    """Consolidate again the metadata of each group in ``groups`` and of the root whose ``zarr.json``
    has none (a run killed between writing a group's attributes and consolidating it: a complete
    store would otherwise stay without it); True if any was. The caller holds the lock."""
    p = pathlib.Path(path)

    def lacking(d):
        return (_group_meta(d) or {}).get("consolidated_metadata") is None

    missing = [g for g in groups if g and lacking(p / g)]
    for g in missing:
        _consolidate(p, g, root=False)
    if missing or lacking(p):
        _consolidate(p)
        return True
    return False


def append_history(path, group=None, what: str = "") -> None:
    """Add a line to the CF ``history`` of the root or of ``group``."""
    update_attrs(path, group, add_history=what)


def read_attrs(path, group=None) -> dict:
    return dict(_group(path, group, consolidated=False).attrs)


def is_pipeline(path) -> bool:
    return read_attrs(path).get("format") == PIPELINE_FORMAT


def _flag_array(path, group=None, mode="r"):
    return _group(path, group, mode=mode, consolidated=False)[f"{BOOKKEEPING}/{FLAG}"]


def read_flags(path, group=None) -> tuple[np.ndarray, list[tuple[int, ...]]]:
    """``(flags, unreadable)``: the uint64 flags over the block grid (0 = not done, else the block's
    checksum) and the indices of flag chunks that could not be decoded (read as 0: not done)."""
    arr = _flag_array(path, group)
    try:
        return np.asarray(arr[...]), []
    except Exception:  # a damaged flag chunk: read them one by one
        flags = np.zeros(arr.shape, dtype=np.uint64)
        bad = []
        for index in np.ndindex(*arr.shape):
            try:
                flags[index] = arr[index]
            except Exception:
                bad.append(tuple(int(i) for i in index))
        return flags, bad


def block_flags(path, group=None) -> np.ndarray:
    """The completion flags (uint8 array over the block grid: 1 = written and checksummed); a store
    (or stage) whose flag array is missing is refused in one line (a run that verifies rebuilds it)."""
    try:
        flags = read_flags(path, group)[0]
    except KeyError:
        where = f"{path}" + (f" (stage {group})" if group else "")
        raise SpecificationError(_terms().store, where, f"has no block flags ({_node(group, f'{BOOKKEEPING}/{FLAG}')} is "
                                 "missing: the store was damaged, or an earlier tubeid was stopped while creating it); "
                                 f"{_terms().rebuild} rebuilds them (the blocks it cannot prove are "
                                 "recomputed)") from None
    return (flags != 0).astype(np.uint8)


def set_flags(path, indices, value: int = 0, group=None) -> None:
    """Set the flags of blocks ``indices`` (0 = not done: the block is recomputed by the next run)."""
    arr = _flag_array(path, group, mode="r+")
    for index in indices:
        arr[tuple(index)] = value


def _check_blocks(path, study, chunks, group=None) -> None:
    stored = [int(c) for c in chunks]
    now_ = [int(study.chunks[d]) for d in study.axes]
    if stored != now_:
        where = f"{path}" + (f" (stage {group})" if group else "")
        raise SpecificationError(
            "chunks", dict(zip(study.axes, now_)),
            f"{where} was written in blocks of {dict(zip(study.axes, stored))}; a block layout that differs "
            "(e.g. another tubeid.runner.default-chunk / TUBEID_RUNNER__DEFAULT_CHUNK here or on a worker) "
            f"would write the wrong regions: use the store's configuration, or {_terms().beside}, or use --overwrite")


def _stored_chunks(path, group, study) -> list[int] | None:
    """The block layout a store (or stage) was written with: from its bookkeeping attributes, else their
    copy in the consolidated metadata, else the chunking of an output array; None if all are gone."""
    for consolidated in (False, True):
        with contextlib.suppress(Exception):
            return list(_group(path, group, consolidated=consolidated)[BOOKKEEPING].attrs["chunks"])
    for consolidated in (False, True):
        for name in study.outputs:
            with contextlib.suppress(Exception):
                return list(_group(path, group, consolidated=consolidated)[name].chunks[:len(study.axes)])
    return None


def check_blocks(path, study, group=None) -> None:
    """Refuse to resume ``path`` (or its stage ``group``) with a block layout other than the one it was written with."""
    stored = _stored_chunks(path, group, study)
    if stored is not None:
        _check_blocks(path, study, stored, group)


class StaleWrite(RuntimeError):
    """A block write refused: the store (or stage) no longer holds the study the block was computed for.

    Raised on a worker by a task an earlier run left running (a runner killed or interrupted on an
    external cluster: cancelling does not stop a running task) after that store was replaced; the
    task fails, the store is not touched."""


def _holds(path, group, expected_hash: str) -> None:
    """Refuse (:class:`StaleWrite`) unless the root (study hash) or ``group`` (stage hash) of ``path``
    holds ``expected_hash`` now: read from its own ``zarr.json`` at each call, no cache."""
    d = pathlib.Path(path) / group if group else pathlib.Path(path)
    key = "stage_hash" if group else "study_hash"
    meta = _group_meta(d)
    attrs = meta.get("attributes") if meta else None
    found = attrs.get(key) if isinstance(attrs, dict) else None
    if found != expected_hash:
        where = f"{path}" + (f" (stage {group})" if group else "")
        held = f"hash {str(found)[:12]}" if found else "no study"
        raise StaleWrite(f"{where} no longer holds the study this block was computed for ({held} there, "
                         f"{str(expected_hash)[:12]} here): a task left running by an earlier run whose store was "
                         "replaced since; its write is refused, the store is not touched")


def write_block(path, study, block, outputs, group=None, *, expected_hash: str | None = None) -> None:
    """Write one block's outputs into their own region (whole chunks), then its flag (their checksum).

    Written with zarr directly into the arrays xarray created (same bytes as an xarray region
    write: no scale/offset encodings are used), which costs a few ms per block instead of ~10.
    The block layout is checked against the store's first (a worker with another default chunk
    size would otherwise write the wrong region). ``expected_hash``: the study hash (root) or stage
    hash (``group``) the block was computed for; checked right before the data are written and again
    before the flag (:class:`StaleWrite` if the store holds another study by then).
    """
    from tubeid.runner.integrity import block_checksum

    g = _group(path, group, mode="r+")
    _check_blocks(path, study, g[BOOKKEEPING].attrs.get("chunks", []), group)
    if expected_hash is not None:
        _holds(path, group, expected_hash)
    region = tuple(block.slices.values())
    try:
        for name, arr in outputs.items():
            g[name][region] = arr
        checksum = block_checksum(outputs, block.index)
        if expected_hash is not None:
            _holds(path, group, expected_hash)
        g[f"{BOOKKEEPING}/{FLAG}"][tuple(block.index)] = checksum
    except (SpecificationError, StaleWrite):
        raise
    except Exception as exc:  # a full disk, a quota, a read-only mount: said as such, not as the study's failure
        system = _system_error(exc)
        if system is None:
            raise
        raise cannot_write(path, system) from None


def open_results(path: str | os.PathLike, group: str | None = None, *, flags: bool = False,
                 chunks: str | int | dict | None = "auto") -> xr.Dataset:
    """The study results as a labelled ``xarray.Dataset`` (lazy, dask-backed; ``chunks=None``: lazy
    without dask, as ``xarray.open_zarr``).

    Parameters
    ----------
    path : path-like
        The store directory.
    group : str, optional
        A stage of a pipeline store.
    flags : bool
        Add the ``block_done`` variable (1 = block written and checksummed, dims ``block_<axis>``).
    chunks : "auto", dict or None
        As ``xarray.open_zarr``: dask-backed, or ``None`` for lazy numpy-backed arrays (no dask).

    Returns
    -------
    xarray.Dataset
        The same variables as ``xarray.open_zarr(path[, group=...])`` (the science: outputs and
        their coordinates), plus the attributes ``blocks_done`` and ``blocks_total``. Blocks not yet
        written read as NaN (float outputs). For a pipeline store without ``group``: no variables;
        the attributes are the pipeline provenance plus ``stage_blocks`` ({stage: [done, total or
        None]}) and ``stages_complete``.
    """
    import xarray as xr

    st = store_status(path, group)
    if "stages" in st and group is None:
        ds = xr.Dataset(attrs=dict(st["attrs"]))
        ds.attrs.update(stage_blocks={n: [s["done"], s["total"]] for n, s in st["stages"].items()},
                        stages_complete=[n for n, s in st["stages"].items() if s["complete"]])
        return ds
    with _quiet():
        ds = xr.open_zarr(str(path), group=group, chunks=chunks) if group else xr.open_zarr(str(path), chunks=chunks)
    if flags:
        arr = _flag_array(path, group)
        ds[FLAG] = xr.DataArray((read_flags(path, group)[0] != 0).astype(np.uint8),
                                dims=tuple(arr.metadata.dimension_names))
    ds.attrs.update(blocks_done=st["done"], blocks_total=st["total"])
    return ds


def open_pipeline(path: str | os.PathLike) -> dict[str, xr.Dataset]:
    """Every stage of a pipeline store started so far.

    Parameters
    ----------
    path : path-like
        The pipeline store directory.

    Returns
    -------
    dict of str to xarray.Dataset
        ``{stage name: open_results(path, stage)}``, in stage order.
    """
    st = store_status(path)
    if "stages" not in st:
        raise SpecificationError(_terms().store, str(path), "is a single-study store, not a pipeline (use open_results)")
    return {name: open_results(path, name) for name, s in st["stages"].items() if s["started"]}
