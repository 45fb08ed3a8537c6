"""Built-in bundle specifications: the paper's reference and simplified models (MODEL.md §1–2).

``paper-reference`` — five parallel clamped–clamped tubes (16 m, hollow circle R = 0.5 m, wall
0.2 m, 250 kg/m³; E = 4.5e8 Pa for the four outer tubes, 7.5e8 Pa for the centre tube), 8 Hermite
elements each; three grids at x = 4, 8, 12 m where every outer tube is tied to the centre tube by
one 4e7 N/m spring on the transverse DOFs (12 springs); a symmetric elastic stop on the centre
tube at x = 6 m (gap 1.5e-6 m, 1e8 N/m); seven transverse forces on the centre tube at
x = 2, 4, …, 14 m; sensor ``P_obs`` at the stop.

``paper-simplified`` (MODEL.md §2) — subsystem A (the centre tube, its stop, the load points, the
sensor) is the reference's; subsystem B, the four outer tubes, is replaced by the usual equivalent
bundle beam: same section and length, clamped–clamped, the summed mass and bending stiffness of
*all five* tubes (1250 kg/m³ = 5 × 250; E = 2.55e9 Pa = 4 × 4.5e8 + 7.5e8), meshed with 4 Hermite
elements (one per grid span, nodes at 0, 4, 8, 12, 16 m), tied to the centre tube at each grid by
the four grid springs lumped in parallel (1.6e8 N/m); Craig–Bampton keeps 2 fixed-interface modes
of B (its 6 internal DOFs allow no more: 3 or more make the reduced mass singular), so B has
n = 5 reduced coordinates and δ_max = √(6/10). The modelling simplifications: the homogenisation
rule of a large bundle applied to five tubes (it also counts the centre tube: +25 % mass, +42 % EI
for B), a coarse mesh, the springs lumped.

``paper-simplified-one-spring`` — the earlier simplified model, kept as the example of a simplified
model the nonparametric uncertainty cannot cover: the four outer tubes replaced by one equivalent
tube (1000 kg/m³, E = 1.8e9 Pa, 8 elements) tied by ONE 4e7 N/m spring per grid. Its B is softer than
the reference's and its J within 0.5 % of J_ref, so δ_opt sits at the lower edge of any δ grid
(random K_B ∈ SE+ only makes B more compliant on average).

Assumptions (where the paper is silent; each is a field of the specification):
modal damping ratio 0.02 on each tube's own clamped–clamped modes, springs and stops undamped;
the grid springs act on the transverse (y) DOF only; band of analysis [−100, 100] Hz;
Craig–Bampton keeps the fixed-interface modes of B below 300 Hz unless the model says otherwise
(``reduction``), every mode of A (the highest frequency of the model, stop closed, is then 947 Hz,
as MODEL.md §3.7). Trap (MODEL.md §2): an equivalent tube of the four outer tubes only, 8 elements
and 4 × 4e7 N/m per grid would coincide exactly with the reference as seen from the centre tube.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

from tubeid.errors import SpecificationError

if TYPE_CHECKING:
    from tubeid.mechanics.spec import BundleSpec, TubeSpec
# the specification classes (and numpy, which they need) are imported where a model is built: the
# registry's names alone (``tubeid model --help``) load no numerical library

__all__ = ["builtin_spec", "BUILTIN_MODELS", "resolve_spec", "model_content"]

GRIDS = (4.0, 8.0, 12.0)
SECTION = dict(length=16.0, outer_radius=0.5, wall=0.2, n_elements=8, ends=("clamped", "clamped"), damping_ratio=0.02)


def _centre() -> TubeSpec:
    from tubeid.mechanics.spec import TubeSpec

    return TubeSpec(name="centre", density=250.0, youngs_modulus=7.5e8, **SECTION)


def _common(name: str, tubes, links, assumptions: str, **extra) -> BundleSpec:
    from tubeid.mechanics.spec import BundleSpec, LoadPoint, SensorSpec, StopSpec

    return BundleSpec(
        name=name,
        tubes=tuple(tubes),
        links=tuple(links),
        stops=(StopSpec(tube="centre", x=6.0, gap=1.5e-6, stiffness=1e8),),
        loads=tuple(LoadPoint(name=f"F{i}", tube="centre", x=2.0 * i, kind="force") for i in range(1, 8)),
        sensors=(SensorSpec(name="P_obs", tube="centre", x=6.0),),
        band_hz=100.0,
        assumptions=assumptions,
        **extra,
    )


def paper_reference() -> BundleSpec:
    from tubeid.mechanics.spec import LinkSpec, TubeSpec

    outer = [TubeSpec(name=f"outer{i}", density=250.0, youngs_modulus=4.5e8, **SECTION) for i in range(1, 5)]
    links = [LinkSpec(tube=t.name, x=x, stiffness=4e7, to_tube="centre") for x in GRIDS for t in outer]
    return _common("paper-reference", [_centre(), *outer], links, __doc__ or "")


def paper_simplified() -> BundleSpec:
    from tubeid.mechanics.spec import LinkSpec, ReductionSpec, TubeSpec

    eq = TubeSpec(name="equivalent", density=5 * 250.0, youngs_modulus=4 * 4.5e8 + 7.5e8, **{**SECTION, "n_elements": 4})
    links = [LinkSpec(tube="equivalent", x=x, stiffness=4 * 4e7, to_tube="centre") for x in GRIDS]
    return _common("paper-simplified", [_centre(), eq], links, __doc__ or "", reduction=ReductionSpec(b_modes=2))


def paper_simplified_one_spring() -> BundleSpec:
    from tubeid.mechanics.spec import LinkSpec, TubeSpec

    eq = TubeSpec(name="equivalent", density=1000.0, youngs_modulus=1.8e9, **SECTION)
    links = [LinkSpec(tube="equivalent", x=x, stiffness=4e7, to_tube="centre") for x in GRIDS]
    return _common("paper-simplified-one-spring", [_centre(), eq], links, __doc__ or "")


BUILTIN_MODELS = {"paper-reference": paper_reference, "paper-simplified": paper_simplified,
                  "paper-simplified-one-spring": paper_simplified_one_spring}


def builtin_spec(name: str) -> BundleSpec:
    """The built-in specification called ``name``.

    Parameters
    ----------
    name : str
        A key of :data:`BUILTIN_MODELS` (``"paper-reference"``, ``"paper-simplified"``, …).

    Returns
    -------
    BundleSpec
        A new specification; an unknown name raises ``SpecificationError`` listing the known ones.
    """
    try:
        return BUILTIN_MODELS[name]()
    except KeyError:
        raise SpecificationError("model", name, f"unknown built-in model; known: {sorted(BUILTIN_MODELS)} or a .yaml/.toml file") from None


def resolve_spec(name_or_path: BundleSpec | str | os.PathLike) -> BundleSpec:
    """A :class:`BundleSpec` from a spec object, a built-in name, or a YAML/TOML file path.

    Parameters
    ----------
    name_or_path : BundleSpec, str or path-like
        A specification (returned as is), a built-in name, or a ``.yaml``/``.yml``/``.toml`` file.

    Returns
    -------
    BundleSpec
        The specification.
    """
    from tubeid.mechanics.spec import BundleSpec, load_spec

    if isinstance(name_or_path, BundleSpec):
        return name_or_path
    s = str(name_or_path)
    if s in BUILTIN_MODELS:
        return builtin_spec(s)
    if s.endswith((".yaml", ".yml", ".toml")):
        return load_spec(s)
    return builtin_spec(s)


def model_content(field: str, value) -> tuple[str, BundleSpec]:
    """A model given as a built-in name, a ``.yaml``/``.toml`` file or its content, as its content.

    For a study parameter naming a model: the value a study stores, hashes and sends to its workers is
    the specification's content, so that a changed file is a changed study (never mixed into a store
    made with the earlier content) and the workers need no file. Idempotent: the content passes
    through unchanged.

    Parameters
    ----------
    field : str
        The field named in a refusal (e.g. ``"parameters.simplified"``).
    value : str
        A built-in name, a specification file, or canonical JSON text ``{"source": ..., "spec": {...}}``.

    Returns
    -------
    text : str
        Canonical JSON text ``{"source": the name or file as given, "spec": the specification's fields}``
        (keys sorted).
    spec : BundleSpec
        The specification.

    Raises
    ------
    SpecificationError
        Not a non-empty string, an unknown name, a missing or invalid file, or text that is none of these.
    """
    import json

    from tubeid.mechanics.spec import spec_from_dict, spec_to_dict

    if not isinstance(value, str) or not value:
        raise SpecificationError(field, value, "must be a built-in model name or a .yaml/.toml specification file")
    try:
        if value.lstrip().startswith("{"):
            content = json.loads(value)
            source, spec = str(content["source"]), spec_from_dict(content["spec"])
        else:
            source, spec = value, resolve_spec(value)
    except SpecificationError as exc:
        raise SpecificationError(field, value if len(value) < 200 else value[:200] + "...", str(exc)) from None
    except (ValueError, KeyError, TypeError, OSError) as exc:
        raise SpecificationError(field, value[:200], f"is neither a model name, a specification file nor its "
                                                      f"content ({type(exc).__name__}: {exc})") from None
    return json.dumps({"source": source, "spec": spec_to_dict(spec)}, sort_keys=True), spec
