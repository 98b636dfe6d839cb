"""Round trips of recordings through every format, ours and others' writers.

Truth is the synthetic generator's RawDevices (tests/synth_telemetry.py): what we
read must be what was written, converted to SI through the mill file's sensor map.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pandas as pd
import pytest

from ident.errors import DataQualityWarning
from ident.io import (RawDevice, Recording, align_devices, read_recording, reduced_torques,
                      write_recording)
from ident.io.sampleblock import json_schema, protobuf_schema
from ident.units import G0
from synth_telemetry import T0_NS, make_synth

FACTOR = {"kN*m": 1e3, "g": G0}


@pytest.fixture(scope="module")
def synth(mill):
    return make_synth(mill, seed=7, duration_s=12.0, idle_s=2.0)


def assert_same(rec: Recording, devices, *, rtol=1e-6):
    """Every written channel comes back in SI, sample for sample, on the right times."""
    origin = min(d.t0_ns for d in devices)
    for d in devices:
        dev = rec.device_of(d.channels[0])
        frame = rec.frames[dev]
        assert rec.rates_hz[dev] == pytest.approx(d.rate_hz, rel=1e-9)
        assert frame.index.name == "time_s"
        assert len(frame) == d.n_samples
        t_expect = (d.t0_ns - origin) / 1e9 + np.arange(d.n_samples) / d.rate_hz
        np.testing.assert_allclose(frame.index.to_numpy(), t_expect, atol=1e-9)
        for i, c in enumerate(d.channels):
            got = frame[c].to_numpy()
            assert got.dtype == np.float32
            expect = d.data[i].astype(np.float64) * FACTOR[d.units[i]]
            np.testing.assert_allclose(got, expect, rtol=rtol, atol=1e-3, equal_nan=True)


@pytest.mark.parametrize("encoding", ["protobuf", "json"])
def test_mcap_round_trip(tmp_path, mill, mill_path, synth, encoding):
    p = tmp_path / f"r-{encoding}.mcap"
    meta = {"mill": "hsm-f1", "stand": "F1", "campaign": "c1", "recording_id": "r-001"}
    write_recording(p, synth.devices, encoding=encoding, metadata=meta,
                    mill_toml=mill_path.read_text())
    rec = read_recording(p, mill)
    assert_same(rec, synth.devices)
    assert rec.metadata == meta
    assert rec.mill_toml == mill_path.read_text()
    assert rec.t0_ns == T0_NS
    assert rec.issues == ()
    assert set(rec.frames) == {"/telemetry/torque", "/telemetry/accel"}


def test_mcap_attached_mill_is_used_without_one(tmp_path, mill_path, synth):
    p = tmp_path / "r.mcap"
    write_recording(p, synth.devices, mill_toml=mill_path.read_text())
    rec = read_recording(p)  # the sensor map comes from the attachment
    assert_same(rec, synth.devices)


@pytest.mark.parametrize("time_format", ["seconds", "iso"])
def test_csv_round_trip_with_siblings(tmp_path, mill, synth, time_format):
    short = [dataclasses.replace(d, data=d.data[:, : int(d.rate_hz * 3)]) for d in synth.devices]
    p = tmp_path / "r.csv"
    write_recording(p, short, time_format=time_format)
    assert (tmp_path / "r.accel.csv").is_file()
    assert (tmp_path / "r.csv").read_text().splitlines()[0] == \
        "time,T_C12 [kN*m],T_C34 [kN*m],T_C46 [kN*m],T_C57 [kN*m]"
    rec = read_recording(p, mill)
    assert_same(rec, short)
    if time_format == "iso":
        assert rec.t0_ns == T0_NS
    only = read_recording(p, mill, siblings=False)
    assert set(only.channels) == set(short[0].channels)


def test_different_rates_and_starts_align(tmp_path, mill):
    t = np.arange(2000) / 1000.0
    torque = RawDevice("/t", 1000.0, T0_NS, ("T_C12",), ("kN*m",),
                       np.sin(2 * np.pi * 3 * t)[None, :].astype(np.float32))
    ta = np.arange(4000) / 4000.0 + 0.25
    accel = RawDevice("/a", 4000.0, T0_NS + 250_000_000, ("A_B23_v",), ("g",),
                      np.cos(2 * np.pi * 2 * ta)[None, :].astype(np.float32))
    p = tmp_path / "two.mcap"
    write_recording(p, [torque, accel], block_samples=128)
    rec = read_recording(p, mill, channels=["T_C12", "A_B23_v"])
    assert_same(rec, [torque, accel])
    assert float(rec.frames["/a"].index[0]) == pytest.approx(0.25)
    al = align_devices(rec)
    f = al.frames["aligned"]
    assert al.rates_hz["aligned"] == 4000.0
    # the 1 kHz torque interpolated onto 4 kHz: a smooth sine stays within 1e-3 kN*m
    tt = f.index.to_numpy()
    ok = np.isfinite(f["T_C12"].to_numpy())
    np.testing.assert_allclose(f["T_C12"].to_numpy()[ok], 1e3 * np.sin(2 * np.pi * 3 * tt[ok]),
                               atol=1.0)
    assert np.isnan(f["A_B23_v"].to_numpy()[tt < 0.249]).all()
    down = align_devices(rec, rate_hz=1000.0).frames["aligned"]
    assert len(down) == 2000
    np.testing.assert_allclose(down["A_B23_v"].to_numpy()[300:1200],
                               G0 * np.cos(2 * np.pi * 2 * down.index.to_numpy()[300:1200]),
                               atol=0.01)
    assert np.isnan(down["A_B23_v"].to_numpy()[1300:]).all()  # after its last sample
    aligned = read_recording(p, mill, align=True, warn=False)
    assert aligned.frames.keys() == {"aligned"}


def test_reduced_torques_divide_by_ratio(tmp_path, mill, synth):
    p = tmp_path / "r.mcap"
    write_recording(p, synth.devices[:1])
    rec = read_recording(p, mill)
    red = reduced_torques(rec, mill)
    for c in ("T_C12", "T_C34", "T_C46", "T_C57"):
        ratio = mill.element(mill.channel(c).element).ratio
        np.testing.assert_allclose(red[c].to_numpy(), rec.channel(c).to_numpy() / ratio,
                                   rtol=1e-6)
    assert red.index.equals(rec.frames["/telemetry/torque"].index)


# ---- files from other writers ---------------------------------------------------------------
def _blocks(dev: RawDevice, n: int):
    for s in range(0, dev.n_samples, n):
        yield dev.t0_ns + round(s * 1e9 / dev.rate_hz), dev.data[:, s:s + n]


def test_official_mcap_writer_json_other_shapes(tmp_path, mill, synth):
    """Pretty-printed JSON, keys in another order, ints, nulls; blocks out of order."""
    from mcap.writer import CompressionType, Writer

    dev = synth.devices[0]
    data = dev.data.copy()
    data[1, 100:105] = np.nan
    dev = dataclasses.replace(dev, data=data)
    p = tmp_path / "official.mcap"
    blocks = list(_blocks(dev, 333))
    order = np.random.default_rng(0).permutation(len(blocks))
    with open(p, "wb") as fh:
        w = Writer(fh, compression=CompressionType.NONE, chunk_size=64 * 1024)
        w.start()
        sid = w.register_schema("ident.SampleBlock", "jsonschema", json_schema())
        cid = w.register_channel("/strain", "json", sid)
        for k in order:
            t0, d = blocks[k]
            rows = [[None if np.isnan(v) else (int(v) if v == int(v) else float(v))
                     for v in row.tolist()] for row in d]
            msg = {"data": rows, "units": list(dev.units), "channels": list(dev.channels),
                   "rate_hz": int(dev.rate_hz), "t0_ns": t0}
            w.add_message(cid, log_time=t0, data=json.dumps(msg, indent=1).encode(),
                          publish_time=t0)
        w.finish()
    with pytest.warns(DataQualityWarning, match=r"official\.mcap, channel 'T_C34', t=0\.0500 s: "
                      r"nan_run: 5 NaN samples"):
        rec = read_recording(p, mill)
    assert_same(rec, [dev])
    assert [i.kind for i in rec.issues] == ["nan_run"]
    assert rec.issues[0].channel == "T_C34"
    assert rec.issues[0].t_start == pytest.approx(100 / dev.rate_hz)


@pytest.mark.parametrize("packed", [True, False])
def test_official_protobuf_writer(tmp_path, mill, synth, packed):
    """mcap_protobuf's writer with the message class built from our schema."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    from mcap_protobuf.writer import Writer

    fds = descriptor_pb2.FileDescriptorSet.FromString(protobuf_schema())
    if not packed:  # a writer that sends repeated floats one by one (legal proto)
        fds.file[0].name = "ident/sample_block_unpacked.proto"
        fds.file[0].message_type[0].field[4].options.packed = False
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fds.file[0])
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName("ident.SampleBlock"))
    dev = dataclasses.replace(synth.devices[0], data=synth.devices[0].data[:, :5000])
    p = tmp_path / "pb.mcap"
    with open(p, "wb") as fh, Writer(fh) as w:
        for t0, d in _blocks(dev, 500):
            msg = cls(t0_ns=t0, rate_hz=dev.rate_hz, channels=dev.channels, units=dev.units,
                      data=d.ravel().tolist())
            w.write_message("/telemetry/torque", msg, log_time=t0, publish_time=t0)
    rec = read_recording(p, mill)
    assert_same(rec, [dev])


def test_unchunked_mcap_is_streamed(tmp_path, mill, synth):
    from mcap.writer import Writer

    from ident.io.sampleblock import encode_protobuf

    dev = dataclasses.replace(synth.devices[0], data=synth.devices[0].data[:, :4000])
    p = tmp_path / "flat.mcap"
    with open(p, "wb") as fh:
        w = Writer(fh, use_chunking=False)
        w.start()
        sid = w.register_schema("ident.SampleBlock", "protobuf", protobuf_schema())
        cid = w.register_channel("/t", "protobuf", sid)
        for t0, d in _blocks(dev, 400):
            w.add_message(cid, t0, encode_protobuf(t0, dev.rate_hz, dev.channels, dev.units, d),
                          t0)
        w.finish()
    rec = read_recording(p, mill)
    assert_same(rec, [dev])
    assert rec.issues == ()


def test_pandas_csv_shapes(tmp_path, mill, synth):
    """No unit header, time column not first, float_format; index named time; ISO times."""
    dev = synth.devices[0]
    n = 4000
    t = np.arange(n) / dev.rate_hz
    df = pd.DataFrame({c: dev.data[i, :n] for i, c in enumerate(dev.channels)})
    df.insert(2, "time", t)
    df = df[["T_C57", "T_C34", "time", "T_C12", "T_C46"]]
    p1 = tmp_path / "pandas1.csv"
    df.to_csv(p1, index=False, float_format="%.9g")
    short = dataclasses.replace(dev, data=dev.data[:, :n])
    assert_same(read_recording(p1, mill), [short])
    p2 = tmp_path / "pandas2.csv"
    df.set_index("time").to_csv(p2)
    assert_same(read_recording(p2, mill), [short])
    p3 = tmp_path / "pandas3.csv"
    iso = df.copy()
    iso["time"] = pd.Timestamp(T0_NS, tz="UTC") + pd.to_timedelta(np.arange(n) * 500_000, "ns")
    iso.to_csv(p3, index=False)
    rec = read_recording(p3, mill)
    assert_same(rec, [short])
    assert rec.t0_ns == T0_NS


def test_semicolon_decimal_comma_csv(tmp_path, mill, synth):
    dev = synth.devices[0]
    n = 3000
    df = pd.DataFrame({f"{c} [kN*m]": dev.data[i, :n] for i, c in enumerate(dev.channels)})
    df.insert(0, "time", np.arange(n) / dev.rate_hz)
    p = tmp_path / "export.csv"
    df.to_csv(p, sep=";", decimal=",", index=False)
    assert "0,0005;" in p.read_text().splitlines()[2]
    rec = read_recording(p, mill)
    assert_same(rec, [dataclasses.replace(dev, data=dev.data[:, :n])])


def test_raw_units_apply_scale_and_offset(tmp_path, mill):
    ch = dataclasses.replace(mill.channel("T_C12"), scale=0.05, offset=-2.0)
    raw_mill = dataclasses.replace(mill, channels=(ch,) + mill.channels[1:])
    counts = np.array([[0, 100, -200, 40]], dtype=np.float32)
    dev = RawDevice("/t", 100.0, T0_NS, ("T_C12",), ("raw",), counts)
    p = tmp_path / "raw.mcap"
    write_recording(p, [dev])
    rec = read_recording(p, raw_mill, warn=False)
    np.testing.assert_allclose(rec.channel("T_C12").to_numpy(), (0.05 * counts[0] - 2.0) * 1e3,
                               rtol=1e-6)
    # a CSV without units counts as recorded values: scale and offset apply too
    pd.DataFrame({"time": [0.0, 0.01, 0.02, 0.03], "T_C12": counts[0]}).to_csv(
        tmp_path / "raw.csv", index=False)
    rec = read_recording(tmp_path / "raw.csv", raw_mill, warn=False)
    np.testing.assert_allclose(rec.channel("T_C12").to_numpy(), (0.05 * counts[0] - 2.0) * 1e3,
                               rtol=1e-6)


def test_channels_selection_reads_less(tmp_path, mill, synth):
    p = tmp_path / "r.mcap"
    write_recording(p, synth.devices)
    rec = read_recording(p, mill, channels=["T_C46", "A_B45_h"])
    assert set(rec.channels) == {"T_C46", "A_B45_h"}
    assert not any(i.kind == "missing_channel" for i in rec.issues)


def test_writer_refuses_bad_input(tmp_path, synth):
    from ident.errors import RecordingError

    with pytest.raises(RecordingError, match=r"unknown recording format '\.txt'"):
        write_recording(tmp_path / "r.txt", synth.devices)
    bad = dataclasses.replace(synth.devices[0], units=("kN*m",))
    with pytest.raises(RecordingError, match=r"4 channels but 1 units"):
        write_recording(tmp_path / "r.mcap", [bad])
    with pytest.raises(RecordingError, match=r"encoding must be 'protobuf' or 'json'; got 'xml'"):
        write_recording(tmp_path / "r.mcap", synth.devices, encoding="xml")
    assert not list(tmp_path.iterdir())  # nothing half-written stays behind


@pytest.mark.parametrize("change, match", [
    (dict(rate_hz=0.0), r"device '/telemetry/torque': rate_hz must be positive; got 0\.0"),
    (dict(channels=("T_C12", "T,C34", "T_C46", "T_C57")),
     r"channel name 'T,C34' is empty or holds one of"),
    (dict(data=np.zeros((3, 10), np.float32)),
     r"data must have shape \(n_channels=4, n_samples\); got \(3, 10\)"),
])
def test_writer_refuses_inconsistent_devices(tmp_path, synth, change, match):
    from ident.errors import RecordingError

    with pytest.raises(RecordingError, match=match):
        write_recording(tmp_path / "r.mcap", [dataclasses.replace(synth.devices[0], **change)])


def test_writer_refuses_clashes(tmp_path, synth):
    from ident.errors import RecordingError

    a, b = synth.devices
    with pytest.raises(RecordingError, match=r"device names must be unique; got \['/telemetry/"
                       r"torque', '/telemetry/torque'\]"):
        write_recording(tmp_path / "r.mcap", [a, dataclasses.replace(b, name=a.name)])
    with pytest.raises(RecordingError, match=r"channel names must be unique over all devices; "
                       r"\['T_C12'\] repeat"):
        write_recording(tmp_path / "r.mcap",
                        [a, dataclasses.replace(b, channels=("T_C12",) + b.channels[1:])])
    with pytest.raises(RecordingError, match=r"give clashing CSV file names"):
        write_recording(tmp_path / "r.csv", [a, dataclasses.replace(b, name="x/torque"),
                                             dataclasses.replace(b, name="y/torque",
                                                                 channels=("Z1", "Z2", "Z3",
                                                                           "Z4"))])
    with pytest.raises(RecordingError, match=r"metadata keys and values must be strings; "
                       r"\['n'\] are not"):
        write_recording(tmp_path / "r.mcap", [a], metadata={"n": 1})
    with pytest.raises(RecordingError, match=r"block_samples must be >= 1; got 0"):
        write_recording(tmp_path / "r.mcap", [a], block_samples=0)
    with pytest.raises(RecordingError, match=r"time_format must be 'seconds' or 'iso'; got 'ms'"):
        write_recording(tmp_path / "r.csv", [a], time_format="ms")
    assert not [p for p in tmp_path.iterdir() if p.suffix != ".csv" or p.stat().st_size]


@pytest.mark.parametrize("compression", ["NONE", "LZ4", "ZSTD"])
def test_chunk_records_match_the_official_parser(tmp_path, synth, compression):
    """Our record walker over a chunk = the mcap library's breakup_chunk, message for message
    (payloads, channels, log-time order with ties kept), in every compression."""
    from mcap.reader import make_reader
    from mcap.records import Channel, Chunk, Message, Schema
    from mcap.stream_reader import StreamReader, breakup_chunk
    from mcap.writer import CompressionType, Writer

    from ident.io.mcap_reader import _chunk_bytes, chunk_records
    from ident.io.sampleblock import encode_protobuf

    dev = dataclasses.replace(synth.devices[0], data=synth.devices[0].data[:, :3000])
    p = tmp_path / "c.mcap"
    blocks = list(_blocks(dev, 100))
    order = np.random.default_rng(1).permutation(len(blocks))
    with open(p, "wb") as fh:
        w = Writer(fh, compression=getattr(CompressionType, compression), chunk_size=20_000)
        w.start()
        sid = w.register_schema("ident.SampleBlock", "protobuf", protobuf_schema())
        cids = [w.register_channel(f"/t{k}", "protobuf", sid) for k in range(2)]
        for j, k in enumerate(order):
            t0, d = blocks[k]
            w.add_message(cids[j % 2], t0 - t0 % 10**8,  # equal log times: ties keep order
                          encode_protobuf(t0, dev.rate_hz, dev.channels, dev.units, d), t0)
        w.finish()
    n = 0
    with open(p, "rb") as fh:
        for rec in StreamReader(fh, emit_chunks=True).records:
            if not isinstance(rec, Chunk):
                continue
            ref = breakup_chunk(rec, validate_crc=True)
            msgs = sorted((m for m in ref if isinstance(m, Message)), key=lambda m: m.log_time)
            data = _chunk_bytes(rec, validate_crc=True)
            defs, ours = chunk_records(data)
            assert [(m.log_time, m.channel_id, m.data) for m in msgs] == \
                [(t, c, data[a:b]) for t, c, a, b in ours]
            assert [type(d) for d in defs] == [type(r) for r in ref
                                               if isinstance(r, (Schema, Channel))]
            n += len(ours)
    assert n == len(blocks) and len(make_reader(open(p, "rb")).get_summary().chunk_indexes) >= 3


def test_chunk_record_running_past_its_chunk_is_an_error():
    import struct

    from ident.io.mcap_reader import ChunkRecordError, chunk_records

    msg = struct.pack("<HIQQ", 1, 0, 5, 5) + b"payload"
    good = struct.pack("<BQ", 0x05, len(msg)) + msg
    assert chunk_records(good)[1] == [(5, 1, 31, len(good))]
    with pytest.raises(ChunkRecordError, match="runs 3 bytes past"):
        chunk_records(struct.pack("<BQ", 0x05, len(msg) + 3) + msg)
    with pytest.raises(ChunkRecordError, match="header at byte 38"):
        chunk_records(good + b"\x05\x00")


def test_large_buffers_are_writable_maps_and_small_ones_plain():
    import mmap

    from ident.io.grid import MMAP_MIN_BYTES, empty_buffer

    big = empty_buffer((3, MMAP_MIN_BYTES // 4), np.float32)
    assert big.shape == (3, MMAP_MIN_BYTES // 4) and big.dtype == np.float32
    assert big.flags.writeable and big.flags.c_contiguous
    base = big
    while isinstance(base, np.ndarray):  # reshape view -> frombuffer array -> memoryview
        base = base.base
    assert isinstance(base, memoryview) and isinstance(base.obj, mmap.mmap)
    big[2, -1] = 7.0
    assert big[2, -1] == 7.0
    small = empty_buffer((4, 8), np.float64)
    assert small.flags.owndata and small.shape == (4, 8) and small.dtype == np.float64
