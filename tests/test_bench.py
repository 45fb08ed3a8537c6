"""Benchmarks run and report their keys (a smoke test: no timing is asserted)."""

import math

from tubeid.bench import bench_j
from tubeid.dynamics.bench import bench_transient


def test_bench_j_reports_rates_and_agreement():
    out = bench_j(n_realisations=10, n_deltas=2, n_baseline=1)
    assert out["j_evaluations_per_second"] > 0 and out["j_speedup"] > 0
    assert out["j_baseline_relative_difference"] < 1e-3  # the loop and the closed form agree


def test_bench_transient_reports_the_issue_keys():
    out = bench_transient(duration=24.0, baseline_window=0.2, n_psd_realisations=1, realisations_per_call=2, repeat=1,
                          psd_sets=3)
    for key in ("seconds_per_realisation", "baseline_seconds_per_realisation", "speedup", "flop_bound_seconds",
                "psd_error_vs_fine_step", "seconds_fast_path"):
        assert key in out and math.isfinite(out[key]) and out[key] >= 0
    # differences of two separately timed runs (with the stops, with the gaps opened): their sign is a
    # timing, which a loaded machine may flip on this short record, so only their presence is checked
    for key in ("seconds_event_handling", "microseconds_per_flagged_step"):
        assert key in out and math.isfinite(out[key])
    assert out["f_max_hz"] > 900  # the stop-closed highest frequency of the paper model (947 Hz, MODEL.md 3.7)
    assert out["integration_step_s"] == 2.5e-4  # default rule: 4 points per period of f_max, dividing 2 ms and 3 ms
    # the step error's scatter: three independent sets, the first the one reported alone (so they differ)
    sets = out["psd_error_sets"]
    assert sets["sets"] == 3
    assert sets["max"] >= out["psd_error_vs_fine_step"] and sets["max"] >= sets["p90"] >= sets["median"]
    assert len({out["psd_error_vs_fine_step"], sets["median"], sets["max"]}) > 1  # not three copies of one set
    # the stop is active in this realisation: contacts are located (about two switches per contact)
    assert out["switches"] > 0 and out["flagged_steps"] >= out["switches"] // 2


def test_bench_transient_refuses_a_bad_set_count():
    import pytest

    from tubeid.errors import SpecificationError

    with pytest.raises(SpecificationError, match="psd_sets = 0"):
        bench_transient(duration=24.0, psd_sets=0)


def test_baseline_agrees_with_symplectic_euler_kernel():
    """The benchmark's per-step numpy loop is the solver's symplectic Euler, step for step."""
    import numpy as np

    from test_solver import DT_LOAD, contact_setup
    from tubeid.dynamics.bench import simulate_baseline
    from tubeid.dynamics.solver import simulate

    M, D, K, stop, B, C, F = contact_setup(n_t=51)
    y_b, h = simulate_baseline(M, D, K, [stop], B, C, F, DT_LOAD, output_dt=DT_LOAD)
    se = simulate(M, D, K, [stop], B, C, F, DT_LOAD, output_dt=DT_LOAD, dt=h, method="symplectic-euler")
    # same scheme, same step; only summation order differs
    np.testing.assert_allclose(y_b, se.observations.values[0], rtol=0, atol=1e-9 * np.max(np.abs(y_b)))


def test_bench_runner_refuses_bad_arguments_before_any_work(capsys, monkeypatch):
    """``tubeid bench-runner``: NaN, infinity or a count below its minimum is one error line, status 2, checked
    before the calibration and the header (a bad --workers used to be refused only by the first run)."""
    import pytest

    from tubeid.cli import main
    from tubeid.runner import bench

    def never(*args, **kwargs):
        raise AssertionError("the benchmark started")

    monkeypatch.setattr(bench, "_calibrate", never)
    for args, field in ((["--block-seconds", "nan"], "--block-seconds = nan"),
                        (["--block-seconds", "inf"], "--block-seconds = inf"),
                        (["--block-seconds", "-1"], "--block-seconds = -1.0"),
                        (["--block-seconds", "1e308"], "--block-seconds = 1e+308"),
                        (["--workers", "-1"], "--workers = -1"),
                        (["--workers", "1", "-2"], "--workers = -2"),
                        (["--blocks", "0"], "--blocks = 0"),
                        # huge: a Study over 4e9 realisations (a MemoryError traceback, or the machine's memory),
                        # days of compute, or a million worker processes
                        (["--blocks", "1000000000"], "--blocks = 1000000000"),
                        (["--blocks", "100000", "--block-seconds", "1"], "--blocks = 100000"),
                        (["--blocks", "200", "--block-seconds", "3600"], "--blocks = 200"),
                        (["--workers", "1", "1000000"], "--workers = 1000000")):
        assert main(["bench-runner", *args]) == 2, args
        out, err = capsys.readouterr()
        assert out == "" and err.startswith(f"tubeid: error: {field}:") and err.count("\n") == 1, (args, err)
        assert ": must be" in err or "more than 86400 s (a day)" in err, (args, err)
    from tubeid.errors import SpecificationError

    with pytest.raises(SpecificationError, match="--workers"):
        bench.main(worker_counts=[])


def test_bench_transient_warms_up_on_any_load_sampling():
    """The kernels' warm-up integrates realisation 0 over discard + 22 s whatever ``dt_load``: it took the
    first 12 001 load samples (24 s at 2 ms), so at 1e-4 s it integrated 1.2 s, less than the 2 s discarded,
    and the bench ended in "discard = 2.0: must be ... in [0, 0.12)" after drawing the loads."""
    out = bench_transient(duration=24.0, baseline_window=0.05, n_psd_realisations=1, realisations_per_call=1,
                          repeat=1, dt_load=1e-4)
    assert out["integration_step_s"] <= 1e-4  # the step divides the load sampling
    assert math.isfinite(out["seconds_per_realisation"]) and out["seconds_per_realisation"] > 0


def test_bench_transient_refuses_bad_arguments_before_any_work(monkeypatch):
    """Each argument out of its range is one SpecificationError naming it, raised before a realisation is
    drawn (a count of 0 ended in an UnboundLocalError or an empty mean after the timed runs)."""
    import pytest

    from tubeid.dynamics import bench
    from tubeid.errors import SpecificationError

    def never(*args, **kwargs):
        raise AssertionError("the benchmark started")

    monkeypatch.setattr(bench, "simulate", never)
    for kwargs, field in ((dict(repeat=0), "repeat = 0"), (dict(realisations_per_call=0), "realisations_per_call = 0"),
                          (dict(n_psd_realisations=0), "n_psd_realisations = 0"), (dict(bands_hz=0.0), "bands_hz = 0.0"),
                          (dict(baseline_window=0.0), "baseline_window = 0.0"), (dict(seed=-1), "seed = -1"),
                          (dict(psd_sets=bench.MAX_PSD_SETS + 1), f"psd_sets = {bench.MAX_PSD_SETS + 1}"),
                          (dict(dt_load=0.01), "dt_load = 0.01: must resolve the band"),
                          (dict(dt_load=1e-9), "dt_load = 1e-09: needs")):
        with pytest.raises(SpecificationError, match="^" + field.replace("(", r"\(")):
            bench.bench_transient(duration=24.0, **kwargs)


def test_bench_command_refuses_bad_options_before_any_section_runs(monkeypatch, capsys):
    """``tubeid bench``: a bad --psd-sets or --dt-load is one line naming the option, status 2, before the j
    section runs (it ran first, then the refusal named ``psd_sets`` or ``dt_load``, or ``duration`` and ``dt``
    for a --dt-load too fine or too coarse); an option of the transient section given to ``bench j`` is
    refused, not ignored; a set count is bounded (1e9 sets ran for years)."""
    import tubeid.bench as cli_bench
    from tubeid.cli import main
    from tubeid.dynamics import bench

    def never(*args, **kwargs):
        raise AssertionError("the benchmark started")

    monkeypatch.setattr(cli_bench, "bench_j", never)
    monkeypatch.setattr(bench, "bench_transient", never)
    for args, start in ((["--psd-sets", "0"], "--psd-sets = 0: must be an integer in [1, "),
                        (["transient", "--psd-sets", "1000000000"], "--psd-sets = 1000000000: must be an integer in"),
                        (["--dt-load", "nan"], "--dt-load = nan: must be"),
                        (["--dt-load", "0.01"], "--dt-load = 0.01: must resolve the band"),
                        (["--dt-load", "1e-9"], "--dt-load = 1e-09: needs"),
                        (["j", "--dt-load", "1e-3"], "--dt-load = 0.001: applies to the transient section only"),
                        (["j", "--psd-sets", "3"], "--psd-sets = 3: applies to the transient section only"),
                        (["j", "--compile-time"], "--compile-time = True: applies to the transient section only")):
        assert main(["bench", *args]) == 2, args
        out, err = capsys.readouterr()
        assert out == "" and err.startswith(f"tubeid: error: {start}") and err.count("\n") == 1, (args, err)


def test_bench_j_refuses_bad_counts_naming_them():
    """More baseline realisations than Monte Carlo ones ended in numpy's broadcast ValueError after the
    timed runs; a count of 0 was refused as ``realisations = array([])``, naming neither argument."""
    import pytest

    from tubeid.errors import SpecificationError

    for kwargs, field in ((dict(n_baseline=20, n_realisations=10), "n_baseline = 20: must be an integer in [1, 10]"),
                          (dict(n_baseline=0), "n_baseline = 0"), (dict(n_realisations=0), "n_realisations = 0"),
                          (dict(n_realisations=2.5), "n_realisations = 2.5"), (dict(n_deltas=0), "n_deltas = 0"),
                          (dict(seed=-1), "seed = -1")):
        with pytest.raises(SpecificationError, match="^" + field.replace("[", r"\[")):
            bench_j(**kwargs)


def test_bench_runner_shows_an_in_process_run_as_such(capsys, monkeypatch):
    """``--workers 0 1``: the in-process run (which counts as one worker in the overhead) was shown as "1" in
    both rows, and the note said "with 1 workers vs 0"."""
    from types import SimpleNamespace

    import tubeid.runner.execute as execute
    import tubeid.runner.testing as testing
    from tubeid.runner import bench

    def fake_run(study, store, *, workers, progress, quiet):
        return SimpleNamespace(workers=max(workers, 1), startup=0.1, wall=2.0 if workers == 0 else 1.0,
                               compute=2.0 if workers == 0 else 1.5, write=0.01, store=store)

    monkeypatch.setattr(bench, "_calibrate", lambda seconds: 1)
    monkeypatch.setattr(execute, "run", fake_run)
    monkeypatch.setattr(testing, "store_digest", lambda store: "same")
    assert bench.main(blocks=2, block_seconds=0.01, worker_counts=(0, 1)) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines()]
    firsts = [r[:2] for r in rows if r and (r[0].isdigit())]
    assert firsts[0] == ["0", "(here)"] and firsts[1][0] == "1", firsts
    note = next(" ".join(r) for r in rows if r and r[0] == "note:")
    assert "with 1 vs 0 (here)" in note, note
