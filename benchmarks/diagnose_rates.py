"""Control records at several sampling rates, diagnosed as given (not a test).

    python benchmarks/diagnose_rates.py

24 s controls of ``paper-reference`` (``tubeid.diagnose.testing.make_record``, sensors at 2, 6 and
10 m, seed 11), each diagnosed against ``paper-reference`` with the test suite's small settings
(``tests/test_diagnose.py``'s ``SMALL``, R = 19: the smallest p-value is 1/20, no effect searched),
without and (below the record's Nyquist frequency) with ``max_frequency_hz = 250``. The record's load is sampled at 1 ms (``make_record``'s
default) or at the record's own step, which is what the diagnosis's realisations use at fast rates:
a 1 ms load read piecewise-linearly has images near 1 kHz that realisations sampled faster lack.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from test_diagnose import SMALL, record  # noqa: E402

from tubeid.diagnose import diagnose  # noqa: E402

CASES = [(3e-3, 1e-3), (1e-3, 1e-3), (1 / 2560, 1 / 2560), (1 / 3000, 1 / 3000), (1 / 2560, 1e-3)]


def main() -> None:
    settings = SMALL.replace(max_effects=0)
    for dt, dt_load in CASES:
        data = record(duration=24.0, dt=dt, dt_load=dt_load)
        cuts = (None, 250.0) if 250.0 < 0.5 / dt else (None,)  # a cut must lie below the Nyquist frequency
        p = [diagnose(data, "paper-reference", settings.replace(max_frequency_hz=f)).report["detection"]["p_value"]
             for f in cuts]
        print(f"record at {1 / dt:7.1f} Hz, load sampled every {dt_load * 1e3:.4g} ms: p = {p[0]:.3g}"
              + (f", with max_frequency_hz = 250: p = {p[1]:.3g}" if len(p) > 1 else ""), flush=True)


if __name__ == "__main__":
    main()
