"""Read and write measured displacement records: NetCDF, Zarr, CSV + sidecar, UFF type 58.

Every reader returns the one canonical, validated Dataset of :mod:`tubeid.measured.validation`
(``displacement`` (time, sensor) in m, ``time`` in s, ``sensor`` with ``x`` (m) and ``tube``).

Formats (chosen by ``format=`` or by the extension):

- ``netcdf`` (``.nc``, ``.nc4``, ``.cdf``, ``.netcdf``): the engine is picked from the file's
  signature, ``h5netcdf`` for NetCDF-4/HDF5, ``scipy`` for classic NetCDF-3. ``write_measurements``
  writes NetCDF-4 (h5netcdf) for ``netcdf``/``netcdf4`` and NetCDF-3 64-bit offset (scipy) for
  ``netcdf3``. ``zarr`` (``.zarr`` directory): written as Zarr v3, strings as variable length.
  Both hold the canonical layout (MODEL.md §5); ``displacement`` must carry a ``units`` attribute.
  CF packing attributes (``scale_factor``, ``add_offset``) of any variable must be finite numbers
  (a text one is refused naming it).
- ``csv`` (``.csv``): one header line ``time,<sensor>,…`` then one row per sample (time in s,
  displacement in m). Sidecar ``<stem>.sensors.csv`` beside it with columns ``sensor,tube,x``
  (x in m) and optionally ``units`` (per channel; empty or absent = ``m``) and ``scale`` (the size
  of one count in ``units``: required for a channel written in integers only, counts, e.g.
  ``S1,centre,6.0,um,0.05``). Every data column must be listed in the sidecar and every sidecar
  row must be a data column. A header (data or sidecar) naming a column twice is refused. Lines
  end in ``\\n`` or ``\\r\\n`` (a lone ``\\r``, old Mac line endings or inside a name, is refused
  naming its line), and no field may exceed the csv module's limit of 131072 characters.
- ``uff`` (``.uff``, ``.unv``): universal file, one type-58 dataset per channel (other dataset
  types are ignored), read and written with pyuff. Convention:

  * sensor name = ID line 1 (record 1); if blank, ``node<rsp_node>dir<rsp_dir>``;
  * position = ID line 4 (record 4) holding ``tube=<name> x=<metres>`` (name without spaces);
    if ID line 4 has neither token, the channel's row in the sidecar ``<stem>.sensors.csv``
    (``sensor,tube,x``; a ``units`` cell there, if any, must agree with the UFF label) is used;
    both present must agree; neither is refused;
  * units = ordinate units label (record 9, field 6); the unit exponents are ignored;
  * data type = ordinate specific data type (record 8, field 1): 8 (displacement); 0 (unknown) and
    1 (general) are read as displacement only with a length units label (m, mm, um, µm, micron,
    nm); any other (acceleration 12, velocity 11, strain 3, …) is refused, never read as a length;
  * function type (record 6) must be 1 (time response), data real, abscissa time
    (specific data type 0 or 17, label ``s`` or blank) and identical for all channels;
  * ID line 5 reads ``channel k of n`` in files tubeid writes; when present, the file must hold
    those n datasets in order.

  Written as binary 58b in float64 with an explicit abscissa, so data and time round-trip
  bit-exactly (pyuff's ASCII 58 keeps 12 significant digits for data, and only 6 for
  the abscissa start and increment of evenly spaced records).

Whole files only. A file cut short (a truncated copy or download) is refused, never read as wrong
or fewer data: a CSV (and sidecar) must end its last line with a line break, every row must have
the header's field count and every value must parse as a whole number token (the message names
file, line and column); a UFF file must close every dataset (pyuff silently drops an unclosed last
one), hold nothing outside datasets, and each dataset must hold the number of values its header
(record 7) declares; NetCDF and HDF5 check their own structure. What no format can reveal: a CSV
cut exactly at a line break reads as a shorter record of exact values, and a UFF file without
``channel k of n`` lines (or a sidecar listing every channel) cut exactly between datasets as
fewer channels.

Limits (configuration ``tubeid.io``, checked before anything is loaded): a NetCDF/Zarr record whose
variables claim more than ``max-bytes`` once loaded (shape × dtype, from the metadata alone), and a
CSV/UFF file larger than that, are refused naming both sizes; more than ``max-sensors`` channels are
refused (:func:`tubeid._validation.channel_count`); Zarr arrays must have all their chunks (a missing
chunk would read as its fill value). :func:`~tubeid.measured.validation.validate_measurements` then
refuses implausible amplitudes (``max-displacement``) and unscaled integer data.

Paths (checked before anything is opened or written): a NetCDF or Zarr path holding ``::`` or ``://``
as given, made absolute or with links resolved is refused (xarray and zarr read it as an fsspec URL:
``a::b.nc`` would open the file ``a:``, :func:`tubeid._paths.local_path`); a path of any format the
file system cannot look up (a name too long, a loop of links) is refused naming it.

Safety: nothing is ever loaded by unpickling. This module uses neither ``pickle`` nor
``np.load``; ``.npy``/``.pkl`` and other extensions are refused as unknown formats, and a file
forced to a format must carry that format's signature or parse as text.
"""

from __future__ import annotations

import csv
import math
import os
import re
import warnings
from collections import Counter
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import xarray as xr

from tubeid._optional import require
from tubeid._paths import local_path, looked_up
from tubeid._validation import byte_size, channel_count, is_number, limit
from tubeid.errors import Described, SpecificationError
from tubeid.measured.validation import LENGTH_UNITS, check_options, layout, length_scale, validate_measurements

__all__ = ["read_measurements", "write_measurements", "sidecar_path", "EXTENSIONS", "FORMATS"]

#: Extension -> format.
EXTENSIONS = {".nc": "netcdf", ".nc4": "netcdf", ".cdf": "netcdf", ".netcdf": "netcdf",
              ".zarr": "zarr", ".csv": "csv", ".uff": "uff", ".unv": "uff"}
#: Accepted ``format=`` values -> format.
FORMATS = {"netcdf": "netcdf", "netcdf4": "netcdf", "netcdf3": "netcdf3", "zarr": "zarr",
           "csv": "csv", "uff": "uff", "uff58": "uff", "unv": "uff"}

_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
_CDF3_MAGIC = (b"CDF\x01", b"CDF\x02")
_UFF_TOKEN_TUBE = re.compile(r"(?:^|\s)tube=(\S+)")
_UFF_TOKEN_X = re.compile(r"(?:^|\s)x=(\S+)")


def sidecar_path(path) -> Path:
    """The sensor sidecar of a data file: ``<dir>/<stem>.sensors.csv``."""
    path = Path(path)
    return path.with_name(path.stem + ".sensors.csv")


def _resolve_format(path: Path, fmt) -> str:
    if fmt is not None:
        key = str(fmt).lower()
        if key not in FORMATS:
            raise SpecificationError("format", fmt, f"unknown format; must be one of {sorted(FORMATS)}")
        return FORMATS[key]
    ext = path.suffix.lower()
    if ext not in EXTENSIONS:
        raise SpecificationError(
            str(path), ext or "(no extension)",
            f"unknown format: extension must be one of {sorted(EXTENSIONS)} or give format= "
            f"(pickled or .npy files are never loaded)")
    return EXTENSIONS[ext]


def _fail_read(source: str, kind: str, exc: Exception):
    if isinstance(exc, ImportError):  # a missing library is not bad input
        raise exc
    raise SpecificationError(source, kind, f"cannot be read as {kind}: {type(exc).__name__}: {exc}") from exc


# --------------------------------------------------------------------------- limits
def _check_claimed(source: str, nbytes: int, what: str) -> None:
    """Refuse a record claiming more memory than ``tubeid.io.max-bytes`` (before anything is loaded)."""
    bound = limit("max-bytes")
    if nbytes > bound:
        raise SpecificationError(
            source, Described(f"{what} of {byte_size(nbytes)}"),
            f"larger than the memory limit {byte_size(bound)} for a record (configuration tubeid.io.max-bytes, "
            f"e.g. TUBEID_IO__MAX_BYTES='{byte_size(2 * nbytes)}' to read it)")


def _read_bytes(path: Path, source: str, kind: str) -> bytes:
    """The whole file, once its size is within the memory limit (text is read whole)."""
    _check_claimed(source, path.stat().st_size, f"{kind} file")
    return path.read_bytes()


# --------------------------------------------------------------------------- NetCDF / Zarr
def _claimed_bytes(ds: xr.Dataset) -> int:
    """Memory the variables of a lazily opened Dataset claim once loaded (shape × decoded dtype)."""
    return sum(math.prod(v.shape) * max(v.dtype.itemsize, 1) for v in ds.variables.values())


def _open_xarray(path: Path, source: str, engine: str, kind: str, **kw) -> xr.Dataset:
    opts = dict(engine=engine, decode_times=False, decode_timedelta=False, create_default_indexes=False, **kw)
    try:  # lazily, without indexes: nothing is read but the metadata until the size is known
        raw = xr.open_dataset(path, **opts)
    except Exception as exc:  # noqa: BLE001 - every library failure becomes a clear refusal
        try:  # a packing attribute xarray cannot even decode (scale_factor = [0.5, 2.0]): name it
            with xr.open_dataset(path, mask_and_scale=False, **opts) as plain:
                _check_packing(plain, source)
        except SpecificationError:
            raise
        except Exception:  # noqa: BLE001 - not that: the first failure is the one to tell
            pass
        _fail_read(source, kind, exc)
    with raw:
        _check_claimed(source, _claimed_bytes(raw), f"{kind} record claiming {_shapes(raw)}")
        _check_packing(raw, source)
        try:
            return raw.load()
        except Exception as exc:  # noqa: BLE001
            _fail_read(source, kind, exc)


def _check_packing(ds: xr.Dataset, source: str) -> None:
    """CF packing attributes must be numbers: xarray unpacks ``stored * scale_factor + add_offset``
    when the data are loaded, and a text one (``scale_factor = 'abc'``) would fail inside numpy."""
    for name, var in ds.variables.items():
        for attr in ("scale_factor", "add_offset"):
            for held in (var.encoding, var.attrs):
                if attr not in held:
                    continue
                value = held[attr]
                if isinstance(value, np.ndarray) and value.size == 1:
                    value = value.reshape(())[()]
                if isinstance(value, np.generic):
                    value = value.item()
                if not is_number(value) or not math.isfinite(float(value)):
                    raise SpecificationError(
                        f"{source}: {name}.{attr}", held[attr],
                        "must be a finite number (CF packing: values are read as stored * scale_factor + add_offset)")


def _shapes(ds: xr.Dataset) -> str:
    dims = ", ".join(f"{d} {n}" for d, n in ds.sizes.items())
    return f"({dims})" if dims else "no dimensions"


def _read_netcdf(path: Path, source: str) -> tuple[xr.Dataset, str]:
    if not path.is_file():
        raise SpecificationError(source, "netcdf", "a NetCDF record must be a file")
    with open(path, "rb") as fh:
        magic = fh.read(8)
    if magic.startswith(_HDF5_MAGIC):
        require("h5netcdf", "reading NetCDF-4 files")
        return _open_xarray(path, source, "h5netcdf", "NetCDF-4"), "netcdf4"
    if magic[:4] in _CDF3_MAGIC:
        # read, not memory-mapped: arrays left pointing into a mapping kept the file open past close()
        # (scipy's "Cannot close a netcdf_file opened with mmap=True" warning, printed by diagnose's workers)
        return _open_xarray(path, source, "scipy", "NetCDF-3", mmap=False), "netcdf3"
    raise SpecificationError(source, magic[:4],
                             "not a NetCDF file: neither the NetCDF-4/HDF5 nor the classic NetCDF-3 signature")


def _read_zarr(path: Path, source: str) -> xr.Dataset:
    if not path.is_dir():
        raise SpecificationError(source, "zarr", "a Zarr store must be a directory")
    ds = _open_xarray(path, source, "zarr", "Zarr", consolidated=False)
    _check_zarr_chunks(path, source, ds)
    return ds


def _check_zarr_chunks(path: Path, source: str, ds: xr.Dataset) -> None:
    """Refuse a store whose numeric arrays lack chunks: Zarr reads a missing chunk as its fill value
    (NaN, or 0, which would pass as data)."""
    import zarr

    try:
        group = zarr.open_group(path, mode="r")
        for name, var in ds.variables.items():
            if var.dtype.kind not in "iuf" or name not in group:
                continue
            arr = group[name]
            have, need = arr.nchunks_initialized, arr.nchunks
            if have < need:
                raise SpecificationError(
                    f"{source}: {name}", Described(f"{have} of {need} chunks present"),
                    "chunks are missing from the store (deleted or never written); their fill value would be "
                    "read as data")
    except SpecificationError:
        raise
    except Exception as exc:  # noqa: BLE001
        _fail_read(source, "Zarr", exc)


# --------------------------------------------------------------------------- CSV
def _decode(raw: bytes, source: str, kind: str) -> str:
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        _fail_read(source, kind, exc)


_LONE_CR = re.compile(r"\r(?=[^\n])")  # a carriage return that ends no line (a final one: a file cut inside \r\n)


def _check_line_ends(text: str, source: str) -> None:
    r"""A CSV (data or sidecar) must end its lines with ``\n`` or ``\r\n``: a lone ``\r`` (old Mac line
    endings, or a ``\r`` inside a name) is refused naming its line, never read as part of a value."""
    lone = _LONE_CR.search(text)
    if lone:
        line_no = text.count("\n", 0, lone.start()) + 1
        raise SpecificationError(
            f"{source}: line {line_no}", Described("a carriage return (\\r) not followed by \\n"),
            "must have lines ending in \\n or \\r\\n: a lone \\r ends no line here (a file saved with old Mac "
            "line endings, or a \\r inside a name); save it with \\n or \\r\\n line endings")


def _csv_error(source: str, line_no: int, exc: csv.Error):
    """A csv module error as a refusal naming the file and line (never the module's traceback)."""
    bound = csv.field_size_limit()
    if "field limit" in str(exc):
        raise SpecificationError(
            f"{source}: line {line_no}", Described(f"a field longer than {bound} characters"),
            f"a CSV field must hold at most {bound} characters (the CSV reader's limit): no name, unit or number "
            f"is that long (a damaged file, or a quote never closed?)") from None
    raise SpecificationError(f"{source}: line {line_no}", Described(str(exc)), "is not valid CSV") from None


def _check_columns(header: list[str], source: str) -> None:
    """Refuse a header naming a column twice (the reader would use one of them silently)."""
    dup = sorted(k for k, c in Counter(header).items() if c > 1)
    if dup:
        raise SpecificationError(f"{source}: header", dup,
                                 "duplicate column name(s): each column needs its own name (for a data file, each "
                                 "sensor's name is its column's)")


def _check_complete_text(text: str, source: str, header: list[str] | None) -> None:
    """A text file must end its last line with a line break: a file cut short (a truncated copy or
    download) ends inside a line, often inside a number that still parses (``-1.14`` of
    ``-1.1431685078884962e-06``), so an unterminated last line is refused, naming it."""
    if not text or text.endswith("\n"):
        return
    line_no = text.count("\n") + 1
    last = text[text.rfind("\n") + 1:]
    cells = last.split(",")
    column = len(cells) - 1
    name = header[column] if header is not None and column < len(header) else f"#{column + 1}"
    where = f"{source}: line {line_no}" + (f", column {name!r}" if header is not None else "")
    raise SpecificationError(
        where, cells[-1],
        "the file ends inside this line, without a line break: it looks cut short (a truncated copy or "
        "download), and the value may be cut too; a complete file ends every line, the last included, with a "
        "line break")


def _read_sidecar(data_path: Path, source: str, *, required: bool):
    """Rows of the sidecar as {sensor: (tube, x, units or "", scale or None)}; None if absent and not required."""
    side = sidecar_path(data_path)
    if not side.is_file():
        if required:
            raise SpecificationError(source, str(side),
                                     "sensor sidecar file is missing; it must list columns sensor,tube,x")
        return None
    sname = str(side)
    text = _decode(_read_bytes(side, sname, "sidecar"), sname, "UTF-8 CSV")
    _check_line_ends(text, sname)
    reader = csv.reader(text.split("\n"))
    lines = []  # (line number, row): a quoted field may span lines
    try:
        for row in reader:
            lines.append((reader.line_num, row))
    except csv.Error as exc:
        _csv_error(sname, reader.line_num, exc)
    header = lines[0][1] if lines else None
    if not header:
        raise SpecificationError(sname, "", "empty sidecar; header must be sensor,tube,x")
    header = [h.strip() for h in header]
    _check_complete_text(text, sname, header)
    _check_columns(header, sname)
    missing = [c for c in ("sensor", "tube", "x") if c not in header]
    if missing:
        raise SpecificationError(f"{sname}: header", header, f"sidecar lacks column(s) {missing}; needs sensor,tube,x")
    col = {c: header.index(c) for c in ("sensor", "tube", "x", "units", "scale") if c in header}
    rows: dict[str, tuple[str, float, str, float | None]] = {}
    for lineno, row in lines[1:]:
        if not row or all(not cell.strip() for cell in row):
            continue
        if len(row) != len(header):
            raise SpecificationError(f"{sname}: line {lineno}", row, f"must have {len(header)} fields")
        name, tube, xs = row[col["sensor"]].strip(), row[col["tube"]].strip(), row[col["x"]].strip()
        units = row[col["units"]].strip() if "units" in col else ""
        scale_text = row[col["scale"]].strip() if "scale" in col else ""
        if name in rows:
            raise SpecificationError(f"{sname}: line {lineno}", name, "duplicate sensor name in sidecar")
        try:
            x = float(xs) if xs else math.nan
        except ValueError:
            raise SpecificationError(f"{sname}: channel {name!r} x", xs, "must be a number (m)") from None
        scale = None
        if scale_text:
            try:
                scale = float(scale_text)
            except ValueError:
                scale = math.nan
            if not math.isfinite(scale) or scale <= 0:
                raise SpecificationError(f"{sname}: channel {name!r} scale", scale_text,
                                         "must be a finite number > 0 (the size of one count in the channel's units)")
        rows[name] = (tube, x, units, scale)
    return rows


def _csv_rows(lines: list[str], ncols: int, header: list[str], source: str, first_line: int):
    """Locate the first bad row of a CSV body (wrong field count or a value that is not a number)."""
    for k, line in enumerate(lines):
        line = line[:-1] if line.endswith("\r") else line
        if not line.strip():
            continue
        cells = line.split(",")
        where = f"{source}: line {first_line + k}"
        if len(cells) != ncols:
            raise SpecificationError(where, Described(f"{len(cells)} fields"),
                                     f"every row must have the header's {ncols} fields (time,<sensor>,...)")
        for j, cell in enumerate(cells):
            try:
                float(cell)
            except ValueError:
                raise SpecificationError(f"{where}, column {header[j]!r}", cell.strip(),
                                         "must be a number (a decimal such as -1.25e-06, or nan/inf)") from None


_NOT_INTEGER = re.compile(r"[.eEnNiI]")  # a decimal point, an exponent, nan or inf


def _integer_written(lines: list[str], column: int) -> bool:
    """Whether every value of ``column`` is written as an integer (no decimal point, exponent, nan, inf)."""
    for line in lines:
        if line.strip():
            cells = line.split(",")
            if _NOT_INTEGER.search(cells[column]):
                return False
    return True


def _read_csv(path: Path, source: str) -> xr.Dataset:
    if not path.is_file():
        raise SpecificationError(source, "csv", "a CSV record must be a file")
    text = _decode(_read_bytes(path, source, "CSV"), source, "CSV")
    _check_line_ends(text, source)
    header_line, _, body = text.partition("\n")
    try:
        header = next(csv.reader([header_line.rstrip("\r")]), None)
    except csv.Error as exc:
        _csv_error(source, 1, exc)
    if not header or not text.strip():
        raise SpecificationError(source, "", "empty CSV; the header must be time,<sensor>,...")
    header = [h.strip() for h in header]
    _check_complete_text(text, source, header)
    if header[0] != "time" or len(header) < 2:
        raise SpecificationError(f"{source}: header", header, "must be time,<sensor>,... (time in s first)")
    _check_columns(header, source)
    names = header[1:]
    channel_count(f"{source}: header", len(names))
    lines = body.split("\n")[:-1]  # the text ends with a line break (checked above)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data": refused below
            data = np.loadtxt(lines, delimiter=",", ndmin=2, dtype=float, comments=None, encoding=None)
    except ValueError as exc:
        _csv_rows(lines, len(header), header, source, first_line=2)
        _fail_read(source, "CSV of numbers", exc)  # a value numpy refuses though Python reads it (1_000)
    if data.size == 0:
        data = np.empty((0, len(header)))
    if data.shape[1] != len(header):
        _csv_rows(lines, len(header), header, source, first_line=2)
        raise SpecificationError(source, data.shape[1], f"rows must have {len(header)} fields like the header")
    side = _read_sidecar(path, source, required=True)
    extra = [s for s in side if s not in names]
    if extra:
        raise SpecificationError(str(sidecar_path(path)), extra, f"sidecar lists sensor(s) that are not columns of {source}")
    for name in names:
        if name not in side:
            raise SpecificationError(f"{source}: channel {name!r}", "position",
                                     f"sensor is missing its position: not listed in sidecar {sidecar_path(path)}")
    values = data[:, 1:]
    for j, name in enumerate(names):
        scale = side[name][3]
        col = values[:, j]
        if scale is None and col.size and np.all(np.isfinite(col)) and np.all(col == np.trunc(col)) \
                and _integer_written(lines, j + 1):
            raise SpecificationError(
                f"{source}: channel {name!r}", Described("integer values only"),
                f"integer data (counts) need an explicit scale: give the size of one count in the channel's units "
                f"in a 'scale' column of the sidecar {sidecar_path(path)} (e.g. sensor,tube,x,units,scale / "
                f"{name},centre,6.0,um,0.05), or write the values as decimals")
        if scale is not None:
            values[:, j] = col * scale
    return _raw_dataset(data[:, 0], values, names,
                        [side[s][0] for s in names], [side[s][1] for s in names], [side[s][2] or "m" for s in names])


def _raw_dataset(t, values, names, tubes, xs, units) -> xr.Dataset:
    return xr.Dataset(
        {"displacement": (("time", "sensor"), np.asarray(values, dtype=float))},
        coords={"time": ("time", np.asarray(t, dtype=float), {"units": "s"}),
                "sensor": ("sensor", np.array(names, dtype=object)),
                "x": ("sensor", np.asarray(xs, dtype=float), {"units": "m"}),
                "tube": ("sensor", np.array(tubes, dtype=object)),
                "units": ("sensor", np.array(units, dtype=object))})


# --------------------------------------------------------------------------- UFF 58
def _uff_text(value) -> str:
    s = "" if value is None else str(value).strip()
    return "" if s == "NONE" else s


def _uff_delimiters(raw: bytes) -> list[int]:
    """Offsets of the ``    -1`` lines that open and close UFF datasets, by pyuff's own rule (the tag
    ends the file, a line, or is padded with blanks to column 80)."""
    tags, i = [], -1
    while (i := raw.find(b"    -1", i + 1)) != -1:
        end = i + 6
        if end == len(raw) or raw[end] in (10, 13) or raw[end:i + 80] == b" " * 74:
            tags.append(i)
    return tags


def _check_uff_whole(raw: bytes, source: str) -> None:
    """pyuff silently drops a dataset that is not closed (a file cut short loses its last channel)."""
    tags = _uff_delimiters(raw)
    if len(tags) % 2:
        raise SpecificationError(
            f"{source}: dataset {len(tags) // 2 + 1}", Described(f"opened at byte {tags[-1]} of {len(raw)}, never closed"),
            "the file ends inside this dataset (no closing '    -1' line): it looks cut short (a truncated copy or "
            "download), and the dataset's channel would be lost")
    tail = raw[tags[-1] + 6:] if tags else raw
    if tail.strip():
        raise SpecificationError(
            source, Described(f"{len(tail.strip())} bytes after the last dataset"),
            "data outside any dataset (between '    -1' lines): a cut or damaged file")


_UFF_CHANNEL_OF = re.compile(r"^channel (\d+) of (\d+)$")
#: UFF specific data types (record 8 field 1) named in messages.
_UFF_DATA_TYPES = {0: "unknown", 1: "general", 2: "stress", 3: "strain", 5: "temperature", 6: "heat flux",
                   8: "displacement", 9: "reaction force", 11: "velocity", 12: "acceleration", 13: "excitation force",
                   15: "pressure", 16: "mass", 17: "time", 18: "frequency", 19: "rpm", 20: "order"}


def _check_uff_data_type(s: dict, unit: str, where: str) -> None:
    """The ordinate must be a displacement (module docstring): a dataset of acceleration with the label
    'm' would otherwise read as metres."""
    raw = s.get("ordinate_spec_data_type")
    kind = int(raw) if isinstance(raw, (int, np.integer)) and not isinstance(raw, bool) else None
    label = Described(f"{kind} ({_UFF_DATA_TYPES[kind]})") if kind in _UFF_DATA_TYPES else raw
    if kind == 8:
        return
    if kind in (0, 1):
        if unit in LENGTH_UNITS:
            return
        raise SpecificationError(
            f"{where} ordinate data type", label,
            f"a dataset of data type 0 (unknown) or 1 (general) is read as displacement only with a length units label "
            f"(record 9 field 6: m, mm, um, µm, micron, nm), not {unit!r}")
    raise SpecificationError(
        f"{where} ordinate data type", label,
        "must be 8 (displacement; record 8 field 1), or 0 (unknown) / 1 (general) with a length units label: tubeid "
        "reads displacement only (acceleration, velocity or strain is never read as a length)")


def _check_uff_channel_count(sets: list[dict], source: str) -> None:
    """tubeid writes ``channel k of n`` in ID line 5 of its datasets: a file cut between two of them
    (which still parses) is refused. Files concatenated whole pass (each group complete, in order);
    datasets without the line are taken as they are."""
    expected = None  # (k, n) the next dataset must carry, within a group
    for i, s in enumerate(sets):
        mark = _UFF_CHANNEL_OF.match(_uff_text(s.get("id5")))
        k, n = (int(mark.group(1)), int(mark.group(2))) if mark else (None, None)
        if expected is not None and (k, n) != expected:
            raise SpecificationError(
                f"{source}: dataset {i + 1} ID line 5", _uff_text(s.get("id5")),
                f"must read 'channel {expected[0]} of {expected[1]}': the datasets of one written record must "
                f"follow each other whole (channels lost or reordered: a truncated or edited file?)")
        if mark and (k < 1 or k > n or (expected is None and k != 1)):
            raise SpecificationError(f"{source}: dataset {i + 1} ID line 5", _uff_text(s.get("id5")),
                                     "a record written as 'channel k of n' must start at channel 1")
        expected = (k + 1, n) if mark and k < n else None
    if expected is not None:
        raise SpecificationError(
            f"{source}: dataset {len(sets)}", _uff_text(sets[-1].get("id5")),
            f"the file ends before 'channel {expected[0]} of {expected[1]}': channels are missing (a file cut "
            f"short between datasets?)")


def _read_uff(path: Path, source: str) -> xr.Dataset:
    pyuff = require("pyuff", "reading UFF 58 files")

    if not path.is_file():
        raise SpecificationError(source, "uff", "a UFF record must be a file")
    _check_uff_whole(_read_bytes(path, source, "UFF"), source)
    try:
        uff = pyuff.UFF(str(path))
        types = list(uff.get_set_types())
    except Exception as exc:  # noqa: BLE001
        _fail_read(source, "UFF", exc)
    sets = []
    for i, kind in enumerate(types):
        if int(kind) == 58:
            try:
                sets.append(uff.read_sets(i))
            except Exception as exc:  # noqa: BLE001
                _fail_read(f"{source}: dataset {i + 1}", "UFF 58", exc)
    if not sets:
        raise SpecificationError(source, [int(k) for k in types], "no type-58 dataset (function at nodal DOF) found")
    channel_count(f"{source}: type-58 datasets", len(sets))
    _check_uff_channel_count(sets, source)
    side = None
    names, tubes, xs, units, columns = [], [], [], [], []
    t_ref, ref_name = None, None
    for k, s in enumerate(sets):
        name = _uff_text(s.get("id1")) or f"node{s.get('rsp_node')}dir{s.get('rsp_dir')}"
        where = f"{source}: channel {name!r}"
        if int(s.get("func_type", -1)) != 1:
            raise SpecificationError(f"{where} function type", s.get("func_type"),
                                     "must be 1 (time response; record 6 field 1)")
        data = np.asarray(s["data"])
        if np.iscomplexobj(data):
            raise SpecificationError(f"{where} data", str(data.dtype), "must be real (a time response)")
        declared = s.get("num_pts")
        if not isinstance(declared, (int, np.integer)) or data.shape != (declared,) or np.shape(s["x"]) != (declared,):
            raise SpecificationError(
                f"{where} data", Described(f"{data.size} values and {np.size(s['x'])} abscissae"),
                f"the dataset header (record 7) declares {declared}: the dataset is incomplete or damaged")
        if int(s.get("abscissa_spec_data_type", 0)) not in (0, 17) or \
                _uff_text(s.get("abscissa_axis_units_lab")) not in ("", "s", "sec", "second", "seconds"):
            raise SpecificationError(f"{where} abscissa", (s.get("abscissa_spec_data_type"),
                                     s.get("abscissa_axis_units_lab")), "abscissa must be time in s")
        t = np.asarray(s["x"], dtype=float)
        if t_ref is None:
            t_ref, ref_name = t, name
        elif t.shape != t_ref.shape or not np.array_equal(t, t_ref):
            raise SpecificationError(f"{where} time axis", f"{t.size} samples",
                                     f"must be identical for all channels (differs from channel {ref_name!r})")
        unit = _uff_text(s.get("ordinate_axis_units_lab"))
        if not unit:
            raise SpecificationError(f"{where} units", unit or None,
                                     "units missing: the ordinate units label (record 9 field 6) must be one of "
                                     "m, mm, um, µm, micron, nm")
        _check_uff_data_type(s, unit, where)
        id4 = _uff_text(s.get("id4"))
        mt, mx = _UFF_TOKEN_TUBE.search(id4), _UFF_TOKEN_X.search(id4)
        if (mt is None) != (mx is None):
            raise SpecificationError(f"{where} ID line 4", id4, "must hold both tube=<name> and x=<metres>")
        if side is None:
            side = _read_sidecar(path, source, required=False) or {}
        if name in side and side[name][3] is not None:
            raise SpecificationError(f"{sidecar_path(path)}: channel {name!r} scale", side[name][3],
                                     "a scale applies to integer CSV columns only; UFF 58 holds real numbers")
        if name in side and side[name][2]:
            side_unit = side[name][2]
            if length_scale(side_unit, f"{sidecar_path(path)}: channel {name!r} units") != length_scale(
                    unit, f"{where} units"):
                raise SpecificationError(f"{where} units", unit,
                                         f"conflicts with sidecar {sidecar_path(path)} units {side_unit!r}")
        if mt is not None:
            tube = mt.group(1)
            try:
                x = float(mx.group(1))
            except ValueError:
                raise SpecificationError(f"{where} ID line 4 x", mx.group(1), "must be a number (m)") from None
            if name in side:
                st, sx = side[name][:2]
                if st != tube or not math.isclose(sx, x, rel_tol=1e-9, abs_tol=1e-12):
                    raise SpecificationError(f"{where} position", (tube, x),
                                             f"conflicts with sidecar {sidecar_path(path)} ({st!r}, {sx!r})")
        elif name in side:
            tube, x = side[name][:2]
        else:
            raise SpecificationError(
                f"{where} position", id4 or None,
                f"sensor is missing its position: ID line 4 must read 'tube=<name> x=<metres>' "
                f"or sidecar {sidecar_path(path)} must list the channel")
        names.append(name)
        tubes.append(tube)
        xs.append(x)
        units.append(unit)
        columns.append(data)
    extra = [s for s in side if s not in names]
    if extra:
        raise SpecificationError(str(sidecar_path(path)), extra, f"sidecar lists sensor(s) that are not channels of {source}")
    return _raw_dataset(t_ref, np.stack([np.asarray(c, dtype=float) for c in columns], axis=1),
                        names, tubes, xs, units)


# --------------------------------------------------------------------------- public API
def _as_path(path, what: str) -> Path:
    try:
        return Path(os.fspath(path))
    except TypeError:
        raise SpecificationError(what, path, "must be a file path") from None


def _checked_path(path: Path, fmt: str, field: str) -> None:
    """Refuse a record path the file system cannot look up (a name too long, a loop of links), and a
    NetCDF or Zarr path xarray or zarr would read as a URL of another file system (``a::b.nc`` opens
    ``a:``): :func:`tubeid._paths.local_path`, before anything is opened."""
    kind = "directory" if fmt == "zarr" else "file"
    if fmt in ("netcdf", "netcdf3", "zarr"):
        local_path(path, field=field, kind=kind)
    else:  # CSV and UFF are opened by Python itself, by their literal name
        looked_up(path, field=field, kind=kind)


def read_measurements(path: str | os.PathLike, *, format: str | None = None, min_resolution_hz: float | None = None,
                      tubes: Mapping[str, float] | None = None) -> xr.Dataset:
    """Read a measured record (NetCDF, Zarr, CSV + sidecar or UFF 58) into the canonical Dataset.

    Parameters
    ----------
    path : str or path-like
        The record (a file, or a directory for Zarr).
    format : str, optional
        One of :data:`FORMATS` (default: from the extension, :data:`EXTENSIONS`).
    min_resolution_hz : float, optional
        Refuse records shorter than 1 / min_resolution_hz (s).
    tubes : mapping, optional
        {tube name: length (m)}; refuse sensors on unknown tubes or off them.

    Returns
    -------
    xarray.Dataset
        The canonical form (module docstring): ``displacement`` (time, sensor) in m, float64.

    Raises
    ------
    SpecificationError
        Naming the file, line/channel and rule, for every refusal of the module docstring
        (incomplete files, limits, units, time, samples); never a library traceback.
    """
    path = _as_path(path, "path")
    source = str(path)
    check_options(min_resolution_hz, tubes)
    fmt = _resolve_format(path, format)
    _checked_path(path, fmt, "data")
    if not path.exists():
        raise SpecificationError(source, fmt, "file does not exist")
    if fmt in ("netcdf", "netcdf3"):
        raw, label = _read_netcdf(path, source)
    elif fmt == "zarr":
        raw, label = _read_zarr(path, source), "zarr"
    elif fmt == "csv":
        raw, label = _read_csv(path, source), "csv"
    else:
        raw, label = _read_uff(path, source), "uff58"
    return validate_measurements(raw, min_resolution_hz=min_resolution_hz, tubes=tubes, source=source, format=label)


def _strings_as_objects(ds: xr.Dataset) -> xr.Dataset:
    out = ds.copy()
    for name, var in ds.variables.items():
        if var.dtype.kind in "US" or var.dtype.kind == "T":
            out[name] = var.copy(data=np.array([str(v) for v in np.asarray(var.values).ravel()],
                                               dtype=object).reshape(var.shape))
    return out


def _write_csv(lay: dict, path: Path) -> None:
    names, x_m = lay["names"], _x_metres(lay, path)
    for what, values in (("sensor name", names), ("tube name", lay["tube"])):  # a tube may be absent ("")
        for name in values:
            if name != name.strip() or any(c in name for c in "\r\n") or (not name and what == "sensor name"):
                raise SpecificationError(f"{path}: {what}", name, "cannot be written to CSV faithfully")
    with open(path, "w", newline="", encoding="utf-8") as fh:
        csv.writer(fh, lineterminator="\n").writerow(["time", *names])
        np.savetxt(fh, np.column_stack([lay["time"], lay["values"]]), delimiter=",", fmt="%.17g")
    with open(sidecar_path(path), "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(["sensor", "tube", "x", "units"])
        for j, name in enumerate(names):
            x = x_m[j]
            units = lay["units"][j]
            w.writerow([name, lay["tube"][j], "" if not math.isfinite(x) else repr(float(x)),
                        "" if units is None else units])


def _x_metres(lay: dict, path: Path) -> np.ndarray:
    """Sensor positions in m (NaN where absent)."""
    if lay["x_units"] is None:
        return lay["x"]
    return lay["x"] * length_scale(lay["x_units"], f"{path}: x.units")


def _write_uff(lay: dict, path: Path) -> None:
    pyuff = require("pyuff", "writing UFF 58 files")

    t, values, x_m = lay["time"], lay["values"], _x_metres(lay, path)
    if not np.all(np.isfinite(values)) or not np.all(np.isfinite(t)):
        raise SpecificationError(f"{path}: displacement", "non-finite",
                                 "UFF cannot hold NaN or infinite samples (pyuff would write them as numbers)")
    if t.size < 2:
        raise SpecificationError(f"{path}: time", t.size, "UFF 58 needs at least 2 samples")
    sets = []
    for j, name in enumerate(lay["names"]):
        tube = lay["tube"][j]
        x = x_m[j]
        if not name or name != name.strip() or len(name) > 80 or not name.isprintable():
            raise SpecificationError(f"{path}: sensor name", name, "UFF ID line 1 needs 1-80 printable characters")
        if tube and (re.search(r"\s", tube) or "=" in tube):
            raise SpecificationError(f"{path}: channel {name!r} tube", tube, "UFF tube names must have no spaces or '='")
        id4 = f"tube={tube} x={float(x)!r}" if tube and math.isfinite(x) else ""
        unit = lay["units"][j]
        unit = "" if unit is None else str(unit).replace("\u00b5", "u").replace("\u03bc", "u")
        if len(id4) > 80 or len(unit) > 20 or not unit.isascii():
            raise SpecificationError(f"{path}: channel {name!r}", (id4, unit), "does not fit UFF 58 fixed fields")
        sets.append(pyuff.prepare_58(
            binary=1, id1=name, id2="tubeid measured displacement", id3="", id4=id4,
            id5=f"channel {j + 1} of {len(lay['names'])}",
            func_type=1, rsp_node=j + 1, rsp_dir=0, ref_node=0, ref_dir=0,
            abscissa_spacing=0, abscissa_spec_data_type=17, abscissa_axis_units_lab="s",
            ordinate_spec_data_type=8, ordinate_len_unit_exp=1, ordinate_axis_units_lab=unit or "NONE",
            orddenom_spec_data_type=0, data=np.array(values[:, j], dtype=float), x=np.array(t, dtype=float)))
    # pyuff truncates the header of the first binary set in 'overwrite' mode: start from an empty
    # file and append every set instead.
    # pyuff also leaves a file handle to the garbage collector (ResourceWarning): silenced here.
    path.write_bytes(b"")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ResourceWarning)
        pyuff.UFF(str(path)).write_sets(sets, mode="add")


def write_measurements(ds: xr.Dataset, path: str | os.PathLike, *, format: str | None = None,
                       validate: bool = True) -> Path:
    """Write a measured record as NetCDF-4, NetCDF-3, Zarr, CSV + sidecar or UFF 58 (module docstring).

    Parameters
    ----------
    ds : xarray.Dataset
        The record: ``displacement`` (time, sensor) with ``x`` and ``tube`` on ``sensor``.
    path : str or path-like
        Where to write (a directory for Zarr). An existing file is replaced; an existing directory
        that is not a Zarr store is refused.
    format : str, optional
        One of :data:`FORMATS` (default: from the extension, :data:`EXTENSIONS`).
    validate : bool
        If True (default) ``ds`` is first validated and written in canonical form (m, s), so
        ``read_measurements`` gives it back; False writes ``ds`` as it is (units included), e.g. to
        make test files; the structure must still be readable.

    Returns
    -------
    pathlib.Path
        The path written.
    """
    path = _as_path(path, "path")
    fmt = _resolve_format(path, format)
    _checked_path(path, fmt, "path")
    if validate:
        ds = validate_measurements(ds)
    lay = layout(ds, str(path))
    if fmt in ("netcdf", "netcdf3"):
        if path.is_dir():
            raise SpecificationError(str(path), fmt, "is a directory, cannot write NetCDF there")
        kw = {"engine": "scipy", "format": "NETCDF3_64BIT"} if fmt == "netcdf3" else {"engine": "h5netcdf"}
        if fmt == "netcdf":
            require("h5netcdf", "writing NetCDF-4 files")
        ds.to_netcdf(path, **kw)
    elif fmt == "zarr":
        if path.exists() and not (path.is_dir() and any((path / m).exists() for m in ("zarr.json", ".zgroup"))):
            raise SpecificationError(str(path), "zarr", "exists and is not a Zarr store; refusing to overwrite it")
        _strings_as_objects(ds).to_zarr(path, mode="w", consolidated=False)
    elif fmt == "csv":
        _write_csv(lay, path)
    else:
        _write_uff(lay, path)
    return path
