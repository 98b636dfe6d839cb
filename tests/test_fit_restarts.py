"""The fit's restarts from a failing best run (ident.fit.core): which gaps a repair moves."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ident import load_mill
from ident.fit.core import _repaired_start, _shared_from_gaps
from ident.fit.model import build_fit_model
from ident.fit.problem import Estimate
from ident.model.linear import angles_from_deflections

pytestmark = pytest.mark.timeout(60)


def _estimate(model, gaps: dict[str, float], swing: dict[str, tuple[float, float]]) -> Estimate:
    """An estimate whose one window swings each element's deflection over ``swing`` (rad)."""
    mill = model.mill
    shared = _shared_from_gaps(model, gaps)
    t = np.linspace(0.0, 1.0, 200)
    lo = np.array([swing[e.id][0] for e in mill.elements])
    hi = np.array([swing[e.id][1] for e in mill.elements])
    delta = lo[None, :] + (hi - lo)[None, :] * 0.5 * (1.0 + np.sin(2 * np.pi * 3 * t))[:, None]
    n = len(mill.masses)
    X = np.zeros((t.size, model.nx))
    for i, d in enumerate(delta):
        X[i, :n] = angles_from_deflections(mill, d, model.motor_index)
    return Estimate(shared=shared, window=np.zeros((1, model.n_window)), x0=X[:1].copy(),
                    trajectories=(X,))


def test_a_gap_no_window_traverses_goes_back_to_the_mill_files(mill):
    model = build_fit_model(mill)
    gaps = {e.id: 2e-3 for e in mill.elements}
    gaps["C57"] = 15e-3  # parked where the data cannot see it
    # every element pressed 1 mrad into both flanks (g1: contact at 0, back flank at -gap),
    # C57 swinging inside its gap only
    swing = {eid: (-g - 1e-3, 1e-3) for eid, g in gaps.items()}
    swing["C57"] = (-5e-3, 1e-3)
    est = _estimate(model, gaps, swing)
    got = _repaired_start(model, est, 1e-4, 5e-4)
    assert got is not None
    for e in mill.elements:
        k = model.shared_names.index(f"{e.id}.gap")
        want = max(e.gap, 5e-4) if e.id == "C57" else gaps[e.id]
        assert got[k] == pytest.approx(want, rel=1e-9), e.id
    # everything else is the best run's
    others = [i for i, nm in enumerate(model.shared_names) if nm != "C57.gap"]
    np.testing.assert_array_equal(got[others], est.shared[others])


def test_nothing_to_repair_when_every_gap_is_traversed(mill):
    model = build_fit_model(mill)
    gaps = {e.id: 2e-3 for e in mill.elements}
    est = _estimate(model, gaps, {eid: (-g - 1e-3, 1e-3) for eid, g in gaps.items()})
    assert _repaired_start(model, est, 1e-4, 5e-4) is None
    # a traversal shallower than half the smoothing width does not count
    shallow = {eid: (-g - 1e-3, 1e-3) for eid, g in gaps.items()}
    shallow["C12"] = (-2e-3 - 4e-5, 4e-5)
    assert _repaired_start(model, _estimate(model, gaps, shallow), 1e-4, 5e-4) is not None


def test_no_repair_without_trajectories(mill):
    model = build_fit_model(mill)
    shared = _shared_from_gaps(model, {e.id: 2e-3 for e in mill.elements})
    est = Estimate(shared=shared, window=np.zeros((1, model.n_window)),
                   x0=np.zeros((1, model.nx)))
    assert _repaired_start(model, est, 1e-4, 5e-4) is None


def test_a_traversal_the_noise_could_explain_counts_as_none(mill):
    """Plantsim hsm-f1 3002's wrong basin: C57 at 14.7 mrad pressed 1.37 mrad into both
    flanks, with a standard error of 1.5 mrad from the noise: not driven across."""
    model = build_fit_model(mill)
    gaps = {e.id: 2e-3 for e in mill.elements}
    gaps["C57"] = 14.7e-3
    swing = {eid: (-g - 1.37e-3, 1.37e-3) for eid, g in gaps.items()}
    est = _estimate(model, gaps, swing)
    assert _repaired_start(model, est, 1e-4, 5e-4, {"C57": 1e-4}) is None
    got = _repaired_start(model, est, 1e-4, 5e-4, {"C57": 1.5e-3})
    assert got is not None
    k = model.shared_names.index("C57.gap")
    assert got[k] == pytest.approx(mill.element("C57").gap)


def test_series_pairs_are_split_equally_then_swapped(mill):
    """A pair of gaps in series is seen through its sum: the restarts move along that
    ridge, to the equal split first (plantsim hsm-f1 5001: the only one of four
    held-path restarts that reached the optimum), then to the swap; pairs already
    about equal are left alone."""
    from types import SimpleNamespace

    from ident.fit.core import _series_starts, series_pairs

    model = build_fit_model(mill)
    pairs = series_pairs(mill)
    assert pairs, "the test mill has elements in series"
    gaps = {e.id: 2e-3 for e in mill.elements}
    a, b = pairs[0]
    gaps[a], gaps[b] = 0.4e-3, 1.2e-3
    best = Estimate(shared=_shared_from_gaps(model, gaps), window=np.zeros((1, 1)),
                    x0=np.zeros((1, 1)))
    worse = Estimate(shared=_shared_from_gaps(model, {e.id: 9e-3 for e in mill.elements}),
                     window=np.zeros((1, 1)), x0=np.zeros((1, 1)))
    runs = [(0, None, worse, SimpleNamespace(cost=5.0, success=True), "continued"),
            (1, None, best, SimpleNamespace(cost=3.0, success=True), "held")]
    got = _series_starts(model, runs)
    tags = [t for _, t in got]
    moved = [p for p in pairs if abs(gaps[p[0]] - gaps[p[1]]) >= 0.1 * max(gaps[p[0]], gaps[p[1]])]
    assert tags == [f"split {x}/{y}" for x, y in moved] + [f"swap {x}/{y}" for x, y in moved]
    ia, ib = (model.shared_names.index(f"{e}.gap") for e in (a, b))
    split, swap = got[tags.index(f"split {a}/{b}")][0], got[tags.index(f"swap {a}/{b}")][0]
    assert split[ia] == pytest.approx(0.8e-3) and split[ib] == pytest.approx(0.8e-3)
    assert (swap[ia], swap[ib]) == pytest.approx((1.2e-3, 0.4e-3))
    others = [j for j in range(model.n_shared) if j not in (ia, ib)]
    assert np.array_equal(split[others], best.shared[others])


def _run(cost: float, success: bool, tag: str = "continued") -> tuple:
    from ident.fit.problem import SolveInfo

    info = SolveInfo(method="collocation", status="Solve_Succeeded" if success else
                     "Maximum_Iterations_Exceeded", success=success, iterations=300,
                     seconds=1.0, cost=cost)
    return (0, np.zeros(1), object(), info, tag)


def test_a_run_stopped_at_its_bound_below_every_converged_one_is_resumed():
    from ident.fit.core import RESTART_GAIN, _resume_candidate

    # plant cold-s5 1300 (diagnose_study): the data start's held path stopped at 300
    # iterations at cost 1.36, the best converged run at 22.7
    stopped = _run(1.36, False, "data")
    runs = [_run(22.7, True), _run(195.3, False, "held"), stopped]
    assert _resume_candidate(runs) is stopped
    # converged, or not below the best converged by more than RESTART_GAIN: nothing to resume
    assert _resume_candidate([_run(22.7, True), _run(1.36, True)]) is None
    assert _resume_candidate([_run(22.7, True),
                              _run(22.7 * (1 - 0.5 * RESTART_GAIN), False)]) is None
    assert _resume_candidate([_run(195.3, False), _run(22.7, True)]) is None
    # nothing converged (plant cold-s5 8100, fit_study): the lowest run stopped at a bound
    # is solved on; the verdict then says whether that converged
    alone = _run(3.0, False)
    assert _resume_candidate([_run(4.0, False), alone]) is alone
    assert _resume_candidate([_run(float("inf"), False), _run(5.0, True)]) is None
    # a run that failed otherwise (not at a bound) is not resumed
    failed = _run(1.0, False)
    failed = failed[:3] + (replace(failed[3], status="Restoration_Failed"),) + failed[4:]
    assert _resume_candidate([_run(22.7, True), failed]) is None


def _stopped(model, gaps: dict, cost: float, *, status: str = "Maximum_Iterations_Exceeded",
             infeasibility: float = 1e-9, iterations: int = 300) -> tuple:
    from ident.fit.core import _shared_from_gaps
    from ident.fit.problem import Estimate, SolveInfo, StageInfo

    est = Estimate(shared=_shared_from_gaps(model, gaps), window=np.zeros((1, 1)),
                   x0=np.zeros((1, 1)))
    stage = StageInfo(width=3e-5, status=status, success=False, iterations=iterations,
                      seconds=1.0, cost=cost, infeasibility=infeasibility)
    return est, SolveInfo(method="collocation", status=status, success=False,
                          iterations=iterations, seconds=1.0, cost=cost, stages=(stage,))


def test_a_resumed_run_that_stops_where_it_began_is_stationary():
    """plant cold-s5 8100 (fit_study): 300 iterations ran out at cost 1.4961, resumed they
    ran out again at 1.4949, feasible, the gaps 0.01 mrad from where they began."""
    from ident.fit.core import STALL_FRACTION, _stalled
    from ident.fit.model import build_fit_model
    from ident.fit.verdict import accuracy

    mill = load_mill(Path(__file__).resolve().parents[1] / "data" / "mills" / "cold-s5.toml")
    model = build_fit_model(mill, family="g1")
    gaps = {"C12": 1.19e-3, "C23": 1.24e-3, "C34": 0.03e-3, "C45": 2.50e-3}
    before = _stopped(model, gaps, 1.4961)
    near = {**gaps, "C45": 2.49e-3}
    assert _stalled(model, *before, *_stopped(model, near, 1.4949))
    # moved more than STALL_FRACTION of the accuracy: still descending
    far = {**gaps, "C45": gaps["C45"] - 1.5 * STALL_FRACTION * accuracy(gaps["C45"])}
    assert not _stalled(model, *before, *_stopped(model, far, 1.4949))
    # infeasible at the end, higher in cost, or converged/failed otherwise: not a stall
    assert not _stalled(model, *before, *_stopped(model, near, 1.4949, infeasibility=2e-3))
    assert not _stalled(model, *before, *_stopped(model, near, 1.6))
    assert not _stalled(model, *before, *_stopped(model, near, 1.4949,
                                                  status="Restoration_Failed"))
    # a bound of a few iterations (ident fit --max-iter 2): a slow descent, not a stall
    assert not _stalled(model, *before, *_stopped(model, near, 1.4949, iterations=2))


def test_a_gross_misfit_opens_the_gaps_its_channel_sees_one_at_a_time(mill, monkeypatch):
    """plantsim hsm-f1 1403 (diagnose_study): C45 at 9.1 mrad was found only from a start
    with C45 alone opened; the excursion starts open the gaps the worst channel sees,
    those without a channel of their own first, only where its model error is beyond
    any the verdict accepts."""
    from types import SimpleNamespace

    from ident.fit import core
    from ident.fit.verdict import EXCESS_AGREED_MAX, BandCheck

    model = build_fit_model(mill)
    gaps = {e.id: 1e-3 for e in mill.elements}
    gaps["C57"] = 6e-3  # already past half its critical limit: not opened again
    est = Estimate(shared=_shared_from_gaps(model, gaps), window=np.zeros((1, 1)),
                   x0=np.zeros((1, 1)))
    runs = [(0, None, est, SimpleNamespace(cost=2.0, success=True), "continued")]
    ch = list(model.measured)
    worst = "C46" if "C46" in ch else ch[-1]

    def check(excess_worst):
        ratio = {c: 1.1 for c in ch}
        rel = {c: 0.01 for c in ch}
        ratio[worst], rel[worst] = 100.0, excess_worst / np.sqrt(99.0 / 100.0)
        return BandCheck(bands=None, ratio=ratio, dof={c: 100.0 for c in ch},
                         noise_sigma={c: 1.0 for c in ch}, noise_source="windows",
                         relative=rel)

    # the worst channel sees C46 (its own) most, C45 (no channel of its own) less, C57
    # too but is open already; C34 hardly
    assert "C45" not in ch and "C46" in ch
    share = {"C45": 0.7, "C46": 0.8, "C57": 0.9, "C34": 0.05}
    iw = ch.index(worst)

    def info(sens, cov, col):
        eid = model.shared_names[col[1]].split(".")[0]
        out = np.zeros(model.ny)
        out[iw] = share.get(eid, 0.0)
        out[(iw + 1) % model.ny] = 0.5
        return out

    monkeypatch.setattr(core, "_residuals", lambda *a: np.zeros(4))
    monkeypatch.setattr(core, "collocation_sensitivity", lambda *a: None)
    monkeypatch.setattr(core, "covariance", lambda *a: None)
    monkeypatch.setattr(core, "channel_information", info)
    monkeypatch.setattr(core, "_band_check", lambda *a: check(2 * EXCESS_AGREED_MAX))
    got = core._open_starts(model, core.Collocation(), None, runs)
    assert [t for _, t in got] == ["open C45", "open C46"][:core.OPEN_MAX]
    j = model.shared_names.index("C45.gap")
    crit = next(e.gap_critical for e in mill.elements if e.id == "C45")
    assert got[0][0][j] == pytest.approx(crit)
    others = [i for i in range(model.n_shared) if i != j]
    assert np.array_equal(got[0][0][others], est.shared[others])
    # a model error the verdict could accept where starts agree: no excursion
    monkeypatch.setattr(core, "_band_check", lambda *a: check(0.5 * EXCESS_AGREED_MAX))
    assert core._open_starts(model, core.Collocation(), None, runs) == []


def test_partner_of_a_parked_series_gap_is_not_identified(mill):
    """A gap whose series partner no window drives across is not identified, whatever its
    own interval: the two trade their slack along a ridge the interval does not see
    (plantsim hsm-f1 wear draw 1602: C12 0.00 [0, 0.05] mrad beside a parked C23 9.07,
    truth 7.06 and 2.57).  Elements outside a pair, and a pair with no parked member,
    keep their verdict."""
    from ident.fit.core import _split_undetermined, series_pairs
    from ident.fit.result import ElementFit

    a, b = series_pairs(mill)[0]
    el = ElementFit(gap=1e-3, gap_ci95=(0.9e-3, 1.1e-3), gap_se=5e-5, gap_open=0.0,
                    gap_open_ci95=(0.0, 0.0), gap_open_windows=(0.0,), gap_mm=None,
                    params={}, params_se={}, identifiable=True, gap_open_identifiable=True)
    parked_el = replace(el, gap=9e-3, gap_ci95=(7e-3, 3e-2), identifiable=False,
                        reason="no window drives it across its gap")
    elements = {e.id: el for e in mill.elements}
    elements[b] = parked_el
    got = _split_undetermined(mill, elements, {b}, 3e-2)
    assert not got[a].identifiable and got[a].gap_ci95 == (0.0, 3e-2)
    assert f"series partner {b}" in got[a].reason
    assert got[b] == parked_el
    partners = {x for p in series_pairs(mill) if b in p for x in p}
    assert all(got[e.id] is el for e in mill.elements if e.id not in partners)
    assert all(not got[x].identifiable for x in partners - {b})
    # nothing parked: unchanged; the partner parked too: both keep their own reasons
    assert all(v is elements[k] for k, v in
               _split_undetermined(mill, elements, set(), 3e-2).items())
    both = _split_undetermined(mill, {**elements, a: parked_el}, {a, b}, 3e-2)
    assert both[a] is parked_el and both[b] is parked_el


def test_confirmation_vector_moves_every_gap_within_bounds(mill):
    """The start the search tries when the best run passes only under the model-error
    allowance: every gap moved off by at least the agreement tolerance (so that falling
    back to it means something), the other parameters kept, the bounds respected."""
    from ident.fit.core import _confirm_vector
    from ident.fit.verdict import agree_tolerance

    model = build_fit_model(mill)
    gaps = {e.id: 2e-3 for e in mill.elements}
    gaps[mill.elements[0].id] = 0.0
    gaps[mill.elements[1].id] = 0.95 * model.gap_max
    sv = _shared_from_gaps(model, gaps)
    got = _confirm_vector(model, sv)
    idx = [model.shared_names.index(f"{e.id}.gap") for e in mill.elements]
    assert np.all(got[idx] >= model.shared_lb[idx]) and np.all(got[idx] <= model.shared_ub[idx])
    moved = np.abs(got[idx] - sv[idx])
    assert np.all(moved > np.array([agree_tolerance(g) for g in sv[idx]]))
    rest = [j for j in range(model.n_shared) if j not in idx]
    assert np.array_equal(got[rest], sv[rest])
    assert np.array_equal(sv, _shared_from_gaps(model, gaps))  # the input is not changed
