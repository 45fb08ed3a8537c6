"""Packaging: a small core, optional extras that name themselves when missing, each extra exercised.

"Missing" is simulated in subprocesses whose ``sitecustomize`` puts ``None`` in ``sys.modules`` for
the blocked packages (``import`` then fails as for an absent package, ``find_spec`` returns None);
the blocker is inherited by the dask worker processes those subprocesses start.
"""

import importlib.metadata
import json
import os
import pathlib
import subprocess
import sys
import tomllib
import urllib.request

import numpy as np
import pytest
import xarray as xr
import yaml
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

from tubeid import _optional
from tubeid.errors import MissingDependencyError

REPO = pathlib.Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
EXTRA_PACKAGES = {canonicalize_name(dist) for dist, _ in _optional.EXTRAS.values()}
# what "pip install tubeid" must never pull: plotting, file formats, cluster back-ends
FORBIDDEN = EXTRA_PACKAGES | {"kubernetes", "kubernetes-asyncio"}


def _requirements(dist: str, extras: frozenset = frozenset()) -> list[Requirement]:
    """The requirements ``dist`` declares for ``extras`` (markers evaluated here)."""
    out = []
    for line in importlib.metadata.requires(dist) or []:
        req = Requirement(line)
        if req.marker is None or any(req.marker.evaluate({"extra": e}) for e in (extras or {""})):
            out.append(req)
    return out


def _closure(dist: str, extras: frozenset = frozenset()) -> set[str]:
    """Every distribution that installing ``dist[extras]`` pulls, read from the installed metadata."""
    seen: set[tuple[str, frozenset]] = set()
    todo = [(canonicalize_name(dist), frozenset(extras))]
    names = set()
    while todo:
        name, ex = todo.pop()
        if (name, ex) in seen:
            continue
        seen.add((name, ex))
        names.add(name)
        try:
            reqs = _requirements(name, ex)
        except importlib.metadata.PackageNotFoundError:
            raise AssertionError(f"{name} is required but not installed (stale environment?)") from None
        for r in reqs:
            todo.append((canonicalize_name(r.name), frozenset(r.extras)))
    return names - {canonicalize_name(dist)}


# -- the core and the extras -----------------------------------------------------------------------
def test_installed_metadata_is_this_pyproject():
    """The checks below read the installed metadata: it must come from this pyproject.toml."""
    core = sorted(canonicalize_name(Requirement(r).name) for r in PYPROJECT["dependencies"])
    installed = sorted(canonicalize_name(r.name) for r in _requirements("tubeid"))
    assert installed == core, "reinstall: pip install -e '.[test]'"
    for extra in PYPROJECT["optional-dependencies"]:
        assert extra in (importlib.metadata.metadata("tubeid").get_all("Provides-Extra") or [])


def test_pip_install_tubeid_pulls_no_plotting_file_format_or_cluster_library():
    pulled = _closure("tubeid")
    assert not pulled & FORBIDDEN, sorted(pulled & FORBIDDEN)
    assert {"numpy", "xarray", "zarr", "dask", "distributed", "numba"} <= pulled  # the walk does see the core


@pytest.mark.parametrize("extra, packages", [
    ("plot", {"matplotlib"}), ("io", {"pyuff", "h5netcdf", "h5py"}), ("dashboard", {"bokeh"}),
    ("slurm", {"dask-jobqueue"}), ("k8s", {"dask-kubernetes"}),
])
def test_each_extra_pulls_its_packages(extra, packages):
    declared = {canonicalize_name(Requirement(r).name) for r in PYPROJECT["optional-dependencies"][extra]}
    assert declared == packages
    # the error table names the same extra for each of those packages
    assert {canonicalize_name(d) for d, e in _optional.EXTRAS.values() if e == extra} == packages


def test_all_and_test_extras():
    opt = PYPROJECT["optional-dependencies"]
    named = {e for e in opt if e not in ("all", "test")}
    (all_req,) = [Requirement(r) for r in opt["all"]]
    assert all_req.name == "tubeid" and set(all_req.extras) == named
    self_ref = [Requirement(r) for r in opt["test"] if Requirement(r).name == "tubeid"]
    assert len(self_ref) == 1 and set(self_ref[0].extras) == named  # the default suite exercises every extra


def test_require_names_the_extra_and_keeps_other_import_errors(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "pyuff", None)  # absent
    with pytest.raises(MissingDependencyError) as err:
        _optional.require("pyuff", "reading UFF 58 files")
    assert str(err.value) == 'reading UFF 58 files needs pyuff: pip install "tubeid[io]"'
    assert isinstance(err.value, ImportError) and err.value.name == "pyuff"
    # installed but broken (its own dependency is missing): the real error, not a wrong hint
    (tmp_path / "brokenpkg.py").write_text("import not_a_module_anywhere_xyz\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(_optional.EXTRAS, "brokenpkg", ("brokenpkg", "io"))
    with pytest.raises(ModuleNotFoundError) as err:
        _optional.require("brokenpkg", "a feature")
    assert not isinstance(err.value, MissingDependencyError) and err.value.name == "not_a_module_anywhere_xyz"


# -- running without the extras --------------------------------------------------------------------
BLOCKED = sorted(_optional.EXTRAS)


@pytest.fixture(scope="module")
def no_extras(tmp_path_factory):
    """Environment of a subprocess (and its dask workers) in which no optional package imports."""
    d = tmp_path_factory.mktemp("blocker")
    (d / "sitecustomize.py").write_text(
        "import sys\n"
        f"for _name in {BLOCKED!r}:\n"
        "    sys.modules[_name] = None  # import fails as for an absent package\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(d), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
    return env


def _run(args, env, cwd=None, timeout=300):
    return subprocess.run(args, capture_output=True, text=True, env=env, cwd=cwd, timeout=timeout)


def test_the_blocker_blocks(no_extras):
    res = _run([sys.executable, "-c", "import importlib.util as u\n"
                "assert u.find_spec('matplotlib') is None\n"
                "try:\n    import h5py\nexcept ImportError as e:\n    print('blocked', e.name)"], no_extras)
    assert res.returncode == 0 and res.stdout.strip() == "blocked h5py", res.stderr


@pytest.mark.distributed
def test_the_core_runs_a_study_on_real_workers_without_any_extra(no_extras, tmp_path):
    """A study that draws SG+ matrices (scipy, numba-free) on a 1-worker LocalCluster, dashboard on."""
    study = tmp_path / "sg.py"
    study.write_text(
        "import numpy as np, sys\n"
        "from tubeid.runner.study import Output, Study, pointwise\n"
        "from tubeid.uncertainty.random_matrices import sg_plus\n"
        "@pointwise\n"
        "def draw(point, rng):\n"
        "    assert sys.modules.get('matplotlib', 0) is None and sys.modules.get('h5py', 0) is None\n"
        "    return {'trace': float(np.trace(sg_plus(4, 0.3, rng=rng)))}\n"
        "study = Study(name='sg', seed=5, axes={'realisation': range(8)}, chunks={'realisation': 4},\n"
        "              task=draw, outputs={'trace': Output(units='1')})\n")
    res = _run([sys.executable, "-m", "tubeid", "run", str(study), "--store", str(tmp_path / "sg.zarr"),
                "--workers", "1", "--no-progress"], no_extras, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    assert 'its plots need bokeh: pip install "tubeid[dashboard]"' in res.stderr
    trace = xr.open_zarr(tmp_path / "sg.zarr")["trace"].values
    assert trace.shape == (8,) and np.all(np.isfinite(trace))
    res = _run([sys.executable, "-m", "tubeid", "model", "paper-simplified", "--json"], no_extras)
    assert res.returncode == 0 and json.loads(res.stdout)["n_dof"] > 0, res.stderr[-2000:]


@pytest.mark.parametrize("command, extra, package", [
    (["report", "results/none.zarr"], "plot", "matplotlib"),
    (["diagnose", "record.nc"], "plot", "matplotlib"),
])
def test_a_command_without_its_extra_says_what_to_install(no_extras, command, extra, package):
    res = _run([sys.executable, "-m", "tubeid", *command], no_extras)
    assert res.returncode == 2
    assert res.stderr.strip() == f'tubeid: error: tubeid {command[0]} needs {package}: pip install "tubeid[{extra}]"'
    res = _run([sys.executable, "-m", "tubeid", command[0], "--help"], no_extras)  # its help needs nothing
    assert res.returncode == 0 and "usage: tubeid " + command[0] in res.stdout, res.stderr[-2000:]


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    """A short valid record written as UFF 58 and as NetCDF-4 (with the extras, in this process)."""
    from tubeid.measured.readers import write_measurements

    d = tmp_path_factory.mktemp("records")
    t = np.arange(2048) * 1e-3
    ds = xr.Dataset({"displacement": (("time", "sensor"), 1e-6 * np.random.default_rng(0).standard_normal((t.size, 1)),
                                      {"units": "m"})},
                    coords={"time": ("time", t, {"units": "s"}), "sensor": ["P_obs"],
                            "x": ("sensor", [6.0], {"units": "m"}), "tube": ("sensor", ["centre"])})
    write_measurements(ds, d / "rec.uff")
    write_measurements(ds, d / "rec.nc")
    return d


@pytest.mark.parametrize("name, message", [
    ("rec.uff", 'reading UFF 58 files needs pyuff: pip install "tubeid[io]"'),
    ("rec.nc", 'reading NetCDF-4 files needs h5netcdf: pip install "tubeid[io]"'),
])
def test_reading_a_file_format_without_its_extra_says_what_to_install(no_extras, records, name, message):
    code = ("from tubeid import read_measurements\n"
            "from tubeid.errors import MissingDependencyError\n"
            f"try:\n    read_measurements({str(records / name)!r})\n"
            "except MissingDependencyError as e:\n    print(e)\n")
    res = _run([sys.executable, "-c", code], no_extras)
    assert res.returncode == 0 and res.stdout.strip() == message, res.stderr[-2000:]


@pytest.fixture(scope="module")
def no_io(tmp_path_factory):
    """Environment of a subprocess (and its dask workers) in which the ``io`` extra's packages do not
    import (pyuff, h5netcdf, h5py) but the others do (``tubeid diagnose`` needs matplotlib)."""
    d = tmp_path_factory.mktemp("io-blocker")
    io = sorted(name for name, (_, extra) in _optional.EXTRAS.items() if extra == "io")
    (d / "sitecustomize.py").write_text(
        "import sys\n"
        f"for _name in {io!r}:\n"
        "    sys.modules[_name] = None  # import fails as for an absent package\n")
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(d), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}


@pytest.fixture(scope="module")
def core_records(tmp_path_factory):
    """A short control record (tubeid.diagnose.testing.make_record) as CSV + sidecar, NetCDF-3 and Zarr."""
    from tubeid.diagnose.testing import make_record
    from tubeid.measured.readers import write_measurements

    d = tmp_path_factory.mktemp("core-records")
    data = make_record(xs=(2.0, 6.0, 10.0), duration=16.0, seed=11)
    write_measurements(data, d / "rec.csv")
    write_measurements(data, d / "rec.nc", format="netcdf3")
    write_measurements(data, d / "rec.zarr")
    return d


@pytest.mark.parametrize("name, workers", [("rec.csv", 1), ("rec.nc", 0), ("rec.zarr", 0)])
def test_diagnose_runs_on_the_core_formats_without_the_io_extra(no_io, core_records, tmp_path, name, workers):
    """The core reads CSV, NetCDF-3 and Zarr records: ``tubeid diagnose`` of each works without pyuff,
    h5netcdf and h5py. The record's copy in --out is NetCDF-3, and with --workers 1 a worker process
    (with the same blocker) reads it back."""
    out = tmp_path / "out"
    settings = ["--set", "fit_realisations=1", "--set", "r0=(4.0,)", "--set", "r_fine_points=3"]
    res = _run([sys.executable, "-m", "tubeid", "diagnose", str(core_records / name), "--model", "paper-reference",
                "--out", str(out), "--max-effects", "0", "--workers", str(workers), "--no-progress",
                "--realisations", "9", "--false-alarm", "0.1", "--delta", "0", *settings], no_io)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "effect: none" in res.stdout
    report = json.loads((out / "report.json").read_text())
    assert report["runner"]["tasks_computed"] > 0
    if workers:  # the tasks ran in a worker process, which read the copy (the blocker is inherited)
        assert "embedded LocalCluster (1 single-threaded worker processes" in res.stderr, res.stderr[-2000:]
    (copy,) = out.glob("data-*.nc")
    assert copy.read_bytes()[:4] in (b"CDF\x01", b"CDF\x02"), "the record's copy must be NetCDF-3"


def test_diagnose_in_python_without_matplotlib_refuses_before_any_work(no_extras, core_records, tmp_path):
    """``tubeid.diagnose.diagnose(..., out=DIR)`` writes figures: without matplotlib it raises the
    command line's MissingDependencyError before reading the record, running or writing anything (no
    DIR, no store, no report.json); so does ``Diagnosis.write`` before writing any file. ``out=None``
    writes no files and does not need matplotlib: it goes on to read the record and check the settings."""
    out, out2 = tmp_path / "out", tmp_path / "out2"
    code = (
        "import os\n"
        "from tubeid.diagnose import DiagnoseSettings, Diagnosis, diagnose\n"
        "from tubeid.errors import MissingDependencyError, SpecificationError\n"
        "small = DiagnoseSettings(realisations=9, false_alarm=0.1, delta=0.0, max_effects=0, fit_realisations=1,\n"
        "                         r0=(4.0,), r_fine_points=3)\n"
        f"rec, out, out2 = {str(core_records / 'rec.nc')!r}, {str(out)!r}, {str(out2)!r}\n"
        "try:\n    diagnose(rec, 'paper-reference', small, out=out)\n"
        "except MissingDependencyError as e:\n    print(e)\n"
        "print('out:', sorted(os.listdir(out)) if os.path.exists(out) else None)\n"
        "try:\n    diagnose(rec, 'paper-reference', DiagnoseSettings(load_dispersion=0.9))\n"
        "except SpecificationError as e:\n    print('refused:', e.field)\n"
        "os.mkdir(out2)\n"
        "try:\n    Diagnosis(report={}, frequency=None, measured=None, sensors=(), bands={}).write(out2)\n"
        "except MissingDependencyError as e:\n    print(e)\n"
        "print('out2:', sorted(os.listdir(out2)))\n")
    res = _run([sys.executable, "-c", code], no_extras)
    message = 'tubeid diagnose needs matplotlib: pip install "tubeid[plot]"'
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.splitlines() == [message, "out: None", "refused: settings.load_dispersion", message, "out2: []"]


def test_slurm_script_without_its_extra_says_what_to_install(no_extras):
    res = _run([sys.executable, str(REPO / "cluster/slurm/run_study.py"), "x.py"], no_extras)
    assert res.returncode == 2
    assert res.stderr.strip() == ('tubeid: error: cluster/slurm/run_study.py needs dask-jobqueue: '
                                  'pip install "tubeid[slurm]"')


# -- each extra exercised where it is installed ----------------------------------------------------
# plot: tests/test_report.py and tests/test_diagnose.py draw the figures; io: tests/test_measured.py
# reads and writes UFF 58 and NetCDF-4; slurm: tests/test_slurm.py; dashboard and k8s: below.
@pytest.mark.distributed
def test_dashboard_extra_serves_the_dask_dashboard_plots():
    pytest.importorskip("bokeh")
    from distributed import LocalCluster

    from tubeid import config

    address = config.get("runner.dashboard-address")  # the embedded cluster's: loopback only
    assert address.startswith("127.0.0.1:")
    with LocalCluster(n_workers=0, processes=False, dashboard_address=address) as cluster:
        port = cluster.scheduler.http_server.port
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/status", timeout=30) as page:
            body = page.read().decode()
            assert page.status == 200
    assert "Bokeh" in body  # the status page is a Bokeh document (without bokeh it is not served)


def test_k8s_extra_daskjob_matches_the_operator_cluster_spec():
    """cluster/kubernetes/daskjob.yaml's cluster spec has the operator's own structure: the ports,
    probes and service selector dask-kubernetes generates, and the worker's name/dashboard args."""
    operator = pytest.importorskip("dask_kubernetes.operator")
    job = yaml.safe_load((REPO / "cluster/kubernetes/daskjob.yaml").read_text())
    ours = job["spec"]["cluster"]["spec"]
    worker = ours["worker"]["spec"]["containers"][0]
    ref = operator.make_cluster_spec(name=job["metadata"]["name"], image=worker["image"],
                                     n_workers=ours["worker"]["replicas"], resources=worker["resources"])["spec"]
    ref_worker = ref["worker"]["spec"]["containers"][0]
    assert worker["ports"] == ref_worker["ports"] and worker["resources"] == ref_worker["resources"]
    assert worker["args"][worker["args"].index("--name") + 1] == "$(DASK_WORKER_NAME)"
    dash = ref_worker["args"][ref_worker["args"].index("--dashboard-address") + 1]
    assert worker["args"][worker["args"].index("--dashboard-address") + 1] == dash
    sched, ref_sched = ours["scheduler"]["spec"]["containers"][0], ref["scheduler"]["spec"]["containers"][0]
    assert sched["ports"] == ref_sched["ports"]
    for probe in ("readinessProbe", "livenessProbe"):
        assert sched[probe]["httpGet"] == ref_sched[probe]["httpGet"]
    assert ours["scheduler"]["service"]["selector"] == ref["scheduler"]["service"]["selector"]
    assert ours["scheduler"]["service"]["ports"] == ref["scheduler"]["service"]["ports"]
