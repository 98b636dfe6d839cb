"""The ``ident.SampleBlock`` codecs against protobuf's own serializer and plain ``json``."""

from __future__ import annotations

import json

import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from ident.io.sampleblock import (BlockDecodeError, encode_json, encode_protobuf, json_schema,
                                  make_decoder, protobuf_schema)

CH = ("T_C12", "T_C34", "A_B23_v")
UNITS = ("kN*m", "raw", "g")


def message_class(fds: descriptor_pb2.FileDescriptorSet):
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fds.file[0])
    return message_factory.GetMessageClass(pool.FindMessageTypeByName("ident.SampleBlock"))


@pytest.fixture
def data():
    d = np.random.default_rng(1).normal(size=(3, 50)).astype(np.float32)
    d[1, 7] = np.nan
    return d


@pytest.mark.parametrize("t0", [1_732_252_800_123_456_789, 0, -5])
def test_protobuf_encoding_is_protobufs_own(data, t0):
    cls = message_class(descriptor_pb2.FileDescriptorSet.FromString(protobuf_schema()))
    ours = encode_protobuf(t0, 2000.0, CH, UNITS, data)
    theirs = cls(t0_ns=t0, rate_hz=2000.0, channels=CH, units=UNITS,
                 data=data.ravel().tolist()).SerializeToString()
    assert ours == theirs
    decode = make_decoder("protobuf", "protobuf", protobuf_schema())
    for _ in range(3):  # the first call parses fully, the next ones take the cached layout
        b = decode(ours)
        assert (b.t0_ns, b.rate_hz, b.channels, b.units) == (t0, 2000.0, CH, UNITS)
        np.testing.assert_array_equal(b.data, data)
    other = decode(encode_protobuf(t0 + 1, 1000.0, CH[:2], UNITS[:2], data[:2]))
    assert other.rate_hz == 1000.0 and other.channels == CH[:2]  # layout change: full parse


def test_unusual_protobuf_schema_uses_the_message_class(data):
    fds = descriptor_pb2.FileDescriptorSet.FromString(protobuf_schema())
    fds.file[0].message_type[0].field[0].type = descriptor_pb2.FieldDescriptorProto.TYPE_FIXED32
    cls = message_class(fds)
    raw = cls(t0_ns=12345, rate_hz=500.0, channels=CH, units=UNITS,
              data=data.ravel().tolist()).SerializeToString()
    b = make_decoder("protobuf", "protobuf", fds.SerializeToString())(raw)
    assert b.t0_ns == 12345 and b.rate_hz == 500.0
    np.testing.assert_array_equal(b.data, data)
    with pytest.raises(BlockDecodeError, match=r"malformed protobuf message"):
        make_decoder("protobuf", "protobuf", fds.SerializeToString())(b"\xff\xff\xff")


def test_protobuf_errors(data):
    decode = make_decoder("protobuf", "protobuf", protobuf_schema())
    good = encode_protobuf(1, 10.0, CH, UNITS, data)
    with pytest.raises(BlockDecodeError, match=r"malformed protobuf message"):
        decode(good[:-3])
    with pytest.raises(BlockDecodeError, match=r"block has 3 channels but 2 units"):
        decode(encode_protobuf(1, 10.0, CH, UNITS[:2], data))
    with pytest.raises(BlockDecodeError, match=r"does not define message 'ident\.SampleBlock'"):
        make_decoder("protobuf", "protobuf", descriptor_pb2.FileDescriptorSet().SerializeToString())
    with pytest.raises(BlockDecodeError, match=r"unsupported encoding: schema 'ros2msg'"):
        make_decoder("ros2msg", "cdr", b"")


def test_json_encoding_is_valid_json(data):
    raw = encode_json(7, 2000.0, CH, UNITS, data)
    doc = json.loads(raw)
    assert doc["t0_ns"] == 7 and doc["channels"] == list(CH) and doc["data"][1][7] is None
    np.testing.assert_array_equal(np.array(doc["data"], dtype=float).astype(np.float32), data)
    b = make_decoder("jsonschema", "json", json_schema())(raw)
    np.testing.assert_array_equal(b.data, data)
    assert json.loads(json_schema())["title"] == "ident.SampleBlock"


@pytest.mark.parametrize("text, match", [
    (b'{"t0_ns": 1, "rate_hz": 10, "channels": ["a"], "data": [[1, 2]', r"not closed"),
    (b'{"t0_ns": 1, "rate_hz": 10, "channels": ["a", "b"], "data": [[1, 2]]}',
     r"2 channels but 1 data rows"),
    (b'{"t0_ns": 1, "rate_hz": 0, "channels": ["a"], "data": [[1, 2]]}',
     r"rate_hz must be positive; got 0\.0"),
    (b'{"rate_hz": 10, "channels": ["a"], "data": [[1, 2]]}', r"lacks or misformats key 't0_ns'"),
    (b'[1, 2]', r"must be an object"),
])
def test_json_errors(text, match):
    with pytest.raises(BlockDecodeError, match=match):
        make_decoder("jsonschema", "json", b"")(text)
