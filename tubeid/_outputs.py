"""Output directories that know what tubeid wrote in them: a manifest, atomic writes, safe removal.

tubeid deletes or replaces only what it wrote and can prove it wrote. Every file written through
:class:`OutputDir` is recorded in the directory's manifest (``.tubeid-manifest.json``) with its size
and SHA-256. Then:

* writing a name that exists but is not in the manifest is refused (a user's ``summary.md`` beside a
  report is never overwritten), and so is writing over a listed file whose content changed since
  tubeid wrote it (the user edited it: it is theirs now);
* :meth:`OutputDir.remove` removes a listed file only if its content still matches the manifest;
  anything else is left in place and reported;
* every write goes to a temporary file in the same directory, then ``os.replace``: a reader sees
  the old file or the new one, never half of one; an interrupted write leaves at most a
  temporary file ``.tubeid-tmp-`` + 8 characters of ``[a-z0-9_]`` (``tempfile.mkstemp``'s exact
  form), which :meth:`OutputDir.remove` clears. A user's file that merely starts with
  ``.tubeid-tmp-`` (``.tubeid-tmp-notes.txt``) is not of that form and is never removed.

Directories (e.g. a Zarr store) are recorded with :meth:`OutputDir.record_directory`; their
contents are the business of whoever wrote them (the runner's store carries its own provenance).

The manifest is updated under an exclusive ``fcntl`` lock on ``.tubeid-manifest.lock``, so several
processes writing into one directory do not lose entries (POSIX; on a network file system this
relies on its ``flock`` support, as NFSv4 and Lustre provide).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import fcntl
import hashlib
import json
import os
import pathlib
import re
import tempfile
from collections.abc import Iterator

from tubeid.errors import SpecificationError

__all__ = ["OutputDir", "MANIFEST_NAME", "file_sha256"]

MANIFEST_NAME = ".tubeid-manifest.json"
_LOCK_NAME = ".tubeid-manifest.lock"
_TMP_PREFIX = ".tubeid-tmp-"
#: the exact name of a temporary file :meth:`OutputDir._atomic_write` makes (``tempfile.mkstemp`` with
#: ``prefix=_TMP_PREFIX``: 8 characters of ``[a-z0-9_]``); any other ``.tubeid-tmp-*`` name is the user's
_TMP_NAME = re.compile(re.escape(_TMP_PREFIX) + r"[a-z0-9_]{8}")
_VERSION = 1


def file_sha256(path: os.PathLike | str, chunk: int = 1 << 20) -> str:
    """SHA-256 (hex) of a file's content."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def _plain_name(name) -> bool:
    """A plain file name inside the directory (no separator, ``..`` or absolute path), not in tubeid's own
    ``.tubeid-*`` names (the manifest, its lock, temporaries, a run's lock): an output is never named so,
    and a manifest listing such a name was edited (this only refuses; nothing is removed by prefix)."""
    if not isinstance(name, str) or not name or "\\" in name:
        return False
    p = pathlib.PurePosixPath(name)
    return not (p.is_absolute() or ".." in p.parts or len(p.parts) != 1 or name.startswith(".tubeid-"))


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


class OutputDir:
    """A directory of outputs with a manifest of what tubeid wrote (see the module docstring).

    Parameters
    ----------
    path : path-like
        The directory; created (with parents) if missing.
    field : str
        How the user named it (e.g. ``"--out"``), used in error messages.
    """

    def __init__(self, path: os.PathLike | str, field: str = "out"):
        self.path = pathlib.Path(path)
        self.field = field
        if self.path.exists() and not self.path.is_dir():
            raise SpecificationError(field, str(self.path), "exists and is not a directory")
        try:
            self.path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise SpecificationError(field, str(self.path), f"cannot create the directory ({exc.strerror})") from None
        if not os.access(self.path, os.W_OK):
            raise SpecificationError(field, str(self.path), "is not writable")

    # ------------------------------------------------------------------ manifest
    @property
    def manifest_path(self) -> pathlib.Path:
        return self.path / MANIFEST_NAME

    @contextlib.contextmanager
    def _locked(self) -> Iterator[dict]:
        """The manifest, read and written back under an exclusive lock."""
        with open(self.path / _LOCK_NAME, "a+") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            try:
                entries = self._read()
                yield entries
                self._write_manifest(entries)
            finally:
                fcntl.flock(lock, fcntl.LOCK_UN)

    def _read(self) -> dict:
        p = self.manifest_path
        if not p.exists():
            return {}
        try:
            doc = json.loads(p.read_text(encoding="utf-8"))
            entries = doc["entries"]
            if not isinstance(entries, dict):
                raise TypeError
        except (ValueError, KeyError, TypeError, OSError):
            raise SpecificationError(f"{self.field} manifest", str(p),
                                     "is not a tubeid manifest (unreadable): tubeid will not touch this directory's "
                                     "files; move it aside or choose another directory") from None
        outside = [n for n in entries if not _plain_name(n)]
        if outside:  # tubeid only ever records plain names: an edited or damaged manifest proves nothing
            raise SpecificationError(f"{self.field} manifest", str(p),
                                     f"lists {outside[:3]}, not plain file names in this directory: tubeid never "
                                     "writes such entries and will not touch this directory's files; move it aside "
                                     "or choose another directory")
        return entries

    def _write_manifest(self, entries: dict) -> None:
        doc = {"tubeid_manifest": _VERSION, "entries": dict(sorted(entries.items()))}
        self._atomic_write(self.manifest_path, json.dumps(doc, indent=1).encode())

    def entries(self) -> dict:
        """``{name: {"kind", "sha256", "size", "written"}}`` of everything recorded."""
        return self._read()

    # ------------------------------------------------------------------ files
    def _atomic_write(self, target: pathlib.Path, data: bytes) -> None:
        fd, tmp = tempfile.mkstemp(prefix=_TMP_PREFIX, dir=self.path)
        try:
            with os.fdopen(fd, "wb") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, target)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise

    def _name(self, name: str) -> str:
        if not _plain_name(name):
            raise SpecificationError("output name", name, "must be a plain file name inside the output directory")
        return name

    def owned(self, name: str) -> bool:
        """True if ``name`` is recorded and (for a file) its content still matches the record."""
        return self._owned(self._read(), name)

    def _owned(self, entries: dict, name: str) -> bool:
        e = entries.get(name)
        target = self.path / name
        if e is None:
            return False
        if e.get("kind") == "directory":
            return target.is_dir()
        return target.is_file() and target.stat().st_size == e.get("size") and file_sha256(target) == e.get("sha256")

    def _check_writable(self, entries: dict, name: str) -> None:
        target = self.path / name
        if not (target.exists() or target.is_symlink()):
            return
        if name not in entries:
            raise SpecificationError(f"{self.field}/{name}", str(target),
                                     "exists and was not written by tubeid: it is left untouched; move it or "
                                     f"choose another {self.field}")
        if not self._owned(entries, name):
            raise SpecificationError(f"{self.field}/{name}", str(target),
                                     "was written by tubeid but changed since (edited or replaced): it is left "
                                     f"untouched; move it or choose another {self.field}")

    def write_bytes(self, name: str, data: bytes) -> pathlib.Path:
        """Write ``data`` to ``name`` atomically and record it; refused over a file tubeid does not own."""
        name = self._name(name)
        with self._locked() as entries:
            self._check_writable(entries, name)
            target = self.path / name
            self._atomic_write(target, data)
            entries[name] = {"kind": "file", "sha256": hashlib.sha256(data).hexdigest(), "size": len(data),
                             "written": _now()}
        return target

    def write_text(self, name: str, text: str) -> pathlib.Path:
        """Write UTF-8 ``text`` to ``name`` (see :meth:`write_bytes`)."""
        return self.write_bytes(name, text.encode("utf-8"))

    def save_figure(self, fig, name: str, **kwargs) -> pathlib.Path:
        """Render a Matplotlib figure to ``name`` (format from the suffix) and write it as above."""
        import io

        buf = io.BytesIO()
        fig.savefig(buf, format=pathlib.PurePath(name).suffix.lstrip(".") or "png", **kwargs)
        return self.write_bytes(name, buf.getvalue())

    def record_directory(self, name: str) -> pathlib.Path:
        """Record that tubeid created the directory ``name`` (it must not exist yet, or be recorded)."""
        name = self._name(name)
        with self._locked() as entries:
            target = self.path / name
            if (target.exists() or target.is_symlink()) and entries.get(name, {}).get("kind") != "directory":
                raise SpecificationError(f"{self.field}/{name}", str(target),
                                         "exists and was not created by tubeid: it is left untouched")
            entries[name] = {"kind": "directory", "written": _now()}
        return target

    def _plan(self, entries: dict, names) -> tuple[list[str], list[str], list[str]]:
        """``(remove, forget, keep)``: the recorded files of ``names`` (default all) whose content still
        matches, those that are missing, and those that changed (kept); directories are left out."""
        remove: list[str] = []
        forget: list[str] = []
        keep: list[str] = []
        for name in list(entries if names is None else names):
            e = entries.get(name)
            if e is None or e.get("kind") == "directory":
                continue
            target = self.path / name
            if not (target.exists() or target.is_symlink()):
                forget.append(name)
            elif self._owned(entries, name):
                remove.append(name)
            else:
                keep.append(name)
        return remove, forget, keep

    def removal(self, names=None) -> tuple[list[str], list[str]]:
        """What :meth:`remove` would do now, without doing it: ``(removed, kept)`` (a dry run; an unreadable
        manifest is refused here as there)."""
        remove, _, keep = self._plan(self._read(), names)
        return remove, keep

    def remove(self, names=None) -> list[str]:
        """Remove recorded files (all, or ``names``) whose content still matches; return what was kept.

        Directories are only forgotten, not removed (their owner removes them). A recorded file that
        is missing is forgotten; one that changed is kept (and listed in the result). Temporary files
        of interrupted writes are removed too: only by their exact name (:data:`_TMP_NAME`), regular
        files, never a user's file that merely shares the prefix.
        """
        with self._locked() as entries:
            remove, forget, kept = self._plan(entries, names)
            for name in remove:
                (self.path / name).unlink()
            for name in remove + forget:
                del entries[name]
            with os.scandir(self.path) as it:  # left by an interrupted write (under this lock no write is in flight)
                left = [e.path for e in it if _TMP_NAME.fullmatch(e.name) and e.is_file(follow_symlinks=False)]
            for tmp in left:
                with contextlib.suppress(OSError):
                    os.unlink(tmp)
        return kept
