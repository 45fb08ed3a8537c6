"""The Zarr store of a study: layout, provenance, per-block writes and completion flags.

Layout: one variable per output with dims (study axes..., extra dims...), chunked exactly by
blocks along the axes (whole along extra dims), so each block owns whole chunks; a ``block_done``
(uint8) variable with dims ``block_<axis>`` and one chunk per block, written after the block's
data. Unwritten float chunks read as NaN (the fill value). The root attributes hold the
provenance: ``tubeid_version``, ``study_name``, ``study_file``, ``study_source``, ``study_hash``,
``seed``, ``seed_axes``, ``parameters`` (JSON), ``model_specification``, ``started`` (first start,
UTC ISO 8601), ``runs`` (every start), ``finished`` ('' until complete), and the values returned by
the study's ``summarize`` (names listed in ``summary_keys``).

A pipeline store holds the same layout once per stage, in a Zarr group named after the stage
(``xarray.open_zarr(store, group="delta")``), whose attributes hold the stage's provenance
(``stage_name``, ``stage_hash``, ``pipeline_hash``, seeds, parameters, times, summary). The root
group holds no arrays; its attributes hold the pipeline provenance (``format`` =
``tubeid-pipeline-store/1``, source, hash, seed, parameters, ``stages``, ``stage_status``, times).
Metadata is consolidated per group and at the root after every metadata change.
"""

from __future__ import annotations

import datetime
import json
import os
import pathlib
import shutil
import tempfile
import warnings
from typing import TYPE_CHECKING

import numpy as np
import zarr

from tubeid.errors import SpecificationError

if TYPE_CHECKING:  # imported where used: `tubeid status` needs no xarray
    import xarray as xr

__all__ = ["init_store", "init_pipeline_store", "init_stage", "check_store", "check_stage", "check_blocks", "block_flags",
           "write_block", "update_attrs", "read_attrs", "open_results", "open_pipeline", "store_status",
           "pipeline_status", "is_pipeline", "prepare_path", "FLAG", "now"]

FLAG = "block_done"
FORMAT = "tubeid-study-store/1"
PIPELINE_FORMAT = "tubeid-pipeline-store/1"
STAGE_FORMAT = "tubeid-pipeline-stage/1"


def now() -> str:
    """Current UTC time, ISO 8601 to the millisecond."""
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="milliseconds")


def tubeid_version() -> str:
    try:
        from importlib.metadata import version

        return version("tubeid")
    except Exception:  # not installed (running from a source tree)
        return "unknown"


def _consolidate(path, group=None):
    """Consolidate the metadata of ``group`` (if any), then of the root (which nests every group's)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Consolidated metadata", category=UserWarning)
        if group:
            zarr.consolidate_metadata(str(path), path=group)
        zarr.consolidate_metadata(str(path))


def _group(path, group=None, mode="r"):
    return zarr.open_group(str(path), mode=mode, path=group) if group else zarr.open_group(str(path), mode=mode)


def _flag_dims(study):
    return tuple(f"block_{d}" for d in study.axes)


def prepare_path(path) -> pathlib.Path:
    """Refuse up front a store path that cannot be written (missing rights, a file in the way)."""
    p = pathlib.Path(path)
    if p.exists() and not p.is_dir():
        raise SpecificationError("store", str(p), "exists and is not a directory (Zarr store)")
    target = p if p.exists() else p.parent
    while not target.exists():  # the nearest existing ancestor must let us create the rest
        target = target.parent
    try:
        fd, probe = tempfile.mkstemp(prefix=".tubeid-probe-", dir=target)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise SpecificationError("store", str(p), f"is not writable ({exc.strerror} in {target})") from exc
    return p


def check_store(path, study_hash: str) -> str:
    """``"new"`` if there is no store at ``path``; ``"resume"`` if it holds this study; else refuse."""
    p = pathlib.Path(path)
    if not p.exists() or (p.is_dir() and not any(p.iterdir())):
        return "new"
    try:
        attrs = dict(zarr.open_group(str(p), mode="r").attrs)
    except Exception as exc:
        raise SpecificationError("store", str(p), f"exists but is not a Zarr store ({exc}); choose another path or --overwrite") from exc
    if attrs.get("format") not in (FORMAT, PIPELINE_FORMAT):
        raise SpecificationError("store", str(p), "exists but is not a tubeid study store; choose another path or --overwrite")
    if attrs.get("study_hash") != study_hash:
        raise SpecificationError(
            "store", str(p),
            f"was made by a different study definition (study {attrs.get('study_name')!r}, hash "
            f"{str(attrs.get('study_hash'))[:12]} here vs {study_hash[:12]} now); refusing to mix them: "
            "use --new-store to write a new store beside it or --overwrite to replace it")
    return "resume"


def _remove_store(p: pathlib.Path) -> None:
    """Delete ``p`` only if it is empty or a tubeid store: ``--overwrite`` never deletes anything else."""
    if not p.exists():
        return
    if p.is_dir() and any(p.iterdir()):
        try:
            fmt = read_attrs(p).get("format")
        except Exception:  # not a zarr group at all
            fmt = None
        if fmt not in (FORMAT, PIPELINE_FORMAT):
            raise SpecificationError("store", str(p), "exists and is not a tubeid store: refusing to delete it (choose another --store)")
    if p.is_dir():
        shutil.rmtree(p)
    else:
        raise SpecificationError("store", str(p), "is a file, not a store directory")


def _fresh_root(path, fmt: str, definition, *, source: str, study_hash: str, study_file: str, overrides) -> tuple[pathlib.Path, dict]:
    """Remove any store at ``path`` and return it with the provenance shared by study and pipeline roots."""
    p = pathlib.Path(path)
    _remove_store(p)
    p.parent.mkdir(parents=True, exist_ok=True)
    t = now()
    return p, {
        "format": fmt,
        "title": definition.description or definition.name,
        "tubeid_version": tubeid_version(),
        "study_name": definition.name,
        "study_file": str(study_file),
        "study_hash": study_hash,
        "study_source": source,
        "seed": int(definition.seed),
        "parameters": json.dumps(definition.values, sort_keys=True),
        "parameter_overrides": json.dumps(dict(overrides or {}), sort_keys=True),
        "started": t,
        "runs": [t],
        "finished": "",
    }


def init_store(study, path, *, source: str, study_hash: str, study_file: str = "", overrides=None) -> None:
    """Create the store: coordinates, empty (lazy) outputs, zero flags and provenance; no data computed."""
    p, attrs = _fresh_root(path, FORMAT, study, source=source, study_hash=study_hash, study_file=study_file, overrides=overrides)
    attrs.update(seed_axes=list(study.seed_axes), model_specification=study.describe_model())
    _write_empty(study, p, attrs)


def _write_empty(study, p, attrs, group=None) -> None:
    """Write coordinates, lazy empty outputs and zero flags of ``study`` (at the root or in ``group``)."""
    import dask.array as da
    import xarray as xr

    axes = list(study.axes)
    block_chunks = tuple(study.chunks[d] for d in axes)
    data_vars = {}
    for name, out in study.outputs.items():
        extra = tuple(study.coords[d].size for d in out.dims)
        arr = da.empty(study.shape + extra, chunks=block_chunks + extra, dtype=out.dtype)
        out_attrs = {k: v for k, v in (("units", out.units), ("long_name", out.long_name)) if v}
        data_vars[name] = (tuple(axes) + out.dims, arr, out_attrs)
    data_vars[FLAG] = (_flag_dims(study), da.zeros(study.block_grid, chunks=1, dtype="u1"),
                       {"long_name": "block completion flag (1 = written)", "chunks": list(block_chunks)})
    coords = {}
    for dim, values in {**study.axes, **study.coords}.items():
        c_attrs = {"units": study.units[dim]} if dim in study.units else {}
        if values.dtype.kind == "U":  # variable-length strings (fixed-width UTF-32 has no Zarr v3 spec)
            values = values.astype(object)
        coords[dim] = (dim, values, c_attrs)
    ds = xr.Dataset(data_vars, coords=coords, attrs=attrs)
    if group:
        ds.to_zarr(str(p), group=group, mode="w", compute=False, consolidated=False)
    else:
        ds.to_zarr(str(p), mode="w", compute=False, consolidated=False)
    _consolidate(p, group)


def init_pipeline_store(pipeline, path, *, source: str, study_hash: str, study_file: str = "", overrides=None) -> None:
    """Create a pipeline store: the root group and its provenance (stage groups come later)."""
    p, attrs = _fresh_root(path, PIPELINE_FORMAT, pipeline, source=source, study_hash=study_hash, study_file=study_file, overrides=overrides)
    attrs.update(stages=pipeline.stage_names, stage_status={n: "pending" for n in pipeline.stage_names})
    zarr.open_group(str(p), mode="w", zarr_format=3, attributes=attrs)
    _consolidate(p)


def init_stage(study, path, name: str, *, pipeline_name: str, pipeline_hash: str, stage_hash: str) -> None:
    """Create (or replace) the group of stage ``name``: the layout of a study store, stage provenance."""
    p = pathlib.Path(path)
    if (p / name).exists():
        shutil.rmtree(p / name)
    t = now()
    attrs = {
        "format": STAGE_FORMAT,
        "title": study.description or name,
        "tubeid_version": tubeid_version(),
        "pipeline_name": pipeline_name,
        "pipeline_hash": pipeline_hash,
        "stage_name": name,
        "stage_hash": stage_hash,
        "seed": int(study.seed),
        "stream_key": list(study.stream_key),
        "seed_axes": list(study.seed_axes),
        "parameters": json.dumps(study.values, sort_keys=True),
        "model_specification": study.describe_model(),
        "started": t,
        "runs": [t],
        "finished": "",
    }
    _write_empty(study, p, attrs, group=name)


def check_stage(path, name: str, stage_hash: str) -> str:
    """``"new"`` if stage ``name`` has no group yet; ``"resume"`` if it holds this stage; else refuse."""
    p = pathlib.Path(path) / name
    if not (p / "zarr.json").exists():
        return "new"
    attrs = read_attrs(path, name)
    if attrs.get("stage_hash") != stage_hash:
        raise SpecificationError(
            "store", f"{path} (stage {name})",
            f"holds stage {name!r} built from different inputs (hash {str(attrs.get('stage_hash'))[:12]} here vs "
            f"{stage_hash[:12]} now: an earlier stage's result or the code that derives this stage from it changed); "
            "refusing to mix them: use --new-store or --overwrite")
    return "resume"


def update_attrs(path, group=None, **attrs) -> None:
    """Update the attributes (provenance) of the root or of ``group`` and re-consolidate the metadata."""
    g = _group(path, group, mode="r+")
    g.attrs.update(attrs)
    _consolidate(path, group)


def read_attrs(path, group=None) -> dict:
    return dict(_group(path, group).attrs)


def is_pipeline(path) -> bool:
    return read_attrs(path).get("format") == PIPELINE_FORMAT


def block_flags(path, group=None) -> np.ndarray:
    """The completion flags (uint8 array over the block grid)."""
    return np.asarray(_group(path, group)[FLAG][...])


def _check_blocks(path, study, flag_array, group=None) -> None:
    stored = [int(c) for c in flag_array.attrs.get("chunks", [])]
    now_ = [int(study.chunks[d]) for d in study.axes]
    if stored != now_:
        where = f"{path}" + (f" (stage {group})" if group else "")
        raise SpecificationError(
            "chunks", dict(zip(study.axes, now_)),
            f"{where} was written in blocks of {dict(zip(study.axes, stored))}; a block layout that differs "
            "(e.g. another tubeid.runner.default-chunk / TUBEID_RUNNER__DEFAULT_CHUNK here or on a worker) "
            "would write the wrong regions: use the store's configuration, or --new-store / --overwrite")


def check_blocks(path, study, group=None) -> None:
    """Refuse to resume ``path`` (or its stage ``group``) with a block layout other than the one it was written with."""
    _check_blocks(path, study, _group(path, group)[FLAG], group)


def write_block(path, study, block, outputs, group=None) -> None:
    """Write one block's outputs into their own region (whole chunks), then its completion flag.

    Written with zarr directly into the arrays xarray created (same bytes as an xarray region
    write: no scale/offset encodings are used), which costs a few ms per block instead of ~10.
    The block layout is checked against the store's first (a worker with another default chunk
    size would otherwise write the wrong region).
    """
    g = _group(path, group, mode="r+")
    _check_blocks(path, study, g[FLAG], group)
    region = tuple(block.slices.values())
    for name, arr in outputs.items():
        g[name][region] = arr
    g[FLAG][tuple(block.index)] = 1


def store_status(path, group=None) -> dict:
    """``{"done", "total", "complete", "attrs"}`` of a study store or of one stage of a pipeline store.

    Readable while a run writes it. For a pipeline store without ``group``, see ``pipeline_status``.
    """
    p = pathlib.Path(path)
    if not p.is_dir():
        raise SpecificationError("store", str(path), "no such store")
    try:
        root = read_attrs(p)
    except Exception as exc:
        raise SpecificationError("store", str(path), f"is not a readable tubeid study store ({exc})") from exc
    if group is None and root.get("format") == PIPELINE_FORMAT:
        return pipeline_status(p)
    if group is not None:
        if root.get("format") != PIPELINE_FORMAT:
            raise SpecificationError("group", group, f"{path} is a single-study store (it has no stages)")
        if group not in root.get("stages", []):
            raise SpecificationError("group", group, f"is not a stage of {path} (stages: {root.get('stages')})")
        if not (p / group / "zarr.json").exists():
            raise SpecificationError("group", group, f"stage not started yet in {path}")
    try:
        attrs = read_attrs(p, group) if group else root
        flags = block_flags(p, group)
    except Exception as exc:
        raise SpecificationError("store", str(path), f"is not a readable tubeid study store ({exc})") from exc
    done, total = int(flags.sum()), int(flags.size)
    complete = done == total and (group is None or bool(attrs.get("finished")))
    return {"done": done, "total": total, "complete": complete, "attrs": attrs}


def pipeline_status(path) -> dict:
    """Per-stage status of a pipeline store: ``{"attrs", "stages": {name: {"started", "done", "total",
    "complete"}}, "done", "total", "complete"}`` (blocks summed over the stages started so far)."""
    p = pathlib.Path(path)
    attrs = read_attrs(p)
    stages = {}
    for name in attrs.get("stages", []):
        if (p / name / "zarr.json").exists():
            st = store_status(p, name)
            stages[name] = {"started": True, "done": st["done"], "total": st["total"], "complete": st["complete"]}
        else:
            stages[name] = {"started": False, "done": 0, "total": None, "complete": False}
    return {"attrs": attrs, "stages": stages,
            "done": sum(s["done"] for s in stages.values()), "total": sum(s["total"] or 0 for s in stages.values()),
            "complete": all(s["complete"] for s in stages.values())}


def open_results(path, group: str | None = None, *, flags: bool = False, chunks="auto") -> xr.Dataset:
    """The study results as a labelled ``xarray.Dataset`` (lazy, dask-backed; ``chunks=None``: lazy
    without dask, as ``xarray.open_zarr``).

    Blocks not yet written read as NaN (float outputs). The attributes ``blocks_done`` and
    ``blocks_total`` say how complete the store is; ``flags=True`` keeps the ``block_done`` variable.
    For a pipeline store: ``group=STAGE`` gives that stage's Dataset; without ``group``, a Dataset
    with no variables whose attributes are the pipeline provenance plus ``stage_blocks``
    ({stage: [done, total or None]}) and ``stages_complete`` (list of complete stages).
    """
    import xarray as xr

    st = store_status(path, group)
    if "stages" in st and group is None:
        ds = xr.Dataset(attrs=dict(st["attrs"]))
        ds.attrs.update(stage_blocks={n: [s["done"], s["total"]] for n, s in st["stages"].items()},
                        stages_complete=[n for n, s in st["stages"].items() if s["complete"]])
        return ds
    ds = xr.open_zarr(str(path), group=group, chunks=chunks) if group else xr.open_zarr(str(path), chunks=chunks)
    if not flags:
        ds = ds.drop_vars(FLAG)
    ds.attrs.update(blocks_done=st["done"], blocks_total=st["total"])
    return ds


def open_pipeline(path) -> dict[str, xr.Dataset]:
    """``{stage name: Dataset}`` of every stage of a pipeline store started so far, in order."""
    st = store_status(path)
    if "stages" not in st:
        raise SpecificationError("store", str(path), "is a single-study store, not a pipeline (use open_results)")
    return {name: open_results(path, name) for name, s in st["stages"].items() if s["started"]}
