"""The ``tubeid`` command line and the lazy package namespace.

Speed is checked structurally, never by timing: which libraries a command imports, seen in
``sys.modules`` of a fresh interpreter (the README gives the measured times).
"""

import argparse
import importlib
import json
import os
import subprocess
import sys
from importlib.metadata import version

import pytest

import tubeid
from tubeid import _lazy
from tubeid.cli import COMMANDS, build_parser, main

HEAVY = ("numba", "distributed", "matplotlib", "xarray", "dask", "numpy", "zarr", "scipy", "pandas")


def _modules_after(code: str) -> set[str]:
    """Top-level packages imported by ``code`` in a fresh interpreter (its stdout is discarded)."""
    probe = ("import sys, io, json, contextlib\n"
             "with contextlib.redirect_stdout(io.StringIO()):\n"
             + "".join(f"    {line}\n" for line in code.splitlines())
             + "print(json.dumps(sorted({m.split('.')[0] for m in sys.modules})))\n")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    return set(json.loads(out.splitlines()[-1]))


def _main_quietly(argv) -> str:
    return (f"from tubeid.cli import main\n"
            f"try:\n    main({argv!r})\nexcept SystemExit:\n    pass")


@pytest.mark.parametrize("code", [
    "import tubeid",
    "import tubeid; tubeid.__version__; dir(tubeid)",
    _main_quietly(["--help"]),
    _main_quietly(["--version"]),
    _main_quietly(["run", "--help"]),      # a command's help imports its module, not the library
])
def test_import_and_help_load_no_numerical_library(code):
    loaded = _modules_after(code)
    assert not loaded & set(HEAVY), f"{code!r} imported {sorted(loaded & set(HEAVY))}"


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    from tubeid.runner.execute import run

    d = tmp_path_factory.mktemp("cli")
    study = d / "tiny.py"
    study.write_text(
        "import numpy as np\n"
        "from tubeid.runner.study import Output, Study, pointwise\n"
        "@pointwise\n"
        "def f(point, rng):\n"
        "    return {'y': float(point['r']) + rng.standard_normal()}\n"
        "study = Study(name='tiny', seed=3, axes={'r': range(6)}, chunks={'r': 2}, task=f,\n"
        "              outputs={'y': Output(units='m')}, units={'r': '1'})\n")
    run(study, d / "tiny.zarr", workers=0, progress=False, quiet=True)
    return d / "tiny.zarr"


def test_status_reads_the_store_without_zarr_xarray_dask_or_numba(store):
    loaded = _modules_after(_main_quietly(["status", str(store)]))
    assert not loaded & {"zarr", "numba", "distributed", "dask", "xarray", "matplotlib", "scipy"}
    out = subprocess.run([sys.executable, "-m", "tubeid", "status", str(store)], capture_output=True, text=True,
                         check=True).stdout
    assert "tiny: 3/3 blocks done (100.0 %), complete" in out  # it did read the flags


def test_status_of_a_store_with_compressed_flags_reads_them_through_zarr(store, tmp_path):
    """A store whose flag array is not in the raw layout (written before, or recompressed) still answers."""
    import shutil

    import zarr

    from tubeid.runner.status import BOOKKEEPING, FLAG, store_status

    old = tmp_path / "old.zarr"
    shutil.copytree(store, old)
    flags = zarr.open_array(str(old / BOOKKEEPING / FLAG), mode="r")[...]
    shutil.rmtree(old / BOOKKEEPING / FLAG)
    g = zarr.open_group(str(old / BOOKKEEPING), mode="r+")
    g.create_array(FLAG, shape=flags.shape, chunks=(1,), dtype="uint64", fill_value=0)[...] = flags  # zstd: default
    assert "zstd" in (old / BOOKKEEPING / FLAG / "zarr.json").read_text()
    zarr.open_array(str(old / BOOKKEEPING / FLAG), mode="r+")[1] = 0
    st = store_status(old)
    assert (st["done"], st["total"], st["complete"]) == (2, 3, False)


def test_show_needs_xarray_but_not_dask_arrays_distributed_or_numba(store):
    code = _main_quietly(["show", str(store)]) + "\nimport sys\nassert 'dask.array' not in sys.modules"
    loaded = _modules_after(code)
    assert "xarray" in loaded
    assert not loaded & {"numba", "distributed", "matplotlib", "scipy"}


def test_status_and_show_report_the_store(store, capsys):
    assert main(["status", str(store)]) == 0
    assert "tiny: 3/3 blocks done (100.0 %), complete" in capsys.readouterr().out
    assert main(["show", str(store)]) == 0
    out = capsys.readouterr().out
    assert "study tiny" in out and "y [m]:" in out and "(100% written)" in out


@pytest.mark.parametrize("buffered", [False, True])
def test_a_reader_that_goes_away_ends_the_command_quietly(store, buffered):
    """``tubeid show STORE | head -1``: the pipe's reader exits after one line and the command's next
    writes fail (EPIPE). No traceback, exit status 141 (as a process ended by SIGPIPE). The reader is
    a process that closes the pipe at once; the command writes many lines. Buffered (no
    PYTHONUNBUFFERED, as ``| true``): the output is still in the buffer when the command ends."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    if not buffered:
        env["PYTHONUNBUFFERED"] = "1"
    proc = subprocess.Popen([sys.executable, "-m", "tubeid", "show", str(store)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    proc.stdout.close()
    err = proc.stderr.read()
    assert proc.wait(timeout=60) == 141, err
    assert "Traceback" not in err and "BrokenPipe" not in err, err


def test_version_is_the_installed_distribution_version(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.strip() == f"tubeid {version('tubeid')}" == f"tubeid {tubeid.__version__}"


def test_help_lists_every_command_with_its_help_line(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    out = " ".join(capsys.readouterr().out.split())  # argparse wraps lines at the terminal width
    for c in COMMANDS:
        assert f"{c.name} {' '.join(c.help.split()[:4])}" in out
    assert "tubeid run studies/paper.py" in out  # the description starts a user off


def test_unknown_command_is_refused_with_the_choices(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["bogus"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "invalid choice: 'bogus'" in err and "'run'" in err


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


@pytest.mark.parametrize("module", sorted({c.module for c in COMMANDS}))
def test_command_table_matches_what_each_module_registers(module):
    """The static table must name exactly the commands a module registers, with the same help line."""
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    importlib.import_module(module).register(sub)
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    registered = {a.dest: a.help for a in action._choices_actions}
    assert registered == {c.name: c.help for c in COMMANDS if c.module == module}


@pytest.mark.parametrize("name", [c.name for c in COMMANDS])
def test_every_positional_argument_has_a_help_line(name):
    command = _subparsers(build_parser(name))[name]
    positionals = [a for a in command._actions if not a.option_strings]
    for a in positionals:
        assert a.help and a.help.strip(), f"tubeid {name}: positional {a.dest!r} has no help"


def test_model_help_names_every_built_in_model_from_the_registry(monkeypatch, capsys):
    """``tubeid model --help`` lists the keys of ``BUILTIN_MODELS`` (one added here appears too): the
    list cannot drift from the registry (it missed paper-simplified-one-spring)."""
    from tubeid.mechanics import library

    monkeypatch.setenv("COLUMNS", "400")  # one line: argparse would wrap at a name's hyphen
    monkeypatch.setitem(library.BUILTIN_MODELS, "my-bundle", library.paper_reference)
    with pytest.raises(SystemExit):
        main(["model", "--help"])
    out = capsys.readouterr().out
    assert "paper-simplified-one-spring" in out
    assert f"built-in name ({', '.join(library.BUILTIN_MODELS)})" in out, out


def test_only_the_chosen_commands_module_is_imported():
    assert not _modules_after("from tubeid.cli import build_parser\nbuild_parser('model')") & set(HEAVY)
    code = ("import json, sys\nfrom tubeid.cli import build_parser\nbuild_parser('model')\n"
            "mods = sorted(m for m in sys.modules if m.startswith('tubeid.'))\n"
            "sys.stderr.write(json.dumps(mods))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    mods = set(json.loads(res.stderr))
    assert "tubeid.mechanics.cli" in mods
    assert not mods & {"tubeid.runner.cli", "tubeid.report", "tubeid.measured.cli", "tubeid.bench"}


# -- the lazy namespace ---------------------------------------------------------------------------
def test_lazy_exports_are_the_objects_of_their_modules():
    from tubeid.runner.study import Study
    from tubeid.uncertainty.random_matrices import sg_plus

    assert tubeid.Study is Study and tubeid.sg_plus is sg_plus
    import tubeid.mechanics as mech
    from tubeid.mechanics.reduction import reduce

    assert mech.reduce is reduce and tubeid.reduce is reduce


@pytest.mark.parametrize("package", ["tubeid", "tubeid.mechanics", "tubeid.uncertainty", "tubeid.dynamics",
                                     "tubeid.identification", "tubeid.measured", "tubeid.runner"])
def test_every_public_name_is_a_lazy_export_and_listed_by_dir(package):
    mod = importlib.import_module(package)
    table = _lazy.lazy_table(mod.__file__)
    assert set(mod.__all__) - {"__version__"} <= set(table), "in __all__ but not in the TYPE_CHECKING block"
    assert set(mod.__all__) <= set(dir(mod))
    for name, (module, attr) in table.items():
        assert getattr(mod, name) is getattr(importlib.import_module(module), attr)


def test_unknown_attribute_and_submodule_access():
    with pytest.raises(AttributeError, match="no attribute 'nonexistent'"):
        tubeid.nonexistent  # noqa: B018
    assert tubeid.seeds is importlib.import_module("tubeid.seeds")
    namespace: dict = {}
    exec("from tubeid import *", namespace)  # every name of __all__ resolves
    assert set(tubeid.__all__) <= set(namespace)


def test_a_name_shared_with_a_submodule_stays_the_exported_object(tmp_path):
    """A package exporting ``thing`` from its sub-module ``thing`` (a function and a module of the same
    name): importing the module first must not rebind the package attribute to the module (it
    would, with a purely lazy binding)."""
    pkg = tmp_path / "lazypkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text(
        "from typing import TYPE_CHECKING\nfrom tubeid._lazy import attach\n"
        "if TYPE_CHECKING:\n    from lazypkg.thing import thing\n"
        "__all__ = ['thing']\n__getattr__, __dir__ = attach(__name__, __file__)\n")
    (pkg / "thing.py").write_text("def thing():\n    return 42\n")
    code = ("import sys\nimport lazypkg.thing\nimport lazypkg as pkg\n"
            "assert pkg.thing is sys.modules['lazypkg.thing'].thing and pkg.thing() == 42, pkg.thing")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=tmp_path)


def test_an_export_imports_only_what_it_needs():
    loaded = _modules_after("from tubeid import read_measurements")
    assert "xarray" in loaded and not loaded & {"numba", "distributed", "matplotlib"}


def test_lazy_table_reads_only_the_type_checking_block(tmp_path):
    init = tmp_path / "init.py"
    init.write_text("from typing import TYPE_CHECKING\nfrom os import sep\n"
                    "if TYPE_CHECKING:\n    from a.b import C, D as E\n    import ignored\n"
                    "if other:\n    from x import y\n")
    assert _lazy.lazy_table(str(init)) == {"C": ("a.b", "C"), "E": ("a.b", "D")}


def test_status_reads_damaged_raw_flags_as_zarr_does(store, tmp_path):
    """The direct flag reader against zarr's, on a chunk deleted, one cut short and one overwritten."""
    import shutil

    from tubeid.runner.status import BOOKKEEPING, FLAG, _flags_direct
    from tubeid.runner.store import read_flags

    bad = tmp_path / "bad.zarr"
    shutil.copytree(store, bad)
    chunks = bad / BOOKKEEPING / FLAG / "c"
    (chunks / "0").unlink()
    (chunks / "1").write_bytes((chunks / "1").read_bytes()[:5])
    (chunks / "2").write_bytes(b"12345678")
    direct, by_zarr = _flags_direct(bad), read_flags(bad)
    assert direct[0].tolist() == by_zarr[0].tolist() == [0, 0, int.from_bytes(b"12345678", "little")]
    assert direct[1] == by_zarr[1] == [(1,)]


def test_show_cuts_a_long_parameter_value_unless_full(tmp_path, capsys):
    """A study parameter holding a long text (as the paper study's model specification) is shown as
    the first 40 characters of its JSON text and that text's length; ``--full`` prints it whole;
    short values stay whole, as stored (JSON, ASCII: a non-ASCII value prints on any terminal)."""
    from tubeid.runner import run

    long = "spec:" + "x" * 200 + ":end"
    study = tmp_path / "long.py"
    study.write_text(
        "from tubeid.runner.study import Output, Study, pointwise\n"
        "@pointwise\n"
        "def f(point, rng, *, note, k, tag):\n"
        "    return {'y': float(point['r']) * k}\n"
        f"study = Study(name='long', seed=3, axes={{'r': range(2)}}, task=f, outputs={{'y': Output()}},\n"
        f"              parameters={{'note': {long!r}, 'k': 2, 'tag': 'δ-run'}})\n")
    run(study, tmp_path / "long.zarr", workers=0, progress=False, quiet=True)
    assert main(["show", str(tmp_path / "long.zarr")]) == 0
    out = capsys.readouterr().out
    text = json.dumps(long)
    assert f'"note": {text[:40]}... ({len(text)} characters; --full prints it)' in out
    assert '"k": 2' in out and '"tag": "\\u03b4-run"' in out and ":end" not in out
    assert main(["show", str(tmp_path / "long.zarr"), "--full"]) == 0
    assert f'"note": {text}' in capsys.readouterr().out


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs Linux's /dev/full")
@pytest.mark.parametrize("buffered", [True, False])
@pytest.mark.parametrize("command", ["show", "--version"])
def test_output_that_cannot_be_written_is_one_error_line(store, command, buffered):
    """Output to a full device (``/dev/full``: ENOSPC): exit status 74 and one line on stderr, no
    traceback and no second report at interpreter exit. Buffered, the error comes at the final flush;
    unbuffered (``PYTHONUNBUFFERED=1``, as many container images set), at the first print inside the
    command (it was a traceback), or inside argparse's ``--version`` (which ignored it: status 0)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    if not buffered:
        env["PYTHONUNBUFFERED"] = "1"
    argv = [command, str(store)] if command == "show" else [command]
    with open("/dev/full", "w") as full:
        proc = subprocess.run([sys.executable, "-m", "tubeid", *argv], stdout=full,
                              stderr=subprocess.PIPE, text=True, env=env, timeout=60)
    assert proc.returncode == 74, proc.stderr
    assert proc.stderr.startswith("tubeid: error: cannot write the output:") and proc.stderr.count("\n") == 1, proc.stderr


@pytest.mark.parametrize("command", ["status", "show"])
def test_ctrl_c_ends_any_command_in_one_line_with_status_130(store, command):
    """A SIGINT (Ctrl-C) while a command works: ``tubeid: interrupted`` on stderr, status 130, no traceback
    (only ``run`` and ``diagnose`` used to catch it). The signal is sent by the command itself, mid-way."""
    import signal

    probe = ("import os, signal, sys, time\n"
             "import tubeid.runner.cli as rc\n"
             "def interrupted(args):\n"
             "    os.kill(os.getpid(), signal.SIGINT)\n"
             "    time.sleep(30)\n"
             f"rc._{command} = interrupted\n"
             "from tubeid.cli import main\n"
             f"sys.exit(main([{command!r}, {str(store)!r}]))\n")
    proc = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60,
                          preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert proc.returncode == 130, proc.stderr
    assert proc.stderr.strip() == "tubeid: interrupted" and proc.stdout == ""


def test_an_interrupt_before_the_command_runs_is_one_line_too(monkeypatch, capsys):
    """Ctrl-C while the command's modules are still being imported (before its own code runs)."""
    import tubeid.cli as cli

    def interrupted(command=None):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "build_parser", interrupted)
    assert main(["report", "x.zarr"]) == 130
    assert capsys.readouterr().err.strip() == "tubeid: interrupted"
