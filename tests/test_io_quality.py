"""Bad input, each made from a generated file: fatal errors and recorded findings.

Every finding must name the file, the channel and the time; fatal ones raise
RecordingError (checked with ``match=``), the rest land in ``Recording.issues``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest

from ident.errors import MillFileError, RecordingError
from ident.io import RawDevice, read_recording, write_recording
from ident.io.writers import McapRecordingWriter
from synth_telemetry import T0_NS, make_synth


@pytest.fixture(scope="module")
def synth(mill):
    return make_synth(mill, seed=3, duration_s=12.0, idle_s=2.0)


@pytest.fixture(scope="module")
def torque(synth) -> RawDevice:
    return synth.devices[0]


def kinds(rec) -> list[str]:
    return [i.kind for i in rec.issues]


def only(rec, kind):
    found = [i for i in rec.issues if i.kind == kind]
    assert found, f"no {kind!r} among {kinds(rec)}"
    return found


def write_blocks(path, dev: RawDevice, blocks, *, rate_hz=None, chunk_size=1 << 20):
    """Write (t0_ns, data) blocks of ``dev`` with the streaming writer."""
    with McapRecordingWriter(path, chunk_size=chunk_size) as w:
        cid = w.add_device(dev.name, rate_hz=rate_hz or dev.rate_hz, channels=dev.channels,
                           units=dev.units)
        for t0, d in blocks:
            w.write_block(cid, t0, d)


def blocks_of(dev: RawDevice, n=200):
    return [(dev.t0_ns + round(s * 1e9 / dev.rate_hz), dev.data[:, s:s + n])
            for s in range(0, dev.n_samples, n)]


# ---- truncated and corrupt MCAP --------------------------------------------------------------
def test_truncated_mcap_reads_what_is_intact(tmp_path, mill, synth):
    p = tmp_path / "full.mcap"
    with McapRecordingWriter(p, chunk_size=64 * 1024) as w:  # blocks interleaved in time
        ids = [w.add_device(d.name, rate_hz=d.rate_hz, channels=d.channels, units=d.units)
               for d in synth.devices]
        for k in range(120):
            for cid, d in zip(ids, synth.devices):
                n = int(d.rate_hz / 10)
                w.write_block(cid, d.t0_ns + k * 100_000_000, d.data[:, k * n:(k + 1) * n])
    raw = p.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(raw[: int(len(raw) * 0.6)])
    rec = read_recording(cut, mill, warn=False)
    issue = only(rec, "truncated")[0]
    assert issue.path == str(cut)
    assert "breaks off at byte" in issue.message
    ends = [float(f.index[-1]) + 1 / rec.rates_hz[d] for d, f in rec.frames.items()]
    assert issue.t_start == pytest.approx(max(ends), abs=1e-6)
    assert 3.0 < issue.t_start < 10.0
    for d in synth.devices:
        f = rec.frames[d.name]
        n = len(f)
        np.testing.assert_allclose(f[d.channels[0]].to_numpy(),
                                   d.data[0, :n] * (1e3 if d.units[0] == "kN*m" else 9.80665),
                                   rtol=1e-6)


def test_mcap_with_nothing_readable_is_fatal(tmp_path, mill, synth):
    p = tmp_path / "full.mcap"
    write_recording(p, synth.devices)
    stub = tmp_path / "stub.mcap"
    stub.write_bytes(p.read_bytes()[:200])
    with pytest.raises(RecordingError, match=r"stub\.mcap: unreadable: nothing readable: the "
                       r"file breaks at byte \d+ of 200"):
        read_recording(stub, mill)
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"this is not an mcap file at all" * 10)
    with pytest.raises(RecordingError, match=r"junk\.mcap: unreadable: not an MCAP file"):
        read_recording(junk, mill)


def test_corrupt_middle_chunk_is_skipped(tmp_path, mill, torque):
    from mcap.reader import make_reader

    p = tmp_path / "corrupt.mcap"
    write_blocks(p, torque, blocks_of(torque), chunk_size=32 * 1024)
    with open(p, "rb") as fh:
        chunks = sorted(make_reader(fh).get_summary().chunk_indexes,
                        key=lambda c: c.message_start_time)
    victim = chunks[len(chunks) // 2]
    raw = bytearray(p.read_bytes())
    at = victim.chunk_start_offset + victim.chunk_length // 2
    raw[at:at + 64] = bytes(64)  # a run of zeros inside the compressed chunk
    p.write_bytes(bytes(raw))
    rec = read_recording(p, mill, warn=False)
    issue = only(rec, "corrupt")[0]
    t_a = (victim.message_start_time - T0_NS) / 1e9
    assert issue.t_start == pytest.approx(t_a)
    assert "its samples from t=" in issue.message
    assert "dropout" not in kinds(rec)  # the lost range is reported once
    f = rec.frames[torque.name]
    assert len(f) == torque.n_samples  # the rest is read, the hole is NaN
    x = f["T_C12"].to_numpy()
    lost = np.isnan(x)
    assert lost.any() and not lost[: int(t_a * torque.rate_hz)].any()
    np.testing.assert_allclose(x[~lost], torque.data[0][~lost] * 1e3, rtol=1e-6)


# ---- dropouts, NaN, overlap, timestamps ------------------------------------------------------
def test_mcap_dropout_is_nan_rows_on_a_uniform_index(tmp_path, mill, torque):
    blocks = blocks_of(torque)
    kept = blocks[:10] + blocks[13:]  # blocks 10, 11, 12 never arrived: 1.0 .. 1.3 s
    p = tmp_path / "drop.mcap"
    write_blocks(p, torque, kept)
    rec = read_recording(p, mill, warn=False)
    issue = only(rec, "dropout")[0]
    assert (issue.t_start, issue.t_end) == (pytest.approx(1.0), pytest.approx(1.3))
    assert issue.channel == "T_C12,T_C34,T_C46,T_C57"
    assert issue.device == torque.name
    f = rec.frames[torque.name]
    assert len(f) == torque.n_samples
    assert np.allclose(np.diff(f.index.to_numpy()), 1 / torque.rate_hz)
    assert np.isnan(f.to_numpy()[2000:2600]).all()
    assert not np.isnan(f.to_numpy()[:2000]).any()
    assert "nan_run" not in kinds(rec)


def test_csv_dropout_and_injected_nans(tmp_path, mill, torque):
    n = 6000
    df = pd.DataFrame({f"{c} [kN*m]": torque.data[i, :n] for i, c in enumerate(torque.channels)})
    df.insert(0, "time", np.arange(n) / torque.rate_hz)
    df.iloc[3000:3010, 2] = np.nan  # T_C34 NaN at 1.5 s
    df = df.drop(index=range(2000, 2200))  # rows 1.0 .. 1.1 s missing
    p = tmp_path / "gaps.csv"
    df.to_csv(p, index=False)
    rec = read_recording(p, mill, warn=False)
    drop = only(rec, "dropout")[0]
    assert (drop.t_start, drop.t_end) == (pytest.approx(1.0), pytest.approx(1.1))
    nan = only(rec, "nan_run")[0]
    assert nan.channel == "T_C34" and nan.t_start == pytest.approx(1.5)
    assert nan.path == str(p)
    f = rec.frames["gaps"]
    assert len(f) == n and np.isnan(f["T_C12"].to_numpy()[2000:2200]).all()


# Time that steps back or repeats is an error naming the file and the time (telemetry.md:
# "the order of samples is not guessed"); these were sorted / "later block wins" findings.
def test_csv_swapped_timestamps_are_fatal(tmp_path, mill, torque):
    n = 4000
    t = np.arange(n) / torque.rate_hz
    t[[1000, 1001]] = t[[1001, 1000]]
    df = pd.DataFrame({"time": t, "T_C12 [kN*m]": torque.data[0, :n]})
    p = tmp_path / "swapped.csv"
    df.to_csv(p, index=False)
    with pytest.raises(RecordingError, match=r"swapped\.csv, t=0\.500000 s: non monotonic: time "
                       r"steps back from t=0\.500500 s to t=0\.500000 s; expected strictly "
                       r"increasing times") as err:
        read_recording(p, mill, warn=False)
    assert err.value.path == str(p) and err.value.time == pytest.approx(0.5)


def test_csv_repeated_time_is_fatal(tmp_path, mill, torque):
    t = np.arange(2000) / torque.rate_hz
    t[700] = t[699]
    p = tmp_path / "repeat.csv"
    pd.DataFrame({"time": t, "T_C12 [kN*m]": torque.data[0, :2000]}).to_csv(p, index=False)
    with pytest.raises(RecordingError, match=r"repeat\.csv, t=0\.349500 s: non monotonic: time "
                       r"repeats: t=0\.349500 s twice"):
        read_recording(p, mill, warn=False)


def test_mcap_overlapping_blocks_are_fatal(tmp_path, mill, torque):
    blocks = blocks_of(torque)
    t0, d = blocks[5]
    blocks.insert(8, (t0 + 50 * 500_000, d))  # a block whose time goes backwards
    p = tmp_path / "overlap.mcap"
    write_blocks(p, torque, blocks)
    with pytest.raises(RecordingError, match=r"overlap\.mcap, channel 'T_C12,T_C34,T_C46,T_C57', "
                       r"t=0\.525000 s: non monotonic: device '/telemetry/torque': a sample block "
                       r"starts at t=0\.525000 s, not after the last sample \(t=0\.599500 s\)"):
        read_recording(p, mill, warn=False)


def test_mcap_repeated_block_is_fatal(tmp_path, mill, torque):
    blocks = blocks_of(torque)
    blocks.append(blocks[3])  # the same block again, at the end of the file
    p = tmp_path / "again.mcap"
    write_blocks(p, torque, blocks)
    with pytest.raises(RecordingError, match=r"again\.mcap, .*t=0\.300000 s: non monotonic: "
                       r"device '/telemetry/torque': a sample block repeats the start "
                       r"t=0\.300000 s of another block"):
        read_recording(p, mill, warn=False)


def test_mcap_blocks_out_of_file_order_are_read_in_time_order(tmp_path, mill, torque):
    blocks = blocks_of(torque)
    blocks[4], blocks[9] = blocks[9], blocks[4]  # arrival order is not time order
    p = tmp_path / "shuffled.mcap"
    write_blocks(p, torque, blocks)
    rec = read_recording(p, mill, warn=False)
    assert rec.issues == ()
    np.testing.assert_allclose(rec.channel("T_C12").to_numpy(), torque.data[0] * 1e3, rtol=1e-6)


def test_mcap_block_less_than_a_sample_late_is_a_finding(tmp_path, mill, torque):
    """A block starting 0.4 samples after the previous block's last sample (a clock
    hiccup): time still increases, so it is read; its first sample shares a grid point."""
    blocks = blocks_of(torque)
    t0, d = blocks[6]
    blocks[6] = (t0 - 300_000, d)  # 0.6 samples early at 2 kHz
    p = tmp_path / "early.mcap"
    write_blocks(p, torque, blocks)
    rec = read_recording(p, mill, warn=False)
    issue = only(rec, "non_monotonic")[0]
    assert "starts less than a sample after the last sample of the block before" in issue.message
    assert issue.t_start == pytest.approx(0.5995)


def test_log_time_disagreeing_with_t0(tmp_path, mill, torque):
    from mcap.writer import CompressionType, Writer

    from ident.io.sampleblock import encode_protobuf, protobuf_schema

    p = tmp_path / "lt.mcap"
    with open(p, "wb") as fh:
        w = Writer(fh, compression=CompressionType.NONE)
        w.start()
        sid = w.register_schema("ident.SampleBlock", "protobuf", protobuf_schema())
        cid = w.register_channel("/t", "protobuf", sid)
        for k, (t0, d) in enumerate(blocks_of(torque)[:20]):
            w.add_message(cid, t0 + (10**9 if k == 7 else 0),
                          encode_protobuf(t0, torque.rate_hz, torque.channels, torque.units, d), t0)
        w.finish()
    rec = read_recording(p, mill, warn=False)
    issue = only(rec, "timestamp_mismatch")[0]
    assert "log_time +1.000000 s off its t0_ns" in issue.message
    assert issue.t_start == pytest.approx(0.7)
    assert len(rec.frames["/t"]) == 4000


# ---- rates ---------------------------------------------------------------------------------
def test_mcap_rate_disagreeing_with_timestamps_is_fatal(tmp_path, mill, torque):
    blocks = [(T0_NS + k * 125_000_000, d) for k, (_, d) in enumerate(blocks_of(torque))]
    p = tmp_path / "rate.mcap"
    write_blocks(p, torque, blocks)  # 200 samples every 0.125 s, declared 2000 Hz
    with pytest.raises(RecordingError, match=r"rate\.mcap, channel 'T_C12,T_C34,T_C46,T_C57': "
                       r"rate mismatch: device '/telemetry/torque' declares rate_hz=2000 but its "
                       r"block timestamps imply 1600 Hz") as err:
        read_recording(p, mill)
    assert err.value.path == str(p)


def test_csv_with_two_rates_is_fatal(tmp_path, mill, torque):
    t = np.concatenate([np.arange(2000) * 0.0005, 1.0 + np.arange(1, 1001) * 0.001])
    df = pd.DataFrame({"time": t, "T_C12 [kN*m]": torque.data[0, : t.size]})
    p = tmp_path / "tworates.csv"
    df.to_csv(p, index=False)
    with pytest.raises(RecordingError, match=r"tworates\.csv, channel 'T_C12', t=1\.001000 s: "
                       r"rate mismatch: the time steps are not one rate: the median step is "
                       r"0\.0005 s \(2000 Hz\)") as err:
        read_recording(p, mill)
    assert err.value.time == pytest.approx(1.0, abs=0.002)


# ---- channels and units ----------------------------------------------------------------------
def test_removed_channel(tmp_path, mill, torque):
    dev = dataclasses.replace(torque, channels=torque.channels[:3], units=torque.units[:3],
                              data=torque.data[:3])
    p = tmp_path / "three.mcap"
    write_recording(p, [dev])
    rec = read_recording(p, mill, warn=False)
    issue = only(rec, "missing_channel")[0]
    assert issue.channel == "T_C57" and "lacks it" in issue.message
    # a torque-only recording: no finding for the absent accelerometer device
    assert [i.channel for i in rec.issues] == ["T_C57"]
    with pytest.raises(RecordingError, match=r"channel 'T_C57': missing channel: requested "
                       r"channel\(s\) \['T_C57'\] are not in the recording"):
        read_recording(p, mill, channels=["T_C12", "T_C57"])


def test_unknown_channel_is_ignored(tmp_path, mill, torque):
    dev = dataclasses.replace(torque, channels=torque.channels + ("T_SPARE",),
                              units=torque.units + ("kN*m",),
                              data=np.vstack([torque.data, torque.data[:1]]))
    p = tmp_path / "spare.mcap"
    write_recording(p, [dev])
    rec = read_recording(p, mill, warn=False)
    assert "T_SPARE" not in rec.channels
    issue = only(rec, "unknown_channel")[0]
    assert issue.channel == "T_SPARE" and "does not name; ignored" in issue.message


def test_no_mapped_channel_is_fatal(tmp_path, mill):
    dev = RawDevice("/x", 100.0, T0_NS, ("X1",), ("kN*m",), np.zeros((1, 50), np.float32))
    p = tmp_path / "x.mcap"
    write_recording(p, [dev])
    with pytest.raises(RecordingError, match=r"no channel of the mill file's sensor map is in "
                       r"the recording; it holds \['X1'\]"):
        read_recording(p, mill, warn=False)


def test_wrong_unit_header_is_fatal(tmp_path, mill, torque):
    n = 1000
    df = pd.DataFrame({"time": np.arange(n) / 2000.0, "T_C12 [N*m]": torque.data[0, :n] * 1e3})
    p = tmp_path / "unit.csv"
    df.to_csv(p, index=False)
    with pytest.raises(RecordingError, match=r"unit\.csv, channel 'T_C12': unit mismatch: recorded "
                       r"in 'N\*m' but the mill file \(.*hsm-f1\.toml\) maps it in 'kN\*m'") as err:
        read_recording(p, mill)
    assert err.value.channel == "T_C12"
    dev = dataclasses.replace(torque, units=("kN*m", "MN*m", "kN*m", "kN*m"))
    q = tmp_path / "unit.mcap"
    write_recording(q, [dev])
    with pytest.raises(RecordingError, match=r"channel 'T_C34': unit mismatch: recorded in "
                       r"'MN\*m'"):
        read_recording(q, mill)


def test_csv_without_time_column(tmp_path, mill):
    p = tmp_path / "notime.csv"
    p.write_text("T_C12,T_C34\n1,2\n3,4\n")
    with pytest.raises(RecordingError, match=r"unreadable: no time column among \['T_C12', "
                       r"'T_C34'\]; expected a first column 'time'"):
        read_recording(p, mill)


def test_unknown_format_and_missing_file(tmp_path, mill):
    with pytest.raises(RecordingError, match=r"unknown recording format '\.bin'"):
        read_recording(tmp_path / "r.bin", mill)
    with pytest.raises(RecordingError, match=r"missing\.csv: unreadable: file not found"):
        read_recording(tmp_path / "missing.csv", mill)


def test_bad_attached_mill_file(tmp_path, torque):
    p = tmp_path / "badmill.mcap"
    write_recording(p, [torque], mill_toml="[mill]\nname = 'x'\n")
    with pytest.raises(MillFileError, match=r"badmill\.mcap#mill\.toml"):
        read_recording(p)


# ---- clipping and dead sensors ---------------------------------------------------------------
def test_clipped_run(tmp_path, mill, synth, torque):
    x = torque.data[2].copy()
    i_peak = int(np.argmax(x))
    level = x[i_peak] - 0.15 * (x[i_peak] - np.median(x))
    x = np.minimum(x, level)  # the sensor saturates at `level`
    data = torque.data.copy()
    data[2] = x
    p = tmp_path / "clip.mcap"
    write_recording(p, [dataclasses.replace(torque, data=data)])
    rec = read_recording(p, mill, warn=False)
    clipped = only(rec, "clipped")
    assert {i.channel for i in clipped} == {"T_C46"}
    t_peak = i_peak / torque.rate_hz
    assert any(i.t_start <= t_peak <= i.t_end for i in clipped)
    assert "stuck at the channel's maximum" in clipped[0].message


def test_clean_synthetic_recording_has_no_findings(tmp_path, mill, synth):
    p = tmp_path / "clean.mcap"
    write_recording(p, synth.devices)
    assert read_recording(p, mill).issues == ()


def test_raw_full_scale_and_flat_channel(tmp_path, mill):
    ch = dataclasses.replace(mill.channel("T_C12"), scale=1e-3)
    raw_mill = dataclasses.replace(mill, channels=(ch,) + mill.channels[1:])
    rng = np.random.default_rng(0)
    counts = np.round(rng.normal(0, 3000, 4000)).astype(np.float32)
    counts[1000:1010] = 32767.0
    counts[1010] = 32000.0  # keeps 32767 from being the only extreme
    counts[2000:2003] = -32768.0
    flat = np.full(4000, 5.0, dtype=np.float32)
    dev = RawDevice("/t", 2000.0, T0_NS, ("T_C12", "T_C34"), ("raw", "kN*m"),
                    np.vstack([counts, flat]))
    p = tmp_path / "fs.mcap"
    write_recording(p, [dev])
    rec = read_recording(p, raw_mill, warn=False)
    clipped = only(rec, "clipped")
    assert any(i.t_start == pytest.approx(0.5) and "16-bit full scale" in i.message
               for i in clipped)
    assert only(rec, "flat")[0].channel == "T_C34"


def test_corrupt_message_is_skipped(tmp_path, mill, torque):
    from mcap.writer import CompressionType, Writer

    from ident.io.sampleblock import encode_json, json_schema

    p = tmp_path / "badmsg.mcap"
    with open(p, "wb") as fh:
        w = Writer(fh, compression=CompressionType.NONE)
        w.start()
        sid = w.register_schema("ident.SampleBlock", "jsonschema", json_schema())
        cid = w.register_channel("/t", "json", sid)
        for k, (t0, d) in enumerate(blocks_of(torque)[:10]):
            msg = b'{"t0_ns": oops' if k == 4 else encode_json(t0, torque.rate_hz,
                                                                torque.channels, torque.units, d)
            w.add_message(cid, t0, msg, t0)
        w.finish()
    rec = read_recording(p, mill, warn=False)
    bad = only(rec, "corrupt")[0]
    assert "is not a sample block" in bad.message and bad.t_start == pytest.approx(0.4)
    drop = only(rec, "dropout")[0]
    assert (drop.t_start, drop.t_end) == (pytest.approx(0.4), pytest.approx(0.5))


def test_device_changing_its_channels_is_fatal(tmp_path, mill, torque):
    from mcap.writer import Writer

    from ident.io.sampleblock import encode_protobuf, protobuf_schema

    p = tmp_path / "change.mcap"
    with open(p, "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema("ident.SampleBlock", "protobuf", protobuf_schema())
        cid = w.register_channel("/t", "protobuf", sid)
        w.add_message(cid, T0_NS, encode_protobuf(T0_NS, 2000.0, torque.channels, torque.units,
                                                  torque.data[:, :200]), T0_NS)
        t1 = T0_NS + 100_000_000
        w.add_message(cid, t1, encode_protobuf(t1, 2000.0, torque.channels[:2],
                                               torque.units[:2], torque.data[:2, 200:400]), t1)
        w.finish()
    with pytest.raises(RecordingError, match=r"device '/t' changes within the recording: a "
                       r"block at t0_ns=\d+ has channels \['T_C12', 'T_C34'\]"):
        read_recording(p, mill)


@pytest.mark.parametrize("text, match", [
    ("", r"bad\.csv: unreadable: the file is empty \(0 bytes\)"),
    ("# only a comment\n\n", r"the CSV file has no header line"),
    ("time T_C12\n0 1\n", r"has no ',', ';' or tab separator"),
    ("time,T_C12\n", r"the CSV file has a header but no data rows"),
    ("time,T_C12\n0.0,1.0\n", r"a single row; cannot tell the sample rate"),
    ("time,T_C12\n0.0,1.0\n0.001,abc\n", r"bad\.csv, channel 'T_C12', t=0\.001000 s: "
                                          r"unreadable: line 3: the value 'abc' is not a number"),
    ("time,T_C12\n0.0,1.0\n0.001,2.0,3.0\n", r"bad\.csv, t=0\.001000 s: unreadable: line 3 has 3 "
                                              r"fields but the header has 2"),
    ("time,T_C12,T_C12\n0.0,1,1\n0.001,2,2\n", r"channel\(s\) \['T_C12'\] appear in more than "
                                                r"one column"),
    ("time,T_C12\nyesterday,1\ntoday,2\n", r"neither float seconds nor an ISO-8601 timestamp"),
])
def test_malformed_csv(tmp_path, mill, text, match):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(RecordingError, match=match):
        read_recording(p, mill, warn=False)


def test_requested_unmapped_channel(tmp_path, mill, torque):
    dev = dataclasses.replace(torque, channels=torque.channels[:3] + ("T_X",))
    p = tmp_path / "x.mcap"
    write_recording(p, [dev])
    with pytest.raises(RecordingError, match=r"channel 'T_X': unknown channel: requested "
                       r"channel\(s\) \['T_X'\] are not in the mill file's sensor map"):
        read_recording(p, mill, channels=["T_X"])
