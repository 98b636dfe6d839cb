"""``ident fit REC --mill M``: the cli.md JSON, exit codes and messages.

One simulated bar (a bite and a release, 0.3 s windows) of the shipped stand
with worn spindles; the converged run is the only full fit here (the
statistics live in ``test_fit.py``).
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from ident.cli import main
from ident.fit.synthetic import synthetic_case

TRUTH = {"C46.gap": 0.006, "C46.gap_open": 0.003, "C57.gap": 0.004, "C57.gap_open": 0.001}
CLI = ["--window-s", "0.3", "--max-transients", "2", "--quiet"]


@pytest.fixture(scope="module")
def recording(mill, tmp_path_factory):
    case = synthetic_case(mill, TRUTH, seed=3, n_bars=1,
                          directory=tmp_path_factory.mktemp("fitcli"))
    return case


@pytest.mark.slow
def test_fit_writes_the_cli_json(tmp_path, mill, mill_path, recording, capsys):
    """Converged collocation fit: every element, cli.md keys, exit 0, one verdict line per element."""
    out = tmp_path / "fit.json"
    code = main(["fit", str(recording.path), "--mill", str(mill_path), "--out", str(out)] + CLI)
    err = capsys.readouterr().err.splitlines()
    doc = json.loads(out.read_text())
    assert code == 0, doc["solver"]
    assert len(err) == len(mill.element_ids), err
    for line, eid in zip(err, mill.element_ids):
        assert line.startswith(f"ident fit: {eid} gap ") and "identified" in line
        assert ("not identified: " in line) == (not doc["elements"][eid]["identified"])
    assert doc["mill"] == "hsm-f1" and doc["family"] == "g1"
    assert set(doc["elements"]) == set(mill.element_ids)
    for eid, el in doc["elements"].items():
        assert {"gap", "gap_ci95", "gap_open", "gap_mm", "params", "identified"} <= set(el)
        assert el["identified"] or el["reason"]
        lo, hi = el["gap_ci95"]
        assert 0.0 <= lo <= el["gap"] <= hi
        assert 0.0 <= el["gap_open"] <= el["gap"] + 1e-12
        e = mill.element(eid)
        assert el["gap_mm"] == pytest.approx(el["gap"] / e.ratio * e.radius * 1e3)
    assert {"nrmse", "nrmse_linear"} <= set(doc["metrics"])
    assert doc["metrics"]["nrmse"] < doc["metrics"]["nrmse_linear"]
    s = doc["solver"]
    assert s["status"] == "Solve_Succeeded" and s["converged"] is True
    assert s["iterations"] > 0 and s["seconds"] > 0
    assert doc["windows_used"] and doc["recording"] == str(recording.path)
    # --held auto: the continued fit reached the noise floor, so no held path was run
    assert doc["metrics"]["reached_noise_floor"] is True
    assert [st["path"] for st in s["starts"]] == ["continued"] and s["path"] == "continued"
    for eid in ("C46", "C57"):  # the worn spindles, measured directly
        assert doc["elements"][eid]["gap"] == pytest.approx(TRUTH[f"{eid}.gap"], rel=0.1)
        assert doc["elements"][eid]["identified"] is True, doc["elements"][eid]


def test_fit_not_converged_writes_json_and_exits_0(tmp_path, mill_path, recording, capsys):
    """Two IPOPT iterations per stage: honest status in the JSON, nothing identified, exit 0
    (cli.md: exit 0 whenever a result was written)."""
    out = tmp_path / "fit.json"
    code = main(["fit", str(recording.path), "--mill", str(mill_path), "--out", str(out),
                 "--max-iter", "2", "--no-uncertainty"] + CLI)
    assert code == 0
    err = capsys.readouterr().err.splitlines()
    doc = json.loads(out.read_text())
    assert len(err) == len(doc["elements"])
    assert all("not identified: the solver did not converge (status "
               "Maximum_Iterations_Exceeded)" in line for line in err), err
    assert not any(el["identified"] for el in doc["elements"].values())
    assert doc["solver"]["converged"] is False
    assert doc["solver"]["status"] == "Maximum_Iterations_Exceeded"
    assert set(doc["elements"]) >= {"C46", "C57"}
    # --held auto: nothing converged, so the first start was solved on before the held path
    # was tried; then the lowest run was solved on again (RESUME_MAX in all), each stopped
    # at the bound again
    from ident.fit.core import RESUME_MAX

    paths = [s["path"] for s in doc["solver"]["starts"]]
    assert paths[:3] == ["continued", "resume", "held"]
    assert 1 <= paths.count("resume") <= RESUME_MAX
    assert set(paths[3:]) <= {"resume"}
    assert not any(s["converged"] for s in doc["solver"]["starts"])


def test_corrupt_recording_exits_2_naming_the_file(tmp_path, mill_path, recording, capsys):
    bad = tmp_path / "cut.mcap"
    bad.write_bytes(recording.path.read_bytes()[:300])
    assert main(["fit", str(bad), "--mill", str(mill_path), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cut.mcap" in err[0]


def test_recording_without_torque_exits_2_naming_channels(tmp_path, mill_path, capsys):
    p = tmp_path / "speed.csv"
    pd.DataFrame({"time": np.arange(2000) / 1000.0, "X_other [N*m]": np.zeros(2000)}).to_csv(
        p, index=False)
    assert main(["fit", str(p), "--mill", str(mill_path), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "T_C46" in err[0]


@pytest.mark.parametrize("opt, value, name", [("--max-transients", "0", "--max-transients"),
                                              ("--starts", "0", "--starts"),
                                              ("--window-s", "-1", "--window-s"),
                                              ("--max-iter", "0", "--max-iter")])
def test_bad_option_values_exit_2(mill_path, recording, capsys, opt, value, name):
    assert main(["fit", str(recording.path), "--mill", str(mill_path), opt, value,
                 "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and name in err[0]


def test_unknown_set_key_exits_2(mill_path, recording, capsys):
    assert main(["fit", str(recording.path), "--mill", str(mill_path), "--set",
                 "C99.gap=0.001", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "C99" in err[0]


def test_held_path_is_reported(tmp_path, mill_path, recording):
    """--held always: every start also runs with the gaps held through the continuation."""
    out = tmp_path / "fit.json"
    main(["fit", str(recording.path), "--mill", str(mill_path), "--out", str(out), "--held",
          "always", "--no-uncertainty"] + CLI)
    doc = json.loads(out.read_text())
    assert [s["path"] for s in doc["solver"]["starts"]] == ["continued", "held"]
    assert doc["solver"]["path"] in ("continued", "held")
    best = min(s["cost"] for s in doc["solver"]["starts"] if s["converged"])
    assert any(s["cost"] == best and s["path"] == doc["solver"]["path"]
               for s in doc["solver"]["starts"])


def test_start_from_an_earlier_fit(tmp_path, mill, mill_path, recording):
    """--start-from: the start is the earlier fit's gaps (--set still wins), reported.

    Only the start is asserted, so the budget (``--time-budget``) stops the fit after its
    first run: from this start the restart rounds ran on for 800 s."""
    prev = tmp_path / "prev.json"
    gaps = {e.id: e.gap for e in mill.elements}
    gaps.update({"C46": 0.0051, "C57": 0.0032})
    prev.write_text(json.dumps({"mill": mill.name, "elements": {
        k: {"gap": v, "gap_open": 0.0} for k, v in gaps.items()}}))
    out = tmp_path / "fit.json"
    main(["fit", str(recording.path), "--mill", str(mill_path), "--out", str(out),
          "--start-from", str(prev), "--set", "C12.gap=0.0012", "--no-uncertainty",
          "--held", "never", "--time-budget", "1"] + CLI)
    start = json.loads(out.read_text())["solver"]["starts"][0]["gaps"]
    assert start == pytest.approx({**gaps, "C12": 0.0012})


@pytest.mark.parametrize("content, match", [
    (None, "cannot read a fit JSON"),
    ("{not json", "cannot read a fit JSON"),
    ('{"mill": "other", "elements": {"C46": {"gap": 0.004}}}', "not 'hsm-f1'"),
    ('{"mill": "hsm-f1", "elements": {"C99": {"gap": 0.004}}}', "no gap of the mill's"),
    ('[1, 2]', "not an 'ident fit' JSON"),
])
def test_start_from_a_bad_file_exits_2(tmp_path, mill_path, recording, capsys, content, match):
    prev = tmp_path / "prev.json"
    if content is not None:
        prev.write_text(content)
    assert main(["fit", str(recording.path), "--mill", str(mill_path), "--start-from",
                 str(prev), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and match in err[0] and "prev.json" in err[0]


@pytest.mark.parametrize("content", [None, b"not a joblib file"])
def test_a_bad_wear_model_exits_2_before_the_fit(tmp_path, mill_path, recording, capsys,
                                                   content):
    model = tmp_path / "model.joblib"
    if content is not None:
        model.write_bytes(content)
    assert main(["fit", str(recording.path), "--mill", str(mill_path), "--model", str(model),
                 "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "model.joblib" in err[0]


def test_ramp_polish_is_on_unless_turned_off():
    """``ident fit`` polishes the load ramps' shape by default (``Collocation``'s
    default), and ``--no-ramp-polish`` turns it off, with ``--max-iter`` or without."""
    import argparse

    from ident.cli import fit as cli_fit

    sub = argparse.ArgumentParser().add_subparsers()
    cli_fit.add_parser(sub)
    parser = sub.choices["fit"]
    base = ["rec.mcap", "--mill", "mill.toml"]
    assert cli_fit._method(parser.parse_args(base)).ramp_polish
    assert not cli_fit._method(parser.parse_args(base + ["--no-ramp-polish"])).ramp_polish
    m = cli_fit._method(parser.parse_args(base + ["--no-ramp-polish", "--max-iter", "50"]))
    assert not m.ramp_polish and m.max_iter == 50
