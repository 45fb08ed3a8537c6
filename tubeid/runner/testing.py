"""Helpers for testing the runner (and studies built on it): a small realisation-bound test study, store digests."""

from __future__ import annotations

import hashlib
import json
import pathlib

import numpy as np
import zarr

__all__ = ["STUDY", "write_study", "store_digest", "flags"]

# A realisation-bound study whose tasks take ~0.1-0.3 s (sleep-free compute loop). The random
# stream of a point is keyed by its realisation only, and x = delta * (a function of that stream),
# so delta = 0.2 must equal exactly 2 x delta = 0.1 (common random numbers). FAIL_AT (environment)
# makes the block containing that realisation raise: a controllable interruption.
STUDY = '''
import os
import numpy as np
from tubeid.runner.study import Output, Parameter, Study

def task(block, rng, *, work, label="x"):
    fail_at = os.environ.get("TUBEID_TEST_FAIL_AT")
    if fail_at is not None and int(fail_at) in block["realisation"]:
        raise RuntimeError("interrupted on purpose")
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


VOLATILE = {"started", "finished", "runs", "study_file"}


def store_digest(path) -> dict:
    """Byte digest of every file of a store except the root metadata, plus its non-volatile attrs."""
    root = pathlib.Path(path)
    out = {}
    for f in sorted(root.rglob("*")):
        if f.is_file() and f != root / "zarr.json":
            out[str(f.relative_to(root))] = hashlib.sha256(f.read_bytes()).hexdigest()
    attrs = dict(zarr.open_group(str(root), mode="r").attrs)
    out["attrs"] = json.dumps({k: v for k, v in attrs.items() if k not in VOLATILE}, sort_keys=True)
    return out


def flags(path) -> np.ndarray:
    try:
        return np.asarray(zarr.open_group(str(path), mode="r")["block_done"][...])
    except Exception:
        return np.zeros(0)
