"""tubeid configuration: ``tubeid/tubeid.yaml`` defaults merged into ``dask.config`` (namespace ``tubeid``).

Precedence (last wins): packaged defaults < dask YAML files (``~/.config/dask/*.yaml``, key
``tubeid:``) < ``DASK_TUBEID__...`` variables < ``TUBEID_...`` variables < ``dask.config.set``.
An environment variable ``TUBEID_RUNNER__THREADS_PER_WORKER=2`` sets ``tubeid.runner.threads-per-worker``:
the prefix is dropped, ``__`` nests, ``_`` becomes ``-`` and the value is read as a Python literal
(falling back to the plain string), as dask does for ``DASK_...`` variables.

Every setting has one check (:data:`SCHEMA`-driven, :func:`check`): code reads a setting through
:func:`value`, which returns it checked and converted (durations in seconds, sizes in bytes), and
:func:`check` checks the whole configuration at once (every setting, no unknown setting, no section
replaced by a plain value, the lock heartbeat shorter than ``lock-stale-after``), as ``tubeid.runner.run``
and the ``tubeid`` commands do before anything else. A bad value is refused with a
:class:`~tubeid.errors.SpecificationError` naming the setting, the variable that sets it, the value and
the rule: ``tubeid.runner.default-chunk (TUBEID_RUNNER__DEFAULT_CHUNK) = 0: must be an integer >= 1``.
"""

from __future__ import annotations

import functools
import os
import pathlib
from collections.abc import Callable, Mapping
from typing import Any

import dask.config
import yaml

__all__ = ["get", "value", "check", "refresh", "collect_env", "setting_name", "schema", "DEFAULTS_PATH"]

DEFAULTS_PATH = pathlib.Path(__file__).with_name("tubeid.yaml")
_PREFIX = "TUBEID_"


class _Unmergeable:
    """A mapping read from an environment variable with keys that are not strings (``TUBEID_IO='{1: 2}'``):
    dask's merge cannot take it (a TypeError at import, in every command), so it is kept whole, as a
    plain value, for :func:`check` to refuse by name."""

    __slots__ = ("value",)

    def __init__(self, value):
        self.value = value

    def __repr__(self) -> str:
        return repr(self.value)


def _string_keys(value) -> bool:
    """Whether every key of ``value`` and of the mappings nested in it is a string."""
    return not isinstance(value, Mapping) or all(isinstance(k, str) and _string_keys(v) for k, v in value.items())


#: Variables that contradict each other (``TUBEID_RUNNER__WORKERS=2`` and ``TUBEID_RUNNER__WORKERS__X=1``:
#: a setting and a part of it), found by :func:`refresh`: refused by :func:`check` and :func:`value`.
_conflicts: list = []


def collect_env(env: Mapping[str, str] | None = None, conflicts: list | None = None) -> dict:
    """The configuration set by ``TUBEID_...`` environment variables.

    Parameters
    ----------
    env : mapping of str to str, optional
        The environment (default: ``os.environ``).
    conflicts : list, optional
        Receives ``(key, variable, value, other variable)`` for a variable that sets a value of which
        another variable sets a part (neither is applied: which one was meant is not known).

    Returns
    -------
    dict
        Nested under ``"tubeid"``, e.g. ``{"tubeid": {"runner": {"workers": 4}}}``; values read
        as Python literals, else kept as strings (a mapping with keys that are not strings is kept
        whole, unmerged, for :func:`check` to refuse).
    """
    env = os.environ if env is None else env
    flat, variables = {}, {}
    for name, value in env.items():
        if name.startswith(_PREFIX) and len(name) > len(_PREFIX):
            key = name[len(_PREFIX):].lower().replace("__", ".").replace("_", "-")
            read = dask.config.interpret_value(value)
            flat[key], variables[key] = (read if _string_keys(read) else _Unmergeable(read)), name
    for key in sorted(flat):  # a key and a key below it: dask's set fails (or keeps one) depending on the order
        for other in sorted(flat):
            if other.startswith(key + ".") and key in flat:
                if conflicts is not None:
                    conflicts.append((key, variables[key], flat[key], variables[other]))
                flat = {k: v for k, v in flat.items() if k != key and not k.startswith(key + ".")}
    flat = {"tubeid." + key: value for key, value in flat.items()}
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
    _conflicts.clear()
    dask.config.update(dask.config.config, collect_env(env, _conflicts), priority="new")


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



# -- the schema: one check per setting ------------------------------------------------------------
#: What a setting of ``tubeid.runner.worker-environ`` may be called: an environment variable name.
_ENV_NAME = r"[A-Z_][A-Z0-9_]*"


def _or_null(check: Callable, meaning: str) -> Callable:
    """``check``, also accepting None (``meaning`` says what None does)."""
    from tubeid.errors import SpecificationError

    def checked(field, value):
        if value is None:
            return None
        try:
            return check(field, value)
        except SpecificationError as exc:
            raise SpecificationError(field, value, f"{exc.rule}, or null ({meaning})") from None
    return checked


def _text(rule: str) -> Callable:
    """A non-blank string."""
    from tubeid.errors import SpecificationError

    def checked(field, value):
        if not isinstance(value, str) or not value.strip():
            raise SpecificationError(field, value, rule)
        return value
    return checked


def _directory(field, value):
    from tubeid.errors import SpecificationError

    if not isinstance(value, (str, os.PathLike)) or not str(value).strip() or "\0" in str(value):
        raise SpecificationError(field, value, "must be a directory path (a string), e.g. results")
    return pathlib.Path(value)


def _scheduler_address(field, value):
    from tubeid.errors import SpecificationError

    if value is None or value == "":  # none: DASK_SCHEDULER_ADDRESS, else the embedded cluster
        return None
    if not isinstance(value, str) or not value.strip() or any(c.isspace() for c in value):
        raise SpecificationError(field, value, "must be a scheduler address such as tcp://host:8786 (a string), "
                                 "or null (none)")
    return value


def _worker_environ(field, value):
    """A mapping of upper-case environment variable names to strings, integers or None (None: nothing)."""
    import re

    from tubeid.errors import SpecificationError

    variable = field[field.index("("):]  # "(TUBEID_RUNNER__WORKER_ENVIRON)": the whole mapping's variable
    if value is None:
        return {}
    if isinstance(value, _Unmergeable):
        value = value.value
    if not isinstance(value, Mapping):
        raise SpecificationError(field, value, "must be a mapping of environment variable names to values (or null)")
    for name, entry in value.items():
        if not isinstance(name, str) or not re.fullmatch(_ENV_NAME, name):
            raise SpecificationError(field, value, f"must hold upper-case environment variable names "
                                     f"([A-Z_][A-Z0-9_]*), not {name!r}; from the environment, set the whole mapping: "
                                     "TUBEID_RUNNER__WORKER_ENVIRON='{\"MALLOC_TRIM_THRESHOLD_\": 268435456}'")
        where = f"tubeid.runner.worker-environ.{name} {variable}"
        if isinstance(entry, bool) or not (entry is None or isinstance(entry, (str, int))):
            raise SpecificationError(where, entry, "must be a string, an integer or null")
        if name.startswith("MALLOC_") and entry is not None and not (
                (isinstance(entry, int) and entry >= 0) or (isinstance(entry, str) and entry.isascii() and entry.isdigit())):
            raise SpecificationError(where, entry, "must be a number of bytes (a non-negative integer; glibc ignores "
                                     "anything else)")
    return dict(value)


@functools.cache
def schema() -> dict[str, dict[str, Callable]]:
    """The check of every setting: ``{section: {key: check(field, value) -> the value as used}}``.

    Its sections and keys are those of ``tubeid.yaml``; a check raises a
    :class:`~tubeid.errors.SpecificationError` naming ``field``, the value and the rule.
    """
    from tubeid import _validation as v

    def count(minimum):
        return lambda field, value: v.integer(field, value, minimum=minimum)

    return {
        "runner": {
            "workers": _or_null(lambda field, value: v.worker_count(field, value, minimum=1), "one per core"),
            "threads-per-worker": count(1),
            "host": _text("must be a host name or address to bind to (e.g. 127.0.0.1)"),
            "embedded-tls": v.boolean,
            "dashboard-address": _text('must be an address host:port (":0" for any free port)'),
            "scheduler-address": _scheduler_address,
            "store-root": _directory,
            "default-chunk": count(1),
            "progress": v.boolean,
            "allowed-failures": count(0),
            "worker-environ": _worker_environ,
            "connect-timeout": v.duration,
            "lock-heartbeat": v.duration,
            "lock-stale-after": v.duration,
        },
        "io": {
            "max-bytes": v.byte_count,
            "max-displacement": lambda field, value: v.positive(field, value, "m"),
            "max-sensors": count(1),
            "max-dof": count(1),
            "max-specification-bytes": v.byte_count,
            "max-substeps": lambda field, value: v.real(field, value, low=1.0),
            "max-bootstrap": count(1),
        },
    }


def _refuse_conflicts() -> None:
    """Refuse the first pair of contradicting ``TUBEID_...`` variables :func:`refresh` found."""
    from tubeid.errors import SpecificationError

    for key, variable, given, other in _conflicts:
        raise SpecificationError(setting_name(key), given, f"is also set in part by {other}: set either {variable} "
                                 f"or the variables of its parts, not both")


def _section(name: str) -> dict:
    """The configured section ``tubeid.<name>`` (a mapping), else refused naming it."""
    from tubeid.errors import SpecificationError

    root = dask.config.get("tubeid", default=None)
    if not isinstance(root, dict):
        raise SpecificationError("tubeid", root, f"must be a mapping of the sections {', '.join(schema())}")
    section = root.get(name)
    if not isinstance(section, dict):
        shown = section.value if isinstance(section, _Unmergeable) else section
        example = f"{_PREFIX}{name.upper()}__{next(iter(schema()[name])).upper().replace('-', '_')}"
        raise SpecificationError(setting_name(name), shown, f"must be a mapping of the settings "
                                 f"{', '.join(schema()[name])} (named by strings); set one setting with its own "
                                 f"variable, e.g. {example}=...")
    return section


def value(key: str) -> Any:
    """The setting ``tubeid.<key>``, checked and converted (durations in seconds, sizes in bytes, counts
    as int, ``store-root`` as a path, ``worker-environ`` as a dict).

    Parameters
    ----------
    key : str
        A key of :func:`schema`, e.g. ``"runner.default-chunk"``.

    Returns
    -------
    object
        The value as tubeid uses it.

    Raises
    ------
    SpecificationError
        Naming the setting and its environment variable, the value and the rule.
    """
    from tubeid.errors import Described

    _refuse_conflicts()
    section, _, leaf = key.partition(".")
    check_ = schema()[section][leaf]
    configured = _section(section)
    given = configured[leaf] if leaf in configured else Described("not set")
    if isinstance(given, _Unmergeable) and leaf != "worker-environ":
        given = given.value  # refused by the check: not what the setting takes
    return check_(setting_name(key), given)


def check(*keys: str) -> dict[str, Any]:
    """Check the settings ``keys`` (default: the whole configuration) at once.

    Without ``keys``, also refused: a setting that is not one of :func:`schema` in a section (a
    misspelt ``TUBEID_RUNNER__WORKRES``), a section that is not one (``TUBEID_RUNER__WORKERS``). With
    both lock durations checked, the heartbeat must be shorter than ``lock-stale-after``.

    Returns
    -------
    dict
        ``{key: value(key)}``.
    """
    from tubeid.errors import SpecificationError

    whole = not keys
    if whole:
        root = dask.config.get("tubeid", default=None)
        for name in ([] if not isinstance(root, dict) else root):
            if name not in schema() and isinstance(root[name], (Mapping, _Unmergeable)):  # TUBEID_TEST_... scalars pass
                raise SpecificationError(setting_name(str(name)), root[name], "is not a section of the tubeid "
                                         f"configuration (its sections: {', '.join(schema())})")
        for name, settings in schema().items():
            for leaf in _section(name):
                if leaf not in settings:
                    raise SpecificationError(setting_name(f"{name}.{leaf}"), _section(name)[leaf],
                                             f"is not a setting of tubeid.{name} (its settings: {', '.join(settings)})")
        keys = tuple(f"{name}.{leaf}" for name, settings in schema().items() for leaf in settings)
    values = {key: value(key) for key in keys}
    heartbeat, stale_after = values.get("runner.lock-heartbeat"), values.get("runner.lock-stale-after")
    if heartbeat is not None and stale_after is not None and heartbeat >= stale_after:
        raise SpecificationError(setting_name("runner.lock-heartbeat"), f"{heartbeat:g} s",
                                 f"must be shorter than tubeid.runner.lock-stale-after = {stale_after:g} s (a lock "
                                 "without heartbeat for that long is taken over by another runner)")
    return values


refresh()
