"""benchmarks/kernel_profile.py: its pure parts (name demangling, the enclosing function of a line,
the kernel's object code from a numba cache file), its workloads, ``--split`` and its argument checks.
The profile itself needs Linux ``perf`` and compiles the kernels with debug information (about a
minute): a slow test, skipped where perf or binutils are missing."""

from __future__ import annotations

import importlib.util
import pathlib
import pickle
import shutil

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def kp():
    spec = importlib.util.spec_from_file_location("kernel_profile", ROOT / "benchmarks" / "kernel_profile.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_short_names_the_module_and_function_of_a_numba_symbol(kp):
    assert kp.short("_ZN6tubeid8dynamics6solver7_events8evaluateB4v104B38c8tJTC_2fWQAlbW1yBEEAAA") \
        == "_events.evaluate"
    assert kp.short("cfunc._ZN6tubeid8dynamics6solver9_fastpath9run_exactB3v12E") == "cfunc._fastpath.run_exact"
    # numba's "<locals>.impl" of an overload is dropped: the overload's own name is kept
    assert kp.short("_ZN5numba4core8builtins6ol_min12_3clocals_3e4implB2v5E") == "builtins.ol_min"


def test_enclosing_functions_gives_the_innermost_function_of_each_line(kp, tmp_path):
    src = tmp_path / "m.py"
    src.write_text("x = 1\n"            # 1
                   "def outer():\n"     # 2
                   "    a = 1\n"        # 3
                   "    def inner():\n"  # 4
                   "        return a\n"  # 5
                   "    return inner\n")  # 6
    where = kp.enclosing_functions(src)
    assert 1 not in where
    assert [where[k] for k in (2, 3, 4, 5, 6)] == ["outer", "outer", "inner", "inner", "outer"]


def test_kernel_object_is_read_from_the_cache_files_pickles(kp, tmp_path):
    elf = b"\x7fELF" + bytes(range(40))
    cache = tmp_path / "cache" / "sub"
    cache.mkdir(parents=True)
    with open(cache / "_fastpath.run_exact-25.py311.1.nbc", "wb") as f:  # an index pickle, then the data
        pickle.dump({"stamp": 1}, f)
        pickle.dump(("library", [b"not an object", {"obj": elf}]), f)
    (cache / "_events.evaluate-100.py311.1.nbc").write_bytes(pickle.dumps(b"\x7fELF other kernel"))
    assert kp.kernel_object(tmp_path / "cache") == elf
    (cache / "_fastpath.run_exact-25.py311.1.nbc").write_bytes(pickle.dumps({"no": b"object"}))
    with pytest.raises(SystemExit, match="no compiled run_exact"):
        kp.kernel_object(tmp_path / "cache")


def test_the_workloads_are_the_bench_realisation_and_the_mean_reference_model(kp):
    from tubeid.mechanics.library import builtin_spec
    from tubeid.mechanics.reduction import reduce

    assert kp.MODELS == ("paper-simplified", "paper-reference")
    M, D, K, B, C, F, stops = kp.workload("paper-reference")
    Mr, Dr, Kr = reduce(builtin_spec("paper-reference")).mean_matrices
    assert M.shape == (50, 50) and np.array_equal(M, Mr) and np.array_equal(K, Kr) and np.array_equal(D, Dr)
    assert F.shape == (110001, 7) and B.shape == (50, 7) and C.shape[1] == 50
    assert [(g, k) for _b, g, k in stops] == [(s.gap, s.stiffness) for s in builtin_spec("paper-reference").stops]
    Ms, _, Ks, _, _, Fs, _ = kp.workload("paper-simplified")
    spec = importlib.util.spec_from_file_location("solver_against_ref", ROOT / "benchmarks" / "solver_against_ref.py")
    ref = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ref)
    Mb, _, Kb, _, _, Fb, _ = ref.realisation(0, 220.0)[0]  # the bench's realisation 0
    assert Ms.shape == (16, 16) and np.array_equal(Ms, Mb) and np.array_equal(Ks, Kb) and np.array_equal(Fs, Fb)
    # the reference's load is the mean spectrum drawn from the same stream (the same normal draws):
    # not the bench's randomised spectrum, but nearly the same history (another stream: uncorrelated)
    assert not np.array_equal(F, Fs)
    assert np.corrcoef(F[:, 0], Fs[:, 0])[0, 1] > 0.9


def test_split_times_both_paths_and_divides_the_difference_by_the_switches(kp):
    out = kp.split("paper-reference", calls=1)
    assert out["model"] == "paper-reference" and out["n_dof"] == 50 and out["calls"] == 1
    assert out["flagged_steps"] >= out["switches"] / 2 and out["evaluations"] >= out["switches"] / 2
    assert out["switches"] > 1000 and out["switches_gap_opened"] == 0  # 220 s: tens of thousands of contacts
    assert 0 < out["seconds_gap_opened"] < out["seconds_stop_active"]
    per = (out["seconds_stop_active"] - out["seconds_gap_opened"]) / out["switches"]
    assert out["microseconds_per_switch"] == pytest.approx(1e6 * per, rel=1e-12, abs=0)


def test_split_uses_the_given_step_in_every_call(kp, monkeypatch):
    import tubeid.dynamics.solver as solver

    seen = []
    timed = solver.simulate

    def recording(*args, **kwargs):
        seen.append((kwargs.get("dt"), args[3][0].gap))
        return timed(*args, **kwargs)

    monkeypatch.setattr(solver, "simulate", recording)
    default = kp.split("paper-simplified", calls=1)
    assert default["dt"] is None and default["steps"] == 880_000  # 220 s at the rule's 0.25 ms
    assert seen and {dt for dt, _ in seen} == {None}
    seen.clear()
    coarse = kp.split("paper-simplified", calls=2, dt=2e-3 / 6)
    assert coarse["dt"] == 2e-3 / 6 and coarse["steps"] == 660_000
    # warm-up then 2 timed calls of each system, alternated, all at the given step
    assert [dt for dt, _ in seen] == [2e-3 / 6] * 6 and [g > 1 for _, g in seen] == [False, True] * 3


@pytest.mark.parametrize("argv, message", [(["--dt", "1e-4"], "--dt applies to --split only"),
                                           (["--split", "--open"], "--open applies to the profile"),
                                           (["--split", "--calls", "0"], "--calls must be at least 1, not 0")])
def test_options_that_do_not_combine_are_refused(argv, message):
    import subprocess
    import sys

    res = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "kernel_profile.py"), *argv],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and message in res.stderr and not res.stdout


@pytest.mark.slow
@pytest.mark.skipif(any(shutil.which(t) is None for t in ("perf", "objdump", "nm")), reason="needs perf and binutils")
def test_the_profile_runs_end_to_end_and_attributes_samples_to_the_kernels_lines():
    """The whole script (a debug build in an empty numba cache: about a minute): its samples fall in
    ``run_exact``, whose lines are named in the solver's files."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "kernel_profile.py"), "--calls", "3", "--top", "5"],
                         capture_output=True, text=True, check=True, timeout=600).stdout
    lines = out.splitlines()
    assert "paper-simplified, stop active, 3 calls of simulate" in lines[0]
    shares = {ln.split("%")[1].strip(): float(ln.split("%")[0]) for ln in lines[1:] if ln.strip().endswith(
        ("run_exact", "evaluate"))}
    assert shares["_fastpath.run_exact"] > 50  # the main loop holds most of the compiled code's samples
    at = [i for i, ln in enumerate(lines) if ln.strip().startswith(tuple("0123456789")) and " line " in ln]
    assert len(at) == 5 and all(float(lines[i].split("%")[0]) > 0 for i in at)
    # each reported line is followed by that line in at least one of the solver's files, with its function
    for i in at:
        assert lines[i + 1].strip().startswith(("fastpath", "modal", "events")), lines[i:i + 2]
