"""Write recordings as MCAP or CSV (``../shared/spec/telemetry.md``).

:func:`write_recording` writes whole :class:`~ident.io.recording.RawDevice` s; the
streaming writers :class:`McapRecordingWriter` and :class:`CsvDeviceWriter` write
block by block, for recordings too long to hold in memory (the benchmark writes an
hour this way).  Every write is atomic: a temporary file in the target's directory,
renamed over the target with ``os.replace`` only when complete.

MCAP layout: one topic per device (the device's ``name``), messages are
``ident.SampleBlock`` blocks in ``protobuf`` (default) or ``json`` encoding, each
message's ``log_time`` = ``publish_time`` = the time of its first sample; optional
``ident.recording`` metadata and a ``mill.toml`` attachment.  Chunks are compressed
with lz4 (zstd if lz4 is missing, none if both are).  The file gets the mode a plain
``open`` would give it (``0o666 & ~umask``), not the temporary file's ``0o600``.

CSV layout: one sample rate per file, so one file per device.  The first device goes
to the given path ``name.csv``; every further device to a sibling
``name.<device>.csv`` where ``<device>`` is the last part of the device name made
file-safe (``/telemetry/accel`` -> ``name.accel.csv``).  The header is
``time,T_C12 [kN*m],...`` (units always written); ``time`` is float seconds from the
recording's start (the earliest first sample over all devices, so siblings share
one time origin) or, with ``time_format="iso"``, absolute ISO-8601 UTC timestamps.
Missing samples are written as ``nan``.  :func:`ident.io.read_recording` reads the
siblings back with the main file.
"""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path
from typing import IO, Literal, Mapping, Sequence

import numpy as np

from ..errors import RecordingError
from .recording import RawDevice
from .sampleblock import (SCHEMA_NAME, encode_json, encode_protobuf, json_schema,
                          protobuf_schema)

__all__ = ["write_recording", "McapRecordingWriter", "CsvDeviceWriter", "csv_sibling_path",
           "AtomicFile", "new_file_mode", "DEFAULT_BLOCK_S"]

#: Default block length of MCAP sample blocks, s.
DEFAULT_BLOCK_S = 0.1

_BAD_NAME = re.compile(r'[,;"\[\]\n\r]')


# ---- atomic files ------------------------------------------------------------------------
def new_file_mode() -> int:
    """``0o666 & ~umask``: the permissions ``open(path, "w")`` gives a new file.

    The umask is read from ``/proc/self/status`` where there is one (setting it to read
    it back would race with other threads creating files); elsewhere by ``os.umask``.
    """
    try:
        with open("/proc/self/status", encoding="ascii", errors="replace") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return 0o666 & ~int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o666 & ~mask


class AtomicFile:
    """A temporary file beside ``path``, renamed onto it by :meth:`commit`.

    ``tempfile.mkstemp`` creates it ``0o600``; it is given :func:`new_file_mode` at
    once, so the final file honours the umask as a plain ``open`` would.
    """

    def __init__(self, path: str | Path, mode: str = "wb") -> None:
        self.path = path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        self.tmp = Path(tmp)
        try:
            os.fchmod(fd, new_file_mode())
            self.fh: IO = os.fdopen(fd, mode)
        except BaseException:
            os.close(fd)
            self.tmp.unlink(missing_ok=True)
            raise

    def commit(self) -> None:
        self.fh.close()
        os.replace(self.tmp, self.path)

    def abort(self) -> None:
        try:
            self.fh.close()
        finally:
            self.tmp.unlink(missing_ok=True)


def _check_device(dev: RawDevice, path: str) -> np.ndarray:
    data = np.asarray(dev.data)
    where = dict(path=path, channel=None)
    if data.ndim != 2 or data.shape[0] != len(dev.channels):
        raise RecordingError(f"device {dev.name!r}: data must have shape (n_channels="
                             f"{len(dev.channels)}, n_samples); got {data.shape}", **where)
    if len(dev.units) != len(dev.channels):
        raise RecordingError(f"device {dev.name!r}: {len(dev.channels)} channels but "
                             f"{len(dev.units)} units", **where)
    if not (np.isfinite(dev.rate_hz) and dev.rate_hz > 0):
        raise RecordingError(f"device {dev.name!r}: rate_hz must be positive; got "
                             f"{dev.rate_hz}", **where)
    for c in dev.channels:
        if not c or _BAD_NAME.search(c):
            raise RecordingError(f"device {dev.name!r}: channel name {c!r} is empty or holds "
                                 "one of , ; \" [ ] or a line break", **where)
    return data


def _check_devices(devices: Sequence[RawDevice], path: str) -> list[np.ndarray]:
    if not devices:
        raise RecordingError("no devices to write; expected at least one RawDevice", path=path)
    names = [d.name for d in devices]
    if len(set(names)) != len(names):
        raise RecordingError(f"device names must be unique; got {names}", path=path)
    seen: set[str] = set()
    for d in devices:
        dup = seen.intersection(d.channels)
        if dup or len(set(d.channels)) != len(d.channels):
            raise RecordingError(f"channel names must be unique over all devices; "
                                 f"{sorted(dup) or list(d.channels)} repeat", path=path)
        seen.update(d.channels)
    return [_check_device(d, path) for d in devices]


# ---- MCAP ---------------------------------------------------------------------------------
def _compression():
    from mcap.writer import CompressionType

    try:
        import lz4.frame  # noqa: F401
        return CompressionType.LZ4
    except ImportError:
        pass
    try:
        import zstandard  # noqa: F401
        return CompressionType.ZSTD
    except ImportError:
        return CompressionType.NONE


class McapRecordingWriter:
    """Write an MCAP recording block by block; the file appears when :meth:`close` succeeds.

    Parameters
    ----------
    path : str or Path
        Target ``.mcap`` file.
    encoding : {"protobuf", "json"}
        Message encoding of the sample blocks.
    metadata : mapping of str to str, optional
        Written as the ``ident.recording`` metadata record (``mill``, ``stand``,
        ``campaign``, ``recording_id``; other keys are kept too).
    mill_toml : str, optional
        Text of the mill file, attached as ``mill.toml``.
    chunk_size : int
        MCAP chunk size, bytes.

    Examples
    --------
    >>> with McapRecordingWriter("r.mcap") as w:                      # doctest: +SKIP
    ...     dev = w.add_device("/telemetry/torque", rate_hz=2000.0,
    ...                        channels=("T_C12",), units=("kN*m",))
    ...     w.write_block(dev, t0_ns, data)          # data: (n_channels, n_samples)
    """

    def __init__(self, path: str | Path, *, encoding: Literal["protobuf", "json"] = "protobuf",
                 metadata: Mapping[str, str] | None = None, mill_toml: str | None = None,
                 chunk_size: int = 1 << 20) -> None:
        from mcap.writer import Writer

        self.path = Path(path)
        if encoding not in ("protobuf", "json"):
            raise RecordingError(f"encoding must be 'protobuf' or 'json'; got {encoding!r}",
                                 path=str(path))
        self._encoding = encoding
        self._encode = encode_protobuf if encoding == "protobuf" else encode_json
        self._file = AtomicFile(self.path)
        try:
            self._w = Writer(self._file.fh, chunk_size=chunk_size, compression=_compression())
            self._w.start(profile="", library="ident")
            if encoding == "protobuf":
                self._schema = self._w.register_schema(SCHEMA_NAME, "protobuf", protobuf_schema())
            else:
                self._schema = self._w.register_schema(SCHEMA_NAME, "jsonschema", json_schema())
            if metadata:
                bad = [k for k, v in metadata.items()
                       if not isinstance(k, str) or not isinstance(v, str)]
                if bad:
                    raise RecordingError(f"metadata keys and values must be strings; {bad} "
                                         "are not", path=str(path))
                self._w.add_metadata("ident.recording", dict(metadata))
            if mill_toml is not None:
                self._w.add_attachment(create_time=0, log_time=0, name="mill.toml",
                                       media_type="application/toml",
                                       data=mill_toml.encode("utf-8"))
        except BaseException:
            self._file.abort()
            raise
        self._devices: dict[int, tuple[str, float, tuple[str, ...], tuple[str, ...]]] = {}
        self._seq: dict[int, int] = {}

    def add_device(self, name: str, *, rate_hz: float, channels: Sequence[str],
                   units: Sequence[str]) -> int:
        """Register a device (one MCAP topic); returns its id for :meth:`write_block`."""
        dev = RawDevice(name, float(rate_hz), 0, tuple(channels), tuple(units),
                        np.empty((len(channels), 0), dtype=np.float32))
        _check_device(dev, str(self.path))
        cid = self._w.register_channel(topic=name, message_encoding=self._encoding,
                                       schema_id=self._schema)
        self._devices[cid] = (name, float(rate_hz), tuple(channels), tuple(units))
        self._seq[cid] = 0
        return cid

    def write_block(self, device: int, t0_ns: int, data: np.ndarray) -> None:
        """Write one sample block.

        Parameters
        ----------
        device : int
            Id from :meth:`add_device`.
        t0_ns : int
            Time of the block's first sample, ns since the Unix epoch.
        data : ndarray, shape (n_channels, n_samples)
            Values in the device's units; NaN for a missing sample.
        """
        _, rate, channels, units = self._devices[device]
        if data.ndim != 2 or data.shape[0] != len(channels):
            raise RecordingError(f"block for device {self._devices[device][0]!r} must have "
                                 f"shape ({len(channels)}, n); got {data.shape}",
                                 path=str(self.path))
        payload = self._encode(int(t0_ns), rate, channels, units, data)
        self._w.add_message(channel_id=device, log_time=int(t0_ns), data=payload,
                            publish_time=int(t0_ns), sequence=self._seq[device])
        self._seq[device] += 1

    def write_device(self, dev: RawDevice, *, block_samples: int | None = None) -> None:
        """Register ``dev`` and write all its samples in blocks of ``block_samples``."""
        data = _check_device(dev, str(self.path))
        cid = self.add_device(dev.name, rate_hz=dev.rate_hz, channels=dev.channels,
                              units=dev.units)
        n = data.shape[1]
        bs = block_samples or max(1, int(round(dev.rate_hz * DEFAULT_BLOCK_S)))
        for start in range(0, n, bs):
            t0 = dev.t0_ns + int(round(start * 1e9 / dev.rate_hz))
            self.write_block(cid, t0, data[:, start:start + bs])

    def close(self) -> None:
        """Finish the file (summary, indexes) and move it into place."""
        try:
            self._w.finish()
            self._file.commit()
        except BaseException:
            self._file.abort()
            raise

    def abort(self) -> None:
        """Drop the partial file."""
        self._file.abort()

    def __enter__(self) -> "McapRecordingWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


# ---- CSV ----------------------------------------------------------------------------------
def csv_sibling_path(path: str | Path, device: str) -> Path:
    """Path of the CSV file of a further device: ``name.csv`` -> ``name.<device>.csv``."""
    p = Path(path)
    tag = re.sub(r"[^A-Za-z0-9_\-]+", "_", device.strip("/").split("/")[-1]) or "device"
    return p.with_name(f"{p.stem}.{tag}{p.suffix}")


class CsvDeviceWriter:
    """Write one device's samples to a CSV file, block by block (atomic on :meth:`close`).

    Parameters
    ----------
    path : str or Path
    channels, units : sequence of str
        Column names and their recorded units (header ``name [unit]``).
    rate_hz : float
    origin_ns : int
        Time that ``time = 0`` stands for, ns since the Unix epoch (float-seconds format).
    time_format : {"seconds", "iso"}
    """

    def __init__(self, path: str | Path, *, channels: Sequence[str], units: Sequence[str],
                 rate_hz: float, origin_ns: int,
                 time_format: Literal["seconds", "iso"] = "seconds") -> None:
        if time_format not in ("seconds", "iso"):
            raise RecordingError(f"time_format must be 'seconds' or 'iso'; got {time_format!r}",
                                 path=str(path))
        self.path = Path(path)
        self.channels = tuple(channels)
        self.rate_hz = float(rate_hz)
        self.origin_ns = int(origin_ns)
        self.time_format = time_format
        self._file = AtomicFile(self.path)
        header = ",".join(["time"] + [f"{c} [{u}]" if u else c
                                      for c, u in zip(self.channels, units)])
        self._file.fh.write((header + "\n").encode())

    def write_block(self, t0_ns: int, data: np.ndarray) -> None:
        """Append samples; ``data`` has shape (n_channels, n_samples), first sample at ``t0_ns``."""
        import pyarrow as pa
        import pyarrow.compute as pc
        import pyarrow.csv as pacsv

        n = data.shape[1]
        k = np.arange(n, dtype=np.float64)
        if self.time_format == "seconds":
            t = np.round((int(t0_ns) - self.origin_ns) / 1e9 + k / self.rate_hz, 9)
            tcol = pa.array(t)
        else:
            ns = int(t0_ns) + np.round(k * (1e9 / self.rate_hz)).astype(np.int64)
            ts = pa.array(ns).cast(pa.timestamp("ns", tz="UTC"))
            tcol = pc.binary_join_element_wise(pc.strftime(ts, format="%Y-%m-%dT%H:%M:%S"),
                                               "Z", "")
        cols = [tcol] + [pa.array(np.asarray(data[i], dtype=np.float32))
                         for i in range(data.shape[0])]
        table = pa.Table.from_arrays(cols, names=["time", *self.channels])
        pacsv.write_csv(table, self._file.fh,
                        write_options=pacsv.WriteOptions(include_header=False,
                                                         quoting_style="none"))

    def close(self) -> None:
        try:
            self._file.commit()
        except BaseException:
            self._file.abort()
            raise

    def abort(self) -> None:
        self._file.abort()


# ---- one call ----------------------------------------------------------------------------
def write_recording(path: str | Path, devices: Sequence[RawDevice], *,
                    encoding: Literal["protobuf", "json"] = "protobuf",
                    metadata: Mapping[str, str] | None = None, mill_toml: str | None = None,
                    block_samples: int | None = None,
                    time_format: Literal["seconds", "iso"] = "seconds") -> None:
    """Write a recording; the format follows the extension (``.mcap`` or ``.csv``).

    Parameters
    ----------
    path : str or Path
        Target file.  For CSV with several devices, the further devices go to siblings
        ``name.<device>.csv`` (see the module docstring).
    devices : sequence of RawDevice
        Samples in their recorded units; NaN for a missing sample.  Channel names must
        be unique over all devices.
    encoding : {"protobuf", "json"}
        MCAP message encoding (ignored for CSV).
    metadata : mapping of str to str, optional
        MCAP ``ident.recording`` metadata (ignored for CSV).
    mill_toml : str, optional
        Mill-file text attached as ``mill.toml`` (MCAP only).
    block_samples : int, optional
        Samples per MCAP sample block; default 0.1 s worth at each device's rate.
    time_format : {"seconds", "iso"}
        CSV time column: float seconds from the recording's start, or ISO-8601 UTC.

    Raises
    ------
    RecordingError
        An unknown extension, or devices that are inconsistent (shapes, names, rates).
    """
    p = Path(path)
    ext = p.suffix.lower()
    if ext not in (".mcap", ".csv"):
        raise RecordingError(f"unknown recording format {p.suffix!r}; expected '.mcap' or "
                             "'.csv'", path=str(p))
    datas = _check_devices(devices, str(p))
    if block_samples is not None and int(block_samples) < 1:
        raise RecordingError(f"block_samples must be >= 1; got {block_samples}", path=str(p))
    if ext == ".mcap":
        with McapRecordingWriter(p, encoding=encoding, metadata=metadata,
                                 mill_toml=mill_toml) as w:
            for dev in devices:
                w.write_device(dev, block_samples=block_samples)
        return
    origin = min(d.t0_ns for d in devices)
    targets = [p] + [csv_sibling_path(p, d.name) for d in devices[1:]]
    if len(set(targets)) != len(targets):
        raise RecordingError(f"device names {[d.name for d in devices]} give clashing CSV "
                             f"file names {[t.name for t in targets]}", path=str(p))
    writers: list[CsvDeviceWriter] = []
    try:
        for dev, data, target in zip(devices, datas, targets):
            w = CsvDeviceWriter(target, channels=dev.channels, units=dev.units,
                                rate_hz=dev.rate_hz, origin_ns=origin, time_format=time_format)
            writers.append(w)
            step = 1 << 18
            for start in range(0, data.shape[1], step):
                w.write_block(dev.t0_ns + int(round(start * 1e9 / dev.rate_hz)),
                              data[:, start:start + step])
        for w in writers:
            w.close()
    except BaseException:
        for w in writers:
            w.abort()
        raise
