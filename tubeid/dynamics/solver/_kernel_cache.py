"""numba's on-disk cache of the solver's kernels, keyed on the sources of the whole solver.

numba keys a cached kernel on its own file's stamp (modification time and size) only. The solver's
main loop (``_fastpath``) compiles its callees from ``_events`` and ``_modal`` into its own code, and
bakes in constants of ``_work`` and ``_regimes``: with numba's key alone, an edit of one of those
files (a ``git pull`` into an editable install, say) leaves the cached main loop running the old
code, silently (an edit of ``_modal.py`` alone does not reach a cached ``run_exact``). Every cached
kernel of the solver is therefore keyed on one fingerprint of all the solver's sources
(:func:`sources_fingerprint`): any edit recompiles them all, once. This uses numba's internal
cache attributes; where they are missing (another numba), numba's own key stays in force.
"""

from __future__ import annotations

import hashlib
import pathlib
from collections.abc import Iterable

__all__ = ["sources_fingerprint", "key_on_sources", "cached_kernels"]

_HERE = pathlib.Path(__file__).resolve().parent


def sources_fingerprint(directory: str | pathlib.Path | None = None) -> str:
    """SHA-256 of the names and bytes of every ``*.py`` file of ``directory`` (default: the solver
    package), as the cache stamp ``"tubeid-solver-sources-<hex>"``.

    Parameters
    ----------
    directory : str or pathlib.Path, optional
        The package directory.

    Returns
    -------
    str
    """
    h = hashlib.sha256()
    for path in sorted(pathlib.Path(directory or _HERE).glob("*.py")):
        h.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return "tubeid-solver-sources-" + h.hexdigest()


def cached_kernels(modules: Iterable) -> list:
    """The numba dispatchers with an on-disk cache (``cache=True``) defined in ``modules``.

    Parameters
    ----------
    modules : iterable of module

    Returns
    -------
    list
    """
    out = []
    for module in modules:
        for name, obj in vars(module).items():
            if getattr(obj, "__module__", None) == module.__name__ and getattr(obj, "_cache", None) is not None \
                    and hasattr(obj, "py_func"):
                out.append(obj)
    return out


def key_on_sources(kernels: Iterable, fingerprint: str) -> int:
    """Key the on-disk cache of each kernel on ``fingerprint`` instead of its own file's stamp
    (before its first call: numba reads the stamp when it loads or saves the cache index).

    Parameters
    ----------
    kernels : iterable of numba dispatchers
    fingerprint : str

    Returns
    -------
    int
        How many kernels were re-keyed (the others keep numba's own key).
    """
    n = 0
    for kernel in kernels:
        cache_file = getattr(getattr(kernel, "_cache", None), "_cache_file", None)
        if cache_file is not None and hasattr(cache_file, "_source_stamp"):
            cache_file._source_stamp = fingerprint
            n += 1
    return n
