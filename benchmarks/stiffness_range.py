"""What the specification's stiffness range rests on (not a test).

    python benchmarks/stiffness_range.py

For the built-in paper models: each link's and stop's stiffness over the element stiffness
12 EI/Le³ of the (softer) tube it acts on; how close links and stops at 1e3 times that come to
rigid (every eigenfrequency below the band, stop open and closed, against links and stops at the
rule's upper end, 1e8 times); and, with the rule lifted in this process only, what grid links far
beyond it do to ``paper-simplified``'s first eigenfrequency (round-off of the tube's stiffness).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.linalg

import tubeid.mechanics.spec as spec_module
from tubeid.mechanics import builtin_spec
from tubeid.mechanics.assembly import assemble

MODELS = ("paper-reference", "paper-simplified", "paper-simplified-one-spring")


def element_stiffness(spec, names) -> float:
    tubes = {t.name: t for t in spec.tubes}
    return min(tubes[n].element_stiffness for n in names if n is not None)


def scaled(spec, ratio_links=None, ratio_stops=None, links_k=None):
    """``spec`` with every link (stop) at ``ratio`` times its element stiffness, or links at ``links_k`` N/m."""
    links = tuple(dataclasses.replace(
        link, stiffness=links_k if links_k is not None else
        (ratio_links * element_stiffness(spec, (link.tube, link.to_tube)) if ratio_links else link.stiffness))
        for link in spec.links)
    stops = tuple(dataclasses.replace(
        s, stiffness=ratio_stops * element_stiffness(spec, (s.tube,)) if ratio_stops else s.stiffness)
        for s in spec.stops)
    return dataclasses.replace(spec, links=links, stops=stops)


def frequencies(spec, closed: bool) -> np.ndarray:
    """Undamped eigenfrequencies [Hz] of the assembled model, with every stop's k b bᵀ added if ``closed``."""
    fe = assemble(spec)
    K = fe.K.copy()
    if closed:
        for s, b in zip(spec.stops, fe.stop_vectors()):
            K += s.stiffness * np.outer(b, b)
    return np.sqrt(scipy.linalg.eigh(K, fe.M, eigvals_only=True)) / (2 * np.pi)


def main() -> None:
    for name in MODELS:
        spec = builtin_spec(name)
        ratios = [link.stiffness / element_stiffness(spec, (link.tube, link.to_tube)) for link in spec.links]
        ratios += [s.stiffness / element_stiffness(spec, (s.tube,)) for s in spec.stops]
        print(f"{name}: links and stops at {min(ratios):.3g} to {max(ratios):.3g} times the element stiffness")
    for name in MODELS[:2]:
        spec = builtin_spec(name)
        for closed in (False, True):
            a = frequencies(scaled(spec, 1e3, 1e3), closed)
            b = frequencies(scaled(spec, 1e8, 1e8), closed)
            band = b < spec.band_hz
            print(f"{name}, stop {'closed' if closed else 'open'}: links and stops at 1e3 against 1e8 times, "
                  f"largest relative difference of the {band.sum()} eigenfrequencies below {spec.band_hz:g} Hz: "
                  f"{np.max(np.abs(a[band] / b[band] - 1)):.2e}")
    spec = builtin_spec("paper-simplified")
    spec_module.STIFFNESS_RATIO = np.inf  # lift the rule in this process only, to see what it prevents
    rigid = frequencies(scaled(spec, 1e8), False)[0]
    for k in (1e19, 1e20, 1e21):
        f1 = frequencies(scaled(spec, links_k=k), False)[0]
        ratio = k / element_stiffness(spec, ("equivalent", "centre"))
        print(f"paper-simplified, grid links of {k:g} N/m ({ratio:.2g} times): first eigenfrequency {f1:.4f} Hz "
              f"against {rigid:.4f} Hz at 1e8 times ({f1 / rigid - 1:+.2%})")


if __name__ == "__main__":
    main()
