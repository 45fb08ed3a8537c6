"""``tubeid diagnose DATA [--model NAME_OR_SPEC] [--out DIR]``: the measured-data loop of
:mod:`tubeid.measured.diagnose` from the command line."""

from __future__ import annotations

import argparse

__all__ = ["register"]


def _cmd_diagnose(args) -> int:
    from tubeid.measured.diagnose import DiagnoseSettings, diagnose

    kw = {k: v for k, v in (("realisations", args.realisations), ("blocks", args.blocks),
                            ("segment_seconds", args.segment_seconds), ("delta", args.delta),
                            ("load_dispersion", args.load_dispersion), ("load", args.load),
                            ("seed", args.seed)) if v is not None}
    result = diagnose(args.data, args.model, DiagnoseSettings(**kw))
    out = result.write(args.out)
    rep = result.report
    params = ", ".join(f"{k} = {v['value']:.4g} {v['units']}" if isinstance(v["value"], float) else f"{k} = {v['value']}"
                       for k, v in rep["parameters"].items())
    print(f"effect: {rep['effect']}" + (f" ({params})" if params else ""))
    print(f"error before: {rep['error_before']:.4g}  after: {rep['error_after']:.4g}  (decades; held-out segments)")
    print(f"report: {out / 'report.json'}, {out / 'report.md'}, {out / 'residual.png'}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "diagnose", help="trace the residual of measured data to a missing effect; error before/after",
        description="Identify the load on measured data for a declared model, compare the held-out "
                    "spectra with the model's confidence band, trace the residual to a catalog effect "
                    "(tone, stop, added_mass, damping, sensor_noise) or 'none', re-identify and report.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("data", help="measured record: NetCDF, Zarr, CSV (+ .sensors.csv) or UFF 58")
    p.add_argument("--model", default="paper-simplified", help="built-in model name or a .yaml/.toml specification")
    p.add_argument("--out", default="diagnosis", help="output directory (report.json, report.md, residual.png)")
    p.add_argument("--realisations", type=int, default=None, help="Monte Carlo size of the band (default 40)")
    p.add_argument("--blocks", type=int, default=None, help="time blocks; even ones fit, odd ones held out (default 4)")
    p.add_argument("--segment-seconds", type=float, default=None, help="Welch segment in s (default 2)")
    p.add_argument("--delta", type=float, default=None, help="model dispersion δ of B's stiffness (default 0.2)")
    p.add_argument("--load-dispersion", type=float, default=None, help="load dispersion δ_F (default 0.04)")
    p.add_argument("--load", choices=("distributed", "force_and_moment"), default=None,
                   help="identification load model (default distributed)")
    p.add_argument("--seed", type=int, default=None, help="seed of all random streams (default 0)")
    p.set_defaults(func=_cmd_diagnose)
