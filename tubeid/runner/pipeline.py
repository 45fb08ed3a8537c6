"""Multi-stage studies: a ``Pipeline`` of stages, each a ``Study`` run after the earlier ones.

A stage is either a ``Study`` or a function ``stage(results, **parameters) -> Study`` called only
when every earlier stage is complete: ``results`` maps the earlier stage names to their
``xarray.Dataset`` (read from the store, with the attributes written by their ``summarize``), and
the keywords are the pipeline parameters the function names. A function stage is named after the
function (``def load_r(results, *, size): ...`` is stage ``load_r``) and must return a ``Study``
with that name and the pipeline's seed. Values a stage takes from earlier results must reach its
task through ``parameters``, ``axes`` or ``coords``: they are then stored and part of the stage
hash, so a changed upstream result is never silently mixed with blocks computed before.

A function stage may instead return :class:`End` (``End("nothing detected")``): the pipeline ends
there, with nothing left to compute. That stage and the later ones are not built; their status is
``"not needed"`` and the store is complete (a loop of optional steps needs no placeholder stages).

Every stage's random streams are keyed by (pipeline seed, stage name, seed-axis coordinates): the
stages draw independent streams, and each keeps common random numbers across its other axes.
"""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
import json
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from tubeid import _validation
from tubeid.errors import SpecificationError
from tubeid.runner.study import RESERVED, Parameter, Parameterised, Study, Warmup, _plain, check_name

__all__ = ["Pipeline", "End", "stage_hash"]


@dataclasses.dataclass(frozen=True)
class End:
    """What a function stage returns when the pipeline has nothing left to compute: it ends before
    that stage (see the module docstring).

    Parameters
    ----------
    reason : str
        Why (stored in the store's root attributes, ``ended``).
    """

    reason: str

    def __post_init__(self):
        if not isinstance(self.reason, str) or not self.reason:
            raise SpecificationError("End.reason", self.reason, "must be a non-empty string")


@dataclasses.dataclass(frozen=True)
class Pipeline(Parameterised):
    """Stages run in order into one Zarr store (one group per stage); see the module docstring.

    Parameters
    ----------
    name : str
        Identifier (the store's file name).
    seed : int
        Non-negative; the seed of every stage.
    stages : sequence of Study or callable
        ``Study`` objects or ``stage(results, **parameters) -> Study`` functions; ``results`` maps
        each earlier stage's name to its Dataset.
    parameters : mapping of str to object
        ``{name: plain value or Parameter}`` passed to the stage functions that name them
        (``tubeid run --set name=value`` overrides one).
    description : str
        One line for the provenance (the store's CF ``title``).
    references : str
        The store's CF ``references`` (default: the method's paper), inherited by stages that give
        none.
    warmup : Warmup, optional
        Work done once per machine before the first stage that has blocks to compute.
    """

    name: str
    seed: int
    stages: Sequence[Study | Callable]
    parameters: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    description: str = ""
    references: str = ""
    warmup: Warmup | None = None

    def __post_init__(self):
        check_name("name", self.name)
        _validation.seed("seed", self.seed)
        stages = list(self.stages)
        if not stages:
            raise SpecificationError("stages", stages, "must hold at least one stage")
        names = []
        for i, st in enumerate(stages):
            if isinstance(st, Study):
                name = st.name
                if st.seed != self.seed:
                    raise SpecificationError(f"stages.{name}.seed", st.seed, f"must be the pipeline seed {self.seed}")
            elif callable(st):
                name = getattr(st, "__name__", None)
            else:
                raise SpecificationError(f"stages[{i}]", st, "must be a Study or a function stage(results, **parameters) -> Study")
            check_name(f"stages[{i}].name", name)
            if name == RESERVED:
                raise SpecificationError(f"stages[{i}].name", name, "is reserved for the store's bookkeeping")
            if name in names:
                raise SpecificationError(f"stages[{i}].name", name, "is already the name of an earlier stage")
            names.append(name)
        object.__setattr__(self, "stages", tuple(stages))
        params = {}
        for name, p in self.parameters.items():
            p = p if isinstance(p, Parameter) else Parameter(p)
            params[name] = dataclasses.replace(p, value=p.check(name, p.value))
        object.__setattr__(self, "parameters", params)
        if not isinstance(self.references, str):
            raise SpecificationError("references", self.references, "must be a string")
        if self.warmup is not None and not isinstance(self.warmup, Warmup):
            raise SpecificationError("warmup", self.warmup, "must be a tubeid.runner.Warmup")
        self._check_signatures()

    def _check_signatures(self):
        used = set()
        open_ended = False
        for st in self.stages:
            if isinstance(st, Study):
                continue
            name = st.__name__
            try:
                sig = inspect.signature(st)
            except (TypeError, ValueError):
                open_ended = True
                continue
            ps = list(sig.parameters.values())
            if not ps or ps[0].kind not in (ps[0].POSITIONAL_ONLY, ps[0].POSITIONAL_OR_KEYWORD):
                raise SpecificationError(f"stages.{name}", str(sig), "must accept the earlier results as first argument")
            for p in ps[1:]:
                if p.kind is p.VAR_KEYWORD:
                    open_ended = True
                elif p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY):
                    if p.name in self.parameters:
                        used.add(p.name)
                    elif p.default is p.empty:
                        raise SpecificationError(f"stages.{name}", p.name,
                                                 f"required by the stage function but not a pipeline parameter {sorted(self.parameters)}")
        unused = set(self.parameters) - used
        if unused and not open_ended:
            name = sorted(unused)[0]
            raise SpecificationError(f"parameters.{name}", self.parameters[name].value, "unknown parameter: no stage function accepts it")

    # -- parameters ---------------------------------------------------------------------------
    # -- stages -------------------------------------------------------------------------------
    @property
    def stage_names(self) -> list[str]:
        return [st.name if isinstance(st, Study) else st.__name__ for st in self.stages]

    def stage(self, name: str, results: Mapping[str, Any]) -> Study | End:
        """The ``Study`` of one stage given the earlier stages' results (or :class:`End`: the
        pipeline ends before it).

        Parameters
        ----------
        name : str
            The stage's name.
        results : mapping of str to xarray.Dataset
            The results of every earlier stage, by name.

        Returns
        -------
        Study or End
            The stage's study, its random streams keyed by ``name``; or the function stage's
            :class:`End`.
        """
        names = self.stage_names
        if name not in names:
            raise SpecificationError("stage", name, f"is not a stage of pipeline {self.name!r} (stages: {names})")
        i = names.index(name)
        missing = [n for n in names[:i] if n not in results]
        if missing:
            raise SpecificationError(f"stages.{name}", name, f"needs the results of the earlier stages {missing}")
        st = self.stages[i]
        if not isinstance(st, Study):
            earlier = {n: results[n] for n in names[:i]}
            sig = inspect.signature(st)
            takes_all = any(p.kind is p.VAR_KEYWORD for p in sig.parameters.values())
            kw = {k: v for k, v in self.values.items() if takes_all or k in sig.parameters}
            st = st(earlier, **kw)
            if isinstance(st, End):
                return st
            if not isinstance(st, Study):
                raise SpecificationError(f"stages.{name}", type(st).__name__,
                                         "the stage function must return a Study (or End)")
            if st.name != name:
                raise SpecificationError(f"stages.{name}.name", st.name, f"must be the stage (function) name {name!r}")
            if st.seed != self.seed:
                raise SpecificationError(f"stages.{name}.seed", st.seed, f"must be the pipeline seed {self.seed}")
        # each stage draws its own streams (keyed by its name) unless it names another stage's key to
        # keep common random numbers with it (e.g. a check of one point of an earlier trial grid)
        return dataclasses.replace(st, stream_key=st.stream_key or (name,))


def stage_hash(pipeline_hash: str, study: Study, upstream: Sequence[tuple[str, str, Mapping]]) -> str:
    """SHA-256 identity of a materialised stage.

    Hashes the pipeline hash (source + parameter overrides), the stage's ``Study.fingerprint()``
    (everything that defines its values, including any derived value it was given) and, for each
    earlier stage, its name, its hash and its stored summary.
    """
    h = hashlib.sha256(pipeline_hash.encode())
    h.update(b"\0" + study.fingerprint().encode())
    h.update(b"\0" + json.dumps([[n, hsh, {k: _plain(v, k) for k, v in summ.items()}] for n, hsh, summ in upstream],
                                sort_keys=True).encode())
    return h.hexdigest()
