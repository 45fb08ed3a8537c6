"""The files of a diagnosis: report.json, report.md, residual.png and delta_f.png.

``residual.png``: per sensor, the measured held-out PSD against the model's confidence band before
(and after, when an effect was chosen). ``delta_f.png`` (only when δ_F was identified): the
likelihood of δ_F (maximum 1) over its grid, with the argmax.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["write_files", "markdown"]


def _json_default(o):
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)


def write_files(diag, out) -> Path:
    """Write the report files of ``diag`` (a :class:`~tubeid.measured.diagnose.Diagnosis`) into ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.json").write_text(json.dumps(diag.report, indent=2, default=_json_default) + "\n")
    (out / "report.md").write_text(markdown(diag.report))
    _residual_figure(diag, out / "residual.png")
    if not diag.report["load"].get("delta_F_given", True):
        _delta_f_figure(diag.report["load"], out / "delta_f.png")
    return out


def _fmt(v, spec=".3g"):
    return "n/a" if v is None else format(v, spec)


def _delta_f_lines(load: dict) -> list[str]:
    if load.get("delta_F_given", True):
        return [f"- δ_F = {load['delta_F']} (given, not identified)"]
    lik = load["delta_F_likelihood"]
    lines = [f"- δ_F = {load['delta_F']:.3g} by maximum likelihood of J_s over {lik['n_observations']} fitting blocks "
             f"(Monte Carlo: {lik['n_realisations']} records per grid value; bootstrap std {_fmt(load['delta_F_std'])} "
             f"over realisations, {_fmt(load['delta_F_std_observations'])} over observations)"]
    if load["delta_F_flat"]:
        lines.append("- **The likelihood of δ_F is flat** over the grid "
                     f"[{lik['grid'][0]:g}, {lik['grid'][-1]:g}]: these data do not identify δ_F; the value used "
                     "(argmax) carries no precision.")
    elif load["delta_F_note"]:
        lines.append(f"- δ_F: {load['delta_F_note']}.")
    if load["load_dispersion"] != load["delta_F"]:
        lines.append(f"- **The band uses δ_F = {load['load_dispersion']:g}** (the fallback), not the argmax: "
                     f"{load['load_dispersion_reason']}.")
    lines.append("- δ_F assumes the fitting blocks are independent load states; blocks of one continuous record "
                 "share one, and then δ_F measures how far it lies from the mean model.")
    return lines


def markdown(rep: dict) -> str:
    """The short report.md of a report dict."""
    lines = [f"# Diagnosis of measured data against `{rep['model']}`", "",
             f"**Effect: `{rep['effect']}`**", ""]
    if not rep["explained_after"]:
        lines += ["**Warning:** the held-out error stays above what the model's own realisations show: the "
                  "residual is not (fully) explained by one catalog effect — consider the model uncertainty "
                  "(δ), the load model, or several effects.", ""]
    if rep["parameters"]:
        lines += ["| parameter | value | units |", "|---|---|---|"]
        lines += [f"| {k} | {v['value']:.4g} | {v['units']} |" if isinstance(v["value"], float) else f"| {k} | {v['value']} | {v['units']} |"
                  for k, v in rep["parameters"].items()]
        lines.append("")
    load = rep["load"]
    r_b = ", ".join(f"{v:.4g} {u}" for v, u in zip(load["r_before"], load["units"]))
    r_a = ", ".join(f"{v:.4g} {u}" for v, u in zip(load["r_after"], load["units"]))
    lines += [f"- error before: {rep['error_before']:.4g} decades; after: {rep['error_after']:.4g} decades",
              f"- metric: {rep['metric']}",
              f"- explained within the band before (error <= null threshold {rep['null_threshold']:.4g}): {rep['explained_before']}; "
              f"after (null threshold {rep['null_threshold_after']:.4g}): {rep['explained_after']}",
              f"- load ({load['model']}): r before ({r_b}), after ({r_a}) ({load['r_trials']} trials before); δ = {load['delta']} (given)",
              *_delta_f_lines(load), "",
              "| candidate | signature score | held-out error | penalised |", "|---|---|---|---|"]
    for c in rep["candidates"]:
        he = f"{c['held_out_error']:.4g}" if "held_out_error" in c else "not fitted"
        pe = f"{c['penalised_error']:.4g}" if "penalised_error" in c else ""
        lines.append(f"| {c['name']} | {c['signature_score']:.3f} | {he} | {pe} |")
    lines += ["", rep["score_rule"], "", "![residual](residual.png)", ""]
    if not load.get("delta_F_given", True):
        lines += ["![likelihood of δ_F](delta_f.png)", ""]
    return "\n".join(lines)


def _plt():
    from tubeid._optional import require

    matplotlib = require("matplotlib", "tubeid diagnose")

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _residual_figure(diag, path: Path) -> None:
    plt = _plt()
    f = diag.frequency
    m = len(diag.sensors)
    rows = 1 if diag.after is None else 2
    fig, axes = plt.subplots(rows, m, figsize=(4.2 * m, 3.2 * rows), squeeze=False)
    for i, (label, band) in enumerate((("before", diag.before), ("after", diag.after))[:rows]):
        for j, s in enumerate(diag.sensors):
            ax = axes[i, j]
            ax.fill_between(f[1:], band.lower[1:, j], band.upper[1:, j], color="0.8", label=f"model {diag.report['settings']['level']:.0%} band")
            ax.semilogy(f[1:], diag.measured[1:, j], "r", lw=0.7, label="measured (held out)")
            ax.set_title(f"{s}: {label}" + ("" if label == "before" else f" ({diag.report['effect']})"), fontsize=9)
            ax.set_xlabel("f [Hz]")
            if j == 0:
                ax.set_ylabel("PSD [m²/Hz, two-sided]")
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _delta_f_figure(load: dict, path: Path) -> None:
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
    fig.savefig(path, dpi=90)
    plt.close(fig)
