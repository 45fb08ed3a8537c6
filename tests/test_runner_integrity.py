"""A store that proves its contents: block checksums, `status --verify`, repair by recomputing exactly the
damaged blocks, `show` on a damaged store, checked output values, CF metadata and a hidden bookkeeping
group, `--overwrite` that removes only what tubeid wrote, typed parameters.

Blocks run in this process (``workers=0``, the same ``run_block`` the workers run). Every repaired store
is compared byte for byte (chunk files and non-volatile metadata) with an undamaged run.
"""

import json
import os
import pathlib
import shutil

import numpy as np
import pytest
import xarray as xr
import zarr

from tubeid.errors import SpecificationError
from tubeid.runner import integrity
from tubeid.runner.cli import main as cli
from tubeid.runner.execute import run
from tubeid.runner.store import (BOOKKEEPING, FLAG, MANIFEST_NAME, REFERENCES, open_results, read_attrs, read_flags,
                                 store_status)
from tubeid.runner.study import Output, Parameter, Study
from tubeid.runner.testing import flags, store_digest, write_pipeline, write_study

# 2 deltas x 8 realisations in blocks of (1, 2): 8 blocks; outputs x (float, extra dim) and count (int32)
SIZE = dict(realisations=8, chunk=2, work=2)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    d = tmp_path_factory.mktemp("ref")
    study = write_study(d, **SIZE)
    run(study, d / "ref.zarr", workers=0, quiet=True)
    return study, d / "ref.zarr", store_digest(d / "ref.zarr")


def _copy(reference, tmp_path) -> pathlib.Path:
    store = tmp_path / "s.zarr"
    shutil.copytree(reference[1], store)
    return store


def _garbage(f: pathlib.Path) -> None:
    f.write_bytes(b"\x28\xb5\x2f\xfd not zstd at all" + os.urandom(16))


def _rewrite_values(store: pathlib.Path) -> None:
    """Valid chunk bytes holding other values (x of block (1, 2) scaled by 2), flag left as it was."""
    arr = zarr.open_group(str(store), mode="r+", use_consolidated=False)["x"]
    arr[1:2, 4:6] = 2.0 * arr[1:2, 4:6]


def _swap_blocks(store: pathlib.Path) -> None:
    """Blocks (0, 1) and (0, 2) swapped whole: their data chunks and their flags (a copy gone wrong)."""
    for a, b in (("x/c/0/1/0", "x/c/0/2/0"), ("count/c/0/1", "count/c/0/2"),
                 (f"{BOOKKEEPING}/{FLAG}/c/0/1", f"{BOOKKEEPING}/{FLAG}/c/0/2")):
        (store / a).rename(store / "swap.tmp")
        (store / b).rename(store / a)
        (store / "swap.tmp").rename(store / b)


def _nan_values(store: pathlib.Path) -> None:
    """Valid chunk bytes of block (0, 2) of x holding NaN (what a careless edit or a failed copy may leave)."""
    arr = zarr.open_group(str(store), mode="r+", use_consolidated=False)["x"]
    arr[0:1, 4:5] = np.nan  # half the block: the chunk stays (a chunk of fill values only would be removed)


# damage -> (what verification names, blocks the repairing run computes, of which found damaged by verification)
DAMAGE = {
    "deleted data chunk": (lambda s: (s / "x/c/0/3/0").unlink(), "block (0, 3): checksum mismatch: chunk x/c/0/3/0 missing", 1, 1),
    "garbage data chunk": (lambda s: _garbage(s / "count/c/1/1"), "block (1, 1): chunk count/c/1/1 undecodable", 1, 1),
    # an integer chunk deleted reads as the fill value 0, not NaN
    "deleted integer chunk": (lambda s: (s / "count/c/1/2").unlink(), "block (1, 2): checksum mismatch: chunk count/c/1/2 missing", 1, 1),
    "changed values": (_rewrite_values, "block (1, 2): checksum mismatch: values differ from what the block wrote", 1, 1),
    # the values are intact but each sits at the other block's coordinates
    "blocks swapped whole": (_swap_blocks, "block (0, 1): checksum mismatch: values differ from what the block wrote", 2, 2),
    "values overwritten with NaN": (_nan_values, "block (0, 2): checksum mismatch: values differ from what the block wrote", 1, 1),
    "deleted array": (lambda s: shutil.rmtree(s / "x"), "array x missing", 8, 8),
    "garbage flag chunk": (lambda s: _garbage(s / BOOKKEEPING / FLAG / "c/0/1"), "block (0, 1): flag chunk undecodable", 1, 1),
    # unproven blocks are recomputed (none is "damaged": there is no flag to check them against)
    "deleted flags": (lambda s: shutil.rmtree(s / BOOKKEEPING / FLAG), "flag array _tubeid/block_done unreadable", 8, 0),
    # metadata and coordinates are rewritten from the study; the blocks are intact
    "deleted coordinate chunk": (lambda s: (s / "realisation/c/0").unlink(), "coordinate realisation changed", 0, 0),
    "garbage array metadata": (lambda s: (s / "count/zarr.json").write_text("{not json"), "array count missing or unreadable", 0, 0),
}


@pytest.mark.parametrize("damage", sorted(DAMAGE))
def test_damage_is_named_and_exactly_the_damaged_blocks_are_recomputed(reference, tmp_path, capsys, damage):
    study, _, ref_digest = reference
    store = _copy(reference, tmp_path)
    do, named, computed, repaired = DAMAGE[damage]
    do(store)
    # status --verify names it and exits 1; plain status never tracebacks
    assert cli(["status", str(store), "--verify"]) == 1
    out = capsys.readouterr().out
    assert named in out and "DAMAGED" in out
    # show never tracebacks on a damaged chunk
    assert cli(["show", str(store)]) == 0
    out = capsys.readouterr().out
    if damage == "garbage data chunk":
        assert "count [1]: DAMAGED" in out and "count/c/1/1" in out
    # ... and names a deleted chunk or array (read as NaN, or 0 for integers), beside the statistics
    shown = {"deleted data chunk": "DAMAGED: block (0, 3): checksum mismatch: chunk x/c/0/3/0 missing",
             "deleted integer chunk": "DAMAGED: block (1, 2): checksum mismatch: chunk count/c/1/2 missing",
             "deleted array": "DAMAGED: block (0, 0): array x missing",
             "values overwritten with NaN": "DAMAGED: block (0, 2): checksum mismatch: values differ"}
    if damage in shown:
        assert shown[damage] in out, out
    # a plain run (no --overwrite) repairs: exactly the damaged blocks are recomputed
    report = run(study, store, workers=0, quiet=True)
    assert (report.computed, report.repaired) == (computed, repaired)
    assert store_digest(store) == ref_digest
    assert cli(["status", str(store), "--verify"]) == 0
    assert "verified: blocks: 8 finished blocks match their checksums" in capsys.readouterr().out


def test_a_store_of_an_earlier_checksum_rule_is_recomputed_and_not_called_damaged(reference, tmp_path, capsys):
    study, _, ref_digest = reference
    store = _copy(reference, tmp_path)
    g = zarr.open_group(str(store / BOOKKEEPING), mode="r+", use_consolidated=False)
    g.attrs["checksum"] = "first 64 bits of SHA-256 over the outputs (an earlier rule)"
    f = g[FLAG]
    f[...] = f[...] ^ np.uint64(1)  # the checksums of another rule: other nonzero values
    assert integrity.verify(store).other_rule == "first 64 bits of SHA-256 over the outputs (an earlier rule)"
    report = run(study, store, workers=0)
    err = capsys.readouterr().err
    assert "made by an earlier tubeid's rule" in err and "8 of 8 finished blocks" in err and "damaged" not in err, err
    assert (report.computed, report.repaired) == (8, 8)
    assert store_digest(store) == ref_digest  # the same values, now under this tubeid's rule
    assert integrity.verify(store).ok and integrity.verify(store).other_rule is None
    assert "damaged" not in read_attrs(store, BOOKKEEPING).get("history", "") + read_attrs(store).get("history", "")


def test_no_verify_trusts_the_flags(reference, tmp_path):
    study = reference[0]
    store = _copy(reference, tmp_path)
    (store / "x/c/0/3/0").unlink()
    report = run(study, store, workers=0, quiet=True, verify_blocks=False)
    assert report.computed == 0 and np.isnan(open_results(store).x.values[0, 6:8]).all()  # told not to look
    assert run(study, store, workers=0, quiet=True).computed == 1
    assert store_digest(store) == reference[2]


def test_checksums_are_of_the_values_written():
    a = {"x": np.arange(6.0).reshape(2, 3), "n": np.array([1, 2], dtype="int32")}
    c = integrity.block_checksum(a, (0, 1))
    assert c != 0 and c == integrity.block_checksum({"n": a["n"].copy(), "x": a["x"].copy()}, [0, 1])  # order-free
    assert integrity.block_checksum(a, (1, 0)) != c  # the same values at another block
    x2 = a["x"].copy()
    x2[1, 2] = np.nextafter(x2[1, 2], np.inf)
    for changed in ({"x": x2, "n": a["n"]},                                                   # one value, by one ulp
                    {"x": a["x"].reshape(3, 2), "n": a["n"]},                               # same bytes, other shape
                    {"x": a["x"], "n": a["n"].astype("int64")},                              # same values, other dtype
                    {"y": a["x"], "n": a["n"]}):                                             # other name
        assert integrity.block_checksum(changed, (0, 1)) != c
    assert integrity.values_checksum([1, 2]) == integrity.values_checksum(np.array([1.0, 2.0]))
    assert integrity.values_checksum(["a", "b"]) != integrity.values_checksum(["ab"])


def test_flags_carry_the_checksums_of_the_stored_blocks(reference):
    study, store, _ = reference
    f, bad = read_flags(store)
    assert bad == [] and f.dtype == np.uint64 and (f != 0).all()
    ds = xr.open_zarr(store)
    x, count = ds.x.values, ds["count"].values
    for i, j in np.ndindex(*f.shape):
        block = {"x": x[i:i + 1, 2 * j:2 * j + 2], "count": count[i:i + 1, 2 * j:2 * j + 2]}
        assert int(f[i, j]) == integrity.block_checksum(block, (i, j))


def test_a_pipeline_stage_is_verified_and_repaired(tmp_path, capsys):
    path = write_pipeline(tmp_path, curve=4, around=4)
    run(path, tmp_path / "ref.zarr", workers=0, quiet=True)
    store = tmp_path / "p.zarr"
    shutil.copytree(tmp_path / "ref.zarr", store)
    (store / "curve/y/c/0/1").unlink()
    _garbage(store / "around" / BOOKKEEPING / FLAG / "c/0/0")
    assert cli(["status", str(store), "--verify"]) == 1
    out = capsys.readouterr().out
    assert "stage curve" in out and "chunk curve/y/c/0/1 missing" in out and "block (0, 0): flag chunk undecodable" in out
    report = run(path, store, workers=0, quiet=True)
    assert report.stages["curve"].computed == 1 and report.stages["around"].computed == 1
    assert report.stages["final"].computed == 0 and report.repaired == 2
    assert store_digest(store) == store_digest(tmp_path / "ref.zarr")
    assert store_status(store)["complete"]


# -- values a block returns are checked before anything is written ------------------------------------------------
def _values_study(values, dtype="float64", finite=True):
    def task(block, rng):
        out = np.zeros(len(block["r"]))
        if 4 in block["r"]:
            out = np.asarray(values, dtype=np.asarray(values).dtype)
        return {"y": out}

    return Study(name="v", seed=1, axes={"r": range(6)}, chunks={"r": 2}, task=task,
                 outputs={"y": Output(dtype=dtype, finite=finite)})


@pytest.mark.parametrize("values, dtype, rule", [
    ([1.0, np.nan], "float64", "must be finite"),
    ([np.inf, 1.0], "float32", "must be finite"),
    ([1e39, 0.0], "float32", "a value overflows it"),                    # finite in float64, inf in float32
    ([127, 128], "int8", "must lie in [-128, 127], the range of int8 (not wrapped)"),
    ([-1, 0], "uint16", "must lie in [0, 65535]"),
    ([1.5, 2.0], "int32", "must be whole numbers"),
    ([np.nan, 1.0], "int64", "cannot hold NaN"),
    ([2, 0], "bool", "must be 0 or 1"),
    ([2.0**63, 0.0], "int64", "must lie in [-9223372036854775808, 9223372036854775807]"),  # max rounds up to 2**63
    ([2.0**64, 1.0], "uint64", "must lie in [0, 18446744073709551615]"),
])
def test_bad_block_values_are_refused_naming_output_block_and_rule(values, dtype, rule):
    s = _values_study(values, dtype)
    s.compute_block(s.block((0,)))  # zeros: fine
    with pytest.raises(SpecificationError) as err:
        s.compute_block(s.block((2,)))
    assert err.value.field == "outputs.y" and rule in err.value.rule and "block (2,)" in str(err.value)
    assert "np." not in str(err.value), str(err.value)  # the value as a plain number, not np.int64(128)


def test_a_refused_block_is_not_marked_done_and_declared_nonfinite_values_are_stored(tmp_path, capsys):
    src = tmp_path / "bad.py"
    src.write_text('''
import numpy as np
from tubeid.runner import Output, Parameter, Study
def task(block, rng, *, finite):
    y = np.asarray(block["r"], float)
    y[block["r"] == 3] = np.nan
    return {"y": y}
study = Study(name="bad", seed=0, axes={"r": range(6)}, chunks={"r": 2}, task=task,
              outputs={"y": Output(finite=FINITE)}, parameters={"finite": FINITE})
''')
    src.write_text(src.read_text().replace("FINITE", "True"))
    with pytest.raises(SpecificationError, match=r"outputs.y = .*block \(1,\).*must be finite"):
        run(src, tmp_path / "b.zarr", workers=0, quiet=True)
    np.testing.assert_array_equal(flags(tmp_path / "b.zarr"), [1, 0, 0])  # block 1 failed: not done
    src.write_text(src.read_text().replace("True", "False"))
    run(src, tmp_path / "ok.zarr", workers=0, quiet=True)
    y = open_results(tmp_path / "ok.zarr").y.values
    assert np.isnan(y[3]) and np.array_equal(y[[0, 1, 2, 4, 5]], [0, 1, 2, 4, 5])
    assert cli(["status", str(tmp_path / "ok.zarr"), "--verify"]) == 0  # NaN is a value, checksummed like any
    assert cli(["show", str(tmp_path / "ok.zarr")]) == 0 and "DAMAGED" not in capsys.readouterr().out


# -- what a plain xarray user sees -------------------------------------------------------------------------------
def test_stores_show_only_science_with_cf_metadata(reference, tmp_path):
    ds = xr.open_zarr(reference[1])
    assert set(ds.variables) == {"x", "count", "delta", "realisation", "component"}
    assert not any(d.startswith("block_") for d in ds.dims)
    assert ds.attrs["Conventions"].startswith("CF-") and ds.attrs["references"] == REFERENCES
    assert ds.attrs["title"] == "runner-test" and "created by `tubeid run" in ds.attrs["history"]
    for name, var in ds.variables.items():
        assert var.attrs.get("long_name"), name
        if var.dtype.kind in "iuf":
            assert "units" in var.attrs, name
    assert ds.realisation.attrs == {"units": "1", "long_name": "Monte Carlo realisation index"}
    assert ds.component.attrs == {"long_name": "component"}  # a label: no units (CF)
    assert ds.delta.attrs["units"] == "1"  # declared by the study
    # the bookkeeping is a sub-group
    assert xr.open_zarr(reference[1], group=BOOKKEEPING)[FLAG].dims == ("block_delta", "block_realisation")
    assert set(open_results(reference[1], flags=True)[FLAG].dims) == {"block_delta", "block_realisation"}
    # a pipeline stage likewise
    path = write_pipeline(tmp_path, curve=2, around=2)
    run(path, tmp_path / "p.zarr", workers=0, quiet=True, overrides={"size": "quick"})
    st = xr.open_zarr(tmp_path / "p.zarr", group="curve")
    assert set(st.variables) == {"y", "x", "realisation"} and st.attrs["Conventions"].startswith("CF-")
    history = xr.open_zarr(tmp_path / "p.zarr", group="curve").attrs["history"].splitlines()
    assert history[0].endswith("stage curve of pipeline pipeline-test created") and "stage complete" in history[-1]


def test_coordinate_metadata_comes_from_the_study_or_the_defaults():
    def task(block, rng):
        return {"y": np.zeros((len(block["realisation"]), len(block["speed"])))}

    s = Study(name="m", seed=0, axes={"realisation": range(2), "speed": [1.0, 2.0]}, task=task,
              outputs={"y": Output()}, units={"speed": "m/s"}, long_names={"speed": "flow speed", "realisation": "draw"})
    assert s.coordinate_attrs("speed") == {"units": "m/s", "long_name": "flow speed"}
    assert s.coordinate_attrs("realisation") == {"units": "1", "long_name": "draw"}
    for field, kw in (("long_names.nope", dict(long_names={"nope": "x"})), ("units.nope", dict(units={"nope": "m"}))):
        with pytest.raises(SpecificationError) as err:
            Study(name="m", seed=0, axes={"r": range(2)}, task=lambda b, rng: {"y": np.zeros(2)}, outputs={"y": Output()}, **kw)
        assert err.value.field == field
    with pytest.raises(SpecificationError, match="reserved"):
        Study(name="m", seed=0, axes={"r": range(2)}, task=lambda b, rng: {"y": 0}, outputs={BOOKKEEPING: Output()})


# -- --overwrite removes only what tubeid wrote --------------------------------------------------------------------
def _user_files(root: pathlib.Path, store: pathlib.Path) -> dict[pathlib.Path, bytes]:
    files = {store / "x.csv": b"a user's file named like the output x\n",      # inside the store, named like an output
             store / "x" / "notes.txt": b"inside an output's directory\n",
             store / "count" / "c" / "README": b"inside the chunk directory\n",
             root / "s.zarr.txt": b"beside the store\n",
             root / "x": b"beside, named like an output\n"}
    for f, data in files.items():
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_bytes(data)
    return files


def test_user_files_in_and_beside_a_store_survive_every_runner_command(tmp_path, capsys):
    study = write_study(tmp_path, **SIZE)
    store = tmp_path / "s.zarr"
    store.mkdir()
    files = _user_files(tmp_path, store)
    # a directory holding only a user's files is not a store: refused, untouched
    assert cli(["run", str(study), "--store", str(store), "--workers", "0", "--no-progress"]) == 2
    assert "not a tubeid study store" in capsys.readouterr().err
    assert cli(["run", str(study), "--store", str(store), "--workers", "0", "--no-progress", "--overwrite"]) == 2
    assert all(f.read_bytes() == d for f, d in files.items())
    for f in files:
        if store in f.parents:
            f.unlink()
    for d in sorted((p for p in store.rglob("*") if p.is_dir()), key=lambda p: -len(p.parts)):
        d.rmdir()
    # a store made by tubeid, then the user's files put in it and beside it
    assert cli(["run", str(study), "--store", str(store), "--workers", "0", "--no-progress"]) == 0
    files = _user_files(tmp_path, store)
    user_group = xr.Dataset({"mine": ("k", np.arange(3.0))})
    user_group.to_zarr(store, group="analysis", mode="w", consolidated=False)
    commands = [["run", str(study), "--store", str(store)],                                   # resume: complete
                ["status", str(store)], ["status", str(store), "--verify"], ["show", str(store)],
                ["run", str(study), "--store", str(store), "--overwrite"],                     # same study, replaced
                ["run", str(study), "--store", str(store), "--set", "work=3"],                 # refused: other study
                ["run", str(study), "--store", str(store), "--set", "work=3", "--new-store"],
                ["run", str(study), "--store", str(store), "--set", "work=3", "--overwrite"]]  # other study
    for cmd in commands:
        extra = ["--workers", "0", "--no-progress"] if cmd[0] == "run" else []
        cli(cmd + extra)
        assert all(f.read_bytes() == d for f, d in files.items()), cmd
        np.testing.assert_array_equal(xr.open_zarr(store, group="analysis", consolidated=False).mine.values, [0.0, 1.0, 2.0])
    err = capsys.readouterr().err
    # the user's 3 files in the store and the 3 files of their zarr group
    assert "--overwrite kept 6 file(s) tubeid did not write" in err and "analysis/mine/c/0" in err and "x.csv" in err
    ds = open_results(store)
    assert (ds["count"].values == 3).all() and cli(["status", str(store), "--verify"]) == 0
    manifest = json.loads((store / MANIFEST_NAME).read_text())["nodes"]
    assert "analysis" not in manifest and manifest["x"] == "array"


def test_a_store_without_manifest_is_not_deleted(reference, tmp_path):
    store = _copy(reference, tmp_path)
    (store / MANIFEST_NAME).unlink()
    before = store_digest(store)
    with pytest.raises(SpecificationError, match="no manifest"):
        run(reference[0], store, workers=0, quiet=True, overwrite=True)
    assert store_digest(store) == before


@pytest.mark.parametrize("entry", ["../victim.zarr/data", "absolute", "symlink"])
def test_a_manifest_naming_files_outside_the_store_deletes_nothing(reference, tmp_path, entry):
    """An edited manifest is no proof: a node outside the store (``..``, absolute, through a symlink) is refused."""
    victim = tmp_path / "victim.zarr"  # a user's Zarr store beside the tubeid store
    zarr.open_group(str(victim), mode="w").create_array("data", data=np.arange(10.0), chunks=(5,))
    before = store_digest(victim)
    store = _copy(reference, tmp_path)
    manifest = json.loads((store / MANIFEST_NAME).read_text())
    if entry == "absolute":
        entry = str(victim / "data")
    elif entry == "symlink":
        (store / "mine").symlink_to(victim / "data", target_is_directory=True)
        entry = "mine"
    manifest["nodes"][entry] = "array"
    (store / MANIFEST_NAME).write_text(json.dumps(manifest))
    kept = store_digest(store)
    with pytest.raises(SpecificationError, match="outside the store"):
        run(reference[0], store, workers=0, quiet=True, overwrite=True)
    assert store_digest(victim) == before and (victim / "zarr.json").is_file() and store_digest(store) == kept


@pytest.mark.parametrize("damage, rule", [
    ("root metadata deleted", "is not a tubeid study store"), ("root metadata garbage", "is not a readable Zarr store"),
    ("garbage lock file", "unreadable lock file"), ("empty lock file", "unreadable lock file")])
def test_damage_a_runner_cannot_repair_is_refused_and_nothing_is_deleted(reference, tmp_path, damage, rule):
    """Without the root's provenance the store cannot be proven to be this study's; a lock file nobody can read
    cannot be proven stale: both are refused by name, every file left as it was."""
    from tubeid.runner.lock import LOCK_NAME

    store = _copy(reference, tmp_path)
    {"root metadata deleted": lambda: (store / "zarr.json").unlink(),
     "root metadata garbage": lambda: (store / "zarr.json").write_text("{garbage"),
     "garbage lock file": lambda: (store / LOCK_NAME).write_text("{garbage"),
     "empty lock file": lambda: (store / LOCK_NAME).write_text("")}[damage]()
    before = {f: f.read_bytes() for f in store.rglob("*") if f.is_file()}
    with pytest.raises(SpecificationError, match=rule):
        run(reference[0], store, workers=0, quiet=True)
    assert {f: f.read_bytes() for f in store.rglob("*") if f.is_file()} == before


# -- parameters are typed --------------------------------------------------------------------------------------------
def test_parameter_values_must_have_the_declared_or_default_type(tmp_path, capsys):
    def task(block, rng, *, n, scale, label, flag, items, anything):
        return {"y": np.zeros(len(block["r"]))}

    s = Study(name="t", seed=0, axes={"r": range(2)}, task=task, outputs={"y": Output()},
              parameters={"n": 3, "scale": 0.5, "label": "a", "flag": False, "items": [1, 2], "anything": None})
    assert s.with_parameters({"scale": 2}).values["scale"] == 2.0  # an int is a number: stored as float
    assert type(s.with_parameters({"scale": 2}).values["scale"]) is float
    for name, value, rule in (("n", 2.5, "must be an integer (the default is 3)"), ("n", "3", "must be an integer"),
                              ("n", True, "must be an integer"), ("scale", "big", "must be a number"),
                              ("label", 1, "must be a string"), ("flag", 1, "must be a boolean"),
                              ("items", 3, "must be a list")):
        with pytest.raises(SpecificationError) as err:
            s.with_parameters({name: value})
        assert err.value.field == f"parameters.{name}" and rule in err.value.rule
    assert s.with_parameters({"anything": "x"}).values["anything"] == "x"  # None: any plain value
    assert Parameter(1, type=float).check("p", 2) == 2.0
    # NumPy defaults and choices are shown as plain numbers (NumPy 2's repr: np.float64(0.5))
    with pytest.raises(SpecificationError) as err:
        Parameter(np.float64(0.5)).check("p", "x")
    assert err.value.rule == "must be a number (the default is 0.5)"
    with pytest.raises(SpecificationError) as err:
        Parameter(1, choices=np.arange(3)).check("p", 5)
    assert err.value.rule == "must be one of [0, 1, 2]"
    with pytest.raises(SpecificationError, match="must be a number"):
        Parameter(None, type=float).check("p", "x")
    # the CLI refuses before anything is written: no store, no lock left behind
    study = write_study(tmp_path, **SIZE)
    store = tmp_path / "typed.zarr"
    assert cli(["run", str(study), "--store", str(store), "--workers", "0", "--set", "work=2.5"]) == 2
    assert "parameters.work = 2.5: must be an integer (the default is 2)" in capsys.readouterr().err
    assert not store.exists()
