"""``tubeid diagnose DATA [--model NAME_OR_SPEC] [--out DIR] [--workers N | --scheduler ADDR]``: the
loop of :mod:`tubeid.diagnose.method` from the command line. Its grids and Monte Carlo simulations run
as a runner pipeline in ``DIR/diagnose.zarr``: rerunning the same command resumes (or reuses) it."""

from __future__ import annotations

import dataclasses
import sys

from tubeid.runner.cli import _setting  # NAME=VALUE, the value read as a Python literal

__all__ = ["register"]


def _settings(args):
    from tubeid.diagnose import DiagnoseSettings
    from tubeid.errors import SpecificationError

    kw = {k: v for k, v in (("realisations", args.realisations), ("blocks", args.blocks),
                            ("segment_seconds", args.segment_seconds), ("delta", args.delta),
                            ("delta_reference", args.delta_reference), ("load_dispersion", args.load_dispersion),
                            ("load", args.load), ("false_alarm", args.false_alarm), ("max_effects", args.max_effects),
                            ("seed", args.seed), ("model_form", args.model_form)) if v is not None}
    fields = {f.name for f in dataclasses.fields(DiagnoseSettings)}
    for name, value in args.settings:
        if name not in fields:
            raise SpecificationError(f"--set {name}", value, f"unknown setting (known: {sorted(fields)})")
        kw[name] = list(value) if isinstance(value, tuple) else value
    return DiagnoseSettings(**kw)


def _cmd_diagnose(args) -> int:
    from tubeid.diagnose import diagnose

    try:
        result = diagnose(args.data, args.model, _settings(args), out=args.out, workers=args.workers,
                          scheduler=args.scheduler, overwrite=args.overwrite,
                          progress=False if args.no_progress else None, quiet=False)
    except KeyboardInterrupt:
        print("\ntubeid: interrupted; finished tasks are kept in the store: rerun the same command to resume", file=sys.stderr)
        return 130
    rep = result.report
    det = rep["detection"]
    print(f"test ({det['model_form']} model form: {', '.join(det['p_values'])}): p = {det['p_value']:.3g} "
          f"(false-alarm rate {det['false_alarm']:g}): " + ("departure detected" if det["detected"] else "nothing detected"))
    for e in rep["effects"]:
        params = ", ".join(f"{k} = {v['value']:.4g} {v['units']}".rstrip() if isinstance(v["value"], float) else f"{k} = {v['value']}"
                           for k, v in e["parameters"].items())
        print(f"effect: {e['name']} ({params})")
    if not rep["effects"]:
        print("effect: none")
    print(f"held-out error before: {rep['error_before']:.4g}  after: {rep['error_after']:.4g}; "
          f"explained after: {rep['explained_after']} ({rep['stop_reason']})")
    load = rep["load"]
    if load["delta_F_given"]:
        print(f"delta_F: {load['delta_F']} ({load['delta_F_source']})")
    else:
        std = load["delta_F_std"]
        print(f"delta_F: {load['delta_F']:.3g}" + (f" ± {std:.2g} (Monte Carlo)" if std is not None else "")
              + (" — the likelihood is flat: not identified" if load["delta_F_flat"] else ""))
        if load["load_dispersion"] != load["delta_F"]:
            print(f"  the band uses delta_F = {load['load_dispersion']:g}: {load['load_dispersion_reason']}")
    out = result.store.parent
    print(f"report: {out / 'report.json'}, {out / 'report.md'}, {out / 'residual.png'}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "diagnose", help="test measured data against a declared model; name the effects it lacks",
        description="Identify the load (r, delta_F) on measured data for a declared model, test the held-out spectra "
                    "against the model's own realisations (calibrated false-alarm rate), and when the test detects a "
                    "departure select catalog effects (tone, stop, added_mass, damping, sensor_noise) by held-out "
                    "error, re-fitting them and the load jointly. Grids and Monte Carlo run as a runner pipeline in "
                    "DIR/diagnose.zarr: rerun the same command to resume.")
    p.add_argument("data", help="measured record: NetCDF, Zarr, CSV (+ .sensors.csv) or UFF 58 (never modified)")
    p.add_argument("--model", default="paper-simplified", help="built-in model name or a .yaml/.toml specification (default: paper-simplified)")
    p.add_argument("--out", default="diagnosis",
                   help="output directory: report.json, report.md, residual.png, delta_f.png, a copy of the validated "
                        "record and the pipeline store diagnose.zarr, listed in its manifest (default: diagnosis)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--workers", type=int, default=None,
                   help="embedded LocalCluster worker processes (default: one per core; 0 = sequentially in this process)")
    g.add_argument("--scheduler", default=None, help="address of an existing dask scheduler (default: DASK_SCHEDULER_ADDRESS)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the diagnosis --out holds: removes only the files its manifest lists, unchanged, "
                        "once every check has passed; refused while another tubeid run uses --out (default: resume "
                        "the same diagnosis, refuse another)")
    p.add_argument("--realisations", type=int, default=None,
                   help="Monte Carlo size of the test (default 39 with the exact model form: exact 5 %%; 159 with "
                        "the simplified one)")
    p.add_argument("--false-alarm", type=float, default=None, help="stated false-alarm rate of the test (default 0.05)")
    p.add_argument("--blocks", type=int, default=None, help="time blocks; even ones fit, odd ones held out (default 4)")
    p.add_argument("--segment-seconds", type=float, default=None, help="Welch segment in s (default 2)")
    p.add_argument("--delta", type=float, default=None, help="model dispersion δ of B's stiffness, given (default 0.2)")
    p.add_argument("--delta-reference", default=None,
                   help="identify δ by the paper's maximum likelihood of J against this reference model (name or file)")
    p.add_argument("--load-dispersion", type=float, default=None,
                   help="impose δ_F (default: identified by maximum likelihood of J_s when there are enough blocks)")
    p.add_argument("--load", choices=("distributed", "force_and_moment"), default=None,
                   help="identification load model (default distributed)")
    p.add_argument("--model-form", choices=("exact", "simplified"), default=None,
                   help="what the declared model is: 'exact' (the structure up to its random B: the test reads the "
                        "spectrum's shape) or 'simplified' (the test reads only lines, the incoherent floor, kurtosis, "
                        "resonance sharpness and the spectrum's log-log slope); default: simplified when "
                        "--delta-reference is given, else exact")
    p.add_argument("--max-effects", type=int, default=None, help="effects selected at most (0: the test only; default 3)")
    p.add_argument("--seed", type=int, default=None, help="seed of all random streams (default 0)")
    p.add_argument("--set", dest="settings", action="append", type=_setting, default=[], metavar="NAME=VALUE",
                   help="any other DiagnoseSettings field, e.g. --set fit_realisations=4 --set r0=[2.0]")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=_cmd_diagnose)
