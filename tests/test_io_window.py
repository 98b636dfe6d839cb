"""Reading a time window of a recording, and walking a long one window by window.

Truth is the full read (itself checked against the written samples by
tests/test_io_roundtrip.py): the windows, put end to end, must be exactly it, in
every format; memory must follow the window, not the file.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np
import pandas as pd
import pytest

from ident.errors import DataQualityWarning, RecordingError
from ident.io import iter_recording, read_recording, recording_span, write_recording
from ident.segment import segment_transients
from synth_telemetry import T0_NS, make_synth


@pytest.fixture(scope="module")
def synth(mill):
    return make_synth(mill, seed=11, duration_s=24.0, idle_s=2.0)


def _write(tmp_path, synth, fmt: str):
    if fmt.startswith("mcap"):
        p = tmp_path / f"r-{fmt}.mcap"
        write_recording(p, synth.devices, encoding=fmt.split("-")[1])
    else:
        p = tmp_path / f"r-{fmt}.csv"
        write_recording(p, synth.devices, time_format=fmt.split("-")[1])
    return p


def _concat(parts, dev):
    return pd.concat([p.frames[dev] for p in parts if dev in p.frames])


@pytest.mark.parametrize("fmt", ["mcap-protobuf", "mcap-json", "csv-seconds", "csv-iso"])
def test_windows_end_to_end_are_the_full_read(tmp_path, mill, synth, fmt):
    p = _write(tmp_path, synth, fmt)
    with warnings.catch_warnings():
        warnings.simplefilter("error", DataQualityWarning)
        full = read_recording(p, mill)
        parts = list(iter_recording(p, mill, window_s=3.7))
    assert len(parts) == int(np.ceil(full.duration / 3.7))
    assert {q.t0_ns for q in parts} == {full.t0_ns}
    for dev, frame in full.frames.items():
        got = _concat(parts, dev)
        np.testing.assert_allclose(got.index.to_numpy(), frame.index.to_numpy(), atol=1e-9)
        np.testing.assert_array_equal(got.to_numpy(), frame.to_numpy())
        assert list(got.columns) == list(frame.columns)
    w = read_recording(p, mill, t_start=5.0, t_end=6.5)
    for dev, frame in w.frames.items():
        rate = full.rates_hz[dev]
        assert len(frame) == pytest.approx(1.5 * rate, abs=1)
        assert frame.index[0] == pytest.approx(5.0, abs=1.0 / rate)
        pd.testing.assert_frame_equal(frame, full.frames[dev].loc[frame.index[0]:frame.index[-1]])


def test_overlap_repeats_the_edge_and_segments_match(tmp_path, mill, synth):
    p = _write(tmp_path, synth, "mcap-protobuf")
    full = read_recording(p, mill, warn=False)
    whole = segment_transients(full, mill)
    found = []
    for part in iter_recording(p, mill, window_s=8.0, overlap_s=3.0, warn=False):
        start = float(next(iter(part.frames.values())).index[0])
        k = round((start + 3.0) / 8.0)
        assert start == pytest.approx(max(0.0, 8.0 * k - 3.0), abs=1e-3)
        for s in segment_transients(part, mill):
            if all(abs(s.t_step - f.t_step) > 0.05 for f in found):
                found.append(s)
    assert len(found) == len(whole) == len(synth.truth)
    for a, b in zip(sorted(found, key=lambda s: s.t_step), whole):
        assert a.kind == b.kind
        assert a.t_step == pytest.approx(b.t_step, abs=1e-3)


def test_memory_follows_the_window(tmp_path, mill, synth):
    """The window's arrays are the window's size (the placer is sized by it, not the file)."""
    p = _write(tmp_path, synth, "mcap-protobuf")
    w = read_recording(p, mill, t_start=10.0, t_end=11.0, warn=False)
    nbytes = sum(f.memory_usage(index=True).sum() for f in w.frames.values())
    full = read_recording(p, mill, warn=False)
    full_bytes = sum(f.memory_usage(index=True).sum() for f in full.frames.values())
    assert nbytes < 1.2 * full_bytes / full.duration


def test_nan_run_inside_a_window_is_reported_with_its_time(tmp_path, mill, synth):
    dev = synth.devices[0]
    cut = int(6.0 * dev.rate_hz)
    data = dev.data.copy()
    data[:, cut:cut + 1000] = np.nan
    p = tmp_path / "nan.mcap"
    write_recording(p, [dataclasses.replace(dev, data=data)], block_samples=200)
    rec = read_recording(p, mill, t_start=5.0, t_end=8.0, warn=False)
    nan = [q for q in rec.issues if q.kind == "nan_run"]
    assert nan and all(5.0 <= q.t_start < 8.0 for q in nan)
    assert any(abs(q.t_start - 6.0) < 1e-3 for q in nan)


def test_truncated_mcap_window(tmp_path, mill, synth):
    p = _write(tmp_path, synth, "mcap-protobuf")
    raw = p.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(raw[: len(raw) // 2])
    whole = read_recording(cut, mill, warn=False)
    w = read_recording(cut, mill, t_start=1.0, t_end=2.0, warn=False)
    dev = "/telemetry/torque"
    pd.testing.assert_frame_equal(w.frames[dev], whole.frames[dev].loc[1.0:2.0 - 1e-9])
    assert recording_span(cut) <= recording_span(p)


def test_bad_and_empty_windows(tmp_path, mill, synth):
    p = _write(tmp_path, synth, "csv-seconds")
    with pytest.raises(RecordingError, match=r"r-csv-seconds.csv.*expected 0 <= t_start < t_end"):
        read_recording(p, mill, t_start=3.0, t_end=2.0)
    with pytest.raises(RecordingError, match=r"empty window: no row between t=100\.0000 s"):
        read_recording(p, mill, t_start=100.0, t_end=101.0)
    q = _write(tmp_path, synth, "mcap-protobuf")
    with pytest.raises(RecordingError, match=r"empty window: no sample between t=100\.0000 s"):
        read_recording(q, mill, t_start=100.0, t_end=101.0)
    with pytest.raises(RecordingError, match="window_s > 0"):
        next(iter_recording(q, mill, window_s=1.0, overlap_s=2.0))


def test_long_dropout_window_is_skipped_with_a_warning(tmp_path, mill, synth):
    dev = synth.devices[0]
    r = int(dev.rate_hz)
    a = dataclasses.replace(dev, data=dev.data[:, : 4 * r])
    p = tmp_path / "gap.mcap"
    # blocks from 0-4 s and 10-14 s: the window 5-7.5 s holds nothing
    from mcap.writer import Writer

    from ident.io.sampleblock import encode_protobuf, protobuf_schema

    with open(p, "wb") as fh:
        wr = Writer(fh)
        wr.start()
        sid = wr.register_schema("ident.SampleBlock", "protobuf", protobuf_schema())
        cid = wr.register_channel("/t", "protobuf", sid)
        for off_s, part in ((0, a.data), (10, dev.data[:, 10 * r: 14 * r])):
            for k in range(0, part.shape[1], 200):
                t0 = T0_NS + int(off_s * 1e9) + int(k * 1e9 / dev.rate_hz)
                wr.add_message(cid, t0, encode_protobuf(t0, dev.rate_hz, dev.channels,
                                                         dev.units, part[:, k:k + 200]), t0)
        wr.finish()
    with pytest.warns(DataQualityWarning, match="empty window.*dropout longer than the window"):
        parts = list(iter_recording(p, mill, window_s=2.5, warn=False))
    starts = [round(float(q.frames["/t"].index[0]), 3) for q in parts]
    assert starts == [0.0, 2.5, 10.0, 12.5]


@pytest.mark.parametrize("fmt", ["mcap-protobuf", "csv-seconds"])
def test_segment_file_in_windows_finds_what_the_whole_read_finds(tmp_path, mill, synth, fmt):
    from ident.segment import segment_file

    p = _write(tmp_path, synth, fmt)
    whole = segment_transients(read_recording(p, mill, warn=False), mill)
    for window_s, overlap_s in ((6.0, 3.0), (9.0, 2.0), (100.0, 30.0)):
        got = segment_file(p, mill, window_s=window_s, overlap_s=overlap_s)
        assert got.windows == (1 if window_s == 100.0 else math.ceil(synth.duration_s / window_s))
        assert [s.kind for s in got.segments] == [s.kind for s in whole]
        np.testing.assert_allclose([s.t_step for s in got.segments], [s.t_step for s in whole],
                                   atol=1e-3)
        np.testing.assert_allclose([s.static_torque for s in got.segments],
                                   [s.static_torque for s in whole], rtol=0.02)
    with pytest.raises(RecordingError, match="overlap_s <= window_s / 2"):
        segment_file(p, mill, window_s=4.0, overlap_s=3.0)
