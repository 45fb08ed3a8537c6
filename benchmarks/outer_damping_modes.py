"""What an outer tube's damping changes at the centre tube's sensors (not a test).

    python benchmarks/outer_damping_modes.py [TUBE] [RATIO]

The linear reference bundle (stop open), with and without ``Damping(TUBE, RATIO)`` (default
``outer2``, 0.005 for the declared 0.02): every mode below 100 Hz with its frequency, its damping
ratio before and after, and its participation at the 7 sensors c02–c14 on the centre tube (the
largest |C v| over the largest |v| of the mode shape v: 0 for a mode the sensors cannot see).
"""

from __future__ import annotations

import sys

import numpy as np

from tubeid.diagnose.testing import sensors
from tubeid.mechanics import builtin_spec
from tubeid.mechanics.assembly import assemble
from tubeid.mechanics.effects import Damping, apply_effects


def modes(spec):
    """(frequency [Hz], damping ratio, participation at the sensors) of every mode, by frequency."""
    fe = assemble(spec)
    n = fe.M.shape[0]
    A = np.block([[np.zeros((n, n)), np.eye(n)], [-np.linalg.solve(fe.M, fe.K), -np.linalg.solve(fe.M, fe.D)]])
    lam, V = np.linalg.eig(A)
    keep = lam.imag > 0
    lam, V = lam[keep], V[:n, keep]
    seen = np.abs(fe.sensor_matrix() @ V).max(axis=0) / np.abs(V).max(axis=0)
    o = np.argsort(np.abs(lam))
    return np.abs(lam[o]) / (2 * np.pi), -lam.real[o] / np.abs(lam[o]), seen[o]


def main() -> None:
    """Print the table of the module docstring."""
    tube = sys.argv[1] if len(sys.argv) > 1 else "outer2"
    ratio = float(sys.argv[2]) if len(sys.argv) > 2 else 0.005
    spec = builtin_spec("paper-reference").replace(sensors=sensors((2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0)))
    f0, z0, seen = modes(spec)
    f1, z1, _ = modes(apply_effects(spec, [Damping(tube, ratio)]))
    print(f"damping of {tube} {ratio:g}: frequency [Hz], damping ratio before -> after, participation at the sensors")
    for f, a, b, s in zip(f0, z0, z1, seen):
        if f < 100.0:
            print(f"{f:7.2f}  {a:.4f} -> {b:.4f}  {s:.3f}")


if __name__ == "__main__":
    main()
