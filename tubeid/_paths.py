"""A path tubeid hands to zarr or xarray, as a local path: the check every store and record path gets first.

zarr (3.x, ``zarr.storage._common._is_fsspec_uri``) and xarray's fsspec-aware backends read a path whose
text holds ``::`` (a chain of file systems) or ``://`` (a protocol) as an fsspec URL: ``prev.zarr::v2.zarr``
opens ``prev.zarr``. tubeid's own checks, lock and manifest work on the literal path, so such a path would
have zarr write into (or read from) another place than the one tubeid checked. Imports nothing heavy
(``tubeid status`` needs no zarr).
"""

from __future__ import annotations

import errno
import os
import pathlib

from tubeid.errors import SpecificationError

__all__ = ["local_path", "looked_up"]


def looked_up(path, field: str = "store", kind: str = "directory") -> tuple[pathlib.Path, str, str]:
    """``path`` as (Path, its text, its resolved form), refused (``SpecificationError`` naming
    ``field``) if it is not a non-empty path or the file system cannot look it up at all (a name
    longer than it allows, a loop of links, a file among its parents). A missing path is no error."""
    text = os.fspath(path) if isinstance(path, (str, os.PathLike)) else path
    if not isinstance(text, str) or not text:
        raise SpecificationError(field, path, f"must be a non-empty path of a local {kind}")
    p = pathlib.Path(text)
    try:
        p.lstat()
    except FileNotFoundError:
        pass
    except (OSError, ValueError) as exc:  # ENAMETOOLONG, ELOOP, EACCES on a parent, a NUL byte
        if getattr(exc, "errno", None) == errno.ENOTDIR:
            raise SpecificationError(field, text, "has a file, not a directory, among its parents") from None
        raise SpecificationError(field, text, f"cannot be looked up: {getattr(exc, 'strerror', None) or exc}") from None
    return p, text, os.path.realpath(p)


def local_path(path, field: str = "store", kind: str = "directory") -> pathlib.Path:
    """``path`` as a local ``kind`` (directory or file) path, refused (``SpecificationError`` naming
    ``field``) if zarr or xarray would read it as a URL (``::`` chains file systems, ``://`` names a
    protocol: tubeid's checks, lock and manifest would look at one place while zarr wrote, or xarray
    read, another) in any form it may reach them: as given, made absolute (a working directory named
    ``a::b``), or with links resolved; or if the file system cannot look it up at all
    (:func:`looked_up`)."""
    p, text, resolved = looked_up(path, field, kind)
    for form in (text, os.path.abspath(p), resolved):  # as given, from the working directory, links followed
        if "::" in form or "://" in form:
            where = "" if form == text else f" (as {form})"
            raise SpecificationError(field, text, f"must be a local {kind} path{where}: zarr and xarray read '::' and "
                                     f"'://' in a path as a URL of another file system, not as part of a {kind} name; "
                                     f"rename the {kind}")
    return p
