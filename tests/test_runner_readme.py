"""The README's runner sections tell the truth: the example files it shows exist under those names with
that content, every `tubeid run/status/show` command (and the `python -c` line) of those sections runs
as written from a fresh directory, the `open_pipeline` example reads the store those commands made as
its comments say, and the notebook example runs on a real LocalCluster client."""

import ast
import math
import os
import pathlib
import re
import shlex
import shutil
import subprocess
import sys

import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text()
SECTIONS = README.split("## Studies and the runner:", 1)[1].split("\n## ", 1)[0]

PI_TOL = 5 * math.sqrt(math.pi * (4 - math.pi) / (100_000 * 256))
pytestmark = [pytest.mark.distributed, pytest.mark.timeout(600)]


def _blocks(lang: str) -> list[str]:
    """The sections' fenced code blocks of language ``lang`` ("" for plain blocks)."""
    blocks, current, kind = [], None, None
    for line in SECTIONS.splitlines(keepends=True):
        if line.startswith("```"):
            if current is None:
                current, kind = [], line[3:].strip()
            else:
                if kind == lang:
                    blocks.append("".join(current))
                current = None
        elif current is not None:
            current.append(line)
    return blocks


def _commands() -> list[str]:
    """Command lines of the sections' plain code blocks, comments removed, `[optional]` parts expanded."""
    out = []
    for block in _blocks(""):
        for line in block.splitlines():
            if not line.startswith(("tubeid ", "python ")):
                continue
            cmd = re.sub(r"\s+#.*$", "", line) if not line.startswith("python ") else line.split("  #")[0]
            out.append(re.sub(r"\s*\[(.*?)\]", "", cmd).strip())  # without the optional part
            opt = re.search(r"\[(.*?)\]", cmd)
            if opt:
                out.append(re.sub(r"\[(.*?)\]", r"\1", cmd).strip())  # and with it
    return out


def test_the_example_files_are_the_ones_shown():
    for block in _blocks("python"):
        first = block.splitlines()[0]
        if first.startswith("# studies/"):
            name = first[2:].strip()
            assert (REPO / name).read_text() == block, f"{name} differs from the README"
    assert {"studies/pi.py", "studies/two_stage.py"} <= {b.splitlines()[0][2:] for b in _blocks("python")}


def _env():
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    for k in ("DASK_SCHEDULER_ADDRESS", "TUBEID_TEST_FAIL_STAGE", "TUBEID_TEST_FAIL_AT"):
        env.pop(k, None)
    return env


def test_every_command_of_the_runner_sections_runs(tmp_path):
    shutil.copytree(REPO / "studies", tmp_path / "studies")
    commands = _commands()
    assert len(commands) >= 8 and any(c.startswith("tubeid run studies/two_stage.py") for c in commands)
    outputs = {}
    for cmd in commands:
        argv = shlex.split(cmd)
        argv = [sys.executable, "-m", "tubeid", *argv[1:]] if argv[0] == "tubeid" else [sys.executable, *argv[1:]]
        proc = subprocess.run(argv, cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, f"{cmd}\n{proc.stderr}"
        assert "Traceback" not in proc.stderr, cmd
        outputs[cmd] = proc.stdout
    # what the comments promise
    assert "pi: 8/8 blocks done (100.0 %), complete" in outputs["tubeid status results/pi.zarr"]
    assert "verified: blocks: 8 finished blocks match their checksums" in outputs["tubeid status results/pi.zarr --verify"]
    # the mean of 256 estimates from 1e5 points each: sd sqrt(pi (4 - pi) / 2.56e7) = 3.2e-4; 5 sd
    assert abs(float(outputs[next(c for c in commands if c.startswith("python"))]) - math.pi) < PI_TOL
    assert "delta: 17/17 blocks done" in outputs["tubeid status results/two-stage.zarr"] or \
        "stages complete, complete" in outputs["tubeid status results/two-stage.zarr"]
    assert "stage delta" in outputs["tubeid show results/two-stage.zarr --stage delta"]
    assert "stage response" not in outputs["tubeid show results/two-stage.zarr --stage delta"]
    _check_the_open_pipeline_example(tmp_path)


def _values_of_the_block(block: str, cwd: pathlib.Path) -> tuple[dict, list]:
    """Run a README block in ``cwd`` as written; return its names and the value of each bare expression line."""
    tree = ast.parse(block)
    for i, stmt in enumerate(tree.body):  # `expr` -> `_values.append(expr)`: the same line, its value kept
        if isinstance(stmt, ast.Expr):
            call = ast.Call(ast.Attribute(ast.Name("_values", ast.Load()), "append", ast.Load()), [stmt.value], [])
            tree.body[i] = ast.copy_location(ast.Expr(call), stmt)
    namespace: dict = {"_values": []}
    here = os.getcwd()
    os.chdir(cwd)
    try:
        exec(compile(ast.fix_missing_locations(tree), "README.md (open_pipeline example)", "exec"), namespace)
    finally:
        os.chdir(here)
    return namespace, namespace["_values"]


def _check_the_open_pipeline_example(tmp_path):
    """The `open_pipeline` block, run on the store the section's commands made, gives what its comments say."""
    (block,) = [b for b in _blocks("python") if "open_pipeline" in b]
    names, (delta_opt, delta, root) = _values_of_the_block(block, tmp_path)
    res = names["res"]
    assert list(res) == ["delta", "response"], list(res)                             # {"delta": ..., "response": ...}
    assert delta_opt == res["delta"].attrs["delta_opt"] and 0.05 <= delta_opt <= 0.85  # the stage's summary
    import xarray as xr
    plain = xr.open_zarr(tmp_path / "results/two-stage.zarr", group="delta")         # = xarray.open_zarr(..., group=)
    assert set(delta.data_vars) == set(plain.data_vars) == {"J"}, \
        f"the README's open_results(..., group=...) line gives {set(delta.data_vars)}, not the delta stage's J"
    assert (delta.J.values == plain.J.values).all()
    for key in ("study_hash", "tubeid_version", "stage_blocks", "stages_complete"):  # provenance and the summary
        assert key in root.attrs, f"root summary lacks {key}"
    assert list(root.attrs["stages_complete"]) == ["delta", "response"]


def test_the_notebook_example_runs_on_its_client(tmp_path):
    (block,) = [b for b in _blocks("python") if "LocalCluster" in b]
    shutil.copytree(REPO / "studies", tmp_path / "studies")
    proc = subprocess.run([sys.executable, "-c", block], cwd=tmp_path, env=_env(), capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "running on the dask Client already open in this process" in proc.stderr
    computed, mean = proc.stdout.split()
    assert computed == "8" and abs(float(mean) - math.pi) < PI_TOL
