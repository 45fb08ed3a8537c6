"""Optional dependencies: which extra installs which package, and a clear error when one is missing.

``require("matplotlib.figure", "tubeid report")`` imports the module, or raises
``MissingDependencyError`` (``tubeid report needs matplotlib: pip install "tubeid[plot]"``)
when the package is not installed. The table below is checked against ``pyproject.toml``'s
extras by the tests.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from tubeid.errors import MissingDependencyError

__all__ = ["EXTRAS", "require"]

#: import name -> (distribution to install, tubeid extra that installs it)
EXTRAS: dict[str, tuple[str, str]] = {
    "matplotlib": ("matplotlib", "plot"),
    "pyuff": ("pyuff", "io"),
    "h5netcdf": ("h5netcdf", "io"),
    "h5py": ("h5py", "io"),
    "bokeh": ("bokeh", "dashboard"),
    "dask_jobqueue": ("dask-jobqueue", "slurm"),
    "dask_kubernetes": ("dask-kubernetes", "k8s"),
}


def require(module: str, feature: str) -> ModuleType:
    """Import ``module`` of an optional dependency, or say which extra installs it.

    Parameters
    ----------
    module : str
        The module to import, e.g. ``"matplotlib.figure"``; its top-level package must be a key
        of ``EXTRAS``.
    feature : str
        What needs it, as the user would name it (``"tubeid report"``, ``"reading UFF 58 files"``).

    Returns
    -------
    types.ModuleType
        The imported module.

    Raises
    ------
    MissingDependencyError
        When the package itself is not installed. An ``ImportError`` from inside an installed
        package (a broken installation) propagates unchanged.
    """
    top = module.partition(".")[0]
    package, extra = EXTRAS[top]
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        if (exc.name or "").partition(".")[0] != top:
            raise
        raise MissingDependencyError(feature, package, extra) from exc
