"""The store is never left wrong by a kill, a full disk, a link or a task an earlier run left running.

Each interruption is a SIGKILL at one point of the runner (a subprocess whose one function is patched
to kill it there, as `kill -9` would), then the same command again: the store must end byte-identical
(:func:`tubeid.runner.testing.store_digest`: chunk files, non-volatile attributes and the consolidated
metadata) to an uninterrupted run. Blocks run in the runner's process (``--workers 0``, the same
``run_block`` the workers run); an orphaned task of a killed run on an external cluster is in
``test_runner_distributed.py``.
"""

import errno
import json
import os
import pathlib
import resource
import shutil
import signal
import subprocess
import sys
import textwrap

import pytest

from tubeid.errors import SpecificationError
from tubeid.runner import integrity
from tubeid.runner.cli import main as cli
from tubeid.runner.execute import run, run_block, run_stage_block, stage_study
from tubeid.runner.store import StaleWrite, read_attrs, store_status
from tubeid.runner.study import load_definition
from tubeid.runner.testing import clear_flag, flags, store_digest, write_pipeline, write_study

# a single study whose `summarize` adds an attribute (2 deltas x 4 realisations in blocks of 2: 4 blocks)
SUMMARY_STUDY = '''
import numpy as np
from tubeid.runner.study import Output, Study

def task(block, rng):
    r, d = block["realisation"], block["delta"]
    return {"x": np.array([[dv + rng(realisation=real).standard_normal() for real in r] for dv in d])}

study = Study(name="summed", seed=3, axes={"delta": [0.1, 0.2], "realisation": range(4)},
              chunks={"delta": 1, "realisation": 2}, seed_axes=("realisation",), task=task,
              outputs={"x": Output(units="m")}, summarize=lambda ds: {"xmean": float(ds.x.mean())})
'''

KILLER = '''
import os, signal, sys

def die(why):
    os.write(2, f"SIGKILL {why}\\n".encode())
    os.kill(os.getpid(), signal.SIGKILL)

PATCH

from tubeid.runner.cli import main
sys.exit(main(sys.argv[1:]))
'''


def _env():
    env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONWARNINGS="ignore")
    for k in ("DASK_SCHEDULER_ADDRESS", "TUBEID_TEST_FAIL_AT", "TUBEID_TEST_FAIL_STAGE", "TUBEID_TEST_BLOCK_SECONDS"):
        env.pop(k, None)
    return env


def _killed(tmp_path, patch: str, args, preexec=None) -> str:
    """Run ``tubeid run ARGS --workers 0`` in a subprocess with ``patch`` applied first; it must die by
    SIGKILL at the patched point. Returns its stderr."""
    script = tmp_path / "killer.py"
    script.write_text(KILLER.replace("PATCH", textwrap.dedent(patch)))
    proc = subprocess.run([sys.executable, str(script), "run", *map(str, args), "--workers", "0", "--no-progress"],
                          env=_env(), capture_output=True, text=True, timeout=120, preexec_fn=preexec)
    assert proc.returncode == -signal.SIGKILL and "SIGKILL" in proc.stderr, proc.stderr
    return proc.stderr


def _cli(args, capsys) -> tuple[int, str]:
    rc = cli(["run", *map(str, args), "--workers", "0", "--no-progress"])
    return rc, capsys.readouterr().err


@pytest.fixture(scope="module")
def defs(tmp_path_factory):
    d = tmp_path_factory.mktemp("defs")
    (d / "summed.py").write_text(SUMMARY_STUDY)
    return {"study": write_study(d, realisations=4, chunk=2, work=2), "summed": d / "summed.py",
            "pipeline": write_pipeline(d, curve=4, around=4, work=0)}


@pytest.fixture(scope="module")
def refs(defs, tmp_path_factory):
    """Uninterrupted runs of each definition: their store digests."""
    d = tmp_path_factory.mktemp("refs")
    out = {}
    for name, path in defs.items():
        run(path, d / f"{name}.zarr", workers=0, quiet=True)
        out[name] = store_digest(d / f"{name}.zarr")
    return out


def _same(store, ref):
    got = store_digest(store)
    assert [k for k in sorted(set(got) | set(ref)) if got.get(k) != ref.get(k)] == []


# -- 1. a task an earlier run left running never writes into the store that replaced it ----------------------
def test_a_block_of_another_study_definition_is_refused_and_the_store_untouched(defs, tmp_path):
    """What an orphaned task of a killed run does when its block is done: run_block with the earlier
    definition (other --set values) against the store an --overwrite run made since."""
    store = tmp_path / "s.zarr"
    run(defs["study"], store, workers=0, quiet=True, overrides={"work": 3})
    before = store_digest(store)
    source = defs["study"].read_text()
    with pytest.raises(StaleWrite, match="no longer holds the study this block was computed for"):
        run_block(str(store), source, {"work": 2}, (1, 0))
    assert store_digest(store) == before and integrity.verify(store).ok
    # the store's own study still writes (the same bytes: idempotent)
    run_block(str(store), source, {"work": 3}, (1, 0))
    assert store_digest(store) == before


def test_a_store_replaced_between_a_blocks_data_and_its_flag_gets_no_flag(defs, tmp_path, monkeypatch):
    """The study hash is checked again right before the flag: a store replaced while the block wrote
    its data never gets the flag that would vouch for them."""
    store = tmp_path / "s.zarr"
    run(defs["study"], store, workers=0, quiet=True)
    clear_flag(store, (0, 1))
    checksum = integrity.block_checksum

    def replaced_meanwhile(outputs, index):  # another study's store is there once the block's data are in
        meta = json.loads((store / "zarr.json").read_text())
        meta["attributes"]["study_hash"] = "0" * 64
        (store / "zarr.json").write_text(json.dumps(meta))
        return checksum(outputs, index)

    monkeypatch.setattr(integrity, "block_checksum", replaced_meanwhile)
    with pytest.raises(StaleWrite):
        run_block(str(store), defs["study"].read_text(), {}, (0, 1))
    assert not flags(store)[0, 1]


def test_a_stage_block_of_another_pipeline_definition_is_refused(defs, tmp_path):
    store = tmp_path / "p.zarr"
    run(defs["pipeline"], store, workers=0, quiet=True, overrides={"work": 1})
    before = store_digest(store)
    pipeline, source, key = load_definition(defs["pipeline"])  # the earlier definition: work = 0
    _, shash = stage_study(pipeline, key, store, "curve")
    with pytest.raises(StaleWrite, match=r"\(stage curve\) no longer holds"):
        run_stage_block(str(store), source, {}, "curve", shash, (0, 1))
    assert store_digest(store) == before


# -- 2. finalisation: `finished` never lands without the summary ---------------------------------------------
AFTER_FINISHED = '''
import zarr
orig = zarr.Group.update_attributes
def update_attributes(self, new_attributes):
    out = orig(self, new_attributes)
    if self.path == GROUP and new_attributes.get("finished"):
        die(f"after the first write of finished in group {self.path!r}")
    return out
zarr.Group.update_attributes = update_attributes
'''


@pytest.mark.parametrize("name, group", [("summed", ""), ("pipeline", "curve")])
def test_a_kill_in_the_finalisation_leaves_the_summary_with_finished(defs, refs, tmp_path, name, group):
    """Killed right after the first attribute write that sets `finished` (store root or stage group): the
    summary was written with it, so the resume (the next stage reads it) ends identical."""
    store = tmp_path / "s.zarr"
    _killed(tmp_path, AFTER_FINISHED.replace("GROUP", repr(group)), [defs[name], "--store", store])
    attrs = read_attrs(store, group or None)
    assert attrs.get("finished") and attrs.get("summary_keys")
    run(defs[name], store, workers=0, quiet=True)
    _same(store, refs[name])


# -- 3, 7. a kill while the store or a stage group is created ------------------------------------------------
AT_CREATION = '''
import zarr
orig = zarr.Group.update_attributes
def update_attributes(self, new_attributes):
    if self.path == GROUP and "format" in new_attributes and "format" not in self.attrs:
        die(f"while creating group {self.path!r}")
    return orig(self, new_attributes)
zarr.Group.update_attributes = update_attributes
'''

# the first metadata write of the root: zarr's temporary zarr.<hex>.partial is there, zarr.json not yet
AT_FIRST_RENAME = '''
import pathlib
orig = pathlib.Path.replace
def replace(self, target):
    target = pathlib.Path(target)
    if self.name.startswith("zarr.") and self.name.endswith(".partial") and self.parent.name.endswith(".zarr") \\
            and not target.exists():
        die(f"before renaming {self.name}")
    return orig(self, target)
pathlib.Path.replace = replace
'''


# the stage's (or store's) arrays are there, its flag array not yet
AT_FLAGS = '''
import zarr
orig = zarr.Group.create_array
def create_array(self, name, **kw):
    if name == "block_done" and self.path == (GROUP + "/_tubeid").lstrip("/"):
        die(f"before creating the flags of group {GROUP!r}")
    return orig(self, name, **kw)
zarr.Group.create_array = create_array
'''


@pytest.mark.parametrize("name, point, group, verify", [
    ("study", AT_FLAGS, "", False), ("pipeline", AT_FLAGS, "around", False),
    ("study", AT_CREATION, "", True), ("study", AT_CREATION, "", False), ("study", AT_FIRST_RENAME, "", False),
    ("pipeline", AT_FIRST_RENAME, "", True), ("pipeline", AT_CREATION, "curve", False),
    ("pipeline", AT_CREATION, "around", True)])
def test_a_kill_while_creating_the_store_or_a_stage_is_resumed(defs, refs, tmp_path, name, point, group, verify):
    """The group's zarr.json (or only zarr's temporary file) is there without tubeid's attributes: the
    rerun recognises its own interrupted creation (the manifest lists the group, no block was written)
    and makes it again, also with --no-verify."""
    store = tmp_path / "s.zarr"
    _killed(tmp_path, point.replace("GROUP", repr(group)), [defs[name], "--store", store])
    run(defs[name], store, workers=0, quiet=True, verify_blocks=verify)
    _same(store, refs[name])


@pytest.mark.parametrize("name, point", [("study", AT_CREATION), ("study", AT_FIRST_RENAME), ("pipeline", AT_FIRST_RENAME)])
def test_status_of_a_store_whose_creation_was_killed_says_so(defs, tmp_path, capsys, name, point):
    """``tubeid status`` on a run's creation killed before its root was written: what it is and what to do
    (one line), not "not a tubeid store"; while its run holds the lock: in progress."""
    from tubeid.runner.lock import StoreLock

    store = tmp_path / "s.zarr"
    _killed(tmp_path, point.replace("GROUP", repr("")), [defs[name], "--store", store])
    with pytest.raises(SpecificationError, match="stopped before its first block .*`tubeid run` with the same study"):
        store_status(store)
    assert cli(["status", str(store)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "stopped before its first block" in err
    with StoreLock(store):  # a run that has just taken the lock and is creating the store
        with pytest.raises(SpecificationError, match=f"being created by a run in progress .*pid {os.getpid()}"):
            store_status(store)
    run(defs[name], store, workers=0, quiet=True)  # and a run makes it again
    assert store_status(store)["complete"]


def test_status_of_a_directory_of_other_files_is_still_not_a_store(tmp_path):
    d = tmp_path / "mine"
    d.mkdir()
    (d / "notes.txt").write_text("x")
    with pytest.raises(SpecificationError, match="is not a readable tubeid study store"):
        store_status(d)
    # a user's file merely named like tubeid's is the user's: still not a store
    (d / ".tubeid-lock-notes").write_text("x")
    (d / "notes.txt").unlink()
    with pytest.raises(SpecificationError, match="is not a readable tubeid study store"):
        store_status(d)
    # only tubeid's own files, by their exact names (a killed lock take's private file): `tubeid run` takes
    # such a directory for a new store, status says so
    (d / ".tubeid-lock-notes").unlink()
    (d / f".tubeid-lock.tmp-{'ab' * 12}").write_text("x")
    with pytest.raises(SpecificationError, match="holds only the start"):
        store_status(d)


def test_status_of_a_creation_says_what_tubeid_run_would_say(tmp_path, monkeypatch):
    """Only a damaged manifest, or an empty lock file (a run killed between its O_EXCL create and its
    write): named as such, as `tubeid run` refuses them; a directory that cannot be listed keeps the
    plain message (no traceback)."""
    d = tmp_path / "s.zarr"
    d.mkdir()
    (d / ".tubeid-manifest.json").write_text("garbage{")
    with pytest.raises(SpecificationError, match="unreadable manifest"):
        store_status(d)
    (d / ".tubeid-manifest.json").unlink()
    (d / ".tubeid-lock").write_bytes(b"")
    with pytest.raises(SpecificationError, match="unreadable lock file .*if no tubeid run is using this store, remove it"):
        store_status(d)
    real = pathlib.Path.iterdir

    def unlistable(self):
        if self == d:
            raise PermissionError(13, "Permission denied", str(self))
        return real(self)

    monkeypatch.setattr(pathlib.Path, "iterdir", unlistable)
    with pytest.raises(SpecificationError, match="is not a readable tubeid study store"):
        store_status(d)


@pytest.mark.parametrize("loss, says", [("attributes", "is not a tubeid study store"),
                                        ("zarr.json", "its root metadata \\(zarr.json\\) is missing, yet it holds blocks")])
def test_a_store_whose_root_metadata_was_lost_is_not_taken_for_an_interrupted_creation(defs, tmp_path, loss, says):
    """Finished blocks (flags) in it: the root's provenance is gone, not yet to be written (damage, or an
    --overwrite stopped while removing the store); refused, nothing deleted."""
    store = tmp_path / "s.zarr"
    run(defs["study"], store, workers=0, quiet=True)
    if loss == "zarr.json":
        (store / "zarr.json").unlink()
    else:
        meta = json.loads((store / "zarr.json").read_text())
        meta["attributes"] = {}
        (store / "zarr.json").write_text(json.dumps(meta))
    before = {f: f.read_bytes() for f in store.rglob("*") if f.is_file()}
    with pytest.raises(SpecificationError, match=says):
        run(defs["study"], store, workers=0, quiet=True)
    assert {f: f.read_bytes() for f in store.rglob("*") if f.is_file()} == before


def test_a_users_group_in_place_of_a_stage_is_not_taken_for_tubeids(defs, tmp_path):
    import zarr

    store = tmp_path / "p.zarr"
    run(defs["pipeline"], store, workers=0, quiet=True)
    shutil.rmtree(store / "final")
    manifest = json.loads((store / ".tubeid-manifest.json").read_text())
    manifest["nodes"] = {n: k for n, k in manifest["nodes"].items() if n != "final" and not n.startswith("final/")}
    (store / ".tubeid-manifest.json").write_text(json.dumps(manifest))
    zarr.open_group(str(store / "final"), mode="w", zarr_format=3).create_array("mine", shape=(2,), dtype="f8")[:] = 1.0
    before = {f: f.read_bytes() for f in (store / "final").rglob("*") if f.is_file()}
    with pytest.raises(SpecificationError, match="without stage provenance"):
        run(defs["pipeline"], store, workers=0, quiet=True)
    assert {f: f.read_bytes() for f in (store / "final").rglob("*") if f.is_file()} == before


def test_no_verify_on_a_store_without_its_flags_is_one_line(defs, tmp_path, capsys):
    """The flag array missing (damage; or an earlier tubeid, which wrote the attributes first, killed while
    creating it): --no-verify refuses in one line (no KeyError traceback); a verifying run repairs it."""
    store = tmp_path / "s.zarr"
    run(defs["study"], store, workers=0, quiet=True)
    shutil.rmtree(store / "_tubeid")
    rc, err = _cli([defs["study"], "--store", store, "--no-verify"], capsys)
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "has no block flags" in err and "Traceback" not in err
    assert run(defs["study"], store, workers=0, quiet=True).computed == 4


# -- 4. a store path that is a symbolic link -------------------------------------------------------------------
@pytest.mark.parametrize("target", ["directory", "dangling"])
@pytest.mark.parametrize("extra", [[], ["--overwrite"]])
def test_a_store_path_that_is_a_symbolic_link_is_refused(defs, refs, tmp_path, capsys, target, extra):
    real = tmp_path / "real.zarr"
    if target == "directory":
        run(defs["study"], real, workers=0, quiet=True)
    link = tmp_path / "link.zarr"
    link.symlink_to(real)
    before = {f: f.read_bytes() for f in tmp_path.rglob("*") if f.is_file()}
    rc, err = _cli([defs["study"], "--store", link, "--set", "work=3", *extra], capsys)
    assert rc == 2 and len(err.strip().splitlines()) == 1 and f"{link}" in err and "symbolic link" in err
    assert {f: f.read_bytes() for f in tmp_path.rglob("*") if f.is_file()} == before
    assert real.exists() == (target == "directory") and link.is_symlink()


# -- 5. a kill between finishing a stage and recording it at the root -------------------------------------------
BEFORE_STAGE_STATE = '''
import tubeid.runner.execute as ex
orig = ex._stage_state
def _stage_state(path, name, state):
    if name == STAGE and state == "complete":
        die(f"before recording stage {name} complete at the root")
    return orig(path, name, state)
ex._stage_state = _stage_state
'''


@pytest.mark.parametrize("stage", ["curve", "final"])
def test_a_stage_finished_but_not_recorded_at_the_root_is_recorded_by_the_resume(defs, refs, tmp_path, stage):
    """A middle stage (the resume goes on with the next) and the last one (the resume finds the pipeline
    complete): the root's stage_status ends "complete", as in an uninterrupted run."""
    store = tmp_path / "p.zarr"
    _killed(tmp_path, BEFORE_STAGE_STATE.replace("STAGE", repr(stage)), [defs["pipeline"], "--store", store])
    assert read_attrs(store)["stage_status"][stage] == "running" and store_status(store, stage)["complete"]
    run(defs["pipeline"], store, workers=0, quiet=True)
    assert set(read_attrs(store)["stage_status"].values()) == {"complete"}
    _same(store, refs["pipeline"])


# -- 6. a kill before the last consolidation of the metadata ----------------------------------------------------
BEFORE_CONSOLIDATION = '''
import json, pathlib
import zarr
orig = zarr.consolidate_metadata
def consolidate_metadata(store, *a, **kw):
    attrs = json.loads((pathlib.Path(str(store)) / "zarr.json").read_text()).get("attributes", {})
    last = attrs.get("history", "").splitlines()[-1].split(": ", 1)[-1]  # "<time> tubeid <version>: <what>"
    if not kw.get("path") and attrs.get("finished") and last.startswith("complete"):
        die("before consolidating the root metadata")
    return orig(store, *a, **kw)
zarr.consolidate_metadata = consolidate_metadata
'''


@pytest.mark.parametrize("name", ["summed", "pipeline"])
def test_a_kill_before_the_last_consolidation_is_consolidated_by_the_resume(defs, refs, tmp_path, name):
    store = tmp_path / "s.zarr"
    _killed(tmp_path, BEFORE_CONSOLIDATION, [defs[name], "--store", store])
    assert "consolidated_metadata" not in json.loads((store / "zarr.json").read_text())
    run(defs[name], store, workers=0, quiet=True)
    assert json.loads((store / "zarr.json").read_text()).get("consolidated_metadata")
    _same(store, refs[name])


# -- 8. a full disk (or quota, read-only file system, permissions) while the store is created ------------------
@pytest.mark.parametrize("code", ["ENOSPC", "EDQUOT", "EFBIG", "EROFS", "EACCES"])
def test_a_write_the_file_system_refuses_is_named_as_such_and_the_store_resumes(defs, refs, tmp_path, monkeypatch, code):
    from zarr.storage import _local

    store = tmp_path / "s.zarr"
    number = getattr(errno, code)
    put = _local._put

    def refusing(path, value, *a, **kw):  # the root's attributes (its provenance) do not fit
        if pathlib.Path(path) == store / "zarr.json" and b"study_hash" in bytes(value.as_buffer_like()):
            raise OSError(number, os.strerror(number))
        return put(path, value, *a, **kw)

    monkeypatch.setattr(_local, "_put", refusing)
    with pytest.raises(SpecificationError) as exc:
        run(defs["study"], store, workers=0, quiet=True)
    assert f"cannot write {store}: {os.strerror(number)}" in str(exc.value) and "did not write" not in str(exc.value)
    monkeypatch.setattr(_local, "_put", put)
    run(defs["study"], store, workers=0, quiet=True)
    _same(store, refs["study"])


def _small_files():
    """In the child: files may not grow beyond 2 KiB (the root's provenance is larger): EFBIG, signal ignored."""
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (2048, 2048))


def test_a_real_file_size_limit_is_one_line_and_the_store_resumes(defs, refs, tmp_path):
    store = tmp_path / "s.zarr"
    proc = subprocess.run([sys.executable, "-m", "tubeid.runner.cli", "run", str(defs["study"]), "--store", str(store),
                           "--workers", "0", "--no-progress"], env=_env(), capture_output=True, text=True, timeout=120,
                          preexec_fn=_small_files)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines() == [proc.stderr.strip()] and os.strerror(errno.EFBIG) in proc.stderr
    assert "cannot write" in proc.stderr and "did not write" not in proc.stderr
    run(defs["study"], store, workers=0, quiet=True)
    _same(store, refs["study"])


# -- 9. paths zarr would read as URLs, names zarr or the file system cannot take ---------------------------------
@pytest.mark.parametrize("form", ["{other}::v2.zarr", "file://{other}", "in {other}::v2: out.zarr",
                                  "{tmp}/lnk/out.zarr"])
def test_a_store_path_zarr_would_read_as_a_url_is_refused_and_nothing_is_touched(defs, tmp_path, capsys, monkeypatch,
                                                                                form):
    """zarr reads `prev.zarr::v2.zarr` as a chain of file systems opening prev.zarr: the run used to write
    into that other store (its provenance wiped). Refused up front by every command taking a store, also
    when only the path made absolute (a working directory `prev.zarr::v2`) or resolved (a link to it) has `::`."""
    monkeypatch.chdir(tmp_path)  # were the check gone, a relative "file:" directory would land here
    other = tmp_path / "prev.zarr"
    run(defs["study"], other, workers=0, quiet=True)
    (tmp_path / "prev.zarr::v2").mkdir()
    (tmp_path / "lnk").symlink_to(tmp_path / "prev.zarr::v2")
    before = {f: f.read_bytes() for f in tmp_path.rglob("*") if f.is_file()}
    path = form.format(other=other, tmp=tmp_path)
    if path.startswith("in "):
        where, path = path[3:].split(": ")
        monkeypatch.chdir(where)
    rc, err = _cli([defs["study"], "--store", path], capsys)
    assert rc == 2 and err.strip().splitlines() == [err.strip()] and "must be a local directory path" in err
    for command in (["status", path], ["status", path, "--verify"], ["show", path]):
        assert cli(command) == 2 and "must be a local directory path" in capsys.readouterr().err
    with pytest.raises(SpecificationError, match="must be a local directory path"):
        integrity.verify(path)
    assert {f: f.read_bytes() for f in tmp_path.rglob("*") if f.is_file()} == before
    assert sorted(f.name for f in (tmp_path / "prev.zarr::v2").iterdir()) == []


def test_a_study_whose_default_store_zarr_would_read_as_a_url_is_told_to_take_store(tmp_path, monkeypatch):
    (tmp_path / "named.py").write_text(SUMMARY_STUDY.replace('name="summed"', 'name="summed::v2"'))
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SpecificationError, match=r"store \(the default one, named after study 'summed::v2': give "
                                                 r"--store, or rename the study\) = .*must be a local directory path"):
        run(tmp_path / "named.py", workers=0, quiet=True)
    assert sorted(f.name for f in tmp_path.iterdir()) == ["named.py"]


def test_a_store_name_longer_than_the_file_system_allows_is_one_line(defs, tmp_path, capsys):
    path = tmp_path / ("x" * 300)
    rc, err = _cli([defs["study"], "--store", path], capsys)
    assert rc == 2 and err.strip().splitlines() == [err.strip()] and os.strerror(errno.ENAMETOOLONG) in err
    assert cli(["status", str(path)]) == 2 and os.strerror(errno.ENAMETOOLONG) in capsys.readouterr().err


# -- 10. --overwrite and files merely named like tubeid's; a kill after --overwrite emptied the store ---------------
def test_overwrite_keeps_a_users_file_named_like_tubeids_own(defs, refs, tmp_path, capsys):
    store = tmp_path / "s.zarr"
    run(defs["study"], store, workers=0, quiet=True)
    mine = {store / ".tubeid-notes.txt": b"mine", store / ".tubeid-tmp-notes": b"also mine",
            store / ".tubeid-tmp-notes_v2": b"mine, named exactly as a temporary file", store / ".tubeid-probe-data0001": b""}
    for f, data in mine.items():
        f.write_bytes(data)
    left = store / ".tubeid-tmp-k2j4_x9q"  # a manifest write killed before its rename: tubeid's, removed
    left.write_text('{\n "tubeid_manifest": 1,\n "nod')
    rc, err = _cli([defs["study"], "--store", store, "--overwrite"], capsys)
    assert rc == 0 and "kept 2 file(s)" in err and ".tubeid-notes.txt" in err, err  # (lists none of its own names)
    assert all(f.read_bytes() == data for f, data in mine.items()) and not left.exists()
    for f in mine:
        f.unlink()
    _same(store, refs["study"])
    # a directory holding only such a file is the user's, not an empty store of tubeid's
    d = tmp_path / "u"
    d.mkdir()
    (d / ".tubeid-settings.yaml").write_text("keep")
    rc, err = _cli([defs["study"], "--store", d, "--overwrite"], capsys)
    assert rc == 2 and "is not a tubeid store" in err and (d / ".tubeid-settings.yaml").read_text() == "keep"
    rc, err = _cli([defs["study"], "--store", d], capsys)
    assert rc == 2 and "did not write" in err and sorted(f.name for f in d.iterdir()) == [".tubeid-settings.yaml"]


BEFORE_NEW_ROOT = '''
import tubeid.runner.store as st
def _fresh_root(*a, **kw):
    die("after --overwrite removed the store, before the new one is created")
st._fresh_root = _fresh_root
'''


@pytest.mark.parametrize("again", [[], ["--overwrite"]])
def test_a_kill_after_overwrite_emptied_the_store_is_run_again(defs, refs, tmp_path, again):
    """The old results are gone and the new store not yet begun: the manifest stays (emptied), so the
    directory is still provably tubeid's and the next run, with or without --overwrite, makes the store;
    the user's file in it is kept."""
    store = tmp_path / "s.zarr"
    run(defs["summed"], store, workers=0, quiet=True)
    (store / "notes.txt").write_text("mine")
    _killed(tmp_path, BEFORE_NEW_ROOT, [defs["study"], "--store", store, "--overwrite"])
    assert json.loads((store / ".tubeid-manifest.json").read_text())["nodes"] == {}
    with pytest.raises(SpecificationError, match="an --overwrite emptied it .* `tubeid run` makes it anew"):
        store_status(store)
    run(defs["study"], store, workers=0, quiet=True, overwrite=bool(again))
    assert (store / "notes.txt").read_text() == "mine"
    (store / "notes.txt").unlink()
    _same(store, refs["study"])


def _as_layout_1(store: pathlib.Path) -> None:
    """``store`` as an older tubeid (layout /1, before manifests) left it: no manifest, format /1."""
    (store / ".tubeid-manifest.json").unlink()
    meta = json.loads((store / "zarr.json").read_text())
    meta["attributes"]["format"] = "tubeid-study-store/1"
    (store / "zarr.json").write_text(json.dumps(meta))


def test_a_store_of_an_older_layout_is_never_replaced_and_new_store_writes_beside_it(defs, tmp_path, capsys):
    """Layout /1 kept no record of what it wrote: nothing in it is provably tubeid's (a user's array, even
    one the user consolidated into its metadata, looks like one), so --overwrite deletes nothing."""
    import zarr

    store = tmp_path / "s.zarr"
    run(defs["summed"], store, workers=0, quiet=True)
    _as_layout_1(store)
    root = zarr.open_group(str(store), mode="r+", use_consolidated=False)
    root.create_array("my_analysis", shape=(3,), dtype="f8")[:] = [1.0, 2.0, 3.0]
    zarr.consolidate_metadata(str(store))
    before = {f: f.read_bytes() for f in tmp_path.rglob("*") if f.is_file()}
    for extra in (["--overwrite"], []):
        rc, err = _cli([defs["study"], "--store", store, *extra], capsys)
        assert rc == 2 and "older tubeid (layout tubeid-study-store/1)" in err and "--new-store" in err, err
        assert {f: f.read_bytes() for f in tmp_path.rglob("*") if f.is_file()} == before
    rep = run(defs["study"], store, workers=0, quiet=True, new_store=True)
    assert rep.store.parent == tmp_path and rep.store.name.startswith("s-") and rep.computed == 4
    assert all(f.read_bytes() == data for f, data in before.items())


# -- 11. --new-store diverts only from a store it cannot use -------------------------------------------------------
def test_new_store_resumes_its_own_store_and_diverts_beside_dot(defs, tmp_path, monkeypatch):
    store = tmp_path / "s.zarr"
    first = run(defs["study"], store, workers=0, quiet=True, new_store=True)  # nothing there: used as given
    assert first.store == store.resolve() and first.computed == 4
    again = run(defs["study"], store, workers=0, quiet=True, new_store=True)  # this study's store: a resume
    assert again.store == store.resolve() and again.computed == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.zarr"]
    monkeypatch.chdir(store)  # "." holds this study: another definition goes beside it, not into "./.-<hash>"
    other = run(defs["summed"], ".", workers=0, quiet=True, new_store=True)
    assert other.store.parent == tmp_path.resolve() and other.store.name.startswith("s-")
    assert read_attrs(other.store)["study_name"] == "summed"
    link = tmp_path / "link.zarr"  # a link, even to this study's store: tubeid never writes through one
    link.symlink_to(store)
    beside = run(defs["study"], link, workers=0, quiet=True, new_store=True)
    assert beside.store.parent == tmp_path.resolve() and beside.store.name.startswith("link-") and beside.computed == 4
    with pytest.raises(SpecificationError, match="root directory: a new store has no name"):
        run(defs["summed"], "/", workers=0, quiet=True, new_store=True)


# -- 12. a full disk while a block is written ------------------------------------------------------------------------
def test_a_full_disk_while_writing_a_block_is_one_line_naming_the_block_and_the_store_resumes(defs, refs, tmp_path,
                                                                                            monkeypatch, capsys):
    from zarr.storage import _local

    store = tmp_path / "s.zarr"
    put = _local._put

    def full(path, value, *a, **kw):  # a data chunk of block (0, 1) does not fit
        if pathlib.Path(path) == store / "x" / "c" / "0" / "1" / "0":
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return put(path, value, *a, **kw)

    monkeypatch.setattr(_local, "_put", full)
    rc, err = _cli([defs["study"], "--store", store], capsys)
    assert rc == 2 and err.strip().splitlines()[-1].startswith("tubeid: error: store = ") and "Traceback" not in err
    assert f"cannot write {store}" in err and os.strerror(errno.ENOSPC) in err and "block (0, 1)" in err, err
    monkeypatch.setattr(_local, "_put", put)
    run(defs["study"], store, workers=0, quiet=True)
    _same(store, refs["study"])
