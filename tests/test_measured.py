"""Measured-data readers and validation (tubeid.measured.readers / .validation).

All files are made in tmp_path from synthetic Gaussian data with fixed seeds. Round trips must be
exact (assert_identical compares floats exactly): NetCDF, Zarr and UFF 58b store float64, CSV is
written with 17 significant digits. Files written by other tools in ASCII UFF are checked with the
tolerances of that format (stated where used).
"""

from __future__ import annotations

import inspect
import pickle
from pathlib import Path

import numpy as np
import pytest
import pyuff
import xarray as xr
from scipy.signal import lfilter

from tubeid.errors import SpecificationError
from tubeid.measured import readers, validation
from tubeid.measured.readers import read_measurements, sidecar_path, write_measurements
from tubeid.measured.validation import validate_measurements
from tubeid.seeds import rng_for

SEED = 20080901
FS = 1024.0  # Hz
N = 1000


def raw_dataset(values, *, names=("S1", "S2", "S3"), x=(0.10, 0.55, 0.30), tube=("centre", "centre", "north"),
                t0=0.25, dt=1 / FS, units="m", time=None) -> xr.Dataset:
    values = np.asarray(values, dtype=float)
    t = t0 + np.arange(values.shape[0]) * dt if time is None else np.asarray(time, dtype=float)
    return xr.Dataset(
        {"displacement": (("time", "sensor"), values, {"units": units})},
        coords={"time": ("time", t, {"units": "s"}), "sensor": ("sensor", list(names)),
                "x": ("sensor", list(x), {"units": "m"}), "tube": ("sensor", list(tube))})


def gaussian(n=N, m=3, key="record", scale=1e-4) -> np.ndarray:
    return scale * rng_for(SEED, key).standard_normal((n, m))


@pytest.fixture
def record() -> xr.Dataset:
    return validate_measurements(raw_dataset(gaussian()))


def write_csv(path: Path, header, rows, sidecar_rows=None, sidecar_header=("sensor", "tube", "x")) -> Path:
    lines = [",".join(header)] + [",".join(repr(float(v)) if not isinstance(v, str) else v for v in r) for r in rows]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    if sidecar_rows is not None:
        side = [",".join(sidecar_header)] + [",".join(str(c) for c in r) for r in sidecar_rows]
        sidecar_path(path).write_text("\n".join(side) + "\n", encoding="utf-8")
    return path


def good_csv(path: Path, values=None, t=None, names=("S1", "S2"), units=None) -> Path:
    values = gaussian(50, len(names), key="csv") if values is None else values
    t = np.arange(values.shape[0]) / FS if t is None else t
    header = ["time", *names]
    if units is None:
        side = [(s, "centre", 0.1 * (j + 1)) for j, s in enumerate(names)]
        return write_csv(path, header, np.column_stack([t, values]), side)
    side = [(s, "centre", 0.1 * (j + 1), u) for j, (s, u) in enumerate(zip(names, units))]
    return write_csv(path, header, np.column_stack([t, values]), side, ("sensor", "tube", "x", "units"))


def refused(call, *words):
    """Run ``call``; it must raise SpecificationError whose message contains every word."""
    with pytest.raises(SpecificationError) as info:
        call()
    msg = str(info.value)
    for w in words:
        assert w in msg, f"{w!r} not in message: {msg}"
    return msg


# --------------------------------------------------------------------------- round trips
@pytest.mark.parametrize(
    "filename, fmt, label",
    [("rec.nc", None, "netcdf4"), ("rec3.nc", "netcdf3", "netcdf3"), ("rec.zarr", None, "zarr"),
     ("rec.csv", None, "csv"), ("rec.uff", None, "uff58")])
def test_round_trip_is_exact(tmp_path, record, filename, fmt, label):
    path = write_measurements(record, tmp_path / filename, format=fmt)
    back = read_measurements(path)
    # Exact: float64 storage everywhere (UFF written as binary 58b doubles with explicit abscissa,
    # CSV with %.17g), so data, time, x and names must be bit-identical.
    xr.testing.assert_identical(back.displacement, record.displacement)
    assert back.attrs == {"source": str(path), "format": label, "dt": record.attrs["dt"]}
    assert back.sensor.dtype.kind == "U" and back.tube.dtype.kind == "U"
    assert back.displacement.attrs["units"] == "m" and back.time.attrs["units"] == "s"
    assert back.x.attrs["units"] == "m"


def test_canonical_form(record):
    assert record.displacement.dims == ("time", "sensor")
    assert record.displacement.dtype == np.float64
    assert list(record.sensor.values) == ["S1", "S2", "S3"]
    assert list(record.tube.values) == ["centre", "centre", "north"]
    np.testing.assert_array_equal(record.x.values, [0.10, 0.55, 0.30])
    assert record.attrs["dt"] == 1 / FS  # (t[-1]-t[0])/(n-1) with t = 0.25 + i/1024, exact in binary
    assert record.attrs["source"] == "<memory>" and record.attrs["format"] == "memory"
    # (sensor, time) order is accepted and transposed; the input is not modified.
    raw = raw_dataset(gaussian())
    swapped = raw.transpose("sensor", "time")
    xr.testing.assert_identical(validate_measurements(swapped), record)
    assert swapped.displacement.dims == ("sensor", "time")


def test_netcdf_signature_picks_engine_not_extension(tmp_path, record):
    path = write_measurements(record, tmp_path / "classic.cdf", format="netcdf3")
    assert path.read_bytes()[:3] == b"CDF"
    assert read_measurements(path).attrs["format"] == "netcdf3"


def test_lab_ascii_uff_with_sidecar_positions_and_mm(tmp_path):
    """A typical lab file: ASCII 58, even abscissa, no positions in ID line 4, units mm, node names."""
    values_m = gaussian(512, 2, key="lab")
    dt = 1 / 2048  # 4.8828125e-4 s, stored by the format with 6 significant digits
    path = tmp_path / "lab.uff"
    sets = []
    for j, id1 in enumerate(["", "upstream"]):
        sets.append(pyuff.prepare_58(
            binary=0, id1=id1, id2="", id3="", id4="", id5="", func_type=1, rsp_node=7 + j, rsp_dir=2,
            ref_node=0, ref_dir=0, abscissa_spacing=1, abscissa_spec_data_type=17, abscissa_axis_units_lab="s",
            ordinate_spec_data_type=8, ordinate_len_unit_exp=1, ordinate_axis_units_lab="mm",
            orddenom_spec_data_type=0, data=values_m[:, j] * 1e3, x=np.arange(512) * dt))
    path.write_bytes(b"")
    pyuff.UFF(str(path)).write_sets(sets, mode="add")
    sidecar_path(path).write_text("sensor,tube,x\nnode7dir2,centre,0.2\nupstream,west,0.75\n")
    ds = read_measurements(path, tubes={"centre": 1.0, "west": 1.0})
    assert list(ds.sensor.values) == ["node7dir2", "upstream"]  # blank ID line 1 -> node/direction
    assert list(ds.tube.values) == ["centre", "west"]
    np.testing.assert_array_equal(ds.x.values, [0.2, 0.75])
    # ASCII 58 double data are written %20.11e: 12 significant digits -> relative error <= 5e-12;
    # mm -> m adds a few ulp. Tolerance 1e-11 relative to each sample.
    np.testing.assert_allclose(ds.displacement.values, values_m, rtol=1e-11, atol=0)
    # The abscissa increment is written %13.5e: dt known to 6 significant digits (<= 5e-6 relative).
    assert abs(ds.attrs["dt"] - dt) / dt <= 5e-6
    assert ds.attrs["format"] == "uff58"


# --------------------------------------------------------------------------- units
@pytest.mark.parametrize("unit, metres", [("m", 1.0), ("mm", 1e-3), ("um", 1e-6), ("\u00b5m", 1e-6),
                                          ("\u03bcm", 1e-6), ("micron", 1e-6), ("nm", 1e-9)])
def test_units_to_metres_in_memory(unit, metres):
    values = np.full((4, 3), 2.5e-4)  # within the plausibility bound of 1 m in every unit
    values[1] = -1e-4  # not constant (a constant channel is refused as dead)
    values[2] = 0.5e-4
    ds = validate_measurements(raw_dataset(values, units=unit))
    assert ds.displacement.attrs["units"] == "m"
    # One multiplication by the table factor: within 1 ulp of the closed form 2.5e-4 * metres.
    np.testing.assert_allclose(ds.displacement.values[0], 2.5e-4 * metres, rtol=2.3e-16, atol=0)


def test_csv_in_mm_converted_to_m(tmp_path, record):
    mm = record.displacement.values * 1e3
    path = good_csv(tmp_path / "mm.csv", values=mm, t=record.time.values, names=("S1", "S2", "S3"),
                    units=("mm", "mm", "mm"))
    ds = read_measurements(path)
    # (v * 1e3 as text %r) * 1e-3: two roundings plus the inexact 1e-3 -> <= ~4e-16 relative.
    np.testing.assert_allclose(ds.displacement.values, record.displacement.values, rtol=1e-15, atol=0)
    assert not np.array_equal(mm * 1e-3, mm)  # the conversion did something


@pytest.mark.parametrize("filename", ["mm.nc", "mm.zarr", "mm.uff", "mm.csv"])
def test_files_in_mm_read_as_m(tmp_path, record, filename):
    in_mm = record.copy()
    in_mm["displacement"] = record.displacement * 1e3
    in_mm.displacement.attrs["units"] = "mm"
    path = write_measurements(in_mm, tmp_path / filename, validate=False)
    ds = read_measurements(path)
    assert ds.displacement.attrs["units"] == "m"
    np.testing.assert_allclose(ds.displacement.values, record.displacement.values, rtol=1e-15, atol=0)


def test_x_units_converted(record):
    raw = record.copy()
    raw["x"] = raw.x * 1e3
    raw.x.attrs["units"] = "mm"
    np.testing.assert_allclose(validate_measurements(raw).x.values, record.x.values, rtol=1e-15)


# --------------------------------------------------------------------------- refusals
def test_refuses_unknown_units_csv(tmp_path):
    path = good_csv(tmp_path / "u.csv", units=("m", "furlong"))
    refused(lambda: read_measurements(path), "u.csv", "'S2'", "furlong", "unknown unit")


def test_refuses_unknown_and_missing_units_uff_and_netcdf(tmp_path, record):
    bad = record.copy()
    bad.displacement.attrs["units"] = "inch"
    path = write_measurements(bad, tmp_path / "inch.uff", validate=False)
    refused(lambda: read_measurements(path), "inch.uff", "'S1'", "inch", "unknown unit")
    bad.displacement.attrs.pop("units")
    path = write_measurements(bad, tmp_path / "none.uff", validate=False)
    refused(lambda: read_measurements(path), "none.uff", "'S1'", "units missing")
    path = write_measurements(bad, tmp_path / "none.nc", validate=False)
    refused(lambda: read_measurements(path), "none.nc", "'S1'", "units missing")


def test_refuses_time_units_other_than_seconds(tmp_path, record):
    bad = record.copy()
    bad.time.attrs["units"] = "ms"
    path = write_measurements(bad, tmp_path / "ms.nc", validate=False)
    refused(lambda: read_measurements(path), "ms.nc", "seconds")
    bad.time.attrs["units"] = "seconds since 2024-01-01"  # accepted: offsets in seconds
    assert validate_measurements(bad).attrs["dt"] == record.attrs["dt"]


def test_refuses_non_increasing_time(tmp_path):
    t = np.arange(50) / FS
    t[[20, 21]] = t[[21, 20]]
    path = good_csv(tmp_path / "order.csv", t=t)
    msg = refused(lambda: read_measurements(path), "order.csv", "time[21]", "strictly increasing",
                  f"(time[20] = {21 / FS!r} s)")  # a plain number, not np.float64(...)
    assert "np." not in msg, msg
    t = np.arange(50) / FS
    t[30] = t[29]
    path = good_csv(tmp_path / "repeat.csv", t=t)
    refused(lambda: read_measurements(path), "repeat.csv", "strictly increasing")


def test_refuses_non_uniform_time(tmp_path):
    t = np.arange(50) / FS
    t[10] += 0.01 / FS  # 1 % of a step; the tolerance is 1e-6
    path = good_csv(tmp_path / "jitter.csv", t=t)
    refused(lambda: read_measurements(path), "jitter.csv", "uniform")
    t = np.arange(50) / FS
    t[10] += 1e-9 / FS  # float-level noise: accepted
    assert read_measurements(good_csv(tmp_path / "ok.csv", t=t)).sizes["time"] == 50


@pytest.mark.parametrize("bad_value, word", [("nan", "nan"), ("inf", "inf"), ("-inf", "-inf")])
def test_refuses_non_finite_samples_csv(tmp_path, bad_value, word):
    values = gaussian(50, 2, key="csv").astype(object)
    values[17, 1] = bad_value
    path = good_csv(tmp_path / "nan.csv", values=values)
    msg = refused(lambda: read_measurements(path), "nan.csv", "'S2'", "displacement[17]", "finite",
                  f"first at t = {17 / FS!r} s")  # a plain number, not np.float64(...)
    assert word in msg and "np." not in msg, msg


def test_refuses_nan_in_netcdf_and_nan_never_written_to_uff(tmp_path, record):
    bad = record.copy(deep=True)
    bad.displacement[5, 2] = np.nan
    path = write_measurements(bad, tmp_path / "nan.nc", validate=False)
    refused(lambda: read_measurements(path), "nan.nc", "'S3'", "finite")
    # pyuff would silently write NaN as 0: the UFF writer refuses instead.
    refused(lambda: write_measurements(bad, tmp_path / "nan.uff", validate=False), "nan.uff", "NaN")
    refused(lambda: write_measurements(bad, tmp_path / "nan2.uff"), "'S3'", "finite")


def test_refuses_sensor_off_the_tube_or_unknown_tube(tmp_path, record):
    path = write_measurements(record, tmp_path / "pos.uff")
    tubes = {"centre": 1.0, "north": 1.0}
    assert read_measurements(path, tubes=tubes).sizes["sensor"] == 3
    refused(lambda: read_measurements(path, tubes={"centre": 0.5, "north": 1.0}),
            "pos.uff", "'S2'", "off the tube", "0.55")
    refused(lambda: read_measurements(path, tubes={"centre": 1.0}), "pos.uff", "'S3'", "unknown tube", "north")
    neg = record.copy()
    neg["x"] = ("sensor", [0.1, -0.01, 0.3], {"units": "m"})
    path = write_measurements(neg, tmp_path / "neg.csv", validate=False)
    refused(lambda: read_measurements(path, tubes=tubes), "neg.csv", "'S2'", "off the tube")
    # Ends of the tube are on it.
    ends = record.copy()
    ends["x"] = ("sensor", [0.0, 1.0, 1.0], {"units": "m"})
    validate_measurements(ends, tubes=tubes)


def test_refuses_missing_positions(tmp_path, record):
    # CSV: sensor absent from the sidecar, or with an empty x.
    path = write_csv(tmp_path / "nopos.csv", ["time", "S1", "S2"],
                     np.column_stack([np.arange(20) / FS, gaussian(20, 2)]), [("S1", "centre", 0.2)])
    refused(lambda: read_measurements(path), "nopos.csv", "'S2'", "missing its position")
    path = write_csv(tmp_path / "emptyx.csv", ["time", "S1", "S2"],
                     np.column_stack([np.arange(20) / FS, gaussian(20, 2)]), [("S1", "centre", 0.2), ("S2", "centre", "")])
    refused(lambda: read_measurements(path), "emptyx.csv", "'S2'", "missing its position")
    # UFF without ID-line-4 position and without sidecar.
    nox = record.drop_vars("x")
    path = write_measurements(nox, tmp_path / "bare.uff", validate=False)
    refused(lambda: read_measurements(path), "bare.uff", "'S1'", "missing its position", "ID line 4")
    # ... a sidecar then supplies the positions.
    sidecar_path(path).write_text("sensor,tube,x\nS1,centre,0.1\nS2,centre,0.55\nS3,north,0.3\n")
    xr.testing.assert_identical(read_measurements(path).displacement, record.displacement)
    # ... and a sidecar that disagrees with ID line 4 is refused.
    path = write_measurements(record, tmp_path / "both.uff")
    sidecar_path(path).write_text("sensor,tube,x\nS1,centre,0.2\n")
    refused(lambda: read_measurements(path), "both.uff", "'S1'", "conflicts")
    # NetCDF without x, and in memory with an empty tube name.
    path = write_measurements(nox, tmp_path / "nopos.nc", validate=False)
    refused(lambda: read_measurements(path), "nopos.nc", "'S1'", "missing its position")
    notube = record.copy()
    notube["tube"] = ("sensor", ["centre", "", "north"])
    refused(lambda: validate_measurements(notube), "<memory>", "'S2'", "missing its position")


def test_refuses_too_short_for_resolution(tmp_path, record):
    path = write_measurements(record, tmp_path / "short.nc")
    duration = N / FS  # 0.9765625 s
    ds = read_measurements(path, min_resolution_hz=1 / duration)  # exactly one segment: accepted
    assert ds.sizes["time"] == N
    refused(lambda: read_measurements(path, min_resolution_hz=1.0), "short.nc", "too short", "1.0 Hz", "one segment")
    refused(lambda: read_measurements(path, min_resolution_hz=-1.0), "min_resolution_hz", "> 0")


def narrowband(n, key, f0=20.0, r=0.995) -> np.ndarray:
    """Oversampled resonant Gaussian process (like a tube response): white noise through a 2-pole resonator."""
    w = rng_for(SEED, key).standard_normal(n + 2000)
    y = lfilter([1.0], [1.0, -2 * r * np.cos(2 * np.pi * f0 / FS), r * r], w)[2000:]
    return y / y.std()


def test_refuses_clipped_channel(tmp_path):
    good = np.column_stack([narrowband(8192, "a"), narrowband(8192, "b")])
    clipped = good.copy()
    clipped[:, 1] = np.clip(clipped[:, 1], -10, 2.0)  # saturates the top only, ~2.3 % of samples
    t = np.arange(8192) / FS
    um = ("um", "um")  # unit-variance records in µm: plausible tube vibrations
    assert read_measurements(good_csv(tmp_path / "fine.csv", values=good, t=t, units=um)).sizes["sensor"] == 2
    path = good_csv(tmp_path / "clip.csv", values=clipped, t=t, units=um)
    refused(lambda: read_measurements(path), "clip.csv", "'S2'", "clipped", "maximum")
    dead = good.copy()
    dead[:, 0] = 0.0
    refused(lambda: validate_measurements(raw_dataset(dead, names=("a", "b"), x=(0.1, 0.2), tube=("c", "c"), units="um")),
            "'a'", "constant")


@pytest.mark.parametrize("kind", ["white", "white16bit", "white32", "narrowband"])
def test_clipping_rule_does_not_fire_on_gaussian_data(kind):
    # 20 independent Gaussian records of 20 000 samples: the rule must stay silent on all of them
    # (continuous data reach their extremes once; 16-bit quantisation over +-6 sigma has steps of
    # 1.8e-4 sigma, so several samples share the extreme level with negligible probability).
    for k in range(20):
        if kind == "narrowband":
            y = narrowband(20_000, ("nb", k))
        else:
            y = rng_for(SEED, "clip-null", k).standard_normal(20_000)
        if kind == "white16bit":
            step = 12.0 / 2**16
            y = np.round(y / step) * step
        elif kind == "white32":
            y = y.astype(np.float32).astype(float)
        validate_measurements(raw_dataset(y[:, None], names=("s",), x=(0.5,), tube=("c",), units="um"))


def test_refuses_fewer_than_two_samples(tmp_path):
    path = good_csv(tmp_path / "one.csv", values=np.array([[1e-4, 2e-4]]), t=np.array([0.0]))
    refused(lambda: read_measurements(path), "one.csv", "fewer than 2 samples")
    path = good_csv(tmp_path / "zero.csv", values=np.empty((0, 2)), t=np.empty(0))
    refused(lambda: read_measurements(path), "zero.csv", "fewer than 2 samples")


def test_refuses_duplicate_sensor_names(tmp_path, record):
    path = good_csv(tmp_path / "dup.csv", names=("S1", "S1"))
    refused(lambda: read_measurements(path), "dup.csv", "S1", "duplicate")
    dup = record.assign_coords(sensor=["A", "B", "A"])
    path = write_measurements(dup, tmp_path / "dup.nc", validate=False)
    refused(lambda: read_measurements(path), "dup.nc", "'A'", "duplicate")


def test_refuses_missing_sidecar_and_bad_sidecar(tmp_path):
    path = good_csv(tmp_path / "lonely.csv")
    sidecar_path(path).unlink()
    refused(lambda: read_measurements(path), "lonely.csv", "lonely.sensors.csv", "sidecar", "missing")
    path = good_csv(tmp_path / "extra.csv")
    with open(sidecar_path(path), "a") as fh:
        fh.write("S9,centre,0.4\n")
    refused(lambda: read_measurements(path), "extra.sensors.csv", "S9", "not columns")
    path = good_csv(tmp_path / "hdr.csv")
    sidecar_path(path).write_text("name,tube,x\nS1,centre,0.1\n")
    refused(lambda: read_measurements(path), "hdr.sensors.csv", "sensor")


def test_refuses_malformed_csv(tmp_path):
    path = tmp_path / "text.csv"
    path.write_text("time,S1\n0.0,abc\n0.001,1e-4\n")
    sidecar_path(path).write_text("sensor,tube,x\nS1,centre,0.1\n")
    refused(lambda: read_measurements(path), "text.csv: line 2, column 'S1' = 'abc': must be a number")
    path.write_text("t,S1\n0.0,1e-4\n")
    refused(lambda: read_measurements(path), "text.csv", "time,<sensor>")


def test_refuses_uff_channels_with_different_time_axes(tmp_path, record):
    path = write_measurements(record, tmp_path / "a.uff")
    other = validate_measurements(raw_dataset(gaussian(N, 1, key="o"), names=("S4",), x=(0.2,), tube=("north",),
                                              t0=0.5))
    path2 = write_measurements(other, tmp_path / "b.uff")
    combined = tmp_path / "mixed.uff"
    combined.write_bytes(path.read_bytes() + path2.read_bytes())
    refused(lambda: read_measurements(combined), "mixed.uff", "'S4'", "identical for all channels")


def test_refuses_unknown_format_and_never_unpickles(tmp_path):
    canary = tmp_path / "canary"

    class Hostile:
        def __reduce__(self):
            return (Path.touch, (canary,))

    payload = pickle.dumps(Hostile())
    pickle.loads(payload)  # the payload really would act if unpickled ...
    assert canary.exists()
    canary.unlink()
    pkl = tmp_path / "data.pkl"
    pkl.write_bytes(payload)
    npy = tmp_path / "data.npy"
    np.save(npy, gaussian(10, 2))
    refused(lambda: read_measurements(pkl), "data.pkl", "unknown format", "never loaded")
    refused(lambda: read_measurements(npy), "data.npy", "unknown format")
    for fmt, word in [("netcdf", "not a NetCDF file"), ("csv", "cannot be read as CSV"), ("uff", "data.pkl"),
                      ("zarr", "directory")]:
        refused(lambda: read_measurements(pkl, format=fmt), word)
    refused(lambda: read_measurements(pkl, format="pickle"), "unknown format")
    assert not canary.exists()  # ... and no reader unpickled it
    for module in (readers, validation):
        code = inspect.getsource(module)
        assert "import pickle" not in code and "np.load(" not in code and "allow_pickle" not in code


def test_refuses_missing_file_and_bad_options(tmp_path, record):
    refused(lambda: read_measurements(tmp_path / "nothere.nc"), "nothere.nc", "does not exist")
    refused(lambda: read_measurements(tmp_path / "x.nc", tubes={"centre": -1.0}), "tubes['centre']", "> 0")
    refused(lambda: validate_measurements(record, tubes={}), "tubes", "non-empty")
    refused(lambda: validate_measurements(record.rename(displacement="d")), "displacement")
    refused(lambda: validate_measurements(record.displacement), "xarray.Dataset")


def test_zarr_writer_will_not_overwrite_a_foreign_directory(tmp_path, record):
    folder = tmp_path / "precious.zarr"
    folder.mkdir()
    (folder / "thesis.tex").write_text("keep me")
    refused(lambda: write_measurements(record, folder), "precious.zarr", "not a Zarr store")
    assert (folder / "thesis.tex").exists()
    path = write_measurements(record, tmp_path / "ok.zarr")
    write_measurements(record, path)  # an existing store is replaced
    xr.testing.assert_identical(read_measurements(path).displacement, record.displacement)


# --------------------------------------------------------------------------- whole files only
def _small_record(n=12, m=3) -> xr.Dataset:
    return validate_measurements(raw_dataset(gaussian(n, m, key="small", scale=1e-6), t0=0.25, names=("S1", "S2", "S3")[:m],
                                             x=(0.10, 0.55, 0.30)[:m], tube=("centre", "centre", "north")[:m]))


def _read_cut(orig: xr.Dataset, path: Path) -> str:
    """What reading a cut file gives: 'refused', 'identical', 'prefix' (the first rows, exact) or
    'fewer channels' (some channels, exact); anything else fails the test (a wrong value)."""
    try:
        back = read_measurements(path)
    except SpecificationError:
        return "refused"
    a, b = orig.displacement.values, back.displacement.values
    names = list(orig.sensor.values)
    if b.shape == a.shape and np.array_equal(a, b):
        return "identical"
    if b.shape[1] == a.shape[1] and np.array_equal(a[: b.shape[0]], b):
        return "prefix"
    assert all(np.array_equal(a[:, names.index(s)], b[:, j]) for j, s in enumerate(back.sensor.values)), path
    return "fewer channels"


def _cuts(orig, full: Path, folder: Path, step: int = 1):
    """Cut ``full`` at every ``step``-th byte (its sidecar kept whole) and count the outcomes."""
    folder.mkdir()
    cut = folder / full.name
    if sidecar_path(full).exists():
        sidecar_path(cut).write_bytes(sidecar_path(full).read_bytes())
    data, counts = full.read_bytes(), {}
    for k in range(0, len(data), step):
        cut.write_bytes(data[:k])
        outcome = _read_cut(orig, cut)
        counts[outcome] = counts.get(outcome, 0) + 1
    return counts


def test_csv_cut_anywhere_is_refused_or_reads_as_the_exact_first_rows(tmp_path):
    """988 cut points of a 12-row CSV: before, 206 read wrong values; now a cut is refused unless it
    falls exactly on a line break, where the file is a shorter record of exact values (10 points)."""
    orig = _small_record()
    full = write_measurements(orig, tmp_path / "r.csv")
    counts = _cuts(orig, full, tmp_path / "cut")
    assert counts == {"refused": len(full.read_bytes()) - 10, "prefix": 10}


def test_a_number_cut_short_is_refused_naming_file_line_and_column(tmp_path):
    path = good_csv(tmp_path / "rec.csv", values=gaussian(6, 2, key="cut", scale=1e-6))
    text = path.read_text()
    last = text.rstrip("\n").split("\n")[-1].split(",")[-1]
    assert len(last) > 10
    path.write_text(text[: len(text) - 1 - (len(last) - 5)])  # the last value keeps 5 characters
    refused(lambda: read_measurements(path), "rec.csv: line 7, column 'S2'", repr(last[:5]), "cut short")
    path.write_text(text.replace("\n", "\n\n", 1)[:-1] + "\n")  # a blank line is harmless
    assert read_measurements(path).sizes["time"] == 6
    lines = text.split("\n")
    lines[3] = lines[3].rsplit(",", 1)[0]  # a row with a field missing
    path.write_text("\n".join(lines))
    refused(lambda: read_measurements(path), "rec.csv: line 4", "2 fields", "header's 3 fields")
    sidecar_path(path).write_text("sensor,tube,x\nS1,centre,0.1\nS2,centre,0.")  # a cut sidecar
    path.write_text(text)
    refused(lambda: read_measurements(path), "rec.sensors.csv: line 3, column 'x'", "cut short")


def _ascii_uff(path: Path, rec: xr.Dataset, positions: bool) -> Path:
    """An ASCII UFF 58 file as a lab tool writes it (pyuff directly; no 'channel k of n' lines)."""
    sets = []
    for j, name in enumerate(rec.sensor.values):
        sets.append(pyuff.prepare_58(
            binary=0, id1=str(name), id4=f"tube=centre x={0.1 * (j + 1)}" if positions else "", func_type=1,
            rsp_node=j + 1, rsp_dir=1, ref_node=0, ref_dir=0, abscissa_spacing=1, abscissa_spec_data_type=17,
            abscissa_axis_units_lab="s", ordinate_spec_data_type=8, ordinate_axis_units_lab="m",
            orddenom_spec_data_type=0, data=rec.displacement.values[:, j], x=rec.time.values))
    path.write_bytes(b"")
    pyuff.UFF(str(path)).write_sets(sets, mode="add")
    return path


def test_uff_cut_anywhere_is_refused(tmp_path):
    """pyuff silently drops an unclosed last dataset: before, 2228 of 3342 cut points of a 3-channel
    binary file read as fewer channels. Now every cut inside a dataset is refused, and so is a cut
    between datasets of a file tubeid wrote ('channel k of n') or whose sidecar lists every channel."""
    orig = _small_record()
    full = write_measurements(orig, tmp_path / "r.uff")
    # (the one cut that only drops the final line break reads the whole record)
    assert _cuts(orig, full, tmp_path / "binary") == {"refused": len(full.read_bytes()) - 1, "identical": 1}
    lab = _ascii_uff(tmp_path / "lab.uff", orig, positions=False)
    sidecar_path(lab).write_text("sensor,tube,x\nS1,centre,0.1\nS2,centre,0.2\nS3,centre,0.3\n")
    counts = _cuts(validate_measurements(read_measurements(lab)), lab, tmp_path / "ascii", step=3)
    assert set(counts) == {"refused"}
    # A lab file with positions in ID line 4 and no sidecar says nothing of its channel count: a cut
    # exactly between two datasets (a few bytes each) reads as fewer channels of exact values.
    # (per byte: 3485 refused, 12 fewer channels, 1 whole; every 5th byte here, for time)
    alone = _ascii_uff(tmp_path / "alone.uff", orig, positions=True)
    counts = _cuts(validate_measurements(read_measurements(alone)), alone, tmp_path / "alone", step=5)
    assert counts["refused"] > 0.99 * len(range(0, len(alone.read_bytes()), 5)) and counts.get("fewer channels", 0) <= 12
    assert set(counts) <= {"refused", "fewer channels", "identical"}


def test_uff_dataset_holding_fewer_values_than_its_header_declares_is_refused(tmp_path):
    orig = _small_record()
    lab = _ascii_uff(tmp_path / "lab.uff", orig, positions=True)
    lines = lab.read_text().split("\n")
    record7 = next(i for i, line in enumerate(lines) if line.startswith("         4        12"))
    lines[record7] = lines[record7].replace("         4        12", "         4        13", 1)
    lab.write_text("\n".join(lines))
    refused(lambda: read_measurements(lab), "lab.uff: channel 'S1' data", "12 values", "declares 13", "incomplete")


def test_whole_concatenated_uff_files_are_read(tmp_path):
    """Files written by tubeid and joined whole (cat a.uff b.uff) keep every channel."""
    a = write_measurements(_small_record(m=2), tmp_path / "a.uff")
    other = validate_measurements(raw_dataset(gaussian(12, 1, key="o", scale=1e-6), names=("S9",), x=(0.2,),
                                              tube=("north",), t0=0.25))
    b = write_measurements(other, tmp_path / "b.uff")
    both = tmp_path / "both.uff"
    both.write_bytes(a.read_bytes() + b.read_bytes())
    assert list(read_measurements(both).sensor.values) == ["S1", "S2", "S9"]
    both.write_bytes(b.read_bytes() + a.read_bytes()[: len(a.read_bytes()) // 2 + 1])
    refused(lambda: read_measurements(both), "dataset", "cut short")


@pytest.mark.parametrize("name, fmt, step", [("r.nc", None, 37), ("r3.nc", "netcdf3", 3)])
def test_netcdf_cut_anywhere_is_refused(tmp_path, name, fmt, step):
    orig = _small_record()
    full = write_measurements(orig, tmp_path / name, format=fmt)
    counts = _cuts(orig, full, tmp_path / "cut", step=step)
    assert counts == {"refused": len(range(0, len(full.read_bytes()), step))}


def _claiming(path: Path, n: int, engine: str) -> Path:
    """A record whose metadata claims n × 2 float64 samples but which holds no data (a few kB):
    written small, then its declared sizes raised (Zarr), or made with h5netcdf without writing."""
    if engine == "zarr":
        import json

        write_measurements(raw_dataset(gaussian(100, 2, key="claim", scale=1e-6), names=("S1", "S2"), x=(1.0, 2.0),
                                       tube=("c", "c")), path)
        for name in ("displacement", "time"):
            meta = json.loads((path / name / "zarr.json").read_text())
            meta["shape"][0] = n
            (path / name / "zarr.json").write_text(json.dumps(meta))
        return path
    import h5netcdf
    import h5py

    with h5netcdf.File(path, "w") as f:
        f.dimensions = {"time": n, "sensor": 2}
        f.create_variable("time", ("time",), float, chunks=(n // 100,)).attrs["units"] = "s"
        d = f.create_variable("displacement", ("time", "sensor"), float, chunks=(n // 100, 2))
        d.attrs.update(units="m", coordinates="x tube")
        f.create_variable("sensor", ("sensor",), h5py.string_dtype())[:] = ["S1", "S2"]
        f.create_variable("x", ("sensor",), float)[:] = [1.0, 2.0]
        f.create_variable("tube", ("sensor",), h5py.string_dtype())[:] = ["c", "c"]
    return path


@pytest.mark.parametrize("name, engine", [("huge.nc", "h5netcdf"), ("huge.zarr", "zarr")])
def test_claimed_size_is_refused_before_anything_is_loaded(tmp_path, monkeypatch, name, engine):
    """A 6 kB header claiming 150 M × 2 samples took 6.2 GB before its refusal: now refused from the
    metadata, naming the claimed size and the limit, and nothing is loaded."""
    path = _claiming(tmp_path / name, 150_000_000, engine)
    assert sum(f.stat().st_size for f in ([path] if path.is_file() else path.rglob("*"))) < 100_000

    def no_load(self, **kw):
        raise AssertionError("loaded before the size check")

    monkeypatch.setattr(xr.Dataset, "load", no_load)
    refused(lambda: read_measurements(path), name, "(time 150000000, sensor 2) of 3.35 GiB",
            "larger than the memory limit 2.00 GiB", "tubeid.io.max-bytes")
    import dask.config

    monkeypatch.undo()
    small = _claiming(tmp_path / ("small" + name), 1000, engine)
    with dask.config.set({"tubeid.io.max-bytes": "10 kB"}):  # configurable
        refused(lambda: read_measurements(small), "claiming (time 1000, sensor 2) of 2", "larger than the memory limit 9.77 kiB")


def test_large_text_files_are_refused_before_they_are_read(tmp_path):
    import dask.config

    path = good_csv(tmp_path / "rec.csv")
    size = path.stat().st_size
    with dask.config.set({"tubeid.io.max-bytes": size - 1}):
        refused(lambda: read_measurements(path), "rec.csv", "CSV file of", "larger than the memory limit")
    assert read_measurements(path).sizes["sensor"] == 2


@pytest.mark.filterwarnings("ignore:Object at displacement is not recognized")
def test_zarr_with_a_missing_or_damaged_chunk_is_refused(tmp_path):
    orig = _small_record(n=64)
    path = tmp_path / "rec.zarr"
    readers._strings_as_objects(orig.chunk({"time": 16})).to_zarr(path, consolidated=False)  # 4 chunks
    assert read_measurements(path).sizes["time"] == 64
    chunks = sorted((path / "displacement" / "c").rglob("*"))
    chunks = [c for c in chunks if c.is_file()]
    assert len(chunks) == 4
    good = chunks[2].read_bytes()
    chunks[2].unlink()
    refused(lambda: read_measurements(path), "rec.zarr: displacement", "3 of 4 chunks present", "fill value")
    chunks[2].write_bytes(b"\x00garbage" * 8)
    refused(lambda: read_measurements(path), "rec.zarr", "cannot be read as Zarr")
    chunks[2].write_bytes(good)
    (path / "displacement" / "zarr.json").unlink()
    refused(lambda: read_measurements(path), "rec.zarr", "displacement")


# --------------------------------------------------------------------------- plausibility
def test_implausible_amplitudes_are_refused_naming_sensor_value_and_bound(tmp_path):
    import dask.config

    values = gaussian(200, 3, key="amp", scale=1e-6)
    values[57, 1] = 1e294
    refused(lambda: validate_measurements(raw_dataset(values)), "channel 'S2' displacement[57]", "1e+294 m",
            "beyond ± 1 m", "tubeid.io.max-displacement")
    values[57, 1] = 3e-6
    path = good_csv(tmp_path / "mm.csv", values=values[:, :2] * 1e3 * 2e5, units=("mm", "mm"))  # ~0.2 m
    assert read_measurements(path).sizes["sensor"] == 2
    with dask.config.set({"tubeid.io.max-displacement": 0.1}):
        refused(lambda: read_measurements(path), "mm.csv: channel", "beyond ± 0.1 m")


def test_integer_samples_need_an_explicit_scale(tmp_path):
    counts = np.round(gaussian(300, 3, key="int", scale=1000.0)).astype(np.int16)
    raw = raw_dataset(counts, units="um")
    raw["displacement"] = raw.displacement.astype(np.int16)
    refused(lambda: validate_measurements(raw), "displacement.dtype = 'int16'", "explicit scale", "scale_factor")
    raw.displacement.attrs.update(scale_factor=0.05, add_offset=1.0)
    ds = validate_measurements(raw)
    np.testing.assert_array_equal(ds.displacement.values, (counts * 0.05 + 1.0) * 1e-6)
    # In a file: CF packing (integers + scale_factor) is unpacked by xarray; without it refused,
    # also when a _FillValue made xarray hand the integers over as floats.
    packed = tmp_path / "packed.nc"
    raw.to_netcdf(packed, engine="h5netcdf")
    np.testing.assert_allclose(read_measurements(packed).displacement.values, ds.displacement.values, rtol=1e-15, atol=0)
    bare = raw.copy()
    bare["displacement"] = bare.displacement.copy()
    bare.displacement.attrs.pop("scale_factor")
    bare.displacement.attrs.pop("add_offset")
    bare.displacement.encoding["_FillValue"] = -32768
    bare.to_netcdf(tmp_path / "bare.nc", engine="h5netcdf")
    refused(lambda: read_measurements(tmp_path / "bare.nc"), "bare.nc: displacement.dtype = 'int16'", "explicit scale")
    raw.displacement.attrs.update(scale_factor=-0.05)  # a sign flip the sidecar refuses too (scale > 0)
    raw.to_netcdf(tmp_path / "negative.nc", engine="h5netcdf")
    refused(lambda: read_measurements(tmp_path / "negative.nc"), "negative.nc: displacement.scale_factor = -0.05", "> 0")


def test_integer_csv_columns_need_a_scale_in_the_sidecar(tmp_path):
    counts = np.round(gaussian(100, 2, key="csvint", scale=1000.0)).astype(int)
    path = tmp_path / "counts.csv"
    rows = [f"{i / FS!r},{a},{b}" for i, (a, b) in enumerate(counts)]
    path.write_text("time,S1,S2\n" + "\n".join(rows) + "\n")
    sidecar_path(path).write_text("sensor,tube,x,units\nS1,centre,0.1,um\nS2,centre,0.2,um\n")
    refused(lambda: read_measurements(path), "channel 'S1' = integer values only", "explicit scale", "'scale' column")
    sidecar_path(path).write_text("sensor,tube,x,units,scale\nS1,centre,0.1,um,0.05\nS2,centre,0.2,um,0.05\n")
    np.testing.assert_array_equal(read_measurements(path).displacement.values, counts * 0.05 * 1e-6)
    sidecar_path(path).write_text("sensor,tube,x,units,scale\nS1,centre,0.1,um,-1\nS2,centre,0.2,um,0.05\n")
    refused(lambda: read_measurements(path), "channel 'S1' scale = '-1'", "> 0")


def test_too_many_sensors_are_refused_with_a_memory_estimate(tmp_path):
    values = gaussian(50, 1000, key="many", scale=1e-6)
    names = [f"s{j}" for j in range(1000)]
    raw = raw_dataset(values, names=names, x=np.linspace(0, 1, 1000), tube=["c"] * 1000)
    refused(lambda: validate_measurements(raw), "sensor = 1000 sensors", "at most 64",
            "15.26 MiB per frequency bin", "14.90 GiB per realisation")
    path = tmp_path / "wide.csv"
    path.write_text("time," + ",".join(names) + "\n")
    refused(lambda: read_measurements(path), "wide.csv: header = 1000 sensors", "at most 64")


# --------------------------------------------------------------------------- hostile records, end to end
def _hostile_records(tmp_path: Path) -> dict[str, tuple[Path, str]]:
    rec = validate_measurements(raw_dataset(gaussian(64, 3, key="hostile", scale=1e-6), tube=("centre",) * 3,
                                            x=(2.0, 6.0, 10.0)))  # on the centre tube of paper-simplified
    cases = {}
    p = write_measurements(rec, tmp_path / "cut.csv")
    p.write_bytes(p.read_bytes()[:-9])
    cases["csv cut inside a number"] = (p, "cut short")
    p = write_measurements(rec, tmp_path / "cut.uff")
    p.write_bytes(p.read_bytes()[:-100])
    cases["uff cut inside its last dataset"] = (p, "never closed")
    cases["netcdf claiming 150 M samples"] = (_claiming(tmp_path / "huge.nc", 150_000_000, "h5netcdf"), "memory limit")
    big = rec.copy(deep=True)
    big["displacement"][3, 1] = 1e294
    cases["amplitude 1e294 m"] = (write_measurements(big, tmp_path / "big.nc", validate=False), "implausible")
    return cases


def test_hostile_records_are_refused_by_the_api_and_the_cli(tmp_path, capsys):
    """tubeid.read_measurements and `tubeid diagnose` give the refusal, never a traceback."""
    import tubeid
    from tubeid.cli import main

    for what, (path, words) in _hostile_records(tmp_path).items():
        refused(lambda: tubeid.read_measurements(path), path.name, words)
        assert main(["diagnose", str(path), "--out", str(tmp_path / "out"), "--workers", "0"]) == 2, what
        err = capsys.readouterr().err
        assert err.startswith("tubeid: error: ") and path.name in err and words in err, (what, err)
        assert "Traceback" not in err


# --------------------------------------------------------------------------- input validation (review)
def test_time_x_and_samples_of_timedelta_or_datetime_type_are_refused():
    """np.issubdtype(timedelta64, np.integer) is True: 1 ms steps were read as dt = 1.0 s."""
    raw = raw_dataset(gaussian())
    steps = np.arange(N) * np.timedelta64(1, "ms")
    for t in (steps, np.datetime64("2024-01-01") + steps, np.arange(N) % 2 == 0):
        refused(lambda: validate_measurements(raw.assign_coords(time=("time", t))), "time.dtype",
                "time must be numeric seconds")
    refused(lambda: validate_measurements(raw.assign_coords(x=("sensor", np.array([1, 2, 3]) * np.timedelta64(1, "s")))),
            "x.dtype", "positions x must be numbers")
    counts = (gaussian() * 1e9).astype("int64").astype("m8[ns]")
    bad = raw.copy()
    bad["displacement"] = (("time", "sensor"), counts, {"units": "nm", "scale_factor": 1.0})
    refused(lambda: validate_measurements(bad), "displacement.dtype", "real numbers")


@pytest.mark.parametrize("length", ["16", np.True_, True, None, np.nan, 0.0])
def test_tube_lengths_must_be_numbers(tmp_path, length):
    """The string "16" was a length of 16 m, and np.True_ one of 1 m (float() of either works)."""
    path = good_csv(tmp_path / "good.csv")
    with pytest.raises(SpecificationError, match=r"^tubes\['centre'\] = .*: must be a finite number > 0 \(m\)"):
        read_measurements(path, tubes={"centre": length})
    assert read_measurements(path, tubes={"centre": np.float32(16.0)}).sizes["sensor"] == 2


def test_units_attribute_and_coordinate_compare_as_units_not_text():
    """'um' beside a per-channel 'µm' was refused as conflicting; a different unit still is."""
    raw = raw_dataset(gaussian())
    same = raw.assign_coords(units=("sensor", ["\u00b5m", "\u03bcm", "micron"]))
    same.displacement.attrs["units"] = "um"
    out = validate_measurements(same)
    np.testing.assert_array_equal(out.displacement.values, raw.displacement.values * 1e-6)
    other = raw.assign_coords(units=("sensor", ["\u00b5m", "mm", "um"]))
    other.displacement.attrs["units"] = "um"
    refused(lambda: validate_measurements(other), "displacement.units", "conflicts")


def test_epoch_time_stamps_pass_the_uniformity_rule(tmp_path):
    """t0 = 1.7e9 s, dt = 1 ms: float64 stores the stamps to ±1.2e-7 s (1.2e-4 of a step), whatever
    the record's length, and t - t0 cannot undo that; the rule allows that rounding on top of
    UNIFORM_RTOL while it stays within STAMP_RTOL of dt."""
    t = 1.7e9 + np.arange(50) * 1e-3
    assert np.abs(np.diff(t) - 1e-3).max() > 1e-4 * 1e-3  # the stamps are not uniform to 1e-6
    back = read_measurements(good_csv(tmp_path / "epoch.csv", t=t))
    np.testing.assert_array_equal(back.time.values, t)  # the stamps as they are
    assert back.attrs["dt"] == pytest.approx(1e-3, rel=validation.STAMP_RTOL / 49, abs=0)
    # genuinely non-uniform sampling is still refused: 1 % of a step
    jitter = t.copy()
    jitter[10] += 1e-5
    refused(lambda: read_measurements(good_csv(tmp_path / "jitter.csv", t=jitter)), "jitter.csv", "uniform",
            "float64 rounding")
    # stamps too coarse for the step (0.1 ms at 1.7e9 s) cannot show uniform sampling: refused, with the remedy
    fast = 1.7e9 + np.arange(50) * 1e-4
    refused(lambda: read_measurements(good_csv(tmp_path / "fast.csv", t=fast)), "fast.csv: time", "too coarse",
            "record's start")
    # exactly representable stamps stay valid however large they are
    exact = 2.0**31 + np.arange(50) * 2.0**-14
    assert read_measurements(good_csv(tmp_path / "exact.csv", t=exact)).attrs["dt"] == 2.0**-14


@pytest.mark.parametrize("fmt", ["netcdf3", "netcdf", "zarr"])
def test_float32_time_stamps_are_judged_by_float32_rounding(tmp_path, fmt):
    """A logger's float32 time axis (t_i = float32(i dt)) is uniform up to float32's rounding, which
    the rule measured in float64 spacings: 2 s at 1 kHz were refused as 'non-uniform' (7e-5 of a
    step). Now the stamps' own type sets the rounding allowed (within STAMP_RTOL): 2 s pass, read as
    the float32 stamps exactly; 30 s (rounding 7.6e-3 of a step) are refused naming float32 and the
    remedy (float64 stamps), not as non-uniform sampling or with advice to count from the start."""
    dt = 1e-3
    for seconds, accepted in ((2.0, True), (30.0, False)):
        n = int(seconds / dt)
        t32 = (np.arange(n) * dt).astype(np.float32)
        assert np.abs(np.diff(t32.astype(float)) - dt).max() > validation.UNIFORM_RTOL * dt  # not uniform in float64
        ds = raw_dataset(gaussian(n), time=t32).assign_coords(time=("time", t32, {"units": "s"}))
        path = write_measurements(ds, tmp_path / f"f32-{seconds:g}.{'zarr' if fmt == 'zarr' else 'nc'}", format=fmt,
                                  validate=False)
        for call in (lambda: validate_measurements(ds), lambda: read_measurements(path)):
            if accepted:
                back = call()
                np.testing.assert_array_equal(back.time.values, t32.astype(float))
                # dt from the end points: their float32 rounding over n - 1 steps
                assert back.attrs["dt"] == pytest.approx(dt, rel=validation.STAMP_RTOL / (2 * (n - 1)), abs=0)
            else:
                msg = refused(call, "time = float32 stamps", "too coarse", "store time as float64")
                assert "record's start" not in msg


# --------------------------------------------------------------------------- review: measured files
def _by_xarray(ds: xr.Dataset, path: Path, zarr: bool = False) -> Path:
    """A record written by xarray itself (not tubeid's writer): NetCDF-4 by h5netcdf, or Zarr; under a
    plain name first, then renamed (zarr would write a name holding '::' elsewhere)."""
    plain = path.with_name("plain-tmp")
    if zarr:
        ds.to_zarr(plain, consolidated=False)
    else:
        ds.to_netcdf(plain, engine="h5netcdf")
    return plain.rename(path)


@pytest.mark.parametrize("name, other", [("a::b.nc", "a:"), ("z::b.zarr", "z:")])
def test_a_record_path_that_xarray_would_read_as_a_url_is_refused(tmp_path, monkeypatch, name, other):
    """xarray and zarr read 'a::b.nc' as the fsspec chain 'a:' (a file of another record, read silently)."""
    monkeypatch.chdir(tmp_path)
    mine = raw_dataset(gaussian(64, 3, key="mine", scale=1e-6))
    _by_xarray(mine, tmp_path / name, zarr=name.endswith(".zarr"))
    _by_xarray(raw_dataset(gaussian(64, 3, key="theirs", scale=1e-6)), tmp_path / other, zarr=name.endswith(".zarr"))
    for path in (name, Path(name)):
        refused(lambda: read_measurements(path), f"data = '{name}'", "must be a local", "'::'", "rename")
    before = sorted(p.name for p in tmp_path.iterdir())
    refused(lambda: write_measurements(validate_measurements(mine), "c::d" + Path(name).suffix), "path = 'c::d",
            "'::'")
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing written, neither 'c::d' nor 'c:'
    # a working directory named like a URL: the relative path is fine, its absolute form is not
    (tmp_path / "w::d").mkdir()
    _by_xarray(mine, tmp_path / "w::d" / "rec.nc")
    monkeypatch.chdir(tmp_path / "w::d")
    refused(lambda: read_measurements("rec.nc"), "data = 'rec.nc'", "(as ", "w::d")


def test_a_record_path_the_file_system_cannot_look_up_is_refused(tmp_path):
    for ext in ("csv", "nc", "uff", "zarr"):
        refused(lambda: read_measurements(tmp_path / ("x" * 300 + "." + ext)), "data = ", "cannot be looked up")


def _csv_by_hand(path: Path, data: str, side: str = "sensor,tube,x\nS1,centre,0.1\nS2,centre,0.2\n") -> Path:
    path.write_bytes(data.encode())
    sidecar_path(path).write_bytes(side.encode())
    return path


_CSV_DATA = "time,S1,S2\n0.0,1.5e-6,-2.5e-6\n0.001,-0.5e-6,3.5e-6\n0.002,2.5e-6,0.5e-6\n"


def test_csv_line_endings_other_than_lf_or_crlf_are_refused_naming_file_and_line(tmp_path):
    """CR-only line endings, and a \\r inside a header name, gave the csv module's traceback
    ("new-line character seen in unquoted field")."""
    assert read_measurements(_csv_by_hand(tmp_path / "lf.csv", _CSV_DATA)).sizes == {"time": 3, "sensor": 2}
    crlf = _csv_by_hand(tmp_path / "crlf.csv", _CSV_DATA.replace("\n", "\r\n"),
                        "sensor,tube,x\r\nS1,centre,0.1\r\nS2,centre,0.2\r\n")
    assert read_measurements(crlf).sizes == {"time": 3, "sensor": 2}
    rule = "must have lines ending in \\n or \\r\\n"
    path = _csv_by_hand(tmp_path / "cr.csv", _CSV_DATA.replace("\n", "\r"))
    refused(lambda: read_measurements(path), "cr.csv: line 1 = ", rule)
    path = _csv_by_hand(tmp_path / "crside.csv", _CSV_DATA, "sensor,tube,x\rS1,centre,0.1\rS2,centre,0.2\r")
    refused(lambda: read_measurements(path), "crside.sensors.csv: line 1 = ", rule)
    path = _csv_by_hand(tmp_path / "name.csv", _CSV_DATA.replace("S2", "S\r2", 1))
    refused(lambda: read_measurements(path), "name.csv: line 1 = ", rule)
    path = _csv_by_hand(tmp_path / "tube.csv", _CSV_DATA, 'sensor,tube,x\nS1,centre,0.1\nS2,"cen\rtre",0.2\n')
    refused(lambda: read_measurements(path), "tube.sensors.csv: line 3 = ", rule)
    # a file cut between \r and \n is cut short, as before
    path = _csv_by_hand(tmp_path / "cut.csv", _CSV_DATA.replace("\n", "\r\n")[:-1])
    refused(lambda: read_measurements(path), "cut.csv: line 4", "cut short")
    # and tubeid never writes a tube name it could not read back
    rec = validate_measurements(raw_dataset(gaussian(8, 1, scale=1e-6), names=("S1",), x=(0.1,), tube=("a\rb",)))
    refused(lambda: write_measurements(rec, tmp_path / "w.csv"), "tube name", "faithfully")


def test_csv_fields_beyond_the_csv_modules_limit_are_refused_naming_file_and_line(tmp_path):
    """A header or sidecar field over 131072 characters gave '_csv.Error: field larger than field limit'."""
    import csv

    long = "S" * (csv.field_size_limit() + 1)
    rule = f"at most {csv.field_size_limit()} characters"
    path = _csv_by_hand(tmp_path / "head.csv", _CSV_DATA.replace("S2", long, 1),
                        f"sensor,tube,x\nS1,centre,0.1\n{long},centre,0.2\n")
    refused(lambda: read_measurements(path), "head.csv: line 1 = ", rule)
    path = _csv_by_hand(tmp_path / "side.csv", _CSV_DATA, f'sensor,tube,x\nS1,centre,0.1\nS2,"{long}",0.2\n')
    refused(lambda: read_measurements(path), "side.sensors.csv: line 3 = ", rule)
    path = _csv_by_hand(tmp_path / "sidehead.csv", _CSV_DATA, f"sensor,tube,x,{long}\nS1,centre,0.1,\nS2,centre,0.2,\n")
    refused(lambda: read_measurements(path), "sidehead.sensors.csv: line 1 = ", rule)
    path = _csv_by_hand(tmp_path / "quote.csv", _CSV_DATA, 'sensor,tube,x\nS1,"centre,0.1\n' + "S2,centre,0.2\n" * 11000)
    refused(lambda: read_measurements(path), "quote.sensors.csv: line ", rule)
    assert csv.field_size_limit() == 131072  # refused, not read by raising the limit


@pytest.mark.parametrize("data, side, name, column", [
    (_CSV_DATA, "sensor,tube,x,x\nS1,centre,0.1,0.3\nS2,centre,0.2,0.4\n", "dup.sensors.csv", "x"),
    (_CSV_DATA, "sensor,tube,tube,x\nS1,centre,north,0.1\nS2,centre,north,0.2\n", "dup.sensors.csv", "tube"),
    (_CSV_DATA.replace("S2", "time", 1), "sensor,tube,x\nS1,centre,0.1\ntime,centre,0.2\n", "dup.csv", "time")])
def test_csv_headers_naming_a_column_twice_are_refused(tmp_path, data, side, name, column):
    """A sidecar 'sensor,tube,x,x' used the first x silently (and 'time,S1,time' made a sensor 'time')."""
    path = _csv_by_hand(tmp_path / "dup.csv", data, side)
    refused(lambda: read_measurements(path), f"{name}: header = ['{column}']", "duplicate column name")


def _uff_of_type(path: Path, rec: xr.Dataset, data_type: int, unit: str, scale: float = 1.0) -> Path:
    """An ASCII UFF 58 file by pyuff directly, its ordinate of specific data type ``data_type`` (record 8)."""
    sets = [pyuff.prepare_58(
        binary=0, id1=str(name), id4=f"tube=centre x={0.1 * (j + 1)}", func_type=1, rsp_node=j + 1, rsp_dir=1,
        ref_node=0, ref_dir=0, abscissa_spacing=1, abscissa_spec_data_type=17, abscissa_axis_units_lab="s",
        ordinate_spec_data_type=data_type, ordinate_axis_units_lab=unit, orddenom_spec_data_type=0,
        data=rec.displacement.values[:, j] * scale, x=rec.time.values) for j, name in enumerate(rec.sensor.values)]
    path.write_bytes(b"")
    pyuff.UFF(str(path)).write_sets(sets, mode="add")
    return path


@pytest.mark.parametrize("data_type, word", [(12, "12 (acceleration)"), (11, "11 (velocity)"), (3, "3 (strain)"),
                                             (9, "9 (reaction force)"), (4, "= 4:")])
def test_uff_datasets_that_are_not_displacement_are_refused(tmp_path, data_type, word):
    """Acceleration, velocity or strain labelled 'm' was read as displacement in metres, silently."""
    rec = _small_record()
    path = _uff_of_type(tmp_path / "acc.uff", rec, data_type, "m")
    refused(lambda: read_measurements(path), "acc.uff: channel 'S1' ordinate data type = ", word, "must be 8 (displacement")


def test_uff_datasets_of_unknown_or_general_type_need_a_length_unit(tmp_path):
    rec = _small_record()
    for data_type in (0, 1, 8):
        back = read_measurements(_uff_of_type(tmp_path / f"t{data_type}.uff", rec, data_type, "mm", scale=1e3))
        # ASCII 58: 12 significant digits (see test_lab_ascii_uff_with_sidecar_positions_and_mm)
        np.testing.assert_allclose(back.displacement.values, rec.displacement.values, rtol=1e-11, atol=0)
    for data_type in (0, 1):
        path = _uff_of_type(tmp_path / f"g{data_type}.uff", rec, data_type, "m/s^2")
        refused(lambda: read_measurements(path), f"g{data_type}.uff: channel 'S1' ordinate data type = {data_type} (",
                "only with a length units label", "'m/s^2'")


@pytest.mark.parametrize("fmt", ["h5netcdf", "scipy", "zarr"])
@pytest.mark.parametrize("attr, value, counts", [("scale_factor", "abc", False), ("add_offset", "abc", False),
                                                 ("scale_factor", "0.05", True), ("scale_factor", [0.5, 2.0], False)])
def test_cf_packing_attributes_that_are_not_numbers_are_refused(tmp_path, fmt, attr, value, counts):
    """A text scale_factor on float data was refused with numpy's "UFuncTypeError: ufunc 'multiply' ..."."""
    raw = raw_dataset(gaussian(64, 3, key="packing", scale=1e-6))
    if counts:
        raw["displacement"] = raw.displacement.copy(data=np.round(raw.displacement.values * 1e9).astype("int32"))
        raw.displacement.attrs["units"] = "nm"
    raw.displacement.attrs[attr] = value  # written as it is by xarray (a text or array attribute is not packing)
    path = tmp_path / ("rec.zarr" if fmt == "zarr" else "rec.nc")
    if fmt == "zarr":
        raw.to_zarr(path, consolidated=False)
    else:
        raw.to_netcdf(path, engine=fmt)
    refused(lambda: read_measurements(path), f"rec.{path.suffix[1:]}: displacement.{attr} = ", "must be a finite number",
            "stored * scale_factor + add_offset")
