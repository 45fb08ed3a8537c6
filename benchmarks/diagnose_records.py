"""Diagnose fresh records of the campaign's cases on 2 workers, one line per record (not a test).

    python benchmarks/diagnose_records.py CASE[,CASE...] SEED[,SEED...] [--paired] [--model NAME] [--set NAME=VALUE ...] [--dir DIR]

Every case with every seed, or with ``--paired`` the i-th case with the i-th seed. Each record is made by ``tubeid.diagnose.testing.make_record`` (the reference model with the case's
effects written by hand, ``studies/diagnose_effects.py``'s ``CASES``; ``added_mass_xF``: the centre
tube's density × F, 7 sensors), written to NetCDF-3 in DIR (scipy: the core install writes it, as
diagnose's own copy of a record; the same values as NetCDF-4, float64), then
diagnosed by the command line of this interpreter (``python -m tubeid diagnose REC.nc --model NAME --out DIR/... --workers 2``).
Printed per record: case, seed, wall time of the diagnosis, p-value, named effects and their
parameters, whether exactly the true effects are named, whether explained after.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import pathlib
import subprocess
import sys
import time

REPO = pathlib.Path(__file__).resolve().parents[1]


def _cases():
    spec = importlib.util.spec_from_file_location("diagnose_effects", REPO / "studies" / "diagnose_effects.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.CASES


def _short(v):
    return round(v, 4) if isinstance(v, float) else v


def main() -> None:
    """Make, diagnose and summarise one record per (case, seed)."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("cases", help="comma-separated case names of studies/diagnose_effects.py CASES")
    p.add_argument("seeds", help="comma-separated record seeds")
    p.add_argument("--paired", action="store_true", help="the i-th case with the i-th seed only")
    p.add_argument("--model", default="paper-reference", help="the declared model (default paper-reference)")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="passed to tubeid diagnose")
    p.add_argument("--dir", default="diagnose-records", help="where records and diagnoses are written")
    args = p.parse_args()
    from tubeid.diagnose.testing import make_record
    from tubeid.measured import write_measurements

    cases = _cases()
    out = pathlib.Path(args.dir)
    out.mkdir(parents=True, exist_ok=True)
    names, seeds = args.cases.split(","), [int(s) for s in args.seeds.split(",")]
    if args.paired and len(names) != len(seeds):
        p.error(f"--paired needs as many seeds as cases ({len(names)}), got {len(seeds)}")
    pairs = list(zip(names, seeds)) if args.paired else [(n, s) for n in names for s in seeds]
    for name, seed in pairs:
        if name.startswith("added_mass_x") and name not in cases:
            from tubeid.diagnose.testing import HandEffects

            effects = HandEffects(density={"centre": float(name.removeprefix("added_mass_x"))})
            truth, xs = ("added_mass",), cases["added_mass"][2]
        else:
            effects, truth, xs, _ = cases[name]
        record = out / f"{name}-{seed}.nc"
        write_measurements(make_record("paper-reference", effects, xs=xs, seed=seed), record, format="netcdf3")
        where = out / f"{name}-{seed}-{args.model}"
        cmd = [sys.executable, "-m", "tubeid", "diagnose", str(record), "--model", args.model, "--out", str(where), "--workers", "2",
               "--no-progress", *[a for s in args.set for a in ("--set", s)]]
        t0 = time.perf_counter()
        res = subprocess.run(cmd, capture_output=True, text=True)
        seconds = time.perf_counter() - t0
        if res.returncode != 0:
            print(name, seed, "FAILED:", res.stderr.strip().splitlines()[-1:], flush=True)
            continue
        rep = json.loads((where / "report.json").read_text())
        named = [e["name"] for e in rep["effects"]]
        found = [(e["name"], {k: _short(v["value"]) for k, v in e["parameters"].items()}) for e in rep["effects"]]
        print(f"{name} seed {seed}: {seconds:.1f} s, p = {rep['detection']['p_value']:.3g}, named {found}, "
              f"exactly right: {sorted(named) == sorted(truth)}, explained after: {rep['explained_after']}",
              flush=True)


if __name__ == "__main__":
    sys.exit(main())
