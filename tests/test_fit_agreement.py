"""The verdict's agreement of starts (ident.fit.verdict, 3.): pure functions, no solve."""

from __future__ import annotations

import pytest

from ident.fit.verdict import agree_tolerance, agreement, confirmation_start

pytestmark = pytest.mark.timeout(60)


def test_agree_tolerance_is_five_percent_or_a_fifth_of_a_milliradian():
    assert agree_tolerance(0.01) == pytest.approx(5e-4)
    assert agree_tolerance(1e-3) == pytest.approx(2e-4)
    assert agree_tolerance(0.0) == pytest.approx(2e-4)


def test_confirmation_start_moves_every_gap_out_of_the_tolerance():
    gaps = {"C12": 2e-3, "C23": 4e-3, "C34": 0.0, "C45": 5e-4, "C56": 8e-3}
    moved = confirmation_start(gaps)
    assert list(moved) == list(gaps)
    for eid, g in gaps.items():
        assert abs(moved[eid] - g) > agree_tolerance(g), eid
        assert moved[eid] >= 0.0
    # neighbours in series move apart: up, down, up, up (under 1 mrad), up
    assert moved["C12"] > gaps["C12"] and moved["C23"] < gaps["C23"]
    assert moved["C45"] > gaps["C45"]


def test_a_run_from_elsewhere_that_falls_back_confirms_only_the_gaps_it_moved():
    best = {"A": 4e-3, "B": 2e-3, "C": 1e-3}
    # started A and B off, C at the best: ended back at A, elsewhere for B
    runs = [({"A": 6e-3, "B": 1.3e-3, "C": 1e-3}, {"A": 4.05e-3, "B": 3.0e-3, "C": 1e-3}, True,
             2.01)]
    got = agreement(best, runs, 2.0)
    assert got == {"A": True, "B": False, "C": False}  # C never moved: no evidence


def test_a_run_that_ends_in_another_minimum_confirms_nothing():
    """Back at the best gap of A, but 10 % higher in cost: another optimum."""
    best = {"A": 4e-3, "B": 2e-3}
    runs = [({"A": 6e-3, "B": 1.3e-3}, {"A": 4.0e-3, "B": 2.0e-3}, True, 2.2)]
    assert agreement(best, runs, 2.0) == {"A": False, "B": False}
    runs = [({"A": 6e-3, "B": 1.3e-3}, {"A": 4.0e-3, "B": 2.0e-3}, True, 2.015)]
    assert agreement(best, runs, 2.0) == {"A": True, "B": True}


def test_an_unconverged_run_confirms_nothing():
    best = {"A": 4e-3}
    runs = [({"A": 6e-3}, {"A": 4e-3}, False, 1.0)]
    assert agreement(best, runs, 1.0) == {"A": False}
    assert agreement(best, [], 1.0) == {"A": False}


def _check(ratio: dict, relative: dict):
    from ident.fit.noise import Bands
    from ident.fit.verdict import BandCheck
    bd = Bands(transient=(5.0, 100.0), noise=(150.0, 250.0))
    return BandCheck(bands=bd, ratio=ratio, dof={c: 100.0 for c in ratio},
                     noise_sigma={c: 1.0 for c in ratio}, noise_source="recording",
                     relative=relative)


def test_excess_takes_the_noise_out_of_the_residual():
    """excess = relative * sqrt((ratio - 1) / ratio): the misfit above the noise over the
    transient (closed form), 0 at or below the noise."""
    c = _check({"a": 4.0, "b": 0.8, "c": 101.0}, {"a": 0.1, "b": 0.5, "c": 0.05})
    assert c.excess("a") == pytest.approx(0.1 * (3 / 4) ** 0.5)
    assert c.excess("b") == 0.0
    assert c.excess("c") == pytest.approx(0.05 * (100 / 101) ** 0.5)
    assert c.excess("missing") != c.excess("missing")  # NaN


def test_a_channel_passes_at_the_noise_or_with_a_small_model_error():
    from ident.fit.noise import BAND_RATIO_MAX
    from ident.fit.verdict import EXCESS_AGREED_MAX, EXCESS_MAX
    assert EXCESS_MAX < EXCESS_AGREED_MAX
    c = _check({"quiet": 1.5, "model": 30.0, "off": 30.0, "nan": float("nan")},
               {"quiet": 0.6, "model": 0.9 * EXCESS_MAX, "off": 1.2 * EXCESS_MAX, "nan": 0.01})
    assert 1.5 <= BAND_RATIO_MAX
    assert c.passes("quiet")  # at the noise: however small the transient
    assert c.passes("model")  # 30x the noise, yet a model error under EXCESS_MAX
    assert not c.passes("off")
    assert c.passes("off", EXCESS_AGREED_MAX)
    assert not c.passes("nan")
    assert not c.all_pass


def _element(gap: float, half: float, half_noise: float = float("nan")):
    from ident.fit.result import ElementFit
    return ElementFit(gap=gap, gap_ci95=(max(gap - half, 0.0), gap + half), gap_se=half / 1.96,
                      gap_open=0.0, gap_open_ci95=(0.0, 0.0), gap_open_windows=(0.0,),
                      gap_mm=None, params={}, params_se={}, identifiable=True,
                      gap_open_identifiable=True, gap_se_noise=half_noise / 1.96)


def test_an_interval_wider_than_the_accuracy_bounds_the_gap_but_does_not_identify_it():
    """4. of the verdict: a gap whose channels fit is identified only when its 95 % interval is
    within max(10 %, 0.3 mrad) (the accuracy by which a gap counts as right); wider, it is
    ``bounded`` with that reason; a gap the band check rejects is neither.  Where the channels
    are at the noise, the interval's noise part and the 2 % floor are judged."""
    from types import SimpleNamespace

    import numpy as np

    import ident
    from ident.fit.verdict import accuracy, verdicts
    mill = ident.load_mill("data/mills/hsm-f1.toml")
    measured = tuple(c.element for c in mill.torque_channels())
    assert measured == ("C12", "C34", "C46", "C57")
    model = SimpleNamespace(mill=mill, measured=measured)
    assert accuracy(9e-3) == pytest.approx(9e-4) and accuracy(1e-3) == pytest.approx(3e-4)
    els = {e.id: _element(1e-3, 2e-4) for e in mill.elements}
    # C12's channel at the noise: +-20 % in all, +-0.2 mrad from the noise -> identified
    els["C12"] = _element(9e-3, 1.8e-3, 0.2e-3)
    # C34's channel keeps a model error (30 times the noise, 1 % of the transient): +-20 %
    # -> bounded, its noise part notwithstanding
    els["C34"] = _element(9e-3, 1.8e-3, 0.2e-3)
    els["C46"] = _element(9e-3, 1.8e-3, 0.2e-3)  # its channel is off: neither
    els["C57"] = _element(9e-3, 0.85e-3)  # within 10 %: identified
    info = {e.id: np.eye(len(measured))[measured.index(e.id)] if e.id in measured
            else np.ones(len(measured)) for e in mill.elements}
    check = _check({"C12": 1.0, "C34": 30.0, "C46": 50.0, "C57": 30.0},
                   {"C12": 0.01, "C34": 0.01, "C46": 0.5, "C57": 0.01})
    out = verdicts(els, model=model, problem=None, check=check, converged=True, status="ok",
                   information=info, moves=None)
    assert out["C12"].identified and not out["C12"].bounded and out["C12"].basis
    assert out["C57"].identified
    assert not out["C34"].identified and out["C34"].bounded
    assert "(+-1.80 mrad) is wider than max(10 %, 0.3 mrad)" in out["C34"].reason
    assert not out["C46"].identified and not out["C46"].bounded
    assert "transient band" in out["C46"].reason
    # the noise part alone wider than the accuracy: bounded at the noise too
    els["C12"] = _element(9e-3, 1.8e-3, 1.2e-3)
    out = verdicts(els, model=model, problem=None, check=check, converged=True, status="ok",
                   information=info, moves=None)
    assert out["C12"].bounded and not out["C12"].identified
    unconverged = verdicts(els, model=model, problem=None, check=check, converged=False,
                           status="Maximum_Iterations_Exceeded", information=info, moves=None)
    assert not any(v.identified or v.bounded for v in unconverged.values())


def test_the_summary_line_says_bounded():
    """``ident fit``'s stderr line per element names a bounded gap as such, still 'not identified'."""
    from dataclasses import replace
    from types import SimpleNamespace

    from ident.cli.fit import element_summary
    els = {"C12": replace(_element(9e-3, 1.8e-3), bounded=True, reason="wide"),
           "C34": replace(_element(2e-3, 1e-4), identified=True),
           "C46": replace(_element(2e-3, 1e-4), reason="off")}
    lines = element_summary(SimpleNamespace(elements=els))
    assert lines[0] == "C12 gap 9.00 mrad [7.20, 10.80] bounded, not identified: wide"
    assert lines[1].endswith("identified") and "not" not in lines[1]
    assert lines[2].endswith("not identified: off") and "bounded" not in lines[2]
