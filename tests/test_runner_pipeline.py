"""Multi-stage studies (pipelines): definition checks, stage-keyed streams, a stage built from an earlier
stage's derived value, one Zarr group per stage, per-stage resume, stage hashes that refuse mixing,
parameter overrides, status/show, and real processes (2 local workers vs in-process, runner SIGKILLed
mid-stage-2 and resumed). Every store comparison is byte-for-byte (chunk files + non-volatile metadata).
"""

import dataclasses
import json
import os
import pathlib
import signal
import subprocess
import sys
import time

import numpy as np
import psutil
import pytest
import xarray as xr
import zarr

from tubeid.errors import SpecificationError
from tubeid.runner.cli import main as cli
from tubeid.runner.execute import run
from tubeid.runner.pipeline import End, Pipeline
from tubeid.runner.store import open_pipeline, open_results, store_status, update_attrs
from tubeid.runner.study import Output, Parameter, Study, load_definition, load_study
from tubeid.runner.testing import clear_flag, flags, store_digest, write_pipeline
from tubeid.seeds import rng_for

REPO = pathlib.Path(__file__).resolve().parents[1]
SEED = 11  # the test pipeline's seed (tubeid.runner.testing.PIPELINE)
X = np.round(np.linspace(0.0, 0.6, 13), 3)
OFFSETS = np.array([-0.1, 0.0, 0.1])


def _task(block, rng):
    return {"y": np.zeros(len(block["r"]))}


def _study(name="a", seed=1, **kw):
    return Study(name=name, seed=seed, axes={"r": range(4)}, task=_task, outputs={"y": Output()}, **kw)


def a(results, *, size):
    return _study("a")


def b(results, *, size, extra):
    return _study("b")


# -- definitions refused up front ----------------------------------------------------------------------
@pytest.mark.parametrize("kw, field", [
    (dict(stages=[]), "stages"),
    (dict(stages=[_study("a"), _study("a")]), "stages[1].name"),                 # duplicate stage names
    (dict(stages=[_study("a", seed=2)]), "stages.a.seed"),                       # not the pipeline seed
    (dict(stages=[a, b]), "stages.b"),                                           # needs an unknown parameter
    (dict(stages=[_study("x")], parameters={"size": 1}), "parameters.size"),    # no stage takes it
    (dict(stages=[42]), "stages[0]"),
    (dict(stages=[a], seed=-1), "seed"),
    (dict(stages=[a], name="p q"), "name"),
])
def test_bad_pipelines_are_refused(kw, field):
    base = dict(name="p", seed=1, stages=[a], parameters={"size": Parameter("big", choices=["big", "small"])})
    base.update(kw)
    with pytest.raises(SpecificationError) as err:
        Pipeline(**base)
    assert err.value.field == field


def test_stage_functions_must_return_their_study():
    def named_wrong(results):
        return _study("other")

    def wrong_seed(results):
        return _study("wrong_seed", seed=2)

    def not_a_study(results):
        return {"y": 1}

    for fn, field in ((named_wrong, "stages.named_wrong.name"), (wrong_seed, "stages.wrong_seed.seed"),
                      (not_a_study, "stages.not_a_study")):
        p = Pipeline(name="p", seed=1, stages=[fn])
        with pytest.raises(SpecificationError) as err:
            p.stage(fn.__name__, {})
        assert err.value.field == field
    p = Pipeline(name="p", seed=1, stages=[_study("a"), named_wrong])
    with pytest.raises(SpecificationError, match="earlier stages"):
        p.stage("named_wrong", {})
    assert p.stage("a", {}).stream_key == ("a",)


def _draws(block, rng):
    return {"y": np.array([rng.at({"r": r}).standard_normal() for r in block["r"]])}


def test_a_stage_may_keep_an_earlier_stages_streams(tmp_path):
    """Common random numbers across stages: a stage naming an earlier stage's stream key draws its
    streams; one that does not draws its own (its name)."""
    def first(results):
        return Study(name="first", seed=1, axes={"r": range(4)}, task=_draws, outputs={"y": Output()})

    def same(results):
        return dataclasses.replace(first(results), name="same", stream_key=("first",))

    def other(results):
        return dataclasses.replace(first(results), name="other")

    p = Pipeline(name="crn", seed=1, stages=[first, same, other])
    assert p.stage("same", {"first": None}).stream_key == ("first",)
    res = {}
    for name in ("first", "same", "other"):
        st = p.stage(name, res)
        res[name] = st.compute_block(st.block((0,)))["y"]
    np.testing.assert_array_equal(res["same"], res["first"])
    assert not np.any(res["other"] == res["first"])


def test_pipeline_overrides_are_validated(tmp_path, capsys):
    path = write_pipeline(tmp_path)
    pipe = load_definition(path)[0]
    assert pipe.with_parameters({"size": "quick"}).values["size"] == "quick"
    with pytest.raises(SpecificationError, match="must be one of"):
        pipe.with_parameters({"size": "huge"})
    with pytest.raises(SpecificationError, match="defines a Pipeline"):
        load_study(path)
    store = tmp_path / "p.zarr"
    assert cli(["run", str(path), "--store", str(store), "--workers", "0", "--set", "size='huge'"]) == 2
    assert "parameters.size = 'huge': must be one of" in capsys.readouterr().err and not store.exists()


# -- results, seeds, derived values ------------------------------------------------------------------------
def _expected(curve_n, around_n):
    """The pipeline's outputs recomputed from tubeid.seeds.rng_for(seed, stage name, realisation)."""
    e = np.array([rng_for(SEED, "curve", r).standard_normal(2) for r in range(curve_n)])
    y = (X[:, None] - 0.3) ** 2 + 0.2 * e[:, 0] * X[:, None] + 0.1 * e[:, 1]
    x_opt = float(X[np.argmin(y.mean(axis=1))])
    e2 = np.array([rng_for(SEED, "around", r).standard_normal() for r in range(around_n)])
    z = x_opt + OFFSETS[:, None] + 0.01 * e2
    w = np.array([rng_for(SEED, "final", r).standard_normal() for r in range(6)])
    return y, x_opt, z, w


def test_stages_use_stage_keyed_streams_and_earlier_results(tmp_path):
    path = write_pipeline(tmp_path, curve=8, around=6)
    report = run(path, tmp_path / "p.zarr", workers=0, quiet=True)
    assert {n: (r.total, r.computed) for n, r in report.stages.items()} == {"curve": (4, 4), "around": (3, 3), "final": (2, 2)}
    res = open_pipeline(tmp_path / "p.zarr")
    assert list(res) == ["curve", "around", "final"]
    y, x_opt, z, w = _expected(8, 6)
    np.testing.assert_array_equal(res["curve"].y.values, y)  # same arithmetic, same streams: bit-identical
    assert res["curve"].attrs["x_opt"] == x_opt and res["curve"].attrs["summary_keys"] == ["x_opt"]
    # the second stage was built from the first's derived value: stored as its parameter, used by its task
    assert json.loads(res["around"].attrs["parameters"])["center"] == x_opt
    np.testing.assert_array_equal(res["around"].z.values, z)
    np.testing.assert_array_equal(res["final"].w.values, w)
    assert res["final"].attrs["stream_key"] == ["final"]
    # plain xarray opens a stage group; the root summary lists every stage
    ds = xr.open_zarr(tmp_path / "p.zarr", group="around")
    assert ds.z.dims == ("offset", "realisation") and ds.z.attrs["units"] == "m"
    root = open_results(tmp_path / "p.zarr")
    assert not root.data_vars and root.attrs["stages"] == ["curve", "around", "final"]
    assert root.attrs["stages_complete"] == ["curve", "around", "final"]
    assert root.attrs["stage_status"] == {"curve": "complete", "around": "complete", "final": "complete"}
    assert root.attrs["study_source"] == path.read_text() and root.attrs["study_hash"] == load_definition(path)[2]
    assert root.attrs["started"] <= root.attrs["finished"]
    assert run(path, tmp_path / "p.zarr", workers=0, quiet=True).computed == 0  # complete: nothing to do


def test_failed_stage_2_resumes_identically_and_a_changed_upstream_value_is_refused(tmp_path, monkeypatch):
    path = write_pipeline(tmp_path, curve=6, around=8)
    run(path, tmp_path / "ref.zarr", workers=0, quiet=True)
    store = tmp_path / "p.zarr"
    monkeypatch.setenv("TUBEID_TEST_FAIL_STAGE", "around")
    monkeypatch.setenv("TUBEID_TEST_FAIL_AT", "4")  # blocks run in C order: realisations 0-3 written, then the failure
    with pytest.raises(RuntimeError, match="on purpose"):
        run(path, store, workers=0, quiet=True)
    st = store_status(store)
    assert {n: (s["done"], s["total"], s["complete"]) for n, s in st["stages"].items()} == \
        {"curve": (3, 3, True), "around": (2, 4, False), "final": (0, None, False)}
    assert np.isnan(open_results(store, "around").z.sel(realisation=[4, 5, 6, 7])).all()
    monkeypatch.delenv("TUBEID_TEST_FAIL_STAGE")
    partial = store_digest(store)
    # an upstream result that changed (here: the stored x_opt) gives another stage hash: refused, store untouched
    g = zarr.open_group(str(store), mode="r+", path="curve")
    x_opt = g.attrs["x_opt"]
    g.attrs["x_opt"] = x_opt + 0.05
    with pytest.raises(SpecificationError, match="stage 'around' built from different inputs"):
        run(path, store, workers=0, quiet=True)
    g.attrs["x_opt"] = x_opt
    assert store_digest(store) == partial
    report = run(path, store, workers=0, quiet=True)
    assert {n: (r.computed, r.skipped) for n, r in report.stages.items()} == \
        {"curve": (0, 3), "around": (2, 2), "final": (2, 0)}
    assert store_digest(store) == store_digest(tmp_path / "ref.zarr")
    assert len(store_status(store, "around")["attrs"]["runs"]) == 2


def test_parameters_change_sizes_and_the_hash(tmp_path):
    path = write_pipeline(tmp_path, curve=6, around=6)
    normal = run(path, tmp_path / "p.zarr", workers=0, quiet=True)
    before = store_digest(tmp_path / "p.zarr")
    with pytest.raises(SpecificationError, match="different study definition"):
        run(path, tmp_path / "p.zarr", workers=0, quiet=True, overrides={"size": "quick"})
    assert store_digest(tmp_path / "p.zarr") == before
    quick = run(path, tmp_path / "p.zarr", workers=0, quiet=True, overrides={"size": "quick"}, new_store=True)
    assert quick.store != normal.store and quick.store.name.startswith("p-")
    res = open_pipeline(quick.store)
    assert res["curve"].sizes["realisation"] == 4 and res["around"].sizes["realisation"] == 4
    qa, na = open_results(quick.store).attrs, open_results(normal.store).attrs
    assert qa["study_hash"] != na["study_hash"] and json.loads(qa["parameter_overrides"]) == {"size": "quick"}
    assert res["curve"].attrs["stage_hash"] != open_results(normal.store, "curve").attrs["stage_hash"]
    # the common realisations of both sizes draw the same numbers (streams keyed by realisation, not size)
    np.testing.assert_array_equal(res["curve"].y.values, open_results(normal.store, "curve").y.values[:, :4])
    run(path, tmp_path / "p.zarr", workers=0, quiet=True, overrides={"size": "quick"}, overwrite=True)
    assert open_results(tmp_path / "p.zarr", "around").sizes["realisation"] == 4


def test_status_and_show_list_the_stages(tmp_path, capsys, monkeypatch):
    path = write_pipeline(tmp_path, curve=4, around=4)
    store = tmp_path / "p.zarr"
    monkeypatch.setenv("TUBEID_TEST_FAIL_STAGE", "around")
    monkeypatch.setenv("TUBEID_TEST_FAIL_AT", "2")
    assert cli(["run", str(path), "--store", str(store), "--workers", "0", "--no-progress"]) == 1
    assert "tubeid: error: stage 'around', block (0, 1) (offset = -0.1 … 0.1, realisation = 2 … 3) failed: " \
        "RuntimeError: interrupted on purpose" in capsys.readouterr().err
    assert cli(["status", str(store)]) == 0
    out = capsys.readouterr().out
    assert "pipeline pipeline-test: 1/3 stages complete, incomplete" in out
    assert "curve: 2/2 blocks done (100.0 %), complete" in out and "around: 1/2 blocks done (50.0 %), incomplete" in out
    assert "final: not started" in out
    assert cli(["status", str(store), "--json"]) == 0
    js = json.loads(capsys.readouterr().out)
    assert js["stages"]["around"] == {"started": True, "done": 1, "total": 2, "complete": False} and not js["complete"]
    assert cli(["show", str(store)]) == 0
    out = capsys.readouterr().out
    assert "stage curve" in out and "x_opt = " in out and "z [m]:" in out and "(50% written)" in out
    assert cli(["show", str(store), "--stage", "curve"]) == 0
    assert "z [m]" not in capsys.readouterr().out
    assert cli(["show", str(store), "--stage", "nope"]) == 2
    with pytest.raises(SpecificationError, match="not started"):
        open_results(store, "final")
    with pytest.raises(SpecificationError, match="not a stage"):
        open_results(store, "nope")


SUMMARIZED = """
import numpy as np
from tubeid.runner.study import Output, Study

def task(block, rng):
    return {"y": np.array([rng(r=r).standard_normal() for r in block["r"]])}

study = Study(name="summarized", seed=5, axes={"r": range(10)}, chunks={"r": 4}, task=task,
              outputs={"y": Output()}, summarize=lambda ds: SUMMARY)
"""


@pytest.mark.parametrize("summary, error", [
    ('{"y_max": ds.y.max().item(), "argmax": [int(ds.y.argmax("r"))]}', None),
    ('{"seed": 1}', "summarize = 'seed': must name new attributes"),
    ('{"m": float("nan")}', "summarize.m = nan: must be a plain finite value"),
    ('[1]', "summarize = 'list': must return a dict"),
])
def test_summarize_of_a_single_study(tmp_path, summary, error):
    path = tmp_path / "s.py"
    path.write_text(SUMMARIZED.replace("SUMMARY", summary))
    if error:
        with pytest.raises(SpecificationError, match=error):
            run(path, tmp_path / "s.zarr", workers=0, quiet=True)
        assert not open_results(tmp_path / "s.zarr").attrs["finished"]  # not marked complete
        with pytest.raises(SpecificationError, match=error):  # a rerun finalises again (and refuses again)
            run(path, tmp_path / "s.zarr", workers=0, quiet=True)
        return
    run(path, tmp_path / "s.zarr", workers=0, quiet=True)
    ds = open_results(tmp_path / "s.zarr")
    y = np.array([rng_for(5, r).standard_normal() for r in range(10)])  # a single study has no stream prefix
    assert ds.attrs["y_max"] == y.max() and ds.attrs["argmax"] == [int(y.argmax())]
    assert ds.attrs["summary_keys"] == ["argmax", "y_max"] and ds.attrs["finished"]


def test_the_documented_pipeline_runs(tmp_path):
    """The pipeline example of README.md, run as written (quick size)."""
    doc = (REPO / "README.md").read_text()
    source = doc.split("# studies/two_stage.py\n", 1)[1].split("```", 1)[0]
    (tmp_path / "two_stage.py").write_text(source)
    run(tmp_path / "two_stage.py", tmp_path / "t.zarr", workers=0, quiet=True, overrides={"size": "quick"})
    res = open_pipeline(tmp_path / "t.zarr")
    j = res["delta"].J.load()
    assert j.sizes == {"delta": 17, "realisation": 40}
    d_opt = res["delta"].attrs["delta_opt"]
    assert d_opt == float(j.delta[int(j.mean("realisation").argmin("delta"))])
    # J = (delta - 0.45)^2 + noise common to every delta (common random numbers): the minimum is exactly 0.45
    assert d_opt == 0.45
    assert json.loads(res["response"].attrs["parameters"]) == {"delta": d_opt}
    u = np.array([d_opt * rng_for(2008, "response", r).standard_normal() for r in range(40)])
    np.testing.assert_array_equal(res["response"].u.values, u)


# -- real processes ----------------------------------------------------------------------------------------
RUNNER = [sys.executable, "-m", "tubeid.runner.cli", "run"]
# curve: 4 blocks, around: 16 blocks of 2 realisations x ~0.05-0.1 s of compute each (work=3000)
SIZE = dict(curve=8, around=32, work=3000)
# the kill test sleeps this long in every block of stage `around` (values unchanged), so that the
# kill lands mid-stage on a fast machine too
PACE = {"TUBEID_TEST_BLOCK_SECONDS": "0.15"}


def _env(**extra):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    for k in ("DASK_SCHEDULER_ADDRESS", "TUBEID_TEST_FAIL_STAGE", "TUBEID_TEST_FAIL_AT", "TUBEID_TEST_BLOCK_SECONDS"):
        env.pop(k, None)
    env.update(extra)
    return env


def _run_cli(args):
    proc = subprocess.run(RUNNER + [str(x) for x in args] + ["--no-progress"], env=_env(), capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return proc


@pytest.fixture(scope="module")
def big(tmp_path_factory):
    return write_pipeline(tmp_path_factory.mktemp("pipeline"), **SIZE)


@pytest.fixture(scope="module")
def reference(big, tmp_path_factory):
    """The uninterrupted run: embedded LocalCluster with 2 workers."""
    store = tmp_path_factory.mktemp("ref") / "ref.zarr"
    _run_cli([big, "--store", store, "--workers", 2])
    return store_digest(store)


@pytest.mark.distributed
@pytest.mark.timeout(120)
def test_two_workers_and_in_process_give_identical_stores(big, reference, tmp_path):
    run(big, tmp_path / "here.zarr", workers=0, quiet=True)
    assert store_digest(tmp_path / "here.zarr") == reference


@pytest.mark.distributed
@pytest.mark.timeout(120)
def test_runner_killed_mid_stage_2_resumes_to_the_identical_store(big, reference, tmp_path):
    store = tmp_path / "killed.zarr"
    proc = subprocess.Popen(RUNNER + [str(big), "--store", str(store), "--workers", "2", "--no-progress"],
                            env=_env(**PACE), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        t0 = time.monotonic()
        while flags(store, "around").sum() < 2:
            assert proc.poll() is None, "runner ended before the kill point"
            assert time.monotonic() - t0 < 90, "no progress in stage 2"
            time.sleep(0.02)
        children = psutil.Process(proc.pid).children(recursive=True)
        proc.send_signal(signal.SIGKILL)  # the runner only: its workers must exit by themselves
        proc.wait(10)
        done = int(flags(store, "around").sum())
        _, alive = psutil.wait_procs(children, timeout=20)
        assert not [p for p in alive if p.status() != psutil.STATUS_ZOMBIE], "workers outlived the runner"
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)
    total = flags(store, "around").size
    assert 2 <= done < total, "the kill must land mid-stage-2"
    assert flags(store, "curve").all() and not (store / "final").exists()
    resumed = _run_cli([big, "--store", store, "--workers", 2])
    assert "stage curve: complete" in resumed.stderr
    assert f"stage around: {total - done} of {total} blocks to compute" in resumed.stderr
    assert store_digest(store) == reference


# -- where blocks run; the per-process cache of opened stages ---------------------------------------------
WHERE = '''
import os
import numpy as np
from tubeid.runner import Output, Pipeline, Study


def _pid(block, rng):
    return {"pid": np.full(len(block["i"]), float(os.getpid()))}


def far(results):
    return Study(name="far", seed=3, axes={"i": range(2)}, chunks={"i": 1}, task=_pid, outputs={"pid": Output()})


def here(results):
    return Study(name="here", seed=3, axes={"i": range(2)}, chunks={"i": 1}, task=_pid, outputs={"pid": Output()},
                 in_process=True)


study = Pipeline(name="where", seed=3, stages=[far, here])
'''


@pytest.mark.distributed
@pytest.mark.timeout(120)
def test_an_in_process_stage_runs_in_the_runner_and_the_others_on_the_workers(tmp_path):
    (tmp_path / "where.py").write_text(WHERE)
    rep = run(tmp_path / "where.py", tmp_path / "w.zarr", workers=1, quiet=True)
    res = open_pipeline(tmp_path / "w.zarr")
    assert rep.stages["far"].computed == rep.stages["here"].computed == 2
    assert set(res["here"].pid.values) == {float(os.getpid())}
    assert float(os.getpid()) not in set(res["far"].pid.values)


def test_an_opened_stage_is_reopened_once_it_finished_again(tmp_path):
    """The per-process cache of opened stages keys on the stage's ``finished`` time: a stage
    recomputed or repaired (a new ``finished``) is opened afresh, with its new attributes."""
    from tubeid.runner.execute import _open_stage
    from tubeid.runner.store import now, update_attrs

    path = write_pipeline(tmp_path)
    run(path, tmp_path / "p.zarr", workers=0, quiet=True)
    attrs = store_status(tmp_path / "p.zarr", "curve")["attrs"]
    first = _open_stage(tmp_path / "p.zarr", "curve", attrs)
    assert _open_stage(tmp_path / "p.zarr", "curve", dict(attrs)) is first
    time.sleep(0.01)
    update_attrs(tmp_path / "p.zarr", "curve", finished=now(), marker=1)
    again = _open_stage(tmp_path / "p.zarr", "curve", store_status(tmp_path / "p.zarr", "curve")["attrs"])
    assert again is not first and again.attrs["marker"] == 1 and "marker" not in first.attrs


ENDS = '''
import os
import numpy as np
from tubeid.runner import End, Output, Pipeline, Study


def _ones(block, rng):
    return {"y": np.ones(len(block["i"]))}


def first(results, *, more):
    return Study(name="first", seed=4, axes={"i": range(3)}, task=_ones, outputs={"y": Output()},
                 summarize=lambda ds: {"more": more})


def second(results):
    if not results["first"].attrs["more"] and not os.environ.get("TUBEID_TEST_GO_ON"):
        return End("nothing left after first")
    return Study(name="second", seed=4, axes={"i": range(2)}, task=_ones, outputs={"y": Output()})


def third(results):
    return Study(name="third", seed=4, axes={"i": range(2)}, task=_ones, outputs={"y": Output()})


study = Pipeline(name="ends", seed=4, stages=[first, second, third], parameters={"more": True})
'''


def test_a_stage_function_may_end_the_pipeline(tmp_path, capsys, monkeypatch):
    """``End(reason)`` from a stage function: that stage and the later ones are not built (no group,
    status "not needed"), the store is complete, a rerun has nothing to do, ``status`` (and its JSON)
    says why; a resume finalises a store stopped just after; a run that goes past the stage where an
    earlier one ended clears ``ended``; with the other parameter value every stage runs."""
    (tmp_path / "ends.py").write_text(ENDS)
    store = tmp_path / "e.zarr"
    rep = run(tmp_path / "ends.py", store, workers=0, overrides={"more": False}, quiet=True)
    assert list(rep.stages) == ["first"] and rep.computed == 1
    assert not (store / "second").exists() and not (store / "third").exists()
    st = store_status(store)
    assert st["complete"] and st["stages"]["second"] == st["stages"]["third"] == {
        "started": False, "done": 0, "total": 0, "complete": True, "needed": False}
    assert st["attrs"]["ended"] == {"stage": "second", "reason": "nothing left after first"}
    assert list(open_pipeline(store)) == ["first"]
    again = run(tmp_path / "ends.py", store, workers=0, overrides={"more": False}, quiet=True)
    assert again.computed == 0
    assert cli(["status", str(store)]) == 0
    out = capsys.readouterr().out
    assert "3/3 stages complete, complete" in out and "third: not needed" in out
    assert "ended before stage second: nothing left after first" in out
    assert cli(["status", str(store), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["ended"]["stage"] == "second"
    # stopped after ending but before the store's finalisation: the resume finalises it
    update_attrs(store, finished="")
    run(tmp_path / "ends.py", store, workers=0, overrides={"more": False}, quiet=True)
    assert store_status(store)["attrs"]["finished"]
    # a later run that goes past the stage where an earlier one ended (here: a stage function reading
    # the environment, as a non-deterministic one would) clears `ended` and runs the rest
    clear_flag(store, (0,), "first")
    update_attrs(store, "first", finished="", root=False)
    monkeypatch.setenv("TUBEID_TEST_GO_ON", "1")
    went_on = run(tmp_path / "ends.py", store, workers=0, overrides={"more": False}, quiet=True)
    monkeypatch.delenv("TUBEID_TEST_GO_ON")
    st = store_status(store)
    assert list(went_on.stages) == ["first", "second", "third"] and st["complete"] and not st["attrs"].get("ended")
    assert all(s["started"] for s in st["stages"].values())
    full = run(tmp_path / "ends.py", tmp_path / "f.zarr", workers=0, quiet=True)
    assert list(full.stages) == ["first", "second", "third"] and "ended" not in store_status(tmp_path / "f.zarr")["attrs"]
    with pytest.raises(SpecificationError, match="End.reason"):
        End("")


def test_a_small_stage_is_read_into_memory_once_and_a_large_one_stays_lazy(tmp_path, monkeypatch):
    """Stage functions and summaries read earlier stages many times: a stage of at most
    ``_LOAD_MAX_BYTES`` is read into memory when opened (its values survive its chunk files being
    moved away), a larger one stays lazy (read then, it gives the missing chunks' fill value)."""
    import shutil

    from tubeid.runner import execute

    path = write_pipeline(tmp_path)
    store = tmp_path / "p.zarr"
    run(path, store, workers=0, quiet=True)
    attrs = store_status(store, "curve")["attrs"]
    execute._OPENED.clear()
    loaded = execute._open_stage(store, "curve", attrs)
    monkeypatch.setattr(execute, "_LOAD_MAX_BYTES", 0)
    execute._OPENED.clear()
    lazy = execute._open_stage(store, "curve", attrs)
    name = next(k for k in loaded.data_vars if (store / "curve" / k / "c").is_dir())
    expected = xr.open_zarr(str(store), group="curve", chunks=None)[name].values
    shutil.move(str(store / "curve" / name / "c"), str(tmp_path / "moved"))
    np.testing.assert_array_equal(loaded[name].values, expected)
    assert not np.array_equal(lazy[name].values, expected)  # read now: the missing chunks' fill value
    execute._OPENED.clear()


# -- workers load the definition while the runner works ---------------------------------------------------
AHEAD = '''
import os
import time
import numpy as np
from tubeid.runner import Output, Pipeline, Study

LOG = {log!r}


def _note(what, t0):
    with open(LOG, "a") as f:
        f.write(f"{{what}} {{os.getpid()}} {{t0!r}} {{time.time()!r}}\\n")


_t0 = time.time()
time.sleep({sleep})  # a definition with heavy imports
_note("definition", _t0)


def _pid(block, rng, *, k):
    return {{"pid": np.full(len(block["i"]), float(os.getpid()))}}


def first(results, *, k):
    t0 = time.time()
    time.sleep({sleep})  # a stage function that takes a while (e.g. an identification from earlier results)
    _note("first", t0)
    return Study(name="first", seed=5, axes={{"i": range(4)}}, chunks={{"i": 1}}, task=_pid, outputs={{"pid": Output()}},
                 parameters={{"k": k}})


study = Pipeline(name="ahead", seed=5, stages=[first], parameters={{"k": 1}})
'''


@pytest.mark.distributed
@pytest.mark.timeout(120)
def test_the_workers_load_the_definition_while_the_runner_builds_the_first_stage(tmp_path):
    """As soon as the cluster runs, each worker executes the definition (with the run's overrides)
    while the runner builds the first stage, not after the runner has submitted its blocks; the
    blocks use that load (one per worker process)."""
    sleep = 1.5
    log = tmp_path / "loads.log"
    (tmp_path / "ahead.py").write_text(AHEAD.format(log=str(log), sleep=sleep))
    rep = run(tmp_path / "ahead.py", tmp_path / "a.zarr", workers=2, overrides={"k": 2}, quiet=True)
    assert rep.computed == 4
    notes = [line.split() for line in log.read_text().splitlines()]
    me = str(os.getpid())
    built = [float(t1) for what, pid, _, t1 in notes if what == "first" and pid == me]
    assert len(built) == 1, notes
    ran_on = {str(int(p)) for p in open_pipeline(tmp_path / "a.zarr")["first"].pid.values}
    assert ran_on and me not in ran_on
    loads = [(pid, float(t0)) for what, pid, t0, _ in notes if what == "definition" and pid in ran_on]
    assert sorted(pid for pid, _ in loads) == sorted(ran_on), notes  # once per worker that ran blocks
    assert all(t0 < built[0] for _, t0 in loads), notes  # started before the runner's build ended


# -- the runner sends each built stage to the workers ---------------------------------------------------
SHIPPED = '''
import os
import numpy as np
from tubeid.runner import Output, Pipeline, Study

LOG = {log!r}


def _values(block, rng, *, scale):
    return {{"v": np.array([scale * rng(i=i).standard_normal() for i in block["i"]])}}


def first(results, *, k):
    return Study(name="first", seed=5, axes={{"i": range(4)}}, chunks={{"i": 1}}, seed_axes=("i",), task=_values,
                 outputs={{"v": Output()}}, parameters={{"scale": float(k)}})


def second(results, *, k):
    with open(LOG, "a") as f:  # every call of this stage function, by process
        f.write(f"{{os.getpid()}}\\n")
    scale = float(np.abs(results["first"].v.values).sum())  # a value derived from the earlier stage
    task = {task}
    return Study(name="second", seed=5, axes={{"i": range(6)}}, chunks={{"i": 1}}, seed_axes=("i",), task=task,
                 outputs={{"v": Output()}}, parameters={{"scale": scale}})


study = Pipeline(name="shipped", seed=5, stages=[first, second], parameters={{"k": 1}})
'''


@pytest.mark.distributed
@pytest.mark.timeout(180)
@pytest.mark.parametrize("task, calls", [
    ("_values", "once"),
    ("lambda block, rng, *, scale: _values(block, rng, scale=scale)", "per process"),
    # a task whose pickling raises something else than a PicklingError (as a netCDF4 Dataset does)
    ("type('NoPickle', (), {'__reduce__': lambda self: (_ for _ in ()).throw(NotImplementedError('no')), "
     "'__call__': lambda self, block, rng, *, scale: _values(block, rng, scale=scale)})()", "per process"),
])
def test_the_workers_get_the_runners_stage_instead_of_building_it_again(tmp_path, task, calls):
    """The runner builds a stage once and sends it with its blocks: the stage function (which may
    be an identification from earlier results) runs in the runner only. A stage that cannot be
    pickled by reference (a lambda as its task) is rebuilt by each worker, as before. Both give the
    in-process result."""
    log = tmp_path / "calls.log"
    (tmp_path / "shipped.py").write_text(SHIPPED.format(log=str(log), task=task))
    run(tmp_path / "shipped.py", tmp_path / "here.zarr", workers=0, quiet=True)
    assert log.read_text().split() == [str(os.getpid())]
    log.unlink()
    rep = run(tmp_path / "shipped.py", tmp_path / "two.zarr", workers=2, quiet=True)
    assert rep.computed == 10
    assert store_digest(tmp_path / "two.zarr") == store_digest(tmp_path / "here.zarr")
    pids = log.read_text().split()
    assert pids.count(str(os.getpid())) == 1, pids
    others = [p for p in pids if p != str(os.getpid())]
    if calls == "once":
        assert others == [], pids
    else:
        assert 1 <= len(others) <= 2 and len(set(others)) == len(others), pids  # once per worker that ran blocks
