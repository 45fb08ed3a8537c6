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
from typing import Any

import dask.config
import yaml

__all__ = ["get", "refresh", "collect_env", "setting_name", "DEFAULTS_PATH"]

DEFAULTS_PATH = pathlib.Path(__file__).with_name("tubeid.yaml")
_PREFIX = "TUBEID_"


def collect_env(env: Mapping[str, str] | None = None) -> dict:
    """The configuration set by ``TUBEID_...`` environment variables.

    Parameters
    ----------
    env : mapping of str to str, optional
        The environment (default: ``os.environ``).

    Returns
    -------
    dict
        Nested under ``"tubeid"``, e.g. ``{"tubeid": {"runner": {"workers": 4}}}``; values read
        as Python literals, else kept as strings.
    """
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
    """(Re)load the packaged defaults into ``dask.config`` and apply ``TUBEID_...`` overrides.

    Parameters
    ----------
    env : mapping of str to str, optional
        The environment (default: ``os.environ``).
    """
    with open(DEFAULTS_PATH) as fh:
        defaults = yaml.safe_load(fh)
    dask.config.update_defaults(defaults)
    dask.config.update(dask.config.config, collect_env(env), priority="new")


def get(key: str, default: Any = None) -> Any:
    """The value of ``tubeid.<key>`` in ``dask.config``.

    Parameters
    ----------
    key : str
        Dotted key below ``tubeid``, e.g. ``"runner.workers"``.
    default : object, optional
        Returned when the key is not set.

    Returns
    -------
    object
        The configured value.
    """
    return dask.config.get("tubeid." + key, default=default)


def setting_name(key: str) -> str:
    """How a refusal names the setting ``tubeid.<key>``: with the environment variable that sets it,
    ``"tubeid.runner.workers (TUBEID_RUNNER__WORKERS)"`` (the inverse of :func:`collect_env`'s rule)."""
    return f"tubeid.{key} ({_PREFIX}{key.upper().replace('.', '__').replace('-', '_')})"


refresh()
