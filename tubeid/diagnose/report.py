"""The report of a diagnosis: assembled from the pipeline store, written as report.json, report.md,
residual.png and delta_f.png through the output directory's manifest.

``residual.png``: per sensor, the measured held-out PSD against the declared model's band before
and, when effects were chosen, the augmented model's band after. ``delta_f.png`` (only when δ_F was
identified): the likelihood of δ_F over its grid, with the argmax.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from tubeid._outputs import OutputDir
from tubeid.diagnose import stages as st
from tubeid.diagnose.catalog import CATALOG
from tubeid.mechanics.effects import effect_from_dict

__all__ = ["assemble", "write_files", "markdown", "OUTPUT_FILES"]

#: Every file a diagnosis writes into its output directory besides the store and the record's copy.
OUTPUT_FILES = ("report.json", "report.md", "residual.png", "delta_f.png")


def _json_default(o):
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)


def _open(store, name):
    from tubeid.runner.store import open_results

    return open_results(store, name).load()


def _band(ds, level):
    P = st.band_samples(ds)[0]
    lo, hi = np.quantile(P, [(1 - level) / 2, (1 + level) / 2], axis=0)
    return lo, hi


def _describe(effect_dict) -> dict:
    e = effect_from_dict(effect_dict)
    return {"name": e.name, "parameters": CATALOG[e.name].describe(e)}


def assemble(store, ctx):
    """The :class:`~tubeid.diagnose.method.Diagnosis` of a complete pipeline store."""
    from tubeid.diagnose.method import ERROR_METRIC, Diagnosis
    from tubeid.runner.store import pipeline_status

    s, meas = ctx.settings, ctx.meas
    status = pipeline_status(store)
    results = {n: _open(store, n) for n, stage in status["stages"].items() if stage["started"]}
    ended = status["attrs"].get("ended") or {}
    fine = results["load_r_fine"]
    error_before = st.point_result(ctx, results, 0)["held_out_error"]
    det0 = json.loads(results["band"].attrs["detection"])
    steps, stop_reason, final = [], "", None
    det_last, band_last = det0, results["band"]
    for k in range(1, st.MAX_EFFECTS + 1):
        if st.absent(results, f"step{k}_trials"):  # the loop ended before step k (tubeid.runner.End)
            stop_reason = ended.get("reason", "")
            break
        sel = st.selection(ctx, results, k)
        prev = st.state_before(ctx, results, k)
        step = {"step": k, "error_current": sel["current"], "chosen": sel["chosen"] or None,
                "continuation": prev.get("continuation"),
                "candidates": [{**c, "signature_score": prev["screen"][c["name"]]["score"],
                                "signature_estimate": prev["screen"][c["name"]]["estimate"],
                                "fitted": _describe(c["effect"])["parameters"]}
                               for c in sel["candidates"]]}
        for c in step["candidates"]:
            c.pop("effect"), c.pop("trial")
        if not sel["chosen"]:
            stop_reason = (f"no candidate pays its penalty at step {k}" if not prev.get("continuation") else
                           f"explained after step {k - 1}; the near-tied runner-up(s) {sorted(prev['continuation'])} "
                           f"did not pay their penalty at step {k}")
            steps.append(step)
            break
        pt = st.point_result(ctx, results, k)
        sweeps = []
        for sweep in range(1, st.sweeps_done(results, k) + 1):
            rf = st.refit_result(ctx, results, k, sweep=sweep)
            chk = st.refit_point(ctx, results, k, rf, sweep=sweep)
            sweeps.append({"lines": rf["lines"],
                           "check": {key: chk[key] for key in ("moved_fit_error", "best_fit_error", "extended_fit_error",
                                                               "point", "fallback")},
                           "reason": "" if sweep == 1 else st.sweep_reason(ctx, results, k, sweep - 1)})
        det_k = json.loads(results[f"step{k}_band"].attrs["detection"])
        step.update({"refit": sweeps[0]["lines"], "refit_check": sweeps[0]["check"], "refit_sweeps": sweeps,
                     "effects_after": [_describe(e) for e in pt["effects"]], "r_after": pt["r"],
                     "error_after": pt["held_out_error"], "fit_error_after": pt["fit_error"],
                     "detection_after": det_k})
        steps.append(step)
        if st.continuation_rejected(results, k):  # the explained answer of step k - 1 stands
            step["kept"] = False
            stop_reason = (f"explained after step {k - 1}; the near-tied runner-up `{sel['chosen']}` added at step {k} "
                           "made the test detect again: not kept")
            break
        det_last, band_last = det_k, results[f"step{k}_band"]
        final = pt
        if not det_last["detected"]:
            stop_reason = f"explained after step {k}: the test no longer detects anything"
            if k == st.MAX_EFFECTS or st.absent(results, f"step{k + 1}_trials"):
                break  # else a near-tied runner-up is tried once more (the next step's continuation)
    else:
        stop_reason = f"max_effects = {s.max_effects} reached"
    effects = [] if final is None else [_describe(e) for e in final["effects"]]
    r_before = [float(v) for v in fine.attrs["r_opt"]]
    r_after = r_before if final is None else [float(v) for v in final["r"]]
    report = {
        "effect": effects[0]["name"] if effects else "none",
        "effects": effects,
        "parameters": effects[0]["parameters"] if effects else {},
        "error_before": error_before,
        "error_after": error_before if final is None else final["held_out_error"],
        "metric": ERROR_METRIC + f"; {meas.n_held_out_blocks} held-out blocks of {meas.block_seconds:.4g} s not used for "
                  f"fitting; sigma from {s.n_realisations} realisations",
        "detection": det0,
        "detection_after": det_last,
        "explained_before": not det0["detected"],
        "explained_after": not det_last["detected"],
        "steps": steps,
        "stop_reason": stop_reason,
        "selection_rule": _selection_rule(s),
        "model": ctx.spec0.name,
        "model_form": s.form,
        "load": _load(ctx, results, r_before, r_after),
        "delta": {k: results["delta_ml"].attrs[k] for k in results["delta_ml"].attrs.get("summary_keys", [])},
        "assumptions": _assumptions(ctx),
        "sensors": [{"name": n, "tube": t, "x": x} for n, t, x in zip(meas.sensors, meas.tube, meas.x)],
        "settings": json.loads(s.to_json()),
    }
    bands = {"before": _band(results["band"], s.level)}
    if band_last is not results["band"]:
        bands["after"] = _band(band_last, s.level)
    return Diagnosis(report=report, frequency=meas.frequency, measured=meas.held_out, sensors=meas.sensors, bands=bands)


def _selection_rule(s) -> str:
    """The selection rule in effect, in one sentence (report.json and report.md)."""
    if s.form == "simplified":
        return ("at each step the catalog effects the strongest statistic of the test points to, not yet chosen, are "
                "fitted on the fitting blocks (the chosen effects held) to that statistic's feature and scored by its "
                "held-out error relative to the current model's in the same feature; the lowest ratio x "
                f"(1 - {s.penalty})^-k (k parameters) is added if it is below 1; then every chosen effect's parameters "
                "are re-fitted jointly on their features (r held) and the augmented model is tested again"
                + _continuation_rule(s) + _tie_rule(s))
    return ("at each step every catalog effect not yet chosen is fitted on the fitting blocks (the chosen effects "
            "held, the level profiled) and scored by its held-out error; the lowest held-out error x "
            f"(1 - {s.penalty})^-k (k parameters) is added if it is below the current model's held-out error; then r "
            "and every chosen effect's parameters are re-fitted jointly and the augmented model is tested again"
            + _continuation_rule(s) + _tie_rule(s))


def _continuation_rule(s) -> str:
    if s.max_effects < 1:
        return ""
    if s.continuation_alarm is not None:
        return f", at the false-alarm rate {s.continuation_rate:g} (given)"
    if s.max_effects <= 2:
        return f", at the false-alarm rate {s.continuation_rate:g} (the first test's: at most one test can continue the loop)"
    return (f", at the false-alarm rate {s.continuation_rate:g} (the first test's {s.false_alarm:g} shared among the "
            f"{s.max_effects - 1} tests that could continue the loop)")


def _tie_rule(s) -> str:
    if s.tie <= 0:
        return ""
    return (f"; a runner-up that also paid its penalty within {s.tie:g} (relative) of the chosen one's ratio is "
            "offered once more, alone, at the first step the test calls the record explained")


def _load(ctx, results, r_before, r_after) -> dict:
    from tubeid.identification.loads import JS_UNITS

    s = ctx.settings
    dF = results["load_delta_f"].attrs
    units = ["N^2/Hz"] if s.load == "distributed" else ["N^2/Hz", "(N m)^2/Hz"]
    fine, coarse = results["load_r_fine"], results["load_r"]
    load = {"model": s.load, "r_before": r_before, "r_after": r_after, "units": units,
            "r_trials": int(np.prod([coarse.sizes[d] for d in st.R_DIMS if d in coarse.dims]))
            + int(np.prod([fine.sizes[d] for d in st.R_DIMS if d in fine.dims])),
            "r_fine_at_boundary": bool(fine.attrs["at_boundary"]),
            "delta_F": float(dF["delta_F"]), "delta_F_given": bool(dF["delta_F_given"]),
            "delta_F_source": dF.get("delta_F_source", ""), "load_dispersion": float(dF["delta_F_used"]), "m": ctx.m,
            "delta_F_refitted": False}
    if not dF["delta_F_given"]:
        load.update({
            "delta_F_std": dF.get("delta_F_std"), "delta_F_std_observations": dF.get("delta_F_std_observations"),
            "delta_F_flat": bool(dF["flat"]), "delta_F_identified": bool(dF["identified"]),
            "delta_F_at_boundary": bool(dF["at_boundary"]), "delta_F_note": dF["note"],
            "load_dispersion_reason": dF["used_reason"] or "the maximum-likelihood δ_F",
            "delta_F_likelihood": {"grid": dF["grid"], "log_likelihood": dF["log_likelihood"], "likelihood": dF["likelihood"],
                                   "n_realisations": dF["n_realisations"], "n_observations": len(dF["J_s_observed"])},
            "J_s_observed": dF["J_s_observed"], "J_s_units": JS_UNITS})
    return load


def _assumptions(ctx) -> list[str]:
    s = ctx.settings
    out = [f"load: {s.load} model ({'the declared force points with coherence exp(-|dx|/%g m)' % s.correlation_length if s.load == 'distributed' else 'force and moment at x = %g m' % s.load_x}); its level r is fitted",
           "δ (dispersion of B's stiffness): " + (f"given ({s.delta})" if s.delta_reference is None else
                                                   f"identified by maximum likelihood of J against {s.delta_reference}"),
           "δ_F (load dispersion) is not re-fitted with the effects",
           "effects of one kind are chosen at most once"]
    if s.form == "simplified":
        from tubeid.diagnose._detection import STATISTICS, applicable

        used = applicable("simplified", st.record_observations(ctx, "held_out"), s.band_width_hz)
        seen = {e for k in used for e in STATISTICS[k].effects}
        unseen = [n for n in (s.candidates or tuple(CATALOG)) if n not in seen]
        out += ["model form: simplified" + (" (δ identified against another model)" if s.model_form is None else " (given)")
                + f": the test reads only {', '.join(used)} (fine segment {ctx.meas.fine_seconds:g} s), each fitted effect "
                "is judged by its own statistic's feature, r is held at its identification"
                + (f"; not testable here (no statistic of this form that this record allows sees them): {unseen}"
                   if unseen else "")]
    else:
        out += ["model form: exact (the declared model is the structure up to its random B): the test reads the "
                "spectrum's shape; if the model simplifies the structure, set model_form=simplified"]
        from tubeid.diagnose._detection import feature_applies

        if st._probes(ctx) and feature_applies("profile", st.record_observations(ctx, "held_out"), s.band_width_hz):
            probe = CATALOG["added_mass"].probe(ctx.spec, "exact")
            out += [f"the test's profile looks for added mass in one direction, its probe's (factor {probe.factor:g} "
                    f"on {probe.tube!r}): a mass on a tube unlike that one is left to the shape statistics"]
    for n in ctx.candidate_names:
        out += CATALOG[n].assumptions(ctx.spec)
    return out


# ----------------------------------------------------------------------------------------------
# Files
# ----------------------------------------------------------------------------------------------


def write_files(diag, out) -> Path:
    """Write the report files of ``diag`` into ``out`` through its manifest (:class:`OutputDir`)."""
    _plt()  # matplotlib (the figures), before any file is written
    d = OutputDir(out, field="out")
    d.write_text("report.json", json.dumps(diag.report, indent=2, default=_json_default) + "\n")
    d.write_text("report.md", markdown(diag.report))
    _residual_figure(diag, d)
    if not diag.report["load"].get("delta_F_given", True):
        _delta_f_figure(diag.report["load"], d)
    return d.path


def _as_written(name: str) -> str:
    """A name (a sensor's, an effect's) as a figure shows it: its dollar signs escaped, so that matplotlib
    does not parse ``c$\\x$`` as TeX math (and fail on it); the axes' own math (log ticks) is untouched."""
    return str(name).replace("$", r"\$")


def _fmt(v, spec=".3g"):
    return "n/a" if v is None else format(v, spec)


def _value(v) -> str:
    return f"{v['value']:.4g}" if isinstance(v["value"], float) else str(v["value"])


def _detection_line(det: dict, when: str) -> str:
    ps = ", ".join(f"{k} {v:.3g}" for k, v in det["p_values"].items())
    verdict = "**detected**" if det["detected"] else "not detected"
    return (f"- test {when}: p = {det['p_value']:.3g} ({ps}; {det['n_realisations']} realisations, stated false-alarm "
            f"rate {det['false_alarm']:g}, exact size {det['size']:.3g}): {verdict}")


def _delta_f_lines(load: dict) -> list[str]:
    if load.get("delta_F_given", True):
        return [f"- δ_F = {load['delta_F']} ({load.get('delta_F_source') or 'given'}; not identified)"]
    lik = load["delta_F_likelihood"]
    lines = [f"- δ_F = {load['delta_F']:.3g} by maximum likelihood of J_s over {lik['n_observations']} fitting blocks "
             f"(Monte Carlo: {lik['n_realisations']} records per grid value; bootstrap std {_fmt(load['delta_F_std'])} "
             f"over realisations, {_fmt(load['delta_F_std_observations'])} over observations)"]
    if load["delta_F_flat"]:
        lines.append("- **The likelihood of δ_F is flat** over the grid: these data do not identify δ_F.")
    elif load["delta_F_note"]:
        lines.append(f"- δ_F: {load['delta_F_note']}.")
    if load["load_dispersion"] != load["delta_F"]:
        lines.append(f"- **The band uses δ_F = {load['load_dispersion']:g}** (the fallback): {load['load_dispersion_reason']}.")
    return lines


def _continuation_line(step: dict) -> str:
    ties = "; ".join(f"`{n}` at step {v['step']} (ratio {v['ratio']:.4g} against `{v['chosen']}`'s {v['chosen_ratio']:.4g})"
                     for n, v in step["continuation"].items())
    return (f"The record was explained after step {step['step'] - 1}, but near-tied runner-ups were never tried with "
            f"the other fitted: {ties}. They are offered once more, alone.\n")


def markdown(rep: dict) -> str:
    """The report.md of a report dict."""
    names = ", ".join(f"`{e['name']}`" for e in rep["effects"]) or "`none`"
    lines = [f"# Diagnosis of measured data against `{rep['model']}` (model form: {rep['model_form']})", "",
             f"**Effects: {names}**", ""]
    if not rep["explained_after"]:
        lines += ["**Warning:** the test still detects a departure from the model after the selection "
                  f"({rep['stop_reason']}): the residual is not fully explained by the catalog — consider the model "
                  "uncertainty (δ), the load model, or an effect the catalog does not hold.", ""]
    for e in rep["effects"]:
        lines += [f"### `{e['name']}`", "", "| parameter | value | units | fitted |", "|---|---|---|---|"]
        lines += [f"| {k} | {_value(v)} | {v['units']} | {'yes' if v['fitted'] else 'no (assumed)'} |"
                  for k, v in e["parameters"].items()]
        lines.append("")
    load, delta = rep["load"], rep["delta"]
    r_b = ", ".join(f"{v:.4g} {u}" for v, u in zip(load["r_before"], load["units"]))
    r_a = ", ".join(f"{v:.4g} {u}" for v, u in zip(load["r_after"], load["units"]))
    lines += [_detection_line(rep["detection"], "before")]
    if rep["steps"] and "detection_after" in rep["steps"][-1]:
        lines.append(_detection_line(rep["detection_after"], "after"))
    spectrum = " (the spectrum's; the effects were judged on their statistics' features, below)" \
        if rep.get("model_form") == "simplified" else ""
    lines += [f"- held-out error before: {rep['error_before']:.4g}; after: {rep['error_after']:.4g}{spectrum} "
              f"({rep['stop_reason']})",
              f"- metric: {rep['metric']}",
              f"- load ({load['model']}): r before ({r_b}), after ({r_a})",
              f"- δ = {delta.get('delta', 'n/a'):.4g} ({delta.get('delta_source', '')})" if delta else "- δ: n/a",
              *_delta_f_lines(load), ""]
    for step in rep["steps"]:
        lines += [f"## Step {step['step']}: {('`' + step['chosen'] + '` added') if step['chosen'] else 'nothing added'}", "",
                  f"Held-out error of the model so far: {step['error_current']:.4g}.", "",
                  *([_continuation_line(step)] if step.get("continuation") else []),
                  "| candidate | judged on | signature | k | fit error | held-out error | current | penalised |",
                  "|---|---|---|---|---|---|---|---|"]
        for c in step["candidates"]:
            lines.append(f"| {c['name']} | {c['feature']} | {c['signature_score']:.3f} | {c['k']} | {c['fit_error']:.4g} | "
                         f"{c['held_out_error']:.4g} | {c['current']:.4g} | {c['penalised']:.4g} |")
        if "error_after" in step:
            lines += ["", f"After the joint re-fit: held-out error {step['error_after']:.4g}, test p = "
                          f"{step['detection_after']['p_value']:.3g}."
                      + (" The test detects again with it: not kept." if step.get("kept") is False else "")]
        lines.append("")
    lines += ["## Rules and assumptions", "", rep["selection_rule"] + ".", ""]
    lines += [f"- {a}" for a in rep["assumptions"]]
    lines += ["", "![residual](residual.png)", ""]
    if not load.get("delta_F_given", True):
        lines += ["![likelihood of δ_F](delta_f.png)", ""]
    return "\n".join(lines)


def _plt():
    from tubeid._optional import require

    matplotlib = require("matplotlib", "tubeid diagnose")

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _residual_figure(diag, d: OutputDir) -> None:
    plt = _plt()
    from matplotlib.ticker import NullLocator

    f = diag.frequency
    m = len(diag.sensors)
    rows = len(diag.bands)
    fig, axes = plt.subplots(rows, m, figsize=(3.6 * m, 3.0 * rows), squeeze=False)
    level = diag.report["settings"]["level"]
    names = ", ".join(_as_written(e["name"]) for e in diag.report["effects"])
    for i, (label, (lo, hi)) in enumerate(diag.bands.items()):
        for j, s in enumerate(diag.sensors):
            ax = axes[i, j]
            ax.fill_between(f[1:], lo[1:, j], hi[1:, j], color="0.8", label=f"model {level:.0%} band")
            ax.semilogy(f[1:], diag.measured[1:, j], "r", lw=0.6, label="measured (held out)")
            ax.yaxis.set_minor_locator(NullLocator())  # decades only: minor log ticks double the drawing time
            # y given: matplotlib then skips placing each title above the axis' tick labels (a third of the drawing)
            ax.set_title(f"{_as_written(s)}: {label}" + (f" ({names})" if label == "after" else ""), fontsize=8, y=1.0)
            ax.set_xlabel("f [Hz]", fontsize=8)
            ax.tick_params(labelsize=7)
            if j == 0:
                ax.set_ylabel("PSD [m²/Hz, two-sided]", fontsize=8)
    axes[0, 0].legend(fontsize=7)
    # fixed margins (inches, as tight_layout would leave them): tight_layout on this grid took longer than the plot
    w, h = fig.get_size_inches()
    fig.subplots_adjust(left=0.75 / w, right=1 - 0.15 / w, bottom=0.5 / h, top=1 - 0.3 / h, wspace=0.3, hspace=0.5)
    d.save_figure(fig, "residual.png", dpi=80)
    plt.close(fig)


def _delta_f_figure(load: dict, d: OutputDir) -> None:
    plt = _plt()
    lik = load["delta_F_likelihood"]
    fig, ax = plt.subplots(figsize=(5, 3.2))
    ax.plot(lik["grid"], lik["likelihood"], "o-", color="C2", ms=3, label="joint likelihood (max 1)")
    ax.axvline(load["delta_F"], color="k", lw=0.8, ls="--", label=f"argmax δ_F = {load['delta_F']:.3g}")
    if load["load_dispersion"] != load["delta_F"]:
        ax.axvline(load["load_dispersion"], color="C3", lw=0.8, ls=":", label=f"band's δ_F = {load['load_dispersion']:g} (fallback)")
    ax.set_xscale("log")
    ax.set_xlabel("δ_F (log scale)")
    ax.set_ylabel("likelihood / max")
    ax.set_title("δ_F by maximum likelihood of J_s" + (" (flat)" if load["delta_F_flat"] else ""), fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    d.save_figure(fig, "delta_f.png", dpi=90)
    plt.close(fig)
