"""Close the loop with measured data: a calibrated test, then the effects the model lacks, several at once.

``diagnose(data, model)`` on a validated record (``displacement`` (time, sensor) [m] with ``x``
and ``tube`` on ``sensor``) for a declared model. Every Monte Carlo realisation and every trial of a
grid is a task of the runner pipeline :mod:`tubeid.diagnose.stages` (one Zarr store in ``out``,
resumable); this module holds the context every stage reads and assembles the report.

1. **Split.** The record is cut into ``blocks`` equal time blocks; the even ones fit, the odd ones
   are held out. Welch auto-PSDs (two-sided per Hz) of each set (:mod:`tubeid.diagnose._spectra`).
2. **Model uncertainty δ** (B's stiffness): given (``delta``, default 0.2), or identified by the
   paper's maximum likelihood of J when a reference model exists (``delta_reference``: J_ref of
   that model against the Monte Carlo of J(δ) of the declared one; MODEL.md §3.2). Not from the
   record: one record is one structure, so its blocks cannot show a spread of structures, and a
   δ fitted to them would absorb the very effect the diagnosis looks for.
3. **Load** on the fitting blocks: r by a coarse-then-fine trial method, δ_F by maximum likelihood
   of J_s when there are enough fitting blocks (:mod:`tubeid.diagnose._load`).
4. **Detection**: the held-out record against R realisations of the declared stochastic model at
   (δ, δ_F, r): a Monte Carlo test, exact at the stated false-alarm rate
   (:mod:`tubeid.diagnose._detection`). Its statistics depend on what the declared model is taken
   to be (``model_form``): *exact* — a scan for lines, a goodness-of-fit of log band energies, the
   sharpness of resonances and, when added mass is a candidate, the spectral profile along another
   tube's added mass; *simplified* (the default when δ is identified against a reference
   model) — only what a simplified model is trusted for: lines at a fine resolution, the flatness
   of the sensors' incoherent floor, the kurtosis of each sensor, the sharpness of the in-band
   resonances, the log-log slope of the in-band spectrum; each of these points to the catalog
   effect that can explain it. Not detected: the answer is ``none``.
5. **Forward selection** (:mod:`tubeid.diagnose._selection`): at each step every catalog effect not
   yet chosen (:mod:`tubeid.diagnose.catalog`) is placed and sized from its signature, fitted by a
   trial grid of the mean model on the fitting blocks (the chosen effects held, the level
   profiled), and judged by its held-out error; the best penalised one is added if it improves on
   the current model (with a simplified model: only the effects the firing statistics point to,
   each judged by its statistic's feature instead of the whole spectrum, relative to the current
   model's error in that feature, r held); then all chosen effects and r are **re-fitted jointly** (one cross-design
   sweep: each parameter and r along a line of 3 trials around the current point, the others
   held — a tone's amplitude along its profile, derived from the centre and one trial without the
   tone, as in the trial grid; each moved to its line's parabola vertex; the moved point is then evaluated, and if its
   fitting-block error is worse than the best point the lines evaluated — the moves overshoot when
   parameters trade off — that point is kept instead; a scale line whose best is at its end is
   extended one step, evaluated beside the moved point, and kept if better than both; where a line
   did not bracket its minimum or the moved point was not kept, a second sweep of the same lines
   runs around the kept point — alternating, since r and e.g. a stop's gap trade off and lines
   evaluated one at a time mis-place both), and the augmented model's band is tested again, at ``continuation_alarm`` (default α / (``max_effects`` −
   1): the tests that could continue the loop share α, so on a record the chosen effects explain they
   raise an alarm, and so a spurious further effect, with probability at most α; the near-tie rule
   below adds a runner-up without an alarm). The loop stops when the test no longer detects
   anything (``explained``), when no
   candidate pays its penalty, or after ``max_effects`` steps — except that a runner-up which also
   paid its penalty within ``tie`` (10 %) of the chosen one's ratio at an earlier step, and was
   never chosen, is first offered once more, alone (``stages.runner_ups``): the data could not order
   the two, and the first one fitted can pull the record inside the band (B's random stiffness)
   with the second one missing.

``report.json``: ``effect`` (the first effect's name, or ``none``), ``effects`` ([{name,
parameters}]), ``detection`` (p-values before), ``steps`` (per step: the candidates' errors, the
``continuation`` that offered them after an explained step (or null), the choice, the re-fitted
effects and r, ``refit`` and ``refit_check`` (the first sweep's lines; the moved point's, the best evaluated
point's and the extended point's fitting errors, which ``point`` was kept, ``fallback``), ``refit_sweeps``
(every sweep's ``lines``, ``check`` and the ``reason`` it ran), the held-out error and the test after), ``error_before``,
``error_after``, ``explained_before``/``explained_after``, ``load``, ``delta``, ``assumptions``.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import xarray as xr

from tubeid._outputs import OutputDir
from tubeid.diagnose._settings import DiagnoseSettings
from tubeid.diagnose._simulate import load_dimension, spec_for
from tubeid.diagnose._spectra import MeasuredSpectra, measured_spectra
from tubeid.dynamics.spectra import j_s
from tubeid.errors import SpecificationError
from tubeid.mechanics.effects import effect_from_dict, effect_to_dict
from tubeid.mechanics.library import resolve_spec
from tubeid.mechanics.spec import BundleSpec, spec_from_dict, spec_to_dict
from tubeid.runner._terms import Terms, speaking
from tubeid.uncertainty.random_matrices import delta_max

__all__ = ["DiagnoseContext", "Diagnosis", "diagnose", "load_context", "data_hash", "effects_to_json",
           "effects_from_json", "STAGES_FILE", "STORE_NAME", "ERROR_METRIC"]

#: The runner pipeline definition run by :func:`diagnose` (workers load it by its source text).
STAGES_FILE = Path(__file__).with_name("stages.py")
#: The pipeline store's name in the output directory.
STORE_NAME = "diagnose.zarr"

#: What ``error_before`` / ``error_after`` measure (one sentence, written into report.json).
ERROR_METRIC = (
    "mean over sensors and 0 < f < f_Nyquist of ((log10 S_held_out - log10 S_mean_model - o) / sigma)^2: the held-out "
    "PSD against the mean model's prediction in units of the declared stochastic model's own scatter sigma of log10 "
    "PSD per bin and sensor (the band before any effect); o the level offset fitted on the fitting blocks")


def data_hash(data: xr.Dataset) -> str:
    """SHA-256 of a validated record's content: time, displacement (time × sensor), sensor names,
    positions and tubes (independent of the file format and of attributes)."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(data["time"].values, dtype="<f8").tobytes())
    h.update(np.ascontiguousarray(data["displacement"].transpose("time", "sensor").values, dtype="<f8").tobytes())
    h.update(json.dumps([[str(s) for s in data["sensor"].values], [float(x) for x in data["x"].values],
                         [str(x) for x in data["tube"].values]]).encode())
    return h.hexdigest()


def effects_from_json(text: str) -> list:
    """Effects from their JSON list form (``effect_to_dict``)."""
    return [effect_from_dict(e, f"effects[{i}]") for i, e in enumerate(json.loads(text))]


def effects_to_json(effects) -> str:
    return json.dumps([effect_to_dict(e) for e in effects], sort_keys=True)


@dataclass(frozen=True)
class DiagnoseContext:
    """What every stage and task of a diagnosis reads: ``settings``, the declared model ``spec0``
    and ``spec`` (with the data's sensors), the spectra ``meas``, the load dimension ``m`` and the
    observed J_s per fitting block ``j_s_observed`` [(m²/Hz)²·rad/s]."""

    settings: DiagnoseSettings
    spec0: BundleSpec
    spec: BundleSpec
    meas: MeasuredSpectra
    m: int
    j_s_observed: np.ndarray

    @property
    def delta_f_grid(self) -> tuple[float, ...]:
        from tubeid.diagnose._load import default_delta_f_grid

        return self.settings.delta_f_grid or default_delta_f_grid(self.m)

    @property
    def identify_delta_f(self) -> bool:
        """δ_F is identified (not given) and the record has enough fitting blocks to try."""
        return self.settings.load_dispersion is None and self.meas.n_fit_blocks >= self.settings.delta_f_min_blocks

    @property
    def candidate_names(self) -> tuple[str, ...]:
        """The catalog effects considered: ``settings.candidates`` (default all); with the simplified
        form, only those a robust statistic points to (the others have no feature to be fitted to)."""
        from tubeid.diagnose._detection import STATISTICS
        from tubeid.diagnose.catalog import CATALOG

        names = self.settings.candidates or tuple(CATALOG)
        if self.settings.form == "simplified":
            seen = {e for st in STATISTICS.values() if st.robust for e in st.effects}
            names = tuple(n for n in names if n in seen)
        return names


def _context(data: xr.Dataset, spec0: BundleSpec, settings: DiagnoseSettings) -> DiagnoseContext:
    t = np.asarray(data["time"].values, dtype=float)
    dt = float((t[-1] - t[0]) / (t.size - 1))
    if 1.0 / (2.0 * dt) < spec0.band_hz:
        raise SpecificationError("data dt", dt, f"the Nyquist frequency 1/(2 dt) must reach the model band {spec0.band_hz} Hz")
    f_max = settings.max_frequency_hz
    if f_max is not None and not spec0.band_hz < f_max < 1.0 / (2.0 * dt):
        raise SpecificationError("settings.max_frequency_hz", f_max,
                                 f"must lie above the model band {spec0.band_hz} Hz and below the record's Nyquist "
                                 f"frequency 1/(2 dt) = {1.0 / (2.0 * dt):.6g} Hz")
    meas = measured_spectra(data, settings.blocks, settings.segment_seconds, settings.fine_segment_seconds, f_max)
    spec = spec_for(spec0, meas.sensors, meas.tube, meas.x)
    m = load_dimension(spec, settings)
    dmax = delta_max(m)
    for name in ("load_dispersion", "delta_f_fallback"):
        v = getattr(settings, name)
        if v is not None and v >= dmax:
            raise SpecificationError(f"settings.{name}", v, f"must be < δ_max = {dmax:.4f} for the {settings.load} load "
                                     f"(SG+ of size m = {m})")
    from tubeid.diagnose._load import default_delta_f_grid

    grid = settings.delta_f_grid or default_delta_f_grid(m)
    if max(grid) >= dmax:
        raise SpecificationError("settings.delta_f_grid", grid, f"must lie in (0, {dmax:.4f}) for the {settings.load} load "
                                 f"(m = {m})")
    if settings.delta_reference is not None:  # refused here if unknown, naming the setting (not the declared model)
        try:
            resolve_spec(settings.delta_reference)
        except SpecificationError as exc:
            rule = exc.rule if exc.value == settings.delta_reference else str(exc)  # a field inside its file: kept
            raise SpecificationError("settings.delta_reference", settings.delta_reference, rule) from None
    if settings.form == "simplified" and meas.fine_seconds < settings.segment_seconds - meas.dt:
        raise SpecificationError("settings.fine_segment_seconds", settings.fine_segment_seconds,
                                 f"half a block of this record is {meas.fine_seconds:.4g} s, shorter than segment_seconds = "
                                 f"{settings.segment_seconds} s: use fewer blocks, a shorter segment_seconds or a longer record")
    from tubeid.mechanics.reduction import reduce

    n_b = reduce(spec).subsystem.n
    if settings.delta >= delta_max(n_b):
        raise SpecificationError("settings.delta", settings.delta, f"must be < δ_max = {delta_max(n_b):.4f} for the "
                                 f"declared model's reduced B (n = {n_b})")
    obs = j_s(meas.frequency, meas.fit_cross, band=spec.band_hz)
    ctx = DiagnoseContext(settings=settings, spec0=spec0, spec=spec, meas=meas, m=m, j_s_observed=np.atleast_1d(obs))
    if settings.max_effects > 0 and not ctx.candidate_names:
        raise SpecificationError("settings.candidates", settings.candidates,
                                 f"none of them is a candidate of the {settings.form} model form (no statistic it is "
                                 "trusted for points to them); give others or max_effects = 0")
    return ctx


_CONTEXTS: dict[tuple, DiagnoseContext] = {}


def load_context(data: str, data_sha256: str, model: str, settings: str) -> DiagnoseContext:
    """The context of a diagnosis from the pipeline's plain parameters (cached per process):
    ``data`` the path of the validated record, ``data_sha256`` its :func:`data_hash` (refused if
    the file no longer matches), ``model`` the declared model as JSON (``spec_to_dict``),
    ``settings`` :meth:`DiagnoseSettings.to_json`."""
    key = (data, data_sha256, model, settings)
    if key not in _CONTEXTS:
        from tubeid.measured.readers import read_measurements

        if not data:
            raise SpecificationError("parameters.data", data, "the pipeline needs the path of the record")
        spec0 = spec_from_dict(json.loads(model))
        ds = read_measurements(data, tubes={t.name: t.length for t in spec0.tubes})
        if data_hash(ds) != data_sha256:
            raise SpecificationError("data", data, f"its content changed since this diagnosis started (sha256 {data_sha256[:12]})")
        _CONTEXTS[key] = _context(ds, spec0, DiagnoseSettings.from_json(settings))
    return _CONTEXTS[key]


# ----------------------------------------------------------------------------------------------
# The result
# ----------------------------------------------------------------------------------------------


@dataclass
class Diagnosis:
    """Result of :func:`diagnose`.

    Parameters
    ----------
    report : dict
        What report.json holds (module docstring).
    frequency : numpy.ndarray
        (F,) [Hz], the Welch bins of the spectra.
    measured : numpy.ndarray
        (F, m) the record's held-out auto-PSD [m²/Hz, two-sided].
    sensors : tuple
        The sensors' names (m).
    bands : dict
        {label: (lower, upper)} of the model's band before and after, each (F, m), at
        ``settings.level`` (the figure's).
    store : pathlib.Path or None
        The pipeline store (None when it lived in a temporary directory).
    """

    report: dict
    frequency: np.ndarray
    measured: np.ndarray
    sensors: tuple
    bands: dict
    store: Path | None = None

    @property
    def effect(self) -> str:
        return self.report["effect"]

    @property
    def effects(self) -> list[str]:
        return [e["name"] for e in self.report["effects"]]

    def write(self, out: str | os.PathLike) -> Path:
        """Write report.json, report.md, residual.png (and delta_f.png when δ_F was identified)
        into directory ``out`` (through its manifest: a file tubeid did not write is never
        replaced).

        Parameters
        ----------
        out : str or os.PathLike
            The output directory.

        Returns
        -------
        pathlib.Path
            The directory written.

        Raises
        ------
        MissingDependencyError
            Without matplotlib (the figures), before any file is written.
        """
        from tubeid.diagnose.report import write_files

        return write_files(self, out)


# ----------------------------------------------------------------------------------------------
# The run
# ----------------------------------------------------------------------------------------------


def _resolve_data(data, spec0: BundleSpec) -> tuple[xr.Dataset, Path | None]:
    tubes = {t.name: t.length for t in spec0.tubes}
    if isinstance(data, xr.Dataset):
        from tubeid.measured.validation import validate_measurements

        return validate_measurements(data, tubes=tubes), None
    from tubeid.measured.readers import read_measurements

    return read_measurements(data, tubes=tubes), Path(data)


def _check_store(store: Path, key: str, overrides: dict | None = None) -> None:
    """Refuse a store in ``out`` made from other data, model or settings, or by another version of
    the diagnosis (its pipeline source, ``stages.py``), before any work."""
    if not store.exists():
        return
    from tubeid.runner.store import read_attrs

    try:
        attrs = read_attrs(store)
    except Exception:
        raise SpecificationError("out", str(store.parent), f"{store.name} exists but is not a diagnosis store; "
                                 "choose another --out") from None
    if attrs.get("study_hash") != key:
        try:
            same_inputs = overrides is not None and json.loads(attrs.get("parameters", "{}")) == overrides
        except (TypeError, ValueError):
            same_inputs = False
        what = (f"the same data, model and settings diagnosed by another version of tubeid's diagnosis (written by "
                f"tubeid {attrs.get('tubeid_version')}; its stages changed since)") if same_inputs else \
            "a diagnosis of other data, model or settings"
        raise SpecificationError(
            "out", str(store.parent),
            f"holds {what} ({store.name}, hash {str(attrs.get('study_hash'))[:12]} vs {key[:12]} now): refusing to "
            "mix them; choose another --out or use --overwrite")


#: Signatures of classic NetCDF-3 files (CDF-1, CDF-2): the format of the record's copy.
_NETCDF3_MAGIC = (b"CDF\x01", b"CDF\x02")


def _copy_bytes(data: xr.Dataset) -> bytes:
    """The validated record as the copy the pipeline reads: NetCDF-3 (64-bit offset), written through
    scipy, so that the core install writes and reads it (NetCDF-4 needs the ``io`` extra). It keeps
    what the diagnosis reads, exactly: float64 time, displacement and x, the sensor and tube names
    (UTF-8), so :func:`data_hash` of the copy is the record's."""
    from tubeid.measured.readers import write_measurements

    with tempfile.TemporaryDirectory(prefix="tubeid-diagnose-") as tmp:
        path = write_measurements(data, Path(tmp) / "record.nc", format="netcdf3")
        return path.read_bytes()


def _is_netcdf3(path: Path) -> bool:
    with open(path, "rb") as fh:
        return fh.read(4) in _NETCDF3_MAGIC


def _check_outputs(outdir: OutputDir, names, removed=()) -> None:
    """Refuse, before any work, to write over a file tubeid did not write (or that changed since);
    ``removed``: the names an ``--overwrite`` will remove first (they are in the way of nothing)."""
    for name in names:
        p = outdir.path / name
        if name not in removed and (p.exists() or p.is_symlink()) and not outdir.owned(name):
            raise SpecificationError(f"{outdir.field}/{name}", str(p),
                                     "exists and was not written by tubeid (or was changed since): it is left untouched; "
                                     f"move it or choose another --{outdir.field}")


def _check_out(out, source: Path | None) -> None:
    """Refuse ``out`` before anything is created: a path zarr would read as a URL (:func:`local_path`),
    or the record being diagnosed itself or a directory inside it (a Zarr record is the user's data:
    tubeid never writes into it). A directory that holds the record (its own directory, ``--out .``)
    is fine: the record in it is never touched."""
    from tubeid._paths import local_path

    target = os.path.realpath(local_path(out, field="out"))
    if source is None:
        return
    record = os.path.realpath(source)
    if target == record or target.startswith(record.rstrip(os.sep) + os.sep):
        where = "is the record being diagnosed" if target == record else "lies inside the record being diagnosed"
        raise SpecificationError("out", os.fspath(out), f"{where} ({os.fspath(source)}): tubeid never writes into the "
                                 "user's record; choose another --out (the record's own directory is fine)")


#: the runner's refusals about the store, worded in ``tubeid diagnose``'s options: its store is ``--out``'s
#: ``diagnose.zarr`` (no ``--store``, no ``--new-store``: a new store is another ``--out``)
_TERMS = Terms(store=f"out/{STORE_NAME}", option="--out", elsewhere="choose another --out", beside="choose another --out",
               rebuild="`tubeid diagnose` with the same --out", changed="other data, model or settings")


def _refuse_store_in_use(store: Path) -> None:
    """Refuse a store whose lock a live run holds (a ``tubeid run`` on it, or a diagnosis by an earlier
    tubeid, which locked only its store), before anything in ``--out`` is removed or written."""
    from tubeid.runner.lock import refuse_if_held

    if store.is_dir() and not store.is_symlink():
        refuse_if_held(store, field=f"out/{STORE_NAME}", advice=_WAIT.format(store=store))


#: what to do about a diagnosis directory (or its store) another run holds
_WAIT = "wait for it to finish (`tubeid status {store}` shows its progress) or choose another --out"


def diagnose(data: xr.Dataset | str | os.PathLike, model: str | BundleSpec = "paper-simplified",
             settings: DiagnoseSettings = DiagnoseSettings(), *, out: str | os.PathLike | None = None,
             workers: int | None = 0, scheduler: str | None = None, overwrite: bool = False,
             progress: bool | None = False, quiet: bool = True) -> Diagnosis:
    """Run the loop of the module docstring.

    Parameters
    ----------
    data : xarray.Dataset or path
        A record: a Dataset (validated here) or a file readable by
        :func:`tubeid.measured.read_measurements`. Never modified, moved or deleted.
    model : str or BundleSpec
        The declared model: built-in name, specification file or :class:`BundleSpec` (without
        carried effects).
    settings : DiagnoseSettings
    out : path, optional
        Output directory: the pipeline store ``diagnose.zarr``, the validated record it reads
        (``data-<sha256[:16]>.nc``, NetCDF-3: the core install writes and reads it) and the report
        files, all recorded in its manifest. Running
        again with the same data, model and settings resumes or reuses the store; other ones are
        refused unless ``overwrite``, which removes only what the manifest lists, unchanged (and
        replaces the store), and only once every check has passed: a refused run removes and writes
        nothing. One diagnosis at a time in a directory (a lock, ``.tubeid-lock``, held from the first
        check to the last file; a run holding the store's lock counts too): another is refused before
        it touches anything. Refused before anything is created: a path zarr reads as a URL (``::``,
        ``://``), the record itself or a directory inside it (a directory holding the record is fine:
        the record is never touched). Default: a temporary directory, removed afterwards (no files written). The report
        files include figures, which need matplotlib (the ``plot`` extra): without it a given ``out``
        is refused before any work, as ``tubeid diagnose`` is; ``out=None`` does not need it.
    workers : int or None
        0 (default): every task in this process; N > 0: an embedded LocalCluster of N
        single-threaded workers; None: the runner's default unless ``scheduler`` is given.
    scheduler : str, optional
        Address of an existing dask scheduler.
    overwrite, progress, quiet
        See above; the runner's progress bars and messages.

    Returns
    -------
    Diagnosis

    Raises
    ------
    MissingDependencyError
        ``out`` given without matplotlib (the figures), before anything is read, run or written.
    """
    if out is not None:  # the figures: refused before any work, like the command line
        from tubeid._optional import require

        require("matplotlib", "tubeid diagnose")
    from tubeid.runner.execute import run
    from tubeid.runner.study import study_hash

    if not isinstance(settings, DiagnoseSettings):
        raise SpecificationError("settings", type(settings).__name__, "must be a DiagnoseSettings")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 0):
        raise SpecificationError("workers", workers, "must be a non-negative integer")
    if out is not None:  # before anything is read or created
        _check_out(out, None if isinstance(data, xr.Dataset) else data)
    spec0 = resolve_spec(model)
    if spec0.effects:
        raise SpecificationError("model.effects", spec0.effects, "diagnose a model without carried effects")
    for i, t in enumerate(spec0.tubes):
        if t.damping_ratio == 0:
            raise SpecificationError(f"model.tubes[{i}].damping_ratio", t.damping_ratio,
                                     f"tube {t.name!r} is declared undamped: a diagnosis needs every tube damped "
                                     "(> 0; a measured bundle is), since the damping candidate scales the declared "
                                     "ratio and J of an undamped subsystem B is infinite")
    data, source = _resolve_data(data, spec0)
    ctx = _context(data, spec0, settings)  # everything that can be refused, before any run
    h = data_hash(data)
    from tubeid import config

    config.check()  # the runner's configuration too, before anything in out is removed or written

    tmp = tempfile.TemporaryDirectory(prefix="tubeid-diagnose-") if out is None else None
    lock = None
    try:
        outdir = OutputDir(tmp.name if tmp is not None else out, field="out")
        from tubeid.runner.lock import StoreLock

        # one diagnosis at a time in a directory, from its first check to its last file: a second one
        # (e.g. --overwrite) is refused before it removes or writes anything
        lock = StoreLock(outdir.path, log=lambda m: None if quiet else print(m, file=sys.stderr), field="out",
                         advice=_WAIT.format(store=outdir.path / STORE_NAME))
        lock.acquire()
        from tubeid.diagnose.report import OUTPUT_FILES

        # every refusal first: nothing is removed or written until all of them passed
        copy = f"data-{h[:16]}.nc"
        source_name = source.resolve().name if source is not None and source.resolve().parent == outdir.path.resolve() else None
        store = outdir.path / STORE_NAME
        if store.is_symlink():
            raise SpecificationError(f"out/{STORE_NAME}", str(store), f"is a symbolic link (to {os.readlink(store)}): "
                                     "tubeid does not write through a link; move it or choose another --out")
        _refuse_store_in_use(store)
        entries = outdir.entries()
        if store.exists() and STORE_NAME not in entries:
            raise SpecificationError(f"out/{STORE_NAME}", str(store), "exists and was not created by tubeid here (not in "
                                     "the manifest): it is left untouched; move it or choose another --out")
        # only what tubeid wrote, unchanged, and never the record being read
        removing = outdir.removal([n for n in entries if n != source_name])[0] if overwrite else []
        _check_outputs(outdir, (copy, *OUTPUT_FILES), removed=removing)
        data_path = (outdir.path / copy).resolve()
        overrides = {"data": str(data_path), "data_sha256": h, "model": json.dumps(spec_to_dict(spec0), sort_keys=True),
                     "settings": settings.to_json()}
        if not overwrite:
            _check_store(store, study_hash(STAGES_FILE.read_text(), overrides), overrides)
        from tubeid.runner.store import prepare_path, remove_store

        # what the runner refuses up front (a store it cannot write; with --overwrite one not tubeid's), now
        with speaking(_TERMS):
            prepare_path(store)
            if overwrite:
                remove_store(store, dry_run=True)
        if overwrite:
            outdir.remove([n for n in outdir.entries() if n != source_name])
        outdir.record_directory(STORE_NAME)
        # a copy written by an earlier tubeid (NetCDF-4, readable with the io extra only) is rewritten as
        # NetCDF-3, same name and content (the store's parameters hold its path and content hash: it
        # resumes), unless it is the very record being read
        if not outdir.owned(copy) or (copy != source_name and not _is_netcdf3(outdir.path / copy)):
            outdir.write_bytes(copy, _copy_bytes(data))
        _CONTEXTS[(overrides["data"], h, overrides["model"], overrides["settings"])] = ctx
        from threadpoolctl import threadpool_limits

        # the runner's refusals name diagnose's options (--out), not its own (--store, --new-store)
        with threadpool_limits(limits=1), speaking(_TERMS):  # many small matrices: BLAS threads would only contend
            report = run(STAGES_FILE, store, workers=workers, scheduler=scheduler, overrides=overrides,
                         overwrite=overwrite, progress=progress, quiet=quiet)
            from tubeid.diagnose.report import assemble

            diagnosis = assemble(store, ctx)
        diagnosis.report["runner"] = {
            "store": str(store.resolve()) if tmp is None else None, "workers": report.workers,
            "tasks_computed": report.computed, "tasks_reused": report.skipped,
            "stages": {n: {"computed": r.computed, "reused": r.skipped, "seconds": round(r.wall, 3)}
                       for n, r in report.stages.items()}}
        if tmp is None:
            diagnosis.store = store.resolve()
            lock.check()  # still ours: another run took it over only if this one stopped beating
            diagnosis.write(outdir.path)
        return diagnosis
    finally:
        if lock is not None:
            lock.release()
        if tmp is not None:
            tmp.cleanup()
