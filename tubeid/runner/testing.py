"""Helpers for testing the runner (and studies built on it): small test studies and pipelines, store digests."""

from __future__ import annotations

import hashlib
import json
import pathlib

import numpy as np
import zarr

__all__ = ["STUDY", "PIPELINE", "write_study", "write_pipeline", "store_digest", "flags", "clear_flag"]

# A realisation-bound study whose tasks cost `work` 48x48 tanh-matmul iterations per realisation
# (work = 3000: ~10-40 ms per block of 2 on this project's 2-core machine). The random stream of a
# point is keyed by its realisation only, and x = delta * (a function of that stream), so
# delta = 0.2 must equal exactly 2 x delta = 0.1 (common random numbers). TUBEID_TEST_FAIL_AT
# (environment) makes the block containing that realisation raise: a controllable interruption.
# TUBEID_TEST_BLOCK_SECONDS (environment) adds that much sleep to every block without changing its
# values: interruption tests pace the run with it, so their signal lands mid-study on a fast machine.
STUDY = '''
import os
import time
import numpy as np
from tubeid.runner.study import Output, Parameter, Study

def task(block, rng, *, work, label="x"):
    fail_at = os.environ.get("TUBEID_TEST_FAIL_AT")
    if fail_at is not None and int(fail_at) in block["realisation"]:
        raise RuntimeError("interrupted on purpose")
    time.sleep(float(os.environ.get("TUBEID_TEST_BLOCK_SECONDS", "0")))
    r, d = block["realisation"], block["delta"]
    out = np.empty((d.size, r.size, 3))
    for j, real in enumerate(r):
        a = rng(realisation=real).standard_normal((48, 48))
        for _ in range(work):
            a = np.tanh(a @ a.T / 48.0)
        for i, dv in enumerate(d):
            out[i, j] = dv * a[:3, 0]
    return {"x": out, "count": np.full((d.size, r.size), work, dtype="int32")}

study = Study(
    name="runner-test",
    seed=7,
    axes={"delta": [0.1, 0.2], "realisation": range(REALISATIONS)},
    chunks={"delta": 1, "realisation": CHUNK},
    seed_axes=("realisation",),
    task=task,
    coords={"component": ["a", "b", "c"]},
    units={"delta": "1"},
    outputs={"x": Output(dims=("component",), units="m", long_name="test output"),
             "count": Output(dtype="int32", units="1")},
    parameters={"work": Parameter(WORK, bounds=(1, 100000)), "label": Parameter("x", choices=["x", "y"])},
    model="MODEL-SPEC-TEXT",
)
'''


def write_study(directory, name="study.py", *, realisations=16, chunk=2, work=5) -> pathlib.Path:
    path = pathlib.Path(directory) / name
    path.write_text(STUDY.replace("REALISATIONS", str(realisations)).replace("CHUNK", str(chunk))
                    .replace("WORK", str(work)))
    return path


# A 3-stage pipeline. Stage `curve`: a noisy parabola y(x) per realisation (x_opt = argmin of the
# mean over realisations is stored by `summarize`); stage `around`: a grid of offsets around x_opt
# (a value derived from stage 1, passed as the parameter `center`); stage `final`: a fixed Study.
# Every point costs `work` 48x48 tanh-matmul iterations. TUBEID_TEST_FAIL_STAGE / _FAIL_AT
# (environment) make the block of that stage containing that realisation raise;
# TUBEID_TEST_BLOCK_SECONDS (environment) paces stage `around`'s blocks as in STUDY.
PIPELINE = '''
import os
import time
import numpy as np
from tubeid.runner.pipeline import Pipeline
from tubeid.runner.study import Output, Parameter, Study

SEED = 11
SIZES = {"normal": {"curve": CURVE, "around": AROUND}, "quick": {"curve": 4, "around": 4}}

def _busy(g, work):
    a = g.standard_normal((48, 48))
    for _ in range(work):
        a = np.tanh(a @ a.T / 48.0)
    return a[0, 0]

def _maybe_fail(stage, realisations):
    if os.environ.get("TUBEID_TEST_FAIL_STAGE") == stage and int(os.environ["TUBEID_TEST_FAIL_AT"]) in realisations:
        raise RuntimeError("interrupted on purpose")

def curve_task(block, rng, *, work):
    _maybe_fail("curve", block["realisation"])
    x, r = block["x"], block["realisation"]
    y = np.empty((x.size, r.size))
    for j, real in enumerate(r):
        g = rng(realisation=real)
        e = g.standard_normal(2)
        y[:, j] = (x - 0.3) ** 2 + 0.2 * e[0] * x + 0.1 * e[1] + 0.0 * _busy(g, work)
    return {"y": y}

def around_task(block, rng, *, center, work):
    _maybe_fail("around", block["realisation"])
    time.sleep(float(os.environ.get("TUBEID_TEST_BLOCK_SECONDS", "0")))
    o, r = block["offset"], block["realisation"]
    z = np.empty((o.size, r.size))
    for j, real in enumerate(r):
        g = rng(realisation=real)
        e = g.standard_normal()
        z[:, j] = center + o + 0.01 * e + 0.0 * _busy(g, work)
    return {"z": z}

def final_task(block, rng):
    return {"w": np.array([rng(realisation=r).standard_normal() for r in block["realisation"]])}

def x_opt(ds):
    return {"x_opt": float(ds.y.mean("realisation").idxmin("x"))}

def curve(results, *, size, work):
    return Study(name="curve", seed=SEED, axes={"x": np.round(np.linspace(0.0, 0.6, 13), 3),
                 "realisation": range(SIZES[size]["curve"])}, chunks={"x": 13, "realisation": 2},
                 seed_axes=("realisation",), task=curve_task, outputs={"y": Output(units="m")},
                 parameters={"work": work}, summarize=x_opt)

def around(results, *, size, work):
    center = results["curve"].attrs["x_opt"]
    return Study(name="around", seed=SEED, axes={"offset": [-0.1, 0.0, 0.1], "realisation": range(SIZES[size]["around"])},
                 chunks={"offset": 3, "realisation": 2}, seed_axes=("realisation",), task=around_task,
                 outputs={"z": Output(units="m")}, parameters={"center": center, "work": work},
                 description=f"offsets around x_opt = {center}")

study = Pipeline(
    name="pipeline-test",
    seed=SEED,
    stages=[curve, around,
            Study(name="final", seed=SEED, axes={"realisation": range(6)}, chunks={"realisation": 3},
                  task=final_task, outputs={"w": Output()})],
    parameters={"size": Parameter("normal", choices=["normal", "quick"]), "work": Parameter(WORK, bounds=(0, 100000))},
    description="three-stage runner test pipeline",
)
'''


def write_pipeline(directory, name="pipeline.py", *, curve=8, around=8, work=2) -> pathlib.Path:
    """Write the test pipeline with ``curve``/``around`` realisations (size "normal") and ``work`` per point."""
    path = pathlib.Path(directory) / name
    path.write_text(PIPELINE.replace("CURVE", str(curve)).replace("AROUND", str(around)).replace("WORK", str(work)))
    return path


VOLATILE = {"started", "finished", "runs", "study_file", "history"}


def _structure(meta):
    """Group metadata without any group's attributes (its own, and those nested in its consolidated
    metadata: compared as ``attrs`` entries, and they may name the store's directory), so that two
    stores in different directories compare equal; arrays' metadata is kept whole."""
    if isinstance(meta, dict):
        return {k: _structure(v) for k, v in meta.items() if not (k == "attributes" and meta.get("node_type") == "group")}
    if isinstance(meta, list):
        return [_structure(v) for v in meta]
    return meta


def store_digest(path) -> dict:
    """Byte digest of every file of a store except group metadata (root and pipeline stages), plus for
    each group its non-volatile attributes (``attrs`` for the root, ``attrs:<group>`` for the others)
    and its metadata without the groups' attributes (``meta``, ``meta:<group>``: the consolidated
    metadata of the nodes below it, which a run stopped before consolidating would lack)."""
    root = pathlib.Path(path)
    out = {}
    groups = []
    for f in sorted(root.rglob("*")):
        if not f.is_file():
            continue
        if f.name == "zarr.json":
            meta = json.loads(f.read_text())
            if meta.get("node_type") == "group":
                groups.append(f.parent)
                label = "meta" if f.parent == root else f"meta:{f.parent.relative_to(root)}"
                out[label] = json.dumps(_structure(meta), sort_keys=True)
                continue
        out[str(f.relative_to(root))] = hashlib.sha256(f.read_bytes()).hexdigest()
    for g in groups:
        attrs = dict(zarr.open_group(str(root), mode="r", path=str(g.relative_to(root)) or None).attrs) if g != root \
            else dict(zarr.open_group(str(root), mode="r").attrs)
        label = "attrs" if g == root else f"attrs:{g.relative_to(root)}"
        out[label] = json.dumps({k: v for k, v in attrs.items() if k not in VOLATILE}, sort_keys=True)
    return out


def flags(path, group=None) -> np.ndarray:
    """The completion flags of a store (or of a pipeline stage), 1 = done; empty if not readable yet."""
    from tubeid.runner.store import BOOKKEEPING, FLAG

    node = f"{group}/{BOOKKEEPING}" if group else BOOKKEEPING
    try:
        g = zarr.open_group(str(path), mode="r", path=node, use_consolidated=False)
        return (np.asarray(g[FLAG][...]) != 0).astype(np.uint8)
    except Exception:
        return np.zeros(0)


def clear_flag(path, index, group=None) -> None:
    """Mark block ``index`` of a store (or of a pipeline stage) not done, as a run stopped before it finished."""
    from tubeid.runner.store import set_flags

    set_flags(path, [tuple(index)], 0, group)
