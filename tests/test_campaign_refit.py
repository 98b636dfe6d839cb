"""Refit from neighbours: the campaign's deterministic second pass (ident.store.refit)."""

from __future__ import annotations

import pytest

from ident.store import load_results, open_store, run_campaign
from ident.store.refit import neighbour_starts

from test_campaign_doubles import double_process, write_double_recording

DAY = 86_400 * 10**9


def _fit(name: str, day: float, identified: set[str], **gaps: float) -> dict:
    return {"file_name": name, "content_sha256": name * 2, "t0_ns": int(day * DAY),
            "gaps": gaps, "identified": identified}


# ---- the choice ------------------------------------------------------------------------
def test_nearest_identified_recording_in_time_earlier_on_a_tie():
    fits = [_fit("a", 0, {"C12", "C46"}, C12=0.001, C46=0.003),
            _fit("b", 10, {"C12"}, C12=0.0011, C46=0.0),
            _fit("c", 20, {"C12", "C46"}, C12=0.0012, C46=0.005),
            _fit("d", 24, {"C12"}, C12=0.0013, C46=0.02)]
    r = {x.file_name: x for x in neighbour_starts(fits)}
    assert set(r) == {"b", "d"}
    assert r["b"].neighbour == "a"  # 10 days either way: the earlier one
    assert r["d"].neighbour == "c" and r["d"].missing == ("C46",)
    # the neighbour's gaps, the recording's own identified ones kept
    assert dict(r["d"].starts) == {"C12": 0.0013, "C46": 0.005}
    # the same choice whatever order the fits come in
    assert neighbour_starts(fits[::-1]) == neighbour_starts(fits)


def test_no_refit_without_a_recording_that_identified_more():
    assert neighbour_starts([]) == ()
    # an element nobody identified is not a reason to refit
    fits = [_fit("a", 0, {"C12"}, C12=0.001), _fit("b", 1, {"C12"}, C12=0.001)]
    assert neighbour_starts(fits) == ()
    # the neighbour is the one that identified most of what is missing, then the nearest
    fits = [_fit("a", 0, {"C46", "C57"}, C46=0.004, C57=0.003),
            _fit("b", 5, set(), C46=0.0, C57=0.0),
            _fit("c", 6, {"C46"}, C46=0.0045, C57=0.0),
            _fit("d", 30, {"C57"}, C46=0.0, C57=0.004)]
    r = {x.file_name: x for x in neighbour_starts(fits)}
    assert r["b"].neighbour == "a" and r["b"].missing == ("C46", "C57")
    assert r["c"].neighbour == "a" and r["d"].neighbour == "c"
    assert all(g >= 0 for x in r.values() for _, g in x.starts)


# ---- the campaign ----------------------------------------------------------------------
@pytest.fixture
def campaign(tmp_path):
    """Six recordings; C46 grows and the fits of days 15 and 25 do not identify it."""
    folder = tmp_path / "c"
    for i in range(6):
        lost = i in (3, 5)
        write_double_recording(folder / f"r{i}.mcap", day=5 * i, seed=i,
                               gaps={"C46": 0.002 + 3e-4 * i},
                               identified=["C12", "C57"] if lost else ["C12", "C46", "C57"],
                               refit_identifies=["C46"])
    return folder


def test_campaign_refits_from_neighbours_and_keeps_the_history(campaign, mill, tmp_path):
    url = f"sqlite:///{tmp_path}/r.db"
    s = run_campaign(campaign, mill, url, workers=0, process=double_process, progress=False)
    assert (s.n_done, s.n_failed, s.n_refit) == (6, 0, 2)
    assert s.to_dict()["refitted"] == 2
    res = load_results(url)
    assert len(res["recordings"]) == 6  # the report sees one row per recording: the refit
    er = res["element_results"]
    c46 = er[er["element"] == "C46"].set_index("file_name")
    assert c46["identifiable"].all()
    q = res["quality_issues"]
    notes = dict(zip(q.loc[q["kind"] == "refit_from_neighbour", "file_name"],
                     q.loc[q["kind"] == "refit_from_neighbour", "message"]))
    assert set(notes) == {"r3.mcap", "r5.mcap"}
    assert "r2.mcap" in notes["r3.mcap"] and "r4.mcap" in notes["r5.mcap"]
    assert "did not identify C46" in notes["r3.mcap"]
    hist = load_results(url, latest_only=False)
    assert len(hist["recordings"]) == 8  # the first fits stay
    first = hist["element_results"]
    assert (~first[(first["element"] == "C46")]["identifiable"]).sum() == 2

    # a rerun finds everything stored, refits included
    again = run_campaign(campaign, mill, url, workers=0, process=double_process, progress=False)
    assert (again.n_done, again.n_skipped, again.n_refit) == (0, 6, 0)
    with open_store(url) as st:
        assert st.count("recordings") == 8


def test_refit_off_and_an_interrupted_second_pass_is_finished(campaign, mill, tmp_path):
    url = f"sqlite:///{tmp_path}/r.db"
    s = run_campaign(campaign, mill, url, workers=0, process=double_process, progress=False,
                     refit=False)
    assert s.n_refit == 0
    with open_store(url) as st:
        assert st.count("recordings") == 6
    # the next run has nothing new to process but does the missing second pass
    s = run_campaign(campaign, mill, url, workers=0, process=double_process, progress=False)
    assert (s.n_done, s.n_skipped, s.n_refit) == (0, 6, 2)
