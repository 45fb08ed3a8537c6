"""Study runner, in-process part: study validation, seeding, store layout, resume, refusals, CLI, config.

The blocks run sequentially in this process (``workers=0``, the same ``run_block`` the dask workers
run); the real multi-process tests are in test_runner_distributed.py.
"""

import hashlib
import json
import os
import pathlib
import subprocess
import sys

import numpy as np
import pytest
import xarray as xr
import yaml

from tubeid.errors import SpecificationError
from tubeid.runner.cli import main as cli
from tubeid.runner.execute import run
from tubeid.runner.store import open_results, store_status
from tubeid.runner.study import Output, Parameter, Study, load_study, pointwise
from tubeid.runner.testing import clear_flag, store_digest, write_study
from tubeid.seeds import rng_for

REPO = pathlib.Path(__file__).resolve().parents[1]


def _task(block, rng, *, k=1):
    return {"y": np.zeros((len(block["r"]),))}


def _study(**kw):
    base = dict(name="s", seed=1, axes={"r": range(4)}, task=_task, outputs={"y": Output()})
    base.update(kw)
    return Study(**base)


# -- definition refused before anything runs ------------------------------------------------------
@pytest.mark.parametrize("kw, field", [
    (dict(parameters={"bogus": 1}), "parameters.bogus"),                     # unknown to the task
    (dict(parameters={"k": Parameter(5, bounds=(0, 3))}), "parameters.k"),  # outside bounds
    (dict(parameters={"k": Parameter(5, choices=[1, 2])}), "parameters.k"),  # not a choice
    (dict(parameters={"k": float("nan")}), "parameters.k"),                  # not plain/finite
    (dict(axes={"r": []}), "axes.r"),                                        # empty axis
    (dict(axes={}), "axes"),
    (dict(axes={"r": [1, 1]}), "axes.r"),                                    # repeated coordinate
    (dict(chunks={"q": 2}), "chunks.q"),
    (dict(chunks={"r": 0}), "chunks.r"),
    (dict(seed=-1), "seed"),
    (dict(seed_axes=("q",)), "seed_axes"),
    (dict(in_process=1), "in_process"),                                      # not a bool
    (dict(outputs={"y": Output(dims=("f",))}), "outputs.y.dims"),            # extra dim without coords
    (dict(name="a b"), "name"),
])
def test_bad_definitions_are_refused(kw, field):
    with pytest.raises(SpecificationError) as err:
        _study(**kw)
    assert err.value.field == field


def test_parameter_overrides_are_validated():
    s = _study(parameters={"k": Parameter(1, bounds=(0, 3))})
    assert s.with_parameters({"k": 2}).values == {"k": 2}
    with pytest.raises(SpecificationError, match="unknown parameter"):
        s.with_parameters({"kk": 2})
    with pytest.raises(SpecificationError, match=r"must lie in \[0, 3\]"):
        s.with_parameters({"k": 4})


def test_cli_refuses_bad_override_before_creating_a_store(tmp_path, capsys):
    study = write_study(tmp_path)
    store = tmp_path / "out.zarr"
    assert cli(["run", str(study), "--store", str(store), "--workers", "0", "--set", "wrok=3"]) == 2
    assert "parameters.wrok = 3: unknown parameter" in capsys.readouterr().err
    assert cli(["run", str(study), "--store", str(store), "--workers", "0", "--set", "label='z'"]) == 2
    assert cli(["run", str(study), "--store", str(store), "--workers", "0", "--set", "work={1}"]) == 2  # a set: not plain
    assert "parameters.work = {1}: must be a plain finite value" in capsys.readouterr().err
    assert not store.exists()
    # the SG+ example refuses a delta grid outside SG+'s admissible range for the requested n
    assert cli(["run", str(REPO / "studies/example_sgplus.py"), "--store", str(store), "--workers", "0",
                "--set", "n=1"]) == 2
    assert "axes.delta" in capsys.readouterr().err and not store.exists()


class _Below(Parameter):
    """A parameter whose admissible set depends on another parameter: k < limit."""

    def check_with(self, name, value, values):
        if not value < values["limit"]:
            raise SpecificationError(f"parameters.{name}", value, f"must be below parameters.limit = {values['limit']}")


def _limited_task(block, rng, *, k=1, limit=3):
    return {"y": np.zeros((len(block["r"]),))}


def test_a_parameter_check_may_depend_on_other_parameters(tmp_path, capsys):
    """``Parameter.check_with`` sees every parameter's value: its rule holds for the defaults, for overrides of
    either parameter, and ``tubeid run`` refuses a breach before any store is created."""
    s = _study(task=_limited_task, parameters={"k": _Below(1, bounds=(0, 10)), "limit": Parameter(3)})
    assert s.with_parameters({"k": 2}).values == {"k": 2, "limit": 3}
    assert s.with_parameters({"k": 5, "limit": 6}).values == {"k": 5, "limit": 6}
    for overrides in ({"k": 3}, {"limit": 1}):
        with pytest.raises(SpecificationError, match=r"parameters\.k = \d: must be below parameters\.limit = \d"):
            s.with_parameters(overrides)
    source = ("import numpy as np\n"
              "from tubeid.errors import SpecificationError\n"
              "from tubeid.runner.study import Output, Parameter, Study\n"
              "class Below(Parameter):\n"
              "    def check_with(self, name, value, values):\n"
              "        if not value < values['limit']:\n"
              "            raise SpecificationError('parameters.' + name, value, 'must be below limit')\n"
              "def task(block, rng, *, k, limit):\n"
              "    return {'y': np.zeros(len(block['r']))}\n"
              "study = Study(name='limited', seed=1, axes={'r': range(2)}, task=task, outputs={'y': Output()},\n"
              "              parameters={'k': Below(1), 'limit': LIMIT})\n")
    path, store = tmp_path / "limited.py", tmp_path / "limited.zarr"
    for limit, sets in ((3, ["k=4"]), (3, ["limit=0"]), (0, [])):  # an override, or the defaults themselves
        path.write_text(source.replace("LIMIT", str(limit)))
        argv = ["run", str(path), "--store", str(store), "--workers", "0"] + [a for v in sets for a in ("--set", v)]
        assert cli(argv) == 2, sets
        err = capsys.readouterr().err
        assert err.startswith("tubeid: error: parameters.k = ") and "must be below limit" in err and err.count("\n") == 1
        assert not store.exists()


TINY = """import numpy as np
from tubeid.runner.study import Output, Study, pointwise
@pointwise
def f(point, rng):
    return {'y': float(point['r']) + rng.standard_normal()}
study = Study(name='tiny', seed=3, axes={'r': range(2)}, task=f, outputs={'y': Output(units='m')}, description=NAME)
"""


def test_a_study_file_is_decoded_as_python_decodes_it(tmp_path, capsys):
    """A study file in another encoding declared by a PEP 263 coding line runs (it used to be a
    UnicodeDecodeError traceback) and stores its decoded text; a file that cannot be decoded is one error line
    naming it; a UTF-8 file's text and study hash are what ``Path.read_text`` gives (CRLF line endings too)."""
    from tubeid.cli import main
    from tubeid.runner.study import load_definition, read_source, study_hash

    latin = tmp_path / "latin.py"
    latin.write_bytes(("# -*- coding: latin-1 -*-\n" + TINY.replace("NAME", "'étude'")).encode("latin-1"))
    assert main(["run", str(latin), "--store", str(tmp_path / "latin.zarr"), "--workers", "0", "--no-progress"]) == 0
    assert open_results(tmp_path / "latin.zarr").attrs["title"] == "étude"
    assert store_status(tmp_path / "latin.zarr")["attrs"]["study_source"] == read_source(latin)
    capsys.readouterr()
    for name, data, why in (
            ("noutf8.py", b"# \xff\xfe\n" + TINY.replace("NAME", "''").encode(), "byte 0xff at position 2 is not UTF-8"),
            ("late.py", TINY.replace("NAME", "''").encode() + b"# \xe9\n", "is not UTF-8"),
            ("cookie.py", b"# coding: no-such-codec\n" + TINY.replace("NAME", "''").encode(), "unknown encoding"),
            ("ascii.py", b"# coding: ascii\n" + TINY.replace("NAME", "'\xc3\xa9'").encode(), "'ascii' codec")):
        path, store = tmp_path / name, tmp_path / f"{name}.zarr"
        path.write_bytes(data)
        assert main(["run", str(path), "--store", str(store), "--workers", "0"]) == 2, name
        err = capsys.readouterr().err
        assert err.startswith(f"tubeid: error: study = {str(path)!r}: cannot be decoded (") and why in err, err
        assert err.count("\n") == 1 and "Traceback" not in err and not store.exists()
    crlf = tmp_path / "crlf.py"
    crlf.write_bytes(TINY.replace("NAME", "'é'").replace("\n", "\r\n").encode())
    for path in (crlf, REPO / "studies" / "paper.py", REPO / "studies" / "pi.py"):
        assert read_source(path) == path.read_text()  # the text, hence the hash, of existing stores' studies
    assert load_definition(crlf)[2] == study_hash(crlf.read_text())


FAILING_AT_IMPORT = """import numpy as np

def helper(x):
    return np.linalg.inv(x)   # a library's frames below this line are not the study's

try:
    {}["k"]
except KeyError:
    helper(np.zeros((2, 2)))
"""


def test_a_study_that_raises_at_import_shows_its_own_frames_then_one_line(tmp_path, capsys):
    """A study file whose code raises: the traceback of the study's own frames (none of tubeid's or of the
    libraries'), then ``tubeid: error: study = ...: raised TYPE: MESSAGE while being executed``, status 1, as a
    failing task; no store. A refusal raised by tubeid while the study builds itself stays one line (status 2)."""
    from tubeid.cli import main
    from tubeid.runner.study import StudyRaised, load_definition

    boom = tmp_path / "r.py"
    boom.write_text('raise RuntimeError("boom")\n')
    store = tmp_path / "r.zarr"
    assert main(["run", str(boom), "--store", str(store), "--workers", "0"]) == 1
    err = capsys.readouterr().err
    lines = err.rstrip("\n").splitlines()
    assert lines == ["Traceback (most recent call last):", f'  File "{boom}", line 1, in <module>',
                     '    raise RuntimeError("boom")', "RuntimeError: boom",
                     f"tubeid: error: study = {str(boom)!r}: raised RuntimeError: boom while being executed"], err
    assert not store.exists()

    lib = tmp_path / "lib.py"
    lib.write_text(FAILING_AT_IMPORT)
    assert main(["run", str(lib), "--store", str(store), "--workers", "0"]) == 1
    err = capsys.readouterr().err
    assert err.count(f'File "{lib}"') == 3 and "in helper" in err and "KeyError: 'k'" in err  # the chain is kept
    assert "/tubeid/" not in err and "numpy" + os.sep not in err and "site-packages" not in err and "<frozen" not in err
    assert err.rstrip().splitlines()[-1] == (f"tubeid: error: study = {str(lib)!r}: raised LinAlgError: Singular matrix "
                                             "while being executed")
    with pytest.raises(StudyRaised) as info:
        load_definition(lib)
    assert type(info.value.__cause__).__name__ == "LinAlgError"
    import pickle

    again = pickle.loads(pickle.dumps(info.value))  # it may come back from a worker
    assert str(again) == str(info.value) and again.user_traceback == info.value.user_traceback

    refused = tmp_path / "refused.py"
    refused.write_text("from tubeid.runner.study import Output, Study\n"
                       "study = Study(name='x', seed=1, axes={}, task=print, outputs={'y': Output()})\n")
    assert main(["run", str(refused), "--store", str(store), "--workers", "0"]) == 2
    err = capsys.readouterr().err
    assert err == "tubeid: error: axes = {}: must name at least one axis\n"


def test_unwritable_store_is_refused_up_front(tmp_path):
    study = write_study(tmp_path)
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    for bad in (blocker / "out.zarr", blocker):  # parent is a file; the store itself is a file
        with pytest.raises(SpecificationError, match="store"):
            run(study, bad, workers=0, quiet=True)
    if os.geteuid() != 0:  # root ignores permission bits
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o555)
        with pytest.raises(SpecificationError, match="not writable"):
            run(study, ro / "out.zarr", workers=0, quiet=True)


# -- seeding ------------------------------------------------------------------------------------------
def test_streams_are_keyed_by_seed_axis_coordinates_only(tmp_path):
    study_a = write_study(tmp_path, "a.py", realisations=6, chunk=2, work=3)
    study_b = write_study(tmp_path, "b.py", realisations=6, chunk=5, work=3)  # other blocks
    run(study_a, tmp_path / "a.zarr", workers=0, quiet=True)
    run(study_b, tmp_path / "b.zarr", workers=0, quiet=True)
    a, b = open_results(tmp_path / "a.zarr").load(), open_results(tmp_path / "b.zarr").load()
    np.testing.assert_array_equal(a.x.values, b.x.values)  # bit-identical whatever the chunking
    # common random numbers across delta: 0.2 * v == 2 * (0.1 * v) exactly (scaling by 2 is exact)
    np.testing.assert_array_equal(a.x.sel(delta=0.2).values, 2 * a.x.sel(delta=0.1).values)
    # independent re-computation of one point from tubeid.seeds.rng_for(seed, realisation)
    v = rng_for(7, 4).standard_normal((48, 48))
    for _ in range(3):
        v = np.tanh(v @ v.T / 48.0)
    np.testing.assert_array_equal(a.x.sel(delta=0.1, realisation=4).values, 0.1 * v[:3, 0])


TWO_SEED_AXES = '''
import numpy as np
from tubeid.runner.study import Output, Study

def task(block, rng):
    r, p, g = block["realisation"], block["point"], block["gain"]
    out = np.empty((r.size, p.size, g.size, 4))
    for i, real in enumerate(r):
        for j, pt in enumerate(p):
            out[i, j, :] = rng(point=pt, realisation=real).standard_normal(4)  # keywords in any order
    return {"draw": out * g[None, None, :, None]}

study = Study(name="two-seed-axes", seed=2024, axes={"realisation": range(3), "point": range(3), "gain": [1.0, 2.0]},
              chunks={"realisation": 2, "point": 2}, seed_axes=("realisation", "point"), stream_key=("draws",),
              task=task, coords={"k": range(4)}, outputs={"draw": Output(dims=("k",))})
'''


def _documented_spawn_key(*key):
    """The documented key rule (tubeid/seeds.py), rebuilt with hashlib: an int in [0, 2³²) as itself,
    anything else as the two little-endian 32-bit words of the 8-byte BLAKE2b digest of its repr."""
    out = []
    for part in key:
        if isinstance(part, int) and 0 <= part < 2**32:
            out.append(part)
        else:
            digest = hashlib.blake2b(repr(part).encode(), digest_size=8).digest()
            out.extend(int.from_bytes(digest[i:i + 4], "little") for i in (0, 4))
    return tuple(out)


def test_stored_draws_follow_the_seed_axes_in_their_declared_order(tmp_path):
    """Two seed axes: the store holds PCG64(SeedSequence(seed, spawn_key=(stream_key, realisation, point)))
    draws, computed here with numpy alone; (realisation, point) = (1, 2) and (2, 1) are different draws."""
    path = tmp_path / "two.py"
    path.write_text(TWO_SEED_AXES)
    run(path, tmp_path / "two.zarr", workers=0, quiet=True)
    draw = open_results(tmp_path / "two.zarr").draw.load()
    for real in range(3):
        for pt in range(3):
            seq = np.random.SeedSequence(2024, spawn_key=_documented_spawn_key("draws", real, pt))
            expected = np.random.Generator(np.random.PCG64(seq)).standard_normal(4)
            for gain in (1.0, 2.0):  # gain is not a seed axis: the same stream, scaled exactly
                np.testing.assert_array_equal(draw.sel(realisation=real, point=pt, gain=gain).values, gain * expected,
                                              err_msg=f"stored draw at realisation={real}, point={pt}, gain={gain} "
                                                      "is not the documented stream")
    swapped = draw.sel(gain=1.0)
    assert not np.array_equal(swapped.sel(realisation=1, point=2).values, swapped.sel(realisation=2, point=1).values), \
        "swapping the coordinates of two seed axes gave the same draws: the stream key ignores their order"


def test_rng_factory_requires_exactly_the_seed_axes():
    s = _study(axes={"r": range(3), "d": [0.5, 1.0]}, seed_axes=("r",))
    assert s.rng(r=2).random() == rng_for(1, 2).random()
    assert s.rng.at({"r": 2, "d": 0.5}).random() == s.rng.at({"r": 2, "d": 1.0}).random()
    with pytest.raises(SpecificationError, match="seed axes"):
        s.rng(r=2, d=0.5)
    # numpy and Python scalars give the same stream (keys use Python scalars)
    s2 = _study(axes={"d": [0.5, 1.0]})
    assert s2.rng(d=np.float64(0.5)).random() == s2.rng(d=0.5).random() == rng_for(1, 0.5).random()


def test_pointwise_stacks_per_point_results():
    @pointwise
    def f(point, rng, *, scale):
        return {"u": scale * point["a"] + point["b"], "v": np.full(2, rng.random())}

    s = Study(name="p", seed=3, axes={"a": [1.0, 2.0], "b": [10, 20, 30]}, task=f, seed_axes=("b",),
              coords={"two": [0, 1]}, outputs={"u": Output(), "v": Output(dims=("two",))},
              parameters={"scale": 3.0})
    out = s.compute_block(s.block((0, 0)))
    np.testing.assert_array_equal(out["u"], [[13, 23, 33], [16, 26, 36]])
    assert out["v"].shape == (2, 3, 2)
    np.testing.assert_array_equal(out["v"][0, :, 0], out["v"][1, :, 0])  # keyed by b only
    assert out["v"][0, 1, 0] == rng_for(3, 20).random()


def test_task_result_shape_is_checked():
    s = _study(task=lambda block, rng: {"y": np.zeros(3)})
    with pytest.raises(SpecificationError, match="y.shape"):
        s.compute_block(s.block((0,)))


# -- store: layout, provenance, partial results, resume ---------------------------------------------
def test_store_layout_and_provenance(tmp_path):
    study = write_study(tmp_path, realisations=6, chunk=4, work=2)
    report = run(study, tmp_path / "s.zarr", workers=0, quiet=True)
    assert (report.total, report.computed, report.skipped) == (4, 4, 0)
    ds = xr.open_zarr(tmp_path / "s.zarr")  # plain xarray works too
    assert ds.x.dims == ("delta", "realisation", "component")
    assert ds.x.encoding["chunks"] == (1, 4, 3) and ds.x.attrs["units"] == "m"
    assert ds["count"].dtype == np.int32 and (ds["count"].values == 2).all()
    assert list(ds.component.values) == ["a", "b", "c"] and ds.delta.attrs["units"] == "1"
    a = ds.attrs
    assert a["study_source"] == study.read_text() and a["study_hash"] == load_study(study)[2]
    assert a["seed"] == 7 and a["seed_axes"] == ["realisation"]
    assert json.loads(a["parameters"]) == {"work": 2, "label": "x"}
    assert a["model_specification"] == "MODEL-SPEC-TEXT" and a["tubeid_version"]
    assert a["started"] <= a["finished"]
    assert store_status(tmp_path / "s.zarr")["complete"]


def test_interrupted_run_is_partial_readable_and_resumes_identically(tmp_path, monkeypatch):
    study = write_study(tmp_path, realisations=8, chunk=2, work=2)
    run(study, tmp_path / "ref.zarr", workers=0, quiet=True)
    monkeypatch.setenv("TUBEID_TEST_FAIL_AT", "5")  # blocks are run in C order: (0,0),(0,1),(0,2) fail
    with pytest.raises(RuntimeError, match="on purpose"):
        run(study, tmp_path / "s.zarr", workers=0, quiet=True)
    st = store_status(tmp_path / "s.zarr")
    assert (st["done"], st["total"], st["complete"]) == (2, 8, False)
    part = open_results(tmp_path / "s.zarr")
    assert part.attrs["blocks_done"] == 2
    assert np.isfinite(part.x.sel(delta=0.1, realisation=[0, 1, 2, 3])).all()
    assert np.isnan(part.x.sel(realisation=[4, 5, 6, 7])).all()  # unwritten chunks read as NaN
    monkeypatch.delenv("TUBEID_TEST_FAIL_AT")
    report = run(study, tmp_path / "s.zarr", workers=0, quiet=True)
    assert (report.computed, report.skipped) == (6, 2)
    assert store_digest(tmp_path / "s.zarr") == store_digest(tmp_path / "ref.zarr")
    assert len(store_status(tmp_path / "s.zarr")["attrs"]["runs"]) == 2
    again = run(study, tmp_path / "s.zarr", workers=0, quiet=True)  # complete: nothing to do
    assert again.computed == 0


def test_a_resume_removes_the_temporaries_a_killed_write_left_and_nothing_else(tmp_path, monkeypatch, capsys):
    """A SIGKILL between zarr's write of ``<chunk>.<32 hex>.partial`` and its rename leaves that file
    (seen in CI); the resume removes it (and ``zarr.<32 hex>.partial``, tubeid's ``.tubeid-tmp-`` +
    8 characters), never a user's look-alike, nor a file behind a link among the chunks."""
    study = write_study(tmp_path, realisations=8, chunk=2, work=2)
    run(study, tmp_path / "ref.zarr", workers=0, quiet=True)
    monkeypatch.setenv("TUBEID_TEST_FAIL_AT", "5")
    with pytest.raises(RuntimeError, match="on purpose"):
        run(study, tmp_path / "s.zarr", workers=0, quiet=True)
    monkeypatch.delenv("TUBEID_TEST_FAIL_AT")
    store = tmp_path / "s.zarr"
    hexes = "f810c525c188462d986b9aa970a711e3"
    left = [store / f"x/c/0/2/0.{hexes}.partial", store / f"x/zarr.{hexes}.partial", store / ".tubeid-tmp-abc12_de"]
    users = [store / "x/c/0/2/0.notes.partial", store / "x/notes.partial", store / "mine" / f"a.{hexes}.partial",
             store / ".tubeid-tmp-my-notes.txt", store / f"my-download.{hexes}.partial"]
    outside = tmp_path / "elsewhere" / "c"
    (outside / "0").mkdir(parents=True)
    (outside / "0" / f"9.{hexes}.partial").write_bytes(b"")
    for f in left + users:
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_bytes(b"")
    (store / "x" / "c" / "9").symlink_to(outside / "0")  # a link among an array's chunks is not entered
    run(study, store, workers=0)
    err = capsys.readouterr().err
    assert "removed 3 temporary file(s)" in err
    assert not any(f.exists() for f in left)
    assert all(f.exists() for f in users) and (outside / "0" / f"9.{hexes}.partial").exists()
    for f in users:
        f.unlink()
    (store / "mine").rmdir()
    (store / "x" / "c" / "9").unlink()
    assert store_digest(store) == store_digest(tmp_path / "ref.zarr")
    # a manifest that cannot be read proves nothing tubeid's: the temporary stays, the run goes on (noted once)
    left[0].write_bytes(b"")
    (store / ".tubeid-manifest.json").write_text("{damaged")
    run(study, store, workers=0)
    err = capsys.readouterr().err
    assert left[0].exists() and err.count("are left in place") == 1


def test_store_of_another_study_is_refused_unless_asked(tmp_path, capsys):
    study = write_study(tmp_path, realisations=4, work=2)
    run(study, tmp_path / "s.zarr", workers=0, quiet=True)
    before = store_digest(tmp_path / "s.zarr")
    with pytest.raises(SpecificationError, match="different study definition"):
        run(study, tmp_path / "s.zarr", workers=0, quiet=True, overrides={"work": 3})
    assert store_digest(tmp_path / "s.zarr") == before
    other = write_study(tmp_path, "other.py", realisations=4, work=3)
    rep = run(other, tmp_path / "s.zarr", workers=0, quiet=True, new_store=True)
    assert rep.store.name.startswith("s-") and rep.store.name.endswith(".zarr")
    assert store_digest(tmp_path / "s.zarr") == before
    rep = run(other, tmp_path / "s.zarr", workers=0, quiet=True, overwrite=True)
    assert rep.store == (tmp_path / "s.zarr").resolve()
    assert (open_results(tmp_path / "s.zarr")["count"].values == 3).all()
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "f.txt").write_text("x")
    with pytest.raises(SpecificationError, match="not a"):
        run(other, tmp_path / "junk", workers=0, quiet=True)


# -- CLI and configuration -----------------------------------------------------------------------------
def test_status_and_show_cli(tmp_path, capsys):
    study = write_study(tmp_path, realisations=4, work=2)
    assert cli(["run", str(study), "--store", str(tmp_path / "s.zarr"), "--workers", "0", "--no-progress"]) == 0
    capsys.readouterr()
    assert cli(["status", str(tmp_path / "s.zarr")]) == 0
    assert "runner-test: 4/4 blocks done (100.0 %), complete" in capsys.readouterr().out
    assert cli(["status", str(tmp_path / "s.zarr"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["done"] == 4
    assert cli(["show", str(tmp_path / "s.zarr")]) == 0
    out = capsys.readouterr().out
    assert "study runner-test" in out and "x [m]:" in out and "(100% written)" in out
    assert cli(["status", str(tmp_path / "nothing.zarr")]) == 2


def _edit_attrs(store, **changes):
    """Set root attributes of a store as a damaged or hand-edited one would have them."""
    meta_path = pathlib.Path(store) / "zarr.json"
    meta = json.loads(meta_path.read_text())
    meta["attributes"].update(changes)
    meta_path.write_text(json.dumps(meta))


def test_status_and_show_report_damaged_attributes_without_a_traceback(tmp_path, capsys):
    """Store attributes of an unexpected type (a damaged or hand-edited store): ``status`` and ``show`` show
    them as damaged (they used to end in TypeError/KeyError tracebacks); a pipeline whose stage list is
    damaged is refused in one line."""
    from tubeid.cli import main
    from tubeid.runner.testing import write_pipeline

    study = write_study(tmp_path, realisations=4, work=2)
    store = tmp_path / "t.zarr"
    run(study, store, workers=0, quiet=True)
    _edit_attrs(store, runs=5, summary_keys=["nope"], model_specification=5, study_source=7)
    assert main(["status", str(store)]) == 0
    out, err = capsys.readouterr()
    assert "runs: DAMAGED (attribute runs = 5)" in out and err == ""
    assert main(["show", str(store), "--source"]) == 0
    out, err = capsys.readouterr()
    assert "summary: nope = DAMAGED (attribute missing)" in out and err == ""
    assert "model specification: DAMAGED (attribute model_specification = 5)" in out
    assert "# study source\nDAMAGED (attribute study_source = 7)" in out
    _edit_attrs(store, summary_keys=5)
    assert main(["show", str(store)]) == 0
    assert "summary: DAMAGED (attribute summary_keys = 5)" in capsys.readouterr().out

    pipe = tmp_path / "p.zarr"
    run(write_pipeline(tmp_path, curve=2, around=2, work=0), pipe, workers=0, quiet=True)
    _edit_attrs(pipe, ended=5, runs={"a": 1})
    for command in ("status", "show"):
        assert main([command, str(pipe)]) == 0
        out, err = capsys.readouterr()
        assert "ended: DAMAGED (attribute ended = 5)" in out and err == "", command
    for damage, shown in (({"stages": 5}, "stages = 5"), ({"stages": ["curve", 3]}, "stages = ['curve', 3]"),
                          ({"stages": ["curve", "around", "final"], "stage_status": [1]}, "stage_status = [1]")):
        _edit_attrs(pipe, **damage)
        for command in ("status", "show"):
            assert main([command, str(pipe)]) == 2
            out, err = capsys.readouterr()
            assert err.startswith(f"tubeid: error: store = {str(pipe)!r}: has a damaged attribute {shown}"), err
            assert err.count("\n") == 1 and "Traceback" not in err


def test_worker_environ_goes_over_dasks_and_refuses_bad_entries():
    """The embedded workers' environment: dask's pre-spawn-environ with tubeid.runner.worker-environ
    over it (tubeid's values replace dask's, dask's other variables stay); a bad entry is refused
    naming the field, the value and the rule (a mangled TUBEID_... override, a MALLOC_ value glibc
    would ignore, which brings dask's fixed 128 KiB mmap threshold back)."""
    import dask

    from tubeid import config
    from tubeid.runner.execute import _worker_environ

    packaged = yaml.safe_load((REPO / "tubeid/tubeid.yaml").read_text())["tubeid"]["runner"]["worker-environ"]
    assert packaged["MALLOC_TRIM_THRESHOLD_"] > 65536 and 131072 < packaged["MALLOC_MMAP_THRESHOLD_"] <= 32 * 2**20
    ours = {"MALLOC_TRIM_THRESHOLD_": 268435456, "MALLOC_MMAP_THRESHOLD_": "33554432", "OTHER": None}
    with dask.config.set({"distributed.nanny.pre-spawn-environ": {"MALLOC_TRIM_THRESHOLD_": 65536, "OMP_NUM_THREADS": 1},
                          "tubeid.runner.worker-environ": ours}):
        assert _worker_environ() == {"MALLOC_TRIM_THRESHOLD_": 268435456, "OMP_NUM_THREADS": 1,
                                     "MALLOC_MMAP_THRESHOLD_": "33554432", "OTHER": None}
    # what TUBEID_RUNNER__WORKER_ENVIRON__MALLOC_TRIM_THRESHOLD_=1 makes of the name
    mangled = config.collect_env({"TUBEID_RUNNER__WORKER_ENVIRON__MALLOC_TRIM_THRESHOLD_": "1"})
    (name,) = mangled["tubeid"]["runner"]["worker-environ"]
    for bad, field, rule in (([1], "runner.worker-environ", "must be a mapping"),
                             ({name: 1}, "runner.worker-environ", "TUBEID_RUNNER__WORKER_ENVIRON='{"),
                             ({"malloc_trim_threshold_": 1}, "runner.worker-environ", "upper-case"),
                             ({"A=B": 1}, "runner.worker-environ", "upper-case"),
                             ({"X": True}, "runner.worker-environ.X", "string, an integer or null"),
                             ({"X": 1.5}, "runner.worker-environ.X", "string, an integer or null"),
                             ({"MALLOC_MMAP_THRESHOLD_": "32MiB"}, "runner.worker-environ.MALLOC_MMAP_THRESHOLD_",
                              "number of bytes"),
                             ({"MALLOC_TRIM_THRESHOLD_": -1}, "runner.worker-environ.MALLOC_TRIM_THRESHOLD_",
                              "number of bytes"),
                             ({"MALLOC_TRIM_THRESHOLD_": "\u00b2"}, "runner.worker-environ.MALLOC_TRIM_THRESHOLD_",
                              "number of bytes")):
        with dask.config.set({"tubeid.runner.worker-environ": bad}), pytest.raises(SpecificationError) as err:
            _worker_environ()
        # named as every setting is, with the variable that sets the whole mapping (never the mangled one)
        assert err.value.field == f"tubeid.{field} (TUBEID_RUNNER__WORKER_ENVIRON)" and rule in str(err.value), \
            (bad, str(err.value))
    with dask.config.set({"distributed.nanny.pre-spawn-environ": ["x"]}), pytest.raises(SpecificationError) as err:
        _worker_environ()
    assert err.value.field == "distributed.nanny.pre-spawn-environ"


def test_configuration_env_overrides_and_default_chunk(tmp_path):
    from tubeid import config

    env = {"TUBEID_RUNNER__DEFAULT_CHUNK": "3", "TUBEID_RUNNER__HOST": "0.0.0.0", "OTHER": "1"}
    assert config.collect_env(env) == {"tubeid": {"runner": {"default-chunk": 3, "host": "0.0.0.0"}}}
    code = ("from tubeid import config; from tubeid.runner.study import Study, Output;"
            "s = Study(name='c', seed=0, axes={'r': range(10)}, task=lambda b, rng: 0, outputs={'y': Output()});"
            "print(s.chunks['r'], config.get('runner.workers'))")
    env = dict(os.environ, TUBEID_RUNNER__DEFAULT_CHUNK="3", TUBEID_RUNNER__WORKERS="5")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    assert out.split() == ["3", "5"]


DEFAULT_CHUNK_STUDY = """
import numpy as np
from tubeid.runner.study import Output, Study
study = Study(name="dc", seed=3, axes={"r": range(12)}, outputs={"y": Output()},
              task=lambda block, rng: {"y": np.asarray(block["r"], float) * 2.0})
"""


def test_resume_with_another_default_chunk_is_refused(tmp_path, monkeypatch):
    """The block layout comes from the configuration when a study gives no chunks: a resume (or a
    worker) with another default chunk would write the wrong regions, so it is refused by name."""
    import dask.config
    import zarr

    import tubeid.runner.study as study_module
    from tubeid.runner.store import write_block

    path = tmp_path / "dc.py"
    path.write_text(DEFAULT_CHUNK_STUDY)
    store = tmp_path / "dc.zarr"
    with dask.config.set({"tubeid.runner.default-chunk": 4}):
        run(path, store, workers=0, quiet=True)
        four = load_study(path)[0]
    clear_flag(store, (1,))  # as if interrupted before block 1 finished
    monkeypatch.setattr(study_module, "_DEFINITIONS", {})  # a fresh process would rebuild the definition
    with dask.config.set({"tubeid.runner.default-chunk": 3}):
        three = load_study(path)[0]
        assert three.chunks == {"r": 3}
        with pytest.raises(SpecificationError, match=r"chunks = \{'r': 3\}: .* blocks of \{'r': 4\}"):
            run(path, store, workers=0, quiet=True)
        with pytest.raises(SpecificationError, match="chunks"):  # the worker-side guard
            write_block(store, three, three.block((1,)), {"y": np.zeros(3)})
    monkeypatch.setattr(study_module, "_DEFINITIONS", {})
    with dask.config.set({"tubeid.runner.default-chunk": 4}):
        run(path, store, workers=0, quiet=True)  # the store's own layout resumes
    np.testing.assert_array_equal(open_results(store).y.values, 2.0 * np.arange(12))
    assert four.chunks == {"r": 4}


def test_example_studies_load_and_pi_runs(tmp_path):
    for f in sorted((REPO / "studies").glob("example_*.py")):
        assert isinstance(load_study(f)[0], Study)
    run(REPO / "studies/pi.py", tmp_path / "pi.zarr", workers=0, quiet=True, overrides={"samples": 2000})
    pi = open_results(tmp_path / "pi.zarr").pi
    assert pi.sizes == {"realisation": 256}
    # each estimate has sd sqrt(pi (4 - pi) / 2000) = 0.0367; the mean of 256 has sd 0.0023: 5 sd
    assert abs(float(pi.mean()) - np.pi) < 5 * np.sqrt(np.pi * (4 - np.pi) / 2000 / 256)
    assert float(pi.std()) == pytest.approx(np.sqrt(np.pi * (4 - np.pi) / 2000), rel=0.25, abs=0)  # sd of sd ~ 4.4 %


def test_cluster_configurations_are_consistent():
    import yaml

    c = REPO / "cluster"
    packaged = yaml.safe_load((REPO / "tubeid/tubeid.yaml").read_text())["tubeid"]["runner"]
    local = yaml.safe_load((c / "local/tubeid-local.yaml").read_text())["tubeid"]["runner"]
    assert local == packaged  # the documented local default is the packaged one
    compose = yaml.safe_load((c / "docker/compose.yaml").read_text())["services"]
    assert "tcp://scheduler:8786" in compose["worker"]["command"] and "--nthreads" in compose["worker"]["command"]
    assert compose["runner"]["environment"]["DASK_SCHEDULER_ADDRESS"] == "tcp://scheduler:8786"
    job = yaml.safe_load((c / "kubernetes/daskjob.yaml").read_text())
    assert job["kind"] == "DaskJob" and job["apiVersion"] == "kubernetes.dask.org/v1"
    runner = job["spec"]["job"]["spec"]["containers"][0]
    worker = job["spec"]["cluster"]["spec"]["worker"]["spec"]["containers"][0]
    assert runner["args"][:2] == ["tubeid", "run"]
    # the runner's settings from the job's environment, read as tubeid reads TUBEID_... variables
    from tubeid import config

    env = {e["name"]: e["value"] for e in runner["env"]}
    assert config.collect_env(env)["tubeid"]["runner"]["connect-timeout"] == "300s"
    from dask.utils import parse_timedelta

    assert parse_timedelta(env["TUBEID_RUNNER__CONNECT_TIMEOUT"]) > parse_timedelta(packaged["connect-timeout"])
    mount = {m["name"]: m["mountPath"] for m in runner["volumeMounts"]}["results"]
    assert {m["name"]: m["mountPath"] for m in worker["volumeMounts"]}["results"] == mount  # same store path
    slurm = yaml.safe_load((c / "slurm/jobqueue.yaml").read_text())["jobqueue"]["slurm"]
    assert slurm["cores"] == slurm["processes"]  # single-threaded workers
    # the workers of every deployment get the embedded workers' allocator variables
    malloc = {k: str(v) for k, v in packaged["worker-environ"].items() if k.startswith("MALLOC_")}
    assert len(malloc) == 2
    assert {k: compose["worker"]["environment"].get(k) for k in malloc} == malloc
    assert compose["worker"]["environment"]["TUBEID_RUNNER__STORE_ROOT"] == "/results"
    assert {k: {e["name"]: e["value"] for e in worker["env"]}.get(k) for k in malloc} == malloc
    exports = " ".join(line for line in slurm["job-script-prologue"] if line.startswith("export "))
    assert all(f"{k}={v}" in exports.split() for k, v in malloc.items()), exports
    tls = (c / "tls/dask-tls.yaml.in").read_text()
    assert "require-encryption: true" in tls
    for role in ("scheduler", "worker", "client"):
        assert f"@DIR@/{role}.pem" in tls and f"@DIR@/{role}-key.pem" in tls


def test_slurm_job_script_has_single_threaded_workers():
    pytest.importorskip("dask_jobqueue")
    out = subprocess.run([sys.executable, str(REPO / "cluster/slurm/run_study.py"), "x.py", "--print-job-script"],
                         capture_output=True, text=True, check=True).stdout
    assert "#SBATCH --cpus-per-task=8" in out and "--nthreads 1" in out and "--nworkers 8" in out


def test_overwrite_never_deletes_a_directory_that_is_not_a_store(tmp_path):
    from tubeid.cli import main

    precious = tmp_path / "precious"
    precious.mkdir()
    (precious / "important.txt").write_text("keep me")
    study = pathlib.Path(__file__).resolve().parents[1] / "studies" / "example_pi.py"
    assert main(["run", str(study), "--store", str(precious), "--overwrite", "--workers", "0", "--no-progress"]) == 2
    assert (precious / "important.txt").read_text() == "keep me"


FAILING = '''
import pathlib
from tubeid.runner.study import Output, Parameter, Study, pointwise

@pointwise
def f(point, rng, marker):
    if point["r"] == 3 and pathlib.Path(marker).exists():  # a cause outside the study (a file, the memory...)
        raise ZeroDivisionError("a failure at r = %d" % point["r"])
    return {"y": float(point["r"])}

study = Study(name="failing", seed=3, axes={"r": range(6)}, chunks={"r": 2}, task=f,
              outputs={"y": Output(units="m")}, units={"r": "1"}, parameters={"marker": Parameter("")})
'''


def test_a_failing_task_names_its_block_keeps_the_others_and_resumes(tmp_path, capsys):
    from tubeid.errors import BlockFailed
    from tubeid.runner.cli import main as cli
    from tubeid.runner.status import store_status

    path = tmp_path / "failing.py"
    path.write_text(FAILING)
    marker = tmp_path / "fail-here"
    marker.touch()
    store = tmp_path / "failing.zarr"
    with pytest.raises(BlockFailed) as info:
        run(path, store, workers=0, quiet=True, overrides={"marker": str(marker)})
    assert "study 'failing', block (1,) (r = 2 … 3) failed: ZeroDivisionError: a failure at r = 3" in str(info.value)
    assert isinstance(info.value.__cause__, ZeroDivisionError)  # the study's own traceback is kept
    assert store_status(store)["done"] == 1  # block (0,) stays; (2,) was never reached
    # the command line: the study's traceback, then one line naming the block, exit status 1
    from tubeid.cli import main

    assert main(["run", str(path), "--store", str(store), "--workers", "0", "--set", f"marker={marker}"]) == 1
    err = capsys.readouterr().err
    assert "ZeroDivisionError: a failure at r = 3" in err and "Traceback" in err
    assert err.rstrip().splitlines()[-1].startswith("tubeid: error: study 'failing', block (1,) (r = 2 … 3) failed")
    # the cause gone, the same command resumes with the blocks not yet done
    marker.unlink()
    report = run(path, store, workers=0, quiet=True, overrides={"marker": str(marker)})
    assert (report.computed, report.skipped) == (2, 1)
    assert cli(["status", str(store)]) == 0 and "3/3 blocks done" in capsys.readouterr().out


@pytest.mark.distributed
def test_a_failing_task_on_workers_names_its_block(tmp_path):
    from tubeid.errors import BlockFailed

    path = tmp_path / "failing.py"
    path.write_text(FAILING)
    (tmp_path / "fail-here").touch()
    with pytest.raises(BlockFailed, match=r"block \(1,\) \(r = 2 … 3\) failed: ZeroDivisionError"):
        run(path, tmp_path / "failing.zarr", workers=2, quiet=True, overrides={"marker": str(tmp_path / "fail-here")})


REFUSING = '''
from tubeid.mechanics import builtin_spec
from tubeid.runner.study import Output, Study, pointwise

@pointwise
def f(point, rng):
    if point["r"] == 3:
        builtin_spec("no-such-model")  # a refusal of tubeid's own, raised inside the task
    return {"y": float(point["r"])}

study = Study(name="refusing", seed=3, axes={"r": range(6)}, chunks={"r": 2}, task=f, outputs={"y": Output(units="m")})
'''


@pytest.mark.parametrize("workers", [0, pytest.param(2, marks=pytest.mark.distributed)])
def test_a_refusal_raised_in_a_task_keeps_its_field_value_and_rule_and_names_the_block(tmp_path, capsys, workers):
    """A SpecificationError raised by a task stays a one-line refusal (exit 2, no traceback) with its field,
    value and rule, and says which block raised it (it crosses from a worker process by pickle)."""
    from tubeid.cli import main

    path = tmp_path / "refusing.py"
    path.write_text(REFUSING)
    with pytest.raises(SpecificationError) as info:
        run(path, tmp_path / "s.zarr", workers=workers, quiet=True)
    assert (info.value.field, info.value.value) == ("model", "no-such-model")
    assert info.value.rule.startswith("unknown built-in model")
    assert str(info.value).endswith("(in study 'refusing', block (1,) (r = 2 … 3))")
    assert main(["run", str(path), "--store", str(tmp_path / "s.zarr"), "--workers", str(workers), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and err.splitlines()[-1] == f"tubeid: error: {info.value}"


def test_tubeids_errors_survive_pickling_with_their_fields():
    """They cross process boundaries (dask workers, multiprocessing): rebuilt with their fields, a value that
    cannot be pickled travelling as its description."""
    import pickle

    from tubeid.errors import MissingDependencyError

    e = pickle.loads(pickle.dumps(SpecificationError("tubes[1].length", -2.0, "must be > 0")))
    assert type(e) is SpecificationError and (e.field, e.value, e.rule) == ("tubes[1].length", -2.0, "must be > 0")
    assert str(e) == "tubes[1].length = -2.0: must be > 0"
    e = pickle.loads(pickle.dumps(SpecificationError("task", lambda x: x, "must be picklable")))
    assert str(e).startswith("task = <function test_tubeids_errors_survive_pickling_with_their_fields.<locals>.<lambda>")
    e = pickle.loads(pickle.dumps(MissingDependencyError("tubeid report", "matplotlib", "plot")))
    assert (e.feature, e.package, e.extra, e.name) == ("tubeid report", "matplotlib", "plot", "matplotlib")
    assert str(e) == 'tubeid report needs matplotlib: pip install "tubeid[plot]"'


@pytest.mark.parametrize("text, read", [("1e-400", "0.0"), ("-2e-999", "0.0"), ("1e400", "inf"), ("-1e309", "-inf"),
                                        ("[1.0, (2, 1e-400)]", "0.0"), ("2.5e-324", "5e-324"), ("{'a': 1e999}", "inf")])
def test_set_refuses_a_number_beyond_a_floats_range(tmp_path, capsys, text, read):
    """`--set delta=1e-400` was read as 0.0 (in the paper study: "use delta_opt"), silently; in a list too."""
    from tubeid.cli import main

    study = write_study(tmp_path, realisations=4, work=0)
    with pytest.raises(SystemExit) as info:
        main(["run", str(study), "--store", str(tmp_path / "s.zarr"), "--set", f"work={text}"])
    err = capsys.readouterr().err
    assert info.value.code == 2 and f"a number beyond a float's range (read as {read}" in err, err
    assert not (tmp_path / "s.zarr").exists()
    from tubeid.runner.cli import _setting

    assert _setting("x=0.0e-400") == ("x", 0.0) and _setting("x=2.5e-300") == ("x", 2.5e-300)  # zeros, small numbers
    assert _setting('x="1e-400"') == ("x", "1e-400")  # text stays text


@pytest.mark.parametrize("samples", [-5, 0, 10**7 + 1])
def test_the_pi_study_refuses_a_sample_count_it_cannot_use_before_any_store(tmp_path, capsys, samples):
    """studies/pi.py: `--set samples=-5` ended in numpy's traceback ("negative dimensions are not allowed") from
    the first block, 0 in a NaN refusal from the first block (a store left), 10**10 would ask for 160 GB per
    point; each is now refused when the file is loaded, naming the parameter and its bounds."""
    from tubeid.cli import main
    from tubeid.runner.study import load_definition

    with pytest.raises(SpecificationError, match=rf"parameters\.samples = {samples}: must lie in \[1, 10000000\]"):
        load_definition(REPO / "studies" / "pi.py", overrides={"samples": samples})
    assert main(["run", str(REPO / "studies" / "pi.py"), "--store", str(tmp_path / "pi.zarr"), "--workers", "0",
                 "--set", f"samples={samples}"]) == 2
    assert capsys.readouterr().err.count("\n") == 1 and not (tmp_path / "pi.zarr").exists()
    assert load_definition(REPO / "studies" / "pi.py", overrides={"samples": 1})[0].values["samples"] == 1


def test_run_help_with_a_study_lists_its_parameters(tmp_path, capsys):
    """`tubeid run studies/pi.py --help` printed only the runner's options: which --set names a study takes (and
    their types, bounds, docs: ``Parameter.doc`` says it is for this help) could only be read in its source."""
    from tubeid.cli import main

    with pytest.raises(SystemExit) as info:
        main(["run", str(REPO / "studies" / "pi.py"), "--help"])
    out = capsys.readouterr().out
    assert info.value.code == 0 and "--set NAME=VALUE" in out
    assert out.endswith(f"\nparameters of {REPO / 'studies' / 'pi.py'} (study 'pi'; --set NAME=VALUE):\n"
                        "  samples = 100000  (an integer in [1, 10000000]: points per realisation)\n"), out
    with pytest.raises(SystemExit):
        main(["run", "--help", str(REPO / "studies" / "two_stage.py")])  # the study after --help too
    assert capsys.readouterr().out.endswith("  size = 'paper'  (one of ['paper', 'quick'])\n")
    with pytest.raises(SystemExit):
        main(["run", "--help"])  # no study: the options only
    assert "parameters of" not in capsys.readouterr().out
    assert main(["run", str(tmp_path / "none.py"), "--help"]) == 2
    assert capsys.readouterr().err == f"tubeid: error: study = {str(tmp_path / 'none.py')!r}: no such study file\n"


def test_a_directory_given_as_the_study_is_named_as_one(tmp_path, capsys):
    """`tubeid run .` or `tubeid run studies` said "no such study file" of a directory that exists."""
    from tubeid.cli import main

    assert main(["run", str(tmp_path), "--workers", "0"]) == 2
    assert capsys.readouterr().err == (f"tubeid: error: study = {str(tmp_path)!r}: is a directory: give a study file "
                                       "(e.g. studies/pi.py)\n")


def test_a_bound_left_open_is_not_shown_as_none():
    """`bounds=(1, None)` was said as "must lie in [1, None]"."""
    with pytest.raises(SpecificationError, match=r"^parameters\.n = 0: must be >= 1$"):
        Parameter(5, bounds=(1, None)).check("n", 0)
    with pytest.raises(SpecificationError, match=r"^parameters\.x = 2\.5: must be <= 2\.0$"):
        Parameter(1.0, bounds=(None, 2.0)).check("x", 2.5)
    with pytest.raises(SpecificationError, match=r"^parameters\.x = 2\.5: must lie in \[0\.0, 2\.0\]$"):
        Parameter(1.0, bounds=(0.0, 2.0)).check("x", 2.5)


def test_a_float_parameter_refuses_an_integer_a_float_cannot_hold():
    with pytest.raises(SpecificationError, match=r"parameters.x = <integer of 1329 bits>: must be a number a float can"):
        Parameter(1.0).check("x", 10 ** 400)


def test_a_setting_is_named_with_the_variable_that_sets_it():
    """Refusals name a setting with its environment variable: that variable must set that setting."""
    import re

    from tubeid import config

    for key in ("runner.workers", "runner.lock-heartbeat", "runner.threads-per-worker", "io.max-bytes"):
        name = config.setting_name(key)
        variable = re.fullmatch(rf"tubeid\.{re.escape(key)} \((TUBEID_[A-Z_]+)\)", name).group(1)
        section, _, leaf = key.partition(".")
        assert config.collect_env({variable: "7"}) == {"tubeid": {section: {leaf: 7}}}
