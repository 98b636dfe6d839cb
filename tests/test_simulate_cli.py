"""``ident simulate`` writes recordings that other tools read: the official mcap reader
(JSON and protobuf encodings) and pandas (CSV)."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from ident.cli import main


def _sim(tmp_path, name, mill_path, *extra):
    out = tmp_path / name
    truth = tmp_path / (name + ".truth.json")
    code = main(["simulate", "--mill", str(mill_path), "--out", str(out), "--bars", "2",
                 "--seed", "4", "--truth", str(truth), "--quiet", *extra])
    assert code == 0
    return out, json.loads(truth.read_text())


def test_mcap_json_read_by_official_reader(tmp_path, mill_path):
    from mcap.reader import make_reader

    out, truth = _sim(tmp_path, "rec.mcap", mill_path, "--encoding", "json",
                      "--set", "C46.gap=0.006")
    assert truth["elements"]["C46"]["gap"] == pytest.approx(0.006)
    topics, n = set(), 0
    with open(out, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert {s.name for s in summary.schemas.values()} == {"ident.SampleBlock"}
        for schema, channel, message in reader.iter_messages():
            assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
            block = json.loads(message.data)
            assert message.log_time == block["t0_ns"]
            assert len(block["channels"]) == len(block["data"]) == len(block["units"])
            topics.add(channel.topic)
            n += 1
        meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        atts = {a.name for a in reader.iter_attachments()}
    assert topics == {"/telemetry/torque", "/telemetry/accel"}
    assert n > 2
    assert meta["ident.recording"]["mill"] == "hsm-f1"
    assert "mill.toml" in atts


def test_mcap_protobuf_read_by_official_reader(tmp_path, mill_path):
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    out, _ = _sim(tmp_path, "rec.mcap", mill_path, "--encoding", "protobuf", "--no-bearings")
    with open(out, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        msgs = list(reader.iter_decoded_messages())
    assert msgs
    _, channel, message, proto = msgs[0]
    assert channel.message_encoding == "protobuf"
    assert list(proto.channels) == ["T_C12", "T_C34", "T_C46", "T_C57"]
    assert proto.rate_hz == 2000.0
    assert len(proto.data) == len(proto.channels) * (len(proto.data) // len(proto.channels))
    assert np.all(np.isfinite(np.asarray(proto.data)))


def test_csv_read_by_pandas(tmp_path, mill_path):
    out, truth = _sim(tmp_path, "rec.csv", mill_path, "--no-bearings")
    df = pd.read_csv(out)
    assert df.columns[0] == "time"
    assert [c.split(" [")[0] for c in df.columns[1:]] == ["T_C12", "T_C34", "T_C46", "T_C57"]
    assert np.all(np.diff(df["time"].to_numpy()) > 0)
    # the motor-shaft torque reaches the bars' static torques (kN*m, ratio 1)
    peak = df.iloc[:, 1].max() * 1e3
    assert peak > max(b["static_torque"] for b in truth["bars"])
