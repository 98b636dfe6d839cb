"""The fit's outcome does not hang on rounding (issue 12, item 7).

A fresh clone on another machine of this kind once failed three fit tests that pass
here, and one IPOPT call sat 50 minutes in MUMPS: the outcome sat on a knife edge.
Here the same recording is fitted from starts perturbed by one part in a million and
from a second draw of the sensor noise: the verdict of every directly measured
element and its gap (within its interval's half-width) must not change.  Every IPOPT
call is bounded (``Collocation.max_cpu_s``) and a bound that is hit is an honest
"did not converge", checked last.
"""

from __future__ import annotations

import numpy as np
import pytest

from ident.fit import Collocation, fit_gaps, synthetic_case

from test_fit import MEASURED

TRUTH = {"C46.gap": 0.005, "C46.gap_open": 0.002, "C57.gap": 0.0035, "C57.gap_open": 0.001}


@pytest.fixture(scope="module")
def case(mill, tmp_path_factory):
    return synthetic_case(mill, TRUTH, seed=31, n_bars=1,
                          directory=tmp_path_factory.mktemp("stab"))


def _outcome(res):
    return {e: (res.elements[e].identified, res.elements[e].gap) for e in MEASURED}


@pytest.mark.slow
def test_perturbed_starts_and_noise_give_the_same_verdict(mill, case, tmp_path):
    base = fit_gaps(mill, case.windows)
    designed = {e.id: max(e.gap, 5e-4) for e in mill.elements}
    rng = np.random.default_rng(0)
    nudged = {k: v * (1 + 1e-6 * rng.standard_normal()) for k, v in designed.items()}
    again = fit_gaps(mill, case.windows, starts=[nudged])
    other = synthetic_case(mill, TRUTH, seed=32, n_bars=1, directory=tmp_path)
    noise2 = fit_gaps(mill, other.windows)
    ref = _outcome(base)
    for res in (again, noise2):
        got = _outcome(res)
        for e in MEASURED:
            assert got[e][0] == ref[e][0], (e, got[e], ref[e], res.elements[e].reason)
            half = max(0.5 * (base.elements[e].gap_ci95[1] - base.elements[e].gap_ci95[0]),
                       1e-4)
            assert abs(got[e][1] - ref[e][1]) <= 3 * half, (e, got[e], ref[e])
    assert all(v[0] for k, v in ref.items() if k in ("C46", "C57")), base.warnings


def test_a_solve_that_hits_its_time_bound_says_so(mill, case):
    """A CPU bound far below what the solve needs: not converged, nothing identified."""
    res = fit_gaps(mill, case.windows, method=Collocation(max_cpu_s=0.05), restarts="never",
                   direct=False, uncertainty=False)
    assert not res.converged
    assert "CpuTime" in res.solver.status, res.solver.status
    assert not any(el.identified for el in res.elements.values())
    assert all("did not converge" in el.reason for el in res.elements.values())
