"""Collocation from the mill file's designed gaps on a random draw (issue 4, item 5).

Its own module so that ``make test`` (one module per xdist worker) can run this, the
suite's slowest fit, beside the rest of ``test_fit.py``.
"""

from __future__ import annotations

import warnings

import pytest

from ident.fit import fit_gaps
from ident.fit.synthetic import synthetic_case

from test_fit import MEASURED, draw, tolerance


@pytest.mark.slow
@pytest.mark.skip(reason="known regression (issue 12, stop 19): this fit now runs past 800 s "
                         "alone, with restarts or without (175-270 s when written), and would "
                         "hit the suite's 900 s timeout; to be fixed, not hidden")
def test_collocation_recovers_the_gaps(mill, tmp_path):
    """Collocation from the mill file's designed gaps, a bite and a release of each of 2 bars.

    Measured: C46 and C57 within 2 %, C12/C34 within 0.25 mrad, nrmse 0.020
    against the linear baseline's 0.060, about 175 s CPU (the slowest fit of
    the suite: six horizon stages, the second at its 300-iteration cap).
    """
    case = synthetic_case(mill, draw(mill, 21), seed=21, n_bars=2, directory=tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no ConvergenceWarning
        res = fit_gaps(mill, case.windows)
    assert res.converged and res.solver.status == "Solve_Succeeded"
    assert res.reached_noise_floor, res.noise_ratio
    for eid in MEASURED:
        g = case.truth[eid]["gap"]
        assert abs(res.elements[eid].gap - g) <= tolerance(g), (eid, res.elements[eid].gap, g)
    assert res.nrmse < 0.5 * res.nrmse_linear
    assert set(res.elements) == set(mill.element_ids)
