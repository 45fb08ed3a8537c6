"""tubeid configuration: ``tubeid/tubeid.yaml`` defaults merged into ``dask.config`` (namespace ``tubeid``).

Precedence (last wins): packaged defaults < dask YAML files (``~/.config/dask/*.yaml``, key
``tubeid:``) < ``DASK_TUBEID__...`` variables < ``TUBEID_...`` variables < ``dask.config.set``.
An environment variable ``TUBEID_RUNNER__THREADS_PER_WORKER=2`` sets ``tubeid.runner.threads-per-worker``:
the prefix is dropped, ``__`` nests, ``_`` becomes ``-`` and the value is read as a Python literal
(falling back to the plain string), as dask does for ``DASK_...`` variables.
"""

from __future__ import annotations

import os
import pathlib
from collections.abc import Mapping

import dask.config
import yaml

__all__ = ["get", "refresh", "collect_env", "DEFAULTS_PATH"]

DEFAULTS_PATH = pathlib.Path(__file__).with_name("tubeid.yaml")
_PREFIX = "TUBEID_"


def collect_env(env: Mapping[str, str] | None = None) -> dict:
    """Nested config dict (under ``"tubeid"``) from ``TUBEID_...`` environment variables."""
    env = os.environ if env is None else env
    flat = {}
    for name, value in env.items():
        if name.startswith(_PREFIX) and len(name) > len(_PREFIX):
            key = name[len(_PREFIX):].lower().replace("__", ".").replace("_", "-")
            flat["tubeid." + key] = dask.config.interpret_value(value)
    out: dict = {}
    dask.config.set(flat, config=out)
    return out


def refresh(env: Mapping[str, str] | None = None) -> None:
    """(Re)load the packaged defaults and apply ``TUBEID_...`` environment overrides."""
    with open(DEFAULTS_PATH) as fh:
        defaults = yaml.safe_load(fh)
    dask.config.update_defaults(defaults)
    dask.config.update(dask.config.config, collect_env(env), priority="new")


def get(key: str, default=None):
    """The value of ``tubeid.<key>`` (e.g. ``get("runner.workers")``)."""
    return dask.config.get("tubeid." + key, default=default)


refresh()
