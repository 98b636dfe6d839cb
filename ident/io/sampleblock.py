"""The ``ident.SampleBlock`` message of MCAP recordings: schemas, encoding, decoding.

A sample block holds consecutive samples of one device's channels
(``../shared/spec/telemetry.md``)::

    int64  t0_ns    = 1;   // time of the first sample, ns since the Unix epoch
    double rate_hz  = 2;   // sample rate, Hz
    repeated string channels = 3;
    repeated string units    = 4;   // recorded unit per channel ("raw": scale/offset apply)
    repeated float  data     = 5;   // channel-major: all of channels[0], then channels[1], ...

Two encodings: ``protobuf`` (schema = a serialized ``FileDescriptorSet`` built here
with ``descriptor_pb2``) and ``json`` (schema = a JSON Schema; ``data`` a list of
lists, ``null`` for a missing sample).

Decoding avoids Python floats per sample.  Protobuf: a small wire-format walker
finds the packed ``data`` field and views it with ``numpy.frombuffer``; field numbers
and types come from the schema's descriptor, and anything the walker does not
recognise falls back to the message class built from the schema.  JSON: the
``data`` array is cut out of the text and parsed by ``numpy.fromstring``; the rest
of the object goes through :mod:`json`.
"""

from __future__ import annotations

import json
import re
import struct
import warnings
from dataclasses import dataclass
from typing import Callable

import numpy as np

__all__ = [
    "SCHEMA_NAME",
    "Block",
    "BlockDecodeError",
    "protobuf_schema",
    "json_schema",
    "encode_protobuf",
    "encode_json",
    "make_decoder",
]

SCHEMA_NAME = "ident.SampleBlock"

_FIELDS = (("t0_ns", 1, "TYPE_INT64", False), ("rate_hz", 2, "TYPE_DOUBLE", False),
           ("channels", 3, "TYPE_STRING", True), ("units", 4, "TYPE_STRING", True),
           ("data", 5, "TYPE_FLOAT", True))


class BlockDecodeError(ValueError):
    """A message is not a decodable sample block (the reader adds path and time)."""


@dataclass(frozen=True)
class Block:
    """One decoded sample block.

    Attributes
    ----------
    t0_ns : int
        Time of the first sample, ns since the Unix epoch.
    rate_hz : float
    channels, units : tuple of str
    data : ndarray, shape (n_channels, n_samples), float32
        Recorded values (NaN = missing); may be a read-only view of the message bytes.
    """

    t0_ns: int
    rate_hz: float
    channels: tuple[str, ...]
    units: tuple[str, ...]
    data: np.ndarray


# ---- schemas ------------------------------------------------------------------------------
def protobuf_schema() -> bytes:
    """Serialized ``FileDescriptorSet`` of ``ident.SampleBlock`` (proto3, packed data)."""
    from google.protobuf import descriptor_pb2

    fds = descriptor_pb2.FileDescriptorSet()
    fd = fds.file.add()
    fd.name = "ident/sample_block.proto"
    fd.package = "ident"
    fd.syntax = "proto3"
    msg = fd.message_type.add()
    msg.name = "SampleBlock"
    for name, number, ftype, repeated in _FIELDS:
        f = msg.field.add()
        f.name = name
        f.number = number
        f.type = getattr(descriptor_pb2.FieldDescriptorProto, ftype)
        f.label = (descriptor_pb2.FieldDescriptorProto.LABEL_REPEATED if repeated
                   else descriptor_pb2.FieldDescriptorProto.LABEL_OPTIONAL)
        f.json_name = name
    return fds.SerializeToString()


def json_schema() -> bytes:
    """JSON Schema (draft 2020-12) of the JSON encoding of ``ident.SampleBlock``."""
    schema = {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": SCHEMA_NAME,
        "type": "object",
        "required": ["t0_ns", "rate_hz", "channels", "units", "data"],
        "properties": {
            "t0_ns": {"type": "integer", "description": "first sample, ns since the Unix epoch"},
            "rate_hz": {"type": "number", "exclusiveMinimum": 0},
            "channels": {"type": "array", "items": {"type": "string"}},
            "units": {"type": "array", "items": {"type": "string"}},
            "data": {"type": "array", "description": "one array per channel; null = missing",
                     "items": {"type": "array", "items": {"type": ["number", "null"]}}},
        },
    }
    return json.dumps(schema, separators=(",", ":")).encode()


# ---- encoding ------------------------------------------------------------------------------
def _varint(value: int) -> bytes:
    value &= (1 << 64) - 1  # int64 two's complement, as protobuf does
    out = bytearray()
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def _read_varint(buf: bytes, pos: int) -> tuple[int, int]:
    """Decode the varint at ``buf[pos]``; returns (value, position after it)."""
    b = buf[pos]
    pos += 1
    value = b & 0x7F
    shift = 7
    while b & 0x80:
        b = buf[pos]
        pos += 1
        value |= (b & 0x7F) << shift
        shift += 7
    return value, pos


def _len_field(number: int, payload: bytes) -> bytes:
    return _varint((number << 3) | 2) + _varint(len(payload)) + payload


def encode_protobuf(t0_ns: int, rate_hz: float, channels: tuple[str, ...],
                    units: tuple[str, ...], data: np.ndarray) -> bytes:
    """Protobuf wire bytes of one block, identical to ``SerializeToString``.

    ``data`` has shape (n_channels, n_samples); it is written channel-major as float32.
    """
    parts = [_varint(1 << 3) + _varint(int(t0_ns))] if int(t0_ns) else []  # proto3: 0 omitted
    parts.append(bytes([(2 << 3) | 1]) + struct.pack("<d", float(rate_hz)))
    parts += [_len_field(3, c.encode()) for c in channels]
    parts += [_len_field(4, u.encode()) for u in units]
    payload = np.ascontiguousarray(data, dtype="<f4").tobytes()
    if payload:
        parts.append(_len_field(5, payload))
    return b"".join(parts)


def encode_json(t0_ns: int, rate_hz: float, channels: tuple[str, ...],
                units: tuple[str, ...], data: np.ndarray) -> bytes:
    """JSON bytes of one block; float32 values in shortest form, NaN as ``null``."""
    import pyarrow as pa
    import pyarrow.compute as pc

    arr = np.ascontiguousarray(data, dtype=np.float32)
    n_ch, n = arr.shape
    if arr.size:
        text = pc.fill_null(pa.array(arr.ravel(), from_pandas=True).cast(pa.string()), "null")
        offsets = pa.array(np.arange(0, arr.size + 1, n, dtype=np.int32))
        rows = pc.binary_join(pa.ListArray.from_arrays(offsets, text), ",").to_pylist()
        body = "[" + "],[".join(rows) + "]"
    else:
        body = ",".join("[]" for _ in range(n_ch))
    head = json.dumps({"t0_ns": int(t0_ns), "rate_hz": float(rate_hz),
                       "channels": list(channels), "units": list(units)},
                      separators=(",", ":"))
    return (head[:-1] + ',"data":[' + body + "]}").encode()


# ---- decoding ------------------------------------------------------------------------------
def make_decoder(schema_encoding: str, message_encoding: str,
                 schema_data: bytes) -> Callable[[bytes], Block]:
    """Return ``decode(message_bytes) -> Block`` for a channel's encodings and schema.

    Raises
    ------
    BlockDecodeError
        Unsupported encodings, or a protobuf schema without ``ident.SampleBlock``.
    """
    if message_encoding == "json":
        return _decode_json
    if message_encoding == "protobuf" and schema_encoding == "protobuf":
        return _protobuf_decoder(schema_data)
    raise BlockDecodeError(
        f"unsupported encoding: schema {schema_encoding!r}, messages {message_encoding!r}; "
        "expected 'jsonschema'/'json' or 'protobuf'/'protobuf'")


# protobuf ---------------------------------------------------------------------------------
_VARINT_TYPES = {"TYPE_INT64", "TYPE_UINT64", "TYPE_INT32", "TYPE_UINT32", "TYPE_SINT64",
                 "TYPE_SINT32"}


def _protobuf_decoder(schema_data: bytes) -> Callable[[bytes], Block]:
    from google.protobuf import descriptor_pb2
    from google.protobuf.message import DecodeError

    try:
        fds = descriptor_pb2.FileDescriptorSet.FromString(schema_data)
    except DecodeError as exc:
        raise BlockDecodeError(f"schema is not a protobuf FileDescriptorSet: {exc}") from None
    fields: dict[str, tuple[int, str, bool]] | None = None
    for fd in fds.file:
        for m in fd.message_type:
            full = f"{fd.package}.{m.name}" if fd.package else m.name
            if full == SCHEMA_NAME:
                fields = {f.name: (f.number, descriptor_pb2.FieldDescriptorProto.Type.Name(f.type),
                                   f.label == descriptor_pb2.FieldDescriptorProto.LABEL_REPEATED)
                          for f in m.field}
    if fields is None:
        raise BlockDecodeError(f"protobuf schema does not define message {SCHEMA_NAME!r}")
    missing = [name for name, *_ in _FIELDS if name not in fields]
    if missing:
        raise BlockDecodeError(f"protobuf schema of {SCHEMA_NAME} lacks fields {missing}")
    t0_num, t0_type, _ = fields["t0_ns"]
    rate_num, rate_type, _ = fields["rate_hz"]
    ch_num, unit_num, data_num = fields["channels"][0], fields["units"][0], fields["data"][0]
    data_type = fields["data"][1]
    fast = (t0_type in _VARINT_TYPES | {"TYPE_FIXED64", "TYPE_SFIXED64"}
            and rate_type in ("TYPE_DOUBLE", "TYPE_FLOAT")
            and data_type in ("TYPE_FLOAT", "TYPE_DOUBLE"))
    if not fast:
        return _slow_protobuf_decoder(schema_data)
    data_dtype = np.dtype("<f4") if data_type == "TYPE_FLOAT" else np.dtype("<f8")
    zigzag = t0_type in ("TYPE_SINT64", "TYPE_SINT32")
    signed_fixed = t0_type == "TYPE_SFIXED64"
    unpack_d = struct.Struct("<d").unpack_from
    unpack_f = struct.Struct("<f").unpack_from
    unpack_q = struct.Struct("<q").unpack_from
    unpack_Q = struct.Struct("<Q").unpack_from

    # Fast path: messages of one channel repeat everything between t0_ns and data
    # (rate, channels, units).  After a full parse of a canonical message (t0_ns first,
    # one packed data field last) those bytes are cached; a message that starts with
    # t0_ns, repeats them and ends with the data field is decoded from its two ends.
    t0_tag = (t0_num << 3) | 0
    data_tag = (data_num << 3) | 2
    fast_ok = t0_type in ("TYPE_INT64", "TYPE_UINT64") and t0_tag < 0x80 and data_tag < 0x80
    cache: list = [None]  # (middle bytes, rate, channels, units), per decoder

    def decode(buf: bytes) -> Block:
        c = cache[0]
        if c is not None and buf and buf[0] == t0_tag:
            try:
                t0, pos = _read_varint(buf, 1)
                middle = c[0]
                if buf.startswith(middle, pos):
                    pos += len(middle)
                    if buf[pos] == data_tag:
                        ln, pos = _read_varint(buf, pos + 1)
                        n_ch = len(c[2])
                        count = ln // data_dtype.itemsize
                        if (pos + ln == len(buf) and ln % data_dtype.itemsize == 0
                                and count % n_ch == 0):
                            if t0 >= (1 << 63):
                                t0 -= 1 << 64
                            flat = np.frombuffer(buf, dtype=data_dtype, count=count, offset=pos)
                            return Block(t0, c[1], c[2], c[3], flat.reshape(n_ch, count // n_ch))
            except IndexError:
                pass  # fall through to the full parse, which reports the problem
        return full(buf)

    def full(buf: bytes) -> Block:
        mv = buf
        n = len(mv)
        pos = 0
        t0 = 0
        rate = 0.0
        channels: list[str] = []
        units: list[str] = []
        pieces: list[np.ndarray] = []
        scalars: list[float] = []
        first_end = -1   # end of the first field when it is t0_ns
        data_at = -1     # tag position of the (single) data field
        try:
            while pos < n:
                tag_at = pos
                tag, pos = _read_varint(mv, pos)
                num, wt = tag >> 3, tag & 7
                if wt == 0:
                    val, pos = _read_varint(mv, pos)
                    if num == t0_num:
                        if zigzag:
                            t0 = (val >> 1) ^ -(val & 1)
                        else:
                            t0 = val - (1 << 64) if val >= (1 << 63) else val
                        if tag_at == 0:
                            first_end = pos
                elif wt == 1:
                    if num == rate_num:
                        rate = unpack_d(mv, pos)[0]
                    elif num == t0_num:
                        t0 = (unpack_q if signed_fixed else unpack_Q)(mv, pos)[0]
                    elif num == data_num:
                        scalars.append(unpack_d(mv, pos)[0])
                    pos += 8
                elif wt == 2:
                    ln, pos = _read_varint(mv, pos)
                    end = pos + ln
                    if end > n:
                        raise BlockDecodeError("malformed protobuf message: a field runs "
                                               "past its end")
                    if num == data_num:
                        if ln % data_dtype.itemsize:
                            raise BlockDecodeError("malformed protobuf message: packed data "
                                                   "length is not a whole number of values")
                        pieces.append(np.frombuffer(mv, dtype=data_dtype,
                                                    count=ln // data_dtype.itemsize, offset=pos))
                        data_at = tag_at
                    elif num == ch_num:
                        channels.append(mv[pos:end].decode())
                    elif num == unit_num:
                        units.append(mv[pos:end].decode())
                    pos = end
                elif wt == 5:
                    if num == rate_num:
                        rate = unpack_f(mv, pos)[0]
                    elif num == data_num:
                        scalars.append(unpack_f(mv, pos)[0])
                    pos += 4
                else:
                    raise BlockDecodeError(f"malformed protobuf message: wire type {wt}")
        except (IndexError, struct.error, UnicodeDecodeError) as exc:
            raise BlockDecodeError(f"malformed protobuf message: {exc}") from None
        if pos != n:
            raise BlockDecodeError("malformed protobuf message: truncated field")
        if scalars:  # unpacked repeated values (legal, unusual): keep wire order
            pieces.append(np.asarray(scalars, dtype=data_dtype))
        if len(pieces) == 1:
            flat = pieces[0]
        elif pieces:
            flat = np.concatenate(pieces)
        else:
            flat = np.empty(0, dtype=np.float32)
        block = _make_block(t0, rate, channels, units, flat)
        if fast_ok and first_end > 0 and data_at > first_end and len(pieces) == 1 \
                and not scalars:
            cache[0] = (bytes(mv[first_end:data_at]), block.rate_hz, block.channels,
                        block.units)
        return block

    return decode


def _slow_protobuf_decoder(schema_data: bytes) -> Callable[[bytes], Block]:
    """Decode through the message class built from the schema (unusual field types)."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    from google.protobuf.message import DecodeError

    fds = descriptor_pb2.FileDescriptorSet.FromString(schema_data)
    pool = descriptor_pool.DescriptorPool()
    for fd in fds.file:
        pool.Add(fd)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(SCHEMA_NAME))

    def decode(buf: bytes) -> Block:
        try:
            msg = cls.FromString(buf)
        except DecodeError as exc:
            raise BlockDecodeError(f"malformed protobuf message: {exc}") from None
        flat = np.fromiter(msg.data, dtype=np.float32, count=len(msg.data))
        return _make_block(int(msg.t0_ns), float(msg.rate_hz), list(msg.channels),
                           list(msg.units), flat)

    return decode


def _make_block(t0: int, rate: float, channels: list[str], units: list[str],
                flat: np.ndarray) -> Block:
    n_ch = len(channels)
    if n_ch == 0:
        raise BlockDecodeError("block names no channels")
    if len(units) not in (0, n_ch):
        raise BlockDecodeError(f"block has {n_ch} channels but {len(units)} units")
    if flat.size % n_ch:
        raise BlockDecodeError(f"block holds {flat.size} values, not a multiple of its "
                               f"{n_ch} channels")
    if not rate > 0:
        raise BlockDecodeError(f"block rate_hz must be positive; got {rate}")
    return Block(int(t0), float(rate), tuple(channels), tuple(units) or ("",) * n_ch,
                 flat.reshape(n_ch, flat.size // n_ch))


# json -------------------------------------------------------------------------------------
_DATA_KEY = re.compile(rb'"data"\s*:\s*\[')
_DATA_END = re.compile(rb"\]\s*\]")


def _decode_json(buf: bytes) -> Block:
    m = _DATA_KEY.search(buf)
    rows: list[str] = []
    flat = np.empty(0, dtype=np.float32)
    head_text = buf
    if m is not None:
        # The data array holds only numbers, null, brackets, commas and blanks, so it
        # ends at the first "]" that is followed (after blanks) by another "]".
        start = m.end()
        rest = buf[start:].lstrip()
        if rest.startswith(b"]"):
            body, end = "", len(buf) - len(rest) + 1
        else:
            end_m = _DATA_END.search(buf, start)
            if end_m is None:
                raise BlockDecodeError("JSON block: the 'data' array is not closed")
            body = buf[start:end_m.start() + 1].decode("ascii", errors="replace")
            end = end_m.end()
        head_text = buf[:m.start()] + b'"data":null' + buf[end:]
        for piece in body.split("]")[:-1]:
            piece = piece.strip().lstrip(",").strip()
            if not piece.startswith("["):
                raise BlockDecodeError("JSON block: 'data' must be a list of lists of numbers")
            rows.append(piece[1:].strip())
        if any(c in body for c in '{}"'):
            raise BlockDecodeError("JSON block: 'data' must be a list of lists of numbers")
        lengths = {r.count(",") + 1 if r else 0 for r in rows}
        if len(lengths) > 1:
            raise BlockDecodeError(f"JSON block: channels hold different numbers of samples "
                                   f"{sorted(lengths)}")
        joined = ",".join(r for r in rows if r)
        if joined:
            n_vals = sum(lengths) * len(rows)
            with warnings.catch_warnings():  # numpy warns, then stops, at a bad token
                warnings.simplefilter("ignore")
                try:
                    flat = np.fromstring(joined.replace("null", "nan"), dtype=np.float32, sep=",")
                except ValueError:
                    flat = np.empty(0, dtype=np.float32)
            if flat.size != n_vals:
                raise BlockDecodeError("JSON block: 'data' holds a value that is not a number "
                                       "or null")
    try:
        head = json.loads(head_text)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise BlockDecodeError(f"JSON block is not valid JSON: {exc}") from None
    if not isinstance(head, dict):
        raise BlockDecodeError("JSON block must be an object")
    try:
        t0 = int(head["t0_ns"])
        rate = float(head["rate_hz"])
        channels = [str(c) for c in head["channels"]]
        units = [str(u) for u in head.get("units") or []]
    except (KeyError, TypeError, ValueError) as exc:
        raise BlockDecodeError(f"JSON block lacks or misformats key {exc}") from None
    if rows and len(rows) != len(channels):
        raise BlockDecodeError(f"JSON block has {len(channels)} channels but {len(rows)} data "
                               "rows")
    return _make_block(t0, rate, channels, units, flat)
