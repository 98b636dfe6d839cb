"""Property-based fuzzing of the readers: any file is either read or refused with a typed error.

Valid recordings are written first (:mod:`ident.io.writers`: CSV with float-seconds or
ISO-8601 times and a sibling device file, MCAP with protobuf or JSON sample blocks in
every chunk compression), then damaged by Hypothesis: truncated, bits flipped, rows or
blocks reordered, duplicated, dropped or shifted in time, units mixed between columns
and between the blocks of one device, text put into cells, separators changed.  Every
outcome of :func:`ident.io.read_recording` (whole, or a time window),
:func:`ident.io.recording_span` and :func:`ident.io.iter_recording` must be a result or
an :class:`~ident.errors.IdentError` -- which the command line answers with exit 2 and
one line -- never another exception.  The last tests run ``ident segment`` in-process on
malformed files: exit 2 and one line naming the file.

Bounded: few examples per property (the same ones every run) and a deadline per example,
so that the module runs in well under a minute; ``IDENT_FUZZ_EXAMPLES=N`` runs N fresh
random examples per property instead.
"""

from __future__ import annotations

import itertools
import math
import os
import random
import shutil
import warnings
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ident.cli import main
from ident.errors import DataQualityWarning, IdentError
from ident.io import RawDevice, iter_recording, quality, read_recording, recording_span, \
    write_recording
from ident.io.recording import Recording
from ident.io.sampleblock import encode_json, encode_protobuf, json_schema, protobuf_schema

T0_NS = 1_732_252_800_000_000_000
RATE = 2000.0
N = 600
BLOCK = 50
UNITS = ("kN*m", "N*m", "MN*m", "raw", "g", "", "furlongs", "kN*m ]")

#: ``IDENT_FUZZ_EXAMPLES=2000`` hunts longer, with fresh random examples each run.
EXAMPLES = int(os.environ.get("IDENT_FUZZ_EXAMPLES", "0")) or None
FUZZ = settings(max_examples=EXAMPLES or 100, deadline=2000, derandomize=EXAMPLES is None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

_counter = itertools.count()


def _devices() -> tuple[RawDevice, RawDevice]:
    rng = np.random.default_rng(0)
    t = np.arange(N) / RATE
    torque = np.vstack([50 * (t > 0.1) + 10 * np.sin(2 * np.pi * f * t) + rng.normal(0, 1, N)
                        for f in (12.0, 15.0, 20.0, 34.0)]).astype(np.float32)
    n2 = 2 * N
    accel = rng.normal(0, 0.1, (2, n2)).astype(np.float32)
    return (RawDevice("/telemetry/torque", RATE, T0_NS, ("T_C12", "T_C34", "T_C46", "T_C57"),
                      ("kN*m",) * 4, torque),
            RawDevice("/telemetry/accel", 2 * RATE, T0_NS, ("A_B23_v", "A_B23_h"), ("g", "g"),
                      accel))


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


@pytest.fixture(scope="module")
def devices():
    return _devices()


@pytest.fixture(scope="module")
def csv_base(work, devices) -> dict[str, tuple[bytes, bytes]]:
    """Key file and sibling bytes of a valid two-device CSV recording, per time format."""
    out = {}
    for fmt in ("seconds", "iso"):
        p = work / f"base-{fmt}.csv"
        write_recording(p, list(devices), time_format=fmt)
        out[fmt] = (p.read_bytes(), (work / f"base-{fmt}.accel.csv").read_bytes())
    return out


def _fresh(work: Path, suffix: str) -> Path:
    d = work / f"case{next(_counter)}"
    d.mkdir()
    return d / f"rec{suffix}"


def check(path: Path, mill) -> None:
    """Every reader entry point either succeeds or raises an IdentError.

    A dropout may last 2 s here (an hour by default): a time stamp damaged into the
    future would otherwise be walked towards in up to 36000 empty 0.1 s windows.
    """
    with mock.patch.object(quality, "MAX_DROPOUT_S", 2.0):
        _check(path, mill)
    shutil.rmtree(path.parent, ignore_errors=True)


def _check(path: Path, mill) -> None:
    for kwargs in ({"mill": mill}, {"mill": None}, {"mill": mill, "t_start": 0.05,
                                                    "t_end": 0.2}):
        try:
            rec = read_recording(path, kwargs.pop("mill"), warn=False, **kwargs)
        except IdentError:
            continue
        assert isinstance(rec, Recording)
        for frame in rec.frames.values():
            idx = frame.index.to_numpy()
            assert idx.size == 0 or np.all(np.diff(idx) > 0)  # time increases
    try:
        span = recording_span(path)
        assert math.isfinite(span)
    except IdentError:
        pass
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DataQualityWarning)  # windows skipped: dropouts
            for _ in itertools.islice(iter_recording(path, mill, window_s=0.1, warn=False), 8):
                pass
    except IdentError:
        pass


def damage(data: bytes, cut: float | None, flips: list[tuple[float, int]]) -> bytes:
    """Truncate at a fraction of the length, then flip bits at fractions of the length."""
    buf = bytearray(data if cut is None else data[:int(len(data) * cut)])
    for where, bit in flips:
        if buf:
            buf[min(len(buf) - 1, int(len(buf) * where))] ^= 1 << bit
    return bytes(buf)


cuts = st.one_of(st.none(), st.floats(0.0, 1.0))
flips = st.one_of(st.just([]), st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(0, 7)),
                                          min_size=1, max_size=4))


# ---- CSV --------------------------------------------------------------------------------------

@st.composite
def csv_edits(draw):
    """Line-level edits of a CSV file: rows swapped, repeated, dropped, reversed; header
    units changed; cells replaced by text; the separator and decimal mark changed."""
    edits = []
    for _ in range(draw(st.integers(0, 4))):
        kind = draw(st.sampled_from(["swap", "repeat", "drop", "reverse", "unit", "cell",
                                     "semicolon", "blank", "comment"]))
        a, b = draw(st.integers(1, N)), draw(st.integers(1, N))
        if kind == "unit":
            edits.append((kind, draw(st.integers(0, 4)), draw(st.sampled_from(UNITS))))
        elif kind == "cell":
            edits.append((kind, a, (draw(st.integers(0, 4)), draw(st.text(max_size=6)))))
        else:
            edits.append((kind, a, b))
    return edits


def apply_csv(text: str, edits) -> str:
    lines = text.splitlines()
    for kind, a, b in edits:
        if kind == "unit":
            cells = lines[0].split(",")
            if a < len(cells):
                name = cells[a].split(" [")[0]
                cells[a] = f"{name} [{b}]" if b else name
            lines[0] = ",".join(cells)
            continue
        a = min(a, len(lines) - 1)
        if len(lines) < 2:
            continue
        if kind == "swap":
            b = min(b, len(lines) - 1)
            lines[a], lines[b] = lines[b], lines[a]
        elif kind == "repeat":
            lines.insert(a, lines[a])
        elif kind == "drop":
            del lines[a:a + 1 + b % 40]
        elif kind == "reverse":
            lo, hi = sorted((a, min(b, len(lines) - 1)))
            lines[lo:hi + 1] = lines[lo:hi + 1][::-1]
        elif kind == "cell":
            col, value = b
            cells = lines[a].split(",")
            cells[col % len(cells)] = value
            lines[a] = ",".join(cells)
        elif kind == "semicolon":
            lines = [ln.replace(",", ";") if i == 0 else ln.replace(",", ";").replace(".", ",")
                     for i, ln in enumerate(lines)]
        elif kind == "blank":
            lines.insert(a, "")
        elif kind == "comment":
            lines.insert(0, "# exported by the telemetry box")
    return "\n".join(lines) + "\n"


@FUZZ
@given(fmt=st.sampled_from(["seconds", "iso"]), edits=csv_edits(),
       sibling_edits=csv_edits(), cut=cuts, flip=flips)
def test_csv_reader_answers_any_damage_with_a_result_or_a_typed_error(
        work, mill, csv_base, fmt, edits, sibling_edits, cut, flip):
    key, sibling = csv_base[fmt]
    p = _fresh(work, ".csv")
    p.write_bytes(damage(apply_csv(key.decode(), edits).encode(), cut, flip))
    (p.parent / "rec.accel.csv").write_bytes(apply_csv(sibling.decode(), sibling_edits).encode())
    check(p, mill)


@FUZZ
@given(data=st.binary(max_size=400), header=st.sampled_from(
    [b"", b"time,T_C12 [kN*m]\n", b"time;T_C12\n0,5;1\n", b"\xef\xbb\xbftime,T_C46\n"]))
def test_csv_reader_answers_garbage(work, mill, data, header):
    p = _fresh(work, ".csv")
    p.write_bytes(header + data)
    check(p, mill)


# ---- MCAP -------------------------------------------------------------------------------------

@st.composite
def mcap_plans(draw):
    """How to write the blocks: order, drops, repeats, time shifts (samples), units per
    block, log_time offsets, the encoding, the chunk size and compression."""
    n_blocks = N // BLOCK
    order = draw(st.permutations(range(n_blocks)))
    return {
        "encoding": draw(st.sampled_from(["protobuf", "json"])),
        "order": order,
        "drop": draw(st.sets(st.integers(0, n_blocks - 1), max_size=3)),
        "repeat": draw(st.lists(st.integers(0, n_blocks - 1), max_size=2)),
        "shift": draw(st.dictionaries(st.integers(0, n_blocks - 1),
                                      st.integers(-2 * BLOCK, 2 * BLOCK), max_size=2)),
        "units": draw(st.dictionaries(st.integers(0, n_blocks - 1), st.sampled_from(UNITS),
                                      max_size=2)),
        "log_shift_ns": draw(st.dictionaries(st.integers(0, n_blocks - 1),
                                             st.integers(-10**9, 10**9), max_size=2)),
        "compression": draw(st.sampled_from(["lz4", "zstd", ""])),
        "chunk_size": draw(st.sampled_from([600, 4096, 1 << 20])),
        "attach": draw(st.sampled_from([None, "mill", "garbage"])),
        "with_accel": draw(st.booleans()),
        # without CRCs (and chunks) flipped bits reach the decoders and the placing
        "crcs": draw(st.booleans()),
        "chunked": draw(st.booleans()),
    }


def write_mcap(path: Path, devices, plan, mill_text: str) -> None:
    from mcap.writer import CompressionType, Writer

    comp = {"lz4": CompressionType.LZ4, "zstd": CompressionType.ZSTD,
            "": CompressionType.NONE}[plan["compression"]]
    encode = encode_protobuf if plan["encoding"] == "protobuf" else encode_json
    with open(path, "wb") as fh:
        w = Writer(fh, chunk_size=plan["chunk_size"], compression=comp,
                   enable_crcs=plan["crcs"], use_chunking=plan["chunked"])
        w.start()
        if plan["encoding"] == "protobuf":
            sid = w.register_schema("ident.SampleBlock", "protobuf", protobuf_schema())
        else:
            sid = w.register_schema("ident.SampleBlock", "jsonschema", json_schema())
        if plan["attach"] is not None:
            text = mill_text if plan["attach"] == "mill" else "[mill]\nname = 1\n"
            w.add_attachment(create_time=0, log_time=0, name="mill.toml",
                             media_type="application/toml", data=text.encode())
        for dev in devices[:2 if plan["with_accel"] else 1]:
            cid = w.register_channel(dev.name, plan["encoding"], sid)
            per = BLOCK * int(dev.rate_hz / RATE)
            seq = [k for k in plan["order"] if k not in plan["drop"]] + list(plan["repeat"])
            for k in seq:
                start = k * per + plan["shift"].get(k, 0)
                t0 = dev.t0_ns + int(round(start * 1e9 / dev.rate_hz))
                units = dev.units if k not in plan["units"] else (plan["units"][k],) * \
                    len(dev.channels)
                data = dev.data[:, k * per:(k + 1) * per]
                log_time = max(0, t0 + plan["log_shift_ns"].get(k, 0))
                w.add_message(cid, log_time, encode(t0, dev.rate_hz, dev.channels, units, data),
                              log_time)
        w.finish()


@FUZZ
@given(plan=mcap_plans(), cut=cuts, flip=flips)
def test_mcap_reader_answers_any_damage_with_a_result_or_a_typed_error(
        work, mill, devices, plan, cut, flip):
    p = _fresh(work, ".mcap")
    write_mcap(p, devices, plan, Path(mill.source).read_text())
    p.write_bytes(damage(p.read_bytes(), cut, flip))
    check(p, mill)


@FUZZ
@given(data=st.binary(max_size=300), magic=st.sampled_from([b"", b"\x89MCAP0\r\n"]))
def test_mcap_reader_answers_garbage(work, mill, data, magic):
    p = _fresh(work, ".mcap")
    p.write_bytes(magic + data)
    check(p, mill)


@FUZZ
@given(payload=st.binary(max_size=200), encoding=st.sampled_from(["protobuf", "json"]),
       seed=st.integers(0, 2**16))
def test_sample_block_decoders_raise_only_their_error(payload, encoding, seed):
    """A message that is not a sample block: BlockDecodeError (the reader skips it)."""
    from ident.io.sampleblock import BlockDecodeError, Block, make_decoder

    dev = _devices()[0]
    rng = random.Random(seed)
    schema = protobuf_schema() if encoding == "protobuf" else json_schema()
    decode = make_decoder("protobuf" if encoding == "protobuf" else "jsonschema", encoding,
                          schema)
    good = (encode_protobuf if encoding == "protobuf" else encode_json)(
        dev.t0_ns, dev.rate_hz, dev.channels, dev.units, dev.data[:, :8])
    decode(good)  # primes the protobuf decoder's cache of the repeated middle bytes
    spliced = bytearray(good)
    for _ in range(rng.randint(0, 3)):
        spliced[rng.randrange(len(spliced))] = rng.randrange(256)
    for msg in (payload, bytes(spliced), good[:rng.randrange(len(good))]):
        try:
            block = decode(msg)
        except BlockDecodeError:
            continue
        assert isinstance(block, Block) and block.data.shape[0] == len(block.channels)


# ---- the command line --------------------------------------------------------------------------

MALFORMED = {
    "cut.mcap": lambda good: good["mcap"][:200],
    "noise.mcap": lambda good: b"\x89MCAP0\r\n" + bytes(range(256)) * 4,
    "text.mcap": lambda good: b"time,T_C12\n0,1\n",
    "empty.csv": lambda good: b"",
    "binary.csv": lambda good: bytes(range(256)) * 8,
    "back.csv": lambda good: good["csv_back"],
    "cut.csv": lambda good: good["csv"][:120],
}


@pytest.fixture(scope="module")
def good_bytes(work, devices) -> dict[str, bytes]:
    p = work / "cli-good.mcap"
    write_recording(p, [devices[0]])
    c = work / "cli-good.csv"
    write_recording(c, [devices[0]])
    lines = c.read_text().splitlines()
    lines[300], lines[301] = lines[301], lines[300]
    return {"mcap": p.read_bytes(), "csv": c.read_bytes(),
            "csv_back": ("\n".join(lines) + "\n").encode()}


@pytest.mark.parametrize("name", list(MALFORMED))
def test_segment_on_a_malformed_file_exits_2_with_one_line(work, mill_path, good_bytes, capsys,
                                                           name):
    p = work / "cli" / name
    p.parent.mkdir(exist_ok=True)
    p.write_bytes(MALFORMED[name](good_bytes))
    capsys.readouterr()
    code = main(["segment", str(p), "--mill", str(mill_path), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert len(err) == 1 and err[0].startswith(f"ident segment: error: {p}"), err


@settings(max_examples=EXAMPLES or 15, deadline=5000, derandomize=EXAMPLES is None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(cut=st.floats(0.0, 0.95), flip=flips, suffix=st.sampled_from(["mcap", "csv"]))
def test_segment_on_a_damaged_file_never_fails_internally(work, mill_path, good_bytes, capsys,
                                                          cut, flip, suffix):
    """Exit 0 (read, maybe with findings) or 2 (one line naming the file), never 1."""
    p = _fresh(work, f".{suffix}")
    p.write_bytes(damage(good_bytes[suffix], cut, flip))
    capsys.readouterr()
    code = main(["segment", str(p), "--mill", str(mill_path), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code in (0, 2), err
    if code == 2:
        assert len(err) == 1 and err[0].startswith(f"ident segment: error: {p}"), err
    shutil.rmtree(p.parent, ignore_errors=True)
