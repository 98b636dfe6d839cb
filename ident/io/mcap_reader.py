"""Read MCAP recordings of ``ident.SampleBlock`` messages into device grids.

Reading goes through the official ``mcap`` library.  When the file has its summary
(chunk index), each chunk is read and checked (CRC) on its own, so a corrupt chunk
costs only its own time range; without a summary (a file cut short) the records are
streamed in file order until the break.  Blocks are placed on each device's uniform
grid at ``round((t0_ns - t_ref) * rate_hz / 1e9)``, so out-of-order blocks land in
place and missing blocks stay NaN (dropouts, never interpolated).  Memory: the
device arrays are allocated once, sized from the summary's message counts, and
each block is copied straight in from the message bytes (float32).

A time window (``window_ns``, relative to the recording's start) reads only the
indexed chunks that can hold samples inside it and keeps only those samples, so
that memory follows the window, not the file: see
:func:`ident.io.readers.iter_recording`.  The recording's start is the earliest
message ``log_time`` of the summary (the first message's, for a file without
one).
"""


from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .grid import DeviceGrid, empty_buffer
from . import quality
from .quality import RATE_TOLERANCE, IssueLog
from .sampleblock import SCHEMA_NAME, Block, BlockDecodeError, make_decoder

__all__ = ["read_mcap", "McapContent", "mcap_span_ns", "MAX_BLOCK_NS"]

#: Longest sample block assumed when choosing the chunks a time window needs, ns.
MAX_BLOCK_NS = 60 * 10**9

try:  # decompressors raise their own error types on corrupt chunks
    from lz4.frame import LZ4FrameError as _LZ4Error  # type: ignore[attr-defined]
except ImportError:  # pragma: no cover - lz4 is a dependency of mcap here
    _LZ4Error = ValueError
try:
    from zstandard import ZstdError as _ZstdError  # type: ignore
except ImportError:
    _ZstdError = ValueError


_REC = struct.Struct("<BQ")
_MSG = struct.Struct("<HIQ")  # channel_id, sequence, log_time (publish_time follows)
_OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE = 0x03, 0x04, 0x05


class ChunkRecordError(ValueError):
    """A chunk's records do not add up (a record runs past the chunk's end)."""


def _chunk_bytes(chunk, validate_crc: bool) -> bytes:
    """The chunk's uncompressed records, CRC-checked as the ``mcap`` library does."""
    from mcap.stream_reader import CRCValidationError

    if chunk.compression == "zstd":
        import zstandard

        data = zstandard.decompress(chunk.data, chunk.uncompressed_size)
    elif chunk.compression == "lz4":
        import lz4.frame

        data = lz4.frame.decompress(chunk.data)
    elif chunk.compression == "":
        data = chunk.data
    else:
        from mcap.exceptions import UnsupportedCompressionError

        raise UnsupportedCompressionError(chunk.compression)
    if validate_crc and chunk.uncompressed_crc != 0:
        crc = zlib.crc32(data)
        if crc != chunk.uncompressed_crc:
            raise CRCValidationError(expected=chunk.uncompressed_crc, actual=crc, record=chunk)
    return data


def chunk_records(data: bytes) -> tuple[list, list[tuple[int, int, int, int]]]:
    """Split a chunk's uncompressed records without building a Python object per message.

    Returns
    -------
    defs : list
        The Schema and Channel records (parsed by the ``mcap`` library), in order.
    messages : list of (log_time, channel_id, start, end)
        Each message's payload is ``data[start:end]``; sorted by log time (stable, as
        the ``mcap`` library's reader yields them).

    Raises
    ------
    ChunkRecordError
        A record's length runs past the end of the chunk.
    """
    from io import BytesIO

    from mcap.data_stream import ReadDataStream
    from mcap.records import Channel, Schema

    unpack_rec, unpack_msg = _REC.unpack_from, _MSG.unpack_from
    n = len(data)
    pos = 0
    defs: list = []
    msgs: list[tuple[int, int, int, int]] = []
    append = msgs.append
    while pos < n:
        if pos + 9 > n:
            raise ChunkRecordError(f"a record header at byte {pos} of the chunk's {n} is cut")
        op, length = unpack_rec(data, pos)
        body = pos + 9
        pos = body + length
        if pos > n:
            raise ChunkRecordError(f"a record at byte {body - 9} runs {pos - n} bytes past "
                                   f"the chunk's end")
        if op == _OP_MESSAGE:
            if length < 22:
                raise ChunkRecordError(f"a message record at byte {body - 9} is too short")
            ch, _seq, log_time = unpack_msg(data, body)
            append((log_time, ch, body + 22, pos))
        elif op == _OP_SCHEMA or op == _OP_CHANNEL:
            stream = ReadDataStream(BytesIO(data[body:pos]))
            defs.append(Schema.read(stream) if op == _OP_SCHEMA else Channel.read(stream))
    if any(msgs[i][0] > msgs[i + 1][0] for i in range(len(msgs) - 1)):
        msgs.sort(key=lambda m: m[0])
    return defs, msgs


def _why(exc: BaseException) -> str:
    text = str(exc).strip()
    name = type(exc).__name__
    if name == "EndOfFile":
        return "unexpected end of file"
    return f"{name}: {text}" if text else name


def _failures() -> tuple[type[BaseException], ...]:
    from mcap.exceptions import McapError

    return (McapError, EOFError, struct.error, ValueError, KeyError, IndexError, OSError,
            RuntimeError, MemoryError, UnicodeDecodeError, _LZ4Error, _ZstdError,
            ChunkRecordError)


@dataclass
class McapContent:
    """What :func:`read_mcap` found."""

    grids: list[DeviceGrid]
    metadata: dict[str, str] = field(default_factory=dict)
    mill_toml: str | None = None
    #: the recording's start, ns since the epoch (set when a time window was read)
    origin_ns: int | None = None


class _Placer:
    """Puts one device's blocks onto its uniform grid as they arrive."""

    def __init__(self, topic: str, block: Block, keep: Callable[[str], bool],
                 capacity: int) -> None:
        self.topic = topic
        self.rate = block.rate_hz
        self.channels = block.channels
        self.units = block.units
        rows = [i for i, c in enumerate(block.channels) if keep(c)]
        self.rows = np.asarray(rows, dtype=np.intp)
        self.all_rows = len(rows) == len(block.channels)
        self.ref = block.t0_ns
        self.lo = 0
        # not prefilled: only the samples no block covers (the gaps) are set to NaN, at
        # the end, so the untouched pages of a large buffer cost nothing until written
        self.buf = empty_buffer((len(rows), max(capacity, block.data.shape[1])), np.float32)
        self.span = (0, block.data.shape[1])  # first and end sample of the blocks placed
        self.pos: list[int] = []
        self.n: list[int] = []
        self.t0: list[int] = []

    def put(self, block: Block, log: IssueLog) -> None:
        n = block.data.shape[1]
        pos = int(round((block.t0_ns - self.ref) * self.rate / 1e9))
        lo, hi = self.span
        gap = max(lo - (pos + n), pos - hi) / self.rate
        if gap > quality.MAX_DROPOUT_S:  # before the buffer grows to hold the gap
            raise log.fatal(
                "time_jump", f"device {self.topic!r}: the block at t0_ns={block.t0_ns} lies "
                f"{gap:.6g} s {'before' if pos < lo else 'after'} the device's other blocks, "
                f"longer than a dropout may last ({quality.MAX_DROPOUT_S:g} s); a wrong time "
                "stamp?", channel=",".join(block.channels),
                time=(block.t0_ns - self.ref) / 1e9)
        self.span = (min(lo, pos), max(hi, pos + n))
        i = pos - self.lo
        k, cap = self.buf.shape
        if i < 0 or i + n > cap:
            new_lo = min(self.lo, pos)
            new_cap = max(pos + n, self.lo + cap) - new_lo
            if i + n > cap:
                new_cap = max(new_cap, int(cap * 1.5))
            new = empty_buffer((k, new_cap), np.float32)
            new[:, self.lo - new_lo:self.lo - new_lo + cap] = self.buf
            self.buf, self.lo = new, new_lo
            i = pos - self.lo
        if k:
            self.buf[:, i:i + n] = block.data if self.all_rows else block.data[self.rows]
        self.pos.append(pos)
        self.n.append(n)
        self.t0.append(block.t0_ns)

    def finish(self, log: IssueLog, corrupt_ns: list[tuple[int, int]],
               origin_ns: int) -> DeviceGrid:
        """The device's grid; ``origin_ns`` (the recording's start) dates the findings."""
        pos = np.asarray(self.pos, dtype=np.int64)
        n = np.asarray(self.n, dtype=np.int64)
        t0 = np.asarray(self.t0, dtype=np.int64)
        order = np.lexsort((pos, t0))  # blocks may arrive in any order: time order
        pos, n, t0 = pos[order], n[order], t0[order]
        rate = self.rate
        kept = tuple(self.channels[i] for i in self.rows.tolist())
        names = ",".join(kept)
        self._check_order(log, t0, n, origin_ns, names)
        order = np.argsort(pos, kind="stable")
        pos, n, t0 = pos[order], n[order], t0[order]
        ends = np.maximum.accumulate(pos + n)
        first, last = int(pos[0]), int(ends[-1])
        if len(pos) > 1:
            dt_samples = np.diff(t0) * rate / 1e9
            ok = n[:-1] > 0
            if ok.any():
                ratio = float(np.median(dt_samples[ok] / n[:-1][ok]))
                if abs(ratio - 1.0) > RATE_TOLERANCE:
                    implied = rate / ratio
                    raise log.fatal(
                        "rate_mismatch",
                        f"device {self.topic!r} declares rate_hz={rate:g} but its block "
                        f"timestamps imply {implied:.6g} Hz (blocks of {int(np.median(n))} "
                        f"samples every {np.median(np.diff(t0)) / 1e9:.6g} s); expected them "
                        "to agree within 0.5 %", channel=names)
        gaps: list[tuple[int, int]] = []
        prev_end = ends[:-1]
        nxt = pos[1:]
        for j in np.flatnonzero(nxt > prev_end).tolist():
            gaps.append((int(prev_end[j]) - first, int(nxt[j]) - first))
        for j in np.flatnonzero(nxt < prev_end).tolist():  # less than a sample after
            t = (self.ref - origin_ns) / 1e9 + int(nxt[j]) / rate
            shared = int(prev_end[j] - nxt[j])
            log.add("non_monotonic",
                    f"device {self.topic!r}: the block starting at t={t:.4f} s starts less than "
                    f"a sample after the last sample of the block before, so {shared} of its "
                    "samples share grid points with it; the block read last wins",
                    channel=names, t_start=t, device=self.topic)
        a, b = first - self.lo, last - self.lo
        for g0, g1 in gaps:  # dropouts: NaN, never interpolated
            self.buf[:, a + g0:a + g1] = np.nan
        data = self.buf[:, a:b]
        if self.buf.shape[1] > 1.1 * (b - a):
            data = np.ascontiguousarray(data)
        self.buf = np.empty((0, 0), dtype=np.float32)
        start_ns = self.ref + int(round(first * 1e9 / rate))
        return DeviceGrid(name=self.topic, rate_hz=rate, start_ns=start_ns, channels=kept,
                          units=tuple(self.units[i] for i in self.rows.tolist()), data=data,
                          gaps=gaps, all_channels=self.channels,
                          corrupt_ns=list(corrupt_ns))


    def _check_order(self, log: IssueLog, t0: np.ndarray, n: np.ndarray, origin_ns: int,
                     names: str) -> None:
        """Refuse time that steps back or repeats: a block (in time order) whose first
        sample is not after the last sample of the blocks before it (telemetry.md)."""
        has = n > 0
        t0, n = t0[has], n[has]
        if t0.size < 2:
            return
        last = t0 + np.round((n - 1) * (1e9 / self.rate)).astype(np.int64)
        reach = np.maximum.accumulate(last)[:-1]  # the latest sample before each block
        bad = np.flatnonzero(t0[1:] <= reach)
        if not bad.size:
            return
        j = int(bad[0])
        t_new = (int(t0[j + 1]) - origin_ns) / 1e9
        t_old = (int(reach[j]) - origin_ns) / 1e9
        what = (f"repeats the start t={t_new:.6f} s of another block" if t0[j + 1] == t0[j]
                else f"starts at t={t_new:.6f} s, not after the last sample (t={t_old:.6f} s) "
                     "of the block before it")
        more = f" ({bad.size} blocks in all)" if bad.size > 1 else ""
        raise log.fatal("non_monotonic", f"device {self.topic!r}: a sample block {what}: time "
                        f"steps back or repeats{more}; expected the blocks of a device not to "
                        "overlap (they may arrive in any order, but the order of samples is "
                        "not guessed)", channel=names, time=t_new)


class _Assembler:
    """Decodes messages per MCAP channel and feeds the placers."""

    def __init__(self, log: IssueLog, keep: Callable[[str], bool],
                 counts: dict[int, int], window_abs_ns: tuple[int, int] | None = None) -> None:
        self.log = log
        self.keep = keep
        self.counts = counts
        self.window = window_abs_ns
        self.decoders: dict[int, Callable[[bytes], Block] | None] = {}
        self.topics: dict[int, str] = {}
        self.placers: dict[str, _Placer] = {}
        self.skip_topics: set[str] = set()
        self.corrupt_ns: list[tuple[int, int]] = []
        self.bad_messages: list[tuple[str, int, BlockDecodeError]] = []
        self.bad_times: list[tuple[str, int, int]] = []

    def channel(self, channel, schema) -> None:
        if channel.id in self.decoders:
            return
        self.topics[channel.id] = channel.topic
        if schema is None or schema.name != SCHEMA_NAME:
            name = schema.name if schema is not None else None
            self.log.add("unknown_channel", f"topic {channel.topic!r} has schema {name!r}, not "
                         f"{SCHEMA_NAME!r}; ignored", channel=None, device=channel.topic)
            self.decoders[channel.id] = None
            return
        try:
            self.decoders[channel.id] = make_decoder(schema.encoding, channel.message_encoding,
                                                     schema.data)
        except BlockDecodeError as exc:
            self.log.add("corrupt", f"topic {channel.topic!r}: {exc}; ignored",
                         device=channel.topic)
            self.decoders[channel.id] = None

    def message(self, msg) -> None:
        """One ``mcap`` Message record."""
        self.message_at(msg.channel_id, msg.log_time, msg.data, 0, len(msg.data))

    def message_at(self, channel_id: int, log_time: int, data: bytes, a: int, b: int) -> None:
        """The message of ``channel_id`` logged at ``log_time`` whose payload is data[a:b]."""
        decode = self.decoders.get(channel_id)
        if decode is None:
            return
        topic = self.topics[channel_id]
        if topic in self.skip_topics:
            return
        try:
            block = decode(data[a:b] if a or b != len(data) else data)
        except BlockDecodeError as exc:
            self.bad_messages.append((topic, log_time, exc))  # reported with times later
            return
        if self.window is not None:
            block = _clip(block, *self.window)
            if block is None:
                return
        placer = self.placers.get(topic)
        if placer is None:
            if not any(self.keep(c) for c in block.channels):
                # still note the device so that unknown/missing channels are reported
                self.placers[topic] = _Placer(topic, block, self.keep, 0)
                self.placers[topic].put(block, self.log)
                self.skip_topics.add(topic)
                return
            cap = self.counts.get(channel_id, 0) * block.data.shape[1]
            if self.window is not None:
                span = (self.window[1] - self.window[0]) * block.rate_hz / 1e9
                cap = min(cap, int(span) + 2 * block.data.shape[1])
            placer = self.placers[topic] = _Placer(topic, block, self.keep, cap)
        elif (block.channels != placer.channels or block.rate_hz != placer.rate
              or block.units != placer.units):
            if block.channels != placer.channels:
                what, was = "channels " + str(list(block.channels)), list(placer.channels)
                kind = "unreadable"
            elif block.rate_hz != placer.rate:
                what, was = f"rate_hz={block.rate_hz:g}", f"rate_hz={placer.rate:g}"
                kind = "rate_mismatch"
            else:  # the same values in other units would be misconverted
                what, was = f"units {list(block.units)}", list(placer.units)
                kind = "unit_mismatch"
            raise self.log.fatal(kind, f"device {topic!r} changes within the recording: a block "
                                 f"at t0_ns={block.t0_ns} has {what}, earlier blocks {was}; "
                                 "expected one layout, rate and unit per device (topic)",
                                 channel=",".join(block.channels))
        if abs(log_time - block.t0_ns) * block.rate_hz > 1e9:
            self.bad_times.append((topic, log_time, block.t0_ns))  # reported later
        placer.put(block, self.log)

    @property
    def n_blocks(self) -> int:
        """Sample blocks placed so far."""
        return sum(len(p.pos) for p in self.placers.values())

    @property
    def last_good_ns(self) -> int:
        """End of the latest block placed, ns since the epoch."""
        return max(p.ref + int((max(np.add(p.pos, p.n)) * 1e9) / p.rate)
                   for p in self.placers.values() if p.pos)


def _clip(block: Block, lo_ns: int, hi_ns: int) -> Block | None:
    """The part of ``block`` with sample times in ``[lo_ns, hi_ns)``; None if nothing."""
    n = block.data.shape[1]
    per = 1e9 / block.rate_hz
    k0 = max(0, math.ceil((lo_ns - block.t0_ns) / per - 1e-9))
    k1 = min(n, math.ceil((hi_ns - block.t0_ns) / per - 1e-9))
    if k1 <= k0:
        return None
    if k0 == 0 and k1 == n:
        return block
    return Block(t0_ns=block.t0_ns + int(round(k0 * per)), rate_hz=block.rate_hz,
                 channels=block.channels, units=block.units, data=block.data[:, k0:k1])


def read_mcap(path: str, *, keep: Callable[[str], bool], log: IssueLog,
              window_ns: tuple[int, int] | None = None) -> McapContent:
    """Read the sample blocks, metadata and mill attachment of an MCAP file.

    Parameters
    ----------
    path : str
    keep : callable
        ``keep(channel_name) -> bool``: channels whose samples are kept.
    log : IssueLog
        Receives the findings (truncation, corrupt chunks, dropouts, overlaps).
    window_ns : (int, int), optional
        Keep only samples at ``[start, end)`` ns from the recording's start.

    Raises
    ------
    RecordingError
        Not an MCAP file, no readable sample block, a rate that disagrees with the
        timestamps, or a device whose channels change.
    """
    from mcap.data_stream import ReadDataStream
    from mcap.reader import make_reader
    from mcap.records import Attachment, Channel, Chunk, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader

    failures = _failures()
    content = McapContent(grids=[])
    try:
        fh = open(path, "rb")
    except OSError as exc:
        raise log.fatal("unreadable", f"cannot open the file ({exc.strerror or exc})") from None
    with fh:
        try:
            reader = make_reader(fh, validate_crcs=True)
        except failures as exc:
            raise log.fatal("unreadable", f"not an MCAP file ({exc}); expected the MCAP magic "
                            "bytes at the start") from None
        summary = None
        try:
            summary = reader.get_summary()
        except failures:
            summary = None  # no footer/summary: a file cut short; stream it below
        asm = _Assembler(log, keep, dict(summary.statistics.channel_message_counts)
                         if summary is not None and summary.statistics is not None else {})
        bad_chunks: list[tuple[int, int, int, BaseException]] = []
        broke: tuple[int, int, BaseException] | None = None
        indexed = summary is not None and bool(summary.chunk_indexes)
        if window_ns is not None:
            start = (min(c.message_start_time for c in summary.chunk_indexes) if indexed
                     else _first_log_time(fh, failures))
            content.origin_ns = start
            asm.window = (start + int(window_ns[0]), start + int(window_ns[1]))
        if indexed:
            schemas_in_chunks: dict[int, object] = {}
            for ch in summary.channels.values():
                asm.channel(ch, summary.schemas.get(ch.schema_id))
            for ci in sorted(summary.chunk_indexes,
                             key=lambda c: (c.message_start_time, c.chunk_start_offset)):
                if asm.window is not None and (
                        ci.message_start_time >= asm.window[1]
                        or ci.message_end_time < asm.window[0] - MAX_BLOCK_NS):
                    continue  # holds no sample of the window
                try:
                    fh.seek(ci.chunk_start_offset + 1 + 8)
                    chunk = Chunk.read(ReadDataStream(fh))
                    data = _chunk_bytes(chunk, validate_crc=True)
                    defs, msgs = chunk_records(data)
                except failures as exc:
                    bad_chunks.append((ci.message_start_time, ci.message_end_time,
                                       ci.chunk_start_offset, exc))
                    asm.corrupt_ns.append((ci.message_start_time, ci.message_end_time))
                    continue
                if defs:  # channels defined only inside chunks (not in the summary)
                    for d in defs:
                        if isinstance(d, Schema):
                            schemas_in_chunks[d.id] = d
                    for d in defs:
                        if isinstance(d, Channel) and d.id not in asm.decoders:
                            asm.channel(d, summary.schemas.get(d.schema_id)
                                        or schemas_in_chunks.get(d.schema_id))
                message = asm.message_at
                for log_time, channel_id, a, b in msgs:
                    message(channel_id, log_time, data, a, b)
            try:
                for md in reader.iter_metadata():
                    if md.name == "ident.recording":
                        content.metadata.update(md.metadata)
                for att in reader.iter_attachments():
                    if att.name == "mill.toml":
                        content.mill_toml = bytes(att.data).decode("utf-8", errors="replace")
            except failures as exc:
                log.add("corrupt", f"metadata or attachments cannot be read ({exc}); ignored")
        else:
            fh.seek(0)
            schemas: dict[int, object] = {}
            pos = 0
            try:
                for rec in StreamReader(fh, validate_crcs=True).records:
                    if isinstance(rec, Message):
                        asm.message(rec)
                    elif isinstance(rec, Schema):
                        schemas[rec.id] = rec
                    elif isinstance(rec, Channel):
                        asm.channel(rec, schemas.get(rec.schema_id))
                    elif isinstance(rec, Metadata) and rec.name == "ident.recording":
                        content.metadata.update(rec.metadata)
                    elif isinstance(rec, Attachment) and rec.name == "mill.toml":
                        content.mill_toml = bytes(rec.data).decode("utf-8", errors="replace")
                    pos = fh.tell()
            except failures as exc:
                broke = (pos, fh.seek(0, 2), exc)
        if asm.n_blocks == 0:
            if asm.window is not None and content.origin_ns is not None:
                a, b = ((w - content.origin_ns) / 1e9 for w in asm.window)
                raise log.fatal("empty_window", f"no sample between t={a:.4f} s and "
                                f"t={b:.4f} s from the recording's start", time=a)
            why = (f"the file breaks at byte {broke[0]} of {broke[1]} ({_why(broke[2])})"
                   if broke else
                   "it holds no readable ident.SampleBlock message")
            raise log.fatal("unreadable", f"nothing readable: {why}")
        used = [p for p in asm.placers.values() if p.rows.size] or list(asm.placers.values())
        origin = min(p.ref + int(round(min(p.pos) * 1e9 / p.rate)) for p in used)
        if content.origin_ns is not None:
            origin = min(origin, content.origin_ns)
            content.origin_ns = origin
        for a, b, offset, exc in bad_chunks:
            log.add("corrupt", f"the chunk at byte {offset} cannot be read "
                    f"({_why(exc)}); its samples from t={(a - origin) / 1e9:.4f} s "
                    f"to t={(b - origin) / 1e9:.4f} s are missing (NaN); the rest is read",
                    t_start=(a - origin) / 1e9, t_end=(b - origin) / 1e9)
        for topic, log_time, exc in asm.bad_messages:
            t = (log_time - origin) / 1e9
            log.add("corrupt", f"topic {topic!r}: the message logged at t={t:.4f} s is not a "
                    f"sample block ({exc}); skipped, its samples are a dropout", t_start=t,
                    device=topic)
        for topic, log_time, t0 in asm.bad_times:
            t = (t0 - origin) / 1e9
            log.add("timestamp_mismatch", f"topic {topic!r}: the block at t={t:.4f} s has a "
                    f"log_time {(log_time - t0) / 1e9:+.6f} s off its t0_ns; t0_ns is used",
                    t_start=t, device=topic)
        if broke is not None:
            t_last = (asm.last_good_ns - origin) / 1e9
            log.add("truncated", f"the file breaks off at byte {broke[0]} of {broke[1]} "
                    f"({_why(broke[2])}); read up to the last good block, "
                    f"which ends at t={t_last:.4f} s; the rest is lost", t_start=t_last)
        for placer in asm.placers.values():
            grid = placer.finish(log, asm.corrupt_ns, origin)
            grid.origin_ns = content.origin_ns
            content.grids.append(grid)
    return content


def _first_log_time(fh, failures: tuple[type[BaseException], ...]) -> int:
    """``log_time`` of the first message of a file streamed from its start."""
    from mcap.records import Message
    from mcap.stream_reader import StreamReader

    fh.seek(0)
    try:
        for rec in StreamReader(fh, validate_crcs=True).records:
            if isinstance(rec, Message):
                return int(rec.log_time)
    except failures:
        pass
    finally:
        fh.seek(0)
    return 0


def mcap_span_ns(path: str, log: IssueLog | None = None) -> tuple[int, int] | None:
    """``(first, last)`` message log times of an MCAP file (its summary, or a stream).

    None when it holds no readable message.  Raises the RecordingError of ``log``
    (``unreadable``) when the file cannot be opened.
    """
    from mcap.reader import make_reader
    from mcap.records import Message
    from mcap.stream_reader import StreamReader

    failures = _failures()
    try:
        fh = open(path, "rb")
    except OSError as exc:
        raise (log or IssueLog(str(path))).fatal(
            "unreadable", f"cannot open the file ({exc.strerror or exc})") from None
    with fh:
        try:
            summary = make_reader(fh).get_summary()
        except failures:
            summary = None
        if summary is not None and summary.chunk_indexes:
            return (min(c.message_start_time for c in summary.chunk_indexes),
                    max(c.message_end_time for c in summary.chunk_indexes))
        fh.seek(0)
        lo = hi = None
        try:
            for rec in StreamReader(fh, validate_crcs=False).records:
                if isinstance(rec, Message):
                    t = int(rec.log_time)
                    lo = t if lo is None else min(lo, t)
                    hi = t if hi is None else max(hi, t)
        except failures:
            pass
    return None if lo is None else (lo, hi)
