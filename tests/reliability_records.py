"""Bad measured records and bad ``tubeid diagnose`` options, counted by how each ends.

Run: ``python tests/reliability_records.py [--json]`` (about a minute). The companion of
``tests/reliability_inputs.py`` (cut files, hostile values, specifications) for the refusals the
measured-data readers and ``tubeid diagnose`` make up front: a record that another tool wrote badly
(CSV headers, line endings and field sizes; UFF data types; NetCDF / Zarr packing attributes; paths
the file system or xarray cannot take) and options a careless user types. Each case ends as:

- **refused**: a ``SpecificationError`` in one line naming the field (for a record: its file), the
  value and the rule (through ``tubeid diagnose``: exit status 2, one line ``tubeid: error: ...``, or
  argparse's usage and its one-line error naming the option; and ``--out`` left as it was);
- **handled**: a legitimate variant read exactly (compared with the values written), or valid options
  reaching the run;
- **unclear**: refused, but the message is not one line or does not name the file / option;
- **wrong**: a bad record or option accepted, a value read wrong, or ``--out`` written by a refusal;
- **traceback**: any other exception.

The runner is replaced by a stand-in here (``tubeid.runner.execute.run`` raising :class:`_Ran`):
options that pass every up-front check "reach the run" without computing a diagnosis. Not collected by
pytest (no ``test_`` prefix); the tests named in the README's table keep each class from coming back.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import csv
import io
import json
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

from tubeid.errors import SpecificationError
from tubeid.measured.readers import read_measurements, sidecar_path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_measured import _by_xarray, _csv_by_hand, _CSV_DATA, _small_record, _uff_of_type, gaussian, raw_dataset  # noqa: E402

COLS = ["refused", "handled", "unclear", "wrong", "traceback"]


def _tree(path: Path) -> dict:
    """Every file under ``path`` with its bytes (``{}`` if it does not exist)."""
    if not path.exists():
        return {}
    if path.is_file():
        return {"": path.read_bytes()}
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def _read(path: Path, expected: np.ndarray | None) -> str:
    """How reading ``path`` ends; ``expected``: the exact displacement [m] of a legitimate record (None: bad)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            back = read_measurements(path)
    except SpecificationError as exc:
        said = str(exc)
        one_line = "\n" not in said and "\r" not in said and exc.rule
        name = Path(str(path)).stem[:60]  # the file, or its sidecar <stem>.sensors.csv, named as given
        names = name in said or repr(name)[1:-1] in said
        return ("refused" if expected is None else "wrong") if one_line and names else "unclear"
    except Exception:  # noqa: BLE001 - counted
        return "traceback"
    if expected is None:
        return "wrong"
    return "handled" if back.displacement.shape == expected.shape and np.array_equal(back.displacement.values, expected) \
        else "wrong"


def records(tmp: Path) -> dict:
    """Bad (and a few legitimate) records, by format; each read once through read_measurements."""
    rows: dict[str, collections.Counter] = {}

    def count(row, path, expected=None):
        rows.setdefault(row, collections.Counter())[_read(path, expected)] += 1

    exact = np.array([[1.5e-6, -2.5e-6], [-0.5e-6, 3.5e-6], [2.5e-6, 0.5e-6]])  # _CSV_DATA's samples [m]
    side = "sensor,tube,x\nS1,centre,0.1\nS2,centre,0.2\n"
    long = "S" * (csv.field_size_limit() + 1)
    csv_bad = {
        "cr.csv": (_CSV_DATA.replace("\n", "\r"), side),
        "crside.csv": (_CSV_DATA, side.replace("\n", "\r")),
        "crname.csv": (_CSV_DATA.replace("S2", "S\r2", 1), side),
        "crtube.csv": (_CSV_DATA, 'sensor,tube,x\nS1,centre,0.1\nS2,"cen\rtre",0.2\n'),
        "longhead.csv": (_CSV_DATA.replace("S2", long, 1), f"sensor,tube,x\nS1,centre,0.1\n{long},centre,0.2\n"),
        "longside.csv": (_CSV_DATA, f'sensor,tube,x\nS1,centre,0.1\nS2,"{long}",0.2\n'),
        "quote.csv": (_CSV_DATA, 'sensor,tube,x\nS1,"centre,0.1\n' + "S2,centre,0.2\n" * 11000),
        "dupx.csv": (_CSV_DATA, "sensor,tube,x,x\nS1,centre,0.1,0.3\nS2,centre,0.2,0.4\n"),
        "duptube.csv": (_CSV_DATA, "sensor,tube,tube,x\nS1,centre,north,0.1\nS2,centre,north,0.2\n"),
        "duptime.csv": (_CSV_DATA.replace("S2", "time", 1), "sensor,tube,x\nS1,centre,0.1\ntime,centre,0.2\n"),
        "dupsensor.csv": (_CSV_DATA.replace("S2", "S1", 1), "sensor,tube,x\nS1,centre,0.1\nS1,centre,0.2\n"),
        "text.csv": (_CSV_DATA.replace("-0.5e-6", "abc", 1), side),
        "short row.csv": (_CSV_DATA.replace(",3.5e-6", "", 1), side),
        "empty.csv": ("", side),
        "header only.csv": ("time,S1,S2\n", side),
        "latin1.csv": (_CSV_DATA.replace("S2", "S\xe92", 1), side.replace("S2", "S\xe92")),
        "nul.csv": (_CSV_DATA.replace("S2", "S\x002", 1), side),
        "no x.csv": (_CSV_DATA, "sensor,tube\nS1,centre\nS2,centre\n"),
        "x text.csv": (_CSV_DATA, "sensor,tube,x\nS1,centre,0.1\nS2,centre,near\n"),
        "x nan.csv": (_CSV_DATA, "sensor,tube,x\nS1,centre,0.1\nS2,centre,nan\n"),
        "missing sensor.csv": (_CSV_DATA, "sensor,tube,x\nS1,centre,0.1\n"),
        "scale zero.csv": (_CSV_DATA, "sensor,tube,x,scale\nS1,centre,0.1,0\nS2,centre,0.2,1\n"),
        "scale text.csv": (_CSV_DATA, "sensor,tube,x,scale\nS1,centre,0.1,big\nS2,centre,0.2,1\n"),
        "units furlong.csv": (_CSV_DATA, "sensor,tube,x,units\nS1,centre,0.1,furlong\nS2,centre,0.2,m\n"),
    }
    for name, (data, sidecar) in csv_bad.items():
        if name == "latin1.csv":
            p = tmp / name
            p.write_bytes(data.encode("latin-1"))
            sidecar_path(p).write_bytes(sidecar.encode("latin-1"))
        else:
            p = _csv_by_hand(tmp / name, data, sidecar)
        count("CSV: bad headers, line endings, fields, sidecars", p)
    (tmp / "nosidecar.csv").write_text(_CSV_DATA)
    count("CSV: bad headers, line endings, fields, sidecars", tmp / "nosidecar.csv")
    count("CSV: legitimate variants (CRLF, quoted names)", _csv_by_hand(tmp / "crlf.csv", _CSV_DATA.replace("\n", "\r\n"),
                                                                      side.replace("\n", "\r\n")), exact)
    count("CSV: legitimate variants (CRLF, quoted names)",
          _csv_by_hand(tmp / "quoted.csv", _CSV_DATA.replace("S2", '"S,2"', 1), 'sensor,tube,x\nS1,centre,0.1\n"S,2",centre,0.2\n'),
          exact)

    rec = _small_record()
    for data_type, unit in ((12, "m"), (11, "m"), (3, "m"), (9, "m"), (4, "m"), (0, "m/s^2"), (1, "m/s^2"), (1, "")):
        count("UFF 58: ordinate not displacement (acceleration, velocity, strain ... as m; general without a length unit)",
              _uff_of_type(tmp / f"t{data_type}-{len(unit)}.uff", rec, data_type, unit))
    for data_type in (0, 1, 8):  # legitimate: displacement, or unknown / general with a length unit
        p = _uff_of_type(tmp / f"ok{data_type}.uff", rec, data_type, "m")
        # ASCII 58 holds 12 significant digits: the reference is what the file says, parsed independently
        count("UFF 58: displacement, or unknown / general type with a length unit", p, _uff_ascii_values(p))

    raw = raw_dataset(gaussian(64, 3, key="packing", scale=1e-6))
    packing = {"scale_factor text": ("scale_factor", "abc", False), "add_offset text": ("add_offset", "abc", False),
               "scale_factor '0.05' on counts": ("scale_factor", "0.05", True),
               "scale_factor array": ("scale_factor", [0.5, 2.0], False),
               "scale_factor NaN on counts": ("scale_factor", np.nan, True),
               "scale_factor inf on counts": ("scale_factor", np.inf, True),
               "add_offset NaN on counts": ("add_offset", np.nan, True),
               "scale_factor -0.05 on counts": ("scale_factor", -0.05, True),
               "scale_factor 0 on counts": ("scale_factor", 0.0, True)}
    for fmt in ("h5netcdf", "scipy", "zarr"):
        for label, (attr, value, counts) in packing.items():
            ds = raw.copy(deep=True)
            if counts:
                ds["displacement"] = ds.displacement.copy(data=np.round(ds.displacement.values * 1e9).astype("int32"))
                ds.displacement.attrs["units"] = "nm"
            ds.displacement.attrs[attr] = value
            stem = label.replace(" ", "_").replace("'", "")
            path = tmp / (f"{stem}-{fmt}.zarr" if fmt == "zarr" else f"{stem}-{fmt}.nc")
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                if fmt == "zarr":
                    ds.to_zarr(path, consolidated=False)
                else:
                    ds.to_netcdf(path, engine=fmt)
            count("NetCDF-4, NetCDF-3, Zarr: CF packing attributes not a finite number > 0", path)
        ds = raw.copy(deep=True)  # legitimate packing: int32 counts [nm] * 0.5 + 3, read as (counts * 0.5 + 3) nm
        counts = np.round(ds.displacement.values * 1e9).astype("int32")
        ds["displacement"] = ds.displacement.copy(data=counts)
        ds.displacement.attrs.update(units="nm", scale_factor=0.5, add_offset=3.0)
        path = tmp / (f"packed-{fmt}.zarr" if fmt == "zarr" else f"packed-{fmt}.nc")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds.to_zarr(path, consolidated=False) if fmt == "zarr" else ds.to_netcdf(path, engine=fmt)
        count("NetCDF-4, NetCDF-3, Zarr: legitimate packing (int32 counts, scale_factor, add_offset)", path,
              (counts * 0.5 + 3.0) * 1e-9)

    mine = raw_dataset(gaussian(64, 3, key="mine", scale=1e-6))
    paths = collections.Counter()
    with contextlib.chdir(tmp):
        for name, other in (("a::b.nc", "a:"), ("z::b.zarr", "z:")):
            _by_xarray(mine, tmp / name, zarr=name.endswith(".zarr"))
            _by_xarray(raw_dataset(gaussian(64, 3, key="theirs", scale=1e-6)), tmp / other, zarr=name.endswith(".zarr"))
            paths[_read(Path(name), None)] += 1
    for ext in ("csv", "nc", "uff", "zarr"):
        paths[_read(tmp / ("x" * 300 + "." + ext), None)] += 1  # a name longer than the file system allows
    (tmp / "afile").write_text("")
    for p in (tmp / "afile" / "rec.nc", tmp / "missing.csv", tmp / "rec.npy", tmp / "noext", tmp / "nul\x00.nc"):
        paths[_read(p, None)] += 1
    (tmp / "dir.csv").mkdir()
    paths[_read(tmp / "dir.csv", None)] += 1
    rows["paths: '::' (xarray reads a URL), too long, a file among the parents, missing, unknown, NUL, a directory"] = paths
    return rows


def _uff_ascii_values(path: Path) -> np.ndarray:
    """The ordinates of an ASCII UFF 58 file written by :func:`_uff_of_type` (one dataset per sensor),
    parsed here without tubeid or pyuff: the lines after each dataset's 11-line header, 6 numbers a line
    (abscissa and ordinate alternate for uneven spacing; ordinates only for even spacing)."""
    lines = path.read_text().splitlines()
    cols, i = [], 0
    while i < len(lines):
        if lines[i].strip() == "-1" and i + 1 < len(lines) and lines[i + 1].strip() == "58":
            j = i + 13
            values = []
            while lines[j].strip() != "-1":
                values += [float(lines[j][k:k + 20]) for k in range(0, len(lines[j].rstrip()), 20)]
                j += 1
            cols.append(values)
            i = j + 1
        else:
            i += 1
    return np.array(cols).T


class _Ran(Exception):
    """The stand-in runner was reached: every up-front check passed."""


def _stand_in_run(*args, **kwargs):
    raise _Ran


def diagnose_options(tmp: Path) -> dict:
    """``tubeid diagnose RECORD OPTIONS`` for bad options (and two valid sets), in this process."""
    from tubeid.cli import main
    from tubeid.diagnose.testing import make_record
    from tubeid.measured import write_measurements
    from tubeid.runner import execute

    rec = make_record(xs=(2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0), duration=48.0, seed=11)
    data = write_measurements(rec, tmp / "rec.nc", format="netcdf3")
    zrec = write_measurements(rec, tmp / "rec.zarr")
    coarse = write_measurements(rec.isel(time=slice(None, None, 40)), tmp / "coarse.nc", format="netcdf3")
    clamped = rec.assign_coords(x=("sensor", np.r_[0.0, rec.x.values[1:]]))  # a sensor at the clamped end
    clamped = write_measurements(clamped, tmp / "clamped.nc", format="netcdf3", validate=False)
    import yaml

    from tubeid.mechanics import builtin_spec
    from tubeid.mechanics.spec import spec_to_dict

    carried = spec_to_dict(builtin_spec("paper-reference"))
    carried["effects"] = [{"kind": "sensor_noise", "level": 1e-16}]
    (tmp / "effects.yaml").write_text(yaml.safe_dump(carried, sort_keys=False))
    (tmp / "a file").write_text("")
    base = ["diagnose", str(data), "--model", "paper-reference", "--no-progress"]
    bad = {
        "--blocks": ["0", "-1", "1", "abc", "1e3"],
        "--segment-seconds": ["0", "-2", "nan", "inf", "1e300"],
        "--false-alarm": ["0", "1", "1.5", "nan", "-0.1"],
        "--delta": ["-0.1", "5", "nan", "1"],
        "--realisations": ["0", "-5", "1"],
        "--load-dispersion": ["2", "nan", "-1", "0.99"],
        "--delta-reference": ["no-such-model"],
        "--model": ["no-such-model", str(tmp / "missing.yaml"), str(tmp / "effects.yaml")],
        "--max-effects": ["-1", "1.5"],
        "--seed": ["-1", "1.5"],
        "--workers": ["-1", "x"],
        "--set": ["unknown=1", "r0=[-1.0]", "candidates=['nope']", "delta_f_grid=[0.5,0.1,0.2]", "penalty=nan",
                  "fit_realisations=0", "blocks='4'", "r_points=0", "tie=-1", "discard=-1", "dt_load_max=0",
                  "band_width_hz=inf", "level=1.5", "n_bootstrap=-1", "delta_f_min_blocks=0", "grid_points=1"],
        "--out": ["a::b", str(data), str(tmp / "a file")],
        "--out (inside the Zarr record diagnosed)": [str(zrec / "inside")],
        "data": [str(tmp / "missing.nc"), str(coarse), str(clamped)],
    }
    # valid, some at their documented limits (a given delta or delta_F of 0, a seed beyond 64 bits, no bootstrap)
    valid = [[], ["--blocks", "6", "--seed", "3", "--set", "fit_realisations=4"], ["--delta", "0"],
             ["--load-dispersion", "0"], ["--seed", str(2**70)], ["--set", "n_bootstrap=0"]]
    out = tmp / "out"
    rows = {"diagnose: bad options and records": collections.Counter(), "diagnose: valid options (reach the run)":
            collections.Counter()}
    notes = []
    real_run = execute.run
    execute.run = _stand_in_run
    try:
        for option, values in bad.items():
            for value in values:
                if option == "data":
                    argv = ["diagnose", value, "--model", "paper-reference", "--no-progress", "--out", str(out)]
                elif option == "--out":
                    argv = [*base, "--out", value]
                elif option.startswith("--out ("):
                    argv = ["diagnose", str(zrec), "--model", "paper-reference", "--no-progress", "--out", value]
                else:
                    argv = [*base, "--out", str(out), option, value]
                where = Path(value) if option.startswith("--out") else out
                if option.startswith("--out") and not where.is_absolute():
                    where = tmp / value
                end = _diagnose(main, argv, where, tmp, expect="refused", named=option.split()[0], value=value)
                rows["diagnose: bad options and records"][end] += 1
                if end != "refused":
                    notes.append(f"{option} {value}: {end}")
        for k, extra in enumerate(valid):
            end = _diagnose(main, [*base, "--out", str(tmp / f"valid{k}"), *extra], tmp / f"valid{k}", tmp,
                            expect="handled")
            rows["diagnose: valid options (reach the run)"][end] += 1
            if end != "handled":
                notes.append(f"valid {extra}: {end}")
    finally:
        execute.run = real_run
    return rows | ({"_notes": notes} if notes else {})


def _diagnose(main, argv, where: Path, tmp: Path, expect: str, named: str = "", value: str = "") -> str:
    """How ``tubeid <argv>`` ends (see the module docstring); ``where``: the --out it must leave as it was."""
    before = _tree(where)
    err = io.StringIO()
    import os

    cwd = os.getcwd()
    try:
        os.chdir(tmp)
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                status = main(argv)
            except SystemExit as exc:  # argparse
                status = exc.code
    except _Ran:
        return "handled" if expect == "handled" else "wrong"
    except Exception:  # noqa: BLE001 - counted
        return "traceback"
    finally:
        os.chdir(cwd)
    text = err.getvalue()
    if "Traceback" in text:
        return "traceback"
    if status == 0:
        return "wrong"
    if status != 2:
        return "traceback"
    if _tree(where) != before:
        return "wrong"  # a refusal that wrote or removed something in --out
    lines = [ln for ln in text.splitlines() if ln.strip()]
    last = lines[-1] if lines else ""
    argparse_error = last.startswith("tubeid diagnose: error: argument")
    ours = last.startswith("tubeid: error: ") and len(lines) == 1
    key = named.lstrip("-").replace("-", "_")
    # the option, the setting it sets (settings.<name>) or, for a path (--model FILE, the record), the value
    names = named in last or key in last or (named == "--set" and "settings." in last) or (named in ("--model", "data") and value in last)
    if (argparse_error or ours) and names:
        return "refused" if expect == "refused" else "wrong"
    return "unclear"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    warnings.filterwarnings("ignore", message=".*does not have a Zarr V3 specification")  # the records' string coordinates
    rows = {}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        for part in (records, diagnose_options):
            sub = tmp / part.__name__
            sub.mkdir()
            rows.update(part(sub))
    notes = rows.pop("_notes", [])
    if args.json:
        print(json.dumps({k: dict(v) for k, v in rows.items()} | {"notes": notes}, indent=1))
        return
    print("refused: one line naming the file or option, the value and the rule (nothing written); handled: a "
          "legitimate record read exactly, valid options reaching the run; unclear: refused, not in one line or "
          "not naming it; wrong: a bad input accepted, a wrong value, --out changed by a refusal; traceback: "
          "another exception")
    print(f"| inputs | cases | {' | '.join(COLS)} |")
    print("|---|---|" + "---|" * len(COLS))
    for label, c in rows.items():
        print(f"| {label} | {sum(c.values())} | " + " | ".join(str(c.get(k, 0)) for k in COLS) + " |")
    for note in notes:
        print("not refused cleanly:", note)


if __name__ == "__main__":
    sys.exit(main())
