"""tubeid's configuration (``tubeid/tubeid.yaml``, ``TUBEID_...`` variables): every setting has one
check (``tubeid.config.schema``); a bad value, from the environment above all, is one line naming the
setting, its variable, the value and the rule, before anything is created or started; never a
traceback from inside dask or the runner, never a silently wrong value."""

import copy
import os
import subprocess
import sys

import dask.config
import pytest
import yaml

from tubeid import config
from tubeid.errors import SpecificationError

TUBEID = [sys.executable, "-m", "tubeid"]

# a study with no chunk for its axis (tubeid.runner.default-chunk is used)
STUDY = """
import numpy as np
from tubeid.runner.study import Output, Study
study = Study(name="cfg", seed=3, axes={"realisation": range(4)}, outputs={"y": Output()},
              task=lambda block, rng: {"y": np.asarray(block["realisation"], float)})
"""


def _env(**extra):
    """This environment without tubeid's settings or a default scheduler, with ``extra``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("TUBEID_RUNNER", "TUBEID_IO"))}
    env.pop("DASK_SCHEDULER_ADDRESS", None)
    env["TUBEID_RUNNER__PROGRESS"] = "false"
    return env | extra


def _refused(proc, setting, variable, value, rule):
    """``proc`` refused one setting: status 2, one line naming it, its variable, the value and the rule."""
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.startswith(f"tubeid: error: tubeid.{setting} ({variable}) = {value}: "), proc.stderr
    assert rule in proc.stderr, proc.stderr
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr, proc.stderr


@pytest.fixture
def environment():
    """``refresh(env)``: the configuration as these variables make it; the configuration is put back after."""
    saved = copy.deepcopy(dask.config.config.get("tubeid"))
    saved_conflicts = list(config._conflicts)

    def apply(env):
        config.refresh(env)

    yield apply
    dask.config.config["tubeid"] = saved
    config._conflicts[:] = saved_conflicts


# -- the reviewer's cases, through the command line ------------------------------------------------
@pytest.mark.parametrize("value, shown", [("123", "123"), ("None", "None"), ("[1]", "[1]")])
def test_a_store_root_that_is_not_a_path_is_refused_before_anything_is_created(tmp_path, value, shown):
    """``TUBEID_RUNNER__STORE_ROOT=123 tubeid run pi.py`` (no --store) was a TypeError traceback."""
    (tmp_path / "cfg.py").write_text(STUDY)
    proc = subprocess.run(TUBEID + ["run", "cfg.py", "--workers", "0"], cwd=tmp_path, capture_output=True, text=True,
                          env=_env(TUBEID_RUNNER__STORE_ROOT=value), timeout=120)
    _refused(proc, "runner.store-root", "TUBEID_RUNNER__STORE_ROOT", shown, "must be a directory path")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cfg.py"]


def test_a_scheduler_address_that_is_not_text_is_refused_before_connecting(tmp_path):
    """``TUBEID_RUNNER__SCHEDULER_ADDRESS=123`` was an AttributeError traceback from the runner's connect."""
    (tmp_path / "cfg.py").write_text(STUDY)
    store = tmp_path / "e.zarr"
    proc = subprocess.run(TUBEID + ["run", "cfg.py", "--store", str(store)], cwd=tmp_path, capture_output=True,
                          text=True, env=_env(TUBEID_RUNNER__SCHEDULER_ADDRESS="123"), timeout=120)
    _refused(proc, "runner.scheduler-address", "TUBEID_RUNNER__SCHEDULER_ADDRESS", "123",
             "must be a scheduler address such as tcp://host:8786")
    assert not store.exists()


def test_a_mapping_with_keys_that_are_not_names_is_refused_not_a_crash_of_every_command():
    """``TUBEID_IO='{1:2}'`` was a TypeError inside dask's configuration at import: every command failed."""
    proc = subprocess.run(TUBEID + ["model", "paper-simplified"], capture_output=True, text=True,
                          env=_env(TUBEID_IO="{1:2}"), timeout=120)
    _refused(proc, "io", "TUBEID_IO", "{1: 2}", "must be a mapping of the settings max-bytes")


def test_a_section_replaced_by_a_value_is_refused_naming_the_variable_that_did_it():
    """``TUBEID_IO=5`` was reported as ``tubeid.io.max-specification-bytes = None`` (neither the variable
    nor its value)."""
    proc = subprocess.run(TUBEID + ["model", "paper-simplified"], capture_output=True, text=True,
                          env=_env(TUBEID_IO="5"), timeout=120)
    _refused(proc, "io", "TUBEID_IO", "5", "must be a mapping of the settings max-bytes, max-displacement")
    assert "TUBEID_IO__MAX_BYTES=" in proc.stderr  # how to set one of them


def test_a_bad_default_chunk_is_named_as_the_setting_not_as_the_studys_chunks(tmp_path):
    """``TUBEID_RUNNER__DEFAULT_CHUNK=0`` was ``chunks.realisation = 0: must be a positive integer``."""
    (tmp_path / "cfg.py").write_text(STUDY)
    store = tmp_path / "e.zarr"
    proc = subprocess.run(TUBEID + ["run", "cfg.py", "--store", str(store), "--workers", "0"], cwd=tmp_path,
                          capture_output=True, text=True, env=_env(TUBEID_RUNNER__DEFAULT_CHUNK="0"), timeout=120)
    _refused(proc, "runner.default-chunk", "TUBEID_RUNNER__DEFAULT_CHUNK", "0", "must be an integer >= 1")
    assert not store.exists()


def test_a_bad_connect_timeout_is_a_refused_setting_not_a_connection_failure(tmp_path):
    """``TUBEID_RUNNER__CONNECT_TIMEOUT=abc --scheduler ...`` was reported as a failure to connect
    ("Invalid time unit") with a TLS hint."""
    (tmp_path / "cfg.py").write_text(STUDY)
    store = tmp_path / "e.zarr"
    proc = subprocess.run(TUBEID + ["run", "cfg.py", "--store", str(store), "--scheduler", "tcp://127.0.0.1:1"],
                          cwd=tmp_path, capture_output=True, text=True, env=_env(TUBEID_RUNNER__CONNECT_TIMEOUT="abc"),
                          timeout=120)
    _refused(proc, "runner.connect-timeout", "TUBEID_RUNNER__CONNECT_TIMEOUT", "'abc'", "must be a duration > 0")
    assert "TLS" not in proc.stderr and "cannot connect" not in proc.stderr
    assert not store.exists()


@pytest.mark.parametrize("variable, value, setting, shown, rule", [
    ("TUBEID_RUNNER__WORKER_ENVIRON", "{1:2}", "runner.worker-environ", "{1: 2}",
     "must hold upper-case environment variable names"),  # was a TypeError at import, in every command
    ("TUBEID_RUNNER__CONNECT_TIMEOUT", "abc", "runner.connect-timeout", "'abc'", "must be a duration > 0"),
    ("TUBEID_RUNNER__WORKRES", "4", "runner.workres", "4", "is not a setting of tubeid.runner"),
])
def test_a_command_checks_every_setting_before_it_runs(variable, value, setting, shown, rule):
    """``tubeid model`` reads no runner setting: a bad one is still refused at once, in one line, rather
    than ignored until a command that reads it has done part of its work."""
    proc = subprocess.run(TUBEID + ["model", "paper-simplified"], capture_output=True, text=True,
                          env=_env(**{variable: value}), timeout=120)
    _refused(proc, setting, variable, shown, rule)
    assert proc.stdout == ""


# -- every setting ---------------------------------------------------------------------------------
def test_the_schema_has_every_setting_of_tubeid_yaml_and_the_defaults_pass():
    packaged = yaml.safe_load(config.DEFAULTS_PATH.read_text())["tubeid"]
    assert {s: list(v) for s, v in config.schema().items()} == {s: list(v) for s, v in packaged.items()}
    with dask.config.set({"tubeid": copy.deepcopy(packaged)}):
        values = config.check()
    assert values["runner.connect-timeout"] == 20.0 and values["io.max-bytes"] == 2 * 2**30
    assert values["runner.workers"] is None and values["io.max-sensors"] == 64


BAD = [  # (variable, value as set, value as shown, rule): each setting of tubeid.yaml, a wrong type or value
    ("TUBEID_RUNNER__WORKERS", "0", "0", "must be an integer >= 1, or null (one per core)"),
    ("TUBEID_RUNNER__WORKERS", "2.0", "2.0", "must be an integer >= 1"),
    ("TUBEID_RUNNER__THREADS_PER_WORKER", "True", "True", "must be an integer >= 1"),
    ("TUBEID_RUNNER__HOST", "[1]", "[1]", "must be a host name or address"),
    ("TUBEID_RUNNER__HOST", "''", "''", "must be a host name or address"),
    ("TUBEID_RUNNER__EMBEDDED_TLS", "no", "'no'", "must be true or false"),
    ("TUBEID_RUNNER__EMBEDDED_TLS", "0", "0", "must be true or false"),
    ("TUBEID_RUNNER__DASHBOARD_ADDRESS", "8787", "8787", "must be an address host:port"),
    ("TUBEID_RUNNER__SCHEDULER_ADDRESS", "123", "123", "must be a scheduler address"),
    ("TUBEID_RUNNER__SCHEDULER_ADDRESS", "tcp://a b", "'tcp://a b'", "must be a scheduler address"),
    ("TUBEID_RUNNER__STORE_ROOT", "None", "None", "must be a directory path"),
    ("TUBEID_RUNNER__DEFAULT_CHUNK", "0", "0", "must be an integer >= 1"),
    ("TUBEID_RUNNER__DEFAULT_CHUNK", "'16'", "'16'", "must be an integer >= 1"),
    ("TUBEID_RUNNER__PROGRESS", "yes", "'yes'", "must be true or false"),
    ("TUBEID_RUNNER__ALLOWED_FAILURES", "-1", "-1", "must be an integer >= 0"),
    ("TUBEID_RUNNER__ALLOWED_FAILURES", "many", "'many'", "must be an integer >= 0"),
    ("TUBEID_RUNNER__WORKER_ENVIRON", "5", "5", "must be a mapping of environment variable names"),
    ("TUBEID_RUNNER__WORKER_ENVIRON", "{1:2}", "{1: 2}", "must hold upper-case environment variable names"),
    ("TUBEID_RUNNER__CONNECT_TIMEOUT", "abc", "'abc'", "must be a duration > 0"),
    ("TUBEID_RUNNER__CONNECT_TIMEOUT", "None", "None", "must be a duration > 0"),
    ("TUBEID_RUNNER__CONNECT_TIMEOUT", "-5", "-5", "must be a duration > 0"),
    ("TUBEID_RUNNER__LOCK_HEARTBEAT", "[10]", "[10]", "must be a duration > 0"),
    ("TUBEID_RUNNER__LOCK_STALE_AFTER", "inf", "'inf'", "must be a duration > 0"),
    ("TUBEID_IO__MAX_BYTES", "abc", "'abc'", "must be a size in bytes > 0"),
    ("TUBEID_IO__MAX_BYTES", "0", "0", "must be a size in bytes > 0"),
    ("TUBEID_IO__MAX_DISPLACEMENT", "nan", "'nan'", "must be a finite number > 0 (m)"),
    ("TUBEID_IO__MAX_DISPLACEMENT", "-1.0", "-1.0", "must be a finite number > 0 (m)"),
    ("TUBEID_IO__MAX_SENSORS", "1.5", "1.5", "must be an integer >= 1"),
    ("TUBEID_IO__MAX_DOF", "True", "True", "must be an integer >= 1"),
    ("TUBEID_IO__MAX_SPECIFICATION_BYTES", "'1 MiBs'", "'1 MiBs'", "must be a size in bytes > 0"),
    ("TUBEID_IO__MAX_SPECIFICATION_BYTES", "None", "None", "must be a size in bytes > 0"),
    ("TUBEID_IO__MAX_SUBSTEPS", "0", "0", "must be a finite number >= 1"),
    ("TUBEID_IO__MAX_SUBSTEPS", "'many'", "'many'", "must be a finite number >= 1"),
    ("TUBEID_RUNNER", "5", "5", "must be a mapping of the settings workers"),
]


@pytest.mark.parametrize("variable, value, shown, rule", BAD)
def test_every_setting_refuses_a_wrong_type_or_value_from_the_environment(environment, variable, value, shown, rule):
    key = variable.removeprefix("TUBEID_").lower().replace("__", ".").replace("_", "-")
    environment({variable: value})
    with pytest.raises(SpecificationError) as err:
        config.check()
    assert str(err.value).startswith(f"tubeid.{key} ({variable}) = {shown}: {rule}"), str(err.value)
    if "." in key:  # the setting alone, as the code reads it, is refused the same way
        with pytest.raises(SpecificationError) as alone:
            config.value(key)
        assert str(alone.value) == str(err.value)


@pytest.mark.parametrize("env, value", [
    ({"TUBEID_RUNNER__WORKERS": "None"}, ("runner.workers", None)),
    ({"TUBEID_RUNNER__WORKERS": "3"}, ("runner.workers", 3)),
    ({"TUBEID_RUNNER__PROGRESS": "false"}, ("runner.progress", False)),
    ({"TUBEID_RUNNER__SCHEDULER_ADDRESS": "tls://10.0.0.1:8786"}, ("runner.scheduler-address", "tls://10.0.0.1:8786")),
    ({"TUBEID_RUNNER__SCHEDULER_ADDRESS": ""}, ("runner.scheduler-address", None)),
    ({"TUBEID_RUNNER__STORE_ROOT": "/results"}, ("runner.store-root", __import__("pathlib").Path("/results"))),
    ({"TUBEID_RUNNER__CONNECT_TIMEOUT": "300s"}, ("runner.connect-timeout", 300.0)),
    ({"TUBEID_RUNNER__CONNECT_TIMEOUT": "2.5"}, ("runner.connect-timeout", 2.5)),
    ({"TUBEID_RUNNER__LOCK_STALE_AFTER": "5 minutes"}, ("runner.lock-stale-after", 300.0)),
    ({"TUBEID_RUNNER__WORKER_ENVIRON": '{"MALLOC_TRIM_THRESHOLD_": 1}'},
     ("runner.worker-environ", {"MALLOC_MMAP_THRESHOLD_": 33554432, "MALLOC_TRIM_THRESHOLD_": 1})),  # merged
    ({"TUBEID_RUNNER__WORKER_ENVIRON": "None"}, ("runner.worker-environ", {})),
    ({"TUBEID_IO__MAX_BYTES": "8 GiB"}, ("io.max-bytes", 8 * 2**30)),
    ({"TUBEID_IO__MAX_BYTES": "1000"}, ("io.max-bytes", 1000.0)),
    ({"TUBEID_IO": '{"max-dof": 10}'}, ("io.max-dof", 10)),  # a mapping merges into the section
    ({"TUBEID_IO__MAX_SUBSTEPS": "1e10"}, ("io.max-substeps", 1e10)),
    ({"TUBEID_TEST_ANYTHING": "1"}, ("io.max-dof", 4000)),  # a plain TUBEID_ variable is no setting
])
def test_good_values_from_the_environment_are_taken(environment, env, value):
    environment(env)
    key, expected = value
    assert config.check()[key] == expected and config.value(key) == expected


@pytest.mark.parametrize("env, says", [
    ({"TUBEID_RUNNER__WORKRES": "4"}, "tubeid.runner.workres (TUBEID_RUNNER__WORKRES) = 4: is not a setting of "
                                      "tubeid.runner (its settings: workers, "),
    ({"TUBEID_RUNER__WORKERS": "4"}, "tubeid.runer (TUBEID_RUNER) = {'workers': 4}: is not a section of the tubeid "
                                     "configuration (its sections: runner, io)"),
    ({"TUBEID_RUNNER__WORKERS": "2", "TUBEID_RUNNER__WORKERS__X": "1"},
     "tubeid.runner.workers (TUBEID_RUNNER__WORKERS) = 2: is also set in part by TUBEID_RUNNER__WORKERS__X"),
    ({"TUBEID_RUNNER__WORKERS__X": "1", "TUBEID_RUNNER__WORKERS": "2"},
     "tubeid.runner.workers (TUBEID_RUNNER__WORKERS) = 2: is also set in part by TUBEID_RUNNER__WORKERS__X"),
    ({"TUBEID_RUNNER__LOCK_HEARTBEAT": "90"}, "tubeid.runner.lock-heartbeat (TUBEID_RUNNER__LOCK_HEARTBEAT) = '90 s': "
                                              "must be shorter than tubeid.runner.lock-stale-after = 60 s"),
])
def test_a_misspelt_setting_or_contradicting_variables_are_refused(environment, env, says):
    """A setting that is none (it would be ignored: a silently wrong value), and a variable that sets
    what another sets a part of (dask's merge failed with a TypeError, or kept one, by their order)."""
    environment(env)
    with pytest.raises(SpecificationError) as err:
        config.check()
    assert str(err.value).startswith(says), str(err.value)
