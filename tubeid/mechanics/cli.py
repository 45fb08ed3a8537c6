"""``tubeid model NAME|SPEC.yaml [--json]``: the numbers that characterise a bundle model."""

from __future__ import annotations

import json

__all__ = ["register", "model_summary"]


def model_summary(name_or_path) -> dict:
    """n_dof, first 10 eigenfrequencies [Hz], J and its unit, n_reduced (size of reduced B), delta_max."""
    import math

    from tubeid.mechanics.library import resolve_spec
    from tubeid.mechanics.reduction import J_UNITS, j_of_spec, reduce

    spec = resolve_spec(name_or_path)
    red = reduce(spec)
    sub = red.subsystem
    J = j_of_spec(spec, sub) if sub.n_c else None
    return {
        "model": spec.name,
        "n_dof": red.fe.n_dof,
        "eigenfrequencies_hz": [round(float(f), 6) for f in red.fe.eigenfrequencies(10)],
        "J": J,
        "J_units": J_UNITS,
        "J_band_hz": [-spec.band_hz, spec.band_hz],
        "n_reduced": sub.n,
        "n_interface": sub.n_c,
        "delta_max": math.sqrt((sub.n + 1) / (sub.n + 5)),
    }


def _run(args) -> int:
    s = model_summary(args.model)
    if args.json:
        print(json.dumps(s, indent=2))
        return 0
    print(f"model               {s['model']}")
    print(f"n_dof               {s['n_dof']}")
    print("eigenfrequencies    " + ", ".join(f"{f:.3f}" for f in s["eigenfrequencies_hz"]) + " Hz")
    print(f"J                   {s['J']:.6e} {s['J_units']}  (over {s['J_band_hz'][0]:g}..{s['J_band_hz'][1]:g} Hz)" if s["J"] is not None else "J                   n/a (no coupling interface)")
    print(f"n_reduced           {s['n_reduced']}  (reduced linear subsystem B, {s['n_interface']} interface DOFs)")
    print(f"delta_max           {s['delta_max']:.6f}  (SG+ admissible bound sqrt((n+1)/(n+5)))")
    return 0


def register(sub) -> None:
    from tubeid.mechanics.library import BUILTIN_MODELS  # the registry itself: the list cannot drift

    p = sub.add_parser("model", help="summarise a built-in model or a specification file")
    p.add_argument("model", help=f"built-in name ({', '.join(BUILTIN_MODELS)}) or a .yaml/.toml specification")
    p.add_argument("--json", action="store_true", help="print a JSON object")
    p.set_defaults(func=_run)
