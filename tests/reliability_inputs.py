"""Hostile and careless inputs to tubeid's readers, specification loader and TLS kit, counted.

Run: ``python tests/reliability_inputs.py [--json]`` (about a minute). Prints, per class of input,
how many cases were tried, refused with a SpecificationError (or, for the TLS kit, a refusal
message), accepted whole (the exact data or a valid specification), read with wrong or lost data,
or ended in another exception (a traceback). The README's reliability table is this output; the
tests named in it keep each class from coming back. Not collected by pytest (no ``test_`` prefix).

A cut file is compared with the record it was cut from: "exact prefix" (a CSV cut exactly at a
line break: the first rows, bit-exact) and "fewer channels" (a UFF file without channel counts or
sidecar cut exactly between datasets) are counted apart: no format can reveal them.
"""

from __future__ import annotations

import argparse
import collections
import copy
import json
import math
import shutil
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import xarray as xr

from tubeid.errors import SpecificationError
from tubeid.measured.readers import read_measurements, sidecar_path, write_measurements
from tubeid.measured.validation import validate_measurements
from tubeid.mechanics import builtin_spec, reduce
from tubeid.mechanics.spec import load_spec, spec_from_dict, spec_to_dict
from tubeid.seeds import rng_for

import tubeid

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_measured import _ascii_uff, _claiming  # noqa: E402 - the tests' own hostile files
from test_mechanics import HOSTILE, _paths  # noqa: E402

REPO = Path(tubeid.__file__).resolve().parents[1]  # the tree under test (its cluster/tls kit too)
SKIP_HUGE = False  # --no-huge: leave out the 150 M-sample header and the alias bomb (for unprotected code)


def _record(n=12, m=3, scale=1e-6, key="survey", validate=True):
    v = scale * rng_for(1, key).standard_normal((n, m))
    ds = xr.Dataset({"displacement": (("time", "sensor"), v, {"units": "m"})},
                    coords={"time": ("time", 0.25 + np.arange(n) / 1024, {"units": "s"}),
                            "sensor": [f"S{j + 1}" for j in range(m)], "x": ("sensor", np.linspace(1.0, 3.0, m)),
                            "tube": ("sensor", ["centre"] * m)})
    return validate_measurements(ds) if validate else ds


def _outcome(call, expected: xr.Dataset | None = None) -> str:
    """refused / accepted / wrong / traceback (an exact prefix or fewer exact channels counted apart)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            back = call()
    except SpecificationError:
        return "refused"
    except Exception:  # noqa: BLE001 - counted
        return "traceback"
    if expected is None:
        return "accepted"
    a, b = expected.displacement.values, back.displacement.values
    names = list(expected.sensor.values)
    if b.shape == a.shape and np.array_equal(a, b):
        return "accepted"
    if b.shape[1] == a.shape[1] and b.shape[0] < a.shape[0] and np.array_equal(a[: b.shape[0]], b):
        return "exact prefix"
    if b.shape[0] == a.shape[0] and all(s in names and np.array_equal(a[:, names.index(s)], b[:, j])
                                        for j, s in enumerate(back.sensor.values)):
        return "fewer channels"
    return "wrong"


def _sweep(orig, full: Path, folder: Path, step=1):
    folder.mkdir()
    cut = folder / full.name
    if sidecar_path(full).exists():
        shutil.copy(sidecar_path(full), sidecar_path(cut))
    data, out = full.read_bytes(), collections.Counter()
    for k in range(0, len(data), step):
        cut.write_bytes(data[:k])
        out[_outcome(lambda: read_measurements(cut), orig)] += 1
    return out


def truncations(tmp: Path) -> dict:
    orig = _record()
    rows = {}
    rows["CSV cut at every byte"] = _sweep(orig, write_measurements(orig, tmp / "rcsv.csv"), tmp / "c1")
    rows["UFF 58b (tubeid) cut at every byte"] = _sweep(orig, write_measurements(orig, tmp / "ruff.uff"), tmp / "c2")
    lab = _ascii_uff(tmp / "lab.uff", orig, positions=False)
    sidecar_path(lab).write_text("sensor,tube,x\n" + "".join(f"{s},centre,{float(x)!r}\n" for s, x in
                                                          zip(orig.sensor.values, orig.x.values)))
    lab_orig = read_measurements(lab)
    rows["UFF 58 ASCII + sidecar cut at every byte"] = _sweep(lab_orig, lab, tmp / "c3")
    alone = _ascii_uff(tmp / "alone.uff", orig, positions=True)
    rows["UFF 58 ASCII, positions in ID line 4, cut at every byte"] = _sweep(read_measurements(alone), alone, tmp / "c4")
    rows["NetCDF-4 cut at every 7th byte"] = _sweep(orig, write_measurements(orig, tmp / "rnc.nc"), tmp / "c5", step=7)
    rows["NetCDF-3 cut at every byte"] = _sweep(orig, write_measurements(orig, tmp / "rnc3.nc", format="netcdf3"),
                                                tmp / "c6")
    # Zarr: each chunk or metadata file deleted, emptied or overwritten with garbage
    big = _record(n=64)
    z = tmp / "r.zarr"
    from tubeid.measured.readers import _strings_as_objects

    _strings_as_objects(big.chunk({"time": 16})).to_zarr(z, consolidated=False)
    out = collections.Counter()
    for f in sorted(p for p in z.rglob("*") if p.is_file()):
        good = f.read_bytes()
        for damage in (None, b"", b"\x00garbage" * 8):
            if damage is None:
                f.unlink()
            else:
                f.write_bytes(damage)
            out[_outcome(lambda: read_measurements(z), big)] += 1
            f.write_bytes(good)
    rows["Zarr: each file deleted, emptied, garbage"] = out
    return rows


def values(tmp: Path) -> dict:
    """One record per hostile value; 'accepted' is right only where the value is legitimate."""
    cases = {}
    rec = _record(n=256, key="values")

    def variant(name, mutate, fmt="nc"):
        ds = rec.copy(deep=True)
        ds = mutate(ds) or ds
        path = tmp / f"{name}.{fmt}"
        if fmt == "nc":  # as another tool would write it (integers included)
            ds.to_netcdf(path, engine="h5netcdf")
            return name, path
        return name, write_measurements(ds, path, validate=False)

    for value in (math.nan, math.inf, -math.inf, 2.0, 1e294, -5.0):
        for fmt in ("nc", "csv"):
            def put(ds, value=value):
                ds["displacement"][100, 1] = value
            name, path = variant(f"sample{value}_{fmt}".replace(".", "p"), put, fmt)
            cases.setdefault("NaN, ±inf, amplitudes 2 m to 1e294 m (NetCDF, CSV)", []).append(path)
    for unit, size in (("mm", 1e-3), ("um", 1e-6)):  # metres (up to ~6 m) written in mm or um
        def units(ds, unit=unit, size=size):
            ds["displacement"] = ds.displacement * 2e6 / size
            ds.displacement.attrs["units"] = unit
        cases.setdefault("amplitudes of metres written in mm / um", []).append(variant(f"units{unit}", units)[1])
    counts = np.round(rec.displacement.values * 3e9).astype(np.int16)

    def int16(ds, fill=False):
        ds["displacement"] = (("time", "sensor"), counts, {"units": "um"})
        if fill:
            ds.displacement.encoding["_FillValue"] = -32768
    cases["int16 counts without scale (NetCDF, plain and with _FillValue)"] = [
        variant("int16", int16)[1], variant("int16fill", lambda ds: int16(ds, True))[1]]
    p = tmp / "counts.csv"
    p.write_text("time,S1,S2\n" + "".join(f"{i / 1024!r},{a},{b}\n" for i, (a, b) in enumerate(counts[:, :2])))
    sidecar_path(p).write_text("sensor,tube,x,units\nS1,centre,1.0,um\nS2,centre,2.0,um\n")
    cases["integer counts in CSV without scale"] = [p]
    wide = _record(n=32, m=1000, key="wide", validate=False)
    cases["1000 sensors (NetCDF, CSV)"] = [write_measurements(wide, tmp / "wide.nc", validate=False),
                                            write_measurements(wide, tmp / "wide.csv", validate=False)]
    if not SKIP_HUGE:
        cases["header claiming 150 M × 2 samples (NetCDF-4, a few kB)"] = [_claiming(tmp / "claim.nc", 150_000_000, "h5netcdf")]
    out = {}
    for label, paths in cases.items():  # every case here is bad input: accepting it is a wrong value
        out[label] = collections.Counter(_invalid(_outcome(lambda p=p: read_measurements(p))) for p in paths)
    return out


def _invalid(outcome: str) -> str:
    return "wrong" if outcome == "accepted" else outcome


#: Specification fields where None is a documented value (the ground, all modes, the stops' tube).
OPTIONAL = {"to_tube", "to_x", "nonlinear_tube", "b_modes", "b_cutoff_hz", "a_modes", "a_cutoff_hz"}


def _fits(base, path, value) -> bool:
    """Whether accepting ``value`` where ``base`` holds its original is right: a number where a number
    was (never text or a bool converted), text where text was."""
    original = base
    for key in path:
        original = original[key]
    number = lambda v: isinstance(v, (int, float)) and not isinstance(v, bool)  # noqa: E731
    if value is None and path and path[-1] in OPTIONAL:
        return True
    if number(original):
        return number(value)
    if isinstance(original, str):
        return isinstance(value, str)
    return True


def specifications(tmp: Path) -> dict:
    base = spec_to_dict(builtin_spec("paper-simplified"))
    base["effects"] = [{"kind": "tone", "frequency_hz": 23.0, "amplitude": 10.0, "tube": "centre", "x": 8.0},
                       {"kind": "sensor_noise", "level": 1e-16}]
    fuzz = collections.Counter()
    for path in _paths(base):
        for value in HOSTILE:
            d = copy.deepcopy(base)
            if path:
                t = d
                for k in path[:-1]:
                    t = t[k]
                t[path[-1]] = value
            else:
                d = value
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("error", RuntimeWarning)
                    red = reduce(spec_from_dict(d))
                mats = [*red.A_part, red.subsystem.M, red.subsystem.D, red.subsystem.K]
                fuzz["accepted" if all(np.all(np.isfinite(m)) for m in mats) and _fits(base, path, value)
                     else "wrong"] += 1
            except SpecificationError:
                fuzz["refused"] += 1
            except Exception:  # noqa: BLE001
                fuzz["traceback"] += 1
    import yaml

    good = yaml.safe_dump(spec_to_dict(builtin_spec("paper-simplified")), sort_keys=False)
    bomb = ['a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    bomb += [f"{c}: &{c} [" + ",".join([f"*{p}"] * 9) + "]" for p, c in zip("abcdefgh", "bcdefghi")] + ["name: *i"]
    files = {
        "alias bomb in name.yaml": "\n".join(bomb),
        "merge key alias.yaml": "d: &d {density: 250.0}\n" + good.replace("- name: centre", "- <<: *d\n  name: centre", 1),
        "key twice.yaml": good.replace("  density: 250.0\n", "  density: 250.0\n  density: 2500.0\n", 1),
        "deep.yaml": "name: " + "[" * 100_000 + "]" * 100_000,
        "deep.toml": "name = " + "[" * 100_000 + "]" * 100_000,
        "bigint.yaml": "name: x\nband_hz: " + "9" * 5000,
        "bigint.toml": "name = 'x'\nband_hz = " + "9" * 5000,
        "tag.yaml": "name: !!python/object/apply:os.system ['true']",
        "date.yaml": "name: 2001-12-14\ntubes: []",
        "empty.yaml": "",
        "huge.yaml": "name: x\n#" + "a" * (2 << 20),
        "quoted number.yaml": good.replace("youngs_modulus: 750000000.0", 'youngs_modulus: "7.5e8"', 1),
        "n_elements 1e6.yaml": good.replace("n_elements: 8", "n_elements: 1000000", 1),
        "text in links x.yaml": good.replace("links:\n- tube: equivalent\n  x: 4.0", "links:\n- tube: equivalent\n  x: '4.0'", 1),
    }
    assert all(v != good for v in files.values())
    if SKIP_HUGE:
        del files["alias bomb in name.yaml"]
    outcome = collections.Counter()
    times = {}
    for name, text in files.items():
        p = tmp / name
        p.write_text(text)
        t0 = time.perf_counter()
        outcome[_invalid(_outcome(lambda: load_spec(p)))] += 1
        times[name] = time.perf_counter() - t0
    p = tmp / "exponent.yaml"
    p.write_text(good.replace("youngs_modulus: 750000000.0", "youngs_modulus: 7.5e8", 1))
    exp = _outcome(lambda: load_spec(p))
    return {"fields × hostile values (111 places × 20 values)": fuzz, "hostile or careless specification files": outcome,
            "YAML 7.5e8 (must be accepted)": collections.Counter({exp: 1}),
            "_seconds": {k: round(v, 4) for k, v in times.items()}}


def tls(tmp: Path) -> dict:
    if shutil.which("openssl") is None:
        return {}
    script = REPO / "cluster" / "tls" / "make-certs.sh"
    out = collections.Counter()

    def run(*args):
        return subprocess.run(["bash", str(script), *map(str, args)], capture_output=True, text=True)

    def exposed(folder: Path) -> bool:
        return any("PRIVATE KEY" in p.read_text(errors="replace") and p.name.startswith("ca")
                   for p in folder.rglob("*") if p.is_file())

    layouts = [("default", (tmp / "t1",)), ("CA_DIR inside OUTPUT_DIR", (tmp / "t2", "DNS:x", tmp / "t2" / "ca")),
               ("CA_DIR = OUTPUT_DIR", (tmp / "t3", "DNS:x", tmp / "t3")), ("bad SAN", (tmp / "t4", "nonsense")),
               ("rerun with the same CA", (tmp / "t5", "DNS:x", tmp / "t1.ca"))]
    (tmp / "t6").mkdir()
    (tmp / "t6" / "ca-key.pem").write_text("legacy")
    layouts.append(("legacy ca-key.pem in OUTPUT_DIR", (tmp / "t6", "DNS:x", tmp / "t6ca")))
    (tmp / "t7" / "keys").mkdir(parents=True)
    (tmp / "t7ca").symlink_to(tmp / "t7" / "keys", target_is_directory=True)  # looks outside, leads inside
    layouts.append(("CA_DIR a symlink into OUTPUT_DIR", (tmp / "t7", "DNS:x", tmp / "t7ca")))
    for _name, args in layouts:
        r = run(*args)
        folder = Path(args[0])
        if folder.name == "t6":
            out["refused" if r.returncode == 2 else "wrong"] += 1
        elif exposed(folder):
            out["wrong"] += 1
        else:
            out["refused" if r.returncode else "accepted"] += 1
    # a user's files where the kit writes: each must be refused and left byte-identical
    kept = collections.Counter()
    (tmp / "u1").mkdir()
    users = {tmp / "u1" / "mine.csr": "x\n", tmp / "u1" / "notes.ext": "y\n", tmp / "u1" / "client.pem": "z\n"}
    (tmp / "u3ca").mkdir()
    users[tmp / "u3ca" / "ca.pem"] = "a CA certificate without its key\n"
    for f, text in users.items():
        f.write_text(text)
    t1_files = {f: f.read_bytes() for f in (tmp / "t1").rglob("*") if f.is_file()}
    cases = [((tmp / "u1",), [f for f in users if f.parent.name == "u1"]),  # OUTPUT_DIR holding a user's files
             ((tmp / "t1",), list(t1_files)),  # a second run into the same OUTPUT_DIR
             ((tmp / "u3", "DNS:x", tmp / "u3ca"), [tmp / "u3ca" / "ca.pem"])]  # CA_DIR with ca.pem, no key
    for args, files in cases:
        before = {f: f.read_bytes() for f in files}
        r = run(*args)
        same = all(f.exists() and f.read_bytes() == b for f, b in before.items())
        kept["refused" if r.returncode == 2 and same else "wrong" if not same else "accepted"] += 1
    r = run(tmp / "u4", "nonsense")  # a failed run (bad SAN) leaves none of its keys
    left = [p for p in (tmp / "u4").rglob("*") if p.is_file()] if (tmp / "u4").exists() else []
    kept["refused" if r.returncode and not left else "wrong"] += 1
    return {"make-certs.sh layouts": out, "make-certs.sh over a user's files": kept}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--no-huge", action="store_true",
                    help="leave out the cases that take GBs or hang on code without limits")
    args = ap.parse_args()
    global SKIP_HUGE
    SKIP_HUGE = args.no_huge
    rows = {}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        for part in (truncations, values, specifications, tls):
            sub = tmp / part.__name__
            sub.mkdir()
            rows.update(part(sub))
    seconds = rows.pop("_seconds", {})
    if args.json:
        print(json.dumps({k: dict(v) for k, v in rows.items()} | {"seconds": seconds}, indent=1))
        return
    cols = ["refused", "accepted", "exact prefix", "fewer channels", "wrong", "traceback"]
    print("refused: a clear refusal; accepted: read whole and right (a valid value, the exact record); exact "
          "prefix / fewer channels: a cut no format reveals, values exact; wrong: a wrong value, lost data or "
          "an exposed CA key; traceback: another exception")
    print(f"| inputs | cases | {' | '.join(cols)} |")
    print("|---|---|" + "---|" * len(cols))
    for label, c in rows.items():
        print(f"| {label} | {sum(c.values())} | " + " | ".join(str(c.get(k, 0)) for k in cols) + " |")
    print("slowest specification refusal: %s (%.3f s)" % max(seconds.items(), key=lambda kv: kv[1]))


if __name__ == "__main__":
    sys.exit(main())
