"""``ident segment REC --mill M``: the cli.md JSON and exit codes."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from ident.cli import main
from ident.io import write_recording
from synth_telemetry import make_synth

CLI_KEYS = {"t_start", "t_step", "t_end", "kind", "static_torque", "step"}


@pytest.fixture(scope="module")
def recording(mill, tmp_path_factory):
    s = make_synth(mill, seed=5, duration_s=20.0, idle_s=2.0, with_accel=False)
    p = tmp_path_factory.mktemp("cli") / "rec.mcap"
    write_recording(p, s.devices)
    return s, p


def test_segment_writes_the_cli_json(tmp_path, mill_path, recording, capsys):
    synth, p = recording
    out = tmp_path / "segments.json"
    assert main(["segment", str(p), "--mill", str(mill_path), "--out", str(out), "--quiet"]) == 0
    assert capsys.readouterr().err == ""
    doc = json.loads(out.read_text())
    assert doc["recording"] == str(p) and doc["mill"] == "hsm-f1"
    assert doc["warnings"] == []
    segs = doc["segments"]
    assert len(segs) == len(synth.truth)
    for seg, tr in zip(segs, synth.truth):
        assert CLI_KEYS <= set(seg)
        assert seg["kind"] == tr.kind
        assert abs(seg["t_step"] - tr.t_step) < 0.005
        assert seg["static_torque"] == pytest.approx(tr.static, rel=0.03)
        assert seg["step"] == pytest.approx(tr.step, rel=0.03)
        assert seg["t_start"] < seg["t_step"] < seg["t_end"]


def test_segment_to_stdout_lists_warnings(tmp_path, mill, mill_path, recording, capsys):
    synth, _ = recording
    dev = synth.devices[0]
    data = dev.data.copy()
    data[1, 5000:5004] = np.nan
    p = tmp_path / "nan.csv"
    from dataclasses import replace

    write_recording(p, [replace(dev, data=data)])
    assert main(["segment", str(p), "--mill", str(mill_path)]) == 0
    captured = capsys.readouterr()
    doc = json.loads(captured.out)
    assert [w["kind"] for w in doc["warnings"]] == ["nan_run"]
    assert doc["warnings"][0]["channel"] == "T_C34"
    assert doc["warnings"][0]["t_start"] == pytest.approx(2.5)
    assert "nan_run" in captured.err  # progress and findings on stderr


def test_corrupt_file_exits_2_with_one_line(tmp_path, mill_path, recording, capsys):
    _, p = recording
    bad = tmp_path / "cut.mcap"
    bad.write_bytes(p.read_bytes()[:300])
    assert main(["segment", str(bad), "--mill", str(mill_path), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "cut.mcap" in err[0] and "nothing readable" in err[0]


def test_wrong_unit_exits_2(tmp_path, mill_path, capsys):
    p = tmp_path / "unit.csv"
    pd.DataFrame({"time": np.arange(100) / 1000.0, "T_C46 [N*m]": np.zeros(100)}).to_csv(
        p, index=False)
    assert main(["segment", str(p), "--mill", str(mill_path), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "channel 'T_C46'" in err[0] and "unit mismatch" in err[0]
