"""Read recordings (MCAP or CSV) into SI through the mill file's sensor map.

:func:`read_recording` is the entry point; :func:`reduced_torques` and
:func:`align_devices` derive views from what it returns.

Units (``../shared/spec/mill-config.md``, ``[[channel]]``): a channel's recorded
unit must be the mill file's ``unit`` (the value is then already in that unit) or
``raw`` (the mill file's ``value = scale * recorded + offset`` makes it), and a CSV
column without a unit counts as recorded (scale and offset apply; they are 1 and 0
unless the mill file says otherwise).  Any other unit is an error, never a silent
conversion.  The value is then converted to SI (:mod:`ident.units`): torque in N*m
on the physical shaft, acceleration in m/s^2, speed in rad/s.

Memory: samples stay float32 (an hour of 8 channels at 2 kHz plus 4 at 10 kHz is
0.8 GB of float32 plus 0.35 GB of float64 time index; ``channels=`` reads fewer);
format readers fill preallocated arrays block by block, the SI conversion is in
place, and the DataFrames wrap the arrays without copying.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import Iterable, Iterator, Sequence

import numpy as np
import pandas as pd

from ..description import Mill, Quantity
from ..errors import DataQualityWarning, RecordingError
from ..units import normalize_unit, quantity_of_unit, to_si_factor
from .csv_reader import first_time, last_time, read_csv
from .grid import DeviceGrid, empty_buffer
from .mcap_reader import MAX_BLOCK_NS, mcap_span_ns, read_mcap
from . import quality
from .quality import IssueLog, gap_issues, gap_mask_of, scan_channel
from .recording import Recording

__all__ = ["read_recording", "iter_recording", "recording_span", "check_recording_path",
           "reduced_torques", "align_devices", "DEFAULT_CHUNK_SAMPLES"]

#: Rows per batch when parsing CSV.
DEFAULT_CHUNK_SAMPLES = 1 << 15


def read_recording(path: str | Path, mill: Mill | None = None, *, align: bool = False,
                   channels: Iterable[str] | None = None,
                   chunk_samples: int = DEFAULT_CHUNK_SAMPLES, siblings: bool = True,
                   warn: bool = True, t_start: float | None = None,
                   t_end: float | None = None) -> Recording:
    """Read an MCAP or CSV recording into SI, checking its quality.

    Parameters
    ----------
    path : str or Path
        ``.mcap`` or ``.csv`` file (a CSV's sibling device files ``name.<device>.csv``
        are read with it).
    mill : Mill, optional
        The sensor map.  Without it, an attached ``mill.toml`` (MCAP) is used; failing
        that, channels are converted by their recorded unit alone.
    align : bool
        Return one frame ``"aligned"`` holding every device on a common time index
        (see :func:`align_devices`) instead of one frame per device.
    channels : iterable of str, optional
        Read only these channels (less memory); each must be present.
    chunk_samples : int
        Rows per batch when parsing CSV.
    siblings : bool
        Read a CSV file's sibling device files too.
    warn : bool
        Emit every finding as a :class:`~ident.errors.DataQualityWarning` as well.
    t_start, t_end : float, optional
        Read only the samples at ``[t_start, t_end)`` s from the recording's start
        (memory follows the window; :func:`iter_recording` walks a long recording
        this way).  Times in the result stay seconds from the recording's start, so
        the frames begin near ``t_start``; findings cover the window only.

    Returns
    -------
    Recording
        Per device a DataFrame indexed by ``time_s`` (s from the earliest first sample;
        uniform, dropouts are NaN rows), float32 columns in SI; ``issues`` lists the
        non-fatal findings (see :mod:`ident.io.quality`).  Devices are named by MCAP
        topic, or for CSV by file (``name.csv`` -> ``name``, ``name.accel.csv`` ->
        ``accel``).  ``t0_ns`` is ns since the Unix epoch, except for CSV files with
        relative float seconds, where it counts from their time zero.

    Raises
    ------
    RecordingError
        A directory, an unknown format, a missing, unreadable, empty or corrupt file, time
        that steps back or repeats, a unit that disagrees with the mill file, a
        rate that disagrees with the timestamps, a requested channel that is absent,
        no mapped channel at all, or no sample inside the requested window.
    ident.errors.MillFileError
        The attached ``mill.toml`` is invalid (only when ``mill`` is None).
    """
    p = check_recording_path(path)
    log = IssueLog(str(p))
    ext = p.suffix.lower()
    window = None
    if t_start is not None or t_end is not None:
        lo = 0.0 if t_start is None else float(t_start)
        hi = math.inf if t_end is None else float(t_end)
        if not (lo >= 0.0 and hi > lo):
            raise log.fatal("bad_window", f"expected 0 <= t_start < t_end. Got t_start="
                            f"{t_start!r}, t_end={t_end!r}")
        window = (lo, hi)
    wanted = None if channels is None else tuple(channels)
    mapped = None if mill is None else {c.name for c in mill.channels}

    def keep(name: str) -> bool:
        if wanted is not None and name not in wanted:
            return False
        return mapped is None or name in mapped

    metadata: dict[str, str] = {}
    mill_toml = None
    if ext == ".mcap":
        content = read_mcap(str(p), keep=keep, log=log, window_ns=None if window is None else
                            (int(round(window[0] * 1e9)),
                             int(min(window[1] * 1e9, 2.0**62))))
        grids, metadata, mill_toml = content.grids, content.metadata, content.mill_toml
        if mill is None and mill_toml is not None:
            from .millfile import parse_mill

            mill = parse_mill(mill_toml, path=f"{p}#mill.toml")
            mapped = {c.name for c in mill.channels}
            grids = [_select(g, mapped) for g in grids]
    else:
        grids = read_csv(str(p), keep=keep, log=log, chunk_samples=chunk_samples,
                         siblings=siblings, window_s=window)
    rec = _assemble(p, grids, mill, log, wanted, metadata, mill_toml, warn)
    return align_devices(rec) if align else rec


def recording_span(path: str | Path) -> float:
    """Seconds from a recording's start to its last sample block (MCAP) or row (CSV).

    MCAP: from the summary's message times (the file is streamed when it has none);
    the last block's own samples extend beyond.  CSV: the first and last rows of the
    file and its siblings.  Cheap: no sample is decoded.
    """
    p = check_recording_path(path)
    log = IssueLog(str(p))
    if p.suffix.lower() == ".mcap":
        span = mcap_span_ns(str(p), log)
        if span is None:
            raise log.fatal("unreadable", "it holds no message")
        return (span[1] - span[0]) / 1e9
    from .csv_reader import csv_siblings

    files = [p] + csv_siblings(p)
    first = min(first_time(f, log) for f in files)
    last = max(last_time(f, log) for f in files)
    if not (math.isfinite(first) and math.isfinite(last) and last >= first):
        raise log.fatal("non_monotonic", f"the first and last rows' times ({first!r} s and "
                        f"{last!r} s) give no span; expected finite, increasing times")
    return last - first


def check_recording_path(path: str | Path) -> Path:
    """The path of a recording, once it names a readable, non-empty ``.mcap`` or ``.csv`` file.

    Raises
    ------
    RecordingError
        A directory, an unknown extension, a missing, unreadable or empty file, each
        naming the path.
    """
    p = Path(path)
    log = IssueLog(str(p))
    if p.is_dir():
        raise log.fatal("unreadable", "is a directory; expected a recording file (.mcap or "
                        ".csv; 'ident campaign DIR' processes a folder)")
    if p.suffix.lower() not in (".mcap", ".csv"):
        raise log.fatal("unreadable", f"unknown recording format {p.suffix!r}; expected "
                        "'.mcap' or '.csv'")
    if not p.exists():
        raise log.fatal("unreadable", "file not found")
    try:
        with open(p, "rb") as fh:
            empty = not fh.read(1)
    except OSError as exc:
        raise log.fatal("unreadable", f"cannot read the file ({exc.strerror or exc})") from None
    if empty:
        raise log.fatal("unreadable", "the file is empty (0 bytes); expected an MCAP or CSV "
                        "recording")
    return p


def iter_recording(path: str | Path, mill: Mill | None = None, *, window_s: float = 600.0,
                   overlap_s: float = 0.0, **kwargs) -> Iterator[Recording]:
    """Read a long recording window by window, with bounded memory.

    Parameters
    ----------
    path : str or Path
    mill : Mill, optional
    window_s : float
        Length of each window, s.
    overlap_s : float
        Each window also holds the last ``overlap_s`` seconds of the one before
        (a transient cut by a window's edge is then whole in the next window).
    **kwargs
        Passed to :func:`read_recording` (``channels``, ``align``, ``warn``, ...).

    Yields
    ------
    Recording
        Windows ``[k * window_s - overlap_s, (k + 1) * window_s)`` s from the
        recording's start (times stay relative to that start), until the end of the
        recording.  A window inside the recording holding no sample at all (a long
        dropout) is skipped with a :class:`~ident.errors.DataQualityWarning`; windows
        without a sample for longer than a dropout may last
        (:data:`ident.io.quality.MAX_DROPOUT_S`) before the recording's last time stamp
        are a RecordingError (that time stamp is wrong).
    """
    if not (window_s > 0 and 0 <= overlap_s < window_s):
        raise RecordingError(f"expected window_s > 0 and 0 <= overlap_s < window_s. Got "
                             f"window_s={window_s!r}, overlap_s={overlap_s!r}", path=str(path))
    last = recording_span(path)
    k = 0
    empty: list = []  # the run of empty windows so far: [first error, its start, count]

    def skipped() -> None:  # one warning per run of empty windows (a long dropout)
        if empty:
            exc, _, n = empty
            more = f"; {n} windows up to t={k * window_s:.4f} s hold no sample" if n > 1 else ""
            warnings.warn(f"{exc} (a dropout longer than the window{more}); skipped",
                          DataQualityWarning, stacklevel=3)
            empty.clear()

    while k * window_s <= last + MAX_BLOCK_NS / 1e9:
        lo = max(0.0, k * window_s - overlap_s)
        try:
            rec = read_recording(path, mill, t_start=lo, t_end=(k + 1) * window_s, **kwargs)
        except RecordingError as exc:
            if "empty window: " not in str(exc):
                raise
            if k * window_s > last:
                skipped()
                return  # past the last block's start: the recording has ended
            if not empty:
                empty[:] = [exc, k * window_s, 0]
            empty[2] += 1
            if (k + 1) * window_s - empty[1] > quality.MAX_DROPOUT_S:
                raise RecordingError(
                    f"time jump: no sample from t={empty[1]:.6f} s for more than a dropout "
                    f"may last ({quality.MAX_DROPOUT_S:g} s), yet the recording's last time "
                    f"stamp is at t={last:.6f} s; a wrong time stamp?", path=str(path),
                    time=empty[1]) from None
        else:
            skipped()
            if k and rec.duration < k * window_s:
                return  # only the overlap with the window before: the recording has ended
            yield rec
        k += 1
    skipped()


def _select(g: DeviceGrid, names: set[str]) -> DeviceGrid:
    rows = [i for i, c in enumerate(g.channels) if c in names]
    if len(rows) == len(g.channels):
        return g
    g.data = g.data[rows]
    g.channels = tuple(g.channels[i] for i in rows)
    g.units = tuple(g.units[i] for i in rows)
    return g


def _si_map(log: IssueLog, mill: Mill | None, name: str,
            unit: str) -> tuple[float, float, bool]:
    """(a, b, raw): SI value = a * recorded + b; raw: the recorded unit is ``raw``."""
    u = normalize_unit(unit) if unit else ""
    if mill is not None:
        ch = mill.channel(name)
        factor = to_si_factor(ch.quantity.value, ch.unit)
        if u in ("", "raw"):
            return ch.scale * factor, ch.offset * factor, u == "raw"
        if u == normalize_unit(ch.unit):
            return factor, 0.0, False
        raise log.fatal("unit_mismatch", f"recorded in {unit!r} but the mill file "
                        f"({mill.source or mill.name}) maps it in {ch.unit!r}; expected "
                        f"{ch.unit!r} or 'raw' (a unit that disagrees is an error, not a "
                        "silent conversion)", channel=name)
    q = quantity_of_unit(u) if u else None
    if q is None:
        log.add("unscaled", f"no mill file maps this channel and its unit {unit!r} is not one "
                "ident converts; kept as recorded", channel=name)
        return 1.0, 0.0, u == "raw"
    return to_si_factor(q, u), 0.0, False


def _assemble(p: Path, grids: list[DeviceGrid], mill: Mill | None, log: IssueLog,
              wanted: tuple[str, ...] | None, metadata: dict[str, str], mill_toml: str | None,
              warn: bool) -> Recording:
    present = {c for g in grids for c in g.all_channels}
    # what is absent or unknown ---------------------------------------------------------
    if wanted is not None:
        absent = [c for c in wanted if c not in present]
        if absent:
            raise log.fatal("missing_channel", f"requested channel(s) {absent} are not in the "
                            f"recording, which holds {sorted(present)}", channel=absent[0])
        if mill is not None:
            unmapped = [c for c in wanted if c not in {ch.name for ch in mill.channels}]
            if unmapped:
                raise log.fatal("unknown_channel", f"requested channel(s) {unmapped} are not "
                                "in the mill file's sensor map", channel=unmapped[0])
    if mill is not None:
        known = {c.name for c in mill.channels}
        for g in grids:
            for c in g.all_channels:
                if c not in known:
                    log.add("unknown_channel", f"device {g.name!r} records channel {c!r} that "
                            "the mill file's sensor map does not name; ignored", channel=c,
                            device=g.name)
        if wanted is None:
            for q in Quantity:
                mapped_q = [c.name for c in mill.channels if c.quantity is q]
                have = [c for c in mapped_q if c in present]
                if have:
                    for c in mapped_q:
                        if c not in present:
                            log.add("missing_channel", f"the mill file maps {q.value} channel "
                                    f"{c!r} but the recording lacks it (it has {have}); the "
                                    "rest is used", channel=c)
    grids = [g for g in grids if g.channels]
    if not grids:
        raise log.fatal("missing_channel", f"no channel of the mill file's sensor map is in the "
                        f"recording; it holds {sorted(present)}, the mill file maps "
                        f"{[c.name for c in mill.channels] if mill else []}")
    # units first (fatal errors come before the long scans) ------------------------------
    maps = [[_si_map(log, mill, c, u) for c, u in zip(g.channels, g.units)] for g in grids]
    origin = min(g.start_ns if g.origin_ns is None else min(g.origin_ns, g.start_ns)
                 for g in grids)
    frames: dict[str, pd.DataFrame] = {}
    rates: dict[str, float] = {}
    for g, m in zip(grids, maps):
        offset_s = (g.start_ns - origin) / 1e9
        skip = [((a - origin) / 1e9, (b - origin) / 1e9) for a, b in g.corrupt_ns]
        gap_issues(log, g.name, g.channels, g.rate_hz, offset_s, g.gaps, skip)
        gmask = gap_mask_of(g.n_samples, g.gaps)
        data = g.data
        if not data.flags.writeable:
            data = data.copy()
        for i, (name, (a, b, raw)) in enumerate(zip(g.channels, m)):
            row = data[i]
            scan_channel(log, g.name, name, row, rate_hz=g.rate_hz, offset_s=offset_s,
                         gap_mask=gmask, recorded=row if raw else None)
            if a != 1.0:
                row *= np.float32(a)
            if b != 0.0:
                row += np.float32(b)
        n = g.n_samples
        idx = g.time_buffer if g.time_buffer is not None and g.time_buffer.size == n \
            else empty_buffer((n,), np.float64)
        step = 1 << 20
        for s in range(0, n, step):
            e = min(n, s + step)
            idx[s:e] = np.arange(s, e, dtype=np.float64) / g.rate_hz + offset_s
        frames[g.name] = pd.DataFrame(data.T, index=pd.Index(idx, name="time_s", copy=False),
                                      columns=list(g.channels), copy=False)
        rates[g.name] = float(g.rate_hz)
        g.data = np.empty((0, 0), dtype=np.float32)
        g.time_buffer = None
    issues = log.finish(warn=warn)
    return Recording(frames=frames, rates_hz=rates, t0_ns=int(origin), path=str(p),
                     metadata=dict(metadata), mill_toml=mill_toml, issues=issues)


def reduced_torques(rec: Recording, mill: Mill) -> pd.DataFrame:
    """Torque channels reduced to the motor shaft: physical torque / element ``ratio``.

    Parameters
    ----------
    rec : Recording
        As read (physical shaft torques in N*m).
    mill : Mill
        Gives each torque channel's element and its ratio.

    Returns
    -------
    DataFrame
        Index ``time_s`` (s), one float32 column per torque channel present, N*m
        reduced to the motor shaft.  Channels on devices of different rates are first
        aligned (:func:`align_devices`).

    Raises
    ------
    RecordingError
        No torque channel of the mill file is in the recording.
    """
    names = [c.name for c in mill.torque_channels() if c.name in rec.channels]
    if not names:
        raise RecordingError(f"no torque channel: the mill file maps "
                             f"{[c.name for c in mill.torque_channels()]}, the recording holds "
                             f"{list(rec.channels)}", path=rec.path)
    devices = {rec.device_of(n) for n in names}
    if len(devices) == 1:
        src = rec.frames[devices.pop()][names]
    else:
        src = align_devices(rec, channels=names).frames["aligned"]
    out = {}
    for n in names:
        ratio = mill.element(mill.channel(n).element).ratio
        out[n] = (src[n].to_numpy() / np.float32(ratio)).astype(np.float32, copy=False)
    return pd.DataFrame(out, index=src.index, copy=False)


def align_devices(rec: Recording, *, rate_hz: float | None = None,
                  channels: Sequence[str] | None = None) -> Recording:
    """Put every device on one common uniform time index.

    Parameters
    ----------
    rec : Recording
    rate_hz : float, optional
        Rate of the common index; default the highest device rate.
    channels : sequence of str, optional
        Only these channels.

    Returns
    -------
    Recording
        One frame ``"aligned"`` from the earliest first sample to the latest last one.
        A device at the common rate whose samples fall on the grid is copied; a slower
        one is linearly interpolated between its own neighbouring samples, a faster one
        averaged over each output interval (a boxcar anti-alias).  A NaN sample (dropout)
        makes every output sample it touches NaN: nothing is bridged.
    """
    frames = {d: f if channels is None else f[[c for c in f.columns if c in channels]]
              for d, f in rec.frames.items()}
    frames = {d: f for d, f in frames.items() if f.shape[1]}
    if not frames:
        raise RecordingError(f"no channel to align among {list(channels or [])}", path=rec.path)
    rate = float(rate_hz or max(rec.rates_hz[d] for d in frames))
    if not rate > 0:
        raise RecordingError(f"rate_hz must be positive; got {rate_hz}", path=rec.path)
    t_first = min(float(f.index[0]) for f in frames.values())
    t_last = max(float(f.index[-1]) for f in frames.values())
    n = int(np.floor((t_last - t_first) * rate + 1e-6)) + 1
    tt = t_first + np.arange(n, dtype=np.float64) / rate
    cols: dict[str, np.ndarray] = {}
    for dev, f in frames.items():
        r = rec.rates_hz[dev]
        t0 = float(f.index[0])
        x = f.to_numpy(dtype=np.float32).T  # (n_ch, m)
        u = (tt - t0) * r  # position in the device's samples
        m = x.shape[1]
        if r <= rate * (1 + 1e-9):
            i = np.floor(u + 1e-6).astype(np.int64)
            frac = (u - i).astype(np.float32)
            frac[np.abs(frac) < 1e-5] = 0.0
            valid = (i >= 0) & (i < m)
            i_c = np.clip(i, 0, m - 1)
            j_c = np.clip(i + 1, 0, m - 1)
            for k, c in enumerate(f.columns):
                a = x[k, i_c]
                b = np.where(frac > 0, x[k, j_c], a)
                y = a + (b - a) * frac
                y[~valid | ((frac > 0) & (i + 1 >= m))] = np.nan
                cols[c] = y.astype(np.float32, copy=False)
        else:
            # average the device's samples in [t - 1/(2 rate), t + 1/(2 rate)] (centred)
            lo = np.clip(np.ceil((tt - 0.5 / rate - t0) * r - 1e-6).astype(np.int64), 0, m)
            hi = np.clip(np.floor((tt + 0.5 / rate - t0) * r + 1e-6).astype(np.int64) + 1, 0, m)
            cnt = hi - lo
            for k, c in enumerate(f.columns):
                bad = np.isnan(x[k])
                cs = np.concatenate(([0.0], np.cumsum(np.where(bad, 0.0, x[k]))))
                cb = np.concatenate(([0], np.cumsum(bad)))
                with np.errstate(invalid="ignore", divide="ignore"):
                    y = (cs[hi] - cs[lo]) / cnt
                y[(cnt == 0) | (cb[hi] > cb[lo])] = np.nan
                cols[c] = y.astype(np.float32)
    df = pd.DataFrame(cols, index=pd.Index(tt, name="time_s", copy=False), copy=False)
    return Recording(frames={"aligned": df}, rates_hz={"aligned": rate}, t0_ns=rec.t0_ns,
                     path=rec.path, metadata=rec.metadata, mill_toml=rec.mill_toml,
                     issues=rec.issues)
